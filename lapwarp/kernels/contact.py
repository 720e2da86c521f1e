"""Contact kernels: particles, rod segments and cloth / surface triangles against signed distance fields and
deforming surfaces, particle-particle contact (brute force and a per-env cell list), contact reports.

Every kernel launches env-first (``env, i = wp.tid()``). The host (:mod:`lapwarp.contact`) hands the kernels a few
``wp.struct`` bundles built once in ``ContactSystem.finalize`` (a recorded launch keeps the struct it was recorded
with, so none is changed afterwards): the collider :class:`ShapeTable`, the contact particles / segments / triangles,
the :class:`ParticleSolve` of a step, the :class:`CutMasks`, the :class:`IgnoreMask` of held particles and the
:class:`ContactReports` the kernels write. Collider shapes are shared by all envs; a shape on a kinematic body reads
its pose from the substep's :class:`lapwarp.kernels.geometry.BodyMotion` exactly like the attachments of
:mod:`lapwarp.kernels.xpbd`, so a tool sweeps through the substeps instead of jumping once per step.

Projection (position-based, Macklin et al. 2014 "Unified particle physics"): a particle of radius ``r`` at
signed distance ``d`` from a shape with thickness ``t`` is pushed out along the SDF normal by
``pen = r + t - d``. Coulomb friction acts on the tangential displacement of the particle relative to the
shape's surface point during this substep: static (the displacement is removed) when it is below
``mu_s * pen``, kinetic (shortened by ``mu_k * pen``) otherwise. The velocity update of the World then turns
these position changes into velocities, so friction and non-penetration hold at the velocity level too.

Reports: per env and per (shape, particle group) pair, ``counts`` (contacts in the last substep of the step)
and ``force`` (summed normal force averaged over the step, N) are accumulated with atomics per env only.
"""

import warp as wp

from lapwarp.kernels.geometry import (
    BodyMotion,
    body_pose,
    closest_point_triangle,
    closest_segment_segment,
    closest_segment_triangle,
    safe_normalize,
)

# closest_segment_segment is re-exported here for callers that import it from this module
from lapwarp.kernels.hold import TetHold, tets_held_now

wp.set_module_options({"enable_backward": False})

#: Deforming-surface corrections are summed in fixed point (1 nm units): atomic float sums depend on the order the
#: threads land in, so two identical GPU runs would drift apart; integer sums do not.
SURFACE_DELTA_SCALE = wp.constant(1.0e9)

# Largest multiple of a contact point's correction that one node of a segment or triangle takes (see node_share)
MAX_NODE_SHARE = wp.constant(2.0)

SHAPE_SPHERE = wp.constant(0)
SHAPE_CAPSULE = wp.constant(1)
SHAPE_BOX = wp.constant(2)
SHAPE_PLANE = wp.constant(3)
SHAPE_CYLINDER = wp.constant(4)
SHAPE_MESH = wp.constant(5)
SHAPE_SURFACE = wp.constant(6)  # deforming per-env triangle surface: collide_surface, not the SDF loop


# ----------------------------------------------------------------------------------------------------
# bundles the host builds once (lapwarp/contact.py)
# ----------------------------------------------------------------------------------------------------


@wp.struct
class ShapeTable:
    """The colliders, shared by all envs (index = shape id), and the report column of each (shape, group) pair
    (``pair_index[shape, group]``, -1: they do not collide)."""

    kind: wp.array(dtype=wp.int32)
    body: wp.array(dtype=wp.int32)  # kinematic body, -1: static in the env frame
    local: wp.array(dtype=wp.transform)  # pose in the body (or env) frame
    params: wp.array(dtype=wp.vec3)
    mesh: wp.array(dtype=wp.uint64)
    thickness: wp.array(dtype=float)
    mu: wp.array(dtype=wp.vec2)  # (static, kinetic)
    pair_index: wp.array2d(dtype=wp.int32)


@wp.struct
class ContactParticles:
    """Particles that collide with the shapes, as spheres of ``radius``, and their particle group."""

    particle: wp.array(dtype=wp.int32)
    group: wp.array(dtype=wp.int32)
    radius: wp.array(dtype=float)


@wp.struct
class ContactSegments:
    """Rod segments (node pairs) that collide along their interior, graph-coloured (a colour is a range)."""

    nodes: wp.array(dtype=wp.vec2i)
    group: wp.array(dtype=wp.int32)
    radius: wp.array(dtype=float)


@wp.struct
class ContactTriangles:
    """Cloth / tissue-surface triangles that collide over their interior, graph-coloured (a colour is a range)."""

    nodes: wp.array(dtype=wp.vec3i)
    group: wp.array(dtype=wp.int32)
    radius: wp.array(dtype=float)


@wp.struct
class ContactSurface:
    """A deforming triangle surface as a collider: ``tris`` (every env's copy over its own ``particle_q`` row) in the
    clustered order of :class:`lapwarp.surface_clusters.SurfaceClusters`, owned by particles
    ``[owner_start, owner_end)``, with every env's leaf and super-leaf boxes (``surface_leaf_bounds`` /
    ``surface_super_bounds`` write them before each query); thickness and friction are its shape's."""

    shape: int
    tris: wp.array(dtype=wp.vec3i)
    owner_start: int
    owner_end: int
    closed: int
    face_col: wp.array(dtype=wp.int32)  # column of each triangle in face_active; empty: not cuttable
    face_active: wp.array2d(dtype=wp.int32)
    leaf_size: int  # leaf l holds triangles [l * leaf_size, (l + 1) * leaf_size)
    leaves_per_super: int  # super leaf s holds leaves [s * leaves_per_super, (s + 1) * leaves_per_super)
    leaf_vert_start: wp.array(dtype=wp.int32)  # CSR of each leaf's distinct vertices
    leaf_verts: wp.array(dtype=wp.int32)
    leaf_lo: wp.array2d(dtype=wp.vec3)  # (num_envs, leaves): each leaf's box, as the vertices are now
    leaf_hi: wp.array2d(dtype=wp.vec3)
    super_lo: wp.array2d(dtype=wp.vec3)  # (num_envs, super leaves)
    super_hi: wp.array2d(dtype=wp.vec3)


@wp.struct
class CutMasks:
    """Cutting masks contact follows. An empty column map (or a ``(1, 0)`` particle mask) means "nothing cut"."""

    particle_active: wp.array2d(dtype=wp.int32)  # (num_envs, particles) or (1, 0)
    seg_col: wp.array(dtype=wp.int32)  # segment_active column of each contact segment, -1: never removed
    segment_active: wp.array2d(dtype=wp.int32)
    tri_col: wp.array(dtype=wp.int32)  # >= 0 tri_active column, <= -2 tet face -2 - col, -1 always collides
    tri_col2: wp.array(dtype=wp.int32)  # a face two tets share: the other tet's face column (-1 none); may be empty
    tri_active: wp.array2d(dtype=wp.int32)
    tet_face_active: wp.array2d(dtype=wp.int32)


@wp.struct
class IgnoreMask:
    """Bit ``b`` of ``bodies[env, particle]`` lets the particle pass through the shapes of body ``b`` (grasping sets
    it for held particles so the jaws do not squeeze them out); ``enabled = 0``: no mask (``bodies`` is a dummy)."""

    bodies: wp.array2d(dtype=wp.int32)
    enabled: int


@wp.struct
class ParticleSolve:
    """What a contact projection needs of the particles besides their positions: inverse masses (leading dim 1 or
    num_envs), the substep's predicted positions and the velocities the World keeps until its velocity update,
    the substep ``h`` and the factor turning a mass-weighted correction into a mean force over the step (0: forces not
    reported, ``ContactSystem.report_forces`` off: the kernels skip their atomic adds into ``report_force``). Where the
    World holds resting tets (``World.tet_hold_speed``): ``wakes[pair]`` 1 where the pair's contacts move tet vertices
    and the World's per-env ``moving`` flags (``hold.TetHold``), which such a contact sets (empty ``wakes``: none)."""

    inv_mass: wp.array2d(dtype=float)
    q_pred: wp.array2d(dtype=wp.vec3)
    qd: wp.array2d(dtype=wp.vec3)
    h: float
    force_scale: float
    wakes: wp.array(dtype=wp.int32)
    moving: wp.array(dtype=wp.int32)


@wp.struct
class ContactReports:
    """Per-env reports and contact records (see ``ContactSystem``), written with atomics per env."""

    report_count: wp.array2d(dtype=wp.int32)
    report_force: wp.array2d(dtype=float)
    contact_count: wp.array(dtype=wp.int32)
    contact_particle: wp.array2d(dtype=wp.int32)
    contact_shape: wp.array2d(dtype=wp.int32)
    contact_normal: wp.array2d(dtype=wp.vec3)
    contact_depth: wp.array2d(dtype=float)
    overflow: wp.array(dtype=wp.int32)
    # ``(num_envs,)`` or empty: an env's flag over its frame skip, set with ``overflow`` (ContactSystem.overflow_sink)
    overflow_sink: wp.array(dtype=wp.int32)


@wp.struct
class ParticleContactSet:
    """Members of one particle-particle contact set; members within ``skip_links`` along one chain never touch."""

    particle: wp.array(dtype=wp.int32)
    radius: wp.array(dtype=float)
    chain: wp.array(dtype=wp.int32)  # -1: not on a chain
    chain_pos: wp.array(dtype=wp.int32)
    chain_len: wp.array(dtype=wp.int32)  # > 0: closed chain of that length
    pair: wp.array(dtype=wp.int32)  # report column
    skip_links: int
    mu: wp.vec2


@wp.struct
class CellGrid:
    """Per-env cell list of one particle-contact set: ``buckets`` (a power of two) hash buckets per env."""

    inv_cell: float
    buckets: int
    bucket_count: wp.array(dtype=wp.int32)
    bucket_start: wp.array(dtype=wp.int32)
    member_bucket: wp.array2d(dtype=wp.int32)
    member_rank: wp.array2d(dtype=wp.int32)
    sorted_member: wp.array(dtype=wp.int32)


