"""gymnasium adapters: the single env passes gymnasium's checker; the VectorEnv batches and auto-resets."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

import lapwarp  # noqa: F401  (registers lapwarp/<Task>-v0)
from lapwarp.vecenv import LapwarpVectorEnv


@pytest.mark.parametrize("action_type", ["CONTINUOUS", "DISCRETE"])
def test_single_env_passes_gymnasium_checker(device, action_type):
    env = gym.make("lapwarp/Reach-v0", device=device, action_type=action_type)
    check_env(env.unwrapped, skip_render_check=True)
    obs, info = env.reset(seed=3)
    assert env.observation_space.contains(obs)
    obs2, _ = env.reset(seed=3)
    np.testing.assert_array_equal(obs, obs2)
    obs, reward, terminated, truncated, info = env.step(env.action_space.sample())
    assert isinstance(reward, float) and not terminated and not truncated and "is_success" in info


def test_single_env_returns_final_observation_on_truncation(device):
    env = gym.make("lapwarp/Reach-v0", device=device, max_episode_steps=3)
    obs, _ = env.reset(seed=0)
    zero = np.zeros(3, dtype=np.float32)
    for _ in range(3):
        last, _, terminated, truncated, _ = env.step(zero)
    assert truncated and not terminated
    np.testing.assert_allclose(last, obs, atol=1e-6)  # zero actions: the final observation is the first one


def test_vector_env_shapes_and_autoreset(device):
    venv = LapwarpVectorEnv("Reach", num_envs=4, device=device, max_episode_steps=2)
    obs, _ = venv.reset(seed=1)
    assert obs.shape == (4, 6) and venv.single_action_space.shape == (3,) and venv.action_space.shape == (4, 3)
    actions = np.zeros((4, 3), dtype=np.float32)
    venv.step(actions)
    obs2, reward, terminated, truncated, infos = venv.step(actions)
    assert reward.shape == (4,) and truncated.all() and not terminated.any()
    np.testing.assert_allclose(infos["final_obs"], obs, atol=1e-6)
    assert not np.allclose(obs2, obs)  # same-step autoreset drew new episodes
    venv.close()
