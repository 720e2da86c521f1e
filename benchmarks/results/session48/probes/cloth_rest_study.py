"""CPU study (forty-eighth session): how many of PrecisionCutting's cloth chains (and warps of 32 chain threads)
have every node slower than a threshold over an env step under the expert, i.e. what a per-chain hold could skip.

    python benchmarks/results/session48/probes/cloth_rest_study.py 8 100 line
"""
import sys

import numpy as np

import lapwarp
from lapwarp.experts import make_expert

n = int(sys.argv[1]) if len(sys.argv) > 1 else 8
steps = int(sys.argv[2]) if len(sys.argv) > 2 else 120
path = sys.argv[3] if len(sys.argv) > 3 else "line"
env = lapwarp.make("PrecisionCutting", num_envs=n, device="cpu", path_function=path, randomize_path=True)
expert = make_expert(env)
env.reset()
G = 40  # the cloth's grid; its rows, columns and one diagonal family stand in for the solver's chains
idx = np.arange(G * G).reshape(G, G)
fams = {"rows": [idx[r] for r in range(G)], "cols": [idx[:, c] for c in range(G)],
        "diag": [np.diagonal(idx, k) for k in range(-(G - 2), G - 1)]}
q_prev = env.world.state.particle_q.numpy().copy()
thr_list = [1e-4, 1e-3, 1e-2]
acc = {(f, t): [] for f in fams for t in thr_list}
warp_acc = {(f, t): [] for f in fams for t in thr_list}
env_quiet = {t: [] for t in thr_list}
for _ in range(steps):
    env.step(expert())
    q = env.world.state.particle_q.numpy()
    v = np.linalg.norm(q - q_prev, axis=-1)[:, :G * G] / 0.1  # mean speed over the 0.1 s env step
    q_prev = q.copy()
    for t in thr_list:
        env_quiet[t].append((v.max(axis=1) < t).mean())
        for f, chains in fams.items():
            act = np.stack([(v[:, c] >= t).any(axis=1) for c in chains], axis=1)  # (n, chains)
            acc[f, t].append(act.mean())
            flat = act.reshape(-1)  # threads (env, chain) as the walk launches them
            pad = (-len(flat)) % 32
            w = np.concatenate([flat, np.zeros(pad, bool)]).reshape(-1, 32).any(axis=1)
            warp_acc[f, t].append(w.mean())
print(f"{n} envs {steps} steps path {path}")
for t in thr_list:
    print(f"thr {t:g} m/s: envs all quiet {np.mean(env_quiet[t]):.3f}")
    for f in fams:
        print(f"   {f}: chains awake {np.mean(acc[f, t]):.3f}, warps awake {np.mean(warp_acc[f, t]):.3f}")
