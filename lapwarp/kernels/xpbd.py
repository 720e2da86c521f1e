"""XPBD solver kernels: integration, constraint projection (distance, dihedral bending, stable
co-rotated FEM tetrahedra, attachments, Cosserat rods), velocity update. (The stability check is
``world_kernels.check_and_restore``.)

Every kernel launches with the env first, ``dim=(num_envs, count)`` and ``env, i = wp.tid()``. Shared
topology is indexed with the local constraint index ``i``; per-env parameters ``p`` with leading
dimension 1 or ``num_envs`` are read as ``p[env % p.shape[0], i]``. Constraint kernels take the
``start`` of their graph colour so one launch per colour touches disjoint particles (no atomics).

XPBD (Macklin et al. 2016) with compliance ``alpha`` in SI units: ``alpha_t = alpha / dt^2`` and
``dlambda = (-C - alpha_t * lambda) / (sum w |grad C|^2 + alpha_t)``. With one iteration per substep
``lambda`` starts at zero and is not stored (``use_lambda = 0``); with more iterations it is
accumulated in per-env arrays so the result stays compliance-consistent.

Cutting masks (``lapwarp.cutting``): constraint kernels take per-env ``active`` masks and skip a constraint whose
element was removed: cloth edges and hinges their own masks (derived from the triangles once per cut), tets the
mask of their element. An empty mask or element map (scenes without cuttable objects) means "no masks": one branch
on a uniform value, no memory traffic.
"""

import warp as wp

from lapwarp.kernels.contact import (
    BodyMotion,
    ContactParticles,
    ContactReports,
    CutMasks,
    IgnoreMask,
    ParticleSolve,
    ShapePoses,
    ShapeTable,
    apply_mean_delta,
    particle_collision_func,
)
from lapwarp.kernels.geodesic import ANCHOR_MASS_RATIO
from lapwarp.kernels.geometry import interpolate_transform, twist_about
from lapwarp.kernels.hold import TetHold, tets_held

wp.set_module_options({"enable_backward": False})


# ----------------------------------------------------------------------------------------------------
# particles
# ----------------------------------------------------------------------------------------------------


@wp.func
def integrate_particle(
    env: int,
    i: int,
    v_old: wp.vec3,
    inv_mass: wp.array2d(dtype=float),
    damping: wp.array2d(dtype=float),
    gravity: wp.vec3,
    dt: float,
    active: wp.array2d(dtype=wp.int32),
    use_active: int,
    force: wp.array2d(dtype=wp.vec3),
    use_force: int,
    vbd_start: wp.array(dtype=wp.int32),
    hold: TetHold,
    q: wp.array2d(dtype=wp.vec3),
    qd: wp.array2d(dtype=wp.vec3),
    q_pred_out: wp.array2d(dtype=wp.vec3),
):
    """Particle ``(env, i)``'s prediction from velocity ``v_old`` (see ``integrate_particles``). ``vbd_start``
    (per particle; empty: none) flags the per-vertex tet solve's vertices: they start their solve from the inertial
    guess without the external acceleration, ``x_pred - h^2 (g + w f)``, written here instead of by
    ``vbd.begin_substep`` (the same arithmetic; ``World._record_step`` says when). With ``hold`` on
    (:class:`TetHold`) such a vertex faster than its speed flags its env as moving, and in a held env a slower one
    starts at rest: no velocity, exactly where it is (what the sweep, skipped there, leaves it)."""
    x = q[env, i]
    w = inv_mass[env % inv_mass.shape[0], i]
    # a particle whose elements were all cut away (``active`` 0) belongs to nothing: it stays where it was (sofa_env
    # removes such points) instead of falling for ever and tripping the stability check
    if use_active != 0:
        if active[env, i] == 0:
            w = 0.0
    if w == 0.0:
        qd[env, i] = wp.vec3(0.0)
        q_pred_out[env, i] = x
        return
    d = damping[env % damping.shape[0], i]
    # implicit damping factor 1 / (1 + d dt) on the old velocity only: stable for any rate d, and it does
    # not scale gravity, so a static equilibrium does not depend on the damping
    acc = gravity
    if use_force != 0:
        acc = acc + force[env, i] * w  # external force (World.particle_force), N
    tet_vertex = False
    if vbd_start.shape[0] > 0:
        tet_vertex = vbd_start[i] != 0
    if tet_vertex and hold.after > 0:
        if wp.length_sq(v_old) > hold.speed2:
            hold.moving[env] = 1  # a plain store: every writer writes 1
        elif hold.quiet[env] >= hold.after:
            # the prediction from rest (v_old = 0); the start is x itself, not x + h^2 a - h^2 a rounded, so a held
            # vertex stays exactly where it is
            v_rest = acc * dt
            qd[env, i] = v_rest
            q_pred_out[env, i] = x + v_rest * dt
            return
    v = v_old / (1.0 + d * dt) + acc * dt
    qd[env, i] = v
    xp = x + v * dt
    start = xp
    if tet_vertex:
        start = xp - acc * (dt * dt)
    q[env, i] = start
    q_pred_out[env, i] = xp


@wp.kernel
def integrate_particles(
    inv_mass: wp.array2d(dtype=float),
    damping: wp.array2d(dtype=float),
    gravity: wp.vec3,
    dt: float,
    active: wp.array2d(dtype=wp.int32),
    use_active: int,
    force: wp.array2d(dtype=wp.vec3),
    use_force: int,
    vbd_start: wp.array(dtype=wp.int32),
    hold: TetHold,
    q: wp.array2d(dtype=wp.vec3),
    qd: wp.array2d(dtype=wp.vec3),
    q_pred_out: wp.array2d(dtype=wp.vec3),
):
    """A substep's prediction: damping, gravity and external forces on the velocity, then the position."""
    env, i = wp.tid()
    integrate_particle(env, i, qd[env, i], inv_mass, damping, gravity, dt, active, use_active, force, use_force,
                       vbd_start, hold, q, qd, q_pred_out)


@wp.kernel
def finish_and_integrate_particles(
    inv_dt_prev: float,
    inv_mass: wp.array2d(dtype=float),
    damping: wp.array2d(dtype=float),
    gravity: wp.vec3,
    dt: float,
    active: wp.array2d(dtype=wp.int32),
    use_active: int,
    force: wp.array2d(dtype=wp.vec3),
    use_force: int,
    vbd_start: wp.array(dtype=wp.int32),
    hold: TetHold,
    q: wp.array2d(dtype=wp.vec3),
    qd: wp.array2d(dtype=wp.vec3),
    q_pred_out: wp.array2d(dtype=wp.vec3),
):
    """``update_particle_velocities`` of the substep before (``q_pred_out`` holds its prediction) and this substep's
    ``integrate_particles`` in one pass: the same arithmetic, one launch and one read of the particles fewer per
    substep (nothing runs between them; ``World._record_step``)."""
    env, i = wp.tid()
    v_old = qd[env, i] + (q[env, i] - q_pred_out[env, i]) * inv_dt_prev
    integrate_particle(env, i, v_old, inv_mass, damping, gravity, dt, active, use_active, force, use_force,
                       vbd_start, hold, q, qd, q_pred_out)


@wp.kernel
def update_particle_velocities(
    q: wp.array2d(dtype=wp.vec3), q_pred: wp.array2d(dtype=wp.vec3), inv_dt: float, qd: wp.array2d(dtype=wp.vec3)
):
    # v = (x - x_prev) / h written as v_pred + (x - x_pred) / h: only the small constraint correction is
    # divided by h, so float32 rounding of large coordinates does not leak into the velocity
    env, i = wp.tid()
    qd[env, i] = qd[env, i] + (q[env, i] - q_pred[env, i]) * inv_dt


# ----------------------------------------------------------------------------------------------------
# distance constraints (edges)
# ----------------------------------------------------------------------------------------------------


@wp.func
def xpbd_scalar_multiplier_step(
    C: float, w: float, alpha: float, use_lambda: int, lam: wp.array2d(dtype=float), env: int, c: int
):
    """XPBD update of one scalar constraint: returns dlambda = (-C - alpha lambda) / (w + alpha) and, with
    multipliers kept across iterations, accumulates it into ``lam[env, c]``."""
    l0 = float(0.0)
    if use_lambda != 0:
        l0 = lam[env, c]
    dl = (-C - alpha * l0) / (w + alpha)
    if use_lambda != 0:
        lam[env, c] = l0 + dl
    return dl


