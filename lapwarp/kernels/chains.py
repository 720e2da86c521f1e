"""Direct (exact, linear-time) XPBD solve of chains of distance constraints: Cosserat rods' segments and the edge
chains of cloth (``lapwarp.builder`` splits a cloth's edges into straight chains, rows, columns and diagonals on a
grid).

One thread per (env, chain) solves the whole chain at once, so a rod or a cloth keeps its length at a handful of
substeps; Gauss-Seidel moves information one link per sweep, and a hanging 100-segment rod stretched ~15x (a
hanging 40 x 40 cloth without tethers 2x on average, 15x at worst) at 20 substeps per 0.1 s. The chains of one
launch (a *family*) share no node, so they run in parallel without atomics; families follow each other
(Gauss-Seidel across families).

A chain is a list of nodes (``chain_node``: global particle indices) and of constraints (``chain_constraint``: the
index of link ``k``'s rest length, compliance, multiplier and cutting mask column in its constraint group). The
chains of a family are stored interleaved, link-major: link ``k`` of the family's ``i``-th chain at slot
``link_base + k * stride + i`` and node ``j`` at ``node_base + j * stride + i`` (``stride`` = chains in the family), so
the threads of a warp, each walking its own chain, read and write neighbouring memory; the per-env scratch uses the
same slots.

Derivation (Deul, Kugelstadt, Weiler, Bender 2018, "Direct Position-Based Solver for Stiff Rods", here
for the scalar stretch constraints only; shear and bend-twist stay local Gauss-Seidel projections).
Segment ``k`` of a rod joins nodes ``k`` and ``k + 1`` (node ``m`` is node ``0`` for a closed loop):

    C_k = |x_{k+1} - x_k| - L_k,   n_k = (x_{k+1} - x_k) / |x_{k+1} - x_k|,
    grad_{x_k} C_k = -n_k,   grad_{x_{k+1}} C_k = n_k.

The XPBD step linearised at the current positions, ``(J W J^T + alpha / h^2) dl = -C - alpha / h^2 lambda``
with ``W`` the inverse masses, couples only segments that share a node, so the matrix is tridiagonal:

    A_kk = w_k + w_{k+1} + alpha_k / h^2,   A_{k,k+1} = A_{k+1,k} = -w_{k+1} n_k . n_{k+1}

and cyclic tridiagonal for a closed loop (extra corner ``A_{m-1,0} = -w_0 n_{m-1} . n_0``). ``A`` is symmetric
and weakly diagonally dominant (``|A_{k,k-1}| + |A_{k,k+1}| <= w_k + w_{k+1}``), strictly so with compliance,
so the Thomas algorithm needs no pivoting. Closed loops use Sherman-Morrison: ``A = T + u v^T`` with
``u = (g, 0, .., 0, s)``, ``v = (1, 0, .., 0, s / g)``, ``g = -A_00``, ``s`` the corner, and ``T`` the tridiagonal
part with ``T_00 = A_00 - g``, ``T_{m-1,m-1} = A_{m-1,m-1} - s^2 / g`` (both only grow, keeping ``T`` dominant);
then ``x = y - (v . y) / (1 + v . z) z`` with ``T y = rhs``, ``T z = u``. Positions move by
``dx_j = w_j (n_{j-1} dl_{j-1} - n_j dl_j)``. Pinned nodes have ``w = 0`` and simply drop out; a segment with
both nodes pinned and no compliance has an all-zero row and gets ``dl = 0``.

Compliance ``alpha_k = L_k / (E A)`` is in SI (m/N), so the stiffness does not depend on the substep count; one
solve per sweep is one Newton step on the nonlinear constraints (the residual is second order in the
correction). Scratch (modified super-diagonal and right-hand sides) is preallocated per env per segment.

Cutting (``lapwarp.cutting``): a removed constraint (``active[env, c] == 0``: a cut rod segment, a cloth edge with no
triangle left) is a break in the chain. Its
row becomes the identity with a zero right-hand side (``dl = 0``) and its couplings to both neighbours are
zeroed, so the tridiagonal system splits into independent blocks, one per remaining piece, solved by the same
sweep; a loop cut anywhere loses its corner coupling (plain tridiagonal). In the transverse filter a removed
constraint has no tension and no direction, so the nodes beside a cut are free ends. ``active`` of shape
``(1, 0)`` means the scene has no cutting masks.
"""

