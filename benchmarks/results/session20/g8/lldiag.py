"""Roll a trained LigatingLoop policy and print per-step features (diagnosis, not part of the package)."""
import sys, json, contextlib
import numpy as np, torch
sys.path.insert(0, "train")
import ppo, lapwarp
ckpt, device, n, steps = sys.argv[1], sys.argv[2], int(sys.argv[3]), int(sys.argv[4])
extra = sys.argv[5:]
weights = {"instrument_shaft_collisions": -0.05, "loop_marking_overlap": 1.0, "loop_closed_around_marking": 0.0,
           "loop_closed_on_marking": 6.0, "successful_task": 1000.0}
argv = ["--task", "LigatingLoop", "--preset", "gpu", "--set", "loop_stiffness=stiff",
        "--set", "reward_weights=" + json.dumps(weights).replace(" ", ""), "--play", ckpt, "--device", device] + extra
parser = ppo.build_parser(); args = parser.parse_args(argv)
preset, num_envs, iterations, train_cfg, overrides = ppo.training_config(args, parser, device, 1)
env = lapwarp.make("LigatingLoop", num_envs=n, device=device, seed=777, **overrides)
runner = ppo.DistributedRunner(env, train_cfg, log_dir=None, device=device)
runner.load(ckpt, map_location=device)
policy = runner.get_inference_policy(device=device)
names = env.reward_features
print("features", names)
obs, _ = env.reset()
rows = []
for t in range(steps):
    with torch.no_grad():
        act = policy(obs)
    obs, rew, done, info = env.step(act)
    f = torch.as_tensor(env.features.numpy())
    a = act.cpu().numpy()
    rows.append((t, a, f.numpy(), done.cpu().numpy(), env.last_episode_success.numpy(),
                 env.task.encircled.numpy().copy(), obs['policy'][:, 4].cpu().numpy().copy()))
    if t % 5 == 0 or done.any():
        for e in range(min(n, 4)):
            fe = dict(zip(names, np.round(f[e].numpy(), 3)))
            print(t, e, "act", np.round(a[e], 2), "ratio_obs", round(float(obs['policy'][e, 4]), 3),
                  {k: v for k, v in fe.items() if k in ("loop_center_in_cavity", "instrument_not_in_cavity",
                   "loop_marking_overlap", "loop_closed_on_marking", "successful_task", "distance_loop_to_marking_center")},
                  "done" if done[e] else "")
F = np.stack([r[2] for r in rows]); A = np.stack([r[1] for r in rows])
print("mean features over steps/envs:", dict(zip(names, np.round(F.mean((0, 1)), 3))))
print("closing action: mean", A[..., 4].mean(), "frac>=0.5", (A[..., 4] >= 0.5).mean(), "frac<=-0.5", (A[..., 4] <= -0.5).mean())
E = np.stack([r[5] for r in rows]); R = np.stack([r[6] for r in rows]); D = np.stack([r[3] for r in rows])
ov = F[..., names.index("loop_marking_overlap")]; inc = F[..., names.index("loop_center_in_cavity")]
print("per env: first done step, max ratio, ratio at end, frac steps encircled, frac in cavity, mean overlap")
for e in range(n):
    d = np.nonzero(D[:, e])[0]
    print(e, d[:1], round(float(R[:, e].max()), 3), round(float(R[-1, e]), 3), round(float(E[:, e].mean()), 2),
          round(float(inc[:, e].mean()), 2), round(float(ov[:, e].mean()), 3))
print("max closed_on_marking per env", np.round(F[..., names.index("loop_closed_on_marking")].max(0), 3))
