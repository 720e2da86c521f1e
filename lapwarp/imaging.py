"""Image files and image grids: PNG writing/reading (Pillow) and tiling per-env images into one grid.

Used to look at renderer output (a grid of the per-env images), by ``lapwarp run --save-images``, by the rollout
videos of :mod:`lapwarp.video` and by the golden-image tests. ``image_grid`` is NumPy only; ``write_png`` and
``read_png`` need Pillow (``pip install "lapwarp[video]"``), imported when first called.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

__all__ = ["image_grid", "read_png", "save_image_grid", "write_png"]

_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
_MODE_CHANNELS = {"L": 1, "LA": 2, "RGB": 3, "RGBA": 4}  # Pillow modes of 8-bit grey, grey+alpha, RGB, RGBA
INSTALL_HINT = 'pip install "lapwarp[video]"'


def _pil_image():
    """``PIL.Image``, or an ImportError that says how to install it."""
    try:
        from PIL import Image
    except ImportError as exc:
        msg = f"reading and writing PNG files needs Pillow: {INSTALL_HINT} (or pip install pillow)"
        raise ImportError(msg) from exc
    return Image


def _to_numpy(images) -> np.ndarray:
    if type(images).__module__.startswith("torch"):
        images = images.detach().cpu().numpy()
    elif hasattr(images, "numpy") and not isinstance(images, np.ndarray):  # wp.array
        images = images.numpy()
    return np.asarray(images)


def write_png(path: str | Path, image) -> None:
    """Writes an 8-bit PNG (whatever the file suffix).

    Args:
        path: Output file.
        image: uint8 ``(H, W)``, ``(H, W, C)`` with C in 1..4 (grey, grey+alpha, RGB, RGBA); NumPy or torch.

    Raises:
        ValueError: not uint8, or not one of those shapes.
        ImportError: Pillow is not installed.
    """
    img = _to_numpy(image)
    if img.dtype != np.uint8:
        raise ValueError(f"write_png expects uint8 pixels, got {img.dtype}")
    if img.ndim == 2:
        img = img[:, :, None]
    if img.ndim != 3 or img.shape[2] not in _MODE_CHANNELS.values() or img.shape[0] < 1 or img.shape[1] < 1:
        raise ValueError(f"write_png expects (H, W) or (H, W, C<=4), got {img.shape}")
    image_cls = _pil_image()
    img = np.ascontiguousarray(img[:, :, 0] if img.shape[2] == 1 else img)
    image_cls.fromarray(img).save(Path(path), format="PNG")


def read_png(path: str | Path) -> np.ndarray:
    """Reads an 8-bit grey / grey+alpha / RGB / RGBA PNG; palette PNGs come back as RGB (RGBA with transparency),
    1-bit ones as grey.

    Returns:
        uint8 ``(H, W, C)``, C = 1 (grey), 2 (grey+alpha), 3 (RGB) or 4 (RGBA).

    Raises:
        ValueError: not a PNG file, or a PNG with 16-bit or other non-8-bit samples.
        ImportError: Pillow is not installed.
    """
    path = Path(path)
    with path.open("rb") as f:
        if f.read(8) != _PNG_SIGNATURE:
            raise ValueError(f"{path} is not a PNG file")
    image_cls = _pil_image()
    try:
        with image_cls.open(path, formats=["PNG"]) as im:
            im.load()
            mode = im.mode
            if mode in ("P", "PA"):
                im = im.convert("RGBA" if mode == "PA" or "transparency" in im.info else "RGB")
            elif mode == "1":
                im = im.convert("L")
            elif mode not in _MODE_CHANNELS:
                raise ValueError(f"{path}: only 8-bit grey/RGB(A) PNGs are supported, got Pillow mode {mode!r}")
            data = np.asarray(im, dtype=np.uint8)
    except (OSError, SyntaxError) as exc:  # Pillow's errors for damaged files (UnidentifiedImageError is an OSError)
        raise ValueError(f"{path}: cannot decode the PNG ({exc})") from exc
    if data.ndim == 2:
        data = data[:, :, None]
    return np.ascontiguousarray(data)


def image_grid(images, ncols: int | None = None, pad: int = 1, pad_value: int = 0) -> np.ndarray:
    """Tiles ``(N, C, H, W)`` uint8 images (C = 1 or 3; NumPy, torch or Warp) into one ``(H', W', C)`` array,
    row-major, ``ncols`` per row (default: about square), separated by ``pad`` pixels of ``pad_value``."""
    imgs = _to_numpy(images)
    if imgs.ndim != 4 or imgs.shape[1] not in (1, 3):
        raise ValueError(f"images must have shape (N, C, H, W) with C in (1, 3), got {imgs.shape}")
    if imgs.dtype != np.uint8:
        raise ValueError(f"images must be uint8, got {imgs.dtype}")
    n, c, h, w = imgs.shape
    if n == 0:
        raise ValueError("no images to tile")
    ncols = int(ncols or int(np.ceil(np.sqrt(n))))
    if ncols < 1:
        raise ValueError(f"ncols must be positive, got {ncols}")
    nrows = -(-n // ncols)
    grid = np.full((nrows * (h + pad) + pad, ncols * (w + pad) + pad, c), pad_value, np.uint8)
    for k in range(n):
        r, q = divmod(k, ncols)
        y, x = pad + r * (h + pad), pad + q * (w + pad)
        grid[y : y + h, x : x + w] = imgs[k].transpose(1, 2, 0)
    return grid


def save_image_grid(images, path: str | Path, ncols: int | None = None, pad: int = 1) -> np.ndarray:
    """Writes ``(N, C, H, W)`` uint8 images (e.g. ``Renderer.rgb``) as one PNG grid; returns the grid."""
    grid = image_grid(images, ncols=ncols, pad=pad)
    write_png(path, grid)
    return grid
