"""The register-resident chain solve (kernels/chains_registers.py, ``World.chain_solver = "registers"``: the serial
walk's thread per chain with its loops unrolled to the chain length and the chain in registers) against the serial
walk (kernels/chains.py): the scenes of tests/test_chains_partitioned.py stepped both ways.

The same operations in the same order: on the CPU the positions are bit-identical (asserted exactly); on a GPU the
two kernels may contract multiply-adds differently, so there the partitioned solve's tolerance applies (max |dx| <=
1e-5 x the chain's length).
"""

from __future__ import annotations

import numpy as np
import pytest
import warp as wp
from test_chains_partitioned import OPEN, SEG, TOL, _cloth_world, _cut_rods, _perturb, _rod_world, _worst

from lapwarp.builder import SceneBuilder

# open rods all of 9 links (pinned at an end, both ends, inside, two adjacent nodes, nowhere): a family of equal
# chains, which takes the register kernel's ``exact`` variant
EQUAL = [(9, [0]), (9, [0, 9]), (9, [4]), (9, [4, 5]), (9, [])]


def _open_rod_world(device, newton_steps: int, iterations: int, rigid: bool, cuttable: bool, specs=OPEN):
    """tests/test_chains_partitioned.py's open rods alone (``specs``; by default 1..17 links, pinned at ends, inside,
    two adjacent nodes), 3 envs, perturbed (and cut)."""
    b = SceneBuilder()
    rods = []
    for row, (m, pinned) in enumerate(specs):
        th = np.pi * row / len(specs)
        pts = np.linspace(0.0, SEG * m, m + 1)[:, None] * np.array([np.cos(th), np.sin(th), 0.0])
        rods.append((b.add_rod(pts, radius=1e-3, youngs_modulus=1e6, damping=1.0, fixed=pinned, cuttable=cuttable),
                     SEG * m))
    world = b.finalize(3, device, substeps=5, iterations=iterations)
    world.rod_newton_steps = newton_steps
    if rigid:
        world.model.rod_stretch_compliance.zero_()
    _perturb(world, 0.1 * SEG)
    if cuttable:
        _cut_rods(world, rods)
    return world, rods


def _step_both(make, simulate=(0.04, 0.02)):
    out = []
    for solver in ("thomas", "registers"):
        world, objects = make()
        world.chain_solver = solver
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


@pytest.mark.parametrize("newton_steps, iterations, rigid", [(1, 1, False), (2, 1, True), (3, 2, False)])
@pytest.mark.parametrize("cuttable", [False, True])
def test_register_rods_match_serial(device, newton_steps, iterations, rigid, cuttable):
    # open rods of 1-17 links in one family (a kernel unrolled to 17 links, shorter chains predicated), 1-3 Newton
    # steps (the multipliers of the earlier ones carried in registers), 1 or 2 sweeps (multipliers kept: use_lambda),
    # compliant or rigid (pinned neighbours: empty rows), intact or cut
    start, out, rods = _step_both(lambda: _open_rod_world(device, newton_steps, iterations, rigid, cuttable))
    assert _worst(start, out[1], rods) > 100 * TOL  # the solves had work to do
    _assert_same(device, out[0], out[1], rods)


# (rigid and intact, these rods trip the stability check, the walk's run as well: envs 0 and 2 at 2 Newton steps and
# one sweep on the CPU, env 2 at 3 and two on an H200, forty-fourth session; so the rigid case runs cut)
@pytest.mark.parametrize("newton_steps, iterations, rigid, cuttable",
                         [(2, 1, False, True), (3, 2, True, True), (3, 2, False, False)])
def test_register_equal_rods_match_serial(device, newton_steps, iterations, rigid, cuttable):
    # a family of equal chains takes the exact-length variant (the chain length a constant, its guards folded): the
    # serial walk's positions, intact and cut, compliant and rigid
    from lapwarp.kernels import chains_registers

    world, _ = _open_rod_world(device, newton_steps, iterations, rigid, cuttable, EQUAL)
    cs = world.model.rod_chains
    first, count, _, _ = cs.families[0]
    assert cs.num_families == 1
    assert chains_registers.family_kernel(cs, first, count) is chains_registers.register_chain_kernel(9, exact=True)
    assert chains_registers.register_chain_kernel(9) is not chains_registers.register_chain_kernel(9, exact=True)
    start, out, rods = _step_both(lambda: _open_rod_world(device, newton_steps, iterations, rigid, cuttable, EQUAL))
    assert _worst(start, out[1], rods) > 100 * TOL  # the solves had work to do
    _assert_same(device, out[0], out[1], rods)


