"""ReachEnv: move a Cartesian end effector to a target sphere (LapGym's ReachEnv, sofa_env-facts §5.1).

Purely kinematic, in metres, no gravity or collisions. One physics step per env step of 0.1 s; the end
effector moves ``time_step * maximum_robot_velocity * a`` per step, and a component that would leave the
workspace keeps its old value (flagged as a workspace violation). Reward features and weights follow
Table A; distances are divided by the workspace diagonal. STATE observation: end-effector position then
target position, each normalised to [-1, 1] by the workspace.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import torch
import warp as wp

from lapwarp.config import EnvConfig
from lapwarp.env import BatchedEnv
from lapwarp.instruments import discrete_action_table
from lapwarp.kernels.random import rand_uniform_vec3
from lapwarp.model import Model
from lapwarp.visuals import CameraSpec, VisualObject, VisualScene, cylinder_mesh, sphere_mesh
from lapwarp.world import World

wp.set_module_options({"enable_backward": False})

REACH_FEATURES = (
    "distance_to_target",
    "delta_distance_to_target",
    "time_step_cost",
    "workspace_violation",
    "successful_task",
)
# Table A (the paper's sofa_zoo weights; sofa_env's own defaults are all 0).
REACH_WEIGHTS = {
    "distance_to_target": -1.0,
    "delta_distance_to_target": -10.0,
    "time_step_cost": 0.0,
    "workspace_violation": 0.0,
    "successful_task": 100.0,
}
_WS_LOW = (-0.15, -0.05, -0.15)
_WS_HIGH = (0.15, 0.14, 0.15)


@dataclass(kw_only=True)
class ReachConfig(EnvConfig):
    """ReachEnv parameters (Table B, Table C); lengths in metres, velocities in m/s.

    Attributes:
        workspace_low / workspace_high: Cartesian workspace of the end effector (m).
        start_low / start_high: box the end effector starts in when ``randomize_start`` (m).
        target_low / target_high: box the target is sampled in (m).
        randomize_start: sample the start position each reset; otherwise start at ``start_position``.
        start_position: fixed start position (m) when ``randomize_start`` is False.
        minimum_distance_to_target_at_start: the target is resampled until this far from the start (m).
        distance_to_target_threshold: success when the end effector is this close to the target (m).
        maximum_robot_velocity: end-effector speed at action 1 (m/s), 35 mm/s.
        discrete_action_magnitude: speed of a discrete action (m/s), 10 mm/s.
        sphere_radius: radius of the target sphere (m), 3, 8 or 20 mm in the paper; visual only.
        rcm_position: remote centre of motion of the decorative PSM main link (m); visual only.
        camera_position: endoscope camera position (m), looking along -Z; ``camera_fov_deg``: vertical FoV.
    """

    time_step: float = 0.1
    frame_skip: int = 1
    max_episode_steps: int = 500
    workspace_low: tuple[float, float, float] = _WS_LOW
    workspace_high: tuple[float, float, float] = _WS_HIGH
    start_low: tuple[float, float, float] = _WS_LOW
    start_high: tuple[float, float, float] = _WS_HIGH
    target_low: tuple[float, float, float] = _WS_LOW
    target_high: tuple[float, float, float] = _WS_HIGH
    randomize_start: bool = True
    start_position: tuple[float, float, float] = (0.0, 0.045, 0.0)
    minimum_distance_to_target_at_start: float = 0.05
    distance_to_target_threshold: float = 0.003
    maximum_robot_velocity: float = 0.035
    discrete_action_magnitude: float = 0.01
    sphere_radius: float = 0.008
    rcm_position: tuple[float, float, float] = (0.0904, 0.1526, 0.0157)
    camera_position: tuple[float, float, float] = (0.0, 0.07, 0.55)
    camera_fov_deg: float = 42.0
    reward_weights: dict[str, float] = field(default_factory=dict)

    def validate(self, reward_features, supported_observations) -> None:
        super().validate(reward_features, supported_observations)
        for lo_name, hi_name in (("workspace_low", "workspace_high"), ("start_low", "start_high"),
                                 ("target_low", "target_high")):
            lo, hi = np.asarray(getattr(self, lo_name), float), np.asarray(getattr(self, hi_name), float)
            if lo.shape != (3,) or hi.shape != (3,) or not np.all(lo < hi) or not np.all(np.isfinite(lo + hi)):
                raise ValueError(f"{lo_name}/{hi_name} must be finite 3-vectors with low < high, got {lo}, {hi}")
        ws_lo, ws_hi = np.asarray(self.workspace_low), np.asarray(self.workspace_high)
        for name in ("start_low", "start_high", "target_low", "target_high", "start_position"):
            p = np.asarray(getattr(self, name), float)
            if np.any(p < ws_lo - 1e-9) or np.any(p > ws_hi + 1e-9):
                raise ValueError(f"{name}={tuple(p)} lies outside the workspace {tuple(ws_lo)}..{tuple(ws_hi)}")
        for name in ("distance_to_target_threshold", "maximum_robot_velocity", "discrete_action_magnitude",
                     "sphere_radius"):
            if not getattr(self, name) > 0.0:
                raise ValueError(f"{name} must be positive, got {getattr(self, name)!r}")
        if self.minimum_distance_to_target_at_start < 0.0:
            raise ValueError("minimum_distance_to_target_at_start must be >= 0")
        if self.frame_skip != 1 and self.time_step * self.frame_skip <= 0:
            raise ValueError("time_step * frame_skip must be positive")


# ---------------------------------------------------------------------------- kernels
@wp.kernel
def scale_reach_actions(
    actions: wp.array2d(dtype=wp.float32),
    step_length: float,
    delta_out: wp.array(dtype=wp.vec3),
    violation_out: wp.array(dtype=wp.int32),
):
    """Normalised action -> displacement per physics step (``time_step * v_max * a``)."""
    env = wp.tid()
    delta_out[env] = wp.vec3(actions[env, 0], actions[env, 1], actions[env, 2]) * step_length
    violation_out[env] = 0


@wp.kernel
def move_reach_end_effector(
    delta: wp.array(dtype=wp.vec3),
    ws_low: wp.vec3,
    ws_high: wp.vec3,
    ee_pos: wp.array(dtype=wp.vec3),
    violation: wp.array(dtype=wp.int32),
):
    """Per-axis workspace masking as in sofa_env: an axis that would leave the workspace keeps its value."""
    env = wp.tid()
    p = ee_pos[env]
    d = delta[env]
    out = p
    for k in range(3):
        q = p[k] + d[k]
        if q < ws_low[k] or q > ws_high[k]:
            violation[env] = 1
        else:
            out[k] = q
    ee_pos[env] = out


@wp.kernel
def eval_reach_features(
    ee_pos: wp.array(dtype=wp.vec3),
    target_pos: wp.array(dtype=wp.vec3),
    violation: wp.array(dtype=wp.int32),
    inv_diagonal: float,
    threshold: float,
    previous_distance: wp.array(dtype=wp.float32),
    features_out: wp.array2d(dtype=wp.float32),
    success_out: wp.array(dtype=wp.int32),
    failure_out: wp.array(dtype=wp.int32),
):
    env = wp.tid()
    dist = wp.length(target_pos[env] - ee_pos[env])
    ok = int(0)
    if dist <= threshold:
        ok = 1
    features_out[env, 0] = dist * inv_diagonal
    features_out[env, 1] = (dist - previous_distance[env]) * inv_diagonal
    features_out[env, 2] = 1.0
    features_out[env, 3] = float(violation[env])
    features_out[env, 4] = float(ok)
    previous_distance[env] = dist
    success_out[env] = ok
    failure_out[env] = 0


@wp.kernel
def reset_reach(
    env_mask: wp.array(dtype=wp.int32),
    randomize_start: int,
    start_position: wp.vec3,
    start_low: wp.vec3,
    start_high: wp.vec3,
    target_low: wp.vec3,
    target_high: wp.vec3,
    min_distance: float,
    rng: wp.array(dtype=wp.uint32),
    ee_pos: wp.array(dtype=wp.vec3),
    target_pos: wp.array(dtype=wp.vec3),
    previous_distance: wp.array(dtype=wp.float32),
    violation: wp.array(dtype=wp.int32),
):
    """Start uniform in the start box, target uniform in the target box at least ``min_distance`` away.

    Rejection sampling with a bounded number of tries keeps the kernel finite; with the paper's boxes
    (0.3 x 0.19 x 0.3 m, 5 cm minimum) a try is rejected with probability < 2%, so 64 tries never all fail
    in practice, and if they did the farthest candidate is kept.
    """
    env = wp.tid()
    if env_mask[env] == 0:
        return
    p = start_position
    if randomize_start != 0:
        p = rand_uniform_vec3(rng, env, start_low, start_high)
    best = rand_uniform_vec3(rng, env, target_low, target_high)
    best_d = wp.length(best - p)
    for _ in range(64):
        if best_d >= min_distance:
            break
        t = rand_uniform_vec3(rng, env, target_low, target_high)
        d = wp.length(t - p)
        if d > best_d:
            best = t
            best_d = d
    ee_pos[env] = p
    target_pos[env] = best
    previous_distance[env] = best_d
    violation[env] = 0


@wp.kernel
def observe_reach(
    ee_pos: wp.array(dtype=wp.vec3),
    target_pos: wp.array(dtype=wp.vec3),
    ws_low: wp.vec3,
    ws_high: wp.vec3,
    inv_diagonal: float,
    privileged: int,
    obs_out: wp.array2d(dtype=wp.float32),
    critic_out: wp.array2d(dtype=wp.float32),
):
    """Positions normalised to [-1, 1] by the workspace: ``2 (p - low) / (high - low) - 1``."""
    env = wp.tid()
    p = ee_pos[env]
    t = target_pos[env]
    for k in range(3):
        span = ws_high[k] - ws_low[k]
        obs_out[env, k] = 2.0 * (p[k] - ws_low[k]) / span - 1.0
        obs_out[env, 3 + k] = 2.0 * (t[k] - ws_low[k]) / span - 1.0
    if privileged != 0:
        rel = (t - p) * inv_diagonal
        for k in range(6):
            critic_out[env, k] = obs_out[env, k]
        for k in range(3):
            critic_out[env, 6 + k] = rel[k]
        critic_out[env, 9] = wp.length(t - p) * inv_diagonal


@wp.kernel
def update_reach_visuals(
    ee_pos: wp.array(dtype=wp.vec3),
    target_pos: wp.array(dtype=wp.vec3),
    rcm: wp.vec3,
    transforms_out: wp.array2d(dtype=wp.transform),
):
    """Instances: 0 end-effector sphere, 1 shaft (its tip at the end effector, pointing away from the RCM),
    2 target sphere."""
    env = wp.tid()
    p = ee_pos[env]
    axis = wp.normalize(p - rcm)
    transforms_out[env, 0] = wp.transform(p, wp.quat_identity())
    transforms_out[env, 1] = wp.transform(p, wp.quat_between_vectors(wp.vec3(0.0, 0.0, 1.0), axis))
    transforms_out[env, 2] = wp.transform(target_pos[env], wp.quat_identity())


# ---------------------------------------------------------------------------- env
class ReachEnv(BatchedEnv):
    """LapGym's ReachEnv, batched. See ``ReachConfig`` for the parameters.

    Privileged critic observation (``privileged_critic=True``): the 6 policy values, the target offset
    divided by the workspace diagonal (3) and the distance divided by the diagonal (1).
    """

    config_class = ReachConfig
    task_name = "Reach"
    reward_features = REACH_FEATURES
    default_reward_weights = REACH_WEIGHTS
    supported_observations = ("STATE", "RGB", "RGBD", "DEPTH")
    cfg: ReachConfig

    def _build(self) -> World:
        cfg, n, dev = self.cfg, self.num_envs, self.wp_device
        world = World(Model(num_envs=n, device=str(dev)), seed=cfg.seed)
        self.ee_position = wp.zeros(n, dtype=wp.vec3, device=dev)
        self.target_position = wp.zeros(n, dtype=wp.vec3, device=dev)
        self.previous_distance = wp.zeros(n, dtype=wp.float32, device=dev)
        self.workspace_violation = wp.zeros(n, dtype=wp.int32, device=dev)
        self.step_delta = wp.zeros(n, dtype=wp.vec3, device=dev)
        self._ws_low, self._ws_high = wp.vec3(*cfg.workspace_low), wp.vec3(*cfg.workspace_high)
        self.workspace_diagonal = float(np.linalg.norm(np.subtract(cfg.workspace_high, cfg.workspace_low)))
        self._visual_scene: VisualScene | None = None
        return world

    def _action_dim(self) -> int:
        return 3

    def _observation_dim(self) -> int:
        return 6

    def _critic_observation_dim(self) -> int:
        return 10

    def _observation_bounds(self) -> tuple[float, float]:
        return -1.0, 1.0  # positions normalised by the workspace the end effector never leaves

    def _discrete_action_table(self) -> np.ndarray:
        # Discrete(7): +-x, +-y, +-z at 10 mm/s, then no-op; normalised by the continuous maximum speed.
        return discrete_action_table([self.cfg.discrete_action_magnitude / self.cfg.maximum_robot_velocity] * 3)

    def _apply_actions(self, actions: wp.array2d) -> None:
        wp.launch(scale_reach_actions, dim=self.num_envs,
                  inputs=[actions, self.cfg.time_step * self.cfg.maximum_robot_velocity],
                  outputs=[self.step_delta, self.workspace_violation], device=self.wp_device)

    def _before_physics_step(self) -> None:
        wp.launch(move_reach_end_effector, dim=self.num_envs,
                  inputs=[self.step_delta, self._ws_low, self._ws_high],
                  outputs=[self.ee_position, self.workspace_violation], device=self.wp_device)

    def _compute_features(self) -> None:
        wp.launch(eval_reach_features, dim=self.num_envs,
                  inputs=[self.ee_position, self.target_position, self.workspace_violation,
                          1.0 / self.workspace_diagonal, self.cfg.distance_to_target_threshold],
                  outputs=[self.previous_distance, self.features, self.success, self.failure],
                  device=self.wp_device)

    def _reset_task(self, env_mask: wp.array) -> None:
        cfg = self.cfg
        wp.launch(reset_reach, dim=self.num_envs,
                  inputs=[env_mask, int(cfg.randomize_start), wp.vec3(*cfg.start_position), wp.vec3(*cfg.start_low),
                          wp.vec3(*cfg.start_high), wp.vec3(*cfg.target_low), wp.vec3(*cfg.target_high),
                          cfg.minimum_distance_to_target_at_start, self.world.rng],
                  outputs=[self.ee_position, self.target_position, self.previous_distance,
                           self.workspace_violation], device=self.wp_device)

    def _compute_observations(self) -> None:
        critic = self.critic_frame if self.cfg.privileged_critic else self.obs_frame
        wp.launch(observe_reach, dim=self.num_envs,
                  inputs=[self.ee_position, self.target_position, self._ws_low, self._ws_high,
                          1.0 / self.workspace_diagonal, int(self.cfg.privileged_critic)],
                  outputs=[self.obs_frame, critic], device=self.wp_device)

    # ------------------------------------------------------------------ visuals
    def visual_scene(self) -> VisualScene:
        """End-effector sphere (grey), instrument shaft from the RCM side (dark grey), target sphere (green).

        Camera: at ``camera_position`` looking along -Z with +Y up (sofa_env's identity orientation), vertical
        FoV ``camera_fov_deg`` (42 degrees), near 0.01 m, far 2 m.
        """
        if self._visual_scene is None:
            cfg, n, dev = self.cfg, self.num_envs, self.wp_device
            self.visual_transforms = wp.zeros((n, 3), dtype=wp.transform, device=dev)
            sphere_v, sphere_f = sphere_mesh(cfg.sphere_radius)
            shaft_v, shaft_f = cylinder_mesh(0.004, 0.12)
            shaft_v[:, 2] -= cfg.sphere_radius  # the shaft ends at the sphere's surface
            instance = [self.visual_transforms[:, k:k + 1] for k in range(3)]
            poses = wp.array([wp.transform(wp.vec3(*cfg.camera_position), wp.quat_identity())] * n,
                             dtype=wp.transform, device=dev)
            self._visual_scene = VisualScene(
                camera=CameraSpec(poses=poses, fov_deg=cfg.camera_fov_deg, near=0.01, far=2.0),
                objects=[
                    VisualObject("end_effector", "rigid", (0.8, 0.8, 0.8), 1, sphere_v, sphere_f, instance[0]),
                    VisualObject("shaft", "rigid", (0.3, 0.3, 0.35), 2, shaft_v, shaft_f, instance[1]),
                    VisualObject("target", "rigid", (0.1, 0.8, 0.2), 3, sphere_v, sphere_f, instance[2]),
                ],
                background=(0.05, 0.05, 0.08),
            )
            self.update_visuals()
        return self._visual_scene

    def update_visuals(self) -> None:
        if self._visual_scene is None:
            return
        wp.launch(update_reach_visuals, dim=self.num_envs,
                  inputs=[self.ee_position, self.target_position, wp.vec3(*self.cfg.rcm_position)],
                  outputs=[self.visual_transforms], device=self.wp_device)

    # ------------------------------------------------------------------ privileged access (experts, tests)
    def privileged_state(self) -> dict[str, torch.Tensor]:
        """Zero-copy torch views of the end-effector and target positions, ``(num_envs, 3)`` in metres."""
        return {"ee_position": wp.to_torch(self.ee_position), "target_position": wp.to_torch(self.target_position)}
