"""ThreadInHoleEnv: the procedural scene against sofa_env's facts (task-cards §8: thread node counts and spacing, the
200-node / 540-tet hollow cylinder with its fixed bottom ring, gravity), the success window ``indices_to_check``,
Table C's timing, the STATE / action spaces and the tracking nodes, the configuration checks, the permanent grasp
(the thread's first node stays on the jaw, the thread settles hanging, its stretch under its own weight against the
closed form), the hole's sag under its own weight against the closed form (xfail at the default substeps), the
thread-hole contact (a thread pushed onto the wall's top face does not enter the wall), the scripted expert's success
with the success window and the reward features checked against an independent hull test, seeding (grasper noise per
env and per seed, the thread carried with the grasper at reset) and sofa_env's reset rule that no thread node starts
inside the hole (sofa_env's redraw rule)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
import trimesh
import warp as wp
from reference_geometry import winding_numbers

import lapwarp
from lapwarp.assets import hollow_cylinder_tets
from lapwarp.kernels.kinematics import point_to_ptsd
from lapwarp.tasks.thread_manipulation.thread_in_hole import (
    CONFIGURATIONS,
    HOLE_HOLD_SPEED,
    HOLE_HOLD_SUBSTEPS,
    THREAD_NEWTON_TOLERANCE,
    WORKSPACE,
    ThreadInHoleEnv,
    ThreadInHoleExpert,
    indices_to_check,
)
from lapwarp.vecenv import LapwarpVectorEnv

wp.set_module_options({"enable_backward": False})

#: the task card's table: thread nodes N = floor(L / 2 r) and the success window (``indices_to_check``)
NODES = {"normal": 12, "flexible": 20, "inverted": 12}
WINDOWS = {"normal": range(6, 12), "flexible": range(12, 20), "inverted": range(6, 12)}
NO_NOISE = dict(ptsd_noise=(0.0, 0.0, 0.0, 0.0), rcm_position_noise=(0.0, 0.0, 0.0), rcm_euler_noise=(0.0, 0.0, 0.0))
GRAVITY = 0.981

DEVICE = "cpu"


@pytest.fixture(autouse=True)
def _on_the_test_device(device):
    """Every env of this module on the device the suite runs on (``--device``)."""
    global DEVICE
    DEVICE = device


def make(num_envs: int = 1, **overrides) -> ThreadInHoleEnv:
    """A small env, seed 1 unless given."""
    overrides.setdefault("seed", 1)
    return lapwarp.make("ThreadInHole", num_envs=num_envs, device=DEVICE, **overrides)


def zeros(env: ThreadInHoleEnv) -> torch.Tensor:
    """The no-op action: no PTSD motion."""
    return torch.zeros(env.num_envs, 4, device=env.device)


def column(env: ThreadInHoleEnv, name: str) -> np.ndarray:
    """This step's reward feature ``name`` of every env."""
    return env.features.numpy()[:, env.reward_features.index(name)]


def state(env: ThreadInHoleEnv) -> dict[str, np.ndarray]:
    """The privileged state on the host, float64: thread ``(n, N, 3)``, hole ``(n, 200, 3)``, tip ``(n, 7)``."""
    return {k: v.detach().cpu().numpy().astype(np.float64) for k, v in env.privileged_state().items()}


def thread_speeds(env: ThreadInHoleEnv) -> np.ndarray:
    """Mean node speed of every env's thread, m/s."""
    t = env.thread
    qd = env.world.state.particle_qd.numpy()[:, t.particle_start:t.particle_start + t.particle_count]
    return np.linalg.norm(qd, axis=2).mean(axis=1)


def rotate_inv(q: np.ndarray, v: np.ndarray) -> np.ndarray:
    """``v`` (..., 3) rotated by the inverse of the unit quaternion ``q`` (x, y, z, w; Warp's order)."""
    u, w = -np.asarray(q[:3]), q[3]
    return v + 2.0 * w * np.cross(u, v) + 2.0 * np.cross(u, np.cross(u, v))


def in_tip_frame(tip: np.ndarray, points: np.ndarray) -> np.ndarray:
    """``points`` (..., 3) in the frame of the grasper tip pose ``tip`` (7: position, quaternion xyzw)."""
    return rotate_inv(tip[3:], points - tip[:3])


def carried(tip_from: np.ndarray, tip_to: np.ndarray, points: np.ndarray) -> np.ndarray:
    """``points`` moved rigidly with the tip from pose ``tip_from`` to ``tip_to``."""
    local = in_tip_frame(tip_from, points)
    u, w = np.asarray(tip_to[3:6]), tip_to[6]
    return local + 2.0 * w * np.cross(u, local) + 2.0 * np.cross(u, np.cross(u, local)) + tip_to[:3]


def wall_depth(points: np.ndarray, r_in: float, r_out: float, height: float) -> np.ndarray:
    """How deep each point lies inside the wall's rest material (the annulus r_in < r < r_out, 0 < z < height): the
    distance to the nearest of its four bounding surfaces, negative outside (then minus that distance, roughly)."""
    r = np.hypot(points[..., 0], points[..., 1])
    z = points[..., 2]
    return np.minimum.reduce([r - r_in, r_out - r, height - z, z])


