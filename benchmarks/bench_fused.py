"""Fused sweeps against the per-colour launches, side by side in one process (one JSON line per run).

    python benchmarks/bench_fused.py --device cuda:0 --num-envs 4096 --out fused.jsonl \\
        --tasks GraspLiftAndTouch TissueDissection --tet-threads 16 32 64 --triangle-threads 32 64

* Tets: ``world.tet_solver`` "colored" (one launch per colour) against "fused" at each ``--tet-threads`` (threads per
  env block), on the physics benchmark's 1,008-tet block (3 and 30 kPa, 20 substeps; physics only, CUDA graph) and on
  each given task with tets.
* Triangle contact: the contact system's ``triangle_sweep`` "colored" against "fused" at each ``--triangle-threads``,
  on each given task with triangle contact.

Tasks: the whole ``env.step``, random actions, default configuration; the other sweep at its default.

Env-steps/s are 4,096 env steps of 0.1 s simulated (physics) or one control step (tasks) per env. Only GPU figures are
speed claims; on the CPU a block has one lane and the runs only check that everything launches.
"""

from __future__ import annotations

import argparse
import json
import time

import torch
import warp as wp
from bench_physics import DT, SCENES, quality, timed_steps

import lapwarp


def physics_runs(args) -> list[dict]:
    runs = []
    for scene in ("tet", "tet_stiff"):
        for solver, threads in [("colored", 0)] + [("fused", t) for t in args.tet_threads]:
            world, obj, rest, _ = SCENES[scene](args.num_envs, args.device, 20, 1, "chains")
            world.tet_solver = solver
            if threads:
                world.tet_block_threads = threads
            for _ in range(3):  # compile, record the launches, settle the first contacts
                world.step(DT)
            rate = args.num_envs * args.steps / timed_steps(world, args.device, args.steps)
            runs.append({"scene": scene, "substeps": 20, "variant": solver, "threads": threads,
                         "env_steps_per_s": rate, **quality(scene, world, obj, rest)})
            del world
    return runs


def _triangle_colors(world) -> int:
    return sum(len(getattr(solver, "tri_color_offsets", [0])) - 1 for solver in world.solvers)


def task_run(task: str, variant: str, threads: int, args) -> dict:
    env = lapwarp.make(task, num_envs=args.num_envs, device=args.device, invalid_actions="zero")
    world = env.world
    kind, _, sweep = variant.partition("-")
    if kind == "tets":
        world.tet_solver = sweep
        if threads:
            world.tet_block_threads = threads
    else:
        for solver in world.solvers:
            if hasattr(solver, "triangle_sweep"):
                solver.triangle_sweep = sweep
                if threads:
                    solver.triangle_block_threads = threads
    gen = torch.Generator(device=env.device).manual_seed(0)
    if env.is_discrete:
        pool = [torch.randint(0, 2 * env.action_dim + 1, (args.num_envs,), device=env.device, generator=gen)
                for _ in range(8)]
    else:
        pool = [torch.rand(args.num_envs, env.num_actions, device=env.device, generator=gen) * 2 - 1 for _ in range(8)]
    for i in range(5):
        env.step(pool[i % 8])
    if str(env.device).startswith("cuda"):
        torch.cuda.synchronize(env.device)
    steps, start = 0, time.perf_counter()
    while time.perf_counter() - start < args.seconds:
        for _ in range(10):
            env.step(pool[steps % 8])
            steps += 1
        if str(env.device).startswith("cuda"):
            torch.cuda.synchronize(env.device)
    rate = args.num_envs * steps / (time.perf_counter() - start)
    m = world.model
    rec = {"task": task, "variant": variant, "threads": threads, "env_steps_per_s": rate, "tets": m.tet_count,
           "tet_colors": len(m.tet_color_offsets) - 1, "triangle_colors": _triangle_colors(world)}
    env.close()
    return rec


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--device", default="cuda:0")
    p.add_argument("--num-envs", type=int, default=4096)
    p.add_argument("--tasks", nargs="*", default=[], choices=lapwarp.list_tasks())
    p.add_argument("--triangle-threads", type=int, nargs="+", default=[32])
    p.add_argument("--tet-threads", type=int, nargs="+", default=[32])
    p.add_argument("--no-physics", action="store_true", help="only the tasks")
    p.add_argument("--steps", type=int, default=20, help="timed physics steps")
    p.add_argument("--seconds", type=float, default=2.0, help="timed seconds per task run")
    p.add_argument("--out", default=None, help="append one JSON line per run to this file")
    args = p.parse_args(argv)
    wp.config.log_level = max(wp.config.log_level, wp.LOG_WARNING)
    wp.init()
    device_name = wp.get_device(args.device).name if wp.get_device(args.device).is_cuda else "cpu"

    def emit(rec: dict) -> None:
        rec = {"device": device_name, "num_envs": args.num_envs, **rec}
        print(json.dumps(rec), flush=True)
        if args.out:
            with open(args.out, "a") as f:
                f.write(json.dumps(rec) + "\n")

    if not args.no_physics:
        for rec in physics_runs(args):
            emit(rec)
    for task in args.tasks:
        probe = lapwarp.make(task, num_envs=1, device="cpu")
        variants = []
        if probe.world.model.tet_count:
            variants += [("tets-colored", 0)] + [("tets-fused", t) for t in args.tet_threads]
        if _triangle_colors(probe.world):
            variants += [("triangles-colored", 0)] + [("triangles-fused", t) for t in args.triangle_threads]
        probe.close()
        for variant, threads in variants:
            emit(task_run(task, variant, threads, args))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
