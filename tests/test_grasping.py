"""Instrument shapes and grasping: jaw poses and limits, grasp / lift / release of a rod and a torus, no grasp with
open jaws or a single jaw in contact, start_grasped and lost-grasp events, env isolation."""

from __future__ import annotations

import math

import numpy as np
import pytest
import warp as wp

from lapwarp.assets import rod_circle, rod_polyline
from lapwarp.builder import SceneBuilder
from lapwarp.contact import ContactSystem
from lapwarp.grasping import GraspSystem
from lapwarp.instrument_shapes import InstrumentShape, tip_poses_numpy

# tip frame pointing down: local +z (jaws) = world -z, local y (jaw opening) = world -y
DOWN = (1.0, 0.0, 0.0, 0.0)


def _scene(device, kind="rod", num_envs=2):
    b = SceneBuilder()
    if kind == "rod":
        r = 1.0e-3
        obj = b.add_rod(rod_polyline([[-0.05, 0, r], [0.05, 0, r]], 21), radius=r, youngs_modulus=1e6, damping=2.0)
        grip = np.array([0.0, 0.0, r])
    else:
        r = 2.0e-3
        obj = b.add_rod(rod_circle(0.014, 30, center=(0, 0, r)), radius=r, youngs_modulus=1e6, closed=True,
                        damping=2.0)
        grip = np.array([0.0, 0.014, r])  # the tube runs along x there, across the jaw opening
    ins = InstrumentShape(b, "grasper", name="grasper")
    w = b.finalize(num_envs=num_envs, device=device, substeps=10, attachment_capacity=2)
    cs = ContactSystem(w, body_ignore_mask=True)
    g = cs.add_particle_group(obj, radius=r, segments=True)
    cs.add_plane(name="floor", mu_static=0.5)
    ins.add_colliders(cs, thickness=0.0)
    cs.finalize()
    angle = wp.array(np.full(num_envs, 30.0, np.float32), dtype=float, device=device)
    gs = GraspSystem(cs, ins, angle, groups=[g])
    return w, cs, gs, ins, obj, angle, grip


def _drive(w, ins, angle, tips, angles):
    tip = wp.array(tip_poses_numpy(tips, np.tile(DOWN, (len(tips), 1))), dtype=wp.transform, device=w.device)
    angle.assign(np.asarray(angles, np.float32))
    ins.pose(w, tip, 0, angle)
    w.step(0.1)


@pytest.mark.parametrize("kind", ["rod", "torus"])
def test_grasp_lift_release(device, kind):
    """Env 0 closes on the rod/torus, grasps it with a jaw body, lifts it 30 mm (the held point follows the jaws
    within 2 mm, grasped = 1), opens (released, grasped = 0) and it falls back to the floor. Env 1 closes its jaws
    20 mm to the side of the object: no contact on both jaws -> no grasp, its object stays on the floor."""
    w, cs, gs, ins, obj, angle, grip = _scene(device, kind)
    hold_z = grip[2] + 0.015  # the object sits 15 mm along the jaws
    tips = np.array([grip + [0, 0, 0.015], grip + [0, 0.02, 0.015]])
    tips[:, 2] = hold_z
    for a in np.linspace(30.0, 0.0, 11):  # close
        _drive(w, ins, angle, tips, [a, a])
    assert list(gs.grasped.numpy()) == [1, 0]
    held = int(w.state.attach_particle.numpy()[0, 0])
    assert obj.particle_start <= held < obj.particle_start + obj.particle_count
    assert int(w.state.attach_body.numpy()[0, 0]) in (ins.jaw_a, ins.jaw_b)  # held by a jaw, not the shaft
    for k in range(1, 11):  # lift 30 mm
        tips[:, 2] = hold_z + 0.003 * k
        _drive(w, ins, angle, tips, [0.0, 0.0])
    x = w.positions()
    target = np.array([tips[0, 0], tips[0, 1], tips[0, 2] - 0.015])
    assert np.linalg.norm(x[0, held] - (grip + [0, 0, 0.03])) < 2.0e-3
    assert np.linalg.norm(x[0, held] - target) < 2.0e-3
    assert x[1, obj.particles, 2].max() < 0.005  # env 1 untouched
    assert list(gs.grasped.numpy()) == [1, 0] and gs.lost_grasp.numpy().sum() == 0
    for a in np.linspace(0.0, 20.0, 5):  # open past the release threshold (15 deg)
        _drive(w, ins, angle, tips, [a, a])
    assert list(gs.grasped.numpy()) == [0, 0] and gs.lost_grasp.numpy().sum() == 0
    for _ in range(10):
        _drive(w, ins, angle, tips, [20.0, 20.0])
    assert w.positions()[0, obj.particles, 2].max() < 0.01


