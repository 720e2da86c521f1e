"""Train (or evaluate) a lapwarp task with rsl-rl's PPO ``OnPolicyRunner``.

    python train/ppo.py                                   # Reach, preset for the machine, prints success rate
    python train/ppo.py --task Reach --device cuda:0 --preset gpu
    python train/ppo.py --task Reach --preset paper       # the paper's PPO table (8 envs, 4 stacked frames)
    python train/ppo.py --play runs/Reach/<run>/model_99.pt
    torchrun --nproc_per_node=2 train/ppo.py --task Reach --distributed   # one process per GPU, --num-envs per GPU

Presets:
    paper  the LapGym paper's PPO (Table "Hyperparameters of PPO"): 8 envs, 128 steps per env per update,
           minibatch 256, 4 epochs, gamma 0.995, lambda 0.95, learning rate 2.5e-4 and clip range 0.1 both
           decaying linearly to 0 over the run, value coefficient 0.5, entropy 0, grad norm 0.5, separate actor
           and critic MLPs 256-256 ReLU, state-independent log-std; 4 stacked frames as in the paper.
           rsl-rl clips the value loss with the policy clip range (the paper used 0.2 for the value).
    gpu    thousands of envs on one GPU: 4,096 envs, 32 steps per env, 4 minibatches, 5 epochs, adaptive
           learning rate (KL 0.01), gamma 0.99.
    cpu    a short demo for CPU machines: 256 envs, 32 steps per env, 80 iterations (under a minute).

Every preset builds the env with ``invalid_actions="zero"``: a non-finite action (a diverged policy) is zeroed on the
device and counted, with no host sync per step (the env's default, "raise", checks every step on the host). The
counts are in rsl-rl's logs (``/action/...``) and the progress line names any fault that occurred in an iteration.

With ``--distributed`` (under torchrun) every process builds ``--num-envs`` envs on ``cuda:<LOCAL_RANK>`` with the seed
``seed + rank * 2**32`` (``train/rank_setup.py``), rsl-rl averages the gradients over NCCL, and only rank 0 prints,
writes logs and checkpoints and runs the final evaluation; the progress and final lines report success and env-steps/s
summed over all ranks. N ranks take the preset's optimiser steps on an N x larger global mini-batch (1/N of the steps
per env-step); ``--same-global-minibatch`` splits each rank's rollout into N x the mini-batches instead, keeping one
process's global mini-batch and steps per env-step (pixel policies learn per env-step as on one GPU; measured in
benchmarks/RESULTS.md).
"""

from __future__ import annotations

import argparse
import contextlib
import csv
import dataclasses
import io
import json
import math
import os
import pickle
import statistics
import sys
import time
from datetime import datetime

import torch
import torch.distributed as dist
import warp as wp
from fast_pixels import Uint8Images, use_fast_pixels, use_shared_encoder
from rank_setup import (
    DistributedRunner,
    bind_device,
    cuda_contexts,
    gather_objects,
    init_process_group,
    rank_settings,
    single_process_settings,
    sum_over_ranks,
)
from reward_normalization import ReturnScaler
from rsl_rl.algorithms import PPO
from rsl_rl.runners import OnPolicyRunner

import lapwarp
from lapwarp.cli import default_device, with_fixed


class ScheduledPPO(PPO):
    """PPO with linear schedules over ``total_updates``: the learning rate and clip range decaying to 0
    (``decay_rate``, the paper's lin(x)), and a cap on the actor's action noise falling from its initial standard
    deviation to ``final_noise_std`` at the last update (``ppo.py --final-noise-std``: late in training the mean
    action has to do what the noise did, so the deterministic policy is the one that was trained; rsl-rl's learned
    std is clamped to the cap, its parameter left alone); and, with ``reward_normalization``, the rewards it stores
    scaled by the running discounted return's spread (``train/reward_normalization.py``)."""

    def __init__(self, *args, total_updates: int = 1, decay_rate: bool = True, final_noise_std: float | None = None,
                 reward_normalization: bool = False, **kwargs):
        super().__init__(*args, **kwargs)
        # rewards scaled by the running return's spread before they are stored (ppo.py --reward-normalization); the
        # runner's logs keep the env's own rewards
        self.return_scaler = ReturnScaler(self.gamma) if reward_normalization else None
        self.total_updates = max(1, int(total_updates))
        self.decay_rate = decay_rate
        self.final_noise_std = final_noise_std
        self.initial_learning_rate = self.learning_rate
        self.initial_clip_param = self.clip_param
        self.initial_noise_std: float | None = None
        self.updates_done = 0

    def apply_schedules(self) -> None:
        """Set this update's rate, clip range and noise cap (before ``PPO.update``)."""
        if self.decay_rate:
            remaining = max(0.0, 1.0 - self.updates_done / self.total_updates)
            self.learning_rate = self.initial_learning_rate * remaining
            self.clip_param = max(self.initial_clip_param * remaining, 1e-8)
            for group in self.optimizer.param_groups:
                group["lr"] = self.learning_rate
        if self.final_noise_std is not None:
            distribution = self._raw_actor.distribution
            if self.initial_noise_std is None:
                std = (torch.exp(distribution.log_std_param) if distribution.std_type == "log"
                       else distribution.std_param)
                self.initial_noise_std = float(std.detach().max())
            # reaches the final value at the last update (the rate's schedule reaches 0 after it)
            progress = min(1.0, (self.updates_done + 1) / self.total_updates)
            cap = self.initial_noise_std + (self.final_noise_std - self.initial_noise_std) * progress
            cap = max(cap, distribution.std_range[0])
            distribution.std_range[1] = cap
            distribution.log_std_range[1] = math.log(cap)
        self.updates_done += 1

    def update(self) -> dict:
        self.apply_schedules()
        return super().update()

    def process_env_step(self, obs, rewards, dones, extras) -> None:
        if self.return_scaler is not None:
            rewards = self.return_scaler.scale(rewards, dones)
        super().process_env_step(obs, rewards, dones, extras)


