"""NumPy references for the tests: the generalised winding number of a closed triangle surface (the task kernels'
inside tests are checked against it)."""

from __future__ import annotations

import numpy as np


def winding_numbers_of_triangles(triangles: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Generalised winding number at ``points`` ``(P, 3)`` of the closed surface of ``triangles`` ``(F, 3, 3)``
    (Van Oosterom-Strackee solid angles): +-1 inside (the sign is the faces' orientation), 0 outside."""
    r = triangles[None] - points[:, None, None, :]  # (P, F, 3, 3)
    a, b, c = r[..., 0, :], r[..., 1, :], r[..., 2, :]
    la, lb, lc = (np.linalg.norm(x, axis=-1) for x in (a, b, c))
    num = np.einsum("pfi,pfi->pf", a, np.cross(b, c))
    den = (la * lb * lc + np.einsum("pfi,pfi->pf", a, b) * lc + np.einsum("pfi,pfi->pf", b, c) * la
           + np.einsum("pfi,pfi->pf", c, a) * lb)
    return np.arctan2(num, den).sum(axis=1) / (2.0 * np.pi)


def winding_numbers(vertices: np.ndarray, faces: np.ndarray, points: np.ndarray) -> np.ndarray:
    """``winding_numbers_of_triangles`` of an indexed mesh."""
    return winding_numbers_of_triangles(vertices[faces], points)
