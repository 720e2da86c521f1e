"""SearchForPointEnv: find a point of interest (POI) with a 30-degree oblique endoscope (sofa_env-facts §5.3).

A pivotized endoscope (TPSD about a trocar in the abdominal wall) must bring a POI on an organ surface to the
image centre at a desired distance (camera-only mode). In active-vision mode the agent also steers an
electrocautery hook (TPSD about a second trocar) and succeeds when the hook's tip touches the POI, optionally with
the hook activated. The anatomy is procedural (``lapwarp.assets.abdomen``); everything else follows sofa_env:

* Camera optical pose ``FK(ptsd) R_xyz(0, 180, 180) R_xyz(-oblique, 0, 0)`` (§3): with ``R_xyz(0, 180, 180) =
  Rx(180)`` this is ``FK(ptsd) Rx(180 - oblique)``; the camera looks along its local -Z with +Y up, i.e. along the
  shaft tilted by ``oblique`` degrees towards the shaft's local +Y. Vertical FoV 45 degrees, near 2 mm, far 300 mm.
* Actions: camera PTSD (4), plus cauter PTSD (4) and optionally an activation scalar (dead zone 0.1) in active
  vision. Velocities ``maximum_state_velocity`` = (20, 20, 30 deg/s, 35 mm/s) for both instruments, applied at each
  of the ``frame_skip = 3`` physics steps of 0.1 s.
* STATE observation (SI units: metres, radians): POI position (3), camera optical pose (position 3, quaternion
  xyzw with w >= 0) and camera PTSD (4) = 14; active vision adds the cauter tip pose (7) and PTSD + activation
  (5) = 26. sofa_env reports millimetres and degrees; we keep the units of the rest of lapwarp.
* Reward features (Table A): camera mode uses the first five and ``successful_task``; active vision uses the
  cauter features and ``successful_task`` (the other weights default to 0 there, as in the paper). The relative
  pixel distance is clipped to [0, 2] and set to 2 while the POI is behind the camera (sofa_env's value is
  unbounded there, which makes its delta explode). Pixels are those of ``image_shape`` also for STATE
  observations, as sofa_env measures them in its render resolution; the relative distance hardly depends on it.
* POIs are precomputed once per process on the host: organ vertices for which a camera state inside the limits
  exists that centres the point at the desired distance with a clear line of sight (and, in active vision, that
  the cauter reaches inside its limits with its shaft clear of the organs). Each reset draws one per env on the
  device.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import torch
import trimesh
import warp as wp

from lapwarp.assets.abdomen import abdomen_parts, inside_dome, organ_mesh
from lapwarp.config import EnvConfig
from lapwarp.env import BatchedEnv
from lapwarp.instruments import TPSDConfig, TPSDInstruments, discrete_action_table
from lapwarp.kernels.kinematics import STATE_LIMITS_VIOLATED
from lapwarp.kernels.raster import world_to_pixel
from lapwarp.model import Model
from lapwarp.render import focal_length
from lapwarp.visuals import CameraSpec, VisualObject, VisualScene, cylinder_mesh, sphere_mesh
from lapwarp.world import World

wp.set_module_options({"enable_backward": False})

SEARCH_FEATURES = (
    "poi_is_in_frame",
    "relative_camera_distance_error_to_poi",
    "delta_relative_camera_distance_error_to_poi",
    "relative_pixel_distance_poi_to_image_center",
    "delta_relative_pixel_distance_poi_to_image_center",
    "collision_cauter",
    "relative_distance_cauter_target",
    "relative_delta_distance_cauter_target",
    "cauter_touches_target",
    "cauter_action_violated_state_limits",
    "successful_task",
)
# Table A, SearchForPointEnv without hook.
CAMERA_WEIGHTS = {
    "poi_is_in_frame": 0.01,
    "relative_camera_distance_error_to_poi": -0.01,
    "delta_relative_camera_distance_error_to_poi": -0.01,
    "relative_pixel_distance_poi_to_image_center": -0.001,
    "delta_relative_pixel_distance_poi_to_image_center": -0.001,
    "successful_task": 100.0,
}
# Table A, SearchForPointEnv with hook (the camera terms are not part of that reward).
ACTIVE_VISION_WEIGHTS = {
    "collision_cauter": -0.001,
    "relative_distance_cauter_target": -0.0005,
    "relative_delta_distance_cauter_target": -5.0,
    "cauter_touches_target": 0.0,
    "cauter_action_violated_state_limits": 0.0,
    "successful_task": 100.0,
}
# Every feature gets a weight in both modes (0 for the other mode's terms), so ``env.reward_weights`` lists all.
CAMERA_WEIGHTS = {**dict.fromkeys(ACTIVE_VISION_WEIGHTS, 0.0), **CAMERA_WEIGHTS}
ACTIVE_VISION_WEIGHTS = {**dict.fromkeys(CAMERA_WEIGHTS, 0.0), **ACTIVE_VISION_WEIGHTS}
_NUM_CAUTER_SPHERES = wp.constant(4)
_CAUTER_SPHERE_SPACING = wp.constant(0.004)  # m between the collision spheres along the hook, tip backwards
_CAUTER_SPHERE_RADIUS = wp.constant(0.0015)  # m
_MAX_PIXEL_DISTANCE = wp.constant(2.0)  # relative pixel distance while the POI is behind the camera


@dataclass(kw_only=True)
class SearchForPointConfig(EnvConfig):
    """SearchForPointEnv parameters (Table B, §5.3); metres, degrees (angles of instruments), seconds.

    Attributes:
        active_vision: also control the electrocautery hook, which must touch the POI (sofa_env's
            ``active_vision_mode``).
        cauter_activation: (active vision) add an activation action (9th column; |a| > ``activation_deadzone``
            switches it, on for a > 0) and require the hook to be active while touching.
        activation_deadzone: dead zone of the activation action.
        target_distance_camera_poi: desired camera-POI distance (m), 120 mm.
        tolerance_target_distance: success tolerance on that distance (m), 10 mm.
        tolerance_image_center: success tolerance of the POI's distance to the image centre, as a fraction of
            the half image diagonal.
        instrument_touch_tolerance: (active vision) the hook tip touches the POI within this distance (m), 5 mm.
        maximum_state_velocity: pan, tilt, spin (deg/s), depth (m/s) at action 1, both instruments.
        discrete_action_magnitude: the same for discrete actions.
        oblique_viewing_angle_deg: angle between the shaft and the optical axis (deg), 30.
        camera_fov_deg / camera_near / camera_far: vertical field of view (deg) and clip planes (m).
        camera_rcm_position / camera_rcm_euler_deg: camera trocar (m, intrinsic XYZ deg).
        camera_start_ptsd / camera_ptsd_noise: reset state and its uniform noise (deg, deg, deg, m).
        camera_state_low / camera_state_high: camera state limits (deg, deg, deg, m).
        cauter_*: the same for the electrocautery hook.
        poi_radius: radius of the drawn POI marker (m); visual only.
    """

    time_step: float = 0.1
    frame_skip: int = 3
    max_episode_steps: int = 500
    active_vision: bool = False
    cauter_activation: bool = False
    activation_deadzone: float = 0.1
    target_distance_camera_poi: float = 0.12
    tolerance_target_distance: float = 0.01
    tolerance_image_center: float = 0.2
    instrument_touch_tolerance: float = 0.005
    maximum_state_velocity: tuple[float, float, float, float] = (20.0, 20.0, 30.0, 0.035)
    discrete_action_magnitude: tuple[float, float, float, float] = (5.0, 5.0, 5.0, 0.005)
    oblique_viewing_angle_deg: float = 30.0
    camera_fov_deg: float = 45.0
    camera_near: float = 0.002
    camera_far: float = 0.3
    camera_rcm_position: tuple[float, float, float] = (0.010, -0.1008, 0.28182)
    camera_rcm_euler_deg: tuple[float, float, float] = (-155.0, 0.0, 0.0)
    camera_start_ptsd: tuple[float, float, float, float] = (0.0, 0.0, 0.0, 0.03)
    camera_ptsd_noise: tuple[float, float, float, float] = (15.0, 15.0, 15.0, 0.015)
    camera_state_low: tuple[float, float, float, float] = (-40.0, -50.0, -180.0, 0.01)
    camera_state_high: tuple[float, float, float, float] = (40.0, 40.0, 180.0, 0.15)
    cauter_rcm_position: tuple[float, float, float] = (0.1172, 0.00229, 0.23362)
    cauter_rcm_euler_deg: tuple[float, float, float] = (-170.0, -30.0, 0.0)
    cauter_start_ptsd: tuple[float, float, float, float] = (0.0, 0.0, 0.0, 0.05)
    cauter_ptsd_noise: tuple[float, float, float, float] = (15.0, 15.0, 30.0, 0.02)
    cauter_state_low: tuple[float, float, float, float] = (-60.0, -60.0, -90.0, 0.0)
    cauter_state_high: tuple[float, float, float, float] = (35.0, 60.0, 90.0, 0.25)
    poi_radius: float = 0.004
    reward_weights: dict[str, float] = field(default_factory=dict)

    def validate(self, reward_features, supported_observations) -> None:
        super().validate(reward_features, supported_observations)
        for name in ("target_distance_camera_poi", "tolerance_target_distance", "tolerance_image_center",
                     "instrument_touch_tolerance", "camera_fov_deg", "camera_near", "poi_radius"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0.0):
                raise ValueError(f"{name} must be a positive number, got {value!r}")
        if not 0.0 < self.oblique_viewing_angle_deg < 90.0:
            raise ValueError(f"oblique_viewing_angle_deg must lie in (0, 90), got {self.oblique_viewing_angle_deg}")
        if not self.camera_far > self.camera_near:
            raise ValueError(f"camera_far ({self.camera_far}) must exceed camera_near ({self.camera_near})")
        if not 0.0 <= self.activation_deadzone < 1.0:
            raise ValueError(f"activation_deadzone must lie in [0, 1), got {self.activation_deadzone}")
        if self.cauter_activation and not self.active_vision:
            raise ValueError("cauter_activation needs active_vision=True")
        for name in ("maximum_state_velocity", "discrete_action_magnitude"):
            v = np.asarray(getattr(self, name), float)
            if v.shape != (4,) or not np.all(np.isfinite(v)) or np.any(v <= 0):
                raise ValueError(f"{name} must be 4 positive numbers, got {getattr(self, name)!r}")
        self.camera_tpsd()  # TPSDConfig checks shapes, limits and the start state
        self.cauter_tpsd()

    def camera_tpsd(self) -> TPSDConfig:
        """The endoscope as a TPSD instrument (its 'tip' is the optic's position)."""
        return TPSDConfig(rcm_position=self.camera_rcm_position, rcm_euler_deg=self.camera_rcm_euler_deg,
                          start_ptsd=self.camera_start_ptsd, state_low=self.camera_state_low,
                          state_high=self.camera_state_high, max_velocity=self.maximum_state_velocity,
                          discrete_magnitude=self.discrete_action_magnitude, ptsd_noise=self.camera_ptsd_noise)

    def cauter_tpsd(self) -> TPSDConfig:
        """The electrocautery hook as a TPSD instrument."""
        return TPSDConfig(rcm_position=self.cauter_rcm_position, rcm_euler_deg=self.cauter_rcm_euler_deg,
                          start_ptsd=self.cauter_start_ptsd, state_low=self.cauter_state_low,
                          state_high=self.cauter_state_high, max_velocity=self.maximum_state_velocity,
                          discrete_magnitude=self.discrete_action_magnitude, ptsd_noise=self.cauter_ptsd_noise)


# ---------------------------------------------------------------------------- camera inverse kinematics (torch)
def _euler_xyz_matrix(angles: torch.Tensor) -> torch.Tensor:
    """``Rx(a0) Ry(a1) Rz(a2)`` for angles ``(..., 3)`` in radians -> ``(..., 3, 3)``."""
    c, s = torch.cos(angles), torch.sin(angles)
    one, zero = torch.ones_like(c[..., 0]), torch.zeros_like(c[..., 0])
    rx = torch.stack([one, zero, zero, zero, c[..., 0], -s[..., 0], zero, s[..., 0], c[..., 0]], -1)
    ry = torch.stack([c[..., 1], zero, s[..., 1], zero, one, zero, -s[..., 1], zero, c[..., 1]], -1)
    rz = torch.stack([c[..., 2], -s[..., 2], zero, s[..., 2], c[..., 2], zero, zero, zero, one], -1)
    shape = angles.shape[:-1] + (3, 3)
    return rx.reshape(shape) @ ry.reshape(shape) @ rz.reshape(shape)


def quat_to_matrix(q: torch.Tensor) -> torch.Tensor:
    """Quaternions ``(..., 4)`` xyzw -> rotation matrices ``(..., 3, 3)``."""
    x, y, z, w = q.unbind(-1)
    return torch.stack([
        1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w),
        2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w),
        2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y),
    ], -1).reshape(q.shape[:-1] + (3, 3))


