"""Direct XPBD solve of chains of distance constraints, one thread block per (env, pack of chains): the systems of
``kernels/chains.py`` (read its docstring first) solved by parallel cyclic reduction (PCR) in shared memory.

``chains.solve_chains`` walks a chain with one thread (Thomas), a chain of ``m`` links taking ~4 m dependent global
loads and stores per Newton step; ``chains_partitioned`` splits the walk over blocks of links but passes its
intermediate values through global scratch over five launches. Here the lanes of one block take the rows of a
*pack* (``chains.ChainPacks``: a family's open chains end to end, an open chain of ``m`` links ``m + 1`` rows, a loop
alone) side by side and keep every intermediate value in shared memory, in one launch per family and sweep, all
Newton steps included. Row ``t`` holds node ``t`` and the link from it to node ``t + 1``; a chain's last node has no
link, an identity row, and the couplings at a chain's ends are zero, so the chains of a pack form one tridiagonal
system that PCR solves at once (short chains, a cloth's diagonals or a few short ropes, then fill the lanes that a
block per chain would leave idle):

0. the lanes load the pack's node positions and inverse masses into shared memory (each row reads up to four);
1. each lane assembles the rows of its links from them (the same linearisation, pinned nodes, removed links,
   compliance and multipliers as the serial kernel);
2. PCR: ``ceil(log2 n)`` rounds over the pack's ``n`` rows, in which every row eliminates its neighbours at distance
   ``s`` (``s = 1, 2, 4, ..``), from one pair of shared buffers into the other, a block barrier between rounds; after
   the last round every row holds one unknown. A closed loop keeps the serial kernel's Sherman-Morrison form (the open
   tridiagonal part ``T`` with the two right-hand sides ``(r, u)``, then ``dl = y - f z``), so that both kernels solve
   the same system;
3. the multipliers' Newton bookkeeping in a shared buffer, then the transverse filter's rows over the nodes
   (``chains.node_row``, the same open-chain filter, ``vec3`` right-hand side) and a second PCR;
4. ``q = par + y`` where ``w > 0``, written to global memory and to the shared copy (its scatter is the barrier
   before the next Newton step).

PCR needs no pivoting where Thomas needs none: its rounds keep a diagonally dominant system dominant. It does
``O(m log m)`` work instead of ``O(m)``, in ``log m`` steps in series instead of ``m``. Round-off differs from the
serial kernel (another elimination order), nothing else (``tests/test_chains_block.py``).

On the CPU a block has one lane, which takes every element of each round in order; the double buffers keep a
round's reads of the previous round's values intact.
"""

# no ``from __future__ import annotations``: the tile arguments' annotations name the kernel's tile length, a local of
# the factory, which Warp can evaluate only as objects
import warp as wp

from lapwarp.kernels.chains import check_newton_tolerance, link_row_terms, node_row, segment_dir

wp.set_module_options({"enable_backward": False})

# the kernels by (tile length: the most rows of a pack, a compile-time constant of the shared tiles; loops; masked;
# Newton tolerance)
_KERNELS: dict[tuple[int, bool, bool, float], wp.Kernel] = {}
# a row of either system, one shared element (so a PCR round writes it with one scatter and one block barrier): sub-,
# main and super-diagonal, then the right-hand sides: a link row's (-C - alpha lambda, loop vector u, 0), a filter
# row's vec3
vec6 = wp.types.vector(length=6, dtype=float)


@wp.func
def pack_loop(closed: int, rows: wp.array(dtype=wp.vec3i), r0: int, n: int, masked: bool,
              active: wp.array2d(dtype=wp.int32), env: int):
    """Whether a pack (a loop has one of its own) is a loop still closed at its corner (``closed3``: a cyclic system)
    and whether its node 0 ends the closing link (``wraps``: also once the loop is cut at a corner, an open chain)."""
    closed3 = int(0)
    if closed != 0 and n >= 3:
        closed3 = 1
    wraps = closed3
    if masked and closed3 != 0:
        if active[env, rows[r0][1]] == 0 or active[env, rows[r0 + n - 1][1]] == 0:
            closed3 = 0
    return closed3, wraps


