"""Contact for a World: particles and rod segments against analytic and mesh colliders, particle-particle
contact (deformable vs deformable, rod self-contact), Coulomb friction and per-env contact reports.

A :class:`ContactSystem` is described on the host (shapes, particle groups, self-contact sets) and then
``finalize()``-d once: it allocates fixed-capacity device arrays and registers itself with
``world.add_solver``. From then on every substep sweep of ``world.step`` also runs its recorded launches, so
contact is part of the env's captured graph and never syncs with the host.

Shapes are shared by all envs. A shape is either static (``body=-1``, placed by ``transform`` in the env
frame; physics runs at the origin in every env) or rides on a kinematic body ``state.body_q[env, body]`` with
``transform`` as its offset in the body frame. Kinds: sphere, capsule (axis = local z), box, plane (the
half-space below the local xy plane), cylinder (axis = local z) and static triangle meshes (one ``wp.Mesh``
shared by all envs, closed and wound outwards).

Reports (see ``docs/contact.md``): ``report_count[env, pair]`` = contacts found in the last substep of the
last ``world.step`` and ``report_force[env, pair]`` = summed normal force averaged over that step (N), for
each (shape, particle group) pair and each self-contact set (the forces only with ``report_forces``, the
default). They are cleared by the first sweep of every
``world.step`` (a launch inside the recorded step), so after a step they describe exactly that step.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import warp as wp

from lapwarp import launching
from lapwarp.kernels import contact as ck
from lapwarp.kernels.geometry import BodyMotion
from lapwarp.launching import make_struct
from lapwarp.surface_clusters import SurfaceClusters

# particle-particle sets with at least this many members per env use the per-env cell list (measured on CPU,
# see docs/contact.md: brute force costs M^2 pair tests, the cell list ~27 buckets + a scan per sweep)
GRID_THRESHOLD = 512
#: triangles per leaf of a deforming surface's clustering (``ContactSystem.surface_leaf_size``'s default; a
#: benchmark may set it before the envs are built, since a task finalizes its contact system when it builds)
SURFACE_LEAF_SIZE = 8
#: whether consecutive shapes on one body are culled as a group first (``ContactSystem.cull_groups``' default; a
#: benchmark may clear it before the envs are built, to time the groups against their absence)
CULL_GROUPS = True
#: ``ContactSystem.pose_per_step``'s default (a benchmark may clear it before the envs are built, to time it): on since
#: the forty-third session (H200, 4,096 envs, expert, same call, off -> on: RopeThreading 189.6k -> 191.8k, RopeCutting
#: 322.9k -> 325.4k, ThreadInHole 199.9k -> 200.4k, TissueDissection 262.0k -> 263.0k, LigatingLoop 101.2k / 101.1k;
#: bit-identical on the CPU)
POSE_PER_STEP = True

_KINDS = {"sphere": 0, "capsule": 1, "box": 2, "plane": 3, "cylinder": 4, "mesh": 5, "surface": 6}


def _transform(tf) -> wp.transform:
    if tf is None:
        return wp.transform_identity()
    if isinstance(tf, wp.transform):
        return tf
    v = [float(c) for c in np.asarray(tf, dtype=np.float64).reshape(-1)]
    if len(v) == 3:
        return wp.transform(wp.vec3(*v), wp.quat_identity())
    if len(v) == 7:
        return wp.transform(wp.vec3(*v[:3]), wp.quat(*v[3:]))
    raise ValueError(f"transform must be (px, py, pz) or (px, py, pz, qx, qy, qz, qw), got {len(v)} values")


@dataclass
class Shape:
    """One collider (host description)."""

    name: str
    kind: str
    params: tuple
    body: int
    transform: wp.transform
    thickness: float
    mu_static: float
    mu_kinetic: float
    groups: tuple | None  # particle group ids it collides with (None: all)
    mesh: wp.Mesh | None = None
    surface: dict | None = None  # deforming surface: tris (F, 3) global, owner (start, end), closed


@dataclass
class ParticleGroup:
    """A set of particles that collide with shapes (rod nodes, cloth vertices, tet surface vertices)."""

    name: str
    particles: np.ndarray  # global particle indices
    radius: float
    segments: np.ndarray | None  # (S, 2) global node indices of rod segments for segment-level contact
    triangles: np.ndarray | None = None  # (F, 3) global vertex indices of cloth / surface triangles
    # cutting: mask column of each segment / triangle (-1 = never removed; triangles: >= 0 tri_active column,
    # <= -2 tet face -2 - col of tet_face_active), None when the object is not cuttable
    seg_col: np.ndarray | None = None
    tri_col: np.ndarray | None = None
    # a tet mesh's face shared by two tets: the other tet's face column (-1: a boundary face or not a tet face)
    tri_col2: np.ndarray | None = None


def _bounding_radius(shape: Shape) -> float:
    """Radius about the shape's local origin that holds all of it (``inf``: planes, meshes and surfaces, never
    culled by it). Rounded up by 1e-6 m and 1e-4 relative so the float32 cull never drops a touching particle."""
    r, h, z = (list(shape.params) + [0.0, 0.0, 0.0])[:3]
    if shape.kind == "sphere":
        bound = r
    elif shape.kind == "capsule":
        bound = h + r
    elif shape.kind == "box":
        bound = float(np.linalg.norm([r, h, z]))
    elif shape.kind == "cylinder":
        bound = float(np.hypot(r, h))
    else:
        return float("inf")
    return bound * (1.0 + 1.0e-4) + 1.0e-6


def _cull_groups(shapes: list[Shape], grouped: bool = True) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The particles' cull groups (``ck.ShapePoses``): runs of consecutive shapes on one body with finite bounds,
    each shape of infinite bound (planes, meshes, surfaces) a group of its own; with ``grouped`` False every shape
    alone (the kernels then skip the group test: a group of one is left to its shape's own cull). Returns
    ``group_start`` (G + 1), each group's centre in its first shape's frame (the mean of its shapes' origins) and its
    radius: the largest distance from the centre to a shape's origin plus that shape's bound and thickness (rounded up
    as the bounds are)."""
    if not shapes:  # the kernels loop over no group
        return np.zeros(1, np.int32), np.zeros((1, 3), np.float32), np.zeros(1, np.float32)
    bounds = [_bounding_radius(s) for s in shapes]
    start = [0]
    for k in range(1, len(shapes)):
        joins = grouped and shapes[k].body == shapes[k - 1].body and np.isfinite(bounds[k]) \
            and np.isfinite(bounds[k - 1])
        if not joins:
            start.append(k)
    start.append(len(shapes))
    centres, radii = [], []
    for a, b in zip(start[:-1], start[1:], strict=True):
        first = wp.transform_inverse(shapes[a].transform)
        origins = np.array([wp.transform_point(first, wp.transform_get_translation(shapes[k].transform))
                            for k in range(a, b)], dtype=np.float64).reshape(-1, 3)
        centre = origins.mean(axis=0)
        reach = max(float(np.linalg.norm(o - centre)) + bounds[k] + shapes[k].thickness
                    for o, k in zip(origins, range(a, b), strict=True))
        centres.append(centre)
        radii.append(reach * (1.0 + 1.0e-4) + 1.0e-6 if np.isfinite(reach) else np.inf)
    return (np.asarray(start, np.int32), np.asarray(centres, np.float32), np.asarray(radii, np.float32))


