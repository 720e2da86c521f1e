"""BatchedEnv: the base of every task env; an ``rsl_rl.env.VecEnv`` over ``num_envs`` scenes.

It owns the env buffers (actions, reward features and their delta baselines, rewards, dones, episode counters,
observation frames and stacks) and the step pipeline. A task *declares* its reward features (``rewards``, a
``lapwarp.tasks.spec.RewardSpec``), its observation blocks and its action blocks; the base derives sizes, bounds,
the discrete action table, delta features, done flags and logging from them. The task fills in:

    _build()                      -> World (and the task's parts: instrument rig, objects, its own state arrays)
    _observation_layout()         STATE blocks and bounds (``ObservationSpec.layout``); ``_critic_layout()`` optional
    _action_layout()              ``ActionLayout`` of the continuous action     } default: the task's instrument
    _apply_actions(actions)       once per env step: actions -> commands        } rig ``self.rig``
    _before_physics_step()        once per physics step (frame skip)            } (``lapwarp.tasks.rig``)
    _compute_features(mask, out)  non-delta reward features of the masked envs (a pure function of the state)
    _update_task()                optional, after rewards and dones: events (a new target, restarting baselines)
    _reset_task(env_mask)         re-randomise the masked envs in place from the per-env RNG (writing ``world.state``
                                  rows; the base then saves them as the World's start state of those envs)
    _compute_observations()       the newest STATE frame ``obs_frame`` (and ``critic_frame``'s own blocks)
    _build_visual_scene()         optional: the ``VisualScene`` image observations, renders and USD read

One env step = action sanitising, ``frame_skip`` physics steps, features, deltas/reward/dones, task events, masked
auto-reset (World, task, then the reset envs' delta baselines from the features of their new state), observations
and frame stacks. On CUDA the whole step is captured once as a CUDA graph and replayed on torch's current stream, so
it runs without host syncs and orders naturally with the policy's torch work. Outputs are torch views of Warp arrays
(zero copy); ``step`` returns clones of them, because rsl-rl keeps references to observations across steps.
"""

from __future__ import annotations

import math
import os
from abc import abstractmethod
from typing import Any, ClassVar

import numpy as np
import torch
import warp as wp
from rsl_rl.env import VecEnv
from tensordict import TensorDict

from lapwarp import launching
from lapwarp.config import EnvConfig, build_config, check_num_envs, check_seed, resolve_device
from lapwarp.kernels import env_kernels
from lapwarp.tasks.spec import ActionLayout, ObservationLayout, RewardSpec
from lapwarp.world import World, check_hybrid_lanes


def float_rows(array: wp.array) -> wp.array:
    """A ``(num_envs, k)`` float32 view (no copy) of a contiguous env-major array of a float-based type (``float32``,
    ``vec3``, ``vec4``, ``transform``, ...), for element-wise checks of any per-env state."""
    if not array.is_contiguous:
        raise ValueError(f"checked state must be a contiguous array, got shape {array.shape} strides {array.strides}")
    scalar = getattr(array.dtype, "_wp_scalar_type_", array.dtype)
    if scalar is not wp.float32:
        raise ValueError(f"checked state must hold float32 values, got {array.dtype}")
    width = array.size // array.shape[0] * (wp.types.type_size_in_bytes(array.dtype) // 4)  # floats per env
    return wp.array(ptr=array.ptr, dtype=wp.float32, shape=(array.shape[0], width), device=array.device, copy=False)


def image_bytes(num_envs: int, cfg: EnvConfig, keep_final_observations: bool = False) -> int:
    """Device bytes of the image observation buffers of ``num_envs`` envs: the rasteriser's visibility buffer (8 bytes
    per pixel), RGB (3) and depth (4) targets, the float frame (4 per channel) and its frame stack and final copy."""
    height, width = cfg.image_shape
    channels = {"RGB": 3, "RGBD": 4, "DEPTH": 1}.get(cfg.observation_type, 0)
    stack = channels * cfg.frame_stack
    per_pixel = 8 + 3 + 4 + 4 * channels + (4 * stack if cfg.frame_stack > 1 else 0)
    per_pixel += 4 * stack if keep_final_observations else 0
    return num_envs * height * width * per_pixel


