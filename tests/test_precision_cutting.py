"""PrecisionCuttingEnv: path labels against a NumPy reference of sofa_env's rules, the cut ratio and cut counts after
removing known triangles, resets restoring a cut cloth, paths per env, invalid configurations, the expert."""

from __future__ import annotations

import numpy as np
import pytest
import torch
import warp as wp

import lapwarp
from lapwarp.assets.meshes import cloth_grid
from lapwarp.experts import make_expert
from lapwarp.tasks.dissection.precision_cutting import GRID, SIZE, path_samples_numpy

F = None  # feature columns come from the env


def reference_labels(kind: int, shape, stroke: float = 1.5e-3):
    """sofa_env's bookkeeping in NumPy: on-path vertices (within the stroke of a sample), on-path triangles (an
    on-path vertex), centre-line vertices (nearest grid vertex of each sample, once, in path order)."""
    verts, tris = cloth_grid(GRID, GRID, SIZE, SIZE, plane="xy", origin=(-0.5 * SIZE, -0.5 * SIZE, 0.0))
    samples = path_samples_numpy(kind, *shape)
    d = np.linalg.norm(verts[:, None, :2] - samples[None], axis=2)
    on_vertex = (d <= stroke).any(axis=1)
    on_tri = on_vertex[tris].any(axis=1)
    centre = []
    for s in samples:
        v = int(np.argmin(np.linalg.norm(verts[:, :2] - s, axis=1)))
        if v not in centre:
            centre.append(v)
    return on_vertex, on_tri, centre, tris


def set_removed(env, env_index: int, triangles) -> None:
    """Remove cloth triangles of one env (as a tool would) and let the cutting system recount."""
    s = env.world.state
    mask = s.tri_active.numpy()
    first = env.cloth_obj.element_start
    mask[env_index, first + np.asarray(triangles, dtype=int)] = 0
    s.tri_active.assign(mask)
    dirty = s.cut_dirty.numpy()
    dirty[env_index] = 1
    s.cut_dirty.assign(dirty)
    env.cutting.refresh()
    recount = env.path.recount.numpy()
    recount[env_index] = 1
    env.path.recount.assign(recount)


def features(env) -> dict[str, float]:
    out = wp.zeros((env.num_envs, len(env.reward_features)), dtype=float, device=env.wp_device)
    env._compute_features(env._all_envs, out)
    return {name: out.numpy()[:, i] for i, name in enumerate(env.reward_features)}


@pytest.mark.parametrize("function", ["line", "sine"])
def test_path_labels_match_sofa_env_rules(device, function):
    env = lapwarp.make("PrecisionCutting", num_envs=1, device=device, path_function=function)
    env.reset()
    ps = env.privileged_state()
    kind = 0 if function == "line" else 1
    shape = ps["path_shape"][0].cpu().numpy().astype(np.float64)
    on_vertex, on_tri, centre, _ = reference_labels(kind, shape)
    np.testing.assert_array_equal(ps["on_vertex"][0].cpu().numpy() != 0, on_vertex)
    np.testing.assert_array_equal(ps["on_tri"][0].cpu().numpy() != 0, on_tri)
    got = ps["centre"][0].cpu().numpy()
    assert got[:len(centre)].tolist() == centre and (got[len(centre):] == -1).all()
    if function == "line":  # the paper's fixed line: 20 centre-line vertices straight up the middle column
        assert centre == [20 + GRID * j for j in range(21)] or centre == [19 + GRID * j for j in range(21)]
    f = features(env)
    assert f["num_tris_on_path"][0] == on_tri.sum() and f["num_tris_off_path"][0] == len(on_tri) - on_tri.sum()
    assert f["cut_ratio"][0] == 0.0 and f["successful_task"][0] == 0.0


def test_cut_ratio_and_cut_counts_follow_removed_triangles(device):
    """cut_ratio = 1 - (countable centre-line vertices with all 6 triangles) / countable; cut counts are the
    triangles removed since the last step, split by label."""
    env = lapwarp.make("PrecisionCutting", num_envs=2, device=device, ratio_to_cut=0.5)
    env.reset()
    ps = env.privileged_state()
    on_tri = ps["on_tri"][0].cpu().numpy() != 0
    centre = [v for v in ps["centre"][0].cpu().numpy() if v >= 0]
    countable = ps["countable"][0].cpu().numpy()[:len(centre)] != 0
    _, _, _, tris = reference_labels(0, ps["path_shape"][0].cpu().numpy().astype(np.float64))
    # cut one triangle at each of the first 7 countable centre-line vertices, plus 3 off-path triangles
    targets = [v for v, c in zip(centre, countable, strict=True) if c][:7]
    removed = [int(np.flatnonzero((tris == v).any(axis=1))[0]) for v in targets]
    off = [int(t) for t in np.flatnonzero(~on_tri)[:3]]
    set_removed(env, 0, removed + off)
    f = features(env)
    total = int(countable.sum())
    assert f["cut_ratio"][0] == pytest.approx(7 / total)
    assert f["cut_on_path"][0] == len(set(removed)) and f["cut_off_path"][0] == 3
    assert f["num_tris_on_path"][0] == on_tri.sum() - len(set(removed))
    assert f["cut_ratio"][1] == 0.0 and f["cut_on_path"][1] == 0.0  # the other env is untouched
    assert f["successful_task"][0] == float(7 / total >= 0.5)
    # half of the countable vertices cut -> success at ratio_to_cut 0.5
    more = [int(np.flatnonzero((tris == v).any(axis=1))[0]) for v, c in zip(centre, countable, strict=True) if c]
    set_removed(env, 0, more)
    assert features(env)["successful_task"][0] == 1.0


