"""PickAndPlaceEnv: grasp a deformable torus, lift it, and place it over the active peg (sofa_env's PickAndPlaceEnv;
task-cards §3).

A board carries nine pegs on a 3 x 3 grid; one (``num_active_pegs``) is active (red, the others blue) and the torus
takes the active colour. A pivotized (TPSD) grasper with jaws grasps the torus, lifts its centre of mass to
``minimum_lift_height`` (phase PICK -> PLACE) and places it over an active peg (success: the COM within 7 mm of the
peg in x, z and every torus node below 10 mm). Losing the grasp in PLACE returns to PICK.

Physics (SI, sofa_env's millimetres converted; **y is up** as in sofa_env, gravity 0.981 m/s^2 along -y: sofa_env's
scene sets -981 mm/s^2): the torus is a closed Cosserat rod of 29 nodes on a 14 mm circle (sofa_env: 30 frames whose
first and last coincide, closed by a bilateral constraint), E = 1 MPa, nu = 0, mass 5 kg, bending of a
``beam_radius`` = 2 mm cross-section (sofa_env's "soft" torus; its "stiff" one: ``torus="stiff"``, beam radius 10 mm,
mass 2 kg), velocity damping 1/s. It collides as a 3.5 mm tube (its nodes and segments) with itself, the nine pegs
(cylinders of r = 5 mm, y in [-10, 20] mm), the board (the plane y = 0; sofa_env: a penalty plane of k = 300 N/m on the
frames at 3.5 mm) and the grasper's shaft and jaws, with friction 0.9. Grasping (``lapwarp.grasping``, sofa_env's
rule): while the jaw angle is below 18 degrees and both jaws touch the torus, the node nearest the jaws' mid-plane
inside the jaw cone is attached to a jaw; its segment turns with the jaws' rotation about the vertical and keeps its
tilt (sofa_env holds the frame with 1e9 N/m and N m/rad springs, "the component that tilts the y axis removed",
task-cards §0.1), so a stiff ring stays level when the shaft tilts towards a far peg; while grasped the jaws do not
collide with the torus (sofa_env switches their collision models off); opening to 18 degrees releases it.

Episode logic (sofa_env's): the active pegs are drawn per env; the torus starts where a drop from 40 mm settles
(``randomize_torus_position``: its COM at x, z uniform in [-80, 80] mm, else at (40, 40, -3.5) mm), or grasped
(``start_grasped``: phase PLACE). sofa_env drops the torus and settles ``settle_steps`` physics steps after every
reset (again if it still moves faster than 25 mm/s); here a bank of ``torus_bank_size`` such settled drops is
simulated once when the env is built (with this physics, the same rule), and a reset copies a drawn one in place.

Reward features (Table A = sofa_zoo's weights; the ``delta_*`` ones are the change since the last step): grasping
(``grasped_torus``), ``lost_grasp`` (-30), and per phase -- features of the other phase read 0 (sofa_env weighs
them 0 there): PICK: ``established_grasp`` (+30), the grasp centre's distance to the torus COM and to the nearest
tracking node (its change, -10, is the *smallest of the per-node changes*, sofa_env's rule), the COM's height
missing to the lift height (its change: -50; only while grasped, and its change only if the last step had it);
PLACE: the COM's distance to the nearest active peg's target (x, 8.1 mm, z) and its change (-100). Always: jaw-peg
overlaps (-0.01; sofa_env counts contacts, here the overlapping (jaw, peg) pairs), the grasp centre below the board
(-0.01), unstable deformation (-0.01: mean node speed above 1.5 x the grasper's speed and above 25 mm/s), torus and
grasper speeds, torus off the board, the two limit flags, success (+50). Every feature with "distance" or
"velocity" in its name is in m (m/s) over the workspace diagonal (353.8 mm), clipped to [-1, 1] (sofa_env's).

STATE observation (33 with the defaults; Table D says 37, sofa_env's code gives 33): grasped (1), PTSD normalised by
the state limits and the jaw angle by its limits (5), grasper tip pose (position normalised by the workspace,
quaternion xyzw; 7), torus COM (3), ``num_torus_tracking_points`` nodes (sofa_env's frames 0, 6, 12, 18, 24; 3 T),
the active pegs' (x, z) (2 P), positions normalised by the workspace.

Deliberate differences from sofa_env (task-cards §3, §12):

* The COM is the mean of the 29 distinct nodes (sofa_env averages its 30 frames and so counts the seam twice).
* ``start_grasped`` (configuration Place): sofa_env stands the torus up in the xy plane, grasped at its top frame.
  Its board is a penalty plane (300 N/m against 1e9 N/m grasp springs), so a held vertical ring can be pushed
  through it until every frame is below 10 mm; on the rigid board here a vertical ring can never lie below 10 mm
  around a peg. The episode starts instead where a Pick ends (the paper's description: "the torus already grasped
  and the instrument at the desired lifting height"): the ring lying flat, grasped at its edge (node
  ``START_GRASP_NODE``) between the jaws, the tip where sofa_env starts it (plus the reset noise), settled.
* The grasp attaches the node to the jaw it touches at its current offset (sofa_env: to an anchor on the shaft axis;
  task-cards §0.1); the jaws do not collide with the board (as in sofa_env, which has no board collision model).
* The board is rigid (sofa_env's penalty plane lets a pressed torus sink into it).
* ``gripper_jaw_peg_collisions`` counts overlapping (jaw, peg) capsule pairs (sofa_env: contact points).
* Physics substeps: the stiff ring's bending converges slowly in XPBD's Gauss-Seidel sweeps; 40 substeps (the stiff
  default) leave its far side 3 mm low when held at its edge (1 mm converged), 10 would leave 24 mm; the soft torus
  hangs as a loop 45.3 mm tall at 5 (its default), 43.2 mm at 160.
* ``randomize_color`` swaps the active and the inactive colour per env (red/blue), the torus taking the active one.
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
from lapwarp.assets import rod_circle
from lapwarp.builder import SceneBuilder
from lapwarp.config import PTSD, Count, EnvConfig, NonNegative, Positive, PositiveInt, Range, numpy_rng
from lapwarp.contact import ContactSystem
from lapwarp.env import BatchedEnv
from lapwarp.experts import Expert
from lapwarp.instruments import TPSDConfig, tpsd_from_config
from lapwarp.kernels.bodies import hinged_jaw_pose
from lapwarp.kernels.geometry import closest_segment_segment, horizontal_distance
from lapwarp.kernels.kinematics import point_to_ptsd, ptsd_to_transform
from lapwarp.tasks.rig import (
    STATE_LIMITS_VIOLATED,
    WORKSPACE_VIOLATED,
    InstrumentRig,
    InstrumentSpec,
    RigBounds,
    count_flag,
    over_diagonal,
    write_unit_point,
    write_unit_ptsd,
)
from lapwarp.tasks.spec import Feature, ObservationLayout, ObservationSpec, RewardSpec, to_unit, write_transform
from lapwarp.tasks.targets import draw_index
from lapwarp.visuals import CameraSpec, VisualObject, VisualScene, look_at_transform
from lapwarp.world import World

wp.set_module_options({"enable_backward": False})

REWARDS = RewardSpec(
    Feature("grasped_torus", 0.0),
    Feature("lost_grasp", -30.0),
    Feature("established_grasp", 30.0),
    Feature("gripper_distance_to_torus_center", 0.0),
    Feature("delta_gripper_distance_to_torus_center", 0.0),
    Feature("gripper_distance_to_torus_tracking_points", 0.0),
    Feature("delta_gripper_distance_to_torus_tracking_points", -10.0),
    Feature("distance_to_minimum_pick_height", 0.0),
    Feature("delta_distance_to_minimum_pick_height", -50.0),
    Feature("torus_distance_to_active_pegs", 0.0),
    Feature("delta_torus_distance_to_active_pegs", -100.0),
    Feature("gripper_jaw_peg_collisions", -0.01),
    Feature("gripper_jaw_floor_collisions", -0.01),
    Feature("unstable_deformation", -0.01),
    Feature("torus_velocity", 0.0),
    Feature("gripper_velocity", 0.0),
    Feature("torus_dropped_off_board", 0.0),
    Feature("action_violated_state_limits", 0.0),
    Feature("action_violated_cartesian_workspace", 0.0),
    Feature("successful_task", 50.0),
)
F = REWARDS.F
OBS = ObservationSpec("grasped", "ptsdj", "pose", "com", "tracking", "pegs")
CRITIC = OBS.extend("grasp_to_com", "com_to_peg", "phase")

PICK, PLACE = 0, 1
NODES = 29  # distinct nodes of sofa_env's 30-frame ring (its first and last frame coincide)
TORUS_RADIUS, TUBE_RADIUS = 0.014, 0.0035
PEG_RADIUS, PEG_BOTTOM, PEG_TOP = 0.005, -0.01, 0.02
PEG_GRID = (-0.08, 0.0, 0.08)
PEGS = tuple((x, z) for x in PEG_GRID for z in PEG_GRID)  # index 3 i + j: x = grid[i], z = grid[j]
PEG_TARGET_Y = 0.0081  # sofa_env's place target height
JAW_LENGTH, JAW_RADIUS = 0.025, 0.001
GRASP_CENTER = 0.015  # sofa_env's grasp centre: anchor 5 on the shaft axis, 15 mm beyond the tip
START_GRASP_NODE = 0
SUCCESS_RADIUS, SUCCESS_HEIGHT = 0.007, 0.01
DROP_HEIGHT = 0.04
SETTLED_SPEED = 0.025  # sofa_env resets again while the mean node speed exceeds it
RED, BLUE = (0.85, 0.1, 0.1), (0.1, 0.25, 0.85)
HOOK_CARRY, HOOK_LOWER, HOOK_CROSS, HOOK_PULL = 0, 1, 2, 3  # the expert's stages placing a hanging (soft) loop
_NODES = wp.constant(NODES)
_PEG_COUNT = wp.constant(len(PEGS))
_HIDDEN = wp.constant(wp.vec3(0.0, -5.0, 0.0))  # far beyond the camera's far plane


@dataclass(kw_only=True)
class PickAndPlaceConfig(EnvConfig):
    """PickAndPlaceEnv parameters (Tables B, C: the paper's = sofa_zoo's values); metres, degrees, kg.

    Attributes:
        torus: ``"soft"`` (beam radius 2 mm, 5 kg) or ``"stiff"`` (10 mm, 2 kg; the paper: "beam radius x 5, mass /
            2.5"); ``beam_radius`` / ``torus_mass`` override either.
        beam_radius: radius of the cross-section whose bending and torsion stiffness the torus has (m; None: from
            ``torus``). Its collision tube is always 3.5 mm.
        torus_mass: kg (None: from ``torus``). youngs_modulus: Pa (sofa_env's 1e3 kg/(mm s^2)).
        torus_damping: velocity damping rate of the torus, 1/s.
        gravity: m/s^2 along -y (sofa_env's -981 mm/s^2).
        friction: Coulomb friction of every torus contact (sofa_env's 0.9).
        start_grasped: start in PLACE with the torus grasped (configuration Place; see the module docstring).
        only_learn_pick: the task succeeds on reaching PLACE (configuration Pick).
        randomize_torus_position: drop the torus at a random x, z in [-80, 80] mm (else at sofa_env's (40, -3.5) mm).
        num_active_pegs: active pegs per episode, drawn uniformly without repetition.
        randomize_color: swap the active and inactive colours (red, blue) per env at reset.
        num_torus_tracking_points: torus nodes in the observation (sofa_env's ``linspace(0, 30, T)`` frames).
        minimum_lift_height: COM height (y) that completes PICK, m.
        block_done_when_unstable: no success while the deformation is unstable.
        start_ptsd / ptsd_noise: the grasper's start state and uniform reset noise (deg, deg, deg, m; sofa_zoo's).
        rcm_position_noise (m) / rcm_euler_noise (deg): uniform reset noise of the grasper's RCM (sofa_zoo's).
        state_low / state_high: the grasper's state limits (deg, deg, deg, m).
        maximum_state_velocity / jaw_speed: speeds at action 1 (deg/s, deg/s, deg/s, m/s; jaw deg/s).
        discrete_action_magnitude / jaw_discrete_speed: speeds of a discrete action.
        jaw_start: jaw angle at reset (deg); jaw limits 0-60 deg. grasp_threshold: grasp below, release at or above
            this jaw angle (deg; sofa_env's 18, its 25 degree release threshold can never fire).
        settle_steps: physics steps a dropped torus settles (sofa_zoo's 50).
        torus_bank_size: settled drops simulated at build time that resets draw from, at least ``num_envs`` (with
            ``randomize_torus_position``; one drop is enough without it). They are simulated ``num_envs`` at a time.
        physics_substeps: XPBD substeps per physics step; None: 5 for the soft torus, 40 for the stiff one. The
            stiff ring's bending converges slowly in XPBD's Gauss-Seidel sweeps: held at its edge, its far side
            sags 23.9 / 9.1 / 3.1 / 1.5 / 1.0 mm at 10 / 20 / 40 / 80 / 160 substeps (measured on the CPU); the soft
            ring hangs as a loop 45.3 / 44.3 / 43.2 mm tall at 5 / 10 / 160 substeps.
        torus_inertia_scale: the torus segments' rotational inertia over a cylinder's (``SceneBuilder.add_rod``'s
            ``inertia_scale``). 100 lets the stiff ring keep its shape at 10 substeps (Place start, after 30 steps:
            far side 1.8 mm below the held node, 40 substeps without it 1.0 mm, 10 without it 22.8 mm, 160 -1.1 mm),
            but the scripted expert then places the stiff ring less often (CPU, 64 first episodes: 53 at 10 or 20
            substeps against 62 at 40 without it), so the default stays 1 with 40 substeps.
        contact_capacity: contact records kept per env per step.
        max_episode_steps: None = 300 per phase (Table C: 300 for Pick or Place, 600 for both).
    """

    time_step: Positive = 0.05
    frame_skip: Count(1000) = 2
    max_episode_steps: PositiveInt | None = None
    torus: Literal["soft", "stiff"] = "soft"
    beam_radius: Positive | None = None
    torus_mass: Positive | None = None
    youngs_modulus: Positive = 1.0e6
    torus_damping: NonNegative = 1.0
    gravity: NonNegative = 0.981
    friction: NonNegative = 0.9
    start_grasped: bool = False
    only_learn_pick: bool = False
    randomize_torus_position: bool = True
    num_active_pegs: Annotated[int, Range(ge=1, le=9)] = 1
    randomize_color: bool = False
    num_torus_tracking_points: Annotated[int, Range(ge=0, le=NODES)] = 5
    minimum_lift_height: Positive = 0.05
    block_done_when_unstable: bool = False
    start_ptsd: PTSD = (0.0, 0.0, 180.0, 0.05)
    ptsd_noise: tuple[NonNegative, NonNegative, NonNegative, NonNegative] = (10.0, 10.0, 45.0, 0.01)
    rcm_position_noise: tuple[NonNegative, NonNegative, NonNegative] = (0.01, 0.01, 0.01)
    rcm_euler_noise: tuple[NonNegative, NonNegative, NonNegative] = (5.0, 5.0, 5.0)
    state_low: PTSD = (-90.0, -90.0, -32767.0, 0.0)
    state_high: PTSD = (90.0, 90.0, 32767.0, 0.15)
    maximum_state_velocity: tuple[Positive, Positive, Positive, Positive] = (20.0, 20.0, 20.0, 0.02)
    discrete_action_magnitude: tuple[Positive, Positive, Positive, Positive] = (15.0, 15.0, 15.0, 0.01)
    jaw_speed: Positive = 5.0
    jaw_discrete_speed: Positive = 2.0
    jaw_start: Annotated[float, Range(ge=0.0, le=60.0)] = 11.0
    grasp_threshold: Annotated[float, Range(gt=0.0, le=60.0)] = 18.0
    settle_steps: Annotated[int, Range(ge=1, le=10_000)] = 50
    torus_bank_size: Count(1_000_000) = 16
    physics_substeps: Count(10_000) | None = None
    torus_inertia_scale: Annotated[float, Range(ge=1.0, le=1.0e6)] = 1.0
    contact_capacity: Count(4096) = 64

    def validate(self, reward_features, supported_observations) -> None:
        super().validate(reward_features, supported_observations)
        if self.start_grasped and self.only_learn_pick:
            raise ValueError("start_grasped=True starts in PLACE, only_learn_pick=True ends on reaching it: choose one")
        if self.start_grasped and self.randomize_torus_position:
            raise ValueError("start_grasped=True starts with the torus in the jaws: set randomize_torus_position=False")
        if self.physics_substeps is None:
            self.physics_substeps = 5 if self.torus == "soft" else 40
        if self.max_episode_steps is None:
            phases = 1 if (self.start_grasped or self.only_learn_pick) else 2
            self.max_episode_steps = 300 * phases  # Table C
        if self.jaw_start >= self.grasp_threshold and self.start_grasped:
            raise ValueError(f"start_grasped needs jaw_start={self.jaw_start} below grasp_threshold="
                             f"{self.grasp_threshold}")
        self.gripper_tpsd()

    @property
    def torus_parameters(self) -> tuple[float, float]:
        """(beam radius m, mass kg) of the configured torus."""
        radius, mass = (0.002, 5.0) if self.torus == "soft" else (0.01, 2.0)
        return (self.beam_radius or radius, self.torus_mass or mass)

    @property
    def workspace(self) -> tuple[np.ndarray, np.ndarray]:
        """The grasper tip's Cartesian workspace (sofa_env's: x, z in [-120, 120] mm, y in [0, 100] mm)."""
        return np.array([-0.12, 0.0, -0.12]), np.array([0.12, 0.1, 0.12])

    def gripper_tpsd(self) -> TPSDConfig:
        """The grasper's TPSD: RCM at (0, 115, 20) mm pointing down (Euler (90, 0, 0)), sofa_env's."""
        low, high = self.workspace
        return tpsd_from_config(self, rcm_position=(0.0, 0.115, 0.02), rcm_euler_deg=(90.0, 0.0, 0.0),
                                start_ptsd="start_ptsd", state_low="state_low", state_high="state_high",
                                workspace_low=tuple(low), workspace_high=tuple(high),
                                max_velocity="maximum_state_velocity", discrete_magnitude="discrete_action_magnitude",
                                ptsd_noise="ptsd_noise", rcm_position_noise="rcm_position_noise",
                                rcm_euler_noise_deg="rcm_euler_noise")


def tracking_nodes(count: int) -> np.ndarray:
    """sofa_env's tracking frames ``linspace(0, 30, count, endpoint=False)`` as node indices (frame 29 = node 0)."""
    return (np.linspace(0, 30, count, endpoint=False).astype(np.int64) % NODES).astype(np.int32)


# ---------------------------------------------------------------------------- kernels
@wp.struct
class Task:
    """Per-env task state: phase, active pegs (``(N, P)`` indices), colour swap, the last step's grasp flag, tip
    position and raw distances (for the delta features), and whether the last step had the lift feature."""

    phase: wp.array(dtype=wp.int32)
    pegs: wp.array2d(dtype=wp.int32)
    swap_color: wp.array(dtype=wp.int32)
    was_grasped: wp.array(dtype=wp.int32)
    last_tip: wp.array(dtype=wp.vec3)
    last_center_distance: wp.array(dtype=float)
    last_tracking: wp.array2d(dtype=float)
    last_lift: wp.array(dtype=float)
    had_lift: wp.array(dtype=wp.int32)
    last_peg_distance: wp.array(dtype=float)


@wp.struct
class Params:
    bounds: RigBounds
    torus_first: int
    segment_first: int
    lift_height: float
    only_pick: int
    block_unstable: int
    control_dt: float  # time_step x frame_skip
    randomize_position: int
    start_grasped: int
    randomize_color: int
    bank_size: int
    jaw_low: float
    jaw_high: float


@wp.func
def torus_com(q: wp.array2d(dtype=wp.vec3), env: int, first: int) -> wp.vec3:
    c = wp.vec3(0.0)
    for i in range(_NODES):
        c += q[env, first + i]
    return c / float(_NODES)


@wp.func
def peg_target(k: int) -> wp.vec3:
    i = k / 3
    j = k - 3 * i
    return wp.vec3(-0.08 + 0.08 * float(i), PEG_TARGET_Y, -0.08 + 0.08 * float(j))


@wp.func
def grasp_center(tip: wp.transform) -> wp.vec3:
    return wp.transform_point(tip, wp.vec3(0.0, 0.0, GRASP_CENTER))


@wp.func
def jaw_peg_overlaps(tip: wp.transform, angle: float) -> int:
    """(jaw, peg) pairs whose capsules overlap (sofa_env counts the jaws' sphere contacts with the pegs)."""
    count = int(0)
    for side in range(2):
        jaw = hinged_jaw_pose(tip, wp.where(side == 0, angle, -angle))
        a = wp.transform_get_translation(jaw)
        b = wp.transform_point(jaw, wp.vec3(0.0, 0.0, JAW_LENGTH))
        for k in range(_PEG_COUNT):
            c = peg_target(k)
            p0 = wp.vec3(c[0], PEG_BOTTOM, c[2])
            p1 = wp.vec3(c[0], PEG_TOP, c[2])
            st = closest_segment_segment(a, b, p0, p1)
            d = wp.length(a + (b - a) * st[0] - (p0 + (p1 - p0) * st[1]))
            if d < PEG_RADIUS + JAW_RADIUS:
                count += 1
    return count


@wp.func
def store_history(task: Task, env: int, held: int, tip_pos: wp.vec3, d_center: float, lift: float, d_peg: float):
    """This step's raw values, which the next step's delta features start from."""
    task.was_grasped[env] = held
    task.last_tip[env] = tip_pos
    task.last_center_distance[env] = d_center
    task.last_lift[env] = lift
    task.had_lift[env] = held
    task.last_peg_distance[env] = d_peg


@wp.func
def nearest_peg(task: Task, env: int, x: wp.vec3) -> wp.vec3:
    """The target of the active peg nearest to ``x`` in x, z."""
    best = float(1.0e9)
    peg = wp.vec3(0.0)
    for k in range(task.pegs.shape[1]):
        c = peg_target(task.pegs[env, k])
        d = (c[0] - x[0]) * (c[0] - x[0]) + (c[2] - x[2]) * (c[2] - x[2])
        if d < best:
            best = d
            peg = c
    return peg


@wp.kernel
def eval_pick_and_place(env_mask: wp.array(dtype=wp.int32), mode: int, q: wp.array2d(dtype=wp.vec3),
                        qd: wp.array2d(dtype=wp.vec3), pose: wp.array2d(dtype=wp.transform),
                        jaw_angle: wp.array2d(dtype=float), flags: wp.array2d(dtype=wp.int32),
                        grasped: wp.array(dtype=wp.int32), tracking: wp.array(dtype=wp.int32), p: Params, task: Task,
                        features_out: wp.array2d(dtype=float)):
    """sofa_env's reward features. ``mode`` 1 (the step's evaluation) also switches the phase and stores this step's
    raw values for the next step's deltas; mode 2 (reset) only stores them (and writes no features)."""
    env = wp.tid()
    if env_mask[env] == 0:
        return
    tip = pose[env, 0]
    tip_pos = wp.transform_get_translation(tip)
    gc = grasp_center(tip)
    com = torus_com(q, env, p.torus_first)
    held = grasped[env]
    # distances
    d_center = wp.length(gc - com)
    d_track_min = float(1.0e9)
    delta_track_min = float(1.0e9)
    for t in range(tracking.shape[0]):
        d = wp.length(gc - q[env, p.torus_first + tracking[t]])
        d_track_min = wp.min(d_track_min, d)
        delta_track_min = wp.min(delta_track_min, d - task.last_tracking[env, t])
        if mode != 0:
            task.last_tracking[env, t] = d
    if tracking.shape[0] == 0:
        d_track_min = 0.0
        delta_track_min = 0.0
    lift = wp.max(p.lift_height - com[1], 0.0)
    d_peg = float(1.0e9)
    xz_peg = float(1.0e9)
    for k in range(task.pegs.shape[1]):
        c = peg_target(task.pegs[env, k])
        d_peg = wp.min(d_peg, wp.length(com - c))
        xz_peg = wp.min(xz_peg, wp.sqrt((com[0] - c[0]) * (com[0] - c[0]) + (com[2] - c[2]) * (com[2] - c[2])))
    speed = float(0.0)
    highest = float(-1.0e9)
    for i in range(_NODES):
        speed += wp.length(qd[env, p.torus_first + i])
        highest = wp.max(highest, q[env, p.torus_first + i][1])
    speed = speed / float(_NODES)
    tip_speed = wp.length(tip_pos - task.last_tip[env]) / p.control_dt
    if mode == 2:  # reset: only the history
        store_history(task, env, held, tip_pos, d_center, lift, d_peg)
        return
    # phase (sofa_env switches before the reward, so the new phase's features count on the switching step)
    phase = task.phase[env]
    if phase == PICK and held != 0 and com[1] >= p.lift_height:
        phase = PLACE
    elif phase == PLACE and held == 0:
        phase = PICK
    pick = wp.where(phase == PICK, 1.0, 0.0)
    place = 1.0 - pick
    inv = p.bounds.inv_diagonal
    established = wp.where(held != 0 and task.was_grasped[env] == 0, 1.0, 0.0)
    lift_now = wp.where(held != 0, lift, 0.0)
    delta_lift = float(0.0)
    if held != 0 and task.had_lift[env] != 0:
        delta_lift = lift - task.last_lift[env]
    unstable = wp.where(speed > 1.5 * tip_speed and speed > SETTLED_SPEED, 1.0, 0.0)
    success = float(0.0)
    if p.only_pick != 0:
        success = wp.where(phase == PLACE, 1.0, 0.0)
    elif xz_peg < SUCCESS_RADIUS and highest < SUCCESS_HEIGHT:
        success = 1.0
    if p.block_unstable != 0 and unstable > 0.0:
        success = 0.0
    off_board = wp.where(com[1] < 0.003 and (wp.abs(com[0]) > 0.08 or wp.abs(com[2]) > 0.08), 1.0, 0.0)
    features_out[env, F.GRASPED_TORUS] = float(held)
    # a grasp lost this step, by opening the jaws or torn out (sofa_env's: grasped before, not now)
    features_out[env, F.LOST_GRASP] = wp.where(held == 0 and task.was_grasped[env] != 0, 1.0, 0.0)
    features_out[env, F.ESTABLISHED_GRASP] = established * pick
    features_out[env, F.GRIPPER_DISTANCE_TO_TORUS_CENTER] = over_diagonal(d_center, inv) * pick
    features_out[env, F.DELTA_GRIPPER_DISTANCE_TO_TORUS_CENTER] = over_diagonal(
        d_center - task.last_center_distance[env], inv) * pick
    features_out[env, F.GRIPPER_DISTANCE_TO_TORUS_TRACKING_POINTS] = over_diagonal(d_track_min, inv) * pick
    features_out[env, F.DELTA_GRIPPER_DISTANCE_TO_TORUS_TRACKING_POINTS] = over_diagonal(delta_track_min, inv) * pick
    features_out[env, F.DISTANCE_TO_MINIMUM_PICK_HEIGHT] = over_diagonal(lift_now, inv) * pick
    features_out[env, F.DELTA_DISTANCE_TO_MINIMUM_PICK_HEIGHT] = over_diagonal(delta_lift, inv) * pick
    features_out[env, F.TORUS_DISTANCE_TO_ACTIVE_PEGS] = over_diagonal(d_peg, inv) * place
    features_out[env, F.DELTA_TORUS_DISTANCE_TO_ACTIVE_PEGS] = over_diagonal(d_peg - task.last_peg_distance[env],
                                                                          inv) * place
    features_out[env, F.GRIPPER_JAW_PEG_COLLISIONS] = float(jaw_peg_overlaps(tip, jaw_angle[env, 0]))
    features_out[env, F.GRIPPER_JAW_FLOOR_COLLISIONS] = wp.where(gc[1] < 0.0, 1.0, 0.0)
    features_out[env, F.UNSTABLE_DEFORMATION] = unstable
    features_out[env, F.TORUS_VELOCITY] = over_diagonal(speed, inv)
    features_out[env, F.GRIPPER_VELOCITY] = over_diagonal(tip_speed, inv)
    features_out[env, F.TORUS_DROPPED_OFF_BOARD] = off_board
    features_out[env, F.ACTION_VIOLATED_STATE_LIMITS] = float(count_flag(flags, env, STATE_LIMITS_VIOLATED))
    features_out[env, F.ACTION_VIOLATED_CARTESIAN_WORKSPACE] = float(count_flag(flags, env, WORKSPACE_VIOLATED))
    features_out[env, F.SUCCESSFUL_TASK] = success
    if mode == 1:
        task.phase[env] = phase
        store_history(task, env, held, tip_pos, d_center, lift, d_peg)


@wp.kernel
def reset_pick_and_place(env_mask: wp.array(dtype=wp.int32), rng: wp.array(dtype=wp.uint32), p: Params,
                         bank_q: wp.array2d(dtype=wp.vec3), bank_segment_q: wp.array2d(dtype=wp.quat),
                         bank_tip: wp.transform, pose: wp.array2d(dtype=wp.transform), task: Task,
                         q: wp.array2d(dtype=wp.vec3), qd: wp.array2d(dtype=wp.vec3),
                         segment_q: wp.array2d(dtype=wp.quat), segment_qd: wp.array2d(dtype=wp.vec3)):
    """sofa_env's reset: active pegs (distinct, uniform), colours, the torus from the bank of settled drops (a drawn
    one with ``randomize_torus_position``), for ``start_grasped`` carried along with the grasper's (noisy) tip."""
    env = wp.tid()
    if env_mask[env] == 0:
        return
    for k in range(task.pegs.shape[1]):
        while True:  # distinct pegs: redraw a repeat (at most 9 pegs, a handful of draws)
            c = draw_index(rng, env, _PEG_COUNT)
            repeat = int(0)
            for m in range(k):
                if task.pegs[env, m] == c:
                    repeat = 1
            if repeat == 0:
                task.pegs[env, k] = c
                break
    task.swap_color[env] = 0
    if p.randomize_color != 0:
        task.swap_color[env] = draw_index(rng, env, 2)
    b = int(0)
    if p.randomize_position != 0:
        b = draw_index(rng, env, p.bank_size)
    carry = wp.transform_identity()
    if p.start_grasped != 0:
        carry = wp.transform_multiply(pose[env, 0], wp.transform_inverse(bank_tip))
    rot = wp.transform_get_rotation(carry)
    for i in range(_NODES):
        q[env, p.torus_first + i] = wp.transform_point(carry, bank_q[b, i])
        qd[env, p.torus_first + i] = wp.vec3(0.0)
        segment_q[env, p.segment_first + i] = wp.normalize(rot * bank_segment_q[b, i])
        segment_qd[env, p.segment_first + i] = wp.vec3(0.0)
    task.phase[env] = wp.where(p.start_grasped != 0, PLACE, PICK)


@wp.kernel
def observe_pick_and_place(q: wp.array2d(dtype=wp.vec3), ptsd: wp.array2d(dtype=wp.vec4),
                           pose: wp.array2d(dtype=wp.transform), jaw_angle: wp.array2d(dtype=float),
                           grasped: wp.array(dtype=wp.int32), tracking: wp.array(dtype=wp.int32), p: Params,
                           task: Task, o: OBS.Columns, c: CRITIC.Columns, privileged: int,
                           obs_out: wp.array2d(dtype=float), critic_out: wp.array2d(dtype=float)):
    """sofa_env's STATE (see the module docstring), positions normalised by the workspace."""
    env = wp.tid()
    b = p.bounds
    obs_out[env, o.grasped] = float(grasped[env])
    write_unit_ptsd(obs_out, env, o.ptsdj, ptsd[env, 0], b)
    obs_out[env, o.ptsdj + 4] = to_unit(jaw_angle[env, 0], p.jaw_low, p.jaw_high)
    tip = pose[env, 0]
    write_transform(obs_out, env, o.pose, tip)
    write_unit_point(obs_out, env, o.pose, wp.transform_get_translation(tip), b)
    com = torus_com(q, env, p.torus_first)
    write_unit_point(obs_out, env, o.com, com, b)
    for t in range(tracking.shape[0]):
        write_unit_point(obs_out, env, o.tracking + 3 * t, q[env, p.torus_first + tracking[t]], b)
    for k in range(task.pegs.shape[1]):
        peg = peg_target(task.pegs[env, k])
        obs_out[env, o.pegs + 2 * k] = to_unit(peg[0], b.ws_low[0], b.ws_high[0])
        obs_out[env, o.pegs + 2 * k + 1] = to_unit(peg[2], b.ws_low[2], b.ws_high[2])
    if privileged == 0:
        return
    rel = (com - grasp_center(tip)) * b.inv_diagonal
    best = float(1.0e9)
    to_peg = wp.vec3(0.0)
    for k in range(task.pegs.shape[1]):
        d = peg_target(task.pegs[env, k]) - com
        if wp.length(d) < best:
            best = wp.length(d)
            to_peg = d * b.inv_diagonal
    for i in range(3):
        critic_out[env, c.grasp_to_com + i] = rel[i]
        critic_out[env, c.com_to_peg + i] = to_peg[i]
    critic_out[env, c.phase] = float(task.phase[env])


@wp.kernel
def place_scene_visuals(q: wp.array2d(dtype=wp.vec3), p: Params, task: Task, ring_out: wp.array2d(dtype=wp.vec3),
                        red_segments: wp.array2d(dtype=wp.int32), blue_segments: wp.array2d(dtype=wp.int32),
                        red_pegs: wp.array2d(dtype=wp.transform), blue_pegs: wp.array2d(dtype=wp.transform)):
    """The closed ring's tube points (node 0 repeated at the end), the torus in the active colour, and every peg's
    red or blue copy in place (the other one hidden beyond the far plane)."""
    env = wp.tid()
    for i in range(_NODES + 1):
        ring_out[env, i] = q[env, p.torus_first + i % _NODES]
    swap = task.swap_color[env]
    for i in range(_NODES):
        red_segments[env, i] = 1 - swap
        blue_segments[env, i] = swap
    for k in range(_PEG_COUNT):
        active = int(0)
        for m in range(task.pegs.shape[1]):
            if task.pegs[env, m] == k:
                active = 1
        red = wp.where(active != swap, 1, 0)  # active pegs are red unless the colours are swapped
        c = peg_target(k)
        place = wp.transform(wp.vec3(c[0], 0.0, c[2]), wp.quat_identity())
        hidden = wp.transform(_HIDDEN, wp.quat_identity())
        red_pegs[env, k] = wp.where(red != 0, place, hidden)
        blue_pegs[env, k] = wp.where(red != 0, hidden, place)


@wp.func
def place_level_ring(q: wp.array2d(dtype=wp.vec3), env: int, p: Params, tip: wp.transform, rcm: wp.transform,
                     com: wp.vec3, peg: wp.vec3, lowest: float, highest: float, clearance: float, descent: float,
                     far_peg: float, centred: float, discrete: int, depth_high: float, depth_margin: float,
                     spin_margin: float, max_shift: float) -> tuple[wp.vec3, float]:
    """PLACE for a ring that stays level when held (the stiff torus): the tip goal and spin error that carry its COM
    over the peg with the ring above the pegs' tops, then lower it around the peg (and keep lowering while it is
    around the peg) once the COM is within ``centred`` of the peg (2 mm; discrete steps land on a lattice 3-4 mm
    apart at the far pegs, which may never come that near: 3.5 mm for them, the ring's hole leaves the peg 5.5 mm)."""
    tip_pos = wp.transform_get_translation(tip)
    center = grasp_center(tip)
    pivot = wp.transform_get_translation(rcm)
    reach = wp.sqrt((peg[0] - pivot[0]) * (peg[0] - pivot[0]) + (peg[2] - pivot[2]) * (peg[2] - pivot[2]))
    if discrete != 0 and reach > far_peg:
        # a peg at the edge of the shaft's reach (the depth limit leaves the grasp centre short of it even with
        # the COM beyond the grasp): aim the COM up to ``max_shift`` short of the peg, towards the RCM (the ring's
        # hole leaves the peg 5.5 mm, success needs the COM within 7 mm)
        toward = wp.normalize(wp.vec3(pivot[0] - peg[0], 0.0, pivot[2] - peg[2]))
        r = wp.sqrt((com[0] - center[0]) * (com[0] - center[0]) + (com[2] - center[2]) * (com[2] - center[2]))
        g = wp.vec3(peg[0] + toward[0] * r, PEG_TARGET_Y, peg[2] + toward[2] * r)
        over = wp.length(g - pivot) - GRASP_CENTER - (depth_high - depth_margin)
        if over > 0.0:
            peg = peg + toward * wp.min(max_shift, over / 0.7)
    dx = peg[0] - com[0]
    dz = peg[2] - com[2]
    e = wp.sqrt(dx * dx + dz * dz)
    dy = PEG_TOP + TUBE_RADIUS + clearance - lowest
    if e < centred or (lowest < PEG_TOP and e < 0.006):
        dy = -wp.min(highest - SUCCESS_HEIGHT * 0.5, descent)
    # spin the torus about the held point until its COM lies beyond the grasp as seen from the RCM: the far
    # pegs are then within the shaft's reach
    heading = wp.atan2(com[2] - center[2], com[0] - center[0])
    wanted = wp.atan2(peg[2] - pivot[2], peg[0] - pivot[0])
    turn = wanted - heading
    spin = float(0.0)
    turn = wp.atan2(wp.sin(turn), wp.cos(turn))
    if discrete != 0 and reach > far_peg:
        # a discrete expert turns slowly (1.5 degrees a step, taking turns with motion): turn only as far as the
        # shaft's depth limit needs, i.e. until the heading is within ``slack`` of ``wanted`` (the grasp centre,
        # the ring's radius from the COM, then lies within reach when the COM is over the peg), and never for less
        # than ``spin_margin`` (the held ring wobbles by several degrees: it would turn back and forth); the error
        # aims ``spin_margin`` inside the slack, so that each step that turns goes towards ``wanted``
        slack = level_ring_slack(rcm, center, com, peg, depth_high, depth_margin)
        if wp.abs(turn) > wp.max(slack, spin_margin):
            spin = turn - wp.sign(turn) * wp.max(slack - spin_margin, 0.0)
    elif reach > far_peg:  # only the far pegs need it
        spin = turn
    return tip_pos + wp.vec3(dx, dy, dz), spin


@wp.func
def level_ring_slack(rcm: wp.transform, center: wp.vec3, com: wp.vec3, peg: wp.vec3, depth_high: float,
                     depth_margin: float) -> float:
    """The largest angle (rad, 0 to pi) between the ring's heading (grasp centre to COM, horizontal) and the
    direction from the RCM to the peg for which the tip still reaches the grasp centre at the board with the COM
    over the peg, ``depth_margin`` short of the depth limit ``depth_high``."""
    pivot = wp.transform_get_translation(rcm)
    r = wp.sqrt((com[0] - center[0]) * (com[0] - center[0]) + (com[2] - center[2]) * (com[2] - center[2]))
    wanted = wp.atan2(peg[2] - pivot[2], peg[0] - pivot[0])
    slack = float(0.0)
    for i in range(61):
        a = float(i) * (wp.pi / 60.0)
        h = wanted + a
        g = wp.vec3(peg[0] - r * wp.cos(h), PEG_TARGET_Y, peg[2] - r * wp.sin(h))  # where it ends, placed
        if wp.length(g - pivot) - GRASP_CENTER <= depth_high - depth_margin:
            slack = a
    return slack


@wp.func
def hook_hanging_loop(q: wp.array2d(dtype=wp.vec3), env: int, p: Params, tip: wp.transform, rcm: wp.transform,
                      held: wp.vec3, com: wp.vec3, peg: wp.vec3, lowest: float, hook_far: float, hook_near: float,
                      clearance: float, cross_height: float, hold_height: float, swing_rate: float, max_swing: float,
                      arrived: int, stage: wp.array(dtype=wp.int32), heading: wp.array(dtype=wp.vec3),
                      swing: wp.array(dtype=float)) -> wp.vec3:
    """PLACE for a loop that hangs from the grasp (the soft torus: two strands side by side, too narrow for the
    peg's top to enter between them when lowered onto it). The tip goal of four stages: CARRY the loop's COM to
    ``hook_far`` beyond the peg (along the loop's normal, away from the RCM) above the pegs' tops; LOWER it until its
    fold lies on the board there; CROSS with the held node at ``cross_height`` over the peg's top to ``hook_near``
    before it, the strands draped over the top one on each side of the peg's axis; PULL the held node down to
    ``hold_height``: the taut strands slide off the top, one around each side of the peg, and the loop lies around
    it. A strand left on the top is pulled off by swinging the held node about the peg towards that strand's side.
    ``held``: where the held node is (discrete actions: where the jaw holds it, see ``expert_commands``); the held
    node has crossed once over ``near`` or, discrete, ``arrived``: no discrete step brings it nearer (they land on a
    lattice 1-4 mm apart)."""
    tip_pos = wp.transform_get_translation(tip)
    # the loop's horizontal normal: its strands lie side by side along the principal axis of its nodes' horizontal
    # spread
    cxx = float(0.0)
    cxz = float(0.0)
    czz = float(0.0)
    for i in range(_NODES):
        x = q[env, p.torus_first + i] - com
        cxx += x[0] * x[0]
        cxz += x[0] * x[2]
        czz += x[2] * x[2]
    angle = 0.5 * wp.atan2(2.0 * cxz, cxx - czz)
    normal = wp.vec3(-wp.sin(angle), 0.0, wp.cos(angle))
    goal = tip_pos
    if stage[env] == HOOK_CARRY:
        # cross towards the RCM: the grasp centre then ends nearer to it, within the shaft's reach at the far pegs
        pivot = wp.transform_get_translation(rcm)
        if (pivot[0] - peg[0]) * normal[0] + (pivot[2] - peg[2]) * normal[2] > 0.0:
            normal = -normal
        heading[env] = normal
        far = peg + normal * hook_far
        dy = PEG_TOP + TUBE_RADIUS + clearance - lowest
        goal = tip_pos + wp.vec3(far[0] - com[0], dy, far[2] - com[2])
        if horizontal_distance(far, com) < 0.002 and wp.abs(dy) < 0.003:
            stage[env] = HOOK_LOWER
    elif stage[env] == HOOK_LOWER:
        far = peg + heading[env] * hook_far
        goal = tip_pos + wp.vec3(0.5 * (far[0] - com[0]), -0.003, 0.5 * (far[2] - com[2]))
        if lowest < 2.0 * TUBE_RADIUS:
            stage[env] = HOOK_CROSS
    elif stage[env] == HOOK_CROSS:
        near = peg - heading[env] * hook_near
        goal = tip_pos + wp.vec3(near[0] - held[0], cross_height - held[1], near[2] - held[2])
        if horizontal_distance(near, held) < 0.0015 or arrived != 0:
            stage[env] = HOOK_PULL
    else:
        u = heading[env]
        side = wp.vec3(-u[2], 0.0, u[0])
        # nodes on the peg's top (above it, within the tube's reach of its axis) once the pull has lowered the
        # held node below the top: swing towards their side of the crossing line
        on_top = wp.vec3(0.0)
        count = int(0)
        for i in range(_NODES):
            x = q[env, p.torus_first + i] - peg
            if x[1] + PEG_TARGET_Y > PEG_TOP and wp.sqrt(x[0] * x[0] + x[2] * x[2]) < PEG_RADIUS + TUBE_RADIUS:
                on_top += x
                count += 1
        if count > 0 and held[1] < PEG_TOP - 0.005:
            step = wp.where(wp.dot(on_top, side) >= 0.0, swing_rate, -swing_rate)
            swing[env] = wp.clamp(swing[env] + step, -max_swing, max_swing)
        a = swing[env]
        near = peg + (side * wp.sin(a) - u * wp.cos(a)) * hook_near
        goal = tip_pos + wp.vec3(near[0] - held[0], hold_height - held[1], near[2] - held[2])
    return goal


@wp.func
def lattice_aim(q: wp.array2d(dtype=wp.vec3), env: int, first: int, rcm: wp.transform, s: wp.vec4, point: wp.vec3,
                step: wp.vec4) -> wp.vec3:
    """(pan, tilt, depth) of the shaft line that discrete steps can reach (pan and tilt are the current ones plus
    whole steps) and that passes nearest to the torus' centre line within 6 mm of ``point``; depth: where it passes.
    One pan or tilt step moves the line 2.5-4 mm at the torus, so aiming at ``point`` itself can leave the tube
    that far off the jaws' mid-plane (they then push it away instead of closing on it); somewhere along the tube
    near it a lattice line passes within a fraction of a millimetre. A line within 0.3 mm of the best is kept, and
    the current one preferred, so that the choice does not flip while the tip moves."""
    origin = wp.transform_get_translation(rcm)
    aim = point_to_ptsd(rcm, point, s[2])
    i0 = wp.round((aim[0] - s[0]) / step[0])
    j0 = wp.round((aim[1] - s[1]) / step[1])
    best = float(1.0e9)
    choice = wp.vec3(s[0] + i0 * step[0], s[1] + j0 * step[1], aim[3])
    for i in range(-2, 3):
        for j in range(-2, 3):
            pan = s[0] + (i0 + float(i)) * step[0]
            tilt = s[1] + (j0 + float(j)) * step[1]
            far = wp.transform_get_translation(ptsd_to_transform(rcm, wp.vec4(pan, tilt, s[2], 0.3)))
            for k in range(_NODES):
                a = q[env, first + k]
                b = q[env, first + (k + 1) % _NODES]
                mid = 0.5 * (a + b)
                if horizontal_distance(mid, point) > 0.006:
                    continue
                st = closest_segment_segment(origin, far, a, b)
                on_line = origin + (far - origin) * st[0]
                d = wp.length(on_line - (a + (b - a) * st[1]))
                if wp.abs(pan - s[0]) < 0.5 * step[0] and wp.abs(tilt - s[1]) < 0.5 * step[1]:
                    d -= 0.0003  # keep the current line unless another is clearly nearer
                if d < best:
                    best = d
                    choice = wp.vec3(pan, tilt, 0.3 * st[0])
    return choice


@wp.func
def discrete_pick(q: wp.array2d(dtype=wp.vec3), env: int, first: int, rcm: wp.transform, s: wp.vec4,
                  point: wp.vec3, jaw_angle: float, open_angle: float, hold_depth: float, clearance: float,
                  step: wp.vec4, closing: wp.array(dtype=wp.int32)) -> tuple[wp.vec3, float]:
    """PICK with discrete actions: the tip goal and jaw error that aim the shaft at the torus (``lattice_aim``; pan
    and tilt at the current depth or ``clearance`` short of the hold), advance it along the shaft (depth only) until
    the tube lies ``hold_depth`` along the jaws, and close. The continuous expert's vertical descent with a 3 mm
    lateral tolerance keeps leaving and re-entering that tolerance on the PTSD lattice; along the shaft the descent
    is exact. Once closing, the jaws close until they grasp or shut on nothing (``closing``; the jaws push the torus
    a little), then open and aim again."""
    aim = lattice_aim(q, env, first, rcm, s, point, step)
    reach = aim[2] - hold_depth  # the depth that puts the tube hold_depth along the jaws
    aimed = wp.abs(aim[0] - s[0]) < 0.5 * step[0] and wp.abs(aim[1] - s[1]) < 0.5 * step[1]
    opened = jaw_angle >= open_angle - 0.5
    if closing[env] != 0 and jaw_angle < 1.0:
        closing[env] = 0  # shut on nothing
    elif closing[env] == 0 and opened and aimed and wp.abs(s[3] - reach) <= step[3]:
        closing[env] = 1
    depth = wp.min(s[3], reach - clearance)  # aim above the torus first
    if aimed:
        depth = reach
    jaw = float(0.0)
    if closing[env] != 0:
        jaw = -60.0  # in place: close (the grasp happens below the grasp threshold)
        aim = wp.vec3(s[0], s[1], 0.0)
        depth = s[3]
    elif not opened:
        jaw = open_angle - jaw_angle
    return wp.transform_get_translation(ptsd_to_transform(rcm, wp.vec4(aim[0], aim[1], s[2], depth))), jaw


@wp.func
def discrete_command(rcm: wp.transform, s: wp.vec4, handle: wp.vec3, goal: wp.vec3, spin: float, jaw: float,
                     step: wp.vec4, jaw_step: float, b: RigBounds, turn: int) -> wp.vec2i:
    """The discrete action (index ``2 k`` moves component k by +``step[k]``, ``2 k + 1`` by -``step[k]``, 10 is
    the no-op) and whether no motion step gets nearer ``goal``. A discrete action moves one PTSD component by a
    whole step (pan and tilt 1.5 degrees: 2-4 mm; depth 1 mm along the tilted shaft), so moving the component with
    the largest PTSD error first sends the tip on arcs far off the straight line to the goal (a far peg needs ~50
    depth steps: depth first pushes a held torus into the board). Instead the motion is the pan, tilt or depth step
    that brings ``handle`` (a point of the tip frame) nearest to ``goal``, or none where no step gets it nearer. The
    jaws go first (closing when in place, opening before a move); spin and motion take turns (``turn``: the episode
    step's parity), so that neither waits for the other (a torus lying on the board does not turn with the jaws:
    spinning first would never lift it)."""
    best = wp.length(goal - wp.transform_point(ptsd_to_transform(rcm, s), handle)) - 0.1 * step[3]
    move = int(10)  # a step must gain a tenth of a depth step
    for k in range(3):
        c = wp.where(k == 2, 3, k)  # pan, tilt, depth
        for sign in range(2):
            t = s
            t[c] = s[c] + wp.where(sign == 0, step[c], -step[c])
            pose = ptsd_to_transform(rcm, t)
            # the env rejects a step beyond the state limits or with the tip out of the workspace
            inside = t[c] >= b.state_low[c] and t[c] <= b.state_high[c]
            x = wp.transform_get_translation(pose)
            for i in range(3):
                inside = inside and x[i] >= b.ws_low[i] and x[i] <= b.ws_high[i]
            d = wp.length(goal - wp.transform_point(pose, handle))
            if inside and d < best:
                best = d
                move = 2 * c + sign
    arrived = wp.where(move == 10, 1, 0)
    if wp.abs(jaw) >= 0.5 * jaw_step:
        return wp.vec2i(wp.where(jaw > 0.0, 8, 9), arrived)
    if wp.abs(spin) >= 0.5 * step[2] and (move == 10 or turn == 0):
        return wp.vec2i(wp.where(spin > 0.0, 4, 5), arrived)
    return wp.vec2i(move, arrived)


@wp.kernel
def expert_commands(q: wp.array2d(dtype=wp.vec3), ptsd: wp.array2d(dtype=wp.vec4),
                    pose: wp.array2d(dtype=wp.transform), rcm: wp.array2d(dtype=wp.transform),
                    jaw_angle: wp.array2d(dtype=float), grasped: wp.array(dtype=wp.int32),
                    attach_particle: wp.array2d(dtype=wp.int32), attach_body: wp.array2d(dtype=wp.int32),
                    attach_offset: wp.array2d(dtype=wp.vec3), body_q: wp.array2d(dtype=wp.transform), p: Params,
                    task: Task, episode_length: wp.array(dtype=wp.int32), open_angle: float, hold_depth: float,
                    clearance: float, descent: float, far_peg: float, hook_far: float, hook_near: float,
                    cross_height: float, hold_height: float, swing_rate: float, max_swing: float, max_step: float,
                    depth_margin: float, spin_margin: float, max_shift: float, discrete: int, discrete_step: wp.vec4,
                    jaw_step: float, stage: wp.array(dtype=wp.int32),
                    heading: wp.array(dtype=wp.vec3), swing: wp.array(dtype=float), anchor: wp.array(dtype=wp.vec3),
                    closing: wp.array(dtype=wp.int32), arrived: wp.array(dtype=wp.int32), ref: wp.array(dtype=wp.vec3),
                    error_out: wp.array2d(dtype=float), action_out: wp.array(dtype=wp.int32)):
    """The scripted grasper (``PickAndPlaceExpert``): PTSD and jaw errors per env (continuous actions) or the
    discrete action index (``discrete`` != 0: ``action_out``), and its per-env state: the hooking ``stage``, the
    crossing direction ``heading``, the ``swing`` about the peg; discrete only: the tip where the grasp happened
    (``anchor``), whether the jaws are ``closing`` in PICK, whether the tip ``arrived`` at the last goal and the
    reference point ``ref`` it chases."""
    env = wp.tid()
    if episode_length[env] == 0 or grasped[env] == 0 or task.phase[env] == PICK:
        stage[env] = HOOK_CARRY
        swing[env] = 0.0
    if episode_length[env] == 0:
        closing[env] = 0
        arrived[env] = 0
    was = stage[env]
    tip = pose[env, 0]
    tip_pos = wp.transform_get_translation(tip)
    axis = wp.transform_vector(tip, wp.vec3(0.0, 0.0, 1.0))  # along the jaws
    opening = wp.transform_vector(tip, wp.vec3(0.0, 1.0, 0.0))  # the jaws open along local y
    com = torus_com(q, env, p.torus_first)
    goal = tip_pos
    jaw = float(0.0)
    spin = float(0.0)
    handle = wp.vec3(0.0)  # discrete: the point of the tip frame that the goal is for (the tip, or the held node)
    if grasped[env] != 0:
        closing[env] = 0  # discrete PICK: a grasp ends the closing
    if grasped[env] == 0:
        anchor[env] = tip_pos  # discrete: the lift goes straight up from where the grasp happens
        # the ring point whose tube runs across the jaw opening: the centre plus the ring radius along the opening
        # (horizontal), on the side nearer the tip; its height is that of the nearest node
        across = wp.normalize(wp.vec3(opening[0], 0.0, opening[2]))
        radius = float(0.0)
        for i in range(_NODES):
            x = q[env, p.torus_first + i] - com
            radius += wp.sqrt(x[0] * x[0] + x[2] * x[2])
        radius = radius / float(_NODES)
        side = wp.where(wp.dot(tip_pos - com, across) >= 0.0, 1.0, -1.0)
        point = com + across * (side * radius)
        best = float(1.0e9)
        for i in range(_NODES):
            x = q[env, p.torus_first + i]
            d = (x[0] - point[0]) * (x[0] - point[0]) + (x[2] - point[2]) * (x[2] - point[2])
            if d < best:
                best = d
                point = wp.vec3(point[0], x[1], point[2])
        hold = point - axis * hold_depth  # tip position that puts the point hold_depth along the jaws
        lateral = wp.sqrt((hold[0] - tip_pos[0]) * (hold[0] - tip_pos[0]) + (hold[2] - tip_pos[2])
                          * (hold[2] - tip_pos[2]))
        goal = hold
        if discrete != 0:
            goal, jaw = discrete_pick(q, env, p.torus_first, rcm[env, 0], ptsd[env, 0], point, jaw_angle[env, 0],
                                      open_angle, hold_depth, clearance, discrete_step, closing)
        elif lateral < 0.003 and wp.abs(hold[1] - tip_pos[1]) < 0.0015:
            jaw = -60.0  # in place: close (the grasp happens below the grasp threshold)
        else:
            opened = jaw_angle[env, 0] >= open_angle - 0.5
            if not opened:
                jaw = open_angle - jaw_angle[env, 0]
            if lateral > 0.003 or not opened:
                goal = wp.vec3(hold[0], wp.max(hold[1] + clearance, tip_pos[1]), hold[2])  # above it first
    elif task.phase[env] == PICK:
        goal = tip_pos + wp.vec3(0.0, p.lift_height - com[1] + 0.005, 0.0)  # lift
        if discrete != 0:
            # straight up from where the grasp happened: discrete steps leave the vertical by up to a step, and a
            # goal above the current tip would let the lift drift along the tilted shaft (depth steps), dragging a
            # ring that lies around a peg against it
            goal = wp.vec3(anchor[env][0], goal[1], anchor[env][2])
    else:
        peg = nearest_peg(task, env, com)
        if discrete != 0 and attach_body[env, 0] >= 0:
            # the held node in the tip frame, where the jaw holds it (the jaw angle does not change while it holds;
            # a torus dropped in PLACE has no attachment: the tip itself goes to the goal)
            jaw_pose = body_q[env, attach_body[env, 0]]
            handle = wp.transform_point(wp.transform_inverse(tip), wp.transform_point(jaw_pose, attach_offset[env, 0]))
        lowest = float(1.0e9)
        highest = float(-1.0e9)
        for i in range(_NODES):
            lowest = wp.min(lowest, q[env, p.torus_first + i][1])
            highest = wp.max(highest, q[env, p.torus_first + i][1])
        # a held stiff ring sags a few mm, a soft one hangs as a loop ~45 mm tall: tell them apart by the height
        if stage[env] == HOOK_CARRY and highest - lowest < 2.0 * TORUS_RADIUS:
            goal, spin = place_level_ring(q, env, p, tip, rcm[env, 0], com, peg, lowest, highest, clearance, descent,
                                          far_peg, wp.where(discrete != 0, 0.0035, 0.002), discrete,
                                          p.bounds.state_high[3], depth_margin, spin_margin, max_shift)
        else:
            # the held node moves with the tip; it need not lie at the grasp centre (a grasp keeps the node's offset
            # in the jaw: after PICK it lies ~7 mm farther along the jaws). Discrete: where the jaw holds it (the
            # node lags when the board or the peg stops it, and a goal relative to the node would then run away
            # with the tip, pressing the node into the board until the grasp tears)
            held = q[env, attach_particle[env, 0]]
            if discrete != 0:
                held = wp.transform_point(tip, handle)
            goal = hook_hanging_loop(q, env, p, tip, rcm[env, 0], held, com, peg, lowest, hook_far, hook_near,
                                     clearance, cross_height, hold_height, swing_rate, max_swing, arrived[env], stage,
                                     heading, swing)
    # at most max_step per step along the straight line to the goal (saturated PTSD errors would move the tip on
    # arcs about the RCM and drag the torus into the board)
    move = goal - tip_pos
    if wp.length(move) > max_step:
        move = move * (max_step / wp.length(move))
    target = point_to_ptsd(rcm[env, 0], tip_pos + move, ptsd[env, 0][2])
    s = ptsd[env, 0]
    error_out[env, 0] = target[0] - s[0]
    error_out[env, 1] = target[1] - s[1]
    error_out[env, 2] = spin
    error_out[env, 3] = target[3] - s[3]
    error_out[env, 4] = jaw
    if discrete != 0:
        # the goal moves the held node in PLACE (a pan or tilt step also turns it about the tip, so a goal for the
        # tip would shift with every step), else the tip
        point = wp.transform_point(tip, handle)
        goal = point + (goal - tip_pos)
        # that point chases a reference that moves like the continuous tip, at most max_step per step along the
        # straight line to the goal. Discrete steps are skewed to that line (a pan step also moves the point up or
        # down, by 2-4 mm); chasing the goal itself, or a point a leg ahead, lets their sideways errors add up, and
        # jerking a hanging loop at full speed swings it: its strands then land on the peg's top (soft Place, CPU,
        # 96 episodes: 27 % chasing the goal, 68 / 85 / 95 / 88 % with a reference at 2 / 1.5 / 1 / 0.7 mm per
        # step; slower runs out of time)
        if episode_length[env] == 0 or wp.length(ref[env] - point) > 0.006:
            ref[env] = point  # a start, or a limit held the tip back: start over from it
        lead = goal - ref[env]
        if wp.length(lead) > max_step:
            lead = lead * (max_step / wp.length(lead))
        ref[env] = ref[env] + lead
        choice = discrete_command(rcm[env, 0], s, handle, ref[env], spin, jaw, discrete_step, jaw_step, p.bounds,
                                  episode_length[env] % 2)
        action_out[env] = choice[0]
        # arrived: the reference is at the goal and no step gets nearer (not yet for a stage that began this step)
        reached = choice[1] != 0 and wp.length(goal - ref[env]) < 1.0e-6 and stage[env] == was
        arrived[env] = wp.where(reached, 1, 0)


# ---------------------------------------------------------------------------- env
class PickAndPlaceEnv(BatchedEnv):
    """LapGym's PickAndPlaceEnv, batched. See the module docstring and ``PickAndPlaceConfig``.

    Actions: 5, the grasper's PTSD then its jaw angle over their maximum speeds. Discrete: ``Discrete(11)``.

    Privileged critic observation (``privileged_critic=True``): the policy values, the grasp centre to COM offset
    and the COM to nearest active peg target offset (over the workspace diagonal; 3 + 3), and the phase (1).
    """

    config_class = PickAndPlaceConfig
    task_name = "PickAndPlace"
    rewards = REWARDS
    supported_observations = ("STATE", "RGB", "RGBD", "DEPTH")
    expert = "lapwarp.tasks.deformable_manipulation.pick_and_place:PickAndPlaceExpert"
    gpu_chain_block_links = 16  # PickAndPlace 716k -> 851k env-steps/s (H100, 4,096 envs)
    # the block (PCR) chain solve over packs (it takes precedence over the partitioned one): the expert's step
    # 1,106,202 -> 1,785,039 env-steps/s (H200, 4,096 envs, same call, thirty-second session)
    gpu_chain_solver = "pcr"
    cfg: PickAndPlaceConfig

    def _build(self) -> World:
        cfg, n, dev = self.cfg, self.num_envs, self.wp_device
        builder = SceneBuilder(gravity=(0.0, -cfg.gravity, 0.0))
        beam_radius, mass = cfg.torus_parameters
        ring = rod_circle(TORUS_RADIUS, NODES, center=(0.0, TUBE_RADIUS, 0.0), normal=(0.0, 1.0, 0.0))
        length = NODES * float(np.linalg.norm(ring[1] - ring[0]))
        self.torus = builder.add_rod(ring, radius=beam_radius, density=mass / (math.pi * beam_radius**2 * length),
                                     youngs_modulus=cfg.youngs_modulus, closed=True, damping=cfg.torus_damping,
                                     inertia_scale=cfg.torus_inertia_scale, name="torus")
        self.rest_ring = ring
        jaw = dict(jaw_speed_deg=cfg.jaw_speed, jaw_discrete_speed_deg=cfg.jaw_discrete_speed,
                   jaw_start_deg=cfg.jaw_start)
        self.rig = InstrumentRig([InstrumentSpec(name="gripper", tpsd=cfg.gripper_tpsd(), shape="grasper", **jaw)],
                                 builder)
        world = builder.finalize(num_envs=n, device=str(dev), substeps=cfg.physics_substeps, seed=cfg.seed,
                                 attachment_capacity=1)
        self.rig.finalize(world)
        self.contact = c = ContactSystem(world, capacity=cfg.contact_capacity, body_ignore_mask=True)
        group = c.add_particle_group(self.torus, radius=TUBE_RADIUS, segments=True)
        up = (0.0, 0.0, 0.0, -math.sqrt(0.5), 0.0, 0.0, math.sqrt(0.5))  # local z -> world y
        c.add_plane(transform=up, name="board", mu_static=cfg.friction)
        half = 0.5 * (PEG_TOP - PEG_BOTTOM)
        for k, (x, z) in enumerate(PEGS):
            c.add_cylinder(PEG_RADIUS, half, transform=(x, PEG_BOTTOM + half, z, *up[3:]), name=f"peg{k}",
                           mu_static=cfg.friction)
        c.add_particle_contact([(self.torus, TUBE_RADIUS)], skip_links=2, mu_static=cfg.friction, name="torus")
        self.rig.add_colliders(c, mu_static=cfg.friction, groups=[group])
        c.finalize()
        self.grasp = self.rig.add_grasping("gripper", c, groups=[group], grasp_threshold=cfg.grasp_threshold,
                                           release_threshold=cfg.grasp_threshold, slots=1,
                                           hold_up=(0.0, 1.0, 0.0), jaws_pass_while_grasped=True)

        P, T = cfg.num_active_pegs, cfg.num_torus_tracking_points
        self.task = t = Task()
        for name, dtype in (("phase", wp.int32), ("swap_color", wp.int32), ("was_grasped", wp.int32),
                            ("last_tip", wp.vec3), ("last_center_distance", float), ("last_lift", float),
                            ("had_lift", wp.int32), ("last_peg_distance", float)):
            setattr(t, name, wp.zeros(n, dtype=dtype, device=dev))
        t.pegs = wp.zeros((n, P), dtype=wp.int32, device=dev)
        t.last_tracking = wp.zeros((n, max(T, 1)), dtype=float, device=dev)
        self._tracking = wp.array(tracking_nodes(T), dtype=wp.int32, device=dev)
        low, high = cfg.workspace
        self.params = p = Params()
        p.bounds, p.torus_first = self.rig.bounds(low, high), self.torus.particle_start
        p.segment_first = self.torus.segment_start
        p.lift_height, p.only_pick = cfg.minimum_lift_height, int(cfg.only_learn_pick)
        p.block_unstable, p.control_dt = int(cfg.block_done_when_unstable), cfg.time_step * cfg.frame_skip
        p.randomize_position, p.start_grasped = int(cfg.randomize_torus_position), int(cfg.start_grasped)
        p.randomize_color = int(cfg.randomize_color)
        p.jaw_low, p.jaw_high = self.rig.shapes[0].angle_limits
        self._settle_bank(world)
        p.bank_size = self.bank_q.shape[0]
        return world

    # ------------------------------------------------------------------ the bank of settled tori
    def _settle_bank(self, world: World) -> None:
        """Simulate the settled torus starts once (see the module docstring): rounds of ``num_envs`` drops (one
        grasped start with ``start_grasped``), each settling ``settle_steps`` physics steps with the grasper at its
        noise-free start; a drop still moving faster than 25 mm/s is dropped again (sofa_env's rule)."""
        cfg, n, dev = self.cfg, self.num_envs, self.wp_device
        size = max(cfg.torus_bank_size, n) if cfg.randomize_torus_position else 1
        rng = numpy_rng(cfg.seed)
        all_envs = wp.ones(n, dtype=wp.int32, device=dev)
        self.rig.reset(all_envs, None)  # the noise-free start
        self._bank_tip = wp.transform(*self.rig.instruments.pose.numpy()[0, 0])
        first, S = self.torus.particle_start, self.torus.segment_start
        bank_q, bank_sq = [], []
        rest_q = world.state.particle_q.numpy()[0, first:first + NODES].copy()
        rest_sq = world.state.segment_q.numpy()[0, S:S + NODES].copy()
        for _round in range(8 * math.ceil(size / n) + 8):
            q = world.state.particle_q.numpy()
            sq = world.state.segment_q.numpy()
            for e in range(n):
                q[e, first:first + NODES], sq[e, S:S + NODES] = self._drop_pose(rest_q, rest_sq, rng)
            world.state.particle_q.assign(q)
            world.state.segment_q.assign(sq)
            world.state.particle_qd.zero_()
            world.state.segment_qd.zero_()
            if cfg.start_grasped:
                self.grasp.start_grasped(first + START_GRASP_NODE, all_envs)
            for _ in range(cfg.settle_steps):
                world.step(cfg.time_step)
            q, sq = world.state.particle_q.numpy(), world.state.segment_q.numpy()
            speed = np.linalg.norm(world.state.particle_qd.numpy()[:, first:first + NODES], axis=2).mean(axis=1)
            held = self.grasp.grasped.numpy()
            for e in np.nonzero((speed < SETTLED_SPEED) & (held > 0 if cfg.start_grasped else True))[0]:
                # copies: on the CPU ``numpy()`` is a view of the live state, which the next round overwrites
                bank_q.append(q[e, first:first + NODES].copy())
                bank_sq.append(sq[e, S:S + NODES].copy())
            if len(bank_q) >= size:
                break
        if len(bank_q) < size:
            raise RuntimeError(f"only {len(bank_q)} of {size} torus drops settled below {SETTLED_SPEED} m/s in "
                               f"{cfg.settle_steps} steps; raise settle_steps")
        self.bank_q = wp.array(np.asarray(bank_q[:size], np.float32), dtype=wp.vec3, device=dev)
        self.bank_segment_q = wp.array(np.asarray(bank_sq[:size], np.float32), dtype=wp.quat, device=dev)
        world.reset(all_envs)  # the initial state again (the task reset writes each env's torus)

    def _drop_pose(self, rest_q: np.ndarray, rest_sq: np.ndarray, rng) -> tuple[np.ndarray, np.ndarray]:
        """The torus before settling: flat, its COM at 40 mm height above a drawn (or sofa_env's) x, z; for
        ``start_grasped`` flat with node ``START_GRASP_NODE`` at the jaws' grasp centre, across the jaw opening."""
        if self.cfg.start_grasped:
            tip = self._bank_tip
            center = np.asarray(wp.transform_point(tip, wp.vec3(0.0, 0.0, GRASP_CENTER)))
            across = np.asarray(wp.transform_vector(tip, wp.vec3(0.0, 1.0, 0.0)))  # the node's radius lies across
            across[1] = 0.0
            across /= np.linalg.norm(across)
            node = rest_q[START_GRASP_NODE] - rest_q.mean(axis=0)  # the node's offset from the ring's centre
            angle = math.atan2(across[2], across[0]) - math.atan2(node[2], node[0])
            rot = np.array([[math.cos(angle), 0.0, -math.sin(angle)], [0.0, 1.0, 0.0],
                            [math.sin(angle), 0.0, math.cos(angle)]])
            # rotate the ring about y so the node's radius points along the opening, then put the node at the centre
            x = (rest_q - rest_q.mean(axis=0)) @ rot.T
            x += center - x[START_GRASP_NODE]
            quat = wp.quat_from_matrix(wp.mat33(*rot.flatten()))
            sq = np.asarray([np.asarray(quat * wp.quat(*s)) for s in rest_sq])
            return x, sq
        if self.cfg.randomize_torus_position:
            xz = rng.uniform(-0.08, 0.08, size=2)
        else:
            xz = np.array([0.04, -0.0035])
        return rest_q - rest_q.mean(axis=0) + np.array([xz[0], DROP_HEIGHT, xz[1]]), rest_sq

    # ------------------------------------------------------------------ BatchedEnv hooks
    def _checked_state(self) -> list[wp.array]:
        return [*super()._checked_state(), self.task.last_tip]

    def _observation_layout(self) -> ObservationLayout:
        # torus points can be pushed a little past the workspace box: [-2, 2]
        T, P = self.cfg.num_torus_tracking_points, self.cfg.num_active_pegs
        return OBS.layout(grasped=(1, 0.0, 1.0), ptsdj=(5, -1.0, 1.0), pose=(7, -1.0, 1.0), com=(3, -2.0, 2.0),
                          tracking=(3 * T, -2.0, 2.0), pegs=(2 * P, -1.0, 1.0))

    def _critic_layout(self) -> ObservationLayout:
        return self.obs_layout.extend(CRITIC, grasp_to_com=(3, -2.0, 2.0), com_to_peg=(3, -2.0, 2.0),
                                      phase=(1, 0.0, 1.0))

    def _features(self, env_mask: wp.array, mode: int, features_out: wp.array2d) -> None:
        s, rig = self.world.state, self.rig
        launching.launch(eval_pick_and_place, dim=self.num_envs,
                         inputs=[env_mask, mode, s.particle_q, s.particle_qd, rig.pose, rig.jaw_angle, rig.flags,
                                 self.grasp.grasped, self._tracking, self.params, self.task], outputs=[features_out],
                         device=self.wp_device)

    def _compute_features(self, env_mask: wp.array, features_out: wp.array2d) -> None:
        # no declared delta features (sofa_env's deltas are gated by phase and one is a min of per-node changes):
        # the base evaluates this once per step, which also advances the phase and the deltas' history
        self._features(env_mask, 1 if features_out is self.features else 0, features_out)

    def _reset_task(self, env_mask: wp.array) -> None:
        w, s = self.world, self.world.state
        self.rig.reset(env_mask, w.rng)
        launching.launch(reset_pick_and_place, dim=self.num_envs,
                         inputs=[env_mask, w.rng, self.params, self.bank_q, self.bank_segment_q, self._bank_tip,
                                 self.rig.pose, self.task],
                         outputs=[s.particle_q, s.particle_qd, s.segment_q, s.segment_qd], device=self.wp_device)
        self.grasp.start_grasped(self.torus.particle_start + START_GRASP_NODE if self.cfg.start_grasped else -1,
                                 env_mask)
        self._features(env_mask, 2, self.features)

    def _compute_observations(self) -> None:
        s, rig = self.world.state, self.rig
        launching.launch(observe_pick_and_place, dim=self.num_envs,
                         inputs=[s.particle_q, rig.ptsd, rig.pose, rig.jaw_angle, self.grasp.grasped, self._tracking,
                                 self.params, self.task, self.obs_layout.columns, self.critic_layout.columns,
                                 int(self.cfg.privileged_critic)], outputs=[self.obs_frame, self.critic_frame],
                         device=self.wp_device)

    # ------------------------------------------------------------------ visuals
    def _build_visual_scene(self) -> VisualScene:
        """The board (wood, 200 x 200 x 10 mm), the pegs (r = 5 mm, y in [-10, 20] mm; each drawn red and blue, the
        copy of the wrong colour hidden), the torus (a 3.5 mm tube, in the active colour) and the grasper; sofa_env's
        camera at (0, 150, -160) mm looking at the board, vertical FoV 60 degrees, near 1 mm, far 350 mm."""
        n, dev = self.num_envs, self.wp_device
        static = wp.full((n, 1), wp.transform_identity(), dtype=wp.transform, device=dev)
        board = trimesh.creation.box(extents=(0.2, 0.01, 0.2))
        board.apply_translation((0.0, -0.005, 0.0))
        objects = [VisualObject("board", "rigid", (0.62, 0.45, 0.27), 1, board.vertices, board.faces, static)]
        peg = trimesh.creation.cylinder(radius=PEG_RADIUS, height=PEG_TOP - PEG_BOTTOM, sections=16)
        peg.apply_transform(trimesh.transformations.rotation_matrix(-math.pi / 2, (1, 0, 0)))
        peg.apply_translation((0.0, 0.5 * (PEG_TOP + PEG_BOTTOM), 0.0))
        self._red_pegs = wp.zeros((n, len(PEGS)), dtype=wp.transform, device=dev)
        self._blue_pegs = wp.zeros((n, len(PEGS)), dtype=wp.transform, device=dev)
        objects.append(VisualObject("pegs_red", "rigid", RED, 2, peg.vertices, peg.faces, self._red_pegs))
        objects.append(VisualObject("pegs_blue", "rigid", BLUE, 3, peg.vertices, peg.faces, self._blue_pegs))
        self._ring = wp.zeros((n, NODES + 1), dtype=wp.vec3, device=dev)
        self._red_segments = wp.ones((n, NODES), dtype=wp.int32, device=dev)
        self._blue_segments = wp.zeros((n, NODES), dtype=wp.int32, device=dev)
        objects.append(VisualObject("torus_red", "rod", RED, 4, points=self._ring, radius=TUBE_RADIUS,
                                    face_active=self._red_segments))
        objects.append(VisualObject("torus_blue", "rod", BLUE, 4, points=self._ring, radius=TUBE_RADIUS,
                                    face_active=self._blue_segments))
        objects += self.rig.visual_objects([(0.72, 0.74, 0.78)], first_segmentation_id=5)
        pose = look_at_transform((0.0, 0.15, -0.16), (0.0, -0.01, 0.0), up=(0.0, 1.0, 0.0))
        camera = CameraSpec(poses=wp.array([pose] * n, dtype=wp.transform, device=dev), fov_deg=60.0, near=0.001,
                            far=0.35)
        return VisualScene(camera=camera, objects=objects, background=(0.05, 0.05, 0.08))

    def update_visuals(self) -> None:
        if self._visual_scene is None:
            return
        launching.launch(place_scene_visuals, dim=self.num_envs,
                         inputs=[self.world.state.particle_q, self.params, self.task],
                         outputs=[self._ring, self._red_segments, self._blue_segments, self._red_pegs, self._blue_pegs],
                         device=self.wp_device)

    # ------------------------------------------------------------------ privileged access (experts, tests)
    def torus_positions(self) -> torch.Tensor:
        """Torus node positions ``(N, 29, 3)`` (a zero-copy view)."""
        first = self.torus.particle_start
        return wp.to_torch(self.world.state.particle_q)[:, first:first + NODES]

    def privileged_state(self) -> dict[str, torch.Tensor]:
        """Torch views: torus nodes ``(N, 29, 3)``, its COM ``(N, 3)`` (fresh), phase, grasped, active pegs
        ``(N, P)``, the active pegs' targets ``(N, P, 3)`` (fresh) and the grasper's tip pose ``(N, 7)``."""
        t = self.task
        nodes = self.torus_positions()
        pegs = wp.to_torch(t.pegs).long()
        grid = torch.tensor([(x, PEG_TARGET_Y, z) for x, z in PEGS], dtype=torch.float32, device=nodes.device)
        return dict(nodes=nodes, com=nodes.mean(dim=1), phase=wp.to_torch(t.phase),
                    grasped=wp.to_torch(self.grasp.grasped), pegs=wp.to_torch(t.pegs), peg_targets=grid[pegs],
                    tip=wp.to_torch(self.rig.pose)[:, 0])


# ---------------------------------------------------------------------------- expert
class PickAndPlaceExpert(Expert):
    """Scripted grasper from the privileged state. PICK: above the torus point whose tube runs across the jaw opening
    (the COM plus the ring radius along the opening, on the tip's side), with the jaws at ``open_angle`` (sofa_env's
    11 degree start already fits the 7 mm tube ``hold_depth`` = 22 mm along the jaws), it descends until that point
    lies ``hold_depth`` along the jaws and closes them (the grasp happens on contact below the grasp threshold), then
    lifts the COM to the lift height. PLACE, a ring that stays level when held (the stiff torus): it carries the COM
    over the nearest active peg with the torus ``clearance`` above the pegs' tops, turning the torus about the held
    point (spin) for pegs farther than ``far_peg`` from the RCM so that its COM lies beyond the grasp (the shaft's
    depth limit reaches them only so), and lowers it around the peg by at most ``descent`` per step. PLACE, a loop
    that hangs from the grasp (the soft torus; lowered onto the peg it lands on the top and slides down around the
    peg only about every other time): it lays the loop's fold on the board ``hook_far`` beyond the peg, crosses over
    the peg's top to ``hook_near`` before it (the held node at ``cross_height``) and pulls the held node down to
    ``hold_height``, so the strands slide off the top around both sides of the peg, swinging about the peg by
    ``swing_rate`` per step (at most ``max_swing``) while a strand stays on the top (see ``hook_hanging_loop``).
    Continuous actions follow the straight line to each goal in legs of ``max_step`` (saturated PTSD errors would
    sweep the tip on arcs about the RCM).

    Discrete actions (``Discrete(11)``: one PTSD or jaw component by a whole step, or nothing) follow the same plan
    with three changes, each against a way the base class's rule (move the component with the largest error in
    steps) failed (CPU, 16 envs, seeds 0 and 1: Pick 56 %, Place 25 %, Pick-and-Place 16 %, soft; 34 %, 13 %, 16 %,
    stiff): the largest PTSD error first sweeps the tip on arcs (a far peg's 50 depth steps first push a held torus
    into the board) and descents along the tilted shaft oscillate in and out of the PICK goal's lateral tolerance.
    (1) The tip (in PLACE: the held node) takes the pan, tilt or depth step that brings it nearest to a reference
    point moving like the continuous tip, at ``max_step`` = 1 mm per step (see ``expert_commands``). (2) PICK aims
    the shaft at the torus (pan and tilt) before advancing along it (depth only), on a shaft line that the lattice
    of discrete steps reaches and that passes within a fraction of a millimetre of the tube (``lattice_aim``: a step
    moves the line 2.5-4 mm at the torus, and jaws off centre by that push the tube away instead of grasping it);
    jaws that shut on nothing open again, and the lift goes straight up from the grasp. (3) Tolerances the lattice
    may not meet: a stiff ring is lowered once its COM is within 3.5 mm of the peg (2 mm), the hook's crossing ends
    where no step gets nearer. (4) A far peg needs the held stiff ring turned (up to ~180 degrees at 1.5 degrees a
    step, taking turns with motion: episodes ran out of steps): it turns only until the shaft's depth limit
    (``depth_margin`` short) reaches the grasp with the COM over the peg (``level_ring_slack``), not until the COM
    lies straight beyond the grasp, and, at a peg at the very edge of reach, the COM aims up to ``max_shift`` short
    of it, towards the RCM (``place_level_ring``); stiff Place, CPU, 64 envs, seeds 0-5 (384 first episodes):
    92.2 % before, 99.5 % after. Jaw steps go first, spin and motion take turns (``discrete_command``). With them
    (CPU, 32 envs, seeds 0-5, 192 first episodes each): Pick 97 % / 99 %, Place 95 % / 95 %, Pick-and-Place 97 % /
    97 % (soft / stiff), taking up to about twice the continuous expert's steps (Place: 188 / 144 against 109 / 75)."""

    def __init__(self, env: PickAndPlaceEnv, open_angle: float = 11.0, hold_depth: float = 0.022,
                 clearance: float = 0.006, descent: float = 0.004, far_peg: float = 0.11, hook_far: float = 0.011,
                 hook_near: float = 0.012, cross_height: float = 0.03, hold_height: float = 0.005,
                 swing_rate: float = 0.05, max_swing: float = 1.2, max_step: float | None = None,
                 depth_margin: float = 0.003, spin_margin: float = 6.0, max_shift: float = 0.003):
        super().__init__(env)
        # discrete actions: how far short of the depth limit the spin of a level ring aims (m), and the smallest
        # heading error (deg) that turns it (see ``place_level_ring``)
        self.depth_margin, self.spin_margin = float(depth_margin), math.radians(spin_margin)
        self.max_shift = float(max_shift)  # discrete: how far short of a peg at the edge of reach the COM may aim
        self.open_angle, self.hold_depth, self.clearance = float(open_angle), float(hold_depth), float(clearance)
        self.descent, self.far_peg = float(descent), float(far_peg)
        self.hook = tuple(float(x) for x in (hook_far, hook_near, cross_height, hold_height, swing_rate, max_swing))
        # discrete actions: the speed of the reference point their tip chases (slower than the continuous legs: a
        # discrete step jerks the tip by up to 4 mm, see ``expert_commands``)
        self.max_step = float(max_step if max_step is not None else (0.001 if env.is_discrete else 0.0015))
        n, dev = env.num_envs, env.wp_device
        self.error = wp.zeros((n, 5), dtype=float, device=dev)
        # per env: the hooking stage, its crossing direction and the swing about the peg (reset by the kernel at an
        # episode's first step and whenever the torus is not held in PLACE)
        self.stage = wp.zeros(n, dtype=wp.int32, device=dev)
        self.heading = wp.zeros(n, dtype=wp.vec3, device=dev)
        self.swing = wp.zeros(n, dtype=float, device=dev)
        # discrete actions only: the tip where the grasp happened (the lift goes straight up from it), whether the
        # jaws are closing in PICK, whether the tip arrived at the last goal, the reference point it chases
        self.anchor = wp.zeros(n, dtype=wp.vec3, device=dev)
        self.closing = wp.zeros(n, dtype=wp.int32, device=dev)
        self.arrived = wp.zeros(n, dtype=wp.int32, device=dev)
        self.ref = wp.zeros(n, dtype=wp.vec3, device=dev)
        self.action = wp.zeros(n, dtype=wp.int32, device=dev)
        self.step_size = self.rig_step_size()
        # what one discrete action moves: PTSD (rad, rad, rad, m) and the jaw (deg)
        moved = (self._discrete_step * self.step_size).tolist()
        self.discrete_step, self.jaw_step = wp.vec4(*moved[:4]), moved[4]

    def __call__(self, obs=None) -> torch.Tensor:
        env, rig, s = self.env, self.env.rig, self.env.world.state
        with env._torch_stream_scope():
            launching.launch(expert_commands, dim=env.num_envs,
                             inputs=[s.particle_q, rig.ptsd, rig.pose, rig.rcm, rig.jaw_angle, env.grasp.grasped,
                                     s.attach_particle, s.attach_body, s.attach_offset, s.body_q, env.params,
                                     env.task, env.episode_length, self.open_angle, self.hold_depth, self.clearance,
                                     self.descent, self.far_peg, *self.hook, self.max_step, self.depth_margin,
                                     self.spin_margin, self.max_shift, int(env.is_discrete),
                                     self.discrete_step, self.jaw_step],
                             outputs=[self.stage, self.heading, self.swing, self.anchor, self.closing, self.arrived,
                                      self.ref, self.error, self.action], device=env.wp_device)
        if env.is_discrete:  # chosen by the kernel (``discrete_command``), not by ``policy_actions``
            return wp.to_torch(self.action).long()
        return self.policy_actions(wp.to_torch(self.error) / self.step_size)
