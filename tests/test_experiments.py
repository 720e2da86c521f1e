"""``train/experiments.py`` (issue #19): the runner's files on a tiny CPU run, its summary format and its rows."""

from __future__ import annotations

import csv
import json
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "train"))

import experiments  # noqa: E402
import ppo  # noqa: E402

TINY = {"tiny": experiments.Experiment("tiny", "one Reach row", [
    experiments.Row("reach", "Reach", {"sphere_radius": 0.008, "randomize_start": True}, "state", 2, 1.0, "solved"),
])}


def test_rows_state_the_paper_configuration_in_set_syntax():
    row = experiments.Row("x", "DeflectSpheres", {"num_deflect_to_win": 1, "single_instrument": True,
                                                   "image_shape": [64, 64], "sampling_mode": "WITHOUT_REPLACEMENT"})
    assert row.config_text() == ("num_deflect_to_win=1 single_instrument=True image_shape=[64,64] "
                                 "sampling_mode=WITHOUT_REPLACEMENT")
    names = [r.name for exp in experiments.EXPERIMENTS.values() for r in exp.rows]
    assert len(names) == len(set(names))
    spatial = {r.name: r for r in experiments.EXPERIMENTS["spatial-rgb"].rows}
    # the paper's text: ~30 % for one sphere / one instrument, ~2 % for five spheres / two instruments from pixels
    assert spatial["deflect-m1-b1-rgb"].paper_success == 0.3 and spatial["deflect-m5-b2-rgb"].paper_success == 0.02
    # the same two with the paper's 4 stacked frames
    for name in ("deflect-m1-b1", "deflect-m5-b2"):
        stacked, single = spatial[f"{name}-fs4-rgb"], spatial[f"{name}-rgb"]
        assert stacked.config == {**single.config, "frame_stack": 4}
        assert stacked.paper_success == single.paper_success
    assert len(experiments.EXPERIMENTS["spatial-state"].rows) == 9  # Reach, 6 x DeflectSpheres, 2 x SearchForPoint
    state = {r.name: r for r in experiments.EXPERIMENTS["spatial-state"].rows}
    assert state["search-active-state"].train_args == ("--obs-normalization",)
    assert state["search-camera-state"].train_args == ()
    # the asymmetric table: every single-frame image row with the state critic, DeflectSpheres 4x longer
    asym = {r.name: r for r in experiments.EXPERIMENTS["spatial-rgb-asym"].rows}
    assert sorted(asym) == sorted(f"{name}-asym" for name, r in spatial.items() if "frame_stack" not in r.config)
    for name, row in asym.items():
        single = spatial[name.removesuffix("-asym")]
        assert row.critic == "state" and row.config == single.config
        assert row.iterations == (600 if row.task == "DeflectSpheres" else single.iterations)


