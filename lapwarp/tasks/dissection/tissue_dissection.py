"""TissueDissectionEnv: free a tissue flap from a board by cutting the connective tissue under it with an electrocautery
hook (sofa_env's TissueDissectionEnv; task-cards §7).

A red tissue flap (60 x 100 x 2 mm, a 6 x 10 x 2 node grid, 270 tets) lies on a board. Its rows 8 - R .. 7 are tied
to a thin layer of blue connective tissue (CT; 6 x R x 2 nodes, 0.1 mm thick, 30 tets for R = 2, 90 for R = 4) whose
bottom is fixed to the board; its rows 0 .. 7 - R are held by springs to the board; a constant retraction force
(0, -100, 100) N on four nodes of the free end (y = 100 mm, x = +-6 mm, both layers) peels the free end back and up,
which exposes the CT. The agent moves a pivotized electrocautery hook (TPSD) and switches it on to cut; the task
succeeds when no CT tet is left. As the CT goes, the flap lifts further.

Physics (SI; sofa_env's millimetre scene converted: lengths x 1e-3, Young's moduli x 1e3, forces x 1e-3; its gravity
981 mm/s^2 along -z is 0.981 m/s^2; its masses are kept, as the task cards advise, although far from physical): both
layers are cuttable co-rotated XPBD tet meshes (``SceneBuilder.add_tet_mesh``): flap E = 0.5 MPa, nu = 0, 100 kg; CT
E = 5 kPa, nu = 0, 0.5 kg; damping: see ``flap_damping_rate`` (the CT: sofa_env's 0.8 kg/s per node); the flap's
board springs (sofa_env's ``RestShapeSpringsForceField``, 1e3 N/m) are anchors; a CT top node and its flap node are
joined by a rigid zero-length distance constraint (sofa_env's ``BilateralLagrangianConstraint``); the retraction
force is an external force (``World.enable_external_forces``); sofa_env's ``PlaneForceField`` under the flap is a
frictionless contact plane at z = 0. The hook's capsules collide with the flap (its nodes and surface triangles).

Cutting (``lapwarp.cutting``): an active hook removes every tet (flap or CT) that comes within 0.8 mm (the hook's
radius) + 0.2 mm (sofa_env's carving distance) of its cutting capsules (the cross bar at the tip and the last 7 mm of
the hook), measured, as sofa_env's CarvingManager does, at its nearest face (``cut_removal="touch"``, the default) or
at its centroid (``"centroid"``, lapwarp's earlier rule; see the config). Labels: 0 = flap, 1 = CT; the counts of both
are per env on the device.

Reward features (Table A, the paper's weights): unstable deformation (a CT node faster than 0.5 m/s in some axis),
distance from the hook's cutting tip to the *border point* (the live CT node of the CT row nearest the free end that
is closest to the tip) and its change, tets of each layer and the tets cut this step, limit violations, collisions of
the hook with the board (how many of 19 points along the hook's cutting end, sofa_env's carving spheres, touch the
board's top at z = -1 mm), success. STATE observation (75; +3 with ``control_retraction_force``): PTSD (4), activation
(1), hook pose (position over the workspace, quaternion xyzw; 7), 10 flap nodes (30), 10 CT nodes (30), the border
point (3), (the retraction force over its limit, 3). Points are normalised by the workspace; missing ones (fewer live
nodes than tracking points, no CT left) read as zeros in their own columns.

Deliberate differences from sofa_env (task-cards §7, §12):

* Every episode starts from the same settled scene, restored from per-env masks and state rows (sofa_env does not
  restore cut topology and sofa_zoo restarts the process per episode).
* The CT rows lie under the flap rows they are tied to (sofa_env pairs them by index although its CT rows are spaced
  10 mm against the flap's 11.1 mm, so its settling shears the 0.1 mm layer by up to 6.7 mm, 67:1).
* The activation is always the fifth action component (sofa_env reads it from the last one with a controllable
  force, a bug); the force action adds ``force_action_scale`` N per physics step (sofa_env's 300 mN), clipped to
  +-``force_limit`` per axis (sofa_env's 1e5 mN).
* Unstable deformation tests the speed of every axis in both directions (sofa_env: the largest signed component).
* The distance feature keeps sofa_env's effective scale (it normalises by the workspace diagonal in the feature and
  again in the reward): ``d / diagonal x (1 mm / diagonal)``, so Table A's -10 weigh what they weighed in the paper.
* Tracking points: farthest-point samples of live nodes from a random start, drawn at reset and again after a step
  that cut that layer (sofa_env's rule; its start point comes from the global unseeded ``np.random``, here from the
  env's RNG stream).
* The remote centre of motion is exact (TPSD kinematics), so sofa_env's RCM-violation features (weight 0) are not
  computed; without ``with_board_collision`` the board feature counts a tip below z = 0 (sofa_env's fallback).
* A CT node whose tets were all cut stays tied to the flap (0.02 kg riding on a 0.8 kg flap node); it no longer falls.
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
from lapwarp.assets.meshes import grid_tets
from lapwarp.builder import SceneBuilder
from lapwarp.config import PTSD, Count, EnvConfig, NonNegative, Positive, PositiveInt, Range
from lapwarp.contact import ContactSystem
from lapwarp.cutting import CuttingSystem, cut_surface
from lapwarp.env import BatchedEnv
from lapwarp.experts import Expert
from lapwarp.instrument_shapes import CAUTER_CUTTING_CENTER
from lapwarp.instruments import TPSDConfig, tpsd_from_config
from lapwarp.kernels.kinematics import point_to_ptsd, ptsd_to_transform
from lapwarp.tasks.rig import (
    CAUTER_TIP,
    PTSD_STEPS,
    STATE_LIMITS_VIOLATED,
    WORKSPACE_VIOLATED,
    InstrumentRig,
    InstrumentSpec,
    RigBounds,
    count_flag,
    cutting_center,
    place_hook_capsules,
    ptsd_accepted,
    ptsd_step,
    ptsd_step_action,
    write_unit_point,
    write_unit_ptsd,
)
from lapwarp.tasks.spec import ActionBlock, ActionLayout, Feature, ObservationLayout, ObservationSpec, RewardSpec
from lapwarp.tasks.targets import draw_index
from lapwarp.visuals import CameraSpec, VisualObject, VisualScene, sphere_mesh
from lapwarp.world import World

wp.set_module_options({"enable_backward": False})

# Table A (the paper's weights = sofa_zoo's; sofa_env's constructor defaults are all 0).
REWARDS = RewardSpec(
    Feature("unstable_deformation", -1.0),
    Feature("distance_cauter_border_point", -10.0),
    Feature("delta_distance_cauter_border_point", -10.0, delta_of="distance_cauter_border_point"),
    Feature("num_tetra_in_connective_tissue", 0.0),
    Feature("cut_connective_tissue", 0.5),
    Feature("num_tetra_in_tissue", 0.0),
    Feature("cut_tissue", -0.1),
    Feature("workspace_violation", 0.0),
    Feature("state_limits_violation", 0.0),
    Feature("collision_with_board", -0.1),
    Feature("successful_task", 50.0),
)
F = REWARDS.F
OBS = ObservationSpec("ptsd", "active", "pose", "flap_points", "ct_points", "border_point", "force")
CRITIC = OBS.extend("tets_left", "offset_to_border")

NX, NY = 6, 10  # flap nodes along x and y (two layers along z)
FLAP_NODES = NX * NY * 2
SIZE_X, SIZE_Y, FLAP_THICKNESS, CT_THICKNESS = 0.06, 0.1, 0.002, 1.0e-4
FLAP, CT = 0, 1  # cutting labels
#: the retraction force's nodes (sofa_env's BoxROI x in [-6, 6] mm, y in [95, 105] mm: x = +-6 mm, y = 100 mm)
FORCE_NODES = (2 + NX * (NY - 1), 3 + NX * (NY - 1), 2 + NX * (NY - 1) + NX * NY, 3 + NX * (NY - 1) + NX * NY)
BOARD_TOP = -1.0e-3  # sofa_env's board collision grid
CONTACT_DISTANCE = 2.0e-4  # sofa_env's LocalMinDistance contact distance
HOOK_RADIUS = 0.8e-3
_FORCE_NODES = wp.constant(wp.vec4i(*FORCE_NODES))
_NX = wp.constant(NX)
FLAP_COLOR, CT_COLOR, BOARD_COLOR, MARKER_COLOR = (0.78, 0.16, 0.14), (0.2, 0.35, 0.9), (0.72, 0.55, 0.36), \
    (0.1, 0.9, 0.2)


@dataclass(kw_only=True)
class TissueDissectionConfig(EnvConfig):
    """TissueDissectionEnv parameters (Table B, Table C: the paper's and sofa_zoo's values); metres, degrees, N, kg.

    Attributes:
        rows_to_cut: rows of connective tissue, R (2 or 4 in the paper; 2 to 7 fit under the flap and leave it
            anchored rows).
        with_board_collision: count the hook's contacts with the board (else: a tip below z = 0 counts one).
        show_border_point: draw the border point (green marker) in images.
        start_ptsd: the hook's start state (deg, deg, deg, m); ``ptsd_noise``: uniform reset noise around it
            (sofa_env's ``randomize_cauter``: +-30 deg, +-10 mm).
        state_low / state_high: the hook's state limits (deg, deg, deg, m).
        maximum_state_velocity: PTSD speed at action 1 (deg/s, deg/s, deg/s, m/s).
        discrete_action_magnitude: PTSD speed of a discrete action (sofa_env has no discrete actions for this task: a
            quarter of the continuous speed, 0.5 deg / 0.5 mm per env step, so a lattice of discrete moves can bring
            the hook within its 1 mm cutting reach of a tet).
        activation_deadzone: the activation component switches the hook on above it and off below its negative.
        control_retraction_force: three more action components change the retraction force (8-D actions, +3
            observations).
        retraction_force: the force on the flap's free end at reset (N, total over its four nodes).
        force_action_scale: force change per physics step at action 1 (N); ``force_limit``: per-axis bound (N).
        num_tracking_points_tissue / num_tracking_points_connective_tissue: tracked flap / CT nodes (10 / 10).
        gravity: m/s^2 along -z (sofa_env's 981 mm/s^2).
        flap_youngs_modulus, ct_youngs_modulus: Pa; flap_mass, ct_mass: kg (sofa_env's, far from physical).
        velocity_damping: sofa_env's ``UniformVelocityDampingForceField`` coefficient, kg/s per node (the CT's damping
            rate: this times its nodes over its mass).
        flap_damping_rate: the flap's velocity damping rate, 1/s. sofa_env damps the flap by 0.8 kg/s per node (~1/s)
            and, far more, by its implicit Euler solver's Rayleigh damping 0.1 M + 0.1 K, whose stiffness term damps
            the flap's flapping modes about critically; lapwarp's XPBD has no stiffness-proportional damping, so a mass
            rate stands in: at 1/s the peeled flap flails for ~2 s after a reset, at 10/s it settles in ~0.6 s (the
            equilibrium does not depend on it).
        anchor_stiffness: springs holding the flap's rows that are not over the CT to the board, N/m.
        carving_distance: m beyond the hook's radius within which an active hook removes tets.
        cut_removal: where a tet's distance to the hook is measured: ``"touch"`` (the default), its nearest face,
            which is sofa_env's (its CarvingManager's proximity query runs against the carved surface, so the hook
            removes what it touches), or ``"centroid"``, its centre (lapwarp's default until PPO compared the two:
            from state at R = 2, 0.0 % evaluation success by centroid against 97.7 % by touch, gpu preset, 300
            iterations, H200, twenty-fifth session). The difference is large for the CT's 12 x 20 x 0.1 mm tets
            (R = 2): by centroid the hook must come within 1 mm of points ~5 mm inside the strip, and the
            observation's border point, a node, is out of cutting reach (CPU, 16 envs: a scripted follower of the
            border point frees the flap in 0 / 16 episodes by centroid, 8 / 16 by touch). The scripted expert,
            by centroid / touch (CPU, 4 envs, seed 3, every episode freed): steps R = 2 112-125 / 67-70 continuous,
            234-280 / 136-149 discrete; R = 4 299-317 / 113-119, 486-549 / 219-246; flap tets it cuts per episode
            (the flap lies on the CT, so touching the CT often touches it too) R = 2 0 / 4-13, 0 / 0-27; R = 4 0-1 /
            18-39, 0-1 / 53-87.
        settle_steps: physics steps the scene settles under the retraction force before every episode (sofa_zoo).
        physics_substeps: XPBD substeps per physics step (of ``time_step``).
        tissue_rotation_update: how the tet sweep updates the flap's and connective tissue's tet rotations
            (``World.tet_rotation_update``): ``sweep`` (extracted once per tet at each sweep's start in one launch over
            every tet, then used as they are) or ``vertex`` (each tet's projection extracts its own inside the
            sweep, whose colours run one after another; earlier versions).
        contact_capacity: contact records kept per env per step (counted when exceeded, never silent).
        max_episode_steps: time limit; ``None`` = max(400, 200 R) (Table C).
    """

    time_step: Positive = 0.01
    frame_skip: Count(1000) = 10
    max_episode_steps: PositiveInt | None = None
    rows_to_cut: Annotated[int, Range(ge=2, le=7)] = 2
    with_board_collision: bool = True
    show_border_point: bool = False
    start_ptsd: PTSD = (0.0, 0.0, 0.0, 0.002)
    ptsd_noise: tuple[NonNegative, NonNegative, NonNegative, NonNegative] = (30.0, 30.0, 30.0, 0.01)
    state_low: PTSD = (-90.0, -90.0, -90.0, 0.0)
    state_high: PTSD = (90.0, 90.0, 90.0, 0.3)
    maximum_state_velocity: tuple[Positive, Positive, Positive, Positive] = (20.0, 20.0, 30.0, 0.02)
    discrete_action_magnitude: tuple[Positive, Positive, Positive, Positive] = (10.0, 10.0, 15.0, 0.01)
    activation_deadzone: Annotated[float, Range(ge=0.0, lt=1.0)] = 0.1
    control_retraction_force: bool = False
    retraction_force: tuple[float, float, float] = (0.0, -100.0, 100.0)
    force_action_scale: Positive = 0.3
    force_limit: Positive = 100.0
    num_tracking_points_tissue: Count(FLAP_NODES) = 10
    num_tracking_points_connective_tissue: Count(FLAP_NODES) = 10
    gravity: NonNegative = 0.981
    flap_youngs_modulus: Positive = 5.0e5
    flap_mass: Positive = 100.0
    ct_youngs_modulus: Positive = 5.0e3
    ct_mass: Positive = 0.5
    velocity_damping: NonNegative = 0.8
    flap_damping_rate: NonNegative = 10.0
    anchor_stiffness: Positive = 1.0e3
    carving_distance: NonNegative = 2.0e-4
    cut_removal: Literal["touch", "centroid"] = "touch"
    settle_steps: Annotated[int, Range(ge=0, le=10_000)] = 10
    physics_substeps: Count(10_000) = 4
    tissue_rotation_update: Literal["vertex", "sweep"] = "sweep"
    contact_capacity: Count(4096) = 64

    def validate(self, reward_features, supported_observations) -> None:
        super().validate(reward_features, supported_observations)
        if self.max_episode_steps is None:
            self.max_episode_steps = max(400, 200 * self.rows_to_cut)  # Table C
        if any(abs(f) > self.force_limit for f in self.retraction_force):
            raise ValueError(f"retraction_force={self.retraction_force} exceeds force_limit={self.force_limit}")
        self.cauter_tpsd()  # names the fields of a start state outside the limits

    @property
    def workspace(self) -> tuple[np.ndarray, np.ndarray]:
        """The hook's Cartesian workspace (m; sofa_env's [-48, 0, -10] .. [48, 110, 80] mm)."""
        return np.array([-0.048, 0.0, -0.01]), np.array([0.048, 0.11, 0.08])

    def cauter_tpsd(self) -> TPSDConfig:
        """The hook's TPSD: sofa_env's RCM at (-20, 110, 30) mm, XYZ Euler (135, 0, 0) degrees."""
        low, high = self.workspace
        return tpsd_from_config(self, rcm_position=(-0.02, 0.11, 0.03), rcm_euler_deg=(135.0, 0.0, 0.0),
                                start_ptsd="start_ptsd", state_low="state_low", state_high="state_high",
                                workspace_low=tuple(low), workspace_high=tuple(high),
                                max_velocity="maximum_state_velocity",
                                discrete_magnitude="discrete_action_magnitude", ptsd_noise="ptsd_noise")


def flap_mesh() -> tuple[np.ndarray, np.ndarray]:
    """The flap's nodes (sofa_env's order: ``ix + 6 iy + 60 iz``) and 270 tets, m."""
    return grid_tets((NX, NY, 2), (-0.5 * SIZE_X, 0.0, CT_THICKNESS), (0.5 * SIZE_X, SIZE_Y,
                                                                       CT_THICKNESS + FLAP_THICKNESS))


def ct_mesh(rows: int) -> tuple[np.ndarray, np.ndarray]:
    """The CT's nodes (``ix + 6 r + 6 R iz``; iz = 0 on the board, 1 under the flap) under flap rows 8 - R .. 7."""
    pitch = SIZE_Y / (NY - 1)
    return grid_tets((NX, rows, 2), (-0.5 * SIZE_X, (8 - rows) * pitch, 0.0), (0.5 * SIZE_X, 7 * pitch, CT_THICKNESS))


