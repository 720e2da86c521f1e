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
from dataclasses import dataclass
from typing import Annotated

import numpy as np
import torch
import trimesh
import warp as wp

from lapwarp import launching
from lapwarp.assets.abdomen import abdomen_parts, inside_dome, organ_mesh
from lapwarp.builder import SceneBuilder
from lapwarp.config import PTSD, Count, EnvConfig, NonNegative, Positive, Range, Vec3
from lapwarp.env import BatchedEnv
from lapwarp.experts import Expert
from lapwarp.instruments import TPSDConfig, tpsd_from_config
from lapwarp.render import focal_length
from lapwarp.tasks.camera import (
    EndoscopeCamera,
    camera_pose_from_ptsd,
    euler_xyz_matrix,
    oblique_camera_ptsd,
    oblique_optic_pose,
    point_to_ptsd,
    quat_to_matrix,
    relative_pixel_distance,
    sight_lines_clear,
)
from lapwarp.tasks.rig import STATE_LIMITS_VIOLATED, InstrumentRig, InstrumentSpec
from lapwarp.tasks.spec import Feature, ObservationLayout, ObservationSpec, RewardSpec, write_transform
from lapwarp.tasks.targets import draw_candidate
from lapwarp.visuals import VisualObject, VisualScene, sphere_mesh
from lapwarp.world import World

wp.set_module_options({"enable_backward": False})

# Every feature of both modes; the default weights depend on the mode (Table A), 0 for the other mode's terms.
REWARDS = RewardSpec(
    Feature("poi_is_in_frame"),
    Feature("relative_camera_distance_error_to_poi"),
    Feature("delta_relative_camera_distance_error_to_poi", delta_of="relative_camera_distance_error_to_poi"),
    Feature("relative_pixel_distance_poi_to_image_center"),
    Feature("delta_relative_pixel_distance_poi_to_image_center",
            delta_of="relative_pixel_distance_poi_to_image_center"),
    Feature("collision_cauter"),
    Feature("relative_distance_cauter_target"),
    Feature("relative_delta_distance_cauter_target", delta_of="relative_distance_cauter_target"),
    Feature("cauter_touches_target"),
    Feature("cauter_action_violated_state_limits"),
    Feature("successful_task"),
)
F = REWARDS.F
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
# STATE in SI units; the cauter blocks exist in active vision only (size 0 otherwise)
OBS = ObservationSpec("poi", "camera_pose", "camera_ptsd", "cauter_pose", "cauter_state")
_OBS_BOUND = 3.2  # positions within ~0.5 m of the origin, quaternions, angles within their limits (spin +-180 deg)
_NUM_CAUTER_SPHERES = wp.constant(4)
_CAUTER_SPHERE_SPACING = wp.constant(0.004)  # m between the collision spheres along the hook, tip backwards
_CAUTER_SPHERE_RADIUS = wp.constant(0.0015)  # m


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

    frame_skip: Count(1000) = 3
    active_vision: bool = False
    cauter_activation: bool = False
    activation_deadzone: Annotated[float, Range(ge=0.0, lt=1.0)] = 0.1
    target_distance_camera_poi: Positive = 0.12
    tolerance_target_distance: Positive = 0.01
    tolerance_image_center: Positive = 0.2
    instrument_touch_tolerance: Positive = 0.005
    maximum_state_velocity: tuple[Positive, Positive, Positive, Positive] = (20.0, 20.0, 30.0, 0.035)
    discrete_action_magnitude: tuple[Positive, Positive, Positive, Positive] = (5.0, 5.0, 5.0, 0.005)
    oblique_viewing_angle_deg: Annotated[float, Range(gt=0.0, lt=90.0)] = 30.0
    camera_fov_deg: Annotated[float, Range(gt=0.0, lt=180.0)] = 45.0
    camera_near: Positive = 0.002
    camera_far: Positive = 0.3
    camera_rcm_position: Vec3 = (0.010, -0.1008, 0.28182)
    camera_rcm_euler_deg: Vec3 = (-155.0, 0.0, 0.0)
    camera_start_ptsd: PTSD = (0.0, 0.0, 0.0, 0.03)
    camera_ptsd_noise: tuple[NonNegative, NonNegative, NonNegative, NonNegative] = (15.0, 15.0, 15.0, 0.015)
    camera_state_low: PTSD = (-40.0, -50.0, -180.0, 0.01)
    camera_state_high: PTSD = (40.0, 40.0, 180.0, 0.15)
    cauter_rcm_position: Vec3 = (0.1172, 0.00229, 0.23362)
    cauter_rcm_euler_deg: Vec3 = (-170.0, -30.0, 0.0)
    cauter_start_ptsd: PTSD = (0.0, 0.0, 0.0, 0.05)
    cauter_ptsd_noise: tuple[NonNegative, NonNegative, NonNegative, NonNegative] = (15.0, 15.0, 30.0, 0.02)
    cauter_state_low: PTSD = (-60.0, -60.0, -90.0, 0.0)
    cauter_state_high: PTSD = (35.0, 60.0, 90.0, 0.25)
    poi_radius: Positive = 0.004

    def validate(self, reward_features, supported_observations) -> None:
        super().validate(reward_features, supported_observations)
        if not self.camera_far > self.camera_near:
            raise ValueError(f"camera_far ({self.camera_far}) must exceed camera_near ({self.camera_near})")
        if self.cauter_activation and not self.active_vision:
            raise ValueError("cauter_activation needs active_vision=True")
        self.camera_tpsd()  # TPSDConfig checks limits and the start state
        self.cauter_tpsd()

    def camera_tpsd(self) -> TPSDConfig:
        """The endoscope as a TPSD instrument (its 'tip' is the optic's position)."""
        return tpsd_from_config(self, rcm_position="camera_rcm_position", rcm_euler_deg="camera_rcm_euler_deg",
                                start_ptsd="camera_start_ptsd", state_low="camera_state_low",
                                state_high="camera_state_high", max_velocity="maximum_state_velocity",
                                discrete_magnitude="discrete_action_magnitude", ptsd_noise="camera_ptsd_noise")

    def cauter_tpsd(self) -> TPSDConfig:
        """The electrocautery hook as a TPSD instrument."""
        return tpsd_from_config(self, rcm_position="cauter_rcm_position", rcm_euler_deg="cauter_rcm_euler_deg",
                                start_ptsd="cauter_start_ptsd", state_low="cauter_state_low",
                                state_high="cauter_state_high", max_velocity="maximum_state_velocity",
                                discrete_magnitude="discrete_action_magnitude", ptsd_noise="cauter_ptsd_noise")


