"""LigatingLoopEnv against sofa_env's facts (task-cards §10) and independent NumPy references.

* Scene: the 750-node / 2,160-tet cavity with its node numbering and its 90 fixed nodes, the N-node loop, the
  59-value STATE, the 5-D action, ``Discrete(11)`` and Table A's default weights.
* Closing mechanism (``LoopClosure``): one index per env step (two with ``index_steps_per_action=2``) within [5, N - 1];
  the pinned nodes at their closed-form places in the tip frame, with a resting and with a moving tip; the free part
  of the loop inextensible.
* Observation: the closed ratio ``(a - N + 1) / (6 - N)`` and the position blocks against a NumPy mapping.
* Reward features against a NumPy reference (winding number of the cavity's capped outer wall, band triangles touched
  by the loop's spheres, band centre distance), after reset and on hand-made states.
* Reset draws (index, band start, PTSD noise, the bank loop carried with the tip, sofa_env's no-touch redraw rule),
  invalid configurations, the settled loop bank, seeding; a strict xfail: the fully open loop's end at the shaft is a
  hinge (sofa_env binds the orientation of every frame from the active index on).
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
import trimesh
import warp as wp
from reference_geometry import winding_numbers_of_triangles

import lapwarp
from lapwarp.experts import make_expert
from lapwarp.tasks.thread_manipulation.ligating_loop import (
    REWARDS,
    LigatingLoopConfig,
    LigatingLoopEnv,
)

wp.set_module_options({"enable_backward": False})

F = REWARDS.F
MM = 1e-3
N = 50  # default num_loop_points
R_IN, R_OUT, LENGTH = 8.0 * MM, 10.0 * MM, 50.0 * MM
RADIAL, ANGULAR, AXIAL = 2, 15, 25
WS_LOW, WS_HIGH = np.array([-0.05, -0.05, 0.0]), np.array([0.05, 0.05, 0.1])
DIAGONAL = float(np.linalg.norm(WS_HIGH - WS_LOW))
SPHERE = 1.0 * MM  # the loop's collision sphere radius
#: the PTSD state limits (rad, rad, rad, m): sofa_env's (+-90, +-90, +-65504 deg, 0..100 mm)
PTSD_LOW = np.array([-math.pi / 2, -math.pi / 2, -math.radians(65504.0), 0.0])
PTSD_HIGH = np.array([math.pi / 2, math.pi / 2, math.radians(65504.0), 0.1])


def make(device: str, num_envs: int = 2, **overrides) -> LigatingLoopEnv:
    """A small env, seed 1 unless given."""
    overrides.setdefault("seed", 1)
    return lapwarp.make("LigatingLoop", num_envs=num_envs, device=device, **overrides)


# ---------------------------------------------------------------------------- NumPy helpers
def rotate(q: np.ndarray, v: np.ndarray) -> np.ndarray:
    """``v`` (..., 3) rotated by the unit quaternion ``q`` (..., 4; x, y, z, w: Warp's order)."""
    u, w = q[..., :3], q[..., 3:4]
    return v + 2.0 * w * np.cross(u, v) + 2.0 * np.cross(u, np.cross(u, v))


def apply(pose: np.ndarray, points: np.ndarray) -> np.ndarray:
    """``points`` (..., 3) from the frame of ``pose`` (7: position, quaternion xyzw) to the world."""
    return pose[:3] + rotate(np.broadcast_to(pose[3:], points.shape[:-1] + (4,)), points)


def state(env: LigatingLoopEnv) -> dict[str, np.ndarray]:
    """The privileged state on the host, float64."""
    return {k: v.detach().cpu().numpy().astype(np.float64) for k, v in env.privileged_state().items()}


def closed_ratio(a) -> np.ndarray:
    return (np.asarray(a, np.float64) - N + 1) / (6.0 - N)


def pin_targets(tip: np.ndarray, a: int, pitch: float) -> np.ndarray:
    """World places of the pinned nodes a..N-1 (node a + i at (0, 0, -i pitch) in the tip frame)."""
    i = np.arange(N - a, dtype=np.float64)
    return apply(tip, np.stack([0.0 * i, 0.0 * i, -i * pitch], axis=1))


def pin_error(s: dict[str, np.ndarray], pitch: float) -> float:
    """Largest distance of a pinned node (0 and a..N-1) from its closed-form place over all envs, m."""
    worst = 0.0
    for e in range(len(s["tip"])):
        a, tip, loop = int(s["active_index"][e]), s["tip"][e], s["loop"][e]
        worst = max(worst, float(np.linalg.norm(loop[a:] - pin_targets(tip, a, pitch), axis=1).max()),
                    float(np.linalg.norm(loop[0] - tip[:3])))
    return worst


def outer_node(j: int, k: int) -> int:
    """Local index of the outer-wall node at angle index j (mod 15), axial ring k."""
    return (ANGULAR + j % ANGULAR) * AXIAL + k


def inner_node(j: int, k: int) -> int:
    return (j % ANGULAR) * AXIAL + k


def capped_wall(cavity: np.ndarray) -> np.ndarray:
    """The cavity's outer wall (its node grid split into outward triangles) closed by fans over both end rings
    (top +z, base -z outward): (T, 3, 3)."""
    tris = []
    for j in range(ANGULAR):
        for k in range(AXIAL - 1):
            a, b, c, d = outer_node(j, k), outer_node(j + 1, k), outer_node(j + 1, k + 1), outer_node(j, k + 1)
            tris += [cavity[[a, b, c]], cavity[[a, c, d]]]
    for k, sign in ((AXIAL - 1, 1), (0, -1)):
        ring = cavity[[outer_node(j, k) for j in range(ANGULAR)]]
        centre = ring.mean(axis=0)
        for j in range(ANGULAR):
            pair = (ring[j], ring[(j + 1) % ANGULAR])[::sign]
            tris.append(np.stack([centre, *pair]))
    return np.asarray(tris)


def winding(cavity: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Generalised winding number of the capped outer wall at ``points``, 1 inside."""
    return winding_numbers_of_triangles(capped_wall(cavity), np.asarray(points, np.float64))


def band_triangles(env: LigatingLoopEnv, start: float, width: float) -> np.ndarray:
    """Local vertex indices of the cavity's outer-wall surface triangles (all three rest vertices at the outer
    radius) whose rest centroid z lies strictly inside the band (start, start + width)."""
    hv, _ = env.cavity_rest
    surf = np.asarray(env.cavity.surface_tris) - env.cavity.particle_start
    on_wall = np.all(np.abs(np.hypot(hv[surf, 0], hv[surf, 1]) - R_OUT) < 1e-9, axis=1)
    z = hv[surf].mean(axis=1)[:, 2]
    return surf[on_wall & (z > start) & (z < start + width)]


def loop_encloses(cavity: np.ndarray, free: np.ndarray, rings: np.ndarray) -> int:
    """How many outer nodes of the band's middle ring the closed polygon of the free loop nodes winds about (more
    than half a turn), seen along the axis between the centres of the rings just outside the band."""
    centre = lambda k: cavity[[outer_node(j, k) for j in range(ANGULAR)]].mean(axis=0)  # noqa: E731
    axis = centre(min(rings[-1] + 1, AXIAL - 1)) - centre(max(rings[0] - 1, 0))
    axis /= np.linalg.norm(axis)
    count = 0
    for j in range(ANGULAR):
        v = free - cavity[outer_node(j, (rings[0] + rings[-1]) // 2)]
        v -= np.outer(v @ axis, axis)
        prev = np.roll(v, 1, axis=0)
        count += abs(np.arctan2(np.cross(prev, v) @ axis, np.einsum("ij,ij->i", prev, v)).sum()) > np.pi
    return count


def reference_features(env: LigatingLoopEnv, cavity: np.ndarray, loop: np.ndarray, tip: np.ndarray, a: int,
                       start: float) -> dict[str, float]:
    """sofa_env's features of one env from its state, float64 (see the module docstring of the task)."""
    cfg = env.cfg
    com = loop[:a].mean(axis=0)
    ring_z = np.arange(AXIAL) * LENGTH / (AXIAL - 1)
    rings = np.nonzero((ring_z > start) & (ring_z < start + cfg.marking_width))[0]
    band = cavity[[outer_node(j, k) for k in rings for j in range(ANGULAR)]].mean(axis=0)
    w = winding(cavity, np.stack([com, tip[:3]]))
    inside, tip_outside = float(w[0] > 0.5), float(w[1] <= 0.5)
    tris = band_triangles(env, start, cfg.marking_width)
    reach = SPHERE + cfg.touch_distance
    touched = 0
    for t in tris:
        tri = np.broadcast_to(cavity[t], (a, 3, 3))
        closest = trimesh.triangles.closest_point(tri, loop[:a])
        touched += bool((np.linalg.norm(closest - loop[:a], axis=1) <= reach).any())
    overlap = touched / max(len(tris), 1)
    ratio = float(closed_ratio(a))
    encircles = float(2 * loop_encloses(cavity, loop[:a], rings) > ANGULAR)  # around the tube, not in its bore
    gate = inside * tip_outside * (encircles if cfg.require_encircling else 1.0)
    around = ratio * overlap * gate
    return dict(distance=min(np.linalg.norm(band - com) / DIAGONAL, 1.0), in_cavity=inside, tip_outside=tip_outside,
                encircles=encircles,
                overlap=overlap, around=around, thin_air=ratio * (1.0 - inside),
                on_marking=ratio * gate if touched else 0.0,
                success=float(around > 0 and overlap > cfg.target_loop_overlap_ratio
                              and ratio > cfg.target_loop_closed_ratio))


