"""Procedural meshes: sizes of the sofa_env budgets, valid (positively oriented, closed-surface) tet meshes."""

from __future__ import annotations

import numpy as np

from lapwarp.assets import box_tets, cloth_grid, hollow_cylinder_tets, rod_circle, rod_polyline, tet_surface, voxel_tets


def _check_tets(v, t):
    d = np.linalg.det(np.stack([v[t[:, i]] - v[t[:, 0]] for i in (1, 2, 3)], axis=2))
    assert np.all(np.abs(d) > 0)
    surf = tet_surface(t, v)
    # a closed 2-manifold boundary: every boundary edge is shared by exactly two boundary faces
    e = np.sort(np.concatenate([surf[:, [0, 1]], surf[:, [1, 2]], surf[:, [2, 0]]]), axis=1)
    _, cnt = np.unique(e, axis=0, return_counts=True)
    assert np.all(cnt == 2)
    # outward winding: the divergence theorem gives +volume
    a, b, c = v[surf[:, 0]], v[surf[:, 1]], v[surf[:, 2]]
    vol_surf = np.einsum("ij,ij->i", a, np.cross(b, c)).sum() / 6.0
    assert np.isclose(vol_surf, np.abs(d).sum() / 6.0, rtol=1e-9)
    return np.abs(d).sum() / 6.0


def test_box_and_cylinder_budgets():
    v, t = box_tets((0.1, 0.02, 0.02), (10, 2, 2))
    assert np.isclose(_check_tets(v, t), 0.1 * 0.02 * 0.02)
    # ThreadInHole's hole: 2 x 10 x 10 nodes -> 200 nodes, 90 hexahedra, 540 tets (sofa_env-facts 5.10)
    v, t = hollow_cylinder_tets(0.005, 0.025, 0.03, 2, 10, 10)
    assert (len(v), len(t)) == (200, 540)
    _check_tets(v, t)
    # LigatingLoop's cavity: 2 x 15 x 25 -> 750 nodes, 2,160 tets (sofa_env-facts 5.12)
    v, t = hollow_cylinder_tets(0.008, 0.010, 0.05, 2, 15, 25)
    assert (len(v), len(t)) == (750, 2160)


def test_voxel_organ_from_surface():
    import trimesh

    sphere = trimesh.creation.icosphere(subdivisions=3, radius=0.03)
    v, t = voxel_tets(sphere, pitch=0.008)
    vol = _check_tets(v, t)
    # voxelisation of a sphere: volume within 35 % of 4/3 pi r^3 at pitch r / 3.75
    assert abs(vol / (4 / 3 * np.pi * 0.03**3) - 1.0) < 0.35
    assert 50 < len(v) < 600  # the liver / gallbladder node budgets (98 / 367)


def test_cloth_and_rods():
    v, t = cloth_grid(40, 40, 0.075, 0.075)
    assert (len(v), len(t)) == (1600, 3042)  # PrecisionCutting's RegularGrid
    n = np.cross(v[t[:, 1]] - v[t[:, 0]], v[t[:, 2]] - v[t[:, 0]])
    assert np.all(n[:, 2] > 0)  # consistently wound, normal +z
    loop = rod_circle(0.014, 30)
    assert np.allclose(np.linalg.norm(loop, axis=1), 0.014)
    line = rod_polyline([[0, 0, 0], [0.03, 0, 0], [0.03, 0.02, 0]], 11)
    assert np.allclose(np.linalg.norm(np.diff(line, axis=0), axis=1), 0.005)