# ---------------------------------------------------------------------------- kernels
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
def eval_search_features(
    env_mask: wp.array(dtype=wp.int32),
    pose: wp.array2d(dtype=wp.transform),
    rcm: wp.array2d(dtype=wp.transform),
    flags: wp.array2d(dtype=wp.int32),
    poi: wp.array(dtype=wp.vec3),
    active: wp.array2d(dtype=wp.int32),
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
    features_out: wp.array2d(dtype=wp.float32),
):
    """Reward features of §5.3 (deltas: the env base). Instrument 0 is the endoscope, 1 the hook."""
    env = wp.tid()
    if env_mask[env] == 0:
        return
    p = poi[env]
    cam = oblique_optic_pose(pose[env, 0], optic_offset)
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
    ok = float(0.0)
    if active_vision != 0:
        if touches != 0 and (require_activation == 0 or active[env, 1] != 0):
            ok = 1.0
    else:
        if dist_err * target_distance < tolerance_distance and pixel[0] < tolerance_center and pixel[1] > 0.0:
            ok = 1.0
    features_out[env, F.POI_IS_IN_FRAME] = pixel[1]
    features_out[env, F.RELATIVE_CAMERA_DISTANCE_ERROR_TO_POI] = dist_err
    features_out[env, F.RELATIVE_PIXEL_DISTANCE_POI_TO_IMAGE_CENTER] = pixel[0]
    features_out[env, F.COLLISION_CAUTER] = float(collisions)
    features_out[env, F.RELATIVE_DISTANCE_CAUTER_TARGET] = cauter_dist
    features_out[env, F.CAUTER_TOUCHES_TARGET] = float(touches)
    features_out[env, F.CAUTER_ACTION_VIOLATED_STATE_LIMITS] = violated
    features_out[env, F.SUCCESSFUL_TASK] = ok


@wp.kernel
def sample_pois(
    env_mask: wp.array(dtype=wp.int32),
    candidates: wp.array(dtype=wp.vec3),
    rng: wp.array(dtype=wp.uint32),
    poi: wp.array(dtype=wp.vec3),
):
    """Draw each masked env's POI uniformly from the precomputed candidates."""
    env = wp.tid()
    if env_mask[env] == 0:
        return
    poi[env] = draw_candidate(rng, env, candidates)


