"""RopeCuttingEnv: cut the highlighted rope with the electrocautery hook (sofa_env's RopeCuttingEnv; task-cards §5).

``num_ropes`` ropes are stretched between two walls 100 mm apart. One rope is active (green); the agent moves a
pivotized cautery hook (TPSD) and switches it on to cut it. Then another intact rope becomes active; after
``num_ropes_to_cut`` correct cuts the task is successful, and it fails as soon as so many wrong ropes are cut that
the remaining intact ropes cannot make up the correct cuts still missing (the only task that ends on failure).

Physics (SI; sofa_env's millimetres converted, gravity -z): each rope is 20 nodes (19 segments) with both ends fixed
on the walls, total mass 10 mg per node pair (10 g per rope), springs of ``rope_stiffness`` (1e4 N/m) whose rest
length is 0.2 x the segment length (sofa_env's ``contraction_ratio`` 0.8): the ropes are strongly pre-tensioned and a
cut rope snaps back to the walls. lapwarp models them as Cosserat rods (``SceneBuilder.add_rod`` with
``stretch_rest_scale=0.2``): the stretch springs are solved exactly per rope (the chain solver), bending is negligible
against the tension. Cutting (``lapwarp.cutting``): an active hook removes every segment within 0.8 mm of its hook
capsules (0.8 mm radius, sofa_env's carving distance); each rope is one label, so a rope counts as cut in a step
when any of its segments went (sofa_env: any topology change of that rope). The hook's capsules collide with the
ropes (0.5 mm contact radius), so an inactive hook pushes them.

Episode logic (sofa_env's ``RopeCuttingEnv``): reset draws every rope's end points on the walls (uniform on each wall
face, at least ``min_rope_distance`` between every pair of ropes, from the env's own RNG stream), an active rope
uniformly, and puts the hook at its start state. STATE observation (12 + 9 (R + 1)): PTSD normalised to [-1, 1] by
the state limits (4), activation (1), hook pose (position normalised by the workspace, quaternion xyzw; 7), three
tracking points (nodes 0, 9, 19) of every rope normalised by the workspace (9 R), then the active rope's three points
again (9). A point whose segments are all cut reads as the workspace's high corner (1, 1, 1), as in sofa_env.
Reward features (Table A): distance from the hook's cutting centre to the active rope (its nearest node, normalised by
the workspace diagonal, and its change), cut active rope, cut inactive ropes (count), limit violations, success and
failure.

Deviations from sofa_env (deliberate): rope layouts come from each env's seeded RNG stream (sofa_env uses the
global unseeded ``np.random``, so episodes were not reproducible); sofa_env's layout rule (1,000 draws per rope, then
everything anew) is bounded at ``LAYOUT_RESTARTS`` restarts, after which the last attempt keeps each rope's best draw
(in a Monte Carlo run with 10 ropes at 20 mm depth the most restarts needed were 24), and one thread block per env
tests 64 draws at once (the first acceptable one in draw order: the same rule and distribution); the spring
rest length is 0.2 x the segment length of a 100 mm rope for every rope (sofa_env: of each rope's own length; the
tension of a 140 mm diagonal rope is then 8 % higher than there); ropes do not collide with each other (sofa_env
lets them; they are 10 mm apart and taut); the discrete action space works (sofa_env's is broken) and moves like
the continuous one; no settle steps are needed (ropes start at rest on their lines).
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
from lapwarp.builder import SceneBuilder
from lapwarp.config import PTSD, Count, EnvConfig, NonNegative, Positive, PositiveInt, Range
from lapwarp.contact import ContactSystem
from lapwarp.cutting import CuttingSystem
from lapwarp.env import BatchedEnv
from lapwarp.experts import Expert
from lapwarp.instruments import TPSDConfig, tpsd_from_config
from lapwarp.kernels.geometry import closest_segment_segment
from lapwarp.kernels.kinematics import point_to_ptsd
from lapwarp.tasks.deformable import rope_newton_tolerance
from lapwarp.tasks.rig import (
    CAUTER_CUTTING_CENTER,
    STATE_LIMITS_VIOLATED,
    WORKSPACE_VIOLATED,
    InstrumentRig,
    InstrumentSpec,
    RigBounds,
    count_flag,
    cutting_center,
    place_hook_tools,
    write_unit_point,
    write_unit_ptsd,
)
from lapwarp.tasks.spec import Feature, ObservationLayout, ObservationSpec, RewardSpec
from lapwarp.tasks.targets import draw_index, draw_index_where
from lapwarp.visuals import CameraSpec, VisualObject, VisualScene
from lapwarp.world import World

wp.set_module_options({"enable_backward": False})

REWARDS = RewardSpec(
    Feature("distance_cauter_active_rope", 0.0),
    Feature("delta_distance_cauter_active_rope", -5.0, delta_of="distance_cauter_active_rope"),
    Feature("cut_active_rope", 5.0),
    Feature("cut_inactive_rope", -5.0),
    Feature("workspace_violation", 0.0),
    Feature("state_limits_violation", 0.0),
    Feature("successful_task", 10.0),
    Feature("failed_task", -20.0),
    failure="failed_task",
)
F = REWARDS.F
OBS = ObservationSpec("ptsd", "active", "pose", "ropes", "active_rope")
CRITIC = OBS.extend("rope_cut", "offset_to_active", "distance_to_active")

NODES = 20  # per rope, both ends included (sofa_env)
SEGMENTS = NODES - 1
TRACKED = (0, 9, 19)  # tracking nodes of every rope
INTACT, CUT = 0, 1
LAYOUT_TRIES = wp.constant(1000)
LAYOUT_RESTARTS = wp.constant(100)
LAYOUT_LANES = 64  # draws tested at once per env (one thread block per env; one lane on the CPU)
_TRACKED = wp.constant(wp.vec3i(*TRACKED))
_NODES = wp.constant(NODES)
_MIDDLE = wp.constant(wp.vec2i(SEGMENTS // 4, SEGMENTS - SEGMENTS // 4))  # the expert's segments: the middle half
ACTIVE_COLOR, IDLE_COLOR = (0.0, 1.0, 0.0), (1.0, 0.0, 0.0)


@dataclass(kw_only=True)
class RopeCuttingConfig(EnvConfig):
    """RopeCuttingEnv parameters (Table B, Table C; the paper's and sofa_zoo's values); metres, degrees, N/m, kg.

    Attributes:
        num_ropes: ropes between the walls, R (5 or 10 in the paper).
        num_ropes_to_cut: correct cuts that complete the task, C (1 or 3).
        depth: extent of the walls along y (m): 20 mm ("flat", the paper's) or sofa_env's default 50 mm.
        min_rope_distance: minimum distance between any two ropes at reset (m), 10 mm.
        rope_mass: mass of one rope (kg), 10 g.
        rope_stiffness: spring constant of every rope segment (N/m), 1e4.
        contraction_ratio: the springs' rest length is ``1 - contraction_ratio`` of a 100 mm rope's segment length.
        rope_radius: contact and drawing radius of the ropes (m).
        rope_damping: velocity damping rate of the rope nodes (1/s).
        start_ptsd: the hook's start state (deg, deg, deg, m); ``ptsd_noise``: uniform reset noise (none).
        state_low / state_high: the hook's state limits (deg, deg, deg, m).
        maximum_state_velocity: PTSD speed at action 1 (deg/s, deg/s, deg/s, m/s).
        discrete_action_magnitude: PTSD speed of a discrete action (sofa_env's discrete actions are broken; these are
            the speeds sofa_env's other PTSD tasks use).
        activation_deadzone: the activation component switches the hook on above it and off below its negative.
        carving_distance: distance (m) beyond the hook capsules within which an active hook removes rope segments.
        physics_substeps: XPBD substeps per physics step (40: see ``rope_newton_steps``).
        rope_newton_steps: Newton steps of each rope's stretch solve per sweep. A rope pre-stretched to 5x its rest
            length is strongly nonlinear: with one or two steps its transverse response overshoots and a pushed
            rope never settles (measured when the task was built: chaotic at 10-80 substeps with 1-4 steps); 6 steps
            at 40 substeps recover the taut-string sag to 1 % after a 20 mm push. Re-measured with
            ``benchmarks/rope_settle.py`` (one rope, middle third bumped 5-20 mm sideways or down): at 40 substeps 4
            steps settle within 0.2 % too, 3 do not after 20 mm, and 30 substeps need 6. The default is 4 since the
            twenty-ninth session: the step is 29 % faster than at 6 (244k against 190k env-steps/s, 4,096 envs, H200;
            5 steps: 213k), the settle test runs at this default and the scripted expert still solves 32 / 32.
        rope_newton_tolerance: (m) a rope stops its Newton steps once one corrected none of its links by this much
            (``World.rod_newton_tolerance``; the register-resident, hybrid and pcr solves only, a value with another
            chain solver raises ``ValueError``). Default 0: every step. Each step corrects the taut ropes ~10x less than
            the one before (at 1e-7 m a rope runs 3.01 of its 4 steps, CPU, the expert's episodes), but on the
            register solve the check slowed the step: H200, expert, 4,096 envs, same call, 318.2k env-steps/s at 0
            against 286.9k at 1e-7 (twice each; the check's 160 B more spill frame, sm_90). On the split solve (two
            threads per rope, RopeCutting's CUDA default since the forty-fourth session) untimed.
        contact_capacity: contact records kept per env per step (counted when exceeded, never silent).
        max_episode_steps: time limit; ``None`` = max(400, 200 C) (Table C).
    """

    max_episode_steps: PositiveInt | None = None
    num_ropes: Count(16) = 5
    num_ropes_to_cut: Count(16) = 1
    depth: Positive = 0.02
    min_rope_distance: NonNegative = 0.01
    rope_mass: Positive = 0.01
    rope_stiffness: Positive = 1.0e4
    contraction_ratio: Annotated[float, Range(ge=0.0, lt=1.0)] = 0.8
    rope_radius: Positive = 5.0e-4
    rope_damping: NonNegative = 1.0
    start_ptsd: PTSD = (45.0, 45.0, 0.0, 0.04)
    ptsd_noise: tuple[NonNegative, NonNegative, NonNegative, NonNegative] = (0.0, 0.0, 0.0, 0.0)
    state_low: PTSD = (-90.0, -90.0, -90.0, 0.0)
    state_high: PTSD = (90.0, 90.0, 90.0, 0.3)
    maximum_state_velocity: tuple[Positive, Positive, Positive, Positive] = (20.0, 20.0, 20.0, 0.02)
    discrete_action_magnitude: tuple[Positive, Positive, Positive, Positive] = (15.0, 15.0, 15.0, 0.01)
    activation_deadzone: Annotated[float, Range(ge=0.0, lt=1.0)] = 0.1
    carving_distance: NonNegative = 8.0e-4
    physics_substeps: Count(10_000) = 40
    rope_newton_steps: Count(64) = 4
    rope_newton_tolerance: NonNegative = 0.0
    contact_capacity: Count(4096) = 64

    def validate(self, reward_features, supported_observations) -> None:
        super().validate(reward_features, supported_observations)
        if self.num_ropes_to_cut > self.num_ropes:
            raise ValueError(f"num_ropes_to_cut={self.num_ropes_to_cut} exceeds num_ropes={self.num_ropes}")
        if self.max_episode_steps is None:
            self.max_episode_steps = max(400, 200 * self.num_ropes_to_cut)  # Table C
        self.cauter_tpsd()  # names the fields of a start state outside the limits

    @property
    def workspace(self) -> tuple[np.ndarray, np.ndarray]:
        """The hook's Cartesian workspace (m): between the walls, 50 mm in front of them, 10 mm behind them, and from
        10 mm below the walls to 10 mm above (sofa_env's)."""
        return np.array([-0.05, -0.05, -0.06]), np.array([0.05, self.depth + 0.01, 0.06])

    def cauter_tpsd(self) -> TPSDConfig:
        """The hook's TPSD: RCM at the workspace's (low x, low y, high z) corner, pointing down (sofa_env's)."""
        low, high = self.workspace
        return tpsd_from_config(self, rcm_position=(low[0], low[1], high[2]), rcm_euler_deg=(-180.0, 0.0, 0.0),
                                start_ptsd="start_ptsd", state_low="state_low", state_high="state_high",
                                workspace_low=tuple(low), workspace_high=tuple(high),
                                max_velocity="maximum_state_velocity",
                                discrete_magnitude="discrete_action_magnitude", ptsd_noise="ptsd_noise")


# ---------------------------------------------------------------------------- kernels
@wp.struct
class Ropes:
    """The task's per-env state: rope end points ``(N, R)`` (m), rope states (``INTACT`` / ``CUT``), the active rope,
    correct and wrong cuts so far, and where each rope's nodes and segments start in the World."""

    start: wp.array2d(dtype=wp.vec3)
    end: wp.array2d(dtype=wp.vec3)
    state: wp.array2d(dtype=wp.int32)
    active: wp.array(dtype=wp.int32)
    cut_active: wp.array(dtype=wp.int32)
    cut_inactive: wp.array(dtype=wp.int32)
    first_node: wp.array(dtype=wp.int32)
    first_segment: wp.array(dtype=wp.int32)


@wp.struct
class Params:
    """Constants of a configuration (SI units, radians)."""

    bounds: RigBounds
    num_to_cut: int


@wp.func
def node_position(q: wp.array2d(dtype=wp.vec3), live: wp.array2d(dtype=wp.int32), env: int, node: int,
                  p: Params) -> wp.vec3:
    """A rope node, or the workspace's high corner once every segment at it is cut (sofa_env's removed points)."""
    if live[env, node] == 0:
        return p.bounds.ws_high
    return q[env, node]


@wp.func
def distance_to_rope(q: wp.array2d(dtype=wp.vec3), live: wp.array2d(dtype=wp.int32), ropes: Ropes, env: int, r: int,
                     x: wp.vec3, p: Params) -> float:
    """sofa_env's distance to a rope: the nearest of its nodes (removed ones at the high corner)."""
    d = float(1.0e9)
    for i in range(_NODES):
        d = wp.min(d, wp.length(node_position(q, live, env, ropes.first_node[r] + i, p) - x))
    return d


@wp.func
def segments_left(seg_active: wp.array2d(dtype=wp.int32), ropes: Ropes, env: int, r: int) -> int:
    count = int(0)
    for i in range(_NODES - 1):
        count += seg_active[env, ropes.first_segment[r] + i]
    return count


@wp.func
def rope_gap(ropes: Ropes, env: int, count: int, a: wp.vec3, b: wp.vec3) -> float:
    """Smallest distance from the segment ``a b`` to the first ``count`` ropes of the env."""
    d = float(1.0e9)
    for o in range(count):
        oa = ropes.start[env, o]
        ob = ropes.end[env, o]
        st = closest_segment_segment(a, b, oa, ob)
        d = wp.min(d, wp.length((a + (b - a) * st[0]) - (oa + (ob - oa) * st[1])))
    return d


@wp.func
def draw_rope_line(seed: int, draw: int, depth: float) -> wp.spatial_vector:
    """Candidate ``draw`` of a reset: ends uniform on the two wall faces (x = -+50 mm, y in [0, depth],
    z in +-50 mm), as ``(a, b)``. Each draw has its own stream, so any lane can re-draw another lane's candidate."""
    s = wp.rand_init(seed, draw)
    ay = wp.randf(s) * depth
    az = -0.05 + 0.1 * wp.randf(s)
    by = wp.randf(s) * depth
    bz = -0.05 + 0.1 * wp.randf(s)
    return wp.spatial_vector(-0.05, ay, az, 0.05, by, bz)


@wp.kernel
def reset_ropes(env_mask: wp.array(dtype=wp.int32), depth: float, min_distance: float,
                rng: wp.array(dtype=wp.uint32), ropes: Ropes, q: wp.array2d(dtype=wp.vec3),
                qd: wp.array2d(dtype=wp.vec3), seg_q: wp.array2d(dtype=wp.quat), seg_qd: wp.array2d(dtype=wp.vec3)):
    """New rope lines, nodes at rest on them, and a uniformly drawn active rope; one thread block per env.

    sofa_env's layout rule: ends uniform on the two wall faces, each rope redrawn until it is ``min_distance`` from
    every rope before it, everything redrawn after ``LAYOUT_TRIES`` failed draws of one rope (at most
    ``LAYOUT_RESTARTS`` times; then the ropes keep their best draws). The block's lanes test ``block_dim`` draws at
    once and take the first acceptable one in draw order, which is the sequential rule's distribution: a thread per
    env needed up to ~10^5 sequential draws for 10 ropes and held every reset of a step that long (one lane on the
    CPU, where Warp's blocks have one thread)."""
    env, lane = wp.tid()
    if env_mask[env] == 0:
        return
    lanes = wp.block_dim()
    R = ropes.start.shape[1]
    seed = int(rng[env])  # every lane reads it before lane 0 advances it below (after the first block reduction)
    batches = (LAYOUT_TRIES + lanes - 1) // lanes
    draws = int(0)  # draws used so far in this reset (the same count in every lane)
    for attempt in range(LAYOUT_RESTARTS):
        complete = int(1)
        for r in range(R):
            best_d = float(-1.0)
            best_draw = int(-1)
            chosen = int(-1)
            for batch in range(batches):
                draw = draws + lane
                d = float(-1.0)
                if batch * lanes + lane < LAYOUT_TRIES:
                    line = draw_rope_line(seed, draw, depth)
                    d = rope_gap(ropes, env, r, wp.spatial_top(line), wp.spatial_bottom(line))
                    if d > best_d:
                        best_d = d
                        best_draw = draw
                key = lanes
                if d >= min_distance:
                    key = lane
                first = wp.tile_min(wp.tile(key))[0]
                draws += lanes
                if first < lanes:
                    chosen = draws - lanes + first
                    break
            if chosen < 0:
                if attempt < LAYOUT_RESTARTS - 1:
                    complete = 0
                    break
                # the last attempt keeps the rope's best draw: the largest gap, ties to the earliest draw
                top = wp.tile_max(wp.tile(best_d))[0]
                candidate = draws
                if best_d == top:
                    candidate = best_draw
                chosen = wp.tile_min(wp.tile(candidate))[0]
            # every lane re-draws the chosen line and writes it (the same values): each lane reads only what it
            # wrote itself, so no barrier is needed before the next rope's gap tests
            line = draw_rope_line(seed, chosen, depth)
            ropes.start[env, r] = wp.spatial_top(line)
            ropes.end[env, r] = wp.spatial_bottom(line)
        if complete != 0:
            break
    for k in range(lane, R * _NODES, lanes):
        r = k // _NODES
        i = k - r * _NODES
        a = ropes.start[env, r]
        axis = ropes.end[env, r] - a
        n = ropes.first_node[r] + i
        q[env, n] = a + axis * (float(i) / float(_NODES - 1))
        qd[env, n] = wp.vec3(0.0)
        if i < _NODES - 1:
            seg_q[env, ropes.first_segment[r] + i] = wp.quat_between_vectors(wp.vec3(0.0, 0.0, 1.0),
                                                                             wp.normalize(axis))  # d3 along it
            seg_qd[env, ropes.first_segment[r] + i] = wp.vec3(0.0)
        if i == 0:
            ropes.state[env, r] = INTACT
    if lane == 0:
        rng[env] = wp.uint32(wp.rand_init(seed, -1 - draws))  # the env's stream moves on past this reset
        ropes.active[env] = draw_index(rng, env, R)
        ropes.cut_active[env] = 0
        ropes.cut_inactive[env] = 0


@wp.kernel
def eval_rope_features(env_mask: wp.array(dtype=wp.int32), q: wp.array2d(dtype=wp.vec3),
                       live: wp.array2d(dtype=wp.int32), seg_active: wp.array2d(dtype=wp.int32),
                       pose: wp.array2d(dtype=wp.transform), flags: wp.array2d(dtype=wp.int32), ropes: Ropes, p: Params,
                       features_out: wp.array2d(dtype=float)):
    """Reward features of sofa_env's ``_get_reward_features`` (the delta: the env base)."""
    env = wp.tid()
    if env_mask[env] == 0:
        return
    a = ropes.active[env]
    d = distance_to_rope(q, live, ropes, env, a, cutting_center(pose[env, 0]), p) * p.bounds.inv_diagonal
    cut_active = int(0)
    cut_inactive = int(0)
    intact = int(0)
    for r in range(ropes.start.shape[1]):
        if ropes.state[env, r] == INTACT:
            if segments_left(seg_active, ropes, env, r) < _NODES - 1:
                if r == a:
                    cut_active = 1
                else:
                    cut_inactive += 1
            else:
                intact += 1
    done = ropes.cut_active[env] + cut_active
    success = done >= p.num_to_cut
    features_out[env, F.DISTANCE_CAUTER_ACTIVE_ROPE] = wp.clamp(d, -1.0, 1.0)
    features_out[env, F.CUT_ACTIVE_ROPE] = float(cut_active)
    features_out[env, F.CUT_INACTIVE_ROPE] = float(cut_inactive)
    features_out[env, F.WORKSPACE_VIOLATION] = float(count_flag(flags, env, WORKSPACE_VIOLATED))
    features_out[env, F.STATE_LIMITS_VIOLATION] = float(count_flag(flags, env, STATE_LIMITS_VIOLATED))
    features_out[env, F.SUCCESSFUL_TASK] = wp.where(success, 1.0, 0.0)
    features_out[env, F.FAILED_TASK] = wp.where(not success and p.num_to_cut - done > intact, 1.0, 0.0)


@wp.kernel
def update_ropes(q: wp.array2d(dtype=wp.vec3), live: wp.array2d(dtype=wp.int32), seg_active: wp.array2d(dtype=wp.int32),
                 pose: wp.array2d(dtype=wp.transform), features: wp.array2d(dtype=float), p: Params,
                 rng: wp.array(dtype=wp.uint32), ropes: Ropes, baselines: wp.array2d(dtype=float)):
    """sofa_env's bookkeeping after a cut: cut ropes leave the candidates; after a correct cut (task not yet
    complete) another intact rope becomes active and the distance delta restarts from it."""
    env = wp.tid()
    if features[env, F.CUT_ACTIVE_ROPE] == 0.0 and features[env, F.CUT_INACTIVE_ROPE] == 0.0:
        return
    for r in range(ropes.start.shape[1]):
        if ropes.state[env, r] == INTACT and segments_left(seg_active, ropes, env, r) < _NODES - 1:
            ropes.state[env, r] = CUT
    ropes.cut_active[env] = ropes.cut_active[env] + int(features[env, F.CUT_ACTIVE_ROPE])
    ropes.cut_inactive[env] = ropes.cut_inactive[env] + int(features[env, F.CUT_INACTIVE_ROPE])
    if features[env, F.CUT_ACTIVE_ROPE] == 0.0 or features[env, F.SUCCESSFUL_TASK] != 0.0:
        return
    if features[env, F.FAILED_TASK] != 0.0:
        return
    a = draw_index_where(rng, env, ropes.state, CUT, 1)
    ropes.active[env] = a
    d = distance_to_rope(q, live, ropes, env, a, cutting_center(pose[env, 0]), p) * p.bounds.inv_diagonal
    baselines[env, F.DISTANCE_CAUTER_ACTIVE_ROPE] = wp.clamp(d, -1.0, 1.0)


@wp.kernel
def observe_ropes(q: wp.array2d(dtype=wp.vec3), live: wp.array2d(dtype=wp.int32), ptsd: wp.array2d(dtype=wp.vec4),
                  pose: wp.array2d(dtype=wp.transform), active: wp.array2d(dtype=wp.int32), ropes: Ropes, p: Params,
                  o: OBS.Columns, c: CRITIC.Columns, privileged: int, obs_out: wp.array2d(dtype=float),
                  critic_out: wp.array2d(dtype=float)):
    """sofa_env's STATE order: PTSD, activation, pose, every rope's tracking points, the active rope's again."""
    env = wp.tid()
    write_unit_ptsd(obs_out, env, o.ptsd, ptsd[env, 0], p.bounds)
    obs_out[env, o.active] = float(active[env, 0])
    tf = pose[env, 0]
    write_unit_point(obs_out, env, o.pose, wp.transform_get_translation(tf), p.bounds)
    rot = wp.transform_get_rotation(tf)
    for i in range(4):
        obs_out[env, o.pose + 3 + i] = rot[i]
    R = ropes.start.shape[1]
    for r in range(R + 1):
        rope = wp.where(r < R, r, ropes.active[env])
        col = wp.where(r < R, o.ropes + 9 * r, o.active_rope)
        for k in range(3):
            x = node_position(q, live, env, ropes.first_node[rope] + _TRACKED[k], p)
            write_unit_point(obs_out, env, col + 3 * k, x, p.bounds)
    if privileged == 0:
        return
    for r in range(R):  # the critic's leading blocks are the policy's (copied by the env base)
        critic_out[env, c.rope_cut + r] = float(ropes.state[env, r])
    x = cutting_center(tf)
    a = ropes.active[env]
    best = wp.vec3(0.0)
    best_d = float(1.0e9)
    for i in range(_NODES):
        y = node_position(q, live, env, ropes.first_node[a] + i, p)
        if wp.length(y - x) < best_d:
            best_d = wp.length(y - x)
            best = y
    rel = (best - x) * p.bounds.inv_diagonal
    for i in range(3):
        critic_out[env, c.offset_to_active + i] = rel[i]
    critic_out[env, c.distance_to_active] = wp.min(best_d * p.bounds.inv_diagonal, 1.0)


@wp.kernel
def rope_colors(seg_active: wp.array2d(dtype=wp.int32), ropes: Ropes, active_out: wp.array2d(dtype=wp.int32),
                idle_out: wp.array2d(dtype=wp.int32)):
    """Thread (env, rope, segment): each rope is drawn twice (green, red); the copy of the wrong colour and the cut
    segments are masked out."""
    env, r, i = wp.tid()
    present = seg_active[env, ropes.first_segment[r] + i]
    is_active = wp.where(r == ropes.active[env], 1, 0)
    active_out[env, r * (_NODES - 1) + i] = present * is_active
    idle_out[env, r * (_NODES - 1) + i] = present * (1 - is_active)


@wp.kernel
def expert_errors(q: wp.array2d(dtype=wp.vec3), seg_active: wp.array2d(dtype=wp.int32),
                  ptsd: wp.array2d(dtype=wp.vec4), pose: wp.array2d(dtype=wp.transform),
                  rcm: wp.array2d(dtype=wp.transform), active: wp.array2d(dtype=wp.int32), ropes: Ropes,
                  switch_on: float, error_out: wp.array2d(dtype=float)):
    """PTSD error of the hook towards the active rope and the activation it wants (see ``RopeCuttingExpert``)."""
    env = wp.tid()
    a = ropes.active[env]
    x = cutting_center(pose[env, 0])
    best = wp.vec3(0.0)
    best_d = float(1.0e9)
    # nearest point on the middle half of the active rope's present segments (the wall ends may lie where the hook's
    # tip would leave its workspace)
    for i in range(_MIDDLE[0], _MIDDLE[1]):
        if seg_active[env, ropes.first_segment[a] + i] != 0:
            n0 = q[env, ropes.first_node[a] + i]
            n1 = q[env, ropes.first_node[a] + i + 1]
            st = closest_segment_segment(n0, n1, x, x)
            y = n0 + (n1 - n0) * st[0]
            if wp.length(y - x) < best_d:
                best_d = wp.length(y - x)
                best = y
    s = ptsd[env, 0]
    goal = point_to_ptsd(rcm[env, 0], best, s[2])
    # the cutting centre lies on the shaft axis, CAUTER_CUTTING_CENTER beyond the TPSD tip
    error_out[env, 0] = goal[0] - s[0]
    error_out[env, 1] = goal[1] - s[1]
    error_out[env, 2] = 0.0
    error_out[env, 3] = goal[3] - CAUTER_CUTTING_CENTER - s[3]
    want = wp.where(best_d < switch_on, 1, 0)
    error_out[env, 4] = float(want - active[env, 0])


# ---------------------------------------------------------------------------- env
class RopeCuttingEnv(BatchedEnv):
    """LapGym's RopeCuttingEnv, batched. See the module docstring and ``RopeCuttingConfig``.

    Actions: 5, the hook's PTSD then its activation (above the dead zone: on; below minus it: off). Discrete:
    ``Discrete(11)``, each the continuous action of its ``discrete_actions`` row.

    Privileged critic observation (``privileged_critic=True``): the policy values, every rope's cut state (R), the
    offset from the cutting centre to the active rope's nearest node and that distance (both over the workspace
    diagonal; 4).
    """

    config_class = RopeCuttingConfig
    task_name = "RopeCutting"
    # the register-resident chain solve (kernels/chains_registers.py): five 19-link ropes per env leave the serial
    # walk's few threads waiting on its loads; the expert's step 273,906 -> 306,287 env-steps/s (H200, 4,096 envs,
    # same call, thirty-third session; the packed PCR blocks 184,560 and the hybrid 198,776 lost to the walk). On
    # CUDA devices its split form, two threads per rope (World.chain_register_split, set in _build)
    gpu_chain_solver = "registers"
    rewards = REWARDS
    supported_observations = ("STATE", "RGB", "RGBD", "DEPTH")
    expert = "lapwarp.tasks.dissection.rope_cutting:RopeCuttingExpert"
    cfg: RopeCuttingConfig

    def _build(self) -> World:
        cfg, n, dev, R = self.cfg, self.num_envs, self.wp_device, self.cfg.num_ropes
        builder = SceneBuilder()  # gravity -z
        nominal = np.stack([np.linspace(-0.05, 0.05, NODES), np.zeros(NODES), np.zeros(NODES)], axis=1)
        segment = 0.1 / SEGMENTS
        area = math.pi * cfg.rope_radius**2
        self.ropes_obj = [
            builder.add_rod(nominal, radius=cfg.rope_radius, density=cfg.rope_mass / (area * 0.1),
                            youngs_modulus=cfg.rope_stiffness * segment / area, fixed=[0, NODES - 1],
                            damping=cfg.rope_damping, cuttable=True, stretch_rest_scale=1.0 - cfg.contraction_ratio,
                            name=f"rope{r}")
            for r in range(R)]
        self.rig = InstrumentRig([InstrumentSpec(name="cauter", tpsd=cfg.cauter_tpsd(), shape="cauter",
                                                 activation=True, activation_deadzone=cfg.activation_deadzone)],
                                 builder)
        world = builder.finalize(num_envs=n, device=str(dev), substeps=cfg.physics_substeps, seed=cfg.seed)
        world.rod_newton_steps = cfg.rope_newton_steps
        world.rod_newton_tolerance = rope_newton_tolerance("rope_newton_tolerance", cfg.rope_newton_tolerance,
                                                           self.chain_solver)
        # the rods' fused sweep (one warp per env) at 64 registers instead of 71: 32 blocks per SM hold 4,096 envs
        # in one wave instead of 1.11 (sm_90; a 16 B spill frame). H200, expert, 4,096 envs, same call as the
        # uncapped step: 320.2k -> 326.6k env-steps/s (benchmarks/RESULTS.md, thirty-sixth session; the CPU
        # ignores the cap). The segment contact's colour sweep at 64 too: 328.1k -> 329.6k (thirty-seventh session,
        # same call; +0.7 % alone in the thirty-sixth)
        world.default_register_caps.update(solve_rods_fused=64, collide_segment_colors=64)
        # the shape contact's particle kernel (71 registers) at 64: 4 blocks of 256 per SM instead of 3. H200, expert,
        # 4,096 envs, same call as the uncapped step (forty-first session, results/session41):
        # 321.4k -> 324.4k env-steps/s
        world.default_register_caps["collide_particles"] = 64
        # the rods' fused sweep with 64 lanes per env instead of 32 (H200, expert, 4,096 envs, same call, forty-third
        # session: 320.6k -> 326.0k env-steps/s), each substep's prediction in its first sweep's rod launch
        # (World.predict_in_rod_sweep) with that launch at 64 registers like the sweep's own (uncapped, 72, it was
        # slower: 324.8k against 326.0k): H200, same call, twice alternated (forty-fourth session, results/session44):
        # 332.0k / 331.9k against 330.6k / 330.5k with the prediction's own launch
        world.rod_block_threads = 64
        world.default_register_caps["predict_and_solve_rods_fused"] = 64
        # the register chain solve with two threads per rope, each half in registers, the eliminations meeting in the
        # middle (kernels/chains_split.py), capped at 168 registers (235: 1,280 warps in 1.2 waves of 8 per SM; 168:
        # 12 per SM, one wave; 169-200 still 8, a warp's registers coming from one of the SM's four 16,384-register
        # sub-partitions: 479k-481k at 176 / 184, forty-fifth session). H200, expert, 4,096 envs, same calls
        # (forty-fourth session, results/session44): the one-thread solve 450.4k / 450.4k / 450.4k env-steps/s (its
        # exact-length variant; 331.1k / 330.8k before it), split 489.0k / 488.7k uncapped, 486.6k / 486.6k at 200,
        # 558.0k at 144, 548.2k at 128, **568.7k / 568.4k / 569.1k at 168**; expert 256 / 256 on it. CUDA only: on
        # the CPU a pair's threads need Warp's cooperative blocks, and the CPU's default chain solver is the serial
        # walk anyway
        world.chain_register_split = bool(dev.is_cuda)
        world.default_register_caps["solve_chains_split"] = 168
        self.rig.finalize(world)
        self.contact = ContactSystem(world, capacity=cfg.contact_capacity)
        for rope in self.ropes_obj:
            self.contact.add_particle_group(rope, radius=cfg.rope_radius, segments=True)
        self.contact.add_plane(transform=(0.0, 0.0, -0.06), name="floor", mu_static=0.0)
        self.rig.add_colliders(self.contact, mu_static=0.0)  # sofa_env: friction 1e-6
        self.contact.finalize()
        self.cutting = CuttingSystem(world, carving_distance=cfg.carving_distance, num_tools=2, num_labels=R,
                                     tool_radius=8.0e-4)
        for r, rope in enumerate(self.ropes_obj):
            self.cutting.add_object(rope, labels=np.full(SEGMENTS, r))
        self.cutting.finalize()

        self.task = Ropes()
        for name, dtype in (("start", wp.vec3), ("end", wp.vec3), ("state", wp.int32)):
            setattr(self.task, name, wp.zeros((n, R), dtype=dtype, device=dev))
        for name in ("active", "cut_active", "cut_inactive"):
            setattr(self.task, name, wp.zeros(n, dtype=wp.int32, device=dev))
        self.task.first_node = wp.array([o.particle_start for o in self.ropes_obj], dtype=wp.int32, device=dev)
        self.task.first_segment = wp.array([o.segment_start for o in self.ropes_obj], dtype=wp.int32, device=dev)
        low, high = cfg.workspace
        self.workspace_diagonal = float(np.linalg.norm(high - low))
        self.params = p = Params()
        p.bounds, p.num_to_cut = self.rig.bounds(low, high), cfg.num_ropes_to_cut
        return world

    def _checked_state(self) -> list[wp.array]:
        return [*super()._checked_state(), self.task.start, self.task.end]

    def _observation_layout(self) -> ObservationLayout:
        # PTSD within the limits and the tip within the workspace: [-1, 1]; rope points may be pushed past the
        # workspace box by the hook (a few mm): [-2, 2]
        R = self.cfg.num_ropes
        return OBS.layout(ptsd=(4, -1.0, 1.0), active=(1, 0.0, 1.0), pose=(7, -1.0, 1.0), ropes=(9 * R, -2.0, 2.0),
                          active_rope=(9, -2.0, 2.0))

    def _critic_layout(self) -> ObservationLayout:
        return self.obs_layout.extend(CRITIC, rope_cut=(self.cfg.num_ropes, 0.0, 1.0),
                                      offset_to_active=(3, -2.0, 2.0), distance_to_active=(1, 0.0, 1.0))

    def _before_physics_step(self) -> None:
        super()._before_physics_step()  # move the hook
        cut = self.cutting
        launching.launch(place_hook_tools, dim=self.num_envs, inputs=[self.rig.pose, self.rig.active],
                         outputs=[cut.tool_a, cut.tool_b, cut.tool_active], device=self.wp_device)
        cut.cut()

    def _compute_features(self, env_mask: wp.array, features_out: wp.array2d) -> None:
        s = self.world.state
        launching.launch(eval_rope_features, dim=self.num_envs,
                         inputs=[env_mask, s.particle_q, s.particle_active, s.segment_active, self.rig.pose,
                                 self.rig.flags, self.task, self.params], outputs=[features_out], device=self.wp_device)

    def _update_task(self) -> None:
        s = self.world.state
        launching.launch(update_ropes, dim=self.num_envs,
                         inputs=[s.particle_q, s.particle_active, s.segment_active, self.rig.pose, self.features,
                                 self.params, self.world.rng], outputs=[self.task, self.baselines],
                         device=self.wp_device)

    def _reset_task(self, env_mask: wp.array) -> None:
        cfg, w, s = self.cfg, self.world, self.world.state
        wp.launch_tiled(reset_ropes, dim=[self.num_envs], block_dim=LAYOUT_LANES,
                        inputs=[env_mask, cfg.depth, cfg.min_rope_distance, w.rng],
                        outputs=[self.task, s.particle_q, s.particle_qd, s.segment_q, s.segment_qd],
                        device=self.wp_device)
        self.rig.reset(env_mask, w.rng)
        self.cutting.refresh()  # the reset restored the masks; recount the pieces of the reset envs

    def _compute_observations(self) -> None:
        s = self.world.state
        launching.launch(observe_ropes, dim=self.num_envs,
                         inputs=[s.particle_q, s.particle_active, self.rig.ptsd, self.rig.pose, self.rig.active,
                                 self.task, self.params, self.obs_layout.columns, self.critic_layout.columns,
                                 int(self.cfg.privileged_critic)], outputs=[self.obs_frame, self.critic_frame],
                         device=self.wp_device)

    # ------------------------------------------------------------------ visuals
    def _build_visual_scene(self) -> VisualScene:
        """Walls (grey, 10 mm thick, visual only as in sofa_env), the ropes (the active one green, the others red; cut
        segments leave gaps) and the hook. Camera per sofa_env: at (50, -66, 66) mm with its orientation, vertical
        FoV 52 degrees, near 2 mm, far 1.2 x the distance to the farthest workspace corner."""
        cfg, n, dev, R = self.cfg, self.num_envs, self.wp_device, self.cfg.num_ropes
        self.active_segments = wp.zeros((n, R * SEGMENTS), dtype=wp.int32, device=dev)
        self.idle_segments = wp.zeros((n, R * SEGMENTS), dtype=wp.int32, device=dev)
        static = wp.full((n, 1), wp.transform_identity(), dtype=wp.transform, device=dev)
        objects = []
        for side, x in (("left", -0.055), ("right", 0.055)):
            wall = trimesh.creation.box(extents=(0.01, cfg.depth, 0.1))
            wall.apply_translation((x, 0.5 * cfg.depth, 0.0))
            objects.append(VisualObject(f"{side}_wall", "rigid", (0.6, 0.6, 0.62), 1, wall.vertices, wall.faces,
                                        static))
        q = self.world.state.particle_q
        for r, rope in enumerate(self.ropes_obj):
            points = q[:, rope.particle_start:rope.particle_start + NODES]
            cols = slice(r * SEGMENTS, (r + 1) * SEGMENTS)
            objects.append(VisualObject(f"rope{r}_active", "rod", ACTIVE_COLOR, 2 + r, points=points,
                                        radius=cfg.rope_radius, face_active=self.active_segments[:, cols]))
            objects.append(VisualObject(f"rope{r}", "rod", IDLE_COLOR, 2 + r, points=points, radius=cfg.rope_radius,
                                        face_active=self.idle_segments[:, cols]))
        objects += self.rig.visual_objects([(0.72, 0.74, 0.78)], first_segmentation_id=2 + R)
        position = np.array([0.05, -0.066, 0.066])
        low, high = cfg.workspace
        far = 1.2 * float(np.linalg.norm(np.array([low[0], high[1], low[2]]) - position))
        pose = wp.transform(wp.vec3(*position), wp.quat(0.5032, 0.1299, 0.1960, 0.8316))
        camera = CameraSpec(poses=wp.array([pose] * n, dtype=wp.transform, device=dev), fov_deg=52.0, near=0.002,
                            far=far)
        return VisualScene(camera=camera, objects=objects, background=(0.05, 0.05, 0.08))

    def update_visuals(self) -> None:
        if self._visual_scene is None:
            return
        launching.launch(rope_colors, dim=(self.num_envs, self.cfg.num_ropes, SEGMENTS),
                         inputs=[self.world.state.segment_active, self.task],
                         outputs=[self.active_segments, self.idle_segments], device=self.wp_device)

    # ------------------------------------------------------------------ privileged access (experts, tests)
    def privileged_state(self) -> dict[str, torch.Tensor]:
        """Zero-copy torch views: rope end points ``(N, R, 3)`` (m), rope states ``(N, R)``, the active rope,
        correct and wrong cuts ``(N,)``, node positions ``(N, n, 3)`` and segment masks ``(N, S)``."""
        t, s = self.task, self.world.state
        views = dict(start=t.start, end=t.end, rope_state=t.state, active=t.active, cut_active=t.cut_active,
                     cut_inactive=t.cut_inactive, positions=s.particle_q, segment_active=s.segment_active)
        return {k: wp.to_torch(v) for k, v in views.items()}


# ---------------------------------------------------------------------------- expert
class RopeCuttingExpert(Expert):
    """Drives the hook's cutting centre to the nearest point of the active rope's middle half and switches the hook
    on within ``switch_on`` of it (off otherwise, so passing other ropes only pushes them)."""

    def __init__(self, env: RopeCuttingEnv, switch_on: float = 0.004):
        super().__init__(env)
        self.switch_on = float(switch_on)
        self.error = wp.zeros((env.num_envs, 5), dtype=float, device=env.wp_device)
        to_internal = torch.tensor([math.pi / 180.0] * 3 + [1.0])
        dt = env.cfg.time_step * env.cfg.frame_skip
        step = (torch.tensor(env.cfg.maximum_state_velocity) * to_internal * dt).tolist()
        # activation: any error is switched in one step (a large ideal value, so a discrete expert switches first)
        self.step_size = torch.tensor([*step, 1.0e-6], device=env.device)

    def __call__(self, obs=None) -> torch.Tensor:
        env, rig, s = self.env, self.env.rig, self.env.world.state
        with env._torch_stream_scope():
            launching.launch(expert_errors, dim=env.num_envs,
                             inputs=[s.particle_q, s.segment_active, rig.ptsd, rig.pose, rig.rcm, rig.active, env.task,
                                     self.switch_on], outputs=[self.error], device=env.wp_device)
        return self.policy_actions(wp.to_torch(self.error) / self.step_size)
