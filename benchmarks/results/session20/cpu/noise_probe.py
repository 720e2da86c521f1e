"""A task's scripted expert with Gaussian noise added to every action component: first-episode success per std.

    python noise_probe.py TASK NUM_ENVS MAX_STEPS SEED STD[,STD...] [KEY=VALUE ...]

Twentieth session: ``LigatingLoop 8 500 1 0,0.5,0.8 loop_stiffness=stiff`` gave 6 / 8, 8 / 8 and 7 / 8 (CPU).
"""

import sys

import numpy as np
import torch

import lapwarp
from lapwarp.experts import make_expert

task, n, steps, seed = sys.argv[1], int(sys.argv[2]), int(sys.argv[3]), int(sys.argv[4])
stds = [float(x) for x in sys.argv[5].split(",")]
config = dict(a.split("=", 1) for a in sys.argv[6:])
for std in stds:
    env = lapwarp.make(task, num_envs=n, device="cpu", seed=seed, use_cuda_graph=False, **config)
    env.reset()
    expert = make_expert(env)
    gen = torch.Generator().manual_seed(seed)
    first = np.full(n, -1)
    for _ in range(steps):
        action = expert()
        obs, reward, done, info = env.step(action + std * torch.randn(action.shape, generator=gen))
        finished, success = done.numpy(), env.last_episode_success.numpy()
        for e in np.nonzero(finished & (first < 0))[0]:
            first[e] = success[e]
        if (first >= 0).all():
            break
    print(task, config, "noise std", std, "success", int((first == 1).sum()), "/", n,
          "unfinished", int((first < 0).sum()), flush=True)
