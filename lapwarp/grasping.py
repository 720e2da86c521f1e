"""Grasping with a two-jaw instrument, per env and inside the recorded step (no host syncs).

Rule (sofa_env's ArticulatedGripper, see sofa_env-facts 4.2): at the end of every ``world.step``, in an env that
holds nothing, if the jaw angle is below ``grasp_threshold`` and the last substep found contacts of graspable
particles with *both* jaws, the particles touching a jaw and lying inside the jaw cone (between the jaws, within
the jaw length) that are nearest to the jaws' mid-plane (up to ``slots`` of them) are attached to the jaw body
they touch, at their current offset in that jaw's frame (so a jaw that opens towards the release angle carries
its particles along): attachment slots ``[slot_start, slot_start + slots)`` of ``state.attach_*`` are written
with a small compliance. For rod nodes the adjacent segment's orientation is held at the jaw rotation times its
orientation at grasp time (projected in every sweep). Held particles stop colliding with the jaws (the
ContactSystem's ``ignore_bodies`` mask), so the jaws do not squeeze them out. Opening the jaws to
``release_threshold`` or more releases them (with ``jaws_pass_while_grasped``, sofa_env's rule, no graspable particle
collides with the jaws while the env holds a grasp); a held particle dragged farther than ``max_offset`` from its jaw
target (torn out by the scene) releases the grasp and raises ``lost_grasp`` for that step. The held segment and its
orientation relative to the jaw sit in the particle's slot (``state.attach_segment`` / ``attach_rotation``, the jaw's
twist axis in ``model.attach_hold_up``), so the World's closing attachment pass of every sweep turns it with the jaw
(before this system's own launch per sweep did, after the contact pass, which does not touch orientations).

State: ``grasped`` ``(num_envs,)`` int32 (sticky), ``lost_grasp`` ``(num_envs,)`` int32 (the event of the last
step). ``start_grasped(particle, env_mask)`` attaches a given particle at reset, as sofa_env's ``start_grasped``.
"""

from __future__ import annotations

import numpy as np
import warp as wp

from lapwarp import launching
from lapwarp.kernels import grasping as gk
from lapwarp.kernels import xpbd
from lapwarp.kernels.contact import IgnoreMask
from lapwarp.launching import make_struct


