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
from dataclasses import dataclass, field

import numpy as np
import torch
import trimesh
import warp as wp

from lapwarp.builder import SceneBuilder
from lapwarp.config import EnvConfig
from lapwarp.contact import ContactSystem
from lapwarp.env import BatchedEnv
from lapwarp.instrument_shapes import InstrumentShape
from lapwarp.instruments import (
    STATE_LIMITS_VIOLATED,
    WORKSPACE_VIOLATED,
    TPSDConfig,
    TPSDInstruments,
    discrete_action_table,
)
from lapwarp.kernels.contact import closest_segment_segment
from lapwarp.kernels.kinematics import point_to_ptsd
from lapwarp.kernels.random import rand_uniform
from lapwarp.visuals import CameraSpec, VisualObject, VisualScene, sphere_mesh
from lapwarp.world import World

wp.set_module_options({"enable_backward": False})

DEFLECT_FEATURES = (
    "action_violated_cartesian_workspace",
    "action_violated_state_limits",
    "tool_collision",
    "distance_to_active_sphere",
    "delta_distance_to_active_sphere",
    "deflection_of_inactive_spheres",
    "deflection_of_active_sphere",
    "delta_deflection_of_active_sphere",
    "done_with_active_sphere",
    "successful_task",
)
# Table A (the paper's sofa_zoo weights; sofa_env's own defaults are all 0).
DEFLECT_WEIGHTS = {
    "action_violated_cartesian_workspace": 0.0,
    "action_violated_state_limits": 0.0,
    "tool_collision": 0.0,
    "distance_to_active_sphere": 0.0,
    "delta_distance_to_active_sphere": -5.0,
    "deflection_of_inactive_spheres": -0.005,
    "deflection_of_active_sphere": 0.0,
    "delta_deflection_of_active_sphere": 1.0,
    "done_with_active_sphere": 10.0,
    "successful_task": 100.0,
}
SAMPLING_MODES = ("WITH_REPLACEMENT", "WITHOUT_REPLACEMENT")

#: Sphere states (sofa_env's ``Post.State``) and their colours.
IDLE, ACTIVE_RIGHT, ACTIVE_LEFT, DONE = 0, 1, 2, 3
SPHERE_COLORS = ((0.7, 0.7, 0.7), (0.0, 0.0, 1.0), (1.0, 0.0, 0.0), (0.0, 1.0, 0.0))
#: The cauter's cutting centre in its tip frame (sofa_env's ``cutting_center_index``): 14.4 mm along the shaft.
CUTTING_CENTER_OFFSET = 0.0144
_HIDDEN = wp.constant(wp.vec3(0.0, 0.0, -1000.0))  # far beyond the camera's far plane: culled


