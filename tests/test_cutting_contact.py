"""Contact ignores cut elements (issue #5): a tool passes through the gap of a cut rope / cloth that holds it in the
uncut env, and a tet surface collider follows the cut (its opened faces collide, removed ones do not)."""

from __future__ import annotations

import numpy as np
import pytest
import warp as wp
from test_contact import _quat_axis_angle

from lapwarp.assets import box_tets, cloth_grid
from lapwarp.builder import SceneBuilder
from lapwarp.contact import ContactSystem
from lapwarp.cutting import CuttingSystem

DT = 0.05


def _cut(world, obj, mask, env, cols):
    """Remove elements ``cols`` of ``mask`` in ``env`` directly and refresh derived masks (surface, particles)."""
    m = mask.numpy().copy()
    m[env, cols] = 0
    mask.assign(m)
    world.state.cut_dirty.fill_(1)
    cut = CuttingSystem(world)
    cut.add_object(obj)
    cut.finalize()
    return cut


def test_rope_falls_through_cut_over_capsule(device):
    b = SceneBuilder()
    n = 21
    pts = np.stack([np.linspace(0.0, 0.1, n), np.zeros(n), np.full(n, 4.5e-3)], axis=1)
    rope = b.add_rod(pts, radius=1e-3, youngs_modulus=1e6, damping=0.5, cuttable=True)
    world = b.finalize(2, device, substeps=10)
    cs = ContactSystem(world)
    cs.add_particle_group(rope, radius=1e-3, segments=True)
    # static capsule (radius 3 mm) across the rope's middle (axis along y)
    cs.add_capsule(3e-3, 0.02, transform=wp.transform((0.05, 0.0, 0.0), wp.quat_from_axis_angle(
        wp.vec3(1.0, 0.0, 0.0), 0.5 * np.pi)), mu_static=0.5)
    cs.finalize()
    _cut(world, rope, world.state.segment_active, 0, [8, 9, 10, 11])  # nodes 9-11 lose every segment
    assert world.state.particle_active.numpy()[0, 10] == 0 and world.state.particle_active.numpy()[1, 10] == 1
    world.simulate(0.3, DT)
    z = world.positions(rope)[..., 2]
    assert z[1, 10] > 0.0  # uncut: the middle rests on the capsule
    live = world.state.particle_active.numpy()[0] != 0
    assert z[0, live].max() < -0.05  # cut: both pieces fall past it
    np.testing.assert_allclose(z[0, ~live], 4.5e-3)  # nodes left without a segment belong to nothing and stay put


def test_cloth_falls_through_hole_over_sphere(device):
    b = SceneBuilder()
    nx, h = 13, 2.5e-3
    v, t = cloth_grid(nx, nx, (nx - 1) * h, (nx - 1) * h)
    v = v - np.array([(nx - 1) * h / 2, (nx - 1) * h / 2, -5e-3])  # centred over the sphere, 1 mm above it
    cloth = b.add_cloth(v, t, areal_density=0.2, stretch_stiffness=1e3, bend_stiffness=1e-6, damping=1.0,
                        cuttable=True)
    world = b.finalize(2, device, substeps=10)
    cs = ContactSystem(world)
    cs.add_particle_group(cloth, radius=2.5e-4, triangles=True)
    cs.add_sphere(4e-3, mu_static=1.0)
    cs.finalize()
    cen = v[t].mean(axis=1)
    hole = np.nonzero(np.linalg.norm(cen[:, :2], axis=1) < 8.5e-3)[0]
    _cut(world, cloth, world.state.tri_active, 0, hole)
    # one step (free fall: 12 mm); later the floppy uncut sheet slides off the small sphere
    world.simulate(0.05, DT)
    z = world.positions(cloth)[..., 2]
    c = (nx * nx) // 2
    assert z[1, c] > 4e-3  # uncut: the sheet rests on the sphere's top
    live = world.state.particle_active.numpy()[0] != 0
    assert z[0, live].max() < -2e-3  # cut: the sphere passes through the hole
    np.testing.assert_allclose(z[0, ~live], 5e-3)  # vertices left without a triangle belong to nothing and stay put


