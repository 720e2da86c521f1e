"""Direct XPBD solve of open chains of equal length with two threads per chain, each holding half of it in registers:
``chains_registers.py``'s solve (read its docstring and ``chains.py``'s first) split at the middle, the Thomas
eliminations run from both ends towards it ("burn at both ends").

The register solve gives each chain one thread. RopeCutting's five 19-link ropes per env are 20,480 threads at 4,096
envs, ~5 warps per SM, each walking 4 Newton steps x 4 serial passes over its chain with a 672-byte spill frame
(sm_90, ``benchmarks/kernel_resources.py``): latency-bound, the step's largest kernel. Here thread 0 of a pair holds
links ``0 .. HA - 1`` and nodes ``0 .. HA - 1`` (``HA = ceil(L / 2)``), thread 1 the links ``HA .. L - 1`` and nodes
``HA .. L`` in reverse order, so both run the same unrolled code on a chain of their own that starts at a chain end
(a reversed chain's rows are the same: a coupling ``-w n_k . n_k+1`` keeps its sign when both directions flip):

1. forward elimination of each half's link rows; the last row of each half couples to the other's last
   (``x_a + c_a x_b = d_a``, ``x_b + c_b x_a = d_b``), exchanged through shared memory and solved as a 2 x 2 system by
   both threads in the same order (the same bits on both); back substitution down each half;
2. the transverse filter's node rows the same way (the middle link's terms, formed by both threads from the same
   values);
3. each thread publishes its two nodes next to the middle, which the other reads as ghosts for the next step's rows.

Three block barriers per Newton step (a pair's two threads sit side by side in one block of ``BLOCK`` lanes; each
exchange has its own shared tile, so no thread writes one before its partner has read it). Each half is half the serial
chain and half the registers; the arithmetic is the register solve's in another elimination order, so the result
agrees to round-off, not bit for bit (``tests/test_chains_split.py``). Every chain of the family must have the same
length ``L >= 2`` (``World.chain_register_split`` falls back to the register solve elsewhere). With a Newton tolerance
each chain stops as the register solve's does (its later steps computed with its block's but not applied), and a block
leaves its loop once all its chains have stopped. On the CPU the pairs' threads are Warp's cooperative fibers
(``wp.config.enable_cpu_blocks``).

Measured (RopeCutting, expert, 4,096 envs, H200, same calls, forty-fourth session; ``benchmarks/RESULTS.md``): the
one-thread register solve (its exact-length variant) 450.4k env-steps/s, this kernel uncapped 489.0k (235 registers:
1,280 warps in 1.2 waves of 8 per SM), at 200 registers 486.6k (still 8 per SM: a warp's registers come from one of
the SM's four 16,384-register sub-partitions, 2 warps each at 169-200 registers; 176 / 184: 479k / 481k, forty-fifth
session), at **168 568.7k / 568.4k / 569.1k** (3 warps per sub-partition: one wave of 12 per SM; RopeCutting's CUDA
default), at 144 558.0k, at 128 548.2k.
"""

# no ``from __future__ import annotations``: the kernel's annotations name the factory's vector types, locals of the
# factory, which Warp can evaluate only as objects
import warp as wp

from lapwarp.kernels.chains import check_newton_tolerance, segment_dir
from lapwarp.kernels.chains_block import vec6
from lapwarp.kernels.chains_registers import eliminate_link, eliminate_node, link_bit

wp.set_module_options({"enable_backward": False})

#: the longest chain (links) the kernel takes: a half's links and the other half's last one in one 32-bit mask
MAX_LINKS = 62
#: lanes per block: 16 chains' pairs (a pair's threads must share a block for their exchanges)
BLOCK = 32

# the kernels by (chain length in links, Newton tolerance)
_KERNELS: dict[tuple[int, float], wp.Kernel] = {}


