"""Procedural abdominal cavity for SearchForPointEnv: an abdominal wall dome, a posterior floor and organ-like shapes.

sofa_env's SearchForPointEnv shows the scanned OpenHELP phantom (173k triangles), which is not ours to copy. This
module builds a stand-in from smoothly deformed icospheres and swept tubes, in metres, z up, +y cranial, laid out
around sofa_env's two trocars (camera RCM (10, -100.8, 281.82) mm, cauter RCM (117.2, 2.29, 233.62) mm) so that
the RCMs lie on the abdominal wall and the organs sit 100-200 mm below the camera, where its 120 mm target distance
lands. Every part is a closed, consistently wound triangle mesh (organs outward, the wall inward: it is seen from
inside and the rasteriser culls back faces). About 37k triangles in all. Deterministic: no RNG state is shared.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np
import trimesh

#: Centre and semi-axes (m) of the ellipsoid whose upper half is the abdominal wall; both trocars lie on it to ~1%.
DOME_CENTER = (0.0, 0.0, 0.07)
DOME_SEMI_AXES = (0.155, 0.19, 0.25)


@dataclass(frozen=True)
class AnatomyPart:
    """One rigid mesh of the scene (env frame, metres)."""

    name: str
    vertices: np.ndarray  # (V, 3) float64
    faces: np.ndarray  # (F, 3) int64, counter-clockwise seen from the side the camera looks at
    color: tuple[float, float, float]
    is_organ: bool  # organs carry points of interest and collide with the cauter; wall and floor do not


def _rotation(euler_deg) -> np.ndarray:
    """Intrinsic XYZ rotation matrix (degrees), the convention used across lapwarp."""
    ax, ay, az = np.radians(euler_deg)
    cx, sx, cy, sy, cz, sz = np.cos(ax), np.sin(ax), np.cos(ay), np.sin(ay), np.cos(az), np.sin(az)
    rx = np.array([[1, 0, 0], [0, cx, -sx], [0, sx, cx]])
    ry = np.array([[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]])
    rz = np.array([[cz, -sz, 0], [sz, cz, 0], [0, 0, 1]])
    return rx @ ry @ rz


def blob(center, semi_axes, euler_deg=(0.0, 0.0, 0.0), bumpiness=0.06, seed=0, subdivisions=4):
    """A smooth organ-like blob: an icosphere with low-frequency radial bumps, scaled, rotated and placed.

    The bumps are a sum of three sinusoids of the direction (wavelength about a radian), so the surface stays
    smooth and star-shaped (closed, outward winding preserved) for ``bumpiness`` below ~0.3.

    Returns:
        ``(vertices (V, 3), faces (F, 3))``.
    """
    rng = np.random.default_rng(seed)
    sphere = trimesh.creation.icosphere(subdivisions=subdivisions, radius=1.0)
    d = np.asarray(sphere.vertices, dtype=np.float64)
    radius = np.ones(len(d))
    for _ in range(3):
        k = rng.normal(size=3)
        k *= rng.uniform(1.5, 3.0) / np.linalg.norm(k)
        radius += bumpiness * np.sin(d @ k + rng.uniform(0, 2 * np.pi))
    v = d * radius[:, None] * np.asarray(semi_axes)
    v = v @ _rotation(euler_deg).T + np.asarray(center)
    return v, np.asarray(sphere.faces, dtype=np.int64)


def tube(curve: np.ndarray, radius: float, sections: int = 12):
    """A closed tube (capped ends) of ``radius`` swept along the polyline ``curve`` (n, 3), outward winding.

    Frames are parallel-transported so the tube does not twist.
    """
    curve = np.asarray(curve, dtype=np.float64)
    n = len(curve)
    tangents = np.gradient(curve, axis=0)
    tangents /= np.linalg.norm(tangents, axis=1, keepdims=True)
    normal = np.cross(tangents[0], [0.0, 0.0, 1.0])
    if np.linalg.norm(normal) < 1e-6:
        normal = np.cross(tangents[0], [1.0, 0.0, 0.0])
    normal /= np.linalg.norm(normal)
    rings = []
    angles = np.linspace(0.0, 2 * np.pi, sections, endpoint=False)
    for i in range(n):
        t = tangents[i]
        normal = normal - t * (normal @ t)
        normal /= np.linalg.norm(normal)
        binormal = np.cross(t, normal)
        rings.append(curve[i] + radius * (np.cos(angles)[:, None] * normal + np.sin(angles)[:, None] * binormal))
    v = np.concatenate(rings + [curve[:1], curve[-1:]])
    faces = []
    for i in range(n - 1):
        for j in range(sections):
            a, b = i * sections + j, i * sections + (j + 1) % sections
            c, d = a + sections, b + sections
            faces += [(a, b, d), (a, d, c)]
    start, end = n * sections, n * sections + 1
    for j in range(sections):
        faces.append((start, (j + 1) % sections, j))
        faces.append((end, (n - 1) * sections + j, (n - 1) * sections + (j + 1) % sections))
    f = np.asarray(faces, dtype=np.int64)
    # the winding above is outward when (normal, binormal, tangent) is right-handed; check and flip if not
    mesh = trimesh.Trimesh(v, f, process=False)
    if mesh.volume < 0:
        f = f[:, ::-1]
    return v, f


def _wall_and_floor():
    """Upper half of the dome ellipsoid (wound to face inwards) closed by a flat floor at its equator."""
    c, s = np.asarray(DOME_CENTER), np.asarray(DOME_SEMI_AXES)
    n_theta, n_phi = 40, 96  # polar x azimuth samples of the upper half
    theta = np.linspace(0.0, 0.5 * np.pi, n_theta)[1:]  # from the pole (excluded, added below) to the equator
    phi = np.linspace(0.0, 2 * np.pi, n_phi, endpoint=False)
    t, p = np.meshgrid(theta, phi, indexing="ij")
    dirs = np.stack([np.sin(t) * np.cos(p), np.sin(t) * np.sin(p), np.cos(t)], axis=-1).reshape(-1, 3)
    v = np.concatenate([[[0.0, 0.0, 1.0]], dirs]) * s + c
    faces = []
    for j in range(n_phi):  # pole fan
        faces.append((0, 1 + j, 1 + (j + 1) % n_phi))
    for i in range(len(theta) - 1):
        for j in range(n_phi):
            a, b = 1 + i * n_phi + j, 1 + i * n_phi + (j + 1) % n_phi
            faces += [(a, a + n_phi, b + n_phi), (a, b + n_phi, b)]
    wall_f = np.asarray(faces, dtype=np.int64)
    if trimesh.Trimesh(v, wall_f, process=False).face_normals[:, 2].mean() > 0:
        wall_f = wall_f[:, ::-1]  # normals must point into the cavity (down, on average)

    # floor: polar grid of the equator ellipse, slightly bowl-shaped so it reads as the posterior wall
    rings = 12
    r = np.linspace(0.0, 1.0, rings + 1)[1:]
    rr, pp = np.meshgrid(r, phi, indexing="ij")
    x, y = rr * np.cos(pp) * s[0], rr * np.sin(pp) * s[1]
    z = c[2] - 0.02 * (1.0 - rr**2)
    floor_v = np.concatenate([[[c[0], c[1], c[2] - 0.02]], np.stack([x, y, z], -1).reshape(-1, 3)])
    faces = [(0, 1 + j, 1 + (j + 1) % n_phi) for j in range(n_phi)]
    for i in range(rings - 1):
        for j in range(n_phi):
            a, b = 1 + i * n_phi + j, 1 + i * n_phi + (j + 1) % n_phi
            faces += [(a, a + n_phi, b + n_phi), (a, b + n_phi, b)]
    floor_f = np.asarray(faces, dtype=np.int64)
    if trimesh.Trimesh(floor_v, floor_f, process=False).face_normals[:, 2].mean() < 0:
        floor_f = floor_f[:, ::-1]  # the floor faces up, into the cavity
    return (v, wall_f), (floor_v, floor_f)


def _small_bowel_curve() -> np.ndarray:
    """A meandering loop pattern filling the lower abdomen (boustrophedon rows with a vertical wave)."""
    pts = []
    rows = 5
    for i in range(rows):
        y = -0.095 + i * 0.024
        xs = np.linspace(-0.075, 0.075, 40)
        if i % 2:
            xs = xs[::-1]
        for k, x in enumerate(xs):
            z = 0.105 + 0.008 * np.sin(7.0 * x / 0.075 + i) + 0.004 * np.cos(3.0 * k / 40 * np.pi)
            pts.append((x, y + 0.006 * np.sin(5.0 * x / 0.075 + 2 * i), z))
        if i < rows - 1:  # a U-turn to the next row
            end = np.asarray(pts[-1])
            sign = 1.0 if i % 2 == 0 else -1.0
            for a in np.linspace(-0.5 * np.pi, 0.5 * np.pi, 8)[1:-1]:
                pts.append((end[0] + sign * 0.012 * np.cos(a), end[1] + 0.012 * (np.sin(a) + 1.0), end[2]))
    return np.asarray(pts)


def _colon_curve() -> np.ndarray:
    """Ascending, transverse and descending colon framing the small bowel (an inverted U)."""
    s = np.linspace(0.0, 1.0, 90)
    x = np.where(s < 1 / 3, 0.105, np.where(s < 2 / 3, 0.105 - (s - 1 / 3) * 3 * 0.21, -0.105))
    y = np.where(s < 1 / 3, -0.11 + s * 3 * 0.13, np.where(s < 2 / 3, 0.02, 0.02 - (s - 2 / 3) * 3 * 0.13))
    curve = np.stack([x, y, 0.1 + 0.005 * np.sin(12 * s)], -1)
    # round the two corners with a moving average
    kernel = np.ones(9) / 9
    padded = np.pad(curve, ((4, 4), (0, 0)), mode="edge")
    return np.stack([np.convolve(padded[:, k], kernel, mode="valid") for k in range(3)], -1)


@functools.lru_cache(maxsize=2)
def abdomen_parts() -> tuple[AnatomyPart, ...]:
    """The anatomy of the scene: wall, floor and eight organ-like parts with distinct colours (cached)."""
    (wall_v, wall_f), (floor_v, floor_f) = _wall_and_floor()
    parts = [
        AnatomyPart("abdominal_wall", wall_v, wall_f, (0.78, 0.52, 0.47), False),
        AnatomyPart("posterior_wall", floor_v, floor_f, (0.55, 0.2, 0.17), False),
    ]
    organs = [
        ("liver", blob((0.035, 0.105, 0.125), (0.1, 0.06, 0.045), (8, -6, 12), 0.07, 1), (0.45, 0.11, 0.09)),
        ("gallbladder", blob((0.055, 0.045, 0.138), (0.014, 0.026, 0.012), (0, 0, 20), 0.05, 2, 3),
         (0.45, 0.44, 0.2)),  # olive: a saturated green would read as the POI marker
        ("stomach", blob((-0.07, 0.085, 0.118), (0.05, 0.04, 0.032), (0, 10, -25), 0.08, 3), (0.88, 0.5, 0.55)),
        ("spleen", blob((-0.115, 0.04, 0.11), (0.022, 0.042, 0.02), (0, -20, 15), 0.06, 4, 3),
         (0.42, 0.13, 0.36)),
        ("bladder", blob((0.0, -0.145, 0.098), (0.035, 0.028, 0.03), (0, 0, 0), 0.05, 5, 3), (0.9, 0.84, 0.45)),
        ("small_bowel", tube(_small_bowel_curve(), 0.012, 12), (0.96, 0.72, 0.55)),
        ("colon", tube(_colon_curve(), 0.016, 14), (0.72, 0.6, 0.4)),
    ]
    for name, (v, f), color in organs:
        parts.append(AnatomyPart(name, v, f, color, True))
    return tuple(parts)


def organ_mesh() -> tuple[np.ndarray, np.ndarray]:
    """All organ parts merged into one mesh ``(vertices, faces)``: the cauter's collision target and the
    occluder for point-of-interest visibility."""
    organs = [p for p in abdomen_parts() if p.is_organ]
    offsets = np.cumsum([0] + [len(p.vertices) for p in organs])
    v = np.concatenate([p.vertices for p in organs])
    f = np.concatenate([p.faces + o for p, o in zip(organs, offsets[:-1], strict=True)])
    return v, f


def inside_dome(points: np.ndarray, margin: float = 0.0) -> np.ndarray:
    """True for points strictly inside the cavity (below the wall, above the floor's rim), ``margin`` m inside."""
    c, s = np.asarray(DOME_CENTER), np.asarray(DOME_SEMI_AXES)
    q = (np.asarray(points) - c) / (s - margin)
    return (np.sum(q * q, axis=-1) < 1.0) & (np.asarray(points)[..., 2] > c[2] + margin)
