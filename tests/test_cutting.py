"""Element-mask cutting (issue #5): hook cuts a rope, closing scissors cut a cloth along a line, a tet slab loses
exactly the tets within the carving distance and keeps a closed surface, masked reset, env independence."""

from __future__ import annotations

import numpy as np
import pytest
import warp as wp

from lapwarp.assets import box_tets, cloth_grid
from lapwarp.builder import SceneBuilder
from lapwarp.cutting import CuttingSystem, cut_surface

DT = 0.1


def _rope(device, num_envs, cuttable=True):
    b = SceneBuilder()
    n = 21
    pts = np.stack([np.zeros(n), np.zeros(n), -np.linspace(0.0, 0.1, n)], axis=1)
    rope = b.add_rod(pts, radius=1e-3, youngs_modulus=1e6, damping=0.5, fixed=[0], cuttable=cuttable)
    return b.finalize(num_envs, device, substeps=10), rope


def test_hook_cuts_hanging_rope(device):
    world, rope = _rope(device, 3)
    ref, _ = _rope(device, 1, cuttable=False)
    cut = CuttingSystem(world, carving_distance=1.2e-3, num_tools=1, tool_radius=1e-3)
    cut.add_object(rope)
    cut.finalize()
    world.simulate(0.3, DT)
    ref.simulate(0.3, DT)
    # all-present masks change nothing: bit-exact with the same rope built without masks
    np.testing.assert_array_equal(world.positions(rope)[1], ref.positions()[0])
    before = world.positions(rope)
    # hook across the rope at segment 9's midpoint; env 0 active, env 1 inside the dead zone, env 2 off
    cut.set_tools([[0.0, -0.01, -0.0475]], [[0.0, 0.01, -0.0475]])
    cut.hook_activation(wp.array([0.8, 0.05, -1.0], dtype=float, device=device), deadzone=0.1)
    cut.cut()
    act = world.state.segment_active.numpy()
    assert act[0].tolist() == [1] * 9 + [0] + [1] * 10
    assert act[1:].min() == 1, "an inactive hook cut something"
    np.testing.assert_array_equal(cut.removed.numpy()[:, 0], [1, 0, 0])
    np.testing.assert_array_equal(cut.cut_happened.numpy(), [1, 0, 0])
    np.testing.assert_array_equal(cut.num_components.numpy()[:, 0], [2, 1, 1])
    comp = cut.component.numpy()[0]
    assert set(comp[:9]) == {0} and set(comp[10:]) == {10} and comp[9] == -1
    world.simulate(0.3, DT)
    ref.simulate(0.3, DT)
    q = world.positions(rope)
    # the lower piece falls freely (~0.44 m in 0.3 s), the upper one still hangs at its length
    assert q[0, -1, 2] < before[0, -1, 2] - 0.3
    assert abs(np.linalg.norm(q[0, 9] - q[0, 0]) - 0.045) < 1e-3
    for e in (1, 2):
        np.testing.assert_array_equal(q[e], ref.positions()[0])
    assert not world.unstable.numpy().any()


def test_orphaned_particle_stays_put_and_stable(device):
    """A node whose segments are both cut belongs to nothing: it must not fall for ever (after ~5 s its speed would
    pass the stability limit and reset the env) but stay where it was, like sofa_env's removed points."""
    world, rope = _rope(device, 2)
    cut = CuttingSystem(world, carving_distance=1.0e-3, num_tools=1, tool_radius=0.5e-3)
    cut.add_object(rope)
    cut.finalize()
    world.simulate(0.3, DT)
    # a short hook along the rope over node 10 removes segments 9 and 10 (their closest points are within reach)
    cut.set_tools([[0.0, 0.0, -0.0495]], [[0.0, 0.0, -0.0505]], active=[1, 0])
    cut.cut()
    act = world.state.segment_active.numpy()
    assert act[0, 9] == 0 and act[0, 10] == 0 and act[1].min() == 1
    assert world.state.particle_active.numpy()[0, 10] == 0
    orphan = world.positions(rope)[0, 10].copy()
    world.simulate(8.0, DT)  # free fall would reach 78 m/s, past the 50 m/s limit
    np.testing.assert_array_equal(world.positions(rope)[0, 10], orphan)
    assert not world.unstable.numpy().any()