COLUMNS = dict(distance=F.DISTANCE_LOOP_TO_MARKING_CENTER, in_cavity=F.LOOP_CENTER_IN_CAVITY,
               tip_outside=F.INSTRUMENT_NOT_IN_CAVITY, overlap=F.LOOP_MARKING_OVERLAP,
               around=F.LOOP_CLOSED_AROUND_MARKING, thin_air=F.LOOP_CLOSED_IN_THIN_AIR,
               on_marking=F.LOOP_CLOSED_ON_MARKING, success=F.SUCCESSFUL_TASK)


def features_now(env: LigatingLoopEnv) -> np.ndarray:
    """The task's feature kernel on the current state (it is a pure function of the state), float64."""
    out = wp.zeros(env.features.shape, dtype=float, device=env.wp_device)
    env._compute_features(env._all_envs, out)
    return out.numpy().astype(np.float64)


def assert_features(env: LigatingLoopEnv, features: np.ndarray, e: int, ref: dict[str, float]) -> None:
    """Every feature of env ``e`` equals the reference: flags exactly, the fractions to float32 (1e-5)."""
    for name, col in COLUMNS.items():
        assert features[e, col] == pytest.approx(ref[name], abs=1e-5), (e, name, features[e, col], ref[name])


def unit(x: np.ndarray, low, high) -> np.ndarray:
    return 2.0 * (np.asarray(x) - low) / (np.asarray(high) - np.asarray(low)) - 1.0


# ---------------------------------------------------------------------------- fixtures
@pytest.fixture(scope="module")
def env(device) -> LigatingLoopEnv:
    """The default configuration, 3 envs (random loop state and band)."""
    return make(device, 3)


@pytest.fixture(scope="module")
def open_env(device) -> LigatingLoopEnv:
    """2 envs whose loop starts fully open (``randomize_loop_state=False``); tests reset it first."""
    return make(device, 2, randomize_loop_state=False)


