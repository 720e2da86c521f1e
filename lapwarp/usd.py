"""USD export of recorded rollouts: a few envs of a batch written to one ``.usda``/``.usd``/``.usdc`` stage.

:class:`UsdRecorder` reads the env's ``visual_scene()`` once (geometry, colours, camera) and on every
:meth:`UsdRecorder.record` call asks the env to ``update_visuals()``, gathers the recorded envs' rows of the
per-env visual arrays on the device (``index_select``) and copies only those rows to the host, then writes
them as time samples at time code = frame index, with ``timeCodesPerSecond = 1 / env.dt`` so a viewer plays
the rollout at the control rate. Nothing is hooked into ``env.step``: without a recorder there is no cost.

Stage layout (``<id>`` is the env index in the batch)::

    /World                                   Xform, the default prim
      /World/Prototypes                      class prim (abstract, not drawn): one Mesh per rigid object
                                             (absent with ``share_meshes=False``: geometry inline instead)
      /World/env_<id>                        Xform translated by the env's grid origin (physics runs at 0)
        /World/env_<id>/camera               Camera, time-sampled translate + orient
        /World/env_<id>/<rigid>              Xform, time-sampled translate + orient (one instance), or
        /World/env_<id>/<rigid>/instance_<k> one time-sampled Xform per instance (several instances);
              .../mesh                       Mesh referencing its prototype (geometry stored once)
        /World/env_<id>/<deformable>         Mesh, time-sampled ``points`` and ``extent``; cut faces hidden
                                             by time-sampled ``holeIndices`` (or rewritten topology)
        /World/env_<id>/<rod>                BasisCurves (linear), time-sampled ``points``, ``widths`` = 2 r; a rod
                                             with cut segments (``face_active`` per segment) is split into one
                                             curve per intact run (time-sampled ``curveVertexCounts``)

Conventions: metres (``metersPerUnit = 1``); the stage's up axis is +Y by default because lapwarp cameras
look along -Z with +Y up (USD's camera convention), so a viewer's default orbit matches the env camera;
pass ``up_axis="Z"`` for scenes built around the physics builder's default -Z gravity. Up axis is metadata
only: coordinates are written unchanged; it decides the viewer's orientation and the plane of the env grid.
"""

from __future__ import annotations

import math
import re
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np
import torch
import warp as wp

from lapwarp.output_paths import check_output_path
from lapwarp.visuals import VisualObject, VisualScene

__all__ = ["UsdRecorder", "grid_origins", "record_rollout", "validate_usd"]

# Filmback height of the exported cameras: 24 mm expressed in tenths of a scene unit (metres), as UsdGeomCamera
# measures apertures and focal lengths; only the ratio to the focal length matters for the field of view.
_VERTICAL_APERTURE = 0.24
HIDE_MODES = ("holes", "topology")


def _import_pxr():
    try:
        from pxr import Gf, Sdf, Usd, UsdGeom, Vt
    except ImportError as exc:  # usd-core is an optional extra
        raise ImportError("USD export needs usd-core: pip install 'lapwarp[usd]' (or pip install usd-core)") from exc
    return Gf, Sdf, Usd, UsdGeom, Vt


