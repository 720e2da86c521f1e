"""Per-vertex tet solve: vertex block descent (Chen et al. 2024) on the co-rotated tet energy.

XPBD projects each tet's constraints starting from zero multipliers every substep, so one sweep carries only part of
a stiff body's load: in the stiff regime (``h c / l`` >> 1) a body sags as if its compliance were ``~h^2 w |grad C|^2``
instead of its material's (LigatingLoop's 2 MPa cavity 12 mm instead of 0.15 mm). This solve works on positions
(the primal problem): each tet vertex takes one Newton step of the substep's incremental potential

    E(x) = m / (2 h^2) |x - x_pred|^2 + sum over incident tets V (mu |F - R|^2 + lambda / 2 (det F - 1)^2)

in its own position, with the other vertices fixed: ``dx = (m / h^2 I + H)^-1 (m / h^2 (x_pred - x) - dE_el/dx)``,
``H`` the Gauss-Newton Hessian (``R`` held: ``2 mu V |m_i|^2 I``; volume ``lambda V g g^T``), which bounds the true
one from above, so a step never overshoots. Vertices of one colour share no tet and move in parallel; the colours
follow each other (Gauss-Seidel). The elastic forces come from the current deformation, not from multipliers rebuilt
every substep, so the iteration's fixed point is the static equilibrium at any stiffness when it starts from the
inertial guess without the external acceleration (``begin_substep``: ``x = x_pred - h^2 a``, VBD's "inertia"
initialisation); with that start a sweep per substep reaches a stiff body's equilibrium in a number of substeps that
grows with its size, instead of settling at the wrong shape.

What it does not do: move a stiff body as a whole. Its rigid motion under gravity or a force comes from
Gauss-Seidel across its vertices, one colour at a time against the stiff tets, so a free 30 kPa block falls 3.7 cm in
0.5 s instead of 1.25 m (XPBD: exact, its prediction moves every particle). The World therefore takes this method
only for tet meshes anchored by pinned particles in every env (``World.tet_method``; a ValueError otherwise): clamped
tissue whose shape under load is the point (LigatingLoop's cavity, ThreadInHole's hole). Starting a free body from
the full prediction instead makes its free fall exact, but one sweep of per-vertex steps does not conserve momentum
(a vertex's step is not mirrored on its neighbours), so such a body resting on a mesh pressed on it with 1.47x its
weight and a block on an incline steep enough to slide stuck: XPBD's constraints, which move both ends, do not have
that problem.

The energy and its constraints are the XPBD tets' (``xpbd.tet_strain``: ``C_D = |F - R|``, ``C_H = det F - 1``
with compliances ``alpha_D = 1 / (2 mu V)``, ``alpha_H = 1 / (lambda V)``, ``alpha_H < 0`` = no volume term), so the
material, per-env parameters, cutting masks and the rotation warm start are shared with the XPBD path; the kernels
read the compliances' reciprocals (``world_kernels.tet_stiffness``, kept by the World), not dividing per incidence
(ThreadInHole's lagged sweep at its 64-register cap, sm_90: spill frame 32 -> 16 B, 1,576 -> 1,560 static
instructions).
"""

import warp as wp

from lapwarp.kernels.hold import TetHold, tets_held
from lapwarp.kernels.xpbd import cofactor, deformation_gradient, tet_removed, tet_strain

wp.set_module_options({"enable_backward": False})


@wp.kernel
def begin_substep(
    vertices: wp.array(dtype=wp.int32),
    inv_mass: wp.array2d(dtype=float),
    gravity: wp.vec3,
    h: float,
    active: wp.array2d(dtype=wp.int32),
    use_active: int,
    force: wp.array2d(dtype=wp.vec3),
    use_force: int,
    q_pred: wp.array2d(dtype=wp.vec3),
    q: wp.array2d(dtype=wp.vec3),
):
    """Start the tet vertices' solve from the inertial guess without the external acceleration,
    ``x = x_pred - h^2 (g + w f)`` (VBD's "inertia" initialisation); particles the prediction left in place
    (``w = 0`` or cut loose, as ``xpbd.integrate_particles`` decides) stay."""
    env, j = wp.tid()
    i = vertices[j]
    w = inv_mass[env % inv_mass.shape[0], i]
    if use_active != 0:
        if active[env, i] == 0:
            w = 0.0
    if w == 0.0:
        return
    if wp.length_sq(q[env, i] - q_pred[env, i]) > 0.0:
        return  # another constraint already moved it this substep: keep that
    acc = gravity
    if use_force != 0:
        acc = acc + force[env, i] * w
    q[env, i] = q_pred[env, i] - acc * (h * h)