class ContactSystem:
    """Contact between the particles of a World and colliders, plus particle-particle contact.

    Args:
        world: the World whose particles collide (its ``state.body_q`` poses the body-mounted shapes).
        capacity: contact records kept per env per step (``contacts()``); more raise ``overflow[env]``.
        report_margin: distance (m) below contact at which a particle counts as touching in the reports and
            the contact records (a resting particle sits exactly at the contact distance).
        body_ignore_mask: allocate ``ignore_bodies`` ``(num_envs, particle_count)`` int32: bit ``b`` set for a
            particle makes it pass through the shapes of body ``b`` (grasping sets it for held particles).

    Attributes (after ``finalize``):
        report_count: ``(num_envs, num_pairs)`` int32 contacts per pair in the last substep of the last step.
        report_force: ``(num_envs, num_pairs)`` float32 summed normal force per pair, averaged over the step (N).
        contact_count: ``(num_envs,)`` int32 contact records of the last step (at most ``capacity``: a record past it
            takes the count back and raises ``overflow``).
        contact_particle, contact_shape: ``(num_envs, capacity)`` int32 records (particle, shape index).
        contact_normal: ``(num_envs, capacity)`` vec3 world normal pointing from the shape to the particle.
        contact_depth: ``(num_envs, capacity)`` float penetration before projection (m, > -report_margin).
        overflow: ``(num_envs,)`` int32, 1 when the records of that env did not fit in ``capacity``.
        pair_names: name of every report column, ``"shape/group"`` or the self-contact set's name.
        shape_table, reports, ignore: the colliders, the reports and records above, and the ``ignore_bodies`` mask
            as the ``wp.struct`` bundles of :mod:`lapwarp.kernels.contact` (``ShapeTable``, ``ContactReports``,
            ``IgnoreMask``) that the contact and grasping kernels take.
    """

    def __init__(self, world, capacity: int = 64, report_margin: float = 1.0e-4, body_ignore_mask: bool = False):
        self.world = world
        self.body_ignore_mask = bool(body_ignore_mask)
        self.device = world.device
        self.num_envs = world.num_envs
        self.capacity = int(capacity)
        self.report_margin = float(report_margin)
        # triangle contact: "colored" = one launch per colour of triangles; "fused" = every colour in one launch, a
        # thread block of triangle_block_threads per env with a barrier between colours (ck.collide_triangle_colors);
        # "outcodes" = the fused sweep with the box cull read from per-particle outcodes in shared memory (the same
        # contacts, fewer loads in series: ck.collide_triangle_outcodes_kernel); "auto" = "outcodes" where the
        # triangles' particle window fits its shared memory, else "fused" (the outcode sweep was 4.5 % faster on
        # TissueDissection's STATE step and 2.6 % on PrecisionCutting's, 4,096 envs on an H200, twenty-ninth session;
        # never slower; a variant starting each env's sweep at its first triangle past the cull gained <= 0.2 %,
        # thirtieth session, and was dropped); "shape_codes" = the outcode sweep with a box per tool along its axis
        # instead of one around all tools (systems of at most ck.SHAPE_CODE_MAX_SHAPES shapes). Read when the World
        # records a step (record_key)
        self.triangle_sweep = "auto"
        self.triangle_block_threads = 32
        # deforming surfaces: triangles per leaf of their clustering (SurfaceClusters; read at finalize)
        self.surface_leaf_size = SURFACE_LEAF_SIZE
        # cull consecutive shapes on one body by their group's bounding sphere first (_cull_groups; read at finalize)
        self.cull_groups = CULL_GROUPS
        # pose the shapes (and the triangle passes' tool axes) of every substep in one launch at a step's first sweep
        # (ck.pose_shapes_substeps, ck.pose_shapes_and_tools_substeps) instead of a launch per sweep: the bodies move
        # only between steps; read when the World records a step (record_key)
        self.pose_per_step = POSE_PER_STEP
        # rod segments' contact colours in one launch per sweep (ck.collide_segment_colors) or a launch each; read when
        # the World records a step
        self.fuse_segment_colors = True
        # deforming surfaces' leaf and super-leaf boxes each sweep: "separate" (``ck.surface_leaf_bounds`` then
        # ``ck.surface_super_bounds``, a thread per box) or "fused" (``ck.surface_bounds_kernel``: one launch, a block
        # of ``surface_bounds_lanes`` threads per env; the same boxes). H200, expert, 4,096 envs, same call:
        # ThreadInHole 216.5k either way, LigatingLoop 101.8k -> 102.1k at 64 lanes, 101.6k at 128 (forty-seventh
        # session; LigatingLoop takes it). Read when the World records a step
        self.surface_bounds = "separate"
        self.surface_bounds_lanes = 64
        # sum each pair's normal force over the step into ``report_force`` (``forces()``): an atomic add per contact
        # and sweep. Off, the contact kernels skip it and ``forces()`` raises (contact counts are still reported).
        # Read when the World records a step
        self.report_forces = True
        # a deforming surface's corrections (averaged per vertex) applied by the next substep's prediction launch where
        # the World can (its particles and rods predicted in one launch that comes next: World launch.defer_deltas)
        # instead of a launch of their own; the same positions. H200, expert, 4,096 envs, same call: ThreadInHole
        # 216.5k -> 217.1k, LigatingLoop 101.8k -> 102.9k env-steps/s (forty-seventh session). Read when the World
        # records a step
        self.defer_surface_deltas = True
        self.shapes: list[Shape] = []
        self.groups: list[ParticleGroup] = []
        self.self_sets: list[dict] = []
        self.pair_names: list[str] = []
        self._finalized = False

    # ------------------------------------------------------------------------------------------------
    # description
    # ------------------------------------------------------------------------------------------------
    def add_particle_group(self, particles, radius: float, name: str | None = None, segments=None,
                           triangles=None) -> int:
        """Particles that collide with the shapes, as spheres of ``radius`` (m).

        Args:
            particles: a ``SceneObject`` (all its particles) or global particle indices / a slice.
            radius: contact radius of each particle (rod radius, half the cloth thickness), m.
            name: report name (defaults to the object's name).
            segments: for rods, ``True`` (the object's edges) or ``(S, 2)`` node pairs: sphere and capsule
                shapes then also collide with the segment interiors, so a thin tool cannot slip between nodes.
            triangles: for cloth / tet meshes, ``True`` (the object's ``surface_tris``) or ``(F, 3)`` vertex
                indices: sphere and capsule shapes then also collide with the triangle interiors (a tool
                moving about its radius per substep cannot pass between the vertices of a sheet).

        Returns:
            The group id.
        """
        self._check_open()
        seg = tri = seg_col = tri_col = tri_col2 = None
        if hasattr(particles, "particle_start"):
            obj = particles
            name = name or obj.name
            if segments is True:
                seg = np.asarray(obj.edges, dtype=np.int64)
                if obj.cuttable and obj.kind == "rod":
                    seg_col = obj.segment_start + np.arange(len(seg))
            if triangles is True:
                tri = np.asarray(obj.surface_tris, dtype=np.int64).reshape(-1, 3)
                if obj.cuttable:
                    tri, tri_col, tri_col2 = self._contact_faces(obj)
                    if obj.kind == "tet_mesh":
                        tri_col = -2 - tri_col
                        tri_col2 = tri_col2.astype(np.int64)
            idx = np.arange(obj.particle_start, obj.particle_start + obj.particle_count)
        elif isinstance(particles, slice):
            idx = np.arange(particles.start, particles.stop)
        else:
            idx = np.asarray(particles, dtype=np.int64).reshape(-1)
        if seg is None and segments is not None and segments is not True and segments is not False:
            seg = np.asarray(segments, dtype=np.int64).reshape(-1, 2)
        if tri is None and triangles is not None and triangles is not True and triangles is not False:
            tri = np.asarray(triangles, dtype=np.int64).reshape(-1, 3)
        self.groups.append(ParticleGroup(name or f"group{len(self.groups)}", idx, float(radius), seg, tri, seg_col,
                                         tri_col, tri_col2))
        return len(self.groups) - 1

    def add_shape(self, kind: str, params=(0.0, 0.0, 0.0), body: int = -1, transform=None, thickness: float = 0.0,
                  mu_static: float = 0.5, mu_kinetic: float | None = None, groups=None, name: str | None = None,
                  mesh: wp.Mesh | None = None) -> int:
        """Add a collider; prefer the typed helpers (``add_sphere`` ...). Returns the shape id.

        Args:
            kind: ``sphere``, ``capsule``, ``box``, ``plane``, ``cylinder`` or ``mesh``.
            params: kind-specific sizes, m (see the helpers).
            body: kinematic body index (``SceneBuilder.add_body``) or -1 for a static shape in the env frame.
            transform: pose in the body frame (or env frame), ``(px, py, pz[, qx, qy, qz, qw])``.
            thickness: contact thickness of this object, m (added to the particle radius).
            mu_static, mu_kinetic: Coulomb friction coefficients (kinetic defaults to static).
            groups: particle group ids this shape collides with (default: all).
            name: report name.
            mesh: the ``wp.Mesh`` of a mesh shape.
        """
        self._check_open()
        if kind not in _KINDS:
            raise ValueError(f"kind {kind!r} is not one of {sorted(_KINDS)}")
        p = tuple(float(v) for v in np.broadcast_to(np.asarray(params, dtype=np.float64).reshape(-1), (3,)))
        mu_k = mu_static if mu_kinetic is None else mu_kinetic
        if mu_k > mu_static + 1e-12:
            raise ValueError(f"mu_kinetic {mu_k} must not exceed mu_static {mu_static}")
        self.shapes.append(Shape(name or f"{kind}{len(self.shapes)}", kind, p, int(body), _transform(transform),
                                 float(thickness), float(mu_static), float(mu_k),
                                 None if groups is None else tuple(int(g) for g in np.atleast_1d(groups)), mesh))
        return len(self.shapes) - 1

    def add_sphere(self, radius: float, **kw) -> int:
        """Sphere of ``radius`` (m) centred at the shape origin."""
        return self.add_shape("sphere", (radius, 0.0, 0.0), **kw)

    def add_capsule(self, radius: float, half_height: float, **kw) -> int:
        """Capsule: points within ``radius`` of the local z segment ``[-half_height, half_height]`` (m)."""
        return self.add_shape("capsule", (radius, half_height, 0.0), **kw)

    def add_box(self, half_extents, **kw) -> int:
        """Box with ``half_extents`` (hx, hy, hz), m."""
        return self.add_shape("box", tuple(half_extents), **kw)

    def add_plane(self, **kw) -> int:
        """Half-space below the local xy plane (normal = local +z); orient it with ``transform``."""
        return self.add_shape("plane", (0.0, 0.0, 0.0), **kw)

    def add_cylinder(self, radius: float, half_height: float, **kw) -> int:
        """Flat-capped cylinder about the local z axis."""
        return self.add_shape("cylinder", (radius, half_height, 0.0), **kw)

    def add_mesh(self, vertices, faces, **kw) -> int:
        """Static triangle mesh shared by all envs (closed, outward winding): one ``wp.Mesh`` (BVH) for all."""
        v = np.ascontiguousarray(np.asarray(vertices, dtype=np.float32).reshape(-1, 3))
        f = np.ascontiguousarray(np.asarray(faces, dtype=np.int32).reshape(-1))
        mesh = wp.Mesh(points=wp.array(v, dtype=wp.vec3, device=self.device),
                       indices=wp.array(f, dtype=wp.int32, device=self.device))
        return self.add_shape("mesh", mesh=mesh, **kw)

    def add_surface(self, obj, thickness: float = 0.0, closed: bool | None = None, **kw) -> int:
        """The deforming triangle surface of a deformable object as a collider for the *other* objects' particle
        groups of the same env (thread through a soft hole, loop around a soft cylinder, rod on tissue).

        The triangles are grouped once from the rest shape into leaves and super leaves (shared by every env,
        :class:`lapwarp.surface_clusters.SurfaceClusters`); before each contact sweep's queries every env's boxes
        are computed from its vertices as they are then. Contact is two-way: the triangle's vertices take their
        mass-weighted share of the correction.

        Args:
            obj: a ``SceneObject`` with ``surface_tris`` (tet mesh surface, cloth triangles) or ``(F, 3)`` global
                vertex indices (then its own vertices are not excluded from colliding with it).
            thickness: extra contact distance on top of the particle radius, m.
            closed: inside/outside from the outward winding (tet surfaces, default for tet meshes); otherwise a
                two-sided sheet where a particle stays on the side it was at the start of the substep.
            **kw: ``mu_static``, ``mu_kinetic``, ``groups``, ``name`` as in :meth:`add_shape`.
        """
        face_col = None
        if hasattr(obj, "particle_start"):
            tris = np.asarray(obj.surface_tris, dtype=np.int64).reshape(-1, 3)
            if obj.cuttable:
                tris, face_col = self._cut_faces(obj)
            owner = (obj.particle_start, obj.particle_start + obj.particle_count)
            closed = obj.kind == "tet_mesh" if closed is None else closed
            kw.setdefault("name", obj.name)
        else:
            tris = np.asarray(obj, dtype=np.int64).reshape(-1, 3)
            owner = (0, 0)
        if len(tris) == 0:
            raise ValueError("the surface has no triangles")
        sid = self.add_shape("surface", thickness=thickness, **kw)
        self.shapes[sid].surface = dict(tris=tris, owner=owner, closed=bool(closed), face_col=face_col,
                                        kind=getattr(obj, "kind", None))
        return sid

    def _cut_faces(self, obj) -> tuple[np.ndarray, np.ndarray]:
        """Triangles of a cuttable object and their columns in its per-env face mask: a cloth's triangles
        (``tri_active``), or *all* ``4 T`` faces of a tet mesh (``tet_face_active``: the current surface,
        including the faces a cut opened; outward wound like ``surface_tris``)."""
        if obj.kind == "cloth":
            return np.asarray(obj.tris, dtype=np.int64).reshape(-1, 3), obj.element_start + np.arange(len(obj.tris))
        if obj.kind == "tet_mesh":
            a, b = 4 * obj.element_start, 4 * (obj.element_start + len(obj.tets))
            return self.world.model.tet_face_indices.numpy()[a:b].astype(np.int64), np.arange(a, b)
        raise ValueError(f"{obj.kind} objects have no triangles")

    def _contact_faces(self, obj) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
        """``_cut_faces`` for the triangle sweeps, a tet mesh's faces merged: every *distinct* face of its ``4 T``
        tet faces, its first tet face's column and the other tet's (-1 on the boundary; no partners for a cloth).

        A face two tets share is one contact triangle: it collides while either column is on (one tet present, the
        other cut), as the two coincident tet faces did one at a time. Contact pushes a triangle to the side its
        tool came from, so the winding (the first tet's) does not matter. Half the interior faces and fewer graph
        colours (TissueDissection's flap: 1,080 tet faces in 46 colours, 658 distinct faces in 28): the fused and
        outcode sweeps take their colours in series, one block barrier each."""
        faces, cols = self._cut_faces(obj)
        if obj.kind != "tet_mesh":
            return faces, cols, None
        _, first, inverse, count = np.unique(np.sort(faces, axis=1), axis=0, return_index=True, return_inverse=True,
                                             return_counts=True)
        if count.max() > 2:
            raise ValueError(f"{obj.name!r}: a face is shared by {int(count.max())} tets (a valid tet mesh shares "
                             "each face between at most two)")
        inverse = inverse.reshape(-1)
        keep = np.sort(first)  # the distinct faces in the order of their first tet face
        last = np.full(len(count), -1, dtype=np.int64)
        np.maximum.at(last, inverse, np.arange(len(faces)))
        second = last[inverse[keep]]  # the face's other occurrence (itself on the boundary)
        return faces[keep], cols[keep], np.where(second != keep, cols[second], -1)

    def add_particle_contact(self, members, skip_links: int = 2, mu_static: float = 0.3,
                             mu_kinetic: float | None = None, name: str = "self", method: str = "auto",
                             grid_threshold: int = GRID_THRESHOLD) -> int:
        """Particle-particle contact among ``members`` (deformable vs deformable and self-contact).

        Args:
            members: list of ``(object_or_indices, radius)``; a rod object is a chain: its nodes closer than
                ``skip_links`` links along the rod (cyclically for closed rods) do not collide with each other.
            skip_links: neighbours along a chain that never collide (they touch at rest); ``radius * 2`` should
                not exceed ``(skip_links + 1)`` segment lengths.
            mu_static, mu_kinetic: friction between the particles.
            name: report column name.
            method: ``"brute"`` (every member against every other of its env), ``"grid"`` (per-env cell list of
                cell size = the largest contact distance: members of the 27 surrounding cells only) or ``"auto"``
                (grid from ``grid_threshold`` members on; the crossover measured on CPU, docs/contact.md).

        Returns:
            The index of the set.
        """
        self._check_open()
        parts, radii, chain, pos, length = [], [], [], [], []
        for c, (obj, radius) in enumerate(members):
            if hasattr(obj, "particle_start"):
                idx = np.arange(obj.particle_start, obj.particle_start + obj.particle_count)
                is_chain = obj.kind == "rod"
                closed = bool(obj.closed)
            else:
                idx = np.asarray(obj, dtype=np.int64).reshape(-1)
                is_chain, closed = False, False
            parts.append(idx)
            radii.append(np.full(len(idx), float(radius)))
            chain.append(np.full(len(idx), c if is_chain else -1))
            pos.append(np.arange(len(idx)))
            length.append(np.full(len(idx), len(idx) if closed else 0))
        mu_k = mu_static if mu_kinetic is None else mu_kinetic
        if method not in ("auto", "brute", "grid"):
            raise ValueError(f"method {method!r} is not auto, brute or grid")
        total = sum(len(p) for p in parts)
        grid = method == "grid" or (method == "auto" and total >= grid_threshold)
        self.self_sets.append(dict(name=name, particles=np.concatenate(parts), radius=np.concatenate(radii),
                                   chain=np.concatenate(chain), pos=np.concatenate(pos),
                                   length=np.concatenate(length), skip=int(skip_links), mu=(mu_static, mu_k),
                                   grid=grid))
        return len(self.self_sets) - 1

    def _check_open(self) -> None:
        if self._finalized:
            raise RuntimeError("the ContactSystem is finalized; describe everything before finalize()")

    # ------------------------------------------------------------------------------------------------
    # build
    # ------------------------------------------------------------------------------------------------
    def finalize(self) -> ContactSystem:
        """Allocate the device arrays and register with ``world.add_solver``. Returns self."""
        self._check_open()
        dev, n = self.device, self.num_envs
        S, G = len(self.shapes), len(self.groups)
        pair = -np.ones((max(S, 1), max(G, 1)), dtype=np.int32)
        names = []
        for s, sh in enumerate(self.shapes):
            for g in range(G):
                if sh.groups is None or g in sh.groups:
                    pair[s, g] = len(names)
                    names.append(f"{sh.name}/{self.groups[g].name}")
        self._self_pair = []
        for ss in self.self_sets:
            self._self_pair.append(len(names))
            names.append(ss["name"])
        self.pair_names = names
        self.num_pairs = len(names)

        def arr(a, dtype):
            return wp.array(a, dtype=dtype, device=dev)

        self.shape_kind = arr(np.array([_KINDS[s.kind] for s in self.shapes] or [0], np.int32), wp.int32)
        self.shape_body = arr(np.array([s.body for s in self.shapes] or [-1], np.int32), wp.int32)
        self.shape_local = wp.array([s.transform for s in self.shapes] or [wp.transform_identity()],
                                    dtype=wp.transform, device=dev)
        self.shape_params = arr(np.array([s.params for s in self.shapes] or [(0, 0, 0)], np.float32), wp.vec3)
        self.shape_mesh = arr(np.array([s.mesh.id if s.mesh is not None else 0 for s in self.shapes] or [0],
                                       np.uint64), wp.uint64)
        self.shape_thickness = arr(np.array([s.thickness for s in self.shapes] or [0], np.float32), float)
        self.shape_mu = arr(np.array([(s.mu_static, s.mu_kinetic) for s in self.shapes] or [(0, 0)], np.float32),
                            wp.vec2)
        if S == 0:  # no shapes: the kernels loop over nothing
            self.shape_kind = wp.zeros(0, dtype=wp.int32, device=dev)
        self.pair_index = arr(pair, wp.int32)
        S1 = max(S, 1)
        group_start, group_centre, group_radius = _cull_groups(self.shapes, bool(self.cull_groups))
        self._shape_poses = make_struct(ck.ShapePoses, tf=wp.zeros((n, S1), dtype=wp.transform, device=dev),
                                        tf_inv=wp.zeros((n, S1), dtype=wp.transform, device=dev),
                                        bound=arr(np.array([_bounding_radius(s) for s in self.shapes] or [0.0],
                                                           np.float32), float),
                                        group_start=arr(group_start, wp.int32), group_centre=arr(group_centre, wp.vec3),
                                        group_radius=arr(group_radius, float))
        self.shape_table = make_struct(ck.ShapeTable, kind=self.shape_kind, body=self.shape_body,
                                       local=self.shape_local, params=self.shape_params, mesh=self.shape_mesh,
                                       thickness=self.shape_thickness, mu=self.shape_mu, pair_index=self.pair_index)

        cp = [g.particles for g in self.groups]
        cp_all = np.concatenate(cp).astype(np.int64) if cp else np.zeros(0, np.int64)
        cp_groups = np.concatenate([np.full(len(g.particles), k) for k, g in enumerate(self.groups)]) if cp else []
        self.cp_particle = arr(np.concatenate(cp).astype(np.int32) if cp else np.zeros(0, np.int32), wp.int32)
        self.cp_group = arr(np.concatenate([np.full(len(g.particles), k) for k, g in enumerate(self.groups)])
                            .astype(np.int32) if cp else np.zeros(0, np.int32), wp.int32)
        self.cp_radius = arr(np.concatenate([np.full(len(g.particles), g.radius) for g in self.groups])
                             .astype(np.float32) if cp else np.zeros(0, np.float32), float)
        self._particles = make_struct(ck.ContactParticles, particle=self.cp_particle, group=self.cp_group,
                                      radius=self.cp_radius)

        # rod segments, graph-coloured so one launch per colour touches disjoint nodes
        from lapwarp.builder import color_graph

        segs, sgrp, srad = [], [], []
        for k, g in enumerate(self.groups):
            if g.segments is not None:
                segs.append(g.segments)
                sgrp.append(np.full(len(g.segments), k))
                srad.append(np.full(len(g.segments), g.radius))
        self.seg_color_offsets = [0]
        if segs:
            seg_all = np.concatenate(segs)
            order, self.seg_color_offsets = color_graph(seg_all)
            self.seg_nodes = arr(seg_all[order].astype(np.int32), wp.vec2i)
            self.seg_group = arr(np.concatenate(sgrp)[order].astype(np.int32), wp.int32)
            self.seg_radius = arr(np.concatenate(srad)[order].astype(np.float32), float)
            self._segments = make_struct(ck.ContactSegments, nodes=self.seg_nodes, group=self.seg_group,
                                         radius=self.seg_radius)
            # the fused sweep's colour table, copied here (never while a step is recorded: an env records its
            # first step inside a CUDA graph capture)
            self._seg_color_table = arr(np.asarray(self.seg_color_offsets, dtype=np.int32), wp.int32)
        # cutting masks of segments / triangles / particles: empty maps (one uniform branch) unless cuttable
        st = self.world.state
        self._no_col = wp.zeros(0, dtype=wp.int32, device=dev)
        self._no_mask = wp.zeros((1, 0), dtype=wp.int32, device=dev)
        self._dummy_mask = wp.zeros((1, 1), dtype=wp.int32, device=dev)
        self.seg_col = self._no_col
        if segs and any(g.seg_col is not None for g in self.groups if g.segments is not None):
            cols = [g.seg_col if g.seg_col is not None else np.full(len(g.segments), -1)
                    for g in self.groups if g.segments is not None]
            self.seg_col = arr(np.concatenate(cols)[order].astype(np.int32), wp.int32)
        self.particle_active = st.particle_active if st.particle_active is not None else self._no_mask
        self.seg_mask = st.segment_active if st.segment_active is not None else self._dummy_mask
        self.tri_mask = st.tri_active if st.tri_active is not None else self._dummy_mask
        self.face_mask = st.tet_face_active if st.tet_face_active is not None else self._dummy_mask

        # cloth / surface triangles against tool capsules, coloured like the segments
        tris, tgrp, trad = [], [], []
        for k, g in enumerate(self.groups):
            if g.triangles is not None:
                tris.append(g.triangles)
                tgrp.append(np.full(len(g.triangles), k))
                trad.append(np.full(len(g.triangles), g.radius))
        self.tri_color_offsets = [0]
        self._tool_axes = None  # the triangle passes' tools (systems with triangles)
        if tris:
            tri_all = np.concatenate(tris)
            order, self.tri_color_offsets = color_graph(tri_all)
            lanes = int(self.triangle_block_threads)
            if max(np.diff(self.tri_color_offsets)) > lanes:
                # the fused sweep takes a colour in chunks of its block's lanes, one colour after another: where
                # colours no larger than the block come without an extra colour, every colour is one chunk
                # (TissueDissection: 28 colours either way, one chunk of 32 lanes each when capped; 46 before its
                # tet faces were merged, ``_contact_faces``). More colours would mean more stages in series (a
                # 40x40 cloth: 10 colours become 97) and another Gauss-Seidel order. A block size set after
                # finalize keeps these colours.
                capped, capped_offsets = color_graph(tri_all, max_size=lanes)
                if len(capped_offsets) == len(self.tri_color_offsets):
                    order, self.tri_color_offsets = capped, capped_offsets
            self.tri_nodes = arr(tri_all[order].astype(np.int32), wp.vec3i)
            self.tri_group = arr(np.concatenate(tgrp)[order].astype(np.int32), wp.int32)
            self.tri_radius = arr(np.concatenate(trad)[order].astype(np.float32), float)
            self._triangles = make_struct(ck.ContactTriangles, nodes=self.tri_nodes, group=self.tri_group,
                                          radius=self.tri_radius)
            S = max(len(self.shapes), 1)
            self._tool_axes = make_struct(ck.ToolAxes, c0=wp.zeros((n, S), dtype=wp.vec3, device=dev),
                                          c1=wp.zeros((n, S), dtype=wp.vec3, device=dev),
                                          tf0=wp.zeros((n, S), dtype=wp.transform, device=dev),
                                          back=wp.zeros((n, S), dtype=wp.transform, device=dev),
                                          lo=wp.zeros(n, dtype=wp.vec3, device=dev),
                                          hi=wp.zeros(n, dtype=wp.vec3, device=dev),
                                          **self._tool_box_arrays(n, dev))
            self._tri_pad = float(np.concatenate(trad).max())
            self._tri_color_table = arr(np.asarray(self.tri_color_offsets, dtype=np.int32), wp.int32)
            # the particles the triangles' nodes span (the outcode sweep's shared window)
            self._tri_window = (int(tri_all.min()), int(tri_all.max() - tri_all.min() + 1))
        self.tri_col = self._no_col
        if tris and any(g.tri_col is not None for g in self.groups if g.triangles is not None):
            cols = [g.tri_col if g.tri_col is not None else np.full(len(g.triangles), -1)
                    for g in self.groups if g.triangles is not None]
            self.tri_col = arr(np.concatenate(cols)[order].astype(np.int32), wp.int32)
        self.tri_col2 = self._no_col
        if tris and any(g.tri_col2 is not None for g in self.groups if g.triangles is not None):
            cols = [g.tri_col2 if g.tri_col2 is not None else np.full(len(g.triangles), -1)
                    for g in self.groups if g.triangles is not None]
            self.tri_col2 = arr(np.concatenate(cols)[order].astype(np.int32), wp.int32)
        self._cut_masks = make_struct(ck.CutMasks, particle_active=self.particle_active, seg_col=self.seg_col,
                                      segment_active=self.seg_mask, tri_col=self.tri_col, tri_col2=self.tri_col2,
                                      tri_active=self.tri_mask, tet_face_active=self.face_mask)

        # deforming surfaces: the triangles in a clustered order from the rest shape (shared topology) and every
        # env's leaf / super-leaf boxes, recomputed from the live positions before each query (SurfaceClusters)
        P = self.world.model.particle_count
        # the tet vertices, for the World's hold of resting tets (World.tet_hold_speed): the pairs that wake it, the
        # surfaces whose boxes stay while held
        tet_particle = np.zeros(max(P, 1), dtype=bool)
        if self.world.model.tet_count:
            tet_particle[np.unique(self.world.model.tet_indices.numpy())] = True
        self._surfaces = []
        rest = self.world.state.particle_q.numpy()[0] if any(sh.surface for sh in self.shapes) else None
        for sidx, sh in enumerate(self.shapes):
            if sh.surface is None:
                continue
            t = sh.surface["tris"]
            clusters = SurfaceClusters(t, rest, leaf_size=self.surface_leaf_size)
            t = t[clusters.order]
            verts = np.unique(t)
            fc = sh.surface["face_col"]
            if fc is None:
                face_col, face_mask = self._no_col, self._dummy_mask
            else:
                face_col = arr(fc[clusters.order].astype(np.int32), wp.int32)
                face_mask = self.tri_mask if sh.surface["kind"] == "cloth" else self.face_mask
            # thickness and friction: the kernel reads the surface's own row of the shape table
            owner = sh.surface["owner"]
            # the contact particles that can touch this surface (their group pairs with it, not its own vertices):
            # the launch covers only them, not every contact particle (LigatingLoop: ~50 loop nodes, not 800)
            cand = np.nonzero((pair[sidx, np.asarray(cp_groups, dtype=np.int64)] >= 0)
                              & ~((cp_all >= owner[0]) & (cp_all < owner[1])))[0] if len(cp_all) else []
            L, S = clusters.num_leaves, clusters.num_supers
            boxes = {key: wp.zeros((n, size), dtype=wp.vec3, device=dev)
                     for key, size in (("leaf_lo", L), ("leaf_hi", L), ("super_lo", S), ("super_hi", S))}
            self._surfaces.append(dict(verts=arr(verts.astype(np.int32), wp.int32), clusters=clusters, **boxes,
                                       leaf_vert_start=arr(clusters.leaf_vert_start, wp.int32),
                                       leaf_verts=arr(clusters.leaf_verts, wp.int32),
                                       candidates=arr(np.asarray(cand, dtype=np.int32), wp.int32),
                                       on_tets=bool(tet_particle[verts].all())))
            sf = self._surfaces[-1]
            sf["surface"] = make_struct(
                ck.ContactSurface, shape=sidx, tris=arr(t.astype(np.int32), wp.vec3i), owner_start=int(owner[0]),
                owner_end=int(owner[1]), closed=int(sh.surface["closed"]), face_col=face_col, face_active=face_mask,
                leaf_size=clusters.leaf_size, leaves_per_super=clusters.leaves_per_super,
                leaf_vert_start=sf["leaf_vert_start"], leaf_verts=sf["leaf_verts"], **boxes)
        # per pair, 1 where its contacts move tet vertices: a particle group holding one, a surface of tets, a
        # self-contact set holding one (a contact on held tets wakes them: ck.add_pair_force)
        wakes = np.zeros(max(self.num_pairs, 1), dtype=np.int32)
        for s_, sh in enumerate(self.shapes):
            on_tets = sh.surface is not None and tet_particle[np.asarray(sh.surface["tris"]).ravel()].any()
            for g, group in enumerate(self.groups):
                if pair[s_, g] >= 0 and (on_tets or tet_particle[np.asarray(group.particles)].any()):
                    wakes[pair[s_, g]] = 1
        for k, ss in enumerate(self.self_sets):
            wakes[self._self_pair[k]] = int(tet_particle[np.asarray(ss["particles"])].any())
        self._wakes = arr(wakes, wp.int32)
        if self._surfaces:
            self.surf_delta = wp.zeros((n, P, 3), dtype=wp.int64, device=dev)  # fixed point, see the kernel
            self.surf_count = wp.zeros((n, P), dtype=wp.int32, device=dev)

        self._self_arrays = []
        for k, ss in enumerate(self.self_sets):
            m = len(ss["particles"])
            members = make_struct(ck.ParticleContactSet, particle=arr(ss["particles"].astype(np.int32), wp.int32),
                                  radius=arr(ss["radius"].astype(np.float32), float),
                                  chain=arr(ss["chain"].astype(np.int32), wp.int32),
                                  chain_pos=arr(ss["pos"].astype(np.int32), wp.int32),
                                  chain_len=arr(ss["length"].astype(np.int32), wp.int32),
                                  pair=arr(np.full(m, self._self_pair[k], np.int32), wp.int32),
                                  skip_links=ss["skip"], mu=wp.vec2(*ss["mu"]))
            grid = None
            if ss["grid"]:
                H = 1 << max(4, int(np.ceil(np.log2(2 * m))))  # ~2 buckets per member: few collisions
                grid = make_struct(ck.CellGrid, inv_cell=1.0 / max(2.0 * float(ss["radius"].max()), 1.0e-9), buckets=H,
                                   bucket_count=wp.zeros(n * H, dtype=wp.int32, device=dev),
                                   bucket_start=wp.zeros(n * H, dtype=wp.int32, device=dev),
                                   member_bucket=wp.zeros((n, m), dtype=wp.int32, device=dev),
                                   member_rank=wp.zeros((n, m), dtype=wp.int32, device=dev),
                                   sorted_member=wp.zeros(n * m, dtype=wp.int32, device=dev))
            self._self_arrays.append(dict(members=members, grid=grid, count=m,
                                          delta=wp.zeros((n, m), dtype=wp.vec3, device=dev)))

        P = max(self.num_pairs, 1)
        self.report_count = wp.zeros((n, P), dtype=wp.int32, device=dev)
        self.report_force = wp.zeros((n, P), dtype=float, device=dev)
        cap = max(self.capacity, 1)
        self.contact_count = wp.zeros(n, dtype=wp.int32, device=dev)
        self.contact_particle = wp.full((n, cap), -1, dtype=wp.int32, device=dev)
        self.contact_shape = wp.full((n, cap), -1, dtype=wp.int32, device=dev)
        self.contact_normal = wp.zeros((n, cap), dtype=wp.vec3, device=dev)
        self.contact_depth = wp.zeros((n, cap), dtype=float, device=dev)
        self.overflow = wp.zeros(n, dtype=wp.int32, device=dev)
        self._no_sink = wp.zeros(0, dtype=wp.int32, device=dev)
        self._overflow_sink = None
        self.reports = make_struct(ck.ContactReports, report_count=self.report_count, report_force=self.report_force,
                                   contact_count=self.contact_count, contact_particle=self.contact_particle,
                                   contact_shape=self.contact_shape, contact_normal=self.contact_normal,
                                   contact_depth=self.contact_depth, overflow=self.overflow,
                                   overflow_sink=self._no_sink)
        self._dummy_tf = wp.zeros((1, 1), dtype=wp.transform, device=dev)
        if self.body_ignore_mask:
            self.ignore_bodies = wp.zeros((n, max(self.world.model.particle_count, 1)), dtype=wp.int32, device=dev)
        else:
            self.ignore_bodies = wp.zeros((1, 1), dtype=wp.int32, device=dev)
        self.ignore = make_struct(ck.IgnoreMask, bodies=self.ignore_bodies, enabled=int(self.body_ignore_mask))
        # per-substep bundles, built when a step is first recorded and kept: recorded launches read them
        self._motions: dict = {}
        self._step_pose_cache: dict = {}
        self._solves: dict = {}
        self._finalized = True
        self.world.add_solver(self)
        return self

    # ------------------------------------------------------------------------------------------------
    # World hooks (recorded into the step)
    # ------------------------------------------------------------------------------------------------
    def body_arrays(self, world) -> tuple:
        """(previous-step, current) body pose arrays as the World interpolates them for attachments."""
        s = world.state
        if s.body_q is None:
            return self._dummy_tf, self._dummy_tf
        prev = world.body_q_previous if world.body_q_previous is not None else s.body_q
        return prev, s.body_q

    def body_motion(self, world, sweep) -> BodyMotion:
        """The kinematic bodies' motion during ``sweep``'s substep (``body_arrays`` and the substep's blends), one
        struct per substep, kept for the launches recorded with it."""
        key = (sweep.substep, sweep.substeps)
        if key not in self._motions:
            bqp, bq = self.body_arrays(world)
            self._motions[key] = make_struct(BodyMotion, body_q_prev=bqp, body_q=bq, blend_prev=sweep.blend_prev,
                                             blend=sweep.blend)
        return self._motions[key]

    def _step_poses(self, substeps: int) -> dict:
        """``pose_per_step``'s arrays for steps of ``substeps`` (cached): the step's poses ``(num_envs, substeps x
        shapes)`` as a ``ShapePoses`` (``all_poses``) and one ``ShapePoses`` per substep viewing its columns
        (``poses``; the cull bounds and groups shared); with triangles the tool axes likewise (``all_axes``,
        ``axes``; each substep's env boxes at column ``sub`` of ``lo`` / ``hi``, viewed as its ``ToolAxes.lo`` /
        ``hi``); the substeps' blends and their starts' (float32, as the per-sweep structs carry them)."""
        cached = self._step_pose_cache.get(substeps)
        if cached is not None:
            return cached
        n, S, dev = self.num_envs, len(self.shapes), self.device
        base = self._shape_poses

        def zeros(dtype, columns=substeps * S):
            return wp.zeros((n, columns), dtype=dtype, device=dev)

        def cols(a, k):
            return a[:, k * S:(k + 1) * S]

        def shape_poses(tf, tf_inv):
            return make_struct(ck.ShapePoses, tf=tf, tf_inv=tf_inv, bound=base.bound, group_start=base.group_start,
                               group_centre=base.group_centre, group_radius=base.group_radius)

        tf, tf_inv = zeros(wp.transform), zeros(wp.transform)
        step = {"all_poses": shape_poses(tf, tf_inv),
                "poses": [shape_poses(cols(tf, k), cols(tf_inv, k)) for k in range(substeps)],
                "blends": wp.array(np.array([(k + 1) / substeps for k in range(substeps)], np.float32), dtype=float,
                                   device=dev),
                "blends_prev": wp.array(np.array([k / substeps for k in range(substeps)], np.float32), dtype=float,
                                        device=dev)}
        if len(self.tri_color_offsets) > 1:
            one = self._tool_axes
            boxes = one.box_centre.shape[1] > 0  # the shape-code sweep's boxes: a column per shape, else none
            arrays = {"c0": zeros(wp.vec3), "c1": zeros(wp.vec3), "tf0": zeros(wp.transform),
                      "back": zeros(wp.transform)}
            if boxes:
                arrays.update(box_centre=zeros(wp.vec3), box_frame=zeros(wp.mat33), box_half=zeros(wp.vec3))
            lo, hi = zeros(wp.vec3, substeps), zeros(wp.vec3, substeps)

            def axes(k):
                views = {name: (a if k is None else cols(a, k)) for name, a in arrays.items()}
                if not boxes:
                    views.update(box_centre=one.box_centre, box_frame=one.box_frame, box_half=one.box_half)
                return make_struct(ck.ToolAxes, lo=one.lo if k is None else lo[:, k],
                                   hi=one.hi if k is None else hi[:, k], **views)

            step.update(all_axes=axes(None), axes=[axes(k) for k in range(substeps)], lo=lo, hi=hi)
        self._step_pose_cache[substeps] = step
        return step

    def _particle_solve(self, world, sweep) -> ck.ParticleSolve:
        # impulse m * dx / h summed over the sweeps, divided by the step duration -> mean force over the step; 0 where
        # forces are not reported (the kernels then skip their atomic adds)
        hold = world.tet_hold_moving is not None
        key = (sweep.h, sweep.substeps, bool(self.report_forces), hold)
        if key not in self._solves:
            h = sweep.h
            scale = 1.0 / (h * h * sweep.substeps) if self.report_forces else 0.0
            wakes, moving = self._no_col, self._no_col  # empty: no tets are held
            if hold:
                wakes, moving = self._wakes, world.tet_hold_moving
            self._solves[key] = make_struct(ck.ParticleSolve, inv_mass=world.model.particle_inv_mass,
                                            q_pred=world.predicted_positions, qd=world.state.particle_qd, h=h,
                                            force_scale=scale, wakes=wakes, moving=moving)
        return self._solves[key]

    #: how ``surface_bounds`` may form the deforming surfaces' boxes
    SURFACE_BOUNDS = ("separate", "fused")
    #: the triangle sweeps ``triangle_sweep`` may name
    TRIANGLE_SWEEPS = ("auto", "colored", "fused", "outcodes", "shape_codes")

    def _outcode_window_fits(self) -> bool:
        return len(self.tri_color_offsets) <= 1 or self._tri_window[1] <= ck.OUTCODE_MAX_PARTICLES

    def _tool_box_arrays(self, n: int, dev) -> dict:
        """``ToolAxes``' oriented boxes of the shape-code sweep: ``(num_envs, shapes)`` where it can code every shape
        (at most ``ck.SHAPE_CODE_MAX_SHAPES``), else ``(num_envs, 0)`` (the pose kernel then forms none)."""
        S = len(self.shapes) if len(self.shapes) <= ck.SHAPE_CODE_MAX_SHAPES else 0
        return {"box_centre": wp.zeros((n, S), dtype=wp.vec3, device=dev),
                "box_frame": wp.zeros((n, S), dtype=wp.mat33, device=dev),
                "box_half": wp.zeros((n, S), dtype=wp.vec3, device=dev)}

    def resolved_triangle_sweep(self) -> str:
        """The sweep the step launches: ``triangle_sweep`` with "auto" resolved."""
        if self.triangle_sweep == "auto":
            return "outcodes" if self._outcode_window_fits() else "fused"
        return self.triangle_sweep

    def record_key(self) -> tuple:
        """The settings the recorded launches depend on (the World records a step again when they change)."""
        if self.triangle_sweep not in self.TRIANGLE_SWEEPS:
            raise ValueError(f"triangle_sweep must be one of {self.TRIANGLE_SWEEPS}, got {self.triangle_sweep!r}")
        if self.triangle_sweep in ("outcodes", "shape_codes") and not self._outcode_window_fits():
            raise ValueError(f"triangle_sweep {self.triangle_sweep!r} keeps an int per particle of the triangles' "
                             f"window in shared memory: this scene's window of {self._tri_window[1]} particles exceeds "
                             f"{ck.OUTCODE_MAX_PARTICLES}; use 'fused'")
        if self.triangle_sweep == "shape_codes" and len(self.shapes) > ck.SHAPE_CODE_MAX_SHAPES:
            raise ValueError(f"triangle_sweep 'shape_codes' codes 6 bits per shape in an int32: this system has "
                             f"{len(self.shapes)} shapes, more than {ck.SHAPE_CODE_MAX_SHAPES}; use 'outcodes'")
        if not 1 <= int(self.triangle_block_threads) <= 1024:
            raise ValueError(f"triangle_block_threads must be in [1, 1024] (threads of one env's block), "
                             f"got {self.triangle_block_threads!r}")
        if self.surface_bounds not in self.SURFACE_BOUNDS:
            raise ValueError(f"surface_bounds must be one of {self.SURFACE_BOUNDS}, got {self.surface_bounds!r}")
        lanes = self.surface_bounds_lanes
        if isinstance(lanes, bool) or not isinstance(lanes, int) or not 1 <= lanes <= 1024:
            raise ValueError(f"surface_bounds_lanes must be an int in [1, 1024] (threads of one env's block), "
                             f"got {lanes!r}")
        for name in ("report_forces", "defer_surface_deltas"):
            if not isinstance(getattr(self, name), bool):
                raise ValueError(f"{name} must be a bool, got {getattr(self, name)!r}")
        return (self.resolved_triangle_sweep(), int(self.triangle_block_threads), id(self.overflow_sink),
                bool(self.fuse_segment_colors), bool(self.pose_per_step), self.surface_bounds, lanes,
                self.report_forces, self.defer_surface_deltas)

    def record_sweep(self, world, launch, sweep) -> None:
        """Record the contact projections of one sweep (called by the World while it records a step)."""
        n, q = self.num_envs, world.state.particle_q
        report = 1 if sweep.last else 0
        shapes, motion, solve = self.shape_table, self.body_motion(world, sweep), self._particle_solve(world, sweep)
        ignore, masks, reports = self.ignore, self._cut_masks, self.reports
        has_triangles = len(self.tri_color_offsets) > 1
        # a step's reports are cleared by its first sweep's pose kernel (or alone where there is none)
        clear = 1 if sweep.first else 0
        poses, axes = self._shape_poses, self._tool_axes
        if has_triangles:  # the triangle passes' tool axes with the shape poses
            lanes = launching.block_lanes(self.device, 32)  # a block per env, its lanes over the shapes
            # each tool's own box only for the sweep that reads it
            boxes = 1 if self.resolved_triangle_sweep() == "shape_codes" else 0
            if self.pose_per_step and len(self.shapes):
                # this substep's columns of the step's poses and axes, every substep's formed by the step's first sweep
                step = self._step_poses(sweep.substeps)
                poses, axes = step["poses"][sweep.substep], step["axes"][sweep.substep]
                if sweep.first:
                    launch(ck.pose_shapes_and_tools_substeps, (n, lanes),
                           [shapes, motion, step["blends"], step["blends_prev"], self._tri_pad, clear, boxes,
                            reports], [step["all_poses"], step["all_axes"], step["lo"], step["hi"]], block_dim=lanes)
            else:
                launch(ck.pose_shapes_and_tools, (n, lanes), [shapes, motion, self._tri_pad, clear, boxes, reports],
                       [self._shape_poses, self._tool_axes], block_dim=lanes)
        elif len(self.shapes) and self.pose_per_step:
            # this substep's columns of the step's poses, every substep's posed by the step's first sweep
            step = self._step_poses(sweep.substeps)
            poses = step["poses"][sweep.substep]
            if sweep.first:
                launch(ck.pose_shapes_substeps, (n, sweep.substeps, len(self.shapes)),
                       [shapes, motion, step["blends"], clear, reports],
                       [step["all_poses"].tf, step["all_poses"].tf_inv])
        elif len(self.shapes):
            launch(ck.pose_shapes, (n, len(self.shapes)), [shapes, motion, clear, reports], [self._shape_poses])
        elif clear:
            launch(ck.clear_reports, n, [], [self.reports])
        if len(self.cp_particle):
            # the variant without the mesh SDF query where no shape is a mesh (fewer registers)
            meshes = any(sh.kind == "mesh" for sh in self.shapes)
            args = (ck.particle_collision_kernel(meshes), (n, len(self.cp_particle)),
                    [self._particles, shapes, motion, poses, solve, ignore, masks, report, self.report_margin],
                    [q, reports])
            if not meshes and hasattr(launch, "defer_contact"):
                # into the next substep's rod launch where nothing else comes first (World.contact_in_rod_launch)
                launch.defer_contact(*args)
            else:
                launch(*args)
        off = self.seg_color_offsets
        if len(off) > 2 and self.fuse_segment_colors:
            # every colour in one launch, a block per env with barriers between colours
            lanes = launching.block_lanes(self.device, 32)
            launch(ck.collide_segment_colors, (n, lanes),
                   [self._segments, self._seg_color_table, shapes, motion, poses, solve, ignore, masks],
                   [q, reports], block_dim=lanes)
        else:
            for c in range(len(off) - 1):
                launch(ck.collide_segments, (n, off[c + 1] - off[c]),
                       [self._segments, off[c], shapes, motion, poses, solve, ignore, masks],
                       [q, reports])
        off = self.tri_color_offsets
        sweep_kind = self.resolved_triangle_sweep()
        if has_triangles and sweep_kind == "fused":
            threads = launching.block_lanes(self.device, self.triangle_block_threads)
            launch(ck.collide_triangle_colors, (n, threads),
                   [self._triangles, self._tri_color_table, shapes, axes, solve, ignore, masks],
                   [q, reports], block_dim=threads)
        elif has_triangles and sweep_kind in ("outcodes", "shape_codes"):
            threads = launching.block_lanes(self.device, self.triangle_block_threads)
            first, window = self._tri_window
            kernel = ck.collide_triangle_outcodes_kernel(window, per_shape=sweep_kind == "shape_codes")
            launch(kernel, (n, threads),
                   [self._triangles, self._tri_color_table, first, shapes, axes, solve, ignore, masks],
                   [q, reports], block_dim=threads)
        elif has_triangles:
            for c in range(len(off) - 1):
                launch(ck.collide_triangles, (n, off[c + 1] - off[c]),
                       [self._triangles, off[c], shapes, axes, solve, ignore, masks], [q, reports])
        for sf in self._surfaces:
            if len(sf["candidates"]) == 0:
                continue  # nothing queries this surface
            # every env's boxes as its vertices are now (after this sweep's constraints), then the queries
            clusters = sf["clusters"]
            # a held env's boxes stay where every vertex of the surface is a tet vertex (World.tet_hold_speed): unmoved
            # since computed; any other surface's boxes are always computed
            hold = world._tet_hold(off=not sf["on_tets"])
            if self.surface_bounds == "fused":
                lanes = launching.block_lanes(self.device, self.surface_bounds_lanes)
                launch(ck.surface_bounds_kernel(clusters.num_leaves), (n, lanes),
                       [sf["leaf_vert_start"], sf["leaf_verts"], clusters.leaves_per_super, q, hold],
                       [sf["leaf_lo"], sf["leaf_hi"], sf["super_lo"], sf["super_hi"]], block_dim=lanes)
            else:
                launch(ck.surface_leaf_bounds, (n, clusters.num_leaves),
                       [sf["leaf_vert_start"], sf["leaf_verts"], q, hold], [sf["leaf_lo"], sf["leaf_hi"]])
                launch(ck.surface_super_bounds, (n, clusters.num_supers),
                       [sf["leaf_lo"], sf["leaf_hi"], clusters.leaves_per_super, hold],
                       [sf["super_lo"], sf["super_hi"]])
            launch(ck.collide_surface, (n, len(sf["candidates"])),
                   [self._particles, sf["candidates"], sf["surface"], shapes, solve, masks, report, self.report_margin],
                   [q, self.surf_delta, self.surf_count, reports])
            apply = (ck.apply_surface_deltas, (n, sf["verts"].shape[0]), [sf["verts"], self.surf_delta,
                                                                          self.surf_count], [q])
            defer = getattr(launch, "defer_deltas", None)
            if self.defer_surface_deltas and defer is not None:
                defer(self.surf_delta, self.surf_count, float(ck.SURFACE_DELTA_SCALE), apply)
            else:
                launch(*apply)
        for a in self._self_arrays:
            members, grid, m = a["members"], a["grid"], a["count"]
            if grid is not None:
                launch(grid.bucket_count.zero_)
                launch(ck.grid_count, (n, m), [members, grid, q])
                # one exclusive scan over every env's buckets gives global offsets (env e starts at e * M)
                launch(lambda g=grid: wp.utils.array_scan(g.bucket_count, g.bucket_start, inclusive=False))
                launch(ck.grid_scatter, (n, m), [grid])
                launch(ck.collide_particle_pairs_grid, (n, m), [members, grid, solve, masks, report],
                       [q, a["delta"], reports])
            else:
                launch(ck.collide_particle_pairs, (n, m), [members, solve, masks, report], [q, a["delta"], reports])
            launch(ck.apply_particle_deltas, (n, m), [members.particle, a["delta"]], [q])

    @property
    def overflow_sink(self):
        """``(num_envs,)`` int32 or None: where set (an env collecting overflow over its frame skip), a record that
        finds the buffer full also sets it (``ck.record_contact``: no launch of the env's after every world step)."""
        return self._overflow_sink

    @overflow_sink.setter
    def overflow_sink(self, sink) -> None:
        self._overflow_sink = sink
        self.reports.overflow_sink = sink if sink is not None else self._no_sink

    def reset(self, env_mask: wp.array) -> None:
        """Clear the masked envs' reports (``World.reset`` calls it): a new episode starts with no contact."""
        launching.launch(ck.clear_reports_masked, dim=self.num_envs, inputs=[env_mask, self.reports],
                         device=self.device)

    def clear_reports(self) -> None:
        """Zero the reports now (``world.step`` already does this at its start; for use outside a step)."""
        launching.launch(ck.clear_reports, dim=self.num_envs, inputs=[self.reports], device=self.device)

    # ------------------------------------------------------------------------------------------------
    # host helpers (sync; for tests and scripts)
    # ------------------------------------------------------------------------------------------------
    def pair(self, shape: int | str, group: int | str) -> int:
        """Report column of a (shape, group) pair (ids or names)."""
        sname = self.shapes[shape].name if isinstance(shape, int) else shape
        gname = self.groups[group].name if isinstance(group, int) else group
        return self.pair_names.index(f"{sname}/{gname}")

    def counts(self) -> np.ndarray:
        """``report_count`` as a NumPy copy ``(num_envs, num_pairs)``."""
        return self.report_count.numpy()[:, : self.num_pairs].copy()

    def forces(self) -> np.ndarray:
        """``report_force`` as a NumPy copy ``(num_envs, num_pairs)``, N (a ``RuntimeError`` where ``report_forces``
        is off: the kernels did not sum them)."""
        if not self.report_forces:
            raise RuntimeError("this contact system does not report forces (report_forces is off); set it before "
                               "the first step to read forces()")
        return self.report_force.numpy()[:, : self.num_pairs].copy()
