"""Tests of the batched rasteriser (lapwarp.render), its ray-cast baseline and the PNG helpers.

Analytic references (plane and sphere depth, Lambert shading, tube width, projection) with named
tolerances, order independence of occlusion, per-env isolation, cutting, a golden image, and agreement
between the rasteriser and the BVH ray caster. Small images keep the CPU backend fast.

Regenerate the golden image (only after an intended change of the shading): ``python tests/test_render.py``.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import torch
import trimesh
import warp as wp

from lapwarp.imaging import image_grid, read_png, save_image_grid, write_png
from lapwarp.render import Renderer, cloth_grid_faces, focal_length, look_at, project_points

DEPTH_RTOL = 0.01  # analytic depth (brief: within 1%)
AGREE_RTOL = 1e-3  # rasteriser vs ray caster depth
AGREE_FRACTION = 0.98  # fraction of pixels that must agree
GOLDEN = Path(__file__).parent / "data" / "render_golden.png"

IDENTITY = np.array([0, 0, 0, 0, 0, 0, 1], dtype=np.float32)



def on_device(device: str, array: np.ndarray) -> torch.Tensor:
    """A torch tensor of ``array`` on the renderer's device (the renderer rejects tensors on other devices)."""
    return torch.from_numpy(np.ascontiguousarray(array)).to(device)

def quad(half: float, z: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """Square in the z plane, front face towards +z (counter-clockwise seen from +z)."""
    v = np.array([[-half, -half, z], [half, -half, z], [half, half, z], [-half, half, z]], dtype=np.float32)
    return v, np.array([[0, 1, 2], [0, 2, 3]], dtype=np.int32)


def pose(p=(0.0, 0.0, 0.0), axis=(1.0, 0.0, 0.0), angle_deg: float = 0.0) -> np.ndarray:
    a = np.asarray(axis, dtype=np.float64)
    a = a / np.linalg.norm(a)
    h = math.radians(angle_deg) / 2
    return np.array([*p, *(a * math.sin(h)), math.cos(h)], dtype=np.float32)


def pixel_rays(width: int, height: int, fov: float) -> np.ndarray:
    """Camera-frame ray directions through pixel centres, scaled so that z = -1: (H, W, 3)."""
    f = focal_length(fov, height)
    cols, rows = np.meshgrid(np.arange(width) + 0.5, np.arange(height) + 0.5)
    return np.stack([(cols - width / 2) / f, -(rows - height / 2) / f, -np.ones_like(cols)], -1)


def rotation(q) -> np.ndarray:
    """Rotation matrix of an xyzw quaternion."""
    x, y, z, w = q
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )


def numpy(t) -> np.ndarray:
    """A copy: renderer outputs are views of buffers that the next call overwrites."""
    return t.detach().cpu().numpy().copy()


# ----------------------------------------------------------------------------------------------- depth


def test_plane_depth_matches_analytic(device):
    w, h, fov = 24, 16, 50.0
    r = Renderer(2, w, h, fov=fov, near=0.05, far=20.0, device=device)
    plane = r.add_instance(r.add_mesh(*quad(50.0), seg_id=3))
    r.finalize()
    r.set_camera_poses(IDENTITY)
    # env 0: facing plane 2 m away; env 1: plane tilted by 35 degrees about x, 3 m away.
    r.set_instance_transforms(np.stack([pose((0, 0, -2.0)), pose((0, 0, -3.0), (1, 0, 0), 35.0)])[:, None])
    r.render()
    depth = numpy(r.depth)[:, 0]
    assert np.allclose(depth[0], 2.0, rtol=DEPTH_RTOL)
    rays = pixel_rays(w, h, fov)
    n = np.array([0.0, -math.sin(math.radians(35.0)), math.cos(math.radians(35.0))])
    expected = np.dot(np.array([0.0, 0.0, -3.0]), n) / (rays @ n)
    assert np.allclose(depth[1], expected, rtol=DEPTH_RTOL)
    assert (numpy(r.segmentation) == 3).all()
    assert plane.index == 0


def test_sphere_depth_matches_analytic(device):
    w, h, fov, radius, dist = 32, 32, 40.0, 0.5, 3.0
    r = Renderer(1, w, h, fov=fov, near=0.1, far=10.0, device=device)
    s = trimesh.creation.icosphere(subdivisions=4, radius=radius)
    r.add_instance(r.add_mesh(s.vertices, s.faces, seg_id=1))
    r.finalize()
    r.set_camera_poses(look_at([0.3, -0.2, dist], [0.3, -0.2, 0.0]))
    r.set_instance_transforms(pose((0.3, -0.2, 0.0))[None, None])
    r.render()
    depth = numpy(r.depth)[0, 0]
    seg = numpy(r.segmentation)[0, 0]
    # Ray-sphere intersection with the sphere at (0, 0, -dist) in the camera frame.
    rays = pixel_rays(w, h, fov)
    c = np.array([0.0, 0.0, -dist])
    a = (rays * rays).sum(-1)
    b = rays @ c
    disc = b * b - a * (c @ c - radius * radius)
    hit = disc > 0
    t = (b - np.sqrt(np.maximum(disc, 0))) / a
    interior = disc > 0.1 * b * b * (1 - (dist * dist - radius * radius) / (dist * dist))  # away from silhouette
    assert interior.sum() > 100
    assert (seg[interior] == 1).all()
    assert np.allclose(depth[interior], t[interior], rtol=DEPTH_RTOL)
    rendered = seg == 1
    iou = (rendered & hit).sum() / (rendered | hit).sum()
    assert iou > 0.95
    assert np.all(depth[~rendered] == r.far)


