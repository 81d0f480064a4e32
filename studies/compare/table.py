"""Table 1 of a capture: one row per method, MAE, SSIM and PSNR against the real images.

Each metric is a mean over taps with a percentile bootstrap interval (taps resampled,
seeded: ``studies.gap.metrics.mean_ci``), both over the full frame, as the paper
published it (the black border included), and masked to the sensor's image circle. Every
row resamples with the same seed, so rows over the same taps resample the same taps.
"""

from __future__ import annotations

import numpy as np

from studies.gap import metrics

SCOPES = ("full", "masked")
CONFIDENCE = 0.95
#: How each metric is printed: its name, unit and digits.
FORMATS = {"mae": ("MAE", "", 4), "ssim": ("SSIM", "", 3), "psnr": ("PSNR", " (dB)", 1)}


def score(real: np.ndarray, images: np.ndarray, mask: np.ndarray) -> dict[str, dict[str, np.ndarray]]:
    """Per-tap metrics of a method's images against the real ones: {scope: {metric: (N,)}}.

    real, images : (N, H, W, 3) float in [0, 1]; mask : (H, W) bool, the image circle.
    """
    return metrics.per_sample(real, images, mask)


def row(label: str, method: dict, values: dict, ids: list[str], resamples: int = 2000, seed: int = 0,
        confidence: float = CONFIDENCE) -> dict:
    """A table row: the method's description, its taps, and per scope and metric the mean
    with its interval; ``per_tap`` keeps the values (for ``subset``)."""
    if resamples < 1:
        raise ValueError(f"resamples must be >= 1, got {resamples}")
    n = len(ids)
    for scope in SCOPES:
        for m in metrics.METRICS:
            if len(values[scope][m]) != n:
                raise ValueError(f"values[{scope!r}][{m!r}] has {len(values[scope][m])} taps for {n} ids")
    out = {"label": label, **method, "taps": n, "ids": list(ids)}
    for scope in SCOPES:
        out[scope] = {m: metrics.mean_ci(values[scope][m], confidence, resamples, seed) for m in metrics.METRICS}
    out["per_tap"] = {scope: {m: [float(v) for v in values[scope][m]] for m in metrics.METRICS} for scope in SCOPES}
    return out


def subset(r: dict, ids: list[str], resamples: int = 2000, seed: int = 0, confidence: float = CONFIDENCE) -> dict:
    """Row ``r`` over the taps ``ids`` only (each one of its taps)."""
    index = {sid: i for i, sid in enumerate(r["ids"])}
    missing = [sid for sid in ids if sid not in index]
    if missing:
        raise ValueError(f"ids must be taps of row {r['label']!r}, got {missing[:5]}")
    pick = [index[sid] for sid in ids]
    values = {scope: {m: np.asarray(r["per_tap"][scope][m])[pick] for m in metrics.METRICS} for scope in SCOPES}
    method = {k: v for k, v in r.items() if k not in ("label", "taps", "ids", "per_tap", *SCOPES)}
    return row(r["label"], method, values, ids, resamples, seed, confidence)


def cell(ci: dict, metric: str) -> str:
    """'mean [low, high]' of a metric's interval."""
    digits = FORMATS[metric][2]
    return f"{ci['mean']:.{digits}f} [{ci['low']:.{digits}f}, {ci['high']:.{digits}f}]"


def header() -> list[str]:
    return ["method", "taps"] + [f"{FORMATS[m][0]}{FORMATS[m][1]}, {'full frame' if s == 'full' else 'image circle'}"
                                 for s in SCOPES for m in metrics.METRICS]


def cells(r: dict) -> list[str]:
    return [r["label"], str(r["taps"])] + [cell(r[s][m], m) for s in SCOPES for m in metrics.METRICS]


def markdown(rows: list[dict], title: str) -> str:
    """A markdown table of ``rows`` under a ``###`` title."""
    head = header()
    lines = [f"### {title}", "", "| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    lines += ["| " + " | ".join(cells(r)) + " |" for r in rows]
    return "\n".join(lines) + "\n"
