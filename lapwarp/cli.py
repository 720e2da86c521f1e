"""The ``lapwarp`` command line: list tasks, run a policy on a batch of envs, benchmark env steps.

    lapwarp list
    lapwarp run Reach --num-envs 16 --steps 300 --policy expert --save-images reach.png --usd reach.usda
    lapwarp run Reach --num-envs 16 --steps 300 --policy expert --video reach.mp4 --image-size 128
    lapwarp bench Reach --device cuda:0 --num-envs 1024 16384

``run`` prints a progress bar (on a terminal) and a summary table: episodes finished, success rate, mean
return and episode length of the finished episodes, env-steps/s, and what was written (USD, PNG grid, MP4 video
of the first ``--video-envs`` envs, one frame per step). Usage errors and invalid settings (unknown
task, unknown config key, unsupported observation type) print one ``lapwarp: error: ...`` line and exit with
status 2; ``main`` returns the exit status instead of raising, so it can be called in-process.
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import math
import sys
import time
from pathlib import Path
from typing import Any, TextIO

import lapwarp
from lapwarp.output_paths import check_output_path

USAGE_ERROR = 2  # argparse's exit status for bad arguments; used for invalid settings too
RUN_ERROR = 1
USD_ENVS = 4  # ``--usd`` records envs 0..min(num_envs, USD_ENVS) - 1
IMAGE_ENVS = 64  # ``--save-images`` tiles at most this many envs (the first ones), so the PNG stays viewable
VIDEO_ENVS = 16  # default of ``--video-envs``: envs tiled in each ``--video`` frame
VIDEO_SIZE = 256  # default tile size of ``--video`` without ``--image-size``
BENCH_SCRIPT = Path(__file__).resolve().parent.parent / "benchmarks" / "bench_env.py"


class CliError(Exception):
    """An error reported as one ``lapwarp: error: ...`` line with an exit status (no traceback)."""

    def __init__(self, message: str, status: int = USAGE_ERROR):
        super().__init__(message)
        self.status = status


# ---------------------------------------------------------------------------- helpers
class ProgressBar:
    """A one-line ``\\r`` progress bar; draws at most every ``interval`` seconds and only when enabled.

    Args:
        total: number of units (env steps) of the run.
        stream: where to draw (stderr, so stdout keeps only the results).
        enabled: draw at all (the CLI enables it on terminals, or with ``--progress``).
        interval: minimum seconds between redraws, so drawing never slows down a fast run.
        width: characters of the bar itself.
    """

    def __init__(self, total: int, stream: TextIO, enabled: bool, interval: float = 0.1, width: int = 30):
        self.total = max(int(total), 1)
        self.stream = stream
        self.enabled = enabled
        self.interval = interval
        self.width = width
        self.start = time.perf_counter()
        self._last_draw = -float("inf")
        self._drawn = False
        self._line_length = 0

    def update(self, done: int, note: str = "", force: bool = False) -> None:
        """Redraw with ``done`` of ``total`` units finished and a short ``note`` after the bar."""
        if not self.enabled:
            return
        now = time.perf_counter()
        if not force and now - self._last_draw < self.interval:
            return
        self._last_draw = now
        frac = min(done / self.total, 1.0)
        filled = int(round(frac * self.width))
        bar = "#" * filled + "." * (self.width - filled)
        line = f"[{bar}] {done}/{self.total} {100 * frac:5.1f}% {now - self.start:6.1f}s {note}".rstrip()
        # pad over the end of a longer previous line: \r only moves the cursor back, it does not clear
        self.stream.write("\r" + line.ljust(self._line_length))
        self._line_length = len(line)
        self.stream.flush()
        self._drawn = True

    def close(self) -> None:
        """End the bar's line so later output starts on a fresh line."""
        if self._drawn:
            self.stream.write("\n")
            self.stream.flush()