_PACK_SETUPS: dict[tuple[bool, bool], wp.Function] = {}


def pack_setup_func(loops: bool, masked: bool) -> wp.Function:
    """A pack's cutting-mask flag and ``pack_loop``'s ``(closed3, wraps)``, with the loop and mask branches compiled
    only where ``loops`` / ``masked`` say the family may need them (else constants: a kernel for open, uncut chains
    holds no registers for them); cached per flags, shared by the block and hybrid kernels."""
    key = (bool(loops), bool(masked))
    cached = _PACK_SETUPS.get(key)
    if cached is not None:
        return cached
    LOOPS, MASKED = key

    @wp.func
    def pack_setup(pack_closed: wp.array(dtype=wp.int32), p: int, rows: wp.array(dtype=wp.vec3i), r0: int, n: int,
                   active: wp.array2d(dtype=wp.int32), env: int):
        masked = False
        if wp.static(MASKED):
            masked = active.shape[1] > 0
        closed3 = int(0)
        wraps = int(0)
        if wp.static(LOOPS):
            closed3, wraps = pack_loop(pack_closed[p], rows, r0, n, masked, active, env)
        return masked, closed3, wraps

    _PACK_SETUPS[key] = pack_setup
    return pack_setup


_PCR_ROUNDS: dict[int, wp.Function] = {}


def pcr_round_func(N: int) -> wp.Function:
    """One PCR round over shared tiles of ``N`` rows (cached per length; also kernels/chains_hybrid.py's reduced
    system)."""
    cached = _PCR_ROUNDS.get(N)
    if cached is not None:
        return cached

    @wp.func
    def pcr_round(src: wp.tile(dtype=vec6, shape=(N,), storage="shared"),
                  dst: wp.tile(dtype=vec6, shape=(N,), storage="shared"), s: int, n: int, lane: int, lanes: int):
        """One PCR round at distance ``s`` over ``n`` rows ``(a, b, c, d_0, d_1, d_2)`` (sub-, main, super-diagonal and
        up to three right-hand sides), ``src`` -> ``dst``."""
        for base in range(0, n, lanes):
            k = wp.min(base + lane, n - 1)
            row = wp.tile_extract(src, k)
            a = float(0.0)
            c = float(0.0)
            b = row[1]
            d = wp.vec3(row[3], row[4], row[5])
            if k - s >= 0:  # a coupling reaching before the first row is zero already
                lo = wp.tile_extract(src, k - s)
                alpha = -row[0] / lo[1]
                a = alpha * lo[0]
                b = b + alpha * lo[2]
                d = d + wp.vec3(lo[3], lo[4], lo[5]) * alpha
            if k + s < n:
                hi = wp.tile_extract(src, k + s)
                gamma = -row[2] / hi[1]
                c = gamma * hi[2]
                b = b + gamma * hi[0]
                d = d + wp.vec3(hi[3], hi[4], hi[5]) * gamma
            wp.tile_scatter_masked(dst, k, vec6(a, b, c, d[0], d[1], d[2]), base + lane < n)

    _PCR_ROUNDS[N] = pcr_round
    return pcr_round


