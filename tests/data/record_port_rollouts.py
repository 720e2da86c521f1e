"""Record fixed-seed rollouts of the spatial tasks (actions, rewards, features, observations, dones).

Run once with the code *before* the task-layer port (commit 28f183c) to produce ``port_rollouts.npz``;
``tests/test_port_equivalence.py`` replays the recorded actions on today's code and compares. Kept for the record:
re-running it on ported code would only record the ported behaviour.

    python tests/data/record_port_rollouts.py
"""

from __future__ import annotations

import os

import numpy as np
import torch

import lapwarp
from lapwarp.experts import make_expert

# name -> (task, overrides, steps, policy); every case keeps 3 envs and the privileged critic group
CASES = {
    "reach_continuous": ("Reach", {"seed": 3}, 80, "expert_noise"),
    "reach_discrete": ("Reach", {"seed": 4, "action_type": "DISCRETE"}, 40, "random"),
    "deflect_one_hook": ("DeflectSpheres", {"seed": 5, "num_deflect_to_win": 2}, 120, "expert_noise"),
    "deflect_two_hooks": ("DeflectSpheres", {"seed": 6, "single_instrument": False, "num_deflect_to_win": 2},
                          120, "expert_noise"),
    "search_camera": ("SearchForPoint", {"seed": 7}, 60, "expert_noise"),
    "search_active_vision": ("SearchForPoint", {"seed": 8, "active_vision": True, "cauter_activation": True},
                             60, "expert_noise"),
    "search_discrete": ("SearchForPoint", {"seed": 9, "action_type": "DISCRETE"}, 40, "random"),
}
NUM_ENVS = 3


def record(task: str, overrides: dict, steps: int, policy: str) -> dict[str, np.ndarray]:
    env = lapwarp.make(task, num_envs=NUM_ENVS, device="cpu", privileged_critic=True, **overrides)
    gen = torch.Generator().manual_seed(1234)
    expert = make_expert(env) if policy == "expert_noise" else None
    obs = env.get_observations()
    out = {k: [] for k in ("actions", "policy", "critic", "reward", "done", "time_out", "features")}
    out["policy0"] = obs["policy"].numpy().copy()
    out["critic0"] = obs["critic"].numpy().copy()
    for _ in range(steps):
        if env.is_discrete:
            actions = torch.randint(0, 2 * env.action_dim + 1, (NUM_ENVS,), generator=gen)
        else:
            actions = expert() + 0.3 * torch.randn(NUM_ENVS, env.num_actions, generator=gen)
            actions = actions.clamp(-1.0, 1.0)
        obs, rew, done, extras = env.step(actions)
        out["actions"].append(actions.numpy().copy())
        out["policy"].append(obs["policy"].numpy().copy())
        out["critic"].append(obs["critic"].numpy().copy())
        out["reward"].append(rew.numpy().copy())
        out["done"].append(done.numpy().copy())
        out["time_out"].append(extras["time_outs"].numpy().copy())
        out["features"].append(env._t["features"].numpy().copy())
    return {k: np.asarray(v) for k, v in out.items()}


def main() -> None:
    arrays = {}
    for name, (task, overrides, steps, policy) in CASES.items():
        for key, value in record(task, overrides, steps, policy).items():
            arrays[f"{name}/{key}"] = value
        print(name, "done:", int(arrays[f"{name}/done"].sum()), "reward sum:", float(arrays[f"{name}/reward"].sum()))
    np.savez_compressed(os.path.join(os.path.dirname(__file__), "port_rollouts.npz"), **arrays)


if __name__ == "__main__":
    main()
