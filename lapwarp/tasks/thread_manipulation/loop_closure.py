"""LoopClosure: a rod loop whose ends are drawn into an instrument's shaft (sofa_env's ligating-loop mechanism).

A ligating-loop instrument holds a Cosserat rod of ``N`` nodes whose node 0 and node ``N - 1`` both start at the
instrument's tip. sofa_env binds rope frame 0 and every frame ``k >= active_index`` to motion targets by 9e20 springs:
frame 0 to the tip, frame ``active_index + i`` to ``tip + i * pitch`` along the shaft, inside it. Lowering
``active_index`` by one pulls one more segment into the shaft and shrinks the loop.

Here the same frames are held by the World's attachment slots (slot ``k`` holds node ``k``, compliance 0, so the
rod's own constraints see a pinned node as immovable) and their segments' orientations are projected onto the
shaft's rotation in every sweep: the segments inside the shaft, segment 0 (node 0's frame) and, while the loop is
fully open, the last segment (node N - 1's frame, which has no segment beyond it inside the shaft); as in the build
circle, the first and last segments leave and enter the tip at half a chord angle to the shaft.

A change of ``active_index`` does not teleport the pinned nodes: within a step each
pinned node moves linearly (in the shaft's frame) from where it was at the step's start to its new place, and a
newly pinned node or segment starts from its own position and orientation, so one step never asks for an impulse.

Per env step the task writes ``active_index``; per physics step it calls :meth:`LoopClosure.pre_step` (after the
instrument's body pose is written, before ``World.step``); the World calls ``record_sweep`` in every sweep.
"""

from __future__ import annotations

import numpy as np
import warp as wp

from lapwarp import launching
from lapwarp.builder import _quat_mul
from lapwarp.kernels.geometry import interpolate_transform

wp.set_module_options({"enable_backward": False})


@wp.struct
class LoopPins:
    """Per-env pin state: the loop's active index, each node's body-frame offset at the step's start and end, each
    segment's body-frame orientation at the step's start and end and whether it is pinned."""

    active_index: wp.array(dtype=wp.int32)
    off_from: wp.array2d(dtype=wp.vec3)
    off_to: wp.array2d(dtype=wp.vec3)
    rel_from: wp.array2d(dtype=wp.quat)
    rel_to: wp.array2d(dtype=wp.quat)
    pinned_segment: wp.array2d(dtype=wp.int32)


@wp.struct
class LoopGeometry:
    first: int  # global index of node 0
    segment_first: int
    nodes: int
    body: int  # the shaft body the pins follow
    pitch: float
    rel_first: wp.quat  # segment 0's orientation in the tip frame
    rel_last: wp.quat  # the last segment's, when the loop is fully open
    rel_inside: wp.quat  # a segment inside the shaft, in the tip frame


@wp.func
def pin_target(g: LoopGeometry, k: int, a: int) -> wp.vec3:
    """Node ``k``'s place in the tip frame when pinned at active index ``a`` (node 0 at the tip; node a + i at i
    pitches inside the shaft, which is the tip frame's -z)."""
    if k == 0:
        return wp.vec3(0.0)
    return wp.vec3(0.0, 0.0, -g.pitch * float(k - a))


@wp.func
def node_pinned(k: int, a: int) -> int:
    if k == 0 or k >= a:
        return 1
    return 0


@wp.func
def segment_pin(g: LoopGeometry, k: int, a: int) -> int:
    """Which orientation segment ``k`` is held at: 0 none, 1 the first (node 0's frame), 2 inside the shaft, 3 the
    last segment of the fully open loop (node N - 1's frame: no segment lies beyond it inside the shaft)."""
    if k == 0:
        return 1
    if node_pinned(k, a) == 1 and node_pinned(k + 1, a) == 1:
        return 2
    if a == g.nodes - 1 and k == g.nodes - 2:
        return 3
    return 0


@wp.func
def segment_target(g: LoopGeometry, pin: int) -> wp.quat:
    if pin == 1:
        return g.rel_first
    if pin == 3:
        return g.rel_last
    return g.rel_inside


