"""Where an env step's device time goes: Warp kernel times summed by kernel name, written as JSON.

    python benchmarks/profile_step.py --task RopeCutting --num-envs 4096 --steps 5 --out profile.json

The env is built without CUDA-graph capture (graph replays are not broken down per kernel) and driven by the
scripted expert (``--policy random`` for random actions); after warm-up, ``--steps`` steps run under
``wp.ScopedTimer(cuda_filter=wp.TIMING_KERNEL)``. Reported per kernel: launches per env step and device
milliseconds per env step, sorted by time. The total is device kernel time only (no launch gaps, no torch ops), so
it is a lower bound of the graph-replayed step.

    python benchmarks/profile_step.py --task LigatingLoop --profiler torch --graph --out profile.json

``--profiler torch`` times the same steps with PyTorch's profiler instead (CUPTI, through Kineto): every kernel the
device runs, Warp's and the others (the BVH refits Warp runs in its native library, memsets, torch's operations), and
with ``--graph`` inside the env's replayed CUDA graph, so the total is the device time of the step as it runs. Rows
are grouped by kernel name (Warp's kernels keep their names); on the CPU the profiler sees no device work and only the
wall time is measured. It also reports where the device idles (``device_gaps``): per env step the span from the first
kernel's start to the last one's end, the busy part, and the longest gaps with the kernels on either side (what Warp's
timer cannot show: LigatingLoop's step ran 45.8 ms against 39.0 ms of device kernels, H200).

    python benchmarks/profile_step.py --diff touch.json centroid.json

compares two written profiles kernel by kernel (ms per env step and launches of each, the difference), largest
differences first: where the device time of one configuration goes that the other's does not.
"""

from __future__ import annotations

import argparse
import collections
import json
import time
from pathlib import Path

import torch
import warp as wp
from bench_env import apply_contact_settings

import lapwarp
from lapwarp.cli import parse_overrides, positive_int
from lapwarp.contact import ContactSystem
from lapwarp.experts import make_expert


def kernel_rows(timing_results, count: int) -> list[tuple[str, float, float]]:
    """``wp.ScopedTimer`` kernel records summed by kernel name: (name, launches per unit, ms per unit) over ``count``
    units (env steps, resets), the most time first."""
    per_kernel = collections.defaultdict(lambda: [0, 0.0])
    for r in timing_results:
        per_kernel[r.name][0] += 1
        per_kernel[r.name][1] += r.elapsed
    return sorted(((name, n / count, ms / count) for name, (n, ms) in per_kernel.items()), key=lambda row: -row[2])


def torch_kernel_rows(events, count: int) -> list[tuple[str, float, float]]:
    """PyTorch profiler events of device work (kernels, memcpys, memsets) summed by name, as ``kernel_rows``."""
    per_kernel = collections.defaultdict(lambda: [0, 0.0])
    for e in events:
        if e.device_type == torch.autograd.DeviceType.CUDA:
            per_kernel[e.name][0] += 1
            per_kernel[e.name][1] += e.time_range.elapsed_us() / 1e3
    return sorted(((name, n / count, ms / count) for name, (n, ms) in per_kernel.items()), key=lambda row: -row[2])


def device_gaps(intervals, count: int, top: int) -> dict:
    """Where the device idles between its work: ``intervals`` are ``(start_us, end_us, name)`` of every device event
    (any stream; overlapping ones merge), ``count`` the env steps they cover. Returns per env step the span from the
    first start to the last end, the busy time (the union of the intervals) and the idle rest (ms), and the ``top``
    longest idle gaps as ``(gap_us, name before, name after)``, longest first: a gap is device time that no kernel
    fills, e.g. the host launching the next work late or a graph's dependency gaps."""
    events = sorted(intervals)
    if not events:
        return {"span_ms_per_step": 0.0, "busy_ms_per_step": 0.0, "idle_ms_per_step": 0.0, "gaps": []}
    busy = 0.0
    gaps = []
    cur_start, cur_end, cur_name = events[0]
    for start, end, name in events[1:]:
        if start > cur_end:
            busy += cur_end - cur_start
            gaps.append((start - cur_end, cur_name, name))
            cur_start, cur_end, cur_name = start, end, name
        elif end > cur_end:
            cur_end, cur_name = end, name
    busy += cur_end - cur_start
    span = cur_end - events[0][0]
    gaps.sort(key=lambda g: -g[0])
    return {"span_ms_per_step": span / 1e3 / count, "busy_ms_per_step": busy / 1e3 / count,
            "idle_ms_per_step": (span - busy) / 1e3 / count, "gaps": gaps[:top]}


