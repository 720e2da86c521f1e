"""Direct XPBD solve of chains of distance constraints with parallelism *within* a chain: the partition (separator,
Schur-complement) form of ``kernels/chains.py``.

``chains.solve_chains`` walks each chain with one thread (Thomas algorithm), so a batch with one long rope per env
has only one thread per env and is latency-bound. This module solves the same systems, with the same linearisation,
pinned nodes, removed links, loops, Newton steps, multipliers and transverse filter (read that module's docstring
first), by splitting every chain into blocks of ``B`` links that threads eliminate side by side.

Partition. Link ``k`` is in block ``k // B``; the last link of every block but the chain's last (``b B + B - 1``)
is a *separator*, the others are the block's *interior* (``B - 1`` links, the last block ``1 .. B``). A tridiagonal
system ``a_k x_{k-1} + b_k x_k + c_k x_{k+1} = r_k`` restricted to a block's interior ``T_b`` couples to the outside
only through its first row (``a_lo`` times the left separator ``X_L``) and its last (``c_hi`` times the right one
``X_R``), so

    x = Y - X_L ZL - X_R ZR,   T_b Y = r,   T_b ZL = a_lo e_first,   T_b ZR = c_hi e_last,

one Thomas sweep with several right-hand sides. ``ZR`` costs nothing: forward elimination leaves ``c'_hi`` in the
last row of ``c_hi e_last`` and zeros above, so ``ZR_hi = c'_hi`` and ``ZR_k = -c'_k ZR_{k+1}``, and the final
back substitution is the ordinary one started from ``x_{hi+1} = X_R``. Putting the block solutions at their ends into
separator ``t``'s row (between blocks ``t`` and ``t + 1``, with ``^l`` the last interior row of block ``t`` and
``^f`` the first of block ``t + 1``) leaves a tridiagonal Schur system on the separators:

    -a ZL^l_t X_{t-1} + (b - a ZR^l_t - c ZL^f_{t+1}) X_t - c ZR^f_{t+1} X_{t+1} = r - a Y^l_t - c Y^f_{t+1}.

It is a Schur complement of a (weakly) diagonally dominant matrix, so it stays dominant and needs no pivoting; an
interior block is only singular where the whole system is (both ends pinned, rigid and straight). A closed loop keeps
the serial kernel's Sherman-Morrison form: every block also eliminates the loop vector ``u`` (the right-hand sides of
the link system are the pair ``(r, u)``, a ``vec2``), and the separator thread forms
``f = (v . y) / (1 + v . z)`` from the loop's first and last links and gives the blocks ``dl = y - f z``. The
transverse filter over the nodes (``vec3`` right-hand side, not symmetric: row ``j`` is scaled by ``w_j``) is
partitioned the same way, with node ``b B + B - 1`` as the separators, so a block's nodes ``b B .. b B + B - 1`` need
exactly the links ``b B - 1 .. b B + B - 1``: its own and its two separators.

Phases of one Newton step of one family (launches in this order, each reading what the previous ones wrote in the
per-env global scratch; no atomics, tiles or shared memory, so it runs the same on the CPU):

1. ``factor_link_blocks`` (env, block, chain): assemble the interior rows and the right separator's row, eliminate
   ``(r, u)`` and ``ZL`` forward, back-substitute for the block's end values ``Y, ZL, ZR`` at both ends.
2. ``solve_link_separators`` (env, chain): Thomas on the separators' Schur system (both right-hand sides), the
   loop's Sherman-Morrison factor, ``dl`` of the separators (and of the loop's last link, which node 0 needs).
3. ``solve_link_blocks`` (env, block, chain): back substitution for the interior ``dl``, the multipliers' Newton
   bookkeeping, then the filter rows of the block's nodes: eliminated forward like phase 1.
4. ``solve_node_separators`` (env, chain): Thomas on the nodes' Schur system.
5. ``solve_node_blocks`` (env, block, chain): filter back substitution and ``q = par + y`` where ``w > 0``.

Layout: the per-link and per-node scratch use the ``ChainSet`` slots (link ``k`` of a family's chain ``i`` at
``link_base + k * stride + i``); per-block values sit at ``block_base + b * stride + i`` (``block_layout``); a
separator's link / node slot holds its Schur elimination. The block launches are ``(env, block, chain)`` with the
chain fastest, so neighbouring threads work on neighbouring chains of a family and touch neighbouring slots; threads
past their chain's last block return at once. Round-off differs from the serial kernel (other elimination order),
nothing else.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import warp as wp

from lapwarp.kernels.chains import link_row_terms, node_row, segment_dir

wp.set_module_options({"enable_backward": False})


@wp.struct
class Family:
    """One family's chains (``ChainSet`` arrays and slot bases) and everything fixed during its solve."""

    first: int  # first chain of the family
    stride: int  # chains in the family
    link_base: int
    node_base: int
    block_base: int
    block_links: int  # B
    edge_count: wp.array(dtype=wp.int32)
    closed: wp.array(dtype=wp.int32)
    node: wp.array(dtype=wp.int32)
    constraint: wp.array(dtype=wp.int32)
    rest: wp.array(dtype=float)
    compliance: wp.array2d(dtype=float)
    inv_mass: wp.array2d(dtype=float)
    active: wp.array2d(dtype=wp.int32)  # cutting masks; (1, 0): none
    lam: wp.array2d(dtype=float)
    use_lambda: int
    newton_steps: int
    inv_dt2: float