@wp.kernel
def solve_edges(
    start: int,
    indices: wp.array(dtype=wp.vec2i),
    rest: wp.array(dtype=float),
    compliance: wp.array2d(dtype=float),
    inv_mass: wp.array2d(dtype=float),
    inv_dt2: float,
    use_lambda: int,
    lam: wp.array2d(dtype=float),
    edge_active: wp.array2d(dtype=wp.int32),
    q: wp.array2d(dtype=wp.vec3),
):
    env, t = wp.tid()
    c = start + t
    # (N, E) cutting mask (an edge lives while one of its triangles does), or (1, 0): no masks
    if edge_active.shape[1] > 0:
        if edge_active[env, c] == 0:
            return
    ij = indices[c]
    pe = env % inv_mass.shape[0]
    wi = inv_mass[pe, ij[0]]
    wj = inv_mass[pe, ij[1]]
    w = wi + wj
    if w == 0.0:
        return
    xi = q[env, ij[0]]
    xj = q[env, ij[1]]
    d = xi - xj
    length = wp.length(d)
    if length < 1.0e-12:
        return
    n = d / length
    C = length - rest[c]
    alpha = compliance[env % compliance.shape[0], c] * inv_dt2
    dl = xpbd_scalar_multiplier_step(C, w, alpha, use_lambda, lam, env, c)
    q[env, ij[0]] = xi + n * (wi * dl)
    q[env, ij[1]] = xj - n * (wj * dl)


# ----------------------------------------------------------------------------------------------------
# dihedral bending (Bridson et al. 2003 gradients)
# ----------------------------------------------------------------------------------------------------


@wp.kernel
def solve_hinges(
    start: int,
    indices: wp.array(dtype=wp.vec4i),
    rest: wp.array(dtype=float),
    compliance: wp.array2d(dtype=float),
    inv_mass: wp.array2d(dtype=float),
    inv_dt2: float,
    use_lambda: int,
    lam: wp.array2d(dtype=float),
    hinge_active: wp.array2d(dtype=wp.int32),
    q: wp.array2d(dtype=wp.vec3),
):
    env, t = wp.tid()
    c = start + t
    # (N, H) cutting mask (a hinge bends two triangles against each other: it needs both), or (1, 0): no masks
    if hinge_active.shape[1] > 0:
        if hinge_active[env, c] == 0:
            return
    h = indices[c]
    pe = env % inv_mass.shape[0]
    w1 = inv_mass[pe, h[0]]
    w2 = inv_mass[pe, h[1]]
    w3 = inv_mass[pe, h[2]]
    w4 = inv_mass[pe, h[3]]
    x1 = q[env, h[0]]
    x2 = q[env, h[1]]
    x3 = q[env, h[2]]
    x4 = q[env, h[3]]
    n1 = wp.cross(x3 - x1, x4 - x1)
    n2 = wp.cross(x4 - x2, x3 - x2)
    l1 = wp.length_sq(n1)
    l2 = wp.length_sq(n2)
    e = x4 - x3
    el = wp.length(e)
    if l1 < 1.0e-20 or l2 < 1.0e-20 or el < 1.0e-10:
        return
    e_hat = e / el
    # signed angle via atan2 (robust near flat, unlike acos of the cosine)
    m1 = n1 / wp.sqrt(l1)
    m2 = n2 / wp.sqrt(l2)
    angle = wp.atan2(wp.dot(wp.cross(m1, m2), e_hat), wp.dot(m1, m2))
    n1 = n1 / l1
    n2 = n2 / l2
    g1 = n1 * el
    g2 = n2 * el
    g3 = n1 * wp.dot(x1 - x4, e_hat) + n2 * wp.dot(x2 - x4, e_hat)
    g4 = n1 * wp.dot(x3 - x1, e_hat) + n2 * wp.dot(x3 - x2, e_hat)
    # Bridson's gradients are of -angle in our sign convention; flip so C = angle - rest
    g1 = -g1
    g2 = -g2
    g3 = -g3
    g4 = -g4
    wsum = w1 * wp.length_sq(g1) + w2 * wp.length_sq(g2) + w3 * wp.length_sq(g3) + w4 * wp.length_sq(g4)
    alpha = compliance[env % compliance.shape[0], c] * inv_dt2
    if wsum + alpha < 1.0e-20:
        return
    C = angle - rest[c]
    # wrap to (-pi, pi] so a hinge passing through +-pi does not snap
    if C > wp.pi:
        C = C - 2.0 * wp.pi
    if C < -wp.pi:
        C = C + 2.0 * wp.pi
    dl = xpbd_scalar_multiplier_step(C, wsum, alpha, use_lambda, lam, env, c)
    q[env, h[0]] = x1 + g1 * (w1 * dl)
    q[env, h[1]] = x2 + g2 * (w2 * dl)
    q[env, h[2]] = x3 + g3 * (w3 * dl)
    q[env, h[3]] = x4 + g4 * (w4 * dl)


# ----------------------------------------------------------------------------------------------------
# tetrahedra: co-rotated FEM as two coupled XPBD constraints, deviatoric |F - R| and volume det F - 1
# ----------------------------------------------------------------------------------------------------


@wp.func
def mat_col(m: wp.mat33, j: int):
    return wp.vec3(m[0, j], m[1, j], m[2, j])


@wp.func
def polar_rotation(F: wp.mat33):
    """Rotation R of the polar decomposition F = R S via SVD, with reflections removed (inverted tets)."""
    U = wp.mat33()
    sig = wp.vec3()
    V = wp.mat33()
    wp.svd3(F, U, sig, V)
    if wp.determinant(U) * wp.determinant(V) < 0.0:
        # flip the direction of the smallest singular value. A guard: Warp's svd3 returns proper U and V (an inverted
        # F gets a negative smallest singular value instead), so this does not run there. Columns picked by constant
        # indices: a run-time index reserved a stack frame for U and sig in every kernel that calls this
        smallest = sig[0]
        k = int(0)
        if sig[1] < smallest:
            k = 1
            smallest = sig[1]
        if sig[2] < smallest:
            k = 2
        c0 = mat_col(U, 0)
        c1 = mat_col(U, 1)
        c2 = mat_col(U, 2)
        if k == 0:
            c0 = -c0
        elif k == 1:
            c1 = -c1
        else:
            c2 = -c2
        U = wp.matrix_from_cols(c0, c1, c2)
    return U * wp.transpose(V)


@wp.func
def extract_rotation(F: wp.mat33, q0: wp.quat, iterations: int) -> wp.quat:
    """Rotation of ``F`` by Mueller et al. 2016 ("A Robust Method to Extract the Rotational Part of
    Deformations"): from the warm start ``q0`` (the tet's rotation of the previous sweep), turn the frame's columns
    towards ``F``'s. Always a proper rotation, also for inverted tets; a few iterations suffice when warm-started,
    which is far cheaper than the SVD of ``polar_rotation``.

    Each turn by the iteration's vector ``omega`` is the normalised quaternion ``(omega / 2, 1)``, a rotation by
    ``2 atan(|omega| / 2)`` (``|omega| - |omega|^3 / 12``) about ``omega`` where the paper turns by ``|omega|``:
    the same fixed point (``omega = 0``, the columns balanced) without the sine, cosine, square root and division
    of an axis-angle quaternion. Why: this runs inside the tet sweeps' serial paths (XPBD: every projection;
    LigatingLoop's cavity), and the trigonometry's slow path gave every kernel that calls it a 32-byte stack frame
    (sm_90, benchmarks/kernel_resources.py)."""
    q = q0
    a0 = mat_col(F, 0)
    a1 = mat_col(F, 1)
    a2 = mat_col(F, 2)
    for _ in range(iterations):
        R = wp.quat_to_matrix(q)
        r0 = mat_col(R, 0)
        r1 = mat_col(R, 1)
        r2 = mat_col(R, 2)
        half = (wp.cross(r0, a0) + wp.cross(r1, a1) + wp.cross(r2, a2)) * (
            0.5 / (wp.abs(wp.dot(r0, a0) + wp.dot(r1, a1) + wp.dot(r2, a2)) + 1.0e-9))
        if wp.length_sq(half) < 2.5e-19:  # |omega| < 1e-9: converged
            break
        q = wp.normalize(wp.quat(half[0], half[1], half[2], 1.0) * q)
    return q


@wp.func
def deformation_gradient(x0: wp.vec3, x1: wp.vec3, x2: wp.vec3, x3: wp.vec3, Dm_inv: wp.mat33):
    """``F = Ds Dm^-1`` of a tet."""
    return wp.matrix_from_cols(x1 - x0, x2 - x0, x3 - x0) * Dm_inv