def diff_profiles(first: dict, second: dict, top: int) -> list[tuple[str, float, float, float, float]]:
    """Per kernel name of either profile: (name, ms per step in ``first``, in ``second``, launches per step in each),
    largest absolute difference in ms first; printed with the totals."""
    a = {k["name"]: k for k in first["kernels"]}
    b = {k["name"]: k for k in second["kernels"]}
    rows = [(name, a.get(name, {}).get("ms_per_step", 0.0), b.get(name, {}).get("ms_per_step", 0.0),
             a.get(name, {}).get("launches_per_step", 0.0), b.get(name, {}).get("launches_per_step", 0.0))
            for name in sorted(set(a) | set(b))]
    rows.sort(key=lambda row: -abs(row[1] - row[2]))
    print(f"kernel ms per env step: {first['kernel_ms_per_step']:.3f} (first) / {second['kernel_ms_per_step']:.3f} "
          f"(second), difference {first['kernel_ms_per_step'] - second['kernel_ms_per_step']:+.3f}")
    for name, ms_a, ms_b, n_a, n_b in rows[:top]:
        print(f"  {ms_a:8.3f} {ms_b:8.3f} {ms_a - ms_b:+8.3f} ms  {n_a:5.0f} / {n_b:5.0f} x  {name}")
    return rows


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--task", default="RopeCutting", choices=lapwarp.list_tasks())
    parser.add_argument("--device", default="cuda:0")
    parser.add_argument("--num-envs", type=positive_int, default=4096)
    parser.add_argument("--steps", type=positive_int, default=5)
    parser.add_argument("--policy", choices=["random", "expert"], default="expert")
    parser.add_argument("--set", nargs="*", default=[], metavar="KEY=VALUE", help="config overrides (JSON values)")
    parser.add_argument("--warmup", type=positive_int, default=3, help="untimed steps first (state develops)")
    parser.add_argument("--timing", choices=["kernel", "all"], default="kernel",
                        help="kernels only, or kernels, memcpys and memsets")
    parser.add_argument("--triangle-sweep", choices=ContactSystem.TRIANGLE_SWEEPS, default=None,
                        help="the contact system's triangle sweep (default: its own)")
    parser.add_argument("--profiler", choices=["warp", "torch"], default="warp",
                        help="Warp's kernel timer (its kernels only, no graph) or PyTorch's profiler (every device "
                             "kernel, also inside a replayed graph)")
    parser.add_argument("--graph", action="store_true",
                        help="with --profiler torch: replay the env's CUDA graph (Warp's timer sees no graph kernels)")
    parser.add_argument("--top", type=positive_int, default=25, help="kernels printed")
    parser.add_argument("--out", default=None)
    parser.add_argument("--diff", nargs=2, default=None, metavar=("FIRST", "SECOND"),
                        help="compare two profiles written with --out (nothing is run)")
    args = parser.parse_args(argv)
    if args.diff:
        try:
            first, second = (json.loads(Path(path).read_text()) for path in args.diff)
        except (OSError, ValueError) as exc:
            parser.error(f"--diff needs two profile JSON files: {exc}")
        if not all(isinstance(p, dict) and isinstance(p.get("kernels"), list) for p in (first, second)):
            parser.error("--diff needs two profile JSON files written by --out (with a 'kernels' list)")
        diff_profiles(first, second, args.top)
        return 0
    if args.graph and args.profiler != "torch":
        parser.error("--graph needs --profiler torch (Warp's kernel timer does not see into a replayed graph)")
    wp.config.log_level = max(wp.config.log_level, wp.LOG_WARNING)
    try:
        overrides = {"invalid_actions": "zero", **parse_overrides(args.set)}  # no host sync unless asked for
        lapwarp.check_config(args.task, **overrides)
    except ValueError as exc:
        parser.error(str(exc))
    env = lapwarp.make(args.task, num_envs=args.num_envs, device=args.device, use_cuda_graph=args.graph, **overrides)
    apply_contact_settings(env, triangle_sweep=args.triangle_sweep)
    if args.policy == "expert":
        expert = make_expert(env)
    else:
        gen = torch.Generator(device=env.device).manual_seed(0)

    def action():
        if args.policy == "expert":
            return expert()
        if env.is_discrete:
            return torch.randint(0, 2 * env.action_dim + 1, (env.num_envs,), device=env.device, generator=gen)
        return torch.rand(env.num_envs, env.num_actions, device=env.device, generator=gen) * 2 - 1

    for _ in range(args.warmup):
        env.step(action())
    actions = [action() for _ in range(args.steps)]  # expert actions drawn outside the timed region
    cuda_filter = wp.TIMING_KERNEL if args.timing == "kernel" else wp.TIMING_ALL
    wp.synchronize_device(env.wp_device)
    start = time.perf_counter()
    if args.profiler == "torch":
        from torch.profiler import ProfilerActivity, profile

        activities = [ProfilerActivity.CPU] + ([ProfilerActivity.CUDA] if env.wp_device.is_cuda else [])
        with profile(activities=activities) as prof:
            for a in actions:
                env.step(a)
            wp.synchronize_device(env.wp_device)
        wall_ms = 1e3 * (time.perf_counter() - start) / args.steps
        rows = torch_kernel_rows(prof.events(), args.steps)
        gaps = device_gaps([(e.time_range.start, e.time_range.end, e.name) for e in prof.events()
                            if e.device_type == torch.autograd.DeviceType.CUDA], args.steps, args.top)
    else:
        with wp.ScopedTimer("profile", cuda_filter=cuda_filter, print=False, synchronize=True) as timer:
            for a in actions:
                env.step(a)
        wall_ms = 1e3 * (time.perf_counter() - start) / args.steps
        rows = kernel_rows(timer.timing_results, args.steps)
        gaps = None
    total = sum(row[2] for row in rows)
    if not env.wp_device.is_cuda:
        print(f"note: {'PyTorch' if args.profiler == 'torch' else 'Warp'} records device times only on CUDA devices; "
              f"on the CPU only the wall time is measured")
    regime = ("graph replayed" if args.graph else "no graph") + f", {args.profiler} profiler"
    print(f"{args.task}, {args.num_envs} envs: {total:.3f} ms kernel time per env step, "
          f"{sum(row[1] for row in rows):.0f} launches; {wall_ms:.3f} ms wall per step ({regime})")
    for name, launches, ms in rows[: args.top]:
        print(f"  {ms:8.3f} ms {100 * ms / total:5.1f}%  {launches:6.0f} x  {name}")
    if gaps is not None and gaps["gaps"]:
        print(f"device per env step: {gaps['span_ms_per_step']:.3f} ms from the first kernel's start to the last's "
              f"end, {gaps['busy_ms_per_step']:.3f} ms busy, {gaps['idle_ms_per_step']:.3f} ms idle; longest gaps:")
        for gap_us, before, after in gaps["gaps"]:
            print(f"  {gap_us:9.1f} us  after {before[:70]}  before {after[:70]}")
    if args.out:
        with open(args.out, "w") as f:
            json.dump({"task": args.task, "num_envs": args.num_envs, "steps": args.steps, "policy": args.policy,
                       "overrides": overrides, "kernel_ms_per_step": total, "warmup": args.warmup,
                       "timing": args.timing, "profiled_wall_ms_per_step": wall_ms, "profiler": args.profiler,
                       "graph": args.graph,
                       "device_name": (torch.cuda.get_device_name(torch.device(args.device))
                                       if env.wp_device.is_cuda else "cpu"),
                       "kernels": [{"name": n, "launches_per_step": k, "ms_per_step": t} for n, k, t in rows],
                       "device_gaps": gaps},
                      f, indent=2)
    env.close()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
