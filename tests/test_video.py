"""Rollout videos (lapwarp.video, ``lapwarp run --video``) and the Pillow-backed PNG helpers (lapwarp.imaging).

Small and fast on the CPU: a few envs, 64-pixel tiles, a handful of steps. Videos are read back with imageio.
"""

from __future__ import annotations

import re
import sys

import numpy as np
import pytest
import torch

import lapwarp
from lapwarp import cli
from lapwarp.imaging import image_grid, read_png, write_png

TILE = 64
STEPS = 5


def read_frames(path) -> list[np.ndarray]:
    iio = pytest.importorskip("imageio.v2")
    reader = iio.get_reader(path, format="FFMPEG")
    try:
        return [np.asarray(frame) for frame in reader]
    finally:
        reader.close()


def grid_shape(num_tiles: int, size: int) -> tuple[int, int]:
    """(H, W) of the frame the writer makes from ``num_tiles`` square tiles (even sizes need no extra padding)."""
    from lapwarp.video import PAD

    grid = image_grid(np.zeros((num_tiles, 3, size, size), np.uint8), pad=PAD)
    return grid.shape[0], grid.shape[1]


@pytest.fixture
def video_module():
    pytest.importorskip("imageio")
    pytest.importorskip("imageio_ffmpeg")
    pytest.importorskip("PIL")
    import lapwarp.video

    return lapwarp.video


def test_record_video_of_reach(video_module, device, tmp_path):
    env = lapwarp.make("Reach", num_envs=4, device=device, seed=0)
    gen = torch.Generator(device=env.device).manual_seed(0)

    def policy(obs):
        return torch.rand((env.num_envs, env.num_actions), device=env.device, generator=gen) * 2.0 - 1.0

    path = tmp_path / "reach.mp4"
    frames = video_module.record_video(env, policy, path, STEPS, tile_size=TILE)
    assert frames == STEPS
    video = read_frames(path)
    assert len(video) == STEPS
    assert video[0].shape == (*grid_shape(4, TILE), 3)  # 2 x 2 tiles of 64 pixels
    assert video[0].max() > 100  # the scene and labels were drawn, not only the background
    assert video_module.video_fps(env.dt) == min(30, max(1, round(1 / env.dt)))
    env.close()