def oblique_camera_ptsd(rcm_position: torch.Tensor, rcm_rotation: torch.Tensor, poi: torch.Tensor, distance: float,
                        oblique_deg: float, num_roll: int = 36) -> torch.Tensor:
    """Camera states that centre ``poi`` at ``distance`` with the oblique optic, one per roll sample.

    Geometry: the optic sits at ``c = rcm + depth s`` on the shaft ``s`` and looks along ``v``, with angle
    ``oblique`` between ``s`` and ``v``. In the triangle (rcm, c, poi) the angle at ``c`` is ``180 - oblique``, so
    ``L^2 = depth^2 + D^2 + 2 depth D cos(oblique)`` (``L = |poi - rcm|``) gives the depth, and the shaft makes
    the angle ``asin(D sin(oblique) / L)`` with the direction to the POI. That leaves one free parameter, the
    azimuth of the shaft about that direction (the image's roll about the POI): we return ``num_roll`` samples of
    it. Pan and tilt follow from the shaft, spin from the oblique direction ``(v - cos(oblique) s) / sin(oblique)``,
    which is the shaft's local +Y.

    Args:
        rcm_position: ``(..., 3)`` trocar positions (m).
        rcm_rotation: ``(..., 3, 3)`` trocar orientations (world from RCM).
        poi: ``(..., 3)`` points of interest (m).
        distance: desired camera-POI distance (m).
        oblique_deg: oblique viewing angle (deg).
        num_roll: number of roll samples.

    Returns:
        ``(..., num_roll, 4)`` states (pan, tilt, spin in rad; depth in m); NaN where no solution exists
        (``L < D sin(oblique)``).
    """
    theta = math.radians(oblique_deg)
    q = (rcm_rotation.transpose(-1, -2) @ (poi - rcm_position)[..., None])[..., 0]  # POI in the RCM frame
    length = q.norm(dim=-1, keepdim=True)
    u = q / length
    depth = -distance * math.cos(theta) + torch.sqrt(length**2 - (distance * math.sin(theta)) ** 2)
    alpha = torch.asin((distance * math.sin(theta) / length).clamp(max=1.0))
    helper = torch.zeros_like(u)
    helper[..., 0] = 1.0
    use_y = u[..., 0].abs() > 0.9
    helper[use_y] = torch.tensor([0.0, 1.0, 0.0], dtype=u.dtype, device=u.device)
    e1 = torch.nn.functional.normalize(torch.linalg.cross(u, helper), dim=-1)
    e2 = torch.linalg.cross(u, e1)
    phi = torch.arange(num_roll, dtype=u.dtype, device=u.device) * (2 * math.pi / num_roll)
    w = torch.cos(phi)[:, None] * e1[..., None, :] + torch.sin(phi)[:, None] * e2[..., None, :]
    s = torch.cos(alpha)[..., None, :] * u[..., None, :] + torch.sin(alpha)[..., None, :] * w
    view = (q[..., None, :] - depth[..., None, :] * s) / distance
    y_s = (view - math.cos(theta) * s) / math.sin(theta)
    pan = torch.atan2(s[..., 0], torch.sqrt(s[..., 1] ** 2 + s[..., 2] ** 2))
    tilt = torch.atan2(-s[..., 1], s[..., 2])
    zero = torch.zeros_like(pan)
    a = _euler_xyz_matrix(torch.stack([tilt, pan, zero], -1))
    local_y = (a.transpose(-1, -2) @ y_s[..., None])[..., 0]
    spin = torch.atan2(-local_y[..., 0], local_y[..., 1])
    return torch.stack([pan, tilt, spin, depth.expand_as(pan)], -1)


