"""TissueManipulationEnv: sofa_env's scene (outline, fixed band, grasp patch, landmark candidates), the physics against
references (displacement-driven equilibrium independent of the Young's modulus; the default substeps against a
many-substep answer), the reachable polygons (regenerated, and against sofa_env's bounding boxes), target sampling,
the workspace, the stuck end, the target overlay, invalid configurations and the scripted expert."""

from __future__ import annotations

import numpy as np
import pytest
import torch

import lapwarp
from lapwarp.experts import make_expert
from lapwarp.tasks.deformable_manipulation.tissue_manipulation import (
    FIXED_BELOW_Z,
    LANDMARKS,
    NUM_LANDMARKS,
    TissueManipulationEnv,
    grasp_patch,
    grasp_patch_center,
    load_reachable_polygons,
    tissue_mesh,
    trace_reachable_polygons,
)

FIXED_LANDMARK = dict(randomize_landmark=False, randomize_grasping_point=False)


DEVICE = "cpu"


@pytest.fixture(autouse=True)
def _on_the_test_device(device):
    """Every env of this module on the device the suite runs on (``--device``)."""
    global DEVICE
    DEVICE = device


def make(num_envs=1, **overrides) -> TissueManipulationEnv:
    return lapwarp.make("TissueManipulation", num_envs=num_envs, device=DEVICE, **overrides)


def point_in_polygon(poly: np.ndarray, x: float, z: float) -> bool:
    inside = False
    for a, b in zip(poly, np.roll(poly, -1, axis=0), strict=True):
        if (a[1] > z) != (b[1] > z) and x < a[0] + (z - a[1]) * (b[0] - a[0]) / (b[1] - a[1]):
            inside = not inside
    return inside


def test_scene_follows_sofa_env():
    v, t = tissue_mesh()
    assert v.shape == (120, 3) and t.shape == (264, 4)  # sofa_env's mesh: 145 nodes, 348 tets
    # sofa_env's world extent of the sheet (without its flange): x in [-0.030, 0.028], y in [-0.01, 0], z to 0.150
    np.testing.assert_allclose(v.min(axis=0), [-0.030, -0.010, 0.045], atol=1e-9)
    np.testing.assert_allclose(v.max(axis=0), [0.02808, 0.0, 0.14993], atol=1e-4)
    patch = grasp_patch(v)
    np.testing.assert_allclose(grasp_patch_center(), [0.0197, -0.005, 0.1441], atol=2e-3)  # sofa_env's rigid frame
    assert len(patch) >= 12 and np.all(v[patch, 2] >= 0.135)
    env = make(**FIXED_LANDMARK)
    # every candidate landmark is embedded in the sheet, on its camera-facing side, where sofa_env has it
    np.testing.assert_allclose(env.landmark_positions()[0].cpu().numpy(), LANDMARKS, atol=2.5e-3)
    fixed = env.world.model.particle_inv_mass.numpy().reshape(-1)[: len(v)] == 0.0
    np.testing.assert_array_equal(fixed, v[:, 2] < FIXED_BELOW_Z)


def drive(env: TissueManipulationEnv, moves) -> list[np.ndarray]:
    """Landmark positions (all candidates, env 0) after each of the grasper moves (continuous actions)."""
    out = []
    for a in moves:
        env.step(torch.tensor([a], dtype=torch.float32, device=env.device))
        out.append(env.landmark_positions()[0].cpu().numpy())
    return out


MOVES = [(1.0, 0.0)] * 15 + [(0.0, -1.0)] * 15


def test_displacement_driven_equilibrium_does_not_depend_on_youngs_modulus():
    """Linear elasticity with prescribed displacements and no load: the equilibrium shape is independent of E. Without
    gravity, at 200 substeps (converged to ~0.1 mm), doubling E moves the landmarks by less than 0.3 mm after 15 mm
    along x (the moves along z buckle the sheet, whose branch is not unique, so the test stops before them)."""
    paths = [drive(make(gravity=0.0, physics_substeps=200, youngs_modulus=e, **FIXED_LANDMARK), MOVES[:15])[-1]
             for e in (8.0e4, 1.6e5)]
    moved = np.linalg.norm(paths[0] - np.asarray(LANDMARKS), axis=1)
    assert moved.min() > 5e-3  # the landmarks really moved
    assert np.abs(paths[0] - paths[1]).max() < 3e-4