# ---------------------------------------------------------------------------- scene
def test_scene_matches_sofa_env(env):
    """Cavity: 750 nodes numbered (i_r * 15 + j) * 25 + k at radius 8 / 10 mm, angle 24 j deg, z = k * 50 / 24 mm
    (rest mesh, 1e-9 m), 2,160 tets, exactly the 90 nodes with z < 5 mm fixed (zero inverse mass); a 50-node loop;
    STATE (3, 59) = 4 + 1 + 18 + 27 + 9; 5-D actions, Discrete(11) whose rows 8 / 9 are the closing +-1; Table A's
    default weights."""
    c = env.cavity
    assert c.particle_count == 750 and len(np.asarray(c.tets)) == 2160
    hv, _ = env.cavity_rest
    for i_r, r in enumerate((R_IN, R_OUT)):
        for j in range(ANGULAR):
            for k in range(AXIAL):
                phi = math.radians(24.0 * j)
                expect = (r * math.cos(phi), r * math.sin(phi), k * LENGTH / (AXIAL - 1))
                np.testing.assert_allclose(hv[(i_r * ANGULAR + j) * AXIAL + k], expect, atol=1e-9)
    fixed = np.sort(np.asarray(c.fixed) - c.particle_start)
    np.testing.assert_array_equal(fixed, np.nonzero(hv[:, 2] < 5.0 * MM)[0])
    assert len(fixed) == 90
    inv = env.world.model.particle_inv_mass.numpy()[0, c.particle_start:c.particle_start + c.particle_count]
    np.testing.assert_array_equal(np.nonzero(inv == 0.0)[0], fixed)
    assert env.loop.particle_count == N == env.cfg.num_loop_points
    obs, _ = env.reset()
    assert tuple(obs["policy"].shape) == (3, 59) and env.observation_dim == 59
    assert dict(zip(env.obs_layout.names, env.obs_layout.sizes, strict=True)) == dict(
        ptsd=4, closed=1, loop=18, cavity=27, marking=9)
    assert env.action_dim == 5 and env.discrete_actions.shape[0] == 11
    table = env.discrete_actions.cpu().numpy()
    np.testing.assert_array_equal(table[8], [0, 0, 0, 0, 1])
    np.testing.assert_array_equal(table[9], [0, 0, 0, 0, -1])
    weights = env.rewards.default_weights()
    assert list(weights) == list(env.rewards.names) == [
        "distance_loop_to_marking_center", "delta_distance_loop_to_marking_center", "loop_center_in_cavity",
        "instrument_not_in_cavity", "instrument_shaft_collisions", "loop_marking_overlap",
        "loop_closed_around_marking", "loop_closed_in_thin_air", "loop_closed_on_marking",
        "delta_loop_closed_on_marking", "successful_task"]
    assert list(weights.values()) == [-0.05, -100.0, 0.0, 0.0, 0.0, 0.8, 0.5, -0.1, 0.0, 0.0, 100.0]


# ---------------------------------------------------------------------------- closing mechanism
def test_closing_and_opening_one_index_per_step(open_env):
    """Zero PTSD, closing component +1 for 46 steps from the open loop (49): the index drops by exactly one per step
    to 5 and stays there; -1 for 46 steps raises it back to 49 and no further. After every step (the pins reach their
    targets within the step) and after 3 settle steps at 5 and at 49: nodes a..N-1 at tip * (0, 0, -(k - a) pitch)
    and node 0 at the tip within 1e-4 m (pins are exact attachments: measured 4e-8 m); the tip does not move
    (1e-7 m); the free part's segments (nodes 0..a) within 2 % of the pitch (inextensible rod: measured 0.3 %) and
    every free node k within min(k, a - k) pitches (+2 %) of the tip (both ends of the free chain sit at the tip)."""
    env = open_env
    env.reset()
    pitch = env.cfg.pitch
    s0 = state(env)
    assert s0["active_index"].tolist() == [N - 1, N - 1]

    def check(s):
        assert pin_error(s, pitch) < 1e-4
        np.testing.assert_allclose(s["tip"], s0["tip"], atol=1e-7)
        for e in range(2):
            a, loop, tip = int(s["active_index"][e]), s["loop"][e], s["tip"][e, :3]
            seg = np.linalg.norm(np.diff(loop[:a + 1], axis=0), axis=1)
            np.testing.assert_allclose(seg, pitch, rtol=0.02)
            k = np.arange(a + 1)
            assert np.all(np.linalg.norm(loop[:a + 1] - tip, axis=1) <= np.minimum(k, a - k) * pitch * 1.02 + 1e-6)

    action = torch.zeros(2, 5)
    for direction, first, last in ((1.0, N - 1, 5), (-1.0, 5, N - 1)):
        expected = first
        for _ in range(46):
            action[:, 4] = direction
            _, _, done, _ = env.step(action)
            assert not done.any()
            expected = min(max(expected - int(direction), 5), N - 1)
            s = state(env)
            assert s["active_index"].tolist() == [expected, expected]
            check(s)
        assert expected == last
        action[:, 4] = 0.0
        for _ in range(3):
            env.step(action)
        s = state(env)
        assert s["active_index"].tolist() == [last, last]
        check(s)


def test_pins_follow_a_moving_tip(device):
    """3 envs (random loop state), 12 steps of seeded random actions in [-1, 1]^5 (the tip moves up to 2 deg and
    2 mm per step, the index changes): after every step the pinned nodes sit at their closed-form places in the tip
    frame and node 0 at the tip within 1e-4 m (measured 4e-8 m), and the index stayed in [5, N - 1], changing by at
    most one per step."""
    env = make(device, 3, seed=2)
    generator = torch.Generator().manual_seed(0)
    previous = state(env)["active_index"]
    for _ in range(12):
        env.step(torch.rand(3, 5, generator=generator) * 2.0 - 1.0)
        s = state(env)
        assert pin_error(s, env.cfg.pitch) < 1e-4
        a = s["active_index"]
        assert np.all((a >= 5) & (a <= N - 1)) and np.all(np.abs(a - previous) <= 1)
        previous = a