@wp.kernel
def observe_search(
    poi: wp.array(dtype=wp.vec3),
    pose: wp.array2d(dtype=wp.transform),
    ptsd: wp.array2d(dtype=wp.vec4),
    active: wp.array2d(dtype=wp.int32),
    optic_offset: wp.quat,
    active_vision: int,
    o: OBS.Columns,
    obs_out: wp.array2d(dtype=wp.float32),
):
    """STATE: POI (3), camera pose (7), camera PTSD (4) [, cauter pose (7), cauter PTSD (4) and activation (1)]."""
    env = wp.tid()
    p = poi[env]
    for k in range(3):
        obs_out[env, o.poi + k] = p[k]
    write_transform(obs_out, env, o.camera_pose, oblique_optic_pose(pose[env, 0], optic_offset))
    s = ptsd[env, 0]
    for k in range(4):
        obs_out[env, o.camera_ptsd + k] = s[k]
    if active_vision != 0:
        write_transform(obs_out, env, o.cauter_pose, pose[env, 1])
        c = ptsd[env, 1]
        for k in range(4):
            obs_out[env, o.cauter_state + k] = c[k]
        obs_out[env, o.cauter_state + 4] = float(active[env, 1])


@wp.kernel
def update_poi_marker(poi: wp.array(dtype=wp.vec3), marker_out: wp.array2d(dtype=wp.transform)):
    env = wp.tid()
    marker_out[env, 0] = wp.transform(poi[env], wp.quat_identity())


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
    rcm_r = euler_xyz_matrix(torch.tensor(np.radians(cfg.camera_rcm_euler_deg)))
    sol = oblique_camera_ptsd(rcm_p, rcm_r, pts_t, cfg.target_distance_camera_poi, cfg.oblique_viewing_angle_deg)
    cam_pos, _ = camera_pose_from_ptsd(rcm_p, rcm_r, sol, cfg.oblique_viewing_angle_deg)
    ok = _limit_mask(sol, cfg.camera_state_low, cfg.camera_state_high) & ~torch.isnan(sol).any(-1)
    ok &= torch.from_numpy(inside_dome(cam_pos.numpy(), margin=0.005))
    idx_point, idx_roll = torch.nonzero(ok, as_tuple=True)
    starts = cam_pos[idx_point, idx_roll].numpy()
    ends = pts[idx_point.numpy()]
    dev = wp.get_device(device)
    mesh = wp.Mesh(points=wp.array(v, dtype=wp.vec3, device=dev), indices=wp.array(f.ravel(), dtype=int, device=dev))
    torch_dev = "cpu" if dev.is_cpu else f"cuda:{dev.ordinal}"

    def clear(a: np.ndarray, b: np.ndarray) -> np.ndarray:
        a, b = (torch.as_tensor(np.ascontiguousarray(x), device=torch_dev) for x in (a, b))
        return sight_lines_clear(mesh, a, b).cpu().numpy() if len(a) else np.zeros(0, bool)

    visible = np.zeros(len(pts), dtype=bool)
    visible[idx_point.numpy()[clear(starts, ends)]] = True
    if cfg.active_vision:
        rcm_c = torch.tensor(cfg.cauter_rcm_position, dtype=torch.float64)
        rot_c = euler_xyz_matrix(torch.tensor(np.radians(cfg.cauter_rcm_euler_deg)))
        visible &= _limit_mask(point_to_ptsd(rcm_c, rot_c, pts_t), cfg.cauter_state_low, cfg.cauter_state_high).numpy()
        visible &= clear(np.broadcast_to(rcm_c.numpy(), pts.shape).copy(), pts)
    result = pts[visible].astype(np.float32)
    if len(result) == 0:
        raise ValueError("no point of interest can be framed with this configuration: no abdomen point is reachable "
                         "at target_distance_camera_poi within camera_state_low..camera_state_high from "
                         "camera_rcm_position / camera_rcm_euler_deg (with active_vision also within "
                         "cauter_state_low..cauter_state_high from cauter_rcm_position / cauter_rcm_euler_deg)")
    _POI_CACHE[key] = result
    return result