from __future__ import annotations

import warp as wp

wp.set_module_options({"enable_backward": False})


def check_newton_tolerance(value) -> float:
    """A Newton tolerance of the chain solves that stop early (m): a finite float >= 0 (0 = every step)."""
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not 0.0 <= float(value) < float("inf"):
        raise ValueError(f"newton_tolerance must be a finite length >= 0 (m), got {value!r}")
    return float(value)


@wp.func
def segment_dir(a: wp.vec3, b: wp.vec3):
    """Unit vector a -> b and the length; a zero vector for a degenerate segment (its row then acts not)."""
    d = b - a
    length = wp.length(d)
    n = wp.vec3(0.0)
    if length > 1.0e-12:
        n = d / length
    return n, length


@wp.func
def link_row_terms(w_k: float, w_k1: float, alpha: float, residual: float, lam: float, k: int, m: int, cyclic: int,
                   g: float, s: float, active: int):
    """Diagonal and right-hand sides ``(-C - alpha lambda, u)`` of link ``k``'s row (``residual = -C_k``, ``lam`` the
    multiplier so far), given the loop's Sherman-Morrison ``g`` and corner ``s`` when ``cyclic``; a removed link or an
    empty row (both nodes pinned, rigid) becomes the identity with a zero right-hand side. For the solves that form
    ``g`` before the sweep (kernels/chains_partitioned.py, kernels/chains_block.py)."""
    b = w_k + w_k1 + alpha
    rhs = residual - alpha * lam
    u = float(0.0)
    if cyclic != 0:
        if k == 0:
            b = b - g
            u = g
        if k == m - 1:
            b = b - s * s / g
            u = s
    if b <= 0.0 or active == 0:
        b = 1.0
        rhs = 0.0
    return b, rhs, u


@wp.func
def node_row(n_prev: wp.vec3, dl_prev: float, k_prev: float, n_j: wp.vec3, dl_j: float, k_j: float, w_j: float,
             j: int):
    """Filter row of a node: sub-diagonal, diagonal, super-diagonal, right-hand side (the transverse part of
    ``dx_j = w_j (n_{j-1} dl_{j-1} - n_j dl_j)``) and the part along the tangent."""
    dx = (n_prev * dl_prev - n_j * dl_j) * w_j
    t = n_prev + n_j
    tl = wp.length(t)
    par = wp.vec3(0.0)
    if tl > 1.0e-12:
        t = t / tl
        par = t * wp.dot(dx, t)
    lo = -w_j * k_prev
    up = -w_j * k_j
    if j == 0:
        lo = 0.0  # open-chain filter (also for loops, see solve_chains)
    return lo, 1.0 - lo - up, up, dx - par, par


