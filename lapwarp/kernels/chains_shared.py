"""Direct XPBD solve of a whole chain set per env in shared memory: the serial walk of ``kernels/chains.py`` (read its
docstring first), every family of the set in one launch per sweep, a thread block per env.

``chains.solve_chains`` walks each chain with a thread, one launch per family, and every step of its walk waits on a
global load (the next node's position, the scratch it wrote a moment before): on a 40 x 40 cloth at 4,096 envs the
three families take ~80 % of PrecisionCutting's step, bound by the latency of those dependent loads, not by their
bytes. Here a block loads its env's nodes (position and inverse mass) into shared memory once per sweep, its lanes walk
the chains of each family in turn (lane ``i`` the family's chains ``i``, ``i + lanes``, ..; a block barrier between
families, which read the nodes the family before moved), every intermediate value in shared memory (a lane's links'
and nodes' scratch at slot ``k * lanes + lane``), and writes the nodes back at the end. The arithmetic is the serial
walk's, value for value (open chains only: a loop's Sherman-Morrison form is left to ``chains.solve_chains``), so on
the CPU, where a block has one lane that walks every chain in order, the result is bit-identical to it
(``tests/test_chains_shared.py``).

Shared memory per block: 16 B per node (padded by one element in eight, so that the lanes of a quarter warp reading
the nodes of neighbouring rows of a grid hit distinct banks) and 16 B per scratch slot: a 40 x 40 cloth with 64 lanes
~69 KB. Warp's barrier after every shared write (``tile_scatter_masked``) needs every lane to take it: the walks loop
to the longest chain of their round (the first: a family's chains are stored longest first) and lanes past their own
chain's end write nothing.
"""

# no ``from __future__ import annotations``: the tile arguments' annotations name the kernel's tile lengths, locals of
# the factory, which Warp can evaluate only as objects
import warp as wp

from lapwarp.kernels.chains import node_row, segment_dir

wp.set_module_options({"enable_backward": False})

_KERNELS: dict[tuple[int, int], wp.Kernel] = {}


def padded_slot(t: int) -> int:
    """Shared slot of a chain set's ``t``-th node: one padding element after every eight (see the module docstring)."""
    return t + (t >> 3)


@wp.func
def node_slot(t: int):
    return t + (t >> 3)


