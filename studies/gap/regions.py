"""Where the gap lies: per-pixel error maps and the error split by region, contact,
colour channel and contact depth.

Regions of the image circle come from the undeformed membrane seen at each pixel. Each
shape family names its own (``scenes.shapes.interface.Family.regions``): a finger's tip
(beyond the capsule's junction with its tip, else the farthest fifth of the visible
membrane along the sensor axis) and body, a flat pad's centre and rim. The area near the
LEDs (the third of the family's last region closest to an LED) is every family's. A
sample's contact area is where its depth map differs from D_ref, grown by the elastic
smoothing's reach.
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage

from scenes.camera import CONTACT_EPS_M, Camera, reference_depth
from scenes.geometry import membrane_mesh
from scenes.image_stats import bootstrap_interval
from scenes.shapes import REGIONS as SHAPE_REGIONS, family
from scenes.spec import SensorSpec

#: Every region of every family, in the order reports list them (``region_names``: a sensor's).
REGIONS = SHAPE_REGIONS + ("near_leds",)
CHANNELS = ("red", "green", "blue")
#: Contact depth bins, metres (lower edges; the last is open).
DEPTH_BINS_M = (0.0, 0.5e-3, 1.0e-3, 1.5e-3, 2.5e-3, 4.0e-3)


def region_names(spec: SensorSpec) -> tuple[str, ...]:
    """The regions ``region_labels`` gives for ``spec``: its shape family's, then near_leds."""
    return family(spec.membrane.shape).REGIONS + ("near_leds",)


def region_labels(spec: SensorSpec, camera: Camera | None = None, ref: np.ndarray | None = None) -> dict[str, np.ndarray]:
    """Boolean (H, W) masks of ``region_names(spec)`` that split the sensor's image circle:
    its shape family's regions, the area near the LEDs carved out of the last."""
    camera = Camera.from_spec(spec) if camera is None else camera
    if ref is None:
        ref = reference_depth(membrane_mesh(spec), camera)[0]
    P = ref[..., None] * camera.rays
    inside = camera.mask
    shape = family(spec.membrane.shape)
    labels = dict(shape.regions(spec.membrane, P, inside))
    last = shape.REGIONS[-1]
    rest = labels[last]
    leds = np.array([led.position for led in spec.leds])
    distance = np.min(np.linalg.norm(P[..., None, :] - leds, axis=-1), axis=-1)
    if rest.any():
        near = rest & (distance <= np.quantile(distance[rest], 1 / 3))
    else:
        near = rest
    labels[last] = rest & ~near
    labels["near_leds"] = near
    return labels


def contact_masks(depth: np.ndarray, ref: np.ndarray, reach_px: int) -> np.ndarray:
    """(N, H, W) bool: where each contact can change the image (its imprint, grown by
    ``reach_px``)."""
    out = np.empty(depth.shape, bool)
    for i, d in enumerate(depth):
        hit = (ref - d) > CONTACT_EPS_M
        out[i] = ndimage.binary_dilation(hit, iterations=reach_px) if hit.any() else hit
    return out


def error_maps(real: np.ndarray, sim: np.ndarray) -> dict[str, np.ndarray]:
    """Per-pixel statistics over samples of the error real - sim:
    mean (H, W, 3) signed, spread (H, W, 3) standard deviation, mean_abs (H, W, 3)."""
    err = real.astype(np.float64) - sim
    return {"mean": err.mean(axis=0), "spread": err.std(axis=0), "mean_abs": np.abs(err).mean(axis=0)}


def _area_stats(err: np.ndarray, masks: np.ndarray, seed: int) -> dict:
    """Per-sample MAE over each sample's mask, and its mean with a bootstrap CI."""
    values = np.array([np.abs(e[m]).mean() if m.any() else np.nan for e, m in zip(err, masks)])
    signed = np.array([e[m].mean() if m.any() else np.nan for e, m in zip(err, masks)])
    ok = np.isfinite(values)
    if not ok.any():
        return {"samples": 0}
    return {"samples": int(ok.sum()), "mae": bootstrap_interval(values[ok], seed=seed), "signed": float(np.mean(signed[ok])),
            "spread": float(np.std(values[ok]))}


def where(real: np.ndarray, sim: np.ndarray, depth: np.ndarray | None, records: list[dict], spec: SensorSpec,
          seed: int = 0) -> dict:
    """The gap split by region, contact, channel and contact depth (per-sample MAE, mean
    with a bootstrap interval, mean signed error real - sim, spread across samples)."""
    camera = Camera.from_spec(spec)
    ref = reference_depth(membrane_mesh(spec), camera)[0]
    labels = region_labels(spec, camera, ref)
    err = real.astype(np.float32) - sim
    n = len(err)
    out = {"regions": {}, "contact": {}, "channels": {}, "depth": {}}
    for name in labels:
        out["regions"][name] = _area_stats(err, np.broadcast_to(labels[name], (n,) + labels[name].shape), seed)
        out["regions"][name]["pixels"] = int(labels[name].sum())
    if depth is not None:
        contact = contact_masks(depth, ref, int(spec.elastic.radius_px)) & camera.mask
        out["contact"]["contact"] = _area_stats(err, contact, seed)
        out["contact"]["no_contact"] = _area_stats(err, camera.mask & ~contact, seed)
    for c, name in enumerate(CHANNELS):
        out["channels"][name] = _area_stats(err[..., c:c + 1], np.broadcast_to(camera.mask, (n,) + camera.shape), seed)
    measured = np.array([float(r.get("measured_depth", r.get("commanded_depth", np.nan)) or np.nan) for r in records])
    if np.isfinite(measured).any():
        edges = np.asarray(DEPTH_BINS_M)
        bins = np.digitize(measured, edges) - 1
        for b in sorted(set(bins[np.isfinite(measured)])):
            sel = (bins == b) & np.isfinite(measured)
            lo = edges[b]
            hi = edges[b + 1] if b + 1 < len(edges) else None
            key = f"{lo * 1e3:.1f}-{hi * 1e3:.1f} mm" if hi is not None else f">= {lo * 1e3:.1f} mm"
            out["depth"][key] = _area_stats(err[sel], np.broadcast_to(camera.mask, (int(sel.sum()),) + camera.shape),
                                            seed)
    return out, labels
