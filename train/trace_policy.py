"""Roll out a trained PPO checkpoint and write what it does, step by step: actions, reward features, reward, done and
success per env, as CSV. For finding out why a policy fails (a component held under its threshold, a gate that never
opens) rather than only that it does.

    python train/trace_policy.py runs/LigatingLoop/<run>/model_99.pt --task LigatingLoop --set loop_stiffness=stiff \\
        --envs 32 --steps 500 --out trace.csv
    python train/trace_policy.py CKPT --task LigatingLoop --force 4=1.0 --force-from 60 --out forced.csv

Everything after the checkpoint that is not an option below is ``train/ppo.py``'s (``--task``, ``--set``, ``--obs``,
``--critic``, ``--preset`` ...): the env and the models are built exactly as that training run built them (the same
``--set`` values are needed). ``--force K=V`` overrides continuous action component ``K`` with ``V`` from step
``--force-from`` on: what would have happened had the policy done that. The policy acts deterministically (its mean)
unless ``--stochastic``. A summary (per-feature means, success of the first episodes) is printed.
"""

from __future__ import annotations

import argparse
import csv
import math
import os
import sys

import numpy as np
import torch

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import ppo  # noqa: E402

from lapwarp.cli import default_device, positive_int  # noqa: E402


def parse_force(text: str) -> tuple[int, float]:
    """``K=V`` -> (component K, value V)."""
    key, sep, value = text.partition("=")
    try:
        component, forced = int(key), float(value)
    except ValueError:
        component, forced = -1, math.nan
    if not sep or component < 0 or not math.isfinite(forced):
        raise argparse.ArgumentTypeError(f"expected COMPONENT=VALUE (a non-negative int, a finite number): {text!r}")
    return component, forced


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("checkpoint", help="an rsl-rl checkpoint written by train/ppo.py")
    parser.add_argument("--envs", type=positive_int, default=16, help="envs rolled out (default 16)")
    parser.add_argument("--steps", type=positive_int, default=None, help="steps (default: the task's episode length)")
    parser.add_argument("--trace-envs", type=positive_int, default=None,
                        help="the first N envs are written to the CSV (default: all)")
    parser.add_argument("--force", type=parse_force, action="append", default=[], metavar="K=V",
                        help="override continuous action component K with V (repeatable)")
    parser.add_argument("--force-from", type=int, default=0, metavar="STEP", help="first step of --force (default 0)")
    parser.add_argument("--stochastic", action="store_true", help="sample actions as in training (default: the mean)")
    parser.add_argument("--seed", type=int, default=12345, help="the env's seed (default 12345)")
    parser.add_argument("--device", default=None, help="default: cuda:0 if there is one, else cpu")
    parser.add_argument("--out", required=True, help="CSV path")
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args, rest = parser.parse_known_args(argv)
    device = args.device or default_device()
    if not os.path.isfile(args.checkpoint):
        parser.error(f"checkpoint {args.checkpoint!r} is not a file")
    if args.trace_envs is not None and args.trace_envs > args.envs:
        parser.error(f"--trace-envs {args.trace_envs} exceeds --envs {args.envs}")
    if args.force_from < 0:
        parser.error(f"--force-from must be non-negative, got {args.force_from}")
    train_parser = ppo.build_parser()
    train_args = train_parser.parse_args([*rest, "--play", args.checkpoint, "--device", device])
    _, _, _, train_cfg, overrides = ppo.training_config(train_args, train_parser, device)
    if "seed" in overrides:
        parser.error("the env's seed is --seed, not --set seed=...")
    # the image group as the run's models were trained on it
    env = ppo.make_run_env(parser, train_args.task, args.envs, device, overrides, args.seed, train_args.fast_pixels)
    if args.force and env.is_discrete:
        parser.error("--force overrides components of continuous actions; this env's actions are discrete")
    for component, _ in args.force:
        if component >= env.num_actions:
            parser.error(f"--force component {component} is outside the {env.num_actions} action components")
    runner = ppo.DistributedRunner(env, train_cfg, log_dir=None, device=device)
    ppo.load_checkpoint(runner, args.checkpoint, device, parser, "checkpoint")
    policy = runner.get_inference_policy(device=device)

    steps = args.steps or env.max_episode_length
    traced = args.trace_envs or args.envs
    names = list(env.reward_features)
    action_columns = ["action"] if env.is_discrete else [f"action_{k}" for k in range(env.num_actions)]
    last_success = env.last_episode_success
    first = np.full(args.envs, -1)
    feature_sums = np.zeros(len(names))
    obs, _ = env.reset()
    with open(args.out, "w", newline="") as f, torch.inference_mode():
        writer = csv.writer(f)
        writer.writerow(["step", "env", *action_columns, *names, "reward", "done", "success"])
        for step in range(steps):
            actions = policy(obs, stochastic_output=True) if args.stochastic else policy(obs)
            if step >= args.force_from:
                for component, value in args.force:
                    actions[:, component] = value
            obs, reward, done, _ = env.step(actions)
            features = env.features.numpy().copy()  # on the CPU numpy() is a view of the env's buffer
            success = last_success.numpy().copy()
            finished = done.cpu().numpy()
            feature_sums += features.sum(0)
            for e in np.nonzero(finished & (first < 0))[0]:
                first[e] = success[e]
            act = actions.cpu().numpy().reshape(args.envs, -1)
            rew = reward.cpu().numpy()
            for e in range(traced):
                writer.writerow([step, e, *act[e].tolist(), *features[e].tolist(), float(rew[e]), int(finished[e]),
                                 int(success[e]) if finished[e] else ""])
    means = ", ".join(f"{n} {v:.4g}" for n, v in zip(names, feature_sums / (steps * args.envs), strict=True))
    done_count = int((first >= 0).sum())
    print(f"{train_args.task}, {args.envs} envs x {steps} steps ({'sampled' if args.stochastic else 'deterministic'}"
          f"{', forced ' + str(args.force) + f' from step {args.force_from}' if args.force else ''}): first episodes "
          f"finished {done_count}, succeeded {int((first == 1).sum())}; feature means per step: {means}; "
          f"trace of {traced} envs in {args.out}")
    env.close()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
