"""MP4 videos of rollouts: per-env images tiled into one frame per env step, each tile labelled.

This module owns video output (``lapwarp run --video``):

* :class:`GridVideoWriter` tiles the first ``max_tiles`` images of a batch (``env.render_rgb()``) into one grid per
  frame (:func:`lapwarp.imaging.image_grid`), writes the env index and running return on every tile and a green
  border and ``success`` on the tiles of envs that succeeded in that step (Pillow's default font), and encodes
  H.264 MP4 through imageio / imageio-ffmpeg.
* :class:`EnvVideoRecorder` keeps the per-env running returns and reads the success flags of an env, one frame per
  :meth:`EnvVideoRecorder.add_step`; the CLI's run loop uses it.
* :func:`record_video` steps an env with a policy and records every step.

Needs the ``video`` extra: ``pip install "lapwarp[video]"`` (imageio, imageio-ffmpeg, Pillow), imported when a
writer is made. Frames are copied to the host, so recording is for looking at policies, not for training loops.
"""

from __future__ import annotations

import math
import os
from pathlib import Path
from typing import Any

import numpy as np

from lapwarp.imaging import INSTALL_HINT, _to_numpy, image_grid
from lapwarp.output_paths import check_output_path

__all__ = ["EnvVideoRecorder", "GridVideoWriter", "record_video", "video_fps"]

PAD = 2  # pixels between tiles (and around the grid); even, so even tile sizes give even frame sizes
PAD_VALUE = 0
SUCCESS_COLOR = (40, 220, 60)
TEXT_COLOR = (255, 255, 255)
LABEL_BACKGROUND = (0, 0, 0)
MAX_FPS = 30


def _video_modules() -> tuple[Any, Any, Any, Any]:
    """``imageio.v2``, ``PIL.Image``, ``PIL.ImageDraw``, ``PIL.ImageFont``; ImportError with the install hint."""
    try:
        import imageio.v2 as iio
        import imageio_ffmpeg  # noqa: F401  (the FFMPEG plugin's ffmpeg binary)
        from PIL import Image, ImageDraw, ImageFont
    except ImportError as exc:
        raise ImportError(f"writing videos needs imageio, imageio-ffmpeg and Pillow ({exc}): {INSTALL_HINT}") from exc
    return iio, Image, ImageDraw, ImageFont


def check_video_support() -> None:
    """Raise ImportError (with the install hint) unless videos can be written; for callers that check up front."""
    _video_modules()


def video_fps(dt: float) -> int:
    """Frames per second of a video with one frame per env step of ``dt`` simulated seconds: real time, clamped
    to 1..30."""
    if not (dt > 0 and math.isfinite(dt)):
        return MAX_FPS
    return int(min(MAX_FPS, max(1, round(1.0 / dt))))


