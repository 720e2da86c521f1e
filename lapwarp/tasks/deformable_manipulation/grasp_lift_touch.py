"""GraspLiftAndTouchEnv: grasp the gallbladder's infundibulum, lift it until a target on the liver is visible, and
touch the target with the activated electrocautery hook (sofa_env's GraspLiftTouchEnv; task-cards §4).

A grasper and an electrocautery hook (two pivotized TPSD instruments, one 10-D action) work on a gallbladder lying
on a liver. Phases per env (sofa_env's): GRASP until the grasper holds the infundibulum (the neck end), LIFT until
the white target sphere is visible from the camera (and the gallbladder is not pushed into the liver), TOUCH until
the active hook is within ``goal_tolerance`` of the target, then DONE. ``start_in_phase`` / ``end_in_phase`` give the
paper's configurations (Gr, GrLi, GrLiTo = the default, ...).

Scene (SI; sofa_env's frame converted from mm: its camera, the instruments' RCMs, start states, limits, the three
target positions and the workspace are sofa_env's). sofa_env's organ meshes are not shipped; the organs here are
procedural and placed to play the same roles:

* Liver: a tetrahedralised ellipsoid (``ellipsoid_tets``: 100 nodes, 288 tets; sofa_env: 98, 273), semi-axes
  72 x 86 x 78 mm, placed so that the three targets lie on the ellipsoid (the coarse mesh's flat faces lie 0.9-3 mm
  below them: the 4.5 mm target spheres sit in its surface); co-rotated FEM E = 3 MPa, nu = 0, 15 kg,
  held by springs (1e4 N/m) on the volume nodes of its back half (sofa_env: the volume nodes in a box at its back).
* Gallbladder: a pear (a tapered ellipsoid, 300 nodes, 1,080 tets; sofa_env: 367, 1,063), 90 x 57 x 48 mm, wrapped
  onto the liver's surface over the targets (they are hidden from the camera under it), its neck (the
  infundibulum, the last 30 mm) curving up to 10 mm off the liver; E = 1.5 MPa, nu = 0, 5 kg, held by springs
  (1e4 N/m) on the 24 surface vertices of its bed nearest the liver in its fundus half (sofa_env: 24 bed vertices).
* Gravity (0, +0.00981, 0) m/s^2: sofa_env's +9.81 *mm*/s^2 along +y (practically none), kept.
* Contact: the gallbladder's surface vertices against the liver's deforming surface (two-way). **sofa_env puts both
  organs in one collision group, so they pass through each other; here they collide** (the overlap feature then
  only counts what the contact solver lets through; only the gallbladder's vertices are tested against the liver's
  triangles, not the liver's against the gallbladder's). The grasper's jaws and shaft and the hook's capsules collide
  with every gallbladder node (a neck squeezed between the jaws brings its inner nodes to them), the liver's surface
  vertices, and both organs' surface triangles.

Grasping (``lapwarp.grasping``, sofa_env's rule): while the jaw angle is below 10 degrees and both jaws touch the
gallbladder, up to ``grasp_slots`` of its nodes touching a jaw inside the jaw cone (5 mm margin; sofa_env accepts a
triangle vertex within 3.2 mm of a contact) are attached to them; the jaws then pass through the gallbladder (sofa_env
switches them off); opening to 10 degrees or more releases it. "Gallbladder grasped" (sofa_env's
``gallblader_is_grasped``) needs a held node of the infundibulum on each jaw.

Target visibility (sofa_env renders the scene every step and looks for white pixels near the projected target): five
rays from the camera to points of the target sphere's camera-facing half (the nearest point and four 60 degrees
around it) against the gallbladder's and the liver's deforming surfaces; visible if one reaches its point. The
instruments do not occlude (they do in sofa_env's image).

Reward features (Table A's weights, the paper's, but for ``gallbladder_is_grasped``, see below; sofa_zoo's differ
where noted in ``REWARDS``): distances over the workspace diagonal (571.6 mm), not clipped (sofa_env's).
Phase-gated features read 0 outside their phase. Table A weighs the cauter-target distance -5 in TOUCH and -0.5
elsewhere: two features (``distance_cauter_target``, ``distance_cauter_target_touch``), likewise its change (-1 in
both; sofa_zoo: -1 and -5).

STATE observation (59, Table D): grasper tip pose (7), hook tip pose (7), grasper PTSD + jaw angle (5), hook PTSD +
activation (5), grasp established (1), target (3), phase id (1), 10 gallbladder surface vertices (30; farthest-point
samples from a random start vertex, fixed per env instance as in sofa_env). Positions normalised by the workspace
to [-1, 1], PTSD by the state limits, the jaw by its limits; quaternions xyzw.

Deliberate differences from sofa_env (task-cards §4, §12):

* The liver and the gallbladder collide (sofa_env's same-group bug fixed). No gallbladder self-contact (sofa_env
  has it; a grasp pinches the neck, it never folds onto itself here).
* ``gallbladder_is_grasped`` weighs 0, not Table A's +20: sofa_zoo misspells the key, so the paper's runs had 0.
  Applied, +20 per step makes holding the grasp worth more than finishing (700 steps x 20 against a +200 success
  that ends the episode): PPO (gpu preset, 150 iterations, H100) then learned to grasp and hold, return 12,200 and
  0 % success, against 97.3 % success with 0. ``reward_weights={"gallbladder_is_grasped": 20}`` restores it.
* Success is ``phase >= end_in_phase`` (sofa_env: equality, so a grasp that exposes the target at once skips LIFT
  and never completes configuration Gr).
* ``dynamic_force_on_gallbladder`` is the summed magnitude of the net force on the gallbladder's nodes over the env
  step, sum m |dv| / dt (sofa_env: the solver's force vector), in sofa_env's units (mN) times 1e-9.
* ``gripper_pulls_gallbladder_out`` is in mm, as in sofa_env (its weight 0.005 is per mm).
* The instruments' collision shapes are capsules (sofa_env: spheres on the jaws and the hook, none on the grasper's
  shaft).
* Starting in LIFT or TOUCH: sofa_env runs a scripted grasp (and lift) inside every reset. Here the scripted expert
  grasps (and lifts until all three targets are visible) once per env when the env is built, from that env's noisy
  instrument start; every reset of that env returns to this grasped state (its instruments, grasp and organs), with
  the target drawn anew. Envs differ from each other, episodes of one env start alike.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Annotated, Literal

import numpy as np
import torch
import warp as wp

from lapwarp import launching
from lapwarp.assets import box_tets, ellipsoid_tets, tet_surface
from lapwarp.builder import SceneBuilder
from lapwarp.config import PTSD, Count, EnvConfig, NonNegative, Positive, PositiveInt, Range, numpy_rng
from lapwarp.contact import ContactSystem
from lapwarp.env import BatchedEnv
from lapwarp.experts import Expert
from lapwarp.instruments import TPSDConfig, tpsd_from_config
from lapwarp.kernels.geometry import closest_segment_segment
from lapwarp.kernels.kinematics import point_to_ptsd
from lapwarp.tasks.deformable import DeformableObject
from lapwarp.tasks.rig import (
    CAUTER_CUTTING_CENTER,
    STATE_LIMITS_VIOLATED,
    WORKSPACE_VIOLATED,
    InstrumentRig,
    InstrumentSpec,
    RigBounds,
    RigContacts,
    cutting_center,
    instrument_touches,
    write_unit_point,
    write_unit_ptsd,
)
from lapwarp.tasks.spec import Feature, ObservationLayout, ObservationSpec, RewardSpec, to_unit, write_transform
from lapwarp.tasks.targets import draw_index
from lapwarp.visuals import CameraSpec, VisualObject, VisualScene, sphere_mesh
from lapwarp.world import World

wp.set_module_options({"enable_backward": False})

REWARDS = RewardSpec(
    Feature("collision_cauter_gripper", -0.1),
    Feature("collision_cauter_gallbladder", -0.1),
    Feature("collision_cauter_liver", -0.1),
    Feature("collision_gripper_liver", -0.1),  # sofa_zoo: -0.01
    Feature("distance_cauter_target", -0.5),  # outside TOUCH
    Feature("distance_cauter_target_touch", -5.0),  # in TOUCH (sofa_zoo: -0.5)
    Feature("delta_distance_cauter_target", -1.0),  # outside TOUCH
    Feature("delta_distance_cauter_target_touch", -1.0),  # in TOUCH (sofa_zoo: -5)
    Feature("cauter_touches_target", 0.0),  # TOUCH
    Feature("cauter_activation_in_target", 0.0),  # TOUCH
    Feature("cauter_delta_activation_in_target", 1.0),  # TOUCH
    Feature("target_visible", 0.0),
    Feature("gripper_distance_to_infundibulum", -0.2),  # GRASP
    Feature("delta_gripper_distance_to_infundibulum", -10.0),  # GRASP
    Feature("gallbladder_is_grasped", 0.0),  # Table A: +20, never applied in the paper's runs (module docstring)
    Feature("new_grasp_on_gallbladder", 10.0),
    Feature("lost_grasp_on_gallbladder", -10.0),
    Feature("active_grasping_springs", 0.0),
    Feature("delta_active_grasping_springs", 0.0),
    Feature("gripper_distance_to_trocar", 0.0),
    Feature("gripper_pulls_gallbladder_out", 0.005),
    Feature("overlap_gallbladder_liver", -0.1),
    Feature("delta_overlap_gallbladder_liver", -0.01),
    Feature("dynamic_force_on_gallbladder", -0.003),
    Feature("gripper_action_violated_state_limits", 0.0),
    Feature("gripper_action_violated_cartesian_workspace", 0.0),
    Feature("cauter_action_violated_state_limits", 0.0),
    Feature("cauter_action_violated_cartesian_workspace", 0.0),
    Feature("phase_change", 10.0),
    Feature("failed_task", 0.0),
    Feature("successful_task", 200.0),
    failure="failed_task",
)
F = REWARDS.F
OBS = ObservationSpec("gripper_pose", "cauter_pose", "gripper_ptsdj", "cauter_ptsda", "grasped", "target", "phase",
                      "tracking")
CRITIC = OBS.extend("cauter_to_target", "grasp_to_infundibulum", "visible")

GRASP, LIFT, TOUCH, DONE = 0, 1, 2, 3
PHASES = {"GRASP": GRASP, "LIFT": LIFT, "TOUCH": TOUCH, "DONE": DONE}
MM = 1.0e-3
#: sofa_env's target positions (m) and radius
TARGETS = tuple(tuple(c * MM for c in t) for t in ((-50.0, 15.0, -25.0), (-55.0, 10.0, -20.0), (-60.0, 8.0, -15.0)))
TARGET_RADIUS = 4.5 * MM
CAMERA_POSITION = (-94.5 * MM, -113.6 * MM, -237.2 * MM)
CAMERA_QUAT = (0.683409, -0.684564, 0.0405591, 0.25036)  # xyzw, looks along its local -z (OpenGL)
WORKSPACE = ((-0.2, -0.2, -0.2), (0.13, 0.13, 0.13))
# procedural organs (mm, see the module docstring)
LIVER_SEMI_AXES = np.array([72.0, 86.0, 78.0])
LIVER_CELLS, GALLBLADDER_CELLS = (3, 4, 4), (9, 5, 4)
GB_LENGTH, GB_WIDTH, GB_THICKNESS = 90.0, 57.0, 48.0
GB_TARGET_AT = 0.5  # the middle target lies under this fraction of the length (fundus 0 -> neck 1)
GB_TAPER, GB_NECK_LIFT, GB_GAP = 0.7, 10.0, 0.5
GB_AXIS_HINT = (0.59, -0.74, -0.32)  # the fundus -> neck direction before projecting onto the liver's tangent plane
INFUNDIBULUM_FROM = 1.0 - 30.0 / GB_LENGTH  # the last 30 mm
BED_VERTICES = 24
JAW_LENGTH = 0.025
GRASP_CENTER = 0.5 * JAW_LENGTH  # sofa_env: the mean of the jaws' 20 sphere centres
NUM_RAYS = 5
PARTICLE_RADIUS = 1.0e-3
LIVER_COLOR, GALLBLADDER_COLOR, GRIPPER_COLOR, CAUTER_COLOR = (0.6, 0.1, 0.08), (0.9, 0.75, 0.2), \
    (0.2, 0.3, 0.85), (0.2, 0.7, 0.3)
_TRACK = 10


def liver_center() -> np.ndarray:
    """The liver's centre (mm): the middle target lies on the ellipsoid where its normal is (-1, 0, -1)/sqrt 2 (the
    normal of the plane through the three targets)."""
    a = LIVER_SEMI_AXES
    k = 1.0 / math.sqrt(a[0] ** 2 + a[2] ** 2)
    t = np.asarray(TARGETS[1]) / MM
    return np.array([t[0] + k * a[0] ** 2, t[1] + 1.0, t[2] + k * a[2] ** 2])


def _liver_surface_point(p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The radial projection of points (mm) onto the liver ellipsoid and its outward normals there."""
    c, a = liver_center(), LIVER_SEMI_AXES
    d = (p - c) / a
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    s = c + d * a
    n = (s - c) / a**2
    return s, n / np.linalg.norm(n, axis=-1, keepdims=True)


