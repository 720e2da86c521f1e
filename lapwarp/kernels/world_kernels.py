"""Kernels that belong to the World itself: per-env RNG seeding, masked state copies, body poses."""

from typing import Any

import warp as wp

from lapwarp.kernels.xpbd import segment_velocity

wp.set_module_options({"enable_backward": False})


@wp.kernel
def init_env_rng(seed: int, rng_out: wp.array(dtype=wp.uint32)):
    env = wp.tid()
    rng_out[env] = wp.rand_init(seed, env)


@wp.kernel
def copy_masked_2d(env_mask: wp.array(dtype=wp.int32), src: wp.array2d(dtype=Any), lanes: int,
                   dst: wp.array2d(dtype=Any)):
    """Copy row ``env % src.shape[0]`` of ``src`` into row ``env`` of ``dst`` for masked envs (any dtype); ``lanes``
    threads per env stride the row (launch ``(num_envs, lanes)``), so an unmasked env costs one thread block's load."""
    env, lane = wp.tid()
    if env_mask[env] == 0:
        return
    for i in range(lane, dst.shape[1], lanes):
        dst[env, i] = src[env % src.shape[0], i]


@wp.kernel
def clear_masked_int(env_mask: wp.array(dtype=wp.int32), flags_out: wp.array(dtype=wp.int32)):
    env = wp.tid()
    if env_mask[env] != 0:
        flags_out[env] = 0


@wp.kernel
def mark_masked_rows(env_mask: wp.array(dtype=wp.int32), flags_out: wp.array2d(dtype=wp.int32)):
    env = wp.tid()
    if env_mask[env] != 0:
        flags_out[env, 0] = 1


@wp.kernel
def write_body_poses(
    poses: wp.array2d(dtype=wp.transform),
    bodies: wp.array(dtype=wp.int32),
    teleport_mask: wp.array(dtype=wp.int32),
    teleport: int,
    body_q: wp.array2d(dtype=wp.transform),
    body_q_prev: wp.array2d(dtype=wp.transform),
    start_body_q: wp.array2d(dtype=wp.transform),
):
    """``body_q[env, bodies[k]] = poses[env, k]``; with ``teleport`` only the masked envs, whose pose at the start of
    the step and start-state pose are set too (no sweep from the old pose after a reset)."""
    env, k = wp.tid()
    b = bodies[k]
    if teleport != 0:
        if teleport_mask[env] == 0:
            return
        body_q_prev[env, b] = poses[env, k]
        start_body_q[env, b] = poses[env, k]
    body_q[env, b] = poses[env, k]


@wp.struct
class StateRows:
    """Every array of a ``lapwarp.model.State`` (absent ones as ``(1, 0)`` placeholders), so one launch copies them
    all (``World.reset`` and ``World.save_start_state`` run every step inside the captured graph)."""

    particle_q: wp.array2d(dtype=wp.vec3)
    particle_qd: wp.array2d(dtype=wp.vec3)
    segment_q: wp.array2d(dtype=wp.quat)
    segment_qd: wp.array2d(dtype=wp.vec3)
    body_q: wp.array2d(dtype=wp.transform)
    attach_particle: wp.array2d(dtype=wp.int32)
    attach_body: wp.array2d(dtype=wp.int32)
    attach_offset: wp.array2d(dtype=wp.vec3)
    attach_compliance: wp.array2d(dtype=float)
    attach_segment: wp.array2d(dtype=wp.int32)
    attach_rotation: wp.array2d(dtype=wp.quat)
    tet_active: wp.array2d(dtype=wp.int32)
    tri_active: wp.array2d(dtype=wp.int32)
    edge_active: wp.array2d(dtype=wp.int32)
    hinge_active: wp.array2d(dtype=wp.int32)
    segment_active: wp.array2d(dtype=wp.int32)
    tet_face_active: wp.array2d(dtype=wp.int32)
    cut_dirty: wp.array2d(dtype=wp.int32)
    particle_active: wp.array2d(dtype=wp.int32)
    geo_dist: wp.array2d(dtype=float)
    geo_source: wp.array2d(dtype=wp.int32)
    geo_anchor: wp.array2d(dtype=wp.int32)
    geo_tri_seen: wp.array2d(dtype=wp.int32)
    geo_status: wp.array2d(dtype=wp.int32)