def format_table(rows: list[list[str]], header: list[str] | None = None) -> str:
    """Columns separated by two spaces; numeric columns right-aligned, text columns left-aligned."""
    table = ([header] if header else []) + rows
    widths = [max(len(r[c]) for r in table) for c in range(len(table[0]))]
    numeric = [all(_is_number(r[c]) for r in rows) for c in range(len(widths))]
    lines = []
    for i, row in enumerate(table):
        cells = [cell.rjust(w) if num else cell.ljust(w) for cell, w, num in zip(row, widths, numeric, strict=True)]
        lines.append("  ".join(cells).rstrip())
        if header and i == 0:
            lines.append("  ".join("-" * w for w in widths))
    return "\n".join(lines)


def _is_number(text: str) -> bool:
    try:
        float(text.replace(",", ""))
    except ValueError:
        return False
    return True


def parse_overrides(items: list[str]) -> dict[str, Any]:
    """``KEY=VALUE`` strings -> config overrides; values are JSON when they parse (``0.02``, ``[32, 32]``,
    ``true``), else plain strings (``DISCRETE``)."""
    overrides: dict[str, Any] = {}
    for item in items:
        key, sep, value = item.partition("=")
        if not sep or not key:
            raise CliError(f"--set expects KEY=VALUE, got {item!r}")
        try:
            overrides[key] = json.loads(value)
        except json.JSONDecodeError:
            overrides[key] = value
        if isinstance(overrides[key], list):  # JSON has no tuples; config fields such as image_shape are tuples
            overrides[key] = tuple(overrides[key])
    return overrides


def with_fixed(overrides: dict[str, Any], option: str, **fixed: Any) -> dict[str, Any]:
    """``overrides`` plus the settings a script sets itself (``fixed``); a ``ValueError`` naming ``option`` if the
    overrides name one of them (passed to ``make`` beside them they were a ``TypeError``)."""
    clash = sorted(set(overrides) & set(fixed))
    if clash:
        raise ValueError(f"{option} cannot set {clash}: the script sets them itself")
    return {**overrides, **fixed}


def default_device() -> str:
    import torch

    return "cuda:0" if torch.cuda.is_available() else "cpu"


def positive_int(text: str) -> int:
    """``argparse`` type of counts (envs, steps, iterations): an integer >= 1."""
    return _bounded(text, int, "a positive integer", lambda v: v >= 1)


def non_negative_int(text: str) -> int:
    """``argparse`` type of counts that may be zero: an integer >= 0."""
    return _bounded(text, int, "a non-negative integer", lambda v: v >= 0)


def positive_float(text: str) -> float:
    """``argparse`` type of durations and budgets: a finite number > 0 (``1e7`` is accepted)."""
    return _bounded(text, float, "a positive number", lambda v: math.isfinite(v) and v > 0)


