"""Physics-only throughput and solution quality of the XPBD core: env-steps/s for a batch of cloths, tet blocks or
rods, with the stretch (or sag) each configuration ends up with.

One env step is 0.1 s of simulated time (LapGym's 10 Hz control) split into ``--substeps`` XPBD substeps with
``--iterations`` sweeps each. On CUDA one env step is captured as a CUDA graph and replayed; timings use
``wp.synchronize_device``. Every figure is reported with its substeps, iterations, edge solver and the quality of the
solution: the mean and max edge stretch (current / rest length over all edges of all envs; the cloth's physical
stretch under its own weight is ~1e-4) or a tet block's sag.

Scenes (SI units; cloths are 40 x 40 vertices over 75 mm, PrecisionCutting's grid: 1,600 vertices, 3,042 triangles,
0.2 kg/m^2, stretch stiffness 1e3 N/m, bending 1e-6 N m):

* ``cloth``: hanging from its pinned top edge with geodesic tethers (``add_cloth(tethers=True)``).
* ``cloth_free``: the same without tethers (``--no-tethers`` of the issue); ``cloth_cut``: cuttable (no tethers,
  cutting masks in every substep, nothing cut); ``cloth_cut_tethers``: cuttable with geodesic tethers.
* ``cloth_drape``: Newton's peer scene (``tools/peer_newton_cloth.py``): flat in the xy plane, pinned along its x = 0
  edge, released to swing down and drape; ``grid_stretch_*`` and ``mid_row_stretch`` are reported the same way as
  the peer script does it (structural row/column edges; the middle row's length / 75 mm).
* ``cloth_pulled``: flat, pinned along its back edge (y = 75 mm); its two front corners are grasped by kinematic
  attachments (compliance 1e-6 m/N) and dragged 15 mm down in 1 s along the arc about the pinned edge, then held:
  PrecisionCutting's support pattern (back edge and near corners) with the corners moving. ``cloth_pulled_tethers``:
  with geodesic tethers (the held corners are anchors too); ``cloth_pulled_cut_tethers``: the same, cuttable.
* ``tet``: 40 x 40 x 20 mm tissue block, 7 x 6 x 4 cells -> 1,008 tets, E = 3 kPa, nu = 0.45, clamped base.
  ``tet_stiff``: the same at E = 30 kPa; ``sag`` is the top face's mean sag.
* ``rod``: 100 segments, 200 mm, r = 1 mm, E = 1e6 Pa, pinned at the top, swinging into its hang.

``--substeps 0`` means automatic (``SceneBuilder.finalize(substeps=None)``: 10, or more for stiff tets).

    python benchmarks/bench_physics.py --device cuda:0 --scene cloth_free cloth_cut cloth_pulled --num-envs 4096 \\
        --substeps 20 40 --out physics.json
    python benchmarks/bench_physics.py --device cpu --num-envs 2 --steps 2 --settle-steps 2   # smoke test
"""

from __future__ import annotations

import argparse
import itertools
import json
import time

import numpy as np
import warp as wp

from lapwarp.assets import box_tets, cloth_grid
from lapwarp.builder import SceneBuilder
from lapwarp.cli import non_negative_int, positive_int
from lapwarp.world import CHAIN_SOLVERS

DT = 0.1  # simulated seconds per env step


def _cloth(builder, v, t, fixed, **kw):
    return builder.add_cloth(v, t, areal_density=0.2, stretch_stiffness=1e3, bend_stiffness=1e-6, damping=1.0,
                             fixed=fixed, **kw)


def build_hanging(num_envs, device, substeps, iterations, edge_solver, tethers=False, cuttable=False):
    b = SceneBuilder()
    v, t = cloth_grid(40, 40, 0.075, 0.075, plane="xz", origin=(0.0, 0.0, -0.075))
    obj = _cloth(b, v, t, np.nonzero(v[:, 2] > -1e-9)[0], tethers=tethers, cuttable=cuttable)
    world = b.finalize(num_envs, device, substeps=substeps, iterations=iterations, edge_solver=edge_solver)
    q = world.state.particle_q.numpy()
    q[..., 1] += 0.2 * (-q[..., 2])  # lean the sheet out of its vertical plane: it swings into its hang
    world.state.particle_q.assign(q)
    world.save_start_state()
    return world, obj, v, None


def build_drape(num_envs, device, substeps, iterations, edge_solver):
    b = SceneBuilder()
    v, t = cloth_grid(40, 40, 0.075, 0.075, plane="xy", origin=(0.0, -0.0375, 0.0))
    obj = _cloth(b, v, t, np.nonzero(v[:, 0] < 1e-9)[0])
    world = b.finalize(num_envs, device, substeps=substeps, iterations=iterations, edge_solver=edge_solver)
    return world, obj, v, None