def test_reset_restores_the_cloth_and_draws_paths_per_env(device):
    env = lapwarp.make("PrecisionCutting", num_envs=3, device=device, randomize_path=True, path_function="sine",
                       seed=5)
    env.reset()
    shapes = env.privileged_state()["path_shape"].cpu().numpy()
    assert len({tuple(np.round(s, 6)) for s in shapes}) == 3  # every env its own path
    low = np.array([0.01, 0.5 / 0.075, 0.3, 0.5]) - 1e-6
    high = np.array([0.02, 1.5 / 0.075, 0.7, 0.7]) + 1e-6
    assert ((shapes >= low) & (shapes <= high)).all()
    set_removed(env, 1, np.arange(200))
    assert env.privileged_state()["tri_active"][1].sum().item() == env.num_tris - 200
    env.reset()
    assert env.privileged_state()["tri_active"].sum().item() == 3 * env.num_tris
    assert (env.world.state.particle_active.numpy() != 0).all()
    env.reset(seed=5)
    again = env.privileged_state()["path_shape"].cpu().numpy()
    env.reset(seed=5)
    np.testing.assert_array_equal(again, env.privileged_state()["path_shape"].cpu().numpy())


def test_random_lines_stay_on_the_cloth(device):
    """The paper's random line ranges reach 41 mm from the centre; such draws are redrawn, never clipped."""
    env = lapwarp.make("PrecisionCutting", num_envs=64, device=device, randomize_path=True, seed=2)
    env.reset()
    for shape in env.privileged_state()["path_shape"].cpu().numpy().astype(np.float64):
        assert np.abs(path_samples_numpy(0, *shape)[:, 0]).max() <= 0.5 * SIZE + 1e-7


@pytest.mark.parametrize("bad, message", [
    (dict(path_slope=0.5, path_position=0.9), "leaves the cloth"),
    (dict(path_function="sine", path_amplitude=0.035, path_position=0.6), "leaves the cloth"),
    (dict(randomize_path=True, position_range=(0.9, 1.0), slope_range=(0.4, 0.6)), "leaves the cloth"),
    (dict(depth_range=(0.7, 0.5)), "low exceeds high"),
    (dict(path_function="zigzag"), "path_function"),
    (dict(ratio_to_cut=0.0), "ratio_to_cut"),
    (dict(path_depth=1.5), "path_depth"),
    (dict(cut_removal="nearest"), "cut_removal"),
])
def test_invalid_configurations_raise(bad, message):
    with pytest.raises(ValueError, match=message):
        lapwarp.make("PrecisionCutting", num_envs=1, device="cpu", **bad)


def test_blades_cut_only_while_closing_when_asked(device):
    """sofa_env cuts at any jaw angle; ``cut_requires_closing`` cuts only on steps where the jaws close."""
    cuts = {}
    for closing in (False, True):
        env = lapwarp.make("PrecisionCutting", num_envs=1, device=device, ptsd_noise=(0.0, 0.0, 0.0, 0.0),
                           cut_requires_closing=closing)
        env.reset()
        expert = make_expert(env)
        removed = 0.0
        for _ in range(40):  # the expert drives the open scissors into the path (jaws held open)
            action = expert()
            action[:, 4] = 0.0
            _, _, _, extras = env.step(action)
            removed += extras["log"]["/feature/cut_on_path"].item() + extras["log"]["/feature/cut_off_path"].item()
        cuts[closing] = removed
    assert cuts[False] > 0 and cuts[True] == 0


