"""Colourings packed for block sweeps (``builder.pack_colors``): the per-vertex tet solve's vertices (kernels/vbd.py)
are coloured so that a sweep taking each colour in passes of a block's lanes needs few passes. Checked: every colour is
a valid one (no two elements share a node), the result is a permutation, it never needs more passes than the plain
greedy colouring and needs fewer on a box mesh (56 -> 44 passes of 32 lanes, counted when written); the vertex layout
leaves out the vertices fixed in every env and still lists every incidence of the others, and the World builds it
that way."""

from __future__ import annotations

import numpy as np
import pytest

from lapwarp.assets import box_tets, hollow_cylinder_tets
from lapwarp.builder import SceneBuilder, color_graph, pack_colors
from lapwarp.vbd import vertex_layout


def _passes(offsets, lanes):
    return int(np.ceil(np.diff(offsets) / lanes).sum())


def _check_colouring(elements, order, offsets):
    assert sorted(order.tolist()) == list(range(len(elements)))
    assert offsets[0] == 0 and offsets[-1] == len(elements)
    for c in range(len(offsets) - 1):
        nodes = elements[order[offsets[c]:offsets[c + 1]]].ravel()
        nodes = nodes[nodes >= 0]
        assert len(np.unique(nodes)) == len(nodes), f"colour {c} has elements sharing a node"


@pytest.mark.parametrize("lanes", [1, 8, 32])
def test_packed_tet_colours_are_valid_and_take_no_more_passes(lanes):
    for _, tets in (box_tets((0.1, 0.1, 0.1), (6, 6, 6)), hollow_cylinder_tets()):
        order, offsets = pack_colors(tets, lanes)
        _check_colouring(tets, order, offsets)
        assert _passes(offsets, lanes) <= _passes(color_graph(tets)[1], lanes)


def test_packing_saves_passes_on_a_box():
    _, tets = box_tets((0.1, 0.1, 0.1), (6, 6, 6))
    assert _passes(color_graph(tets)[1], 32) == 56
    assert _passes(pack_colors(tets, 32)[1], 32) == 44
    with pytest.raises(ValueError, match="lanes"):
        pack_colors(tets, 0)
    order, offsets = pack_colors(np.zeros((0, 4), dtype=np.int64), 32)
    assert len(order) == 0 and offsets == [0]


def test_vertex_layout_leaves_out_fixed_vertices():
    v, tets = box_tets((0.04, 0.02, 0.01), (6, 3, 2))
    fixed = np.zeros(len(v), dtype=bool)
    fixed[v[:, 0] < 1e-9] = True
    lay = vertex_layout(tets, fixed=fixed, lanes=32)
    free = np.nonzero(~fixed)[0]
    assert sorted(lay.vertices.tolist()) == free.tolist()
    color = {int(x): c for c in range(len(lay.color_offsets) - 1)
             for x in lay.vertices[lay.color_offsets[c]:lay.color_offsets[c + 1]]}
    for tet in tets:  # no tet has two free vertices of one colour
        cols = [color[int(x)] for x in tet if not fixed[x]]
        assert len(set(cols)) == len(cols)
    seen = set()
    for j, x in enumerate(lay.vertices):
        for a in range(lay.adj_offsets[j], lay.adj_offsets[j + 1]):
            assert tets[lay.adj_tets[a], lay.adj_corners[a]] == x
            seen.add((int(lay.adj_tets[a]), int(lay.adj_corners[a])))
    expected = {(t, k) for t in range(len(tets)) for k in range(4) if not fixed[tets[t, k]]}
    assert seen == expected and lay.adj_offsets[-1] == len(expected)
    # all fixed: the layout keeps every vertex (the solve skips them) rather than going empty
    assert len(vertex_layout(tets, fixed=np.ones(len(v), dtype=bool)).vertices) == len(np.unique(tets))


def test_world_vertex_layout_excludes_pinned(device):
    v, tets = box_tets((0.04, 0.02, 0.01), (6, 3, 2))
    b = SceneBuilder()
    pinned = np.nonzero(v[:, 0] < 1e-9)[0]
    b.add_tet_mesh(v, tets, density=1000.0, youngs_modulus=5e3, poisson_ratio=0.45, fixed=pinned)
    world = b.finalize(num_envs=2, device=device, substeps=4)
    world.tet_method = "vbd"
    vertices = world._vbd_layout[0].numpy()
    assert len(vertices) == len(v) - len(pinned) and not np.isin(pinned, vertices).any()


def test_world_packs_xpbd_tet_colours_on_request(device):
    """``finalize(tet_colors="packed")``: the XPBD tets' colours as :func:`pack_colors` packs them for the fused
    sweep's lanes (a valid colouring of the model's tets, their per-tet arrays permuted with them: the rest shapes
    match the indices), fewer passes than the greedy default on the box (56 -> 44); an unknown value raises."""
    from lapwarp.builder import TET_BLOCK_LANES

    v, tets = box_tets((0.1, 0.1, 0.1), (6, 6, 6))

    def build(colors):
        b = SceneBuilder()
        b.add_tet_mesh(v, tets, density=1000.0, youngs_modulus=5e3, poisson_ratio=0.45, fixed=[0])
        return b.finalize(num_envs=1, device=device, substeps=4, tet_colors=colors)

    passes = {}
    for colors in ("greedy", "packed"):
        m = build(colors).model
        idx = m.tet_indices.numpy()
        offsets = list(m.tet_color_offsets)
        _check_colouring(idx, np.arange(len(idx)), offsets)
        assert sorted(map(tuple, np.sort(idx, axis=1))) == sorted(map(tuple, np.sort(tets, axis=1)))
        # each tet's inverse rest matrix belongs to its (permuted) indices
        x = v[idx]
        Dm = np.stack([x[:, 1] - x[:, 0], x[:, 2] - x[:, 0], x[:, 3] - x[:, 0]], axis=2)
        np.testing.assert_allclose(np.linalg.inv(Dm), m.tet_inv_rest.numpy(), rtol=1e-4, atol=1e-2)
        passes[colors] = _passes(offsets, TET_BLOCK_LANES)
    assert passes == {"greedy": 56, "packed": 44}
    with pytest.raises(ValueError, match="tet_colors"):
        build("balanced")