@wp.func
def strain_terms(F: wp.mat33, R: wp.mat33):
    """``(C_D, C_H, DC, cof)`` of :func:`tet_strain` for a deformation ``F`` and a given rotation ``R``."""
    FR = F - R
    C_D = wp.sqrt(wp.ddot(FR, FR))
    C_H = wp.determinant(F) - 1.0
    DC = wp.mat33(0.0)
    if C_D > 1.0e-9:
        DC = FR * (1.0 / C_D)
    return C_D, C_H, DC, cofactor(F)


@wp.func
def cofactor(F: wp.mat33):
    """``cof F = d det F / d F`` (columns: the cross products of the other two columns)."""
    f1 = mat_col(F, 0)
    f2 = mat_col(F, 1)
    f3 = mat_col(F, 2)
    return wp.matrix_from_cols(wp.cross(f2, f3), wp.cross(f3, f1), wp.cross(f1, f2))


@wp.func
def tet_strain(
    x0: wp.vec3, x1: wp.vec3, x2: wp.vec3, x3: wp.vec3,
    Dm_inv: wp.mat33,
    q0: wp.quat,
    rotation_iterations: int,
):
    """The co-rotated tet's deformation: ``(C_D, C_H, qr, DC, cof)``: the constraints ``C_D = |F - R|_F`` and
    ``C_H = det F - 1``, the extracted rotation ``qr`` (warm start of the next extraction; ``rotation_iterations``
    0 = SVD polar decomposition), ``dC_D / dF = (F - R) / C_D`` (0 at rest) and ``dC_H / dF = cof F``. The gradient at
    corner ``j`` = 1..3 is the matrix times row ``j - 1`` of ``Dm_inv``; corner 0's is minus their sum."""
    F = deformation_gradient(x0, x1, x2, x3, Dm_inv)
    # Energy V (mu |F - R|^2 + lambda/2 (det F - 1)^2) = C_D^2 / (2 alpha_D) + C_H^2 / (2 alpha_H): both
    # constraints vanish at rest, so stiff materials (alpha / dt^2 << w |grad C|^2) stay stable.
    qr = q0
    R = wp.mat33()
    if rotation_iterations > 0:  # warm-started rotation extraction (the default)
        qr = extract_rotation(F, q0, rotation_iterations)
        R = wp.quat_to_matrix(qr)
    else:
        R = polar_rotation(F)
    C_D, C_H, DC, cof = strain_terms(F, R)
    return C_D, C_H, qr, DC, cof


@wp.func
def corner_gradients(DC: wp.mat33, cof: wp.mat33, Dm_inv: wp.mat33):
    """The constraints' gradients at the four corners from ``dC_D / dF = DC`` and ``dC_H / dF = cof``: ``(d0 .. d3,
    h0 .. h3)``, corner ``j`` = 1..3 the matrix times row ``j - 1`` of ``Dm_inv``, corner 0 minus their sum."""
    DmT = wp.transpose(Dm_inv)
    GD = DC * DmT
    GH = cof * DmT
    d1 = mat_col(GD, 0)
    d2 = mat_col(GD, 1)
    d3 = mat_col(GD, 2)
    h1 = mat_col(GH, 0)
    h2 = mat_col(GH, 1)
    h3 = mat_col(GH, 2)
    return -(d1 + d2 + d3), d1, d2, d3, -(h1 + h2 + h3), h1, h2, h3


@wp.func
def constraint_projection(
    C_D: float, C_H: float,
    d0: wp.vec3, d1: wp.vec3, d2: wp.vec3, d3: wp.vec3,
    h0: wp.vec3, h1: wp.vec3, h2: wp.vec3, h3: wp.vec3,
    w0: float, w1: float, w2: float, w3: float,
    p: wp.vec3,
    inv_dt2: float,
    lD: float,
    lH: float,
):
    """One coupled XPBD projection of a tet's two constraints (values and corner gradients): returns whether it
    acts, the multiplier increments ``(dlD, dlH)`` and the four corner displacements."""
    aD = p[0] * inv_dt2
    hydro = p[1] >= 0.0  # alpha_H < 0 marks lambda = 0 (nu = 0): no volume term
    aH = wp.max(p[1], 0.0) * inv_dt2
    A11 = w0 * wp.dot(d0, d0) + w1 * wp.dot(d1, d1) + w2 * wp.dot(d2, d2) + w3 * wp.dot(d3, d3)
    b1 = -C_D - aD * lD
    dlD = float(0.0)
    dlH = float(0.0)
    ok = int(1)
    if hydro:
        A22 = w0 * wp.dot(h0, h0) + w1 * wp.dot(h1, h1) + w2 * wp.dot(h2, h2) + w3 * wp.dot(h3, h3)
        A12 = w0 * wp.dot(d0, h0) + w1 * wp.dot(d1, h1) + w2 * wp.dot(d2, h2) + w3 * wp.dot(d3, h3)
        # Gram determinant A11 A22 - A12^2 as A22 |d - proj_h d|^2 (no cancellation when nearly parallel)
        gram = float(0.0)
        if A22 > 0.0:
            s = A12 / A22
            r0 = d0 - h0 * s
            r1 = d1 - h1 * s
            r2 = d2 - h2 * s
            r3 = d3 - h3 * s
            gram = A22 * (w0 * wp.dot(r0, r0) + w1 * wp.dot(r1, r1) + w2 * wp.dot(r2, r2) + w3 * wp.dot(r3, r3))
        det = gram + A11 * aH + A22 * aD + aD * aH
        if det < 1.0e-30:
            ok = 0
        else:
            b2 = -C_H - aH * lH
            dlD = ((A22 + aH) * b1 - A12 * b2) / det
            dlH = ((A11 + aD) * b2 - A12 * b1) / det
    else:
        if A11 + aD < 1.0e-30:
            ok = 0
        else:
            dlD = b1 / (A11 + aD)
    return (ok, dlD, dlH, (d0 * dlD + h0 * dlH) * w0, (d1 * dlD + h1 * dlH) * w1, (d2 * dlD + h2 * dlH) * w2,
            (d3 * dlD + h3 * dlH) * w3)


@wp.func
def tet_removed(env: int, c: int, tet_element: wp.array(dtype=wp.int32), tet_active: wp.array2d(dtype=wp.int32)):
    """Tet ``c`` (colour-ordered) of env ``env`` was cut away (an empty element map: nothing is cuttable)."""
    if tet_element.shape[0] > 0:
        return tet_active[env, tet_element[c]] == 0
    return False


@wp.func
def tet_multipliers(env: int, c: int, use_lambda: int, lam: wp.array2d(dtype=wp.vec2)):
    """Tet ``c``'s multipliers ``(lD, lH)`` of the substep so far (0 when a sweep per substep does not keep them)."""
    lD = float(0.0)
    lH = float(0.0)
    if use_lambda != 0:
        lv = lam[env, c]
        lD = lv[0]
        lH = lv[1]
    return lD, lH


@wp.func
def project_strained_tet(
    env: int,
    c: int,
    k: wp.vec4i,
    C_D: float, C_H: float, DC: wp.mat33, cof: wp.mat33,
    Dm_inv: wp.mat33,
    params: wp.array2d(dtype=wp.vec3),
    inv_mass: wp.array2d(dtype=float),
    inv_dt2: float,
    use_lambda: int,
    lam: wp.array2d(dtype=wp.vec2),
    write: bool,
):
    """The coupled projection of tet ``c`` of env ``env`` (corners ``k``) from its strain terms (``strain_terms``)
    with the substep's multipliers; when ``write`` and it acts, stores them. Returns whether it acts and the four
    corner displacements (the caller moves the corners). Shared by :func:`project_tet` and
    :func:`project_tet_lagged`, which differ only in where the rotation comes from."""
    pe = env % inv_mass.shape[0]
    lD, lH = tet_multipliers(env, c, use_lambda, lam)
    d0, d1, d2, d3, h0, h1, h2, h3 = corner_gradients(DC, cof, Dm_inv)
    ok, dlD, dlH, dx0, dx1, dx2, dx3 = constraint_projection(
        C_D, C_H, d0, d1, d2, d3, h0, h1, h2, h3, inv_mass[pe, k[0]], inv_mass[pe, k[1]], inv_mass[pe, k[2]],
        inv_mass[pe, k[3]], params[env % params.shape[0], c], inv_dt2, lD, lH)
    if write and ok != 0 and use_lambda != 0:
        lam[env, c] = wp.vec2(lD + dlD, lH + dlH)
    return ok, dx0, dx1, dx2, dx3


