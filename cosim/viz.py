"""Small image helpers for looking at what the cameras see: mosaics, PNGs and GIFs.

Pure numpy plus imageio (imported when a file is written), so the mosaic logic is
testable without a renderer.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np


def upscale(image: np.ndarray, scale: int) -> np.ndarray:
    """Nearest-neighbour enlargement by an integer factor (keeps pixels crisp)."""
    if scale < 1:
        raise ValueError(f"scale must be an integer >= 1, got {scale}")
    return np.repeat(np.repeat(image, scale, axis=0), scale, axis=1)


def mosaic(images, cols: int, scale: int = 1, pad: int = 2,
           background: tuple[int, int, int] = (32, 32, 32)) -> np.ndarray:
    """Tile equally sized RGB images (n, H, W, 3) into a grid with `cols` columns.

    Args:
        images: a sequence or array of uint8 images of one size.
        cols: images per row; rows follow from the count.
        scale: nearest-neighbour enlargement of each image.
        pad: pixels of `background` between and around tiles.
        background: RGB of the padding and of empty cells.

    Returns:
        uint8 (rows * (H * scale + pad) + pad, cols * (W * scale + pad) + pad, 3).
    """
    images = [np.asarray(im, np.uint8) for im in images]
    if not images:
        raise ValueError("mosaic needs at least one image")
    if cols < 1:
        raise ValueError(f"cols must be >= 1, got {cols}")
    h, w = images[0].shape[:2]
    if any(im.shape[:2] != (h, w) for im in images):
        raise ValueError("mosaic images must all have the same size")
    h, w = h * scale, w * scale
    rows = -(-len(images) // cols)
    out = np.empty((rows * (h + pad) + pad, cols * (w + pad) + pad, 3), np.uint8)
    out[:] = background
    for k, im in enumerate(images):
        r, c = divmod(k, cols)
        y, x = pad + r * (h + pad), pad + c * (w + pad)
        out[y:y + h, x:x + w] = upscale(im[:, :, :3], scale)
    return out


def side_by_side(left: np.ndarray, right: np.ndarray, pad: int = 2,
                 background: tuple[int, int, int] = (32, 32, 32)) -> np.ndarray:
    """Two RGB images next to each other, top-aligned, the shorter one padded."""
    h = max(left.shape[0], right.shape[0])
    out = np.empty((h, left.shape[1] + pad + right.shape[1], 3), np.uint8)
    out[:] = background
    out[: left.shape[0], : left.shape[1]] = left[:, :, :3]
    out[: right.shape[0], left.shape[1] + pad:] = right[:, :, :3]
    return out


def save_png(path, image: np.ndarray) -> Path:
    """Write an RGB uint8 image as PNG (folders created); returns the path."""
    import imageio.v3 as iio

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    iio.imwrite(path, np.asarray(image, np.uint8))
    return path


def save_gif(path, frames, fps: float = 10.0) -> Path:
    """Write RGB uint8 frames as a looping GIF (folders created); returns the path."""
    import imageio.v3 as iio

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    iio.imwrite(path, np.stack([np.asarray(f, np.uint8) for f in frames]),
                duration=1000.0 / fps, loop=0)
    return path