@dataclass(kw_only=True)
class DeflectSpheresConfig(EnvConfig):
    """DeflectSpheresEnv parameters (Table B, Table C); lengths in metres, angles in degrees, stiffness in N/m.

    Attributes:
        board_size: (width along x, depth along y) of the board (m), 100 x 100 mm.
        workspace_height: height of the box over the board the hooks work in (m); the Cartesian workspace of the
            hook tips is the board enlarged by 10 mm on every side, from z = -10 mm to ``workspace_height`` + 10 mm.
        num_spheres: spheres on the board (sofa_env's ``num_objects``).
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
        physics_substeps: XPBD substeps per physics step.
        max_episode_steps: time limit; ``None`` = 500 x ``num_deflect_to_win`` (Table C).
    """

    time_step: float = 0.1
    frame_skip: int = 1
    max_episode_steps: int | None = None
    board_size: tuple[float, float] = (0.1, 0.1)
    workspace_height: float = 0.08
    num_spheres: int = 5
    sphere_height_limits: tuple[float, float] = (0.03, 0.06)
    sphere_margin: float = 0.005
    min_sphere_distance: float = 0.02
    stalk_stiffness_limits: tuple[float, float] = (1.0e3, 1.0e3)
    post_mass: float = 0.1
    sphere_radius: float = 0.006
    single_instrument: bool = True
    num_deflect_to_win: int = 5
    min_deflection_distance: float = 0.003
    allow_deflection_with_instrument_shaft: bool = False
    sampling_mode: str = "WITHOUT_REPLACEMENT"
    instrument_reset_noise: tuple[float, float, float, float] = (30.0, 30.0, 30.0, 0.01)
    maximum_state_velocity: tuple[float, float, float, float] = (20.0, 20.0, 20.0, 0.02)
    discrete_action_magnitude: tuple[float, float, float, float] = (15.0, 15.0, 15.0, 0.01)
    right_start_ptsd: tuple[float, float, float, float] = (-44.0, 76.0, 0.0, 0.04)
    left_start_ptsd: tuple[float, float, float, float] = (44.0, 45.0, 0.0, 0.015)
    instrument_state_low: tuple[float, float, float, float] = (-90.0, -90.0, -90.0, 0.0)
    instrument_state_high: tuple[float, float, float, float] = (90.0, 90.0, 90.0, 0.3)
    contact_friction: float = 1.0
    tool_collision_distance: float = 0.0015
    camera_position: tuple[float, float, float] = (0.0, -0.14, 0.12)
    camera_euler_deg: tuple[float, float, float] = (58.0, 0.0, 0.0)
    camera_fov_deg: float = 45.0
    physics_substeps: int = 10
    reward_weights: dict[str, float] = field(default_factory=dict)

    def __post_init__(self) -> None:
        if self.max_episode_steps is None and isinstance(self.num_deflect_to_win, int):
            self.max_episode_steps = 500 * self.num_deflect_to_win

    def validate(self, reward_features, supported_observations) -> None:
        super().validate(reward_features, supported_observations)
        if self.sampling_mode not in SAMPLING_MODES:
            raise ValueError(f"sampling_mode={self.sampling_mode!r} is not valid; choose one of {list(SAMPLING_MODES)}")
        for name in ("num_spheres", "num_deflect_to_win", "physics_substeps"):
            value = getattr(self, name)
            if not isinstance(value, int) or value < 1:
                raise ValueError(f"{name} must be an integer >= 1, got {value!r}")
        if self.sampling_mode == "WITHOUT_REPLACEMENT" and self.num_deflect_to_win > self.num_spheres:
            raise ValueError(f"num_deflect_to_win={self.num_deflect_to_win} exceeds num_spheres={self.num_spheres}, "
                             "which WITHOUT_REPLACEMENT cannot reach")
        for name in ("workspace_height", "post_mass", "sphere_radius", "min_deflection_distance",
                     "tool_collision_distance", "camera_fov_deg"):
            if not getattr(self, name) > 0.0:
                raise ValueError(f"{name} must be positive, got {getattr(self, name)!r}")
        if len(self.board_size) != 2 or min(self.board_size) <= 2.0 * self.sphere_margin:
            raise ValueError(f"board_size must be (width, depth) > 2 * sphere_margin, got {self.board_size}")
        lo, hi = self.sphere_height_limits
        if not 0.0 < lo <= hi <= self.workspace_height:
            raise ValueError(f"sphere_height_limits must satisfy 0 < low <= high <= workspace_height, got {(lo, hi)}")
        klo, khi = self.stalk_stiffness_limits
        if not 0.0 < klo <= khi:
            raise ValueError(f"stalk_stiffness_limits must satisfy 0 < low <= high, got {(klo, khi)}")
        if self.min_sphere_distance < 0.0 or self.sphere_margin < 0.0 or self.contact_friction < 0.0:
            raise ValueError("min_sphere_distance, sphere_margin and contact_friction must be >= 0")
        for name in ("maximum_state_velocity", "discrete_action_magnitude", "instrument_reset_noise"):
            v = np.asarray(getattr(self, name), float)
            if v.shape != (4,) or np.any(v < 0.0) or not np.all(np.isfinite(v)):
                raise ValueError(f"{name} must be 4 finite values >= 0, got {getattr(self, name)!r}")

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
        common = dict(rcm_euler_deg=(-180.0, 0.0, 0.0), state_low=self.instrument_state_low,
                      state_high=self.instrument_state_high, workspace_low=tuple(low), workspace_high=tuple(high),
                      max_velocity=self.maximum_state_velocity, discrete_magnitude=self.discrete_action_magnitude,
                      ptsd_noise=self.instrument_reset_noise)
        configs = [TPSDConfig(rcm_position=(high[0], low[1], high[2]), start_ptsd=self.right_start_ptsd, **common)]
        if not self.single_instrument:
            configs.append(TPSDConfig(rcm_position=(low[0], low[1], high[2]), start_ptsd=self.left_start_ptsd,
                                      **common))
        return configs


# ---------------------------------------------------------------------------- kernels
@wp.func
def cutting_center(pose: wp.transform) -> wp.vec3:
    return wp.transform_point(pose, wp.vec3(0.0, 0.0, CUTTING_CENTER_OFFSET))


@wp.func
def draw_index(rng: wp.array(dtype=wp.uint32), env: int, count: int) -> int:
    """Uniform integer in [0, count)."""
    return wp.min(int(rand_uniform(rng, env, 0.0, float(count))), count - 1)


@wp.func
def draw_active_sphere(rng: wp.array(dtype=wp.uint32), env: int, num_hooks: int, without_replacement: int,
                       sphere_state: wp.array2d(dtype=wp.int32)) -> wp.vec2i:
    """(sphere, hook) of a new active sphere: uniform over the valid spheres, uniform hook with two hooks."""
    num = sphere_state.shape[1]
    count = int(0)
    for k in range(num):
        if without_replacement == 0 or sphere_state[env, k] != DONE:
            count += 1
    pick = draw_index(rng, env, wp.max(count, 1))
    chosen = int(0)
    seen = int(0)
    for k in range(num):
        if without_replacement == 0 or sphere_state[env, k] != DONE:
            if seen == pick:
                chosen = k
            seen += 1
    hook = int(0)
    if num_hooks > 1:
        hook = draw_index(rng, env, 2)
    return wp.vec2i(chosen, hook)


@wp.kernel
def scale_deflect_actions(
    actions: wp.array2d(dtype=wp.float32),
    action_columns: wp.array(dtype=wp.int32),
    scale: wp.array(dtype=wp.vec4),
    dt: float,
    delta_out: wp.array2d(dtype=wp.vec4),
):
    """``delta = a * scale * dt`` per hook; ``scale`` is the maximum velocity (continuous actions, already clipped)
    or 1 (discrete actions, whose table holds the velocities themselves), in rad/s and m/s."""
    env, k = wp.tid()
    col = action_columns[k]
    s = scale[k]
    delta_out[env, k] = wp.vec4(actions[env, col] * s[0], actions[env, col + 1] * s[1], actions[env, col + 2] * s[2],
                                actions[env, col + 3] * s[3]) * dt


