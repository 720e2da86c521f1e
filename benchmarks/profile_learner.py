"""Where a PPO iteration's time goes (issue #19's pixel learner): rollout vs update wall time, and the update's GPU
time by operator, written as JSON.

    python benchmarks/profile_learner.py --out learner.json -- --task Reach --obs rgb --set image_shape=[64,64] \
        --fast-pixels --shared-encoder [--compile default]

Everything after ``--`` is a ``train/ppo.py`` command line (task, observation, preset, learner options), validated by
ppo.py's own parser, so the profiled learner is the one that trains. ``--warmup`` iterations run first (cuDNN's
algorithm search and ``torch.compile`` happen there), then ``--iterations`` timed ones: the wall seconds of each
rollout (``num_steps_per_env`` env steps with policy inference) and of each update (``alg.update``), with a device
synchronisation at each boundary (benchmark only: training has none there). Then ``--profile-iterations`` run under
``torch.profiler``: their GPU time by operator (self CUDA time; CPU time on the CPU; top ``--top``), and the
ranges ``act`` / ``env.step`` / ``update``.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import statistics
import sys
import time

import torch

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "train"))

import ppo  # noqa: E402  (train/ is not a package)
from rank_setup import DistributedRunner  # noqa: E402

from lapwarp.cli import default_device, positive_int  # noqa: E402


class Timed:
    """Wraps a callable: each call runs inside a profiler range named ``name`` and, while ``timing``, its wall time
    (device synchronised before and after) is appended to ``seconds``."""

    def __init__(self, name: str, fn, sync):
        self.name, self.fn, self.sync = name, fn, sync
        self.timing = False
        self.seconds: list[float] = []

    def __call__(self, *args, **kwargs):
        with torch.profiler.record_function(self.name):
            if not self.timing:
                return self.fn(*args, **kwargs)
            self.sync()
            start = time.perf_counter()
            result = self.fn(*args, **kwargs)
            self.sync()
            self.seconds.append(time.perf_counter() - start)
            return result


def build(ppo_argv: list[str]):
    """The env and rsl-rl runner ``train/ppo.py`` would train with these arguments (one process)."""
    parser = ppo.build_parser()
    args = parser.parse_args(ppo_argv)
    if args.play or args.resume or args.distributed:
        parser.error("the profiler trains from scratch in one process (no --play, --resume or --distributed)")
    device = args.device or default_device()
    preset, num_envs, _, train_cfg, overrides = ppo.training_config(args, parser, device)
    train_cfg["seed"] = args.seed
    torch.manual_seed(args.seed)
    env = ppo.make_run_env(parser, args.task, num_envs, device, overrides, args.seed, args.fast_pixels)
    runner = DistributedRunner(env, train_cfg, log_dir=None, device=device)
    return args, device, preset, num_envs, train_cfg, env, runner


def operator_table(prof, top: int, cuda: bool) -> list[dict]:
    """The profiled operators by self CUDA time (self CPU time on the CPU), largest first (milliseconds summed over
    the profiled iterations)."""
    rows = []
    for event in prof.key_averages():
        if cuda:
            us = getattr(event, "self_device_time_total", None)
            us = getattr(event, "self_cuda_time_total", 0.0) if us is None else us
        else:
            us = event.self_cpu_time_total
        if us > 0:
            rows.append({"name": event.key, "calls": event.count, "self_ms": us / 1e3})
    rows.sort(key=lambda row: -row["self_ms"])
    return rows[:top]


def range_times(prof, names: tuple[str, ...]) -> dict[str, dict]:
    """Total CPU wall and CUDA time of each named ``record_function`` range (milliseconds)."""
    out = {}
    for event in prof.key_averages():
        if event.key in names:
            cuda_us = getattr(event, "device_time_total", None)
            if cuda_us is None:
                cuda_us = getattr(event, "cuda_time_total", 0.0)
            out[event.key] = {"calls": event.count, "cpu_ms": event.cpu_time_total / 1e3, "cuda_ms": cuda_us / 1e3}
    return out


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    ours, ppo_argv = (argv[:argv.index("--")], argv[argv.index("--") + 1:]) if "--" in argv else (argv, [])
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--warmup", type=positive_int, default=5, help="untimed iterations first")
    parser.add_argument("--iterations", type=positive_int, default=10, help="timed iterations")
    parser.add_argument("--profile-iterations", type=int, default=2,
                        help="iterations under torch.profiler (0: none)")
    parser.add_argument("--top", type=positive_int, default=25, help="operators listed")
    parser.add_argument("--out", default=None, help="JSON file")
    args = parser.parse_args(ours)
    if args.profile_iterations < 0:
        parser.error(f"--profile-iterations must be >= 0, got {args.profile_iterations}")

    start = time.time()
    ppo_args, device, preset, num_envs, train_cfg, env, runner = build(ppo_argv)
    cuda = device.startswith("cuda")
    sync = (lambda: torch.cuda.synchronize(device)) if cuda else (lambda: None)
    # wrap the calls rsl-rl's learn() makes: the policy's action, the env step, the update
    act = runner.alg.act = Timed("act", runner.alg.act, sync)
    step = Timed("env.step", runner.env.step, sync)
    runner.env.step = step
    update = runner.alg.update = Timed("update", runner.alg.update, sync)
    build_s = time.time() - start

    warm_start = time.time()
    runner.learn(num_learning_iterations=args.warmup, init_at_random_ep_len=True)
    sync()
    warmup_s = time.time() - warm_start

    for timed in (act, step, update):
        timed.timing = True
    rollouts = []
    for _ in range(args.iterations):
        sync()
        it_start = time.perf_counter()
        before = len(update.seconds)
        runner.learn(num_learning_iterations=1)
        sync()
        assert len(update.seconds) == before + 1
        rollouts.append(time.perf_counter() - it_start - update.seconds[-1])
    for timed in (act, step, update):
        timed.timing = False

    operators, ranges = [], {}
    if args.profile_iterations:
        activities = [torch.profiler.ProfilerActivity.CPU] + ([torch.profiler.ProfilerActivity.CUDA] if cuda else [])
        with torch.profiler.profile(activities=activities) as prof:
            runner.learn(num_learning_iterations=args.profile_iterations)
            sync()
        operators = operator_table(prof, args.top, cuda)
        ranges = range_times(prof, ("act", "env.step", "update"))

    steps_per_it = num_envs * train_cfg["num_steps_per_env"]
    per_it = [r + u for r, u in zip(rollouts, update.seconds, strict=True)]
    result = {
        "ppo_argv": ppo_argv, "preset": preset, "num_envs": num_envs, "steps_per_env": train_cfg["num_steps_per_env"],
        "device": ppo.device_name(device), "torch": torch.__version__,
        "build_s": round(build_s, 2), "warmup_iterations": args.warmup, "warmup_s": round(warmup_s, 2),
        "iterations": args.iterations,
        "rollout_s_per_it": statistics.median(rollouts), "update_s_per_it": statistics.median(update.seconds),
        "env_step_ms": 1e3 * statistics.median(step.seconds), "act_ms": 1e3 * statistics.median(act.seconds),
        # the timed iterations' totals: the env steps and actions ran inside the rollouts
        "rollout_s_total": sum(rollouts), "env_step_s_total": sum(step.seconds), "act_s_total": sum(act.seconds),
        "env_steps_per_s": steps_per_it / statistics.median(per_it),
        "update_share": statistics.median(update.seconds) / statistics.median(per_it),
        "profile_iterations": args.profile_iterations, "ranges_ms": ranges, "top_operators": operators,
    }
    print(f"{ppo.device_name(device)}, {num_envs} envs: rollout {result['rollout_s_per_it']:.3f} s/it "
          f"(env.step {result['env_step_ms']:.2f} ms, act {result['act_ms']:.2f} ms), update "
          f"{result['update_s_per_it']:.3f} s/it ({result['update_share']:.0%}), "
          f"{result['env_steps_per_s']:,.0f} env-steps/s (build {build_s:.1f} s, warm-up {warmup_s:.1f} s)")
    for row in operators[:args.top]:
        print(f"  {row['self_ms']:9.2f} ms  {row['calls']:6d}x  {row['name'][:90]}")
    if args.out:
        with open(args.out, "w") as f:
            json.dump(result, f, indent=1)
    return 0


if __name__ == "__main__":
    with contextlib.suppress(BrokenPipeError):
        sys.exit(main())
