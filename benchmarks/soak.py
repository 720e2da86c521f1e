"""Soak run: every registered task, continuous and discrete, random actions at the bounds of the action space for a
long time; counts everything that should never happen, and measures GPU run-to-run determinism.

    python benchmarks/soak.py --device cuda:0 --num-envs 4096 --env-steps 1e8 --out soak.jsonl
    python benchmarks/soak.py --device cpu --num-envs 4 --env-steps 64 --tasks Reach     # smoke test

Per (task, action type) one JSON line: env-steps run, env-steps/s (whole ``env.step`` with the counting, no host
sync inside a block of steps), non-finite observation / reward values (must be 0), envs flagged unstable and reset,
episodes finished, env-steps that lost contact records (``/contact/overflow_fraction``), non-finite or invalid
actions seen (0 here: the pool is valid), and memory in use at start and end (device memory on CUDA, resident set
size on the CPU). Actions: continuous components drawn from {-1, 1} and U(-1, 1) in equal parts (the bounds are
where the instruments hit their limits); discrete indices uniform over every action. The envs run with
``invalid_actions="zero"`` (training's setting, no per-step host sync).

``--determinism K``: two envs built with the same seed run the same K action batches; the largest absolute
difference of observations and rewards between them is reported (0 on the CPU, where the suite also tests it; on the
GPU atomics may reorder float sums).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time

import torch

import lapwarp
from lapwarp.cli import default_device, parse_overrides, quiet_warp, with_fixed

POOL = 16  # pre-drawn action batches, cycled


def memory_in_use(device: str) -> int:
    """Bytes in use: device memory (all processes) on CUDA, this process' resident set on the CPU."""
    if device.startswith("cuda"):
        free, total = torch.cuda.mem_get_info(torch.device(device))
        return int(total - free)
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")


def action_pool(env, seed: int) -> list[torch.Tensor]:
    gen = torch.Generator(device=env.device).manual_seed(seed)
    n = env.num_envs
    if env.is_discrete:
        return [torch.randint(0, 2 * env.action_dim + 1, (n,), device=env.device, generator=gen) for _ in range(POOL)]
    pool = []
    for _ in range(POOL):
        uniform = torch.rand(n, env.num_actions, device=env.device, generator=gen) * 2 - 1
        at_bound = torch.where(torch.rand(n, env.num_actions, device=env.device, generator=gen) < 0.5, -1.0, 1.0)
        pick = torch.rand(n, env.num_actions, device=env.device, generator=gen) < 0.5
        pool.append(torch.where(pick, at_bound, uniform))
    return pool


def sync(device: str) -> None:
    if device.startswith("cuda"):
        torch.cuda.synchronize(torch.device(device))