def liver_mesh() -> tuple[np.ndarray, np.ndarray]:
    """Liver nodes (m) and tets."""
    v, t = ellipsoid_tets(LIVER_CELLS, LIVER_SEMI_AXES)
    return (v + liver_center()) * MM, t


def gallbladder_mesh() -> dict[str, np.ndarray]:
    """Gallbladder nodes (m), tets, each node's position along it (0 fundus .. 1 neck), the nodes of the grid's end
    face at the neck (``neck_end``), its bed vertices (anchored) and the frame it lies in (axis fundus -> neck, liver
    normal; unit vectors)."""
    v, t = ellipsoid_tets(GALLBLADDER_CELLS, (1.0, 1.0, 1.0))
    grid, _ = box_tets(size=(2.0, 2.0, 2.0), cells=GALLBLADDER_CELLS, origin=(-1.0, -1.0, -1.0))
    target = np.asarray(TARGETS[1]) / MM
    _, n = _liver_surface_point(target[None])
    n = n[0]
    u = np.asarray(GB_AXIS_HINT, dtype=np.float64)
    u = u - (u @ n) * n
    u /= np.linalg.norm(u)
    w = np.cross(n, u)
    s = 0.5 * (v[:, 0] + 1.0)
    scale = 1.0 - GB_TAPER * np.clip((s - 0.35) / 0.65, 0.0, 1.0) ** 1.5  # a pear: full fundus, narrow neck
    along = (s - GB_TARGET_AT) * GB_LENGTH
    across = v[:, 1] * 0.5 * GB_WIDTH * scale
    height = (v[:, 2] + 1.0) * 0.5 * GB_THICKNESS * scale  # above the slice's lowest point
    base, normal = _liver_surface_point(target + along[:, None] * u + across[:, None] * w)
    lift = GB_GAP + GB_NECK_LIFT * np.clip((s - 0.6) / 0.4, 0.0, 1.0) ** 2
    x = base + normal * (height + lift)[:, None]
    # the shaping must not turn a tet inside out (the builder would silently re-order it and keep the fold)
    signs = [np.sign(np.linalg.det(np.stack([p[t[:, i]] - p[t[:, 0]] for i in (1, 2, 3)], axis=2))) for p in (grid, x)]
    if np.any(signs[0] != signs[1]):
        raise RuntimeError(f"{int((signs[0] != signs[1]).sum())} gallbladder tets inverted by the shaping")
    surface = np.unique(tet_surface(t))
    low = surface[s[surface] < 0.5]
    bed = low[np.argsort(height[low] + 1e-3 * np.abs(across[low]))[:BED_VERTICES]]
    return dict(vertices=x * MM, tets=t, s=s, neck_end=np.nonzero(grid[:, 0] > 1.0 - 1e-9)[0], bed=np.sort(bed),
                axis=u, normal=n)


def tet_volume(vertices: np.ndarray, tets: np.ndarray) -> float:
    """Total volume of a tet mesh (m^3)."""
    edges = np.stack([vertices[tets[:, i]] - vertices[tets[:, 0]] for i in (1, 2, 3)], axis=2)
    return float(np.abs(np.linalg.det(edges)).sum() / 6.0)


def tracking_vertices(surface: np.ndarray, positions: np.ndarray, num_envs: int, count: int,
                      rng: np.random.Generator) -> np.ndarray:
    """Per env ``count`` surface vertices by farthest-point sampling from a random start vertex (sofa_env's, once per
    env instance): ``(num_envs, count)`` indices local to the gallbladder."""
    x = positions[surface]
    out = np.zeros((num_envs, count), dtype=np.int64)
    out[:, 0] = rng.integers(len(surface), size=num_envs)
    dist = np.linalg.norm(x[None, :, :] - x[out[:, 0]][:, None, :], axis=2)
    for k in range(1, count):
        out[:, k] = dist.argmax(axis=1)
        dist = np.minimum(dist, np.linalg.norm(x[None, :, :] - x[out[:, k]][:, None, :], axis=2))
    return surface[out].astype(np.int32)


