"""DeflectSpheresEnv: deflect the highlighted sphere with the electrocautery hook of its colour (sofa_env-facts §5.2).

A 100 x 100 mm board carries ``num_spheres`` spheres on stalks. As in sofa_env the stalks have no mechanics of
their own: each sphere is one XPBD particle held to its rest point (its *anchor*) by an attachment of compliance
``1 / k`` (sofa_env: a Rigid3d frame on a ``RestShapeSpringsForceField`` of k = 1e3 N/m), under gravity, and the
deflection of a sphere is its distance from the anchor. One or two cauter hooks move in TPSD about their remote
centres of motion; their shaft and hook are capsule colliders on kinematic bodies that follow the TPSD tip pose
every physics step (interpolated across the XPBD substeps), so they push the spheres through contact, and the
contact reports tell whether a hook's tip (the hook capsules) or its shaft touches a sphere.

Episode logic follows sofa_env's ``DeflectSpheresEnv``: one sphere is active and coloured by the hook that must
deflect it (right hook blue, left hook red); it is done when it is deflected by at least
``min_deflection_distance`` while the matching hook's tip touches it. Then a new active sphere is drawn from all
spheres (``WITH_REPLACEMENT``) or from those not done yet (``WITHOUT_REPLACEMENT``, done spheres turn green), with
a random hook when there are two; after ``num_deflect_to_win`` deflections the task is successful.

Units are metres, radians inside, degrees at the API; sofa_env's millimetres are converted. Reward features
(Table A): distances are divided by the workspace diagonal and clipped to [-1, 1] as in sofa_env, deflections by
the minimum deflection. STATE observation (29 values with one hook, 41 with two), in sofa_env's order: every
sphere's position (3 N), the active sphere's position (3), the right hook's PTSD (4) and tip pose (position 3,
quaternion xyzw 4), then with two hooks the active hook id (1 = left), the left hook's PTSD (4) and pose (7).
Positions are mapped from the Cartesian workspace to [-1, 1] and PTSD from the state limits to [-1, 1].

Deviations from sofa_env (deliberate): the left hook's position is used for the delta-distance baseline after a
new sphere is drawn for the left hook (sofa_env reads the right hook there, a bug); with two hooks,
``allow_deflection_with_instrument_shaft`` is supported (sofa_env forces it off) and means "any part of the
matching hook touches the sphere" rather than "no contact needed"; spheres start at their gravity equilibrium, so
no settle steps are needed after a reset. As in sofa_env, deflections are measured from the spring anchor, so every
sphere shows its gravity sag (0.49 mm with the defaults) in the inactive-deflection feature.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Annotated, Literal

import numpy as np
import torch
import trimesh
import warp as wp

from lapwarp import launching
from lapwarp.builder import SceneBuilder
from lapwarp.config import PTSD, Count, EnvConfig, NonNegative, Positive, PositiveInt, Range, Vec3, check_low_high
from lapwarp.contact import ContactSystem
from lapwarp.env import BatchedEnv
from lapwarp.experts import Expert
from lapwarp.instruments import TPSDConfig, tpsd_from_config
from lapwarp.kernels.geometry import closest_segment_segment
from lapwarp.kernels.kinematics import point_to_ptsd
from lapwarp.kernels.random import rand_uniform
from lapwarp.tasks.camera import fixed_camera
from lapwarp.tasks.deformable import DeformableObject
from lapwarp.tasks.rig import (
    CAUTER_CUTTING_CENTER,
    STATE_LIMITS_VIOLATED,
    WORKSPACE_VIOLATED,
    InstrumentRig,
    InstrumentSpec,
    RigBounds,
    RigContacts,
    RigState,
    count_flag,
    cutting_center,
    instrument_touches,
    write_unit_point,
    write_unit_ptsd,
)
from lapwarp.tasks.spec import Feature, ObservationLayout, ObservationSpec, RewardSpec
from lapwarp.tasks.targets import draw_index, draw_index_where, sample_separated
from lapwarp.visuals import VisualObject, VisualScene, sphere_mesh
from lapwarp.world import World

wp.set_module_options({"enable_backward": False})

# Table A (the paper's sofa_zoo weights; sofa_env's own defaults are all 0).
REWARDS = RewardSpec(
    Feature("action_violated_cartesian_workspace", 0.0),
    Feature("action_violated_state_limits", 0.0),
    Feature("tool_collision", 0.0),
    Feature("distance_to_active_sphere", 0.0),
    Feature("delta_distance_to_active_sphere", -5.0, delta_of="distance_to_active_sphere"),
    Feature("deflection_of_inactive_spheres", -0.005),
    Feature("deflection_of_active_sphere", 0.0),
    Feature("delta_deflection_of_active_sphere", 1.0, delta_of="deflection_of_active_sphere"),
    Feature("done_with_active_sphere", 10.0),
    Feature("successful_task", 100.0),
)
F = REWARDS.F
# sofa_env's STATE order; the active hook id and the left hook exist with two hooks only (size 0 otherwise)
OBS = ObservationSpec("spheres", "active_sphere", "right_hook", "active_hook", "left_hook")
CRITIC = OBS.extend("deflections", "offset_to_active", "tip_contact")

#: Sphere states (sofa_env's ``Post.State``) and their colours.
IDLE, ACTIVE_RIGHT, ACTIVE_LEFT, DONE = 0, 1, 2, 3
SPHERE_COLORS = ((0.7, 0.7, 0.7), (0.0, 0.0, 1.0), (1.0, 0.0, 0.0), (0.0, 1.0, 0.0))
_HIDDEN = wp.constant(wp.vec3(0.0, 0.0, -1000.0))  # far beyond the camera's far plane: culled
_SPHERE_TRIES = wp.constant(200)  # candidate positions per sphere at reset (rejection sampling, minimum distance)


@dataclass(kw_only=True)
class DeflectSpheresConfig(EnvConfig):
    """DeflectSpheresEnv parameters (Table B, Table C); lengths in metres, angles in degrees, stiffness in N/m.

    Attributes:
        board_size: (width along x, depth along y) of the board (m), 100 x 100 mm.
        workspace_height: height of the box over the board the hooks work in (m); the Cartesian workspace of the
            hook tips is the board enlarged by 10 mm on every side, from z = -10 mm to ``workspace_height`` + 10 mm.
        num_spheres: spheres on the board (sofa_env's ``num_objects``), at most 64.
        sphere_height_limits: the height of each sphere centre is uniform in this range at reset (m).
        sphere_margin: sphere x, y are uniform in the board shrunk by this margin on each side (m), +-45 mm.
        min_sphere_distance: minimum distance between sphere centres at reset (m), 20 mm.
        stalk_stiffness_limits: each stalk's spring stiffness is uniform in this range at reset (N/m), 1e3.
        post_mass: mass of one post (kg); sofa_env spreads it over the stalk's two frames, so the sphere
            carries half of it.
        sphere_radius: collision radius of a sphere (m), 6 mm.
        single_instrument: one hook (the right, blue one) or two (right blue, left red).
        num_deflect_to_win: correct deflections that complete the task (1, 2 or 5 in the paper).
        min_deflection_distance: deflection that marks the active sphere done (m), 3 mm.
        allow_deflection_with_instrument_shaft: also count contact of the hook's shaft, not only its tip.
        sampling_mode: "WITHOUT_REPLACEMENT" (done spheres are not drawn again; sofa_zoo's setting) or
            "WITH_REPLACEMENT" (sofa_env's constructor default).
        instrument_reset_noise: uniform PTSD noise at reset (deg, deg, deg, m), [30, 30, 30, 10 mm].
        maximum_state_velocity: PTSD speed at action 1 (deg/s, deg/s, deg/s, m/s), [20, 20, 20, 20 mm/s].
        discrete_action_magnitude: PTSD speed of a discrete action (deg/s, deg/s, deg/s, m/s), [15, 15, 15, 10 mm/s].
        right_start_ptsd / left_start_ptsd: start states (deg, deg, deg, m).
        instrument_state_low / instrument_state_high: state limits (deg, deg, deg, m), depth 0 .. 300 mm.
        contact_friction: Coulomb friction between hooks and spheres (sofa_env: 1.0).
        tool_collision_distance: the hooks collide when their RCM-to-tip segments are closer than this (m), 1.5 mm.
        camera_position: camera position (m); ``camera_euler_deg``: its XYZ Euler angles; ``camera_fov_deg``:
            vertical field of view.
        physics_substeps: XPBD substeps per physics step (at most 10,000).
        contact_capacity: contact records kept per env per step (``ContactSystem.capacity``, at most 4096); an env
            with more is counted under ``extras["log"]["/contact/overflow_fraction"]`` (the contact response is
            unaffected).
        max_episode_steps: time limit; ``None`` = 500 x ``num_deflect_to_win`` (Table C).
    """

    max_episode_steps: PositiveInt | None = None
    board_size: tuple[Positive, Positive] = (0.1, 0.1)
    workspace_height: Positive = 0.08
    num_spheres: Count(64) = 5
    sphere_height_limits: tuple[Positive, Positive] = (0.03, 0.06)
    sphere_margin: NonNegative = 0.005
    min_sphere_distance: NonNegative = 0.02
    stalk_stiffness_limits: tuple[Positive, Positive] = (1.0e3, 1.0e3)
    post_mass: Positive = 0.1
    sphere_radius: Positive = 0.006
    single_instrument: bool = True
    num_deflect_to_win: Count(1000) = 5
    min_deflection_distance: Positive = 0.003
    allow_deflection_with_instrument_shaft: bool = False
    sampling_mode: Literal["WITH_REPLACEMENT", "WITHOUT_REPLACEMENT"] = "WITHOUT_REPLACEMENT"
    instrument_reset_noise: tuple[NonNegative, NonNegative, NonNegative, NonNegative] = (30.0, 30.0, 30.0, 0.01)
    maximum_state_velocity: tuple[Positive, Positive, Positive, Positive] = (20.0, 20.0, 20.0, 0.02)
    discrete_action_magnitude: tuple[Positive, Positive, Positive, Positive] = (15.0, 15.0, 15.0, 0.01)
    right_start_ptsd: PTSD = (-44.0, 76.0, 0.0, 0.04)
    left_start_ptsd: PTSD = (44.0, 45.0, 0.0, 0.015)
    instrument_state_low: PTSD = (-90.0, -90.0, -90.0, 0.0)
    instrument_state_high: PTSD = (90.0, 90.0, 90.0, 0.3)
    contact_friction: NonNegative = 1.0
    tool_collision_distance: Positive = 0.0015
    camera_position: Vec3 = (0.0, -0.14, 0.12)
    camera_euler_deg: Vec3 = (58.0, 0.0, 0.0)
    camera_fov_deg: Annotated[float, Range(gt=0.0, lt=180.0)] = 45.0
    physics_substeps: Count(10_000) = 10
    contact_capacity: Count(4096) = 16

    def validate(self, reward_features, supported_observations) -> None:
        super().validate(reward_features, supported_observations)
        if self.max_episode_steps is None:
            self.max_episode_steps = 500 * self.num_deflect_to_win  # Table C: 500 steps per deflection
        if self.sampling_mode == "WITHOUT_REPLACEMENT" and self.num_deflect_to_win > self.num_spheres:
            raise ValueError(f"num_deflect_to_win={self.num_deflect_to_win} exceeds num_spheres={self.num_spheres}, "
                             "which WITHOUT_REPLACEMENT cannot reach")
        if min(self.board_size) <= 2.0 * self.sphere_margin:
            raise ValueError(f"board_size {self.board_size} must exceed 2 * sphere_margin ({self.sphere_margin})")
        lo, hi = self.sphere_height_limits
        if not lo <= hi <= self.workspace_height:
            raise ValueError(f"sphere_height_limits must satisfy low <= high <= workspace_height, got {(lo, hi)}")
        check_low_high(self, "instrument_state_low", "instrument_state_high", strict=False)
        if self.stalk_stiffness_limits[0] > self.stalk_stiffness_limits[1]:
            raise ValueError(f"stalk_stiffness_limits must satisfy low <= high, got {self.stalk_stiffness_limits}")
        self.instrument_configs()  # TPSDConfig checks the start states against the limits

    # derived geometry -------------------------------------------------------------------------------
    @property
    def workspace(self) -> tuple[np.ndarray, np.ndarray]:
        """Cartesian workspace (low, high) of the hook tips (m): sofa_env's board + 10 mm on every side."""
        w, d = self.board_size
        low = np.array([-w / 2 - 0.01, -d / 2 - 0.01, -0.01])
        high = np.array([w / 2 + 0.01, d / 2 + 0.01, self.workspace_height + 0.01])
        return low, high

    def instrument_configs(self) -> list[TPSDConfig]:
        """TPSD configs of the right hook and (with two hooks) the left one; RCMs above the front corners."""
        low, high = self.workspace
        common = dict(rcm_euler_deg=(-180.0, 0.0, 0.0), state_low="instrument_state_low",
                      state_high="instrument_state_high", workspace_low=tuple(low), workspace_high=tuple(high),
                      max_velocity="maximum_state_velocity", discrete_magnitude="discrete_action_magnitude",
                      ptsd_noise="instrument_reset_noise")
        configs = [tpsd_from_config(self, rcm_position=(high[0], low[1], high[2]), start_ptsd="right_start_ptsd",
                                    **common)]
        if not self.single_instrument:
            configs.append(tpsd_from_config(self, rcm_position=(low[0], low[1], high[2]),
                                            start_ptsd="left_start_ptsd", **common))
        return configs


# ---------------------------------------------------------------------------- kernels
@wp.struct
class Spheres:
    """The task's per-env state: anchors ``(N, S)`` (m), stalk stiffnesses (N/m), sphere states (``IDLE`` ...), the
    active sphere and its hook, the previously active sphere, deflections done and the matching tip's contact."""

    anchors: wp.array2d(dtype=wp.vec3)
    stiffness: wp.array2d(dtype=float)
    state: wp.array2d(dtype=wp.int32)
    active: wp.array(dtype=wp.int32)
    active_hook: wp.array(dtype=wp.int32)
    previous_active: wp.array(dtype=wp.int32)
    num_deflections: wp.array(dtype=wp.int32)
    tip_contact: wp.array(dtype=wp.int32)


@wp.struct
class Params:
    """Constants of a configuration (SI units, radians)."""

    bounds: RigBounds
    min_deflection: float
    tool_collision_distance: float
    tool_only: int  # 1 - allow_deflection_with_instrument_shaft
    num_to_win: int
    without_replacement: int


@wp.func
def draw_active_sphere(rng: wp.array(dtype=wp.uint32), env: int, num_hooks: int, without_replacement: int,
                       sphere_state: wp.array2d(dtype=wp.int32)) -> wp.vec2i:
    """(sphere, hook) of a new active sphere: uniform over the valid spheres, uniform hook with two hooks."""
    chosen = draw_index_where(rng, env, sphere_state, DONE, without_replacement)
    hook = int(0)
    if num_hooks > 1:
        hook = draw_index(rng, env, 2)
    return wp.vec2i(chosen, hook)


@wp.func
def activate_sphere(spheres: Spheres, env: int, pick: wp.vec2i):
    spheres.active[env] = pick[0]
    spheres.active_hook[env] = pick[1]
    spheres.state[env, pick[0]] = ACTIVE_RIGHT + pick[1]


@wp.kernel
def reset_spheres(env_mask: wp.array(dtype=wp.int32), low: wp.vec3, high: wp.vec3, min_distance: float,
                  stiffness_limits: wp.vec2, num_hooks: int, rng: wp.array(dtype=wp.uint32), spheres: Spheres):
    """New anchors (uniform over the board, ``low``/``high`` holding x, y and the height range, at least
    ``min_distance`` apart from up to 200 candidates), stalk stiffnesses and the active sphere."""
    env = wp.tid()
    if env_mask[env] == 0:
        return
    for k in range(spheres.anchors.shape[1]):
        spheres.anchors[env, k] = sample_separated(rng, env, low, high, spheres.anchors, 0, k, min_distance,
                                                   _SPHERE_TRIES)
        spheres.stiffness[env, k] = rand_uniform(rng, env, stiffness_limits[0], stiffness_limits[1])
        spheres.state[env, k] = IDLE
    activate_sphere(spheres, env, draw_active_sphere(rng, env, num_hooks, 0, spheres.state))
    spheres.previous_active[env] = -1
    spheres.num_deflections[env] = 0


@wp.kernel
def eval_deflect_features(env_mask: wp.array(dtype=wp.int32), q: wp.array2d(dtype=wp.vec3), rig: RigState,
                          contacts: RigContacts, spheres: Spheres, p: Params, features_out: wp.array2d(dtype=float)):
    """Reward features of sofa_env's ``_get_reward_features`` (deltas: the env base); caches the matching hook's
    contact with the active sphere in ``tip_contact`` for the critic."""
    env = wp.tid()
    if env_mask[env] == 0:
        return
    a = spheres.active[env]
    hook = spheres.active_hook[env]
    collision = float(0.0)
    if rig.pose.shape[1] > 1:  # the two hooks' RCM-to-cutting-centre segments come too close
        p1 = wp.transform_get_translation(rig.rcm[env, 0])
        q1 = cutting_center(rig.pose[env, 0])
        p2 = wp.transform_get_translation(rig.rcm[env, 1])
        q2 = cutting_center(rig.pose[env, 1])
        st = closest_segment_segment(p1, q1, p2, q2)
        if wp.length((p1 + (q1 - p1) * st[0]) - (p2 + (q2 - p2) * st[1])) < p.tool_collision_distance:
            collision = 1.0
    valid = instrument_touches(contacts, env, hook, a, p.tool_only)  # contact particle group k = sphere k
    spheres.tip_contact[env] = valid
    dist = wp.length(cutting_center(rig.pose[env, hook]) - q[env, a])
    deflection = wp.length(q[env, a] - spheres.anchors[env, a])
    inactive = float(0.0)
    for k in range(spheres.anchors.shape[1]):
        if k != a and k != spheres.previous_active[env]:
            inactive += wp.length(q[env, k] - spheres.anchors[env, k]) / p.min_deflection
    done = wp.where(valid != 0 and deflection >= p.min_deflection, 1.0, 0.0)
    features_out[env, F.ACTION_VIOLATED_CARTESIAN_WORKSPACE] = float(count_flag(rig.flags, env, WORKSPACE_VIOLATED))
    features_out[env, F.ACTION_VIOLATED_STATE_LIMITS] = float(count_flag(rig.flags, env, STATE_LIMITS_VIOLATED))
    features_out[env, F.TOOL_COLLISION] = collision
    features_out[env, F.DISTANCE_TO_ACTIVE_SPHERE] = wp.clamp(dist * p.bounds.inv_diagonal, -1.0, 1.0)
    features_out[env, F.DEFLECTION_OF_INACTIVE_SPHERES] = inactive
    features_out[env, F.DEFLECTION_OF_ACTIVE_SPHERE] = float(valid) * deflection / p.min_deflection
    features_out[env, F.DONE_WITH_ACTIVE_SPHERE] = done
    won = spheres.num_deflections[env] + int(done) >= p.num_to_win
    features_out[env, F.SUCCESSFUL_TASK] = wp.where(won, 1.0, 0.0)


@wp.kernel
def update_active_sphere(q: wp.array2d(dtype=wp.vec3), rig: RigState, features: wp.array2d(dtype=float), p: Params,
                         rng: wp.array(dtype=wp.uint32), spheres: Spheres, baselines: wp.array2d(dtype=float)):
    """sofa_env's bookkeeping after a done sphere: count it, mark it (done / idle) and, unless the task is won, draw a
    new active sphere and hook; the delta features then restart from the new sphere (sofa_env: without the contact
    factor of the deflection feature)."""
    env = wp.tid()
    if features[env, F.DONE_WITH_ACTIVE_SPHERE] == 0.0:
        return
    a = spheres.active[env]
    spheres.num_deflections[env] = spheres.num_deflections[env] + 1
    spheres.state[env, a] = wp.where(p.without_replacement != 0, DONE, IDLE)
    if features[env, F.SUCCESSFUL_TASK] != 0.0:
        return
    pick = draw_active_sphere(rng, env, rig.pose.shape[1], p.without_replacement, spheres.state)
    spheres.previous_active[env] = a
    activate_sphere(spheres, env, pick)
    dist = wp.length(cutting_center(rig.pose[env, pick[1]]) - q[env, pick[0]])
    baselines[env, F.DISTANCE_TO_ACTIVE_SPHERE] = wp.clamp(dist * p.bounds.inv_diagonal, -1.0, 1.0)
    deflection = wp.length(q[env, pick[0]] - spheres.anchors[env, pick[0]])
    baselines[env, F.DEFLECTION_OF_ACTIVE_SPHERE] = deflection / p.min_deflection


@wp.func
def write_hook(out: wp.array2d(dtype=float), env: int, col: int, rig: RigState, k: int, p: Params):
    """PTSD (by the state limits) and tip position (by the workspace) in [-1, 1], then the tip quaternion (xyzw)."""
    write_unit_ptsd(out, env, col, rig.ptsd[env, k], p.bounds)
    write_unit_point(out, env, col + 4, wp.transform_get_translation(rig.pose[env, k]), p.bounds)
    rot = wp.transform_get_rotation(rig.pose[env, k])
    for i in range(4):
        out[env, col + 7 + i] = rot[i]


@wp.kernel
def observe_deflect(q: wp.array2d(dtype=wp.vec3), rig: RigState, spheres: Spheres, p: Params, o: OBS.Columns,
                    c: CRITIC.Columns, privileged: int, obs_out: wp.array2d(dtype=float),
                    critic_out: wp.array2d(dtype=float)):
    """sofa_env's STATE order: spheres, active sphere, right PTSD and pose, [active hook, left PTSD and pose]; the
    critic adds every sphere's deflection, the offset to the active sphere and the tip contact."""
    env = wp.tid()
    num = q.shape[1]
    pa = q[env, spheres.active[env]]
    for k in range(num):
        write_unit_point(obs_out, env, o.spheres + 3 * k, q[env, k], p.bounds)
    write_unit_point(obs_out, env, o.active_sphere, pa, p.bounds)
    write_hook(obs_out, env, o.right_hook, rig, 0, p)
    if rig.pose.shape[1] > 1:
        obs_out[env, o.active_hook] = float(spheres.active_hook[env])
        write_hook(obs_out, env, o.left_hook, rig, 1, p)
    if privileged == 0:
        return
    for k in range(num):  # the critic's leading blocks are the policy's (copied by the env base)
        critic_out[env, c.deflections + k] = wp.length(q[env, k] - spheres.anchors[env, k]) / p.min_deflection
    rel = (pa - cutting_center(rig.pose[env, spheres.active_hook[env]])) * p.bounds.inv_diagonal
    for i in range(3):
        critic_out[env, c.offset_to_active + i] = rel[i]
    critic_out[env, c.tip_contact] = float(spheres.tip_contact[env])


@wp.kernel
def update_deflect_visuals(q: wp.array2d(dtype=wp.vec3), spheres: Spheres, sphere_out: wp.array2d(dtype=wp.transform),
                           stalk_points: wp.array2d(dtype=wp.vec3)):
    """Sphere ``k`` is drawn by instance ``k`` of the object of its state (columns ``state * N + k``); the other
    three instances of that sphere are parked beyond the far plane. Stalk ``k`` runs from its base on the board to
    the sphere centre (points ``2k``, ``2k + 1``)."""
    env = wp.tid()
    num = q.shape[1]
    for k in range(num):
        for c in range(4):
            x = wp.where(c == spheres.state[env, k], q[env, k], _HIDDEN)
            sphere_out[env, c * num + k] = wp.transform(x, wp.quat_identity())
        base = spheres.anchors[env, k]
        stalk_points[env, 2 * k] = wp.vec3(base[0], base[1], 0.0)
        stalk_points[env, 2 * k + 1] = q[env, k]


@wp.kernel
def expert_ptsd_errors(q: wp.array2d(dtype=wp.vec3), rig: RigState, spheres: Spheres, contact_distance: float,
                       push: float, error_out: wp.array2d(dtype=wp.vec4)):
    """PTSD error of each hook towards the expert's target (see ``DeflectSpheresExpert``); zero for idle hooks."""
    env, h = wp.tid()
    error_out[env, h] = wp.vec4(0.0)
    if h != spheres.active_hook[env]:
        return
    anchor = spheres.anchors[env, spheres.active[env]]
    u = cutting_center(rig.pose[env, h]) - anchor
    if wp.length(u) < 1.0e-6:
        u = wp.vec3(0.0, 0.0, 1.0)
    target = anchor + wp.normalize(u) * (contact_distance - push)
    s = rig.ptsd[env, h]
    goal = point_to_ptsd(rig.rcm[env, h], target, s[2])
    # the cutting centre lies on the shaft axis, CAUTER_CUTTING_CENTER beyond the TPSD tip
    error_out[env, h] = wp.vec4(goal[0] - s[0], goal[1] - s[1], 0.0, goal[3] - CAUTER_CUTTING_CENTER - s[3])


# ---------------------------------------------------------------------------- env
class DeflectSpheresEnv(BatchedEnv):
    """LapGym's DeflectSpheresEnv, batched. See the module docstring and ``DeflectSpheresConfig``.

    Actions: one hook: 4 (PTSD of the right hook); two hooks: 8, the left hook's PTSD then the right hook's (sofa_env's
    ``_do_action_multi`` order). Discrete actions: ``Discrete(2d + 1)`` over the same ``d`` = 4 or 8 dimensions
    (sofa_env's scheme for two hooks: each action moves one PTSD component of one hook; the last is the no-op), each
    the continuous action of its ``discrete_actions`` row (the discrete speeds over the maximum speeds).

    Privileged critic observation (``privileged_critic=True``): the policy values, every sphere's deflection divided
    by the minimum deflection (N), the offset from the active hook's cutting centre to the active sphere divided by
    the workspace diagonal (3) and whether the matching tip touches the active sphere (1).
    """

    config_class = DeflectSpheresConfig
    task_name = "DeflectSpheres"
    rewards = REWARDS
    supported_observations = ("STATE", "RGB", "RGBD", "DEPTH")
    expert = "lapwarp.tasks.spatial.deflect_spheres:DeflectSpheresExpert"
    cfg: DeflectSpheresConfig

    def _build(self) -> World:
        cfg, n, dev, num = self.cfg, self.num_envs, self.wp_device, self.cfg.num_spheres
        self.num_hooks = 1 if cfg.single_instrument else 2
        builder = SceneBuilder(gravity=(0.0, 0.0, -9.81))
        sphere_mass = 0.5 * cfg.post_mass  # sofa_env spreads the post's mass over its stalk's two frames
        line = np.stack([np.linspace(-0.03, 0.03, num), np.zeros(num), np.full(num, 0.045)], axis=1)  # placeholder
        self.spheres = DeformableObject.particles(builder, line, mass=sphere_mass, damping=2.0, name="spheres")
        self.spheres.anchor(np.arange(num), stiffness=cfg.stalk_stiffness_limits[0])
        names = ("right_cauter", "left_cauter")[: self.num_hooks]
        specs = [InstrumentSpec(name=name, tpsd=tpsd, shape="cauter")
                 for name, tpsd in zip(names, cfg.instrument_configs(), strict=True)]
        self.rig = InstrumentRig(specs, builder, action_order=list(reversed(names)))  # left hook's PTSD first
        world = builder.finalize(num_envs=n, device=str(dev), substeps=cfg.physics_substeps, seed=cfg.seed)
        self.spheres.finalize(world)
        self.rig.finalize(world)
        self.contact = ContactSystem(world, capacity=cfg.contact_capacity, report_margin=5.0e-4)
        for k in range(num):  # one particle group per sphere: the reports tell which sphere a hook touches
            self.contact.add_particle_group([self.spheres.obj.particle_start + k], radius=cfg.sphere_radius,
                                            name=f"sphere{k}")
        self.rig.add_colliders(self.contact, mu_static=cfg.contact_friction)
        self.contact.finalize()
        self.rig_contacts = self.rig.contacts()

        self.task = Spheres()
        for name, dtype in (("anchors", wp.vec3), ("stiffness", float), ("state", wp.int32)):
            setattr(self.task, name, wp.zeros((n, num), dtype=dtype, device=dev))
        for name in ("active", "active_hook", "previous_active", "num_deflections", "tip_contact"):
            setattr(self.task, name, wp.zeros(n, dtype=wp.int32, device=dev))
        low, high = cfg.workspace
        self.workspace_diagonal = float(np.linalg.norm(high - low))
        self.params = p = Params()
        p.bounds, p.min_deflection = self.rig.bounds(low, high), cfg.min_deflection_distance
        p.tool_collision_distance, p.tool_only = cfg.tool_collision_distance, int(
            not cfg.allow_deflection_with_instrument_shaft)
        p.num_to_win, p.without_replacement = cfg.num_deflect_to_win, int(cfg.sampling_mode == "WITHOUT_REPLACEMENT")
        self._sag = (0.0, 0.0, -9.81 * sphere_mass / cfg.stalk_stiffness_limits[0])
        return world

    def _checked_state(self) -> list[wp.array]:
        return [*super()._checked_state(), self.task.anchors]

    def _observation_layout(self) -> ObservationLayout:
        two = int(self.num_hooks == 2)
        # PTSD stay within their limits and tips within the workspace (sofa_env's update rules): [-1, 1]. A hook can
        # push a sphere past the workspace box by at most its own and the sphere's radius (< 10 mm, |x| < 1.2), and
        # an unstable env is reset before it is observed: [-2, 2]
        spheres = (3 * self.cfg.num_spheres, -2.0, 2.0)
        return OBS.layout(spheres=spheres, active_sphere=(3, -2.0, 2.0), right_hook=(11, -1.0, 1.0),
                          active_hook=(two, 0.0, 1.0), left_hook=(11 * two, -1.0, 1.0))

    def _critic_layout(self) -> ObservationLayout:
        return self.obs_layout.extend(CRITIC, deflections=(self.cfg.num_spheres, 0.0, np.inf),
                                      offset_to_active=(3, -1.0, 1.0), tip_contact=(1, 0.0, 1.0))

    def _compute_features(self, env_mask: wp.array, features_out: wp.array2d) -> None:
        launching.launch(eval_deflect_features, dim=self.num_envs,
                         inputs=[env_mask, self.world.state.particle_q, self.rig.state, self.rig_contacts, self.task,
                                 self.params], outputs=[features_out], device=self.wp_device)

    def _update_task(self) -> None:
        launching.launch(update_active_sphere, dim=self.num_envs,
                         inputs=[self.world.state.particle_q, self.rig.state, self.features, self.params,
                                 self.world.rng], outputs=[self.task, self.baselines], device=self.wp_device)

    def _reset_task(self, env_mask: wp.array) -> None:
        cfg, w = self.cfg, self.world
        half = 0.5 * np.asarray(cfg.board_size) - cfg.sphere_margin
        lo_h, hi_h = cfg.sphere_height_limits
        launching.launch(reset_spheres, dim=self.num_envs,
                         inputs=[env_mask, wp.vec3(-half[0], -half[1], lo_h), wp.vec3(half[0], half[1], hi_h),
                                 cfg.min_sphere_distance, wp.vec2(*cfg.stalk_stiffness_limits), self.num_hooks, w.rng],
                         outputs=[self.task], device=self.wp_device)
        # spheres start at rest at their gravity equilibrium: no settle steps after a reset
        self.spheres.place_anchors(env_mask, self.task.anchors, self.task.stiffness, rest_offset=self._sag)
        self.rig.reset(env_mask, w.rng)

    def _compute_observations(self) -> None:
        launching.launch(observe_deflect, dim=self.num_envs,
                         inputs=[self.world.state.particle_q, self.rig.state, self.task, self.params,
                                 self.obs_layout.columns, self.critic_layout.columns, int(self.cfg.privileged_critic)],
                         outputs=[self.obs_frame, self.critic_frame], device=self.wp_device)

    # ------------------------------------------------------------------ visuals
    def _build_visual_scene(self) -> VisualScene:
        """Board (wood), stalks (grey tubes), spheres coloured by state (grey idle, blue/red active for the right/left
        hook, green done) and the hooks (right blue, left red; the rig's bodies).

        Spheres: one object per colour with one instance per sphere; ``update_visuals`` places the instance of each
        sphere's current colour and parks the other three beyond the far plane (the renderer's colours are per
        object, so the colour changes by which instance is visible). Camera per sofa_env: vertical FoV 45 degrees,
        near 5 mm, far 1.2 x the distance to the farthest workspace corner.
        """
        cfg, n, dev, num = self.cfg, self.num_envs, self.wp_device, self.cfg.num_spheres
        self.sphere_transforms = wp.zeros((n, 4 * num), dtype=wp.transform, device=dev)
        self.stalk_points = wp.zeros((n, 2 * num), dtype=wp.vec3, device=dev)
        board = trimesh.creation.box(extents=(*cfg.board_size, 0.005))
        board.apply_translation((0.0, 0.0, -0.0025))
        sphere_v, sphere_f = sphere_mesh(cfg.sphere_radius, subdivisions=2)
        objects = [VisualObject("board", "rigid", (246 / 255, 205 / 255, 139 / 255), 1, board.vertices, board.faces,
                                wp.full((n, 1), wp.transform_identity(), dtype=wp.transform, device=dev))]
        objects += [VisualObject(f"stalk{k}", "rod", (0.7, 0.7, 0.7), 2, points=self.stalk_points[:, 2 * k:2 * k + 2],
                                 radius=0.001) for k in range(num)]
        objects += [VisualObject(f"spheres_{name}", "rigid", SPHERE_COLORS[c], 3 + c, sphere_v, sphere_f,
                                 self.sphere_transforms[:, c * num:(c + 1) * num])
                    for c, name in enumerate(("idle", "active_right", "active_left", "done"))]
        objects += self.rig.visual_objects(SPHERE_COLORS[1:3], first_segmentation_id=7)
        low, high = cfg.workspace
        far = 1.2 * float(np.linalg.norm(np.array([low[0], high[1], low[2]]) - np.asarray(cfg.camera_position)))
        camera = fixed_camera(n, dev, cfg.camera_position, cfg.camera_fov_deg, near=0.005, far=far,
                              euler_deg=cfg.camera_euler_deg)
        return VisualScene(camera=camera, objects=objects, background=(0.1, 0.1, 0.12))

    def update_visuals(self) -> None:
        if self._visual_scene is None:
            return
        launching.launch(update_deflect_visuals, dim=self.num_envs, inputs=[self.world.state.particle_q, self.task],
                         outputs=[self.sphere_transforms, self.stalk_points], device=self.wp_device)

    # ------------------------------------------------------------------ privileged access (experts, tests)
    @property
    def instruments(self):
        """The hooks' ``TPSDInstruments`` (hook 0 = right, 1 = left)."""
        return self.rig.instruments

    def privileged_state(self) -> dict[str, torch.Tensor]:
        """Zero-copy torch views: sphere positions and anchors ``(N, S, 3)`` (m), sphere states ``(N, S)``, active
        sphere and hook ``(N,)``, deflections done ``(N,)``, hook PTSD ``(N, H, 4)`` (rad, m) and tip poses
        ``(N, H, 7)``."""
        t = self.task
        views = dict(sphere_positions=self.world.state.particle_q, anchors=t.anchors, sphere_state=t.state,
                     active=t.active, active_hook=t.active_hook, num_deflections=t.num_deflections,
                     ptsd=self.rig.ptsd, tip_pose=self.rig.pose)
        return {k: wp.to_torch(v) for k, v in views.items()}


# ---------------------------------------------------------------------------- expert
class DeflectSpheresExpert(Expert):
    """Drives the active hook's cutting centre through the active sphere; the other hook stays still.

    The target is a point ``contact - push`` from the sphere's rest position on the line to the cutting centre,
    where ``contact`` = sphere radius + hook radius: the hook closes in from wherever it is and, once touching, keeps
    pressing ``push`` (4.5 mm by default, above the 3 mm needed) into the sphere. The target is converted to PTSD
    with the inverse kinematics (the cutting centre lies on the shaft axis, 14.4 mm beyond the TPSD tip); the ideal
    action is the PTSD error over one step's maximum motion.
    """

    def __init__(self, env: DeflectSpheresEnv, push: float = 0.0045):
        super().__init__(env)
        self.push = float(push)
        self.error = wp.zeros((env.num_envs, env.num_hooks), dtype=wp.vec4, device=env.wp_device)
        to_internal = torch.tensor([math.pi / 180.0] * 3 + [1.0])
        dt = env.cfg.time_step * env.cfg.frame_skip
        self.step_size = (torch.tensor(env.cfg.maximum_state_velocity) * to_internal * dt).to(env.device)

    def __call__(self, obs=None) -> torch.Tensor:
        env = self.env
        with env._torch_stream_scope():
            launching.launch(expert_ptsd_errors, dim=(env.num_envs, env.num_hooks),
                             inputs=[env.world.state.particle_q, env.rig.state, env.task,
                                     env.cfg.sphere_radius + 0.8e-3, self.push], outputs=[self.error],
                             device=env.wp_device)
        error = wp.to_torch(self.error)  # (N, H, 4), hook 0 = right
        if env.num_hooks == 2:
            error = error[:, [1, 0]]  # action layout: left hook's PTSD, then the right hook's
        return self.policy_actions((error / self.step_size).reshape(env.num_envs, -1))