@wp.func
def copy_element(env: int, i: int, src: wp.array2d(dtype=Any), dst: wp.array2d(dtype=Any)):
    if i < dst.shape[1]:
        dst[env, i] = src[env, i]


@wp.func
def copy_row_elements(env: int, lane: int, lanes: int, width: int, src: StateRows, dst: StateRows,
                      body_q_prev: wp.array2d(dtype=wp.transform), write_body_q_prev: int):
    """Lane ``lane`` of ``lanes``'s share of env ``env``'s rows of every state array, ``src`` -> ``dst``."""
    for i in range(lane, width, lanes):
        copy_element(env, i, src.particle_q, dst.particle_q)
        copy_element(env, i, src.particle_qd, dst.particle_qd)
        copy_element(env, i, src.segment_q, dst.segment_q)
        copy_element(env, i, src.segment_qd, dst.segment_qd)
        copy_element(env, i, src.body_q, dst.body_q)
        copy_element(env, i, src.attach_particle, dst.attach_particle)
        copy_element(env, i, src.attach_body, dst.attach_body)
        copy_element(env, i, src.attach_offset, dst.attach_offset)
        copy_element(env, i, src.attach_compliance, dst.attach_compliance)
        copy_element(env, i, src.attach_segment, dst.attach_segment)
        copy_element(env, i, src.attach_rotation, dst.attach_rotation)
        copy_element(env, i, src.tet_active, dst.tet_active)
        copy_element(env, i, src.tri_active, dst.tri_active)
        copy_element(env, i, src.edge_active, dst.edge_active)
        copy_element(env, i, src.hinge_active, dst.hinge_active)
        copy_element(env, i, src.segment_active, dst.segment_active)
        copy_element(env, i, src.tet_face_active, dst.tet_face_active)
        copy_element(env, i, src.cut_dirty, dst.cut_dirty)
        copy_element(env, i, src.particle_active, dst.particle_active)
        copy_element(env, i, src.geo_dist, dst.geo_dist)
        copy_element(env, i, src.geo_source, dst.geo_source)
        copy_element(env, i, src.geo_anchor, dst.geo_anchor)
        copy_element(env, i, src.geo_tri_seen, dst.geo_tri_seen)
        copy_element(env, i, src.geo_status, dst.geo_status)
        if write_body_q_prev != 0:
            copy_element(env, i, src.body_q, body_q_prev)


@wp.kernel
def copy_state_rows(env_mask: wp.array(dtype=wp.int32), src: StateRows, dst: StateRows,
                    body_q_prev: wp.array2d(dtype=wp.transform), write_body_q_prev: int, width: int, lanes: int):
    """Every array's row of the masked envs, ``src`` -> ``dst`` (and the body poses at the start of the step when
    restoring, so the next step does not sweep bodies from where they were). ``lanes`` threads per env stride the
    rows' elements up to ``width`` (launch ``(num_envs, lanes)``): most envs of most steps are not reset, and one
    thread per (env, element) cost TissueDissection ~0.4 ms per env step at 4,096 envs for nothing."""
    env, lane = wp.tid()
    if env_mask[env] == 0:
        return
    copy_row_elements(env, lane, lanes, width, src, dst, body_q_prev, write_body_q_prev)


