"""Kernels of the batched software rasteriser: visibility buffer, shading, point clouds, tubes.

The renderer front-end (``lapwarp/render.py``) owns the arrays; this module owns the GPU work:

* ``rasterize_rigid`` / ``rasterize_deformable``: a thread per (env, triangle slot) projects one triangle
  with the env's own camera, clips it against the near plane and writes, for every covered pixel centre,
  an atomic minimum of a packed 64-bit key ``(depth float bits << 32) | triangle id`` into the visibility
  buffer ``vbuf (num_envs, H, W)``. Positive float bits order like the floats, so the minimum key is the
  nearest fragment, with ties broken by the lower triangle id (deterministic).
* ``shade_visibility``: a thread per (env, pixel) decodes the key, re-fetches the winning triangle,
  shades it (Lambert, ambient + head light at the camera) and writes RGB / depth / segmentation, then
  resets the key so the next frame needs no separate clear pass.
* helpers: smooth normals of deformable surfaces, tube vertices from rod nodes, point copies,
  depth -> point cloud, world -> pixel projection.

Camera conventions (OpenGL, as SOFA): the camera looks along its local -Z with +Y up; ``focal`` is in
pixels, ``focal = (H / 2) / tan(fovy / 2)`` for both axes (square pixels). A view-space point
``(x, y, z)`` with ``z < 0`` projects to the continuous image coordinates ``col = cx + focal * x / -z``,
``row = cy - focal * y / -z`` with ``cx = W / 2``, ``cy = H / 2``; pixel ``(r, c)`` covers
``[r, r + 1) x [c, c + 1)``, its centre is ``(r + 0.5, c + 0.5)`` and row 0 is the top of the image.
Depth is the distance along the view axis (``-z``), in metres.
"""

import warp as wp

wp.set_module_options({"enable_backward": False})

# All bits set: larger than any key holding a finite positive depth, i.e. "no fragment".
EMPTY_KEY = wp.constant(wp.uint64(0xFFFFFFFFFFFFFFFF))

# obj_flags bits
FLAG_DOUBLE_SIDED = wp.constant(1)
FLAG_SMOOTH = wp.constant(2)
FLAG_VERTEX_COLORS = wp.constant(4)

# obj_kind values
KIND_RIGID = wp.constant(0)
KIND_DEFORMABLE = wp.constant(1)


@wp.func
def pack_key(depth: float, tri: int) -> wp.uint64:
    return (wp.uint64(wp.cast(depth, wp.uint32)) << wp.uint64(32)) | wp.uint64(wp.uint32(tri))


@wp.func
def key_depth(key: wp.uint64) -> float:
    return wp.cast(wp.uint32(key >> wp.uint64(32)), wp.float32)


@wp.func
def key_triangle(key: wp.uint64) -> int:
    return wp.int32(wp.uint32(key))


@wp.func
def edge_function(a: wp.vec2, b: wp.vec2, p: wp.vec2) -> float:
    # Evaluated with the endpoints in a canonical order so that the two triangles sharing an edge get
    # exactly opposite values: a pixel centre on a shared edge is then covered by at least one of them
    # (no cracks in watertight meshes), whatever the rounding.
    if a[0] < b[0] or (a[0] == b[0] and a[1] < b[1]):
        return (b[0] - a[0]) * (p[1] - a[1]) - (b[1] - a[1]) * (p[0] - a[0])
    return -((a[0] - b[0]) * (p[1] - b[1]) - (a[1] - b[1]) * (p[0] - b[0]))


