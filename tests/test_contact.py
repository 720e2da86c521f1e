"""Contact: resting bounds, Coulomb friction on an incline, no tunnelling of fast tools, reports that match a
hand-built scene, env isolation, static meshes and particle-particle contact."""

from __future__ import annotations

import math

import numpy as np
import pytest
import trimesh
import warp as wp

from lapwarp.assets import box_tets, cloth_grid, rod_circle, rod_polyline
from lapwarp.builder import SceneBuilder
from lapwarp.contact import ContactSystem
from lapwarp.kernels.hold import TetHold
from lapwarp.surface_clusters import SurfaceClusters


def _quat_axis_angle(axis, angle):
    a = np.asarray(axis, dtype=np.float64) / np.linalg.norm(axis)
    s = math.sin(angle / 2.0)
    return (a[0] * s, a[1] * s, a[2] * s, math.cos(angle / 2.0))


def _rotate(points, q):
    r = trimesh.transformations.quaternion_matrix([q[3], q[0], q[1], q[2]])[:3, :3]
    return np.asarray(points) @ r.T


# ----------------------------------------------------------------------------------------------------
def test_rest_on_plane_box_sphere_cylinder_within_thickness(device):
    """Particles dropped on each primitive come to rest at distance radius + thickness (bound: 1e-5 m)."""
    b = SceneBuilder()
    pts = np.array([[0.0, 0.0, 0.02], [0.2, 0.0, 0.05], [0.4, 0.0, 0.05], [0.6, 0.0, 0.05], [0.8, 0.0, 0.05]])
    p = b.add_particles(pts, mass=0.01, damping=2.0)
    w = b.finalize(num_envs=2, device=device, substeps=10)
    cs = ContactSystem(w)
    cs.add_particle_group(p, radius=0.002)
    cs.add_plane(thickness=0.001, name="floor")
    cs.add_sphere(0.01, transform=(0.2, 0.0, 0.0), thickness=0.0005, name="ball")
    cs.add_box((0.01, 0.01, 0.01), transform=(0.4, 0.0, 0.0), thickness=0.0005, name="box")
    cs.add_cylinder(0.01, 0.01, transform=(0.6, 0.0, 0.0), thickness=0.0005, name="cyl")
    cs.add_capsule(0.01, 0.02, transform=(0.8, 0.0, 0.0, *_quat_axis_angle((1, 0, 0), math.pi / 2)),
                   thickness=0.0005, name="capsule")
    cs.finalize()
    w.simulate(1.5, 0.1)
    z = w.positions()[:, :, 2]
    expect = np.array([0.003, 0.0125, 0.0125, 0.0125, 0.0125])
    assert np.abs(z - expect).max() < 1.0e-5, z
    # weight carried by each collider: the mean normal force over the step equals m g (within 1 %)
    f = cs.forces()
    for name, col in (("floor", 0), ("ball", 1), ("box", 2), ("cyl", 3), ("capsule", 4)):
        assert f[0, cs.pair(name, "particles")] == pytest.approx(0.01 * 9.81 * (col >= 0), rel=0.01)


def _incline(device, theta_deg, mu, seconds=1.0):
    theta = math.radians(theta_deg)
    q = _quat_axis_angle((0, 1, 0), theta)
    v, t = box_tets((0.02, 0.02, 0.01), (2, 2, 1), origin=(-0.01, -0.01, 0.0005))
    b = SceneBuilder()
    blk = b.add_tet_mesh(_rotate(v, q), t, density=1000.0, youngs_modulus=1e5, poisson_ratio=0.3)
    w = b.finalize(num_envs=1, device=device, substeps=20)
    cs = ContactSystem(w)
    cs.add_particle_group(blk, radius=0.0)
    cs.add_plane(transform=(0, 0, 0, *q), thickness=0.0005, mu_static=mu, mu_kinetic=mu)
    cs.finalize()
    # the elastic block settles (sags and shears by ~0.15 mm) in its first steps: measure from t = 0.5 s
    w.simulate(0.5, 0.05)
    x0 = w.positions()[0].mean(axis=0)
    w.simulate(seconds, 0.05)
    x1 = w.positions()[0].mean(axis=0)
    downhill = _rotate(np.array([[1.0, 0.0, 0.0]]), q)[0]
    downhill *= -np.sign(downhill[2])
    return float(np.dot(x1 - x0, downhill)), theta


def test_incline_sticks_below_atan_mu_and_slides_above(device):
    """Block on an incline with mu = 0.5: sticks for tan(theta) = 0.8 mu (moves < 1 um from t = 0.5 to 1.5 s);
    for tan(theta) = 1.3 mu it slides from rest with a = g (sin - mu cos): x(1.5) - x(0.5) = a (closed form,
    within 3 %)."""
    mu = 0.5
    stick, _ = _incline(device, math.degrees(math.atan(0.8 * mu)), mu)
    assert abs(stick) < 1.0e-6
    slide, theta = _incline(device, math.degrees(math.atan(1.3 * mu)), mu)
    expected = 0.5 * 9.81 * (math.sin(theta) - mu * math.cos(theta)) * (1.5**2 - 0.5**2)
    assert slide == pytest.approx(expected, rel=0.03)


# ----------------------------------------------------------------------------------------------------
def _seg_seg_dist(p, q, c0, c1):
    """Distances between segments p[k]q[k] and the segment c0c1 (sampled finely: test-side reference)."""
    t = np.linspace(0.0, 1.0, 41)
    a = p[:, None, :] + (q - p)[:, None, :] * t[None, :, None]  # (k, 41, 3)
    d = c1 - c0
    u = np.clip(((a - c0) @ d) / (d @ d), 0.0, 1.0)
    return np.linalg.norm(a - (c0 + u[..., None] * d), axis=2).min(axis=1)


def _push_capsule(device, speed, segments=True, kind="rod", substeps=10, triangles=True, triangle_sweep="fused",
                  positions=None, triangle_block_threads=None, fuse_segments=True, pose_per_step=False,
                  report_forces=True):
    """A capsule (r = 1 mm, axis along y) on body 0 moves along +z at ``speed`` through a free, weightless rod
    (r = 0.5 mm, 5 mm node spacing) or cloth (1 mm spacing) lying across its path.

    Returns:
        ``(gap, ahead)``: the minimum over the steps of the distance between the deformable (rod segments or
        cloth vertices, triangle centroids and edge midpoints) and the capsule axis minus both radii (negative =
        penetration), and whether the deformable is still carried in front of the tool at the end (a tool that
        tunnels leaves it behind). ``positions``, a list, receives the deformable's final positions.
    """
    b = SceneBuilder(gravity=(0.0, 0.0, 0.0))
    if kind == "rod":
        obj = b.add_rod(rod_polyline([[-0.05, 0, 0.005], [0.05, 0, 0.005]], 21), radius=5e-4, youngs_modulus=1e6)
        r = 5e-4
    else:
        v, tri = cloth_grid(41, 21, 0.04, 0.02, plane="xy", origin=(-0.02, -0.01, 0.005))
        obj = b.add_cloth(v, tri, areal_density=0.2, stretch_stiffness=1000.0, bend_stiffness=1e-7)
        r = 2.5e-4
    body = b.add_body("tool", pose=(0, 0, 0, *_quat_axis_angle((1, 0, 0), math.pi / 2)))
    w = b.finalize(num_envs=1, device=device, substeps=substeps)
    cs = ContactSystem(w)
    cs.add_particle_group(obj, radius=r, segments=segments if kind == "rod" else None,
                          triangles=triangles if kind == "cloth" else None)
    rc, hh = 1e-3, 0.012
    cs.add_capsule(rc, hh, body=body)  # axis along world y after the body rotation: crosses the rod
    cs.finalize()
    cs.triangle_sweep = triangle_sweep
    cs.fuse_segment_colors = fuse_segments
    cs.pose_per_step = pose_per_step
    cs.report_forces = report_forces
    if triangle_block_threads is not None:
        cs.triangle_block_threads = triangle_block_threads
    dt = 0.1
    pose = w.state.body_q.numpy()
    gap = np.inf
    for k in range(1, 16):
        zc = speed * dt * k
        pose[0, 0, 2] = zc
        w.state.body_q.assign(pose)
        w.step(dt)
        x = w.positions(obj)[0]
        c0, c1 = np.array([0.0, -hh, zc]), np.array([0.0, hh, zc])
        if kind == "rod":
            d = _seg_seg_dist(x[:-1], x[1:], c0, c1)
        else:
            # vertices, triangle centroids and edge midpoints (the tool must not sink into the triangles either)
            t = obj.surface_tris - obj.particle_start
            pts = np.concatenate([x, x[t].mean(axis=1), 0.5 * (x[t[:, 0]] + x[t[:, 1]]),
                                  0.5 * (x[t[:, 1]] + x[t[:, 2]]), 0.5 * (x[t[:, 2]] + x[t[:, 0]])])
            d = _seg_seg_dist(pts, pts, c0, c1)
        gap = min(gap, float(d.min()) - rc - r)
    if positions is not None:
        positions.append(x)
    return gap, bool(x[:, 2].max() > zc + rc)