def camera_pose_from_ptsd(rcm_position: torch.Tensor, rcm_rotation: torch.Tensor, ptsd: torch.Tensor,
                          oblique_deg: float) -> tuple[torch.Tensor, torch.Tensor]:
    """Optic position ``(..., 3)`` and orientation ``(..., 3, 3)`` (looks along -Z) from camera states (torch)."""
    local = _euler_xyz_matrix(torch.stack([ptsd[..., 1], ptsd[..., 0], ptsd[..., 2]], -1))
    rot = rcm_rotation @ local
    position = rcm_position + rot[..., :, 2] * ptsd[..., 3:4]
    offset = _euler_xyz_matrix(torch.tensor([math.radians(180.0 - oblique_deg), 0.0, 0.0], dtype=ptsd.dtype,
                                            device=ptsd.device))
    return position, rot @ offset


# ---------------------------------------------------------------------------- kernels
@wp.func
def camera_pose(tip: wp.transform, optic_offset: wp.quat) -> wp.transform:
    """Optical pose of the endoscope: its TPSD tip pose rotated by ``Rx(180 - oblique)`` (see the module doc)."""
    return wp.transform(wp.transform_get_translation(tip), wp.transform_get_rotation(tip) * optic_offset)


@wp.func
def relative_pixel_distance(cam: wp.transform, poi: wp.vec3, focal: float, width: float, height: float,
                            near: float) -> wp.vec2:
    """(relative pixel distance of the POI to the image centre in [0, 2], in frame 0/1)."""
    pix = world_to_pixel(cam, poi, focal, 0.5 * width, 0.5 * height)
    rel = float(_MAX_PIXEL_DISTANCE)
    in_frame = float(0.0)
    if pix[2] > near:
        dr = pix[0] - 0.5 * height
        dc = pix[1] - 0.5 * width
        rel = wp.min(wp.sqrt(dr * dr + dc * dc) / (0.5 * wp.sqrt(width * width + height * height)),
                     float(_MAX_PIXEL_DISTANCE))
        if pix[0] >= 0.0 and pix[0] < height and pix[1] >= 0.0 and pix[1] < width:
            in_frame = 1.0
    return wp.vec2(rel, in_frame)


