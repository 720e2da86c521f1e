"""The PPO launcher, the env benchmark and the soak script run end to end with tiny settings (CPU)."""

from __future__ import annotations

import json
import math
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

import lapwarp
from lapwarp.vecenv import LapwarpVectorEnv

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "train"))
sys.path.insert(0, str(ROOT / "benchmarks"))

import bench_env  # noqa: E402
import bench_fused  # noqa: E402
import bench_reset  # noqa: E402
import border_follower  # noqa: E402
import cloth_sag  # noqa: E402
import expert_success  # noqa: E402
import launch_counts  # noqa: E402
import ppo  # noqa: E402
import profile_learner  # noqa: E402
import profile_step  # noqa: E402
import soak  # noqa: E402
import tet_hold  # noqa: E402
import visibility  # noqa: E402


def test_ppo_trains_saves_resumes_and_plays(device, tmp_path, capsys):
    args = ["--task", "Reach", "--device", device, "--preset", "cpu", "--num-envs", "16", "--max-iterations", "2",
            "--set", "sphere_radius=0.02", "distance_to_target_threshold=0.004",
            "--eval-envs", "8", "--log-dir", str(tmp_path)]
    assert ppo.main(args) == 0
    out = capsys.readouterr().out
    assert "it     2/2" in out and "evaluation on 8 episodes: success rate" in out
    assert "sampled actions (as in training rollouts), 8 episodes: success rate" in out
    checkpoints = sorted(tmp_path.glob("Reach/*/model_*.pt"))
    assert checkpoints, "training must save a checkpoint"
    assert ppo.main(args[:-2] + ["--log-dir", str(tmp_path / "resumed"), "--resume", str(checkpoints[-1])]) == 0
    # an explicit rate replaces the one the checkpoint's optimizer state brings back (rsl-rl's load restores it)
    assert ppo.main(args[:-2] + ["--log-dir", str(tmp_path / "resumed_rate"), "--resume", str(checkpoints[-1]),
                                 "--lr-schedule", "fixed", "--learning-rate", "5e-5"]) == 0
    out = capsys.readouterr().out
    assert "learning rate 5.00e-05 (the checkpoint's was" in out and "lr 5.00e-05" in out
    assert ppo.main(["--device", device, "--preset", "cpu", "--num-envs", "4", "--eval-envs", "4",
                     "--play", str(checkpoints[-1])]) == 0
    assert "loaded" in capsys.readouterr().out


def test_paper_preset_matches_the_paper_table():
    cfg, env_overrides = ppo.preset_config("paper", num_envs=8, max_iterations=100)
    alg = cfg["algorithm"]
    assert cfg["num_steps_per_env"] == 128 and alg["num_mini_batches"] == 4  # 8 * 128 / 256
    assert (alg["num_learning_epochs"], alg["gamma"], alg["lam"]) == (4, 0.995, 0.95)
    assert (alg["learning_rate"], alg["clip_param"], alg["entropy_coef"]) == (2.5e-4, 0.1, 0.0)
    assert (alg["value_loss_coef"], alg["max_grad_norm"]) == (0.5, 0.5)
    assert cfg["actor"]["hidden_dims"] == [256, 256] and cfg["actor"]["activation"] == "relu"
    # invalid_actions="zero": no host sync per step in training; non-finite actions are counted, not raised
    assert env_overrides == {"frame_stack": 4, "invalid_actions": "zero"}


def test_linear_schedule_decays_to_zero(device):
    from rsl_rl.runners import OnPolicyRunner

    import lapwarp

    cfg, _ = ppo.preset_config("paper", num_envs=2, max_iterations=4)
    cfg["num_steps_per_env"] = 4
    cfg["algorithm"]["num_mini_batches"] = 1
    runner = OnPolicyRunner(lapwarp.make("Reach", num_envs=2, device=device), cfg, log_dir=None, device=device)
    lrs = []
    for _ in range(4):
        runner.learn(1)
        lrs.append(runner.alg.learning_rate)
    assert lrs == pytest.approx([2.5e-4, 1.875e-4, 1.25e-4, 0.625e-4])


def test_bench_env_writes_json(device, tmp_path):
    out = tmp_path / "bench.json"
    assert bench_env.main(["--device", device, "--num-envs", "1", "8", "--seconds", "0.05", "--out", str(out),
                           "--both-nan-modes"]) == 0
    report = json.loads(out.read_text())
    assert [r["num_envs"] for r in report["results"]] == [1, 1, 8, 8]
    assert all(r["env_steps_per_s"] > 0 for r in report["results"])
    assert report["config_overrides"] == {}
    # --set overrides are recorded with the figures they produced
    assert bench_env.main(["--device", device, "--num-envs", "1", "--seconds", "0.05", "--out", str(out),
                           "--set", "sphere_radius=0.02"]) == 0
    assert json.loads(out.read_text())["config_overrides"] == {"sphere_radius": 0.02}


def test_bench_reset_times_cut_and_uncut_resets_after_as_many_steps(device, tmp_path):
    """Both resets follow the same number of steps (idle before the uncut one, the expert before the cut one), and
    the JSON says how many elements each found removed: none after the idle steps, some after the expert's.
    ``--profile`` writes one profiled reset of each kind in profile_step's format (kernel records come only on CUDA:
    on the CPU the list is empty and the wall time is measured)."""
    out = tmp_path / "reset.json"
    assert bench_reset.main(["--tasks", "TissueDissection", "--device", device, "--num-envs", "2", "--repeats", "2",
                             "--expert-steps", "30", "--out", str(out), "--profile", str(tmp_path / "prof")]) == 0
    result = json.loads(out.read_text())["results"][0]
    assert result["steps_before_each_reset"] == 30
    # the second repeat runs the cut reset first, then the idle steps and the uncut reset, which must find nothing
    # removed: the cut reset restored every cut env
    assert result["removed_elements_per_env_at_uncut_reset"] == 0.0
    assert result["removed_elements_per_env_at_cut_reset"] > 0.0
    assert result["uncut_reset_ms"] > 0.0 and result["cut_reset_ms"] > 0.0
    assert len(result["uncut_reset_ms_all"]) == len(result["cut_reset_ms_all"]) == 2
    ratios = sorted(c / u for c, u in zip(result["cut_reset_ms_all"], result["uncut_reset_ms_all"], strict=True))
    paired = result["cut_over_uncut_paired"]
    assert paired["q25"] == pytest.approx(ratios[0] + 0.25 * (ratios[1] - ratios[0]))
    assert paired["median"] == pytest.approx(sum(ratios) / 2) and paired["q75"] <= ratios[1]
    profiles = {kind: json.loads((tmp_path / "prof" / f"TissueDissection_reset_{kind}.json").read_text())
                for kind in ("uncut", "cut")}
    assert profiles["uncut"]["removed_elements_per_env"] == 0.0 and profiles["cut"]["removed_elements_per_env"] > 0.0
    for p in profiles.values():
        assert p["profiled_wall_ms_per_step"] > 0.0 and isinstance(p["kernels"], list)
        assert p["kernel_ms_per_step"] == pytest.approx(sum(k["ms_per_step"] for k in p["kernels"]))