@wp.struct
class Scratch:
    """Per-env scratch of a chain set; ``(num_envs, slots)`` arrays (link, node, block or chain slots)."""

    newton_dl: wp.array2d(dtype=float)  # link: dl of this sweep's earlier Newton steps (serial kernel's scratch_l)
    link_c: wp.array2d(dtype=float)  # link: modified super-diagonal c' (separators: of the Schur system)
    link_d: wp.array2d(dtype=wp.vec2)  # link: forward-eliminated right-hand sides (r, u)
    link_zl: wp.array2d(dtype=float)  # link: forward-eliminated left coupling column
    dl: wp.array2d(dtype=float)  # link: the solution
    node_c: wp.array2d(dtype=float)  # node: as link_c for the filter
    node_d: wp.array2d(dtype=wp.vec3)  # node: forward-eliminated right-hand side; separators: then the solution
    node_zl: wp.array2d(dtype=float)  # node: forward-eliminated left coupling column
    node_par: wp.array2d(dtype=wp.vec3)  # node: base point, position plus the correction along the tangent
    link_first_y: wp.array2d(dtype=wp.vec2)  # block: Y at its first interior link
    link_first_z: wp.array2d(dtype=wp.vec2)  # block: (ZL, ZR) there
    link_last_y: wp.array2d(dtype=wp.vec2)  # block: Y at its last interior link
    link_last_z: wp.array2d(dtype=wp.vec2)
    link_sep_abc: wp.array2d(dtype=wp.vec3)  # block: (a, b, c) of its right separator's row
    link_sep_rhs: wp.array2d(dtype=wp.vec2)  # block: (r, u) of that row
    node_first_y: wp.array2d(dtype=wp.vec3)  # block: the same for the filter
    node_first_z: wp.array2d(dtype=wp.vec2)
    node_last_y: wp.array2d(dtype=wp.vec3)
    node_last_z: wp.array2d(dtype=wp.vec2)
    node_sep_abc: wp.array2d(dtype=wp.vec3)
    node_sep_rhs: wp.array2d(dtype=wp.vec3)
    loop: wp.array2d(dtype=wp.vec2)  # chain: Sherman-Morrison factor f and dl of the last link


# ---------------------------------------------------------------------------------------------------- addressing
@wp.func
def link_slot(fam: Family, i: int, k: int) -> int:
    return fam.link_base + k * fam.stride + i


@wp.func
def node_slot(fam: Family, i: int, j: int) -> int:
    return fam.node_base + j * fam.stride + i


@wp.func
def block_slot(fam: Family, i: int, b: int) -> int:
    return fam.block_base + b * fam.stride + i


@wp.func
def separator_slot(fam: Family, base: int, t: int) -> int:
    """Slot of separator ``t`` (link or node ``(t + 1) B - 1``) of the chain whose link or node 0 is at ``base``."""
    return base + ((t + 1) * fam.block_links - 1) * fam.stride


@wp.func
def node_x(fam: Family, q: wp.array2d(dtype=wp.vec3), env: int, i: int, j: int) -> wp.vec3:
    return q[env, fam.node[node_slot(fam, i, j)]]


