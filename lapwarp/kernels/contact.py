"""Contact kernels: particles and rod segments against signed distance fields, particle-particle contact,
contact reports and grasping.

Every kernel launches env-first (``env, i = wp.tid()``). Collider shapes are shared by all envs; a shape on a
kinematic body reads its pose from ``body_q[env, body]`` interpolated across the substeps of one step exactly
like the attachments of :mod:`lapwarp.kernels.xpbd` (``blend`` = fraction of the step done at the end of this
substep, ``blend_prev`` at its start), so a tool sweeps through the substeps instead of jumping once per step.

Projection (position-based, Macklin et al. 2014 "Unified particle physics"): a particle of radius ``r`` at
signed distance ``d`` from a shape with thickness ``t`` is pushed out along the SDF normal by
``pen = r + t - d``. Coulomb friction acts on the tangential displacement of the particle relative to the
shape's surface point during this substep: static (the displacement is removed) when it is below
``mu_s * pen``, kinetic (shortened by ``mu_k * pen``) otherwise. The velocity update of the World then turns
these position changes into velocities, so friction and non-penetration hold at the velocity level too.

Reports: per env and per (shape, particle group) pair, ``counts`` (contacts in the last substep of the step)
and ``force`` (summed normal force averaged over the step, N) are accumulated with atomics per env only.
"""

import warp as wp

wp.set_module_options({"enable_backward": False})

SHAPE_SPHERE = wp.constant(0)
SHAPE_CAPSULE = wp.constant(1)
SHAPE_BOX = wp.constant(2)
SHAPE_PLANE = wp.constant(3)
SHAPE_CYLINDER = wp.constant(4)
SHAPE_MESH = wp.constant(5)
SHAPE_SURFACE = wp.constant(6)  # deforming per-env triangle surface: collide_surface, not the SDF loop


# ----------------------------------------------------------------------------------------------------
# signed distance functions, shape-local frame; return (normal, distance) packed as vec4
# ----------------------------------------------------------------------------------------------------


@wp.func
def safe_normalize(v: wp.vec3, fallback: wp.vec3):
    n = wp.length(v)
    if n > 1.0e-12:
        return v / n
    return fallback


@wp.func
def sdf_local(kind: int, params: wp.vec3, mesh: wp.uint64, p: wp.vec3, max_dist: float):
    """Signed distance and outward normal of a shape at local point ``p`` (vec4: nx, ny, nz, d)."""
    up = wp.vec3(0.0, 0.0, 1.0)
    if kind == SHAPE_SPHERE:
        n = safe_normalize(p, up)
        return wp.vec4(n[0], n[1], n[2], wp.length(p) - params[0])
    if kind == SHAPE_CAPSULE:
        # axis along local z, params = (radius, half height of the axis segment, -)
        c = wp.vec3(0.0, 0.0, wp.clamp(p[2], -params[1], params[1]))
        n = safe_normalize(p - c, wp.vec3(1.0, 0.0, 0.0))
        return wp.vec4(n[0], n[1], n[2], wp.length(p - c) - params[0])
    if kind == SHAPE_BOX:
        q = wp.vec3(wp.abs(p[0]) - params[0], wp.abs(p[1]) - params[1], wp.abs(p[2]) - params[2])
        qm = wp.max(q[0], wp.max(q[1], q[2]))
        if qm > 0.0:
            o = wp.vec3(wp.max(q[0], 0.0) * wp.sign(p[0]), wp.max(q[1], 0.0) * wp.sign(p[1]),
                        wp.max(q[2], 0.0) * wp.sign(p[2]))
            n = safe_normalize(o, up)
            return wp.vec4(n[0], n[1], n[2], wp.length(o))
        # inside: leave through the nearest face
        if q[0] >= q[1] and q[0] >= q[2]:
            return wp.vec4(wp.sign(p[0]), 0.0, 0.0, qm)
        if q[1] >= q[2]:
            return wp.vec4(0.0, wp.sign(p[1]), 0.0, qm)
        return wp.vec4(0.0, 0.0, wp.sign(p[2]), qm)
    if kind == SHAPE_PLANE:
        # half-space below the local xy plane; params unused
        return wp.vec4(0.0, 0.0, 1.0, p[2])
    if kind == SHAPE_CYLINDER:
        # axis along local z, params = (radius, half height, -)
        rho = wp.sqrt(p[0] * p[0] + p[1] * p[1])
        radial = wp.vec3(1.0, 0.0, 0.0)
        if rho > 1.0e-12:
            radial = wp.vec3(p[0] / rho, p[1] / rho, 0.0)
        axial = wp.vec3(0.0, 0.0, wp.sign(p[2]))
        dr = rho - params[0]
        dz = wp.abs(p[2]) - params[1]
        if dr > 0.0 and dz > 0.0:
            n = safe_normalize(radial * dr + axial * dz, up)
            return wp.vec4(n[0], n[1], n[2], wp.sqrt(dr * dr + dz * dz))
        if dr > dz:
            return wp.vec4(radial[0], radial[1], radial[2], dr)
        return wp.vec4(axial[0], axial[1], axial[2], dz)
    if kind == SHAPE_MESH:
        # closed meshes: inside/outside from the normal at the closest point (angle-weighted at edges)
        res = wp.mesh_query_point_sign_normal(mesh, p, max_dist)
        if res.result:
            cp = wp.mesh_eval_position(mesh, res.face, res.u, res.v)
            delta = p - cp
            dist = wp.length(delta)
            fn = wp.mesh_eval_face_normal(mesh, res.face)
            n = fn
            if dist > 1.0e-9:
                n = delta / dist * res.sign
            return wp.vec4(n[0], n[1], n[2], dist * res.sign)
    return wp.vec4(0.0, 0.0, 1.0, 1.0e6)


@wp.func
def interpolate_transform(a: wp.transform, b: wp.transform, s: float):
    p = wp.transform_get_translation(a) * (1.0 - s) + wp.transform_get_translation(b) * s
    r = wp.quat_slerp(wp.transform_get_rotation(a), wp.transform_get_rotation(b), s)
    return wp.transform(p, r)


@wp.func
def shape_pose(body: int, local: wp.transform, env: int, body_q_prev: wp.array2d(dtype=wp.transform),
               body_q: wp.array2d(dtype=wp.transform), blend: float):
    if body < 0:
        return local
    return wp.transform_multiply(interpolate_transform(body_q_prev[env, body], body_q[env, body], blend), local)