# ----------------------------------------------------------------------------------------------------
# signed distance functions, shape-local frame; return (normal, distance) packed as vec4
# ----------------------------------------------------------------------------------------------------



@wp.func
def add_pair_force(reports: ContactReports, env: int, pair: int, impulse: float, solve: ParticleSolve):
    """Add a contact's mass-weighted correction (``impulse``: penetration over the inverse masses) to its pair's force
    over the step, unless forces are not reported (``solve.force_scale`` 0: ``ContactSystem.report_forces`` off, no
    atomic add). A correction of a pair that moves held tets' vertices flags the env as moving (``ParticleSolve``): a
    body held under a load must be solved again when the load goes, which no velocity would show."""
    if solve.wakes.shape[0] > 0:
        if solve.wakes[pair] != 0:
            solve.moving[env] = 1
    if solve.force_scale != 0.0:
        wp.atomic_add(reports.report_force, env, pair, impulse * solve.force_scale)


@wp.func
def apply_mean_delta(env: int, i: int, delta: wp.array3d(dtype=wp.int64), count: wp.array2d(dtype=wp.int32),
                     scale: float, q: wp.array2d(dtype=wp.vec3)):
    """Move particle ``i`` by the mean of its corrections (Jacobi with averaging: the fixed-point sum ``delta[env, i]``
    in units of ``1 / scale`` over ``count[env, i]`` contributions) and clear them; nothing where it has none."""
    c = count[env, i]
    if c > 0:
        d = wp.vec3(float(delta[env, i, 0]), float(delta[env, i, 1]), float(delta[env, i, 2]))
        q[env, i] = q[env, i] + d / (scale * float(c))
        for a in range(3):
            delta[env, i, a] = wp.int64(0)
        count[env, i] = 0

@wp.func
def sdf_primitive(kind: int, params: wp.vec3, p: wp.vec3):
    """Signed distance and outward normal of a primitive shape (no mesh) at local point ``p`` (vec4: nx, ny, nz,
    d); far away for a mesh or an unknown kind."""
    up = wp.vec3(0.0, 0.0, 1.0)
    if kind == SHAPE_SPHERE:
        n = safe_normalize(p, up)
        return wp.vec4(n[0], n[1], n[2], wp.length(p) - params[0])
    if kind == SHAPE_CAPSULE:
        # axis along local z, params = (radius, half height of the axis segment, -)
        c = wp.vec3(0.0, 0.0, wp.clamp(p[2], -params[1], params[1]))
        n = safe_normalize(p - c, wp.vec3(1.0, 0.0, 0.0))
        return wp.vec4(n[0], n[1], n[2], wp.length(p - c) - params[0])
    if kind == SHAPE_BOX:
        q = wp.vec3(wp.abs(p[0]) - params[0], wp.abs(p[1]) - params[1], wp.abs(p[2]) - params[2])
        qm = wp.max(q[0], wp.max(q[1], q[2]))
        if qm > 0.0:
            o = wp.vec3(wp.max(q[0], 0.0) * wp.sign(p[0]), wp.max(q[1], 0.0) * wp.sign(p[1]),
                        wp.max(q[2], 0.0) * wp.sign(p[2]))
            n = safe_normalize(o, up)
            return wp.vec4(n[0], n[1], n[2], wp.length(o))
        # inside: leave through the nearest face
        if q[0] >= q[1] and q[0] >= q[2]:
            return wp.vec4(wp.sign(p[0]), 0.0, 0.0, qm)
        if q[1] >= q[2]:
            return wp.vec4(0.0, wp.sign(p[1]), 0.0, qm)
        return wp.vec4(0.0, 0.0, wp.sign(p[2]), qm)
    if kind == SHAPE_PLANE:
        # half-space below the local xy plane; params unused
        return wp.vec4(0.0, 0.0, 1.0, p[2])
    if kind == SHAPE_CYLINDER:
        # axis along local z, params = (radius, half height, -)
        rho = wp.sqrt(p[0] * p[0] + p[1] * p[1])
        radial = wp.vec3(1.0, 0.0, 0.0)
        if rho > 1.0e-12:
            radial = wp.vec3(p[0] / rho, p[1] / rho, 0.0)
        axial = wp.vec3(0.0, 0.0, wp.sign(p[2]))
        dr = rho - params[0]
        dz = wp.abs(p[2]) - params[1]
        if dr > 0.0 and dz > 0.0:
            n = safe_normalize(radial * dr + axial * dz, up)
            return wp.vec4(n[0], n[1], n[2], wp.sqrt(dr * dr + dz * dz))
        if dr > dz:
            return wp.vec4(radial[0], radial[1], radial[2], dr)
        return wp.vec4(axial[0], axial[1], axial[2], dz)
    return wp.vec4(0.0, 0.0, 1.0, 1.0e6)


@wp.func
def sdf_local(kind: int, params: wp.vec3, mesh: wp.uint64, p: wp.vec3, max_dist: float):
    """Signed distance and outward normal of a shape at local point ``p`` (vec4: nx, ny, nz, d)."""
    if kind == SHAPE_MESH:
        # closed meshes: inside/outside from the normal at the closest point (angle-weighted at edges)
        res = wp.mesh_query_point_sign_normal(mesh, p, max_dist)
        if res.result:
            cp = wp.mesh_eval_position(mesh, res.face, res.u, res.v)
            delta = p - cp
            dist = wp.length(delta)
            fn = wp.mesh_eval_face_normal(mesh, res.face)
            n = fn
            if dist > 1.0e-9:
                n = delta / dist * res.sign
            return wp.vec4(n[0], n[1], n[2], dist * res.sign)
        return wp.vec4(0.0, 0.0, 1.0, 1.0e6)
    return sdf_primitive(kind, params, p)


@wp.func
def shape_pose(shapes: ShapeTable, s: int, env: int, motion: BodyMotion, blend: float):
    """World pose of shape ``s`` at the fraction ``blend`` of the step."""
    body = shapes.body[s]
    if body < 0:
        return shapes.local[s]
    return wp.transform_multiply(body_pose(motion, env, body, blend), shapes.local[s])


@wp.func
def ignored_bodies(ignore: IgnoreMask, env: int, i: int):
    """Bit mask of the bodies particle ``i`` passes through (0 without a mask)."""
    if ignore.enabled != 0:
        return ignore.bodies[env, i]
    return 0


@wp.func
def passes_through(shapes: ShapeTable, s: int, ignore: int):
    """Shape ``s`` rides on a body in the ``ignore`` bit mask (grasped particles do not collide with the jaws)."""
    return shapes.body[s] >= 0 and ((ignore >> shapes.body[s]) & 1) != 0


@wp.func
def particle_live(masks: CutMasks, env: int, i: int):
    """Particle ``i`` of ``env`` still belongs to a live element (always, where nothing is cut)."""
    if masks.particle_active.shape[1] == 0:
        return True
    return masks.particle_active[env, i] != 0


@wp.func
def start_position(solve: ParticleSolve, env: int, i: int):
    """Position of particle ``i`` at the start of this substep: the World predicted ``q_pred = x0 + v h`` and keeps
    ``v`` until the velocity update."""
    return solve.q_pred[env, i] - solve.qd[env, i] * solve.h


@wp.func
def record_contact(env: int, particle: int, shape: int, normal: wp.vec3, depth: float, reports: ContactReports):
    slot = wp.atomic_add(reports.contact_count, env, 1)
    if slot < reports.contact_particle.shape[1]:
        reports.contact_particle[env, slot] = particle
        reports.contact_shape[env, slot] = shape
        reports.contact_normal[env, slot] = normal
        reports.contact_depth[env, slot] = depth
    else:
        # a full buffer: take the count back, so that it ends at the capacity (the first record past it found the
        # count at the capacity with every slot below taken, and no later one can find it lower: no slot is handed
        # out twice), and raise the flags here, where a launch per world step clamped and ORed them before
        wp.atomic_sub(reports.contact_count, env, 1)
        reports.overflow[env] = 1
        if reports.overflow_sink.shape[0] > 0:
            reports.overflow_sink[env] = 1


@wp.func
def node_share(weight: float, inv_mass: float, inv_mass_sum: float):
    """Multiple of a contact point's correction that a node with barycentric ``weight`` moves by: the XPBD lever
    ``weight w / sum(weight^2 w)``, capped at ``MAX_NODE_SHARE``.

    With every node free the lever is at most ~1.2 (equal masses), but near a pinned node it grows like
    ``1 / weight``: a tool touching a triangle next to its pinned corner (weights ~(0.98, 0.01, 0.01)) threw the two
    free nodes ~50 x the penetration, tens of mm in one substep (PrecisionCutting's scissors at the cloth's fixed
    corners tripped the stability check at > 50 m/s). Such a contact cannot be resolved by moving the sheet (the
    point is held by the pin), so the free nodes take at most twice the correction and the rest of the penetration
    stays."""
    return wp.min(weight * inv_mass / inv_mass_sum, MAX_NODE_SHARE)


@wp.func
def friction_correction(rel: wp.vec3, n: wp.vec3, pen: float, mu: wp.vec2):
    """Positional Coulomb friction: the correction that cancels (static) or shortens (kinetic) the tangential
    part of the relative displacement ``rel`` of this substep."""
    t = rel - n * wp.dot(rel, n)
    lt = wp.length(t)
    if lt <= mu[0] * pen:
        return -t
    if lt > 0.0:
        return -t * wp.min(mu[1] * pen / lt, 1.0)
    return wp.vec3(0.0)


@wp.func
def shape_axis_end(shapes: ShapeTable, s: int, tf: wp.transform, side: float):
    """End ``side`` (-1 or +1) of the axis of a sphere (a point) or capsule shape, in the world frame."""
    hh = float(0.0)
    if shapes.kind[s] == SHAPE_CAPSULE:
        hh = shapes.params[s][1]
    return wp.transform_point(tf, wp.vec3(0.0, 0.0, side * hh))