@pytest.mark.parametrize("speed", [0.035, 0.1])
def test_capsule_never_tunnels_through_thin_rod(device, speed):
    """35 mm/s (max instrument speed) and 0.1 m/s (1 mm per substep, 5 mm node spacing > 2 mm tool diameter):
    the rod stays in front of the capsule, penetration below 0.05 mm at every step."""
    gap, ahead = _push_capsule(device, speed)
    assert gap > -5.0e-5 and ahead


def test_tunnelling_detected_without_segment_contact(device):
    """The measurement can fail: with node-only contact the 2 mm tool slips between 5 mm spaced nodes."""
    gap, ahead = _push_capsule(device, 0.1, segments=False)
    assert gap < -2.0e-4 or not ahead


@pytest.mark.parametrize("speed", [0.035, 0.1])
def test_capsule_never_tunnels_through_cloth(device, speed):
    """Cloth with 1 mm vertex spacing (the tool radius), 10 substeps: at 35 mm/s and at 0.1 m/s (1 mm per
    substep) no cloth point (vertex, centroid, edge midpoint) lies more than 0.1 mm inside the tool and the cloth
    is carried in front of it (triangle contact: the capsule axis against every triangle). The triangles are
    projected colour by colour, so a later colour moving a shared vertex leaves ~0.07 mm at 1 mm per substep."""
    gap, ahead = _push_capsule(device, speed, kind="cloth")
    assert gap > -1.0e-4 and ahead


def test_fused_triangle_sweep_matches_one_launch_per_colour(device):
    """``triangle_sweep = "fused"`` (every colour in one launch, a block per env, a barrier between colours) and
    ``"outcodes"`` (the same with the box cull read from per-particle outcodes in shared memory, updated where a
    contact moves a node) project the same triangles in the same order as one launch per colour: the same cloth, bit
    for bit on the CPU (one lane per block), within float32 rounding on the GPU; and they still stop the tool at
    0.1 m/s."""
    x = {}
    for sweep in ("colored", "fused", "outcodes", "shape_codes"):
        out = []
        gap, ahead = _push_capsule(device, 0.1, kind="cloth", triangle_sweep=sweep, positions=out)
        assert gap > -1.0e-4 and ahead
        x[sweep] = out[0]
    assert np.abs(x["colored"][:, 2] - 0.005).max() > 1.0e-3  # the tool carried the cloth: contacts were projected
    for sweep in ("fused", "outcodes", "shape_codes"):
        if device == "cpu":
            np.testing.assert_array_equal(x[sweep], x["colored"])
        else:
            np.testing.assert_allclose(x[sweep], x["colored"], atol=1e-6)


def test_outcode_sweep_matches_the_fused_sweep_in_a_cutting_task(device):
    """TissueDissection (tissue surfaces of tet faces masked as the hook cuts, four tool shapes): 40 steps of the
    scripted expert give the same particles, cut tets and contact reports under ``"outcodes"`` and ``"shape_codes"``
    as under ``"fused"`` (bit for bit on the CPU; float32 rounding on the GPU, where the reports are summed
    atomically)."""
    import lapwarp
    from lapwarp.experts import make_expert

    out = {}
    for sweep in ("fused", "outcodes", "shape_codes"):
        env = lapwarp.make("TissueDissection", num_envs=2, device=device, seed=3)
        env.contact.triangle_sweep = sweep
        env.contact.pose_per_step = False  # the boxes read below are the per-sweep ones (the same values either way)
        expert = make_expert(env)
        env.reset()
        for _ in range(40):
            env.step(expert())
        out[sweep] = (env.world.state.particle_q.numpy(), env.world.state.tet_active.numpy(),
                      env.contact.reports.report_force.numpy())
        env.close()
    assert (out["fused"][1] == 0).any()  # the hook cut: masked faces were in play
    assert np.abs(out["fused"][2]).max() > 0.0  # and touched the tissue
    for sweep in ("outcodes", "shape_codes"):
        for a, b in zip(out[sweep], out["fused"], strict=True):
            if device == "cpu":
                np.testing.assert_array_equal(a, b)
            else:
                np.testing.assert_allclose(a, b, atol=1e-6)


def test_outcode_sweep_refuses_a_window_beyond_shared_memory(device, monkeypatch):
    from lapwarp.kernels import contact as ck

    monkeypatch.setattr(ck, "OUTCODE_MAX_PARTICLES", 100)
    with pytest.raises(ValueError, match="window of .* particles exceeds 100; use 'fused'"):
        _push_capsule(device, 0.1, kind="cloth", triangle_sweep="outcodes")


def test_auto_triangle_sweep_takes_outcodes_where_the_window_fits(device, monkeypatch):
    """The default ``"auto"`` launches the outcode sweep when the triangles' particle window fits its shared memory
    (ThreadInHole's does) and falls back to the fused one, without an error, when it does not."""
    import lapwarp
    from lapwarp.kernels import contact as ck

    env = lapwarp.make("ThreadInHole", num_envs=1, device=device, seed=0)
    assert env.contact.triangle_sweep == "auto"
    assert env.contact.resolved_triangle_sweep() == "outcodes"
    monkeypatch.setattr(ck, "OUTCODE_MAX_PARTICLES", 10)
    assert env.contact.resolved_triangle_sweep() == "fused"
    env.contact.record_key()  # "auto" never refuses a window
    env.close()


def test_unknown_triangle_sweep_is_rejected(device):
    with pytest.raises(ValueError, match="auto.*colored.*fused.*outcodes"):
        _push_capsule(device, 0.1, kind="cloth", triangle_sweep="jacobi")


@pytest.mark.parametrize("threads", [0, -32, 2048])
def test_triangle_block_threads_outside_a_block_is_rejected(device, threads):
    """The fused sweep's threads per env block are checked when the step is recorded, not left to the launch."""
    with pytest.raises(ValueError, match="triangle_block_threads"):
        _push_capsule(device, 0.1, kind="cloth", triangle_block_threads=threads)


def test_cloth_tunnelling_detected_with_vertex_only_contact(device):
    """The measurement can fail: with vertex-only contact at 0.1 m/s and 10 substeps the tensioned sheet slides
    off the tool's crest and the tool passes through it."""
    gap, ahead = _push_capsule(device, 0.1, kind="cloth", triangles=False)
    assert gap < -2.0e-4 or not ahead