def test_cut_tet_surface_drops_resting_rope(device):
    b = SceneBuilder()
    tv, tt = box_tets((0.02, 0.02, 0.01), (4, 4, 2))
    slab = b.add_tet_mesh(tv, tt, fixed=np.arange(len(tv)), cuttable=True)
    top = tv[:, 2].max()
    pts = np.stack([np.linspace(0.008, 0.012, 3), np.full(3, 0.01), np.full(3, top + 1e-3)], axis=1)
    rope = b.add_rod(pts, radius=5e-4, youngs_modulus=1e6, damping=0.5)
    world = b.finalize(2, device, substeps=10)
    cs = ContactSystem(world)
    cs.add_particle_group(rope, radius=5e-4)
    cs.add_surface(slab, mu_static=0.0, mu_kinetic=0.0)
    cs.finalize()
    cen = tv[tt].mean(axis=1)
    column = np.nonzero((np.abs(cen[:, 0] - 0.01) < 5e-3) & (np.abs(cen[:, 1] - 0.01) < 5e-3))[0]
    _cut(world, slab, world.state.tet_active, 0, column)
    # the opened hole walls are on the surface now, the removed tets' faces are not
    fa = world.state.tet_face_active.numpy()
    assert fa[0, 4 * column].sum() == 0 and fa[0].sum() > fa[1].sum()
    world.simulate(0.3, DT)
    z = world.positions(rope)[..., 2]
    assert np.all(z[1] > top)  # uncut: resting on the top face
    assert np.all(z[0] < -0.05)  # cut: falls through the hole


def _slab_with_tool(device, reverse=False):
    """A 20 x 20 x 10 mm tet slab (5 mm cells, bottom fixed, no gravity) whose triangles collide with a capsule
    (r = 1 mm, axis along y at x = 12.5 mm: 2.5 mm from every node column, so only face interiors can touch it).
    ``reverse``: the tets in reverse order (a shared face's first tet is then the upper one)."""
    b = SceneBuilder(gravity=(0.0, 0.0, 0.0))
    tv, tt = box_tets((0.02, 0.02, 0.01), (4, 4, 2))
    if reverse:
        tt = tt[::-1].copy()
    slab = b.add_tet_mesh(tv, tt, youngs_modulus=1e5, damping=1.0, fixed=np.nonzero(tv[:, 2] == 0.0)[0],
                          cuttable=True)
    body = b.add_body("tool", pose=(0.0125, 0.01, 0.012, *_quat_axis_angle((1, 0, 0), 0.5 * np.pi)))
    world = b.finalize(2, device, substeps=10)
    cs = ContactSystem(world)
    cs.add_particle_group(slab, radius=2.5e-4, triangles=True)
    cs.add_capsule(1e-3, 2e-3, body=body)
    cs.finalize()
    return world, cs, slab, tv, tt


def test_tet_contact_triangles_are_the_distinct_faces(device):
    """A tet mesh collides through its distinct faces: a face two tets share is one triangle holding both tets'
    face columns (on while either is: one tet present, the other cut), a boundary face one column."""
    _, cs, slab, tv, tt = _slab_with_tool(device)
    g = cs.groups[0]
    faces = np.concatenate([tt[:, [1, 2, 3]], tt[:, [0, 2, 3]], tt[:, [0, 1, 3]], tt[:, [0, 1, 2]]])
    distinct, count = np.unique(np.sort(faces, axis=1), axis=0, return_counts=True)
    assert len(g.triangles) == len(distinct) < 4 * len(tt)
    assert (g.tri_col2 < 0).sum() == (count == 1).sum()  # boundary faces have no partner
    table = slab.particle_start + cs.world.model.tet_face_indices.numpy()
    cols = -2 - g.tri_col
    same = np.sort(table[cols], axis=1) == np.sort(g.triangles, axis=1)
    shared = g.tri_col2 >= 0
    partner_same = np.sort(table[g.tri_col2[shared]], axis=1) == np.sort(g.triangles[shared], axis=1)
    assert same.all() and partner_same.all() and (g.tri_col2[shared] != cols[shared]).all()