class LinearSchedulePPO(ScheduledPPO):
    """PPO whose learning rate and clip range decay linearly to 0 over ``total_updates`` (the paper's lin(x))."""


def mlp(activation: str, init_std: float | None = None) -> dict:
    model = {"class_name": "MLPModel", "hidden_dims": [256, 256], "activation": activation, "obs_normalization": False}
    if init_std is not None:
        model["distribution_cfg"] = {"class_name": "GaussianDistribution", "init_std": init_std, "std_type": "log"}
    return model


# The paper's image encoder (NatureCNN: 32/64/64 channels, kernels 8/4/3, strides 4/2/1), then FC 512 and the
# state heads' 256-256 (SB3's DoubleNatureCNN with net_arch [256, 256]).
NATURE_CNN = {"output_channels": [32, 64, 64], "kernel_size": [8, 4, 3], "stride": [4, 2, 1], "activation": "relu"}


def use_images(train_cfg: dict, privileged_critic: bool = False) -> dict:
    """Switch a preset's MLPs to CNN models reading the ``image`` group (the critic may read ``critic``)."""
    for role in ("actor", "critic"):
        model = train_cfg[role]
        model.update(class_name="CNNModel", cnn_cfg=dict(NATURE_CNN), hidden_dims=[512, 256, 256])
    train_cfg["obs_groups"] = {"actor": ["image"], "critic": ["critic"] if privileged_critic else ["image"]}
    alg = train_cfg["algorithm"]
    if alg.get("schedule") == "adaptive":
        # Measured on the H100 (Reach RGB, 1,024 envs): the KL-adaptive rate climbed to its 1e-2 ceiling and the
        # CNN policy collapsed; a fixed small rate is the usual choice for pixel PPO.
        alg.update(schedule="fixed", learning_rate=3e-4, desired_kl=None)
    if privileged_critic:
        train_cfg["critic"].update(class_name="MLPModel", hidden_dims=[256, 256])
        train_cfg["critic"].pop("cnn_cfg")
    return train_cfg


