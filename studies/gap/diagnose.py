"""The whole diagnosis of one real dataset against its simulated counterpart.

``diagnose`` answers three questions and returns them as one JSON-ready dict (the
content of ``report.json``):

- where the gap lies: MAE, SSIM and PSNR per sample, object and tap position (full
  frame as the paper measured, and masked to the image circle), and the error split by
  region, contact, channel and contact depth;
- which effect causes it: every effect of the catalogue fitted on the training split and
  judged on the held-out split, ranked by the held-out MAE it removes (significant ones
  only), then greedy forward selection of combinations;
- how far it shrinks: held-out metrics before and after each effect and each step, with
  confidence intervals, and the share of the gap closed.
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from scenes import image_stats
from scenes.images import block_mean

from . import metrics
from .diagnosis import Diagnosis
from .fit import INTERVAL_EFFECTS, PARAM_RESAMPLES
from .judge import MIN_RANK_SHARE, RANK_BY, Judged
from .pairs import Pairs, load_pairs, split
from .regions import error_maps, where
from .selection import size


def _judged(j: Judged) -> dict:
    return {"effects": list(j.fit.effects), "params": j.fit.params,
            "train_mse": {"before": j.fit.train_mse_before, "after": j.fit.train_mse},
            "train_loss": {"before": j.fit.train_loss_before, "after": j.fit.train_loss,
                           "what": "the fitted loss: smooth MAE over the image circle (Charbonnier, eps one 8-bit level)"},
            "fit_status": j.fit.status,
            "fit_seconds": j.fit.seconds, "evaluations": j.fit.evaluations,
            "heldout": {"after": metrics.summarise(j.after), "improvement": j.improvement},
            "significant": j.significant, "share_closed": {k: j.improvement[k]["mae"]["share"] for k in j.improvement}}


def _per_sample(pairs: Pairs, values: dict, index: np.ndarray) -> list[dict]:
    rows = []
    for k, i in enumerate(index):
        r = pairs.records[i]
        rows.append({"id": pairs.ids[i], "object": r.get("object"), "path": r.get("path"),
                     "position": r.get("position"),
                     **{f"{scope}_{m}": float(values[scope][m][k]) for scope in values for m in image_stats.METRICS}})
    return rows


def _groups(pairs: Pairs, values: dict, index: np.ndarray, key) -> dict:
    keys = [key(pairs.records[i]) for i in index]
    return {scope: {m: metrics.group_means(values[scope][m], keys) for m in image_stats.METRICS} for scope in values}


#: Why held-out samples are judged at the resolution they are (report settings.judged_at).
JUDGED_AT_WHY = {
    "fast": "the images' resolution",
    "pbr": ("the reference model's basis film (block means of the images), low-passed by a Gaussian of about a film "
            "pixel: it predicts what a candidate changes only there, and the renders' Monte Carlo noise, which no "
            "candidate can predict and a resampling one would smooth, is smaller there"),
}


def diagnose(pairs: Pairs, heldout_fraction: float = 0.5, seed: int = 0, factor: int = 2,
             effects: tuple[str, ...] | None = None, progress=None,
             sides: tuple[np.ndarray, np.ndarray] | None = None,
             intervals: int = PARAM_RESAMPLES) -> tuple[dict, dict]:
    """Run the diagnosis; returns (report, artefacts) where artefacts holds the arrays
    the figures need (error maps, region labels, example predictions).

    sides : an explicit (train, held-out) pair of boolean masks over the samples, in
        place of the stratified ``split``.
    intervals : bootstrap resamples behind the parameter intervals of the best-ranked
        effects (``Fitter.intervals``); 0 leaves them out (the benchmarks, which do
        not score them).
    """
    t0 = time.perf_counter()
    train, heldout = split(pairs, heldout_fraction, seed) if sides is None else sides
    every = np.arange(len(pairs))
    gap_all = image_stats.per_sample(pairs.real, pairs.sim, _mask(pairs))
    located, labels = where(pairs.real, pairs.sim, pairs.depth, pairs.records, pairs.spec, seed)
    maps = error_maps(pairs.real, pairs.sim)

    diagnosis = Diagnosis(pairs, train, heldout, factor=factor, effects=effects, seed=seed, progress=progress,
                          regions=labels)
    singles = diagnosis.singles()
    ranked = diagnosis.rank(singles)
    bounds = {n: diagnosis.intervals(singles[n].fit, intervals) for n in ranked[:INTERVAL_EFFECTS]} if intervals else {}
    steps = diagnosis.select(singles, ranked)
    final = steps[-1] if steps else None
    best_params = final.fit.params if final is not None else {}
    noise = diagnosis.noise(best_params)

    report = {
        "real_dir": str(pairs.real_dir), "sim_dir": str(pairs.sim_dir), "pairs": len(pairs),
        "image_size": [pairs.shape[1], pairs.shape[0]],
        "split": {"train": int(train.sum()), "heldout": int(heldout.sum()), "heldout_fraction": heldout_fraction,
                  "fit_samples": len(diagnosis.train_index),
                  "seed": seed, "stratified_by": "object",
                  "heldout_ids": [pairs.ids[i] for i in np.flatnonzero(heldout)]},
        "settings": {"working_resolution": [pairs.shape[1] // diagnosis.work.factor,
                                            pairs.shape[0] // diagnosis.work.factor],
                     "judged_at": [pairs.shape[1] // diagnosis.full.factor, pairs.shape[0] // diagnosis.full.factor],
                     "judged_at_why": JUDGED_AT_WHY[diagnosis.work.kind],
                     "rank_by": "/".join(RANK_BY), "confidence": 0.95, "bootstrap_resamples": 2000,
                     "significant": "95% bootstrap interval of the paired held-out MAE improvement above 0",
                     "param_intervals": (f"95% intervals of the {INTERVAL_EFFECTS} best-ranked effects' parameters: "
                                         f"the fitted value plus the percentiles over {intervals} bootstrap resamples "
                                         "of the training samples (drawn with replacement) of one Newton step from the "
                                         "fit on the resample's loss (per-sample gradients and Hessians by finite "
                                         "differences), less the step of the training samples themselves: the spread "
                                         "over taps, not the bias of the renders the fit leans on; a parameter at a "
                                         "bound is held there" if intervals else "not computed"),
                     "ranked_if": (f"significant and closing at least {MIN_RANK_SHARE:.0%} of the held-out gap less "
                                   "its sensor-noise MAE floor (estimated from the held-out residual before any "
                                   "effect)"),
                     "min_gain": diagnosis.min_gain, "noise_floor_before": diagnosis.noise_floor},
        "gap_contact": (metrics.summarise({"contact": diagnosis.before["contact"]}, seed=seed)["contact"]
                        if "contact" in diagnosis.before else None),
        "gap": {"all": metrics.summarise(gap_all, seed=seed),
                "heldout": metrics.summarise({k: v for k, v in diagnosis.before.items() if k != "contact"},
                                             seed=seed),
                "per_object": _groups(pairs, gap_all, every, lambda r: r.get("object")),
                "per_position": _groups(pairs, gap_all, every, lambda r: f"path {r.get('path')} position {r.get('position')}"),
                "per_sample": _per_sample(pairs, gap_all, every)},
        "where": located,
        "effects": {n: {**_judged(j), **({"param_intervals": bounds[n]} if n in bounds else {})}
                    for n, j in singles.items()},
        "not_applicable": diagnosis.not_applicable,
        "ranking": ranked,
        # the two first-ranked effects, fitted together, where they took the first place
        # from a single effect with more parameters that closes no more (``selection.rank``)
        "first_pair": None if diagnosis.first_pair is None else {
            **_judged(diagnosis.first_pair), "instead_of": diagnosis.first_pair.instead_of,
            "parameters": sum(size(diagnosis.catalogue[n]) for n in diagnosis.first_pair.fit.effects),
            "instead_of_parameters": size(diagnosis.catalogue[diagnosis.first_pair.instead_of])},
        "not_significant": [n for n in singles if n not in ranked],
        # Fits whose search ended where it started while leaving most of the gap, and what
        # the check around the start found (a local optimum, or a restart that moved on).
        "stopped_at_start": {n: j.fit.status["note"] for n, j in singles.items()
                             if j.fit.status.get("stopped_at_start")},
        # Fitted on the training samples but not judged on the held-out ones, and why.
        "screened": {n: j.fit.status["screened"] for n, j in singles.items() if "screened" in j.fit.status},
        "selection": [{"added": s.added, **_judged(s)} for s in steps],
        "explained": {"effects": list(final.fit.effects) if final else [],
                      "share_closed": ({k: final.improvement[k]["mae"]["share"] for k in final.improvement}
                                       if final else {"full": 0.0, "masked": 0.0})},
        "noise": {"std": noise, "mae_floor": noise * float(np.sqrt(2 / np.pi)),
                  "note": "estimated from held-out residuals after the selected effects (differences of adjacent "
                          "pixels, robust spread); noise cannot be predicted, so it stays in the gap"},
        "model": diagnosis.work.kind,
        "catalogue": {n: {"stage": diagnosis.work.stages[n], "doc": diagnosis.catalogue[n].doc,
                          "params": {p.name: {"low": p.low, "high": p.high, "identity": p.identity, "unit": p.unit,
                                              "doc": p.doc} for p in diagnosis.catalogue[n].params},
                          **_physical_entry(diagnosis.work, n)}
                      for n in diagnosis.names},
    }
    mc = render_noise(pairs, diagnosis.heldout_index, _mask(pairs), diagnosis.full.factor,
                      getattr(diagnosis.full, "compared_sigma_px", 0.0))
    if mc is not None:
        report["noise"]["monte_carlo"] = mc
    if diagnosis.work.kind == "pbr":
        basis = diagnosis.work.basis
        report["renders"] = {"film": list(basis.film), "photons": basis.photons, "spp": basis.spp,
                             "no_contact_runs": basis.no_contact_runs,
                             "passes": basis.passes, "seed": basis.seed, "count": basis.renders,
                             "seconds": round(basis.seconds, 1),
                             "identity": basis.cost.get("identity", {"renders": 0, "seconds": 0.0}),
                             "reweighting": basis.reweighting}
        own = diagnosis.work.basis_noise(basis.rendered_keys())
        if own is not None:
            own.update({"min_gain": diagnosis.min_gain, "under_min_gain": own["mae_floor"] < diagnosis.min_gain,
                        "note": "the basis renders' own Monte Carlo noise, as the images are compared (basis film, "
                                "low-passed), from their variance maps with pixels as independent (a lower bound), "
                                "beside the held-out MAE a candidate must remove to be named (min_gain): a basis "
                                "noisier than that can name or hide a candidate by its noise"})
            report["noise"]["basis"] = own
    report["seconds"] = time.perf_counter() - t0
    examples = _examples(diagnosis, final)
    return report, {"maps": maps, "labels": labels, "mask": _mask(pairs), "examples": examples}


def heldout_gap(pairs: Pairs, heldout_fraction: float = 0.5, seed: int = 0, factor: int = 2) -> float:
    """The held-out masked MAE between the two sides as ``diagnose`` judges it (its split,
    resolution and comparison) before any effect: its report's gap.heldout.masked.mae."""
    train, heldout = split(pairs, heldout_fraction, seed)
    diagnosis = Diagnosis(pairs, train, heldout, factor=factor, seed=seed, progress=False)
    return float(metrics.summarise(diagnosis.before, seed=seed)["masked"]["mae"]["mean"])