@wp.func
def fill_triangle(
    vbuf: wp.array3d(dtype=wp.uint64),
    env: int,
    a: wp.vec3,
    b: wp.vec3,
    c: wp.vec3,
    tri: int,
    cull_back: int,
    part: int,
    nparts: int,
    focal: float,
    cx: float,
    cy: float,
    far: float,
    width: int,
    height: int,
    early_z: int,
):
    """Rasterises a view-space triangle whose vertices all lie at or beyond the near plane."""
    za = -a[2]
    zb = -b[2]
    zc = -c[2]
    sa = wp.vec2(cx + focal * a[0] / za, cy - focal * a[1] / za)
    sb = wp.vec2(cx + focal * b[0] / zb, cy - focal * b[1] / zb)
    sc = wp.vec2(cx + focal * c[0] / zc, cy - focal * c[1] / zc)
    area = edge_function(sa, sb, sc)
    # With rows growing downwards, a triangle wound counter-clockwise in view space (front face,
    # outward normal towards the camera) has a negative signed area here.
    if area == 0.0:
        return
    if cull_back != 0 and area > 0.0:
        return
    # Pixel centres at +0.5: the covered index range of [lo, hi] is [ceil(lo - 0.5), floor(hi - 0.5)].
    x0 = wp.max(int(wp.ceil(wp.min(wp.min(sa[0], sb[0]), sc[0]) - 0.5)), 0)
    x1 = wp.min(int(wp.floor(wp.max(wp.max(sa[0], sb[0]), sc[0]) - 0.5)), width - 1)
    y0 = wp.max(int(wp.ceil(wp.min(wp.min(sa[1], sb[1]), sc[1]) - 0.5)), 0)
    y1 = wp.min(int(wp.floor(wp.max(wp.max(sa[1], sb[1]), sc[1]) - 0.5)), height - 1)
    if x0 > x1 or y0 > y1:
        return
    sign = 1.0
    if area < 0.0:
        sign = -1.0
    inv_area = 1.0 / area
    iza = 1.0 / za
    izb = 1.0 / zb
    izc = 1.0 / zc
    lo = wp.uint64(wp.uint32(tri))
    # Big triangles are split over `nparts` threads that take interleaved rows of the bounding box.
    for y in range(y0 + part, y1 + 1, nparts):
        py = float(y) + 0.5
        for x in range(x0, x1 + 1):
            p = wp.vec2(float(x) + 0.5, py)
            wa = edge_function(sb, sc, p)
            wb = edge_function(sc, sa, p)
            wc = edge_function(sa, sb, p)
            if wa * sign >= 0.0 and wb * sign >= 0.0 and wc * sign >= 0.0:
                # 1/z is affine in screen space: perspective-correct depth.
                depth = 1.0 / ((wa * iza + wb * izb + wc * izc) * inv_area)
                if depth <= far:
                    key = (wp.uint64(wp.cast(depth, wp.uint32)) << wp.uint64(32)) | lo
                    # Early depth test: keys only ever decrease, so even a stale read that is already
                    # below our key proves the fragment hidden and saves the atomic.
                    if early_z == 0 or key < vbuf[env, y, x]:
                        wp.atomic_min(vbuf, env, y, x, key)


@wp.func
def clip_point(inside: wp.vec3, outside: wp.vec3, near: float) -> wp.vec3:
    # Always interpolated from the inside endpoint, so neighbours sharing the edge get the same point.
    t = (-near - inside[2]) / (outside[2] - inside[2])
    return inside + t * (outside - inside)


@wp.func
def raster_view_triangle(
    vbuf: wp.array3d(dtype=wp.uint64),
    env: int,
    a: wp.vec3,
    b: wp.vec3,
    c: wp.vec3,
    tri: int,
    cull_back: int,
    part: int,
    nparts: int,
    focal: float,
    cx: float,
    cy: float,
    near: float,
    far: float,
    width: int,
    height: int,
    early_z: int,
):
    """Culls a view-space triangle against near/far, clips it at the near plane and rasterises it."""
    ina = -a[2] >= near
    inb = -b[2] >= near
    inc = -c[2] >= near
    if -a[2] > far and -b[2] > far and -c[2] > far:
        return
    n_in = int(ina) + int(inb) + int(inc)
    if n_in == 0:
        return
    # Up to two triangles (p0, p1, p2) and (p0, p2, p3) remain after clipping; one fill_triangle call site
    # keeps the inlined code small.
    p0 = a
    p1 = b
    p2 = c
    p3 = c
    count = 1
    if n_in < 3:
        # Rotate (cyclically, keeping the winding) so that p is the vertex alone on its side of the plane.
        p = a
        q = b
        r = c
        if (n_in == 1 and inb) or (n_in == 2 and not inb):
            p = b
            q = c
            r = a
        elif (n_in == 1 and inc) or (n_in == 2 and not inc):
            p = c
            q = a
            r = b
        if n_in == 1:
            p0 = p
            p1 = clip_point(p, q, near)
            p2 = clip_point(p, r, near)
        else:
            p0 = clip_point(q, p, near)
            p1 = q
            p2 = r
            p3 = clip_point(r, p, near)
            count = 2
    for k in range(count):
        v1 = p1
        v2 = p2
        if k == 1:
            v1 = p2
            v2 = p3
        fill_triangle(vbuf, env, p0, v1, v2, tri, cull_back, part, nparts, focal, cx, cy, far, width, height, early_z)


