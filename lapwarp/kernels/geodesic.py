"""Kernels of the geodesic tethers: per-env long-range attachments from cloth particles to the nearest anchor of each
anchor group, with lengths that follow cuts and grasps (``SceneBuilder.add_cloth(tethers=True)``; host side in
``lapwarp.world``).

A tether (Kim et al. 2012, "long range attachments") keeps particle ``p`` within its rest geodesic distance
``dist[env, g * n + p]`` of anchor ``source[env, g * n + p]``, the nearest anchor of group ``g``: an inequality
constraint, so a sheet can fold and swing but the weight of the whole sheet never has to travel through dozens of
edge constraints within one sweep. Anchors are the particles that cannot move on their own: pinned (inverse mass 0) or
held by a stiff attachment (a grasp, a held corner); a group is a set of anchors connected through present triangle
edges (a pinned edge, a grasped patch, one held corner). Every particle is tied to every group (up to ``GROUPS``
distance fields per env): an inextensible sheet satisfies all of them at once, and tying each particle to its nearest
anchor only let a sheet held at two corners be pulled apart where the corners' regions met (docs/physics.md). The
distances are geodesics over the *present* triangles of each env, so a cut lengthens them (the path goes around the
cut) and a piece cut off every anchor has no tether and falls.

Distances are computed per env on the device by fast sweeping (Zhao 2005) of the triangle-mesh eikonal update
(Kimmel and Sethian 1998): one thread per env labels the anchor groups, then visits the triangles in four
precomputed orders (sorted along four directions) and updates each corner from the other two, in every group's field,
from a virtual point source when both carry the same anchor and along the edges otherwise. One round (four orders)
converges on a convex sheet; a cut adds rounds. An env is swept only after its anchors or its triangles changed
(``status[env, 0]`` 2: start again from the anchors) and until a round changes nothing (``status`` 1 -> 0); before
that, unreached particles have no tether (never a wrong one). ``status[env, 1]`` holds the env's number of groups.
"""

from __future__ import annotations

import warp as wp

INF = 1.0e30
# an attached particle whose effective inverse mass (attachments folded in) is below this fraction of its own is an
# anchor: the attachment, not the sheet, decides where it goes within a sweep
ANCHOR_MASS_RATIO = 1.0e-3
# a distance must drop by more than this (m) to count as a change: float rounding cannot keep a round "changing"
CHANGE_TOL = 1.0e-7
# anchor groups with their own distance field per env: a particle is tethered to its nearest anchor of each (a sheet
# held at its back edge and at two corners: three); further groups share the last field
GROUPS = wp.constant(4)


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
def _relax(env: int, base: int, k: int, cand: float, src: int, rest: wp.array(dtype=wp.vec3),
           dist: wp.array2d(dtype=float), source: wp.array2d(dtype=wp.int32)) -> int:
    # a geodesic is never shorter than the straight rest distance to its anchor (guards the eikonal estimate)
    c = wp.max(cand, wp.length(rest[k] - rest[src]))
    if c < dist[env, base + k] - CHANGE_TOL:
        dist[env, base + k] = c
        source[env, base + k] = src
        return 1
    return 0


@wp.func
def _update_corner(env: int, base: int, i: int, j: int, k: int, rest: wp.array(dtype=wp.vec3),
                   dist: wp.array2d(dtype=float), source: wp.array2d(dtype=wp.int32)) -> int:
    """Improve corner ``k`` of triangle (i, j, k) from ``i`` and ``j`` in the distance field at column ``base``
    (one anchor group's); 1 if it changed."""
    changed = int(0)
    xi = rest[i]
    xj = rest[j]
    xk = rest[k]
    si = source[env, base + i]
    sj = source[env, base + j]
    di = dist[env, base + i]
    dj = dist[env, base + j]
    if si >= 0:
        changed += _relax(env, base, k, di + wp.length(xk - xi), si, rest, dist, source)
    if sj >= 0:
        changed += _relax(env, base, k, dj + wp.length(xk - xj), sj, rest, dist, source)
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
                    changed += _relax(env, base, k, wp.sqrt(dx * dx + dy * dy), si, rest, dist, source)
    return changed


@wp.func
def _tri_present(env: int, f: int, tri_element: wp.array(dtype=wp.int32), tri_active: wp.array2d(dtype=wp.int32),
                 masked: int) -> int:
    if masked != 0:
        e = tri_element[f]
        if e >= 0:
            if tri_active[env, e] == 0:
                return 0
    return 1


@wp.func
def _join(env: int, a: int, b: int, label: wp.array2d(dtype=wp.int32)) -> int:
    """Both anchors take the smaller of their component labels; 1 if one changed."""
    la = label[env, a]
    lb = label[env, b]
    if la < 0 or lb < 0 or la == lb:
        return 0
    lo = wp.min(la, lb)
    label[env, a] = lo
    label[env, b] = lo
    return 1


