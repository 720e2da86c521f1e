"""Kernels of the geodesic tethers: per-env long-range attachments from cloth particles to their nearest anchor,
with lengths that follow cuts and grasps (``SceneBuilder.add_cloth(tethers=True)``; host side in ``lapwarp.world``).

A tether (Kim et al. 2012, "long range attachments") keeps particle ``p`` within its rest geodesic distance
``dist[env, p]`` of its anchor ``source[env, p]``: an inequality constraint, so a sheet can fold and swing but the
weight of the whole sheet never has to travel through dozens of edge constraints within one sweep. Anchors are the
particles that cannot move on their own: pinned (inverse mass 0) or held by a stiff attachment (a grasp, a held
corner). The distances are geodesics over the *present* triangles of each env, so a cut lengthens them (the path
goes around the cut) and a piece cut off every anchor has no tether and falls.

Distances are computed per env on the device by fast sweeping (Zhao 2005) of the triangle-mesh eikonal update
(Kimmel and Sethian 1998): one thread per env visits the triangles in four precomputed orders (sorted along four
directions) and updates each corner from the other two, from a virtual point source when both carry the same
anchor and along the edges otherwise. One round (four orders) converges on a convex sheet; a cut adds rounds. An env
is swept only after its anchors or its triangles changed (``status`` 2: start again from the anchors) and until a
round changes nothing (``status`` 1 -> 0); before that, unreached particles have no tether (never a wrong one).
"""

from __future__ import annotations

import warp as wp

INF = 1.0e30
# an attached particle whose effective inverse mass (attachments folded in) is below this fraction of its own is an
# anchor: the attachment, not the sheet, decides where it goes within a sweep
ANCHOR_MASS_RATIO = 1.0e-3
# a distance must drop by more than this (m) to count as a change: float rounding cannot keep a round "changing"
CHANGE_TOL = 1.0e-7


@wp.kernel
def detect_anchor_changes(
    particles: wp.array(dtype=wp.int32),
    inv_mass: wp.array2d(dtype=float),
    w_eff: wp.array2d(dtype=float),
    anchor: wp.array2d(dtype=wp.int32),
    status: wp.array2d(dtype=wp.int32),
):
    """``anchor[env, p]`` = 1 for pinned or stiffly attached particles; a change restarts the env's sweep."""
    env, i = wp.tid()
    p = particles[i]
    w = inv_mass[env % inv_mass.shape[0], p]
    flag = int(0)
    if w == 0.0:
        flag = 1
    elif w_eff[env % w_eff.shape[0], p] <= ANCHOR_MASS_RATIO * w:
        flag = 1
    if anchor[env, p] != flag:
        anchor[env, p] = flag
        status[env, 0] = 2


@wp.kernel
def detect_cut_changes(
    tri_element: wp.array(dtype=wp.int32),
    tri_active: wp.array2d(dtype=wp.int32),
    seen: wp.array2d(dtype=wp.int32),
    status: wp.array2d(dtype=wp.int32),
):
    """``seen`` mirrors the tethered cloths' triangle masks; a removed (or restored) triangle restarts the sweep."""
    env, f = wp.tid()
    e = tri_element[f]
    if e < 0:
        return
    a = tri_active[env, e]
    if seen[env, f] != a:
        seen[env, f] = a
        status[env, 0] = 2


@wp.func
def _relax(env: int, k: int, cand: float, src: int, rest: wp.array(dtype=wp.vec3), dist: wp.array2d(dtype=float),
           source: wp.array2d(dtype=wp.int32)) -> int:
    # a geodesic is never shorter than the straight rest distance to its anchor (guards the eikonal estimate)
    c = wp.max(cand, wp.length(rest[k] - rest[src]))
    if c < dist[env, k] - CHANGE_TOL:
        dist[env, k] = c
        source[env, k] = src
        return 1
    return 0