@dataclass(kw_only=True)
class GraspLiftAndTouchConfig(EnvConfig):
    """GraspLiftAndTouchEnv parameters (Tables B, C: the paper's = sofa_zoo's values); metres, degrees, kg.

    Attributes:
        start_in_phase / end_in_phase: the paper's configurations: (GRASP, LIFT) = Gr, (GRASP, TOUCH) = GrLi,
            (GRASP, DONE) = GrLiTo (default), (LIFT, TOUCH) = Li, (LIFT, DONE) = LiTo, (TOUCH, DONE) = To. A start
            in LIFT or TOUCH begins grasped (and, for TOUCH, lifted until every target is visible): see
            ``grasped_start_steps`` and the module docstring.
        grasped_start_steps: env steps the build-time scripted grasp (and lift) may take per try (three tries).
        tool_collision_distance: the instruments' axes (grasp centre -> RCM, hook centre -> RCM) closer than this
            count as colliding, m.
        goal_tolerance: hook centre to target distance that touches it, m.
        cauter_has_to_activate_in_target: DONE needs the hook switched on in the target (else touching suffices).
        max_gallbladder_liver_overlap: TOUCH needs the overlap feature at or below this.
        gallbladder_force_scaling_factor: scale of ``dynamic_force_on_gallbladder`` (sofa_env's 1e-9 on mN).
        losing_grasp_ends_episode: a grasp lost after LIFT ends the episode as failed.
        gripper_start_ptsd / cauter_start_ptsd (deg, deg, deg, m), gripper_jaw_start (deg), ptsd_noise,
            jaw_noise: sofa_env's start states and reset noise (uniform +-).
        state_low / state_high: both instruments' state limits (deg, deg, deg, m).
        maximum_state_velocity / jaw_speed: speeds at action 1 (deg/s, deg/s, deg/s, m/s; deg/s).
        discrete_action_magnitude / jaw_discrete_speed: speeds of a discrete action (sofa_env's).
        grasp_threshold: grasp below, release at or above this jaw angle (deg).
        grasp_slots: gallbladder vertices a grasp holds at most.
        liver_youngs_modulus / gallbladder_youngs_modulus (Pa), poisson_ratio, liver_mass / gallbladder_mass (kg),
            anchor_stiffness (N/m), damping (1/s), gravity (m/s^2 along +y): the organs (see the module docstring).
        physics_substeps: XPBD substeps per physics step.
        contact_capacity: contact records kept per env per step.
        max_episode_steps: None = 400 + 100 x (end - start phase) (Table C).
    """

    time_step: Positive = 0.05
    frame_skip: Count(1000) = 2
    max_episode_steps: PositiveInt | None = None
    start_in_phase: Literal["GRASP", "LIFT", "TOUCH"] = "GRASP"
    end_in_phase: Literal["LIFT", "TOUCH", "DONE"] = "DONE"
    tool_collision_distance: NonNegative = 0.005
    goal_tolerance: Positive = 0.005
    cauter_has_to_activate_in_target: bool = True
    max_gallbladder_liver_overlap: Annotated[float, Range(ge=0.0, le=1.0)] = 0.1
    gallbladder_force_scaling_factor: NonNegative = 1.0e-9
    losing_grasp_ends_episode: bool = False
    grasped_start_steps: Count(10_000) = 200
    gripper_start_ptsd: PTSD = (-15.0, 30.0, -20.0, 0.13)
    cauter_start_ptsd: PTSD = (-15.0, 45.0, 0.0, 0.15)
    gripper_jaw_start: Annotated[float, Range(ge=0.0, le=60.0)] = 45.0
    ptsd_noise: tuple[NonNegative, NonNegative, NonNegative, NonNegative] = (10.0, 10.0, 45.0, 0.01)
    jaw_noise: NonNegative = 20.0
    state_low: PTSD = (-75.0, -40.0, -1000.0, 0.012)
    state_high: PTSD = (75.0, 75.0, 1000.0, 0.3)
    maximum_state_velocity: tuple[Positive, Positive, Positive, Positive] = (15.0, 15.0, 25.0, 0.025)
    discrete_action_magnitude: tuple[Positive, Positive, Positive, Positive] = (10.0, 10.0, 15.0, 0.015)
    jaw_speed: Positive = 20.0
    jaw_discrete_speed: Positive = 12.0
    grasp_threshold: Annotated[float, Range(gt=0.0, le=60.0)] = 10.0
    grasp_slots: Annotated[int, Range(ge=1, le=64)] = 8
    liver_youngs_modulus: Positive = 3.0e6
    gallbladder_youngs_modulus: Positive = 1.5e6
    poisson_ratio: Annotated[float, Range(ge=0.0, lt=0.5)] = 0.0
    liver_mass: Positive = 15.0
    gallbladder_mass: Positive = 5.0
    anchor_stiffness: Positive = 1.0e4
    damping: NonNegative = 10.0
    gravity: float = 0.00981
    physics_substeps: Count(10_000) = 5
    contact_capacity: Count(4096) = 128

    def validate(self, reward_features, supported_observations) -> None:
        super().validate(reward_features, supported_observations)
        start, end = PHASES[self.start_in_phase], PHASES[self.end_in_phase]
        if end <= start:
            raise ValueError(f"end_in_phase={self.end_in_phase!r} must come after start_in_phase="
                             f"{self.start_in_phase!r} (GRASP < LIFT < TOUCH < DONE)")
        if self.max_episode_steps is None:
            self.max_episode_steps = 400 + 100 * (end - start)  # Table C
        self.tpsd("gripper")
        self.tpsd("cauter")

    def tpsd(self, instrument: str) -> TPSDConfig:
        """sofa_env's RCMs: grasper at (-160, 30, -200) mm, Euler (0, 20, 45); hook at (-150, -200, 0) mm, Euler
        (0, 90, 180)."""
        rcm = {"gripper": ((-0.16, 0.03, -0.2), (0.0, 20.0, 45.0)), "cauter": ((-0.15, -0.2, 0.0), (0.0, 90.0, 180.0))}
        position, euler = rcm[instrument]
        return tpsd_from_config(self, rcm_position=position, rcm_euler_deg=euler,
                                start_ptsd=f"{instrument}_start_ptsd", state_low="state_low", state_high="state_high",
                                workspace_low=WORKSPACE[0], workspace_high=WORKSPACE[1],
                                max_velocity="maximum_state_velocity", discrete_magnitude="discrete_action_magnitude",
                                ptsd_noise="ptsd_noise")


# ---------------------------------------------------------------------------- kernels
@wp.struct
class Task:
    """Per-env task state: phase, target index and position, the gallbladder's tracking vertices, this step's
    visibility rays and overlap count, and the last step's raw values for the delta features."""

    phase: wp.array(dtype=wp.int32)
    target_index: wp.array(dtype=wp.int32)
    target: wp.array(dtype=wp.vec3)
    tracking: wp.array2d(dtype=wp.int32)
    ray_clear: wp.array2d(dtype=wp.int32)
    overlap_count: wp.array(dtype=wp.int32)
    overlap_at_reset: wp.array(dtype=float)
    was_grasped: wp.array(dtype=wp.int32)
    last_cauter_distance: wp.array(dtype=float)
    last_infundibulum_distance: wp.array(dtype=float)
    last_springs: wp.array(dtype=float)
    last_trocar_distance: wp.array(dtype=float)
    last_overlap: wp.array(dtype=float)
    last_activation: wp.array(dtype=float)
    last_velocity: wp.array2d(dtype=wp.vec3)


@wp.struct
class Params:
    bounds: RigBounds
    gb_first: int
    gb_count: int
    liver_first: int
    inv_node_count: float
    slot_start: int
    slots: int
    jaw_a: int
    jaw_b: int
    tool_distance: float
    tolerance: float
    must_activate: int
    max_overlap: float
    force_scale: float
    lose_ends: int
    end_phase: int
    start_phase: int
    control_dt: float
    jaw_low: float
    jaw_high: float
    camera: wp.vec3


@wp.struct
class Organs:
    """Gallbladder node flags (infundibulum), node masses, both organs' surface triangles (global indices) and the
    liver's rest surface (for the overlap test)."""

    infundibulum: wp.array(dtype=wp.int32)
    infundibulum_nodes: wp.array(dtype=wp.int32)
    mass: wp.array(dtype=float)
    gb_tris: wp.array(dtype=wp.vec3i)
    liver_tris: wp.array(dtype=wp.vec3i)
    liver_rest: wp.uint64


