"""The converged deformable solver: cloth edge chains (lapwarp.chains, kernels/chains.py), the per-vertex tet solve
(kernels/vbd.py) against XPBD's tets at many substeps, per-env materials.

A cloth's physical stretch under its own weight is ~1e-4 (its weight over 1e3 N/m), so edge stretch beyond ~1 % is
solver error. Tolerances: mean edge stretch <= 1.01 and max <= 1.10 (the issue's targets); the coloured Gauss-Seidel
solver at the same settings stretches the same cloth to ~2x on average, which shows these tests can fail.
"""

from __future__ import annotations

import numpy as np
import pytest
import trimesh
import warp as wp

from lapwarp.assets import box_tets, cloth_grid
from lapwarp.builder import SceneBuilder, color_graph
from lapwarp.chains import chain_families, straight_chains
from lapwarp.cutting import CuttingSystem

G = 9.81


def edge_stretch(world, obj, rest: np.ndarray) -> tuple[float, float]:
    """(mean, max) of current / rest length over the object's edges and all envs."""
    e = obj.edges - obj.particle_start
    q = world.positions(obj)
    rest_length = np.linalg.norm(rest[e[:, 0]] - rest[e[:, 1]], axis=1)
    ratio = np.linalg.norm(q[:, e[:, 0]] - q[:, e[:, 1]], axis=2) / rest_length
    return float(ratio.mean()), float(ratio.max())


def hanging_cloth(device, n=40, num_envs=1, lean=0.2, **kw):
    """PrecisionCutting's 40 x 40 cloth (75 mm, 0.2 kg/m^2, 1e3 N/m) pinned along its top edge, leaning out of its
    plane so it swings into its hang."""
    v, t = cloth_grid(n, n, 0.075, 0.075, plane="xz", origin=(0.0, 0.0, -0.075))
    b = SceneBuilder()
    finalize = {k: kw.pop(k) for k in ("substeps", "edge_solver", "iterations") if k in kw}
    obj = b.add_cloth(v, t, areal_density=0.2, stretch_stiffness=1e3, bend_stiffness=1e-6, damping=1.0,
                      fixed=np.nonzero(v[:, 2] > -1e-9)[0], **kw)
    world = b.finalize(num_envs, device, **finalize)
    q = world.state.particle_q.numpy()
    q[..., 1] += lean * (-q[..., 2])
    world.state.particle_q.assign(q)
    world.save_start_state()
    return world, obj, v, t


# ---------------------------------------------------------------------------------------------------- chains
def test_grid_edges_split_into_rows_columns_and_diagonals():
    v, t = cloth_grid(6, 5, 0.05, 0.04, plane="xy")
    edges = np.unique(np.sort(np.concatenate([t[:, [0, 1]], t[:, [1, 2]], t[:, [2, 0]]]), axis=1), axis=0)
    chains = straight_chains(edges, v)
    ids = np.concatenate([c[1] for c in chains])
    assert sorted(ids.tolist()) == list(range(len(edges)))  # every edge in exactly one chain
    lengths = sorted(len(c[1]) for c in chains)
    # 5 rows of 5 links, 6 columns of 4, and the diagonals (one per quad direction): 2 x (1 + 2 + 3) + 4 + 4
    assert lengths.count(5) == 5 and lengths.count(4) == 6 + 2 and sum(lengths) == len(edges)
    for nodes, ids_c, closed in chains:
        assert not closed and len(nodes) == len(ids_c) + 1
        for k, e in enumerate(ids_c):  # consecutive nodes are joined by the chain's edges, in order
            assert sorted(edges[e]) == sorted((nodes[k], nodes[k + 1]))
        d = np.diff(v[nodes], axis=0)
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        assert np.all(np.einsum("ij,ij->i", d[1:], d[:-1]) > 0.99)  # straight
    family = chain_families(chains, len(v))
    assert max(family) == 2  # rows, columns, diagonals
    for f in set(family):
        nodes = np.concatenate([chains[c][0] for c in range(len(chains)) if family[c] == f])
        assert len(np.unique(nodes)) == len(nodes)  # chains of a family share no node


def test_irregular_mesh_chains_cover_every_edge_and_families_are_disjoint():
    mesh = trimesh.creation.icosphere(subdivisions=2)
    edges = mesh.edges_unique
    chains = straight_chains(edges, mesh.vertices)
    ids = np.concatenate([c[1] for c in chains])
    assert sorted(ids.tolist()) == list(range(len(edges)))
    assert any(c[2] for c in chains) or max(len(c[1]) for c in chains) > 2  # great circles: loops or long chains
    family = chain_families(chains, len(mesh.vertices))
    for f in set(family):
        nodes = np.concatenate([chains[c][0] for c in range(len(chains)) if family[c] == f])
        assert len(np.unique(nodes)) == len(nodes)


