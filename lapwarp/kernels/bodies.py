"""Instrument body kernels (see :mod:`lapwarp.instrument_shapes`): body poses from a TPSD tip pose and the jaw
angle, and the jaw angle's response to an action."""

import warp as wp

wp.set_module_options({"enable_backward": False})


@wp.func
def hinged_jaw_pose(tip: wp.transform, angle_deg: float) -> wp.transform:
    """A jaw hinged at the tip, rotated by ``angle_deg`` about the tip's local x (jaw A: +angle, jaw B: -angle)."""
    a = angle_deg * (wp.pi / 180.0)
    return wp.transform_multiply(tip, wp.transform(wp.vec3(0.0), wp.quat_from_axis_angle(wp.vec3(1.0, 0.0, 0.0), a)))


@wp.kernel
def pose_instrument_bodies(
    tip_pose: wp.array2d(dtype=wp.transform),
    column: int,
    jaw_angle_deg: wp.array(dtype=float),
    poses_out: wp.array2d(dtype=wp.transform),
):
    # column 0: the shaft at the tip pose; columns 1, 2 (articulated tools): the jaws hinged at the tip, rotated by
    # +angle and -angle about the tip's local x
    env = wp.tid()
    tip = tip_pose[env, column]
    poses_out[env, 0] = tip
    if poses_out.shape[1] > 1:
        poses_out[env, 1] = hinged_jaw_pose(tip, jaw_angle_deg[env])
        poses_out[env, 2] = hinged_jaw_pose(tip, -jaw_angle_deg[env])


@wp.kernel
def step_jaw_angle(
    action: wp.array2d(dtype=float),
    column: int,
    max_speed_deg: float,
    dt: float,
    low: float,
    high: float,
    grasped: wp.array(dtype=wp.int32),
    use_grasped: int,
    angle_deg: wp.array(dtype=float),
):
    # sofa_env: angle += a * max_speed * dt, clipped to the limits; closing is ignored while grasping
    env = wp.tid()
    d = wp.clamp(action[env, column], -1.0, 1.0) * max_speed_deg * dt
    if use_grasped != 0 and grasped[env] != 0 and d < 0.0:
        d = 0.0
    angle_deg[env] = wp.clamp(angle_deg[env] + d, low, high)
