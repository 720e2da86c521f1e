"""Env configuration: the keyword-only dataclass every task config derives from, and override checks.

Fields carry their units in comments; defaults are the paper's values (Tables B and C). Unknown
override keys, unknown reward feature names and invalid enumerations raise ``ValueError`` listing the
valid choices: nothing is silently ignored.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from typing import Any, TypeVar

OBSERVATION_TYPES = ("STATE", "RGB", "RGBD", "DEPTH")
ACTION_TYPES = ("CONTINUOUS", "DISCRETE")
INVALID_ACTION_MODES = ("raise", "zero")

C = TypeVar("C", bound="EnvConfig")


@dataclass(kw_only=True)
class EnvConfig:
    """Fields shared by every task.

    Attributes:
        observation_type: "STATE" (default), or "RGB", "RGBD", "DEPTH" once a task has a camera.
        action_type: "CONTINUOUS" (Box [-1, 1]^d scaled by the maximum velocities) or "DISCRETE"
            (``Discrete(2d+1)``, see ``lapwarp.instruments.discrete_action_table``).
        time_step: simulated seconds per physics step (sofa_env's ``time_step``).
        frame_skip: physics steps per env step; the action is applied at every one of them.
        max_episode_steps: time limit in env steps (Table C); reaching it truncates the episode.
        frame_stack: number of stacked observation frames, newest last (the paper stacks 4).
        reward_weights: weights by feature name; given names replace the task's defaults (Table A).
        invalid_actions: "raise" (default) raises ``ValueError`` on NaN/inf actions, which costs one
            device-to-host sync per step; "zero" replaces non-finite components by 0 on the device and
            counts them under ``extras["log"]["/action/nonfinite_fraction"]``.
        clip_actions: clip continuous actions to [-1, 1] (the action space's bounds); the fraction of
            clipped components is logged under ``/action/clipped_fraction``.
        privileged_critic: also return a ``critic`` observation group with privileged state.
        image_shape: (height, width) of image observations in pixels.
        seed: seed of the per-env device RNG streams.
    """

    observation_type: str = "STATE"
    action_type: str = "CONTINUOUS"
    time_step: float = 0.1
    frame_skip: int = 1
    max_episode_steps: int = 500
    frame_stack: int = 1
    reward_weights: dict[str, float] = field(default_factory=dict)
    invalid_actions: str = "raise"
    clip_actions: bool = True
    privileged_critic: bool = False
    image_shape: tuple[int, int] = (64, 64)
    seed: int = 0

    def validate(self, reward_features: tuple[str, ...], supported_observations: tuple[str, ...]) -> None:
        """Check enumerations and numbers; raise ``ValueError`` naming the offending field."""
        _check_choice("observation_type", self.observation_type, supported_observations)
        _check_choice("action_type", self.action_type, ACTION_TYPES)
        _check_choice("invalid_actions", self.invalid_actions, INVALID_ACTION_MODES)
        if not (math.isfinite(self.time_step) and self.time_step > 0.0):
            raise ValueError(f"time_step must be a positive number of seconds, got {self.time_step!r}")
        for name in ("frame_skip", "max_episode_steps", "frame_stack"):
            value = getattr(self, name)
            if not isinstance(value, int) or value < 1:
                raise ValueError(f"{name} must be an integer >= 1, got {value!r}")
        unknown = sorted(set(self.reward_weights) - set(reward_features))
        if unknown:
            raise ValueError(f"unknown reward feature(s) {unknown}; valid features: {list(reward_features)}")
        if len(self.image_shape) != 2 or min(self.image_shape) < 1:
            raise ValueError(f"image_shape must be (height, width) with positive sizes, got {self.image_shape!r}")


def _check_choice(name: str, value: Any, choices: tuple[str, ...]) -> None:
    if value not in choices:
        raise ValueError(f"{name}={value!r} is not valid; choose one of {list(choices)}")


def build_config(cfg_class: type[C], overrides: dict[str, Any]) -> C:
    """Instantiate ``cfg_class`` from keyword overrides, rejecting unknown keys with the valid ones listed."""
    valid = [f.name for f in dataclasses.fields(cfg_class) if f.init]
    unknown = sorted(set(overrides) - set(valid))
    if unknown:
        raise ValueError(f"unknown config key(s) {unknown} for {cfg_class.__name__}; valid keys: {sorted(valid)}")
    return cfg_class(**overrides)