@wp.func
def cauter_collisions(tip: wp.transform, mesh: wp.uint64) -> int:
    """Number of the hook's collision spheres (tip and three behind it along the shaft) touching an organ."""
    count = int(0)
    for i in range(_NUM_CAUTER_SPHERES):
        p = wp.transform_point(tip, wp.vec3(0.0, 0.0, -float(i) * _CAUTER_SPHERE_SPACING))
        # winding numbers, not the closest face's normal: organs overlap (gallbladder in liver, colon and bowel),
        # and the closest face can belong to a part the point is outside of while it is inside another
        query = wp.mesh_query_point_sign_winding_number(mesh, p, 0.5, 2.0, 0.5)
        if query.result:
            closest = wp.mesh_eval_position(mesh, query.face, query.u, query.v)
            if query.sign < 0.0 or wp.length(p - closest) < _CAUTER_SPHERE_RADIUS:
                count += 1
    return count


@wp.kernel
def apply_activation(actions: wp.array2d(dtype=wp.float32), column: int, deadzone: float,
                     active: wp.array(dtype=wp.int32)):
    """sofa_env's cauter activation: outside the dead zone the sign switches it, inside it stays as it was."""
    env = wp.tid()
    a = actions[env, column]
    if wp.abs(a) > deadzone:
        if a > 0.0:
            active[env] = 1
        else:
            active[env] = 0


@wp.kernel
def eval_search_features(
    pose: wp.array2d(dtype=wp.transform),
    rcm: wp.array2d(dtype=wp.transform),
    flags: wp.array2d(dtype=wp.int32),
    poi: wp.array(dtype=wp.vec3),
    active: wp.array(dtype=wp.int32),
    optic_offset: wp.quat,
    focal: float,
    width: float,
    height: float,
    near: float,
    target_distance: float,
    tolerance_distance: float,
    tolerance_center: float,
    touch_tolerance: float,
    active_vision: int,
    require_activation: int,
    organ_mesh: wp.uint64,
    update_previous: int,
    env_mask: wp.array(dtype=wp.int32),
    previous: wp.array2d(dtype=wp.float32),
    features_out: wp.array2d(dtype=wp.float32),
    success_out: wp.array(dtype=wp.int32),
    failure_out: wp.array(dtype=wp.int32),
):
    """Reward features of §5.3 (order of ``SEARCH_FEATURES``); ``previous`` holds (distance error, pixel distance,
    cauter distance) of the last step for the deltas. With ``update_previous`` = 0 this is the reset pass: it only
    stores the starting values of the masked envs."""
    env = wp.tid()
    if update_previous == 0 and env_mask[env] == 0:
        return
    p = poi[env]
    cam = camera_pose(pose[env, 0], optic_offset)
    dist_err = wp.abs(wp.length(p - wp.transform_get_translation(cam)) - target_distance) / target_distance
    pixel = relative_pixel_distance(cam, p, focal, width, height, near)
    cauter_dist = float(0.0)
    collisions = int(0)
    touches = int(0)
    violated = float(0.0)
    if active_vision != 0:
        tip = pose[env, 1]
        d = wp.length(wp.transform_get_translation(tip) - p)
        cauter_dist = d / wp.max(wp.length(wp.transform_get_translation(rcm[env, 1]) - p), 1.0e-6)
        collisions = cauter_collisions(tip, organ_mesh)
        if d <= touch_tolerance:
            touches = 1
        if (flags[env, 1] & STATE_LIMITS_VIOLATED) != 0:
            violated = 1.0
    if update_previous == 0:
        previous[env, 0] = dist_err
        previous[env, 1] = pixel[0]
        previous[env, 2] = cauter_dist
        return
    ok = int(0)
    if active_vision != 0:
        if touches != 0 and (require_activation == 0 or active[env] != 0):
            ok = 1
    else:
        if (dist_err * target_distance < tolerance_distance and pixel[0] < tolerance_center
                and pixel[1] > 0.0):
            ok = 1
    features_out[env, 0] = pixel[1]
    features_out[env, 1] = dist_err
    features_out[env, 2] = dist_err - previous[env, 0]
    features_out[env, 3] = pixel[0]
    features_out[env, 4] = pixel[0] - previous[env, 1]
    features_out[env, 5] = float(collisions)
    features_out[env, 6] = cauter_dist
    features_out[env, 7] = cauter_dist - previous[env, 2]
    features_out[env, 8] = float(touches)
    features_out[env, 9] = violated
    features_out[env, 10] = float(ok)
    previous[env, 0] = dist_err
    previous[env, 1] = pixel[0]
    previous[env, 2] = cauter_dist
    success_out[env] = ok
    failure_out[env] = 0


@wp.kernel
def sample_pois(
    env_mask: wp.array(dtype=wp.int32),
    candidates: wp.array(dtype=wp.vec3),
    rng: wp.array(dtype=wp.uint32),
    poi: wp.array(dtype=wp.vec3),
    active: wp.array(dtype=wp.int32),
):
    """Draw each masked env's POI uniformly from the precomputed candidates; switch the hook off."""
    env = wp.tid()
    if env_mask[env] == 0:
        return
    s = rng[env]
    n = candidates.shape[0]
    i = wp.min(int(wp.randf(s) * float(n)), n - 1)
    rng[env] = s
    poi[env] = candidates[i]
    active[env] = 0