def test_bench_env_applies_and_records_the_contact_settings(device, tmp_path):
    """``--triangle-sweep``, ``--triangle-block-threads``, ``--surface-leaf-size``, ``--no-cull-groups``,
    ``--pose-per-step``, ``--surface-bounds``, ``--surface-bounds-lanes``, ``--contact-forces``,
    ``--defer-surface-deltas``, ``--rod-block-threads`` and ``--no-graph`` reach the env's contact system and world
    before the first step and are written with the result; the leaf size and the cull groups are the benchmark's only
    (the next env built has the defaults)."""
    import lapwarp
    import lapwarp.contact

    out = tmp_path / "bench.json"
    assert bench_env.main(["--device", device, "--task", "ThreadInHole", "--num-envs", "1", "--seconds", "0.05",
                           "--triangle-sweep", "colored", "--no-graph", "--surface-leaf-size", "4",
                           "--triangle-block-threads", "16", "--no-cull-groups", "--pose-per-step", "off",
                           "--rod-block-threads", "64", "--surface-bounds", "fused", "--surface-bounds-lanes", "32",
                           "--contact-forces", "off", "--defer-surface-deltas", "on", "--out", str(out)]) == 0
    (r,) = json.loads(out.read_text())["results"]
    assert r["triangle_sweep"] == "colored" and r["cuda_graph"] is False
    assert r["pose_per_step"] is False and r["rod_block_threads"] == 64
    assert r["surface_bounds"] == "fused" and r["surface_bounds_lanes"] == 32 and r["report_forces"] is False
    assert r["defer_surface_deltas"] is True
    assert r["triangle_block_threads"] == 16 and r["surface_leaf_size"] == 4 and r["cull_groups"] is False
    assert lapwarp.contact.SURFACE_LEAF_SIZE == 8 and lapwarp.contact.CULL_GROUPS is True
    env = lapwarp.make("ThreadInHole", num_envs=1, device=device)
    assert env.contact.surface_leaf_size == 8 and env.contact._surfaces[0]["clusters"].leaf_size == 8
    assert env.contact.cull_groups is True
    env.close()
    assert r["env_steps_per_s"] > 0


def test_bench_env_times_variants_in_one_process(device, tmp_path):
    """``--variant NAME=ARGS``: each variant's settings on top of the command's, one after another, each written to
    NAME.json beside ``--out`` and all of them into it; a malformed or duplicate variant is refused before anything is
    timed."""
    out = tmp_path / "all.json"
    base = ["--device", device, "--task", "ThreadInHole", "--num-envs", "1", "--seconds", "0.05"]
    assert bench_env.main([*base, "--variant", "plain=", "--variant", "nof=--contact-forces off --surface-bounds fused",
                           "--out", str(out)]) == 0
    plain = json.loads((tmp_path / "plain.json").read_text())["results"][0]
    nof = json.loads((tmp_path / "nof.json").read_text())["results"][0]
    assert plain["report_forces"] is True and plain["surface_bounds"] == "separate"
    assert nof["report_forces"] is False and nof["surface_bounds"] == "fused"
    assert sorted(json.loads(out.read_text())["variants"]) == ["nof", "plain"]
    for bad in (["--variant", "a b=--no-graph"], ["--variant", "x=--no-such-flag"],
                ["--variant", "x=", "--variant", "x=--no-graph"]):
        with pytest.raises(SystemExit):
            bench_env.main([*base, *bad, "--out", str(tmp_path / "bad.json")])
        assert not (tmp_path / "x.json").exists()


def test_bench_env_predicts_in_the_rod_sweep_where_asked(device, tmp_path):
    """``--predict-in-rod-sweep on|off`` moves a rods-only world's (RopeCutting's) substep prediction into its fused rod
    launch (RopeCutting's default since the forty-fourth session) or gives it its own; the result records where the
    prediction ran."""
    runs = []
    for flag in (["--predict-in-rod-sweep", "on"], ["--predict-in-rod-sweep", "off"]):
        out = tmp_path / f"bench_{flag[1]}.json"
        assert bench_env.main(["--device", device, "--task", "RopeCutting", "--num-envs", "1", "--seconds", "0.05",
                               *flag, "--out", str(out)]) == 0
        runs.append(json.loads(out.read_text())["results"][0]["predict_in_rod_sweep"])
    assert runs == [True, False]


def test_bench_env_splits_the_register_chain_solve_where_asked(device, tmp_path):
    """``--register-split on`` solves RopeCutting's ropes (the register solve, equal chains) with two threads per
    chain; the result records the setting."""
    runs = []
    for flag in ([], ["--register-split", "on"]):
        out = tmp_path / f"bench{len(flag)}.json"
        assert bench_env.main(["--device", device, "--task", "RopeCutting", "--num-envs", "1", "--seconds", "0.05",
                               "--set", "chain_solver=registers", *flag, "--out", str(out)]) == 0
        runs.append(json.loads(out.read_text())["results"][0]["chain_register_split"])
    assert runs == [False, True]


def test_bench_env_applies_and_records_register_caps(device, tmp_path, capsys):
    """``--max-registers KERNEL=N`` caps a kernel of the world's step (recorded with the result, beside the task's
    own caps: ThreadInHole's lagged vertex sweep, rods and pose kernel at 64); a malformed item or a cap out of range
    is a usage error before anything runs."""
    out = tmp_path / "bench.json"
    assert bench_env.main(["--device", device, "--task", "ThreadInHole", "--num-envs", "1", "--seconds", "0.05",
                           "--max-registers", "collide_particles=64", "--out", str(out)]) == 0
    (r,) = json.loads(out.read_text())["results"]
    assert r["max_registers"] == {"collide_particles": 64, "solve_vertices_fused": 64, "solve_rods_fused": 64,
                                  "pose_shapes_and_tools": 64} and r["env_steps_per_s"] > 0
    for bad, message in (("collide_particles", "KERNEL=N"), ("collide_particles=x", "KERNEL=N"),
                         ("collide_particles=300", "register cap must be an int")):
        with pytest.raises(SystemExit) as exc:
            bench_env.main(["--device", device, "--task", "ThreadInHole", "--max-registers", bad])
        assert exc.value.code == 2 and message in capsys.readouterr().err


def test_bench_env_replayed_expert_actions_reproduce_the_expert_run(device):
    """``--policy replay`` times the expert's regime without the expert: its recorded actions must take a fresh env
    of the same seed through the same states, cuts included (RopeCutting: the expert cuts ropes and the cut envs
    reset). Exact on the CPU (one thread, no atomics' order)."""
    kwargs = dict(num_envs=2, device=device, seed=3, use_cuda_graph=False)
    expert_env = lapwarp.make("RopeCutting", **kwargs)
    actions = bench_env.record_expert_actions(expert_env, 50)  # cuts at steps 7, 13, 21, 30, 48
    replay_env = lapwarp.make("RopeCutting", **kwargs)
    cuts = 0
    for a in actions:
        replay_env.step(a)
        cuts += int(replay_env.cutting.cut_happened.numpy().sum())
    tol = 0.0 if device == "cpu" else 1e-4
    for name in ("particle_q", "particle_qd"):
        expected = getattr(expert_env.world.state, name).numpy()
        assert np.abs(getattr(replay_env.world.state, name).numpy() - expected).max() <= tol, name
    for name in ("removed", "component"):
        assert np.array_equal(getattr(replay_env.cutting, name).numpy(), getattr(expert_env.cutting, name).numpy())
    assert cuts >= 3, "the replay cut (almost) nothing: the test would show little"


