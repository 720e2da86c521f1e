"""Physics core checks against closed forms: free fall, pendulum period, catenary sag, rest stays at rest,
batch invariance, per-env parameters, instability flags and masked resets."""

from __future__ import annotations

import numpy as np
import pytest
import warp as wp

from lapwarp.assets import box_tets, cloth_grid
from lapwarp.builder import SceneBuilder

G = 9.81


def test_free_fall_matches_closed_form(device):
    # Symplectic Euler with substep h gives z_n = z0 - g h^2 n (n + 1) / 2 exactly (up to float32 rounding);
    # against the continuous z0 - g t^2 / 2 the error is g t h / 2 = 9.81 * 1 * 1e-3 / 2 = 4.9 mm.
    b = SceneBuilder()
    b.add_particles([[0.0, 0.0, 10.0], [1.0, 0.0, 10.0]], mass=0.1)
    world = b.finalize(3, device, substeps=10)
    for _ in range(100):
        world.step(0.01)
    z = world.positions()[..., 2]
    n, h = 1000, 1e-3
    assert np.allclose(z, 10.0 - G * h * h * n * (n + 1) / 2, atol=1e-4)
    assert np.all(np.abs(z - (10.0 - 0.5 * G * 1.0)) <= 0.5 * G * 1.0 * h + 1e-4)
    v = world.state.particle_qd.numpy()[..., 2]
    assert np.allclose(v, -G * 1.0, rtol=1e-4)


def _crossings(t: np.ndarray, x: np.ndarray) -> np.ndarray:
    """Times where x changes sign from - to +, linearly interpolated."""
    i = np.nonzero((x[:-1] < 0.0) & (x[1:] >= 0.0))[0]
    return t[i] - x[i] * (t[i + 1] - t[i]) / (x[i + 1] - x[i])


def test_pendulum_period(device):
    # Small-amplitude pendulum: T = 2 pi sqrt(L / g) (1 + theta0^2 / 16) = 1.4192 s for L = 0.5 m,
    # theta0 = 5 deg (the amplitude term is 0.05 %). XPBD with h = 0.5 ms has O(h) phase error (< 0.1 %);
    # tolerance 0.5 %, measured from rising zero crossings at 10 ms sampling with linear interpolation.
    L, th = 0.5, np.radians(5.0)
    b = SceneBuilder()
    b.add_particles([[0.0, 0.0, 0.0], [L * np.sin(th), 0.0, -L * np.cos(th)]], mass=1.0, fixed=[0])
    b.add_distance(0, 1)
    world = b.finalize(1, device, substeps=20)
    ts, xs = [], []
    for k in range(350):
        world.step(0.01)
        ts.append((k + 1) * 0.01)
        xs.append(world.state.particle_q.numpy()[0, 1, 0])
    c = _crossings(np.array(ts), np.array(xs))
    assert len(c) >= 2
    period = float(np.mean(np.diff(c)))
    expected = 2 * np.pi * np.sqrt(L / G) * (1 + th**2 / 16)
    assert abs(period - expected) / expected < 5e-3, (period, expected)


def test_catenary_sag(device):
    # Inextensible chain of length S = 1 m between supports D = 0.8 m apart: catenary a solves
    # S = 2 a sinh(D / 2a) and the sag is a (cosh(D / 2a) - 1) = 0.2722 m. 40 point masses approximate
    # the uniform cable to O(1/N^2) ~ 0.1 %; XPBD stretch at h = 0.5 ms is < 0.1 %. Tolerance 1.5 %.
    S, D, n = 1.0, 0.8, 41
    xs = np.linspace(-D / 2, D / 2, n)
    pts = np.stack([xs, np.zeros(n), np.zeros(n)], axis=1)
    # start from a shallow V with the right length so constraints start satisfied
    seg = S / (n - 1)
    half = (n - 1) // 2
    dz = np.sqrt(seg**2 - (D / (n - 1)) ** 2)
    pts[:, 2] = -dz * (half - np.abs(np.arange(n) - half))
    b = SceneBuilder()
    b.add_particles(pts, mass=0.01, fixed=[0, n - 1], damping=2.0)
    for i in range(n - 1):
        b.add_distance(i, i + 1)
    world = b.finalize(1, device, substeps=20)
    for _ in range(500):
        world.step(0.01)
    q = world.positions()[0]
    from scipy.optimize import brentq

    a = brentq(lambda a: 2 * a * np.sinh(D / (2 * a)) - S, 0.05, 10.0)
    sag = a * (np.cosh(D / (2 * a)) - 1)
    measured = -q[:, 2].min()
    assert abs(measured - sag) / sag < 0.015, (measured, sag)
    assert np.abs(world.state.particle_qd.numpy()).max() < 1e-2  # settled


