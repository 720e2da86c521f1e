"""gymnasium adapters of the batched envs (the batched env itself already is an ``rsl_rl`` VecEnv).

* ``LapwarpGymEnv``: a single-env ``gymnasium.Env`` (``gymnasium.make("lapwarp/Reach-v0")``).
* ``LapwarpVectorEnv``: a ``gymnasium.vector.VectorEnv`` over one batched env, with gymnasium's
  SAME_STEP autoreset (the returned observation of a finished env is its first one of the next episode;
  the final one is in ``infos["final_obs"]``). Both return NumPy arrays, as gymnasium expects; use the
  batched env directly for zero-copy torch tensors on the GPU.
"""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np
import torch
from gymnasium.vector import AutoresetMode, VectorEnv

from lapwarp.env import BatchedEnv
from lapwarp.registry import make


def _spaces(env: BatchedEnv) -> tuple[gym.spaces.Space, gym.spaces.Space]:
    if env.cfg.proprioception:
        # a Box space holds one group; the proprio group would be dropped without a word
        raise ValueError("proprioception=True adds a second observation group, which the gymnasium adapters (one Box "
                         "observation) do not return; use the batched env (lapwarp.make) and its TensorDict groups")
    low, high = (0.0, 1.0) if env.uses_images else env.observation_bounds()
    obs_space = gym.spaces.Box(low=np.float32(low), high=np.float32(high), shape=env.observation_shape,
                               dtype=np.float32)
    if env.is_discrete:
        act_space = gym.spaces.Discrete(2 * env.action_dim + 1)
    else:
        act_space = gym.spaces.Box(low=-1.0, high=1.0, shape=(env.action_dim,), dtype=np.float32)
    return obs_space, act_space


class LapwarpGymEnv(gym.Env):
    """One lapwarp scene as a ``gymnasium.Env``.

    Args:
        task: task name (see ``lapwarp.list_tasks()``).
        device: Warp device; "cpu" by default (one scene gains nothing from a GPU).
        render_mode: None, or "rgb_array": ``render()`` returns the scene as an ``(H, W, 3)`` uint8 image drawn by
            the batched rasteriser (``render_size`` pixels, square).
        render_size: side of the ``render()`` image in pixels.
        **overrides: task config fields.
    """

    metadata = {"render_modes": ["rgb_array"]}

    def __init__(self, task: str = "Reach", device: str = "cpu", render_mode: str | None = None,
                 render_size: int = 256, **overrides: Any):
        if render_mode not in (None, "rgb_array"):
            raise ValueError(f"render_mode={render_mode!r} is not supported; choose None or 'rgb_array'")
        self.env = make(task, num_envs=1, device=device, keep_final_observations=True, **overrides)
        self.observation_space, self.action_space = _spaces(self.env)
        self.render_mode = render_mode
        self.render_size = int(render_size)
        self.metadata = {"render_modes": ["rgb_array"], "render_fps": 1.0 / self.env.dt}

    def render(self):
        """The scene as an ``(H, W, 3)`` uint8 image (``render_mode="rgb_array"``), else None."""
        if self.render_mode != "rgb_array":
            return None
        image = self.env.render_rgb(self.render_size, self.render_size)[0]
        return image.permute(1, 2, 0).cpu().numpy()

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        obs, _ = self.env.reset(seed=seed)
        return obs[self.env.policy_group][0].cpu().numpy(), {}

    def step(self, action):
        if self.env.is_discrete:
            batch = torch.as_tensor(np.asarray(action, dtype=np.int64).reshape(1))
        else:
            batch = torch.as_tensor(np.asarray(action, dtype=np.float32).reshape(1, -1))
        obs, reward, done, extras = self.env.step(batch.to(self.env.device))
        terminated = bool(self.env._t["terminated"][0])
        truncated = bool(extras["time_outs"][0])
        if terminated or truncated:
            # the batched env has already auto-reset; gymnasium wants the last observation of the episode
            observation = extras["final_observations"][0]
        else:
            observation = obs[self.env.policy_group][0]
        info = {"is_success": bool(self.env._t["success"][0])}
        return observation.cpu().numpy(), float(reward[0]), terminated, truncated, info


class LapwarpVectorEnv(VectorEnv):
    """``num_envs`` lapwarp scenes as a ``gymnasium.vector.VectorEnv`` (SAME_STEP autoreset)."""

    metadata = {"autoreset_mode": AutoresetMode.SAME_STEP}

    def __init__(self, task: str = "Reach", num_envs: int = 1, device: str = "cpu", **overrides: Any):
        self.env = make(task, num_envs=num_envs, device=device, keep_final_observations=True, **overrides)
        self.num_envs = num_envs
        self.single_observation_space, self.single_action_space = _spaces(self.env)
        self.observation_space = gym.vector.utils.batch_space(self.single_observation_space, num_envs)
        self.action_space = gym.vector.utils.batch_space(self.single_action_space, num_envs)
        self.metadata = {"autoreset_mode": AutoresetMode.SAME_STEP, "render_fps": 1.0 / self.env.dt}

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        obs, _ = self.env.reset(seed=seed)
        return obs[self.env.policy_group].cpu().numpy(), {}

    def step(self, actions):
        dtype = torch.int64 if self.env.is_discrete else torch.float32
        obs, reward, done, extras = self.env.step(torch.as_tensor(np.asarray(actions), dtype=dtype).to(self.env.device))
        terminated = self.env._t["terminated"].bool().cpu().numpy()
        truncated = extras["time_outs"].cpu().numpy()
        infos: dict[str, Any] = {"is_success": self.env._t["success"].bool().cpu().numpy()}
        if done.any():
            infos["final_obs"] = extras["final_observations"].cpu().numpy()
            infos["_final_obs"] = done.cpu().numpy()
        return obs[self.env.policy_group].cpu().numpy(), reward.cpu().numpy(), terminated, truncated, infos

    def close_extras(self, **kwargs: Any) -> None:
        self.env.close()