@wp.func
def node_w(fam: Family, env: int, i: int, j: int) -> float:
    return fam.inv_mass[env % fam.inv_mass.shape[0], fam.node[node_slot(fam, i, j)]]


@wp.func
def link_active(fam: Family, env: int, i: int, k: int) -> int:
    act = int(1)
    if fam.active.shape[1] > 0:
        act = fam.active[env, fam.constraint[link_slot(fam, i, k)]]
    return act


@wp.func
def link_dir(fam: Family, q: wp.array2d(dtype=wp.vec3), env: int, i: int, k: int, nodes: int):
    """Unit vector and length of link ``k`` (node ``k`` to node ``k + 1``, node 0 after a loop's last)."""
    n, length = segment_dir(node_x(fam, q, env, i, k), node_x(fam, q, env, i, (k + 1) % nodes))
    return n, length


@wp.func
def chain_info(fam: Family, env: int, i: int):
    """Links ``m``, nodes, and whether the chain is solved as a loop: closed, at least 3 links and neither corner link
    removed (a loop cut at its closing corner is an open chain; cut elsewhere, blocks split inside the solve)."""
    r = fam.first + i
    m = fam.edge_count[r]
    nodes = m + 1
    loop = int(0)
    if fam.closed[r] != 0:
        nodes = m
        if m >= 3:
            loop = 1
            if link_active(fam, env, i, 0) == 0 or link_active(fam, env, i, m - 1) == 0:
                loop = 0
    return m, nodes, loop


@wp.func
def block_range(m: int, B: int, b: int):
    """Interior links ``lo .. hi`` of block ``b`` and whether it is the chain's last block (no right separator,
    which would be link ``hi + 1``)."""
    lo = b * B
    hi = lo + B - 2
    last = int(0)
    if lo + B >= m:
        hi = m - 1
        last = 1
    return lo, hi, last


@wp.func
def block_nodes_end(hi: int, last: int, nodes: int) -> int:
    """Last interior node of a block (its interior nodes start at its first link's; ``hi + 1`` is its separator)."""
    end = hi
    if last != 0:
        end = nodes - 1
    return end


# ---------------------------------------------------------------------------------------------------- link rows
@wp.func
def link_coupling(fam: Family, env: int, i: int, k: int, m: int, n_k: wp.vec3, n_k1: wp.vec3, w_shared: float):
    """``A_{k,k+1} = -w n_k . n_{k+1}`` through the shared node; 0 past the chain's end and across a removed link."""
    c = float(0.0)
    if k + 1 < m:
        c = -w_shared * wp.dot(n_k, n_k1)
        if link_active(fam, env, i, k) == 0 or link_active(fam, env, i, k + 1) == 0:
            c = 0.0
    return c


@wp.func
def loop_corner(fam: Family, q: wp.array2d(dtype=wp.vec3), env: int, i: int, m: int, nodes: int, loop: int):
    """Sherman-Morrison data of a loop, ``A = T + u v^T``: whether it is used (not when the corner coupling ``s``
    vanishes, node 0 pinned: then a plain tridiagonal system), ``g = -A_00``, ``s = A_{m-1,0}`` and the direction of
    the closing link (which node 0's correction needs)."""
    cyclic = int(0)
    g = float(0.0)
    s = float(0.0)
    n_last = wp.vec3(0.0)
    if loop != 0:
        n_0, len_0 = link_dir(fam, q, env, i, 0, nodes)
        n_last, len_last = link_dir(fam, q, env, i, m - 1, nodes)
        w_0 = node_w(fam, env, i, 0)
        s = -w_0 * wp.dot(n_last, n_0)
        if s != 0.0:
            cyclic = 1
            alpha = fam.compliance[env % fam.compliance.shape[0], fam.constraint[link_slot(fam, i, 0)]] * fam.inv_dt2
            g = -(w_0 + node_w(fam, env, i, 1) + alpha)
    return cyclic, g, s, n_last


