"""Kernels that belong to the World itself: per-env RNG seeding and masked state copies."""

from typing import Any

import warp as wp

wp.set_module_options({"enable_backward": False})


@wp.kernel
def init_env_rng(seed: int, rng_out: wp.array(dtype=wp.uint32)):
    env = wp.tid()
    rng_out[env] = wp.rand_init(seed, env)


@wp.kernel
def copy_masked_2d(env_mask: wp.array(dtype=wp.int32), src: wp.array2d(dtype=Any), dst: wp.array2d(dtype=Any)):
    """Copy row ``env % src.shape[0]`` of ``src`` into row ``env`` of ``dst`` for masked envs (any dtype)."""
    env, i = wp.tid()
    if env_mask[env] != 0:
        dst[env, i] = src[env % src.shape[0], i]


@wp.kernel
def clear_masked_int(env_mask: wp.array(dtype=wp.int32), flags_out: wp.array(dtype=wp.int32)):
    env = wp.tid()
    if env_mask[env] != 0:
        flags_out[env] = 0


@wp.kernel
def write_body_poses(
    poses: wp.array2d(dtype=wp.transform),
    bodies: wp.array(dtype=wp.int32),
    teleport_mask: wp.array(dtype=wp.int32),
    teleport: int,
    body_q: wp.array2d(dtype=wp.transform),
    body_q_prev: wp.array2d(dtype=wp.transform),
    start_body_q: wp.array2d(dtype=wp.transform),
):
    """``body_q[env, bodies[k]] = poses[env, k]``; with ``teleport`` only the masked envs, whose pose at the start of
    the step and start-state pose are set too (no sweep from the old pose after a reset)."""
    env, k = wp.tid()
    b = bodies[k]
    if teleport != 0:
        if teleport_mask[env] == 0:
            return
        body_q_prev[env, b] = poses[env, k]
        start_body_q[env, b] = poses[env, k]
    body_q[env, b] = poses[env, k]
