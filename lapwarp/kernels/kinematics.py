"""Kinematics of pivotized (TPSD) instruments: forward/inverse maps, limits, per-step update and reset.

This module owns the math of instruments that move about a remote centre of motion (RCM), as in
sofa_env's ``PivotizedRigidObject``. Everything here is in radians and metres; the host side
(``lapwarp.instruments``) converts from the degrees used at the API.

Conventions (sofa_env ``ptsd_to_pose``):

- ``ptsd = (pan, tilt, spin, depth)``.
- Euler angles are intrinsic XYZ: ``R_xyz(a) = Rx(a0) @ Ry(a1) @ Rz(a2)``.
- Tip pose ``T = rcm @ R_xyz(tilt, pan, spin) @ Trans(0, 0, depth)``: tilt about local X, pan about
  local Y, spin about the shaft, which is local +Z.

Arrays are env-major: per-env quantities have shape ``(num_envs, num_instruments)`` and kernels are
launched with ``dim=(num_envs, num_instruments)`` (``env, k = wp.tid()``), except the reset kernel,
which runs one thread per env so that an env's RNG state is never shared between threads.
"""

import warp as wp

wp.set_module_options({"enable_backward": False})

# Bits of the per-instrument ``flags`` array, overwritten by every update.
STATE_LIMITS_VIOLATED = wp.constant(1)
WORKSPACE_VIOLATED = wp.constant(2)

# Below this norm (m) a direction from the RCM is undefined; the inverse maps then fall back.
DIRECTION_EPS = wp.constant(1.0e-9)


# ---------------------------------------------------------------------------------------------
# Functions
# ---------------------------------------------------------------------------------------------


@wp.func
def euler_xyz_to_quat(angles: wp.vec3) -> wp.quat:
    """Quaternion of ``Rx(angles[0]) @ Ry(angles[1]) @ Rz(angles[2])`` (intrinsic XYZ, radians)."""
    qx = wp.quat_from_axis_angle(wp.vec3(1.0, 0.0, 0.0), angles[0])
    qy = wp.quat_from_axis_angle(wp.vec3(0.0, 1.0, 0.0), angles[1])
    qz = wp.quat_from_axis_angle(wp.vec3(0.0, 0.0, 1.0), angles[2])
    return qx * qy * qz


@wp.func
def rcm_transform(position: wp.vec3, euler_xyz: wp.vec3) -> wp.transform:
    """RCM frame from a position (m) and intrinsic XYZ Euler angles (rad)."""
    return wp.transform(position, euler_xyz_to_quat(euler_xyz))


@wp.func
def ptsd_to_transform(rcm: wp.transform, ptsd: wp.vec4) -> wp.transform:
    """Tip pose of an instrument: ``rcm @ R_xyz(tilt, pan, spin) @ Trans(0, 0, depth)``.

    Args:
        rcm: remote centre of motion frame (world).
        ptsd: (pan, tilt, spin) in radians and depth in metres.

    Returns:
        The tip pose in world coordinates; its local +Z is the shaft direction.
    """
    q_local = euler_xyz_to_quat(wp.vec3(ptsd[1], ptsd[0], ptsd[2]))
    local = wp.transform(wp.quat_rotate(q_local, wp.vec3(0.0, 0.0, ptsd[3])), q_local)
    return wp.transform_multiply(rcm, local)


@wp.func
def direction_to_pan_tilt(d: wp.vec3) -> wp.vec2:
    """(pan, tilt) whose shaft ``Rx(tilt) @ Ry(pan) @ e_z`` points along ``d`` (RCM frame, any length > 0).

    The shaft direction is ``(sin pan, -sin tilt cos pan, cos tilt cos pan)``. We return the branch
    pan in [-pi/2, pi/2], tilt in (-pi, pi], the one a forward map with |pan| <= 90 deg produces.
    atan2 instead of asin keeps pan accurate near +-90 deg.
    """
    pan = wp.atan2(d[0], wp.sqrt(d[1] * d[1] + d[2] * d[2]))
    tilt = wp.atan2(-d[1], d[2])
    return wp.vec2(pan, tilt)


@wp.func
def point_to_ptsd(rcm: wp.transform, point: wp.vec3, spin: float) -> wp.vec4:
    """PTSD that puts the tip at ``point`` with the given spin.

    Args:
        rcm: remote centre of motion frame (world).
        point: target tip position (world, m).
        spin: spin to return (rad); it does not change the tip position.

    Returns:
        (pan, tilt, spin, depth) with pan in [-pi/2, pi/2], tilt in (-pi, pi], depth >= 0. A point at
        the RCM itself gives pan = tilt = 0.
    """
    d = wp.quat_rotate_inv(wp.transform_get_rotation(rcm), point - wp.transform_get_translation(rcm))
    depth = wp.length(d)
    pan = float(0.0)
    tilt = float(0.0)
    if depth > DIRECTION_EPS:
        pt = direction_to_pan_tilt(d)
        pan = pt[0]
        tilt = pt[1]
    return wp.vec4(pan, tilt, spin, depth)


