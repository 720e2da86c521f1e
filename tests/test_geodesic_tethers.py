"""Geodesic tethers (``SceneBuilder.add_cloth(tethers=True)``, ``lapwarp.kernels.geodesic``): distances against closed
forms on a flat sheet, around a cut, from a grasp that appears and goes; a piece cut off every anchor falls; a sheet
held at points stretches less with them."""

from __future__ import annotations

import numpy as np
import warp as wp

from lapwarp.assets import cloth_grid
from lapwarp.builder import SceneBuilder
from lapwarp.cutting import CuttingSystem

DT = 0.1


def _fields(world, env=0):
    """(distances, sources, groups): each ``(GROUPS, n)``, one row per anchor group (``geodesic.GROUPS``), and the
    env's number of anchor groups."""
    s = world.state
    n = s.geo_anchor.shape[1]
    d = s.geo_dist.numpy()[env].reshape(-1, n)
    src = s.geo_source.numpy()[env].reshape(-1, n)
    return d, src, int(s.geo_status.numpy()[env, 1])


def _sheet(device, nx=11, size=0.05, fixed=(0,), num_envs=1, **kw):
    v, t = cloth_grid(nx, nx, size, size, plane="xy")
    b = SceneBuilder()
    obj = b.add_cloth(v, t, areal_density=0.2, stretch_stiffness=1e3, bend_stiffness=1e-6, damping=1.0,
                      fixed=np.asarray(fixed), tethers=True, **kw)
    world = b.finalize(num_envs, device, substeps=10, attachment_capacity=1)
    return world, obj, v, t


def test_distances_on_a_flat_sheet_are_euclidean(device):
    # one pinned corner of a convex sheet: every geodesic is the straight rest distance to it (the eikonal update
    # with a virtual source is exact for a point source on a flat mesh; a graph shortest path would be up to 8 % long)
    world, obj, v, _ = _sheet(device)
    world.step(DT)
    s = world.state
    assert s.geo_status.numpy()[0, 0] == 0  # converged within the first step
    d, src, groups = _fields(world)
    assert groups == 1 and np.all(src[1:] == -1)
    d, src = d[0], src[0]
    assert np.all(src == 0)
    exact = np.linalg.norm(v - v[0], axis=1)
    np.testing.assert_allclose(d, exact, rtol=1e-4, atol=1e-7)


def test_distances_go_around_a_cut(device):
    # a slit (one band of quads, x in [20, 25] mm, y up to 30 mm) between the pinned corner (0, 0) and a point
    # behind it: the geodesic wraps around the slit's top corners A and B, |A| + |AB| + |B p|. Measured 2.9 % long:
    # past a corner the update's virtual source is only approximate, and it errs long (a slack tether, never a tight
    # one); bound: never shorter, at most 5 % longer
    nx, size = 11, 0.05
    world, obj, v, t = _sheet(device, nx=nx, size=size, cuttable=True)
    world.step(DT)
    h = size / (nx - 1)
    cen = v[t].mean(axis=1)
    slit = (cen[:, 0] > 4 * h) & (cen[:, 0] < 5 * h) & (cen[:, 1] < 6 * h)
    act = world.state.tri_active.numpy()
    act[0, slit] = 0
    world.state.tri_active.assign(act)
    world.step(DT)  # the changed mask restarts the sweep; 2 rounds per step may not finish around a cut
    world.step(DT)
    s = world.state
    assert s.geo_status.numpy()[0, 0] == 0
    p = 1 * nx + 8  # (40, 5) mm, behind the slit
    a, b = np.array([4 * h, 6 * h, 0.0]), np.array([5 * h, 6 * h, 0.0])
    ref = np.linalg.norm(a - v[0]) + h + np.linalg.norm(v[p] - b)
    d = _fields(world)[0][0, p]
    assert ref * (1.0 - 1e-4) <= d < 1.05 * ref, (d, ref)
    assert d > 1.3 * np.linalg.norm(v[p] - v[0])
    # in front of the slit nothing changed
    q = 3 * nx + 2
    np.testing.assert_allclose(_fields(world)[0][0, q], np.linalg.norm(v[q] - v[0]), rtol=1e-4)


