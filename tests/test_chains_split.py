"""The split register chain solve (kernels/chains_split.py, ``World.chain_register_split``: two threads per chain, the
Thomas eliminations from both ends meeting in the middle) against the serial walk (kernels/chains.py).

Another elimination order than the walk's, so the positions agree to round-off, not bit for bit: within the
partitioned solve's tolerance (max |dx| <= 1e-5 x the chain's length, tests/test_chains_partitioned.py), after solves
that moved the rods by over 100 x that. On the CPU a pair's two threads are Warp's cooperative fibers with real
barriers (``wp.config.enable_cpu_blocks``), so the exchanges run as on the GPU.
"""

from __future__ import annotations

import numpy as np
import pytest
import warp as wp
from test_chains_partitioned import TOL, _perturb, _worst
from test_chains_registers import EQUAL, _open_rod_world

from lapwarp.kernels import chains_split


@pytest.fixture(autouse=True)
def _cpu_blocks(monkeypatch):
    monkeypatch.setattr(wp.config, "enable_cpu_blocks", True)


def _step(device, solver: str, split: bool, specs, newton_steps=3, iterations=1, rigid=False, cuttable=True,
          tolerance=0.0):
    world, rods = _open_rod_world(device, newton_steps, iterations, rigid, cuttable, specs)
    world.chain_solver = solver
    world.chain_register_split = split
    world.rod_newton_tolerance = tolerance
    start = world.positions()
    world.simulate(0.04, 0.02)
    assert world.unstable.numpy().sum() == 0
    return start, world.positions(), rods


# equal chains of odd and even lengths (the halves of 9 links are 5 and 4, of 20 both 10), 2 links (a link each), 19
# (RopeCutting's ropes); 9 chains x 3 envs = 27 pairs fill a block and part of a second
SPECS = {
    "9 links, pinned variously": EQUAL,
    "2 links": [(2, [0, 2]), (2, [0]), (2, [])],
    "19 links, both ends pinned": [(19, [0, 19])] * 5,
    "20 links, nine chains": [(20, [0, 20]), (20, [0]), (20, [10, 11])] * 3,
}


@pytest.mark.parametrize("name", list(SPECS))
@pytest.mark.parametrize("newton_steps, iterations, rigid, cuttable",
                         [(1, 1, False, False), (3, 1, False, True), (2, 2, True, True)])
def test_split_matches_serial(device, name, newton_steps, iterations, rigid, cuttable):
    # 1-3 Newton steps (the earlier steps' multipliers carried), 1 or 2 sweeps (use_lambda), compliant or rigid
    # (pinned neighbours: empty rows), intact or cut (a cut at the middle decouples the halves' 2 x 2 system)
    specs = SPECS[name]
    start, walk, rods = _step(device, "thomas", False, specs, newton_steps, iterations, rigid, cuttable)
    _, split, _ = _step(device, "registers", True, specs, newton_steps, iterations, rigid, cuttable)
    assert _worst(start, walk, rods) > 100 * TOL  # the solves had work to do
    assert _worst(walk, split, rods) <= TOL


def test_split_takes_equal_open_chains_only(device):
    # the family of EQUAL takes the split kernel (with a Newton tolerance its own variant); chains of different
    # lengths or a length outside 2..MAX_LINKS keep the one-thread register solve, bit for bit on the CPU
    world, _ = _open_rod_world(device, 2, 1, False, False, EQUAL)
    cs = world.model.rod_chains
    first, count, _, _ = cs.families[0]
    assert chains_split.family_kernel(cs, first, count) is chains_split.split_chain_kernel(9)
    assert chains_split.family_kernel(cs, first, count, 1e-7) is chains_split.split_chain_kernel(9, 1e-7)
    assert chains_split.split_chain_kernel(9, 1e-7) is not chains_split.split_chain_kernel(9)
    mixed = [(9, [0]), (8, [0]), (9, [])]
    world, _ = _open_rod_world(device, 2, 1, False, False, mixed)
    cs = world.model.rod_chains
    assert chains_split.family_kernel(cs, *cs.families[0][:2]) is None
    _, one, _ = _step(device, "registers", False, mixed)
    _, fallback, _ = _step(device, "registers", True, mixed)
    if wp.get_device(device).is_cpu:
        np.testing.assert_array_equal(one, fallback)
    for links in (1, chains_split.MAX_LINKS + 1):
        with pytest.raises(ValueError, match="split chain solve takes chains of 2"):
            chains_split.split_chain_kernel(links)
    with pytest.raises(ValueError, match="finite length"):
        chains_split.split_chain_kernel(9, -1.0)
    assert chains_split.launch_dim(3, 5) == (1, chains_split.BLOCK)  # 15 pairs, 30 lanes
    assert chains_split.launch_dim(3, 9) == (2, chains_split.BLOCK)  # 27 pairs, 54 lanes