@wp.func
def write_pose(obs: wp.array2d(dtype=wp.float32), env: int, start: int, xf: wp.transform):
    """Position then quaternion (xyzw), sign chosen so that w >= 0 (q and -q are the same rotation)."""
    t = wp.transform_get_translation(xf)
    q = wp.transform_get_rotation(xf)
    if q[3] < 0.0:
        q = wp.quat(-q[0], -q[1], -q[2], -q[3])
    for k in range(3):
        obs[env, start + k] = t[k]
    for k in range(4):
        obs[env, start + 3 + k] = q[k]


@wp.kernel
def observe_search(
    poi: wp.array(dtype=wp.vec3),
    pose: wp.array2d(dtype=wp.transform),
    ptsd: wp.array2d(dtype=wp.vec4),
    active: wp.array(dtype=wp.int32),
    optic_offset: wp.quat,
    active_vision: int,
    obs_out: wp.array2d(dtype=wp.float32),
):
    """STATE: POI (3), camera pose (7), camera PTSD (4) [, cauter pose (7), cauter PTSD (4), activation (1)]."""
    env = wp.tid()
    p = poi[env]
    for k in range(3):
        obs_out[env, k] = p[k]
    write_pose(obs_out, env, 3, camera_pose(pose[env, 0], optic_offset))
    s = ptsd[env, 0]
    for k in range(4):
        obs_out[env, 10 + k] = s[k]
    if active_vision != 0:
        write_pose(obs_out, env, 14, pose[env, 1])
        c = ptsd[env, 1]
        for k in range(4):
            obs_out[env, 21 + k] = c[k]
        obs_out[env, 25] = float(active[env])


@wp.kernel
def update_search_visuals(
    pose: wp.array2d(dtype=wp.transform),
    poi: wp.array(dtype=wp.vec3),
    optic_offset: wp.quat,
    active_vision: int,
    camera_out: wp.array(dtype=wp.transform),
    marker_out: wp.array2d(dtype=wp.transform),
    cauter_out: wp.array2d(dtype=wp.transform),
):
    """Per-env camera pose of the renderer, POI marker and hook transforms from the current state."""
    env = wp.tid()
    camera_out[env] = camera_pose(pose[env, 0], optic_offset)
    marker_out[env, 0] = wp.transform(poi[env], wp.quat_identity())
    if active_vision != 0:
        cauter_out[env, 0] = pose[env, 1]


@wp.kernel
def check_sight_lines(
    mesh: wp.uint64,
    start: wp.array(dtype=wp.vec3),
    end: wp.array(dtype=wp.vec3),
    slack: float,
    clear_out: wp.array(dtype=wp.int32),
):
    """1 where the segment start -> end hits no organ before ``slack`` m short of its end (POI precompute, expert)."""
    i = wp.tid()
    d = end[i] - start[i]
    length = wp.length(d)
    if length <= slack:
        clear_out[i] = 1
        return
    query = wp.mesh_query_ray(mesh, start[i], d / length, length - slack)
    clear_out[i] = 1
    if query.result:
        clear_out[i] = 0


# ---------------------------------------------------------------------------- POI candidates (host, once)
_POI_CACHE: dict[str, np.ndarray] = {}


def _limit_mask(ptsd: torch.Tensor, low, high, margin=(0.5, 0.5, 0.5, 0.002)) -> torch.Tensor:
    """States (rad, m) inside limits given in deg and m, ``margin`` (deg, m) away from them: candidates must leave
    the expert room to arrive without its last step being clipped."""
    low = torch.tensor(np.radians(low[:3]).tolist() + [low[3]], dtype=ptsd.dtype) + torch.tensor(
        np.radians(margin[:3]).tolist() + [margin[3]], dtype=ptsd.dtype)
    high = torch.tensor(np.radians(high[:3]).tolist() + [high[3]], dtype=ptsd.dtype) - torch.tensor(
        np.radians(margin[:3]).tolist() + [margin[3]], dtype=ptsd.dtype)
    return ((ptsd >= low) & (ptsd <= high)).all(-1)