@wp.kernel
def solve_chains(
    family_start: int,
    stride: int,
    link_base: int,
    node_base: int,
    chain_edge_count: wp.array(dtype=wp.int32),
    chain_closed: wp.array(dtype=wp.int32),
    chain_node: wp.array(dtype=wp.int32),
    chain_constraint: wp.array(dtype=wp.int32),
    rest: wp.array(dtype=float),
    compliance: wp.array2d(dtype=float),
    inv_mass: wp.array2d(dtype=float),
    inv_dt2: float,
    use_lambda: int,
    newton_steps: int,
    lam: wp.array2d(dtype=float),
    scratch_l: wp.array2d(dtype=float),
    scratch_c: wp.array2d(dtype=float),
    scratch_d: wp.array2d(dtype=float),
    scratch_e: wp.array2d(dtype=float),
    node_c: wp.array2d(dtype=float),
    node_d: wp.array2d(dtype=wp.vec3),
    node_par: wp.array2d(dtype=wp.vec3),
    active: wp.array2d(dtype=wp.int32),
    q: wp.array2d(dtype=wp.vec3),
):
    env, i = wp.tid()
    r = family_start + i  # chain index
    # link k of this chain at slot s0 + k * stride, node j at nb + j * stride: the chains of a family are interleaved
    # (link-major), so the threads of a warp, walking their chains in step, touch neighbouring memory
    s0 = link_base + i
    nb = node_base + i
    m = chain_edge_count[r]
    nodes = m + 1
    closed3 = int(0)
    if chain_closed[r] != 0:
        nodes = m
        if m >= 3:
            closed3 = 1
    # node 0 of a loop also ends the closing link m - 1, also once the loop is cut at link 0 (an open chain then)
    wraps = closed3
    pe = env % inv_mass.shape[0]
    ce = env % compliance.shape[0]
    masked = active.shape[1] > 0
    if masked and closed3 != 0:
        # a loop cut at its closing corner is an open chain (cut elsewhere: blocks split inside the solve)
        if active[env, chain_constraint[s0]] == 0 or active[env, chain_constraint[s0 + (m - 1) * stride]] == 0:
            closed3 = 0

    for it in range(newton_steps):
        cyclic = closed3
        # ---- forward elimination (Thomas); for a loop also the second right-hand side u --------------------
        x_first = q[env, chain_node[nb]]
        w_first = inv_mass[pe, chain_node[nb]]
        # the walk carries node k + 1 (index and position: the next link's start, loaded once), link k's constraint
        # and whether it is active from one link to the next, so that a link loads one new node and one new
        # constraint (a link loaded both its nodes' indices and positions and its constraint's index up to five times)
        node_k1 = chain_node[nb + (1 % nodes) * stride]
        x_k1 = q[env, node_k1]
        n_cur, len_cur = segment_dir(x_first, x_k1)
        cons_k = chain_constraint[s0]
        act_k = int(1)
        if masked:
            act_k = active[env, cons_k]
        # closing segment m-1 (node m-1 -> node 0) and its coupling s = A_{m-1,0} for a loop
        n_last = wp.vec3(0.0)
        g = float(0.0)
        s = float(0.0)
        if cyclic != 0:
            n_last, len_last = segment_dir(q[env, chain_node[nb + (m - 1) * stride]], x_first)
            s = -w_first * wp.dot(n_last, n_cur)
            if s == 0.0:
                cyclic = 0  # no corner coupling (node 0 pinned): a plain tridiagonal system
        w_k = w_first  # inverse mass of node k
        c_prev = float(0.0)  # modified super-diagonal c'_{k-1}
        d_prev = float(0.0)  # modified right-hand side d'_{k-1}
        e_prev = float(0.0)  # modified second right-hand side (Sherman-Morrison u)
        a_k = float(0.0)  # sub-diagonal A_{k,k-1}
        for k in range(m):
            w_k1 = inv_mass[pe, node_k1]
            # look one segment ahead for the super-diagonal A_{k,k+1}
            n_next = wp.vec3(0.0)
            len_next = float(0.0)
            c_k = float(0.0)
            node_k2 = node_k1
            x_k2 = x_k1
            cons_next = cons_k
            act_next = act_k
            if k + 1 < m:
                k2 = k + 2
                if k2 >= nodes:
                    k2 = k2 - nodes
                node_k2 = chain_node[nb + k2 * stride]
                x_k2 = q[env, node_k2]
                n_next, len_next = segment_dir(x_k1, x_k2)
                c_k = -w_k1 * wp.dot(n_cur, n_next)
                cons_next = chain_constraint[s0 + (k + 1) * stride]
                if masked:
                    act_next = active[env, cons_next]
                    if act_k == 0 or act_next == 0:
                        c_k = 0.0  # no coupling across a cut
            alpha = compliance[ce, cons_k] * inv_dt2
            b_k = w_k + w_k1 + alpha
            rhs = rest[cons_k] - len_cur  # -C_k
            # lambda of this sweep so far: earlier sweeps (iterations > 1) plus the earlier Newton step
            lam_k = float(0.0)
            if use_lambda != 0:
                lam_k = lam[env, cons_k]
            if it > 0:
                lam_k = lam_k + scratch_l[env, s0 + k * stride]
            rhs = rhs - alpha * lam_k
            u_k = float(0.0)
            if cyclic != 0:
                if k == 0:
                    g = -b_k
                    b_k = b_k - g
                    u_k = g
                if k == m - 1:
                    b_k = b_k - s * s / g
                    u_k = s
            if b_k <= 0.0 or act_k == 0:
                # both nodes pinned and rigid (empty row) or a removed segment: keep it out of the solve, dl = 0
                b_k = 1.0
                rhs = 0.0
            denom = b_k - a_k * c_prev
            inv = 1.0 / denom
            c_prev = c_k * inv
            d_prev = (rhs - a_k * d_prev) * inv
            e_prev = (u_k - a_k * e_prev) * inv
            scratch_c[env, s0 + k * stride] = c_prev
            scratch_d[env, s0 + k * stride] = d_prev
            if cyclic != 0:
                scratch_e[env, s0 + k * stride] = e_prev
            a_k = c_k
            n_cur = n_next
            len_cur = len_next
            w_k = w_k1
            node_k1 = node_k2
            x_k1 = x_k2
            cons_k = cons_next
            act_k = act_next

        # ---- back substitution, dl overwrites scratch_d (and z overwrites scratch_e for a loop) --------------
        y_next = float(0.0)
        z_next = float(0.0)
        for kk in range(m):
            k = m - 1 - kk
            c = scratch_c[env, s0 + k * stride]
            y_next = scratch_d[env, s0 + k * stride] - c * y_next
            scratch_d[env, s0 + k * stride] = y_next
            if cyclic != 0:
                z_next = scratch_e[env, s0 + k * stride] - c * z_next
                scratch_e[env, s0 + k * stride] = z_next
        if cyclic != 0:
            # y_next, z_next now hold y_0, z_0; v = (1, 0, .., 0, s / g)
            vy = y_next + (s / g) * scratch_d[env, s0 + (m - 1) * stride]
            vz = z_next + (s / g) * scratch_e[env, s0 + (m - 1) * stride]
            f = vy / (1.0 + vz)
            for k in range(m):
                sk = s0 + k * stride
                scratch_d[env, sk] = scratch_d[env, sk] - f * scratch_e[env, sk]

        # ---- corrections dx_j = w_j (n_{j-1} dl_{j-1} - n_j dl_j), normals from the positions before this solve.
        # Applied as is, the transverse part of dx is an explicit diffusion of kinks, d <- d + r Lap(d) with
        # r = w Lambda / l (Lambda = -dl the tension impulse of the substep): unstable once r > 1/2, i.e. when the
        # tension impulse moves a node by more than half a segment (a hanging 100-segment rod at 20 substeps
        # has r ~ 12 near the top; Tournier et al. 2015 "Stable Constrained Dynamics" describe the same
        # instability). The transverse part is therefore filtered implicitly, (I - r Lap) y = dx_perp: the
        # geometric-stiffness term of the tension, solved per rod as one more tridiagonal system (vec3
        # right-hand side). Smooth transverse modes (a swinging rope) pass almost unchanged, the zigzag mode is
        # damped by 1 / (1 + 4 r); the component along the local tangent (what keeps the lengths) is untouched.
        # For a loop the coupling across the closing segment is left explicit (open-chain filter).
        x_cur = x_first
        n_prev = wp.vec3(0.0)
        dl_prev = float(0.0)
        k_prev = float(0.0)  # w-free tension weight Lambda / l of segment j - 1
        if wraps != 0:
            # the closing link's correction (node 0 pinned: w_0 = 0 below)
            n_prev, len_prev = segment_dir(q[env, chain_node[nb + (m - 1) * stride]], x_first)
            if masked:
                if active[env, chain_constraint[s0 + (m - 1) * stride]] == 0:
                    n_prev = wp.vec3(0.0)  # removed: node 0 is a free end
            dl_prev = scratch_d[env, s0 + (m - 1) * stride]
        cn_prev = float(0.0)
        dn_prev = wp.vec3(0.0)
        node_j = chain_node[nb]  # carried like the forward walk's
        for j in range(nodes):
            n_j = wp.vec3(0.0)
            dl_j = float(0.0)
            k_j = float(0.0)
            x_next = wp.vec3(0.0)
            node_next = node_j
            if j < m:
                jn = j + 1
                if jn == nodes:
                    x_next = x_first  # closing segment of a loop: node 0 as it was before the update
                else:
                    node_next = chain_node[nb + jn * stride]
                    x_next = q[env, node_next]
                n_j, len_j = segment_dir(x_cur, x_next)
                cj = chain_constraint[s0 + j * stride]
                if masked:
                    if active[env, cj] == 0:
                        n_j = wp.vec3(0.0)  # a removed segment: the nodes beside it are free ends
                dl_j = scratch_d[env, s0 + j * stride]
                # multiplier of this sweep's Newton steps so far (kept in scratch_l for the next step)
                acc = dl_j
                if it > 0:
                    acc = scratch_l[env, s0 + j * stride] + dl_j
                if it < newton_steps - 1:
                    scratch_l[env, s0 + j * stride] = acc
                if use_lambda != 0 and it == newton_steps - 1:
                    lam[env, cj] = lam[env, cj] + acc
                if j + 1 < nodes and len_j > 1.0e-12:
                    k_j = wp.max(-dl_j, 0.0) / len_j
            w_j = inv_mass[pe, node_j]
            lo, diag, up, rhs_j, par = node_row(n_prev, dl_prev, k_prev, n_j, dl_j, k_j, w_j, j)
            inv = 1.0 / (diag - lo * cn_prev)
            cn_prev = up * inv
            dn_prev = (rhs_j - dn_prev * lo) * inv
            node_c[env, nb + j * stride] = cn_prev
            node_d[env, nb + j * stride] = dn_prev
            node_par[env, nb + j * stride] = par + x_cur
            x_cur = x_next
            node_j = node_next
            n_prev = n_j
            dl_prev = dl_j
            k_prev = k_j
        y = wp.vec3(0.0)
        for jj in range(nodes):
            j = nodes - 1 - jj
            y = node_d[env, nb + j * stride] - y * node_c[env, nb + j * stride]
            if inv_mass[pe, chain_node[nb + j * stride]] > 0.0:
                q[env, chain_node[nb + j * stride]] = node_par[env, nb + j * stride] + y


