"""Geometry shared by the kernel modules (``@wp.func`` and ``@wp.struct`` only, so this module never compiles on
its own): closest points of segments and triangles, normalisation with a fallback, and the motion of kinematic
bodies across the substeps of one step (:class:`BodyMotion`, :func:`interpolate_transform`).
"""

import warp as wp

wp.set_module_options({"enable_backward": False})


@wp.func
def safe_normalize(v: wp.vec3, fallback: wp.vec3):
    n = wp.length(v)
    if n > 1.0e-12:
        return v / n
    return fallback


@wp.func
def twist_about(rot: wp.quat, up: wp.vec3) -> wp.quat:
    """``rot``'s twist about the unit axis ``up`` (swing-twist split; the identity where ``rot`` has no twist about
    it), or ``rot`` itself for a zero ``up``."""
    if wp.length(up) == 0.0:
        return rot
    v = wp.vec3(rot[0], rot[1], rot[2])
    p = up * wp.dot(v, up)
    twist = wp.quat(p[0], p[1], p[2], rot[3])
    if wp.length(twist) < 1.0e-9:
        return wp.quat_identity()
    return wp.normalize(twist)


@wp.func
def horizontal_distance(a: wp.vec3, b: wp.vec3) -> float:
    """Distance between two points in the horizontal (x, z) plane; y is up in every scene."""
    return wp.sqrt((a[0] - b[0]) * (a[0] - b[0]) + (a[2] - b[2]) * (a[2] - b[2]))


@wp.func
def interpolate_transform(a: wp.transform, b: wp.transform, s: float):
    p = wp.transform_get_translation(a) * (1.0 - s) + wp.transform_get_translation(b) * s
    r = wp.quat_slerp(wp.transform_get_rotation(a), wp.transform_get_rotation(b), s)
    return wp.transform(p, r)


@wp.struct
class BodyMotion:
    """Kinematic body poses during one substep: the World moves every body linearly from its pose at the start of
    the step (``body_q_prev``) to ``body_q``; ``blend_prev`` / ``blend`` are the fractions of the step done at the
    start / end of this substep. Built once per substep when a step is recorded, never changed afterwards (a
    recorded launch keeps reading the struct it was recorded with)."""

    body_q_prev: wp.array2d(dtype=wp.transform)
    body_q: wp.array2d(dtype=wp.transform)
    blend_prev: float
    blend: float


@wp.func
def body_pose(motion: BodyMotion, env: int, body: int, blend: float):
    """Pose of ``body`` in ``env`` at the fraction ``blend`` of the step."""
    return interpolate_transform(motion.body_q_prev[env, body], motion.body_q[env, body], blend)


@wp.func
def closest_segment_segment(p1: wp.vec3, q1: wp.vec3, p2: wp.vec3, q2: wp.vec3):
    """Parameters (s, t) in [0, 1] of the closest points of segments p1q1 and p2q2 (Ericson 5.1.9)."""
    d1 = q1 - p1
    d2 = q2 - p2
    r = p1 - p2
    a = wp.dot(d1, d1)
    e = wp.dot(d2, d2)
    f = wp.dot(d2, r)
    s = float(0.0)
    t = float(0.0)
    eps = 1.0e-14
    if a <= eps and e <= eps:
        return wp.vec2(0.0, 0.0)
    if a <= eps:
        t = wp.clamp(f / e, 0.0, 1.0)
        return wp.vec2(0.0, t)
    c = wp.dot(d1, r)
    if e <= eps:
        s = wp.clamp(-c / a, 0.0, 1.0)
        return wp.vec2(s, 0.0)
    b = wp.dot(d1, d2)
    denom = a * e - b * b
    if denom > eps * a * e:
        s = wp.clamp((b * f - c * e) / denom, 0.0, 1.0)
    t = (b * s + f) / e
    if t < 0.0:
        t = 0.0
        s = wp.clamp(-c / a, 0.0, 1.0)
    elif t > 1.0:
        t = 1.0
        s = wp.clamp((b - c) / a, 0.0, 1.0)
    return wp.vec2(s, t)


