"""The instrument rig of a task: its pivotized (TPSD) instruments, their kinematic bodies, colliders, jaws, activation
and grasping, driven by one action path for continuous and discrete actions.

A task lists its instruments as :class:`InstrumentSpec` and gets an :class:`InstrumentRig`::

    rig = InstrumentRig([InstrumentSpec(name="right_hook", tpsd=cfg_right, shape="cauter")], builder)
    world = builder.finalize(...)
    rig.finalize(world)                       # TPSD state arrays, body pose buffers
    shape_ids = rig.add_colliders(contact)    # before contact.finalize()

and then, inside the env step, ``rig.apply_actions(actions, time_step)`` once per env step and ``rig.step()`` once per
physics step (frame skip); ``rig.reset(env_mask, rng)`` at reset. The action vector is the concatenation of each
instrument's block in ``action_order``: pan, tilt, spin, depth, then the jaw angle (articulated shapes with
``jaw_speed_deg``) and the activation (``activation=True``). Every component is normalised to [-1, 1] by its maximum
speed, and :attr:`InstrumentRig.action_layout` gives each component's discrete step in the same units, so a discrete
action is a row of the continuous table and moves exactly like it.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import warp as wp

from lapwarp import launching
from lapwarp.instrument_shapes import CAUTER_CUTTING_CENTER, InstrumentShape
from lapwarp.instruments import STATE_LIMITS_VIOLATED, WORKSPACE_VIOLATED, TPSDConfig, TPSDInstruments
from lapwarp.kernels.bodies import hinged_jaw_pose
from lapwarp.kernels.kinematics import ptsd_to_transform, step_tpsd_instrument
from lapwarp.kernels.random import rand_uniform
from lapwarp.tasks.spec import ActionBlock, ActionLayout, to_unit

wp.set_module_options({"enable_backward": False})

#: Roles of a rig body: the instrument's shaft (its tip frame) and the two jaws of articulated instruments.
ROLE_SHAFT, ROLE_JAW_A, ROLE_JAW_B = 0, 1, 2


@dataclass(kw_only=True)
class InstrumentSpec:
    """One instrument of a rig.

    Attributes:
        name: instrument name (body and collider names start with it).
        tpsd: its pivotized kinematics, limits, speeds and reset noise (degrees and metres).
        shape: ``lapwarp.instrument_shapes`` kind with kinematic bodies and colliders (``cauter``, ``grasper``,
            ``scissors``, ...) or None for kinematics only (an endoscope, a hook checked by reward only).
        jaw_speed_deg: jaw angle speed at action 1 (deg/s) for articulated shapes; None = no jaw action.
        jaw_discrete_speed_deg: jaw speed of a discrete action (deg/s); default ``jaw_speed_deg``.
        jaw_start_deg: jaw angle at reset (deg).
        jaw_noise_deg: uniform reset noise of the jaw angle, +- deg around ``jaw_start_deg`` (clipped to the jaw's
            angle limits; drawn only when non-zero, so other instruments' RNG streams do not change).
        activation: add an activation component: outside the dead zone its sign switches the instrument on/off.
        activation_deadzone: dead zone of the activation component.
    """

    name: str
    tpsd: TPSDConfig
    shape: str | None = None
    jaw_speed_deg: float | None = None
    jaw_discrete_speed_deg: float | None = None
    jaw_start_deg: float = 0.0
    jaw_noise_deg: float = 0.0
    activation: bool = False
    activation_deadzone: float = 0.1


# ---------------------------------------------------------------------------------------------------- kernels
@wp.struct
class RigContacts:
    """What a reward kernel needs to ask "did instrument k touch particle group g in the last step": the
    ``ContactSystem``'s report counts and (shape, group) -> column table, and which instrument (-1: none) and
    whether its working end (hook, jaws, blades; not the shaft) each collider is."""

    report_count: wp.array2d(dtype=wp.int32)
    pair_index: wp.array2d(dtype=wp.int32)
    shape_instrument: wp.array(dtype=wp.int32)
    shape_is_tool: wp.array(dtype=wp.int32)


@wp.struct
class RigState:
    """The rig's per-env arrays for kernels, ``(num_envs, K)`` each: PTSD (rad, m), tip and RCM transforms, flags of
    the last update, activation (1 = on) and jaw angle (deg)."""

    ptsd: wp.array2d(dtype=wp.vec4)
    pose: wp.array2d(dtype=wp.transform)
    rcm: wp.array2d(dtype=wp.transform)
    flags: wp.array2d(dtype=wp.int32)
    active: wp.array2d(dtype=wp.int32)
    jaw_angle: wp.array2d(dtype=float)


@wp.struct
class RigBounds:
    """What normalises a TPSD task's observations and distances: the tips' Cartesian workspace (m), the PTSD state
    limits (rad, m) and one over the workspace diagonal (sofa_env's distance factor). :meth:`InstrumentRig.bounds`."""

    ws_low: wp.vec3
    ws_high: wp.vec3
    state_low: wp.vec4
    state_high: wp.vec4
    inv_diagonal: float


#: candidates of :func:`ptsd_step`: pan +/-, tilt +/-, depth +/- (the one-component discrete moves experts weigh)
PTSD_STEPS = 6


@wp.func
def ptsd_step_component(j: int) -> int:
    """The PTSD component candidate ``j`` moves: 0 pan, 1 tilt, 3 depth (spin is left alone)."""
    k = j // 2
    return wp.where(k == 2, 3, k)


@wp.func
def ptsd_step(s: wp.vec4, step: wp.vec4, j: int) -> wp.vec4:
    """PTSD ``s`` after candidate ``j`` (0 .. ``PTSD_STEPS`` - 1) of the discrete moves: its component by +``step``
    (even ``j``) or -``step`` (odd); the env's discrete action index of the move is :func:`ptsd_step_action`."""
    c = ptsd_step_component(j)
    t = s
    t[c] = s[c] + wp.where(j % 2 == 0, step[c], -step[c])
    return t


@wp.func
def ptsd_step_action(j: int) -> int:
    """The discrete action index of candidate ``j`` (row ``2 c`` moves component ``c`` up, ``2 c + 1`` down)."""
    return 2 * ptsd_step_component(j) + j % 2


@wp.func
def ptsd_accepted(rcm: wp.transform, t: wp.vec4, b: RigBounds) -> bool:
    """Whether the env accepts PTSD ``t`` (it rejects a move beyond the state limits or with the tip out of the
    Cartesian workspace)."""
    inside = True
    for c in range(4):
        inside = inside and t[c] >= b.state_low[c] and t[c] <= b.state_high[c]
    x = wp.transform_get_translation(ptsd_to_transform(rcm, t))
    for i in range(3):
        inside = inside and x[i] >= b.ws_low[i] and x[i] <= b.ws_high[i]
    return inside


@wp.func
def over_diagonal(x: float, inv_diagonal: float) -> float:
    """sofa_env's normalisation of distance and velocity features: x over the workspace diagonal, clipped to
    [-1, 1]."""
    return wp.clamp(x * inv_diagonal, -1.0, 1.0)


@wp.func
def write_unit_point(out: wp.array2d(dtype=wp.float32), env: int, col: int, x: wp.vec3, b: RigBounds):
    """A position mapped from the workspace box to [-1, 1] into ``out[env, col:col + 3]``."""
    for i in range(3):
        out[env, col + i] = to_unit(x[i], b.ws_low[i], b.ws_high[i])


@wp.func
def write_unit_ptsd(out: wp.array2d(dtype=wp.float32), env: int, col: int, s: wp.vec4, b: RigBounds):
    """A PTSD state mapped from the state limits to [-1, 1] into ``out[env, col:col + 4]``."""
    for i in range(4):
        out[env, col + i] = to_unit(s[i], b.state_low[i], b.state_high[i])


#: The hook's cutting tip (sofa_env's carving sphere 0, the end of the cross bar) in the tip frame, m.
CAUTER_TIP = wp.constant(wp.vec3(0.0, -1.5e-3, CAUTER_CUTTING_CENTER))


@wp.func
def cutting_center(tip: wp.transform) -> wp.vec3:
    """The electrocautery hook's cutting centre (on the shaft axis, ``CAUTER_CUTTING_CENTER`` beyond the tip)."""
    return wp.transform_point(tip, wp.vec3(0.0, 0.0, CAUTER_CUTTING_CENTER))


@wp.func
def place_hook_capsules(env: int, pose: wp.array2d(dtype=wp.transform), active: wp.array2d(dtype=wp.int32),
                        tool_a: wp.array2d(dtype=wp.vec3), tool_b: wp.array2d(dtype=wp.vec3),
                        tool_active: wp.array(dtype=wp.int32)):
    """The electrocautery hook's (instrument 0) two cutting capsules in the env frame for a ``CuttingSystem`` with
    ``num_tools=2`` -- the cross bar at the tip and the last 7 mm of the hook, the part sofa_env's carving spheres
    cover -- and whether the hook is switched on (for a task's kernel that has more to do per physics step)."""
    tf = pose[env, 0]
    tool_a[env, 0] = wp.transform_point(tf, wp.vec3(0.0, -1.5e-3, CAUTER_CUTTING_CENTER))
    tool_b[env, 0] = wp.transform_point(tf, wp.vec3(0.0, 1.6e-3, CAUTER_CUTTING_CENTER))
    tool_a[env, 1] = wp.transform_point(tf, wp.vec3(0.0, 0.0, 7.4e-3))
    tool_b[env, 1] = wp.transform_point(tf, wp.vec3(0.0, 0.0, CAUTER_CUTTING_CENTER))
    tool_active[env] = active[env, 0]


@wp.kernel
def place_hook_tools(pose: wp.array2d(dtype=wp.transform), active: wp.array2d(dtype=wp.int32),
                     tool_a: wp.array2d(dtype=wp.vec3), tool_b: wp.array2d(dtype=wp.vec3),
                     tool_active: wp.array(dtype=wp.int32)):
    """Thread per env: ``place_hook_capsules``."""
    place_hook_capsules(wp.tid(), pose, active, tool_a, tool_b, tool_active)


@wp.func
def instrument_touches(contacts: RigContacts, env: int, k: int, group: int, tool_only: int) -> int:
    """1 if a collider of instrument ``k`` (its working end only with ``tool_only``) touched particle group
    ``group`` in the last step."""
    for s in range(contacts.shape_instrument.shape[0]):
        if contacts.shape_instrument[s] == k and (contacts.shape_is_tool[s] != 0 or tool_only == 0):
            pair = contacts.pair_index[s, group]
            if pair >= 0:
                if contacts.report_count[env, pair] > 0:
                    return 1
    return 0


@wp.func
def count_flag(flags: wp.array2d(dtype=wp.int32), env: int, bit: int) -> int:
    """Number of instruments of ``env`` whose last update raised ``bit`` (``STATE_LIMITS_VIOLATED`` ...)."""
    count = int(0)
    for k in range(flags.shape[1]):
        if (flags[env, k] & bit) != 0:
            count += 1
    return count


@wp.func
def rig_body_pose(tip: wp.transform, jaw_angle_deg: float, role: int) -> wp.transform:
    """A body riding on an instrument: the shaft on its tip frame, jaw A / B rotated by +angle / -angle about the
    tip's local x (``lapwarp.instrument_shapes``)."""
    if role == ROLE_SHAFT:
        return tip
    if role == ROLE_JAW_A:
        return hinged_jaw_pose(tip, jaw_angle_deg)
    return hinged_jaw_pose(tip, -jaw_angle_deg)


@wp.kernel
def pose_rig_bodies(
    tip_pose: wp.array2d(dtype=wp.transform),
    jaw_angle_deg: wp.array2d(dtype=float),
    body_instrument: wp.array(dtype=wp.int32),
    body_role: wp.array(dtype=wp.int32),
    poses_out: wp.array2d(dtype=wp.transform),
):
    """Body ``b`` rides on instrument ``body_instrument[b]`` (``rig_body_pose``)."""
    env, b = wp.tid()
    k = body_instrument[b]
    poses_out[env, b] = rig_body_pose(tip_pose[env, k], jaw_angle_deg[env, k], body_role[b])


@wp.kernel
def step_and_pose_rig(
    rcm: wp.array2d(dtype=wp.transform),
    state_low: wp.array(dtype=wp.vec4),
    state_high: wp.array(dtype=wp.vec4),
    workspace_low: wp.array(dtype=wp.vec3),
    workspace_high: wp.array(dtype=wp.vec3),
    delta: wp.array2d(dtype=wp.vec4),
    jaw_angle_deg: wp.array2d(dtype=float),
    body_instrument: wp.array(dtype=wp.int32),
    body_role: wp.array(dtype=wp.int32),
    body_ids: wp.array(dtype=wp.int32),
    ptsd: wp.array2d(dtype=wp.vec4),
    pose: wp.array2d(dtype=wp.transform),
    flags: wp.array2d(dtype=wp.int32),
    poses_out: wp.array2d(dtype=wp.transform),
    body_q: wp.array2d(dtype=wp.transform),
):
    """A rig without jaws to step, one physics step in one launch (a thread per env): every instrument's TPSD step
    (``kinematics.step_tpsd_instrument``), then its bodies posed and written into the World's ``body_q`` (what
    ``World.set_body_poses`` does outside a reset). Three launches per physics step were nearly all fixed cost."""
    env = wp.tid()
    for k in range(ptsd.shape[1]):
        step_tpsd_instrument(env, k, rcm, state_low, state_high, workspace_low, workspace_high, delta, ptsd, pose,
                             flags)
    for b in range(body_ids.shape[0]):
        k = body_instrument[b]
        tf = rig_body_pose(pose[env, k], jaw_angle_deg[env, k], body_role[b])
        poses_out[env, b] = tf
        body_q[env, body_ids[b]] = tf


@wp.kernel
def apply_activation(actions: wp.array2d(dtype=wp.float32), column: int, deadzone: float, k: int,
                     active: wp.array2d(dtype=wp.int32)):
    """sofa_env's activation: outside the dead zone the sign switches the instrument, inside it stays as it was."""
    env = wp.tid()
    a = actions[env, column]
    if wp.abs(a) > deadzone:
        if a > 0.0:
            active[env, k] = 1
        else:
            active[env, k] = 0


@wp.kernel
def reset_rig_state(env_mask: wp.array(dtype=wp.int32), jaw_start: wp.array(dtype=float),
                    jaw_noise: wp.array(dtype=float), jaw_limits: wp.array(dtype=wp.vec2),
                    rng: wp.array(dtype=wp.uint32), use_rng: int,
                    jaw_angle: wp.array2d(dtype=float), active: wp.array2d(dtype=wp.int32)):
    """Thread per env (the instruments in order, so each env's RNG stream is drawn in a fixed order)."""
    env = wp.tid()
    if env_mask[env] == 0:
        return
    for k in range(jaw_start.shape[0]):
        angle = jaw_start[k]
        if use_rng != 0 and jaw_noise[k] > 0.0:
            angle = wp.clamp(angle + rand_uniform(rng, env, -jaw_noise[k], jaw_noise[k]), jaw_limits[k][0],
                             jaw_limits[k][1])
        jaw_angle[env, k] = angle
        active[env, k] = 0


@wp.kernel
def restore_rig_state(env_mask: wp.array(dtype=wp.int32), ptsd_in: wp.array2d(dtype=wp.vec4),
                      rcm_in: wp.array2d(dtype=wp.transform), jaw_in: wp.array2d(dtype=float),
                      ptsd: wp.array2d(dtype=wp.vec4), rcm: wp.array2d(dtype=wp.transform),
                      pose: wp.array2d(dtype=wp.transform), flags: wp.array2d(dtype=wp.int32),
                      jaw_angle: wp.array2d(dtype=float), active: wp.array2d(dtype=wp.int32)):
    env, k = wp.tid()
    if env_mask[env] == 0:
        return
    ptsd[env, k] = ptsd_in[env, k]
    rcm[env, k] = rcm_in[env, k]
    pose[env, k] = ptsd_to_transform(rcm_in[env, k], ptsd_in[env, k])
    flags[env, k] = 0
    jaw_angle[env, k] = jaw_in[env, k]
    active[env, k] = 0


# ---------------------------------------------------------------------------------------------------- rig
class InstrumentRig:
    """Instruments, bodies and the action path of a task (see the module docstring).

    Args:
        specs: the instruments; their index in this list is their column in the state arrays
            (``ptsd``, ``pose``, ``flags``, ``jaw_angle``, ``active``).
        builder: the ``SceneBuilder`` that gets the kinematic bodies of instruments with a ``shape`` (before its
            ``finalize``); None when no instrument has one.
        action_order: instrument names in the order of their action blocks (default: the order of ``specs``).
    """

    def __init__(self, specs: Sequence[InstrumentSpec], builder=None, action_order: Sequence[str] | None = None):
        self.specs = list(specs)
        if not self.specs:
            raise ValueError("a rig needs at least one instrument")
        names = [s.name for s in self.specs]
        if len(set(names)) != len(names):
            raise ValueError(f"duplicate instrument names {names}")
        self.names = names
        self.num_instruments = len(self.specs)
        #: a rig without jaws steps its instruments and poses its bodies in one launch per physics step
        #: (``step_and_pose_rig``); False keeps the three launches (the same results)
        self.fuse_step = True
        order = list(action_order) if action_order is not None else names
        if sorted(order) != sorted(names):
            raise ValueError(f"action_order {order} must list every instrument of {names} once")
        self.action_order = order

        self.shapes: list[InstrumentShape | None] = []
        body_instrument, body_role = [], []
        for k, spec in enumerate(self.specs):
            shape = None
            if spec.shape is not None:
                if builder is None:
                    raise ValueError(f"instrument {spec.name!r} has a shape: pass the SceneBuilder")
                shape = InstrumentShape(builder, kind=spec.shape, name=spec.name)
                body_instrument += [k]
                body_role += [ROLE_SHAFT]
                if shape.articulated:
                    body_instrument += [k, k]
                    body_role += [ROLE_JAW_A, ROLE_JAW_B]
            if spec.jaw_speed_deg is not None and (shape is None or not shape.articulated):
                raise ValueError(f"instrument {spec.name!r} has a jaw action but no articulated shape")
            self.shapes.append(shape)
        self.body_ids_host = [b for shape in self.shapes if shape is not None for b in shape.bodies]
        self._body_instrument = np.asarray(body_instrument, np.int32)
        self._body_role = np.asarray(body_role, np.int32)

        # action layout: PTSD (+ jaw) (+ activation) per instrument, in action order
        blocks, self._ptsd_column, self._jaw_column, self._activation_column = [], {}, {}, {}
        offset = 0
        for name in order:
            spec = self.specs[names.index(name)]
            t = spec.tpsd
            blocks.append(ActionBlock(f"{name}/ptsd", 4, tuple(
                float(d / v) if v > 0 else 0.0 for d, v in zip(t.discrete_magnitude, t.max_velocity, strict=True))))
            self._ptsd_column[name] = offset
            offset += 4
            if spec.jaw_speed_deg is not None:
                jd = spec.jaw_discrete_speed_deg if spec.jaw_discrete_speed_deg is not None else spec.jaw_speed_deg
                blocks.append(ActionBlock(f"{name}/jaw", 1, (float(jd / spec.jaw_speed_deg),)))
                self._jaw_column[name] = offset
                offset += 1
            if spec.activation:
                blocks.append(ActionBlock(f"{name}/activation", 1, (1.0,)))
                self._activation_column[name] = offset
                offset += 1
        #: The continuous action vector of this rig and its discrete table (``ActionLayout``).
        self.action_layout = ActionLayout(blocks)
        # what an action of 1 moves per second, per action column: rad/s (pan, tilt, spin), m/s, deg/s (jaw), and 1 for
        # an activation switch (``action_scale``)
        rates = []
        for name in order:
            spec = self.specs[names.index(name)]
            rates += [v * k for v, k in zip(spec.tpsd.max_velocity, (math.pi / 180.0,) * 3 + (1.0,), strict=True)]
            rates += [spec.jaw_speed_deg] if spec.jaw_speed_deg is not None else []
            rates += [math.inf] if spec.activation else []
        self._rates = np.asarray(rates, dtype=np.float64)
        self.world = None
        self.grasps: dict[str, object] = {}

    # ------------------------------------------------------------------------------------------------ setup
    def finalize(self, world) -> InstrumentRig:
        """Allocate the per-env state on the World's device (after ``SceneBuilder.finalize``)."""
        self.world = world
        n, dev = world.num_envs, world.device
        K = self.num_instruments
        self.instruments = TPSDInstruments([s.tpsd for s in self.specs], n, device=str(dev),
                                           action_columns=[self._ptsd_column[s.name] for s in self.specs])
        self.jaw_angle = wp.zeros((n, K), dtype=float, device=dev)
        #: ``(num_envs, K)`` int32 activation state (1 = on) of instruments with an activation component.
        self.active = wp.zeros((n, K), dtype=wp.int32, device=dev)
        self._jaw_start = wp.array(np.array([s.jaw_start_deg for s in self.specs], np.float32), dtype=float,
                                   device=dev)
        self._jaw_noise = wp.array(np.array([s.jaw_noise_deg for s in self.specs], np.float32), dtype=float,
                                   device=dev)
        limits = [shape.angle_limits if shape is not None and shape.articulated else (0.0, 0.0)
                  for shape in self.shapes]
        self._jaw_limits = wp.array(np.asarray(limits, np.float32), dtype=wp.vec2, device=dev)
        self._no_rng = wp.zeros(1, dtype=wp.uint32, device=dev)
        self._jaw_views = [self.jaw_angle[:, k] for k in range(K)]
        #: ``RigState`` view of the arrays above, for kernels.
        self.state = RigState()
        ins = self.instruments
        self.state.ptsd, self.state.pose, self.state.rcm, self.state.flags = ins.ptsd, ins.pose, ins.rcm, ins.flags
        self.state.active, self.state.jaw_angle = self.active, self.jaw_angle
        self.num_bodies = len(self.body_ids_host)
        if self.num_bodies:
            self.body_ids = wp.array(np.asarray(self.body_ids_host, np.int32), dtype=wp.int32, device=dev)
            self._body_instrument_arr = wp.array(self._body_instrument, dtype=wp.int32, device=dev)
            self._body_role_arr = wp.array(self._body_role, dtype=wp.int32, device=dev)
            self.body_poses = wp.zeros((n, self.num_bodies), dtype=wp.transform, device=dev)
        return self

    def action_scale(self, control_dt: float) -> np.ndarray:
        """What a continuous action of 1 changes in one env step of ``control_dt`` seconds, per action column (rad,
        rad, rad, m, then deg for a jaw; 1 for an activation switch): scripted experts divide their state errors by
        it to get actions."""
        return np.where(np.isinf(self._rates), 1.0, self._rates * float(control_dt))

    def add_colliders(self, contact, **kwargs) -> dict[str, dict[str, list[int]]]:
        """Add every shaped instrument's capsules to a ``ContactSystem`` (before its ``finalize``); keyword arguments
        go to ``InstrumentShape.add_colliders`` (``mu_static``, ``thickness``, ``groups``). Returns
        ``{instrument: {role: [shape ids]}}``; after ``contact.finalize()``, :meth:`contacts` views the reports."""
        ids = {spec.name: shape.add_colliders(contact, **kwargs)
               for spec, shape in zip(self.specs, self.shapes, strict=True) if shape is not None}
        self._shape_table = []
        for name, roles in ids.items():
            for role, sids in roles.items():
                self._shape_table += [(sid, self.names.index(name), int(role != "shaft")) for sid in sids]
        self._contact = contact
        return ids

    def contacts(self) -> RigContacts:
        """The ``RigContacts`` view of the contact reports (after ``contact.finalize()``), for reward kernels."""
        contact, dev = self._contact, self.world.device
        size = max(sid for sid, _, _ in self._shape_table) + 1
        instrument, tool = np.full(size, -1, np.int32), np.zeros(size, np.int32)
        for sid, k, is_tool in self._shape_table:
            instrument[sid], tool[sid] = k, is_tool
        view = RigContacts()
        view.report_count, view.pair_index = contact.report_count, contact.pair_index
        view.shape_instrument = wp.array(instrument, dtype=wp.int32, device=dev)
        view.shape_is_tool = wp.array(tool, dtype=wp.int32, device=dev)
        return view

    def add_grasping(self, name: str, contact, **kwargs):
        """A ``GraspSystem`` for the articulated instrument ``name`` (after ``contact.finalize()``); its ``grasped``
        flag then blocks closing the jaw further, as in sofa_env."""
        from lapwarp.grasping import GraspSystem

        k = self.names.index(name)
        grasp = GraspSystem(contact, self.shapes[k], self._jaw_views[k], **kwargs)
        self.grasps[name] = grasp
        return grasp

    # ------------------------------------------------------------------------------------------------ stepping
    def apply_actions(self, actions: wp.array, time_step: float) -> None:
        """Normalised actions ``(num_envs, action_layout.size)`` in [-1, 1] -> the per-physics-step PTSD increments,
        activation switches (once per env step)."""
        self.instruments.set_actions(actions, time_step)
        self._actions, self._time_step = actions, float(time_step)
        for name, col in self._activation_column.items():
            k = self.names.index(name)
            launching.launch(apply_activation, dim=self.world.num_envs,
                             inputs=[actions, col, self.specs[k].activation_deadzone, k], outputs=[self.active],
                             device=self.world.device)

    def step(self) -> None:
        """One physics step: move the instruments (sofa_env's limit rules), the jaws, and pose the bodies."""
        if self.fuse_step and not self._jaw_column and self.num_bodies:
            # no jaw moves between the instruments and their bodies: one launch
            ins, w = self.instruments, self.world
            launching.launch(step_and_pose_rig, dim=w.num_envs,
                             inputs=[ins.rcm, ins.state_low, ins.state_high, ins.workspace_low, ins.workspace_high,
                                     ins.delta, self.jaw_angle, self._body_instrument_arr, self._body_role_arr,
                                     self.body_ids],
                             outputs=[ins.ptsd, ins.pose, ins.flags, self.body_poses, w.state.body_q],
                             device=w.device)
            return
        self.instruments.step()
        for name, col in self._jaw_column.items():
            k = self.names.index(name)
            grasp = self.grasps.get(name)
            self.shapes[k].step_jaw(self._actions, col, self.specs[k].jaw_speed_deg, self._time_step,
                                    self._jaw_views[k], grasp.grasped if grasp is not None else None)
        self._pose_bodies(None)

    def reset(self, env_mask: wp.array, rng: wp.array | None) -> None:
        """Re-draw the masked envs' instrument states (TPSD noise from their RNG streams), open the jaws to their
        start angle, switch activations off and teleport the bodies there (start state of the World)."""
        w = self.world
        self.instruments.reset(env_mask, rng)
        launching.launch(reset_rig_state, dim=w.num_envs,
                         inputs=[env_mask, self._jaw_start, self._jaw_noise, self._jaw_limits,
                                 rng if rng is not None else self._no_rng, int(rng is not None)],
                         outputs=[self.jaw_angle, self.active], device=w.device)
        self._pose_bodies(env_mask)

    def snapshot(self) -> tuple[wp.array, wp.array, wp.array]:
        """Copies of every env's (PTSD, RCM, jaw angle) for :meth:`restore`."""
        return wp.clone(self.instruments.ptsd), wp.clone(self.instruments.rcm), wp.clone(self.jaw_angle)

    def restore(self, env_mask: wp.array, snapshot: tuple[wp.array, wp.array, wp.array]) -> None:
        """Put the masked envs' instruments back to a :meth:`snapshot` (activations off, flags cleared) and teleport
        their bodies there (a task that starts its episodes from a scripted state); graph-capturable."""
        w, ins = self.world, self.instruments
        launching.launch(restore_rig_state, dim=(w.num_envs, self.num_instruments), inputs=[env_mask, *snapshot],
                         outputs=[ins.ptsd, ins.rcm, ins.pose, ins.flags, self.jaw_angle, self.active], device=w.device)
        self._pose_bodies(env_mask)

    def _pose_bodies(self, teleport_mask: wp.array | None) -> None:
        if not self.num_bodies:
            return
        w = self.world
        launching.launch(pose_rig_bodies, dim=(w.num_envs, self.num_bodies),
                         inputs=[self.instruments.pose, self.jaw_angle, self._body_instrument_arr, self._body_role_arr],
                         outputs=[self.body_poses], device=w.device)
        w.set_body_poses(self.body_poses, self.body_ids, teleport_mask)

    def set_ptsd(self, ptsd, env_ids=None) -> None:
        """Host utility for tests and tools: write instrument states (deg, deg, deg, m; shape as
        ``TPSDInstruments.set_ptsd``) without limit checks and teleport the bodies there (no sweep)."""
        self.instruments.set_ptsd(ptsd, env_ids)
        self._pose_bodies(wp.ones(self.world.num_envs, dtype=wp.int32, device=self.world.device))

    def visual_objects(self, colors, first_segmentation_id: int) -> list:
        """``VisualObject``s of every shaped instrument's bodies (shaft with its tool, and each jaw), placed by the
        body poses the rig writes every physics step (no update launch of their own). ``colors`` holds one RGB per
        instrument (in rig order); instrument ``k`` gets segmentation id ``first_segmentation_id + k``."""
        import trimesh

        from lapwarp.visuals import VisualObject

        objects = []
        column = 0
        for k, shape in enumerate(self.shapes):
            if shape is None:
                continue
            for body in shape.bodies:
                meshes = [m for _, b, m in shape.visual_meshes() if b == body]
                mesh = trimesh.util.concatenate(meshes)
                objects.append(VisualObject(self.world.model.body_names[body], "rigid", colors[k],
                                            first_segmentation_id + k, mesh.vertices, mesh.faces,
                                            self.body_poses[:, column:column + 1]))
                column += 1
        return objects

    # ------------------------------------------------------------------------------------------------ views
    @property
    def ptsd(self) -> wp.array:
        """``(num_envs, K)`` vec4 (pan, tilt, spin rad; depth m)."""
        return self.instruments.ptsd

    @property
    def pose(self) -> wp.array:
        """``(num_envs, K)`` tip transforms in the env frame (local +Z = shaft)."""
        return self.instruments.pose

    @property
    def rcm(self) -> wp.array:
        return self.instruments.rcm

    @property
    def flags(self) -> wp.array:
        """``(num_envs, K)`` int32 bits of the last update (``STATE_LIMITS_VIOLATED``, ``WORKSPACE_VIOLATED``)."""
        return self.instruments.flags

    def bounds(self, workspace_low, workspace_high) -> RigBounds:
        """``RigBounds`` of the given Cartesian workspace (m) and the first instrument's state limits."""
        b = RigBounds()
        b.ws_low, b.ws_high = wp.vec3(*workspace_low), wp.vec3(*workspace_high)
        b.state_low, b.state_high = self.state_limits()
        b.inv_diagonal = 1.0 / float(np.linalg.norm(np.subtract(workspace_high, workspace_low)))
        return b

    def state_limits(self) -> tuple[wp.vec4, wp.vec4]:
        """(low, high) PTSD state limits of the first instrument in rad / m (for observation normalisation)."""
        to_internal = np.array([math.pi / 180.0] * 3 + [1.0])
        t = self.specs[0].tpsd
        return (wp.vec4(*(np.asarray(t.state_low) * to_internal)), wp.vec4(*(np.asarray(t.state_high) * to_internal)))


__all__ = ["CAUTER_CUTTING_CENTER", "InstrumentRig", "InstrumentSpec", "RigBounds", "RigContacts", "RigState",
           "STATE_LIMITS_VIOLATED", "WORKSPACE_VIOLATED", "count_flag", "cutting_center", "instrument_touches",
           "over_diagonal", "write_unit_point", "write_unit_ptsd"]