def preset_config(name: str, num_envs: int, max_iterations: int) -> tuple[dict, dict]:
    """(rsl-rl train config, env overrides) of a preset."""
    if name == "paper":
        steps = 128
        algorithm = {
            "class_name": LinearSchedulePPO, "total_updates": max_iterations,
            "num_learning_epochs": 4, "num_mini_batches": max(1, num_envs * steps // 256),
            "clip_param": 0.1, "gamma": 0.995, "lam": 0.95, "value_loss_coef": 0.5, "entropy_coef": 0.0,
            "learning_rate": 2.5e-4, "max_grad_norm": 0.5, "use_clipped_value_loss": True, "schedule": "fixed",
            "desired_kl": None,
        }
        activation, env_overrides = "relu", {"frame_stack": 4, "invalid_actions": "zero"}
    elif name in ("gpu", "cpu"):
        steps = 32
        algorithm = {
            "class_name": "PPO", "num_learning_epochs": 5, "num_mini_batches": 4, "clip_param": 0.2,
            "gamma": 0.99, "lam": 0.95, "value_loss_coef": 1.0, "entropy_coef": 0.0, "learning_rate": 1e-3,
            "max_grad_norm": 1.0, "use_clipped_value_loss": True, "schedule": "adaptive", "desired_kl": 0.01,
        }
        activation, env_overrides = "elu", {"invalid_actions": "zero"}
    else:
        raise ValueError(f"unknown preset {name!r}; choose paper, gpu or cpu")
    train_cfg = {
        "num_steps_per_env": steps,
        "save_interval": 50,
        "obs_groups": {"actor": ["policy"], "critic": ["policy"]},
        "algorithm": algorithm,
        "actor": mlp(activation, init_std=1.0),
        "critic": mlp(activation),
        "check_for_nan": False,  # the env guarantees finite outputs; the check costs a host sync per step
        "logger": "tensorboard",
    }
    return train_cfg, env_overrides


PRESET_DEFAULTS = {"paper": (8, 1000), "gpu": (4096, 150), "cpu": (256, 80)}


@dataclasses.dataclass
class Evaluation:
    """One evaluation: every env's first episode.

    ``success`` and ``mean_return`` are the headline figures; the rest say how the other episodes failed:
    ``timeouts`` ended at the time limit, ``terminations`` ended early without success (a failure feature, a wrong
    cut, an unstable reset), and ``stalled`` counts the failed episodes whose actions had died away, the mean
    ``|action|`` (clipped to [-1, 1], over components) below ``STALL_THRESHOLD`` over their last ``STALL_WINDOW``
    steps: a deterministic policy sitting at a fixed point short of the goal, which sampled actions' noise can
    leave (None where the actions are not continuous vectors). ``success_steps``: the successful episodes' mean
    length (None without one)."""

    success: float
    mean_return: float
    episodes: int
    timeouts: int
    terminations: int
    stalled: int | None
    success_steps: float | None

    def __iter__(self):  # ``success, mean_return = evaluate(...)``
        return iter((self.success, self.mean_return))

    def summary(self) -> str:
        failed = self.timeouts + self.terminations
        stalled = "" if self.stalled is None else f", {self.stalled} with their actions died away"
        steps = "" if self.success_steps is None else f"; successes took {self.success_steps:.0f} steps on average"
        return (f"{failed} of {self.episodes} failed: {self.timeouts} at the time limit, {self.terminations} ended "
                f"early{stalled}{steps}")


#: the stall test of ``evaluate``: mean |action| below this over an episode's last ``STALL_WINDOW`` steps
STALL_THRESHOLD, STALL_WINDOW = 0.05, 20


@torch.inference_mode()
def evaluate(env, policy, max_steps: int | None = None) -> Evaluation:
    """Run ``policy`` (the deterministic one, or one that samples) until every env finished one episode.

    An episode succeeded when the env says so (``last_episode_success``), not merely because it ended before its
    time limit: failures (RopeCutting's wrong cut, GraspLiftAndTouch's and TissueManipulation's failure features)
    and unstable resets also terminate an episode. Every env starts at the reset together, so step ``t`` is each
    unfinished env's episode step and one ring buffer of the last ``STALL_WINDOW`` steps' mean |action| serves all."""
    last_success = wp.to_torch(env.last_episode_success)
    obs, _ = env.reset()
    n, device = env.num_envs, env.device
    finished = torch.zeros(n, dtype=torch.bool, device=device)
    success = torch.zeros_like(finished)
    timeout = torch.zeros_like(finished)
    stalled = torch.zeros_like(finished)
    continuous = True
    returns = torch.zeros(n, device=device)
    running = torch.zeros(n, device=device)
    length = torch.zeros(n, device=device)
    recent = torch.zeros(n, STALL_WINDOW, device=device)
    for t in range(max_steps or env.max_episode_length):
        actions = policy(obs)
        continuous = continuous and torch.is_tensor(actions) and actions.is_floating_point() and actions.dim() == 2
        if continuous:
            recent[:, t % STALL_WINDOW] = actions.detach().clamp(-1.0, 1.0).abs().mean(dim=1)
        obs, reward, done, extras = env.step(actions)
        running += reward
        new = done & ~finished
        won = new & (last_success != 0)
        success |= won
        timeout |= new & ~won & extras["time_outs"].to(device=device, dtype=torch.bool)
        if continuous:
            window_mean = recent.sum(dim=1) / min(t + 1, STALL_WINDOW)
            stalled |= new & ~won & (window_mean < STALL_THRESHOLD)
        length = torch.where(new, torch.full_like(length, t + 1), length)
        returns = torch.where(new, running, returns)
        running = torch.where(done, torch.zeros_like(running), running)
        finished |= done
        if bool(finished.all()):
            break
    failed = finished & ~success
    return Evaluation(
        success=success.float().mean().item(), mean_return=returns.mean().item(), episodes=n,
        timeouts=int(timeout.sum()), terminations=int((failed & ~timeout).sum()),
        stalled=int(stalled.sum()) if continuous else None,
        success_steps=length[success].mean().item() if bool(success.any()) else None)


#: ``extras["log"]`` keys of faults the one-line progress shows when they occur in an iteration.
FAULT_KEYS = {"/action/nonfinite_fraction": "non-finite actions", "/action/invalid_fraction": "invalid actions",
              "/env/unstable_fraction": "unstable envs", "/contact/overflow_fraction": "contact overflows"}


def log_mean(logs: list[dict], key: str) -> float | None:
    """Mean of ``key`` over an iteration's step logs (``extras["log"]`` dicts); None when no step logged it."""
    values = [torch.as_tensor(entry[key], dtype=torch.float32) for entry in logs if key in entry]
    return float(torch.stack(values).mean()) if values else None


def fault_summary(logs: list[dict]) -> str:
    """``"  [non-finite actions 0.1%, ...]"`` for the fault keys with a non-zero mean over an iteration's step logs
    (empty when there is none)."""
    means = {label: log_mean(logs, key) for key, label in FAULT_KEYS.items()}
    parts = [f"{label} {mean:.3%}" for label, mean in means.items() if mean]
    return f"  [{', '.join(parts)}]" if parts else ""


def reward_means(logs: list[dict]) -> dict[str, float]:
    """Mean over an iteration's step logs of every weighted reward term (``/reward/<feature>``)."""
    keys = dict.fromkeys(k for entry in logs for k in entry if k.startswith("/reward/"))
    return {key[len("/reward/"):]: log_mean(logs, key) for key in keys}


class ProgressCsv:
    """One row per training iteration: env-steps (all ranks), wall seconds since training began, training success,
    mean return, the iteration's rollout (env + policy inference) and learning seconds, and the mean of every
    weighted reward term (the learning-results runner reads these files)."""

    def __init__(self, path: str):
        self.path = path
        self.start = time.time()
        self.columns: list[str] | None = None
        os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)

    def write(self, row: dict) -> None:
        if self.columns is None:
            self.columns = list(row)
            with open(self.path, "w", newline="") as f:
                csv.writer(f).writerow(self.columns)
        with open(self.path, "a", newline="") as f:
            csv.writer(f).writerow([row.get(c, "") for c in self.columns])


