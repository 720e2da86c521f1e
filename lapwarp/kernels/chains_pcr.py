"""The direct chain solve of ``kernels/chains.py`` with one thread block per chain: parallel cyclic reduction (PCR).

``solve_chains`` walks a chain in one thread (Thomas algorithm): for a few short chains per env (RopeCutting's five
19-link ropes: 20k threads at 4,096 envs, each doing 6 Newton steps of ~80 dependent steps per substep) the GPU sits
mostly idle waiting on each thread's chain of dependent loads and divisions. Here a block of ``lanes`` threads solves
one open chain of up to ``lanes - 1`` links: lane ``k`` owns link ``k`` and node ``k``, builds its row of the stretch
system from its own and its neighbours' nodes (exchanged through shared memory), and both tridiagonal systems of a
Newton step (the multipliers' and the transverse filter's, same matrices and right-hand sides as ``solve_chains``)
are solved by PCR (Hockney 1965): ``log2(lanes)`` steps in each of which every row eliminates its neighbours at
distance ``2^s``, after which every row is decoupled. PCR does ``O(m log m)`` work instead of ``O(m)``, but in
``log2(lanes)`` dependent steps instead of ``m``. The matrices are diagonally dominant (stretch: weakly, strictly with
compliance; filter: strictly), so PCR needs no pivoting, as Thomas does not. Results equal ``solve_chains``'s up to
rounding (``tests/test_chains_pcr.py``).

Rows past a chain's end (``k >= m`` links, ``k > m`` nodes) are identity rows with zero right-hand sides, so they
neither act nor couple. Cut links (``active == 0``) and rigid pinned links become identity rows exactly as in
``solve_chains``. Closed chains (loops) are not handled here (the World keeps ``solve_chains`` for a family with a
loop or a chain longer than ``lanes - 1`` links).

On the CPU the block's lanes run as Warp's cooperative fibers (``wp.config.enable_cpu_blocks``, set while the World
records the launch; ``lapwarp.launching.cpu_blocks``), so the same kernel is tested there.
"""

from __future__ import annotations

import warp as wp

from lapwarp.kernels.chains import node_row, segment_dir

wp.set_module_options({"enable_backward": False})

#: the block sizes (threads per chain) with a compiled kernel; a chain of m links needs lanes >= m + 1
PCR_LANES = (32, 64, 128)

_KERNELS: dict = {}


def pcr_lanes_for(max_links: int) -> int:
    """The smallest block that holds a chain of ``max_links`` links (one lane per node), 0 if none does."""
    for lanes in PCR_LANES:
        if max_links + 1 <= lanes:
            return lanes
    return 0