@pytest.mark.parametrize("removal", ["centroid", "vertex"])
@pytest.mark.parametrize("function", ["line", "sine"])
def test_expert_solves_the_fixed_path(device, function, removal):
    """By lapwarp's centroid rule and by sofa_env's vertex rule (``cut_removal``)."""
    env = lapwarp.make("PrecisionCutting", num_envs=4, device=device, seed=3, path_function=function,
                       cut_removal=removal)
    expert = make_expert(env)
    obs = env.get_observations()
    episodes = successes = 0
    for _ in range(200):
        obs, _, done, _ = env.step(expert(obs))
        finished = done.cpu().numpy()
        episodes += int(finished.sum())
        successes += int(env.last_episode_success.numpy()[finished].sum())
        if episodes >= 4:
            break
    assert episodes >= 4 and successes / episodes >= 0.9, f"{successes}/{episodes}"


@pytest.mark.parametrize("function", ["line", "sine"])
def test_discrete_expert_solves_the_fixed_path(device, function):
    """Discrete actions (one PTSD component by one step) solve each env's first episode (the base expert's rule, the
    component with the largest error first, measured 2/8 on the sine, CPU, seed 1)."""
    env = lapwarp.make("PrecisionCutting", num_envs=4, device=device, seed=3, path_function=function,
                       action_type="DISCRETE")
    expert = make_expert(env)
    obs = env.get_observations()
    counted = np.zeros(4, dtype=bool)
    successes = 0
    for _ in range(400):
        obs, _, done, _ = env.step(expert(obs))
        first = done.cpu().numpy().astype(bool) & ~counted
        successes += int(env.last_episode_success.numpy()[first].sum())
        counted |= first
        if counted.all():
            break
    assert counted.all() and successes == 4, f"{successes}/{int(counted.sum())}"


def test_rendering_shows_the_path_and_holes(device):
    env = lapwarp.make("PrecisionCutting", num_envs=1, device=device, observation_type="RGB", image_shape=(48, 48))
    obs, _ = env.reset()
    img = obs["image"][0].float().cpu().numpy() if obs["image"].dtype == torch.uint8 else obs["image"][0].cpu().numpy()
    img = img.reshape(-1, img.shape[-1]) if img.shape[-1] in (3, 4) else img.reshape(img.shape[0], -1).T
    red = (img[:, 0] > 1.5 * img[:, 1]) & (img[:, 0] > 1.5 * img[:, 2])
    assert red.sum() > 0  # the red path is visible
    scene = env.visual_scene()
    canvas = next(o for o in scene.objects if o.name == "cloth").face_active.numpy()
    path = next(o for o in scene.objects if o.name == "cutting_path").face_active.numpy()
    on = env.privileged_state()["on_tri"][0].cpu().numpy() != 0
    np.testing.assert_array_equal(path[0] != 0, on)
    np.testing.assert_array_equal(canvas[0] != 0, ~on)
    set_removed(env, 0, np.flatnonzero(on)[:5])
    env.update_visuals()
    path = next(o for o in scene.objects if o.name == "cutting_path").face_active.numpy()
    assert path[0].sum() == on.sum() - 5


def test_continuous_expert_gives_up_a_target_it_stands_at(device):
    """``expert_continuous_patience``: with the hinge at its goal (no error) and the same target, the 15th step gives
    the target up (``skip`` = its sample + 1); a hinge 5 mm from its goal never does; a new target restarts the count;
    an episode's first step clears ``skip``."""
    from lapwarp.tasks.dissection.precision_cutting import expert_continuous_patience

    n, dev = 2, device
    ptsd = wp.array([[wp.vec4(0.0, 1.3, 0.0, 0.05)]] * n, dtype=wp.vec4, device=dev)
    rcm = wp.array([[wp.transform((0.0, -0.06, 0.01), (0.0, 0.0, 0.0, 1.0))]] * n, dtype=wp.transform, device=dev)
    error = wp.array(np.array([[0.0] * 5, [0.0, 0.0, 0.0, 0.005, 0.0]], dtype=np.float32), dtype=float, device=dev)
    length = wp.array([1, 1], dtype=wp.int32, device=dev)
    target = wp.array([5, 5], dtype=wp.int32, device=dev)
    last, stall, skip = (wp.full(n, v, dtype=wp.int32, device=dev) for v in (5, 0, 0))

    def call(times=1):
        for _ in range(times):
            wp.launch(expert_continuous_patience, dim=n, inputs=[ptsd, rcm, error, length, 15, target],
                      outputs=[last, stall, skip], device=dev)

    call(14)
    assert skip.numpy().tolist() == [0, 0] and stall.numpy().tolist() == [14, 0]
    call()
    assert skip.numpy().tolist() == [6, 0] and stall.numpy()[0] == 0
    target.assign(np.array([7, 7], dtype=np.int32))
    call(14)
    assert skip.numpy().tolist() == [6, 0]  # the new target's count started over
    length.assign(np.array([0, 0], dtype=np.int32))
    call()
    assert skip.numpy().tolist() == [0, 0]