@wp.func
def _label_anchor_groups(env: int, particles: wp.array(dtype=wp.int32), tris: wp.array(dtype=wp.vec3i),
                         tri_element: wp.array(dtype=wp.int32), order: wp.array2d(dtype=wp.int32),
                         anchor: wp.array2d(dtype=wp.int32), tri_active: wp.array2d(dtype=wp.int32), masked: int,
                         label: wp.array2d(dtype=wp.int32)) -> int:
    """Anchor groups: the env's anchors connected through the edges of present triangles (a pinned edge, a grasped
    patch, a held corner). ``label[env, p]`` = the anchor's group (0 .. GROUPS - 1, numbered by smallest particle;
    groups past the last slot share it), -1 for other particles. Returns the number of groups used."""
    for i in range(particles.shape[0]):
        p = particles[i]
        label[env, p] = wp.where(anchor[env, p] != 0, p, -1)
    # the smallest particle index spreads through each component; the four sweep orders carry it along any straight
    # run of anchors in one round
    for _round in range(particles.shape[0]):
        changed = int(0)
        for o in range(order.shape[0]):
            for n in range(order.shape[1]):
                f = order[o, n]
                if _tri_present(env, f, tri_element, tri_active, masked) != 0:
                    t = tris[f]
                    changed += _join(env, t[0], t[1], label)
                    changed += _join(env, t[1], t[2], label)
                    changed += _join(env, t[2], t[0], label)
        if changed == 0:
            break
    # a component's root (label == own index) gets the next slot, encoded as -(slot + 2) (-1 means no anchor); the
    # other anchors copy their root's code; then every code is decoded
    groups = int(0)
    for i in range(particles.shape[0]):
        p = particles[i]
        if label[env, p] == p:
            label[env, p] = -(wp.min(groups, GROUPS - 1) + 2)
            groups += 1
    for i in range(particles.shape[0]):
        p = particles[i]
        r = label[env, p]
        if r >= 0:
            label[env, p] = label[env, r]
    for i in range(particles.shape[0]):
        p = particles[i]
        code = label[env, p]
        label[env, p] = wp.where(code <= -2, -code - 2, -1)
    return wp.min(groups, GROUPS)


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
    label: wp.array2d(dtype=wp.int32),
    dist: wp.array2d(dtype=float),
    source: wp.array2d(dtype=wp.int32),
    status: wp.array2d(dtype=wp.int32),
):
    """One thread per env: restart from the anchors if asked (status 2: label the anchor groups, each group's own
    anchors at distance 0), then up to ``max_rounds`` rounds of the four sweep orders over every group's distance
    field; status 0 once a round changed nothing. ``status[env, 1]`` keeps the number of groups."""
    env = wp.tid()
    st = status[env, 0]
    if st == 0:
        return
    n_all = dist.shape[1] // GROUPS
    if st == 2:
        status[env, 1] = _label_anchor_groups(env, particles, tris, tri_element, order, anchor, tri_active, masked,
                                              label)
        for i in range(particles.shape[0]):
            p = particles[i]
            for g in range(GROUPS):
                dist[env, g * n_all + p] = INF
                source[env, g * n_all + p] = -1
            g = label[env, p]
            if g >= 0:
                dist[env, g * n_all + p] = 0.0
                source[env, g * n_all + p] = p
    groups = status[env, 1]
    st = int(1)
    for _round in range(max_rounds):
        changed = int(0)
        for o in range(order.shape[0]):
            for n in range(order.shape[1]):
                f = order[o, n]
                if _tri_present(env, f, tri_element, tri_active, masked) != 0:
                    t = tris[f]
                    for g in range(groups):
                        base = g * n_all
                        changed += _update_corner(env, base, t[0], t[1], t[2], rest, dist, source)
                        changed += _update_corner(env, base, t[1], t[2], t[0], rest, dist, source)
                        changed += _update_corner(env, base, t[2], t[0], t[1], rest, dist, source)
        if changed == 0:
            st = 0
            break
    status[env, 0] = st


# a point counts as inside a tether's ball within this fraction of its length (float32 rounding of the exact
# intersection points; the cloth's physical stretch is ~1e-4)
FEASIBLE_TOL = 1.0e-5


@wp.func
def _ball(env: int, p: int, g: int, n_all: int, dist: wp.array2d(dtype=float), source: wp.array2d(dtype=wp.int32),
          q: wp.array2d(dtype=wp.vec3)) -> wp.vec4:
    """Group ``g``'s tether of particle ``p`` as (centre, radius); radius < 0 where the particle has none."""
    a = source[env, g * n_all + p]
    if a < 0 or a == p:
        return wp.vec4(0.0, 0.0, 0.0, -1.0)
    c = q[env, a]
    return wp.vec4(c[0], c[1], c[2], dist[env, g * n_all + p])


