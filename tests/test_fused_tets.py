"""The fused tet sweep (``world.tet_solver = "fused"``: one thread block per env, every colour in one launch, the env's
tet particles in shared memory) against the per-colour launches: the same projections in the same order, so the same
positions (bit for bit on the CPU, where a block has one lane; within float32 rounding on the GPU, where the two
kernels may contract multiply-adds differently), with per-env materials, a window that does not start at particle 0,
several sweeps per substep (multipliers), the SVD rotation, and cut tets; for both tet methods (XPBD projections and
the per-vertex solve, kernels/vbd.py), both also with the rotations refreshed once per sweep. Also: the per-vertex
solve's layout (a vertex colouring no tet violates, every incidence listed once), its refusal of unanchored meshes and
of unknown method names and rotation updates."""

from __future__ import annotations

import numpy as np
import pytest

from lapwarp.assets import box_tets, cloth_grid
from lapwarp.builder import SceneBuilder


def _scene(device, solver, iterations=1, rotation_iterations=2, cut=False, method="xpbd"):
    b = SceneBuilder()
    # a cloth first, so the tets' particle window starts past particle 0
    cv, ct = cloth_grid(4, 4, 0.02, 0.02, plane="xz")
    b.add_cloth(cv, ct, fixed=np.nonzero(cv[:, 2] > 0.02 - 1e-9)[0])
    v, t = box_tets((0.04, 0.02, 0.01), (6, 3, 2))
    block = b.add_tet_mesh(v, t, density=1000.0, youngs_modulus=[3e3, 8e3, 5e3], poisson_ratio=0.45,
                           fixed=np.nonzero(v[:, 0] < 1e-9)[0], cuttable=cut)
    world = b.finalize(num_envs=3, device=device, substeps=8, iterations=iterations)
    world.tet_solver = solver
    world.tet_method = method.removesuffix("-sweep")
    if method.endswith("-sweep"):
        world.tet_rotation_update = "sweep"  # kernels/xpbd.py refresh_tet_rotations
    world.tet_rotation_iterations = rotation_iterations
    if cut:
        import warp as wp

        active = np.ones((3, len(t)), dtype=np.int32)
        active[1, ::3] = 0  # env 1 loses every third tet
        wp.copy(world.state.tet_active, wp.array(active, dtype=wp.int32, device=device))
    return world, block


@pytest.mark.parametrize("method,iterations,rotation_iterations,cut", [
    ("xpbd", 1, 2, False), ("xpbd", 2, 0, False), ("xpbd", 1, 2, True), ("xpbd-sweep", 1, 2, False),
    ("xpbd-sweep", 2, 1, True),
    ("vbd", 1, 2, False), ("vbd", 2, 0, False), ("vbd", 1, 2, True), ("vbd-sweep", 1, 2, False),
    ("vbd-sweep", 2, 1, True)])
def test_fused_tet_sweep_matches_the_per_colour_launches(device, method, iterations, rotation_iterations, cut):
    result = {}
    for solver in ("colored", "fused"):
        world, block = _scene(device, solver, iterations, rotation_iterations, cut, method)
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
    for method in ("xpbd", "vbd"):
        world, _ = _scene(device, "colored", method=method)
        world.tet_rotation_update = "never"
        with pytest.raises(ValueError, match="vertex.*sweep"):
            world.step(0.05)
        world.tet_rotation_update = "sweep"
        world.tet_rotation_iterations = 0  # SVD rotations are not stored: nothing to lag
        with pytest.raises(ValueError, match="tet_rotation_iterations > 0"):
            world.step(0.05)
        world.tet_rotation_iterations = 2
        for every in (0, 1.5, True):
            world.tet_rotation_refresh = every
            with pytest.raises(ValueError, match="tet_rotation_refresh must be an int >= 1"):
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