# ---------------------------------------------------------------------------- kernels
@wp.struct
class Tissue:
    """Per-env task state: tracked flap / CT nodes (local indices, -1 = none), the tet counts after the last step, the
    retraction force (N) and the last border point (for the marker)."""

    flap_track: wp.array2d(dtype=wp.int32)
    ct_track: wp.array2d(dtype=wp.int32)
    flap_prev: wp.array(dtype=wp.int32)
    ct_prev: wp.array(dtype=wp.int32)
    force: wp.array(dtype=wp.vec3)
    border: wp.array(dtype=wp.vec3)


@wp.struct
class Params:
    """Constants of a configuration (SI units)."""

    bounds: RigBounds
    distance_scale: float  # sofa_env's effective distance factor: 1 / diagonal x 1 mm / diagonal
    flap_first: int
    ct_first: int
    ct_nodes: int
    ct_row_nodes: int  # CT nodes per layer (6 R)
    flap_tets: int
    ct_tets: int
    force0: wp.vec3
    force_step: float
    force_limit: float
    controlled: int
    force_column: int
    with_board: int
    unstable_speed: float


@wp.func
def ct_row(p: Params, k: int) -> int:
    """Row of CT node ``k`` (local), 0 = farthest from the free end."""
    return (k % p.ct_row_nodes) // _NX


