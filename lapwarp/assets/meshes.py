"""Procedural meshes for the deformable objects of the tasks (NumPy in, NumPy out, SI units).

Tet meshes come from hexahedral grids split into 6 tets per cell (Kuhn / Freudenthal subdivision,
conforming across cells), as SOFA's Hexa2TetraTopologicalMapping does for the LapGym scenes. Every
tet generator returns ``(vertices (n, 3) float64, tets (T, 4) int64)``; ``tet_surface`` gives the
outward boundary triangles used for rendering and contact (``SceneBuilder.add_tet_mesh`` computes the
same). Sizes follow sofa_env's mesh budgets (sofa_env-facts section 11).
"""

from __future__ import annotations

import itertools

import numpy as np

__all__ = [
    "box_tets",
    "cloth_grid",
    "ellipsoid_tets",
    "grid_tets",
    "hollow_cylinder_tets",
    "rod_circle",
    "rod_polyline",
    "ruled_sheet_tets",
    "tet_surface",
    "voxel_tets",
]

# Kuhn subdivision of the unit cube: one tet per permutation of the axes, all sharing the 000-111 diagonal
_KUHN = []
for perm in itertools.permutations(range(3)):
    c = [0, 0, 0]
    path = [tuple(c)]
    for a in perm:
        c[a] = 1
        path.append(tuple(c))
    _KUHN.append(path)
_KUHN = np.asarray(_KUHN)  # (6, 4, 3) corner offsets


def _hex_grid_tets(cells: np.ndarray, node_id) -> np.ndarray:
    """Tets of the given ``(m, 3)`` integer cells; ``node_id(i, j, k)`` maps corner indices to vertex ids."""
    corners = cells[:, None, None, :] + _KUHN[None]  # (m, 6, 4, 3)
    return node_id(corners[..., 0], corners[..., 1], corners[..., 2]).reshape(-1, 4)


def box_tets(size=(0.1, 0.1, 0.1), cells=(4, 4, 4), origin=(0.0, 0.0, 0.0)):
    """Tetrahedralised box (block, slab, beam) of ``cells`` hexahedra, 6 tets each.

    Args:
        size: extents along x, y, z in m.
        cells: number of cells along x, y, z.
        origin: position of the minimum corner.
    """
    nx, ny, nz = (int(c) for c in cells)
    g = np.stack(np.meshgrid(np.arange(nx + 1), np.arange(ny + 1), np.arange(nz + 1), indexing="ij"), axis=-1)
    verts = g.reshape(-1, 3) * (np.asarray(size, dtype=np.float64) / np.array([nx, ny, nz])) + np.asarray(origin)
    cl = np.stack(np.meshgrid(np.arange(nx), np.arange(ny), np.arange(nz), indexing="ij"), axis=-1).reshape(-1, 3)
    tets = _hex_grid_tets(cl, lambda i, j, k: (i * (ny + 1) + j) * (nz + 1) + k)
    return verts, tets


def ellipsoid_tets(cells=(3, 4, 4), semi_axes=(1.0, 1.0, 1.0)):
    """A tetrahedralised ellipsoid: a ``cells`` hexahedral grid over the cube [-1, 1]^3 mapped onto the unit ball
    (the cube-to-sphere map x' = x sqrt(1 - y^2/2 - z^2/2 + y^2 z^2/3), cyclic; its Jacobian is positive inside the
    cube, so no tet inverts) and scaled by ``semi_axes``. The boundary vertices lie on the ellipsoid, so the surface
    is smooth at any resolution (a voxelised one is a staircase). 3 x 4 x 4 cells give 100 nodes and 288 tets
    (sofa_env's liver: 98 and 273), 9 x 5 x 4 give 300 and 1,080 (its gallbladder: 367 and 1,063).

    Returns:
        ``(vertices (n, 3), tets (T, 4))`` centred at the origin, axes along x, y, z.
    """
    nx, ny, nz = (int(c) for c in cells)
    verts, tets = box_tets(size=(2.0, 2.0, 2.0), cells=(nx, ny, nz), origin=(-1.0, -1.0, -1.0))
    x, y, z = verts.T
    x2, y2, z2 = x * x, y * y, z * z
    ball = np.stack([x * np.sqrt(1.0 - y2 / 2 - z2 / 2 + y2 * z2 / 3), y * np.sqrt(1.0 - z2 / 2 - x2 / 2 + z2 * x2 / 3),
                     z * np.sqrt(1.0 - x2 / 2 - y2 / 2 + x2 * y2 / 3)], axis=1)
    return ball * np.asarray(semi_axes, dtype=np.float64), tets


