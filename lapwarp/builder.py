"""SceneBuilder: describe one scene (deformables, fixed particles, kinematic bodies, attachments) in
NumPy, then ``finalize(num_envs, device)`` into a batched ``World``.

Topology is stored once and shared by all envs. Every material parameter (density, Young's modulus,
Poisson ratio, stiffnesses, damping, compliances) accepts a scalar or a sequence of ``num_envs``
values (domain randomisation); a per-env value makes the affected model array ``(num_envs, count)``
instead of ``(1, count)``. Units are SI (m, kg, s, Pa).

Constraint groups are graph-coloured here, once, with a greedy colouring in NumPy, and stored sorted
by colour (see ``lapwarp.model``).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import warp as wp

from lapwarp.kernels import geodesic
from lapwarp.model import Model, SceneObject, State

__all__ = ["SceneBuilder", "color_graph", "pack_colors"]


# ----------------------------------------------------------------------------------------------------
# helpers
# ----------------------------------------------------------------------------------------------------


#: Model arrays that hold material parameters (per env with ``finalize(per_env_materials=True)``).
MATERIAL_ARRAYS = ("particle_inv_mass", "particle_damping", "edge_compliance", "hinge_compliance", "tet_params",
                   "segment_compliance", "segment_inv_inertia", "segment_damping", "bend_compliance",
                   "rod_stretch_compliance")


def _per_env(value, name: str) -> np.ndarray:
    """A scalar or per-env sequence as a 1-D float64 array (length 1 or num_envs, checked later)."""
    a = np.atleast_1d(np.asarray(value, dtype=np.float64))
    if a.ndim != 1 or a.size == 0:
        raise ValueError(f"{name} must be a scalar or a 1-D sequence of per-env values, got shape {a.shape}")
    return a


def color_graph(elements: np.ndarray, max_size: int | None = None) -> tuple[np.ndarray, list[int]]:
    """Greedy graph colouring of constraints that share nodes.

    Args:
        elements: ``(m, k)`` node indices of each constraint (negative entries are ignored).
        max_size: most constraints per colour (None: no limit). A sweep that takes each colour in chunks of a thread
            block's lanes runs one chunk per colour when the colours fit the block.

    Returns:
        ``(order, offsets)``: a permutation that sorts constraints by colour and the host list of colour
        offsets into the permuted order. Constraints of one colour share no node.
    """
    elements = np.asarray(elements, dtype=np.int64)
    m = len(elements)
    if m == 0:
        return np.zeros(0, dtype=np.int64), [0]
    if max_size is not None and max_size < 1:
        raise ValueError(f"max_size must be >= 1 or None, got {max_size!r}")
    used: dict[int, int] = {}
    colors = np.empty(m, dtype=np.int64)
    size: dict[int, int] = {}
    full = 0  # bit mask of the colours holding max_size constraints
    for c, nodes in enumerate(elements.tolist()):
        mask = full
        for v in nodes:
            if v >= 0:
                mask |= used.get(v, 0)
        col = ((~mask) & (mask + 1)).bit_length() - 1  # lowest free colour
        colors[c] = col
        bit = 1 << col
        size[col] = size.get(col, 0) + 1
        if max_size is not None and size[col] == max_size:
            full |= bit
        for v in nodes:
            if v >= 0:
                used[v] = used.get(v, 0) | bit
    order = np.argsort(colors, kind="stable")
    counts = np.bincount(colors)
    offsets = [0] + np.cumsum(counts).tolist()
    return order, offsets


#: lanes of the thread block per env that the fused tet and vertex sweeps give a colour (``World.tet_block_threads``'s
#: default): the per-vertex tet solve's vertices are coloured for passes of this width (:func:`pack_colors`)
TET_BLOCK_LANES = 32


def pack_colors(elements: np.ndarray, lanes: int) -> tuple[np.ndarray, list[int]]:
    """A colouring of ``elements`` (as :func:`color_graph`) for a sweep that takes each colour in passes of ``lanes``
    threads, one pass after the other: the one of a few greedy colourings that needs the fewest passes
    (``sum(ceil(size / lanes))``), then the fewest colours. Candidates: the elements in the given order, by
    descending and by ascending sum of their nodes' degrees, each uncapped and capped at 1-4 passes per colour.
    Why: a pass costs a lane's latency whether the colour fills it or not, and plain greedy colours leave ragged
    last passes (LigatingLoop's 2,160 tets would take 78 passes of 32 lanes in 17 colours, packed 72 against at
    least 68; GraspLiftAndTouch's 1,368 61 -> 45; the XPBD tets keep their colours, see ``finalize``)."""
    elements = np.asarray(elements, dtype=np.int64)
    if lanes < 1:
        raise ValueError(f"lanes must be >= 1, got {lanes!r}")
    m = len(elements)
    if m == 0:
        return color_graph(elements)
    nodes = elements[elements >= 0]
    degree = np.bincount(nodes) if len(nodes) else np.zeros(1, dtype=np.int64)
    score = np.where(elements >= 0, degree[np.maximum(elements, 0)], 0).sum(axis=1)
    best = None
    for perm in (np.arange(m), np.argsort(-score, kind="stable"), np.argsort(score, kind="stable")):
        for cap in (None, lanes, 2 * lanes, 3 * lanes, 4 * lanes):
            order, offsets = color_graph(elements[perm], cap)
            sizes = np.diff(offsets)
            key = (int(np.ceil(sizes / lanes).sum()), len(sizes))
            if best is None or key < best[0]:
                best = (key, perm[order], offsets)
    return best[1], best[2]


def _quat_from_frame(d1: np.ndarray, d2: np.ndarray, d3: np.ndarray) -> np.ndarray:
    """Quaternion (x, y, z, w) of the rotation whose columns are the orthonormal frame d1, d2, d3."""
    m = np.stack([d1, d2, d3], axis=1)
    t = np.trace(m)
    if t > 0.0:
        s = np.sqrt(t + 1.0) * 2.0
        q = [(m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s, 0.25 * s]
    elif m[0, 0] > m[1, 1] and m[0, 0] > m[2, 2]:
        s = np.sqrt(1.0 + m[0, 0] - m[1, 1] - m[2, 2]) * 2.0
        q = [0.25 * s, (m[0, 1] + m[1, 0]) / s, (m[0, 2] + m[2, 0]) / s, (m[2, 1] - m[1, 2]) / s]
    elif m[1, 1] > m[2, 2]:
        s = np.sqrt(1.0 + m[1, 1] - m[0, 0] - m[2, 2]) * 2.0
        q = [(m[0, 1] + m[1, 0]) / s, 0.25 * s, (m[1, 2] + m[2, 1]) / s, (m[0, 2] - m[2, 0]) / s]
    else:
        s = np.sqrt(1.0 + m[2, 2] - m[0, 0] - m[1, 1]) * 2.0
        q = [(m[0, 2] + m[2, 0]) / s, (m[1, 2] + m[2, 1]) / s, 0.25 * s, (m[1, 0] - m[0, 1]) / s]
    q = np.asarray(q)
    return q / np.linalg.norm(q)


def _quat_mul(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    ax, ay, az, aw = a
    bx, by, bz, bw = b
    return np.array([
        aw * bx + ax * bw + ay * bz - az * by,
        aw * by - ax * bz + ay * bw + az * bx,
        aw * bz + ax * by - ay * bx + az * bw,
        aw * bw - ax * bx - ay * by - az * bz,
    ])


def _quat_conj(a: np.ndarray) -> np.ndarray:
    return np.array([-a[0], -a[1], -a[2], a[3]])


def _build_geodesic_tethers(model: Model, state: State, cloths: list, x: np.ndarray, N: int, dev) -> None:
    """Shared tables and per-env state of the geodesic tethers (``lapwarp.kernels.geodesic``) of the cloths built
    with ``tethers=True``: their triangles, the four sweep orders, rest positions; distances start unknown and every
    env's first step computes them (``geo_status`` 2)."""
    tris = np.concatenate([t for t, _ in cloths])
    elem = np.concatenate([start + np.arange(len(t)) if start >= 0 else np.full(len(t), -1) for t, start in cloths])
    particles = np.unique(tris)
    # fast-sweeping orders: the triangles sorted along the four diagonals of the sheets' two main directions
    cen = x[tris].mean(axis=1)
    _, _, axes = np.linalg.svd(cen - cen.mean(axis=0), full_matrices=False)
    u, v = (cen - cen.mean(axis=0)) @ axes[0], (cen - cen.mean(axis=0)) @ axes[min(1, len(axes) - 1)]
    order = np.stack([np.argsort(su * u + sv * v, kind="stable") for su, sv in ((1, 1), (1, -1), (-1, 1), (-1, -1))])
    model.geo_particles = wp.array(particles.astype(np.int32), dtype=wp.int32, device=dev)
    model.geo_tris = wp.array(tris.astype(np.int32), dtype=wp.vec3i, device=dev)
    model.geo_tri_element = wp.array(elem.astype(np.int32), dtype=wp.int32, device=dev)
    model.geo_order = wp.array(order.astype(np.int32), dtype=wp.int32, device=dev)
    model.geo_rest = wp.array(x.astype(np.float32), dtype=wp.vec3, device=dev)
    n = len(x)
    groups = geodesic.GROUPS
    state.geo_dist = wp.full((N, groups * n), 1.0e30, dtype=float, device=dev)
    state.geo_source = wp.full((N, groups * n), -1, dtype=wp.int32, device=dev)
    state.geo_anchor = wp.full((N, n), -1, dtype=wp.int32, device=dev)  # unknown: the first step finds them
    state.geo_label = wp.full((N, n), -1, dtype=wp.int32, device=dev)
    state.geo_tri_seen = wp.ones((N, len(tris)), dtype=wp.int32, device=dev)
    # column 0: 2 = restart from the anchors; column 1: the number of anchor groups (set by the restart)
    state.geo_status = wp.array(np.tile(np.array([2, 0], np.int32), (N, 1)), dtype=wp.int32, device=dev)


def _dihedral_angle(x1, x2, x3, x4) -> float:
    """Signed dihedral angle with the same convention as ``xpbd.solve_hinges``."""
    n1 = np.cross(x3 - x1, x4 - x1)
    n2 = np.cross(x4 - x2, x3 - x2)
    n1 = n1 / np.linalg.norm(n1)
    n2 = n2 / np.linalg.norm(n2)
    e = (x4 - x3) / np.linalg.norm(x4 - x3)
    return float(np.arctan2(np.dot(np.cross(n1, n2), e), np.dot(n1, n2)))


@dataclass
class _Group:
    """Constraints of one kind: topology rows plus per-constraint compliance = geom * scale[env]."""

    indices: list = field(default_factory=list)  # arrays (m, k) of node indices
    rest: list = field(default_factory=list)  # arrays (m, ...) of rest data
    geom: list = field(default_factory=list)  # arrays (m, ...) geometric factors
    scale: list = field(default_factory=list)  # per-env arrays (1 or N, ...) multiplying geom
    extra: list = field(default_factory=list)  # arrays (m,...) shared extra data (e.g. tet Dm^-1)

    def count(self) -> int:
        return sum(len(i) for i in self.indices)


# ----------------------------------------------------------------------------------------------------
# builder
# ----------------------------------------------------------------------------------------------------


class SceneBuilder:
    """Collects the objects of one scene; ``finalize`` turns them into a batched ``World``.

    Example::

        b = SceneBuilder()
        cloth = b.add_cloth_grid(40, 40, 0.075, 0.075, areal_density=0.2, stretch_stiffness=500.0,
                                 bend_stiffness=1e-6, fixed_edge="top")
        world = b.finalize(num_envs=4096, device="cuda:0", substeps=20)
        world.simulate(1.0, dt=0.1)
        q = world.positions(cloth)  # (4096, 1600, 3)

    Args:
        gravity: gravity vector in m/s^2 (z up by default).
    """

    def __init__(self, gravity=(0.0, 0.0, -9.81)):
        self.gravity = tuple(float(g) for g in gravity)
        self._pos: list[np.ndarray] = []
        self._mass_base: list[np.ndarray] = []  # per particle, multiplied by the object's density
        self._density: list[tuple[slice, np.ndarray]] = []
        self._damping: list[tuple[slice, np.ndarray]] = []
        self._fixed: list[np.ndarray] = []
        self._n = 0
        self.objects: list[SceneObject] = []
        self._edges = _Group()
        self._hinges = _Group()
        self._tets = _Group()
        # cloths with geodesic tethers: (their triangles in global particle indices, first cloth-triangle index or -1)
        self._geodesic: list[tuple[np.ndarray, int]] = []
        # cutting: cloth triangles / tets in insertion order and the triangles beside each edge / hinge
        self._tris: list[np.ndarray] = []
        self._ntri = 0
        self._ntet = 0
        self._edge_tris: list[np.ndarray] = []  # parallel to self._edges.indices, (m, 2) int, -1 = none
        self._hinge_tris: list[np.ndarray] = []  # parallel to self._hinges.indices
        self._cuttable = False
        self._segments = _Group()
        self._bends = _Group()
        self._seg_q: list[np.ndarray] = []
        self._seg_inertia_base: list[np.ndarray] = []
        self._seg_density: list[tuple[slice, np.ndarray]] = []
        self._seg_damping: list[tuple[slice, np.ndarray]] = []
        self._seg_fixed: list[np.ndarray] = []
        self._nseg = 0
        self._rod_stretch = _Group()  # rows (particle_start, segment_start, segment_count, closed), one per rod
        self._bodies: list[tuple[str, np.ndarray]] = []
        self._attachments: list[tuple[int, int, np.ndarray, float]] = []
        self._tet_omega = 0.0  # largest elastic frequency of the tet meshes, 1/s (0: none)

    # ---------------------------------------------------------------------------------------------
    @property
    def particle_count(self) -> int:
        return self._n

    def _add_points(self, x: np.ndarray, mass_base: np.ndarray, density, damping, fixed) -> slice:
        x = np.asarray(x, dtype=np.float64).reshape(-1, 3)
        start = self._n
        sl = slice(start, start + len(x))
        self._pos.append(x)
        self._mass_base.append(np.asarray(mass_base, dtype=np.float64))
        self._density.append((sl, _per_env(density, "density")))
        self._damping.append((sl, _per_env(damping, "damping")))
        if fixed is not None:
            f = np.asarray(fixed)
            if f.dtype == bool:
                f = np.nonzero(f)[0]
            self._fixed.append(f.astype(np.int64) + start)
        self._n += len(x)
        return sl

    def _fixed_of(self, sl: slice) -> np.ndarray:
        allf = np.concatenate(self._fixed) if self._fixed else np.zeros(0, dtype=np.int64)
        return allf[(allf >= sl.start) & (allf < sl.stop)]

    def fix_particles(self, indices) -> None:
        """Pin global particles in place (inverse mass 0) in every env."""
        self._fixed.append(np.asarray(indices, dtype=np.int64).reshape(-1))

    # ---------------------------------------------------------------------------------------------
    def add_particles(self, positions, mass=1.0, fixed=None, damping=0.0, name: str = "particles") -> SceneObject:
        """Free point masses.

        Args:
            positions: ``(n, 3)`` initial positions, m.
            mass: kg per particle: scalar (shared), ``(num_envs,)`` per env, all particles alike.
            fixed: bool mask or local indices of particles pinned in place.
            damping: linear velocity damping rate, 1/s (scalar or per env).
            name: object name.
        """
        x = np.asarray(positions, dtype=np.float64).reshape(-1, 3)
        sl = self._add_points(x, np.ones(len(x)), mass, damping, fixed)
        obj = SceneObject(name, "particles", sl.start, len(x), fixed=self._fixed_of(sl))
        self.objects.append(obj)
        return obj

    def add_distance(self, i: int, j: int, compliance=0.0, rest_length: float | None = None) -> None:
        """Distance constraint between global particles ``i`` and ``j`` (compliance m/N, 0 = rigid)."""
        if rest_length is None:
            rest_length = float(np.linalg.norm(self._pos_all()[i] - self._pos_all()[j]))
        self._edges.indices.append(np.array([[i, j]], dtype=np.int64))
        self._edges.rest.append(np.array([rest_length]))
        self._edges.geom.append(np.ones(1))
        self._edges.scale.append(_per_env(compliance, "compliance")[:, None])
        self._edge_tris.append(np.full((1, 2), -1, dtype=np.int64))

    def _pos_all(self) -> np.ndarray:
        return np.concatenate(self._pos) if self._pos else np.zeros((0, 3))

    # ---------------------------------------------------------------------------------------------
    def add_cloth(
        self,
        vertices,
        triangles,
        areal_density=0.2,
        stretch_stiffness=1.0e3,
        bend_stiffness=1.0e-6,
        damping=0.0,
        fixed=None,
        tethers: bool = False,
        name: str = "cloth",
        cuttable: bool = False,
    ) -> SceneObject:
        """Triangle cloth: edge springs for stretch/shear plus dihedral bending hinges.

        Args:
            vertices: ``(n, 3)`` rest = initial positions, m.
            triangles: ``(F, 3)`` consistently wound triangles (local indices).
            areal_density: kg/m^2 (scalar or per env).
            stretch_stiffness: membrane stiffness ``E * thickness``, N/m (scalar or per env). Each edge is
                a spring of stiffness ``Y * (area of its triangles) / length^2`` (Van Gelder 1998); on a
                regular grid this is within ~25% of the continuum membrane.
            bend_stiffness: flexural rigidity ``E t^3 / (12 (1 - nu^2))``, N m (scalar or per env); 0 adds
                no hinges. Hinge stiffness is ``D |e|^2 / (A1 + A2)``: a regular grid bent into a cylinder
                of curvature k then stores the continuum energy ``D k^2 / 2`` per area (checked in tests).
            damping: linear velocity damping rate, 1/s.
            fixed: bool mask or local indices of pinned vertices.
            tethers: geodesic long-range attachments (Kim et al. 2012; ``lapwarp.kernels.geodesic``): every particle
                stays within its rest geodesic distance of the nearest *anchor* of every anchor group, an anchor being
                a pinned particle or one held by a stiff attachment (a grasp, a held corner), per env. The distances
                are recomputed on the device when an env's anchors change or a cut removes triangles (the path then
                goes around the cut; a piece cut off every anchor has no tether and falls). They carry a held sheet's
                weight to its supports within one sweep, which the edge chains alone do only over many substeps when
                the load crosses rows and columns (a sheet held at points). Inextensible along those geodesics, so a
                soft sheet that sags by stretching sags less than its material says (docs/physics.md). Off by
                default (the chain solver holds a hanging or cut sheet without them).
            name: object name.
            cuttable: its triangles get per-env active masks (``lapwarp.cutting``); an edge spring acts while one
                of its triangles is present, a hinge while both are.
        """
        x = np.asarray(vertices, dtype=np.float64).reshape(-1, 3)
        tri = np.asarray(triangles, dtype=np.int64).reshape(-1, 3)
        a, b, c = x[tri[:, 0]], x[tri[:, 1]], x[tri[:, 2]]
        area = 0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=1)
        mass_base = np.zeros(len(x))
        np.add.at(mass_base, tri.ravel(), np.repeat(area / 3.0, 3))
        sl = self._add_points(x, mass_base, areal_density, damping, fixed)
        off = sl.start

        # unique edges with their adjacent triangles
        he = np.concatenate([tri[:, [0, 1]], tri[:, [1, 2]], tri[:, [2, 0]]])
        he_tri = np.tile(np.arange(len(tri)), 3)
        he_opp = np.concatenate([tri[:, 2], tri[:, 0], tri[:, 1]])
        key = np.sort(he, axis=1)
        uniq, inv = np.unique(key, axis=0, return_inverse=True)
        inv = inv.ravel()
        adj_area = np.zeros(len(uniq))
        np.add.at(adj_area, inv, area[he_tri])
        length = np.linalg.norm(x[uniq[:, 0]] - x[uniq[:, 1]], axis=1)
        self._edges.indices.append(uniq + off)
        self._edges.rest.append(length)
        self._edges.geom.append(length**2 / adj_area)
        self._edges.scale.append(1.0 / _per_env(stretch_stiffness, "stretch_stiffness")[:, None])
        # the (one or two) triangles beside each edge, in the scene's triangle insertion order
        etri = np.full((len(uniq), 2), -1, dtype=np.int64)
        order_he = np.argsort(inv, kind="stable")
        first_he = np.searchsorted(inv[order_he], np.arange(len(uniq)))
        cnt_he = np.bincount(inv, minlength=len(uniq))
        etri[:, 0] = he_tri[order_he[first_he]]
        two = cnt_he >= 2
        etri[two, 1] = he_tri[order_he[first_he[two] + 1]]
        self._edge_tris.append(etri + self._ntri)

        # hinges: interior edges shared by two triangles
        bend = _per_env(bend_stiffness, "bend_stiffness")
        if np.any(bend > 0.0):
            order = np.argsort(inv, kind="stable")
            sinv = inv[order]
            first = np.searchsorted(sinv, np.arange(len(uniq)))
            cnt = np.bincount(inv, minlength=len(uniq))
            hinges, rest, geom, htri = [], [], [], []
            for e in np.nonzero(cnt == 2)[0]:
                h0, h1 = order[first[e]], order[first[e] + 1]
                htri.append((he_tri[h0] + self._ntri, he_tri[h1] + self._ntri))
                # c -> d in the winding of the first triangle, so flat rest gives angle 0
                cc, dd = he[h0]
                aa, bb = he_opp[h0], he_opp[h1]
                hinges.append((aa, bb, cc, dd))
                rest.append(_dihedral_angle(x[aa], x[bb], x[cc], x[dd]))
                geom.append((area[he_tri[h0]] + area[he_tri[h1]]) / length[e] ** 2)
            if hinges:
                self._hinges.indices.append(np.asarray(hinges, dtype=np.int64) + off)
                self._hinges.rest.append(np.asarray(rest))
                self._hinges.geom.append(np.asarray(geom))
                self._hinge_tris.append(np.asarray(htri, dtype=np.int64))
                with np.errstate(divide="ignore"):
                    self._hinges.scale.append(1.0 / bend[:, None])

        fixed_g = self._fixed_of(sl)
        if tethers:
            self._geodesic.append((tri + off, self._ntri if cuttable else -1))
        obj = SceneObject(name, "cloth", sl.start, len(x), surface_tris=(tri + off).astype(np.int32),
                          tris=(tri + off).astype(np.int32), edges=(uniq + off).astype(np.int32), fixed=fixed_g,
                          element_start=self._ntri, cuttable=bool(cuttable))
        self._tris.append(tri + off)
        self._ntri += len(tri)
        self._cuttable |= bool(cuttable)
        self.objects.append(obj)
        return obj

    def add_cloth_grid(self, nx: int, ny: int, size_x: float, size_y: float, origin=(0.0, 0.0, 0.0),
                       fixed_edge: str | None = "top", **kwargs) -> SceneObject:
        """A rectangular ``nx`` x ``ny`` vertex cloth grid in a vertical x-z plane (hanging under -z gravity).

        ``fixed_edge`` is ``"top"`` (max z row), ``"bottom"``, ``"left"``, ``"right"`` or None. Other keyword
        arguments go to ``add_cloth``; see ``lapwarp.assets.cloth_grid`` for horizontal sheets.
        """
        from lapwarp.assets.meshes import cloth_grid

        verts, tris = cloth_grid(nx, ny, size_x, size_y, plane="xz", origin=origin)
        fixed = kwargs.pop("fixed", None)
        if fixed is None and fixed_edge is not None:
            u = verts[:, 0]
            v = verts[:, 2]
            sel = {"top": v >= v.max() - 1e-9, "bottom": v <= v.min() + 1e-9,
                   "left": u <= u.min() + 1e-9, "right": u >= u.max() - 1e-9}[fixed_edge]
            fixed = np.nonzero(sel)[0]
        return self.add_cloth(verts, tris, fixed=fixed, **kwargs)

    # ---------------------------------------------------------------------------------------------
    def add_tet_mesh(
        self,
        vertices,
        tets,
        density=1000.0,
        youngs_modulus=1.0e4,
        poisson_ratio=0.3,
        damping=0.0,
        fixed=None,
        name: str = "tet_mesh",
        cuttable: bool = False,
    ) -> SceneObject:
        """Volumetric FEM body (co-rotated: XPBD constraints |F - R| and det F - 1) from a tetrahedral mesh.

        Args:
            vertices: ``(n, 3)`` rest = initial positions, m.
            tets: ``(T, 4)`` local indices; inverted rest tets are re-ordered, degenerate ones rejected.
            density: kg/m^3; youngs_modulus: Pa; poisson_ratio: in [0, 0.5) (all scalar or per env).
            damping: linear velocity damping rate, 1/s.
            fixed: bool mask or local indices of pinned vertices.
            name: object name.
            cuttable: its tets get per-env active masks and a per-env surface (``lapwarp.cutting``).
        """
        x = np.asarray(vertices, dtype=np.float64).reshape(-1, 3)
        t = np.asarray(tets, dtype=np.int64).reshape(-1, 4).copy()
        Ds = np.stack([x[t[:, 1]] - x[t[:, 0]], x[t[:, 2]] - x[t[:, 0]], x[t[:, 3]] - x[t[:, 0]]], axis=2)
        det = np.linalg.det(Ds)
        neg = det < 0
        t[neg, 1], t[neg, 2] = t[neg, 2].copy(), t[neg, 1].copy()
        Ds[neg] = Ds[neg][:, :, [1, 0, 2]]
        det = np.abs(det)
        if np.any(det < 1e-18):
            raise ValueError("tet mesh has degenerate (zero-volume) tetrahedra")
        vol = det / 6.0
        mass_base = np.zeros(len(x))
        np.add.at(mass_base, t.ravel(), np.repeat(vol / 4.0, 4))
        sl = self._add_points(x, mass_base, density, damping, fixed)
        off = sl.start
        E = _per_env(youngs_modulus, "youngs_modulus")
        nu = _per_env(poisson_ratio, "poisson_ratio")
        if np.any(nu >= 0.5) or np.any(nu < 0.0):
            raise ValueError("poisson_ratio must be in [0, 0.5)")
        P = max(len(E), len(nu))
        E = np.broadcast_to(E, (P,)) if len(E) == 1 else E
        nu = np.broadcast_to(nu, (P,)) if len(nu) == 1 else nu
        if len(E) != len(nu):
            raise ValueError("youngs_modulus and poisson_ratio have different per-env lengths")
        mu = E / (2.0 * (1.0 + nu))
        lam = E * nu / ((1.0 + nu) * (1.0 - 2.0 * nu))
        # energy V (mu |F - R|^2 + lambda / 2 (det F - 1)^2) = C^2 / (2 alpha) per constraint, so
        # alpha_D = 1 / (2 mu V) and alpha_H = 1 / (lambda V); -1 marks lambda = 0 (no volume term)
        with np.errstate(divide="ignore"):
            a_vol = np.where(lam[:, None] > 0.0, 1.0 / (lam[:, None] * vol[None, :]), -1.0)
        params = np.stack([
            1.0 / (2.0 * mu[:, None] * vol[None, :]),
            np.broadcast_to(a_vol, (P, len(vol))),
            np.ones((P, len(vol))),
        ], axis=2)
        # fastest elastic wave across a tet (P-wave speed over its shortest edge): the substep length at which XPBD's
        # single sweep per substep still reaches this material's compliance (SceneBuilder.finalize, substeps=None)
        edges = np.stack([x[t[:, a]] - x[t[:, b]] for a, b in ((0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3))], 1)
        shortest = np.linalg.norm(edges, axis=2).min()
        rho = float(np.min(_per_env(density, "density")))
        self._tet_omega = max(self._tet_omega, float(np.sqrt((lam + 2.0 * mu).max() / rho) / shortest))
        self._tets.indices.append(t + off)
        self._tets.rest.append(np.linalg.inv(Ds))
        self._tets.geom.append(np.ones(len(t)))
        self._tets.scale.append(params)  # (P, T, 3), used as-is
        # boundary faces (appear once), wound outwards for a positively oriented tet
        faces = np.concatenate([t[:, [1, 2, 3]], t[:, [0, 3, 2]], t[:, [0, 1, 3]], t[:, [0, 2, 1]]])
        key = np.sort(faces, axis=1)
        _, idx, cnt = np.unique(key, axis=0, return_index=True, return_counts=True)
        surf = faces[np.sort(idx[cnt == 1])]
        obj = SceneObject(name, "tet_mesh", sl.start, len(x), surface_tris=(surf + off).astype(np.int32),
                          tets=(t + off).astype(np.int32), fixed=self._fixed_of(sl), element_start=self._ntet,
                          cuttable=bool(cuttable))
        self._ntet += len(t)
        self._cuttable |= bool(cuttable)
        self.objects.append(obj)
        return obj

    # ---------------------------------------------------------------------------------------------
    def add_rod(
        self,
        points,
        radius=1.0e-3,
        density=1000.0,
        youngs_modulus=1.0e6,
        shear_modulus=None,
        closed: bool = False,
        rest_curvature: bool = True,
        damping=0.0,
        angular_damping=None,
        fixed=None,
        fixed_orientations=None,
        name: str = "rod",
        cuttable: bool = False,
        stretch_rest_scale: float = 1.0,
        inertia_scale: float = 1.0,
    ) -> SceneObject:
        """Cosserat rod: centreline particles plus one orientation quaternion per segment.

        Args:
            points: ``(m, 3)`` centreline, m (a closed loop does not repeat the first point).
            radius: cross-section radius, m. density: kg/m^3. youngs_modulus, shear_modulus: Pa
                (shear defaults to ``E / 2``, i.e. nu = 0). All scalar or per env.
            closed: connect the last point to the first (a loop or torus).
            rest_curvature: the initial shape is the rest shape; otherwise the rod is straight at rest.
            damping: linear velocity damping rate of the particles, 1/s; angular_damping of the
                segment orientations (defaults to ``damping``).
            fixed: local indices (or bool mask) of pinned points.
            fixed_orientations: local indices of segments whose orientation is clamped (a cantilever's
                root segment).
            name: object name.
            cuttable: its segments get per-env active masks (``lapwarp.cutting``); a removed segment is a break
                in the chain (no stretch, shear or bend-twist across it).
            stretch_rest_scale: rest length of every segment's stretch constraint over its length in ``points``
                (1: the given shape is at rest). Below 1 the rod is pre-tensioned: sofa_env's rope-cutting ropes
                are springs of rest length 0.2 x their initial length (scale 0.2), so a cut rope snaps back. The
                stretch compliance stays ``l / (E A)`` of the given length ``l``, i.e. a spring constant ``E A / l``.
            inertia_scale: multiplies the segments' rotational inertia (mass scaling of the orientations). A thin,
                heavy rod's segments turn so easily that each stretch-shear projection moves its orientations and
                barely its nodes, so its bending reaches the node positions only over very many sweeps; heavier
                orientations let a quasi-static rod's shape converge at the control rate (equilibria do not
                change; rotational dynamics slow down).
        """
        if not stretch_rest_scale > 0.0:
            raise ValueError(f"stretch_rest_scale must be positive, got {stretch_rest_scale!r}")
        if not inertia_scale > 0.0:
            raise ValueError(f"inertia_scale must be positive, got {inertia_scale!r}")
        x = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        m = len(x)
        nseg = m if closed else m - 1
        if nseg < 1:
            raise ValueError("a rod needs at least 2 points")
        seg = np.stack([np.arange(nseg), (np.arange(nseg) + 1) % m], axis=1)
        L = np.linalg.norm(x[seg[:, 1]] - x[seg[:, 0]], axis=1)
        area = np.pi * radius**2
        mass_base = np.zeros(m)
        np.add.at(mass_base, seg.ravel(), np.repeat(0.5 * area * L, 2))
        sl = self._add_points(x, mass_base, density, damping, fixed)
        off = sl.start
        # parallel-transported frames, d3 along each segment
        tang = (x[seg[:, 1]] - x[seg[:, 0]]) / L[:, None]
        ref = np.array([0.0, 0.0, 1.0]) if abs(tang[0, 2]) < 0.9 else np.array([1.0, 0.0, 0.0])
        d1 = np.cross(ref, tang[0])
        d1 /= np.linalg.norm(d1)
        quats = []
        for s in range(nseg):
            if s > 0:
                proj = d1 - np.dot(d1, tang[s]) * tang[s]
                if np.linalg.norm(proj) > 1e-6:
                    d1 = proj / np.linalg.norm(proj)
                else:
                    # the rod turns so that d1 lies along the new tangent (a right-angled corner): projecting leaves
                    # nothing (a NaN frame), so d1 is rotated with the tangent instead (Rodrigues, about their normal)
                    axis = np.cross(tang[s - 1], tang[s])
                    sin, cos = np.linalg.norm(axis), float(np.dot(tang[s - 1], tang[s]))
                    k = axis / sin
                    d1 = d1 * cos + np.cross(k, d1) * sin + k * np.dot(k, d1) * (1.0 - cos)
                    d1 = d1 - np.dot(d1, tang[s]) * tang[s]
                    d1 /= np.linalg.norm(d1)
            d2 = np.cross(tang[s], d1)
            quats.append(_quat_from_frame(d1, d2, tang[s]))
        quats = np.asarray(quats)
        # quaternion inverse mass 1 / (4 I), I = m (r^2/4 + l^2/12) (scalar inertia of a short cylinder)
        inertia_base = area * L * (radius**2 / 4.0 + L**2 / 12.0) * float(inertia_scale)
        E = _per_env(youngs_modulus, "youngs_modulus")
        G = _per_env(shear_modulus if shear_modulus is not None else E / 2.0, "shear_modulus")
        I_b = np.pi * radius**4 / 4.0
        J = np.pi * radius**4 / 2.0
        # stretch-shear: energy 0.5 l (G A g1^2 + G A g2^2 + E A g3^2) -> compliance 1/(k A l) per axis.
        # The stretch axis is solved as a segment distance constraint (compliance l / (E A)) by the direct
        # per-rod chain solver (kernels/chains.py), exact along the whole rod in one sweep; along d3 a lagging
        # orientation would stretch the rod sideways. A negative z compliance tells the stretch-shear kernel
        # to skip that axis.
        ss_geom = np.stack([1.0 / (area * L), 1.0 / (area * L), -1.0 / (area * L)], axis=1)
        P = max(len(E), len(G))
        Eb = np.broadcast_to(E, (P,))
        Gb = np.broadcast_to(G, (P,))
        ss_scale = np.stack([1.0 / Gb, 1.0 / Gb, 1.0 / Eb], axis=1)[:, None, :]
        self._rod_stretch.indices.append(np.array([[off, self._nseg, nseg, int(closed)]], dtype=np.int64))
        # rest lengths as the kernel measures them (float32 differences of float32 coordinates), so a rod at
        # rest has C = 0 exactly instead of rounding residuals that the global solve spreads along the rod
        x32 = x.astype(np.float32)
        d32 = x32[seg[:, 1]] - x32[seg[:, 0]]
        rest = np.sqrt(d32[:, 0] * d32[:, 0] + d32[:, 1] * d32[:, 1] + d32[:, 2] * d32[:, 2])
        self._rod_stretch.rest.append(rest if stretch_rest_scale == 1.0 else rest * float(stretch_rest_scale))
        self._rod_stretch.geom.append(L / area)
        self._rod_stretch.scale.append((1.0 / Eb)[:, None])
        self._segments.indices.append(np.concatenate([seg + off, (np.arange(nseg) + self._nseg)[:, None]], axis=1))
        self._segments.rest.append(L)
        self._segments.geom.append(ss_geom)
        self._segments.scale.append(ss_scale)
        seg_sl = slice(self._nseg, self._nseg + nseg)
        self._seg_q.append(quats)
        self._seg_inertia_base.append(inertia_base)
        self._seg_density.append((seg_sl, _per_env(density, "density")))
        self._seg_damping.append((seg_sl, _per_env(damping if angular_damping is None else angular_damping,
                                                   "angular_damping")))
        if fixed_orientations is not None:
            self._seg_fixed.append(np.asarray(fixed_orientations, dtype=np.int64).reshape(-1) + self._nseg)
        # bend-twist between consecutive segments: energy 0.5 l (EI k1^2 + EI k2^2 + GJ tau^2) with the
        # Darboux vector Omega ~ l k / 2 -> compliance l / (4 EI) (bend) and l / (4 GJ) (twist)
        nb = nseg if closed else nseg - 1
        if nb > 0:
            bs = np.stack([np.arange(nb), (np.arange(nb) + 1) % nseg], axis=1)
            lb = 0.5 * (L[bs[:, 0]] + L[bs[:, 1]])
            if rest_curvature:
                rest = np.asarray([_quat_mul(_quat_conj(quats[a]), quats[b]) for a, b in bs])
            else:
                rest = np.tile([0.0, 0.0, 0.0, 1.0], (nb, 1))
            self._bends.indices.append(bs + self._nseg)
            self._bends.rest.append(rest)
            self._bends.geom.append(np.stack([lb / (4.0 * I_b), lb / (4.0 * I_b), lb / (4.0 * J)], axis=1))
            self._bends.scale.append(np.stack([1.0 / Eb, 1.0 / Eb, 1.0 / Gb], axis=1)[:, None, :])
        obj = SceneObject(name, "rod", sl.start, m, edges=(seg + off).astype(np.int32), segment_start=self._nseg,
                          segment_count=nseg, closed=closed, fixed=self._fixed_of(sl), cuttable=bool(cuttable))
        self._cuttable |= bool(cuttable)
        self._nseg += nseg
        self.objects.append(obj)
        return obj

    # ---------------------------------------------------------------------------------------------
    def add_body(self, name: str, pose=None) -> int:
        """A kinematic rigid body (e.g. an instrument jaw) whose pose the env layer writes each step into
        ``world.state.body_q[env, body]``; particles attach to it. ``pose`` is (px, py, pz, qx, qy, qz, qw)."""
        p = np.asarray(pose if pose is not None else (0, 0, 0, 0, 0, 0, 1), dtype=np.float64)
        self._bodies.append((name, p))
        return len(self._bodies) - 1

    def add_attachment(self, particle: int, body: int = -1, compliance: float = 0.0, offset=None) -> int:
        """Attach global ``particle`` to kinematic ``body`` (-1: a fixed point in the world) with a
        compliance in m/N. ``offset`` (body frame) defaults to the particle's initial position seen from the
        body's initial pose, so the attachment starts relaxed. Returns its slot (column of the ``attach_*`` state
        arrays)."""
        if offset is None:
            x = self._pos_all()[particle]
            if body >= 0:
                pose = [float(v) for v in self._bodies[body][1]]
                tf = wp.transform(wp.vec3(*pose[:3]), wp.quat(*pose[3:]))
                offset = np.asarray(wp.transform_point(wp.transform_inverse(tf), wp.vec3(*[float(c) for c in x])))
            else:
                offset = x
        self._attachments.append((int(particle), int(body), np.asarray(offset, dtype=np.float64), float(compliance)))
        return len(self._attachments) - 1

    # ---------------------------------------------------------------------------------------------
    def finalize(
        self,
        num_envs: int,
        device: str | None = None,
        substeps: int | None = None,
        iterations: int = 1,
        attachment_capacity: int = 0,
        seed: int = 0,
        max_speed: float = 50.0,
        auto_reset_unstable: bool = True,
        edge_solver: str = "chains",
        per_env_materials: bool = False,
        tet_colors: str = "greedy",
    ):
        """Build the batched ``World`` of ``num_envs`` copies of this scene on ``device``.

        Args:
            num_envs: number of independent envs.
            device: Warp device name (``"cpu"``, ``"cuda:0"``); None = Warp's default.
            substeps: XPBD substeps per ``world.step``; None (default) = automatic: at least 10 (cloth edge chains
                and rods converge there), and for tet meshes enough that a substep resolves the fastest elastic
                wave across the stiffest tet (``h c / l_min <= 0.7``, P-wave speed ``c``), where one sweep per
                substep reaches the material's stiffness (fewer substeps make stiff tets too soft); see
                ``World.substeps_for``.
            iterations: constraint sweeps per substep.
            attachment_capacity: attachment slots per env (at least the static attachments); grasping
                code writes new ones into ``state.attach_*``.
            seed: per-env RNG seed.
            max_speed: speed in m/s above which an env is flagged unstable.
            auto_reset_unstable: restore envs flagged unstable at the end of each step.
            edge_solver: ``"chains"`` (default): the distance constraints (cloth edges, springs) are split into
                straight chains solved directly, one linear-time solve per chain and sweep (``lapwarp.chains``), so
                a cloth keeps its length at the control rate without tethers; ``"colored"``: one Gauss-Seidel
                projection per constraint, colour by colour (cheaper per sweep, converges slowly on long paths).
            per_env_materials: give every env its own row of every material array (stiffness, damping, mass), so
                ``World.set_materials`` can change them per env at reset (domain randomisation of materials).
            tet_colors: how the tets are coloured for the XPBD sweep: ``"greedy"`` (default: plain greedy colours,
                the order every task's XPBD tets were tuned on) or ``"packed"`` (:func:`pack_colors` for the fused
                sweep's ``TET_BLOCK_LANES`` lanes: fewer passes per sweep, e.g. LigatingLoop's cavity 72 instead of
                78; another Gauss-Seidel order, so a body's shape after a step differs slightly).
        """
        from lapwarp.chains import build_chain_set, straight_chains
        from lapwarp.world import World

        if edge_solver not in ("chains", "colored"):
            raise ValueError(f"edge_solver={edge_solver!r} is not 'chains' or 'colored'")
        if tet_colors not in ("greedy", "packed"):
            raise ValueError(f"tet_colors={tet_colors!r} is not 'greedy' or 'packed'")
        dev = wp.get_device(device)
        N = int(num_envs)
        n = self._n

        def per_env_rows(lst, total, shape_tail=()):
            P = max([len(v) for _, v in lst] + [1])
            if P not in (1, N):
                raise ValueError(f"per-env parameter has {P} values but num_envs is {N}")
            return P

        model = Model(num_envs=N, device=str(dev), gravity=wp.vec3(*self.gravity), particle_count=n)
        model.max_speed = float(max_speed)
        model.max_substep = 0.7 / self._tet_omega if self._tet_omega > 0.0 else float("inf")
        model.objects = list(self.objects)
        f32 = np.float32
        state = State()
        if n:
            x = np.concatenate(self._pos)
            mb = np.concatenate(self._mass_base)
            P = per_env_rows(self._density, n)
            mass = np.empty((P, n))
            for sl, dens in self._density:
                mass[:, sl] = mb[None, sl] * (dens[:, None] if len(dens) == P else dens[0])
            inv = np.zeros_like(mass)
            np.divide(1.0, mass, out=inv, where=mass > 0)
            fixed = np.concatenate(self._fixed) if self._fixed else np.zeros(0, dtype=np.int64)
            inv[:, fixed] = 0.0
            model.particle_inv_mass = wp.array(inv.astype(f32), dtype=float, device=dev)
            P = per_env_rows(self._damping, n)
            damp = np.empty((P, n))
            for sl, d in self._damping:
                damp[:, sl] = d[:, None] if len(d) == P else d[0]
            model.particle_damping = wp.array(damp.astype(f32), dtype=float, device=dev)
            xq = np.broadcast_to(x.astype(f32), (N, n, 3))
            state.particle_q = wp.array(np.ascontiguousarray(xq), dtype=wp.vec3, device=dev)
            state.particle_qd = wp.zeros((N, n), dtype=wp.vec3, device=dev)

        def scales(g: _Group, N: int):
            P = max([s.shape[0] for s in g.scale] + [1])
            if P not in (1, N):
                raise ValueError(f"per-env parameter has {P} values but num_envs is {N}")
            return P

        def build_comp(g: _Group, order) -> np.ndarray:
            P = scales(g, N)
            parts = []
            for geom, sc in zip(g.geom, g.scale, strict=True):
                v = geom[None, ...] * (sc if sc.shape[0] == P else np.repeat(sc, P, axis=0))
                parts.append(np.broadcast_to(v, (P,) + geom.shape) if v.shape[0] == 1 and P == 1 else v)
            comp = np.concatenate(parts, axis=1)
            return np.ascontiguousarray(comp[:, order].astype(f32))

        # edges -----------------------------------------------------------------------------------
        if self._edges.count():
            idx = np.concatenate(self._edges.indices)
            order, offs = color_graph(idx)
            model.edge_count = len(idx)
            model.edge_indices = wp.array(idx[order].astype(np.int32), dtype=wp.vec2i, device=dev)
            model.edge_rest = wp.array(np.concatenate(self._edges.rest)[order].astype(f32), dtype=float, device=dev)
            model.edge_compliance = wp.array(build_comp(self._edges, order), dtype=float, device=dev)
            model.edge_color_offsets = offs
            if edge_solver == "chains":
                model.edge_chains = build_chain_set(straight_chains(idx[order], x), n, dev)
            if self._cuttable:
                etri = np.concatenate(self._edge_tris)[order]
                model.edge_tris = wp.array(etri.astype(np.int32), dtype=wp.vec2i, device=dev)
        if self._hinges.count():
            idx = np.concatenate(self._hinges.indices)
            order, offs = color_graph(idx)
            model.hinge_count = len(idx)
            model.hinge_indices = wp.array(idx[order].astype(np.int32), dtype=wp.vec4i, device=dev)
            model.hinge_rest = wp.array(np.concatenate(self._hinges.rest)[order].astype(f32), dtype=float,
                                        device=dev)
            model.hinge_compliance = wp.array(build_comp(self._hinges, order), dtype=float, device=dev)
            model.hinge_color_offsets = offs
            if self._cuttable:
                htri = np.concatenate(self._hinge_tris)[order]
                model.hinge_tris = wp.array(htri.astype(np.int32), dtype=wp.vec2i, device=dev)
        if self._tets.count():
            idx = np.concatenate(self._tets.indices)
            # plain greedy colours unless asked to pack them: the XPBD tets' shape after a step depends on the
            # Gauss-Seidel order (not converged per sweep), and repacked colours moved TissueManipulation's traced
            # reachable polygons to 0.85 IoU of the stored ones and failed experts that were tuned on this order
            if tet_colors == "packed":
                order, offs = pack_colors(idx, TET_BLOCK_LANES)
            else:
                order, offs = color_graph(idx)
            model.tet_count = len(idx)
            model.tet_indices = wp.array(idx[order].astype(np.int32), dtype=wp.vec4i, device=dev)
            model.tet_inv_rest = wp.array(np.concatenate(self._tets.rest)[order].astype(f32), dtype=wp.mat33,
                                          device=dev)
            P = scales(self._tets, N)
            params = np.concatenate([s if s.shape[0] == P else np.repeat(s, P, axis=0) for s in self._tets.scale],
                                    axis=1)
            model.tet_params = wp.array(np.ascontiguousarray(params[:, order].astype(f32)), dtype=wp.vec3,
                                        device=dev)
            model.tet_color_offsets = offs
            model.tet_element = wp.array(order.astype(np.int32), dtype=wp.int32, device=dev)
            model.tet_elements = wp.array(idx.astype(np.int32), dtype=wp.vec4i, device=dev)
            # faces 4 t + k of tet t, wound outwards, and the tet across each face (shared topology, built once)
            faces = np.stack([idx[:, [1, 2, 3]], idx[:, [0, 3, 2]], idx[:, [0, 1, 3]], idx[:, [0, 2, 1]]],
                             axis=1).reshape(-1, 3)
            _, finv = np.unique(np.sort(faces, axis=1), axis=0, return_inverse=True)
            finv = finv.ravel()
            forder = np.argsort(finv, kind="stable")
            nbr = np.full(len(faces), -1, dtype=np.int64)
            same = finv[forder[1:]] == finv[forder[:-1]]
            a, b = forder[:-1][same], forder[1:][same]
            nbr[a], nbr[b] = b // 4, a // 4
            model.tet_face_indices = wp.array(faces.astype(np.int32), dtype=wp.vec3i, device=dev)
            model.tet_face_neighbor = wp.array(nbr.astype(np.int32), dtype=wp.int32, device=dev)
            self._tet_face_boundary = (nbr < 0).astype(np.int32)
        if self._geodesic:
            _build_geodesic_tethers(model, state, self._geodesic, x, N, dev)
        # rods ------------------------------------------------------------------------------------
        if self._nseg:
            S = self._nseg
            idx = np.concatenate(self._segments.indices)  # (S, 3): p0, p1, segment id
            nodes = idx.copy()
            nodes[:, 2] += n  # segments are nodes too: one writer per quaternion per colour
            order, offs = color_graph(nodes)
            model.segment_count = S
            # constraint arrays are in colour order; per-segment arrays (inertia, damping, state) keep the
            # insertion order so SceneObject.segments slices the state
            model.segment_particles = wp.array(idx[order].astype(np.int32), dtype=wp.vec3i, device=dev)
            model.segment_rest = wp.array(np.concatenate(self._segments.rest)[order].astype(f32), dtype=float,
                                          device=dev)
            model.segment_compliance = wp.array(build_comp(self._segments, order), dtype=wp.vec3, device=dev)
            model.segment_color_offsets = offs
            ib = np.concatenate(self._seg_inertia_base)
            P = per_env_rows(self._seg_density, S)
            inertia = np.empty((P, S))
            for sl, dens in self._seg_density:
                inertia[:, sl] = ib[None, sl] * (dens[:, None] if len(dens) == P else dens[0])
            wq = 1.0 / (4.0 * inertia)
            if self._seg_fixed:
                wq[:, np.concatenate(self._seg_fixed)] = 0.0
            model.segment_inv_inertia = wp.array(wq.astype(f32), dtype=float, device=dev)
            P = per_env_rows(self._seg_damping, S)
            sd = np.empty((P, S))
            for sl, d in self._seg_damping:
                sd[:, sl] = d[:, None] if len(d) == P else d[0]
            model.segment_damping = wp.array(sd.astype(f32), dtype=float, device=dev)
            sq = np.concatenate(self._seg_q).astype(f32)
            state.segment_q = wp.array(np.ascontiguousarray(np.broadcast_to(sq, (N, S, 4))), dtype=wp.quat, device=dev)
            state.segment_qd = wp.zeros((N, S), dtype=wp.vec3, device=dev)
            # direct stretch solve: one chain per rod, per-segment data in insertion order
            rows = np.concatenate(self._rod_stretch.indices)
            model.rod_count = len(rows)
            model.rod_chains = build_chain_set(
                [(list(range(p0, p0 + m + (0 if closed else 1))), list(range(s0, s0 + m)), bool(closed))
                 for p0, s0, m, closed in rows.tolist()], n, dev)
            model.rod_stretch_rest = wp.array(np.concatenate(self._rod_stretch.rest).astype(f32), dtype=float,
                                              device=dev)
            model.rod_stretch_compliance = wp.array(build_comp(self._rod_stretch, np.arange(S)), dtype=float,
                                                    device=dev)
            if self._bends.count():
                bidx = np.concatenate(self._bends.indices)
                border, boffs = color_graph(bidx)
                model.bend_count = len(bidx)
                model.bend_segments = wp.array(bidx[border].astype(np.int32), dtype=wp.vec2i, device=dev)
                model.bend_rest = wp.array(np.concatenate(self._bends.rest)[border].astype(f32), dtype=wp.quat,
                                           device=dev)
                model.bend_compliance = wp.array(build_comp(self._bends, border), dtype=wp.vec3, device=dev)
                model.bend_color_offsets = boffs
        if self._tris:
            tris = np.concatenate(self._tris)
            model.tri_count = len(tris)
            model.tri_indices = wp.array(tris.astype(np.int32), dtype=wp.vec3i, device=dev)
        if self._cuttable:
            # per-env active masks (all present); reset restores them with the rest of the state
            if model.tet_count:
                state.tet_active = wp.ones((N, model.tet_count), dtype=wp.int32, device=dev)
                fa = np.broadcast_to(self._tet_face_boundary, (N, 4 * model.tet_count))
                state.tet_face_active = wp.array(np.ascontiguousarray(fa), dtype=wp.int32, device=dev)
            if model.tri_count:
                state.tri_active = wp.ones((N, model.tri_count), dtype=wp.int32, device=dev)
                state.edge_active = wp.ones((N, model.edge_count), dtype=wp.int32, device=dev)
                if model.hinge_count:
                    state.hinge_active = wp.ones((N, model.hinge_count), dtype=wp.int32, device=dev)
            if model.segment_count:
                state.segment_active = wp.ones((N, model.segment_count), dtype=wp.int32, device=dev)
            # 1 = surfaces / connectivity of this env must be recomputed: set at build and restored as 1 by reset
            state.cut_dirty = wp.ones((N, 1), dtype=wp.int32, device=dev)
            # 0 once every element holding the particle is gone (CuttingSystem); contact skips such particles
            state.particle_active = wp.ones((N, max(model.particle_count, 1)), dtype=wp.int32, device=dev)
        # bodies and attachments -----------------------------------------------------------------
        model.body_count = len(self._bodies)
        model.body_names = [b[0] for b in self._bodies]
        if self._bodies:
            poses = np.stack([b[1] for b in self._bodies]).astype(f32)
            state.body_q = wp.array(np.ascontiguousarray(np.broadcast_to(poses, (N, len(poses), 7))),
                                    dtype=wp.transform, device=dev)
        cap = max(int(attachment_capacity), len(self._attachments))
        model.attachment_capacity = cap
        static_particles = [a[0] for a in self._attachments]
        model.attachments_distinct = cap == len(static_particles) and len(set(static_particles)) == cap
        if cap:
            ap = np.full((N, cap), -1, dtype=np.int32)
            ab = np.full((N, cap), -1, dtype=np.int32)
            ao = np.zeros((N, cap, 3), dtype=f32)
            ac = np.zeros((N, cap), dtype=f32)
            for k, (p, b, o, c) in enumerate(self._attachments):
                ap[:, k], ab[:, k], ao[:, k], ac[:, k] = p, b, o, c
            state.attach_particle = wp.array(ap, dtype=wp.int32, device=dev)
            state.attach_body = wp.array(ab, dtype=wp.int32, device=dev)
            state.attach_offset = wp.array(ao, dtype=wp.vec3, device=dev)
            state.attach_compliance = wp.array(ac, dtype=float, device=dev)
            # held rod segments (grasping writes them; the attachment pass turns a held segment with its body)
            state.attach_segment = wp.array(np.full((N, cap), -1, dtype=np.int32), dtype=wp.int32, device=dev)
            rot = np.zeros((N, cap, 4), dtype=f32)
            rot[..., 3] = 1.0
            state.attach_rotation = wp.array(rot, dtype=wp.quat, device=dev)
            model.attach_hold_up = wp.zeros(cap, dtype=wp.vec3, device=dev)
        surf = [o.surface_tris for o in self.objects if o.surface_tris is not None and len(o.surface_tris)]
        if surf:
            model.surface_tris = wp.array(np.concatenate(surf).astype(np.int32), dtype=wp.vec3i, device=dev)
        if per_env_materials:
            # one row per env of every material array, and the built values to scale from (World.set_materials)
            for name in MATERIAL_ARRAYS:
                arr = getattr(model, name)
                if arr is None:
                    continue
                if arr.shape[0] != N:
                    arr = wp.array(np.ascontiguousarray(np.repeat(arr.numpy(), N, axis=0)), dtype=arr.dtype,
                                   device=dev)
                    setattr(model, name, arr)
                model.material_base[name] = wp.clone(arr)
        return World(model, state, seed=seed, substeps=substeps, iterations=iterations,
                     auto_reset_unstable=auto_reset_unstable)