@wp.kernel
def rasterize_rigid(
    slot_tri: wp.array(dtype=wp.int32),
    slot_split: wp.array(dtype=wp.int32),
    tri_obj: wp.array(dtype=wp.int32),
    tri_vidx: wp.array(dtype=wp.vec3i),
    obj_inst: wp.array(dtype=wp.int32),
    obj_flags: wp.array(dtype=wp.int32),
    rigid_verts: wp.array(dtype=wp.vec3),
    obj_visible: wp.array2d(dtype=wp.int32),
    cam_xf: wp.array(dtype=wp.transform),
    inst_xf: wp.array2d(dtype=wp.transform),
    focal: float,
    cx: float,
    cy: float,
    near: float,
    far: float,
    width: int,
    height: int,
    early_z: int,
    vbuf_out: wp.array3d(dtype=wp.uint64),
):
    """One thread per (env, slot); a slot is one triangle of one rigid instance, or one row-interleaved
    part of it for meshes made of few large triangles (``slot_split = part | nparts << 16``)."""
    env, s = wp.tid()
    tri = slot_tri[s]
    obj = tri_obj[tri]
    if obj_visible[env, obj] == 0:
        return
    split = slot_split[s]
    view = wp.transform_multiply(wp.transform_inverse(cam_xf[env]), inst_xf[env, obj_inst[obj]])
    idx = tri_vidx[tri]
    a = wp.transform_point(view, rigid_verts[idx[0]])
    b = wp.transform_point(view, rigid_verts[idx[1]])
    c = wp.transform_point(view, rigid_verts[idx[2]])
    cull = int((obj_flags[obj] & FLAG_DOUBLE_SIDED) == 0)
    raster_view_triangle(
        vbuf_out, env, a, b, c, tri, cull, split & 0xFFFF, split >> 16, focal, cx, cy, near, far, width, height, early_z
    )


@wp.kernel
def rasterize_deformable(
    tri_vidx: wp.array(dtype=wp.vec3i),
    tri_begin: int,
    nparts: int,
    obj: int,
    cull: int,
    def_points: wp.array2d(dtype=wp.vec3),
    active: wp.array2d(dtype=wp.int32),
    obj_visible: wp.array2d(dtype=wp.int32),
    cam_xf: wp.array(dtype=wp.transform),
    focal: float,
    cx: float,
    cy: float,
    near: float,
    far: float,
    width: int,
    height: int,
    early_z: int,
    vbuf_out: wp.array3d(dtype=wp.uint64),
):
    """One thread per (env, face * nparts + part) of one deformable surface; ``active`` is
    ``(1 or num_envs, F)`` and faces with ``active == 0`` (cut) are skipped."""
    env, s = wp.tid()
    f = s // nparts
    if obj_visible[env, obj] == 0:
        return
    if active[env % active.shape[0], f] == 0:
        return
    tri = tri_begin + f
    view = wp.transform_inverse(cam_xf[env])
    idx = tri_vidx[tri]
    a = wp.transform_point(view, def_points[env, idx[0]])
    b = wp.transform_point(view, def_points[env, idx[1]])
    c = wp.transform_point(view, def_points[env, idx[2]])
    part = s - f * nparts
    raster_view_triangle(
        vbuf_out, env, a, b, c, tri, cull, part, nparts, focal, cx, cy, near, far, width, height, early_z
    )


@wp.kernel
def rasterize_deformable_u8(
    tri_vidx: wp.array(dtype=wp.vec3i),
    tri_begin: int,
    nparts: int,
    obj: int,
    cull: int,
    def_points: wp.array2d(dtype=wp.vec3),
    active: wp.array2d(dtype=wp.uint8),
    obj_visible: wp.array2d(dtype=wp.int32),
    cam_xf: wp.array(dtype=wp.transform),
    focal: float,
    cx: float,
    cy: float,
    near: float,
    far: float,
    width: int,
    height: int,
    early_z: int,
    vbuf_out: wp.array3d(dtype=wp.uint64),
):
    """``rasterize_deformable`` for uint8/bool ``active`` masks."""
    env, s = wp.tid()
    f = s // nparts
    if obj_visible[env, obj] == 0:
        return
    if active[env % active.shape[0], f] == wp.uint8(0):
        return
    tri = tri_begin + f
    view = wp.transform_inverse(cam_xf[env])
    idx = tri_vidx[tri]
    a = wp.transform_point(view, def_points[env, idx[0]])
    b = wp.transform_point(view, def_points[env, idx[1]])
    c = wp.transform_point(view, def_points[env, idx[2]])
    part = s - f * nparts
    raster_view_triangle(
        vbuf_out, env, a, b, c, tri, cull, part, nparts, focal, cx, cy, near, far, width, height, early_z
    )