@wp.func
def matrix_to_euler_xyz(m: wp.mat33) -> wp.vec3:
    """Intrinsic XYZ Euler angles (a0, a1, a2) of ``m = Rx(a0) @ Ry(a1) @ Rz(a2)``, a1 in [-pi/2, pi/2].

    At gimbal lock (|a1| = pi/2) only a0 +- a2 is defined; we return a2 = 0.
    """
    c1 = wp.sqrt(m[1, 2] * m[1, 2] + m[2, 2] * m[2, 2])
    a1 = wp.atan2(m[0, 2], c1)
    a0 = float(0.0)
    a2 = float(0.0)
    if c1 > 1.0e-6:
        a0 = wp.atan2(-m[1, 2], m[2, 2])
        a2 = wp.atan2(-m[0, 1], m[0, 0])
    else:
        a0 = wp.atan2(m[2, 1], m[1, 1])
    return wp.vec3(a0, a1, a2)


@wp.func
def transform_to_ptsd(rcm: wp.transform, tip: wp.transform) -> wp.vec4:
    """Full inverse of ``ptsd_to_transform``, spin included.

    As sofa_env's ``target_pose_to_ptsd``, the tip *position* defines pan, tilt and depth (so the
    returned state always reaches the position), and the orientation only defines spin: the spin whose
    ``Rz(spin)`` is closest to the remaining rotation ``(R_xyz(tilt, pan, 0))^T R_local``. For a pose made
    by the forward map this is exact. A tip at the RCM (no direction) falls back to the Euler
    decomposition of the orientation with depth 0.

    Args:
        rcm: remote centre of motion frame (world).
        tip: tip pose (world).

    Returns:
        (pan, tilt, spin, depth): pan in [-pi/2, pi/2], tilt and spin in (-pi, pi], depth >= 0.
    """
    q_rcm = wp.transform_get_rotation(rcm)
    q_local = wp.quat_inverse(q_rcm) * wp.transform_get_rotation(tip)
    d = wp.quat_rotate_inv(q_rcm, wp.transform_get_translation(tip) - wp.transform_get_translation(rcm))
    depth = wp.length(d)
    result = wp.vec4(0.0, 0.0, 0.0, 0.0)
    if depth > DIRECTION_EPS:
        pt = direction_to_pan_tilt(d)
        q_pt = euler_xyz_to_quat(wp.vec3(pt[1], pt[0], 0.0))
        r = wp.quat_to_matrix(wp.quat_inverse(q_pt) * q_local)
        # Best rotation about z in the Frobenius sense: maximise trace of the xy block.
        spin = wp.atan2(r[1, 0] - r[0, 1], r[0, 0] + r[1, 1])
        result = wp.vec4(pt[0], pt[1], spin, depth)
    else:
        e = matrix_to_euler_xyz(wp.quat_to_matrix(q_local))
        result = wp.vec4(e[1], e[0], e[2], 0.0)
    return result


@wp.func
def is_inside_vec3(p: wp.vec3, low: wp.vec3, high: wp.vec3) -> bool:
    """True when ``low <= p <= high`` componentwise; NaN counts as outside. Infinite bounds work."""
    inside = True
    for i in range(3):
        if not (p[i] >= low[i] and p[i] <= high[i]):
            inside = False
    return inside


@wp.func
def is_inside_vec4(p: wp.vec4, low: wp.vec4, high: wp.vec4) -> bool:
    """True when ``low <= p <= high`` componentwise; NaN counts as outside."""
    inside = True
    for i in range(4):
        if not (p[i] >= low[i] and p[i] <= high[i]):
            inside = False
    return inside


# ---------------------------------------------------------------------------------------------
# Per-step kernels
# ---------------------------------------------------------------------------------------------