def test_scissors_cut_cloth_along_line(device):
    b = SceneBuilder()
    nx, h = 13, 0.005
    v, t = cloth_grid(nx, nx, (nx - 1) * h, (nx - 1) * h, plane="xz")
    top = np.nonzero(v[:, 2] > v[:, 2].max() - 1e-9)[0]
    cloth = b.add_cloth(v, t, areal_density=0.2, stretch_stiffness=1e3, bend_stiffness=1e-6, damping=1.0,
                        fixed=top, cuttable=True)
    world = b.finalize(2, device, substeps=10)
    z0 = 5.5 * h  # the cutting line runs through the middle of a band of quads
    cen = v[t].mean(axis=1)
    on = np.abs(cen[:, 2] - z0) < 0.5 * h  # both triangles of every quad of that band (centroids at z0 +- h/6)
    assert on.sum() == 2 * (nx - 1)
    cut = CuttingSystem(world, carving_distance=0.2e-3, num_tools=1, num_labels=2, tool_radius=0.5 * h - 0.2e-3)
    cut.add_object(cloth, labels=on.astype(int))
    cut.finalize()
    angle = wp.array([0.5, 0.5], dtype=float, device=device)
    cut.scissors_closing(angle)  # first call only stores the angle
    ratios = []
    x_end = (nx - 1) * h
    for k, (x0, x1) in enumerate([(-h, 0.4 * x_end), (0.4 * x_end, x_end + h)]):
        # env 0 closes its jaws, env 1 keeps them still; the blade lies on the line from x0 to x1
        angle.assign(np.array([0.4 - 0.1 * k, 0.5], dtype=np.float32))
        cut.scissors_closing(angle)
        cut.set_tools([[x0, 0.0, z0]], [[x1, 0.0, z0]])
        cut.cut()
        ratios.append(cut.cut_ratio.numpy()[:, 1].copy())
    # opening the jaws over the same blade cuts nothing
    angle.assign(np.array([0.6, 0.6], dtype=np.float32))
    cut.scissors_closing(angle)
    cut.cut()
    assert cut.removed.numpy().sum() == 0
    assert 0.2 < ratios[0][0] < 0.8 and ratios[1][0] == 1.0, ratios
    assert ratios[0][1] == 0.0 and ratios[1][1] == 0.0
    act = world.state.tri_active.numpy()
    np.testing.assert_array_equal(act[0], (~on).astype(np.int32))  # exactly the line's triangles went
    assert act[1].min() == 1
    np.testing.assert_array_equal(cut.active_count.numpy()[:, 0], [(~on).sum()] * 2)
    np.testing.assert_array_equal(cut.num_components.numpy()[:, 0], [2, 1])
    faces, fa = cut_surface(world, cloth)
    assert faces.shape == (len(t), 3) and fa.shape == (2, len(t))
    before = world.positions(cloth)
    world.simulate(0.3, DT)
    q = world.positions(cloth)
    low = v[:, 2] < z0
    drop = q[:, low, 2] - before[:, low, 2]
    # the piece below the cut falls away (free fall ~0.4 m in 0.3 s); the uncut cloth of env 1 only sags
    assert drop[0].max() < drop[1].min() - 0.2
    assert drop[1].min() > -0.15
    assert not world.unstable.numpy().any()


def _closed_and_oriented(faces: np.ndarray) -> bool:
    """Every directed edge appears once and its reverse once: a closed, consistently wound surface."""
    e = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    fwd = {tuple(x) for x in e.tolist()}
    return len(fwd) == len(e) and all((b, a) in fwd for a, b in fwd)