def test_vertex_layout_colours_and_incidences(device):
    from lapwarp.vbd import tet_components, vertex_layout

    world, _ = _scene(device, "colored")
    tets = world.model.tet_indices.numpy()
    lay = vertex_layout(tets)
    color = {int(v): c for c in range(len(lay.color_offsets) - 1)
             for v in lay.vertices[lay.color_offsets[c]:lay.color_offsets[c + 1]]}
    assert sorted(color) == sorted(np.unique(tets).tolist())
    for tet in tets:  # no tet has two vertices of one colour
        assert len({color[int(v)] for v in tet}) == 4
    seen = set()
    for j, v in enumerate(lay.vertices):
        for a in range(lay.adj_offsets[j], lay.adj_offsets[j + 1]):
            assert tets[lay.adj_tets[a], lay.adj_corners[a]] == v
            seen.add((int(lay.adj_tets[a]), int(lay.adj_corners[a])))
    assert len(seen) == 4 * len(tets) == lay.adj_offsets[-1]
    assert len(tet_components(tets)) == 1
    assert len(tet_components(np.array([[0, 1, 2, 3], [4, 5, 6, 7], [3, 8, 9, 10]]))) == 2


def test_vertex_solve_refuses_unanchored_meshes_and_unknown_methods(device):
    b = SceneBuilder()
    v, t = box_tets((0.02, 0.02, 0.01), (2, 2, 1))
    b.add_tet_mesh(v, t, density=1000.0, youngs_modulus=3e4, poisson_ratio=0.3)  # free: nothing pinned
    world = b.finalize(num_envs=2, device=device, substeps=4)
    world.tet_method = "vbd"
    with pytest.raises(ValueError, match="pinned particle"):
        world.step(0.05)
    world.tet_method = "implicit"
    with pytest.raises(ValueError, match="xpbd.*vbd"):
        world.step(0.05)


@pytest.mark.parametrize("force", [False, True])
def test_vertex_solve_start_in_the_prediction_matches_begin_substep(device, force):
    """The per-vertex solve's start of a substep (``x_pred - h^2 (g + w f)``) written by the prediction
    (``xpbd.integrate_particle``'s ``vbd_start``, where nothing in the sweep moves the tet vertices before the solve)
    against ``vbd.begin_substep`` after the prediction: the same positions after four steps of a hanging block with
    per-env materials (bit for bit on the CPU; within float32 rounding on the GPU, where the two kernels may contract
    multiply-adds differently), also with an external force on the particles. With a cloth in the scene (its plain
    edge constraints run before the tets) the World keeps begin_substep."""
    import warp as wp

    result = {}
    for in_prediction in (False, True):
        b = SceneBuilder()
        v, t = box_tets((0.04, 0.02, 0.01), (6, 3, 2))
        block = b.add_tet_mesh(v, t, density=1000.0, youngs_modulus=[3e3, 8e3, 5e3], poisson_ratio=0.45,
                               fixed=np.nonzero(v[:, 0] < 1e-9)[0])
        world = b.finalize(num_envs=3, device=device, substeps=8)
        world.tet_method = "vbd"
        assert world._vbd_start_in_prediction()
        if not in_prediction:
            world._vbd_start_in_prediction = lambda: False
        if force:
            f = np.zeros((3, world.model.particle_count, 3), dtype=np.float32)
            f[:, :, 1] = 2.0e-4  # sideways, N per particle
            wp.copy(world.enable_external_forces(), wp.array(f, dtype=wp.vec3, device=device))
        for _ in range(4):
            world.step(0.05)
        result[in_prediction] = world.positions(block)
    sag = -result[False][..., 2].min()
    assert sag > 1e-3  # the free end hangs: the comparison is not between two resting blocks
    if device == "cpu":
        np.testing.assert_array_equal(result[True], result[False])
    else:
        np.testing.assert_allclose(result[True], result[False], atol=1e-6 * 0.04 + 1e-3 * sag)
    if force:
        assert result[True][..., 1].max() > 1e-4  # the force moved the block sideways

    b = SceneBuilder()
    cv, ct = cloth_grid(4, 4, 0.02, 0.02, plane="xz")
    b.add_cloth(cv, ct, fixed=np.nonzero(cv[:, 2] > 0.02 - 1e-9)[0])
    b.add_tet_mesh(v, t, density=1000.0, youngs_modulus=3e3, poisson_ratio=0.45, fixed=np.nonzero(v[:, 0] < 1e-9)[0])
    world = b.finalize(num_envs=1, device=device, substeps=4)
    world.tet_method = "vbd"
    assert world._vbd_start_in_prediction() == (world.model.edge_chains is not None)
