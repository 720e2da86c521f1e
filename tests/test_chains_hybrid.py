"""The hybrid chain solve (kernels/chains_hybrid.py, ``World.chain_solver = "hybrid"``: the block solve's packs, each
lane a few consecutive rows eliminated in registers, PCR over one interface row per lane) against the serial one
(kernels/chains.py): the scenes of tests/test_chains_partitioned.py stepped both ways must end at the same positions,
and the partition solve alone must match numpy's dense solve.

The same linear systems, another elimination order: positions differ by float32 round-off. Tolerance as for the
partitioned and block solves: max |dx| <= 1e-5 x the chain's length (measured <= 6e-7 x on the CPU). On the CPU the
lanes run as Warp's cooperative fibers (``wp.config.enable_cpu_blocks``), real threads with real barriers, so these
tests run the GPU's partition and reduced system.
"""

from __future__ import annotations

import numpy as np
import pytest
import warp as wp
from test_chains_partitioned import TOL, _cloth_world, _rod_world, _worst
from test_chains_registers import _assert_same


@pytest.fixture(autouse=True)
def cpu_blocks(monkeypatch):
    # a process-wide Warp setting, restored after each test
    monkeypatch.setattr(wp.config, "enable_cpu_blocks", True)


def _step_both(make, device, simulate=(0.04, 0.02), **settings):
    out = []
    for solver in ("thomas", "hybrid"):
        world, objects = make()
        world.chain_solver = solver
        for key, value in settings.items():
            setattr(world, key, value)
        start = world.positions()
        world.simulate(*simulate)
        assert world.unstable.numpy().sum() == 0
        out.append(world.positions())
    return start, out, objects