def test_tet_slab_carving_surface_and_reset(device):
    b = SceneBuilder()
    v, t = box_tets((0.04, 0.04, 0.01), (8, 8, 2))
    slab = b.add_tet_mesh(v, t, density=1000.0, youngs_modulus=3e3, poisson_ratio=0.3, damping=1.0,
                          fixed=np.nonzero(v[:, 2] < 1e-9)[0], cuttable=True)
    world = b.finalize(2, device, substeps=5)
    q0 = world.positions(slab)
    surf0 = world.state.tet_face_active.numpy().copy()
    cut = CuttingSystem(world, carving_distance=6e-3, num_tools=1)
    cut.add_object(slab)
    cut.finalize()
    tip = np.array([0.02, 0.02, 0.01])  # a point tool (a = b) on the top face
    cut.set_tools([tip], [tip], active=[1, 0])
    cut.cut()
    tets = slab.tets - slab.particle_start
    d = np.linalg.norm(v[tets].mean(axis=1) - tip, axis=1)
    expect = (d > 6e-3).astype(np.int32)
    assert 0 < (expect == 0).sum() < len(t) // 2
    act = world.state.tet_active.numpy()
    np.testing.assert_array_equal(act[0], expect)
    assert act[1].min() == 1
    assert cut.removed.numpy()[0, 0] == (expect == 0).sum()
    faces, fa = cut_surface(world, slab)
    fa = fa.numpy()
    # reference surface: faces of present tets that appear once among present tets
    all_faces = np.stack([tets[:, [1, 2, 3]], tets[:, [0, 3, 2]], tets[:, [0, 1, 3]], tets[:, [0, 2, 1]]], axis=1)
    live = all_faces[expect == 1].reshape(-1, 3)
    _, inv, cnt = np.unique(np.sort(live, axis=1), axis=0, return_inverse=True, return_counts=True)
    ref = {tuple(sorted(f)) for f in live[cnt[inv.ravel()] == 1].tolist()}
    got = faces[fa[0] == 1]
    assert {tuple(sorted(f)) for f in got.tolist()} == ref
    assert _closed_and_oriented(got)
    assert len(got) > (surf0[0] == 1).sum()  # the crater adds faces
    np.testing.assert_array_equal(fa[1], surf0[1])
    assert cut.num_components.numpy()[0, 0] == 1 and cut.cut_ratio.numpy()[0, 0] > 0.0
    world.simulate(0.3, DT)
    assert not world.unstable.numpy().any()
    # masked reset of env 0 restores masks, surface and rest state; env 1 keeps its (moved) state
    q1 = world.positions(slab)[1]
    world.reset(wp.array([1, 0], dtype=wp.int32, device=device))
    cut.refresh()
    np.testing.assert_array_equal(world.state.tet_active.numpy()[0], np.ones(len(t), dtype=np.int32))
    np.testing.assert_array_equal(world.state.tet_face_active.numpy(), surf0)
    np.testing.assert_array_equal(world.positions(slab)[0], q0[0])
    np.testing.assert_array_equal(world.positions(slab)[1], q1)
    np.testing.assert_array_equal(cut.cut_ratio.numpy()[:, 0], [0.0, 0.0])


def _point_segment_distance(p, a, b):
    """Reference: distance from p to segment ab."""
    d = b - a
    t = np.clip(float((p - a) @ d) / max(float(d @ d), 1e-300), 0.0, 1.0)
    return float(np.linalg.norm(p - (a + t * d)))


def _point_triangle_distance(p, a, b, c):
    """Reference: distance from p to triangle abc (projection if it falls inside, else the nearest edge)."""
    n = np.cross(b - a, c - a)
    n = n / np.linalg.norm(n)
    proj = p - np.dot(p - a, n) * n
    inside = all(np.dot(np.cross(y - x, proj - x), n) >= 0 for x, y in ((a, b), (b, c), (c, a)))
    if inside:
        return abs(np.dot(p - a, n))
    return min(_point_segment_distance(p, a, b), _point_segment_distance(p, b, c), _point_segment_distance(p, c, a))


