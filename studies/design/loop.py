"""The design loop: sweep a sensor's design parameters, score each design with the fast
path, check the best and the worst with the physically based reference, and report.

For each design (``studies.design.sweep``):

1. its standard taps: the extended protocol's nominal contact points (5 rows x 16
   contacts over the membrane, ``scenes.protocol.extended_protocol``), each pressed by one
   indenter (default the paper's sphere) along the local normal to STANDARD_DEPTH_M (1 mm,
   so that designs with an elastomer thinner than the protocol's 2 mm can be compared;
   a design thinner than the tap's depth is refused), on the MuJoCo rig, as a dataset
   captures them (the rig's no-contact capture is D_ref);
2. the fast path renders each tap as ``tactile-sim dataset`` does (the dataset renderer
   ``phong_reference.plugin`` with one light field, the elastic layer model so that the
   elastomer's thickness matters, no background);
3. ``studies.design.score`` scores the taps: contrast in camera-noise units per unit
   depth, its spread, and dead taps.

The fast path's light fields are unit directions: it has no falloff of light along the
membrane, so it cannot see a dead zone that distance or the shape's bends leave dark. So
when the reference runs, it renders every scored design's no-contact frame
(``reference_reach``): the share of the membrane it sees darker than DARK_FRACTION of
its own 99.5th percentile (the dark share), and the 10th percentile over its 99.5th (the
evenness of the light). The report puts both beside the fast path's score.

The designs are ranked by score. The best and the worst are rendered again by the
reference (``pbr_tactile``, through ``studies.pbr_field_comparison.reference_frame`` and
its cache) on the same REFERENCE_TAPS taps (the same rows and positions on each
membrane): the no-contact frame and each tap. Within one renderer the two designs'
contrasts share units, so the check compares ratios: per tap, best over worst, in the fast
path and in the reference. The reference agrees with the ranking on a tap when its ratio
is above 1 as well.

Run ``tactile-sim design --spec TOML --sweep NAME=START:STOP:COUNT [--sweep NAME2=...]
--out DIR``. It writes ``design.json``, ``summary.md``, ``sweep.png``, ``maps.png`` and
``check.png``.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np
from tqdm import tqdm

from scenes.camera import Camera
from scenes.dataset import atomic_write_json
from scenes.spec import SensorSpec

from .score import changed_pixels, design_score, tap_contrast
from .sweep import designs

#: The indenter of the standard tap, and its depth along the normal, metres.
INDENTER = "sphere"
STANDARD_DEPTH_M = 1.0e-3
#: The fast path's light field (the dataset renderer's default).
FIELD = "plane"
#: Taps the reference renders per checked design (it takes about a minute a frame here).
REFERENCE_TAPS = 4
#: A membrane pixel of the reference's no-contact frame darker than this share of the
#: frame's 99.5th percentile (largest channel) is dark: light hardly reaches it.
DARK_FRACTION = 0.05
JSON_NAME = "design.json"


def standard_taps(spec: SensorSpec, mesh, indenter: str = INDENTER, count: int | None = None,
                  depth: float = STANDARD_DEPTH_M):
    """The extended protocol's nominal taps of one indenter at ``depth`` metres: (N,)
    ``scenes.taps.Tap``; ``count`` of them spread evenly over the protocol's order
    (default all 80)."""
    from scenes.protocol import extended_protocol

    n = standard_tap_count(count)  # refuses a bad count before the protocol is built
    taps = extended_protocol(spec, mesh, (indenter,), replicas=1, depth=depth).taps
    return taps if count is None else tuple(taps[i] for i in spread(len(taps), n))


def standard_tap_count(count: int | None = None) -> int:
    """How many taps ``standard_taps`` gives, without building the protocol: the extended
    protocol's rows x contacts per row (80), or ``count`` of them (a whole number >= 1)."""
    from scenes.protocol import EXTENDED_CONTACTS_PER_ROW, EXTENDED_ROLLS_RAD

    if count is not None and (not isinstance(count, int) or isinstance(count, bool) or count < 1):
        raise ValueError(f"count must be a whole number >= 1, got {count!r}")
    n = len(EXTENDED_ROLLS_RAD) * EXTENDED_CONTACTS_PER_ROW
    return n if count is None else min(count, n)