@wp.func
def border_point(q: wp.array2d(dtype=wp.vec3), live: wp.array2d(dtype=wp.int32), env: int, x: wp.vec3, p: Params):
    """sofa_env's border point: among the live CT nodes of the row nearest the free end, the one closest to ``x``.
    Returns the point and 1, or a zero vector and 0 when no CT node is live."""
    top = int(-1)
    for k in range(p.ct_nodes):
        if live[env, p.ct_first + k] != 0:
            top = wp.max(top, ct_row(p, k))
    best = wp.vec3(0.0)
    best_d = float(1.0e9)
    for k in range(p.ct_nodes):
        if live[env, p.ct_first + k] != 0 and ct_row(p, k) == top:
            y = q[env, p.ct_first + k]
            if wp.length(y - x) < best_d:
                best_d = wp.length(y - x)
                best = y
    return best, wp.where(top >= 0, 1, 0)


@wp.func
def board_contacts(tf: wp.transform, with_board: int) -> int:
    """How many of 19 points along the hook's cutting end (4 on the cross bar, 15 back along the hook: sofa_env's
    carving spheres, radius 0.8 mm) touch the board's top within the contact distance, over the board; without the
    board's collision model: 1 if the tip is below z = 0 (sofa_env's fallback)."""
    if with_board == 0:
        return wp.where(wp.transform_point(tf, CAUTER_TIP)[2] < 0.0, 1, 0)
    count = int(0)
    for i in range(19):
        local = wp.vec3(0.0, -1.5e-3 + float(i) * (3.1e-3 / 3.0), CAUTER_CUTTING_CENTER)
        if i >= 4:
            local = wp.vec3(0.0, 0.0, 7.4e-3 + float(i - 4) * 0.5e-3)
        x = wp.transform_point(tf, local)
        over = wp.abs(x[0]) <= 0.5 * SIZE_X and x[1] >= 0.0 and x[1] <= SIZE_Y
        if over and x[2] - HOOK_RADIUS < BOARD_TOP + CONTACT_DISTANCE:
            count += 1
    return count


@wp.func
def spread_force(env: int, f: wp.vec3, p: Params, force_out: wp.array2d(dtype=wp.vec3)):
    """The retraction force split evenly over the four free-end nodes (sofa_env's ``totalForce``)."""
    for k in range(4):
        force_out[env, p.flap_first + _FORCE_NODES[k]] = f * 0.25


@wp.func
def apply_retraction(env: int, actions: wp.array2d(dtype=wp.float32), p: Params, tissue: Tissue,
                     force_out: wp.array2d(dtype=wp.vec3)):
    """The agent's force change (with ``control_retraction_force``), then the force spread over the four free-end
    nodes."""
    f = tissue.force[env]
    if p.controlled != 0:
        for i in range(3):
            f[i] = wp.clamp(f[i] + actions[env, p.force_column + i] * p.force_step, -p.force_limit, p.force_limit)
        tissue.force[env] = f
    spread_force(env, f, p, force_out)


@wp.kernel
def retract_and_place_hook(actions: wp.array2d(dtype=wp.float32), p: Params, tissue: Tissue,
                           pose: wp.array2d(dtype=wp.transform), active: wp.array2d(dtype=wp.int32),
                           force_out: wp.array2d(dtype=wp.vec3), tool_a: wp.array2d(dtype=wp.vec3),
                           tool_b: wp.array2d(dtype=wp.vec3), tool_active: wp.array(dtype=wp.int32)):
    """Per physics step: ``apply_retraction`` and the hook's cutting capsules (``rig.place_hook_capsules``)."""
    env = wp.tid()
    apply_retraction(env, actions, p, tissue, force_out)
    place_hook_capsules(env, pose, active, tool_a, tool_b, tool_active)