def test_grasp_makes_an_anchor_and_release_removes_it(device):
    world, obj, v, _ = _sheet(device, fixed=(0,))
    world.step(DT)
    s = world.state
    far = len(v) - 1  # the opposite corner
    q = world.positions(obj)[0]
    s.attach_particle.assign(np.array([[far]], np.int32))
    s.attach_body.assign(np.array([[-1]], np.int32))
    s.attach_offset.assign(q[far][None, None].astype(np.float32))
    s.attach_compliance.assign(np.array([[1e-8]], np.float32))
    world.step(DT)
    d, src, groups = _fields(world)
    # two anchor groups (the pinned corner 0 and the grasped corner, numbered by their smallest particle): every
    # particle is tied to both, at its rest distance from each
    assert groups == 2
    assert src[1, far] == far and d[1, far] == 0.0 and src[0, far] == 0
    assert np.all(src[0] == 0) and np.all(src[1] == far)
    d0, d1 = np.linalg.norm(v - v[0], axis=1), np.linalg.norm(v - v[far], axis=1)
    np.testing.assert_allclose(d[0], d0, rtol=1e-4, atol=1e-7)
    np.testing.assert_allclose(d[1], d1, rtol=1e-4, atol=1e-7)
    s.attach_particle.assign(np.array([[-1]], np.int32))
    world.step(DT)
    d, src, groups = _fields(world)
    assert groups == 1
    np.testing.assert_array_equal(src[0], 0)
    np.testing.assert_array_equal(src[1:], -1)


def test_piece_cut_off_every_anchor_has_no_tether_and_falls(device):
    # a hanging sheet cut across by scissors: the lower piece loses its tethers and falls (~0.4 m in 0.3 s), the
    # uncut env keeps hanging
    b = SceneBuilder()
    nx, h = 13, 0.005
    v, t = cloth_grid(nx, nx, (nx - 1) * h, (nx - 1) * h, plane="xz")
    top = np.nonzero(v[:, 2] > v[:, 2].max() - 1e-9)[0]
    cloth = b.add_cloth(v, t, areal_density=0.2, stretch_stiffness=1e3, bend_stiffness=1e-6, damping=1.0,
                        fixed=top, cuttable=True, tethers=True)
    world = b.finalize(2, device, substeps=10)
    world.step(DT)
    z0 = 5.5 * h
    cut = CuttingSystem(world, carving_distance=0.2e-3, num_tools=1, tool_radius=0.5 * h - 0.2e-3)
    cut.add_object(cloth)
    cut.finalize()
    cut.hook_activation(wp.array([1.0, 0.0], dtype=float, device=device))
    cut.set_tools([[-h, 0.0, z0]], [[(nx - 1) * h + h, 0.0, z0]])
    cut.cut()
    before = world.positions(cloth)
    world.simulate(0.3, DT)
    low = v[:, 2] < z0
    src0, src1 = _fields(world, 0)[1], _fields(world, 1)[1]
    assert np.all(src0[:, low] == -1) and np.all(src1[0, low] >= 0)
    drop = world.positions(cloth)[:, low, 2] - before[:, low, 2]
    assert drop[0].max() < -0.2 and drop[1].min() > -0.01
    assert not world.unstable.numpy().any()


def _held_sheet(device, tethers: bool, substeps: int = 10):
    """(edge stretch, distance of each particle from the rigidly rotated sheet, m). The benchmark's cloth_pulled in
    small: a 16 x 16 sheet pinned along its back edge, its front corners held by stiff attachments 6 mm down along
    the arc about that edge, i.e. where a rigid rotation of the sheet about its back edge puts them."""
    nx, size = 16, 0.03
    v, t = cloth_grid(nx, nx, size, size, plane="xy")
    b = SceneBuilder()
    obj = b.add_cloth(v, t, areal_density=0.2, stretch_stiffness=1e3, bend_stiffness=1e-6, damping=1.0,
                      fixed=np.nonzero(v[:, 1] > size - 1e-9)[0], tethers=tethers)
    drop = 0.006
    back = size - np.sqrt(size**2 - drop**2)
    for c in (0, nx - 1):
        b.add_attachment(c, -1, offset=tuple(v[c] + (0.0, back, -drop)), compliance=1e-6)
    world = b.finalize(1, device, substeps=substeps)
    world.simulate(2.0, DT)
    if tethers:  # three anchor groups: the pinned back edge (16 particles, one group) and each held corner
        assert int(world.state.geo_status.numpy()[0, 1]) == 3
    e = obj.edges
    q = world.positions(obj)[0]
    ratio = np.linalg.norm(q[e[:, 0]] - q[e[:, 1]], axis=1) / np.linalg.norm(v[e[:, 0]] - v[e[:, 1]], axis=1)
    angle = np.arcsin(drop / size)
    arm = size - v[:, 1]  # distance from the back edge
    rigid = np.stack([v[:, 0], size - arm * np.cos(angle), -arm * np.sin(angle)], axis=1)
    return ratio, np.linalg.norm(q - rigid, axis=1)


