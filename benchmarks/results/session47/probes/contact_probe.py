"""Probe (forty-seventh session, for the next lease): where the particle contact launch's time goes
(``contact.particle_collision_kernel``; RopeThreading 5.2 ms, ThreadInHole 1.5 ms, LigatingLoop 3.7 ms per env step at
4,096 envs). Captures one recorded launch of it from an env's step, then times variants on the same inputs with CUDA
events, the positions restored before each launch (the same contacts every time): as it is; loads only (the index,
inverse mass, live flag and position, no shape); every shape's cull but no contact; no friction; no reports or force
sums.

    python benchmarks/results/session47/probes/contact_probe.py RopeThreading 4096 out.json
"""
import json
import sys
import time

import numpy as np
import torch
import warp as wp

import lapwarp
import lapwarp.kernels.contact as ck
from lapwarp.kernels.contact import (
    SHAPE_SURFACE,
    BodyMotion,
    ContactParticles,
    ContactReports,
    CutMasks,
    IgnoreMask,
    ParticleSolve,
    ShapePoses,
    ShapeTable,
    add_pair_force,
    friction_correction,
    group_out_of_reach,
    ignored_bodies,
    particle_live,
    passes_through,
    record_contact,
    sdf_local,
    sdf_primitive,
    shape_pose,
    start_position,
)

meshes = False  # the variants are the rod tasks' (no mesh shape): wp.static(meshes) below

def cp_loads_only(
    particles: ContactParticles,
    shapes: ShapeTable,
    motion: BodyMotion,
    poses: ShapePoses,
    solve: ParticleSolve,
    ignore: IgnoreMask,
    masks: CutMasks,
    report: int,
    report_margin: float,
    q: wp.array2d(dtype=wp.vec3),
    reports: ContactReports,
):
    env, k = wp.tid()
    i = particles.particle[k]
    w = solve.inv_mass[env % solve.inv_mass.shape[0], i]
    if w == 0.0:
        return
    if not particle_live(masks, env, i):
        return  # every element of the particle was cut away
    g = particles.group[k]
    r = particles.radius[k]
    x = q[env, i]
    # the particle's start of substep and its pass-through mask are read only where a shape is near (again for a
    # second shape: cached): most particles (a cavity's 750 nodes against an instrument) are culled for every
    # shape, and these loads were most of their memory traffic
    if x[0] > 1.0e30:
        q[env, i] = x
    return
    moved = int(0)
    for grp in range(poses.group_start.shape[0] - 1):
        # beyond the group's sphere by more than r + report margin, every shape below would be culled (x does
        # not move while none is touched)
        if group_out_of_reach(poses, env, grp, x, r + report_margin):
            continue
        for s in range(poses.group_start[grp], poses.group_start[grp + 1]):
            pair = shapes.pair_index[s, g]
            if pair < 0 or shapes.kind[s] == SHAPE_SURFACE:
                continue
            reach = r + shapes.thickness[s]
            tf = poses.tf[env, s]
            # exact cull: beyond the shape's bounding sphere by more than reach + report margin there is neither
            # contact nor a report (pen <= -report_margin below)
            if wp.length(x - wp.transform_get_translation(tf)) > poses.bound[s] + reach + report_margin:
                continue
            if passes_through(shapes, s, ignored_bodies(ignore, env, i)):
                continue
            pl = wp.transform_point(poses.tf_inv[env, s], x)
            nd = wp.vec4()
            if wp.static(meshes):
                nd = sdf_local(shapes.kind[s], shapes.params[s], shapes.mesh[s], pl,
                               reach + report_margin + 1.0e-3)
            else:
                nd = sdf_primitive(shapes.kind[s], shapes.params[s], pl)
            d = nd[3]
            pen = reach - d
            if report != 0 and pen > -report_margin:
                wp.atomic_add(reports.report_count, env, pair, 1)
                record_contact(env, i, s, wp.transform_vector(tf, wp.vec3(nd[0], nd[1], nd[2])), pen, reports)
            if pen <= 0.0:
                continue
            n = wp.transform_vector(tf, wp.vec3(nd[0], nd[1], nd[2]))
            x = x + n * pen
            x0 = start_position(solve, env, i)
            # where the touched surface point was at the start of the substep (moving tools drag particles along)
            tf0 = shape_pose(shapes, s, env, motion, motion.blend_prev)
            xs0 = wp.transform_point(tf0, wp.transform_point(wp.transform_inverse(tf), x))
            x = x + friction_correction((x - x0) - (x - xs0), n, pen, shapes.mu[s])
            add_pair_force(reports, env, pair, pen / w, solve)
            moved = 1
    # only a moved particle is written: a particle in two groups (GraspLiftAndTouch's gallbladder surface meets the
    # instruments in one and the liver in another) has two threads here, and an unconditional write of the other
    # thread's stale copy would race
    if moved != 0:
        q[env, i] = x



