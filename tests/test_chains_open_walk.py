"""The serial chain walk in three walks per Newton step for families without a loop (``chains.solve_open_chains``,
``World.chain_solver = "open_walk"``) against the four-walk serial kernel (``chains.solve_chains``): the scenes of
tests/test_chains_partitioned.py stepped both ways must end at the same positions.

Both solve the same linear systems exactly; the three-walk kernel eliminates each chain's transverse filter from its
far end instead of its first node, so the positions differ by float32 round-off. Tolerance: max |dx| <= 1e-5 x the
object's length, as for the other chain solves.
"""

from __future__ import annotations

import numpy as np
import pytest
from test_chains_partitioned import TOL, _cloth_world, _rod_world, _worst
from test_chains_registers import _open_rod_world


def _launched(monkeypatch) -> list:
    """The names of the chain kernels the worlds' steps record."""
    import lapwarp.world as world_module

    names = []
    original = world_module.wp.launch

    def launch(kernel, *args, **kwargs):
        names.append(kernel.key)
        return original(kernel, *args, **kwargs)

    monkeypatch.setattr(world_module.wp, "launch", launch)
    return names


@pytest.mark.parametrize("newton_steps, iterations, cuttable", [(1, 1, False), (2, 1, True), (2, 2, True)])
def test_open_walk_cloth_edge_chains_match_serial(device, newton_steps, iterations, cuttable, monkeypatch):
    # a 6 x 5 cloth pinned at two corners: rows, columns and diagonals in 3 families; env 1 with every fourth edge
    # removed; 1 or 2 Newton steps, 1 sweep or 2 (the multipliers carried)
    names = _launched(monkeypatch)
    out = []
    for solver in ("thomas", "open_walk"):
        world, objects = _cloth_world(device, 0, newton_steps, cuttable)
        world.set_iterations(iterations)
        world.chain_solver = solver
        start = world.positions()
        world.simulate(0.04, 0.02)
        assert world.unstable.numpy().sum() == 0
        out.append(world.positions())
    assert _worst(start, out[1], objects) > 100 * TOL  # the solves had work to do
    assert _worst(out[0], out[1], objects) <= TOL
    assert any(name.startswith("solve_open_chains") for name in names)


@pytest.mark.parametrize("newton_steps, iterations, rigid", [(1, 1, False), (2, 1, True), (2, 2, False)])
@pytest.mark.parametrize("cuttable", [False, True])
def test_open_walk_rods_match_serial(device, newton_steps, iterations, rigid, cuttable, monkeypatch):
    # open rods of 1-17 links pinned at either end, inside, at two adjacent nodes (an empty row when rigid); 3 envs of
    # different positions and cuts
    names = _launched(monkeypatch)
    out = []
    for solver in ("thomas", "open_walk"):
        world, rods = _open_rod_world(device, newton_steps, iterations, rigid, cuttable)
        world.chain_solver = solver
        world.simulate(0.04, 0.02)
        assert world.unstable.numpy().sum() == 0
        out.append(world.positions())
    assert _worst(out[0], out[1], rods) <= TOL
    assert any(name.startswith("solve_open_chains") for name in names)


def test_open_walk_keeps_loops_on_the_serial_kernel(monkeypatch):
    # the rods' scene holds loops in its one family (rods share no node: a single family): every launch is the
    # four-walk kernel, and the positions are the serial kernel's bit for bit
    names = _launched(monkeypatch)
    out = []
    for solver in ("thomas", "open_walk"):
        world, rods = _rod_world("cpu", 0, 2, 1, False, True)
        assert world.model.rod_chains.closed_host.any()
        world.chain_solver = solver
        world.simulate(0.04, 0.02)
        out.append(world.positions())
    assert not any(name.startswith("solve_open_chains") for name in names)
    assert np.array_equal(out[0], out[1])


def test_env_config_selects_the_open_walk():
    import lapwarp

    env = lapwarp.make("PrecisionCutting", num_envs=1, device="cpu", chain_solver="open_walk")
    assert env.world.chain_solver == "open_walk"
    env.step(np.zeros((1, env.action_dim), dtype=np.float32))
    assert env.world.unstable.numpy().sum() == 0