@wp.func
def record_contact(env: int, particle: int, shape: int, normal: wp.vec3, depth: float,
                   contact_count: wp.array(dtype=wp.int32), contact_particle: wp.array2d(dtype=wp.int32),
                   contact_shape: wp.array2d(dtype=wp.int32), contact_normal: wp.array2d(dtype=wp.vec3),
                   contact_depth: wp.array2d(dtype=float), overflow: wp.array(dtype=wp.int32)):
    slot = wp.atomic_add(contact_count, env, 1)
    if slot < contact_particle.shape[1]:
        contact_particle[env, slot] = particle
        contact_shape[env, slot] = shape
        contact_normal[env, slot] = normal
        contact_depth[env, slot] = depth
    else:
        overflow[env] = 1


@wp.func
def friction_correction(rel: wp.vec3, n: wp.vec3, pen: float, mu: wp.vec2):
    """Positional Coulomb friction: the correction that cancels (static) or shortens (kinetic) the tangential
    part of the relative displacement ``rel`` of this substep."""
    t = rel - n * wp.dot(rel, n)
    lt = wp.length(t)
    if lt <= mu[0] * pen:
        return -t
    if lt > 0.0:
        return -t * wp.min(mu[1] * pen / lt, 1.0)
    return wp.vec3(0.0)


# ----------------------------------------------------------------------------------------------------
# particles against shapes
# ----------------------------------------------------------------------------------------------------


@wp.kernel
def collide_particles(
    cp_particle: wp.array(dtype=wp.int32),
    cp_group: wp.array(dtype=wp.int32),
    cp_radius: wp.array(dtype=float),
    shape_kind: wp.array(dtype=wp.int32),
    shape_body: wp.array(dtype=wp.int32),
    shape_local: wp.array(dtype=wp.transform),
    shape_params: wp.array(dtype=wp.vec3),
    shape_mesh: wp.array(dtype=wp.uint64),
    shape_thickness: wp.array(dtype=float),
    shape_mu: wp.array(dtype=wp.vec2),
    pair_index: wp.array2d(dtype=wp.int32),
    body_q_prev: wp.array2d(dtype=wp.transform),
    body_q: wp.array2d(dtype=wp.transform),
    blend_prev: float,
    blend: float,
    inv_mass: wp.array2d(dtype=float),
    q_pred: wp.array2d(dtype=wp.vec3),
    qd: wp.array2d(dtype=wp.vec3),
    h: float,
    force_scale: float,
    report: int,
    report_margin: float,
    ignore_bodies: wp.array2d(dtype=wp.int32),
    use_ignore: int,
    particle_active: wp.array2d(dtype=wp.int32),
    q: wp.array2d(dtype=wp.vec3),
    report_count: wp.array2d(dtype=wp.int32),
    report_force: wp.array2d(dtype=float),
    contact_count: wp.array(dtype=wp.int32),
    contact_particle: wp.array2d(dtype=wp.int32),
    contact_shape: wp.array2d(dtype=wp.int32),
    contact_normal: wp.array2d(dtype=wp.vec3),
    contact_depth: wp.array2d(dtype=float),
    overflow: wp.array(dtype=wp.int32),
):
    env, k = wp.tid()
    i = cp_particle[k]
    w = inv_mass[env % inv_mass.shape[0], i]
    if w == 0.0:
        return
    if particle_active.shape[1] > 0:
        if particle_active[env, i] == 0:
            return  # every element of the particle was cut away
    g = cp_group[k]
    r = cp_radius[k]
    x = q[env, i]
    # start of this substep: the World predicted q_pred = x0 + v h and keeps v in qd until the velocity update
    x0 = q_pred[env, i] - qd[env, i] * h
    ignore = int(0)
    if use_ignore != 0:
        ignore = ignore_bodies[env, i]
    for s in range(shape_kind.shape[0]):
        pair = pair_index[s, g]
        if pair < 0 or shape_kind[s] == SHAPE_SURFACE:
            continue
        # grasped particles do not collide with the jaws holding them (bit b = body b)
        if shape_body[s] >= 0 and ((ignore >> shape_body[s]) & 1) != 0:
            continue
        reach = r + shape_thickness[s]
        tf = shape_pose(shape_body[s], shape_local[s], env, body_q_prev, body_q, blend)
        pl = wp.transform_point(wp.transform_inverse(tf), x)
        nd = sdf_local(shape_kind[s], shape_params[s], shape_mesh[s], pl, reach + report_margin + 1.0e-3)
        d = nd[3]
        pen = reach - d
        if report != 0 and pen > -report_margin:
            wp.atomic_add(report_count, env, pair, 1)
            record_contact(env, i, s, wp.transform_vector(tf, wp.vec3(nd[0], nd[1], nd[2])), pen, contact_count,
                           contact_particle, contact_shape, contact_normal, contact_depth, overflow)
        if pen <= 0.0:
            continue
        n = wp.transform_vector(tf, wp.vec3(nd[0], nd[1], nd[2]))
        x = x + n * pen
        # where the touched surface point was at the start of the substep (moving tools drag particles along)
        tf0 = shape_pose(shape_body[s], shape_local[s], env, body_q_prev, body_q, blend_prev)
        xs0 = wp.transform_point(tf0, wp.transform_point(wp.transform_inverse(tf), x))
        x = x + friction_correction((x - x0) - (x - xs0), n, pen, shape_mu[s])
        wp.atomic_add(report_force, env, pair, pen / w * force_scale)
    q[env, i] = x


# ----------------------------------------------------------------------------------------------------
# rod segments (capsules) against spheres and capsules: thin tools between rod nodes
# ----------------------------------------------------------------------------------------------------


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


