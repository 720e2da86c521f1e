"""Physics-only throughput of the XPBD core: env-steps/s for a batch of cloths, tet blocks or rods.

One env step is 0.1 s of simulated time (LapGym's 10 Hz control) split into ``--substeps`` XPBD
substeps with ``--iterations`` sweeps each. On CUDA one env step is captured as a CUDA graph and
replayed; timings use ``wp.synchronize_device``. Every figure is reported with the substeps,
iterations and solution quality (stretch = max edge length / rest length after the hang settles).

Scenes (SI units):

* ``cloth``: 40 x 40 vertices, 75 mm (PrecisionCutting's grid: 1,600 vertices, 3,042 triangles),
  hanging from its pinned top edge, 0.2 kg/m^2, stretch stiffness 1e3 N/m, bending 1e-6 N m, tethers.
* ``tet``: 40 x 40 x 20 mm tissue block, 7 x 6 x 4 cells -> 1,008 tets, E = 3 kPa, nu = 0.45,
  clamped base, sagging under gravity.
* ``rod``: 100 segments, 200 mm, r = 1 mm, E = 1e6 Pa, pinned at the top, released 30 degrees from the
  vertical and swinging into its hang (stretch solved exactly per rod, see kernels/rods.py; elastic strain
  at the top 0.2 %, so ``stretch`` ~1.002 is the physical value).

Rod sweep on the GPU::

    python benchmarks/bench_physics.py --device cuda:0 --scene rod --num-envs 1024 4096 16384 --substeps 10 20 \\
        --out benchmarks/physics_rod.json

Examples::

    python benchmarks/bench_physics.py --device cuda:0 --num-envs 1024 4096 16384 --scene all \\
        --out benchmarks/physics.json
    python benchmarks/bench_physics.py --device cpu --num-envs 2 --steps 2 --settle-steps 2   # smoke test
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np
import warp as wp

from lapwarp.assets import box_tets, cloth_grid
from lapwarp.builder import SceneBuilder

DT = 0.1  # simulated seconds per env step


def build_cloth(num_envs: int, device: str, substeps: int, iterations: int):
    b = SceneBuilder()
    v, t = cloth_grid(40, 40, 0.075, 0.075, plane="xz", origin=(0.0, 0.0, -0.075))
    top = np.nonzero(v[:, 2] > -1e-9)[0]
    obj = b.add_cloth(v, t, areal_density=0.2, stretch_stiffness=1e3, bend_stiffness=1e-6, damping=1.0, fixed=top)
    # a small sideways tilt so the cloth swings into its hang instead of starting exactly at rest
    world = b.finalize(num_envs, device, substeps=substeps, iterations=iterations)
    q = world.state.particle_q.numpy()
    q[..., 1] += 0.2 * (-q[..., 2])  # lean the sheet out of its vertical plane
    world.state.particle_q.assign(q)
    world.save_start_state()
    return world, obj, v, obj.edges - obj.particle_start


def build_tet(num_envs: int, device: str, substeps: int, iterations: int):
    b = SceneBuilder()
    v, t = box_tets((0.04, 0.04, 0.02), (7, 6, 4))
    obj = b.add_tet_mesh(v, t, density=1000.0, youngs_modulus=3e3, poisson_ratio=0.45, damping=1.0,
                         fixed=np.nonzero(v[:, 2] < 1e-9)[0])
    world = b.finalize(num_envs, device, substeps=substeps, iterations=iterations)
    e = np.unique(np.sort(np.concatenate([t[:, [a, c]] for a in range(4) for c in range(a + 1, 4)]), axis=1), axis=0)
    return world, obj, v, e


def build_rod(num_envs: int, device: str, substeps: int, iterations: int):
    b = SceneBuilder()
    n = 101
    # pinned at the top, starting 30 degrees from the vertical so it swings into its hang
    s = np.linspace(0.0, 0.2, n)
    pts = np.stack([s * np.sin(np.radians(30.0)), np.zeros(n), -s * np.cos(np.radians(30.0))], axis=1)
    obj = b.add_rod(pts, radius=0.001, density=1000.0, youngs_modulus=1e6, damping=1.0, fixed=[0])
    world = b.finalize(num_envs, device, substeps=substeps, iterations=iterations)
    return world, obj, pts, obj.edges - obj.particle_start


SCENES = {"cloth": build_cloth, "tet": build_tet, "rod": build_rod}
SIZES = {"cloth": "40x40 grid, 1,600 vertices, 3,042 tris", "tet": "1,008 tets, 280 nodes",
         "rod": "100 segments, 101 nodes"}


def stretch_of(world, obj, rest_pos, edges) -> float:
    q = world.positions(obj)
    rest = np.linalg.norm(rest_pos[edges[:, 0]] - rest_pos[edges[:, 1]], axis=1)
    cur = np.linalg.norm(q[:, edges[:, 0]] - q[:, edges[:, 1]], axis=2)
    return float(np.nanmax(cur / rest))


def run(scene: str, num_envs: int, device: str, substeps: int, iterations: int, steps: int, settle: int) -> dict:
    wp.synchronize_device(device)
    world, obj, rest_pos, edges = SCENES[scene](num_envs, device, substeps, iterations)
    dev = wp.get_device(device)
    # settle the hang (also compiles kernels and records the launches of a step)
    for _ in range(max(1, settle)):
        world.step(DT)
    wp.synchronize_device(device)
    graph = None
    if dev.is_cuda:
        with wp.ScopedCapture(device=dev) as cap:
            world.step(DT)
        graph = cap.graph
        wp.capture_launch(graph)  # warm
    wp.synchronize_device(device)
    t0 = time.perf_counter()
    for _ in range(steps):
        if graph is not None:
            wp.capture_launch(graph)
        else:
            world.step(DT)
    wp.synchronize_device(device)
    elapsed = time.perf_counter() - t0
    m = world.model
    launches = 2 + (len(m.edge_color_offsets) - 1) + (len(m.hinge_color_offsets) - 1) + (len(m.tet_color_offsets) - 1)
    launches += (len(m.segment_color_offsets) - 1) + (len(m.bend_color_offsets) - 1) + (1 if m.tether_count else 0)
    launches += 2 if m.segment_count else 0
    launches += 1 if m.rod_count else 0  # direct rod stretch solve, one thread per (env, rod)
    rec = {
        "scene": scene,
        "size": SIZES[scene],
        "device": dev.name if dev.is_cuda else "cpu",
        "num_envs": num_envs,
        "sim_seconds_per_env_step": DT,
        "substeps": world.substeps,
        "iterations": world.iterations,
        "kernel_launches_per_substep": launches,
        "cuda_graph": graph is not None,
        "steps_timed": steps,
        "seconds": elapsed,
        "env_steps_per_s": num_envs * steps / elapsed,
        "stretch_max": stretch_of(world, obj, rest_pos, edges),
        "unstable_envs": int(world.unstable.numpy().sum()),
        "state_bytes_per_env": world.state_bytes_per_env(),
        "colors": {"edges": len(m.edge_color_offsets) - 1, "hinges": len(m.hinge_color_offsets) - 1,
                   "tets": len(m.tet_color_offsets) - 1, "segments": len(m.segment_color_offsets) - 1,
                   "bends": len(m.bend_color_offsets) - 1},
    }
    del world
    return rec


def fits_16k_cloth(device: str, substeps: int, iterations: int) -> dict:
    """Allocate 16,384 cloth envs and run one step; report success and the device memory used."""
    try:
        free0 = wp.get_device(device).free_memory if wp.get_device(device).is_cuda else None
        world, *_ = build_cloth(16384, device, substeps, iterations)
        world.step(DT)
        wp.synchronize_device(device)
        free1 = wp.get_device(device).free_memory if wp.get_device(device).is_cuda else None
        used = None if free0 is None else int(free0 - free1)
        return {"cloth_16k_envs_fit": True, "device_bytes_used": used,
                "state_bytes_per_env": world.state_bytes_per_env()}
    except Exception as exc:  # report, do not crash the benchmark
        return {"cloth_16k_envs_fit": False, "error": repr(exc)}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--device", default="cuda:0")
    p.add_argument("--num-envs", type=int, nargs="+", default=[1024, 4096])
    p.add_argument("--scene", choices=["cloth", "tet", "rod", "all"], default="all")
    p.add_argument("--substeps", type=int, nargs="+", default=[20], help="one run per value")
    p.add_argument("--iterations", type=int, default=1)
    p.add_argument("--steps", type=int, default=50, help="timed env steps")
    p.add_argument("--settle-steps", type=int, default=30, help="untimed env steps before timing (hang settles)")
    p.add_argument("--check-16k", action="store_true", help="also check that 16,384 cloth envs allocate and step")
    p.add_argument("--out", default=None, help="write the results as JSON here")
    args = p.parse_args()

    wp.config.log_level = max(wp.config.log_level, wp.LOG_WARNING)  # no per-module load lines
    wp.init()
    scenes = ["cloth", "tet", "rod"] if args.scene == "all" else [args.scene]
    results = []
    for scene in scenes:
        for sub, n in [(sub, n) for sub in args.substeps for n in args.num_envs]:
            rec = run(scene, n, args.device, sub, args.iterations, args.steps, args.settle_steps)
            results.append(rec)
            print(f"{scene:5s} envs={n:6d} substeps={rec['substeps']} iters={rec['iterations']} "
                  f"{rec['env_steps_per_s']:12.1f} env-steps/s  stretch={rec['stretch_max']:.4f}  "
                  f"state={rec['state_bytes_per_env']} B/env  unstable={rec['unstable_envs']}", flush=True)
    out = {"results": results}
    if args.check_16k:
        out["cloth_16k"] = fits_16k_cloth(args.device, args.substeps[0], args.iterations)
        print("cloth 16k:", out["cloth_16k"], flush=True)
    if args.out:
        with open(args.out, "w") as f:
            json.dump(out, f, indent=2)


if __name__ == "__main__":
    main()