def grid_origins(count: int, spacing: float, up_axis: str = "Y") -> np.ndarray:
    """Origins ``(count, 3)`` of ``count`` envs on a near-square grid in the plane normal to ``up_axis``.

    Row-major: slot k sits in column ``k % ncols`` along +X and row ``k // ncols`` along ``up x X`` (-Z when Y is
    up, +Y when Z is up), i.e. rows recede from a viewer in the default front view of either convention.
    """
    if count < 1:
        raise ValueError(f"count must be positive, got {count}")
    ncols = math.ceil(math.sqrt(count))
    k = np.arange(count)
    origins = np.zeros((count, 3))
    origins[:, 0] = (k % ncols) * spacing
    if up_axis == "Y":
        origins[:, 2] = -(k // ncols) * spacing
    else:
        origins[:, 1] = (k // ncols) * spacing
    return origins


def _safe_name(name: str) -> str:
    """A valid USD prim name from an object name (identifiers only; a leading digit gets an underscore)."""
    out = re.sub(r"[^A-Za-z0-9_]", "_", name) or "_"
    return "_" + out if out[0].isdigit() else out


class UsdRecorder:
    """Records envs ``env_ids`` of a batched env into a USD stage, one time sample per :meth:`record` call.

    Typical use::

        rec = UsdRecorder(env, "reach.usda", env_ids=(0, 1))
        rec.record()                      # time code 0: the state after reset
        for _ in range(steps):
            env.step(policy(obs))
            rec.record()                  # time code 1, 2, ...
        rec.close()                       # writes the file (also on ``with UsdRecorder(...) as rec:`` exit)

    Frames are held in an in-memory stage and written by :meth:`close` (or :meth:`save`), so the file on disk is
    always complete and the format follows the extension (``.usda`` text, ``.usd``/``.usdc`` binary crate).

    Args:
        env: a lapwarp env (or anything exposing ``visual_scene()``, ``update_visuals()``, ``num_envs``, ``dt``,
            and optionally ``device`` and ``cfg.image_shape`` for the camera aspect ratio).
        path: output file, ``.usda``, ``.usd`` or ``.usdc``.
        env_ids: envs of the batch to record, distinct, in ``[0, num_envs)``.
        spacing: distance between neighbouring envs on the grid (m); ``None`` picks 1.25 x the larger horizontal
            extent of the first recorded frame (at least 0.1 m).
        origins: explicit env origins ``(len(env_ids), 3)`` in metres instead of the grid.
        up_axis: "Y" (default, the camera convention) or "Z"; stage metadata and the grid plane.
        hide_cut_faces: how faces with ``face_active == 0`` disappear: "holes" (default) writes time-sampled
            ``holeIndices``, the UsdGeomMesh attribute for removed faces, keeping the topology (and anything
            indexed by face) fixed; Hydra-based viewers (usdview, Omniverse) honour it. "topology" instead writes
            time-sampled ``faceVertexCounts``/``faceVertexIndices`` of the active faces only, which any tool that
            reads animated meshes shows correctly, at the cost of varying topology.
        share_meshes: store each rigid mesh once under ``/World/Prototypes`` and reference it from every instance
            (default); ``False`` writes the geometry inline in every instance, for tools that do not compose
            references.
        make_dirs: create the missing folders of ``path``; otherwise a missing folder (like an unwritable one)
            raises ``ValueError`` here, before anything is recorded.
    """

    def __init__(self, env, path: str | Path, env_ids: Sequence[int] = (0,), spacing: float | None = None,
                 origins: np.ndarray | None = None, up_axis: str = "Y", hide_cut_faces: str = "holes",
                 share_meshes: bool = True, make_dirs: bool = False):
        self._pxr = _import_pxr()
        Gf, Sdf, Usd, UsdGeom, Vt = self._pxr
        if Path(path).suffix not in (".usda", ".usd", ".usdc"):
            raise ValueError(f"USD path must end in .usda, .usd or .usdc, got {str(path)!r}")
        self.path = check_output_path(path, "USD path", make_dirs)  # fail now, not after the recording
        if up_axis not in ("Y", "Z"):
            raise ValueError(f"up_axis must be 'Y' or 'Z', got {up_axis!r}")
        if hide_cut_faces not in HIDE_MODES:
            raise ValueError(f"hide_cut_faces must be one of {HIDE_MODES}, got {hide_cut_faces!r}")
        ids = [int(i) for i in env_ids]
        if not ids or len(set(ids)) != len(ids) or min(ids) < 0 or max(ids) >= env.num_envs:
            raise ValueError(f"env_ids must be distinct indices in [0, {env.num_envs}), got {list(env_ids)}")
        if spacing is not None and not spacing > 0.0:
            raise ValueError(f"spacing must be positive, got {spacing!r}")
        self.env = env
        self.env_ids = ids
        self.up_axis = up_axis
        self.hide_cut_faces = hide_cut_faces
        self.share_meshes = bool(share_meshes)
        self.dt = float(env.dt)
        self.scene: VisualScene = env.visual_scene()
        self.num_frames = 0
        self._closed = False
        self._spacing = spacing
        self.spacing: float | None = spacing  # resolved by the first record() when None (automatic)
        self.origins: np.ndarray | None = None  # (len(env_ids), 3) env origins, set by the first record()
        self._origins = None if origins is None else np.asarray(origins, dtype=np.float64)
        if self._origins is not None and self._origins.shape != (len(ids), 3):
            raise ValueError(f"origins must have shape ({len(ids)}, 3), got {self._origins.shape}")
        device = getattr(env, "device", None) or str(self.scene.camera.poses.device)
        self._torch_device = torch.device(str(device))
        self._index = torch.as_tensor(ids, dtype=torch.long, device=self._torch_device)
        self._streams: dict[int, wp.Stream] = {}  # torch stream handle -> Warp stream

        self.stage = Usd.Stage.CreateInMemory()
        UsdGeom.SetStageUpAxis(self.stage, UsdGeom.Tokens.y if up_axis == "Y" else UsdGeom.Tokens.z)
        UsdGeom.SetStageMetersPerUnit(self.stage, 1.0)
        self.stage.SetTimeCodesPerSecond(1.0 / self.dt)
        self.stage.SetFramesPerSecond(1.0 / self.dt)
        self.stage.SetStartTimeCode(0)
        self.stage.SetEndTimeCode(0)
        world = UsdGeom.Xform.Define(self.stage, "/World")
        self.stage.SetDefaultPrim(world.GetPrim())
        self._object_names = self._unique_names(self.scene.objects)
        if self.share_meshes:
            self._define_prototypes()
        self._env_paths = [f"/World/env_{i}" for i in ids]
        self._ops: dict[str, tuple] = {}  # prim path -> (translate op, orient op)
        self._prims: dict[str, object] = {}  # prim path -> schema object of a time-varying gprim
        self._last_holes: dict[str, np.ndarray] = {}
        self._env_xforms = []
        for path in self._env_paths:
            xform = UsdGeom.Xform.Define(self.stage, path)
            self._env_xforms.append(xform.AddTranslateOp())
            self._define_env(path)

    # ------------------------------------------------------------------ stage set-up
    @staticmethod
    def _unique_names(objects: list[VisualObject]) -> list[str]:
        names, seen = [], set()
        reserved = {"camera", "Prototypes"}
        for obj in objects:
            base = _safe_name(obj.name)
            name, k = base, 1
            while name in seen or name in reserved:
                name, k = f"{base}_{k}", k + 1
            seen.add(name)
            names.append(name)
        return names

    def _color(self, obj: VisualObject):
        Gf = self._pxr[0]
        return [Gf.Vec3f(*(float(c) for c in obj.color))]

    def _define_prototypes(self) -> None:
        """Rigid meshes once, under an abstract class prim that viewers do not draw; instances reference them."""
        self.stage.CreateClassPrim("/World/Prototypes")
        self._prototype_paths: dict[int, str] = {}
        for k, obj in enumerate(self.scene.objects):
            if obj.kind == "rigid":
                path = f"/World/Prototypes/{self._object_names[k]}"
                self._define_rigid_mesh(path, obj)
                self._prototype_paths[k] = path

    def _define_rigid_mesh(self, path: str, obj: VisualObject):
        Gf, Sdf, Usd, UsdGeom, Vt = self._pxr
        mesh = UsdGeom.Mesh.Define(self.stage, path)
        self._write_static_mesh(mesh, obj.vertices, obj.faces, double_sided=False)
        mesh.CreateExtentAttr(Vt.Vec3fArray([Gf.Vec3f(*obj.vertices.min(0).tolist()),
                                             Gf.Vec3f(*obj.vertices.max(0).tolist())]))
        mesh.CreateDisplayColorPrimvar(UsdGeom.Tokens.constant).Set(self._color(obj))
        return mesh

    def _write_static_mesh(self, mesh, vertices: np.ndarray, faces: np.ndarray, double_sided: bool) -> None:
        Gf, Sdf, Usd, UsdGeom, Vt = self._pxr
        mesh.CreatePointsAttr(Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(vertices, dtype=np.float32)))
        mesh.CreateFaceVertexCountsAttr(Vt.IntArray.FromNumpy(np.full(len(faces), 3, dtype=np.int32)))
        mesh.CreateFaceVertexIndicesAttr(Vt.IntArray.FromNumpy(np.ascontiguousarray(faces, dtype=np.int32).ravel()))
        # Triangle soups, not subdivision cages: without "none" viewers would smooth them with Catmull-Clark.
        mesh.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)
        mesh.CreateDoubleSidedAttr(double_sided)

    def _define_xform(self, path: str):
        Gf, Sdf, Usd, UsdGeom, Vt = self._pxr
        xform = UsdGeom.Xform.Define(self.stage, path)
        self._ops[path] = (xform.AddTranslateOp(UsdGeom.XformOp.PrecisionFloat),
                           xform.AddOrientOp(UsdGeom.XformOp.PrecisionFloat))
        return xform

    def _define_env(self, env_path: str) -> None:
        Gf, Sdf, Usd, UsdGeom, Vt = self._pxr
        cam_spec = self.scene.camera
        cam = UsdGeom.Camera.Define(self.stage, f"{env_path}/camera")
        # float precision: the env's poses are float32, doubles would only add digits of noise to the file
        self._ops[cam.GetPath().pathString] = (cam.AddTranslateOp(UsdGeom.XformOp.PrecisionFloat),
                                               cam.AddOrientOp(UsdGeom.XformOp.PrecisionFloat))
        height, width = getattr(getattr(self.env, "cfg", None), "image_shape", (1, 1))
        cam.CreateProjectionAttr(UsdGeom.Tokens.perspective)
        cam.CreateVerticalApertureAttr(_VERTICAL_APERTURE)
        cam.CreateHorizontalApertureAttr(_VERTICAL_APERTURE * width / height)
        cam.CreateFocalLengthAttr(0.5 * _VERTICAL_APERTURE / math.tan(0.5 * math.radians(cam_spec.fov_deg)))
        cam.CreateClippingRangeAttr(Gf.Vec2f(float(cam_spec.near), float(cam_spec.far)))

        for k, obj in enumerate(self.scene.objects):
            path = f"{env_path}/{self._object_names[k]}"
            if obj.kind == "rigid":
                count = obj.transforms.shape[1]
                root = self._define_xform(path) if count == 1 else UsdGeom.Xform.Define(self.stage, path)
                for j in range(count):
                    inst = path if count == 1 else f"{path}/instance_{j}"
                    if count > 1:
                        self._define_xform(inst)
                    if self.share_meshes:
                        mesh = UsdGeom.Mesh.Define(self.stage, f"{inst}/mesh")
                        mesh.GetPrim().GetReferences().AddInternalReference(self._prototype_paths[k])
                    else:
                        self._define_rigid_mesh(f"{inst}/mesh", obj)
                imageable = root
            elif obj.kind == "deformable":
                mesh = UsdGeom.Mesh.Define(self.stage, path)
                # cloth and cut tissue show their inner side, so deformables are double sided
                self._write_static_mesh(mesh, obj.vertices, obj.faces, double_sided=True)
                mesh.CreateDisplayColorPrimvar(UsdGeom.Tokens.constant).Set(self._color(obj))
                self._prims[path] = mesh
                imageable = mesh
            else:
                curves = UsdGeom.BasisCurves.Define(self.stage, path)
                curves.CreateTypeAttr(UsdGeom.Tokens.linear)
                curves.CreateWrapAttr(UsdGeom.Tokens.nonperiodic)
                curves.CreateCurveVertexCountsAttr(Vt.IntArray([int(obj.points.shape[1])]))
                curves.CreateWidthsAttr(Vt.FloatArray([2.0 * float(obj.radius)]))
                curves.SetWidthsInterpolation(UsdGeom.Tokens.constant)
                curves.CreateDisplayColorPrimvar(UsdGeom.Tokens.constant).Set(self._color(obj))
                self._prims[path] = curves
                imageable = curves
            if not obj.visible:
                imageable.CreateVisibilityAttr(UsdGeom.Tokens.invisible)

    # ------------------------------------------------------------------ recording
    def _device_scope(self):
        """On CUDA, launch ``update_visuals`` on torch's current stream, where the env's step and our gathers run."""
        if self._torch_device.type != "cuda":
            return wp.ScopedDevice(str(self._torch_device))
        current = torch.cuda.current_stream(self._torch_device)
        stream = self._streams.get(current.cuda_stream)
        if stream is None:
            stream = self._streams[current.cuda_stream] = wp.stream_from_torch(current)
        return wp.ScopedStream(stream)

    def _gather(self, array: wp.array) -> np.ndarray:
        """Rows ``env_ids`` of a per-env array: selected on the device, then only those rows copied to the host."""
        # wp.to_torch is a zero-copy view; wp.transform / wp.vec3 elements become a trailing axis of 7 / 3 floats
        return wp.to_torch(array).index_select(0, self._index).cpu().numpy()

    def _set_pose(self, path: str, pose: np.ndarray, time: float) -> None:
        Gf = self._pxr[0]
        translate, orient = self._ops[path]
        p, q = pose[:3], pose[3:7]  # wp.transform layout: position, then quaternion xyzw
        translate.Set(Gf.Vec3f(*(float(v) for v in p)), time)
        orient.Set(Gf.Quatf(float(q[3]), float(q[0]), float(q[1]), float(q[2])), time)

    def _frame_extent(self, frame: dict) -> np.ndarray:
        """Bounds (2, 3) of every object of env slot 0 in this frame (rigid meshes by their placed vertices)."""
        lo, hi = np.full(3, np.inf), np.full(3, -np.inf)
        for k, obj in enumerate(self.scene.objects):
            if obj.kind == "rigid":
                for pose in frame[k][0][0]:
                    rot = _quat_to_matrix(pose[3:7])
                    pts = obj.vertices @ rot.T + pose[:3]
                    lo, hi = np.minimum(lo, pts.min(0)), np.maximum(hi, pts.max(0))
            else:
                pts = frame[k][0][0]
                pad = float(obj.radius) if obj.kind == "rod" else 0.0
                lo, hi = np.minimum(lo, pts.min(0) - pad), np.maximum(hi, pts.max(0) + pad)
        return np.stack([lo, hi])

    def _resolve_origins(self, frame: dict) -> np.ndarray:
        if self._origins is not None:
            return self._origins
        spacing = self._spacing
        if spacing is None:
            lo, hi = self._frame_extent(frame) if self.scene.objects else (np.zeros(3), np.zeros(3))
            horizontal = [0, 2] if self.up_axis == "Y" else [0, 1]
            size = float(np.max(hi[horizontal] - lo[horizontal])) if np.all(np.isfinite(lo)) else 0.0
            spacing = max(1.25 * size, 0.1)
        self.spacing = spacing
        return grid_origins(len(self.env_ids), spacing, self.up_axis)

    def record(self) -> int:
        """Write the recorded envs' current visual state as the next time sample; returns its time code.

        Call it once after ``reset`` (time code 0) and once after every ``env.step``: time code t is the state
        after t steps. Auto-reset envs show their new episode, exactly as the env returns it.
        """
        if self._closed:
            raise RuntimeError("this UsdRecorder is closed")
        Gf, Sdf, Usd, UsdGeom, Vt = self._pxr
        with self._device_scope():
            self.env.update_visuals()
            cams = self._gather(self.scene.camera.poses)
            frame = {}
            for k, obj in enumerate(self.scene.objects):
                if obj.kind == "rigid":
                    frame[k] = (self._gather(obj.transforms),)
                else:
                    mask = self._gather(obj.face_active) if obj.face_active is not None else None
                    frame[k] = (self._gather(obj.points), mask)
        t = float(self.num_frames)
        if self.num_frames == 0:
            self.origins = self._resolve_origins(frame)
            for op, origin in zip(self._env_xforms, self.origins, strict=True):
                op.Set(Gf.Vec3d(*origin.tolist()))
        for slot, env_path in enumerate(self._env_paths):
            self._set_pose(f"{env_path}/camera", cams[slot], t)
            for k, obj in enumerate(self.scene.objects):
                path = f"{env_path}/{self._object_names[k]}"
                if obj.kind == "rigid":
                    poses = frame[k][0][slot]
                    if len(poses) == 1:
                        self._set_pose(path, poses[0], t)
                    else:
                        for j, pose in enumerate(poses):
                            self._set_pose(f"{path}/instance_{j}", pose, t)
                    continue
                points, masks = frame[k]
                pts = np.ascontiguousarray(points[slot], dtype=np.float32)
                prim = self._prims[path]
                prim.GetPointsAttr().Set(Vt.Vec3fArray.FromNumpy(pts), t)
                pad = float(obj.radius) if obj.kind == "rod" else 0.0
                lo, hi = pts.min(0) - pad, pts.max(0) + pad
                prim.GetExtentAttr().Set(Vt.Vec3fArray([Gf.Vec3f(*lo.tolist()), Gf.Vec3f(*hi.tolist())]), t)
                if masks is not None and obj.kind == "rod":
                    self._write_cut_segments(prim, pts, masks[slot], t)
                elif masks is not None:
                    self._write_cut_faces(path, prim, obj, masks[slot], t)
        self.num_frames += 1
        self.stage.SetEndTimeCode(t)
        return int(t)

    def _write_cut_segments(self, curves, pts: np.ndarray, active: np.ndarray, t: float) -> None:
        """A rod with removed segments: one linear curve per run of present segments (an isolated node becomes a
        zero-length curve, so the points still cover every node); counts and points are time-sampled."""
        Vt = self._pxr[4]
        runs, start = [], 0
        for k, present in enumerate(np.asarray(active).reshape(-1)):
            if present == 0:
                runs.append((start, k))
                start = k + 1
        runs.append((start, len(pts) - 1))
        counts = [max(b - a + 1, 2) for a, b in runs]
        # written every frame (before a first sample USD would hold the first sample's counts)
        points = np.concatenate([pts[a:b + 1] if b > a else pts[[a, a]] for a, b in runs])
        curves.GetPointsAttr().Set(Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(points, dtype=np.float32)), t)
        curves.GetCurveVertexCountsAttr().Set(Vt.IntArray(counts), t)

    def _write_cut_faces(self, path: str, mesh, obj: VisualObject, active: np.ndarray, t: float) -> None:
        """Hide inactive faces; a sample is written only when the set changes (int arrays hold their value)."""
        Vt = self._pxr[4]
        holes = np.flatnonzero(active == 0).astype(np.int32)
        last = self._last_holes.get(path)
        if last is not None and np.array_equal(last, holes):
            return
        self._last_holes[path] = holes
        if self.hide_cut_faces == "holes":
            mesh.GetHoleIndicesAttr().Set(Vt.IntArray.FromNumpy(holes), t)
        else:
            keep = obj.faces[active != 0]
            mesh.GetFaceVertexCountsAttr().Set(Vt.IntArray.FromNumpy(np.full(len(keep), 3, dtype=np.int32)), t)
            mesh.GetFaceVertexIndicesAttr().Set(Vt.IntArray.FromNumpy(np.ascontiguousarray(keep).ravel()), t)

    # ------------------------------------------------------------------ output
    def save(self) -> Path:
        """Write the stage recorded so far to ``path`` (may be called repeatedly); returns the path."""
        self.path.parent.mkdir(parents=True, exist_ok=True)
        if not self.stage.GetRootLayer().Export(str(self.path)):
            raise OSError(f"could not write USD file {self.path}")
        return self.path

    def close(self) -> Path:
        """Write the file and stop recording; returns the path."""
        if not self._closed:
            self.save()
            self._closed = True
        return self.path

    def __enter__(self) -> UsdRecorder:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def _quat_to_matrix(q: np.ndarray) -> np.ndarray:
    x, y, z, w = (float(v) for v in q)
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ])