@wp.kernel
def eval_dissection_features(env_mask: wp.array(dtype=wp.int32), q: wp.array2d(dtype=wp.vec3),
                             qd: wp.array2d(dtype=wp.vec3), live: wp.array2d(dtype=wp.int32),
                             counts: wp.array2d(dtype=wp.int32), pose: wp.array2d(dtype=wp.transform),
                             flags: wp.array2d(dtype=wp.int32), tissue: Tissue, p: Params,
                             features_out: wp.array2d(dtype=float)):
    """Reward features of sofa_env's ``_get_reward_features`` (the delta: the env base)."""
    env = wp.tid()
    if env_mask[env] == 0:
        return
    tf = pose[env, 0]
    border, found = border_point(q, live, env, wp.transform_point(tf, CAUTER_TIP), p)
    d = float(0.0)
    if found != 0:
        d = wp.length(border - wp.transform_point(tf, CAUTER_TIP)) * p.distance_scale
    fast = float(0.0)
    for k in range(p.ct_nodes):
        u = qd[env, p.ct_first + k]
        if live[env, p.ct_first + k] != 0 and wp.max(wp.max(wp.abs(u[0]), wp.abs(u[1])), wp.abs(u[2])) > \
                p.unstable_speed:
            fast = 1.0
    flap = counts[env, FLAP]
    ct = counts[env, CT]
    features_out[env, F.UNSTABLE_DEFORMATION] = fast
    features_out[env, F.DISTANCE_CAUTER_BORDER_POINT] = d
    features_out[env, F.NUM_TETRA_IN_CONNECTIVE_TISSUE] = float(ct)
    features_out[env, F.CUT_CONNECTIVE_TISSUE] = float(wp.max(tissue.ct_prev[env] - ct, 0))
    features_out[env, F.NUM_TETRA_IN_TISSUE] = float(flap)
    features_out[env, F.CUT_TISSUE] = float(wp.max(tissue.flap_prev[env] - flap, 0))
    features_out[env, F.WORKSPACE_VIOLATION] = float(count_flag(flags, env, WORKSPACE_VIOLATED))
    features_out[env, F.STATE_LIMITS_VIOLATION] = float(count_flag(flags, env, STATE_LIMITS_VIOLATED))
    features_out[env, F.COLLISION_WITH_BOARD] = float(board_contacts(tf, p.with_board))
    features_out[env, F.SUCCESSFUL_TASK] = wp.where(ct == 0, 1.0, 0.0)


@wp.func
def farthest_points(q: wp.array2d(dtype=wp.vec3), live: wp.array2d(dtype=wp.int32), rng: wp.array(dtype=wp.uint32),
                    env: int, first: int, count: int, track: wp.array2d(dtype=wp.int32),
                    min_d2: wp.array2d(dtype=float)):
    """Farthest-point sample of ``track.shape[1]`` live nodes among ``first .. first + count`` (current positions)
    from a random live start; -1 for the points there are no live nodes for."""
    candidates = int(0)
    for k in range(count):
        ok = live[env, first + k] != 0
        min_d2[env, k] = wp.where(ok, 1.0e9, -1.0)
        if ok:
            candidates += 1
    m = track.shape[1]
    for j in range(m):
        track[env, j] = -1
    if candidates == 0:
        return
    pick = draw_index(rng, env, candidates)
    current = int(0)
    for k in range(count):
        if min_d2[env, k] > 0.0:
            if pick == 0:
                current = k
            pick -= 1
    for j in range(wp.min(m, candidates)):
        track[env, j] = current
        min_d2[env, current] = -1.0
        x = q[env, first + current]
        best = float(-1.0)
        for k in range(count):
            d = min_d2[env, k]
            if d >= 0.0:
                d = wp.min(d, wp.length_sq(q[env, first + k] - x))
                min_d2[env, k] = d
                if d > best:
                    best = d
                    current = k


@wp.kernel
def update_tissue(env_mask: wp.array(dtype=wp.int32), force: int, q: wp.array2d(dtype=wp.vec3),
                  live: wp.array2d(dtype=wp.int32), counts: wp.array2d(dtype=wp.int32), rng: wp.array(dtype=wp.uint32),
                  p: Params, tissue: Tissue, scratch: wp.array2d(dtype=float)):
    """After a step (or at reset, ``force``): re-sample the tracking points of a layer that lost tets (sofa_env's
    rule), then remember the counts."""
    env = wp.tid()
    if env_mask[env] == 0:
        return
    if force != 0 or counts[env, FLAP] < tissue.flap_prev[env]:
        farthest_points(q, live, rng, env, p.flap_first, FLAP_NODES, tissue.flap_track, scratch)
    if force != 0 or counts[env, CT] < tissue.ct_prev[env]:
        farthest_points(q, live, rng, env, p.ct_first, p.ct_nodes, tissue.ct_track, scratch)
    tissue.flap_prev[env] = counts[env, FLAP]
    tissue.ct_prev[env] = counts[env, CT]


@wp.kernel
def reset_tissue(env_mask: wp.array(dtype=wp.int32), p: Params, tissue: Tissue, force_out: wp.array2d(dtype=wp.vec3)):
    env = wp.tid()
    if env_mask[env] == 0:
        return
    tissue.force[env] = p.force0
    tissue.flap_prev[env] = p.flap_tets
    tissue.ct_prev[env] = p.ct_tets
    spread_force(env, p.force0, p, force_out)


@wp.func
def write_tracked(obs_out: wp.array2d(dtype=float), env: int, col: int, q: wp.array2d(dtype=wp.vec3),
                  live: wp.array2d(dtype=wp.int32), first: int, track: wp.array2d(dtype=wp.int32), p: Params):
    for j in range(track.shape[1]):
        k = track[env, j]
        if k >= 0 and live[env, first + k] != 0:
            write_unit_point(obs_out, env, col + 3 * j, q[env, first + k], p.bounds)
        else:
            for i in range(3):
                obs_out[env, col + 3 * j + i] = 0.0


@wp.kernel
def observe_dissection(q: wp.array2d(dtype=wp.vec3), live: wp.array2d(dtype=wp.int32),
                       counts: wp.array2d(dtype=wp.int32), ptsd: wp.array2d(dtype=wp.vec4),
                       pose: wp.array2d(dtype=wp.transform), active: wp.array2d(dtype=wp.int32), tissue: Tissue,
                       p: Params, o: OBS.Columns, c: CRITIC.Columns, privileged: int, obs_out: wp.array2d(dtype=float),
                       critic_out: wp.array2d(dtype=float)):
    """sofa_env's STATE order: PTSD, activation, pose, flap points, CT points, border point (, force)."""
    env = wp.tid()
    write_unit_ptsd(obs_out, env, o.ptsd, ptsd[env, 0], p.bounds)
    obs_out[env, o.active] = float(active[env, 0])
    tf = pose[env, 0]
    write_unit_point(obs_out, env, o.pose, wp.transform_get_translation(tf), p.bounds)
    rot = wp.transform_get_rotation(tf)
    for i in range(4):
        obs_out[env, o.pose + 3 + i] = rot[i]
    write_tracked(obs_out, env, o.flap_points, q, live, p.flap_first, tissue.flap_track, p)
    write_tracked(obs_out, env, o.ct_points, q, live, p.ct_first, tissue.ct_track, p)
    tip = wp.transform_point(tf, CAUTER_TIP)
    border, found = border_point(q, live, env, tip, p)
    tissue.border[env] = border
    if found != 0:
        write_unit_point(obs_out, env, o.border_point, border, p.bounds)
    else:
        for i in range(3):
            obs_out[env, o.border_point + i] = 0.0
    if p.controlled != 0:
        for i in range(3):
            obs_out[env, o.force + i] = tissue.force[env][i] / p.force_limit
    if privileged == 0:
        return
    critic_out[env, c.tets_left] = float(counts[env, FLAP]) / float(p.flap_tets)
    critic_out[env, c.tets_left + 1] = float(counts[env, CT]) / float(p.ct_tets)
    rel = (border - tip) * p.bounds.inv_diagonal
    if found == 0:
        rel = wp.vec3(0.0)
    for i in range(3):
        critic_out[env, c.offset_to_border + i] = rel[i]


@wp.kernel
def place_marker(tissue: Tissue, out: wp.array2d(dtype=wp.transform)):
    env = wp.tid()
    out[env, 0] = wp.transform(tissue.border[env], wp.quat_identity())


@wp.func
def tet_extreme_node(q: wp.array2d(dtype=wp.vec3), env: int, n: wp.vec4i, axis: int, sign: float) -> wp.vec3:
    """The node of tet ``n`` with the largest ``sign`` x coordinate ``axis`` (the first of equals)."""
    best = q[env, n[0]]
    for i in range(1, 4):
        if sign * q[env, n[i]][axis] > sign * best[axis]:
            best = q[env, n[i]]
    return best