@wp.kernel
def collide_segments(
    seg_nodes: wp.array(dtype=wp.vec2i),
    seg_group: wp.array(dtype=wp.int32),
    seg_radius: wp.array(dtype=float),
    start: int,
    shape_kind: wp.array(dtype=wp.int32),
    shape_body: wp.array(dtype=wp.int32),
    shape_local: wp.array(dtype=wp.transform),
    shape_params: wp.array(dtype=wp.vec3),
    shape_thickness: wp.array(dtype=float),
    shape_mu: wp.array(dtype=wp.vec2),
    pair_index: wp.array2d(dtype=wp.int32),
    body_q_prev: wp.array2d(dtype=wp.transform),
    body_q: wp.array2d(dtype=wp.transform),
    blend_prev: float,
    blend: float,
    inv_mass: wp.array2d(dtype=float),
    q_pred: wp.array2d(dtype=wp.vec3),
    qd: wp.array2d(dtype=wp.vec3),
    h: float,
    force_scale: float,
    ignore_bodies: wp.array2d(dtype=wp.int32),
    use_ignore: int,
    seg_col: wp.array(dtype=wp.int32),
    segment_active: wp.array2d(dtype=wp.int32),
    q: wp.array2d(dtype=wp.vec3),
    report_force: wp.array2d(dtype=float),
):
    # one launch per colour of segments (segments of one colour share no node): no write races
    env, k0 = wp.tid()
    k = start + k0
    if seg_col.shape[0] > 0:
        # cuttable rods: a removed segment does not collide
        sc = seg_col[k]
        if sc >= 0:
            if segment_active[env, sc] == 0:
                return
    a = seg_nodes[k][0]
    b = seg_nodes[k][1]
    pe = env % inv_mass.shape[0]
    wa = inv_mass[pe, a]
    wb = inv_mass[pe, b]
    if wa + wb == 0.0:
        return
    g = seg_group[k]
    xa = q[env, a]
    xb = q[env, b]
    ignore = int(0)
    if use_ignore != 0:
        ignore = ignore_bodies[env, a] | ignore_bodies[env, b]
    for s in range(shape_kind.shape[0]):
        kind = shape_kind[s]
        pair = pair_index[s, g]
        if pair < 0 or kind > SHAPE_CAPSULE:
            continue
        if shape_body[s] >= 0 and ((ignore >> shape_body[s]) & 1) != 0:
            continue
        tf = shape_pose(shape_body[s], shape_local[s], env, body_q_prev, body_q, blend)
        hh = float(0.0)
        if kind == SHAPE_CAPSULE:
            hh = shape_params[s][1]
        c0 = wp.transform_point(tf, wp.vec3(0.0, 0.0, -hh))
        c1 = wp.transform_point(tf, wp.vec3(0.0, 0.0, hh))
        st = closest_segment_segment(xa, xb, c0, c1)
        u = st[0]
        # the nodes themselves are handled by collide_particles; here only the segment interior
        if u <= 0.0 or u >= 1.0:
            continue
        p = xa * (1.0 - u) + xb * u
        c = c0 * (1.0 - st[1]) + c1 * st[1]
        n = safe_normalize(p - c, wp.vec3(0.0, 0.0, 1.0))
        pen = seg_radius[k] + shape_params[s][0] + shape_thickness[s] - wp.length(p - c)
        if pen <= 0.0:
            continue
        # point correction distributed to the nodes with barycentric weights (Mueller et al. 2020)
        wsum = (1.0 - u) * (1.0 - u) * wa + u * u * wb
        # friction on the relative motion of the contact point during this substep
        pa0 = q_pred[env, a] - qd[env, a] * h
        pb0 = q_pred[env, b] - qd[env, b] * h
        tf0 = shape_pose(shape_body[s], shape_local[s], env, body_q_prev, body_q, blend_prev)
        c_0 = wp.transform_point(tf0, wp.transform_point(wp.transform_inverse(tf), c))
        rel = (p + n * pen - (pa0 * (1.0 - u) + pb0 * u)) - (c - c_0)
        dp = n * pen + friction_correction(rel, n, pen, shape_mu[s])
        xa = xa + dp * ((1.0 - u) * wa / wsum)
        xb = xb + dp * (u * wb / wsum)
        wp.atomic_add(report_force, env, pair, pen / wsum * force_scale)
    q[env, a] = xa
    q[env, b] = xb


# ----------------------------------------------------------------------------------------------------
# triangles: cloth / tissue-surface triangles against tool spheres and capsules, particles against the
# deforming triangle surface of another object (grouped wp.Mesh, one BVH subtree per env)
# ----------------------------------------------------------------------------------------------------


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


