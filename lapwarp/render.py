"""Batched renderer front-end: scene set-up, cameras and per-env image outputs as torch tensors.

One :class:`Renderer` serves a whole batch of ``num_envs`` environments, each with its own camera. It is
configured once (meshes, instances, deformable surfaces, tubes), finalised (all device memory allocated),
then :meth:`Renderer.render` is called every step; it only launches kernels on preallocated arrays (no
allocation, no host synchronisation, no Python loop over envs), so it can be captured in a CUDA graph.

Outputs (zero-copy torch views of Warp arrays, ``(num_envs, C, H, W)`` as rsl_rl's CNNs expect):

* ``rgb``: uint8 ``(N, 3, H, W)``; background pixels get ``background_color``.
* ``depth``: float32 ``(N, 1, H, W)``, metric distance along the camera's view axis (metres, i.e. the
  linearised OpenGL depth sofa_env computes); background pixels hold ``far``, like an OpenGL depth buffer
  cleared to 1 and linearised.
* ``segmentation``: int32 ``(N, 1, H, W)``, the ``seg_id`` of the visible object; background is ``-1``.

Conventions (as SOFA / OpenGL): a camera pose is a ``wp.transform`` (position, quaternion xyzw) from the
camera frame to the world; the camera looks along its local -Z with +Y up; ``fov`` is the *vertical* field
of view in degrees and pixels are square (``focal = (H / 2) / tan(fov / 2)`` pixels). Row 0 is the top of
the image; pixel ``(r, c)`` covers the continuous image coordinates ``[r, r + 1) x [c, c + 1)``;
:func:`project_points` returns continuous ``(row, col, depth)`` (``floor`` gives the pixel a point lands
in). Front faces are wound counter-clockwise seen from outside (trimesh/OpenGL); single-sided objects
have their back faces culled.

Per frame, :meth:`Renderer.render` launches: vertex copies / tube generation / smooth normals for
deformables; ``prepare_views`` (per env and rigid instance: local-to-view matrix, instance frustum culling);
the visibility pass; ``shade_visibility`` (per pixel: outputs, and clearing the visibility buffer for the
next frame). Two visibility back-ends share everything else: ``method="raster"`` (``kernels/raster.py``:
``cull_clusters`` rejects groups of 32 triangles of rigid meshes that are outside the frustum, cover no
pixel centre or face away, then a thread per triangle writes atomic-min keys of packed depth and triangle
id) and ``method="raycast"`` (``kernels/raycast.py``, the BVH baseline; its grouped deformable BVH is built
by its first render, so render once before capturing a graph). For the ray caster only, a single-sided
object's back face is stepped over a bounded number of times (``MAX_RECASTS``) per ray.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np
import warp as wp

from lapwarp import launching
from lapwarp.kernels import raster, raycast

__all__ = [
    "DeformableHandle",
    "InstanceHandle",
    "MeshHandle",
    "Renderer",
    "TubeHandle",
    "cloth_grid_faces",
    "focal_length",
    "look_at",
    "project_points",
]

_OUTPUTS = ("rgb", "depth", "segmentation")


@dataclass(frozen=True)
class MeshHandle:
    """A rigid mesh stored once on the device; instance it with :meth:`Renderer.add_instance`."""

    index: int
    num_vertices: int
    num_faces: int


@dataclass(frozen=True)
class InstanceHandle:
    """One placement of a rigid mesh in every env.

    Attributes:
        index: Column of this instance in ``instance_transforms`` ``(num_envs, num_instances)``.
        object: Column in the per-object tables ``object_colors`` / ``object_visible``.
    """

    index: int
    object: int
    mesh: MeshHandle


@dataclass(frozen=True)
class DeformableHandle:
    """A triangle surface whose vertices are given per env every frame.

    Attributes:
        index: Deformable number (order of addition among deformables and tubes).
        object: Column in the per-object tables ``object_colors`` / ``object_visible``.
        num_vertices: Vertices per env (the ``V`` of ``(num_envs, V, 3)`` point arrays).
        num_faces: Triangles (the ``F`` of ``(num_envs, F)`` active masks).
    """

    index: int
    object: int
    num_vertices: int
    num_faces: int


@dataclass(frozen=True)
class TubeHandle(DeformableHandle):
    """A deformable surface generated from rod nodes ``(num_envs, num_nodes, 3)`` by a kernel."""

    num_nodes: int = 0
    radius: float = 0.0
    sides: int = 0
    caps: bool = True


@dataclass
class _Object:
    kind: int
    color: tuple[float, float, float]
    seg_id: int
    flags: int
    mesh: int = -1
    instance: int = -1
    deformable: int = -1


@dataclass
class _Mesh:
    vertices: np.ndarray  # (V, 3) float32
    faces: np.ndarray  # (F, 3) int32, reordered into spatially coherent clusters
    normals: np.ndarray  # (V, 3) float32
    vertex_colors: np.ndarray | None
    raster_split: int
    cluster_bounds: np.ndarray  # (K, 4) bounding sphere (centre, radius) per cluster
    cluster_cones: np.ndarray  # (K, 4) normal cone (unit axis, half-angle in radians; >= pi/2: never culled)
    face_cluster: np.ndarray  # (F,) cluster of each (reordered) face


@dataclass
class _Deformable:
    faces: np.ndarray
    num_vertices: int
    vertex_colors: np.ndarray | None
    raster_split: int
    smooth: bool
    tube: TubeHandle | None = None
    vert_begin: int = 0
    tri_begin: int = 0


def focal_length(fov: float, height: int) -> float:
    """Focal length in pixels of a vertical field of view ``fov`` (degrees) over ``height`` pixels."""
    return 0.5 * height / math.tan(math.radians(fov) * 0.5)


def _quat_from_matrix(m: np.ndarray) -> np.ndarray:
    """Rotation matrices ``(..., 3, 3)`` -> unit quaternions ``(..., 4)`` in xyzw order (Shepperd)."""
    m = np.asarray(m, dtype=np.float64)
    q = np.empty(m.shape[:-2] + (4,))
    tr = m[..., 0, 0] + m[..., 1, 1] + m[..., 2, 2]
    cases = np.stack([tr, m[..., 0, 0], m[..., 1, 1], m[..., 2, 2]], axis=-1).argmax(axis=-1)
    for case in range(4):
        sel = cases == case
        if not np.any(sel):
            continue
        r = m[sel]
        if case == 0:
            s = 2.0 * np.sqrt(1.0 + r[:, 0, 0] + r[:, 1, 1] + r[:, 2, 2])
            v = [(r[:, 2, 1] - r[:, 1, 2]) / s, (r[:, 0, 2] - r[:, 2, 0]) / s, (r[:, 1, 0] - r[:, 0, 1]) / s, s / 4]
        elif case == 1:
            s = 2.0 * np.sqrt(1.0 + r[:, 0, 0] - r[:, 1, 1] - r[:, 2, 2])
            v = [s / 4, (r[:, 0, 1] + r[:, 1, 0]) / s, (r[:, 0, 2] + r[:, 2, 0]) / s, (r[:, 2, 1] - r[:, 1, 2]) / s]
        elif case == 2:
            s = 2.0 * np.sqrt(1.0 + r[:, 1, 1] - r[:, 0, 0] - r[:, 2, 2])
            v = [(r[:, 0, 1] + r[:, 1, 0]) / s, s / 4, (r[:, 1, 2] + r[:, 2, 1]) / s, (r[:, 0, 2] - r[:, 2, 0]) / s]
        else:
            s = 2.0 * np.sqrt(1.0 + r[:, 2, 2] - r[:, 0, 0] - r[:, 1, 1])
            v = [(r[:, 0, 2] + r[:, 2, 0]) / s, (r[:, 1, 2] + r[:, 2, 1]) / s, s / 4, (r[:, 1, 0] - r[:, 0, 1]) / s]
        q[sel] = np.stack(v, axis=-1)
    return q / np.linalg.norm(q, axis=-1, keepdims=True)


def _quat_to_matrix(q: np.ndarray) -> np.ndarray:
    """Quaternions ``(..., 4)`` xyzw -> rotation matrices ``(..., 3, 3)``."""
    x, y, z, w = np.moveaxis(np.asarray(q, dtype=np.float64), -1, 0)
    return np.stack(
        [
            np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)], -1),
            np.stack([2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)], -1),
            np.stack([2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], -1),
        ],
        -2,
    )


def look_at(eye: Sequence[float] | np.ndarray, target: Sequence[float] | np.ndarray, up=(0.0, 1.0, 0.0)) -> np.ndarray:
    """Camera pose(s) looking from ``eye`` at ``target`` (host helper, NumPy).

    Args:
        eye: Camera position(s) ``(..., 3)`` in metres.
        target: Point(s) ``(..., 3)`` the camera's -Z axis passes through.
        up: World direction(s) ``(..., 3)`` that appears as up (+Y) in the image; must not be parallel
            to the viewing direction.

    Returns:
        ``(..., 7)`` float32 poses ``(px, py, pz, qx, qy, qz, qw)``: the ``wp.transform`` layout, ready
        for ``wp.array(poses, dtype=wp.transform)`` or a ``(num_envs, 7)`` torch tensor.
    """
    eye = np.asarray(eye, dtype=np.float64)
    target = np.asarray(target, dtype=np.float64)
    up = np.asarray(up, dtype=np.float64)
    z = eye - target
    z_norm = np.linalg.norm(z, axis=-1, keepdims=True)
    if np.any(z_norm == 0.0):
        raise ValueError("look_at: eye and target coincide")
    z = z / z_norm
    x = np.cross(up, z)
    x_norm = np.linalg.norm(x, axis=-1, keepdims=True)
    if np.any(x_norm < 1e-9):
        raise ValueError("look_at: up is parallel to the viewing direction")
    x = x / x_norm
    y = np.cross(z, x)
    rot = np.stack([x, y, z], axis=-1)
    eye, rot = np.broadcast_arrays(eye[..., None, :], rot)
    return np.concatenate([eye[..., 0, :], _quat_from_matrix(rot)], axis=-1).astype(np.float32)


def project_points(points: np.ndarray, camera_pose: np.ndarray, fov: float, width: int, height: int) -> np.ndarray:
    """World points -> continuous pixel coordinates, exactly as the rasteriser projects them (NumPy).

    Args:
        points: ``(..., 3)`` world points in metres.
        camera_pose: ``(..., 7)`` camera-to-world poses (broadcast against ``points``' leading shape).
        fov: Vertical field of view in degrees.
        width: Image width in pixels.
        height: Image height in pixels.

    Returns:
        ``(..., 3)`` float64 ``(row, col, depth)``: ``floor(row), floor(col)`` is the pixel the point
        lands in (row 0 at the top) when it lies inside the image, ``depth`` the distance along the view
        axis; rows and columns are meaningless for ``depth <= 0`` (behind the camera).
    """
    points = np.asarray(points, dtype=np.float64)
    pose = np.asarray(camera_pose, dtype=np.float64)
    rot = _quat_to_matrix(pose[..., 3:7])
    rel = points - pose[..., :3]
    q = np.einsum("...ji,...j->...i", rot, rel)
    f = focal_length(fov, height)
    z = -q[..., 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        row = 0.5 * height - f * q[..., 1] / z
        col = 0.5 * width + f * q[..., 0] / z
    return np.stack([row, col, z], axis=-1)


def cloth_grid_faces(nx: int, ny: int) -> np.ndarray:
    """Faces ``(2 (nx-1)(ny-1), 3)`` of a regular ``nx x ny`` vertex grid (vertex ``i * nx + j`` at row
    i, column j), wound counter-clockwise when rows go along +y and columns along +x."""
    i, j = np.meshgrid(np.arange(ny - 1), np.arange(nx - 1), indexing="ij")
    v00 = (i * nx + j).ravel()
    v01 = v00 + 1
    v10 = v00 + nx
    v11 = v10 + 1
    return np.concatenate([np.stack([v00, v01, v11], 1), np.stack([v00, v11, v10], 1)]).astype(np.int32)


def _vertex_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    n = np.zeros_like(vertices)
    fn = np.cross(vertices[faces[:, 1]] - vertices[faces[:, 0]], vertices[faces[:, 2]] - vertices[faces[:, 0]])
    for k in range(3):
        np.add.at(n, faces[:, k], fn)
    length = np.linalg.norm(n, axis=1, keepdims=True)
    return np.where(length > 0, n / np.maximum(length, 1e-30), 0.0)


CLUSTER_SIZE = 32  # triangles per culling cluster of a rigid mesh


def _morton_order(points: np.ndarray) -> np.ndarray:
    """Indices sorting points along a 3-D Morton (Z-order) curve of their bounding box."""
    lo, hi = points.min(0), points.max(0)
    q = ((points - lo) / np.maximum(hi - lo, 1e-12) * 1023).astype(np.uint64)
    code = np.zeros(len(points), np.uint64)
    for bit in range(10):
        for axis in range(3):
            code |= ((q[:, axis] >> np.uint64(bit)) & np.uint64(1)) << np.uint64(3 * bit + axis)
    return np.argsort(code, kind="stable")


def _build_clusters(v: np.ndarray, f: np.ndarray, double_sided: bool):
    """Reorders faces into spatially coherent groups of ``CLUSTER_SIZE`` and computes, per group, a bounding
    sphere (frustum culling) and a normal cone (whole-cluster back-face culling; never for double-sided)."""
    f = f[_morton_order(v[f].mean(1))]
    fn = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    length = np.linalg.norm(fn, axis=1, keepdims=True)
    fn = np.where(length > 0, fn / np.maximum(length, 1e-30), 0.0)
    k = -(-len(f) // CLUSTER_SIZE)
    bounds, cones = np.zeros((k, 4)), np.zeros((k, 4))
    for c in range(k):
        cf = f[c * CLUSTER_SIZE : (c + 1) * CLUSTER_SIZE]
        pts = v[np.unique(cf)]
        centre = 0.5 * (pts.min(0) + pts.max(0))
        bounds[c] = [*centre, np.linalg.norm(pts - centre, axis=1).max() * (1 + 1e-5) + 1e-7]
        n = fn[c * CLUSTER_SIZE : (c + 1) * CLUSTER_SIZE]
        n = n[np.linalg.norm(n, axis=1) > 0]
        axis = n.sum(0)
        if double_sided or len(n) == 0 or np.linalg.norm(axis) < 1e-6:
            cones[c] = [0.0, 0.0, 1.0, np.pi]
            continue
        axis /= np.linalg.norm(axis)
        cones[c] = [*axis, np.arccos(np.clip(n @ axis, -1.0, 1.0)).max() + 1e-4]
    return f, bounds.astype(np.float32), cones.astype(np.float32), np.arange(len(f)) // CLUSTER_SIZE


def _check_faces(faces, num_vertices: int) -> np.ndarray:
    faces = np.asarray(faces)
    if faces.ndim != 2 or faces.shape[1] != 3 or len(faces) == 0:
        raise ValueError(f"faces must have shape (F, 3) with F > 0, got {faces.shape}")
    if faces.min() < 0 or faces.max() >= num_vertices:
        raise ValueError(f"face indices must lie in [0, {num_vertices}), got [{faces.min()}, {faces.max()}]")
    return faces.astype(np.int32)


def _check_color(color) -> tuple[float, float, float]:
    c = np.asarray(color, dtype=np.float64).ravel()
    if c.shape != (3,) or np.any(c < 0) or np.any(c > 1):
        raise ValueError(f"color must be 3 floats in [0, 1], got {color}")
    return (float(c[0]), float(c[1]), float(c[2]))


def _check_vertex_colors(vertex_colors, num_vertices: int) -> np.ndarray | None:
    if vertex_colors is None:
        return None
    vc = np.asarray(vertex_colors, dtype=np.float32)
    if vc.shape != (num_vertices, 3):
        raise ValueError(f"vertex_colors must have shape ({num_vertices}, 3), got {vc.shape}")
    if vc.min() < 0 or vc.max() > 1:
        raise ValueError("vertex_colors must lie in [0, 1]")
    return vc


class Renderer:
    """Batched renderer: every env has its own camera and its own object poses / deformable vertices.

    Typical use::

        r = Renderer(num_envs=4096, width=64, height=64, fov=42.0, near=0.01, far=2.0, device="cuda:0")
        sphere = r.add_instance(r.add_mesh(verts, faces, color=(0.9, 0.2, 0.2), seg_id=1))
        cloth = r.add_deformable(cloth_faces, num_vertices=1600, color=(0.8, 0.6, 0.5), seg_id=2)
        r.finalize()
        r.render(camera_poses, instance_transforms, deformable_points={cloth: particle_q})
        obs = r.rgb  # torch uint8 (4096, 3, 64, 64), same memory every step

    Args:
        num_envs: Number of environments (images) rendered per call.
        width: Image width in pixels.
        height: Image height in pixels.
        fov: Vertical field of view in degrees (sofa_env convention), shared by all envs.
        near: Near clipping distance in metres (geometry closer than this is clipped away).
        far: Far clipping distance in metres; also the depth written for background pixels.
        device: Warp device (``"cpu"``, ``"cuda:0"``); ``None`` for Warp's default device.
        outputs: Which of ``"rgb"``, ``"depth"``, ``"segmentation"`` to allocate and write.
        background_color: RGB in [0, 1] of pixels that see no geometry.
        ambient: Ambient light term of the Lambert model.
        diffuse: Intensity of the head light at the camera (an endoscope's light): a surface facing the
            camera gets ``color * (ambient + diffuse)``.
        method: ``"raster"`` (visibility-buffer rasteriser) or ``"raycast"`` (BVH ray caster baseline).
        early_depth_test: Rasteriser only: read the visibility buffer before each atomic and skip the
            atomic when the fragment is already hidden (a plain load against an atomic; which is faster
            depends on depth complexity and the GPU: ``benchmarks/bench_render.py`` measures both).
    """

    def __init__(
        self,
        num_envs: int,
        width: int,
        height: int,
        fov: float = 45.0,
        near: float = 0.01,
        far: float = 10.0,
        device: str | None = None,
        *,
        outputs: Sequence[str] = _OUTPUTS,
        background_color: Sequence[float] = (0.0, 0.0, 0.0),
        ambient: float = 0.3,
        diffuse: float = 0.7,
        method: str = "raster",
        early_depth_test: bool = False,
    ):
        if num_envs < 1 or width < 1 or height < 1:
            raise ValueError(f"num_envs, width and height must be positive, got {num_envs}, {width}, {height}")
        if not 0.0 < fov < 180.0:
            raise ValueError(f"fov (vertical, degrees) must lie in (0, 180), got {fov}")
        if not 0.0 < near < far:
            raise ValueError(f"need 0 < near < far, got near={near}, far={far}")
        unknown = set(outputs) - set(_OUTPUTS)
        if unknown or not outputs:
            raise ValueError(f"outputs must be a non-empty subset of {_OUTPUTS}, got {tuple(outputs)}")
        if method not in ("raster", "raycast"):
            raise ValueError(f"method must be 'raster' or 'raycast', got {method!r}")
        if ambient < 0 or diffuse < 0:
            raise ValueError("ambient and diffuse must be non-negative")
        self.num_envs = int(num_envs)
        self.width = int(width)
        self.height = int(height)
        self.fov = float(fov)
        self.near = float(near)
        self.far = float(far)
        self.device = wp.get_device(device)
        self.outputs = tuple(o for o in _OUTPUTS if o in outputs)
        self.background_color = _check_color(background_color)
        self.ambient = float(ambient)
        self.diffuse = float(diffuse)
        self.method = method
        self.early_depth_test = bool(early_depth_test)
        self.focal = focal_length(self.fov, self.height)
        self.cx = 0.5 * self.width
        self.cy = 0.5 * self.height

        self._meshes: list[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray | None, int]] = []
        self._mesh_defaults: list[tuple[tuple[float, float, float], int, int]] = []
        self._objects: list[_Object] = []
        self._instances: list[int] = []  # object index of each instance column
        self._deformables: list[_Deformable] = []
        self._deformable_objects: list[int] = []
        self.finalized = False

    # ------------------------------------------------------------------ scene description

    def _check_open(self):
        if self.finalized:
            raise RuntimeError("the renderer is finalised; add objects before finalize() / the first render()")

    def add_mesh(
        self,
        vertices,
        faces,
        color: Sequence[float] = (0.8, 0.8, 0.8),
        seg_id: int = 0,
        *,
        smooth: bool = True,
        double_sided: bool = False,
        vertex_colors=None,
        raster_split: int | None = None,
    ) -> MeshHandle:
        """Stores a rigid triangle mesh once (in its local frame, metres) for all envs.

        Args:
            vertices: ``(V, 3)`` local vertex positions.
            faces: ``(F, 3)`` vertex indices, counter-clockwise seen from outside.
            color: Default RGB albedo in [0, 1] of its instances.
            seg_id: Default segmentation id of its instances (>= 0; -1 is the background).
            smooth: Interpolate vertex normals (area-weighted, computed here) instead of face normals.
            double_sided: Draw back faces too (lit from their own side) instead of culling them.
            vertex_colors: Optional ``(V, 3)`` RGB in [0, 1], multiplied with the instance colour.
            raster_split: Threads per triangle (each takes every n-th row of its bounding box) so that
                large triangles do not serialise one thread. ``None``: the image height for meshes of at
                most 32 triangles (quads, boxes: likely large on screen), else 1.

        Returns:
            A handle for :meth:`add_instance`.
        """
        self._check_open()
        v = np.asarray(vertices, dtype=np.float64)
        if v.ndim != 2 or v.shape[1] != 3 or len(v) == 0:
            raise ValueError(f"vertices must have shape (V, 3) with V > 0, got {v.shape}")
        if not np.all(np.isfinite(v)):
            raise ValueError("vertices must be finite")
        f = _check_faces(faces, len(v))
        if raster_split is None:
            raster_split = self.height if len(f) <= 32 else 1
        if not 1 <= raster_split <= 0xFFFF:
            raise ValueError(f"raster_split must lie in [1, 65535], got {raster_split}")
        color = _check_color(color)
        vc = _check_vertex_colors(vertex_colors, len(v))
        flags = (raster.FLAG_DOUBLE_SIDED if double_sided else 0) | (raster.FLAG_SMOOTH if smooth else 0)
        if vc is not None:
            flags |= raster.FLAG_VERTEX_COLORS
        normals = _vertex_normals(v, f)
        f, bounds, cones, face_cluster = _build_clusters(v, f, double_sided)
        self._meshes.append(
            _Mesh(
                v.astype(np.float32), f, normals.astype(np.float32), vc, int(raster_split), bounds, cones, face_cluster
            )
        )
        self._mesh_defaults.append((color, int(seg_id), int(flags)))
        return MeshHandle(len(self._meshes) - 1, len(v), len(f))

    def add_instance(
        self, mesh: MeshHandle, color: Sequence[float] | None = None, seg_id: int | None = None
    ) -> InstanceHandle:
        """Places a rigid mesh in every env; its per-env pose is column ``handle.index`` of the
        ``instance_transforms`` passed to :meth:`render` (or of :attr:`instance_transforms`).

        Args:
            mesh: Handle from :meth:`add_mesh`.
            color: RGB in [0, 1]; the mesh's default if ``None``. Per-env colours: :attr:`object_colors`.
            seg_id: Segmentation id; the mesh's default if ``None``.
        """
        self._check_open()
        if not isinstance(mesh, MeshHandle) or not 0 <= mesh.index < len(self._meshes):
            raise ValueError("mesh must be a MeshHandle returned by this renderer's add_mesh()")
        d_color, d_seg, flags = self._mesh_defaults[mesh.index]
        seg = d_seg if seg_id is None else int(seg_id)
        if seg < 0:
            raise ValueError(f"seg_id must be >= 0 (-1 marks the background), got {seg}")
        obj = _Object(raster.KIND_RIGID, d_color if color is None else _check_color(color), seg, flags)
        obj.mesh = mesh.index
        obj.instance = len(self._instances)
        self._objects.append(obj)
        self._instances.append(len(self._objects) - 1)
        return InstanceHandle(obj.instance, len(self._objects) - 1, mesh)

    def _add_deformable(self, faces, num_vertices, color, seg_id, double_sided, smooth, vertex_colors, split):
        self._check_open()
        if num_vertices < 3:
            raise ValueError(f"num_vertices must be >= 3, got {num_vertices}")
        f = _check_faces(faces, num_vertices)
        if seg_id < 0:
            raise ValueError(f"seg_id must be >= 0 (-1 marks the background), got {seg_id}")
        if not 1 <= split <= 0xFFFF:
            raise ValueError(f"raster_split must lie in [1, 65535], got {split}")
        vc = _check_vertex_colors(vertex_colors, num_vertices)
        flags = (raster.FLAG_DOUBLE_SIDED if double_sided else 0) | (raster.FLAG_SMOOTH if smooth else 0)
        if vc is not None:
            flags |= raster.FLAG_VERTEX_COLORS
        obj = _Object(raster.KIND_DEFORMABLE, _check_color(color), int(seg_id), flags)
        obj.deformable = len(self._deformables)
        self._objects.append(obj)
        self._deformables.append(_Deformable(f, int(num_vertices), vc, int(split), bool(smooth)))
        self._deformable_objects.append(len(self._objects) - 1)
        return obj.deformable, len(self._objects) - 1, f

    def add_deformable(
        self,
        faces,
        num_vertices: int,
        color: Sequence[float] = (0.8, 0.8, 0.8),
        seg_id: int = 0,
        *,
        double_sided: bool = True,
        smooth: bool = True,
        vertex_colors=None,
        raster_split: int = 1,
    ) -> DeformableHandle:
        """Adds a triangle surface whose vertices come from a per-env array ``(num_envs, V, 3)``.

        The faces are shared by all envs; per env and frame, :meth:`render` takes the vertex positions
        (``deformable_points``) and optionally an ``active`` mask ``(num_envs or 1, F)`` whose zero
        entries (cut elements) are not drawn. The faces may reference only part of the vertices (e.g. the
        surface of a tet mesh indexed into all its particles).

        Args:
            faces: ``(F, 3)`` indices into the ``V`` vertices.
            num_vertices: ``V``.
            color: RGB albedo in [0, 1]; per-env colours: :attr:`object_colors`.
            seg_id: Segmentation id (>= 0).
            double_sided: Draw both sides (cloth, membranes); ``False`` culls back faces (closed surfaces).
            smooth: Shade with per-frame vertex normals (one extra gather kernel) instead of face normals.
            vertex_colors: Optional shared ``(V, 3)`` RGB in [0, 1], multiplied with ``color``.
            raster_split: Threads per triangle (see :meth:`add_mesh`).
        """
        index, obj, f = self._add_deformable(
            faces, num_vertices, color, seg_id, double_sided, smooth, vertex_colors, raster_split
        )
        return DeformableHandle(index, obj, int(num_vertices), len(f))

    def add_tube(
        self,
        num_nodes: int,
        radius: float,
        color: Sequence[float] = (0.8, 0.8, 0.8),
        seg_id: int = 0,
        *,
        sides: int = 8,
        caps: bool = True,
    ) -> TubeHandle:
        """Adds a rod / thread drawn as a tube of ``radius`` metres around per-env node positions.

        Per frame, :meth:`render` takes ``tube_nodes={handle: (num_envs, num_nodes, 3)}``; a kernel writes
        ``sides`` vertices (with analytic normals) around every node into the deformable vertex buffer.
        The tube is a smooth-shaded, single-sided deformable surface (closed by end caps if ``caps``).
        """
        if num_nodes < 2:
            raise ValueError(f"a tube needs at least 2 nodes, got {num_nodes}")
        if sides < 3:
            raise ValueError(f"a tube needs at least 3 sides, got {sides}")
        if not radius > 0:
            raise ValueError(f"radius must be positive, got {radius}")
        ring = np.arange(sides)
        i = np.arange(num_nodes - 1)[:, None]
        a = i * sides + ring
        b = i * sides + (ring + 1) % sides
        faces = [np.stack([a, b, b + sides], -1).reshape(-1, 3), np.stack([a, b + sides, a + sides], -1).reshape(-1, 3)]
        num_vertices = num_nodes * sides
        if caps:
            start, end = num_vertices, num_vertices + 1
            last = (num_nodes - 1) * sides
            faces.append(np.stack([np.full(sides, start), (ring + 1) % sides, ring], -1))
            faces.append(np.stack([np.full(sides, end), last + ring, last + (ring + 1) % sides], -1))
            num_vertices += 2
        index, obj, f = self._add_deformable(np.concatenate(faces), num_vertices, color, seg_id, False, True, None, 1)
        handle = TubeHandle(index, obj, num_vertices, len(f), int(num_nodes), float(radius), int(sides), bool(caps))
        self._deformables[index].tube = handle
        return handle

    # ------------------------------------------------------------------ allocation

    def finalize(self):
        """Uploads the scene and allocates every buffer; called by the first :meth:`render` if needed.

        Call it explicitly (and render once) before capturing :meth:`render` in a CUDA graph.
        """
        if self.finalized:
            return
        if not self._objects:
            raise RuntimeError("the scene is empty: add at least one instance, deformable or tube")
        dev = self.device
        n, h, w = self.num_envs, self.height, self.width

        # Rigid: vertices of all meshes concatenated; triangles of all instances first in the id space.
        mesh_vert_begin = np.cumsum([0] + [len(m.vertices) for m in self._meshes])
        tri_vidx, tri_obj, slot_tri, slot_split = [], [], [], []
        tri_cluster, cluster_inst, cluster_bounds, cluster_cones = [], [], [], []
        self._inst_tri_begin = []
        num_tris = num_clusters = 0
        for inst, obj_index in enumerate(self._instances):
            obj = self._objects[obj_index]
            mesh = self._meshes[obj.mesh]
            faces, split = mesh.faces, mesh.raster_split
            self._inst_tri_begin.append(num_tris)
            tri_vidx.append(faces + mesh_vert_begin[obj.mesh])
            tri_obj.append(np.full(len(faces), obj_index))
            tri_cluster.append(mesh.face_cluster + num_clusters)
            cluster_inst.append(np.full(len(mesh.cluster_bounds), inst))
            cluster_bounds.append(mesh.cluster_bounds)
            cluster_cones.append(mesh.cluster_cones)
            tris = np.arange(num_tris, num_tris + len(faces))
            # Slots padded to whole warps (tri -1: no work) so that, with clusters of 32 triangles, a warp
            # holds exactly one cluster: a culled cluster is an idle warp rather than divergent lanes.
            pad = -(len(faces) * split) % 32
            slot_tri.append(np.concatenate([np.repeat(tris, split), np.full(pad, -1)]))
            slot_split.append(np.concatenate([np.tile(np.arange(split) | (split << 16), len(faces)), np.zeros(pad)]))
            num_tris += len(faces)
            num_clusters += len(mesh.cluster_bounds)
        self.num_clusters = num_clusters
        self.num_rigid_triangles = num_tris
        # Deformables: vertices concatenated into one per-env buffer, triangles after the rigid ones.
        vert_begin = 0
        for d, obj_index in zip(self._deformables, self._deformable_objects, strict=True):
            d.vert_begin = vert_begin
            d.tri_begin = num_tris
            tri_vidx.append(d.faces + vert_begin)
            tri_obj.append(np.full(len(d.faces), obj_index))
            vert_begin += d.num_vertices
            num_tris += len(d.faces)
        self.num_deformable_vertices = vert_begin
        self.num_triangles = num_tris

        def arr(a, dtype, shape=None):
            a = np.asarray(a)
            if a.size == 0:
                return wp.zeros(shape or 1, dtype=dtype, device=dev)
            return wp.array(a, dtype=dtype, device=dev)

        self._tri_vidx = arr(np.concatenate(tri_vidx).astype(np.int32), wp.vec3i)
        self._tri_obj = arr(np.concatenate(tri_obj).astype(np.int32), wp.int32)
        self._slot_tri = arr(np.concatenate(slot_tri).astype(np.int32) if slot_tri else [], wp.int32)
        self._slot_split = arr(np.concatenate(slot_split).astype(np.int32) if slot_split else [], wp.int32)
        self._num_slots = int(sum(len(s) for s in slot_tri))
        objs = self._objects
        self._obj_kind = arr([o.kind for o in objs], wp.int32)
        self._obj_inst = arr([max(o.instance, 0) for o in objs], wp.int32)
        self._obj_flags = arr([o.flags for o in objs], wp.int32)
        self._obj_seg = arr([o.seg_id for o in objs], wp.int32)
        colors = np.tile(np.asarray([o.color for o in objs], dtype=np.float32), (n, 1, 1))
        self._obj_color = wp.array(colors, dtype=wp.vec3, device=dev)
        self._obj_visible = wp.ones((n, len(objs)), dtype=wp.int32, device=dev)

        self._tri_cluster = arr(np.concatenate(tri_cluster).astype(np.int32) if tri_cluster else [], wp.int32)
        self._cluster_inst = arr(np.concatenate(cluster_inst).astype(np.int32) if cluster_inst else [], wp.int32)
        self._cluster_bounds = arr(np.concatenate(cluster_bounds) if cluster_bounds else [], wp.vec4)
        self._cluster_cones = arr(np.concatenate(cluster_cones) if cluster_cones else [], wp.vec4)
        self._cluster_draw = wp.zeros((n, max(num_clusters, 1)), dtype=wp.int32, device=dev)
        if self._meshes:
            self._rigid_verts = arr(np.concatenate([m.vertices for m in self._meshes]), wp.vec3)
            self._rigid_normals = arr(np.concatenate([m.normals for m in self._meshes]), wp.vec3)
            self._rigid_colors = arr(
                np.concatenate(
                    [m.vertex_colors if m.vertex_colors is not None else np.ones_like(m.vertices) for m in self._meshes]
                ),
                wp.vec3,
            )
        else:
            self._rigid_verts = self._rigid_normals = self._rigid_colors = wp.zeros(1, dtype=wp.vec3, device=dev)
        num_inst = len(self._instances)
        bounds = []
        for obj_index in self._instances:
            v = self._meshes[self._objects[obj_index].mesh].vertices
            centre = 0.5 * (v.min(0) + v.max(0))
            bounds.append([*centre, np.linalg.norm(v - centre, axis=1).max() * (1 + 1e-5) + 1e-7])
        self._inst_bounds = arr(np.asarray(bounds, np.float32), wp.vec4)
        self._inst_obj = arr(np.asarray(self._instances, np.int32), wp.int32)
        # Local-to-view matrices per (env, instance) and the world-to-view matrix in the last column.
        self._views = wp.zeros((n, num_inst + 1), dtype=wp.mat44, device=dev)
        self._inst_draw = wp.zeros((n, max(num_inst, 1)), dtype=wp.int32, device=dev)
        ident = np.tile(np.array([0, 0, 0, 0, 0, 0, 1], dtype=np.float32), (n, max(num_inst, 1), 1))
        self._inst_xf = wp.array(ident, dtype=wp.transform, device=dev)
        self._cam_xf = wp.array(ident[:, 0].copy(), dtype=wp.transform, device=dev)

        nv = self.num_deformable_vertices
        if self._deformables:
            self._def_points = wp.zeros((n, nv), dtype=wp.vec3, device=dev)
            any_smooth = any(d.smooth for d in self._deformables)
            self._def_normals = wp.zeros((n, nv) if any_smooth else (1, 1), dtype=wp.vec3, device=dev)
            self._def_colors = arr(
                np.concatenate(
                    [
                        d.vertex_colors if d.vertex_colors is not None else np.ones((d.num_vertices, 3))
                        for d in self._deformables
                    ]
                ).astype(np.float32),
                wp.vec3,
            )
            self._all_active = [wp.ones((1, len(d.faces)), dtype=wp.int32, device=dev) for d in self._deformables]
            self._adjacency = []
            for d in self._deformables:
                order = np.argsort(d.faces.ravel(), kind="stable")
                counts = np.bincount(d.faces.ravel(), minlength=d.num_vertices)
                start = np.concatenate([[0], np.cumsum(counts)]).astype(np.int32)
                self._adjacency.append((arr(start, wp.int32), arr((order // 3).astype(np.int32), wp.int32)))
        else:
            self._def_points = self._def_normals = wp.zeros((1, 1), dtype=wp.vec3, device=dev)
            self._def_colors = wp.zeros(1, dtype=wp.vec3, device=dev)
            self._all_active, self._adjacency = [], []

        # Visibility buffer, cleared once here and afterwards by the shading pass itself.
        self._vbuf = wp.full((n, h, w), value=wp.uint64(0xFFFFFFFFFFFFFFFF), dtype=wp.uint64, device=dev)
        self._vbuf_flat = self._vbuf.flatten()  # the rasteriser indexes it flat: fewer registers
        empty4 = {"rgb": wp.uint8, "depth": wp.float32, "segmentation": wp.int32}
        chans = {"rgb": 3, "depth": 1, "segmentation": 1}
        self._out = {}
        for name, dtype in empty4.items():
            shape = (n, chans[name], h, w) if name in self.outputs else (1, 1, 1, 1)
            self._out[name] = wp.zeros(shape, dtype=dtype, device=dev)
        self._no_frame = wp.zeros((1, 1, 1, 1), dtype=wp.float32, device=dev)
        self._frame, self._frame_rgb, self._frame_depth = self._no_frame, 0, 0
        self._points = None

        if self.method == "raycast":
            self._build_raycast()
        self.finalized = True

    def _build_raycast(self):
        dev = self.device
        self._rc_meshes = []
        for m in self._meshes:
            points = wp.array(m.vertices, dtype=wp.vec3, device=dev)
            indices = wp.array(m.faces.ravel(), dtype=wp.int32, device=dev)
            self._rc_meshes.append((wp.Mesh(points=points, indices=indices), points, indices))
        meshes = [self._rc_meshes[self._objects[o].mesh][0].id for o in self._instances]
        self._rc_inst_mesh = wp.array(np.array(meshes, dtype=np.uint64), dtype=wp.uint64, device=dev)
        self._rc_inst_obj = wp.array(np.array(self._instances, dtype=np.int32), dtype=wp.int32, device=dev)
        self._rc_inst_tri = wp.array(np.array(self._inst_tri_begin, dtype=np.int32), dtype=wp.int32, device=dev)
        self._rc_def_tris = self.num_triangles - self.num_rigid_triangles
        self._rc_def_mesh = None
        self._rc_def_active = wp.ones(
            (self.num_envs if self._rc_def_tris else 1, max(self._rc_def_tris, 1)), dtype=wp.int32, device=dev
        )

    def _build_raycast_deformables(self):
        """Builds one grouped BVH over every env's deformable triangles (group = env) on the flattened vertex
        buffer. Built at the first ray-cast render, once the buffer holds real vertices, because refitting
        keeps the tree topology of the build (a build on all-zero points would stay degenerate)."""
        n = self.num_envs
        local = self._tri_vidx.numpy()[self.num_rigid_triangles :]
        offsets = (np.arange(n) * self.num_deformable_vertices)[:, None, None]
        indices = (local[None] + offsets).astype(np.int32).ravel()
        groups = np.repeat(np.arange(n, dtype=np.int32), self._rc_def_tris)
        self._rc_def_indices = wp.array(indices, dtype=wp.int32, device=self.device)
        self._rc_def_groups = wp.array(groups, dtype=wp.int32, device=self.device)
        self._rc_def_mesh = wp.Mesh(
            points=self._def_points.flatten(), indices=self._rc_def_indices, groups=self._rc_def_groups
        )

    # ------------------------------------------------------------------ user-visible state

    def _require_final(self):
        if not self.finalized:
            self.finalize()

    @property
    def rgb(self):
        """uint8 torch tensor ``(num_envs, 3, H, W)`` (zero-copy view, overwritten by every render)."""
        return self._output_view("rgb")

    @property
    def depth(self):
        """float32 torch tensor ``(num_envs, 1, H, W)``: metres along the view axis; background = ``far``."""
        return self._output_view("depth")

    @property
    def segmentation(self):
        """int32 torch tensor ``(num_envs, 1, H, W)``: the visible object's ``seg_id``; background = -1."""
        return self._output_view("segmentation")

    def set_frame_output(self, frame, rgb: bool, depth: bool) -> None:
        """Have every render also write an observation frame: ``frame`` float32 ``(num_envs, C, H, W)`` in [0, 1],
        ``C = 3 * rgb + depth``, the RGB bytes / 255 and then depth / far (at most 1), in the shading pass (one launch
        and one pass over the pixels fewer than converting the outputs afterwards); ``None`` stops it."""
        self._require_final()
        if frame is None:
            self._frame, self._frame_rgb, self._frame_depth = self._no_frame, 0, 0
            return
        shape = (self.num_envs, 3 * int(bool(rgb)) + int(bool(depth)), self.height, self.width)
        if not (rgb or depth) or tuple(frame.shape) != shape or frame.dtype != wp.float32:
            raise ValueError(f"the frame output must be float32 of shape {shape} with rgb and / or depth, got "
                             f"{frame.dtype} {tuple(frame.shape)} (rgb={rgb}, depth={depth})")
        self._frame, self._frame_rgb, self._frame_depth = frame, int(bool(rgb)), int(bool(depth))

    def _output_view(self, name):
        self._require_final()
        if name not in self.outputs:
            raise RuntimeError(f"output {name!r} was not requested (outputs={self.outputs})")
        return wp.to_torch(self._out[name])

    @property
    def camera_poses(self):
        """float32 torch view ``(num_envs, 7)`` of the renderer's own camera poses (camera to world,
        ``px py pz qx qy qz qw``), used when :meth:`render` gets no ``camera_poses``."""
        self._require_final()
        return wp.to_torch(self._cam_xf)

    @property
    def instance_transforms(self):
        """float32 torch view ``(num_envs, num_instances, 7)`` of the renderer's own instance poses (local
        to world), used when :meth:`render` gets no ``instance_transforms``."""
        self._require_final()
        return wp.to_torch(self._inst_xf)[:, : len(self._instances)]

    @property
    def object_colors(self):
        """float32 torch view ``(num_envs, num_objects, 3)`` of per-env object colours in [0, 1] (initialised
        from the static colours; index with ``handle.object``)."""
        self._require_final()
        return wp.to_torch(self._obj_color)

    @property
    def object_visible(self):
        """int32 torch view ``(num_envs, num_objects)``: 0 hides an object in that env (index with
        ``handle.object``)."""
        self._require_final()
        return wp.to_torch(self._obj_visible)

    def set_camera_poses(self, poses):
        """Copies camera poses ``(num_envs, 7)`` (NumPy, torch or Warp; e.g. from :func:`look_at`) into the
        renderer's own array; a single ``(7,)`` pose is used for every env."""
        self._require_final()
        self._copy_in(self._cam_xf, poses, (self.num_envs,), wp.transform, "camera_poses")

    def set_instance_transforms(self, transforms):
        """Copies instance poses ``(num_envs, num_instances, 7)`` into the renderer's own array."""
        self._require_final()
        dst = self._inst_xf if self._instances else None
        if dst is None:
            raise RuntimeError("the scene has no rigid instances")
        self._copy_in(dst, transforms, (self.num_envs, len(self._instances)), wp.transform, "instance_transforms")

    def deformable_points(self, handle: DeformableHandle):
        """Writable Warp view ``(num_envs, V)`` of vec3 into the renderer's deformable vertex buffer: a
        physics kernel can write the surface vertices here directly (no copy in :meth:`render`)."""
        self._require_final()
        d = self._deformable(handle)
        return self._def_points[:, d.vert_begin : d.vert_begin + d.num_vertices]

    def _copy_in(self, dst, src, shape, dtype, name):
        if isinstance(src, wp.array):
            a = src
        else:
            if type(src).__module__.startswith("torch"):
                src = src.detach().cpu().numpy()
            a = np.asarray(src, dtype=np.float32)
            width = dtype._length_
            if a.shape == (width,):
                a = np.broadcast_to(a, shape + (width,))
            if a.shape != shape + (width,):
                raise ValueError(f"{name} must have shape {shape + (width,)}, got {a.shape}")
            a = wp.array(np.ascontiguousarray(a), dtype=dtype, device=self.device)
        if a.shape != shape or a.dtype != dtype:
            raise ValueError(f"{name} must be a {shape} array of {dtype.__name__}, got {a.shape} {a.dtype}")
        wp.copy(dst, a)

    def _deformable(self, handle) -> _Deformable:
        if not isinstance(handle, DeformableHandle) or not 0 <= handle.index < len(self._deformables):
            raise ValueError(f"expected a DeformableHandle of this renderer, got {handle!r}")
        return self._deformables[handle.index]

    # ------------------------------------------------------------------ per-step work

    def _as_array(self, x, dtype, shape, name, allow_broadcast=False):
        """Zero-copy Warp view of a Warp array or torch tensor, with shape/device checks (no allocation
        of device memory, no synchronisation)."""
        if isinstance(x, wp.array):
            a = x
        elif type(x).__module__.startswith("torch"):
            import torch

            if x.dtype == torch.bool:
                x = x.view(torch.uint8)
            a = wp.from_torch(x, dtype=dtype if dtype not in (wp.int32, wp.uint8) else None)
        else:
            raise TypeError(f"{name} must be a Warp array or a torch tensor on {self.device}, got {type(x).__name__}")
        if a.device != self.device:
            raise ValueError(f"{name} lives on {a.device}, the renderer on {self.device}")
        if dtype in (wp.int32, wp.uint8):
            if a.dtype not in (wp.int32, wp.uint8):
                raise ValueError(f"{name} must hold int32, uint8 or bool, got {a.dtype}")
        elif a.dtype != dtype:
            raise ValueError(f"{name} must hold {dtype.__name__} (last torch dim {dtype._length_}), got {a.dtype}")
        ok = a.shape == shape or (allow_broadcast and a.ndim == 2 and a.shape[0] == 1 and a.shape[1] == shape[1])
        if not ok:
            alt = " or (1, ...)" if allow_broadcast else ""
            raise ValueError(f"{name} must have shape {shape}{alt}, got {a.shape}")
        return a

    def render(
        self,
        camera_poses=None,
        instance_transforms=None,
        deformable_points: Mapping[DeformableHandle, object] | None = None,
        active_masks: Mapping[DeformableHandle, object] | None = None,
        tube_nodes: Mapping[TubeHandle, object] | None = None,
    ):
        """Renders every env into :attr:`rgb`, :attr:`depth` and :attr:`segmentation`.

        Array arguments are Warp arrays or torch tensors on the renderer's device, used in place (zero-copy).

        Args:
            camera_poses: ``(num_envs,)`` ``wp.transform`` / torch ``(num_envs, 7)``; ``None`` uses
                :attr:`camera_poses`.
            instance_transforms: ``(num_envs, num_instances)`` ``wp.transform`` / torch
                ``(num_envs, num_instances, 7)``; ``None`` uses :attr:`instance_transforms`.
            deformable_points: ``{handle: (num_envs, V) vec3 / torch (num_envs, V, 3)}``, copied into the
                vertex buffer; a deformable not listed keeps the buffer's content (see
                :meth:`deformable_points`).
            active_masks: ``{handle: (num_envs or 1, F)}`` int32 / uint8 / bool; 0 = cut, not drawn.
                Deformables not listed are drawn whole.
            tube_nodes: ``{tube: (num_envs, num_nodes) vec3 / torch (num_envs, num_nodes, 3)}``; a tube
                not listed keeps its previous vertices.
        """
        self._require_final()
        n = self.num_envs
        dev = self.device
        cam = self._cam_xf if camera_poses is None else self._as_array(camera_poses, wp.transform, (n,), "camera_poses")
        num_inst = len(self._instances)
        if instance_transforms is None:
            inst = self._inst_xf
        else:
            if num_inst == 0:
                raise ValueError("instance_transforms given but the scene has no rigid instances")
            inst = self._as_array(instance_transforms, wp.transform, (n, num_inst), "instance_transforms")

        masks = [None] * len(self._deformables)
        for handle, m in (active_masks or {}).items():
            d = self._deformable(handle)
            masks[handle.index] = self._as_array(m, wp.int32, (n, len(d.faces)), "active_masks", True)
        for handle, p in (deformable_points or {}).items():
            d = self._deformable(handle)
            if d.tube is not None:
                raise ValueError("tube vertices are generated from tube_nodes, not deformable_points")
            src = self._as_array(p, wp.vec3, (n, d.num_vertices), "deformable_points")
            launching.launch(
                raster.copy_points, dim=src.shape, inputs=[src, d.vert_begin], outputs=[self._def_points],
                device=dev
            )
        for handle, p in (tube_nodes or {}).items():
            d = self._deformable(handle)
            if d.tube is None:
                raise ValueError(f"{handle!r} is not a tube")
            t = d.tube
            nodes = self._as_array(p, wp.vec3, (n, t.num_nodes), "tube_nodes")
            launching.launch(
                raster.generate_tube,
                dim=(n, t.num_nodes * t.sides),
                inputs=[nodes, t.radius, t.sides, int(t.caps), d.vert_begin],
                outputs=[self._def_points, self._def_normals],
                device=dev,
            )
        for k, d in enumerate(self._deformables):
            if d.smooth and d.tube is None:
                mask = masks[k] if masks[k] is not None else self._all_active[k]
                start, faces = self._adjacency[k]
                kernel = raster.compute_vertex_normals_u8 if mask.dtype == wp.uint8 else raster.compute_vertex_normals
                launching.launch(
                    kernel,
                    dim=(n, d.num_vertices),
                    inputs=[self._tri_vidx, d.tri_begin, d.vert_begin, start, faces, self._def_points, mask],
                    outputs=[self._def_normals],
                    device=dev,
                )

        tan_x, tan_y = 0.5 * self.width / self.focal, 0.5 * self.height / self.focal
        launching.launch(
            raster.prepare_views,
            dim=(n, num_inst + 1),
            inputs=[cam, inst, self._inst_obj, self._inst_bounds, self._obj_visible, tan_x, tan_y, self.near,
                    self.far],
            outputs=[self._views, self._inst_draw],
            device=dev,
        )
        if self.method == "raster":
            self._raster(masks)
        else:
            self._raycast(masks)

        launching.launch(
            raster.shade_visibility,
            dim=(n, self.height, self.width),
            inputs=[
                self._tri_obj,
                self._tri_vidx,
                self._obj_kind,
                self._obj_inst,
                self._obj_flags,
                self._obj_seg,
                self._obj_color,
                self._rigid_verts,
                self._rigid_normals,
                self._rigid_colors,
                self._def_points,
                self._def_normals,
                self._def_colors,
                self._views,
                self.focal,
                self.cx,
                self.cy,
                self.far,
                wp.vec3(*self.background_color),
                self.ambient,
                self.diffuse,
                int("rgb" in self.outputs),
                int("depth" in self.outputs),
                int("segmentation" in self.outputs),
                self._frame_rgb,
                self._frame_depth,
                1.0 / self.far,
                self._vbuf,
            ],
            outputs=[self._out["rgb"], self._out["depth"], self._out["segmentation"], self._frame],
            device=dev,
        )

    def _raster(self, masks):
        n, dev = self.num_envs, self.device
        common = [
            self.focal,
            self.cx,
            self.cy,
            self.near,
            self.far,
            self.width,
            self.height,
            int(self.early_depth_test),
        ]
        if self._num_slots:
            tan_x, tan_y = 0.5 * self.width / self.focal, 0.5 * self.height / self.focal
            launching.launch(
                raster.cull_clusters,
                dim=(n, self.num_clusters),
                inputs=[
                    self._cluster_inst,
                    self._cluster_bounds,
                    self._cluster_cones,
                    self._views,
                    self._inst_draw,
                    tan_x,
                    tan_y,
                    self.focal,
                    self.cx,
                    self.cy,
                    self.near,
                    self.far,
                    self.width,
                    self.height,
                ],
                outputs=[self._cluster_draw],
                device=dev,
            )
            launching.launch(
                raster.rasterize_rigid,
                dim=(n, self._num_slots),
                inputs=[
                    self._slot_tri,
                    self._slot_split,
                    self._tri_obj,
                    self._tri_vidx,
                    self._tri_cluster,
                    self._obj_inst,
                    self._obj_flags,
                    self._rigid_verts,
                    self._views,
                    self._cluster_draw,
                    *common,
                ],
                outputs=[self._vbuf_flat],
                device=dev,
            )
        for k, d in enumerate(self._deformables):
            mask = masks[k] if masks[k] is not None else self._all_active[k]
            kernel = raster.rasterize_deformable_u8 if mask.dtype == wp.uint8 else raster.rasterize_deformable
            obj = self._deformable_objects[k]
            cull = int((self._objects[obj].flags & raster.FLAG_DOUBLE_SIDED) == 0)
            launching.launch(
                kernel,
                dim=(n, len(d.faces) * d.raster_split),
                inputs=[
                    self._tri_vidx,
                    d.tri_begin,
                    d.raster_split,
                    obj,
                    cull,
                    self._def_points,
                    mask,
                    self._obj_visible,
                    self._views,
                    *common,
                ],
                outputs=[self._vbuf_flat],
                device=dev,
            )

    def _raycast(self, masks):
        n, dev = self.num_envs, self.device
        def_mesh = 0
        if self._rc_def_tris:
            for k, d in enumerate(self._deformables):
                mask = masks[k] if masks[k] is not None else self._all_active[k]
                kernel = raycast.copy_active_mask_u8 if mask.dtype == wp.uint8 else raycast.copy_active_mask
                launching.launch(
                    kernel,
                    dim=(n, len(d.faces)),
                    inputs=[mask, d.tri_begin - self.num_rigid_triangles],
                    outputs=[self._rc_def_active],
                    device=dev,
                )
            if self._rc_def_mesh is None:
                self._build_raycast_deformables()
            else:
                self._rc_def_mesh.refit()
            def_mesh = self._rc_def_mesh.id
        launching.launch(
            raycast.raycast_visibility,
            dim=(n, self.height, self.width),
            inputs=[
                self._rc_inst_mesh,
                self._rc_inst_obj,
                self._rc_inst_tri,
                self._inst_draw,
                wp.uint64(def_mesh),
                self._rc_def_tris,
                self.num_rigid_triangles,
                self._rc_def_active,
                self._tri_obj,
                self._obj_flags,
                self._obj_visible,
                self._views,
                self.focal,
                self.cx,
                self.cy,
                self.near,
                self.far,
            ],
            outputs=[self._vbuf],
            device=dev,
        )

    # ------------------------------------------------------------------ derived outputs

    def point_cloud(self, camera_poses=None, world: bool = True):
        """Back-projects :attr:`depth` into points, one per pixel: torch float32 ``(num_envs, H * W, 3)``
        with pixel ``(r, c)`` at index ``r * W + c`` (a preallocated buffer, allocated by the first call).

        Background pixels lie on the far plane; mask them with ``segmentation == -1`` (or
        ``depth >= far``).

        Args:
            camera_poses: The poses used for the last render (``None``: :attr:`camera_poses`).
            world: World-frame points if ``True``, else camera-frame (x right, y up, -z forward).
        """
        self._require_final()
        if "depth" not in self.outputs:
            raise RuntimeError("point_cloud() needs the 'depth' output")
        n = self.num_envs
        cam = self._cam_xf if camera_poses is None else self._as_array(camera_poses, wp.transform, (n,), "camera_poses")
        if self._points is None:
            self._points = wp.zeros((n, self.height * self.width), dtype=wp.vec3, device=self.device)
        launching.launch(
            raster.depth_to_points,
            dim=(n, self.height, self.width),
            inputs=[self._out["depth"], cam, self.focal, self.cx, self.cy, int(world)],
            outputs=[self._points],
            device=self.device,
        )
        return wp.to_torch(self._points)

    def project_points(self, points, camera_poses=None, out=None):
        """Projects per-env world points on the device, consistently with the rasteriser.

        Args:
            points: ``(num_envs, P)`` vec3 Warp array / torch ``(num_envs, P, 3)``.
            camera_poses: ``None`` uses :attr:`camera_poses`.
            out: Optional preallocated ``(num_envs, P)`` vec3 array (keeps the call allocation-free).

        Returns:
            torch float32 ``(num_envs, P, 3)``: continuous ``(row, col, depth)`` (see :func:`project_points`).
        """
        self._require_final()
        n = self.num_envs
        cam = self._cam_xf if camera_poses is None else self._as_array(camera_poses, wp.transform, (n,), "camera_poses")
        if isinstance(points, wp.array):
            pts = points
        else:
            pts = wp.from_torch(points, dtype=wp.vec3)
        if pts.ndim != 2 or pts.shape[0] != n or pts.dtype != wp.vec3:
            raise ValueError(f"points must be (num_envs, P) vec3 / (num_envs, P, 3), got {pts.shape} {pts.dtype}")
        if out is None:
            out = wp.empty(pts.shape, dtype=wp.vec3, device=self.device)
        launching.launch(
            raster.project_world_points,
            dim=pts.shape,
            inputs=[pts, cam, self.focal, self.cx, self.cy],
            outputs=[out],
            device=self.device,
        )
        return wp.to_torch(out)