def poi_candidates(cfg: SearchForPointConfig, device=None) -> np.ndarray:
    """Organ points (m) a camera state inside the limits can centre at the desired distance with a clear line of
    sight; in active vision also reachable by the hook (inside its limits, shaft clear). Cached per geometry.

    The sight lines are cast on ``device`` (the env's, so a GPU machine compiles no CPU kernels for this)."""
    # repr: overrides may arrive as lists (JSON from the command line), which do not hash
    key = repr((cfg.active_vision, cfg.target_distance_camera_poi, cfg.oblique_viewing_angle_deg,
                [list(map(float, x)) for x in (cfg.camera_rcm_position, cfg.camera_rcm_euler_deg, cfg.camera_state_low,
                                               cfg.camera_state_high, cfg.cauter_rcm_position, cfg.cauter_rcm_euler_deg,
                                               cfg.cauter_state_low, cfg.cauter_state_high)]))
    if key in _POI_CACHE:
        return _POI_CACHE[key]
    v, f = organ_mesh()
    normals = trimesh.Trimesh(v, f, process=False).vertex_normals
    pts = v[(normals[:, 2] > -0.2) & inside_dome(v, margin=0.005)]  # the underside is never in view
    pts_t = torch.from_numpy(pts)
    rcm_p = torch.tensor(cfg.camera_rcm_position, dtype=torch.float64)
    rcm_r = _euler_xyz_matrix(torch.tensor(np.radians(cfg.camera_rcm_euler_deg)))
    sol = oblique_camera_ptsd(rcm_p, rcm_r, pts_t, cfg.target_distance_camera_poi, cfg.oblique_viewing_angle_deg)
    cam_pos, _ = camera_pose_from_ptsd(rcm_p, rcm_r, sol, cfg.oblique_viewing_angle_deg)
    ok = _limit_mask(sol, cfg.camera_state_low, cfg.camera_state_high) & ~torch.isnan(sol).any(-1)
    ok &= torch.from_numpy(inside_dome(cam_pos.numpy(), margin=0.005))
    idx_point, idx_roll = torch.nonzero(ok, as_tuple=True)
    starts = cam_pos[idx_point, idx_roll].numpy()
    ends = pts[idx_point.numpy()]
    dev = wp.get_device(device)
    mesh = wp.Mesh(points=wp.array(v, dtype=wp.vec3, device=dev), indices=wp.array(f.ravel(), dtype=int, device=dev))

    def clear(a: np.ndarray, b: np.ndarray) -> np.ndarray:
        out = wp.zeros(len(a), dtype=wp.int32, device=dev)
        if len(a):
            wp.launch(check_sight_lines, dim=len(a), inputs=[mesh.id, wp.array(a, dtype=wp.vec3, device=dev),
                                                             wp.array(b, dtype=wp.vec3, device=dev), 0.002],
                      outputs=[out], device=dev)
        return out.numpy().astype(bool)

    visible = np.zeros(len(pts), dtype=bool)
    visible[idx_point.numpy()[clear(starts, ends)]] = True
    if cfg.active_vision:
        rcm_c = np.asarray(cfg.cauter_rcm_position)
        rot_c = _euler_xyz_matrix(torch.tensor(np.radians(cfg.cauter_rcm_euler_deg))).numpy()
        local = (pts - rcm_c) @ rot_c  # R^T (p - rcm), row-wise
        depth = np.linalg.norm(local, axis=1)
        pan = np.arctan2(local[:, 0], np.hypot(local[:, 1], local[:, 2]))
        tilt = np.arctan2(-local[:, 1], local[:, 2])
        cauter_ptsd = torch.from_numpy(np.stack([pan, tilt, np.zeros_like(pan), depth], -1))
        visible &= _limit_mask(cauter_ptsd, cfg.cauter_state_low, cfg.cauter_state_high).numpy()
        visible &= clear(np.broadcast_to(rcm_c, pts.shape).copy(), pts)
    result = pts[visible].astype(np.float32)
    if len(result) == 0:
        raise ValueError("no point of interest satisfies the camera (and cauter) limits with this configuration")
    _POI_CACHE[key] = result
    return result