def spread(n: int, count: int) -> list[int]:
    """``count`` indices spread evenly over range(n), both ends included (all when count >= n)."""
    if count >= n:
        return list(range(n))
    return sorted(set(np.linspace(0, n - 1, count).round().astype(int).tolist()))


def evaluate(spec: SensorSpec, field: str = FIELD, indenter: str = INDENTER, taps: int | None = None,
             keep: Sequence[int] = (), depth: float = STANDARD_DEPTH_M) -> dict:
    """Score one design with the fast path.

    taps : standard taps used (default all). keep : indices (into those taps) whose depth
    maps and frames are returned for the reference check and the figures.

    Returns {"score": ..., "taps": [{row, position, point, depth_m, contrast}],
    "no_contact": (H, W, 3), "kept": {index: (depth, frame)}, "ref_depth", "seconds"}.
    """
    from phong_reference.plugin import PhongDatasetRenderer
    from scenes.geometry import membrane_mesh
    from scenes.rig import tap_depths

    t0 = time.perf_counter()
    mesh = membrane_mesh(spec)
    camera = Camera.from_spec(spec)
    standard = standard_taps(spec, mesh, indenter, taps, depth)
    captures = tap_depths(spec, standard, mesh)
    ref_depth, _ = next(captures)
    renderer = PhongDatasetRenderer(spec, mesh, camera, ref_depth, {"field": field, "elastic": "layer"})
    no_contact = renderer.no_contact
    rows, kept = [], {}
    for k, (pressed, tap) in enumerate(captures):
        frame = renderer.render(pressed)
        rows.append({"row": tap.row, "position": tap.position, "point": list(map(float, tap.point)),
                     "depth_m": float(tap.depth), "contrast": tap_contrast(no_contact, frame)})
        if k in keep:
            kept[k] = (pressed, frame)
    score = design_score(np.array([r["contrast"] for r in rows]), np.array([r["depth_m"] for r in rows]))
    return {"score": score, "taps": rows, "no_contact": no_contact, "kept": kept, "ref_depth": ref_depth,
            "seconds": time.perf_counter() - t0}


def reference_check(spec: SensorSpec, evaluated: dict, indices: Sequence[int], settings, cache: Path,
                    label: str) -> dict:
    """The reference's contrast on some of a design's taps: raw radiance, p95 over the
    pixels the fast path's tap changes (area-averaged to the film) of the largest
    channel's |change|; and the reference's noise there, the same statistic far from the
    contact (more than 2 film pixels away)."""
    from scipy import ndimage

    from scenes.geometry import membrane_mesh
    from studies.pbr_field_comparison.contacts import NO_CONTACT
    from studies.pbr_field_comparison.frames import downsample, reference_frame

    mesh = membrane_mesh(spec)
    camera = Camera.from_spec(spec)
    shape = (settings.height, settings.width)
    mask = camera.scaled(settings.width, settings.height).mask
    ref_depth = evaluated["ref_depth"]
    mean0, _, _ = reference_frame(f"{label}_{NO_CONTACT}", None, ref_depth, mesh, spec, camera, settings, cache)
    out = []
    for k in indices:
        depth, frame = evaluated["kept"][k]
        changed = changed_pixels(evaluated["no_contact"], frame)
        near = downsample(np.repeat(changed[..., None], 3, axis=-1).astype(np.float32), shape)[..., 0] > 0
        near &= mask
        far = mask & ~ndimage.binary_dilation(near, iterations=2)
        mean, _, _ = reference_frame(f"{label}_tap{k}", depth, ref_depth, mesh, spec, camera, settings, cache)
        change = np.abs(mean - mean0).max(axis=-1)
        contrast = float(np.percentile(change[near], 95.0)) if near.any() else 0.0
        noise = float(np.percentile(change[far], 95.0)) if far.any() else 0.0
        out.append({"tap": int(k), "contrast": contrast, "noise": noise, "frame": mean, "no_contact": mean0})
    return {"taps": out}