@wp.func
def step_tpsd_instrument(
    env: int,
    k: int,
    rcm_in: wp.array2d(dtype=wp.transform),
    state_low: wp.array(dtype=wp.vec4),
    state_high: wp.array(dtype=wp.vec4),
    workspace_low: wp.array(dtype=wp.vec3),
    workspace_high: wp.array(dtype=wp.vec3),
    delta_in: wp.array2d(dtype=wp.vec4),
    ptsd: wp.array2d(dtype=wp.vec4),
    pose: wp.array2d(dtype=wp.transform),
    flags_out: wp.array2d(dtype=wp.int32),
):
    """Advance instrument ``k`` of env ``env`` by one sub-step with sofa_env's ``set_state`` semantics.

    Components of ``ptsd + delta`` outside the state limits keep their old value (each component on
    its own); if the resulting tip leaves the Cartesian workspace the whole update is rejected and
    ``ptsd`` / ``pose`` keep their old values. ``ptsd`` and ``pose`` are read and written in place.
    A NaN component counts as a violation, so a NaN action cannot poison the state.
    """
    old = ptsd[env, k]
    proposed = old + delta_in[env, k]
    low = state_low[k]
    high = state_high[k]
    new = old
    flags = int(0)
    for i in range(4):
        if proposed[i] >= low[i] and proposed[i] <= high[i]:
            new[i] = proposed[i]
        else:
            flags = flags | STATE_LIMITS_VIOLATED
    tip = ptsd_to_transform(rcm_in[env, k], new)
    if is_inside_vec3(wp.transform_get_translation(tip), workspace_low[k], workspace_high[k]):
        ptsd[env, k] = new
        pose[env, k] = tip
    else:
        flags = flags | WORKSPACE_VIOLATED
    flags_out[env, k] = flags


@wp.kernel
def step_tpsd_instruments(
    rcm_in: wp.array2d(dtype=wp.transform),
    state_low: wp.array(dtype=wp.vec4),
    state_high: wp.array(dtype=wp.vec4),
    workspace_low: wp.array(dtype=wp.vec3),
    workspace_high: wp.array(dtype=wp.vec3),
    delta_in: wp.array2d(dtype=wp.vec4),
    ptsd: wp.array2d(dtype=wp.vec4),
    pose: wp.array2d(dtype=wp.transform),
    flags_out: wp.array2d(dtype=wp.int32),
):
    """Advance every instrument by one sub-step with sofa_env's ``set_state`` semantics (``step_tpsd_instrument``),
    a thread per (env, instrument)."""
    env, k = wp.tid()
    step_tpsd_instrument(env, k, rcm_in, state_low, state_high, workspace_low, workspace_high, delta_in, ptsd, pose,
                         flags_out)


@wp.kernel
def compute_continuous_deltas(
    actions: wp.array2d(dtype=float),
    action_columns: wp.array(dtype=wp.int32),
    max_velocity: wp.array(dtype=wp.vec4),
    dt: float,
    delta_out: wp.array2d(dtype=wp.vec4),
):
    """``delta = clip(a, -1, 1) * max_velocity * dt`` per instrument (rad, m per sub-step).

    Instrument ``k`` reads its four action entries from columns ``action_columns[k] .. +3``, so an
    action row may interleave other entries (e.g. a jaw angle after each PTSD block). NaN reads as 0.
    """
    env, k = wp.tid()
    col = action_columns[k]
    v = max_velocity[k]
    d = wp.vec4(0.0)
    for i in range(4):
        a = actions[env, col + i]
        if a != a:
            a = 0.0
        a = wp.clamp(a, -1.0, 1.0)
        d[i] = a * v[i] * dt
    delta_out[env, k] = d


@wp.kernel
def compute_discrete_deltas(
    indices: wp.array2d(dtype=wp.int32),
    table: wp.array2d(dtype=wp.vec4),
    dt: float,
    delta_out: wp.array2d(dtype=wp.vec4),
):
    """``delta = table[k, index] * dt``; ``table`` is ``(num_instruments, 9)`` in rad/s, m/s.

    An index outside ``[0, 8]`` acts as the no-op row (the last one), never as an out-of-bounds read.
    """
    env, k = wp.tid()
    idx = indices[env, k]
    n = table.shape[1]
    if idx < 0 or idx >= n:
        idx = n - 1
    delta_out[env, k] = table[k, idx] * dt


@wp.kernel
def compute_tip_poses(
    rcm_in: wp.array2d(dtype=wp.transform),
    ptsd_in: wp.array2d(dtype=wp.vec4),
    pose_out: wp.array2d(dtype=wp.transform),
    flags_out: wp.array2d(dtype=wp.int32),
):
    """Recompute every tip pose from its state without limit checks (after a direct state write)."""
    env, k = wp.tid()
    pose_out[env, k] = ptsd_to_transform(rcm_in[env, k], ptsd_in[env, k])
    flags_out[env, k] = 0


# ---------------------------------------------------------------------------------------------
# Reset
# ---------------------------------------------------------------------------------------------