def soak_one(task: str, action_type: str, num_envs: int, device: str, env_steps: float, seed: int,
             overrides: dict) -> dict:
    memory_start = memory_in_use(device)
    env = lapwarp.make(task, num_envs=num_envs, device=device, action_type=action_type, invalid_actions="zero",
                       seed=seed, **overrides)
    pool = action_pool(env, seed)
    keys = env.log_keys
    counted = {k: torch.zeros((), dtype=torch.float64, device=env.device) for k in keys
               if k.startswith(("/env/", "/action/", "/contact/"))}
    nonfinite_obs = torch.zeros((), dtype=torch.int64, device=env.device)
    nonfinite_reward = torch.zeros((), dtype=torch.int64, device=env.device)
    episodes = torch.zeros((), dtype=torch.int64, device=env.device)
    steps = max(1, int(float(env_steps) // num_envs))
    env.step(pool[0])  # compile, capture the graph
    sync(env.device)
    memory_warm = memory_in_use(device)
    start = time.perf_counter()
    for i in range(steps):
        obs, reward, done, extras = env.step(pool[i % POOL])
        for group in obs.values():
            nonfinite_obs += (~torch.isfinite(group)).sum()
        nonfinite_reward += (~torch.isfinite(reward)).sum()
        episodes += done.sum()
        for k, total in counted.items():  # fractions of envs (or of action components) -> counts
            total += extras["log"][k] * num_envs
    sync(env.device)
    elapsed = time.perf_counter() - start
    record = {
        "task": task, "action_type": action_type, "num_envs": num_envs, "device": device_label(device),
        "env_steps": steps * num_envs, "seconds": elapsed, "env_steps_per_s": steps * num_envs / elapsed,
        "nonfinite_observation_values": int(nonfinite_obs), "nonfinite_rewards": int(nonfinite_reward),
        "episodes_finished": int(episodes),
        "unstable_env_resets": round(float(counted.pop("/env/unstable_fraction", torch.zeros(())))),
        "contact_overflow_env_steps": round(float(counted.pop("/contact/overflow_fraction", torch.zeros(())))),
        "contact_systems": "/contact/overflow_fraction" in keys,
        "memory_bytes_before_build": memory_start, "memory_bytes_warm": memory_warm,
        "memory_bytes_end": memory_in_use(device),
        "frame_skip": env.cfg.frame_skip, "time_step": env.cfg.time_step,
    }
    record.update({k.replace("/action/", "actions_").replace("_fraction", "_sum"): float(v)
                   for k, v in counted.items()})
    env.close()
    return record


def determinism(task: str, action_type: str, num_envs: int, device: str, steps: int, seed: int,
                overrides: dict) -> dict:
    envs = [lapwarp.make(task, num_envs=num_envs, device=device, action_type=action_type, invalid_actions="zero",
                         seed=seed, **overrides) for _ in range(2)]
    pool = action_pool(envs[0], seed)
    obs_diff = reward_diff = 0.0
    for i in range(steps):
        (oa, ra, _, _), (ob, rb, _, _) = (e.step(pool[i % POOL]) for e in envs)
        obs_diff = max(obs_diff, max(float((oa[k] - ob[k]).abs().max()) for k in oa.keys()))
        reward_diff = max(reward_diff, float((ra - rb).abs().max()))
    for e in envs:
        e.close()
    return {"task": task, "action_type": action_type, "num_envs": num_envs, "device": device_label(device),
            "determinism_steps": steps, "max_abs_observation_difference": obs_diff,
            "max_abs_reward_difference": reward_diff}


def device_label(device: str) -> str:
    return torch.cuda.get_device_name(torch.device(device)) if device.startswith("cuda") else "cpu"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--device", default=default_device())
    parser.add_argument("--num-envs", type=int, default=4096)
    parser.add_argument("--env-steps", type=float, default=1e8, help="env steps per (task, action type)")
    parser.add_argument("--tasks", nargs="*", default=None, help="default: every registered task")
    parser.add_argument("--action-types", nargs="*", type=str.upper, choices=["CONTINUOUS", "DISCRETE"],
                        default=["CONTINUOUS", "DISCRETE"])
    parser.add_argument("--determinism", type=int, default=0, metavar="K",
                        help="also compare two same-seed runs over K steps")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--set", nargs="*", default=[], metavar="KEY=VALUE", help="config overrides (JSON values)")
    parser.add_argument("--out", default=None, help="append one JSON line per result to this file")
    args = parser.parse_args(argv)
    tasks = args.tasks or lapwarp.list_tasks()
    unknown = sorted(set(tasks) - set(lapwarp.list_tasks()))
    if unknown or args.num_envs < 1 or args.env_steps < 1 or args.determinism < 0:
        parser.error(f"unknown tasks {unknown}" if unknown else
                     "--num-envs and --env-steps must be positive and --determinism non-negative")
    try:  # every configuration before the first run takes device time
        overrides = parse_overrides(args.set)
        for task in tasks:
            for action_type in args.action_types:
                lapwarp.check_config(task, **with_fixed(overrides, "--set", action_type=action_type,
                                                        invalid_actions="zero", seed=args.seed))
    except ValueError as exc:
        parser.error(str(exc))
    quiet_warp()
    failures = 0
    for task in tasks:
        for action_type in args.action_types:
            records = [soak_one(task, action_type, args.num_envs, args.device, args.env_steps, args.seed, overrides)]
            if args.determinism > 0:
                records.append(determinism(task, action_type, min(args.num_envs, 1024), args.device,
                                           args.determinism, args.seed, overrides))
            for record in records:
                line = json.dumps(record)
                print(line, flush=True)
                if args.out:
                    with open(args.out, "a") as f:
                        f.write(line + "\n")
            failures += records[0]["nonfinite_observation_values"] + records[0]["nonfinite_rewards"] > 0
    return 1 if failures else 0


if __name__ == "__main__":
    sys.exit(main())