# ----------------------------------------------------------------------------------------------------
def test_contact_counts_match_hand_built_scene_and_envs_are_isolated(device):
    """Env 0: particles A, B resting on the floor, C in the air, D on a sphere -> floor 2, ball 1 contacts.
    Env 1: the tool body sits on C too -> tool 1 more. Env 0's physics is bit-identical to a run without the
    tool and its reports never see env 1's contacts."""

    def build(with_tool):
        b = SceneBuilder()
        pts = np.array([[0.0, 0, 0.002], [0.01, 0, 0.002], [0.05, 0, 0.05], [0.1, 0, 0.012]])
        b.add_particles(pts, mass=0.01)
        b.fix_particles([2])
        tool = b.add_body("tool", pose=(0.05, 0, 0.5, 0, 0, 0, 1))
        w = b.finalize(num_envs=2, device=device, substeps=10)
        cs = ContactSystem(w, capacity=8)
        cs.add_particle_group([0, 1, 3], radius=0.002, name="free")
        cs.add_particle_group([2], radius=0.002, name="pinned")
        cs.add_plane(name="floor")
        cs.add_sphere(0.01, transform=(0.1, 0, 0), name="ball")
        if with_tool:
            cs.add_sphere(0.005, body=tool, name="tool")
        cs.finalize()
        return w, cs

    w, cs = build(True)
    pose = w.state.body_q.numpy()
    pose[1, 0, :3] = (0.05, 0.0, 0.05 + 0.0069)  # env 1 only: tool touching the (pinned) particle C
    w.set_body_poses(wp.array(pose, dtype=wp.transform, device=device), wp.array([0], dtype=wp.int32, device=device),
                     teleport_mask=wp.ones(2, dtype=wp.int32, device=device))
    w.simulate(0.3, 0.1)
    c = cs.counts()
    assert c[0, cs.pair("floor", "free")] == 2 and c[0, cs.pair("ball", "free")] == 1
    # pinned particles never move, so they are skipped by the projection and not reported either
    assert c[1, cs.pair("tool", "pinned")] == 0
    assert c[0].sum() == 3 and c[1].sum() == 3
    assert list(cs.contact_count.numpy()) == [3, 3]
    assert cs.overflow.numpy().sum() == 0
    recs = sorted(zip(cs.contact_particle.numpy()[0, :3], cs.contact_shape.numpy()[0, :3], strict=True))
    assert recs == [(0, 0), (1, 0), (3, 1)]
    w2, _ = build(False)
    w2.simulate(0.3, 0.1)
    assert np.array_equal(w.positions()[0], w2.positions()[0])


def test_tool_contact_only_in_its_env_and_overflow_flag(device):
    """A tool lowered onto a particle row in env 1 only: env 1 counts 5 tool contacts and, with capacity 3,
    raises its overflow flag; env 0 sees no tool contact and no overflow."""
    b = SceneBuilder(gravity=(0.0, 0.0, 0.0))
    p = b.add_particles(np.stack([np.linspace(-0.004, 0.004, 5), np.zeros(5), np.zeros(5)], 1), mass=0.01)
    tool = b.add_body("tool", pose=(0, 0, 0.5, *_quat_axis_angle((0, 1, 0), math.pi / 2)))
    w = b.finalize(num_envs=2, device=device, substeps=10)
    cs = ContactSystem(w, capacity=3)
    cs.add_particle_group(p, radius=0.001)
    cs.add_capsule(0.002, 0.01, body=tool, name="tool")
    cs.finalize()
    sink = wp.zeros(2, dtype=wp.int32, device=device)
    cs.overflow_sink = sink  # an env's flag over its frame skip, raised by the record that found the buffer full
    pose = w.state.body_q.numpy()
    pose[1, 0, 2] = 0.0029
    w.state.body_q.assign(pose)
    w.step(0.1)
    c = cs.counts()[:, 0]
    assert list(c) == [0, 5]
    assert list(cs.overflow.numpy()) == [0, 1]
    assert list(sink.numpy()) == [0, 1]
    # the last sweep's 5 records: the count ends at the capacity (records past it take it back), the 3 slots full
    assert list(cs.contact_count.numpy()) == [0, 3]
    kept = cs.contact_particle.numpy()[1]
    assert len(set(kept)) == 3 and set(kept) <= set(range(5))  # three of the row's five particles, none twice
    assert np.all(w.positions()[0, :, 2] == 0.0)
    assert np.allclose(w.positions()[1, :, 2], 0.0029 - 0.002 - 0.001, atol=1e-6)  # pushed below the tool


# ----------------------------------------------------------------------------------------------------
def test_rest_on_static_mesh_within_thickness(device):
    """A tet block dropped on a static mesh box (shared wp.Mesh) rests with its bottom at the thickness (within
    0.05 mm) and the mesh carries its weight."""
    box = trimesh.creation.box(extents=(0.1, 0.1, 0.02))
    b = SceneBuilder()
    v, t = box_tets((0.02, 0.02, 0.01), (2, 2, 1), origin=(-0.01, -0.01, 0.015))
    blk = b.add_tet_mesh(v, t, density=1000.0, youngs_modulus=1e5, poisson_ratio=0.3, damping=5.0)
    w = b.finalize(num_envs=2, device=device, substeps=20)
    cs = ContactSystem(w)
    cs.add_particle_group(blk, radius=0.0)
    cs.add_mesh(box.vertices, box.faces, thickness=0.001, name="table")  # top face at z = 0.01
    cs.finalize()
    w.simulate(1.0, 0.1)
    z = w.positions(blk)[:, :, 2]
    bottom = z[:, v[:, 2] < 0.0151]
    assert np.abs(bottom - 0.011).max() < 5.0e-5, bottom
    mass = 1000.0 * 0.02 * 0.02 * 0.01
    assert cs.forces()[0, 0] == pytest.approx(mass * 9.81, rel=0.02)


@pytest.mark.parametrize("method", ["brute", "grid"])
def test_rod_self_contact_and_torus_on_peg(device, method):
    """A closed rod (torus, r = 3 mm) dropped over a peg cylinder stays around it (no particle inside the peg)
    and a rod dropped onto itself keeps its nodes >= 2 r - 0.1 mm apart (self-contact), with the brute-force
    pair loop and with the per-env cell list."""
    w, cs, torus, bar = _rods_on_peg(device, seconds=1.0, method=method)
    x = w.positions()[0]
    xt = x[torus.particles]
    assert np.hypot(xt[:, 0], xt[:, 1]).min() > 0.005 + 0.003 - 1e-4
    xb = x[bar.particles]
    d = np.linalg.norm(xt[:, None, :] - xb[None, :, :], axis=2)
    assert d.min() > 0.006 - 1e-4
    assert xb[:, 2].min() > 0.0  # the bar rests on the torus / floor, not through them
    assert cs.counts()[0, cs.pair_names.index("rods")] > 0


