"""Image files without a PIL dependency: PNG writing/reading (zlib + struct) and image grids.

Used to look at renderer output (a grid of the per-env images) and by the golden-image tests.
"""

from __future__ import annotations

import struct
import zlib
from pathlib import Path

import numpy as np

__all__ = ["image_grid", "read_png", "save_image_grid", "write_png"]

_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
_COLOR_TYPES = {1: 0, 2: 4, 3: 2, 4: 6}  # channels -> PNG colour type (grey, grey+alpha, RGB, RGBA)


def _to_numpy(images) -> np.ndarray:
    if type(images).__module__.startswith("torch"):
        images = images.detach().cpu().numpy()
    elif hasattr(images, "numpy") and not isinstance(images, np.ndarray):  # wp.array
        images = images.numpy()
    return np.asarray(images)


def _chunk(tag: bytes, data: bytes) -> bytes:
    return struct.pack(">I", len(data)) + tag + data + struct.pack(">I", zlib.crc32(tag + data) & 0xFFFFFFFF)


def write_png(path: str | Path, image) -> None:
    """Writes an 8-bit PNG.

    Args:
        path: Output file.
        image: uint8 ``(H, W)``, ``(H, W, C)`` with C in 1..4 (grey, grey+alpha, RGB, RGBA); NumPy or torch.
    """
    img = _to_numpy(image)
    if img.dtype != np.uint8:
        raise ValueError(f"write_png expects uint8 pixels, got {img.dtype}")
    if img.ndim == 2:
        img = img[:, :, None]
    if img.ndim != 3 or img.shape[2] not in _COLOR_TYPES or img.shape[0] < 1 or img.shape[1] < 1:
        raise ValueError(f"write_png expects (H, W) or (H, W, C<=4), got {img.shape}")
    h, w, c = img.shape
    # Filter type 0 (none) on every row.
    raw = np.concatenate([np.zeros((h, 1), np.uint8), np.ascontiguousarray(img).reshape(h, w * c)], axis=1)
    header = struct.pack(">IIBBBBB", w, h, 8, _COLOR_TYPES[c], 0, 0, 0)
    data = _PNG_SIGNATURE + _chunk(b"IHDR", header) + _chunk(b"IDAT", zlib.compress(raw.tobytes(), 6))
    Path(path).write_bytes(data + _chunk(b"IEND", b""))


def _paeth(a: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
    p = a + b - c
    pa, pb, pc = np.abs(p - a), np.abs(p - b), np.abs(p - c)
    return np.where((pa <= pb) & (pa <= pc), a, np.where(pb <= pc, b, c))


def read_png(path: str | Path) -> np.ndarray:
    """Reads an 8-bit, non-interlaced grey / grey+alpha / RGB / RGBA PNG (any filter types).

    Returns:
        uint8 ``(H, W, C)``.
    """
    data = Path(path).read_bytes()
    if data[:8] != _PNG_SIGNATURE:
        raise ValueError(f"{path} is not a PNG file")
    pos, idat, header = 8, [], None
    while pos < len(data):
        (length,) = struct.unpack(">I", data[pos : pos + 4])
        tag = data[pos + 4 : pos + 8]
        body = data[pos + 8 : pos + 8 + length]
        pos += 12 + length
        if tag == b"IHDR":
            header = struct.unpack(">IIBBBBB", body)
        elif tag == b"IDAT":
            idat.append(body)
        elif tag == b"IEND":
            break
    if header is None:
        raise ValueError(f"{path}: no IHDR chunk")
    w, h, depth, color_type, _, _, interlace = header
    channels = {v: k for k, v in _COLOR_TYPES.items()}.get(color_type)
    if depth != 8 or channels is None or interlace != 0:
        raise ValueError(f"{path}: only 8-bit non-interlaced grey/RGB(A) PNGs are supported")
    stride = w * channels
    raw = np.frombuffer(zlib.decompress(b"".join(idat)), np.uint8).reshape(h, stride + 1)
    out = np.zeros((h, stride), np.int32)
    prev = np.zeros(stride, np.int32)
    for y in range(h):
        kind, row = raw[y, 0], raw[y, 1:].astype(np.int32)
        if kind == 0:
            cur = row
        elif kind == 2:
            cur = (row + prev) & 0xFF
        elif kind in (1, 3, 4):
            # These depend on the already decoded left neighbour: decode pixel by pixel.
            cur = np.zeros(stride, np.int32)
            for x in range(stride):
                left = cur[x - channels] if x >= channels else 0
                up_left = prev[x - channels] if x >= channels else 0
                if kind == 1:
                    pred = left
                elif kind == 3:
                    pred = (left + prev[x]) // 2
                else:
                    pred = int(_paeth(np.array(left), np.array(prev[x]), np.array(up_left)))
                cur[x] = (row[x] + pred) & 0xFF
        else:
            raise ValueError(f"{path}: unknown PNG filter type {kind}")
        out[y] = cur
        prev = cur
    return out.astype(np.uint8).reshape(h, w, channels)


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