def _block(b: SceneBuilder, E=1e4, nu=0.3, cells=2):
    v, t = box_tets((0.02, 0.02, 0.02), (cells,) * 3)
    return b.add_tet_mesh(v, t, density=1000.0, youngs_modulus=E, poisson_ratio=nu, fixed=np.nonzero(v[:, 2] < 1e-9)[0])


def test_rest_stays_at_rest(device):
    # With no gravity every constraint is satisfied at the start (C = 0), so nothing may move: a tet block
    # (stiff: alpha / h^2 << w |grad C|^2), a cloth with hinges and a curved rod loop. Bound: 5e-6 m, i.e.
    # 2.5e-4 of the 20 mm loop radius (float32 rounding of rest data and coordinates up to 0.3 m, ~2e-8 m,
    # re-projected every substep for 1,000 substeps; measured 1.8e-6 m on the loop, 0 elsewhere).
    from lapwarp.assets import rod_circle

    b = SceneBuilder(gravity=(0.0, 0.0, 0.0))
    _block(b, E=1e7)
    v, t = cloth_grid(8, 8, 0.05, 0.05, origin=(0.1, 0.0, 0.0))
    b.add_cloth(v, t, stretch_stiffness=1e3, bend_stiffness=1e-5)
    b.add_rod(rod_circle(0.02, 16, center=(0.3, 0.0, 0.0)), radius=0.002, youngs_modulus=1e7, closed=True)
    world = b.finalize(2, device, substeps=10)
    x0 = world.positions()
    for _ in range(100):
        world.step(0.01)
    assert np.abs(world.positions() - x0).max() < 5e-6


def test_batch_invariance_and_per_env_params(device):
    # N identical envs must reproduce the single-env result bit for bit (same kernels, same order); a per-env
    # Young's modulus changes only its own env.
    def run(num_envs, E):
        b = SceneBuilder()
        obj = _block(b, E=E)
        world = b.finalize(num_envs, device, substeps=5)
        for _ in range(20):
            world.step(0.01)
        return world.positions(obj)

    one = run(1, 2e3)
    many = run(3, 2e3)
    assert np.array_equal(many, np.repeat(one, 3, axis=0))
    mixed = run(3, [2e3, 8e3, 2e3])
    assert np.array_equal(mixed[0], one[0]) and np.array_equal(mixed[2], one[0])
    assert np.abs(mixed[1] - one[0]).max() > 1e-5  # stiffer env sags visibly less


def test_masked_reset_and_instability(device):
    # Env 1 gets a NaN and env 2 a runaway velocity: only they are flagged and restored; env 0 keeps moving.
    b = SceneBuilder()
    obj = _block(b, E=5e3)
    world = b.finalize(3, device, substeps=5, max_speed=10.0)
    x0 = world.positions(obj)
    for _ in range(5):
        world.step(0.01)
    q = world.state.particle_q.numpy()
    q[1, 3] = np.nan
    world.state.particle_q.assign(q)
    qd = world.state.particle_qd.numpy()
    qd[2, :] = (0.0, 0.0, 100.0)  # a rigid kick the constraints do not absorb
    world.state.particle_qd.assign(qd)
    world.step(0.01)
    assert world.unstable.numpy().tolist() == [0, 1, 1]
    x = world.positions(obj)
    assert np.array_equal(x[1], x0[1]) and np.array_equal(x[2], x0[2])  # auto-reset to the initial state
    assert np.abs(x[0] - x0[0]).max() > 1e-6
    mask = wp.array([0, 1, 0], dtype=wp.int32, device=device)
    world.reset(mask)
    assert world.unstable.numpy().tolist() == [0, 0, 1]
    world.reset(wp.array([1, 0, 0], dtype=wp.int32, device=device))
    assert np.array_equal(world.positions(obj)[0], x0[0])


