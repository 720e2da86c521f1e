"""DeflectSpheresEnv: spaces, features against hand computations, resets, done logic with the matching hook, expert,
images."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

import lapwarp
from lapwarp.experts import make_expert
from lapwarp.tasks.rig import CAUTER_CUTTING_CENTER as CUTTING_CENTER_OFFSET
from lapwarp.tasks.spatial.deflect_spheres import DONE

WS_LOW = np.array([-0.06, -0.06, -0.01])
WS_HIGH = np.array([0.06, 0.06, 0.09])
DIAG = float(np.linalg.norm(WS_HIGH - WS_LOW))


def quat_rotate(q: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Rotate v by the xyzw quaternion q."""
    u, w = q[:3], q[3]
    return v + 2.0 * np.cross(u, np.cross(u, v) + w * v)


def cutting_centres(env) -> np.ndarray:
    """(N, H, 3) cutting centres: 14.4 mm along each tip frame's +Z."""
    pose = env.instruments.pose.numpy().astype(np.float64)
    out = np.empty(pose.shape[:2] + (3,))
    for e in range(pose.shape[0]):
        for h in range(pose.shape[1]):
            out[e, h] = pose[e, h, :3] + quat_rotate(pose[e, h, 3:], np.array([0.0, 0.0, CUTTING_CENTER_OFFSET]))
    return out


def place_cutting_centre(env, env_id: int, hook: int, point: np.ndarray) -> None:
    """Put a hook's cutting centre at ``point`` (inverse TPSD kinematics in NumPy), with no sweep from the old pose."""
    rcm = env.instruments.rcm.numpy()[env_id, hook].astype(np.float64)
    q = rcm[3:]
    d = quat_rotate(q * np.array([-1, -1, -1, 1]), point - rcm[:3])  # into the RCM frame
    pan = math.degrees(math.atan2(d[0], math.hypot(d[1], d[2])))
    tilt = math.degrees(math.atan2(-d[1], d[2]))
    ptsd = env.instruments.ptsd_numpy()[env_id].copy()
    ptsd[hook] = [pan, tilt, ptsd[hook, 2], np.linalg.norm(d) - CUTTING_CENTER_OFFSET]
    env.rig.set_ptsd(ptsd[None], env_ids=[env_id])


def test_spaces_and_observation_sizes(device):
    one = lapwarp.make("DeflectSpheres", num_envs=3, device=device)
    assert one.observation_dim == 29 and one.num_actions == 4 and one.max_episode_length == 2500
    two = lapwarp.make("DeflectSpheres", num_envs=3, device=device, single_instrument=False, num_deflect_to_win=2)
    assert two.observation_dim == 41 and two.num_actions == 8 and two.max_episode_length == 1000
    assert two.get_observations()["policy"].shape == (3, 41)
    discrete = lapwarp.make("DeflectSpheres", num_envs=2, device=device, single_instrument=False,
                            action_type="DISCRETE")
    assert discrete.discrete_actions.shape == (17, 8)  # Discrete(2 * 8 + 1): one PTSD component of one hook per action
    critic = lapwarp.make("DeflectSpheres", num_envs=2, device=device, privileged_critic=True)
    assert critic.get_observations()["critic"].shape == (2, 29 + 5 + 4)
    with pytest.raises(ValueError, match="sampling_mode"):
        lapwarp.make("DeflectSpheres", sampling_mode="SOMETIMES")
    with pytest.raises(ValueError, match="num_deflect_to_win"):
        lapwarp.make("DeflectSpheres", num_spheres=2, num_deflect_to_win=3)


def test_observation_layout(device):
    env = lapwarp.make("DeflectSpheres", num_envs=2, device=device, single_instrument=False)
    obs = env.get_observations()["policy"].cpu().numpy()
    q = env.world.state.particle_q.numpy().astype(np.float64)
    unit = 2 * (q - WS_LOW) / (WS_HIGH - WS_LOW) - 1
    np.testing.assert_allclose(obs[:, :15], unit.reshape(2, 15), atol=1e-5)
    active = env.task.active.numpy()
    np.testing.assert_allclose(obs[:, 15:18], unit[np.arange(2), active], atol=1e-5)
    ptsd = env.instruments.ptsd_numpy()
    low, high = np.array([-90, -90, -90, 0.0]), np.array([90, 90, 90, 0.3])
    pose = env.instruments.pose.numpy()
    for hook, col in ((0, 18), (1, 30)):
        np.testing.assert_allclose(obs[:, col:col + 4], 2 * (ptsd[:, hook] - low) / (high - low) - 1, atol=1e-4)
        np.testing.assert_allclose(obs[:, col + 4:col + 7], 2 * (pose[:, hook, :3] - WS_LOW) / (WS_HIGH - WS_LOW) - 1,
                                   atol=1e-5)
        np.testing.assert_allclose(obs[:, col + 7:col + 11], pose[:, hook, 3:], atol=1e-6)
    np.testing.assert_array_equal(obs[:, 29], env.task.active_hook.numpy())