# ---------------------------------------------------------------------------------------------------- cloth
@pytest.mark.parametrize("cuttable", [False, True])
def test_untethered_cloth_keeps_its_length_at_default_settings(device, cuttable):
    world, obj, v, _ = hanging_cloth(device, cuttable=cuttable)  # default substeps (10), 1 iteration, no tethers
    assert world.model.geo_particles is None and world.model.edge_chains.num_families == 3
    world.simulate(3.0, 0.1)
    mean, worst = edge_stretch(world, obj, v)
    assert mean <= 1.01 and worst <= 1.10, (mean, worst)
    assert not world.unstable.numpy().any()


def test_colored_gauss_seidel_stretches_the_same_cloth():
    # the old path at the same settings (the reason for the chains): the test above can fail
    world, obj, v, _ = hanging_cloth("cpu", edge_solver="colored", substeps=20)
    world.simulate(3.0, 0.1)
    mean, worst = edge_stretch(world, obj, v)
    assert mean > 1.5 and worst > 5.0, (mean, worst)


def test_cut_piece_falls_away_and_the_rest_keeps_its_length(device):
    n = 20
    world, obj, v, t = hanging_cloth(device, n=n, num_envs=2, lean=0.0, cuttable=True)
    cut = CuttingSystem(world, carving_distance=1.0e-3, tool_radius=0.0)
    cut.add_object(obj)
    cut.finalize()
    world.simulate(1.0, 0.1)
    z_half = -0.0375
    below = np.nonzero(v[:, 2] < z_half - 1e-3)[0]
    z0 = world.positions(obj)[:, below, 2].mean(axis=1)
    # env 0: a blade across the sheet through the middle of a row of quads (1/6 of the spacing from the centroids of
    # both triangles of each quad) cuts it in two; env 1: the tool is off
    q = world.positions(obj)
    row = np.argmin(np.abs(v[:, 2] - z_half))
    zc = float(q[0, row, 2] - 0.5 * 0.075 / (n - 1))
    cut.set_tools([[[-0.01, 0.0, zc]]], [[[0.085, 0.0, zc]]], active=[1, 0])
    cut.cut()
    cut.set_tools([[[-0.01, 0.0, zc]]], [[[0.085, 0.0, zc]]], active=[0, 0])
    assert cut.num_components.numpy()[0, 0] == 2 and cut.num_components.numpy()[1, 0] == 1
    world.simulate(0.2, 0.1)
    z1 = world.positions(obj)[:, below, 2].mean(axis=1)
    fall = 0.5 * G * 0.2**2  # 0.196 m of free fall in 0.2 s
    assert z0[0] - z1[0] > 0.8 * fall, (z0, z1)  # the cut-off piece falls (air damping 1/s slows it a little)
    assert abs(z0[1] - z1[1]) < 1e-3  # the uncut sheet still hangs
    upper = np.nonzero(v[:, 2] > z_half + 2e-3)[0]
    e = obj.edges - obj.particle_start
    keep = np.isin(e[:, 0], upper) & np.isin(e[:, 1], upper)
    qq = world.positions(obj)[0]
    ratio = np.linalg.norm(qq[e[keep, 0]] - qq[e[keep, 1]], axis=1) / np.linalg.norm(v[e[keep, 0]] - v[e[keep, 1]],
                                                                                      axis=1)
    assert ratio.mean() <= 1.01 and ratio.max() <= 1.10, (ratio.mean(), ratio.max())


def pulled_cloth(device, num_envs=1, substeps=20, edge_solver="chains"):
    """A horizontal 40 x 40 sheet (75 mm, 0.2 kg/m^2, 1e3 N/m) pinned along its back edge (y = 75 mm); its two front
    corners are grasped (attachments of compliance 1e-6 m/N to kinematic bodies) and dragged 15 mm down in 1 s,
    along the arc about the pinned edge, so the sheet needs no stretch to follow: whatever stretch appears beyond
    its weight's ~1e-4 is solver error. Returns (world, cloth, rest vertices, drag(step) -> None)."""
    v, t = cloth_grid(40, 40, 0.075, 0.075, plane="xy")
    b = SceneBuilder()
    obj = b.add_cloth(v, t, areal_density=0.2, stretch_stiffness=1e3, bend_stiffness=1e-6, damping=1.0,
                      fixed=np.nonzero(v[:, 1] > 0.075 - 1e-9)[0])
    corners = [0, 39]
    bodies = [b.add_body(f"grasper{k}", pose=(*v[c], 0.0, 0.0, 0.0, 1.0)) for k, c in enumerate(corners)]
    for c, body in zip(corners, bodies, strict=True):
        b.add_attachment(obj.particle_start + c, body, compliance=1e-6)
    world = b.finalize(num_envs, device, substeps=substeps, edge_solver=edge_solver)
    ids = wp.array(np.array(bodies, np.int32), dtype=wp.int32, device=device)

    def drag(step: int, steps: int = 10) -> None:
        drop = 0.015 * min(step, steps) / steps
        back = 0.075 - np.sqrt(0.075**2 - drop**2)  # along the arc about the pinned edge
        pose = [[*(v[c] + (0.0, back, -drop)), 0.0, 0.0, 0.0, 1.0] for c in corners]
        world.set_body_poses(wp.array(np.array([pose] * num_envs, np.float32), dtype=wp.transform, device=device),
                             ids)

    return world, obj, v, drag


