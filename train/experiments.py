"""The paper's PPO table as named experiments: run every row over several seeds, record, summarise and plot (#19).

    python train/experiments.py --list
    python train/experiments.py spatial-state --seeds 0 1 2                # one GPU, runs one after another
    python train/experiments.py spatial-rgb --seeds 0 1 2 --devices cuda:0 cuda:1   # one run per GPU at a time
    python train/experiments.py spatial-state --rows reach-state --summarize-only   # re-read the files, re-plot
    python train/experiments.py --queue jobs.txt --devices cuda:0 cuda:1 cuda:2 cuda:3  # (experiment, row, seeds)

An experiment is a list of rows (``train/experiment_rows.py``, the registry ``EXPERIMENTS``); a row is one
configuration of the paper's learning results (task, the config values that define it, observation type, iterations,
the paper's final success). Each (row, seed) is one ``train/ppo.py`` process, so runs are isolated, can use
``--distributed`` (``--nproc-per-run``) and can run side by side on several GPUs (``--devices``). Files, under
``--out`` (``benchmarks/results/learning``):

    <experiment>/<row>/seed<k>.csv    per iteration: env_steps, wall_s, success (training), mean_return, reward/<term>
    <experiment>/<row>/seed<k>.json   final: evaluation success (deterministic policy; ``sampled_success`` with
                                      actions sampled as in training), how the failed episodes ended
                                      (``evaluation``, ``sampled_evaluation``), env-steps, times, device
    <experiment>/<row>/seed<k>.log    the run's console output
    <experiment>/summary.csv          one line per row (columns ``SUMMARY_COLUMNS``)
    <experiment>/<row>.png            success against env-steps and against wall time, the paper's value dashed

The paper's values are read from its text (task-cards §13; its figures are not in our copy): "solved" is entered as
1.0, "fails" as 0.0, and rows whose value the text does not give have none.
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import statistics
import subprocess
import sys
import textwrap
import time
from pathlib import Path
from typing import Any

from experiment_rows import EXPERIMENTS, Experiment, Row, set_value

ROOT = Path(__file__).resolve().parents[1]
PPO_SCRIPT = ROOT / "train" / "ppo.py"
#: ``ppo.py --compile``'s modes (ppo.COMPILE_MODES; not imported: this runner stays free of torch and Warp, and a test
#: keeps the two equal)
COMPILE_MODES = ("default", "reduce-overhead", "max-autotune", "max-autotune-no-cudagraphs")
DEFAULT_OUT = ROOT / "benchmarks" / "results" / "learning"
# curves of runs a lease cut off (no result JSON), laid out like DEFAULT_OUT; read for run-time estimates only
PARTIAL_OUT = ROOT / "benchmarks" / "results" / "partial"
# with --deadline, the run time assumed for a row that no result or curve estimates (its task never ran here): a new
# task's row ran 5-13 min on an H200, and a row started 70 s before a deadline this way was cut off
UNKNOWN_RUN_S = 600.0

SUMMARY_COLUMNS = ["row", "task", "config", "obs", "learner", "seeds", "env_steps", "success_mean", "success_std",
                   "sampled_success_mean", "wall_s_per_run", "device", "commit", "paper_success", "paper_note"]




# ------------------------------------------------------------------------------------------------ running
def git_commit() -> str:
    """Short commit of the source tree, with ``-dirty`` when tracked files differ from it; outside a git checkout (a
    copy of the tree on a GPU machine) the ``LAPWARP_COMMIT`` environment variable, else ``unknown``."""
    try:
        commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True, text=True,
                                check=True).stdout.strip()
        dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"], cwd=ROOT,
                               capture_output=True, text=True, check=True).stdout.strip()
        return commit + ("-dirty" if dirty else "")
    except (OSError, subprocess.CalledProcessError):
        return os.environ.get("LAPWARP_COMMIT") or "unknown"


def run_paths(out: Path, experiment: str, row: str, seed: int) -> dict[str, Path]:
    base = out / experiment / row
    return {suffix: base / f"seed{seed}.{suffix}" for suffix in ("csv", "json", "log")}


def run_command(row: Row, seed: int, preset: str, paths: dict[str, Path], device: str | None, nproc: int,
                num_envs: int | None, iterations: int | None, eval_envs: int, log_dir: Path,
                fast_pixels: bool = False, shared_encoder: bool = False, compile_mode: str | None = None) -> list[str]:
    """The ``train/ppo.py`` command line of one (row, seed). ``shared_encoder`` applies with ``fast_pixels`` to the
    RGB rows whose critic reads the images; ``compile_mode`` (torch.compile) to every row."""
    launcher = [sys.executable]
    if nproc > 1:
        launcher += ["-m", "torch.distributed.run", "--standalone", f"--nproc_per_node={nproc}"]
    cmd = launcher + [str(PPO_SCRIPT), "--task", row.task, "--obs", row.obs, "--preset", preset, "--seed", str(seed),
                      "--max-iterations", str(iterations or row.iterations), "--eval-envs", str(eval_envs),
                      "--log-dir", str(log_dir), "--progress-csv", str(paths["csv"]),
                      "--result-json", str(paths["json"])]
    if row.critic != "same":
        cmd += ["--critic", row.critic]
    cmd += list(row.train_args)
    if fast_pixels and row.obs == "rgb":
        cmd.append("--fast-pixels")
        if shared_encoder and row.critic == "same":
            cmd.append("--shared-encoder")
    if compile_mode:
        cmd += ["--compile", compile_mode]
    if nproc > 1:
        cmd.append("--distributed")
    elif device:
        cmd += ["--device", device]
    if num_envs:
        cmd += ["--num-envs", str(num_envs)]
    if row.config:
        cmd += ["--set", *[f"{k}={set_value(v)}" for k, v in row.config.items()]]
    return cmd


def _shape_key(task: str, obs: str, image_shape: Any) -> tuple[str, str, str]:
    return task, obs, json.dumps(image_shape) if obs != "state" else ""


def wall_estimates(jobs: list[tuple[Experiment, Row, int]], result_dirs: list[Path],
                   registry: dict[str, Experiment] | None = None) -> dict[tuple[str, str], float]:
    """Expected wall seconds per (experiment, row) of ``jobs`` from the runs in ``result_dirs`` (``--out``, the
    committed ``benchmarks/results/learning`` and ``PARTIAL_OUT``, the curves of runs a lease cut off):

    - a row with finished results (``seed*.json``): the mean of their ``wall_s``;
    - else a row with a cut-off run (a ``seed*.csv`` without its JSON): its iterations x that run's training seconds
      per iteration (the CSV's last ``wall_s`` over its iteration) plus the start-up and evaluation overhead;
    - else a new variant: its iterations x the mean training seconds per iteration of every run of the same task,
      observation type and image size (rows found in ``registry``, default ``EXPERIMENTS``), plus the overhead;
    rows with none of these are left out. The overhead is the mean ``wall_s - train_s`` of the finished results (0
    where none records ``train_s``)."""
    registry = EXPERIMENTS if registry is None else registry
    per_row: dict[tuple[str, str], list[float]] = {}  # (experiment, row) folder names -> wall seconds
    per_row_rate: dict[tuple[str, str], list[float]] = {}  # -> training seconds per iteration of cut-off runs
    per_shape_rate: dict[tuple[str, str, str], list[float]] = {}
    overheads: list[float] = []
    for base in result_dirs:
        for path in sorted(base.glob("*/*/seed*.json")):
            result = json.loads(path.read_text())
            if not isinstance(result.get("wall_s"), (int, float)):
                continue
            per_row.setdefault((path.parent.parent.name, path.parent.name), []).append(result["wall_s"])
            train_s = result.get("train_s")
            if isinstance(train_s, (int, float)):
                overheads.append(result["wall_s"] - train_s)
            if result.get("iterations"):
                key = _shape_key(result.get("task"), result.get("obs"), result.get("settings", {}).get("image_shape"))
                seconds = train_s if isinstance(train_s, (int, float)) else result["wall_s"]
                per_shape_rate.setdefault(key, []).append(seconds / result["iterations"])
        for path in sorted(base.glob("*/*/seed*.csv")):
            rate = _csv_seconds_per_iteration(path)
            if rate is None or path.with_suffix(".json").is_file():
                continue
            names = path.parent.parent.name, path.parent.name
            per_row_rate.setdefault(names, []).append(rate)
            experiment = registry.get(names[0])
            row = next((r for r in experiment.rows if r.name == names[1]), None) if experiment else None
            if row is not None:
                key = _shape_key(row.task, row.obs, row.config.get("image_shape"))
                per_shape_rate.setdefault(key, []).append(rate)
    overhead = sum(overheads) / len(overheads) if overheads else 0.0
    estimates = {}
    for experiment, row, _ in jobs:
        walls = per_row.get((experiment.name, row.name))
        rates = per_row_rate.get((experiment.name, row.name)) or per_shape_rate.get(
            _shape_key(row.task, row.obs, row.config.get("image_shape")))
        if walls:
            estimates[experiment.name, row.name] = sum(walls) / len(walls)
        elif rates:
            estimates[experiment.name, row.name] = row.iterations * sum(rates) / len(rates) + overhead
    return estimates


def _csv_seconds_per_iteration(path: Path) -> float | None:
    """Training seconds per iteration of a run's curve (its last ``wall_s`` over its ``iteration``); None for an
    empty or unreadable curve."""
    try:
        with path.open(newline="") as handle:
            rows = list(csv.DictReader(handle))
        last = rows[-1] if rows else None
        return float(last["wall_s"]) / float(last["iteration"]) if last and float(last["iteration"]) > 0 else None
    except (OSError, KeyError, TypeError, ValueError):
        return None


def run_jobs(jobs: list[tuple[Experiment, Row, int]], out: Path, devices: list[str | None], nproc: int,
             preset: str | None, num_envs: int | None, iterations: int | None, eval_envs: int, skip_done: bool,
             log_dir: Path, stream=None, fast_pixels: bool = False, shared_encoder: bool = False,
             compile_mode: str | None = None, deadline: float | None = None,
             estimates: dict[tuple[str, str], float] | None = None) -> list[tuple[Experiment, Row, int, int | None]]:
    """Run every (experiment, row, seed) in order, one run per entry of ``devices`` at a time (name a GPU twice to run
    two runs on it side by side); ``preset`` None: each experiment's own. Returns ``(experiment, row, seed, exit
    status)``, status None for a run not started.

    With ``deadline`` (seconds from the call; a leased machine's remaining time) a free device takes the first queued
    run expected to finish by then: ``estimates[experiment, row]`` seconds (``wall_estimates``), a run without an
    estimate ``UNKNOWN_RUN_S`` (10 min: a new task's row). A run that cannot finish in time is dropped and reported
    (time only moves on), so shorter runs behind it still use the device instead of a run cut off at the end."""
    stream = stream or sys.stdout
    commit = git_commit()
    queue = list(jobs)
    if skip_done:
        queue = [(e, r, s) for e, r, s in queue if not run_paths(out, e.name, r.name, s)["json"].is_file()]
    estimates = estimates or {}
    begin = time.time()
    running: dict[int, tuple] = {}  # slot (index into devices; a device may be named more than once) -> run
    results = []

    def drop_late() -> None:
        if deadline is None:
            return
        left = deadline - (time.time() - begin)
        for job in list(queue):
            experiment, row, seed = job
            expected = estimates.get((experiment.name, row.name))
            if (UNKNOWN_RUN_S if expected is None else expected) > left or left <= 0.0:
                queue.remove(job)
                results.append((experiment, row, seed, None))
                guess = (f"no estimate ({UNKNOWN_RUN_S:.0f} s assumed)" if expected is None
                         else f"expected {expected:.0f} s")
                print(f"not started {row.name} seed {seed}: {guess}, {max(left, 0.0):.0f} s left before the deadline",
                      file=stream, flush=True)

    while queue or running:
        drop_late()
        for slot, device in enumerate(devices):
            if slot not in running and queue:
                experiment, row, seed = queue.pop(0)
                paths = run_paths(out, experiment.name, row.name, seed)
                paths["csv"].parent.mkdir(parents=True, exist_ok=True)
                for path in paths.values():
                    path.unlink(missing_ok=True)
                cmd = run_command(row, seed, preset or experiment.preset, paths, device, nproc, num_envs, iterations,
                                  eval_envs, log_dir, fast_pixels, shared_encoder, compile_mode)
                log = open(paths["log"], "w")
                log.write(" ".join(cmd) + "\n")
                log.flush()
                env = dict(os.environ, PYTHONUNBUFFERED="1")
                proc = subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT, cwd=ROOT, env=env)
                running[slot] = (proc, experiment, row, seed, paths, log, time.time())
                print(f"started {row.name} seed {seed} on {device or 'the default device'}", file=stream, flush=True)
        time.sleep(0.2)
        for slot, (proc, experiment, row, seed, paths, log, started) in list(running.items()):
            status = proc.poll()
            if status is None:
                continue
            log.close()
            del running[slot]
            if status == 0 and paths["json"].is_file():
                result = json.loads(paths["json"].read_text())
                result.update(commit=commit, row=row.name, config=row.config_text(),
                              learner=row.learner("--fast-pixels" in proc.args, "--shared-encoder" in proc.args))
                paths["json"].write_text(json.dumps(result, indent=1))
                sampled = result.get("sampled_success")
                sampled = "" if sampled is None else f" (sampled {sampled:.1%})"
                print(f"finished {row.name} seed {seed}: evaluation success {result['success']:.1%}{sampled} in "
                      f"{time.time() - started:.0f} s{failure_text(result.get('evaluation'))}", file=stream,
                      flush=True)
            else:
                print(f"FAILED {row.name} seed {seed} (exit {status}); see {paths['log']}", file=stream, flush=True)
            results.append((experiment, row, seed, status))
    return results


def failure_text(evaluation: dict | None) -> str:
    """``"; failures: 20 at the time limit, 3 ended early, 12 of the failures stalled"`` from a result's
    ``evaluation`` (ppo.py's ``Evaluation`` as a dict; empty for results written before it existed or without
    failures)."""
    if not evaluation or not evaluation["timeouts"] + evaluation["terminations"]:
        return ""
    stalled = "" if evaluation.get("stalled") is None else f", {evaluation['stalled']} of the failures stalled"
    return f"; failures: {evaluation['timeouts']} at the time limit, {evaluation['terminations']} ended early{stalled}"


def read_queue(path: Path, experiments: dict[str, Experiment]) -> list[tuple[Experiment, Row, int]]:
    """The jobs of a queue file: one ``EXPERIMENT ROW SEED [SEED ...]`` per line, run in the file's order (``#``
    starts a comment). Raises ValueError naming the line of an unknown experiment or row, or a bad seed."""
    jobs, seen = [], set()
    for number, text in enumerate(path.read_text().splitlines(), 1):
        fields = text.split("#", 1)[0].split()
        if not fields:
            continue
        where = f"{path}:{number}"
        if len(fields) < 3:
            raise ValueError(f"{where}: expected EXPERIMENT ROW SEED [SEED ...], got {text.strip()!r}")
        if fields[0] not in experiments:
            raise ValueError(f"{where}: unknown experiment {fields[0]!r}; choose from {sorted(experiments)}")
        experiment = experiments[fields[0]]
        try:
            row = select_rows(experiment, [fields[1]])[0]
        except ValueError as exc:
            raise ValueError(f"{where}: {exc}") from None
        for text_seed in fields[2:]:
            if not text_seed.isdigit():
                raise ValueError(f"{where}: seeds are non-negative integers, got {text_seed!r}")
            job = (experiment.name, row.name, int(text_seed))
            if job in seen:  # it would overwrite its own files
                raise ValueError(f"{where}: {' '.join(map(str, job))} is queued twice")
            seen.add(job)
            jobs.append((experiment, row, int(text_seed)))
    if not jobs:
        raise ValueError(f"{path} queues no run")
    return jobs


# ------------------------------------------------------------------------------------------------ summary
def summarize(experiment: Experiment, rows: list[Row], out: Path) -> list[dict]:
    """Write ``<experiment>/summary.csv`` from the runs' JSON files (rows without finished runs are left out)."""
    lines = []
    for row in rows:
        results = []
        for path in sorted((out / experiment.name / row.name).glob("seed*.json")):
            results.append(json.loads(path.read_text()))
        if not results:
            continue
        successes = [r["success"] for r in results]
        lines.append({
            "row": row.name, "task": row.task, "config": row.config_text(), "obs": row.obs,
            "learner": " / ".join(sorted({r.get("learner", row.learner()) for r in results})),
            "seeds": " ".join(str(r["seed"]) for r in sorted(results, key=lambda r: r["seed"])),
            "env_steps": results[0]["env_steps"],
            "success_mean": round(statistics.fmean(successes), 4),
            "success_std": round(statistics.pstdev(successes), 4) if len(successes) > 1 else 0.0,
            # sampled actions, as the paper's training-rollout curves (runs from before ppo.py reported it: none)
            "sampled_success_mean": (round(statistics.fmean(sampled), 4) if (sampled := [
                r["sampled_success"] for r in results if "sampled_success" in r]) else ""),
            "wall_s_per_run": round(statistics.fmean(r["wall_s"] for r in results), 1),
            "device": " / ".join(sorted({r["device"] for r in results})),
            "commit": " / ".join(sorted({r.get("commit", "unknown") for r in results})),
            "paper_success": "" if row.paper_success is None else row.paper_success,
            "paper_note": row.paper_note,
        })
    path = out / experiment.name / "summary.csv"
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=SUMMARY_COLUMNS)
        writer.writeheader()
        writer.writerows(lines)
    return lines