@wp.func
def write_pins(env: int, k: int, g: LoopGeometry, pins: LoopPins, a: int, frm: wp.vec3, rfrm: wp.quat, blend: float,
               attach_particle: wp.array2d(dtype=wp.int32), attach_body: wp.array2d(dtype=wp.int32),
               attach_offset: wp.array2d(dtype=wp.vec3), attach_compliance: wp.array2d(dtype=float)):
    """Node ``k``'s pin (and segment ``k``'s) at active index ``a``, moving from ``frm`` / ``rfrm`` (tip frame) to its
    place; the attachment offset at ``blend`` of the way."""
    if node_pinned(k, a) == 1:
        to = pin_target(g, k, a)
        pins.off_from[env, k] = frm
        pins.off_to[env, k] = to
        attach_particle[env, k] = g.first + k
        attach_body[env, k] = g.body
        attach_compliance[env, k] = 0.0
        attach_offset[env, k] = frm + (to - frm) * blend
    else:
        attach_particle[env, k] = -1
    if k < g.nodes - 1:
        pin = segment_pin(g, k, a)
        if pin != 0:
            pins.rel_from[env, k] = rfrm
            pins.rel_to[env, k] = segment_target(g, pin)
            pins.pinned_segment[env, k] = 1
        else:
            pins.pinned_segment[env, k] = 0


@wp.kernel
def pin_loop(g: LoopGeometry, pins: LoopPins, body_q_prev: wp.array2d(dtype=wp.transform),
             q: wp.array2d(dtype=wp.vec3), segment_q: wp.array2d(dtype=wp.quat), first_blend: float,
             attach_particle: wp.array2d(dtype=wp.int32), attach_body: wp.array2d(dtype=wp.int32),
             attach_offset: wp.array2d(dtype=wp.vec3), attach_compliance: wp.array2d(dtype=float)):
    """Start of a physics step: the pins of the current active index, each moving from where it is now (a pin that
    was already held continues from its last target)."""
    env, k = wp.tid()
    inv = wp.transform_inverse(body_q_prev[env, g.body])
    frm = pins.off_to[env, k]
    if attach_particle[env, k] < 0:
        frm = wp.transform_point(inv, q[env, g.first + k])
    rfrm = wp.quat_identity()
    if k < g.nodes - 1:
        rfrm = pins.rel_to[env, k]
        if pins.pinned_segment[env, k] == 0:
            rfrm = wp.normalize(wp.transform_get_rotation(inv) * segment_q[env, g.segment_first + k])
    write_pins(env, k, g, pins, pins.active_index[env], frm, rfrm, first_blend, attach_particle, attach_body,
               attach_offset, attach_compliance)


@wp.kernel
def advance_loop_pins(g: LoopGeometry, pins: LoopPins, body_q_prev: wp.array2d(dtype=wp.transform),
                      body_q: wp.array2d(dtype=wp.transform), blend: float, next_blend: float,
                      attach_particle: wp.array2d(dtype=wp.int32), attach_offset: wp.array2d(dtype=wp.vec3),
                      segment_q: wp.array2d(dtype=wp.quat)):
    """After each sweep: the pinned segments' orientations at this sweep's blend, and the pinned nodes' offsets for
    the next sweep's attachment solve."""
    env, k = wp.tid()
    if attach_particle[env, k] >= 0:
        frm = pins.off_from[env, k]
        attach_offset[env, k] = frm + (pins.off_to[env, k] - frm) * next_blend
    if k < g.nodes - 1:
        if pins.pinned_segment[env, k] == 1:
            tf = interpolate_transform(body_q_prev[env, g.body], body_q[env, g.body], blend)
            rel = wp.quat_slerp(pins.rel_from[env, k], pins.rel_to[env, k], blend)
            segment_q[env, g.segment_first + k] = wp.normalize(wp.transform_get_rotation(tf) * rel)


@wp.kernel
def settle_loop_pins(env_mask: wp.array(dtype=wp.int32), g: LoopGeometry, pins: LoopPins,
                     attach_particle: wp.array2d(dtype=wp.int32), attach_body: wp.array2d(dtype=wp.int32),
                     attach_offset: wp.array2d(dtype=wp.vec3), attach_compliance: wp.array2d(dtype=float)):
    """The masked envs' pins at rest at their active index (after a reset placed the loop there)."""
    env, k = wp.tid()
    if env_mask[env] == 0:
        return
    a = pins.active_index[env]
    write_pins(env, k, g, pins, a, pin_target(g, k, a), segment_target(g, segment_pin(g, k, a)), 1.0,
               attach_particle, attach_body, attach_offset, attach_compliance)


