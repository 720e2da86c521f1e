"""``train/ppo.py --distributed`` (issue #20): per-rank settings from torchrun's variables, distinct seed streams per
rank, and a two-process gloo training run of the whole path (rsl-rl's gradient averaging included) on the CPU."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest
import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "train"))

import rank_setup  # noqa: E402


def torchrun_env(world_size, rank, local_rank):
    return {"WORLD_SIZE": str(world_size), "RANK": str(rank), "LOCAL_RANK": str(local_rank)}


def test_rank_settings_follow_the_torchrun_variables():
    two_nodes_rank3 = rank_setup.rank_settings(torchrun_env(4, 3, 1), seed=7, device=None, cuda_available=True)
    assert two_nodes_rank3 == rank_setup.RankSettings(4, 3, 1, "cuda:1", 7 + 3 * 2**32)
    assert not two_nodes_rank3.is_main and two_nodes_rank3.distributed
    main = rank_setup.rank_settings(torchrun_env(2, 0, 0), seed=7, device="cuda", cuda_available=True)
    assert main.device == "cuda:0" and main.is_main and main.seed == 7  # rank 0 = the single-process run
    assert rank_setup.rank_settings(torchrun_env(2, 1, 1), 0, None, cuda_available=False).device == "cpu"
    assert rank_setup.rank_settings(torchrun_env(2, 1, 1), 0, "cpu", cuda_available=True).device == "cpu"
    assert rank_setup.rank_settings(torchrun_env(2, 1, 1), 0, "cuda:1", cuda_available=True).device == "cuda:1"


@pytest.mark.parametrize("environ, device, message", [
    ({}, None, "WORLD_SIZE"),
    ({"WORLD_SIZE": "2", "RANK": "x", "LOCAL_RANK": "0"}, None, "RANK"),
    (torchrun_env(2, 2, 0), None, "inconsistent"),
    (torchrun_env(2, 0, 1), None, "inconsistent"),
    (torchrun_env(2, 1, 1), "cuda:0", "its own GPU, cuda:1"),
])
def test_rank_settings_reject_missing_or_inconsistent_variables(environ, device, message):
    with pytest.raises(ValueError, match=message):
        rank_setup.rank_settings(environ, 0, device, cuda_available=True)


def test_rank_seeds_give_distinct_env_streams(device):
    import lapwarp

    def first_observation(seed):
        env = lapwarp.make("Reach", num_envs=3, device=device, seed=seed)
        obs, _ = env.reset()
        return obs["policy"].cpu()

    single = first_observation(5)
    rank0, rank1 = (first_observation(rank_setup.rank_seed(5, r)) for r in (0, 1))
    assert torch.equal(single, rank0)
    # every env of rank 1 starts elsewhere than every env of rank 0 (no shared stream), and than the run of seed 6
    assert torch.cdist(rank0, rank1).min() > 1e-3
    assert torch.cdist(first_observation(6), rank1).min() > 1e-3


def test_collectives_are_identities_in_one_process():
    assert rank_setup.sum_over_ranks([1, 2.5], "cpu") == [1.0, 2.5]
    assert rank_setup.gather_objects("x") == ["x"]


def test_ppo_usage_errors_for_distributed_runs(capsys):
    import ppo

    with pytest.raises(SystemExit):
        ppo.main(["--distributed", "--play", "nothing.pt"])
    assert "--play evaluates in one process" in capsys.readouterr().err
    saved = {k: os.environ.pop(k) for k in rank_setup.TORCHRUN_VARIABLES if k in os.environ}
    try:
        with pytest.raises(SystemExit):
            ppo.main(["--distributed", "--device", "cpu"])
        assert "torchrun --nproc_per_node=N" in capsys.readouterr().err
    finally:
        os.environ.update(saved)


def test_two_process_gloo_training(tmp_path):
    """torchrun with two CPU processes: both train, gradients are averaged (equal parameters at the end), only rank 0
    prints, writes a run directory and evaluates, and the totals count both ranks."""
    log_dir = tmp_path / "runs"
    cmd = [sys.executable, "-m", "torch.distributed.run", "--nproc_per_node=2", "--standalone",
           str(ROOT / "train" / "ppo.py"), "--task", "Reach", "--distributed", "--device", "cpu", "--preset", "cpu",
           "--num-envs", "4", "--max-iterations", "2", "--eval-envs", "4", "--log-dir", str(log_dir)]
    done = subprocess.run(cmd, capture_output=True, text=True, timeout=600, cwd=tmp_path)
    assert done.returncode == 0, done.stderr[-3000:]
    out = done.stdout
    assert out.count("training Reach: preset cpu, 2 processes x 4 envs") == 1
    assert out.count("Actor Model") == 1  # rank 1's rsl-rl set-up output is silenced
    assert len(re.findall(r"^it +\d+/2 ", out, flags=re.M)) == 2
    assert "trained 512 env-steps on 2 process(es)" in out  # 2 ranks x 4 envs x 32 steps x 2 iterations
    assert "policy parameters identical on all ranks: yes" in out
    assert out.count("evaluation on 4 episodes") == 1
    runs = list((log_dir / "Reach").iterdir())
    assert len(runs) == 1 and sorted(p.name for p in runs[0].glob("model_*.pt")) == ["model_0.pt", "model_1.pt"]


@pytest.mark.parametrize("preset, per_rank", [("gpu", 8), ("paper", 2 * 4 * 128 // 256)])
def test_same_global_minibatch_splits_each_rank_rollout_world_size_times(preset, per_rank):
    """Two ranks with --same-global-minibatch: each rank's rollout is split into twice the preset's mini-batches, so
    the mini-batch summed over ranks (and the optimiser steps per env-step) equal one process's."""
    import ppo

    parser = ppo.build_parser()
    args = parser.parse_args(["--distributed", "--same-global-minibatch", "--preset", preset, "--num-envs", "4"])
    _, num_envs, iterations, cfg, _ = ppo.training_config(args, parser, "cpu", world_size=2)
    single, _ = ppo.preset_config(preset, num_envs, iterations)
    assert cfg["algorithm"]["num_mini_batches"] == 2 * single["algorithm"]["num_mini_batches"] == per_rank
    rollout = num_envs * cfg["num_steps_per_env"]
    assert 2 * rollout // cfg["algorithm"]["num_mini_batches"] == rollout // single["algorithm"]["num_mini_batches"]
    plain = parser.parse_args(["--distributed", "--preset", preset, "--num-envs", "4"])
    assert ppo.training_config(plain, parser, "cpu", world_size=2)[3]["algorithm"] == single["algorithm"]


def test_same_global_minibatch_usage_errors(capsys):
    import ppo

    parser = ppo.build_parser()
    with pytest.raises(SystemExit):
        ppo.training_config(parser.parse_args(["--same-global-minibatch"]), parser, "cpu")
    assert "applies to --distributed runs" in capsys.readouterr().err
    args = parser.parse_args(["--distributed", "--same-global-minibatch", "--preset", "paper", "--num-envs", "1"])
    with pytest.raises(SystemExit):  # 1 env x 128 steps: 1 mini-batch of 128 per rank x 200 ranks > 128 samples
        ppo.training_config(args, parser, "cpu", world_size=200)
    assert "exceed the rollout's 128 samples" in capsys.readouterr().err