def test_bench_env_replay_writes_json_and_checks_its_length(device, tmp_path, capsys):
    out = tmp_path / "bench.json"
    assert bench_env.main(["--device", device, "--task", "Reach", "--num-envs", "2", "--seconds", "10",
                           "--policy", "replay", "--replay-steps", "12", "--out", str(out)]) == 0
    report = json.loads(out.read_text())
    (r,) = report["results"]
    # timing stops with the recording: 12 recorded steps, 5 of them warm-up
    assert r["policy"] == "replay" and r["replay_steps"] == 12 and r["env_steps"] == 7 * 2
    assert report["regime"] == "env step only, the expert's recorded actions replayed"
    with pytest.raises(SystemExit):
        bench_env.main(["--device", device, "--task", "Reach", "--policy", "replay", "--replay-steps", "5"])
    assert "--replay-steps must exceed the 5 warm-up steps, got 5" in capsys.readouterr().err


def test_tet_hold_counts_held_envs_and_refuses_a_world_without_a_hold(device, tmp_path, capsys):
    # ThreadInHole's hole is held by default: after a step every env ends held or, just reset, solved; the shares are
    # fractions and the JSON row names the hold; with the hold off there is nothing to count
    out = tmp_path / "hold.json"
    tet_hold.main(["--task", "ThreadInHole", "--device", device, "--num-envs", "2", "--steps", "3", "--out", str(out)])
    row = json.loads(out.read_text())
    assert (row["hold_speed"], row["hold_substeps"], len(row["held_per_step"])) == (1.0e-4, 10, 3)
    assert 0.0 <= row["held_at_step_end"] <= 1.0 and row["held_per_step"][-1] == 1.0  # at rest, untouched
    assert json.loads(capsys.readouterr().out.strip().splitlines()[-1])["steps"] == 3
    with pytest.raises(ValueError, match="holds no tets"):
        tet_hold.hold_fractions("ThreadInHole", device, 1, 1, "expert", overrides={"hole_hold_speed": 0.0})


def test_profile_step_records_warmup_timing_and_wall(device, tmp_path):
    out = tmp_path / "profile.json"
    assert profile_step.main(["--device", device, "--task", "Reach", "--num-envs", "2", "--steps", "2", "--warmup",
                              "1", "--timing", "all", "--policy", "random", "--out", str(out)]) == 0
    report = json.loads(out.read_text())
    assert report["warmup"] == 1 and report["timing"] == "all" and report["profiled_wall_ms_per_step"] > 0


def test_profile_step_with_torch_profiler(device, tmp_path, capsys):
    """``--profiler torch`` (with ``--graph`` where the device has graphs) runs the steps under PyTorch's profiler and
    writes the same report; on the CPU it sees no device kernels (rows empty, the wall time measured); ``--graph``
    without it is a usage error."""
    out = tmp_path / "profile.json"
    graph = ["--graph"] if device.startswith("cuda") else []
    assert profile_step.main(["--device", device, "--task", "Reach", "--num-envs", "2", "--steps", "2", "--warmup",
                              "1", "--policy", "random", "--profiler", "torch", *graph, "--out", str(out)]) == 0
    report = json.loads(out.read_text())
    assert report["profiler"] == "torch" and report["graph"] == bool(graph) and report["profiled_wall_ms_per_step"] > 0
    if device.startswith("cuda"):
        assert report["kernel_ms_per_step"] > 0 and report["kernels"]
        gaps = report["device_gaps"]
        assert gaps["busy_ms_per_step"] <= gaps["span_ms_per_step"] + 1e-9
    else:
        assert report["kernels"] == [] and "only the wall time" in capsys.readouterr().out
        assert report["device_gaps"]["gaps"] == []
    with pytest.raises(SystemExit):
        profile_step.main(["--task", "Reach", "--graph"])
    assert "--graph needs --profiler torch" in capsys.readouterr().err


def test_device_gaps_merge_overlaps_and_rank_idle_gaps():
    # two steps of device work in microseconds: overlapping events (another stream) merge, touching ones leave no gap
    events = [(0.0, 10.0, "a"), (5.0, 12.0, "b"), (12.0, 20.0, "c"), (50.0, 60.0, "d"), (62.0, 70.0, "e"),
              (65.0, 66.0, "f")]
    gaps = profile_step.device_gaps(events, 2, 5)
    assert gaps["span_ms_per_step"] == pytest.approx(70.0 / 1e3 / 2)
    assert gaps["busy_ms_per_step"] == pytest.approx((20.0 + 10.0 + 8.0) / 1e3 / 2)
    assert gaps["idle_ms_per_step"] == pytest.approx((30.0 + 2.0) / 1e3 / 2)
    assert gaps["gaps"] == [(30.0, "c", "d"), (2.0, "d", "e")]
    assert profile_step.device_gaps(events, 2, 1)["gaps"] == [(30.0, "c", "d")]
    assert profile_step.device_gaps([], 1, 3) == {"span_ms_per_step": 0.0, "busy_ms_per_step": 0.0,
                                                  "idle_ms_per_step": 0.0, "gaps": []}


def test_profile_step_diff_compares_two_profiles_kernel_by_kernel(tmp_path, capsys):
    def profile(path, kernels):
        path.write_text(json.dumps({"kernel_ms_per_step": sum(k[2] for k in kernels), "kernels": [
            {"name": n, "launches_per_step": c, "ms_per_step": t} for n, c, t in kernels]}))
        return str(path)

    first = profile(tmp_path / "a.json", [("cut", 11, 1.5), ("tets", 40, 5.0), ("only_a", 1, 0.1)])
    second = profile(tmp_path / "b.json", [("cut", 11, 0.5), ("tets", 40, 5.2), ("only_b", 2, 0.3)])
    assert profile_step.main(["--diff", first, second]) == 0
    out = capsys.readouterr().out
    lines = [line.split() for line in out.splitlines()[1:]]
    # largest difference first; a kernel missing from one profile counts 0 there
    assert [line[-1] for line in lines] == ["cut", "only_b", "tets", "only_a"]
    assert lines[0][:3] == ["1.500", "0.500", "+1.000"] and lines[1][:3] == ["0.000", "0.300", "-0.300"]
    assert "6.600 (first) / 6.000 (second), difference +0.600" in out.splitlines()[0]
    with pytest.raises(SystemExit):
        profile_step.main(["--diff", first, str(tmp_path / "missing.json")])
    assert "needs two profile JSON files" in capsys.readouterr().err