@wp.func
def to_u8(v: float) -> wp.uint8:
    return wp.uint8(wp.int32(wp.clamp(v, 0.0, 1.0) * 255.0 + 0.5))


@wp.kernel
def shade_visibility(
    tri_obj: wp.array(dtype=wp.int32),
    tri_vidx: wp.array(dtype=wp.vec3i),
    obj_kind: wp.array(dtype=wp.int32),
    obj_inst: wp.array(dtype=wp.int32),
    obj_flags: wp.array(dtype=wp.int32),
    obj_seg: wp.array(dtype=wp.int32),
    obj_color: wp.array2d(dtype=wp.vec3),
    rigid_verts: wp.array(dtype=wp.vec3),
    rigid_normals: wp.array(dtype=wp.vec3),
    rigid_colors: wp.array(dtype=wp.vec3),
    def_points: wp.array2d(dtype=wp.vec3),
    def_normals: wp.array2d(dtype=wp.vec3),
    def_colors: wp.array(dtype=wp.vec3),
    cam_xf: wp.array(dtype=wp.transform),
    inst_xf: wp.array2d(dtype=wp.transform),
    focal: float,
    cx: float,
    cy: float,
    background_depth: float,
    background_color: wp.vec3,
    ambient: float,
    diffuse: float,
    write_rgb: int,
    write_depth: int,
    write_seg: int,
    vbuf: wp.array3d(dtype=wp.uint64),
    rgb_out: wp.array4d(dtype=wp.uint8),
    depth_out: wp.array4d(dtype=wp.float32),
    seg_out: wp.array4d(dtype=wp.int32),
):
    """One thread per (env, row, col): resolve the visibility buffer into the image outputs and clear it."""
    env, y, x = wp.tid()
    key = vbuf[env, y, x]
    vbuf[env, y, x] = EMPTY_KEY
    if key == EMPTY_KEY:
        if write_rgb != 0:
            rgb_out[env, 0, y, x] = to_u8(background_color[0])
            rgb_out[env, 1, y, x] = to_u8(background_color[1])
            rgb_out[env, 2, y, x] = to_u8(background_color[2])
        if write_depth != 0:
            depth_out[env, 0, y, x] = background_depth
        if write_seg != 0:
            seg_out[env, 0, y, x] = -1
        return
    tri = key_triangle(key)
    obj = tri_obj[tri]
    if write_depth != 0:
        depth_out[env, 0, y, x] = key_depth(key)
    if write_seg != 0:
        seg_out[env, 0, y, x] = obj_seg[obj]
    if write_rgb == 0:
        return
    idx = tri_vidx[tri]
    flags = obj_flags[obj]
    view = wp.transform_inverse(cam_xf[env])
    a = wp.vec3()
    b = wp.vec3()
    c = wp.vec3()
    na = wp.vec3()
    nb = wp.vec3()
    nc = wp.vec3()
    ca = wp.vec3(1.0, 1.0, 1.0)
    cb = wp.vec3(1.0, 1.0, 1.0)
    cc = wp.vec3(1.0, 1.0, 1.0)
    if obj_kind[obj] == KIND_RIGID:
        view = wp.transform_multiply(view, inst_xf[env, obj_inst[obj]])
        a = wp.transform_point(view, rigid_verts[idx[0]])
        b = wp.transform_point(view, rigid_verts[idx[1]])
        c = wp.transform_point(view, rigid_verts[idx[2]])
        if (flags & FLAG_SMOOTH) != 0:
            na = wp.transform_vector(view, rigid_normals[idx[0]])
            nb = wp.transform_vector(view, rigid_normals[idx[1]])
            nc = wp.transform_vector(view, rigid_normals[idx[2]])
        if (flags & FLAG_VERTEX_COLORS) != 0:
            ca = rigid_colors[idx[0]]
            cb = rigid_colors[idx[1]]
            cc = rigid_colors[idx[2]]
    else:
        a = wp.transform_point(view, def_points[env, idx[0]])
        b = wp.transform_point(view, def_points[env, idx[1]])
        c = wp.transform_point(view, def_points[env, idx[2]])
        if (flags & FLAG_SMOOTH) != 0:
            na = wp.transform_vector(view, def_normals[env, idx[0]])
            nb = wp.transform_vector(view, def_normals[env, idx[1]])
            nc = wp.transform_vector(view, def_normals[env, idx[2]])
        if (flags & FLAG_VERTEX_COLORS) != 0:
            ca = def_colors[idx[0]]
            cb = def_colors[idx[1]]
            cc = def_colors[idx[2]]
    # Perspective-correct barycentrics of the pixel ray (origin at the camera) through the triangle
    # (Moller-Trumbore); robust for triangles clipped at the near plane, unlike screen-space weights.
    d = wp.vec3((float(x) + 0.5 - cx) / focal, -(float(y) + 0.5 - cy) / focal, -1.0)
    e1 = b - a
    e2 = c - a
    pvec = wp.cross(d, e2)
    det = wp.dot(e1, pvec)
    u = float(1.0 / 3.0)
    v = float(1.0 / 3.0)
    if det != 0.0:
        inv_det = 1.0 / det
        tvec = -a
        u = wp.clamp(wp.dot(tvec, pvec) * inv_det, 0.0, 1.0)
        v = wp.clamp(wp.dot(d, wp.cross(tvec, e1)) * inv_det, 0.0, 1.0 - u)
    w = 1.0 - u - v
    ng = wp.cross(e1, e2)
    n = ng
    if (flags & FLAG_SMOOTH) != 0:
        n = w * na + u * nb + v * nc
    # A visible back face (double-sided surface) is lit from its own side.
    if wp.dot(ng, d) > 0.0:
        n = -n
    light = -wp.normalize(d)
    lambert = wp.max(wp.dot(wp.normalize(n), light), 0.0)
    albedo = wp.cw_mul(obj_color[env, obj], w * ca + u * cb + v * cc)
    col = albedo * (ambient + diffuse * lambert)
    rgb_out[env, 0, y, x] = to_u8(col[0])
    rgb_out[env, 1, y, x] = to_u8(col[1])
    rgb_out[env, 2, y, x] = to_u8(col[2])