def test_loop_slots_solve_a_thread_each(device):
    """The loop owns every attachment slot (slot k holds node k or nothing), so the World solves them a thread per
    (env, slot) (``Model.attachments_distinct``); 12 steps of seeded random actions in [-1, 1]^5 (the index moves,
    slots fill and empty) end where one thread walking each env's slots in order ends: bit-identical on the CPU
    (the same order), within 1e-6 m on the GPU."""

    def rollout(distinct: bool):
        env = make(device, 3, seed=2)
        assert env.world.model.attachments_distinct
        env.world.model.attachments_distinct = distinct
        generator = torch.Generator().manual_seed(0)
        indices = set()
        for _ in range(12):
            env.step(torch.rand(3, 5, generator=generator) * 2.0 - 1.0)
            indices.update(state(env)["active_index"].tolist())
        return env.world.state.particle_q.numpy(), env.world.state.segment_q.numpy(), indices

    (q, r, indices), (q_walk, r_walk, _) = rollout(True), rollout(False)
    assert len(indices) > 3  # the pins moved between slots
    if device == "cpu":
        np.testing.assert_array_equal(q, q_walk)
        np.testing.assert_array_equal(r, r_walk)
    else:
        np.testing.assert_allclose(q, q_walk, atol=1e-6)
        np.testing.assert_allclose(r, r_walk, atol=1e-6)


def test_index_steps_per_action_2(device):
    """``index_steps_per_action=2`` (sofa_zoo's frame skip 2): each closing step lowers the index by 2 (49, 47, 45),
    an opening step raises it by 2 (47), and the clamps hold: 6 closes to 5 (not 4), 48 opens to 49 (not 50)."""
    env = make(device, 2, randomize_loop_state=False, index_steps_per_action=2)
    action = torch.zeros(2, 5)

    def step(u: float) -> list[int]:
        action[:, 4] = u
        env.step(action)
        return env.task.active_index.numpy().tolist()

    assert step(1.0) == [47, 47] and step(1.0) == [45, 45] and step(-1.0) == [47, 47] and step(0.3) == [47, 47]
    env.task.active_index.assign(np.array([6, 48], np.int32))
    assert step(1.0) == [5, 46]
    env.task.active_index.assign(np.array([6, 48], np.int32))
    assert step(-1.0) == [8, 49]


# ---------------------------------------------------------------------------- observation
def test_closed_ratio_and_positions_in_observation(open_env):
    """Over 8 steps of mixed closing commands: observation column 4 (after the 4 PTSD values, the ``closed`` block)
    equals (a - N + 1) / (6 - N) per env (float32: 1e-6); the PTSD block is the rig state over the state limits
    (+-90, +-90, +-65504 deg, 0..0.1 m), and the loop (nodes 0, 8, 16, 25, 33, 41), cavity (inner nodes at 0 / 120 /
    240 deg on rings 0, 12, 24) and marking (outer nodes at 0 / 120 / 240 deg on the first ring beyond the band
    start) blocks are those nodes mapped from the workspace box to [-1, 1] (NumPy, 1e-5)."""
    env = open_env
    env.reset()
    layout = env.obs_layout
    assert layout.slice("closed") == slice(4, 5)
    commands = [1.0, 1.0, 1.0, -1.0, 1.0, 0.0, -1.0, 1.0]
    ring_z = np.arange(AXIAL) * LENGTH / (AXIAL - 1)
    for e_cmd, u in enumerate(commands):
        action = torch.zeros(2, 5)
        action[0, 4], action[1, 4] = u, -u if e_cmd % 2 else u
        obs = env.step(action)[0]["policy"].cpu().numpy().astype(np.float64)
        s = state(env)
        np.testing.assert_allclose(obs[:, 4], closed_ratio(s["active_index"]), atol=1e-6)
        ptsd = env.rig.ptsd.numpy()[:, 0].astype(np.float64)
        np.testing.assert_allclose(obs[:, :4], unit(ptsd, PTSD_LOW, PTSD_HIGH), atol=1e-5)
        for e in range(2):
            loop = s["loop"][e, [0, 8, 16, 25, 33, 41]]
            np.testing.assert_allclose(obs[e, layout.slice("loop")], unit(loop, WS_LOW, WS_HIGH).ravel(), atol=1e-5)
            cav = s["cavity"][e, [inner_node(j, k) for k in (0, 12, 24) for j in (0, 5, 10)]]
            np.testing.assert_allclose(obs[e, layout.slice("cavity")], unit(cav, WS_LOW, WS_HIGH).ravel(), atol=1e-5)
            ring = int(np.nonzero(ring_z > s["band_start"][e])[0][0])
            mark = s["cavity"][e, [outer_node(j, ring) for j in (0, 5, 10)]]
            np.testing.assert_allclose(obs[e, layout.slice("marking")], unit(mark, WS_LOW, WS_HIGH).ravel(),
                                       atol=1e-5)