@wp.func
def _centre(b: wp.vec4) -> wp.vec3:
    return wp.vec3(b[0], b[1], b[2])


@wp.func
def _violation(env: int, p: int, y: wp.vec3, groups: int, n_all: int, dist: wp.array2d(dtype=float),
               source: wp.array2d(dtype=wp.int32), q: wp.array2d(dtype=wp.vec3)) -> float:
    """How far ``y`` lies outside its tethers' balls at most, as a fraction of the tether's length (<= 0: inside)."""
    worst = float(-1.0)
    for g in range(groups):
        b = _ball(env, p, g, n_all, dist, source, q)
        if b[3] > 0.0:
            worst = wp.max(worst, (wp.length(y - _centre(b)) - b[3]) / b[3])
    return worst


@wp.func
def _onto_ball(x: wp.vec3, b: wp.vec4) -> wp.vec3:
    """``x`` moved onto ball ``b`` along the line to its centre (unchanged inside it)."""
    c = _centre(b)
    d = x - c
    length = wp.length(d)
    if length > b[3]:
        return c + d * (b[3] / length)
    return x


@wp.func
def _any_perpendicular(u: wp.vec3) -> wp.vec3:
    t = wp.vec3(1.0, 0.0, 0.0)
    if wp.abs(u[0]) > 0.9:
        t = wp.vec3(0.0, 1.0, 0.0)
    return wp.normalize(wp.cross(u, t))


@wp.func
def _circle_point(x: wp.vec3, b1: wp.vec4, b2: wp.vec4) -> wp.vec4:
    """The point of the two spheres' intersection circle closest to ``x`` (w = 1), or w = 0 where one ball holds the
    other. Tangent balls (a particle on the straight line between two held corners of a taut edge) meet in one point;
    balls a little apart (the corners' attachments give a little) give the point that shares the gap out in
    proportion to the tethers' lengths."""
    c1 = _centre(b1)
    d_vec = _centre(b2) - c1
    d = wp.length(d_vec)
    r1 = b1[3]
    r2 = b2[3]
    if d < 1.0e-12 or d < wp.abs(r1 - r2):
        return wp.vec4(0.0)
    u = d_vec / d
    if d >= r1 + r2:
        y = c1 + u * (r1 * d / (r1 + r2))
        return wp.vec4(y[0], y[1], y[2], 1.0)
    a = (d * d + r1 * r1 - r2 * r2) / (2.0 * d)
    h = wp.sqrt(wp.max(r1 * r1 - a * a, 0.0))
    m = c1 + u * a
    w = x - m
    w = w - u * wp.dot(w, u)
    lw = wp.length(w)
    direction = _any_perpendicular(u)
    if lw > 1.0e-12:
        direction = w / lw
    y = m + direction * h
    return wp.vec4(y[0], y[1], y[2], 1.0)


@wp.func
def _triple_points(b1: wp.vec4, b2: wp.vec4, b3: wp.vec4) -> wp.mat33:
    """The two common points of three spheres (rows 0 and 1; row 2 = (1, 0, 0), or zeros for coincident or collinear
    centres): trilateration; a negative height (the three spheres tangent, as on a sheet held taut at three anchors,
    or just missing each other) is taken as zero."""
    p1 = _centre(b1)
    e = _centre(b2) - p1
    d = wp.length(e)
    if d < 1.0e-12:
        return wp.mat33(0.0)
    ex = e / d
    v = _centre(b3) - p1
    i = wp.dot(ex, v)
    ey_raw = v - ex * i
    j = wp.length(ey_raw)
    if j < 1.0e-9:
        return wp.mat33(0.0)  # collinear centres: the pair circles cover it
    ey = ey_raw / j
    ez = wp.cross(ex, ey)
    r1 = b1[3]
    X = (r1 * r1 - b2[3] * b2[3] + d * d) / (2.0 * d)
    Y = (r1 * r1 - b3[3] * b3[3] + i * i + j * j) / (2.0 * j) - (i / j) * X
    z2 = r1 * r1 - X * X - Y * Y  # < 0: the balls just miss a common point; the point between them is the nearest
    Z = wp.sqrt(wp.max(z2, 0.0))
    base = p1 + ex * X + ey * Y
    top = base + ez * Z
    bottom = base - ez * Z
    return wp.mat33(top[0], top[1], top[2], bottom[0], bottom[1], bottom[2], 1.0, 0.0, 0.0)


