"""``train/device/merge_results.py``: a lease's results archive merged into the learning results, cut-off curves kept
apart, logs copied, summaries rewritten."""

from __future__ import annotations

import csv
import json
import sys
import tarfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "train"))
sys.path.insert(0, str(ROOT / "train" / "device"))

import experiments  # noqa: E402
import merge_results  # noqa: E402

REGISTRY = {"tiny": experiments.Experiment("tiny", "one Reach row", [
    experiments.Row("reach", "Reach", {"sphere_radius": 0.008}, "state", 2, 1.0, "solved")])}


def _run_files(folder: Path, seed: int, finished: bool, success: float = 0.5) -> None:
    folder.mkdir(parents=True, exist_ok=True)
    (folder / f"seed{seed}.csv").write_text("iteration,env_steps,wall_s,success,mean_return\n1,64,2.0,0.25,1.0\n")
    (folder / f"seed{seed}.log").write_text("log\n")
    if finished:
        (folder / f"seed{seed}.json").write_text(json.dumps({
            "task": "Reach", "obs": "state", "seed": seed, "success": success, "sampled_success": success,
            "env_steps": 64, "wall_s": 10.0, "train_s": 5.0, "iterations": 1, "device": "NVIDIA H200",
            "commit": "abc1234", "settings": {}}))


def _archive(tmp_path: Path, name: str, runs: list[tuple[str, str, int, bool]], extra: dict[str, str]) -> Path:
    base = tmp_path / f"build-{name}"
    for experiment, row, seed, finished in runs:
        _run_files(base / "r" / "learning" / experiment / row, seed, finished)
    for file_name, text in extra.items():
        (base / "r" / file_name).parent.mkdir(parents=True, exist_ok=True)
        (base / "r" / file_name).write_text(text)
    path = tmp_path / f"{name}.tgz"
    with tarfile.open(path, "w:gz") as archive:
        archive.add(base / "r", arcname="r")
    return path


def test_merge_copies_finished_runs_keeps_cut_off_curves_apart_and_summarises(tmp_path, capsys):
    learning, partial, session = tmp_path / "learning", tmp_path / "partial", tmp_path / "session"
    first = _archive(tmp_path, "a", [("tiny", "reach", 0, True), ("tiny", "reach", 1, False),
                                     ("tiny", "unknown-row", 0, True), ("other", "reach", 0, True)],
                     {"queue.log": "started\n", "gpu.txt": "NVIDIA H200\n", "soak.jsonl": "{}\n",
                      "td_touch/summary.txt": "TissueDissection_STATE_replay rc=0\n"})
    # the second lease finishes seed 1, which the first cut off
    second = _archive(tmp_path, "b", [("tiny", "reach", 1, True)], {"queue.log": "again\n"})
    assert merge_results.main([str(first), "--learning", str(learning), "--partial", str(partial), "--session",
                               str(session), "--no-plots"], REGISTRY) == 0
    out = capsys.readouterr()
    assert "finished tiny reach seed 0" in out.out and "cut off  tiny reach seed 1" in out.out
    assert "learning/tiny/unknown-row/seed0.csv" in out.err and "learning/other/reach/seed0.csv" in out.err
    row_dir = learning / "tiny" / "reach"
    assert sorted(p.name for p in row_dir.iterdir()) == ["seed0.csv", "seed0.json", "seed0.log"]
    assert (partial / "tiny" / "reach" / "seed1.csv").is_file()
    assert not (learning / "other").exists() and not (learning / "tiny" / "unknown-row").exists()
    assert sorted(p.name for p in session.iterdir()) == ["gpu-1.txt", "queue-1.log", "soak-1.jsonl", "td_touch-1"]
    assert (session / "td_touch-1" / "summary.txt").read_text() == "TissueDissection_STATE_replay rc=0\n"
    summary = list(csv.DictReader((learning / "tiny" / "summary.csv").open()))
    assert [(s["row"], s["seeds"], float(s["success_mean"])) for s in summary] == [("reach", "0", 0.5)]

    merge_results.main([str(second), "--learning", str(learning), "--partial", str(partial), "--session",
                        str(session), "--no-plots"], REGISTRY)
    # one lease's collections: the later archive's log begins with the earlier one's, which is dropped
    lease = tmp_path / "lease"
    grown = [_archive(tmp_path, f"c{k}", [], {
        "queue.log": "started\n" + "finished\n" * k, "gpu.txt": "H200\n",
        "td_touch/summary.txt": "TissueDissection_STATE_replay rc=0\n" + "TissueDissection_RGB_replay rc=0\n" * k,
        **({"td_touch/RGB.json": "{}"} if k == 2 else {}), "other/a.txt": "xy"[k - 1]}) for k in (1, 2)]
    merge_results.merge([first, *grown], tmp_path / "l3", tmp_path / "p3", lease, REGISTRY)
    # queue-1 ("started") begins queue-2, which begins queue-3; gpu-2 equals gpu-3; gpu-1 differs from both;
    # td_touch-3 holds every file of td_touch-1 and -2 as they grew; other-2's file is not how other-3's began
    assert sorted(p.name for p in lease.iterdir()) == ["gpu-1.txt", "gpu-3.txt", "other-2", "other-3", "queue-3.log",
                                                       "soak-1.jsonl", "td_touch-3"]
    assert sorted(p.name for p in (lease / "td_touch-3").iterdir()) == ["RGB.json", "summary.txt"]
    assert (lease / "queue-3.log").read_text() == "started\nfinished\nfinished\n"
    assert not (partial / "tiny" / "reach" / "seed1.csv").exists()  # superseded by the finished run
    both = merge_results.merge([first, second], tmp_path / "l2", tmp_path / "p2", None, REGISTRY)
    assert both.cut_off == [] and ("tiny", "reach", 1) in both.finished  # the report says how each run ended
    assert (row_dir / "seed1.json").is_file() and (session / "queue-1.log").read_text() == "again\n"
    summary = list(csv.DictReader((learning / "tiny" / "summary.csv").open()))
    assert [(s["row"], s["seeds"]) for s in summary] == [("reach", "0 1")]

    # a cut-off curve of a seed that has finished results is not kept
    third = _archive(tmp_path, "c", [("tiny", "reach", 0, False)], {})
    merged = merge_results.merge([third], learning, partial, None, REGISTRY)
    assert merged.cut_off == [] and not (partial / "tiny" / "reach" / "seed0.csv").exists()


def test_merge_refuses_what_is_not_an_archive(tmp_path, capsys):
    not_an_archive = tmp_path / "r.tgz"
    not_an_archive.write_text("text")
    with pytest.raises(SystemExit):
        merge_results.main([str(not_an_archive), "--learning", str(tmp_path / "l")], REGISTRY)
    assert "neither a folder nor a tar archive" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        merge_results.main([str(tmp_path / "missing.tgz")], REGISTRY)
    assert "no such archive or folder" in capsys.readouterr().err
