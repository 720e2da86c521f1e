"""Direct XPBD solve of open chains of distance constraints with every node in shared memory: one thread block per
env solves every family of a chain set (a cloth's rows, columns and diagonals) in one launch per sweep. The systems
are those of ``kernels/chains.py`` (read its docstring first); each lane walks one chain as its serial kernel does.

Why: the serial kernel (``chains.solve_chains`` / ``solve_cloth_chains``, a thread per (env, chain), one launch per
family) keeps its eliminations' intermediate values in per-env global scratch and gathers every node's position
from global memory several times per Newton step: PrecisionCutting's 40 x 40 cloth moves ~0.5 KB of global memory
per link per sweep, at 4,096 envs far more than the L2 holds, so its chain solve (~80 % of the step) runs at the
speed of device memory. Here a block loads its env's node window ``q[env, node_start : node_start + P]`` and inverse
masses into shared memory once per sweep and stores it back at the end; the scratch lives in shared memory as well,
one column of ``M + 1`` slots per lane.

Per family, in rounds of ``block_dim`` chains (a family's chains are stored longest first, so a round's loop bound
is its first chain's length), each lane solves its chain in three walks per Newton step:

1. forward over the links: the Thomas elimination of the link system, as the serial kernel (``(c', d')`` into the
   lane's slots);
2. backward over the links: the back substitution gives ``dl_k``; with ``dl_k`` and ``dl_{k+1}`` known, node
   ``k + 1``'s row of the transverse filter is formed (``chains.node_row``, the same row as the serial kernel's) and
   eliminated at once, the filter's Thomas run from the chain's far end (its ``(c, d)`` into the slot the link
   system no longer needs; the node's tangential part plus its position into the shared position, which no later
   row of the chain reads: each row reads its neighbours' positions as they were before this Newton step, carried
   in registers);
3. forward over the nodes: the filter's substitution, ``x_j = par_j + y_j`` where ``w_j > 0``.

The serial kernel eliminates the filter from the chain's first node; here it is eliminated from the last, so the
two agree to round-off (the system is diagonally dominant either way), not bit for bit (``tests/test_chains_shared
.py``). Multipliers (``use_lambda``, ``newton_steps > 1``) are kept in the same global arrays as the serial kernel's.

Only open chains (a closed loop's Sherman-Morrison form is left to the other solves) whose nodes lie in one window
of at most ``world.SHARED_CHAIN_MAX_NODES`` particles. The lanes of a family never share a node or a slot column,
so the block barriers that Warp's shared-memory writes include order nothing within a family; between families
they make one family's positions visible to the next (Gauss-Seidel across families, as the serial launches).

On the CPU a block has one lane, which takes the chains of each family one by one in order.
"""

import warp as wp

from lapwarp.kernels.chains import node_row, segment_dir

wp.set_module_options({"enable_backward": False})

# the kernels by (window of nodes, longest chain's links, lanes, masked): a tile's shape is a compile-time constant
_KERNELS: dict[tuple[int, int, int, bool], wp.Kernel] = {}