@wp.func
def grasp_center(tip: wp.transform) -> wp.vec3:
    return wp.transform_point(tip, wp.vec3(0.0, 0.0, GRASP_CENTER))


@wp.func
def infundibulum_center(q: wp.array2d(dtype=wp.vec3), env: int, organs: Organs) -> wp.vec3:
    c = wp.vec3(0.0)
    m = organs.infundibulum_nodes.shape[0]
    for i in range(m):
        c += q[env, organs.infundibulum_nodes[i]]
    return c / float(m)


@wp.func
def ray_point(target: wp.vec3, camera: wp.vec3, r: int) -> wp.vec3:
    """Ray ``r``'s end on the target sphere: the point nearest the camera (r = 0) or one of four 60 degrees off it."""
    d = wp.normalize(camera - target)
    if r == 0:
        return target + d * TARGET_RADIUS
    e1 = wp.normalize(wp.cross(d, wp.vec3(0.0, 1.0, 0.0)))
    e2 = wp.cross(d, e1)
    phi = float(r - 1) * 0.5 * wp.pi
    side = e1 * wp.cos(phi) + e2 * wp.sin(phi)
    return target + (d * 0.5 + side * 0.8660254) * TARGET_RADIUS


@wp.func
def segment_hits_triangle(a: wp.vec3, b: wp.vec3, p0: wp.vec3, p1: wp.vec3, p2: wp.vec3) -> int:
    """Moeller-Trumbore: 1 if the segment a -> b crosses the triangle."""
    d = b - a
    e1 = p1 - p0
    e2 = p2 - p0
    h = wp.cross(d, e2)
    det = wp.dot(e1, h)
    if wp.abs(det) < 1.0e-14:
        return 0
    inv = 1.0 / det
    s = a - p0
    u = wp.dot(s, h) * inv
    if u < 0.0 or u > 1.0:
        return 0
    qv = wp.cross(s, e1)
    v = wp.dot(d, qv) * inv
    if v < 0.0 or u + v > 1.0:
        return 0
    t = wp.dot(e2, qv) * inv
    if t > 0.0 and t < 1.0:
        return 1
    return 0


@wp.kernel
def cast_target_rays(q: wp.array2d(dtype=wp.vec3), organs: Organs, p: Params, task: Task):
    """Thread per (env, ray): whether the ray from the camera to its point on the target sphere misses both organs'
    surfaces (stopping 0.3 mm short of the point)."""
    env, r = wp.tid()
    end = ray_point(task.target[env], p.camera, r)
    start = p.camera
    end = end + wp.normalize(start - end) * 3.0e-4
    clear = int(1)
    for f in range(organs.gb_tris.shape[0]):
        t = organs.gb_tris[f]
        if segment_hits_triangle(start, end, q[env, t[0]], q[env, t[1]], q[env, t[2]]) != 0:
            clear = 0
            break
    if clear != 0:
        for f in range(organs.liver_tris.shape[0]):
            t = organs.liver_tris[f]
            if segment_hits_triangle(start, end, q[env, t[0]], q[env, t[1]], q[env, t[2]]) != 0:
                clear = 0
                break
    task.ray_clear[env, r] = clear


@wp.kernel
def count_overlap(q: wp.array2d(dtype=wp.vec3), organs: Organs, p: Params, task: Task):
    """Thread per (env, gallbladder node): nodes inside the liver's rest surface (sofa_env's MeshROI on the liver's
    file surface), counted per env."""
    env, i = wp.tid()
    x = q[env, p.gb_first + i]
    query = wp.mesh_query_point_sign_normal(organs.liver_rest, x, 1.0)
    if query.result:
        if query.sign < 0.0:
            wp.atomic_add(task.overlap_count, env, 1)


@wp.func
def held_infundibulum_sides(attach_particle: wp.array2d(dtype=wp.int32), attach_body: wp.array2d(dtype=wp.int32),
                            env: int, p: Params, organs: Organs) -> wp.vec3i:
    """(held vertices, held infundibulum vertices on jaw A, on jaw B) of the grasp slots."""
    count = int(0)
    a = int(0)
    b = int(0)
    for k in range(p.slots):
        i = attach_particle[env, p.slot_start + k]
        body = attach_body[env, p.slot_start + k]
        if i >= 0 and (body == p.jaw_a or body == p.jaw_b):
            count += 1
            if organs.infundibulum[i - p.gb_first] != 0:
                if body == p.jaw_a:
                    a += 1
                else:
                    b += 1
    return wp.vec3i(count, a, b)


@wp.func
def store_history(task: Task, env: int, grasped: int, d_cauter: float, d_infundibulum: float, springs: float,
                  d_trocar: float, overlap: float, in_target: float):
    """This step's raw values, which the next step's delta features start from."""
    task.was_grasped[env] = grasped
    task.last_cauter_distance[env] = d_cauter
    task.last_infundibulum_distance[env] = d_infundibulum
    task.last_springs[env] = springs
    task.last_trocar_distance[env] = d_trocar
    task.last_overlap[env] = overlap
    task.last_activation[env] = in_target