def test_default_substeps_stay_close_to_the_converged_answer():
    """The default 20 substeps against 200 (within 1.1 mm of an 800-substep answer): the landmarks' (x, z) within
    2 mm (about 10 % of their travel) over 15 mm along x then 15 mm down (which buckles the flap)."""
    fine = np.asarray(drive(make(physics_substeps=200, **FIXED_LANDMARK), MOVES))
    default = np.asarray(drive(make(**FIXED_LANDMARK), MOVES))
    travel = np.linalg.norm((fine - np.asarray(LANDMARKS))[..., [0, 2]], axis=-1).max()
    error = np.linalg.norm((default - fine)[..., [0, 2]], axis=-1).max()
    assert travel > 0.015
    assert error < 2e-3, error



def test_per_vertex_tissue_solve_is_close_to_the_converged_answer():
    """``tissue_solver="vbd"`` at the default 20 substeps against XPBD at 800 (within 0.11 mm of 1,600 substeps, and
    VBD at 400 within 0.07 mm of that): the landmarks' (x, z) within 0.6 mm over the same moves (measured 0.41 mm,
    mean 0.22 mm; XPBD at 20 substeps: 3.0 mm, mean 1.1 mm)."""
    converged = np.asarray(drive(make(physics_substeps=800, **FIXED_LANDMARK), MOVES))
    per_vertex = np.asarray(drive(make(tissue_solver="vbd", **FIXED_LANDMARK), MOVES))
    error = np.linalg.norm((per_vertex - converged)[..., [0, 2]], axis=-1)
    assert error.max() < 6e-4 and error.mean() < 3e-4, (error.max(), error.mean())


def polygon_iou(a: np.ndarray, b: np.ndarray, resolution: int = 200) -> float:
    """Intersection over union of two simple polygons ``(V, 2)``, on a ``resolution`` x ``resolution`` grid over both
    (even-odd ray casting)."""
    lo, hi = np.minimum(a.min(0), b.min(0)), np.maximum(a.max(0), b.max(0))
    grid = np.stack(np.meshgrid(*[np.linspace(lo[i], hi[i], resolution) for i in range(2)]), -1).reshape(-1, 2)

    def inside(poly):
        x, y = grid[:, 0], grid[:, 1]
        result = np.zeros(len(grid), bool)
        for (x0, y0), (x1, y1) in zip(poly, np.roll(poly, -1, axis=0), strict=True):
            crosses = (y0 > y) != (y1 > y)
            with np.errstate(divide="ignore", invalid="ignore"):
                result ^= crosses & (x < (x1 - x0) * (y - y0) / (y1 - y0) + x0)
        return result

    ia, ib = inside(a), inside(b)
    return float((ia & ib).sum() / max((ia | ib).sum(), 1))


@pytest.mark.parametrize("solver", ["xpbd", "vbd"])
def test_reachable_polygons_are_this_physics_and_match_sofa_env_boxes(solver):
    stored = load_reachable_polygons(solver)
    assert stored.shape == (NUM_LANDMARKS, 48, 2)
    # the stored regions are this physics' output: traced again, every landmark's region overlaps the stored one with
    # an intersection over union >= 0.95. Not vertex by vertex: float rounding differs between machines (another CPU's
    # vector code, the H100) and can tip the flap into the other buckling branch while the grasper presses it down
    # (an AMD EPYC CPU traced points up to 9.7 mm away at landmark 6, IoU 0.978; the other landmarks >= 0.993)
    traced = trace_reachable_polygons(DEVICE, tissue_solver=solver)
    for k in range(NUM_LANDMARKS):
        assert polygon_iou(traced[k], stored[k]) >= 0.95, k
    if solver == "vbd":
        # the converged tissue's regions are narrower at low x than sofa_env's boxes (landmarks 4 and 7 reach -15.2
        # and -11.7 mm, sofa_env's -19 mm or less): not compared (module docstring, "Convergence")
        return
    # sofa_env's polygons (traced by its own scene) span these bounding boxes (task-cards §2), m
    low, high = stored.min(axis=1), stored.max(axis=1)
    margin = 3.5e-3  # our tets are not sofa_env's mesh: the largest deviation is 3.1 mm (landmark 8's top)
    assert np.all(low[:, 0] > -0.036 - margin) and np.all(low[:, 0] < -0.019 + margin)
    assert np.all(high[:, 0] > 0.039 - margin) and np.all(high[:, 0] < 0.067 + margin)
    assert np.all(low[:, 1] > 0.103 - margin) and np.all(low[:, 1] < 0.112 + margin)
    assert np.all(high[:, 1] > 0.135 - margin) and np.all(high[:, 1] < 0.153 + margin)