@wp.kernel
def check_and_restore(
    max_speed: float,
    restore: int,
    start: StateRows,
    live: StateRows,
    body_q_prev: wp.array2d(dtype=wp.transform),
    write_body_q_prev: int,
    width: int,
    start_rotation: wp.array2d(dtype=wp.quat),
    rotation: wp.array2d(dtype=wp.quat),
    copy_body_q: int,
    finish_inv_dt: float,
    q_pred: wp.array2d(dtype=wp.vec3),
    segment_q_prev: wp.array2d(dtype=wp.quat),
    flags_now: wp.array(dtype=wp.int32),
    unstable: wp.array(dtype=wp.int32),
    hold_quiet: wp.array(dtype=wp.int32),
):
    """``World.check_stability`` in one launch, a thread block per env: an env is unstable when a particle's position
    or velocity is not finite, its speed exceeds ``max_speed`` or it is beyond 10^6 m (``flags_now``, and the sticky
    ``unstable``); with ``restore`` its rows of every state array and its tet rotations go back to the start state
    (the body poses at the start of the step too) and its cut surfaces are marked dirty. Replaces a memset and five
    launches per world step (check, merge, three masked copies) that ran for every env whether or not it failed.
    With ``copy_body_q`` (the end of a world step) it first keeps the body poses as the next step's start
    (``body_q_prev``), which was a copy of its own per world step. With ``finish_inv_dt > 0`` it first runs the
    step's last velocity update (``xpbd.update_particle_velocities`` from ``q_pred``, ``update_segment_velocities``
    from ``segment_q_prev`` where that has columns), which was a launch or two of its own per world step: each lane
    updates the particles it then checks, so no barrier comes between. A restored env's held tets (``hold.TetHold``)
    are solved again (``hold_quiet`` cleared)."""
    env, lane = wp.tid()
    lanes = wp.block_dim()
    q = live.particle_q
    qd = live.particle_qd
    if finish_inv_dt > 0.0:
        for i in range(lane, q.shape[1], lanes):
            # xpbd.update_particle_velocities' arithmetic
            qd[env, i] = qd[env, i] + (q[env, i] - q_pred[env, i]) * finish_inv_dt
        for i in range(lane, segment_q_prev.shape[1], lanes):
            live.segment_qd[env, i] = segment_velocity(live.segment_q[env, i], segment_q_prev[env, i], finish_inv_dt)
    if copy_body_q != 0:
        # before the block-wide maximum below, whose barrier orders it before a restore's writes
        for i in range(lane, body_q_prev.shape[1], lanes):
            body_q_prev[env, i] = live.body_q[env, i]
    bad = int(0)
    for i in range(lane, q.shape[1], lanes):
        v2 = wp.length_sq(qd[env, i])
        x2 = wp.length_sq(q[env, i])
        # written so that NaN fails both comparisons and is flagged
        if not (v2 <= max_speed * max_speed) or not (x2 < 1.0e12):
            bad = 1
    # a block-wide maximum: every lane reads the block's verdict
    failed = wp.tile_max(wp.tile(bad))[0]
    if lane == 0:
        flags_now[env] = failed
        if failed != 0:
            unstable[env] = 1
    if restore == 0 or failed == 0:
        return
    copy_row_elements(env, lane, lanes, width, start, live, body_q_prev, write_body_q_prev)
    for i in range(lane, rotation.shape[1], lanes):
        rotation[env, i] = start_rotation[env % start_rotation.shape[0], i]
    if lane == 0:
        hold_quiet[env] = 0
    if lane == 0 and live.cut_dirty.shape[1] > 0:
        # after this lane's own copy of the flag: the restored masks differ from what the cutting system last
        # counted, so its next update recomputes this env's surfaces, pieces and counters
        live.cut_dirty[env, 0] = 1


@wp.kernel
def scale_material_columns(env_mask: wp.array(dtype=wp.int32), columns: wp.array(dtype=wp.int32),
                           base: wp.array2d(dtype=Any), factor: wp.array(dtype=float), out: wp.array2d(dtype=Any)):
    """``out[env, c] = base[env, c] * factor[env]`` for the masked envs and the given columns (compliances divided
    by a stiffness scale, inverse masses by a density scale)."""
    env, k = wp.tid()
    if env_mask[env] == 0:
        return
    c = columns[k]
    out[env, c] = base[env, c] * factor[env]