def test_no_grasp_with_jaws_open(device):
    """Jaws held at 12 deg (above the 10 deg grasp threshold) around the rod never grasp, although the jaws
    touch it; a lost grasp is raised when a held rod is torn out of the jaws (start_grasped at node 10, then
    the jaw jumps 5 cm away within one step)."""
    w, cs, gs, ins, obj, angle, grip = _scene(device, "rod", num_envs=1)
    tip = grip + [0, 0, 0.015]
    for _ in range(5):
        _drive(w, ins, angle, [tip], [12.0])
    assert gs.grasped.numpy()[0] == 0
    # start_grasped at a given particle (reset-time host call)
    _drive(w, ins, angle, [tip], [0.0])
    gs.start_grasped(obj.particle_start + 10)
    assert gs.grasped.numpy()[0] == 1 and w.state.attach_particle.numpy()[0, 0] == obj.particle_start + 10
    assert w.state.attach_body.numpy()[0, 0] in (ins.jaw_a, ins.jaw_b)
    _drive(w, ins, angle, [tip + [0, 0, 0.005]], [0.0])
    assert gs.grasped.numpy()[0] == 1
    # a stiffly attached node follows any jaw motion, so tear it by making the attachment soft
    w.state.attach_compliance.assign(np.full((1, 2), 1.0e3, np.float32))
    _drive(w, ins, angle, [tip + [0.05, 0, 0.005]], [0.0])
    assert gs.grasped.numpy()[0] == 0 and gs.lost_grasp.numpy()[0] == 1
    _drive(w, ins, angle, [tip + [0.05, 0, 0.005]], [0.0])
    assert gs.lost_grasp.numpy()[0] == 0  # an event: only the step it happened


def test_instrument_poses_and_jaw_limits(device):
    """Jaw bodies hinge at the tip and rotate about local x by +-angle; jaw angle follows the action within
    its limits and does not close while grasped."""
    b = SceneBuilder()
    b.add_particles(np.zeros((1, 3)), mass=1.0)
    ins = InstrumentShape(b, "grasper", angle_limits=(0.0, 40.0))
    w = b.finalize(num_envs=2, device=device)
    angle = wp.array(np.array([10.0, 39.0], np.float32), dtype=float, device=device)
    tip = wp.array(tip_poses_numpy([[0.1, 0.0, 0.0], [0.0, 0.0, 0.0]]), dtype=wp.transform, device=device)
    ins.pose(w, tip, 0, angle)
    bq = w.state.body_q.numpy()
    a = math.radians(10.0)
    assert np.allclose(bq[0, ins.jaw_a], [0.1, 0, 0, math.sin(a / 2), 0, 0, math.cos(a / 2)], atol=1e-6)
    assert np.allclose(bq[0, ins.jaw_b], [0.1, 0, 0, -math.sin(a / 2), 0, 0, math.cos(a / 2)], atol=1e-6)
    act = wp.array(np.array([[1.0], [1.0]], np.float32), dtype=float, device=device)
    ins.step_jaw(act, 0, max_speed_deg=20.0, dt=0.1, angle_deg=angle)
    assert np.allclose(angle.numpy(), [12.0, 40.0])
    grasped = wp.array(np.array([1, 0], np.int32), dtype=wp.int32, device=device)
    act.assign(np.array([[-1.0], [-1.0]], np.float32))
    ins.step_jaw(act, 0, max_speed_deg=20.0, dt=0.1, angle_deg=angle, grasped=grasped)
    assert np.allclose(angle.numpy(), [12.0, 38.0])
    for kind in ("cauter", "scissors", "loop", "endoscope"):
        b = SceneBuilder()
        sh = InstrumentShape(b, kind, name=kind)
        meshes = sh.visual_meshes()
        assert meshes and all(m.is_watertight for _, _, m in meshes)
        assert sh.articulated == (kind == "scissors")