def test_tethers_carry_a_sheet_held_at_points(device):
    # issue #14's quality target for a held sheet: mean edge stretch <= 1.01, worst edge <= 1.10, here at 10
    # substeps. Closed form: a sheet this stiff (1e3 N/m; its weight strains it ~1e-4) held on the arc about its
    # pinned edge is the flat sheet rotated about that edge; a 1e-4 strain lets its 30 mm span sag ~0.2 mm, so every
    # particle within 0.3 mm of the rotated sheet. Measured (CPU, 5 / 10 / 20 substeps): stretch max 1.0000 and
    # 8 um off the rotated sheet at each; without tethers, mean / max stretch 2.66 / 13.7 at 10 substeps (1.034 /
    # 2.96 at 20). Before the tethers were projected onto their balls' intersection in one step and the held
    # corners placed first in each sweep: 20 substeps 0.9996 / 1.052, 10 substeps corner edges at 1.3-1.4
    free, _ = _held_sheet(device, False)
    tethered, off_rigid = _held_sheet(device, True)
    assert tethered.mean() <= 1.01 and tethered.max() <= 1.10
    assert off_rigid.max() < 3e-4
    assert free.mean() > 1.03 and free.max() > 2.0  # the scene needs the tethers (the test can fail)


def test_anchor_groups_past_the_last_field_share_it(device):
    # five separate anchors (four corners and the centre of an 11 x 11 sheet) in four fields: numbered by particle,
    # the fourth and fifth (particles 110 and 120) share the last field, which holds the nearer of the two
    fixed = (0, 10, 60, 110, 120)
    world, obj, v, _ = _sheet(device, fixed=fixed)
    world.step(DT)
    d, src, groups = _fields(world)
    assert groups == 4 == d.shape[0]
    for g, a in enumerate(fixed[:3]):
        assert np.all(src[g] == a)
        np.testing.assert_allclose(d[g], np.linalg.norm(v - v[a], axis=1), rtol=1e-4, atol=1e-7)
    d3, d4 = np.linalg.norm(v - v[110], axis=1), np.linalg.norm(v - v[120], axis=1)
    np.testing.assert_allclose(d[3], np.minimum(d3, d4), rtol=1e-4, atol=1e-7)
    assert set(np.unique(src[3])) == {110, 120}


def test_tether_projection_is_the_closest_point_of_the_balls(device):
    # the tether solve moves a particle to the closest point of the intersection of its tethers' balls (one per
    # anchor group). Reference: scipy's SLSQP on the same problem, for random sets of 1-4 balls that share a point
    # (some exactly tangent to it: the taut sheet's case) and particles outside them
    from scipy.optimize import minimize

    from lapwarp.kernels import geodesic

    rng = np.random.default_rng(3)
    groups = int(geodesic.GROUPS)
    cases = []
    for k in range(40):
        count = 1 + k % groups
        shared = rng.normal(size=3) * 0.01
        centres = shared + rng.normal(size=(count, 3)) * 0.03
        slack = np.where(rng.random(count) < 0.3, 0.0, rng.random(count) * 0.01)
        radii = np.linalg.norm(centres - shared, axis=1) + slack
        x = shared + rng.normal(size=3) * 0.03
        cases.append((x, centres, radii))
    n = 1 + groups  # particle 0 is tethered, 1..groups are the anchors
    N = len(cases)
    q = np.zeros((N, n, 3), np.float32)
    dist = np.zeros((N, groups * n), np.float32)
    source = np.full((N, groups * n), -1, np.int32)
    status = np.zeros((N, 2), np.int32)
    for env, (x, centres, radii) in enumerate(cases):
        q[env, 0] = x
        q[env, 1:1 + len(centres)] = centres
        for g, r in enumerate(radii):
            source[env, g * n] = 1 + g
            dist[env, g * n] = r
        status[env, 1] = len(radii)
    inv_mass = np.ones((1, n), np.float32)
    q_wp = wp.array(q, dtype=wp.vec3, device=device)
    wp.launch(geodesic.solve_geodesic_tethers, dim=(N, 1),
              inputs=[wp.array([0], dtype=wp.int32, device=device), wp.array(dist, device=device),
                      wp.array(source, device=device), wp.array(status, device=device),
                      wp.array(inv_mass, device=device), 2], outputs=[q_wp], device=device)
    got = q_wp.numpy()[:, 0].astype(np.float64)
    for env, (x, centres, radii) in enumerate(cases):
        cons = [{"type": "ineq", "fun": (lambda y, c=c, r=r: r**2 - np.sum((y - c) ** 2))}
                for c, r in zip(centres, radii, strict=True)]
        ref = minimize(lambda y, x=x: np.sum((y - x) ** 2), x0=got[env], constraints=cons, method="SLSQP",
                       options={"ftol": 1e-15, "maxiter": 500}).x
        # inside every ball (float32: 1e-5 of a tether's length), and no farther from x than the reference
        assert np.all(np.linalg.norm(got[env] - centres, axis=1) <= radii * (1 + 2e-5) + 1e-9), env
        assert np.linalg.norm(got[env] - x) <= np.linalg.norm(ref - x) + 2e-6, env
        np.testing.assert_allclose(got[env], ref, atol=2e-5)
