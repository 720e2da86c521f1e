"""SceneRenderer: draws an env's ``VisualScene`` with the batched rasteriser (``lapwarp.render.Renderer``).

It maps the scene description onto the renderer once (one shared mesh per rigid object, one instance column
per object instance, deformables and rod tubes), then each ``render()`` gathers the per-env transforms into
the renderer's instance array and renders: kernel launches only, so it sits inside the env's CUDA graph.
"""

from __future__ import annotations

from collections.abc import Sequence

import warp as wp

from lapwarp import launching
from lapwarp.kernels import env_kernels
from lapwarp.render import Renderer
from lapwarp.visuals import VisualScene


@wp.kernel
def tube_face_mask(segment_active: wp.array2d(dtype=wp.int32), sides: int, faces: wp.array2d(dtype=wp.int32)):
    """Thread (env, segment, side): the two triangle blocks of a tube (``Renderer.add_tube``: ``S * sides`` faces
    each, segment-major, then the caps) follow the rod segment's mask, so a cut segment leaves a gap."""
    env, seg, side = wp.tid()
    on = wp.where(segment_active[env, seg] != 0, 1, 0)
    f = seg * sides + side
    faces[env, f] = on
    faces[env, segment_active.shape[1] * sides + f] = on


class SceneRenderer:
    """Renders ``scene`` for ``num_envs`` envs at ``width`` x ``height`` into ``rgb``/``depth``/``segmentation``.

    Args:
        scene: the env's visual scene (its arrays are read in place every frame).
        num_envs: number of envs (images per render).
        width, height: image size in pixels.
        device: Warp device.
        outputs: subset of ("rgb", "depth", "segmentation") to produce.
        method: "raster" (default) or "raycast" (the BVH baseline).
    """

    def __init__(self, scene: VisualScene, num_envs: int, width: int, height: int, device,
                 outputs: Sequence[str] = ("rgb", "depth", "segmentation"), method: str = "raster"):
        cam = scene.camera
        self.scene = scene
        self.device = wp.get_device(device)
        self.renderer = Renderer(num_envs, width, height, fov=cam.fov_deg, near=cam.near, far=cam.far,
                                 device=self.device, outputs=outputs, background_color=scene.background,
                                 method=method)
        self._rigid: list[tuple[wp.array, int]] = []  # (per-env transforms, first instance column)
        self._deformable_points: dict = {}
        self._active_masks: dict = {}
        self._tubes: dict = {}
        self._tube_masks: list = []  # (segment mask (N, S), sides, face mask (N, F)) of tubes with cut segments
        column = 0
        for obj in scene.objects:
            if not obj.visible:
                continue
            if obj.kind == "rigid":
                mesh = self.renderer.add_mesh(obj.vertices, obj.faces, color=obj.color, seg_id=obj.segmentation_id)
                for _ in range(obj.transforms.shape[1]):
                    self.renderer.add_instance(mesh)
                self._rigid.append((obj.transforms, column))
                column += obj.transforms.shape[1]
            elif obj.kind == "deformable":
                handle = self.renderer.add_deformable(obj.faces, num_vertices=obj.points.shape[1], color=obj.color,
                                                      seg_id=obj.segmentation_id)
                self._deformable_points[handle] = obj.points
                if obj.face_active is not None:
                    self._active_masks[handle] = obj.face_active
            else:
                handle = self.renderer.add_tube(obj.points.shape[1], obj.radius, color=obj.color,
                                                seg_id=obj.segmentation_id)
                self._tubes[handle] = obj.points
                if obj.face_active is not None:  # per-segment mask -> the tube's faces (caps always drawn)
                    faces = 2 * handle.sides * (handle.num_nodes - 1) + (2 * handle.sides if handle.caps else 0)
                    mask = wp.ones((num_envs, faces), dtype=wp.int32, device=self.device)
                    self._tube_masks.append((obj.face_active, handle.sides, mask))
                    self._active_masks[handle] = mask
        self._instances = wp.zeros((num_envs, max(column, 1)), dtype=wp.transform, device=self.device)
        self._num_instances = column
        self.renderer.finalize()

    def set_frame_output(self, frame, rgb: bool, depth: bool) -> None:
        """``Renderer.set_frame_output``: every render also writes the observation frame ``frame``."""
        self.renderer.set_frame_output(frame, rgb, depth)

    def render(self) -> None:
        """Render every env from its current visual state (the env must have called ``update_visuals``)."""
        for transforms, column in self._rigid:
            launching.launch(env_kernels.gather_transform_columns, dim=transforms.shape, inputs=[transforms, column],
                             outputs=[self._instances], device=self.device)
        for segments, sides, faces in self._tube_masks:
            launching.launch(tube_face_mask, dim=(segments.shape[0], segments.shape[1], sides),
                             inputs=[segments, sides], outputs=[faces], device=self.device)
        self.renderer.render(
            camera_poses=self.scene.camera.poses,
            instance_transforms=self._instances if self._num_instances else None,
            deformable_points=self._deformable_points or None,
            active_masks=self._active_masks or None,
            tube_nodes=self._tubes or None,
        )

    @property
    def rgb(self):
        """uint8 torch ``(num_envs, 3, H, W)``."""
        return self.renderer.rgb

    @property
    def depth(self):
        """float32 torch ``(num_envs, 1, H, W)``, metres along the view axis; background = far."""
        return self.renderer.depth

    @property
    def segmentation(self):
        """int32 torch ``(num_envs, 1, H, W)``; background -1."""
        return self.renderer.segmentation