@pytest.mark.parametrize("case", ["stiff_x100", "stretched_x3"])
def test_no_nan_under_abuse(device, case):
    # Stiffness x100 (cloth 1e5 N/m, tets 1e8 Pa, far in the stiff regime) or a start stretched 3x must
    # stay finite and within the speed bound; XPBD projections are bounded by construction.
    k = 100.0 if case == "stiff_x100" else 1.0
    b = SceneBuilder()
    _block(b, E=1e6 * k, nu=0.45)
    v, t = cloth_grid(10, 10, 0.05, 0.05, origin=(0.1, 0.0, 0.0))
    b.add_cloth(v, t, stretch_stiffness=1e3 * k, bend_stiffness=1e-5 * k, fixed=[0, 9], tethers=False)
    world = b.finalize(2, device, substeps=10, auto_reset_unstable=False)
    if case == "stretched_x3":
        q = world.state.particle_q.numpy()
        c = q.mean(axis=1, keepdims=True)
        world.state.particle_q.assign(c + 3.0 * (q - c))
    for _ in range(30):
        world.step(0.01)
    assert np.all(np.isfinite(world.positions()))
    assert world.unstable.numpy().sum() == 0


def test_block_dim_spreads_small_grids_over_the_gpu():
    """Launch block sizes (launching.block_dim_for): Warp's 256 on grids with >= 4 blocks per SM, smaller blocks below
    (down to 32) so a per-env kernel at 4,096 envs reaches ~128 of an H100's 132 SMs instead of 16; the cap of
    register-heavy kernels applies to any grid; the CPU (no SMs) gets the cap."""
    from lapwarp.launching import block_dim_for

    assert block_dim_for(4096, 132) == 32  # 128 blocks
    assert block_dim_for((4096, 5), 132) == 32  # 640 blocks
    assert block_dim_for((4096, 20), 132) == 128  # 640 blocks (320 of 256 would leave SMs with 2)
    assert block_dim_for((4096, 40), 132) == 256  # 640 blocks
    assert block_dim_for((4096, 1600), 132) == 256
    assert block_dim_for((4096, 1600), 132, cap=64) == 64
    assert block_dim_for(10**7, 132, cap=64) == 64
    assert block_dim_for(4096, 0) == 256
    for threads in (1, 100, 5000, 70000, 10**6):
        block = block_dim_for(threads, 132)
        assert block in (32, 64, 128, 256)
        assert block == 32 or threads >= 4 * 132 * block


def _pendulum_world(device, max_registers=None):
    b = SceneBuilder()
    b.add_particles([[0.0, 0.0, 0.0], [0.3, 0.0, -0.4]], mass=1.0, fixed=[0])
    b.add_distance(0, 1)
    world = b.finalize(2, device, substeps=5)
    world.max_registers = dict(max_registers or {})
    return world


def test_register_caps_keep_the_results_and_reject_bad_caps(device):
    """A register cap (``World.max_registers``, by kernel function name) recompiles the kernel in its own module and
    must not change what it computes: the capped step matches the plain one to float32 round-off (on the CPU the cap
    is ignored and the results are identical). A cap CUDA's compilers refuse, a non-string name, or a name the step
    does not launch raise ``ValueError``s when the step is recorded."""
    plain, capped = _pendulum_world(device), _pendulum_world(device, {"integrate_particles": 32})
    for _ in range(20):
        plain.step(0.01)
        capped.step(0.01)
    np.testing.assert_allclose(capped.positions(), plain.positions(), rtol=0, atol=1e-6)
    for caps, message in (({"integrate_particles": 8}, r"register cap must be an int in \[16, 255\]"),
                          ({"integrate_particles": True}, "register cap must be an int"),
                          ({3: 64}, "map kernel function names"),
                          ({"no_such_kernel": 64}, r"does not launch: \['no_such_kernel'\]")):
        with pytest.raises(ValueError, match=message):
            _pendulum_world(device, caps).step(0.01)


def test_default_register_caps_apply_where_launched_and_yield_to_max_registers(device):
    """A task's own caps (``World.default_register_caps``) apply to the kernels the step launches and are passed over
    where another setting launches another kernel (no error, unlike ``max_registers``); ``max_registers`` overrides
    them; a bad cap among them is still a ``ValueError``."""
    world = _pendulum_world(device)
    world.default_register_caps = {"integrate_particles": 32, "no_such_kernel": 64}
    world.step(0.01)
    assert world.register_caps == {"integrate_particles": 32, "no_such_kernel": 64}
    world.max_registers = {"integrate_particles": 48}
    assert world.register_caps == {"integrate_particles": 48, "no_such_kernel": 64}
    world.step(0.01)
    assert np.isfinite(world.positions()).all()
    world.default_register_caps = {"integrate_particles": 8}
    world.max_registers = {}
    with pytest.raises(ValueError, match=r"register cap must be an int in \[16, 255\]"):
        world.step(0.01)


class _SubstepEndProbe:
    """A solver with a substep-end hook (nothing else): the World then updates velocities after every substep
    instead of fusing the update into the next substep's prediction."""

    def __init__(self):
        self.calls = 0

    def record_sweep(self, world, launch, sweep):
        pass

    def record_substep_end(self, world, launch, sweep):
        self.calls += 1