@wp.kernel
def pose_hook_bodies(
    tip_pose: wp.array2d(dtype=wp.transform),
    env_mask: wp.array(dtype=wp.int32),
    use_mask: int,
    body_q: wp.array2d(dtype=wp.transform),
    body_q_prev: wp.array2d(dtype=wp.transform),
    body_q_initial: wp.array2d(dtype=wp.transform),
):
    """Hook ``k`` rides on body ``k`` (its tip frame). With ``use_mask`` (reset) the start-of-step and initial poses
    of the masked envs are set too, so the first step after a reset does not sweep the hook from its old pose."""
    env, k = wp.tid()
    if use_mask != 0:
        if env_mask[env] == 0:
            return
        body_q_prev[env, k] = tip_pose[env, k]
        body_q_initial[env, k] = tip_pose[env, k]
    body_q[env, k] = tip_pose[env, k]


@wp.kernel
def reset_spheres(
    env_mask: wp.array(dtype=wp.int32),
    xy_low: wp.vec2,
    xy_high: wp.vec2,
    height_low: float,
    height_high: float,
    min_distance: float,
    stiffness_low: float,
    stiffness_high: float,
    sag: wp.vec3,
    num_hooks: int,
    rng: wp.array(dtype=wp.uint32),
    anchors: wp.array2d(dtype=wp.vec3),
    particle_q: wp.array2d(dtype=wp.vec3),
    particle_qd: wp.array2d(dtype=wp.vec3),
    initial_q: wp.array2d(dtype=wp.vec3),
    attach_offset: wp.array2d(dtype=wp.vec3),
    initial_offset: wp.array2d(dtype=wp.vec3),
    attach_compliance: wp.array2d(dtype=float),
    initial_compliance: wp.array2d(dtype=float),
    sphere_state: wp.array2d(dtype=wp.int32),
    active: wp.array(dtype=wp.int32),
    active_hook: wp.array(dtype=wp.int32),
    previous_active: wp.array(dtype=wp.int32),
    num_deflections: wp.array(dtype=wp.int32),
):
    """New sphere rest positions (rejection sampling for the minimum distance), stiffnesses and active sphere.

    Sphere ``k`` is particle ``k`` and attachment slot ``k``. Each sphere gets up to 200 candidates; if none keeps
    the minimum distance (only possible with crowded custom settings) the candidate farthest from the others is
    kept, so the kernel always ends. The sphere starts at rest at its gravity equilibrium ``anchor + sag``; the
    rows of the World's initial state get the same values, so a stability restore keeps this episode's layout.
    """
    env = wp.tid()
    if env_mask[env] == 0:
        return
    num = anchors.shape[1]
    for k in range(num):
        best = wp.vec3(0.0)
        best_d = float(-1.0)
        for _ in range(200):
            c = wp.vec3(rand_uniform(rng, env, xy_low[0], xy_high[0]), rand_uniform(rng, env, xy_low[1], xy_high[1]),
                        rand_uniform(rng, env, height_low, height_high))
            d = float(1.0e9)
            for j in range(k):
                d = wp.min(d, wp.length(c - anchors[env, j]))
            if d > best_d:
                best = c
                best_d = d
            if best_d >= min_distance:
                break
        anchors[env, k] = best
        particle_q[env, k] = best + sag
        initial_q[env, k] = best + sag
        particle_qd[env, k] = wp.vec3(0.0)
        attach_offset[env, k] = best
        initial_offset[env, k] = best
        compliance = 1.0 / rand_uniform(rng, env, stiffness_low, stiffness_high)
        attach_compliance[env, k] = compliance
        initial_compliance[env, k] = compliance
        sphere_state[env, k] = IDLE
    pick = draw_active_sphere(rng, env, num_hooks, 0, sphere_state)
    active[env] = pick[0]
    active_hook[env] = pick[1]
    sphere_state[env, pick[0]] = ACTIVE_RIGHT + pick[1]
    previous_active[env] = -1
    num_deflections[env] = 0


@wp.kernel
def init_previous_features(
    env_mask: wp.array(dtype=wp.int32),
    particle_q: wp.array2d(dtype=wp.vec3),
    tip_pose: wp.array2d(dtype=wp.transform),
    active: wp.array(dtype=wp.int32),
    active_hook: wp.array(dtype=wp.int32),
    previous_distance: wp.array(dtype=wp.float32),
    previous_deflection: wp.array(dtype=wp.float32),
):
    """Baselines of the delta features after a reset (no hook touches a sphere yet, so the active deflection
    feature starts at 0)."""
    env = wp.tid()
    if env_mask[env] == 0:
        return
    cc = cutting_center(tip_pose[env, active_hook[env]])
    previous_distance[env] = wp.length(cc - particle_q[env, active[env]])
    previous_deflection[env] = 0.0


