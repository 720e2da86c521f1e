"""A faster pixel learner for rsl-rl's PPO (``train/ppo.py --fast-pixels``, issue #19).

Pixel PPO spends most of its time in the CNNs, not in the env (SearchForPoint RGB 64x64: the env alone steps 950k
env-steps/s, PPO trained at 75k). What this module changes, all inside rsl-rl's public extension points (a model
class named in the train config and a VecEnv wrapper), so rsl-rl itself is unchanged:

- ``Uint8Images``: the env's RGB images (float32 in [0, 1], made from the renderer's uint8 pixels, so the round trip
  is exact) are handed to rsl-rl as uint8; its rollout storage keeps the observation's dtype, so the buffer and every
  minibatch gather move 4x fewer bytes (4,096 envs x 32 steps of 64x64 RGB: 1.6 GB instead of 6.4 GB).
- ``FastCNNModel``: rsl-rl's ``CNNModel`` whose encoders run in channels-last memory order under bf16 autocast
  (tensor-core convolutions), taking uint8 or float images; the MLP heads and the distribution stay float32.
- ``SpaceToDepthConv``: the first convolution (NatureCNN's 8x8, stride 4, on 3 channels) computed as the equal 2x2,
  stride-1 convolution over 4x4 pixel blocks (48 channels), the uint8 image converted, rearranged and cast in one copy
  and the 1/255 scale folded into the weights. cuDNN ran the 3-channel convolution with a non-tensor-core kernel plus
  a channel-padding pass (H100 profile, Reach RGB: 108 ms and 44 ms of a 486 ms update); 48 channels suit its
  implicit-GEMM kernels. The parameters are the original convolution's (same names and shapes).
- cuDNN's algorithm search for the convolutions (``cudnn.benchmark``) and TF32 matmuls. Measured (H100, Reach RGB,
  before these two settings were added): 1.40x PPO throughput, 109.8k vs 78.3k env-steps/s; see RESULTS.md.
- ``--shared-encoder`` (``use_shared_encoder``): one image encoder for the actor and the critic, run once per batch.
  rsl-rl's own ``share_cnn_encoders`` shares the parameters but still runs the encoder for the actor and again for the
  critic (forward and backward), and puts the shared parameters into its optimizer twice, so Adam steps them twice
  per update (twice the encoder's learning rate; torch warns "duplicate parameters"). Here the critic takes the
  latent the actor has just computed from the same observation tensor (``LatentCache``), the encoder's parameters
  belong to the actor alone (in the optimizer once, clipped with the actor's gradients), and only the policy loss
  trains the encoder: the critic's head reads the features detached (as in DrQ and SAC-AE, where the actor instead
  reads the critic's). See ``FastCNNModel`` for why.

Depth images are not quantised (``Uint8Images`` only converts RGB observations).
"""

from __future__ import annotations

import weakref

import torch
import torch.nn.functional as F
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


def _version(tensor: torch.Tensor) -> int:
    """The tensor's in-place version counter (-1 for an inference tensor, which has none: it cannot be changed in
    place outside inference mode, and rsl-rl changes no observation between the actor's and the critic's call)."""
    try:
        return tensor._version
    except RuntimeError:
        return -1


class LatentCache:
    """The last encoder output of a shared encoder, handed from the model that computed it to the other one.

    An entry is taken at most once, and only by the other model, for the same observation tensor (the same object,
    unchanged in place), the same encoder parameters (unchanged by an optimizer step) and the same grad, inference and
    autocast modes; anything else recomputes. rsl-rl calls the actor and then the critic on one observation
    ``TensorDict`` in ``act`` and in every mini-batch of ``update`` (whose summed loss back-propagates once), and
    the critic alone in ``compute_returns`` (no entry then: the critic took the last one)."""

    def __init__(self):
        self._entry = None

    @staticmethod
    def _key(group: str, image: torch.Tensor, encoder: torch.nn.Module) -> tuple:
        return (group, _version(image), tuple(_version(p) for p in encoder.parameters()), torch.is_grad_enabled(),
                torch.is_inference_mode_enabled(), torch.is_autocast_enabled(image.device.type))

    @torch.compiler.disable  # Python bookkeeping: reads version counters, which torch.compile cannot trace
    def take(self, model: torch.nn.Module, group: str, image: torch.Tensor, encoder: torch.nn.Module):
        entry = self._entry
        if entry is None or entry[0] is model or entry[1]() is not image:
            return None
        if entry[2] != self._key(group, image, encoder):
            return None
        self._entry = None
        return entry[3]

    @torch.compiler.disable
    def put(self, model: torch.nn.Module, group: str, image: torch.Tensor, encoder: torch.nn.Module,
            latent: torch.Tensor) -> None:
        self._entry = (model, weakref.ref(image), self._key(group, image, encoder), latent)