def test_success_tiles_are_marked(video_module, tmp_path):
    path = tmp_path / "synthetic.mp4"
    images = np.full((5, 3, TILE, TILE), 100, np.uint8)  # five identical grey envs
    with video_module.GridVideoWriter(path, fps=10, tile_size=TILE, max_tiles=2) as writer:
        for _ in range(3):
            writer.add_frame(torch.from_numpy(images), np.array([1, 0, 1, 0, 0]), np.array([1.5, -2.0, 0, 0, 0]))
        assert writer.num_tiles == 2
    assert writer.close() == 3  # closing twice is fine and keeps the count
    video = read_frames(path)
    assert len(video) == 3
    assert video[0].shape == (*grid_shape(2, TILE), 3)  # only the first max_tiles envs are tiled

    frame = video[-1].astype(np.int32)
    pad = video_module.PAD
    rows = slice(pad + TILE // 4, pad + 3 * TILE // 4)  # away from the label at the top and "success" at the bottom

    def right_edge(tile: int) -> np.ndarray:
        x = pad + tile * (TILE + pad) + TILE - 2
        return frame[rows, x : x + 2].reshape(-1, 3).mean(0)

    success, plain = right_edge(0), right_edge(1)
    assert success[1] > 150 and success[1] - success[0] > 80  # green border on env 0
    assert np.all(np.abs(plain - 100) < 12)  # env 1 keeps its grey pixels there
    # The labels differ from the plain image: text was drawn in the top left corner of each tile.
    label = frame[pad + 2 : pad + 10, pad + TILE + pad + 2 : pad + TILE + pad + 30]
    assert np.abs(label - 100).max() > 60


def test_writer_validation(video_module, tmp_path):
    writer_cls = video_module.GridVideoWriter
    with pytest.raises(ValueError, match=r"\.mp4"):
        writer_cls(tmp_path / "video.avi", fps=10)
    with pytest.raises(ValueError, match="fps"):
        writer_cls(tmp_path / "v.mp4", fps=0)
    with pytest.raises(ValueError, match="max_tiles"):
        writer_cls(tmp_path / "v.mp4", fps=10, max_tiles=0)
    with pytest.raises(ValueError, match="does not exist"):
        writer_cls(tmp_path / "missing" / "v.mp4", fps=10)
    images = np.zeros((2, 3, 16, 16), np.uint8)
    with writer_cls(tmp_path / "v.mp4", fps=5, tile_size=16) as writer:
        with pytest.raises(ValueError, match="uint8"):
            writer.add_frame(images.astype(np.float32), np.zeros(2), np.zeros(2))
        with pytest.raises(ValueError, match="success"):
            writer.add_frame(images, np.zeros(3), np.zeros(2))
        writer.add_frame(images, np.zeros(2, bool), np.zeros(2))
        with pytest.raises(ValueError, match="first frame"):
            writer.add_frame(np.zeros((2, 3, 16, 24), np.uint8), np.zeros(2), np.zeros(2))
        with pytest.raises(ValueError, match="first frame"):
            writer.add_frame(np.zeros((3, 3, 16, 16), np.uint8), np.zeros(3), np.zeros(3))
    with pytest.raises(RuntimeError, match="closed"):
        writer.add_frame(images, np.zeros(2), np.zeros(2))
    assert len(read_frames(tmp_path / "v.mp4")) == 1


def test_cli_run_writes_a_video(video_module, capsys, device, tmp_path):
    path = tmp_path / "run.mp4"
    status = cli.main(["run", "Reach", "--num-envs", "4", "--steps", "3", "--device", device, "--video", str(path),
                       "--image-size", str(TILE), "--no-progress"])
    out, err = capsys.readouterr()
    assert status == 0, err
    row = next(line for line in out.splitlines() if line.startswith("video"))
    assert str(path) in row and "3 frames" in row and "4 envs tiled" in row
    video = read_frames(path)
    assert len(video) == 3 and video[0].shape == (*grid_shape(4, TILE), 3)

    status = cli.main(["run", "Reach", "--steps", "1", "--video", str(tmp_path / "run.gif")])
    assert status == 2 and "ending in .mp4" in capsys.readouterr().err


def test_missing_extra_gives_install_hint(monkeypatch, capsys, tmp_path):
    import lapwarp.video

    pytest.importorskip("PIL")
    png = tmp_path / "a.png"
    write_png(png, np.zeros((2, 2), np.uint8))
    monkeypatch.setitem(sys.modules, "imageio", None)  # makes "import imageio" raise ImportError
    monkeypatch.setitem(sys.modules, "imageio.v2", None)
    hint = re.escape('pip install "lapwarp[video]"')
    with pytest.raises(ImportError, match=hint):
        lapwarp.video.GridVideoWriter(tmp_path / "v.mp4", fps=10)
    status = cli.main(["run", "Reach", "--steps", "1", "--video", str(tmp_path / "v.mp4")])
    err = capsys.readouterr().err
    assert status == 1 and "lapwarp[video]" in err and "Traceback" not in err
    assert not (tmp_path / "v.mp4").exists()

    monkeypatch.setitem(sys.modules, "PIL", None)
    with pytest.raises(ImportError, match=hint):
        write_png(tmp_path / "b.png", np.zeros((2, 2), np.uint8))
    with pytest.raises(ImportError, match=hint):
        read_png(png)
    status = cli.main(["run", "Reach", "--steps", "1", "--save-images", str(tmp_path / "g.png")])
    err = capsys.readouterr().err
    assert status == 1 and "lapwarp[video]" in err and not (tmp_path / "g.png").exists()


@pytest.mark.parametrize("shape", [(6, 5), (6, 5, 1), (6, 5, 2), (6, 5, 3), (6, 5, 4)])
def test_png_round_trip_with_pillow(tmp_path, shape):
    image_module = pytest.importorskip("PIL.Image")
    rng = np.random.default_rng(1)
    img = rng.integers(0, 256, size=shape, dtype=np.uint8)
    path = tmp_path / "x.png"
    write_png(path, torch.from_numpy(img))
    back = read_png(path)
    assert back.dtype == np.uint8 and back.shape == (6, 5, shape[2] if len(shape) == 3 else 1)
    assert np.array_equal(back, img.reshape(back.shape))
    with image_module.open(path) as im:  # a standard PNG, readable by other decoders
        assert im.format == "PNG" and im.size == (5, 6)


def test_png_errors_and_palette_files(tmp_path):
    image_module = pytest.importorskip("PIL.Image")
    with pytest.raises(ValueError, match="uint8"):
        write_png(tmp_path / "f.png", np.zeros((2, 2), np.float32))
    with pytest.raises(ValueError, match=r"\(H, W\)"):
        write_png(tmp_path / "f.png", np.zeros((2, 2, 5), np.uint8))
    (tmp_path / "t.png").write_text("not an image")
    with pytest.raises(ValueError, match="not a PNG"):
        read_png(tmp_path / "t.png")
    rgb = np.zeros((4, 4, 3), np.uint8)
    rgb[1:3, 1:3] = (200, 30, 10)
    palette = image_module.fromarray(rgb).convert("P", palette=image_module.Palette.ADAPTIVE, colors=2)
    palette.save(tmp_path / "p.png")  # a palette PNG comes back as RGB
    assert np.array_equal(read_png(tmp_path / "p.png"), rgb)
    image_module.fromarray(np.full((3, 3), 1000, np.uint16)).save(tmp_path / "i16.png")
    with pytest.raises(ValueError, match="8-bit"):
        read_png(tmp_path / "i16.png")
