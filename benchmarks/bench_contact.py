"""Cost of contact: env-steps/s of the physics benchmark scenes with and without a ContactSystem.

The scenes are those of ``bench_physics.py`` (cloth 40 x 40, tet block 1,008 tets, rod 100 segments). "With
contact" adds, per env: an instrument capsule (r = 2.25 mm, on a kinematic body) crossing the object, a static
triangle-mesh box (one ``wp.Mesh`` shared by all envs, 12 triangles) the object swings or sags into, a floor
plane, and for the rod segment-level contact plus brute-force self-contact of its 101 nodes (skip 2 links).
Every particle of the object is in the contact group. One env step = 0.1 s; CUDA graph on GPUs.

Examples::

    python benchmarks/bench_contact.py --device cuda:0 --num-envs 1024 4096 --out benchmarks/contact.json
    python benchmarks/bench_contact.py --device cpu --num-envs 2 --steps 2 --settle-steps 1   # smoke test
"""

from __future__ import annotations

import argparse
import json
import os
import sys

import numpy as np
import trimesh
import warp as wp

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from bench_physics import DT, SCENES, timed_steps  # noqa: E402

from lapwarp.contact import ContactSystem  # noqa: E402

# per scene: capsule (position, quaternion xyzw), mesh box (extents, centre), radius of the particles
_AXIS_X = (0.0, 0.70710678, 0.0, 0.70710678)  # capsule axis (local z) along world x
LAYOUT = {
    "cloth": dict(capsule=((0.0375, 0.004, -0.04), _AXIS_X), box=((0.09, 0.01, 0.1), (0.0375, 0.02, -0.04)),
                  radius=5e-4),
    # the capsule indents the top 2 mm below its rest height and the prop's face touches the block's +x side
    "tet": dict(capsule=((0.02, 0.02, 0.02 + 2.25e-3 - 2e-3), _AXIS_X),
                box=((0.01, 0.06, 0.05), (0.045, 0.02, 0.0)), radius=0.0, thickness=2e-4),
    "rod": dict(capsule=((0.0, 0.0, -0.1), _AXIS_X), box=((0.1, 0.1, 0.02), (0.05, 0.0, -0.2)), radius=0.001),
}


def add_contact(world, obj, scene: str, body: int) -> ContactSystem:
    lay = LAYOUT[scene]
    cs = ContactSystem(world, capacity=64)
    # cloth: triangle contact too, so the tool cannot pass between vertices (docs/contact.md)
    cs.add_particle_group(obj, radius=lay["radius"], segments=True if scene == "rod" else None,
                          triangles=True if scene == "cloth" else None)
    (pos, quat) = lay["capsule"]
    q = np.zeros((world.num_envs, 1, 7), dtype=np.float32)
    q[:, 0, :3] = pos
    q[:, 0, 3:] = quat
    world.set_body_poses(wp.array(q, dtype=wp.transform, device=world.device),
                         wp.array([body], dtype=wp.int32, device=world.device),
                         teleport_mask=wp.ones(world.num_envs, dtype=wp.int32, device=world.device))
    cs.add_capsule(2.25e-3, 0.04, body=body, name="instrument")
    ext, centre = lay["box"]
    box = trimesh.creation.box(extents=ext)
    box.apply_translation(centre)
    cs.add_mesh(box.vertices, box.faces, name="prop", thickness=lay.get("thickness", 0.0))
    cs.add_plane(transform=(0.0, 0.0, -0.3), name="floor")
    if scene == "rod":
        cs.add_particle_contact([(obj, 0.001)], skip_links=2, name="self")
    return cs.finalize()