@wp.func
def closest_point_triangle(p: wp.vec3, a: wp.vec3, b: wp.vec3, c: wp.vec3):
    """Barycentric weights (wa, wb, wc) of the point of triangle abc closest to ``p`` (Ericson 5.1.5)."""
    ab = b - a
    ac = c - a
    ap = p - a
    d1 = wp.dot(ab, ap)
    d2 = wp.dot(ac, ap)
    if d1 <= 0.0 and d2 <= 0.0:
        return wp.vec3(1.0, 0.0, 0.0)
    bp = p - b
    d3 = wp.dot(ab, bp)
    d4 = wp.dot(ac, bp)
    if d3 >= 0.0 and d4 <= d3:
        return wp.vec3(0.0, 1.0, 0.0)
    vc = d1 * d4 - d3 * d2
    if vc <= 0.0 and d1 >= 0.0 and d3 <= 0.0:
        v = d1 / (d1 - d3)
        return wp.vec3(1.0 - v, v, 0.0)
    cp = p - c
    d5 = wp.dot(ab, cp)
    d6 = wp.dot(ac, cp)
    if d6 >= 0.0 and d5 <= d6:
        return wp.vec3(0.0, 0.0, 1.0)
    vb = d5 * d2 - d1 * d6
    if vb <= 0.0 and d2 >= 0.0 and d6 <= 0.0:
        w = d2 / (d2 - d6)
        return wp.vec3(1.0 - w, 0.0, w)
    va = d3 * d6 - d5 * d4
    if va <= 0.0 and (d4 - d3) >= 0.0 and (d5 - d6) >= 0.0:
        w = (d4 - d3) / ((d4 - d3) + (d5 - d6))
        return wp.vec3(0.0, 1.0 - w, w)
    denom = va + vb + vc
    if wp.abs(denom) < 1.0e-30:  # degenerate triangle: its first vertex
        return wp.vec3(1.0, 0.0, 0.0)
    v = vb / denom
    w = vc / denom
    return wp.vec3(1.0 - v - w, v, w)


@wp.func
def closest_segment_triangle(p0: wp.vec3, p1: wp.vec3, a: wp.vec3, b: wp.vec3, c: wp.vec3):
    """Closest points of segment p0p1 and triangle abc: (s along the segment, wa, wb, wc) as a vec4.

    Two disjoint convex sets are closest at a segment end or a triangle edge; a segment that pierces the
    triangle has distance 0 at the piercing point."""
    best = wp.vec4(0.0, 1.0, 0.0, 0.0)
    best_d = float(1.0e30)
    # segment ends against the triangle
    for e in range(2):
        p = p0
        if e == 1:
            p = p1
        bw = closest_point_triangle(p, a, b, c)
        d = wp.length_sq(p - (a * bw[0] + b * bw[1] + c * bw[2]))
        if d < best_d:
            best_d = d
            best = wp.vec4(float(e), bw[0], bw[1], bw[2])
    # segment against the three edges
    for e in range(3):
        u = a
        v = b
        if e == 1:
            u = b
            v = c
        elif e == 2:
            u = c
            v = a
        st = closest_segment_segment(p0, p1, u, v)
        d = wp.length_sq((p0 + (p1 - p0) * st[0]) - (u + (v - u) * st[1]))
        if d < best_d:
            best_d = d
            t = st[1]
            if e == 0:
                best = wp.vec4(st[0], 1.0 - t, t, 0.0)
            elif e == 1:
                best = wp.vec4(st[0], 0.0, 1.0 - t, t)
            else:
                best = wp.vec4(st[0], t, 0.0, 1.0 - t)
    # piercing
    n = wp.cross(b - a, c - a)
    den = wp.dot(n, p1 - p0)
    if wp.abs(den) > 1.0e-30:
        s = wp.dot(n, a - p0) / den
        if s >= 0.0 and s <= 1.0:
            x = p0 + (p1 - p0) * s
            bw = closest_point_triangle(x, a, b, c)
            if wp.length_sq(x - (a * bw[0] + b * bw[1] + c * bw[2])) < 1.0e-20 * wp.max(wp.length_sq(n), 1.0e-30):
                best = wp.vec4(s, bw[0], bw[1], bw[2])
    return best