# ----------------------------------------------------------------------------------------------------
# particles against shapes
# ----------------------------------------------------------------------------------------------------


@wp.struct
class ShapePoses:
    """Every shape's world pose and inverse at the end of the current substep, per env (``pose_shapes``, once per
    sweep), and its bounding radius about its local origin (``inf`` for planes and meshes: never culled).

    Cull groups: runs of consecutive shapes on one body (``group_start``, G + 1 entries) share a bounding sphere
    about ``group_centre`` (in the frame of the group's first shape) of ``group_radius`` (thicknesses included), so a
    particle far from, say, an eye's eleven spheres is culled once for all of them (``collide_particles``)."""

    tf: wp.array2d(dtype=wp.transform)
    tf_inv: wp.array2d(dtype=wp.transform)
    bound: wp.array(dtype=float)
    group_start: wp.array(dtype=wp.int32)
    group_centre: wp.array(dtype=wp.vec3)
    group_radius: wp.array(dtype=float)


@wp.func
def group_out_of_reach(poses: ShapePoses, env: int, grp: int, p: wp.vec3, reach: float):
    """Whether every shape of cull group ``grp`` lies beyond ``reach`` of ``p`` (the group's bounding sphere, which
    holds each shape's sphere grown by its thickness; ``ShapePoses``). A group of one shape is left to that shape's
    own cull."""
    s0 = poses.group_start[grp]
    if poses.group_start[grp + 1] - s0 < 2:
        return False
    centre = wp.transform_point(poses.tf[env, s0], poses.group_centre[grp])
    return wp.length(p - centre) > poses.group_radius[grp] + reach


@wp.kernel
def pose_shapes(shapes: ShapeTable, motion: BodyMotion, clear: int, reports: ContactReports, poses: ShapePoses):
    """The substep's shape poses, once per (env, shape) instead of once per (particle, shape): a pose interpolates
    the body's motion (a slerp), which ``collide_particles`` did for every particle against every shape. With
    ``clear`` (a step's first sweep) shape 0's thread also clears the env's contact reports (a launch fewer)."""
    env, s = wp.tid()
    if clear != 0 and s == 0:
        clear_env_reports(env, reports)
    tf = shape_pose(shapes, s, env, motion, motion.blend)
    poses.tf[env, s] = tf
    poses.tf_inv[env, s] = wp.transform_inverse(tf)


@wp.kernel
def pose_shapes_substeps(shapes: ShapeTable, motion: BodyMotion, blends: wp.array(dtype=float), clear: int,
                         reports: ContactReports, tf: wp.array2d(dtype=wp.transform),
                         tf_inv: wp.array2d(dtype=wp.transform)):
    """``pose_shapes`` for every substep of a step in one launch (``ContactSystem.pose_per_step``): substep ``sub``'s
    poses (at the fraction ``blends[sub]`` of the step) at columns ``sub * S .. sub * S + S - 1``. The bodies move
    only between steps, so their poses at every substep are known at its start; ``motion``'s own blends go unused."""
    env, sub, s = wp.tid()
    if clear != 0 and sub == 0 and s == 0:
        clear_env_reports(env, reports)
    t = shape_pose(shapes, s, env, motion, blends[sub])
    column = sub * shapes.kind.shape[0] + s
    tf[env, column] = t
    tf_inv[env, column] = wp.transform_inverse(t)


_PARTICLE_FUNCS: dict = {}
_PARTICLE_KERNELS: dict = {}


def particle_collision_func(meshes: bool) -> wp.Function:
    """``collide_particle(env, k, ...)`` (cached per variant): contact particle ``k`` of ``env`` against the env's
    shapes, the body of ``collide_particles`` and of the rod launch that runs a substep's contact before the next
    substep's prediction (``xpbd.contact_rods_fused_kernel``). ``meshes`` False leaves out the mesh shapes'
    SDF query (see ``particle_collision_kernel``)."""
    func = _PARTICLE_FUNCS.get(bool(meshes))
    if func is not None:
        return func

    @wp.func
    def collide_particle(
        env: int,
        k: int,
        particles: ContactParticles,
        shapes: ShapeTable,
        motion: BodyMotion,
        poses: ShapePoses,
        solve: ParticleSolve,
        ignore: IgnoreMask,
        masks: CutMasks,
        report: int,
        report_margin: float,
        q: wp.array2d(dtype=wp.vec3),
        reports: ContactReports,
    ):
        i = particles.particle[k]
        w = solve.inv_mass[env % solve.inv_mass.shape[0], i]
        if w == 0.0:
            return
        if not particle_live(masks, env, i):
            return  # every element of the particle was cut away
        g = particles.group[k]
        r = particles.radius[k]
        x = q[env, i]
        # the particle's start of substep and its pass-through mask are read only where a shape is near (again for a
        # second shape: cached): most particles (a cavity's 750 nodes against an instrument) are culled for every
        # shape, and these loads were most of their memory traffic
        moved = int(0)
        for grp in range(poses.group_start.shape[0] - 1):
            # beyond the group's sphere by more than r + report margin, every shape below would be culled (x does
            # not move while none is touched)
            if group_out_of_reach(poses, env, grp, x, r + report_margin):
                continue
            for s in range(poses.group_start[grp], poses.group_start[grp + 1]):
                pair = shapes.pair_index[s, g]
                if pair < 0 or shapes.kind[s] == SHAPE_SURFACE:
                    continue
                reach = r + shapes.thickness[s]
                tf = poses.tf[env, s]
                # exact cull: beyond the shape's bounding sphere by more than reach + report margin there is neither
                # contact nor a report (pen <= -report_margin below)
                if wp.length(x - wp.transform_get_translation(tf)) > poses.bound[s] + reach + report_margin:
                    continue
                if passes_through(shapes, s, ignored_bodies(ignore, env, i)):
                    continue
                pl = wp.transform_point(poses.tf_inv[env, s], x)
                nd = wp.vec4()
                if wp.static(meshes):
                    nd = sdf_local(shapes.kind[s], shapes.params[s], shapes.mesh[s], pl,
                                   reach + report_margin + 1.0e-3)
                else:
                    nd = sdf_primitive(shapes.kind[s], shapes.params[s], pl)
                d = nd[3]
                pen = reach - d
                if report != 0 and pen > -report_margin:
                    wp.atomic_add(reports.report_count, env, pair, 1)
                    record_contact(env, i, s, wp.transform_vector(tf, wp.vec3(nd[0], nd[1], nd[2])), pen, reports)
                if pen <= 0.0:
                    continue
                n = wp.transform_vector(tf, wp.vec3(nd[0], nd[1], nd[2]))
                x = x + n * pen
                x0 = start_position(solve, env, i)
                # where the touched surface point was at the start of the substep (moving tools drag particles along)
                tf0 = shape_pose(shapes, s, env, motion, motion.blend_prev)
                xs0 = wp.transform_point(tf0, wp.transform_point(wp.transform_inverse(tf), x))
                x = x + friction_correction((x - x0) - (x - xs0), n, pen, shapes.mu[s])
                add_pair_force(reports, env, pair, pen / w, solve)
                moved = 1
        # only a moved particle is written: a particle in two groups (GraspLiftAndTouch's gallbladder surface meets the
        # instruments in one and the liver in another) has two threads here, and an unconditional write of the other
        # thread's stale copy would race
        if moved != 0:
            q[env, i] = x

    _PARTICLE_FUNCS[bool(meshes)] = collide_particle
    return collide_particle


def particle_collision_kernel(meshes: bool) -> wp.Kernel:
    """``collide_particles`` (cached per variant): the contact particles against the env's shapes
    (``particle_collision_func``), a thread each. ``meshes`` False leaves out the mesh shapes' SDF query (scenes without
    one): its BVH stack and registers went with it (sm_90: 108 -> 66 registers, a 128 -> 32 byte frame,
    ``benchmarks/kernel_resources.py``), so more warps fit an SM in the rod tasks' per-substep contact launch; the same
    arithmetic for every other shape."""
    kernel = _PARTICLE_KERNELS.get(bool(meshes))
    if kernel is not None:
        return kernel
    collide_particle = particle_collision_func(meshes)

    def collide_particles(
        particles: ContactParticles,
        shapes: ShapeTable,
        motion: BodyMotion,
        poses: ShapePoses,
        solve: ParticleSolve,
        ignore: IgnoreMask,
        masks: CutMasks,
        report: int,
        report_margin: float,
        q: wp.array2d(dtype=wp.vec3),
        reports: ContactReports,
    ):
        env, k = wp.tid()
        collide_particle(env, k, particles, shapes, motion, poses, solve, ignore, masks, report, report_margin, q,
                         reports)

    kernel = wp.kernel(collide_particles, module="unique", enable_backward=False)
    _PARTICLE_KERNELS[bool(meshes)] = kernel
    return kernel


# ----------------------------------------------------------------------------------------------------
# rod segments (capsules) against spheres and capsules: thin tools between rod nodes
# ----------------------------------------------------------------------------------------------------