def surface_distances(vertices: np.ndarray, faces: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Distance of each point to the nearest triangle of the surface (trimesh's exact closest point, brute force)."""
    tri = vertices[faces]
    p, f = len(points), len(faces)
    query = np.repeat(points, f, axis=0)
    closest = trimesh.triangles.closest_point(np.tile(tri, (p, 1, 1)), query)
    return np.linalg.norm(closest - query, axis=1).reshape(p, f).min(axis=1)


def hole_clearance(env: ThreadInHoleEnv, hole: np.ndarray, thread: np.ndarray) -> tuple[float, float]:
    """(deepest thread node inside the hole's deformed closed surface, m, 0 when none is; the smallest distance of a
    node outside it to that surface, m)."""
    faces = np.asarray(env.hole.surface_tris) - env.hole.particle_start
    inside = np.abs(winding_numbers(hole, faces, thread)) > 0.5
    distance = surface_distances(hole, faces, thread)
    depth = float(distance[inside].max()) if inside.any() else 0.0
    gap = float(distance[~inside].min()) if (~inside).any() else 0.0
    return depth, gap


def top_ring(name: str) -> np.ndarray:
    """Local indices of the hole's outer top ring, found from the rest mesh (10 nodes at r_out, z = height)."""
    r_in, r_out, height = CONFIGURATIONS[name]["hole"][:3]
    hv, _ = hollow_cylinder_tets(r_in, r_out, height, 2, 10, 10)
    ring = np.nonzero((np.abs(np.hypot(hv[:, 0], hv[:, 1]) - r_out) < 1e-9) & (np.abs(hv[:, 2] - height) < 1e-9))[0]
    assert len(ring) == 10
    return ring


def inside_hull(points: np.ndarray, opening: np.ndarray, r_out: float, margin: float = 0.0) -> np.ndarray:
    """sofa_env's inside test as the task documents it: inside the cylinder of radius ``r_out`` from the floor centre
    (0, 0, 0) to the hole opening, grown by ``margin`` (negative: shrunk)."""
    length = np.linalg.norm(opening)
    axis = opening / length
    s = points @ axis
    radial = np.linalg.norm(points - s[..., None] * axis, axis=-1)
    return (s >= -margin) & (s <= length + margin) & (radial <= r_out + margin)


@wp.kernel
def ptsd_towards(ptsd: wp.array2d(dtype=wp.vec4), rcm: wp.array2d(dtype=wp.transform),
                 target: wp.array(dtype=wp.vec3), error_out: wp.array2d(dtype=float)):
    """PTSD error (rad, rad, 0, m) that puts each env's grasper tip at ``target`` (the expert's machinery)."""
    env = wp.tid()
    s = ptsd[env, 0]
    t = point_to_ptsd(rcm[env, 0], target[env], s[2])
    error_out[env, 0] = t[0] - s[0]
    error_out[env, 1] = t[1] - s[1]
    error_out[env, 2] = 0.0
    error_out[env, 3] = t[3] - s[3]


def move_tip(env: ThreadInHoleEnv, target: np.ndarray) -> None:
    """One env step of continuous actions towards the tip positions ``target`` ``(n, 3)`` (clipped to the maximum
    speeds: 2 degrees, 2 mm per step)."""
    cfg = env.cfg
    dt = cfg.time_step * cfg.frame_skip
    step = np.array([v * k * dt for v, k in zip(cfg.maximum_state_velocity, [math.pi / 180.0] * 3 + [1.0],
                                                 strict=True)])
    error = wp.zeros((env.num_envs, 4), dtype=float, device=env.wp_device)
    wp.launch(ptsd_towards, dim=env.num_envs,
              inputs=[env.rig.ptsd, env.rig.rcm, wp.array(target.astype(np.float32), dtype=wp.vec3,
                                                          device=env.wp_device)],
              outputs=[error], device=env.wp_device)
    env.step(torch.tensor(error.numpy() / step, dtype=torch.float32, device=env.device).clamp(-1.0, 1.0))


# ---------------------------------------------------------------------------- scene
@pytest.mark.parametrize("name", list(CONFIGURATIONS))
def test_scene_matches_sofa_env(name):
    """The task card's table per configuration. Thread: N = floor(L / 2 r) nodes (normal 12, flexible 20, inverted 12),
    rest spacing L / N (the rod's stretch rest lengths, 1e-5 relative), total mass the table's (1, 1, 10 kg; the sum of
    the nodes' masses, 1e-5 relative). Hole: the built object has 200 particles and 540 tets, the tets of
    ``hollow_cylinder_tets`` (as vertex sets); its rest nodes lie on the two radii r_in / r_out, on 10 levels from 0 to
    the height and on 10 angles; at the start (settled at build) every hole node is within 0.5 mm of its rest position
    (sag under gravity; measured at most 0.24 mm, inverted; see ``test_hole_sag_matches_closed_form``). Exactly the 20
    nodes of the bottom ring (z = 0) have inverse mass 0, every other hole node and every thread node a positive one.
    Gravity (0, 0, -0.981) m/s^2 (sofa_env's -981 mm/s^2)."""
    length, radius, _, _, mass = CONFIGURATIONS[name]["thread"]
    r_in, r_out, height = CONFIGURATIONS[name]["hole"][:3]
    N = NODES[name]
    assert N == math.floor(length / (2.0 * radius) + 1e-9)
    env = make(configuration=name)
    thread, hole, model = env.thread, env.hole, env.world.model
    assert thread.particle_count == N and env.cfg.thread_nodes == N
    rest = model.rod_stretch_rest.numpy()[:N - 1]
    np.testing.assert_allclose(rest, length / N, rtol=1e-5)
    inv_mass = model.particle_inv_mass.numpy()[0]
    thread_inv = inv_mass[thread.particle_start:thread.particle_start + N]
    assert np.all(thread_inv > 0.0)
    assert float((1.0 / thread_inv.astype(np.float64)).sum()) == pytest.approx(mass, rel=1e-5)

    hv, ht = hollow_cylinder_tets(r_in, r_out, height, 2, 10, 10)
    assert hv.shape == (200, 3) and ht.shape == (540, 4)
    assert hole.particle_count == 200 and np.asarray(hole.tets).shape == (540, 4)
    # the same tets (the builder may reorder a tet's vertices to orient it)
    np.testing.assert_array_equal(np.sort(np.asarray(hole.tets) - hole.particle_start, axis=1), np.sort(ht, axis=1))
    radii = np.hypot(hv[:, 0], hv[:, 1])
    np.testing.assert_allclose(np.sort(np.unique(np.round(radii, 9))), [r_in, r_out], atol=1e-9)
    np.testing.assert_allclose(np.unique(np.round(hv[:, 2], 9)), np.linspace(0.0, height, 10), atol=1e-9)
    assert len(np.unique(np.round(np.arctan2(hv[:, 1], hv[:, 0]), 6))) == 10
    start = state(env)["hole"][0]
    assert np.abs(start - hv).max() < 5e-4

    hole_inv = inv_mass[hole.particle_start:hole.particle_start + 200]
    fixed = np.nonzero(hole_inv == 0.0)[0]
    np.testing.assert_array_equal(fixed, np.nonzero(hv[:, 2] == 0.0)[0])
    assert len(fixed) == 20 and np.all(hole_inv[hv[:, 2] > 0.0] > 0.0)
    np.testing.assert_allclose(start[fixed], hv[fixed], atol=1e-7)  # the fixed ring did not move
    np.testing.assert_allclose(np.asarray(model.gravity, dtype=np.float64), [0.0, 0.0, -GRAVITY], rtol=1e-6)


@pytest.mark.parametrize("name", list(CONFIGURATIONS))
def test_success_window(name):
    """``indices_to_check`` (the success window) per the task card: normal nodes 6-11 (ratio 0.5), flexible 12-19
    (the last half, 38 mm, is longer than the 30 mm hole, so the ratio drops to floor(30 / 4) / 19 = 7/19), inverted
    6-11 (its hole is 60 mm tall). The same window from the function and on the built env."""
    length, radius = CONFIGURATIONS[name]["thread"][:2]
    height = CONFIGURATIONS[name]["hole"][2]
    N = NODES[name]
    np.testing.assert_array_equal(indices_to_check(N, length, height, 0.5), list(WINDOWS[name]))
    np.testing.assert_array_equal(make(configuration=name).check, list(WINDOWS[name]))
    if name == "flexible":
        assert int((1.0 - 7.0 / 19.0) * N) == 12


# ---------------------------------------------------------------------------- Table C and the spaces
def test_table_c_and_spaces():
    """Table C: 0.01 s physics steps, frame skip 10 (0.1 s per env step), 300 steps. STATE (Table D): 29 values with
    4 tracking nodes [0, 3, 7, 11] (normal), blocks ptsd 4 / pose 7 / center 3 / tracking 12 / opening 3, every value
    inside its declared bounds at reset; the tracking block holds the tracking nodes' positions mapped from the
    workspace box to [-1, 1] (1e-5), the opening block the centre of the hole's outer top ring. Actions: a 4-D Box
    [-1, 1]; with ``action_type="DISCRETE"`` a Discrete(9) whose table is +-[15, 15, 15, 10] / [20, 20, 20, 20] on
    the diagonal (the discrete over the maximum speeds) and a no-op last row; a discrete step of pan + moves the pan
    by 1.5 degrees (15 degrees/s x 0.1 s)."""
    venv = LapwarpVectorEnv("ThreadInHole", num_envs=1, device=DEVICE, seed=1)
    env = venv.env
    assert env.cfg.time_step == 0.01 and env.cfg.frame_skip == 10 and env.dt == pytest.approx(0.1)
    assert env.max_episode_length == 300
    assert env.observation_dim == 29 and env.action_dim == 4
    assert venv.single_observation_space.shape == (29,) and venv.single_action_space.shape == (4,)
    assert float(venv.single_action_space.low.min()) == -1.0 and float(venv.single_action_space.high.max()) == 1.0
    layout = env.obs_layout
    assert dict(zip(layout.names, layout.sizes, strict=True)) == dict(ptsd=4, pose=7, center=3, tracking=12,
                                                                      opening=3)
    obs, _ = venv.reset(seed=1)
    assert obs.shape == (1, 29) and venv.single_observation_space.contains(obs[0])
    np.testing.assert_array_equal(env.params.tracking.numpy(), [0, 3, 7, 11])
    low, high = np.asarray(WORKSPACE[0]), np.asarray(WORKSPACE[1])
    s = state(env)
    expected = 2.0 * (s["thread"][0, [0, 3, 7, 11]] - low) / (high - low) - 1.0
    np.testing.assert_allclose(obs[0, layout.slice("tracking")].reshape(4, 3), expected, atol=1e-5)
    opening = s["hole"][0, top_ring("normal")].mean(axis=0)
    np.testing.assert_allclose(obs[0, layout.slice("opening")], 2.0 * (opening - low) / (high - low) - 1.0, atol=1e-5)

    discrete = LapwarpVectorEnv("ThreadInHole", num_envs=1, device=DEVICE, seed=1, action_type="DISCRETE")
    assert discrete.single_action_space.n == 9 and discrete.env.is_discrete
    table = discrete.env.discrete_actions.cpu().numpy()
    assert table.shape == (9, 4)
    np.testing.assert_allclose(table[0::2][:4], np.diag([0.75, 0.75, 0.75, 0.5]), atol=1e-7)
    np.testing.assert_allclose(table[1::2][:4], -np.diag([0.75, 0.75, 0.75, 0.5]), atol=1e-7)
    np.testing.assert_array_equal(table[8], 0.0)
    before = discrete.env.rig.ptsd.numpy()[0, 0].copy()
    obs, reward, *_ = discrete.step(np.array([0]))
    change = discrete.env.rig.ptsd.numpy()[0, 0] - before
    assert math.degrees(change[0]) == pytest.approx(1.5, abs=1e-3)
    np.testing.assert_allclose(change[1:], 0.0, atol=1e-6)
    assert obs.shape == (1, 29) and np.isfinite(reward).all()


@pytest.mark.parametrize("name, count, tracking", [
    ("normal", 0, []),
    ("normal", 6, [0, 2, 4, 6, 8, 11]),
    ("flexible", 4, [0, 6, 12, 19]),
    ("flexible", 20, list(range(20))),
])
def test_tracking_points(name, count, tracking):
    """STATE has 4 + 7 + 3 + 3 T + 3 values (T = 0: 17, T = 6: 35, T = 20: 77) with the tracking nodes at
    ``linspace(0, N - 1, T)`` (the card's flexible [0, 6, 12, 19]); T = N (flexible 20) is allowed."""
    env = make(configuration=name, num_thread_tracking_points=count)
    assert env.observation_dim == 4 + 7 + 3 + 3 * count + 3
    np.testing.assert_array_equal(env.params.tracking.numpy()[:count], tracking)
    assert env.get_observations()["policy"].shape == (1, env.observation_dim)


@pytest.mark.parametrize("overrides, message", [
    (dict(configuration="bogus"), "configuration"),
    (dict(configuration="Normal"), "configuration"),  # names are case-sensitive
    (dict(num_thread_tracking_points=13), "exceeds the 12 thread nodes"),
    (dict(configuration="inverted", num_thread_tracking_points=13), "exceeds the 12 thread nodes"),
    (dict(configuration="flexible", num_thread_tracking_points=21), "num_thread_tracking_points"),
    (dict(hole_solver="xpbd", hole_hold_speed=1e-4), "only with hole_solver 'vbd'"),
    (dict(hole_hold_speed=-1e-4), "hole_hold_speed"),
])
def test_invalid_configuration_raises(overrides, message):
    """An unknown configuration name, more tracking points than the thread has nodes, or a hole hold with the XPBD
    hole (which has none) or below zero raises ValueError naming the problem (before anything is built)."""
    with pytest.raises(ValueError, match=message):
        make(**overrides)


def test_thread_newton_tolerance():
    """The thread's Newton tolerance reaches the World where the register-resident solve runs the thread (the GPU's
    default: ``THREAD_NEWTON_TOLERANCE`` there, 0 on the serial walk, which runs every step, and a value with it
    refused; an explicit value with the pcr solve kept); with the
    default 3e-4 m the thread of 2 envs ends 10 no-op env steps within 1e-6 m of every step's (measured 1.4e-7 m on the
    CPU: the second steps skipped correct at most 2.4e-7 m along the expert's episodes, docs/physics.md)."""
    default = make()
    assert default.world.rod_newton_tolerance == (THREAD_NEWTON_TOLERANCE if default.wp_device.is_cuda else 0.0)
    assert default.world.chain_register_split == default.wp_device.is_cuda  # two threads per chain on CUDA
    assert THREAD_NEWTON_TOLERANCE == 3e-4
    with pytest.raises(ValueError, match="thread_newton_tolerance=.*register-resident, hybrid and pcr chain solves"):
        make(chain_solver="thomas", thread_newton_tolerance=3e-4)
    out = []
    assert make(chain_solver="pcr").world.rod_newton_tolerance == 0.0
    assert make(chain_solver="pcr", thread_newton_tolerance=1e-4).world.rod_newton_tolerance == 1e-4
    for tolerance, expected in ((0.0, 0.0), (None, THREAD_NEWTON_TOLERANCE)):
        env = make(num_envs=2, chain_solver="registers", thread_newton_tolerance=tolerance)
        assert env.world.rod_newton_tolerance == expected
        env.reset()
        for _ in range(10):
            env.step(zeros(env))
        out.append(env.world.positions(env.thread))
    assert np.abs(out[0] - out[1]).max() <= 1e-6


# ---------------------------------------------------------------------------- the grasp and the hanging thread
def test_grasp_holds_and_thread_settles_hanging():
    """4 envs (seed 1, the reset noise), 30 no-op steps after reset: the grasper does not move, the thread's first
    node stays within 1 mm of where it started in the tip frame (measured: < 1e-4 mm; it is attached) and the
    first segment's direction in the tip frame turns by less than 5 degrees (its orientation is held); the thread
    settles (mean node speed below 5 mm/s; measured 0.002-0.004 mm/s), and the ``thread_velocity`` feature is that
    speed over the 346.4 mm workspace diagonal (1e-6). It hangs: the free end lies below the first node by at least
    80 % of the thread's rest span (L (N - 1) / N; measured 98.3-100.0 %: a stiff rod leaving the jaw at the jaw's
    angle, drooping towards the vertical, and stretched by its weight)."""
    env = make(num_envs=4)
    N = NODES["normal"]
    span = 0.05 * (N - 1) / N
    s0 = state(env)
    local0 = np.stack([in_tip_frame(s0["tip"][e], s0["thread"][e]) for e in range(4)])
    for _ in range(30):
        env.step(zeros(env))
    s1 = state(env)
    np.testing.assert_array_equal(s1["tip"], s0["tip"])
    local1 = np.stack([in_tip_frame(s1["tip"][e], s1["thread"][e]) for e in range(4)])
    assert np.linalg.norm(local1[:, 0] - local0[:, 0], axis=1).max() < 1e-3
    d0, d1 = local0[:, 1] - local0[:, 0], local1[:, 1] - local1[:, 0]
    cos = np.sum(d0 * d1, axis=1) / np.linalg.norm(d0, axis=1) / np.linalg.norm(d1, axis=1)
    assert np.degrees(np.arccos(np.clip(cos, -1.0, 1.0))).max() < 5.0
    speed = thread_speeds(env)
    assert speed.max() < 5e-3, speed
    np.testing.assert_allclose(column(env, "thread_velocity"), speed / math.sqrt(3 * 0.2**2), atol=1e-6)
    drop = (s1["thread"][:, 0, 2] - s1["thread"][:, -1, 2]) / span
    assert drop.min() >= 0.8, drop


@pytest.mark.parametrize("name", list(CONFIGURATIONS))
def test_hanging_stretch_matches_closed_form(name):
    """A thread hanging still and free (no noise, the grasper started 30 mm shallower, depth 60 mm, so that even the
    flexible thread clears the hole; from the default start it rests against the outer wall) stretches under its own
    weight: segment k carries the weight of the nodes below it, so its axial strain is g cos(angle) sum_{j > k} m_j /
    (E pi a^2) (E and the beam radius a of the table: normal 0.16 % mean, flexible 1.7 %, inverted 0.06 %). After the
    build's settling and 20 no-op steps the thread is vertical within 2 degrees and every interior segment (1 to
    N - 2) matches that within 2 % (measured: within 0.8 %). The first segment, held at the jaw, is stretched more
    (measured: 1.6 x normal, 1.05 x flexible, 4 x inverted, i.e. 7 / 7 / 15 micrometres: XPBD's residual at the
    attachment); the last one carries only half a node."""
    length, _, youngs, beam_radius, _ = CONFIGURATIONS[name]["thread"]
    env = make(configuration=name, start_ptsd=(60.0, 0.0, 180.0, 0.06), **NO_NOISE)
    N = NODES[name]
    for _ in range(20):
        env.step(zeros(env))
    assert thread_speeds(env)[0] < 1e-3
    x = state(env)["thread"][0]
    segment = x[1:] - x[:-1]
    lengths = np.linalg.norm(segment, axis=1)
    cos = -segment[:, 2] / lengths
    assert cos.min() > math.cos(math.radians(2.0))
    t = env.thread
    mass = 1.0 / env.world.model.particle_inv_mass.numpy()[0, t.particle_start:t.particle_start + N].astype(float)
    below = np.cumsum(mass[::-1])[::-1][1:]
    expected = GRAVITY * cos * below / (youngs * math.pi * beam_radius**2)
    strain = lengths / (length / N) - 1.0
    np.testing.assert_allclose(strain[1:-1], expected[1:-1], rtol=0.02)


@pytest.mark.parametrize("solver, substeps, rotations, refresh", [
    ("vbd", None, "sweep", 1), ("vbd", None, "sweep", 4), ("vbd", None, "vertex", 1), ("xpbd", 40, "sweep", 1)])
def test_hole_sag_matches_closed_form(solver, substeps, rotations, refresh):
    """The normal configuration's hole, settled at build (50 physics steps, no contact with the thread): a column
    under its own weight with its bottom fixed sags at its top by rho g h^2 / (2 E), rho = 10 kg over the annulus'
    volume pi (r_out^2 - r_in^2) h: 15.6 micrometres. The outer top ring's mean sag matches that within 25 % (a
    linear-tet wall with Poisson's ratio 0.3 and a fixed bottom ring is somewhat stiffer than the 1D column) with the
    default per-vertex solve at the default 4 substeps (its tets' rotations refreshed once per physics step, the
    default ``hole_rotation_refresh=4``, once per sweep, or by every vertex; measured 14.23 / 14.26 um at 4 / 1),
    and with XPBD's tets at 40 substeps (measured 15.2 um; 80: 13.7 um). XPBD's tets at the default substeps sag
    149 um (9.6 x: one sweep per substep does not reach a stiff tet's modulus;
    ``test_hole_sag_with_xpbd_at_default_substeps_is_far_too_soft``)."""
    r_in, r_out, height, youngs, mass = CONFIGURATIONS["normal"]["hole"]
    overrides = {} if substeps is None else dict(physics_substeps=substeps)
    env = make(hole_solver=solver, hole_rotation_update=rotations, hole_rotation_refresh=refresh, **overrides)
    assert (env.world.tet_rotation_update, env.world.tet_rotation_refresh) == (rotations, refresh)
    # the lagged per-vertex sweep runs capped at 64 registers (one wave of 4,096 envs on an H200), the other sweeps
    # uncapped; the rods' sweep and the contact's pose kernel at 64 in every configuration
    lagged_vertex = (solver, rotations) == ("vbd", "sweep")
    caps = {"solve_rods_fused": 64, "pose_shapes_and_tools": 64}
    assert env.world.default_register_caps == ({**caps, "solve_vertices_fused": 64} if lagged_vertex else caps)
    assert thread_speeds(env)[0] < 1e-3
    density = mass / (math.pi * (r_out**2 - r_in**2) * height)
    expected = density * GRAVITY * height**2 / (2.0 * youngs)
    sag = height - state(env)["hole"][0, top_ring("normal"), 2].mean()
    assert sag == pytest.approx(expected, rel=0.25), (sag, expected)


def test_hole_sag_with_xpbd_at_default_substeps_is_far_too_soft():
    """The control of the test above: XPBD's tets at the default 4 substeps sag > 5x the closed form (measured 149 um
    against 15.6 um), so the test above can fail."""
    r_in, r_out, height, youngs, mass = CONFIGURATIONS["normal"]["hole"]
    env = make(hole_solver="xpbd")
    expected = mass / (math.pi * (r_out**2 - r_in**2) * height) * GRAVITY * height**2 / (2.0 * youngs)
    sag = height - state(env)["hole"][0, top_ring("normal"), 2].mean()
    assert sag > 5.0 * expected, (sag, expected)


# ---------------------------------------------------------------------------- contact
def end_above_the_wall(env: ThreadInHoleEnv, radius: float = 0.008) -> dict[str, np.ndarray]:
    """Bring env 0's thread end 5 mm above the wall's top face at ``radius`` (30 steps of a 0.3-gain servo, then 10
    still steps); the state there, checked clear of the wall."""
    r_in, r_out, height = CONFIGURATIONS["normal"]["hole"][:3]
    above = np.array([radius, 0.0, height + 0.005])
    for _ in range(30):
        s = state(env)
        move = 0.3 * (above - s["thread"][0, -1])
        move *= min(1.0, 0.003 / np.linalg.norm(move))
        move_tip(env, s["tip"][:, :3] + move)
    for _ in range(10):
        env.step(zeros(env))
    s0 = state(env)
    end = s0["thread"][0, -1]
    assert np.linalg.norm(end[:2] - above[:2]) < 2e-3 and abs(end[2] - above[2]) < 2e-3, end
    assert wall_depth(s0["thread"][0], r_in, r_out, height).max() < -2e-3  # clear of the wall before the descent
    return s0


def test_thread_does_not_enter_the_wall():
    """Normal configuration, 1 env, seed 1. The grasper brings the thread's free end 5 mm above the wall's top face
    at radius 8 mm (between r_in 5 and r_out 25 mm; 30 steps of a 0.3-gain servo, then 10 still steps), then
    descends 12 mm (1 mm per step) and holds 10 steps. Control: carried rigidly with the grasper, the thread's
    pre-descent shape would put its free end 6.3 mm deep inside the wall's rest material (asserted > 5 mm: the
    descent is deep enough). Result: at every step of the descent no thread node is inside the wall's rest material
    by more than 1 mm (measured: none inside; max -0.8 mm), no node is inside the hole's deformed closed surface
    (winding number), every node keeps at least 1 mm from that surface (the tube radius is 2 mm; measured 1.99 mm),
    and the grasp holds throughout (first node within 1 mm of the jaw in the tip frame; measured < 1e-4 mm). On the
    frictionless top face the stiff, slightly tilted thread slides outward (measured: the end stops at the outer
    rim, r = 25.9 mm, z = 28.7 mm, where rigid carrying would put it at z = 23.7 mm inside the wall)."""
    r_in, r_out, height = CONFIGURATIONS["normal"]["hole"][:3]
    env = make()
    node0 = in_tip_frame(state(env)["tip"][0], state(env)["thread"][0, 0])
    s0 = end_above_the_wall(env)

    worst_depth, worst_inside, worst_gap, worst_grip = -1.0, 0.0, 1.0, 0.0
    for k in range(22):
        move_tip(env, s0["tip"][:, :3] - np.array([0.0, 0.0, 0.001 * min(k + 1, 12)]))
        s = state(env)
        worst_depth = max(worst_depth, float(wall_depth(s["thread"][0], r_in, r_out, height).max()))
        depth, gap = hole_clearance(env, s["hole"][0], s["thread"][0])
        worst_inside, worst_gap = max(worst_inside, depth), min(worst_gap, gap)
        worst_grip = max(worst_grip, float(np.linalg.norm(in_tip_frame(s["tip"][0], s["thread"][0, 0]) - node0)))
    assert s0["tip"][0, 2] - s["tip"][0, 2] == pytest.approx(0.012, abs=2e-4)
    rigid = carried(s0["tip"][0], s["tip"][0], s0["thread"][0, -1])
    assert wall_depth(rigid, r_in, r_out, height) > 5e-3, rigid
    assert worst_depth <= 1e-3, worst_depth
    assert worst_inside == 0.0, worst_inside
    assert worst_gap >= 1e-3, worst_gap
    assert worst_grip < 1e-3, worst_grip


def test_hole_held_at_rest_wakes_under_the_thread():
    """The hole is held at rest by default (``hole_hold_speed``, ``World.tet_hold_speed``): the descent of
    ``test_thread_does_not_enter_the_wall`` (30 + 10 approach steps, a 12 mm descent into the wall's top face, 10
    still steps), then 30 more still steps, with the hold and without (``hole_hold_speed=0``). The hole is held
    (its quiet counter saturated) when the thread arrives above it, the thread's contact wakes it and keeps it awake
    while the thread rests on it, and it gives way as the unheld hole does: its deepest push 0.601 against 0.599 mm
    (within 3 %), every step's push within 5 um of the unheld run's (measured 1.6 um: the unheld hole still creeps ~1
    um while the held one waits) and the final hole within 1 um (measured 0.013 um). A hold that missed the contact
    would leave the held hole undented (its push ~0, against the 0.6 mm asserted below)."""
    runs = {}
    for speed in (None, 0.0):
        env = make(hole_hold_speed=speed)
        rest = state(env)["hole"][0]
        s0 = end_above_the_wall(env)
        quiet = [int(env.world._hold_quiet.numpy()[0])]
        push = []
        for k in range(52):
            if k < 22:
                move_tip(env, s0["tip"][:, :3] - np.array([0.0, 0.0, 0.001 * min(k + 1, 12)]))
            else:
                env.step(zeros(env))
            push.append(np.abs(state(env)["hole"][0] - rest).max())
            quiet.append(int(env.world._hold_quiet.numpy()[0]))
        runs[speed] = (env.world.tet_hold_speed, np.array(push), np.array(quiet), state(env)["hole"][0])
    (speed, push, quiet, hole), (off, push_ref, _, hole_ref) = runs[None], runs[0.0]
    assert (speed, off) == (HOLE_HOLD_SPEED, 0.0)
    assert quiet[0] == HOLE_HOLD_SUBSTEPS + 1, quiet[:5]  # held (its sweep skipped) above the wall
    assert (quiet[10:] == 0).all(), quiet  # woken, and kept awake by the resting thread
    assert push.max() > 3e-4 and push.max() == pytest.approx(push_ref.max(), rel=0.03), (push.max(), push_ref.max())
    assert np.abs(push - push_ref).max() < 5e-6
    assert np.abs(hole - hole_ref).max() < 1e-6


@pytest.mark.parametrize("bounds", ["separate", "fused"])
def test_held_hole_keeps_its_contact_boxes(bounds):
    """A held env's hole surface boxes are not recomputed (``contact.surface_leaf_bounds`` returns for it): after 3
    expert steps (held from the 10th substep on) every env's leaf and super-leaf boxes equal those of its vertices as
    they are (min / max, exact), with the boxes computed by either launch form."""
    env = make(num_envs=2)
    env.contact.surface_bounds = bounds
    expert = ThreadInHoleExpert(env)
    for _ in range(3):
        env.step(expert())
    assert (env.world._hold_quiet.numpy() == HOLE_HOLD_SUBSTEPS + 1).all()  # held, its sweeps skipped
    sf = env.contact._surfaces[0]
    clusters, q = sf["clusters"], env.world.state.particle_q.numpy()
    for e in range(2):
        lo, hi = [], []
        for leaf in range(clusters.num_leaves):
            v = q[e, clusters.leaf_verts[clusters.leaf_vert_start[leaf]:clusters.leaf_vert_start[leaf + 1]]]
            lo.append(v.min(axis=0))
            hi.append(v.max(axis=0))
        np.testing.assert_array_equal(sf["leaf_lo"].numpy()[e], np.array(lo))
        np.testing.assert_array_equal(sf["leaf_hi"].numpy()[e], np.array(hi))
        per = clusters.leaves_per_super
        np.testing.assert_array_equal(sf["super_lo"].numpy()[e],
                                      [np.min(lo[k:k + per], axis=0) for k in range(0, len(lo), per)])


def test_thread_does_not_tunnel_into_the_wall_at_full_speed():
    """Normal configuration, 1 env, seed 1, the thread end 5 mm above the middle of the wall's top face (radius 15 mm,
    10 mm from either rim), then 12 steps at the maximum instrument speed towards a tip 30 mm lower: pan, tilt and
    depth bang-bang (+-1: 2 deg, 2 deg, 2 mm a step), so the grasper drives the thread into the wall as fast as an
    agent can. Control: the thread carried rigidly with the tip would put a node deep inside the wall's rest material
    (asserted > 5 mm; measured 8.5 mm of the annulus' 10 mm half-width). Result: the same episode throughout; after
    every step no thread node is inside the hole's deformed closed surface (winding number) nor more than 1 mm inside
    the wall's rest material (measured: none inside, max -0.1 mm), and the grasp holds (first node within 1 mm of the
    jaw in the tip frame). The thread bends and its end slides outward over the frictionless top face and down the
    outside of the wall (at the end r = 36 mm, z = 17 mm)."""
    r_in, r_out, height = CONFIGURATIONS["normal"]["hole"][:3]
    env = make()
    node0 = in_tip_frame(state(env)["tip"][0], state(env)["thread"][0, 0])
    s0 = end_above_the_wall(env, radius=0.015)
    target = wp.array((s0["tip"][:, :3] - np.array([0.0, 0.0, 0.03])).astype(np.float32), dtype=wp.vec3,
                      device=env.wp_device)
    error = wp.zeros((1, 4), dtype=float, device=env.wp_device)
    worst_inside, worst_depth, worst_grip, rigid = 0.0, -1.0, 0.0, -1.0
    for _ in range(12):
        wp.launch(ptsd_towards, dim=1, inputs=[env.rig.ptsd, env.rig.rcm, target], outputs=[error],
                  device=env.wp_device)
        _, _, done, _ = env.step(torch.tensor(np.sign(error.numpy()), dtype=torch.float32, device=env.device))
        assert not bool(done[0])  # the same episode throughout
        s = state(env)
        depth, _ = hole_clearance(env, s["hole"][0], s["thread"][0])
        worst_inside = max(worst_inside, depth)
        worst_depth = max(worst_depth, float(wall_depth(s["thread"][0], r_in, r_out, height).max()))
        worst_grip = max(worst_grip, float(np.linalg.norm(in_tip_frame(s["tip"][0], s["thread"][0, 0]) - node0)))
        moved = carried(s0["tip"][0], s["tip"][0], s0["thread"][0])
        rigid = max(rigid, float(wall_depth(moved, r_in, r_out, height).max()))
    assert rigid > 5e-3, rigid
    assert worst_inside == 0.0, worst_inside
    assert worst_depth <= 1e-3, worst_depth
    assert worst_grip < 1e-3, worst_grip


# ---------------------------------------------------------------------------- the expert, success and features
@pytest.mark.parametrize("name", ["normal", "inverted"])
def test_expert_succeeds_with_the_window_inside(name):
    """2 envs, seed 1, the expert: every env's first episode ends in success (``last_episode_success``, not a time-out)
    within Table C's 300 steps (measured: normal 52 / 46 steps, inverted 42 / 53). With all 12 nodes as tracking points
    the observations expose the whole thread, and ``keep_final_observations`` the terminal state before the auto-reset.
    At reset ``ratio_rope_in_hole`` (the privileged critic's ratio) is 0 and the independent count (below) finds no node
    inside. On every step the ``ratio_rope_in_hole`` feature agrees with an independent count of the nodes inside the
    cylinder from the floor centre to the opening (radius r_out; a node within 10 micrometres of its boundary may count
    either way), and ``successful_task`` is 0 until the episode ends. On the success step: ``successful_task`` 1,
    ``ratio_rope_in_hole`` >= the window's share (6/12; measured 0.5 in all four episodes), every window
    node of the terminal state inside that cylinder, the reward the weighted sum of the step's features (1e-4) including
    the +100 (reward > 99; measured 100.1), and the post-reset critic ratio 0 again (seed 1 draws clean starts;
    see ``test_reset_never_starts_inside_the_hole``). The whole run keeps the thread out of the wall: no node inside the
    hole's deformed closed surface by more than 1 mm."""
    N = NODES[name]
    r_out, height = CONFIGURATIONS[name]["hole"][1:3]
    env = lapwarp.make("ThreadInHole", num_envs=2, device=DEVICE, seed=1, configuration=name,
                       num_thread_tracking_points=N, privileged_critic=True, keep_final_observations=True)
    expert = ThreadInHoleExpert(env)
    window = list(WINDOWS[name])
    weights = np.array([env.reward_weights[f] for f in env.reward_features])
    assert env.reward_weights["successful_task"] == 100.0
    low, high = np.asarray(WORKSPACE[0]), np.asarray(WORKSPACE[1])
    layout, critic = env.obs_layout, env.critic_layout
    ring = top_ring(name)
    faces = np.asarray(env.hole.surface_tris) - env.hole.particle_start

    def unpack(obs_row):
        nodes = low + (obs_row[layout.slice("tracking")].reshape(N, 3) + 1.0) * 0.5 * (high - low)
        opening = low + (obs_row[layout.slice("opening")] + 1.0) * 0.5 * (high - low)
        return nodes, opening

    obs = env.get_observations()
    np.testing.assert_array_equal(obs["critic"][:, critic.slice("ratio")].cpu().numpy(), 0.0)
    s = state(env)
    for e in range(2):
        opening = s["hole"][e, ring].mean(axis=0)
        assert not inside_hull(s["thread"][e], opening, r_out, margin=1e-5).any()
    finished = np.zeros(2, dtype=bool)
    solved = np.zeros(2, dtype=bool)
    worst_inside = 0.0
    for _ in range(env.max_episode_length):
        obs, reward, done, extras = env.step(expert())
        done = done.cpu().numpy()
        features = env.features.numpy()
        ratio, success = column(env, "ratio_rope_in_hole"), column(env, "successful_task")
        final = extras["final_observations"].cpu().numpy()
        s = state(env)
        for e in range(2):
            if finished[e]:
                continue
            if done[e]:
                assert success[e] == 1.0 and env.last_episode_success.numpy()[e] == 1
                assert not bool(extras["time_outs"][e])
                assert ratio[e] >= len(window) / N - 1e-6
                nodes, opening = unpack(final[e])
                assert inside_hull(nodes[window], opening, r_out, margin=1e-5).all()
                assert float(reward[e]) == pytest.approx(float(weights @ features[e]), rel=1e-4)
                assert float(reward[e]) > 99.0
                assert float(obs["critic"][e, critic.slice("ratio")]) == 0.0
                solved[e] = True
                finished[e] = True
                continue
            assert success[e] == 0.0
            opening = s["hole"][e, ring].mean(axis=0)
            sure = inside_hull(s["thread"][e], opening, r_out, margin=-1e-5).sum()
            maybe = inside_hull(s["thread"][e], opening, r_out, margin=1e-5).sum()
            assert sure / N - 1e-6 <= ratio[e] <= maybe / N + 1e-6, (sure, maybe, ratio[e])
            inside = np.abs(winding_numbers(s["hole"][e], faces, s["thread"][e])) > 0.5
            if inside.any():
                worst_inside = max(worst_inside, float(surface_distances(
                    s["hole"][e], faces, s["thread"][e][inside]).max()))
        if finished.all():
            break
    assert finished.all() and solved.all(), (finished.tolist(), solved.tolist())
    assert worst_inside <= 1e-3, worst_inside


def first_episode_successes(env: ThreadInHoleEnv, expert, steps: int) -> tuple[int, int, int]:
    """Run ``expert`` for at most ``steps`` steps: (first episodes that ended in success, first episodes that ended,
    steps run)."""
    finished = np.zeros(env.num_envs, dtype=bool)
    solved = np.zeros(env.num_envs, dtype=bool)
    step = 0
    while step < steps and not finished.all():
        _, _, done, _ = env.step(expert())
        step += 1
        done = done.cpu().numpy().astype(bool)
        solved |= done & ~finished & (env.last_episode_success.numpy() == 1)
        finished |= done
    return int(solved.sum()), int(finished.sum()), step


@pytest.mark.parametrize("action_type, name, steps", [
    ("CONTINUOUS", "flexible", 150), ("CONTINUOUS", "inverted", 150),
    ("DISCRETE", "normal", 200), ("DISCRETE", "flexible", 200), ("DISCRETE", "inverted", 200)])
def test_expert_solves_first_episodes(action_type, name, steps):
    """16 envs, seed 0: at least 15 of the expert's 16 first episodes end in success within ``steps`` (Table C allows
    300). Measured (CPU): 16 / 16 each, the last after 88 / 64 (continuous flexible / inverted), 118 / 130 / 109
    (discrete normal / flexible / inverted) steps. The earlier expert (a fraction of the end's offset per step;
    discrete: the PTSD component with the largest error) failed these: continuous flexible 15 / 16 but one only after
    282 steps and one timed out (a start beside the hole, below its top), continuous inverted 14 / 16 (that start, and
    a steady 4-6 mm swing of the stiff thread above the opening); discrete 0-6 of 32 (32 envs, seeds 0 and 1)."""
    env = make(num_envs=16, seed=0, configuration=name, action_type=action_type)
    solved, finished, ran = first_episode_successes(env, ThreadInHoleExpert(env), steps)
    assert solved >= 15, (solved, finished, ran)


# ---------------------------------------------------------------------------- seeding and reset
def test_seeding_and_the_carried_reset():
    """Two envs of 3 scenes built with seed 7 reset their graspers to the same poses (bit for bit) at build and after
    ``reset()``; seed 8 and the next episode draw other poses; the 3 scenes of one env differ (tips > 1 mm apart).
    Every drawn PTSD lies in sofa_env's noise box around (60, 0, 180 deg, 90 mm): +-15, +-15, 0 (spin exactly 180),
    +-20 mm, and every RCM position within +-10 mm of (100, 0, 150) mm. After every reset the thread is the settled
    noise-free thread carried with the grasper: in the tip frame its first node is within 2 mm of where the noise-free
    start has it, and every node within 0.1 mm (the shape is carried rigidly; measured: < 1e-4 mm)."""
    reference = make(**NO_NOISE)
    s = state(reference)
    local_ref = in_tip_frame(s["tip"][0], s["thread"][0])

    a, b, c = make(num_envs=3, seed=7), make(num_envs=3, seed=7), make(num_envs=3, seed=8)
    tips = [state(env)["tip"] for env in (a, b, c)]
    np.testing.assert_array_equal(tips[0], tips[1])
    assert np.abs(tips[0] - tips[2]).max() > 1e-3
    for e, f in ((0, 1), (0, 2), (1, 2)):
        assert np.linalg.norm(tips[0][e, :3] - tips[0][f, :3]) > 1e-3
    first_episode = tips[0]
    start = np.array([60.0, 0.0, 180.0, 90.0])
    noise = np.array([15.0, 15.0, 0.0, 20.0])
    for reset in range(3):
        if reset:
            a.reset()
            b.reset()
            ta, tb = state(a)["tip"], state(b)["tip"]
            np.testing.assert_array_equal(ta, tb)
            assert np.abs(ta - first_episode).max() > 1e-3
        ptsd = a.rig.ptsd.numpy()[:, 0].astype(np.float64)
        ptsd = np.concatenate([np.degrees(ptsd[:, :3]), 1e3 * ptsd[:, 3:]], axis=1)
        assert np.all(np.abs(ptsd - start) <= noise + 1e-3), ptsd
        rcm = a.rig.rcm.numpy()[:, 0, :3]
        assert np.all(np.abs(rcm - np.array([0.1, 0.0, 0.15])) <= 0.01 + 1e-6), rcm
        s = state(a)
        for e in range(3):
            local = in_tip_frame(s["tip"][e], s["thread"][e])
            assert np.linalg.norm(local[0] - local_ref[0]) < 2e-3
            assert np.linalg.norm(local - local_ref, axis=1).max() < 1e-4


@pytest.mark.parametrize("name, seed", [("normal", 10), ("normal", 23), ("flexible", 10), ("inverted", 23)])
def test_reset_never_starts_inside_the_hole(name, seed):
    """sofa_env's reset rule: no thread frame starts inside the hole's shell (it resets again otherwise). 2 envs
    with the given seed, right after the build's reset: the privileged critic's ratio is 0, the independent count of
    nodes inside the cylinder from the floor to the opening (radius r_out) is 0, and no node lies inside the hole's
    deformed closed surface (winding number) or inside the wall's rest material. The normal thread hangs clear of
    the hole (z >= 27 mm, r >= 29 mm over 192 resets); the flexible and inverted ones reach below its top, and before
    the redraw rule these seeds started inside (flexible seed 10: 1.8 / 5.9 mm inside the wall; inverted seed 23: 5
    nodes inside the hull)."""
    r_in, r_out, height = CONFIGURATIONS[name]["hole"][:3]
    env = make(num_envs=2, configuration=name, seed=seed, privileged_critic=True)
    ratio = env.get_observations()["critic"][:, env.critic_layout.slice("ratio")].cpu().numpy()[:, 0]
    s = state(env)
    ring = top_ring(name)
    faces = np.asarray(env.hole.surface_tris) - env.hole.particle_start
    inside = [int(inside_hull(s["thread"][e], s["hole"][e, ring].mean(axis=0), r_out, margin=-1e-5).sum())
              for e in range(2)]
    in_surface = [int((np.abs(winding_numbers(s["hole"][e], faces, s["thread"][e])) > 0.5).sum()) for e in range(2)]
    depth = wall_depth(s["thread"], r_in, r_out, height).max(axis=1)
    assert ratio.tolist() == [0.0, 0.0] and inside == [0, 0] and in_surface == [0, 0] and np.all(depth <= 0.0), (
        ratio, inside, in_surface, depth)