@wp.func
def link_row(fam: Family, sc: Scratch, env: int, i: int, k: int, m: int, len_k: float, w_k: float, w_k1: float,
             cyclic: int, g: float, s: float, step: int):
    """Diagonal and right-hand sides ``(-C - alpha lambda, u)`` of link ``k``'s row; a removed link or an empty row
    (both nodes pinned, rigid) becomes the identity with a zero right-hand side."""
    slot = link_slot(fam, i, k)
    c = fam.constraint[slot]
    alpha = fam.compliance[env % fam.compliance.shape[0], c] * fam.inv_dt2
    # lambda of this sweep so far: earlier sweeps (iterations > 1) plus the earlier Newton steps
    lam = float(0.0)
    if fam.use_lambda != 0:
        lam = fam.lam[env, c]
    if step > 0:
        lam = lam + sc.newton_dl[env, slot]
    b, rhs, u = link_row_terms(w_k, w_k1, alpha, fam.rest[c] - len_k, lam, k, m, cyclic, g, s,
                               link_active(fam, env, i, k))
    return b, wp.vec2(rhs, u)


@wp.func
def link_solution(sc: Scratch, env: int, slot: int, f: float, x_left: float, x_next: float) -> float:
    """Back substitution of an interior link: ``dl = y - f z - X_L ZL - c' dl_{k+1}`` (``dl_{hi+1} = X_R``)."""
    d = sc.link_d[env, slot]
    return d[0] - f * d[1] - x_left * sc.link_zl[env, slot] - sc.link_c[env, slot] * x_next


@wp.func
def record_multiplier(fam: Family, sc: Scratch, env: int, i: int, k: int, step: int):
    """The multiplier of this sweep's Newton steps so far: kept for the next step, added to ``lam`` after the last."""
    slot = link_slot(fam, i, k)
    acc = sc.dl[env, slot]
    if step > 0:
        acc = sc.newton_dl[env, slot] + acc
    if step < fam.newton_steps - 1:
        sc.newton_dl[env, slot] = acc
    if fam.use_lambda != 0 and step == fam.newton_steps - 1:
        c = fam.constraint[slot]
        fam.lam[env, c] = fam.lam[env, c] + acc


# ---------------------------------------------------------------------------------------------------- filter rows
@wp.func
def filter_link(fam: Family, sc: Scratch, q: wp.array2d(dtype=wp.vec3), env: int, i: int, k: int, m: int,
                nodes: int):
    """Link ``k``'s part of the filter rows of its nodes: direction (zero if removed: the nodes beside a cut are
    free ends), ``dl`` and the w-free tension weight ``Lambda / l`` (none past the chain's end or across a loop's
    closing link: open-chain filter)."""
    n = wp.vec3(0.0)
    dl = float(0.0)
    weight = float(0.0)
    if k < m:
        n, length = link_dir(fam, q, env, i, k, nodes)
        if link_active(fam, env, i, k) == 0:
            n = wp.vec3(0.0)
        dl = sc.dl[env, link_slot(fam, i, k)]
        if k + 1 < nodes and length > 1.0e-12:
            weight = wp.max(-dl, 0.0) / length
    return n, dl, weight


# ---------------------------------------------------------------------------------------------------- shared solves
@wp.func
def eliminate_row(sub: float, diag: float, sup: float, rhs: Any, zl_rhs: float, c_prev: float, d_prev: Any,
                  zl_prev: float):
    """One forward-elimination (Thomas) step of a block row with its right-hand side and the ZL column: the
    modified super-diagonal, right-hand side and ZL entry of this row."""
    inv = 1.0 / (diag - sub * c_prev)
    return sup * inv, (rhs - sub * d_prev) * inv, (zl_rhs - sub * zl_prev) * inv


@wp.func
def block_ends(c: wp.array2d(dtype=float), d: wp.array2d(dtype=Any), zl: wp.array2d(dtype=float), env: int,
               first: int, last: int, stride: int, first_y: wp.array2d(dtype=Any), first_z: wp.array2d(dtype=wp.vec2),
               last_y: wp.array2d(dtype=Any), last_z: wp.array2d(dtype=wp.vec2), bs: int):
    """Back substitution of a block's interior (slots ``first``, ``first + stride`` .. ``last``) for ``Y``, ``ZL`` and
    ``ZR`` at its two ends. ``ZR``: forward elimination left ``c'`` in the last row, so ``ZR_last = c'_last``."""
    y = d[env, last]
    z_l = zl[env, last]
    z_r = c[env, last]
    last_y[env, bs] = y
    last_z[env, bs] = wp.vec2(z_l, z_r)
    slot = last
    while slot != first:
        slot = slot - stride
        cs = c[env, slot]
        y = d[env, slot] - cs * y
        z_l = zl[env, slot] - cs * z_l
        z_r = -cs * z_r
    first_y[env, bs] = y
    first_z[env, bs] = wp.vec2(z_l, z_r)


