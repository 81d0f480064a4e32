"""The renders of a comparison, in the real camera's frame: a capture's taps replayed at
their measured poses with the fast path (each light field, each background) and with the
physically based reference, scored against the real images (``table``).

The fast path is replayed once per light field with no background; each background is
then added as the renderer adds it, ``clip(S + k_a i_a B, 0, 1)`` in the image circle
(``phong_reference.render.finish``). The LED terms S are >= 0, so this equals rendering
with that background; the equality is tested. It lets the background stay where the real
camera sees it while the membrane's shading is aligned.

Alignment: with a profile, the renderers render the calibrated unit, already in the real
camera's frame. Without one, a capture's ``alignment`` block (``scenes.profile.Alignment``)
moves each simulated image into the real camera's frame (``scenes.profile.align_image``)
and the lens' image circle, which does not move, is applied again.

Every replay is a dataset under ``OUT/renders/`` (resumable: a second run renders only
what is missing).
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from phong_reference import plugin as phong
from phong_reference.background import make_background
from phong_reference.bake import METHODS
from phong_reference.plugin import OPTIONS as FAST_OPTIONS
from phong_reference.render import finish
from scenes.camera import Camera
from scenes.captures import frame_spread, press_regions, split
from scenes.dataset import load_sample, read_samples
from scenes.image_stats import contact_contrast, contact_strength
from scenes.images import read_rgb
from scenes.profile import Alignment, align_image, load_profile
from scenes.renderers import RendererPlugin
from rig.align import alignment_from_dict
from scenes.replay import Capture, read_capture, replay

from . import table

#: The renderers' names in the renders' folders (the fast path's) and in the table (the reference's).
FAST = "phong"
REFERENCE = "pbr"
#: The fast path's backgrounds: none, the renderer's solid colour, and the capture's own
#: no-contact image (background.png), as the paper used.
BACKGROUNDS = ("none", "solid", "real")
#: The peer simulators a comparison can score beside ours.
PEERS = ("taxim",)
#: Taps the reference renders by default: it takes minutes per tap.
REFERENCE_TAPS = 4
#: Examples shown in the report.
EXAMPLES = 3


def spread(ids: Sequence[str], n: int | None) -> list[str]:
    """``n`` of ``ids`` spread evenly over them, in order (all when ``n`` is None or at
    least their number)."""
    ids = list(ids)
    if n is None or n >= len(ids):
        return ids
    if n < 1:
        raise ValueError(f"the number of taps must be >= 1, got {n}")
    return [ids[i] for i in np.unique(np.linspace(0, len(ids) - 1, n).round().astype(int))]


def heldout_ids(ids: Sequence[str]) -> list[str]:
    """The judged half of a capture's samples: those a calibration from it holds out (the
    odd positions, ``scenes.captures.split``), in order."""
    ids = list(ids)
    return [sid for sid, fitted in zip(ids, split(len(ids))) if not fitted]


def with_background(shading: np.ndarray, background: np.ndarray, ambient: float, mask: np.ndarray) -> np.ndarray:
    """The fast path's image of LED terms ``shading`` (H, W, 3, >= 0) on ``background``
    (H, W, 3): clip(S + k_a i_a B, 0, 1) inside the image circle ``mask`` (H, W)."""
    return finish((np.asarray(shading, np.float32) + np.float32(ambient) * background).transpose(2, 0, 1), mask)


def load_images(root: Path, ids: Sequence[str], shape: tuple[int, int]) -> np.ndarray:
    """(N, H, W, 3) float32 images of the samples ``ids`` of a dataset."""
    by_id = {r["id"]: r for r in read_samples(root)}
    missing = [i for i in ids if i not in by_id]
    if missing:
        raise ValueError(f"{root} lacks samples {missing[:5]}")
    return np.stack([load_sample(root, by_id[i], shape)[0] for i in ids]).astype(np.float32)


class Aligner:
    """Simulated images -> the real camera's frame (module doc); the identity when there
    is nothing to apply."""

    def __init__(self, alignment: Alignment | None, camera: Camera, mask: np.ndarray):
        self.alignment, self.camera, self.mask = alignment, camera, mask

    def __call__(self, images: np.ndarray, masked: bool = True) -> np.ndarray:
        if self.alignment is None:
            return images
        out = np.stack([align_image(im, self.alignment, self.camera) for im in images]).astype(np.float32)
        return out * self.mask[..., None] if masked else out


def no_contact_of(root: Path, camera: Camera) -> np.ndarray:
    """(H, W, 3) float32, a replay's no-contact image (its background.png): what its contact
    strength is measured against."""
    return read_rgb(Path(root) / "background.png", camera.shape).astype(np.float32)


def _backgrounds(capture: Capture, camera: Camera, wanted: Sequence[str] | None) -> dict[str, np.ndarray]:
    have_real = (capture.root / "background.png").is_file()
    names = list(wanted) if wanted is not None else [b for b in BACKGROUNDS if b != "real" or have_real]
    unknown = [b for b in names if b not in BACKGROUNDS]
    if unknown or not names:
        raise ValueError(f"backgrounds must be some of {BACKGROUNDS}, got {names}")
    if "real" in names and not have_real:
        raise ValueError(f"background 'real' needs the capture's no-contact image, and {capture.root}/background.png "
                         "is missing")
    return {b: make_background(capture.root / "background.png" if b == "real" else b, camera) for b in names}


def contrast_budget(sim: dict, real: dict, sim_frame: dict, real_frame: dict) -> dict:
    """Where a method's contact strength against the real one comes from, per channel,
    from ``scenes.image_stats.contact_contrast`` of its taps and of the real ones and
    ``frame_spread`` of each no-contact image: the medians over the taps of

    - ``level_ratio``, its level over the real level: the camera's share (exposure, gains);
    - ``relative_ratio``, its relative change over the real one: the light's share, less
      what the camera's offset and response dilute (``relative``, ``real_relative``);
    - ``spread_ratio``, its change over its frame's spread against the real one's: what no
      gain, offset or response of a camera fitted to the no-contact image changes, so
      below 1 the light itself makes the contact too weak for how unevenly it lights the
      frame, and a calibration that evens the frame weakens the contact by as much;

    and each frame's ``range`` (high over low percentile) beside the real one's."""
    def median(x):
        x = np.asarray(x, np.float64)
        return [float(np.nanmedian(x[:, c])) if np.isfinite(x[:, c]).any() else float("nan") for c in range(3)]

    with np.errstate(invalid="ignore", divide="ignore"):
        spread = (sim["change"] / sim_frame["spread"]) / (real["change"] / real_frame["spread"])
        return {"level_ratio": median(sim["level"] / real["level"]),
                "relative_ratio": median(sim["relative"] / real["relative"]),
                "spread_ratio": median(spread),
                "relative": median(sim["relative"]), "real_relative": median(real["relative"]),
                "range": [float(v) for v in sim_frame["range"]], "real_range": [float(v) for v in real_frame["range"]],
                "channels": "rgb"}


def compare(
    capture_dir: str | Path,
    out: str | Path,
    profile: str | Path | None = None,
    options: dict | None = None,
    taps: int | None = None,
    heldout: bool = False,
    reference_taps: int = REFERENCE_TAPS,
    fields: Sequence[str] = METHODS,
    backgrounds: Sequence[str] | None = None,
    reference: bool = True,
    reference_renderer: RendererPlugin | None = None,
    reference_label: str = REFERENCE,
    peers: Sequence[str] = (),
    bootstrap: int = 2000,
    seed: int = 0,
    workers: int = 1,
    progress: bool = True,
) -> dict:
    """Render, score and report; returns the content of ``table.json``.

    Parameters
    ----------
    capture_dir : a capture of the rig (``scenes.replay.read_capture``).
    out : where table.json, table.md, report.html, its figures and ``renders/`` go.
    profile : a calibrated unit's profile.toml: both renderers render the unit (already
        in the real camera's frame), and the fast path's background is the profile's.
    options : renderer options as ``tactile-sim dataset`` takes them (but field and
        background, which the comparison sweeps): the fast path's (``rectify``,
        ``elastic``) go to it, the others to the reference.
    taps : the fast path's taps, spread evenly over the capture (None: all).
    heldout : only the capture's judged half (:func:`heldout_ids`): the taps a calibration
        from it did not fit.
    reference_taps : the reference's taps, spread evenly over the fast path's.
    fields, backgrounds : the fast path's light fields and backgrounds (None: every one
        the capture allows: ``real`` needs its background.png).
    reference : False leaves the reference out.
    reference_renderer, reference_label : the reference's renderer plugin (None: the
        physically based reference, ``pbr_tactile.plugin``; a stand-in in tests) and its
        name in the table (its row ``reference: <label>`` and the row's ``renderer``).
    peers : peer simulators scored beside ours, some of PEERS ("taxim": Taxim with its
        shipped calibration and refitted on the capture's fitted half, ``studies.compare.taxim``;
        an imported set of ball presses). One that cannot run here is listed in the
        result's ``peers`` with its reason.
    bootstrap, seed : bootstrap resamples of the intervals, and their seed.
    """
    from .report import write_report

    t0 = time.perf_counter()
    out = Path(out)
    options = dict(options or {})
    for key in ("field", "background", "profile"):
        if key in options:
            raise ValueError(f"options must not hold {key!r}: the comparison sets it (fields, backgrounds, profile)")
    for peer in peers:
        if peer not in PEERS:
            raise ValueError(f"peers must be some of {PEERS}, got {peer!r}")
    unknown = [f for f in fields if f not in METHODS]
    if unknown or not fields:
        raise ValueError(f"fields must be some of {METHODS}, got {list(fields)}")
    if profile is not None and backgrounds is not None:
        raise ValueError("give backgrounds or a profile, not both: the profile's background term is the "
                         "calibrated unit's")
    capture = read_capture(capture_dir)
    spec = capture.spec
    camera = Camera.from_spec(spec)
    unit = spec if profile is None else load_profile(profile, spec).sensor_spec(spec)
    mask = Camera.from_spec(unit).mask  # the lens' image circle (the profile's, if any)
    block = capture.meta.get("alignment")
    alignment = alignment_from_dict(block) if block is not None and profile is None else None
    align = Aligner(alignment, camera, mask)
    ids = spread(heldout_ids(capture.ids) if heldout else capture.ids, taps)
    ref_ids = spread(ids, reference_taps) if reference else []
    real = load_images(capture.root, ids, camera.shape)
    by_id = {r["id"]: r for r in capture.records}
    real_bg = read_rgb(capture.root / "background.png", camera.shape) if (capture.root / "background.png").is_file() \
        else None
    annotated = all("contact_center_px" in by_id[i] for i in ids)
    regions = None if real_bg is None and not annotated else press_regions(
        [by_id[i] for i in ids], real, real_bg if real_bg is not None else np.zeros_like(real[0]), mask)
    real_strength = None if regions is None or real_bg is None else contact_strength(real, real_bg, regions)
    real_contrast = None if real_strength is None else contact_contrast(real, real_bg, regions)
    fast_options = {k: v for k, v in options.items() if k in FAST_OPTIONS}
    ref_options = {k: v for k, v in options.items() if k not in FAST_OPTIONS}
    common = {"workers": workers, "progress": progress}
    renders = out / "renders"

    shown = spread(ref_ids or ids, EXAMPLES)  # the report's example taps
    rows = []
    examples = {"ids": shown, "real": real[[ids.index(i) for i in shown]], "images": {}, "mean_abs": {}}

    def add(label: str, method: dict, stack: np.ndarray, which: list[str], no_contact: np.ndarray | None) -> None:
        """Score a method's images of the taps ``which`` (and its no-contact image, for the
        contact strength); keep its error map and examples."""
        pick = [ids.index(i) for i in which]
        region = None if regions is None else regions[pick]
        values = table.score(real[pick], stack, mask, region)
        strength = None
        if real_strength is not None and no_contact is not None:
            strength = contact_strength(stack, no_contact, region) / real_strength[pick]
        rows.append(table.row(label, method, values, which, bootstrap, seed, strength=strength))
        if strength is not None:
            rows[-1]["contrast"] = contrast_budget(contact_contrast(stack, no_contact, region),
                                                   {k: v[pick] for k, v in real_contrast.items()},
                                                   frame_spread(no_contact, mask), frame_spread(real_bg, mask))
        examples["mean_abs"][label] = np.abs(stack - real[pick]).mean(axis=(0, 3))
        examples["images"][label] = stack[[which.index(i) for i in shown]]

    bgs = None if profile is not None else _backgrounds(capture, camera, backgrounds)
    for field in fields:
        if profile is None:
            where = renders / f"{FAST}_{field}"
            replay(capture, where, phong, {**fast_options, "field": field, "background": "none"}, ids=ids, **common)
            shading = align(load_images(where, ids, camera.shape), masked=False)
            shading_0 = align(no_contact_of(where, camera)[None], masked=False)[0]
            for name, background in bgs.items():
                stack = np.stack([with_background(s, background, spec.material.ambient, mask) for s in shading])
                add(f"fast: {field}, background {name}", {"method": "fast", "field": field, "background": name},
                    stack, ids, with_background(shading_0, background, spec.material.ambient, mask))
        else:
            where = renders / f"{FAST}_{field}_profile"
            replay(capture, where, phong, {**fast_options, "field": field, "profile": str(profile)}, ids=ids, **common)
            add(f"fast: {field}, profile", {"method": "fast", "field": field, "background": "profile"},
                load_images(where, ids, camera.shape), ids, no_contact_of(where, camera))
    peer_status = {}
    for peer in peers:
        from . import taxim

        fitted_ids = [sid for sid, f in zip(capture.ids, split(len(capture.ids))) if f]
        try:
            renders_of = taxim.peer_renders(capture, ids, fitted_ids, load_images(capture.root, fitted_ids, camera.shape),
                                            real_bg)
        except (ImportError, ValueError) as exc:
            peer_status[peer] = {"ran": False, "why": str(exc)}
            continue
        peer_status[peer] = {"ran": True, "variants": {v: r["note"] for v, r in renders_of.items()}}
        for variant, r in renders_of.items():
            add(f"peer: {peer}, {variant}", {"method": "peer", "peer": peer, "variant": variant},
                r["images"] * mask[..., None], ids, r["no_contact"] * mask[..., None])
    if reference:
        if reference_renderer is None:
            from pbr_tactile import plugin as reference_renderer
        where = renders / ("reference" if profile is None else "reference_profile")
        opts = ref_options if profile is None else {**ref_options, "profile": str(profile)}
        replay(capture, where, reference_renderer, opts, ids=ref_ids, **common)
        add(f"reference: {reference_label}", {"method": "reference", "renderer": reference_label},
            align(load_images(where, ref_ids, camera.shape)), ref_ids, align(no_contact_of(where, camera)[None])[0])

    best = min((r for r in rows if r["method"] == "fast"), key=lambda r: r["masked"]["mae"]["mean"])
    on_reference = [table.subset(r, ref_ids, bootstrap, seed) for r in rows] if 0 < len(ref_ids) < len(ids) else []
    if profile is not None:
        note = "not applied: the renderers render the profile's unit, in the real camera's frame already"
    elif alignment is None:
        note = "not applied: the capture has no alignment block"
    else:
        note = "applied: each simulated image moved by the capture's alignment block (scenes.profile.align_image)"
    result = {
        "capture": str(capture.root.resolve()),
        "heldout": heldout,
        "contact": ("each tap's annotated contact disc" if regions is not None and annotated else
                    "where each real tap differs from the real no-contact image (scenes.captures.contact_region)"
                    if regions is not None else "none: the capture has neither annotations nor a background.png"),
        "real_strength": None if real_strength is None else [float(v) for v in real_strength],
        "peers": peer_status,
        "taps": ids,
        "reference_taps": ref_ids,
        "profile": None if profile is None else str(profile),
        "alignment": {"applied": alignment is not None, "block": block, "note": note},
        "mask": {"what": "the lens' image circle", "pixels": int(mask.sum()), "radius_px": unit.camera.mask_radius_px,
                 "center_px": unit.camera.mask_center_px},
        "confidence": table.CONFIDENCE,
        "bootstrap": bootstrap,
        "seed": seed,
        "options": options,
        "best_fast": best["label"],
        "rows": rows,
        "on_reference_taps": on_reference,
        "seconds": time.perf_counter() - t0,
    }
    write_report(out, result, examples, mask)
    return result