@wp.func
def collide_segment(
    env: int,
    k: int,
    segments: ContactSegments,
    shapes: ShapeTable,
    motion: BodyMotion,
    poses: ShapePoses,
    solve: ParticleSolve,
    ignore: IgnoreMask,
    masks: CutMasks,
    q: wp.array2d(dtype=wp.vec3),
    reports: ContactReports,
):
    """Segment ``k``'s interior against the env's capsules and spheres (its nodes are ``collide_particles``')."""
    if masks.seg_col.shape[0] > 0:
        # cuttable rods: a removed segment does not collide
        sc = masks.seg_col[k]
        if sc >= 0:
            if masks.segment_active[env, sc] == 0:
                return
    a = segments.nodes[k][0]
    b = segments.nodes[k][1]
    pe = env % solve.inv_mass.shape[0]
    wa = solve.inv_mass[pe, a]
    wb = solve.inv_mass[pe, b]
    if wa + wb == 0.0:
        return
    g = segments.group[k]
    xa = q[env, a]
    xb = q[env, b]
    ignore_bits = ignored_bodies(ignore, env, a) | ignored_bodies(ignore, env, b)
    for grp in range(poses.group_start.shape[0] - 1):
        # the group's bounding sphere against the segment's: beyond it, every shape is culled
        if group_out_of_reach(poses, env, grp, 0.5 * (xa + xb), segments.radius[k] + 0.5 * wp.length(xb - xa)):
            continue
        for s in range(poses.group_start[grp], poses.group_start[grp + 1]):
            kind = shapes.kind[s]
            pair = shapes.pair_index[s, g]
            if pair < 0 or kind > SHAPE_CAPSULE:
                continue
            if passes_through(shapes, s, ignore_bits):
                continue
            tf = poses.tf[env, s]
            # exact cull: the segment's bounding sphere against the shape's
            reach = segments.radius[k] + shapes.thickness[s] + poses.bound[s] + 0.5 * wp.length(xb - xa)
            if wp.length(0.5 * (xa + xb) - wp.transform_get_translation(tf)) > reach:
                continue
            c0 = shape_axis_end(shapes, s, tf, -1.0)
            c1 = shape_axis_end(shapes, s, tf, 1.0)
            st = closest_segment_segment(xa, xb, c0, c1)
            u = st[0]
            # the nodes themselves are handled by collide_particles; here only the segment interior
            if u <= 0.0 or u >= 1.0:
                continue
            p = xa * (1.0 - u) + xb * u
            c = c0 * (1.0 - st[1]) + c1 * st[1]
            n = safe_normalize(p - c, wp.vec3(0.0, 0.0, 1.0))
            pen = segments.radius[k] + shapes.params[s][0] + shapes.thickness[s] - wp.length(p - c)
            if pen <= 0.0:
                continue
            # point correction distributed to the nodes with barycentric weights (Mueller et al. 2020)
            wsum = (1.0 - u) * (1.0 - u) * wa + u * u * wb
            # friction on the relative motion of the contact point during this substep
            pa0 = start_position(solve, env, a)
            pb0 = start_position(solve, env, b)
            tf0 = shape_pose(shapes, s, env, motion, motion.blend_prev)
            c_0 = wp.transform_point(tf0, wp.transform_point(wp.transform_inverse(tf), c))
            rel = (p + n * pen - (pa0 * (1.0 - u) + pb0 * u)) - (c - c_0)
            dp = n * pen + friction_correction(rel, n, pen, shapes.mu[s])
            xa = xa + dp * node_share(1.0 - u, wa, wsum)
            xb = xb + dp * node_share(u, wb, wsum)
            add_pair_force(reports, env, pair, pen / wsum, solve)
    q[env, a] = xa
    q[env, b] = xb


@wp.kernel
def collide_segments(
    segments: ContactSegments,
    start: int,
    shapes: ShapeTable,
    motion: BodyMotion,
    poses: ShapePoses,
    solve: ParticleSolve,
    ignore: IgnoreMask,
    masks: CutMasks,
    q: wp.array2d(dtype=wp.vec3),
    reports: ContactReports,
):
    """One colour of segments from ``start`` (segments of one colour share no node: no write races), a thread each."""
    env, k0 = wp.tid()
    collide_segment(env, start + k0, segments, shapes, motion, poses, solve, ignore, masks, q, reports)


@wp.kernel
def collide_segment_colors(
    segments: ContactSegments,
    color_offsets: wp.array(dtype=wp.int32),
    shapes: ShapeTable,
    motion: BodyMotion,
    poses: ShapePoses,
    solve: ParticleSolve,
    ignore: IgnoreMask,
    masks: CutMasks,
    q: wp.array2d(dtype=wp.vec3),
    reports: ContactReports,
):
    """Every colour of segments in one launch: a thread block per env whose lanes take a colour's segments side by
    side, a block barrier between colours (positions in global memory, which the barrier makes visible to the block).
    The same function per segment as ``collide_segments`` in the same order on the CPU (one lane): bit-identical
    there. RopeCutting's 95 segments per env in 2 colours were 2 launches per substep."""
    env, lane = wp.tid()
    lanes = wp.block_dim()
    barrier = wp.tile_zeros(shape=1, dtype=int, storage="shared")
    for color in range(color_offsets.shape[0] - 1):
        for k in range(color_offsets[color] + lane, color_offsets[color + 1], lanes):
            collide_segment(env, k, segments, shapes, motion, poses, solve, ignore, masks, q, reports)
        wp.tile_scatter_masked(barrier, 0, 0, False)  # a block barrier (nothing written)


# ----------------------------------------------------------------------------------------------------
# triangles: cloth / tissue-surface triangles against tool spheres and capsules, particles against the
# deforming triangle surface of another object (each env's own boxes over a shared clustering)
# ----------------------------------------------------------------------------------------------------


@wp.struct
class ToolAxes:
    """The sphere and capsule colliders of every env at the end of the current substep, computed once per sweep
    for the triangle passes: axis ends ``(num_envs, shapes)`` and one padded box around all of them per env. Most
    triangles of a sheet are far from every tool and return after comparing their box with the env's."""

    c0: wp.array2d(dtype=wp.vec3)
    c1: wp.array2d(dtype=wp.vec3)
    # a triangle touching a tool needs the tool's pose at the substep start (tf0: which side the tool came from) and
    # its motion over the substep (back = tf0 * tf^-1 maps a point on the tool to where it was, for friction);
    # blending the body poses per triangle and shape, as before, cost more than the contact itself
    tf0: wp.array2d(dtype=wp.transform)
    back: wp.array2d(dtype=wp.transform)
    lo: wp.array(dtype=wp.vec3)
    hi: wp.array(dtype=wp.vec3)
    # each tool's own box, oriented along its axis (the shape-code sweep, ``shape_codes``): centre, rotation into the
    # box's frame (rows: two unit normals of the axis, then the axis) and half extents, padded like the env's box
    box_centre: wp.array2d(dtype=wp.vec3)
    box_frame: wp.array2d(dtype=wp.mat33)
    box_half: wp.array2d(dtype=wp.vec3)


@wp.func
def pose_env_shapes_and_tools(shapes: ShapeTable, motion: BodyMotion, blend: float, blend_prev: float, pad: float,
                              boxes: int, env: int, lane: int, lanes: int, col: int, poses: ShapePoses,
                              axes: ToolAxes):
    """One env's shape poses and tool axes at the fraction ``blend`` of the step (the substep's start at
    ``blend_prev``), written at columns ``col + s``; every lane of the env's block calls it (its box is a block-wide
    minimum and maximum). Returns the env's padded tool box ``(lo, hi)``."""
    lo = wp.vec3(1.0e30)
    hi = wp.vec3(-1.0e30)
    for s in range(lane, shapes.kind.shape[0], lanes):
        tf = shape_pose(shapes, s, env, motion, blend)
        poses.tf[env, col + s] = tf
        poses.tf_inv[env, col + s] = wp.transform_inverse(tf)
        if shapes.kind[s] > SHAPE_CAPSULE:
            continue
        a = shape_axis_end(shapes, s, tf, -1.0)
        b = shape_axis_end(shapes, s, tf, 1.0)
        axes.c0[env, col + s] = a
        axes.c1[env, col + s] = b
        tf0 = shape_pose(shapes, s, env, motion, blend_prev)
        axes.tf0[env, col + s] = tf0
        axes.back[env, col + s] = wp.transform_multiply(tf0, wp.transform_inverse(tf))
        r = wp.vec3(shapes.params[s][0] + shapes.thickness[s])
        lo = wp.min(lo, wp.min(a, b) - r)
        hi = wp.max(hi, wp.max(a, b) + r)
        if boxes != 0:
            # the oriented box: half the axis plus the padded radius along it, the padded radius across
            w = b - a
            half_len = 0.5 * wp.length(w)
            w = wp.vec3(0.0, 0.0, 1.0)
            if half_len > 0.0:
                w = (b - a) / (2.0 * half_len)
            e = wp.vec3(1.0, 0.0, 0.0)
            if wp.abs(w[0]) > 0.7:
                e = wp.vec3(0.0, 1.0, 0.0)
            u = wp.normalize(wp.cross(w, e))
            reach = r[0] + pad
            axes.box_centre[env, col + s] = 0.5 * (a + b)
            axes.box_frame[env, col + s] = wp.matrix_from_rows(u, wp.cross(w, u), w)
            axes.box_half[env, col + s] = wp.vec3(reach, reach, half_len + reach)
    box_lo = wp.vec3(wp.tile_extract(wp.tile_min(wp.tile(lo[0])), 0), wp.tile_extract(wp.tile_min(wp.tile(lo[1])), 0),
                     wp.tile_extract(wp.tile_min(wp.tile(lo[2])), 0))
    box_hi = wp.vec3(wp.tile_extract(wp.tile_max(wp.tile(hi[0])), 0), wp.tile_extract(wp.tile_max(wp.tile(hi[1])), 0),
                     wp.tile_extract(wp.tile_max(wp.tile(hi[2])), 0))
    return box_lo - wp.vec3(pad), box_hi + wp.vec3(pad)