def render_noise(pairs: Pairs, index: np.ndarray, mask: np.ndarray, factor: int = 1,
                 sigma: float = 0.0) -> dict | None:
    """The Monte Carlo noise of reference-rendered images, from their datasets' own
    variance maps (``variance/<id>.npy``, the variance of each pixel's linear mean, at
    the dataset's exposure gain): its MAE floor, sqrt(2 / pi) sigma per pixel averaged
    over the image circle, per side and for the difference of the two (independent
    renders add their variances). None when neither side has them.

    factor > 1 adds ``judged``: the floor of ``factor`` x ``factor`` block means (where a
    reference model is judged), each block's variance divided by the film pixels it
    holds, as if they were independent. Neighbouring pixels of a photon map are not (its
    kernel spans several), so this is a lower bound of that floor. sigma > 0: the blocks
    low-passed by a Gaussian of that many blocks, as the reference model compares them
    (``ReferenceModel.compared``): each variance is the squared kernel's weighted sum."""
    sides, films = {}, {}
    for side, root, meta in (("real", pairs.real_dir, pairs.real_meta), ("sim", pairs.sim_dir, pairs.sim_meta)):
        renderer = meta.get("renderer") or {}
        gain = renderer.get("exposure_gain")
        if gain is None:
            continue
        variances = []
        for i in index:
            path = Path(root) / "variance" / f"{pairs.ids[i]}.npy"
            if not path.is_file():
                break
            variances.append(float(gain) ** 2 * np.load(path))
        if len(variances) == len(index) and variances:
            sides[side] = variances
            films[side] = renderer.get("film") or [pairs.shape[1], pairs.shape[0]]
    if not sides:
        return None

    def floor(variances: list, area: np.ndarray) -> float:
        return float(np.mean([image_stats.mae_floor(v, area) for v in variances]))

    def summary(variances: dict, area: np.ndarray) -> dict:
        out = {"mae_floor": {side: floor(vs, area) for side, vs in variances.items()}}
        if len(variances) == 2:  # independent renders add their variances
            out["mae_floor_difference"] = floor([sum(vs) for vs in zip(*variances.values())], area)
        return out

    out = {"sides": sorted(sides), **summary(sides, mask),
           "note": "the Monte Carlo noise of the renders (from their variance maps): it cannot be predicted, and an "
                   "effect that smooths the simulation (blur) closes the part of it that is the simulation's"}
    if factor > 1:
        blocks = {}
        for side, vs in sides.items():
            held = max(1.0, (factor * float(films[side][0]) / pairs.shape[1]) ** 2)  # film pixels in a block
            blocks[side] = [image_stats.low_passed_variance(block_mean(v, factor, (0, 1)) / held, sigma) for v in vs]
        area = block_mean(mask.astype(np.float32), factor, (0, 1)) >= 0.5
        out["judged"] = {"factor": int(factor), "sigma": float(sigma), **summary(blocks, area),
                         "note": "the same at the resolution the held-out samples are judged at (block means), as "
                                 "if the film's pixels were independent: a lower bound"}
    return out


