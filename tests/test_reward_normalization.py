"""``train/reward_normalization.py``: rewards scaled by the running discounted return's spread (sb3's
``VecNormalize(norm_reward=True)``, which the LapGym paper's runs used), against a NumPy reference of that algorithm
and against the closed-form variance of a discounted sum of i.i.d. rewards; and ``ppo.py --reward-normalization``."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest
import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "train"))

import ppo  # noqa: E402
from reward_normalization import ReturnScaler  # noqa: E402


def reference_scaled_rewards(rewards: np.ndarray, dones: np.ndarray, gamma: float, clip: float) -> np.ndarray:
    """VecNormalize's reward path step by step (float64): R <- gamma R + r; merge R's batch mean and variance into
    the running ones (count starting at 1e-4, mean 0, variance 1); r / sqrt(var + 1e-8), clipped; R <- 0 where done."""
    mean, var, count = 0.0, 1.0, 1.0e-4
    ret = np.zeros(rewards.shape[1])
    out = np.empty_like(rewards)
    for t in range(rewards.shape[0]):
        ret = ret * gamma + rewards[t]
        n = ret.size
        b_mean, b_var = ret.mean(), ret.var()
        delta, total = b_mean - mean, count + n
        m2 = var * count + b_var * n + delta**2 * count * n / total
        mean, var, count = mean + delta * n / total, m2 / total, total
        out[t] = np.clip(rewards[t] / np.sqrt(var + 1e-8), -clip, clip)
        ret[dones[t]] = 0.0
    return out


def test_scaled_rewards_match_the_vecnormalize_reference():
    """Random rewards of mixed scale (a rare large bonus among small shaping terms) and random dones, 16 envs x 200
    steps, a clip of 3 (it is hit). Agreement to 1e-5 relative (float32 rewards out)."""
    gen = np.random.default_rng(0)
    rewards = gen.normal(0.0, 0.01, (200, 16)) + 50.0 * (gen.random((200, 16)) < 0.01)
    dones = gen.random((200, 16)) < 0.05
    expected = reference_scaled_rewards(rewards, dones, 0.99, 3.0)
    assert np.abs(expected).max() == pytest.approx(3.0)  # some bonus is clipped
    scaler = ReturnScaler(0.99, clip=3.0)
    got = np.stack([scaler.scale(torch.tensor(r, dtype=torch.float32), torch.tensor(d)).numpy()
                    for r, d in zip(rewards, dones, strict=True)])
    np.testing.assert_allclose(got, expected.astype(np.float32), rtol=1e-5, atol=1e-9)


def test_running_variance_converges_to_the_discounted_sums_closed_form():
    """i.i.d. rewards of mean 0 and standard deviation 2, no dones, gamma 0.9: the stationary variance of
    R = sum gamma^k r_k is 4 / (1 - 0.81) = 21.05. Over 4,096 envs x 400 steps (the first ~30 steps, the transient,
    weigh little) the running estimate is within 3 % of it; the scaled rewards' spread is then 2 / sqrt(21.05)."""
    gen = torch.Generator().manual_seed(1)
    scaler = ReturnScaler(0.9)
    dones = torch.zeros(4096, dtype=torch.bool)
    for _ in range(400):
        scaled = scaler.scale(2.0 * torch.randn(4096, generator=gen), dones)
    assert float(scaler.var) == pytest.approx(4.0 / (1.0 - 0.81), rel=0.03)
    assert float(scaled.std()) == pytest.approx(2.0 / np.sqrt(4.0 / 0.19), rel=0.05)


def test_scaler_rejects_bad_input():
    for kwargs, message in (({"gamma": 1.5}, "gamma must be in"), ({"gamma": 0.9, "clip": 0.0}, "clip must be")):
        with pytest.raises(ValueError, match=message):
            ReturnScaler(**kwargs)
    with pytest.raises(ValueError, match=r"\(num_envs,\) vectors"):
        ReturnScaler(0.9).scale(torch.zeros(4, 1), torch.zeros(4, 1, dtype=torch.bool))


def test_ppo_option_selects_the_scaling_algorithm(device, tmp_path, capsys):
    """``--reward-normalization`` makes the algorithm ``ScheduledPPO`` with the scaler (the rate left to the preset),
    or adds it to the linear schedule; a short CPU run trains with it and the logs keep the env's own rewards."""
    parser = ppo.build_parser()
    *_, cfg, _ = ppo.training_config(parser.parse_args(["--preset", "gpu", "--reward-normalization"]), parser, "cpu")
    alg = cfg["algorithm"]
    assert alg["class_name"] is ppo.ScheduledPPO and alg["reward_normalization"] is True
    assert (alg["decay_rate"], alg["schedule"]) == (False, "adaptive")
    *_, cfg, _ = ppo.training_config(parser.parse_args(["--preset", "gpu", "--lr-schedule", "linear",
                                                        "--reward-normalization"]), parser, "cpu")
    assert cfg["algorithm"]["class_name"] is ppo.LinearSchedulePPO and cfg["algorithm"]["reward_normalization"]
    assert ppo.main(["--task", "Reach", "--device", device, "--preset", "cpu", "--num-envs", "16",
                     "--max-iterations", "2", "--reward-normalization", "--eval-envs", "4",
                     "--log-dir", str(tmp_path)]) == 0
    assert "it     2/2" in capsys.readouterr().out
