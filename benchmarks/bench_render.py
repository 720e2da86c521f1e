"""Frames/s of the batched rasteriser (lapwarp.render) against the Warp BVH ray caster on the same scenes.

Scenes (every env has its own camera and its own object poses / cloth shape):

* ``rigid``: Reach-like. An icosphere of 5,120 triangles (``trimesh`` subdivisions=4; sofa_env's unit_sphere
  has 4,450), radius ``--sphere-radius`` (default 20 mm, the largest zoo setting), a capsule "instrument" of
  1,728 triangles (8 mm x 12 cm) and a 1 m ground quad (2 large triangles behind everything). Camera near
  Reach's (0, 0.07, 0.55) m with per-env jitter, 42 degree vertical FoV; sphere and instrument poses random
  per env in Reach's workspace.
* ``cloth``: a 40 x 40 vertex cloth (1,600 vertices, 3,042 triangles, 30 cm) per env, displaced every frame
  by a travelling-wave kernel (per-env phase), double-sided with per-frame smooth normals, filling most of a
  45 degree view.

Each configuration renders RGB + depth + segmentation. The timed step is "update the scene on the device
(cloth wave kernel) + render"; on CUDA it is captured once in a CUDA graph (``wp.ScopedCapture``) and
replayed, with ``wp.synchronize_device`` around the timed loop; on CPU it runs eagerly. On CUDA one extra
eager step is profiled per configuration (``wp.timing_begin``) for a per-kernel breakdown.

Usage::

    python benchmarks/bench_render.py --device cuda:0 --num-envs 1024 4096 16384 --res 64 --variants \\
        --out benchmarks/results/render_h100.json
    python benchmarks/bench_render.py --device cpu --num-envs 2 --res 32   # smoke test
"""

from __future__ import annotations

import argparse
import json
import math
import platform
import sys
import time
from pathlib import Path

import numpy as np
import trimesh
import warp as wp

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from lapwarp.cli import non_negative_int, positive_int  # noqa: E402
from lapwarp.render import Renderer, cloth_grid_faces, look_at  # noqa: E402

wp.set_module_options({"enable_backward": False})

CLOTH_N = 40
CLOTH_SIZE = 0.3


@wp.kernel
def wave_cloth(
    rest: wp.array(dtype=wp.vec3),
    phase: wp.array(dtype=wp.float32),
    clock: wp.array(dtype=wp.float32),
    points_out: wp.array2d(dtype=wp.vec3),
):
    env, i = wp.tid()
    p = rest[i]
    t = clock[0]
    z = 0.03 * wp.sin(25.0 * p[0] + 3.0 * t + phase[env]) * wp.cos(15.0 * p[1] - 2.0 * t)
    points_out[env, i] = wp.vec3(p[0], p[1], p[2] + z)


@wp.kernel
def advance_clock(dt: float, clock: wp.array(dtype=wp.float32)):
    clock[0] = clock[0] + dt


def quat_axis_angle(axis: np.ndarray, angle: np.ndarray) -> np.ndarray:
    axis = axis / np.linalg.norm(axis, axis=-1, keepdims=True)
    return np.concatenate([axis * np.sin(angle / 2)[..., None], np.cos(angle / 2)[..., None]], -1)


def build_rigid(n: int, res: int, device, method: str, args, **kwargs):
    rng = np.random.default_rng(0)
    r = Renderer(
        n,
        res,
        res,
        fov=42.0,
        near=0.01,
        far=2.0,
        device=device,
        method=method,
        background_color=(0.05, 0.05, 0.08),
        **kwargs,
    )
    sphere = trimesh.creation.icosphere(subdivisions=4, radius=args.sphere_radius)
    capsule = trimesh.creation.capsule(height=0.12, radius=0.008, count=(48, 18))
    r.add_instance(r.add_mesh(sphere.vertices, sphere.faces, color=(0.8, 0.8, 0.8), seg_id=1))
    r.add_instance(r.add_mesh(capsule.vertices, capsule.faces, color=(0.3, 0.3, 0.35), seg_id=2))
    ground = np.array([[-0.5, -0.5, 0], [0.5, -0.5, 0], [0.5, 0.5, 0], [-0.5, 0.5, 0]], np.float32)
    split = None if args.quad_split is None else args.quad_split
    r.add_instance(r.add_mesh(ground, [[0, 1, 2], [0, 2, 3]], color=(0.4, 0.3, 0.3), seg_id=3, raster_split=split))
    r.finalize()
    eye = np.array([0.0, 0.07, 0.55]) + rng.uniform(-0.02, 0.02, (n, 3))
    cams = look_at(eye, np.zeros((n, 3)) + rng.uniform(-0.01, 0.01, (n, 3)))
    xf = np.zeros((n, 3, 7), np.float32)
    xf[:, 0, :3] = rng.uniform([-0.1, -0.04, -0.1], [0.1, 0.12, 0.1], (n, 3))
    xf[:, 0, 6] = 1.0
    xf[:, 1, :3] = rng.uniform([-0.1, -0.04, -0.1], [0.1, 0.12, 0.1], (n, 3))
    xf[:, 1, 3:] = quat_axis_angle(rng.normal(size=(n, 3)), rng.uniform(0, math.pi, n))
    xf[:, 2, :3] = [0.0, 0.0, -0.15]
    xf[:, 2, 6] = 1.0
    r.set_camera_poses(cams)
    r.set_instance_transforms(xf)

    def step():
        r.render()

    return r, step