def read_progress(path: Path) -> dict[str, list[float]]:
    with open(path, newline="") as f:
        rows = list(csv.DictReader(f))
    return {key: [float(r[key]) for r in rows] for key in ("env_steps", "wall_s", "success")}


def plot_rows(experiment: Experiment, rows: list[Row], out: Path) -> list[Path]:
    """One PNG per row: training success against env-steps and against wall seconds, one line per seed, the
    paper's final value dashed. Needs matplotlib (``pip install "lapwarp[plots]"``)."""
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError as exc:
        raise ImportError(f"plots need matplotlib: pip install \"lapwarp[plots]\" ({exc})") from None
    written = []
    for row in rows:
        runs = sorted((out / experiment.name / row.name).glob("seed*.csv"))
        if not runs:
            continue
        fig, axes = plt.subplots(1, 2, figsize=(9, 3.4), sharey=True)
        for run in runs:
            data = read_progress(run)
            for ax, x in zip(axes, ("env_steps", "wall_s"), strict=True):
                ax.plot(data[x], data["success"], label=run.stem, linewidth=1.2)
        for ax, label in zip(axes, ("env-steps", "wall time (s)"), strict=True):
            if row.paper_success is not None:
                ax.axhline(row.paper_success, linestyle="--", color="k", linewidth=1, label="paper (final)")
            ax.set_xlabel(label)
            ax.set_ylim(-0.02, 1.02)
            ax.grid(alpha=0.3)
        axes[0].set_ylabel("training success")
        axes[1].legend(fontsize=7, loc="lower right")
        # long configurations (reward weights) wrap instead of running off the figure
        fig.suptitle(textwrap.fill(f"{row.name}: {row.task} {row.obs} {row.config_text()}", 120), fontsize=9)
        fig.tight_layout()
        path = out / experiment.name / f"{row.name}.png"
        fig.savefig(path, dpi=110)
        plt.close(fig)
        written.append(path)
    return written