def test_fused_velocity_update_and_prediction_match_the_separate_kernels(device):
    # xpbd.finish_and_integrate_* runs a substep's velocity update and the next substep's prediction in one kernel;
    # the same arithmetic, so a swinging rod (particles and segments) and a falling cloth pinned at a corner end at
    # the same positions and velocities to float32 round-off (1e-6 relative; measured identical on the CPU); so do
    # particles and segments predicted in one launch (World.integrate_together, the default) or a launch each
    out = []
    for hooked, together in ((False, True), (True, True), (True, False)):
        b = SceneBuilder()
        pts = np.stack([np.linspace(0.0, 0.1, 11), np.zeros(11), np.zeros(11)], axis=1)
        b.add_rod(pts, radius=1e-3, youngs_modulus=1e6, damping=0.3, fixed=[0])
        v, t = cloth_grid(4, 4, 0.03, 0.03, plane="xz", origin=(0.2, 0.0, 0.0))
        b.add_cloth(v, t, areal_density=0.2, stretch_stiffness=1e3, bend_stiffness=1e-6, damping=0.5, fixed=[0])
        world = b.finalize(2, device, substeps=6)
        world.integrate_together = together
        probe = _SubstepEndProbe()
        if hooked:
            world.add_solver(probe)
        world.simulate(0.1, 0.02)
        assert (probe.calls > 0) == hooked  # recorded once: one call per substep
        st = world.state
        out.append([a.numpy() for a in (st.particle_q, st.particle_qd, st.segment_q, st.segment_qd)])
    assert np.abs(out[0][1]).max() > 0.1  # the scene moves
    for other in out[1:]:
        for fused, separate in zip(out[0], other, strict=True):
            np.testing.assert_allclose(fused, separate, rtol=1e-6, atol=1e-6 * np.abs(separate).max())
        assert np.abs(out[0][0] - other[0]).max() <= 1e-6


def test_prediction_in_the_rod_sweep_matches_the_separate_launch(device):
    # in a world whose only constraints are rods the substep's prediction runs in its first sweep's fused rod launch
    # (xpbd.predict_and_solve_rods_fused, World.predict_in_rod_sweep): the same arithmetic on the same elements, so a
    # swinging rod held at one end ends where the separate prediction launch leaves it (bit for bit on the CPU, to
    # float32 round-off on a GPU), at 1 and 2 sweeps per substep; a world with a cloth keeps the separate launch
    out = []
    for in_sweep, iterations in ((True, 1), (False, 1), (True, 2), (False, 2)):
        b = SceneBuilder()
        pts = np.stack([np.linspace(0.0, 0.1, 11), np.zeros(11), np.zeros(11)], axis=1)
        b.add_rod(pts, radius=1e-3, youngs_modulus=1e6, damping=0.3, fixed=[0])
        world = b.finalize(2, device, substeps=6)
        world.predict_in_rod_sweep = in_sweep
        world.set_iterations(iterations)
        assert world._predicts_in_rod_sweep() == in_sweep
        world.simulate(0.1, 0.02)
        st = world.state
        out.append([a.numpy() for a in (st.particle_q, st.particle_qd, st.segment_q, st.segment_qd)])
    assert np.abs(out[0][1]).max() > 0.1 and out[0][0][:, -1, 2].min() < -0.01  # the rod swings down
    for fused, separate in ((out[0], out[1]), (out[2], out[3])):
        for a, b_ in zip(fused, separate, strict=True):
            if device == "cpu":
                np.testing.assert_array_equal(a, b_)
            else:
                np.testing.assert_allclose(a, b_, rtol=1e-5, atol=1e-5 * np.abs(b_).max())
    b = SceneBuilder()
    b.add_rod(pts, radius=1e-3, youngs_modulus=1e6, damping=0.3, fixed=[0])
    v, t = cloth_grid(4, 4, 0.03, 0.03, plane="xz", origin=(0.2, 0.0, 0.0))
    b.add_cloth(v, t, areal_density=0.2, stretch_stiffness=1e3, bend_stiffness=1e-6, damping=0.5, fixed=[0])
    assert not b.finalize(1, device, substeps=6)._predicts_in_rod_sweep()  # the cloth's edges come first