@wp.func
def _consider(env: int, p: int, x: wp.vec3, y: wp.vec3, best: wp.vec4, groups: int, n_all: int,
              dist: wp.array2d(dtype=float), source: wp.array2d(dtype=wp.int32), q: wp.array2d(dtype=wp.vec3)
              ) -> wp.vec4:
    """``best`` as (point, score): a point inside every ball (within ``FEASIBLE_TOL``) scores its squared distance to
    ``x`` (< 1 m^2), one outside scores 1 + its violation; the lower score is kept."""
    v = _violation(env, p, y, groups, n_all, dist, source, q)
    score = 1.0 + v
    if v <= FEASIBLE_TOL:
        score = wp.length_sq(y - x)
    if score < best[3]:
        return wp.vec4(y[0], y[1], y[2], score)
    return best


@wp.kernel
def solve_geodesic_tethers(
    particles: wp.array(dtype=wp.int32),
    dist: wp.array2d(dtype=float),
    source: wp.array2d(dtype=wp.int32),
    status: wp.array2d(dtype=wp.int32),
    inv_mass: wp.array2d(dtype=float),
    passes: int,
    q: wp.array2d(dtype=wp.vec3),
):
    """Move each tethered particle to the closest point that lies within the geodesic distance of its nearest anchor
    of every group (unilateral; the anchors do not move: pinned or held, and never themselves tethered).

    The closest point of an intersection of balls has one, two or three tethers taut: it is the nearest of the
    candidates (the projection onto each sphere, the closest point of each pair's intersection circle, the common
    points of each triple) that lies in every ball. Projecting onto the balls one after the other converges slowly
    where they barely overlap, which is the usual case for a held sheet: a particle of the edge between two held
    corners has tethers to both whose lengths add up to the corners' distance, so its only admissible place is on the
    straight line between them (a pulled sheet at 10 substeps: corner edges stretched 1.42 / 1.26 / 1.18 with 1 / 4 /
    16 sequential passes). Where the balls share no point (anchors pulled apart further than the sheet reaches),
    ``passes`` sequential projections, group after group, share the violation out instead."""
    env, i = wp.tid()
    p = particles[i]
    if inv_mass[env % inv_mass.shape[0], p] == 0.0:
        return
    n_all = dist.shape[1] // GROUPS
    groups = status[env, 1]
    x = q[env, p]
    v0 = _violation(env, p, x, groups, n_all, dist, source, q)
    if v0 <= 0.0:
        return
    best = wp.vec4(0.0, 0.0, 0.0, INF)
    for g in range(groups):
        b = _ball(env, p, g, n_all, dist, source, q)
        if b[3] > 0.0 and wp.length(x - _centre(b)) > b[3]:
            best = _consider(env, p, x, _onto_ball(x, b), best, groups, n_all, dist, source, q)
    # a feasible projection onto one ball is the answer; otherwise the nearest feasible point on two or three spheres
    # (all of them: a feasible point of one pair can be farther than the answer on a triple of others)
    if best[3] >= 1.0:
        for g in range(groups):
            bg = _ball(env, p, g, n_all, dist, source, q)
            for h in range(g + 1, groups):
                bh = _ball(env, p, h, n_all, dist, source, q)
                if bg[3] > 0.0 and bh[3] > 0.0:
                    y = _circle_point(x, bg, bh)
                    if y[3] > 0.0:
                        best = _consider(env, p, x, wp.vec3(y[0], y[1], y[2]), best, groups, n_all, dist, source, q)
        for g in range(groups):
            bg = _ball(env, p, g, n_all, dist, source, q)
            for h in range(g + 1, groups):
                bh = _ball(env, p, h, n_all, dist, source, q)
                for k in range(h + 1, groups):
                    bk = _ball(env, p, k, n_all, dist, source, q)
                    if bg[3] > 0.0 and bh[3] > 0.0 and bk[3] > 0.0:
                        pts = _triple_points(bg, bh, bk)
                        if pts[2, 0] > 0.0:
                            best = _consider(env, p, x, wp.vec3(pts[0, 0], pts[0, 1], pts[0, 2]), best, groups, n_all,
                                             dist, source, q)
                            best = _consider(env, p, x, wp.vec3(pts[1, 0], pts[1, 1], pts[1, 2]), best, groups, n_all,
                                             dist, source, q)
    if best[3] < 1.0 or best[3] - 1.0 < v0:
        x = wp.vec3(best[0], best[1], best[2])
    if best[3] >= 1.0:
        # no common point: share the violation out, group after group
        for _pass in range(passes):
            for g in range(groups):
                b = _ball(env, p, g, n_all, dist, source, q)
                if b[3] >= 0.0:
                    x = _onto_ball(x, b)
    q[env, p] = x
