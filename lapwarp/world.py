"""World: owns one batch of scenes (model, state, control, per-env RNG) and advances its physics.

The World is what ``SceneBuilder.finalize`` returns and what every task env steps. It never imports
task code. ``step()`` and ``reset(env_mask)`` only launch kernels on preallocated arrays, so they
can be captured into a CUDA graph by the env that owns the World.

One ``step(dt)`` runs ``substeps`` XPBD substeps of ``dt / substeps`` (Macklin et al. 2019, "Small
Steps"); each substep predicts positions (gravity, damping), runs ``iterations`` Gauss-Seidel sweeps
over the graph colours of every constraint group (rod stretch: one exact chain solve per rod per sweep),
and derives velocities from the position change.
After the substeps a stability check flags envs with NaN or runaway speed in ``unstable`` (sticky
until that env is reset) and, when ``auto_reset_unstable`` is set, restores only those envs.

The World owns each env's *start state*: ``reset(env_mask)`` restores it for the masked envs, and a task that
randomises its scene writes the new rows into ``state`` during its reset and then calls ``save_start_state(mask)``
so that later restores (a stability reset) return to this episode's start. Kinematic bodies are posed through
``set_body_poses``; systems plugged in with ``add_solver`` get the position of each sweep as a :class:`Sweep` and the
substep's predicted positions through ``predicted_positions``. Nothing outside this module touches its scratch.
"""

from __future__ import annotations

import copy
from dataclasses import dataclass

import numpy as np
import warp as wp

from lapwarp import launching
from lapwarp.builder import TET_BLOCK_LANES
from lapwarp.chains import pack_chains
from lapwarp.config import check_seed, rng_seed32
from lapwarp.kernels import (
    chains,
    chains_block,
    chains_hybrid,
    chains_partitioned,
    chains_registers,
    chains_split,
    geodesic,
    world_kernels,
)
from lapwarp.launching import make_struct
from lapwarp.model import Control, Model, State
from lapwarp.vbd import tet_components, vertex_layout

# Kernels with ~150 registers per thread (the chain solves): in blocks of 256 only one block fits an SM's register
# file, in blocks of 64 six do (measured on the H100: the cloth's three chain families take 2.77 ms per substep at 64
# threads per block, 3.08 ms at 256)
#: the tet sweeps ``World.tet_solver`` may name
TET_SOLVERS = ("auto", "colored", "fused")
#: the rod sweeps ``World.rod_solver`` may name: a launch per colour of the stretch-shear and bend-twist constraints, or
#: one launch for all of them ("fused", a thread block per env, xpbd.solve_rods_fused; "auto" = "fused")
ROD_SOLVERS = ("auto", "colored", "fused")
#: the tet methods ``World.tet_method`` may name: XPBD constraint projection, per-vertex descent (kernels/vbd.py), or
#: "auto": per vertex where every tet mesh has a pinned particle in every env, else XPBD
TET_METHODS = ("auto", "xpbd", "vbd")
#: how a tet sweep updates its tets' rotations (``World.tet_rotation_update``: where they are used, or once per sweep)
TET_ROTATION_UPDATES = ("vertex", "sweep")
#: the direct chain solves ``World.chain_solver`` may name: "thomas" = a thread walks each chain (kernels/chains.py;
#: partitioned where ``chain_block_links`` > 1), "pcr" = a thread block per chain, parallel cyclic reduction in shared
#: memory (kernels/chains_block.py), "hybrid" = the same packs, each lane ``chain_lane_rows`` consecutive rows
#: eliminated in registers and PCR over one interface row per lane (kernels/chains_hybrid.py), "registers" = the serial
#: walk's thread per chain with the whole chain in registers (kernels/chains_registers.py; families of open chains of
#: at most chains_registers.MAX_LINKS links, the serial walk elsewhere), "open_walk" = the serial walk in three walks
#: per Newton step for families without a loop (chains.solve_open_chains: the filter eliminated inside the back
#: substitution), four for a family with one
CHAIN_SOLVERS = ("thomas", "pcr", "hybrid", "registers", "open_walk")
#: the longest chain (links) the "pcr" solve takes: its block keeps ~33 floats per row in shared memory (~34 KB)
PCR_MAX_LINKS = 256
#: rows of the "pcr" solve's packs by default: the open chains of a family laid end to end in blocks of up to this
#: many rows (chains.pack_chains), so that short chains (a cloth's diagonals, a few short ropes) fill a block's lanes
PCR_PACK_ROWS = 128
#: the largest tet particle window the fused sweep keeps in shared memory (12 B each: 48 KB, the static limit)
FUSED_TET_MAX_PARTICLES = 4096

def check_hybrid_lanes(device) -> None:
    """A ``ValueError`` where the "hybrid" chain solve cannot run: on the CPU its lanes need Warp's cooperative CPU
    blocks (``wp.config.enable_cpu_blocks``). The env calls it before building its World, the World at its step."""
    if wp.get_device(device).is_cpu and not wp.config.enable_cpu_blocks:
        raise ValueError("chain_solver='hybrid' runs a thread block's lanes as threads: on the CPU set "
                         "wp.config.enable_cpu_blocks = True first (Warp's cooperative CPU blocks), or use "
                         "chain_solver='thomas'")


# the "open_walk" kernel of each serial walk (rods, the cloth's capped one)
_OPEN_WALKS = {chains.solve_chains: chains.solve_open_chains, chains.solve_cloth_chains: chains.solve_open_cloth_chains}
_REGISTER_HEAVY = frozenset({chains.solve_chains, chains.solve_cloth_chains, chains.solve_open_chains,
                             chains.solve_open_cloth_chains, chains_partitioned.factor_link_blocks,
                             chains_partitioned.solve_link_separators, chains_partitioned.solve_link_blocks,
                             chains_partitioned.solve_node_separators, chains_partitioned.solve_node_blocks})


def _clone_state(state: State) -> State:
    out = copy.copy(state)
    for name, arr in state.arrays().items():
        setattr(out, name, wp.clone(arr))
    return out


@dataclass(frozen=True)
class Sweep:
    """Where a constraint sweep sits in the recorded step (what ``add_solver`` systems get per sweep).

    Attributes:
        substep, iteration: indices of this sweep's substep and of the sweep within it.
        substeps, iterations: counts per step.
        h: substep length (s).
        blend_prev, blend: kinematic body poses at the start and end of this substep, as fractions of the way from
            ``body_q_previous`` to ``state.body_q`` (the World interpolates bodies linearly across a step).
    """

    substep: int
    iteration: int
    substeps: int
    iterations: int
    h: float

    @property
    def first(self) -> bool:
        """The first sweep of the step (clear per-step accumulators here)."""
        return self.substep == 0 and self.iteration == 0

    @property
    def last(self) -> bool:
        """The last sweep of the step (report, grasp or release here)."""
        return self.substep == self.substeps - 1 and self.iteration == self.iterations - 1

    @property
    def blend_prev(self) -> float:
        return self.substep / self.substeps

    @property
    def blend(self) -> float:
        return (self.substep + 1) / self.substeps


