"""Model / State / Control: the struct-of-arrays data of a batch of scenes.

* ``Model`` is static after ``SceneBuilder.finalize``: topology in *local* indices shared by all envs,
  rest shapes and material parameters. A per-env parameter has leading dimension 1 (shared) or
  ``num_envs`` (randomised) and kernels read it as ``p[env % p.shape[0]]``.
* ``State`` is dynamic and env-major: every array is ``(num_envs, count)``.
* ``Control`` holds the per-env commands after action scaling.

Physics fields start empty (count 0) so a purely kinematic scene such as Reach carries no cost.

Units are SI throughout (metres, kilograms, seconds, pascals); gravity defaults to ``(0, 0, -9.81)``.

Cutting (``lapwarp.cutting``, ``docs/cutting.md``): when the scene has a cuttable object the State carries
per-env ``active`` masks (1 = present) over tets, cloth triangles and rod segments in *insertion* order (the
order of ``SceneObject.tets`` / ``tris`` / ``segments``); constraint groups map their colour-ordered
constraints to those elements (``tet_element``, ``edge_tris``, ``hinge_tris``, ``segment_particles[:, 2]``) and
skip constraints of removed elements. Scenes without cuttable objects carry no masks and pay nothing.

Constraint groups are stored sorted by graph colour: ``<group>_color_offsets`` is a host list of
``num_colors + 1`` offsets, and constraints ``[offsets[c], offsets[c + 1])`` share no particle (or rod
segment), so one kernel launch per colour updates them in parallel without atomics (Gauss-Seidel
across colours, Jacobi-free within a colour).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import warp as wp


@dataclass
class SceneObject:
    """Handle of one object added to a ``SceneBuilder`` (a cloth, a tet mesh, a rod, a particle set).

    Index ranges are global particle indices of the scene (shared by all envs). ``surface_tris`` are in
    *global* particle indices and wound outwards for tet meshes; ``tets`` / ``tris`` / ``edges`` /
    ``segments`` likewise. Use ``obj.particles`` to slice ``world.state.particle_q.numpy()``.
    """

    name: str
    kind: str
    particle_start: int
    particle_count: int
    surface_tris: object = None  # np.ndarray (F, 3) int32, global particle indices
    tets: object = None  # np.ndarray (T, 4) int32
    tris: object = None  # np.ndarray (F, 3) int32 (cloth elements)
    edges: object = None  # np.ndarray (E, 2) int32 (rod / spring topology)
    segment_start: int = 0  # first rod segment (rods only)
    segment_count: int = 0
    closed: bool = False
    fixed: object = None  # np.ndarray of global particle indices fixed in place
    element_start: int = 0  # first cloth triangle / tet of this object in the scene's insertion order
    cuttable: bool = False  # its elements carry per-env active masks (lapwarp.cutting)

    @property
    def particles(self) -> slice:
        """Slice of this object's particles along the particle axis of state arrays."""
        return slice(self.particle_start, self.particle_start + self.particle_count)

    @property
    def segments(self) -> slice:
        """Slice of this rod's segments along the segment axis of rod state arrays."""
        return slice(self.segment_start, self.segment_start + self.segment_count)