@wp.func
def project_tet(
    env: int,
    c: int,
    k: wp.vec4i,
    x0: wp.vec3, x1: wp.vec3, x2: wp.vec3, x3: wp.vec3,
    inv_rest: wp.array(dtype=wp.mat33),
    params: wp.array2d(dtype=wp.vec3),
    inv_mass: wp.array2d(dtype=float),
    inv_dt2: float,
    use_lambda: int,
    lam: wp.array2d(dtype=wp.vec2),
    rotation_iterations: int,
    tet_rotation: wp.array2d(dtype=wp.quat),
    write: bool,
):
    """One coupled XPBD projection of the co-rotated tet ``c`` of env ``env`` (corners ``k`` at ``x0 .. x3``), its
    rotation extracted warm-started from the stored one (``rotation_iterations`` 0 or no stored rotations: the SVD
    polar decomposition); when ``write``, stores its new rotation and (if it acts) multipliers. Returns whether it
    acts and the four corner displacements (the caller moves the corners)."""
    iters = int(0)
    q0 = wp.quat_identity()
    if tet_rotation.shape[1] > 0:  # warm-started rotation extraction (the default)
        iters = rotation_iterations
        q0 = tet_rotation[env, c]
    Dm_inv = inv_rest[c]
    C_D, C_H, qr, DC, cof = tet_strain(x0, x1, x2, x3, Dm_inv, q0, iters)
    if write and iters > 0:
        tet_rotation[env, c] = qr
    return project_strained_tet(env, c, k, C_D, C_H, DC, cof, Dm_inv, params, inv_mass, inv_dt2, use_lambda, lam,
                                write)


@wp.func
def project_tet_lagged(
    env: int,
    c: int,
    k: wp.vec4i,
    x0: wp.vec3, x1: wp.vec3, x2: wp.vec3, x3: wp.vec3,
    inv_rest: wp.array(dtype=wp.mat33),
    params: wp.array2d(dtype=wp.vec3),
    inv_mass: wp.array2d(dtype=float),
    inv_dt2: float,
    use_lambda: int,
    lam: wp.array2d(dtype=wp.vec2),
    tet_rotation: wp.array2d(dtype=wp.quat),
    write: bool,
):
    """:func:`project_tet` with the tet's rotation as :func:`refresh_tet_rotations` stored it at the sweep's start
    (``World.tet_rotation_update`` "sweep"): read, neither extracted nor stored, so the coloured sweep, whose colours
    run one after another, leaves the extraction to a launch over every tet at once."""
    Dm_inv = inv_rest[c]
    F = deformation_gradient(x0, x1, x2, x3, Dm_inv)
    C_D, C_H, DC, cof = strain_terms(F, wp.quat_to_matrix(tet_rotation[env, c]))
    return project_strained_tet(env, c, k, C_D, C_H, DC, cof, Dm_inv, params, inv_mass, inv_dt2, use_lambda, lam,
                                write)


@wp.kernel
def refresh_tet_rotations(
    indices: wp.array(dtype=wp.vec4i),
    inv_rest: wp.array(dtype=wp.mat33),
    tet_element: wp.array(dtype=wp.int32),
    tet_active: wp.array2d(dtype=wp.int32),
    rotation_iterations: int,
    hold: TetHold,
    q: wp.array2d(dtype=wp.vec3),
    tet_rotation: wp.array2d(dtype=wp.quat),
):
    """Every tet's rotation extracted once at the start of a sweep (warm-started from the stored one), for the
    sweep's lagged use (``World.tet_rotation_update`` "sweep": :func:`project_tet_lagged`, the per-vertex solve's
    ``vbd.tet_vertex_terms_lagged``). Why: extracted inside the coloured sweep, the rotation is arithmetic on the
    sweep's serial path (XPBD: a block per env runs the colours one after another) or repeated by each of a tet's four
    vertices (the per-vertex solve); here every tet of every env runs at once. For a stiff or slowly moving body the
    rotation barely changes within a sweep. A held env's (:class:`TetHold`) stay: its vertices have not moved."""
    env, c = wp.tid()
    if tet_removed(env, c, tet_element, tet_active) or tets_held(hold, env):
        return
    k = indices[c]
    F = deformation_gradient(q[env, k[0]], q[env, k[1]], q[env, k[2]], q[env, k[3]], inv_rest[c])
    tet_rotation[env, c] = extract_rotation(F, tet_rotation[env, c], rotation_iterations)


@wp.kernel
def solve_tets(
    start: int,
    indices: wp.array(dtype=wp.vec4i),
    inv_rest: wp.array(dtype=wp.mat33),
    params: wp.array2d(dtype=wp.vec3),
    inv_mass: wp.array2d(dtype=float),
    inv_dt2: float,
    use_lambda: int,
    lam: wp.array2d(dtype=wp.vec2),
    tet_element: wp.array(dtype=wp.int32),
    tet_active: wp.array2d(dtype=wp.int32),
    rotation_iterations: int,
    lagged: int,
    tet_rotation: wp.array2d(dtype=wp.quat),
    q: wp.array2d(dtype=wp.vec3),
):
    """The tets of one graph colour, one thread per (env, tet); ``lagged``: the rotations as refreshed at the sweep's
    start (:func:`project_tet_lagged`)."""
    env, t = wp.tid()
    c = start + t
    if tet_removed(env, c, tet_element, tet_active):
        return
    k = indices[c]
    x0 = q[env, k[0]]
    x1 = q[env, k[1]]
    x2 = q[env, k[2]]
    x3 = q[env, k[3]]
    ok = int(0)
    dx0 = wp.vec3()
    dx1 = wp.vec3()
    dx2 = wp.vec3()
    dx3 = wp.vec3()
    if lagged != 0:
        ok, dx0, dx1, dx2, dx3 = project_tet_lagged(env, c, k, x0, x1, x2, x3, inv_rest, params, inv_mass, inv_dt2,
                                                    use_lambda, lam, tet_rotation, True)
    else:
        ok, dx0, dx1, dx2, dx3 = project_tet(env, c, k, x0, x1, x2, x3, inv_rest, params, inv_mass, inv_dt2,
                                             use_lambda, lam, rotation_iterations, tet_rotation, True)
    if ok == 0:
        return
    q[env, k[0]] = x0 + dx0
    q[env, k[1]] = x1 + dx1
    q[env, k[2]] = x2 + dx2
    q[env, k[3]] = x3 + dx3


_FUSED_TET_KERNELS: dict = {}


def fused_tet_kernel(tile_particles: int, lagged: bool = False):
    """``solve_tets_fused`` for a particle window of ``tile_particles`` (a tile's shape is a compile-time constant,
    so one kernel per window size and rotation update, cached; ``lagged``: the rotations as refreshed at the sweep's
    start, :func:`project_tet_lagged`, compiled without the extraction).

    One thread block per env runs every colour of one sweep in a single launch: the env's tet particles
    ``q[env, first : first + tile_particles]`` are loaded into shared memory once, each colour's tets are
    projected by the block's threads in chunks of ``block_dim`` (a colour's tets share no particle, so a chunk's
    writes never collide), each chunk's new positions are scattered into the shared tile (a block barrier), and
    the window is stored back at the end. Against one launch per colour (~30 for GraspLiftAndTouch's organs)
    this removes the launches' fixed cost and tail and keeps the positions on chip; the arithmetic per tet is
    :func:`project_tet` (lagged: :func:`project_tet_lagged`), the same as ``solve_tets``, in the same order
    (bit-identical on the CPU, where a block has one lane)."""
    key = (int(tile_particles), bool(lagged))
    kernel = _FUSED_TET_KERNELS.get(key)
    if kernel is not None:
        return kernel
    P = key[0]
    LAGGED = key[1]

    def solve_tets_fused(
        color_offsets: wp.array(dtype=wp.int32),
        first: int,
        indices: wp.array(dtype=wp.vec4i),
        inv_rest: wp.array(dtype=wp.mat33),
        params: wp.array2d(dtype=wp.vec3),
        inv_mass: wp.array2d(dtype=float),
        inv_dt2: float,
        use_lambda: int,
        lam: wp.array2d(dtype=wp.vec2),
        tet_element: wp.array(dtype=wp.int32),
        tet_active: wp.array2d(dtype=wp.int32),
        rotation_iterations: int,
        tet_rotation: wp.array2d(dtype=wp.quat),
        q: wp.array2d(dtype=wp.vec3),
    ):
        env, lane = wp.tid()
        lanes = wp.block_dim()
        xs = wp.tile_load(q[env], shape=P, offset=first, storage="shared")
        for col in range(color_offsets.shape[0] - 1):
            start = color_offsets[col]
            end = color_offsets[col + 1]
            for base in range(start, end, lanes):
                # every lane runs the cooperative scatters below, the ones past the colour's end with nothing
                c = wp.min(base + lane, end - 1)
                has = base + lane < end and not tet_removed(env, c, tet_element, tet_active)
                k = indices[c]
                i0 = k[0] - first
                i1 = k[1] - first
                i2 = k[2] - first
                i3 = k[3] - first
                x0 = wp.tile_extract(xs, i0)
                x1 = wp.tile_extract(xs, i1)
                x2 = wp.tile_extract(xs, i2)
                x3 = wp.tile_extract(xs, i3)
                ok = int(0)
                dx0 = wp.vec3()
                dx1 = wp.vec3()
                dx2 = wp.vec3()
                dx3 = wp.vec3()
                if wp.static(LAGGED):
                    ok, dx0, dx1, dx2, dx3 = project_tet_lagged(env, c, k, x0, x1, x2, x3, inv_rest, params, inv_mass,
                                                                inv_dt2, use_lambda, lam, tet_rotation, has)
                else:
                    ok, dx0, dx1, dx2, dx3 = project_tet(env, c, k, x0, x1, x2, x3, inv_rest, params, inv_mass,
                                                         inv_dt2, use_lambda, lam, rotation_iterations, tet_rotation,
                                                         has)
                moves = has and ok != 0
                # the corners read again from the tile (unchanged since: a colour's tets share no particle) rather than
                # held in registers through the projection
                wp.tile_scatter_masked(xs, i0, wp.tile_extract(xs, i0) + dx0, moves)
                wp.tile_scatter_masked(xs, i1, wp.tile_extract(xs, i1) + dx1, moves)
                wp.tile_scatter_masked(xs, i2, wp.tile_extract(xs, i2) + dx2, moves)
                wp.tile_scatter_masked(xs, i3, wp.tile_extract(xs, i3) + dx3, moves)
        wp.tile_store(q[env], xs, offset=first)

    kernel = wp.kernel(solve_tets_fused, module="unique", enable_backward=False)
    _FUSED_TET_KERNELS[key] = kernel
    return kernel