def grid_tets(nodes=(2, 2, 2), low=(0.0, 0.0, 0.0), high=(1.0, 1.0, 1.0)):
    """Tetrahedralised grid in SOFA's ``RegularGridTopology`` node order (x fastest: vertex ``ix + nx iy + nx ny
    iz``), 6 tets per hexahedron, so node indices match a sofa_env scene's.

    Args:
        nodes: vertices along x, y, z (at least 2 each).
        low, high: the grid's corners, m.
    """
    nx, ny, nz = (int(c) for c in nodes)
    if min(nx, ny, nz) < 2:
        raise ValueError(f"a grid needs at least 2 nodes per axis, got {nodes}")
    axes = [np.linspace(lo, hi, k) for lo, hi, k in zip(low, high, (nx, ny, nz), strict=True)]
    z, y, x = np.meshgrid(axes[2], axes[1], axes[0], indexing="ij")
    verts = np.stack([x.ravel(), y.ravel(), z.ravel()], axis=1)
    cl = np.stack(np.meshgrid(np.arange(nx - 1), np.arange(ny - 1), np.arange(nz - 1), indexing="ij"),
                  axis=-1).reshape(-1, 3)
    tets = _hex_grid_tets(cl, lambda i, j, k: i + nx * (j + ny * k))
    return verts, tets


def ruled_sheet_tets(left, right, rows: int, columns: int, thickness: float, layers: int = 2):
    """Tetrahedralised sheet between two outline curves in the xz plane, extruded along -y (a flat organ flap).

    Row ``i`` runs straight from the point at arc-length fraction ``i / (rows - 1)`` of ``left`` to the same fraction of
    ``right``, with ``columns`` nodes on it; the sheet spans ``y`` in ``[-thickness, 0]`` with ``layers`` node layers.
    Node order is ``grid_tets``'s over ``(columns, layers, rows)`` (column fastest), 6 tets per cell.

    Args:
        left, right: ``(k, 2)`` polylines of (x, z) points, both from the sheet's base to its top, m.
        rows, columns, layers: nodes along the outlines, across the sheet and through its thickness (>= 2 each).
        thickness: m.
    """
    def at_fractions(curve, t):
        curve = np.asarray(curve, dtype=np.float64).reshape(-1, 2)
        s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(curve, axis=0), axis=1))])
        return np.stack([np.interp(t * s[-1], s, curve[:, a]) for a in range(2)], axis=1)

    verts, tets = grid_tets((columns, layers, rows))  # unit box: x across, y through, z along
    t = verts[:, 2]
    a, b = at_fractions(left, t), at_fractions(right, t)
    v = verts[:, 0:1]
    xz = (1.0 - v) * a + v * b
    out = np.stack([xz[:, 0], (verts[:, 1] - 1.0) * thickness, xz[:, 1]], axis=1)
    return out, tets


