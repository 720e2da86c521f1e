"""Host-side layout of the per-vertex tet solve (vertex block descent, ``World.tet_method = "vbd"``).

The solve (``lapwarp.kernels.vbd``) updates one tet vertex per thread from the elastic forces of its incident tets,
so two vertices of one tet must not move at the same time: the vertices are graph-coloured (those sharing a tet get
different colours) and each colour is one Gauss-Seidel pass. This module builds, once per model, the vertices in
colour order, the colour offsets and each vertex's incident tets (CSR) with its corner in each, and splits the tets
into connected meshes (the World checks that each is anchored).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from lapwarp.builder import TET_BLOCK_LANES, pack_colors


@dataclass
class VertexLayout:
    """The tet vertices of a model in colour order and their incident tets.

    Attributes:
        vertices: ``(V,)`` particle indices, sorted by colour.
        color_offsets: host list of ``colors + 1`` offsets into ``vertices``.
        adj_offsets: ``(V + 1,)`` CSR offsets of each (colour-ordered) vertex's incident tets.
        adj_tets: tet indices (into the model's colour-ordered tets) of the incident tets.
        adj_corners: the vertex's corner (0-3) in each incident tet.
    """

    vertices: np.ndarray
    color_offsets: list[int]
    adj_offsets: np.ndarray
    adj_tets: np.ndarray
    adj_corners: np.ndarray


def vertex_layout(tet_indices: np.ndarray, fixed: np.ndarray | None = None,
                  lanes: int = TET_BLOCK_LANES) -> VertexLayout:
    """Colour the vertices of ``tet_indices`` ``(T, 4)`` so that no tet has two vertices of one colour, and list
    every vertex's incident tets. ``fixed``: a boolean mask over the particles that never move (pinned in every env):
    they are left out (the solve skips a vertex without inverse mass anyway, but it would hold a lane). The colours
    are packed for sweeps of ``lanes`` threads (``builder.pack_colors``: ThreadInHole's 180 free vertices in 8 passes
    of 32 instead of 9 with its 20 pinned ones)."""
    tets = np.asarray(tet_indices, dtype=np.int64)
    flat = tets.ravel()
    vertices, inverse = np.unique(flat, return_inverse=True)
    tet_of = np.repeat(np.arange(len(tets)), 4)
    corner_of = np.tile(np.arange(4), len(tets))
    if fixed is not None:
        moving = ~np.asarray(fixed, dtype=bool)[vertices]
        if not moving.any():
            moving[:] = True  # nothing moves: keep the layout non-empty (the solve skips every vertex)
        # the moving vertices renumbered 0..V'-1, the fixed ones' incidences dropped
        keep = moving[inverse]
        vertices = vertices[moving]
        inverse = (np.cumsum(moving) - 1)[inverse[keep]]
        flat, tet_of, corner_of = flat[keep], tet_of[keep], corner_of[keep]
    by_vertex = np.argsort(inverse, kind="stable")
    counts = np.bincount(inverse, minlength=len(vertices))
    starts = np.concatenate([[0], np.cumsum(counts)])
    # a vertex as an "element" whose nodes are its incident tets: vertices that share a tet share a node
    incident = np.full((len(vertices), int(counts.max())), -1, dtype=np.int64)
    slot = np.arange(len(flat)) - starts[inverse[by_vertex]]
    incident[inverse[by_vertex], slot] = tet_of[by_vertex]
    order, color_offsets = pack_colors(incident, lanes)
    adj_tets, adj_corners, adj_offsets = [], [], [0]
    for v in order:
        entries = by_vertex[starts[v]:starts[v + 1]]
        adj_tets.append(tet_of[entries])
        adj_corners.append(corner_of[entries])
        adj_offsets.append(adj_offsets[-1] + len(entries))
    return VertexLayout(vertices=vertices[order].astype(np.int32), color_offsets=color_offsets,
                        adj_offsets=np.asarray(adj_offsets, dtype=np.int32),
                        adj_tets=np.concatenate(adj_tets).astype(np.int32),
                        adj_corners=np.concatenate(adj_corners).astype(np.int32))


def tet_components(tet_indices: np.ndarray) -> list[np.ndarray]:
    """The particle indices of each connected tet mesh in ``tet_indices`` ``(T, 4)`` (tets sharing a particle are
    connected)."""
    tets = np.asarray(tet_indices, dtype=np.int64)
    parent = {int(v): int(v) for v in np.unique(tets)}

    def root(v: int) -> int:
        while parent[v] != v:
            parent[v] = parent[parent[v]]
            v = parent[v]
        return v

    for a, *others in tets.tolist():
        for b in others:
            ra, rb = root(a), root(b)
            if ra != rb:
                parent[rb] = ra
    groups: dict[int, list[int]] = {}
    for v in parent:
        groups.setdefault(root(v), []).append(v)
    return [np.asarray(sorted(g), dtype=np.int64) for g in groups.values()]
