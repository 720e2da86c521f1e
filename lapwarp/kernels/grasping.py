"""Grasping kernels (see :mod:`lapwarp.grasping`): attach, hold and release particles with a two-jaw instrument.

Attachments are written into the per-env slots ``[slot_start, slot_start + slots)`` of ``state.attach_*``
(:class:`lapwarp.kernels.xpbd.Attachments`, part of the :class:`GraspState` the kernels write); the contact records
and the shape table come from :mod:`lapwarp.kernels.contact`, and the ``ignore_bodies`` bits of held particles
(:class:`lapwarp.kernels.contact.IgnoreMask`) keep the jaws from squeezing them out. A held rod node's segment is
written into its slot too (``state.attach_segment`` / ``attach_rotation``): the World's attachment pass turns it with
the jaw in every sweep. One thread per env.
"""

import warp as wp

from lapwarp.kernels.contact import ContactReports, IgnoreMask, ShapeTable
from lapwarp.kernels.geometry import twist_about
from lapwarp.kernels.xpbd import Attachments

wp.set_module_options({"enable_backward": False})


@wp.struct
class Grasper:
    """One grasper's bodies, rule and slots (built once by ``GraspSystem``)."""

    shaft: int
    jaw_a: int
    jaw_b: int
    jaw_length: float
    grasp_threshold: float  # deg: below it a grasp is attempted
    release_threshold: float  # deg: at or above it a grasp is released
    cone_margin: float
    max_offset: float
    slot_start: int
    slots: int
    compliance: float
    graspable: wp.array(dtype=wp.int32)  # per particle
    particle_segment: wp.array(dtype=wp.int32)  # per particle: an adjacent rod segment, -1 for none
    hold: int  # 1: a held rod node's segment turns with the jaw (its slot's attach_segment), 0: it turns freely
    hold_up: wp.vec3  # zero: held segments turn with the jaw; else only with the jaw's turn about this axis


@wp.func
def held_rotation(grasper: Grasper, rot: wp.quat) -> wp.quat:
    """The rotation a held segment follows: the jaw's, or only its twist about ``hold_up`` (swing-twist split)."""
    return twist_about(rot, grasper.hold_up)


@wp.struct
class GraspScene:
    """The World state a grasp reads: kinematic body poses, particle positions and rod segment orientations (a
    ``(1, 1)`` placeholder without rods)."""

    body_q: wp.array2d(dtype=wp.transform)
    particle_q: wp.array2d(dtype=wp.vec3)
    segment_q: wp.array2d(dtype=wp.quat)


@wp.struct
class GraspState:
    """What grasping writes: per env ``grasped`` (sticky) and ``lost_grasp`` (event of the last step), the attachment
    slots (with the held segment and its orientation relative to its jaw at grasp time) and the contact ignore mask
    of held particles."""

    grasped: wp.array(dtype=wp.int32)
    lost_grasp: wp.array(dtype=wp.int32)
    attach: Attachments
    ignore: IgnoreMask


@wp.func
def jaw_mask(grasper: Grasper):
    return (1 << grasper.jaw_a) | (1 << grasper.jaw_b)


@wp.func
def release_slots(env: int, grasper: Grasper, grasp: GraspState):
    for k in range(grasper.slots):
        i = grasp.attach.particle[env, grasper.slot_start + k]
        if i >= 0 and grasp.ignore.enabled != 0:
            grasp.ignore.bodies[env, i] = grasp.ignore.bodies[env, i] & (~jaw_mask(grasper))
        grasp.attach.particle[env, grasper.slot_start + k] = -1
        grasp.attach.segment[env, grasper.slot_start + k] = -1


@wp.func
def attach_to_jaw(env: int, k: int, particle: int, body: int, grasper: Grasper, scene: GraspScene,
                  grasp: GraspState):
    """Hold ``particle`` in slot ``k`` by jaw ``body`` at its current offset in the jaw frame (so a jaw that opens
    towards the release angle carries it along); its rod segment keeps its orientation relative to the jaw."""
    s = grasper.slot_start + k
    jaw = scene.body_q[env, body]
    grasp.attach.particle[env, s] = particle
    grasp.attach.body[env, s] = body
    grasp.attach.offset[env, s] = wp.transform_point(wp.transform_inverse(jaw), scene.particle_q[env, particle])
    grasp.attach.compliance[env, s] = grasper.compliance
    seg = int(-1)
    if grasper.hold != 0:
        seg = grasper.particle_segment[particle]
    grasp.attach.segment[env, s] = seg
    if seg >= 0:
        rot = held_rotation(grasper, wp.transform_get_rotation(jaw))
        grasp.attach.rotation[env, s] = wp.mul(wp.quat_inverse(rot), scene.segment_q[env, seg])
    if grasp.ignore.enabled != 0:
        grasp.ignore.bodies[env, particle] = grasp.ignore.bodies[env, particle] | jaw_mask(grasper)


@wp.func
def in_jaw_cone(pl: wp.vec3, angle: float, jaw_length: float, margin: float):
    """Local tip-frame point between the jaws: within the jaw length and inside the opening angle (+ margin)."""
    if pl[2] < -margin or pl[2] > jaw_length + margin:
        return False
    if wp.abs(pl[0]) > margin:
        return False
    return wp.abs(pl[1]) <= wp.max(pl[2], 0.0) * wp.tan(angle) + margin


