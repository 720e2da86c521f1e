"""Task registry: ``make(name, ...)`` and ``list_tasks()``; tasks are imported only when made."""

from __future__ import annotations

import importlib
from typing import Any

from lapwarp.config import build_config

# name -> "module:EnvClass"; the module is imported lazily so ``import lapwarp`` stays light.
_TASKS: dict[str, str] = {
    "Reach": "lapwarp.tasks.spatial.reach:ReachEnv",
    "SearchForPoint": "lapwarp.tasks.spatial.search_for_point:SearchForPointEnv",
    "DeflectSpheres": "lapwarp.tasks.spatial.deflect_spheres:DeflectSpheresEnv",
    "RopeCutting": "lapwarp.tasks.dissection.rope_cutting:RopeCuttingEnv",
    "PrecisionCutting": "lapwarp.tasks.dissection.precision_cutting:PrecisionCuttingEnv",
    "TissueDissection": "lapwarp.tasks.dissection.tissue_dissection:TissueDissectionEnv",
    "GraspLiftAndTouch": "lapwarp.tasks.deformable_manipulation.grasp_lift_touch:GraspLiftAndTouchEnv",
    "ThreadInHole": "lapwarp.tasks.thread_manipulation.thread_in_hole:ThreadInHoleEnv",
    "RopeThreading": "lapwarp.tasks.thread_manipulation.rope_threading:RopeThreadingEnv",
    "LigatingLoop": "lapwarp.tasks.thread_manipulation.ligating_loop:LigatingLoopEnv",
    "TissueManipulation": "lapwarp.tasks.deformable_manipulation.tissue_manipulation:TissueManipulationEnv",
    "PickAndPlace": "lapwarp.tasks.deformable_manipulation.pick_and_place:PickAndPlaceEnv",
}


def list_tasks() -> list[str]:
    """Names of the tasks ``make`` accepts."""
    return sorted(_TASKS)


def task_class(name: str) -> type:
    """The env class registered under ``name``."""
    if name not in _TASKS:
        raise ValueError(f"unknown task {name!r}; available tasks: {list_tasks()}")
    module_name, class_name = _TASKS[name].split(":")
    return getattr(importlib.import_module(module_name), class_name)


def check_config(name: str, **overrides: Any):
    """The config ``make(name, **overrides)`` would build, validated without building the env (scripts that run many
    configurations check them all before the first one takes device time). Raises ``ValueError`` as ``make`` does."""
    env_class = task_class(name)
    cfg = build_config(env_class.config_class, overrides)
    cfg.validate(env_class.rewards.names, env_class.supported_observations)
    return cfg


def make(name: str, num_envs: int = 1, device: str = "cpu", **overrides: Any):
    """Build the batched env of task ``name`` with ``num_envs`` scenes on a Warp device.

    Args:
        name: task name, see ``list_tasks()``.
        num_envs: number of parallel scenes.
        device: "cpu" or "cuda:N".
        **overrides: fields of the task's config dataclass; unknown keys raise ``ValueError``.

    Returns:
        A ``lapwarp.env.BatchedEnv`` (an ``rsl_rl.env.VecEnv``).
    """
    env_class = task_class(name)
    return env_class.from_overrides(num_envs=num_envs, device=device, **overrides)