@wp.func
def tet_target(q: wp.array2d(dtype=wp.vec3), env: int, n: wp.vec4i, touch: int, high: float,
               y_min: float) -> wp.vec3:
    """Where the expert takes the hook to cut CT tet ``n``: its centroid; with the touch rule, a tet whose centroid
    the peeled flap has lifted more than ``high`` above the board (its top nodes ride on the flap, its bottom one
    stays fixed) at its lowest node, which the hook reaches (the centroid may leave the workspace). (Aiming at the
    tet's point nearest the hook instead cut two to three times the flap tets: CPU, seed 3, 4 envs.) With the touch
    rule a target below ``y_min`` (the hook's workspace ends at y = 0, and at R = 7 the flap folded back towards -y
    carries CT nodes to y = -46 mm, taking tets' centroids with them) moves along the segment from the tet's node of
    largest y (on the board) towards it, to ``y_min``: a point inside the tet that the hook reaches."""
    y = (q[env, n[0]] + q[env, n[1]] + q[env, n[2]] + q[env, n[3]]) * 0.25
    if touch != 0 and y[2] > high:
        y = tet_extreme_node(q, env, n, 2, -1.0)  # the lowest
    if touch != 0 and y[1] < y_min:
        inner = tet_extreme_node(q, env, n, 1, 1.0)  # the one of largest y
        if inner[1] > y_min:
            y = inner + (y - inner) * ((inner[1] - y_min) / (inner[1] - y[1]))
    return y


@wp.func
def approach_errors(env: int, x: wp.vec3, point: wp.vec3, s: wp.vec4, rcm: wp.transform, on: int, switch_on: float,
                    keep_on: float, lift: float, error_out: wp.array2d(dtype=float)):
    """The expert's move of the hook's cutting centre ``x`` onto ``point`` as a PTSD error (spin left alone) and its
    activation change: it approaches from ``lift`` above the point and descends as the horizontal distance closes,
    switches on within ``switch_on`` and, once on, stays on within ``keep_on`` (no step lost to switching)."""
    d = wp.length(point - x)
    flat = wp.vec3(point[0] - x[0], point[1] - x[1], 0.0)
    goal = point_to_ptsd(rcm, point + wp.vec3(0.0, 0.0, wp.min(lift, wp.length(flat))), s[2])
    error_out[env, 0] = goal[0] - s[0]
    error_out[env, 1] = goal[1] - s[1]
    error_out[env, 2] = 0.0
    error_out[env, 3] = goal[3] - CAUTER_CUTTING_CENTER - s[3]
    want = wp.where(d < switch_on or (on != 0 and d < keep_on), 1, 0)
    error_out[env, 4] = float(want - on)


@wp.kernel
def expert_errors(q: wp.array2d(dtype=wp.vec3), tet_active: wp.array2d(dtype=wp.int32),
                  ct_tets: wp.array(dtype=wp.vec4i), rest_y: wp.array(dtype=float), ct_tet0: int,
                  ptsd: wp.array2d(dtype=wp.vec4), pose: wp.array2d(dtype=wp.transform),
                  rcm: wp.array2d(dtype=wp.transform), active: wp.array2d(dtype=wp.int32), band: float,
                  switch_on: float, keep_on: float, lift: float, touch: int, high: float, y_min: float,
                  error_out: wp.array2d(dtype=float)):
    """PTSD error of the hook's cutting centre towards the next CT tet and the activation the expert wants (see
    ``TissueDissectionExpert``)."""
    env = wp.tid()
    x = cutting_center(pose[env, 0])
    # the band is chosen by rest positions (a fixed order, free end first), so tets that the moving flap carries
    # about do not make the choice flip from step to step; within it the nearest tet (current positions) is next
    top = float(-1.0e9)
    for t in range(ct_tets.shape[0]):
        if tet_active[env, ct_tet0 + t] != 0:
            top = wp.max(top, rest_y[t])
    best = wp.vec3(0.0)
    best_d = float(1.0e9)
    for t in range(ct_tets.shape[0]):
        if tet_active[env, ct_tet0 + t] != 0 and rest_y[t] >= top - band:
            y = tet_target(q, env, ct_tets[t], touch, high, y_min)
            if wp.length(y - x) < best_d:
                best_d = wp.length(y - x)
                best = y
    if best_d > 1.0e8:  # nothing left to cut
        for i in range(5):
            error_out[env, i] = 0.0
        return
    approach_errors(env, x, best, ptsd[env, 0], rcm[env, 0], active[env, 0], switch_on, keep_on, lift, error_out)


@wp.func
def segment_distance(y: wp.vec3, a: wp.vec3, b: wp.vec3) -> float:
    """Distance from ``y`` to the segment ``a`` - ``b``."""
    ab = b - a
    t = wp.clamp(wp.dot(y - a, ab) / wp.max(wp.dot(ab, ab), 1.0e-18), 0.0, 1.0)
    return wp.length(y - (a + ab * t))


@wp.func
def hook_reach(tf: wp.transform, y: wp.vec3) -> float:
    """Distance from ``y`` to the axes of the hook's cutting capsules at tip pose ``tf`` (``place_hook_capsules``: the
    cross bar and the last 7 mm of the hook); an active hook removes a tet that comes within ~1 mm of them
    (its nearest face, or its centroid with ``cut_removal="centroid"``)."""
    bar = segment_distance(y, wp.transform_point(tf, wp.vec3(0.0, -1.5e-3, CAUTER_CUTTING_CENTER)),
                           wp.transform_point(tf, wp.vec3(0.0, 1.6e-3, CAUTER_CUTTING_CENTER)))
    shaft = segment_distance(y, wp.transform_point(tf, wp.vec3(0.0, 0.0, 7.4e-3)),
                             wp.transform_point(tf, wp.vec3(0.0, 0.0, CAUTER_CUTTING_CENTER)))
    return wp.min(bar, shaft)


@wp.func
def steps_to(rcm: wp.transform, s: wp.vec4, y: wp.vec3, step: wp.vec4) -> float:
    """Discrete steps (pan, tilt, depth; one component a step) from PTSD ``s`` to a hook whose cutting capsules
    reach ``y``: the PTSD difference to the cutting centre at ``y``, where a depth up to 6 mm beyond it costs nothing
    (the last 7 mm of the hook cut too)."""
    g = point_to_ptsd(rcm, y, s[2])
    depth = g[3] - CAUTER_CUTTING_CENTER - s[3]
    beyond = wp.max(-depth - 6.0e-3, 0.0)
    return wp.abs(g[0] - s[0]) / step[0] + wp.abs(g[1] - s[1]) / step[1] + (wp.max(depth, 0.0) + beyond) / step[3]