@wp.kernel
def eval_grasp_lift_touch(env_mask: wp.array(dtype=wp.int32), mode: int, q: wp.array2d(dtype=wp.vec3),
                          qd: wp.array2d(dtype=wp.vec3), pose: wp.array2d(dtype=wp.transform),
                          rcm: wp.array2d(dtype=wp.transform), active: wp.array2d(dtype=wp.int32),
                          flags: wp.array2d(dtype=wp.int32), grasped: wp.array(dtype=wp.int32),
                          attach_particle: wp.array2d(dtype=wp.int32), attach_body: wp.array2d(dtype=wp.int32),
                          contacts: RigContacts, gb_group: int, liver_group: int, organs: Organs, p: Params,
                          task: Task, features_out: wp.array2d(dtype=float)):
    """sofa_env's reward features and phase switch. ``mode`` 1 (the step's evaluation) also switches the phase and
    stores this step's raw values for the next step's deltas; mode 2 (reset) only stores them."""
    env = wp.tid()
    if env_mask[env] == 0:
        return
    g_tip = pose[env, 0]
    c_tip = pose[env, 1]
    gc = grasp_center(g_tip)
    cc = cutting_center(c_tip)
    target = task.target[env]
    held = held_infundibulum_sides(attach_particle, attach_body, env, p, organs)
    is_grasped = int(0)
    if grasped[env] != 0 and held[1] > 0 and held[2] > 0:
        is_grasped = 1
    visible = int(0)
    for r in range(task.ray_clear.shape[1]):
        visible = visible | task.ray_clear[env, r]
    overlap = float(task.overlap_count[env]) * p.inv_node_count
    if mode == 2:
        task.overlap_at_reset[env] = overlap
    overlap = overlap - task.overlap_at_reset[env]
    inv = p.bounds.inv_diagonal
    d_cauter = wp.length(cc - target)
    d_infundibulum = wp.length(gc - infundibulum_center(q, env, organs))
    d_trocar = wp.length(wp.transform_get_translation(g_tip) - wp.transform_get_translation(rcm[env, 0]))
    springs = float(held[0])
    in_target = wp.where(active[env, 1] != 0 and d_cauter < p.tolerance, 1.0, 0.0)
    force = float(0.0)
    for i in range(p.gb_count):
        v = qd[env, p.gb_first + i]
        force += organs.mass[i] * wp.length(v - task.last_velocity[env, i])
        if mode != 0:
            task.last_velocity[env, i] = v
    force = force / p.control_dt * 1.0e3 * p.force_scale  # N -> mN (sofa_env's mm scene), then its scale
    if mode == 2:
        store_history(task, env, is_grasped, d_cauter, d_infundibulum, springs, d_trocar, overlap, in_target)
        return
    # phase (sofa_env's order: grasp, then lift / touch from visibility and overlap, then done)
    old = task.phase[env]
    phase = old
    if old != DONE:
        if is_grasped == 0:
            phase = GRASP
        elif visible != 0 and overlap <= p.max_overlap:
            phase = TOUCH
        else:
            phase = LIFT
        touching = d_cauter < p.tolerance and (active[env, 1] != 0 or p.must_activate == 0)
        if phase == TOUCH and touching:
            phase = DONE
    touch = wp.where(phase == TOUCH, 1.0, 0.0)
    grasp_phase = wp.where(phase == GRASP, 1.0, 0.0)
    other = 1.0 - touch
    # the instruments' axes (sofa_env: grasp centre -> RCM and hook centre -> RCM)
    a0 = gc
    a1 = wp.transform_get_translation(rcm[env, 0])
    b0 = cc
    b1 = wp.transform_get_translation(rcm[env, 1])
    st = closest_segment_segment(a0, a1, b0, b1)
    axes = wp.length(a0 + (a1 - a0) * st[0] - (b0 + (b1 - b0) * st[1]))
    features_out[env, F.COLLISION_CAUTER_GRIPPER] = wp.where(axes < p.tool_distance, 1.0, 0.0)
    features_out[env, F.COLLISION_CAUTER_GALLBLADDER] = float(instrument_touches(contacts, env, 1, gb_group, 0))
    features_out[env, F.COLLISION_CAUTER_LIVER] = float(instrument_touches(contacts, env, 1, liver_group, 0))
    features_out[env, F.COLLISION_GRIPPER_LIVER] = float(instrument_touches(contacts, env, 0, liver_group, 0))
    features_out[env, F.DISTANCE_CAUTER_TARGET] = d_cauter * inv * other
    features_out[env, F.DISTANCE_CAUTER_TARGET_TOUCH] = d_cauter * inv * touch
    delta_cauter = (d_cauter - task.last_cauter_distance[env]) * inv
    features_out[env, F.DELTA_DISTANCE_CAUTER_TARGET] = delta_cauter * other
    features_out[env, F.DELTA_DISTANCE_CAUTER_TARGET_TOUCH] = delta_cauter * touch
    features_out[env, F.CAUTER_TOUCHES_TARGET] = wp.where(d_cauter < p.tolerance, 1.0, 0.0) * touch
    features_out[env, F.CAUTER_ACTIVATION_IN_TARGET] = in_target * touch
    features_out[env, F.CAUTER_DELTA_ACTIVATION_IN_TARGET] = (in_target - task.last_activation[env]) * touch
    features_out[env, F.TARGET_VISIBLE] = float(visible)
    features_out[env, F.GRIPPER_DISTANCE_TO_INFUNDIBULUM] = d_infundibulum * inv * grasp_phase
    features_out[env, F.DELTA_GRIPPER_DISTANCE_TO_INFUNDIBULUM] = (
        (d_infundibulum - task.last_infundibulum_distance[env]) * inv * grasp_phase)
    features_out[env, F.GALLBLADDER_IS_GRASPED] = float(is_grasped)
    new_grasp = wp.where(is_grasped != 0 and task.was_grasped[env] == 0, 1.0, 0.0)
    lost = wp.where(is_grasped == 0 and task.was_grasped[env] != 0, 1.0, 0.0)
    features_out[env, F.NEW_GRASP_ON_GALLBLADDER] = new_grasp
    features_out[env, F.LOST_GRASP_ON_GALLBLADDER] = lost
    features_out[env, F.ACTIVE_GRASPING_SPRINGS] = springs
    features_out[env, F.DELTA_ACTIVE_GRASPING_SPRINGS] = springs - task.last_springs[env]
    features_out[env, F.GRIPPER_DISTANCE_TO_TROCAR] = d_trocar * inv
    features_out[env, F.GRIPPER_PULLS_GALLBLADDER_OUT] = float(is_grasped) * (
        task.last_trocar_distance[env] - d_trocar) / MM
    features_out[env, F.OVERLAP_GALLBLADDER_LIVER] = overlap
    features_out[env, F.DELTA_OVERLAP_GALLBLADDER_LIVER] = overlap - task.last_overlap[env]
    features_out[env, F.DYNAMIC_FORCE_ON_GALLBLADDER] = force
    features_out[env, F.GRIPPER_ACTION_VIOLATED_STATE_LIMITS] = wp.where(
        (flags[env, 0] & STATE_LIMITS_VIOLATED) != 0, 1.0, 0.0)
    features_out[env, F.GRIPPER_ACTION_VIOLATED_CARTESIAN_WORKSPACE] = wp.where(
        (flags[env, 0] & WORKSPACE_VIOLATED) != 0, 1.0, 0.0)
    features_out[env, F.CAUTER_ACTION_VIOLATED_STATE_LIMITS] = wp.where(
        (flags[env, 1] & STATE_LIMITS_VIOLATED) != 0, 1.0, 0.0)
    features_out[env, F.CAUTER_ACTION_VIOLATED_CARTESIAN_WORKSPACE] = wp.where(
        (flags[env, 1] & WORKSPACE_VIOLATED) != 0, 1.0, 0.0)
    features_out[env, F.PHASE_CHANGE] = float(phase - old)
    failed = float(0.0)
    if p.lose_ends != 0 and lost > 0.0 and old >= LIFT:
        failed = 1.0
    features_out[env, F.FAILED_TASK] = failed
    features_out[env, F.SUCCESSFUL_TASK] = wp.where(phase >= p.end_phase, 1.0, 0.0)
    if mode == 1:
        task.phase[env] = phase
        store_history(task, env, is_grasped, d_cauter, d_infundibulum, springs, d_trocar, overlap, in_target)


@wp.kernel
def reset_grasp_lift_touch(env_mask: wp.array(dtype=wp.int32), rng: wp.array(dtype=wp.uint32),
                           targets: wp.array(dtype=wp.vec3), p: Params, task: Task):
    """sofa_env's reset: the target drawn uniformly from its three positions, the start phase."""
    env = wp.tid()
    if env_mask[env] == 0:
        return
    k = draw_index(rng, env, targets.shape[0])
    task.target_index[env] = k
    task.target[env] = targets[k]
    task.phase[env] = p.start_phase


@wp.kernel
def observe_grasp_lift_touch(q: wp.array2d(dtype=wp.vec3), ptsd: wp.array2d(dtype=wp.vec4),
                             pose: wp.array2d(dtype=wp.transform), jaw_angle: wp.array2d(dtype=float),
                             active: wp.array2d(dtype=wp.int32), grasped: wp.array(dtype=wp.int32), organs: Organs,
                             p: Params, task: Task, o: OBS.Columns, c: CRITIC.Columns, privileged: int,
                             obs_out: wp.array2d(dtype=float), critic_out: wp.array2d(dtype=float)):
    """sofa_env's STATE (see the module docstring), positions normalised by the workspace."""
    env = wp.tid()
    b = p.bounds
    for k in range(2):
        col = wp.where(k == 0, o.gripper_pose, o.cauter_pose)
        tip = pose[env, k]
        write_transform(obs_out, env, col, tip)
        write_unit_point(obs_out, env, col, wp.transform_get_translation(tip), b)
    write_unit_ptsd(obs_out, env, o.gripper_ptsdj, ptsd[env, 0], b)
    obs_out[env, o.gripper_ptsdj + 4] = to_unit(jaw_angle[env, 0], p.jaw_low, p.jaw_high)
    write_unit_ptsd(obs_out, env, o.cauter_ptsda, ptsd[env, 1], b)
    obs_out[env, o.cauter_ptsda + 4] = float(active[env, 1])
    obs_out[env, o.grasped] = float(grasped[env])
    write_unit_point(obs_out, env, o.target, task.target[env], b)
    obs_out[env, o.phase] = float(task.phase[env])
    for t in range(task.tracking.shape[1]):
        write_unit_point(obs_out, env, o.tracking + 3 * t, q[env, p.gb_first + task.tracking[env, t]], b)
    if privileged == 0:
        return
    to_target = (task.target[env] - cutting_center(pose[env, 1])) * b.inv_diagonal
    to_neck = (infundibulum_center(q, env, organs) - grasp_center(pose[env, 0])) * b.inv_diagonal
    for i in range(3):
        critic_out[env, c.cauter_to_target + i] = to_target[i]
        critic_out[env, c.grasp_to_infundibulum + i] = to_neck[i]
    visible = int(0)
    for r in range(task.ray_clear.shape[1]):
        visible = visible | task.ray_clear[env, r]
    critic_out[env, c.visible] = float(visible)


@wp.kernel
def place_target_visual(task: Task, poses_out: wp.array2d(dtype=wp.transform)):
    env = wp.tid()
    poses_out[env, 0] = wp.transform(task.target[env], wp.quat_identity())


@wp.func
def ptsd_error_toward(rcm: wp.transform, tip_pos: wp.vec3, s: wp.vec4, goal: wp.vec3, max_step: float) -> wp.vec4:
    """The PTSD change that moves the tip at most ``max_step`` along the straight line to ``goal``."""
    move = goal - tip_pos
    if wp.length(move) > max_step:
        move = move * (max_step / wp.length(move))
    t = point_to_ptsd(rcm, tip_pos + move, s[2])
    return wp.vec4(t[0] - s[0], t[1] - s[1], 0.0, t[3] - s[3])


