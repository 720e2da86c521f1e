"""The partitioned chain solve (kernels/chains_partitioned.py, ``World.chain_block_links > 1``) against the serial
one (kernels/chains.py, ``chain_block_links = 0``): the same scenes stepped both ways must end at the same positions,
and (tests/test_physics_rods.py) a hanging rod solved the partitioned way keeps its length.

Both solve the same linear systems exactly; only the elimination order differs, so the positions differ by float32
round-off, which the nonlinear steps amplify a little. Tolerance: max |dx| <= 1e-5 x the chain's length (its rest
length summed) over a few short steps; measured <= 1e-6 x (as much as 1e-9 m of noise in the start positions
makes, so this is round-off, not a difference in the maths).
"""

from __future__ import annotations

import numpy as np
import pytest

from lapwarp.assets import cloth_grid, rod_circle
from lapwarp.builder import SceneBuilder

SEG = 0.01  # segment length of the test rods (m)
TOL = 1.0e-5  # max position difference over the chain's length

# open rods: (links, pinned nodes). Lengths below, at and above multiples of the block lengths tested (2, 3, 4, 8),
# 1 and 2 links; pinned first, last, interior, two adjacent nodes (an empty row when rigid), at block separators
OPEN = [(1, [0]), (2, []), (3, [3]), (4, [2]), (5, [2, 3]), (8, [0]), (9, [9]), (13, [4, 5]), (17, [7, 8])]
# loops: (links, pinned nodes); node 0 pinned: no corner coupling (plain tridiagonal); pinned at the corner's two nodes
LOOPS = [(3, []), (4, [0]), (5, []), (9, [4]), (12, [0, 1]), (30, [])]


def _add_rods(b: SceneBuilder, cuttable: bool) -> list:
    """The OPEN rods and the LOOPS, all about the origin (they do not interact; positions stay small, so a float32
    ulp stays small against the shortest chain); returns (object, rest length) pairs."""
    rods = []
    for row, (m, pinned) in enumerate(OPEN):
        th = np.pi * row / len(OPEN)
        pts = np.linspace(0.0, SEG * m, m + 1)[:, None] * np.array([np.cos(th), np.sin(th), 0.0])
        rods.append((b.add_rod(pts, radius=1e-3, youngs_modulus=1e6, damping=1.0, fixed=pinned, cuttable=cuttable),
                     SEG * m))
    for row, (m, pinned) in enumerate(LOOPS):
        radius = SEG * m / (2.0 * np.pi)
        th = np.pi * row / len(LOOPS)
        pts = rod_circle(radius, m, normal=(np.cos(th), 0.0, np.sin(th)))
        rods.append((b.add_rod(pts, radius=1e-3, youngs_modulus=1e5, closed=True, damping=1.0, fixed=pinned,
                               cuttable=cuttable), 2.0 * np.pi * radius))
    return rods


def _perturb(world, scale: float, seed: int = 0) -> None:
    """Every env its own positions: the rest shape plus noise (constraints violated from the start)."""
    q = world.state.particle_q.numpy()
    q += np.random.default_rng(seed).normal(scale=scale, size=q.shape).astype(np.float32)
    world.state.particle_q.assign(q)