@pytest.mark.parametrize("hold_up", [None, (0.0, 0.0, 1.0)])
def test_hold_up_keeps_the_tilt(device, hold_up):
    """A torus node held by a jaw (start_grasped), then the tip tilted by 30 degrees about world x within a step: with
    ``hold_up`` = +z the held segment turns only with the jaw's twist about z (none here) and keeps its orientation
    (within 3 degrees: the rest of the ring pulls on it between projections); without it the segment turns with the
    jaw by the full 30 degrees (within 3). With ``jaws_pass_while_grasped`` every torus node of the holding env ignores
    the jaws, and none after the release."""
    b = SceneBuilder(gravity=(0.0, 0.0, 0.0))
    r = 2.0e-3
    obj = b.add_rod(rod_circle(0.014, 30, center=(0, 0, r)), radius=r, youngs_modulus=1e6, closed=True, damping=2.0)
    ins = InstrumentShape(b, "grasper", name="grasper")
    w = b.finalize(num_envs=1, device=device, substeps=10, attachment_capacity=1)
    cs = ContactSystem(w, body_ignore_mask=True)
    g = cs.add_particle_group(obj, radius=r, segments=True)
    ins.add_colliders(cs, thickness=0.0)
    cs.finalize()
    angle = wp.array(np.zeros(1, np.float32), dtype=float, device=device)
    gs = GraspSystem(cs, ins, angle, groups=[g], hold_up=hold_up, jaws_pass_while_grasped=True)
    grip = np.array([0.0, 0.014, r])
    _drive(w, ins, angle, [grip + [0, 0, 0.015]], [0.0])
    node = obj.particle_start + 7  # node 7 of 30 lies near +y (angle 84 deg): its segment is the one held
    gs.start_grasped(node)
    seg = obj.segment_start + 7
    q0 = w.state.segment_q.numpy()[0, seg].copy()
    ignore = cs.ignore.bodies.numpy()[0, obj.particle_start:obj.particle_start + obj.particle_count]
    assert np.all(ignore & gs.jaw_mask == gs.jaw_mask)
    tilt = math.radians(30.0)
    q_tilt = np.array([math.sin(tilt / 2), 0.0, 0.0, math.cos(tilt / 2)])
    down = np.array(DOWN)
    # compose q_tilt * DOWN (xyzw)
    x1, y1, z1, w1 = q_tilt
    x2, y2, z2, w2 = down
    quat = [w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2, w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2,
            w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2, w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2]
    tip = wp.array(tip_poses_numpy([grip + [0, 0, 0.015]], [quat]), dtype=wp.transform, device=device)
    ins.pose(w, tip, 0, angle)
    w.step(0.1)
    q1 = w.state.segment_q.numpy()[0, seg]
    turned = math.degrees(2.0 * math.acos(min(1.0, abs(float(np.dot(q0, q1))))))
    assert gs.grasped.numpy()[0] == 1
    if hold_up is None:
        assert abs(turned - 30.0) < 3.0
    else:
        assert turned < 3.0
    gs.start_grasped(-1)  # release: the jaws collide again
    ignore = cs.ignore.bodies.numpy()[0, obj.particle_start:obj.particle_start + obj.particle_count]
    assert np.all(ignore & gs.jaw_mask == 0)
