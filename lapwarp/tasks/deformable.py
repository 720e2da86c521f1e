"""The deformable objects of a task: how they enter the scene (builder), what holds them (springs to world anchors,
attachments to instrument bodies), and how each env re-places them at reset.

:class:`DeformableObject` wraps one ``SceneBuilder`` object (particles, cloth, tet mesh or rod). Its anchors are
sofa_env's ``RestShapeSpringsForceField``: springs of stiffness ``k`` (compliance ``1 / k``) from particles to points
of the env frame. A task's reset kernel draws each env's anchor points and stiffnesses; :meth:`place_anchors` then
moves the anchors there and puts the particles at rest at ``anchor + rest_offset`` (e.g. the gravity sag), writing
only ``world.state`` rows of the masked envs (the env base saves them as the World's start state).
:func:`rope_newton_tolerance` resolves a rope task's Newton tolerance against the chain solver in use.
"""

from __future__ import annotations

import numpy as np
import warp as wp

from lapwarp import launching

wp.set_module_options({"enable_backward": False})


def rope_newton_tolerance(field: str, value: float | None, chain_solver: str,
                          default_on: tuple[str, float] | None = None) -> float:
    """``World.rod_newton_tolerance`` for a rope (thread) task's config ``field`` of ``value``: ``None`` means the
    tolerance of ``default_on = (solver, tolerance)`` where the ropes run that solver (the task's GPU chain solve,
    one that stops early) and 0 elsewhere (every Newton step); a value > 0 with a solver that runs every step is
    refused rather than ignored."""
    if value is None:
        return default_on[1] if default_on is not None and chain_solver == default_on[0] else 0.0
    if value and chain_solver not in ("registers", "hybrid", "pcr"):
        raise ValueError(f"{field}={value!r} stops the Newton steps of the register-resident, hybrid and pcr chain "
                         f"solves only; this env runs chain_solver {chain_solver!r}: leave it None or 0")
    return value


@wp.kernel
def place_anchored_particles(
    env_mask: wp.array(dtype=wp.int32),
    particles: wp.array(dtype=wp.int32),
    slots: wp.array(dtype=wp.int32),
    anchors: wp.array2d(dtype=wp.vec3),
    stiffness: wp.array2d(dtype=float),
    rest_offset: wp.vec3,
    particle_q: wp.array2d(dtype=wp.vec3),
    particle_qd: wp.array2d(dtype=wp.vec3),
    attach_offset: wp.array2d(dtype=wp.vec3),
    attach_compliance: wp.array2d(dtype=float),
):
    env, k = wp.tid()
    if env_mask[env] == 0:
        return
    p = particles[k]
    s = slots[k]
    a = anchors[env, k]
    particle_q[env, p] = a + rest_offset
    particle_qd[env, p] = wp.vec3(0.0)
    attach_offset[env, s] = a
    attach_compliance[env, s] = 1.0 / stiffness[env, k]


class DeformableObject:
    """One deformable object of a task's scene (see the module docstring).

    Build it with a classmethod (:meth:`particles`, :meth:`cloth`, :meth:`tet_mesh`, :meth:`rod`; keyword arguments go
    to the ``SceneBuilder`` call), add anchors or body attachments before ``builder.finalize``, then
    :meth:`finalize` with the World.

    Attributes:
        obj: the builder's ``SceneObject`` (particle range, topology).
    """

    def __init__(self, builder, obj):
        self.builder = builder
        self.obj = obj
        self.world = None
        self._anchor_particles: list[int] = []
        self._anchor_slots: list[int] = []

    @classmethod
    def particles(cls, builder, positions, **kwargs) -> DeformableObject:
        """Free particles (``SceneBuilder.add_particles``)."""
        return cls(builder, builder.add_particles(positions, **kwargs))

    @classmethod
    def cloth(cls, builder, vertices, triangles, **kwargs) -> DeformableObject:
        """A cloth sheet (``SceneBuilder.add_cloth``)."""
        return cls(builder, builder.add_cloth(vertices, triangles, **kwargs))

    @classmethod
    def tet_mesh(cls, builder, vertices, tets, **kwargs) -> DeformableObject:
        """A volumetric FEM mesh (``SceneBuilder.add_tet_mesh``)."""
        return cls(builder, builder.add_tet_mesh(vertices, tets, **kwargs))

    @classmethod
    def rod(cls, builder, points, **kwargs) -> DeformableObject:
        """A Cosserat rod (``SceneBuilder.add_rod``)."""
        return cls(builder, builder.add_rod(points, **kwargs))

    # ------------------------------------------------------------------------------------------------ holding
    def anchor(self, local_indices, stiffness: float) -> None:
        """Hold particles (indices local to this object) by springs of ``stiffness`` (N/m) to their current
        positions in the env frame; :meth:`place_anchors` moves the anchors per env at reset."""
        for i in np.atleast_1d(np.asarray(local_indices, dtype=np.int64)):
            p = self.obj.particle_start + int(i)
            self._anchor_particles.append(p)
            self._anchor_slots.append(self.builder.add_attachment(p, body=-1, compliance=1.0 / float(stiffness)))

    def attach_to_body(self, local_indices, body: int, compliance: float = 0.0) -> list[int]:
        """Attach particles to a kinematic body at their current offset from it; returns the attachment slots."""
        return [self.builder.add_attachment(self.obj.particle_start + int(i), body=body, compliance=compliance)
                for i in np.atleast_1d(np.asarray(local_indices, dtype=np.int64))]

    @property
    def num_anchors(self) -> int:
        return len(self._anchor_particles)

    def finalize(self, world) -> DeformableObject:
        """Bind to the World built from the builder (allocates the small index tables)."""
        self.world = world
        dev = world.device
        self._anchor_particles_arr = wp.array(np.asarray(self._anchor_particles, np.int32), dtype=wp.int32, device=dev)
        self._anchor_slots_arr = wp.array(np.asarray(self._anchor_slots, np.int32), dtype=wp.int32, device=dev)
        return self

    # ------------------------------------------------------------------------------------------------ reset
    def place_anchors(self, env_mask: wp.array, anchors: wp.array, stiffness: wp.array,
                      rest_offset=(0.0, 0.0, 0.0)) -> None:
        """Move anchor ``k`` of every masked env to ``anchors[env, k]`` with ``stiffness[env, k]`` (N/m) and put its
        particle at rest at ``anchor + rest_offset`` (one launch; graph-capturable).

        Args:
            env_mask: ``(num_envs,)`` int32.
            anchors: ``(num_envs, num_anchors)`` ``wp.vec3`` in the env frame, m.
            stiffness: ``(num_envs, num_anchors)`` float, N/m.
            rest_offset: offset of the particle from its anchor at rest (m).
        """
        w, s = self.world, self.world.state
        launching.launch(place_anchored_particles, dim=(w.num_envs, self.num_anchors),
                         inputs=[env_mask, self._anchor_particles_arr, self._anchor_slots_arr, anchors, stiffness,
                                 wp.vec3(*[float(c) for c in rest_offset])],
                         outputs=[s.particle_q, s.particle_qd, s.attach_offset, s.attach_compliance], device=w.device)