@pytest.mark.parametrize("removal", ["centroid", "touch"])
def test_removal_by_centroid_or_by_touch(device, removal):
    """A point tool just above a thin slab (0.1 mm, like TissueDissection's connective tissue): by centroid only the
    tets whose centroid is within reach go; by touch (SOFA's CarvingManager) every tet with a face within reach, the
    reference distance taken to each tet's nearest face in NumPy, tolerance 1e-6 m around the reach."""
    b = SceneBuilder(gravity=(0.0, 0.0, 0.0))
    v, t = box_tets((0.06, 0.02, 1e-4), (5, 1, 1))
    slab = b.add_tet_mesh(v, t, density=1000.0, youngs_modulus=5e3, poisson_ratio=0.0, damping=1.0,
                          fixed=np.arange(len(v)), cuttable=True)
    world = b.finalize(1, device, substeps=1)
    reach = 1.0e-3
    cut = CuttingSystem(world, carving_distance=2e-4, num_tools=1, tool_radius=reach - 2e-4, removal=removal)
    cut.add_object(slab)
    cut.finalize()
    tip = np.array([0.025, 0.019, 1e-4 + 0.5e-3])  # above the slab's far edge, 0.5 mm over its top
    cut.set_tools([tip], [tip], active=[1])
    cut.cut()
    tets = slab.tets - slab.particle_start
    if removal == "centroid":
        d = np.linalg.norm(v[tets].mean(axis=1) - tip, axis=1)
    else:
        faces = ((0, 1, 2), (0, 1, 3), (0, 2, 3), (1, 2, 3))
        d = np.array([min(_point_triangle_distance(tip, *v[tet[list(f)]]) for f in faces) for tet in tets])
    assert not np.any(np.abs(d - reach) < 1e-6)  # no tet on the boundary of the rule
    expect = (d > reach).astype(np.int32)
    np.testing.assert_array_equal(world.state.tet_active.numpy()[0], expect)
    removed = int((expect == 0).sum())
    # touching removes the tets under the tool; no centroid of these 12 x 20 mm tets is within 1 mm of it
    assert removed == 0 if removal == "centroid" else removed >= 1


def _segment_segment_distance(p0, p1, q0, q1, samples=2001):
    """Reference: distance between segments p0p1 and q0q1 (the closest point of q0q1 to each of ``samples`` points of
    p0p1 is exact; the sampling error along p0p1 is below (|p1 - p0| / samples)^2 / 8 / curvature: sub-nanometre for
    the millimetre segments here, far inside the tests' 1e-6 m margin)."""
    s = np.linspace(0.0, 1.0, samples)[:, None]
    p = p0 + s * (p1 - p0)
    d = q1 - q0
    t = np.clip(((p - q0) @ d) / max(float(d @ d), 1e-300), 0.0, 1.0)[:, None]
    return float(np.min(np.linalg.norm(p - (q0 + t * d), axis=1)))


def _segment_triangle_distance(p0, p1, a, b, c):
    """Reference: distance between segment p0p1 and triangle abc: 0 where the segment pierces it, else the least of its
    ends' distances to the triangle and its distances to the triangle's three edges (disjoint convex sets are closest
    at a segment end or a triangle edge)."""
    n = np.cross(b - a, c - a)
    den = float(n @ (p1 - p0))
    if abs(den) > 1e-30:
        s = float(n @ (a - p0)) / den
        if 0.0 <= s <= 1.0 and _point_triangle_distance(p0 + s * (p1 - p0), a, b, c) < 1e-12:
            return 0.0
    return min(_point_triangle_distance(p0, a, b, c), _point_triangle_distance(p1, a, b, c),
               *(_segment_segment_distance(p0, p1, x, y) for x, y in ((a, b), (b, c), (c, a))))