def test_profile_learner_splits_iterations_and_lists_operators(device, tmp_path, capsys):
    out = tmp_path / "learner.json"
    assert profile_learner.main(["--warmup", "1", "--iterations", "2", "--profile-iterations", "1", "--top", "5",
                                 "--out", str(out), "--", "--device", device, "--task", "Reach", "--preset", "cpu",
                                 "--num-envs", "4"]) == 0
    report = json.loads(out.read_text())
    assert report["num_envs"] == 4 and report["steps_per_env"] == 32 and report["iterations"] == 2
    assert report["rollout_s_per_it"] > 0 and report["update_s_per_it"] > 0 and 0 < report["update_share"] < 1
    # the rollouts hold 32 env steps and 32 actions each, timed within them: the totals nest (the medians need not:
    # a per-call median against a two-iteration median failed under load, 32 x 38.8 ms against 0.82 s)
    assert report["env_step_s_total"] + report["act_s_total"] <= report["rollout_s_total"]
    assert report["env_step_ms"] > 0 and report["act_ms"] > 0
    assert report["env_steps_per_s"] > 0 and 0 < len(report["top_operators"]) <= 5
    # the profiled iteration: one update, 32 env steps and actions
    assert report["ranges_ms"]["update"]["calls"] == 1 and report["ranges_ms"]["env.step"]["calls"] == 32
    assert "env-steps/s" in capsys.readouterr().out


@pytest.mark.parametrize("args, message", [
    (["--profile-iterations", "-1", "--", "--task", "Reach"], "--profile-iterations must be >= 0, got -1"),
    (["--iterations", "0", "--", "--task", "Reach"], "expected a positive integer, got 0"),
    (["--", "--task", "Reach", "--play", "model.pt"], "trains from scratch in one process"),
    (["--", "--task", "Reach", "--obs", "state", "--fast-pixels"], "applies to image observations"),
])
def test_profile_learner_refuses_bad_input_before_any_run(args, message, capsys, monkeypatch):
    import lapwarp

    def no_env(*_, **__):
        raise AssertionError("an env was built before the arguments were checked")

    monkeypatch.setattr(lapwarp, "make", no_env)
    with pytest.raises(SystemExit):
        profile_learner.main(args)
    assert message in capsys.readouterr().err


def test_bench_fused_compares_each_sweep_of_a_task(device, tmp_path):
    """``bench_fused.py`` times the per-colour and the fused tet and triangle sweeps of a task (one JSON line each)."""
    out = tmp_path / "fused.jsonl"
    assert bench_fused.main(["--device", device, "--num-envs", "2", "--no-physics", "--seconds", "0.05", "--tasks",
                             "TissueDissection", "--out", str(out)]) == 0
    rows = [json.loads(line) for line in out.read_text().splitlines()]
    assert [(r["variant"], r["threads"]) for r in rows] == [("tets-colored", 0), ("tets-fused", 32),
                                                            ("triangles-colored", 0), ("triangles-fused", 32)]
    assert all(r["env_steps_per_s"] > 0 and r["tets"] == 300 and r["triangle_colors"] > 1 for r in rows)


def test_ppo_trains_from_rgb_images(device, tmp_path, capsys):
    args = ["--device", device, "--preset", "cpu", "--obs", "rgb", "--num-envs", "4", "--max-iterations", "1",
            "--eval-envs", "2", "--log-dir", str(tmp_path)]
    assert ppo.main(args) == 0
    assert "evaluation on 2 episodes" in capsys.readouterr().out


def test_image_preset_uses_the_papers_cnn():
    cfg, _ = ppo.preset_config("paper", num_envs=8, max_iterations=10)
    cfg = ppo.use_images(cfg)
    assert cfg["actor"]["class_name"] == "CNNModel" and cfg["obs_groups"]["actor"] == ["image"]
    assert cfg["actor"]["cnn_cfg"]["kernel_size"] == [8, 4, 3] and cfg["actor"]["cnn_cfg"]["stride"] == [4, 2, 1]


def test_soak_counts_faults_and_checks_determinism(device, tmp_path, capsys):
    out = tmp_path / "soak.jsonl"
    assert soak.main(["--device", device, "--num-envs", "4", "--env-steps", "80", "--tasks", "DeflectSpheres",
                      "--determinism", "5", "--out", str(out), "--set", "contact_capacity=1"]) == 0
    lines = [json.loads(line) for line in out.read_text().splitlines()]
    runs = [r for r in lines if "env_steps" in r]
    assert [r["action_type"] for r in runs] == ["CONTINUOUS", "DISCRETE"]
    for r in runs:
        assert r["env_steps"] == 80 and r["nonfinite_observation_values"] == 0 and r["nonfinite_rewards"] == 0
        assert r["contact_systems"] and r["memory_bytes_end"] > 0
    determinism = [r for r in lines if "determinism_steps" in r]
    assert determinism and all(r["max_abs_observation_difference"] == 0.0 for r in determinism)  # CPU: bit-exact


@pytest.mark.parametrize("script, args, message", [
    (soak, ["--tasks", "Reach", "--action-types", "SIDEWAYS"], "invalid choice: 'SIDEWAYS'"),
    (soak, ["--tasks", "Reach", "--determinism", "-1"], "--determinism non-negative"),
    (soak, ["--tasks", "DeflectSpheres", "--set", "num_spheres=1"], "exceeds num_spheres=1"),
    (expert_success, ["--task", "Reach", "--episodes", "0"], "must be positive, got 256, 0 and 2000"),
    (expert_success, ["--task", "Reach", "--max-steps", "0"], "must be positive"),
    (expert_success, ["--task", "Reach", "--action-types", "BAR"], "invalid choice: 'BAR'"),
    (expert_success, ["--task", "DeflectSpheres", "--config", "num_spheres=5", "--config", "num_spheres=1"],
     "exceeds num_spheres=1"),
    (bench_env, ["--task", "Reach", "--seconds", "-1"], "expected a positive number, got -1.0"),
    (bench_env, ["--task", "Reach", "--num-envs", "4", "0"], "expected a positive integer, got 0"),
    (bench_env, ["--task", "Reach", "--set", "sphere_radus=0.01"], "unknown config key(s) ['sphere_radus']"),
    (profile_step, ["--task", "Reach", "--steps", "0"], "expected a positive integer, got 0"),
    (profile_step, ["--task", "Reach", "--warmup", "0"], "expected a positive integer, got 0"),
    (profile_step, ["--task", "Reach", "--timing", "some"], "invalid choice: 'some'"),
    (bench_env, ["--task", "Reach", "--pcr-rows", "-1"], "expected a non-negative integer, got -1"),
    (bench_env, ["--task", "Reach", "--triangle-sweep", "shared"], "invalid choice: 'shared'"),
    (profile_step, ["--task", "Reach", "--set", "invalid_actions=maybe"], "invalid_actions"),
    (soak, ["--tasks", "Reach", "--set", "seed=3"], "--set cannot set ['seed']"),
    (expert_success, ["--task", "Reach", "--config", "action_type=DISCRETE"], "--config cannot set ['action_type']"),
    (expert_success, ["--task", "Reach", "--action-noise", "0.5"], "add --action-types CONTINUOUS"),
    (expert_success, ["--task", "Reach", "--action-noise", "nan"], "--action-noise must be in [0, 10]"),
    (border_follower, ["--num-envs", "0"], "--num-envs must be positive"),
    (visibility, ["--task", "Reach", "--steps", "-1"], "--steps non-negative"),
    (visibility, ["--task", "DeflectSpheres", "--set", "num_spheres=1"], "exceeds num_spheres=1"),
    (border_follower, ["--rows-to-cut", "1"], "rows_to_cut"),
])
def test_benchmark_scripts_refuse_bad_input_before_any_run(script, args, message, capsys, monkeypatch):
    """A bad configuration anywhere in the list is a usage error before the first env is built (on the GPU the first
    configurations would otherwise run for minutes before the last one fails)."""
    import lapwarp

    def no_env(*_, **__):
        raise AssertionError("an env was built before the arguments were checked")

    monkeypatch.setattr(lapwarp, "make", no_env)
    with pytest.raises(SystemExit):
        script.main(["--device", "cpu", *args])
    assert message in capsys.readouterr().err


