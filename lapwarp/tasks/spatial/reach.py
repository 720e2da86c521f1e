"""ReachEnv: move a Cartesian end effector to a target sphere (LapGym's ReachEnv, sofa_env-facts §5.1).

Purely kinematic, in metres, no gravity or collisions. One physics step per env step of 0.1 s; the end
effector moves ``time_step * maximum_robot_velocity * a`` per step, and a component that would leave the
workspace keeps its old value (flagged as a workspace violation). Reward features and weights follow
Table A; distances are divided by the workspace diagonal. STATE observation: end-effector position then
target position, each normalised to [-1, 1] by the workspace.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Annotated

import numpy as np
import torch
import warp as wp

from lapwarp import launching
from lapwarp.config import EnvConfig, NonNegative, Positive, Range, Vec3, check_low_high
from lapwarp.env import BatchedEnv
from lapwarp.experts import Expert
from lapwarp.kernels.random import rand_uniform_vec3
from lapwarp.model import Model
from lapwarp.tasks.camera import fixed_camera
from lapwarp.tasks.spec import (
    ActionBlock,
    ActionLayout,
    Feature,
    ObservationLayout,
    ObservationSpec,
    RewardSpec,
    to_unit,
)
from lapwarp.tasks.targets import sample_separated
from lapwarp.visuals import VisualObject, VisualScene, cylinder_mesh, sphere_mesh
from lapwarp.world import World

wp.set_module_options({"enable_backward": False})

# Table A (the paper's sofa_zoo weights; sofa_env's own defaults are all 0). Distances / workspace diagonal.
REWARDS = RewardSpec(
    Feature("distance_to_target", -1.0),
    Feature("delta_distance_to_target", -10.0, delta_of="distance_to_target"),
    Feature("time_step_cost", 0.0),
    Feature("workspace_violation", 0.0),
    Feature("successful_task", 100.0),
)
F = REWARDS.F
OBS = ObservationSpec("end_effector", "target")
CRITIC = OBS.extend("offset", "distance")
EE, TARGET = wp.constant(0), wp.constant(1)  # columns of ReachEnv.positions
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

    workspace_low: Vec3 = _WS_LOW
    workspace_high: Vec3 = _WS_HIGH
    start_low: Vec3 = _WS_LOW
    start_high: Vec3 = _WS_HIGH
    target_low: Vec3 = _WS_LOW
    target_high: Vec3 = _WS_HIGH
    randomize_start: bool = True
    start_position: Vec3 = (0.0, 0.045, 0.0)
    minimum_distance_to_target_at_start: NonNegative = 0.05
    distance_to_target_threshold: Positive = 0.003
    maximum_robot_velocity: Positive = 0.035
    discrete_action_magnitude: Positive = 0.01
    sphere_radius: Positive = 0.008
    rcm_position: Vec3 = (0.0904, 0.1526, 0.0157)
    camera_position: Vec3 = (0.0, 0.07, 0.55)
    camera_fov_deg: Annotated[float, Range(gt=0.0, lt=180.0)] = 42.0

    def validate(self, reward_features, supported_observations) -> None:
        super().validate(reward_features, supported_observations)
        for box in ("workspace", "start", "target"):
            check_low_high(self, f"{box}_low", f"{box}_high")
        ws_lo, ws_hi = np.asarray(self.workspace_low), np.asarray(self.workspace_high)
        for name in ("start_low", "start_high", "target_low", "target_high", "start_position"):
            p = np.asarray(getattr(self, name))
            if np.any(p < ws_lo - 1e-9) or np.any(p > ws_hi + 1e-9):
                raise ValueError(f"{name}={getattr(self, name)} lies outside the workspace "
                                 f"workspace_low..workspace_high = {self.workspace_low}..{self.workspace_high}")


# ---------------------------------------------------------------------------- kernels
@wp.kernel
def move_reach_end_effector(actions: wp.array2d(dtype=float), step_length: float, ws_low: wp.vec3, ws_high: wp.vec3,
                            positions: wp.array2d(dtype=wp.vec3), violation: wp.array(dtype=wp.int32)):
    """Move by ``time_step * v_max * a``; as in sofa_env an axis that would leave the workspace keeps its value (and
    flags the env's workspace violation of this env step)."""
    env = wp.tid()
    p = positions[env, EE]
    for k in range(3):
        x = p[k] + actions[env, k] * step_length
        if x < ws_low[k] or x > ws_high[k]:
            violation[env] = 1
        else:
            p[k] = x
    positions[env, EE] = p


@wp.kernel
def eval_reach_features(
    env_mask: wp.array(dtype=wp.int32),
    positions: wp.array2d(dtype=wp.vec3),
    violation: wp.array(dtype=wp.int32),
    inv_diagonal: float,
    threshold: float,
    features_out: wp.array2d(dtype=wp.float32),
):
    env = wp.tid()
    if env_mask[env] == 0:
        return
    dist = wp.length(positions[env, TARGET] - positions[env, EE])
    features_out[env, F.DISTANCE_TO_TARGET] = dist * inv_diagonal
    features_out[env, F.TIME_STEP_COST] = 1.0
    features_out[env, F.WORKSPACE_VIOLATION] = float(violation[env])
    features_out[env, F.SUCCESSFUL_TASK] = wp.where(dist <= threshold, 1.0, 0.0)


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
    positions: wp.array2d(dtype=wp.vec3),
    violation: wp.array(dtype=wp.int32),
):
    """Start uniform in the start box, target uniform in the target box at least ``min_distance`` away (with the
    paper's boxes, 0.3 x 0.19 x 0.3 m and 5 cm, a draw is rejected with probability < 2%; 65 draws)."""
    env = wp.tid()
    if env_mask[env] == 0:
        return
    p = start_position
    if randomize_start != 0:
        p = rand_uniform_vec3(rng, env, start_low, start_high)
    positions[env, EE] = p
    positions[env, TARGET] = sample_separated(rng, env, target_low, target_high, positions, EE, 1, min_distance, 65)
    violation[env] = 0