def run(scene: str, num_envs: int, device: str, substeps: int, steps: int, settle: int, contact: bool) -> dict:
    import lapwarp.builder as lb

    # the scene builders finalize internally: add the instrument body by wrapping finalize once
    orig = lb.SceneBuilder.finalize
    holder = {}

    def finalize(self, *a, **k):
        holder["body"] = self.add_body("instrument")
        return orig(self, *a, **k)

    lb.SceneBuilder.finalize = finalize
    try:
        world, obj, _, _ = SCENES[scene](num_envs, device, substeps, 1, "chains")
    finally:
        lb.SceneBuilder.finalize = orig
    cs = add_contact(world, obj, scene, holder["body"]) if contact else None
    dev = wp.get_device(device)
    for _ in range(max(1, settle)):
        world.step(DT)
    elapsed = timed_steps(world, device, steps)
    rec = {"scene": scene, "contact": contact, "device": dev.name if dev.is_cuda else "cpu", "num_envs": num_envs,
           "substeps": substeps, "steps_timed": steps, "seconds": elapsed, "cuda_graph": dev.is_cuda,
           "env_steps_per_s": num_envs * steps / elapsed, "unstable_envs": int(world.unstable.numpy().sum())}
    if cs is not None:
        counts = cs.counts()
        rec["mean_contacts_per_env"] = {n: float(counts[:, k].mean()) for k, n in enumerate(cs.pair_names)}
        rec["overflow_envs"] = int(cs.overflow.numpy().sum())
    return rec


def crossover(device: str, num_envs: int, sizes, steps: int) -> list[dict]:
    """Particle-particle contact cost, brute force vs per-env cell list: a random cloud of M particles
    (r = 1 mm, density of a loosely packed pile: 5 % volume fraction) per env, 10 substeps, no other physics."""
    import numpy as np

    from lapwarp.builder import SceneBuilder

    out = []
    for m in sizes:
        rec = {"members": m, "num_envs": num_envs}
        side = (m * (4.0 / 3.0) * np.pi * 1e-9 / 0.05) ** (1.0 / 3.0)
        for method in ("brute", "grid"):
            b = SceneBuilder(gravity=(0.0, 0.0, 0.0))
            p = b.add_particles(np.random.default_rng(0).uniform(0.0, side, (m, 3)), mass=1e-3, damping=5.0)
            w = b.finalize(num_envs, device, substeps=10)
            cs = ContactSystem(w)
            cs.add_particle_contact([(p, 0.001)], method=method)
            cs.finalize()
            w.step(DT)
            rec[f"{method}_env_steps_per_s"] = num_envs * steps / timed_steps(w, device, steps)
        print(f"members={m:5d} envs={num_envs}: brute {rec['brute_env_steps_per_s']:10.1f}  "
              f"grid {rec['grid_env_steps_per_s']:10.1f} env-steps/s", flush=True)
        out.append(rec)
    return out


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--device", default="cuda:0")
    p.add_argument("--num-envs", type=int, nargs="+", default=[1024, 4096])
    p.add_argument("--scene", choices=["cloth", "tet", "rod", "all"], default="all")
    p.add_argument("--substeps", type=int, default=20)
    p.add_argument("--steps", type=int, default=50)
    p.add_argument("--settle-steps", type=int, default=10)
    p.add_argument("--out", default=None)
    p.add_argument("--crossover", type=int, nargs="*", default=None,
                   help="instead: particle-particle brute force vs cell list for these set sizes")
    args = p.parse_args()
    wp.config.quiet = True
    wp.init()
    if args.crossover is not None:
        res = crossover(args.device, args.num_envs[0], args.crossover or [64, 128, 256, 512, 1024, 2048], args.steps)
        if args.out:
            with open(args.out, "w") as f:
                json.dump(res, f, indent=2)
        return
    scenes = ["cloth", "tet", "rod"] if args.scene == "all" else [args.scene]
    results = []
    for scene in scenes:
        for n in args.num_envs:
            pair = [run(scene, n, args.device, args.substeps, args.steps, args.settle_steps, c) for c in (False, True)]
            ratio = pair[0]["env_steps_per_s"] / pair[1]["env_steps_per_s"]
            for r in pair:
                r["slowdown_with_contact"] = ratio
                results.append(r)
            print(f"{scene:5s} envs={n:6d} without={pair[0]['env_steps_per_s']:12.1f} "
                  f"with={pair[1]['env_steps_per_s']:12.1f} env-steps/s  slowdown x{ratio:.2f}  "
                  f"contacts/env={pair[1].get('mean_contacts_per_env')}", flush=True)
    if args.out:
        with open(args.out, "w") as f:
            json.dump(results, f, indent=2)


if __name__ == "__main__":
    main()