class GridVideoWriter:
    """Writes an MP4 with one grid of labelled per-env tiles per frame.

    Args:
        path: output file; must end in ``.mp4`` and its folder must exist.
        fps: frames per second (> 0).
        tile_size: height of a tile in pixels; images of another height are resized (keeping the aspect ratio).
        max_tiles: only the first ``max_tiles`` envs of each batch are tiled.

    Frames are ``ceil(sqrt(n))`` tiles wide (``n`` tiles), separated and surrounded by ``PAD`` black pixels, plus one
    more row / column of padding where needed to make the size even (H.264 with yuv420p needs even sizes). The file is
    opened at the first frame: a writer closed without frames writes nothing.

    Raises:
        ValueError: bad suffix, folder or settings; ``add_frame`` with shapes unlike the first frame's.
        ImportError: imageio, imageio-ffmpeg or Pillow missing.
    """

    def __init__(self, path: str | os.PathLike, fps: float, tile_size: int = 256, max_tiles: int = 16):
        path = Path(path)
        if path.suffix.lower() != ".mp4":
            raise ValueError(f"video path must end in .mp4, got {str(path)!r}")
        try:
            fps = float(fps)
        except (TypeError, ValueError):
            raise ValueError(f"fps must be a positive number, got {fps!r}") from None
        if not (fps > 0 and math.isfinite(fps)):
            raise ValueError(f"fps must be a positive number, got {fps!r}")
        for name, value in (("tile_size", tile_size), ("max_tiles", max_tiles)):
            if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 1:
                raise ValueError(f"{name} must be a positive integer, got {value!r}")
        self._iio, self._image, self._draw, font_module = _video_modules()
        self.path = check_output_path(path, "video path")
        self.fps = fps
        self.tile_size = int(tile_size)
        self.max_tiles = int(max_tiles)
        self.num_frames = 0
        #: tiles per frame, ``(H, W)`` of a frame and ``(N, C, H, W)`` of the first batch; set by the first frame
        self.num_tiles: int | None = None
        self.frame_shape: tuple[int, int] | None = None
        self._input_shape: tuple[int, ...] | None = None
        self._writer = None
        self._closed = False
        font_size = max(8, self.tile_size // 16)
        try:
            self._font = font_module.load_default(size=font_size)  # FreeType (Pillow >= 10.1)
        except (TypeError, ImportError, OSError, AttributeError):
            self._font = font_module.load_default()  # the fixed-size bitmap font

    # ------------------------------------------------------------------ frames
    def add_frame(self, images, success, returns) -> None:
        """Append one frame.

        Args:
            images: uint8 ``(N, 3, H, W)`` (or ``(N, 1, H, W)`` grey), torch (any device), NumPy or Warp.
            success: ``(N,)`` bool or int, non-zero where the env succeeded in this step.
            returns: ``(N,)`` float, the running return drawn on each tile.
        """
        if self._closed:
            raise RuntimeError(f"GridVideoWriter for {str(self.path)!r} is closed")
        shape = tuple(images.shape)
        if len(shape) != 4 or shape[1] not in (1, 3) or shape[0] < 1:
            raise ValueError(f"images must have shape (N, 3, H, W) with N >= 1, got {shape}")
        if self._input_shape is not None and shape != self._input_shape:
            raise ValueError(f"images of shape {shape} differ from the first frame's {self._input_shape}")
        n = min(shape[0], self.max_tiles)
        imgs = _to_numpy(images[:n])  # only the tiled envs leave the device
        if imgs.dtype != np.uint8:
            raise ValueError(f"images must be uint8, got {imgs.dtype}")
        flags = self._per_env(success, shape[0], "success")[:n] != 0
        rets = self._per_env(returns, shape[0], "returns")[:n].astype(np.float64)
        if imgs.shape[1] == 1:
            imgs = np.repeat(imgs, 3, axis=1)
        tiles = np.stack([self._tile(imgs[k], k, bool(flags[k]), float(rets[k])) for k in range(n)])
        grid = image_grid(tiles, pad=PAD, pad_value=PAD_VALUE)
        h, w = grid.shape[:2]
        if h % 2 or w % 2:
            grid = np.pad(grid, ((0, h % 2), (0, w % 2), (0, 0)), constant_values=PAD_VALUE)
        if self._writer is None:
            self._input_shape, self.num_tiles, self.frame_shape = shape, n, grid.shape[:2]
            self._writer = self._iio.get_writer(self.path, format="FFMPEG", mode="I", fps=self.fps, codec="libx264",
                                                macro_block_size=1, pixelformat="yuv420p", quality=8,
                                                ffmpeg_log_level="error")
        self._writer.append_data(grid)
        self.num_frames += 1

    @staticmethod
    def _per_env(values, n: int, name: str) -> np.ndarray:
        arr = _to_numpy(values)
        if arr.shape != (n,):
            raise ValueError(f"{name} must have shape ({n},) like the images' first axis, got {tuple(arr.shape)}")
        return arr

    def _tile(self, chw: np.ndarray, index: int, success: bool, ret: float) -> np.ndarray:
        """One env's image, resized to ``tile_size`` high, with its label (and success border); ``(3, H, W)``."""
        img = self._image.fromarray(np.ascontiguousarray(chw.transpose(1, 2, 0)))
        if img.height != self.tile_size:
            width = max(1, round(img.width * self.tile_size / img.height))
            img = img.resize((width, self.tile_size), self._image.Resampling.BILINEAR)
        draw = self._draw.Draw(img)
        margin = max(1, self.tile_size // 64)
        if success:
            border = max(2, self.tile_size // 32)
            draw.rectangle((0, 0, img.width - 1, img.height - 1), outline=SUCCESS_COLOR, width=border)
            margin += border
        text = f"env {index}  R {ret:.1f}"
        if draw.textlength(text, font=self._font) > img.width - 2 * margin:
            text = f"env {index}\nR {ret:.1f}"  # small tiles: two short lines
        box = draw.multiline_textbbox((margin, margin), text, font=self._font)
        draw.rectangle((box[0] - 1, box[1] - 1, box[2] + 1, box[3] + 1), fill=LABEL_BACKGROUND)
        draw.multiline_text((margin, margin), text, fill=TEXT_COLOR, font=self._font)
        if success:
            y = img.height - margin
            box = draw.textbbox((margin, y), "success", font=self._font, anchor="ls")
            draw.rectangle((box[0] - 1, box[1] - 1, box[2] + 1, box[3] + 1), fill=LABEL_BACKGROUND)
            draw.text((margin, y), "success", fill=SUCCESS_COLOR, font=self._font, anchor="ls")
        return np.asarray(img, dtype=np.uint8).transpose(2, 0, 1)

    # ------------------------------------------------------------------ closing
    def close(self) -> int:
        """Finish the file; returns the number of frames written (0: no file). Safe to call twice."""
        if not self._closed:
            self._closed = True
            if self._writer is not None:
                self._writer.close()
                self._writer = None
        return self.num_frames

    def __enter__(self) -> GridVideoWriter:
        return self

    def __exit__(self, *exc_info) -> None:
        self.close()


class EnvVideoRecorder:
    """Records one frame of an env batch per :meth:`add_step`: ``env.render_rgb(tile_size, tile_size)`` of the
    first ``max_tiles`` envs, labelled with their running returns and the step's success flags (``env.success``).

    Envs reset themselves when done, so the frame of a step that ended an episode shows the new episode's first
    state, labelled with the finished episode's return (and ``success`` if it succeeded); the return restarts at 0
    after that frame.

    Args:
        env: a lapwarp env (``render_rgb``, ``success``, ``num_envs``, ``device``, ``dt``).
        path: ``.mp4`` output file.
        tile_size: render size of each env image (square).
        max_tiles: how many envs (the first ones) are tiled.
        fps: frames per second (default: :func:`video_fps` of ``env.dt``, real time clamped to 1..30).
    """

    def __init__(self, env, path: str | os.PathLike, tile_size: int = 256, max_tiles: int = 16,
                 fps: float | None = None):
        import torch
        import warp as wp

        if not hasattr(env, "render_rgb"):
            raise ValueError(f"{type(env).__name__} has no render_rgb(): cannot record a video")
        self.env = env
        self.tile_size = tile_size
        self.writer = GridVideoWriter(path, fps if fps is not None else video_fps(float(env.dt)), tile_size=tile_size,
                                      max_tiles=max_tiles)
        self._success = wp.to_torch(env.success)  # (num_envs,) int32 view, written by every step
        self.returns = torch.zeros(env.num_envs, dtype=torch.float64, device=env.device)

    @property
    def num_frames(self) -> int:
        return self.writer.num_frames

    @property
    def num_tiles(self) -> int:
        """Envs tiled per frame."""
        return min(self.env.num_envs, self.writer.max_tiles)

    def add_step(self, rewards, dones) -> None:
        """Record the frame after an ``env.step`` that returned ``rewards`` and ``dones``."""
        self.returns += rewards
        images = self.env.render_rgb(self.tile_size, self.tile_size)
        self.writer.add_frame(images, self._success, self.returns)
        self.returns.masked_fill_(dones.bool(), 0.0)

    def close(self) -> int:
        """Finish the file; returns the number of frames written."""
        return self.writer.close()

    def __enter__(self) -> EnvVideoRecorder:
        return self

    def __exit__(self, *exc_info) -> None:
        self.close()


def record_video(env, policy, path: str | os.PathLike, steps: int, tile_size: int = 256, max_tiles: int = 16) -> int:
    """Run ``steps`` env steps of ``policy`` from the env's current state (no reset) and record one frame per step.

    Args:
        env: a lapwarp env.
        policy: ``policy(observations) -> actions`` (as ``env.step`` takes them).
        path: ``.mp4`` output file.
        steps: env steps to run (= frames).
        tile_size: render size of each env image (square).
        max_tiles: how many envs (the first ones) are tiled.

    Returns:
        Frames written.
    """
    if isinstance(steps, bool) or not isinstance(steps, (int, np.integer)) or steps < 0:
        raise ValueError(f"steps must be a non-negative integer, got {steps!r}")
    with EnvVideoRecorder(env, path, tile_size=tile_size, max_tiles=max_tiles) as recorder:
        obs = env.get_observations()
        for _ in range(int(steps)):
            obs, rewards, dones, _ = env.step(policy(obs))
            recorder.add_step(rewards, dones)
    return recorder.num_frames