@pytest.mark.parametrize("single", [True, False])
def test_random_actions_stay_finite(device, single):
    env = lapwarp.make("DeflectSpheres", num_envs=16, device=device, single_instrument=single)
    gen = torch.Generator().manual_seed(0)
    for _ in range(40):
        obs, reward, done, _ = env.step(torch.rand(16, env.num_actions, generator=gen) * 2 - 1)
        assert torch.isfinite(obs["policy"]).all() and torch.isfinite(reward).all()
    assert not env.world.unstable.numpy().any()
    tips = env.instruments.tip_positions_numpy()
    assert np.all(tips >= WS_LOW - 1e-5) and np.all(tips <= WS_HIGH + 1e-5)


def test_reward_features_match_hand_computed_values(device):
    env = lapwarp.make("DeflectSpheres", num_envs=3, device=device)
    # knock every sphere off its equilibrium (the stiff, damped springs pull them mostly back within the step)
    q = env.world.state.particle_q.numpy()
    q[:, :, 0] += 0.002
    env.world.state.particle_q.assign(q)
    prev = np.linalg.norm(cutting_centres(env)[np.arange(3), 0] - q[np.arange(3), env.task.active.numpy()], axis=1)
    # env 2 presses into the spin limit: a state-limit violation (spin does not move the tip)
    ptsd = env.instruments.ptsd_numpy()
    ptsd[2, 0, 2] = 89.9
    env.rig.set_ptsd(ptsd)
    prev[2] = np.linalg.norm(cutting_centres(env)[2, 0] - q[2, env.task.active.numpy()[2]])
    env.restart_baselines()
    action = np.zeros((3, 4), dtype=np.float32)
    action[1, 3] = 0.5  # deeper by 1 mm
    action[2, 2] = 1.0
    _, reward, _, _ = env.step(torch.tensor(action, device=env.device))

    q = env.world.state.particle_q.numpy().astype(np.float64)
    anchors = env.task.anchors.numpy().astype(np.float64)
    active = env.task.active.numpy()
    deflection = np.linalg.norm(q - anchors, axis=2)
    dist = np.linalg.norm(cutting_centres(env)[np.arange(3), 0] - q[np.arange(3), active], axis=1)
    inactive = np.array([deflection[e].sum() - deflection[e, active[e]] for e in range(3)]) / 0.003
    expected = np.zeros((3, 10))
    expected[2, 1] = 1.0
    expected[:, 3] = dist / DIAG
    expected[:, 4] = (dist - prev) / DIAG
    expected[:, 5] = inactive
    features = env._t["features"].cpu().numpy()
    np.testing.assert_allclose(features, expected, atol=2e-5)
    assert np.all(inactive > 4 * 0.00049 / 0.003)  # at least the gravity sag of the four inactive spheres
    assert abs(features[1, 4]) > 1e-3  # the depth action changed the distance
    weights = np.array([0, 0, 0, 0, -5.0, -0.005, 0, 1.0, 10.0, 100.0])
    np.testing.assert_allclose(reward.cpu().numpy(), expected @ weights, atol=1e-4)


