"""The PCR chain solve (kernels/chains_pcr.py, ``World.chain_solver = "pcr"``) against the serial one
(kernels/chains.py): the same scenes stepped both ways must end at the same positions.

Both solve the same linear systems exactly (Thomas in one thread, parallel cyclic reduction in a block of threads);
only the elimination order differs, so the positions differ by float32 round-off, which the nonlinear steps amplify
a little. Tolerance as for the partitioned solve (tests/test_chains_partitioned.py): max |dx| <= 1e-5 x the chain's
length over a few short steps. On the CPU the block's lanes run as Warp's cooperative fibers.
"""

from __future__ import annotations

import numpy as np
import pytest

from lapwarp.assets import cloth_grid
from lapwarp.builder import SceneBuilder
from lapwarp.kernels import chains_pcr

SEG = 0.01  # segment length of the test rods (m)
TOL = 1.0e-5  # max position difference over the chain's length

# open rods: (links, pinned nodes): 1 and 2 links, 31 links (a full 32-lane block), 40 (a 64-lane block); pinned
# first, last, interior, two adjacent nodes (an empty row when rigid)
OPEN = [(1, [0]), (2, []), (3, [3]), (5, [2, 3]), (9, [9]), (13, [4, 5]), (19, [0, 19]), (31, [0]), (40, [])]