@wp.kernel
def collide_triangles(
    tri_nodes: wp.array(dtype=wp.vec3i),
    tri_group: wp.array(dtype=wp.int32),
    tri_radius: wp.array(dtype=float),
    start: int,
    shape_kind: wp.array(dtype=wp.int32),
    shape_body: wp.array(dtype=wp.int32),
    shape_local: wp.array(dtype=wp.transform),
    shape_params: wp.array(dtype=wp.vec3),
    shape_thickness: wp.array(dtype=float),
    shape_mu: wp.array(dtype=wp.vec2),
    pair_index: wp.array2d(dtype=wp.int32),
    body_q_prev: wp.array2d(dtype=wp.transform),
    body_q: wp.array2d(dtype=wp.transform),
    blend_prev: float,
    blend: float,
    inv_mass: wp.array2d(dtype=float),
    q_pred: wp.array2d(dtype=wp.vec3),
    qd: wp.array2d(dtype=wp.vec3),
    h: float,
    force_scale: float,
    ignore_bodies: wp.array2d(dtype=wp.int32),
    use_ignore: int,
    tri_col: wp.array(dtype=wp.int32),
    tri_active: wp.array2d(dtype=wp.int32),
    tet_face_active: wp.array2d(dtype=wp.int32),
    q: wp.array2d(dtype=wp.vec3),
    report_force: wp.array2d(dtype=float),
):
    # One launch per colour of triangles (a colour shares no vertex): a tool resting on a triangle's interior is
    # seen even where no vertex is near it, so a capsule moving ~its radius per substep cannot slip between
    # the vertices of a tensioned sheet (vertex-only contact let it through at 1 mm per substep).
    env, k0 = wp.tid()
    k = start + k0
    if tri_col.shape[0] > 0:
        # cuttable objects: tri_col >= 0 is a cloth triangle (tri_active), <= -2 the tet face -2 - tri_col
        # (tet_face_active: only faces on the current surface collide), -1 always collides
        tc = tri_col[k]
        if tc >= 0:
            if tri_active[env, tc] == 0:
                return
        elif tc <= -2:
            if tet_face_active[env, -2 - tc] == 0:
                return
    tri = tri_nodes[k]
    pe = env % inv_mass.shape[0]
    w0 = inv_mass[pe, tri[0]]
    w1 = inv_mass[pe, tri[1]]
    w2 = inv_mass[pe, tri[2]]
    if w0 + w1 + w2 == 0.0:
        return
    g = tri_group[k]
    x0 = q[env, tri[0]]
    x1 = q[env, tri[1]]
    x2 = q[env, tri[2]]
    ignore = int(0)
    if use_ignore != 0:
        ignore = ignore_bodies[env, tri[0]] | ignore_bodies[env, tri[1]] | ignore_bodies[env, tri[2]]
    for s in range(shape_kind.shape[0]):
        kind = shape_kind[s]
        pair = pair_index[s, g]
        if pair < 0 or kind > SHAPE_CAPSULE:
            continue
        if shape_body[s] >= 0 and ((ignore >> shape_body[s]) & 1) != 0:
            continue
        tf = shape_pose(shape_body[s], shape_local[s], env, body_q_prev, body_q, blend)
        hh = float(0.0)
        if kind == SHAPE_CAPSULE:
            hh = shape_params[s][1]
        c0 = wp.transform_point(tf, wp.vec3(0.0, 0.0, -hh))
        c1 = wp.transform_point(tf, wp.vec3(0.0, 0.0, hh))
        # cheap reject (most triangles are far from the tool): bounding sphere about the centroid vs the axis
        cen = (x0 + x1 + x2) / 3.0
        bound = wp.sqrt(wp.max(wp.length_sq(x0 - cen), wp.max(wp.length_sq(x1 - cen), wp.length_sq(x2 - cen))))
        ax = c1 - c0
        u = wp.clamp(wp.dot(cen - c0, ax) / wp.max(wp.dot(ax, ax), 1.0e-20), 0.0, 1.0)
        if wp.length(cen - (c0 + ax * u)) > bound + tri_radius[k] + shape_params[s][0] + shape_thickness[s]:
            continue
        cl = closest_segment_triangle(c0, c1, x0, x1, x2)
        bw = wp.vec3(cl[1], cl[2], cl[3])
        p = x0 * bw[0] + x1 * bw[1] + x2 * bw[2]
        c = c0 * (1.0 - cl[0]) + c1 * cl[0]
        fn = safe_normalize(wp.cross(x1 - x0, x2 - x0), wp.vec3(0.0, 0.0, 1.0))
        # axis touching the triangle: push to the side the tool came from (its centre at the substep start)
        tf0 = shape_pose(shape_body[s], shape_local[s], env, body_q_prev, body_q, blend_prev)
        side = wp.dot(p - wp.transform_get_translation(tf0), fn)
        if side < 0.0:
            fn = -fn
        n = safe_normalize(p - c, fn)
        pen = tri_radius[k] + shape_params[s][0] + shape_thickness[s] - wp.length(p - c)
        if pen <= 0.0:
            continue
        wsum = bw[0] * bw[0] * w0 + bw[1] * bw[1] * w1 + bw[2] * bw[2] * w2
        if wsum <= 0.0:
            continue
        # friction on the relative motion of the contact point during this substep
        p0 = (q_pred[env, tri[0]] - qd[env, tri[0]] * h) * bw[0] + (q_pred[env, tri[1]] - qd[env, tri[1]] * h) * bw[1]
        p0 = p0 + (q_pred[env, tri[2]] - qd[env, tri[2]] * h) * bw[2]
        c_0 = wp.transform_point(tf0, wp.transform_point(wp.transform_inverse(tf), c))
        rel = (p + n * pen - p0) - (c - c_0)
        dp = n * pen + friction_correction(rel, n, pen, shape_mu[s])
        x0 = x0 + dp * (bw[0] * w0 / wsum)
        x1 = x1 + dp * (bw[1] * w1 / wsum)
        x2 = x2 + dp * (bw[2] * w2 / wsum)
        wp.atomic_add(report_force, env, pair, pen / wsum * force_scale)
    q[env, tri[0]] = x0
    q[env, tri[1]] = x1
    q[env, tri[2]] = x2