def test_resets_rerandomise_and_respect_minimum_distance(device):
    env = lapwarp.make("DeflectSpheres", num_envs=64, device=device)
    anchors = env.task.anchors.numpy().astype(np.float64)
    assert np.all(np.abs(anchors[..., :2]) <= 0.045 + 1e-6)
    assert np.all((anchors[..., 2] >= 0.03 - 1e-6) & (anchors[..., 2] <= 0.06 + 1e-6))
    gaps = np.linalg.norm(anchors[:, :, None] - anchors[:, None], axis=3) + np.eye(5) * 1.0
    assert gaps.min() >= 0.02 - 1e-6
    assert anchors[:, 0, 0].std() > 0.015 and anchors[:, 0, 2].std() > 0.005  # envs differ
    # spheres start at rest at their gravity equilibrium (half the post mass on a 1e3 N/m spring)
    np.testing.assert_allclose(env.world.state.particle_q.numpy() - anchors, np.broadcast_to([0, 0, -0.05 * 9.81e-3],
                                                                                              anchors.shape), atol=1e-6)
    env.reset()
    assert not np.allclose(env.task.anchors.numpy(), anchors)
    # auto-reset touches only finished envs
    env = lapwarp.make("DeflectSpheres", num_envs=16, device=device, num_deflect_to_win=1)
    expert = make_expert(env)
    changed = np.zeros(16, dtype=bool)
    for _ in range(12):
        before = env.task.anchors.numpy().copy()
        _, _, done, _ = env.step(expert())
        moved = np.any(env.task.anchors.numpy() != before, axis=(1, 2))
        np.testing.assert_array_equal(moved, done.cpu().numpy())
        changed |= moved
    assert changed.any()


@pytest.mark.parametrize("matching", [True, False])
def test_deflection_counts_only_with_the_matching_hook(device, matching):
    env = lapwarp.make("DeflectSpheres", num_envs=2, device=device, single_instrument=False, num_deflect_to_win=2)
    active, hook = env.task.active.numpy().copy(), env.task.active_hook.numpy().copy()
    anchors = env.task.anchors.numpy().astype(np.float64)
    for e in range(2):
        pusher = hook[e] if matching else 1 - hook[e]
        # from the hook's side, 5 mm into the sphere (sphere radius 6 mm + hook radius 0.8 mm)
        rcm = env.instruments.rcm.numpy()[e, pusher, :3]
        side = anchors[e, active[e]] - rcm
        side[2] = 0.0
        side /= np.linalg.norm(side)
        place_cutting_centre(env, e, pusher, anchors[e, active[e]] - side * 0.0018)
    env.step(torch.zeros(2, 8, device=env.device))
    deflection = np.linalg.norm(env.world.state.particle_q.numpy() - env.task.anchors.numpy(), axis=2)
    assert np.all(deflection[np.arange(2), active] >= 0.003)  # pushed out of the hook either way
    features = env._t["features"].cpu().numpy()
    if matching:
        np.testing.assert_array_equal(features[:, 8], 1.0)
        np.testing.assert_allclose(features[:, 6], deflection[np.arange(2), active] / 0.003, rtol=1e-4)
        np.testing.assert_array_equal(env.task.num_deflections.numpy(), 1)
        np.testing.assert_array_equal(env.task.state.numpy()[np.arange(2), active], DONE)  # without replacement
        assert np.all(env.task.active.numpy() != active)
    else:
        np.testing.assert_array_equal(features[:, 8], 0.0)
        np.testing.assert_array_equal(features[:, 6], 0.0)
        np.testing.assert_array_equal(env.task.num_deflections.numpy(), 0)
        np.testing.assert_array_equal(env.task.active.numpy(), active)


def test_expert_solves_one_sphere_one_hook(device):
    env = lapwarp.make("DeflectSpheres", num_envs=16, device=device, num_deflect_to_win=1)
    expert = make_expert(env)
    finished = succeeded = 0
    for _ in range(120):
        _, _, done, _ = env.step(expert())
        d = done.cpu().numpy()
        finished += int(d.sum())
        succeeded += int(env._t["last_episode_success"].cpu().numpy()[d].sum())
    assert finished >= 32
    assert succeeded / finished >= 0.9


def test_rgb_observation(device):
    env = lapwarp.make("DeflectSpheres", num_envs=2, device=device, observation_type="RGB", image_shape=(48, 64))
    image = env.get_observations()["image"]
    assert image.shape == (2, 3, 48, 64) and image.dtype == torch.float32
    assert float(image.min()) >= 0.0 and float(image.max()) <= 1.0
    rgb = image.cpu().numpy()
    board = (rgb[:, 0] > 0.5) & (rgb[:, 1] > 0.4) & (rgb[:, 2] < 0.5)  # wood
    blue = (rgb[:, 2] > 0.2) & (rgb[:, 2] > 2 * rgb[:, 0]) & (rgb[:, 2] > 2 * rgb[:, 1])  # active sphere, hook
    assert board.sum(axis=(1, 2)).min() > 200 and blue.sum(axis=(1, 2)).min() > 3
    out, _, _, _ = env.step(torch.zeros(2, 4, device=env.device))
    assert out["image"].shape == (2, 3, 48, 64)
