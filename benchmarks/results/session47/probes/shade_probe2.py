"""Probe (forty-seventh session, second): the shading pass with its visibility-buffer clear last (the new default),
first (the old order), left out (then a fill launch clears the buffer). ThreadInHole / RopeThreading RGB, 4,096 envs,
CUDA events on replayed render launches."""
import json
import sys
import time

import numpy as np
import torch
import warp as wp

import lapwarp
from lapwarp import launching
from lapwarp.kernels import raster as R
from lapwarp.kernels.raster import (
    EMPTY_KEY,
    FLAG_SMOOTH,
    FLAG_VERTEX_COLORS,
    KIND_RIGID,
    inverse_rigid_point,
    inverse_rigid_vector,
    key_depth,
    key_triangle,
    store_color,
)


def shade_clear_first(
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
    vbuf[env, y, x] = EMPTY_KEY
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




def shade_no_clear(
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




VARIANTS = {
    "clear_last": R.shade_visibility,
    "clear_first": wp.kernel(shade_clear_first, module="unique", enable_backward=False, cuda_max_registers=48),
    "no_clear": wp.kernel(shade_no_clear, module="unique", enable_backward=False, cuda_max_registers=48),
}
FILL = wp.uint64(0xFFFFFFFFFFFFFFFF)


def main():
    task, n, out = sys.argv[1], int(sys.argv[2]), sys.argv[3]
    env = lapwarp.make(task, num_envs=n, device="cuda:0", observation_type="RGB", use_cuda_graph=False)
    env.reset()
    zero = torch.zeros((n, env.num_actions), device=env.device)
    for _ in range(5):
        env.step(zero)
    wp.synchronize()
    rec = []
    orig = launching.launch

    def spy(kernel, dim, inputs=(), outputs=(), device=None, block_dim=None, **kw):
        rec.append((kernel, dim, list(inputs), list(outputs), device, block_dim, kw))
        return orig(kernel, dim, inputs=inputs, outputs=outputs, device=device, block_dim=block_dim, **kw)

    import lapwarp.render as render_mod
    render_mod.launching.launch = spy
    env.step(zero)
    render_mod.launching.launch = orig
    wp.synchronize()
    names = [r[0].key for r in rec]
    print("render launches:", names)
    i_shade = next(i for i, r in enumerate(rec) if r[0] is R.shade_visibility)
    first = i_shade
    while first > 0 and hasattr(R, rec[first - 1][0].key):
        first -= 1  # the render pass: the raster module's launches just before the shading
    pre = rec[first:i_shade]
    print("replayed:", [r[0].key for r in pre])
    shade = rec[i_shade]
    results = {"task": task, "num_envs": n, "launches": names, "shade_dim": list(shade[1])}

    def replay(items):
        for kernel, dim, inputs, outputs, device, block_dim, kw in items:
            orig(kernel, dim, inputs=inputs, outputs=outputs, device=device, block_dim=block_dim, **kw)

    def timed(kernel, block_dim=None, reps=30, fill=False):
        ev = [(wp.Event(enable_timing=True), wp.Event(enable_timing=True)) for _ in range(reps)]
        _, dim, inputs, outputs, device, bd, kw = shade
        vbuf = inputs[-1]
        for k in range(reps + 3):
            replay(pre)
            if k >= 3:
                wp.record_event(ev[k - 3][0])
            wp.launch(kernel, dim=dim, inputs=inputs, outputs=outputs, device=device,
                      block_dim=block_dim or bd or 256)
            if fill:
                vbuf.fill_(FILL)
            if k >= 3:
                wp.record_event(ev[k - 3][1])
        wp.synchronize()
        t = [wp.get_event_elapsed_time(a, b) for a, b in ev]
        return float(np.median(t))

    # each pre launch alone
    per = {}
    for item in pre:
        kernel, dim, inputs, outputs, device, block_dim, kw = item
        ev = [(wp.Event(enable_timing=True), wp.Event(enable_timing=True)) for _ in range(10)]
        for k in range(10):
            replay(pre)
            wp.launch(R.shade_visibility, dim=shade[1], inputs=shade[2], outputs=shade[3], device=shade[4],
                      block_dim=shade[5] or 256)
            wp.record_event(ev[k][0])
            orig(kernel, dim, inputs=inputs, outputs=outputs, device=device, block_dim=block_dim, **kw)
            wp.record_event(ev[k][1])
        wp.synchronize()
        per.setdefault(kernel.key, []).append(float(np.median([wp.get_event_elapsed_time(a, b) for a, b in ev])))
    results["pre_ms"] = per
    print("pre launches (ms):", json.dumps(per))
    shade_ms = {}
    for _round in range(2):
        for name, kernel in VARIANTS.items():
            shade_ms.setdefault(name, []).append(timed(kernel))
        shade_ms.setdefault("no_clear_fill", []).append(timed(VARIANTS["no_clear"], fill=True))
        shade_ms.setdefault("clear_last_block128", []).append(timed(R.shade_visibility, block_dim=128))
    results["shade_ms"] = shade_ms
    for k, v in shade_ms.items():
        print(f"{k:20s} {v}")
    # output shapes/strides
    results["outputs"] = [(getattr(a, "shape", None), getattr(a, "strides", None), str(getattr(a, "dtype", "")))
                          for a in shade[3]]
    print("outputs", results["outputs"])
    with open(out, "w") as f:
        json.dump(results, f, indent=1)


if __name__ == "__main__":
    t0 = time.time()
    main()
    print(f"done in {time.time() - t0:.1f} s")