# ------------------------------------------------------------------------------- occlusion / ids


@pytest.mark.parametrize("near_first", [True, False])
def test_nearer_triangles_occlude_farther_ones(device, near_first):
    r = Renderer(1, 20, 20, fov=60.0, near=0.05, far=10.0, device=device)
    near_mesh = r.add_mesh(*quad(0.3), color=(1, 0, 0), seg_id=7)
    far_mesh = r.add_mesh(*quad(5.0), color=(0, 0, 1), seg_id=2)
    order = [near_mesh, far_mesh] if near_first else [far_mesh, near_mesh]
    handles = [r.add_instance(m) for m in order]
    r.finalize()
    r.set_camera_poses(IDENTITY)
    z = {near_mesh.index: -1.0, far_mesh.index: -1.5}
    r.set_instance_transforms(np.stack([pose((0, 0, z[hd.mesh.index])) for hd in handles])[None])
    r.render()
    seg = numpy(r.segmentation)[0, 0]
    depth = numpy(r.depth)[0, 0]
    assert seg[10, 10] == 7 and depth[10, 10] == pytest.approx(1.0, rel=1e-5)
    assert seg[0, 0] == 2 and depth[0, 0] == pytest.approx(1.5, rel=1e-5)
    assert set(np.unique(seg)) == {2, 7}
    rgb = numpy(r.rgb)[0]
    assert rgb[0, 10, 10] > 200 and rgb[2, 10, 10] == 0
    assert rgb[2, 0, 0] > 150 and rgb[0, 0, 0] == 0


def test_segmentation_ids_and_background(device):
    r = Renderer(1, 30, 10, fov=40.0, near=0.05, far=10.0, device=device)
    mesh = r.add_mesh(*quad(0.3), seg_id=0)
    left = r.add_instance(mesh, seg_id=11)
    mid = r.add_instance(mesh)
    right = r.add_instance(mesh, seg_id=4)
    r.finalize()
    r.set_camera_poses(IDENTITY)
    r.set_instance_transforms(np.stack([pose((x, 0, -3.0)) for x in (-1.2, 0.0, 1.2)])[None])
    r.render()
    seg = numpy(r.segmentation)[0, 0]
    # focal 13.7 px: the squares span columns 8-10, 14-15 and 19-21 of rows 4-5.
    assert seg[5, 9] == 11 and seg[5, 15] == 0 and seg[4, 20] == 4
    assert seg[0, 0] == -1 and seg[5, 12] == -1 and seg[7, 15] == -1
    assert set(np.unique(seg)) == {-1, 0, 4, 11}
    assert (left.object, mid.object, right.object) == (0, 1, 2)


def test_back_faces_culled_unless_double_sided(device):
    r = Renderer(1, 8, 8, fov=40.0, device=device)
    single = r.add_instance(r.add_mesh(*quad(2.0), seg_id=1))
    double = r.add_instance(r.add_mesh(*quad(2.0), seg_id=2, double_sided=True))
    r.finalize()
    r.set_camera_poses(IDENTITY)
    # Both turned away from the camera (front faces towards -z); the single-sided one is nearer.
    flipped = [pose((0, 0, -1.0), (0, 1, 0), 180.0), pose((0, 0, -2.0), (0, 1, 0), 180.0)]
    r.set_instance_transforms(np.stack(flipped)[None])
    r.render()
    assert (numpy(r.segmentation) == 2).all()
    assert single.index == 0 and double.index == 1
    # Lit from its own side: a back face seen head-on is as bright as a front face.
    assert numpy(r.rgb)[0, :, 4, 4].min() > 200


def test_cluster_culling_changes_nothing_but_work(device):
    """Whole clusters of a closed single-sided mesh are culled (back-facing or off-screen) without changing
    the image: a double-sided copy (never cluster back-face culled) renders identically."""
    s = trimesh.creation.icosphere(subdivisions=4, radius=0.5)
    images = []
    for double in (False, True):
        r = Renderer(2, 24, 24, fov=40.0, near=0.1, far=10.0, device=device)
        r.add_instance(r.add_mesh(s.vertices, s.faces, seg_id=1, double_sided=double))
        r.finalize()
        # env 0: sphere in view; env 1: sphere half out of the image on the right.
        r.set_camera_poses(IDENTITY)
        r.set_instance_transforms(np.stack([pose((0, 0, -3.0)), pose((1.1, 0, -3.0))])[:, None])
        r.render()
        images.append((numpy(r.depth), numpy(r.segmentation), numpy(r.rgb)))
        drawn = r._cluster_draw.numpy()
        if not double:
            culled = 1 - drawn.mean(1)
            assert 0.25 < culled[0] < 0.6  # 58% of the sphere faces away; cones are conservative
            assert culled[1] > culled[0] + 0.1  # and more clusters are culled when half off-screen
        else:
            assert drawn[0].all()
    for a, b in zip(images[0], images[1], strict=True):
        assert np.array_equal(a, b)