def shared_chain_kernel(num_nodes: int, max_links: int, lanes: int, masked: bool) -> wp.Kernel:
    """The shared-memory chain solve for a node window of ``num_nodes`` particles, chains of at most ``max_links``
    links and blocks of ``lanes`` threads (``launching.block_lanes``: 1 on the CPU), cached; ``masked``
    (compile-time): whether the scene has cutting masks. Launch ``(num_envs, lanes)`` with ``block_dim=lanes``,
    once per sweep for every family of the chain set."""
    key = (int(num_nodes), int(max_links), int(lanes), bool(masked))
    cached = _KERNELS.get(key)
    if cached is not None:
        return cached
    P, M, L, MASKED = key
    SLOTS = (M + 1) * L

    def solve_chains_shared(
        families: wp.array(dtype=wp.vec4i),
        node_start: int,
        chain_edge_count: wp.array(dtype=wp.int32),
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
        active: wp.array2d(dtype=wp.int32),
        q: wp.array2d(dtype=wp.vec3),
    ):
        env, lane = wp.tid()
        pe = env % inv_mass.shape[0]
        ce = env % compliance.shape[0]
        xs = wp.tile_load(q[env], shape=P, offset=node_start, storage="shared")
        ws = wp.tile_load(inv_mass[pe], shape=P, offset=node_start, storage="shared")
        # a lane's column: slot k * L + lane holds link k's (c', d') in walk 1, node k's filter (c, d) from walk 2
        slots = wp.tile_zeros(shape=SLOTS, dtype=wp.vec4, storage="shared")
        for f in range(families.shape[0]):
            fam = families[f]
            first = fam[0]
            count = fam[1]
            stride = count
            for r0 in range(0, count, L):
                i = wp.min(r0 + lane, count - 1)
                m = int(0)
                if r0 + lane < count:
                    m = chain_edge_count[first + i]
                mr = chain_edge_count[first + r0]  # the round's longest chain: the loops' bound for every lane
                valid = r0 + lane < count
                s0 = fam[2] + i  # link k at s0 + k * stride, node j at nb + j * stride (kernels/chains.py)
                nb = fam[3] + i
                for it in range(newton_steps):
                    # ---- 1. forward elimination of the link system (the serial kernel's, open chains) ----------
                    node_k1 = chain_node[nb + stride]
                    x_k1 = wp.tile_extract(xs, node_k1 - node_start)
                    n_cur, len_cur = segment_dir(wp.tile_extract(xs, chain_node[nb] - node_start), x_k1)
                    cons_k = chain_constraint[s0]
                    act_k = int(1)
                    if wp.static(MASKED):
                        act_k = active[env, cons_k]
                    w_k = wp.tile_extract(ws, chain_node[nb] - node_start)
                    c_prev = float(0.0)
                    d_prev = float(0.0)
                    a_k = float(0.0)
                    for k in range(mr):
                        if k < m:
                            w_k1 = wp.tile_extract(ws, node_k1 - node_start)
                            n_next = wp.vec3(0.0)
                            len_next = float(0.0)
                            c_k = float(0.0)
                            node_k2 = node_k1
                            x_k2 = x_k1
                            cons_next = cons_k
                            act_next = act_k
                            if k + 1 < m:
                                node_k2 = chain_node[nb + (k + 2) * stride]
                                x_k2 = wp.tile_extract(xs, node_k2 - node_start)
                                n_next, len_next = segment_dir(x_k1, x_k2)
                                c_k = -w_k1 * wp.dot(n_cur, n_next)
                                cons_next = chain_constraint[s0 + (k + 1) * stride]
                                if wp.static(MASKED):
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
                            a_k = c_k
                            n_cur = n_next
                            len_cur = len_next
                            w_k = w_k1
                            node_k1 = node_k2
                            x_k1 = x_k2
                            cons_k = cons_next
                            act_k = act_next
                        wp.tile_scatter_masked(slots, k * L + lane, wp.vec4(c_prev, d_prev, 0.0, 0.0), k < m)

                    # ---- 2. back substitution of the links; node k + 1's filter row, eliminated from the far end
                    # carried from link k + 1 to link k: its dl, direction (zero where removed) and tension weight,
                    # node k + 1's position before this Newton step and its filter elimination (c, d)
                    node_hi = chain_node[nb + m * stride]
                    x_hi = wp.tile_extract(xs, node_hi - node_start)
                    dl_hi = float(0.0)
                    n_hi = wp.vec3(0.0)
                    k_hi = float(0.0)
                    ct_hi = float(0.0)
                    dt_hi = wp.vec3(0.0)
                    for kk in range(mr):
                        k = mr - 1 - kk
                        row = k + 1  # the node this step eliminates
                        has = k < m
                        ct = float(0.0)
                        dt = wp.vec3(0.0)
                        x_new = wp.vec3(0.0)
                        local_row = int(0)
                        if has:
                            link = wp.tile_extract(slots, k * L + lane)
                            dl_k = link[1] - link[0] * dl_hi
                            cons = chain_constraint[s0 + k * stride]
                            # the multiplier of this sweep's Newton steps so far (the serial kernel's bookkeeping)
                            acc = dl_k
                            if it > 0:
                                acc = scratch_l[env, s0 + k * stride] + dl_k
                            if it < newton_steps - 1:
                                scratch_l[env, s0 + k * stride] = acc
                            if use_lambda != 0 and it == newton_steps - 1:
                                lam[env, cons] = lam[env, cons] + acc
                            node_k = chain_node[nb + k * stride]
                            x_k = wp.tile_extract(xs, node_k - node_start)
                            n_k, len_k = segment_dir(x_k, x_hi)
                            k_k = float(0.0)
                            if len_k > 1.0e-12:
                                k_k = wp.max(-dl_k, 0.0) / len_k
                            if wp.static(MASKED):
                                if active[env, cons] == 0:
                                    n_k = wp.vec3(0.0)  # a removed link: the nodes beside it are free ends
                            w_row = wp.tile_extract(ws, node_hi - node_start)
                            lo, diag, up, rhs_j, par = node_row(n_k, dl_k, k_k, n_hi, dl_hi, k_hi, w_row, row)
                            inv = 1.0 / (diag - up * ct_hi)
                            ct = lo * inv
                            dt = (rhs_j - dt_hi * up) * inv
                            x_new = par + x_hi
                            local_row = node_hi - node_start
                            # node k + 1 done: node k is the next step's
                            ct_hi = ct
                            dt_hi = dt
                            dl_hi = dl_k
                            n_hi = n_k
                            k_hi = k_k
                            x_hi = x_k
                            node_hi = node_k
                        wp.tile_scatter_masked(slots, row * L + lane, wp.vec4(ct, dt[0], dt[1], dt[2]), has)
                        wp.tile_scatter_masked(xs, local_row, x_new, has)
                    # node 0 (no link before it: lo = 0)
                    w0 = wp.tile_extract(ws, node_hi - node_start)
                    lo0, diag0, up0, rhs0, par0 = node_row(wp.vec3(0.0), 0.0, 0.0, n_hi, dl_hi, k_hi, w0, 0)
                    inv0 = 1.0 / (diag0 - up0 * ct_hi)
                    dt0 = (rhs0 - dt_hi * up0) * inv0
                    wp.tile_scatter_masked(slots, lane, wp.vec4(0.0, dt0[0], dt0[1], dt0[2]), valid)
                    wp.tile_scatter_masked(xs, node_hi - node_start, par0 + x_hi, valid)

                    # ---- 3. the filter's substitution from the chain's first node: x_j = par_j + y_j --------------
                    y = wp.vec3(0.0)
                    for j in range(mr + 1):
                        has = j <= m and valid
                        local = chain_node[nb + wp.min(j, m) * stride] - node_start
                        moved = False
                        x_new = wp.vec3(0.0)
                        if has:
                            node = wp.tile_extract(slots, j * L + lane)
                            y = wp.vec3(node[1], node[2], node[3]) - y * node[0]
                            moved = wp.tile_extract(ws, local) > 0.0
                            x_new = wp.tile_extract(xs, local) + y
                        wp.tile_scatter_masked(xs, local, x_new, moved)
        wp.tile_store(q[env], xs, offset=node_start)

    kernel = wp.kernel(solve_chains_shared, module="unique", enable_backward=False)
    _KERNELS[key] = kernel
    return kernel