def _physical_entry(model, name: str) -> dict:
    """What the report says of a reference model's candidate besides its parameters: how
    it is evaluated, its grid, the fast catalogue's counterpart, and what it cost."""
    if model.kind != "pbr":
        return {}
    from .physical import COUNTERPARTS

    entry = {"evaluated": {"linear": "from the per-source images, no render",
                           "bool-linear": "from the per-source images, no render",
                           "render": "re-rendered per source on a grid, interpolated",
                           "bool-render": "re-rendered per source with the switch flipped, blended",
                           "image": "on the image", "fast": "on the image (the fast catalogue's model)",
                           "unpredictable": "not fitted"}[model.kinds[name]],
             "counterpart": COUNTERPARTS.get(name)}
    if name in model.grids:
        entry["grid"] = list(model.grids[name]["values"])
    cost = model.basis.cost.get(name)
    if cost is not None:
        entry["cost"] = {"renders": cost["renders"], "seconds": round(cost["seconds"], 1)}
    return entry


def _mask(pairs: Pairs) -> np.ndarray:
    from scenes.camera import Camera

    return Camera.from_spec(pairs.spec).mask


def _examples(diagnosis: Diagnosis, final: Judged | None, count: int = 4) -> dict:
    """A few held-out samples (the worst gaps): real, simulated, and with the selected effects."""
    judging = diagnosis.judging
    before = judging.before["masked"]["mae"]
    order = np.argsort(-before)[:count]
    pred = judging.predict(final.fit.params)[order] if final is not None else judging.sim_h[order]
    return {"ids": [diagnosis.pairs.ids[judging.heldout_index[i]] for i in order], "real": judging.real_h[order],
            "sim": judging.sim_h[order], "model": pred}