def compact_progress(runner: OnPolicyRunner, env, verbose: bool, main_rank: bool = True,
                     progress_csv: ProgressCsv | None = None, world_size: int = 1) -> None:
    """Replace rsl-rl's 20-line block per iteration by one line (``--verbose`` keeps the block). Under
    ``--distributed`` the success rate and env-steps/s are summed over ranks and only rank 0 prints (the return and
    the reward terms are rank 0's)."""
    original = runner.logger.log

    def log(**kwargs):
        # read the iteration's fault counts and reward terms before rsl-rl's log clears them (one host sync per
        # iteration)
        faults = fault_summary(runner.logger.ep_extras)
        rewards_by_term = reward_means(runner.logger.ep_extras) if progress_csv is not None else {}
        if verbose and main_rank:
            original(**kwargs)
        else:
            with contextlib.redirect_stdout(io.StringIO()):
                original(**kwargs)
        it, total = kwargs["it"], kwargs["total_it"]
        t = env._t
        finished = t["finished_episodes"] > 0
        steps = runner.cfg["num_steps_per_env"] * env.num_envs
        seconds = max(kwargs["collect_time"] + kwargs["learn_time"], 1e-9)
        # one collective per iteration (every rank calls log): successes, finished envs, env-steps/s
        successes, finished_envs, fps = sum_over_ranks(
            [float((t["last_episode_success"] * finished).sum()), float(finished.sum()), steps / seconds], env.device)
        if not main_rank:
            return
        success = successes / max(finished_envs, 1.0)
        returns = runner.logger.rewbuffer
        mean_return = statistics.mean(returns) if returns else float("nan")
        print(f"it {it + 1:5d}/{total}  return {mean_return:9.2f}  success {success:6.1%}  "
              f"lr {kwargs['learning_rate']:.2e}  {fps:,.0f} steps/s{faults}", flush=True)
        if progress_csv is not None:
            row = {"iteration": it + 1, "env_steps": (it + 1) * steps * world_size,
                   "wall_s": round(time.time() - progress_csv.start, 3), "success": success,
                   "mean_return": mean_return, "collect_s": round(kwargs["collect_time"], 4),
                   "learn_s": round(kwargs["learn_time"], 4)}
            row.update({f"reward/{k}": v for k, v in rewards_by_term.items()})
            progress_csv.write(row)

    runner.logger.log = log


def parameter_checksum(runner: OnPolicyRunner) -> float:
    """Sum of every actor and critic parameter (ranks that averaged their gradients agree on it)."""
    with torch.no_grad():
        return float(sum(p.double().sum() for m in (runner.alg.actor, runner.alg.critic) for p in m.parameters()))


def parse_set(items: list[str]) -> dict:
    """``--set KEY=VALUE ...`` as config overrides: values parsed as JSON, anything else kept as a string (the config
    coerces and checks it)."""
    overrides = {}
    for item in items:
        key, sep, value = item.partition("=")
        if not sep:
            raise ValueError(f"--set expects KEY=VALUE, got {item!r}")
        try:
            overrides[key] = json.loads(value)
        except json.JSONDecodeError:
            overrides[key] = value
    return overrides


def device_name(device: str) -> str:
    """The GPU's name (``NVIDIA H100 80GB HBM3``) or ``cpu``."""
    return torch.cuda.get_device_name(torch.device(device)) if device.startswith("cuda") else "cpu"


def write_result(path: str, **result) -> None:
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    with open(path, "w") as f:
        json.dump(result, f, indent=1, default=str)


def main(argv: list[str] | None = None) -> int:
    # ranks other than 0 train silently (rsl-rl prints its models and set-up on every rank); warnings and errors
    # still reach stderr
    with contextlib.ExitStack() as quiet:
        return train(argv, quiet)