def test_bead_rests_on_deforming_tissue_surface_per_env(device):
    """A bead (r = 0.5 mm, 0.1 g) dropped on the top face of a soft tet block (bottom fixed) rests at r + t from
    the *deformed* surface triangle below it (within 0.02 mm; the block sags under it, contact is two-way) and
    the surface carries its weight (m g within 1 %). Env 1's block starts 4 mm lower: its bead rests 4 mm lower
    (within 0.02 mm), so the grouped per-env BVH never mixes envs although all of them sit at the origin. The
    bead sits over a triangle interior, 4-5 mm from the nearest vertex, so vertex contact could not hold it."""
    v, t = box_tets((0.02, 0.02, 0.01), (2, 2, 1), origin=(-0.01, -0.01, 0.0))
    b = SceneBuilder()
    blk = b.add_tet_mesh(v, t, density=1000.0, youngs_modulus=1e5, poisson_ratio=0.3, damping=5.0,
                         fixed=np.nonzero(v[:, 2] < 1e-9)[0])
    bead = b.add_particles(np.array([[0.005, 0.004, 0.02]]), mass=1.0e-4, damping=2.0)
    w = b.finalize(num_envs=2, device=device, substeps=20)
    q = w.state.particle_q.numpy()
    q[1, blk.particles, 2] -= 0.004
    w.state.particle_q.assign(q)
    w.save_start_state()
    cs = ContactSystem(w)
    cs.add_particle_group(bead, radius=5.0e-4, name="bead")
    cs.add_surface(blk, thickness=2.0e-4, name="tissue")
    cs.finalize()
    w.simulate(1.0, 0.1)
    x = w.positions()
    xb = x[:, bead.particle_start]
    top = blk.surface_tris[np.all(v[blk.surface_tris - blk.particle_start, 2] > 0.0099, axis=1)]
    for env in range(2):
        # height of the deformed top surface below the bead (the top triangle containing its xy)
        heights = []
        for tri in top:
            a, bb, c = x[env, tri]
            m = np.array([[bb[0] - a[0], c[0] - a[0]], [bb[1] - a[1], c[1] - a[1]]])
            uv = np.linalg.solve(m, xb[env, :2] - a[:2])
            if uv.min() >= -1e-9 and uv.sum() <= 1 + 1e-9:
                p = a + uv[0] * (bb - a) + uv[1] * (c - a)
                heights.append(np.dot(xb[env] - p, np.cross(bb - a, c - a)) / np.linalg.norm(np.cross(bb - a, c - a)))
        assert heights and abs(abs(heights[0]) - 7.0e-4) < 2.0e-5, heights
    assert xb[0, 2] - xb[1, 2] == pytest.approx(0.004, abs=2.0e-5)
    assert np.allclose(cs.forces()[:, cs.pair("tissue", "bead")], 1.0e-4 * 9.81, rtol=0.01)
    assert list(cs.counts()[:, 0]) == [1, 1]


def _thrown_block(device, num_envs=2, steps=3, rod=False, **settings):
    """A free tet block (2 x 2 x 1 cm) thrown at 0.1 m/s into 9 beads (r = 0.5 mm, at rest, no gravity) 2 mm above its
    top face (env 1's block also slides sideways at 0.03 m/s), ``steps`` steps of 0.05 s at 10 substeps: the surface
    moves 0.5 mm per substep, 5 mm per step; with ``rod`` into a 9-node rod (r = 0.5 mm) across its top instead. The
    contact system's ``settings`` are set before it is finalized; returns ``(world, contact, block, beads)``."""
    v, t = box_tets((0.02, 0.02, 0.01), (2, 2, 1), origin=(-0.01, -0.01, 0.0))
    # off every edge and diagonal of the top face's 1 cm cells: no bead lies at the same distance from two triangles,
    # so the closest triangle does not depend on the order they are tested in (a bead over an edge would tie, and on
    # the GPU a tie's last-bit difference grows: it sits on a ridge)
    beads0 = np.array([[x, y, 0.012] for x in (-0.0063, 0.0017, 0.0058) for y in (-0.0049, 0.0031, 0.0072)])
    b = SceneBuilder(gravity=(0.0, 0.0, 0.0))
    blk = b.add_tet_mesh(v, t, density=1000.0, youngs_modulus=1e5, poisson_ratio=0.3)
    if rod:
        beads = b.add_rod(rod_polyline([[-0.0083, 0.0013, 0.012], [0.0077, 0.0013, 0.012]], 9), radius=5.0e-4,
                          youngs_modulus=1e6)
    else:
        beads = b.add_particles(beads0, mass=1.0e-4)
    w = b.finalize(num_envs=num_envs, device=device, substeps=10)
    qd = w.state.particle_qd.numpy()
    qd[:, blk.particles, 2] = 0.1
    if num_envs > 1:
        qd[1, blk.particles, 0] = 0.03
    w.state.particle_qd.assign(qd)
    cs = ContactSystem(w)
    cs.add_particle_group(beads, radius=5.0e-4, name="beads")
    cs.add_surface(blk, thickness=0.0, name="block")
    for name, value in settings.items():
        setattr(cs, name, value)
    cs.finalize()
    for _ in range(steps):
        w.step(0.05)
    return w, cs, blk, beads


