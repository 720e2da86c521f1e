"""USD export: a Reach rollout and hand-made deformable / rod scenes written, validated and read back."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
import warp as wp

import lapwarp
from lapwarp.experts import make_expert
from lapwarp.usd import UsdRecorder, grid_origins, record_rollout, validate_usd
from lapwarp.visuals import CameraSpec, VisualObject, VisualScene, look_at_transform

pxr = pytest.importorskip("pxr")
from pxr import Gf, Usd, UsdGeom  # noqa: E402

STEPS = 5


def _assert_valid(path) -> None:
    errors = validate_usd(path)
    assert errors == [], "USD validation errors:\n" + "\n".join(errors)


def _world_translation(stage, path: str, t: float) -> np.ndarray:
    xform = UsdGeom.Xformable(stage.GetPrimAtPath(path))
    return np.array(xform.ComputeLocalToWorldTransform(t).ExtractTranslation())


@pytest.fixture(scope="module")
def reach_rollout(tmp_path_factory, request):
    """Reach with 3 envs, envs 0 and 2 recorded over 5 expert steps; positions kept per frame for checks."""
    device = request.getfixturevalue("device")
    env = lapwarp.make("Reach", num_envs=3, device=device)
    expert = make_expert(env)
    path = tmp_path_factory.mktemp("usd") / "reach.usda"
    ee, target = [], []
    rec = UsdRecorder(env, path, env_ids=(0, 2))
    rec.record()
    ee.append(env.ee_position.numpy().copy())
    target.append(env.target_position.numpy().copy())
    for _ in range(STEPS):
        env.step(expert())
        rec.record()
        ee.append(env.ee_position.numpy().copy())
        target.append(env.target_position.numpy().copy())
    rec.close()
    return env, rec, path, np.array(ee), np.array(target)


def test_reach_usd_passes_validation(reach_rollout):
    _, _, path, _, _ = reach_rollout
    _assert_valid(path)


def test_reach_usd_metadata_and_prims(reach_rollout):
    env, rec, path, _, _ = reach_rollout
    stage = Usd.Stage.Open(str(path))
    assert UsdGeom.GetStageUpAxis(stage) == UsdGeom.Tokens.y
    assert UsdGeom.GetStageMetersPerUnit(stage) == 1.0
    assert stage.GetTimeCodesPerSecond() == pytest.approx(1.0 / env.dt) == pytest.approx(10.0)
    assert (stage.GetStartTimeCode(), stage.GetEndTimeCode()) == (0.0, STEPS)
    assert stage.GetDefaultPrim().GetPath() == "/World"
    for env_id in (0, 2):
        root = f"/World/env_{env_id}"
        assert stage.GetPrimAtPath(f"{root}/camera").IsA(UsdGeom.Camera)
        for name in ("end_effector", "shaft", "target"):
            assert stage.GetPrimAtPath(f"{root}/{name}").IsA(UsdGeom.Xform)
            mesh = UsdGeom.Mesh(stage.GetPrimAtPath(f"{root}/{name}/mesh"))
            assert mesh, f"{root}/{name}/mesh is not a Mesh"
            obj = next(o for o in env.visual_scene().objects if o.name == name)
            # geometry comes through the reference to the prototype, stored once
            np.testing.assert_allclose(np.array(mesh.GetPointsAttr().Get()), obj.vertices, atol=1e-7)
            assert list(mesh.GetFaceVertexIndicesAttr().Get()) == obj.faces.ravel().tolist()
            assert mesh.GetSubdivisionSchemeAttr().Get() == UsdGeom.Tokens.none
            color = mesh.GetDisplayColorPrimvar().Get()[0]
            np.testing.assert_allclose(np.array(color), obj.color, atol=1e-6)
    assert not stage.GetPrimAtPath("/World/env_1").IsValid()  # not recorded
    # the prototypes are abstract: they are not part of the drawn scene
    drawn = [p.GetPath().pathString for p in stage.Traverse() if p.IsA(UsdGeom.Mesh)]
    assert len(drawn) == 6 and not any("Prototypes" in p for p in drawn)


def test_reach_usd_samples_match_the_env(reach_rollout):
    env, rec, path, ee, target = reach_rollout
    stage = Usd.Stage.Open(str(path))
    origins = {0: rec.origins[0], 2: rec.origins[1]}
    assert np.allclose(origins[0], 0.0) and origins[2][0] > 0.2 and origins[2][1] == 0.0 == origins[2][2]
    rcm = np.array(env.cfg.rcm_position)
    for env_id, origin in origins.items():
        root = f"/World/env_{env_id}"
        op = UsdGeom.Xformable(stage.GetPrimAtPath(f"{root}/end_effector")).GetOrderedXformOps()[0]
        assert op.GetTimeSamples() == [float(t) for t in range(STEPS + 1)]
        for t in range(STEPS + 1):
            np.testing.assert_allclose(_world_translation(stage, f"{root}/end_effector", t), ee[t, env_id] + origin,
                                       atol=1e-6)
            np.testing.assert_allclose(_world_translation(stage, f"{root}/target", t), target[t, env_id] + origin,
                                       atol=1e-6)
            # the shaft's local +Z (its axis) points from the RCM through the end effector
            m = UsdGeom.Xformable(stage.GetPrimAtPath(f"{root}/shaft")).ComputeLocalToWorldTransform(t)
            axis = np.array(m.TransformDir(Gf.Vec3d(0, 0, 1)))
            expected = (ee[t, env_id] - rcm) / np.linalg.norm(ee[t, env_id] - rcm)
            np.testing.assert_allclose(axis / np.linalg.norm(axis), expected, atol=1e-5)
        assert not np.allclose(ee[0, env_id], ee[STEPS, env_id])  # the expert moved it: samples differ
        cam = UsdGeom.Camera(stage.GetPrimAtPath(f"{root}/camera"))
        gf_cam = cam.GetCamera(2.0)
        assert gf_cam.GetFieldOfView(Gf.Camera.FOVVertical) == pytest.approx(env.cfg.camera_fov_deg, rel=1e-5)
        assert (gf_cam.clippingRange.min, gf_cam.clippingRange.max) == pytest.approx((0.01, 2.0))
        np.testing.assert_allclose(np.array(gf_cam.transform.ExtractTranslation()),
                                   np.array(env.cfg.camera_position) + origin, atol=1e-6)


def test_recording_does_not_change_the_rollout(device, tmp_path):
    plain = lapwarp.make("Reach", num_envs=2, device=device, seed=3)
    recorded = lapwarp.make("Reach", num_envs=2, device=device, seed=3)
    gen = torch.Generator().manual_seed(0)
    actions = [(torch.rand(2, 3, generator=gen) * 2 - 1).to(plain.device) for _ in range(4)]
    plain_obs = [plain.step(a)[0]["policy"] for a in actions]
    it = iter(actions)
    record_rollout(recorded, lambda obs: next(it), len(actions), tmp_path / "r.usd", env_ids=(1,))
    np.testing.assert_array_equal(plain.ee_position.numpy(), recorded.ee_position.numpy())
    assert torch.equal(plain_obs[-1], recorded.get_observations()["policy"])
    # binary crate output re-opens with the same samples
    stage = Usd.Stage.Open(str(tmp_path / "r.usd"))
    np.testing.assert_allclose(_world_translation(stage, "/World/env_1/end_effector", len(actions)),
                               recorded.ee_position.numpy()[1], atol=1e-6)


def test_inline_meshes_without_references(device, tmp_path):
    env = lapwarp.make("Reach", num_envs=1, device=device)
    path = tmp_path / "inline.usda"
    record_rollout(env, None, 2, path, share_meshes=False)
    _assert_valid(path)
    stage = Usd.Stage.Open(str(path))
    assert not stage.GetPrimAtPath("/World/Prototypes").IsValid()
    prim = stage.GetPrimAtPath("/World/env_0/target/mesh")
    assert not prim.HasAuthoredReferences()
    obj = next(o for o in env.visual_scene().objects if o.name == "target")
    np.testing.assert_allclose(np.array(UsdGeom.Mesh(prim).GetPointsAttr().Get()), obj.vertices, atol=1e-7)
    assert UsdGeom.Mesh(stage.GetPrimAtPath("/World/env_0/end_effector/mesh")).GetDisplayColorPrimvar().Get()[0] \
        == Gf.Vec3f(0.8, 0.8, 0.8)


# ---------------------------------------------------------------------------- deformables and rods
class FakeDeformableEnv:
    """A minimal env exposing only what the recorder needs: a quad cloth (2 triangles) and a 5-node rod.

    ``frame`` drives the visual state: points move by ``0.01 * frame`` along x (+ ``0.1 * env`` in y), and env 1
    loses triangle 1 from frame 2 on (a cut).
    """

    num_envs = 3
    dt = 0.05
    device = "cpu"

    def __init__(self, device: str):
        self.device = device
        self.frame = 0
        self.updates = 0
        n = self.num_envs
        self.rest = np.array([[0, 0, 0], [0.1, 0, 0], [0.1, 0.1, 0], [0, 0.1, 0]], np.float32)
        self.faces = np.array([[0, 1, 2], [0, 2, 3]], np.int32)
        self.rod_rest = np.stack([np.linspace(0, 0.2, 5), np.zeros(5), np.full(5, 0.05)], 1).astype(np.float32)
        self.cloth_points = wp.zeros((n, 4), dtype=wp.vec3, device=device)
        self.rod_points = wp.zeros((n, 5), dtype=wp.vec3, device=device)
        self.face_active = wp.ones((n, 2), dtype=wp.int32, device=device)
        pose = look_at_transform((0.05, 0.05, 0.5), (0.05, 0.05, 0.0))
        self.scene = VisualScene(
            camera=CameraSpec(poses=wp.array([pose] * n, dtype=wp.transform, device=device), fov_deg=30.0,
                              near=0.02, far=3.0),
            objects=[
                VisualObject("cloth", "deformable", (0.9, 0.6, 0.5), 1, self.rest, self.faces,
                             points=self.cloth_points, face_active=self.face_active),
                VisualObject("thread 1", "rod", (0.2, 0.3, 0.9), 2, points=self.rod_points, radius=0.002),
            ],
        )

    def expected(self, frame: int, env: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        shift = np.array([0.01 * frame, 0.1 * env, 0.0], np.float32)
        active = np.ones(2, np.int32)
        if env == 1 and frame >= 2:
            active[1] = 0
        return self.rest + shift, self.rod_rest + shift, active

    def visual_scene(self) -> VisualScene:
        return self.scene

    def update_visuals(self) -> None:
        self.updates += 1
        rows = [self.expected(self.frame, e) for e in range(self.num_envs)]
        self.cloth_points.assign(np.stack([r[0] for r in rows]))
        self.rod_points.assign(np.stack([r[1] for r in rows]))
        self.face_active.assign(np.stack([r[2] for r in rows]))


@pytest.mark.parametrize("hide", ["holes", "topology"])
def test_deformable_and_rod_samples(device, tmp_path, hide):
    env = FakeDeformableEnv(device)
    path = tmp_path / f"cloth_{hide}.usda"
    frames = 4
    with UsdRecorder(env, path, env_ids=(0, 1), spacing=0.5, hide_cut_faces=hide) as rec:
        for frame in range(frames):
            env.frame = frame
            rec.record()
    assert env.updates == frames  # update_visuals before every sample
    _assert_valid(path)
    stage = Usd.Stage.Open(str(path))
    assert stage.GetTimeCodesPerSecond() == pytest.approx(20.0)
    for slot, env_id in enumerate((0, 1)):
        root = f"/World/env_{env_id}"
        origin = np.array([0.5 * slot, 0.0, 0.0])
        np.testing.assert_allclose(_world_translation(stage, root, 0), origin)
        cloth = UsdGeom.Mesh(stage.GetPrimAtPath(f"{root}/cloth"))
        rod = UsdGeom.BasisCurves(stage.GetPrimAtPath(f"{root}/thread_1"))  # name made a valid identifier
        assert cloth and rod
        assert cloth.GetPointsAttr().GetTimeSamples() == [float(t) for t in range(frames)]
        assert rod.GetTypeAttr().Get() == UsdGeom.Tokens.linear
        assert list(rod.GetCurveVertexCountsAttr().Get()) == [5]
        assert list(rod.GetWidthsAttr().Get()) == pytest.approx([0.004])
        assert rod.GetWidthsInterpolation() == UsdGeom.Tokens.constant
        for t in range(frames):
            cloth_pts, rod_pts, active = env.expected(t, env_id)
            np.testing.assert_allclose(np.array(cloth.GetPointsAttr().Get(t)), cloth_pts, atol=1e-7)
            np.testing.assert_allclose(np.array(rod.GetPointsAttr().Get(t)), rod_pts, atol=1e-7)
            lo, hi = np.array(rod.GetExtentAttr().Get(t))
            np.testing.assert_allclose(lo, rod_pts.min(0) - 0.002, atol=1e-7)
            np.testing.assert_allclose(hi, rod_pts.max(0) + 0.002, atol=1e-7)
            if hide == "holes":
                assert list(cloth.GetHoleIndicesAttr().Get(t)) == np.flatnonzero(active == 0).tolist()
                assert list(cloth.GetFaceVertexIndicesAttr().Get(t)) == env.faces.ravel().tolist()
            else:
                visible = env.faces[active != 0]
                assert list(cloth.GetFaceVertexIndicesAttr().Get(t)) == visible.ravel().tolist()
                assert list(cloth.GetFaceVertexCountsAttr().Get(t)) == [3] * len(visible)
        cam = UsdGeom.Camera(stage.GetPrimAtPath(f"{root}/camera")).GetCamera(0.0)
        assert cam.GetFieldOfView(Gf.Camera.FOVVertical) == pytest.approx(30.0, rel=1e-5)
        # look_at: the camera's -Z (USD's viewing direction) points from the eye at the cloth centre
        view = np.array(cam.transform.TransformDir(Gf.Vec3d(0, 0, -1)))
        np.testing.assert_allclose(view / np.linalg.norm(view), [0, 0, -1], atol=1e-6)


def test_grid_origins_and_up_axis(device, tmp_path):
    np.testing.assert_allclose(grid_origins(5, 2.0, "Y"), [[0, 0, 0], [2, 0, 0], [4, 0, 0], [0, 0, -2], [2, 0, -2]])
    np.testing.assert_allclose(grid_origins(3, 1.0, "Z"), [[0, 0, 0], [1, 0, 0], [0, 1, 0]])
    env = FakeDeformableEnv(device)
    path = tmp_path / "z.usda"
    with UsdRecorder(env, path, env_ids=(2, 0, 1), spacing=1.0, up_axis="Z") as rec:
        rec.record()
    stage = Usd.Stage.Open(str(path))
    assert UsdGeom.GetStageUpAxis(stage) == UsdGeom.Tokens.z
    np.testing.assert_allclose(_world_translation(stage, "/World/env_1", 0), [0, 1, 0])  # third slot: row 1


def test_automatic_spacing_separates_envs(device, tmp_path):
    env = FakeDeformableEnv(device)
    with UsdRecorder(env, tmp_path / "auto.usda", env_ids=(0, 1)) as rec:
        rec.record()
    # the scene spans 0.2 m + 2 rod radii along x: envs sit 1.25 x that apart
    assert rec.spacing == pytest.approx(1.25 * 0.204, rel=1e-5)
    assert math.isclose(rec.origins[1][0], rec.spacing)


def test_bad_recorder_arguments(device, tmp_path):
    env = FakeDeformableEnv(device)
    with pytest.raises(ValueError, match="env_ids"):
        UsdRecorder(env, tmp_path / "a.usda", env_ids=(0, 3))
    with pytest.raises(ValueError, match="env_ids"):
        UsdRecorder(env, tmp_path / "a.usda", env_ids=(1, 1))
    with pytest.raises(ValueError, match=r"\.usda"):
        UsdRecorder(env, tmp_path / "a.obj")
    with pytest.raises(ValueError, match="up_axis"):
        UsdRecorder(env, tmp_path / "a.usda", up_axis="X")
    with pytest.raises(ValueError, match="hide_cut_faces"):
        UsdRecorder(env, tmp_path / "a.usda", hide_cut_faces="delete")
    rec = UsdRecorder(env, tmp_path / "a.usda")
    rec.record()
    rec.close()
    with pytest.raises(RuntimeError, match="closed"):
        rec.record()
