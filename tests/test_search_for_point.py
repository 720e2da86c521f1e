"""SearchForPointEnv: spaces, oblique-camera geometry and reward features on hand-built states, resets, the
scripted expert, and image observations checked against an independent NumPy camera model."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

import lapwarp
from lapwarp.experts import make_expert
from lapwarp.tasks.camera import oblique_camera_ptsd
from lapwarp.tasks.spatial.search_for_point import REWARDS

SEARCH_FEATURES = REWARDS.names

F = {name: i for i, name in enumerate(SEARCH_FEATURES)}
CAM_RCM = np.array([0.010, -0.1008, 0.28182])
CAM_EULER = (-155.0, 0.0, 0.0)
CAUTER_RCM = np.array([0.1172, 0.00229, 0.23362])
CAUTER_EULER = (-170.0, -30.0, 0.0)
CAM_LOW, CAM_HIGH = np.array([-40, -50, -180, 0.01]), np.array([40, 40, 180, 0.15])


def rot_xyz(deg) -> np.ndarray:
    """Rx(a) Ry(b) Rz(c), degrees (sofa_env's euler_to_rotation_matrix)."""
    a, b, c = np.radians(deg)
    rx = np.array([[1, 0, 0], [0, math.cos(a), -math.sin(a)], [0, math.sin(a), math.cos(a)]])
    ry = np.array([[math.cos(b), 0, math.sin(b)], [0, 1, 0], [-math.sin(b), 0, math.cos(b)]])
    rz = np.array([[math.cos(c), -math.sin(c), 0], [math.sin(c), math.cos(c), 0], [0, 0, 1]])
    return rx @ ry @ rz


def optic(ptsd_deg_m) -> tuple[np.ndarray, np.ndarray]:
    """Camera position and orientation by §3: FK(ptsd) R_xyz(0, 180, 180) R_xyz(-30, 0, 0), written out in NumPy."""
    pan, tilt, spin, depth = ptsd_deg_m
    shaft = rot_xyz(CAM_EULER) @ rot_xyz((tilt, pan, spin))
    position = CAM_RCM + shaft @ np.array([0.0, 0.0, depth])
    return position, shaft @ rot_xyz((0.0, 180.0, 180.0)) @ rot_xyz((-30.0, 0.0, 0.0))


def pixel_of(point, position, rotation, size=64, fov=45.0) -> tuple[float, float, float]:
    """Pinhole projection, camera looking along its local -Z with +Y up: (row, col, depth)."""
    q = rotation.T @ (np.asarray(point) - position)
    focal = 0.5 * size / math.tan(math.radians(fov) / 2)
    return 0.5 * size - focal * q[1] / -q[2], 0.5 * size + focal * q[0] / -q[2], -q[2]


def centring_ptsd(poi: np.ndarray, distance: float = 0.12) -> np.ndarray:
    """A camera state (deg, m) inside the limits that centres ``poi`` at ``distance``: the highest optic position
    among the roll solutions (high optics look over the organs)."""
    sol = oblique_camera_ptsd(torch.tensor(CAM_RCM), torch.tensor(rot_xyz(CAM_EULER)),
                              torch.tensor(poi, dtype=torch.float64), distance, 30.0).numpy()
    sol = sol * np.array([180 / math.pi] * 3 + [1.0])
    margin = np.array([0.5, 0.5, 0.5, 0.002])
    ok = np.all((sol > CAM_LOW + margin) & (sol < CAM_HIGH - margin), axis=1)
    assert ok.any(), f"no centring state for {poi}"
    heights = [optic(s)[0][2] if good else -np.inf for s, good in zip(sol, ok, strict=True)]
    return sol[int(np.argmax(heights))]


def cauter_ptsd(point: np.ndarray, spin: float = 0.0) -> np.ndarray:
    local = rot_xyz(CAUTER_EULER).T @ (point - CAUTER_RCM)
    pan = math.degrees(math.atan2(local[0], math.hypot(local[1], local[2])))
    tilt = math.degrees(math.atan2(-local[1], local[2]))
    return np.array([pan, tilt, spin, np.linalg.norm(local)])


def features(env) -> np.ndarray:
    return env._t["features"].cpu().numpy().astype(np.float64)


def test_spaces_and_observation_layout(device):
    env = lapwarp.make("SearchForPoint", num_envs=3, device=device)
    assert env.num_actions == 4 and env.observation_dim == 14 and env.max_episode_length == 500
    assert env.dt == pytest.approx(0.3)  # frame_skip 3 x 0.1 s
    obs = env.get_observations()["policy"].cpu().numpy()
    np.testing.assert_allclose(obs[:, :3], env.poi.numpy(), atol=1e-7)
    ptsd = env.instruments.ptsd_numpy()[:, 0]
    np.testing.assert_allclose(obs[:, 10:14], ptsd * np.array([math.pi / 180] * 3 + [1]), atol=1e-5)
    for e in range(3):
        position, rotation = optic(ptsd[e])
        np.testing.assert_allclose(obs[e, 3:6], position, atol=1e-5)
        x, y, z, w = obs[e, 6:10]
        assert w >= 0.0
        q_rot = np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                          [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                          [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])
        np.testing.assert_allclose(q_rot, rotation, atol=1e-5)

    active = lapwarp.make("SearchForPoint", num_envs=2, device=device, active_vision=True)
    assert active.num_actions == 8 and active.observation_dim == 26
    assert active.reward_weights["relative_delta_distance_cauter_target"] == -5.0
    assert active.reward_weights["poi_is_in_frame"] == 0.0  # camera terms are not part of the hook's reward
    hook = lapwarp.make("SearchForPoint", num_envs=2, device=device, active_vision=True, cauter_activation=True,
                        action_type="DISCRETE")
    assert hook.num_actions == 1 and hook.action_dim == 9 and hook.observation_dim == 26
    with pytest.raises(ValueError, match="active_vision"):
        lapwarp.make("SearchForPoint", cauter_activation=True)


def test_camera_moves_by_velocity_times_time_and_respects_limits(device):
    env = lapwarp.make("SearchForPoint", num_envs=2, device=device)
    env.set_ptsd(np.array([[[0.0, 0.0, 0.0, 0.05]], [[39.0, 0.0, 0.0, 0.05]]]))
    env.step(torch.tensor([[1.0, -1.0, 0.5, 1.0], [1.0, 0.0, 0.0, -1.0]], device=env.device))
    ptsd = env.instruments.ptsd_numpy()[:, 0]
    # 3 sub-steps of 0.1 s at (20, 20, 30 deg/s, 35 mm/s)
    np.testing.assert_allclose(ptsd[0], [6.0, -6.0, 4.5, 0.05 + 0.0105], atol=1e-4)
    np.testing.assert_allclose(ptsd[1], [39.0, 0.0, 0.0, 0.05 - 0.0105], atol=1e-4)  # pan 40 limit holds


def test_random_actions_stay_finite_and_inside_limits(device):
    env = lapwarp.make("SearchForPoint", num_envs=6, device=device, active_vision=True, cauter_activation=True)
    gen = torch.Generator().manual_seed(0)
    for _ in range(25):
        obs, reward, done, _ = env.step(torch.rand(6, 9, generator=gen) * 2 - 1)
        assert torch.isfinite(obs["policy"]).all() and torch.isfinite(reward).all()
        assert float(obs["policy"].abs().max()) <= 3.2  # the declared observation bounds
    ptsd = env.instruments.ptsd_numpy()
    assert np.all(ptsd[:, 0] >= CAM_LOW - 1e-4) and np.all(ptsd[:, 0] <= CAM_HIGH + 1e-4)


def test_reward_features_on_hand_built_camera_states(device):
    env = lapwarp.make("SearchForPoint", num_envs=3, device=device)
    pois = env.candidates.numpy()[[0, 1000, 2000]].astype(np.float64)
    env.set_poi(pois)
    exact = centring_ptsd(pois[0])
    far = centring_ptsd(pois[1], distance=0.15)  # 30 mm too far, centred
    rolled = centring_ptsd(pois[2]) + np.array([0.0, 0.0, 6.0, 0.0])  # spin moves the POI off the centre
    env.set_ptsd(np.stack([exact, far, rolled])[:, None])
    _, reward, done, _ = env.step(torch.zeros(3, 4, device=env.device))
    f = features(env)

    assert f[0, F["poi_is_in_frame"]] == 1.0
    assert f[0, F["relative_camera_distance_error_to_poi"]] == pytest.approx(0.0, abs=2e-4)
    assert f[0, F["relative_pixel_distance_poi_to_image_center"]] == pytest.approx(0.0, abs=2e-3)
    assert f[0, F["successful_task"]] == 1.0 and bool(done[0])

    assert f[1, F["relative_camera_distance_error_to_poi"]] == pytest.approx(0.25, abs=2e-4)  # |150 - 120| / 120
    assert f[1, F["relative_pixel_distance_poi_to_image_center"]] == pytest.approx(0.0, abs=2e-3)
    assert f[1, F["successful_task"]] == 0.0 and not bool(done[1])

    position, rotation = optic(rolled)
    row, col, depth = pixel_of(pois[2], position, rotation)
    expected = math.hypot(row - 32, col - 32) / (0.5 * math.hypot(64, 64))
    assert 0.05 < expected < 0.9
    assert f[2, F["relative_pixel_distance_poi_to_image_center"]] == pytest.approx(expected, abs=1e-3)
    assert f[2, F["poi_is_in_frame"]] == 1.0
    error = abs(np.linalg.norm(pois[2] - position) - 0.12) / 0.12
    assert f[2, F["relative_camera_distance_error_to_poi"]] == pytest.approx(error, abs=2e-4)
    assert f[2, F["successful_task"]] == float(expected < 0.2 and error * 0.12 < 0.01)
    for name in ("collision_cauter", "relative_distance_cauter_target", "cauter_touches_target"):
        assert np.all(f[:, F[name]] == 0.0)  # no hook in camera-only mode

    weights = np.array([env.reward_weights.get(n, 0.0) for n in SEARCH_FEATURES])
    np.testing.assert_allclose(reward.cpu().numpy(), f @ weights, rtol=1e-5, atol=1e-6)

    # env 1 keeps its state (env 0 was reset): a zero action gives zero deltas; a depth step changes the error
    env.step(torch.tensor([[0, 0, 0, 0], [0, 0, 0, 1.0], [0, 0, 0, 0]], dtype=torch.float32, device=env.device))
    f2 = features(env)
    assert f2[2, F["delta_relative_camera_distance_error_to_poi"]] == pytest.approx(0.0, abs=1e-6)
    assert f2[2, F["delta_relative_pixel_distance_poi_to_image_center"]] == pytest.approx(0.0, abs=1e-6)
    new_error = f2[1, F["relative_camera_distance_error_to_poi"]]
    assert f2[1, F["delta_relative_camera_distance_error_to_poi"]] == pytest.approx(new_error - 0.25, abs=2e-4)
    assert new_error < 0.25 - 0.05  # 10.5 mm deeper along the oblique line of sight is closer to the POI


def test_poi_behind_the_camera_is_out_of_frame(device):
    env = lapwarp.make("SearchForPoint", num_envs=1, device=device)
    env.set_ptsd(np.array([0.0, 0.0, 0.0, 0.03]))
    position, rotation = optic([0.0, 0.0, 0.0, 0.03])
    env.set_poi((position + rotation @ np.array([0.0, 0.0, 0.05]))[None])  # 5 cm behind the optic
    env.step(torch.zeros(1, 4, device=env.device))
    f = features(env)[0]
    assert f[F["poi_is_in_frame"]] == 0.0 and f[F["relative_pixel_distance_poi_to_image_center"]] == 2.0


def test_active_vision_touch_activation_and_collision(device):
    env = lapwarp.make("SearchForPoint", num_envs=3, device=device, active_vision=True, cauter_activation=True)
    pois = env.candidates.numpy()[[0, 1, 2]].astype(np.float64)
    env.set_poi(pois)
    camera = np.array([0.0, 0.0, 0.0, 0.03])
    liver_centre = np.array([0.035, 0.105, 0.125])
    states = [[camera, cauter_ptsd(pois[0])], [camera, cauter_ptsd(pois[1])],
              [camera, cauter_ptsd(liver_centre)]]
    env.set_ptsd(np.array(states))
    env.step(torch.zeros(3, 9, device=env.device) + torch.tensor([0] * 8 + [-1.0], device=env.device))
    f = features(env)
    assert np.all(f[:2, F["cauter_touches_target"]] == 1.0)
    assert np.all(f[:, F["successful_task"]] == 0.0)  # the hook is off
    assert f[2, F["collision_cauter"]] == 4.0  # all four spheres inside the liver
    distance = np.linalg.norm(liver_centre - pois[2]) / np.linalg.norm(CAUTER_RCM - pois[2])
    assert f[2, F["relative_distance_cauter_target"]] == pytest.approx(distance, rel=1e-4)

    action = torch.zeros(3, 9, device=env.device)
    action[:, 8] = 0.05  # inside the dead zone: stays off
    env.step(action)
    assert np.all(features(env)[:, F["successful_task"]] == 0.0)
    action[:, 8] = 1.0
    _, _, done, _ = env.step(action)
    f = features(env)
    assert list(f[:, F["successful_task"]]) == [1.0, 1.0, 0.0] and done.tolist() == [True, True, False]

    env.set_ptsd(np.array([camera, [0.0, 0.0, 0.0, 0.01]]))  # hook just inside its trocar, far from organs
    env.step(torch.zeros(3, 9, device=env.device))
    assert np.all(features(env)[:, F["collision_cauter"]] == 0.0)


def test_resets_rerandomise_each_env(device):
    env = lapwarp.make("SearchForPoint", num_envs=8, device=device)
    poi0, ptsd0 = env.poi.numpy().copy(), env.instruments.ptsd_numpy().copy()
    assert len(np.unique(poi0, axis=0)) == 8 and len(np.unique(ptsd0[:, 0, 0])) == 8
    env.reset()
    assert not np.any(np.all(env.poi.numpy() == poi0, axis=1))
    assert not np.any(ptsd0 == env.instruments.ptsd_numpy())
    # one env succeeds: only it is re-drawn
    poi1 = env.poi.numpy().copy()
    ptsd = env.instruments.ptsd_numpy()[:, 0]
    ptsd[3] = centring_ptsd(poi1[3].astype(np.float64))
    env.set_ptsd(ptsd[:, None])
    _, _, done, _ = env.step(torch.zeros(8, 4, device=env.device))
    assert done.tolist() == [i == 3 for i in range(8)]
    poi2 = env.poi.numpy()
    assert np.all(poi2[np.arange(8) != 3] == poi1[np.arange(8) != 3]) and np.any(poi2[3] != poi1[3])


@pytest.mark.parametrize("active_vision", [False, True])
def test_expert_succeeds(device, active_vision):
    env = lapwarp.make("SearchForPoint", num_envs=16, device=device, active_vision=active_vision,
                       cauter_activation=active_vision, seed=7)
    expert = make_expert(env)
    finished = successes = 0
    for _ in range(40):
        _, _, done, extras = env.step(expert())
        finished += int(done.sum())
        successes += int((done & ~extras["time_outs"]).sum())
    assert finished >= 16
    assert successes / finished >= 0.9


def test_discrete_expert_finishes_episodes(device):
    env = lapwarp.make("SearchForPoint", num_envs=16, device=device, action_type="DISCRETE", seed=3)
    expert = make_expert(env)
    done_once = torch.zeros(16, dtype=torch.bool)
    for _ in range(150):  # 5 deg/s and 5 mm/s steps: about 90 steps per episode
        _, _, done, extras = env.step(expert())
        assert not bool(extras["time_outs"].any())
        done_once |= done.cpu()
    assert int(done_once.sum()) >= 14
    assert env._t["last_episode_success"][done_once].all()


def test_rgb_shows_the_poi_where_the_pixel_feature_says(device):
    # a tolerance nobody meets keeps the episodes running, so the observation shows these states, not a reset
    env = lapwarp.make("SearchForPoint", num_envs=4, device=device, observation_type="RGB", frame_stack=2,
                       tolerance_image_center=1e-3)
    obs = env.get_observations()["image"]
    assert obs.shape == (4, 6, 64, 64) and obs.dtype == torch.float32
    pois = env.candidates.numpy()[[10, 800, 1600, 2400]].astype(np.float64)
    env.set_poi(pois)
    # spin offsets move the POI around the image; it stays in frame and in front of the organs' other parts
    states = [centring_ptsd(p) + np.array([0.0, 0.0, s, 0.0]) for p, s in zip(pois, (1.0, 4.0, -5.0, 8.0),
                                                                                strict=True)]
    env.set_ptsd(np.array(states)[:, None])
    obs, _, _, _ = env.step(torch.zeros(4, 4, device=env.device))
    image = obs["image"][:, 3:6].cpu().numpy()  # newest frame
    f = features(env)
    green = 0
    for e in range(4):
        position, rotation = optic(states[e])
        row, col, depth = pixel_of(pois[e], position, rotation)
        expected = math.hypot(row - 32, col - 32) / (0.5 * math.hypot(64, 64))
        assert f[e, F["relative_pixel_distance_poi_to_image_center"]] == pytest.approx(expected, abs=1e-3)
        r, g, b = image[e, :, int(row), int(col)]
        green += int(g > 0.3 and g > 3 * r and g > 3 * b)
    assert green == 4
