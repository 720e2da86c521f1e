"""The per-vertex tet solve's terms with stored rotations (``kernels/vbd.py`` ``tet_vertex_terms_lagged``) against
their definition: each vertex's force ``-(F - R) m / alpha_D - cof(F) m (det F - 1) / alpha_H`` and Gauss-Newton
Hessian block ``|m|^2 / alpha_D I + (cof(F) m)(cof(F) m)^T / alpha_H`` formed from ``F = Ds Dm^-1`` in float64 (NumPy),
for every corner of tets of both orientations, stretched, sheared, inverted and at rest, with and without a volume
term. The kernel forms them from ``F m``, a triple product and a cross product with the rest-shape factors of
``lapwarp.vbd.lagged_incidence_terms`` instead of ``F``, its determinant and cofactor, and multiplies by the
stiffnesses of ``world_kernels.tet_stiffness``."""

import numpy as np
import pytest
import warp as wp

from lapwarp.kernels import vbd as vbd_kernels
from lapwarp.kernels.world_kernels import tet_stiffness
from lapwarp.vbd import lagged_incidence_terms, vertex_layout


@wp.kernel
def eval_lagged_terms(
    adj_tets: wp.array(dtype=wp.int32),
    adj_particles: wp.array(dtype=wp.vec4i),
    adj_coef0: wp.array(dtype=wp.vec4),
    adj_coef1: wp.array(dtype=wp.vec4),
    stiffness: wp.array2d(dtype=wp.vec2),
    tet_rotation: wp.array2d(dtype=wp.quat),
    q: wp.array2d(dtype=wp.vec3),
    f_out: wp.array(dtype=wp.vec3),
    H_out: wp.array(dtype=wp.mat33),
):
    e = wp.tid()
    k = adj_particles[e]
    f, H = vbd_kernels.tet_vertex_terms_lagged(0, adj_tets[e], q[0, k[0]], q[0, k[1]], q[0, k[2]], q[0, k[3]],
                                                adj_coef0[e], adj_coef1[e], stiffness, tet_rotation)
    f_out[e] = f
    H_out[e] = H


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
    lay = vertex_layout(indices, lanes=32)
    particles, coef0, coef1 = lagged_incidence_terms(indices, inv_rest, lay.adj_tets, lay.adj_corners)
    assert len(particles) == 4 * T
    alpha_D = 10.0 ** rng.uniform(-7, -5, size=T)
    alpha_H = 10.0 ** rng.uniform(-7, -5, size=T) if volume else -np.ones(T)
    params = wp.array(np.stack([alpha_D, alpha_H, np.zeros(T)], axis=1).astype(np.float32)[None], dtype=wp.vec3,
                      device=device)
    stiffness = wp.empty((1, T), dtype=wp.vec2, device=device)
    wp.launch(tet_stiffness, dim=(1, T), inputs=[params], outputs=[stiffness], device=device)
    E = len(particles)
    f_out = wp.zeros(E, dtype=wp.vec3, device=device)
    H_out = wp.zeros(E, dtype=wp.mat33, device=device)
    wp.launch(eval_lagged_terms, dim=E, device=device, inputs=[
        wp.array(lay.adj_tets, dtype=wp.int32, device=device), wp.array(particles, dtype=wp.vec4i, device=device),
        wp.array(coef0, dtype=wp.vec4, device=device), wp.array(coef1, dtype=wp.vec4, device=device),
        stiffness, wp.array(rotations[None], dtype=wp.quat, device=device),
        wp.array(positions[None], dtype=wp.vec3, device=device)], outputs=[f_out, H_out])
    f, H = f_out.numpy().astype(np.float64), H_out.numpy().astype(np.float64)

    x = positions.astype(np.float64)
    for e, (t, corner) in enumerate(zip(lay.adj_tets, lay.adj_corners, strict=True)):
        k = indices[t]
        assert particles[e, 0] == k[corner]
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
        # float32 round-off against the force's scale |m| (|F| + 1) (1 / alpha_D + |cof F| / alpha_H): at most 9e-7
        # here (positions 0.1 m from the origin carry ~1e-8 m, ~3e-6 of a 3 mm edge); a wrong sign, corner order or
        # rotation is off by O(1) of it
        scale = np.linalg.norm(m) * (np.linalg.norm(F) + 1.0) * (1.0 / alpha_D[t] + (np.linalg.norm(cof) / alpha_H[t]
                                                                                       if volume else 0.0))
        np.testing.assert_allclose(f[e], f_ref, rtol=0, atol=1e-5 * scale, err_msg=f"tet {t} corner {corner}")
        np.testing.assert_allclose(H[e], H_ref, rtol=2e-4, atol=2e-4 * np.abs(H_ref).max(),
                                   err_msg=f"tet {t} corner {corner}")


def test_incidence_terms_sign_the_volume_by_the_corners_order():
    """``det Ds = (x_p - x_a) . ((x_b - x_a) x (x_c - x_a))`` times the sign in ``s / det Dm^-1``, for every corner."""
    rng = np.random.default_rng(3)
    indices, inv_rest, positions, _ = scene(rng)
    lay = vertex_layout(indices, lanes=32)
    particles, coef0, _ = lagged_incidence_terms(indices, inv_rest, lay.adj_tets, lay.adj_corners)
    x = positions.astype(np.float64)
    for e, t in enumerate(lay.adj_tets):
        k = indices[t]
        det_ds = np.linalg.det(np.stack([x[k[1]] - x[k[0]], x[k[2]] - x[k[0]], x[k[3]] - x[k[0]]], axis=1))
        p, a, b, c = (x[i] for i in particles[e])
        sign = coef0[e, 3] / np.linalg.det(inv_rest[t].astype(np.float64))
        assert sign == pytest.approx(np.sign(sign), rel=1e-5)
        assert np.sign(sign) * np.dot(p - a, np.cross(b - a, c - a)) == pytest.approx(det_ds, rel=1e-9)