# ---------------------------------------------------------------------------- env
class SearchForPointEnv(BatchedEnv):
    """LapGym's SearchForPointEnv, batched. See the module docstring and ``SearchForPointConfig``."""

    config_class = SearchForPointConfig
    task_name = "SearchForPoint"
    reward_features = SEARCH_FEATURES
    default_reward_weights = CAMERA_WEIGHTS
    supported_observations = ("STATE", "RGB", "RGBD", "DEPTH")
    cfg: SearchForPointConfig

    def __init__(self, cfg: SearchForPointConfig, *args, **kwargs):
        if isinstance(cfg, SearchForPointConfig) and cfg.active_vision:
            # the instance attribute shadows the class default the base class merges overrides into
            self.default_reward_weights = ACTIVE_VISION_WEIGHTS
        super().__init__(cfg, *args, **kwargs)

    def _build(self) -> World:
        cfg, n, dev = self.cfg, self.num_envs, self.wp_device
        world = World(Model(num_envs=n, device=str(dev)), seed=cfg.seed)
        configs = [cfg.camera_tpsd()] + ([cfg.cauter_tpsd()] if cfg.active_vision else [])
        self.instruments = TPSDInstruments(configs, n, device=str(dev))
        self.candidates = wp.array(poi_candidates(cfg, dev), dtype=wp.vec3, device=dev)
        self.poi = wp.zeros(n, dtype=wp.vec3, device=dev)
        self.cauter_active = wp.zeros(n, dtype=wp.int32, device=dev)
        self.previous = wp.zeros((n, 3), dtype=wp.float32, device=dev)
        v, f = organ_mesh()
        self._organ_points = wp.array(v, dtype=wp.vec3, device=dev)
        self._organ_indices = wp.array(f.ravel(), dtype=int, device=dev)
        self.organ_mesh = wp.Mesh(points=self._organ_points, indices=self._organ_indices, support_winding_number=True)
        angle = math.radians(180.0 - cfg.oblique_viewing_angle_deg)
        self.optic_offset = wp.quat_from_axis_angle(wp.vec3(1.0, 0.0, 0.0), angle)
        height, width = cfg.image_shape
        self._focal = focal_length(cfg.camera_fov_deg, height)
        self._visual_scene: VisualScene | None = None
        self.camera_poses = wp.zeros(n, dtype=wp.transform, device=dev)
        self.marker_transforms = wp.zeros((n, 1), dtype=wp.transform, device=dev)
        self.cauter_transforms = wp.zeros((n, 1), dtype=wp.transform, device=dev)
        return world

    def _action_dim(self) -> int:
        if not self.cfg.active_vision:
            return 4
        return 9 if self.cfg.cauter_activation else 8

    def _observation_dim(self) -> int:
        return 26 if self.cfg.active_vision else 14

    def _observation_bounds(self) -> tuple[float, float]:
        # positions stay within ~0.5 m of the origin, quaternions in [-1, 1], angles within their limits (spin of
        # the camera up to +-180 deg), depths below 0.25 m: every value lies in [-3.2, 3.2]
        return -3.2, 3.2

    def _discrete_action_table(self) -> np.ndarray:
        ratio = (np.asarray(self.cfg.discrete_action_magnitude) / np.asarray(self.cfg.maximum_state_velocity))
        magnitudes = list(ratio) * (2 if self.cfg.active_vision else 1)
        if self.cfg.cauter_activation:
            magnitudes.append(1.0)
        return discrete_action_table(magnitudes)

    def _apply_actions(self, actions: wp.array2d) -> None:
        self.instruments.set_actions(actions, self.cfg.time_step)
        if self.cfg.cauter_activation:
            wp.launch(apply_activation, dim=self.num_envs, inputs=[actions, 8, self.cfg.activation_deadzone],
                      outputs=[self.cauter_active], device=self.wp_device)

    def _before_physics_step(self) -> None:
        self.instruments.step()

    def _launch_features(self, update_previous: int, env_mask: wp.array) -> None:
        cfg = self.cfg
        height, width = cfg.image_shape
        ins = self.instruments
        wp.launch(eval_search_features, dim=self.num_envs,
                  inputs=[ins.pose, ins.rcm, ins.flags, self.poi, self.cauter_active, self.optic_offset, self._focal,
                          float(width), float(height), cfg.camera_near, cfg.target_distance_camera_poi,
                          cfg.tolerance_target_distance, cfg.tolerance_image_center, cfg.instrument_touch_tolerance,
                          int(cfg.active_vision), int(cfg.cauter_activation), self.organ_mesh.id, update_previous,
                          env_mask],
                  outputs=[self.previous, self.features, self.success, self.failure], device=self.wp_device)

    def _compute_features(self) -> None:
        self._launch_features(1, self.reset_mask)

    def _reset_task(self, env_mask: wp.array) -> None:
        self.instruments.reset(env_mask, self.world.rng)
        wp.launch(sample_pois, dim=self.num_envs, inputs=[env_mask, self.candidates, self.world.rng],
                  outputs=[self.poi, self.cauter_active], device=self.wp_device)
        self._launch_features(0, env_mask)

    def _compute_observations(self) -> None:
        ins = self.instruments
        wp.launch(observe_search, dim=self.num_envs,
                  inputs=[self.poi, ins.pose, ins.ptsd, self.cauter_active, self.optic_offset,
                          int(self.cfg.active_vision)], outputs=[self.obs_frame], device=self.wp_device)
        if self.cfg.privileged_critic:
            wp.copy(self.critic_frame, self.obs_frame)  # the STATE is already privileged (the POI position)

    # ------------------------------------------------------------------ visuals
    def visual_scene(self) -> VisualScene:
        """The procedural abdomen (wall, floor, organs), the POI marker (bright green) and, in active vision, the
        hook (silver). Camera: the oblique endoscope, one pose per env in ``camera_poses``."""
        if self._visual_scene is None:
            cfg, n, dev = self.cfg, self.num_envs, self.wp_device
            self._static_transforms = wp.array([wp.transform_identity()] * n, dtype=wp.transform,
                                               device=dev).reshape((n, 1))
            objects = []
            for seg, part in enumerate(abdomen_parts(), start=1):
                objects.append(VisualObject(part.name, "rigid", part.color, seg, part.vertices, part.faces,
                                            self._static_transforms))
            sv, sf = sphere_mesh(cfg.poi_radius, subdivisions=2)
            objects.append(VisualObject("poi", "rigid", (0.1, 0.95, 0.2), len(objects) + 1, sv, sf,
                                        self.marker_transforms))
            if cfg.active_vision:
                hv, hf = _hook_mesh()
                objects.append(VisualObject("cauter", "rigid", (0.72, 0.74, 0.78), len(objects) + 1, hv, hf,
                                            self.cauter_transforms))
            self._visual_scene = VisualScene(
                camera=CameraSpec(poses=self.camera_poses, fov_deg=cfg.camera_fov_deg, near=cfg.camera_near,
                                  far=cfg.camera_far),
                objects=objects, background=(0.0, 0.0, 0.0))
            self.update_visuals()
        return self._visual_scene

    def update_visuals(self) -> None:
        wp.launch(update_search_visuals, dim=self.num_envs,
                  inputs=[self.instruments.pose, self.poi, self.optic_offset, int(self.cfg.active_vision)],
                  outputs=[self.camera_poses, self.marker_transforms, self.cauter_transforms], device=self.wp_device)

    # ------------------------------------------------------------------ privileged access (experts, tests)
    def privileged_state(self) -> dict[str, torch.Tensor]:
        """Zero-copy torch views: ``poi`` (N, 3) m, ``ptsd`` (N, K, 4) rad/m, ``pose`` / ``rcm`` (N, K, 7)
        transforms (K = 1 camera, 2 with the cauter), ``cauter_active`` (N,)."""
        ins = self.instruments
        return {"poi": wp.to_torch(self.poi), "ptsd": wp.to_torch(ins.ptsd), "pose": wp.to_torch(ins.pose),
                "rcm": wp.to_torch(ins.rcm), "cauter_active": wp.to_torch(self.cauter_active)}

    def set_ptsd(self, ptsd: np.ndarray, env_ids=None) -> None:
        """Host utility for tests: write instrument states (deg, deg, deg, m) and start the deltas from them."""
        self.instruments.set_ptsd(ptsd, env_ids)
        self._launch_features(0, self._all_envs_mask())

    def set_poi(self, poi: np.ndarray) -> None:
        """Host utility for tests: place the POIs ``(num_envs, 3)`` (m) and start the deltas from them."""
        self.poi.assign(wp.array(np.asarray(poi, np.float32), dtype=wp.vec3, device=self.wp_device))
        self._launch_features(0, self._all_envs_mask())

    def sight_lines_clear(self, start: torch.Tensor, end: torch.Tensor) -> torch.Tensor:
        """Whether each segment ``start -> end`` ``(M, 3)`` (torch, env device) misses the organs until 2 mm before
        its end: one launch, no host sync (for experts: a centred POI should also be visible)."""
        start = start.reshape(-1, 3).to(torch.float32).contiguous()
        end = end.reshape(-1, 3).to(torch.float32).contiguous()
        out = torch.zeros(start.shape[0], dtype=torch.int32, device=start.device)
        with self._torch_stream_scope():  # on torch's stream: ordered after the torch ops that made the inputs
            wp.launch(check_sight_lines, dim=start.shape[0],
                      inputs=[self.organ_mesh.id, wp.from_torch(start, dtype=wp.vec3),
                              wp.from_torch(end, dtype=wp.vec3), 0.002], outputs=[wp.from_torch(out)],
                      device=self.wp_device)
        return out.bool()

    def _all_envs_mask(self) -> wp.array:
        return wp.full(self.num_envs, 1, dtype=wp.int32, device=self.wp_device)