def _quat_between(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """xyzw rotation taking unit ``u`` to unit ``v`` (not antiparallel)."""
    c = np.cross(u, v)
    q = np.array([c[0], c[1], c[2], 1.0 + float(np.dot(u, v))])
    return q / np.linalg.norm(q)


def _rotate(q: np.ndarray, v: np.ndarray) -> np.ndarray:
    return np.asarray(wp.quat_rotate(wp.quat(*[float(c) for c in q]), wp.vec3(*[float(c) for c in v])))


class LoopClosure:
    """The pins of one loop rod held by one instrument body (see the module docstring).

    Args:
        world: the World (with ``attachment_capacity >= N``; slot ``k`` is node ``k``).
        rod: the loop's ``SceneObject`` (an open rod whose first and last nodes sit at the tip).
        body: the instrument body (its frame is the tip frame: local +z forward along the shaft).
        tip_rotation: the tip frame's rotation (xyzw) in the pose the rod was built in.
        pitch: the spacing of the nodes drawn into the shaft (sofa_env: the rope's first segment length), m.
    """

    def __init__(self, world, rod, body: int, tip_rotation, pitch: float):
        n, dev, N = world.num_envs, world.device, rod.particle_count
        if world.model.attachment_capacity < N:
            raise ValueError(f"the loop's {N} nodes need {N} attachment slots, the World has "
                             f"{world.model.attachment_capacity}")
        self.world, self.rod, self.nodes = world, rod, N
        # its slots change at run time, but slot k only ever holds node k (write_pins): where the loop owns every slot
        # no particle is in two, so a thread per (env, slot) solves them (xpbd.solve_attachment_slots: the same
        # result, bit-identical on the CPU) instead of one thread walking an env's N slots (LigatingLoop: 2.6 ms of
        # its 44.6 ms of kernels per env step, H200, 4,096 envs); with more slots (grasping beside the loop) one
        # thread walks them in order
        world.model.attachments_distinct = world.model.attachment_capacity == N
        seg_q = world.state.segment_q.numpy()[0, rod.segment_start:rod.segment_start + rod.segment_count]
        inv_tip = np.asarray(tip_rotation, np.float64) * np.array([-1.0, -1.0, -1.0, 1.0])
        rel_first = _quat_mul(inv_tip, seg_q[0])
        rel_last = _quat_mul(inv_tip, seg_q[-1])
        d3 = _rotate(rel_first, np.array([0.0, 0.0, 1.0]))
        rel_inside = _quat_mul(_quat_between(d3, np.array([0.0, 0.0, -1.0])), rel_first)
        self.geometry = g = LoopGeometry()
        g.first, g.segment_first, g.nodes, g.body, g.pitch = rod.particle_start, rod.segment_start, N, int(body), pitch
        g.rel_first = wp.quat(*[float(c) for c in rel_first])
        g.rel_last = wp.quat(*[float(c) for c in rel_last])
        g.rel_inside = wp.quat(*[float(c) for c in rel_inside / np.linalg.norm(rel_inside)])
        self.pins = p = LoopPins()
        #: ``(num_envs,)`` int32: the loop's active index (sofa_env's), N - 1 = fully open.
        self.active_index = p.active_index = wp.full(n, N - 1, dtype=wp.int32, device=dev)
        p.off_from = wp.zeros((n, N), dtype=wp.vec3, device=dev)
        p.off_to = wp.zeros((n, N), dtype=wp.vec3, device=dev)
        p.rel_from = wp.zeros((n, N - 1), dtype=wp.quat, device=dev)
        p.rel_to = wp.zeros((n, N - 1), dtype=wp.quat, device=dev)
        p.pinned_segment = wp.zeros((n, N - 1), dtype=wp.int32, device=dev)
        world.add_solver(self)

    def settle(self, env_mask: wp.array) -> None:
        """Pins of the masked envs at rest at their ``active_index`` (the loop was just placed there)."""
        w, s = self.world, self.world.state
        launching.launch(settle_loop_pins, dim=(w.num_envs, self.nodes), inputs=[env_mask, self.geometry, self.pins],
                         outputs=[s.attach_particle, s.attach_body, s.attach_offset, s.attach_compliance],
                         device=w.device)

    def pre_step(self, dt: float) -> None:
        """Once per physics step, after the instrument's body pose is written and before ``World.step(dt)``."""
        w, s = self.world, self.world.state
        substeps = w.substeps_for(dt)
        launching.launch(pin_loop, dim=(w.num_envs, self.nodes),
                         inputs=[self.geometry, self.pins, w.body_q_previous, s.particle_q, s.segment_q,
                                 1.0 / substeps],
                         outputs=[s.attach_particle, s.attach_body, s.attach_offset, s.attach_compliance],
                         device=w.device)

    def record_sweep(self, world, launch, sweep) -> None:
        s = world.state
        next_blend = min(1.0, (sweep.substep + 2) / sweep.substeps) if sweep.iteration == sweep.iterations - 1 \
            else sweep.blend
        launch(advance_loop_pins, (world.num_envs, self.nodes),
               [self.geometry, self.pins, world.body_q_previous, s.body_q, sweep.blend, next_blend,
                s.attach_particle], [s.attach_offset, s.segment_q])