@pytest.mark.parametrize("newton_steps, cuttable", [(1, False), (2, True)])
def test_register_cloth_edge_chains_match_serial(device, newton_steps, cuttable):
    # a 6 x 5 cloth: rows, columns and diagonals of several lengths in 3 families (a kernel per family length); env 1
    # with every fourth edge removed
    _, out, objects = _step_both(lambda: _cloth_world(device, 0, newton_steps, cuttable))
    _assert_same(device, out[0], out[1], objects)


def test_loops_and_long_chains_keep_the_serial_walk(device):
    # a family with a closed chain, or a chain longer than MAX_LINKS, is not the register kernel's: the serial walk
    # solves it (the same positions), the others still take the register kernel
    from lapwarp.kernels import chains_registers

    world, rods = _rod_world(device, 0, 2, 1, False, True)  # open rods and loops, one family
    cs = world.model.rod_chains
    assert cs.num_families == 1 and cs.closed_host.any()
    first, count, _, _ = cs.families[0]
    assert chains_registers.family_kernel(cs, first, count) is None
    start, out, rods = _step_both(lambda: _rod_world(device, 0, 2, 1, False, True))
    _assert_same(device, out[0], out[1], rods)

    b = SceneBuilder()
    m = chains_registers.MAX_LINKS + 1
    b.add_rod(np.stack([np.linspace(0.0, SEG * m, m + 1), np.zeros(m + 1), np.zeros(m + 1)], axis=1), radius=1e-3,
              youngs_modulus=1e6, fixed=[0])
    long = b.finalize(1, device).model.rod_chains
    assert chains_registers.family_kernel(long, 0, 1) is None
    with pytest.raises(ValueError, match="1..64 links"):
        chains_registers.register_chain_kernel(m)


def test_env_config_selects_the_register_solve(device):
    # RopeCutting's five 19-link ropes (both ends fixed), plucked: the same positions both ways. On the CPU bit for
    # bit after three env steps (120 substeps of 4 Newton steps) with the hook moving and cutting, every node moved by
    # ~2 mm. On a GPU the two kernels contract multiply-adds differently, and a 2 mm pluck of 2.6 mm links folds some
    # of them, a bifurcation that rounding decides: on the CPU 1e-8 m of noise on the plucked start moves the result
    # of one env step by 3.9 cm (GPU: thomas and registers 3.3 cm apart, each deterministic, thirty-fifth session's
    # lease). So there one env step with the hook still and a 0.2 mm pluck (1e-8 m of noise: 3e-8 m after the
    # step; the ropes move 0.65 mm), within 10 um
    import lapwarp

    cpu = wp.get_device(device).is_cpu
    steps, lift, pluck = (3, 0.3, 2e-3) if cpu else (1, 0.0, 2e-4)
    out, cut = [], []
    for solver in ("thomas", "registers"):
        # every Newton step both ways (the register solve's default tolerance off): the kernels' arithmetic compared
        env = lapwarp.make("RopeCutting", num_envs=2, device=device, chain_solver=solver, rope_newton_tolerance=0.0)
        assert env.world.chain_solver == solver
        env.world.chain_register_split = False  # the one-thread kernel (its split form: tests/test_chains_split.py)
        env.reset(seed=3)
        actions = np.tile(np.array([[0.0, 0.0, 1.0, lift, 0.0]], dtype=np.float32), (2, 1))[:, :env.action_dim]
        if not cpu:
            actions[:] = 0.0
        _perturb(env.world, pluck, seed=5)
        start = env.world.positions()
        for _ in range(steps):
            env.step(actions)
        out.append(env.world.positions())
        cut.append(env.world.state.segment_active.numpy().copy())
        assert env.world.unstable.numpy().sum() == 0
    assert np.abs(out[0] - start).max() > 1e-4  # the ropes moved
    np.testing.assert_array_equal(cut[0], cut[1])
    if cpu:
        np.testing.assert_array_equal(out[0], out[1])
    else:
        np.testing.assert_allclose(out[0], out[1], atol=1e-5)