@wp.func
def solve_separators(fam: Family, env: int, i: int, separators: int, base: int, c: wp.array2d(dtype=float),
                     d: wp.array2d(dtype=Any), first_y: wp.array2d(dtype=Any), first_z: wp.array2d(dtype=wp.vec2),
                     last_y: wp.array2d(dtype=Any), last_z: wp.array2d(dtype=wp.vec2),
                     sep_abc: wp.array2d(dtype=wp.vec3), sep_rhs: wp.array2d(dtype=Any)):
    """Thomas algorithm on the separators' Schur system (rows from the block ends, see the module docstring); ``d``
    at the separators' slots holds the solution afterwards."""
    c_prev = float(0.0)
    for t in range(separators):
        bs = block_slot(fam, i, t)
        bs1 = block_slot(fam, i, t + 1)
        abc = sep_abc[env, bs]
        zl = last_z[env, bs]
        zr = first_z[env, bs1]
        sub = -abc[0] * zl[0]
        diag = abc[1] - abc[0] * zl[1] - abc[2] * zr[0]
        rhs = sep_rhs[env, bs] - abc[0] * last_y[env, bs] - abc[2] * first_y[env, bs1]
        slot = separator_slot(fam, base, t)
        if t > 0:
            rhs = rhs - sub * d[env, separator_slot(fam, base, t - 1)]
        inv = 1.0 / (diag - sub * c_prev)
        c_prev = -abc[2] * zr[1] * inv
        c[env, slot] = c_prev
        d[env, slot] = rhs * inv
    for tt in range(separators - 1):
        t = separators - 2 - tt
        slot = separator_slot(fam, base, t)
        d[env, slot] = d[env, slot] - c[env, slot] * d[env, separator_slot(fam, base, t + 1)]


# ---------------------------------------------------------------------------------------------------- phase 1
@wp.kernel
def factor_link_blocks(fam: Family, sc: Scratch, step: int, q: wp.array2d(dtype=wp.vec3)):
    """Phase 1: eliminate each block's interior links (right-hand sides ``(r, u)`` and the left coupling), keep its
    end values and its right separator's row."""
    env, b, i = wp.tid()
    m, nodes, loop = chain_info(fam, env, i)
    if b * fam.block_links >= m:
        return
    lo, hi, last = block_range(m, fam.block_links, b)
    cyclic = int(0)
    g = float(0.0)
    s = float(0.0)
    if lo == 0 or last != 0:  # rows 0 and m - 1 carry a loop's corner
        cyclic, g, s, n_last = loop_corner(fam, q, env, i, m, nodes, loop)
    n_k, len_k = link_dir(fam, q, env, i, lo, nodes)
    w_k = node_w(fam, env, i, lo)
    zl_rhs = float(0.0)  # A_{lo,lo-1} in the block's first row, 0 below
    if lo > 0:
        n_p, len_p = link_dir(fam, q, env, i, lo - 1, nodes)
        zl_rhs = link_coupling(fam, env, i, lo - 1, m, n_p, n_k, w_k)
    a = float(0.0)  # sub-diagonal inside the block (the first row's is the ZL column)
    c_prev = float(0.0)
    d_prev = wp.vec2(0.0)
    zl_prev = float(0.0)
    for k in range(lo, hi + 1):
        w_k1 = node_w(fam, env, i, (k + 1) % nodes)
        n_next = wp.vec3(0.0)
        len_next = float(0.0)
        if k + 1 < m:
            n_next, len_next = link_dir(fam, q, env, i, k + 1, nodes)
        c_k = link_coupling(fam, env, i, k, m, n_k, n_next, w_k1)
        b_k, rhs = link_row(fam, sc, env, i, k, m, len_k, w_k, w_k1, cyclic, g, s, step)
        c_prev, d_prev, zl_prev = eliminate_row(a, b_k, c_k, rhs, zl_rhs, c_prev, d_prev, zl_prev)
        slot = link_slot(fam, i, k)
        sc.link_c[env, slot] = c_prev
        sc.link_d[env, slot] = d_prev
        sc.link_zl[env, slot] = zl_prev
        a = c_k
        zl_rhs = 0.0
        n_k = n_next
        len_k = len_next
        w_k = w_k1
    bs = block_slot(fam, i, b)
    if last == 0:
        # the right separator's row (never a loop's corner row); n_k, len_k, w_k are its own by now
        sep = hi + 1
        w_k1 = node_w(fam, env, i, sep + 1)
        n_next, len_next = link_dir(fam, q, env, i, sep + 1, nodes)
        c_k = link_coupling(fam, env, i, sep, m, n_k, n_next, w_k1)
        b_k, rhs = link_row(fam, sc, env, i, sep, m, len_k, w_k, w_k1, cyclic, g, s, step)
        sc.link_sep_abc[env, bs] = wp.vec3(a, b_k, c_k)
        sc.link_sep_rhs[env, bs] = rhs
    block_ends(sc.link_c, sc.link_d, sc.link_zl, env, link_slot(fam, i, lo), link_slot(fam, i, hi), fam.stride,
               sc.link_first_y, sc.link_first_z, sc.link_last_y, sc.link_last_z, bs)


