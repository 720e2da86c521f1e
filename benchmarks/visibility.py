"""Which objects a task's camera shows: the fraction of envs in whose image each visual object has a pixel.

    python benchmarks/visibility.py --task DeflectSpheres --set num_deflect_to_win=5 single_instrument=false \\
        --num-envs 256 --steps 0 20 --out visibility.jsonl

For a pixel policy without memory an object out of view does not exist: DeflectSpheres' left hook starts outside
the 64x64 image in about a third of the episodes (CPU, 256 envs, seed 1: visible in 66.8 % of the reset frames, the
right hook in 100 %), where sofa_env's camera and reset noise put it, so an actor that must deflect a red sphere
with it cannot see where the hook is. Per ``--steps`` value (random actions for that many steps after a reset) one
JSON line: per object (by name), the fraction of envs showing it, rendered at the task's ``image_shape`` (or
``--size``) with the segmentation output.
"""

from __future__ import annotations

import argparse

import torch
import warp as wp

import lapwarp
from lapwarp.cli import default_device, emit_json_lines, parse_overrides, quiet_warp, with_fixed
from lapwarp.scene_render import SceneRenderer


def visibility(task: str, overrides: dict, num_envs: int, steps: int, device: str, seed: int,
               size: int | None) -> dict:
    env = lapwarp.make(task, num_envs=num_envs, device=device, seed=seed, invalid_actions="zero", **overrides)
    env.reset()
    generator = torch.Generator(device=env.device).manual_seed(seed)
    for _ in range(steps):
        if env.is_discrete:
            actions = torch.randint(0, env.num_actions, (num_envs,), generator=generator, device=env.device)
        else:
            actions = torch.rand((num_envs, env.num_actions), generator=generator, device=env.device) * 2.0 - 1.0
        env.step(actions)
    height, width = (size, size) if size else tuple(env.cfg.image_shape)
    scene = env.visual_scene()
    camera = SceneRenderer(scene, num_envs, width, height, env.wp_device, outputs=("segmentation",))
    with env._torch_stream_scope():
        env.update_visuals()
        camera.render()
    seg = wp.to_torch(camera.segmentation) if isinstance(camera.segmentation, wp.array) else camera.segmentation
    seg = seg.reshape(num_envs, -1)
    shown: dict[str, float] = {}
    for obj in scene.objects:
        visible = (seg == obj.segmentation_id).any(dim=1)
        # objects may share an id (a hook's shaft and tip): the fraction is that of the id
        shown[obj.name] = float(visible.float().mean())
    env.close()
    return {"task": task, "overrides": overrides, "num_envs": num_envs, "steps_after_reset": steps,
            "image": [height, width], "seed": seed, "visible_fraction": shown}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--task", required=True, choices=lapwarp.list_tasks())
    parser.add_argument("--set", nargs="*", default=[], metavar="KEY=VALUE", help="config overrides (JSON values)")
    parser.add_argument("--num-envs", type=int, default=256)
    parser.add_argument("--steps", type=int, nargs="+", default=[0], help="random-action steps after the reset")
    parser.add_argument("--size", type=int, default=None, help="square image size (default: the task's image_shape)")
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--device", default=default_device())
    parser.add_argument("--out", default=None, help="append one JSON line per --steps value to this file")
    args = parser.parse_args(argv)
    if args.num_envs < 1 or min(args.steps) < 0 or (args.size is not None and args.size < 1):
        parser.error(f"--num-envs and --size must be positive and --steps non-negative, got {args.num_envs}, "
                     f"{args.size} and {args.steps}")
    try:
        overrides = parse_overrides(args.set)
        lapwarp.check_config(args.task, **with_fixed(overrides, "--set", seed=args.seed, invalid_actions="zero"))
    except ValueError as exc:
        parser.error(str(exc))
    quiet_warp()
    records = [visibility(args.task, overrides, args.num_envs, steps, args.device, args.seed, args.size)
               for steps in args.steps]
    emit_json_lines(args.out, records)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
