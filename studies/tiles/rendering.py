"""Both renderers on a recovered contact: each one's tile scored against the real one, and
what its Monte Carlo noise alone reads as."""

from __future__ import annotations

import time

import numpy as np

from .frames import Alignment, to_tile
from .recovery import Contact
from .scoring import score


def simulated(contact: Contact, renderers: dict, shape, spec_inputs: tuple, real: np.ndarray, real_nc: np.ndarray,
              alignment: Alignment, region: np.ndarray, inside: np.ndarray | None = None,
              keep: dict | None = None) -> tuple[dict, dict]:
    """Each renderer's tile of a contact pressed on our membrane (``spec_inputs``: D_ref,
    camera, mesh), scored against the real tile (``score``, over ``inside`` for its
    exposure, with the renderer's record: the reference's passes and contact RSE):
    ({name: score}, {name: s}). ``keep``, a dict: each renderer's (tile, no-contact tile,
    exposure gains) put in it, for ``change_figure``."""
    from scenes.generate import render_sample

    ref_depth, camera, mesh = spec_inputs
    try:
        depth = contact.depth_map(ref_depth, camera, mesh, shape)
    except ValueError as exc:
        return {name: {"strength": None, "strength_ratio": None, "shape_corr": None, "error": str(exc)}
                for name in renderers}, {}
    shape_hw = real.shape[:2]
    scores, seconds = {}, {}
    for name, r in renderers.items():
        t0 = time.perf_counter()
        out = render_sample(r, depth)
        seconds[name] = time.perf_counter() - t0
        tile, nc_tile = to_tile(out["image"], shape_hw, alignment), to_tile(r.no_contact, shape_hw, alignment)
        sc = score(tile, nc_tile, real, real_nc, region, inside)
        if keep is not None:
            keep[name] = (tile, nc_tile, (sc.get("exposed") or {}).get("gains", [1.0, 1.0, 1.0]))
        noise = image_noise(r, out)
        if noise is not None and region.any():
            sc.update(noise_floor([to_tile(n, shape_hw, alignment) for n in noise], region, sc))
        scores[name] = {**sc, **{k: v for k, v in out["record"].items() if k in ("passes", "contact_rse")}}
    return scores, seconds


#: Noise images drawn per render to read what its noise alone shows (``noise_floor``).
NOISE_DRAWS = 4


def image_noise(renderer, out: dict, draws: int = NOISE_DRAWS, seed: int = 0) -> list[np.ndarray] | None:
    """``draws`` (H, W, 3) images of a Monte Carlo render's noise alone: zero-mean Gaussian
    film pixels of the render's standard error (its variance of the mean,
    ``arrays["variance"]``, block-averaged back to the film), brought to the camera's size
    as the render's image is (the renderer's ``camera_size``) and seen at its exposure
    ``gain`` in its image circle; None for a renderer without a variance (the fast path) or
    with a profile's image model."""
    variance = out["arrays"].get("variance")
    gain = getattr(renderer, "gain", None)
    if variance is None or gain is None or getattr(renderer, "profile", None) is not None:
        return None
    from scenes.images import block_mean

    variance = np.maximum(np.asarray(variance, np.float64), 0.0)
    factor = variance.shape[1] // renderer.opts["film"][0]
    sigma = np.sqrt(block_mean(variance, factor) if factor > 1 else variance)
    rng = np.random.default_rng(seed)
    mask = renderer.camera.mask[..., None]
    return [gain * np.asarray(renderer.camera_size(sigma * rng.standard_normal(sigma.shape)), np.float64) * mask
            for _ in range(draws)]


def noise_floor(noise_tiles: list[np.ndarray], region: np.ndarray, sc: dict) -> dict:
    """What a render's own noise alone reads as contact strength over the region: the
    mean |change| of its noise images (``image_noise``, brought to the tile), all channels
    (``noise_strength``) and, through the exposure, the judged ones
    (``exposed.noise_strength``). A strength within a few of these is noise's."""
    per_channel = np.mean([np.abs(t[region]).mean(axis=0) for t in noise_tiles], axis=0)
    out = {"noise_strength": float(per_channel.mean())}
    e = sc.get("exposed")
    if e is not None:
        judged = np.array([ch in e["channels"] for ch in "rgb"])
        e["noise_strength"] = float(np.mean(np.asarray(e["gains"])[judged] * per_channel[judged]))
    return out
