"""The camera of a task: a fixed endoscope view (a pose given by position and Euler angles or a look-at point) or a
pivotized oblique endoscope that rides on an instrument of the rig. Either way the task gets a
``lapwarp.visuals.CameraSpec`` whose per-env poses the renderer reads (the camera looks along its local -Z with +Y
up, as SOFA and OpenGL do).

For experts and target selection it also owns the oblique endoscope's kinematics in torch (batched, on the env's
device): the camera states that centre a point at a distance (:func:`oblique_camera_ptsd`), the optical pose of a
state (:func:`camera_pose_from_ptsd`), and line-of-sight checks against a mesh (:func:`sight_lines_clear`).
"""

from __future__ import annotations

import math

import numpy as np
import torch
import warp as wp

from lapwarp import launching
from lapwarp.kernels.raster import world_to_pixel
from lapwarp.visuals import CameraSpec, look_at_transform

wp.set_module_options({"enable_backward": False})


def rotation_from_euler_deg(euler) -> wp.quat:
    """Intrinsic XYZ Euler angles in degrees (sofa_env's camera orientation) as a quaternion."""
    q = wp.quat_identity()
    for axis, angle in zip(((1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0)), euler, strict=True):
        q = q * wp.quat_from_axis_angle(wp.vec3(*axis), math.radians(angle))
    return q


def fixed_camera(num_envs: int, device, position, fov_deg: float, near: float, far: float, euler_deg=(0.0, 0.0, 0.0),
                 look_at=None) -> CameraSpec:
    """The same camera pose in every env: at ``position`` (m) with intrinsic XYZ ``euler_deg``, or looking at
    ``look_at``; vertical field of view ``fov_deg``, clip planes ``near``/``far`` (m)."""
    if look_at is not None:
        pose = look_at_transform(position, look_at)
    else:
        eye = wp.vec3(*np.asarray(position, dtype=np.float64).tolist())
        pose = wp.transform(eye, rotation_from_euler_deg(euler_deg))
    poses = wp.array([pose] * num_envs, dtype=wp.transform, device=device)
    return CameraSpec(poses=poses, fov_deg=float(fov_deg), near=float(near), far=float(far))


@wp.func
def oblique_optic_pose(tip: wp.transform, optic_offset: wp.quat) -> wp.transform:
    """Optical pose of an oblique endoscope: its TPSD tip pose rotated by the optic offset."""
    return wp.transform(wp.transform_get_translation(tip), wp.transform_get_rotation(tip) * optic_offset)


#: Relative pixel distance of a point behind the camera (sofa_env's value is unbounded there, which makes a delta
#: feature of it explode).
MAX_PIXEL_DISTANCE = wp.constant(2.0)


@wp.func
def relative_pixel_distance(cam: wp.transform, poi: wp.vec3, focal: float, width: float, height: float,
                            near: float) -> wp.vec2:
    """(relative pixel distance of the POI to the image centre in [0, 2], in frame 0/1)."""
    pix = world_to_pixel(cam, poi, focal, 0.5 * width, 0.5 * height)
    rel = float(MAX_PIXEL_DISTANCE)
    in_frame = float(0.0)
    if pix[2] > near:
        dr = pix[0] - 0.5 * height
        dc = pix[1] - 0.5 * width
        rel = wp.min(wp.sqrt(dr * dr + dc * dc) / (0.5 * wp.sqrt(width * width + height * height)),
                     float(MAX_PIXEL_DISTANCE))
        if pix[0] >= 0.0 and pix[0] < height and pix[1] >= 0.0 and pix[1] < width:
            in_frame = 1.0
    return wp.vec2(rel, in_frame)


@wp.kernel
def update_endoscope_poses(tip_pose: wp.array2d(dtype=wp.transform), column: int, optic_offset: wp.quat,
                           poses_out: wp.array(dtype=wp.transform)):
    env = wp.tid()
    poses_out[env] = oblique_optic_pose(tip_pose[env, column], optic_offset)


