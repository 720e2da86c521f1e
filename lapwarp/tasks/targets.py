"""Target sampling on the device, per env from its own RNG stream (``wp.func`` only): points in a box kept apart
from other points (targets, sphere layouts) and draws from a precomputed candidate table (points of interest).

Every helper reads the env's RNG state from ``rng[env]``, advances it and writes it back
(``lapwarp.kernels.random``), so draws inside one kernel follow each other in a fixed order and a seed reproduces an
episode.
"""

from __future__ import annotations

import warp as wp

from lapwarp.kernels.random import rand_uniform, rand_uniform_vec3

wp.set_module_options({"enable_backward": False})


@wp.func
def draw_index(rng: wp.array(dtype=wp.uint32), env: int, count: int) -> int:
    """Uniform integer in ``[0, count)``."""
    return wp.min(int(rand_uniform(rng, env, 0.0, float(count))), count - 1)


@wp.func
def sample_separated(
    rng: wp.array(dtype=wp.uint32),
    env: int,
    low: wp.vec3,
    high: wp.vec3,
    others: wp.array2d(dtype=wp.vec3),
    first: int,
    count: int,
    min_distance: float,
    tries: int,
) -> wp.vec3:
    """A point uniform in the box ``[low, high]`` at least ``min_distance`` from ``others[env, first:first+count]``.

    Rejection sampling with a bounded number of draws keeps kernels finite: of up to ``tries`` candidates the first
    that keeps the distance is returned, and if none does, the one farthest from the others (only possible with
    crowded custom settings). With no others the first draw is returned.
    """
    best = wp.vec3(0.0)
    best_d = float(-1.0)
    for _ in range(tries):
        c = rand_uniform_vec3(rng, env, low, high)
        d = float(1.0e9)
        for j in range(count):
            d = wp.min(d, wp.length(c - others[env, first + j]))
        if d > best_d:
            best = c
            best_d = d
        if best_d >= min_distance:
            break
    return best


@wp.func
def draw_candidate(rng: wp.array(dtype=wp.uint32), env: int, candidates: wp.array(dtype=wp.vec3)) -> wp.vec3:
    """One of the precomputed ``candidates``, uniformly."""
    return candidates[draw_index(rng, env, candidates.shape[0])]


@wp.func
def draw_index_where(rng: wp.array(dtype=wp.uint32), env: int, states: wp.array2d(dtype=wp.int32), excluded: int,
                     exclude: int) -> int:
    """Uniform column ``k`` of ``states[env]`` among those whose state is not ``excluded`` (among all columns when
    ``exclude`` is 0): a new active target that is not done yet. 0 when no column qualifies."""
    count = int(0)
    for k in range(states.shape[1]):
        if exclude == 0 or states[env, k] != excluded:
            count += 1
    pick = draw_index(rng, env, wp.max(count, 1))
    seen = int(0)
    for k in range(states.shape[1]):
        if exclude == 0 or states[env, k] != excluded:
            if seen == pick:
                return k
            seen += 1
    return 0