def test_shared_edges_through_pixel_centres_leave_no_cracks(device):
    """A grid whose vertices and diagonals pass exactly through pixel centres: every centre on a shared edge
    must be covered by one of the two triangles (canonical edge functions), so the backdrop never shows."""
    w, h, fov = 16, 12, 50.0
    f = focal_length(fov, h)
    cols = np.arange(-1.5, w + 2.0, 2.0)  # pixel-centre coordinates, every other pixel
    rows = np.arange(-1.5, h + 2.0, 2.0)
    nx, ny = len(cols), len(rows)
    cc, rr = np.meshgrid(cols, rows)
    # Rows of the cloth grid must go along +y for counter-clockwise faces: flip the image rows.
    pts = np.stack([(cc - w / 2) / f, -(rr - h / 2) / f, -np.ones_like(cc)], -1)[::-1].reshape(-1, 3)
    r = Renderer(1, w, h, fov=fov, near=0.05, far=10.0, device=device)
    r.add_instance(r.add_mesh(*quad(10.0), seg_id=1))
    sheet = r.add_deformable(cloth_grid_faces(nx, ny), nx * ny, seg_id=2, double_sided=False)
    r.finalize()
    r.set_camera_poses(IDENTITY)
    r.set_instance_transforms(pose((0, 0, -2.0))[None, None])
    r.render(deformable_points={sheet: on_device(device, pts[None].astype(np.float32))})
    assert (numpy(r.segmentation) == 2).all()
    assert np.allclose(numpy(r.depth), 1.0, rtol=1e-5)


def test_raster_split_and_early_depth_test_render_identically(device):
    """Splitting triangles over several row-interleaved threads, or skipping atomics for fragments already
    hidden, only changes who writes which pixel."""
    outputs = []
    for split, early_z in ((1, False), (3, False), (1, True)):
        r = Renderer(2, 20, 16, fov=50.0, near=0.05, far=10.0, device=device, early_depth_test=early_z)
        r.add_instance(r.add_mesh(*quad(1.0), seg_id=1, raster_split=split))
        sheet = r.add_deformable(cloth_grid_faces(4, 4), 16, seg_id=2, raster_split=split)
        r.finalize()
        r.set_camera_poses(look_at([[0, 0, 3.0], [0.5, 0.3, 2.5]], [[0, 0, 0]] * 2))
        r.set_instance_transforms(np.stack([pose((0.2, 0, -0.5), (1, 1, 0), 30.0)] * 2)[:, None])
        pts = np.stack([cloth_points(4, 0.6, 0.3), cloth_points(4, 0.5, 0.2, (0.2, 0.1))])
        r.render(deformable_points={sheet: on_device(device, pts)})
        outputs.append((numpy(r.depth), numpy(r.segmentation), numpy(r.rgb)))
        assert {1, 2} <= set(np.unique(outputs[-1][1]))
    for other in outputs[1:]:
        for a, b in zip(outputs[0], other, strict=True):
            assert np.array_equal(a, b)


def test_near_plane_clipping(device):
    w, h, fov, near = 24, 24, 60.0, 0.5
    renders = []
    for method in ("raster", "raycast"):
        r = Renderer(1, w, h, fov=fov, near=near, far=10.0, device=device, method=method)
        r.add_instance(r.add_mesh(*quad(3.0), seg_id=1))
        r.finalize()
        r.set_camera_poses(IDENTITY)
        # A floor-like plane tilted by 60 degrees: it crosses the near plane in the lower image quarter and
        # extends behind the camera.
        r.set_instance_transforms(pose((0, -0.2, -0.4), (1, 0, 0), -60.0)[None, None])
        r.render()
        renders.append(r)
    depth = numpy(renders[0].depth)[0, 0]
    seg = numpy(renders[0].segmentation)[0, 0]
    rays = pixel_rays(w, h, fov)
    n = np.array([0.0, math.sin(math.radians(60.0)), math.cos(math.radians(60.0))])
    with np.errstate(divide="ignore"):
        expected = np.dot(np.array([0.0, -0.2, -0.4]), n) / (rays @ n)
    visible = (expected > near * 1.02) & (expected < 3.0)
    clipped = (expected > 0) & (expected < near * 0.98)
    assert visible.sum() > 50 and clipped.sum() > 20
    assert (seg[visible] == 1).all()
    assert np.allclose(depth[visible], expected[visible], rtol=DEPTH_RTOL)
    assert (seg[clipped] == -1).all()
    assert np.allclose(depth, numpy(renders[1].depth)[0, 0], rtol=AGREE_RTOL)


# ---------------------------------------------------------------------------------- projection


