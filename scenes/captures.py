"""Real taps of a sensor for calibration: images, where each was pressed (depth maps),
and where its contact shows.

A calibration of the reference uses at most MAX_TAPS taps of a capture dataset
(``docs/dataset-format.md``, ``source: "real"``). A real capture has no depth map: its tap
is replayed on the MuJoCo rig from the dataset's protocol.json. The capture's samples
alternate between fitted (even positions) and judged (odd ones), and so do the taps
loaded from it: the fitted ones are spread evenly over its even samples, the judged ones
over its odd samples, so that a calibration never fits a tap that ``compare --heldout``
judges it on. A tap's contact region is its annotated disc where the capture has one (an
imported set, ``scenes.imports``), else found in the real images alone, before any
alignment: where the tap differs from the no-contact capture.
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
    depth map (H, W), each tap's id, and its annotated contact disc where it has one:
    ``discs`` (T, 3) (u, v, radius) px at the camera's size, NaN rows for taps without
    (None: none has one)."""

    images: np.ndarray
    depths: np.ndarray
    ref_depth: np.ndarray
    ids: list[str]
    discs: np.ndarray | None = None

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
        if self.discs is not None and np.shape(self.discs) != (len(images), 3):
            raise ValueError(f"taps: discs must be ({len(images)}, 3) (u, v, radius px), got {np.shape(self.discs)}")

    def subset(self, pick) -> "RealTaps":
        """The taps ``pick`` (indices or a bool mask)."""
        pick = np.flatnonzero(pick) if np.asarray(pick).dtype == bool else np.asarray(pick, int)
        return RealTaps(self.images[pick], self.depths[pick], self.ref_depth, [self.ids[i] for i in pick],
                        None if self.discs is None else np.asarray(self.discs)[pick])

    def regions(self, background: np.ndarray, inside: np.ndarray, images: np.ndarray | None = None) -> np.ndarray:
        """(T, h, w) bool, each tap's contact region at the size of ``background`` (h, w, 3)
        and ``inside`` (h, w): its annotated disc scaled to that size, else where its image
        (``images``, (T, h, w, 3) at that size; default the taps' own) differs from the
        no-contact ``background`` (:func:`contact_region`)."""
        images = self.images if images is None else images
        shape = np.shape(inside)
        scale = shape[0] / self.images.shape[1]
        out = np.zeros((len(images), *shape), bool)
        for t, image in enumerate(images):
            disc = None if self.discs is None else np.asarray(self.discs[t], np.float64)
            if disc is not None and np.all(np.isfinite(disc)):
                out[t] = contact_disc(shape, (disc[:2] + 0.5) * scale - 0.5, disc[2] * scale) & inside
            else:
                out[t] = contact_region(image, background, inside)
        return out


def split(count: int) -> np.ndarray:
    """(T,) bool: which taps are fitted (even positions); the others judge."""
    return np.arange(count) % 2 == 0


def contact_region(tap: np.ndarray, background: np.ndarray, inside: np.ndarray) -> np.ndarray:
    """(h, w) bool: where a real tap (h, w, 3) differs from the real no-contact image by
    more than CHANGE_LEVEL in some channel, inside the image circle (module doc)."""
    changed = (np.abs(np.asarray(tap, np.float64) - background).max(axis=2) > CHANGE_LEVEL) & inside
    changed = ndimage.binary_opening(changed)
    return ndimage.binary_dilation(changed, iterations=REGION_DILATION) & inside


def contact_disc(shape: tuple[int, int], centre_px, radius_px: float) -> np.ndarray:
    """(H, W) bool: the pixels whose centres lie within ``radius_px`` of ``centre_px``
    (u = column, v = row): an annotated press's contact region."""
    v, u = np.mgrid[: shape[0], : shape[1]]
    return np.hypot(u - float(centre_px[0]), v - float(centre_px[1])) <= float(radius_px)