@wp.kernel
def expert_discrete(q: wp.array2d(dtype=wp.vec3), tet_active: wp.array2d(dtype=wp.int32),
                    ct_tets: wp.array(dtype=wp.vec4i), rest_x: wp.array(dtype=float), ct_top: wp.array(dtype=float),
                    ct_tet0: int, ptsd: wp.array2d(dtype=wp.vec4), pose: wp.array2d(dtype=wp.transform),
                    rcm: wp.array2d(dtype=wp.transform), active: wp.array2d(dtype=wp.int32), switch_on: float,
                    keep_on: float, reach: float, margin: float, sweep: float, lifted: float, step: wp.vec4,
                    b: RigBounds, noop: int, touch: int, high: float, y_min: float,
                    target_out: wp.array(dtype=wp.vec3), action_out: wp.array(dtype=wp.int32)):
    """The discrete action of ``TissueDissectionExpert`` (see there) and the CT tet centroid it goes for."""
    env = wp.tid()
    tf = pose[env, 0]
    s = ptsd[env, 0]
    # the sweep across the CT: from the end (rest x of the live tets) nearer the hook to the other end
    x_lo = float(1.0e9)
    x_hi = float(-1.0e9)
    for t in range(ct_tets.shape[0]):
        if tet_active[env, ct_tet0 + t] != 0:
            x_lo = wp.min(x_lo, rest_x[t])
            x_hi = wp.max(x_hi, rest_x[t])
    hook_x = cutting_center(tf)[0]
    x_end = wp.where(wp.abs(hook_x - x_lo) <= wp.abs(hook_x - x_hi), x_lo, x_hi)
    # the next tet: fewest discrete steps away, counting sweep steps per mm behind the sweep's end, and
    # ``lifted`` steps less per node tied to the flap (those rise with it and are chased far once the CT around
    # them is gone)
    best = wp.vec3(0.0)
    best_d = float(1.0e9)
    best_cost = float(1.0e9)
    for t in range(ct_tets.shape[0]):
        if tet_active[env, ct_tet0 + t] != 0:
            y = tet_target(q, env, ct_tets[t], touch, high, y_min)
            cost = steps_to(rcm[env, 0], s, y, step) + sweep * 1.0e3 * wp.abs(rest_x[t] - x_end) - lifted * ct_top[t]
            if cost < best_cost:
                best_cost = cost
                best_d = hook_reach(tf, y)
                best = y
    target_out[env] = best
    if best_d > 1.0e8:  # nothing left to cut
        action_out[env] = noop
        return
    # switching costs a step: on within ``switch_on`` of the next tet, then on while within ``keep_on``
    on = active[env, 0]
    want = wp.where(best_d < switch_on or (on != 0 and best_d < keep_on), 1, 0)
    if want != on:
        action_out[env] = wp.where(want != 0, 8, 9)  # the activation is the fifth component
        return
    # the pan, tilt or depth step that brings the cutting capsules nearest to the tet (a step must gain ``margin``);
    # short of ``reach`` the hook takes the best step even if it gains nothing (it never rests beside a tet)
    gain = best_d - margin
    move = noop
    forced = noop
    forced_d = float(1.0e9)
    for j in range(PTSD_STEPS):
        u = ptsd_step(s, step, j)
        if ptsd_accepted(rcm[env, 0], u, b):
            d = hook_reach(ptsd_to_transform(rcm[env, 0], u), best)
            if d < gain:
                gain = d
                move = ptsd_step_action(j)
            if d < forced_d:
                forced_d = d
                forced = ptsd_step_action(j)
    if move == noop and best_d > reach:
        move = forced
    action_out[env] = move