def test_project_points_matches_rasterised_markers(device):
    w, h, fov = 40, 30, 50.0
    cams = look_at([[0.2, 0.1, 2.0], [1.5, 1.0, 1.0]], [[0.0, 0.0, 0.0], [0.1, -0.1, 0.0]])
    # Points built from chosen continuous pixel coordinates (0.1-0.3 px from their pixel's centre) and depths.
    rng = np.random.default_rng(3)
    target = np.stack(
        [
            rng.integers(0, h, (2, 6)) + 0.5 + rng.uniform(-0.3, 0.3, (2, 6)),
            rng.integers(0, w, (2, 6)) + 0.5 + rng.uniform(-0.3, 0.3, (2, 6)),
            rng.uniform(1.0, 3.0, (2, 6)),
        ],
        -1,
    )
    f = focal_length(fov, h)
    z = target[..., 2]
    cam_pts = np.stack([(target[..., 1] - w / 2) / f * z, -(target[..., 0] - h / 2) / f * z, -z], -1)
    rot = np.stack([rotation(q) for q in cams[:, 3:]])
    points = (np.einsum("eij,ekj->eki", rot, cam_pts) + cams[:, None, :3]).astype(np.float32)
    proj = project_points(points, cams[:, None], fov, w, h)
    assert np.allclose(proj, target, atol=1e-4)

    # Marker k: a square facing the camera, centred on point k, 0.9 px wide at its depth. Sizes differ per
    # env (shared meshes), so each env gets its own one-env renderer.
    half = 0.45 * proj[..., 2] / focal_length(fov, h)
    for e in range(2):
        r = Renderer(1, w, h, fov=fov, near=0.05, far=10.0, device=device)
        for k in range(points.shape[1]):
            r.add_instance(r.add_mesh(*quad(float(half[e, k])), seg_id=k, double_sided=True))
        r.finalize()
        r.set_camera_poses(cams[e])
        xf = np.concatenate([points[e], np.tile(cams[e, 3:], (points.shape[1], 1))], -1)
        r.set_instance_transforms(xf[None])
        r.render()
        seg = numpy(r.segmentation)[0, 0]
        seen = 0
        for k in range(points.shape[1]):
            rows, cols = np.nonzero(seg == k)
            if len(rows) == 0:  # hidden behind a nearer marker
                continue
            seen += 1
            assert len(rows) == 1
            assert (rows[0], cols[0]) == (int(proj[e, k, 0]), int(proj[e, k, 1]))
        assert seen >= points.shape[1] - 1
    # The device projection agrees with the NumPy one.
    r = Renderer(2, w, h, fov=fov, near=0.05, far=10.0, device=device)
    r.add_instance(r.add_mesh(*quad(1.0)))
    r.finalize()
    r.set_camera_poses(cams)
    dev = numpy(r.project_points(on_device(device, points)))
    assert np.allclose(dev, proj, rtol=1e-4, atol=1e-3)


def test_look_at_and_image_orientation(device):
    w, h, fov = 21, 15, 45.0
    cam = look_at([1.0, 2.0, 3.0], [0.0, 0.5, 0.0])
    centre = project_points(np.array([0.0, 0.5, 0.0]), cam, fov, w, h)
    assert centre[0] == pytest.approx(h / 2, abs=1e-4) and centre[1] == pytest.approx(w / 2, abs=1e-4)
    assert centre[2] == pytest.approx(math.sqrt(1 + 1.5**2 + 9), rel=1e-6)
    up = project_points(np.array([0.0, 0.6, 0.0]), cam, fov, w, h)
    assert up[0] < h / 2  # world up is image up: smaller row
    # Identity camera: +x world goes right in the image, +y goes up (row 0 = top).
    r = Renderer(1, w, h, fov=fov, device=device)
    r.add_instance(r.add_mesh(*quad(0.2), seg_id=5))
    r.finalize()
    r.set_camera_poses(IDENTITY)
    r.set_instance_transforms(pose((0.5, 0.4, -2.0))[None, None])
    r.render()
    rows, cols = np.nonzero(numpy(r.segmentation)[0, 0] == 5)
    assert rows.max() < h / 2 and cols.min() > w / 2


# -------------------------------------------------------------------------- deformables, envs


def cloth_points(nx: int, half: float, z: float, offset=(0.0, 0.0)) -> np.ndarray:
    g = np.linspace(-half, half, nx)
    x, y = np.meshgrid(g, g)
    return np.stack([x + offset[0], y + offset[1], np.full_like(x, z)], -1).reshape(-1, 3).astype(np.float32)


@pytest.mark.parametrize("mask_dtype", [torch.int32, torch.bool])
def test_cut_triangles_disappear(device, mask_dtype):
    results = {}
    for method in ("raster", "raycast"):
        r = Renderer(2, 16, 16, fov=40.0, near=0.05, far=10.0, device=device, method=method)
        r.add_instance(r.add_mesh(*quad(5.0), seg_id=1))
        sheet = r.add_deformable(np.array([[0, 1, 2], [0, 2, 3]]), 4, seg_id=9, smooth=True)
        r.finalize()
        r.set_camera_poses(IDENTITY)
        r.set_instance_transforms(pose((0, 0, -3.0))[None, None].repeat(2, 0))
        # Slightly off-centre so that no pixel centre lies exactly on the diagonal (a tie either way).
        pts = on_device(device, np.tile(quad(2.0, -2.0)[0] + [0.013, 0.007, 0.0], (2, 1, 1)).astype(np.float32))
        mask = torch.ones((2, 2), dtype=mask_dtype, device=device)
        mask[1, 0] = 0  # cut the lower-right triangle in env 1 only
        r.render(deformable_points={sheet: pts}, active_masks={sheet: mask})
        results[method] = (numpy(r.segmentation)[:, 0], numpy(r.depth)[:, 0])
    seg, depth = results["raster"]
    assert (seg[0] == 9).all()
    assert seg[1, 12, 13] == 1 and depth[1, 12, 13] == pytest.approx(3.0, rel=1e-5)  # below the diagonal
    assert seg[1, 3, 2] == 9 and depth[1, 3, 2] == pytest.approx(2.0, rel=1e-5)
    assert (seg[1] == 1).sum() > 80 and (seg[1] == 9).sum() > 80
    assert (results["raycast"][0] == seg).mean() >= AGREE_FRACTION


