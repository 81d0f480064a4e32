"""results.json's numbers: the paper's tables from the runs' results (``summarise``), beside
the paper's own (``PAPER``), and how strongly the contacts show in each set (``contrast``).

A cell is the mean over seeds with Student's t interval (``interval``); the share of the
gap a training closes is (S2R with it - S2R with none) / (R2R - S2R with none).
"""

from __future__ import annotations

import numpy as np

from scenes.image_stats import t_interval
from scenes.indenters import INDENTERS

from . import data
from .plan import INPUTS, TASKS, Run, Settings

#: The paper's Tables 2 and 3: accuracy (%) and localisation error (mm).
PAPER = {
    "r2r": {"base": {"full": {"accuracy": 64.3, "localisation_mm": 8.4}, "patch": {"accuracy": 35.7}}},
    "s2s": {"base": {"full": {"accuracy": 75.0, "localisation_mm": 3.7}, "patch": {"accuracy": 96.4}},
            "extended": {"full": {"accuracy": 100.0, "localisation_mm": 5.4}, "patch": {"accuracy": 100.0}}},
    "s2r": {"base": {"full": {"accuracy": 42.8, "localisation_mm": 11.8}, "patch": {"accuracy": 14.3}},
            "extended": {"full": {"accuracy": 50.0, "localisation_mm": 13.3}, "patch": {"accuracy": 32.1}}},
}


def interval(values: list[float], confidence: float = 0.95) -> dict:
    """Mean, and Student's t interval of the mean over seeds (``scenes.image_stats.t_interval``),
    as results.json holds them, with the seeds' values."""
    ci = t_interval(values, confidence)
    return {"mean": ci["mean"], "interval": [ci["low"], ci["high"]], "seeds": np.asarray(values, np.float64).tolist()}


METRIC = {"classification": "accuracy", "localisation": "localisation_mm"}


def summarise(results: dict[str, dict], settings: Settings, sim_sets: list[str], plane_sets: list[str]) -> dict:
    """results.json's tables from the runs' results (keyed by ``Run.name``)."""
    def cell(train_set: str, training: str, inp: str, test: str) -> dict:
        out = {}
        for task in TASKS:
            got = [results.get(Run(train_set, training, inp, task, s).name, {}).get(test)
                   for s in range(settings.seeds)]
            vals = [g[METRIC[task]] for g in got if g is not None]
            if vals:
                out[METRIC[task]] = interval(vals)
        return out

    def table(test: str, sets: list[str], training: str = "none") -> dict:
        return {name: {inp: cell(name, training, inp, test) for inp in INPUTS} for name in sets}

    r2r = {"base": {inp: cell("real", "none", inp, "own") for inp in INPUTS}}
    by_set = {"s2s": table("own", sim_sets), "s2r": table("real", sim_sets),
              "s2r_all_real_taps": table("real_all", sim_sets)}
    # the published field's tables keyed by protocol, as the paper's
    key = {s: s.split("_", 1)[0] for s in plane_sets}
    s2s = {key[s]: by_set["s2s"][s] for s in plane_sets}
    s2r = {key[s]: by_set["s2r"][s] for s in plane_sets}
    by_training = {t: {key[s]: table("real", [s], t)[s] for s in plane_sets} for t in settings.trainings}
    by_training_all = {t: {key[s]: table("real_all", [s], t)[s] for s in plane_sets} for t in settings.trainings}
    gap = {}
    for t in settings.trainings:
        gap[t] = {}
        for s in plane_sets:
            gap[t][key[s]] = {}
            for inp in INPUTS:
                entry = {}
                for task in TASKS:
                    per_seed = []
                    for seed in range(settings.seeds):
                        names = [Run(s, t, inp, task, seed).name, Run(s, "none", inp, task, seed).name,
                                 Run("real", "none", inp, task, seed).name]
                        if not all(n in results for n in names):
                            continue
                        m = METRIC[task]
                        with_t = results[names[0]]["real"][m]
                        none = results[names[1]]["real"][m]
                        r2r_v = results[names[2]]["own"][m]
                        per_seed.append((with_t, none, r2r_v))
                    if not per_seed:
                        continue
                    a = np.asarray(per_seed)
                    denominator = a[:, 2].mean() - a[:, 1].mean()
                    ratio = float((a[:, 0].mean() - a[:, 1].mean()) / denominator) if denominator else None
                    seeds = [float((w - n) / (r - n)) if r != n else None for w, n, r in per_seed]
                    good = [v for v in seeds if v is not None]
                    entry[task] = {"share": ratio, "per_seed": seeds,
                                   **({"interval": interval(good)["interval"]} if len(good) > 1 else {}),
                                   "what": "(S2R with it - S2R with none) / (R2R - S2R with none), means over "
                                           "seeds; per_seed: the same of each seed's paired runs"}
                gap[t][key[s]][inp] = entry
    return {"r2r": r2r, "s2s": s2s, "s2r": s2r, "by_set": by_set, "s2r_by_training": by_training,
            "s2r_by_training_all_real_taps": by_training_all, "gap_closed": gap, "paper": PAPER}


def contrast(sets: dict[str, data.Arrays], region_from: data.Arrays, mask: np.ndarray,
             pressed_m: float = 1e-4) -> dict:
    """How strongly each indenter's contact shows in each set: per indenter, the mean
    |image - the set's per-pixel median| ([0, 1] units, channels averaged) over the contact
    (where ``region_from``'s indentation, aligned by sample id, exceeds ``pressed_m``) and
    over the rest of the image circle (the noise a classifier must see the contact
    through)."""
    where = {str(i): k for k, i in enumerate(region_from.ids)}
    out = {}
    for name, a in sets.items():
        x = a.images.astype(np.float32) / 255.0
        change = np.abs(x - np.median(x, axis=0)).mean(axis=-1)
        rows = {}
        for c in np.unique(a.labels):
            contact, rest = [], []
            for i in np.flatnonzero(a.labels == c):
                ind = region_from.indentation[where[str(a.ids[i])]]
                contact.append(float(change[i][ind > pressed_m].mean()))
                rest.append(float(change[i][mask & (ind == 0)].mean()))
            rows[INDENTERS[c]] = {"contact": float(np.mean(contact)), "elsewhere": float(np.mean(rest))}
        out[name] = rows
    return {"per_set": out, "what": "mean |image - per-pixel median of the set| over the contact (the fast path's "
                                    f"base taps' indentation > {pressed_m * 1e3:g} mm) and elsewhere in the image "
                                    "circle, [0, 1] units, channels averaged, at the arrays' resolution"}
