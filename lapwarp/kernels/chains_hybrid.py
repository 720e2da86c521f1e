"""Direct XPBD solve of chains of distance constraints, one thread block per (env, pack of chains), each lane a few
consecutive rows: the systems of ``kernels/chains.py`` (read its docstring first) on ``chains_block.py``'s packs
(``chains.ChainPacks``), solved by the partition method (a Thomas-like elimination within each lane's rows, parallel
cyclic reduction over one interface row per lane, then back substitution).

``chains_block.py`` gives each row a lane and eliminates by PCR: ``O(n log n)`` work, every intermediate row in shared
memory and a block barrier per round (~20 per Newton step); on the GPU the 40 x 40 cloth ran at half the speed of
the serial walk (``chains.solve_chains``), whose ~4 dependent global loads and stores per link are what both try to
avoid. Here lane ``l`` owns the ``P`` rows ``s = lP .. e = lP + P - 1`` of a pack and keeps them in registers
(``P`` is a compile-time constant, so the per-row vectors' indices are constants of unrolled loops):

1. it reads its nodes ``s - 1 .. e + 2`` from global memory (neighbouring lanes read a few of the same nodes, which
   the caches serve) and forms its rows ``a_i x_{i-1} + b_i x_i + c_i x_{i+1} = d_i`` (``d``: up to three
   right-hand sides);
2. downward elimination keeps the coupling to ``x_{s-1}``: row ``i`` becomes ``al_i x_{s-1} + be_i x_i + c_i x_{i+1}
   = de_i``; an upward pass over these from row ``e - 1`` gives row ``s`` as ``alu x_{s-1} + beu x_s + gau x_e = deu``,
   which the lane publishes in shared memory;
3. its last row, with ``x_{e+1} = x_{s'}`` of the next lane replaced by that lane's published row, couples only the
   interface unknowns ``X_{l-1} = x_{s-1}``, ``X_l = x_e`` and ``X_{l+1} = x_{e'}``: a tridiagonal system of one row
   per lane (the Schur complement, diagonally dominant where the chain's system is), solved by PCR in shared memory
   (``chains_block.pcr_round_func``);
4. back substitution from ``x_e = X_l``: ``x_i = (de_i - al_i X_{l-1} - c_i x_{i+1}) / be_i``.

Work is ``O(n)`` plus ``O(L log L)`` for ``L = n / P`` lanes, with ~2 log2 L + 3 barriers per system. The Newton
steps, multipliers, cuts (identity rows), loops (Sherman-Morrison, their own pack) and the transverse filter are those
of ``chains_block.py``; round-off differs from the serial solve (another elimination order), nothing else
(``tests/test_chains_hybrid.py``). Positions move in global memory: a lane writes its nodes at the end of a Newton
step, after the barriers of its solves, and a barrier opens the next step, so every lane reads its neighbours'
updated nodes.

Measured (H100, 4,096 envs, thirty-second session; ``benchmarks/RESULTS.md``): the free 40 x 40 cloth 37.7k env-steps/s
at 4 rows per lane against 59.1k for the serial walk (29.4k at 2, 18.5k at 1), a 100-segment rod 737k against 364k.
At 4 rows per lane the kernel takes 255 registers (``benchmarks/kernel_resources.py``): 8 warps per SM. Not a task's
default.

Lanes are real threads on the CPU too: Warp's cooperative CPU blocks (``wp.config.enable_cpu_blocks``) run a block's
lanes as fibers with real barriers, so the CPU tests run the GPU's partition, reduced system and all.
"""

# no ``from __future__ import annotations``: the tile arguments' annotations name the kernel's tile length, a local of
# the factory, which Warp can evaluate only as objects
import warp as wp

from lapwarp.kernels.chains import check_newton_tolerance, link_row_terms, node_row, segment_dir
from lapwarp.kernels.chains_block import pack_setup_func, pcr_round_func, vec6

wp.set_module_options({"enable_backward": False})

# the kernels by (most rows of a pack, rows per lane, loops, masked, Newton tolerance)
_KERNELS: dict[tuple, wp.Kernel] = {}


