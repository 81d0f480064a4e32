"""The whole study, stage by stage, each cached under ``DIR`` and resumed (``run``).

1. ``DIR/real``: the "real" data, a virtual-rig capture of the base protocol (all 8
   indenters, 144 taps) whose camera is the physically based reference (``capture``), or
   a given capture (``capture=``);
2. ``DIR/replay_<field>``: the fast path's replay of the capture with each light field
   and the capture's background; the field whose replay is nearest the capture (MAE over
   the image circle) is the best field, beside the published plane field (``datasets``);
3. ``DIR/diagnosis``: the gap diagnosis of the capture against the plane field's replay:
   the effects to add, fitted (``datasets.ensure_diagnosis``);
4. ``DIR/sim_<protocol>_<field>``: the fast path's base and extended protocols (all 8
   indenters) with the capture's background (``studies.sim2real.plugin``);
5. ``DIR/runs/<model>/<settings tag>/<run>.json``: one trained model each, evaluated
   (``study.Study``);
6. ``DIR/results.json`` (``summary``), ``DIR/tables.md`` and ``DIR/transfer.png``
   (``report``).
"""

from __future__ import annotations

import json
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from scenes.dataset import atomic_write_json, read_meta

from . import augment, data
from .capture import ensure_capture
from .datasets import ensure_diagnosis, ensure_replays, ensure_sim, field_gaps
from .learn import need
from .plan import FIELDS, PROTOCOLS, Settings, runs
from .report import figure, tables
from .study import Study
from .summary import contrast, summarise


def real_data(out: Path, capture: str | Path | None, spec: str | None, progress: bool) -> tuple[Path, dict]:
    """Stage 1: the capture's folder, and its one-time cost (none for a given capture)."""
    if capture is None:
        return out / "real", ensure_capture(out, spec, progress)
    root = Path(capture)
    meta = read_meta(root)
    if meta.get("source") != "real":
        raise ValueError(f"{root} is not a capture (source {meta.get('source')!r}, expected 'real')")
    return root, {"seconds": 0.0, "frames": 0, "given": str(root)}


def simulated_sets(study: Study, real_root: Path, protocols: tuple[str, ...], best: str) -> tuple[list, list]:
    """Stage 4: each protocol with the plane field and the best one, added to ``study``;
    (every simulated set's name, the plane field's)."""
    spec = data.dataset_spec(real_root)
    objects = tuple(read_meta(real_root)["protocol"]["objects"])  # the capture's indenters
    sim_sets, plane_sets = [], []
    for p in protocols:
        for f in dict.fromkeys(("plane", best)):
            name = f"{p}_{f}"
            study.add(name, ensure_sim(study.out, p, f, real_root / "background.png", study.settings, spec, objects,
                                       study.progress))
            sim_sets.append(name)
            if f == "plane":
                plane_sets.append(name)
    return sim_sets, plane_sets


def shown_contrast(study: Study, real_root: Path) -> dict | None:
    """How strongly the contacts show in the capture and in the base protocol's images,
    as trained with each training (None without the base protocol)."""
    if "base_plane" not in study.sets:
        return None
    settings, real = study.settings, study.sets["real"]
    inside = data.circle(real_root, settings.factor, share=0.99)
    base = study.sets["base_plane"]
    # the trained images too: how far each training brings the contacts' strength to the capture's
    trained = {"base_plane" + ("" if t == "none" else f" {t}"):
               replace(base, images=study.training_images("base_plane", t))
               for t in dict.fromkeys(("none",) + tuple(settings.trainings))}
    if set(map(str, real.ids)) == set(map(str, base.ids)):
        trained = {"real": real, **{k: data.aligned(v, real.ids, "the base protocol") for k, v in trained.items()}}
    return contrast(trained, base, inside)


def run(out: str | Path, settings: Settings = Settings(), capture: str | Path | None = None, spec: str | None = None,
        fields: tuple[str, ...] = FIELDS, protocols: tuple[str, ...] = PROTOCOLS, diagnose_options: dict | None = None,
        progress: bool = True) -> dict:
    """Run (or resume) the study into ``out``; returns results.json's content.

    capture : an existing capture of the base protocol (``source: "real"``) to use instead
        of rendering ``DIR/real``; spec : the sensor spec TOML of a capture rendered here.
    fields : the light fields whose replays pick the best one (plane is always one).
    diagnose_options : keywords of the gap diagnosis (``studies.gap.diagnose.run``: e.g.
        ``effects``, ``intervals``).
    """
    why = need(settings.model)
    if why:
        raise RuntimeError(why)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    seconds = {}
    real_root, cost = real_data(out, capture, spec, progress)
    study = Study(out, settings, progress)
    real = study.add("real", real_root)
    fields = tuple(dict.fromkeys(("plane",) + tuple(fields)))
    t0 = time.perf_counter()
    replays = ensure_replays(out, real_root, fields, settings.workers, progress)
    seconds["replays"] = time.perf_counter() - t0
    mask = data.circle(real_root, settings.factor)
    gaps = field_gaps(real, {f: data.load(r, settings.factor, study.cache, settings.workers) for f, r in replays.items()},
                      mask)
    best = min(gaps, key=gaps.get)
    t0 = time.perf_counter()
    report = ensure_diagnosis(out, real_root, replays["plane"], dict(diagnose_options or {}), progress)
    seconds["diagnosis"] = time.perf_counter() - t0
    study.params = augment.diagnosed_params(report)
    augment.check_effects(study.params)
    t0 = time.perf_counter()
    sim_sets, plane_sets = simulated_sets(study, real_root, protocols, best)
    seconds["simulated_datasets_and_arrays"] = time.perf_counter() - t0
    todo = runs(settings, sim_sets, plane_sets)
    t0 = time.perf_counter()
    for t in settings.trainings:
        for s in plane_sets:
            if t != "none":
                study.training_images(s, t)
    seconds["effects"] = time.perf_counter() - t0
    from tqdm import tqdm

    t0 = time.perf_counter()
    results = {}
    for r in tqdm(todo, desc="runs", unit="run", disable=not progress):
        results[r.name] = study.evaluate(r)
    seconds["runs"] = time.perf_counter() - t0
    summary = summarise(results, settings, sim_sets, plane_sets)
    shown = shown_contrast(study, real_root)
    train_seconds = [v["seconds"] for v in results.values()]
    effects_cost = {p.stem: json.loads(p.read_text()) for p in study.cache.glob("*.json")}
    doc = {
        "settings": settings.to_dict(),
        "data": {name: data.describe(root) for name, root in study.roots.items()},
        "capture_cost": cost,
        "replays": {"fields": list(fields), "mae_to_capture": gaps, "best_field": best},
        "diagnosis": {"report": str(out / "diagnosis" / "report.json"), "effects": list(study.params),
                      "params": study.params,
                      "share_closed": (report.get("explained") or {}).get("share_closed")},
        **summary,
        "contrast": shown,
        "timing": {"this_call_seconds": seconds, "runs": len(results),
                   "train_seconds_total": float(sum(train_seconds)),
                   "train_seconds_median": float(np.median(train_seconds)) if train_seconds else None,
                   "effects_images": effects_cost},
    }
    stem = settings.stem
    atomic_write_json(out / f"results{stem}.json", doc)
    (out / f"tables{stem}.md").write_text(tables(doc))
    figure(doc, results, study, out / f"transfer{stem}.png")
    return doc
