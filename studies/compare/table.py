"""Table 1 of a capture: one row per method, MAE, SSIM and PSNR against the real images.

Each metric is a mean over taps with a percentile bootstrap interval (taps resampled,
seeded: ``scenes.image_stats.bootstrap_interval``), over the full frame, as the paper published it
(the black border included), masked to the sensor's image circle, and over each tap's
contact region (``scenes.captures.press_regions``). Every row resamples with the same
seed, so rows over the same taps resample the same taps. A row also has the contact
strength (``scenes.image_stats.contact_strength``): simulated over real, per tap, its mean
with an interval and its median.
"""

from __future__ import annotations

import numpy as np

from scenes import image_stats

SCOPES = ("full", "masked", "contact")
#: How each scope is named in tables.
SCOPE_NAMES = {"full": "full frame", "masked": "image circle", "contact": "contact"}
CONFIDENCE = 0.95
#: How each metric is printed: its name, unit and digits.
FORMATS = {"mae": ("MAE", "", 4), "ssim": ("SSIM", "", 3), "psnr": ("PSNR", " (dB)", 1)}


def score(real: np.ndarray, images: np.ndarray, mask: np.ndarray,
          contact: np.ndarray | None = None) -> dict[str, dict[str, np.ndarray]]:
    """Per-tap metrics of a method's images against the real ones: {scope: {metric: (N,)}}.

    real, images : (N, H, W, 3) float in [0, 1]; mask : (H, W) bool, the image circle;
    contact : (N, H, W) bool, each tap's contact region (None: no contact scope).
    """
    return image_stats.per_sample(real, images, mask, contact=contact)


def _interval(values, confidence: float, resamples: int, seed: int) -> dict:
    """bootstrap_interval of the finite values (a tap whose region is empty is NaN); NaN when none."""
    values = np.asarray(values, np.float64)
    finite = values[np.isfinite(values)]
    if len(finite) == 0:
        return {"mean": float("nan"), "low": float("nan"), "high": float("nan")}
    return image_stats.bootstrap_interval(finite, confidence, resamples, seed)


def row(label: str, method: dict, values: dict, ids: list[str], resamples: int = 2000, seed: int = 0,
        confidence: float = CONFIDENCE, strength: np.ndarray | None = None) -> dict:
    """A table row: the method's description, its taps, and per scope and metric the mean
    with its interval; ``per_tap`` keeps the values (for ``subset``). ``strength`` (N,),
    each tap's contact strength ratio (simulated over real), adds ``strength``: its mean
    with an interval, its median and the values."""
    if resamples < 1:
        raise ValueError(f"resamples must be >= 1, got {resamples}")
    n = len(ids)
    scopes = [s for s in SCOPES if s in values]
    for scope in scopes:
        for m in image_stats.METRICS:
            if len(values[scope][m]) != n:
                raise ValueError(f"values[{scope!r}][{m!r}] has {len(values[scope][m])} taps for {n} ids")
    out = {"label": label, **method, "taps": n, "ids": list(ids)}
    for scope in scopes:
        out[scope] = {m: _interval(values[scope][m], confidence, resamples, seed) for m in image_stats.METRICS}
    out["per_tap"] = {scope: {m: [float(v) for v in values[scope][m]] for m in image_stats.METRICS} for scope in scopes}
    if strength is not None:
        strength = np.asarray(strength, np.float64)
        if strength.shape != (n,):
            raise ValueError(f"strength must be ({n},), one ratio per tap, got {strength.shape}")
        finite = strength[np.isfinite(strength)]
        out["strength"] = {**_interval(strength, confidence, resamples, seed),
                           "median": float(np.median(finite)) if len(finite) else float("nan"),
                           "per_tap": [float(v) for v in strength]}
    return out


def subset(r: dict, ids: list[str], resamples: int = 2000, seed: int = 0, confidence: float = CONFIDENCE) -> dict:
    """Row ``r`` over the taps ``ids`` only (each one of its taps)."""
    index = {sid: i for i, sid in enumerate(r["ids"])}
    missing = [sid for sid in ids if sid not in index]
    if missing:
        raise ValueError(f"ids must be taps of row {r['label']!r}, got {missing[:5]}")
    pick = [index[sid] for sid in ids]
    scopes = [s for s in SCOPES if s in r["per_tap"]]
    values = {scope: {m: np.asarray(r["per_tap"][scope][m])[pick] for m in image_stats.METRICS} for scope in scopes}
    method = {k: v for k, v in r.items() if k not in ("label", "taps", "ids", "per_tap", "strength", *SCOPES)}
    strength = np.asarray(r["strength"]["per_tap"])[pick] if "strength" in r else None
    return row(r["label"], method, values, ids, resamples, seed, confidence, strength)


def cell(ci: dict, metric: str) -> str:
    """'mean [low, high]' of a metric's interval."""
    digits = FORMATS[metric][2]
    return f"{ci['mean']:.{digits}f} [{ci['low']:.{digits}f}, {ci['high']:.{digits}f}]"


def scopes_of(rows: list[dict]) -> list[str]:
    """The scopes every row has, in SCOPES' order."""
    return [s for s in SCOPES if all(s in r for r in rows)]


def header(rows: list[dict]) -> list[str]:
    strength = ["contact strength, sim / real (mean [CI]; median)"] if any("strength" in r for r in rows) else []
    return ["method", "taps"] + [f"{FORMATS[m][0]}{FORMATS[m][1]}, {SCOPE_NAMES[s]}"
                                 for s in scopes_of(rows) for m in image_stats.METRICS] + strength


def cells(r: dict, rows: list[dict] | None = None) -> list[str]:
    rows = rows or [r]
    out = [r["label"], str(r["taps"])] + [cell(r[s][m], m) for s in scopes_of(rows) for m in image_stats.METRICS]
    if any("strength" in x for x in rows):
        st = r.get("strength")
        out.append(f"{st['mean']:.2f} [{st['low']:.2f}, {st['high']:.2f}]; {st['median']:.2f}" if st else "-")
    return out


def markdown(rows: list[dict], title: str) -> str:
    """A markdown table of ``rows`` under a ``###`` title."""
    head = header(rows)
    lines = [f"### {title}", "", "| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    lines += ["| " + " | ".join(cells(r, rows)) + " |" for r in rows]
    return "\n".join(lines) + "\n"