def lanes_for(max_rows: int, rows_per_lane: int) -> int:
    """Lanes that hold a pack of ``max_rows`` rows at ``rows_per_lane`` each (the reduced system's rows)."""
    return max(-(-int(max_rows) // int(rows_per_lane)), 1)


@wp.func
def link_at(rows: wp.array(dtype=wp.vec3i), r0: int, n: int, k: int, wraps: int, masked: bool,
            active: wp.array2d(dtype=wp.int32), env: int, q: wp.array2d(dtype=wp.vec3)):
    """Link ``k`` of a pack (``k = -1``: a loop's closing link ``n - 1``): direction, length, constraint (-1: none,
    then nothing else) and whether it is active."""
    kk = k
    if kk < 0 and wraps != 0:
        kk = n - 1
    d = wp.vec3(0.0)
    length = float(0.0)
    cons = int(-1)
    act = int(0)
    if kk >= 0 and kk < n:
        cons = rows[r0 + kk][1]
        if cons >= 0:
            k1 = kk + 1
            if k1 == n:
                k1 = 0
            d, length = segment_dir(q[env, rows[r0 + kk][0]], q[env, rows[r0 + k1][0]])
            act = 1
            if masked:
                act = active[env, cons]
    return d, length, cons, act


_SOLVERS: dict[tuple[int, int], wp.Function] = {}


def partition_solver(P: int, L: int) -> wp.Function:
    """The per-lane partition solve of a tridiagonal system of at most ``L`` lanes x ``P`` rows (cached)."""
    cached = _SOLVERS.get((P, L))
    if cached is not None:
        return cached
    vec_p = wp.types.vector(length=P, dtype=float)
    mat_p3 = wp.types.matrix(shape=(P, 3), dtype=float)
    pcr_round = pcr_round_func(L)
    # loop counts as plain names: Warp unrolls a range of a constant name, not of an expression (``range(P - 1)``
    # became a dynamic loop, its vectors' indices dynamic, the vectors in local memory)
    P_1 = P - 1
    P_2 = max(P - 2, 0)

    @wp.func
    def solve_partition(a: vec_p, b: vec_p, c: vec_p, d: mat_p3,
                        up: wp.tile(dtype=vec6, shape=(L,), storage="shared"),
                        red0: wp.tile(dtype=vec6, shape=(L,), storage="shared"),
                        red1: wp.tile(dtype=vec6, shape=(L,), storage="shared"),
                        lane: int, lanes: int, nl: int):
        """Solve the pack's tridiagonal system whose rows ``lane * P + i`` this lane holds as ``(a, b, c, d)``
        (``nl`` lanes hold rows; every lane of the block calls it, for its barriers). Returns the lane's unknowns and
        the previous lane's last one (``x_{s-1}``; zero for lane 0)."""
        # downward: row i as al_i x_{s-1} + be_i x_i + c_i x_{i+1} = de_i (a, b, d overwritten)
        for i in range(1, P):
            m = a[i] / b[i - 1]
            a[i] = -m * a[i - 1]
            b[i] = b[i] - m * c[i - 1]
            d[i] = d[i] - m * d[i - 1]
        # upward from row e - 1, whose downward form couples x_{s-1} and x_e already: row s as
        # alu x_{s-1} + beu x_s + gau x_e = deu (one row: x_s = x_e itself)
        alu = float(0.0)
        beu = float(1.0)
        gau = float(-1.0)
        deu = wp.vec3(0.0)
        if wp.static(P >= 2):
            alu = a[P - 2]
            beu = b[P - 2]
            gau = c[P - 2]
            deu = d[P - 2]
            for t in range(P_2):
                i = P - 3 - t
                m = c[i] / beu
                alu = a[i] - m * alu
                beu = b[i]
                gau = -m * gau
                deu = d[i] - m * deu
        holds = lane < nl
        wp.tile_scatter_masked(up, wp.min(lane, L - 1), vec6(alu, beu, gau, deu[0], deu[1], deu[2]), holds)
        # the reduced row of X_l = x_e: x_{e+1} = x_{s'} from the next lane's row s' (in X_l and X_{l+1})
        rb = b[P - 1]
        rc = float(0.0)
        rd = d[P - 1]
        if lane + 1 < nl:
            nxt = wp.tile_extract(up, lane + 1)
            f = c[P - 1] / nxt[1]
            rb = rb - f * nxt[0]
            rc = -f * nxt[2]
            rd = rd - wp.vec3(nxt[3], nxt[4], nxt[5]) * f
        wp.tile_scatter_masked(red0, wp.min(lane, L - 1), vec6(a[P - 1], rb, rc, rd[0], rd[1], rd[2]), holds)
        sd = int(1)
        while sd < nl:
            pcr_round(red0, red1, sd, nl, lane, lanes)
            pcr_round(red1, red0, 2 * sd, nl, lane, lanes)
            sd = 4 * sd
        x = mat_p3()
        x_prev = wp.vec3(0.0)
        if holds:
            row = wp.tile_extract(red0, lane)
            x[P - 1] = wp.vec3(row[3], row[4], row[5]) / row[1]
            if lane > 0:
                prev = wp.tile_extract(red0, lane - 1)
                x_prev = wp.vec3(prev[3], prev[4], prev[5]) / prev[1]
            for t in range(P_1):
                i = P - 2 - t
                x[i] = (d[i] - x_prev * a[i] - x[i + 1] * c[i]) / b[i]
        return x, x_prev

    _SOLVERS[(P, L)] = solve_partition
    return solve_partition


def hybrid_chain_kernel(max_rows: int, rows_per_lane: int, loops: bool = True, masked: bool = True,
                        newton_tolerance: float = 0.0) -> wp.Kernel:
    """The partitioned block solve for packs of at most ``max_rows`` rows, ``rows_per_lane`` rows per lane (cached):
    launch ``(num_envs, packs, lanes)`` with ``block_dim=lanes``, ``lanes >= lanes_for(max_rows, rows_per_lane)``
    (extra lanes idle), one family at a time. ``loops`` / ``masked`` (compile-time): whether the family may hold a
    closed loop / the scene has cutting masks; without them the variant holds no registers for their branches
    (RopeThreading's open, uncut rope: 255 registers and a 112-byte spill frame -> 217 and none at 4 rows, sm_90).
    ``newton_tolerance`` (m, compile-time; 0 = off): a pack stops its Newton steps once one has corrected none of its
    links by that much (``chains_registers.register_chain_kernel``'s rule; the block's largest correction, a tile
    reduction, decides for all its lanes)."""
    P = int(rows_per_lane)
    if not 1 <= P <= 16:
        raise ValueError(f"rows per lane must be in [1, 16] (unrolled per lane), got {rows_per_lane!r}")
    tol = check_newton_tolerance(newton_tolerance)
    L = lanes_for(max_rows, P)
    LOOPS, MASKED = bool(loops), bool(masked)
    key = (L * P, P, LOOPS, MASKED, tol)
    cached = _KERNELS.get(key)
    if cached is not None:
        return cached
    # a lane's rows (coefficients, right-hand sides, multipliers) in registers
    vec_p = wp.types.vector(length=P, dtype=float)
    mat_p3 = wp.types.matrix(shape=(P, 3), dtype=float)

    solve_partition = partition_solver(P, L)
    pack_setup = pack_setup_func(LOOPS, MASKED)

    def solve_chains_hybrid(
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
        env, i_pack, lane = wp.tid()
        lanes = wp.block_dim()
        p = pack_base + i_pack
        r0 = pack_start[p]  # row t of this pack at rows[r0 + t]: (particle, link's constraint or -1, chain start)
        n = pack_rows[p]
        nl = (n + P - 1) // P  # lanes holding rows
        s_row = lane * P  # this lane's first row
        pe = env % inv_mass.shape[0]
        ce = env % compliance.shape[0]
        masked, closed3, wraps = pack_setup(pack_closed, p, rows, r0, n, active, env)
        up = wp.tile_zeros(shape=L, dtype=vec6, storage="shared")
        red0 = wp.tile_zeros(shape=L, dtype=vec6, storage="shared")
        red1 = wp.tile_zeros(shape=L, dtype=vec6, storage="shared")
        ends = wp.tile_zeros(shape=2, dtype=wp.vec3, storage="shared")  # a loop's rows 0 and n - 1 (y, z)
        dl_tot = vec_p()  # this sweep's multipliers so far, per row
        if wp.static(tol > 0.0):
            largest = wp.tile_zeros(shape=L, dtype=float, storage="shared")  # each lane's largest link correction
        for it in range(newton_steps):
            # the previous Newton step's node writes before this step's reads (a barrier; nothing written)
            wp.tile_scatter_masked(ends, 0, wp.vec3(0.0), False)
            # ---- a loop's corner and Sherman-Morrison g (every lane forms them)
            cyclic = closed3
            g = float(0.0)
            s = float(0.0)
            if cyclic != 0:
                x_first = q[env, rows[r0][0]]
                w_first = inv_mass[pe, rows[r0][0]]
                n_first, len_first = segment_dir(x_first, q[env, rows[r0 + 1][0]])
                n_last, len_last = segment_dir(q[env, rows[r0 + n - 1][0]], x_first)
                s = -w_first * wp.dot(n_last, n_first)
                if s == 0.0:
                    cyclic = 0  # no corner coupling (node 0 pinned): a plain tridiagonal system
                else:
                    w1 = inv_mass[pe, rows[r0 + 1][0]]
                    g = -(w_first + w1 + compliance[ce, rows[r0][1]] * inv_dt2)
            # ---- the link system's rows: row k the link from node k, an identity row where none. The links
            # k - 1, k, k + 1 roll along the lane's rows (read again from memory, not kept, to spare registers)
            la = vec_p()
            lb = vec_p()
            lc = vec_p()
            ld = mat_p3()
            wsum = vec_p()  # w_k + w_{k+1} of each row's link (only with a tolerance)
            p_dir, p_len, p_cons, p_act = link_at(rows, r0, n, s_row - 1, wraps, masked, active, env, q)
            c_dir, c_len, c_cons, c_act = link_at(rows, r0, n, s_row, wraps, masked, active, env, q)
            for i in range(P):
                k = s_row + i
                x_dir, x_len, x_cons, x_act = link_at(rows, r0, n, k + 1, wraps, masked, active, env, q)
                lb[i] = 1.0
                if k < n and c_cons >= 0:
                    k1 = k + 1
                    if k1 == n:
                        k1 = 0
                    w_k = inv_mass[pe, rows[r0 + k][0]]
                    w_k1 = inv_mass[pe, rows[r0 + k1][0]]
                    if k + 1 < n and x_cons >= 0:
                        lc[i] = -w_k1 * wp.dot(c_dir, x_dir)
                        if c_act == 0 or x_act == 0:
                            lc[i] = 0.0  # no coupling across a cut
                    if rows[r0 + k][2] == 0:
                        la[i] = -w_k * wp.dot(p_dir, c_dir)
                        if c_act == 0 or p_act == 0:
                            la[i] = 0.0
                    lam_k = dl_tot[i]  # earlier Newton steps of this sweep
                    if use_lambda != 0:
                        lam_k = lam_k + lam[env, c_cons]
                    b_k, rhs, u_k = link_row_terms(w_k, w_k1, compliance[ce, c_cons] * inv_dt2, rest[c_cons] - c_len,
                                                   lam_k, k, n, cyclic, g, s, c_act)
                    lb[i] = b_k
                    ld[i] = wp.vec3(rhs, u_k, 0.0)
                    if wp.static(tol > 0.0):
                        wsum[i] = w_k + w_k1
                p_dir = c_dir
                p_act = c_act
                c_dir = x_dir
                c_len = x_len
                c_cons = x_cons
                c_act = x_act
            yz, yz_prev = solve_partition(la, lb, lc, ld, up, red0, red1, lane, lanes, nl)
            # ---- a loop: rows 0 and n - 1 to every lane (the correction f, the closing link's dl)
            f = float(0.0)
            dl_last = float(0.0)
            if wraps != 0:
                last = wp.vec3(0.0)
                has_last = int(0)
                for i in range(P):
                    if s_row + i == n - 1:
                        last = yz[i]
                        has_last = 1
                wp.tile_scatter_masked(ends, 0, yz[0], lane == 0)
                wp.tile_scatter_masked(ends, 1, last, has_last != 0)
                first_yz = wp.tile_extract(ends, 0)
                last_yz = wp.tile_extract(ends, 1)
                if cyclic != 0:
                    f = (first_yz[0] + (s / g) * last_yz[0]) / (1.0 + first_yz[1] + (s / g) * last_yz[1])
                dl_last = last_yz[0] - f * last_yz[1]
            dl = vec_p()
            for i in range(P):
                dl[i] = yz[i, 0] - f * yz[i, 1]
                dl_tot[i] = dl_tot[i] + dl[i]
            final_step = int(0)  # this sweep's last Newton step: the multipliers go out
            if it == newton_steps - 1:
                final_step = 1
            if wp.static(tol > 0.0):
                mine = float(0.0)
                for i in range(P):
                    mine = wp.max(mine, wp.abs(dl[i]) * wsum[i])
                wp.tile_scatter_masked(largest, wp.min(lane, L - 1), mine, lane < nl)
                if wp.tile_extract(wp.tile_max(largest), 0) < tol:
                    final_step = 1  # converged: this step is applied, then the pack stops
            dl_before = yz_prev[0] - f * yz_prev[1]  # link s - 1's
            if s_row == 0:
                dl_before = dl_last  # a loop's closing link (0 for an open pack: no link before row 0)
            # ---- the transverse filter's rows over the nodes, positions before this step's update (links j - 1, j
            # rolling; a lane's multipliers go out at the last Newton step)
            fa = vec_p()
            fb = vec_p()
            fc = vec_p()
            fd = mat_p3()
            par = mat_p3()
            p_dir, p_len, p_cons, p_act = link_at(rows, r0, n, s_row - 1, wraps, masked, active, env, q)
            dl_prev = dl_before
            for i in range(P):
                j = s_row + i
                c_dir, c_len, c_cons, c_act = link_at(rows, r0, n, j, wraps, masked, active, env, q)
                fb[i] = 1.0
                if j < n:
                    if use_lambda != 0 and final_step != 0 and c_cons >= 0:
                        lam[env, c_cons] = lam[env, c_cons] + dl_tot[i]
                    start = rows[r0 + j][2]
                    n_prev = wp.vec3(0.0)
                    dl_p = float(0.0)
                    k_prev = float(0.0)
                    if start == 0 or (j == 0 and wraps != 0):
                        if p_act != 0:
                            n_prev = p_dir
                        dl_p = dl_prev
                        if start == 0 and p_len > 1.0e-12:  # the loop's closing link: no k_prev
                            k_prev = wp.max(-dl_p, 0.0) / p_len
                    n_j = wp.vec3(0.0)
                    dl_j = float(0.0)
                    k_j = float(0.0)
                    if c_cons >= 0:
                        if c_act != 0:
                            n_j = c_dir
                        dl_j = dl[i]
                        if j + 1 < n and c_len > 1.0e-12:  # not a loop's closing link
                            k_j = wp.max(-dl_j, 0.0) / c_len
                    node = rows[r0 + j][0]
                    lo, diag, upper, rhs_j, par_j = node_row(n_prev, dl_p, k_prev, n_j, dl_j, k_j, inv_mass[pe, node],
                                                             1 - start)
                    fa[i] = lo
                    fb[i] = diag
                    fc[i] = upper
                    fd[i] = rhs_j
                    par[i] = par_j + q[env, node]
                p_dir = c_dir
                p_len = c_len
                p_act = c_act
                dl_prev = dl[i]
            y, y_prev = solve_partition(fa, fb, fc, fd, up, red0, red1, lane, lanes, nl)
            for i in range(P):
                j = s_row + i
                if j < n:
                    node = rows[r0 + j][0]
                    if inv_mass[pe, node] > 0.0:
                        q[env, node] = par[i] + y[i]
            if wp.static(tol > 0.0):
                if final_step != 0:
                    break  # every lane alike (the block's one largest correction)

    kernel = wp.kernel(solve_chains_hybrid, module="unique", enable_backward=False)
    _KERNELS[key] = kernel
    return kernel