@wp.kernel
def pose_shapes_and_tools(shapes: ShapeTable, motion: BodyMotion, pad: float, clear: int, boxes: int,
                          reports: ContactReports, poses: ShapePoses, axes: ToolAxes):
    """``pose_shapes`` and the tool axes of the triangle passes in one launch (a system with contact triangles): both
    are a few transforms per env, nearly all launch cost when apart. A thread block per env (launch ``(num_envs,
    lanes)``), its lanes over the shapes, then the env's tool box as a block-wide minimum and maximum: one thread
    walking the shapes was latency-bound (TissueDissection: 0.525 ms of its 21.1 ms step, H200). On the CPU one lane
    walks them in order. With ``clear`` (a step's first sweep) lane 0 also clears the env's contact reports; with
    ``boxes`` (the shape-code sweep) each tool's own box along its axis is formed too."""
    env, lane = wp.tid()
    lanes = wp.block_dim()
    if clear != 0 and lane == 0:
        clear_env_reports(env, reports)
    lo, hi = pose_env_shapes_and_tools(shapes, motion, motion.blend, motion.blend_prev, pad, boxes, env, lane, lanes,
                                       0, poses, axes)
    if lane == 0:
        axes.lo[env] = lo
        axes.hi[env] = hi


@wp.kernel
def pose_shapes_and_tools_substeps(shapes: ShapeTable, motion: BodyMotion, blends: wp.array(dtype=float),
                                   blends_prev: wp.array(dtype=float), pad: float, clear: int, boxes: int,
                                   reports: ContactReports, poses: ShapePoses, axes: ToolAxes,
                                   lo_all: wp.array2d(dtype=wp.vec3), hi_all: wp.array2d(dtype=wp.vec3)):
    """``pose_shapes_and_tools`` for every substep of a step in one launch (``ContactSystem.pose_per_step``):
    substep ``sub``'s poses and axes at columns ``sub * S ..`` of ``poses`` / ``axes`` and its box at
    ``lo_all[env, sub]``, ``hi_all[env, sub]`` (``axes.lo`` / ``axes.hi`` go unused)."""
    env, lane = wp.tid()
    lanes = wp.block_dim()
    if clear != 0 and lane == 0:
        clear_env_reports(env, reports)
    S = shapes.kind.shape[0]
    for sub in range(blends.shape[0]):
        lo, hi = pose_env_shapes_and_tools(shapes, motion, blends[sub], blends_prev[sub], pad, boxes, env, lane,
                                           lanes, sub * S, poses, axes)
        if lane == 0:
            lo_all[env, sub] = lo
            hi_all[env, sub] = hi


@wp.func
def outcode(x: wp.vec3, lo: wp.vec3, hi: wp.vec3) -> int:
    """Cohen-Sutherland outcode of ``x`` against the box ``[lo, hi]``: bit ``2 a`` set below ``lo[a]``, bit
    ``2 a + 1`` above ``hi[a]``. A triangle's bounding box misses the box exactly when its three vertices' codes share
    a set bit (its largest coordinate is below ``lo[a]`` iff every vertex's is): the cull of ``collide_triangle``."""
    code = int(0)
    for a in range(3):
        if x[a] < lo[a]:
            code = code | (1 << (2 * a))
        if x[a] > hi[a]:
            code = code | (2 << (2 * a))
    return code


@wp.func
def collide_triangle_at(
    env: int,
    k: int,
    tri: wp.vec3i,
    x0: wp.vec3,
    x1: wp.vec3,
    x2: wp.vec3,
    triangles: ContactTriangles,
    shapes: ShapeTable,
    axes: ToolAxes,
    solve: ParticleSolve,
    ignore: IgnoreMask,
    masks: CutMasks,
    reports: ContactReports,
):
    """The contact of triangle ``k`` (nodes ``tri`` at ``x0, x1, x2``, past the box cull) with the env's tools: the
    corrected positions and 1 where a tool pushed them (0: unchanged)."""
    touched = int(0)
    if masks.tri_col.shape[0] > 0:
        # cuttable objects: tri_col >= 0 is a cloth triangle (tri_active), <= -2 the tet face -2 - tri_col
        # (tet_face_active: only faces on the current surface collide), -1 always collides
        tc = masks.tri_col[k]
        if tc >= 0:
            if masks.tri_active[env, tc] == 0:
                return x0, x1, x2, touched
        elif tc <= -2:
            # a face two tets share is on the surface while either tet's face is (one tet present, one cut)
            on = masks.tet_face_active[env, -2 - tc]
            if on == 0 and masks.tri_col2.shape[0] > 0:
                partner = masks.tri_col2[k]
                if partner >= 0:
                    on = masks.tet_face_active[env, partner]
            if on == 0:
                return x0, x1, x2, touched
    pe = env % solve.inv_mass.shape[0]
    w0 = solve.inv_mass[pe, tri[0]]
    w1 = solve.inv_mass[pe, tri[1]]
    w2 = solve.inv_mass[pe, tri[2]]
    if w0 + w1 + w2 == 0.0:
        return x0, x1, x2, touched
    g = triangles.group[k]
    ignore_bits = ignored_bodies(ignore, env, tri[0]) | ignored_bodies(ignore, env, tri[1])
    ignore_bits = ignore_bits | ignored_bodies(ignore, env, tri[2])
    for s in range(shapes.kind.shape[0]):
        kind = shapes.kind[s]
        pair = shapes.pair_index[s, g]
        if pair < 0 or kind > SHAPE_CAPSULE:
            continue
        if passes_through(shapes, s, ignore_bits):
            continue
        c0 = axes.c0[env, s]
        c1 = axes.c1[env, s]
        # cheap reject (most triangles are far from the tool): bounding sphere about the centroid vs the axis
        cen = (x0 + x1 + x2) / 3.0
        bound = wp.sqrt(wp.max(wp.length_sq(x0 - cen), wp.max(wp.length_sq(x1 - cen), wp.length_sq(x2 - cen))))
        ax = c1 - c0
        u = wp.clamp(wp.dot(cen - c0, ax) / wp.max(wp.dot(ax, ax), 1.0e-20), 0.0, 1.0)
        if wp.length(cen - (c0 + ax * u)) > bound + triangles.radius[k] + shapes.params[s][0] + shapes.thickness[s]:
            continue
        cl = closest_segment_triangle(c0, c1, x0, x1, x2)
        bw = wp.vec3(cl[1], cl[2], cl[3])
        p = x0 * bw[0] + x1 * bw[1] + x2 * bw[2]
        c = c0 * (1.0 - cl[0]) + c1 * cl[0]
        pen = triangles.radius[k] + shapes.params[s][0] + shapes.thickness[s] - wp.length(p - c)
        if pen <= 0.0:
            continue
        fn = safe_normalize(wp.cross(x1 - x0, x2 - x0), wp.vec3(0.0, 0.0, 1.0))
        # axis touching the triangle: push to the side the tool came from (its centre at the substep start)
        side = wp.dot(p - wp.transform_get_translation(axes.tf0[env, s]), fn)
        if side < 0.0:
            fn = -fn
        n = safe_normalize(p - c, fn)
        wsum = bw[0] * bw[0] * w0 + bw[1] * bw[1] * w1 + bw[2] * bw[2] * w2
        if wsum <= 0.0:
            continue
        # friction on the relative motion of the contact point during this substep
        p0 = start_position(solve, env, tri[0]) * bw[0] + start_position(solve, env, tri[1]) * bw[1]
        p0 = p0 + start_position(solve, env, tri[2]) * bw[2]
        c_0 = wp.transform_point(axes.back[env, s], c)
        rel = (p + n * pen - p0) - (c - c_0)
        dp = n * pen + friction_correction(rel, n, pen, shapes.mu[s])
        x0 = x0 + dp * node_share(bw[0], w0, wsum)
        x1 = x1 + dp * node_share(bw[1], w1, wsum)
        x2 = x2 + dp * node_share(bw[2], w2, wsum)
        add_pair_force(reports, env, pair, pen / wsum, solve)
        touched = 1
    return x0, x1, x2, touched


@wp.func
def collide_triangle(
    env: int,
    k: int,
    triangles: ContactTriangles,
    shapes: ShapeTable,
    axes: ToolAxes,
    solve: ParticleSolve,
    ignore: IgnoreMask,
    masks: CutMasks,
    q: wp.array2d(dtype=wp.vec3),
    reports: ContactReports,
):
    """Triangle ``k`` of env ``env`` against the env's tools (capsules), over its interior: a tool resting on a
    triangle's interior is seen even where no vertex is near it, so a capsule moving ~its radius per substep cannot
    slip between the vertices of a tensioned sheet (vertex-only contact let it through at 1 mm per substep).
    The tests run cheapest-first: nearly every triangle is far from every tool, and the env's box test needs only
    the nodes and their positions, so the cut masks and inverse masses are read only for triangles near a tool
    (the colours of a fused sweep run one after another, so each dependent load here is paid in series)."""
    tri = triangles.nodes[k]
    x0 = q[env, tri[0]]
    x1 = q[env, tri[1]]
    x2 = q[env, tri[2]]
    # cull: the triangle's box against the box around every tool of the env (padded by the triangles' radius)
    tmin = wp.min(x0, wp.min(x1, x2))
    tmax = wp.max(x0, wp.max(x1, x2))
    lo = axes.lo[env]
    hi = axes.hi[env]
    if tmax[0] < lo[0] or tmax[1] < lo[1] or tmax[2] < lo[2] or tmin[0] > hi[0] or tmin[1] > hi[1] or tmin[2] > hi[2]:
        return
    y0, y1, y2, touched = collide_triangle_at(env, k, tri, x0, x1, x2, triangles, shapes, axes, solve, ignore, masks,
                                              reports)
    if touched != 0:
        q[env, tri[0]] = y0
        q[env, tri[1]] = y1
        q[env, tri[2]] = y2


@wp.kernel
def collide_triangles(
    triangles: ContactTriangles,
    start: int,
    shapes: ShapeTable,
    axes: ToolAxes,
    solve: ParticleSolve,
    ignore: IgnoreMask,
    masks: CutMasks,
    q: wp.array2d(dtype=wp.vec3),
    reports: ContactReports,
):
    """One colour of triangles (a colour shares no vertex), one thread per (env, triangle)."""
    env, k0 = wp.tid()
    collide_triangle(env, start + k0, triangles, shapes, axes, solve, ignore, masks, q, reports)