@wp.kernel
def eval_deflect_features(
    particle_q: wp.array2d(dtype=wp.vec3),
    anchors: wp.array2d(dtype=wp.vec3),
    tip_pose: wp.array2d(dtype=wp.transform),
    rcm: wp.array2d(dtype=wp.transform),
    flags: wp.array2d(dtype=wp.int32),
    report_count: wp.array2d(dtype=wp.int32),
    pair_index: wp.array2d(dtype=wp.int32),
    shape_hook: wp.array(dtype=wp.int32),
    shape_is_tip: wp.array(dtype=wp.int32),
    inv_diagonal: float,
    inv_min_deflection: float,
    min_deflection: float,
    tool_collision_distance: float,
    allow_shaft: int,
    without_replacement: int,
    num_to_win: int,
    rng: wp.array(dtype=wp.uint32),
    sphere_state: wp.array2d(dtype=wp.int32),
    active: wp.array(dtype=wp.int32),
    active_hook: wp.array(dtype=wp.int32),
    previous_active: wp.array(dtype=wp.int32),
    num_deflections: wp.array(dtype=wp.int32),
    previous_distance: wp.array(dtype=wp.float32),
    previous_deflection: wp.array(dtype=wp.float32),
    tip_contact: wp.array(dtype=wp.int32),
    features_out: wp.array2d(dtype=wp.float32),
    success_out: wp.array(dtype=wp.int32),
    failure_out: wp.array(dtype=wp.int32),
):
    """Reward features (sofa_env's ``_get_reward_features`` and ``_get_reward``) and the sphere bookkeeping."""
    env = wp.tid()
    num_hooks = tip_pose.shape[1]
    num = anchors.shape[1]
    a = active[env]
    hook = active_hook[env]

    ws = int(0)
    limits = int(0)
    for h in range(num_hooks):
        if (flags[env, h] & WORKSPACE_VIOLATED) != 0:
            ws += 1
        if (flags[env, h] & STATE_LIMITS_VIOLATED) != 0:
            limits += 1
    collision = int(0)
    if num_hooks > 1:
        p1 = wp.transform_get_translation(rcm[env, 0])
        q1 = cutting_center(tip_pose[env, 0])
        p2 = wp.transform_get_translation(rcm[env, 1])
        q2 = cutting_center(tip_pose[env, 1])
        st = closest_segment_segment(p1, q1, p2, q2)
        if wp.length((p1 + (q1 - p1) * st[0]) - (p2 + (q2 - p2) * st[1])) < tool_collision_distance:
            collision = 1

    # contact of the matching hook with the active sphere (sphere k is particle group k)
    valid = int(0)
    for s in range(shape_hook.shape[0]):
        if shape_hook[s] == hook and (shape_is_tip[s] != 0 or allow_shaft != 0):
            pair = pair_index[s, a]
            if pair >= 0 and report_count[env, pair] > 0:
                valid = 1
    tip_contact[env] = valid

    dist = wp.length(cutting_center(tip_pose[env, hook]) - particle_q[env, a])
    deflection = wp.length(particle_q[env, a] - anchors[env, a])
    inactive = float(0.0)
    for k in range(num):
        if k != a and k != previous_active[env]:
            inactive += wp.length(particle_q[env, k] - anchors[env, k]) * inv_min_deflection
    active_feature = float(valid) * deflection * inv_min_deflection
    done = int(0)
    if valid != 0 and deflection >= min_deflection:
        done = 1
    count = num_deflections[env] + done
    ok = int(0)
    if count >= num_to_win:
        ok = 1

    features_out[env, 0] = float(ws)
    features_out[env, 1] = float(limits)
    features_out[env, 2] = float(collision)
    features_out[env, 3] = wp.clamp(dist * inv_diagonal, -1.0, 1.0)
    features_out[env, 4] = wp.clamp((dist - previous_distance[env]) * inv_diagonal, -1.0, 1.0)
    features_out[env, 5] = inactive
    features_out[env, 6] = active_feature
    features_out[env, 7] = active_feature - previous_deflection[env]
    features_out[env, 8] = float(done)
    features_out[env, 9] = float(ok)
    success_out[env] = ok
    failure_out[env] = 0

    num_deflections[env] = count
    previous_distance[env] = dist
    previous_deflection[env] = active_feature
    if done != 0:
        if without_replacement != 0:
            sphere_state[env, a] = DONE
        else:
            sphere_state[env, a] = IDLE
        if ok == 0:
            pick = draw_active_sphere(rng, env, num_hooks, without_replacement, sphere_state)
            previous_active[env] = a
            active[env] = pick[0]
            active_hook[env] = pick[1]
            sphere_state[env, pick[0]] = ACTIVE_RIGHT + pick[1]
            # baselines of the delta features restart from the new sphere (sofa_env: without the contact factor)
            previous_distance[env] = wp.length(cutting_center(tip_pose[env, pick[1]]) - particle_q[env, pick[0]])
            previous_deflection[env] = wp.length(particle_q[env, pick[0]] - anchors[env, pick[0]]) * inv_min_deflection


@wp.func
def to_unit(x: float, low: float, high: float) -> float:
    return 2.0 * (x - low) / (high - low) - 1.0


@wp.kernel
def observe_deflect(
    particle_q: wp.array2d(dtype=wp.vec3),
    anchors: wp.array2d(dtype=wp.vec3),
    ptsd: wp.array2d(dtype=wp.vec4),
    tip_pose: wp.array2d(dtype=wp.transform),
    active: wp.array(dtype=wp.int32),
    active_hook: wp.array(dtype=wp.int32),
    tip_contact: wp.array(dtype=wp.int32),
    ws_low: wp.vec3,
    ws_high: wp.vec3,
    state_low: wp.vec4,
    state_high: wp.vec4,
    inv_diagonal: float,
    inv_min_deflection: float,
    privileged: int,
    obs_out: wp.array2d(dtype=wp.float32),
    critic_out: wp.array2d(dtype=wp.float32),
):
    """sofa_env's STATE order: spheres, active sphere, right PTSD and pose, [active hook, left PTSD and pose]."""
    env = wp.tid()
    num = particle_q.shape[1]
    num_hooks = ptsd.shape[1]
    for k in range(num):
        p = particle_q[env, k]
        for i in range(3):
            obs_out[env, 3 * k + i] = to_unit(p[i], ws_low[i], ws_high[i])
    pa = particle_q[env, active[env]]
    col = 3 * num
    for i in range(3):
        obs_out[env, col + i] = to_unit(pa[i], ws_low[i], ws_high[i])
    col += 3
    for h in range(num_hooks):
        if h == 1:
            obs_out[env, col] = float(active_hook[env])
            col += 1
        s = ptsd[env, h]
        for i in range(4):
            obs_out[env, col + i] = to_unit(s[i], state_low[i], state_high[i])
        pose = tip_pose[env, h]
        p = wp.transform_get_translation(pose)
        q = wp.transform_get_rotation(pose)
        for i in range(3):
            obs_out[env, col + 4 + i] = to_unit(p[i], ws_low[i], ws_high[i])
        for i in range(4):
            obs_out[env, col + 7 + i] = q[i]
        col += 11
    if privileged != 0:
        for i in range(col):
            critic_out[env, i] = obs_out[env, i]
        for k in range(num):
            critic_out[env, col + k] = wp.length(particle_q[env, k] - anchors[env, k]) * inv_min_deflection
        rel = (pa - cutting_center(tip_pose[env, active_hook[env]])) * inv_diagonal
        for i in range(3):
            critic_out[env, col + num + i] = rel[i]
        critic_out[env, col + num + 3] = float(tip_contact[env])


