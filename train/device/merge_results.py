"""Merge the learning results of a leased GPU machine (``train/device/collect.sh``'s ``r.tgz``) into the repository.

    python train/device/merge_results.py /work/.device/5/r.tgz /work/.device/11/r.tgz \\
        --session benchmarks/results/session25

Each archive (or an extracted folder holding ``r/``) is read in the order given, later ones winning:

- a finished run, ``r/learning/<experiment>/<row>/seed<k>.json`` with its ``.csv`` and ``.log``, is copied to
  ``benchmarks/results/learning/<experiment>/<row>/``, and a cut-off curve of that seed kept earlier is removed;
- a cut-off run (a ``.csv`` without its ``.json``: the lease ended first) goes to
  ``benchmarks/results/partial/<experiment>/<row>/`` (read by ``experiments.py --deadline`` for run times), unless
  the seed has finished results;
- with ``--session``, the archive's ``queue.log``, ``gpu.txt``, ``jobs.txt``, ``beside.log`` and ``*.jsonl`` are
  copied there as ``<name>-<n>.<ext>`` (``n``: the archive's place in the list, from 1), and every other folder of
  ``r/`` (what a command beside the queue wrote, e.g. ``benchmarks/step_targets.sh``'s output) as ``<folder>-<n>/``;
  a lease's collections each archive everything so far, so a copied file that the same name's copy from a later
  archive begins with (its content at an earlier collection) is removed, and so is a copied folder whose every file
  the later folder's copy begins with;

then every experiment with a newly finished run gets its ``summary.csv`` (and plots, unless ``--no-plots``) rewritten.
Runs of experiments or rows the registry does not know are reported and left out.
"""

from __future__ import annotations

import argparse
import shutil
import sys
import tarfile
import tempfile
from dataclasses import dataclass, field
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # train/: the runner and its registry

import experiments  # noqa: E402
from experiment_rows import EXPERIMENTS, Experiment  # noqa: E402

SESSION_FILES = ("queue.log", "gpu.txt", "jobs.txt", "beside.log")


@dataclass
class Merged:
    """What a merge did: ``(experiment, row, seed)`` per finished and cut-off run, and the paths it left out."""

    finished: list[tuple[str, str, int]] = field(default_factory=list)
    cut_off: list[tuple[str, str, int]] = field(default_factory=list)
    skipped: list[str] = field(default_factory=list)
    session_files: list[Path] = field(default_factory=list)


def _seed_of(path: Path) -> int | None:
    digits = path.stem.removeprefix("seed")
    return int(digits) if path.stem.startswith("seed") and digits.isdigit() else None


def _results_root(source: Path, scratch: Path) -> Path:
    """The ``r`` folder of an archive (extracted into ``scratch``) or of an extracted folder."""
    if source.is_dir():
        return source / "r" if (source / "r").is_dir() else source
    if not tarfile.is_tarfile(source):
        raise ValueError(f"{source} is neither a folder nor a tar archive")
    with tarfile.open(source) as archive:
        archive.extractall(scratch, filter="data")  # no paths outside scratch, no links out of it
    return scratch / "r"


