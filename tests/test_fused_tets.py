"""The fused tet sweep (``world.tet_solver = "fused"``: one thread block per env, every colour in one launch, the env's
tet particles in shared memory) against the per-colour launches: the same projections in the same order, so the same
positions (bit for bit on the CPU, where a block has one lane; within float32 rounding on the GPU, where the two
kernels may contract multiply-adds differently), with per-env materials, a window that does not start at particle 0,
several sweeps per substep (multipliers), the SVD rotation, and cut tets."""

from __future__ import annotations

import numpy as np
import pytest

from lapwarp.assets import box_tets, cloth_grid
from lapwarp.builder import SceneBuilder


def _scene(device, solver, iterations=1, rotation_iterations=2, cut=False):
    b = SceneBuilder()
    # a cloth first, so the tets' particle window starts past particle 0
    cv, ct = cloth_grid(4, 4, 0.02, 0.02, plane="xz")
    b.add_cloth(cv, ct, fixed=np.nonzero(cv[:, 2] > 0.02 - 1e-9)[0])
    v, t = box_tets((0.04, 0.02, 0.01), (6, 3, 2))
    block = b.add_tet_mesh(v, t, density=1000.0, youngs_modulus=[3e3, 8e3, 5e3], poisson_ratio=0.45,
                           fixed=np.nonzero(v[:, 0] < 1e-9)[0], cuttable=cut)
    world = b.finalize(num_envs=3, device=device, substeps=8, iterations=iterations)
    world.tet_solver = solver
    world.tet_rotation_iterations = rotation_iterations
    if cut:
        import warp as wp

        active = np.ones((3, len(t)), dtype=np.int32)
        active[1, ::3] = 0  # env 1 loses every third tet
        wp.copy(world.state.tet_active, wp.array(active, dtype=wp.int32, device=device))
    return world, block


@pytest.mark.parametrize("iterations,rotation_iterations,cut", [(1, 2, False), (2, 0, False), (1, 2, True)])
def test_fused_tet_sweep_matches_the_per_colour_launches(device, iterations, rotation_iterations, cut):
    result = {}
    for solver in ("colored", "fused"):
        world, block = _scene(device, solver, iterations, rotation_iterations, cut)
        for _ in range(4):
            world.step(0.05)
        result[solver] = world.positions(block)
    sag = -result["colored"][..., 2].min()
    assert sag > 1e-3  # the free end hangs: the comparison is not between two resting blocks
    if device == "cpu":
        np.testing.assert_array_equal(result["fused"], result["colored"])
    else:
        np.testing.assert_allclose(result["fused"], result["colored"], atol=1e-6 * 0.04 + 1e-3 * sag)


def test_unknown_tet_solver_is_rejected(device):
    world, _ = _scene(device, "colored")
    world.tet_solver = "jacobi"
    with pytest.raises(ValueError, match="auto.*colored.*fused"):
        world.step(0.05)


def test_auto_fuses_the_tets_that_fit_shared_memory(device):
    from lapwarp import world as world_module

    world, _ = _scene(device, "auto")
    assert world.fused_tets
    world_module_limit = world_module.FUSED_TET_MAX_PARTICLES
    try:
        world_module.FUSED_TET_MAX_PARTICLES = world._tet_window[1] - 1
        assert not world.fused_tets  # a window too large for shared memory falls back to the per-colour launches
        world.tet_solver = "fused"
        with pytest.raises(ValueError, match="shared memory"):
            world.step(0.05)
    finally:
        world_module.FUSED_TET_MAX_PARTICLES = world_module_limit