# ---------------------------------------------------------------------------- reward features
def test_features_after_reset_match_reference(open_env):
    """After reset (loop open, away from the cavity by sofa_env's redraw rule) the features of the reset state and of
    the state after one zero step equal the NumPy reference: loop centre not in the cavity (0), tip outside (1),
    overlap 0, closed around 0, thin air = closed ratio x (1 - in cavity) (0 for the open loop), no success; the
    distance is |band centre - loop COM| over the workspace diagonal (float32: 1e-5) and its delta the change of the
    distance over the step (1e-5)."""
    env = open_env
    env.reset()
    s = state(env)
    before = features_now(env)
    for e in range(2):
        ref = reference_features(env, s["cavity"][e], s["loop"][e], s["tip"][e], int(s["active_index"][e]),
                                 float(s["band_start"][e]))
        assert ref["in_cavity"] == 0.0 and ref["tip_outside"] == 1.0 and ref["overlap"] == 0.0
        assert ref["thin_air"] == 0.0 and ref["success"] == 0.0
        assert_features(env, before, e, ref)
    action = torch.zeros(2, 5)
    action[:, 4] = 1.0  # close by one: thin air becomes 1 / 44
    env.step(action)
    s = state(env)
    after = env.features.numpy().astype(np.float64)
    for e in range(2):
        ref = reference_features(env, s["cavity"][e], s["loop"][e], s["tip"][e], int(s["active_index"][e]),
                                 float(s["band_start"][e]))
        assert ref["thin_air"] == pytest.approx(1.0 / 44.0)
        assert_features(env, after, e, ref)
        delta = after[e, F.DELTA_DISTANCE_LOOP_TO_MARKING_CENTER]
        assert delta == pytest.approx(ref["distance"] - before[e, F.DISTANCE_LOOP_TO_MARKING_CENTER], abs=1e-5)


def test_features_on_hand_made_states(device):
    """Hand-made states (band fixed at 35..41 mm), features from the task's kernel against the NumPy reference:

    * env 0, a = 10 (ratio 39/44 > 0.8): the loop around the band's middle, nodes 36 deg apart, 3 of them (0, 108,
      216 deg) at 10.5 mm from the axis and 7 at 15 mm: the loop centre is in the cavity, the tip outside, the loop
      winds once about the axis, the overlap a fraction strictly between 0.1 and 1, closed-around = ratio x overlap
      and success 1.
    * env 1, a = 20, tip moved into the bore at z = 30 mm: tip outside 0, thin air = ratio (1e-5).
    * env 2, a = 10, the loop pushed into the tube's bore (what a PPO policy learned against sofa_env's test): 6
      nodes on an arc at 7.2 mm from 0 to 150 deg and 4 back at 2 mm: centre in the cavity, tip outside, band
      touched through the wall (overlap > 0.1), but zero turns about the axis: closed-around 0, success 0 (sofa_env's
      test alone: 1). The same for a 7 mm ring about the axis inside the bore (one turn, but inside).
    * then the in / out test itself at 7 points (all loop nodes 0..a-1 at the point in env 0, the tip at the point in
      env 1; inside: bore, wall material, near the free end; outside: 1.5 mm beyond the wall, 3 mm beyond the free
      end, behind the base, far away), and again with the cavity shifted 15 mm along x (the test must use the current
      nodes, not the rest mesh)."""
    env = make(device, 3, randomize_loop_state=False, randomize_marking_position=False)
    s = state(env)
    assert s["band_start"].tolist() == pytest.approx([0.035, 0.035, 0.035])
    q = env.world.state.particle_q.numpy()
    first = env.loop.particle_start
    zc = 0.035 + 0.5 * env.cfg.marking_width

    def polar(r, deg):
        phi = np.radians(deg)
        return np.stack([r * np.cos(phi), r * np.sin(phi), np.full(len(phi), zc)], axis=1)

    q[0, first:first + 10] = polar(np.where(np.isin(np.arange(10), (0, 3, 6)), 0.0105, 0.015), 36.0 * np.arange(10))
    q[2, first:first + 10] = np.concatenate([polar(np.full(6, 0.0072), 30.0 * np.arange(6)),
                                             polar(np.full(4, 0.002), [120.0, 80.0, 40.0, 0.0])])
    env.world.state.particle_q.assign(q)
    env.task.active_index.assign(np.array([10, 20, 10], np.int32))
    pose = env.rig.pose.numpy()
    pose[1, 0, :3] = (0.0, 0.0, 0.03)
    env.rig.pose.assign(pose)
    s, features = state(env), features_now(env)
    refs = [reference_features(env, s["cavity"][e], s["loop"][e], s["tip"][e], int(s["active_index"][e]),
                               float(s["band_start"][e])) for e in range(3)]
    assert refs[0]["in_cavity"] == 1.0 and refs[0]["tip_outside"] == 1.0 and 0.1 < refs[0]["overlap"] < 1.0
    assert refs[0]["encircles"] == 1.0
    assert refs[0]["success"] == 1.0 and refs[0]["around"] == pytest.approx(39.0 / 44.0 * refs[0]["overlap"])
    assert refs[0]["on_marking"] == pytest.approx(39.0 / 44.0)  # the closed ratio, not scaled by the overlap
    assert refs[1]["on_marking"] == 0.0 and refs[2]["on_marking"] == 0.0  # tip inside; not wound round the band
    assert refs[1]["tip_outside"] == 0.0 and refs[1]["thin_air"] == pytest.approx(29.0 / 44.0)
    assert refs[2]["in_cavity"] == 1.0 and refs[2]["tip_outside"] == 1.0 and refs[2]["overlap"] > 0.1
    assert refs[2]["encircles"] == 0.0 and refs[2]["around"] == 0.0 and refs[2]["success"] == 0.0
    for e in range(3):
        assert_features(env, features, e, refs[e])
    q[2, first:first + 10] = polar(np.full(10, 0.007), 36.0 * np.arange(10))  # a ring inside the bore
    env.world.state.particle_q.assign(q)
    s, features = state(env), features_now(env)
    ref = reference_features(env, s["cavity"][2], s["loop"][2], s["tip"][2], 10, 0.035)
    assert ref["in_cavity"] == 1.0 and ref["overlap"] > 0.1 and ref["encircles"] == 0.0 and ref["success"] == 0.0
    assert_features(env, features, 2, ref)

    points = np.array([[0.0, 0.0, 0.025], [0.009 * math.cos(0.7), 0.009 * math.sin(0.7), 0.02], [0.0, 0.0, 0.048],
                       [0.0115, 0.0, 0.03], [0.0, 0.0, 0.053], [0.0, 0.0, -0.003], [0.03, 0.03, 0.03]])
    inside = [True, True, True, False, False, False, False]
    cavity = slice(env.cavity.particle_start, env.cavity.particle_start + env.cavity.particle_count)
    for shift in (0.0, 0.015):
        q = env.world.state.particle_q.numpy()
        q[:, cavity] = s["cavity"] + (shift, 0.0, 0.0)
        for p, expected in zip(points, inside, strict=True):
            x = p + (shift, 0.0, 0.0)
            q[0, first:first + 10] = x
            env.world.state.particle_q.assign(q)
            pose[1, 0, :3] = x
            env.rig.pose.assign(pose)
            cav = q[0, cavity].astype(np.float64)
            assert (winding(cav, x[None])[0] > 0.5) == expected  # the reference agrees with the geometry
            features = features_now(env)
            assert features[0, F.LOOP_CENTER_IN_CAVITY] == float(expected), (shift, p)
            assert features[1, F.INSTRUMENT_NOT_IN_CAVITY] == float(not expected), (shift, p)
        if shift:
            q[0, first:first + 10] = (0.0, 0.0, 0.025)  # the rest bore centre is 15 mm off the shifted axis
            env.world.state.particle_q.assign(q)
            assert features_now(env)[0, F.LOOP_CENTER_IN_CAVITY] == 0.0