@wp.kernel
def collide_triangle_colors(
    triangles: ContactTriangles,
    color_offsets: wp.array(dtype=wp.int32),
    shapes: ShapeTable,
    axes: ToolAxes,
    solve: ParticleSolve,
    ignore: IgnoreMask,
    masks: CutMasks,
    q: wp.array2d(dtype=wp.vec3),
    reports: ContactReports,
):
    """Every colour in one launch: a thread block per env takes each colour's triangles in chunks of ``block_dim``,
    with a block barrier between colours (Gauss-Seidel across them, as one launch per colour). A colour is small
    (TissueDissection's flap faces are 28 colours per sweep) and most of its triangles are culled at once, so the
    per-colour launches were nearly all fixed cost. On the CPU a block has one lane: the same triangles in order."""
    env, lane = wp.tid()
    lanes = wp.block_dim()
    barrier = wp.tile_zeros(shape=1, dtype=int, storage="shared")
    for c in range(color_offsets.shape[0] - 1):
        end = color_offsets[c + 1]
        for base in range(color_offsets[c], end, lanes):
            if base + lane < end:
                collide_triangle(env, base + lane, triangles, shapes, axes, solve, ignore, masks, q, reports)
        # nothing written: a barrier, so the next colour reads the positions this one moved
        wp.tile_scatter_masked(barrier, 0, 0, False)


#: the most shapes the shape-code sweep codes (6 bits each in an int32)
SHAPE_CODE_MAX_SHAPES = 5


@wp.func
def shape_codes(x: wp.vec3, env: int, shapes: ShapeTable, axes: ToolAxes) -> int:
    """``outcode`` of ``x`` against each tool's own oriented box (``ToolAxes.box_*``), 6 bits per shape (shape ``s``
    in bits ``6 s .. 6 s + 5``); a shape that is no tool (not a sphere or capsule) sets all six, so it never passes a
    triangle. A triangle misses a box when its three vertices' codes share a bit of that box's six (all beyond one
    face plane of it): :func:`codes_meet` tells whether some box may meet it."""
    code = int(0)
    for s in range(shapes.kind.shape[0]):
        bits = int(63)
        if shapes.kind[s] <= SHAPE_CAPSULE:
            half = axes.box_half[env, s]
            bits = outcode(axes.box_frame[env, s] * (x - axes.box_centre[env, s]), -half, half)
        code = code | (bits << (6 * s))
    return code


@wp.func
def codes_meet(shared: int, num_shapes: int) -> bool:
    """Whether a triangle whose vertices' ``shape_codes`` AND to ``shared`` may meet some tool's box (a shape whose
    six bits are all clear in ``shared``)."""
    meet = int(0)
    for s in range(num_shapes):
        if (shared >> (6 * s)) & 63 == 0:
            meet = 1
    return meet != 0


# the outcode sweep keeps one int per particle of the triangles' window in shared memory
OUTCODE_MAX_PARTICLES = 8192
_OUTCODE_KERNELS: dict[tuple[int, bool], wp.Kernel] = {}


def collide_triangle_outcodes_kernel(window: int, per_shape: bool = False) -> wp.Kernel:
    """``collide_triangle_colors`` for a triangle set whose nodes lie in a window of ``window`` particles (a tile's
    shape is a compile-time constant, so one kernel per window size, cached): the same contacts in the same order,
    with the box cull read from shared memory.

    The fused sweep pays, per colour, a load of each lane's triangle and then of its three positions before the cull can
    reject it (TissueDissection: 28 colours in series, 46 before its tet faces were merged; 2 % of the triangles past
    the cull). Here the block first computes every window particle's outcode against the env's tool box (``outcode``: a
    particle load each, in parallel), then each colour tests its triangles by the AND of three shared codes, loading
    positions only for the triangles that pass; a triangle a tool pushed rewrites its three nodes' codes (a block
    barrier), so a later colour's test sees the moved nodes, as the fused sweep's position test does. Exact: a
    triangle's box misses the tool box iff its vertices' codes share a bit, and positions change within a launch only
    where a contact moves them (bit-identical to the fused sweep on the CPU, where a block has one lane).

    ``per_shape`` (the "shape_codes" sweep): the codes are ``shape_codes``, against each tool's own box along its axis,
    instead of one box around every tool: an instrument's shaft crossing a sheet at a slant spans a box over much of
    it (PrecisionCutting's 147 mm shaft: a 7 mm x 42 mm strip of its 75 mm cloth), and every triangle in that box paid
    the narrow phase's loads, one per lane of a warp that waited for all of them. The same contacts (a box never
    culls a triangle the narrow phase would touch: it holds the capsule grown by the triangles' largest radius)."""
    key = (int(window), bool(per_shape))
    kernel = _OUTCODE_KERNELS.get(key)
    if kernel is not None:
        return kernel
    P = key[0]
    PER_SHAPE = key[1]

    def collide_triangle_outcodes(
        triangles: ContactTriangles,
        color_offsets: wp.array(dtype=wp.int32),
        first: int,
        shapes: ShapeTable,
        axes: ToolAxes,
        solve: ParticleSolve,
        ignore: IgnoreMask,
        masks: CutMasks,
        q: wp.array2d(dtype=wp.vec3),
        reports: ContactReports,
    ):
        env, lane = wp.tid()
        lanes = wp.block_dim()
        lo = axes.lo[env]
        hi = axes.hi[env]
        num_shapes = shapes.kind.shape[0]
        codes = wp.tile_zeros(shape=P, dtype=int, storage="shared")
        for base in range(0, P, lanes):
            i = wp.min(base + lane, P - 1)
            code = int(0)
            if wp.static(PER_SHAPE):
                code = shape_codes(q[env, first + i], env, shapes, axes)
            else:
                code = outcode(q[env, first + i], lo, hi)
            wp.tile_scatter_masked(codes, i, code, base + lane < P)
        colors = color_offsets.shape[0] - 1
        for c in range(colors):
            start = color_offsets[c]
            end = color_offsets[c + 1]
            for base in range(start, end, lanes):
                # every lane runs the cooperative scatters below, the ones past the colour's end with nothing
                k = wp.min(base + lane, end - 1)
                tri = triangles.nodes[k]
                i0 = tri[0] - first
                i1 = tri[1] - first
                i2 = tri[2] - first
                shared = wp.tile_extract(codes, i0) & wp.tile_extract(codes, i1) & wp.tile_extract(codes, i2)
                meet = bool(shared == 0)
                if wp.static(PER_SHAPE):
                    meet = codes_meet(shared, num_shapes)
                x0 = wp.vec3(0.0)
                x1 = wp.vec3(0.0)
                x2 = wp.vec3(0.0)
                touched = int(0)
                if base + lane < end and meet:
                    x0, x1, x2, touched = collide_triangle_at(env, k, tri, q[env, tri[0]], q[env, tri[1]],
                                                              q[env, tri[2]], triangles, shapes, axes, solve, ignore,
                                                              masks, reports)
                    if touched != 0:
                        q[env, tri[0]] = x0
                        q[env, tri[1]] = x1
                        q[env, tri[2]] = x2
                moved = touched != 0
                code0 = int(0)
                code1 = int(0)
                code2 = int(0)
                if moved:
                    if wp.static(PER_SHAPE):
                        code0 = shape_codes(x0, env, shapes, axes)
                        code1 = shape_codes(x1, env, shapes, axes)
                        code2 = shape_codes(x2, env, shapes, axes)
                    else:
                        code0 = outcode(x0, lo, hi)
                        code1 = outcode(x1, lo, hi)
                        code2 = outcode(x2, lo, hi)
                wp.tile_scatter_masked(codes, i0, code0, moved)
                wp.tile_scatter_masked(codes, i1, code1, moved)
                wp.tile_scatter_masked(codes, i2, code2, moved)

    kernel = wp.kernel(collide_triangle_outcodes, module="unique", enable_backward=False)
    _OUTCODE_KERNELS[key] = kernel
    return kernel


@wp.func
def box_gap_sq(p: wp.vec3, lo: wp.vec3, hi: wp.vec3):
    """Squared distance from ``p`` to the box ``[lo, hi]`` (0 inside): a sphere about ``p`` meets the box when it
    is at most the radius squared."""
    gx = wp.max(wp.max(lo[0] - p[0], p[0] - hi[0]), 0.0)
    gy = wp.max(wp.max(lo[1] - p[1], p[1] - hi[1]), 0.0)
    gz = wp.max(wp.max(lo[2] - p[2], p[2] - hi[2]), 0.0)
    return gx * gx + gy * gy + gz * gz