def hollow_cylinder_tets(inner_radius=0.005, outer_radius=0.025, height=0.03, radial=2, angular=10, vertical=10,
                         origin=(0.0, 0.0, 0.0)):
    """Tetrahedralised hollow cylinder (ThreadInHole's hole, LigatingLoop's cavity) along +z.

    ``radial`` x ``angular`` x ``vertical`` are node counts as in sofa_env's Cavity discretisation
    (2 x 10 x 10 gives 200 nodes, 90 hexahedra, 540 tets; 2 x 15 x 25 gives 750 nodes, 2,160 tets).
    """
    r = np.linspace(inner_radius, outer_radius, radial)
    a = np.linspace(0.0, 2.0 * np.pi, angular, endpoint=False)
    z = np.linspace(0.0, height, vertical)
    R, A, Z = np.meshgrid(r, a, z, indexing="ij")
    verts = np.stack([R * np.cos(A), R * np.sin(A), Z], axis=-1).reshape(-1, 3) + np.asarray(origin)
    cl = np.stack(np.meshgrid(np.arange(radial - 1), np.arange(angular), np.arange(vertical - 1), indexing="ij"),
                  axis=-1).reshape(-1, 3)
    tets = _hex_grid_tets(cl, lambda i, j, k: (i * angular + j % angular) * vertical + k)
    return verts, tets


def voxel_tets(surface, pitch: float):
    """Tetrahedralise a closed surface (organ-like shape) on a voxel grid.

    Args:
        surface: a ``trimesh.Trimesh`` or a ``(vertices, faces)`` pair; must be watertight.
        pitch: voxel edge length in m (the liver/gallbladder budgets need ~100-400 nodes).
    """
    import trimesh

    mesh = surface if isinstance(surface, trimesh.Trimesh) else trimesh.Trimesh(*surface, process=True)
    lo, hi = mesh.bounds
    dims = np.maximum(np.ceil((hi - lo) / pitch).astype(int), 1)
    origin = 0.5 * (lo + hi) - 0.5 * dims * pitch
    cells = np.stack(np.meshgrid(*[np.arange(d) for d in dims], indexing="ij"), axis=-1).reshape(-1, 3)
    centres = origin + (cells + 0.5) * pitch
    # a voxel belongs to the solid when its centre is inside (volume error O(pitch) at the surface)
    inside = _winding_number(np.asarray(mesh.vertices), np.asarray(mesh.faces), centres) > 0.5
    cells = cells[inside]
    if len(cells) == 0:
        raise ValueError("no voxel centre inside the surface: reduce the pitch")
    nd = dims + 1
    corners = cells[:, None, None, :] + _KUHN[None]
    lin = (corners[..., 0] * nd[1] + corners[..., 1]) * nd[2] + corners[..., 2]
    used, tets = np.unique(lin.reshape(-1, 4), return_inverse=True)
    tets = tets.reshape(-1, 4)
    verts = origin + np.stack(np.unravel_index(used, tuple(nd)), axis=1) * pitch
    return verts, tets


def _winding_number(verts: np.ndarray, faces: np.ndarray, points: np.ndarray, chunk: int = 2048) -> np.ndarray:
    """Generalised winding number of closed triangle surfaces at ``points`` (Van Oosterom solid angles)."""
    out = np.empty(len(points))
    tri = verts[faces]  # (F, 3, 3)
    for s in range(0, len(points), chunk):
        r = tri[None, :, :, :] - points[s:s + chunk, None, None, :]  # (P, F, 3, 3)
        a, b, c = r[..., 0, :], r[..., 1, :], r[..., 2, :]
        la, lb, lc = (np.linalg.norm(x, axis=-1) for x in (a, b, c))
        num = np.einsum("pfi,pfi->pf", a, np.cross(b, c))
        den = (la * lb * lc + np.einsum("pfi,pfi->pf", a, b) * lc + np.einsum("pfi,pfi->pf", b, c) * la
               + np.einsum("pfi,pfi->pf", c, a) * lb)
        out[s:s + chunk] = np.arctan2(num, den).sum(axis=1) / (2.0 * np.pi)
    return out