@wp.func
def _update_corner(env: int, i: int, j: int, k: int, rest: wp.array(dtype=wp.vec3), dist: wp.array2d(dtype=float),
                   source: wp.array2d(dtype=wp.int32)) -> int:
    """Improve corner ``k`` of triangle (i, j, k) from ``i`` and ``j``; 1 if it changed."""
    changed = int(0)
    xi = rest[i]
    xj = rest[j]
    xk = rest[k]
    si = source[env, i]
    sj = source[env, j]
    di = dist[env, i]
    dj = dist[env, j]
    if si >= 0:
        changed += _relax(env, k, di + wp.length(xk - xi), si, rest, dist, source)
    if sj >= 0:
        changed += _relax(env, k, dj + wp.length(xk - xj), sj, rest, dist, source)
    if si >= 0 and si == sj:
        # virtual point source s in the triangle's plane with |s - i| = di, |s - j| = dj, across edge ij from k; the
        # straight ray s -> k must enter the triangle through edge ij for the estimate to hold
        e = xj - xi
        c = wp.length(e)
        if c > 0.0:
            u = e / c
            r = xk - xi
            kx = wp.dot(r, u)
            ky = wp.length(r - u * kx)
            sx = (di * di - dj * dj + c * c) / (2.0 * c)
            sy2 = di * di - sx * sx
            if sy2 >= 0.0 and ky > 0.0:
                sy = -wp.sqrt(sy2)
                t = -sy / (ky - sy)
                xc = sx + t * (kx - sx)
                if xc >= 0.0 and xc <= c:
                    dx = kx - sx
                    dy = ky - sy
                    changed += _relax(env, k, wp.sqrt(dx * dx + dy * dy), si, rest, dist, source)
    return changed


@wp.kernel
def sweep_geodesics(
    particles: wp.array(dtype=wp.int32),
    tris: wp.array(dtype=wp.vec3i),
    tri_element: wp.array(dtype=wp.int32),
    order: wp.array2d(dtype=wp.int32),
    rest: wp.array(dtype=wp.vec3),
    anchor: wp.array2d(dtype=wp.int32),
    tri_active: wp.array2d(dtype=wp.int32),
    masked: int,
    max_rounds: int,
    dist: wp.array2d(dtype=float),
    source: wp.array2d(dtype=wp.int32),
    status: wp.array2d(dtype=wp.int32),
):
    """One thread per env: restart from the anchors if asked (status 2), then up to ``max_rounds`` rounds of the four
    sweep orders; status 0 once a round changed nothing."""
    env = wp.tid()
    st = status[env, 0]
    if st == 0:
        return
    if st == 2:
        for i in range(particles.shape[0]):
            p = particles[i]
            if anchor[env, p] != 0:
                dist[env, p] = 0.0
                source[env, p] = p
            else:
                dist[env, p] = INF
                source[env, p] = -1
    st = int(1)
    for _round in range(max_rounds):
        changed = int(0)
        for o in range(order.shape[0]):
            for n in range(order.shape[1]):
                f = order[o, n]
                if masked != 0:
                    e = tri_element[f]
                    if e >= 0:
                        if tri_active[env, e] == 0:
                            continue
                t = tris[f]
                changed += _update_corner(env, t[0], t[1], t[2], rest, dist, source)
                changed += _update_corner(env, t[1], t[2], t[0], rest, dist, source)
                changed += _update_corner(env, t[2], t[0], t[1], rest, dist, source)
        if changed == 0:
            st = 0
            break
    status[env, 0] = st


@wp.kernel
def solve_geodesic_tethers(
    particles: wp.array(dtype=wp.int32),
    dist: wp.array2d(dtype=float),
    source: wp.array2d(dtype=wp.int32),
    inv_mass: wp.array2d(dtype=float),
    q: wp.array2d(dtype=wp.vec3),
):
    """Pull each tethered particle back onto the sphere of its geodesic distance about its anchor (unilateral; the
    anchor does not move: it is pinned or held, and never itself tethered)."""
    env, i = wp.tid()
    p = particles[i]
    a = source[env, p]
    if a < 0 or a == p:
        return
    if inv_mass[env % inv_mass.shape[0], p] == 0.0:
        return
    x = q[env, p]
    xa = q[env, a]
    d = x - xa
    length = wp.length(d)
    m = dist[env, p]
    if length > m:
        q[env, p] = xa + d * (m / length)