def press_regions(records, images: np.ndarray, background: np.ndarray, inside: np.ndarray) -> np.ndarray:
    """(N, H, W) bool: each real press's contact region: its annotated disc where its
    record has one (``contact_center_px``, ``contact_radius_px``: an imported capture,
    ``scenes.imports``), else where its image differs from the no-contact one
    (:func:`contact_region`); within ``inside`` (the image circle) either way.

    records : N sample records; images : (N, H, W, 3) real frames in [0, 1];
    background : (H, W, 3) the real no-contact frame; inside : (H, W) bool.
    """
    images = np.asarray(images)
    out = np.zeros(images.shape[:3], bool)
    for i, record in enumerate(records):
        centre, radius = record.get("contact_center_px"), record.get("contact_radius_px")
        if centre is not None and radius is not None:
            out[i] = contact_disc(images.shape[1:3], centre, radius) & inside
        else:
            out[i] = contact_region(images[i], background, inside)
    return out


def frame_spread(image: np.ndarray, inside: np.ndarray, low: float = 5.0, high: float = 95.0) -> dict[str, np.ndarray]:
    """How unevenly the LEDs light a no-contact image (H, W, 3) inside ``inside`` (H, W),
    per channel (3,): its ``low`` and ``high`` percentiles, their difference ``spread`` and
    their ratio ``range`` (NaN where the low percentile is 0).

    A contact's mean change over the frame's spread is unchanged by any gain and offset
    of the camera, and to first order by its response curve: a camera fitted to the
    no-contact image cannot make a contact stronger against the frame's unevenness than
    the light made it (``studies.compare.run.contrast_budget``)."""
    image = np.asarray(image, np.float64)
    inside = np.asarray(inside, bool)
    if image.ndim != 3 or image.shape[-1] != 3 or inside.shape != image.shape[:2]:
        raise ValueError(f"image must be (H, W, 3) and inside (H, W) like it, got {image.shape} and {inside.shape}")
    if not inside.any():
        raise ValueError("inside selects no pixel")
    lo, hi = np.percentile(image[inside], [low, high], axis=0)
    with np.errstate(invalid="ignore", divide="ignore"):
        return {"low": lo, "high": hi, "spread": hi - lo, "range": np.where(lo > 0, hi / lo, np.nan)}


def halves(count: int, limit: int) -> np.ndarray:
    """Up to ``limit`` of ``count`` samples, the fitted ones (even positions of the result)
    spread evenly over the even samples and the judged ones (odd positions) over the odd
    samples (module doc): (K,) int, the samples' indices, fitted and judged in turn."""
    even, odd = np.arange(0, max(count, 0), 2), np.arange(1, max(count, 0), 2)
    n_judge = min(len(odd), max(limit, 0) // 2)
    n_fit = min(len(even), max(limit, 0) - n_judge, n_judge + 1)

    def spread(pool, n):
        return pool[np.linspace(0, len(pool) - 1, n).round().astype(int)] if n else pool[:0]

    out = np.empty(n_fit + n_judge, int)
    out[0::2], out[1::2] = spread(even, n_fit), spread(odd, n_judge)
    return out


def load_real_taps(folder: str | Path, spec, camera, limit: int = MAX_TAPS) -> RealTaps:
    """Up to ``limit`` taps of a capture dataset (replica 0 only), fitted and judged in
    turn from its even and odd samples (:func:`halves`), with their depth maps: a
    sample's own depth file, or else its tap replayed on the MuJoCo rig from the dataset's
    protocol.json (a real capture has no depth), and their annotated discs if any."""
    from scenes.dataset import DatasetError, load_sample, read_samples
    from scenes.taps import Protocol
    from scenes.rig import tap_depths

    folder = Path(folder)
    records = [r for r in read_samples(folder) if int(r.get("replica", 0)) == 0]
    if not records:
        raise DatasetError(f"REAL {folder} has no taps (samples.jsonl is empty)")
    records = [records[i] for i in halves(len(records), limit)]
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
    from scenes.dataset import read_meta

    size = read_meta(folder).get("image_size") or [camera.width, camera.height]
    scale = camera.height / float(size[1])  # annotations are at the capture's size
    discs = np.array([[*r["contact_center_px"], r["contact_radius_px"]] if "contact_center_px" in r
                      and "contact_radius_px" in r else [np.nan] * 3 for r in records], np.float64)
    discs = None if np.isnan(discs).all() else discs * [scale, scale, scale]
    return RealTaps(np.stack(images).astype(np.float64), np.stack(depths).astype(np.float32),
                    np.asarray(ref_depth, np.float32), [str(r.get("id")) for r in records], discs)