#: torch.compile's modes (torch >= 2.1); an unknown one failed deep inside rsl-rl's compile call
COMPILE_MODES = ("default", "reduce-overhead", "max-autotune", "max-autotune-no-cudagraphs")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--task", default="Reach", choices=lapwarp.list_tasks())
    parser.add_argument("--device", default=None,
                        help="torch/Warp device (default: cuda:0, or cuda:<LOCAL_RANK> with --distributed; cpu "
                             "without CUDA)")
    parser.add_argument("--preset", choices=["paper", "gpu", "cpu"], default=None,
                        help="hyper-parameter preset (default: gpu on CUDA, cpu otherwise)")
    parser.add_argument("--obs", choices=["state", "rgb", "rgbd", "depth"], default="state",
                        help="observation type (images use the paper's NatureCNN encoders)")
    parser.add_argument("--set", nargs="*", default=[], metavar="KEY=VALUE",
                        help="task config overrides, values parsed as JSON (e.g. sphere_radius=0.02)")
    parser.add_argument("--num-envs", type=int, default=None,
                        help="training envs (per process, i.e. per GPU, with --distributed)")
    parser.add_argument("--max-iterations", type=int, default=None)
    parser.add_argument("--seed", type=int, default=0, help="seed (rank r of --distributed uses seed + r * 2**32)")
    parser.add_argument("--log-dir", default="runs")
    parser.add_argument("--resume", default=None, help="checkpoint to continue training from")
    parser.add_argument("--play", default=None, help="checkpoint to evaluate (no training)")
    parser.add_argument("--eval-envs", type=int, default=256, help="envs used for the final evaluation")
    parser.add_argument("--distributed", action="store_true",
                        help="one process per GPU under torchrun (reads WORLD_SIZE, RANK, LOCAL_RANK)")
    parser.add_argument("--same-global-minibatch", action="store_true",
                        help="with --distributed on N ranks, split each rank's rollout into N x the preset's "
                             "mini-batches, so the mini-batch summed over ranks and the updates per env-step equal "
                             "one process's (without it N ranks take the preset's updates on N x larger batches)")
    parser.add_argument("--critic", choices=["same", "state"], default="same",
                        help="the critic reads the actor's observations (same, the paper's) or the task's privileged "
                             "state (state: asymmetric actor-critic; for image runs the state, for state runs the "
                             "policy's observation plus privileged values)")
    parser.add_argument("--proprio", action="store_true",
                        help="image runs: the actor (and a critic that reads the actor's observations) also reads the "
                             "instruments' PTSD in [-1, 1] (the env's proprioception group; not in the paper's image "
                             "observation)")
    parser.add_argument("--fast-pixels", action="store_true",
                        help="image runs: uint8 rollout storage, channels-last bf16 encoders (train/fast_pixels.py)")
    parser.add_argument("--shared-encoder", action="store_true",
                        help="with --fast-pixels: one image encoder for the actor and the critic, run once per "
                             "batch (train/fast_pixels.py)")
    parser.add_argument("--first-conv", choices=["space-to-depth", "direct"], default="space-to-depth",
                        help="with --fast-pixels: the encoders' strided first convolution computed over pixel blocks "
                             "(space-to-depth, the same function, tensor-core friendly) or as is (direct)")
    parser.add_argument("--compile", default=None, choices=COMPILE_MODES,
                        help="torch.compile mode of the actor and critic")
    parser.add_argument("--video", default=None, metavar="MP4",
                        help="after training or --play: an MP4 of one episode of the deterministic policy, a grid of "
                             "--video-envs envs at 256x256 with each step's success and return")
    parser.add_argument("--video-envs", type=int, default=16, help="envs in the --video grid (default 16)")
    parser.add_argument("--progress-csv", default=None, metavar="CSV",
                        help="write one row per iteration (env-steps, wall seconds, success, return, reward terms)")
    parser.add_argument("--result-json", default=None, metavar="JSON",
                        help="write the run's final figures (evaluation success, env-steps, times, device)")
    parser.add_argument("--learning-rate", type=float, default=None, metavar="LR",
                        help="override the preset's (initial) learning rate")
    parser.add_argument("--lr-schedule", choices=["adaptive", "fixed", "linear"], default=None,
                        help="override the preset's learning-rate schedule: adaptive (rsl-rl's KL-adaptive, target "
                             "KL 0.01), fixed, or linear (rate and clip range decay to 0 over --max-iterations, the "
                             "paper preset's schedule)")
    parser.add_argument("--learning-epochs", type=int, default=None, metavar="N",
                        help="passes over each rollout per update (default: the preset's; gpu 5)")
    parser.add_argument("--mini-batches", type=int, default=None, metavar="N",
                        help="mini-batches per pass (default: the preset's; gpu 4)")
    parser.add_argument("--init-noise-std", type=float, default=None, metavar="STD",
                        help="the actor's initial action standard deviation (default 1.0; image presets too): "
                             "smaller for tasks whose reward needs precise placement (LigatingLoop)")
    parser.add_argument("--final-noise-std", type=float, default=None, metavar="STD",
                        help="cap the actor's action noise, falling linearly from its initial std to STD at the last "
                             "iteration (the deterministic policy is then the trained one: for policies whose mean "
                             "actions stall where the noise moved them)")
    parser.add_argument("--entropy-coef", type=float, default=None, metavar="C",
                        help="weight of the policy's entropy bonus in the PPO loss (default: the preset's, 0): keeps "
                             "the action noise from collapsing before a sparse success is found")
    parser.add_argument("--obs-normalization", action="store_true",
                        help="normalise the state observations of the MLP models (actor and critic, or an image run's "
                             "state critic) by running mean and standard deviation (rsl-rl's empirical "
                             "normalisation): for tasks whose success needs millimetres out of observations in metres")
    parser.add_argument("--reward-normalization", action="store_true",
                        help="scale the rewards PPO learns from by the running discounted return's standard deviation, "
                             "clipped to +-10 (sb3's VecNormalize, which the paper's runs used; the logs keep the "
                             "env's rewards)")
    parser.add_argument("--verbose", action="store_true", help="print rsl-rl's full block per iteration")
    return parser