def test_run_commands_carry_the_learner_options(tmp_path):
    asym = {r.name: r for r in experiments.EXPERIMENTS["spatial-rgb-asym"].rows}["reach-r20-rgb-asym"]
    paths = experiments.run_paths(tmp_path, "x", asym.name, 0)
    cmd = experiments.run_command(asym, 0, "gpu", paths, "cuda:1", 1, None, None, 256, tmp_path, fast_pixels=True)
    assert cmd[cmd.index("--critic") + 1] == "state" and "--fast-pixels" in cmd
    assert cmd[cmd.index("--device") + 1] == "cuda:1" and cmd[cmd.index("--obs") + 1] == "rgb"
    assert cmd[cmd.index("--set") + 1:] == ["sphere_radius=0.02", "image_shape=[64,64]"]
    assert asym.learner(True) == "PPO, CNN actor, state critic (asymmetric), fast pixels"
    # a shared encoder only where the critic reads the images too
    cmd = experiments.run_command(asym, 0, "gpu", paths, None, 1, None, None, 256, tmp_path, fast_pixels=True,
                                  shared_encoder=True)
    assert "--shared-encoder" not in cmd
    reach = {r.name: r for r in experiments.EXPERIMENTS["spatial-rgb"].rows}["reach-r20-rgb"]
    cmd = experiments.run_command(reach, 0, "gpu", paths, None, 1, None, None, 256, tmp_path, fast_pixels=True,
                                  shared_encoder=True)
    assert cmd.index("--shared-encoder") == cmd.index("--fast-pixels") + 1
    assert reach.learner(True, True) == "PPO, CNN actor, CNN critic, fast pixels, shared encoder"
    cmd = experiments.run_command(reach, 0, "gpu", paths, None, 1, None, None, 256, tmp_path, compile_mode="default")
    assert cmd[cmd.index("--compile") + 1] == "default" and "--fast-pixels" not in cmd
    assert experiments.COMPILE_MODES == ppo.COMPILE_MODES
    state = experiments.EXPERIMENTS["spatial-state"].rows[0]
    cmd = experiments.run_command(state, 3, "gpu", paths, None, 2, 8, 5, 16, tmp_path, fast_pixels=True)
    assert "--fast-pixels" not in cmd and "--critic" not in cmd and "--distributed" in cmd
    assert cmd[1:4] == ["-m", "torch.distributed.run", "--standalone"] and "--device" not in cmd
    assert cmd[cmd.index("--num-envs") + 1] == "8" and cmd[cmd.index("--max-iterations") + 1] == "5"
    # a row's own training options (PickAndPlace's rate schedules) reach the command and the summary's learner
    place = {r.name: r for r in experiments.EXPERIMENTS["deformable-state"].rows}["pnp-place-stiff-state"]
    cmd = experiments.run_command(place, 0, "gpu", paths, None, 1, None, None, 1024, tmp_path)
    assert cmd[cmd.index("--lr-schedule") + 1] == "linear" and cmd[cmd.index("--learning-rate") + 1] == "3e-4"
    assert cmd[cmd.index("--max-iterations") + 1] == "250"
    assert place.learner() == "PPO, MLP actor and critic, --lr-schedule linear --learning-rate 3e-4"


def test_every_row_config_is_valid_for_its_task():
    """Every row's settings, parsed from its ``--set`` text as ``ppo.py`` parses them, are config keys and values its
    task accepts (a typo would otherwise fail on the GPU)."""
    import ppo

    from lapwarp.config import build_config
    from lapwarp.registry import task_class

    for exp in experiments.EXPERIMENTS.values():
        for row in exp.rows:
            env_class = task_class(row.task)
            config = ppo.parse_set(row.config_text().split(" ")) if row.config else {}
            config["observation_type"] = row.obs.upper()
            cfg = build_config(env_class.config_class, config)
            cfg.validate(env_class.rewards.names, env_class.supported_observations)

            def plain(value):
                return [plain(v) for v in value] if isinstance(value, (list, tuple)) else value

            # the values the env gets (after the config's coercion of e.g. "True") are the row's
            assert {k: plain(getattr(cfg, k)) for k in row.config} == {k: plain(v) for k, v in row.config.items()}
            # and its command line (as the device queue runs it: fast pixels, shared encoder) is one ppo.py accepts
            # (parsed and checked as ppo.py checks them)
            parser = ppo.build_parser()
            paths = {"csv": Path("seed0.csv"), "json": Path("seed0.json")}
            command = experiments.run_command(row, 0, exp.preset, paths, None, 1, None, None, 4, Path("runs"),
                                              fast_pixels=True, shared_encoder=True)
            assert command[1] == str(experiments.PPO_SCRIPT)
            ppo.training_config(parser.parse_args(command[2:]), parser, "cpu")


