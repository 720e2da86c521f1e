"""Kernels of the BVH ray-cast visibility pass: the baseline the rasteriser is measured against.

It fills the same visibility buffer as ``raster.py`` (packed ``depth bits << 32 | triangle id`` keys), so
both back-ends share ``raster.shade_visibility`` and produce identical output layouts; only the visibility
pass differs. Acceleration structures (built by ``lapwarp/render.py``):

* rigid meshes: one ``wp.Mesh`` per mesh in its local frame, shared by all envs; each pixel ray is moved
  into every instance's local frame with that env's instance transform (no per-env copies, no refit);
* deformable surfaces: one grouped ``wp.Mesh`` over all envs' deformable triangles (group = env, env-major
  face order) built on the renderer's deformable vertex buffer and refit once per frame, so that every
  ray only traverses its own env's subtree.

Rays start at the near plane and use a direction whose view-space z component is -1, so the hit distance
``t`` is directly the depth along the view axis (rigid transforms preserve lengths).
"""

import warp as wp

from lapwarp.kernels.raster import EMPTY_KEY, FLAG_DOUBLE_SIDED, pack_key

wp.set_module_options({"enable_backward": False})

# Rejected hits (back faces of single-sided objects, cut triangles) are stepped over at most this many
# times per ray and object group before the ray gives up on that group.
MAX_RECASTS = wp.constant(8)


@wp.kernel
def raycast_visibility(
    inst_mesh: wp.array(dtype=wp.uint64),
    inst_obj: wp.array(dtype=wp.int32),
    inst_tri_begin: wp.array(dtype=wp.int32),
    def_mesh: wp.uint64,
    def_tris_per_env: int,
    def_tri_begin: int,
    def_active: wp.array2d(dtype=wp.int32),
    tri_obj: wp.array(dtype=wp.int32),
    obj_flags: wp.array(dtype=wp.int32),
    obj_visible: wp.array2d(dtype=wp.int32),
    cam_xf: wp.array(dtype=wp.transform),
    inst_xf: wp.array2d(dtype=wp.transform),
    focal: float,
    cx: float,
    cy: float,
    near: float,
    far: float,
    vbuf_out: wp.array3d(dtype=wp.uint64),
):
    """One thread per (env, row, col): closest hit over all rigid instances and the env's deformables."""
    env, y, x = wp.tid()
    cam = cam_xf[env]
    d = wp.vec3((float(x) + 0.5 - cx) / focal, -(float(y) + 0.5 - cy) / focal, -1.0)
    best = far
    best_tri = int(-1)
    for i in range(inst_mesh.shape[0]):
        obj = inst_obj[i]
        if obj_visible[env, obj] == 0:
            continue
        to_local = wp.transform_multiply(wp.transform_inverse(inst_xf[env, i]), cam)
        dl = wp.transform_vector(to_local, d)
        t0 = near
        cull = (obj_flags[obj] & FLAG_DOUBLE_SIDED) == 0
        for _k in range(MAX_RECASTS):
            o = wp.transform_point(to_local, t0 * d)
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
        dw = wp.transform_vector(cam, d)
        t0 = near
        for _k in range(MAX_RECASTS):
            o = wp.transform_point(cam, t0 * d)
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