@wp.kernel
def copy_points(src: wp.array2d(dtype=wp.vec3), offset: int, dst: wp.array2d(dtype=wp.vec3)):
    env, i = wp.tid()
    dst[env, offset + i] = src[env, i]


@wp.kernel
def compute_vertex_normals(
    faces: wp.array(dtype=wp.vec3i),
    tri_begin: int,
    vert_begin: int,
    adj_start: wp.array(dtype=wp.int32),
    adj_faces: wp.array(dtype=wp.int32),
    def_points: wp.array2d(dtype=wp.vec3),
    active: wp.array2d(dtype=wp.int32),
    normals_out: wp.array2d(dtype=wp.vec3),
):
    """Area-weighted vertex normals of one deformable surface by gathering over the (shared, CSR)
    vertex-face adjacency: no atomics; cut faces do not contribute."""
    env, i = wp.tid()
    n = wp.vec3()
    for k in range(adj_start[i], adj_start[i + 1]):
        f = adj_faces[k]
        if active[env % active.shape[0], f] != 0:
            idx = faces[tri_begin + f]
            a = def_points[env, idx[0]]
            n += wp.cross(def_points[env, idx[1]] - a, def_points[env, idx[2]] - a)
    length = wp.length(n)
    if length > 0.0:
        n = n / length
    normals_out[env, vert_begin + i] = n