def build_cloth(n: int, res: int, device, method: str, args, **kwargs):
    rng = np.random.default_rng(1)
    r = Renderer(
        n,
        res,
        res,
        fov=45.0,
        near=0.01,
        far=2.0,
        device=device,
        method=method,
        background_color=(0.05, 0.05, 0.08),
        **kwargs,
    )
    cloth = r.add_deformable(cloth_grid_faces(CLOTH_N, CLOTH_N), CLOTH_N * CLOTH_N, color=(0.85, 0.6, 0.55), seg_id=1)
    r.finalize()
    g = np.linspace(-CLOTH_SIZE / 2, CLOTH_SIZE / 2, CLOTH_N)
    x, y = np.meshgrid(g, g)
    rest = wp.array(np.stack([x, y, np.zeros_like(x)], -1).reshape(-1, 3), dtype=wp.vec3, device=device)
    phase = wp.array(rng.uniform(0, 2 * math.pi, n).astype(np.float32), device=device)
    clock = wp.zeros(1, dtype=wp.float32, device=device)
    eye = np.array([0.0, -0.12, 0.36]) + rng.uniform(-0.02, 0.02, (n, 3))
    r.set_camera_poses(look_at(eye, np.zeros((n, 3))))
    # Zero-copy path: the wave kernel writes straight into the renderer's deformable vertex buffer.
    points = r.deformable_points(cloth)

    def step():
        wp.launch(advance_clock, dim=1, inputs=[0.01], outputs=[clock], device=device)
        wp.launch(wave_cloth, dim=(n, CLOTH_N * CLOTH_N), inputs=[rest, phase, clock], outputs=[points], device=device)
        r.render()

    step()  # the ray caster builds its grouped BVH on the first render, from real vertices
    return r, step


SCENES = {"rigid": build_rigid, "cloth": build_cloth}


def kernel_breakdown(step, device) -> dict[str, float]:
    """Milliseconds per kernel of one eager step (CUDA only)."""
    wp.synchronize_device(device)
    wp.timing_begin(cuda_filter=wp.TIMING_KERNEL | wp.TIMING_KERNEL_BUILTIN)
    step()
    results = wp.timing_end()
    out: dict[str, float] = {}
    for res in results:
        out[res.name] = out.get(res.name, 0.0) + res.elapsed
    return {k: round(v, 4) for k, v in sorted(out.items(), key=lambda kv: -kv[1])}


