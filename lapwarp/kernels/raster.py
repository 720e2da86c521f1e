"""Kernels of the batched software rasteriser: visibility buffer, shading, point clouds, tubes.

The renderer front-end (``lapwarp/render.py``) owns the arrays; this module owns the GPU work:

* ``prepare_views`` / ``cull_clusters``: per env, local-to-view matrices of the rigid instances and a draw
  flag per instance and per cluster of 32 triangles (frustum, no pixel centre covered, normal cone).
* ``rasterize_rigid`` / ``rasterize_deformable``: a thread per (env, triangle slot) projects one triangle
  with the env's own camera (homogeneous rasterisation: no clipping into sub-triangles, near plane as a
  per-pixel test) and writes, for every covered pixel centre, an atomic minimum of a packed 64-bit key
  ``(depth float bits << 32) | triangle id`` into the visibility buffer ``vbuf (num_envs, H, W)``.
  Positive float bits order like the floats, so the minimum key is the nearest fragment, with ties broken
  by the lower triangle id (deterministic).
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

# The rasteriser's and the shader's kernels (53-55 registers uncapped, sm_90: 4 blocks of 256 threads per SM) at 48:
# 5 blocks per SM, spill frames of 16-32 bytes. H200, 4,096 envs, RGB 64x64, expert, same call (forty-sixth session,
# benchmarks/RESULTS.md): ThreadInHole 195.4k -> 197.2k env-steps/s, RopeThreading 181.1k -> 182.6k. The CPU ignores it.
RASTER_MAX_REGISTERS = 48

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
def homogeneous(p: wp.vec3, focal: float, cx: float, cy: float) -> wp.vec3:
    """2-D homogeneous image coordinates ``(col * w, row * w, w)`` of a view-space point, ``w = -z``."""
    w = -p[2]
    return wp.vec3(cx * w + focal * p[0], cy * w - focal * p[1], w)


@wp.func
def edge_coefficients(a: wp.vec3, b: wp.vec3) -> wp.vec3:
    """``(A, B, C)`` of the homogeneous edge function ``A col + B row + C`` of the directed edge a -> b."""
    # Built from the endpoints in a canonical order and negated for the other direction: the two
    # triangles sharing an edge get exactly opposite values at every pixel centre, so a centre on a
    # shared edge is covered by at least one of them (no cracks in watertight meshes), whatever the
    # rounding.
    if a[0] < b[0] or (a[0] == b[0] and (a[1] < b[1] or (a[1] == b[1] and a[2] < b[2]))):
        return wp.cross(a, b)
    return -wp.cross(b, a)


@wp.func
def bbox_include(box: wp.vec4, h: wp.vec3) -> wp.vec4:
    """Grows a screen box ``(col_min, row_min, col_max, row_max)`` by a homogeneous point with ``w > 0``."""
    inv_w = 1.0 / h[2]
    col = h[0] * inv_w
    row = h[1] * inv_w
    return wp.vec4(wp.min(box[0], col), wp.min(box[1], row), wp.max(box[2], col), wp.max(box[3], row))


@wp.func
def clip_point(inside: wp.vec3, outside: wp.vec3, near: float) -> wp.vec3:
    """Homogeneous point where the edge crosses the near plane ``w = near`` (homogeneous coordinates are
    linear in view space). Always interpolated from the inside endpoint, so that the neighbour sharing the
    edge gets the same point."""
    t = (near - inside[2]) / (outside[2] - inside[2])
    return inside + t * (outside - inside)


@wp.func
def raster_view_triangle(
    vbuf: wp.array(dtype=wp.uint64),
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
    """Rasterises a view-space triangle into the flat visibility buffer of ``env``.

    Homogeneous rasterisation (Olano & Greer 1997): edge functions of the 2-D homogeneous vertices are
    valid for triangles crossing the camera plane, so there is no clipping into sub-triangles; the near
    plane only bounds the pixel box (from the clipped polygon) and is a per-pixel depth test. For pixel
    centre ``p``, ``e_i(p) = det * b_i / w(p)`` (``b_i`` the barycentrics), hence the inside test "all
    ``e_i >= 0``" (after orienting by ``sign(det)``, which also rejects the mirror image behind the camera)
    and the perspective-correct depth ``w(p) = |det| / sum_i e_i(p)``.
    """
    ha = homogeneous(a, focal, cx, cy)
    hb = homogeneous(b, focal, cx, cy)
    hc = homogeneous(c, focal, cx, cy)
    if ha[2] > far and hb[2] > far and hc[2] > far:
        return
    ina = ha[2] >= near
    inb = hb[2] >= near
    inc = hc[2] >= near
    if not (ina or inb or inc):
        return
    # Screen box of the part in front of the near plane: the vertices in front and the crossing points.
    box = wp.vec4(1.0e30, 1.0e30, -1.0e30, -1.0e30)
    if ina:
        box = bbox_include(box, ha)
    if inb:
        box = bbox_include(box, hb)
    if inc:
        box = bbox_include(box, hc)
    if ina != inb:
        if ina:
            box = bbox_include(box, clip_point(ha, hb, near))
        else:
            box = bbox_include(box, clip_point(hb, ha, near))
    if inb != inc:
        if inb:
            box = bbox_include(box, clip_point(hb, hc, near))
        else:
            box = bbox_include(box, clip_point(hc, hb, near))
    if inc != ina:
        if inc:
            box = bbox_include(box, clip_point(hc, ha, near))
        else:
            box = bbox_include(box, clip_point(ha, hc, near))
    # Pixel centres at +0.5: the covered index range of [lo, hi] is [ceil(lo - 0.5), floor(hi - 0.5)];
    # clamped as floats first so that far-off vertices cannot overflow the int conversion.
    x0 = int(wp.ceil(wp.max(box[0] - 0.5, 0.0)))
    y0 = int(wp.ceil(wp.max(box[1] - 0.5, 0.0)))
    x1 = int(wp.floor(wp.min(box[2] - 0.5, float(width - 1))))
    y1 = int(wp.floor(wp.min(box[3] - 0.5, float(height - 1))))
    if x0 > x1 or y0 > y1:
        return
    ea = edge_coefficients(hb, hc)
    eb = edge_coefficients(hc, ha)
    ec = edge_coefficients(ha, hb)
    # det = focal^2 * dot(a, normal): negative for a front face (counter-clockwise seen from the camera).
    # NaN vertices fail both comparisons.
    det = wp.dot(ha, ea)
    if not (det < 0.0 or det > 0.0):
        return
    if cull_back != 0 and det > 0.0:
        return
    if det < 0.0:
        # Orient by sign(det); exact negation keeps the neighbour symmetry. Inside is "all three >= 0".
        ea = -ea
        eb = -eb
        ec = -ec
    es = ea + eb + ec
    adet = wp.abs(det)
    lo = wp.uint64(wp.uint32(tri))
    base = env * height * width
    # Big triangles are split over `nparts` threads that take interleaved rows of the bounding box.
    for y in range(y0 + part, y1 + 1, nparts):
        py = float(y) + 0.5
        ra = ea[1] * py + ea[2]
        rb = eb[1] * py + eb[2]
        rc = ec[1] * py + ec[2]
        rs = es[1] * py + es[2]
        for x in range(x0, x1 + 1):
            px = float(x) + 0.5
            if ea[0] * px + ra >= 0.0 and eb[0] * px + rb >= 0.0 and ec[0] * px + rc >= 0.0:
                depth = adet / (es[0] * px + rs)
                if depth >= near and depth <= far:
                    key = (wp.uint64(wp.cast(depth, wp.uint32)) << wp.uint64(32)) | lo
                    pix = base + y * width + x
                    # Early depth test: keys only ever decrease, so even a stale read that is already
                    # below our key proves the fragment hidden and saves the atomic.
                    if early_z == 0 or key < vbuf[pix]:
                        wp.atomic_min(vbuf, pix, key)


@wp.func
def inverse_rigid_vector(m: wp.mat44, v: wp.vec3) -> wp.vec3:
    """``v`` moved by the inverse of the rigid matrix ``m`` (rotation part only): ``R^T v``."""
    return wp.vec3(
        m[0, 0] * v[0] + m[1, 0] * v[1] + m[2, 0] * v[2],
        m[0, 1] * v[0] + m[1, 1] * v[1] + m[2, 1] * v[2],
        m[0, 2] * v[0] + m[1, 2] * v[1] + m[2, 2] * v[2],
    )


@wp.func
def inverse_rigid_point(m: wp.mat44, p: wp.vec3) -> wp.vec3:
    """``p`` moved by the inverse of the rigid matrix ``m``: ``R^T (p - t)``."""
    return inverse_rigid_vector(m, p - wp.vec3(m[0, 3], m[1, 3], m[2, 3]))


@wp.func
def transform_matrix(t: wp.transform) -> wp.mat44:
    r = wp.quat_to_matrix(wp.transform_get_rotation(t))
    p = wp.transform_get_translation(t)
    # fmt: off
    return wp.mat44(
        r[0, 0], r[0, 1], r[0, 2], p[0],
        r[1, 0], r[1, 1], r[1, 2], p[1],
        r[2, 0], r[2, 1], r[2, 2], p[2],
        0.0, 0.0, 0.0, 1.0,
    )
    # fmt: on


@wp.kernel
def prepare_views(
    cam_xf: wp.array(dtype=wp.transform),
    inst_xf: wp.array2d(dtype=wp.transform),
    inst_obj: wp.array(dtype=wp.int32),
    inst_bounds: wp.array(dtype=wp.vec4),
    obj_visible: wp.array2d(dtype=wp.int32),
    tan_x: float,
    tan_y: float,
    near: float,
    far: float,
    views_out: wp.array2d(dtype=wp.mat44),
    inst_draw_out: wp.array2d(dtype=wp.int32),
):
    """One thread per (env, instance column, plus one): local-to-view matrices of every rigid instance and,
    in the last column, the world-to-view matrix; ``inst_draw_out`` is 0 for instances that are hidden or
    whose bounding sphere lies outside the view frustum, so their triangle threads stop at once."""
    env, i = wp.tid()
    cam_inv = wp.transform_inverse(cam_xf[env])
    num_inst = views_out.shape[1] - 1
    if i == num_inst:
        views_out[env, i] = transform_matrix(cam_inv)
        return
    if i >= inst_obj.shape[0]:
        return
    view = wp.transform_multiply(cam_inv, inst_xf[env, i])
    views_out[env, i] = transform_matrix(view)
    bound = inst_bounds[i]
    c = wp.transform_point(view, wp.vec3(bound[0], bound[1], bound[2]))
    r = bound[3]
    draw = obj_visible[env, inst_obj[i]] != 0 and not sphere_outside_frustum(c, r, tan_x, tan_y, near, far)
    inst_draw_out[env, i] = int(draw)


@wp.func
def sphere_outside_frustum(c: wp.vec3, r: float, tan_x: float, tan_y: float, near: float, far: float) -> bool:
    """Whether a view-space sphere lies entirely outside the view frustum (conservative)."""
    if -c[2] + r < near or -c[2] - r > far:
        return True
    # Signed distances to the four side planes (outward normals).
    sx = 1.0 / wp.sqrt(1.0 + tan_x * tan_x)
    sy = 1.0 / wp.sqrt(1.0 + tan_y * tan_y)
    if (c[0] + c[2] * tan_x) * sx > r or (-c[0] + c[2] * tan_x) * sx > r:
        return True
    return (c[1] + c[2] * tan_y) * sy > r or (-c[1] + c[2] * tan_y) * sy > r


@wp.func
def sphere_misses_pixel_centres(
    c: wp.vec3, r: float, focal: float, cx: float, cy: float, near: float, width: int, height: int
) -> bool:
    """Whether a view-space sphere (in front of the near plane) covers no pixel centre: its conservative
    screen box (x / z and y / z over the sphere's bounding box) contains none. Prunes sub-pixel clusters of
    finely tessellated meshes far from the camera."""
    z0 = -c[2] - r
    if z0 < near:
        return False
    z1 = -c[2] + r
    xa = c[0] - r
    xb = c[0] + r
    ya = c[1] - r
    yb = c[1] + r
    col0 = cx + focal * wp.min(xa / z0, xa / z1)
    col1 = cx + focal * wp.max(xb / z0, xb / z1)
    row0 = cy - focal * wp.max(yb / z0, yb / z1)
    row1 = cy - focal * wp.min(ya / z0, ya / z1)
    x0 = wp.ceil(wp.max(col0 - 0.5, 0.0))
    x1 = wp.floor(wp.min(col1 - 0.5, float(width - 1)))
    y0 = wp.ceil(wp.max(row0 - 0.5, 0.0))
    y1 = wp.floor(wp.min(row1 - 0.5, float(height - 1)))
    return x0 > x1 or y0 > y1


@wp.kernel
def cull_clusters(
    cluster_inst: wp.array(dtype=wp.int32),
    cluster_bounds: wp.array(dtype=wp.vec4),
    cluster_cones: wp.array(dtype=wp.vec4),
    views: wp.array2d(dtype=wp.mat44),
    inst_draw: wp.array2d(dtype=wp.int32),
    tan_x: float,
    tan_y: float,
    focal: float,
    cx: float,
    cy: float,
    near: float,
    far: float,
    width: int,
    height: int,
    cluster_draw_out: wp.array2d(dtype=wp.int32),
):
    """One thread per (env, cluster of 32 triangles of a rigid instance): 0 when the instance is not drawn,
    when the cluster's bounding sphere is outside the frustum or covers no pixel centre, or when its normal
    cone proves every triangle back-facing from this camera (single-sided meshes), so that its triangle
    threads stop at once."""
    env, k = wp.tid()
    inst = cluster_inst[k]
    draw = inst_draw[env, inst] != 0
    if draw:
        view = views[env, inst]
        bound = cluster_bounds[k]
        c = wp.transform_point(view, wp.vec3(bound[0], bound[1], bound[2]))
        r = bound[3]
        if sphere_outside_frustum(c, r, tan_x, tan_y, near, far):
            draw = False
        elif sphere_misses_pixel_centres(c, r, focal, cx, cy, near, width, height):
            draw = False
        cone = cluster_cones[k]
        dist = wp.length(c)
        if draw and cone[3] < 0.5 * wp.pi and dist > r:
            # All normals within cone[3] of the axis, all points within asin(r / dist) of the direction to
            # the centre: every triangle faces away when the two angles leave the axis beyond 90 degrees.
            axis = wp.transform_vector(view, wp.vec3(cone[0], cone[1], cone[2]))
            spread = cone[3] + wp.asin(r / dist)
            if spread < 0.5 * wp.pi and wp.dot(axis, c) > dist * wp.sin(spread):
                draw = False
    cluster_draw_out[env, k] = int(draw)


@wp.kernel(cuda_max_registers=RASTER_MAX_REGISTERS)
def rasterize_rigid(
    slot_tri: wp.array(dtype=wp.int32),
    slot_split: wp.array(dtype=wp.int32),
    tri_obj: wp.array(dtype=wp.int32),
    tri_vidx: wp.array(dtype=wp.vec3i),
    tri_cluster: wp.array(dtype=wp.int32),
    obj_inst: wp.array(dtype=wp.int32),
    obj_flags: wp.array(dtype=wp.int32),
    rigid_verts: wp.array(dtype=wp.vec3),
    views: wp.array2d(dtype=wp.mat44),
    cluster_draw: wp.array2d(dtype=wp.int32),
    focal: float,
    cx: float,
    cy: float,
    near: float,
    far: float,
    width: int,
    height: int,
    early_z: int,
    vbuf_out: wp.array(dtype=wp.uint64),
):
    """One thread per (env, slot); a slot is one triangle of one rigid instance, or one row-interleaved
    part of it for meshes made of few large triangles (``slot_split = part | nparts << 16``), or padding
    (``slot_tri = -1``)."""
    env, s = wp.tid()
    tri = slot_tri[s]
    if tri < 0:
        return
    if cluster_draw[env, tri_cluster[tri]] == 0:
        return
    obj = tri_obj[tri]
    split = slot_split[s]
    view = views[env, obj_inst[obj]]
    idx = tri_vidx[tri]
    a = wp.transform_point(view, rigid_verts[idx[0]])
    b = wp.transform_point(view, rigid_verts[idx[1]])
    c = wp.transform_point(view, rigid_verts[idx[2]])
    cull = int((obj_flags[obj] & FLAG_DOUBLE_SIDED) == 0)
    raster_view_triangle(
        vbuf_out, env, a, b, c, tri, cull, split & 0xFFFF, split >> 16, focal, cx, cy, near, far, width, height, early_z
    )


@wp.kernel(cuda_max_registers=RASTER_MAX_REGISTERS)
def rasterize_deformable(
    tri_vidx: wp.array(dtype=wp.vec3i),
    tri_begin: int,
    nparts: int,
    obj: int,
    cull: int,
    def_points: wp.array2d(dtype=wp.vec3),
    active: wp.array2d(dtype=wp.int32),
    obj_visible: wp.array2d(dtype=wp.int32),
    views: wp.array2d(dtype=wp.mat44),
    focal: float,
    cx: float,
    cy: float,
    near: float,
    far: float,
    width: int,
    height: int,
    early_z: int,
    vbuf_out: wp.array(dtype=wp.uint64),
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
    view = views[env, views.shape[1] - 1]
    idx = tri_vidx[tri]
    a = wp.transform_point(view, def_points[env, idx[0]])
    b = wp.transform_point(view, def_points[env, idx[1]])
    c = wp.transform_point(view, def_points[env, idx[2]])
    part = s - f * nparts
    raster_view_triangle(
        vbuf_out, env, a, b, c, tri, cull, part, nparts, focal, cx, cy, near, far, width, height, early_z
    )


@wp.kernel(cuda_max_registers=RASTER_MAX_REGISTERS)
def rasterize_deformable_u8(
    tri_vidx: wp.array(dtype=wp.vec3i),
    tri_begin: int,
    nparts: int,
    obj: int,
    cull: int,
    def_points: wp.array2d(dtype=wp.vec3),
    active: wp.array2d(dtype=wp.uint8),
    obj_visible: wp.array2d(dtype=wp.int32),
    views: wp.array2d(dtype=wp.mat44),
    focal: float,
    cx: float,
    cy: float,
    near: float,
    far: float,
    width: int,
    height: int,
    early_z: int,
    vbuf_out: wp.array(dtype=wp.uint64),
):
    """``rasterize_deformable`` for uint8/bool ``active`` masks."""
    env, s = wp.tid()
    f = s // nparts
    if obj_visible[env, obj] == 0:
        return
    if active[env % active.shape[0], f] == wp.uint8(0):
        return
    tri = tri_begin + f
    view = views[env, views.shape[1] - 1]
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


@wp.func
def store_color(env: int, y: int, x: int, col: wp.vec3, write_rgb: int, frame_rgb: int,
                rgb_out: wp.array4d(dtype=wp.uint8), frame_out: wp.array4d(dtype=wp.float32)):
    """A pixel's colour as bytes (``write_rgb``) and / or as the observation frame's bytes / 255 (``frame_rgb``)."""
    if write_rgb == 0 and frame_rgb == 0:
        return
    for k in range(3):
        byte = to_u8(col[k])
        if write_rgb != 0:
            rgb_out[env, k, y, x] = byte
        if frame_rgb != 0:
            frame_out[env, k, y, x] = float(byte) / 255.0


@wp.kernel(cuda_max_registers=RASTER_MAX_REGISTERS)
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
    views: wp.array2d(dtype=wp.mat44),
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
    frame_rgb: int,
    frame_depth: int,
    inv_far: float,
    vbuf: wp.array3d(dtype=wp.uint64),
    rgb_out: wp.array4d(dtype=wp.uint8),
    depth_out: wp.array4d(dtype=wp.float32),
    seg_out: wp.array4d(dtype=wp.int32),
    frame_out: wp.array4d(dtype=wp.float32),
):
    """One thread per (env, row, col): resolve the visibility buffer into the image outputs and clear it. With
    ``frame_rgb`` / ``frame_depth`` it also writes an observation frame ``(num_envs, C, H, W)`` in [0, 1]: the RGB
    bytes / 255, then depth / far (at most 1), as ``env_kernels.write_image_frame`` does in a launch of its own (the env
    keeps that launch where a task draws overlays into the bytes after the shading).

    A covered pixel's key is cleared last, after every load: cleared first (before the triangle's and the view's
    loads) the pass took twice as long on an H200 (ThreadInHole RGB, 4,096 envs: 1.15 ms against 0.55 ms without the
    clear, forty-seventh session's probe); an empty pixel's key is already clear and is not written."""
    env, y, x = wp.tid()
    key = vbuf[env, y, x]
    if key == EMPTY_KEY:
        store_color(env, y, x, background_color, write_rgb, frame_rgb, rgb_out, frame_out)
        if write_depth != 0:
            depth_out[env, 0, y, x] = background_depth
        if frame_depth != 0:
            frame_out[env, 3 * frame_rgb, y, x] = wp.min(background_depth * inv_far, 1.0)
        if write_seg != 0:
            seg_out[env, 0, y, x] = -1
        return
    tri = key_triangle(key)
    obj = tri_obj[tri]
    if write_depth != 0:
        depth_out[env, 0, y, x] = key_depth(key)
    if frame_depth != 0:
        frame_out[env, 3 * frame_rgb, y, x] = wp.min(key_depth(key) * inv_far, 1.0)
    if write_seg != 0:
        seg_out[env, 0, y, x] = obj_seg[obj]
    if write_rgb == 0 and frame_rgb == 0:
        vbuf[env, y, x] = EMPTY_KEY
        return
    idx = tri_vidx[tri]
    flags = obj_flags[obj]
    is_rigid = obj_kind[obj] == KIND_RIGID
    # Shade in the object's own frame (mesh-local for rigid instances, world for deformables): the pixel ray
    # is moved there once instead of moving three vertices and three normals into view space. Lambert with a
    # head light is invariant under that rigid motion.
    view = views[env, views.shape[1] - 1]
    if is_rigid:
        view = views[env, obj_inst[obj]]
    d_view = wp.vec3((float(x) + 0.5 - cx) / focal, -(float(y) + 0.5 - cy) / focal, -1.0)
    d = inverse_rigid_vector(view, d_view)
    o = inverse_rigid_point(view, wp.vec3(0.0, 0.0, 0.0))
    a = wp.vec3()
    b = wp.vec3()
    c = wp.vec3()
    if is_rigid:
        a = rigid_verts[idx[0]]
        b = rigid_verts[idx[1]]
        c = rigid_verts[idx[2]]
    else:
        a = def_points[env, idx[0]]
        b = def_points[env, idx[1]]
        c = def_points[env, idx[2]]
    # Perspective-correct barycentrics of the pixel ray through the triangle (Moller-Trumbore); robust for
    # triangles clipped at the near plane, unlike screen-space weights.
    e1 = b - a
    e2 = c - a
    pvec = wp.cross(d, e2)
    det = wp.dot(e1, pvec)
    u = float(1.0 / 3.0)
    v = float(1.0 / 3.0)
    if det != 0.0:
        inv_det = 1.0 / det
        tvec = o - a
        u = wp.clamp(wp.dot(tvec, pvec) * inv_det, 0.0, 1.0)
        v = wp.clamp(wp.dot(d, wp.cross(tvec, e1)) * inv_det, 0.0, 1.0 - u)
    w = 1.0 - u - v
    ng = wp.cross(e1, e2)
    n = ng
    if (flags & FLAG_SMOOTH) != 0:
        if is_rigid:
            n = w * rigid_normals[idx[0]] + u * rigid_normals[idx[1]] + v * rigid_normals[idx[2]]
        else:
            n = w * def_normals[env, idx[0]] + u * def_normals[env, idx[1]] + v * def_normals[env, idx[2]]
    # A visible back face (double-sided surface) is lit from its own side.
    if wp.dot(ng, d) > 0.0:
        n = -n
    albedo = obj_color[env, obj]
    if (flags & FLAG_VERTEX_COLORS) != 0:
        if is_rigid:
            vc = w * rigid_colors[idx[0]] + u * rigid_colors[idx[1]] + v * rigid_colors[idx[2]]
        else:
            vc = w * def_colors[idx[0]] + u * def_colors[idx[1]] + v * def_colors[idx[2]]
        albedo = wp.cw_mul(albedo, vc)
    lambert = wp.max(-wp.dot(n, d) / wp.sqrt(wp.dot(n, n) * wp.dot(d, d) + 1.0e-30), 0.0)
    store_color(env, y, x, albedo * (ambient + diffuse * lambert), write_rgb, frame_rgb, rgb_out, frame_out)
    vbuf[env, y, x] = EMPTY_KEY


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
    """Vertex ``s`` of the ring of ``sides`` vertices (and analytic radial normals) around node ``i`` of a polyline,
    a thread per ring vertex (launch ``(num_envs, nodes * sides)``): neighbouring threads write neighbouring vertices
    (a thread per node writing its whole ring wrote ``sides`` vertices apart across a warp: RopeThreading RGB, 4,096
    envs, 0.27 ms per frame, H200). With caps, two extra centre vertices close the ends (written by the first and last
    ring's vertex 0). The ring frame is Frisvad's orthonormal basis of the local tangent: no sequential frame
    propagation, continuous except for tangents close to -Z."""
    env, v = wp.tid()
    i = v / sides
    s = v - i * sides
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
    ang = 2.0 * wp.pi * float(s) / float(sides)
    radial = wp.cos(ang) * b1 + wp.sin(ang) * b2
    points_out[env, vert_begin + v] = p + radius * radial
    normals_out[env, vert_begin + v] = radial
    if caps != 0 and s == 0:
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
