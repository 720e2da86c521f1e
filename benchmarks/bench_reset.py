"""Cost of resetting cut envs against uncut ones, for the cutting tasks, written as JSON.

    python benchmarks/bench_reset.py --tasks RopeCutting --device cuda:0 --num-envs 4096 --out reset.json

Resets are in place: masks, surfaces and rest state of the masked envs are restored from their initial rows (no
rebuild, no reallocation), so a cut env should cost what an uncut one costs. Measured per task:

* ``uncut``: ``env.reset()`` of every env after ``--expert-steps`` steps of the idle action (zero for continuous
  actions, the no-op for discrete ones: the instruments stay where the reset put them and nothing is cut), median
  over ``--repeats``;
* ``cut``: ``env.reset()`` of every env after ``--expert-steps`` steps of the scripted expert (which cuts),
  median over ``--repeats``.

Each repeat times one reset of each kind, in alternating order (uncut first in even repeats, cut first in odd ones);
the JSON keeps every sample and the quartiles of the ratio within each repeat (``cut_over_uncut_paired``), so a
ratio off 1 can be told from the spread between resets.

Both follow the same number of steps, so both resets meet the caches as a step leaves them (timing an uncut reset
right after another reset, as this script did before the twenty-sixth session, met warm caches and favoured it: on
the CPU that alone made TissueDissection's cut reset 1.2x the uncut one). The removed elements per env at the moment
of each kind of reset are reported too (0 expected for ``uncut``).

Each reset is timed alone, with a device sync before and after (it is a host call that launches the masked reset
and the observation kernels; no CUDA graph).

``--profile DIR`` then profiles one more reset of each kind kernel by kernel (``wp.ScopedTimer`` with kernel timing,
outside the timed resets, whose figures it would distort) and writes ``DIR/<task>_reset_uncut.json`` and
``_cut.json`` in ``profile_step.py``'s format (ms per reset for each kernel, and the profiled reset's wall time), then
prints their difference (``profile_step.py --diff``): whether a cut reset's extra time is device work or host time.
"""

from __future__ import annotations

import argparse
import json
import statistics
import time
from pathlib import Path

import torch
import warp as wp
from bench_env import device_name, sync
from profile_step import diff_profiles, kernel_rows

import lapwarp
from lapwarp.cli import default_device, parse_overrides
from lapwarp.experts import make_expert


def removed_elements(env) -> float:
    """Mean number of removed (cut) elements per env, over every cuttable element kind."""
    state = env.world.state
    total = 0
    for name in ("tet_active", "tri_active", "segment_active"):
        mask = getattr(state, name, None)
        if mask is not None:
            total += int((wp.to_torch(mask) == 0).sum().item())
    return total / env.num_envs


def timed_reset(env) -> float:
    sync(env.device)
    start = time.perf_counter()
    env.reset()
    sync(env.device)
    return time.perf_counter() - start


def paired_ratio_quartiles(cut: list[float], uncut: list[float]) -> dict:
    """Quartiles (25 / 50 / 75 %) of ``cut[i] / uncut[i]``, the ratio within each repeat."""
    ratios = sorted(c / u for c, u in zip(cut, uncut, strict=True))
    if len(ratios) == 1:
        return {"q25": ratios[0], "median": ratios[0], "q75": ratios[0]}
    q25, q50, q75 = statistics.quantiles(ratios, n=4, method="inclusive")
    return {"q25": q25, "median": q50, "q75": q75}


def profiled_reset(env) -> dict:
    """One reset under ``wp.ScopedTimer`` kernel timing: per-kernel ms and launches, and the reset's wall time."""
    sync(env.device)
    start = time.perf_counter()
    with wp.ScopedTimer("reset", cuda_filter=wp.TIMING_KERNEL, print=False, synchronize=True) as timer:
        env.reset()
    wall_ms = 1e3 * (time.perf_counter() - start)
    rows = kernel_rows(timer.timing_results, 1)
    return {"kernel_ms_per_step": sum(row[2] for row in rows), "profiled_wall_ms_per_step": wall_ms,
            "kernels": [{"name": n, "launches_per_step": k, "ms_per_step": t} for n, k, t in rows]}