def merge(sources: list[Path], learning: Path, partial: Path, session: Path | None,
          registry: dict[str, Experiment] | None = None) -> Merged:
    """Copy the runs of ``sources`` into ``learning`` / ``partial`` (and the logs into ``session``); see the module
    docstring. Returns what was merged; summaries are not written here (``main`` does)."""
    registry = EXPERIMENTS if registry is None else registry
    merged = Merged()
    for number, source in enumerate(sources, 1):
        with tempfile.TemporaryDirectory() as scratch:
            root = _results_root(Path(source), Path(scratch))
            for curve in sorted((root / "learning").glob("*/*/seed*.csv")):
                seed, row, experiment = _seed_of(curve), curve.parent.name, curve.parent.parent.name
                known = experiment in registry and any(r.name == row for r in registry[experiment].rows)
                if seed is None or not known:
                    merged.skipped.append(str(curve.relative_to(root)))
                    continue
                finished_dir, partial_dir = learning / experiment / row, partial / experiment / row
                if curve.with_suffix(".json").is_file():
                    finished_dir.mkdir(parents=True, exist_ok=True)
                    for suffix in (".csv", ".json", ".log"):
                        if curve.with_suffix(suffix).is_file():
                            shutil.copy2(curve.with_suffix(suffix), finished_dir / f"seed{seed}{suffix}")
                    (partial_dir / f"seed{seed}.csv").unlink(missing_ok=True)  # superseded by the finished run
                    merged.finished.append((experiment, row, seed))
                elif not (finished_dir / f"seed{seed}.json").is_file():
                    partial_dir.mkdir(parents=True, exist_ok=True)
                    shutil.copy2(curve, partial_dir / f"seed{seed}.csv")
                    merged.cut_off.append((experiment, row, seed))
            if session is not None:
                session.mkdir(parents=True, exist_ok=True)
                for path in [root / name for name in SESSION_FILES] + sorted(root.glob("*.jsonl")):
                    if path.is_file():
                        target = session / f"{path.stem}-{number}{path.suffix}"
                        shutil.copy2(path, target)
                        merged.session_files.append(target)
                for folder in sorted(p for p in root.iterdir() if p.is_dir() and p.name != "learning"):
                    target = session / f"{folder.name}-{number}"
                    shutil.copytree(folder, target, dirs_exist_ok=True)
                    merged.session_files.append(target)
    # a run one archive cut off and a later one finished (a lease lost and its queue run again) counts as finished
    merged.cut_off = [run for run in merged.cut_off if run not in merged.finished]
    merged.session_files = _drop_earlier_prefixes(merged.session_files)
    return merged


def _begins(later: Path, earlier: Path) -> bool:
    """Whether ``later`` holds ``earlier`` as it grew: a file whose content begins with the earlier file's, or a folder
    holding each of the earlier folder's files (by relative path) in that sense."""
    if earlier.is_file():
        return later.is_file() and later.read_bytes().startswith(earlier.read_bytes())
    return later.is_dir() and all(_begins(later / path.relative_to(earlier), path)
                                  for path in earlier.rglob("*") if path.is_file())


def _drop_earlier_prefixes(paths: list[Path]) -> list[Path]:
    """Remove each copy (``<stem>-<n><suffix>``, a file or a folder) that the copy of the same name from a later
    archive begins with (the later collection of one lease holds it all); returns the paths kept."""
    def key(path: Path) -> tuple[str, bool, int]:
        """(the name without the archive's number, whether a folder, that number)"""
        stem, suffix = (path.name, "") if path.is_dir() else (path.stem, path.suffix)
        name, _, number = stem.rpartition("-")
        return name + suffix, path.is_dir(), int(number)

    keys = {path: key(path) for path in paths}  # before any removal
    kept = list(paths)
    for earlier in paths:
        name, is_dir, number = keys[earlier]
        later = [path for path in paths
                 if path.exists() and keys[path][:2] == (name, is_dir) and keys[path][2] > number]
        if any(_begins(path, earlier) for path in later):
            shutil.rmtree(earlier) if earlier.is_dir() else earlier.unlink()
            kept.remove(earlier)
    return kept


def main(argv: list[str] | None = None, registry: dict[str, Experiment] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("sources", nargs="+", type=Path, help="r.tgz archives or folders holding r/")
    parser.add_argument("--learning", type=Path, default=experiments.DEFAULT_OUT)
    parser.add_argument("--partial", type=Path, default=experiments.PARTIAL_OUT)
    parser.add_argument("--session", type=Path, default=None, help="folder for the lease's logs (e.g. "
                        "benchmarks/results/session25)")
    parser.add_argument("--no-plots", action="store_true")
    args = parser.parse_args(argv)
    registry = EXPERIMENTS if registry is None else registry
    missing = [str(s) for s in args.sources if not s.exists()]
    if missing:
        parser.error(f"no such archive or folder: {missing}")
    try:
        merged = merge(args.sources, args.learning, args.partial, args.session, registry)
    except (ValueError, tarfile.TarError) as exc:
        parser.error(str(exc))
    for experiment, row, seed in merged.finished:
        print(f"finished {experiment} {row} seed {seed}")
    for experiment, row, seed in merged.cut_off:
        print(f"cut off  {experiment} {row} seed {seed} (curve in {args.partial})")
    for path in merged.skipped:
        print(f"skipped  {path}: not a run of a known experiment and row", file=sys.stderr)
    for name in dict.fromkeys(experiment for experiment, _, _ in merged.finished):
        experiments.summarize_and_plot(registry[name], list(registry[name].rows), args.learning, not args.no_plots)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