def test_reset_draws_landmarks_and_targets_as_sofa_env():
    env = make(num_envs=64, seed=5)
    polygons = load_reachable_polygons()
    for _ in range(2):
        s = env.privileged_state()
        index = s["landmark_index"].cpu().numpy()
        assert len(set(index.tolist())) >= 7  # uniform over the 9 candidates
        target, landmark = s["target"].cpu().numpy(), s["landmark"].cpu().numpy()
        assert np.all(np.linalg.norm((target - landmark)[:, [0, 2]], axis=1) > 0.01)
        np.testing.assert_allclose(target[:, 1], landmark[:, 1], atol=1e-7)
        assert all(point_in_polygon(polygons[k], x, z) for k, (x, _, z) in zip(index, target, strict=True))
        np.testing.assert_allclose(s["grasper"].cpu().numpy(), np.tile(grasp_patch_center(), (64, 1)), atol=1e-6)
        env.reset()
    fixed = make(num_envs=8, landmark_index=6, **FIXED_LANDMARK)
    assert np.all(fixed.privileged_state()["landmark_index"].cpu().numpy() == 6)


def test_workspace_keeps_old_component_and_flags_it():
    env = make(**FIXED_LANDMARK)
    high_x = env.cfg.workspace_high[0]
    start = env.privileged_state()["grasper"][0].cpu().numpy().copy()
    steps = int(np.ceil((high_x - start[0]) / 0.001))
    invalid = []
    for _ in range(steps + 3):
        env.step(torch.tensor([[1.0, 0.0]], device=env.device))
        invalid.append(env._t["features"][0, 3].item())
    g = env.privileged_state()["grasper"][0].cpu().numpy()
    assert g[0] <= high_x + 1e-7 and g[0] > high_x - 1e-3
    np.testing.assert_allclose(g[[1, 2]], start[[1, 2]], atol=1e-7)  # y fixed, z untouched
    assert invalid[-1] == 1.0 and invalid[0] == 0.0
    obs = env.get_observations()["policy"][0].cpu().numpy()
    assert obs[1] == 0.0 and obs[4] == 0.0 and obs[7] == 0.0  # y set to 0 (sofa_env)
    assert abs(obs[0] - (2 * (g[0] + 0.035) / 0.1 - 1)) < 1e-5


def test_standing_still_ends_stuck_after_50_steps():
    env = make(**FIXED_LANDMARK)
    for step in range(1, 51):
        _, reward, done, _ = env.step(torch.zeros(1, 2, device=env.device))
        if step < 50:
            assert not done[0]
    assert done[0] and env._t["last_episode_success"][0] == 0
    assert env._t["last_episode_length"][0] == 50
    distance = env._t["features"][0, 0].item()
    assert reward[0].item() == pytest.approx(-distance - 5.0, abs=1e-5)


def test_target_overlay_is_drawn_at_the_target():
    env = make(num_envs=2, observation_type="RGB", seed=2)
    image = env.get_observations()["image"].cpu().numpy()  # (N, 3, 64, 64) in [0, 1]
    turquoise = np.all(np.abs(image * 255 - np.array([51, 223, 255])[None, :, None, None]) < 1.0, axis=1)
    assert turquoise[0].sum() >= 4 and turquoise[1].sum() >= 4
    rows, cols = np.nonzero(turquoise[0])
    assert np.ptp(rows) <= 3 and np.ptp(cols) <= 3  # a dot of radius round(64 / 64) = 1 px
    off = make(num_envs=2, observation_type="RGB", seed=2, show_target=False)
    image = off.get_observations()["image"].cpu().numpy()
    assert not np.any(np.all(np.abs(image * 255 - np.array([51, 223, 255])[None, :, None, None]) < 1.0, axis=1))


@pytest.mark.parametrize("overrides, message", [
    (dict(landmark_index=9), "landmark_index"),
    (dict(workspace_low=(0.0, 0.2)), "workspace_low"),
    (dict(workspace_high=(0.0, 0.13)), "outside the workspace"),
    (dict(poisson_ratio=0.5), "poisson_ratio"),
    (dict(end_position_treshold=0.002), "end_position_treshold"),
])
def test_invalid_configurations_raise(overrides, message):
    with pytest.raises(ValueError, match=message):
        make(**overrides)


@pytest.mark.parametrize("threshold, randomize, solver", [(0.002, True, "xpbd"), (0.005, True, "xpbd"),
                                                        (0.002, False, "xpbd"), (0.002, True, "vbd")])
def test_expert_solves_the_paper_configurations(threshold, randomize, solver):
    env = make(num_envs=12, end_position_threshold=threshold, randomize_landmark=randomize, seed=11,
               tissue_solver=solver)
    expert = make_expert(env)
    first = torch.full((12,), -1, device=env.device)
    for _ in range(80):
        _, _, done, _ = env.step(expert())
        first[(first < 0) & done] = env._t["last_episode_success"][(first < 0) & done].long()
    assert torch.all(first >= 0)
    assert first.float().mean() >= 0.9
