"""Reach image observations (RGB / RGBD / DEPTH through the batched rasteriser), checked against projections."""

from __future__ import annotations

import math

import gymnasium as gym
import numpy as np
import pytest
import torch
from gymnasium.utils.env_checker import check_env

import lapwarp

CAMERA = np.array([0.0, 0.07, 0.55])  # ReachConfig.camera_position, looking along -Z with +Y up
FOV_DEG = 42.0


def project(points: np.ndarray, height: int, width: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Pinhole projection with the vertical FoV: (row, col, depth along the view axis)."""
    rel = points - CAMERA
    depth = -rel[:, 2]
    focal = 0.5 * height / math.tan(math.radians(FOV_DEG) / 2)
    col = 0.5 * width + focal * rel[:, 0] / depth
    row = 0.5 * height - focal * rel[:, 1] / depth
    return row, col, depth


@pytest.mark.parametrize("obs_type, channels", [("RGB", 3), ("RGBD", 4), ("DEPTH", 1)])
def test_image_observation_shapes(device, obs_type, channels):
    env = lapwarp.make("Reach", num_envs=2, device=device, observation_type=obs_type, frame_stack=2,
                       image_shape=(32, 48))
    obs = env.get_observations()
    assert set(obs.keys()) == {"image"} and env.policy_group == "image"
    assert obs["image"].shape == (2, 2 * channels, 32, 48) and obs["image"].dtype == torch.float32
    assert float(obs["image"].min()) >= 0.0 and float(obs["image"].max()) <= 1.0
    out, _, _, _ = env.step(torch.zeros(2, 3, device=env.device))
    assert out["image"].shape == (2, 2 * channels, 32, 48)


def test_target_and_end_effector_appear_where_they_project(device):
    size = 64
    env = lapwarp.make("Reach", num_envs=3, device=device, observation_type="RGBD", sphere_radius=0.02,
                       image_shape=(size, size))
    image = env.get_observations()["image"].cpu().numpy()
    ee, target = env.ee_position.numpy(), env.target_position.numpy()
    checked = 0
    for env_id in range(3):
        for pos, is_target in ((target[env_id], True), (ee[env_id], False)):
            row, col, depth = project(pos[None].astype(np.float64), size, size)
            r, c = int(row[0]), int(col[0])
            if not (2 <= r < size - 2 and 2 <= c < size - 2):
                continue  # outside the view
            others = ee[env_id] if is_target else target[env_id]
            if np.linalg.norm((others - pos)[:2]) < 0.05:
                continue  # the other sphere may overlap on screen
            red, green, blue, d = image[env_id, :, r, c]
            if is_target:
                assert green > 0.3 and green > 2 * red and green > 2 * blue  # the green target
            else:
                assert abs(red - green) < 0.05 and abs(green - blue) < 0.1 and red > 0.3  # the grey sphere
            # depth channel = metric depth / far (2 m); the sphere's front surface is ~radius nearer
            assert d * 2.0 == pytest.approx(depth[0] - 0.02, abs=0.004)
            checked += 1
    assert checked >= 2


def test_image_changes_when_the_end_effector_moves(device):
    env = lapwarp.make("Reach", num_envs=1, device=device, observation_type="RGB", sphere_radius=0.02)
    before = env.get_observations()["image"].clone()
    after = env.step(torch.ones(1, 3, device=env.device))[0]["image"]
    assert (after - before).abs().sum() > 1.0


def test_gymnasium_checker_with_rgb_observations(device):
    env = gym.make("lapwarp/Reach-v0", device=device, observation_type="RGB", image_shape=(32, 32))
    check_env(env.unwrapped, skip_render_check=True)
    assert env.observation_space.shape == (3, 32, 32)


def test_render_rgb_for_people(device, tmp_path):
    from lapwarp.imaging import save_image_grid

    env = lapwarp.make("Reach", num_envs=4, device=device)  # STATE observations: rendering is on demand
    images = env.render_rgb(width=48, height=40)
    assert images.shape == (4, 3, 40, 48) and images.dtype == torch.uint8
    assert images.float().std() > 1.0  # not a blank image
    save_image_grid(images, tmp_path / "grid.png")
    assert (tmp_path / "grid.png").stat().st_size > 100


def test_gymnasium_rgb_array_render(device):
    env = gym.make("lapwarp/Reach-v0", device=device, render_mode="rgb_array", render_size=40, sphere_radius=0.02)
    env.reset(seed=0)
    frame = env.render()
    assert frame.shape == (40, 40, 3) and frame.dtype == np.uint8 and frame.std() > 1.0
    check_env(env.unwrapped)  # render check included