@wp.func
def corner_row(Dm_inv: wp.mat33, corner: int):
    """``m``: d F / d x_corner = I (x) m, the corner's row of ``Dm^-1`` (corner 0: minus their sum). The rows are
    picked by constant indices: a run-time row index (``Dm_inv[corner - 1, k]``) put the matrix in local memory (an
    88-byte frame per thread in the fused kernel on sm_90, benchmarks/kernel_resources.py)."""
    row0 = wp.vec3(Dm_inv[0, 0], Dm_inv[0, 1], Dm_inv[0, 2])
    row1 = wp.vec3(Dm_inv[1, 0], Dm_inv[1, 1], Dm_inv[1, 2])
    row2 = wp.vec3(Dm_inv[2, 0], Dm_inv[2, 1], Dm_inv[2, 2])
    m = row2
    if corner == 0:
        m = -(row0 + row1 + row2)
    elif corner == 1:
        m = row0
    elif corner == 2:
        m = row1
    return m


@wp.func
def add_volume_term(f: wp.vec3, mm: float, k: wp.vec2, C_H: float, g: wp.vec3):
    """The vertex's force and Gauss-Newton Hessian block from its deviatoric force ``f`` (the Hessian ``|m|^2 /
    alpha_D I``, ``mm = |m|^2``) plus the volume term ``-g C_H / alpha_H``, ``g g^T / alpha_H``; ``k = (1 / alpha_D,
    1 / alpha_H)`` (``world_kernels.tet_stiffness``; ``k_H < 0``: ``lambda = 0``, no volume term)."""
    H = wp.identity(3, dtype=float) * (mm * k[0])
    if k[1] >= 0.0:
        f = f - g * (C_H * k[1])
        H = H + wp.outer(g, g) * k[1]
    return f, H


@wp.func
def tet_vertex_terms(
    env: int,
    c: int,
    corner: int,
    x0: wp.vec3, x1: wp.vec3, x2: wp.vec3, x3: wp.vec3,
    inv_rest: wp.array(dtype=wp.mat33),
    stiffness: wp.array2d(dtype=wp.vec2),
    rotation_iterations: int,
    tet_rotation: wp.array2d(dtype=wp.quat),
):
    """Tet ``c``'s elastic force on its vertex ``corner`` and that vertex's Gauss-Newton Hessian block. Every vertex
    extracts the tet's rotation (warm-started from the stored one) and the thread of corner 0 stores it: the tet's
    vertices have different colours, so no two threads touch it at once. (Letting the other three use the stored
    rotation as it is, a sweep old, slowed the 30 kPa block's approach to its sag: 8 % short after 2 s at 10
    substeps instead of 0.3 %; :func:`tet_vertex_terms_lagged` uses one refreshed at the sweep's start.)"""
    iters = int(0)
    q0 = wp.quat_identity()
    if tet_rotation.shape[1] > 0:
        iters = rotation_iterations
        q0 = tet_rotation[env, c]
    Dm_inv = inv_rest[c]
    C_D, C_H, qr, DC, cof = tet_strain(x0, x1, x2, x3, Dm_inv, q0, iters)
    if corner == 0 and iters > 0:
        tet_rotation[env, c] = qr
    k = stiffness[env % stiffness.shape[0], c]
    m = corner_row(Dm_inv, corner)
    d = DC * m
    g = cof * m
    return add_volume_term(-d * (C_D * k[0]), wp.dot(m, m), k, C_H, g)


@wp.func
def tet_vertex_terms_lagged(
    env: int,
    c: int,
    corner: int,
    x0: wp.vec3, x1: wp.vec3, x2: wp.vec3, x3: wp.vec3,
    inv_rest: wp.array(dtype=wp.mat33),
    stiffness: wp.array2d(dtype=wp.vec2),
    tet_rotation: wp.array2d(dtype=wp.quat),
):
    """:func:`tet_vertex_terms` with the tet's rotation as stored at the sweep's start (``xpbd.refresh_tet_rotations``;
    ``World.tet_rotation_update`` "sweep"): one extraction per tet and sweep instead of four. With ``R`` held,
    ``-C_D dC_D / dx = -(F - R) m``: the norm ``C_D`` and its division cancel (the co-rotated linear force).

    ``F``, its determinant and cofactor are formed here from the tet's four positions and ``Dm^-1`` (shared by the
    tet's four incidences, so they stay in cache): the vertex's terms written with per-incidence rest-shape factors
    instead (``F m_p = sum_{k != p} (m_k . m_p) (x_k - x_p)``, ``det F`` and ``cof(F) m_p`` from a triple and a cross
    product; 48 bytes per incidence against 8 and 52 per tet) halved the arithmetic but ran ThreadInHole's sweep 9.8 ->
    12.7 ms per env step (H200, 4,096 envs, forty-fifth session): this kernel waits on its loads, not its
    arithmetic."""
    Dm_inv = inv_rest[c]
    F = deformation_gradient(x0, x1, x2, x3, Dm_inv)
    k = stiffness[env % stiffness.shape[0], c]
    m = corner_row(Dm_inv, corner)
    f = -((F - wp.quat_to_matrix(tet_rotation[env, c])) * m) * k[0]
    return add_volume_term(f, wp.dot(m, m), k, wp.determinant(F) - 1.0, cofactor(F) * m)


