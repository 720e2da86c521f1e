"""ReachEnv and the BatchedEnv plumbing it exercises: spaces, kinematics, rewards, resets, dones, stacking."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
import warp as wp

import lapwarp
from lapwarp.tasks.spatial.reach import ReachExpert

WS_LOW = np.array([-0.15, -0.05, -0.15])
WS_HIGH = np.array([0.15, 0.14, 0.15])
DIAG = float(np.linalg.norm(WS_HIGH - WS_LOW))


def set_positions(env, ee: np.ndarray, target: np.ndarray) -> None:
    """Place end effectors and targets by hand and make the delta feature start from their distance."""
    env.ee_position.assign(wp.array(ee.astype(np.float32), dtype=wp.vec3, device=env.wp_device))
    env.target_position.assign(wp.array(target.astype(np.float32), dtype=wp.vec3, device=env.wp_device))
    env.restart_baselines()


def positions(env) -> tuple[np.ndarray, np.ndarray]:
    return env.ee_position.numpy().astype(np.float64), env.target_position.numpy().astype(np.float64)


def normalised(ee: np.ndarray, target: np.ndarray) -> np.ndarray:
    """The STATE observation by its definition: both positions mapped from the workspace to [-1, 1]."""
    return np.concatenate([2 * (p - WS_LOW) / (WS_HIGH - WS_LOW) - 1 for p in (ee, target)], axis=1)


def test_spaces_and_shapes(device):
    env = lapwarp.make("Reach", num_envs=5, device=device)
    assert env.num_actions == 3 and env.observation_dim == 6 and env.max_episode_length == 500
    obs = env.get_observations()
    assert obs["policy"].shape == (5, 6) and obs["policy"].dtype == torch.float32
    assert "critic" not in obs.keys()
    assert float(obs["policy"].abs().max()) <= 1.0
    out, reward, done, extras = env.step(torch.zeros(5, 3, device=env.device))
    assert reward.shape == (5,) and done.shape == (5,) and extras["time_outs"].shape == (5,)
    assert set(extras["log"]) >= {f"/reward/{f}" for f in env.reward_features} | {"/episode/success"}


def test_observation_is_normalised_positions(device):
    env = lapwarp.make("Reach", num_envs=3, device=device)
    ee, target = positions(env)
    np.testing.assert_allclose(env.get_observations()["policy"].cpu().numpy(), normalised(ee, target), atol=1e-5)


def test_action_moves_end_effector_by_velocity_times_dt(device):
    env = lapwarp.make("Reach", num_envs=2, device=device)
    ee0 = np.array([[0.0, 0.05, 0.0], [0.01, 0.02, -0.03]])
    set_positions(env, ee0, np.array([[0.1, 0.1, 0.1], [-0.1, 0.1, 0.1]]))
    action = np.array([[1.0, -0.5, 0.25], [-1.0, 0.0, 1.0]], dtype=np.float32)
    env.step(torch.tensor(action, device=env.device))
    ee1, _ = positions(env)
    # one step of 0.1 s at 35 mm/s per unit action: 3.5 mm at |a| = 1
    np.testing.assert_allclose(ee1 - ee0, 0.1 * 0.035 * action, atol=1e-6)


def test_workspace_masks_only_the_violating_axis(device):
    env = lapwarp.make("Reach", num_envs=1, device=device)
    ee0 = np.array([[0.149, 0.0, 0.0]])
    set_positions(env, ee0, np.array([[-0.1, 0.1, 0.1]]))
    env.step(torch.tensor([[1.0, 1.0, 0.0]], device=env.device))
    ee1, _ = positions(env)
    assert ee1[0, 0] == pytest.approx(0.149, abs=1e-7)  # x would leave the workspace: keeps its value
    assert ee1[0, 1] == pytest.approx(0.0035, abs=1e-6)  # y moves
    features = env._t["features"].cpu().numpy()[0]
    assert features[3] == 1.0  # workspace_violation


def test_reward_features_match_hand_computed_values(device):
    env = lapwarp.make("Reach", num_envs=2, device=device)
    ee0 = np.array([[0.0, 0.0, 0.0], [0.05, 0.05, 0.05]])
    target = np.array([[0.1, 0.0, 0.0], [0.05, 0.05, 0.0521]])
    set_positions(env, ee0, target)
    action = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 0.6]], dtype=np.float32)
    _, reward, done, _ = env.step(torch.tensor(action, device=env.device))
    d0 = np.linalg.norm(target - ee0, axis=1)
    d1 = np.linalg.norm(target - (ee0 + 0.0035 * action), axis=1)
    success = (d1 <= 0.003).astype(float)
    expected = np.stack([d1 / DIAG, (d1 - d0) / DIAG, np.ones(2), np.zeros(2), success], axis=1)
    np.testing.assert_allclose(env._t["features"].cpu().numpy(), expected, atol=1e-6)
    weights = np.array([-1.0, -10.0, 0.0, 0.0, 100.0])
    np.testing.assert_allclose(reward.cpu().numpy(), expected @ weights, atol=1e-4)
    assert success.tolist() == [0.0, 1.0]  # env 1 ends 0.0021 - 0.0021 = 0 mm from the target
    assert done.cpu().tolist() == [False, True]


def test_reward_weight_override(device):
    env = lapwarp.make("Reach", num_envs=1, device=device, reward_weights={"time_step_cost": -2.5,
                                                                        "distance_to_target": 0.0,
                                                                        "delta_distance_to_target": 0.0})
    _, reward, _, _ = env.step(torch.zeros(1, 3, device=env.device))
    assert float(reward[0]) == pytest.approx(-2.5)


def test_reset_samples_inside_boxes_with_minimum_distance(device):
    env = lapwarp.make("Reach", num_envs=256, device=device)
    ee, target = positions(env)
    for p in (ee, target):
        assert np.all(p >= WS_LOW - 1e-6) and np.all(p <= WS_HIGH + 1e-6)
    assert np.all(np.linalg.norm(target - ee, axis=1) >= 0.05 - 1e-6)
    # samples cover the box (a broken RNG that repeats one value per env would fail this)
    assert np.all(ee.std(axis=0) > 0.2 * (WS_HIGH - WS_LOW) / math.sqrt(12))
    assert np.abs(np.corrcoef(ee[:, 0], target[:, 0])[0, 1]) < 0.3


def test_resets_rerandomise_and_seed_reproduces(device):
    env = lapwarp.make("Reach", num_envs=4, device=device, seed=7)
    first = env.get_observations()["policy"].cpu().numpy()
    second = env.reset()[0]["policy"].cpu().numpy()
    assert not np.allclose(first, second)  # each reset draws new positions
    again = env.reset(seed=7)[0]["policy"].cpu().numpy()
    np.testing.assert_array_equal(first, again)
    other = lapwarp.make("Reach", num_envs=4, device=device, seed=8).get_observations()["policy"].cpu().numpy()
    assert not np.allclose(first, other)


def test_time_limit_truncates_and_resets(device):
    env = lapwarp.make("Reach", num_envs=3, device=device, max_episode_steps=4)
    for i in range(4):
        before = env.get_observations()["policy"].clone()
        _, _, done, extras = env.step(torch.zeros(3, 3, device=env.device))
        assert env.episode_length_buf.tolist() == ([i + 1] * 3 if i < 3 else [0] * 3)
    assert done.all() and extras["time_outs"].all()
    # zero actions keep the end effector still, so a changed target proves the auto-reset re-randomised
    assert not torch.allclose(before[:, 3:], env.get_observations()["policy"][:, 3:])


def test_success_terminates_only_that_env(device):
    env = lapwarp.make("Reach", num_envs=3, device=device)
    ee, target = positions(env)
    target[1] = ee[1] + np.array([0.001, 0.0, 0.0])
    set_positions(env, ee, target)
    obs_before = env.get_observations()["policy"].cpu().numpy()
    obs, reward, done, extras = env.step(torch.zeros(3, 3, device=env.device))
    assert done.cpu().tolist() == [False, True, False]
    assert not extras["time_outs"].any()  # a success is a termination, never a time-out
    assert float(reward[1]) > 99.0
    after = obs["policy"].cpu().numpy()
    np.testing.assert_allclose(after[[0, 2]], obs_before[[0, 2]], atol=1e-6)  # untouched envs
    assert not np.allclose(after[1], obs_before[1])  # env 1 was reset
    assert float(extras["log"]["/episode/success"]) == 1.0


def test_actions_of_one_env_never_change_another(device):
    env_a = lapwarp.make("Reach", num_envs=4, device=device, seed=3)
    env_b = lapwarp.make("Reach", num_envs=4, device=device, seed=3)
    gen = torch.Generator().manual_seed(0)
    for _ in range(5):
        actions = torch.rand(4, 3, generator=gen) * 2 - 1
        other = actions.clone()
        other[2] = -other[2]  # only env 2 differs
        obs_a = env_a.step(actions.to(env_a.device))[0]["policy"]
        obs_b = env_b.step(other.to(env_b.device))[0]["policy"]
    diff = (obs_a - obs_b).abs().sum(dim=1).cpu().numpy()
    assert diff[2] > 0 and np.all(diff[[0, 1, 3]] == 0)


def test_batch_of_identical_envs_equals_single_env(device):
    single = lapwarp.make("Reach", num_envs=1, device=device, randomize_start=False)
    batch = lapwarp.make("Reach", num_envs=3, device=device, randomize_start=False)
    ee = np.array([[0.0, 0.045, 0.0]])
    target = np.array([[0.05, 0.1, -0.08]])
    set_positions(single, ee, target)
    set_positions(batch, np.repeat(ee, 3, 0), np.repeat(target, 3, 0))
    actions = torch.tensor([[0.3, -0.7, 0.9]])
    for _ in range(6):
        o1, r1, _, _ = single.step(actions.to(single.device))
        o3, r3, _, _ = batch.step(actions.repeat(3, 1).to(batch.device))
    for k in range(3):
        torch.testing.assert_close(o3["policy"][k], o1["policy"][0], rtol=0, atol=0)
        torch.testing.assert_close(r3[k], r1[0], rtol=0, atol=0)


def test_frame_stack_newest_last(device):
    env = lapwarp.make("Reach", num_envs=2, device=device, frame_stack=3, privileged_critic=True)
    stack0 = env.get_observations()["policy"].cpu().numpy()
    assert stack0.shape == (2, 18)
    np.testing.assert_array_equal(stack0[:, 0:6], stack0[:, 12:18])  # a fresh reset repeats the first frame
    assert env.get_observations()["critic"].shape == (2, 30)
    env.step(torch.ones(2, 3, device=env.device))
    stack1 = env.get_observations()["policy"].cpu().numpy()
    np.testing.assert_array_equal(stack1[:, 0:12], stack0[:, 6:18])  # shifted towards the front
    ee, target = positions(env)
    np.testing.assert_allclose(stack1[:, 12:18], normalised(ee, target), atol=1e-5)


def test_final_observations_before_auto_reset(device):
    env = lapwarp.make("Reach", num_envs=2, device=device, max_episode_steps=2, frame_stack=2,
                       keep_final_observations=True)
    env.step(torch.zeros(2, 3, device=env.device))
    pre = env.get_observations()["policy"]
    obs, _, done, extras = env.step(torch.zeros(2, 3, device=env.device))
    assert done.all()
    final = extras["final_observations"]
    # zero actions: the final frame equals the previous one, and the stack shifted once
    torch.testing.assert_close(final[:, 0:6], pre[:, 6:12])
    torch.testing.assert_close(final[:, 6:12], pre[:, 6:12])
    assert not torch.allclose(obs["policy"], final)
    torch.testing.assert_close(obs["policy"][:, 0:6], obs["policy"][:, 6:12])


def run_expert_episode(env) -> tuple[np.ndarray, np.ndarray]:
    """Run the expert until every env finished one episode; return (initial L1 distances, success flags)."""
    ee, target = positions(env)
    l1 = np.abs(target - ee).sum(axis=1)
    expert = ReachExpert(env)
    finished = torch.zeros(env.num_envs, dtype=torch.bool)
    succeeded = torch.zeros(env.num_envs, dtype=torch.bool)
    for _ in range(env.max_episode_length):
        _, _, done, extras = env.step(expert())
        new = done.cpu() & ~finished
        succeeded |= new & ~extras["time_outs"].cpu()
        finished |= done.cpu()
        if finished.all():
            break
    assert finished.all()
    return l1, succeeded.numpy()


def test_expert_solves_reach(device):
    env = lapwarp.make("Reach", num_envs=128, device=device, seed=11)
    _, succeeded = run_expert_episode(env)
    assert succeeded.mean() >= 0.99, succeeded.mean()


def test_discrete_expert_solves_every_reachable_target(device):
    # Discrete actions move 1 mm per step along one axis, so within 500 steps only targets closer than
    # ~0.5 m in L1 distance can be reached (the paper's boxes allow up to 0.79 m): the expert must solve
    # all of those and cannot solve the others.
    env = lapwarp.make("Reach", num_envs=128, device=device, action_type="DISCRETE", seed=11)
    l1, succeeded = run_expert_episode(env)
    assert np.all(succeeded[l1 < 0.495]) and not np.any(succeeded[l1 > 0.505])
    assert succeeded.mean() >= 0.9


def test_discrete_action_table_moves(device):
    env = lapwarp.make("Reach", num_envs=7, device=device, action_type="DISCRETE")
    assert env.num_actions == 1
    ee = np.zeros((7, 3))
    set_positions(env, ee, np.full((7, 3), 0.1))
    env.step(torch.arange(7, device=env.device))
    ee1, _ = positions(env)
    step = 0.1 * 0.01  # 10 mm/s for 0.1 s
    expected = np.zeros((7, 3))
    for i in range(3):
        expected[2 * i, i] = step
        expected[2 * i + 1, i] = -step
    np.testing.assert_allclose(ee1, expected, atol=1e-6)  # row 6 is the no-op


@pytest.mark.parametrize("bad, match", [
    (torch.zeros(3, 2), r"expected actions of shape \(3, 3\), got \(3, 2\)"),
    (torch.zeros(3), r"expected actions of shape \(3, 3\), got \(3,\)"),
    (torch.zeros(3, 3, dtype=torch.int32), "floating point"),
])
def test_bad_action_shapes_and_dtypes_raise(device, bad, match):
    env = lapwarp.make("Reach", num_envs=3, device=device)
    with pytest.raises(ValueError, match=match):
        env.step(bad.to(env.device))


def test_nan_actions_raise_or_are_zeroed(device):
    env = lapwarp.make("Reach", num_envs=2, device=device)
    bad = torch.tensor([[0.0, float("nan"), 0.0], [0.0, 0.0, float("inf")]])
    with pytest.raises(ValueError, match="non-finite"):
        env.step(bad.to(env.device))
    env = lapwarp.make("Reach", num_envs=2, device=device, invalid_actions="zero")
    ee0, _ = positions(env)
    obs, reward, _, extras = env.step(bad.to(env.device))
    ee1, _ = positions(env)
    np.testing.assert_array_equal(ee0, ee1)  # the only non-zero components were non-finite: no motion
    assert torch.isfinite(obs["policy"]).all() and torch.isfinite(reward).all()
    assert float(extras["log"]["/action/nonfinite_fraction"]) == pytest.approx(1 / 3)


def test_out_of_range_actions_are_clipped_and_counted(device):
    env = lapwarp.make("Reach", num_envs=1, device=device)
    set_positions(env, np.zeros((1, 3)), np.full((1, 3), 0.1))
    _, _, _, extras = env.step(torch.tensor([[5.0, -5.0, 0.5]], device=env.device))
    ee1, _ = positions(env)
    np.testing.assert_allclose(ee1[0], [0.0035, -0.0035, 0.00175], atol=1e-6)
    assert float(extras["log"]["/action/clipped_fraction"]) == pytest.approx(2 / 3)


def test_config_errors_list_valid_choices():
    with pytest.raises(ValueError, match="valid keys.*sphere_radius"):
        lapwarp.make("Reach", num_envs=1, sphere_radus=0.01)
    with pytest.raises(ValueError, match="available tasks.*Reach"):
        lapwarp.make("Reech")
    with pytest.raises(ValueError, match="valid features"):
        lapwarp.make("Reach", reward_weights={"worspace_violation": 1.0})
    with pytest.raises(ValueError, match="observation_type"):
        lapwarp.make("Reach", observation_type="LIDAR")
    with pytest.raises(ValueError, match="outside the workspace"):
        lapwarp.make("Reach", target_low=(-0.3, -0.05, -0.15))
    assert "Reach" in lapwarp.list_tasks()


def test_episode_length_buf_assignment_keeps_device_buffer(device):
    env = lapwarp.make("Reach", num_envs=4, device=device, max_episode_steps=10)
    env.episode_length_buf = torch.tensor([0, 3, 8, 9])  # what rsl-rl does with init_at_random_ep_len
    _, _, done, extras = env.step(torch.zeros(4, 3, device=env.device))
    assert done.cpu().tolist() == [False, False, False, True]
    assert extras["time_outs"].cpu().tolist() == [False, False, False, True]


def test_unstable_env_is_reset_alone(device):
    env = lapwarp.make("Reach", num_envs=3, device=device)
    obs_before = env.get_observations()["policy"].clone()
    flags = np.array([0, 1, 0], dtype=np.int32)
    env.world.unstable.assign(wp.array(flags, dtype=wp.int32, device=env.wp_device))
    obs, reward, done, _ = env.step(torch.zeros(3, 3, device=env.device))
    assert done.cpu().tolist() == [False, True, False]
    assert float(reward[1]) == 0.0
    torch.testing.assert_close(obs["policy"][[0, 2]], obs_before[[0, 2]])
    assert env.world.unstable.numpy().tolist() == [0, 0, 0]  # the reset cleared the flag