def tet_surface(tets: np.ndarray, vertices: np.ndarray | None = None) -> np.ndarray:
    """Boundary triangles of a tet mesh, wound outwards when ``vertices`` is given (else as positive tets)."""
    t = np.asarray(tets, dtype=np.int64).copy()
    if vertices is not None:
        x = np.asarray(vertices)
        det = np.linalg.det(np.stack([x[t[:, i]] - x[t[:, 0]] for i in (1, 2, 3)], axis=2))
        neg = det < 0
        t[neg, 1], t[neg, 2] = t[neg, 2].copy(), t[neg, 1].copy()
    faces = np.concatenate([t[:, [1, 2, 3]], t[:, [0, 3, 2]], t[:, [0, 1, 3]], t[:, [0, 2, 1]]])
    _, idx, cnt = np.unique(np.sort(faces, axis=1), axis=0, return_index=True, return_counts=True)
    return faces[np.sort(idx[cnt == 1])]


def cloth_grid(nx=40, ny=40, size_x=0.075, size_y=0.075, plane: str = "xy", origin=(0.0, 0.0, 0.0)):
    """Regular ``nx`` x ``ny`` vertex cloth with one diagonal per quad (PrecisionCutting: 40 x 40 over
    75 mm gives 1,600 vertices and 3,042 triangles, like SOFA's RegularGrid).

    Args:
        plane: ``"xy"`` (horizontal sheet, normal +z) or ``"xz"`` (vertical sheet, rows go up in z).
        origin: position of vertex 0 (the minimum corner).

    Returns:
        ``(vertices (nx*ny, 3), triangles (2 (nx-1)(ny-1), 3))``, vertex ``j * nx + i`` at column i, row j.
    """
    u = np.linspace(0.0, size_x, nx)
    v = np.linspace(0.0, size_y, ny)
    U, V = np.meshgrid(u, v, indexing="xy")
    zeros = np.zeros_like(U)
    if plane == "xy":
        verts = np.stack([U, V, zeros], axis=-1).reshape(-1, 3)
    elif plane == "xz":
        verts = np.stack([U, zeros, V], axis=-1).reshape(-1, 3)
    else:
        raise ValueError("plane must be 'xy' or 'xz'")
    verts = verts + np.asarray(origin, dtype=np.float64)
    i, j = np.meshgrid(np.arange(nx - 1), np.arange(ny - 1), indexing="xy")
    a = (j * nx + i).ravel()
    b, c, d = a + 1, a + nx, a + nx + 1
    tris = np.concatenate([np.stack([a, b, d], 1), np.stack([a, d, c], 1)])
    return verts, tris


def rod_polyline(points, num_points: int) -> np.ndarray:
    """``num_points`` points evenly spaced by arc length along a polyline (threads, ropes)."""
    p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    seg = np.linalg.norm(np.diff(p, axis=0), axis=1)
    s = np.concatenate([[0.0], np.cumsum(seg)])
    t = np.linspace(0.0, s[-1], num_points)
    return np.stack([np.interp(t, s, p[:, k]) for k in range(3)], axis=1)


def rod_circle(radius: float, num_points: int, center=(0.0, 0.0, 0.0), normal=(0.0, 0.0, 1.0)) -> np.ndarray:
    """``num_points`` points on a circle (PickAndPlace's torus: 30 on r = 14 mm; LigatingLoop's loop: 50
    on r = 15 mm), for ``SceneBuilder.add_rod(..., closed=True)``; the first point is not repeated."""
    n = np.asarray(normal, dtype=np.float64)
    n = n / np.linalg.norm(n)
    ref = np.array([1.0, 0.0, 0.0]) if abs(n[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    e1 = np.cross(n, ref)
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(n, e1)
    a = np.linspace(0.0, 2.0 * np.pi, num_points, endpoint=False)
    return np.asarray(center) + radius * (np.cos(a)[:, None] * e1 + np.sin(a)[:, None] * e2)