# ----------------------------------------------------------------------------------------------------
# attachments to kinematic bodies
# ----------------------------------------------------------------------------------------------------


# an attachment whose h^2 / alpha exceeds this multiple of its particle's inverse mass holds the particle where its
# body puts it: the tethers' anchor bound (geodesic.ANCHOR_MASS_RATIO) seen from the attachment
STIFF_ATTACHMENT = wp.constant(1.0 / ANCHOR_MASS_RATIO)


@wp.func
def solve_attachment_slot(
    env: int,
    s: int,
    attach_particle: wp.array2d(dtype=wp.int32),
    attach_body: wp.array2d(dtype=wp.int32),
    attach_offset: wp.array2d(dtype=wp.vec3),
    attach_compliance: wp.array2d(dtype=float),
    attach_segment: wp.array2d(dtype=wp.int32),
    attach_rotation: wp.array2d(dtype=wp.quat),
    attach_hold_up: wp.array(dtype=wp.vec3),
    body_q_prev: wp.array2d(dtype=wp.transform),
    body_q: wp.array2d(dtype=wp.transform),
    blend: float,
    inv_mass: wp.array2d(dtype=float),
    inv_dt2: float,
    stiff_only: int,
    q: wp.array2d(dtype=wp.vec3),
    sq: wp.array2d(dtype=wp.quat),
):
    """Attachment slot ``s`` of env ``env``: its particle pulled towards its body's point (``solve_attachments``)
    and, in the closing pass (``stiff_only`` 0), the rod segment it holds (``attach_segment`` >= 0) set to the body's
    rotation (its twist about ``attach_hold_up[s]`` where that is not zero) times ``attach_rotation``."""
    i = attach_particle[env, s]
    if i < 0:
        return
    b = attach_body[env, s]
    tf = wp.transform_identity()
    if b >= 0:
        # the body pose moves linearly across the substeps of one step, not in one jump
        tf = interpolate_transform(body_q_prev[env, b], body_q[env, b], blend)
    w = inv_mass[env % inv_mass.shape[0], i]
    if w != 0.0:
        target = attach_offset[env, s]
        if b >= 0:
            target = wp.transform_point(tf, target)
        x = q[env, i]
        alpha = attach_compliance[env, s] * inv_dt2
        if stiff_only == 0 or alpha * STIFF_ATTACHMENT <= w:
            q[env, i] = x + (target - x) * (w / (w + alpha))
    seg = attach_segment[env, s]
    if seg >= 0 and stiff_only == 0:
        # a grasped rod frame turns with its jaw (GraspSystem): a projection, like a pinned node's position
        sq[env, seg] = wp.normalize(wp.mul(twist_about(wp.transform_get_rotation(tf), attach_hold_up[s]),
                                           attach_rotation[env, s]))


@wp.kernel
def solve_attachments(
    attach_particle: wp.array2d(dtype=wp.int32),
    attach_body: wp.array2d(dtype=wp.int32),
    attach_offset: wp.array2d(dtype=wp.vec3),
    attach_compliance: wp.array2d(dtype=float),
    attach_segment: wp.array2d(dtype=wp.int32),
    attach_rotation: wp.array2d(dtype=wp.quat),
    attach_hold_up: wp.array(dtype=wp.vec3),
    body_q_prev: wp.array2d(dtype=wp.transform),
    body_q: wp.array2d(dtype=wp.transform),
    blend: float,
    inv_mass: wp.array2d(dtype=float),
    inv_dt2: float,
    stiff_only: int,
    q: wp.array2d(dtype=wp.vec3),
    sq: wp.array2d(dtype=wp.quat),
):
    """Pull attached particles towards their bodies' points (compliance ``attach_compliance``) and set the rod
    segments they hold to their bodies' rotation (``solve_attachment_slot``). ``stiff_only``: only the attachments
    that make their particle an anchor (``h^2 / alpha`` over ``STIFF_ATTACHMENT`` times its inverse mass), and no
    segment: the sweep starts with those, so that the constraints solved before the closing attachment pass see a held
    point where its body holds it, not where gravity's prediction moved it (a sheet held at two corners at 10
    substeps: the corner edges ended 12 % long, stretched towards the corners' predicted positions 1 mm below)."""
    # one thread per env walks its few slots in order: several slots may hold the same particle
    env = wp.tid()
    for s in range(attach_particle.shape[1]):
        solve_attachment_slot(env, s, attach_particle, attach_body, attach_offset, attach_compliance, attach_segment,
                              attach_rotation, attach_hold_up, body_q_prev, body_q, blend, inv_mass, inv_dt2,
                              stiff_only, q, sq)


@wp.kernel
def solve_attachment_slots(
    attach_particle: wp.array2d(dtype=wp.int32),
    attach_body: wp.array2d(dtype=wp.int32),
    attach_offset: wp.array2d(dtype=wp.vec3),
    attach_compliance: wp.array2d(dtype=float),
    attach_segment: wp.array2d(dtype=wp.int32),
    attach_rotation: wp.array2d(dtype=wp.quat),
    attach_hold_up: wp.array(dtype=wp.vec3),
    body_q_prev: wp.array2d(dtype=wp.transform),
    body_q: wp.array2d(dtype=wp.transform),
    blend: float,
    inv_mass: wp.array2d(dtype=float),
    inv_dt2: float,
    stiff_only: int,
    q: wp.array2d(dtype=wp.vec3),
    sq: wp.array2d(dtype=wp.quat),
):
    """``solve_attachments`` with a thread per (env, slot), for worlds where no particle is ever in two slots
    (``Model.attachments_distinct``: static anchors, or LigatingLoop's slot k that only ever holds node k): each slot
    then touches its own particle, so the order is immaterial and the result is the same. The walk over an env's
    slots in one thread was latency-bound (TissueDissection: 36 anchors, 1.5 ms of its ~20 ms step on the H200, 40
    launches)."""
    env, s = wp.tid()
    solve_attachment_slot(env, s, attach_particle, attach_body, attach_offset, attach_compliance, attach_segment,
                          attach_rotation, attach_hold_up, body_q_prev, body_q, blend, inv_mass, inv_dt2, stiff_only,
                          q, sq)


@wp.struct
class Attachments:
    """The World's attachment slots (``state.attach_*``, ``(num_envs, capacity)``; grasping writes them too)."""

    particle: wp.array2d(dtype=wp.int32)
    body: wp.array2d(dtype=wp.int32)
    offset: wp.array2d(dtype=wp.vec3)
    compliance: wp.array2d(dtype=float)
    segment: wp.array2d(dtype=wp.int32)
    rotation: wp.array2d(dtype=wp.quat)