def test_touch_removal_of_random_tool_segments_matches_a_reference(device):
    """By touch a tet goes when a tool's axis comes within reach of one of its faces. 24 envs, each with a random
    segment tool (1-12 mm long, any direction, a third along an axis, three of zero length) around a thin slab of 60
    tets (2 mm thick, like TissueDissection's flap), against a NumPy reference of the segment-to-face distance; cases
    within 1e-6 m of the reach are redrawn. Checks every shortcut the kernel takes (bounding sphere, box, vertex and
    face tests) against the plain definition."""
    rng = np.random.default_rng(7)
    b = SceneBuilder(gravity=(0.0, 0.0, 0.0))
    v, t = box_tets((0.02, 0.01, 0.002), (5, 2, 1))
    slab = b.add_tet_mesh(v, t, density=1000.0, youngs_modulus=5e3, poisson_ratio=0.0, damping=1.0,
                          fixed=np.arange(len(v)), cuttable=True)
    num_envs, reach = 24, 1.0e-3
    world = b.finalize(num_envs, device, substeps=1)
    cut = CuttingSystem(world, carving_distance=2e-4, num_tools=1, tool_radius=reach - 2e-4, removal="touch")
    cut.add_object(slab)
    cut.finalize()
    tets = slab.tets - slab.particle_start
    faces = ((0, 1, 2), (0, 1, 3), (0, 2, 3), (1, 2, 3))

    def distances(p0, p1):
        return np.array([min(_segment_triangle_distance(p0, p1, *v[tet[list(f)]]) for f in faces) for tet in tets])

    starts, ends, expect = [], [], []
    while len(starts) < num_envs:
        p0 = rng.uniform((-0.002, -0.002, -0.003), (0.022, 0.012, 0.005))
        direction = rng.normal(size=3)
        if len(starts) % 3 == 1:  # along an axis: the box test's zero-extent slabs
            direction = np.eye(3)[rng.integers(3)] * rng.choice([-1.0, 1.0])
        length = 0.0 if len(starts) % 8 == 5 else rng.uniform(0.001, 0.012)  # a few point tools too
        p1 = p0 + direction / np.linalg.norm(direction) * length
        d = distances(p0, p1)
        if np.any(np.abs(d - reach) < 1e-6):
            continue
        starts.append(p0)
        ends.append(p1)
        expect.append((d > reach).astype(np.int32))
    cut.set_tools(np.array(starts)[:, None, :], np.array(ends)[:, None, :], active=np.ones(num_envs))
    cut.cut()
    expect = np.array(expect)
    np.testing.assert_array_equal(world.state.tet_active.numpy(), expect)
    removed = (expect == 0).sum(axis=1)
    assert (removed == 0).sum() >= 3 and (removed > 0).sum() >= 6  # misses, near misses and hits among the draws
    np.testing.assert_array_equal(cut.removed.numpy()[:, 0], removed)


