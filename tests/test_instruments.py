"""Tests of pivotized (TPSD) instruments against an independent NumPy implementation of sofa_env's maps.

The reference below builds every rotation from explicit Rx, Ry, Rz matrices and never calls the Warp
code; it mirrors sofa_env's ``ptsd_to_pose`` and ``PivotizedRigidObject.set_state``.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
import warp as wp

from lapwarp.instruments import (
    STATE_LIMITS_VIOLATED,
    WORKSPACE_VIOLATED,
    TPSDConfig,
    TPSDInstruments,
    discrete_action_table,
)
from lapwarp.kernels import kinematics

# float32 state tolerances (m, rad) named once.
POS_TOL = 1e-5
ANGLE_TOL = 1e-5
ROT_TOL = 1e-5
N_CASES = 1000

# --------------------------------------------------------------------------------------------------
# Independent NumPy reference (float64)
# --------------------------------------------------------------------------------------------------


def rx(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def ry(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def rz(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def euler_xyz(angles) -> np.ndarray:
    return rx(angles[0]) @ ry(angles[1]) @ rz(angles[2])


def homogeneous(rotation: np.ndarray, translation) -> np.ndarray:
    t = np.eye(4)
    t[:3, :3] = rotation
    t[:3, 3] = translation
    return t


def ref_fk(rcm_pos, rcm_rot: np.ndarray, ptsd) -> np.ndarray:
    """sofa_env ptsd_to_pose: T(rcm) R(rcm) R_xyz(tilt, pan, spin) T(0, 0, depth), radians and metres."""
    pan, tilt, spin, depth = ptsd
    return (
        homogeneous(rcm_rot, rcm_pos)
        @ homogeneous(euler_xyz([tilt, pan, spin]), [0.0, 0.0, 0.0])
        @ homogeneous(np.eye(3), [0.0, 0.0, depth])
    )


def quat_to_matrix(q) -> np.ndarray:
    """Rotation matrix of a unit quaternion in (x, y, z, w) order."""
    x, y, z, w = q
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )


def matrix_to_quat(m: np.ndarray) -> np.ndarray:
    """(x, y, z, w) quaternion of a rotation matrix (Shepperd's method)."""
    tr = np.trace(m)
    if tr > 0:
        s = math.sqrt(tr + 1.0) * 2
        q = [(m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s, 0.25 * s]
    elif m[0, 0] > m[1, 1] and m[0, 0] > m[2, 2]:
        s = math.sqrt(1.0 + m[0, 0] - m[1, 1] - m[2, 2]) * 2
        q = [0.25 * s, (m[0, 1] + m[1, 0]) / s, (m[0, 2] + m[2, 0]) / s, (m[2, 1] - m[1, 2]) / s]
    elif m[1, 1] > m[2, 2]:
        s = math.sqrt(1.0 + m[1, 1] - m[0, 0] - m[2, 2]) * 2
        q = [(m[0, 1] + m[1, 0]) / s, 0.25 * s, (m[1, 2] + m[2, 1]) / s, (m[0, 2] - m[2, 0]) / s]
    else:
        s = math.sqrt(1.0 + m[2, 2] - m[0, 0] - m[1, 1]) * 2
        q = [(m[0, 2] + m[2, 0]) / s, (m[1, 2] + m[2, 1]) / s, 0.25 * s, (m[1, 0] - m[0, 1]) / s]
    return np.array(q)


def transform_row(t: np.ndarray) -> np.ndarray:
    """4x4 homogeneous matrix -> Warp transform row (px, py, pz, qx, qy, qz, qw)."""
    return np.concatenate([t[:3, 3], matrix_to_quat(t[:3, :3])])


def angle_diff(a, b):
    return (np.asarray(a) - np.asarray(b) + np.pi) % (2 * np.pi) - np.pi


def random_rcm(rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    return rng.uniform(-0.5, 0.5, 3), euler_xyz(rng.uniform(-np.pi, np.pi, 3))


def to_deg_m(ptsd_rad_m: np.ndarray) -> np.ndarray:
    return np.asarray(ptsd_rad_m) * np.array([180 / np.pi] * 3 + [1.0])


# --------------------------------------------------------------------------------------------------
# Helpers around the Warp side
# --------------------------------------------------------------------------------------------------


def eval_1d(kernel, inputs: list[np.ndarray], dtypes: list, out_dtype, device: str) -> np.ndarray:
    arrays = [
        wp.array(np.asarray(x, dtype=np.float32), dtype=t, device=device) for x, t in zip(inputs, dtypes, strict=True)
    ]
    out = wp.zeros(len(inputs[0]), dtype=out_dtype, device=device)
    wp.launch(kernel, dim=len(inputs[0]), inputs=arrays, outputs=[out], device=device)
    return out.numpy().astype(np.float64)


def make_rng(num_envs: int, seed: int, device: str) -> wp.array:
    values = np.random.default_rng(seed).integers(0, 2**32, num_envs, dtype=np.uint32)
    return wp.array(values, dtype=wp.uint32, device=device)


def float_array(values: np.ndarray, device: str) -> wp.array:
    return wp.array(np.asarray(values, dtype=np.float32), dtype=float, device=device)


# --------------------------------------------------------------------------------------------------
# Forward and inverse maps
# --------------------------------------------------------------------------------------------------


def test_euler_xyz_to_quat_matches_rx_ry_rz(device):
    rng = np.random.default_rng(1)
    angles = rng.uniform(-np.pi, np.pi, (N_CASES, 3))
    quats = eval_1d(kinematics.eval_euler_xyz_to_quat, [angles], [wp.vec3], wp.quat, device)
    for a, q in zip(angles, quats, strict=True):
        np.testing.assert_allclose(quat_to_matrix(q), euler_xyz(a), atol=ROT_TOL)


def test_ptsd_to_transform_matches_numpy(device):
    rng = np.random.default_rng(2)
    rcms, ptsds, refs = [], [], []
    for _ in range(N_CASES):
        pos, rot = random_rcm(rng)
        ptsd = np.concatenate([rng.uniform(-np.pi, np.pi, 3), rng.uniform(-0.1, 0.3, 1)])
        rcms.append(transform_row(homogeneous(rot, pos)))
        ptsds.append(ptsd)
        refs.append(ref_fk(pos, rot, ptsd))
    tips = eval_1d(kinematics.eval_ptsd_to_transform, [rcms, ptsds], [wp.transform, wp.vec4], wp.transform, device)
    for tip, ref in zip(tips, refs, strict=True):
        np.testing.assert_allclose(tip[:3], ref[:3, 3], atol=POS_TOL)
        np.testing.assert_allclose(quat_to_matrix(tip[3:]), ref[:3, :3], atol=ROT_TOL)


def test_instrument_poses_follow_config_in_degrees(device):
    """The host API (degrees, metres, RCM Euler angles) against the NumPy map, 1,024 (env, instrument) pairs."""
    rng = np.random.default_rng(3)
    configs = [
        TPSDConfig(
            rcm_position=rng.uniform(-0.3, 0.3, 3),
            rcm_euler_deg=rng.uniform(-180, 180, 3),
            state_low=(-180, -180, -180, -1),
            state_high=(180, 180, 180, 1),
        )
        for _ in range(4)
    ]
    inst = TPSDInstruments(configs, num_envs=256, device=device)
    ptsd_deg = np.concatenate([rng.uniform(-180, 180, (256, 4, 3)), rng.uniform(0.0, 0.3, (256, 4, 1))], axis=-1)
    inst.set_ptsd(ptsd_deg)
    np.testing.assert_allclose(inst.ptsd_numpy(), ptsd_deg, atol=1e-4)
    poses = inst.pose.numpy()
    for k, c in enumerate(configs):
        rot = euler_xyz(np.radians(c.rcm_euler_deg))
        np.testing.assert_allclose(quat_to_matrix(inst.rcm.numpy()[0, k, 3:]), rot, atol=ROT_TOL)
        for env in range(256):
            ref = ref_fk(
                np.array(c.rcm_position), rot, np.radians(ptsd_deg[env, k, :3]).tolist() + [ptsd_deg[env, k, 3]]
            )
            np.testing.assert_allclose(poses[env, k, :3], ref[:3, 3], atol=POS_TOL)
            np.testing.assert_allclose(quat_to_matrix(poses[env, k, 3:]), ref[:3, :3], atol=ROT_TOL)
    np.testing.assert_allclose(inst.tip_positions_numpy(), poses[..., :3])


def _random_branch_states(rng: np.random.Generator, n: int) -> np.ndarray:
    """States on the inverse's branch, away from its singularities (|pan| = 90 deg, depth = 0, +-180 deg).

    In float32 the tip position carries ~1e-7 m of rounding; the recovered tilt amplifies it by
    1 / (depth cos(pan)), so depth >= 5 cm and |pan| <= 75 deg keep the error below 1e-5 rad.
    """
    return np.stack(
        [
            rng.uniform(-np.radians(75), np.radians(75), n),
            rng.uniform(-np.radians(175), np.radians(175), n),
            rng.uniform(-np.radians(175), np.radians(175), n),
            rng.uniform(0.05, 0.3, n),
        ],
        axis=1,
    )


def test_point_to_ptsd_round_trip(device):
    rng = np.random.default_rng(4)
    states = _random_branch_states(rng, N_CASES)
    rcms, points = [], []
    for s in states:
        pos, rot = random_rcm(rng)
        rcms.append(transform_row(homogeneous(rot, pos)))
        points.append(ref_fk(pos, rot, s)[:3, 3])
    spins = rng.uniform(-1.0, 1.0, N_CASES)
    out = eval_1d(kinematics.eval_point_to_ptsd, [rcms, points, spins], [wp.transform, wp.vec3, float], wp.vec4, device)
    np.testing.assert_allclose(angle_diff(out[:, :2], states[:, :2]), 0.0, atol=ANGLE_TOL)
    np.testing.assert_allclose(out[:, 2], spins, atol=1e-6)
    np.testing.assert_allclose(out[:, 3], states[:, 3], atol=POS_TOL)


def test_transform_to_ptsd_round_trip(device):
    rng = np.random.default_rng(5)
    states = _random_branch_states(rng, N_CASES)
    rcms, tips = [], []
    for s in states:
        pos, rot = random_rcm(rng)
        rcms.append(transform_row(homogeneous(rot, pos)))
        tips.append(transform_row(ref_fk(pos, rot, s)))
    out = eval_1d(kinematics.eval_transform_to_ptsd, [rcms, tips], [wp.transform, wp.transform], wp.vec4, device)
    np.testing.assert_allclose(angle_diff(out[:, :3], states[:, :3]), 0.0, atol=ANGLE_TOL)
    np.testing.assert_allclose(out[:, 3], states[:, 3], atol=POS_TOL)


def test_transform_to_ptsd_reproduces_pose_on_every_branch(device):
    """Off the inverse's branch (|pan| > 90 deg), at gimbal lock and at depth 0 the state may differ, the pose not."""
    rng = np.random.default_rng(6)
    states = np.concatenate([rng.uniform(-np.pi, np.pi, (N_CASES, 3)), rng.uniform(0.0, 0.3, (N_CASES, 1))], axis=1)
    states[:20, 0] = np.pi / 2  # gimbal lock: only tilt + spin is defined
    states[20:40, 0] = -np.pi / 2
    states[40:60, 3] = 0.0  # tip at the RCM: direction undefined, orientation decides
    rcms, tips, refs = [], [], []
    for s in states:
        pos, rot = random_rcm(rng)
        rcms.append(transform_row(homogeneous(rot, pos)))
        refs.append(ref_fk(pos, rot, s))
        tips.append(transform_row(refs[-1]))
    out = eval_1d(kinematics.eval_transform_to_ptsd, [rcms, tips], [wp.transform, wp.transform], wp.vec4, device)
    assert np.all(np.abs(out[:, 0]) <= np.pi / 2 + 1e-6)
    assert np.all(out[:, 3] >= 0.0)
    again = eval_1d(kinematics.eval_ptsd_to_transform, [rcms, out], [wp.transform, wp.vec4], wp.transform, device)
    for tip, ref in zip(again, refs, strict=True):
        np.testing.assert_allclose(tip[:3], ref[:3, 3], atol=POS_TOL)
        np.testing.assert_allclose(quat_to_matrix(tip[3:]), ref[:3, :3], atol=1e-4)


# --------------------------------------------------------------------------------------------------
# One sub-step: state limits, workspace, flags
# --------------------------------------------------------------------------------------------------


def ref_step(rcm_pos, rcm_rot, ptsd, delta, low, high, ws_low, ws_high):
    """sofa_env set_state on float32 inputs; returns (ptsd, tip position or None when rejected, flags, margin)."""
    old = ptsd.astype(np.float32)
    proposed = old + delta.astype(np.float32)
    invalid = (low.astype(np.float32) > proposed) | (proposed > high.astype(np.float32))
    new = np.where(invalid, old, proposed).astype(np.float64)
    tip = ref_fk(rcm_pos, rcm_rot, new)[:3, 3]
    outside = np.any((ws_low > tip) | (tip > ws_high))
    # Distance of the tip to the nearest workspace face: float32 and float64 may disagree right on it.
    margin = np.min(np.abs(np.concatenate([tip - ws_low, ws_high - tip])))
    flags = (STATE_LIMITS_VIOLATED if invalid.any() else 0) | (WORKSPACE_VIOLATED if outside else 0)
    return (old.astype(np.float64) if outside else new), flags, margin


def test_step_matches_set_state_semantics(device):
    """Random states and deltas, many of them crossing limits, against the NumPy set_state."""
    rng = np.random.default_rng(7)
    num_envs = 512
    config = TPSDConfig(
        rcm_position=(0.01, -0.02, 0.03),
        rcm_euler_deg=(170.0, 20.0, -30.0),
        start_ptsd=(0.0, 0.0, 0.0, 0.1),
        state_low=(-30.0, -40.0, -90.0, 0.05),
        state_high=(30.0, 40.0, 90.0, 0.15),
        workspace_low=(0.0, -np.inf, -0.2),  # cuts off roughly a third of the reachable tips
        workspace_high=(np.inf, 0.0, 0.2),
    )
    other = TPSDConfig()  # second instrument, default limits and infinite workspace
    inst = TPSDInstruments([config, other], num_envs=num_envs, device=device)
    low = np.radians(config.state_low[:3]).tolist() + [config.state_low[3]]
    high = np.radians(config.state_high[:3]).tolist() + [config.state_high[3]]
    low, high = np.array(low), np.array(high)
    start = rng.uniform(low, high, (num_envs, 4))
    inst.set_ptsd(np.stack([to_deg_m(start), np.zeros((num_envs, 4))], axis=1))
    old = inst.ptsd.numpy()[:, 0].astype(np.float64)
    delta = rng.uniform(-1.0, 1.0, (num_envs, 4)) * np.array([0.3, 0.3, 0.3, 0.03])
    delta_all = np.zeros((num_envs, 2, 4), np.float32)
    delta_all[:, 0] = delta
    inst.delta.assign(delta_all)
    inst.step()

    ptsd, flags, poses = inst.ptsd.numpy(), inst.flags.numpy(), inst.pose.numpy()
    rot = euler_xyz(np.radians(config.rcm_euler_deg))
    ws_low, ws_high = np.array(config.workspace_low), np.array(config.workspace_high)
    seen = {0: 0, STATE_LIMITS_VIOLATED: 0, WORKSPACE_VIOLATED: 0, STATE_LIMITS_VIOLATED | WORKSPACE_VIOLATED: 0}
    compared = 0
    for env in range(num_envs):
        exp_ptsd, exp_flags, margin = ref_step(
            np.array(config.rcm_position), rot, old[env], delta[env], low, high, ws_low, ws_high
        )
        if margin < 1e-5:
            continue
        compared += 1
        seen[exp_flags] += 1
        assert flags[env, 0] == exp_flags, env
        np.testing.assert_allclose(ptsd[env, 0], exp_ptsd, atol=1e-6)
        ref = ref_fk(np.array(config.rcm_position), rot, exp_ptsd)
        np.testing.assert_allclose(poses[env, 0, :3], ref[:3, 3], atol=POS_TOL)
        np.testing.assert_allclose(quat_to_matrix(poses[env, 0, 3:]), ref[:3, :3], atol=ROT_TOL)
    assert compared > 0.95 * num_envs
    assert all(count > 10 for count in seen.values()), seen  # every branch was exercised
    # The untouched second instrument moved by its zero delta: no flags, same state.
    assert np.all(flags[:, 1] == 0)
    np.testing.assert_allclose(ptsd[:, 1], 0.0)


def test_state_limits_keep_old_value_per_component(device):
    inst = TPSDInstruments([TPSDConfig(start_ptsd=(85.0, 0.0, 0.0, 0.1))], num_envs=2, device=device)
    delta = np.zeros((2, 1, 4), np.float32)
    delta[0, 0] = [np.radians(10.0), np.radians(5.0), 0.0, 0.01]  # pan would reach 95 deg > 90
    inst.delta.assign(delta)
    inst.step()
    ptsd = inst.ptsd_numpy()
    np.testing.assert_allclose(ptsd[0, 0], [85.0, 5.0, 0.0, 0.11], atol=1e-4)
    np.testing.assert_allclose(ptsd[1, 0], [85.0, 0.0, 0.0, 0.1], atol=1e-5)  # env 1 had no delta
    assert inst.flags_numpy().tolist() == [[STATE_LIMITS_VIOLATED], [0]]
    # Flags describe the last update only.
    inst.delta.zero_()
    inst.step()
    assert inst.flags_numpy().tolist() == [[0], [0]]


def test_workspace_rejects_whole_update(device):
    # RCM at the origin, shaft along +z: the tip is at z = depth * cos(pan) * cos(tilt).
    config = TPSDConfig(start_ptsd=(0.0, 0.0, 0.0, 0.1), workspace_low=(-1, -1, -1), workspace_high=(1, 1, 0.12))
    inst = TPSDInstruments([config], num_envs=3, device=device)
    pose_before = inst.pose.numpy().copy()
    delta = np.zeros((3, 1, 4), np.float32)
    delta[0, 0] = [np.radians(5.0), 0.0, np.radians(3.0), 0.05]  # tip z = 0.149 > 0.12: nothing may change
    delta[1, 0] = [np.radians(5.0), 0.0, np.radians(3.0), 0.01]  # tip z = 0.1096: accepted
    delta[2, 0] = [np.radians(95.0), 0.0, 0.0, 0.05]  # pan over its limit (kept), depth pushes tip out
    inst.delta.assign(delta)
    inst.step()
    ptsd = inst.ptsd_numpy()
    np.testing.assert_allclose(ptsd[0, 0], [0.0, 0.0, 0.0, 0.1], atol=1e-6)
    np.testing.assert_allclose(inst.pose.numpy()[0], pose_before[0])
    np.testing.assert_allclose(ptsd[1, 0], [5.0, 0.0, 3.0, 0.11], atol=1e-4)
    np.testing.assert_allclose(ptsd[2, 0], [0.0, 0.0, 0.0, 0.1], atol=1e-6)
    np.testing.assert_allclose(inst.tip_positions_numpy()[1, 0, 2], 0.11 * math.cos(math.radians(5.0)), atol=POS_TOL)
    assert inst.flags_numpy()[:, 0].tolist() == [
        WORKSPACE_VIOLATED,
        0,
        STATE_LIMITS_VIOLATED | WORKSPACE_VIOLATED,
    ]


# --------------------------------------------------------------------------------------------------
# Actions
# --------------------------------------------------------------------------------------------------


def test_continuous_action_moves_a_times_vmax_times_dt(device):
    rng = np.random.default_rng(8)
    num_envs, dt = 64, 0.01
    v_max = (20.0, 15.0, 30.0, 0.02)
    configs = [TPSDConfig(start_ptsd=(0, 10, 0, 0.1), max_velocity=v_max), TPSDConfig(start_ptsd=(5, 0, 0, 0.05))]
    # Two PTSDA-like blocks of five: column 4 and 9 belong to someone else (e.g. a jaw).
    inst = TPSDInstruments(configs, num_envs=num_envs, device=device, action_columns=[0, 5])
    assert inst.action_dim == 9
    actions = rng.uniform(-1.0, 1.0, (num_envs, 10))
    actions[0, :] = 0.0  # env 0 does nothing: other envs' actions must not move it
    actions[1, :4] = [3.0, -7.0, np.nan, 1.0]  # clipped to [1, -1, 0, 1]
    before = inst.ptsd_numpy()
    before_pose = inst.pose.numpy()
    inst.apply_actions(float_array(actions, device), dt)
    moved = inst.ptsd_numpy() - before
    expected = np.stack([actions[:, 0:4] * v_max * dt, actions[:, 5:9] * np.array(TPSDConfig().max_velocity) * dt], 1)
    expected[1, 0] = np.array([1.0, -1.0, 0.0, 1.0]) * v_max * dt
    np.testing.assert_allclose(moved[..., :3], expected[..., :3], atol=1e-4)  # deg
    np.testing.assert_allclose(moved[..., 3], expected[..., 3], atol=1e-7)  # m
    np.testing.assert_allclose(inst.pose.numpy()[0], before_pose[0])
    assert np.all(inst.flags_numpy() == 0)

    # The delta buffer stays: step() repeats the sub-step (frame skip).
    inst.step()
    np.testing.assert_allclose(inst.ptsd_numpy() - before, 2 * expected, atol=2e-4)


def test_discrete_action_table_layout():
    table = discrete_action_table([1.0, 2.0, 3.0])
    assert table.shape == (7, 3)
    expected = np.array([[1, 0, 0], [-1, 0, 0], [0, 2, 0], [0, -2, 0], [0, 0, 3], [0, 0, -3], [0, 0, 0]])
    np.testing.assert_array_equal(table, expected)
    assert discrete_action_table([0.5] * 4).shape == (9, 4)
    for bad in ([], [[1.0, 2.0]], [-1.0], [np.inf]):
        with pytest.raises(ValueError):
            discrete_action_table(bad)


def test_discrete_actions_move_one_component(device):
    dt = 0.02
    magnitude = (10.0, 20.0, 30.0, 0.01)
    start = (0.0, 0.0, 0.0, 0.1)
    inst = TPSDInstruments([TPSDConfig(start_ptsd=start, discrete_magnitude=magnitude)], num_envs=11, device=device)
    indices = np.arange(11, dtype=np.int32)  # 0..8 valid, 9 and 10 out of range -> no-op
    indices[10] = -3
    inst.apply_discrete(wp.array(indices, dtype=wp.int32, device=device), dt)
    moved = inst.ptsd_numpy()[:, 0] - np.array(start)
    expected = np.zeros((11, 4))
    for i in range(4):
        expected[2 * i, i] = magnitude[i] * dt
        expected[2 * i + 1, i] = -magnitude[i] * dt
    np.testing.assert_allclose(moved[:, :3], expected[:, :3], atol=1e-4)
    np.testing.assert_allclose(moved[:, 3], expected[:, 3], atol=1e-7)
    # 2-D indices work as well.
    inst.apply_discrete(wp.array(indices.reshape(11, 1), dtype=wp.int32, device=device), dt)
    np.testing.assert_allclose(inst.ptsd_numpy()[:, 0, 3] - start[3], 2 * expected[:, 3], atol=1e-7)


# --------------------------------------------------------------------------------------------------
# Reset
# --------------------------------------------------------------------------------------------------


def _noisy_config() -> TPSDConfig:
    # The workspace cuts the noise region roughly in half, so rejection sampling has work to do.
    return TPSDConfig(
        rcm_position=(0.0, 0.0, 0.0),
        start_ptsd=(0.0, 0.0, 0.0, 0.1),
        state_low=(-20.0, -20.0, -90.0, 0.08),
        state_high=(20.0, 20.0, 90.0, 0.2),
        workspace_low=(-1.0, -1.0, -1.0),
        workspace_high=(0.0, 1.0, 1.0),
        ptsd_noise=(30.0, 30.0, 45.0, 0.05),
        rcm_position_noise=(0.01, 0.01, 0.0),
    )


def test_masked_reset_touches_only_masked_envs_and_stays_inside(device):
    num_envs = 256
    config = _noisy_config()
    inst = TPSDInstruments([config, TPSDConfig(start_ptsd=(0, 0, 0, 0.05))], num_envs=num_envs, device=device)
    # Move everything away from the start first.
    inst.apply_actions(float_array(np.full((num_envs, 8), -0.5), device), 0.1)
    mask = (np.arange(num_envs) % 3 == 0).astype(np.int32)
    rng = make_rng(num_envs, 0, device)
    rng_before = rng.numpy().copy()
    before = {name: getattr(inst, name).numpy().copy() for name in ("ptsd", "pose", "rcm", "flags")}
    inst.reset(wp.array(mask, dtype=wp.int32, device=device), rng)

    keep = mask == 0
    for name, old in before.items():
        np.testing.assert_array_equal(getattr(inst, name).numpy()[keep], old[keep], err_msg=name)
    np.testing.assert_array_equal(rng.numpy()[keep], rng_before[keep])
    assert np.all(rng.numpy()[~keep] != rng_before[~keep])

    ptsd = inst.ptsd_numpy()[~keep]
    tips = inst.tip_positions_numpy()[~keep]
    rcm = inst.rcm.numpy()[~keep]
    # Instrument 0: inside limits and workspace, noisy (not all equal), RCM noise within bounds.
    low, high = np.array(config.state_low), np.array(config.state_high)
    assert np.all(ptsd[:, 0] >= low - 1e-4) and np.all(ptsd[:, 0] <= high + 1e-4)
    assert np.all(tips[:, 0, 0] <= 1e-6)
    assert np.ptp(ptsd[:, 0, 0]) > 10.0 and np.ptp(ptsd[:, 0, 3]) > 0.02
    assert np.all(np.abs(rcm[:, 0, :2]) <= 0.01 + 1e-7) and np.ptp(rcm[:, 0, 0]) > 0.01
    np.testing.assert_allclose(rcm[:, 0, 2], 0.0)
    # x <= 0 needs pan <= asin(0.01 / 0.08) = 7.2 deg while the noise box reaches the 20 deg limit:
    # rejection sampling did its work.
    assert ptsd[:, 0, 0].max() < 7.5 and ptsd[:, 0, 0].min() < -10.0
    # Instrument 1 has no noise: exactly its start state. Poses agree with the NumPy map.
    np.testing.assert_allclose(ptsd[:, 1], np.tile([0, 0, 0, 0.05], (len(ptsd), 1)), atol=1e-6)
    for p, tip, r in zip(ptsd, tips, rcm, strict=True):
        ref = ref_fk(r[0, :3], quat_to_matrix(r[0, 3:]), np.radians(p[0, :3]).tolist() + [p[0, 3]])
        np.testing.assert_allclose(tip[0], ref[:3, 3], atol=POS_TOL)
    assert np.all(inst.flags_numpy()[~keep] == 0)


def test_reset_is_reproducible_and_seed_dependent(device):
    num_envs = 32
    results = []
    for seed in (5, 5, 6):
        inst = TPSDInstruments([_noisy_config()], num_envs=num_envs, device=device)
        inst.reset(rng=make_rng(num_envs, seed, device))
        results.append((inst.ptsd.numpy(), inst.rcm.numpy()))
    np.testing.assert_array_equal(results[0][0], results[1][0])
    np.testing.assert_array_equal(results[0][1], results[1][1])
    assert not np.allclose(results[0][0], results[2][0])


def test_reset_without_rng_and_fallback(device):
    # Start state outside the workspace and a noise region that never reaches it: fall back to the start.
    config = TPSDConfig(
        start_ptsd=(10.0, 0.0, 0.0, 0.1),
        workspace_low=(-1.0, -1.0, -1.0),
        workspace_high=(1.0, 1.0, 0.0),
        ptsd_noise=(5.0, 5.0, 5.0, 0.01),
        rcm_euler_deg=(0.0, 0.0, 0.0),
    )
    inst = TPSDInstruments([config], num_envs=4, device=device, max_reset_tries=7)
    inst.reset(rng=make_rng(4, 1, device))
    np.testing.assert_allclose(inst.ptsd_numpy()[:, 0], np.tile([10.0, 0.0, 0.0, 0.1], (4, 1)), atol=1e-5)
    inst.set_ptsd([1.0, 2.0, 3.0, 0.15])
    inst.reset()
    np.testing.assert_allclose(inst.ptsd_numpy()[:, 0], np.tile([10.0, 0.0, 0.0, 0.1], (4, 1)), atol=1e-5)


# --------------------------------------------------------------------------------------------------
# Validation
# --------------------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "kwargs",
    [
        {"rcm_position": (0.0, 0.0)},
        {"rcm_euler_deg": (0.0, np.nan, 0.0)},
        {"start_ptsd": (0.0, 0.0, 0.0, 0.0, 0.0)},
        {"start_ptsd": (100.0, 0.0, 0.0, 0.1)},  # outside the default state limits
        {"state_low": (10.0, -90.0, -90.0, 0.0), "state_high": (-10.0, 90.0, 90.0, 0.2)},
        {"workspace_low": (0.0, 0.0, 1.0), "workspace_high": (1.0, 1.0, 0.0)},
        {"workspace_low": (np.nan, 0.0, 0.0)},
        {"max_velocity": (20.0, 20.0, -1.0, 0.02)},
        {"max_velocity": (20.0, 20.0, np.inf, 0.02)},
        {"discrete_magnitude": (1.0, 1.0, 1.0)},
        {"ptsd_noise": (-1.0, 0.0, 0.0, 0.0)},
        {"rcm_position_noise": (0.0, 0.0, -0.1)},
    ],
)
def test_bad_config_raises(kwargs):
    with pytest.raises(ValueError):
        TPSDConfig(**kwargs)


def test_bad_instrument_arguments_raise(device):
    with pytest.raises(ValueError):
        TPSDInstruments([], num_envs=2, device=device)
    with pytest.raises(ValueError):
        TPSDInstruments([TPSDConfig()], num_envs=0, device=device)
    with pytest.raises(ValueError):
        TPSDInstruments([TPSDConfig(), TPSDConfig()], num_envs=2, device=device, action_columns=[0])
    inst = TPSDInstruments([TPSDConfig()], num_envs=2, device=device)
    with pytest.raises(ValueError):
        inst.apply_actions(float_array(np.zeros((2, 3)), device), 0.01)
    with pytest.raises(ValueError):
        inst.apply_actions(float_array(np.zeros((3, 4)), device), 0.01)
    with pytest.raises(ValueError):
        inst.apply_actions(float_array(np.zeros((2, 4)), device), 0.0)
    with pytest.raises(ValueError):
        inst.apply_discrete(wp.zeros((2, 2), dtype=wp.int32, device=device), 0.01)
    with pytest.raises(ValueError):
        inst.set_ptsd(np.zeros(3))


def test_defaults_match_sofa_env():
    c = TPSDConfig()
    assert c.state_low == (-90.0, -90.0, -90.0, 0.0) and c.state_high == (90.0, 90.0, 90.0, 0.2)
    assert c.workspace_low == (-math.inf,) * 3 and c.workspace_high == (math.inf,) * 3
    assert c.max_velocity == (20.0, 20.0, 20.0, 0.02)


@pytest.mark.parametrize("task", ["RopeCutting", "TissueDissection"])
def test_fused_rig_step_matches_the_three_launches(device, task):
    # a rig without jaws (the cautery hooks) steps its instruments and writes its bodies' poses into the World in one
    # launch per physics step (rig.step_and_pose_rig): the same instrument states, flags and body poses as the TPSD
    # step, the body posing and World.set_body_poses apart, under random actions (the same arithmetic per env: bit
    # for bit); the particles too (bit for bit on the CPU; on a GPU within what
    # the contact's atomic sums leave)
    import lapwarp

    out = []
    for fused in (True, False):
        env = lapwarp.make(task, num_envs=2, device=device, seed=5)
        assert not env.rig._jaw_column and env.rig.num_bodies
        env.rig.fuse_step = fused
        rng = np.random.default_rng(0)
        for _ in range(8):
            env.step(torch.as_tensor(rng.uniform(-1, 1, (2, env.action_dim)), dtype=torch.float32))
        w = env.world
        out.append([a.numpy().copy() for a in (env.rig.instruments.ptsd, env.rig.instruments.flags,
                                               w.state.body_q, w.state.particle_q)])
        env.close()
    for fused, apart in zip(out[0][:3], out[1][:3], strict=True):
        np.testing.assert_array_equal(fused, apart)
    if device == "cpu":
        np.testing.assert_array_equal(out[0][3], out[1][3])
    else:
        np.testing.assert_allclose(out[0][3], out[1][3], atol=1e-6)