def cp_cull_only(
    particles: ContactParticles,
    shapes: ShapeTable,
    motion: BodyMotion,
    poses: ShapePoses,
    solve: ParticleSolve,
    ignore: IgnoreMask,
    masks: CutMasks,
    report: int,
    report_margin: float,
    q: wp.array2d(dtype=wp.vec3),
    reports: ContactReports,
):
    env, k = wp.tid()
    i = particles.particle[k]
    w = solve.inv_mass[env % solve.inv_mass.shape[0], i]
    if w == 0.0:
        return
    if not particle_live(masks, env, i):
        return  # every element of the particle was cut away
    g = particles.group[k]
    r = particles.radius[k]
    x = q[env, i]
    # the particle's start of substep and its pass-through mask are read only where a shape is near (again for a
    # second shape: cached): most particles (a cavity's 750 nodes against an instrument) are culled for every
    # shape, and these loads were most of their memory traffic
    moved = int(0)
    for grp in range(poses.group_start.shape[0] - 1):
        # beyond the group's sphere by more than r + report margin, every shape below would be culled (x does
        # not move while none is touched)
        if group_out_of_reach(poses, env, grp, x, r + report_margin):
            continue
        for s in range(poses.group_start[grp], poses.group_start[grp + 1]):
            pair = shapes.pair_index[s, g]
            if pair < 0 or shapes.kind[s] == SHAPE_SURFACE:
                continue
            reach = r + shapes.thickness[s]
            tf = poses.tf[env, s]
            # exact cull: beyond the shape's bounding sphere by more than reach + report margin there is neither
            # contact nor a report (pen <= -report_margin below)
            if wp.length(x - wp.transform_get_translation(tf)) > poses.bound[s] + reach + report_margin:
                continue
            if x[0] < 1.0e30:
                continue
            if passes_through(shapes, s, ignored_bodies(ignore, env, i)):
                continue
            pl = wp.transform_point(poses.tf_inv[env, s], x)
            nd = wp.vec4()
            if wp.static(meshes):
                nd = sdf_local(shapes.kind[s], shapes.params[s], shapes.mesh[s], pl,
                               reach + report_margin + 1.0e-3)
            else:
                nd = sdf_primitive(shapes.kind[s], shapes.params[s], pl)
            d = nd[3]
            pen = reach - d
            if report != 0 and pen > -report_margin:
                wp.atomic_add(reports.report_count, env, pair, 1)
                record_contact(env, i, s, wp.transform_vector(tf, wp.vec3(nd[0], nd[1], nd[2])), pen, reports)
            if pen <= 0.0:
                continue
            n = wp.transform_vector(tf, wp.vec3(nd[0], nd[1], nd[2]))
            x = x + n * pen
            x0 = start_position(solve, env, i)
            # where the touched surface point was at the start of the substep (moving tools drag particles along)
            tf0 = shape_pose(shapes, s, env, motion, motion.blend_prev)
            xs0 = wp.transform_point(tf0, wp.transform_point(wp.transform_inverse(tf), x))
            x = x + friction_correction((x - x0) - (x - xs0), n, pen, shapes.mu[s])
            add_pair_force(reports, env, pair, pen / w, solve)
            moved = 1
    # only a moved particle is written: a particle in two groups (GraspLiftAndTouch's gallbladder surface meets the
    # instruments in one and the liver in another) has two threads here, and an unconditional write of the other
    # thread's stale copy would race
    if moved != 0:
        q[env, i] = x