@wp.kernel
def update_deflect_visuals(
    particle_q: wp.array2d(dtype=wp.vec3),
    tip_pose: wp.array2d(dtype=wp.transform),
    sphere_state: wp.array2d(dtype=wp.int32),
    sphere_out: wp.array2d(dtype=wp.transform),
    hook_out: wp.array2d(dtype=wp.transform),
):
    """Sphere ``k`` is drawn by instance ``k`` of the object of its state (columns ``state * N + k``); the other
    three instances of that sphere are parked beyond the far plane."""
    env = wp.tid()
    num = particle_q.shape[1]
    for k in range(num):
        st = sphere_state[env, k]
        for c in range(4):
            p = _HIDDEN
            if c == st:
                p = particle_q[env, k]
            sphere_out[env, c * num + k] = wp.transform(p, wp.quat_identity())
    for h in range(tip_pose.shape[1]):
        hook_out[env, h] = tip_pose[env, h]


@wp.kernel
def update_stalk(
    particle_q: wp.array2d(dtype=wp.vec3),
    anchors: wp.array2d(dtype=wp.vec3),
    k: int,
    points_out: wp.array2d(dtype=wp.vec3),
):
    """The stalk of sphere ``k``: a line from its base on the board to the sphere centre."""
    env = wp.tid()
    base = anchors[env, k]
    points_out[env, 0] = wp.vec3(base[0], base[1], 0.0)
    points_out[env, 1] = particle_q[env, k]


@wp.kernel
def expert_ptsd_targets(
    particle_q: wp.array2d(dtype=wp.vec3),
    anchors: wp.array2d(dtype=wp.vec3),
    tip_pose: wp.array2d(dtype=wp.transform),
    rcm: wp.array2d(dtype=wp.transform),
    ptsd: wp.array2d(dtype=wp.vec4),
    active: wp.array(dtype=wp.int32),
    active_hook: wp.array(dtype=wp.int32),
    contact_distance: float,
    push: float,
    error_out: wp.array2d(dtype=wp.vec4),
):
    """PTSD error of each hook towards the expert's target (see ``DeflectSpheresExpert``); zero for idle hooks."""
    env, h = wp.tid()
    error_out[env, h] = wp.vec4(0.0)
    if h != active_hook[env]:
        return
    a = active[env]
    anchor = anchors[env, a]
    cc = cutting_center(tip_pose[env, h])
    u = cc - anchor
    if wp.length(u) < 1.0e-6:
        u = wp.vec3(0.0, 0.0, 1.0)
    u = wp.normalize(u)
    target = anchor + u * (contact_distance - push)
    s = ptsd[env, h]
    goal = point_to_ptsd(rcm[env, h], target, s[2])
    # the cutting centre lies on the shaft axis, CUTTING_CENTER_OFFSET beyond the TPSD tip
    error_out[env, h] = wp.vec4(goal[0] - s[0], goal[1] - s[1], 0.0, goal[3] - CUTTING_CENTER_OFFSET - s[3])


# ---------------------------------------------------------------------------- env
def _rotation_from_euler_deg(euler) -> wp.quat:
    q = wp.quat_identity()
    for axis, angle in zip(((1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0)), euler, strict=True):
        q = q * wp.quat_from_axis_angle(wp.vec3(*axis), math.radians(angle))
    return q