class EndoscopeCamera:
    """A pivotized endoscope with an oblique optic, riding on instrument ``column`` of a rig.

    sofa_env's optical pose is ``FK(ptsd) R_xyz(0, 180, 180) R_xyz(-oblique, 0, 0)``; with ``R_xyz(0, 180, 180) =
    Rx(180)`` this is ``FK(ptsd) Rx(180 - oblique)``: the camera looks along the shaft tilted by ``oblique`` degrees
    towards the shaft's local +Y.

    Args:
        rig: the ``InstrumentRig`` (finalized) that moves the endoscope.
        column: the endoscope's instrument index in the rig.
        oblique_deg: angle between the shaft and the optical axis (deg).
        fov_deg, near, far: vertical field of view (deg) and clip planes (m).
    """

    def __init__(self, rig, column: int, oblique_deg: float, fov_deg: float, near: float, far: float):
        self.rig = rig
        self.column = int(column)
        self.optic_offset = wp.quat_from_axis_angle(wp.vec3(1.0, 0.0, 0.0), math.radians(180.0 - oblique_deg))
        w = rig.world
        self.poses = wp.zeros(w.num_envs, dtype=wp.transform, device=w.device)
        self.spec = CameraSpec(poses=self.poses, fov_deg=float(fov_deg), near=float(near), far=float(far))

    def update(self) -> None:
        """Bring ``poses`` up to the rig's current tip poses (one launch)."""
        w = self.rig.world
        launching.launch(update_endoscope_poses, dim=w.num_envs, inputs=[self.rig.pose, self.column, self.optic_offset],
                         outputs=[self.poses], device=w.device)


# ---------------------------------------------------------------------------------------------- kinematics (torch)
def euler_xyz_matrix(angles: torch.Tensor) -> torch.Tensor:
    """``Rx(a0) Ry(a1) Rz(a2)`` for angles ``(..., 3)`` in radians -> ``(..., 3, 3)``."""
    c, s = torch.cos(angles), torch.sin(angles)
    one, zero = torch.ones_like(c[..., 0]), torch.zeros_like(c[..., 0])
    rx = torch.stack([one, zero, zero, zero, c[..., 0], -s[..., 0], zero, s[..., 0], c[..., 0]], -1)
    ry = torch.stack([c[..., 1], zero, s[..., 1], zero, one, zero, -s[..., 1], zero, c[..., 1]], -1)
    rz = torch.stack([c[..., 2], -s[..., 2], zero, s[..., 2], c[..., 2], zero, zero, zero, one], -1)
    shape = angles.shape[:-1] + (3, 3)
    return rx.reshape(shape) @ ry.reshape(shape) @ rz.reshape(shape)


def quat_to_matrix(q: torch.Tensor) -> torch.Tensor:
    """Quaternions ``(..., 4)`` xyzw -> rotation matrices ``(..., 3, 3)``."""
    x, y, z, w = q.unbind(-1)
    return torch.stack([
        1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w),
        2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w),
        2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y),
    ], -1).reshape(q.shape[:-1] + (3, 3))


def oblique_camera_ptsd(rcm_position: torch.Tensor, rcm_rotation: torch.Tensor, poi: torch.Tensor, distance: float,
                        oblique_deg: float, num_roll: int = 36) -> torch.Tensor:
    """Camera states that centre ``poi`` at ``distance`` with the oblique optic, one per roll sample.

    Geometry: the optic sits at ``c = rcm + depth s`` on the shaft ``s`` and looks along ``v``, with angle
    ``oblique`` between ``s`` and ``v``. In the triangle (rcm, c, poi) the angle at ``c`` is ``180 - oblique``, so
    ``L^2 = depth^2 + D^2 + 2 depth D cos(oblique)`` (``L = |poi - rcm|``) gives the depth, and the shaft makes
    the angle ``asin(D sin(oblique) / L)`` with the direction to the POI. That leaves one free parameter, the
    azimuth of the shaft about that direction (the image's roll about the POI): we return ``num_roll`` samples of
    it. Pan and tilt follow from the shaft, spin from the oblique direction ``(v - cos(oblique) s) / sin(oblique)``,
    which is the shaft's local +Y.

    Args:
        rcm_position: ``(..., 3)`` trocar positions (m).
        rcm_rotation: ``(..., 3, 3)`` trocar orientations (world from RCM).
        poi: ``(..., 3)`` points of interest (m).
        distance: desired camera-POI distance (m).
        oblique_deg: oblique viewing angle (deg).
        num_roll: number of roll samples.

    Returns:
        ``(..., num_roll, 4)`` states (pan, tilt, spin in rad; depth in m); NaN where no solution exists
        (``L < D sin(oblique)``).
    """
    theta = math.radians(oblique_deg)
    q = (rcm_rotation.transpose(-1, -2) @ (poi - rcm_position)[..., None])[..., 0]  # POI in the RCM frame
    length = q.norm(dim=-1, keepdim=True)
    u = q / length
    depth = -distance * math.cos(theta) + torch.sqrt(length**2 - (distance * math.sin(theta)) ** 2)
    alpha = torch.asin((distance * math.sin(theta) / length).clamp(max=1.0))
    helper = torch.zeros_like(u)
    helper[..., 0] = 1.0
    use_y = u[..., 0].abs() > 0.9
    helper[use_y] = torch.tensor([0.0, 1.0, 0.0], dtype=u.dtype, device=u.device)
    e1 = torch.nn.functional.normalize(torch.linalg.cross(u, helper), dim=-1)
    e2 = torch.linalg.cross(u, e1)
    phi = torch.arange(num_roll, dtype=u.dtype, device=u.device) * (2 * math.pi / num_roll)
    w = torch.cos(phi)[:, None] * e1[..., None, :] + torch.sin(phi)[:, None] * e2[..., None, :]
    s = torch.cos(alpha)[..., None, :] * u[..., None, :] + torch.sin(alpha)[..., None, :] * w
    view = (q[..., None, :] - depth[..., None, :] * s) / distance
    y_s = (view - math.cos(theta) * s) / math.sin(theta)
    pan = torch.atan2(s[..., 0], torch.sqrt(s[..., 1] ** 2 + s[..., 2] ** 2))
    tilt = torch.atan2(-s[..., 1], s[..., 2])
    zero = torch.zeros_like(pan)
    a = euler_xyz_matrix(torch.stack([tilt, pan, zero], -1))
    local_y = (a.transpose(-1, -2) @ y_s[..., None])[..., 0]
    spin = torch.atan2(-local_y[..., 0], local_y[..., 1])
    return torch.stack([pan, tilt, spin, depth.expand_as(pan)], -1)


