"""Env-step throughput of a task vs num_envs, random actions, written as JSON.

    python benchmarks/bench_env.py --task Reach --device cuda:0 --num-envs 1 64 1024 16384 65536 --out reach.json

``--policy expert`` times the task's scripted expert with each step (the regime where instruments cut and grasp).
``--policy replay`` times the same regime without the expert: the expert's actions are recorded first (untimed, in
one env), then replayed into a fresh env of the same seed, which the deterministic step takes through the same states
(exactly on the CPU; on CUDA up to float atomics' order); timing stops at the end of the recording
(``--replay-steps``).

Regime: env step only (physics + observations + rewards + dones + masked auto-resets, the whole
``env.step`` as rsl-rl calls it, including the returned clones and log tensors); no policy. Actions are
drawn once per benchmark into a pool of random batches and cycled, so action generation is not timed.
``--invalid-actions zero`` (default here) checks NaN actions on the device; ``raise`` adds the one host
sync per step that the default env config pays for its NaN check, and is reported separately with
``--both-nan-modes``.
"""

from __future__ import annotations

import argparse
import json
import platform
import shlex
import sys
import time
from pathlib import Path

import torch
import warp as wp

import lapwarp
import lapwarp.contact
from lapwarp import launching
from lapwarp.cli import default_device, non_negative_int, parse_overrides, positive_float, positive_int
from lapwarp.contact import ContactSystem
from lapwarp.experts import make_expert
from lapwarp.world import ROD_SOLVERS


def device_name(device: str) -> str:
    if device.startswith("cuda"):
        return torch.cuda.get_device_name(torch.device(device))
    return f"CPU ({platform.processor() or platform.machine()}), Warp CPU backend"


def sync(device: str) -> None:
    if device.startswith("cuda"):
        torch.cuda.synchronize(torch.device(device))


def contact_systems(env) -> list:
    """The env's contact systems (the World's solvers that have contact settings)."""
    return [solver for solver in env.world.solvers if hasattr(solver, "triangle_sweep")]


def apply_contact_settings(env, triangle_sweep: str | None = None, triangle_block_threads: int | None = None,
                           pose_per_step: bool | None = None, surface_bounds: str | None = None,
                           surface_bounds_lanes: int | None = None, report_forces: bool | None = None,
                           defer_surface_deltas: bool | None = None) -> None:
    """Set the contact systems' triangle sweep, the fused sweep's threads per env block, whether their shapes are
    posed once per step, how their deforming surfaces' boxes are formed, whether they sum contact forces and whether a
    surface's corrections wait for the next prediction launch (None: keep theirs), before the first step records the
    launches (and the env captures them)."""
    for contact in contact_systems(env):
        if triangle_sweep is not None:
            contact.triangle_sweep = triangle_sweep
        if triangle_block_threads is not None:
            contact.triangle_block_threads = triangle_block_threads
        if pose_per_step is not None:
            if not hasattr(contact, "pose_per_step"):  # an older lapwarp, timed beside this one
                raise ValueError("--pose-per-step: this lapwarp's contact systems pose their shapes every sweep")
            contact.pose_per_step = pose_per_step
        for name, value in (("surface_bounds", surface_bounds), ("surface_bounds_lanes", surface_bounds_lanes),
                            ("report_forces", report_forces), ("defer_surface_deltas", defer_surface_deltas)):
            if value is not None:
                if not hasattr(contact, name):  # an older lapwarp, timed beside this one
                    raise ValueError(f"{name}: this lapwarp's contact systems have no such setting")
                setattr(contact, name, value)


def parse_register_caps(items: list[str]) -> dict[str, int]:
    """``KERNEL=N`` items as ``{kernel function name: cap}``; a ``ValueError`` for a malformed item or cap (a name the
    step does not launch is caught when the world records its step)."""
    caps = {}
    for item in items:
        name, sep, value = item.partition("=")
        if not sep or not name or not value.strip().isdigit():
            raise ValueError(f"--max-registers takes KERNEL=N items, got {item!r}")
        caps[name] = int(value)
        launching.check_register_cap(caps[name])
    return caps