def _bounded(text: str, kind: type, what: str, accept) -> Any:
    try:
        value = kind(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected {what}, got {text!r}") from None
    if not accept(value):
        raise argparse.ArgumentTypeError(f"expected {what}, got {value}")
    return value


def append_json_lines(path: str | None, records: list[dict]) -> None:
    """Append one JSON line per record to ``path`` (the benchmark scripts' ``--out``; nothing when it is None)."""
    if path:
        with open(path, "a") as f:
            f.writelines(json.dumps(r) + "\n" for r in records)


def emit_json_lines(path: str | None, records: list[dict]) -> None:
    """Print one JSON line per record and append them to ``path`` (``append_json_lines``)."""
    for record in records:
        print(json.dumps(record), flush=True)
    append_json_lines(path, records)


def quiet_warp() -> None:
    import warp as wp

    # Warp's init banner and per-module load lines would bury the CLI's own output; keep its warnings.
    if hasattr(wp, "LOG_WARNING"):
        wp.config.log_level = max(wp.config.log_level, wp.LOG_WARNING)
    else:  # Warp releases before the logging module
        wp.config.quiet = True


# ---------------------------------------------------------------------------- list
def cmd_list(args: argparse.Namespace, out: TextIO) -> int:
    """Table of the registered tasks with their observation and action sizes (from a 1-env CPU instance)."""
    from lapwarp.registry import task_class

    quiet_warp()
    rows = []
    for name in lapwarp.list_tasks():
        env = lapwarp.make(name, num_envs=1, device="cpu")
        cls = task_class(name)
        rows.append([name, str(env.observation_dim), ",".join(cls.supported_observations),
                     f"Box(-1, 1, ({env.action_dim},))", f"Discrete({2 * env.action_dim + 1})"])
        env.close()
    out.write(format_table(rows, ["task", "obs size (STATE)", "observation types", "continuous actions",
                                  "discrete actions"]) + "\n")
    return 0


# ---------------------------------------------------------------------------- run
def _make_policy(env, name: str, seed: int):
    import torch

    if name == "expert":
        from lapwarp.experts import make_expert

        expert = make_expert(env)
        return lambda obs: expert(obs)
    gen = torch.Generator(device=env.device).manual_seed(seed)
    if env.is_discrete:
        count = 2 * env.action_dim + 1  # +-e_i for every axis, then the no-op (README, "Actions")
        return lambda obs: torch.randint(0, count, (env.num_envs,), device=env.device, generator=gen)
    shape = (env.num_envs, env.num_actions)
    return lambda obs: torch.rand(shape, device=env.device, generator=gen) * 2.0 - 1.0


def cmd_run(args: argparse.Namespace, out: TextIO, err: TextIO) -> int:
    """Build the env, run ``--steps`` steps of the policy, print a summary; optionally save images / USD / a video."""
    import torch
    import warp as wp

    quiet_warp()
    overrides = parse_overrides(args.set)
    overrides.setdefault("observation_type", args.obs.upper())
    overrides.setdefault("seed", args.seed)
    if args.image_size is not None and overrides["observation_type"] != "STATE":
        overrides.setdefault("image_shape", (args.image_size, args.image_size))
    save_images = Path(args.save_images) if args.save_images else None
    if save_images is not None and save_images.suffix.lower() != ".png":
        raise CliError(f"--save-images writes a PNG; give a path ending in .png, got {args.save_images!r}")
    if save_images is not None:
        from lapwarp.imaging import _pil_image

        try:  # Pillow writes the PNG: say so before the run, not after it
            _pil_image()
        except ImportError as exc:
            raise CliError(str(exc), RUN_ERROR) from None
    if args.usd and Path(args.usd).suffix not in (".usda", ".usd", ".usdc"):
        raise CliError(f"--usd path must end in .usda, .usd or .usdc, got {args.usd!r}")
    video = Path(args.video) if args.video else None
    if video is not None:
        if video.suffix.lower() != ".mp4":
            raise CliError(f"--video writes an MP4; give a path ending in .mp4, got {args.video!r}")
        try:
            from lapwarp.video import check_video_support

            check_video_support()
        except ImportError as exc:
            raise CliError(str(exc), RUN_ERROR) from None
    try:  # before the env is built: a long run must not end in an unwritable path
        for option, path in (("--save-images", save_images), ("--usd", args.usd), ("--video", video)):
            if path:
                check_output_path(path, option, make_dirs=args.mkdir)
    except ValueError as exc:
        raise CliError(f"{exc}{'' if args.mkdir else ' (--mkdir creates missing folders)'}") from None
    try:
        env = lapwarp.make(args.task, num_envs=args.num_envs, device=args.device, **overrides)
        policy = _make_policy(env, args.policy, args.seed)
    except ValueError as exc:
        raise CliError(str(exc)) from None

    recorder = None
    if args.usd:
        try:
            from lapwarp.usd import UsdRecorder

            recorder = UsdRecorder(env, args.usd, env_ids=range(min(env.num_envs, USD_ENVS)), make_dirs=args.mkdir)
        except ImportError as exc:
            raise CliError(str(exc), RUN_ERROR) from None
        except ValueError as exc:
            raise CliError(str(exc)) from None
        recorder.record()
    video_recorder = None
    if video is not None:
        from lapwarp.video import EnvVideoRecorder

        try:
            video_recorder = EnvVideoRecorder(env, video, tile_size=args.image_size or VIDEO_SIZE,
                                              max_tiles=args.video_envs)
        except ValueError as exc:
            raise CliError(str(exc)) from None

    obs = env.get_observations()
    # Episode statistics accumulate on the device (no host sync per step); read at the end.
    last_success = wp.to_torch(env.last_episode_success)
    last_return = wp.to_torch(env.last_episode_return)
    last_length = wp.to_torch(env.last_episode_length)
    episodes = torch.zeros((), dtype=torch.long, device=env.device)
    successes = torch.zeros((), dtype=torch.long, device=env.device)
    return_sum = torch.zeros((), dtype=torch.float64, device=env.device)
    length_sum = torch.zeros((), dtype=torch.long, device=env.device)
    reward_sum = torch.zeros((), dtype=torch.float64, device=env.device)
    overflow_sum = torch.zeros((), dtype=torch.float64, device=env.device)  # env-steps with a full contact buffer

    progress = ProgressBar(args.steps, err, enabled=args.progress if args.progress is not None else err.isatty())
    start = time.perf_counter()
    try:
        for step in range(args.steps):
            obs, rewards, dones, extras = env.step(policy(obs))
            episodes += dones.sum()
            successes += (last_success * dones).sum()
            return_sum += (last_return * dones).sum()
            length_sum += (last_length * dones).sum()
            reward_sum += rewards.sum()
            if "/contact/overflow_fraction" in extras["log"]:
                overflow_sum += extras["log"]["/contact/overflow_fraction"] * env.num_envs
            if recorder is not None:
                recorder.record()
            if video_recorder is not None:
                video_recorder.add_step(rewards, dones)
            if progress.enabled:
                # on a GPU this is the launch rate (no sync per step); the summary's figure is synchronised
                elapsed = time.perf_counter() - start
                progress.update(step + 1, f"{(step + 1) * env.num_envs / max(elapsed, 1e-9):,.0f} env-steps/s")
    except KeyboardInterrupt:
        progress.close()
        if recorder is not None:  # keep what was recorded: the file is written only on close
            err.write(f"lapwarp: saved {recorder.num_frames} time samples to {recorder.close()}\n")
        if video_recorder is not None and video_recorder.close():  # the frames so far make a playable file
            err.write(f"lapwarp: saved {video_recorder.num_frames} video frames to {video}\n")
        raise
    if env.device.startswith("cuda"):
        torch.cuda.synchronize(env.device)
    elapsed = time.perf_counter() - start
    progress.update(args.steps, f"{args.steps * env.num_envs / max(elapsed, 1e-9):,.0f} env-steps/s", force=True)
    progress.close()

    n_episodes = int(episodes)
    env_steps = args.steps * env.num_envs
    recording = " and ".join(name for name, on in (("USD", recorder), ("video", video_recorder)) if on is not None)
    rows = [
        ["task", args.task],
        ["envs / device", f"{env.num_envs} / {env.device}"],
        ["policy", args.policy],
        ["observation", overrides["observation_type"]],
        ["env steps", f"{args.steps} x {env.num_envs} = {env_steps}"],
        ["episodes finished", str(n_episodes)],
        ["success rate", f"{100.0 * int(successes) / n_episodes:.1f} %" if n_episodes else "n/a (no episode ended)"],
        ["mean return", f"{float(return_sum) / n_episodes:.3f}" if n_episodes else "n/a"],
        ["mean episode length", f"{int(length_sum) / n_episodes:.1f}" if n_episodes else "n/a"],
        ["mean reward per step", f"{float(reward_sum) / env_steps:.4f}" if env_steps else "n/a"],
        ["env-steps/s", f"{env_steps / elapsed:,.0f}" + (f" (with {recording} recording)" if recording else "")
         if env_steps else "n/a"],
    ]
    if "/contact/overflow_fraction" in env.log_keys:
        rows.append(["contact overflows", f"{round(float(overflow_sum))} env-steps lost contact records (capacity "
                     "is a task config value)" if float(overflow_sum) > 0 else "none"])
    if recorder is not None:
        path = recorder.close()
        rows.append(["usd", f"{path} (envs 0..{len(recorder.env_ids) - 1}, {recorder.num_frames} time samples)"])
    if video_recorder is not None:
        frames, writer = video_recorder.close(), video_recorder.writer
        size = video_recorder.tile_size
        rows.append(["video", f"{video} ({frames} frames at {writer.fps:g} fps, {video_recorder.num_tiles} envs "
                              f"tiled, {size}x{size} each)" if frames else f"none written ({args.steps} steps)"])
    if save_images is not None:
        rows.append(["images", _save_images(env, save_images, args.image_size or 128)])
    out.write(format_table(rows) + "\n")
    env.close()
    return 0


def _save_images(env, path: Path, size: int) -> str:
    """Render every env once with the batched rasteriser and write one PNG grid."""
    try:
        from lapwarp.imaging import save_image_grid
    except ImportError as exc:
        raise CliError(f"rendering is not available: {exc}", RUN_ERROR) from None
    if not hasattr(env, "render_rgb"):
        raise CliError(f"rendering is not available for {type(env).__name__}", RUN_ERROR)
    images = env.render_rgb(size, size)[:IMAGE_ENVS]
    grid = save_image_grid(images, path)
    return f"{path} ({len(images)} envs, {size}x{size} each, grid {grid.shape[1]}x{grid.shape[0]})"


# ---------------------------------------------------------------------------- bench
def _load_bench_module():
    if not BENCH_SCRIPT.is_file():
        raise CliError(f"{BENCH_SCRIPT} is missing: 'lapwarp bench' runs benchmarks/bench_env.py from the source "
                       "tree (git clone the repository and pip install -e .)", RUN_ERROR)
    # benchmarks/ is a folder of scripts, not a package: import the file by its path.
    spec = importlib.util.spec_from_file_location("lapwarp_bench_env", BENCH_SCRIPT)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def cmd_bench(args: argparse.Namespace, out: TextIO) -> int:
    """Run benchmarks/bench_env.py for TASK; options after TASK go to it unchanged."""
    if args.task not in lapwarp.list_tasks():
        raise CliError(f"unknown task {args.task!r}; available tasks: {lapwarp.list_tasks()}")
    quiet_warp()
    bench = _load_bench_module()
    try:
        return int(bench.main(["--task", args.task, *args.bench_args]) or 0)
    except SystemExit as exc:  # the script's own argparse errors and --help
        return exc.code if isinstance(exc.code, int) else USAGE_ERROR
    except ValueError as exc:
        raise CliError(str(exc)) from None


# ---------------------------------------------------------------------------- parser and entry point
def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="lapwarp", description="LapGym's surgical RL environments, batched in Warp.",
                                     epilog="'lapwarp COMMAND --help' describes each command.")
    parser.add_argument("--version", action="version", version=f"lapwarp {lapwarp.__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")

    sub.add_parser("list", help="tasks with their observation and action sizes",
                   description="List the tasks with their observation and action sizes (builds a 1-env CPU "
                               "instance of each).")

    run = sub.add_parser("run", help="run a random or expert policy on a batch of envs",
                         description="Run a policy on a batch of envs and print a summary table.")
    run.add_argument("task", help="task name (see 'lapwarp list')")
    run.add_argument("--num-envs", type=positive_int, default=16, help="parallel envs (default 16)")
    run.add_argument("--steps", type=non_negative_int, default=200, help="env steps to run (default 200)")
    run.add_argument("--policy", choices=["random", "expert"], default="random",
                     help="uniform random actions on the device, or the task's scripted expert (default random)")
    run.add_argument("--obs", type=str.lower, choices=["state", "rgb", "rgbd", "depth"], default="state",
                     help="observation type (default state)")
    run.add_argument("--device", default=None, help="Warp/torch device, cpu or cuda:N (default: cuda:0 if torch "
                                                    "sees a GPU, else cpu)")
    run.add_argument("--seed", type=int, default=0, help="seed of the env RNG and the random policy (default 0)")
    run.add_argument("--image-size", type=positive_int, default=None,
                     help="square image side in pixels for image observations (default: the task's), for "
                          f"--save-images (default 128) and the tiles of --video (default {VIDEO_SIZE})")
    run.add_argument("--save-images", metavar="PNG", default=None,
                     help=f"after the run, render the envs (the first {IMAGE_ENVS} at most) and save the images "
                          "as one PNG grid")
    run.add_argument("--usd", metavar="FILE", default=None,
                     help=f"record envs 0..{USD_ENVS - 1} (at most) to a .usda/.usd/.usdc file, one time sample "
                          "per step")
    run.add_argument("--video", metavar="MP4", default=None,
                     help="record an MP4 video, one frame per step: the first --video-envs envs tiled, labelled with "
                          "their running return and a green border on success (needs pip install "
                          "\"lapwarp[video]\"; renders every env each step, so keep --num-envs small)")
    run.add_argument("--video-envs", type=positive_int, default=VIDEO_ENVS, metavar="N",
                     help=f"envs tiled in each --video frame (the first ones; default {VIDEO_ENVS})")
    run.add_argument("--mkdir", action="store_true",
                     help="create missing folders of the --usd, --save-images and --video paths (otherwise an error "
                          "before the run)")
    run.add_argument("--set", nargs="*", default=[], metavar="KEY=VALUE",
                     help="config overrides, values parsed as JSON (e.g. sphere_radius=0.02 action_type=DISCRETE)")
    progress = run.add_mutually_exclusive_group()
    progress.add_argument("--progress", dest="progress", action="store_true", default=None,
                          help="always draw the progress bar (default: only on a terminal)")
    progress.add_argument("--no-progress", dest="progress", action="store_false", help="never draw it")

    bench = sub.add_parser("bench", help="env-step throughput (wraps benchmarks/bench_env.py)",
                           description="Measure env-steps/s of TASK with benchmarks/bench_env.py. Options after "
                                       "TASK are passed to the script unchanged; 'lapwarp bench Reach --help' "
                                       "lists them (--device, --num-envs N [N ...], --seconds, --obs, --out, ...).")
    bench.add_argument("task", help="task name (see 'lapwarp list')")
    bench.add_argument("bench_args", nargs=argparse.REMAINDER, help="options for benchmarks/bench_env.py")
    return parser


def main(argv: list[str] | None = None) -> int:
    """Entry point of the ``lapwarp`` console script; returns the exit status instead of raising ``SystemExit``.

    Results go to stdout; errors and the progress bar to stderr.

    Args:
        argv: arguments without the program name (default: ``sys.argv[1:]``).
    """
    out, err = sys.stdout, sys.stderr
    parser = build_parser()
    try:
        args = parser.parse_args(argv)
    except SystemExit as exc:  # argparse already printed usage and message (or help / version, status 0)
        return exc.code if isinstance(exc.code, int) else USAGE_ERROR
    if args.command is None:
        parser.print_help(err)
        return USAGE_ERROR
    try:
        if args.command == "list":
            return cmd_list(args, out)
        if args.command == "run":
            if args.device is None:
                args.device = default_device()
            return cmd_run(args, out, err)
        return cmd_bench(args, out)
    except CliError as exc:
        err.write(f"lapwarp: error: {exc}\n")
        return exc.status
    except KeyboardInterrupt:
        err.write("\nlapwarp: interrupted\n")
        return 130


if __name__ == "__main__":
    raise SystemExit(main())