@wp.kernel
def collide_surface(
    particles: ContactParticles,
    candidates: wp.array(dtype=wp.int32),
    surface: ContactSurface,
    shapes: ShapeTable,
    solve: ParticleSolve,
    masks: CutMasks,
    report: int,
    report_margin: float,
    q: wp.array2d(dtype=wp.vec3),
    surf_delta: wp.array3d(dtype=wp.int64),
    surf_count: wp.array2d(dtype=wp.int32),
    reports: ContactReports,
):
    # Particles of one object against the deforming triangles of another in the same env: the env's own leaf and
    # super-leaf boxes (written this sweep, before this launch) lead to its triangles, so envs never see each other
    # although all of them sit at the origin. Two-way: the triangle's share of the correction goes to surf_delta
    # (averaged later).
    # ``candidates``: the contact particles whose group pairs with this surface, minus its own vertices.
    env, k0 = wp.tid()
    k = candidates[k0]
    g = particles.group[k]
    pair = shapes.pair_index[surface.shape, g]
    if pair < 0:
        return
    i = particles.particle[k]
    if i >= surface.owner_start and i < surface.owner_end:
        return  # a surface does not collide with its own vertices
    if not particle_live(masks, env, i):
        return
    pe = env % solve.inv_mass.shape[0]
    w = solve.inv_mass[pe, i]
    x = q[env, i]
    reach = particles.radius[k] + shapes.thickness[surface.shape]
    tris = surface.tris
    ntri = tris.shape[0]
    # swept query (the particle's path during this substep): a particle that crossed a surface within one
    # substep still finds the triangle it crossed; the side / inside test below then pushes it back
    xs = start_position(solve, env, i)
    centre = (x + xs) * 0.5
    radius = wp.length(x - xs) * 0.5 + reach + report_margin
    radius_sq = radius * radius
    # The boxes were computed from this sweep's vertex positions: super leaves, then the leaves of those the sphere
    # meets, then the triangles of the leaves it meets, each triangle kept only if its own bounds meet the sphere
    num_leaves = surface.leaf_lo.shape[1]
    best = int(-1)
    best_d = float(1.0e30)
    best_bw = wp.vec3(0.0)
    for s in range(surface.super_lo.shape[1]):
        if box_gap_sq(centre, surface.super_lo[env, s], surface.super_hi[env, s]) > radius_sq:
            continue
        for leaf in range(s * surface.leaves_per_super, wp.min((s + 1) * surface.leaves_per_super, num_leaves)):
            if box_gap_sq(centre, surface.leaf_lo[env, leaf], surface.leaf_hi[env, leaf]) > radius_sq:
                continue
            for f in range(leaf * surface.leaf_size, wp.min((leaf + 1) * surface.leaf_size, ntri)):
                if surface.face_col.shape[0] > 0:
                    # cuttable surface: removed triangles / tet faces off the current surface do not collide
                    if surface.face_active[env, surface.face_col[f]] == 0:
                        continue
                t = tris[f]
                ta = q[env, t[0]]
                tb = q[env, t[1]]
                tc = q[env, t[2]]
                if box_gap_sq(centre, wp.min(wp.min(ta, tb), tc), wp.max(wp.max(ta, tb), tc)) > radius_sq:
                    continue
                bw = closest_point_triangle(x, ta, tb, tc)
                d = wp.length(x - (ta * bw[0] + tb * bw[1] + tc * bw[2]))
                if d < best_d:
                    best_d = d
                    best = f
                    best_bw = bw
    if best < 0:
        return
    t = tris[best]
    a = q[env, t[0]]
    b = q[env, t[1]]
    c = q[env, t[2]]
    cp = a * best_bw[0] + b * best_bw[1] + c * best_bw[2]
    fn = safe_normalize(wp.cross(b - a, c - a), wp.vec3(0.0, 0.0, 1.0))
    side = float(1.0)
    n = fn
    d = best_d
    if surface.closed != 0:
        # closed tissue surface wound outwards: inside when behind the closest face
        if wp.dot(x - cp, fn) < 0.0:
            side = -1.0
        if best_d > 1.0e-9:
            n = (x - cp) / best_d * side
        d = best_d * side
    else:
        # open sheet: the particle belongs on the side it was at the start of the substep (it cannot be
        # pushed through a cloth it crossed during the substep)
        a0 = start_position(solve, env, t[0])
        b0 = start_position(solve, env, t[1])
        c0 = start_position(solve, env, t[2])
        x0 = start_position(solve, env, i)
        fn0 = wp.cross(b0 - a0, c0 - a0)
        s0 = wp.dot(x0 - (a0 * best_bw[0] + b0 * best_bw[1] + c0 * best_bw[2]), fn0)
        s1 = wp.dot(x - cp, fn)
        if s0 < 0.0:
            n = -fn
        if best_d > 1.0e-9 and s0 * s1 >= 0.0:
            n = (x - cp) / best_d
            d = best_d
        else:
            d = -best_d
    pen = reach - d
    if report != 0 and pen > -report_margin:
        wp.atomic_add(reports.report_count, env, pair, 1)
        record_contact(env, i, surface.shape, n, pen, reports)
    if pen <= 0.0:
        return
    w0 = solve.inv_mass[pe, t[0]]
    w1 = solve.inv_mass[pe, t[1]]
    w2 = solve.inv_mass[pe, t[2]]
    wt = best_bw[0] * best_bw[0] * w0 + best_bw[1] * best_bw[1] * w1 + best_bw[2] * best_bw[2] * w2
    if w + wt <= 0.0:
        return
    # friction on the motion of the particle relative to the surface point during this substep
    x0p = start_position(solve, env, i)
    cp0 = start_position(solve, env, t[0]) * best_bw[0] + start_position(solve, env, t[1]) * best_bw[1]
    cp0 = cp0 + start_position(solve, env, t[2]) * best_bw[2]
    rel = (x - x0p) - (cp - cp0)
    dp = n * pen + friction_correction(rel, n, pen, shapes.mu[surface.shape])
    q[env, i] = x + dp * (w / (w + wt))
    for j in range(3):
        wj = solve.inv_mass[pe, t[j]]
        # only a vertex the contact moves counts in its average: the far vertex of a triangle touched on an edge
        # (weight 0) would otherwise dilute that vertex's other corrections, and two triangles tied across that
        # edge would move the surface differently
        if wj > 0.0 and best_bw[j] > 0.0:
            share = -dp * node_share(best_bw[j], wj, w + wt)
            for axis in range(3):  # fixed point: integer sums do not depend on the order of the atomics
                wp.atomic_add(surf_delta, env, t[j], axis, wp.int64(wp.round(share[axis] * SURFACE_DELTA_SCALE)))
            wp.atomic_add(surf_count, env, t[j], 1)
    add_pair_force(reports, env, pair, pen / (w + wt), solve)


@wp.func
def leaf_box(leaf_vert_start: wp.array(dtype=wp.int32), leaf_verts: wp.array(dtype=wp.int32),
             q: wp.array2d(dtype=wp.vec3), env: int, leaf: int):
    """The box (lo, hi) of env ``env``'s vertices of ``leaf`` as they are now."""
    lo = wp.vec3(1.0e30)
    hi = wp.vec3(-1.0e30)
    for k in range(leaf_vert_start[leaf], leaf_vert_start[leaf + 1]):
        x = q[env, leaf_verts[k]]
        lo = wp.min(lo, x)
        hi = wp.max(hi, x)
    return lo, hi


@wp.kernel
def surface_leaf_bounds(leaf_vert_start: wp.array(dtype=wp.int32), leaf_verts: wp.array(dtype=wp.int32),
                        q: wp.array2d(dtype=wp.vec3), hold: TetHold, leaf_lo: wp.array2d(dtype=wp.vec3),
                        leaf_hi: wp.array2d(dtype=wp.vec3)):
    """Each env's leaf boxes from its vertices as they are now (a thread per env and leaf). A held env's (``hold``:
    the surface of held tets, ``after`` 0 otherwise; ``hold.tets_held_now``) stay as they are: its vertices have not
    moved since they were computed."""
    env, leaf = wp.tid()
    if tets_held_now(hold, env):
        return
    lo, hi = leaf_box(leaf_vert_start, leaf_verts, q, env, leaf)
    leaf_lo[env, leaf] = lo
    leaf_hi[env, leaf] = hi


@wp.kernel
def surface_super_bounds(leaf_lo: wp.array2d(dtype=wp.vec3), leaf_hi: wp.array2d(dtype=wp.vec3),
                         leaves_per_super: int, hold: TetHold, super_lo: wp.array2d(dtype=wp.vec3),
                         super_hi: wp.array2d(dtype=wp.vec3)):
    """Each env's super-leaf boxes: the union of their leaves' boxes (a thread per env and super leaf); a held env's
    stay (``surface_leaf_bounds``)."""
    env, s = wp.tid()
    if tets_held_now(hold, env):
        return
    lo = wp.vec3(1.0e30)
    hi = wp.vec3(-1.0e30)
    for leaf in range(s * leaves_per_super, wp.min((s + 1) * leaves_per_super, leaf_lo.shape[1])):
        lo = wp.min(lo, leaf_lo[env, leaf])
        hi = wp.max(hi, leaf_hi[env, leaf])
    super_lo[env, s] = lo
    super_hi[env, s] = hi


_SURFACE_BOUNDS_KERNELS: dict[int, wp.Kernel] = {}


def surface_bounds_kernel(num_leaves: int) -> wp.Kernel:
    """``surface_leaf_bounds`` and ``surface_super_bounds`` in one launch (``ContactSystem.surface_bounds`` "fused";
    cached per leaf count: a tile's shape is a compile-time constant): a thread block per env, whose lanes take the
    leaves (each leaf's box from its vertices, written out and kept in shared memory), then the super leaves (each the
    union of its leaves' boxes, read from shared memory). The same boxes (a minimum or maximum is exact in any order),
    one launch per sweep instead of two and no pass over the leaf boxes in global memory; launch ``(num_envs,
    lanes)`` with ``block_dim=lanes`` (on the CPU one lane takes every leaf, then every super leaf). A held env's boxes
    stay (``surface_leaf_bounds``)."""
    L = int(num_leaves)
    kernel = _SURFACE_BOUNDS_KERNELS.get(L)
    if kernel is not None:
        return kernel

    def surface_bounds(leaf_vert_start: wp.array(dtype=wp.int32), leaf_verts: wp.array(dtype=wp.int32),
                       leaves_per_super: int, q: wp.array2d(dtype=wp.vec3), hold: TetHold,
                       leaf_lo: wp.array2d(dtype=wp.vec3), leaf_hi: wp.array2d(dtype=wp.vec3),
                       super_lo: wp.array2d(dtype=wp.vec3), super_hi: wp.array2d(dtype=wp.vec3)):
        env, lane = wp.tid()
        if tets_held_now(hold, env):
            return  # every lane: the same values
        lanes = wp.block_dim()
        los = wp.tile_zeros(shape=L, dtype=wp.vec3, storage="shared")
        his = wp.tile_zeros(shape=L, dtype=wp.vec3, storage="shared")
        for base in range(0, L, lanes):
            # every lane runs the cooperative scatters below, the ones past the last leaf with nothing
            leaf = wp.min(base + lane, L - 1)
            live = base + lane < L
            lo = wp.vec3(1.0e30)
            hi = wp.vec3(-1.0e30)
            if live:
                lo, hi = leaf_box(leaf_vert_start, leaf_verts, q, env, leaf)
                leaf_lo[env, leaf] = lo
                leaf_hi[env, leaf] = hi
            wp.tile_scatter_masked(los, leaf, lo, live)
            wp.tile_scatter_masked(his, leaf, hi, live)
        for s in range(lane, super_lo.shape[1], lanes):
            lo = wp.vec3(1.0e30)
            hi = wp.vec3(-1.0e30)
            for leaf in range(s * leaves_per_super, wp.min((s + 1) * leaves_per_super, L)):
                lo = wp.min(lo, wp.tile_extract(los, leaf))
                hi = wp.max(hi, wp.tile_extract(his, leaf))
            super_lo[env, s] = lo
            super_hi[env, s] = hi

    kernel = wp.kernel(surface_bounds, module="unique", enable_backward=False)
    _SURFACE_BOUNDS_KERNELS[L] = kernel
    return kernel


