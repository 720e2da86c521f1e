"""Roll a LigatingLoop PPO checkpoint (the closure row's reward weights) and print per-step reward features.

    python ll_forced_close.py CKPT DEVICE NUM_ENVS STEPS FORCE_AT EVERY

From step ``FORCE_AT`` on (``-1``: never) the closing component is forced to 1. Run from the repository root. With
``FORCE_AT = -1`` and ``EVERY = 5`` this is the rollout of ``g8/diag.log`` (32 envs, 500 steps, cuda:0); the CPU
log beside this file is ``model_59 cpu 4 110 60 2``. The CPU run of that log took each step's features as a view of
the env's array (on the CPU ``numpy()`` shares memory), so its end-of-run summary lines repeat the last step; fixed
here with ``copy()``.
"""

import json
import sys

import numpy as np
import torch

sys.path.insert(0, "train")
import ppo  # noqa: E402

import lapwarp  # noqa: E402

ckpt, device, n, steps = sys.argv[1], sys.argv[2], int(sys.argv[3]), int(sys.argv[4])
force_at, every = int(sys.argv[5]), int(sys.argv[6])
weights = {"instrument_shaft_collisions": -0.05, "loop_marking_overlap": 1.0, "loop_closed_around_marking": 0.0,
           "loop_closed_on_marking": 6.0, "successful_task": 1000.0}
argv = ["--task", "LigatingLoop", "--preset", "gpu", "--set", "loop_stiffness=stiff",
        "--set", "reward_weights=" + json.dumps(weights).replace(" ", ""), "--play", ckpt, "--device", device]
parser = ppo.build_parser()
args = parser.parse_args(argv)
preset, num_envs, iterations, train_cfg, overrides = ppo.training_config(args, parser, device, 1)
env = lapwarp.make("LigatingLoop", num_envs=n, device=device, seed=777, **overrides)
runner = ppo.DistributedRunner(env, train_cfg, log_dir=None, device=device)
runner.load(ckpt, map_location=device)
policy = runner.get_inference_policy(device=device)
names = list(env.reward_features)
shown = ("distance_loop_to_marking_center", "loop_center_in_cavity", "instrument_not_in_cavity",
         "loop_marking_overlap", "loop_closed_on_marking", "successful_task")
obs, _ = env.reset()
features, actions, dones, encircled, ratios = [], [], [], [], []
for t in range(steps):
    with torch.no_grad():
        act = policy(obs)
    if 0 <= force_at <= t:
        act[:, 4] = 1.0
    obs, rew, done, info = env.step(act)
    f = env.features.numpy().copy()
    a = act.cpu().numpy()
    features.append(f)
    actions.append(a)
    dones.append(done.cpu().numpy())
    encircled.append(env.task.encircled.numpy().copy())
    ratios.append(obs["policy"][:, 4].cpu().numpy().copy())
    if t % every == 0 or done.any():
        for e in range(min(n, 4)):
            row = {k: round(float(f[e, names.index(k)]), 3) for k in shown}
            print(t, e, "act", np.round(a[e], 2), "ratio_obs", round(float(ratios[-1][e]), 3), row,
                  "enc", int(encircled[-1][e]), "done" if dones[-1][e] else "")
F, A, D = np.stack(features), np.stack(actions), np.stack(dones)
E, R = np.stack(encircled), np.stack(ratios)
print("mean features over steps/envs:", {k: round(float(v), 3) for k, v in zip(names, F.mean((0, 1)), strict=True)})
close = A[..., 4]
print("closing action: mean", close.mean(), "frac>=0.5", (close >= 0.5).mean(), "frac<=-0.5", (close <= -0.5).mean())
overlap = F[..., names.index("loop_marking_overlap")]
inside = F[..., names.index("loop_center_in_cavity")]
print("per env: first done step, max ratio, ratio at end, frac steps encircled, frac in cavity, mean overlap")
for e in range(n):
    print(e, np.nonzero(D[:, e])[0][:1], round(float(R[:, e].max()), 3), round(float(R[-1, e]), 3),
          round(float(E[:, e].mean()), 2), round(float(inside[:, e].mean()), 2), round(float(overlap[:, e].mean()), 3))
print("max closed_on_marking per env", np.round(F[..., names.index("loop_closed_on_marking")].max(0), 3))
