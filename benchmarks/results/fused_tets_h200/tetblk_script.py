"""Block-size sweep of the fused tet sweep: physics tet scenes and task envs (random actions), 4,096 envs."""
import json, sys, time
import torch, warp as wp
sys.path.insert(0, ".")
from benchmarks.bench_physics import build_tet
import lapwarp
wp.config.log_level = wp.LOG_WARNING
wp.init()
out = open(sys.argv[1], "a")
def timed(step, n, steps=20):
    for _ in range(3):
        step()
    wp.synchronize_device("cuda:0")
    with wp.ScopedCapture(device="cuda:0") as cap:
        step()
    wp.capture_launch(cap.graph)
    wp.synchronize_device("cuda:0")
    t0 = time.perf_counter()
    for _ in range(steps):
        wp.capture_launch(cap.graph)
    wp.synchronize_device("cuda:0")
    return n * steps / (time.perf_counter() - t0)
for youngs in ((3e3, 3e4) if "tets" in sys.argv else ()):
    for solver, threads in (("colored", 0), ("fused", 32), ("fused", 64), ("fused", 128)):
        world, obj, rest, _ = build_tet(4096, "cuda:0", 20, 1, "chains", youngs=youngs)
        world.tet_solver = solver
        if threads:
            world.tet_block_threads = threads
        r = timed(lambda: world.step(0.1), 4096)
        q = world.positions(obj)
        rec = {"scene": f"tet E={youngs:g}", "substeps": 20, "solver": solver, "threads": threads, "env_steps_per_s": r,
               "sag": float(-(q[:, rest[:, 2] > 0.02 - 1e-9, 2] - 0.02).mean())}
        print(rec, flush=True); out.write(json.dumps(rec) + "\n"); out.flush()
        del world
for task in ("GraspLiftAndTouch", "ThreadInHole", "LigatingLoop", "TissueDissection", "TissueManipulation"):
    for solver, threads in (("fused", 32), ("fused", 16)):
        env = lapwarp.make(task, num_envs=4096, device="cuda:0", invalid_actions="zero")
        env.world.tet_solver = solver
        if threads:
            env.world.tet_block_threads = threads
        g = torch.Generator(device="cuda:0").manual_seed(0)
        if env.is_discrete:
            acts = [torch.randint(0, 2 * env.action_dim + 1, (4096,), device="cuda:0", generator=g) for _ in range(8)]
        else:
            acts = [torch.rand(4096, env.num_actions, device="cuda:0", generator=g) * 2 - 1 for _ in range(8)]
        for i in range(5):
            env.step(acts[i % 8])
        torch.cuda.synchronize()
        t0 = time.perf_counter(); k = 0
        while time.perf_counter() - t0 < 2.0:
            for _ in range(10):
                env.step(acts[k % 8]); k += 1
            torch.cuda.synchronize()
        r = 4096 * k / (time.perf_counter() - t0)
        rec = {"task": task, "solver": solver, "threads": threads, "env_steps_per_s": r,
               "tets": env.world.model.tet_count, "colors": len(env.world.model.tet_color_offsets) - 1,
               "window": env.world._tet_window}
        print(rec, flush=True); out.write(json.dumps(rec) + "\n"); out.flush()
        env.close()