def _rod_world(device, solver: str, newton_steps: int, iterations: int, rigid: bool, cuttable: bool):
    """The OPEN rods (one family: they share no node) in 3 envs at 5 substeps per step, perturbed (and cut)."""
    b = SceneBuilder()
    rods = []
    for row, (m, pinned) in enumerate(OPEN):
        th = np.pi * row / len(OPEN)
        pts = np.linspace(0.0, SEG * m, m + 1)[:, None] * np.array([np.cos(th), np.sin(th), 0.0])
        rods.append((b.add_rod(pts, radius=1e-3, youngs_modulus=1e6, damping=1.0, fixed=pinned, cuttable=cuttable),
                     SEG * m))
    world = b.finalize(3, device, substeps=5, iterations=iterations)
    world.rod_newton_steps = newton_steps
    world.chain_solver = solver
    if rigid:
        world.model.rod_stretch_compliance.zero_()
    q = world.state.particle_q.numpy()
    q += np.random.default_rng(0).normal(scale=0.1 * SEG, size=q.shape).astype(np.float32)
    world.state.particle_q.assign(q)
    if cuttable:
        # env 0: the last link of every rod, env 1 the middle one, env 2 every third from the end
        mask = world.state.segment_active.numpy()
        for obj, _ in rods:
            s0, m = obj.segment_start, obj.segment_count
            mask[0, s0 + m - 1] = 0
            mask[1, s0 + m // 2] = 0
            mask[2, s0 + np.arange(m - 1, -1, -3)] = 0
        world.state.segment_active.assign(mask)
    return world, rods


def _worst(a: np.ndarray, b: np.ndarray, objects) -> float:
    return max(float(np.abs(a[:, obj.particles] - b[:, obj.particles]).max()) / length for obj, length in objects)


def test_pcr_block_sizes():
    assert [chains_pcr.pcr_lanes_for(m) for m in (1, 31, 32, 63, 64, 127, 128)] == [32, 32, 64, 64, 128, 128, 0]


@pytest.mark.parametrize("newton_steps, iterations, rigid", [(1, 1, False), (2, 1, True), (6, 2, False)])
@pytest.mark.parametrize("cuttable", [False, True])
def test_pcr_rods_match_serial(device, newton_steps, iterations, rigid, cuttable):
    # open rods of many lengths and pins, 3 envs of different positions (and cuts); compliance > 0 or rigid, 1 to 6
    # Newton steps, 1 sweep or 2 (multipliers carried: use_lambda)
    out = []
    for solver in ("serial", "pcr"):
        world, rods = _rod_world(device, solver, newton_steps, iterations, rigid, cuttable)
        assert world._pcr_lanes(world.model.rod_chains) == [64]  # one family; its longest rod needs 64 lanes
        start = world.positions()
        world.simulate(0.04, 0.02)
        assert world.unstable.numpy().sum() == 0
        out.append(world.positions())
    assert _worst(start, out[1], rods) > 100 * TOL  # the solves had work to do
    assert _worst(out[0], out[1], rods) <= TOL


@pytest.mark.parametrize("newton_steps, cuttable", [(1, False), (2, True)])
def test_pcr_cloth_edge_chains_match_serial(device, newton_steps, cuttable):
    # a 6 x 5 cloth pinned at two top corners: rows, columns and diagonals in 3 families of several chains each;
    # env 1 with every fourth edge removed. Length scale: the sheet's width.
    out = []
    for solver in ("serial", "pcr"):
        v, t = cloth_grid(6, 5, 0.05, 0.04, plane="xz", origin=(0.0, 0.0, -0.04))
        b = SceneBuilder()
        obj = b.add_cloth(v, t, areal_density=0.2, stretch_stiffness=1e3, bend_stiffness=1e-6, damping=1.0,
                          fixed=np.nonzero(v[:, 2] > -1e-9)[0][:2], cuttable=cuttable)
        world = b.finalize(2, device, substeps=5)
        world.chain_newton_steps = newton_steps
        world.chain_solver = solver
        q = world.state.particle_q.numpy()
        q += np.random.default_rng(1).normal(scale=2e-3, size=q.shape).astype(np.float32)
        world.state.particle_q.assign(q)
        if cuttable:
            mask = world.state.edge_active.numpy()
            mask[1, ::4] = 0
            world.state.edge_active.assign(mask)
        assert world._pcr_lanes(world.model.edge_chains) == [32, 32, 32]
        world.simulate(0.04, 0.02)
        out.append(world.positions())
    assert _worst(out[0], out[1], [(obj, 0.05)]) <= TOL


def test_unknown_chain_solver_is_rejected(device):
    world, _ = _rod_world(device, "thomas", 1, 1, False, False)
    with pytest.raises(ValueError, match="chain_solver"):
        world.step(0.02)


def test_pcr_pretensioned_rope_matches_serial(device):
    """RopeCutting's regime, where the transverse filter does real work: a 31-link rope stretched to 5x its rest length
    between pinned ends (``stretch_rest_scale=0.2``), bowed sideways by 2 mm (env 0) and 1 mm the other way (env 1),
    6 Newton steps per sweep at 40 substeps per 0.1 s; the filter's coupling then reaches across the whole rope (a PCR
    that skipped its last step, the couplings 16 nodes apart, misses the tolerance; float32 PCR missed it by 10^4:
    hence float64 inside the PCR). Measured 7e-9 m apart after 0.2 s. (A 3-bump bow is not a test case: there the
    serial solve itself moves 13 mm apart after 0.1 s from a 1 nm change of the start positions.)"""
    out = []
    for solver in ("serial", "pcr"):
        b = SceneBuilder()
        m = 31
        pts = np.linspace(-0.05, 0.05, m + 1)[:, None] * np.array([1.0, 0.0, 0.0])
        rope = b.add_rod(pts, radius=1e-3, youngs_modulus=1e7, damping=1.0, fixed=[0, m], stretch_rest_scale=0.2)
        world = b.finalize(2, device, substeps=40)
        world.rod_newton_steps = 6
        world.chain_solver = solver
        q = world.state.particle_q.numpy()
        x = np.linspace(0.0, 1.0, m + 1)
        q[0, rope.particles, 1] += 0.002 * np.sin(np.pi * x)
        q[1, rope.particles, 2] -= 0.001 * np.sin(np.pi * x)
        world.state.particle_q.assign(q)
        start = q.copy()  # (on the CPU numpy() is a view of the state)
        world.simulate(0.2, 0.1)
        assert world.unstable.numpy().sum() == 0
        out.append(world.positions())
    assert np.abs(out[0] - start).max() > 0.9e-3  # the bows were pulled straight
    assert _worst(out[0], out[1], [(rope, 0.1)]) <= TOL