def test_vertex_removal_of_random_tool_segments_matches_a_reference(device):
    """By vertex (SOFA's CarvingManager on a point model, sofa_env's PrecisionCutting cloth) a triangle goes when one of
    its vertices is within reach of a tool's axis. 16 envs, each with a random segment tool over a 7 x 7 cloth grid of
    2 mm cells (PrecisionCutting's 1.9 mm), against a NumPy reference of the vertex-to-segment distance (cases within
    1e-6 m of the reach redrawn); the same draws by touch remove a superset (a triangle with a vertex within reach is
    within reach), and at least one draw shows the difference (a tool over a cell's middle touches it with no vertex
    in reach)."""
    rng = np.random.default_rng(11)
    v, t = cloth_grid(7, 7, 0.012, 0.012, plane="xy")
    num_envs, reach = 16, 1.0e-3
    worlds = {}
    for removal in ("vertex", "touch"):
        b = SceneBuilder(gravity=(0.0, 0.0, 0.0))
        cloth = b.add_cloth(v, t, areal_density=0.2, stretch_stiffness=1e3, bend_stiffness=1e-6, damping=1.0,
                            fixed=np.arange(len(v)), cuttable=True)
        world = b.finalize(num_envs, device, substeps=1)
        cut = CuttingSystem(world, carving_distance=2e-4, num_tools=1, tool_radius=reach - 2e-4, removal=removal)
        cut.add_object(cloth)
        cut.finalize()
        worlds[removal] = (world, cut)
    lo, hi = v.min(axis=0), v.max(axis=0)
    starts, ends, expect = [], [], []
    while len(starts) < num_envs:
        p0 = rng.uniform(lo - 0.002, hi + 0.002) + np.array([0.0, 0.0, rng.uniform(-0.0015, 0.0015)])
        direction = rng.normal(size=3)
        if len(starts) % 4 == 1:
            direction[2] = 0.0  # in the cloth's plane, at a height: over cell middles without reaching a vertex
        p1 = p0 + direction / np.linalg.norm(direction) * (0.0 if len(starts) % 8 == 5 else rng.uniform(0.001, 0.01))
        d = np.array([_point_segment_distance(x, p0, p1) for x in v])
        if np.any(np.abs(d - reach) < 1e-6):
            continue
        starts.append(p0)
        ends.append(p1)
        expect.append((d[t] > reach).all(axis=1).astype(np.int32))
    expect = np.array(expect)
    masks = {}
    for removal, (world, cut) in worlds.items():
        cut.set_tools(np.array(starts)[:, None, :], np.array(ends)[:, None, :], active=np.ones(num_envs))
        cut.cut()
        masks[removal] = world.state.tri_active.numpy()
    np.testing.assert_array_equal(masks["vertex"], expect)
    removed = (expect == 0).sum(axis=1)
    assert (removed == 0).sum() >= 2 and (removed > 0).sum() >= 6
    np.testing.assert_array_equal(worlds["vertex"][1].removed.numpy()[:, 0], removed)
    assert np.all(masks["touch"] <= masks["vertex"]) and (masks["touch"] < masks["vertex"]).any()


def test_removal_rule_is_checked(device):
    world, rope = _rope(device, 1)
    with pytest.raises(ValueError, match="removal must be one of"):
        CuttingSystem(world, removal="nearest")


def test_flap_detaches_from_connective_tissue(device):
    """Labels + links: a cloth flap (label 0) hangs from a connective strip (label 1); cutting the strip's
    link row through the full width detaches them."""
    b = SceneBuilder(gravity=(0.0, 0.0, 0.0))
    nx, h = 9, 0.005
    v, t = cloth_grid(nx, nx, (nx - 1) * h, (nx - 1) * h, plane="xz")
    cloth = b.add_cloth(v, t, bend_stiffness=0.0, cuttable=True)
    world = b.finalize(1, device, substeps=2)
    cen = v[t].mean(axis=1)
    conn = cen[:, 2] > 5 * h  # connective tissue: the quads above the cut band
    cut = CuttingSystem(world, carving_distance=1e-4, num_tools=1, num_labels=2, tool_radius=0.5 * h - 1e-4)
    cut.add_object(cloth, labels=conn.astype(int))
    cut.finalize()
    assert cut.labels_connected(0, 1).all()
    cut.set_tools([[-h, 0.0, 4.5 * h]], [[nx * h, 0.0, 4.5 * h]], active=[1])
    cut.cut()
    assert not cut.labels_connected(0, 1).any()
    assert cut.labels_connected(1, 1).all() and cut.labels_connected(0, 0).all()
    assert cut.removed.numpy()[0, 1] == 0 and cut.removed.numpy()[0, 0] > 0