@pytest.mark.parametrize("leaf_size", [1, 8])
def test_clustered_surface_query_matches_a_search_of_every_triangle(device, leaf_size):
    """The thrown block (``_thrown_block``): the clustered query (leaves of ``leaf_size`` triangles in super leaves,
    every env's boxes recomputed each sweep) gives exactly the trajectories of one leaf holding every triangle (each
    query then tests them all): it meets every triangle near the bead, however far the surface moved."""
    out = []
    for size in (10_000, leaf_size):
        w, cs, blk, beads = _thrown_block(device, surface_leaf_size=size)
        clusters = cs._surfaces[0]["clusters"]
        assert clusters.num_leaves == (1 if size == 10_000 else -(-len(blk.surface_tris) // leaf_size))
        out.append(w.positions())
    ref, x = out
    np.testing.assert_allclose(x, ref, rtol=0.0, atol=1.0e-9)
    assert x[:, beads.particle_start:, 2].min() > 0.02  # every bead was pushed up by the surface (it started at 12 mm)


@pytest.mark.parametrize("lanes", [1, 3, 8])
def test_fused_surface_bounds_kernel_gives_each_leafs_and_super_leafs_box(device, monkeypatch, lanes):
    """``ck.surface_bounds_kernel`` (a block per env) on random positions: each leaf's box is its vertices' minimum and
    maximum, each super leaf's the union of its leaves' (numpy), in each env, with fewer lanes than leaves (several
    passes), a lane per leaf-ish and one lane. On the CPU the lanes are Warp's cooperative fibers with real barriers
    (``wp.config.enable_cpu_blocks``). With a hold of resting tets (``hold.TetHold``) an env whose sweep skipped it
    (quiet one past the limit, nothing moving) keeps its boxes (left at zero here), and the separate launches do the
    same; an env at the limit (its sweep has just solved it) or flagged moving is computed."""
    monkeypatch.setattr(wp.config, "enable_cpu_blocks", True)
    from lapwarp.kernels import contact as ck

    n = 32
    ij = np.arange((n + 1) ** 2).reshape(n + 1, n + 1)
    quads = np.stack([ij[:-1, :-1], ij[1:, :-1], ij[1:, 1:], ij[:-1, 1:]], axis=-1).reshape(-1, 4)
    tris = np.concatenate([quads[:, [0, 1, 2]], quads[:, [0, 2, 3]]])
    xs, ys = np.meshgrid(np.arange(n + 1.0), np.arange(n + 1.0), indexing="ij")
    c = SurfaceClusters(tris, np.stack([xs.ravel(), ys.ravel(), np.zeros(xs.size)], axis=1), leaf_size=5)
    assert c.num_leaves % c.leaves_per_super != 0  # a short last super leaf
    envs, L, S = 5, c.num_leaves, c.num_supers
    q = np.random.default_rng(0).normal(size=(envs, (n + 1) ** 2, 3)).astype(np.float32)
    starts = wp.array(c.leaf_vert_start.astype(np.int32), device=device)
    verts = wp.array(c.leaf_verts.astype(np.int32), device=device)
    qa = wp.array(q, dtype=wp.vec3, device=device)
    # env 0: no hold; 1: held (skipped); 2: at the limit, just solved; 3: held but touched since; 4: held
    hold = TetHold()
    hold.quiet = wp.array([0, 3, 2, 3, 3], dtype=wp.int32, device=device)
    hold.moving = wp.array([0, 0, 0, 1, 0], dtype=wp.int32, device=device)
    hold.after, hold.speed2 = 2, 1.0
    computed = [0, 2, 3]
    out = [wp.zeros((envs, k), dtype=wp.vec3, device=device) for k in (L, L, S, S)]
    wp.launch(ck.surface_bounds_kernel(L), (envs, lanes), [starts, verts, c.leaves_per_super, qa, hold], out,
              block_dim=lanes, device=device)
    separate = [wp.zeros((envs, k), dtype=wp.vec3, device=device) for k in (L, L, S, S)]
    wp.launch(ck.surface_leaf_bounds, (envs, L), [starts, verts, qa, hold], separate[:2], device=device)
    wp.launch(ck.surface_super_bounds, (envs, S), [separate[0], separate[1], c.leaves_per_super, hold], separate[2:],
              device=device)
    for a, b in zip(out, separate, strict=True):
        np.testing.assert_array_equal(a.numpy(), b.numpy())
    leaf_lo, leaf_hi, super_lo, super_hi = (a.numpy() for a in out)
    for held in (1, 4):
        assert not any(a[held].any() for a in (leaf_lo, leaf_hi, super_lo, super_hi))
    for leaf in range(L):
        v = q[computed][:, c.leaf_verts[c.leaf_vert_start[leaf]:c.leaf_vert_start[leaf + 1]]]
        np.testing.assert_array_equal(leaf_lo[computed, leaf], v.min(axis=1))
        np.testing.assert_array_equal(leaf_hi[computed, leaf], v.max(axis=1))
    for s in range(S):
        leaves = slice(s * c.leaves_per_super, min((s + 1) * c.leaves_per_super, L))
        np.testing.assert_array_equal(super_lo[computed, s], leaf_lo[computed][:, leaves].min(axis=1))
        np.testing.assert_array_equal(super_hi[computed, s], leaf_hi[computed][:, leaves].max(axis=1))


def test_fused_surface_bounds_step_as_the_two_launches(device):
    """``ContactSystem.surface_bounds`` "fused" against "separate": the thrown block (leaves of one triangle) takes
    exactly the same trajectories and leaves exactly the same boxes; a bad setting or lane count is a clear error when
    the step is recorded."""
    out = []
    for bounds in ("separate", "fused"):
        w, cs, blk, beads = _thrown_block(device, surface_leaf_size=1, surface_bounds=bounds)
        assert cs.surface_bounds == bounds
        sf = cs._surfaces[0]
        out.append([w.positions()] + [sf[k].numpy() for k in ("leaf_lo", "leaf_hi", "super_lo", "super_hi")])
    for ref, x in zip(*out, strict=True):
        np.testing.assert_array_equal(x, ref)
    assert out[0][0][:, beads.particle_start:, 2].min() > 0.02  # the surface pushed every bead
    for setting, value, match in (("surface_bounds", "tiled", "surface_bounds must be"),
                                  ("surface_bounds_lanes", 0, "surface_bounds_lanes"),
                                  ("surface_bounds_lanes", 2.0, "surface_bounds_lanes")):
        cs.surface_bounds, cs.surface_bounds_lanes = "fused", 64
        setattr(cs, setting, value)
        with pytest.raises(ValueError, match=match):
            w.step(0.05)


def test_deferred_surface_deltas_keep_the_positions(device):
    """``ContactSystem.defer_surface_deltas``: a surface's averaged corrections applied by the next substep's
    prediction launch instead of their own. The block thrown into a rod (particles and rod segments predicted in one
    launch): the same positions bit for bit, with the surface pushing the rod (it ends above its start), and one
    launch fewer per substep but the last of each step; thrown into beads (no rods: the prediction is another kernel,
    so the deferred launch runs before it as it was) the same positions and launches. A non-bool setting is refused
    when the step is recorded."""
    rods = [_thrown_block(device, rod=True, defer_surface_deltas=defer) for defer in (False, True)]
    (w_off, _, _, rod), (w_on, *_) = rods
    np.testing.assert_array_equal(w_on.positions(), w_off.positions())
    assert w_on.positions()[:, rod.particles, 2].min() > 0.013  # pushed up from 12 mm by the surface
    assert len(w_off._cmds) - len(w_on._cmds) == w_on.substeps_for(0.05) - 1 == 9
    blocks = [_thrown_block(device, defer_surface_deltas=defer) for defer in (False, True)]
    np.testing.assert_array_equal(blocks[1][0].positions(), blocks[0][0].positions())
    assert len(blocks[1][0]._cmds) == len(blocks[0][0]._cmds)
    w, cs = blocks[1][:2]
    cs.defer_surface_deltas = "yes"
    with pytest.raises(ValueError, match="defer_surface_deltas must be a bool"):
        w.step(0.05)


def _rods_on_peg(device, report_forces=True, seconds=0.3, method="auto"):
    """A closed rod (a torus) and a straight one dropped over a peg cylinder on the floor (particles against a plane
    and a cylinder, rod segments, rod-rod pairs by ``method``), ``seconds`` simulated in steps of 0.1 s; returns
    ``(world, contact, torus, bar)``."""
    b = SceneBuilder()
    torus = b.add_rod(rod_circle(0.014, 24, center=(0, 0, 0.03)), radius=0.003, youngs_modulus=1e5, closed=True,
                      damping=1.0)
    bar = b.add_rod(rod_polyline([[-0.03, 0.005, 0.045], [0.03, 0.005, 0.045]], 13), radius=0.003,
                    youngs_modulus=1e5, damping=1.0)
    w = b.finalize(num_envs=1, device=device, substeps=20)
    cs = ContactSystem(w)
    cs.add_particle_group(torus, radius=0.003, segments=True, name="torus")
    cs.add_particle_group(bar, radius=0.003, segments=True, name="bar")
    cs.add_plane(name="floor")
    cs.add_cylinder(0.005, 0.04, transform=(0, 0, 0.04), name="peg")
    cs.add_particle_contact([(torus, 0.003), (bar, 0.003)], skip_links=2, name="rods", method=method)
    cs.report_forces = report_forces
    cs.finalize()
    w.simulate(seconds, 0.1)
    return w, cs, torus, bar


def test_contact_forces_off_keep_the_trajectories_and_counts(device):
    """``ContactSystem.report_forces`` off (the kernels skip their atomic adds into ``report_force``): rods on a peg
    and the floor (particle, segment and pair contact), a block thrown into beads (surface contact) and a capsule
    pushed through a cloth (triangle contact) move bit for bit as with forces reported, with the same contact counts;
    the forces summed with it on are positive, and ``forces()`` with it off is an error, not zeros. A non-bool setting
    is refused when the step is recorded."""
    scenes = (lambda on: _rods_on_peg(device, report_forces=on),
              lambda on: _thrown_block(device, num_envs=1, steps=1, report_forces=on))
    for scene in scenes:
        (w_on, cs_on, *_), (w_off, cs_off, *_) = scene(True), scene(False)
        np.testing.assert_array_equal(w_off.positions(), w_on.positions())
        np.testing.assert_array_equal(cs_off.counts(), cs_on.counts())
        assert cs_on.forces().max() > 0.0
        with pytest.raises(RuntimeError, match="report_forces"):
            cs_off.forces()
    cloth = []
    for on in (True, False):
        _push_capsule(device, 0.1, kind="cloth", positions=cloth, report_forces=on)
    np.testing.assert_array_equal(cloth[1], cloth[0])
    cs_off.report_forces = 1
    with pytest.raises(ValueError, match="report_forces must be a bool"):
        w_off.step(0.05)


def test_surface_clusters_are_compact_and_cover_every_triangle():
    """A 32 x 32 grid of unit squares (2,048 triangles): the clustered order is a permutation, each leaf of 8
    triangles lies within a 2 x 2 block of squares (the median splits halve the grid: extent 2 per axis), each
    super leaf's leaves are neighbours, and each leaf's vertex list is its triangles' distinct vertices."""
    n = 32
    ij = np.arange((n + 1) ** 2).reshape(n + 1, n + 1)
    quads = np.stack([ij[:-1, :-1], ij[1:, :-1], ij[1:, 1:], ij[:-1, 1:]], axis=-1).reshape(-1, 4)
    tris = np.concatenate([quads[:, [0, 1, 2]], quads[:, [0, 2, 3]]])
    xs, ys = np.meshgrid(np.arange(n + 1.0), np.arange(n + 1.0), indexing="ij")
    points = np.stack([xs.ravel(), ys.ravel(), np.zeros(xs.size)], axis=1)
    c = SurfaceClusters(tris, points)
    assert np.array_equal(np.sort(c.order), np.arange(len(tris)))
    assert (c.num_leaves, c.leaves_per_super, c.num_supers) == (256, 16, 16)
    ordered = tris[c.order]
    for leaf in range(c.num_leaves):
        verts = np.unique(ordered[leaf * 8:(leaf + 1) * 8])
        assert np.array_equal(c.leaf_verts[c.leaf_vert_start[leaf]:c.leaf_vert_start[leaf + 1]], verts)
        extent = points[verts].max(axis=0) - points[verts].min(axis=0)
        assert extent.max() <= 2.0
    for s in range(c.num_supers):
        verts = np.unique(ordered[s * 128:(s + 1) * 128])
        assert np.ptp(points[verts], axis=0).max() <= 8.0  # 16 leaves of 2 x 2: an 8 x 8 block
    with pytest.raises(ValueError, match="leaf_size"):
        SurfaceClusters(tris, points, leaf_size=0)


def _bead_over_surface(device, **settings):
    """A bead above a free tet block's surface, one env, the contact system's ``settings`` set before finalize."""
    v, t = box_tets((0.02, 0.02, 0.01), (2, 2, 1), origin=(-0.01, -0.01, 0.0))
    b = SceneBuilder()
    blk = b.add_tet_mesh(v, t, density=1000.0, youngs_modulus=1e5, poisson_ratio=0.3)
    bead = b.add_particles(np.array([[0.0, 0.0, 0.02]]), mass=1.0e-4)
    w = b.finalize(num_envs=1, device=device, substeps=2)
    cs = ContactSystem(w)
    cs.add_particle_group(bead, radius=5.0e-4)
    cs.add_surface(blk)
    for name, value in settings.items():
        setattr(cs, name, value)
    cs.finalize()
    return w


@pytest.mark.parametrize("size", [0, -8, 1.5, True])
def test_bad_surface_leaf_size_is_rejected(device, size):
    """``surface_leaf_size`` must be an int >= 1: anything else is a clear error at finalize."""
    with pytest.raises(ValueError, match="leaf_size"):
        _bead_over_surface(device, surface_leaf_size=size)


def test_cell_list_matches_brute_force(device):
    """One step of 300 random particles (r = 1 mm, many overlapping) per env in a 2 cm box: the per-env cell list
    finds exactly the pairs of the brute force (same contact count, positions equal to 1e-6 m; the order of the
    float sums differs), env 1 holds a different cloud (envs never mix)."""
    rng = np.random.default_rng(3)
    out = []
    for method in ("brute", "grid"):
        b = SceneBuilder(gravity=(0.0, 0.0, 0.0))
        p = b.add_particles(rng.uniform(-0.01, 0.01, (300, 3)), mass=1e-3)
        w = b.finalize(num_envs=2, device=device, substeps=2)
        q = w.state.particle_q.numpy()
        q[1] = np.random.default_rng(4).uniform(-0.01, 0.01, (300, 3))
        w.state.particle_q.assign(q)
        rng = np.random.default_rng(3)
        cs = ContactSystem(w)
        cs.add_particle_contact([(p, 0.001)], name="cloud", method=method)
        cs.finalize()
        w.step(0.01)
        out.append((w.positions(), cs.counts()[:, 0]))
    assert out[0][1].min() > 100 and np.array_equal(out[0][1], out[1][1])
    assert np.abs(out[0][0] - out[1][0]).max() < 1.0e-6


def test_tool_at_a_pinned_corner_does_not_throw_the_sheet(device):
    """A capsule (1 mm) pressing 0.45 mm into a 90 N/m cloth 0.05 mm from its pinned corner: the contact point sits
    on triangles whose barycentric weights are ~(0.99, 0.005, 0.005), and the uncapped XPBD lever moved the two free
    nodes ~1 / 0.005 x the penetration per projection (measured: 45.9 mm in one 25 ms step, 31.7 m/s; in
    PrecisionCutting the scissors at the fixed corners tripped the 50 m/s stability check). With the lever capped
    (``contact.node_share``) no node moves faster than 2 m/s (measured 0.19 m/s) or further than 15 mm (5.6 mm: the
    sheet turns about its pin to clear the tool, as it must)."""
    b = SceneBuilder(gravity=(0.0, 0.0, 0.0))
    v, tri = cloth_grid(3, 3, 0.02, 0.02, plane="xy", origin=(-0.01, -0.01, 0.0))
    obj = b.add_cloth(v, tri, areal_density=0.2, stretch_stiffness=90.0, bend_stiffness=1e-7, fixed=[0])
    off = 5e-5
    body = b.add_body("tool", pose=(-0.01 + off, -0.01 + off, 8e-4, *_quat_axis_angle((1, 0, 0), math.pi / 2)))
    w = b.finalize(num_envs=1, device=device, substeps=8)
    cs = ContactSystem(w)
    cs.add_particle_group(obj, radius=2.5e-4, triangles=True)
    cs.add_capsule(1e-3, 1e-4, body=body)
    cs.finalize()
    x0 = w.positions(obj)[0].copy()
    w.step(0.025)
    speed = np.linalg.norm(w.state.particle_qd.numpy()[0], axis=1)
    assert speed.max() < 2.0
    assert np.abs(w.positions(obj)[0] - x0).max() < 0.015
    assert np.allclose(w.positions(obj)[0][0], x0[0])  # the pinned corner stays



def test_fused_segment_colours_match_a_launch_per_colour(device):
    """``ContactSystem.fuse_segment_colors`` (every colour of rod-segment contact in one launch, a block per env,
    barriers between colours; the default) projects the same segments in the same order as a launch per colour: the
    rod the capsule pushes at 0.1 m/s (segment contact needed: node contact alone lets the tool through) ends in the
    same place, bit for bit on the CPU, within float32 rounding on the GPU; and the tool still does not tunnel."""
    x = {}
    for fused in (True, False):
        out = []
        gap, ahead = _push_capsule(device, 0.1, fuse_segments=fused, positions=out)
        assert gap > -5.0e-5 and ahead
        x[fused] = out[0]
    assert np.abs(x[True][:, 2] - 0.005).max() > 1.0e-3  # the tool carried the rod: contacts were projected
    if device == "cpu":
        np.testing.assert_array_equal(x[True], x[False])
    else:
        np.testing.assert_allclose(x[True], x[False], atol=1e-6)


def test_particle_kernel_without_meshes_matches_the_full_one(device, monkeypatch):
    """The particle contact launch without the mesh SDF query (``particle_collision_kernel(False)``, what a scene
    without mesh shapes runs) against the variant that takes every kind, forced on the same scene: the same positions
    (bit for bit on the CPU; within float32 rounding on a GPU, where the two kernels compile separately) after
    particles dropped on every primitive came to rest, and the scene did pick the reduced variant."""
    from lapwarp import contact as contact_module
    from lapwarp.kernels import contact as ck

    used = []
    real = ck.particle_collision_kernel

    def spy(meshes, force=None):
        used.append(meshes)
        return real(meshes if force is None else force)

    out = []
    for force in (None, True):
        monkeypatch.setattr(contact_module.ck, "particle_collision_kernel", lambda m, f=force: spy(m, f))
        b = SceneBuilder()
        pts = np.array([[0.0, 0.0, 0.02], [0.2, 0.003, 0.05], [0.4, 0.002, 0.05], [0.6, 0.001, 0.05],
                        [0.8, 0.004, 0.05]])
        p = b.add_particles(pts, mass=0.01, damping=2.0)
        w = b.finalize(num_envs=2, device=device, substeps=10)
        cs = ContactSystem(w)
        cs.add_particle_group(p, radius=0.002)
        cs.add_plane(thickness=0.001)
        cs.add_sphere(0.01, transform=(0.2, 0.0, 0.0), thickness=0.0005)
        cs.add_box((0.01, 0.01, 0.01), transform=(0.4, 0.0, 0.0), thickness=0.0005)
        cs.add_cylinder(0.01, 0.01, transform=(0.6, 0.0, 0.0), thickness=0.0005)
        cs.add_capsule(0.01, 0.02, transform=(0.8, 0.0, 0.0, *_quat_axis_angle((1, 0, 0), math.pi / 2)),
                       thickness=0.0005)
        cs.finalize()
        w.simulate(0.5, 0.1)
        out.append(w.positions())
    assert used and not any(used)  # no mesh shape: the scene asked for the variant without meshes
    assert np.abs(out[0] - np.array(pts)).max() > 1e-3  # they fell
    if device == "cpu":
        np.testing.assert_array_equal(out[0], out[1])
    else:
        np.testing.assert_allclose(out[0], out[1], atol=1e-6)


def test_shapes_on_one_body_are_culled_as_a_group_with_the_same_contacts(device):
    """A 6 x 6 sheet of free particles (r = 2 mm) and a rod of 4 nodes 15 mm apart (its segments collide: its two
    middle nodes straddle a 12 mm sphere, which only their segment meets) dropped onto a ring of six 6 mm spheres
    on one tilted body: culling the six as one group (their bounding sphere, 21.2 mm about the ring's centre, then
    each shape's) gives exactly the trajectories and contact counts of the same spheres each on a body of its own
    (no group), and particles and rod landed on the ring (a group sphere too small drops them through)."""
    offsets = [(0.015 * math.cos(a), 0.015 * math.sin(a), 0.0) for a in np.linspace(0.0, 2 * math.pi, 7)[:-1]]
    xs, ys = np.meshgrid(np.linspace(-0.02, 0.02, 6), np.linspace(-0.02, 0.02, 6), indexing="ij")
    sheet = np.stack([xs.ravel(), ys.ravel(), np.full(xs.size, 0.02)], axis=1)
    pose = (0.001, -0.002, 0.0, *_quat_axis_angle((1, 1, 0), 0.3))
    runs = []
    # grouped; each sphere on a body of its own; on one body with the groups switched off (cull_groups)
    for grouped, one_body in ((True, True), (False, False), (False, True)):
        b = SceneBuilder()
        b.add_particles(sheet, mass=1.0e-3)
        rod = b.add_rod(rod_polyline([[0.015, -0.0225, 0.03], [0.015, 0.0225, 0.03]], 4), radius=5e-4,
                        youngs_modulus=1e6)
        bodies = [b.add_body("ring", pose=pose)] * len(offsets) if one_body else \
            [b.add_body(f"ring{k}", pose=pose) for k in range(len(offsets))]
        w = b.finalize(num_envs=2, device=device, substeps=10)
        cs = ContactSystem(w)
        cs.cull_groups = grouped
        cs.add_particle_group(np.arange(len(sheet)), radius=0.002, name="sheet")
        cs.add_particle_group(rod, radius=5e-4, segments=True, name="rod")
        for k, (body, off) in enumerate(zip(bodies, offsets, strict=True)):
            cs.add_sphere(0.006, body=body, transform=off, thickness=2.0e-4, name=f"ball{k}")
        cs.finalize()
        starts = cs._shape_poses.group_start.numpy()
        assert list(starts) == ([0, 6] if grouped else list(range(7)))
        for _ in range(4):
            w.step(0.05)
        runs.append((w.positions(), cs.counts()))
    (x, counts), (x_ref, counts_ref), (x_off, counts_off) = runs
    assert np.array_equal(x, x_ref) and np.array_equal(counts, counts_ref)
    assert np.array_equal(x_off, x_ref) and np.array_equal(counts_off, counts_ref)
    assert counts.sum() > 0 and x[:, :len(sheet), 2].max() > 0.005  # some rest on the ring (the rest fell through)
    # the rod's middle nodes hang on the sphere between them (without its segment they fall through the ring)
    assert x[:, rod.particle_start + 1:rod.particle_start + 3, 2].min() > 0.0


def test_shape_code_sweep_culls_to_each_tool_in_precision_cutting(device):
    """PrecisionCutting's scissors: a 147 mm shaft crosses the sheet at a slant, so the one box around every tool
    spans a strip of the cloth. Each tool's own box along its axis (``"shape_codes"``) passes a small part of the
    triangles that box does (counted here in numpy from the sweep's boxes: 160 against 21 after 25 expert steps,
    CPU), and 60 expert steps give the same cloth and cuts as the union-box sweep (bit for bit on the CPU)."""
    import lapwarp
    from lapwarp.experts import make_expert

    out = {}
    for sweep in ("outcodes", "shape_codes"):
        env = lapwarp.make("PrecisionCutting", num_envs=2, device=device, seed=3)
        env.contact.triangle_sweep = sweep
        env.contact.pose_per_step = False  # the boxes read below are the per-sweep ones (the same values either way)
        expert = make_expert(env)
        env.reset()
        for step in range(60):
            env.step(expert())
            if step == 24 and sweep == "shape_codes":
                ax, tri = env.contact._tool_axes, env.contact.tri_nodes.numpy()
                x = env.world.state.particle_q.numpy()[0][tri]  # (triangles, 3 corners, 3)
                lo, hi = ax.lo.numpy()[0], ax.hi.numpy()[0]
                union = ~((x.max(1) < lo).any(1) | (x.min(1) > hi).any(1))
                own = np.zeros(len(tri), dtype=bool)
                for s in range(ax.box_centre.shape[1]):
                    local = (x - ax.box_centre.numpy()[0, s]) @ ax.box_frame.numpy()[0, s].T
                    half = ax.box_half.numpy()[0, s]
                    own |= ~((local.max(1) < -half).any(1) | (local.min(1) > half).any(1))
                assert union.sum() > 50 and 3 * own.sum() < union.sum()
        out[sweep] = (env.world.state.particle_q.numpy(), env.world.state.tri_active.numpy())
        env.close()
    assert (out["outcodes"][1] == 0).any()  # the scissors cut: the sweep met the masks
    for a, b in zip(out["shape_codes"], out["outcodes"], strict=True):
        if device == "cpu":
            np.testing.assert_array_equal(a, b)
        else:
            np.testing.assert_allclose(a, b, atol=1e-6)


def test_shape_code_sweep_refuses_more_shapes_than_its_bits(device, monkeypatch):
    from lapwarp.kernels import contact as ck

    monkeypatch.setattr(ck, "SHAPE_CODE_MAX_SHAPES", 0)
    with pytest.raises(ValueError, match="6 bits per shape .* more than 0; use 'outcodes'"):
        _push_capsule(device, 0.1, kind="cloth", triangle_sweep="shape_codes")


@pytest.mark.parametrize("iterations", [1, 2])
def test_shapes_posed_once_per_step_give_the_same_contacts(device, iterations):
    """``ContactSystem.pose_per_step`` (every substep's shape poses in one launch at a step's first sweep) against a
    pose launch per sweep: a capsule and a sphere on a body that moves (and turns) during each step sweep through a
    rod (segment contact) and loose particles lying on a plane; the same positions, contact counts and reported
    forces (bit for bit on the CPU), at 1 and 2 sweeps per substep, with substeps x sweeps - 1 launches fewer per
    step."""
    runs = []
    for once in (False, True):
        b = SceneBuilder()
        rod = b.add_rod(rod_polyline([[-0.03, 0.0, 0.002], [0.03, 0.0, 0.002]], 13), radius=5e-4, youngs_modulus=1e6)
        loose = b.add_particles(np.array([[0.0, 0.01, 0.002], [0.005, -0.01, 0.002], [-0.01, 0.004, 0.002]]),
                                mass=1.0e-3)
        body = b.add_body("tool", pose=(-0.04, 0.0, 0.004, *_quat_axis_angle((1, 0, 0), math.pi / 2)))
        w = b.finalize(num_envs=2, device=device, substeps=6, iterations=iterations)
        cs = ContactSystem(w)
        cs.add_particle_group(rod, radius=5e-4, segments=True, name="rod")
        cs.add_particle_group(loose, radius=1e-3, name="loose")
        cs.add_plane(thickness=5e-4)
        cs.add_capsule(1e-3, 0.015, body=body, name="shaft")
        cs.add_sphere(2e-3, body=body, transform=(0.0, 0.0, 0.012), name="tip")
        cs.finalize()
        cs.pose_per_step = once
        pose = w.state.body_q.numpy()
        for k in range(8):
            pose[:, 0, 0] = -0.04 + 0.01 * (k + 1)  # 10 mm per step along x, through the rod's middle
            pose[1, 0, 3:] = _quat_axis_angle((1.0, 0.2, 0.0), math.pi / 2 + 0.05 * (k + 1))  # env 1 also turns
            w.state.body_q.assign(pose)
            w.step(0.05)
        launches = len(w._cmds)
        runs.append((w.positions(), cs.counts(), cs.report_force.numpy(), launches))
    (x0, c0, f0, n0), (x1, c1, f1, n1) = runs
    assert n0 - n1 == 6 * iterations - 1
    assert np.abs(x0[:, rod.particles, 0]).max() > 1e-3  # the tool carried the rod along x: contacts were projected
    if device == "cpu":
        np.testing.assert_array_equal(x0, x1)
        np.testing.assert_array_equal(f0, f1)
    else:
        np.testing.assert_allclose(x0, x1, atol=1e-6)
    np.testing.assert_array_equal(c0, c1)


@pytest.mark.parametrize("sweep_kind", ["fused", "outcodes", "shape_codes"])
def test_tool_axes_formed_once_per_step_give_the_same_contacts(device, sweep_kind):
    """``ContactSystem.pose_per_step`` where the system has triangles: every substep's shape poses, tool axes, tool
    boxes and (for the shape-code sweep) per-tool boxes formed by one launch at a step's first sweep
    (``pose_shapes_and_tools_substeps``) against the per-sweep launch: the capsule pushed through a cloth ends it in
    the same place (bit for bit on the CPU) with the same contact counts, in each triangle sweep."""
    runs = []
    for once in (False, True):
        out = []
        gap, ahead = _push_capsule(device, 0.1, kind="cloth", triangle_sweep=sweep_kind, positions=out,
                                   pose_per_step=once)
        assert gap > -1.0e-4 and ahead
        runs.append(out[0])
    assert np.abs(runs[0][:, 2] - 0.005).max() > 1.0e-3  # the tool carried the cloth
    if device == "cpu":
        np.testing.assert_array_equal(runs[0], runs[1])
    else:
        np.testing.assert_allclose(runs[0], runs[1], atol=1e-6)


def test_pose_per_step_without_shapes(device):
    """A system with triangles and particles but no shape (nothing to pose) steps with ``pose_per_step`` as without:
    the cloth falls freely, the same positions."""
    out = []
    for once in (False, True):
        b = SceneBuilder()
        v, tri = cloth_grid(4, 4, 0.01, 0.01, plane="xy", origin=(0.0, 0.0, 0.05))
        cloth = b.add_cloth(v, tri, areal_density=0.2, stretch_stiffness=100.0, bend_stiffness=0.0)
        w = b.finalize(num_envs=1, device=device, substeps=3)
        cs = ContactSystem(w)
        cs.add_particle_group(cloth, radius=2.5e-4, triangles=True)
        cs.finalize()
        cs.pose_per_step = once
        w.simulate(0.1, 0.05)
        out.append(w.positions())
    assert out[0][0, :, 2].max() < 0.05  # it fell
    np.testing.assert_array_equal(out[0], out[1])


def _launches_of(world, name: str) -> int:
    """How many of the recorded step's launches run a kernel whose key holds ``name``."""
    kernels = [getattr(getattr(cmd, "__self__", None), "kernel", None) for cmd in world._cmds]
    return sum(1 for k in kernels if k is not None and name in k.key)


def _fused_contact_launches(world) -> int:
    """How many of the recorded step's launches run a substep's particle contact inside the next rod launch."""
    return _launches_of(world, "contact_predict_and_solve_rods_fused")


@pytest.mark.parametrize("held", ["pinned", "attached"])
def test_contact_in_the_rod_launch_matches_its_own_launch(device, held):
    """``World.contact_in_rod_launch``: a substep's closing attachment pass and particle contact, its last two
    launches, run at the start of the next substep's fused rod launch (``xpbd.contact_rods_fused_kernel``) instead of
    in their own. A rod held at one end (pinned, or by a stiff attachment to a fixed point: then the attachment pass
    is deferred too) swings down onto a sphere and the floor (friction 0.5, forces reported): positions, velocities,
    contact counts and forces match the separate launches (bit for bit on the CPU, to float32 round-off on a GPU); the
    step recorded the fused launch for every substep but the first (the last substep's launches stay their own, before
    the velocity update, and so does the first substep's attachment pass, which the step's shape pose launch
    follows); the rod did touch both shapes. A scene with a mesh shape keeps the separate launch; a
    non-bool setting is refused when the step is recorded."""
    substeps = 6
    out = []
    for fused in (True, False):
        b = SceneBuilder()
        rod = b.add_rod(rod_polyline([[0.0, 0.0, 0.03], [0.1, 0.0, 0.03]], 11), radius=1e-3, youngs_modulus=1e6,
                        damping=0.3, fixed=[0] if held == "pinned" else [])
        if held == "attached":
            b.add_attachment(0, compliance=1e-8)
        world = b.finalize(2, device, substeps=substeps)
        cs = ContactSystem(world)
        cs.add_particle_group(rod, radius=1e-3)
        cs.add_plane(thickness=0.0, mu_static=0.5)
        cs.add_sphere(0.01, transform=(0.06, 0.0, 0.0), thickness=0.0, mu_static=0.5)
        cs.finalize()
        world.contact_in_rod_launch = fused
        assert world._contact_in_rod_launch() == fused
        world.simulate(0.3, 0.02)
        assert _fused_contact_launches(world) == (substeps - 1 if fused else 0)
        # the first substep's attachment pass keeps its launch too: the step's shape pose launch comes after it
        assert _launches_of(world, "solve_attachment") == (0 if held == "pinned" else 2 if fused else substeps)
        st = world.state
        out.append(([a.numpy() for a in (st.particle_q, st.particle_qd, st.segment_q, st.segment_qd)],
                    cs.counts(), cs.forces()))
    (arrays, counts, forces), (arrays_own, counts_own, forces_own) = out
    assert counts.min() > 0 and forces.min() > 0.0  # every env touches the floor and the sphere
    assert np.abs(arrays[0][:, 0] - [0.0, 0.0, 0.03]).max() < 1e-4  # the held end stays
    np.testing.assert_array_equal(counts, counts_own)
    for a, b_ in zip((*arrays, forces), (*arrays_own, forces_own), strict=True):
        if device == "cpu":
            np.testing.assert_array_equal(a, b_)
        else:
            np.testing.assert_allclose(a, b_, rtol=1e-5, atol=1e-5 * max(np.abs(b_).max(), 1e-9))
    b = SceneBuilder()
    rod = b.add_rod(rod_polyline([[0.0, 0.0, 0.03], [0.1, 0.0, 0.03]], 11), radius=1e-3, youngs_modulus=1e6,
                    fixed=[0])
    world = b.finalize(1, device, substeps=substeps)
    cs = ContactSystem(world)
    cs.add_particle_group(rod, radius=1e-3)
    box = trimesh.creation.box((0.02, 0.02, 0.02))
    cs.add_mesh(box.vertices, box.faces, transform=(0.06, 0.0, 0.0))
    cs.finalize()
    world.step(0.02)
    assert world._contact_in_rod_launch() and _fused_contact_launches(world) == 0
    world.contact_in_rod_launch = "on"  # (1 would equal the recorded True and not re-record)
    with pytest.raises(ValueError, match="contact_in_rod_launch must be a bool"):
        world.step(0.02)