def _cut_rods(world, rods) -> None:
    """Per-env cuts. Loops: env 0 at the last link, env 1 at the first (either corner: an open chain), env 2 at inner
    links 1, 4, 7, .. (still cyclic, split inside). Open rods: env 0 the last link, env 1 the middle one, env 2 every
    third from the end."""
    mask = world.state.segment_active.numpy()
    for obj, _ in rods:
        s0, m = obj.segment_start, obj.segment_count
        mask[0, s0 + m - 1] = 0
        mask[1, s0 + (0 if obj.closed else m // 2)] = 0
        mask[2, s0 + (np.arange(1, m - 1, 3) if obj.closed else np.arange(m - 1, -1, -3))] = 0
    world.state.segment_active.assign(mask)


def _rod_world(device, block_links: int, newton_steps: int, iterations: int, rigid: bool, cuttable: bool):
    """The rods in 3 envs at 5 substeps per step, perturbed (and cut), solved with ``block_links``."""
    b = SceneBuilder()
    rods = _add_rods(b, cuttable)
    world = b.finalize(3, device, substeps=5, iterations=iterations)
    world.rod_newton_steps = newton_steps
    world.chain_block_links = block_links
    if rigid:
        world.model.rod_stretch_compliance.zero_()
    _perturb(world, 0.1 * SEG)
    if cuttable:
        _cut_rods(world, rods)
    return world, rods


def _worst(a: np.ndarray, b: np.ndarray, objects) -> float:
    """Largest position difference of any object over its length, all envs."""
    return max(float(np.abs(a[:, obj.particles] - b[:, obj.particles]).max()) / length for obj, length in objects)


@pytest.mark.parametrize(
    "block_links, newton_steps, iterations, rigid",
    [(4, 1, 1, False), (3, 2, 1, True), (2, 2, 2, False), (8, 1, 2, True)],
)
@pytest.mark.parametrize("cuttable", [False, True])
def test_partitioned_rods_match_serial(device, block_links, newton_steps, iterations, rigid, cuttable):
    # open rods and loops of many lengths and pins, 3 envs of different positions (and cuts), all rods of a scene in
    # one family; compliance > 0 or rigid, 1 or 2 Newton steps, 1 sweep or 2 (multipliers carried: use_lambda)
    out = []
    for links in (0, block_links):
        world, rods = _rod_world(device, links, newton_steps, iterations, rigid, cuttable)
        start = world.positions()
        world.simulate(0.04, 0.02)
        assert world.unstable.numpy().sum() == 0
        out.append(world.positions())
    assert _worst(start, out[1], rods) > 100 * TOL  # the solves had work to do
    assert _worst(out[0], out[1], rods) <= TOL


def _cloth_world(device, block_links: int, newton_steps: int, cuttable: bool):
    """A 6 x 5 cloth pinned at two top corners, 2 envs, perturbed (env 1: every fourth edge removed)."""
    v, t = cloth_grid(6, 5, 0.05, 0.04, plane="xz", origin=(0.0, 0.0, -0.04))
    b = SceneBuilder()
    obj = b.add_cloth(v, t, areal_density=0.2, stretch_stiffness=1e3, bend_stiffness=1e-6, damping=1.0,
                      fixed=np.nonzero(v[:, 2] > -1e-9)[0][:2], cuttable=cuttable)
    world = b.finalize(2, device, substeps=5)
    world.chain_newton_steps = newton_steps
    world.chain_block_links = block_links
    _perturb(world, 2e-3, seed=1)
    if cuttable:
        mask = world.state.edge_active.numpy()
        mask[1, ::4] = 0
        world.state.edge_active.assign(mask)
    return world, [(obj, 0.05)]


@pytest.mark.parametrize("block_links, newton_steps, cuttable", [(2, 1, False), (3, 2, True)])
def test_partitioned_cloth_edge_chains_match_serial(device, block_links, newton_steps, cuttable):
    # a 6 x 5 cloth: rows, columns and diagonals in 3 families of several chains each; env 1 with every fourth edge
    # removed. Length scale: the sheet's width.
    out = []
    for links in (0, block_links):
        world, objects = _cloth_world(device, links, newton_steps, cuttable)
        assert world.model.edge_chains.num_families == 3
        world.simulate(0.04, 0.02)
        out.append(world.positions())
    assert _worst(out[0], out[1], objects) <= TOL


def test_block_length_switches_between_steps(device):
    # chain_block_links is part of the recorded step's key: setting it between steps re-records (and allocates the
    # partitioned scratch), setting it back returns to the serial kernel
    world, rods = _rod_world(device, 0, 2, 1, False, False)
    ref, _ = _rod_world(device, 0, 2, 1, False, False)
    serial_bytes = world.state_bytes_per_env()
    world.step(0.02)
    world.chain_block_links = 4
    world.step(0.02)
    assert world.state_bytes_per_env() > serial_bytes
    world.chain_block_links = 0
    world.step(0.02)
    ref.simulate(0.06, 0.02)
    assert _worst(world.positions(), ref.positions(), rods) <= TOL


def test_block_layout_interleaves_families():
    # per family: first block slot and blocks of its longest chain; slots of one family's chains interleaved
    from lapwarp.kernels.chains_partitioned import block_layout

    families = [(0, 2, 0, 0), (2, 3, 18, 20)]  # (first chain, chains, link base, node base)
    lengths = np.array([9, 4, 5, 5, 1])
    assert block_layout(families, lengths, 4) == ([(0, 3), (6, 2)], 12)


def test_chain_block_links_setting_resolves_per_device():
    """``chain_block_links=-1`` (default) is the task's GPU setting on CUDA and 0 on the CPU; explicit values are
    used as given; anything below -1 is a config error naming the field."""
    from types import SimpleNamespace

    import lapwarp
    from lapwarp.env import BatchedEnv
    from lapwarp.tasks.thread_manipulation.rope_threading import RopeThreadingEnv

    env = lapwarp.make("Reach", num_envs=1, device="cpu")
    assert env.cfg.chain_block_links == -1 and env.world.chain_block_links == 0
    assert lapwarp.make("Reach", num_envs=1, device="cpu", chain_block_links=8).world.chain_block_links == 8
    with pytest.raises(ValueError, match="chain_block_links"):
        lapwarp.make("Reach", num_envs=1, device="cpu", chain_block_links=-2)
    fake = SimpleNamespace(cfg=SimpleNamespace(chain_block_links=-1), wp_device=SimpleNamespace(is_cuda=True),
                           gpu_chain_block_links=RopeThreadingEnv.gpu_chain_block_links)
    assert BatchedEnv.chain_block_links.fget(fake) == RopeThreadingEnv.gpu_chain_block_links == 8
    fake.wp_device.is_cuda = False
    assert BatchedEnv.chain_block_links.fget(fake) == 0


@pytest.mark.parametrize("block_links", [0, 4])
def test_loop_cut_at_its_first_link_closes_its_last(device, block_links):
    """A rigid loop of 12 links cut at link 0 is an open chain ending at node 0 through link m - 1. One direct solve
    (2 Newton steps) from positions 10 % of a link off must bring every remaining link to its length to second
    order (residual <= 1e-3 of the link; measured 2.5e-5). Node 0 used to get no correction from link m - 1
    although the solve counted its mass: that link kept 7.2 % (both kernels, measured)."""
    b = SceneBuilder(gravity=(0.0, 0.0, 0.0))
    m = 12
    obj = b.add_rod(rod_circle(SEG * m / (2.0 * np.pi), m, normal=(0.0, 0.0, 1.0)), radius=1e-3, youngs_modulus=1e5,
                    closed=True, damping=0.0, cuttable=True)
    world = b.finalize(1, device, substeps=1)
    world.model.rod_stretch_compliance.zero_()
    world.rod_newton_steps = 2
    world.chain_block_links = block_links
    rest = np.linalg.norm(np.roll(world.positions(obj)[0], -1, axis=0) - world.positions(obj)[0], axis=1)
    _perturb(world, 0.1 * SEG, seed=3)
    mask = world.state.segment_active.numpy()
    mask[0, obj.segment_start] = 0
    world.state.segment_active.assign(mask)
    world.step(1e-3)
    x = world.positions(obj)[0]
    length = np.linalg.norm(np.roll(x, -1, axis=0) - x, axis=1)
    assert np.abs(length[1:] / rest[1:] - 1.0).max() <= 1e-3
