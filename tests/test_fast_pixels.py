"""``train/fast_pixels.py`` (issue #19): uint8 image storage is exact, the fast encoder computes what rsl-rl's
``CNNModel`` computes, and ``train/ppo.py`` trains with it, with the privileged state critic and writes a video."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest
import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "train"))

import fast_pixels  # noqa: E402
import ppo  # noqa: E402


@pytest.fixture(scope="module")
def rgb_env(device):
    import lapwarp

    return lapwarp.make("Reach", num_envs=3, device=device, seed=2, observation_type="RGB", image_shape=(48, 48))


def test_uint8_images_are_exact_and_forward_the_env(rgb_env):
    wrapped = fast_pixels.Uint8Images(rgb_env)
    float_images = rgb_env.get_observations()["image"]
    images = wrapped.get_observations()["image"]
    assert images.dtype == torch.uint8 and images.shape == float_images.shape
    # the float images are the renderer's bytes / 255: the bytes come back exactly (no information lost)
    assert (images.float() / 255.0 - float_images).abs().max() < 1e-6
    obs, rewards, dones, extras = wrapped.step(torch.zeros(3, rgb_env.num_actions, device=rgb_env.device))
    assert obs["image"].dtype == torch.uint8 and rewards.shape == (3,)
    wrapped.episode_length_buf = torch.full((3,), 7)
    assert rgb_env.episode_length_buf.tolist() == [7, 7, 7]
    assert wrapped.num_envs == 3 and wrapped.max_episode_length == rgb_env.max_episode_length


def test_uint8_images_refuse_depth(device):
    import lapwarp

    env = lapwarp.make("Reach", num_envs=1, device=device, observation_type="RGBD", image_shape=(16, 16))
    with pytest.raises(ValueError, match="only for RGB"):
        fast_pixels.Uint8Images(env)


def test_fast_model_matches_rsl_rl_cnn_model(rgb_env):
    from rsl_rl.models import CNNModel

    obs = rgb_env.get_observations()
    cfg = ppo.use_images(ppo.preset_config("gpu", 3, 1)[0])["actor"]
    kwargs = {k: v for k, v in cfg.items() if k != "class_name"}
    torch.manual_seed(0)
    reference = CNNModel(obs, cfg_groups := {"actor": ["image"], "critic": ["image"]}, "actor", 3, **kwargs)
    fast = fast_pixels.FastCNNModel(obs, cfg_groups, "actor", 3, autocast_bf16=False, **kwargs)
    fast.load_state_dict(reference.state_dict())
    uint8_obs = fast_pixels.Uint8Images(rgb_env).get_observations()
    with torch.no_grad():
        expected = reference(obs.cpu())
        assert torch.allclose(fast(obs.cpu()), expected, atol=1e-5)
        assert torch.allclose(fast(uint8_obs.cpu()), expected, atol=1e-5)
        if torch.cuda.is_available():  # bf16 tensor-core encoders: close, not equal
            fast_cuda = fast_pixels.FastCNNModel(obs, cfg_groups, "actor", 3, **kwargs).cuda()
            fast_cuda.load_state_dict(reference.state_dict())
            assert torch.allclose(fast_cuda(uint8_obs.cuda()).cpu(), expected, atol=0.05)


def test_ppo_trains_fast_pixels_with_state_critic_and_writes_a_video(device, tmp_path, capsys):
    imageio = pytest.importorskip("imageio.v3")
    pytest.importorskip("imageio_ffmpeg")
    video = tmp_path / "play.mp4"
    args = ["--device", device, "--preset", "cpu", "--task", "Reach", "--obs", "rgb", "--fast-pixels",
            "--critic", "state", "--set", "image_shape=[48,48]", "max_episode_steps=6", "--num-envs", "4",
            "--max-iterations", "2", "--eval-envs", "4", "--log-dir", str(tmp_path), "--video", str(video),
            "--video-envs", "2"]
    assert ppo.main(args) == 0
    out = capsys.readouterr().out
    assert "evaluation on 4 episodes" in out and f"video: {video} (6 frames, 2 envs)" in out
    frames = imageio.imread(video)
    assert frames.shape[0] == 6 and frames.shape[-1] == 3
    checkpoint = sorted(tmp_path.rglob("model_*.pt"))[-1]
    state = torch.load(checkpoint, map_location="cpu", weights_only=False)
    assert any("cnns" in k for k in state["actor_state_dict"]) and not any("cnns" in k
                                                                          for k in state["critic_state_dict"])


@pytest.mark.parametrize("bad, message", [
    (["--fast-pixels"], "apply to image observations"),
    (["--obs", "rgbd", "--fast-pixels"], "exact only for --obs rgb"),
    (["--obs", "rgb", "--video", "x.gif"], "--video writes an .mp4"),
])
def test_ppo_rejects_inconsistent_pixel_options(bad, message, capsys):
    with pytest.raises(SystemExit):
        ppo.main(["--device", "cpu", *bad])
    assert message in capsys.readouterr().err
