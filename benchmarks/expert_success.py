"""Success rate of a task's scripted expert over many episodes per configuration, written as JSON lines.

    python benchmarks/expert_success.py --task PrecisionCutting --num-envs 256 --episodes 256 \\
        --config path_function=line --config path_function=sine randomize_path=true --out expert.jsonl

Each ``--config`` is one configuration (space-separated KEY=VALUE overrides, JSON values); every configuration runs
with continuous and discrete actions. Episodes are counted as they finish (success = the env's success term at the
end of the episode, time-outs count as failures) until ``--episodes`` have finished or ``--max-steps`` steps passed.
By default only each env's first episode counts (``--episodes`` is then ``--num-envs``): counting episodes as they
finish (``--as-finished``, what this script did before) favours short ones, because an env that succeeds quickly
finishes a second episode before a slow one times out, so a run that stops at ``--episodes`` can report 100 % before
any time-out was counted.

``--action-noise SIGMA`` adds Gaussian noise of that standard deviation to the expert's continuous actions (clipped
to [-1, 1]): how precise a policy must be to solve the task (TissueDissection's expert still frees the flap in every
episode at SIGMA = 1, the width of the action box). Each record also gives the counted episodes' mean return and
length.
"""

from __future__ import annotations

import argparse
import json
import time

import torch
import warp as wp

import lapwarp
from lapwarp.cli import append_json_lines, default_device, parse_overrides, with_fixed
from lapwarp.experts import make_expert


def run(task: str, overrides: dict, action_type: str, num_envs: int, episodes: int, max_steps: int,
        device: str, seed: int, first_episodes: bool = False, action_noise: float = 0.0,
        world: dict | None = None) -> dict:
    env = lapwarp.make(task, num_envs=num_envs, device=device, action_type=action_type, seed=seed,
                       invalid_actions="zero", **overrides)
    for key, value in (world or {}).items():  # the World's own settings (checked by the World at its next step)
        if key.startswith("_") or not hasattr(env.world, key) or callable(getattr(env.world, key)):
            env.close()
            raise ValueError(f"--world {key}: {task}'s World has no setting {key!r}")
        setattr(env.world, key, value)
    expert = make_expert(env)
    noise = torch.Generator(device=env.device).manual_seed(seed)
    obs = env.get_observations()
    finished = succeeded = 0
    return_sum = length_sum = 0.0
    counted = torch.zeros(num_envs, dtype=torch.bool, device=env.device)
    start = time.perf_counter()
    step = 0
    for step in range(max_steps):  # noqa: B007 (reported below)
        actions = expert(obs)
        if action_noise > 0.0:
            actions = (actions + action_noise * torch.randn(actions.shape, generator=noise, device=env.device)).clamp(
                -1.0, 1.0)
        obs, _, done, _ = env.step(actions)
        mask = done.bool()
        if first_episodes:
            mask = mask & ~counted
            counted |= mask
        if mask.any():
            finished += int(mask.sum())
            succeeded += int(wp.to_torch(env.last_episode_success)[mask].sum())
            # the env keeps each finished episode's return and length
            return_sum += float(wp.to_torch(env.last_episode_return)[mask].sum())
            length_sum += float(wp.to_torch(env.last_episode_length)[mask].sum())
        if finished >= episodes:
            break
    env.close()
    return {"task": task, "overrides": overrides, "world": world or {}, "action_type": action_type,
            "num_envs": num_envs,
            "action_noise": action_noise, "episodes": finished, "successes": succeeded,
            "success_rate": succeeded / max(finished, 1), "mean_return": return_sum / max(finished, 1),
            "mean_length": length_sum / max(finished, 1), "first_episodes": first_episodes, "steps": step + 1,
            "seconds": time.perf_counter() - start}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--task", required=True, choices=lapwarp.list_tasks())
    parser.add_argument("--config", nargs="*", action="append", default=None, metavar="KEY=VALUE")
    parser.add_argument("--action-types", nargs="+", type=str.upper, choices=["CONTINUOUS", "DISCRETE"],
                        default=["CONTINUOUS", "DISCRETE"])
    parser.add_argument("--num-envs", type=int, default=256)
    parser.add_argument("--episodes", type=int, default=256)
    parser.add_argument("--max-steps", type=int, default=2000)
    parser.add_argument("--device", default=default_device())
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--first-episodes", action="store_true", default=True,
                        help="count only each env's first episode (the default; unbiased when episode lengths differ)")
    parser.add_argument("--as-finished", dest="first_episodes", action="store_false",
                        help="count episodes as they finish until --episodes (biased towards short episodes)")
    parser.add_argument("--action-noise", type=float, default=0.0, metavar="SIGMA",
                        help="Gaussian noise added to the expert's continuous actions (clipped to [-1, 1])")
    parser.add_argument("--world", nargs="*", default=[], metavar="KEY=VALUE",
                        help="settings of the env's World (JSON values) for every configuration, set after the env is "
                             "made, e.g. chain_register_split=true: to check an expert on a solver option before it "
                             "is a task's default")
    parser.add_argument("--out", default=None,
                        help="append one JSON line per result to this file (as bench_physics.py and soak.py do)")
    args = parser.parse_args(argv)
    if min(args.num_envs, args.episodes, args.max_steps) < 1:
        parser.error(f"--num-envs, --episodes and --max-steps must be positive, got {args.num_envs}, "
                     f"{args.episodes} and {args.max_steps}")
    if not 0.0 <= args.action_noise <= 10.0:  # NaN fails the comparison too
        parser.error(f"--action-noise must be in [0, 10], got {args.action_noise}")
    if args.action_noise > 0.0 and "DISCRETE" in args.action_types:
        parser.error("--action-noise perturbs continuous actions: add --action-types CONTINUOUS")
    if args.first_episodes:
        args.episodes = args.num_envs
    wp.config.log_level = max(wp.config.log_level, wp.LOG_WARNING)
    wp.config.enable_cpu_blocks = True  # the 'hybrid' chain solve's lanes as Warp's fibers on a CPU
    try:  # every configuration before the first run takes device time
        configs = [parse_overrides(c) for c in (args.config or [[]])]
        world = parse_overrides(args.world)
        for overrides in configs:
            for action_type in args.action_types:
                lapwarp.check_config(args.task, **with_fixed(overrides, "--config", action_type=action_type,
                                                             seed=args.seed, invalid_actions="zero"))
    except ValueError as exc:
        parser.error(str(exc))
    records = []
    for overrides in configs:
        for action_type in args.action_types:
            try:
                r = run(args.task, overrides, action_type, args.num_envs, args.episodes, args.max_steps, args.device,
                        args.seed, args.first_episodes, args.action_noise, world)
            except ValueError as exc:
                parser.error(str(exc))
            records.append(r)
            print(json.dumps(r), flush=True)
    append_json_lines(args.out, records)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