@wp.kernel
def collide_surface(
    cp_particle: wp.array(dtype=wp.int32),
    cp_group: wp.array(dtype=wp.int32),
    cp_radius: wp.array(dtype=float),
    shape: int,
    mesh: wp.uint64,
    tris: wp.array(dtype=wp.vec3i),
    owner_start: int,
    owner_end: int,
    closed: int,
    thickness: float,
    mu: wp.vec2,
    pair_index: wp.array2d(dtype=wp.int32),
    inv_mass: wp.array2d(dtype=float),
    q_pred: wp.array2d(dtype=wp.vec3),
    qd: wp.array2d(dtype=wp.vec3),
    h: float,
    force_scale: float,
    report: int,
    report_margin: float,
    face_col: wp.array(dtype=wp.int32),
    face_active: wp.array2d(dtype=wp.int32),
    particle_active: wp.array2d(dtype=wp.int32),
    q: wp.array2d(dtype=wp.vec3),
    surf_delta: wp.array2d(dtype=wp.vec3),
    surf_count: wp.array2d(dtype=wp.int32),
    report_count: wp.array2d(dtype=wp.int32),
    report_force: wp.array2d(dtype=float),
    contact_count: wp.array(dtype=wp.int32),
    contact_particle: wp.array2d(dtype=wp.int32),
    contact_shape: wp.array2d(dtype=wp.int32),
    contact_normal: wp.array2d(dtype=wp.vec3),
    contact_depth: wp.array2d(dtype=float),
    overflow: wp.array(dtype=wp.int32),
):
    # Particles of one object against the deforming triangles of another in the same env. The grouped mesh
    # holds every env's triangles over the flat view of state.particle_q (group = env), refit just before
    # this launch; the query starts at this env's subtree so envs never see each other although all of them
    # sit at the origin. Two-way: the triangle's share of the correction goes to surf_delta (averaged later).
    env, k = wp.tid()
    g = cp_group[k]
    pair = pair_index[shape, g]
    if pair < 0:
        return
    i = cp_particle[k]
    if i >= owner_start and i < owner_end:
        return  # a surface does not collide with its own vertices
    if particle_active.shape[1] > 0:
        if particle_active[env, i] == 0:
            return
    pe = env % inv_mass.shape[0]
    w = inv_mass[pe, i]
    x = q[env, i]
    reach = cp_radius[k] + thickness
    ntri = tris.shape[0]
    root = wp.mesh_get_group_root(mesh, env)
    # swept query (the particle's path during this substep): a particle that crossed a surface within one
    # substep still finds the triangle it crossed; the side / inside test below then pushes it back
    xs = q_pred[env, i] - qd[env, i] * h
    query = wp.bvh_query_sphere(wp.mesh_get_bvh(mesh), (x + xs) * 0.5, wp.length(x - xs) * 0.5 + reach + report_margin,
                                root)
    face = int(0)
    best = int(-1)
    best_d = float(1.0e30)
    best_bw = wp.vec3(0.0)
    while wp.bvh_query_next(query, face):
        f = face - env * ntri
        if f < 0 or f >= ntri:
            continue
        if face_col.shape[0] > 0:
            # cuttable surface: removed triangles / tet faces off the current surface do not collide
            if face_active[env, face_col[f]] == 0:
                continue
        t = tris[f]
        bw = closest_point_triangle(x, q[env, t[0]], q[env, t[1]], q[env, t[2]])
        d = wp.length(x - (q[env, t[0]] * bw[0] + q[env, t[1]] * bw[1] + q[env, t[2]] * bw[2]))
        if d < best_d:
            best_d = d
            best = f
            best_bw = bw
    if best < 0:
        return
    t = tris[best]
    a = q[env, t[0]]
    b = q[env, t[1]]
    c = q[env, t[2]]
    cp = a * best_bw[0] + b * best_bw[1] + c * best_bw[2]
    fn = safe_normalize(wp.cross(b - a, c - a), wp.vec3(0.0, 0.0, 1.0))
    side = float(1.0)
    n = fn
    d = best_d
    if closed != 0:
        # closed tissue surface wound outwards: inside when behind the closest face
        if wp.dot(x - cp, fn) < 0.0:
            side = -1.0
        if best_d > 1.0e-9:
            n = (x - cp) / best_d * side
        d = best_d * side
    else:
        # open sheet: the particle belongs on the side it was at the start of the substep (it cannot be
        # pushed through a cloth it crossed during the substep)
        a0 = q_pred[env, t[0]] - qd[env, t[0]] * h
        b0 = q_pred[env, t[1]] - qd[env, t[1]] * h
        c0 = q_pred[env, t[2]] - qd[env, t[2]] * h
        x0 = q_pred[env, i] - qd[env, i] * h
        fn0 = wp.cross(b0 - a0, c0 - a0)
        s0 = wp.dot(x0 - (a0 * best_bw[0] + b0 * best_bw[1] + c0 * best_bw[2]), fn0)
        s1 = wp.dot(x - cp, fn)
        if s0 < 0.0:
            n = -fn
        if best_d > 1.0e-9 and s0 * s1 >= 0.0:
            n = (x - cp) / best_d
            d = best_d
        else:
            d = -best_d
    pen = reach - d
    if report != 0 and pen > -report_margin:
        wp.atomic_add(report_count, env, pair, 1)
        record_contact(env, i, shape, n, pen, contact_count, contact_particle, contact_shape, contact_normal,
                       contact_depth, overflow)
    if pen <= 0.0:
        return
    w0 = inv_mass[pe, t[0]]
    w1 = inv_mass[pe, t[1]]
    w2 = inv_mass[pe, t[2]]
    wt = best_bw[0] * best_bw[0] * w0 + best_bw[1] * best_bw[1] * w1 + best_bw[2] * best_bw[2] * w2
    if w + wt <= 0.0:
        return
    # friction on the motion of the particle relative to the surface point during this substep
    x0p = q_pred[env, i] - qd[env, i] * h
    cp0 = (q_pred[env, t[0]] - qd[env, t[0]] * h) * best_bw[0] + (q_pred[env, t[1]] - qd[env, t[1]] * h) * best_bw[1]
    cp0 = cp0 + (q_pred[env, t[2]] - qd[env, t[2]] * h) * best_bw[2]
    rel = (x - x0p) - (cp - cp0)
    dp = n * pen + friction_correction(rel, n, pen, mu)
    q[env, i] = x + dp * (w / (w + wt))
    for j in range(3):
        wj = inv_mass[pe, t[j]]
        if wj > 0.0:
            wp.atomic_add(surf_delta, env, t[j], -dp * (best_bw[j] * wj / (w + wt)))
            wp.atomic_add(surf_count, env, t[j], 1)
    wp.atomic_add(report_force, env, pair, pen / (w + wt) * force_scale)


@wp.kernel
def apply_surface_deltas(verts: wp.array(dtype=wp.int32), surf_delta: wp.array2d(dtype=wp.vec3),
                         surf_count: wp.array2d(dtype=wp.int32), q: wp.array2d(dtype=wp.vec3)):
    # Jacobi with averaging: a vertex pushed by several particles moves by their mean correction
    env, k = wp.tid()
    i = verts[k]
    c = surf_count[env, i]
    if c > 0:
        q[env, i] = q[env, i] + surf_delta[env, i] / float(c)
        surf_delta[env, i] = wp.vec3(0.0)
        surf_count[env, i] = 0


# ----------------------------------------------------------------------------------------------------
# particle-particle contact (deformable vs deformable, rod self-contact), Jacobi with averaging
# ----------------------------------------------------------------------------------------------------


@wp.func
def chain_skipped(k: int, m: int, sp_chain: wp.array(dtype=wp.int32), sp_chain_pos: wp.array(dtype=wp.int32),
                  sp_chain_len: wp.array(dtype=wp.int32), skip_links: int):
    """Members ``k`` and ``m`` are close neighbours along one chain (they touch at rest): no contact."""
    if m == k:
        return True
    if sp_chain[m] == sp_chain[k] and sp_chain[k] >= 0:
        gap = wp.abs(sp_chain_pos[m] - sp_chain_pos[k])
        ln = sp_chain_len[k]
        if ln > 0:
            gap = wp.min(gap, ln - gap)  # closed loop: cyclic distance along the chain
        if gap <= skip_links:
            return True
    return False


@wp.func
def pair_correction(env: int, k: int, m: int, sp_particle: wp.array(dtype=wp.int32),
                    sp_radius: wp.array(dtype=float), mu: wp.vec2, pe: int, wi: float, xi: wp.vec3, xi0: wp.vec3,
                    inv_mass: wp.array2d(dtype=float), q_pred: wp.array2d(dtype=wp.vec3),
                    qd: wp.array2d(dtype=wp.vec3), h: float, q: wp.array2d(dtype=wp.vec3)):
    """Correction of member k against member m (xyz) and the penetration (w; <= 0: no contact)."""
    j = sp_particle[m]
    xj = q[env, j]
    dvec = xi - xj
    pen = sp_radius[k] + sp_radius[m] - wp.length(dvec)
    if pen <= 0.0:
        return wp.vec4(0.0, 0.0, 0.0, pen)
    wj = inv_mass[pe, j]
    n = safe_normalize(dvec, wp.vec3(0.0, 0.0, 1.0))
    share = wi / (wi + wj)
    xj0 = q_pred[env, j] - qd[env, j] * h
    corr = n * (pen * share) + friction_correction((xi - xi0) - (xj - xj0), n, pen, mu) * share
    return wp.vec4(corr[0], corr[1], corr[2], pen / (wi + wj))