# ---------------------------------------------------------------------------------------------------- phase 2
@wp.kernel
def solve_link_separators(fam: Family, sc: Scratch, q: wp.array2d(dtype=wp.vec3)):
    """Phase 2: the links' Schur system, a loop's Sherman-Morrison factor, ``dl`` of the separators."""
    env, i = wp.tid()
    m, nodes, loop = chain_info(fam, env, i)
    blocks = (m + fam.block_links - 1) // fam.block_links
    base = fam.link_base + i
    solve_separators(fam, env, i, blocks - 1, base, sc.link_c, sc.link_d, sc.link_first_y, sc.link_first_z,
                     sc.link_last_y, sc.link_last_z, sc.link_sep_abc, sc.link_sep_rhs)
    cyclic, g, s, n_last = loop_corner(fam, q, env, i, m, nodes, loop)
    f = float(0.0)
    if cyclic != 0:
        # y and z (the pair) at link 0 (block 0's first) and link m - 1 (the last block's last); v = (1, 0.., s / g)
        bs0 = block_slot(fam, i, 0)
        bsl = block_slot(fam, i, blocks - 1)
        y0 = sc.link_first_y[env, bs0]
        yl = sc.link_last_y[env, bsl]
        if blocks > 1:
            y0 = y0 - sc.link_first_z[env, bs0][1] * sc.link_d[env, separator_slot(fam, base, 0)]
            yl = yl - sc.link_last_z[env, bsl][0] * sc.link_d[env, separator_slot(fam, base, blocks - 2)]
        vy = y0[0] + (s / g) * yl[0]
        vz = y0[1] + (s / g) * yl[1]
        f = vy / (1.0 + vz)
    x_sep = float(0.0)  # dl of the last separator: X_L of the last block
    for t in range(blocks - 1):
        slot = separator_slot(fam, base, t)
        x = sc.link_d[env, slot]
        x_sep = x[0] - f * x[1]
        sc.dl[env, slot] = x_sep
    dl_last = float(0.0)
    if fam.closed[fam.first + i] != 0 and m >= 3:
        # node 0 of a loop (also of one cut at link 0) needs dl of link m - 1, which phase 3 writes concurrently:
        # the same arithmetic here (f = 0 unless solved cyclically)
        dl_last = link_solution(sc, env, link_slot(fam, i, m - 1), f, x_sep, 0.0)
    sc.loop[env, fam.first + i] = wp.vec2(f, dl_last)