def alternate(pairs: Pairs) -> tuple[np.ndarray, np.ndarray]:
    """(train, held-out) masks: the real capture's even samples train, its odd ones are
    held out, as a calibration from it splits them (``scenes.captures.split``), so that
    a calibrated simulation is judged on the taps it was not fitted on."""
    from scenes.captures import split as halves
    from scenes.dataset import read_samples

    order = {r["id"]: k for k, r in enumerate(read_samples(pairs.real_dir))}
    fitted = halves(len(order))
    train = np.array([bool(fitted[order[i]]) for i in pairs.ids])
    return train, ~train


#: How ``run`` splits the samples: stratified by object at random, or alternate.
SPLITS = ("stratified", "alternate")


def run(real_dir: str | Path, sim_dir: str | Path, out: str | Path, heldout_fraction: float = 0.5, seed: int = 0,
        factor: int = 2, effects: tuple[str, ...] | None = None, progress: bool = True,
        intervals: int = PARAM_RESAMPLES, split_by: str = "stratified", ids=None) -> dict:
    """Load, diagnose, and write ``out/report.json``, ``out/report.html`` and figures.

    split_by : "stratified" (``heldout_fraction`` of each object's samples at random,
        ``seed``) or "alternate" (:func:`alternate`: the capture's odd samples held out).
    ids : the samples diagnosed (``pairs.load_pairs``), None: all."""
    if split_by not in SPLITS:
        raise ValueError(f"split_by must be one of {SPLITS}, got {split_by!r}")
    from .report import write_report

    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=0, unit="step", desc="loading", leave=False)

    def loading(done, total):
        if bar is not None:
            bar.total = total
            bar.n = done
            bar.refresh()

    pairs = load_pairs(real_dir, sim_dir, progress=loading, ids=ids)

    def fitting(done, total, name):
        if bar is not None:
            bar.set_description(f"fitting ({name})")
            bar.total = total
            bar.n = done
            bar.refresh()

    if bar is not None:
        bar.reset(total=0)
        bar.set_description("fitting")
    sides = alternate(pairs) if split_by == "alternate" else None
    report, artefacts = diagnose(pairs, heldout_fraction, seed, factor, effects, fitting, intervals=intervals,
                                 sides=sides)
    if sides is not None:
        report["split"]["stratified_by"] = "none: the capture's even samples train, its odd ones are held out"
    if bar is not None:
        bar.close()
    write_report(Path(out), report, artefacts)
    return report