@wp.kernel
def collide_particle_pairs(
    sp_particle: wp.array(dtype=wp.int32),
    sp_radius: wp.array(dtype=float),
    sp_chain: wp.array(dtype=wp.int32),
    sp_chain_pos: wp.array(dtype=wp.int32),
    sp_chain_len: wp.array(dtype=wp.int32),
    sp_pair: wp.array(dtype=wp.int32),
    skip_links: int,
    mu: wp.vec2,
    inv_mass: wp.array2d(dtype=float),
    q_pred: wp.array2d(dtype=wp.vec3),
    qd: wp.array2d(dtype=wp.vec3),
    h: float,
    force_scale: float,
    report: int,
    q: wp.array2d(dtype=wp.vec3),
    delta: wp.array2d(dtype=wp.vec3),
    report_count: wp.array2d(dtype=wp.int32),
    report_force: wp.array2d(dtype=float),
):
    # brute force over the (small) contact set of one env: below ~grid_threshold members (docs/contact.md) the
    # M^2 tests cost less than building and querying the per-env cell list, and envs never see each other
    env, k = wp.tid()
    i = sp_particle[k]
    pe = env % inv_mass.shape[0]
    wi = inv_mass[pe, i]
    if wi == 0.0:
        delta[env, k] = wp.vec3(0.0)
        return
    xi = q[env, i]
    xi0 = q_pred[env, i] - qd[env, i] * h
    acc = wp.vec3(0.0)
    cnt = int(0)
    for m in range(sp_particle.shape[0]):
        if chain_skipped(k, m, sp_chain, sp_chain_pos, sp_chain_len, skip_links):
            continue
        c = pair_correction(env, k, m, sp_particle, sp_radius, mu, pe, wi, xi, xi0, inv_mass, q_pred, qd, h, q)
        if c[3] <= 0.0:
            continue
        acc = acc + wp.vec3(c[0], c[1], c[2])
        cnt += 1
        if sp_pair[k] >= 0:
            # each pair is seen from both sides: half the force per side
            wp.atomic_add(report_force, env, sp_pair[k], 0.5 * c[3] * force_scale)
            if report != 0:
                wp.atomic_add(report_count, env, sp_pair[k], 1)
    if cnt > 0:
        acc = acc / float(cnt)
    delta[env, k] = acc


# per-env cell list (spatial hash with counting sort): all envs sit at the origin, so one wp.HashGrid would mix
# them; instead every env owns ``H`` hash buckets in one flat array, filled by atomics, turned into offsets by
# one exclusive scan over all envs (env e's buckets start at e * M because each env holds exactly M members)


@wp.func
def cell_hash(c: wp.vec3i, H: int):
    hv = (c[0] * 73856093) ^ (c[1] * 19349663) ^ (c[2] * 83492791)
    return hv & (H - 1)


@wp.func
def cell_of(x: wp.vec3, inv_cell: float):
    return wp.vec3i(int(wp.floor(x[0] * inv_cell)), int(wp.floor(x[1] * inv_cell)), int(wp.floor(x[2] * inv_cell)))


@wp.kernel
def grid_count(sp_particle: wp.array(dtype=wp.int32), inv_cell: float, H: int, q: wp.array2d(dtype=wp.vec3),
               bucket_count: wp.array(dtype=wp.int32), member_bucket: wp.array2d(dtype=wp.int32),
               member_rank: wp.array2d(dtype=wp.int32)):
    env, k = wp.tid()
    b = env * H + cell_hash(cell_of(q[env, sp_particle[k]], inv_cell), H)
    member_bucket[env, k] = b
    member_rank[env, k] = wp.atomic_add(bucket_count, b, 1)


@wp.kernel
def grid_scatter(bucket_start: wp.array(dtype=wp.int32), member_bucket: wp.array2d(dtype=wp.int32),
                 member_rank: wp.array2d(dtype=wp.int32), sorted_member: wp.array(dtype=wp.int32)):
    env, k = wp.tid()
    sorted_member[bucket_start[member_bucket[env, k]] + member_rank[env, k]] = k


@wp.kernel
def collide_particle_pairs_grid(
    sp_particle: wp.array(dtype=wp.int32),
    sp_radius: wp.array(dtype=float),
    sp_chain: wp.array(dtype=wp.int32),
    sp_chain_pos: wp.array(dtype=wp.int32),
    sp_chain_len: wp.array(dtype=wp.int32),
    sp_pair: wp.array(dtype=wp.int32),
    skip_links: int,
    mu: wp.vec2,
    inv_cell: float,
    H: int,
    bucket_start: wp.array(dtype=wp.int32),
    bucket_count: wp.array(dtype=wp.int32),
    sorted_member: wp.array(dtype=wp.int32),
    inv_mass: wp.array2d(dtype=float),
    q_pred: wp.array2d(dtype=wp.vec3),
    qd: wp.array2d(dtype=wp.vec3),
    h: float,
    force_scale: float,
    report: int,
    q: wp.array2d(dtype=wp.vec3),
    delta: wp.array2d(dtype=wp.vec3),
    report_count: wp.array2d(dtype=wp.int32),
    report_force: wp.array2d(dtype=float),
):
    # same projection as collide_particle_pairs, over the members in the 27 cells around this one (cell size
    # >= the largest contact distance, so nothing farther can touch)
    env, k = wp.tid()
    i = sp_particle[k]
    pe = env % inv_mass.shape[0]
    wi = inv_mass[pe, i]
    if wi == 0.0:
        delta[env, k] = wp.vec3(0.0)
        return
    xi = q[env, i]
    xi0 = q_pred[env, i] - qd[env, i] * h
    ci = cell_of(xi, inv_cell)
    acc = wp.vec3(0.0)
    cnt = int(0)
    for nb in range(27):
        b = env * H + cell_hash(ci + wp.vec3i(nb % 3 - 1, (nb / 3) % 3 - 1, nb / 9 - 1), H)
        # two neighbour cells may hash to the same bucket: visit each bucket once
        seen = int(0)
        for pb in range(nb):
            if env * H + cell_hash(ci + wp.vec3i(pb % 3 - 1, (pb / 3) % 3 - 1, pb / 9 - 1), H) == b:
                seen = 1
        if seen != 0:
            continue
        s0 = bucket_start[b]
        for e in range(bucket_count[b]):
            m = sorted_member[s0 + e]
            if chain_skipped(k, m, sp_chain, sp_chain_pos, sp_chain_len, skip_links):
                continue
            c = pair_correction(env, k, m, sp_particle, sp_radius, mu, pe, wi, xi, xi0, inv_mass, q_pred, qd, h,
                                q)
            if c[3] <= 0.0:
                continue
            acc = acc + wp.vec3(c[0], c[1], c[2])
            cnt += 1
            if sp_pair[k] >= 0:
                wp.atomic_add(report_force, env, sp_pair[k], 0.5 * c[3] * force_scale)
                if report != 0:
                    wp.atomic_add(report_count, env, sp_pair[k], 1)
    if cnt > 0:
        acc = acc / float(cnt)
    delta[env, k] = acc