class SpaceToDepthConv(torch.nn.Conv2d):
    """A strided convolution computed over pixel blocks: with kernel k = r * s and stride s (per dimension), the
    output at (p, q) sums the input's blocks (p + a, q + b), a, b < r, of s x s pixels, so it equals an r x r,
    stride-1 convolution over the image rearranged into blocks of C * s * s channels, with the weight rearranged to
    match. The input (uint8 pixels, or float) is cropped to the blocks the convolution reads, rearranged and cast to
    the autocast dtype in one copy, into channels-last memory; uint8 pixels are scaled by 1/255 through the weight
    (bf16 holds the integers 0-255 exactly). Shares the weight and bias of the convolution it replaces."""

    def __init__(self, conv: torch.nn.Conv2d):
        if not self.applies_to(conv):
            raise ValueError(f"not a space-to-depth convolution: {conv}")
        super().__init__(conv.in_channels, conv.out_channels, conv.kernel_size, conv.stride,
                         bias=conv.bias is not None, device=conv.weight.device, dtype=conv.weight.dtype)
        self.weight, self.bias = conv.weight, conv.bias

    @staticmethod
    def applies_to(conv: torch.nn.Module) -> bool:
        return (type(conv) is torch.nn.Conv2d and conv.groups == 1 and conv.dilation == (1, 1)
                and conv.padding == (0, 0) and conv.stride != (1, 1)
                and all(k % s == 0 for k, s in zip(conv.kernel_size, conv.stride, strict=True)))

    def block_weight(self, scale: float) -> torch.Tensor:
        """The weight over blocks: (O, C, r*s, r*s) -> (O, C*s*s, r, r), channel c*s*s + i*s + j holding pixel (i, j)
        of a block of channel c."""
        (kh, kw), (sh, sw) = self.kernel_size, self.stride
        o, c = self.weight.shape[:2]
        w = self.weight.view(o, c, kh // sh, sh, kw // sw, sw).permute(0, 1, 3, 5, 2, 4)
        return w.reshape(o, c * sh * sw, kh // sh, kw // sw) * scale

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        n, c, h, w = x.shape
        (kh, kw), (sh, sw) = self.kernel_size, self.stride
        if h < kh or w < kw:
            raise ValueError(f"a {h}x{w} image is smaller than the {kh}x{kw} kernel")
        bh, bw = (h - kh) // sh + kh // sh, (w - kw) // sw + kw // sw  # blocks read: out - 1 + r
        blocks = x[:, :, :bh * sh, :bw * sw].reshape(n, c, bh, sh, bw, sw).permute(0, 2, 4, 1, 3, 5)
        dtype = (torch.get_autocast_dtype(x.device.type) if torch.is_autocast_enabled(x.device.type)
                 else self.weight.dtype)
        packed = torch.empty(blocks.shape, dtype=dtype, device=x.device).copy_(blocks)
        packed = packed.view(n, bh, bw, c * sh * sw).permute(0, 3, 1, 2)  # NCHW shape, channels-last memory
        scale = 1.0 / 255.0 if x.dtype == torch.uint8 else 1.0
        return F.conv2d(packed, self.block_weight(scale), self.bias)


class FastCNNModel(CNNModel):
    """``CNNModel`` with channels-last, bf16-autocast encoders that accept uint8 images (scaled by 1/255). Given
    another model's ``cnns`` (rsl-rl's ``share_cnn_encoders``), the two models run the shared encoder once per
    observation (``LatentCache``); the model given them (the critic) borrows them without owning their parameters and
    reads their features without training them unless ``train_shared_encoder``. With rsl-rl's plain
    ``share_cnn_encoders`` plus a single encoder run, Reach RGB did not learn at all in 150 iterations (H100, 4,096
    envs: 0.1 % training success against 88.5 % with two encoders; detaching the critic's features alone did not
    help, 0.3 % on an H200): the encoder's gradient was clipped together with the value head's."""

    def __init__(self, *args, autocast_bf16: bool = True, train_shared_encoder: bool = False,
                 space_to_depth: bool = True, **kwargs):
        super().__init__(*args, **kwargs)
        self.autocast_bf16 = bool(autocast_bf16)
        if space_to_depth and kwargs.get("cnns") is None:  # a borrowed encoder is its owner's
            for encoder in self.cnns.values():
                if SpaceToDepthConv.applies_to(encoder[0]):
                    encoder._modules["0"] = SpaceToDepthConv(encoder[0])
        self.cnns.to(memory_format=torch.channels_last)
        self.detach_latent = False
        if kwargs.get("cnns") is not None:  # the critic given the actor's encoders: both now read one cache
            self.cnns.latent_cache = LatentCache()
            self.detach_latent = not train_shared_encoder
            # Borrowed, not owned: the encoders leave this model's parameters and state dict (the actor's hold
            # them). rsl-rl clips the actor's and the critic's gradient norms separately, and with the encoders
            # among the critic's parameters their gradient was scaled down with the value head's (hundreds of
            # times larger at the start), so the encoder hardly learned; its optimizer also held them twice.
            shared = self._modules.pop("cnns")
            object.__setattr__(self, "cnns", shared)

    def _encode(self, group: str, image: torch.Tensor) -> torch.Tensor:
        encoder = self.cnns[group]
        if isinstance(encoder[0], SpaceToDepthConv):
            x = image  # the stem converts, scales and lays the pixels out itself
        else:
            x = image.float().mul_(1.0 / 255.0) if image.dtype == torch.uint8 else image.float()
            x = x.contiguous(memory_format=torch.channels_last)
        with torch.autocast(device_type=x.device.type, dtype=torch.bfloat16, enabled=self.autocast_bf16 and x.is_cuda):
            return encoder(x)

    def get_latent(self, obs: TensorDict, masks=None, hidden_state=None) -> torch.Tensor:
        cache = getattr(self.cnns, "latent_cache", None)
        latents = []
        for group in self.obs_groups_2d:
            image, encoder = obs[group], self.cnns[group]
            latent = cache.take(self, group, image, encoder) if cache is not None else None
            if latent is None:
                latent = self._encode(group, image)
                if cache is not None:
                    cache.put(self, group, image, encoder, latent)
            latents.append(latent.detach() if self.detach_latent else latent)
        latent_cnn = torch.cat(latents, dim=-1).float()
        if not self.obs_groups:
            return latent_cnn
        return torch.cat([super(CNNModel, self).get_latent(obs), latent_cnn], dim=-1)


def use_fast_pixels(train_cfg: dict, space_to_depth: bool = True) -> dict:
    """Switch the image models of a config made by ``ppo.use_images`` to ``FastCNNModel`` (first convolution over
    pixel blocks unless not ``space_to_depth``), and let cuDNN time its convolution algorithms for the (fixed) rollout
    and minibatch shapes and float32 matmuls use TF32 (process-wide settings; both are off in PyTorch by default)."""
    torch.backends.cudnn.benchmark = True
    torch.backends.cuda.matmul.allow_tf32 = True
    for role in ("actor", "critic"):
        if train_cfg[role]["class_name"] == "CNNModel":
            train_cfg[role]["class_name"] = FastCNNModel
            train_cfg[role]["space_to_depth"] = space_to_depth
    return train_cfg


def use_shared_encoder(train_cfg: dict) -> dict:
    """One encoder for the actor and the critic (after ``use_fast_pixels``; the critic must read the images), run
    once per batch."""
    if train_cfg["critic"]["class_name"] is not FastCNNModel or train_cfg["actor"]["class_name"] is not FastCNNModel:
        raise ValueError("a shared encoder needs the fast CNN models for both the actor and the critic "
                         "(--fast-pixels, with the critic reading the images)")
    train_cfg["algorithm"]["share_cnn_encoders"] = True
    return train_cfg
