"""The env contract, checked for every registered task and both action types: a task is held to it the moment it
appears in ``lapwarp.list_tasks()``.

Per task: reset/step shapes and dtypes; observations inside the declared bounds; every feature logged by name and the
weighted features summing to the reward; the same seed giving the same episode; discrete action ``k`` moving exactly
like the continuous action ``env.discrete_actions[k]``; out-of-range, non-finite and wrongly shaped actions handled as
documented; gymnasium's ``check_env``; USD export; and the expert producing valid actions.
"""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest
import torch
from gymnasium.utils.env_checker import check_env

import lapwarp
from lapwarp.experts import make_expert

TASKS = lapwarp.list_tasks()
ACTION_TYPES = ("CONTINUOUS", "DISCRETE")
N = 3
STEPS = 12


def random_actions(env, gen: torch.Generator) -> torch.Tensor:
    """Actions spanning the whole action space: continuous components at and near the bounds, every discrete index."""
    if env.is_discrete:
        return torch.randint(0, 2 * env.action_dim + 1, (env.num_envs,), generator=gen)
    return (torch.rand(env.num_envs, env.num_actions, generator=gen) * 2.4 - 1.2).clamp(-1.0, 1.0)


@pytest.fixture(scope="module")
def envs(device):
    """One env per (task, action type), shared by the tests of this module (building compiles kernels)."""
    made = {}

    def get(task: str, action_type: str, **overrides):
        key = (task, action_type, tuple(sorted(overrides.items())))
        if key not in made:
            made[key] = lapwarp.make(task, num_envs=N, device=device, action_type=action_type, seed=11, **overrides)
        return made[key]

    return get


@pytest.mark.parametrize("action_type", ACTION_TYPES)
@pytest.mark.parametrize("task", TASKS)
def test_shapes_dtypes_bounds_and_reward_logging(envs, task, action_type):
    env = envs(task, action_type, privileged_critic=True)
    obs, _ = env.reset(seed=5)
    low, high = env.observation_bounds()
    assert obs["policy"].shape == (N, env.observation_dim) == (N, len(low)) and obs["policy"].dtype == torch.float32
    assert obs["critic"].shape == (N, env.critic_layout.size)
    assert env.discrete_actions.shape == (2 * env.action_dim + 1, env.action_dim)
    weights = torch.tensor([env.reward_weights[f] for f in env.reward_features])
    gen = torch.Generator().manual_seed(0)
    for _ in range(STEPS):
        obs, reward, done, extras = env.step(random_actions(env, gen))
        assert reward.shape == (N,) and reward.dtype == torch.float32
        assert done.shape == (N,) and done.dtype == torch.bool
        assert extras["time_outs"].shape == (N,) and extras["time_outs"].dtype == torch.bool
        policy = obs["policy"].cpu().numpy()
        assert np.all(np.isfinite(policy))
        assert np.all(policy >= low - 1e-5) and np.all(policy <= high + 1e-5), "observation outside its bounds"
        features = env.features.numpy() if env.device == "cpu" else env._t["features"].cpu().numpy()
        log = extras["log"]
        for i, name in enumerate(env.reward_features):
            assert float(log[f"/feature/{name}"]) == pytest.approx(features[:, i].mean(), abs=1e-6)
            assert float(log[f"/reward/{name}"]) == pytest.approx(features[:, i].mean() * float(weights[i]), abs=1e-4)
        stable = ~env._t["unstable"].bool().cpu()
        expected = torch.as_tensor(features) @ weights
        np.testing.assert_allclose(reward.cpu()[stable].numpy(), expected[stable].numpy(), rtol=1e-5, atol=1e-4)
        terms = sum(float(log[f"/reward/{name}"]) for name in env.reward_features)
        if bool(stable.all()):
            assert terms == pytest.approx(float(reward.mean()), rel=1e-4, abs=1e-4)


@pytest.mark.parametrize("action_type", ACTION_TYPES)
@pytest.mark.parametrize("task", TASKS)
def test_same_seed_same_episode(device, task, action_type):
    if device != "cpu":
        pytest.skip("bit-exact replay is a CPU property (GPU atomics may reorder float sums)")
    runs = []
    for _ in range(2):
        env = lapwarp.make(task, num_envs=2, device=device, action_type=action_type, seed=21)
        gen = torch.Generator().manual_seed(3)
        trace = [env.get_observations()["policy"].numpy().copy()]
        for _ in range(8):
            obs, reward, done, _ = env.step(random_actions(env, gen))
            trace += [obs["policy"].numpy().copy(), reward.numpy().copy(), done.numpy().copy()]
        runs.append(trace)
    for a, b in zip(*runs, strict=True):
        np.testing.assert_array_equal(a, b)