@wp.kernel
def expert_commands(q: wp.array2d(dtype=wp.vec3), ptsd: wp.array2d(dtype=wp.vec4),
                    pose: wp.array2d(dtype=wp.transform), rcm: wp.array2d(dtype=wp.transform),
                    jaw_angle: wp.array2d(dtype=float), active: wp.array2d(dtype=wp.int32),
                    grasped: wp.array(dtype=wp.int32), organs: Organs, neck_tip: wp.array(dtype=wp.int32),
                    across: wp.vec3, p: Params, task: Task, hold_depth: float,
                    standoff: float, retract: float, max_step: float, in_place: float, lateral_first: int,
                    closing: wp.array(dtype=wp.int32),
                    error_out: wp.array2d(dtype=float)):
    """The scripted grasper and hook (``GraspLiftAndTouchExpert``): PTSD, jaw and activation errors per env."""
    env = wp.tid()
    g_tip = pose[env, 0]
    g_pos = wp.transform_get_translation(g_tip)
    g_s = ptsd[env, 0]
    g_rcm = rcm[env, 0]
    for i in range(10):
        error_out[env, i] = 0.0
    phase = task.phase[env]
    if grasped[env] == 0:
        # the neck's end between the jaws, ``hold_depth`` along them, the jaws opening across the neck
        neck = wp.vec3(0.0)
        for i in range(neck_tip.shape[0]):
            neck += q[env, neck_tip[i]]
        neck = neck / float(neck_tip.shape[0])
        axis = wp.normalize(neck - wp.transform_get_translation(g_rcm))
        hold = neck - axis * hold_depth
        approach = hold - axis * standoff
        # the point of the approach line nearest the tip: off the line, go to the stand-off point first
        off_line = wp.length(wp.cross(g_pos - hold, axis))
        goal = hold
        if off_line > 2.0 * in_place:
            goal = approach
        e = ptsd_error_toward(g_rcm, g_pos, g_s, goal, max_step)
        if lateral_first != 0 and off_line > in_place:
            e = wp.vec4(e[0], e[1], e[2], 0.0)  # a discrete step does one thing: line up before advancing
        opening = wp.transform_vector(g_tip, wp.vec3(0.0, 1.0, 0.0))
        want = wp.normalize(across - axis * wp.dot(across, axis))
        turn = wp.atan2(wp.dot(wp.cross(opening, want), axis), wp.dot(opening, want))
        if turn > 0.5 * wp.pi:
            turn = turn - wp.pi
        if turn < -0.5 * wp.pi:
            turn = turn + wp.pi
        # close once in place with the jaws open, and keep closing (one discrete step does one thing: the position
        # waits) unless the tip left the neck or the jaws shut on nothing; then open and try again
        jaw = float(45.0) - jaw_angle[env, 0]
        off_hold = wp.length(g_pos - hold)
        if closing[env] != 0 and (off_hold > 0.006 or jaw_angle[env, 0] < 1.0):
            closing[env] = 0
        elif closing[env] == 0 and off_hold < in_place and jaw_angle[env, 0] > 44.0:
            closing[env] = 1
        if closing[env] != 0:
            jaw = -60.0
        error_out[env, 0] = e[0]
        error_out[env, 1] = e[1]
        error_out[env, 2] = turn
        error_out[env, 3] = e[3]
        error_out[env, 4] = jaw
    else:  # a held grasp keeps its jaw angle (closing further is blocked)
        closing[env] = 0
        if phase == GRASP:  # held, but not the infundibulum on both jaws: let go and try again
            error_out[env, 4] = 45.0 - jaw_angle[env, 0]
        elif phase == LIFT:
            error_out[env, 3] = -retract  # pull the neck back towards the trocar
    # the hook: along its line from the RCM to the target, stand off until the target is exposed, then touch
    c_tip = pose[env, 1]
    c_pos = wp.transform_get_translation(c_tip)
    c_rcm = rcm[env, 1]
    target = task.target[env]
    c_axis = wp.normalize(target - wp.transform_get_translation(c_rcm))
    reach = float(0.5) * p.tolerance
    if phase < TOUCH:
        reach = 0.03
    goal = target - c_axis * (CAUTER_CUTTING_CENTER + reach)
    e = ptsd_error_toward(c_rcm, c_pos, ptsd[env, 1], goal, max_step)
    error_out[env, 5] = e[0]
    error_out[env, 6] = e[1]
    error_out[env, 8] = e[3]
    near = wp.length(cutting_center(c_tip) - target) < 0.8 * p.tolerance
    switch_on = wp.where(phase == TOUCH and near, 1, 0)
    error_out[env, 9] = float(switch_on - active[env, 1])  # switch only when needed (a discrete step does one thing)