@wp.kernel
def reset_tpsd_instruments(
    env_mask: wp.array(dtype=wp.int32),
    rcm_position: wp.array(dtype=wp.vec3),
    rcm_euler: wp.array(dtype=wp.vec3),
    rcm_position_noise: wp.array(dtype=wp.vec3),
    rcm_euler_noise: wp.array(dtype=wp.vec3),
    start_ptsd: wp.array(dtype=wp.vec4),
    ptsd_noise: wp.array(dtype=wp.vec4),
    state_low: wp.array(dtype=wp.vec4),
    state_high: wp.array(dtype=wp.vec4),
    workspace_low: wp.array(dtype=wp.vec3),
    workspace_high: wp.array(dtype=wp.vec3),
    use_noise: int,
    max_tries: int,
    rng: wp.array(dtype=wp.uint32),
    rcm_out: wp.array2d(dtype=wp.transform),
    ptsd_out: wp.array2d(dtype=wp.vec4),
    pose_out: wp.array2d(dtype=wp.transform),
    flags_out: wp.array2d(dtype=wp.int32),
):
    """Reset the instruments of the envs with ``env_mask[env] != 0`` (one thread per env).

    With ``use_noise`` set, each instrument's RCM is the base RCM plus uniform noise in
    +-``rcm_*_noise`` (position in m, XYZ Euler in rad, drawn once per reset as in sofa_env), and its
    state is ``start_ptsd`` plus uniform noise in +-``ptsd_noise``, redrawn until it lies inside the state
    limits and its tip inside the workspace. After ``max_tries`` failed draws the state falls back to
    ``start_ptsd`` (sofa_env would loop forever). Without noise the RNG is not touched. Flags are cleared.
    """
    env = wp.tid()
    if env_mask[env] == 0:
        return
    s = wp.uint32(0)
    if use_noise != 0:
        s = rng[env]
    for k in range(start_ptsd.shape[0]):
        pos = rcm_position[k]
        euler = rcm_euler[k]
        if use_noise != 0:
            pn = rcm_position_noise[k]
            en = rcm_euler_noise[k]
            for i in range(3):
                pos[i] = pos[i] + wp.randf(s, -pn[i], pn[i])
            for i in range(3):
                euler[i] = euler[i] + wp.randf(s, -en[i], en[i])
        rcm = rcm_transform(pos, euler)

        start = start_ptsd[k]
        state = start
        if use_noise != 0:
            noise = ptsd_noise[k]
            found = int(0)
            tries = int(0)
            while found == 0 and tries < max_tries:
                candidate = start
                for i in range(4):
                    candidate[i] = start[i] + wp.randf(s, -noise[i], noise[i])
                tries += 1
                if is_inside_vec4(candidate, state_low[k], state_high[k]):
                    tip_candidate = ptsd_to_transform(rcm, candidate)
                    p = wp.transform_get_translation(tip_candidate)
                    if is_inside_vec3(p, workspace_low[k], workspace_high[k]):
                        state = candidate
                        found = 1

        rcm_out[env, k] = rcm
        ptsd_out[env, k] = state
        pose_out[env, k] = ptsd_to_transform(rcm, state)
        flags_out[env, k] = 0
    if use_noise != 0:
        rng[env] = s


# ---------------------------------------------------------------------------------------------
# Batched evaluation of the maps (1-D launches over any number of cases; experts and tests)
# ---------------------------------------------------------------------------------------------


@wp.kernel
def eval_euler_xyz_to_quat(angles_in: wp.array(dtype=wp.vec3), quat_out: wp.array(dtype=wp.quat)):
    """``quat_out[i] = euler_xyz_to_quat(angles_in[i])`` (radians)."""
    i = wp.tid()
    quat_out[i] = euler_xyz_to_quat(angles_in[i])


@wp.kernel
def eval_ptsd_to_transform(
    rcm_in: wp.array(dtype=wp.transform), ptsd_in: wp.array(dtype=wp.vec4), tip_out: wp.array(dtype=wp.transform)
):
    """``tip_out[i] = ptsd_to_transform(rcm_in[i], ptsd_in[i])``."""
    i = wp.tid()
    tip_out[i] = ptsd_to_transform(rcm_in[i], ptsd_in[i])


@wp.kernel
def eval_point_to_ptsd(
    rcm_in: wp.array(dtype=wp.transform),
    point_in: wp.array(dtype=wp.vec3),
    spin_in: wp.array(dtype=float),
    ptsd_out: wp.array(dtype=wp.vec4),
):
    """``ptsd_out[i] = point_to_ptsd(rcm_in[i], point_in[i], spin_in[i])``."""
    i = wp.tid()
    ptsd_out[i] = point_to_ptsd(rcm_in[i], point_in[i], spin_in[i])


@wp.kernel
def eval_transform_to_ptsd(
    rcm_in: wp.array(dtype=wp.transform), tip_in: wp.array(dtype=wp.transform), ptsd_out: wp.array(dtype=wp.vec4)
):
    """``ptsd_out[i] = transform_to_ptsd(rcm_in[i], tip_in[i])``."""
    i = wp.tid()
    ptsd_out[i] = transform_to_ptsd(rcm_in[i], tip_in[i])