# ------------------------------------------------------------------------------------------------ CLI
def select_rows(experiment: Experiment, names: list[str] | None) -> list[Row]:
    if not names:
        return list(experiment.rows)
    known = {row.name: row for row in experiment.rows}
    unknown = [n for n in names if n not in known]
    if unknown:
        raise ValueError(f"unknown row(s) {unknown} of {experiment.name}; rows: {list(known)}")
    return [known[n] for n in names]


def summarize_and_plot(experiment: Experiment, rows: list[Row], out: Path, plots: bool) -> None:
    """Write the experiment's summary.csv (and plots), printing a line per row."""
    for line in summarize(experiment, rows, out):
        paper = "" if line["paper_success"] == "" else f" (paper {line['paper_success']:.0%})"
        print(f"{line['row']:24s} success {line['success_mean']:.1%} +- {line['success_std']:.1%} over seeds "
              f"{line['seeds']}, {line['wall_s_per_run']:.0f} s per run{paper}")
    print(f"summary: {out / experiment.name / 'summary.csv'}")
    if plots:
        try:
            written = plot_rows(experiment, rows, out)
            print(f"plots: {len(written)} PNG files in {out / experiment.name}")
        except ImportError as exc:
            print(f"no plots: {exc}", file=sys.stderr)


def main(argv: list[str] | None = None, experiments: dict[str, Experiment] | None = None) -> int:
    experiments = EXPERIMENTS if experiments is None else experiments
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("experiment", nargs="?", help=f"one of {sorted(experiments)}")
    parser.add_argument("--list", action="store_true", help="list the experiments and their rows")
    parser.add_argument("--rows", nargs="+", default=None, help="only these rows (default: all)")
    parser.add_argument("--seeds", nargs="+", type=int, default=None, help="default: 0 1 2")
    parser.add_argument("--queue", type=Path, default=None, metavar="FILE",
                        help="run the (experiment, row, seeds) of FILE's lines (EXPERIMENT ROW SEED [SEED ...]) in "
                             "its order over --devices, instead of one experiment's rows x seeds; then summarise "
                             "every experiment it named")
    parser.add_argument("--devices", nargs="+", default=[None],
                        help="run one (row, seed) per entry at a time, e.g. cuda:0 cuda:1, or cuda:0 cuda:0 for two "
                             "runs side by side on one GPU (default: one run at a time on ppo.py's device)")
    parser.add_argument("--nproc-per-run", type=int, default=1,
                        help="GPUs per run through torchrun and ppo.py --distributed (default 1)")
    parser.add_argument("--preset", default=None, help="ppo.py preset (default: the experiment's, gpu)")
    parser.add_argument("--num-envs", type=int, default=None, help="override the preset's envs (per rank)")
    parser.add_argument("--iterations", type=int, default=None, help="override every row's iterations")
    parser.add_argument("--eval-envs", type=int, default=256, help="episodes of the final evaluation")
    parser.add_argument("--fast-pixels", action="store_true", help="RGB rows: ppo.py --fast-pixels")
    parser.add_argument("--shared-encoder", action="store_true",
                        help="with --fast-pixels, RGB rows whose critic reads the images: ppo.py --shared-encoder")
    parser.add_argument("--compile", default=None, choices=COMPILE_MODES,
                        help="every run: ppo.py --compile MODE (torch.compile of the actor and critic)")
    parser.add_argument("--out", type=Path, default=DEFAULT_OUT)
    parser.add_argument("--log-dir", type=Path, default=ROOT / "runs" / "experiments",
                        help="rsl-rl's logs and checkpoints")
    parser.add_argument("--skip-done", action="store_true", help="keep (row, seed) runs that already have a result")
    parser.add_argument("--deadline", type=float, default=None, metavar="SECONDS",
                        help="start only runs expected to end within SECONDS of the start (a lease's time left): "
                             "expected = the mean wall time of the row's results in --out and "
                             "benchmarks/results/learning, else its iterations at the seconds per iteration of its "
                             "cut-off curves (benchmarks/results/partial) or of its task's runs, else 600 s; runs "
                             "that cannot fit are reported and skipped")
    parser.add_argument("--summarize-only", action="store_true", help="only rewrite summary.csv and the plots")
    parser.add_argument("--no-plots", action="store_true")
    args = parser.parse_args(argv)

    if args.list:
        for exp in experiments.values():
            print(f"{exp.name}: {exp.description}")
            for row in exp.rows:
                paper = "-" if row.paper_success is None else f"{row.paper_success:.0%}"
                critic = "  [state critic]" if row.critic == "state" else ""
                # the row's own ppo.py options (a schedule, the initial noise) define it as much as its config
                extra = f"  [ppo.py {' '.join(row.train_args)}]" if row.train_args else ""
                print(f"  {row.name:24s} {row.task:16s} {row.obs:5s} paper {paper:>5s}  {row.config_text()}{critic}"
                      f"{extra}")
        return 0
    if args.queue is not None:
        if args.experiment is not None or args.rows is not None or args.seeds is not None or args.summarize_only:
            parser.error("--queue names the experiments, rows and seeds itself (leave out EXPERIMENT, --rows, "
                         "--seeds and --summarize-only)")
    elif args.experiment not in experiments:
        parser.error(f"choose an experiment: {sorted(experiments)} (or --list)")
    args.seeds = [0, 1, 2] if args.seeds is None else args.seeds
    if args.nproc_per_run < 1 or (args.num_envs is not None and args.num_envs < 1) or args.eval_envs < 1 or (
            args.iterations is not None and args.iterations < 1):
        parser.error("--nproc-per-run, --num-envs, --iterations and --eval-envs must be positive")
    if args.deadline is not None and not args.deadline > 0.0:  # NaN fails the comparison too
        parser.error(f"--deadline must be a positive number of seconds, got {args.deadline}")
    if any(seed < 0 for seed in args.seeds) or len(set(args.seeds)) != len(args.seeds):
        # a negative one reached ppo.py as an option ("--seed -1") and every run failed; a repeated one would
        # overwrite its own files
        parser.error(f"--seeds must be distinct non-negative integers, got {args.seeds}")
    if args.shared_encoder and not args.fast_pixels:
        parser.error("--shared-encoder needs --fast-pixels")
    if args.nproc_per_run > 1 and args.devices != [None]:
        parser.error("--nproc-per-run uses torchrun's devices (cuda:0..N-1); leave out --devices")
    try:
        if args.queue is not None:
            jobs = read_queue(args.queue, experiments)
        else:
            experiment = experiments[args.experiment]
            jobs = [(experiment, row, seed) for row in select_rows(experiment, args.rows) for seed in args.seeds]
    except (OSError, ValueError) as exc:
        parser.error(str(exc))
    failed = []
    if not args.summarize_only:
        estimates = wall_estimates(jobs, list(dict.fromkeys([args.out, DEFAULT_OUT, PARTIAL_OUT])), experiments)
        results = run_jobs(jobs, args.out, args.devices, args.nproc_per_run, args.preset, args.num_envs,
                           args.iterations, args.eval_envs, args.skip_done, args.log_dir,
                           fast_pixels=args.fast_pixels, shared_encoder=args.shared_encoder, compile_mode=args.compile,
                           deadline=args.deadline, estimates=estimates)
        failed = [(exp.name, row.name, seed) for exp, row, seed, status in results if status not in (0, None)]
    # the summary of each experiment run covers all its rows that have results, not only those of this command
    # (a summary of the rows of one --rows run used to replace the whole table)
    for name in dict.fromkeys(experiment.name for experiment, _, _ in jobs):
        summarize_and_plot(experiments[name], list(experiments[name].rows), args.out, not args.no_plots)
    if failed:
        print(f"failed runs: {failed}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