def record_expert_actions(env, steps: int) -> list[torch.Tensor]:
    """The scripted expert's actions over ``steps`` steps of ``env`` (which they advance), one tensor per step."""
    expert = make_expert(env)
    actions = []
    for _ in range(steps):
        actions.append(expert().clone())
        env.step(actions[-1])
    return actions


def bench_one(task: str, num_envs: int, device: str, seconds: float, invalid_actions: str, overrides: dict,
              policy: str = "random", tet_solver: str | None = None, cuda_graph: bool = True,
              triangle_sweep: str | None = None, triangle_block_threads: int | None = None,
              replay_steps: int = 600, max_registers: dict[str, int] | None = None, pcr_rows: int | None = None,
              rod_solver: str | None = None, lane_rows: int | None = None,
              surface_leaf_size: int | None = None, cull_groups: bool = True,
              pose_per_step: bool | None = None, rod_block_threads: int | None = None,
              predict_in_rod_sweep: bool | None = None, register_split: bool | None = None,
              contact_in_rod_launch: bool | None = None, surface_bounds: str | None = None,
              surface_bounds_lanes: int | None = None,
              report_forces: bool | None = None, defer_surface_deltas: bool | None = None) -> dict:
    def make_env():
        # the leaf size and the cull groups are read when the task finalizes its contact system, i.e. while the env is
        # built (an older lapwarp, timed beside this one, may have neither: it is left alone there)
        default_leaf_size = getattr(lapwarp.contact, "SURFACE_LEAF_SIZE", None)
        default_groups = getattr(lapwarp.contact, "CULL_GROUPS", None)
        if surface_leaf_size is not None:
            lapwarp.contact.SURFACE_LEAF_SIZE = surface_leaf_size
        if not cull_groups:
            if default_groups is None:
                raise ValueError("--no-cull-groups: this lapwarp has no cull groups")
            lapwarp.contact.CULL_GROUPS = False
        try:
            env = lapwarp.make(task, num_envs=num_envs, device=device, invalid_actions=invalid_actions,
                               use_cuda_graph=cuda_graph, **overrides)
        finally:
            if default_leaf_size is not None:
                lapwarp.contact.SURFACE_LEAF_SIZE = default_leaf_size
            if default_groups is not None:
                lapwarp.contact.CULL_GROUPS = default_groups
        if tet_solver is not None:
            env.world.tet_solver = tet_solver  # before the first step records (and the env captures) the launches
        # the task's own caps (ThreadInHole's lagged vertex sweep) stay unless named here
        env.world.max_registers = {**env.world.max_registers, **(max_registers or {})}
        if pcr_rows is not None:
            env.world.chain_pcr_rows = pcr_rows
        if lane_rows is not None:
            env.world.chain_lane_rows = lane_rows
        if rod_solver is not None:
            env.world.rod_solver = rod_solver
        if rod_block_threads is not None:
            env.world.rod_block_threads = rod_block_threads
        if predict_in_rod_sweep is not None:
            if not hasattr(env.world, "predict_in_rod_sweep"):  # an older lapwarp, timed beside this one
                raise ValueError("--predict-in-rod-sweep: this lapwarp predicts every substep in its own launch")
            env.world.predict_in_rod_sweep = predict_in_rod_sweep
        if register_split is not None:
            if not hasattr(env.world, "chain_register_split"):  # an older lapwarp, timed beside this one
                raise ValueError("--register-split: this lapwarp solves a chain with one thread")
            env.world.chain_register_split = register_split
        if contact_in_rod_launch is not None:
            if not hasattr(env.world, "contact_in_rod_launch"):  # an older lapwarp, timed beside this one
                raise ValueError("--contact-in-rod-launch: this lapwarp launches every substep's contact on its own")
            env.world.contact_in_rod_launch = contact_in_rod_launch
        apply_contact_settings(env, triangle_sweep, triangle_block_threads, pose_per_step, surface_bounds,
                               surface_bounds_lanes, report_forces, defer_surface_deltas)
        return env

    env = make_env()
    gen = torch.Generator(device=env.device).manual_seed(0)
    recorded = None
    if policy == "replay":
        recorded = record_expert_actions(env, replay_steps)
        env.close()
        env = make_env()  # same config and seed: the replayed actions take it through the expert's states
    if policy == "expert":
        # The scripted expert acts on the live state every step (its own device work is timed too): this is the
        # regime where instruments really cut, grasp and touch, and where cut envs are reset.
        expert = make_expert(env)
        pool = None
    elif policy == "replay":
        pool = None
    elif env.is_discrete:
        pool = [torch.randint(0, 2 * env.action_dim + 1, (num_envs,), device=env.device, generator=gen)
                for _ in range(8)]
    else:
        pool = [torch.rand(num_envs, env.num_actions, device=env.device, generator=gen) * 2 - 1 for _ in range(8)]

    def action(i: int):
        if recorded is not None:
            return recorded[i]
        return expert() if pool is None else pool[i % 8]
    warmup = 5
    for i in range(warmup):  # compile kernels, capture the CUDA graph, warm caches
        env.step(action(i))
    sync(env.device)
    # a replay ends with its recording: steps past it would no longer follow the expert's states
    available = len(recorded) - warmup if recorded is not None else None
    steps, elapsed = 0, 0.0
    batch = 10
    start = time.perf_counter()
    while elapsed < seconds and (available is None or steps < available):
        if available is not None:
            batch = min(batch, available - steps)
        for i in range(batch):
            env.step(action(warmup + steps + i))
        steps += batch
        sync(env.device)
        elapsed = time.perf_counter() - start
        batch = min(batch * 2, 1000)
    result = {
        "task": task, "num_envs": num_envs, "env_steps": steps * num_envs, "seconds": elapsed,
        "env_steps_per_s": steps * num_envs / elapsed, "step_ms": 1e3 * elapsed / steps,
        "invalid_actions": invalid_actions, "policy": policy,
        "replay_steps": len(recorded) if recorded is not None else None, "frame_skip": env.cfg.frame_skip,
        "time_step": env.cfg.time_step,
        "observation_type": env.cfg.observation_type, "cuda_graph": env._use_cuda_graph,
        "resolution": list(env.cfg.image_shape) if env.uses_images else None,
        "triangle_sweep": next((c.resolved_triangle_sweep() for c in contact_systems(env)), None),
        "triangle_block_threads": next((c.triangle_block_threads for c in contact_systems(env)), None),
        "surface_bounds": next((getattr(c, "surface_bounds", "separate") for c in contact_systems(env)), None),
        "surface_bounds_lanes": next((getattr(c, "surface_bounds_lanes", None) for c in contact_systems(env)), None),
        "report_forces": next((getattr(c, "report_forces", True) for c in contact_systems(env)), None),
        "defer_surface_deltas": next((getattr(c, "defer_surface_deltas", False) for c in contact_systems(env)), None),
        # (an older lapwarp, timed beside this one, has no clustered surfaces)
        "surface_leaf_size": next((getattr(c, "surface_leaf_size", None) for c in contact_systems(env)), None),
        "cull_groups": next((getattr(c, "cull_groups", None) for c in contact_systems(env)), None),
        "pose_per_step": next((getattr(c, "pose_per_step", None) for c in contact_systems(env)), None),
        "tet_solver": ("fused" if env.world.fused_tets else "colored") if env.world.model.tet_count else None,
        # (an older lapwarp, timed beside this one, has max_registers only)
        "max_registers": dict(getattr(env.world, "register_caps", env.world.max_registers)),
        "chain_solver": env.world.chain_solver,
        "rod_solver": env.world.rod_solver if env.world.model.segment_count else None,
        "rod_block_threads": env.world.rod_block_threads if env.world.model.segment_count else None,
        "predict_in_rod_sweep": (env.world._predicts_in_rod_sweep()
                                 if hasattr(env.world, "_predicts_in_rod_sweep") else None),
        "contact_in_rod_launch": (env.world._contact_in_rod_launch()
                                  if hasattr(env.world, "_contact_in_rod_launch") else None),
        "chain_register_split": (env.world.chain_register_split if env.world.chain_solver == "registers"
                                 and hasattr(env.world, "chain_register_split") else None),
        "chain_pcr_rows": env.world.chain_pcr_rows if env.world.chain_solver in ("pcr", "hybrid") else None,
        "chain_lane_rows": env.world.chain_lane_rows if env.world.chain_solver == "hybrid" else None,
    }
    env.close()
    return result


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--task", default="Reach", choices=lapwarp.list_tasks())
    parser.add_argument("--device", default=default_device())
    parser.add_argument("--num-envs", type=positive_int, nargs="+", default=[1, 16, 256, 4096, 16384, 65536])
    parser.add_argument("--seconds", type=positive_float, default=2.0, help="timed seconds per point")
    parser.add_argument("--invalid-actions", choices=["zero", "raise"], default="zero")
    parser.add_argument("--both-nan-modes", action="store_true", help="also time invalid_actions='raise'")
    parser.add_argument("--obs", choices=["STATE", "RGB", "RGBD", "DEPTH"], default="STATE")
    parser.add_argument("--image-size", type=positive_int, default=64, help="square image side for image observations")
    parser.add_argument("--set", nargs="*", default=[], metavar="KEY=VALUE",
                        help="extra config overrides, values parsed as JSON (e.g. sphere_radius=0.02)")
    parser.add_argument("--policy", choices=["random", "expert", "replay"], default="random",
                        help="random actions from a pre-drawn pool, the scripted expert (timed with the step), or the "
                             "expert's recorded actions replayed (the expert's regime, the step alone timed)")
    parser.add_argument("--replay-steps", type=positive_int, default=600,
                        help="--policy replay: expert steps recorded (timing stops after them, 5 warm-up steps first)")
    parser.add_argument("--tet-solver", choices=["auto", "colored", "fused"], default=None,
                        help="the world's tet sweep (default: the world's own choice)")
    parser.add_argument("--triangle-sweep", choices=ContactSystem.TRIANGLE_SWEEPS, default=None,
                        help="the contact system's triangle sweep (default: its own)")
    parser.add_argument("--triangle-block-threads", type=positive_int, default=None,
                        help="threads per env block of the fused triangle sweep (default: the contact system's own)")
    parser.add_argument("--no-cull-groups", action="store_true",
                        help="every contact shape culled alone (lapwarp.contact.CULL_GROUPS off while the env is "
                             "built): to time the cull groups against their absence")
    parser.add_argument("--pose-per-step", choices=["on", "off"], default=None,
                        help="the contact systems' shapes posed for every substep in one launch per step, or a launch "
                             "per sweep (ContactSystem.pose_per_step; default: theirs)")
    parser.add_argument("--surface-bounds", choices=list(ContactSystem.SURFACE_BOUNDS), default=None,
                        help="the deforming surfaces' leaf and super-leaf boxes in two launches per sweep or in one, a "
                             "block per env (ContactSystem.surface_bounds; default: theirs)")
    parser.add_argument("--surface-bounds-lanes", type=positive_int, default=None,
                        help="threads of the fused surface bounds' block per env (default: the contact system's)")
    parser.add_argument("--contact-forces", choices=["on", "off"], default=None,
                        help="the contact systems sum each pair's force over the step (ContactSystem.report_forces; "
                             "default: theirs)")
    parser.add_argument("--defer-surface-deltas", choices=["on", "off"], default=None,
                        help="a deforming surface's corrections applied by the next substep's prediction launch where "
                             "the World can (ContactSystem.defer_surface_deltas; default: theirs)")
    parser.add_argument("--surface-leaf-size", type=positive_int, default=None,
                        help="triangles per leaf of deforming contact surfaces' clustering (default: "
                             "lapwarp.contact.SURFACE_LEAF_SIZE)")
    parser.add_argument("--max-registers", nargs="*", default=[], metavar="KERNEL=N",
                        help="register caps of the world step's kernels by function name, e.g. "
                             "collide_triangle_colors=64 (launching.register_capped; CUDA only has an effect)")
    parser.add_argument("--pcr-rows", type=non_negative_int, default=None,
                        help="rows per pack of the 'pcr' and 'hybrid' chain solves (--set chain_solver=pcr; 0: the "
                             "world's default, 1: a chain per block)")
    parser.add_argument("--lane-rows", type=positive_int, default=None,
                        help="rows per lane of the 'hybrid' chain solve (--set chain_solver=hybrid; default: the "
                             "world's)")
    parser.add_argument("--rod-solver", choices=list(ROD_SOLVERS), default=None,
                        help="the world's rod sweep: one launch per colour or all colours in one (default: its own)")
    parser.add_argument("--rod-block-threads", type=positive_int, default=None,
                        help="lanes of the fused rod sweep's block per env (world.rod_block_threads; default: the "
                             "world's)")
    parser.add_argument("--predict-in-rod-sweep", choices=["on", "off"], default=None,
                        help="a rods-only world's substep prediction in its fused rod launch or its own "
                             "(world.predict_in_rod_sweep; default: the world's)")
    parser.add_argument("--contact-in-rod-launch", choices=["on", "off"], default=None,
                        help="a rods-only world's substep particle contact at the start of the next substep's rod "
                             "launch or in its own (world.contact_in_rod_launch; default: the world's)")
    parser.add_argument("--register-split", choices=["on", "off"], default=None,
                        help="the register chain solve with two threads per chain where a family's chains are all of "
                             "one length (world.chain_register_split; default: the world's)")
    parser.add_argument("--no-graph", action="store_true",
                        help="launch the step's kernels one by one instead of replaying a CUDA graph")
    parser.add_argument("--out", default=None, help="JSON output path")
    parser.add_argument("--variant", action="append", default=[], metavar="NAME=ARGS",
                        help="time the command's settings plus ARGS (more options of this script) as NAME, each "
                             "variant in turn in this process (one start-up and one compile of the shared kernels for "
                             "all); with --out each goes to NAME.json beside it and --out holds them all")
    args = parser.parse_args(argv)
    if args.variant:
        return run_variants(parser, list(sys.argv[1:] if argv is None else argv), args)

    wp.config.log_level = max(wp.config.log_level, wp.LOG_WARNING)  # no per-module load lines
    wp.config.enable_cpu_blocks = True  # the 'hybrid' chain solve's lanes as Warp's fibers on a CPU
    if args.policy == "replay" and args.replay_steps <= 5:
        parser.error(f"--replay-steps must exceed the 5 warm-up steps, got {args.replay_steps}")
    modes = ["zero", "raise"] if args.both_nan_modes else [args.invalid_actions]
    overrides = {"observation_type": args.obs}
    if args.obs != "STATE":
        overrides["image_shape"] = (args.image_size, args.image_size)
    try:  # every point's configuration before the first one is timed
        max_registers = parse_register_caps(args.max_registers)
        overrides.update(parse_overrides(args.set))
        for mode in modes:
            lapwarp.check_config(args.task, invalid_actions=mode, **overrides)
    except ValueError as exc:
        parser.error(str(exc))
    results = []
    print(f"{'task':<10} {'num_envs':>9} {'nan mode':>8} {'env-steps/s':>14} {'step ms':>9}")
    for n in args.num_envs:
        for mode in modes:
            r = bench_one(args.task, n, args.device, args.seconds, mode, overrides, args.policy, args.tet_solver,
                          cuda_graph=not args.no_graph, triangle_sweep=args.triangle_sweep,
                          triangle_block_threads=args.triangle_block_threads,
                          replay_steps=args.replay_steps, max_registers=max_registers, pcr_rows=args.pcr_rows,
                          rod_solver=args.rod_solver, lane_rows=args.lane_rows,
                          surface_leaf_size=args.surface_leaf_size, cull_groups=not args.no_cull_groups,
                          pose_per_step=None if args.pose_per_step is None else args.pose_per_step == "on",
                          rod_block_threads=args.rod_block_threads,
                          predict_in_rod_sweep=(None if args.predict_in_rod_sweep is None
                                                else args.predict_in_rod_sweep == "on"),
                          register_split=None if args.register_split is None else args.register_split == "on",
                          contact_in_rod_launch=(None if args.contact_in_rod_launch is None
                                                 else args.contact_in_rod_launch == "on"),
                          surface_bounds=args.surface_bounds, surface_bounds_lanes=args.surface_bounds_lanes,
                          report_forces=None if args.contact_forces is None else args.contact_forces == "on",
                          defer_surface_deltas=(None if args.defer_surface_deltas is None
                                                else args.defer_surface_deltas == "on"))
            results.append(r)
            print(f"{r['task']:<10} {n:>9} {mode:>8} {r['env_steps_per_s']:>14,.0f} {r['step_ms']:>9.3f}", flush=True)
    regime = "the expert's recorded actions replayed" if args.policy == "replay" else f"{args.policy} actions"
    report = {"benchmark": "env_step", "regime": f"env step only, {regime}", "device": args.device,
              "device_name": device_name(args.device), "warp": wp.__version__, "torch": torch.__version__,
              "config_overrides": parse_overrides(args.set), "results": results}
    if args.out:
        with open(args.out, "w") as f:
            json.dump(report, f, indent=2)
    return 0