# ---------------------------------------------------------------------------------------------------- phase 3
@wp.func
def factor_node_block(fam: Family, sc: Scratch, q: wp.array2d(dtype=wp.vec3), env: int, i: int, b: int, m: int,
                      nodes: int, lo: int, hi: int, last: int):
    """Filter rows of a block's nodes: eliminate the interior (right-hand side and left coupling), keep the end
    values and the right separator node's row. Each node's base point goes to ``node_par``."""
    n_p = wp.vec3(0.0)
    dl_p = float(0.0)
    k_p = float(0.0)
    if lo > 0:
        n_p, dl_p, k_p = filter_link(fam, sc, q, env, i, lo - 1, m, nodes)
    elif fam.closed[fam.first + i] != 0 and m >= 3:
        # node 0 of a loop also moves with the closing link (tension weight 0: open filter), also once the loop is
        # cut at link 0; a removed closing link leaves node 0 a free end
        n_p, len_p = link_dir(fam, q, env, i, m - 1, nodes)
        if link_active(fam, env, i, m - 1) == 0:
            n_p = wp.vec3(0.0)
        dl_p = sc.loop[env, fam.first + i][1]
    end = block_nodes_end(hi, last, nodes)
    zl_rhs = float(0.0)
    c_prev = float(0.0)
    d_prev = wp.vec3(0.0)
    zl_prev = float(0.0)
    for j in range(lo, end + 1):
        n_j, dl_j, k_j = filter_link(fam, sc, q, env, i, j, m, nodes)
        lo_j, diag, up, rhs, par = node_row(n_p, dl_p, k_p, n_j, dl_j, k_j, node_w(fam, env, i, j), j)
        a = lo_j
        if j == lo:
            a = 0.0  # the block's first row couples to the left separator through the ZL column
            zl_rhs = lo_j
        c_prev, d_prev, zl_prev = eliminate_row(a, diag, up, rhs, zl_rhs, c_prev, d_prev, zl_prev)
        slot = node_slot(fam, i, j)
        sc.node_c[env, slot] = c_prev
        sc.node_d[env, slot] = d_prev
        sc.node_zl[env, slot] = zl_prev
        sc.node_par[env, slot] = par + node_x(fam, q, env, i, j)
        zl_rhs = 0.0
        n_p = n_j
        dl_p = dl_j
        k_p = k_j
    bs = block_slot(fam, i, b)
    if last == 0:
        sep = hi + 1
        n_j, dl_j, k_j = filter_link(fam, sc, q, env, i, sep, m, nodes)
        lo_j, diag, up, rhs, par = node_row(n_p, dl_p, k_p, n_j, dl_j, k_j, node_w(fam, env, i, sep), sep)
        sc.node_sep_abc[env, bs] = wp.vec3(lo_j, diag, up)
        sc.node_sep_rhs[env, bs] = rhs
        sc.node_par[env, node_slot(fam, i, sep)] = par + node_x(fam, q, env, i, sep)
    block_ends(sc.node_c, sc.node_d, sc.node_zl, env, node_slot(fam, i, lo), node_slot(fam, i, end), fam.stride,
               sc.node_first_y, sc.node_first_z, sc.node_last_y, sc.node_last_z, bs)


@wp.kernel
def solve_link_blocks(fam: Family, sc: Scratch, step: int, q: wp.array2d(dtype=wp.vec3)):
    """Phase 3: ``dl`` of each block's interior links, the multipliers' bookkeeping of its links and right separator,
    then its nodes' filter rows (which need exactly these links and the left separator)."""
    env, b, i = wp.tid()
    m, nodes, loop = chain_info(fam, env, i)
    if b * fam.block_links >= m:
        return
    lo, hi, last = block_range(m, fam.block_links, b)
    f = sc.loop[env, fam.first + i][0]
    x_left = float(0.0)
    if lo > 0:
        x_left = sc.dl[env, link_slot(fam, i, lo - 1)]
    x = float(0.0)
    own = hi  # links whose multiplier this thread records: the interior and the right separator
    if last == 0:
        x = sc.dl[env, link_slot(fam, i, hi + 1)]
        own = hi + 1
    for kk in range(hi - lo + 1):
        slot = link_slot(fam, i, hi - kk)
        x = link_solution(sc, env, slot, f, x_left, x)
        sc.dl[env, slot] = x
    for k in range(lo, own + 1):
        record_multiplier(fam, sc, env, i, k, step)
    factor_node_block(fam, sc, q, env, i, b, m, nodes, lo, hi, last)