# ----------------------------------------------------------------------------------------------------
# Cosserat rods: positions + one quaternion per segment (Kugelstadt & Schoemer 2016)
# ----------------------------------------------------------------------------------------------------


@wp.func
def integrate_segment(
    env: int,
    s: int,
    om_old: wp.vec3,
    inv_inertia: wp.array2d(dtype=float),
    segment_damping: wp.array2d(dtype=float),
    dt: float,
    sq: wp.array2d(dtype=wp.quat),
    sqd: wp.array2d(dtype=wp.vec3),
    sq_prev_out: wp.array2d(dtype=wp.quat),
):
    """Segment ``(env, s)``'s prediction from angular velocity ``om_old`` (see ``integrate_segments``)."""
    r = sq[env, s]
    sq_prev_out[env, s] = r
    if inv_inertia[env % inv_inertia.shape[0], s] == 0.0:
        sqd[env, s] = wp.vec3(0.0)
        return
    d = segment_damping[env % segment_damping.shape[0], s]
    om = om_old / (1.0 + d * dt)
    sqd[env, s] = om
    # isotropic scalar inertia: no gyroscopic term
    dq = wp.quat(om[0], om[1], om[2], 0.0) * r
    sq[env, s] = wp.normalize(wp.quat(r[0] + 0.5 * dt * dq[0], r[1] + 0.5 * dt * dq[1], r[2] + 0.5 * dt * dq[2],
                                      r[3] + 0.5 * dt * dq[3]))


@wp.func
def segment_velocity(r: wp.quat, r_prev: wp.quat, inv_dt: float):
    """The angular velocity that turns ``r_prev`` into ``r`` in ``1 / inv_dt`` (the shorter way round)."""
    dq = r * wp.quat_inverse(r_prev)
    om = wp.vec3(dq[0], dq[1], dq[2]) * (2.0 * inv_dt)
    if dq[3] < 0.0:
        om = -om
    return om


@wp.kernel
def integrate_segments(
    inv_inertia: wp.array2d(dtype=float),
    segment_damping: wp.array2d(dtype=float),
    dt: float,
    sq: wp.array2d(dtype=wp.quat),
    sqd: wp.array2d(dtype=wp.vec3),
    sq_prev_out: wp.array2d(dtype=wp.quat),
):
    env, s = wp.tid()
    integrate_segment(env, s, sqd[env, s], inv_inertia, segment_damping, dt, sq, sqd, sq_prev_out)


@wp.kernel
def finish_and_integrate_segments(
    inv_dt_prev: float,
    inv_inertia: wp.array2d(dtype=float),
    segment_damping: wp.array2d(dtype=float),
    dt: float,
    sq: wp.array2d(dtype=wp.quat),
    sqd: wp.array2d(dtype=wp.vec3),
    sq_prev_out: wp.array2d(dtype=wp.quat),
):
    """``update_segment_velocities`` of the substep before and this substep's ``integrate_segments`` in one pass."""
    env, s = wp.tid()
    om_old = segment_velocity(sq[env, s], sq_prev_out[env, s], inv_dt_prev)
    integrate_segment(env, s, om_old, inv_inertia, segment_damping, dt, sq, sqd, sq_prev_out)


@wp.kernel
def update_segment_velocities(
    sq: wp.array2d(dtype=wp.quat), sq_prev: wp.array2d(dtype=wp.quat), inv_dt: float, sqd_out: wp.array2d(dtype=wp.vec3)
):
    env, s = wp.tid()
    sqd_out[env, s] = segment_velocity(sq[env, s], sq_prev[env, s], inv_dt)


@wp.struct
class Prediction:
    """A substep's prediction of particles and rod segments: the inputs of ``predict_particle_and_segment`` and its
    outputs besides the positions and orientations. ``finish`` != 0: the substep before's velocity update
    (``inv_dt_prev``) first, as ``finish_and_integrate_particles`` / ``_segments``."""

    finish: int
    inv_dt_prev: float
    inv_mass: wp.array2d(dtype=float)  # the true inverse masses (not the attachment-weighted ones)
    damping: wp.array2d(dtype=float)
    gravity: wp.vec3
    dt: float
    active: wp.array2d(dtype=wp.int32)
    use_active: int
    force: wp.array2d(dtype=wp.vec3)
    use_force: int
    vbd_start: wp.array(dtype=wp.int32)
    hold: TetHold
    qd: wp.array2d(dtype=wp.vec3)
    q_pred: wp.array2d(dtype=wp.vec3)
    inv_inertia: wp.array2d(dtype=float)
    segment_damping: wp.array2d(dtype=float)
    sqd: wp.array2d(dtype=wp.vec3)
    sq_prev: wp.array2d(dtype=wp.quat)
    # a solver's particle corrections deferred from the substep before (``World``'s ``launch.defer_deltas``), applied
    # by ``apply_deltas_and_integrate``: fixed-point sums ``delta[env, k]`` (scaled by ``delta_scale``) over
    # ``delta_count[env, k]`` contributions
    delta_scale: float
    delta: wp.array3d(dtype=wp.int64)
    delta_count: wp.array2d(dtype=wp.int32)


@wp.func
def predict_particle_and_segment(env: int, k: int, p: Prediction, q: wp.array2d(dtype=wp.vec3),
                                 sq: wp.array2d(dtype=wp.quat)):
    """Particle ``k`` and segment ``k`` of ``env`` (where they exist) predicted: ``integrate_particles_and_segments``'
    thread."""
    if k < q.shape[1]:
        v_old = p.qd[env, k]
        if p.finish != 0:
            v_old = v_old + (q[env, k] - p.q_pred[env, k]) * p.inv_dt_prev
        integrate_particle(env, k, v_old, p.inv_mass, p.damping, p.gravity, p.dt, p.active, p.use_active, p.force,
                           p.use_force, p.vbd_start, p.hold, q, p.qd, p.q_pred)
    if k < sq.shape[1]:
        om_old = p.sqd[env, k]
        if p.finish != 0:
            om_old = segment_velocity(sq[env, k], p.sq_prev[env, k], p.inv_dt_prev)
        integrate_segment(env, k, om_old, p.inv_inertia, p.segment_damping, p.dt, sq, p.sqd, p.sq_prev)


@wp.kernel
def integrate_particles_and_segments(pred: Prediction, q: wp.array2d(dtype=wp.vec3), sq: wp.array2d(dtype=wp.quat)):
    """``integrate_particles`` and ``integrate_segments`` in one launch over ``max(particles, segments)`` threads
    per env (thread ``k`` takes particle ``k`` and segment ``k`` where they exist), with ``pred.finish`` != 0 as
    ``finish_and_integrate_particles`` / ``_segments``: the same arithmetic on independent elements, one launch fewer
    per substep in a scene with rods (RopeThreading: 99 per env step)."""
    env, k = wp.tid()
    predict_particle_and_segment(env, k, pred, q, sq)


@wp.kernel
def apply_deltas_and_integrate(pred: Prediction, q: wp.array2d(dtype=wp.vec3), sq: wp.array2d(dtype=wp.quat)):
    """``integrate_particles_and_segments`` after adding to each particle the mean of the corrections a solver
    deferred from the substep before (``pred.delta`` over ``pred.delta_count``, then cleared:
    ``contact.apply_mean_delta``, as ``contact.apply_surface_deltas`` does), one launch instead of two (its own
    kernel, so that the plain prediction carries no delta loads; sm_90: 38 registers each since the hold's branch, 32
    and 34 before it)."""
    env, k = wp.tid()
    if k < q.shape[1]:
        apply_mean_delta(env, k, pred.delta, pred.delta_count, pred.delta_scale, q)
    predict_particle_and_segment(env, k, pred, q, sq)


@wp.func
def quat_add_scaled(a: wp.quat, b: wp.quat, s: float):
    return wp.quat(a[0] + b[0] * s, a[1] + b[1] * s, a[2] + b[2] * s, a[3] + b[3] * s)


