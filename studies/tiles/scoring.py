"""A simulation scored against the real tile: its no-contact image, the exposure, the
change's strength, shape and sign, and the changes side by side."""

from __future__ import annotations

import math
import warnings

import numpy as np
from scipy import ndimage

from scenes import image_stats

from .frames import CHANGE_LEVEL, Alignment, align, change, inner, to_tile

#: With fewer real tiles than this, the real no-contact image joins their median.
MIN_MEDIAN_TILES = 3


def real_alignment(tile: np.ndarray, real_background: np.ndarray) -> Alignment:
    """A real tile's alignment to the published real no-contact image (H, W, 3): fitted on
    every inner pixel, then again without where the tile differs from it (the contact)."""
    shape_hw = tile.shape[:2]
    alignment, _ = align(tile, real_background)
    hot = change(tile, to_tile(real_background, shape_hw, alignment)) > CHANGE_LEVEL
    alignment, _ = align(tile, real_background, inner(shape_hw) & ~ndimage.binary_dilation(hot, iterations=2),
                         alignment)
    return alignment


def real_no_contact(tiles: dict[int, np.ndarray], alignments: dict[int, Alignment],
                    real_background: np.ndarray | None = None) -> tuple[dict[int, np.ndarray], str]:
    """Each real tile's no-contact image at its own pixels: the per-pixel median of every
    real tile resampled there (through their alignments); with fewer than
    MIN_MEDIAN_TILES tiles, the published real no-contact image (H, W, 3), brought to the
    tile, fills the median up to that many members. Returns ({column: (h, w, 3)}, how it
    was made)."""
    fill = max(0, MIN_MEDIAN_TILES - len(tiles))
    with_background = fill > 0
    if with_background and real_background is None:
        raise ValueError(f"fewer than {MIN_MEDIAN_TILES} real tiles need the real no-contact image for the median")
    out = {}
    for k, tile in tiles.items():
        shape_hw = tile.shape[:2]
        rows, cols = np.mgrid[: shape_hw[0], : shape_hw[1]]
        u, v = alignments[k].to_frame(rows, cols)
        stack = []
        for j, other in tiles.items():
            r, c = alignments[j].to_tile(u, v)
            stack.append(np.stack([ndimage.map_coordinates(other[..., ch], [r, c], order=1, mode="constant",
                                                           cval=np.nan) for ch in range(3)], axis=-1))
        if fill:
            stack += [to_tile(real_background, shape_hw, alignments[k])] * fill
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN pixels: none of the tiles reaches them
            median = np.nanmedian(np.stack(stack), axis=0)
        out[k] = np.where(np.isfinite(median), median, tile)
    how = (f"per-pixel median of the {len(tiles)} real tiles, each resampled onto the tile's pixels through their "
           "alignments" + (f", with the published real no-contact image as {fill} more" if with_background else ""))
    return out, how


def pearson(a: np.ndarray, b: np.ndarray) -> float | None:
    """Pearson correlation of two equal-size arrays (flattened); None when either is constant
    or holds fewer than two values (``scenes.image_stats.pearson``)."""
    if np.size(a) < 2:
        return None
    return image_stats.pearson(a, b, constant=None)


def _ratio(a: float, b: float) -> float | None:
    return a / b if b > 0 and math.isfinite(a) and math.isfinite(b) else None


def exposure(sim_no_contact: np.ndarray, real_nc: np.ndarray, where: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The camera's exposure that one no-contact image pins down, per channel: (gains (3,),
    judged (3,) bool). Each gain brings the simulation's no-contact tile to the real one's
    by least squares over the pixels of ``where`` (h, w) that the real camera did not clip
    (below ``pbr_tactile.real_image.CLIP_LEVEL``). A channel clipped over more than
    ``SATURATED_SHARE`` of ``where`` shows no contact and is not judged (as the
    calibration censors it); nor is a channel the simulation leaves dark (its mean there
    below ``CIRCLE_THRESHOLD``, an unlit pixel's level: a fast path without its background
    term), whose gain would be its noise's."""
    from pbr_tactile.real_image import CIRCLE_THRESHOLD, CLIP_LEVEL, SATURATED_SHARE

    gains, judged = np.zeros(3), np.zeros(3, bool)
    for c in range(3):
        s, r = sim_no_contact[..., c][where], real_nc[..., c][where]
        ok = r < CLIP_LEVEL
        if not ok.any():
            continue
        ss = float(np.sum(s[ok] ** 2))
        gains[c] = float(np.sum(s[ok] * r[ok])) / ss if ss > 0 else 0.0
        judged[c] = (1.0 - ok.mean()) <= SATURATED_SHARE and gains[c] > 0 and s.mean() >= CIRCLE_THRESHOLD
    return gains, judged