def available_memory(device: wp.context.Device) -> int | None:
    """Free memory of a Warp device in bytes (host: available physical memory), None where unknown."""
    if device.is_cuda:
        return int(device.free_memory)
    try:
        return int(os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE"))
    except (ValueError, OSError, AttributeError):
        return None


def check_image_memory(num_envs: int, cfg: EnvConfig, device: wp.context.Device, keep_final: bool) -> None:
    """Raise ``ValueError`` before anything is allocated when the image buffers would not fit in 90% of the device's
    free memory (the renderer's scene buffers come on top)."""
    need, free = image_bytes(num_envs, cfg, keep_final), available_memory(device)
    if free is not None and need > 0.9 * free:
        raise ValueError(f"image_shape={tuple(cfg.image_shape)} with {cfg.observation_type} and frame_stack="
                         f"{cfg.frame_stack} needs {need / 2**30:.2f} GiB of image buffers for {num_envs} envs, but "
                         f"{device.alias} has {free / 2**30:.2f} GiB free: use fewer envs or smaller images")


class BatchedEnv(VecEnv):
    """Base class of all lapwarp task envs (see the module docstring for what a task declares and provides).

    Args:
        cfg: the task's config dataclass.
        num_envs: number of parallel scenes.
        device: Warp/torch device, "cpu" or "cuda:N".
        use_cuda_graph: capture the env step as a CUDA graph on CUDA devices (default True).
        keep_final_observations: also keep the observation each env had when its episode ended, before
            the auto-reset, in ``extras["final_observations"]`` (gymnasium's semantics; costs one extra
            observation pass per step, so rsl-rl training leaves it off).
    """

    config_class: ClassVar[type[EnvConfig]] = EnvConfig
    task_name: ClassVar[str] = ""
    #: The task's reward features, weights, deltas and success/failure terms.
    rewards: ClassVar[RewardSpec | None] = None
    supported_observations: ClassVar[tuple[str, ...]] = ("STATE",)
    #: ``"module:Class"`` of the task's scripted expert (``lapwarp.experts.make_expert``), imported when asked for.
    expert: ClassVar[str | None] = None
    #: ``chain_block_links`` that ``-1`` (automatic) means on CUDA devices: blocks of this many links when the task's
    #: few long rods per env leave the one-thread-per-chain solve latency-bound (benchmarks/RESULTS.md), else 0.
    gpu_chain_block_links: ClassVar[int] = 0
    #: ``chain_solver`` that ``"auto"`` means on CUDA devices: the one the task's step measured fastest with
    #: (``EnvConfig.chain_solver`` lists them; benchmarks/RESULTS.md), else ``"thomas"``
    gpu_chain_solver: ClassVar[str] = "thomas"

    @classmethod
    def from_overrides(cls, num_envs: int = 1, device: str = "cpu", use_cuda_graph: bool = True,
                       keep_final_observations: bool = False, **overrides: Any):
        """Build the env from config keyword overrides (unknown keys raise ``ValueError``)."""
        return cls(build_config(cls.config_class, overrides), num_envs=num_envs, device=device,
                   use_cuda_graph=use_cuda_graph, keep_final_observations=keep_final_observations)

    def __init__(self, cfg: EnvConfig, num_envs: int = 1, device: str = "cpu", use_cuda_graph: bool = True,
                 keep_final_observations: bool = False):
        if not isinstance(cfg, self.config_class):
            raise TypeError(f"{type(self).__name__} needs a {self.config_class.__name__}, got {type(cfg).__name__}")
        num_envs = check_num_envs(num_envs)
        device = resolve_device(device)
        if self.rewards is None:
            raise TypeError(f"{type(self).__name__} declares no rewards (a lapwarp.tasks.spec.RewardSpec)")
        cfg.validate(self.rewards.names, self.supported_observations)
        wp.init()
        self.cfg = cfg
        self.num_envs = num_envs
        self.wp_device = wp.get_device(device)
        self.device = "cpu" if self.wp_device.is_cpu else f"cuda:{self.wp_device.ordinal}"
        self.max_episode_length = cfg.max_episode_steps
        self.dt = cfg.time_step * cfg.frame_skip  # simulated seconds per env step
        self.reward_weights = {**self._default_reward_weights(), **cfg.reward_weights}
        self.keep_final_observations = bool(keep_final_observations)
        self._visual_scene = None
        if cfg.observation_type != "STATE":
            check_image_memory(num_envs, cfg, self.wp_device, self.keep_final_observations)
        if self.chain_solver == "hybrid":
            check_hybrid_lanes(self.wp_device)  # before the build: the World would refuse only at its first step

        with wp.ScopedDevice(self.wp_device):
            self.world: World = self._build()
            self.world.chain_block_links = self.chain_block_links
            self.world.chain_solver = self.chain_solver
            self.obs_layout: ObservationLayout = self._observation_layout()
            # built even without the critic group: kernels take its columns as an argument of their declared type
            self.critic_layout: ObservationLayout = self._critic_layout()
            self.action_layout: ActionLayout = self._action_layout()
            self.action_dim = self.action_layout.size
            self.is_discrete = cfg.action_type == "DISCRETE"
            self.num_actions = 1 if self.is_discrete else self.action_dim
            self._allocate_buffers()
        self._use_cuda_graph = bool(use_cuda_graph) and self.wp_device.is_cuda
        self._graph = None
        self._torch_streams: dict[int, wp.Stream] = {}
        self.reset()

    # ------------------------------------------------------------------ what a task provides
    @abstractmethod
    def _build(self) -> World:
        """Build the scene: return the World and allocate the task's parts and state arrays."""

    @abstractmethod
    def _observation_layout(self) -> ObservationLayout:
        """The STATE observation blocks of this configuration (``ObservationSpec.layout``)."""

    def _critic_layout(self) -> ObservationLayout:
        """The privileged critic blocks (only with ``privileged_critic``); the policy layout by default. A critic
        layout made by ``obs_layout.extend(...)`` starts with the policy's values, which the base copies in."""
        return self.obs_layout

    def _action_layout(self) -> ActionLayout:
        """The continuous action's blocks; by default those of the task's instrument rig (``self.rig``)."""
        return self.rig.action_layout

    def _default_reward_weights(self) -> dict[str, float]:
        """Default weight per feature (Table A); a task whose weights depend on its config overrides this."""
        return self.rewards.default_weights()

    def _apply_actions(self, actions: wp.array2d) -> None:
        """Turn sanitised normalised actions ``(num_envs, action_dim)`` into per-physics-step commands; by default the
        instrument rig's (``self.rig``)."""
        self.rig.apply_actions(actions, self.cfg.time_step)

    def _before_physics_step(self) -> None:
        """Per physics step (frame skip) work before ``World.step``: move the instrument rig if the task has one."""
        rig = getattr(self, "rig", None)
        if rig is not None:
            rig.step()

    @abstractmethod
    def _compute_features(self, env_mask: wp.array, features_out: wp.array2d) -> None:
        """Write the non-delta features of the envs whose ``env_mask`` entry is non-zero into ``features_out``
        ``(num_envs, F)`` (columns ``self.rewards.F.<NAME>``); a pure function of the state, also used on freshly
        reset envs to start their delta baselines. Delta columns are filled by the base."""

    def _checked_state(self) -> list[wp.array]:
        """Per-env task state (env-major, contiguous arrays of float-based types) checked for NaN/inf after every
        physics step: an env with one is flagged unstable, ends this step and is reset alone, so a fault never reaches
        the observations of any env. Default: the instrument rig's PTSD and tip poses; tasks add their own state.
        The World checks its particles itself."""
        rig = getattr(self, "rig", None)
        return [rig.state.ptsd, rig.state.pose] if rig is not None else []

    def _update_task(self) -> None:
        """After features, reward and dones of a step: task events (a new active target...), which may restart delta
        baselines by writing ``self.baselines[env, F.<BASE>]``. Nothing by default."""

    @abstractmethod
    def _reset_task(self, env_mask: wp.array) -> None:
        """Re-randomise the task state of the envs whose ``env_mask`` entry is non-zero (after ``World.reset``)."""

    @abstractmethod
    def _compute_observations(self) -> None:
        """Write the newest ``obs_frame`` (and ``critic_frame`` with ``privileged_critic``)."""

    def _build_visual_scene(self):
        """The ``lapwarp.visuals.VisualScene`` of this task (built once, on first use)."""
        raise ValueError(f"{type(self).__name__} does not describe its visuals yet")

    def update_visuals(self) -> None:
        """Bring the per-env visual transforms/points of ``visual_scene()`` up to date (launches only)."""

    def _draw_overlays(self, rgb: wp.array, fov_deg: float) -> None:
        """Draw 2-D overlays (sofa_env's image markers) into freshly rendered images: ``rgb`` is uint8 ``(num_envs,
        3, H, W)``, ``fov_deg`` the camera's vertical field of view. Launches only; nothing by default."""

    def visual_scene(self):
        """The ``lapwarp.visuals.VisualScene`` renderers and exporters draw (camera and objects), built on first use."""
        if self._visual_scene is None:
            with wp.ScopedDevice(self.wp_device):
                self._visual_scene = self._build_visual_scene()
                self.update_visuals()
        return self._visual_scene

    # ------------------------------------------------------------------ derived from the declarations
    @property
    def log_keys(self) -> tuple[str, ...]:
        """Keys of ``extras["log"]`` in order (``/contact/overflow_fraction`` only for tasks with contact systems)."""
        return tuple(self._log_keys)

    @property
    def reward_features(self) -> tuple[str, ...]:
        """Feature names in column order."""
        return self.rewards.names

    @property
    def discrete_actions(self) -> torch.Tensor:
        """``(2d + 1, d)`` table on the env's device: discrete action ``k`` moves exactly like the continuous action
        ``discrete_actions[k]`` (rows ``2i``/``2i+1`` = +-one discrete step along component ``i``, last = no-op)."""
        return torch.as_tensor(self.action_layout.discrete_table(), device=self.device)

    def observation_bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """``(low, high)`` of every value of the STATE ``policy`` observation (frames included), float32."""
        s = self.cfg.frame_stack
        return np.tile(self.obs_layout.low, s), np.tile(self.obs_layout.high, s)

    # ------------------------------------------------------------------ buffers
    def _allocate_buffers(self) -> None:
        n, dev = self.num_envs, self.wp_device
        self.actions_in = wp.zeros((n, self.action_dim), dtype=wp.float32, device=dev)
        self.actions = wp.zeros((n, self.action_dim), dtype=wp.float32, device=dev)
        self.discrete_in = wp.zeros(n, dtype=wp.int64, device=dev)
        if self.is_discrete:
            self.action_table = wp.array(self.action_layout.discrete_table(), dtype=wp.float32, device=dev)
        self.nonfinite_actions = wp.zeros(n, dtype=wp.int32, device=dev)
        self.clipped_actions = wp.zeros(n, dtype=wp.int32, device=dev)

        spec = self.rewards
        self.features = wp.zeros((n, spec.size), dtype=wp.float32, device=dev)
        #: ``(num_envs, F)`` delta baselines, by the column of the feature they are the change of.
        self.baselines = wp.zeros((n, spec.size), dtype=wp.float32, device=dev)
        weights = np.array([self.reward_weights.get(f, 0.0) for f in spec.names], dtype=np.float32)
        self.weights = wp.array(weights, dtype=wp.float32, device=dev)
        deltas = np.asarray(spec.deltas, dtype=np.int32).reshape(-1, 2)
        self._delta_columns = wp.array(deltas[:, 0].copy(), dtype=wp.int32, device=dev)
        self._delta_bases = wp.array(deltas[:, 1].copy(), dtype=wp.int32, device=dev)
        self._all_envs = wp.ones(n, dtype=wp.int32, device=dev)
        # extras["log"]: weighted and raw feature means, episode statistics, action checks (env_kernels.reduce_log)
        self._log_keys = [f"/reward/{f}" for f in spec.names] + [f"/feature/{f}" for f in spec.names] + [
            "/episode/success", "/episode/return", "/episode/length", "/env/unstable_fraction",
            *(("/action/invalid_fraction",) if self.is_discrete else
              ("/action/nonfinite_fraction", "/action/clipped_fraction"))]
        self._state_rows = [float_rows(a) for a in self._checked_state()]
        # contact systems' record buffers (ContactSystem.overflow): a full buffer is counted, never silent. Each ORs its
        # flags into contact_overflow itself at every world step's end (ContactSystem.overflow_sink)
        #: ``(num_envs,)`` int32: 1 where a contact system of the env ran out of record capacity in the last step.
        self.contact_overflow = wp.zeros(n, dtype=wp.int32, device=dev)
        self._overflow_term = -1
        for solver in self.world.solvers:
            if hasattr(solver, "overflow_sink"):
                solver.overflow_sink = self.contact_overflow
                self._overflow_term = len(self._log_keys)
        if self._overflow_term >= 0:
            self._log_keys.append("/contact/overflow_fraction")
        self.log_values = wp.zeros(len(self._log_keys), dtype=wp.float32, device=dev)
        self._log_sums = wp.zeros(len(self._log_keys) + 1, dtype=wp.float32, device=dev)
        self.success = wp.zeros(n, dtype=wp.int32, device=dev)
        self.failure = wp.zeros(n, dtype=wp.int32, device=dev)
        self.reward = wp.zeros(n, dtype=wp.float32, device=dev)
        self.terminated = wp.zeros(n, dtype=wp.int32, device=dev)
        self.truncated = wp.zeros(n, dtype=wp.int32, device=dev)
        self.done = wp.zeros(n, dtype=wp.int32, device=dev)
        self.reset_mask = wp.zeros(n, dtype=wp.int32, device=dev)
        self.episode_length = wp.zeros(n, dtype=wp.int32, device=dev)
        self.episode_return = wp.zeros(n, dtype=wp.float32, device=dev)
        self.last_episode_success = wp.zeros(n, dtype=wp.int32, device=dev)
        self.finished_episodes = wp.zeros(n, dtype=wp.int32, device=dev)
        self.last_episode_return = wp.zeros(n, dtype=wp.float32, device=dev)
        self.last_episode_length = wp.zeros(n, dtype=wp.int32, device=dev)

        stack = self.cfg.frame_stack
        self.obs_frame = wp.zeros((n, self.obs_layout.size), dtype=wp.float32, device=dev)
        self.obs_stack = self.obs_frame if stack == 1 else wp.zeros(
            (n, stack * self.obs_layout.size), dtype=wp.float32, device=dev)
        policy_names = self.obs_layout.names
        self._critic_has_policy_prefix = (self.critic_layout.names[:len(policy_names)] == policy_names
                                          and self.critic_layout.sizes[:len(policy_names)] == self.obs_layout.sizes)
        if self.cfg.privileged_critic:
            self.critic_frame = wp.zeros((n, self.critic_layout.size), dtype=wp.float32, device=dev)
            self.critic_stack = self.critic_frame if stack == 1 else wp.zeros(
                (n, stack * self.critic_layout.size), dtype=wp.float32, device=dev)
        else:
            self.critic_frame = self.obs_frame  # kernels may write it unconditionally; nothing reads it
        self.uses_images = self.cfg.observation_type != "STATE"
        if self.uses_images:
            self._allocate_image_buffers()
        policy_stack = self.image_stack if self.uses_images else self.obs_stack
        if self.keep_final_observations:
            self.final_obs = wp.zeros_like(policy_stack)

        # zero-copy torch views of the buffers users and rsl-rl read
        self._t = {name: wp.to_torch(getattr(self, name)) for name in (
            "actions_in", "discrete_in", "features", "weights", "reward", "terminated", "truncated", "done",
            "episode_length", "success", "last_episode_success", "finished_episodes", "last_episode_return",
            "last_episode_length", "nonfinite_actions", "clipped_actions", "obs_stack")}
        self._t["log"] = wp.to_torch(self.log_values)
        if self.uses_images:
            self._t["image_stack"] = wp.to_torch(self.image_stack)
        self._t["unstable"] = wp.to_torch(self.world.unstable)
        if self.keep_final_observations:
            self._t["final_obs"] = wp.to_torch(self.final_obs)
        if self.cfg.privileged_critic:
            self._t["critic_stack"] = wp.to_torch(self.critic_stack)
        if self.cfg.proprioception:
            self._setup_proprioception()

    def _setup_proprioception(self) -> None:
        """The ``proprio`` group's source (the rig's PTSD, a zero-copy view) and its map from each instrument's state
        limits (deg, deg, deg, m) to [-1, 1] about their midpoint; a component whose limits coincide reads 0."""
        rig = getattr(self, "rig", None)  # (a STATE observation with it was refused by the config's validate)
        if rig is None:
            raise ValueError(f"{type(self).__name__} has no instrument rig to read (proprioception=True)")
        to_rad = np.array([math.pi / 180.0] * 3 + [1.0])
        low = np.concatenate([np.asarray(spec.tpsd.state_low, np.float64) * to_rad for spec in rig.specs])
        high = np.concatenate([np.asarray(spec.tpsd.state_high, np.float64) * to_rad for spec in rig.specs])
        span = high - low
        self._proprio_mid = torch.as_tensor(0.5 * (low + high), dtype=torch.float32, device=self.device)
        self._proprio_scale = torch.as_tensor(np.divide(2.0, span, out=np.zeros_like(span), where=span > 0.0),
                                              dtype=torch.float32, device=self.device)
        self._t["ptsd"] = wp.to_torch(rig.ptsd)

    def _allocate_image_buffers(self) -> None:
        """Camera, image frame ``(N, C, H, W)`` in [0, 1] and its stack ``(N, S*C, H, W)`` (newest last)."""
        from lapwarp.scene_render import SceneRenderer  # the rasteriser compiles only for image tasks

        n, dev = self.num_envs, self.wp_device
        height, width = self.cfg.image_shape
        self.image_channels = {"RGB": 3, "RGBD": 4, "DEPTH": 1}[self.cfg.observation_type]
        self.camera = SceneRenderer(self.visual_scene(), n, width, height, dev, outputs=("rgb", "depth"))
        self._camera_rgb = wp.from_torch(self.camera.rgb)
        self._camera_depth = wp.from_torch(self.camera.depth)
        c, s = self.image_channels, self.cfg.frame_stack
        self.image_frame = wp.zeros((n, c, height, width), dtype=wp.float32, device=dev)
        self.image_stack = self.image_frame if s == 1 else wp.zeros((n, s * c, height, width), dtype=wp.float32,
                                                                     device=dev)
        # the shading pass writes the frame itself unless the task draws overlays into the bytes after it
        self._frame_in_shading = type(self)._draw_overlays is BatchedEnv._draw_overlays
        if self._frame_in_shading:
            kind = self.cfg.observation_type
            self.camera.set_frame_output(self.image_frame, rgb=kind != "DEPTH", depth=kind != "RGB")

    def _observe_images(self, push_mode: int) -> None:
        self.update_visuals()
        self.camera.render()
        self._draw_overlays(self._camera_rgb, self.camera.scene.camera.fov_deg)
        if not self._frame_in_shading:
            kind = self.cfg.observation_type
            height, width = self.cfg.image_shape
            launching.launch(env_kernels.write_image_frame, dim=(self.num_envs, height, width),
                             inputs=[self._camera_rgb, self._camera_depth, int(kind != "DEPTH"), int(kind != "RGB"),
                                     1.0 / self.camera.scene.camera.far], outputs=[self.image_frame],
                             device=self.wp_device)
        if self.cfg.frame_stack > 1:
            flat = self.image_frame.reshape((self.num_envs, -1))
            launching.launch(env_kernels.push_observation_frame, dim=flat.shape,
                             inputs=[flat, self.reset_mask, self.cfg.frame_stack, int(push_mode)],
                             outputs=[self.image_stack.reshape((self.num_envs, -1))], device=self.wp_device)

    # ------------------------------------------------------------------ VecEnv API
    @property
    def episode_length_buf(self) -> torch.Tensor:
        """Steps taken in the current episode, per env (a view of the device buffer)."""
        return self._t["episode_length"]

    @episode_length_buf.setter
    def episode_length_buf(self, value: torch.Tensor) -> None:
        # rsl-rl assigns random lengths at start (init_at_random_ep_len): copy into our buffer, keep the view.
        self._t["episode_length"].copy_(torch.as_tensor(value).to(self._t["episode_length"]))

    @property
    def policy_group(self) -> str:
        """Name of the observation group the policy reads: ``policy`` (STATE) or ``image`` (camera types)."""
        return "image" if self.uses_images else "policy"

    def get_observations(self) -> TensorDict:
        """Current observation groups (clones): ``policy`` (STATE) or ``image`` ``(N, S*C, H, W)`` in [0, 1]
        (RGB / RGBD / DEPTH), ``critic`` (privileged state) with ``privileged_critic`` and ``proprio`` ``(N, 4 K)`` (the
        K instruments' PTSD in [-1, 1], the newest frame only) with ``proprioception``."""
        if self.uses_images:
            groups = {"image": self._t["image_stack"].clone()}
        else:
            groups = {"policy": self._t["obs_stack"].clone()}
        if self.cfg.privileged_critic:
            groups["critic"] = self._t["critic_stack"].clone()
        if self.cfg.proprioception:
            ptsd = self._t["ptsd"].reshape(self.num_envs, -1)
            groups["proprio"] = (ptsd - self._proprio_mid) * self._proprio_scale
        return TensorDict(groups, batch_size=[self.num_envs], device=self.device)

    def reset(self, seed: int | None = None) -> tuple[TensorDict, dict]:
        """Reset every env (re-seeding the device RNG streams first when ``seed`` is given)."""
        if seed is not None:
            self.world.seed_rng(check_seed(seed))
        with self._torch_stream_scope():
            launching.launch(env_kernels.fill_int_array, dim=self.num_envs, inputs=[1], outputs=[self.reset_mask],
                             device=self.wp_device)
            self._reset_and_observe()
            launching.launch(env_kernels.fill_int_array, dim=self.num_envs, inputs=[0], outputs=[self.reset_mask],
                             device=self.wp_device)
        return self.get_observations(), {}

    def step(self, actions: torch.Tensor) -> tuple[TensorDict, torch.Tensor, torch.Tensor, dict]:
        """Advance every env by one env step; finished envs are reset automatically (obs are post-reset).

        Args:
            actions: ``(num_envs, num_actions)`` floats in [-1, 1] (CONTINUOUS) or ``(num_envs,)`` /
                ``(num_envs, 1)`` integer indices in ``[0, 2 d]`` (DISCRETE).

        Returns:
            observations, rewards ``(num_envs,)``, dones ``(num_envs,)`` and extras with ``time_outs`` and
            ``log``: every weighted reward term under ``/reward/<feature>``, every raw feature under
            ``/feature/<feature>``, ``/episode/success`` and friends.
        """
        self._load_actions(actions)
        if self._use_cuda_graph:
            stream = self._torch_stream()
            if self._graph is None:
                with wp.ScopedCapture(device=self.wp_device) as capture:
                    self._step_launches()
                self._graph = capture.graph
            wp.capture_launch(self._graph, stream=stream)
        else:
            with self._torch_stream_scope():
                self._step_launches()
        return self._step_outputs()

    # ------------------------------------------------------------------ internals
    def _load_actions(self, actions: torch.Tensor) -> None:
        if not isinstance(actions, torch.Tensor):
            actions = torch.as_tensor(np.asarray(actions))
        if self.is_discrete:
            if actions.shape not in ((self.num_envs,), (self.num_envs, 1)):
                raise ValueError(f"expected discrete actions of shape ({self.num_envs},) or ({self.num_envs}, 1), "
                                 f"got {tuple(actions.shape)}")
            if actions.dtype.is_floating_point or actions.dtype == torch.bool or actions.dtype.is_complex:
                raise ValueError(f"discrete actions must be integer indices, got dtype {actions.dtype}")
            if self.cfg.invalid_actions == "raise":
                bad = ((actions < 0) | (actions > 2 * self.action_dim)).reshape(-1)
                if bool(bad.any()):
                    envs = bad.nonzero().flatten().tolist()[:10]
                    raise ValueError(f"discrete actions outside [0, {2 * self.action_dim}] in envs {envs}; pass "
                                     "invalid_actions='zero' to treat them as the no-op")
            self._t["discrete_in"].copy_(actions.reshape(self.num_envs))
            return
        expected = (self.num_envs, self.num_actions)
        if tuple(actions.shape) != expected:
            raise ValueError(f"expected actions of shape {expected}, got {tuple(actions.shape)}")
        if not actions.dtype.is_floating_point:
            raise ValueError(f"continuous actions must be floating point, got dtype {actions.dtype}")
        if self.cfg.invalid_actions == "raise" and not bool(torch.isfinite(actions).all()):
            bad = (~torch.isfinite(actions)).any(dim=1).nonzero().flatten().tolist()[:10]
            raise ValueError(f"non-finite (NaN/inf) actions in envs {bad}; pass invalid_actions='zero' to zero them")
        self._t["actions_in"].copy_(actions)

    @property
    def chain_block_links(self) -> int:
        """The chain solve's block length in use: ``cfg.chain_block_links``, with -1 resolved per device."""
        if self.cfg.chain_block_links >= 0:
            return self.cfg.chain_block_links
        return self.gpu_chain_block_links if self.wp_device.is_cuda else 0

    @property
    def chain_solver(self) -> str:
        """The chain solve in use: ``cfg.chain_solver``, with ``"auto"`` resolved per device (the CPU runs one thread
        per block, so there the serial solve)."""
        if self.cfg.chain_solver != "auto":
            return self.cfg.chain_solver
        return self.gpu_chain_solver if self.wp_device.is_cuda else "thomas"

    def _step_launches(self) -> None:
        """Every launch of one env step, in order; captured as one CUDA graph on CUDA devices."""
        dev = self.wp_device
        if self.is_discrete:
            launching.launch(env_kernels.lookup_discrete_actions, dim=(self.num_envs, self.action_dim),
                             inputs=[self.discrete_in, self.action_table],
                             outputs=[self.actions, self.nonfinite_actions], device=dev)
        else:
            launching.launch(env_kernels.sanitize_continuous_actions, dim=self.num_envs,
                             inputs=[self.actions_in, int(self.cfg.clip_actions)],
                             outputs=[self.actions, self.nonfinite_actions, self.clipped_actions], device=dev)
        self._apply_actions(self.actions)
        if self._overflow_term >= 0:
            self.contact_overflow.zero_()
        for _ in range(self.cfg.frame_skip):
            self._before_physics_step()
            self.world.step(self.cfg.time_step)
        for rows in self._state_rows:
            launching.launch(env_kernels.flag_nonfinite_rows, dim=self.num_envs, inputs=[rows],
                             outputs=[self.world.unstable],
                             device=dev)
        self._compute_features(self._all_envs, self.features)
        spec = self.rewards
        launching.launch(env_kernels.finish_env_step, dim=self.num_envs,
                         inputs=[self._delta_columns, self._delta_bases, spec.success, spec.failure, self.weights,
                                 self.world.unstable, self.cfg.max_episode_steps, self.episode_length,
                                 self.episode_return],
                         outputs=[self.features, self.baselines, self.success, self.failure, self.reward,
                                  self.terminated, self.truncated, self.done, self.reset_mask,
                                  self.last_episode_success, self.finished_episodes, self.last_episode_return,
                                  self.last_episode_length], device=dev)
        self._update_task()
        self._reduce_log()
        if self.keep_final_observations:
            # observe before the reset: the stack gets the final frame for every env, then the reset envs
            # alone get their first frame (PUSH_MASKED_ONLY) so no env is shifted twice.
            self._observe(env_kernels.PUSH_SHIFT_ONLY)
            wp.copy(self.final_obs, self.image_stack if self.uses_images else self.obs_stack)
            self._reset_and_observe(env_kernels.PUSH_MASKED_ONLY)
        else:
            self._reset_and_observe(env_kernels.PUSH_ALL)

    def _reduce_log(self) -> None:
        """Means over the envs of everything ``extras["log"]`` reports, into ``log_values`` (two launches)."""
        dev = self.wp_device
        self._log_sums.zero_()
        chunks = (self.num_envs + env_kernels.LOG_CHUNK - 1) // env_kernels.LOG_CHUNK
        launching.launch(env_kernels.sum_log_terms, dim=(chunks, self._log_sums.shape[0]),
                         inputs=[self.features, self.weights, self.finished_episodes, self.last_episode_success,
                                 self.last_episode_return, self.last_episode_length, self.world.unstable,
                                 self.nonfinite_actions, self.clipped_actions, int(self.is_discrete),
                                 self.contact_overflow, self._overflow_term], outputs=[self._log_sums], device=dev)
        launching.launch(env_kernels.finish_log_terms, dim=1,
                         inputs=[self._log_sums, self.rewards.size, self.num_envs, self.action_dim,
                                 int(self.is_discrete), self._overflow_term], outputs=[self.log_values], device=dev)

    def _reset_and_observe(self, push_mode: int = env_kernels.PUSH_ALL) -> None:
        """Reset the envs flagged in ``reset_mask`` in place, start their delta baselines from the features of the
        new state, then write observations (and frame stacks)."""
        self.world.reset(self.reset_mask)
        self._reset_task(self.reset_mask)
        self.world.save_start_state(self.reset_mask)  # a stability restore returns to this episode's start
        if self.rewards.deltas:
            # the task's feature kernel writes the reset envs' features straight into the baselines (a delta's base
            # column is the column of its baseline; the other columns of ``baselines`` are never read)
            self._compute_features(self.reset_mask, self.baselines)
        launching.launch(env_kernels.clear_episode_buffers, dim=self.num_envs, inputs=[self.reset_mask],
                         outputs=[self.episode_length, self.episode_return], device=self.wp_device)
        self._observe(push_mode)

    def _observe(self, push_mode: int) -> None:
        """Write the newest frames and push them onto the frame stacks."""
        self._compute_observations()
        if self.cfg.privileged_critic and self._critic_has_policy_prefix:
            launching.launch(env_kernels.copy_leading_columns, dim=self.obs_frame.shape, inputs=[self.obs_frame],
                             outputs=[self.critic_frame], device=self.wp_device)
        if self.uses_images:
            self._observe_images(push_mode)
        if self.cfg.frame_stack == 1:
            return
        pairs = [(self.obs_frame, self.obs_stack)]
        if self.cfg.privileged_critic:
            pairs.append((self.critic_frame, self.critic_stack))
        for frame, stack in pairs:
            launching.launch(env_kernels.push_observation_frame, dim=frame.shape,
                             inputs=[frame, self.reset_mask, self.cfg.frame_stack, int(push_mode)], outputs=[stack],
                             device=self.wp_device)

    def _step_outputs(self) -> tuple[TensorDict, torch.Tensor, torch.Tensor, dict]:
        t = self._t
        # the log values were reduced on the device inside the step (_reduce_log): one copy, then views of it (a
        # fresh tensor per step, since rsl-rl keeps every step's log until the end of its iteration)
        log: dict[str, torch.Tensor] = dict(zip(self._log_keys, t["log"].clone().unbind(), strict=True))
        extras = {"time_outs": t["truncated"].bool(), "log": log}
        if self.keep_final_observations:
            extras["final_observations"] = t["final_obs"].clone()
        return self.get_observations(), t["reward"].clone(), t["done"].bool(), extras

    def _torch_stream(self) -> wp.Stream:
        """torch's current CUDA stream as a Warp stream (cached), so Warp work orders with torch work."""
        ts = torch.cuda.current_stream(self.device)
        stream = self._torch_streams.get(ts.cuda_stream)
        if stream is None:
            stream = wp.stream_from_torch(ts)
            self._torch_streams[ts.cuda_stream] = stream
        return stream

    def _torch_stream_scope(self):
        if self.wp_device.is_cuda:
            return wp.ScopedStream(self._torch_stream())
        return wp.ScopedDevice(self.wp_device)

    # ------------------------------------------------------------------ conveniences
    def restart_baselines(self, env_mask: wp.array | None = None) -> None:
        """Start the delta features of the masked envs (all without a mask) from their current state, as a reset
        does (host utility for tests and tools that place things by hand)."""
        with self._torch_stream_scope():
            self._compute_features(self._all_envs if env_mask is None else env_mask, self.baselines)

    @property
    def observation_dim(self) -> int:
        """Size of the flattened STATE ``policy`` observation (frames included)."""
        return self.obs_stack.shape[1]

    @property
    def observation_shape(self) -> tuple[int, ...]:
        """Shape of one env's policy observation: ``(D,)`` for STATE, ``(S*C, H, W)`` for images."""
        return tuple(self.image_stack.shape[1:]) if self.uses_images else (self.obs_stack.shape[1],)

    def render_rgb(self, width: int | None = None, height: int | None = None) -> torch.Tensor:
        """RGB images of every env for people, uint8 ``(num_envs, 3, H, W)`` (default: 256 x 256).

        Uses its own camera buffers, so it never disturbs image observations; the first call per size compiles
        and allocates (not meant for the training loop).
        """
        from lapwarp.scene_render import SceneRenderer

        height = height or 256
        width = width or height
        key = (width, height)
        if getattr(self, "_human_camera_key", None) != key:
            self._human_camera = SceneRenderer(self.visual_scene(), self.num_envs, width, height, self.wp_device,
                                               outputs=("rgb",))
            self._human_camera_key = key
        with self._torch_stream_scope():
            self.update_visuals()
            self._human_camera.render()
            self._draw_overlays(wp.from_torch(self._human_camera.rgb), self._human_camera.scene.camera.fov_deg)
        return self._human_camera.rgb.clone()

    def close(self) -> None:
        """Release the captured graph (buffers are freed with the env)."""
        self._graph = None