@wp.kernel
def scale_tet_compliance(env_mask: wp.array(dtype=wp.int32), columns: wp.array(dtype=wp.int32),
                         base: wp.array2d(dtype=wp.vec3), stiffness: wp.array(dtype=float),
                         out: wp.array2d(dtype=wp.vec3)):
    """Tet compliances (deviatoric, volumetric; -1 marks no volume term) divided by a stiffness scale."""
    env, k = wp.tid()
    if env_mask[env] == 0:
        return
    c = columns[k]
    p = base[env, c]
    s = 1.0 / stiffness[env]
    vol = p[1]
    if vol >= 0.0:
        vol = vol * s
    out[env, c] = wp.vec3(p[0] * s, vol, p[2])


@wp.kernel
def set_material_columns(env_mask: wp.array(dtype=wp.int32), columns: wp.array(dtype=wp.int32),
                         value: wp.array(dtype=float), out: wp.array2d(dtype=float)):
    """``out[env, c] = value[env]`` for the masked envs and the given columns (damping rates)."""
    env, k = wp.tid()
    if env_mask[env] == 0:
        return
    out[env, columns[k]] = value[env]


@wp.kernel
def tet_stiffness(params: wp.array2d(dtype=wp.vec3), out: wp.array2d(dtype=wp.vec2)):
    """The tets' stiffnesses ``(1 / alpha_D, 1 / alpha_H)`` from their compliances (``alpha_H < 0``, no volume term:
    -1): the per-vertex tet solve (kernels/vbd.py) multiplies by them in every incidence instead of dividing."""
    i, c = wp.tid()
    p = params[i, c]
    k_H = float(-1.0)
    if p[1] >= 0.0:
        k_H = 1.0 / p[1]
    out[i, c] = wp.vec2(1.0 / p[0], k_H)


@wp.kernel
def reciprocal(values: wp.array(dtype=float), out: wp.array(dtype=float)):
    i = wp.tid()
    out[i] = 1.0 / values[i]


@wp.kernel
def attachment_inverse_masses(inv_mass: wp.array2d(dtype=float), attach_particle: wp.array2d(dtype=wp.int32),
                              attach_compliance: wp.array2d(dtype=float), inv_dt2: float, distinct: int,
                              w_out: wp.array2d(dtype=float)):
    """Inverse mass of each particle as the deformables' constraints see it: a particle held by attachments of
    compliances alpha_s counts as ``1 / (1 / w + sum h^2 / alpha_s)``, i.e. the attachment springs' resistance
    added to its inertia (0 for a stiff attachment: a grasped point then acts as pinned in the cloth, rod and tet
    solves, instead of being dragged off by the whole sheet's weight within a sweep and snapped back by its
    attachment afterwards).

    A thread block per env: its lanes copy the true inverse masses, then (after a block barrier) each attachment
    slot rewrites its particle's from every slot that holds it (slots sharing a particle store the same value). One
    thread per (env, particle) scanning every slot cost TissueDissection's 36 slots x 144 particles ~0.4 ms per env
    step at 4,096 envs. ``distinct`` (``Model.attachments_distinct``: no particle in two slots): each slot is its
    particle's only one, so no slot scans the others. On the CPU a block has one lane."""
    env, lane = wp.tid()
    lanes = wp.block_dim()
    barrier = wp.tile_zeros(shape=1, dtype=int, storage="shared")
    row = env % inv_mass.shape[0]
    for i in range(lane, w_out.shape[1], lanes):
        w_out[env, i] = inv_mass[row, i]
    wp.tile_scatter_masked(barrier, 0, 0, False)  # a block barrier (nothing written): the copies are done
    slots = attach_particle.shape[1]
    for s0 in range(lane, slots, lanes):
        i = attach_particle[env, s0]
        if i < 0:
            continue
        w = inv_mass[row, i]
        if w > 0.0:
            resistance = float(0.0)
            first = int(0)
            last = slots
            if distinct != 0:
                first = s0
                last = s0 + 1
            for s in range(first, last):
                if attach_particle[env, s] == i:
                    a = attach_compliance[env, s] * inv_dt2
                    if a <= 0.0:
                        w = 0.0
                    else:
                        resistance += 1.0 / a
            if w > 0.0 and resistance > 0.0:
                w = 1.0 / (1.0 / w + resistance)
        w_out[env, i] = w