# ---------------------------------------------------------------------------- reset draws
def test_reset_draws(env, device):
    """Default noise, 3 envs x 6 resets: the index lies in [5, N - 1] (at least 6 distinct values of 18 draws), the
    band start in [20, 40] mm (all distinct), the PTSD within sofa_env's noise box around (0, 0, 180 deg, 30 mm):
    +-20 deg, +-20 deg, 0, +-10 mm (1e-4 deg, 1e-7 m); the loop is the bank's loop of that index carried with the
    tip (NumPy transform, 1e-6 m), and no loop node lies within 2 mm of the cavity's rest hull (sofa_env's redraw
    rule) unless the env fell back to the noise-free tip. With ``randomize_marking_position=False`` the band start is
    ``marking_start`` (float32) and with ``randomize_loop_state=False`` the index is N - 1."""
    bank = env._bank_q.numpy().astype(np.float64)
    start_tip = np.asarray(env._start_tip, np.float64)
    indices, starts = [], []
    for _ in range(6):
        env.reset()
        s = state(env)
        ptsd = np.degrees(env.rig.ptsd.numpy()[:, 0].astype(np.float64))
        ptsd[:, 3] = np.radians(ptsd[:, 3])
        for e in range(3):
            a, b = int(s["active_index"][e]), float(s["band_start"][e])
            indices.append(a)
            starts.append(b)
            assert 5 <= a <= N - 1 and 0.02 - 1e-7 <= b <= 0.04 + 1e-7
            assert abs(ptsd[e, 0]) <= 20.0 + 1e-4 and abs(ptsd[e, 1]) <= 20.0 + 1e-4
            assert ptsd[e, 2] == pytest.approx(180.0, abs=1e-4) and abs(ptsd[e, 3] - 0.03) <= 0.01 + 1e-7
            loop, tip = s["loop"][e], s["tip"][e]
            np.testing.assert_allclose(loop, apply(tip, bank[a - 5]), atol=1e-6)
            near = (loop[:, 2] < LENGTH + 2.0 * MM) & (np.hypot(loop[:, 0], loop[:, 1]) < R_OUT + 2.0 * MM)
            assert not near.any() or np.allclose(tip, start_tip, atol=1e-6), (e, a, tip)
    assert len(set(indices)) >= 6 and len(set(starts)) == len(starts), (indices, starts)

    fixed = make(device, 2, randomize_marking_position=False, randomize_loop_state=False)
    for _ in range(2):
        fixed.reset()
        s = state(fixed)
        assert s["band_start"].tolist() == [float(np.float32(0.035))] * 2
        assert s["active_index"].tolist() == [N - 1, N - 1]


# ---------------------------------------------------------------------------- configuration checks
def test_loop_newton_tolerance(device):
    """The loop's Newton tolerance reaches the env's World on the pcr solve and is refused on the serial walk (which
    runs every step); at 1e-4 m the hanging loops of 2 envs end 10 no-op env steps within 1e-5 m of every step's
    (measured 1.1e-6 m on the CPU)."""
    with pytest.raises(ValueError, match="loop_newton_tolerance=.*register-resident, hybrid and pcr chain solves only"):
        make(device, 1, chain_solver="thomas", loop_newton_tolerance=1e-4)
    out = []
    for tolerance in (0.0, 1e-4):
        env = make(device, chain_solver="pcr", loop_newton_tolerance=tolerance)
        assert env.world.rod_newton_tolerance == tolerance
        env.reset()
        for _ in range(10):
            env.step(torch.zeros(env.num_envs, env.action_dim, device=env.device))
        out.append(env.world.positions(env.loop))
    assert np.abs(out[0] - out[1]).max() <= 1e-5


@pytest.mark.parametrize("overrides, message", [
    (dict(marking_start_range=(0.04, 0.02)), "low <= high"),
    (dict(marking_start=0.045, marking_width=0.01), "beyond the cavity"),
    (dict(loop_stiffness="medium"), "loop_stiffness"),
    (dict(num_loop_points=5), "num_loop_points"),
    (dict(cavity_rotation_iterations=0), "cavity_rotation_iterations"),
])
def test_invalid_configuration_raises(overrides, message, device):
    """An inverted band range, a band ending beyond the 50 mm cavity, an unknown stiffness, fewer than 12 loop
    nodes and no rotation extraction iteration raise ValueError naming the problem; the extreme valid band (start
    44 mm, width 6 mm, ending at 50 mm) validates."""
    with pytest.raises(ValueError, match=message):
        make(device, 1, **overrides)
    LigatingLoopConfig(marking_start=0.044, marking_start_range=(0.02, 0.044)).validate(
        REWARDS.names, LigatingLoopEnv.supported_observations)