# ---------------------------------------------------------------------------- env
class SearchForPointEnv(BatchedEnv):
    """LapGym's SearchForPointEnv, batched. See the module docstring and ``SearchForPointConfig``."""

    config_class = SearchForPointConfig
    task_name = "SearchForPoint"
    rewards = REWARDS
    supported_observations = ("STATE", "RGB", "RGBD", "DEPTH")
    expert = "lapwarp.tasks.spatial.search_for_point:SearchForPointExpert"
    cfg: SearchForPointConfig

    def _default_reward_weights(self) -> dict[str, float]:
        chosen = ACTIVE_VISION_WEIGHTS if self.cfg.active_vision else CAMERA_WEIGHTS
        return {**dict.fromkeys(self.rewards.names, 0.0), **chosen}

    def _build(self) -> World:
        cfg, n, dev = self.cfg, self.num_envs, self.wp_device
        builder = SceneBuilder()
        specs = [InstrumentSpec(name="endoscope", tpsd=cfg.camera_tpsd())]
        if cfg.active_vision:  # its body carries the hook's visual; its contact is checked by the reward only
            specs.append(InstrumentSpec(name="cauter", tpsd=cfg.cauter_tpsd(), shape="cauter",
                                        activation=cfg.cauter_activation, activation_deadzone=cfg.activation_deadzone))
        self.rig = InstrumentRig(specs, builder)
        world = builder.finalize(num_envs=n, device=str(dev), seed=cfg.seed)
        self.rig.finalize(world)
        self.endoscope = EndoscopeCamera(self.rig, 0, cfg.oblique_viewing_angle_deg, cfg.camera_fov_deg,
                                         cfg.camera_near, cfg.camera_far)
        self.candidates = wp.array(poi_candidates(cfg, dev), dtype=wp.vec3, device=dev)
        self.poi = wp.zeros(n, dtype=wp.vec3, device=dev)
        v, f = organ_mesh()
        self._organ_points = wp.array(v, dtype=wp.vec3, device=dev)
        self._organ_indices = wp.array(f.ravel(), dtype=int, device=dev)
        self.organ_mesh = wp.Mesh(points=self._organ_points, indices=self._organ_indices, support_winding_number=True)
        height, width = cfg.image_shape
        self._focal = focal_length(cfg.camera_fov_deg, height)
        return world

    @property
    def instruments(self):
        """The endoscope's (and hook's) ``TPSDInstruments``."""
        return self.rig.instruments

    @property
    def cauter_active(self) -> wp.array:
        """``(num_envs,)`` int32, 1 while the hook is switched on (active vision with activation)."""
        return self.rig.active[:, self.rig.num_instruments - 1]

    def _checked_state(self) -> list[wp.array]:
        return [*super()._checked_state(), self.poi]

    def _observation_layout(self) -> ObservationLayout:
        b, av = _OBS_BOUND, int(self.cfg.active_vision)
        return OBS.layout(poi=(3, -b, b), camera_pose=(7, -b, b), camera_ptsd=(4, -b, b), cauter_pose=(7 * av, -b, b),
                          cauter_state=(5 * av, -b, b))

    def _compute_features(self, env_mask: wp.array, features_out: wp.array2d) -> None:
        cfg, rig = self.cfg, self.rig
        height, width = cfg.image_shape
        launching.launch(eval_search_features, dim=self.num_envs,
                         inputs=[env_mask, rig.pose, rig.rcm, rig.flags, self.poi, rig.active,
                                 self.endoscope.optic_offset, self._focal, float(width), float(height),
                                 cfg.camera_near, cfg.target_distance_camera_poi, cfg.tolerance_target_distance,
                                 cfg.tolerance_image_center, cfg.instrument_touch_tolerance, int(cfg.active_vision),
                                 int(cfg.cauter_activation), self.organ_mesh.id], outputs=[features_out],
                         device=self.wp_device)

    def _reset_task(self, env_mask: wp.array) -> None:
        self.rig.reset(env_mask, self.world.rng)
        launching.launch(sample_pois, dim=self.num_envs, inputs=[env_mask, self.candidates, self.world.rng],
                         outputs=[self.poi], device=self.wp_device)

    def _compute_observations(self) -> None:
        rig = self.rig
        launching.launch(observe_search, dim=self.num_envs,
                         inputs=[self.poi, rig.pose, rig.ptsd, rig.active, self.endoscope.optic_offset,
                                 int(self.cfg.active_vision), self.obs_layout.columns], outputs=[self.obs_frame],
                         device=self.wp_device)
        if self.cfg.privileged_critic:
            wp.copy(self.critic_frame, self.obs_frame)  # the STATE is already privileged (the POI position)

    # ------------------------------------------------------------------ visuals
    def _build_visual_scene(self) -> VisualScene:
        """The procedural abdomen (wall, floor, organs), the POI marker (bright green) and, in active vision, the
        hook (silver). Camera: the oblique endoscope, one pose per env."""
        cfg, n, dev = self.cfg, self.num_envs, self.wp_device
        self.marker_transforms = wp.zeros((n, 1), dtype=wp.transform, device=dev)
        static = wp.full((n, 1), wp.transform_identity(), dtype=wp.transform, device=dev)
        objects = [VisualObject(part.name, "rigid", part.color, seg, part.vertices, part.faces, static)
                   for seg, part in enumerate(abdomen_parts(), start=1)]
        sv, sf = sphere_mesh(cfg.poi_radius, subdivisions=2)
        objects.append(VisualObject("poi", "rigid", (0.1, 0.95, 0.2), len(objects) + 1, sv, sf,
                                    self.marker_transforms))
        objects += self.rig.visual_objects([None, (0.72, 0.74, 0.78)], first_segmentation_id=len(objects))
        return VisualScene(camera=self.endoscope.spec, objects=objects, background=(0.0, 0.0, 0.0))

    def update_visuals(self) -> None:
        self.endoscope.update()
        if self._visual_scene is None:
            return
        launching.launch(update_poi_marker, dim=self.num_envs, inputs=[self.poi], outputs=[self.marker_transforms],
                         device=self.wp_device)

    # ------------------------------------------------------------------ privileged access (experts, tests)
    def privileged_state(self) -> dict[str, torch.Tensor]:
        """Zero-copy torch views: ``poi`` (N, 3) m, ``ptsd`` (N, K, 4) rad/m, ``pose`` / ``rcm`` (N, K, 7)
        transforms (K = 1 camera, 2 with the cauter), ``cauter_active`` (N,)."""
        rig = self.rig
        return {"poi": wp.to_torch(self.poi), "ptsd": wp.to_torch(rig.ptsd), "pose": wp.to_torch(rig.pose),
                "rcm": wp.to_torch(rig.rcm), "cauter_active": wp.to_torch(rig.active)[:, -1]}

    def set_ptsd(self, ptsd: np.ndarray, env_ids=None) -> None:
        """Host utility for tests: write instrument states (deg, deg, deg, m) and start the deltas from them."""
        self.rig.instruments.set_ptsd(ptsd, env_ids)
        self.restart_baselines()

    def set_poi(self, poi: np.ndarray) -> None:
        """Host utility for tests: place the POIs ``(num_envs, 3)`` (m) and start the deltas from them."""
        self.poi.assign(wp.array(np.asarray(poi, np.float32), dtype=wp.vec3, device=self.wp_device))
        self.restart_baselines()

    def sight_lines_clear(self, start: torch.Tensor, end: torch.Tensor) -> torch.Tensor:
        """Whether each segment ``start -> end`` ``(M, 3)`` (torch, env device) misses the organs until 2 mm before
        its end (for experts: a centred POI should also be visible)."""
        return sight_lines_clear(self.organ_mesh, start, end, 0.002)


