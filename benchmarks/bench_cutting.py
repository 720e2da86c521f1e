"""Cost of element-mask cutting: physics throughput with and without cutting active in every env, and the cost of
a masked reset of cut vs uncut envs (issue #5 targets: cutting <= 20 % of the throughput at 4,096 envs; resetting
cut envs no dearer than uncut ones).

Scenes (the ``bench_physics.py`` ones, made cuttable):

* ``cloth``: 40 x 40 vertices, 75 mm, pinned top edge, 0.2 kg/m^2, 1e3 N/m, bending 1e-6 N m (3,042 triangles).
  Cuttable cloth has no tethers, so every mode here runs without tethers.
* ``tet``: 40 x 40 x 20 mm block, 7 x 6 x 4 cells (1,008 tets), E = 3 kPa, nu = 0.45, clamped base.

Modes, env-steps/s (0.1 s per env step, ``--substeps`` substeps, one CUDA graph per step on CUDA):

* ``plain``: not cuttable (no masks in the constraint kernels);
* ``masked``: cuttable, masks read by the constraint kernels, no tool;
* ``cutting``: a tool capsule (radius 1 mm, carving distance 1.2 mm) sweeps across the object in every env and
  ``CuttingSystem.cut()`` runs after every step (removal, surface, union-find connectivity and counters of every
  env, since every env cuts every step: the worst case).

Split: ``masks_cost = 1 - masked / plain``, ``cut_pass_cost = 1 - cutting / masked``, ``cut_ms`` (tool kernel +
``cut()``, every env cutting) and ``update_ms`` (``cut.refresh()`` of every env: surfaces, particle masks,
connectivity, counters).

Reset: ``world.reset(all envs) + cut.refresh()`` after cutting (cut envs) vs on a fresh world (uncut envs).

Examples::

    python benchmarks/bench_cutting.py --device cuda:0 --num-envs 1024 4096 --out benchmarks/results/cutting_h100.json
    python benchmarks/bench_cutting.py --device cpu --num-envs 2 --steps 2        # smoke test
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np
import warp as wp

from lapwarp.assets import box_tets, cloth_grid
from lapwarp.builder import SceneBuilder
from lapwarp.cutting import CuttingSystem

DT = 0.1


@wp.kernel
def sweep_tool(step: wp.array(dtype=wp.int32), lo: wp.vec3, hi: wp.vec3, axis: wp.vec3, period: int,
               tool_a: wp.array2d(dtype=wp.vec3), tool_b: wp.array2d(dtype=wp.vec3),
               tool_active: wp.array(dtype=wp.int32)):
    """Move a short blade from ``lo`` to ``hi`` over ``period`` steps (env-dependent phase), always active."""
    env = wp.tid()
    k = (step[0] + env * 7) % period
    s = float(k) / float(period)
    c = lo * (1.0 - s) + hi * s
    tool_a[env, 0] = c - axis
    tool_b[env, 0] = c + axis
    tool_active[env] = 1


@wp.kernel
def advance(step: wp.array(dtype=wp.int32)):
    step[0] = step[0] + 1


def build(scene: str, num_envs: int, device: str, substeps: int, cuttable: bool):
    b = SceneBuilder()
    if scene == "cloth":
        v, t = cloth_grid(40, 40, 0.075, 0.075, plane="xz", origin=(0.0, 0.0, -0.075))
        top = np.nonzero(v[:, 2] > -1e-9)[0]
        obj = b.add_cloth(v, t, areal_density=0.2, stretch_stiffness=1e3, bend_stiffness=1e-6, damping=1.0,
                          fixed=top, tethers=False, cuttable=cuttable)
        # a horizontal blade sweeping down the sheet
        path = (wp.vec3(0.0375, 0.0, -0.005), wp.vec3(0.0375, 0.0, -0.07), wp.vec3(0.004, 0.0, 0.0))
    else:
        v, t = box_tets((0.04, 0.04, 0.02), (7, 6, 4))
        obj = b.add_tet_mesh(v, t, density=1000.0, youngs_modulus=3e3, poisson_ratio=0.45, damping=1.0,
                             fixed=np.nonzero(v[:, 2] < 1e-9)[0], cuttable=cuttable)
        # a vertical blade through the whole (sagging) thickness dragged across the block
        path = (wp.vec3(0.0, 0.02, 0.012), wp.vec3(0.04, 0.02, 0.012), wp.vec3(0.0, 0.0, 0.012))
    world = b.finalize(num_envs, device, substeps=substeps)
    return world, obj, path


def timed(device, fn, steps: int) -> float:
    """Seconds per call of ``fn`` (captured as one CUDA graph on CUDA)."""
    dev = wp.get_device(device)
    fn()
    wp.synchronize_device(dev)
    graph = None
    if dev.is_cuda:
        with wp.ScopedCapture(device=dev) as cap:
            fn()
        graph = cap.graph
        wp.capture_launch(graph)
    wp.synchronize_device(dev)
    t0 = time.perf_counter()
    for _ in range(steps):
        if graph is not None:
            wp.capture_launch(graph)
        else:
            fn()
    wp.synchronize_device(dev)
    return (time.perf_counter() - t0) / steps


def run(scene: str, num_envs: int, device: str, substeps: int, steps: int) -> dict:
    out = {"scene": scene, "num_envs": num_envs, "device": str(wp.get_device(device)), "substeps": substeps}
    world, _, _ = build(scene, num_envs, device, substeps, cuttable=False)
    out["plain_env_steps_per_s"] = num_envs / timed(device, lambda: world.step(DT), steps)
    del world
    world, _, _ = build(scene, num_envs, device, substeps, cuttable=True)
    out["masked_env_steps_per_s"] = num_envs / timed(device, lambda: world.step(DT), steps)
    # reset of uncut envs (fresh world)
    ones = wp.ones(num_envs, dtype=wp.int32, device=device)
    world, obj, path = build(scene, num_envs, device, substeps, cuttable=True)
    cut = CuttingSystem(world, carving_distance=1.2e-3, num_tools=1, tool_radius=1e-3)
    cut.add_object(obj)
    cut.finalize()

    def reset():
        world.reset(ones)
        cut.refresh()

    out["reset_uncut_ms"] = 1e3 * timed(device, reset, steps)
    counter = wp.zeros(1, dtype=wp.int32, device=device)
    period = 20

    def step_and_cut():
        world.step(DT)
        wp.launch(sweep_tool, dim=num_envs, inputs=[counter, *path, period],
                  outputs=[cut.tool_a, cut.tool_b, cut.tool_active], device=device)
        cut.cut()
        wp.launch(advance, dim=1, outputs=[counter], device=device)

    out["cutting_env_steps_per_s"] = num_envs / timed(device, step_and_cut, steps)
    out["cutting_cost"] = 1.0 - out["cutting_env_steps_per_s"] / out["plain_env_steps_per_s"]
    # split: masks in the constraint kernels vs the tool / cut() pass
    out["masks_cost"] = 1.0 - out["masked_env_steps_per_s"] / out["plain_env_steps_per_s"]
    out["cut_pass_cost"] = 1.0 - out["cutting_env_steps_per_s"] / out["masked_env_steps_per_s"]

    def tool_and_cut():
        wp.launch(sweep_tool, dim=num_envs, inputs=[counter, *path, period],
                  outputs=[cut.tool_a, cut.tool_b, cut.tool_active], device=device)
        cut.cut()
        wp.launch(advance, dim=1, outputs=[counter], device=device)

    def update_all():  # surfaces, particle masks, connectivity and counters of every env
        world.state.cut_dirty.fill_(1)
        cut.refresh()

    out["cut_ms"] = 1e3 * timed(device, tool_and_cut, steps)  # removal + update, every env cutting
    out["update_ms"] = 1e3 * timed(device, update_all, steps)  # the update part alone
    total = cut.label_total_host.sum()
    out["removed_fraction_mean"] = float(1.0 - cut.active_count.numpy()[:, 0].mean() / total)
    out["components_mean"] = float(cut.num_components.numpy()[:, 0].mean())
    # reset of the cut envs: the same copies, and connectivity of every env recomputed
    out["reset_cut_ms"] = 1e3 * timed(device, reset, steps)
    out["unstable_envs"] = int(world.unstable.numpy().sum())
    return out


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--device", default="cuda:0")
    p.add_argument("--num-envs", type=int, nargs="+", default=[4096])
    p.add_argument("--scene", choices=["cloth", "tet", "all"], default="all")
    p.add_argument("--substeps", type=int, default=20)
    p.add_argument("--steps", type=int, default=20)
    p.add_argument("--out", default=None)
    a = p.parse_args()
    wp.config.log_level = max(wp.config.log_level, wp.LOG_WARNING)
    wp.init()
    scenes = ["cloth", "tet"] if a.scene == "all" else [a.scene]
    rows = []
    for n in a.num_envs:
        for sc in scenes:
            r = run(sc, n, a.device, a.substeps, a.steps)
            rows.append(r)
            print(json.dumps(r), flush=True)
    if a.out:
        with open(a.out, "w") as f:
            json.dump(rows, f, indent=1)


if __name__ == "__main__":
    main()