@dataclass
class Model:
    """Static description of one scene, shared by all ``num_envs`` copies.

    Per-constraint arrays are 1-D (topology, shared) or 2-D ``(P, count)`` with ``P`` 1 or ``num_envs``
    (material parameters, randomisable per env). Empty groups have count 0 and their arrays are None.
    """

    num_envs: int
    device: str
    gravity: wp.vec3 = field(default_factory=lambda: wp.vec3(0.0, 0.0, 0.0))
    particle_count: int = 0

    # particles ------------------------------------------------------------------------------------
    particle_inv_mass: wp.array2d | None = None  # (P, n) 1/kg, 0 = fixed
    particle_damping: wp.array2d | None = None  # (P, n) linear velocity damping rate 1/s
    max_speed: float = 50.0  # m/s, above this an env is flagged unstable
    max_substep: float = float("inf")  # s, the longest substep at which stiff tets still converge (builder)

    # distance constraints (cloth stretch/shear edges, springs, pendulum links) ----------------------
    edge_count: int = 0
    edge_indices: wp.array | None = None  # (E,) vec2i
    edge_rest: wp.array | None = None  # (E,) rest length m
    edge_compliance: wp.array2d | None = None  # (P, E) m/N
    edge_color_offsets: list = field(default_factory=lambda: [0])
    edge_tris: wp.array | None = None  # (E,) vec2i cloth triangles beside the edge (-1 none); cutting masks only

    # dihedral bending hinges (cloth) ----------------------------------------------------------------
    hinge_count: int = 0
    hinge_indices: wp.array | None = None  # (H,) vec4i: opposite a, opposite b, edge c, edge d
    hinge_rest: wp.array | None = None  # (H,) rest dihedral angle rad
    hinge_compliance: wp.array2d | None = None  # (P, H) 1/(N m)
    hinge_color_offsets: list = field(default_factory=lambda: [0])
    hinge_tris: wp.array | None = None  # (H,) vec2i the hinge's two cloth triangles; cutting masks only

    # tetrahedral FEM, co-rotated (|F - R| and det F - 1 constraints) -----------------------------------
    tet_count: int = 0
    tet_indices: wp.array | None = None  # (T,) vec4i
    tet_inv_rest: wp.array | None = None  # (T,) mat33 Dm^-1
    tet_params: wp.array2d | None = None  # (P, T) vec3 (alpha_dev, alpha_vol or -1, unused), 1/(Pa m^3)
    tet_color_offsets: list = field(default_factory=lambda: [0])
    tet_element: wp.array | None = None  # (T,) int32 insertion index of each colour-ordered tet
    tet_elements: wp.array | None = None  # (T,) vec4i tets in insertion order (global particle indices)
    # the 4 faces of every tet in insertion order (face 4 t + k, wound outwards) and the tet across each face
    tet_face_indices: wp.array | None = None  # (4T,) vec3i global particle indices
    tet_face_neighbor: wp.array | None = None  # (4T,) int32 tet across the face, -1 on the boundary

    # cloth triangles in insertion order (all cloth objects concatenated) ---------------------------------
    tri_count: int = 0
    tri_indices: wp.array | None = None  # (F,) vec3i global particle indices

    # geodesic tethers of cloths (lapwarp.kernels.geodesic) ------------------------------------------
    geo_particles: wp.array | None = None  # (G,) int32 particles of tethered cloths
    geo_tris: wp.array | None = None  # (Fg,) vec3i their triangles (global particle indices)
    geo_tri_element: wp.array | None = None  # (Fg,) int32 the triangle's index in State.tri_active, -1 = not cuttable
    geo_order: wp.array | None = None  # (4, Fg) int32 the four fast-sweeping orders
    geo_rest: wp.array | None = None  # (n,) vec3 rest positions (geodesics are measured on the rest sheet)

    # Cosserat rods (Kugelstadt & Schoemer 2016) ----------------------------------------------------
    segment_count: int = 0
    segment_particles: wp.array | None = None  # (S,) vec3i: p0, p1, segment index (constraint order)
    segment_rest: wp.array | None = None  # (S,) rest length m
    segment_inv_inertia: wp.array2d | None = None  # (P, S) quaternion inverse mass 1/(4 I)
    segment_damping: wp.array2d | None = None  # (P, S) angular velocity damping rate 1/s
    segment_compliance: wp.array2d | None = None  # (P, S) vec3 stretch-shear compliance, material frame
    segment_color_offsets: list = field(default_factory=lambda: [0])
    bend_count: int = 0
    bend_segments: wp.array | None = None  # (B,) vec2i
    bend_rest: wp.array | None = None  # (B,) quat rest Darboux quaternion
    bend_compliance: wp.array2d | None = None  # (P, B) vec3 bend-twist compliance, material frame
    bend_color_offsets: list = field(default_factory=lambda: [0])
    # direct stretch solve (kernels/chains.py): one (env, rod) thread solves the rod's chain of segment
    # distance constraints exactly; per-segment arrays in insertion order (SceneObject.segments)
    rod_count: int = 0
    rod_chains: object = None  # lapwarp.chains.ChainSet, one chain per rod (constraints = segments)
    rod_stretch_rest: wp.array | None = None  # (S,) segment rest length m
    rod_stretch_compliance: wp.array2d | None = None  # (P, S) l / (E A), m/N
    # the distance constraints (edges) as straight chains solved directly (lapwarp.chains); None = coloured
    # Gauss-Seidel over the edge colours
    edge_chains: object = None  # lapwarp.chains.ChainSet (constraints = edge indices)

    # kinematic bodies (instrument jaws) and attachments ---------------------------------------------
    body_count: int = 0
    body_names: list = field(default_factory=list)
    attachment_capacity: int = 0
    # no particle is ever in two slots (finalize: every slot a static attachment of its own particle, no free slot for
    # grasping; LigatingLoop's closure: slot k only ever holds loop node k): the attachment pass may run a thread per
    # slot (xpbd.solve_attachment_slots)
    attachments_distinct: bool = False
    # (C,) vec3 per attachment slot: a segment it holds turns only with its body's rotation about this unit axis
    # (zero: with the body's rotation; GraspSystem's ``hold_up``)
    attach_hold_up: wp.array | None = None

    objects: list = field(default_factory=list)  # SceneObject handles, in insertion order
    # built values of the material arrays when every env has its own row (finalize(per_env_materials=True))
    material_base: dict = field(default_factory=dict)
    surface_tris: wp.array | None = None  # (F,) vec3i all render/contact triangles, global indices


