"""``train/fast_pixels.py`` (issue #19): uint8 image storage is exact, the fast encoder computes what rsl-rl's
``CNNModel`` computes, a shared encoder runs once per batch with the values and gradients of two separate calls, and
``train/ppo.py`` trains with it, with the privileged state critic and writes a video."""

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


def test_fast_model_matches_rsl_rl_cnn_model_with_proprioception(device):
    """With the ``proprio`` group beside the image (``ppo.py --proprio``) the fast model still computes rsl-rl's
    ``CNNModel``: the 1-D group joins the encoder's features before the MLP, and uint8 storage leaves it as it is."""
    from rsl_rl.models import CNNModel

    import lapwarp

    env = lapwarp.make("DeflectSpheres", num_envs=3, device=device, seed=2, observation_type="RGB",
                       image_shape=(48, 48), proprioception=True, single_instrument=False)
    obs = env.get_observations()
    cfg = ppo.use_images(ppo.preset_config("gpu", 3, 1)[0])["actor"]
    kwargs = {k: v for k, v in cfg.items() if k != "class_name"}
    groups = {"actor": ["image", "proprio"], "critic": ["image", "proprio"]}
    torch.manual_seed(0)
    reference = CNNModel(obs, groups, "actor", 5, **kwargs)
    fast = fast_pixels.FastCNNModel(obs, groups, "actor", 5, autocast_bf16=False, **kwargs)
    fast.load_state_dict(reference.state_dict())
    uint8_obs = fast_pixels.Uint8Images(env).get_observations()
    assert torch.equal(uint8_obs["proprio"], obs["proprio"])
    with torch.no_grad():
        expected = reference(obs.cpu())
        assert torch.allclose(fast(uint8_obs.cpu()), expected, atol=1e-5)
        moved = obs.cpu().clone()
        moved["proprio"] = moved["proprio"] + 0.5  # the group reaches the output
        assert not torch.allclose(reference(moved), expected, atol=1e-5)


@pytest.mark.parametrize("size, kernel, stride", [((64, 64), 8, 4), ((50, 47), 8, 4), ((8, 8), 8, 4),
                                                  ((13, 16), 4, 2), ((12, 9), (6, 3), (3, 3))])
def test_space_to_depth_conv_is_the_strided_convolution(size, kernel, stride):
    torch.manual_seed(1)
    conv = torch.nn.Conv2d(3, 5, kernel, stride)
    stem = fast_pixels.SpaceToDepthConv(conv)
    assert stem.weight is conv.weight and stem.bias is conv.bias and list(stem.state_dict()) == ["weight", "bias"]
    pixels = torch.randint(0, 256, (2, 3, *size), dtype=torch.uint8)
    # uint8 pixels are scaled by 1/255 (through the weight); float images are taken as they are
    expected = conv(pixels.float() / 255.0)
    with torch.no_grad():
        images = torch.rand(2, 3, *size)
        assert torch.allclose(stem(images), conv(images), atol=1e-5)
    got = stem(pixels)
    assert got.shape == expected.shape and got.dtype == torch.float32
    assert torch.allclose(got, expected, atol=1e-5)
    # the same gradients for the shared weight and bias
    grad_out = torch.randn(expected.shape)
    wb = torch.autograd.grad((expected * grad_out).sum(), (conv.weight, conv.bias))
    got_wb = torch.autograd.grad((got * grad_out).sum(), (conv.weight, conv.bias))
    for reference, value in zip(wb, got_wb, strict=True):
        assert torch.allclose(reference, value, atol=1e-4, rtol=1e-4)
    # channels-last parameters (FastCNNModel's memory order) change nothing
    stem.to(memory_format=torch.channels_last)
    assert torch.allclose(stem(pixels), expected, atol=1e-5)