def test_check_config_validates_without_building():
    import lapwarp

    cfg = lapwarp.check_config("DeflectSpheres", num_spheres=3, num_deflect_to_win=2)
    assert (cfg.num_spheres, cfg.num_deflect_to_win) == (3, 2)
    for bad in ({"num_spheres": 1}, {"no_such_key": 1}, {"action_type": "SIDEWAYS"}):
        with pytest.raises(ValueError):
            lapwarp.check_config("DeflectSpheres", **bad)
    with pytest.raises(ValueError, match="unknown task"):
        lapwarp.check_config("NoSuchTask")


def test_progress_line_names_faults():
    import torch

    logs = [{"/action/nonfinite_fraction": torch.tensor(0.0), "/env/unstable_fraction": torch.tensor(0.5)},
            {"/action/nonfinite_fraction": torch.tensor(0.02), "/env/unstable_fraction": torch.tensor(0.0)}]
    assert ppo.fault_summary(logs) == "  [non-finite actions 1.000%, unstable envs 25.000%]"
    assert ppo.fault_summary([{"/action/nonfinite_fraction": torch.tensor(0.0)}]) == ""


def test_learning_rate_options_override_the_preset():
    parser = ppo.build_parser()
    args = parser.parse_args(["--preset", "gpu", "--lr-schedule", "fixed", "--learning-rate", "3e-4"])
    *_, cfg, _ = ppo.training_config(args, parser, "cpu")
    assert (cfg["algorithm"]["schedule"], cfg["algorithm"]["learning_rate"], cfg["algorithm"]["desired_kl"]) == (
        "fixed", 3e-4, None)
    args = parser.parse_args(["--preset", "gpu", "--lr-schedule", "linear", "--max-iterations", "250"])
    *_, cfg, _ = ppo.training_config(args, parser, "cpu")
    assert cfg["algorithm"]["class_name"] is ppo.LinearSchedulePPO and cfg["algorithm"]["total_updates"] == 250
    assert (cfg["algorithm"]["schedule"], cfg["algorithm"]["desired_kl"]) == ("fixed", None)
    for bad in (["--learning-rate", "0"], ["--learning-rate", "nan"], ["--preset", "paper", "--lr-schedule", "fixed"]):
        with pytest.raises(SystemExit):
            ppo.training_config(parser.parse_args(bad), parser, "cpu")


def test_final_noise_std_caps_the_action_noise_linearly(capsys):
    """``--final-noise-std``: the config's algorithm becomes ``ScheduledPPO`` (the rate left to the preset) or adds
    the cap to the paper preset's linear schedule; the cap falls from the initial std to the final one at the last
    update and clamps rsl-rl's std (its parameter left alone); out-of-range values are usage errors."""
    from rsl_rl.modules.distribution import GaussianDistribution

    parser = ppo.build_parser()
    args = parser.parse_args(["--preset", "gpu", "--final-noise-std", "0.2", "--max-iterations", "4"])
    *_, cfg, _ = ppo.training_config(args, parser, "cpu")
    alg = cfg["algorithm"]
    assert alg["class_name"] is ppo.ScheduledPPO and (alg["total_updates"], alg["decay_rate"], alg["final_noise_std"],
                                                      alg["schedule"]) == (4, False, 0.2, "adaptive")
    args = parser.parse_args(["--preset", "paper", "--final-noise-std", "0.3"])
    *_, cfg, _ = ppo.training_config(args, parser, "cpu")
    assert cfg["algorithm"]["class_name"] is ppo.LinearSchedulePPO and cfg["algorithm"]["final_noise_std"] == 0.3
    for bad in ("0", "nan", "11"):
        with pytest.raises(SystemExit):
            ppo.training_config(parser.parse_args(["--final-noise-std", bad]), parser, "cpu")
        assert "--final-noise-std must be in (0, 10]" in capsys.readouterr().err

    # the schedule itself, on a bare object with the attributes PPO.__init__ would have set
    for std_type in ("log", "scalar"):
        alg = object.__new__(ppo.ScheduledPPO)
        distribution = GaussianDistribution(2, init_std=1.0, std_type=std_type)
        alg._raw_actor = torch.nn.Module()
        alg._raw_actor.distribution = distribution
        alg.total_updates, alg.decay_rate, alg.final_noise_std = 4, False, 0.2
        alg.initial_noise_std, alg.updates_done = None, 0
        caps = []
        for _ in range(4):
            alg.apply_schedules()
            caps.append(distribution.std_range[1])
            distribution.update(torch.zeros(3, 2))
            assert torch.allclose(distribution.std, torch.full((3, 2), caps[-1]))  # the std in use is the cap
        assert caps == pytest.approx([0.8, 0.6, 0.4, 0.2])
        assert distribution.log_std_range[1] == pytest.approx(math.log(0.2))


def test_update_shape_options_override_the_preset(capsys):
    parser = ppo.build_parser()
    args = parser.parse_args(["--preset", "gpu", "--learning-epochs", "3", "--mini-batches", "8"])
    *_, cfg, _ = ppo.training_config(args, parser, "cpu")
    assert (cfg["algorithm"]["num_learning_epochs"], cfg["algorithm"]["num_mini_batches"]) == (3, 8)
    *_, cfg, _ = ppo.training_config(parser.parse_args(["--preset", "gpu"]), parser, "cpu")
    assert (cfg["algorithm"]["num_learning_epochs"], cfg["algorithm"]["num_mini_batches"]) == (5, 4)
    for bad, message in ((["--learning-epochs", "0"], "--learning-epochs must be positive"),
                         (["--mini-batches", "-1"], "--mini-batches must be positive"),
                         (["--num-envs", "2", "--mini-batches", "65"], "65 mini-batches exceed the rollout's 64")):
        with pytest.raises(SystemExit):
            ppo.training_config(parser.parse_args(["--preset", "gpu", *bad]), parser, "cpu")
        assert message in capsys.readouterr().err