class DeflectSpheresEnv(BatchedEnv):
    """LapGym's DeflectSpheresEnv, batched. See the module docstring and ``DeflectSpheresConfig``.

    Actions: one hook: 4 (PTSD of the right hook); two hooks: 8, the left hook's PTSD then the right hook's (sofa_env's
    ``_do_action_multi`` order). Discrete actions: ``Discrete(2d + 1)`` over the same ``d`` = 4 or 8 dimensions
    (sofa_env's scheme for two hooks: each action moves one PTSD component of one hook; the last is the no-op).

    Privileged critic observation (``privileged_critic=True``): the policy values, every sphere's deflection divided
    by the minimum deflection (N), the offset from the active hook's cutting centre to the active sphere divided by
    the workspace diagonal (3) and whether the matching tip touches the active sphere (1).
    """

    config_class = DeflectSpheresConfig
    task_name = "DeflectSpheres"
    reward_features = DEFLECT_FEATURES
    default_reward_weights = DEFLECT_WEIGHTS
    supported_observations = ("STATE", "RGB", "RGBD", "DEPTH")
    cfg: DeflectSpheresConfig

    def _build(self) -> World:
        cfg, n, dev = self.cfg, self.num_envs, self.wp_device
        self.num_hooks = 1 if cfg.single_instrument else 2
        num = cfg.num_spheres
        low, high = cfg.workspace
        self._ws_low, self._ws_high = wp.vec3(*low), wp.vec3(*high)
        self.workspace_diagonal = float(np.linalg.norm(high - low))

        builder = SceneBuilder(gravity=(0.0, 0.0, -9.81))
        sphere_mass = 0.5 * cfg.post_mass
        # placeholder layout (a grid); every reset draws the real one per env
        xs = np.linspace(-0.03, 0.03, num)
        self.spheres = builder.add_particles(np.stack([xs, np.zeros(num), np.full(num, 0.045)], axis=1),
                                             mass=sphere_mass, damping=2.0, name="spheres")
        self.hook_shapes = [InstrumentShape(builder, kind="cauter", name=name)
                            for name in ("right_cauter", "left_cauter")[: self.num_hooks]]
        for k in range(num):
            builder.add_attachment(k, body=-1, compliance=1.0 / cfg.stalk_stiffness_limits[0])
        world = builder.finalize(num_envs=n, device=str(dev), substeps=cfg.physics_substeps, seed=cfg.seed)
        # hook k's tip frame is body k (the kernels rely on it)
        assert [s.shaft_body for s in self.hook_shapes] == list(range(self.num_hooks))

        self.contact = ContactSystem(world, capacity=16, report_margin=5.0e-4)
        # one particle group per sphere, so the reports tell which sphere a hook touches (group k = sphere k)
        for k in range(num):
            self.contact.add_particle_group([k], radius=cfg.sphere_radius, name=f"sphere{k}")
        shape_hook, shape_tip = [], []
        for h, shape in enumerate(self.hook_shapes):
            ids = shape.add_colliders(self.contact, mu_static=cfg.contact_friction)
            for role, sids in ids.items():
                for _ in sids:
                    shape_hook.append(h)
                    shape_tip.append(int(role == "tool"))
        self.contact.finalize()
        # shape ids are assigned in insertion order: role lists were appended shape by shape
        order = np.argsort(np.concatenate([sids for shape in self.hook_shapes for sids in shape.shape_ids.values()]))
        self.shape_hook = wp.array(np.asarray(shape_hook, np.int32)[order], dtype=wp.int32, device=dev)
        self.shape_is_tip = wp.array(np.asarray(shape_tip, np.int32)[order], dtype=wp.int32, device=dev)

        self.instruments = TPSDInstruments(cfg.instrument_configs(), n, device=str(dev),
                                           action_columns=[0] if self.num_hooks == 1 else [4, 0])
        self._sag = wp.vec3(0.0, 0.0, -9.81 * sphere_mass / cfg.stalk_stiffness_limits[0])
        self.anchors = wp.zeros((n, num), dtype=wp.vec3, device=dev)
        self.sphere_state = wp.zeros((n, num), dtype=wp.int32, device=dev)
        self.active = wp.zeros(n, dtype=wp.int32, device=dev)
        self.active_hook = wp.zeros(n, dtype=wp.int32, device=dev)
        self.previous_active = wp.full(n, -1, dtype=wp.int32, device=dev)
        self.num_deflections = wp.zeros(n, dtype=wp.int32, device=dev)
        self.previous_distance = wp.zeros(n, dtype=wp.float32, device=dev)
        self.previous_deflection = wp.zeros(n, dtype=wp.float32, device=dev)
        self.tip_contact = wp.zeros(n, dtype=wp.int32, device=dev)
        deg = math.pi / 180.0
        to_internal = np.array([deg, deg, deg, 1.0])
        if cfg.action_type == "DISCRETE":
            scale = np.ones((self.num_hooks, 4))  # the discrete table holds velocities (rad/s, m/s)
        else:
            scale = np.tile(np.asarray(cfg.maximum_state_velocity) * to_internal, (self.num_hooks, 1))
        self._action_scale = wp.array(scale.astype(np.float32), dtype=wp.vec4, device=dev)
        self._state_low = wp.vec4(*(np.asarray(cfg.instrument_state_low) * to_internal))
        self._state_high = wp.vec4(*(np.asarray(cfg.instrument_state_high) * to_internal))
        self._visual_scene: VisualScene | None = None
        return world

    def _action_dim(self) -> int:
        return 4 * self.num_hooks

    def _observation_dim(self) -> int:
        return 3 * self.cfg.num_spheres + 3 + 11 * self.num_hooks + (self.num_hooks - 1)

    def _critic_observation_dim(self) -> int:
        return self._observation_dim() + self.cfg.num_spheres + 4

    def _discrete_action_table(self) -> np.ndarray:
        # rows 2i / 2i+1 = +-e_i at the discrete speed (rad/s, m/s), last row the no-op; one hook moves per action
        deg = math.pi / 180.0
        mags = np.tile(np.asarray(self.cfg.discrete_action_magnitude) * np.array([deg, deg, deg, 1.0]),
                       self.num_hooks)
        return discrete_action_table(mags)

    def _apply_actions(self, actions: wp.array2d) -> None:
        wp.launch(scale_deflect_actions, dim=(self.num_envs, self.num_hooks),
                  inputs=[actions, self.instruments.action_columns, self._action_scale, self.cfg.time_step],
                  outputs=[self.instruments.delta], device=self.wp_device)

    def _before_physics_step(self) -> None:
        self.instruments.step()
        w = self.world
        wp.launch(pose_hook_bodies, dim=(self.num_envs, self.num_hooks),
                  inputs=[self.instruments.pose, self.reset_mask, 0],
                  outputs=[w.state.body_q, w.body_q_previous, w._start_state.body_q], device=self.wp_device)

    def _compute_features(self) -> None:
        cfg, c = self.cfg, self.contact
        wp.launch(eval_deflect_features, dim=self.num_envs,
                  inputs=[self.world.state.particle_q, self.anchors, self.instruments.pose, self.instruments.rcm,
                          self.instruments.flags, c.report_count, c.pair_index, self.shape_hook, self.shape_is_tip,
                          1.0 / self.workspace_diagonal, 1.0 / cfg.min_deflection_distance,
                          cfg.min_deflection_distance, cfg.tool_collision_distance,
                          int(cfg.allow_deflection_with_instrument_shaft),
                          int(cfg.sampling_mode == "WITHOUT_REPLACEMENT"), cfg.num_deflect_to_win, self.world.rng],
                  outputs=[self.sphere_state, self.active, self.active_hook, self.previous_active,
                           self.num_deflections, self.previous_distance, self.previous_deflection, self.tip_contact,
                           self.features, self.success, self.failure], device=self.wp_device)

    def _reset_task(self, env_mask: wp.array) -> None:
        cfg, w, dev = self.cfg, self.world, self.wp_device
        half = 0.5 * np.asarray(cfg.board_size) - cfg.sphere_margin
        s, init = w.state, w._start_state
        wp.launch(reset_spheres, dim=self.num_envs,
                  inputs=[env_mask, wp.vec2(*(-half)), wp.vec2(*half), cfg.sphere_height_limits[0],
                          cfg.sphere_height_limits[1], cfg.min_sphere_distance, cfg.stalk_stiffness_limits[0],
                          cfg.stalk_stiffness_limits[1], self._sag, self.num_hooks, w.rng],
                  outputs=[self.anchors, s.particle_q, s.particle_qd, init.particle_q, s.attach_offset,
                           init.attach_offset, s.attach_compliance, init.attach_compliance, self.sphere_state,
                           self.active, self.active_hook, self.previous_active, self.num_deflections], device=dev)
        self.instruments.reset(env_mask, w.rng)
        wp.launch(pose_hook_bodies, dim=(self.num_envs, self.num_hooks),
                  inputs=[self.instruments.pose, env_mask, 1],
                  outputs=[s.body_q, w.body_q_previous, init.body_q], device=dev)
        wp.launch(init_previous_features, dim=self.num_envs,
                  inputs=[env_mask, s.particle_q, self.instruments.pose, self.active, self.active_hook],
                  outputs=[self.previous_distance, self.previous_deflection], device=dev)

    def _compute_observations(self) -> None:
        critic = self.critic_frame if self.cfg.privileged_critic else self.obs_frame
        wp.launch(observe_deflect, dim=self.num_envs,
                  inputs=[self.world.state.particle_q, self.anchors, self.instruments.ptsd, self.instruments.pose,
                          self.active, self.active_hook, self.tip_contact, self._ws_low, self._ws_high,
                          self._state_low, self._state_high, 1.0 / self.workspace_diagonal,
                          1.0 / self.cfg.min_deflection_distance, int(self.cfg.privileged_critic)],
                  outputs=[self.obs_frame, critic], device=self.wp_device)

    # ------------------------------------------------------------------ visuals
    def camera_pose(self) -> wp.transform:
        """sofa_env's camera: at (0, -140, 120) mm, rotated 58 degrees about x, looking along its local -Z."""
        return wp.transform(wp.vec3(*self.cfg.camera_position), _rotation_from_euler_deg(self.cfg.camera_euler_deg))

    def visual_scene(self) -> VisualScene:
        """Board (wood), stalks (grey tubes), spheres coloured by state (grey idle, blue/red active for the right/left
        hook, green done) and the hooks (right blue, left red).

        Spheres: one object per colour with one instance per sphere; ``update_visuals`` places the instance of each
        sphere's current colour and parks the other three beyond the far plane (the renderer's colours are per
        object, so the colour changes by which instance is visible). Camera per sofa_env: vertical FoV 45 degrees,
        near 5 mm, far 1.2 x the distance to the farthest workspace corner.
        """
        if self._visual_scene is None:
            cfg, n, dev, num = self.cfg, self.num_envs, self.wp_device, self.cfg.num_spheres
            self.sphere_transforms = wp.zeros((n, 4 * num), dtype=wp.transform, device=dev)
            self.hook_transforms = wp.zeros((n, self.num_hooks), dtype=wp.transform, device=dev)
            self.board_transforms = wp.full((n, 1), wp.transform_identity(), dtype=wp.transform, device=dev)
            self.stalk_points = [wp.zeros((n, 2), dtype=wp.vec3, device=dev) for _ in range(num)]
            w, d = cfg.board_size
            board = trimesh.creation.box(extents=(w, d, 0.005))
            board.apply_translation((0.0, 0.0, -0.0025))
            sphere_v, sphere_f = sphere_mesh(cfg.sphere_radius, subdivisions=2)
            low, high = cfg.workspace
            cam = np.asarray(cfg.camera_position)
            far = 1.2 * float(np.linalg.norm(np.array([low[0], high[1], low[2]]) - cam))
            poses = wp.array([self.camera_pose()] * n, dtype=wp.transform, device=dev)
            objects = [VisualObject("board", "rigid", (246 / 255, 205 / 255, 139 / 255), 1,
                                    board.vertices, board.faces, self.board_transforms)]
            for k in range(num):
                objects.append(VisualObject(f"stalk{k}", "rod", (0.7, 0.7, 0.7), 2, points=self.stalk_points[k],
                                            radius=0.001))
            for c, name in enumerate(("idle", "active_right", "active_left", "done")):
                objects.append(VisualObject(f"spheres_{name}", "rigid", SPHERE_COLORS[c], 3 + c, sphere_v, sphere_f,
                                            self.sphere_transforms[:, c * num:(c + 1) * num]))
            for h, shape in enumerate(self.hook_shapes):
                mesh = trimesh.util.concatenate([m for _, _, m in shape.visual_meshes()])
                objects.append(VisualObject(shape.name, "rigid", SPHERE_COLORS[1 + h], 7 + h, mesh.vertices,
                                            mesh.faces, self.hook_transforms[:, h:h + 1]))
            self._visual_scene = VisualScene(camera=CameraSpec(poses=poses, fov_deg=cfg.camera_fov_deg, near=0.005,
                                                               far=far), objects=objects, background=(0.1, 0.1, 0.12))
            self.update_visuals()
        return self._visual_scene

    def update_visuals(self) -> None:
        if self._visual_scene is None:
            return
        q = self.world.state.particle_q
        wp.launch(update_deflect_visuals, dim=self.num_envs,
                  inputs=[q, self.instruments.pose, self.sphere_state],
                  outputs=[self.sphere_transforms, self.hook_transforms], device=self.wp_device)
        for k, points in enumerate(self.stalk_points):
            wp.launch(update_stalk, dim=self.num_envs, inputs=[q, self.anchors, k], outputs=[points],
                      device=self.wp_device)

    # ------------------------------------------------------------------ privileged access (experts, tests)
    def privileged_state(self) -> dict[str, torch.Tensor]:
        """Zero-copy torch views: sphere positions and anchors ``(N, S, 3)`` (m), sphere states ``(N, S)``, active
        sphere and hook ``(N,)``, deflections done ``(N,)``, hook PTSD ``(N, H, 4)`` (rad, m) and tip poses
        ``(N, H, 7)``."""
        return {
            "sphere_positions": wp.to_torch(self.world.state.particle_q),
            "anchors": wp.to_torch(self.anchors),
            "sphere_state": wp.to_torch(self.sphere_state),
            "active": wp.to_torch(self.active),
            "active_hook": wp.to_torch(self.active_hook),
            "num_deflections": wp.to_torch(self.num_deflections),
            "ptsd": wp.to_torch(self.instruments.ptsd),
            "tip_pose": wp.to_torch(self.instruments.pose),
        }