def time_step(step, device, warmup: int, iters: int) -> tuple[float, bool]:
    """Seconds per step and whether a CUDA graph was replayed (falls back to eager launches, reported, if the
    capture fails)."""
    for _ in range(warmup):
        step()
    wp.synchronize_device(device)
    graph = None
    if device.is_cuda:
        try:
            with wp.ScopedCapture(device=device) as capture:
                step()
            graph = capture.graph
            wp.capture_launch(graph)
        except Exception as exc:
            print(f"  CUDA graph capture failed ({type(exc).__name__}: {exc}); timing eager launches")
            graph = None
    wp.synchronize_device(device)
    t0 = time.perf_counter()
    for _ in range(iters):
        if graph is not None:
            wp.capture_launch(graph)
        else:
            step()
    wp.synchronize_device(device)
    return (time.perf_counter() - t0) / iters, graph is not None


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--device", default=None, help="Warp device (default: cuda:0 if available, else cpu)")
    parser.add_argument("--num-envs", type=positive_int, nargs="+", default=[1024, 4096, 16384])
    parser.add_argument("--res", type=positive_int, default=64, help="square image resolution")
    parser.add_argument("--scenes", nargs="+", default=list(SCENES), choices=list(SCENES))
    parser.add_argument("--methods", nargs="+", default=["raster", "raycast"], choices=["raster", "raycast"])
    parser.add_argument(
        "--variants",
        action="store_true",
        help="also time rasteriser variants: early depth test; ground quad without row split",
    )
    parser.add_argument("--sphere-radius", type=float, default=0.02, help="rigid scene sphere radius (m)")
    parser.add_argument("--quad-split", type=int, default=None, help="raster_split of the ground quad (default auto)")
    parser.add_argument("--iters", type=positive_int, default=None, help="timed steps (default 50 on CUDA, 2 on CPU)")
    parser.add_argument("--warmup", type=non_negative_int, default=3)
    parser.add_argument("--out", type=Path, default=None, help="write results as JSON here")
    args = parser.parse_args()

    wp.config.log_level = max(wp.config.log_level, wp.LOG_WARNING)  # no per-module load lines
    wp.init()
    device = wp.get_device(args.device or ("cuda:0" if wp.is_cuda_available() else "cpu"))
    iters = args.iters or (50 if device.is_cuda else 2)

    configs = []
    for scene in args.scenes:
        for method in args.methods:
            configs.append((scene, method, "default", {}))
            if args.variants and method == "raster":
                configs.append((scene, method, "early_z", {"early_depth_test": True}))
                if scene == "rigid":
                    configs.append((scene, method, "quad_split_1", {"_quad_split": 1}))

    rows = []
    print(f"device: {device.name} ({device.alias}), resolution {args.res}x{args.res}, {iters} timed steps")
    print(f"{'scene':6s} {'method':8s} {'variant':13s} {'envs':>7s} {'ms/step':>9s} {'frames/s':>12s}")
    for n in args.num_envs:
        for scene, method, variant, opts in configs:
            opts = dict(opts)
            if "_quad_split" in opts:
                sub = argparse.Namespace(**{**vars(args), "quad_split": opts.pop("_quad_split")})
            else:
                sub = args
            try:
                renderer, step = SCENES[scene](n, args.res, device, method, sub, **opts)
                seconds, graphed = time_step(step, device, args.warmup, iters)
                breakdown = kernel_breakdown(step, device) if device.is_cuda else {}
            except Exception as exc:  # keep going: report the failure (e.g. out of memory) in the table
                print(f"{scene:6s} {method:8s} {variant:13s} {n:7d}   failed: {type(exc).__name__}: {exc}")
                rows.append(
                    {
                        "scene": scene,
                        "method": method,
                        "variant": variant,
                        "num_envs": n,
                        "error": f"{type(exc).__name__}: {exc}",
                    }
                )
                continue
            fps = n / seconds
            print(f"{scene:6s} {method:8s} {variant:13s} {n:7d} {seconds * 1e3:9.3f} {fps:12,.0f}")
            rows.append(
                {
                    "scene": scene,
                    "method": method,
                    "variant": variant,
                    "num_envs": n,
                    "triangles_per_env": renderer.num_triangles,
                    "ms_per_step": seconds * 1e3,
                    "frames_per_s": fps,
                    "cuda_graph": graphed,
                    "kernel_ms": breakdown,
                }
            )
            del renderer, step
            wp.synchronize_device(device)

    # Speed-up of the default rasteriser over the ray caster per (scene, num_envs).
    fps = {(r["scene"], r["method"], r["variant"], r["num_envs"]): r.get("frames_per_s") for r in rows}
    for (scene, method, variant, n), v in fps.items():
        rc = fps.get((scene, "raycast", "default", n))
        if method == "raster" and variant == "default" and v and rc:
            print(f"{scene}: {n} envs: rasteriser {v / rc:.2f}x the ray caster")

    result = {
        "benchmark": "bench_render",
        "device": device.alias,
        "device_name": device.name,
        "platform": platform.platform(),
        "warp": wp.__version__,
        "resolution": [args.res, args.res],
        "outputs": ["rgb", "depth", "segmentation"],
        "iters": iters,
        "cuda_graph": device.is_cuda,
        "sphere_radius_m": args.sphere_radius,
        "results": rows,
    }
    if args.out:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(json.dumps(result, indent=2))
        print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