@wp.kernel
def update_grasp(
    grasper: Grasper,
    jaw_angle_deg: wp.array(dtype=float),
    shapes: ShapeTable,
    reports: ContactReports,
    scene: GraspScene,
    grasp: GraspState,
):
    env = wp.tid()
    grasp.lost_grasp[env] = 0
    angle = jaw_angle_deg[env]
    body_q = scene.body_q
    q = scene.particle_q
    jaw_a = grasper.jaw_a
    jaw_b = grasper.jaw_b
    slot_start = grasper.slot_start
    tip = body_q[env, grasper.shaft]
    if grasp.grasped[env] != 0:
        far = int(0)
        for k in range(grasper.slots):
            i = grasp.attach.particle[env, slot_start + k]
            if i >= 0:
                jaw = body_q[env, grasp.attach.body[env, slot_start + k]]
                target = wp.transform_point(jaw, grasp.attach.offset[env, slot_start + k])
                if wp.length(q[env, i] - target) > grasper.max_offset:
                    far = 1
        if angle >= grasper.release_threshold or far != 0:
            release_slots(env, grasper, grasp)
            grasp.grasped[env] = 0
            grasp.lost_grasp[env] = far
        return
    if angle >= grasper.grasp_threshold:
        return
    n = wp.min(reports.contact_count[env], reports.contact_particle.shape[1])
    has_a = int(0)
    has_b = int(0)
    for c in range(n):
        if grasper.graspable[reports.contact_particle[env, c]] == 0:
            continue
        b = shapes.body[reports.contact_shape[env, c]]
        if b == jaw_a:
            has_a = 1
        if b == jaw_b:
            has_b = 1
    if has_a == 0 or has_b == 0:
        return
    inv_tip = wp.transform_inverse(tip)
    rad = angle * (wp.pi / 180.0)
    got = int(0)
    for k in range(grasper.slots):
        best = int(-1)
        best_b = int(-1)
        best_d = float(1.0e9)
        for c in range(n):
            i = reports.contact_particle[env, c]
            b = shapes.body[reports.contact_shape[env, c]]
            if grasper.graspable[i] == 0 or (b != jaw_a and b != jaw_b):
                continue
            taken = int(0)
            for m in range(k):
                if grasp.attach.particle[env, slot_start + m] == i:
                    taken = 1
            if taken != 0:
                continue
            pl = wp.transform_point(inv_tip, q[env, i])
            if not in_jaw_cone(pl, rad, grasper.jaw_length, grasper.cone_margin):
                continue
            # nearest to the jaws' mid-plane
            d = wp.abs(pl[1]) + wp.abs(pl[0])
            if d < best_d:
                best_d = d
                best = i
                best_b = b
        if best < 0:
            break
        # held by the jaw it touches (the jaws are bodies)
        attach_to_jaw(env, k, best, best_b, grasper, scene, grasp)
        got += 1
    if got > 0:
        grasp.grasped[env] = 1


@wp.kernel
def sync_jaw_contact(grasper: Grasper, grasp: GraspState):
    """Thread (env, particle): every graspable particle ignores the jaws while its env holds a grasp (sofa_env
    switches the jaws' collision models off while grasping)."""
    env, i = wp.tid()
    if grasper.graspable[i] == 0 or grasp.ignore.enabled == 0:
        return
    if grasp.grasped[env] != 0:
        grasp.ignore.bodies[env, i] = grasp.ignore.bodies[env, i] | jaw_mask(grasper)
    else:
        grasp.ignore.bodies[env, i] = grasp.ignore.bodies[env, i] & (~jaw_mask(grasper))


@wp.kernel
def start_grasp(
    env_mask: wp.array(dtype=wp.int32),
    particle_all: int,
    particle_each: wp.array(dtype=wp.int32),
    grasper: Grasper,
    scene: GraspScene,
    grasp: GraspState,
):
    env = wp.tid()
    if env_mask[env] == 0:
        return
    release_slots(env, grasper, grasp)
    grasp.lost_grasp[env] = 0
    grasp.grasped[env] = 0
    # one particle for every env, or (a non-empty ``particle_each``) one per env
    particle = particle_all
    if particle_each.shape[0] > 0:
        particle = particle_each[env]
    if particle < 0:
        return
    # the jaw on the particle's side of the mid-plane holds it (jaw A closes from local -y, jaw B from +y)
    body = grasper.jaw_b
    tip = scene.body_q[env, grasper.shaft]
    if wp.transform_point(wp.transform_inverse(tip), scene.particle_q[env, particle])[1] < 0.0:
        body = grasper.jaw_a
    attach_to_jaw(env, 0, particle, body, grasper, scene, grasp)
    grasp.grasped[env] = 1


@wp.kernel
def restore_grasp(env_mask: wp.array(dtype=wp.int32), grasper: Grasper, saved: GraspState, grasp: GraspState):
    """Thread per env: the masked envs' grasp (flag, held slots, their orientation offsets and the jaw bits of the
    ignore mask) back to a saved copy (``GraspSystem.snapshot``)."""
    env = wp.tid()
    if env_mask[env] == 0:
        return
    grasp.grasped[env] = saved.grasped[env]
    grasp.lost_grasp[env] = 0
    for k in range(grasper.slots):
        s = grasper.slot_start + k
        grasp.attach.particle[env, s] = saved.attach.particle[env, s]
        grasp.attach.body[env, s] = saved.attach.body[env, s]
        grasp.attach.offset[env, s] = saved.attach.offset[env, s]
        grasp.attach.compliance[env, s] = saved.attach.compliance[env, s]
        grasp.attach.segment[env, s] = saved.attach.segment[env, s]
        grasp.attach.rotation[env, s] = saved.attach.rotation[env, s]
    if grasp.ignore.enabled != 0:
        m = jaw_mask(grasper)
        for i in range(grasp.ignore.bodies.shape[1]):
            grasp.ignore.bodies[env, i] = (grasp.ignore.bodies[env, i] & (~m)) | (saved.ignore.bodies[env, i] & m)