def build_pulled(num_envs, device, substeps, iterations, edge_solver, tethers=False, cuttable=False):
    b = SceneBuilder()
    v, t = cloth_grid(40, 40, 0.075, 0.075, plane="xy")
    obj = _cloth(b, v, t, np.nonzero(v[:, 1] > 0.075 - 1e-9)[0], tethers=tethers, cuttable=cuttable)
    corners = [0, 39]
    bodies = [b.add_body(f"grasper{k}", pose=(*v[c], 0.0, 0.0, 0.0, 1.0)) for k, c in enumerate(corners)]
    for c, body in zip(corners, bodies, strict=True):
        b.add_attachment(obj.particle_start + c, body, compliance=1e-6)
    world = b.finalize(num_envs, device, substeps=substeps, iterations=iterations, edge_solver=edge_solver)
    ids = wp.array(np.array(bodies, np.int32), dtype=wp.int32, device=device)

    def drag(step: int) -> None:  # host-side: before timing
        drop = 0.015 * min(step, 10) / 10
        back = 0.075 - np.sqrt(0.075**2 - drop**2)  # along the arc about the pinned edge: no stretch needed
        pose = [[*(v[c] + (0.0, back, -drop)), 0.0, 0.0, 0.0, 1.0] for c in corners]
        world.set_body_poses(wp.array(np.array([pose] * num_envs, np.float32), dtype=wp.transform, device=device),
                             ids)

    return world, obj, v, drag


def build_tet(num_envs, device, substeps, iterations, edge_solver, youngs=3e3):
    b = SceneBuilder()
    v, t = box_tets((0.04, 0.04, 0.02), (7, 6, 4))
    obj = b.add_tet_mesh(v, t, density=1000.0, youngs_modulus=youngs, poisson_ratio=0.45, damping=1.0,
                         fixed=np.nonzero(v[:, 2] < 1e-9)[0])
    world = b.finalize(num_envs, device, substeps=substeps, iterations=iterations)
    return world, obj, v, None


def build_rod(num_envs, device, substeps, iterations, edge_solver):
    b = SceneBuilder()
    n = 101
    s = np.linspace(0.0, 0.2, n)
    pts = np.stack([s * np.sin(np.radians(30.0)), np.zeros(n), -s * np.cos(np.radians(30.0))], axis=1)
    obj = b.add_rod(pts, radius=0.001, density=1000.0, youngs_modulus=1e6, damping=1.0, fixed=[0])
    world = b.finalize(num_envs, device, substeps=substeps, iterations=iterations)
    return world, obj, pts, None


SCENES = {
    "cloth": lambda *a: build_hanging(*a, tethers=True),
    "cloth_free": build_hanging,
    "cloth_cut": lambda *a: build_hanging(*a, cuttable=True),
    "cloth_cut_tethers": lambda *a: build_hanging(*a, tethers=True, cuttable=True),
    "cloth_drape": build_drape,
    "cloth_pulled": build_pulled,
    "cloth_pulled_tethers": lambda *a: build_pulled(*a, tethers=True),
    "cloth_pulled_cut_tethers": lambda *a: build_pulled(*a, tethers=True, cuttable=True),
    "tet": build_tet,
    "tet_stiff": lambda *a: build_tet(*a, youngs=3e4),
    "rod": build_rod,
}


def quality(scene: str, world, obj, rest: np.ndarray) -> dict:
    q = world.positions(obj).astype(np.float64)
    out = {"nan_envs": int((~np.isfinite(q).all(axis=(1, 2))).sum())}
    if scene.startswith("tet"):
        top = np.nonzero(rest[:, 2] > 0.02 - 1e-9)[0]
        out["sag_m"] = float(-(q[:, top, 2] - rest[top, 2]).mean())
        return out
    e = obj.edges - obj.particle_start
    ratio = np.linalg.norm(q[:, e[:, 0]] - q[:, e[:, 1]], axis=2) / np.linalg.norm(rest[e[:, 0]] - rest[e[:, 1]],
                                                                                     axis=1)
    out.update(stretch_mean=float(np.nanmean(ratio)), stretch_max=float(np.nanmax(ratio)))
    if scene.startswith("cloth"):
        grid = q.reshape(q.shape[0], 40, 40, 3)  # vertex j * 40 + i: row j, column i
        rows = np.linalg.norm(np.diff(grid, axis=2), axis=3) / (0.075 / 39)
        cols = np.linalg.norm(np.diff(grid, axis=1), axis=3) / (0.075 / 39)
        structural = np.concatenate([rows.reshape(len(q), -1), cols.reshape(len(q), -1)], axis=1)
        out.update(grid_stretch_mean=float(np.nanmean(structural)), grid_stretch_max=float(np.nanmax(structural)))
        if scene.startswith("cloth_drape"):  # the peer script's metric: the middle row (y = 0) from pinned to free edge
            out["mid_row_stretch"] = float(np.nanmax(rows[:, 20].sum(axis=1) / 39))
    return out


