"""What a scene looks like: the visual objects and camera an env exposes to renderers and exporters.

An env's ``visual_scene()`` returns a ``VisualScene``: the camera and a list of ``VisualObject``s whose geometry
is stored once (shared by all envs) and whose per-env placement lives in device arrays the env keeps up to date
(``env.update_visuals()``). The batched rasteriser (image observations) and the USD exporter both read this one
description, so what an agent sees and what a person inspects cannot drift apart.

Kinds of objects:
* ``rigid``: a mesh in local coordinates placed by ``transforms[env, instance]`` (a ``wp.transform`` array of
  shape ``(num_envs, instances)``; instrument parts, props, targets).
* ``deformable``: a surface whose vertices are read from ``points`` ``(num_envs, V)`` ``wp.vec3`` every frame,
  with shared ``faces``; ``face_active`` ``(num_envs, F)`` int32 hides cut faces when given.
* ``rod``: a thread or rope drawn as a tube of ``radius`` through ``points`` ``(num_envs, n)`` ``wp.vec3``.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import trimesh
import warp as wp

KINDS = ("rigid", "deformable", "rod")


@dataclass
class VisualObject:
    """One drawable object of a scene (see the module docstring for the kinds)."""

    name: str
    kind: str
    color: tuple[float, float, float]
    segmentation_id: int
    vertices: np.ndarray | None = None  # (V, 3) float32, local frame (rigid) or rest shape (deformable)
    faces: np.ndarray | None = None  # (F, 3) int32
    transforms: wp.array | None = None  # rigid: (num_envs, instances) wp.transform
    points: wp.array | None = None  # deformable / rod: (num_envs, n) wp.vec3
    face_active: wp.array | None = None  # deformable: (num_envs, F) int32, 0 = removed by cutting; rod: per segment
    radius: float = 0.0  # rod: tube radius (m)
    visible: bool = True

    def __post_init__(self) -> None:
        if self.kind not in KINDS:
            raise ValueError(f"kind={self.kind!r} is not one of {KINDS}")
        if self.kind in ("rigid", "deformable"):
            if self.faces is None or self.vertices is None:
                raise ValueError(f"{self.kind} object {self.name!r} needs vertices and faces")
            self.vertices = np.ascontiguousarray(self.vertices, dtype=np.float32)
            self.faces = np.ascontiguousarray(self.faces, dtype=np.int32)
        if self.kind == "rigid" and self.transforms is None:
            raise ValueError(f"rigid object {self.name!r} needs per-env transforms")
        if self.kind in ("deformable", "rod") and self.points is None:
            raise ValueError(f"{self.kind} object {self.name!r} needs per-env points")
        if self.kind == "rod" and not self.radius > 0.0:
            raise ValueError(f"rod {self.name!r} needs a positive radius")


@dataclass
class CameraSpec:
    """A per-env camera: pose (looks along its local -Z, +Y up, as SOFA/OpenGL), vertical FoV in degrees."""

    poses: wp.array  # (num_envs,) wp.transform, world from camera
    fov_deg: float
    near: float
    far: float


@dataclass
class VisualScene:
    """Everything needed to draw one batch of scenes."""

    camera: CameraSpec
    objects: list[VisualObject] = field(default_factory=list)
    background: tuple[float, float, float] = (0.0, 0.0, 0.0)


def sphere_mesh(radius: float, subdivisions: int = 3) -> tuple[np.ndarray, np.ndarray]:
    """Icosphere vertices and faces (trimesh), outward winding."""
    mesh = trimesh.creation.icosphere(subdivisions=subdivisions, radius=radius)
    return mesh.vertices.astype(np.float32), mesh.faces.astype(np.int32)


def cylinder_mesh(radius: float, length: float, sections: int = 16) -> tuple[np.ndarray, np.ndarray]:
    """A cylinder along local +Z from z = -length to z = 0 (so its end sits at the origin, like a tool tip)."""
    mesh = trimesh.creation.cylinder(radius=radius, height=length, sections=sections)
    mesh.apply_translation((0.0, 0.0, -0.5 * length))
    return mesh.vertices.astype(np.float32), mesh.faces.astype(np.int32)


def look_at_transform(eye, target, up=(0.0, 1.0, 0.0)) -> wp.transform:
    """Camera pose whose local -Z points from ``eye`` to ``target`` with local +Y towards ``up``."""
    eye, target, up = (np.asarray(v, dtype=np.float64) for v in (eye, target, up))
    back = eye - target
    back /= np.linalg.norm(back)
    right = np.cross(up, back)
    if np.linalg.norm(right) < 1e-9:
        raise ValueError("look_at: up is parallel to the viewing direction")
    right /= np.linalg.norm(right)
    true_up = np.cross(back, right)
    rot = np.stack([right, true_up, back], axis=1)  # columns: camera x, y, z in world
    q = wp.quat_from_matrix(wp.mat33(*rot.flatten().tolist()))
    return wp.transform(wp.vec3(*eye.tolist()), q)