def test_tiny_cpu_run_writes_progress_results_summary_and_plots(tmp_path, capsys):
    out = tmp_path / "learning"
    args = ["tiny", "--seeds", "0", "1", "--preset", "cpu", "--num-envs", "4", "--eval-envs", "4", "--out", str(out),
            "--log-dir", str(tmp_path / "runs"), "--devices", "cpu"]
    assert experiments.main(args, TINY) == 0
    row_dir = out / "tiny" / "reach"
    for seed in (0, 1):
        with open(row_dir / f"seed{seed}.csv", newline="") as f:
            progress = list(csv.DictReader(f))
        assert [int(r["iteration"]) for r in progress] == [1, 2]
        assert [int(r["env_steps"]) for r in progress] == [128, 256]  # 4 envs x 32 steps per iteration
        assert all(0.0 <= float(r["success"]) <= 1.0 for r in progress)
        assert {"wall_s", "mean_return", "reward/distance_to_target"} <= set(progress[0])
        result = json.loads((row_dir / f"seed{seed}.json").read_text())
        assert result["seed"] == seed and result["env_steps"] == 256 and result["device"] == "cpu"
        assert result["row"] == "reach" and result["config"] == "sphere_radius=0.008 randomize_start=True"
        assert 0.0 <= result["success"] <= 1.0 and 0.0 <= result["sampled_success"] <= 1.0 and result["commit"]
        for key in ("evaluation", "sampled_evaluation"):  # how the episodes ended, as ppo.evaluate counts them
            ended = result[key]
            assert ended["episodes"] == result["eval_episodes"]
            assert ended["timeouts"] + ended["terminations"] == round((1 - ended["success"]) * ended["episodes"])
    with open(out / "tiny" / "summary.csv", newline="") as f:
        reader = csv.DictReader(f)
        summary = list(reader)
    assert reader.fieldnames == experiments.SUMMARY_COLUMNS
    assert len(summary) == 1
    line = summary[0]
    assert (line["task"], line["obs"], line["seeds"], line["env_steps"]) == ("Reach", "state", "0 1", "256")
    assert line["learner"] == "PPO, MLP actor and critic"
    assert line["config"] == "sphere_radius=0.008 randomize_start=True" and line["paper_success"] == "1.0"
    mean = (json.loads((row_dir / "seed0.json").read_text())["success"]
            + json.loads((row_dir / "seed1.json").read_text())["success"]) / 2
    assert float(line["success_mean"]) == pytest.approx(mean, abs=1e-4)
    sampled = [json.loads((row_dir / f"seed{k}.json").read_text())["sampled_success"] for k in (0, 1)]
    assert float(line["sampled_success_mean"]) == pytest.approx(sum(sampled) / 2, abs=1e-4)
    assert (out / "tiny" / "reach.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    text = capsys.readouterr().out
    assert "finished reach seed 1" in text and "summary:" in text

    # --summarize-only re-reads the files; --skip-done starts nothing when every run has a result
    (out / "tiny" / "summary.csv").unlink()
    assert experiments.main(args + ["--summarize-only", "--no-plots"], TINY) == 0
    assert (out / "tiny" / "summary.csv").is_file()
    assert experiments.main(args + ["--skip-done", "--no-plots"], TINY) == 0
    assert "started" not in capsys.readouterr().out


def test_failed_run_is_reported(tmp_path, capsys):
    bad = {"bad": experiments.Experiment("bad", "a config the task rejects", [
        experiments.Row("reach", "Reach", {"sphere_radius": -1.0}, "state", 1)])}
    args = ["bad", "--seeds", "0", "--preset", "cpu", "--num-envs", "2", "--out", str(tmp_path), "--no-plots",
            "--log-dir", str(tmp_path / "runs"), "--devices", "cpu"]
    assert experiments.main(args, bad) == 1
    assert "FAILED reach seed 0" in capsys.readouterr().out
    assert "sphere_radius" in (tmp_path / "bad" / "reach" / "seed0.log").read_text()


def test_usage_errors(capsys):
    with pytest.raises(SystemExit):
        experiments.main(["nope"])
    with pytest.raises(SystemExit):
        experiments.main(["spatial-state", "--rows", "reach-nothing"])
    assert "unknown row" in capsys.readouterr().err
    for seeds in (["-1"], ["0", "0"]):
        with pytest.raises(SystemExit):
            experiments.main(["spatial-state", "--seeds", *seeds])
        assert "--seeds must be distinct non-negative integers" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        experiments.main(["spatial-rgb", "--shared-encoder"])
    assert "--shared-encoder needs --fast-pixels" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        experiments.main(["spatial-rgb", "--compile", "fastest"])
    assert "invalid choice: 'fastest'" in capsys.readouterr().err
    assert experiments.main(["--list"]) == 0
    listing = capsys.readouterr().out
    assert "deflect-m5-b2-rgb" in listing
    # a row's own ppo.py options are listed with it
    (line,) = [row for row in listing.splitlines() if row.strip().startswith("ll-stiff-closure-n05-i2-state ")]
    assert line.endswith("[ppo.py --init-noise-std 0.5]") and "index_steps_per_action=2" in line


def test_commit_outside_a_checkout_comes_from_the_environment(tmp_path, monkeypatch):
    monkeypatch.setattr(experiments, "ROOT", tmp_path)  # a copy of the tree without .git
    monkeypatch.setenv("GIT_CEILING_DIRECTORIES", str(tmp_path.parent))
    monkeypatch.delenv("LAPWARP_COMMIT", raising=False)
    assert experiments.git_commit() == "unknown"
    monkeypatch.setenv("LAPWARP_COMMIT", "abc1234")
    assert experiments.git_commit() == "abc1234"


def test_queue_runs_rows_of_several_experiments_in_its_order(tmp_path, capsys):
    two = {**TINY, "tiny2": experiments.Experiment("tiny2", "another", [
        experiments.Row("reach-big", "Reach", {"sphere_radius": 0.02}, "state", 1, 1.0, "solved")])}
    queue = tmp_path / "jobs.txt"
    queue.write_text("# experiment row seeds\ntiny2 reach-big 1   # the second experiment first\n\ntiny reach 0\n")
    out = tmp_path / "learning"
    args = ["--queue", str(queue), "--preset", "cpu", "--num-envs", "4", "--eval-envs", "4", "--out", str(out),
            "--log-dir", str(tmp_path / "runs"), "--devices", "cpu", "--no-plots"]
    assert experiments.main(args, two) == 0
    text = capsys.readouterr().out
    assert text.index("started reach-big seed 1") < text.index("started reach seed 0")
    assert sorted(p.relative_to(out).as_posix() for p in out.glob("*/*/*.json")) == [
        "tiny/reach/seed0.json", "tiny2/reach-big/seed1.json"]
    for name, row, iterations in (("tiny", "reach", 2), ("tiny2", "reach-big", 1)):
        with open(out / name / "summary.csv", newline="") as f:
            (line,) = list(csv.DictReader(f))
        assert line["row"] == row and int(line["env_steps"]) == 4 * 32 * iterations  # each row its own iterations

    # usage: every line is checked before anything runs, and named in the error
    for content, message in (("tiny reach\n", "jobs.txt:1: expected EXPERIMENT ROW SEED"),
                             ("tiny reach 0\nnope reach 0\n", "jobs.txt:2: unknown experiment 'nope'"),
                             ("tiny reach-x 0\n", "jobs.txt:1: unknown row(s) ['reach-x']"),
                             ("tiny reach -1\n", "jobs.txt:1: seeds are non-negative integers, got '-1'"),
                             ("tiny reach 0\ntiny reach 1 0\n", "jobs.txt:2: tiny reach 0 is queued twice"),
                             ("# nothing\n", "queues no run")):
        queue.write_text(content)
        with pytest.raises(SystemExit):
            experiments.main(args, two)
        assert message in capsys.readouterr().err
    for extra in (["tiny"], ["--seeds", "0"], ["--rows", "reach"], ["--summarize-only"]):
        with pytest.raises(SystemExit):
            experiments.main([*extra, *args], two)
        assert "--queue names the experiments, rows and seeds itself" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        experiments.main(["--queue", str(tmp_path / "missing.txt")], two)
    assert "missing.txt" in capsys.readouterr().err


def test_failure_text_summarises_how_episodes_failed():
    assert experiments.failure_text(None) == ""
    assert experiments.failure_text({"timeouts": 0, "terminations": 0, "stalled": 0}) == ""
    assert experiments.failure_text({"timeouts": 20, "terminations": 3, "stalled": 12}) == (
        "; failures: 20 at the time limit, 3 ended early, 12 of the failures stalled")
    assert experiments.failure_text({"timeouts": 1, "terminations": 0, "stalled": None}) == (
        "; failures: 1 at the time limit, 0 ended early")


def test_deadline_skips_runs_that_cannot_finish_in_time(tmp_path):
    """``--deadline``: a run expected (from the row's earlier results) to outlast the time left is not started but
    reported with status None, and is no failure; a row nothing estimates is assumed to take 10 min. The estimate is
    the mean ``wall_s`` over the row's results in every directory given."""
    exp = TINY["tiny"]
    for base, wall in ((tmp_path / "a", 100.0), (tmp_path / "b", 300.0)):
        row_dir = base / "tiny" / "reach"
        row_dir.mkdir(parents=True)
        (row_dir / "seed0.json").write_text(json.dumps({"wall_s": wall, "success": 1.0, "task": "Reach",
                                                        "obs": "state", "iterations": 2, "settings": {}}))
    jobs = [(exp, exp.rows[0], 1), (exp, exp.rows[0], 2)]
    # a new variant of a measured row: its iterations x the seconds per iteration of the same task's results (100 s
    # per iteration here); a task with no result has no estimate
    longer = experiments.Row("reach-long", "Reach", {}, "state", 5, None, "")
    pixels = experiments.Row("reach-rgb", "Reach", {"image_shape": [64, 64]}, "rgb", 5, None, "")
    estimates = experiments.wall_estimates(jobs + [(exp, longer, 0), (exp, pixels, 0)],
                                           [tmp_path / "a", tmp_path / "b", tmp_path / "missing"])
    assert estimates == {("tiny", "reach"): 200.0, ("tiny", "reach-long"): 500.0}
    # a row with only a cut-off run (its curve, no JSON): its iterations x the curve's seconds per iteration (40 s at
    # iteration 2 -> 20 s) plus the overhead wall_s - train_s of finished runs (30 s here); the curve also stands
    # for its task in a new variant's estimate; finished results record train_s, so their rate is train_s/iteration
    cut_off = experiments.Row("reach-cut", "Reach", {}, "state", 5, None, "")
    registry = {"tiny": experiments.Experiment("tiny", exp.description, [*exp.rows, cut_off], exp.preset)}
    (tmp_path / "c" / "tiny" / "reach-cut").mkdir(parents=True)
    (tmp_path / "c" / "tiny" / "reach-cut" / "seed0.csv").write_text(
        "iteration,env_steps,wall_s,success\n1,10,15.0,0.0\n2,20,40.0,0.1\n")
    (tmp_path / "c" / "tiny" / "reach").mkdir(parents=True)
    (tmp_path / "c" / "tiny" / "reach" / "seed3.json").write_text(json.dumps(
        {"wall_s": 230.0, "train_s": 200.0, "task": "Reach", "obs": "state", "iterations": 2, "settings": {}}))
    (tmp_path / "c" / "tiny" / "reach" / "seed3.csv").write_text("iteration,wall_s\n2,1000.0\n")  # has its JSON
    with_cut = experiments.wall_estimates([(exp, cut_off, 0), (exp, longer, 0)], [tmp_path / "c"], registry)
    assert with_cut == {("tiny", "reach-cut"): pytest.approx(5 * 20.0 + 30.0),
                        ("tiny", "reach-long"): pytest.approx(5 * (20.0 + 100.0) / 2 + 30.0)}
    lines = []

    class Stream:
        def write(self, text):
            lines.append(text)

        def flush(self):
            pass

    out = tmp_path / "out"
    # a row nothing estimates (here the pixel row) is assumed to take UNKNOWN_RUN_S (600 s)
    results = experiments.run_jobs(jobs + [(exp, pixels, 0)], out, [None], 1, "cpu", 2, 1, 2, False,
                                   tmp_path / "logs", stream=Stream(), deadline=550.0,
                                   estimates={("tiny", "reach"): 560.0})
    assert [(row.name, seed, status) for _, row, seed, status in results] == [
        ("reach", 1, None), ("reach", 2, None), ("reach-rgb", 0, None)]
    assert "not started reach seed 1: expected 560 s, 550 s left before the deadline" in "".join(lines)
    assert "not started reach-rgb seed 0: no estimate (600 s assumed), 550 s left before the deadline" in "".join(lines)
    assert not (out / "tiny").exists()  # nothing was started


def test_deadline_must_be_positive(capsys):
    with pytest.raises(SystemExit):
        experiments.main(["tiny", "--deadline", "nan"], TINY)
    assert "--deadline must be a positive number of seconds" in capsys.readouterr().err
