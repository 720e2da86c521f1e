"""Scripted experts: privileged-state controllers that solve each task (proof of solvability, demos).

An expert is called like a policy: ``expert = make_expert(env); actions = expert()`` returns a
``(num_envs, num_actions)`` tensor on the env's device, computed from privileged state with torch ops (no host syncs).
"""

from __future__ import annotations

import importlib

import torch


class ReachExpert:
    """Moves the end effector straight at the target at full speed, slowing to land on it.

    Continuous: ``a = clip((target - ee) / (v_max * dt), -1, 1)`` per axis, so the last step lands exactly
    on the target. Discrete: moves along the axis with the largest remaining error.
    """

    def __init__(self, env):
        if env.task_name != "Reach":
            raise ValueError(f"ReachExpert drives Reach, not {env.task_name}")
        self.env = env

    def __call__(self, obs=None) -> torch.Tensor:
        env = self.env
        state = env.privileged_state()
        error = state["target_position"] - state["ee_position"]
        if env.is_discrete:
            axis = error.abs().argmax(dim=1)
            negative = (error.gather(1, axis[:, None])[:, 0] < 0).long()
            return 2 * axis + negative  # rows of lapwarp.instruments.discrete_action_table
        step_length = env.cfg.maximum_robot_velocity * env.cfg.time_step * env.cfg.frame_skip
        return (error / step_length).clamp(-1.0, 1.0)


# task name -> "module:Class"; experts that reuse their task's kernels live in the task module and are imported
# only when asked for.
_EXPERTS = {
    "Reach": "lapwarp.experts:ReachExpert",
    "DeflectSpheres": "lapwarp.tasks.spatial.deflect_spheres:DeflectSpheresExpert",
    "SearchForPoint": "lapwarp.tasks.spatial.search_for_point:SearchForPointExpert",
}


def make_expert(env):
    """The scripted expert of ``env``'s task."""
    if env.task_name not in _EXPERTS:
        raise ValueError(f"no expert for task {env.task_name!r}; experts exist for {sorted(_EXPERTS)}")
    module_name, class_name = _EXPERTS[env.task_name].split(":")
    return getattr(importlib.import_module(module_name), class_name)(env)