@wp.func
def stretch_shear_constraint(
    env: int,
    c: int,
    particles: wp.array(dtype=wp.vec3i),
    rest: wp.array(dtype=float),
    compliance: wp.array2d(dtype=wp.vec3),
    inv_inertia: wp.array2d(dtype=float),
    inv_mass: wp.array2d(dtype=float),
    inv_dt2: float,
    use_lambda: int,
    lam: wp.array2d(dtype=wp.vec3),
    segment_active: wp.array2d(dtype=wp.int32),
    q: wp.array2d(dtype=wp.vec3),
    sq: wp.array2d(dtype=wp.quat),
):
    """Stretch-shear constraint ``c`` of env ``env`` (a segment's Gamma, Kugelstadt & Schoemer 2016)."""
    ij = particles[c]
    s = ij[2]
    # segment_active is (N, S) with cutting masks and (1, 0) without
    if segment_active.shape[1] > 0:
        if segment_active[env, s] == 0:
            return
    pe = env % inv_mass.shape[0]
    w0 = inv_mass[pe, ij[0]]
    w1 = inv_mass[pe, ij[1]]
    wq = inv_inertia[env % inv_inertia.shape[0], s]
    p0 = q[env, ij[0]]
    p1 = q[env, ij[1]]
    r = sq[env, s]
    L = rest[c]
    d3 = wp.quat_rotate(r, wp.vec3(0.0, 0.0, 1.0))
    # strain Gamma = (p1 - p0) / L - d3, solved per material axis (shear x, shear y, stretch z) with its
    # own compliance. Generalised inverse mass: (w0 + w1) / L^2 from the positions plus 4 wq = 1 / I from
    # the orientation for the shear axes only (rotating d3 cannot change the stretch along d3).
    gamma_w = (p1 - p0) / L - d3
    wp_sum = (w0 + w1) / (L * L)
    wsh = wp_sum + 4.0 * wq
    if wp_sum + wsh == 0.0:
        return
    a = compliance[env % compliance.shape[0], c] * inv_dt2
    gamma_m = wp.quat_rotate_inv(r, gamma_w)
    l0 = wp.vec3(0.0)
    if use_lambda != 0:
        l0 = lam[env, c]
    dz = float(0.0)
    if a[2] >= 0.0 and wp_sum + a[2] > 0.0:
        dz = (-gamma_m[2] - a[2] * l0[2]) / (wp_sum + a[2])
    dl = wp.vec3((-gamma_m[0] - a[0] * l0[0]) / (wsh + a[0]), (-gamma_m[1] - a[1] * l0[1]) / (wsh + a[1]), dz)
    if use_lambda != 0:
        lam[env, c] = l0 + dl
    corr = wp.quat_rotate(r, dl)  # = -(scaled Gamma) in world frame
    q[env, ij[0]] = p0 - corr * (w0 / L)
    q[env, ij[1]] = p1 + corr * (w1 / L)
    if wq > 0.0:
        # dq = 2 wq (Gamma_s q e3_bar) with Gamma_s = -(shear part of corr); q e3_bar = (q.z, -q.y, q.x, -q.w)
        # as (w, x, y, z)
        qe3b = wp.quat(-r[1], r[0], -r[3], r[2])
        # The frame also turns d3 towards the unit edge direction along the stretch axis (z moves no particle:
        # stretch is the direct rod solve's job). Without this term |Gamma_xy|^2 = sin^2(theta) has a stable
        # minimum with d3 anti-parallel to the edge: flipped segments stuck there and the bend-twist
        # constraints of their neighbours spun the frames at the 2 / h velocity limit. Near alignment the
        # z term turns nothing (first order), so the shear response is unchanged.
        e_len = wp.length(p1 - p0)
        dzr = float(0.0)
        if e_len > 1.0e-12:
            dzr = (1.0 - wp.dot(p1 - p0, d3) / e_len) / (4.0 * wq + a[0])
        cs = wp.quat_rotate(r, wp.vec3(dl[0], dl[1], dzr))
        dq = wp.quat(-cs[0], -cs[1], -cs[2], 0.0) * qe3b
        sq[env, s] = wp.normalize(quat_add_scaled(r, dq, 2.0 * wq))


@wp.func
def bend_twist_constraint(
    env: int,
    b: int,
    segments: wp.array(dtype=wp.vec2i),
    rest: wp.array(dtype=wp.quat),
    compliance: wp.array2d(dtype=wp.vec3),
    inv_inertia: wp.array2d(dtype=float),
    inv_dt2: float,
    use_lambda: int,
    lam: wp.array2d(dtype=wp.vec3),
    segment_active: wp.array2d(dtype=wp.int32),
    sq: wp.array2d(dtype=wp.quat),
):
    """Bend-twist constraint ``b`` of env ``env`` (the Darboux quaternion of two adjacent segments)."""
    ab = segments[b]
    if segment_active.shape[1] > 0:
        # bend-twist couples two segments: gone with either of them
        if segment_active[env, ab[0]] == 0 or segment_active[env, ab[1]] == 0:
            return
    pe = env % inv_inertia.shape[0]
    wa = inv_inertia[pe, ab[0]]
    wb = inv_inertia[pe, ab[1]]
    wsum = wa + wb
    if wsum == 0.0:
        return
    qa = sq[env, ab[0]]
    qb = sq[env, ab[1]]
    om = wp.quat_inverse(qa) * qb  # Darboux quaternion in qa's material frame
    r0 = rest[b]
    om_minus = wp.vec4(om[0] - r0[0], om[1] - r0[1], om[2] - r0[2], om[3] - r0[3])
    om_plus = wp.vec4(om[0] + r0[0], om[1] + r0[1], om[2] + r0[2], om[3] + r0[3])
    C = wp.vec3(om_minus[0], om_minus[1], om_minus[2])
    # q and -q are the same rotation: take the nearer representative of the rest Darboux vector
    if wp.length_sq(om_minus) > wp.length_sq(om_plus):
        C = wp.vec3(om_plus[0], om_plus[1], om_plus[2])
    a = compliance[env % compliance.shape[0], b] * inv_dt2
    l0 = wp.vec3(0.0)
    if use_lambda != 0:
        l0 = lam[env, b]
    dl = wp.vec3(
        (-C[0] - a[0] * l0[0]) / (wsum + a[0]),
        (-C[1] - a[1] * l0[1]) / (wsum + a[1]),
        (-C[2] - a[2] * l0[2]) / (wsum + a[2]),
    )
    if use_lambda != 0:
        lam[env, b] = l0 + dl
    # PBD library form with omega_corr = -dlambda: dqa = wa qb omega, dqb = -wb qa omega
    oc = wp.quat(-dl[0], -dl[1], -dl[2], 0.0)
    sq[env, ab[0]] = wp.normalize(quat_add_scaled(qa, qb * oc, wa))
    sq[env, ab[1]] = wp.normalize(quat_add_scaled(qb, qa * oc, -wb))


@wp.kernel
def solve_stretch_shear(
    start: int,
    particles: wp.array(dtype=wp.vec3i),
    rest: wp.array(dtype=float),
    compliance: wp.array2d(dtype=wp.vec3),
    inv_inertia: wp.array2d(dtype=float),
    inv_mass: wp.array2d(dtype=float),
    inv_dt2: float,
    use_lambda: int,
    lam: wp.array2d(dtype=wp.vec3),
    segment_active: wp.array2d(dtype=wp.int32),
    q: wp.array2d(dtype=wp.vec3),
    sq: wp.array2d(dtype=wp.quat),
):
    """One colour of stretch-shear constraints from ``start``, a thread each."""
    env, t = wp.tid()
    stretch_shear_constraint(env, start + t, particles, rest, compliance, inv_inertia, inv_mass, inv_dt2, use_lambda,
                             lam, segment_active, q, sq)


@wp.kernel
def solve_bend_twist(
    start: int,
    segments: wp.array(dtype=wp.vec2i),
    rest: wp.array(dtype=wp.quat),
    compliance: wp.array2d(dtype=wp.vec3),
    inv_inertia: wp.array2d(dtype=float),
    inv_dt2: float,
    use_lambda: int,
    lam: wp.array2d(dtype=wp.vec3),
    segment_active: wp.array2d(dtype=wp.int32),
    sq: wp.array2d(dtype=wp.quat),
):
    """One colour of bend-twist constraints from ``start``, a thread each."""
    env, t = wp.tid()
    bend_twist_constraint(env, start + t, segments, rest, compliance, inv_inertia, inv_dt2, use_lambda, lam,
                          segment_active, sq)


@wp.struct
class RodSweep:
    """The rods' constraints as one argument of the fused rod launches: the colour ranges of the stretch-shear and
    bend-twist groups, their constraints, the segments' inverse inertias, the particles' (attachment-weighted)
    inverse masses, ``1 / h^2``, the multipliers (``use_lambda``) and the cut mask."""

    segment_offsets: wp.array(dtype=wp.int32)
    particles: wp.array(dtype=wp.vec3i)
    segment_rest: wp.array(dtype=float)
    segment_compliance: wp.array2d(dtype=wp.vec3)
    bend_offsets: wp.array(dtype=wp.int32)
    bend_segments: wp.array(dtype=wp.vec2i)
    bend_rest: wp.array(dtype=wp.quat)
    bend_compliance: wp.array2d(dtype=wp.vec3)
    inv_inertia: wp.array2d(dtype=float)
    inv_mass: wp.array2d(dtype=float)
    inv_dt2: float
    use_lambda: int
    segment_lam: wp.array2d(dtype=wp.vec3)
    bend_lam: wp.array2d(dtype=wp.vec3)
    segment_active: wp.array2d(dtype=wp.int32)


