"""TissueDissection: can a policy that sees only the STATE observation's border point free the flap?

    python benchmarks/border_follower.py --num-envs 16 --cut-removal centroid touch --out follower.jsonl

A scripted follower takes the hook's cutting centre to the border point (sofa_env's: the live CT node of the row
nearest the free end that is closest to the hook's tip, the observation's last three values, here read from the env
unnormalised) with the scripted expert's approach (from above, activation with hysteresis), without any privileged
state. One JSON line per cut rule: episodes freed among each env's first episode, mean return and length. (CPU, 16
envs, seed 5: 0 / 16 by centroid, 8 / 16 by touch: by centroid the border point, a node, lies ~5 mm from the centres
the hook must come within 1 mm of.)
"""

from __future__ import annotations

import argparse
import time

import torch
import warp as wp

import lapwarp
from lapwarp import launching
from lapwarp.cli import default_device, emit_json_lines, quiet_warp
from lapwarp.tasks.dissection.tissue_dissection import TissueDissectionExpert, approach_errors
from lapwarp.tasks.rig import cutting_center


@wp.kernel
def follow_border(border: wp.array(dtype=wp.vec3), pose: wp.array2d(dtype=wp.transform),
                  rcm: wp.array2d(dtype=wp.transform), ptsd: wp.array2d(dtype=wp.vec4),
                  active: wp.array2d(dtype=wp.int32), switch_on: float, keep_on: float, lift: float,
                  error_out: wp.array2d(dtype=float)):
    """The expert's approach (``approach_errors``) aimed at the border point."""
    env = wp.tid()
    approach_errors(env, cutting_center(pose[env, 0]), border[env], ptsd[env, 0], rcm[env, 0], active[env, 0],
                    switch_on, keep_on, lift, error_out)


def run(cut_removal: str, num_envs: int, seed: int, device: str, rows_to_cut: int) -> dict:
    env = lapwarp.make("TissueDissection", num_envs=num_envs, device=device, seed=seed, cut_removal=cut_removal,
                       rows_to_cut=rows_to_cut, invalid_actions="zero")
    env.reset()
    expert = TissueDissectionExpert(env)  # for its PTSD step sizes and action clipping only
    rig = env.rig
    episode_return = torch.zeros(num_envs, device=env.device)
    finished = torch.zeros(num_envs, dtype=torch.bool, device=env.device)
    successes, returns, lengths = 0, 0.0, 0.0
    start = time.perf_counter()
    for step in range(env.cfg.max_episode_steps):
        launching.launch(follow_border, dim=num_envs,
                         inputs=[env.tissue.border, rig.pose, rig.rcm, rig.ptsd, rig.active, expert.switch_on,
                                 expert.keep_on, expert.lift], outputs=[expert.error], device=env.wp_device)
        _, reward, done, _ = env.step(expert.policy_actions(wp.to_torch(expert.error) / expert.step_size))
        episode_return += reward
        first = done.bool() & ~finished
        if first.any():
            successes += int(wp.to_torch(env.last_episode_success)[first].sum())
            returns += float(episode_return[first].sum())
            lengths += float(first.sum()) * (step + 1)
        episode_return[done.bool()] = 0.0
        finished |= first
        if finished.all():
            break
    env.close()
    episodes = int(finished.sum())
    return {"task": "TissueDissection", "policy": "border-point follower", "cut_removal": cut_removal,
            "rows_to_cut": rows_to_cut, "num_envs": num_envs, "seed": seed, "episodes": episodes,
            "successes": successes, "success_rate": successes / max(episodes, 1),
            "mean_return": returns / max(episodes, 1), "mean_length": lengths / max(episodes, 1),
            "seconds": time.perf_counter() - start}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--cut-removal", nargs="+", choices=["centroid", "touch"], default=["centroid", "touch"])
    parser.add_argument("--num-envs", type=int, default=16)
    parser.add_argument("--rows-to-cut", type=int, default=2)
    parser.add_argument("--seed", type=int, default=5)
    parser.add_argument("--device", default=default_device())
    parser.add_argument("--out", default=None, help="append one JSON line per cut rule to this file")
    args = parser.parse_args(argv)
    if args.num_envs < 1:
        parser.error(f"--num-envs must be positive, got {args.num_envs}")
    try:
        lapwarp.check_config("TissueDissection", rows_to_cut=args.rows_to_cut)
    except ValueError as exc:
        parser.error(str(exc))
    quiet_warp()
    records = [run(rule, args.num_envs, args.seed, args.device, args.rows_to_cut) for rule in args.cut_removal]
    emit_json_lines(args.out, records)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