def cp_no_friction(
    particles: ContactParticles,
    shapes: ShapeTable,
    motion: BodyMotion,
    poses: ShapePoses,
    solve: ParticleSolve,
    ignore: IgnoreMask,
    masks: CutMasks,
    report: int,
    report_margin: float,
    q: wp.array2d(dtype=wp.vec3),
    reports: ContactReports,
):
    env, k = wp.tid()
    i = particles.particle[k]
    w = solve.inv_mass[env % solve.inv_mass.shape[0], i]
    if w == 0.0:
        return
    if not particle_live(masks, env, i):
        return  # every element of the particle was cut away
    g = particles.group[k]
    r = particles.radius[k]
    x = q[env, i]
    # the particle's start of substep and its pass-through mask are read only where a shape is near (again for a
    # second shape: cached): most particles (a cavity's 750 nodes against an instrument) are culled for every
    # shape, and these loads were most of their memory traffic
    moved = int(0)
    for grp in range(poses.group_start.shape[0] - 1):
        # beyond the group's sphere by more than r + report margin, every shape below would be culled (x does
        # not move while none is touched)
        if group_out_of_reach(poses, env, grp, x, r + report_margin):
            continue
        for s in range(poses.group_start[grp], poses.group_start[grp + 1]):
            pair = shapes.pair_index[s, g]
            if pair < 0 or shapes.kind[s] == SHAPE_SURFACE:
                continue
            reach = r + shapes.thickness[s]
            tf = poses.tf[env, s]
            # exact cull: beyond the shape's bounding sphere by more than reach + report margin there is neither
            # contact nor a report (pen <= -report_margin below)
            if wp.length(x - wp.transform_get_translation(tf)) > poses.bound[s] + reach + report_margin:
                continue
            if passes_through(shapes, s, ignored_bodies(ignore, env, i)):
                continue
            pl = wp.transform_point(poses.tf_inv[env, s], x)
            nd = wp.vec4()
            if wp.static(meshes):
                nd = sdf_local(shapes.kind[s], shapes.params[s], shapes.mesh[s], pl,
                               reach + report_margin + 1.0e-3)
            else:
                nd = sdf_primitive(shapes.kind[s], shapes.params[s], pl)
            d = nd[3]
            pen = reach - d
            if report != 0 and pen > -report_margin:
                wp.atomic_add(reports.report_count, env, pair, 1)
                record_contact(env, i, s, wp.transform_vector(tf, wp.vec3(nd[0], nd[1], nd[2])), pen, reports)
            if pen <= 0.0:
                continue
            n = wp.transform_vector(tf, wp.vec3(nd[0], nd[1], nd[2]))
            x = x + n * pen
            add_pair_force(reports, env, pair, pen / w, solve)
            moved = 1
    # only a moved particle is written: a particle in two groups (GraspLiftAndTouch's gallbladder surface meets the
    # instruments in one and the liver in another) has two threads here, and an unconditional write of the other
    # thread's stale copy would race
    if moved != 0:
        q[env, i] = x



def cp_no_report(
    particles: ContactParticles,
    shapes: ShapeTable,
    motion: BodyMotion,
    poses: ShapePoses,
    solve: ParticleSolve,
    ignore: IgnoreMask,
    masks: CutMasks,
    report: int,
    report_margin: float,
    q: wp.array2d(dtype=wp.vec3),
    reports: ContactReports,
):
    env, k = wp.tid()
    i = particles.particle[k]
    w = solve.inv_mass[env % solve.inv_mass.shape[0], i]
    if w == 0.0:
        return
    if not particle_live(masks, env, i):
        return  # every element of the particle was cut away
    g = particles.group[k]
    r = particles.radius[k]
    x = q[env, i]
    # the particle's start of substep and its pass-through mask are read only where a shape is near (again for a
    # second shape: cached): most particles (a cavity's 750 nodes against an instrument) are culled for every
    # shape, and these loads were most of their memory traffic
    moved = int(0)
    for grp in range(poses.group_start.shape[0] - 1):
        # beyond the group's sphere by more than r + report margin, every shape below would be culled (x does
        # not move while none is touched)
        if group_out_of_reach(poses, env, grp, x, r + report_margin):
            continue
        for s in range(poses.group_start[grp], poses.group_start[grp + 1]):
            pair = shapes.pair_index[s, g]
            if pair < 0 or shapes.kind[s] == SHAPE_SURFACE:
                continue
            reach = r + shapes.thickness[s]
            tf = poses.tf[env, s]
            # exact cull: beyond the shape's bounding sphere by more than reach + report margin there is neither
            # contact nor a report (pen <= -report_margin below)
            if wp.length(x - wp.transform_get_translation(tf)) > poses.bound[s] + reach + report_margin:
                continue
            if passes_through(shapes, s, ignored_bodies(ignore, env, i)):
                continue
            pl = wp.transform_point(poses.tf_inv[env, s], x)
            nd = wp.vec4()
            if wp.static(meshes):
                nd = sdf_local(shapes.kind[s], shapes.params[s], shapes.mesh[s], pl,
                               reach + report_margin + 1.0e-3)
            else:
                nd = sdf_primitive(shapes.kind[s], shapes.params[s], pl)
            d = nd[3]
            pen = reach - d
            if pen <= 0.0:
                continue
            n = wp.transform_vector(tf, wp.vec3(nd[0], nd[1], nd[2]))
            x = x + n * pen
            x0 = start_position(solve, env, i)
            # where the touched surface point was at the start of the substep (moving tools drag particles along)
            tf0 = shape_pose(shapes, s, env, motion, motion.blend_prev)
            xs0 = wp.transform_point(tf0, wp.transform_point(wp.transform_inverse(tf), x))
            x = x + friction_correction((x - x0) - (x - xs0), n, pen, shapes.mu[s])
            moved = 1
    # only a moved particle is written: a particle in two groups (GraspLiftAndTouch's gallbladder surface meets the
    # instruments in one and the liver in another) has two threads here, and an unconditional write of the other
    # thread's stale copy would race
    if moved != 0:
        q[env, i] = x