@wp.func
def solve_rod_colors(env: int, lane: int, lanes: int, barrier: wp.tile(dtype=int, shape=(1,), storage="shared"),
                     r: RodSweep, q: wp.array2d(dtype=wp.vec3), sq: wp.array2d(dtype=wp.quat)):
    """Lane ``lane`` of ``lanes``' share of every stretch-shear colour, then every bend-twist colour, of env ``env``,
    a block barrier after each (``solve_rods_fused``)."""
    for color in range(r.segment_offsets.shape[0] - 1):
        for c in range(r.segment_offsets[color] + lane, r.segment_offsets[color + 1], lanes):
            stretch_shear_constraint(env, c, r.particles, r.segment_rest, r.segment_compliance, r.inv_inertia,
                                     r.inv_mass, r.inv_dt2, r.use_lambda, r.segment_lam, r.segment_active, q, sq)
        wp.tile_scatter_masked(barrier, 0, 0, False)  # a block barrier (nothing written)
    for color in range(r.bend_offsets.shape[0] - 1):
        for b in range(r.bend_offsets[color] + lane, r.bend_offsets[color + 1], lanes):
            bend_twist_constraint(env, b, r.bend_segments, r.bend_rest, r.bend_compliance, r.inv_inertia, r.inv_dt2,
                                  r.use_lambda, r.bend_lam, r.segment_active, sq)
        wp.tile_scatter_masked(barrier, 0, 0, False)


@wp.kernel
def solve_rods_fused(rods: RodSweep, q: wp.array2d(dtype=wp.vec3), sq: wp.array2d(dtype=wp.quat)):
    """Every colour of the stretch-shear constraints, then every colour of the bend-twist ones, in one launch: a
    thread block per env whose lanes take a colour's constraints side by side, a block barrier between colours (the
    positions and orientations stay in global memory, which a barrier makes visible to the block). The same
    ``wp.func`` per constraint as the per-colour kernels, in the same order on the CPU (one lane there): bit-identical.
    Why: a rod task's colours are small (RopeCutting's 95 segments per env in 2 colours, RopeThreading's 100), so its
    four launches per sweep were mostly fixed cost."""
    env, lane = wp.tid()
    barrier = wp.tile_zeros(shape=1, dtype=int, storage="shared")
    solve_rod_colors(env, lane, wp.block_dim(), barrier, rods, q, sq)


@wp.kernel
def predict_and_solve_rods_fused(pred: Prediction, rods: RodSweep, q: wp.array2d(dtype=wp.vec3),
                                 sq: wp.array2d(dtype=wp.quat)):
    """``integrate_particles_and_segments`` for the env's particles and segments, a block barrier, then
    ``solve_rods_fused``: the substep's prediction and its first sweep's rod colours in one launch, where nothing
    comes between them (``World.predict_in_rod_sweep``: a world whose only constraints are rods, e.g. RopeThreading
    and RopeCutting). Each lane predicts the elements ``lane, lane + lanes, ...`` of its env: the same arithmetic on
    the same independent elements as the separate launch, so bit-identical on the CPU (one lane, in order); one launch
    and a pass of the env's rods through memory fewer per substep, the prediction's writes read back by the same
    block."""
    env, lane = wp.tid()
    lanes = wp.block_dim()
    barrier = wp.tile_zeros(shape=1, dtype=int, storage="shared")
    for k in range(lane, wp.max(q.shape[1], sq.shape[1]), lanes):
        predict_particle_and_segment(env, k, pred, q, sq)
    wp.tile_scatter_masked(barrier, 0, 0, False)  # every element predicted before any colour reads it
    solve_rod_colors(env, lane, lanes, barrier, rods, q, sq)


@wp.struct
class AttachmentPass:
    """``solve_attachments``' arguments as one bundle, for the rod launch that runs a substep's closing attachment pass
    first (``contact_rods_fused_kernel``); no slots (``particle`` of shape ``(n, 0)``) where none was deferred."""

    particle: wp.array2d(dtype=wp.int32)
    body: wp.array2d(dtype=wp.int32)
    offset: wp.array2d(dtype=wp.vec3)
    compliance: wp.array2d(dtype=float)
    segment: wp.array2d(dtype=wp.int32)
    rotation: wp.array2d(dtype=wp.quat)
    hold_up: wp.array(dtype=wp.vec3)
    body_q_prev: wp.array2d(dtype=wp.transform)
    body_q: wp.array2d(dtype=wp.transform)
    blend: float
    inv_mass: wp.array2d(dtype=float)
    inv_dt2: float
    stiff_only: int


#: ``AttachmentPass``' fields in ``solve_attachments``' argument order
ATTACHMENT_PASS_FIELDS = ("particle", "body", "offset", "compliance", "segment", "rotation", "hold_up", "body_q_prev",
                          "body_q", "blend", "inv_mass", "inv_dt2", "stiff_only")

_CONTACT_ROD_KERNELS: list = []


def contact_rods_fused_kernel() -> wp.Kernel:
    """``contact_predict_and_solve_rods_fused`` (built once, in a module of its own: only RopeThreading-like worlds
    compile it). The particle contact is the variant without the mesh query: a world with a mesh shape keeps the
    contact in its own launch."""
    if _CONTACT_ROD_KERNELS:
        return _CONTACT_ROD_KERNELS[0]
    collide_particle = particle_collision_func(False)

    def contact_predict_and_solve_rods_fused(attach: AttachmentPass, particles: ContactParticles,
                                             shapes: ShapeTable, motion: BodyMotion, poses: ShapePoses,
                                             solve: ParticleSolve, ignore: IgnoreMask, masks: CutMasks, report: int,
                                             report_margin: float, pred: Prediction, rods: RodSweep,
                                             q: wp.array2d(dtype=wp.vec3), sq: wp.array2d(dtype=wp.quat),
                                             reports: ContactReports):
        """The substep before's last two launches, deferred by ``World.contact_in_rod_launch``: its closing attachment
        pass (``solve_attachments``: lane 0 walks the env's slots in order; none where ``attach`` has no slots) and
        its particle contact (``contact.collide_particles``: each lane takes the contact particles ``lane, lane +
        lanes, ...``), a block barrier after each, then ``predict_and_solve_rods_fused``: two launches fewer per
        substep. Both read the substep's start (``solve``: its prediction and velocities) before the next prediction
        overwrites them: the same arithmetic in the same order as the separate launches on the CPU (one lane), so
        bit-identical there. Why: RopeThreading's contact launch over 409,600 threads took 53 us per substep on an
        H200 and its attachment launch 11 us (together 6.4 of the 21.7 ms of kernel time per RGB env step) for a few
        loads per particle and slot; here the env's block does them beside its rods (untimed)."""
        env, lane = wp.tid()
        lanes = wp.block_dim()
        barrier = wp.tile_zeros(shape=1, dtype=int, storage="shared")
        if lane == 0:
            for s in range(attach.particle.shape[1]):
                solve_attachment_slot(env, s, attach.particle, attach.body, attach.offset, attach.compliance,
                                      attach.segment, attach.rotation, attach.hold_up, attach.body_q_prev,
                                      attach.body_q, attach.blend, attach.inv_mass, attach.inv_dt2, attach.stiff_only,
                                      q, sq)
        wp.tile_scatter_masked(barrier, 0, 0, False)  # the attachments written before the contact reads them
        for k in range(lane, particles.particle.shape[0], lanes):
            collide_particle(env, k, particles, shapes, motion, poses, solve, ignore, masks, report, report_margin, q,
                             reports)
        wp.tile_scatter_masked(barrier, 0, 0, False)  # every contact written before any prediction reads it
        for k in range(lane, wp.max(q.shape[1], sq.shape[1]), lanes):
            predict_particle_and_segment(env, k, pred, q, sq)
        wp.tile_scatter_masked(barrier, 0, 0, False)
        solve_rod_colors(env, lane, lanes, barrier, rods, q, sq)

    _CONTACT_ROD_KERNELS.append(wp.kernel(contact_predict_and_solve_rods_fused, module="unique",
                                          enable_backward=False))
    return _CONTACT_ROD_KERNELS[0]