def shared_chain_kernel(node_slots: int, scratch_slots: int) -> wp.Kernel:
    """The shared-memory solve for chain sets of at most ``node_slots`` padded nodes (``padded_slot(nodes - 1) + 1``)
    and ``scratch_slots`` = (longest chain's links + 1) x lanes (cached per pair): launch ``(num_envs, lanes)`` with
    ``block_dim=lanes`` (``launching.block_lanes``), once per sweep."""
    NP, NS = max(int(node_slots), 1), max(int(scratch_slots), 1)
    cached = _KERNELS.get((NP, NS))
    if cached is not None:
        return cached

    @wp.func
    def node_x(xw: wp.tile(dtype=wp.vec4, shape=(NP,), storage="shared"), t: int):
        """Node ``t``'s (shared slot) position."""
        v = wp.tile_extract(xw, t)
        return wp.vec3(v[0], v[1], v[2])

    def solve_chains_shared(
        families: int,
        family_first: wp.array(dtype=wp.int32),
        family_count: wp.array(dtype=wp.int32),
        family_link_base: wp.array(dtype=wp.int32),
        family_node_base: wp.array(dtype=wp.int32),
        chain_edge_count: wp.array(dtype=wp.int32),
        chain_slot: wp.array(dtype=wp.int32),
        chain_constraint: wp.array(dtype=wp.int32),
        set_particles: wp.array(dtype=wp.int32),
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
        lanes = wp.block_dim()
        pe = env % inv_mass.shape[0]
        ce = env % compliance.shape[0]
        masked = active.shape[1] > 0
        count = set_particles.shape[0]
        xw = wp.tile_zeros(shape=NP, dtype=wp.vec4, storage="shared")  # per node: position, inverse mass
        # per (link or node, lane): the forward walk's (c', d') then dl; the node filter's (c, d) over them
        sc = wp.tile_zeros(shape=NS, dtype=wp.vec4, storage="shared")
        for base in range(0, count, lanes):
            t = wp.min(base + lane, count - 1)
            p = set_particles[t]
            x = q[env, p]
            wp.tile_scatter_masked(xw, node_slot(t), wp.vec4(x[0], x[1], x[2], inv_mass[pe, p]), base + lane < count)

        for f in range(families):
            first = family_first[f]
            stride = family_count[f]
            link_base = family_link_base[f]
            node_base = family_node_base[f]
            for round_base in range(0, stride, lanes):
                i = round_base + lane
                mine = i < stride
                if not mine:
                    i = round_base  # walk the round's first chain's indices, write nothing
                m = chain_edge_count[first + i]
                longest = chain_edge_count[first + round_base]  # chains longest first within a family
                nodes = m + 1
                if not mine:
                    m = 0
                    nodes = 0  # past the family's last chain: the lane walks nothing
                s0 = link_base + i
                nb = node_base + i
                for it in range(newton_steps):
                    # ---- forward elimination (Thomas), as chains.solve_chains for an open chain. The walk's global
                    # loads (the next node's slot, the next link's constraint and mask) are issued one link ahead of
                    # their use, so that they are in flight across the barrier of the link before
                    slot_first = chain_slot[nb]
                    x_first = node_x(xw, slot_first)
                    w_first = wp.tile_extract(xw, slot_first)[3]
                    slot_k1 = chain_slot[nb + wp.min(1, m) * stride]
                    x_k1 = node_x(xw, slot_k1)
                    n_cur, len_cur = segment_dir(x_first, x_k1)
                    cons_k = chain_constraint[s0]
                    act_k = int(1)
                    if masked and m > 0:
                        act_k = active[env, cons_k]
                    # node k + 2 and link k + 1, loaded one link ahead
                    slot_ahead = chain_slot[nb + wp.min(2, m) * stride]
                    cons_ahead = chain_constraint[s0 + wp.max(wp.min(1, m - 1), 0) * stride]
                    act_ahead = act_k
                    if masked and m > 1:
                        act_ahead = active[env, cons_ahead]
                    w_k = w_first
                    c_prev = float(0.0)
                    d_prev = float(0.0)
                    a_k = float(0.0)
                    for k in range(longest):
                        walk = k < m
                        w_k1 = float(0.0)
                        n_next = wp.vec3(0.0)
                        len_next = float(0.0)
                        c_k = float(0.0)
                        slot_k2 = slot_k1
                        x_k2 = x_k1
                        cons_next = cons_k
                        act_next = act_k
                        if walk:
                            w_k1 = wp.tile_extract(xw, slot_k1)[3]
                            if k + 1 < m:
                                slot_k2 = slot_ahead
                                x_k2 = node_x(xw, slot_k2)
                                n_next, len_next = segment_dir(x_k1, x_k2)
                                c_k = -w_k1 * wp.dot(n_cur, n_next)
                                cons_next = cons_ahead
                                if masked:
                                    act_next = act_ahead
                                    if act_k == 0 or act_next == 0:
                                        c_k = 0.0  # no coupling across a cut
                                if k + 2 < m:
                                    slot_ahead = chain_slot[nb + (k + 3) * stride]
                                    cons_ahead = chain_constraint[s0 + (k + 2) * stride]
                                    if masked:
                                        act_ahead = active[env, cons_ahead]
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
                                b_k = 1.0
                                rhs = 0.0
                            denom = b_k - a_k * c_prev
                            inv = 1.0 / denom
                            c_prev = c_k * inv
                            d_prev = (rhs - a_k * d_prev) * inv
                            a_k = c_k
                            n_cur = n_next
                            len_cur = len_next
                            w_k = w_k1
                            slot_k1 = slot_k2
                            x_k1 = x_k2
                            cons_k = cons_next
                            act_k = act_next
                        wp.tile_scatter_masked(sc, k * lanes + lane, wp.vec4(c_prev, d_prev, 0.0, 0.0), walk)

                    # ---- back substitution: dl overwrites d'
                    y_next = float(0.0)
                    for kk in range(longest):
                        k = m - 1 - kk
                        walk = kk < m
                        slot = wp.max(k, 0) * lanes + lane
                        if walk:
                            row = wp.tile_extract(sc, slot)
                            y_next = row[1] - row[0] * y_next
                        wp.tile_scatter_masked(sc, slot, wp.vec4(0.0, y_next, 0.0, 0.0), walk)

                    # ---- the transverse filter's forward pass; its rows overwrite the links' slots one by one (link
                    # j's dl is read before node j's row is written) and each node's base point overwrites the node
                    # (no lane reads it again before the backward pass). Node j + 1 and link j loaded a node ahead
                    x_cur = x_first
                    n_prev = wp.vec3(0.0)
                    dl_prev = float(0.0)
                    k_prev = float(0.0)
                    cn_prev = float(0.0)
                    dn_prev = wp.vec3(0.0)
                    slot_j = slot_first
                    slot_ahead = chain_slot[nb + wp.min(1, m) * stride]
                    cons_ahead = chain_constraint[s0]
                    act_ahead = int(1)
                    if masked and m > 0:
                        act_ahead = active[env, cons_ahead]
                    for j in range(longest + 1):
                        walk = j < nodes
                        w_j = float(0.0)
                        n_j = wp.vec3(0.0)
                        dl_j = float(0.0)
                        k_j = float(0.0)
                        x_next = wp.vec3(0.0)
                        slot_next = slot_j
                        base_point = x_cur
                        if walk:
                            if j < m:
                                slot_next = slot_ahead
                                cj = cons_ahead
                                act_j = act_ahead
                                if j + 1 < m:
                                    slot_ahead = chain_slot[nb + (j + 2) * stride]
                                    cons_ahead = chain_constraint[s0 + (j + 1) * stride]
                                    if masked:
                                        act_ahead = active[env, cons_ahead]
                                x_next = node_x(xw, slot_next)
                                n_j, len_j = segment_dir(x_cur, x_next)
                                if masked:
                                    if act_j == 0:
                                        n_j = wp.vec3(0.0)  # a removed segment: the nodes beside it are free ends
                                dl_j = wp.tile_extract(sc, j * lanes + lane)[1]
                                acc = dl_j
                                if it > 0:
                                    acc = scratch_l[env, s0 + j * stride] + dl_j
                                if it < newton_steps - 1:
                                    scratch_l[env, s0 + j * stride] = acc
                                if use_lambda != 0 and it == newton_steps - 1:
                                    lam[env, cj] = lam[env, cj] + acc
                                if j + 1 < nodes and len_j > 1.0e-12:
                                    k_j = wp.max(-dl_j, 0.0) / len_j
                            w_j = wp.tile_extract(xw, slot_j)[3]
                            lo, diag, up, rhs_j, par = node_row(n_prev, dl_prev, k_prev, n_j, dl_j, k_j, w_j, j)
                            inv = 1.0 / (diag - lo * cn_prev)
                            cn_prev = up * inv
                            dn_prev = (rhs_j - dn_prev * lo) * inv
                            base_point = par + x_cur
                        wp.tile_scatter_masked(sc, j * lanes + lane, wp.vec4(cn_prev, dn_prev[0], dn_prev[1],
                                                                              dn_prev[2]), walk)
                        wp.tile_scatter_masked(xw, slot_j, wp.vec4(base_point[0], base_point[1], base_point[2], w_j),
                                               walk)
                        if walk:
                            x_cur = x_next
                            slot_j = slot_next
                            n_prev = n_j
                            dl_prev = dl_j
                            k_prev = k_j
                    # ---- its backward pass: q = base point + y where w > 0 (the node before's slot loaded ahead)
                    y = wp.vec3(0.0)
                    slot_ahead = chain_slot[nb + wp.max(nodes - 1, 0) * stride]
                    for jj in range(longest + 1):
                        j = nodes - 1 - jj
                        walk = jj < nodes
                        slot = slot_ahead
                        if j >= 1:
                            slot_ahead = chain_slot[nb + (j - 1) * stride]
                        e = wp.tile_extract(xw, slot)
                        if walk:
                            row = wp.tile_extract(sc, j * lanes + lane)
                            y = wp.vec3(row[1], row[2], row[3]) - y * row[0]
                        write = walk and e[3] > 0.0
                        wp.tile_scatter_masked(xw, slot, wp.vec4(e[0] + y[0], e[1] + y[1], e[2] + y[2], e[3]), write)

        for base in range(0, count, lanes):
            t = wp.min(base + lane, count - 1)
            e = wp.tile_extract(xw, node_slot(t))
            if base + lane < count and e[3] > 0.0:
                q[env, set_particles[t]] = wp.vec3(e[0], e[1], e[2])

    kernel = wp.Kernel(solve_chains_shared, key=f"solve_chains_shared_{NP}_{NS}",
                       module=wp.get_module(f"lapwarp.kernels.chains_shared_{NP}_{NS}"))
    _KERNELS[(NP, NS)] = kernel
    return kernel