def test_init_noise_std_sets_the_actor_distribution(capsys):
    parser = ppo.build_parser()
    for extra in ([], ["--obs", "rgb"]):
        *_, cfg, _ = ppo.training_config(parser.parse_args(["--preset", "gpu", "--init-noise-std", "0.4", *extra]),
                                         parser, "cpu")
        assert cfg["actor"]["distribution_cfg"] == {"class_name": "GaussianDistribution", "init_std": 0.4,
                                                    "std_type": "log"}
    *_, cfg, _ = ppo.training_config(parser.parse_args(["--preset", "gpu"]), parser, "cpu")
    assert cfg["actor"]["distribution_cfg"]["init_std"] == 1.0
    for bad in ("0", "-1", "nan", "11"):
        with pytest.raises(SystemExit):
            ppo.training_config(parser.parse_args(["--preset", "gpu", "--init-noise-std", bad]), parser, "cpu")
        assert "--init-noise-std must be in (0, 10]" in capsys.readouterr().err



def test_obs_normalization_normalises_the_state_models(tmp_path, capsys):
    parser = ppo.build_parser()
    *_, cfg, _ = ppo.training_config(parser.parse_args(["--preset", "gpu", "--obs-normalization"]), parser, "cpu")
    assert cfg["actor"]["obs_normalization"] and cfg["critic"]["obs_normalization"]
    *_, cfg, _ = ppo.training_config(parser.parse_args(["--preset", "gpu"]), parser, "cpu")
    assert not cfg["actor"]["obs_normalization"] and not cfg["critic"]["obs_normalization"]
    # an image run: only its state critic reads a vector to normalise
    *_, cfg, _ = ppo.training_config(parser.parse_args(["--preset", "gpu", "--obs", "rgb", "--critic", "state",
                                                        "--obs-normalization"]), parser, "cpu")
    assert cfg["critic"]["obs_normalization"] and "obs_normalization" not in cfg["actor"].get("cnn_cfg", {})
    assert cfg["actor"]["class_name"] == "CNNModel" and not cfg["actor"]["obs_normalization"]
    with pytest.raises(SystemExit):
        ppo.training_config(parser.parse_args(["--preset", "gpu", "--obs", "rgb", "--obs-normalization"]), parser,
                            "cpu")
    assert "--obs-normalization applies to state observations" in capsys.readouterr().err
    # a run's checkpoint carries the running statistics of the observations it saw
    assert ppo.main(["--task", "Reach", "--device", "cpu", "--preset", "cpu", "--num-envs", "8", "--max-iterations",
                     "1", "--eval-envs", "4", "--log-dir", str(tmp_path), "--obs-normalization"]) == 0
    checkpoint = torch.load(sorted(tmp_path.glob("Reach/*/model_*.pt"))[-1], weights_only=False)
    for model in ("actor_state_dict", "critic_state_dict"):
        stats = checkpoint[model]
        assert int(stats["obs_normalizer.count"]) == 8 * 32  # one rollout: 8 envs x 32 steps
        assert torch.all(stats["obs_normalizer._std"] > 0) and torch.any(stats["obs_normalizer._mean"] != 0)

def test_unloadable_checkpoint_and_unwritable_log_dir_are_usage_errors(tmp_path, capsys):
    not_a_checkpoint = tmp_path / "notes.pt"
    not_a_checkpoint.write_text("not a checkpoint")
    base = ["--device", "cpu", "--preset", "cpu", "--task", "Reach", "--num-envs", "2", "--eval-envs", "2"]
    with pytest.raises(SystemExit):
        ppo.main([*base, "--play", str(not_a_checkpoint)])
    assert "does not load into this run's models (UnpicklingError" in capsys.readouterr().err
    with pytest.raises(SystemExit):  # a folder below a file cannot be made
        ppo.main([*base, "--max-iterations", "1", "--log-dir", str(not_a_checkpoint / "runs")])
    assert f"--log-dir {str(not_a_checkpoint / 'runs')!r}" in capsys.readouterr().err


def test_seed_is_set_by_its_option_not_by_set(capsys):
    with pytest.raises(SystemExit):
        ppo.main(["--device", "cpu", "--preset", "cpu", "--task", "Reach", "--num-envs", "2", "--max-iterations", "1",
                  "--set", "seed=3"])
    assert "--set cannot set ['seed']" in capsys.readouterr().err


def test_unknown_compile_mode_is_a_usage_error(capsys):
    parser = ppo.build_parser()
    assert parser.parse_args(["--compile", "max-autotune-no-cudagraphs"]).compile == "max-autotune-no-cudagraphs"
    with pytest.raises(SystemExit):
        parser.parse_args(["--compile", "fastest"])
    assert "invalid choice: 'fastest'" in capsys.readouterr().err


class _EndsAtStepTwo:
    """Four envs whose episodes all end at step 2 before the time limit, envs 0 and 3 in success and envs 1 and 2 in
    failure (as RopeCutting's wrong cut or an unstable reset ends one): the env's own success flag tells them apart.
    With ``end_steps`` / ``time_outs`` / ``success`` per env the episodes end when and as these say."""

    device = "cpu"

    def __init__(self, end_steps=(2, 2, 2, 2), time_outs=(False,) * 4, success=(1, 0, 0, 1), max_episode_length=10):
        import warp as wp

        self.num_envs, self.max_episode_length = len(end_steps), max_episode_length
        self.end_steps, self.time_outs, self.success = end_steps, time_outs, success
        self.last_episode_success = wp.zeros(self.num_envs, dtype=wp.int32, device="cpu")
        self.steps = 0

    def reset(self):
        import torch

        self.steps = 0
        return torch.zeros(self.num_envs, 1), {}

    def step(self, actions):
        import torch

        self.steps += 1
        done = torch.tensor([self.steps == end for end in self.end_steps])
        self.last_episode_success.assign([s if self.steps == end else 0
                                          for s, end in zip(self.success, self.end_steps, strict=True)])
        return (torch.full((self.num_envs, 1), float(self.steps)), torch.ones(self.num_envs), done,
                {"time_outs": done & torch.tensor(self.time_outs)})


def test_evaluation_counts_failed_episodes_as_failures():
    evaluation = ppo.evaluate(_EndsAtStepTwo(), lambda obs: obs * 0.0)
    success, mean_return = evaluation
    assert (success, mean_return) == (0.5, 2.0)
    # the two failures ended early (no time-out) with zero actions throughout: both stalled; successes took 2 steps
    assert (evaluation.episodes, evaluation.timeouts, evaluation.terminations, evaluation.stalled,
            evaluation.success_steps) == (4, 0, 2, 2, 2.0)