def bench_task(task: str, num_envs: int, device: str, repeats: int, expert_steps: int, overrides: dict,
               profile_dir: str | None = None) -> dict:
    env = lapwarp.make(task, num_envs=num_envs, device=device, invalid_actions="zero", **overrides)
    expert = make_expert(env)
    env.reset()
    for _ in range(3):  # compile and warm every reset and step kernel
        env.step(expert())
        timed_reset(env)
    if env.is_discrete:
        idle = torch.full((num_envs,), 2 * env.action_dim, dtype=torch.long, device=env.device)  # the no-op
    else:
        idle = torch.zeros(num_envs, env.num_actions, device=env.device)
    uncut, removed_uncut, cut, removed = [], [], [], []

    def uncut_reset():
        for _ in range(expert_steps):
            env.step(idle)
        removed_uncut.append(removed_elements(env))
        uncut.append(timed_reset(env))

    def cut_reset():
        for _ in range(expert_steps):
            env.step(expert())
        removed.append(removed_elements(env))
        cut.append(timed_reset(env))

    for repeat in range(repeats):
        # the order alternates, so neither kind always follows the other (what one leaves in the caches, the
        # allocator or the clocks meets the other kind as often)
        for reset in ((uncut_reset, cut_reset) if repeat % 2 == 0 else (cut_reset, uncut_reset)):
            reset()
    profiles = {}
    if profile_dir is not None:
        for kind, act in (("uncut", lambda: idle), ("cut", expert)):
            for _ in range(expert_steps):
                env.step(act())
            profiles[kind] = {"task": task, "num_envs": num_envs, "reset": kind, "overrides": overrides,
                              "removed_elements_per_env": removed_elements(env), **profiled_reset(env)}
            path = Path(profile_dir) / f"{task}_reset_{kind}.json"
            path.parent.mkdir(parents=True, exist_ok=True)
            path.write_text(json.dumps(profiles[kind], indent=2))
    env.close()
    if profiles:
        walls = [profiles[kind]["profiled_wall_ms_per_step"] for kind in ("cut", "uncut")]
        print(f"{task}: kernels per reset, cut (first) against uncut (second); wall {walls[0]:.3f} / {walls[1]:.3f} "
              "ms (profiled)")
        diff_profiles(profiles["cut"], profiles["uncut"], top=15)
    return {
        "task": task, "num_envs": num_envs, "repeats": repeats, "steps_before_each_reset": expert_steps,
        "uncut_reset_ms": 1e3 * statistics.median(uncut), "cut_reset_ms": 1e3 * statistics.median(cut),
        "cut_over_uncut": statistics.median(cut) / statistics.median(uncut),
        # the ratio within each repeat (its two resets close in time), and its spread over the repeats
        "cut_over_uncut_paired": paired_ratio_quartiles(cut, uncut),
        "uncut_reset_ms_all": [1e3 * t for t in uncut], "cut_reset_ms_all": [1e3 * t for t in cut],
        "removed_elements_per_env_at_cut_reset": statistics.mean(removed),
        "removed_elements_per_env_at_uncut_reset": statistics.mean(removed_uncut),
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--tasks", nargs="+", default=["RopeCutting"])
    parser.add_argument("--device", default=default_device())
    parser.add_argument("--num-envs", type=int, default=4096)
    parser.add_argument("--repeats", type=int, default=10)
    parser.add_argument("--expert-steps", type=int, default=40,
                        help="steps (idle or the expert's) before each timed reset")
    parser.add_argument("--set", nargs="*", default=[], metavar="KEY=VALUE",
                        help="config overrides (JSON values); a task that ends at its first cut needs more cuts to "
                             "leave cut envs standing, e.g. RopeCutting num_ropes_to_cut=3")
    parser.add_argument("--out", default=None, help="JSON output path")
    parser.add_argument("--profile", default=None, metavar="DIR",
                        help="also profile one reset of each kind kernel by kernel into DIR (see above)")
    args = parser.parse_args(argv)
    wp.config.log_level = max(wp.config.log_level, wp.LOG_WARNING)
    overrides = parse_overrides(args.set)
    results = []
    for task in args.tasks:
        r = bench_task(task, args.num_envs, args.device, args.repeats, args.expert_steps, overrides, args.profile)
        r["overrides"] = overrides
        results.append(r)
        paired = r["cut_over_uncut_paired"]
        print(f"{task:<18} uncut {r['uncut_reset_ms']:.3f} ms  cut {r['cut_reset_ms']:.3f} ms  "
              f"ratio {r['cut_over_uncut']:.3f} (within repeats: median {paired['median']:.3f}, quartiles "
              f"{paired['q25']:.3f}-{paired['q75']:.3f})  removed/env {r['removed_elements_per_env_at_cut_reset']:.1f} "
              f"(uncut {r['removed_elements_per_env_at_uncut_reset']:.1f})",
              flush=True)
    report = {"benchmark": "reset_cost", "device": args.device, "device_name": device_name(args.device),
              "warp": wp.__version__, "torch": torch.__version__, "results": results}
    if args.out:
        with open(args.out, "w") as f:
            json.dump(report, f, indent=2)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