def test_per_env_geometry_and_cameras_are_isolated(device):
    n, w, h, fov = 3, 16, 16, 50.0
    r = Renderer(n, w, h, fov=fov, near=0.05, far=20.0, device=device)
    box = r.add_instance(r.add_mesh(*quad(0.3), seg_id=1, double_sided=True))
    sheet = r.add_deformable(cloth_grid_faces(3, 3), 9, seg_id=2)
    r.finalize()
    # Every env looks at the origin from its own side; only env e has its objects there, the other envs
    # have theirs far outside every camera's view. A shared-index bug would show foreign geometry.
    cams = look_at([[0, 0, 3.0], [3.0, 0, 0.5], [0, 3.0, 0.5]], [[0, 0, 0]] * 3, up=[[0, 1, 0], [0, 1, 0], [0, 0, 1]])
    r.set_camera_poses(cams)
    xf = np.tile(IDENTITY, (n, 1, 1))
    xf[:, 0, :3] = [[0.0, 0.0, 0.0], [50.0, 0, 0], [0, 0, -50.0]]
    xf[:, 0, 3:] = cams[:, 3:]  # face the env's own camera
    pts = np.stack([cloth_points(3, 1.0, -40.0), cloth_points(3, 0.5, 0.0), cloth_points(3, 1.0, 40.0)])
    pts[1] = pts[1][:, [2, 1, 0]]  # env 1: the sheet in the x=0 plane, facing its camera on +x
    r.render(instance_transforms=on_device(device, xf), deformable_points={sheet: on_device(device, pts)})
    seg = numpy(r.segmentation)[:, 0]
    assert set(np.unique(seg[0])) == {-1, 1}
    assert set(np.unique(seg[1])) == {-1, 2}
    assert set(np.unique(seg[2])) == {-1}
    assert box.index == 0
    proj = project_points(np.array([0.3, 0.3, 0.0]), cams, fov, w, h)
    rows, cols = np.nonzero(seg[0] == 1)
    # Covered pixels are those whose centres lie inside the projected square.
    assert rows.min() == math.ceil(proj[0, 0] - 0.5) and cols.max() == math.floor(proj[0, 1] - 0.5)


