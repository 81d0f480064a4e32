"""Sim-to-real localisation of real presses: models trained on simulated presses alone,
tested on a capture's real held-out presses.

The capture is an imported set of ball presses (``scenes.imports``): each real press has
an annotated centre and a depth. Its fitted half (the even samples, which a calibration
fits) sets where and how deep the simulated presses go: ``count`` presses of the same
ball, their centres uniform over the box the fitted presses' centres span (grown by
``SPREAD_PX``) and their depths uniform over the fitted presses' range
(:func:`sample_presses`), pressed on the MuJoCo rig and rendered by the calibrated fast
path (``--profile``, one light field: ``scenes.generate``). The held-out half (the odd
samples) is never seen until the test.

Three trainings of equal cost, as ``studies.sim2real`` trains (``augment.TRAININGS``): the
simulated images as rendered (``none``), with every effect of the gap diagnosis'
catalogue at random strengths per image (``randomised``), and with the effects
``tactile-sim diagnose`` selected on the capture against the calibrated fast path's
replay of it (``diagnosed``). Every model sees each image less its own no-contact frame
(the capture's for a real press, the fast path's under the same effects for a simulated
one), since a press shows as a change of the frame.

Models (:data:`MODELS`):

- ``filter``: a correlation filter learned by ridge regression in the Fourier domain
  (Bolme et al.'s MOSSE, with the three colour channels solved jointly per frequency as
  Kiani Galoogahi et al.'s multi-channel filters are): its response to a difference image
  should be a Gaussian at the press's centre; the centre is the response's peak, refined
  by a parabola through its neighbours. The Gaussian's width and the ridge are chosen,
  per training, among FILTER_SIGMAS_PX x FILTER_RIDGES by the median error on the
  capture's fitted half (real presses, which the model never trains on and the test
  never sees). The depth is a ridge regression
  (scikit-learn) on the |change| in a (2 PATCH_PX + 1)^2 window about that centre.
  numpy and scikit-learn only: it runs wherever the project does.
- ``cnn``: the study's small CNN (``learn``, torch: ``pip install '.[sim2real]'``) regressing
  the centre and depth, trained as published (MSE, Adadelta, batches of 64).

The offset (:class:`Offset`, on unless ``--no-offset``): every simulated training misses
the real presses by about the same vector, 1.5 to 1.9 px up the image on the shared set,
on the fitted half as on the held-out one, whatever the press's depth or place; the
press-by-press shift that best aligns a real press with its calibrated replay is about
the same in v. It lies between where the annotations put a press and where its image
puts it, which no simulation can learn. So each model is calibrated by one constant
vector, its mean error on the real fitted half, taken off its centres; the held-out
presses are scored as annotated. ``real_no_offset`` keeps each model's scores without it.

Beside them, what bounds the result: ``real2real``, the same filter trained on the real
fitted half (:func:`real2real`), which measures how consistently the annotations place
the presses' own images; each training's mean error vector (``bias_px``), a systematic
offset between where the simulated and the real images put a press; and ``appearance``,
the radius at which the change peaks round the centre in the real and the simulated
presses (:func:`appearance`).

Scores: each held-out real press's localisation error, the distance from the predicted
centre to the annotated one in millimetres (the import's pixel size); the depth error
against the imported depth (itself an estimate: ``scenes.imports``); the same on
simulated presses held out of the training (Sim2Sim). ``results.json`` holds the medians
and per-press values, ``table.md`` the table.
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np

from .augment import TRAININGS, Augmenter, diagnosed_params
from .locators import MODELS, CorrelationLocator, Offset, locator
from .press_data import real_presses, sample_presses, simulate, trained_on
from .press_scores import appearance, errors, paired, real2real

#: Simulated presses by default.
SIM_PRESSES = 1200
#: Simulated presses held out of the training, for Sim2Sim.
SIM_HELDOUT = 0.2
#: The filter's width and ridge each training chooses among, by the median localisation
#: error on the capture's fitted half (real presses a calibration already fitted; the
#: held-out half stays unseen).
FILTER_SIGMAS_PX = (1.5, 3.0)
FILTER_RIDGES = (1e-1, 1.0, 10.0)


def run(capture_dir, out, profile=None, field: str = "linear", diagnosis=None, count: int = SIM_PRESSES,
        seed: int = 0, models=("filter",), trainings=TRAININGS, workers: int = 2, progress: bool = True,
        offset: bool = True) -> dict:
    """The study (module doc); returns and writes ``out/results.json`` and ``out/table.md``.

    profile : the calibrated unit's profile.toml the fast path renders (None: the spec's
        constants, no background). diagnosis : the report.json of ``tactile-sim diagnose``
        on the capture against the fast path's replay (``diagnosed`` needs it). offset :
        calibrate each model's constant offset on the real fitted half (:class:`Offset`;
        False: none).
    """
    from scenes.captures import split
    from scenes.dataset import atomic_write_json
    from scenes.files import atomic_write_bytes
    from scenes.replay import read_capture

    t0 = time.perf_counter()
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    capture = read_capture(capture_dir)
    block = capture.meta.get("import") or {}
    if "pixel_mm" not in block:
        raise ValueError(f"capture {capture.root} is no imported set of presses (its dataset.json has no import "
                         "block): the study needs annotated presses and their pixel size")
    pixel_m = float(block["pixel_mm"]) * 1e-3
    unknown = [t for t in trainings if t not in TRAININGS] + [m for m in models if m not in MODELS]
    if unknown:
        raise ValueError(f"trainings must be some of {TRAININGS} and models some of {MODELS}, got {unknown}")
    params = {}
    if "diagnosed" in trainings:
        if diagnosis is None:
            raise ValueError("the diagnosed training needs the diagnosis' report.json (--diagnosis)")
        params = diagnosed_params(json.loads(Path(diagnosis).read_text()))
    fitted = split(len(capture.ids))
    fit_ids = [i for i, f in zip(capture.ids, fitted) if f]
    test_ids = [i for i, f in zip(capture.ids, fitted) if not f]
    fit_real = real_presses(capture, fit_ids)
    real = real_presses(capture, test_ids)
    shape = real.images.shape[1:3]
    centres, depths = sample_presses(fit_real.centres, fit_real.depths, count, seed, shape)
    t_sim = time.perf_counter()
    sim, renderer = simulate(capture, centres, depths, profile, field, out / "sim", workers, progress)
    sim_seconds = time.perf_counter() - t_sim
    rng = np.random.default_rng(seed)
    held = rng.permutation(count) < int(round(SIM_HELDOUT * count))
    augmenter = Augmenter(capture.spec, renderer, 1) if set(trainings) - {"none"} else None
    calibrated = Offset.fitted if offset else (lambda m, _presses: Offset(m))
    results = {}
    for training in trainings:
        shown = trained_on(training, sim, augmenter, params, seed)
        train_set, sim_test = shown.subset(~held), shown.subset(held)
        for model_name in models:
            key = f"{model_name}/{training}"
            try:
                model = locator(model_name, seed)
            except RuntimeError as exc:
                results[key] = {"ran": False, "why": str(exc)}
                continue
            t_fit = time.perf_counter()
            chosen = None
            if model_name == "filter":  # its width and ridge (and offset), chosen on the real fitted half alone
                trials = {(sigma, ridge): calibrated(CorrelationLocator(ridge, sigma).fit(
                    train_set.differences(), train_set.centres, train_set.depths), fit_real)
                    for sigma in FILTER_SIGMAS_PX for ridge in FILTER_RIDGES}
                scores = {k: errors(m, fit_real, pixel_m)["localisation_mm_median"] for k, m in trials.items()}
                chosen = min(scores, key=scores.get)
                model = trials[chosen]
            else:
                model = calibrated(model.fit(train_set.differences(), train_set.centres, train_set.depths), fit_real)
            results[key] = {"ran": True, "model": model_name, "training": training,
                            "fit_seconds": time.perf_counter() - t_fit, "sim_train": int((~held).sum()),
                            "offset_px": model.offset_px.tolist(),
                            "real": errors(model, real, pixel_m), "real_no_offset": errors(model.model, real, pixel_m),
                            "sim": errors(model.model, sim_test, pixel_m),
                            "fitted_half": errors(model, fit_real, pixel_m)}
            if chosen is not None:
                results[key]["chosen"] = {"sigma_px": chosen[0], "ridge": chosen[1],
                                          "by": "the median localisation error on the real fitted half",
                                          "scores_mm": {f"sigma {k[0]:g}, ridge {k[1]:g}": v for k, v in
                                                        scores.items()}}
    ball_px = float(block["ball_mm"]) * 0.5e-3 / pixel_m
    floor = {"real2real": real2real(fit_real, real, pixel_m),
             "appearance": appearance(real_presses(capture, capture.ids), sim, ball_px)}
    comparisons = {}
    for model_name in models:
        runs = {t: results.get(f"{model_name}/{t}", {}) for t in trainings}
        if runs.get("diagnosed", {}).get("ran"):
            for other in ("randomised", "none"):
                if runs.get(other, {}).get("ran"):
                    comparisons[f"{model_name}: diagnosed - {other}"] = paired(runs["diagnosed"], runs[other])
    summary = {
        "capture": str(capture.root.resolve()),
        "paired": comparisons, "profile": None if profile is None else str(profile), "field": field,
        "diagnosed_effects": params, "simulated_presses": count, "sim_heldout": int(held.sum()),
        "fitted_real": fit_ids, "tested_real": test_ids, "pixel_mm": pixel_m * 1e3,
        "centres_box_px": [centres.min(axis=0).tolist(), centres.max(axis=0).tolist()],
        "depths_mm": [float(depths.min() * 1e3), float(depths.max() * 1e3)],
        "labels": "real centres: the annotated ones; real depths: the import's (scenes.imports), themselves estimates",
        "offset": ("each model's mean centre error on the real fitted half, taken off its predictions (Offset)"
                   if offset else "none"),
        "results": results, **floor, "seconds": {"simulate": sim_seconds, "total": time.perf_counter() - t0},
    }
    atomic_write_json(out / "results.json", summary)
    atomic_write_bytes(out / "table.md", table(summary).encode())
    return summary


def table(summary: dict) -> str:
    """table.md: medians per model and training."""
    lines = [f"# Sim-to-real localisation of real presses ({len(summary['tested_real'])} held-out real presses)", "",
             f"Trained on {summary['simulated_presses'] - summary['sim_heldout']} simulated presses (the calibrated fast "
             f"path, field {summary['field']}); Sim2Sim on {summary['sim_heldout']} more. Median over presses "
             f"[95 % bootstrap interval]; the mean beside it. Offset: {summary.get('offset', 'none')}.", "",
             "| model | training | localisation, real (mm) | mean (mm) | without the offset (mm) | depth error, real (mm) "
             "| localisation, sim (mm) |",
             "|---|---|---|---|---|---|---|"]
    for key, r in summary["results"].items():
        if not r.get("ran"):
            lines.append(f"| {key.split('/')[0]} | {key.split('/')[1]} | not run: {r['why']} | | | | |")
            continue
        ci, raw = r["real"]["localisation_mm_median_ci"], r["real_no_offset"]["localisation_mm_median_ci"]
        lines.append(f"| {r['model']} | {r['training']} | {ci['median']:.3f} [{ci['low']:.3f}, {ci['high']:.3f}] | "
                     f"{r['real']['localisation_mm_mean']:.3f} | {raw['median']:.3f} [{raw['low']:.3f}, "
                     f"{raw['high']:.3f}] | {r['real']['depth_error_mm_median_abs']:.3f} | "
                     f"{r['sim']['localisation_mm_median']:.3f} |")
    if "real2real" in summary:
        r = summary["real2real"]["real"]
        ci = r["localisation_mm_median_ci"]
        lines.append(f"| filter | real (Real2Real: the real fitted half) | {ci['median']:.3f} [{ci['low']:.3f}, "
                     f"{ci['high']:.3f}] | {r['localisation_mm_mean']:.3f} | | {r['depth_error_mm_median_abs']:.3f} | |")
    lines += ["", "Offset (u, v px) fitted on the real fitted half; mean error (predicted less annotated) on the "
              "real held-out presses without it; and the median error with the held-out presses' own mean taken "
              "off (mm, an oracle):", ""]
    for key, r in summary["results"].items():
        if r.get("ran"):
            o, b = r.get("offset_px", [0.0, 0.0]), r["real_no_offset"]["bias_px"]
            lines.append(f"- {key}: offset ({o[0]:+.2f}, {o[1]:+.2f}) px; held-out mean error without it "
                         f"({b[0]:+.2f}, {b[1]:+.2f}) px; {r['real']['localisation_mm_median_unbiased']:.3f} mm")
    if "appearance" in summary:
        a = summary["appearance"]
        lines.append(f"\nThe change peaks {a['ring_px_real']:.1f} px from the centre in the real presses (median) and "
                     f"{a['ring_px_sim']:.1f} px in the simulated ones ({a['sim_over_real']:.2f} of the real).")
    for name, c in summary.get("paired", {}).items():
        lines.append(f"\n{name}, press by press: median {c['median']:+.3f} mm [{c['low']:+.3f}, {c['high']:+.3f}]; "
                     f"the first better on {c['a_better_share']:.0%} of the presses.")
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    import argparse

    p = argparse.ArgumentParser(prog="python -m studies.sim2real.presses", description=__doc__.splitlines()[0])
    p.add_argument("--capture", required=True, metavar="DIR", help="an imported set of presses (tactile-sim import)")
    p.add_argument("--out", required=True, metavar="DIR")
    p.add_argument("--profile", metavar="TOML", help="the calibrated unit's profile the fast path renders")
    p.add_argument("--field", default="linear", help="the fast path's light field (default linear)")
    p.add_argument("--diagnosis", metavar="REPORT_JSON", help="tactile-sim diagnose's report.json (for diagnosed)")
    p.add_argument("--count", type=int, default=SIM_PRESSES, help=f"simulated presses (default {SIM_PRESSES})")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--models", default="filter", help=f"some of {', '.join(MODELS)} (default filter)")
    p.add_argument("--trainings", default=",".join(TRAININGS), help=f"some of {', '.join(TRAININGS)}")
    p.add_argument("--workers", type=int, default=2)
    p.add_argument("--no-offset", action="store_true",
                   help="do not calibrate each model's constant offset on the real fitted half")
    p.add_argument("--quiet", action="store_true")
    args = p.parse_args(argv)
    summary = run(args.capture, args.out, args.profile, args.field, args.diagnosis, args.count, args.seed,
                  tuple(m for m in args.models.split(",") if m), tuple(t for t in args.trainings.split(",") if t),
                  args.workers, not args.quiet, not args.no_offset)
    print(table(summary))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