def membrane_pixels(valid: np.ndarray, camera: Camera, shape: tuple[int, int]) -> np.ndarray:
    """(h, w) bool: film pixels inside the image circle whose every depth-camera pixel sees
    the membrane (``valid``, (H, W) bool, from ``scenes.camera.reference_depth``)."""
    from studies.pbr_field_comparison.frames import downsample

    seen = np.repeat(np.asarray(valid, bool)[..., None], 3, axis=-1).astype(np.float32)
    return (downsample(seen, shape)[..., 0] == 1.0) & camera.scaled(shape[1], shape[0]).mask


def reference_reach(spec: SensorSpec, evaluated: dict, settings, cache: Path, label: str) -> dict:
    """Where the reference's light reaches a design's membrane without contact: the dark
    share (pixels under DARK_FRACTION of the frame's p99.5, largest channel), the evenness
    (p10 over p99.5) and the p99.5 itself (linear radiance, comparable between designs)."""
    from scenes.camera import reference_depth
    from scenes.geometry import membrane_mesh
    from studies.pbr_field_comparison.contacts import NO_CONTACT
    from studies.pbr_field_comparison.frames import reference_frame

    camera = Camera.from_spec(spec)
    mesh = membrane_mesh(spec)
    mean, _, _ = reference_frame(f"{label}_{NO_CONTACT}", None, evaluated["ref_depth"], mesh, spec, camera, settings,
                                 cache)
    seen = membrane_pixels(reference_depth(mesh, camera)[1], camera, (settings.height, settings.width))
    level = mean.max(axis=-1)[seen]
    top = float(np.percentile(level, 99.5))
    if not top > 0:
        return {"dark_share": 1.0, "evenness": 0.0, "p99_5": top}
    return {"dark_share": float(np.mean(level < DARK_FRACTION * top)),
            "evenness": float(np.percentile(level, 10.0) / top), "p99_5": top}