def test_tube_width_and_orientation(device):
    w, h, fov, radius, dist = 40, 40, 30.0, 0.05, 2.0
    r = Renderer(1, w, h, fov=fov, near=0.05, far=10.0, device=device)
    tube = r.add_tube(6, radius, seg_id=3, sides=12)
    r.finalize()
    r.set_camera_poses(IDENTITY)
    nodes = np.stack([np.linspace(-2, 2, 6), np.zeros(6), np.full(6, -dist)], -1)[None].astype(np.float32)
    r.render(tube_nodes={tube: on_device(device, nodes)})
    seg = numpy(r.segmentation)[0, 0]
    column = seg[:, w // 2] == 3
    expected = 2 * radius * focal_length(fov, h) / dist
    assert abs(column.sum() - expected) <= 1.5
    depth = numpy(r.depth)[0, 0]
    assert depth[h // 2, w // 2] == pytest.approx(dist - radius, rel=0.01)  # single-sided: outer surface seen
    assert (seg[:, 0] == 3).sum() == column.sum()  # straight tube: same width across the image


@pytest.mark.parametrize("caps", [0, 1])
def test_tube_vertices_ring_each_node(device, caps):
    """``raster.generate_tube`` (a thread per ring vertex) on a random polyline in 2 envs, with a repeated node (a
    zero tangent) and a run along -z: ring vertex ``s`` of node ``i`` lies at the tube radius from the node (1e-6 m)
    with its unit normal pointing at it, orthogonal to the node's central-difference tangent, the ring's vertices
    ``2 pi / sides`` apart in angle; with caps the two extra vertices sit on the end nodes, normals along -t / +t.
    Vertices before ``vert_begin`` are not written."""
    from lapwarp.kernels import raster

    rng = np.random.default_rng(3)
    n, N, sides, radius, begin = 2, 23, 7, 0.004, 5
    nodes = rng.normal(scale=0.05, size=(n, N, 3))
    nodes[0, 8:10] = nodes[0, 7]
    nodes[1, 12:, :] = nodes[1, 12] - np.outer(np.arange(N - 12), [0.0, 0.0, 0.01])
    total = begin + N * sides + 2
    pts = wp.zeros((n, total), dtype=wp.vec3, device=device)
    nrm = wp.zeros((n, total), dtype=wp.vec3, device=device)
    wp.launch(raster.generate_tube, dim=(n, N * sides),
              inputs=[wp.array(nodes.astype(np.float32), dtype=wp.vec3, device=device), radius, sides, caps, begin],
              outputs=[pts, nrm], device=device)
    P, R = pts.numpy().astype(np.float64), nrm.numpy().astype(np.float64)
    assert not P[:, :begin].any() and not R[:, :begin].any()
    ring_p = P[:, begin:begin + N * sides].reshape(n, N, sides, 3)
    ring_n = R[:, begin:begin + N * sides].reshape(n, N, sides, 3)
    np.testing.assert_allclose(np.linalg.norm(ring_p - nodes[:, :, None], axis=-1), radius, atol=1e-6)
    np.testing.assert_allclose(np.linalg.norm(ring_n, axis=-1), 1.0, atol=1e-5)
    np.testing.assert_allclose(ring_p, nodes[:, :, None] + radius * ring_n, atol=1e-6)
    tangent = nodes[:, np.minimum(np.arange(N) + 1, N - 1)] - nodes[:, np.maximum(np.arange(N) - 1, 0)]
    moving = np.linalg.norm(tangent, axis=-1) > 0
    t = tangent / np.where(moving, np.linalg.norm(tangent, axis=-1), 1.0)[..., None]
    assert np.abs(np.einsum("ekd,eksd->eks", t, ring_n)[moving]).max() < 1e-5
    cos = np.einsum("eksd,eksd->eks", ring_n, np.roll(ring_n, -1, axis=2))
    np.testing.assert_allclose(cos, math.cos(2 * math.pi / sides), atol=1e-5)
    cap_p, cap_n = P[:, -2:], R[:, -2:]
    if caps:
        np.testing.assert_allclose(cap_p, nodes[:, [0, N - 1]], atol=1e-7)
        np.testing.assert_allclose(cap_n[:, 0], -t[:, 0], atol=1e-6)
        np.testing.assert_allclose(cap_n[:, 1], t[:, N - 1], atol=1e-6)
    else:
        assert not cap_p.any() and not cap_n.any()


def test_object_visibility_and_per_env_colors(device):
    r = Renderer(2, 8, 8, fov=40.0, device=device, outputs=("rgb", "segmentation"))
    plane = r.add_instance(r.add_mesh(*quad(3.0), color=(1, 1, 1), seg_id=1), color=(0.5, 0.5, 0.5))
    r.finalize()
    r.set_camera_poses(IDENTITY)
    r.set_instance_transforms(pose((0, 0, -2.0))[None, None].repeat(2, 0))
    r.object_colors[1, plane.object] = torch.tensor([1.0, 0.0, 0.0])
    r.render()
    rgb = numpy(r.rgb)
    assert np.all(rgb[0, 0] == rgb[0, 1]) and rgb[0, 0, 4, 4] == pytest.approx(128, abs=2)
    assert rgb[1, 0, 4, 4] > 250 and rgb[1, 1, 4, 4] == 0
    r.object_visible[0, plane.object] = 0
    r.render()
    assert (numpy(r.segmentation)[0] == -1).all() and (numpy(r.segmentation)[1] == 1).all()
    with pytest.raises(RuntimeError, match="depth"):
        _ = r.depth


# ------------------------------------------------------------------------------------ shading


def test_lambert_head_light_shading_matches_analytic(device):
    w, h, fov, radius, dist = 32, 32, 40.0, 0.6, 2.5
    albedo, ambient, diffuse = np.array([0.9, 0.6, 0.3]), 0.2, 0.8
    r = Renderer(1, w, h, fov=fov, near=0.1, far=10.0, device=device, ambient=ambient, diffuse=diffuse)
    s = trimesh.creation.icosphere(subdivisions=4, radius=radius)
    r.add_instance(r.add_mesh(s.vertices, s.faces, color=tuple(albedo), seg_id=1, smooth=True))
    r.finalize()
    r.set_camera_poses(IDENTITY)
    r.set_instance_transforms(pose((0, 0, -dist))[None, None])
    r.render()
    rgb = numpy(r.rgb)[0].transpose(1, 2, 0).astype(np.float64)
    rays = pixel_rays(w, h, fov)
    c = np.array([0.0, 0.0, -dist])
    a = (rays * rays).sum(-1)
    b = rays @ c
    disc = b * b - a * (c @ c - radius * radius)
    inside = disc > 0.2 * disc.max()
    t = (b - np.sqrt(np.maximum(disc, 0))) / a
    normal = (rays * t[..., None] - c) / radius
    light = -rays / np.linalg.norm(rays, axis=-1, keepdims=True)
    lam = np.clip((normal * light).sum(-1), 0, 1)
    expected = 255 * albedo * (ambient + diffuse * lam)[..., None]
    err = np.abs(rgb[inside] - expected[inside])
    assert err.mean() < 2.0 and err.max() < 8.0


def golden_scene(device, method: str = "raster") -> Renderer:
    """Two envs with a sphere, an instrument-like capsule, a floor, a cloth with a cut and a tube."""
    r = Renderer(
        2, 32, 24, fov=45.0, near=0.05, far=5.0, device=device, background_color=(0.1, 0.1, 0.2), method=method
    )
    s = trimesh.creation.icosphere(subdivisions=3, radius=0.2)
    r.add_instance(r.add_mesh(s.vertices, s.faces, color=(0.9, 0.15, 0.1), seg_id=1))
    cap = trimesh.creation.capsule(height=0.6, radius=0.05, count=(16, 8))
    vc = (0.5 + 0.5 * (cap.vertices[:, 2:3] > 0)).repeat(3, 1)
    r.add_instance(r.add_mesh(cap.vertices, cap.faces, color=(0.8, 0.8, 0.8), seg_id=2, vertex_colors=vc))
    r.add_instance(r.add_mesh(*quad(1.0), color=(0.2, 0.7, 0.3), seg_id=3))
    cloth = r.add_deformable(cloth_grid_faces(6, 6), 36, color=(0.9, 0.8, 0.4), seg_id=4)
    tube = r.add_tube(10, 0.035, color=(0.2, 0.3, 1.0), seg_id=5)
    r.finalize()
    r.set_camera_poses(look_at([[0, 0.2, 2.0], [0.4, 0.5, 1.6]], [[0, 0, 0], [0, 0, 0]]))
    xf = np.tile(IDENTITY, (2, 3, 1))
    xf[:, 0, :3] = [[0.1, 0.0, 0.1], [-0.1, 0.1, 0.0]]
    xf[:, 1] = [pose((0.35, -0.1, 0.3), (1, 1, 0), 70.0), pose((0.3, 0.0, 0.2), (0, 1, 0), 80.0)]
    xf[:, 2, :3] = [0.0, 0.0, -0.3]
    r.set_instance_transforms(xf)
    pts = np.stack([cloth_points(6, 0.3, 0.0, (-0.4, 0.35)), cloth_points(6, 0.35, 0.05, (-0.35, 0.3))])
    pts[..., 2] += 0.1 * np.sin(5 * pts[..., 0])
    mask = np.ones((2, cloth.num_faces), np.int32)
    mask[1, 10:20] = 0
    tt = np.linspace(0, 1, 10)
    nodes = np.stack([0.6 * tt - 0.3, -0.35 + 0.08 * np.sin(8 * tt), 0.25 + 0 * tt], -1)[None].repeat(2, 0)
    r.render(
        deformable_points={cloth: on_device(device, pts.astype(np.float32))},
        active_masks={cloth: on_device(device, mask)},
        tube_nodes={tube: on_device(device, nodes.astype(np.float32))},
    )
    return r


def test_golden_image(device):
    grid = image_grid(golden_scene(device).rgb, ncols=2)
    golden = read_png(GOLDEN)
    assert golden.shape == grid.shape
    diff = np.abs(grid.astype(np.int32) - golden.astype(np.int32)).max(-1)
    # Tolerance for float differences between backends: a few pixels may flip at silhouettes.
    assert (diff > 12).mean() < 0.01 and diff.mean() < 1.0


def test_rasteriser_agrees_with_ray_caster(device):
    raster = golden_scene(device)
    cast = golden_scene(device, method="raycast")
    d_r, d_c = numpy(raster.depth), numpy(cast.depth)
    assert (np.abs(d_r - d_c) <= AGREE_RTOL * d_c).mean() >= AGREE_FRACTION
    assert (numpy(raster.segmentation) == numpy(cast.segmentation)).mean() >= AGREE_FRACTION
    assert (np.abs(numpy(raster.rgb).astype(int) - numpy(cast.rgb)) <= 2).mean() >= AGREE_FRACTION


# ------------------------------------------------------------------------------ derived outputs


def test_point_cloud_lies_on_the_plane(device):
    w, h = 12, 10
    r = Renderer(2, w, h, fov=55.0, near=0.05, far=10.0, device=device)
    r.add_instance(r.add_mesh(*quad(20.0), seg_id=1))
    r.finalize()
    r.set_camera_poses(look_at([[0, 0, 2.0], [1.0, 0.5, 1.5]], [[0, 0, 0], [0.5, 0.5, 0]]))
    r.set_instance_transforms(np.tile(IDENTITY, (2, 1, 1)))
    r.render()
    pts = numpy(r.point_cloud())
    assert pts.shape == (2, w * h, 3)
    assert np.allclose(pts[..., 2], 0.0, atol=1e-4)
    cam_pts = numpy(r.point_cloud(world=False))
    assert np.allclose(-cam_pts[..., 2], numpy(r.depth).reshape(2, -1), rtol=1e-6)
    # Back-projected pixel centres project back onto themselves.
    proj = project_points(pts, numpy(r.camera_poses)[:, None], 55.0, w, h)
    rows, cols = np.divmod(np.arange(w * h), w)
    assert np.allclose(proj[..., 0], rows + 0.5, atol=1e-3) and np.allclose(proj[..., 1], cols + 0.5, atol=1e-3)


# --------------------------------------------------------------------------------- validation


def test_input_validation(device):
    with pytest.raises(ValueError, match="fov"):
        Renderer(1, 8, 8, fov=0.0, device=device)
    with pytest.raises(ValueError, match="near"):
        Renderer(1, 8, 8, near=1.0, far=0.5, device=device)
    with pytest.raises(ValueError, match="outputs"):
        Renderer(1, 8, 8, outputs=("normals",), device=device)
    r = Renderer(2, 8, 8, device=device)
    with pytest.raises(ValueError, match="face indices"):
        r.add_mesh(*quad(1.0)[:1], faces=[[0, 1, 4]])
    with pytest.raises(ValueError, match="color"):
        r.add_mesh(*quad(1.0), color=(2, 0, 0))
    mesh = r.add_mesh(*quad(1.0))
    with pytest.raises(ValueError, match="seg_id"):
        r.add_instance(mesh, seg_id=-1)
    r.add_instance(mesh)
    sheet = r.add_deformable(np.array([[0, 1, 2]]), 3)
    with pytest.raises(RuntimeError, match="empty"):
        Renderer(1, 8, 8, device=device).finalize()
    r.finalize()
    with pytest.raises(RuntimeError, match="finalised"):
        r.add_mesh(*quad(1.0))
    with pytest.raises(ValueError, match="camera_poses"):
        r.render(camera_poses=torch.zeros((3, 7)))
    with pytest.raises(ValueError, match="instance_transforms"):
        r.render(instance_transforms=torch.zeros((2, 2, 7)))
    with pytest.raises(ValueError, match="deformable_points"):
        r.render(deformable_points={sheet: torch.zeros((2, 4, 3))})
    with pytest.raises(ValueError, match="active_masks"):
        r.render(active_masks={sheet: torch.ones((2, 2), dtype=torch.int32)})
    with pytest.raises(TypeError, match="camera_poses"):
        r.render(camera_poses=np.zeros((2, 7), np.float32))
    with pytest.raises(ValueError, match="not a tube"):
        r.render(tube_nodes={sheet: torch.zeros((2, 3, 3))})


# ------------------------------------------------------------------------------------ imaging


def _png_with_filters(img: np.ndarray, path: Path) -> None:
    """Encodes every row with filter (row % 5): exercises all of read_png's filter decoders."""
    import struct
    import zlib

    h, w, c = img.shape
    x = img.reshape(h, w * c).astype(np.int32)
    rows = []
    for y in range(h):
        up = x[y - 1] if y else np.zeros(w * c, np.int32)
        left = np.concatenate([np.zeros(c, np.int32), x[y, :-c]])
        ul = np.concatenate([np.zeros(c, np.int32), up[:-c]])
        kind = y % 5
        if kind == 0:
            pred = 0
        elif kind == 1:
            pred = left
        elif kind == 2:
            pred = up
        elif kind == 3:
            pred = (left + up) // 2
        else:
            p = left + up - ul
            pa, pb, pc = np.abs(p - left), np.abs(p - up), np.abs(p - ul)
            pred = np.where((pa <= pb) & (pa <= pc), left, np.where(pb <= pc, up, ul))
        rows.append(bytes([kind]) + ((x[y] - pred) & 0xFF).astype(np.uint8).tobytes())

    def chunk(tag, data):
        return struct.pack(">I", len(data)) + tag + data + struct.pack(">I", zlib.crc32(tag + data) & 0xFFFFFFFF)

    head = struct.pack(">IIBBBBB", w, h, 8, 2, 0, 0, 0)
    data = b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", head) + chunk(b"IDAT", zlib.compress(b"".join(rows)))
    path.write_bytes(data + chunk(b"IEND", b""))


def test_png_roundtrip_and_grid(tmp_path):
    rng = np.random.default_rng(0)
    img = rng.integers(0, 256, size=(7, 5, 3), dtype=np.uint8)
    write_png(tmp_path / "a.png", img)
    assert np.array_equal(read_png(tmp_path / "a.png"), img)
    _png_with_filters(img, tmp_path / "f.png")
    assert np.array_equal(read_png(tmp_path / "f.png"), img)
    batch = rng.integers(0, 256, size=(5, 3, 4, 6), dtype=np.uint8)
    grid = save_image_grid(torch.from_numpy(batch), tmp_path / "g.png", ncols=2, pad=1)
    assert grid.shape == (3 * 5 + 1, 2 * 7 + 1, 3)
    assert np.array_equal(grid[1:5, 8:14], batch[1].transpose(1, 2, 0))
    assert np.array_equal(read_png(tmp_path / "g.png"), grid)
    with pytest.raises(ValueError):
        image_grid(batch.astype(np.float32))


if __name__ == "__main__":
    wp.init()
    GOLDEN.parent.mkdir(parents=True, exist_ok=True)
    save_image_grid(golden_scene("cpu").rgb, GOLDEN, ncols=2)
    print(f"wrote {GOLDEN}")


@pytest.mark.parametrize("obs_type", ["RGB", "RGBD", "DEPTH"])
def test_env_frames_written_in_the_shading_pass_match_the_outputs(device, obs_type):
    # Reach's observation frame comes from the shading pass itself (Renderer.set_frame_output): exactly the RGB bytes
    # / 255, then depth / far at most 1 (what a launch of env_kernels.write_image_frame computed after it); a task that
    # draws overlays into the bytes (TissueManipulation) keeps that launch
    import lapwarp

    env = lapwarp.make("Reach", num_envs=2, device=device, observation_type=obs_type, image_shape=(24, 32),
                       sphere_radius=0.02)
    assert env._frame_in_shading
    env.step(torch.zeros(2, env.num_actions, device=env.device))
    frame = env.image_frame.numpy()
    rgb = env.camera.renderer.rgb.cpu().numpy().astype(np.float32) / 255.0
    depth = np.minimum(env.camera.renderer.depth.cpu().numpy() / env.camera.scene.camera.far, 1.0)
    expected = {"RGB": rgb, "RGBD": np.concatenate([rgb, depth], axis=1), "DEPTH": depth}[obs_type]
    assert frame.shape == expected.shape
    np.testing.assert_array_equal(frame, expected)
    assert 0.0 < frame.mean() < 1.0 and frame.std() > 0.0  # a scene, not a blank
    assert not lapwarp.make("TissueManipulation", num_envs=1, device=device, observation_type="RGB")._frame_in_shading


def test_frame_output_shape_is_checked(device):
    r = Renderer(2, 8, 6, fov=40.0, near=0.01, far=2.0, device=device)
    r.add_instance(r.add_mesh(*quad(0.3)))
    r.finalize()
    with pytest.raises(ValueError, match="frame output"):
        r.set_frame_output(wp.zeros((2, 3, 6, 8), dtype=wp.float32, device=device), rgb=True, depth=True)
    with pytest.raises(ValueError, match="frame output"):
        r.set_frame_output(wp.zeros((2, 1, 6, 8), dtype=wp.float32, device=device), rgb=False, depth=False)
    r.set_frame_output(wp.zeros((2, 4, 6, 8), dtype=wp.float32, device=device), rgb=True, depth=True)
    r.set_frame_output(None, rgb=False, depth=False)