def score(sim: np.ndarray, sim_no_contact: np.ndarray, real: np.ndarray, real_nc: np.ndarray,
          region: np.ndarray, inside: np.ndarray | None = None) -> dict:
    """A simulated tile (h, w, 3) against the real one over the contact region (h, w):
    ``strength`` (``scenes.image_stats.contact_strength``), ``strength_ratio`` (sim over real)
    and ``shape_corr`` (Pearson of the signed change images there, all channels).

    With ``inside`` (the tile's image circle), also the strength's two factors per channel
    (``contrast``: ``level_ratio``, the no-contact images' means over the region, sim over
    real, which is the camera's; ``relative_ratio``, the change over the level, which is
    the light's; ``scenes.image_stats.contact_contrast``), and ``exposed``: the simulation
    seen through the real camera's exposure (``exposure``, fitted on ``inside`` less the
    region, so never on the contact), its strength, ratio and shape over the judged
    (unsaturated) channels."""
    from scenes.image_stats import contact_contrast, contact_strength

    s_sim = float(contact_strength(sim[None], sim_no_contact, region[None])[0])
    s_real = float(contact_strength(real[None], real_nc, region[None])[0])
    corr = pearson((sim - sim_no_contact)[region], (real - real_nc)[region]) if region.any() else None
    out = {"strength": s_sim if math.isfinite(s_sim) else None, "strength_ratio": _ratio(s_sim, s_real),
           "shape_corr": corr}
    if inside is None or not region.any():
        return out
    cs = contact_contrast(sim[None], sim_no_contact, region[None])
    cr = contact_contrast(real[None], real_nc, region[None])
    out["contrast"] = {key: [_ratio(float(a), float(b)) for a, b in zip(cs[name][0], cr[name][0])]
                       for key, name in (("level_ratio", "level"), ("relative_ratio", "relative"))}
    gains, judged = exposure(sim_no_contact, real_nc, inside & ~region)
    if judged.any():
        e_sim = float(np.mean(gains[judged] * cs["change"][0][judged]))
        e_real = float(np.mean(cr["change"][0][judged]))
        d_sim = ((sim - sim_no_contact) * gains)[region][:, judged]
        d_real = (real - real_nc)[region][:, judged]
        out["exposed"] = {
            "gains": gains.tolist(), "channels": "".join(ch for ch, j in zip("rgb", judged) if j),
            "strength": e_sim, "strength_real": e_real, "strength_ratio": _ratio(e_sim, e_real),
            "shape_corr": pearson(d_sim, d_real), **signed_change(d_sim, d_real)}
    return out


def signed_change(sim_change: np.ndarray, real_change: np.ndarray) -> dict:
    """Whether a contact brightens or darkens the region as the real one does, which the
    strength (a mean of |change|) cannot tell: ``signed``, the mean signed change per
    channel over the region's pixels (N, C) of each, and ``signed_ratio``, the
    simulation's mean change projected on the real's, (m_sim . m_real) / |m_real|^2: 1
    when it changes the region's colour by as much and the same way, 0 when not along it,
    negative when it darkens what the real contact brightens. None where the real
    change's mean is 0. A ValueError where the two are not of one (N, C) shape."""
    sim_change, real_change = np.asarray(sim_change, np.float64), np.asarray(real_change, np.float64)
    if real_change.ndim != 2 or sim_change.shape != real_change.shape:
        raise ValueError(f"sim_change and real_change must be (N, C) pixels by channels of one shape, got "
                         f"{sim_change.shape} and {real_change.shape}")
    m_sim, m_real = sim_change.mean(axis=0), real_change.mean(axis=0)
    norm = float(m_real @ m_real)
    return {"signed": {"sim": m_sim.tolist(), "real": m_real.tolist()},
            "signed_ratio": float(m_sim @ m_real) / norm if norm > 0 and np.isfinite(norm) else None}


#: A change image is shown as 0.5 + CHANGE_VIEW_GAIN * change: mid grey where nothing
#: changes, brighter where the contact brightens the tile (``change_figure``).
CHANGE_VIEW_GAIN = 2.0


def change_figure(real: np.ndarray, real_nc: np.ndarray, region: np.ndarray, sims: dict) -> np.ndarray:
    """A column's contacts to judge by eye, one row (h, W, 3) in [0, 1]: the real tile,
    its change (0.5 + CHANGE_VIEW_GAIN * (real - no-contact)) and its contact region
    (white), then for each renderer of ``sims`` ({name: (tile, no-contact tile, gains
    (3,))}) its no-contact tile and its change, each times the gains (the real camera's
    exposure, ``exposure``), so the sign and shape of both changes read on one scale. A
    ValueError names a tile whose shape is not the real tile's (h, w, 3)."""
    real, real_nc = np.asarray(real, np.float64), np.asarray(real_nc, np.float64)
    if real.ndim != 3 or real.shape[2] != 3 or real_nc.shape != real.shape:
        raise ValueError(f"real and real_nc must be (h, w, 3) tiles of one shape, got {real.shape} and "
                         f"{real_nc.shape}")
    if np.shape(region) != real.shape[:2]:
        raise ValueError(f"region must be the tile's (h, w) {real.shape[:2]}, got {np.shape(region)}")

    def view(change):
        return 0.5 + CHANGE_VIEW_GAIN * change

    panels = [real, view(real - real_nc), np.repeat(np.asarray(region, np.float64)[..., None], 3, axis=2)]
    for name, (sim, sim_nc, gains) in sims.items():
        sim, sim_nc = np.asarray(sim, np.float64), np.asarray(sim_nc, np.float64)
        if sim.shape != real.shape or sim_nc.shape != real.shape:
            raise ValueError(f"{name}: its tile and no-contact tile must be the real tile's {real.shape}, got "
                             f"{sim.shape} and {sim_nc.shape}")
        g = np.asarray(gains, np.float64).reshape(3)
        panels += [sim_nc * g, view((sim - sim_nc) * g)]
    return np.clip(np.concatenate(panels, axis=1), 0.0, 1.0)