# ---------------------------------------------------------------------------- env
class GraspLiftAndTouchEnv(BatchedEnv):
    """LapGym's GraspLiftAndTouchEnv, batched. See the module docstring and ``GraspLiftAndTouchConfig``.

    Actions: 10, the grasper's PTSD and jaw angle, then the hook's PTSD and activation (outside the 0.1 dead zone its
    sign switches the hook), over their maximum speeds. Discrete: ``Discrete(21)``.

    Privileged critic observation (``privileged_critic=True``): the policy values, the hook centre to target and grasp
    centre to infundibulum offsets (over the workspace diagonal; 3 + 3), and the target's visibility (1).
    """

    config_class = GraspLiftAndTouchConfig
    task_name = "GraspLiftAndTouch"
    rewards = REWARDS
    supported_observations = ("STATE", "RGB", "RGBD", "DEPTH")
    expert = "lapwarp.tasks.deformable_manipulation.grasp_lift_touch:GraspLiftAndTouchExpert"
    cfg: GraspLiftAndTouchConfig

    def _build(self) -> World:
        cfg, n, dev = self.cfg, self.num_envs, self.wp_device
        builder = SceneBuilder(gravity=(0.0, cfg.gravity, 0.0))
        lv, lt = liver_mesh()
        gb = gallbladder_mesh()
        self.gb_rest = gb
        self._rest_vertices = {"liver": lv, "gallbladder": gb["vertices"]}
        liver = DeformableObject.tet_mesh(builder, lv, lt, density=cfg.liver_mass / tet_volume(lv, lt),
                                          youngs_modulus=cfg.liver_youngs_modulus, poisson_ratio=cfg.poisson_ratio,
                                          damping=cfg.damping, name="liver")
        gall = DeformableObject.tet_mesh(builder, gb["vertices"], gb["tets"],
                                         density=cfg.gallbladder_mass / tet_volume(gb["vertices"], gb["tets"]),
                                         youngs_modulus=cfg.gallbladder_youngs_modulus,
                                         poisson_ratio=cfg.poisson_ratio, damping=cfg.damping, name="gallbladder")
        self.liver, self.gallbladder = liver.obj, gall.obj
        liver.anchor(np.nonzero(lv[:, 2] > liver_center()[2] * MM)[0], cfg.anchor_stiffness)
        gall.anchor(gb["bed"], cfg.anchor_stiffness)
        jaw = dict(jaw_speed_deg=cfg.jaw_speed, jaw_discrete_speed_deg=cfg.jaw_discrete_speed,
                   jaw_start_deg=cfg.gripper_jaw_start, jaw_noise_deg=cfg.jaw_noise)
        self.rig = InstrumentRig([InstrumentSpec(name="gripper", tpsd=cfg.tpsd("gripper"), shape="grasper", **jaw),
                                  InstrumentSpec(name="cauter", tpsd=cfg.tpsd("cauter"), shape="cauter",
                                                 activation=True)], builder)
        slot_start = liver.num_anchors + gall.num_anchors
        world = builder.finalize(num_envs=n, device=str(dev), substeps=cfg.physics_substeps, seed=cfg.seed,
                                 attachment_capacity=slot_start + cfg.grasp_slots)
        world.tet_method = "xpbd"  # organs held by springs, not pinned: the per-vertex solve would not move them
        liver.finalize(world)
        gall.finalize(world)
        self.rig.finalize(world)
        self.contact = c = ContactSystem(world, capacity=cfg.contact_capacity, body_ignore_mask=True)
        # every gallbladder node meets the instruments (a squeezed neck's inner nodes reach the jaws: a firmer grasp),
        # its surface vertices meet the liver, and the liver's surface vertices meet the instruments
        self.gb_group = c.add_particle_group(self.gallbladder, radius=PARTICLE_RADIUS, triangles=True)
        gb_surface = c.add_particle_group(np.unique(self.gallbladder.surface_tris), radius=PARTICLE_RADIUS,
                                          name="gallbladder_surface")
        self.liver_group = c.add_particle_group(np.unique(self.liver.surface_tris), radius=PARTICLE_RADIUS,
                                                name="liver", triangles=self.liver.surface_tris)
        c.add_surface(self.liver, groups=[gb_surface], name="liver_surface")
        self.rig.add_colliders(c, groups=[self.gb_group, self.liver_group])
        c.finalize()
        self.grasp = self.rig.add_grasping("gripper", c, groups=[self.gb_group], grasp_threshold=cfg.grasp_threshold,
                                           release_threshold=cfg.grasp_threshold, slot_start=slot_start,
                                           slots=cfg.grasp_slots, max_offset=0.02, cone_margin=0.005,
                                           jaws_pass_while_grasped=True)
        self._rig_contacts = self.rig.contacts()

        # organs: infundibulum flags, masses, surfaces, the liver's rest surface (a static mesh)
        gfirst, gcount = self.gallbladder.particle_start, self.gallbladder.particle_count
        infundibulum = (gb["s"] >= INFUNDIBULUM_FROM - 1e-9).astype(np.int32)
        self.organs = o = Organs()
        o.infundibulum = wp.array(infundibulum, dtype=wp.int32, device=dev)
        o.infundibulum_nodes = wp.array(np.nonzero(infundibulum)[0].astype(np.int32) + gfirst, dtype=wp.int32,
                                        device=dev)
        inv_mass = world.model.particle_inv_mass.numpy()[0, gfirst:gfirst + gcount]
        o.mass = wp.array(np.where(inv_mass > 0, 1.0 / np.maximum(inv_mass, 1e-30), 0.0).astype(np.float32),
                          dtype=float, device=dev)
        o.gb_tris = wp.array(self.gallbladder.surface_tris.astype(np.int32), dtype=wp.vec3i, device=dev)
        o.liver_tris = wp.array(self.liver.surface_tris.astype(np.int32), dtype=wp.vec3i, device=dev)
        lfirst = self.liver.particle_start
        self._liver_rest = wp.Mesh(points=wp.array(lv.astype(np.float32), dtype=wp.vec3, device=dev),
                                   indices=wp.array((self.liver.surface_tris - lfirst).astype(np.int32).reshape(-1),
                                                    dtype=wp.int32, device=dev))
        o.liver_rest = self._liver_rest.id
        self._neck_tip = wp.array(gb["neck_end"].astype(np.int32) + gfirst, dtype=wp.int32, device=dev)
        self._across = wp.vec3(*np.cross(gb["normal"], gb["axis"]))
        self._targets = wp.array(np.asarray(TARGETS, np.float32), dtype=wp.vec3, device=dev)

        self.task = t = Task()
        for name, dtype in (("phase", wp.int32), ("target_index", wp.int32), ("target", wp.vec3),
                            ("overlap_count", wp.int32), ("overlap_at_reset", float), ("was_grasped", wp.int32),
                            ("last_cauter_distance", float), ("last_infundibulum_distance", float),
                            ("last_springs", float), ("last_trocar_distance", float), ("last_overlap", float),
                            ("last_activation", float)):
            setattr(t, name, wp.zeros(n, dtype=dtype, device=dev))
        surface = np.unique(self.gallbladder.surface_tris) - gfirst
        tracking = tracking_vertices(surface, gb["vertices"], n, _TRACK, numpy_rng(cfg.seed))
        t.tracking = wp.array(tracking, dtype=wp.int32, device=dev)
        t.ray_clear = wp.zeros((n, NUM_RAYS), dtype=wp.int32, device=dev)
        t.last_velocity = wp.zeros((n, gcount), dtype=wp.vec3, device=dev)
        self.params = p = Params()
        p.bounds = self.rig.bounds(*WORKSPACE)
        p.gb_first, p.gb_count, p.liver_first = gfirst, gcount, lfirst
        p.inv_node_count = 1.0 / gcount
        p.slot_start, p.slots = slot_start, cfg.grasp_slots
        shape = self.rig.shapes[0]
        p.jaw_a, p.jaw_b = shape.jaw_a, shape.jaw_b
        p.tool_distance, p.tolerance = cfg.tool_collision_distance, cfg.goal_tolerance
        p.must_activate, p.max_overlap = int(cfg.cauter_has_to_activate_in_target), cfg.max_gallbladder_liver_overlap
        p.force_scale, p.lose_ends = cfg.gallbladder_force_scaling_factor, int(cfg.losing_grasp_ends_episode)
        p.start_phase, p.end_phase = PHASES[cfg.start_in_phase], PHASES[cfg.end_in_phase]
        p.control_dt = cfg.time_step * cfg.frame_skip
        p.jaw_low, p.jaw_high = shape.angle_limits
        p.camera = wp.vec3(*CAMERA_POSITION)
        # sofa_env settles the scene after every reset; it is the same scene every time, so it settles once here
        self.rig.reset(wp.ones(n, dtype=wp.int32, device=dev), None)
        for _ in range(10):
            world.step(cfg.time_step)
        world.save_start_state()
        self._start_rig = self._start_grasp = None
        if p.start_phase > GRASP:
            self.world = world  # the base sets it after the build; the script's feature evaluation reads it
            self._prepare_grasped_starts(world)
        return world

    def _prepare_grasped_starts(self, world: World) -> None:
        """The scripted grasp (and lift) of the LIFT / TOUCH starts, once per env (see the module docstring): the
        expert's commands from each env's noisy instrument start until the infundibulum is held on both jaws (for
        TOUCH: then retracting until all three targets are visible); an env that does not get there within
        ``grasped_start_steps`` starts over (three tries). Host loop at build time."""
        cfg, n, dev, t = self.cfg, self.num_envs, self.wp_device, self.task
        rng = world.rng
        everything = wp.ones(n, dtype=wp.int32, device=dev)
        self.rig.reset(everything, rng)
        self.grasp.reset(everything)
        error = wp.zeros((n, 10), dtype=float, device=dev)
        closing = wp.zeros(n, dtype=wp.int32, device=dev)
        scale = self.rig.action_scale(cfg.time_step * cfg.frame_skip)
        actions = wp.zeros((n, 10), dtype=wp.float32, device=dev)
        done = np.zeros(n, dtype=bool)
        scratch = wp.zeros((n, REWARDS.size), dtype=wp.float32, device=dev)  # the base allocates features later
        for _ in range(3):
            t.phase.assign(np.full(n, GRASP, np.int32))
            for _ in range(cfg.grasped_start_steps):
                launching.launch(expert_commands, dim=n,
                                 inputs=[world.state.particle_q, self.rig.ptsd, self.rig.pose, self.rig.rcm,
                                         self.rig.jaw_angle, self.rig.active, self.grasp.grasped, self.organs,
                                         self._neck_tip, self._across, self.params, t, 0.012, 0.015, 0.0025, 0.0025,
                                         0.0015, 0], outputs=[closing, error], device=dev)
                a = np.clip(error.numpy() / scale, -1.0, 1.0)
                a[done] = 0.0
                a[:, 9] = 0.0  # the hook stays off
                actions.assign(a.astype(np.float32))
                self.rig.apply_actions(actions, cfg.time_step)
                for _ in range(cfg.frame_skip):
                    self.rig.step()
                    world.step(cfg.time_step)
                self._features(everything, 0, scratch)  # mode 0: features only, no history
                grasped = scratch.numpy()[:, F.GALLBLADDER_IS_GRASPED] > 0.0
                phase = np.where(grasped, LIFT, GRASP).astype(np.int32)
                if self.params.start_phase == LIFT:
                    done |= grasped
                else:
                    seen = np.ones(n, dtype=bool)
                    for target in TARGETS:
                        t.target.fill_(wp.vec3(*target))
                        launching.launch(cast_target_rays, dim=(n, NUM_RAYS),
                                         inputs=[world.state.particle_q, self.organs, self.params, t], device=dev)
                        seen &= t.ray_clear.numpy().any(axis=1)
                    done |= grasped & seen
                t.phase.assign(phase)
                if done.all():
                    break
            if done.all():
                break
            retry = wp.array((~done).astype(np.int32), dtype=wp.int32, device=dev)
            world.reset(retry)
            self.rig.reset(retry, rng)
        if not done.all():
            raise RuntimeError(f"the scripted grasp of start_in_phase={cfg.start_in_phase!r} failed in "
                               f"{int((~done).sum())} of {n} envs; raise grasped_start_steps")
        world.save_start_state()
        self._start_rig = self.rig.snapshot()
        self._start_grasp = self.grasp.snapshot()

    # ------------------------------------------------------------------ BatchedEnv hooks
    def _checked_state(self) -> list[wp.array]:
        return [*super()._checked_state(), self.task.target]

    def _observation_layout(self) -> ObservationLayout:
        return OBS.layout(gripper_pose=(7, -1.0, 1.0), cauter_pose=(7, -1.0, 1.0), gripper_ptsdj=(5, -1.0, 1.0),
                          cauter_ptsda=(5, -1.0, 1.0), grasped=(1, 0.0, 1.0), target=(3, -1.0, 1.0),
                          phase=(1, 0.0, 3.0), tracking=(3 * _TRACK, -2.0, 2.0))

    def _critic_layout(self) -> ObservationLayout:
        return self.obs_layout.extend(CRITIC, cauter_to_target=(3, -2.0, 2.0), grasp_to_infundibulum=(3, -2.0, 2.0),
                                      visible=(1, 0.0, 1.0))

    def _features(self, env_mask: wp.array, mode: int, features_out: wp.array2d) -> None:
        s, rig, n, dev = self.world.state, self.rig, self.num_envs, self.wp_device
        launching.launch(cast_target_rays, dim=(n, NUM_RAYS),
                         inputs=[s.particle_q, self.organs, self.params, self.task], device=dev)
        self.task.overlap_count.zero_()
        launching.launch(count_overlap, dim=(n, self.params.gb_count),
                         inputs=[s.particle_q, self.organs, self.params, self.task], device=dev)
        launching.launch(eval_grasp_lift_touch, dim=n,
                         inputs=[env_mask, mode, s.particle_q, s.particle_qd, rig.pose, rig.rcm, rig.active, rig.flags,
                                 self.grasp.grasped, s.attach_particle, s.attach_body, self._rig_contacts,
                                 self.gb_group, self.liver_group, self.organs, self.params, self.task],
                         outputs=[features_out], device=dev)

    def _compute_features(self, env_mask: wp.array, features_out: wp.array2d) -> None:
        # phase-gated deltas are computed in-task; the base evaluates this once per step
        self._features(env_mask, 1 if features_out is self.features else 0, features_out)

    def _reset_task(self, env_mask: wp.array) -> None:
        w = self.world
        if self._start_rig is None:
            self.rig.reset(env_mask, w.rng)
            self.grasp.reset(env_mask)
        else:  # the env's grasped start (world.reset restored its organs)
            self.rig.restore(env_mask, self._start_rig)
            self.grasp.restore(env_mask, self._start_grasp)
        launching.launch(reset_grasp_lift_touch, dim=self.num_envs,
                         inputs=[env_mask, w.rng, self._targets, self.params, self.task], device=self.wp_device)
        self._features(env_mask, 2, self.features)

    def _compute_observations(self) -> None:
        s, rig = self.world.state, self.rig
        launching.launch(observe_grasp_lift_touch, dim=self.num_envs,
                         inputs=[s.particle_q, rig.ptsd, rig.pose, rig.jaw_angle, rig.active, self.grasp.grasped,
                                 self.organs, self.params, self.task, self.obs_layout.columns,
                                 self.critic_layout.columns, int(self.cfg.privileged_critic)],
                         outputs=[self.obs_frame, self.critic_frame], device=self.wp_device)

    # ------------------------------------------------------------------ visuals
    def _build_visual_scene(self) -> VisualScene:
        """The liver (red), the gallbladder (yellow), the white target sphere, the grasper (blue) and the hook
        (green); sofa_env's camera (vertical FoV 45 degrees, near 100 mm, far 500 mm)."""
        n, dev = self.num_envs, self.wp_device
        q = self.world.state.particle_q
        objects = []
        for k, (obj, color) in enumerate(((self.liver, LIVER_COLOR), (self.gallbladder, GALLBLADDER_COLOR))):
            first, count = obj.particle_start, obj.particle_count
            objects.append(VisualObject(obj.name, "deformable", color, 1 + k, self._rest_vertices[obj.name],
                                        obj.surface_tris - first,
                                        points=q[:, first:first + count]))
        self._target_pose = wp.zeros((n, 1), dtype=wp.transform, device=dev)
        sv, sf = sphere_mesh(TARGET_RADIUS, subdivisions=2)
        objects.append(VisualObject("target", "rigid", (1.0, 1.0, 1.0), 3, sv, sf, self._target_pose))
        objects += self.rig.visual_objects([GRIPPER_COLOR, CAUTER_COLOR], first_segmentation_id=4)
        pose = wp.transform(wp.vec3(*CAMERA_POSITION), wp.normalize(wp.quat(*CAMERA_QUAT)))
        camera = CameraSpec(poses=wp.array([pose] * n, dtype=wp.transform, device=dev), fov_deg=45.0, near=0.1,
                            far=0.5)
        return VisualScene(camera=camera, objects=objects, background=(0.08, 0.05, 0.05))

    def update_visuals(self) -> None:
        if self._visual_scene is None:
            return
        launching.launch(place_target_visual, dim=self.num_envs, inputs=[self.task], outputs=[self._target_pose],
                         device=self.wp_device)

    # ------------------------------------------------------------------ privileged access (experts, tests)
    def privileged_state(self) -> dict[str, torch.Tensor]:
        """Torch views: gallbladder and liver nodes ``(N, n, 3)``, phase, grasp established, target ``(N, 3)``,
        visibility rays ``(N, 5)``, both tips' poses ``(N, 2, 7)``."""
        q = wp.to_torch(self.world.state.particle_q)
        g, lv = self.gallbladder, self.liver
        return dict(gallbladder=q[:, g.particle_start:g.particle_start + g.particle_count],
                    liver=q[:, lv.particle_start:lv.particle_start + lv.particle_count],
                    phase=wp.to_torch(self.task.phase), grasped=wp.to_torch(self.grasp.grasped),
                    target=wp.to_torch(self.task.target), rays=wp.to_torch(self.task.ray_clear),
                    tips=wp.to_torch(self.rig.pose))