def test_evaluation_tells_time_outs_and_stalled_policies_apart():
    """Env 0 succeeds at step 30, envs 1-3 reach the time limit (40) and env 4 ends early in failure at 25. The policy
    moves (|a| = 0.5) until its stop step, then holds still (|a| = 0.01): env 1 stops at 35 (5 still steps of the
    last 20: window mean 0.3775, moving), env 2 at 10 (30 still steps: stalled), env 3 never; env 4 stops at 2
    (stalled at its end). The stall window is ``STALL_WINDOW`` = 20 steps, the threshold 0.05."""
    import torch

    env = _EndsAtStepTwo(end_steps=(30, 40, 40, 40, 25), time_outs=(False, True, True, True, False),
                         success=(1, 0, 0, 0, 0), max_episode_length=40)
    stop = torch.tensor([1000.0, 35.0, 10.0, 1000.0, 2.0])

    def policy(obs):  # obs = the step count so far: move until the env's stop step, then hold still
        moving = obs[:, 0] < stop
        return torch.where(moving, 0.5, 0.01)[:, None].expand(-1, 2) * torch.tensor([1.0, -1.0])

    evaluation = ppo.evaluate(env, policy)
    assert evaluation.success == pytest.approx(0.2)
    assert (evaluation.timeouts, evaluation.terminations, evaluation.stalled, evaluation.success_steps) == (
        3, 1, 2, 30.0)
    assert "4 of 5 failed: 3 at the time limit, 1 ended early, 2 with their actions died away" in evaluation.summary()
    # discrete actions (indices) have no magnitude to die away: no stall count
    assert ppo.evaluate(_EndsAtStepTwo(), lambda obs: obs[:, 0].long()).stalled is None


def test_trace_policy_writes_actions_features_and_forced_components(device, tmp_path, capsys):
    """``train/trace_policy.py`` rolls a checkpoint out in the env its training run built and writes one CSV row per
    (step, traced env); a forced component holds its value from ``--force-from`` on and not before."""
    import csv

    import trace_policy

    base = ["--task", "Reach", "--device", device, "--preset", "cpu", "--num-envs", "4", "--eval-envs", "2"]
    assert ppo.main([*base, "--max-iterations", "1", "--log-dir", str(tmp_path)]) == 0
    (checkpoint,) = tmp_path.glob("Reach/*/model_0.pt")
    out = tmp_path / "trace.csv"
    capsys.readouterr()
    assert trace_policy.main([str(checkpoint), "--task", "Reach", "--preset", "cpu", "--device", device, "--envs",
                              "3", "--trace-envs", "2", "--steps", "6", "--force", "1=0.75", "--force-from", "2",
                              "--out", str(out)]) == 0
    assert "Reach, 3 envs x 6 steps (deterministic, forced [(1, 0.75)] from step 2)" in capsys.readouterr().out
    rows = list(csv.DictReader(out.open()))
    env = lapwarp.make("Reach", num_envs=1, device=device)
    assert [(int(r["step"]), int(r["env"])) for r in rows] == [(s, e) for s in range(6) for e in range(2)]
    assert set(env.reward_features) <= set(rows[0]) and {"action_0", "action_2", "reward", "done"} <= set(rows[0])
    forced = [float(r["action_1"]) for r in rows]
    assert all(v == 0.75 for v in forced[4:]) and not any(v == 0.75 for v in forced[:4])
    for bad, message in ((["--force", "7=1.0"], "outside the 3 action components"),
                         (["--force", "1=nan"], "expected COMPONENT=VALUE"),
                         (["--envs", "2", "--trace-envs", "3"], "--trace-envs 3 exceeds --envs 2"),
                         (["--set", "seed=4"], "the env's seed is --seed")):
        with pytest.raises(SystemExit):
            trace_policy.main([str(checkpoint), "--task", "Reach", "--preset", "cpu", "--device", device, *bad,
                               "--out", str(out)])
        assert message in capsys.readouterr().err


def test_state_run_with_a_privileged_critic(tmp_path):
    """``--critic state`` on a state run: the actor reads the policy's observation, the critic the task's privileged
    layout (the policy's values first, then e.g. Reach's offset to the target), and the run trains and evaluates."""
    parser = ppo.build_parser()
    *_, cfg, overrides = ppo.training_config(parser.parse_args(["--preset", "gpu", "--critic", "state"]), parser,
                                             "cpu")
    assert cfg["obs_groups"] == {"actor": ["policy"], "critic": ["critic"]} and overrides["privileged_critic"]
    *_, cfg, overrides = ppo.training_config(parser.parse_args(["--preset", "gpu"]), parser, "cpu")
    assert cfg["obs_groups"] == {"actor": ["policy"], "critic": ["policy"]} and "privileged_critic" not in overrides
    assert ppo.main(["--task", "Reach", "--device", "cpu", "--preset", "cpu", "--num-envs", "8", "--max-iterations",
                     "1", "--eval-envs", "4", "--log-dir", str(tmp_path), "--critic", "state"]) == 0
    checkpoint = torch.load(sorted(tmp_path.glob("Reach/*/model_*.pt"))[-1], weights_only=False)
    env = lapwarp.make("Reach", num_envs=1, device="cpu", privileged_critic=True)
    obs, _ = env.reset()
    policy_dim, critic_dim = obs["policy"].shape[1], obs["critic"].shape[1]
    assert critic_dim > policy_dim

    def first_weight(state):  # the first linear layer's weight: (hidden, input dim)
        return next(v for k, v in state.items() if k.endswith("weight") and v.dim() == 2)

    assert first_weight(checkpoint["actor_state_dict"]).shape[1] == policy_dim
    assert first_weight(checkpoint["critic_state_dict"]).shape[1] == critic_dim


def test_entropy_coef_sets_the_loss_weight(capsys):
    parser = ppo.build_parser()
    for preset in ("gpu", "paper"):
        *_, cfg, _ = ppo.training_config(parser.parse_args(["--preset", preset, "--entropy-coef", "0.005"]), parser,
                                         "cpu")
        assert cfg["algorithm"]["entropy_coef"] == 0.005
    *_, cfg, _ = ppo.training_config(parser.parse_args(["--preset", "gpu"]), parser, "cpu")
    assert cfg["algorithm"]["entropy_coef"] == 0.0
    for bad in ("-0.1", "nan", "2"):
        with pytest.raises(SystemExit):
            ppo.training_config(parser.parse_args(["--preset", "gpu", "--entropy-coef", bad]), parser, "cpu")
        assert "--entropy-coef must be in [0, 1]" in capsys.readouterr().err


def test_expert_success_with_action_noise():
    """``expert_success.run``: the Reach expert solves its first episodes; noise on its actions changes what the
    episodes return (so it is applied), and each record gives the counted episodes' mean return and length."""
    clean = expert_success.run("Reach", {}, "CONTINUOUS", 4, 4, 500, "cpu", 0, True)
    noisy = expert_success.run("Reach", {}, "CONTINUOUS", 4, 4, 500, "cpu", 0, True, action_noise=0.3)
    assert clean["episodes"] == noisy["episodes"] == 4 and clean["success_rate"] == 1.0
    assert clean["action_noise"] == 0.0 and noisy["action_noise"] == 0.3
    assert 0 < clean["mean_length"] <= 500 and 0 < noisy["mean_length"] <= 500
    assert math.isfinite(clean["mean_return"]) and noisy["mean_return"] != clean["mean_return"]


