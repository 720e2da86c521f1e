"""Instrument bodies, collision shapes and procedural visual meshes, posed per env from a TPSD tip transform.

An :class:`InstrumentShape` adds kinematic bodies to a ``SceneBuilder`` (the shaft, and for articulated tools two
jaws or blades), then colliders to a :class:`lapwarp.contact.ContactSystem`, and poses the bodies from the
instrument's tip pose (``TPSDInstruments.pose``) and a per-env jaw angle: one kernel launch into the instrument's
own pose array, handed to ``World.set_body_poses``. Frames follow sofa_env: the shaft is the tip's local +Z (tip at
the origin, shaft behind it at negative z); the jaws hinge at the tip and rotate about local X, jaw A by ``+angle``
and jaw B by ``-angle`` (degrees at the API), so the opening between them is ``2 * angle``.

Geometry (metres) after sofa_env's collision models: grasper jaws 25 mm with r = 1 mm spheres -> capsules;
shaft r = 2.25 mm; cauter hook r = 0.8 mm at the tip with a r = 1.5 mm shaft; scissors blades 15 mm.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import trimesh
import warp as wp

from lapwarp import launching
from lapwarp.kernels.bodies import pose_instrument_bodies, step_jaw_angle

KINDS = ("grasper", "cauter", "scissors", "loop", "endoscope")
#: The electrocautery hook's cutting centre on its shaft axis, beyond the tip (sofa_env's cutting sphere 5), m.
CAUTER_CUTTING_CENTER = 0.0144


def _capsule_between(z0: float, z1: float, radius: float, y: float = 0.0, axis: str = "z"):
    """(params, transform) of a capsule whose axis runs from z0 to z1 (or along y at height y for axis='y')."""
    if axis == "z":
        return (radius, 0.5 * (z1 - z0), 0.0), (0.0, y, 0.5 * (z0 + z1), 0.0, 0.0, 0.0, 1.0)
    # axis along local y: rotate the capsule's z onto y (about x by -90 deg); here z0..z1 are y-limits, y = z
    s = math.sin(-math.pi / 4.0)
    return (radius, 0.5 * (z1 - z0), 0.0), (0.0, 0.5 * (z0 + z1), y, s, 0.0, 0.0, math.cos(-math.pi / 4.0))


def _visual_capsule(params, tf) -> trimesh.Trimesh:
    r, hh, _ = params
    m = trimesh.creation.capsule(height=2.0 * hh, radius=r, count=[8, 8])
    q = tf[3:]
    mat = trimesh.transformations.quaternion_matrix([q[3], q[0], q[1], q[2]])
    mat[:3, 3] = tf[:3]
    m.apply_transform(mat)
    return m


@dataclass
class InstrumentShape:
    """Bodies, colliders and visuals of one instrument (see the module docstring).

    Args:
        builder: the SceneBuilder that gets the bodies (before ``finalize``).
        kind: one of ``grasper``, ``cauter``, ``scissors``, ``loop``, ``endoscope``.
        name: body name prefix.
        jaw_length: jaw / blade length, m (grasper 25 mm, scissors 15 mm by default).
        jaw_radius: jaw capsule radius, m.
        shaft_radius, shaft_length: m.
        angle_limits: jaw angle limits in degrees (articulated kinds).
    """

    builder: object
    kind: str = "grasper"
    name: str = "instrument"
    jaw_length: float | None = None
    jaw_radius: float = 1.0e-3
    shaft_radius: float | None = None
    shaft_length: float = 0.15
    angle_limits: tuple = (0.0, 60.0)
    bodies: list = field(default_factory=list)
    parts: list = field(default_factory=list)  # (role, params, transform) role: shaft | jaw_a | jaw_b | tool
    shape_ids: dict = field(default_factory=dict)  # role -> [shape ids]
    # allocated by the first pose(): (num_envs, len(bodies)) poses, the body indices, closed jaws (angle 0)
    _poses: wp.array | None = field(default=None, init=False, repr=False, compare=False)
    _body_index: wp.array | None = field(default=None, init=False, repr=False, compare=False)
    _closed_jaws: wp.array | None = field(default=None, init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        if self.kind not in KINDS:
            raise ValueError(f"kind {self.kind!r} is not one of {KINDS}")
        b = self.builder
        self.articulated = self.kind in ("grasper", "scissors")
        if self.jaw_length is None:
            self.jaw_length = 0.025 if self.kind == "grasper" else 0.015
        default_r = {"grasper": 2.25e-3, "cauter": 1.5e-3, "scissors": 2.25e-3, "loop": 2.0e-3, "endoscope": 5.0e-3}
        if self.shaft_radius is None:
            self.shaft_radius = default_r[self.kind]
        self.shaft_body = b.add_body(f"{self.name}/shaft")
        self.bodies = [self.shaft_body]
        self.jaw_a = self.jaw_b = -1
        if self.articulated:
            self.jaw_a = b.add_body(f"{self.name}/jaw_a")
            self.jaw_b = b.add_body(f"{self.name}/jaw_b")
            self.bodies += [self.jaw_a, self.jaw_b]
        r = self.shaft_radius
        # shaft ends a little behind the hinge so the open jaws are free
        self.parts.append(("shaft", *_capsule_between(-self.shaft_length, -r - 0.001, r)))
        if self.articulated:
            jr, L = self.jaw_radius, self.jaw_length
            # closed jaws touch along the shaft axis: jaw A (rotated +angle about x -> towards -y) sits at y = -r
            self.parts.append(("jaw_a", *_capsule_between(jr, L, jr, y=-jr)))
            self.parts.append(("jaw_b", *_capsule_between(jr, L, jr, y=jr)))
        elif self.kind == "cauter":
            self.parts.append(("tool", *_capsule_between(-0.001, CAUTER_CUTTING_CENTER, 0.8e-3)))
            self.parts.append(("tool", *_capsule_between(-1.5e-3, 1.6e-3, 0.8e-3, y=CAUTER_CUTTING_CENTER, axis="y")))

    def body_of(self, role: str) -> int:
        return {"shaft": self.shaft_body, "tool": self.shaft_body, "jaw_a": self.jaw_a, "jaw_b": self.jaw_b}[role]

    def add_colliders(self, contact, thickness: float = 0.0, mu_static: float = 0.5, mu_kinetic=None,
                      groups=None) -> dict:
        """Add the instrument's capsules to a ContactSystem; returns ``{role: [shape ids]}``."""
        for role, params, tf in self.parts:
            sid = contact.add_capsule(params[0], params[1], body=self.body_of(role), transform=tf,
                                      thickness=thickness, mu_static=mu_static, mu_kinetic=mu_kinetic, groups=groups,
                                      name=f"{self.name}/{role}{len(self.shape_ids.get(role, []))}")
            self.shape_ids.setdefault(role, []).append(sid)
        return self.shape_ids

    def visual_meshes(self) -> list[tuple[str, int, trimesh.Trimesh]]:
        """Procedural visual meshes ``(role, body, mesh in the body frame)``, one per collision part."""
        return [(role, self.body_of(role), _visual_capsule(p, tf)) for role, p, tf in self.parts]

    def body_array(self) -> wp.vec3i:
        return wp.vec3i(self.shaft_body, self.jaw_a, self.jaw_b)

    def pose(self, world, tip_pose: wp.array, column: int, jaw_angle_deg: wp.array | None = None,
             teleport_mask: wp.array | None = None) -> None:
        """Pose this instrument's bodies in every env: one launch writes them into the instrument's own
        ``(num_envs, len(bodies))`` array, which ``world.set_body_poses`` then applies (graph-capturable; the first
        call allocates that array).

        Args:
            world: the World whose kinematic bodies these are.
            tip_pose: ``(num_envs, k)`` ``wp.transform`` tip poses (``TPSDInstruments.pose``).
            column: this instrument's column of ``tip_pose``.
            jaw_angle_deg: ``(num_envs,)`` float jaw angle in degrees (articulated kinds; None: closed jaws).
            teleport_mask: ``(num_envs,)`` int32 or None: the masked envs' bodies jump to the pose and keep it as
                their start state (at reset) instead of sweeping there during the next step (see
                ``World.set_body_poses``).
        """
        n, dev = world.num_envs, world.device
        if self._poses is None or self._poses.shape[0] != n:
            self._poses = wp.zeros((n, len(self.bodies)), dtype=wp.transform, device=dev)
            self._body_index = wp.array(self.bodies, dtype=wp.int32, device=dev)
            self._closed_jaws = wp.zeros(n, dtype=float, device=dev)
        ang = jaw_angle_deg if jaw_angle_deg is not None else self._closed_jaws
        launching.launch(pose_instrument_bodies, dim=n, inputs=[tip_pose, int(column), ang], outputs=[self._poses],
                         device=dev)
        world.set_body_poses(self._poses, self._body_index, teleport_mask)

    def step_jaw(self, actions: wp.array, column: int, max_speed_deg: float, dt: float, angle_deg: wp.array,
                 grasped: wp.array | None = None) -> None:
        """Jaw angle follows the action: ``angle += clip(a) * max_speed * dt`` within ``angle_limits``; closing
        is ignored in envs whose ``grasped`` flag is set (as sofa_env's gripper)."""
        g = grasped if grasped is not None else wp.zeros(1, dtype=wp.int32, device=angle_deg.device)
        launching.launch(step_jaw_angle, dim=angle_deg.shape[0],
                         inputs=[actions, int(column), float(max_speed_deg), float(dt), float(self.angle_limits[0]),
                                 float(self.angle_limits[1]), g, int(grasped is not None)], outputs=[angle_deg],
                         device=angle_deg.device)


def tip_poses_numpy(positions, quats=None) -> np.ndarray:
    """Helper for tests/scripts: ``(num_envs, 1, 7)`` transforms from tip positions (and xyzw quaternions)."""
    p = np.asarray(positions, dtype=np.float32).reshape(-1, 3)
    q = np.tile([0, 0, 0, 1], (len(p), 1)) if quats is None else np.asarray(quats).reshape(-1, 4)
    return np.concatenate([p, q], axis=1).astype(np.float32)[:, None, :]
