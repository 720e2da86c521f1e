"""How often a task's resting tets are held (``World.tet_hold_speed``), as JSON: per env step, the share of envs whose
tets were held at its end and of those whose last substep was solved, under the scripted expert or random actions.

    python benchmarks/tet_hold.py --task ThreadInHole --device cuda:0 --num-envs 4096 --steps 100 --policy expert \\
        --out hold.json

An env is held once its tet vertices moved slower than the hold speed for ``tet_hold_substeps`` substeps in a row with
no contact on them; reset (every finished episode) wakes it, so an env held at the end of each step is solved only in
the first substeps after a reset. The hold's speed is the task's default (``--set`` overrides config values, e.g.
``hole_hold_speed=0`` for none). Counts are read between steps (the quiet counters), so they show how many envs end a
step held, not each substep's.
"""

from __future__ import annotations

import argparse
import json

import numpy as np
import torch

import lapwarp
from lapwarp.cli import default_device, parse_overrides
from lapwarp.experts import make_expert


def hold_fractions(task: str, device: str, num_envs: int, steps: int, policy: str, seed: int = 0,
                   overrides: dict | None = None) -> dict:
    """Run ``steps`` env steps and return the hold's per-step shares and their means."""
    env = lapwarp.make(task, num_envs=num_envs, device=device, seed=seed, **(overrides or {}))
    world = env.world
    if float(world.tet_hold_speed) <= 0.0:
        raise ValueError(f"{task}'s world holds no tets (tet_hold_speed {world.tet_hold_speed}): nothing to count")
    env.reset()
    expert = make_expert(env) if policy == "expert" else None
    generator = torch.Generator(device=env.device).manual_seed(seed)
    held, woken, finished = [], [], 0
    for _ in range(steps):
        if expert is not None:
            actions = expert()
        else:
            actions = torch.rand((num_envs, env.num_actions), generator=generator, device=env.device) * 2.0 - 1.0
        _, _, done, _ = env.step(actions)
        quiet = world._hold_quiet.numpy()
        held.append(float((quiet >= world.tet_hold_substeps).mean()))
        woken.append(float((quiet == 0).mean()))
        finished += int(done.sum())
    return {"task": task, "device": str(env.wp_device), "num_envs": num_envs, "steps": steps, "policy": policy,
            "seed": seed, "hold_speed": float(world.tet_hold_speed), "hold_substeps": int(world.tet_hold_substeps),
            "episodes_finished": finished, "held_at_step_end": float(np.mean(held)),
            "solved_last_substep": float(np.mean(woken)), "held_per_step": held}


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--task", default="ThreadInHole", choices=lapwarp.list_tasks())
    parser.add_argument("--device", default=default_device())
    parser.add_argument("--num-envs", type=int, default=16)
    parser.add_argument("--steps", type=int, default=100)
    parser.add_argument("--policy", choices=["expert", "random"], default="expert")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--set", nargs="*", default=[], metavar="KEY=VALUE", help="task config overrides")
    parser.add_argument("--out", default=None, help="JSON output path")
    args = parser.parse_args(argv)
    if args.num_envs < 1 or args.steps < 1:
        parser.error("--num-envs and --steps must be positive")
    row = hold_fractions(args.task, args.device, args.num_envs, args.steps, args.policy, args.seed,
                         parse_overrides(args.set))
    summary = {k: v for k, v in row.items() if k != "held_per_step"}
    print(json.dumps(summary))
    if args.out:
        with open(args.out, "w") as f:
            json.dump(row, f, indent=1)


if __name__ == "__main__":
    main()
