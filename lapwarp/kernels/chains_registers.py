"""Direct XPBD solve of short open chains of distance constraints, one thread per (env, chain) with the whole chain in
registers: the serial walk of ``kernels/chains.py`` (read its docstring first) with its loops unrolled to a
compile-time chain length.

The serial walk (``chains.solve_chains``) keeps its per-link and per-node intermediates (modified super-diagonals and
right-hand sides, the filter's rows) in global scratch and reads the positions again at every Newton step: four walks
over the chain per Newton step, each link waiting on a few dependent loads (its loop count is a run-time value, so
nothing is issued ahead). A task with a few short ropes per env (RopeCutting: five 19-link ropes, 4 Newton steps at 40
substeps) launches only ~5 threads per env, too few to hide that latency: the walk took 63 % of RopeCutting's step
(H100, 4,096 envs, ``benchmarks/results/session28``). Here the chain's node positions and inverse masses, its links'
constants (rest length, compliance, mask bit, earlier sweeps' multiplier), this sweep's multipliers and the
eliminations' rows live in Warp vectors and matrices indexed by the constants of unrolled loops (``max_links`` is a
closure constant, so Warp unrolls ``range(L)``; ``max_unroll`` is raised for these kernels' modules), i.e. in
registers: a thread loads its chain once per launch, runs every Newton step without touching memory, and stores the
moved nodes and the multipliers at the end.

The arithmetic is the serial walk's, operation for operation, so the result is bit-identical to it on the CPU
(``tests/test_chains_registers.py``). Chains shorter than ``max_links`` run the same unrolled code with the links past
their end predicated off. Open chains only: a loop's Sherman-Morrison terms would cost another vector of registers
for every chain, so a family with a closed chain keeps the serial walk (``World.chain_solver = "registers"``
chooses per family of chains; so does a family with a chain longer than ``MAX_LINKS``).

Measured (expert, 4,096 envs, H200, same call, thirty-third session): RopeCutting 306,287 env-steps/s against 273,906
for the serial walk (its GPU default since), ThreadInHole 95,635 against 95,427, the free 40 x 40 cloth 30,635 against
65,184: from 8 links on the rows spill (sm_90: 1,760 B per thread at 19 links, 4,696 B at 39,
``benchmarks/kernel_resources.py --registers``), and the cloth's 164k threads per family move more through those
spills than the walk does through its scratch. A family of equal chains takes the ``exact`` variant (forty-fourth
session: RopeCutting 331.1k -> 450.4k env-steps/s, its 19-link spill frame 1,760 -> 672 B), and on CUDA RopeCutting
splits each chain between two threads (``kernels/chains_split.py``: 568.7k).
"""

# no ``from __future__ import annotations``: the kernel's annotations name the factory's vector types, locals of the
# factory, which Warp can evaluate only as objects
import warp as wp

from lapwarp.kernels.chains import check_newton_tolerance, node_row, segment_dir

wp.set_module_options({"enable_backward": False})

#: the longest chain (links) the kernel takes (LigatingLoop's rod has 49): from 8 links on, its rows no longer fit 255
#: registers and spill to (per-thread, coalesced, cached) local memory; past this the unrolled code only grows
MAX_LINKS = 64

@wp.func
def link_bit(lo: int, hi: int, k: int) -> int:
    """Bit ``k`` of the 64-bit set ``(hi, lo)`` (``k`` a constant of an unrolled loop: the branch folds)."""
    if k < 32:
        return (lo >> k) & 1
    return (hi >> (k - 32)) & 1


@wp.func
def eliminate_link(w_k: float, w_k1: float, alpha: float, residual: float, lam_k: float, active: int, c_k: float,
                   a_k: float, c_prev: float, d_prev: float):
    """One link of a chain's forward (Thomas) elimination, the register and split solves': its row ``a_k dl_{k-1} +
    (w_k + w_{k+1} + alpha) dl_k + c_k dl_{k+1} = residual - alpha lam_k`` (``residual = -C_k``; both nodes pinned and
    rigid, an empty row, or a removed link: the identity with a zero right-hand side) against the previous row's
    modified super-diagonal and right-hand side: this row's ``(c, d)``."""
    b_k = w_k + w_k1 + alpha
    rhs = residual - alpha * lam_k
    if b_k <= 0.0 or active == 0:
        b_k = 1.0
        rhs = 0.0
    inv = 1.0 / (b_k - a_k * c_prev)
    return c_k * inv, (rhs - a_k * d_prev) * inv