@pytest.mark.parametrize("reverse", [False, True])
def test_tool_rests_on_faces_a_cut_opens(device, reverse):
    """The capsule descends to 5.5 mm (its bottom 0.5 mm under the slab's mid plane). Env 0 has the top layer's tets
    above the tool cut away: the hole's floor, faces the cut tets shared with the tets below, must stop it and is
    pushed down (interior faces collide once a cut opens them, whichever of the two tets holds the face's first
    column); env 1, uncut, is pressed at its top (10 mm): its top sinks (~2 mm) until the soft slab lets the short
    tool through."""
    world, cs, slab, tv, tt = _slab_with_tool(device, reverse)
    cen = tv[tt].mean(axis=1)
    above = np.nonzero((np.abs(cen[:, 0] - 0.0125) < 2.5e-3) & (np.abs(cen[:, 1] - 0.01) < 5e-3)
                       & (cen[:, 2] > 5e-3))[0]
    _cut(world, slab, world.state.tet_active, 0, above)
    floor = np.nonzero((np.abs(tv[:, 0] - 0.0125) < 3e-3) & (np.abs(tv[:, 1] - 0.01) < 6e-3)
                       & (np.abs(tv[:, 2] - 5e-3) < 1e-6))[0]
    top = np.nonzero((np.abs(tv[:, 0] - 0.0125) < 3e-3) & (np.abs(tv[:, 1] - 0.01) < 6e-3)
                     & (np.abs(tv[:, 2] - 0.01) < 1e-6))[0]
    assert len(floor) == 6 and len(top) == 6
    pose = world.state.body_q.numpy()
    lowest_top = np.inf
    for zc in np.linspace(0.012, 0.0055, 14):
        pose[:, 0, 2] = zc
        world.state.body_q.assign(pose)
        world.step(0.02)
        lowest_top = min(lowest_top, float(world.positions(slab)[1, top, 2].mean()))
    x = world.positions(slab)
    # the floor carries the tool: its nodes (2.5 mm beside the axis) sink by most of the 0.75 mm overlap (measured:
    # 0.54 mm); a floor that does not collide leaves them at 5 mm
    assert x[0, floor, 2].mean() < 5e-3 - 3e-4, x[0, floor, 2]
    assert lowest_top < 0.01 - 1e-3, lowest_top  # uncut: the top is pressed down (measured: 2.1 mm)


@pytest.mark.parametrize("method", ["brute", "grid"])
def test_particle_contact_skips_particles_cut_loose(device, method):
    """A bead sent down at 5 cm/s (no gravity) onto the middle node of a straight rope pinned at both ends, rope and
    bead in one particle-contact set: where the rope is whole (env 1) the bead stops on the node and pushes the rope
    down; where its middle segments are cut (env 0: nodes 9-11 lose every segment, stay where they were and belong
    to nothing) the bead passes the loose node 10 that would otherwise stop it, an invisible obstacle."""
    b = SceneBuilder(gravity=(0.0, 0.0, 0.0))
    n = 21
    pts = np.stack([np.linspace(0.0, 0.1, n), np.zeros(n), np.zeros(n)], axis=1)
    rope = b.add_rod(pts, radius=1e-3, youngs_modulus=1e6, damping=0.5, cuttable=True)
    b.fix_particles([rope.particle_start, rope.particle_start + n - 1])
    bead = b.add_particles(np.array([[0.05, 0.0, 0.004]]), mass=1e-4)
    world = b.finalize(2, device, substeps=10)
    qd = world.state.particle_qd.numpy()
    qd[:, bead.particle_start, 2] = -0.05
    world.state.particle_qd.assign(qd)
    cs = ContactSystem(world)
    cs.add_particle_contact([(rope, 1e-3), (bead, 1e-3)], method=method)
    cs.finalize()
    _cut(world, rope, world.state.segment_active, 0, [8, 9, 10, 11])
    assert world.state.particle_active.numpy()[0, rope.particle_start + 10] == 0
    gaps, node = [], []
    for _ in range(6):
        world.step(DT)
        z_bead, z_node = world.positions(bead)[:, 0, 2], world.positions(rope)[:, 10, 2]
        gaps.append(z_bead - z_node)
        node.append(z_node)
    gaps, node = np.array(gaps), np.array(node)
    # whole rope: the node is pushed down over 1 mm and the bead never gets closer to it than the contact distance
    assert node[:, 1].min() < -1.0e-3 and gaps[:, 1].min() > 1.9e-3
    np.testing.assert_allclose(node[:, 0], 0.0, atol=1e-9)  # the loose node stays put
    assert gaps[-1, 0] < -0.005  # cut rope: the bead passed the loose node
