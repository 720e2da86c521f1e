"""The shared two-level bounding hierarchy of a deforming contact surface (its topology; bounds live per env).

A deforming surface (a soft hole, a squeezed cavity, a liver) is queried by the particles of other objects in the
same env at every contact sweep. Its triangles are grouped once, on the host, from the rest shape: a median split
along the longest axis (recursively, at multiples of ``leaf_size``) orders them so that each run of ``leaf_size``
consecutive triangles is a spatially compact *leaf*, and each run of ``leaves_per_super`` consecutive leaves a
compact *super leaf*. The grouping is topology, shared by every env; each sweep, the kernels of
:mod:`lapwarp.kernels.contact` compute every env's leaf and super-leaf boxes from the live vertex positions
(``surface_leaf_bounds``, ``surface_super_bounds``: one pass over the surface's vertices, as cheap as measuring
how far they moved) and a query tests the super-leaf boxes, then the boxes of the leaves inside those it meets,
then the triangles of the leaves it meets.

Why not Warp's ``wp.Mesh`` BVH: a grouped mesh over every env's copy has to be refit as a whole (a tree over
``num_envs * F`` triangles, ~30 % of LigatingLoop's step when refit every sweep), so it was refit a few times per
env step and queried with the sphere grown by the surface's largest move since, and a cavity squeezed by the loop
moves up to ~4.5 mm within a physics step: its loop's queries then met ~36 triangles each instead of ~4.6
(LigatingLoop, expert, env step 60, CPU count). The boxes here are always current, so a query meets only what is
near it now.
"""

import math

import numpy as np


def cluster_order(centroids: np.ndarray, leaf_size: int) -> np.ndarray:
    """Order of the triangles (by their ``(F, 3)`` rest ``centroids``) that makes each run of ``leaf_size``
    consecutive triangles spatially compact: a recursive median split along the longest axis of the set's
    centroids, at a multiple of ``leaf_size`` (only the last leaf may be short)."""
    order = np.empty(len(centroids), dtype=np.int64)
    stack = [(np.arange(len(centroids)), 0)]
    while stack:
        idx, at = stack.pop()
        if len(idx) <= leaf_size:
            order[at:at + len(idx)] = idx
            continue
        c = centroids[idx]
        axis = int(np.argmax(c.max(axis=0) - c.min(axis=0)))
        idx = idx[np.argsort(c[:, axis], kind="stable")]
        half = leaf_size * math.ceil(len(idx) / (2 * leaf_size))  # the lower part holds whole leaves
        stack.append((idx[:half], at))
        stack.append((idx[half:], at + half))
    return order


class SurfaceClusters:
    """The two-level grouping of one surface's triangles (host arrays; :class:`lapwarp.contact.ContactSystem`
    uploads them).

    Attributes:
        order: ``(F,)`` the triangles' new order (``tris[order]`` is the clustered triangle list).
        leaf_size: triangles per leaf (leaf ``l`` holds clustered triangles ``[l * leaf_size, (l + 1) * leaf_size)``).
        num_leaves, leaves_per_super, num_supers: the hierarchy's sizes (super leaf ``s`` holds leaves
            ``[s * leaves_per_super, (s + 1) * leaves_per_super)``; the last of each may be short).
        leaf_vert_start, leaf_verts: CSR of each leaf's distinct vertex indices (what its box is computed from).
    """

    def __init__(self, tris: np.ndarray, rest_positions: np.ndarray, leaf_size: int = 8,
                 leaves_per_super: int | None = None):
        tris = np.asarray(tris, dtype=np.int64).reshape(-1, 3)
        if len(tris) == 0:
            raise ValueError("the surface has no triangles")
        if isinstance(leaf_size, bool) or not isinstance(leaf_size, (int, np.integer)) or leaf_size < 1:
            raise ValueError(f"leaf_size must be an int >= 1 (triangles per leaf), got {leaf_size!r}")
        rest = np.asarray(rest_positions, dtype=np.float64)
        self.leaf_size = int(leaf_size)
        self.order = cluster_order(rest[tris].mean(axis=1), self.leaf_size)
        self.num_leaves = -(-len(tris) // self.leaf_size)
        # about as many super leaves as leaves per super leaf: a query scans ~2 sqrt(leaves) boxes before its
        # triangles (LigatingLoop's 1,500 triangles: 188 leaves in 14 super leaves of 14)
        self.leaves_per_super = int(leaves_per_super or max(2, math.ceil(math.sqrt(self.num_leaves))))
        self.num_supers = -(-self.num_leaves // self.leaves_per_super)
        ordered = tris[self.order]
        starts, verts = [0], []
        for leaf in range(self.num_leaves):
            v = np.unique(ordered[leaf * self.leaf_size:(leaf + 1) * self.leaf_size])
            verts.append(v)
            starts.append(starts[-1] + len(v))
        self.leaf_vert_start = np.asarray(starts, dtype=np.int32)
        self.leaf_verts = np.concatenate(verts).astype(np.int32)