@wp.func
def eliminate_node(n_prev: wp.vec3, dl_prev: float, k_prev: float, n_j: wp.vec3, dl_j: float, k_j: float, w_j: float,
                   j: int, cn_prev: float, dn_prev: wp.vec3):
    """One node of the transverse filter's forward elimination, the register and split solves': its row
    (``chains.node_row``) against the previous row's modified super-diagonal and right-hand side: this row's ``(c,
    d)`` and the node's part along the tangent."""
    lo, diag, up, rhs_j, par = node_row(n_prev, dl_prev, k_prev, n_j, dl_j, k_j, w_j, j)
    inv = 1.0 / (diag - lo * cn_prev)
    return up * inv, (rhs_j - dn_prev * lo) * inv, par


# the kernels by (chain length in links, Newton tolerance, every chain exactly that long)
_KERNELS: dict[tuple[int, float, bool], wp.Kernel] = {}


def register_chain_kernel(max_links: int, newton_tolerance: float = 0.0, exact: bool = False) -> wp.Kernel:
    """The register-resident solve of open chains of at most ``max_links`` links (cached): launch ``(num_envs,
    chains of the family)`` with ``chains.solve_chains``'s arguments (its scratch arrays go unused).

    ``exact`` (compile-time): every chain of the family has exactly ``max_links`` links, so the chain length is a
    constant and the unrolled links' guards (``k < m``) fold away. Same arithmetic; at 19 links (RopeCutting's ropes)
    the spill frame shrinks from 1,760 to 672 B, at 10 from 512 B to none (sm_90, ``benchmarks/kernel_resources.py``).

    ``newton_tolerance`` (m, 0 = off): a chain stops its Newton steps once one has corrected none of its links by
    that much or more (a link's correction ``|dl_k| (w_k + w_{k+1})``, the length change its own row asks for), the
    step itself applied. The next step would correct by far less (RopeCutting's 5x pre-stretched ropes: each step
    ~10x less than the one before, CPU), so the result stays within about the tolerance of running every step. A
    compile-time constant: 0 compiles the check away. Measured slower where timed (RopeCutting, H200: 318.2k
    env-steps/s without, 286.9k at 1e-7 m: the check grows the spill frame of 19 links from 1,760 to 1,920 B)."""
    L = int(max_links)
    if not 1 <= L <= MAX_LINKS:
        raise ValueError(f"the register chain solve takes chains of 1..{MAX_LINKS} links, got {max_links!r}")
    tol = check_newton_tolerance(newton_tolerance)
    EXACT = bool(exact)
    cached = _KERNELS.get((L, tol, EXACT))
    if cached is not None:
        return cached
    N = L + 1  # nodes of the longest chain
    L_1 = L - 1  # loop bounds and index caps as plain names: Warp unrolls a range of a constant name only
    vec_l = wp.types.vector(length=L, dtype=float)
    vec_n = wp.types.vector(length=N, dtype=float)
    mat_n3 = wp.types.matrix(shape=(N, 3), dtype=float)

    def solve_chains_in_registers(
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
        r = family_start + i
        s0 = link_base + i  # link k at s0 + k * stride, node j at nb + j * stride (chains.py's interleaved layout)
        nb = node_base + i
        m = chain_edge_count[r]
        if wp.static(EXACT):
            m = L  # a constant: the guards below fold (the load above is dead)
        nodes = m + 1
        pe = env % inv_mass.shape[0]
        ce = env % compliance.shape[0]
        masked = active.shape[1] > 0
        # the chain's nodes, once per launch (every load issued ahead: the loop is unrolled)
        x = mat_n3()
        w = vec_n()
        for j in range(N):
            if j < nodes:
                node = chain_node[nb + j * stride]
                x[j] = q[env, node]
                w[j] = inv_mass[pe, node]
        # the links' constants, once per launch too: read inside the Newton loop, their loop-invariant addresses were
        # hoisted out of it by the compiler, ~8 registers a link (sm_90: 218 registers at 4 links)
        rest_v = vec_l()
        alpha_v = vec_l()
        lam0 = vec_l()  # the multipliers of earlier sweeps
        acts_lo = int(0)  # bit k of lo (k < 32) or k - 32 of hi: link k is active (not cut)
        acts_hi = int(0)
        for k in range(L):
            if k < m:
                cons = chain_constraint[s0 + k * stride]
                rest_v[k] = rest[cons]
                alpha_v[k] = compliance[ce, cons] * inv_dt2
                if use_lambda != 0:
                    lam0[k] = lam[env, cons]
                if not masked or active[env, cons] != 0:
                    if k < 32:
                        acts_lo = acts_lo | (1 << k)
                    else:
                        acts_hi = acts_hi | (1 << (k - 32))
        acc = vec_l()  # this sweep's multipliers so far (the serial walk's scratch_l)
        for it in range(newton_steps):
            # ---- forward elimination (Thomas): modified super-diagonals cp and right-hand sides dp
            cp = vec_l()
            dp = vec_l()
            n_cur, len_cur = segment_dir(x[0], x[1])
            c_prev = float(0.0)
            d_prev = float(0.0)
            a_k = float(0.0)  # sub-diagonal A_{k,k-1}
            for k in range(L):
                if k < m:
                    w_k1 = w[k + 1]
                    act_k = link_bit(acts_lo, acts_hi, k)
                    n_next = wp.vec3(0.0)
                    len_next = float(0.0)
                    c_k = float(0.0)
                    if k + 1 < m:
                        # k + 2 <= L here; the cap keeps the unrolled copy of the last link (never run) in range
                        n_next, len_next = segment_dir(x[k + 1], x[wp.min(k + 2, L)])
                        c_k = -w_k1 * wp.dot(n_cur, n_next)
                        if act_k == 0 or link_bit(acts_lo, acts_hi, k + 1) == 0:
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
            # ---- back substitution: dp becomes dl
            y_next = float(0.0)
            largest = float(0.0)  # the step's largest link correction (only with a tolerance)
            for kk in range(L):
                k = L_1 - kk
                if k < m:
                    y_next = dp[k] - cp[k] * y_next
                    dp[k] = y_next
                    if wp.static(tol > 0.0):
                        largest = wp.max(largest, wp.abs(y_next) * (w[k] + w[k + 1]))
            # ---- the transverse filter (chains.py: the implicit geometric-stiffness smoothing of dx's transverse
            # part), rows formed from the positions before this step's update; a node's position takes its part
            # along the tangent as soon as its row is formed (no later row reads it), the filtered rest below
            n_prev = wp.vec3(0.0)
            dl_prev = float(0.0)
            k_prev = float(0.0)
            cn_prev = float(0.0)
            dn_prev = wp.vec3(0.0)
            nc = vec_n()
            nd = mat_n3()
            for j in range(N):
                if j < nodes:
                    n_j = wp.vec3(0.0)
                    dl_j = float(0.0)
                    k_j = float(0.0)
                    if j < m:
                        n_j, len_j = segment_dir(x[j], x[wp.min(j + 1, L)])
                        jl = wp.min(j, L_1)
                        if link_bit(acts_lo, acts_hi, jl) == 0:
                            n_j = wp.vec3(0.0)  # a removed segment: the nodes beside it are free ends
                        dl_j = dp[jl]
                        total = dl_j
                        if it > 0:
                            total = acc[jl] + dl_j
                        acc[jl] = total
                        if j + 1 < nodes and len_j > 1.0e-12:
                            k_j = wp.max(-dl_j, 0.0) / len_j
                    cn_prev, dn_prev, par = eliminate_node(n_prev, dl_prev, k_prev, n_j, dl_j, k_j, w[j], j, cn_prev,
                                                           dn_prev)
                    nc[j] = cn_prev
                    nd[j] = dn_prev
                    if w[j] > 0.0:
                        x[j] = par + x[j]
                    n_prev = n_j
                    dl_prev = dl_j
                    k_prev = k_j
            y = wp.vec3(0.0)
            for jj in range(N):
                j = L - jj
                if j < nodes:
                    y = nd[j] - y * nc[j]
                    if w[j] > 0.0:
                        x[j] = x[j] + y
            if wp.static(tol > 0.0):
                if largest < tol:
                    break  # converged: this step's update applied, the next would move the chain by far less
        # the moved nodes and this sweep's multipliers, once per launch
        for j in range(N):
            if j < nodes:
                if w[j] > 0.0:
                    q[env, chain_node[nb + j * stride]] = x[j]
        if use_lambda != 0 and newton_steps > 0:
            for k in range(L):
                if k < m:
                    cons = chain_constraint[s0 + k * stride]
                    lam[env, cons] = lam0[k] + acc[k]

    kernel = wp.kernel(solve_chains_in_registers, module="unique", enable_backward=False,
                       module_options={"max_unroll": N})
    _KERNELS[(L, tol, EXACT)] = kernel
    return kernel


def family_kernel(cs, first: int, count: int, newton_tolerance: float = 0.0) -> wp.Kernel | None:
    """The register solve for the chains ``first .. first + count - 1`` of a ``chains.ChainSet`` (one family), or
    ``None`` where it does not take them (a closed chain, or one longer than ``MAX_LINKS``): the serial walk then.
    Chains all of one length take the ``exact`` variant."""
    lengths = cs.lengths[first:first + count]
    if count == 0 or cs.closed_host[first:first + count].any() or int(lengths.max()) > MAX_LINKS:
        return None
    return register_chain_kernel(int(lengths.max()), newton_tolerance, exact=bool(lengths.min() == lengths.max()))


def is_register_kernel(kernel) -> bool:
    """Whether ``kernel`` is one of this module's solves (launched in small blocks, like the serial walk)."""
    return any(kernel is k for k in _KERNELS.values())