def split_chain_kernel(links: int, newton_tolerance: float = 0.0) -> wp.Kernel:
    """The two-threads-per-chain solve of open chains of exactly ``links`` links (cached): launch ``(blocks, BLOCK)``
    with ``block_dim=BLOCK``, ``blocks = ceil(2 num_envs chains / BLOCK)`` (:func:`launch_dim`), with
    ``chains.solve_chains``'s arguments (its scratch arrays go unused).

    ``newton_tolerance`` (m, compile-time; 0 = off): ``chains_registers.register_chain_kernel``'s rule per chain (a
    chain whose step corrected none of its links by that much stops after that step; the pair's two halves decide
    together), so a chain's result does not depend on the others in its block; the block leaves its Newton loop once
    all its chains have stopped (a fourth barrier per step: a block maximum)."""
    L = int(links)
    if not 2 <= L <= MAX_LINKS:
        raise ValueError(f"the split chain solve takes chains of 2..{MAX_LINKS} links, got {links!r}")
    tol = check_newton_tolerance(newton_tolerance)
    cached = _KERNELS.get((L, tol))
    if cached is not None:
        return cached
    HA = (L + 1) // 2  # links of thread 0's half (thread 1: L - HA)
    HB = L - HA
    H = HA  # the unrolled link bound
    NH = max(HA, HB + 1)  # the unrolled own-node bound (thread 0 holds HA nodes, thread 1 HB + 1)
    S = NH + 2  # node slots: the own nodes, then two of the other half's (ghosts)
    L_1 = L - 1
    vec_h = wp.types.vector(length=H, dtype=float)
    vec_s = wp.types.vector(length=S, dtype=float)
    mat_s3 = wp.types.matrix(shape=(S, 3), dtype=float)

    def solve_chains_split(
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
        blk, lane = wp.tid()
        pairs = q.shape[0] * stride
        pair = blk * (BLOCK // 2) + lane // 2
        real = pair < pairs  # the last block's extra pairs repeat the last chain's solve and store nothing
        pair = wp.min(pair, pairs - 1)
        env = pair // stride
        i = pair - env * stride
        side = lane & 1
        partner = lane ^ 1
        s0 = link_base + i  # link k at s0 + k * stride, node j at nb + j * stride (chains.py's interleaved layout)
        nb = node_base + i
        pe = env % inv_mass.shape[0]
        ce = env % compliance.shape[0]
        masked = active.shape[1] > 0
        h = HA  # own links, then own nodes
        nn = HA
        if side == 1:
            h = HB
            nn = HB + 1
        # local node j is chain node j (thread 0) or L - j (thread 1); local link k is link k or L - 1 - k
        x = mat_s3()
        w = vec_s()
        for j in range(S):
            if j <= L:
                g = j
                if side == 1:
                    g = L - j
                node = chain_node[nb + g * stride]
                x[j] = q[env, node]
                w[j] = inv_mass[pe, node]
        rest_v = vec_h()
        alpha_v = vec_h()
        lam0 = vec_h()
        acts = int(0)  # bit k: local link k (k <= h, the other half's last link included) is active
        for k in range(H + 1):
            if k <= L_1 and k <= h:
                gk = k
                if side == 1:
                    gk = L_1 - k
                cons = chain_constraint[s0 + gk * stride]
                if k < h:
                    kk = wp.min(k, H - 1)
                    rest_v[kk] = rest[cons]
                    alpha_v[kk] = compliance[ce, cons] * inv_dt2
                    if use_lambda != 0:
                        lam0[kk] = lam[env, cons]
                if not masked or active[env, cons] != 0:
                    acts = acts | (1 << k)
        up_link = wp.tile_zeros(shape=BLOCK, dtype=vec6, storage="shared")  # each half's last link row
        up_node = wp.tile_zeros(shape=BLOCK, dtype=vec6, storage="shared")  # ... and last node row
        ghosts = wp.tile_zeros(shape=BLOCK, dtype=vec6, storage="shared")  # each half's two nodes by the middle
        if wp.static(tol > 0.0):
            busy = wp.tile_zeros(shape=BLOCK, dtype=float, storage="shared")  # 1: the lane's chain still iterates
        running = int(1)  # 0 once the chain has converged: its later steps are computed (the block's) but not applied
        acc = vec_h()  # this sweep's multipliers so far (own links)
        for it in range(newton_steps):
            # ---- forward elimination of the own link rows (Thomas); the last couples to the other half's last
            cp = vec_h()
            dp = vec_h()
            n_cur, len_cur = segment_dir(x[0], x[1])
            c_prev = float(0.0)
            d_prev = float(0.0)
            a_k = float(0.0)
            for k in range(H):
                if k < h:
                    w_k1 = w[k + 1]
                    act_k = link_bit(acts, 0, k)
                    n_next, len_next = segment_dir(x[k + 1], x[k + 2])
                    c_k = -w_k1 * wp.dot(n_cur, n_next)
                    if act_k == 0 or link_bit(acts, 0, k + 1) == 0:
                        c_k = 0.0  # no coupling across a cut
                    lam_k = lam0[k]
                    if it > 0:
                        lam_k = lam_k + acc[k]
                    c_prev, d_prev = eliminate_link(w[k], w_k1, alpha_v[k], rest_v[k] - len_cur, lam_k, act_k, c_k,
                                                    a_k, c_prev, d_prev)
                    cp[k] = c_prev
                    dp[k] = d_prev
                    a_k = c_k
                    n_cur = n_next
                    len_cur = len_next
            # ---- the middle: x_a + c_a x_b = d_a, x_b + c_b x_a = d_b, solved by both threads in thread 0's order
            wp.tile_scatter_masked(up_link, lane, vec6(c_prev, d_prev, 0.0, 0.0, 0.0, 0.0), True)
            other = wp.tile_extract(up_link, partner)
            c_a = c_prev
            d_a = d_prev
            c_b = other[0]
            d_b = other[1]
            if side == 1:
                c_a = other[0]
                d_a = other[1]
                c_b = c_prev
                d_b = d_prev
            x_a = (d_a - c_a * d_b) / (1.0 - c_a * c_b)
            x_b = d_b - c_b * x_a
            dl_me = x_a
            dl_other = x_b  # the other half's last link, the ghost link of thread 1's last node row
            if side == 1:
                dl_me = x_b
                dl_other = x_a
            # ---- back substitution down the own rows: dp becomes dl
            y_next = dl_me
            largest = float(0.0)  # the step's largest correction of an own link (only with a tolerance)
            for kk in range(H):
                k = H - 1 - kk
                if k < h - 1:
                    y_next = dp[k] - cp[k] * y_next
                    dp[k] = y_next
                elif k == h - 1:
                    dp[k] = dl_me
                if wp.static(tol > 0.0):
                    if k < h:
                        largest = wp.max(largest, wp.abs(dp[k]) * (w[k] + w[k + 1]))
            # ---- the transverse filter over the own nodes (chains_registers' order within each half); a node's
            # tangential part applied as its row is formed
            n_prev = wp.vec3(0.0)
            dl_prev = float(0.0)
            k_prev = float(0.0)
            cn_prev = float(0.0)
            dn_prev = wp.vec3(0.0)
            nc = vec_s()
            nd = mat_s3()
            for j in range(NH):
                if j < nn:
                    n_j, len_j = segment_dir(x[j], x[j + 1])
                    if link_bit(acts, 0, j) == 0:
                        n_j = wp.vec3(0.0)  # a removed segment: the nodes beside it are free ends
                    dl_j = dl_other  # the other half's last link (thread 1's last node only)
                    if j < h:
                        jl = wp.min(j, H - 1)
                        dl_j = dp[jl]
                        total = dl_j
                        if it > 0:
                            total = acc[jl] + dl_j
                        if running != 0:
                            acc[jl] = total
                    k_j = float(0.0)
                    if len_j > 1.0e-12:
                        k_j = wp.max(-dl_j, 0.0) / len_j
                    cn_prev, dn_prev, par = eliminate_node(n_prev, dl_prev, k_prev, n_j, dl_j, k_j, w[j], j, cn_prev,
                                                           dn_prev)
                    nc[j] = cn_prev
                    nd[j] = dn_prev
                    if w[j] > 0.0 and running != 0:
                        x[j] = par + x[j]
                    n_prev = n_j
                    dl_prev = dl_j
                    k_prev = k_j
            # (the spare slot: this half's largest link correction, for the pair's decision below)
            wp.tile_scatter_masked(up_node, lane, vec6(cn_prev, dn_prev[0], dn_prev[1], dn_prev[2], largest, 0.0),
                                   True)
            on = wp.tile_extract(up_node, partner)
            cn_a = cn_prev
            dn_a = dn_prev
            cn_b = on[0]
            dn_b = wp.vec3(on[1], on[2], on[3])
            if side == 1:
                cn_a = on[0]
                dn_a = wp.vec3(on[1], on[2], on[3])
                cn_b = cn_prev
                dn_b = dn_prev
            y_a = (dn_a - dn_b * cn_a) / (1.0 - cn_a * cn_b)
            y = y_a
            if side == 1:
                y = dn_b - y_a * cn_b
            for jj in range(NH):
                j = NH - 1 - jj
                if j < nn:
                    if j < nn - 1:
                        y = nd[j] - y * nc[j]
                    if w[j] > 0.0 and running != 0:
                        x[j] = x[j] + y
            # ---- the two nodes by the middle to the other half (its ghosts, slots nn and nn + 1)
            last = wp.vec3(0.0)
            second = wp.vec3(0.0)
            for j in range(NH):
                if j == nn - 1:
                    last = x[j]
                if j == nn - 2:
                    second = x[j]
            wp.tile_scatter_masked(ghosts, lane, vec6(last[0], last[1], last[2], second[0], second[1], second[2]),
                                   True)
            gh = wp.tile_extract(ghosts, partner)
            for j in range(S):
                if j == nn:
                    x[j] = wp.vec3(gh[0], gh[1], gh[2])
                if j == nn + 1:
                    x[j] = wp.vec3(gh[3], gh[4], gh[5])
            if wp.static(tol > 0.0):
                # the pair stops once neither half corrected a link by tol (this step applied); the block leaves the
                # loop once none of its chains iterates
                if wp.max(largest, on[4]) < tol:
                    running = 0
                wp.tile_scatter_masked(busy, lane, float(running), True)
                if wp.tile_extract(wp.tile_max(busy), 0) == 0.0:
                    break
        # the moved own nodes and this sweep's multipliers of the own links
        if real:
            for j in range(NH):
                if j < nn and w[j] > 0.0:
                    g = j
                    if side == 1:
                        g = L - j
                    q[env, chain_node[nb + g * stride]] = x[j]
            if use_lambda != 0 and newton_steps > 0:
                for k in range(H):
                    if k < h:
                        gk = k
                        if side == 1:
                            gk = L_1 - k
                        lam[env, chain_constraint[s0 + gk * stride]] = lam0[k] + acc[k]

    kernel = wp.kernel(solve_chains_split, module="unique", enable_backward=False,
                       module_options={"max_unroll": S + 1, "block_dim": BLOCK})
    _KERNELS[(L, tol)] = kernel
    return kernel


def launch_dim(num_envs: int, chains: int) -> tuple[int, int]:
    """The launch of a family of ``chains`` chains per env: ``(blocks, BLOCK)``, two lanes per chain."""
    return (-(-2 * int(num_envs) * int(chains) // BLOCK), BLOCK)


def family_kernel(cs, first: int, count: int, newton_tolerance: float = 0.0) -> wp.Kernel | None:
    """The split solve for the chains ``first .. first + count - 1`` of a ``chains.ChainSet`` (one family), or
    ``None`` where it does not take them (a closed chain, chains of different lengths, or a length outside
    ``2 .. MAX_LINKS``)."""
    lengths = cs.lengths[first:first + count]
    if count == 0 or cs.closed_host[first:first + count].any() or lengths.min() != lengths.max():
        return None
    if not 2 <= int(lengths.max()) <= MAX_LINKS:
        return None
    return split_chain_kernel(int(lengths.max()), newton_tolerance)


def is_split_kernel(kernel) -> bool:
    """Whether ``kernel`` is one of this module's solves (launched with :func:`launch_dim`)."""
    return any(kernel is k for k in _KERNELS.values())
