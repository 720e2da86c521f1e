"""Kernels of the BVH ray-cast visibility pass: the baseline the rasteriser is measured against.

It fills the same visibility buffer as ``raster.py`` (packed ``depth bits << 32 | triangle id`` keys), so
both back-ends share ``raster.shade_visibility`` and produce identical output layouts; only the visibility
pass differs. Acceleration structures (built by ``lapwarp/render.py``):

* rigid meshes: one ``wp.Mesh`` per mesh in its local frame, shared by all envs; each pixel ray is moved
  into every instance's local frame with that env's view matrix (no per-env copies, no refit); instances
  culled by the shared ``raster.prepare_views`` pass (hidden, outside the frustum) are skipped;
* deformable surfaces: one grouped ``wp.Mesh`` over all envs' deformable triangles (group = env, env-major
  face order) built on the renderer's deformable vertex buffer and refit once per frame, so that every
  ray only traverses its own env's subtree.

Rays start at the near plane and use a direction whose view-space z component is -1, so the hit distance
``t`` is directly the depth along the view axis (rigid transforms preserve lengths).
"""

import warp as wp

from lapwarp.kernels.raster import EMPTY_KEY, FLAG_DOUBLE_SIDED, inverse_rigid_point, inverse_rigid_vector, pack_key

wp.set_module_options({"enable_backward": False})

# Rejected hits (back faces of single-sided objects, cut triangles) are stepped over at most this many
# times per ray and object group before the ray gives up on that group.
MAX_RECASTS = wp.constant(8)


@wp.kernel
def raycast_visibility(
    inst_mesh: wp.array(dtype=wp.uint64),
    inst_obj: wp.array(dtype=wp.int32),
    inst_tri_begin: wp.array(dtype=wp.int32),
    inst_draw: wp.array2d(dtype=wp.int32),
    def_mesh: wp.uint64,
    def_tris_per_env: int,
    def_tri_begin: int,
    def_active: wp.array2d(dtype=wp.int32),
    tri_obj: wp.array(dtype=wp.int32),
    obj_flags: wp.array(dtype=wp.int32),
    obj_visible: wp.array2d(dtype=wp.int32),
    views: wp.array2d(dtype=wp.mat44),
    focal: float,
    cx: float,
    cy: float,
    near: float,
    far: float,
    vbuf_out: wp.array3d(dtype=wp.uint64),
):
    """One thread per (env, row, col): closest hit over all rigid instances and the env's deformables.

    ``views``/``inst_draw`` come from ``raster.prepare_views`` (shared with the rasteriser): instances that
    are hidden or outside the frustum are skipped, like the rasteriser skips them."""
    env, y, x = wp.tid()
    d = wp.vec3((float(x) + 0.5 - cx) / focal, -(float(y) + 0.5 - cy) / focal, -1.0)
    best = far
    best_tri = int(-1)
    for i in range(inst_mesh.shape[0]):
        if inst_draw[env, i] == 0:
            continue
        obj = inst_obj[i]
        view = views[env, i]
        dl = inverse_rigid_vector(view, d)
        t0 = near
        cull = (obj_flags[obj] & FLAG_DOUBLE_SIDED) == 0
        for _k in range(MAX_RECASTS):
            o = inverse_rigid_point(view, t0 * d)
            q = wp.mesh_query_ray(inst_mesh[i], o, dl, best - t0)
            if not q.result:
                break
            if cull and q.sign < 0.0:
                t0 = t0 + q.t * 1.0001 + 1.0e-7
                continue
            best = t0 + q.t
            best_tri = inst_tri_begin[i] + q.face
            break
    if def_tris_per_env > 0:
        root = wp.mesh_get_group_root(def_mesh, env)
        view = views[env, views.shape[1] - 1]
        dw = inverse_rigid_vector(view, d)
        t0 = near
        for _k in range(MAX_RECASTS):
            o = inverse_rigid_point(view, t0 * d)
            q = wp.mesh_query_ray(def_mesh, o, dw, best - t0, root)
            if not q.result:
                break
            local = q.face - env * def_tris_per_env
            tri = def_tri_begin + local
            obj = tri_obj[tri]
            keep = obj_visible[env, obj] != 0 and def_active[env % def_active.shape[0], local] != 0
            if keep and (obj_flags[obj] & FLAG_DOUBLE_SIDED) == 0 and q.sign < 0.0:
                keep = False
            if not keep:
                t0 = t0 + q.t * 1.0001 + 1.0e-7
                continue
            best = t0 + q.t
            best_tri = tri
            break
    if best_tri >= 0:
        vbuf_out[env, y, x] = pack_key(best, best_tri)
    else:
        vbuf_out[env, y, x] = EMPTY_KEY


@wp.kernel
def copy_active_mask(src: wp.array2d(dtype=wp.int32), offset: int, dst: wp.array2d(dtype=wp.int32)):
    env, f = wp.tid()
    dst[env, offset + f] = src[env % src.shape[0], f]


@wp.kernel
def copy_active_mask_u8(src: wp.array2d(dtype=wp.uint8), offset: int, dst: wp.array2d(dtype=wp.int32)):
    env, f = wp.tid()
    dst[env, offset + f] = wp.int32(src[env % src.shape[0], f])
