"""Image files at the edges: 8-bit PNG in and out, linear float RGB in [0, 1] inside.

The fast path's intensities are, as in the paper, the camera's output values, so 8-bit
files map to [0, 1] by a plain division by 255 (no sRGB transfer): a real image read here
and written back is unchanged. The camera's own response is a separate, explicit model.
Physically based renders (linear radiance) are sRGB-encoded for viewing (``srgb``).
"""

from __future__ import annotations

import io
from pathlib import Path

import numpy as np
from PIL import Image

from .files import atomic_write_bytes


def read_rgb(path: str | Path, shape: tuple[int, int] | None = None) -> np.ndarray:
    """Read an image file as (H, W, 3) float32 in [0, 1].

    shape : expected (H, W); a mismatch is an error, never a silent resize.
    """
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"image {path} does not exist")
    try:
        with Image.open(path) as im:
            im = im.convert("RGB")
            rgb = np.asarray(im, dtype=np.float32) / 255.0
    except (OSError, ValueError) as exc:
        raise ValueError(f"image {path} could not be read: {exc}") from None
    if shape is not None and rgb.shape[:2] != tuple(shape):
        raise ValueError(f"image {path} must be {shape[1]}x{shape[0]} px, got {rgb.shape[1]}x{rgb.shape[0]}")
    return rgb


def srgb(linear: np.ndarray) -> np.ndarray:
    """Linear [0, 1] -> sRGB-encoded [0, 1] (IEC 61966-2-1), for viewing only; clips first."""
    x = np.clip(linear, 0.0, 1.0)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1 / 2.4) - 0.055)


def to_uint8(rgb: np.ndarray) -> np.ndarray:
    """Linear [0, 1] float RGB to 8-bit, rounding and clipping."""
    return np.clip(np.rint(np.asarray(rgb) * 255.0), 0, 255).astype(np.uint8)


def png_bytes(rgb: np.ndarray, compress_level: int = 6) -> bytes:
    """(H, W, 3) float RGB in [0, 1] as the bytes of an 8-bit PNG.

    compress_level : zlib level 0-9 (1 is several times faster, for bulk datasets).
    """
    rgb = np.asarray(rgb)
    if rgb.ndim != 3 or rgb.shape[2] != 3:
        raise ValueError(f"image must be (H, W, 3), got {rgb.shape}")
    buf = io.BytesIO()
    Image.fromarray(to_uint8(rgb)).save(buf, format="PNG", compress_level=compress_level)
    return buf.getvalue()


def write_rgb(path: str | Path, rgb: np.ndarray, compress_level: int = 6) -> Path:
    """Write (H, W, 3) float RGB in [0, 1] as an 8-bit PNG (:func:`png_bytes`), atomically."""
    path = Path(path)
    atomic_write_bytes(path, png_bytes(rgb, compress_level))
    return path


def block_mean(image: np.ndarray, factor: int, axes: tuple[int, int] = (0, 1)) -> np.ndarray:
    """Average ``factor`` x ``factor`` pixel blocks over the two image ``axes`` (rows,
    columns) of an array, accumulating in float64 and keeping its dtype."""
    from skimage.measure import block_reduce

    image = np.asarray(image)
    if factor == 1:
        return image
    rows, cols = (image.shape[a] for a in axes)
    if factor < 1 or rows % factor or cols % factor:
        raise ValueError(f"an image of {cols}x{rows} pixels cannot be averaged in blocks of {factor}x{factor}: "
                         "its size must be a whole multiple of the factor")
    block = [1] * image.ndim
    for a in axes:
        block[a] = factor
    return block_reduce(image, tuple(block), np.mean, func_kwargs={"dtype": np.float64}).astype(image.dtype)


def pyplot():
    """matplotlib's pyplot on the Agg backend (files, no display), imported only when a
    figure is drawn."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def save_figure(fig, path: str | Path, dpi: int = 80) -> Path:
    """Lay ``fig`` out (``tight_layout``), write it to ``path`` as a PNG whole
    (``scenes.files.atomic_write_bytes``) and close it."""
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=dpi)
    pyplot().close(fig)
    path = Path(path)
    atomic_write_bytes(path, buf.getvalue())
    return path