@wp.kernel
def apply_surface_deltas(verts: wp.array(dtype=wp.int32), surf_delta: wp.array3d(dtype=wp.int64),
                         surf_count: wp.array2d(dtype=wp.int32), q: wp.array2d(dtype=wp.vec3)):
    # Jacobi with averaging: a vertex pushed by several particles moves by their mean correction
    env, k = wp.tid()
    apply_mean_delta(env, verts[k], surf_delta, surf_count, SURFACE_DELTA_SCALE, q)


# ----------------------------------------------------------------------------------------------------
# particle-particle contact (deformable vs deformable, rod self-contact), Jacobi with averaging
# ----------------------------------------------------------------------------------------------------


@wp.func
def chain_skipped(k: int, m: int, members: ParticleContactSet):
    """Members ``k`` and ``m`` are close neighbours along one chain (they touch at rest): no contact."""
    if m == k:
        return True
    if members.chain[m] == members.chain[k] and members.chain[k] >= 0:
        gap = wp.abs(members.chain_pos[m] - members.chain_pos[k])
        ln = members.chain_len[k]
        if ln > 0:
            gap = wp.min(gap, ln - gap)  # closed loop: cyclic distance along the chain
        if gap <= members.skip_links:
            return True
    return False


@wp.func
def pair_correction(env: int, k: int, m: int, members: ParticleContactSet, pe: int, wi: float, xi: wp.vec3,
                    xi0: wp.vec3, solve: ParticleSolve, q: wp.array2d(dtype=wp.vec3)):
    """Correction of member k against member m (xyz) and the penetration (w; <= 0: no contact)."""
    j = members.particle[m]
    xj = q[env, j]
    dvec = xi - xj
    pen = members.radius[k] + members.radius[m] - wp.length(dvec)
    if pen <= 0.0:
        return wp.vec4(0.0, 0.0, 0.0, pen)
    wj = solve.inv_mass[pe, j]
    n = safe_normalize(dvec, wp.vec3(0.0, 0.0, 1.0))
    share = wi / (wi + wj)
    xj0 = start_position(solve, env, j)
    corr = n * (pen * share) + friction_correction((xi - xi0) - (xj - xj0), n, pen, members.mu) * share
    return wp.vec4(corr[0], corr[1], corr[2], pen / (wi + wj))


@wp.func
def report_pair_contact(env: int, k: int, c: wp.vec4, members: ParticleContactSet, solve: ParticleSolve,
                        report: int, reports: ContactReports):
    """Report one contact of member ``k`` (``c`` from pair_correction)."""
    pair = members.pair[k]
    if pair >= 0:
        # each pair is seen from both sides: half the force per side
        add_pair_force(reports, env, pair, 0.5 * c[3], solve)
        if report != 0:
            wp.atomic_add(reports.report_count, env, pair, 1)


@wp.kernel
def collide_particle_pairs(
    members: ParticleContactSet,
    solve: ParticleSolve,
    masks: CutMasks,
    report: int,
    q: wp.array2d(dtype=wp.vec3),
    delta: wp.array2d(dtype=wp.vec3),
    reports: ContactReports,
):
    # brute force over the (small) contact set of one env: below ~grid_threshold members (docs/contact.md) the
    # M^2 tests cost less than building and querying the per-env cell list, and envs never see each other
    env, k = wp.tid()
    i = members.particle[k]
    pe = env % solve.inv_mass.shape[0]
    wi = solve.inv_mass[pe, i]
    # a particle left without a live element (cut away) stays where it is and touches nothing
    if wi == 0.0 or not particle_live(masks, env, i):
        delta[env, k] = wp.vec3(0.0)
        return
    xi = q[env, i]
    xi0 = start_position(solve, env, i)
    acc = wp.vec3(0.0)
    cnt = int(0)
    for m in range(members.particle.shape[0]):
        if chain_skipped(k, m, members) or not particle_live(masks, env, members.particle[m]):
            continue
        c = pair_correction(env, k, m, members, pe, wi, xi, xi0, solve, q)
        if c[3] <= 0.0:
            continue
        acc = acc + wp.vec3(c[0], c[1], c[2])
        cnt += 1
        report_pair_contact(env, k, c, members, solve, report, reports)
    if cnt > 0:
        acc = acc / float(cnt)
    delta[env, k] = acc


# per-env cell list (spatial hash with counting sort): all envs sit at the origin, so one wp.HashGrid would mix
# them; instead every env owns ``H`` hash buckets in one flat array, filled by atomics, turned into offsets by
# one exclusive scan over all envs (env e's buckets start at e * M because each env holds exactly M members)


@wp.func
def cell_hash(c: wp.vec3i, H: int):
    hv = (c[0] * 73856093) ^ (c[1] * 19349663) ^ (c[2] * 83492791)
    return hv & (H - 1)


@wp.func
def cell_of(x: wp.vec3, inv_cell: float):
    return wp.vec3i(int(wp.floor(x[0] * inv_cell)), int(wp.floor(x[1] * inv_cell)), int(wp.floor(x[2] * inv_cell)))


@wp.kernel
def grid_count(members: ParticleContactSet, grid: CellGrid, q: wp.array2d(dtype=wp.vec3)):
    env, k = wp.tid()
    H = grid.buckets
    b = env * H + cell_hash(cell_of(q[env, members.particle[k]], grid.inv_cell), H)
    grid.member_bucket[env, k] = b
    grid.member_rank[env, k] = wp.atomic_add(grid.bucket_count, b, 1)


@wp.kernel
def grid_scatter(grid: CellGrid):
    env, k = wp.tid()
    grid.sorted_member[grid.bucket_start[grid.member_bucket[env, k]] + grid.member_rank[env, k]] = k


@wp.kernel
def collide_particle_pairs_grid(
    members: ParticleContactSet,
    grid: CellGrid,
    solve: ParticleSolve,
    masks: CutMasks,
    report: int,
    q: wp.array2d(dtype=wp.vec3),
    delta: wp.array2d(dtype=wp.vec3),
    reports: ContactReports,
):
    # same projection as collide_particle_pairs, over the members in the 27 cells around this one (cell size
    # >= the largest contact distance, so nothing farther can touch)
    env, k = wp.tid()
    i = members.particle[k]
    pe = env % solve.inv_mass.shape[0]
    wi = solve.inv_mass[pe, i]
    # a particle left without a live element (cut away) stays where it is and touches nothing
    if wi == 0.0 or not particle_live(masks, env, i):
        delta[env, k] = wp.vec3(0.0)
        return
    H = grid.buckets
    xi = q[env, i]
    xi0 = start_position(solve, env, i)
    ci = cell_of(xi, grid.inv_cell)
    acc = wp.vec3(0.0)
    cnt = int(0)
    for nb in range(27):
        b = env * H + cell_hash(ci + wp.vec3i(nb % 3 - 1, (nb / 3) % 3 - 1, nb / 9 - 1), H)
        # two neighbour cells may hash to the same bucket: visit each bucket once
        seen = int(0)
        for pb in range(nb):
            if env * H + cell_hash(ci + wp.vec3i(pb % 3 - 1, (pb / 3) % 3 - 1, pb / 9 - 1), H) == b:
                seen = 1
        if seen != 0:
            continue
        s0 = grid.bucket_start[b]
        for e in range(grid.bucket_count[b]):
            m = grid.sorted_member[s0 + e]
            if chain_skipped(k, m, members) or not particle_live(masks, env, members.particle[m]):
                continue
            c = pair_correction(env, k, m, members, pe, wi, xi, xi0, solve, q)
            if c[3] <= 0.0:
                continue
            acc = acc + wp.vec3(c[0], c[1], c[2])
            cnt += 1
            report_pair_contact(env, k, c, members, solve, report, reports)
    if cnt > 0:
        acc = acc / float(cnt)
    delta[env, k] = acc


@wp.kernel
def apply_particle_deltas(sp_particle: wp.array(dtype=wp.int32), delta: wp.array2d(dtype=wp.vec3),
                          q: wp.array2d(dtype=wp.vec3)):
    env, k = wp.tid()
    i = sp_particle[k]
    q[env, i] = q[env, i] + delta[env, k]


# ----------------------------------------------------------------------------------------------------
# reports
# ----------------------------------------------------------------------------------------------------


@wp.func
def clear_env_reports(env: int, reports: ContactReports):
    for p in range(reports.report_count.shape[1]):
        reports.report_count[env, p] = 0
        reports.report_force[env, p] = 0.0
    reports.contact_count[env] = 0
    reports.overflow[env] = 0


@wp.kernel
def clear_reports(reports: ContactReports):
    clear_env_reports(wp.tid(), reports)


@wp.kernel
def clear_reports_masked(env_mask: wp.array(dtype=wp.int32), reports: ContactReports):
    env = wp.tid()
    if env_mask[env] != 0:
        clear_env_reports(env, reports)