def test_split_refuses_bad_settings(device, monkeypatch):
    world, _ = _open_rod_world(device, 2, 1, False, False, EQUAL)
    world.chain_solver = "registers"
    world.chain_register_split = 1
    with pytest.raises(ValueError, match="chain_register_split must be a bool"):
        world.simulate(0.02, 0.02)
    if wp.get_device(device).is_cpu:
        world.chain_register_split = True
        monkeypatch.setattr(wp.config, "enable_cpu_blocks", False)
        with pytest.raises(ValueError, match="chain_register_split.*enable_cpu_blocks"):
            world.simulate(0.02, 0.02)


def test_rope_cutting_on_the_split_solve(device):
    # RopeCutting's five 19-link ropes (both ends fixed), plucked by 0.2 mm, one env step with the hook still: the
    # serial walk's positions within 10 um (tests/test_chains_registers.py's GPU comparison: a larger pluck folds
    # links, a bifurcation that rounding decides)
    import lapwarp

    out = []
    for solver, split in (("thomas", False), ("registers", True)):
        env = lapwarp.make("RopeCutting", num_envs=2, device=device, chain_solver=solver, rope_newton_tolerance=0.0)
        env.world.chain_register_split = split
        env.reset(seed=3)
        _perturb(env.world, 2e-4, seed=5)
        start = env.world.positions()
        env.step(np.zeros((2, env.action_dim), dtype=np.float32))
        out.append(env.world.positions())
        assert env.world.unstable.numpy().sum() == 0
    assert np.abs(out[0] - start).max() > 1e-4  # the ropes moved
    np.testing.assert_allclose(out[0], out[1], atol=1e-5)
    cs = env.world.model.rod_chains
    assert cs.num_families == 1 and chains_split.family_kernel(cs, *cs.families[0][:2]) is not None


def test_split_newton_tolerance_stops_each_chain(device):
    # A chain stops as on the one-thread register solve (its own corrections, not its block's): at 1 m every chain
    # stops after its first Newton step (the positions of one step, bit for bit on the CPU); at 1e-30 m none stops
    # early (every step's); at 1e-3 m some chains stop after fewer steps than others, and the split solve stops each
    # where the one-thread solve does (the same positions to round-off; a block-wide stop would let converged chains
    # run on, off by up to a step's correction, which at 1e-3 m exceeds the comparison's tolerance)
    specs = SPECS["20 links, nine chains"]
    _, one, rods = _step(device, "registers", True, specs, newton_steps=1)
    _, four, _ = _step(device, "registers", True, specs, newton_steps=4)
    _, stopped, _ = _step(device, "registers", True, specs, newton_steps=4, tolerance=1.0)
    _, tiny, _ = _step(device, "registers", True, specs, newton_steps=4, tolerance=1e-30)
    if wp.get_device(device).is_cpu:
        np.testing.assert_array_equal(one, stopped)
        np.testing.assert_array_equal(four, tiny)
    else:
        assert _worst(one, stopped, rods) <= TOL and _worst(four, tiny, rods) <= TOL
    _, split_mm, _ = _step(device, "registers", True, specs, newton_steps=4, tolerance=1e-3)
    _, single_mm, _ = _step(device, "registers", False, specs, newton_steps=4, tolerance=1e-3)
    assert _worst(four, split_mm, rods) > 10 * TOL  # the tolerance stopped some chains early
    assert _worst(single_mm, split_mm, rods) <= TOL