@wp.func
def vertex_step(x: wp.vec3, x_pred: wp.vec3, w: float, inv_dt2: float, f: wp.vec3, H: wp.mat33):
    """The vertex's Newton step on the substep's incremental potential: ``x + (m / h^2 + H)^-1 (m / h^2 (x_pred - x)
    + f)``."""
    k = inv_dt2 / w
    A = H + wp.identity(3, dtype=float) * k
    return x + wp.inverse(A) * ((x_pred - x) * k + f)


@wp.kernel
def solve_vertices(
    start: int,
    vertices: wp.array(dtype=wp.int32),
    adj_offsets: wp.array(dtype=wp.int32),
    adj_tets: wp.array(dtype=wp.int32),
    adj_corners: wp.array(dtype=wp.int32),
    indices: wp.array(dtype=wp.vec4i),
    inv_rest: wp.array(dtype=wp.mat33),
    stiffness: wp.array2d(dtype=wp.vec2),
    inv_mass: wp.array2d(dtype=float),
    q_pred: wp.array2d(dtype=wp.vec3),
    inv_dt2: float,
    tet_element: wp.array(dtype=wp.int32),
    tet_active: wp.array2d(dtype=wp.int32),
    rotation_iterations: int,
    lagged: int,
    tet_rotation: wp.array2d(dtype=wp.quat),
    q: wp.array2d(dtype=wp.vec3),
):
    """The vertices of one colour, one thread per (env, vertex)."""
    env, t = wp.tid()
    j = start + t
    i = vertices[j]
    w = inv_mass[env % inv_mass.shape[0], i]
    if w == 0.0:
        return
    f = wp.vec3(0.0)
    H = wp.mat33(0.0)
    for a in range(adj_offsets[j], adj_offsets[j + 1]):
        c = adj_tets[a]
        if tet_removed(env, c, tet_element, tet_active):
            continue
        k = indices[c]
        x0 = q[env, k[0]]
        x1 = q[env, k[1]]
        x2 = q[env, k[2]]
        x3 = q[env, k[3]]
        fa = wp.vec3(0.0)
        Ha = wp.mat33(0.0)
        if lagged != 0:
            fa, Ha = tet_vertex_terms_lagged(env, c, adj_corners[a], x0, x1, x2, x3, inv_rest, stiffness,
                                             tet_rotation)
        else:
            fa, Ha = tet_vertex_terms(env, c, adj_corners[a], x0, x1, x2, x3, inv_rest, stiffness,
                                      rotation_iterations, tet_rotation)
        f = f + fa
        H = H + Ha
    q[env, i] = vertex_step(q[env, i], q_pred[env, i], w, inv_dt2, f, H)


_FUSED_KERNELS: dict = {}