def _hook_mesh() -> tuple[np.ndarray, np.ndarray]:
    """Electrocautery hook, tip at the origin: a 5 mm shaft (z < -8 mm), a thin electrode and a 4 mm hook."""
    shaft_v, shaft_f = cylinder_mesh(0.0025, 0.3)
    shaft_v[:, 2] -= 0.008
    rod = trimesh.creation.cylinder(radius=0.0008, height=0.008, sections=10)
    rod.apply_translation((0.0, 0.0, -0.004))
    hook = trimesh.creation.cylinder(radius=0.0008, height=0.004, sections=10)
    hook.apply_transform(trimesh.transformations.rotation_matrix(math.pi / 2, (1, 0, 0)))
    hook.apply_translation((0.0, 0.002, 0.0))
    mesh = trimesh.util.concatenate([trimesh.Trimesh(shaft_v, shaft_f, process=False), rod, hook])
    return np.asarray(mesh.vertices, np.float32), np.asarray(mesh.faces, np.int32)


class SearchForPointExpert:
    """Privileged controller: drives the camera to the state that centres the POI at the desired distance.

    Each call solves the oblique-optic inverse kinematics (``oblique_camera_ptsd``) for 36 roll samples, keeps the
    ones inside the state limits, prefers those with a clear line of sight to the POI, and heads for the one
    reachable soonest at maximum velocity (time = the largest per-component distance / speed), stepping exactly
    onto it when it is within one step. In active vision the
    hook heads for ``point_to_ptsd`` of the POI (spin kept) and, with activation, switches on. Discrete actions
    move the component with the largest remaining error, in units of one discrete step.
    """

    def __init__(self, env: SearchForPointEnv):
        if env.task_name != "SearchForPoint":
            raise ValueError(f"SearchForPointExpert drives SearchForPoint, not {env.task_name}")
        self.env = env
        cfg = env.cfg
        dev = env.device
        scale = torch.tensor([math.pi / 180] * 3 + [1.0], device=dev)
        self.v_max = torch.tensor(cfg.maximum_state_velocity, device=dev) * scale
        self.discrete = torch.tensor(cfg.discrete_action_magnitude, device=dev) * scale
        self.low = torch.tensor(cfg.camera_state_low, device=dev) * scale
        self.high = torch.tensor(cfg.camera_state_high, device=dev) * scale
        self.step_time = cfg.time_step * cfg.frame_skip

    def __call__(self, obs=None) -> torch.Tensor:
        env, cfg = self.env, self.env.cfg
        state = env.privileged_state()
        poi, ptsd, rcm = state["poi"], state["ptsd"], state["rcm"]
        rcm_rot = quat_to_matrix(rcm[:, 0, 3:7])
        candidates = oblique_camera_ptsd(rcm[:, 0, :3], rcm_rot, poi, cfg.target_distance_camera_poi,
                                         cfg.oblique_viewing_angle_deg)
        current = ptsd[:, 0]
        time = ((candidates - current[:, None]).abs() / self.v_max).amax(-1)
        valid = ((candidates >= self.low) & (candidates <= self.high)).all(-1) & torch.isfinite(time)
        time = torch.where(valid, time, torch.full_like(time, float("inf")))
        # prefer rolls from which the POI is not hidden behind another organ (a 1000 s penalty, not a ban)
        eye, _ = camera_pose_from_ptsd(rcm[:, 0, None, :3], rcm_rot[:, None], candidates,
                                       cfg.oblique_viewing_angle_deg)
        clear = env.sight_lines_clear(eye, poi[:, None].expand_as(eye)).reshape(time.shape)
        time = time + 1000.0 * (~clear).to(time.dtype)
        best = time.argmin(dim=1)
        target = candidates[torch.arange(env.num_envs, device=env.device), best]
        target = torch.where(torch.isfinite(target), target, current).clamp(self.low, self.high)
        errors = [target - current]
        if cfg.active_vision:
            errors.append(self._cauter_target(poi, ptsd[:, 1], rcm[:, 1]) - ptsd[:, 1])
        if env.is_discrete:
            action = self._discrete(errors)
            if cfg.cauter_activation:  # switch the hook on first (row 16 = +activation); it stays on
                action = torch.where(state["cauter_active"] == 0, torch.full_like(action, 16), action)
            return action
        actions = [(e / (self.v_max * self.step_time)).clamp(-1.0, 1.0) for e in errors]
        if cfg.cauter_activation:
            actions.append(torch.ones(env.num_envs, 1, device=env.device))
        return torch.cat(actions, dim=1)

    @staticmethod
    def _cauter_target(poi: torch.Tensor, ptsd: torch.Tensor, rcm: torch.Tensor) -> torch.Tensor:
        local = (quat_to_matrix(rcm[:, 3:7]).transpose(-1, -2) @ (poi - rcm[:, :3])[..., None])[..., 0]
        depth = local.norm(dim=-1)
        pan = torch.atan2(local[:, 0], torch.sqrt(local[:, 1] ** 2 + local[:, 2] ** 2))
        tilt = torch.atan2(-local[:, 1], local[:, 2])
        return torch.stack([pan, tilt, ptsd[:, 2], depth], -1)

    def _discrete(self, errors: list[torch.Tensor]) -> torch.Tensor:
        steps = torch.cat([e / (self.discrete * self.step_time) for e in errors], dim=1)
        index = steps.abs().argmax(dim=1)
        chosen = steps.gather(1, index[:, None])[:, 0]
        action = 2 * index + (chosen < 0).long()
        no_op = torch.full_like(action, 2 * self.env.action_dim)
        return torch.where(chosen.abs() < 0.5, no_op, action)