def block_chain_kernel(max_rows: int, loops: bool = True, masked: bool = True,
                       newton_tolerance: float = 0.0) -> wp.Kernel:
    """The block solve for packs (``chains.ChainPacks``) of at most ``max_rows`` rows (cached per length and flags):
    launch ``(num_envs, packs, lanes)`` with ``block_dim=lanes`` (``launching.block_lanes``), one family at a time.
    ``loops`` / ``masked`` (compile-time): whether the family may hold a closed loop / the scene has cutting masks
    (without them the variant compiles neither branch). ``newton_tolerance`` (m, compile-time; 0 = off): a pack stops
    its Newton steps once one has corrected none of its links by that much (``chains_registers``' rule; the largest
    of the pack's rows, a tile reduction, decides for the whole block)."""
    N = max(int(max_rows), 1)
    LOOPS, MASKED = bool(loops), bool(masked)
    tol = check_newton_tolerance(newton_tolerance)
    key = (N, LOOPS, MASKED, tol)
    cached = _KERNELS.get(key)
    if cached is not None:
        return cached

    @wp.func
    def node_x(xw: wp.tile(dtype=wp.vec4, shape=(N,), storage="shared"), j: int):
        """Node ``j``'s position from the block's shared (position, inverse mass) rows."""
        v = wp.tile_extract(xw, j)
        return wp.vec3(v[0], v[1], v[2])

    pcr_round = pcr_round_func(N)
    pack_setup = pack_setup_func(LOOPS, MASKED)

    def solve_chains_block(
        pack_base: int,
        pack_start: wp.array(dtype=wp.int32),
        pack_rows: wp.array(dtype=wp.int32),
        pack_closed: wp.array(dtype=wp.int32),
        rows: wp.array(dtype=wp.vec3i),
        rest: wp.array(dtype=float),
        compliance: wp.array2d(dtype=float),
        inv_mass: wp.array2d(dtype=float),
        inv_dt2: float,
        use_lambda: int,
        newton_steps: int,
        lam: wp.array2d(dtype=float),
        active: wp.array2d(dtype=wp.int32),
        q: wp.array2d(dtype=wp.vec3),
    ):
        env, i, lane = wp.tid()
        lanes = wp.block_dim()
        p = pack_base + i
        r0 = pack_start[p]  # row t of this pack at rows[r0 + t]: (particle, link's constraint or -1, chain start)
        n = pack_rows[p]
        # a loop has a pack of its own: n links over n nodes, link n - 1 closing it; open chains: n rows, the links
        # those with a constraint
        pe = env % inv_mass.shape[0]
        ce = env % compliance.shape[0]
        masked, closed3, wraps = pack_setup(pack_closed, p, rows, r0, n, active, env)
        rows0 = wp.tile_zeros(shape=N, dtype=vec6, storage="shared")  # link rows (a, b, c, r, u, 0), PCR buffer 0
        rows1 = wp.tile_zeros(shape=N, dtype=vec6, storage="shared")  # ... and 1
        dl_acc = wp.tile_zeros(shape=N, dtype=wp.vec2, storage="shared")  # per link: dl, this sweep's multiplier so far
        node0 = wp.tile_zeros(shape=N, dtype=vec6, storage="shared")  # filter rows (a, b, c, d), PCR buffer 0
        node1 = wp.tile_zeros(shape=N, dtype=vec6, storage="shared")  # ... and 1
        par_tile = wp.tile_zeros(shape=N, dtype=wp.vec3, storage="shared")  # the tangential part plus the position
        if wp.static(tol > 0.0):
            corrections = wp.tile_zeros(shape=N, dtype=float, storage="shared")  # per link: |dl| (w_k + w_{k+1})
        # the nodes' positions and inverse masses, loaded once: the rows read each node up to four times
        xw = wp.tile_zeros(shape=N, dtype=wp.vec4, storage="shared")
        for base in range(0, n, lanes):
            j = wp.min(base + lane, n - 1)
            node = rows[r0 + j][0]
            x = q[env, node]
            wp.tile_scatter_masked(xw, j, wp.vec4(x[0], x[1], x[2], inv_mass[pe, node]), base + lane < n)

        for it in range(newton_steps):
            cyclic = closed3
            x_first = node_x(xw, 0)
            w_first = wp.tile_extract(xw, 0)[3]
            g = float(0.0)
            s = float(0.0)
            if cyclic != 0:
                # the corner A_{n-1,0} and Sherman-Morrison's g = -A_00 (every lane forms them)
                n_first, len_first = segment_dir(x_first, node_x(xw, 1 % n))
                n_last, len_last = segment_dir(node_x(xw, n - 1), x_first)
                s = -w_first * wp.dot(n_last, n_first)
                if s == 0.0:
                    cyclic = 0  # no corner coupling (node 0 pinned): a plain tridiagonal system
                else:
                    w1 = wp.tile_extract(xw, 1 % n)[3]
                    g = -(w_first + w1 + compliance[ce, rows[r0][1]] * inv_dt2)
            # ---- rows of the link system (buffers 0): row k the link from node k, an identity row where none
            for base in range(0, n, lanes):
                k = wp.min(base + lane, n - 1)
                row_k = rows[r0 + k]
                cons = row_k[1]
                a_k = float(0.0)
                b_k = float(1.0)
                c_k = float(0.0)
                rhs = float(0.0)
                u_k = float(0.0)
                if cons >= 0:
                    k1 = k + 1
                    if k1 == n:
                        k1 = 0  # a loop's closing link
                    xk = node_x(xw, k)
                    xk1 = node_x(xw, k1)
                    n_k, len_k = segment_dir(xk, xk1)
                    w_k = wp.tile_extract(xw, k)[3]
                    w_k1 = wp.tile_extract(xw, k1)[3]
                    act_k = int(1)
                    if masked:
                        act_k = active[env, cons]
                    if k + 1 < n:
                        cons_next = rows[r0 + k + 1][1]  # -1: k + 1 is the chain's last node
                        if cons_next >= 0:
                            k2 = k + 2
                            if k2 >= n:
                                k2 = k2 - n
                            n_next, len_next = segment_dir(xk1, node_x(xw, k2))
                            c_k = -w_k1 * wp.dot(n_k, n_next)
                            if masked:
                                if act_k == 0 or active[env, cons_next] == 0:
                                    c_k = 0.0  # no coupling across a cut
                    if row_k[2] == 0:
                        n_prev, len_prev = segment_dir(node_x(xw, k - 1), xk)
                        a_k = -w_k * wp.dot(n_prev, n_k)
                        if masked:
                            if act_k == 0 or active[env, rows[r0 + k - 1][1]] == 0:
                                a_k = 0.0
                    lam_k = wp.tile_extract(dl_acc, k)[1]  # earlier Newton steps of this sweep
                    if use_lambda != 0:
                        lam_k = lam_k + lam[env, cons]
                    b_k, rhs, u_k = link_row_terms(w_k, w_k1, compliance[ce, cons] * inv_dt2, rest[cons] - len_k,
                                                   lam_k, k, n, cyclic, g, s, act_k)
                wp.tile_scatter_masked(rows0, k, vec6(a_k, b_k, c_k, rhs, u_k, 0.0), base + lane < n)
            # ---- PCR, two rounds per pass (0 -> 1 -> 0); a round at a distance >= n copies
            sd = int(1)
            while sd < n:
                pcr_round(rows0, rows1, sd, n, lane, lanes)
                pcr_round(rows1, rows0, 2 * sd, n, lane, lanes)
                sd = 4 * sd
            f = float(0.0)
            if cyclic != 0:
                first_row = wp.tile_extract(rows0, 0)
                last_row = wp.tile_extract(rows0, n - 1)
                y0 = first_row[3] / first_row[1]
                z0 = first_row[4] / first_row[1]
                yl = last_row[3] / last_row[1]
                zl = last_row[4] / last_row[1]
                f = (y0 + (s / g) * yl) / (1.0 + z0 + (s / g) * zl)
            for base in range(0, n, lanes):
                k = wp.min(base + lane, n - 1)
                row = wp.tile_extract(rows0, k)
                dl = (row[3] - f * row[4]) / row[1]
                total = wp.tile_extract(dl_acc, k)[1] + dl
                write = base + lane < n
                if wp.static(tol > 0.0):
                    correction = float(0.0)
                    if rows[r0 + k][1] >= 0:
                        k1 = k + 1
                        if k1 == n:
                            k1 = 0
                        correction = wp.abs(dl) * (wp.tile_extract(xw, k)[3] + wp.tile_extract(xw, k1)[3])
                    wp.tile_scatter_masked(corrections, k, correction, write)
                else:
                    if write and use_lambda != 0 and it == newton_steps - 1:
                        cons = rows[r0 + k][1]
                        if cons >= 0:
                            lam[env, cons] = lam[env, cons] + total
                wp.tile_scatter_masked(dl_acc, k, wp.vec2(dl, total), write)
            final_step = int(0)  # this sweep's last Newton step (only with a tolerance: it may come early)
            if wp.static(tol > 0.0):
                if it == newton_steps - 1 or wp.tile_extract(wp.tile_max(corrections), 0) < tol:
                    final_step = 1
                if use_lambda != 0 and final_step != 0:
                    # the multipliers go out at the step that stops
                    for base in range(0, n, lanes):
                        k = wp.min(base + lane, n - 1)
                        cons = rows[r0 + k][1]
                        if base + lane < n and cons >= 0:
                            lam[env, cons] = lam[env, cons] + wp.tile_extract(dl_acc, k)[1]
            # ---- the transverse filter's rows over the nodes (buffers 0), positions before this step's update
            for base in range(0, n, lanes):
                j = wp.min(base + lane, n - 1)
                row_j = rows[r0 + j]
                x_cur = node_x(xw, j)
                n_prev = wp.vec3(0.0)
                dl_prev = float(0.0)
                k_prev = float(0.0)
                if row_j[2] == 0:
                    n_prev, len_p = segment_dir(node_x(xw, j - 1), x_cur)
                    if masked:
                        if active[env, rows[r0 + j - 1][1]] == 0:
                            n_prev = wp.vec3(0.0)
                    dl_prev = wp.tile_extract(dl_acc, j - 1)[0]
                    if len_p > 1.0e-12:
                        k_prev = wp.max(-dl_prev, 0.0) / len_p
                elif wraps != 0:
                    # the closing link's correction (node 0 pinned: w_0 = 0 below); open-chain filter: no k_prev
                    n_prev, len_p = segment_dir(node_x(xw, n - 1), x_cur)
                    if masked:
                        if active[env, rows[r0 + n - 1][1]] == 0:
                            n_prev = wp.vec3(0.0)
                    dl_prev = wp.tile_extract(dl_acc, n - 1)[0]
                n_j = wp.vec3(0.0)
                dl_j = float(0.0)
                k_j = float(0.0)
                if row_j[1] >= 0:
                    jn = j + 1
                    if jn == n:
                        jn = 0
                    n_j, len_j = segment_dir(x_cur, node_x(xw, jn))
                    if masked:
                        if active[env, row_j[1]] == 0:
                            n_j = wp.vec3(0.0)
                    dl_j = wp.tile_extract(dl_acc, j)[0]
                    if jn != 0 and len_j > 1.0e-12:  # not a loop's closing link: an open-chain filter
                        k_j = wp.max(-dl_j, 0.0) / len_j
                w_j = wp.tile_extract(xw, j)[3]
                lo, diag, up, rhs_j, par = node_row(n_prev, dl_prev, k_prev, n_j, dl_j, k_j, w_j, 1 - row_j[2])
                write = base + lane < n
                wp.tile_scatter_masked(node0, j, vec6(lo, diag, up, rhs_j[0], rhs_j[1], rhs_j[2]), write)
                wp.tile_scatter_masked(par_tile, j, par + x_cur, write)
            sd = int(1)
            while sd < n:
                pcr_round(node0, node1, sd, n, lane, lanes)
                pcr_round(node1, node0, 2 * sd, n, lane, lanes)
                sd = 4 * sd
            for base in range(0, n, lanes):
                j = wp.min(base + lane, n - 1)
                xwj = wp.tile_extract(xw, j)
                moved = base + lane < n and xwj[3] > 0.0
                x = wp.vec3(0.0)
                if moved:
                    frow = wp.tile_extract(node0, j)
                    x = wp.tile_extract(par_tile, j) + wp.vec3(frow[3], frow[4], frow[5]) / frow[1]
                    q[env, rows[r0 + j][0]] = x
                # the shared copy too (its scatter is the barrier before the next Newton step reads it)
                wp.tile_scatter_masked(xw, j, wp.vec4(x[0], x[1], x[2], xwj[3]), moved)
            if wp.static(tol > 0.0):
                if final_step != 0:
                    break  # converged (every lane alike: the block's one largest correction)

    kernel = wp.kernel(solve_chains_block, module="unique", enable_backward=False)
    _KERNELS[key] = kernel
    return kernel