# ---------------------------------------------------------------------------- the settled loop bank
def test_settled_bank(env):
    """The bank (45 entries, indices 5..49, tip frame of the start pose) settled without instability; in every entry
    the pinned nodes sit at (0, 0, -(k - a) pitch) and node 0 at the origin (1e-6 m), the free segments keep the pitch
    within 2 % (inextensible: measured 0.25 %), the loop stays in its plane x = 0 (1e-5 m: the start tip's local y is
    world -y, so gravity lies in the loop's plane) and hangs below the tip: every node's local y >= -1e-4 m (local y
    is world down), the open loop (entry N - 1 - 5) reaching at least 2 R below the tip (a ring hanging under its own
    weight only lengthens vertically)."""
    assert env._bank_stable
    bank = env._bank_q.numpy().astype(np.float64)
    assert bank.shape == (N - 5, N, 3)
    down = rotate(np.asarray(env._start_tip, np.float64)[3:], np.array([0.0, 1.0, 0.0]))
    np.testing.assert_allclose(down, [0.0, -1.0, 0.0], atol=1e-6)
    pitch = env.cfg.pitch
    for a in range(5, N):
        x = bank[a - 5]
        i = np.arange(N - a, dtype=np.float64)
        np.testing.assert_allclose(x[a:], np.stack([0 * i, 0 * i, -i * pitch], axis=1), atol=1e-6)
        np.testing.assert_allclose(x[0], 0.0, atol=1e-6)
        np.testing.assert_allclose(np.linalg.norm(np.diff(x[:a + 1], axis=0), axis=1), pitch, rtol=0.02)
        assert np.abs(x[:, 0]).max() < 1e-5 and x[:, 1].min() >= -1e-4
    assert bank[N - 1 - 5, :, 1].max() >= 2.0 * env.cfg.loop_radius


def test_open_loop_is_clamped_at_both_ends(env):
    """sofa_env binds the orientation of frame 0 and of every frame k >= a, the last frame of the fully open loop
    included: the settled open loop (a = N - 1) leaves and enters the tip at the same angle to the shaft (within 0.5
    deg; both ends are held at half a chord angle, 7.3 deg; a free hinge at node N - 1 gave 33 deg), and closing by
    one index keeps the end within 8 deg of that (the shaft-side clamp of a < N - 1 acts through the bend-twist
    constraint with the segment inside the shaft, measured 10.8 deg)."""
    bank = env._bank_q.numpy().astype(np.float64)

    def end_angle(a: int) -> float:
        d = bank[a - 5, a] - bank[a - 5, a - 1]
        return math.degrees(math.atan2(-d[1], -d[2]))

    def start_angle(a: int) -> float:
        d = bank[a - 5, 1] - bank[a - 5, 0]
        return math.degrees(math.atan2(d[1], -d[2]))

    assert abs(end_angle(N - 1) - start_angle(N - 1)) < 0.5
    assert abs(end_angle(N - 2) - end_angle(N - 1)) < 8.0


# ---------------------------------------------------------------------------- seeding
def test_seeding(device):
    """Two envs built with seed 7 (default noise, 2 envs) give bit-identical observations after reset and after each
    of 5 steps of the same seeded random actions (on CUDA within 1e-5 after steps); seed 8 gives different ones (the
    reset draws differ: > 1e-3)."""
    a, b, c = make(device, 2, seed=7), make(device, 2, seed=7), make(device, 2, seed=8)
    obs = [x.get_observations()["policy"].cpu().numpy() for x in (a, b, c)]
    np.testing.assert_array_equal(obs[0], obs[1])
    assert np.abs(obs[0] - obs[2]).max() > 1e-3
    generator = torch.Generator().manual_seed(5)
    for _ in range(5):
        action = torch.rand(2, 5, generator=generator) * 2.0 - 1.0
        obs = [x.step(action.clone())[0]["policy"].cpu().numpy() for x in (a, b, c)]
        if device == "cpu":
            np.testing.assert_array_equal(obs[0], obs[1])
        else:  # GPU atomics may reorder float sums
            np.testing.assert_allclose(obs[0], obs[1], atol=1e-5)
        assert np.abs(obs[0] - obs[2]).max() > 1e-3


# ---------------------------------------------------------------------------- expert
def _expert_first_episodes(env, steps: int) -> tuple[np.ndarray, np.ndarray]:
    """Whether each env's first episode under the scripted expert ended in success within ``steps`` steps, and its
    return."""
    expert = make_expert(env)
    counted = np.zeros(env.num_envs, bool)
    success = np.zeros(env.num_envs, bool)
    returns = np.zeros(env.num_envs)
    for _ in range(steps):
        _, reward, done, _ = env.step(expert())
        returns += np.where(counted, 0.0, reward.cpu().numpy())
        done = done.bool().cpu().numpy() & ~counted
        success |= done & (env.last_episode_success.numpy() > 0)
        counted |= done
        if counted.all():
            break
    return success, returns


def test_expert_closes_the_loop_on_the_band(device):
    """The scripted expert (continuous, the paper's randomised starts, stiff small loop) succeeds in at least 6 of the
    first episodes of 8 envs within 200 steps by the default test (the loop encircled the band, then closed past 0.8
    on it with its centre inside the cavity and the tip outside; the issue asks >= 80 %). (Holding the tip at a fixed
    distance beside the band, the former rule, it solved about a quarter: the shrinking loop lifted the over-soft
    cavity, its centre left the cavity's hull and the encircling flag reset.)"""
    success, _ = _expert_first_episodes(make(device, 8, seed=1), 200)
    assert success.sum() >= 6, success


