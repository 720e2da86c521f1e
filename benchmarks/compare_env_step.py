"""Env-step speed of this checkout against another lapwarp source tree, in one process, interleaved.

    python benchmarks/compare_env_step.py --other /path/to/old/checkout --tasks Reach DeflectSpheres SearchForPoint \\
        --num-envs 4096 --out compare.json

The other tree's ``lapwarp`` package is copied to a temporary folder as ``lapwarp_other`` (its imports rewritten),
so both versions run side by side in the same process, on the same GPU, under the same host load. For each task
both envs are built and warmed, then timed in alternating blocks (old, new, old, new, ...):

* ``step``: the whole ``env.step`` as rsl-rl calls it (host work, CUDA-graph replay, output clones and log tensors),
  wall time per step with a device sync at the end of each block;
* ``graph``: only the captured step graph replayed back to back, timed with CUDA events (the device work alone).

The median over blocks is reported per version, with the ratio new / old. Random actions come from a pre-drawn pool.
"""

from __future__ import annotations

import argparse
import importlib
import json
import os
import re
import shutil
import statistics
import sys
import tempfile
import time

import torch
import warp as wp

import lapwarp


def import_other(root: str):
    """Import ``root/lapwarp`` as ``lapwarp_other`` (every ``lapwarp`` module reference rewritten)."""
    tmp = tempfile.mkdtemp(prefix="lapwarp_other_")
    dst = os.path.join(tmp, "lapwarp_other")
    shutil.copytree(os.path.join(root, "lapwarp"), dst)
    word = re.compile(r"\blapwarp\b(?!_)")
    for folder, _, files in os.walk(dst):
        for name in files:
            if name.endswith(".py"):
                path = os.path.join(folder, name)
                with open(path) as f:
                    text = f.read()
                with open(path, "w") as f:
                    f.write(word.sub("lapwarp_other", text))
    sys.path.insert(0, tmp)
    return importlib.import_module("lapwarp_other")


def time_block(env, pool, steps: int, graph_only: bool) -> float:
    dev = torch.device(env.device)
    if graph_only:
        stream = env._torch_stream()
        start, end = torch.cuda.Event(enable_timing=True), torch.cuda.Event(enable_timing=True)
        start.record()
        for _ in range(steps):
            wp.capture_launch(env._graph, stream=stream)
        end.record()
        torch.cuda.synchronize(dev)
        return start.elapsed_time(end) * 1e-3 / steps
    torch.cuda.synchronize(dev)
    t0 = time.perf_counter()
    for i in range(steps):
        env.step(pool[i % len(pool)])
    torch.cuda.synchronize(dev)
    return (time.perf_counter() - t0) / steps


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--other", required=True, help="root of the other checkout (holds lapwarp/)")
    p.add_argument("--tasks", nargs="+", default=["Reach", "DeflectSpheres", "SearchForPoint"])
    p.add_argument("--num-envs", type=int, default=4096)
    p.add_argument("--obs", default="STATE")
    p.add_argument("--blocks", type=int, default=12)
    p.add_argument("--steps", type=int, default=200, help="steps per timed block")
    p.add_argument("--device", default="cuda:0")
    p.add_argument("--out", default=None)
    args = p.parse_args()
    wp.config.log_level = max(wp.config.log_level, wp.LOG_WARNING)
    other = import_other(args.other)
    results = []
    for task in args.tasks:
        overrides = dict(invalid_actions="zero", observation_type=args.obs)
        envs = {"old": other.make(task, num_envs=args.num_envs, device=args.device, **overrides),
                "new": lapwarp.make(task, num_envs=args.num_envs, device=args.device, **overrides)}
        gen = torch.Generator(device=args.device).manual_seed(0)
        pool = [torch.rand(args.num_envs, envs["new"].num_actions, device=args.device, generator=gen) * 2 - 1
                for _ in range(8)]
        for env in envs.values():
            for i in range(20):
                env.step(pool[i % 8])
        times = {(v, m): [] for v in envs for m in ("step", "graph")}
        for _ in range(args.blocks):
            for version, env in envs.items():
                for mode in ("step", "graph"):
                    times[(version, mode)].append(time_block(env, pool, args.steps, mode == "graph"))
        rec = {"task": task, "num_envs": args.num_envs, "obs": args.obs, "device": torch.cuda.get_device_name(),
               "blocks": args.blocks, "steps_per_block": args.steps}
        for mode in ("step", "graph"):
            old, new = (statistics.median(times[(v, mode)]) for v in ("old", "new"))
            rec[f"{mode}_ms_old"], rec[f"{mode}_ms_new"] = old * 1e3, new * 1e3
            rec[f"{mode}_env_steps_per_s_old"], rec[f"{mode}_env_steps_per_s_new"] = (args.num_envs / old,
                                                                                        args.num_envs / new)
            rec[f"{mode}_new_over_old_speed"] = old / new
        results.append(rec)
        print(json.dumps(rec), flush=True)
        for env in envs.values():
            env.close()
    if args.out:
        with open(args.out, "w") as f:
            json.dump({"benchmark": "compare_env_step", "results": results}, f, indent=2)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
