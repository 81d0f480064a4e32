"""The study's Markdown report (``summary.md``) from its results."""

from __future__ import annotations

from scenes.curvature import CLASSES, CURVATURE_RADIUS_M, FLAT_RADIUS_M

from .metrics import CHANGE_KINDS, CORRELATION, KINDS, METRICS


def _cell(c: dict, digits: int) -> str:
    return f"{c['mean']:.{digits}f} [{c['ci_low']:.{digits}f}, {c['ci_high']:.{digits}f}]"


def markdown(results: dict) -> str:
    s = results["settings"]
    digits = {"mae": 4, "ssim": 3, "psnr_db": 2}
    lines = [
        "# Fast-path light fields against the physically based reference",
        "",
        (f"Reference: photon estimator, {s['width']}x{s['height']}, {s['photons']} photons per LED per pass, "
         f"{s['passes']} passes, {s['spp']} spp, seed {s['seed']}; normalised by its no-contact "
         f"p{results['reference_percentile']} = {results['reference_scale']:.4g}. "
         f"Mean over {len(results['contacts'])} contacts with {results['confidence']:.0%} percentile-bootstrap "
         "intervals (contacts resampled). Change = contact − no-contact. Calibration: per-channel gain >= 0 from "
         "the other contacts' changes, offset from the no-contact frame (see the study's docstring). "
         f"Unreliable reference pixels left out: {results['unreliable_share']:.1%} of the circle."),
        "",
        "| field | " + " | ".join(f"{k} {m}" for k in KINDS for m in METRICS) + f" | contact {CORRELATION} |",
        "|---|" + "---|" * (len(KINDS) * len(METRICS) + 1),
    ]
    for method, row in results["table"].items():
        mark = " **(best)**" if method == results["best"] else ""
        lines.append(f"| {method}{mark} | " + " | ".join(_cell(row[k][m], digits[m]) for k in KINDS for m in METRICS)
                     + f" | {_cell(row['contact'][CORRELATION], 2)} |")
    b, n = results["baseline_no_change"], results["noise_mae"]
    lines += [
        "| no change (baseline) | | | | "
        + " | ".join(_cell(b[k][m], digits[m]) for k in CHANGE_KINDS for m in METRICS) + " | |",
        f"| reference noise (MAE) | {_cell(n['full'], 4)} | | | {_cell(n['change_far'], 4)} | | | | | | |",
        "",
        ("Reference noise: full, sqrt(2/pi) x the estimator's standard error; change, the mean |reference change| "
         "farther than a pixel from where the deformed surface moved (noise left by common random numbers, plus any real "
         "far-field change, which every field misses alike)."),
        "",
        f"**Conclusion.** {results['conclusion']}",
        "",
        "Best by each metric: " + ", ".join(f"{k}: {v}" for k, v in results["best_by_metric"].items()) + ".",
        "",
        f"Paired differences from {results['best']} in {results['criterion']} (other − best): "
        + ", ".join(f"{f} {_cell(d, 4)}" for f, d in results["best_minus_others"].items()) + ".",
        "",
        ("| contact | source | region | principal curvatures (1/m) | max indentation along the camera ray (mm) "
         "| max displacement along the normal (mm) |"),
        "|---|---|---|---|---|---|",
    ]
    for name, c in results["contacts"].items():
        k = ", ".join(f"{v:.0f}" for v in c["curvatures_per_m"])
        lines.append(f"| {name} | {c['source']} | {c['region']} | {k} | {c['max_indentation_m'] * 1e3:.2f} | "
                     f"{c['max_displacement_m'] * 1e3:.2f} |")
    if results["skipped"]:
        lines += ["", "Refused at their real depth: " + "; ".join(f"{k}: {v}" for k, v in results["skipped"].items())]
    lines += region_markdown(results)
    lines += ["", "Calibrated on the no-contact frame alone instead (diagnostic; degenerate for tangent fields):",
              "", "| field | gain (R, G, B) | fast no-contact std | change MAE |", "|---|---|---|---|"]
    for method, c in results["no_contact_calibration"].items():
        lines.append(f"| {method} | {', '.join(f'{g:.3g}' for g in c['gain'])} | "
                     f"{', '.join(f'{v:.4f}' for v in c['fast_std_no_contact'])} | {c['change_mae_mean']:.4f} |")
    return "\n".join(lines) + "\n"


def region_markdown(results: dict) -> list[str]:
    """The tables of where each field fails, by class of region (empty when none)."""
    regions = results.get("pixel_regions")
    if not regions or not any(regions["ratio"].values()):
        return []
    classes = [c for c in CLASSES if any(c in t for t in regions["ratio"].values())]
    lines = ["", "## Where each field fails, by class of region", "",
             ("Classes by the principal curvatures of the undeformed membrane over a "
              f"{CURVATURE_RADIUS_M * 1e3:g} mm ball (``scenes.curvature``: flat within 1/{FLAT_RADIUS_M * 1e3:g} mm). "
              "Pixel ratio: the calibrated change's |error| summed over the pixels near the contacts that see that "
              "class, over the |reference change| there (the error of predicting no change); below 1 the field "
              "tracks the contact, at or above 1 it does no better than no change. Interval: contacts resampled."),
             "", "| field | " + " | ".join(f"{c} ({regions['pixels_in_circle'].get(c, 0)} px in circle)"
                                           for c in classes) + " |",
             "|---|" + "---|" * len(classes)]
    for method, table in regions["ratio"].items():
        cells = [f"{table[c]['ratio']:.2f} [{table[c]['ci_low']:.2f}, {table[c]['ci_high']:.2f}] "
                 f"({table[c]['contacts']} contacts)" if c in table else "" for c in classes]
        lines.append(f"| {method} | " + " | ".join(cells) + " |")
    by_contact = regions["by_contact"]
    if by_contact:
        methods = list(results["table"])
        lines += ["", ("Change MAE over the contacts that press on each class (the class at the contact point), "
                       "and no change − field (above 0: the field beats predicting no change there):"), "",
                  "| class | contacts | no change | " + " | ".join(methods) + " |",
                  "|---|---|---|" + "---|" * len(methods)]
        for cls, row in by_contact.items():
            cells = [f"{_cell(row[m]['mae'], 4)}; {_cell(row[m]['no_change_minus_field'], 4)}" for m in methods]
            lines.append(f"| {cls} | {row['contacts']} | {_cell(row['no_change'], 4)} | " + " | ".join(cells) + " |")
    return lines


def print_report(results: dict) -> None:
    print(markdown(results))