def record_rollout(env, policy: Callable | None, steps: int, path: str | Path, env_ids: Sequence[int] = (0,),
                   **recorder_kwargs) -> Path:
    """Run ``steps`` env steps from the env's current state and record envs ``env_ids`` to ``path``.

    Args:
        env: a lapwarp env.
        policy: ``actions = policy(observations)``; ``None`` sends zero actions (no-op).
        steps: number of env steps; the file holds ``steps + 1`` time samples (0 = the current state).
        path: output ``.usda``/``.usd``/``.usdc`` file.
        env_ids: envs of the batch to record.
        **recorder_kwargs: passed to :class:`UsdRecorder` (``spacing``, ``up_axis``, ``hide_cut_faces``, ...).

    Returns:
        The path written.
    """
    if steps < 0:
        raise ValueError(f"steps must be >= 0, got {steps}")
    obs = env.get_observations()
    with UsdRecorder(env, path, env_ids=env_ids, **recorder_kwargs) as rec:
        rec.record()
        for _ in range(steps):
            if policy is None:
                shape = (env.num_envs,) if env.is_discrete else (env.num_envs, env.num_actions)
                dtype = torch.long if env.is_discrete else torch.float32
                # index 2d is the discrete no-op row (lapwarp.instruments.discrete_action_table)
                fill = 2 * env.action_dim if env.is_discrete else 0
                actions = torch.full(shape, fill, dtype=dtype, device=env.device)
            else:
                actions = policy(obs)
            obs, _, _, _ = env.step(actions)
            rec.record()
    return Path(path)


def validate_usd(path: str | Path) -> list[str]:
    """Validate a USD file with every validator registered in usd-core; returns the error messages (empty = valid).

    Uses the ``UsdValidation`` framework (what ``usdchecker`` runs in usd-core >= 25); older usd-core releases
    fall back to ``UsdUtils.ComplianceChecker``. Warnings and infos are not returned.
    """
    Gf, Sdf, Usd, UsdGeom, Vt = _import_pxr()
    stage = Usd.Stage.Open(str(path))
    if stage is None:
        return [f"could not open {path}"]
    try:
        from pxr import UsdValidation
    except ImportError:
        UsdValidation = None
    if UsdValidation is not None and hasattr(UsdValidation, "ValidationContext"):
        validators = UsdValidation.ValidationRegistry().GetOrLoadAllValidators()
        errors = UsdValidation.ValidationContext(validators).Validate(stage)
        return [e.GetErrorAsString() for e in errors if e.GetType() == UsdValidation.ValidationErrorType.Error]
    from pxr import UsdUtils

    checker = UsdUtils.ComplianceChecker()
    checker.CheckCompliance(str(path))
    return list(checker.GetErrors()) + list(checker.GetFailedChecks())