# The same solve capped at 96 registers per thread (from 148; a few values spill to local memory). A cloth launches
# hundreds of chains per env, enough warps to hide the spills, and more of them fit an SM: on the H100 at 4,096 envs
# the 40 x 40 cloth's chain families take 2.26 ms per substep instead of 2.77 (cloth_free, 10 substeps: 101.7k ->
# 116.1k env-steps/s). A rod's few long chains are latency-bound and lose 5 % with the cap, so they keep solve_chains.
solve_cloth_chains = wp.kernel(solve_chains.func, cuda_max_registers=96, module="unique", enable_backward=False)


@wp.kernel
def solve_open_chains(
    family_start: int,
    stride: int,
    link_base: int,
    node_base: int,
    chain_edge_count: wp.array(dtype=wp.int32),
    chain_closed: wp.array(dtype=wp.int32),
    chain_node: wp.array(dtype=wp.int32),
    chain_constraint: wp.array(dtype=wp.int32),
    rest: wp.array(dtype=float),
    compliance: wp.array2d(dtype=float),
    inv_mass: wp.array2d(dtype=float),
    inv_dt2: float,
    use_lambda: int,
    newton_steps: int,
    lam: wp.array2d(dtype=float),
    scratch_l: wp.array2d(dtype=float),
    scratch_c: wp.array2d(dtype=float),
    scratch_d: wp.array2d(dtype=float),
    scratch_e: wp.array2d(dtype=float),
    node_c: wp.array2d(dtype=float),
    node_d: wp.array2d(dtype=wp.vec3),
    node_par: wp.array2d(dtype=wp.vec3),
    active: wp.array2d(dtype=wp.int32),
    q: wp.array2d(dtype=wp.vec3),
):
    """``solve_chains`` for families of open chains (``chain_closed`` and ``scratch_e`` go unused) in three walks per
    Newton step instead of four: the link system's back substitution also forms each node's filter row (with ``dl_k``
    and ``dl_{k+1}`` known, node ``k + 1``'s row is the serial kernel's ``node_row``) and eliminates it at once, the
    filter's Thomas run from the chain's far end; a last walk from node 0 substitutes and moves the nodes. Against the
    serial kernel this drops the walk that re-reads every ``dl`` and re-loads each node's index, constraint and mask:
    the same systems, the filter eliminated in the other direction, so the positions agree to round-off
    (``tests/test_chains_partitioned.py``)."""
    env, i = wp.tid()
    r = family_start + i
    s0 = link_base + i
    nb = node_base + i
    m = chain_edge_count[r]
    pe = env % inv_mass.shape[0]
    ce = env % compliance.shape[0]
    masked = active.shape[1] > 0

    for it in range(newton_steps):
        # ---- 1. forward elimination of the link system (the serial kernel's, open chains) --------------------
        node_k1 = chain_node[nb + stride]
        x_k1 = q[env, node_k1]
        n_cur, len_cur = segment_dir(q[env, chain_node[nb]], x_k1)
        cons_k = chain_constraint[s0]
        act_k = int(1)
        if masked:
            act_k = active[env, cons_k]
        w_k = inv_mass[pe, chain_node[nb]]
        c_prev = float(0.0)
        d_prev = float(0.0)
        a_k = float(0.0)
        for k in range(m):
            w_k1 = inv_mass[pe, node_k1]
            n_next = wp.vec3(0.0)
            len_next = float(0.0)
            c_k = float(0.0)
            node_k2 = node_k1
            x_k2 = x_k1
            cons_next = cons_k
            act_next = act_k
            if k + 1 < m:
                node_k2 = chain_node[nb + (k + 2) * stride]
                x_k2 = q[env, node_k2]
                n_next, len_next = segment_dir(x_k1, x_k2)
                c_k = -w_k1 * wp.dot(n_cur, n_next)
                cons_next = chain_constraint[s0 + (k + 1) * stride]
                if masked:
                    act_next = active[env, cons_next]
                    if act_k == 0 or act_next == 0:
                        c_k = 0.0  # no coupling across a cut
            alpha = compliance[ce, cons_k] * inv_dt2
            b_k = w_k + w_k1 + alpha
            rhs = rest[cons_k] - len_cur  # -C_k
            lam_k = float(0.0)
            if use_lambda != 0:
                lam_k = lam[env, cons_k]
            if it > 0:
                lam_k = lam_k + scratch_l[env, s0 + k * stride]
            rhs = rhs - alpha * lam_k
            if b_k <= 0.0 or act_k == 0:
                b_k = 1.0  # an empty row (both nodes pinned, rigid) or a removed link: dl = 0
                rhs = 0.0
            inv = 1.0 / (b_k - a_k * c_prev)
            c_prev = c_k * inv
            d_prev = (rhs - a_k * d_prev) * inv
            scratch_c[env, s0 + k * stride] = c_prev
            scratch_d[env, s0 + k * stride] = d_prev
            a_k = c_k
            n_cur = n_next
            len_cur = len_next
            w_k = w_k1
            node_k1 = node_k2
            x_k1 = x_k2
            cons_k = cons_next
            act_k = act_next

        # ---- 2. back substitution of the links; node k + 1's filter row, eliminated from the far end ----------
        # carried from link k + 1 to link k: its dl, direction (zero where removed) and tension weight, node k + 1
        # (index and position before this Newton step) and its filter elimination (c, d)
        node_hi = chain_node[nb + m * stride]
        x_hi = q[env, node_hi]
        dl_hi = float(0.0)
        n_hi = wp.vec3(0.0)
        k_hi = float(0.0)
        ct_hi = float(0.0)
        dt_hi = wp.vec3(0.0)
        for kk in range(m):
            k = m - 1 - kk
            sk = s0 + k * stride
            dl_k = scratch_d[env, sk] - scratch_c[env, sk] * dl_hi
            cons = chain_constraint[sk]
            # the multiplier of this sweep's Newton steps so far (the serial kernel's bookkeeping)
            acc = dl_k
            if it > 0:
                acc = scratch_l[env, sk] + dl_k
            if it < newton_steps - 1:
                scratch_l[env, sk] = acc
            if use_lambda != 0 and it == newton_steps - 1:
                lam[env, cons] = lam[env, cons] + acc
            node_k = chain_node[nb + k * stride]
            x_k = q[env, node_k]
            n_k, len_k = segment_dir(x_k, x_hi)
            k_k = float(0.0)
            if len_k > 1.0e-12:
                k_k = wp.max(-dl_k, 0.0) / len_k
            if masked:
                if active[env, cons] == 0:
                    n_k = wp.vec3(0.0)  # a removed link: the nodes beside it are free ends
            lo, diag, up, rhs_j, par = node_row(n_k, dl_k, k_k, n_hi, dl_hi, k_hi, inv_mass[pe, node_hi], k + 1)
            inv = 1.0 / (diag - up * ct_hi)
            ct_hi = lo * inv
            dt_hi = (rhs_j - dt_hi * up) * inv
            slot = nb + (k + 1) * stride
            node_c[env, slot] = ct_hi
            node_d[env, slot] = dt_hi
            node_par[env, slot] = par + x_hi
            dl_hi = dl_k
            n_hi = n_k
            k_hi = k_k
            x_hi = x_k
            node_hi = node_k
        # node 0: no link before it (lo = 0), so its filter value is its eliminated right-hand side
        w0 = inv_mass[pe, node_hi]
        lo0, diag0, up0, rhs0, par0 = node_row(wp.vec3(0.0), 0.0, 0.0, n_hi, dl_hi, k_hi, w0, 0)
        y = (rhs0 - dt_hi * up0) / (diag0 - up0 * ct_hi)
        if w0 > 0.0:
            q[env, node_hi] = par0 + x_hi + y

        # ---- 3. the filter's substitution from node 1 on: x_j = par_j + y_j where w_j > 0 --------------------
        for j in range(1, m + 1):
            slot = nb + j * stride
            y = node_d[env, slot] - y * node_c[env, slot]
            node = chain_node[slot]
            if inv_mass[pe, node] > 0.0:
                q[env, node] = node_par[env, slot] + y


# capped at 96 registers as solve_cloth_chains (the cloth's chains are its launch's only user)
solve_open_cloth_chains = wp.kernel(solve_open_chains.func, cuda_max_registers=96, module="unique",
                                    enable_backward=False)
