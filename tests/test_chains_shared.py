"""The shared-memory chain solve (kernels/chains_shared.py, ``World.chain_solver = "shared"``: a thread block per env
walks every family of a chain set with the set's nodes in shared memory) against the serial walk (kernels/chains.py):
the scenes of tests/test_chains_partitioned.py and PrecisionCutting's cloth stepped both ways.

The same operations in the same order: on the CPU, where a block has one lane that walks every chain in order, the
positions are bit-identical (asserted exactly); on a GPU the two kernels may contract multiply-adds differently, so
there the partitioned solve's tolerance applies (max |dx| <= 1e-5 x the object's length).
"""

from __future__ import annotations

import numpy as np
import pytest
import warp as wp
from test_chains_partitioned import TOL, _cloth_world, _rod_world, _worst
from test_chains_registers import _open_rod_world

from lapwarp.chains import shared_chain_layout


def _step_both(make, simulate=(0.04, 0.02), lanes: int = 64):
    out = []
    for solver in ("thomas", "shared"):
        world, objects = make()
        world.chain_solver = solver
        world.chain_shared_lanes = lanes
        start = world.positions()
        world.simulate(*simulate)
        assert world.unstable.numpy().sum() == 0
        out.append(world.positions())
    return start, out, objects


def _assert_same(device, a: np.ndarray, b: np.ndarray, objects) -> None:
    if wp.get_device(device).is_cpu:
        np.testing.assert_array_equal(a, b)
    else:
        assert _worst(a, b, objects) <= TOL


def _launched(world) -> set:
    """Names of the kernels the world's recorded step launches."""
    names = set()
    for cmd in world._cmds:
        kernel = getattr(cmd, "kernel", None) or getattr(getattr(cmd, "__self__", None), "kernel", None)
        if kernel is not None:
            names.add(kernel.key)
    return names


@pytest.mark.parametrize("newton_steps, iterations, cuttable", [(1, 1, False), (2, 1, True), (1, 2, True)])
@pytest.mark.parametrize("cpu_blocks", [False, True])
def test_shared_cloth_edge_chains_match_serial(device, newton_steps, iterations, cuttable, cpu_blocks, monkeypatch):
    # a 6 x 5 cloth: rows, columns and diagonals of several lengths in 3 families, one launch for all of them; 1 or 2
    # Newton steps (the multipliers of the earlier one in global scratch), 1 or 2 sweeps (multipliers kept:
    # use_lambda, with the sweeps set directly); env 1 with every fourth edge removed. 3 lanes: the diagonals take
    # two rounds, lanes past a family's last chain or a short chain's end write nothing. On the CPU one lane walks
    # every chain, or (cpu_blocks) the 3 lanes run as Warp's cooperative fibers with real barriers: the GPU's
    # rounds, bit-identical all the same (each chain's arithmetic is the serial walk's)
    monkeypatch.setattr(wp.config, "enable_cpu_blocks", cpu_blocks)

    def make():
        world, objects = _cloth_world(device, 0, newton_steps, cuttable)
        world.iterations = iterations
        return world, objects

    start, out, objects = _step_both(make, lanes=3)
    assert _worst(start, out[1], objects) > 100 * TOL  # the solve had work to do
    _assert_same(device, out[0], out[1], objects)


@pytest.mark.parametrize("newton_steps, iterations, rigid", [(1, 1, False), (3, 2, True)])
def test_shared_rods_match_serial(device, newton_steps, iterations, rigid):
    # open rods of 1-17 links, pinned at ends, inside and at two adjacent nodes (an empty row when rigid), cut: one
    # family of chains of different lengths (the lanes past a short chain's end walk on, writing nothing)
    start, out, rods = _step_both(lambda: _open_rod_world(device, newton_steps, iterations, rigid, True))
    assert _worst(start, out[1], rods) > 100 * TOL
    _assert_same(device, out[0], out[1], rods)


def test_loops_keep_the_serial_walk(device):
    # a chain set with a closed chain has no shared layout: the serial walk solves it (the same positions) and the
    # shared kernel is not launched
    world, _ = _rod_world(device, 0, 2, 1, False, True)
    assert world.model.rod_chains.closed_host.any()
    assert shared_chain_layout(world.model.rod_chains, device) is None
    _, out, rods = _step_both(lambda: _rod_world(device, 0, 2, 1, False, True))
    _assert_same(device, out[0], out[1], rods)
    world.chain_solver = "shared"
    world.simulate(0.02, 0.02)
    assert not any(name.startswith("solve_chains_shared") for name in _launched(world))


def test_layout_numbers_the_set_nodes():
    # every node slot of the set holds its particle's padded shared slot, and the particles are the set's nodes
    world, _ = _cloth_world("cpu", 0, 1, False)
    cs = world.model.edge_chains
    layout = shared_chain_layout(cs, "cpu")
    particles = layout.particles.numpy()
    slot = layout.slot.numpy()
    for first, count, _, node_base in cs.families:
        for i in range(count):
            idx = node_base + i + count * np.arange(int(cs.lengths[first + i]) + 1)
            t = np.searchsorted(particles, cs.node_host[idx])
            np.testing.assert_array_equal(particles[t], cs.node_host[idx])
            np.testing.assert_array_equal(slot[idx], t + (t >> 3))
    last = len(particles) - 1
    assert layout.node_slots == last + (last >> 3) + 1
    assert layout.longest == int(cs.lengths.max())


def test_invalid_lanes_raise(device):
    world, _ = _cloth_world(device, 0, 1, False)
    world.chain_solver = "shared"
    for bad in (0, 1025, 2.0, True):
        world.chain_shared_lanes = bad
        with pytest.raises(ValueError, match="chain_shared_lanes"):
            world.simulate(0.02, 0.02)


def test_env_config_selects_the_shared_solve(device):
    # PrecisionCutting's 40 x 40 cloth with its expert cutting: on the CPU bit for bit after four env steps (the cut
    # masks too); on a GPU within 10 um after one
    import lapwarp
    from lapwarp.experts import make_expert

    cpu = wp.get_device(device).is_cpu
    out = []
    for solver in ("thomas", "shared"):
        env = lapwarp.make("PrecisionCutting", num_envs=2, device=device, chain_solver=solver)
        assert env.world.chain_solver == solver
        env.reset(seed=5)
        expert = make_expert(env)
        for _ in range(4 if cpu else 1):
            env.step(expert())
        out.append((env.world.positions(), env.world.state.edge_active.numpy().copy()))
        if solver == "shared":
            assert any(name.startswith("solve_chains_shared") for name in _launched(env.world))
    if cpu:
        np.testing.assert_array_equal(out[0][0], out[1][0])
        np.testing.assert_array_equal(out[0][1], out[1][1])
    else:
        # the two kernels may contract multiply-adds differently: within 10 um after one env step (RopeCutting's
        # bound for the register solve, tests/test_chains_registers.py)
        assert np.abs(out[0][0] - out[1][0]).max() <= 1.0e-5