@pytest.mark.parametrize("task", TASKS)
def test_discrete_action_moves_like_its_continuous_row(device, task):
    discrete = lapwarp.make(task, num_envs=N, device=device, action_type="DISCRETE", seed=4)
    continuous = lapwarp.make(task, num_envs=N, device=device, seed=4)
    table = discrete.discrete_actions
    first = [e.get_observations()["policy"].cpu() for e in (continuous, discrete)]
    np.testing.assert_allclose(*first)
    gen = torch.Generator().manual_seed(8)
    for _ in range(6):
        index = torch.randint(0, table.shape[0], (N,), generator=gen)
        obs_d, rew_d, _, _ = discrete.step(index.to(discrete.device))
        obs_c, rew_c, _, _ = continuous.step(table[index.to(table.device)])
        np.testing.assert_allclose(obs_d["policy"].cpu(), obs_c["policy"].cpu(), atol=1e-6)
        np.testing.assert_allclose(rew_d.cpu(), rew_c.cpu(), atol=1e-5)


@pytest.mark.parametrize("task", TASKS)
def test_invalid_actions_are_handled_as_documented(envs, task):
    cont, disc = envs(task, "CONTINUOUS"), envs(task, "DISCRETE")
    nan = torch.zeros(N, cont.num_actions, device=cont.device)
    nan[1, 0] = float("nan")
    with pytest.raises(ValueError, match="non-finite"):
        cont.step(nan)
    with pytest.raises(ValueError, match="expected actions of shape"):
        cont.step(torch.zeros(N, cont.num_actions + 1, device=cont.device))
    with pytest.raises(ValueError, match="outside"):
        disc.step(torch.tensor([0, 2 * disc.action_dim + 1, 0], device=disc.device))
    with pytest.raises(ValueError, match="integer"):
        disc.step(torch.zeros(N, device=disc.device))
    # invalid_actions="zero": NaN components act as 0 and out-of-range indices as the no-op, both counted
    zeroing = lapwarp.make(task, num_envs=N, device=cont.device, invalid_actions="zero", seed=2)
    reference = lapwarp.make(task, num_envs=N, device=cont.device, seed=2)
    obs_z, _, _, extras = zeroing.step(nan)
    obs_r, _, _, _ = reference.step(torch.nan_to_num(nan))
    np.testing.assert_allclose(obs_z["policy"].cpu(), obs_r["policy"].cpu(), atol=1e-6)
    assert float(extras["log"]["/action/nonfinite_fraction"]) == pytest.approx(1.0 / (N * cont.num_actions))
    zero_disc = lapwarp.make(task, num_envs=N, device=cont.device, action_type="DISCRETE", invalid_actions="zero",
                             seed=2)
    fresh = lapwarp.make(task, num_envs=N, device=cont.device, seed=2)
    noop = 2 * zero_disc.action_dim
    obs_z, _, _, extras = zero_disc.step(torch.tensor([noop, -5, noop + 7], device=cont.device))
    obs_r, _, _, _ = fresh.step(torch.zeros(N, cont.num_actions, device=cont.device))  # the no-op is the zero action
    np.testing.assert_allclose(obs_z["policy"].cpu(), obs_r["policy"].cpu(), atol=1e-6)
    assert float(extras["log"]["/action/invalid_fraction"]) == pytest.approx(2.0 / N)


@pytest.mark.parametrize("action_type", ACTION_TYPES)
@pytest.mark.parametrize("task", TASKS)
def test_gymnasium_checker(device, task, action_type):
    env = gym.make(f"lapwarp/{task}-v0", device=device, action_type=action_type)
    check_env(env.unwrapped, skip_render_check=True)
    low, high = env.unwrapped.env.observation_bounds()
    np.testing.assert_array_equal(env.observation_space.low, low)
    np.testing.assert_array_equal(env.observation_space.high, high)


@pytest.mark.parametrize("task", TASKS)
def test_usd_export_and_expert(envs, task, tmp_path):
    pytest.importorskip("pxr")
    from lapwarp.usd import record_rollout, validate_usd

    for action_type in ACTION_TYPES:
        env = envs(task, action_type)
        expert = make_expert(env)
        actions = expert()
        if env.is_discrete:
            assert actions.shape == (N,) and not actions.dtype.is_floating_point
            assert bool(((actions >= 0) & (actions <= 2 * env.action_dim)).all())
        else:
            assert actions.shape == (N, env.num_actions) and bool((actions.abs() <= 1.0).all())
    path = record_rollout(envs(task, "CONTINUOUS"), make_expert(envs(task, "CONTINUOUS")), 3, tmp_path / "r.usda",
                          env_ids=(0, 2))
    assert validate_usd(path) == []