@wp.kernel
def observe_reach(
    positions: wp.array2d(dtype=wp.vec3),
    ws_low: wp.vec3,
    ws_high: wp.vec3,
    inv_diagonal: float,
    o: OBS.Columns,
    c: CRITIC.Columns,
    privileged: int,
    obs_out: wp.array2d(dtype=wp.float32),
    critic_out: wp.array2d(dtype=wp.float32),
):
    """Positions normalised to [-1, 1] by the workspace: ``2 (p - low) / (high - low) - 1``."""
    env = wp.tid()
    p = positions[env, EE]
    t = positions[env, TARGET]
    for k in range(3):
        obs_out[env, o.end_effector + k] = to_unit(p[k], ws_low[k], ws_high[k])
        obs_out[env, o.target + k] = to_unit(t[k], ws_low[k], ws_high[k])
    if privileged != 0:  # the critic's leading blocks are the policy's (copied by the env base)
        rel = (t - p) * inv_diagonal
        for k in range(3):
            critic_out[env, c.offset + k] = rel[k]
        critic_out[env, c.distance] = wp.length(t - p) * inv_diagonal


@wp.kernel
def update_reach_visuals(
    positions: wp.array2d(dtype=wp.vec3),
    rcm: wp.vec3,
    transforms_out: wp.array2d(dtype=wp.transform),
):
    """Instances: 0 end-effector sphere, 1 shaft (its tip at the end effector, pointing away from the RCM),
    2 target sphere."""
    env = wp.tid()
    p = positions[env, EE]
    axis = wp.normalize(p - rcm)
    transforms_out[env, 0] = wp.transform(p, wp.quat_identity())
    transforms_out[env, 1] = wp.transform(p, wp.quat_between_vectors(wp.vec3(0.0, 0.0, 1.0), axis))
    transforms_out[env, 2] = wp.transform(positions[env, TARGET], wp.quat_identity())