def test_pulled_cloth_converges_with_substeps(device):
    # PrecisionCutting's support pattern (back edge pinned, front corners held) with the corners dragged 15 mm down:
    # gravity loads the sheet across the taut lines between its supports, which every position-based solver
    # resolves only to O(h) (the sheet sags, its lines stretch); the converged answer (400 substeps, measured on the
    # H100) has mean stretch 1.0003, max 1.09 at the point-held corners. At 80 substeps the edge chains hold the mean
    # within 1 % (measured 1.002); the colored solver at the same substeps does not (4x more stretch, checked).
    means = {}
    for solver in ("chains", "colored"):
        world, obj, v, drag = pulled_cloth(device, substeps=80, edge_solver=solver)
        for step in range(15):  # 1 s dragging, 0.5 s holding
            drag(step + 1)
            world.step(0.1)
        means[solver], worst = edge_stretch(world, obj, v)
        if solver == "chains":
            q = world.positions(obj)[0]
            assert np.all(np.abs(q[[0, 39], 2] + 0.015) < 1e-3)  # the corners followed the graspers down
            assert worst < 3.0, worst
    assert means["chains"] <= 1.01, means
    assert means["colored"] - 1.0 > 4.0 * (means["chains"] - 1.0), means


# ---------------------------------------------------------------------------------------------------- tets
def _block_sag(device, substeps, method: str | None = "vbd", E=3e4, nu=0.45, steps=20):
    """(top face's mean sag after ``steps`` env steps, substeps per step, the tet method used); ``method`` None
    keeps the World's default."""
    v, t = box_tets((0.04, 0.04, 0.02), (7, 6, 4))
    b = SceneBuilder()
    obj = b.add_tet_mesh(v, t, density=1000.0, youngs_modulus=E, poisson_ratio=nu, damping=1.0,
                         fixed=np.nonzero(v[:, 2] < 1e-9)[0])
    world = b.finalize(1, device, substeps=substeps)
    if method is not None:
        world.tet_method = method
    world.simulate(0.1 * steps, 0.1)
    top = np.nonzero(v[:, 2] > 0.02 - 1e-9)[0]
    return (float(-(world.positions(obj)[0, top, 2] - v[top, 2]).mean()), world.substeps_for(0.1),
            world.tet_method_in_use)


def test_stiff_tet_block_converges_at_the_default_setting(device):
    # A 40 x 40 x 20 mm block of 1,008 tets, E = 30 kPa, nu = 0.45, clamped base, sagging under gravity for 2 s.
    # The World's default for a pinned mesh (tet_method "auto" -> the per-vertex solve, 10 substeps per 0.1 s) lands
    # within 5 % of its own 200-substep
    # answer and of XPBD's at 800 substeps (an independent reference: another method, converged). XPBD with 1 sweep
    # per substep reaches the material's stiffness only when a substep resolves the fastest elastic wave across a tet
    # (h c / l_min <= 0.7: its automatic count is 305 substeps here); at 10 substeps it sags > 10x too much
    # (measured ~50x), which shows the test can fail. Measured (CPU): vbd 10 / 200 substeps and XPBD 800 agree to 0.4 %.
    sag, substeps, method = _block_sag(device, None, method=None)
    assert (substeps, method) == (10, "vbd"), (substeps, method)
    fine, _, _ = _block_sag(device, 200)
    xpbd_converged, _, _ = _block_sag(device, 800, "xpbd")
    assert abs(sag / fine - 1.0) < 0.05, (sag, fine)
    assert abs(sag / xpbd_converged - 1.0) < 0.05, (sag, xpbd_converged)
    coarse, _, _ = _block_sag(device, 10, "xpbd")
    assert coarse > 10.0 * xpbd_converged, (coarse, xpbd_converged)


