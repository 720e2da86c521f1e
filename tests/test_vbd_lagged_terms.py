"""The per-vertex tet solve's terms with stored rotations (``kernels/vbd.py`` ``tet_vertex_terms_lagged``) against
their definition: each vertex's force ``-(F - R) m / alpha_D - cof(F) m (det F - 1) / alpha_H`` and Gauss-Newton
Hessian block ``|m|^2 / alpha_D I + (cof(F) m)(cof(F) m)^T / alpha_H`` formed from ``F = Ds Dm^-1`` in float64 (NumPy),
for every corner of tets of both orientations, stretched, sheared, inverted and at rest, with and without a volume
term; the kernel multiplies by the stiffnesses of ``world_kernels.tet_stiffness`` (the reciprocal compliances)."""

import numpy as np
import pytest
import warp as wp

from lapwarp.kernels import vbd as vbd_kernels
from lapwarp.kernels.world_kernels import tet_stiffness


@wp.kernel
def eval_lagged_terms(
    indices: wp.array(dtype=wp.vec4i),
    inv_rest: wp.array(dtype=wp.mat33),
    stiffness: wp.array2d(dtype=wp.vec2),
    tet_rotation: wp.array2d(dtype=wp.quat),
    q: wp.array2d(dtype=wp.vec3),
    f_out: wp.array2d(dtype=wp.vec3),
    H_out: wp.array2d(dtype=wp.mat33),
):
    c, corner = wp.tid()
    k = indices[c]
    f, H = vbd_kernels.tet_vertex_terms_lagged(0, c, corner, q[0, k[0]], q[0, k[1]], q[0, k[2]], q[0, k[3]], inv_rest,
                                                stiffness, tet_rotation)
    f_out[c, corner] = f
    H_out[c, corner] = H


def random_rotation(rng) -> np.ndarray:
    q = rng.normal(size=4)
    return q / np.linalg.norm(q)  # (x, y, z, w), Warp's order


def quat_matrix(q: np.ndarray) -> np.ndarray:
    x, y, z, w = q
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                     [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                     [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])


def scene(rng):
    """Eight tets on 32 particles placed 0.1 m from the origin with ~3 mm edges (a surgical mesh's scale, where
    float32 positions carry ~1e-8 m): half of them in the opposite orientation; deformed by a rotation times a
    stretch / shear (one inverted, one at rest)."""
    T = 8
    rest = 0.1 + 0.003 * rng.normal(size=(T, 4, 3))
    rest[::2, [1, 2]] = rest[::2, [2, 1]]  # both orientations
    Dm = np.stack([rest[:, 1] - rest[:, 0], rest[:, 2] - rest[:, 0], rest[:, 3] - rest[:, 0]], axis=2)
    inv_rest = np.linalg.inv(Dm).astype(np.float32)
    x = np.empty_like(rest)
    for t in range(T):
        A = quat_matrix(random_rotation(rng)) @ (np.eye(3) + 0.15 * rng.normal(size=(3, 3)))
        if t == 3:
            A = A @ np.diag([1.0, 1.0, -0.5])  # inverted
        if t == 5:
            A = np.eye(3)  # at rest
        x[t] = 0.1 + (rest[t] - 0.1) @ A.T
    positions = x.reshape(-1, 3).astype(np.float32)
    indices = np.arange(4 * T).reshape(T, 4)
    rotations = np.stack([random_rotation(rng) for _ in range(T)]).astype(np.float32)
    return indices, inv_rest, positions, rotations


@pytest.mark.parametrize("volume", [True, False])
def test_lagged_vertex_terms_match_the_deformation_gradient_form(device, volume):
    rng = np.random.default_rng(7)
    indices, inv_rest, positions, rotations = scene(rng)
    T = len(indices)
    alpha_D = 10.0 ** rng.uniform(-7, -5, size=T)
    alpha_H = 10.0 ** rng.uniform(-7, -5, size=T) if volume else -np.ones(T)
    params = wp.array(np.stack([alpha_D, alpha_H, np.zeros(T)], axis=1).astype(np.float32)[None], dtype=wp.vec3,
                      device=device)
    stiffness = wp.empty((1, T), dtype=wp.vec2, device=device)
    wp.launch(tet_stiffness, dim=(1, T), inputs=[params], outputs=[stiffness], device=device)
    f_out = wp.zeros((T, 4), dtype=wp.vec3, device=device)
    H_out = wp.zeros((T, 4), dtype=wp.mat33, device=device)
    wp.launch(eval_lagged_terms, dim=(T, 4), device=device, inputs=[
        wp.array(indices.astype(np.int32), dtype=wp.vec4i, device=device),
        wp.array(inv_rest, dtype=wp.mat33, device=device), stiffness,
        wp.array(rotations[None], dtype=wp.quat, device=device),
        wp.array(positions[None], dtype=wp.vec3, device=device)], outputs=[f_out, H_out])
    f, H = f_out.numpy().astype(np.float64), H_out.numpy().astype(np.float64)

    x = positions.astype(np.float64)
    for t, corner in np.ndindex(T, 4):
        k = indices[t]
        Dm_inv = inv_rest[t].astype(np.float64)
        F = np.stack([x[k[1]] - x[k[0]], x[k[2]] - x[k[0]], x[k[3]] - x[k[0]]], axis=1) @ Dm_inv
        m = -Dm_inv.sum(axis=0) if corner == 0 else Dm_inv[corner - 1]
        cof = np.linalg.det(F) * np.linalg.inv(F).T
        g = cof @ m
        f_ref = -(F - quat_matrix(rotations[t].astype(np.float64))) @ m / alpha_D[t]
        H_ref = np.eye(3) * (m @ m) / alpha_D[t]
        if volume:
            f_ref -= g * (np.linalg.det(F) - 1.0) / alpha_H[t]
            H_ref += np.outer(g, g) / alpha_H[t]
        # float32 round-off against the force's scale |m| (|F| + 1) (1 / alpha_D + |cof F| / alpha_H): at most 2e-7
        # here (positions 0.1 m from the origin carry ~1e-8 m, ~3e-6 of a 3 mm edge); a wrong sign, corner order or
        # rotation is off by O(1) of it
        scale = np.linalg.norm(m) * (np.linalg.norm(F) + 1.0) * (1.0 / alpha_D[t] + (np.linalg.norm(cof) / alpha_H[t]
                                                                                       if volume else 0.0))
        np.testing.assert_allclose(f[t, corner], f_ref, rtol=0, atol=1e-5 * scale, err_msg=f"tet {t} corner {corner}")
        np.testing.assert_allclose(H[t, corner], H_ref, rtol=2e-4, atol=2e-4 * np.abs(H_ref).max(),
                                   err_msg=f"tet {t} corner {corner}")