def training_config(args: argparse.Namespace, parser: argparse.ArgumentParser, device: str, world_size: int = 1):
    """(preset, envs per rank, iterations, rsl-rl train config, env overrides) from the command line for one of
    ``world_size`` ranks; usage errors end in ``parser.error``."""
    preset = args.preset or ("gpu" if device.startswith("cuda") else "cpu")
    num_envs = PRESET_DEFAULTS[preset][0] if args.num_envs is None else args.num_envs
    iterations = PRESET_DEFAULTS[preset][1] if args.max_iterations is None else args.max_iterations
    if num_envs < 1 or iterations < 1 or args.eval_envs < 1:
        parser.error(f"--num-envs, --max-iterations and --eval-envs must be positive, got {num_envs}, {iterations} "
                     f"and {args.eval_envs}")
    train_cfg, env_overrides = preset_config(preset, num_envs, iterations)
    for option, key, value in (("--learning-epochs", "num_learning_epochs", args.learning_epochs),
                               ("--mini-batches", "num_mini_batches", args.mini_batches)):
        if value is not None:
            if value < 1:
                parser.error(f"{option} must be positive, got {value}")
            train_cfg["algorithm"][key] = value
    if args.same_global_minibatch:
        if not args.distributed:
            parser.error("--same-global-minibatch applies to --distributed runs")
        # rsl-rl averages each mini-batch's gradient over the ranks, so N ranks with the preset's mini-batch count
        # take the same number of optimiser steps per iteration on N x the data: fewer steps per env-step. N x the
        # mini-batches per rank restores one process's global mini-batch size and steps per env-step.
        train_cfg["algorithm"]["num_mini_batches"] *= world_size
    rollout = num_envs * train_cfg["num_steps_per_env"]
    if train_cfg["algorithm"]["num_mini_batches"] > rollout:
        parser.error(f"{train_cfg['algorithm']['num_mini_batches']} mini-batches exceed the rollout's "
                     f"{rollout} samples; use fewer --mini-batches (or no --same-global-minibatch) or more --num-envs")
    if args.obs != "state":
        env_overrides["observation_type"] = args.obs.upper()
        if args.critic == "state":
            env_overrides["privileged_critic"] = True
        use_images(train_cfg, privileged_critic=args.critic == "state")
        if args.proprio:
            env_overrides["proprioception"] = True
            for role in ("actor", "critic"):
                if "image" in train_cfg["obs_groups"][role]:
                    train_cfg["obs_groups"][role].append("proprio")
        if args.fast_pixels:
            use_fast_pixels(train_cfg, space_to_depth=args.first_conv == "space-to-depth")
    elif args.fast_pixels:
        parser.error("--fast-pixels applies to image observations (--obs rgb ...)")
    elif args.proprio:
        parser.error("--proprio applies to image observations (the STATE observation already holds the PTSD)")
    elif args.critic == "state":
        # state actor, critic on the task's privileged layout (the policy's values first, then what the actor may
        # not see, e.g. tets left to cut): a value estimate of the sparse success the actor's observation hides
        env_overrides["privileged_critic"] = True
        train_cfg["obs_groups"] = {"actor": ["policy"], "critic": ["critic"]}
    if args.first_conv != "space-to-depth" and not args.fast_pixels:
        parser.error("--first-conv applies to the --fast-pixels encoders")
    if args.fast_pixels and args.obs != "rgb":
        parser.error("--fast-pixels stores uint8 images, exact only for --obs rgb")
    if args.shared_encoder:
        if not args.fast_pixels or args.critic != "same":
            parser.error("--shared-encoder needs --fast-pixels and a critic that reads the images (--critic same)")
        use_shared_encoder(train_cfg)
    if args.compile:
        train_cfg["torch_compile_mode"] = args.compile
    alg = train_cfg["algorithm"]
    if args.lr_schedule is not None:
        if alg.get("class_name") is LinearSchedulePPO:
            parser.error("--lr-schedule: the paper preset decays its rate linearly; use --preset gpu or cpu")
        if args.lr_schedule == "linear":
            alg.update(class_name=LinearSchedulePPO, total_updates=iterations, schedule="fixed", desired_kl=None)
        else:
            alg.update(schedule=args.lr_schedule, desired_kl=0.01 if args.lr_schedule == "adaptive" else None)
    if args.learning_rate is not None:
        if not 0.0 < args.learning_rate <= 1.0:  # NaN fails the comparison too
            parser.error(f"--learning-rate must be in (0, 1], got {args.learning_rate}")
        alg["learning_rate"] = args.learning_rate
    if args.final_noise_std is not None:
        if not 0.0 < args.final_noise_std <= 10.0:  # NaN fails the comparison too
            parser.error(f"--final-noise-std must be in (0, 10], got {args.final_noise_std}")
        if alg.get("class_name") is LinearSchedulePPO:
            alg["final_noise_std"] = args.final_noise_std
        else:
            alg.update(class_name=ScheduledPPO, total_updates=iterations, decay_rate=False,
                       final_noise_std=args.final_noise_std)
    if args.reward_normalization:
        if alg.get("class_name") not in (LinearSchedulePPO, ScheduledPPO):
            alg.update(class_name=ScheduledPPO, total_updates=iterations, decay_rate=False)
        alg["reward_normalization"] = True
    if args.entropy_coef is not None:
        if not 0.0 <= args.entropy_coef <= 1.0:  # NaN fails the comparison too
            parser.error(f"--entropy-coef must be in [0, 1], got {args.entropy_coef}")
        alg["entropy_coef"] = args.entropy_coef
    if args.init_noise_std is not None:
        if not 0.0 < args.init_noise_std <= 10.0:  # NaN fails the comparison too
            parser.error(f"--init-noise-std must be in (0, 10], got {args.init_noise_std}")
        train_cfg["actor"].setdefault("distribution_cfg", {}).update(init_std=args.init_noise_std)
    if args.obs_normalization:
        state_models = [train_cfg[role] for role in ("actor", "critic") if train_cfg[role]["class_name"] == "MLPModel"]
        if not state_models:
            parser.error("--obs-normalization applies to state observations (--obs state, or --critic state)")
        for model in state_models:
            model["obs_normalization"] = True
    if args.video is not None:
        if not args.video.endswith(".mp4") or args.video_envs < 1:
            parser.error(f"--video writes an .mp4 file of --video-envs >= 1 envs, got {args.video!r}, "
                         f"{args.video_envs}")
        from lapwarp.video import check_video_support

        try:  # before training, not after it
            check_video_support()
        except ImportError as exc:
            parser.error(str(exc))
    try:
        env_overrides.update(parse_set(args.set))
    except ValueError as exc:
        parser.error(str(exc))
    return preset, num_envs, iterations, train_cfg, env_overrides