def test_xpbd_tets_pick_their_substeps_automatically(device):
    # With tet_method "xpbd" the automatic substep count resolves the stiffest tet's elastic wave: 305 per 0.1 s for
    # the 30 kPa block; the per-vertex solve needs only the minimum of 10. The block has no pinned particle, so the
    # World's default ("auto") solves it with XPBD.
    world = SceneBuilder()
    v, t = box_tets((0.04, 0.04, 0.02), (7, 6, 4))
    world.add_tet_mesh(v, t, density=1000.0, youngs_modulus=3e4, poisson_ratio=0.45)
    w = world.finalize(1, device, substeps=None)
    assert (w.tet_method, w.tet_method_in_use) == ("auto", "xpbd")  # the World's default, for a free mesh
    assert 250 <= w.substeps_for(0.1) <= 350, w.substeps_for(0.1)
    w.tet_method = "vbd"
    assert w.substeps_for(0.1) == 10


# ---------------------------------------------------------------------------------------------------- materials
def test_per_env_materials_set_at_reset(device):
    # Tet column (nu = 0, clamped base): top sag rho g H^2 / (2 E) is proportional to density / stiffness. Env 0
    # keeps the built material, env 1 gets half the stiffness, env 2 twice the density, env 3 both (4x the sag);
    # the same world built with those materials per env from the start must agree (1e-4 relative).
    def column(youngs, density):
        v, t = box_tets((0.02, 0.02, 0.02), (2, 2, 2))
        b = SceneBuilder()
        obj = b.add_tet_mesh(v, t, density=density, youngs_modulus=youngs, poisson_ratio=0.0, damping=40.0,
                             fixed=np.nonzero(v[:, 2] < 1e-9)[0])
        return b, obj, v

    b, obj, v = column(5e3, 1000.0)
    world = b.finalize(4, device, substeps=20, per_env_materials=True)
    stiffness = wp.array([1.0, 0.5, 1.0, 0.5], dtype=float, device=device)
    density = wp.array([1.0, 1.0, 2.0, 2.0], dtype=float, device=device)
    damping = wp.array([40.0, 40.0, 40.0, 40.0], dtype=float, device=device)
    mask = wp.array([0, 1, 1, 1], dtype=wp.int32, device=device)
    world.set_materials(obj, mask, stiffness_scale=stiffness, density_scale=density, damping=damping)
    world.reset_all()
    world.simulate(0.6, 0.01)
    top = np.nonzero(v[:, 2] > 0.02 - 1e-9)[0]
    sag = -(world.positions(obj)[:, top, 2] - v[top, 2]).mean(axis=1)
    np.testing.assert_allclose(sag / sag[0], [1.0, 2.0, 2.0, 4.0], rtol=0.03)
    b2, obj2, _ = column([5e3, 2.5e3, 5e3, 2.5e3], [1000.0, 1000.0, 2000.0, 2000.0])
    world2 = b2.finalize(4, device, substeps=20)
    world2.simulate(0.6, 0.01)
    np.testing.assert_allclose(world.positions(obj), world2.positions(obj2), rtol=1e-4, atol=1e-7)
    with pytest.raises(ValueError, match="per_env_materials"):
        world2.set_materials(obj2, mask, stiffness_scale=stiffness)


@pytest.mark.parametrize("max_size", [None, 32, 5])
def test_color_graph_colours_share_no_node_and_respect_max_size(max_size):
    """Every colour of a tet mesh's faces (interior ones too: up to ~36 faces meet at a node) shares no node, every
    face gets exactly one colour, and no colour holds more than ``max_size`` faces."""
    _, tets = box_tets((0.06, 0.04, 0.02), (6, 4, 2))
    faces = np.unique(np.sort(np.concatenate([tets[:, [0, 1, 2]], tets[:, [0, 1, 3]], tets[:, [0, 2, 3]],
                                              tets[:, [1, 2, 3]]]), axis=1), axis=0)
    order, offsets = color_graph(faces, max_size)
    assert sorted(order.tolist()) == list(range(len(faces))) and offsets[-1] == len(faces)
    sizes = np.diff(offsets)
    assert sizes.min() > 0
    if max_size is not None:
        assert sizes.max() <= max_size
    for c in range(len(sizes)):
        nodes = faces[order[offsets[c]:offsets[c + 1]]].ravel()
        assert len(np.unique(nodes)) == len(nodes), f"colour {c} shares a node"


def test_color_graph_rejects_a_max_size_below_one():
    with pytest.raises(ValueError, match="max_size"):
        color_graph(np.array([[0, 1, 2]]), 0)