def run_variants(parser: argparse.ArgumentParser, argv: list[str], args: argparse.Namespace) -> int:
    """``--variant NAME=ARGS`` items: the command line without them (and without ``--out``) plus each variant's
    ``ARGS``, timed one after another by :func:`main` in this process; every variant's arguments are parsed before the
    first is timed, so a bad one fails at once. Prints ``variant NAME: <env-steps/s> <ms per step>`` per variant."""
    base, skip = [], False
    for item in argv:
        if skip:
            skip = False
        elif item in ("--variant", "--out"):
            skip = True
        elif not item.startswith(("--variant=", "--out=")):
            base.append(item)
    out = Path(args.out) if args.out else None
    runs = []
    for item in args.variant:
        name, sep, extra = item.partition("=")
        if not sep or not name or not all(c.isalnum() or c in "._-" for c in name):
            parser.error(f"--variant takes NAME=ARGS with a NAME of letters, digits, '.', '_' and '-', got {item!r}")
        sub = [*base, *shlex.split(extra)]
        if "--variant" in sub or any(a.startswith("--variant=") for a in sub):
            parser.error(f"--variant {name}: a variant cannot name variants")
        if out is not None:
            sub += ["--out", str(out.with_name(f"{name}.json"))]
        parser.parse_args(sub)  # exits with the parser's message on a bad variant, before anything is timed
        runs.append((name, sub))
    if len({name for name, _ in runs}) != len(runs):
        parser.error("--variant names must differ")
    summary = {}
    for name, sub in runs:
        print(f"== variant {name}: {shlex.join(sub)}", flush=True)
        main(sub)
        if out is not None:
            summary[name] = json.loads(out.with_name(f"{name}.json").read_text())
            r = summary[name]["results"][-1]
            print(f"variant {name}: {r['env_steps_per_s']:,.0f} env-steps/s {r['step_ms']:.3f} ms", flush=True)
    if out is not None:
        out.write_text(json.dumps({"benchmark": "env_step_variants", "variants": summary}, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