def test_space_to_depth_conv_refuses_what_it_cannot_compute():
    for conv in (torch.nn.Conv2d(3, 4, 3, 1), torch.nn.Conv2d(3, 4, 8, 4, padding=1), torch.nn.Conv2d(3, 4, 7, 4),
                 torch.nn.Conv2d(3, 4, 8, 4, dilation=2), torch.nn.Conv2d(4, 4, 8, 4, groups=2)):
        assert not fast_pixels.SpaceToDepthConv.applies_to(conv)
        with pytest.raises(ValueError, match="not a space-to-depth"):
            fast_pixels.SpaceToDepthConv(conv)
    with pytest.raises(ValueError, match="smaller than the 8x8 kernel"):
        fast_pixels.SpaceToDepthConv(torch.nn.Conv2d(3, 4, 8, 4))(torch.zeros(1, 3, 7, 9))


def test_fast_model_first_conv_option_keeps_rsl_rl_parameters(rgb_env):
    from rsl_rl.models import CNNModel

    obs = rgb_env.get_observations()
    cfg = ppo.use_images(ppo.preset_config("gpu", 3, 1)[0])["actor"]
    kwargs = {k: v for k, v in cfg.items() if k != "class_name"}
    groups = {"actor": ["image"], "critic": ["image"]}
    reference = CNNModel(obs, groups, "actor", 3, **kwargs)
    blocks = fast_pixels.FastCNNModel(obs, groups, "actor", 3, autocast_bf16=False, **kwargs)
    direct = fast_pixels.FastCNNModel(obs, groups, "actor", 3, autocast_bf16=False, space_to_depth=False, **kwargs)
    assert isinstance(blocks.cnns["image"][0], fast_pixels.SpaceToDepthConv)
    assert type(direct.cnns["image"][0]) is torch.nn.Conv2d
    shapes = {k: v.shape for k, v in reference.state_dict().items()}
    for model in (blocks, direct):  # checkpoints load either way
        assert {k: v.shape for k, v in model.state_dict().items()} == shapes
    direct.load_state_dict(blocks.state_dict())
    uint8_obs = fast_pixels.Uint8Images(rgb_env).get_observations().cpu()
    with torch.no_grad():
        assert torch.allclose(blocks(uint8_obs), direct(uint8_obs), atol=1e-5)
    cfg_fast = fast_pixels.use_fast_pixels(ppo.use_images(ppo.preset_config("gpu", 3, 1)[0]), space_to_depth=False)
    assert cfg_fast["actor"]["space_to_depth"] is False and cfg_fast["actor"]["class_name"] is fast_pixels.FastCNNModel


def test_shared_encoder_models_run_under_torch_compile(rgb_env):
    """``--compile``: torch.compile traced into the latent cache's version counters and failed on the rollout's
    inference tensors (H100); the cache's bookkeeping now runs outside the compiled graph. The eager backend traces
    with TorchDynamo as the real one does, without a C++ compiler."""
    obs = fast_pixels.Uint8Images(rgb_env).get_observations().cpu()
    actor, critic, calls = _shared_models(obs)
    with torch.no_grad():
        expected = actor(obs), critic(obs)
    compiled_actor, compiled_critic = (torch.compile(m, backend="eager") for m in (actor, critic))
    with torch.inference_mode():
        fresh = fast_pixels.Uint8Images(rgb_env).get_observations().cpu()
        n = len(calls)
        got = compiled_actor(fresh), compiled_critic(fresh)
        assert len(calls) == n + 1  # still one encoder run for the two models
    for e, g in zip(expected, got, strict=True):
        assert torch.allclose(e, g, atol=1e-5)
    a, c = compiled_actor(obs), compiled_critic(obs)  # and with gradients (the update's mini-batches)
    (a.sum() + c.sum()).backward()
    assert all(p.grad is not None for p in actor.cnns.parameters())