@wp.kernel
def apply_particle_deltas(sp_particle: wp.array(dtype=wp.int32), delta: wp.array2d(dtype=wp.vec3),
                          q: wp.array2d(dtype=wp.vec3)):
    env, k = wp.tid()
    i = sp_particle[k]
    q[env, i] = q[env, i] + delta[env, k]


# ----------------------------------------------------------------------------------------------------
# reports
# ----------------------------------------------------------------------------------------------------


@wp.kernel
def clear_reports(report_count: wp.array2d(dtype=wp.int32), report_force: wp.array2d(dtype=float),
                  contact_count: wp.array(dtype=wp.int32), overflow: wp.array(dtype=wp.int32)):
    env = wp.tid()
    for p in range(report_count.shape[1]):
        report_count[env, p] = 0
        report_force[env, p] = 0.0
    contact_count[env] = 0
    overflow[env] = 0


@wp.kernel
def clear_reports_masked(env_mask: wp.array(dtype=wp.int32), report_count: wp.array2d(dtype=wp.int32),
                         report_force: wp.array2d(dtype=float), contact_count: wp.array(dtype=wp.int32),
                         overflow: wp.array(dtype=wp.int32)):
    env = wp.tid()
    if env_mask[env] == 0:
        return
    for p in range(report_count.shape[1]):
        report_count[env, p] = 0
        report_force[env, p] = 0.0
    contact_count[env] = 0
    overflow[env] = 0


@wp.kernel
def clamp_contact_count(capacity: int, contact_count: wp.array(dtype=wp.int32)):
    env = wp.tid()
    contact_count[env] = wp.min(contact_count[env], capacity)


# ----------------------------------------------------------------------------------------------------
# grasping: attachments written into the per-env slots of state.attach_* (see lapwarp/grasping.py)
# ----------------------------------------------------------------------------------------------------


@wp.func
def release_slots(env: int, slot_start: int, slots: int, jaw_mask: int, attach_particle: wp.array2d(dtype=wp.int32),
                  ignore_bodies: wp.array2d(dtype=wp.int32), use_ignore: int):
    for k in range(slots):
        i = attach_particle[env, slot_start + k]
        if i >= 0 and use_ignore != 0:
            ignore_bodies[env, i] = ignore_bodies[env, i] & (~jaw_mask)
        attach_particle[env, slot_start + k] = -1


@wp.func
def in_jaw_cone(pl: wp.vec3, angle: float, jaw_length: float, margin: float):
    """Local tip-frame point between the jaws: within the jaw length and inside the opening angle (+ margin)."""
    if pl[2] < -margin or pl[2] > jaw_length + margin:
        return False
    if wp.abs(pl[0]) > margin:
        return False
    return wp.abs(pl[1]) <= wp.max(pl[2], 0.0) * wp.tan(angle) + margin


@wp.kernel
def update_grasp(
    jaw_angle_deg: wp.array(dtype=float),
    grasp_threshold: float,
    release_threshold: float,
    shaft: int,
    jaw_a: int,
    jaw_b: int,
    jaw_length: float,
    cone_margin: float,
    max_offset: float,
    slot_start: int,
    slots: int,
    compliance: float,
    graspable: wp.array(dtype=wp.int32),
    particle_segment: wp.array(dtype=wp.int32),
    shape_body: wp.array(dtype=wp.int32),
    contact_count: wp.array(dtype=wp.int32),
    contact_particle: wp.array2d(dtype=wp.int32),
    contact_shape: wp.array2d(dtype=wp.int32),
    body_q: wp.array2d(dtype=wp.transform),
    q: wp.array2d(dtype=wp.vec3),
    segment_q: wp.array2d(dtype=wp.quat),
    use_ignore: int,
    grasped: wp.array(dtype=wp.int32),
    lost_grasp: wp.array(dtype=wp.int32),
    attach_particle: wp.array2d(dtype=wp.int32),
    attach_body: wp.array2d(dtype=wp.int32),
    attach_offset: wp.array2d(dtype=wp.vec3),
    attach_compliance: wp.array2d(dtype=float),
    grasp_delta: wp.array2d(dtype=wp.quat),
    ignore_bodies: wp.array2d(dtype=wp.int32),
):
    env = wp.tid()
    lost_grasp[env] = 0
    angle = jaw_angle_deg[env]
    jaw_mask = (1 << jaw_a) | (1 << jaw_b)
    tip = body_q[env, shaft]
    if grasped[env] != 0:
        far = int(0)
        for k in range(slots):
            i = attach_particle[env, slot_start + k]
            if i >= 0:
                jaw = body_q[env, attach_body[env, slot_start + k]]
                if wp.length(q[env, i] - wp.transform_point(jaw, attach_offset[env, slot_start + k])) > max_offset:
                    far = 1
        if angle >= release_threshold or far != 0:
            release_slots(env, slot_start, slots, jaw_mask, attach_particle, ignore_bodies, use_ignore)
            grasped[env] = 0
            lost_grasp[env] = far
        return
    if angle >= grasp_threshold:
        return
    n = wp.min(contact_count[env], contact_particle.shape[1])
    has_a = int(0)
    has_b = int(0)
    for c in range(n):
        if graspable[contact_particle[env, c]] == 0:
            continue
        b = shape_body[contact_shape[env, c]]
        if b == jaw_a:
            has_a = 1
        if b == jaw_b:
            has_b = 1
    if has_a == 0 or has_b == 0:
        return
    inv_tip = wp.transform_inverse(tip)
    rad = angle * (wp.pi / 180.0)
    got = int(0)
    for k in range(slots):
        best = int(-1)
        best_b = int(-1)
        best_d = float(1.0e9)
        for c in range(n):
            i = contact_particle[env, c]
            b = shape_body[contact_shape[env, c]]
            if graspable[i] == 0 or (b != jaw_a and b != jaw_b):
                continue
            taken = int(0)
            for m in range(k):
                if attach_particle[env, slot_start + m] == i:
                    taken = 1
            if taken != 0:
                continue
            pl = wp.transform_point(inv_tip, q[env, i])
            if not in_jaw_cone(pl, rad, jaw_length, cone_margin):
                continue
            # nearest to the jaws' mid-plane
            d = wp.abs(pl[1]) + wp.abs(pl[0])
            if d < best_d:
                best_d = d
                best = i
                best_b = b
        if best < 0:
            break
        # held by the jaw it touches (the jaws are bodies): opening towards the release angle carries it along
        s = slot_start + k
        jaw = body_q[env, best_b]
        attach_particle[env, s] = best
        attach_body[env, s] = best_b
        attach_offset[env, s] = wp.transform_point(wp.transform_inverse(jaw), q[env, best])
        attach_compliance[env, s] = compliance
        seg = particle_segment[best]
        if seg >= 0:
            grasp_delta[env, k] = wp.mul(wp.quat_inverse(wp.transform_get_rotation(jaw)), segment_q[env, seg])
        if use_ignore != 0:
            ignore_bodies[env, best] = ignore_bodies[env, best] | jaw_mask
        got += 1
    if got > 0:
        grasped[env] = 1


