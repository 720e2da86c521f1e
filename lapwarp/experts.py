"""Scripted experts: privileged-state controllers that solve each task (proof of solvability, demos).

An expert is called like a policy: ``expert = make_expert(env); actions = expert()`` returns a
``(num_envs, num_actions)`` tensor on the env's device (``(num_envs,)`` indices for discrete actions), computed from
privileged state with torch ops (no host syncs). Each task names its expert class in ``env.expert``
(``"module:Class"``); it is imported only when asked for.
"""

from __future__ import annotations

import importlib

import numpy as np
import torch


def make_expert(env):
    """The scripted expert of ``env``'s task."""
    if not getattr(env, "expert", None):
        raise ValueError(f"task {env.task_name!r} has no scripted expert")
    module_name, class_name = env.expert.split(":")
    return getattr(importlib.import_module(module_name), class_name)(env)


class Expert:
    """Base of the scripted experts: turns the *ideal* normalised action into the env's action type.

    A subclass computes ``ideal`` ``(num_envs, action_dim)``: per component, the remaining error divided by how far a
    continuous action of 1 moves in one env step (so ``ideal`` = 1 closes the error in exactly one step). Continuous
    actions are ``ideal`` clipped to [-1, 1]; a discrete action moves along the component whose error is the most
    discrete steps (``env.discrete_actions``), or is the no-op when every error is within half a step.
    """

    def __init__(self, env):
        self.env = env
        table = env.discrete_actions
        d = table.shape[1]
        self._discrete_step = table[0:2 * d:2].diagonal().clamp(min=1.0e-12)  # row 2i moves component i by +step

    def rig_step_size(self, *extra: float) -> torch.Tensor:
        """What a continuous action of 1 changes in one env step, per action column: the instrument rig's
        ``action_scale`` over the env's control period, then ``extra`` for the task's own columns (float32, on the
        env's device); ``ideal`` is an error divided by it."""
        cfg = self.env.cfg
        scale = np.append(self.env.rig.action_scale(cfg.time_step * cfg.frame_skip), extra)
        return torch.tensor(scale, dtype=torch.float32, device=self.env.device)

    def policy_actions(self, ideal: torch.Tensor) -> torch.Tensor:
        if not self.env.is_discrete:
            return ideal.clamp(-1.0, 1.0)
        ratio = ideal / self._discrete_step
        component = ratio.abs().argmax(dim=1)
        chosen = ratio.gather(1, component[:, None])[:, 0]
        action = 2 * component + (chosen < 0).long()
        return torch.where(chosen.abs() < 0.5, torch.full_like(action, 2 * ideal.shape[1]), action)