# ---------------------------------------------------------------------------- env
class ReachEnv(BatchedEnv):
    """LapGym's ReachEnv, batched. See ``ReachConfig`` for the parameters.

    Privileged critic observation (``privileged_critic=True``): the 6 policy values, the target offset
    divided by the workspace diagonal (3) and the distance divided by the diagonal (1).
    """

    config_class = ReachConfig
    task_name = "Reach"
    rewards = REWARDS
    supported_observations = ("STATE", "RGB", "RGBD", "DEPTH")
    expert = "lapwarp.tasks.spatial.reach:ReachExpert"
    cfg: ReachConfig

    def _build(self) -> World:
        cfg, n, dev = self.cfg, self.num_envs, self.wp_device
        world = World(Model(num_envs=n, device=str(dev)), seed=cfg.seed)
        #: ``(num_envs, 2)`` end-effector (column ``EE``) and target (``TARGET``) positions, m.
        self.positions = wp.zeros((n, 2), dtype=wp.vec3, device=dev)
        self.workspace_violation = wp.zeros(n, dtype=wp.int32, device=dev)
        self._ws_low, self._ws_high = wp.vec3(*cfg.workspace_low), wp.vec3(*cfg.workspace_high)
        self.workspace_diagonal = float(np.linalg.norm(np.subtract(cfg.workspace_high, cfg.workspace_low)))
        return world

    def _checked_state(self) -> list[wp.array]:
        return [self.positions]

    def _observation_layout(self) -> ObservationLayout:
        # positions normalised by the workspace the end effector never leaves (targets are sampled inside it)
        return OBS.layout(end_effector=(3, -1.0, 1.0), target=(3, -1.0, 1.0))

    def _critic_layout(self) -> ObservationLayout:
        return self.obs_layout.extend(CRITIC, offset=(3, -1.0, 1.0), distance=(1, 0.0, 1.0))

    def _action_layout(self) -> ActionLayout:
        # Discrete(7): +-x, +-y, +-z at 10 mm/s, then no-op: in units of the continuous maximum speed
        step = self.cfg.discrete_action_magnitude / self.cfg.maximum_robot_velocity
        return ActionLayout([ActionBlock("end_effector", 3, (step, step, step))])

    def _apply_actions(self, actions: wp.array2d) -> None:
        self.workspace_violation.zero_()

    def _before_physics_step(self) -> None:
        launching.launch(move_reach_end_effector, dim=self.num_envs,
                         inputs=[self.actions, self.cfg.time_step * self.cfg.maximum_robot_velocity, self._ws_low,
                                 self._ws_high], outputs=[self.positions, self.workspace_violation],
                         device=self.wp_device)

    def _compute_features(self, env_mask: wp.array, features_out: wp.array2d) -> None:
        launching.launch(eval_reach_features, dim=self.num_envs,
                         inputs=[env_mask, self.positions, self.workspace_violation, 1.0 / self.workspace_diagonal,
                                 self.cfg.distance_to_target_threshold], outputs=[features_out], device=self.wp_device)

    def _reset_task(self, env_mask: wp.array) -> None:
        cfg = self.cfg
        launching.launch(reset_reach, dim=self.num_envs,
                         inputs=[env_mask, int(cfg.randomize_start), wp.vec3(*cfg.start_position),
                                 wp.vec3(*cfg.start_low), wp.vec3(*cfg.start_high), wp.vec3(*cfg.target_low),
                                 wp.vec3(*cfg.target_high), cfg.minimum_distance_to_target_at_start, self.world.rng],
                         outputs=[self.positions, self.workspace_violation], device=self.wp_device)

    def _compute_observations(self) -> None:
        launching.launch(observe_reach, dim=self.num_envs,
                         inputs=[self.positions, self._ws_low, self._ws_high, 1.0 / self.workspace_diagonal,
                                 self.obs_layout.columns, self.critic_layout.columns, int(self.cfg.privileged_critic)],
                         outputs=[self.obs_frame, self.critic_frame], device=self.wp_device)

    # ------------------------------------------------------------------ visuals
    def _build_visual_scene(self) -> VisualScene:
        """End-effector sphere (grey), instrument shaft from the RCM side (dark grey), target sphere (green).

        Camera: at ``camera_position`` looking along -Z with +Y up (sofa_env's identity orientation), vertical
        FoV ``camera_fov_deg`` (42 degrees), near 0.01 m, far 2 m.
        """
        cfg, n, dev = self.cfg, self.num_envs, self.wp_device
        self.visual_transforms = wp.zeros((n, 3), dtype=wp.transform, device=dev)
        sphere_v, sphere_f = sphere_mesh(cfg.sphere_radius)
        shaft_v, shaft_f = cylinder_mesh(0.004, 0.12)
        shaft_v[:, 2] -= cfg.sphere_radius  # the shaft ends at the sphere's surface
        instance = [self.visual_transforms[:, k:k + 1] for k in range(3)]
        return VisualScene(
            camera=fixed_camera(n, dev, cfg.camera_position, cfg.camera_fov_deg, near=0.01, far=2.0),
            objects=[
                VisualObject("end_effector", "rigid", (0.8, 0.8, 0.8), 1, sphere_v, sphere_f, instance[0]),
                VisualObject("shaft", "rigid", (0.3, 0.3, 0.35), 2, shaft_v, shaft_f, instance[1]),
                VisualObject("target", "rigid", (0.1, 0.8, 0.2), 3, sphere_v, sphere_f, instance[2]),
            ],
            background=(0.05, 0.05, 0.08),
        )

    def update_visuals(self) -> None:
        if self._visual_scene is None:
            return
        launching.launch(update_reach_visuals, dim=self.num_envs,
                         inputs=[self.positions, wp.vec3(*self.cfg.rcm_position)], outputs=[self.visual_transforms],
                         device=self.wp_device)

    # ------------------------------------------------------------------ privileged access (experts, tests)
    @property
    def ee_position(self) -> wp.array:
        """``(num_envs,)`` end-effector positions (a view of ``positions``), m."""
        return self.positions[:, EE]

    @property
    def target_position(self) -> wp.array:
        """``(num_envs,)`` target positions (a view of ``positions``), m."""
        return self.positions[:, TARGET]

    def privileged_state(self) -> dict[str, torch.Tensor]:
        """Zero-copy torch views of the end-effector and target positions, ``(num_envs, 3)`` in metres."""
        positions = wp.to_torch(self.positions)
        return {"ee_position": positions[:, EE], "target_position": positions[:, TARGET]}


class ReachExpert(Expert):
    """Moves the end effector straight at the target at full speed, landing on it with the last step (discrete: along
    the axis with the largest remaining error)."""

    def __call__(self, obs=None) -> torch.Tensor:
        env = self.env
        state = env.privileged_state()
        step_length = env.cfg.maximum_robot_velocity * env.cfg.time_step * env.cfg.frame_skip
        return self.policy_actions((state["target_position"] - state["ee_position"]) / step_length)