def _rods_stepped(device, newton_steps: int, tolerance: float, simulate=(0.04, 0.02)):
    """The open rods (perturbed, compliant, intact) on the register solve after ``simulate``."""
    world, rods = _open_rod_world(device, newton_steps, 1, False, False)
    world.chain_solver = "registers"
    world.rod_newton_tolerance = tolerance
    start = world.positions()
    world.simulate(*simulate)
    assert world.unstable.numpy().sum() == 0
    return start, world.positions(), rods


def test_newton_tolerance_stops_the_steps(device):
    # A tolerance above any correction stops every chain after its first Newton step: the positions of one step,
    # bit for bit on the CPU (the same code runs, then the loop breaks). 1e-30 m stops only a chain whose step
    # corrected nothing at all, which the next would not either: the positions of every step (the exit is the only
    # difference).
    _, one, rods = _rods_stepped(device, 1, 0.0)
    _, four, _ = _rods_stepped(device, 4, 0.0)
    _, stopped, _ = _rods_stepped(device, 4, 1.0)
    _, tiny, _ = _rods_stepped(device, 4, 1e-30)
    assert _worst(one, four, rods) > 100 * TOL  # the later Newton steps move the rods
    _assert_same(device, one, stopped, rods)
    _assert_same(device, four, tiny, rods)


def test_newton_tolerance_keeps_the_converged_result(device):
    # At 1e-7 m the rods end within that tolerance of running every step, up to float32 round-off at these positions
    # (measured 7e-9 m on the CPU, 1.12e-7 m on an H200, whose kernels contract multiply-adds differently: two ulps
    # of the largest coordinate allowed on top): each Newton step corrects far less than the one before. The
    # perturbed rods move by up to 0.63 of their length, and the later steps matter (one step against four: 0.048 of
    # a rod's length)
    start, four, rods = _rods_stepped(device, 4, 0.0)
    _, early, _ = _rods_stepped(device, 4, 1e-7)
    assert _worst(start, four, rods) > 1e4 * TOL
    assert np.abs(four - early).max() <= 1e-7 + 2 * np.spacing(np.abs(four).max().astype(np.float32))


@pytest.mark.parametrize("value, message", [(-1e-7, "finite length >= 0"), (float("nan"), "finite length >= 0"),
                                            (float("inf"), "finite length >= 0"), (True, "finite length >= 0"),
                                            (1e-7, "register-resident, hybrid and pcr")])
def test_newton_tolerance_rejects_bad_values(device, value, message):
    # a bad length, or a tolerance the chain solver in use would not honour (the serial walk runs every step)
    world, _ = _open_rod_world(device, 2, 1, False, False)
    world.chain_solver = "registers" if message.startswith("finite") else "thomas"
    world.rod_newton_tolerance = value
    with pytest.raises(ValueError, match=message):
        world.simulate(0.02, 0.02)
    with pytest.raises(ValueError, match="finite length"):
        from lapwarp.kernels import chains_registers
        chains_registers.register_chain_kernel(4, -1.0)


def test_newton_tolerance_refused_where_a_family_walks(device):
    # rods with a loop in their family run the serial walk, which takes no tolerance; neither does the partitioned
    # solve (chain_block_links > 1, which takes precedence over the register solve)
    world, _ = _rod_world(device, 0, 2, 1, False, True)
    world.chain_solver = "registers"
    world.rod_newton_tolerance = 1e-7
    with pytest.raises(ValueError, match="serial walk"):
        world.simulate(0.02, 0.02)
    world, _ = _open_rod_world(device, 2, 1, False, False)
    world.chain_solver = "registers"
    world.chain_block_links = 4
    world.rod_newton_tolerance = 1e-7
    with pytest.raises(ValueError, match="partitioned solve"):
        world.simulate(0.02, 0.02)