# ---------------------------------------------------------------------------- expert
class DeflectSpheresExpert:
    """Drives the active hook's cutting centre through the active sphere; the other hook stays still.

    The target is a point ``contact - push`` from the sphere's rest position on the line to the cutting centre,
    where ``contact`` = sphere radius + hook radius: the hook closes in from wherever it is and, once touching, keeps
    pressing ``push`` (4.5 mm by default, above the 3 mm needed) into the sphere. The target is converted to PTSD
    with the inverse kinematics (the cutting centre lies on the shaft axis, 14.4 mm beyond the TPSD tip) and the
    action is the PTSD error divided by one step's maximum motion, clipped to [-1, 1]. Discrete: the PTSD component
    with the largest error relative to its discrete step moves.
    """

    def __init__(self, env, push: float = 0.0045):
        if env.task_name != "DeflectSpheres":
            raise ValueError(f"DeflectSpheresExpert drives DeflectSpheres, not {env.task_name}")
        self.env = env
        self.push = float(push)
        self.error = wp.zeros((env.num_envs, env.num_hooks), dtype=wp.vec4, device=env.wp_device)
        deg = math.pi / 180.0
        to_internal = torch.tensor([deg, deg, deg, 1.0], dtype=torch.float32)
        dt = env.cfg.time_step * env.cfg.frame_skip
        self.step_size = (torch.tensor(env.cfg.maximum_state_velocity, dtype=torch.float32) * to_internal * dt).to(
            env.device)
        self.discrete_step = (torch.tensor(env.cfg.discrete_action_magnitude, dtype=torch.float32) * to_internal
                              * dt).to(env.device)

    def __call__(self, obs=None) -> torch.Tensor:
        env = self.env
        wp.launch(expert_ptsd_targets, dim=(env.num_envs, env.num_hooks),
                  inputs=[env.world.state.particle_q, env.anchors, env.instruments.pose, env.instruments.rcm,
                          env.instruments.ptsd, env.active, env.active_hook, env.cfg.sphere_radius + 0.8e-3, self.push],
                  outputs=[self.error], device=env.wp_device)
        error = wp.to_torch(self.error)  # (N, H, 4), hook 0 = right
        if env.num_hooks == 2:
            error = error[:, [1, 0]]  # action layout: left hook's PTSD, then the right hook's
        if env.is_discrete:
            ratio = (error / self.discrete_step).reshape(env.num_envs, -1)
            dim = ratio.abs().argmax(dim=1)
            negative = (ratio.gather(1, dim[:, None])[:, 0] < 0).long()
            idle = ratio.abs().max(dim=1).values < 0.5  # within half a step: no-op
            return torch.where(idle, torch.full_like(dim, 2 * ratio.shape[1]), 2 * dim + negative)
        return (error / self.step_size).clamp(-1.0, 1.0).reshape(env.num_envs, -1)