# ---------------------------------------------------------------------------------------------------- phases 4, 5
@wp.kernel
def solve_node_separators(fam: Family, sc: Scratch):
    """Phase 4: the filter's Schur system on the separator nodes."""
    env, i = wp.tid()
    m = fam.edge_count[fam.first + i]
    blocks = (m + fam.block_links - 1) // fam.block_links
    solve_separators(fam, env, i, blocks - 1, fam.node_base + i, sc.node_c, sc.node_d, sc.node_first_y,
                     sc.node_first_z, sc.node_last_y, sc.node_last_z, sc.node_sep_abc, sc.node_sep_rhs)


@wp.func
def write_node(fam: Family, sc: Scratch, q: wp.array2d(dtype=wp.vec3), env: int, i: int, j: int, y: wp.vec3):
    """``q = par + y`` for a node that can move."""
    if node_w(fam, env, i, j) > 0.0:
        q[env, fam.node[node_slot(fam, i, j)]] = sc.node_par[env, node_slot(fam, i, j)] + y


@wp.kernel
def solve_node_blocks(fam: Family, sc: Scratch, q: wp.array2d(dtype=wp.vec3)):
    """Phase 5: filter back substitution of each block's nodes; writes them and the block's right separator."""
    env, b, i = wp.tid()
    m, nodes, loop = chain_info(fam, env, i)
    if b * fam.block_links >= m:
        return
    lo, hi, last = block_range(m, fam.block_links, b)
    y_left = wp.vec3(0.0)
    if lo > 0:
        y_left = sc.node_d[env, node_slot(fam, i, lo - 1)]
    y = wp.vec3(0.0)
    if last == 0:
        y = sc.node_d[env, node_slot(fam, i, hi + 1)]
        write_node(fam, sc, q, env, i, hi + 1, y)
    end = block_nodes_end(hi, last, nodes)
    for jj in range(end - lo + 1):
        j = end - jj
        slot = node_slot(fam, i, j)
        y = sc.node_d[env, slot] - y_left * sc.node_zl[env, slot] - y * sc.node_c[env, slot]
        write_node(fam, sc, q, env, i, j, y)


# ---------------------------------------------------------------------------------------------------- host side
def block_layout(families: list, lengths: np.ndarray, block_links: int) -> tuple[list[tuple[int, int]], int]:
    """Per family of a ``ChainSet`` its first block slot and blocks per chain (of its longest chain), and the block
    slots in all (the per-block scratch is ``(num_envs, slots)``)."""
    layout, total = [], 0
    for first, count, _, _ in families:
        blocks = -(-int(np.max(lengths[first:first + count])) // block_links)
        layout.append((total, blocks))
        total += blocks * count
    return layout, total


def record_family(launch, num_envs: int, fam: Family, blocks: int, scratch: Scratch, q: wp.array) -> None:
    """Record one family's solve: per Newton step the five phases, ``launch(kernel, dim, inputs, outputs)``."""
    chains = fam.stride
    for step in range(fam.newton_steps):
        launch(factor_link_blocks, (num_envs, blocks, chains), [fam, scratch, step, q])
        launch(solve_link_separators, (num_envs, chains), [fam, scratch, q])
        launch(solve_link_blocks, (num_envs, blocks, chains), [fam, scratch, step, q])
        launch(solve_node_separators, (num_envs, chains), [fam, scratch])
        launch(solve_node_blocks, (num_envs, blocks, chains), [fam, scratch], [q])


def family(chains, index: int, block_base: int, block_links: int, rest: wp.array, compliance: wp.array,
           inv_mass: wp.array, active: wp.array, lam: wp.array, use_lambda: int, newton_steps: int,
           inv_dt2: float) -> Family:
    """The ``Family`` argument of family ``index`` of a ``ChainSet`` (arrays as for ``chains.solve_chains``)."""
    fam = Family()
    fam.first, fam.stride, fam.link_base, fam.node_base = chains.families[index]
    fam.block_base, fam.block_links = block_base, block_links
    fam.edge_count, fam.closed = chains.edge_count, chains.closed
    fam.node, fam.constraint = chains.node, chains.constraint
    fam.rest, fam.compliance, fam.inv_mass, fam.active, fam.lam = rest, compliance, inv_mass, active, lam
    fam.use_lambda, fam.newton_steps, fam.inv_dt2 = use_lambda, newton_steps, inv_dt2
    return fam