# ---------------------------------------------------------------------------- expert
class GraspLiftAndTouchExpert(Expert):
    """Scripted grasper and hook from the privileged state. GRASP: the grasper goes to a stand-off point on the line
    from its RCM through the neck's end, with the jaws open (45 degrees) and turned to open across the neck (parallel
    to the liver), advances until the neck's end lies ``hold_depth`` along the jaws and closes them (the grasp happens
    on contact below 10 degrees). LIFT: it pulls the neck back towards the trocar (depth) until the target is
    visible. The hook meanwhile goes along its line from its RCM towards the target and waits 30 mm short of it; in
    TOUCH it advances to the target and switches on. Moves follow straight lines in legs of ``max_step``."""

    def __init__(self, env: GraspLiftAndTouchEnv, hold_depth: float = 0.012, standoff: float = 0.015,
                 retract: float = 0.0025, max_step: float | None = None):
        super().__init__(env)
        self.hold_depth, self.standoff, self.retract = float(hold_depth), float(standoff), float(retract)
        self.max_step = float(max_step if max_step is not None else (1.0 if env.is_discrete else 0.0025))
        # how close to the hold point the jaws start closing: a discrete step of 1 degree moves the tip ~3 mm at the
        # neck's depth, so discrete actions cannot come closer than that
        self.in_place = 0.0035 if env.is_discrete else 0.0015
        self.error = wp.zeros((env.num_envs, 10), dtype=float, device=env.wp_device)
        self.closing = wp.zeros(env.num_envs, dtype=wp.int32, device=env.wp_device)  # per env: closing the jaws
        self.step_size = self.rig_step_size()

    def __call__(self, obs=None) -> torch.Tensor:
        env, rig, s = self.env, self.env.rig, self.env.world.state
        with env._torch_stream_scope():
            launching.launch(expert_commands, dim=env.num_envs,
                             inputs=[s.particle_q, rig.ptsd, rig.pose, rig.rcm, rig.jaw_angle, rig.active,
                                     env.grasp.grasped, env.organs, env._neck_tip, env._across, env.params, env.task,
                                     self.hold_depth, self.standoff, self.retract, self.max_step, self.in_place,
                                     int(env.is_discrete)], outputs=[self.closing, self.error], device=env.wp_device)
        return self.policy_actions(wp.to_torch(self.error) / self.step_size)