class SearchForPointExpert(Expert):
    """Privileged controller: drives the camera to the state that centres the POI at the desired distance.

    Each call solves the oblique-optic inverse kinematics (``oblique_camera_ptsd``) for 36 roll samples, keeps the
    ones inside the state limits, prefers those with a clear line of sight to the POI, and heads for the one
    reachable soonest at maximum velocity (time = the largest per-component distance / speed), stepping exactly
    onto it when it is within one step. In active vision the hook heads for ``point_to_ptsd`` of the POI (spin kept)
    and, with activation, switches on first.
    """

    def __init__(self, env: SearchForPointEnv):
        super().__init__(env)
        cfg, dev = env.cfg, env.device
        scale = torch.tensor([math.pi / 180] * 3 + [1.0], device=dev)
        self.v_max = torch.tensor(cfg.maximum_state_velocity, device=dev) * scale
        self.low = torch.tensor(cfg.camera_state_low, device=dev) * scale
        self.high = torch.tensor(cfg.camera_state_high, device=dev) * scale
        self.step = self.v_max * cfg.time_step * cfg.frame_skip  # PTSD change of a continuous action of 1

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
        target = candidates[torch.arange(env.num_envs, device=env.device), time.argmin(dim=1)]
        target = torch.where(torch.isfinite(target), target, current).clamp(self.low, self.high)
        ideal = [(target - current) / self.step]
        if cfg.active_vision:  # the hook's tip to the POI, spin kept
            hook = point_to_ptsd(rcm[:, 1, :3], quat_to_matrix(rcm[:, 1, 3:7]), poi, ptsd[:, 1, 2])
            ideal.append((hook - ptsd[:, 1]) / self.step)
        if cfg.cauter_activation:  # switch the hook on before anything else; it then stays on (dead zone)
            ideal.append(1.0e6 * (state["cauter_active"] == 0).to(poi.dtype)[:, None])
        return self.policy_actions(torch.cat(ideal, dim=1))