VARIANT_NAMES = ['cp_loads_only', 'cp_cull_only', 'cp_no_friction', 'cp_no_report']


def main():
    task, n, out = sys.argv[1], int(sys.argv[2]), sys.argv[3]
    device = sys.argv[4] if len(sys.argv) > 4 else "cuda:0"
    reps = 30 if device.startswith("cuda") else 2
    # the events are recorded on the current device's stream: on cuda:1 (the forty-eighth session's lease) without
    # this they timed cuda:0's idle stream (2.9 us for every variant)
    wp.set_device(device)
    env = lapwarp.make(task, num_envs=n, device=device, use_cuda_graph=False)
    env.reset()
    zero = torch.zeros((n, env.num_actions), device=env.device)
    captured = []
    launch = wp.launch

    def spy(kernel, *args, **kw):
        if "collide_particles" in kernel.key and not captured:
            captured.append((kernel, args, dict(kw)))
        return launch(kernel, *args, **kw)

    wp.launch = spy
    env.world._record_step(env.cfg.time_step)  # records (record_cmd=True: nothing runs) the world step's launches
    wp.launch = launch
    for _ in range(3):
        env.step(zero)
    wp.synchronize()
    kernel, args, kw = captured[0]
    kw.pop("record_cmd", None)
    inputs, outputs = list(kw.pop("inputs")), list(kw.pop("outputs"))
    if len(inputs) != 9 or len(outputs) != 2:
        raise RuntimeError(f"unexpected arguments of {kernel.key}: {len(inputs)} inputs, {len(outputs)} outputs")
    meshes_here = kernel is ck.particle_collision_kernel(True)
    q = outputs[0]
    saved = wp.clone(q)
    variants = {"as_is": kernel}
    if not meshes_here:
        for name in VARIANT_NAMES:
            variants[name] = wp.kernel(globals()[name], module="unique", enable_backward=False)

    def timed(k):
        """ms per launch of ``k`` (CUDA): ``reps`` launches, each after restoring the positions, captured in a CUDA
        graph, less a graph of the restores alone. With events around each launch from Python (the forty-eighth
        session's first run) loads only read 38 us per launch for RopeThreading's 409,600 threads and LigatingLoop's
        3.3M alike: a floor that does not scale with the work, most likely the host packing the launch while the GPU
        waited."""
        if not device.startswith("cuda"):
            launch(k, inputs=inputs, outputs=outputs, **kw)
            return 0.0

        def graph_ms(with_kernel):
            with wp.ScopedCapture(device) as capture:
                for _ in range(reps):
                    wp.copy(q, saved)
                    if with_kernel:
                        launch(k, inputs=inputs, outputs=outputs, **kw)
            wp.capture_launch(capture.graph)  # warm-up
            times = []
            for _ in range(5):
                a, b = wp.Event(enable_timing=True), wp.Event(enable_timing=True)
                wp.record_event(a)
                wp.capture_launch(capture.graph)
                wp.record_event(b)
                wp.synchronize()
                times.append(wp.get_event_elapsed_time(a, b))
            return float(np.median(times))

        return (graph_ms(True) - graph_ms(False)) / reps

    result = {"task": task, "num_envs": n, "kernel": kernel.key, "dim": list(kw.get("dim") or []),
              "block_dim": kw.get("block_dim"), "meshes": meshes_here, "ms": {}}
    for _round in range(2):
        for name, k in variants.items():
            result["ms"].setdefault(name, []).append(timed(k))
    for name, v in result["ms"].items():
        print(f"{name:16s} {v}")
    with open(out, "w") as f:
        json.dump(result, f, indent=1)


if __name__ == "__main__":
    t0 = time.time()
    main()
    print(f"done in {time.time() - t0:.1f} s")
