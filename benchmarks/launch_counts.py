"""Device operations per env step by task: kernel launches, memsets and copies, i.e. the nodes of the CUDA graph an env
captures per step (each costs a launch gap however small its kernel). Counted on any device, the CPU included, by
wrapping ``wp.launch``, ``wp.copy`` and ``wp.array.zero_`` while the scripted expert steps; a count, never a speed.

    python benchmarks/launch_counts.py --tasks TissueDissection RopeCutting --out counts.json

Kernel names are reported per env step too (``--by-kernel``). Launches made inside Warp's own utilities (e.g. the
contact grid's scan) are not seen.
"""

from __future__ import annotations

import argparse
import collections
import json

import warp as wp

import lapwarp
from lapwarp.cli import positive_int
from lapwarp.experts import make_expert


def count_step_ops(task: str, num_envs: int, steps: int, warmup: int) -> dict:
    """Device operations per env step of ``task`` on the CPU with its expert acting (after ``warmup`` steps)."""
    env = lapwarp.make(task, num_envs=num_envs, device="cpu")
    expert = make_expert(env)
    for _ in range(warmup):
        env.step(expert())
    counts: collections.Counter = collections.Counter()
    launch, copy, zero = wp.launch, wp.copy, wp.array.zero_

    def counted_launch(kernel, *args, **kwargs):
        counts[f"kernel {getattr(kernel, 'key', kernel)}"] += 1
        return launch(kernel, *args, **kwargs)

    def counted_copy(*args, **kwargs):
        counts["copy"] += 1
        return copy(*args, **kwargs)

    def counted_zero(self, *args, **kwargs):
        counts["memset"] += 1
        return zero(self, *args, **kwargs)

    def counted_replay(cmd):
        # the World replays its step's launches as recorded ``wp.Launch`` objects, which bypass ``wp.launch``
        rec = getattr(cmd, "__self__", None)
        if not isinstance(rec, wp.Launch):
            return cmd

        def replay():
            counts[f"kernel {rec.kernel.key}"] += 1
            return cmd()
        return replay

    world = env.world
    world._cmds = [counted_replay(cmd) for cmd in world._cmds]
    recorded_key = world._cmd_key
    wp.launch, wp.copy, wp.array.zero_ = counted_launch, counted_copy, counted_zero
    try:
        for _ in range(steps):
            env.step(expert())
    finally:
        wp.launch, wp.copy, wp.array.zero_ = launch, copy, zero
    if world._cmd_key != recorded_key:
        raise RuntimeError(f"{task}: the World recorded its step again while counting; raise --warmup")
    env.close()
    per_step = {name: n / steps for name, n in counts.most_common()}
    kernels = sum(n for name, n in per_step.items() if name.startswith("kernel "))
    return {"task": task, "num_envs": num_envs, "steps": steps, "ops_per_step": sum(per_step.values()),
            "kernels_per_step": kernels, "by_name": per_step}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--tasks", nargs="+", default=lapwarp.list_tasks(), choices=lapwarp.list_tasks())
    parser.add_argument("--num-envs", type=positive_int, default=2)
    parser.add_argument("--steps", type=positive_int, default=3)
    parser.add_argument("--warmup", type=positive_int, default=2)
    parser.add_argument("--by-kernel", action="store_true", help="print the counts by name too")
    parser.add_argument("--out", default=None, help="JSON output path")
    args = parser.parse_args(argv)
    wp.config.log_level = max(wp.config.log_level, wp.LOG_WARNING)
    rows = []
    for task in args.tasks:
        r = count_step_ops(task, args.num_envs, args.steps, args.warmup)
        rows.append(r)
        print(f"{task:<20} {r['ops_per_step']:8.1f} device operations per env step "
              f"({r['kernels_per_step']:.1f} kernels)", flush=True)
        if args.by_kernel:
            for name, n in r["by_name"].items():
                print(f"    {n:7.1f}  {name}")
    if args.out:
        with open(args.out, "w") as f:
            json.dump({"benchmark": "launch_counts", "device": "cpu", "results": rows}, f, indent=2)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