def _shared_models(obs, train_shared_encoder=False):
    cfg = ppo.use_images(ppo.preset_config("gpu", 3, 1)[0])
    groups = {"actor": ["image"], "critic": ["image"]}
    kwargs = {role: {k: v for k, v in cfg[role].items() if k != "class_name"} for role in ("actor", "critic")}
    torch.manual_seed(0)
    actor = fast_pixels.FastCNNModel(obs, groups, "actor", 3, autocast_bf16=False, **kwargs["actor"])
    critic = fast_pixels.FastCNNModel(obs, groups, "critic", 1, autocast_bf16=False, cnns=actor.cnns,
                                      train_shared_encoder=train_shared_encoder, **kwargs["critic"])
    calls = []
    actor.cnns["image"].register_forward_hook(lambda *_: calls.append(1))
    return actor, critic, calls


def test_shared_encoder_is_trained_by_the_actor_only(rgb_env):
    obs = fast_pixels.Uint8Images(rgb_env).get_observations().cpu()
    actor, critic, calls = _shared_models(obs, train_shared_encoder=False)
    a, c = actor(obs), critic(obs)
    assert len(calls) == 1
    (a.sum() + 3.0 * c.sum()).backward()
    encoder_grads = [p.grad.clone() for p in actor.cnns.parameters()]
    head_grads = [p.grad for name, p in critic.named_parameters() if not name.startswith("cnns.")]
    assert head_grads and all(g is not None and g.abs().sum() > 0 for g in head_grads)  # the critic's head learns
    actor.zero_grad()
    critic.zero_grad()
    actor(obs).sum().backward()  # the policy's loss alone gives the encoder the same gradient
    for g, p in zip(encoder_grads, actor.cnns.parameters(), strict=True):
        assert torch.allclose(g, p.grad, atol=1e-6, rtol=1e-5)
    assert any(g.abs().sum() > 0 for g in encoder_grads)


def test_shared_encoder_runs_once_with_the_values_and_gradients_of_two_calls(rgb_env):
    obs = fast_pixels.Uint8Images(rgb_env).get_observations().cpu()
    actor, critic, calls = _shared_models(obs, train_shared_encoder=True)
    assert critic.cnns is actor.cnns
    cache = actor.cnns.latent_cache
    # actor then critic on one observation (rsl-rl's act and every update mini-batch): one encoder run
    a, c = actor(obs), critic(obs)
    assert len(calls) == 1
    (a.sum() + 3.0 * c.sum()).backward()
    cached_grads = [p.grad.clone() for p in actor.cnns.parameters()]
    # the same without the cache: two runs, the same outputs and the same (summed) encoder gradients
    actor.zero_grad()
    critic.zero_grad()
    del actor.cnns.latent_cache
    a2, c2 = actor(obs), critic(obs)
    assert len(calls) == 3
    assert torch.allclose(a, a2) and torch.allclose(c, c2)
    (a2.sum() + 3.0 * c2.sum()).backward()
    for g, p in zip(cached_grads, actor.cnns.parameters(), strict=True):
        assert torch.allclose(g, p.grad, atol=1e-6, rtol=1e-5)
    actor.cnns.latent_cache = cache
    # what must recompute: a parameter changed in place between the calls (an optimizer step), another observation
    # tensor, the same model twice (the critic alone in compute_returns), another grad mode; an entry is taken once
    def runs(call):
        n = len(calls)
        call()
        return len(calls) - n

    assert runs(lambda: actor(obs)) == 1
    with torch.no_grad():
        next(actor.cnns.parameters()).add_(0.01)
    assert runs(lambda: critic(obs)) == 1  # the actor's entry is stale
    assert runs(lambda: actor(obs)) == 0  # the critic's is not (either model may come first)
    assert runs(lambda: critic(obs)) == 1  # taken already
    assert runs(lambda: actor(obs.clone())) == 1
    assert runs(lambda: critic(obs)) == 1
    assert runs(lambda: critic(obs)) == 1
    with torch.no_grad():
        assert runs(lambda: actor(obs)) == 1
    count = len(calls)
    # inference mode (rsl-rl's rollout): the images are inference tensors without a version counter; one run
    with torch.inference_mode():
        fresh = fast_pixels.Uint8Images(rgb_env).get_observations().cpu()
        actor(fresh), critic(fresh)
    assert len(calls) == count + 1