def run(spec: SensorSpec, sweep: Mapping[str, Sequence[float]], out: Path, field: str = FIELD,
        indenter: str = INDENTER, taps: int | None = None, reference: bool = True,
        reference_taps: int = REFERENCE_TAPS, settings=None, progress: bool = True,
        depth: float = STANDARD_DEPTH_M) -> dict:
    """Sweep, score, check and report; writes into ``out``. Returns the results."""
    from phong_reference.bake import METHODS
    from studies.pbr_field_comparison.frames import CACHE_FOLDER, Settings, check_settings

    from . import report

    if field not in METHODS:
        raise ValueError(f"field must be one of {METHODS}, got {field!r}")
    settings = Settings(width=160, height=120, photons=1 << 18, passes=4, spp=32) if settings is None else settings
    if reference:
        check_settings(settings, Camera.from_spec(spec))
    if not isinstance(reference_taps, int) or reference_taps < 1:
        raise ValueError(f"reference_taps must be a whole number >= 1, got {reference_taps!r}")
    t0 = time.perf_counter()
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    candidates = designs(spec, sweep)
    n_taps = standard_tap_count(taps)
    checked = spread(n_taps, reference_taps)
    shown = sorted(set(checked) | set(spread(n_taps, 4)))
    results, evaluated = [], {}
    for i, d in enumerate(tqdm(candidates, desc="designs", unit="design", disable=not progress)):
        entry = {"values": dict(d.values), "label": d.label, "refused": d.refused}
        if d.spec is not None:
            try:
                ev = evaluate(d.spec, field, indenter, taps, keep=shown, depth=depth)
            except ValueError as exc:  # a protocol the rig cannot reach on this membrane
                entry["refused"] = str(exc)
            else:
                evaluated[i] = ev
                entry.update(score=ev["score"], taps=ev["taps"], seconds=ev["seconds"])
        results.append(entry)
    scored = [i for i, r in enumerate(results) if r["refused"] is None]
    if not scored:
        raise ValueError("every design was refused: " + "; ".join(f"{r['label']}: {r['refused']}" for r in results))
    order = sorted(scored, key=lambda i: results[i]["score"]["score"], reverse=True)
    best, worst = order[0], order[-1]
    check = None
    cache = out / CACHE_FOLDER
    if reference:
        for i in tqdm(scored, desc="reference, no contact", unit="design", disable=not progress):
            results[i]["reference_reach"] = reference_reach(candidates[i].spec, evaluated[i], settings, cache,
                                                            f"design{i}")
    if reference and best != worst:
        check = {}
        for role, i in (("best", best), ("worst", worst)):
            check[role] = reference_check(candidates[i].spec, evaluated[i], checked, settings, cache,
                                          f"design{i}")
        check = summarise_check(check, evaluated[best], evaluated[worst], checked)
    data = {
        "sensor": spec.name, "family": spec.membrane.shape, "sweep": {k: list(v) for k, v in sweep.items()},
        "field": field, "indenter": indenter, "tap_depth_m": depth, "taps_per_design": n_taps,
        "designs": results, "ranking": [results[i]["label"] for i in order], "best": best, "worst": worst,
        "reference_settings": dataclasses.asdict(settings) if reference else None, "dark_fraction": DARK_FRACTION,
        "reference_check": None if check is None else {k: v for k, v in check.items() if k != "images"},
        "seconds": time.perf_counter() - t0,
    }
    atomic_write_json(out / JSON_NAME, data)
    (out / "summary.md").write_text(report.markdown(data))
    report.sweep_figure(out / "sweep.png", data)
    report.maps_figure(out / "maps.png", data, candidates, evaluated)
    report.check_figure(out / "check.png", data, evaluated, check)
    return data


def summarise_check(check: dict, best: dict, worst: dict, indices: Sequence[int]) -> dict:
    """Per checked tap, best over worst in each renderer; the reference agrees on a tap
    when both ratios exceed 1 (or both fall short)."""
    rows = []
    for k, rb, rw in zip(indices, check["best"]["taps"], check["worst"]["taps"]):
        fast = _ratio(best["taps"][k]["contrast"], worst["taps"][k]["contrast"])
        ref = _ratio(rb["contrast"], rw["contrast"])
        rows.append({"tap": int(k), "row": best["taps"][k]["row"], "position": best["taps"][k]["position"],
                     "fast_best": best["taps"][k]["contrast"], "fast_worst": worst["taps"][k]["contrast"],
                     "reference_best": rb["contrast"], "reference_worst": rw["contrast"],
                     "reference_noise_best": rb["noise"], "reference_noise_worst": rw["noise"],
                     "fast_ratio": fast, "reference_ratio": ref,
                     "agrees": None if fast is None or ref is None else bool((fast > 1) == (ref > 1))})
    known = lambda key: [r[key] for r in rows if r[key] is not None]  # noqa: E731
    return {"taps": rows, "agreeing_taps": sum(bool(r["agrees"]) for r in rows),
            "median_fast_ratio": float(np.median(known("fast_ratio"))) if known("fast_ratio") else None,
            "median_reference_ratio": float(np.median(known("reference_ratio"))) if known("reference_ratio") else None,
            "images": {role: check[role]["taps"] for role in ("best", "worst")}}


def _ratio(a: float, b: float) -> float | None:
    """a / b; None when the worst design shows nothing there (b = 0)."""
    return a / b if b > 0 else None