def make_run_env(parser: argparse.ArgumentParser, task: str, num_envs: int, device: str, overrides: dict, seed: int,
                 fast_pixels: bool):
    """The env a run trains or plays on: ``lapwarp.make`` with the run's overrides and its seed (a bad config value,
    or a ``--set`` of the seed, is a usage error), its image group handed over as uint8 with ``--fast-pixels``."""
    try:  # bad config values end as one usage line, not a traceback
        env = lapwarp.make(task, num_envs=num_envs, device=device, **with_fixed(overrides, "--set", seed=seed))
    except ValueError as exc:
        parser.error(str(exc))
    return Uint8Images(env) if fast_pixels else env


def load_checkpoint(runner: OnPolicyRunner, path: str, device: str, parser: argparse.ArgumentParser,
                    option: str) -> None:
    """Load ``path`` into ``runner``'s models; a file that is not a checkpoint, or one of other models (another task,
    observation or network), is a usage error naming ``option``."""
    try:
        runner.load(path, map_location=device)
    except (pickle.UnpicklingError, EOFError, KeyError, RuntimeError, ValueError) as exc:
        parser.error(f"{option} {path!r} does not load into this run's models "
                     f"({type(exc).__name__}: {' '.join(str(exc).split())[:300]})")


def train(argv: list[str] | None, quiet: contextlib.ExitStack) -> int:
    """Parse, set up this rank (device, seed, process group), train, then on rank 0 evaluate, report and record."""
    parser = build_parser()
    args = parser.parse_args(argv)

    start = time.time()
    throughput = ""
    total_steps, train_seconds = 0, 0.0
    if args.distributed:
        if args.play:
            parser.error("--play evaluates in one process; leave out --distributed")
        try:
            ranks = rank_settings(os.environ, args.seed, args.device, torch.cuda.is_available())
        except ValueError as exc:
            parser.error(str(exc))
    else:
        ranks = single_process_settings(args.seed, args.device or default_device())
    device = ranks.device
    preset, num_envs, iterations, train_cfg, env_overrides = training_config(args, parser, device, ranks.world_size)
    train_cfg["seed"] = ranks.seed

    for option, path in (("--play", args.play), ("--resume", args.resume)):
        if path and not os.path.isfile(path):
            parser.error(f"{option} {path!r} is not a file")
    if ranks.is_main and not args.play:
        try:  # before the env is built: training must not end in an unwritable log folder
            os.makedirs(args.log_dir, exist_ok=True)
            if not os.access(args.log_dir, os.W_OK | os.X_OK):
                raise PermissionError(f"{args.log_dir!r} is not writable")
        except OSError as exc:
            parser.error(f"--log-dir {args.log_dir!r}: {exc}")
    if not ranks.is_main:
        quiet.enter_context(contextlib.redirect_stdout(io.StringIO()))
    if ranks.distributed:
        bind_device(device)  # before Warp or NCCL touch any GPU
        init_process_group(ranks)
    torch.manual_seed(ranks.seed)
    env = make_run_env(parser, args.task, num_envs, device, env_overrides, ranks.seed, args.fast_pixels)
    run_dir = None if args.play or not ranks.is_main else os.path.join(
        args.log_dir, args.task, f"{datetime.now():%Y%m%d-%H%M%S}_{preset}_seed{args.seed}")
    runner = DistributedRunner(env, train_cfg, log_dir=run_dir, device=device)
    progress_csv = ProgressCsv(args.progress_csv) if args.progress_csv and ranks.is_main and not args.play else None
    compact_progress(runner, env, args.verbose, ranks.is_main, progress_csv, ranks.world_size)
    checkpoint = args.play or args.resume
    if checkpoint:
        load_checkpoint(runner, checkpoint, device, parser, "--play" if args.play else "--resume")
        if ranks.is_main:
            print(f"loaded {checkpoint}")
        if args.resume and args.learning_rate is not None:
            # rsl-rl's load restores the optimizer with the checkpoint's rate; an explicit rate is what the user asked
            restored = runner.alg.learning_rate
            runner.alg.learning_rate = args.learning_rate
            for group in runner.alg.optimizer.param_groups:
                group["lr"] = args.learning_rate
            if ranks.is_main:
                print(f"learning rate {args.learning_rate:.2e} (the checkpoint's was {restored:.2e})")
    if not args.play:
        contexts = gather_objects(cuda_contexts()) if ranks.distributed else None
        if ranks.is_main:
            where = (f"{ranks.world_size} processes x {num_envs} envs (per rank; Warp CUDA contexts by rank: "
                     f"{contexts})" if ranks.distributed else f"{num_envs} envs on {device}")
            print(f"training {args.task}: preset {preset}, {where}, {iterations} iterations, logs in {run_dir} "
                  f"(start-up {time.time() - start:.1f} s)", flush=True)
        train_start = time.time()
        if progress_csv is not None:
            progress_csv.start = train_start
        runner.learn(num_learning_iterations=iterations, init_at_random_ep_len=True)
        train_seconds = time.time() - train_start
        env_steps = iterations * train_cfg["num_steps_per_env"] * num_envs
        total_steps, = sum_over_ranks([env_steps], device)
        checksums = gather_objects(parameter_checksum(runner)) if ranks.distributed else None
        throughput = f", training {total_steps / train_seconds:,.0f} env-steps/s on {ranks.world_size} process(es)"
        if ranks.is_main:
            agree = "" if checksums is None else (
                f", policy parameters identical on all ranks: {'yes' if len(set(checksums)) == 1 else checksums}")
            print(f"trained {total_steps:,.0f} env-steps on {ranks.world_size} process(es) in {train_seconds:.1f} s: "
                  f"{total_steps / train_seconds:,.0f} env-steps/s{agree}", flush=True)
    if ranks.distributed:
        dist.destroy_process_group()
        if not ranks.is_main:
            return 0
    policy = runner.get_inference_policy(device=device)
    eval_env = lapwarp.make(args.task, num_envs=args.eval_envs, device=device, seed=args.seed + 12345,
                            **env_overrides)
    deterministic = evaluate(eval_env, policy)
    success, mean_return = deterministic
    # the paper's success rates are its training rollouts', i.e. of actions sampled from the policy's distribution:
    # the same policy evaluated that way on fresh first episodes is the like-for-like figure (the deterministic one,
    # the policy's mean action, is the headline; it can be lower where noise gets a policy unstuck)
    sampled = evaluate(eval_env, lambda obs: policy(obs, stochastic_output=True))
    sampled_success, sampled_return = sampled
    if args.result_json:
        write_result(args.result_json, task=args.task, obs=args.obs, preset=preset, settings=env_overrides,
                     seed=args.seed, num_envs_per_rank=num_envs, world_size=ranks.world_size, iterations=iterations,
                     env_steps=int(total_steps), train_s=round(train_seconds, 3), wall_s=round(time.time() - start, 3),
                     eval_episodes=args.eval_envs, success=success, mean_return=mean_return,
                     sampled_success=sampled_success, sampled_mean_return=sampled_return,
                     evaluation=dataclasses.asdict(deterministic), sampled_evaluation=dataclasses.asdict(sampled),
                     device=device_name(device), checkpoint=args.play)
    print(f"evaluation on {args.eval_envs} episodes: success rate {success:.1%}, mean return {mean_return:.2f} "
          f"(wall time {time.time() - start:.1f} s{throughput})", flush=True)
    print(f"  {deterministic.summary()}", flush=True)
    print(f"sampled actions (as in training rollouts), {args.eval_envs} episodes: success rate {sampled_success:.1%}, "
          f"mean return {sampled_return:.2f}", flush=True)
    print(f"  {sampled.summary()}", flush=True)
    if args.video:
        from lapwarp.video import record_video

        video_env = lapwarp.make(args.task, num_envs=args.video_envs, device=device, seed=args.seed + 54321,
                                 **env_overrides)
        frames = record_video(video_env, policy, args.video, steps=video_env.max_episode_length,
                              max_tiles=args.video_envs)
        print(f"video: {args.video} ({frames} frames, {args.video_envs} envs)", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