@dataclass
class State:
    """Dynamic per-env arrays, shape ``(num_envs, count)``."""

    particle_q: wp.array2d | None = None  # (N, n) vec3 m
    particle_qd: wp.array2d | None = None  # (N, n) vec3 m/s
    segment_q: wp.array2d | None = None  # (N, S) quat, rod segment orientations (d3 = local z)
    segment_qd: wp.array2d | None = None  # (N, S) vec3 angular velocity rad/s (world frame)
    body_q: wp.array2d | None = None  # (N, B) transform of kinematic bodies, written by the env layer
    attach_particle: wp.array2d | None = None  # (N, C) int32 particle index, -1 = free slot
    attach_body: wp.array2d | None = None  # (N, C) int32 body index, -1 = world frame
    attach_offset: wp.array2d | None = None  # (N, C) vec3 target in the body frame
    attach_compliance: wp.array2d | None = None  # (N, C) float m/N
    attach_segment: wp.array2d | None = None  # (N, C) int32 rod segment whose orientation the slot holds, -1 = none
    attach_rotation: wp.array2d | None = None  # (N, C) quat the held segment's orientation in its body's frame
    # cutting (only when the scene has a cuttable object; 1 = present, 0 = removed; insertion order)
    tet_active: wp.array2d | None = None  # (N, T) int32
    tri_active: wp.array2d | None = None  # (N, F) int32 cloth triangles (also their render face mask)
    edge_active: wp.array2d | None = None  # (N, E) int32 an edge acts while one of its triangles is present
    hinge_active: wp.array2d | None = None  # (N, H) int32 a hinge acts while both its triangles are present
    segment_active: wp.array2d | None = None  # (N, S) int32 rod segments
    tet_face_active: wp.array2d | None = None  # (N, 4T) int32 tet faces on the current surface
    cut_dirty: wp.array2d | None = None  # (N, 1) int32 surfaces/connectivity need recomputing (1 after reset)
    particle_active: wp.array2d | None = None  # (N, n) int32 0 = every element of the particle removed (no contact)
    # geodesic tethers (only with a tethered cloth): distance and anchor per particle, anchor flags and triangle
    # masks they were computed for, status 0 done / 1 sweeping / 2 start again from the anchors
    geo_dist: wp.array2d | None = None  # (N, GROUPS * n) float m per anchor group (column g * n + p), 1e30 = no tether
    geo_source: wp.array2d | None = None  # (N, GROUPS * n) int32 nearest anchor particle of the group, -1 = none
    geo_anchor: wp.array2d | None = None  # (N, n) int32
    geo_tri_seen: wp.array2d | None = None  # (N, Fg) int32
    geo_label: wp.array2d | None = None  # (N, n) int32 anchor group of each anchor (scratch of a restart), -1 = none
    geo_status: wp.array2d | None = None  # (N, 2) int32 sweep status, number of anchor groups

    def arrays(self) -> dict:
        """All allocated arrays by name (used for reset copies and memory reports)."""
        return {k: v for k, v in self.__dict__.items() if isinstance(v, wp.array)}


@dataclass
class Control:
    """Per-env commands after action scaling."""

    pass
