"""The study's summary over contacts: bootstrap means, the best field, and the answer in words."""

from __future__ import annotations

import numpy as np

from scenes.image_stats import bootstrap_interval

from .metrics import CHANGE_KINDS, CORRELATION, KINDS, METRICS

#: The criterion that names the best field: lowest mean contact-change MAE.
CRITERION = ("change", "mae")

CONFIDENCE = 0.95
N_RESAMPLES = 9999
#: Fewer contacts than this and the conclusion says the intervals mean little.
MIN_CONTACTS_FOR_CI = 5


def bootstrap_mean(values, seed: int, confidence: float = CONFIDENCE, n_resamples: int = N_RESAMPLES) -> dict:
    """Mean over contacts and its percentile-bootstrap interval (contacts resampled:
    ``scenes.image_stats.bootstrap_interval``) as this study reports it, with the values."""
    values = np.asarray(values, dtype=np.float64)
    if values.ndim != 1 or len(values) < 2 or not np.isfinite(values).all():
        raise ValueError(f"values must be >= 2 finite numbers, got {values!r}")
    ci = bootstrap_interval(values, confidence, n_resamples, seed)
    return {"mean": ci["mean"], "ci_low": ci["low"], "ci_high": ci["high"], "values": values.tolist()}


def summarise(per_contact: dict[str, list[dict]], seed: int, no_change: list[dict]) -> dict:
    """Per field, kind and metric: mean over contacts with its bootstrap CI; the best field
    by CRITERION, with paired bootstrap CIs of every other field's difference from it, and
    of the no-change baseline's difference from it (``no_change``: its per-contact change
    metrics, from ``no_change_metrics``)."""
    table = {
        method: {kind: {m: bootstrap_mean([c[kind][m] for c in rows], seed) for m in METRICS} for kind in KINDS}
        for method, rows in per_contact.items()
    }
    for method, rows in per_contact.items():
        table[method]["contact"][CORRELATION] = bootstrap_mean([c["contact"][CORRELATION] for c in rows], seed)
    kind, metric = CRITERION
    best = min(table, key=lambda f: table[f][kind][metric]["mean"])
    best_values = np.array(table[best][kind][metric]["values"])
    differences = {
        f: bootstrap_mean(np.array(table[f][kind][metric]["values"]) - best_values, seed)
        for f in table if f != best
    }
    baseline = {k: {m: bootstrap_mean([c[k][m] for c in no_change], seed) for m in METRICS} for k in CHANGE_KINDS}
    lower_better = {"mae": True, "ssim": False, "psnr_db": False}
    best_by = {
        f"{k}_{m}": (min if lower_better[m] else max)(table, key=lambda f, k=k, m=m: table[f][k][m]["mean"])
        for k in KINDS for m in METRICS
    }
    distinct = all(d["ci_low"] > 0 for d in differences.values())
    versus_baseline = bootstrap_mean(np.array(baseline[kind][metric]["values"]) - best_values, seed)
    return {"table": table, "best": best, "criterion": f"{kind} {metric}", "best_minus_others": differences,
            "best_by_metric": best_by, "best_is_distinct": distinct, "baseline_no_change": baseline,
            "no_change_minus_best": versus_baseline, "best_beats_no_change": versus_baseline["ci_low"] > 0}


def conclusion(results: dict) -> str:
    """The answer in words, with the caveats the numbers call for."""
    kind, metric = CRITERION
    best = results["best"]
    cell = results["table"][best][kind][metric]
    n = len(cell["values"])
    text = (f"{best} has the lowest mean contact-change MAE ({cell['mean']:.4f}, {results['confidence']:.0%} CI "
            f"{cell['ci_low']:.4f} to {cell['ci_high']:.4f}, n = {n} contacts)")
    if results["best_is_distinct"]:
        text += "; the paired bootstrap separates it from every other field"
    else:
        close = [f for f, d in results["best_minus_others"].items() if d["ci_low"] <= 0]
        text += f"; the paired bootstrap does not separate it from {', '.join(close)}"
    base = results["baseline_no_change"][kind][metric]["mean"]
    if results["best_beats_no_change"]:
        text += f", and it beats predicting no change (MAE {base:.4f})."
    else:
        text += (f", but it does not clearly beat predicting no change (MAE {base:.4f}), so no field is shown "
                 "to track the reference's contact signal at these settings.")
    if n < MIN_CONTACTS_FOR_CI:
        text += f" With {n} contacts the intervals are not meaningful: this is a smoke run."
    where = []
    for method, f in results.get("failures", {}).items():
        if f["fails"] or f["tracks"]:
            parts = ([f"fails on {', '.join(f['fails'])}"] if f["fails"] else []) + (
                [f"tracks on {', '.join(f['tracks'])}"] if f["tracks"] else [])
            where.append(f"{method} {' and '.join(parts)}")
    if where:
        text += (" By region (error near the contacts over that of predicting no change, interval over contacts): "
                 + "; ".join(where) + ".")
    return text
