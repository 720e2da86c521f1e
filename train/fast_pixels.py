"""A faster pixel learner for rsl-rl's PPO (``train/ppo.py --fast-pixels``, issue #19).

Pixel PPO spends most of its time in the CNNs, not in the env (SearchForPoint RGB 64x64: the env alone steps 950k
env-steps/s, PPO trained at 75k). What this module changes, all inside rsl-rl's public extension points (a model
class named in the train config and a VecEnv wrapper), so rsl-rl itself is unchanged:

- ``Uint8Images``: the env's RGB images (float32 in [0, 1], made from the renderer's uint8 pixels, so the round trip
  is exact) are handed to rsl-rl as uint8; its rollout storage keeps the observation's dtype, so the buffer and every
  minibatch gather move 4x fewer bytes (4,096 envs x 32 steps of 64x64 RGB: 1.6 GB instead of 6.4 GB).
- ``FastCNNModel``: rsl-rl's ``CNNModel`` whose encoders run in channels-last memory order under bf16 autocast
  (tensor-core convolutions), taking uint8 or float images; the MLP heads and the distribution stay float32.
- cuDNN's algorithm search for the convolutions (``cudnn.benchmark``) and TF32 matmuls. Measured (H100, Reach RGB,
  before these two settings were added): 1.40x PPO throughput, 109.8k vs 78.3k env-steps/s; see RESULTS.md.

Depth images are not quantised (``Uint8Images`` only converts RGB observations).
"""

from __future__ import annotations

import torch
from rsl_rl.models import CNNModel
from tensordict import TensorDict


class Uint8Images:
    """VecEnv wrapper that returns the ``image`` group as uint8 (exact for RGB). Everything else is the env's."""

    def __init__(self, env):
        if env.cfg.observation_type != "RGB":
            raise ValueError(f"uint8 image storage is exact only for RGB observations, got {env.cfg.observation_type}")
        self.env = env

    def __getattr__(self, name):
        return getattr(self.env, name)

    @property
    def episode_length_buf(self) -> torch.Tensor:
        return self.env.episode_length_buf

    @episode_length_buf.setter
    def episode_length_buf(self, value: torch.Tensor) -> None:
        self.env.episode_length_buf = value

    @staticmethod
    def _convert(obs: TensorDict) -> TensorDict:
        obs["image"] = obs["image"].mul(255.0).round_().to(torch.uint8)
        return obs

    def get_observations(self) -> TensorDict:
        return self._convert(self.env.get_observations())

    def step(self, actions: torch.Tensor):
        obs, rewards, dones, extras = self.env.step(actions)
        return self._convert(obs), rewards, dones, extras


class FastCNNModel(CNNModel):
    """``CNNModel`` with channels-last, bf16-autocast encoders that accept uint8 images (scaled by 1/255)."""

    def __init__(self, *args, autocast_bf16: bool = True, **kwargs):
        super().__init__(*args, **kwargs)
        self.autocast_bf16 = bool(autocast_bf16)
        self.cnns.to(memory_format=torch.channels_last)

    def get_latent(self, obs: TensorDict, masks=None, hidden_state=None) -> torch.Tensor:
        latents = []
        for group in self.obs_groups_2d:
            image = obs[group]
            image = image.float().mul_(1.0 / 255.0) if image.dtype == torch.uint8 else image.float()
            image = image.contiguous(memory_format=torch.channels_last)
            with torch.autocast(device_type=image.device.type, dtype=torch.bfloat16,
                                enabled=self.autocast_bf16 and image.is_cuda):
                latents.append(self.cnns[group](image))
        latent_cnn = torch.cat(latents, dim=-1).float()
        if not self.obs_groups:
            return latent_cnn
        return torch.cat([super(CNNModel, self).get_latent(obs), latent_cnn], dim=-1)


def use_fast_pixels(train_cfg: dict) -> dict:
    """Switch the image models of a config made by ``ppo.use_images`` to ``FastCNNModel``, and let cuDNN time its
    convolution algorithms for the (fixed) rollout and minibatch shapes and float32 matmuls use TF32 (process-wide
    settings; both are off in PyTorch by default)."""
    torch.backends.cudnn.benchmark = True
    torch.backends.cuda.matmul.allow_tf32 = True
    for role in ("actor", "critic"):
        if train_cfg[role]["class_name"] == "CNNModel":
            train_cfg[role]["class_name"] = FastCNNModel
    return train_cfg
