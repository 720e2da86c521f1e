"""Rewards scaled by a running estimate of the discounted return's standard deviation, as stable-baselines3's
``VecNormalize(norm_reward=True)`` does: sofa_zoo trained every PPO run of the LapGym paper behind ``VecNormalize``
with reward normalisation always on and its discount matched to PPO's gamma (sofa_env-facts §7; observations were
normalised too, for state runs except Reach: ``ppo.py --obs-normalization``), rewards clipped to +-10 (SB3's default).

Per env a discounted return ``R <- gamma R + r`` is kept (zeroed after a done); its mean and variance over every
env and step so far are merged batch by batch (Chan et al.'s parallel update, starting from mean 0, variance 1 and a
count of 1e-4, SB3's ``RunningMeanStd``); each reward is divided by ``sqrt(var + 1e-8)`` and clipped. The scale is not
centred (subtracting a mean would change which policy is optimal). Small shaping terms, such as Table A's distances
scaled twice by the workspace diagonal, then weigh what they weigh against the return's spread rather than against
the rare success bonus.

Everything stays on the device (no host sync per step). The statistics are per process: ``--distributed`` ranks
keep their own, and ``--resume`` starts them afresh.
"""

from __future__ import annotations

import torch


class ReturnScaler:
    """``scale(rewards, dones)``: the rewards of one step of every env, divided by the running return's standard
    deviation and clipped to ``[-clip, clip]``."""

    def __init__(self, gamma: float, clip: float = 10.0, epsilon: float = 1.0e-8):
        if not 0.0 <= gamma <= 1.0:
            raise ValueError(f"gamma must be in [0, 1], got {gamma}")
        if not clip > 0.0:  # NaN fails the comparison too
            raise ValueError(f"clip must be positive, got {clip}")
        self.gamma = float(gamma)
        self.clip = float(clip)
        self.epsilon = float(epsilon)
        self.returns: torch.Tensor | None = None
        self.mean: torch.Tensor | None = None
        self.var: torch.Tensor | None = None
        self.count: torch.Tensor | None = None

    def _start(self, rewards: torch.Tensor) -> None:
        kw = {"dtype": torch.float64, "device": rewards.device}  # the statistics add up millions of steps
        self.returns = torch.zeros(rewards.shape, **kw)
        self.mean = torch.zeros((), **kw)
        self.var = torch.ones((), **kw)
        self.count = torch.full((), 1.0e-4, **kw)

    def update(self, batch: torch.Tensor) -> None:
        """Merge the mean and (population) variance of ``batch`` into the running ones."""
        n = batch.numel()
        batch_mean = batch.mean()
        batch_var = batch.var(unbiased=False)
        delta = batch_mean - self.mean
        total = self.count + n
        m2 = self.var * self.count + batch_var * n + delta.square() * self.count * n / total
        self.mean = self.mean + delta * n / total
        self.var = m2 / total
        self.count = total

    def scale(self, rewards: torch.Tensor, dones: torch.Tensor) -> torch.Tensor:
        if rewards.dim() != 1 or dones.shape != rewards.shape:
            raise ValueError(f"rewards and dones must be (num_envs,) vectors, got {tuple(rewards.shape)} and "
                             f"{tuple(dones.shape)}")
        if self.returns is None or self.returns.shape != rewards.shape or self.returns.device != rewards.device:
            self._start(rewards)
        r = rewards.to(torch.float64)
        self.returns = self.returns * self.gamma + r
        self.update(self.returns)
        scaled = (r / torch.sqrt(self.var + self.epsilon)).clamp(-self.clip, self.clip)
        self.returns = torch.where(dones.bool(), torch.zeros_like(self.returns), self.returns)
        return scaled.to(rewards.dtype)
