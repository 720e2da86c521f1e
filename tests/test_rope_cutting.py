"""RopeCuttingEnv: the pre-tensioned rope against closed forms, the reset layout, the cut/success/failure logic, the
observation of cut points, the rendering of cut and active ropes, and the scripted expert (CPU)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
import warp as wp

import lapwarp
from lapwarp.cutting import CuttingSystem
from lapwarp.experts import make_expert
from lapwarp.tasks.dissection.rope_cutting import NODES, SEGMENTS, TRACKED

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
import rope_settle  # noqa: E402

K, CONTRACTION, MASS = 1.0e4, 0.8, 0.01  # the env's rope: spring constant (N/m), rest-length ratio, kg per rope


def one_rope(device, cuttable=False):
    """The env's rope (same construction, ``benchmarks/rope_settle.py``) stretched horizontally between (-50, 0, 0)
    and (50, 0, 0) mm, at the env's substeps and Newton steps."""
    from lapwarp.tasks.dissection.rope_cutting import RopeCuttingConfig

    cfg = RopeCuttingConfig()
    return rope_settle.task_rope(device, cfg.physics_substeps, cfg.rope_newton_steps, cuttable=cuttable)


def test_pretensioned_rope_sags_like_a_taut_string(device):
    """Closed form: a string under horizontal tension H with point loads P every h hangs on the parabola
    P x (L - x) / (2 H h) (P L^2 / (8 H h) = 29 micrometres in the middle; H = k (h - 0.2 h) = 42.1 N); tolerance
    3 %."""
    world, rope = one_rope(device)
    world.simulate(2.0, dt=0.1)
    x = world.positions(rope)[0]
    h = 0.1 / SEGMENTS
    tension = K * (h - (1.0 - CONTRACTION) * h)
    load = MASS / SEGMENTS * 9.81  # an interior node carries one segment's mass
    # the nodes lie on y(x) = (P / h) x (L - x) / (2 H); with 19 segments nodes 9 and 10 sit at L/2 -+ h/2
    sag = -x[NODES // 2 - 1:NODES // 2 + 1, 2].mean()
    expected = load / h * (0.05 - h / 2) * (0.05 + h / 2) / (2.0 * tension)
    assert sag == pytest.approx(expected, rel=0.03)
    assert abs(x[:, 1]).max() < 1e-7  # stays in its vertical plane


@pytest.mark.parametrize("newton, tolerance, settles", [(None, 0.0, True), (None, 1e-7, True), (3, 0.0, False)])
def test_bumped_rope_settles_on_the_taut_string(device, newton, tolerance, settles):
    """The rope with its middle third pushed 20 mm down (tapering to the walls), released at rest: at the env's solver
    setting (40 substeps, 4 Newton steps per sweep) it settles on the taut-string closed form within 3 % and stays in
    its vertical plane, also on the register solve stopping its Newton steps at 1e-7 m (``rope_newton_tolerance``);
    with 3 Newton steps the tension's transverse response overshoots and it is still swinging after 3 s
    (benchmarks/rope_settle.py sweeps the settings)."""
    from lapwarp.tasks.dissection.rope_cutting import RopeCuttingConfig

    cfg = RopeCuttingConfig()
    row = rope_settle.settle(device, cfg.physics_substeps, newton or cfg.rope_newton_steps, 0.02, 2, 3.0, tolerance)
    settled = abs(row["sag_over_closed_form"] - 1.0) < 0.03 and row["max_sideways_m"] < 1e-6
    assert settled == settles, row
    assert not row["unstable"]


def test_cut_rope_snaps_back_to_its_rest_length(device):
    """A rope cut in the middle: every remaining spring relaxes to its rest length 0.2 h (plus the weight it
    carries, < 0.5 %), i.e. each half retracts to about 10 mm at its wall."""
    world, rope = one_rope(device, cuttable=True)
    world.simulate(0.5, dt=0.1)
    cut = CuttingSystem(world, carving_distance=0.0, num_tools=1, tool_radius=1.0e-3)
    cut.add_object(rope)
    cut.finalize()
    cut.set_tools([[0.0, 0.0, -0.01]], [[0.0, 0.0, 0.01]], active=[1])  # a vertical blade through the middle
    cut.cut()
    active = world.state.segment_active.numpy()[0]
    assert active.sum() == SEGMENTS - 1 and active[SEGMENTS // 2] == 0
    cut.set_tools([[0.0, 0.0, -0.01]], [[0.0, 0.0, 0.01]], active=[0])
    world.simulate(2.0, dt=0.1)
    x = world.positions(rope)[0]
    lengths = np.linalg.norm(np.diff(x, axis=0), axis=1)[active != 0]
    rest = (1.0 - CONTRACTION) * 0.1 / SEGMENTS
    np.testing.assert_allclose(lengths, rest, rtol=0.01)
    assert abs(x[NODES // 2 - 1, 0] + 0.05) < 0.012 and abs(x[NODES // 2 + 1, 0] - 0.05) < 0.012  # at the walls
    assert not world.unstable.numpy().any()


def test_reset_layout(device):
    """Ends on the two wall faces, every pair of ropes at least 10 mm apart, 20 nodes evenly on each line, at rest."""
    env = lapwarp.make("RopeCutting", num_envs=6, device=device, seed=4)
    s = env.privileged_state()
    a, b = s["start"].cpu().numpy(), s["end"].cpu().numpy()
    assert np.allclose(a[..., 0], -0.05) and np.allclose(b[..., 0], 0.05)
    for p in (a, b):
        assert (p[..., 1] >= 0).all() and (p[..., 1] <= 0.02).all() and (abs(p[..., 2]) <= 0.05).all()
    x = s["positions"].cpu().numpy()
    for e in range(6):
        for r in range(5):
            nodes = x[e, r * NODES:(r + 1) * NODES]
            line = a[e, r] + (b[e, r] - a[e, r]) * np.linspace(0, 1, NODES)[:, None]
            np.testing.assert_allclose(nodes, line, atol=1e-6)
            for o in range(r):
                assert segment_distance(a[e, r], b[e, r], a[e, o], b[e, o]) >= 0.01 - 1e-6
    assert (s["rope_state"].cpu() == 0).all() and ((s["active"] >= 0) & (s["active"] < 5)).all().item()


LANES_SCRIPT = """
import sys
import numpy as np
import warp as wp
wp.config.quiet = True
wp.config.enable_cpu_blocks = True  # Warp's CPU blocks then have block_dim threads, as on the GPU
import lapwarp
from lapwarp.tasks.dissection import rope_cutting
rope_cutting.LAYOUT_LANES = 16
env = lapwarp.make("RopeCutting", num_envs=96, device="cpu", seed=11, num_ropes=int(sys.argv[2]))
s = env.privileged_state()
np.save(sys.argv[1], np.concatenate([s["start"].numpy(), s["end"].numpy(), s["positions"].numpy()[:, :1]], 1))
"""


@pytest.mark.parametrize("ropes", [5, 10])
def test_block_parallel_layout_draws_the_sequential_rule(tmp_path, ropes):
    """The reset tests a block of draws at once (16 lanes here, 64 on the GPU) and keeps the first acceptable one in
    draw order: same rule, same distribution as one draw at a time (one lane, the CPU default). Run with Warp's
    cooperative CPU blocks in a subprocess (a process-wide Warp setting); compared by two-sample KS tests on every end
    coordinate (96 envs x R ropes each), and every pair of the block path's ropes is >= 10 mm apart."""
    from scipy.stats import ks_2samp

    script, out = tmp_path / "lanes.py", tmp_path / "lanes.npy"
    script.write_text(LANES_SCRIPT)
    done = subprocess.run([sys.executable, str(script), str(out), str(ropes)], capture_output=True, text=True,
                          timeout=600)
    assert done.returncode == 0, done.stderr[-2000:]
    blocks = np.load(out)
    env = lapwarp.make("RopeCutting", num_envs=96, device="cpu", seed=11, num_ropes=ropes)
    s = env.privileged_state()
    single = np.concatenate([s["start"].numpy(), s["end"].numpy()], 1)
    a, b = blocks[:, :ropes], blocks[:, ropes:2 * ropes]
    assert not np.allclose(blocks[:, :2 * ropes], single)  # different draws ...
    for k, (axis, name) in enumerate([(1, "a.y"), (2, "a.z"), (1, "b.y"), (2, "b.z")]):
        half = slice(0, ropes) if k < 2 else slice(ropes, 2 * ropes)
        p = ks_2samp(blocks[:, half, axis].ravel(), single[:, half, axis].ravel()).pvalue
        assert p > 1e-3, (name, p)  # ... from the same law
    for e in range(0, 96, 8):
        for r in range(ropes):
            for o in range(r):
                assert segment_distance(a[e, r], b[e, r], a[e, o], b[e, o]) >= 0.01 - 1e-6


def segment_distance(p1, q1, p2, q2, samples=401):
    t = np.linspace(0.0, 1.0, samples)
    u = p1 + (q1 - p1) * t[:, None]
    v = p2 + (q2 - p2) * t[:, None]
    return np.sqrt(((u[:, None] - v[None]) ** 2).sum(-1)).min()


def cut_segment(env, env_id: int, rope: int, segment: int = SEGMENTS // 2) -> None:
    """Remove one segment of a rope in one env (host write, as a test fixture), marking the env's masks dirty."""
    s = env.world.state
    mask = s.segment_active.numpy()
    mask[env_id, env.ropes_obj[rope].segment_start + segment] = 0
    s.segment_active.assign(mask)
    dirty = s.cut_dirty.numpy()
    dirty[env_id] = 1
    s.cut_dirty.assign(dirty)


def idle(env):
    return torch.tensor([[0.0, 0.0, 0.0, 0.0, -1.0]] * env.num_envs, device=env.device)


def test_cuts_success_failure_and_new_active_rope(device):
    """C = 2 of R = 3: cutting the active rope pays +5, keeps going and makes another intact rope active (its
    distance delta restarts); with one correct cut done, a wrong cut (-5) leaves 1 intact rope for 1 missing cut
    (not failed); env 1 cuts the active rope twice and succeeds (+10). With C = R = 3 one wrong cut fails (-20,
    terminated, not a time out)."""
    env = lapwarp.make("RopeCutting", num_envs=2, device=device, seed=7, num_ropes=3, num_ropes_to_cut=2)
    w = env.reward_weights
    env.step(idle(env))
    first = env.task.active.numpy().copy()
    for e in range(2):
        cut_segment(env, e, int(first[e]))
    _, reward, done, extras = env.step(idle(env))
    f = env.features.numpy()
    F = env.rewards.F
    assert (f[:, F.CUT_ACTIVE_ROPE] == 1).all() and (f[:, F.SUCCESSFUL_TASK] == 0).all() and not done.any()
    second = env.task.active.numpy()
    assert (second != first).all() and (env.task.state.numpy()[np.arange(2), first] == 1).all()
    assert reward.cpu().numpy() == pytest.approx(w["cut_active_rope"] + w["delta_distance_cauter_active_rope"]
                                                 * f[:, F.DELTA_DISTANCE_CAUTER_ACTIVE_ROPE], abs=1e-5)
    _, _, _, _ = env.step(idle(env))  # the restarted delta: a still hook sees no change of distance
    assert abs(env.features.numpy()[:, F.DELTA_DISTANCE_CAUTER_ACTIVE_ROPE]).max() < 1e-4
    wrong = [r for r in range(3) if r not in (first[0], second[0])][0]
    cut_segment(env, 0, wrong)  # env 0: one wrong cut, one intact rope left for one missing cut
    cut_segment(env, 1, int(second[1]))  # env 1: the second correct cut
    _, reward, done, _ = env.step(idle(env))
    f = env.features.numpy()
    # the retracting halves move the active rope's nearest node: the distance delta pays too
    moved = w["delta_distance_cauter_active_rope"] * f[:, F.DELTA_DISTANCE_CAUTER_ACTIVE_ROPE]
    assert f[0, F.CUT_INACTIVE_ROPE] == 1 and f[0, F.FAILED_TASK] == 0 and not done[0]
    assert reward[0].item() == pytest.approx(w["cut_inactive_rope"] + moved[0], abs=1e-4)
    assert done[1] and env.last_episode_success.numpy()[1] == 1
    assert reward[1].item() == pytest.approx(w["cut_active_rope"] + w["successful_task"] + moved[1], abs=1e-4)
    # failure: 3 of 3 to cut, so the first wrong cut leaves 2 intact ropes for 3 missing cuts
    env3 = lapwarp.make("RopeCutting", num_envs=1, device=device, seed=3, num_ropes=3, num_ropes_to_cut=3)
    env3.step(idle(env3))
    active = int(env3.task.active.numpy()[0])
    cut_segment(env3, 0, (active + 1) % 3)
    _, reward, done, extras = env3.step(idle(env3))
    f = env3.features.numpy()
    moved = w["delta_distance_cauter_active_rope"] * f[0, F.DELTA_DISTANCE_CAUTER_ACTIVE_ROPE]
    assert done[0] and env3.last_episode_success.numpy()[0] == 0 and not extras["time_outs"][0]
    assert reward[0].item() == pytest.approx(w["cut_inactive_rope"] + w["failed_task"] + moved, abs=1e-4)


def test_cut_points_read_as_the_workspace_corner(device):
    """A tracking node whose both segments are cut (node 9 of rope 0) observes as (1, 1, 1), as in sofa_env."""
    env = lapwarp.make("RopeCutting", num_envs=1, device=device, seed=5)
    cut_segment(env, 0, 0, segment=8)
    cut_segment(env, 0, 0, segment=9)
    obs, *_ = env.step(idle(env))
    cols = env.obs_layout.columns
    rope0 = obs["policy"][0, cols.ropes:cols.ropes + 9].cpu().numpy().reshape(3, 3)
    np.testing.assert_allclose(rope0[TRACKED.index(9)], 1.0, atol=1e-6)
    ends = rope0[[0, 2]]  # the fixed ends are still there: on the walls (x = -+1), inside the workspace
    np.testing.assert_allclose(ends[:, 0], [-1.0, 1.0], atol=1e-5)
    assert (abs(ends[:, 1:]) < 1.0).all()


def test_rendering_shows_the_active_rope_green_and_hides_cut_segments(device):
    env = lapwarp.make("RopeCutting", num_envs=2, device=device, seed=6, observation_type="RGB", image_shape=(96, 96))
    rgb = env.render_rgb(96, 96).float()
    green = (rgb[:, 1] > 150) & (rgb[:, 0] < 80)
    red = (rgb[:, 0] > 150) & (rgb[:, 1] < 80)
    assert green.sum(dim=(1, 2)).min() > 20 and red.sum(dim=(1, 2)).min() > 20
    active = int(env.task.active.numpy()[0])
    wrong = (active + 1) % 5  # an inactive rope: the episode goes on
    cut_segment(env, 0, wrong)
    env.step(idle(env))
    env.update_visuals()
    green_mask, red_mask = env.active_segments.numpy()[0], env.idle_segments.numpy()[0]
    assert green_mask[active * SEGMENTS:(active + 1) * SEGMENTS].all() and green_mask.sum() == SEGMENTS
    assert red_mask[wrong * SEGMENTS + SEGMENTS // 2] == 0 and red_mask.sum() == 4 * SEGMENTS - 1


@pytest.mark.parametrize("action_type", ["CONTINUOUS", "DISCRETE"])
@pytest.mark.parametrize("ropes, to_cut", [(5, 1), (10, 3)])
def test_expert_solves_the_paper_configurations(device, action_type, ropes, to_cut):
    """The scripted expert (privileged state) solves >= 90 % of the episodes of every paper configuration."""
    env = lapwarp.make("RopeCutting", num_envs=8, device=device, seed=11, num_ropes=ropes, num_ropes_to_cut=to_cut,
                       action_type=action_type)
    expert = make_expert(env)
    obs = env.get_observations()
    episodes = successes = 0
    for _ in range(420 if to_cut == 3 else 160):
        obs, _, done, _ = env.step(expert(obs))
        finished = done.cpu().numpy()
        episodes += int(finished.sum())
        successes += int(env.last_episode_success.numpy()[finished].sum())
        if episodes >= (16 if to_cut == 1 else 8):
            break
    assert episodes >= 8
    assert successes / episodes >= 0.9, f"{successes}/{episodes}"


def test_rope_newton_tolerance_follows_the_chain_solver(device):
    # every Newton step by default; a tolerance where the register solve runs the ropes; one with the serial walk,
    # which would not honour it, is refused at build
    assert lapwarp.make("RopeCutting", num_envs=1, device=device, chain_solver="registers").world \
        .rod_newton_tolerance == 0.0
    assert lapwarp.make("RopeCutting", num_envs=1, device=device, chain_solver="registers",
                        rope_newton_tolerance=1e-7).world.rod_newton_tolerance == 1e-7
    with pytest.raises(ValueError, match="rope_newton_tolerance=.*register-resident, hybrid and pcr chain solves only"):
        lapwarp.make("RopeCutting", num_envs=1, device=device, chain_solver="thomas", rope_newton_tolerance=1e-7)
    with pytest.raises(ValueError, match="rope_newton_tolerance"):
        lapwarp.make("RopeCutting", num_envs=1, device=device, rope_newton_tolerance=-1e-7)


def test_world_is_built_with_the_papers_rope_physics(device):
    env = lapwarp.make("RopeCutting", num_envs=1, device=device)
    m = env.world.model
    rest = m.rod_stretch_rest.numpy()
    np.testing.assert_allclose(rest, 0.2 * 0.1 / SEGMENTS, rtol=1e-5)
    compliance = m.rod_stretch_compliance.numpy().ravel()
    np.testing.assert_allclose(1.0 / compliance, K, rtol=1e-4)  # spring constant per segment
    mass = 1.0 / m.particle_inv_mass.numpy().ravel()[1:NODES - 1]
    np.testing.assert_allclose(mass, MASS / SEGMENTS, rtol=1e-4)
    assert wp.types.types_equal(env.world.state.segment_active.dtype, wp.int32)
