"""Real taps of a sensor for calibration: images, where each was pressed (depth maps),
and where its contact shows.

A calibration uses at most MAX_TAPS taps of a capture dataset (``docs/dataset-format.md``,
``source: "real"``), spread evenly over it. A real capture has no depth map: its tap is
replayed on the MuJoCo rig from the dataset's protocol.json. Taps alternate between fitted
(even positions) and judged. A tap's contact region is found in the real images alone,
before any alignment: where the tap differs from the no-contact capture.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy import ndimage

#: At most this many taps are used (fitted plus judged).
MAX_TAPS = 10
#: A tap's pixel (at the film's resolution) whose real value differs from the real
#: no-contact image's by more than this in some channel is in its contact region.
CHANGE_LEVEL = 6.0 / 255.0
#: The contact region is opened by 1 pixel (specks of noise out), then dilated by this.
REGION_DILATION = 2
#: A contact region smaller than this many film pixels leaves the tap out (no contact seen).
MIN_REGION = 4

@dataclass
class RealTaps:
    """Real taps at the camera's size: images (T, H, W, 3) in [0, 1], contact depth maps
    (T, H, W) m (planar z, the spec's camera, the membrane's frame), the no-contact
    depth map (H, W) and each tap's id."""

    images: np.ndarray
    depths: np.ndarray
    ref_depth: np.ndarray
    ids: list[str]

    def __post_init__(self):
        images, depths = np.asarray(self.images), np.asarray(self.depths)
        if images.ndim != 4 or images.shape[-1] != 3:
            raise ValueError(f"taps: images must be (T, H, W, 3), got shape {images.shape}")
        if depths.shape != images.shape[:3] or np.shape(self.ref_depth) != images.shape[1:3]:
            raise ValueError(f"taps: depths {depths.shape} and ref_depth {np.shape(self.ref_depth)} must match the "
                             f"images' {images.shape[:3]}")
        if len(self.ids) != len(images):
            raise ValueError(f"taps: {len(self.ids)} ids for {len(images)} images")
        if not (np.all(np.isfinite(depths)) and np.all(np.isfinite(self.ref_depth))):
            raise ValueError("taps: depth maps must be finite (NaN or inf found)")
        if len(images) > MAX_TAPS:
            raise ValueError(f"taps: at most {MAX_TAPS} taps, got {len(images)}")


def split(count: int) -> np.ndarray:
    """(T,) bool: which taps are fitted (even positions); the others judge."""
    return np.arange(count) % 2 == 0


def contact_region(tap: np.ndarray, background: np.ndarray, inside: np.ndarray) -> np.ndarray:
    """(h, w) bool: where a real tap (h, w, 3) differs from the real no-contact image by
    more than CHANGE_LEVEL in some channel, inside the image circle (module doc)."""
    changed = (np.abs(np.asarray(tap, np.float64) - background).max(axis=2) > CHANGE_LEVEL) & inside
    changed = ndimage.binary_opening(changed)
    return ndimage.binary_dilation(changed, iterations=REGION_DILATION) & inside


def load_real_taps(folder: str | Path, spec, camera, limit: int = MAX_TAPS) -> RealTaps:
    """Up to ``limit`` taps of a capture dataset, evenly spread over its samples (replica 0
    only), with their depth maps: a sample's own depth file, or else its tap replayed on
    the MuJoCo rig from the dataset's protocol.json (a real capture has no depth)."""
    from scenes.dataset import DatasetError, load_sample, read_samples
    from scenes.protocol import Protocol
    from scenes.rig import tap_depths

    folder = Path(folder)
    records = [r for r in read_samples(folder) if int(r.get("replica", 0)) == 0]
    if not records:
        raise DatasetError(f"REAL {folder} has no taps (samples.jsonl is empty)")
    pick = np.unique(np.linspace(0, len(records) - 1, min(limit, len(records))).round().astype(int))
    records = [records[i] for i in pick]
    images, depths = [], []
    for record in records:
        image, depth = load_sample(folder, record, (camera.height, camera.width))
        images.append(image)
        depths.append(depth)
    missing = [i for i, d in enumerate(depths) if d is None]
    protocol = None
    if missing:
        path = folder / "protocol.json"
        try:
            protocol = Protocol.from_dict(json.loads(path.read_text()))
        except FileNotFoundError:
            raise DatasetError(f"REAL {folder}: samples without depth maps need protocol.json to replay their taps"
                               ) from None
        except (json.JSONDecodeError, ValueError) as exc:
            raise DatasetError(f"REAL {path}: {exc}") from None
    taps = []
    for i in missing:
        index = records[i].get("tap_index")
        if not isinstance(index, int) or not 0 <= index < len(protocol.taps):
            raise DatasetError(f"REAL {folder}: sample {records[i].get('id')} has tap_index {index!r}, not a tap of "
                               f"its protocol.json ({len(protocol.taps)} taps)")
        taps.append(protocol.taps[index])
    replay = tap_depths(spec, taps)
    try:
        ref_depth = next(replay)[0]
        for i, (depth, _) in zip(missing, replay):
            depths[i] = depth
    finally:
        replay.close()
    for record, depth in zip(records, depths):
        if np.shape(depth) != (camera.height, camera.width):
            raise DatasetError(f"REAL {folder}: sample {record.get('id')}: depth map of shape {np.shape(depth)}, "
                               f"expected ({camera.height}, {camera.width})")
    return RealTaps(np.stack(images).astype(np.float64), np.stack(depths).astype(np.float32),
                    np.asarray(ref_depth, np.float32), [str(r.get("id")) for r in records])