@pytest.mark.parametrize("rows_per_lane", [1, 3, 4, 8])
def test_partition_solve_matches_numpy(device, rows_per_lane):
    # random diagonally dominant tridiagonal systems of 1..33 rows with three right-hand sides: lanes holding a
    # partial partition (padding), one lane, many lanes, the reduced system of 1..33 rows (on the GPU a warp's
    # multiple of lanes, the extra ones idle)
    from lapwarp.kernels.chains_block import vec6
    from lapwarp.kernels.chains_hybrid import lanes_for, partition_solver

    P = rows_per_lane
    L = lanes_for(33, P)
    solve = partition_solver(P, L)
    vec_p = wp.types.vector(length=P, dtype=float)
    mat_p3 = wp.types.matrix(shape=(P, 3), dtype=float)

    @wp.kernel(module="unique")
    def solve_rows(A: wp.array3d(dtype=float), D: wp.array3d(dtype=float), sizes: wp.array(dtype=wp.int32),
                   X: wp.array3d(dtype=float)):
        system, lane = wp.tid()
        n = sizes[system]
        up = wp.tile_zeros(shape=L, dtype=vec6, storage="shared")
        red0 = wp.tile_zeros(shape=L, dtype=vec6, storage="shared")
        red1 = wp.tile_zeros(shape=L, dtype=vec6, storage="shared")
        a = vec_p()
        b = vec_p()
        c = vec_p()
        d = mat_p3()
        for i in range(P):
            k = lane * P + i
            b[i] = 1.0
            if k < n:
                a[i] = A[system, k, 0]
                b[i] = A[system, k, 1]
                c[i] = A[system, k, 2]
                d[i] = wp.vec3(D[system, k, 0], D[system, k, 1], D[system, k, 2])
        x, x_prev = solve(a, b, c, d, up, red0, red1, lane, wp.block_dim(), (n + P - 1) // P)
        for i in range(P):
            k = lane * P + i
            if k < n:
                for r in range(3):
                    X[system, k, r] = x[i, r]

    rng = np.random.default_rng(P)
    sizes = np.arange(1, 34)
    A = rng.uniform(-1.0, 1.0, (len(sizes), 33, 3))
    A[:, :, 1] = 2.0 + rng.uniform(0.0, 1.0, (len(sizes), 33))
    D = rng.normal(size=(len(sizes), 33, 3))
    lanes = 32 * ((L + 31) // 32) if wp.get_device(device).is_cuda else L
    X = wp.zeros(D.shape, dtype=float, device=device)
    wp.launch(solve_rows, dim=(len(sizes), lanes), inputs=[wp.array(A, dtype=float, device=device),
              wp.array(D, dtype=float, device=device), wp.array(sizes, dtype=wp.int32, device=device)], outputs=[X],
              block_dim=lanes, device=device)
    for s, n in enumerate(sizes):
        M = np.diag(A[s, :n, 1]) + np.diag(A[s, 1:n, 0], -1) + np.diag(A[s, :n - 1, 2], 1)
        ref = np.linalg.solve(M, D[s, :n])
        np.testing.assert_allclose(X.numpy()[s, :n], ref, atol=1e-6 * np.abs(ref).max())


@pytest.mark.parametrize("newton_steps, iterations, rigid", [(1, 1, False), (2, 1, True), (2, 2, False)])
@pytest.mark.parametrize("cuttable", [False, True])
def test_hybrid_rods_match_serial(device, newton_steps, iterations, rigid, cuttable):
    # open rods of 1-17 links and loops of 3-30 (pinned first, last, inside, two adjacent nodes; cut at either corner
    # or inside), 3 envs, 1 or 2 Newton steps, 1 or 2 sweeps (the multipliers carried); 4 rows per lane
    start, out, rods = _step_both(lambda: _rod_world(device, 0, newton_steps, iterations, rigid, cuttable), device)
    assert _worst(start, out[1], rods) > 100 * TOL  # the solves had work to do
    assert _worst(out[0], out[1], rods) <= TOL


@pytest.mark.parametrize("rows_per_lane, pack_rows", [(1, 1), (2, 12), (3, 64), (8, 0), (16, 1)])
def test_hybrid_rows_per_lane_and_packs_match_serial(device, rows_per_lane, pack_rows):
    # a row per lane (PCR alone), lanes split inside a chain, several chains per lane (8 or 16 rows: the short rods
    # in one lane), cut rods, 2 Newton steps
    _, out, rods = _step_both(lambda: _rod_world(device, 0, 2, 1, False, True), device,
                              chain_lane_rows=rows_per_lane, chain_pcr_rows=pack_rows)
    assert _worst(out[0], out[1], rods) <= TOL


@pytest.mark.parametrize("newton_steps, cuttable", [(1, False), (2, True)])
def test_hybrid_cloth_edge_chains_match_serial(device, newton_steps, cuttable):
    # a 6 x 5 cloth: rows, columns and diagonals in 3 families; env 1 with every fourth edge removed
    _, out, objects = _step_both(lambda: _cloth_world(device, 0, newton_steps, cuttable), device)
    assert _worst(out[0], out[1], objects) <= TOL


def test_hybrid_long_rope_matches_serial(device, monkeypatch):
    # a hanging rope of 200 links swinging from horizontal for 0.5 s (2 Newton steps, 20 substeps): 51 lanes of 4
    # rows, a reduced system of 51 rows. An open, uncut rope: the kernel variant compiled without the loop and cut
    # branches ran
    from lapwarp.builder import SceneBuilder
    from lapwarp.kernels import chains_hybrid

    variants = []
    original = chains_hybrid.hybrid_chain_kernel
    monkeypatch.setattr(chains_hybrid, "hybrid_chain_kernel",
                        lambda rows, per_lane, **flags: variants.append(flags) or original(rows, per_lane, **flags))

    def make():
        b = SceneBuilder()
        pts = np.stack([np.linspace(0.0, 0.2, 201), np.zeros(201), np.zeros(201)], axis=1)
        rod = b.add_rod(pts, radius=5e-4, youngs_modulus=1e6, damping=0.5, fixed=[0])
        world = b.finalize(2, device, substeps=20)
        return world, [(rod, 0.2)]

    _, out, rods = _step_both(make, device, simulate=(0.5, 0.1))
    assert out[1][0, 200, 2] < -0.05  # the tip fell and swings
    assert _worst(out[0], out[1], rods) <= TOL * 0.2
    assert variants and all(v == {"loops": False, "masked": False, "newton_tolerance": 0.0}
                            for v in variants), variants


def test_hybrid_setting_is_checked(device, monkeypatch):
    world, _ = _rod_world(device, 0, 1, 1, False, False)
    world.chain_solver = "hybrid"
    for rows in (0, 17, 2.5, True):
        world.chain_lane_rows = rows
        with pytest.raises(ValueError, match="chain_lane_rows"):
            world.step(0.02)
    world.chain_lane_rows = 4
    if wp.get_device(device).is_cpu:
        monkeypatch.setattr(wp.config, "enable_cpu_blocks", False)
        with pytest.raises(ValueError, match="enable_cpu_blocks"):
            world.step(0.02)


def test_env_config_selects_the_hybrid_solve(device):
    import lapwarp

    env = lapwarp.make("RopeCutting", num_envs=1, device=device, chain_solver="hybrid")
    assert env.world.chain_solver == "hybrid"
    env.step(np.zeros((1, env.action_dim), dtype=np.float32))
    assert env.world.unstable.numpy().sum() == 0


def test_env_refuses_the_hybrid_solve_without_cpu_blocks(monkeypatch):
    # at make, naming the field (the World alone would refuse only at its first step)
    import lapwarp

    monkeypatch.setattr(wp.config, "enable_cpu_blocks", False)
    with pytest.raises(ValueError, match="chain_solver='hybrid'.*enable_cpu_blocks"):
        lapwarp.make("RopeCutting", num_envs=1, device="cpu", chain_solver="hybrid")


def _stopping_rods(device, solver: str, newton_steps: int, iterations: int, tolerance: float):
    """tests/test_chains_partitioned.py's open rods and loops (perturbed, cut) on a block solve (``solver``: "hybrid"
    or "pcr") stopping at ``tolerance``: their positions after 0.04 s."""
    world, rods = _rod_world(device, 0, newton_steps, iterations, False, True)
    world.chain_solver = solver
    world.rod_newton_tolerance = tolerance
    world.simulate(0.04, 0.02)
    assert world.unstable.numpy().sum() == 0
    return world.positions(), rods


@pytest.mark.parametrize("solver", ["hybrid", "pcr"])
@pytest.mark.parametrize("iterations", [1, 2])
def test_block_newton_tolerance_stops_the_steps(device, solver, iterations):
    # A tolerance above any correction stops every pack after its first Newton step, the block's lanes together:
    # the positions of one step (bit for bit on the CPU), with 2 sweeps also the multipliers the first step leaves
    # for the second sweep. 1e-30 m stops only a pack whose step corrected nothing: every step's positions. The pcr
    # solve (kernels/chains_block.py) the same way.
    one, rods = _stopping_rods(device, solver, 1, iterations, 0.0)
    three, _ = _stopping_rods(device, solver, 3, iterations, 0.0)
    assert _worst(one, three, rods) > 10 * TOL  # the later Newton steps move the rods
    _assert_same(device, one, _stopping_rods(device, solver, 3, iterations, 1.0)[0], rods)
    _assert_same(device, three, _stopping_rods(device, solver, 3, iterations, 1e-30)[0], rods)


@pytest.mark.parametrize("solver", ["hybrid", "pcr"])
def test_block_newton_tolerance_keeps_the_converged_result(device, solver):
    # at 1e-7 m within that tolerance of running every step (open rods and loops, cut)
    three, rods = _stopping_rods(device, solver, 3, 1, 0.0)
    early, _ = _stopping_rods(device, solver, 3, 1, 1e-7)
    assert np.abs(three - early).max() <= 1e-7