class GraspSystem:
    """Grasp logic of one articulated instrument.

    Args:
        contact: the finalized ContactSystem (built with ``body_ignore_mask=True`` so held particles pass through
            the jaws; it also provides the contact records of the last substep).
        instrument: an articulated :class:`lapwarp.instrument_shapes.InstrumentShape` whose jaws are colliders.
        jaw_angle_deg: ``(num_envs,)`` float32 device array of the current jaw angle (degrees), read every step.
        groups: ContactSystem particle group ids that can be grasped (default: all).
        grasp_threshold: jaw angle (deg) below which a grasp is attempted.
        release_threshold: jaw angle (deg) at or above which a grasp is released (>= grasp_threshold).
        slot_start: first attachment slot reserved for this grasper (``finalize(attachment_capacity=...)`` must
            leave ``slot_start + slots`` slots).
        slots: particles held at most (1 = the single nearest point, as sofa_env's rope grasp).
        compliance: attachment compliance, m/N (small: a stiff spring).
        cone_margin: tolerance of the jaw-cone test, m.
        max_offset: distance (m) from the jaw target beyond which a grasp counts as lost.
        hold_orientation: project grasped rod segments' orientations onto the jaw rotation.
        hold_up: with ``hold_orientation``, a held segment turns only with the jaw's rotation about this (world) axis
            and keeps its tilt (None: it turns with the jaw). PickAndPlace's torus stays level when the shaft tilts.
        jaws_pass_while_grasped: while an env holds a grasp, none of its graspable particles collides with the
            jaws (sofa_env switches the jaws' collision models off while grasping); otherwise only held ones.
    """

    def __init__(self, contact, instrument, jaw_angle_deg: wp.array, groups=None, grasp_threshold: float = 10.0,
                 release_threshold: float = 15.0, slot_start: int = 0, slots: int = 1, compliance: float = 1.0e-6,
                 cone_margin: float = 3.0e-3, max_offset: float = 0.01, hold_orientation: bool = True,
                 hold_up=None, jaws_pass_while_grasped: bool = False):
        if not instrument.articulated:
            raise ValueError(f"{instrument.kind} has no jaws")
        if release_threshold < grasp_threshold:
            raise ValueError("release_threshold must be >= grasp_threshold")
        world = contact.world
        cap = world.model.attachment_capacity
        if slot_start < 0 or slot_start + slots > cap:
            raise ValueError(f"slots [{slot_start}, {slot_start + slots}) exceed attachment_capacity {cap}")
        if max(instrument.bodies) >= 31:
            raise ValueError("the ignore mask holds bodies 0..30")
        world.model.attachments_distinct = False  # its slots change at run time (one thread walks an env's slots)
        self.contact, self.world, self.instrument = contact, world, instrument
        self.jaw_angle = jaw_angle_deg
        self.grasp_threshold, self.release_threshold = float(grasp_threshold), float(release_threshold)
        self.slot_start, self.slots, self.compliance = int(slot_start), int(slots), float(compliance)
        self.cone_margin, self.max_offset = float(cone_margin), float(max_offset)
        self.hold_orientation = bool(hold_orientation) and world.model.segment_count > 0
        self.jaws_pass_while_grasped = bool(jaws_pass_while_grasped)
        n, dev, m = world.num_envs, world.device, world.model
        graspable = np.zeros(max(m.particle_count, 1), dtype=np.int32)
        for g in (range(len(contact.groups)) if groups is None else np.atleast_1d(groups)):
            graspable[contact.groups[int(g)].particles] = 1
        # rod node -> an adjacent segment (node k of a rod: segment k, the last node of an open rod: the last one)
        seg_of = -np.ones(max(m.particle_count, 1), dtype=np.int32)
        for obj in m.objects:
            if obj.kind == "rod":
                k = np.arange(obj.particle_count)
                seg_of[obj.particles] = obj.segment_start + np.minimum(k, obj.segment_count - 1)
        self.graspable = wp.array(graspable, dtype=wp.int32, device=dev)
        self.particle_segment = wp.array(seg_of, dtype=wp.int32, device=dev)
        self.grasped = wp.zeros(n, dtype=wp.int32, device=dev)
        self.lost_grasp = wp.zeros(n, dtype=wp.int32, device=dev)
        up = np.zeros(3) if hold_up is None else np.asarray(hold_up, float) / np.linalg.norm(hold_up)
        if self.hold_orientation and hold_up is not None:
            # the World's attachment pass reads each slot's axis (a zero axis: the jaw's whole rotation)
            axes = m.attach_hold_up.numpy()
            axes[self.slot_start:self.slot_start + self.slots] = up
            m.attach_hold_up.assign(axes)
        self._dummy_q = wp.zeros((1, 1), dtype=wp.quat, device=dev)
        self._no_particles = wp.zeros(0, dtype=wp.int32, device=dev)
        self.jaw_mask = (1 << instrument.jaw_a) | (1 << instrument.jaw_b)
        if contact not in world.solvers:
            raise ValueError("finalize() the ContactSystem before creating the GraspSystem")
        self._grasper = make_struct(gk.Grasper, shaft=instrument.shaft_body, jaw_a=instrument.jaw_a,
                                    jaw_b=instrument.jaw_b, jaw_length=float(instrument.jaw_length),
                                    grasp_threshold=self.grasp_threshold, release_threshold=self.release_threshold,
                                    cone_margin=self.cone_margin, max_offset=self.max_offset,
                                    slot_start=self.slot_start, slots=self.slots, compliance=self.compliance,
                                    graspable=self.graspable, particle_segment=self.particle_segment,
                                    hold=int(self.hold_orientation),
                                    hold_up=wp.vec3(*up))
        s = world.state
        attach = make_struct(xpbd.Attachments, particle=s.attach_particle, body=s.attach_body, offset=s.attach_offset,
                             compliance=s.attach_compliance, segment=s.attach_segment, rotation=s.attach_rotation)
        self._state = make_struct(gk.GraspState, grasped=self.grasped, lost_grasp=self.lost_grasp, attach=attach,
                                  ignore=contact.ignore)
        self._scene = make_struct(gk.GraspScene, body_q=s.body_q, particle_q=s.particle_q, segment_q=self._segq())
        world.add_solver(self)

    def _segq(self):
        s = self.world.state
        return s.segment_q if s.segment_q is not None else self._dummy_q

    # World hooks ------------------------------------------------------------------------------------
    def record_sweep(self, world, launch, sweep) -> None:
        """After the last sweep of the step, grasp or release from the contact records that the ContactSystem (added
        before this system) just wrote (the held segments turn with their jaws in the World's attachment pass)."""
        if sweep.last:
            c = self.contact
            launch(gk.update_grasp, world.num_envs,
                   [self._grasper, self.jaw_angle, c.shape_table, c.reports, self._scene], [self._state])
            if self.jaws_pass_while_grasped:
                launch(gk.sync_jaw_contact, (world.num_envs, self.graspable.shape[0]), [self._grasper],
                       [self._state])

    # host-side (reset time) -------------------------------------------------------------------------
    def start_grasped(self, particle: int | wp.array, env_mask: wp.array | None = None) -> None:
        """Release the masked envs' grasps and, if ``particle >= 0``, attach that global particle at its current
        offset to the jaw on its side of the jaws' mid-plane (call after ``world.reset`` and after posing the
        instrument). ``particle`` may be a ``(num_envs,)`` int32 device array: one particle per env (a randomised
        grasp index; graph-capturable)."""
        w = self.world
        mask = env_mask if env_mask is not None else wp.ones(w.num_envs, dtype=wp.int32, device=w.device)
        each = particle if isinstance(particle, wp.array) else self._no_particles
        if each.shape != (0,) and each.shape != (w.num_envs,):
            raise ValueError(f"per-env grasp particles must have shape ({w.num_envs},), got {each.shape}")
        single = -1 if isinstance(particle, wp.array) else int(particle)
        launching.launch(gk.start_grasp, dim=w.num_envs, inputs=[mask, single, each, self._grasper, self._scene],
                         outputs=[self._state], device=w.device)
        if self.jaws_pass_while_grasped:
            launching.launch(gk.sync_jaw_contact, dim=(w.num_envs, self.graspable.shape[0]),
                             inputs=[self._grasper], outputs=[self._state], device=w.device)

    def reset(self, env_mask: wp.array) -> None:
        """Forget the grasps of the masked envs (``world.reset`` restores the attachment slots themselves)."""
        self.start_grasped(-1, env_mask)

    def snapshot(self):
        """A copy of every env's grasp (flag, held slots, orientation offsets, ignore mask) for :meth:`restore`: a
        task that starts its episodes grasped saves the grasp its build-time script made."""
        s = self._state

        def copy(a):
            return wp.clone(a)

        attach = make_struct(xpbd.Attachments, particle=copy(s.attach.particle), body=copy(s.attach.body),
                             offset=copy(s.attach.offset), compliance=copy(s.attach.compliance),
                             segment=copy(s.attach.segment), rotation=copy(s.attach.rotation))
        ignore = make_struct(IgnoreMask, bodies=copy(s.ignore.bodies), enabled=s.ignore.enabled)
        return make_struct(gk.GraspState, grasped=copy(s.grasped), lost_grasp=copy(s.lost_grasp),
                           attach=attach, ignore=ignore)

    def restore(self, env_mask: wp.array, snapshot) -> None:
        """Put the masked envs' grasps back to a :meth:`snapshot` (after ``world.reset``, whose reset of this system
        released them); one launch, graph-capturable."""
        launching.launch(gk.restore_grasp, dim=self.world.num_envs, inputs=[env_mask, self._grasper, snapshot],
                         outputs=[self._state], device=self.world.device)