def pcr_chain_kernel(lanes: int):
    """``solve_chains_pcr`` for blocks of ``lanes`` threads (a tile's shape is a compile-time constant: one kernel per
    size, cached). Launch with ``dim = (num_envs, chains_in_family, lanes)`` and ``block_dim = lanes``."""
    kernel = _KERNELS.get(lanes)
    if kernel is not None:
        return kernel
    L = int(lanes)
    steps = L.bit_length() - 1  # log2(L): PCR steps
    if 1 << steps != L:
        raise ValueError(f"PCR lanes must be a power of two, got {lanes}")

    def solve_chains_pcr(
        family_start: int,
        stride: int,
        link_base: int,
        node_base: int,
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
        active: wp.array2d(dtype=wp.int32),
        q: wp.array2d(dtype=wp.vec3),
    ):
        env, i, k = wp.tid()  # k: this lane's link and node
        r = family_start + i
        m = chain_edge_count[r]
        nodes = m + 1
        has_link = k < m
        has_node = k < nodes
        pe = env % inv_mass.shape[0]
        ce = env % compliance.shape[0]
        masked = active.shape[1] > 0
        # this lane's node and link, fixed over the Newton steps
        node = chain_node[node_base + wp.min(k, nodes - 1) * stride + i]
        w = float(0.0)
        if has_node:
            w = inv_mass[pe, node]
        cons = chain_constraint[link_base + wp.min(k, m - 1) * stride + i]
        act = int(0)
        alpha = float(0.0)
        rest_k = float(0.0)
        lam0 = float(0.0)
        if has_link:
            act = 1
            if masked:
                act = active[env, cons]
            alpha = compliance[ce, cons] * inv_dt2
            rest_k = rest[cons]
            if use_lambda != 0:
                lam0 = lam[env, cons]
        acc = float(0.0)  # this sweep's multiplier of the link so far (solve_chains' scratch_l)

        t_xw = wp.tile_zeros(shape=L, dtype=wp.vec4, storage="shared")  # node position, inverse mass
        t_link = wp.tile_zeros(shape=L, dtype=wp.vec4, storage="shared")  # link direction, active / then dl
        t_k = wp.tile_zeros(shape=L, dtype=float, storage="shared")  # link tension weight Lambda / l
        t_s0 = wp.tile_zeros(shape=L, dtype=wp.vec4d, storage="shared")  # PCR rows (a, b, c, d), two buffers
        t_s1 = wp.tile_zeros(shape=L, dtype=wp.vec4d, storage="shared")
        t_v0 = wp.tile_zeros(shape=L, dtype=wp.spatial_vectord, storage="shared")  # (a, b, c, d.xyz)
        t_v1 = wp.tile_zeros(shape=L, dtype=wp.spatial_vectord, storage="shared")
        up_k = wp.min(k + 1, L - 1)
        dn_k = wp.max(k - 1, 0)

        for it in range(newton_steps):
            x = wp.vec3(0.0)
            if has_node:
                x = q[env, node]
            wp.tile_scatter_masked(t_xw, k, wp.vec4(x[0], x[1], x[2], w), True)
            nxt = wp.tile_extract(t_xw, up_k)
            x_next = wp.vec3(nxt[0], nxt[1], nxt[2])
            w_next = nxt[3]
            n_k = wp.vec3(0.0)
            len_k = float(0.0)
            if has_link:
                n_k, len_k = segment_dir(x, x_next)
            wp.tile_scatter_masked(t_link, k, wp.vec4(n_k[0], n_k[1], n_k[2], float(act)), True)
            # row k of (J W J^T + alpha / h^2) dl = -C - alpha / h^2 lambda: A_{k,k+1} = -w_{k+1} n_k . n_{k+1},
            # A_{k,k-1} = -w_k n_{k-1} . n_k, no coupling across a cut
            a = float(0.0)
            b = float(1.0)
            c = float(0.0)
            d = float(0.0)
            if has_link:
                nl = wp.tile_extract(t_link, up_k)
                pl = wp.tile_extract(t_link, dn_k)
                if k + 1 < m and act != 0 and nl[3] != 0.0:
                    c = -w_next * wp.dot(n_k, wp.vec3(nl[0], nl[1], nl[2]))
                if k >= 1 and act != 0 and pl[3] != 0.0:
                    a = -w * wp.dot(wp.vec3(pl[0], pl[1], pl[2]), n_k)
                b = w + w_next + alpha
                d = rest_k - len_k - alpha * (lam0 + acc)
                if b <= 0.0 or act == 0:
                    # both nodes pinned and rigid (empty row) or a removed link: dl = 0
                    b = 1.0
                    d = 0.0
            # ---- PCR on the multipliers' system, in float64: a stretched chain's rows are nearly singular (tension
            # against stiff links), its corrections are differences of nearly equal multipliers, and PCR's float32
            # rounding errors, unlike Thomas's, are not smooth along the chain (measured: a zigzag of 0.3 mm on a rope
            # pre-stretched 5x, where Thomas is within 0.01 mm of a float64 solve)
            pa = wp.float64(a)
            pb = wp.float64(b)
            pc = wp.float64(c)
            pd = wp.float64(d)
            for s in range(steps):
                h = 1 << s
                row = wp.vec4d(pa, pb, pc, pd)
                lo = wp.vec4d(wp.float64(0.0), wp.float64(1.0), wp.float64(0.0), wp.float64(0.0))
                hi = wp.vec4d(wp.float64(0.0), wp.float64(1.0), wp.float64(0.0), wp.float64(0.0))
                if s % 2 == 0:
                    wp.tile_scatter_masked(t_s0, k, row, True)
                    if k - h >= 0:
                        lo = wp.tile_extract(t_s0, k - h)
                    if k + h < L:
                        hi = wp.tile_extract(t_s0, k + h)
                else:
                    wp.tile_scatter_masked(t_s1, k, row, True)
                    if k - h >= 0:
                        lo = wp.tile_extract(t_s1, k - h)
                    if k + h < L:
                        hi = wp.tile_extract(t_s1, k + h)
                al = -pa / lo[1]
                ga = -pc / hi[1]
                pa = al * lo[0]
                pc = ga * hi[2]
                pb = pb + al * lo[2] + ga * hi[0]
                pd = pd + al * lo[3] + ga * hi[3]
            dl = float(pd / pb)
            if not has_link:
                dl = 0.0
            acc = acc + dl
            if use_lambda != 0 and it == newton_steps - 1 and has_link:
                lam[env, cons] = lam0 + acc

            # ---- node rows of the transverse filter (solve_chains' node_row), from links k - 1 and k
            n_eff = n_k
            if act == 0:
                n_eff = wp.vec3(0.0)  # a removed link: the nodes beside it are free ends
            k_w = float(0.0)
            if has_link and len_k > 1.0e-12:
                k_w = wp.max(-dl, 0.0) / len_k
            wp.tile_scatter_masked(t_link, k, wp.vec4(n_eff[0], n_eff[1], n_eff[2], dl), True)
            wp.tile_scatter_masked(t_k, k, k_w, True)
            va = float(0.0)
            vb = float(1.0)
            vc = float(0.0)
            vd = wp.vec3(0.0)
            par = wp.vec3(0.0)
            if has_node:
                n_prev = wp.vec3(0.0)
                dl_prev = float(0.0)
                k_prev = float(0.0)
                if k >= 1:
                    pn = wp.tile_extract(t_link, k - 1)
                    n_prev = wp.vec3(pn[0], pn[1], pn[2])
                    dl_prev = pn[3]
                    k_prev = wp.tile_extract(t_k, k - 1)
                va, vb, vc, vd, par = node_row(n_prev, dl_prev, k_prev, n_eff, dl, k_w, w, k)
            # ---- PCR on the filter's system (vec3 right-hand side), in float64 as above
            fa = wp.float64(va)
            fb = wp.float64(vb)
            fc = wp.float64(vc)
            fd = wp.vec3d(wp.float64(vd[0]), wp.float64(vd[1]), wp.float64(vd[2]))
            zero = wp.float64(0.0)
            one = wp.float64(1.0)
            for s in range(steps):
                h = 1 << s
                vrow = wp.spatial_vectord(fa, fb, fc, fd[0], fd[1], fd[2])
                vlo = wp.spatial_vectord(zero, one, zero, zero, zero, zero)
                vhi = wp.spatial_vectord(zero, one, zero, zero, zero, zero)
                if s % 2 == 0:
                    wp.tile_scatter_masked(t_v0, k, vrow, True)
                    if k - h >= 0:
                        vlo = wp.tile_extract(t_v0, k - h)
                    if k + h < L:
                        vhi = wp.tile_extract(t_v0, k + h)
                else:
                    wp.tile_scatter_masked(t_v1, k, vrow, True)
                    if k - h >= 0:
                        vlo = wp.tile_extract(t_v1, k - h)
                    if k + h < L:
                        vhi = wp.tile_extract(t_v1, k + h)
                al = -fa / vlo[1]
                ga = -fc / vhi[1]
                fa = al * vlo[0]
                fc = ga * vhi[2]
                fb = fb + al * vlo[2] + ga * vhi[0]
                fd = fd + al * wp.vec3d(vlo[3], vlo[4], vlo[5]) + ga * wp.vec3d(vhi[3], vhi[4], vhi[5])
            yd = fd / fb
            y = wp.vec3(float(yd[0]), float(yd[1]), float(yd[2]))
            if has_node and w > 0.0:
                q[env, node] = x + par + y

    kernel = wp.kernel(solve_chains_pcr, module="unique", enable_backward=False)
    _KERNELS[lanes] = kernel
    return kernel
