"""Kernels that belong to the World itself: per-env RNG seeding and masked state copies."""

from typing import Any

import warp as wp

wp.set_module_options({"enable_backward": False})


@wp.kernel
def init_env_rng(seed: int, rng_out: wp.array(dtype=wp.uint32)):
    env = wp.tid()
    rng_out[env] = wp.rand_init(seed, env)


@wp.kernel
def reseed_env_rng(seed: int, env_mask: wp.array(dtype=wp.int32), rng_out: wp.array(dtype=wp.uint32)):
    env = wp.tid()
    if env_mask[env] != 0:
        rng_out[env] = wp.rand_init(seed, env)


@wp.kernel
def copy_masked_vec3(
    env_mask: wp.array(dtype=wp.int32), src: wp.array2d(dtype=wp.vec3), dst: wp.array2d(dtype=wp.vec3)
):
    env, i = wp.tid()
    if env_mask[env] != 0:
        dst[env, i] = src[env % src.shape[0], i]


@wp.kernel
def clear_masked_flags(env_mask: wp.array(dtype=wp.int32), flags: wp.array(dtype=wp.int32)):
    env = wp.tid()
    if env_mask[env] != 0:
        flags[env] = 0


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