class World:
    """A batch of ``num_envs`` independent scenes on one Warp device.

    Args:
        model: static scene description (topology shared by all envs).
        state: initial dynamic state; a copy is kept so ``reset`` can restore masked envs in place.
        control: per-env commands written by the env's action kernels.
        seed: seed of the per-env device RNG streams (env ``i`` uses stream ``rand_init(seed, i)``).
        substeps: XPBD substeps per ``step`` call; None = automatic (``substeps_for``).
        iterations: constraint sweeps per substep (1 is usually best: spend the budget on substeps).
        auto_reset_unstable: restore the initial state of envs flagged unstable at the end of ``step``.

    Attributes:
        unstable: ``(num_envs,)`` int32, 1 once an env produced NaN or a speed above
            ``model.max_speed``; cleared by ``reset`` of that env.
    """

    def __init__(
        self,
        model: Model,
        state: State | None = None,
        control: Control | None = None,
        seed: int = 0,
        substeps: int | None = 10,
        iterations: int = 1,
        auto_reset_unstable: bool = True,
    ):
        self.model = model
        self.num_envs = model.num_envs
        self.device = wp.get_device(model.device)
        self.state = state if state is not None else State()
        self.control = control if control is not None else Control()
        self.seed = check_seed(seed)
        #: substeps per ``step``; None = chosen per step length by ``substeps_for``
        self.substeps = None if substeps is None else int(substeps)
        self.iterations = int(iterations)
        self.auto_reset_unstable = bool(auto_reset_unstable)
        # Newton steps of the direct rod stretch solve per sweep: the second one, linearised after the first,
        # removes what the first leaves on curved rods (its transverse filter keeps kinks stable but is not
        # exact in length where the rod bends); its residual is small, so its tension filter barely acts
        self.rod_newton_steps = 2
        # (m) a rod chain stops its Newton steps early once one corrected no link by this much (0: every step); only
        # the register-resident, hybrid and pcr solves take it (chains_registers.register_chain_kernel)
        self.rod_newton_tolerance = 0.0
        # Newton steps of each cloth edge-chain solve per sweep (the families' solves follow each other)
        self.chain_newton_steps = 1
        # passes over a particle's geodesic tethers (one per anchor group, kernels/geodesic.py), group after group,
        # where its tethers' balls share no point (anchors pulled apart further than the sheet reaches); otherwise the
        # particle goes to the closest point of their intersection in one step
        self.tether_passes = 2
        # links per block of the direct chain solves (rods and cloth edge chains): 0 (or 1) = one thread walks each
        # chain (kernels/chains.py); B > 1 = the partitioned solve (kernels/chains_partitioned.py), blocks of B links
        # side by side plus a serial pass over the m / B separators, for few long chains (a rope per env on the GPU)
        self.chain_block_links = 0
        # CHAIN_SOLVERS: "pcr" solves packs of chains with a thread block each (one launch per family and sweep,
        # every Newton step in it; same systems, round-off aside): the open chains of a family end to end in packs of
        # up to chain_pcr_rows rows (0 = PCR_PACK_ROWS; 1 = a chain per block; a loop always alone); lanes per
        # block: chain_pcr_threads (0 = the largest pack's rows rounded up to a warp, at most 128)
        self.chain_solver = "thomas"
        self.chain_pcr_threads = 0
        # "hybrid": rows per lane (compile-time, unrolled in registers); the lanes follow from the largest pack
        self.chain_lane_rows = 4
        self._chain_pcr_rows = 0
        # ROD_SOLVERS: the rods' stretch-shear and bend-twist colours in one launch per sweep (a block of
        # rod_block_threads lanes per env) or a launch each
        self.rod_solver = "auto"
        self.rod_block_threads = 32
        # a substep's prediction of particles and rod segments in one launch (False: a launch each, as before)
        self.integrate_together = True
        # in a world whose only constraints are rods: the substep's prediction inside its first sweep's fused rod
        # launch (xpbd.predict_and_solve_rods_fused; _predicts_in_rod_sweep says where), one launch fewer per substep
        self.predict_in_rod_sweep = True
        # where the prediction runs in the rod launch and a substep ends with its closing attachment pass and its
        # particle contact (primitive shapes only): they run at the start of the next substep's rod launch instead
        # (xpbd.contact_rods_fused_kernel), two launches fewer per substep (RopeThreading)
        self.contact_in_rod_launch = True
        # with chain_solver "registers": a family of open chains all of one length (2..chains_split.MAX_LINKS links)
        # solved by two threads per chain, each half in registers (kernels/chains_split.py); families it does not
        # take keep the one-thread register solve. Off by default; RopeCutting turns it on on CUDA devices (568.7k
        # against 450.4k env-steps/s, H200, forty-fourth session), ThreadInHole too (its thread: 211.1k against 206.1k
        # one thread per chain, forty-fifth session)
        self.chain_register_split = False
        # tets' rotation: warm-started extraction iterations per projection (0 = SVD polar decomposition)
        self.tet_rotation_iterations = 2
        # TET_ROTATION_UPDATES, how a sweep updates its tets' rotations: "vertex" = where it uses them (XPBD: each
        # tet's projection; the per-vertex solve "vbd": each vertex for its tets, four extractions per tet and sweep);
        # "sweep" = once per tet at the sweep's start, in a launch over every tet at once, then used as they are
        # (kernels/xpbd.py refresh_tet_rotations; needs tet_rotation_iterations > 0)
        self.tet_rotation_update = "vertex"
        # with "sweep": refresh the stored rotations at every tet_rotation_refresh-th sweep of a step (its first
        # always, so a reset env starts from its own), used as they are in between (fewer launches over every tet;
        # a body that turns little within that many sweeps, e.g. ThreadInHole's clamped hole)
        self.tet_rotation_refresh = 1
        # tet sweep (TET_SOLVERS): "colored" = one launch per graph colour; "fused" = one launch per sweep, a thread
        # block of tet_block_threads per env with the env's tet particles in shared memory (xpbd.fused_tet_kernel);
        # "auto" = fused where the particle window fits FUSED_TET_MAX_PARTICLES. 32 threads measured fastest on the
        # H200 for every task with tets (16 / 32 / 64 / 128 tried; benchmarks/RESULTS.md, "Fused tet sweep")
        self.tet_solver = "auto"
        self.tet_block_threads = TET_BLOCK_LANES
        # how a sweep solves the tets (TET_METHODS): "xpbd" projects each tet's constraints from zero multipliers
        # every substep (a stiff body carries its load only at h c / l <~ 0.7); "vbd" moves each vertex by a Newton
        # step of the substep's potential (kernels/vbd.py), whose fixed point is the equilibrium at any stiffness
        # "auto" (default) = "vbd" where every tet mesh is pinned somewhere (its equilibrium at 10 substeps: a 30 kPa
        # block within 0.3 % of the converged sag, where XPBD needs ~300), else "xpbd" (the per-vertex solve moves a
        # free body as a whole only slowly). Tasks name theirs (measured speeds and expert rates depend on it)
        self.tet_method = "auto"
        # resting tets held (kernels/hold.py TetHold; the per-vertex solve "vbd", fused, its start in the prediction):
        # an env whose tet vertices all moved slower than tet_hold_speed (m/s) at the start of tet_hold_substeps
        # substeps in a row, untouched, skips its tet sweep, rotation refresh and surface boxes, its tet vertices
        # starting each substep at rest where they are, until one moves faster or a contact touches them; 0 = off. It
        # must stay above the rounding floor of a held vertex's velocity, ~ulp(|x|) / h (3.7e-9 m / 2.5e-3 s =
        # 1.5e-6 m/s for a body 5 cm from the origin at h = 2.5 ms)
        self.tet_hold_speed = 0.0
        self.tet_hold_substeps = 10
        # register caps of the recorded step's kernels by their function's name (``{"collide_triangle_colors": 64}``;
        # launching.register_capped), for measuring what a cap does to a latency-bound kernel (bench_env.py
        # --max-registers): a name no kernel of the step has is an error when the step is recorded
        self.max_registers: dict[str, int] = {}
        # the caps a task measured faster for its own step (ThreadInHole's vertex sweep, the rods' sweep and contact
        # kernels of the rod and tissue tasks, LigatingLoop's cavity sweep), applied where the step launches that
        # kernel and silently not where another setting launches another one (e.g. bench_env.py --tet-solver
        # colored); max_registers overrides them
        self.default_register_caps: dict[str, int] = {}
        self.rng = wp.empty(self.num_envs, dtype=wp.uint32, device=self.device)
        self.unstable = wp.zeros(self.num_envs, dtype=wp.int32, device=self.device)
        self._unstable_now = wp.zeros(self.num_envs, dtype=wp.int32, device=self.device)
        self._start_state = _clone_state(self.state)
        self._alloc_scratch()
        self.seed_rng(self.seed)

    # ------------------------------------------------------------------------------------------------
    def _alloc_scratch(self) -> None:
        m, n, dev = self.model, self.num_envs, self.device
        self._q_pred = None
        self._sq_prev = None
        self._body_q_prev = None
        if m.particle_count:
            self._q_pred = wp.zeros((n, m.particle_count), dtype=wp.vec3, device=dev)
        if m.segment_count:
            self._sq_prev = wp.zeros((n, m.segment_count), dtype=wp.quat, device=dev)
        # per-env inverse masses of the deformables' constraints with attachments folded in (None: no attachments)
        self._w_eff = wp.zeros((n, m.particle_count), dtype=float, device=dev) if m.attachment_capacity else None
        self._rod_scratch = self._chain_scratch(m.rod_chains)
        # per (env, tet) rotation of the last projection: the warm start of the next one (identity at rest)
        self._tet_rotation = wp.full((n, max(m.tet_count, 1)), wp.quat_identity(), dtype=wp.quat, device=dev)
        # ... and at the start state (saved and restored with it, so a reset episode repeats bit for bit)
        self._start_tet_rotation = wp.clone(self._tet_rotation) if m.tet_count else None
        self._alloc_vertex_solve()
        self._no_rotation = wp.zeros((1, 0), dtype=wp.quat, device=dev)
        # the fused tet sweep's colour table and particle window (the tets' lowest particle and the window's length)
        self._tet_color_offsets = wp.array(np.asarray(m.tet_color_offsets, dtype=np.int32), dtype=wp.int32,
                                           device=dev)
        # the fused rod sweep's colour tables (device copies made here: never while a step is recorded, see _packs)
        self._segment_color_offsets = wp.array(np.asarray(m.segment_color_offsets, dtype=np.int32), dtype=wp.int32,
                                               device=dev)
        self._bend_color_offsets = wp.array(np.asarray(m.bend_color_offsets, dtype=np.int32), dtype=wp.int32,
                                            device=dev)
        self._tet_window = (0, 0)
        if m.tet_count:
            idx = m.tet_indices.numpy()
            self._tet_window = (int(idx.min()), int(idx.max() - idx.min() + 1))
        self._edge_scratch = self._chain_scratch(m.edge_chains)
        # the partitioned chain solve's extra scratch per chain set, allocated on first use (_chain_partition)
        self._partitions = {}
        # the block (PCR) solve's packs per chain set, laid out here and whenever chain_pcr_rows changes: their
        # device arrays are copied from the host, which a step recorded inside a CUDA graph capture must not do
        self._packs = {}
        self._lay_out_chain_packs()
        if self.state.body_q is not None:
            self._body_q_prev = wp.clone(self.state.body_q)
        self._dummy_f = wp.zeros((1, 1), dtype=float, device=dev)
        self._dummy_v2 = wp.zeros((1, 1), dtype=wp.vec2, device=dev)
        self._dummy_v3 = wp.zeros((1, 1), dtype=wp.vec3, device=dev)
        # "no cutting masks" for the constraint kernels: empty element maps / a (1, 0) mask
        self._no_map_i = wp.zeros(0, dtype=wp.int32, device=dev)
        # the prediction's deferred particle deltas where there are none (xpbd.Prediction)
        self._no_delta = wp.zeros((1, 0, 3), dtype=wp.int64, device=dev)
        self._no_delta_count = wp.zeros((1, 0), dtype=wp.int32, device=dev)
        self._no_mask = wp.zeros((1, 0), dtype=wp.int32, device=dev)
        self._dummy_mask = wp.zeros((1, 1), dtype=wp.int32, device=dev)
        # per env: substeps its tet vertices have been quiet (saturating at tet_hold_substeps, one past it once its
        # sweep skipped it) and whether one moved faster than tet_hold_speed or a contact touched them (hold.TetHold)
        self._hold_quiet = wp.zeros(n, dtype=wp.int32, device=dev)
        self._hold_moving = wp.zeros(n, dtype=wp.int32, device=dev)
        self._tet_holds: dict = {}  # the TetHold struct per hold setting (_tet_hold)
        self._empty_attachment_pass = None  # built on first use (_no_attachment_pass)
        #: ``(num_envs, particles)`` external forces (N), allocated by :meth:`enable_external_forces`
        self.particle_force = None
        self._lam = {}
        self._alloc_lambdas()
        self._cmds: list = []
        self._cmd_key = None
        self.solvers: list = []

    def _alloc_vertex_solve(self) -> None:
        """The per-vertex tet solve's layout (``lapwarp.vbd``: vertices by colour, incident tets) and the tet meshes
        without a pinned particle in some env (which it refuses, kernels/vbd.py says why). Built with the World, as
        its host copies must not happen while a step is recorded inside a CUDA graph capture."""
        m, dev = self.model, self.device
        self._vbd_layout = None
        self._tet_stiffness = None  # (P, T) vec2, set below where there are tets
        self._vbd_start_flags = None  # set below where there are tets (_vbd_start_in_prediction needs them)
        self._unanchored_tets: list[tuple[int, int]] = []
        if not m.tet_count:
            return
        idx = m.tet_indices.numpy()
        pinned = m.particle_inv_mass.numpy() == 0.0  # (1 or num_envs, particles)
        self._unanchored_tets = [(int(c.min()), int(c.max())) for c in tet_components(idx)
                                 if not pinned[:, c].any(axis=1).all()]
        lay = vertex_layout(idx, fixed=pinned.all(axis=0), lanes=self.tet_block_threads)
        # the solve's vertices flagged per particle: the prediction writes their start of the solve
        # (xpbd.integrate_particle's vbd_start) where nothing moves them in between (_vbd_start_in_prediction)
        flags = np.zeros(m.particle_count, dtype=np.int32)
        flags[np.asarray(lay.vertices, dtype=np.int64)] = 1
        self._vbd_start_flags = wp.array(flags, dtype=wp.int32, device=dev)
        # the tets' stiffnesses (the reciprocal compliances the solve multiplies by), kept with the compliances by
        # set_materials, their only writer after the build
        self._tet_stiffness = wp.empty(m.tet_params.shape, dtype=wp.vec2, device=dev)
        self._refresh_tet_stiffness()
        self._vbd_layout = (
            wp.array(lay.vertices, dtype=wp.int32, device=dev), lay.color_offsets,
            wp.array(np.asarray(lay.color_offsets, dtype=np.int32), dtype=wp.int32, device=dev),
            wp.array(lay.adj_offsets, dtype=wp.int32, device=dev), wp.array(lay.adj_tets, dtype=wp.int32, device=dev),
            wp.array(lay.adj_corners, dtype=wp.int32, device=dev))

    def _refresh_tet_stiffness(self) -> None:
        """``world_kernels.tet_stiffness`` of every tet's compliances."""
        launching.launch(world_kernels.tet_stiffness, dim=self.model.tet_params.shape, inputs=[self.model.tet_params],
                         outputs=[self._tet_stiffness], device=self.device)

    def _chain_scratch(self, chains) -> tuple:
        """Per-env scratch of a chain set's direct solve: per link the multiplier of the Newton steps, modified
        super-diagonal, right-hand side / dl and loop correction; per node (a chain has at most links + 1 nodes)
        the transverse filter's super-diagonal, right-hand side and base point."""
        if chains is None:
            return ()
        n, dev = self.num_envs, self.device
        links, nodes = max(chains.link_slots, 1), max(chains.node_slots, 1)
        return (*(wp.zeros((n, links), dtype=float, device=dev) for _ in range(4)),
                wp.zeros((n, nodes), dtype=float, device=dev), wp.zeros((n, nodes), dtype=wp.vec3, device=dev),
                wp.zeros((n, nodes), dtype=wp.vec3, device=dev))

    @property
    def chain_pcr_rows(self) -> int:
        """Rows per pack of the block (PCR) chain solve: 0 = ``PCR_PACK_ROWS``, 1 = a chain per block, else at most
        this many rows (a longer chain alone). Setting it lays the packs out again (host work, outside any step)."""
        return self._chain_pcr_rows

    @chain_pcr_rows.setter
    def chain_pcr_rows(self, rows: int) -> None:
        if isinstance(rows, bool) or not isinstance(rows, (int, np.integer)) or not 0 <= rows <= 4 * PCR_PACK_ROWS:
            raise ValueError(f"world.chain_pcr_rows must be an int in [0, {4 * PCR_PACK_ROWS}] (0: {PCR_PACK_ROWS}, "
                             f"1: a chain per block), got {rows!r}")
        self._chain_pcr_rows = int(rows)
        self._lay_out_chain_packs()

    def _lay_out_chain_packs(self) -> None:
        capacity = self._chain_pcr_rows or PCR_PACK_ROWS
        for cs in (self.model.rod_chains, self.model.edge_chains):
            if cs is not None and cs.count:
                self._packs[id(cs)] = pack_chains(cs, capacity, self.device)

    def _chain_partition(self, chains, scratch: tuple) -> tuple[list, object]:
        """Block layout and scratch of the partitioned solve of a chain set at ``chain_block_links`` (allocated on
        first use and again for another block length). It shares the serial solve's scratch (``_chain_scratch``):
        per link the Newton multipliers, super-diagonals and dl, per node the filter's arrays."""
        from lapwarp.kernels import chains_partitioned as cp

        B = self.chain_block_links
        cached = self._partitions.get(id(chains))
        if cached is not None and cached[0] == B:
            return cached[1], cached[2]
        layout, blocks = cp.block_layout(chains.families, chains.lengths, B)
        links, nodes = chains.link_slots, chains.node_slots
        sc = cp.Scratch()
        sc.newton_dl, sc.link_c, sc.dl, _, sc.node_c, sc.node_d, sc.node_par = scratch
        own = {"link_d": (links, wp.vec2), "link_zl": (links, float), "node_zl": (nodes, float),
               "link_first_y": (blocks, wp.vec2), "link_first_z": (blocks, wp.vec2), "link_last_y": (blocks, wp.vec2),
               "link_last_z": (blocks, wp.vec2), "link_sep_abc": (blocks, wp.vec3), "link_sep_rhs": (blocks, wp.vec2),
               "node_first_y": (blocks, wp.vec3), "node_first_z": (blocks, wp.vec2), "node_last_y": (blocks, wp.vec3),
               "node_last_z": (blocks, wp.vec2), "node_sep_abc": (blocks, wp.vec3), "node_sep_rhs": (blocks, wp.vec3),
               "loop": (chains.count, wp.vec2)}
        for name, (slots, dtype) in own.items():
            setattr(sc, name, wp.zeros((self.num_envs, max(slots, 1)), dtype=dtype, device=self.device))
        self._partitions[id(chains)] = (B, layout, sc, [getattr(sc, name) for name in own])
        return layout, sc

    def _alloc_lambdas(self) -> None:
        """Multiplier arrays exist only when iterations > 1 (with one sweep lambda starts at 0)."""
        m, n, dev = self.model, self.num_envs, self.device
        self._lam = {}
        if self.iterations <= 1:
            return
        for name, count, dtype in (
            ("edge", m.edge_count, float),
            ("hinge", m.hinge_count, float),
            ("tet", m.tet_count, wp.vec2),
            ("segment", m.segment_count, wp.vec3),
            ("bend", m.bend_count, wp.vec3),
            ("rod", m.segment_count if m.rod_count else 0, float),
        ):
            if count:
                self._lam[name] = wp.zeros((n, count), dtype=dtype, device=dev)

    @property
    def predicted_positions(self) -> wp.array | None:
        """Particle positions after this substep's prediction (gravity, damping), before any constraint
        ``(num_envs, particles)``: contact uses them for friction and velocity-consistent corrections."""
        return self._q_pred

    @property
    def body_q_previous(self) -> wp.array | None:
        """Kinematic body poses at the start of the current step ``(num_envs, bodies)``; during a step the
        World interpolates from these to ``state.body_q`` across the substeps (None without bodies)."""
        return self._body_q_prev

    def add_solver(self, solver) -> None:
        """Plug an extra constraint system (contact, grasping, ...) into every substep sweep.

        ``solver.record_sweep(world, launch, sweep)`` is called while a step is recorded, once per sweep of every
        substep, after the built-in constraint groups, with the sweep's :class:`Sweep`; it must only
        ``launch(kernel, dim, inputs, outputs)`` (which records the launch for replay, so it ends up in the env's
        CUDA graph) or ``launch(fn)`` with a plain callable that only launches device work (e.g.
        an array scan); ``launch.defer_deltas(delta, count, scale, apply)`` hands the World a launch of averaged
        particle corrections that the next substep's prediction launch may apply itself (else it is launched as given
        before any other launch). An optional ``solver.record_substep_end(world, launch, sweep)`` runs after the
        velocity update of each substep (e.g. for velocity-level friction or restitution), and an optional
        ``solver.reset(env_mask)`` runs at the end of ``World.reset`` (launches only: clear the masked envs'
        reports or grasps). Systems never reallocate after being added.
        """
        self.solvers.append(solver)
        self._cmd_key = None

    #: fewest automatic substeps (cloth edge chains and rods converge from here at 0.1 s steps)
    MIN_AUTO_SUBSTEPS = 10
    #: threads per env that copy the rows of reset / saved envs (CUDA; one on the CPU)
    ROW_COPY_LANES = 128

    def enable_external_forces(self) -> wp.array:
        """Allocate (once) and return ``particle_force``, a ``(num_envs, particles)`` ``wp.vec3`` array of external
        forces in N, zero at first, added to gravity in every substep (a constant force field such as sofa_env's
        ``ConstantForceField``). Tasks write it from kernels; it is control input, not State, so a reset does not
        touch it. Particles with inverse mass 0 (pinned, or orphaned by cutting) ignore it."""
        if self.particle_force is None:
            self.particle_force = wp.zeros((self.num_envs, max(self.model.particle_count, 1)), dtype=wp.vec3,
                                           device=self.device)
            self._cmd_key = None  # re-record the step with the force term
        return self.particle_force

    @property
    def tet_method_in_use(self) -> str:
        """``tet_method`` with "auto" resolved: "vbd" where every tet mesh has a pinned particle in every env."""
        if self.tet_method != "auto":
            return self.tet_method
        return "vbd" if self.model.tet_count and not self._unanchored_tets else "xpbd"

    def substeps_for(self, dt: float) -> int:
        """Substeps of a ``step(dt)``: the fixed count, or automatically 10, and with ``tet_method`` "xpbd"
        ``max(10, ceil(dt / model.max_substep))`` (XPBD tets reach their stiffness only at ``h c / l <~ 0.7``; the
        per-vertex solve has no such bound)."""
        if self.substeps is not None:
            return self.substeps
        xpbd_tets = self.tet_method_in_use == "xpbd" and np.isfinite(self.model.max_substep)
        need = dt / self.model.max_substep if xpbd_tets else 0.0
        return max(self.MIN_AUTO_SUBSTEPS, int(np.ceil(need - 1e-9)))

    @property
    def fused_tets(self) -> bool:
        """Whether the tet sweep runs fused (``tet_solver`` "fused", or "auto" with the window in shared memory)."""
        return self.tet_solver == "fused" or (self.tet_solver == "auto"
                                              and self._tet_window[1] <= FUSED_TET_MAX_PARTICLES)

    def set_iterations(self, iterations: int) -> None:
        """Change the sweeps per substep (allocates multipliers; not inside a captured graph)."""
        self.iterations = int(iterations)
        self._alloc_lambdas()
        self._cmd_key = None

    def seed_rng(self, seed: int) -> None:
        """Re-seed every env's RNG stream (host-side call, not part of the captured step). Any Python integer is a
        distinct seed (``lapwarp.config.rng_seed32``); a non-integer raises ``ValueError``."""
        self.seed = check_seed(seed)
        launching.launch(world_kernels.init_env_rng, dim=self.num_envs, inputs=[rng_seed32(self.seed)],
                         outputs=[self.rng], device=self.device)

    # ------------------------------------------------------------------------------------------------
    def step(self, dt: float) -> None:
        """Advance the physics of every env by ``dt`` seconds. A kinematic scene has nothing to do.

        The launches of one step are recorded once per ``dt`` and replayed (less Python overhead); the
        state arrays are updated in place and must not be re-assigned after ``finalize``.
        """
        if self.model.particle_count == 0:
            return
        key = (float(dt), self.substeps_for(float(dt)), self.iterations, self.rod_newton_steps,
               self.rod_newton_tolerance,
               self.chain_newton_steps, self.tet_rotation_iterations, self.tet_rotation_update,
               self.tet_rotation_refresh, self.chain_block_links, self.chain_solver, self.chain_pcr_threads,
               self.chain_pcr_rows, self.chain_lane_rows, self.tet_solver, self.tet_block_threads,
               self.model.attachments_distinct, self.rod_solver, self.rod_block_threads, self.integrate_together,
               self.predict_in_rod_sweep, self.contact_in_rod_launch, self.chain_register_split,
               self.tet_method_in_use,
               self.tet_hold_speed, self.tet_hold_substeps, self._register_caps_key(),
               *(solver.record_key() for solver in self.solvers if hasattr(solver, "record_key")))
        if self._cmd_key != key:
            if int(self.iterations) > 1 and not self._lam:
                # iterations set directly (set_iterations allocates): the multipliers the sweeps index must exist
                self._alloc_lambdas()
            if self.tet_method not in TET_METHODS:
                raise ValueError(f"world.tet_method must be one of {TET_METHODS}, got {self.tet_method!r}")
            if self.tet_method == "vbd" and self._unanchored_tets:
                first, last = self._unanchored_tets[0]
                raise ValueError(f"world.tet_method 'vbd' moves a stiff body as a whole only slowly, so it takes only "
                                 f"tet meshes with a pinned particle in every env; the mesh of particles "
                                 f"{first}..{last} has none: use 'xpbd' (docs/physics.md)")
            if self.tet_rotation_update not in TET_ROTATION_UPDATES:
                raise ValueError(f"world.tet_rotation_update must be one of {TET_ROTATION_UPDATES}, got "
                                 f"{self.tet_rotation_update!r}")
            if self.tet_rotation_update == "sweep" and self.tet_rotation_iterations <= 0:
                raise ValueError("world.tet_rotation_update 'sweep' stores warm-started rotations: it needs "
                                 f"tet_rotation_iterations > 0, got {self.tet_rotation_iterations!r}")
            every = self.tet_rotation_refresh
            if isinstance(every, bool) or not isinstance(every, (int, np.integer)) or every < 1:
                raise ValueError(f"world.tet_rotation_refresh must be an int >= 1 (sweeps between refreshes of the "
                                 f"stored tet rotations), got {every!r}")
            if self.chain_solver not in CHAIN_SOLVERS:
                raise ValueError(f"world.chain_solver must be one of {CHAIN_SOLVERS}, got {self.chain_solver!r}")
            if self.chain_solver == "hybrid":
                rows = self.chain_lane_rows
                if isinstance(rows, bool) or not isinstance(rows, (int, np.integer)) or not 1 <= rows <= 16:
                    raise ValueError(f"world.chain_lane_rows must be an int in [1, 16] (rows per lane, unrolled in "
                                     f"registers), got {rows!r}")
                check_hybrid_lanes(self.device)
            if self.chain_solver in ("pcr", "hybrid"):
                longest = max([int(cs.lengths.max()) for cs in (self.model.rod_chains, self.model.edge_chains)
                               if cs is not None and cs.count], default=0)
                if longest > PCR_MAX_LINKS:
                    raise ValueError(f"world.chain_solver {self.chain_solver!r} keeps a chain in one block: this "
                                     f"scene's longest chain has {longest} links, more than {PCR_MAX_LINKS}; use "
                                     f"'thomas'")
            self._check_rod_newton_tolerance()
            self._check_tet_hold()
            if not 0 <= int(self.chain_pcr_threads) <= 1024:
                raise ValueError(f"world.chain_pcr_threads must be in [0, 1024] (0: automatic), got "
                                 f"{self.chain_pcr_threads!r}")
            if self.rod_solver not in ROD_SOLVERS:
                raise ValueError(f"world.rod_solver must be one of {ROD_SOLVERS}, got {self.rod_solver!r}")
            if isinstance(self.rod_block_threads, bool) or not isinstance(self.rod_block_threads, int) \
                    or not 1 <= self.rod_block_threads <= 1024:
                raise ValueError(f"world.rod_block_threads must be an int in [1, 1024], got {self.rod_block_threads!r}")
            for name in ("integrate_together", "predict_in_rod_sweep", "contact_in_rod_launch", "chain_register_split"):
                if not isinstance(getattr(self, name), (bool, np.bool_)):
                    raise ValueError(f"world.{name} must be a bool, got {getattr(self, name)!r}")
            if self.chain_register_split and self.chain_solver == "registers" and self.device.is_cpu \
                    and not wp.config.enable_cpu_blocks:
                raise ValueError("world.chain_register_split runs a chain's two halves as threads of one block: on the "
                                 "CPU set wp.config.enable_cpu_blocks = True first (Warp's cooperative CPU blocks), "
                                 "or leave chain_register_split False")
            if self.tet_solver not in TET_SOLVERS:
                raise ValueError(f"world.tet_solver must be one of {TET_SOLVERS}, got {self.tet_solver!r}")
            if self.tet_solver == "fused" and self._tet_window[1] > FUSED_TET_MAX_PARTICLES:
                raise ValueError(f"world.tet_solver 'fused' keeps the tets' particles in shared memory: this scene's "
                                 f"window of {self._tet_window[1]} particles exceeds {FUSED_TET_MAX_PARTICLES}; use "
                                 f"'colored' or 'auto'")
            self._cmds = self._record_step(float(dt))
            self._cmd_key = key
        for cmd in self._cmds:
            cmd()

    def _check_rod_newton_tolerance(self) -> None:
        """``rod_newton_tolerance`` is a finite length >= 0, and where it is set the rods run a chain solve that
        stops early ("registers" on every family, "hybrid" or "pcr"; the serial walks run every Newton step)."""
        tol = self.rod_newton_tolerance
        if isinstance(tol, (np.floating, np.integer)):
            tol = float(tol)
        try:
            chains.check_newton_tolerance(tol)
        except ValueError:
            raise ValueError(f"world.rod_newton_tolerance must be a finite length >= 0 (m), got {tol!r}") from None
        cs = self.model.rod_chains
        if float(tol) == 0.0 or cs is None or not cs.count or self.chain_solver in ("hybrid", "pcr"):
            return
        if int(self.chain_block_links) > 1:
            raise ValueError(f"world.rod_newton_tolerance: chain_block_links={self.chain_block_links} runs the "
                             f"partitioned solve, which runs every Newton step; set chain_block_links to 0 or the "
                             f"tolerance to 0")
        if self.chain_solver != "registers":
            raise ValueError(f"world.rod_newton_tolerance stops the Newton steps of the register-resident, hybrid and "
                             f"pcr chain solves only: set chain_solver 'registers', 'hybrid' or 'pcr' (it is "
                             f"{self.chain_solver!r}) or the tolerance to 0")
        for first, count, _, _ in cs.families:
            if chains_registers.family_kernel(cs, first, count) is None:
                raise ValueError(f"world.rod_newton_tolerance: the rod chains {first}..{first + count - 1} run the "
                                 f"serial walk (a loop, or longer than {chains_registers.MAX_LINKS} links), which "
                                 f"runs every Newton step; set the tolerance to 0")

    def _check_tet_hold(self) -> None:
        """``tet_hold_speed`` is a finite speed >= 0 and ``tet_hold_substeps`` an int >= 1; a hold (speed > 0) needs the
        per-vertex tet solve, fused, with its start in the prediction (the launches that read the hold)."""
        speed, after = self.tet_hold_speed, self.tet_hold_substeps
        if isinstance(speed, bool) or not isinstance(speed, (int, float, np.integer, np.floating)) \
                or not np.isfinite(speed) or speed < 0:
            raise ValueError(f"world.tet_hold_speed must be a finite speed >= 0 (m/s; 0 = off), got {speed!r}")
        if isinstance(after, bool) or not isinstance(after, (int, np.integer)) or not 1 <= after <= 2**30:
            raise ValueError(f"world.tet_hold_substeps must be an int >= 1, got {after!r}")
        if speed == 0:
            return
        if not self.model.tet_count or self.tet_method_in_use != "vbd" or not self.fused_tets \
                or not self._vbd_start_in_prediction():
            raise ValueError("world.tet_hold_speed holds resting tets of the per-vertex solve only where its sweep is "
                             "fused and its start is in the prediction (tet_method 'vbd', tet_solver 'auto' or "
                             f"'fused', no tethers or plain edges before the tets); this world has tet_count="
                             f"{self.model.tet_count}, tet_method {self.tet_method_in_use!r}, fused "
                             f"{self.fused_tets}: set tet_hold_speed to 0")

    def _tet_hold(self, off: bool = False):
        """The recorded launches' ``hold.TetHold`` (``after`` 0 where the hold is off, or with ``off``), one struct
        per setting (built on the host, read by the launches recorded with it)."""
        from lapwarp.kernels.hold import TetHold

        on = self.tet_hold_moving is not None and not off
        key = (float(self.tet_hold_speed), int(self.tet_hold_substeps)) if on else None
        if key not in self._tet_holds:
            self._tet_holds[key] = make_struct(TetHold, quiet=self._hold_quiet, moving=self._hold_moving,
                                               after=key[1] if on else 0, speed2=key[0] ** 2 if on else 0.0)
        return self._tet_holds[key]

    @property
    def tet_hold_moving(self) -> wp.array | None:
        """The per-env flags a contact on held tets sets (``hold.TetHold.moving``; ``contact.ParticleSolve``), or
        None where the hold is off."""
        return self._hold_moving if float(self.tet_hold_speed) > 0.0 else None

    def wake_tets(self, env_mask: wp.array | None = None) -> None:
        """Let the masked envs' (every env's without a mask) held tets (``tet_hold_speed``) be solved again from the
        next substep on, until they are quiet for ``tet_hold_substeps`` substeps: for a task that writes their
        positions or materials between steps. ``reset``, ``save_start_state``, ``set_materials`` and a stability
        restore do it themselves (one launch; graph-capturable)."""
        mask = env_mask if env_mask is not None else self._all_envs()
        launching.launch(world_kernels.clear_masked_int, dim=self.num_envs, inputs=[mask],
                         outputs=[self._hold_quiet], device=self.device)

    @property
    def register_caps(self) -> dict[str, int]:
        """The caps the recorded step applies: the task's defaults, then ``max_registers`` over them."""
        return {**self.default_register_caps, **self.max_registers}

    def _register_caps_key(self) -> tuple:
        """The caps (``max_registers`` and ``default_register_caps``: kernel function names to caps CUDA takes) checked
        and as a sorted tuple."""
        for name, cap in (*self.max_registers.items(), *self.default_register_caps.items()):
            if not isinstance(name, str):
                raise ValueError(f"world.max_registers and default_register_caps map kernel function names to caps, "
                                 f"got key {name!r}")
            launching.check_register_cap(cap)
        return tuple(sorted(self.register_caps.items()))

    def _record_step(self, dt: float) -> list:
        from lapwarp.kernels import xpbd

        m, n, dev, s = self.model, self.num_envs, self.device, self.state
        cmds: list = []

        sm_count = dev.sm_count if dev.is_cuda else 0
        caps = self.register_caps
        capped = set()

        # a solver's particle corrections deferred to the next substep's prediction (launch.defer_deltas): at most
        # one at a time, launched as it was given before any other launch (so nothing reads the particles without
        # them) unless the next substep's prediction launch applies them itself
        pending: list = []
        # a substep's closing attachment pass and then its particle contact, deferred into the next substep's fused
        # rod launch (launch.defer_attachments, launch.defer_contact): at most one of each, launched as given (in
        # that order) before any other launch
        pending_attach: list = []
        pending_contact: list = []

        def flush():
            if pending:
                launch_now(*pending.pop()[3])
            if pending_attach:
                launch_now(*pending_attach.pop()[:4])
            if pending_contact:
                launch_now(*pending_contact.pop())

        def launch(kernel, dim=None, inputs=(), outputs=(), block_dim=None):
            flush()
            launch_now(kernel, dim, inputs, outputs, block_dim)

        def defer_deltas(delta, count, scale: float, apply: tuple):
            """Record ``apply`` (``(kernel, dim, inputs, outputs)``: adds the mean of the fixed-point sums ``delta``
            (``(num_envs, particles, 3)`` int64, scaled by ``scale``) over ``count`` to each particle and clears both)
            later: the next substep's prediction does it where it would be ``xpbd.integrate_particles_and_segments``
            and comes next (``xpbd.apply_deltas_and_integrate``, one launch fewer per substep); any other launch first
            launches ``apply``."""
            flush()
            pending.append((delta, count, float(scale), tuple(apply)))

        launch.defer_deltas = defer_deltas

        def defer_attachments(kernel, dim, inputs, outputs, bundle):
            """Record the closing attachment launch ``(kernel, dim, inputs, outputs)`` later (``bundle``: its
            ``xpbd.AttachmentPass``): the next substep's fused rod launch runs it first where it comes next, before
            the deferred contact (``take_prologue``); any other launch first launches it."""
            flush()
            pending_attach.append((kernel, dim, tuple(inputs), tuple(outputs), bundle))

        def defer_contact(kernel, dim, inputs, outputs):
            """Record the particle contact launch ``(kernel, dim, inputs, outputs)`` later, after a deferred attachment
            pass (``defer_attachments``), the same way."""
            if pending:
                launch_now(*pending.pop()[3])
            if pending_contact:
                launch_now(*pending_contact.pop())
            pending_contact.append((kernel, dim, tuple(inputs), tuple(outputs)))

        def take_prologue():
            """The deferred attachment pass (its launch and bundle) and particle contact (``(inputs, outputs)``) for
            the launch about to be recorded, each None where none was deferred."""
            attach = pending_attach.pop() if pending_attach else None
            contact = pending_contact.pop()[2:] if pending_contact else None
            return attach, contact

        if self._contact_in_rod_launch():
            launch.defer_attachments = defer_attachments
            launch.defer_contact = defer_contact
            launch.take_prologue = take_prologue

        def launch_now(kernel, dim=None, inputs=(), outputs=(), block_dim=None):
            # A plain callable (e.g. an array scan) is recorded as is: it must only launch device work.
            if dim is None and not isinstance(kernel, wp.Kernel):
                cmds.append(kernel)
                return
            if dev.is_cuda:
                heavy = kernel in _REGISTER_HEAVY or chains_registers.is_register_kernel(kernel)
                block = block_dim or launching.block_dim_for(dim, sm_count, 64 if heavy else 256)
            else:
                # a thread at a time on the CPU unless a kernel asks for lanes (then Warp's cooperative fibers, where
                # wp.config.enable_cpu_blocks is set): plain kernels never run as fiber blocks
                block = block_dim or 1
            name = kernel.func.__name__
            if name in caps:
                kernel = launching.register_capped(kernel, caps[name])
                capped.add(name)
            rec = wp.launch(kernel, dim=dim, inputs=inputs, outputs=list(outputs), device=dev, record_cmd=True,
                            block_dim=block)
            cmds.append(rec.launch)

        substeps = self.substeps_for(dt)
        h = dt / substeps
        inv_dt2 = 1.0 / (h * h)
        if self._w_eff is not None:
            # attachments change only between steps (grasping updates them after the last sweep)
            lanes = launching.block_lanes(dev, 64)  # a block per env (world_kernels.attachment_inverse_masses)
            launch(world_kernels.attachment_inverse_masses, (n, lanes),
                   [m.particle_inv_mass, s.attach_particle, s.attach_compliance, inv_dt2,
                    int(m.attachments_distinct)], [self._w_eff],
                   block_dim=lanes)
        if m.geo_particles is not None:
            self._record_geodesic_refresh(launch)
        iters = max(1, self.iterations)
        use_lam = 1 if iters > 1 else 0
        lam = self._lam
        # a substep's velocity update and the next one's prediction run as one kernel where nothing comes between
        # them (a solver's record_substep_end would): one launch and one pass over the particles fewer per substep
        fuse = not any(hasattr(solver, "record_substep_end") for solver in self.solvers)
        # the empty int32 array where the prediction writes no tet solve's start
        start_flags = self._vbd_start_flags if self._vbd_start_in_prediction() else self._no_map_i
        in_rod_sweep = self._predicts_in_rod_sweep()
        active, use_active, force, use_force = self._prediction_masks()
        hold = self._tet_hold()
        for sub in range(substeps):
            particle_args = [m.particle_inv_mass, m.particle_damping, m.gravity, h, active, use_active, force,
                             use_force, start_flags, hold, s.particle_q, s.particle_qd]
            prediction = None
            if m.segment_count and self.integrate_together:
                # particles and segments in one launch (the same arithmetic on independent elements), or where nothing
                # else moves them before the rods, in the first sweep's rod launch
                # the deltas a solver deferred from the substep before, applied by this launch where it comes next
                delta, count, scale = self._no_delta, self._no_delta_count, 0.0
                if pending and not in_rod_sweep:
                    delta, count, scale, _ = pending.pop()
                prediction = make_struct(xpbd.Prediction, finish=int(sub > 0 and fuse), inv_dt_prev=1.0 / h,
                                         inv_mass=m.particle_inv_mass, damping=m.particle_damping, gravity=m.gravity,
                                         dt=h, active=active, use_active=use_active, force=force, use_force=use_force,
                                         vbd_start=start_flags, hold=hold, qd=s.particle_qd, q_pred=self._q_pred,
                                         inv_inertia=m.segment_inv_inertia, segment_damping=m.segment_damping,
                                         sqd=s.segment_qd, sq_prev=self._sq_prev, delta_scale=scale, delta=delta,
                                         delta_count=count)
                if not in_rod_sweep:
                    kernel = xpbd.apply_deltas_and_integrate if scale != 0.0 else xpbd.integrate_particles_and_segments
                    launch(kernel, (n, max(m.particle_count, m.segment_count)), [prediction],
                           [s.particle_q, s.segment_q])
                    prediction = None
            elif sub > 0 and fuse:
                launch(xpbd.finish_and_integrate_particles, (n, m.particle_count), [1.0 / h, *particle_args],
                       [self._q_pred])
            else:
                launch(xpbd.integrate_particles, (n, m.particle_count), particle_args, [self._q_pred])
            if m.segment_count and not self.integrate_together:
                if sub > 0 and fuse:
                    launch(xpbd.finish_and_integrate_segments, (n, m.segment_count),
                           [1.0 / h, m.segment_inv_inertia, m.segment_damping, h, s.segment_q, s.segment_qd],
                           [self._sq_prev])
                else:
                    launch(xpbd.integrate_segments, (n, m.segment_count),
                           [m.segment_inv_inertia, m.segment_damping, h, s.segment_q, s.segment_qd], [self._sq_prev])
            for arr in lam.values():
                cmds.append(arr.zero_)
            for it in range(iters):
                sweep = Sweep(sub, it, substeps, iters, h)
                self._record_sweep(launch, xpbd, inv_dt2, use_lam, sweep, prediction if it == 0 else None)
                for solver in self.solvers:
                    solver.record_sweep(self, launch, sweep)
            # the last substep's velocity update: in the stability check's launch below where nothing comes between
            if not fuse:
                launch(xpbd.update_particle_velocities, (n, m.particle_count), [s.particle_q, self._q_pred, 1.0 / h],
                       [s.particle_qd])
                if m.segment_count:
                    launch(xpbd.update_segment_velocities, (n, m.segment_count),
                           [s.segment_q, self._sq_prev, 1.0 / h], [s.segment_qd])
            for solver in self.solvers:
                if hasattr(solver, "record_substep_end"):
                    solver.record_substep_end(self, launch, Sweep(sub, iters - 1, substeps, iters, h))
        # the stability check also keeps the body poses as the next step's start (body_q_prev) and, fused, runs the
        # last substep's velocity update first: one launch
        finish = 1.0 / h if fuse else 0.0
        flush()  # the last substep's deferred deltas, before the velocity update below
        cmds.append(lambda: self._check_and_restore(end_of_step=True, finish_inv_dt=finish))
        unknown = sorted(set(self.max_registers) - capped)
        if unknown:
            raise ValueError(f"world.max_registers names kernels this world's step does not launch: {unknown}")
        return cmds

    def _predicts_in_rod_sweep(self) -> bool:
        """Whether a substep's prediction runs in its first sweep's fused rod launch
        (``xpbd.predict_and_solve_rods_fused``): ``predict_in_rod_sweep`` set, particles and segments predicted
        together, the rods' colours fused, and no other constraint (tethers, edges, tets, hinges) solved before them in
        the sweep. RopeThreading, RopeCutting and PickAndPlace are such worlds."""
        m = self.model
        return (bool(self.predict_in_rod_sweep) and m.segment_count > 0 and bool(self.integrate_together)
                and self.rod_solver in ("auto", "fused") and m.geo_particles is None and m.edge_count == 0
                and m.tet_count == 0 and m.hinge_count == 0)

    def _no_attachment_pass(self):
        """An ``xpbd.AttachmentPass`` without slots, for a fused rod launch that runs a deferred contact alone."""
        if self._empty_attachment_pass is None:
            from lapwarp.kernels import xpbd

            dev = self.device

            def empty(dtype, ndim=2):
                return wp.zeros((1, 0) if ndim == 2 else 0, dtype=dtype, device=dev)

            self._empty_attachment_pass = make_struct(
                xpbd.AttachmentPass, particle=empty(wp.int32), body=empty(wp.int32), offset=empty(wp.vec3),
                compliance=empty(float), segment=empty(wp.int32), rotation=empty(wp.quat),
                hold_up=empty(wp.vec3, 1), body_q_prev=empty(wp.transform), body_q=empty(wp.transform), blend=0.0,
                inv_mass=empty(float), inv_dt2=0.0, stiff_only=0)
        return self._empty_attachment_pass

    def _contact_in_rod_launch(self) -> bool:
        """Whether a substep's closing attachment pass and particle contact may be deferred into the next substep's
        fused rod launch (``xpbd.contact_rods_fused_kernel``): ``contact_in_rod_launch`` set and the prediction in the
        rod launch (``_predicts_in_rod_sweep``). The contact system defers its contact where no shape is a mesh; any
        other launch recorded before the next substep's rod launch launches them first (each in its own launch, the
        order kept), and a deferred attachment pass without a contact after it keeps its own launch."""
        return bool(self.contact_in_rod_launch) and self._predicts_in_rod_sweep()

    def _record_sweep(self, launch, xpbd, inv_dt2: float, use_lam: int, sweep: Sweep, prediction=None) -> None:
        """Record one sweep's projections; ``prediction`` (an ``xpbd.Prediction``, a substep's first sweep where
        ``_predicts_in_rod_sweep``): the substep's prediction goes into the fused rod launch."""
        m, n, s = self.model, self.num_envs, self.state
        lam = self._lam
        blend = sweep.blend
        # inverse masses for the deformables' own constraints: attached particles count as heavier (see
        # attachment_inverse_masses); the attachments themselves and the integration use the true ones
        w_eff = self._w_eff if self._w_eff is not None else m.particle_inv_mass
        # cutting masks (state arrays, restored by reset); (1, 0) arrays mean "no masks"
        edge_mask = s.edge_active if s.edge_active is not None else self._no_mask
        hinge_mask = s.hinge_active if s.hinge_active is not None else self._no_mask
        tet_mask = s.tet_active if s.tet_active is not None else self._dummy_mask
        tet_map = m.tet_element if s.tet_active is not None else self._no_map_i
        seg_mask = s.segment_active if s.segment_active is not None else self._no_mask

        def solve_chains(cs, rest, compliance, lam_arr, scratch, mask, newton_steps, kernel, tolerance=0.0):
            if self.chain_solver in ("pcr", "hybrid"):
                # a thread block per (env, pack of chains), one launch per family with every Newton step in it
                packs = self._packs[id(cs)]
                if self.chain_solver == "pcr":  # a row per lane
                    lanes = int(self.chain_pcr_threads) or min(128, 32 * ((packs.max_rows + 31) // 32))
                    lanes = launching.block_lanes(self.device, lanes)
                    # compiled without the loop and cut branches where the family has no loop / the scene no masks
                    kernel = chains_block.block_chain_kernel(packs.max_rows, loops=packs.any_closed,
                                                             masked=mask.shape[1] > 0, newton_tolerance=tolerance)
                else:
                    # chain_lane_rows rows per lane: a warp's multiple of lanes on the GPU; on the CPU exactly the
                    # lanes that hold rows, as Warp's cooperative fibers
                    held = chains_hybrid.lanes_for(packs.max_rows, int(self.chain_lane_rows))
                    lanes = 32 * ((held + 31) // 32) if self.device.is_cuda else held
                    # compiled without the loop and cut branches where the family has no loop / the scene no masks
                    kernel = chains_hybrid.hybrid_chain_kernel(packs.max_rows, int(self.chain_lane_rows),
                                                               loops=packs.any_closed, masked=mask.shape[1] > 0,
                                                               newton_tolerance=tolerance)
                for pack_base, count in packs.families:
                    launch(kernel, (n, count, lanes),
                           [pack_base, packs.pack_start, packs.pack_rows, packs.pack_closed, packs.rows, rest,
                            compliance, w_eff, inv_dt2, use_lam, newton_steps, lam_arr, mask],
                           [s.particle_q], block_dim=lanes)
                return
            if self.chain_block_links > 1:
                # partitioned, family after family: per Newton step five launches, blocks of chain_block_links links
                # side by side
                layout, sc = self._chain_partition(cs, scratch)
                for f, (block_base, blocks) in enumerate(layout):
                    fam = chains_partitioned.family(cs, f, block_base, self.chain_block_links, rest, compliance, w_eff,
                                                    mask, lam_arr, use_lam, newton_steps, inv_dt2)
                    chains_partitioned.record_family(launch, n, fam, blocks, sc, s.particle_q)
                return
            # one launch per family of chains that share no node (Gauss-Seidel across families)
            for first, count, link_base, node_base in cs.families:
                args = [first, count, link_base, node_base, cs.edge_count, cs.closed, cs.node, cs.constraint, rest,
                        compliance, w_eff, inv_dt2, use_lam, newton_steps, lam_arr, *scratch, mask]
                split = None
                if self.chain_solver == "registers" and self.chain_register_split:
                    split = chains_split.family_kernel(cs, first, count, tolerance)
                if split is not None:
                    # two lanes per chain, a pair's lanes in one block (their exchanges in shared memory)
                    launch(split, chains_split.launch_dim(n, count), args, [s.particle_q], block_dim=chains_split.BLOCK)
                    continue
                family_kernel = kernel
                if self.chain_solver == "registers":
                    family_kernel = chains_registers.family_kernel(cs, first, count, tolerance) or kernel
                elif self.chain_solver == "open_walk" and not cs.closed_host[first:first + count].any():
                    family_kernel = _OPEN_WALKS[kernel]
                launch(family_kernel, (n, count), args, [s.particle_q])

        def solve_tethers():
            launch(geodesic.solve_geodesic_tethers, (n, m.geo_particles.shape[0]),
                   [m.geo_particles, s.geo_dist, s.geo_source, s.geo_status, w_eff, self.tether_passes], [s.particle_q])

        if m.attachment_capacity:
            bq = s.body_q if s.body_q is not None else self._dummy_tf()
            bqp = self._body_q_prev if self._body_q_prev is not None else bq
            attachment_args = [s.attach_particle, s.attach_body, s.attach_offset, s.attach_compliance,
                               s.attach_segment, s.attach_rotation, m.attach_hold_up, bqp, bq, blend,
                               m.particle_inv_mass, inv_dt2]
            # the held segments' orientations (a world without rods holds none: attach_segment stays -1)
            attachment_out = [s.particle_q, s.segment_q if s.segment_q is not None else self._dummy_quat()]

            def solve_attachments(stiff_only: int):
                if m.attachments_distinct:
                    # distinct static slots: a thread each (the order is immaterial)
                    args = (xpbd.solve_attachment_slots, (n, m.attachment_capacity), [*attachment_args, stiff_only],
                            attachment_out)
                else:
                    args = (xpbd.solve_attachments, n, [*attachment_args, stiff_only], attachment_out)
                if stiff_only == 0 and hasattr(launch, "defer_attachments"):
                    # the closing pass into the next substep's rod launch where nothing else comes first but the
                    # contact (contact_in_rod_launch)
                    launch.defer_attachments(*args, make_struct(xpbd.AttachmentPass, **dict(zip(
                        xpbd.ATTACHMENT_PASS_FIELDS, (*attachment_args, stiff_only), strict=True))))
                else:
                    launch(*args)
            if m.geo_particles is not None:
                # held points first where their bodies hold them, so that the tethers see their anchors there, not
                # one substep of gravity below (stiff attachments only: a soft one projected twice per sweep would be
                # stiffer than its compliance); every attachment again at the end. Only with tethers: elsewhere it
                # was not needed and cost TissueManipulation 12 % (H100)
                solve_attachments(1)
        if m.geo_particles is not None:
            solve_tethers()
        if m.edge_chains is None:
            off = m.edge_color_offsets
            for c in range(len(off) - 1):
                launch(xpbd.solve_edges, (n, off[c + 1] - off[c]),
                       [off[c], m.edge_indices, m.edge_rest, m.edge_compliance, w_eff, inv_dt2, use_lam,
                        lam.get("edge", self._dummy_f), edge_mask], [s.particle_q])
        tet_args = [m.tet_indices, m.tet_inv_rest, m.tet_params, w_eff, inv_dt2, use_lam,
                    lam.get("tet", self._dummy_v2), tet_map, tet_mask, self.tet_rotation_iterations]
        tet_out = [self._tet_rotation if self.tet_rotation_iterations > 0 else self._no_rotation, s.particle_q]
        off = m.tet_color_offsets
        lagged = self.tet_rotation_update == "sweep"
        # the stored rotations refreshed at this sweep (lagged only): its first of the step, then every
        # tet_rotation_refresh-th
        refresh = lagged and (sweep.substep * sweep.iterations + sweep.iteration) % self.tet_rotation_refresh == 0
        if m.tet_count and self.tet_method_in_use == "vbd":
            self._record_vbd_sweep(launch, w_eff, inv_dt2, sweep, tet_map, tet_mask, tet_out[0], lagged, refresh)
        elif m.tet_count:
            if refresh:
                self._record_rotation_refresh(launch, tet_map, tet_mask, tet_out[0])
            if self.fused_tets:
                first, count = self._tet_window
                # on the CPU a tiled block has one lane (Warp's CPU tile semantics): the same sweep, in order
                threads = launching.block_lanes(self.device, self.tet_block_threads)
                launch(xpbd.fused_tet_kernel(count, lagged), (n, threads), [self._tet_color_offsets, first, *tet_args],
                       tet_out, block_dim=threads)
            else:
                for c in range(len(off) - 1):
                    launch(xpbd.solve_tets, (n, off[c + 1] - off[c]), [off[c], *tet_args, int(lagged)], tet_out)
        off = m.hinge_color_offsets
        for c in range(len(off) - 1):
            launch(xpbd.solve_hinges, (n, off[c + 1] - off[c]),
                   [off[c], m.hinge_indices, m.hinge_rest, m.hinge_compliance, w_eff, inv_dt2, use_lam,
                    lam.get("hinge", self._dummy_f), hinge_mask], [s.particle_q])
        if m.edge_chains is not None:
            # after the bending hinges, so every sweep ends with the cloth at its length
            solve_chains(m.edge_chains, m.edge_rest, m.edge_compliance, lam.get("edge", self._dummy_f),
                         self._edge_scratch, edge_mask, self.chain_newton_steps, chains.solve_cloth_chains)
        if m.geo_particles is not None:
            # again after the edges: before them the tethers take the sheet's weight off the chains, after them
            # they undo what the chains' Gauss-Seidel across families moved too far (a held sheet at 10 substeps:
            # mean stretch 2.50 with the first projection only, 1.059 with both; CPU, one env)
            solve_tethers()
        if m.segment_count and self.rod_solver in ("auto", "fused"):
            # every colour of both groups in one launch, a block per env (on the CPU one lane: the same order)
            lanes = launching.block_lanes(self.device, self.rod_block_threads)
            rods = make_struct(xpbd.RodSweep, segment_offsets=self._segment_color_offsets,
                               particles=m.segment_particles, segment_rest=m.segment_rest,
                               segment_compliance=m.segment_compliance, bend_offsets=self._bend_color_offsets,
                               bend_segments=m.bend_segments, bend_rest=m.bend_rest, bend_compliance=m.bend_compliance,
                               inv_inertia=m.segment_inv_inertia, inv_mass=w_eff, inv_dt2=inv_dt2, use_lambda=use_lam,
                               segment_lam=lam.get("segment", self._dummy_v3), bend_lam=lam.get("bend", self._dummy_v3),
                               segment_active=seg_mask)
            # the substep before's closing attachment pass and particle contact, where they were deferred to this
            # launch (contact_in_rod_launch)
            attach, contact = (launch.take_prologue() if prediction is not None and hasattr(launch, "take_prologue")
                               else (None, None))
            if contact is None and attach is not None:
                launch(*attach[:4])  # the attachments alone: in their own launch, as given
            if prediction is None:
                launch(xpbd.solve_rods_fused, (n, lanes), [rods], [s.particle_q, s.segment_q], block_dim=lanes)
            elif contact is None:
                launch(xpbd.predict_and_solve_rods_fused, (n, lanes), [prediction, rods], [s.particle_q, s.segment_q],
                       block_dim=lanes)
            else:
                (particles, shapes, motion, poses, solve, ignore, masks, report, margin), (_, reports) = contact
                bundle = attach[4] if attach is not None else self._no_attachment_pass()
                launch(xpbd.contact_rods_fused_kernel(), (n, lanes),
                       [bundle, particles, shapes, motion, poses, solve, ignore, masks, report, margin, prediction,
                        rods], [s.particle_q, s.segment_q, reports], block_dim=lanes)
        elif m.segment_count:
            off = m.segment_color_offsets
            for c in range(len(off) - 1):
                launch(xpbd.solve_stretch_shear, (n, off[c + 1] - off[c]),
                       [off[c], m.segment_particles, m.segment_rest, m.segment_compliance, m.segment_inv_inertia,
                        w_eff, inv_dt2, use_lam, lam.get("segment", self._dummy_v3), seg_mask],
                       [s.particle_q, s.segment_q])
            off = m.bend_color_offsets
            for c in range(len(off) - 1):
                launch(xpbd.solve_bend_twist, (n, off[c + 1] - off[c]),
                       [off[c], m.bend_segments, m.bend_rest, m.bend_compliance, m.segment_inv_inertia, inv_dt2,
                        use_lam, lam.get("bend", self._dummy_v3), seg_mask], [s.segment_q])
        if m.rod_count:
            # after shear and bend-twist so every sweep ends with the rods at their length
            solve_chains(m.rod_chains, m.rod_stretch_rest, m.rod_stretch_compliance, lam.get("rod", self._dummy_f),
                         self._rod_scratch, seg_mask, self.rod_newton_steps, chains.solve_chains,
                         float(self.rod_newton_tolerance))
        if m.attachment_capacity:
            solve_attachments(0)

    def _prediction_masks(self) -> tuple:
        """``(active, use_active, force, use_force)`` of the prediction (``xpbd.integrate_particles``) and of what
        must repeat its choices (``vbd.begin_substep``): cut-loose particles and external forces, or dummies."""
        s = self.state
        return (s.particle_active if s.particle_active is not None else self._dummy_mask,
                int(s.particle_active is not None),
                self.particle_force if self.particle_force is not None else self._dummy_v3,
                int(self.particle_force is not None))

    def _vbd_start_in_prediction(self) -> bool:
        """Whether the prediction writes the per-vertex tet solve's start (``xpbd.integrate_particle``'s
        ``vbd_start``) instead of ``vbd.begin_substep`` after it: where the solve is in use and nothing the sweep runs
        before it moves particles (geodesic tethers, held points among them, and plain edge constraints do; the
        tets come next). One launch and one pass over the tet vertices fewer per substep (ThreadInHole: 40 per env
        step)."""
        m = self.model
        return (self.tet_method_in_use == "vbd" and m.tet_count > 0 and m.geo_particles is None
                and (m.edge_chains is not None or len(m.edge_color_offsets) <= 1))

    def _record_rotation_refresh(self, launch, tet_map, tet_mask, rotation) -> None:
        """Every tet's rotation once, before the sweep that uses them as they are (``tet_rotation_update`` "sweep",
        ``xpbd.refresh_tet_rotations``)."""
        from lapwarp.kernels import xpbd

        m, s = self.model, self.state
        launch(xpbd.refresh_tet_rotations, (self.num_envs, m.tet_count),
               [m.tet_indices, m.tet_inv_rest, tet_map, tet_mask, self.tet_rotation_iterations, self._tet_hold(),
                s.particle_q], [rotation])

    def _record_vbd_sweep(self, launch, w_eff, inv_dt2: float, sweep: Sweep, tet_map, tet_mask, rotation,
                          lagged: bool, refresh: bool) -> None:
        """The tets' per-vertex sweep (``tet_method`` "vbd", kernels/vbd.py); the first sweep of a substep starts the
        tet vertices from the inertial guess without gravity (``vbd.begin_substep``). ``lagged``: the sweep reads the
        stored rotations (``tet_rotation_update`` "sweep"), ``refresh``: refreshed first, after that start."""
        from lapwarp.kernels import vbd

        m, n, s, dev = self.model, self.num_envs, self.state, self.device
        vertices, offsets, offsets_dev, adj_offsets, adj_tets, adj_corners = self._vbd_layout
        if sweep.iteration == 0 and not self._vbd_start_in_prediction():
            launch(vbd.begin_substep, (n, vertices.shape[0]),
                   [vertices, m.particle_inv_mass, m.gravity, sweep.h, *self._prediction_masks(), self._q_pred],
                   [s.particle_q])
        if refresh:
            self._record_rotation_refresh(launch, tet_map, tet_mask, rotation)
        common = [vertices, adj_offsets, adj_tets, adj_corners, m.tet_indices, m.tet_inv_rest,
                  self._tet_stiffness, w_eff, self._q_pred, inv_dt2, tet_map, tet_mask, self.tet_rotation_iterations]
        if self.fused_tets:
            first, count = self._tet_window
            threads = launching.block_lanes(dev, self.tet_block_threads)
            # the substep's last sweep counts the env's quiet substeps or marks it skipped (hold.TetHold)
            hold_update = int(sweep.iteration == sweep.iterations - 1)
            launch(vbd.fused_vertex_kernel(count, lagged), (n, threads),
                   [offsets_dev, first, *common, self._tet_hold(), hold_update], [rotation, s.particle_q],
                   block_dim=threads)
        else:
            for c in range(len(offsets) - 1):
                launch(vbd.solve_vertices, (n, offsets[c + 1] - offsets[c]), [offsets[c], *common, int(lagged)],
                       [rotation, s.particle_q])

    #: sweep rounds (four orders each) of the geodesic tethers' distances per step while an env's are not final
    GEODESIC_ROUNDS_PER_STEP = 2

    def _record_geodesic_refresh(self, launch) -> None:
        """Once per step, before the substeps: flag envs whose anchors (pinned or stiffly held particles) or cloth
        triangles changed, and sweep the flagged envs' tether distances (``lapwarp.kernels.geodesic``)."""
        m, n, s = self.model, self.num_envs, self.state
        w_eff = self._w_eff if self._w_eff is not None else m.particle_inv_mass
        launch(geodesic.detect_anchor_changes, (n, m.geo_particles.shape[0]),
               [m.geo_particles, m.particle_inv_mass, w_eff], [s.geo_anchor, s.geo_status])
        masked = int(s.tri_active is not None)
        if masked:
            launch(geodesic.detect_cut_changes, (n, m.geo_tris.shape[0]), [m.geo_tri_element, s.tri_active],
                   [s.geo_tri_seen, s.geo_status])
        launch(geodesic.sweep_geodesics, n,
               [m.geo_particles, m.geo_tris, m.geo_tri_element, m.geo_order, m.geo_rest, s.geo_anchor,
                s.tri_active if masked else self._dummy_mask, masked, self.GEODESIC_ROUNDS_PER_STEP],
               [s.geo_label, s.geo_dist, s.geo_source, s.geo_status])

    def _dummy_tf(self) -> wp.array:
        if not hasattr(self, "_dummy_tf_arr"):
            self._dummy_tf_arr = wp.zeros((1, 1), dtype=wp.transform, device=self.device)
        return self._dummy_tf_arr

    def _dummy_quat(self) -> wp.array:
        if not hasattr(self, "_dummy_quat_arr"):
            self._dummy_quat_arr = wp.zeros((1, 1), dtype=wp.quat, device=self.device)
        return self._dummy_quat_arr

    def check_stability(self, end_of_step: bool = False) -> None:
        """Flag envs with NaN or speed above ``model.max_speed``; optionally reset just those envs. One launch
        (``world_kernels.check_and_restore``, a block per env) at the end of every step, which (``end_of_step``) also
        keeps the body poses as the next step's start."""
        self._check_and_restore(end_of_step)

    def _check_and_restore(self, end_of_step: bool, finish_inv_dt: float = 0.0) -> None:
        """``check_stability``'s launch; ``finish_inv_dt > 0`` (the World's step) also runs the last substep's velocity
        update first (``world_kernels.check_and_restore``)."""
        m = self.model
        if m.particle_count == 0:
            return
        live, start, width = self._row_structs()
        body_prev = self._body_q_prev if self._body_q_prev is not None else self._dummy_tf()
        restore_prev = int(self.auto_reset_unstable and self._body_q_prev is not None)
        rotations = ((self._start_tet_rotation, self._tet_rotation) if self._start_tet_rotation is not None
                     else (self._no_rotation, self._no_rotation))
        lanes = launching.block_lanes(self.device, self.ROW_COPY_LANES)
        copy_body_q = int(end_of_step and self._body_q_prev is not None)
        launching.launch(world_kernels.check_and_restore, dim=(self.num_envs, lanes),
                         inputs=[float(m.max_speed), int(self.auto_reset_unstable), start, live, body_prev,
                                 restore_prev, width, *rotations, copy_body_q, float(finish_inv_dt),
                                 self._q_pred if finish_inv_dt > 0.0 else self._dummy_v3,
                                 self._sq_prev if finish_inv_dt > 0.0 and self._sq_prev is not None
                                 else self._no_rotation],
                         outputs=[self._unstable_now, self.unstable, self._hold_quiet], device=self.device,
                         block_dim=lanes)

    # ------------------------------------------------------------------------------------------------
    def _state_rows(self, state: State) -> world_kernels.StateRows:
        rows = world_kernels.StateRows()
        empty = {}
        for name, dtype in world_kernels.StateRows.cls.__annotations__.items():
            arr = getattr(state, name, None)
            if arr is None:
                dt = dtype.dtype
                if dt not in empty:
                    empty[dt] = wp.zeros((self.num_envs, 0), dtype=dt, device=self.device)
                arr = empty[dt]
            setattr(rows, name, arr)
        return rows

    def _row_structs(self) -> tuple:
        """``(live, start, width)``: the state's and the start state's arrays as ``StateRows`` and their widest row."""
        if not hasattr(self, "_rows"):
            arrays = self.state.arrays().values()
            self._rows = (self._state_rows(self.state), self._state_rows(self._start_state),
                          max([a.shape[1] for a in arrays if a.ndim == 2] or [0]))
        return self._rows

    def _copy_rows(self, env_mask: wp.array, src: State, dst: State, restore: bool) -> None:
        live, start, width = self._row_structs()
        if width == 0:
            return
        body_prev = self._body_q_prev if self._body_q_prev is not None else self._dummy_tf()
        lanes = launching.block_lanes(self.device, self.ROW_COPY_LANES)
        launching.launch(world_kernels.copy_state_rows, dim=(self.num_envs, lanes),
                         inputs=[env_mask, start if restore else live, live if restore else start, body_prev,
                                 int(restore and self._body_q_prev is not None), width, lanes], device=self.device)

    def _copy_tet_rotations(self, env_mask: wp.array, restore: bool) -> None:
        if self._start_tet_rotation is None:
            return
        src, dst = ((self._start_tet_rotation, self._tet_rotation) if restore
                    else (self._tet_rotation, self._start_tet_rotation))
        lanes = launching.block_lanes(self.device, self.ROW_COPY_LANES)
        launching.launch(world_kernels.copy_masked_2d, dim=(self.num_envs, lanes), inputs=[env_mask, src, lanes],
                         outputs=[dst], device=self.device)

    def _restore(self, env_mask: wp.array) -> None:
        self._copy_rows(env_mask, self._start_state, self.state, restore=True)
        self._copy_tet_rotations(env_mask, restore=True)
        if self.state.cut_dirty is not None:
            # the restored masks differ from what the cutting system last counted: its surfaces, pieces and counters
            # of these envs are recomputed by its next update (the saved start state may hold a clean flag)
            launching.launch(world_kernels.mark_masked_rows, dim=self.num_envs, inputs=[env_mask],
                             outputs=[self.state.cut_dirty], device=self.device)

    def reset(self, env_mask: wp.array) -> None:
        """Restore the start state of the envs whose ``env_mask`` entry is non-zero, in place; then let every
        added system forget those envs (``solver.reset``)."""
        self._restore(env_mask)
        launching.launch(world_kernels.clear_masked_int, dim=self.num_envs, inputs=[env_mask], outputs=[self.unstable],
                         device=self.device)
        self.wake_tets(env_mask)
        for solver in self.solvers:
            if hasattr(solver, "reset"):
                solver.reset(env_mask)

    def save_start_state(self, env_mask: wp.array | None = None) -> None:
        """Make the current state of the masked envs (all envs without a mask) their start state: what ``reset``
        and a stability restore return to. The env base calls it after every task reset, so a randomised start
        written into ``state`` is kept for the episode (one launch, graph-capturable)."""
        mask = env_mask if env_mask is not None else self._all_envs()
        self._copy_rows(mask, self.state, self._start_state, restore=False)
        self._copy_tet_rotations(mask, restore=False)
        # a task's reset wrote this start (a randomised pose, a material): its tets are solved until they rest there
        self.wake_tets(mask)

    def set_body_poses(self, poses: wp.array, bodies: wp.array, teleport_mask: wp.array | None = None) -> None:
        """Pose kinematic bodies: ``state.body_q[env, bodies[k]] = poses[env, k]`` for every env.

        During a step the World moves each body linearly from its pose at the start of the step to this one across
        the substeps. With ``teleport_mask`` (at reset) the masked envs' bodies jump there instead (no sweep through
        the scene from the old pose) and the pose becomes part of their start state; the other envs are untouched.

        Args:
            poses: ``(num_envs, K)`` ``wp.transform`` in the env frame.
            bodies: ``(K,)`` int32 body indices (``SceneBuilder.add_body``).
            teleport_mask: ``(num_envs,)`` int32 or None.
        """
        s = self.state
        if s.body_q is None:
            raise ValueError("the scene has no kinematic bodies (SceneBuilder.add_body)")
        if poses.ndim != 2 or poses.shape[0] != self.num_envs or poses.shape[1] != bodies.shape[0]:
            raise ValueError(f"poses must be ({self.num_envs}, {bodies.shape[0]}) transforms, got {poses.shape}")
        teleport = teleport_mask is not None
        launching.launch(world_kernels.write_body_poses, dim=poses.shape,
                         inputs=[poses, bodies, teleport_mask if teleport else self.unstable, int(teleport)],
                         outputs=[s.body_q, self._body_q_prev, self._start_state.body_q], device=self.device)

    def set_materials(self, obj, env_mask: wp.array, stiffness_scale: wp.array | None = None,
                      damping: wp.array | None = None, density_scale: wp.array | None = None) -> None:
        """Give the masked envs their own material for ``obj`` (a ``SceneObject``): the built stiffness (Young's
        modulus, membrane, bending, rod moduli) times ``stiffness_scale[env]``, the built density times
        ``density_scale[env]``, and the velocity damping rate ``damping[env]`` (1/s); each a ``(num_envs,)`` float
        array or None (unchanged). Launches only (call it in a task's reset, inside the captured step); the scene
        must be built with ``finalize(per_env_materials=True)``. The first call per object builds its column tables
        on the host: make it once before capturing."""
        m = self.model
        if not m.material_base:
            raise ValueError("per-env materials need SceneBuilder.finalize(per_env_materials=True)")
        cols = self._material_columns(obj)
        inv_stiffness = inv_density = None
        if stiffness_scale is not None:
            inv_stiffness = self._scratch_reciprocal("stiffness", stiffness_scale)
        if density_scale is not None:
            inv_density = self._scratch_reciprocal("density", density_scale)
        n, dev = self.num_envs, self.device
        for name, columns in cols.items():
            base, out = m.material_base[name], getattr(m, name)
            if name == "tet_params" and stiffness_scale is not None:
                launching.launch(world_kernels.scale_tet_compliance, dim=(n, columns.shape[0]),
                                 inputs=[env_mask, columns, base, stiffness_scale], outputs=[out], device=dev)
                self._refresh_tet_stiffness()
            elif name.endswith("compliance") and inv_stiffness is not None:
                launching.launch(world_kernels.scale_material_columns, dim=(n, columns.shape[0]),
                                 inputs=[env_mask, columns, base, inv_stiffness], outputs=[out], device=dev)
            elif name in ("particle_inv_mass", "segment_inv_inertia") and inv_density is not None:
                launching.launch(world_kernels.scale_material_columns, dim=(n, columns.shape[0]),
                                 inputs=[env_mask, columns, base, inv_density], outputs=[out], device=dev)
            elif name.endswith("damping") and damping is not None:
                launching.launch(world_kernels.set_material_columns, dim=(n, columns.shape[0]),
                                 inputs=[env_mask, columns, damping], outputs=[out], device=dev)
        self.wake_tets(env_mask)  # a held body rests where its old material held it

    def _scratch_reciprocal(self, key: str, values: wp.array) -> wp.array:
        if not hasattr(self, "_reciprocals"):
            self._reciprocals = {}
        out = self._reciprocals.setdefault(key, wp.zeros(self.num_envs, dtype=float, device=self.device))
        launching.launch(world_kernels.reciprocal, dim=self.num_envs, inputs=[values], outputs=[out],
                         device=self.device)
        return out

    def _material_columns(self, obj) -> dict:
        """Columns of every material array that belong to ``obj`` (host tables built once per object)."""
        if not hasattr(self, "_material_cols"):
            self._material_cols = {}
        if obj.name in self._material_cols:
            return self._material_cols[obj.name]
        m, dev = self.model, self.device
        lo, hi = obj.particle_start, obj.particle_start + obj.particle_count
        seg = np.arange(obj.segment_start, obj.segment_start + obj.segment_count)

        def inside(values):
            return np.nonzero((values >= lo) & (values < hi))[0]

        found = {"particle_inv_mass": np.arange(lo, hi), "particle_damping": np.arange(lo, hi)}
        if m.edge_count:
            found["edge_compliance"] = inside(m.edge_indices.numpy()[:, 0])
        if m.hinge_count:
            found["hinge_compliance"] = inside(m.hinge_indices.numpy()[:, 2])
        if m.tet_count:
            found["tet_params"] = inside(m.tet_indices.numpy()[:, 0])
        if m.segment_count and len(seg):
            found["segment_compliance"] = inside(m.segment_particles.numpy()[:, 0])
            found["segment_inv_inertia"] = found["segment_damping"] = found["rod_stretch_compliance"] = seg
            if m.bend_count:
                b = m.bend_segments.numpy()[:, 0]
                found["bend_compliance"] = np.nonzero((b >= seg[0]) & (b <= seg[-1]))[0]
        cols = {name: wp.array(idx.astype(np.int32), dtype=wp.int32, device=dev) for name, idx in found.items()
                if len(idx) and name in m.material_base}
        self._material_cols[obj.name] = cols
        return cols

    def _all_envs(self) -> wp.array:
        if not hasattr(self, "_all_envs_mask"):
            self._all_envs_mask = wp.ones(self.num_envs, dtype=wp.int32, device=self.device)
        return self._all_envs_mask

    def reset_all(self) -> None:
        """Reset every env."""
        self.reset(self._all_envs())

    # ------------------------------------------------------------------------------------------------
    def simulate(self, duration: float, dt: float) -> None:
        """Run ``round(duration / dt)`` steps of ``dt`` (host-side convenience for scripts and tests)."""
        for _ in range(int(round(duration / dt))):
            self.step(dt)

    def positions(self, obj=None) -> np.ndarray:
        """Particle positions as a ``(num_envs, n, 3)`` NumPy copy (of one SceneObject if given). Syncs."""
        q = np.array(self.state.particle_q.numpy(), copy=True)  # .numpy() is a view on CPU
        return q if obj is None else q[:, obj.particles]

    def state_bytes_per_env(self) -> int:
        """Bytes of dynamic per-env data: state arrays plus solver scratch (excludes shared topology)."""
        total = sum(a.capacity for a in self.state.arrays().values())
        total += sum(a.capacity for a in self._start_state.arrays().values())
        partitions = [a for *_, arrays in self._partitions.values() for a in arrays]
        for a in (self._q_pred, self._sq_prev, self._body_q_prev, *self._rod_scratch, *self._edge_scratch,
                  *self._lam.values(), *partitions):
            if a is not None:
                total += a.capacity
        return total // max(1, self.num_envs)