@wp.kernel
def hold_grasped_orientations(
    slot_start: int,
    particle_segment: wp.array(dtype=wp.int32),
    attach_particle: wp.array2d(dtype=wp.int32),
    attach_body: wp.array2d(dtype=wp.int32),
    grasp_delta: wp.array2d(dtype=wp.quat),
    body_q_prev: wp.array2d(dtype=wp.transform),
    body_q: wp.array2d(dtype=wp.transform),
    blend: float,
    segment_q: wp.array2d(dtype=wp.quat),
):
    # a grasped rod frame turns with its jaw: its segment orientation is projected onto jaw rotation * delta
    env, k = wp.tid()
    i = attach_particle[env, slot_start + k]
    if i < 0:
        return
    seg = particle_segment[i]
    if seg < 0:
        return
    jaw = attach_body[env, slot_start + k]
    tf = interpolate_transform(body_q_prev[env, jaw], body_q[env, jaw], blend)
    segment_q[env, seg] = wp.normalize(wp.mul(wp.transform_get_rotation(tf), grasp_delta[env, k]))


@wp.kernel
def start_grasp(
    env_mask: wp.array(dtype=wp.int32),
    particle: int,
    shaft: int,
    jaw_a: int,
    jaw_b: int,
    slot_start: int,
    slots: int,
    compliance: float,
    particle_segment: wp.array(dtype=wp.int32),
    body_q: wp.array2d(dtype=wp.transform),
    q: wp.array2d(dtype=wp.vec3),
    segment_q: wp.array2d(dtype=wp.quat),
    use_ignore: int,
    grasped: wp.array(dtype=wp.int32),
    lost_grasp: wp.array(dtype=wp.int32),
    attach_particle: wp.array2d(dtype=wp.int32),
    attach_body: wp.array2d(dtype=wp.int32),
    attach_offset: wp.array2d(dtype=wp.vec3),
    attach_compliance: wp.array2d(dtype=float),
    grasp_delta: wp.array2d(dtype=wp.quat),
    ignore_bodies: wp.array2d(dtype=wp.int32),
):
    env = wp.tid()
    if env_mask[env] == 0:
        return
    jaw_mask = (1 << jaw_a) | (1 << jaw_b)
    release_slots(env, slot_start, slots, jaw_mask, attach_particle, ignore_bodies, use_ignore)
    lost_grasp[env] = 0
    grasped[env] = 0
    if particle < 0:
        return
    # the jaw on the particle's side of the mid-plane holds it (jaw A closes from local -y, jaw B from +y)
    body = jaw_b
    if wp.transform_point(wp.transform_inverse(body_q[env, shaft]), q[env, particle])[1] < 0.0:
        body = jaw_a
    jaw = body_q[env, body]
    attach_particle[env, slot_start] = particle
    attach_body[env, slot_start] = body
    attach_offset[env, slot_start] = wp.transform_point(wp.transform_inverse(jaw), q[env, particle])
    attach_compliance[env, slot_start] = compliance
    seg = particle_segment[particle]
    if seg >= 0:
        grasp_delta[env, 0] = wp.mul(wp.quat_inverse(wp.transform_get_rotation(jaw)), segment_q[env, seg])
    if use_ignore != 0:
        ignore_bodies[env, particle] = ignore_bodies[env, particle] | jaw_mask
    grasped[env] = 1


# ----------------------------------------------------------------------------------------------------
# instrument bodies (lapwarp/instrument_shapes.py)
# ----------------------------------------------------------------------------------------------------


@wp.kernel
def pose_instrument_bodies(
    tip_pose: wp.array2d(dtype=wp.transform),
    column: int,
    jaw_angle_deg: wp.array(dtype=float),
    bodies: wp.vec3i,
    body_q: wp.array2d(dtype=wp.transform),
):
    env = wp.tid()
    tip = tip_pose[env, column]
    body_q[env, bodies[0]] = tip
    if bodies[1] >= 0:
        a = jaw_angle_deg[env] * (wp.pi / 180.0)
        body_q[env, bodies[1]] = wp.transform_multiply(
            tip, wp.transform(wp.vec3(0.0), wp.quat_from_axis_angle(wp.vec3(1.0, 0.0, 0.0), a)))
        body_q[env, bodies[2]] = wp.transform_multiply(
            tip, wp.transform(wp.vec3(0.0), wp.quat_from_axis_angle(wp.vec3(1.0, 0.0, 0.0), -a)))


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