def fused_vertex_kernel(tile_particles: int, lagged: bool = False):
    """``solve_vertices_fused`` for a particle window of ``tile_particles`` (cached per size and rotation update):
    one thread block per env runs every colour of one sweep, with the env's tet particles ``q[env, first : first +
    tile_particles]`` in shared memory (as ``xpbd.fused_tet_kernel`` does for the XPBD tets). Each lane takes one
    vertex of the colour and writes it back into the tile (a block barrier per write); the arithmetic is
    ``solve_vertices``'s, in the same order (bit-identical on the CPU, where a block has one lane). ``lagged``
    (compile-time: the variant holds only its own branch's registers, sm_90 128 with both): the rotations refreshed at
    the sweep's start (:func:`tet_vertex_terms_lagged`). A held env (``hold.TetHold``: its vertices at rest, started
    where they are by the prediction) returns at once, marked as skipped with ``hold_update`` (a substep's last
    sweep); otherwise lane 0 counts the env's quiet substeps at the end, after every lane has read them (the colours'
    barriers come between)."""
    key = (int(tile_particles), bool(lagged))
    kernel = _FUSED_KERNELS.get(key)
    if kernel is not None:
        return kernel
    P = int(tile_particles)
    LAGGED = bool(lagged)

    def solve_vertices_fused(
        color_offsets: wp.array(dtype=wp.int32),
        first: int,
        vertices: wp.array(dtype=wp.int32),
        adj_offsets: wp.array(dtype=wp.int32),
        adj_tets: wp.array(dtype=wp.int32),
        adj_corners: wp.array(dtype=wp.int32),
        indices: wp.array(dtype=wp.vec4i),
        inv_rest: wp.array(dtype=wp.mat33),
        stiffness: wp.array2d(dtype=wp.vec2),
        inv_mass: wp.array2d(dtype=float),
        q_pred: wp.array2d(dtype=wp.vec3),
        inv_dt2: float,
        tet_element: wp.array(dtype=wp.int32),
        tet_active: wp.array2d(dtype=wp.int32),
        rotation_iterations: int,
        hold: TetHold,
        hold_update: int,
        tet_rotation: wp.array2d(dtype=wp.quat),
        q: wp.array2d(dtype=wp.vec3),
    ):
        env, lane = wp.tid()
        if tets_held(hold, env):
            # every lane returns: lane 0's mark (after + 1, hold.TetHold) is read as held by a lane reading it late
            if hold_update != 0 and lane == 0:
                hold.quiet[env] = hold.after + 1
            return
        lanes = wp.block_dim()
        xs = wp.tile_load(q[env], shape=P, offset=first, storage="shared")
        pe = env % inv_mass.shape[0]
        for col in range(color_offsets.shape[0] - 1):
            start = color_offsets[col]
            end = color_offsets[col + 1]
            for base in range(start, end, lanes):
                # every lane runs the cooperative scatter below, the ones past the colour's end with nothing
                j = wp.min(base + lane, end - 1)
                i = vertices[j]
                w = inv_mass[pe, i]
                moves = base + lane < end and w != 0.0
                x = wp.vec3(0.0)  # written only where the lane moves its vertex
                if moves:
                    # the Hessian is symmetric (each tet's block is |m|^2 / alpha_D I + g g^T / alpha_H, whose mirrored
                    # entries are the same products), so its sum is held as diagonal and upper entries: six registers
                    # instead of nine through the loop, the same sums
                    f = wp.vec3(0.0)
                    Hd = wp.vec3(0.0)
                    Hu = wp.vec3(0.0)
                    for a in range(adj_offsets[j], adj_offsets[j + 1]):
                        c = adj_tets[a]
                        if tet_removed(env, c, tet_element, tet_active):
                            continue
                        k = indices[c]
                        x0 = wp.tile_extract(xs, k[0] - first)
                        x1 = wp.tile_extract(xs, k[1] - first)
                        x2 = wp.tile_extract(xs, k[2] - first)
                        x3 = wp.tile_extract(xs, k[3] - first)
                        fa = wp.vec3(0.0)
                        Ha = wp.mat33(0.0)
                        if wp.static(LAGGED):
                            fa, Ha = tet_vertex_terms_lagged(env, c, adj_corners[a], x0, x1, x2, x3, inv_rest,
                                                             stiffness, tet_rotation)
                        else:
                            fa, Ha = tet_vertex_terms(env, c, adj_corners[a], x0, x1, x2, x3, inv_rest, stiffness,
                                                      rotation_iterations, tet_rotation)
                        f = f + fa
                        Hd = Hd + wp.vec3(Ha[0, 0], Ha[1, 1], Ha[2, 2])
                        Hu = Hu + wp.vec3(Ha[0, 1], Ha[0, 2], Ha[1, 2])
                    H = wp.mat33(Hd[0], Hu[0], Hu[1], Hu[0], Hd[1], Hu[2], Hu[1], Hu[2], Hd[2])
                    # the vertex read from the tile here, not held through the loop (no lane writes it meanwhile)
                    x = vertex_step(wp.tile_extract(xs, i - first), q_pred[env, i], w, inv_dt2, f, H)
                wp.tile_scatter_masked(xs, i - first, x, moves)
        wp.tile_store(q[env], xs, offset=first)
        if hold_update != 0 and hold.after > 0 and lane == 0:
            quiet = int(0)
            if hold.moving[env] == 0:
                quiet = wp.min(hold.quiet[env] + 1, hold.after)
            hold.quiet[env] = quiet
            hold.moving[env] = 0

    kernel = wp.kernel(solve_vertices_fused, module="unique", enable_backward=False)
    _FUSED_KERNELS[key] = kernel
    return kernel