def test_shared_encoder_belongs_to_the_actor_alone(rgb_env):
    from itertools import chain

    obs = fast_pixels.Uint8Images(rgb_env).get_observations().cpu()
    actor, critic, _ = _shared_models(obs)
    encoder = {id(p) for p in actor.cnns.parameters()}
    assert encoder and encoder <= {id(p) for p in actor.parameters()}
    assert not encoder & {id(p) for p in critic.parameters()}  # rsl-rl's optimizer chain holds each once
    assert not any(k.startswith("cnns.") for k in critic.state_dict())
    params = list(chain(actor.parameters(), critic.parameters()))
    assert len(params) == len({id(p) for p in params})
    # rsl-rl clips the critic's gradient norm on its own: a large value loss must not shrink the encoder's gradient
    (actor(obs).sum() + 1.0e4 * critic(obs).sum()).backward()
    encoder_grads = [p.grad.clone() for p in actor.cnns.parameters()]
    torch.nn.utils.clip_grad_norm_(critic.parameters(), 1.0)
    for g, p in zip(encoder_grads, actor.cnns.parameters(), strict=True):
        assert torch.equal(g, p.grad)


def test_ppo_trains_a_shared_encoder(device, tmp_path, capsys):
    args = ["--device", device, "--preset", "cpu", "--task", "Reach", "--obs", "rgb", "--fast-pixels",
            "--shared-encoder", "--set", "image_shape=[48,48]", "max_episode_steps=6", "--num-envs", "4",
            "--max-iterations", "2", "--eval-envs", "4", "--log-dir", str(tmp_path)]
    assert ppo.main(args) == 0
    assert "evaluation on 4 episodes" in capsys.readouterr().out
    state = torch.load(sorted(tmp_path.rglob("model_*.pt"))[-1], map_location="cpu", weights_only=False)
    assert any("cnns" in k for k in state["actor_state_dict"])
    assert not any("cnns" in k for k in state["critic_state_dict"])  # the actor's, borrowed by the critic
    groups = state["optimizer_state_dict"]["param_groups"]
    assert len(groups) == 1 and len(groups[0]["params"]) == len(state["optimizer_state_dict"]["state"])


def test_ppo_trains_fast_pixels_on_stacked_frames(device, tmp_path, capsys):
    """The paper's 4 stacked frames: 12 uint8 channels through the block convolution."""
    args = ["--device", device, "--preset", "cpu", "--task", "Reach", "--obs", "rgb", "--fast-pixels",
            "--shared-encoder", "--set", "image_shape=[48,48]", "frame_stack=4", "max_episode_steps=6",
            "--num-envs", "4", "--max-iterations", "2", "--eval-envs", "4", "--log-dir", str(tmp_path)]
    assert ppo.main(args) == 0
    assert "evaluation on 4 episodes" in capsys.readouterr().out
    state = torch.load(sorted(tmp_path.rglob("model_*.pt"))[-1], map_location="cpu", weights_only=False)
    assert state["actor_state_dict"]["cnns.image.0.weight"].shape == (32, 12, 8, 8)


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
    (["--fast-pixels"], "applies to image observations"),
    (["--obs", "rgbd", "--fast-pixels"], "exact only for --obs rgb"),
    (["--obs", "rgb", "--video", "x.gif"], "--video writes an .mp4"),
    (["--obs", "rgb", "--shared-encoder"], "--shared-encoder needs --fast-pixels"),
    (["--obs", "rgb", "--fast-pixels", "--critic", "state", "--shared-encoder"], "--shared-encoder needs"),
    (["--obs", "rgb", "--first-conv", "direct"], "--first-conv applies to the --fast-pixels"),
])
def test_ppo_rejects_inconsistent_pixel_options(bad, message, capsys):
    with pytest.raises(SystemExit):
        ppo.main(["--device", "cpu", *bad])
    assert message in capsys.readouterr().err