def test_expert_closes_the_loop_with_discrete_actions(device):
    """The same with discrete actions (one component per step), within 250 steps: at least 7 of 8. The squeezed
    cylinder snaps sideways in the closing loop; uncorrected, the error around the cylinder (``side_band``) let the
    loop's COM drift out of the cavity's hull and the encircling flag reset (measured on CPU: 8 of 8 here, 5 of 8
    without the correction)."""
    success, _ = _expert_first_episodes(make(device, 8, seed=1, action_type="DISCRETE", invalid_actions="zero"),
                                        250)
    assert success.sum() >= 7, success


def test_delta_closure_shaping_pays_the_net_closure_on_the_band(device):
    """``delta_loop_closed_on_marking`` (the per-step change of closed-on-marking, potential-based shaping) sums over
    an episode to its final value minus its first: with every other weight 0 but success's 1,000 and the delta's 100,
    each of the expert's successful first episodes (two closing indices per action; measured: success in 59-65
    steps) returns 1,000 + 100 x the closed ratio on the band at success, i.e. in (1,000 + 100 x 0.8, 1,100] by the
    success test (ratio > 0.8), and the same for every env (same closing schedule from the open loop's 0). Holding a
    partly closed loop would earn nothing."""
    weights = dict.fromkeys(REWARDS.names, 0.0)
    weights.update(delta_loop_closed_on_marking=100.0, successful_task=1000.0)
    env = make(device, 4, seed=3, index_steps_per_action=2, reward_weights=weights)
    success, returns = _expert_first_episodes(env, 150)
    assert success.all(), success
    assert np.all((returns > 1000.0 + 100.0 * env.cfg.target_loop_closed_ratio) & (returns <= 1100.0 + 1e-3)), returns


def test_loop_shape_converged_at_default_substeps(device):
    """The heavy, thin loop's settled shapes (the bank, every 10th active index) at the default 20 substeps lie within
    1.5 mm of the shapes at 80 substeps (measured 0.8 mm for the stiff loop; XPBD's answer converges with substeps);
    without the segments' inertia scaling (``loop_inertia_scale=1``) they are > 5 mm off (measured ~20 mm: the
    bending does not reach the nodes within a step), which is why the scaling is on by default."""
    def bank(**overrides):
        return make(device, 1, **overrides)._bank_q.numpy().astype(np.float64)

    fine, default, unscaled = bank(physics_substeps=80), bank(), bank(loop_inertia_scale=1.0)

    def deviation(b):
        return max(np.abs(b[a - 5, :a] - fine[a - 5, :a]).max() for a in range(N - 1, 5, -10))

    assert deviation(default) < 1.5e-3
    assert deviation(unscaled) > 5.0e-3


@pytest.mark.parametrize("method", ["vbd", "xpbd", "xpbd-sweep"])
def test_cavity_sag_matches_closed_form(device, method):
    """The cavity as a cantilevered tube under its own weight (0.1 kg over 50 mm, g = 0.981 m/s^2, E 2 MPa, nu 0 so
    G = E / 2), clamped over its three fixed rings (z < 5 mm) and free over L = 50 - 4.17 mm: Euler-Bernoulli bending
    w L^4 / (8 E I) plus Timoshenko shear w L^2 / (2 kappa G A) (thin-walled tube, kappa = 1/2) = 0.153 mm. At the
    default 20 substeps per physics step, with the per-vertex tet solve (``cavity_solver = "vbd"``), the free end
    ring's mean drop after 2 s with zero actions matches it within 10 % (measured 0.145 mm: the coarse linear tets are
    a little stiffer than the beam; it creeps there, 0.13 mm after 1 s, because one sweep per substep relaxes a stiff
    body's slow modes over many substeps). With XPBD's tets (the task's default, known limitation) it sags > 10x the
    closed form within 0.5 s (measured 12 mm: one sweep per substep does not reach a stiff tet's modulus; 320
    substeps per physics step 0.18 mm). With the rotations refreshed once per sweep (``cavity_rotation_update =
    "sweep"``) XPBD's cavity is stiffer, 5-20x the closed form (measured 2.5 mm at 0.5 s; 1.6 mm at 1 s)."""
    env = make(device, 1, randomize_loop_state=False, bank_settle_steps=1, cavity_solver=method.removesuffix("-sweep"),
               cavity_rotation_update="sweep" if method.endswith("-sweep") else "vertex")
    env.reset()
    for _ in range(40 if method == "vbd" else 5):
        env.step(torch.zeros(1, 5))
    end = state(env)["cavity"][0, [outer_node(j, AXIAL - 1) for j in range(ANGULAR)]].mean(axis=0)
    free = LENGTH - 2.0 * LENGTH / (AXIAL - 1)  # the last fixed ring is at z = 4.17 mm
    w = 0.1 * 0.981 / LENGTH
    youngs = 2.0e6
    inertia = math.pi / 4.0 * (R_OUT**4 - R_IN**4)
    area = math.pi * (R_OUT**2 - R_IN**2)
    expected = w * free**4 / (8.0 * youngs * inertia) + w * free**2 / (2.0 * 0.5 * 0.5 * youngs * area)
    assert expected == pytest.approx(1.53e-4, rel=0.01)
    if method == "vbd":
        assert -end[1] == pytest.approx(expected, rel=0.1), (-end[1], expected)
    elif method == "xpbd":
        assert -end[1] > 10.0 * expected, (-end[1], expected)
    else:
        assert 5.0 * expected < -end[1] < 20.0 * expected, (-end[1], expected)