@wp.kernel
def compute_vertex_normals_u8(
    faces: wp.array(dtype=wp.vec3i),
    tri_begin: int,
    vert_begin: int,
    adj_start: wp.array(dtype=wp.int32),
    adj_faces: wp.array(dtype=wp.int32),
    def_points: wp.array2d(dtype=wp.vec3),
    active: wp.array2d(dtype=wp.uint8),
    normals_out: wp.array2d(dtype=wp.vec3),
):
    """``compute_vertex_normals`` for uint8/bool ``active`` masks."""
    env, i = wp.tid()
    n = wp.vec3()
    for k in range(adj_start[i], adj_start[i + 1]):
        f = adj_faces[k]
        if active[env % active.shape[0], f] != wp.uint8(0):
            idx = faces[tri_begin + f]
            a = def_points[env, idx[0]]
            n += wp.cross(def_points[env, idx[1]] - a, def_points[env, idx[2]] - a)
    length = wp.length(n)
    if length > 0.0:
        n = n / length
    normals_out[env, vert_begin + i] = n


@wp.kernel
def generate_tube(
    nodes: wp.array2d(dtype=wp.vec3),
    radius: float,
    sides: int,
    caps: int,
    vert_begin: int,
    points_out: wp.array2d(dtype=wp.vec3),
    normals_out: wp.array2d(dtype=wp.vec3),
):
    """Ring of ``sides`` vertices (and analytic radial normals) around node i of a polyline; with caps,
    two extra centre vertices close the ends. The ring frame is Frisvad's orthonormal basis of the local
    tangent: no sequential frame propagation, continuous except for tangents close to -Z."""
    env, i = wp.tid()
    n = nodes.shape[1]
    prev = wp.max(i - 1, 0)
    nxt = wp.min(i + 1, n - 1)
    t = nodes[env, nxt] - nodes[env, prev]
    length = wp.length(t)
    if length > 0.0:
        t = t / length
    else:
        t = wp.vec3(1.0, 0.0, 0.0)
    b1 = wp.vec3(0.0, -1.0, 0.0)
    b2 = wp.vec3(-1.0, 0.0, 0.0)
    if t[2] > -0.9999999:
        h = 1.0 / (1.0 + t[2])
        k = -t[0] * t[1] * h
        b1 = wp.vec3(1.0 - t[0] * t[0] * h, k, -t[0])
        b2 = wp.vec3(k, 1.0 - t[1] * t[1] * h, -t[1])
    p = nodes[env, i]
    for s in range(sides):
        ang = 2.0 * wp.pi * float(s) / float(sides)
        radial = wp.cos(ang) * b1 + wp.sin(ang) * b2
        points_out[env, vert_begin + i * sides + s] = p + radius * radial
        normals_out[env, vert_begin + i * sides + s] = radial
    if caps != 0:
        if i == 0:
            points_out[env, vert_begin + n * sides] = p
            normals_out[env, vert_begin + n * sides] = -t
        if i == n - 1:
            points_out[env, vert_begin + n * sides + 1] = p
            normals_out[env, vert_begin + n * sides + 1] = t


@wp.kernel
def depth_to_points(
    depth: wp.array4d(dtype=wp.float32),
    cam_xf: wp.array(dtype=wp.transform),
    focal: float,
    cx: float,
    cy: float,
    world: int,
    points_out: wp.array2d(dtype=wp.vec3),
):
    """Back-projects every pixel centre at its depth; ``points_out[env, row * W + col]``."""
    env, y, x = wp.tid()
    z = depth[env, 0, y, x]
    p = wp.vec3((float(x) + 0.5 - cx) / focal * z, -(float(y) + 0.5 - cy) / focal * z, -z)
    if world != 0:
        p = wp.transform_point(cam_xf[env], p)
    points_out[env, y * depth.shape[3] + x] = p


@wp.func
def world_to_pixel(cam: wp.transform, p: wp.vec3, focal: float, cx: float, cy: float) -> wp.vec3:
    """World point -> ``(row, col, depth)``: continuous pixel coordinates (``floor`` gives the pixel index,
    row 0 at the top) and the distance along the view axis; meaningless when ``depth <= 0``."""
    q = wp.transform_point(wp.transform_inverse(cam), p)
    z = -q[2]
    return wp.vec3(cy - focal * q[1] / z, cx + focal * q[0] / z, z)


@wp.kernel
def project_world_points(
    points: wp.array2d(dtype=wp.vec3),
    cam_xf: wp.array(dtype=wp.transform),
    focal: float,
    cx: float,
    cy: float,
    out: wp.array2d(dtype=wp.vec3),
):
    env, i = wp.tid()
    out[env, i] = world_to_pixel(cam_xf[env], points[env, i], focal, cx, cy)
