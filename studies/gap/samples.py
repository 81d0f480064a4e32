"""Which of a diagnosis' samples are compared, and where: the fit's share of the training
samples, the part of an image each sample covers, and each tap's contact region, at a
model's resolution (``FastModel`` or ``ReferenceModel``: its ``factor``, ``mask`` and
``working_images``).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from scenes.images import block_mean

from .pairs import Pairs


def fit_subset(pairs: Pairs, index: np.ndarray, count: int, seed: int) -> np.ndarray:
    """At most ``count`` of the training samples, taken round-robin over objects."""
    if len(index) <= count:
        return index
    rng = np.random.default_rng(seed)
    objects = [str(pairs.records[i].get("object", "")) for i in index]
    groups = [list(rng.permutation(index[[o == obj for o in objects]])) for obj in sorted(set(objects))]
    out = []
    while len(out) < count:
        for g in groups:
            if g and len(out) < count:
                out.append(g.pop())
    return np.sort(np.array(out))


def areas_at(model, areas: np.ndarray) -> np.ndarray:
    """(N, H, W) bool areas at ``model``'s resolution: blocks at least half inside."""
    if model.factor == 1:
        return areas
    return model.working_images(areas.astype(np.float32)[..., None])[..., 0] >= 0.5


def contact_at(model, pairs: Pairs, index: np.ndarray) -> np.ndarray | None:
    """(N, h, w) bool: the samples ``index``'s contact regions at ``model``'s resolution
    (``scenes.captures.press_regions``: the real capture's annotated discs, else where a
    real image differs from the real no-contact image), within its image circle; None
    where the real side has neither (then no sample has a contact scope)."""
    from scenes.captures import press_regions
    from scenes.dataset import read_samples
    from scenes.images import read_rgb

    real_records = {r["id"]: r for r in read_samples(pairs.real_dir)}
    records = [real_records.get(pairs.ids[i], {}) for i in index]
    background = Path(pairs.real_dir) / "background.png"
    if not (records and (background.is_file() or all("contact_center_px" in r for r in records))):
        return None
    bg = read_rgb(background, pairs.shape) if background.is_file() else np.zeros(pairs.shape + (3,), np.float32)
    from scenes.camera import Camera

    full = press_regions(records, pairs.real[index], bg, Camera.from_spec(pairs.spec).mask)
    regions = (block_mean(full.astype(np.float32), model.factor, (1, 2)) >= 0.5) & model.mask
    return regions if regions.any() else None