def timed_steps(world, device: str, steps: int) -> float:
    """Seconds for ``steps`` env steps of ``DT``: on CUDA one step captured as a graph (after one warm replay) and
    replayed; on the CPU plain steps. The world's launches must already be recorded (step it once before)."""
    wp.synchronize_device(device)
    graph = None
    if wp.get_device(device).is_cuda:
        with wp.ScopedCapture(device=device) as cap:
            world.step(DT)
        graph = cap.graph
        wp.capture_launch(graph)  # warm
    wp.synchronize_device(device)
    t0 = time.perf_counter()
    for _ in range(steps):
        if graph is not None:
            wp.capture_launch(graph)
        else:
            world.step(DT)
    wp.synchronize_device(device)
    return time.perf_counter() - t0


def run(scene: str, num_envs: int, device: str, substeps: int, iterations: int, edge_solver: str, steps: int,
        settle: int, newton_steps: int | None = None, block_links: int = 0, tet_solver: str | None = None,
        tet_method: str | None = None, tether_passes: int | None = None, chain_solver: str = "thomas",
        pcr_rows: int = 0, lane_rows: int = 4) -> dict:
    wp.synchronize_device(device)
    world, obj, rest, drag = SCENES[scene](num_envs, device, substeps or None, iterations, edge_solver)
    if tet_solver is not None:
        world.tet_solver = tet_solver
    if tet_method is not None:
        world.tet_method = tet_method
    if newton_steps:
        world.chain_newton_steps = newton_steps
    world.chain_block_links = block_links
    world.chain_solver = chain_solver
    world.chain_pcr_rows = pcr_rows
    world.chain_lane_rows = lane_rows
    if tether_passes is not None:
        world.tether_passes = tether_passes
    dev = wp.get_device(device)
    # settle (and drag) before timing; this also compiles the kernels and records a step's launches
    for k in range(max(1, settle)):
        if drag is not None:
            drag(k + 1)
        world.step(DT)
    elapsed = timed_steps(world, device, steps)
    m = world.model
    rec = {
        "scene": scene, "device": dev.name if dev.is_cuda else "cpu", "num_envs": num_envs,
        "sim_seconds_per_env_step": DT, "substeps": world.substeps_for(DT), "iterations": world.iterations,
        "edge_solver": "chains" if m.edge_chains is not None else ("colored" if m.edge_count else None),
        "chain_newton_steps": world.chain_newton_steps if m.edge_chains is not None else None,
        "chain_block_links": world.chain_block_links,
        "chain_solver": world.chain_solver,
        "chain_pcr_rows": world.chain_pcr_rows if world.chain_solver in ("pcr", "hybrid") else None,
        "chain_lane_rows": world.chain_lane_rows if world.chain_solver == "hybrid" else None,
        "chain_families": m.edge_chains.num_families if m.edge_chains is not None else None,
        "tet_solver": ("fused" if world.fused_tets else "colored") if m.tet_count else None,
        "tet_method": world.tet_method_in_use if m.tet_count else None,
        "tethers": m.geo_particles is not None,
        "tether_passes": world.tether_passes if m.geo_particles is not None else None,
        "cuda_graph": dev.is_cuda, "steps_timed": steps,
        "seconds": elapsed,
        "env_steps_per_s": num_envs * steps / elapsed, "unstable_envs": int(world.unstable.numpy().sum()),
        "state_bytes_per_env": world.state_bytes_per_env(),
        "sim_time_s": DT * (max(1, settle) + 2 + steps) if dev.is_cuda else DT * (max(1, settle) + steps),
    }
    rec.update(quality(scene, world, obj, rest))
    del world
    return rec


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--device", default="cuda:0")
    p.add_argument("--num-envs", type=positive_int, nargs="+", default=[4096])
    p.add_argument("--scene", nargs="+", default=["cloth", "cloth_free", "tet", "rod"], choices=[*SCENES, "all"])
    p.add_argument("--substeps", type=non_negative_int, nargs="+", default=[20],
                   help="one run per value; 0 = automatic")
    p.add_argument("--iterations", type=positive_int, nargs="+", default=[1], help="one run per value")
    p.add_argument("--edge-solver", nargs="+", default=["chains"], choices=["chains", "colored"])
    p.add_argument("--newton-steps", type=int, default=None, help="Newton steps per cloth chain solve")
    p.add_argument("--chain-block-links", type=int, nargs="+", default=[0],
                   help="one run per value: 0 = one thread per chain, B >= 2 = blocks of B links")
    p.add_argument("--chain-solver", nargs="+", default=["thomas"], choices=list(CHAIN_SOLVERS),
                   help="one run per value: thomas = a thread walks each chain (or its blocks, --chain-block-links), "
                        "pcr = a thread block per pack of chains (kernels/chains_block.py), hybrid = the same packs, "
                        "a few rows per lane (kernels/chains_hybrid.py)")
    p.add_argument("--pcr-rows", type=non_negative_int, nargs="+", default=[0],
                   help="rows per pack of the 'pcr' chain solve, one run per value (0: the world's default, 1: a chain "
                        "per block)")
    p.add_argument("--lane-rows", type=positive_int, nargs="+", default=[4],
                   help="rows per lane of the 'hybrid' chain solve, one run per value")
    p.add_argument("--tet-solver", nargs="+", default=[None], choices=["auto", "colored", "fused"],
                   help="one run per value (tet scenes; default: the world's own choice)")
    p.add_argument("--tet-method", nargs="+", default=[None], choices=["auto", "xpbd", "vbd"],
                   help="one run per value (tet scenes; default: the world's own)")
    p.add_argument("--tether-passes", type=int, nargs="+", default=[None],
                   help="passes over each particle's geodesic tethers per projection (tethered scenes; default: the "
                        "World's)")
    p.add_argument("--steps", type=positive_int, default=30, help="timed env steps")
    p.add_argument("--settle-steps", type=non_negative_int, default=30, help="untimed env steps before timing")
    p.add_argument("--out", default=None, help="append one JSON line per run to this file")
    args = p.parse_args()

    wp.config.log_level = max(wp.config.log_level, wp.LOG_WARNING)  # no per-module load lines
    wp.config.enable_cpu_blocks = True  # the 'hybrid' chain solve's lanes as Warp's fibers on a CPU
    wp.init()
    scenes = list(SCENES) if "all" in args.scene else args.scene
    for scene in scenes:
        solvers = args.edge_solver if scene.startswith("cloth") else ["chains"]
        for solver in solvers:
            for sub in args.substeps:
                for it in args.iterations:
                    tet_solvers = args.tet_solver if scene.startswith("tet") else [None]
                    tet_methods = args.tet_method if scene.startswith("tet") else [None]
                    passes = args.tether_passes if "tethers" in scene or scene == "cloth" else [None]
                    for n, block, chain, rows, lane_rows, tets, method, tp in itertools.product(
                            args.num_envs, args.chain_block_links, args.chain_solver, args.pcr_rows, args.lane_rows,
                            tet_solvers, tet_methods, passes):
                        if chain not in ("pcr", "hybrid") and rows != args.pcr_rows[0]:
                            continue  # the packs are the block solves' alone
                        if chain != "hybrid" and lane_rows != args.lane_rows[0]:
                            continue  # rows per lane: the hybrid solve's alone
                        rec = run(scene, n, args.device, sub, it, solver, args.steps, args.settle_steps,
                                  args.newton_steps, block, tets, method, tp, chain, rows, lane_rows)
                        quality_text = (f"sag={rec['sag_m']:.3e} m" if "sag_m" in rec else
                                        f"stretch mean={rec['stretch_mean']:.4f} max={rec['stretch_max']:.3f}")
                        print(f"{scene:12s} {str(rec['edge_solver']):8s} envs={n:6d} substeps={rec['substeps']:4d} "
                              f"iters={it} block={block} chains={chain}/{rows}/{lane_rows} "
                              f"tets={rec['tet_solver']}/{rec['tet_method']} "
                              f"tether_passes={rec['tether_passes']} "
                              f"{rec['env_steps_per_s']:12.1f} env-steps/s  {quality_text}  "
                              f"unstable={rec['unstable_envs']}", flush=True)
                        if args.out:
                            with open(args.out, "a") as f:
                                f.write(json.dumps(rec) + "\n")


if __name__ == "__main__":
    main()
