"""The networks' inputs and targets: a set's images as the full image averaged down, or as
the patch around each contact, optionally as each image's difference from its no-contact
frame; the indenter's class or the contact's pixel.

The cropped patch is ``patch_px`` square at the arrays' resolution, centred on the
contact's pixel.
"""

from __future__ import annotations

import math

import numpy as np

from scenes.images import block_mean
from scenes.indenters import INDENTERS

from . import data
from .plan import INPUTS, TASKS, Settings

#: Difference inputs are stored as uint8 DIFFERENCE_ZERO + DIFFERENCE_SCALE z (``difference``).
DIFFERENCE_ZERO = 128
DIFFERENCE_SCALE = 8.0


def full_inputs(images: np.ndarray, block: int, chunk: int = 1024) -> np.ndarray:
    """The full-image input: (N, h, w, 3) uint8 averaged over ``block`` blocks (in chunks:
    23,040 images in float would take 5 GB)."""
    if block == 1:
        return images
    return np.concatenate([np.clip(np.rint(block_mean(images[i:i + chunk].astype(np.float32), block, (1, 2))), 0, 255)
                           .astype(np.uint8) for i in range(0, len(images), chunk)])


def patches(images: np.ndarray, pixel: np.ndarray, factor: int, size: int, fill: int = 0) -> np.ndarray:
    """(N, size, size, 3) crops centred on each contact's pixel (full-resolution (u, v),
    ``pixel``) at the arrays' resolution (1/``factor``), ``fill`` outside the image."""
    n, h, w, _ = images.shape
    pad = size
    padded = np.pad(images, ((0, 0), (pad, pad), (pad, pad), (0, 0)), constant_values=fill)
    out = np.empty((n, size, size, 3), np.uint8)
    centre = (np.asarray(pixel, np.float64) + 0.5) / factor - 0.5  # full-res pixel centre -> array pixels
    for i in range(n):
        c0 = int(math.floor(centre[i, 0] - size / 2 + 0.5)) + pad
        r0 = int(math.floor(centre[i, 1] - size / 2 + 0.5)) + pad
        c0, r0 = min(max(c0, 0), w + pad), min(max(r0, 0), h + pad)
        out[i] = padded[i, r0:r0 + size, c0:c0 + size]
    return out


def difference(images: np.ndarray, frames: np.ndarray, mask: np.ndarray, chunk: int = 1024) -> np.ndarray:
    """(N, h, w, 3) uint8 images and their no-contact frames ((h, w, 3), or one per image)
    -> uint8 DIFFERENCE_ZERO + DIFFERENCE_SCALE z, clipped, z = (image - frame) over its
    RMS inside the image circle ``mask`` (h, w), zero outside it.

    Scaled per image, the input keeps the contact's shape and drops its strength, which a
    simulator may get wrong by an order of magnitude (``visibility``); an image equal to
    its frame gives z = 0."""
    images = np.asarray(images)
    frames = np.asarray(frames)
    if images.ndim != 4 or frames.shape[-3:] != images.shape[1:] or frames.ndim not in (3, 4) or (
            frames.ndim == 4 and len(frames) != len(images)):
        raise ValueError(f"frames {frames.shape} must be one (h, w, 3) frame or one per image of {images.shape}")
    if mask.shape != images.shape[1:3]:
        raise ValueError(f"mask {mask.shape} must be the images' (h, w) {images.shape[1:3]}")
    out = np.empty_like(images, dtype=np.uint8)
    for i in range(0, len(images), chunk):
        f = frames if frames.ndim == 3 else frames[i:i + chunk]
        d = images[i:i + chunk].astype(np.float32) - f.astype(np.float32)
        d *= mask[None, :, :, None]
        rms = np.sqrt((d ** 2).sum(axis=(1, 2, 3)) / (3.0 * mask.sum()))
        z = d / np.maximum(rms, 1e-6)[:, None, None, None]
        out[i:i + chunk] = np.clip(np.rint(DIFFERENCE_ZERO + DIFFERENCE_SCALE * z), 0, 255)
    return out


def inputs(arrays: data.Arrays, images: np.ndarray, kind: str, settings: Settings) -> np.ndarray:
    """A set's images as the network input ``kind`` (``INPUTS``): the full image or the patch."""
    if kind == "full":
        return full_inputs(images, settings.full_block)
    if kind == "patch":
        return patches(images, arrays.pixel, arrays.factor, settings.patch_px,
                       fill=DIFFERENCE_ZERO if settings.difference else 0)
    raise ValueError(f"input must be one of {INPUTS}, got {kind!r}")


def targets(arrays: data.Arrays, task: str, size: tuple[int, int]) -> np.ndarray:
    """Classification: the one-hot indenter; localisation: the contact's pixel over the
    full image's (width, height), in [0, 1]."""
    if task == "classification":
        return np.eye(len(INDENTERS), dtype=np.float32)[arrays.labels]
    if task == "localisation":
        return (arrays.pixel / np.asarray(size, np.float32)).astype(np.float32)
    raise ValueError(f"task must be one of {TASKS}, got {task!r}")