def camera_pose_from_ptsd(rcm_position: torch.Tensor, rcm_rotation: torch.Tensor, ptsd: torch.Tensor,
                          oblique_deg: float) -> tuple[torch.Tensor, torch.Tensor]:
    """Optic position ``(..., 3)`` and orientation ``(..., 3, 3)`` (looks along -Z) from camera states (torch)."""
    local = euler_xyz_matrix(torch.stack([ptsd[..., 1], ptsd[..., 0], ptsd[..., 2]], -1))
    rot = rcm_rotation @ local
    position = rcm_position + rot[..., :, 2] * ptsd[..., 3:4]
    offset = euler_xyz_matrix(torch.tensor([math.radians(180.0 - oblique_deg), 0.0, 0.0], dtype=ptsd.dtype,
                                            device=ptsd.device))
    return position, rot @ offset



def point_to_ptsd(rcm_position: torch.Tensor, rcm_rotation: torch.Tensor, point: torch.Tensor,
                  spin: torch.Tensor | float = 0.0) -> torch.Tensor:
    """The TPSD state ``(..., 4)`` (rad, m) that puts an instrument's tip on ``point`` (torch version of
    ``lapwarp.kernels.kinematics.point_to_ptsd``): the point in the RCM frame gives pan, tilt and depth."""
    local = (rcm_rotation.transpose(-1, -2) @ (point - rcm_position)[..., None])[..., 0]
    pan = torch.atan2(local[..., 0], torch.sqrt(local[..., 1] ** 2 + local[..., 2] ** 2))
    tilt = torch.atan2(-local[..., 1], local[..., 2])
    return torch.stack([pan, tilt, torch.as_tensor(spin, dtype=local.dtype).expand_as(pan), local.norm(dim=-1)], -1)


# ---------------------------------------------------------------------------------------------- line of sight
@wp.kernel
def check_sight_lines(
    mesh: wp.uint64,
    start: wp.array(dtype=wp.vec3),
    end: wp.array(dtype=wp.vec3),
    slack: float,
    clear_out: wp.array(dtype=wp.int32),
):
    """1 where the segment start -> end hits nothing before ``slack`` m short of its end."""
    i = wp.tid()
    d = end[i] - start[i]
    length = wp.length(d)
    if length <= slack:
        clear_out[i] = 1
        return
    query = wp.mesh_query_ray(mesh, start[i], d / length, length - slack)
    clear_out[i] = 1
    if query.result:
        clear_out[i] = 0


def sight_lines_clear(mesh: wp.Mesh, start: torch.Tensor, end: torch.Tensor, slack: float = 0.002) -> torch.Tensor:
    """Whether each segment ``start -> end`` ``(M, 3)`` (torch, on the mesh's device) misses ``mesh`` until ``slack``
    m before its end: one launch on torch's current stream, no host sync."""
    start = start.reshape(-1, 3).to(torch.float32).contiguous()
    end = end.reshape(-1, 3).to(torch.float32).contiguous()
    out = torch.zeros(start.shape[0], dtype=torch.int32, device=start.device)
    stream = wp.stream_from_torch(torch.cuda.current_stream(start.device)) if start.is_cuda else None
    with wp.ScopedStream(stream) if stream is not None else wp.ScopedDevice(mesh.device):
        launching.launch(check_sight_lines, dim=start.shape[0],
                         inputs=[mesh.id, wp.from_torch(start, dtype=wp.vec3), wp.from_torch(end, dtype=wp.vec3),
                                 float(slack)], outputs=[wp.from_torch(out)], device=mesh.device)
    return out.bool()