def test_instability_restores_cut_masks_and_rotations(device):
    # the stability check (world_kernels.check_and_restore, one launch per step) restores every state array of a
    # failed env, its tet rotations and its cut masks, and marks its cut surfaces dirty; the other envs keep theirs
    b = SceneBuilder()
    v, t = box_tets((0.02, 0.02, 0.02), (2, 2, 2))
    b.add_tet_mesh(v, t, density=1000.0, youngs_modulus=5e3, poisson_ratio=0.3,
                   fixed=np.nonzero(v[:, 2] < 1e-9)[0], cuttable=True)
    world = b.finalize(2, device, substeps=5, max_speed=10.0)
    st = world.state
    active0 = st.tet_active.numpy().copy()
    rot0 = world._tet_rotation.numpy().copy()
    for _ in range(3):
        world.step(0.01)
    st.cut_dirty.zero_()
    active = active0.copy()
    active[:, 0] = 0  # both envs "cut" their first tet
    st.tet_active.assign(active)
    rot = world._tet_rotation.numpy()
    rot[:, 1] = (0.0, 0.0, 0.6, 0.8)
    world._tet_rotation.assign(rot)
    q = st.particle_q.numpy().copy()
    q[1, 5] = np.nan
    st.particle_q.assign(q)
    world.check_stability()  # what every step ends with (called alone: the solves would rewrite the rotations)
    assert world.unstable.numpy().tolist() == [0, 1]
    assert st.tet_active.numpy()[1].tolist() == active0[1].tolist()  # env 1 restored
    assert st.tet_active.numpy()[0, 0] == 0  # env 0 keeps its cut
    assert st.cut_dirty.numpy()[:, 0].tolist() == [0, 1]
    np.testing.assert_array_equal(world._tet_rotation.numpy()[1], rot0[1])
    assert world._tet_rotation.numpy()[0, 1].tolist() == [0.0, 0.0, 0.6000000238418579, 0.800000011920929]
    np.testing.assert_array_equal(st.particle_q.numpy()[0], q[0])  # env 0 untouched
    assert np.all(np.isfinite(st.particle_q.numpy()))
    world.step(0.01)
    assert world.unstable.numpy().tolist() == [0, 1]  # sticky until the env is reset


def test_step_keeps_body_poses_as_next_start(device):
    # a body moved between steps is swept from its pose at the step's start to the new one; the step's last launch
    # (the stability check) then keeps the new pose as the next step's start (it was a copy of its own)
    v, t = cloth_grid(3, 3, 0.02, 0.02, plane="xy")
    b = SceneBuilder()
    obj = b.add_cloth(v, t, areal_density=0.2, stretch_stiffness=1e3, bend_stiffness=1e-6, damping=1.0)
    body = b.add_body("grasper", pose=(*v[0], 0.0, 0.0, 0.0, 1.0))
    b.add_attachment(obj.particle_start, body, compliance=1e-6)
    world = b.finalize(2, device, substeps=4)
    pose = np.array([[[*(v[0] + (0.0, 0.0, -0.01)), 0.0, 0.0, 0.0, 1.0]]] * 2, np.float32)  # (envs, bodies, 7)
    world.set_body_poses(wp.array(pose, dtype=wp.transform, device=device),
                         wp.array([body], dtype=wp.int32, device=device))
    assert not np.allclose(world.body_q_previous.numpy(), world.state.body_q.numpy())  # moved, not yet swept
    world.step(0.02)
    np.testing.assert_array_equal(world.body_q_previous.numpy(), world.state.body_q.numpy())
    np.testing.assert_allclose(world.positions()[:, obj.particle_start], np.tile(v[0] + (0.0, 0.0, -0.01), (2, 1)),
                               atol=1e-4)  # the held vertex followed the body


def test_iterations_set_directly_allocate_the_multipliers(device):
    # world.iterations assigned after finalize (set_iterations allocates the XPBD multipliers): the step allocates
    # them where the sweeps index them (a (1, 1) dummy was indexed out of bounds before: a segfault on the CPU), and
    # the result equals set_iterations'
    v, t = cloth_grid(6, 5, 0.05, 0.04, plane="xz", origin=(0.0, 0.0, -0.04))
    out = []
    for direct in (False, True):
        b = SceneBuilder()
        b.add_cloth(v, t, areal_density=0.2, stretch_stiffness=1e3, bend_stiffness=1e-6, damping=1.0,
                    fixed=np.nonzero(v[:, 2] > -1e-9)[0][:2])
        world = b.finalize(2, device, substeps=5)
        if direct:
            world.iterations = 2
        else:
            world.set_iterations(2)
        world.simulate(0.04, 0.02)
        assert "edge" in world._lam
        out.append(world.positions())
    np.testing.assert_array_equal(out[0], out[1])
    assert np.isfinite(out[0]).all()