# ---------------------------------------------------------------------------- env
class TissueDissectionEnv(BatchedEnv):
    """LapGym's TissueDissectionEnv, batched. See the module docstring and ``TissueDissectionConfig``.

    Actions: 5, the hook's PTSD then its activation (above the dead zone: on; below minus it: off); with
    ``control_retraction_force`` three more, the change of the retraction force. Discrete: ``Discrete(2d + 1)``, each
    the continuous action of its ``discrete_actions`` row.

    Privileged critic observation (``privileged_critic=True``): the policy values, the fraction of flap and CT tets
    left (2) and the offset from the cutting tip to the border point over the workspace diagonal (3).
    """

    config_class = TissueDissectionConfig
    task_name = "TissueDissection"
    rewards = REWARDS
    supported_observations = ("STATE", "RGB", "RGBD", "DEPTH")
    expert = "lapwarp.tasks.dissection.tissue_dissection:TissueDissectionExpert"
    cfg: TissueDissectionConfig

    def _build(self) -> World:
        cfg, n, dev, R = self.cfg, self.num_envs, self.wp_device, self.cfg.rows_to_cut
        builder = SceneBuilder(gravity=(0.0, 0.0, -cfg.gravity))
        fv, ft = flap_mesh()
        cv, ct = ct_mesh(R)
        flap_volume = SIZE_X * SIZE_Y * FLAP_THICKNESS
        ct_volume = SIZE_X * float(np.ptp(cv[:, 1])) * CT_THICKNESS
        self.flap_obj = builder.add_tet_mesh(
            fv, ft, density=cfg.flap_mass / flap_volume, youngs_modulus=cfg.flap_youngs_modulus, poisson_ratio=0.0,
            damping=cfg.flap_damping_rate, cuttable=True, name="flap")
        ct_nodes = len(cv)
        self.ct_obj = builder.add_tet_mesh(
            cv, ct, density=cfg.ct_mass / ct_volume, youngs_modulus=cfg.ct_youngs_modulus, poisson_ratio=0.0,
            damping=cfg.velocity_damping * ct_nodes / cfg.ct_mass, fixed=np.arange(ct_nodes // 2), cuttable=True,
            name="connective_tissue")
        # ties: CT top node of row r <-> flap bottom node of row 8 - R + r (they start at the same point)
        half = ct_nodes // 2
        tied_flap_nodes = [k % NX + NX * (8 - R + k // NX) for k in range(half)]
        for k in range(half):
            builder.add_distance(self.ct_obj.particle_start + half + k,
                                 self.flap_obj.particle_start + tied_flap_nodes[k], compliance=0.0, rest_length=0.0)
        anchored = [ix + NX * iy for iy in range(8 - R) for ix in range(NX)]
        for k in anchored:
            builder.add_attachment(self.flap_obj.particle_start + k, body=-1, compliance=1.0 / cfg.anchor_stiffness)
        self.rig = InstrumentRig([InstrumentSpec(name="cauter", tpsd=cfg.cauter_tpsd(), shape="cauter",
                                                 activation=True, activation_deadzone=cfg.activation_deadzone)],
                                 builder)
        world = builder.finalize(num_envs=n, device=str(dev), substeps=cfg.physics_substeps, seed=cfg.seed)
        world.tet_method = "xpbd"  # the flap's speed and expert rates were measured with XPBD tets (not "auto")
        world.tet_rotation_update = cfg.tissue_rotation_update
        self.rig.finalize(world)
        self._force = world.enable_external_forces()

        self.ct_tets_global = ct.astype(np.int32) + self.ct_obj.particle_start
        self._rest_vertices = {"flap": fv, "connective_tissue": cv}
        self.tissue = t = Tissue()
        t.flap_track = wp.full((n, cfg.num_tracking_points_tissue), -1, dtype=wp.int32, device=dev)
        t.ct_track = wp.full((n, cfg.num_tracking_points_connective_tissue), -1, dtype=wp.int32, device=dev)
        t.flap_prev = wp.full(n, len(ft), dtype=wp.int32, device=dev)
        t.ct_prev = wp.full(n, len(ct), dtype=wp.int32, device=dev)
        t.force = wp.full(n, wp.vec3(*cfg.retraction_force), dtype=wp.vec3, device=dev)
        t.border = wp.zeros(n, dtype=wp.vec3, device=dev)
        self._fps_scratch = wp.zeros((n, FLAP_NODES), dtype=float, device=dev)
        low, high = cfg.workspace
        diagonal = float(np.linalg.norm(high - low))
        self.params = p = Params()
        p.bounds = self.rig.bounds(low, high)
        p.distance_scale = 1.0e-3 / diagonal**2
        p.flap_first, p.ct_first, p.ct_nodes, p.ct_row_nodes = (self.flap_obj.particle_start,
                                                                self.ct_obj.particle_start, ct_nodes, half)
        p.flap_tets, p.ct_tets = len(ft), len(ct)
        p.force0 = wp.vec3(*cfg.retraction_force)
        p.force_step, p.force_limit = cfg.force_action_scale, cfg.force_limit
        p.controlled, p.force_column = int(cfg.control_retraction_force), 5
        p.with_board, p.unstable_speed = int(cfg.with_board_collision), 0.5

        # the scene settles under the retraction force (sofa_zoo's settle steps) before the hook and the contacts
        # exist; every episode starts from this state
        everyone = wp.ones(n, dtype=wp.int32, device=dev)
        launching.launch(reset_tissue, dim=n, inputs=[everyone, p, t], outputs=[self._force], device=dev)
        for _ in range(cfg.settle_steps):
            world.step(cfg.time_step)
        world.save_start_state()

        self.contact = ContactSystem(world, capacity=cfg.contact_capacity)
        flap_group = self.contact.add_particle_group(self.flap_obj, radius=CT_THICKNESS, triangles=True)
        self.contact.add_plane(transform=(0.0, 0.0, 0.0), name="floor", mu_static=0.0, groups=[flap_group])
        self.rig.add_colliders(self.contact, mu_static=0.0, groups=[flap_group])  # sofa_env: friction 0
        self.contact.finalize()
        # each tool's own box for the triangle sweep's cull (the hook's shaft and tip, not one box around both). H200,
        # expert, 4,096 envs, same call: 244.0k -> 261.3k env-steps/s (forty-first session)
        self.contact.triangle_sweep = "shape_codes"
        # the contact's shape and tool-axis pose kernel (launched from here on; one warp per env) at 64 registers
        # instead of 72: one wave of 4,096 envs instead of 1.11 (sm_90; a 32 B spill frame). H200, expert, 4,096 envs,
        # same call as the uncapped step: 243.9k -> 245.8k env-steps/s (benchmarks/RESULTS.md, thirty-sixth session;
        # the CPU ignores the cap); its triangle sweep over the outcodes at 64 too: 247.1k -> 247.7k (thirty-seventh
        # session, same call; +0.2 % alone in the thirty-sixth)
        world.default_register_caps.update(pose_shapes_and_tools=64, collide_triangle_outcodes=64)
        self.cutting = CuttingSystem(world, carving_distance=cfg.carving_distance, num_tools=2, num_labels=2,
                                     tool_radius=HOOK_RADIUS, removal=cfg.cut_removal)
        flap_id = self.cutting.add_object(self.flap_obj, labels=np.full(len(ft), FLAP))
        ct_id = self.cutting.add_object(self.ct_obj, labels=np.full(len(ct), CT))
        # the ties join the pieces: a CT tet at a tied node and a flap tet at its partner count as connected
        links_ct = [int(np.nonzero((ct == half + k).any(axis=1))[0][0]) for k in range(half)]
        links_flap = [int(np.nonzero((ft == tied_flap_nodes[k]).any(axis=1))[0][0]) for k in range(half)]
        self.cutting.add_links(ct_id, links_ct, flap_id, links_flap)
        self.cutting.finalize()
        return world

    def _checked_state(self) -> list[wp.array]:
        return [*super()._checked_state(), self.tissue.force]

    def _action_layout(self) -> ActionLayout:
        blocks = list(self.rig.action_layout.blocks)
        if self.cfg.control_retraction_force:
            blocks.append(ActionBlock("retraction_force", 3, (1.0, 1.0, 1.0)))
        return ActionLayout(blocks)

    def _observation_layout(self) -> ObservationLayout:
        # PTSD within the limits and the tip within the workspace: [-1, 1]; tissue points leave the workspace box: the
        # retraction force stretches the flap's free end up to ~5x near its four nodes, and once the CT is cut the
        # part beyond the anchored rows (45 mm at R = 2) can reach ~200 mm from them: [-5, 5]
        cfg = self.cfg
        return OBS.layout(ptsd=(4, -1.0, 1.0), active=(1, 0.0, 1.0), pose=(7, -1.0, 1.0),
                          flap_points=(3 * cfg.num_tracking_points_tissue, -5.0, 5.0),
                          ct_points=(3 * cfg.num_tracking_points_connective_tissue, -5.0, 5.0),
                          border_point=(3, -5.0, 5.0), force=(3 * int(cfg.control_retraction_force), -1.0, 1.0))

    def _critic_layout(self) -> ObservationLayout:
        return self.obs_layout.extend(CRITIC, tets_left=(2, 0.0, 1.0), offset_to_border=(3, -5.0, 5.0))

    def _before_physics_step(self) -> None:
        super()._before_physics_step()  # move the hook
        cut, dev, n = self.cutting, self.wp_device, self.num_envs
        # the retraction force and the hook's cutting capsules in one launch per physics step (were two)
        launching.launch(retract_and_place_hook, dim=n, inputs=[self.actions, self.params, self.tissue, self.rig.pose,
                                                                self.rig.active],
                         outputs=[self._force, cut.tool_a, cut.tool_b, cut.tool_active], device=dev)
        cut.cut()

    def _compute_features(self, env_mask: wp.array, features_out: wp.array2d) -> None:
        s = self.world.state
        launching.launch(eval_dissection_features, dim=self.num_envs,
                         inputs=[env_mask, s.particle_q, s.particle_qd, s.particle_active, self.cutting.active_count,
                                 self.rig.pose, self.rig.flags, self.tissue, self.params], outputs=[features_out],
                         device=self.wp_device)

    def _update_task(self) -> None:
        s = self.world.state
        launching.launch(update_tissue, dim=self.num_envs,
                         inputs=[self._all_envs, 0, s.particle_q, s.particle_active, self.cutting.active_count,
                                 self.world.rng, self.params], outputs=[self.tissue, self._fps_scratch],
                         device=self.wp_device)

    def _reset_task(self, env_mask: wp.array) -> None:
        w, dev, n = self.world, self.wp_device, self.num_envs
        launching.launch(reset_tissue, dim=n, inputs=[env_mask, self.params, self.tissue], outputs=[self._force],
                         device=dev)
        self.rig.reset(env_mask, w.rng)
        self.cutting.refresh()  # the reset restored the masks; recount surfaces and pieces of the reset envs
        launching.launch(update_tissue, dim=n,
                         inputs=[env_mask, 1, w.state.particle_q, w.state.particle_active, self.cutting.active_count,
                                 w.rng, self.params], outputs=[self.tissue, self._fps_scratch], device=dev)

    def _compute_observations(self) -> None:
        s = self.world.state
        launching.launch(observe_dissection, dim=self.num_envs,
                         inputs=[s.particle_q, s.particle_active, self.cutting.active_count, self.rig.ptsd,
                                 self.rig.pose, self.rig.active, self.tissue, self.params, self.obs_layout.columns,
                                 self.critic_layout.columns, int(self.cfg.privileged_critic)],
                         outputs=[self.obs_frame, self.critic_frame], device=self.wp_device)

    # ------------------------------------------------------------------ visuals
    def _build_visual_scene(self) -> VisualScene:
        """The flap (red) and the CT (blue), cut tets leaving holes, the board (wood, 60 x 100 x 4 mm under z = 0),
        the hook and, with ``show_border_point``, a green marker on the border point. Camera per sofa_env: at (60,
        127, 34) mm with its orientation, vertical FoV 62 degrees, near 1 mm, far 250 mm."""
        n, dev, q = self.num_envs, self.wp_device, self.world.state.particle_q
        objects = []
        for obj, name, color, seg in ((self.flap_obj, "flap", FLAP_COLOR, 1),
                                      (self.ct_obj, "connective_tissue", CT_COLOR, 2)):
            faces, mask = cut_surface(self.world, obj)
            objects.append(VisualObject(name, "deformable", color, seg, self._rest_vertices[name], faces,
                                        points=q[:, obj.particle_start:obj.particle_start + obj.particle_count],
                                        face_active=mask))
        board = trimesh.creation.box(extents=(SIZE_X, SIZE_Y, 0.004))
        board.apply_translation((0.0, 0.5 * SIZE_Y, -0.002))
        static = wp.full((n, 1), wp.transform_identity(), dtype=wp.transform, device=dev)
        objects.append(VisualObject("board", "rigid", BOARD_COLOR, 3, board.vertices, board.faces, static))
        objects += self.rig.visual_objects([(0.72, 0.74, 0.78)], first_segmentation_id=4)
        self._marker_pose = wp.full((n, 1), wp.transform_identity(), dtype=wp.transform, device=dev)
        mv, mf = sphere_mesh(1.5e-3, subdivisions=2)
        objects.append(VisualObject("border_point", "rigid", MARKER_COLOR, 5 + len(objects), mv, mf,
                                    self._marker_pose, visible=bool(self.cfg.show_border_point)))
        pose = wp.transform(wp.vec3(0.06, 0.127, 0.034), wp.quat(0.2239, 0.5439, 0.7563, 0.2865))
        camera = CameraSpec(poses=wp.array([pose] * n, dtype=wp.transform, device=dev), fov_deg=62.0, near=0.001,
                            far=0.25)
        return VisualScene(camera=camera, objects=objects, background=(0.05, 0.05, 0.08))

    def update_visuals(self) -> None:
        if self._visual_scene is None:
            return
        launching.launch(place_marker, dim=self.num_envs, inputs=[self.tissue], outputs=[self._marker_pose],
                         device=self.wp_device)

    # ------------------------------------------------------------------ privileged access (experts, tests)
    def privileged_state(self) -> dict[str, torch.Tensor]:
        """Zero-copy torch views: node positions ``(N, n, 3)``, tet masks ``(N, T)`` (flap tets first, then CT), the
        tet counts ``(N, 2)`` (flap, CT), the retraction force ``(N, 3)``, tracked flap / CT nodes and the last
        border point ``(N, 3)``."""
        t, s = self.tissue, self.world.state
        views = dict(positions=s.particle_q, tet_active=s.tet_active, tet_counts=self.cutting.active_count,
                     force=t.force, flap_track=t.flap_track, ct_track=t.ct_track, border=t.border)
        return {k: wp.to_torch(v) for k, v in views.items()}


# ---------------------------------------------------------------------------- expert
class TissueDissectionExpert(Expert):
    """Cuts the CT from the free end inwards: it drives the hook's cutting centre to the nearest live CT tet (centroids,
    current positions) among those within ``band`` of the CT's live edge nearest the free end (rest positions),
    approaching from ``lift`` above it,
    and switches the hook on within ``switch_on`` of it, keeping it on while the next tet is within ``keep_on`` (off
    otherwise, so moving about cuts nothing).

    Discrete actions (``Discrete(2d + 1)``: pan or tilt by 1 degree, spin by 1.5 degrees, depth by 1 mm, the
    activation, or nothing) follow their own plan (``expert_discrete``), against the ways the base class's rule (move
    the PTSD component with the largest error in steps towards the continuous plan's goal) failed (CPU, 16 envs, seeds
    0 and 1: R = 2 81 % / 81 %, R = 4 0 % / 0 %; time-outs with 10-50 CT tets left): a step moves the hook about as
    far as its 1 mm cutting reach, so the lattice of steps could leave the cutting centre out of reach of the tet with
    every error under half a step, where the hook rested for good; the lift over each tet and the switching cost
    steps; tets left behind rise with the flap once the CT around them is cut (seen 37 mm from the hook, 26 mm above
    the board), a long chase at 1 mm a step. Instead (1) the next tet is the one fewest discrete steps away
    (``steps_to``), counting ``sweep`` steps per mm of rest x behind the end of the live CT nearer the hook, so that
    the hook sweeps across the CT leaving no tet behind, and ``lifted`` steps less per node tied to the flap, so that
    the tets that would rise go first (``lifted`` = 5 took the mean episode at R = 2 from 271 to 228 steps); (2) the
    hook takes the pan, tilt or depth step that brings its cutting capsules (the cross bar and the last 7 mm,
    ``hook_reach``, not just the cutting centre) nearest to the tet, without the lift, and does not rest farther than
    ``reach`` from it; (3) it switches on within ``switch_on`` and stays on while the next tet is within
    ``discrete_keep_on`` (1 m: for the rest of the episode; it cuts a few flap tets, 0-6 an episode at R = 4). With
    them (CPU, first episodes, 16 envs with seeds 0 and 1, 32 envs with seed 2): R = 2 100 % / 100 % / 100 % (the
    slowest episode 300 / 289 / 298 of 400 steps), R = 4 100 % / 100 % / 100 % (584 / 575 / 620 of 800 steps)."""

    def __init__(self, env: TissueDissectionEnv, band: float = 0.012, switch_on: float = 0.003,
                 keep_on: float = 0.008, lift: float = 0.004, discrete_keep_on: float = 1.0, reach: float = 9.0e-4,
                 margin: float = 1.0e-4, sweep: float = 0.5, lifted: float = 5.0, high: float = 0.01,
                 y_margin: float = 0.002):
        super().__init__(env)
        # with the touch cut rule a CT tet the flap has stretched upwards is cut at its lowest node (``tet_target``)
        self.touch, self.high = int(env.cfg.cut_removal == "touch"), float(high)
        # and a target below the hook's workspace is moved into it along the tet (``tet_target``)
        self.y_min = float(env.cfg.workspace[0][1] + y_margin)
        self.band, self.switch_on, self.keep_on, self.lift = float(band), float(switch_on), float(keep_on), float(lift)
        n, dev = env.num_envs, env.wp_device
        self.error = wp.zeros((n, 5), dtype=float, device=dev)
        self.ct_tets = wp.array(env.ct_tets_global, dtype=wp.vec4i, device=dev)
        cv, ct = ct_mesh(env.cfg.rows_to_cut)
        self.rest_y = wp.array(cv[ct, 1].mean(axis=1).astype(np.float32), dtype=float, device=dev)
        self.ct_tet0 = int(env.ct_obj.element_start)
        to_internal = torch.tensor([math.pi / 180.0] * 3 + [1.0])
        dt = env.cfg.time_step * env.cfg.frame_skip
        step = (torch.tensor(env.cfg.maximum_state_velocity) * to_internal * dt).tolist()
        self.step_size = torch.tensor([*step, 1.0e-6], device=env.device)
        # discrete actions (``expert_discrete``): the CT tets' rest x and how many of their nodes are tied to the flap,
        # what one step moves (rad, rad, rad, m), the tet centroid each env goes for and the chosen action
        self.discrete_keep_on, self.reach, self.margin = float(discrete_keep_on), float(reach), float(margin)
        self.sweep, self.lifted = float(sweep), float(lifted)
        self.rest_x = wp.array(cv[ct, 0].mean(axis=1).astype(np.float32), dtype=float, device=dev)
        self.ct_top = wp.array((ct >= len(cv) // 2).sum(axis=1).astype(np.float32), dtype=float, device=dev)
        self.discrete_step = wp.vec4(*(self._discrete_step[:4] * self.rig_step_size()[:4]).tolist())
        self.target = wp.zeros(n, dtype=wp.vec3, device=dev)
        self.action = wp.zeros(n, dtype=wp.int32, device=dev)

    def __call__(self, obs=None) -> torch.Tensor:
        env, rig, s = self.env, self.env.rig, self.env.world.state
        if env.is_discrete:  # chosen by the kernel, not by ``policy_actions``
            with env._torch_stream_scope():
                launching.launch(expert_discrete, dim=env.num_envs,
                                 inputs=[s.particle_q, s.tet_active, self.ct_tets, self.rest_x, self.ct_top,
                                         self.ct_tet0, rig.ptsd, rig.pose, rig.rcm, rig.active, self.switch_on,
                                         self.discrete_keep_on, self.reach, self.margin, self.sweep, self.lifted,
                                         self.discrete_step, env.params.bounds, 2 * env.action_dim, self.touch,
                                         self.high, self.y_min],
                                 outputs=[self.target, self.action], device=env.wp_device)
            return wp.to_torch(self.action).long()
        with env._torch_stream_scope():
            launching.launch(expert_errors, dim=env.num_envs,
                             inputs=[s.particle_q, s.tet_active, self.ct_tets, self.rest_y, self.ct_tet0, rig.ptsd,
                                     rig.pose, rig.rcm, rig.active, self.band, self.switch_on, self.keep_on, self.lift,
                                     self.touch, self.high, self.y_min],
                             outputs=[self.error], device=env.wp_device)
        ideal = wp.to_torch(self.error) / self.step_size
        if env.action_dim > 5:  # leave the retraction force alone
            ideal = torch.cat([ideal, torch.zeros(env.num_envs, env.action_dim - 5, device=env.device)], dim=1)
        return self.policy_actions(ideal)