def test_not_cuttable_rejected(device):
    b = SceneBuilder()
    v, t = cloth_grid(3, 3, 0.01, 0.01)
    b.add_cloth(v, t)
    world = b.finalize(1, device)
    assert world.state.tri_active is None  # no masks, no cost
    with pytest.raises(ValueError):
        CuttingSystem(world)


@pytest.mark.parametrize("lanes", [0, -1, 1025, 2.5, True])
def test_block_threads_outside_a_block_is_rejected(device, lanes):
    # zero lanes would launch nothing and leave masks and counters silently stale
    b = SceneBuilder()
    v, t = cloth_grid(3, 3, 0.01, 0.01)
    cloth = b.add_cloth(v, t, cuttable=True)
    world = b.finalize(1, device)
    cut = CuttingSystem(world)
    cut.add_object(cloth)
    cut.block_threads = lanes
    with pytest.raises(ValueError, match="block_threads"):
        cut.finalize()


def test_connectivity_matches_sequential_union_find(device):
    """Random removals in a cloth + a tet slab + a rope with 3 labels: the concurrent union-find gives exactly the
    sequential result (component = smallest element of the piece, counts, label links)."""
    b = SceneBuilder()
    v, t = cloth_grid(9, 9, 0.02, 0.02)
    cloth = b.add_cloth(v, t, cuttable=True)
    tv, tt = box_tets((0.02, 0.02, 0.01), (4, 4, 2))
    slab = b.add_tet_mesh(tv + 0.1, tt, cuttable=True)
    rope = b.add_rod(np.stack([np.linspace(0, 0.05, 12), np.zeros(12), np.zeros(12)], 1) - 0.1, radius=1e-3,
                     cuttable=True)
    N = 6
    world = b.finalize(N, device, substeps=2)
    cut = CuttingSystem(world, num_labels=3)
    rng = np.random.default_rng(3)
    for o in (cloth, slab, rope):
        n = len(o.tris) if o.kind == "cloth" else len(o.tets) if o.kind == "tet_mesh" else len(o.edges)
        cut.add_object(o, labels=rng.integers(0, 3, n))
    cut.add_links(0, [0, 5], 1, [3, 7])
    cut.finalize()
    s = world.state
    for arr in (s.tri_active, s.tet_active, s.segment_active):
        arr.assign((rng.random(arr.shape) > 0.35).astype(np.int32))
    s.cut_dirty.fill_(1)
    cut.refresh()
    alive = np.concatenate([s.tri_active.numpy(), s.tet_active.numpy(), s.segment_active.numpy()], axis=1)
    pairs, lab, obj = cut._pairs.numpy(), cut._label.numpy(), cut._obj.numpy()
    comp = cut.component.numpy()
    for env in range(N):
        par = np.where(alive[env] != 0, np.arange(cut.num_elements), -1)

        def find(x, par=par):
            while par[x] != x:
                x = par[x]
            return x

        for a, c in pairs:
            if par[a] >= 0 and par[c] >= 0:
                ra, rc = find(a), find(c)
                par[max(ra, rc)] = min(ra, rc)
        ref = np.array([find(e) if par[e] >= 0 else -1 for e in range(cut.num_elements)])
        np.testing.assert_array_equal(comp[env], ref)
        live = ref >= 0
        np.testing.assert_array_equal(cut.active_count.numpy()[env], np.bincount(lab[live], minlength=3))
        roots = live & (ref == np.arange(len(ref)))
        np.testing.assert_array_equal(cut.num_components.numpy()[env], np.bincount(obj[roots], minlength=3))
        links = np.zeros((3, 3), np.int32)
        for r in np.nonzero(roots)[0]:
            ls = np.unique(lab[live & (ref == r)])
            links[np.ix_(ls, ls)] = 1
        np.testing.assert_array_equal(cut.label_links.numpy()[env], links.reshape(-1))
    assert s.cut_dirty.numpy().sum() == 0
