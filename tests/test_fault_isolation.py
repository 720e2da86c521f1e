"""Faults stay in their env: a non-finite state injected into a few envs mid-episode ends and resets exactly those
envs, and every other env's trajectory is bit-identical to a run without the injection (CPU).

Two fault paths are covered: physics state (DeflectSpheres' sphere particles: the World's stability check flags and
restores the env) and task state (Reach's end effector, SearchForPoint's endoscope PTSD: the env base flags an env
whose reward features turn non-finite).
"""

from __future__ import annotations

import numpy as np
import pytest
import torch
import warp as wp

import lapwarp

N = 5
STEPS = 8
INJECT_AT = 3
FAULTY = (1, 3)


def poison(env) -> None:
    """Write NaN into a piece of the state of the envs in ``FAULTY`` (host round trip: a test, not a step)."""
    if env.world.model.particle_count > 0:
        target = env.world.state.particle_q
    elif hasattr(env, "rig"):
        target = env.rig.state.ptsd
    else:
        target = env.positions
    values = target.numpy()
    for k in FAULTY:
        values[k] = np.nan
    target.assign(wp.array(values, dtype=target.dtype, device=target.device))


def rollout(task: str, device: str, inject: bool):
    env = lapwarp.make(task, num_envs=N, device=device, seed=21)
    gen = torch.Generator().manual_seed(5)
    records = []
    for step in range(STEPS):
        actions = (torch.rand(N, env.num_actions, generator=gen) * 2 - 1).to(env.device)
        if inject and step == INJECT_AT:
            poison(env)
        obs, reward, done, extras = env.step(actions)
        records.append(dict(obs=obs["policy"].cpu().clone(), reward=reward.cpu().clone(), done=done.cpu().clone(),
                            unstable=float(extras["log"]["/env/unstable_fraction"]),
                            log_finite=all(bool(torch.isfinite(v)) for v in extras["log"].values())))
    return records


@pytest.mark.parametrize("task", lapwarp.list_tasks())
def test_injected_fault_resets_only_its_envs(device, task):
    clean, faulty = rollout(task, device, False), rollout(task, device, True)
    others = [k for k in range(N) if k not in FAULTY]
    for step, (a, b) in enumerate(zip(clean, faulty, strict=True)):
        for key in ("obs", "reward", "done"):
            assert torch.equal(a[key][others], b[key][others]), f"step {step}: {key} of untouched envs changed"
        assert torch.isfinite(b["obs"]).all() and torch.isfinite(b["reward"]).all(), f"step {step}: NaN escaped"
        assert b["log_finite"], f"step {step}: NaN in extras['log']"
    assert all(r["unstable"] == 0.0 and not r["done"].any() for r in clean[:INJECT_AT + 2]), "false alarm"
    hit = faulty[INJECT_AT]
    assert hit["done"][list(FAULTY)].all(), "the poisoned envs must end at the step they went bad"
    assert hit["unstable"] == pytest.approx(len(FAULTY) / N)
    assert (hit["reward"][list(FAULTY)] == 0).all()
    assert faulty[INJECT_AT + 1]["unstable"] == 0.0  # reset envs start clean