def test_expert_success_sets_world_settings(capsys):
    """``--world KEY=VALUE``: a World setting applied before the first step and recorded; the World still checks
    its value (a non-bool split is refused at the step)."""
    r = expert_success.run("Reach", {}, "CONTINUOUS", 2, 2, 500, "cpu", 0, True, world={"iterations": 2})
    assert r["world"] == {"iterations": 2} and r["episodes"] == 2
    # names the World does not have, or its methods, are usage errors (checked on the first env made)
    for key, message in (("chain_split", "--world chain_split: Reach's World has no setting 'chain_split'"),
                         ("step", "has no setting 'step'")):
        with pytest.raises(SystemExit):
            expert_success.main(["--device", "cpu", "--task", "Reach", "--num-envs", "1", "--world", f"{key}=1"])
        assert message in capsys.readouterr().err
    with pytest.raises(ValueError, match="chain_register_split must be a bool"):
        expert_success.run("RopeCutting", {}, "CONTINUOUS", 1, 1, 2, "cpu", 0, True,
                           world={"chain_register_split": "yes"})


def test_border_follower_records_each_cut_rule():
    """``benchmarks/border_follower.py`` on 2 envs for one rule: a record per rule with every first episode counted
    (the follower's success is measured in benchmarks/results/session24, not asserted: it is a diagnostic)."""
    record = border_follower.run("touch", 2, 5, "cpu", 2)
    assert record["episodes"] == 2 and 0 <= record["successes"] <= 2 and record["cut_removal"] == "touch"
    assert 0 < record["mean_length"] <= 400 and math.isfinite(record["mean_return"])


def test_visibility_reports_each_visual_object():
    """``benchmarks/visibility.py``: every visual object of the scene gets the fraction of envs showing it; the board
    fills the view of every env, and each fraction is one of k / num_envs."""
    record = visibility.visibility("DeflectSpheres", {"single_instrument": False}, 4, 2, "cpu", 1, 32)
    shown = record["visible_fraction"]
    assert shown["board"] == 1.0 and record["image"] == [32, 32] and record["steps_after_reset"] == 2
    assert {"right_cauter/shaft", "left_cauter/shaft"} <= set(shown)
    assert all(v * 4 == int(v * 4) and 0.0 <= v <= 1.0 for v in shown.values())


def test_proprio_group_beside_images(tmp_path, capsys):
    """``--proprio``: the actor (and a critic reading the actor's groups) also reads the ``proprio`` group, the
    instruments' PTSD mapped from their state limits to [-1, 1]; a 1-iteration run trains and evaluates with it, and
    the actor's MLP input grows by the group's 4 values per instrument."""
    parser = ppo.build_parser()
    *_, cfg, overrides = ppo.training_config(parser.parse_args(["--preset", "gpu", "--obs", "rgb", "--proprio"]),
                                             parser, "cpu")
    assert overrides["proprioception"] and cfg["obs_groups"] == {"actor": ["image", "proprio"],
                                                                 "critic": ["image", "proprio"]}
    *_, cfg, _ = ppo.training_config(parser.parse_args(["--preset", "gpu", "--obs", "rgb", "--critic", "state",
                                                        "--proprio"]), parser, "cpu")
    assert cfg["obs_groups"] == {"actor": ["image", "proprio"], "critic": ["critic"]}
    with pytest.raises(SystemExit):
        ppo.training_config(parser.parse_args(["--preset", "gpu", "--proprio"]), parser, "cpu")
    assert "--proprio applies to image observations" in capsys.readouterr().err
    assert ppo.main(["--task", "DeflectSpheres", "--device", "cpu", "--preset", "cpu", "--obs", "rgb", "--num-envs",
                     "4", "--max-iterations", "1", "--eval-envs", "2", "--log-dir", str(tmp_path), "--proprio",
                     "--critic", "state", "--set", "single_instrument=False",
                     "max_episode_steps=40"]) == 0  # a short evaluation (Table C's 2,500 steps took ~40 s on the CPU)
    checkpoint = torch.load(sorted(tmp_path.glob("DeflectSpheres/*/model_*.pt"))[-1], weights_only=False)
    # the MLP reads the 64x64 NatureCNN's 64 x 4 x 4 features and the two instruments' 2 x 4 PTSD values
    assert checkpoint["actor_state_dict"]["mlp.0.weight"].shape[1] == 64 * 4 * 4 + 8
    env = lapwarp.make("DeflectSpheres", num_envs=2, device="cpu", observation_type="RGB", proprioception=True,
                       single_instrument=False)
    obs, _ = env.reset()
    ptsd = env.rig.ptsd.numpy().reshape(2, 8).astype(np.float64)
    low = np.tile(np.radians([-90.0, -90.0, -90.0]).tolist() + [0.0], 2)
    high = np.tile(np.radians([90.0, 90.0, 90.0]).tolist() + [0.3], 2)
    assert [s.tpsd.state_high[3] for s in env.rig.specs] == [0.3, 0.3]  # the limits this reference assumes
    np.testing.assert_allclose(obs["proprio"].numpy(), 2.0 * (ptsd - low) / (high - low) - 1.0, atol=1e-5)
    for bad, message in ((dict(observation_type="STATE"), "already holds it"),
                         (dict(task="Reach"), "no instrument rig")):
        with pytest.raises(ValueError, match=message):
            lapwarp.make(bad.pop("task", "DeflectSpheres"), num_envs=1, device="cpu",
                         **{"observation_type": "RGB", **bad}, proprioception=True)
    with pytest.raises(ValueError, match="gymnasium adapters"):
        LapwarpVectorEnv("DeflectSpheres", num_envs=1, observation_type="RGB", proprioception=True)


def test_cloth_sag_reports_a_hanging_cloth_per_second(device, tmp_path, capsys):
    """One record per simulated second per setting: the cloth hangs below its flat rest plane (z = 0) and not by more
    than its 75 mm side; a malformed setting is a usage error."""
    out = tmp_path / "sag.jsonl"
    assert cloth_sag.main(["--device", device, "--settings", "2x1", "--seconds", "1", "--out", str(out)]) == 0
    (row,) = [json.loads(line) for line in out.read_text().splitlines()]
    assert (row["physics_substeps"], row["cloth_newton_steps"]) == (2, 1)
    assert len(row["centre_z_m"]) == len(row["lowest_z_m"]) == 1
    assert -0.075 < row["lowest_z_m"][0] <= row["centre_z_m"][0] < 0.0
    for bad in ("8", "8x0", "ax2"):
        with pytest.raises(SystemExit):
            cloth_sag.main(["--settings", bad])
        err = capsys.readouterr().err
        assert "SUBSTEPSxNEWTON" in err or "must be positive" in err


def test_launch_counts_sees_the_worlds_replayed_launches(tmp_path, capsys):
    # the World replays recorded wp.Launch objects (not wp.launch): the count must include them; DeflectSpheres'
    # world step (10 substeps of integration, contact and velocity update) is most of its operations
    assert launch_counts.main(["--tasks", "DeflectSpheres", "--out", str(tmp_path / "c.json")]) == 0
    row = json.loads((tmp_path / "c.json").read_text())["results"][0]
    assert row["task"] == "DeflectSpheres" and row["ops_per_step"] == sum(row["by_name"].values())
    replayed = sum(n for name, n in row["by_name"].items() if "integrate" in name or "collide" in name)
    assert replayed >= 10 and row["kernels_per_step"] > 20
    assert "device operations per env step" in capsys.readouterr().out
