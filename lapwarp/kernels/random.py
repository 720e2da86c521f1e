"""Per-env device RNG helpers (``@wp.func`` only).

Every env owns one ``uint32`` stream state in ``rng[env]``. Warp passes scalars to functions by value,
so a helper that called ``wp.randf(state)`` on a local copy would hand every caller the same number;
these helpers therefore read the state from the array, advance it and write it back.
"""

import warp as wp


@wp.func
def rand_uniform(rng: wp.array(dtype=wp.uint32), env: int, low: float, high: float) -> float:
    s = rng[env]
    x = low + (high - low) * wp.randf(s)
    rng[env] = s
    return x


@wp.func
def rand_uniform_vec3(rng: wp.array(dtype=wp.uint32), env: int, low: wp.vec3, high: wp.vec3) -> wp.vec3:
    s = rng[env]
    x = wp.randf(s)
    y = wp.randf(s)
    z = wp.randf(s)
    rng[env] = s
    return wp.vec3(low[0] + (high[0] - low[0]) * x, low[1] + (high[1] - low[1]) * y, low[2] + (high[2] - low[2]) * z)
