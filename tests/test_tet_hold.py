"""Resting tets held (``World.tet_hold_speed``, ``hold.TetHold``): an env whose per-vertex-solved tets have been at
rest for ``tet_hold_substeps`` substeps skips their sweep until something moves them.

Scene: a soft tet block (E = 30 kPa, clamped base) sagging under gravity, and per env a kinematic sphere 8 mm above
its top. The block settles and is held; then env 0's sphere presses 1.5 mm into the top (env 1's stays) and lifts
again. Reference: the same world without the hold. A held block must be where the solve would have kept it (the
hold's only change is that a vertex slower than the hold speed starts a substep at rest), so every position of both
runs agrees within 2 um at every step (measured 0.9 um on the CPU: the block held while it still crept below the
hold speed), while the press deforms the block by ~1 mm: a hold that missed the press fails by far more (one that
woke only on velocity, not on contact, left the block dented 1.7 mm after the sphere lifted). A held env's tet
vertices do not move at all (bit for bit), and the other env's press does not wake it."""

from __future__ import annotations

import numpy as np
import pytest
import warp as wp

from lapwarp.assets import box_tets
from lapwarp.builder import SceneBuilder
from lapwarp.contact import ContactSystem

HOLD_SPEED = 1.0e-4  # m/s
HOLD_SUBSTEPS = 10
TOP = 0.01  # the block's top face (m)


def _scene(device, hold: bool):
    v, t = box_tets((0.02, 0.02, TOP), (4, 4, 2), origin=(-0.01, -0.01, 0.0))
    b = SceneBuilder()
    blk = b.add_tet_mesh(v, t, density=1000.0, youngs_modulus=3e4, poisson_ratio=0.3, damping=5.0,
                         fixed=np.nonzero(v[:, 2] < 1e-9)[0])
    tool = b.add_body("tool", pose=(0.0, 0.0, TOP + 0.008 + 0.003, 0.0, 0.0, 0.0, 1.0))
    w = b.finalize(num_envs=2, device=device, substeps=10)
    cs = ContactSystem(w)
    cs.add_particle_group(blk, radius=2.0e-4, name="block")
    cs.add_sphere(0.003, body=tool, name="tool")
    cs.finalize()
    if hold:
        w.tet_hold_speed = HOLD_SPEED
        w.tet_hold_substeps = HOLD_SUBSTEPS
    assert w.tet_method_in_use == "vbd" and w.fused_tets
    return w, blk, v


def _run(device, hold: bool):
    """Positions after every 0.05 s step, the hold's quiet counters, and the block's particle range."""
    w, blk, v = _scene(device, hold)
    centre = np.array([0.0, 0.0, TOP + 0.008 + 0.003])
    heights = [0.0] * 20 + list(np.linspace(0.0, -0.0095, 10)) + [-0.0095] * 6 + [0.0] * 24  # tool below rest (m)
    out, quiet = [], []
    for dz in heights:
        pose = w.state.body_q.numpy()
        pose[0, 0, :3] = centre + (0.0, 0.0, dz)  # env 0 only
        w.set_body_poses(wp.array(pose, dtype=wp.transform, device=device),
                         wp.array([0], dtype=wp.int32, device=device))
        w.step(0.05)
        out.append(w.state.particle_q.numpy().copy())
        quiet.append(w._hold_quiet.numpy().copy())
    return np.array(out), np.array(quiet), slice(blk.particle_start, blk.particle_start + blk.particle_count), v


def test_held_block_stays_put_wakes_when_pressed_and_matches_the_unheld_solve(device):
    q_ref, _, block, v = _run(device, hold=False)
    q, quiet, _, _ = _run(device, hold=True)
    # settled and held in both envs before the press (step 19), env 1 to the end
    assert (quiet[19] == HOLD_SUBSTEPS + 1).all(), quiet[15:20]  # held: the sweep skipped (marked after + 1)
    assert (quiet[19:, 1] == HOLD_SUBSTEPS + 1).all()
    # the held env's block does not move at all while held, nor when the other env's block is pressed
    assert np.array_equal(q[19:, 1, block], np.broadcast_to(q[19, 1, block], q[19:, 1, block].shape))
    # env 0 woke during the press: its block deformed under the sphere
    top = np.nonzero(v[:, 2] > TOP - 1e-9)[0] + block.start
    dent = q[:, 0, top, 2].min(axis=1) - q[19, 0, top, 2].min()
    assert dent.min() < -1.0e-3, dent.min()
    assert (quiet[21:36, 0] < HOLD_SUBSTEPS).any()
    # and rests, held again, after the sphere lifted
    assert quiet[-1, 0] == HOLD_SUBSTEPS + 1, quiet[-5:, 0]
    # the same motion as the world without the hold
    err = np.abs(q - q_ref).max()
    assert err < 2.0e-6, err


def test_tet_hold_settings_are_checked(device):
    w, _, _ = _scene(device, hold=False)
    for speed in (-1.0, float("nan"), True, "fast"):
        w.tet_hold_speed = speed
        with pytest.raises(ValueError, match="tet_hold_speed"):
            w.step(0.05)
    w.tet_hold_speed = HOLD_SPEED
    for after in (0, 1.5, True):
        w.tet_hold_substeps = after
        with pytest.raises(ValueError, match="tet_hold_substeps"):
            w.step(0.05)
    # the XPBD tets have no hold
    w.tet_hold_substeps = HOLD_SUBSTEPS
    w.tet_method = "xpbd"
    with pytest.raises(ValueError, match="per-vertex solve"):
        w.step(0.05)
