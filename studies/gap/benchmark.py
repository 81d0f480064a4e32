"""Blind validation of the diagnosis on data whose effect is withheld from it.

Each case is a "real" dataset made by the fast path with one or two effects injected at a
random strength (``studies.gap.inject``, written apart from the diagnosis' own models so
the benchmark cannot pass by construction) and its simulated counterpart without them.
The diagnosis sees only the two dataset folders. A case is scored on

- top-1: the first ranked effect is one of the hidden ones;
- top-3: every hidden effect is among the first three ranked;
- held-out shrink: the share of the held-out masked MAE gap the diagnosis' selected
  combination closes (the gap is what the hidden effects caused: nothing else differs).

The contacts come from the MuJoCo tapping rig (the base protocol, all eight indenters),
captured once; each case draws its own subset of them, its hidden effects, their
strengths and the simulator's background (none or solid) from its seed.

``stratified=True`` covers the grid instead: every effect alone on every background
(none, solid, and the real no-contact capture of the published data), at one known
strength, then each mechanism written unlike the catalogue's formulas
(``studies.gap.unlike``) on its background, and scores each cell (``per_cell``) and the
worst cell's share closed (``min_cell_shrink``), leaving out the cells whose gap is mostly
sensor noise, which no prediction can remove (``noise_cells``).

``null`` cases hide nothing: the "real" frames are the simulated ones with camera noise
of their own (the real GelTip's measured noise, ``scenes.reference_data.CAMERA_NOISE_RGB``),
on each background in turn; a correct diagnosis names nothing (``top1`` there: the
ranking is empty). A mechanism at strength 0 is still a weak but visible effect on each
of the benchmark's scales; the null case is the effect at none.

``described=True`` runs the third source instead: each mechanism of
``studies.gap.described``, written from a prose description of a physical effect by a hand
that had not read the catalogue's formulas, on its own background, at strengths spread
over [0, 1] (``described_cases``); it is scored as the others are (top-1 against the
catalogue effect the mechanism stands for, and the held-out shrink).
"""

from __future__ import annotations

import dataclasses
import json
import tempfile
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np

from scenes.dataset import DatasetWriter, read_meta, read_samples, write_sample_files
from scenes.spec import SensorSpec
from scenes.spec_read import default_spec

#: Chance that a case hides two effects rather than one.
TWO_EFFECTS = 0.4
BACKGROUNDS = ("none", "solid")
#: The backgrounds of a stratified run; "real" is the published real no-contact capture.
STRATIFIED_BACKGROUNDS = ("none", "solid", "real")
#: Strength of the hidden effect in a stratified run (``inject``'s scale: 0 weak but
#: clearly visible, 1 strong).
STRATIFIED_STRENGTH = 0.5
#: A cell's gap is noise-only when the estimated sensor-noise MAE floor is at least this
#: share of it: then no prediction can close half of it.
NOISE_ONLY_SHARE = 0.5


def real_background() -> Path:
    """The real no-contact capture of the published GelTip data (``real/bkg.png``)."""
    from scenes.reference_data import require_reference_dir

    path = require_reference_dir() / "real" / "bkg.png"
    if not path.is_file():
        raise FileNotFoundError(f"the real no-contact image {path} is missing from the reference data")
    return path


def contacts(root: Path, spec: SensorSpec, progress: bool = True) -> Path:
    """The base protocol's depth maps from the MuJoCo rig (cached in ``root``)."""
    import phong_reference.plugin
    from scenes.generate import generate
    from scenes.geometry import membrane_mesh
    from scenes.indenters import INDENTERS
    from scenes.protocol import base_protocol

    folder = root / "contacts"
    protocol = base_protocol(spec, membrane_mesh(spec), tuple(INDENTERS))
    generate(folder, spec, protocol, phong_reference.plugin, {"field": "plane", "background": "none"},
             progress=progress)
    return folder


def _draw(case_seed: int, n_available: int, pairs: int) -> dict:
    from .inject import EFFECTS

    rng = np.random.default_rng(case_seed)
    count = 2 if rng.random() < TWO_EFFECTS else 1
    hidden = [str(e) for e in rng.choice(EFFECTS, size=count, replace=False)]
    chosen = np.sort(rng.choice(n_available, size=min(pairs, n_available), replace=False))
    return {"hidden": hidden, "samples": chosen, "background": str(rng.choice(BACKGROUNDS)), "rng": rng,
            "strength": None}


def stratified_cells() -> list[tuple[str, str, str | None]]:
    """(effect, background, mechanism) for every effect of the injector on every
    background (mechanism None), then every mechanism of ``studies.gap.unlike`` on each
    of its own backgrounds (effect: the catalogue effect that should come first). New cells go
    last, so that a case keeps its index, hence its cell and seed."""
    from .inject import EFFECTS
    from .unlike import BACKGROUNDS as UNLIKE_BACKGROUNDS
    from .unlike import MECHANISMS

    return ([(effect, background, None) for background in STRATIFIED_BACKGROUNDS for effect in EFFECTS]
            + [(effect, background, name) for name, effect in MECHANISMS.items()
               for background in UNLIKE_BACKGROUNDS[name]])


def cell_name(effect: str, mechanism: str | None) -> str:
    """A cell's name in ``per_cell``: the hidden effect, or effect/mechanism for one
    written unlike the catalogue."""
    return effect if mechanism is None else f"{effect}/{mechanism}"


def stratified_cases(cases: int, hidden: tuple[str, ...] | None = None) -> list[int]:
    """The case indices of a stratified run of ``cases`` cases whose cell hides one of
    ``hidden`` (effects of the injector, or mechanisms of ``studies.gap.unlike``; None:
    every case). A case keeps its index, hence its cell and seed."""
    from .inject import EFFECTS
    from .unlike import MECHANISMS

    if hidden is not None and (not hidden or any(h not in EFFECTS and h not in MECHANISMS for h in hidden)):
        raise ValueError(f"hidden must be a non-empty subset of {EFFECTS} and {tuple(MECHANISMS)}, got {hidden!r}")
    cells = stratified_cells()
    return [case for case in range(cases)
            if hidden is None or cells[case % len(cells)][0] in hidden or cells[case % len(cells)][2] in hidden]


def _draw_stratified(case: int, case_seed: int, n_available: int, pairs: int, strength: float) -> dict:
    cells = stratified_cells()
    effect, background, mechanism = cells[case % len(cells)]
    rng = np.random.default_rng(case_seed)
    chosen = np.sort(rng.choice(n_available, size=min(pairs, n_available), replace=False))
    return {"hidden": [effect], "samples": chosen, "background": background, "rng": rng, "strength": strength,
            "mechanism": mechanism}


def _draw_null(case: int, case_seed: int, n_available: int, pairs: int) -> dict:
    rng = np.random.default_rng(case_seed)
    chosen = np.sort(rng.choice(n_available, size=min(pairs, n_available), replace=False))
    return {"hidden": [], "samples": chosen, "background": STRATIFIED_BACKGROUNDS[case % len(STRATIFIED_BACKGROUNDS)],
            "rng": rng, "strength": 0.0, "null": True}


def with_camera_noise(image: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """(H, W, 3) float32 image plus Gaussian noise of the real GelTip camera's spread per
    channel (``CAMERA_NOISE_RGB``), clipped to [0, 1]: a null case's "real" frame."""
    from scenes.reference_data import CAMERA_NOISE_RGB

    noisy = image + rng.standard_normal(image.shape) * np.asarray(CAMERA_NOISE_RGB)
    return np.clip(noisy, 0.0, 1.0).astype(np.float32)


def described_cases(cases: int) -> list[tuple[str, float]]:
    """(mechanism, strength) of a described run's ``cases`` cases: the mechanisms of
    ``studies.gap.described`` in turn, each round at another strength (0.5, then 0, 1,
    0.25, 0.75, ...), so that a run of one case per mechanism is at the middle strength."""
    from .described import MECHANISMS

    names = list(MECHANISMS)
    strengths = (0.5, 0.0, 1.0, 0.25, 0.75)
    return [(names[k % len(names)], strengths[(k // len(names)) % len(strengths)]) for k in range(cases)]


def _draw_described(case: int, case_seed: int, n_available: int, pairs: int) -> dict:
    from .described import BACKGROUNDS as DESCRIBED_BACKGROUNDS
    from .described import MECHANISMS

    mechanism, strength = described_cases(case + 1)[case]
    rng = np.random.default_rng(case_seed)
    chosen = np.sort(rng.choice(n_available, size=min(pairs, n_available), replace=False))
    return {"hidden": [MECHANISMS[mechanism]], "samples": chosen, "background": DESCRIBED_BACKGROUNDS[mechanism],
            "rng": rng, "strength": strength, "described": mechanism}


def make_case(folder: Path, base: Path, spec: SensorSpec, case: int, seed: int, pairs: int,
              stratified_strength: float | None = None, described: bool = False, null: bool = False) -> dict:
    """Write one case's real and simulated datasets; returns what was hidden.

    stratified_strength : None, a random case (``_draw``); else the case-th cell of
        ``stratified_cells`` with its effect at this strength (for a cell written unlike
        the catalogue: the plain fast path, then its mechanism at this strength).
    described : the case-th of ``described_cases`` (the plain fast path, then a mechanism
        of ``studies.gap.described``); ``stratified_strength`` is then ignored.
    null : a case that hides nothing (module doc), on the case-th background; the others
        are then ignored.
    """
    from .inject import Injector
    from .unlike import Unlike
    from .unlike import sample_params as unlike_params

    meta = read_meta(base)
    records = read_samples(base)
    case_seed = seed * 100_003 + case
    if null:
        draw = _draw_null(case, case_seed, len(records), pairs)
    elif described:
        draw = _draw_described(case, case_seed, len(records), pairs)
    elif stratified_strength is None:
        draw = _draw(case_seed, len(records), pairs)
    else:
        draw = _draw_stratified(case, case_seed, len(records), pairs, stratified_strength)
    rng = draw["rng"]
    background = str(real_background()) if draw["background"] == "real" else draw["background"]
    injector = Injector(spec, field="plane", background=background)
    mechanism = draw.get("mechanism")
    written_by = draw.get("described")
    if draw.get("null"):  # the plain fast path with camera noise: nothing hidden
        injections = []
    elif written_by is not None:  # the plain fast path, then the mechanism written from prose
        from .described import Described
        from .described import sample_params as described_params

        injections, prose = [], Described(spec, injector.ref_depth)
        written = described_params(written_by, draw["strength"], rng)
    elif mechanism is None:
        injections = [injector.sample(effect, rng, draw["strength"]) for effect in draw["hidden"]]
    else:  # the plain fast path, then the mechanism written unlike the catalogue
        injections, unlike = [], Unlike(spec, injector.ref_depth)
        written = unlike_params(mechanism, draw["strength"], rng)
    renderer = {**meta["renderer"], "background": background}
    protocol = json.loads((base / "protocol.json").read_text())
    chosen = [records[i] for i in draw["samples"]]
    for source in ("real", "sim"):
        root = folder / source
        writer = DatasetWriter(root, {**{k: meta[k] for k in ("sensor", "image_size", "depth", "image")},
                                      "source": source, "protocol": meta["protocol"], "renderer": renderer},
                               protocol)

        def one(record: dict, source=source, root=root) -> dict:
            depth = np.load(base / record["depth"])
            if source == "real" and draw.get("null"):
                image = with_camera_noise(injector.render(depth), np.random.default_rng([seed, case, record["tap_index"]]))
                return {**record, **write_sample_files(root, record["id"], image, None), "depth": None}
            if source == "real" and written_by is not None:
                image = prose.apply(injector.render(depth), written_by, written, depth=depth, render=injector.render)
                return {**record, **write_sample_files(root, record["id"], image, None), "depth": None}
            if source == "real" and mechanism is not None:
                image = unlike.apply(injector.render(depth), mechanism, written)
                return {**record, **write_sample_files(root, record["id"], image, None), "depth": None}
            if source == "real":
                image = injector.render(depth, injections, np.random.default_rng([seed, case, record["tap_index"]]))
                return {**record, **write_sample_files(root, record["id"], image, None), "depth": None}
            image = injector.render(depth)
            return {**record, **write_sample_files(root, record["id"], image, depth)}

        todo = [r for r in chosen if r["id"] not in writer.done]
        with ThreadPoolExecutor(max_workers=2) as pool:
            for rec in pool.map(one, todo):
                if rec.get("depth") is None:
                    rec.pop("depth")
                writer.append(rec)
    out = {"hidden": draw["hidden"], "background": draw["background"],
           "injections": [dataclasses.asdict(i) for i in injections], "pairs": len(chosen)}
    if mechanism is not None:
        out.update(mechanism=mechanism, mechanism_params=written)
    if written_by is not None:
        out.update(described=written_by, strength=draw["strength"], mechanism_params=written)
    if draw.get("null"):
        out.update(null=True, strength=0.0)
    return out


def score(hidden: list[str], report: dict) -> dict:
    ranking = report["ranking"]
    gap = float(report["gap"]["heldout"]["masked"]["mae"]["mean"]) if "gap" in report else 0.0
    noise = float(report["noise"]["mae_floor"]) if "noise" in report else 0.0
    return {"top1": (bool(ranking) and ranking[0] in hidden) if hidden else not ranking,
            "noise_share": noise / gap if gap > 0 else 0.0,
            "top3": (bool(ranking) and all(h in ranking[:3] for h in hidden)) if hidden else not ranking,
            "shrink": float(report["explained"]["share_closed"]["masked"]),
            "shrink_top1": (float(report["effects"][ranking[0]]["share_closed"]["masked"]) if ranking else 0.0),
            "ranking": ranking, "selected": report["explained"]["effects"]}


def run_benchmark(cases: int = 20, seed: int = 0, work: str | Path | None = None, pairs: int = 48,
                  progress: bool = True, spec: SensorSpec | None = None, factor: int = 2,
                  stratified: bool = False, strength: float = STRATIFIED_STRENGTH,
                  hidden: tuple[str, ...] | None = None, described: bool = False, null: int = 0) -> dict:
    """Build ``cases`` blind cases, diagnose each, and score them.

    stratified : cover every (effect, background) cell of ``stratified_cells`` in turn, each
        effect alone at ``strength``; ``cases`` None or below the number of cells: one
        case per cell.
    hidden : stratified only: run just the cases whose cell hides one of these effects
        (None: all). A case keeps its index, so its data and seed are those of the full run.
    described : the cases are ``described_cases`` (the mechanisms written from prose);
        not with ``stratified``.
    null : this many cases more that hide nothing (``make_case``'s null), on the
        backgrounds in turn: the result's ``null`` says how many named nothing.
    """
    from tqdm import tqdm

    from .diagnose import diagnose
    from .pairs import load_pairs
    from scenes.files import write_json

    spec = default_spec() if spec is None else spec
    if described and stratified:
        raise ValueError("described and stratified are separate benchmarks; give one")
    if stratified:
        if not 0.0 <= strength <= 1.0:
            raise ValueError(f"strength must be in [0, 1], got {strength}")
        real_background()  # fail now, naming where it looked, rather than at the first real case
        cases = max(int(cases or 0), len(stratified_cells()))
    if described:
        real_background()
    if hidden is not None and not stratified:
        raise ValueError(f"hidden selects stratified cells and needs stratified=True, got hidden={hidden!r}")
    if null < 0:
        raise ValueError(f"null must be >= 0 cases, got {null}")
    todo = [(case, False) for case in (stratified_cases(cases, hidden) if stratified else range(cases))]
    todo += [(case, True) for case in range(null)]
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="tactile-gap-bench-") as tmp:
        root = Path(work) if work is not None else Path(tmp)
        root.mkdir(parents=True, exist_ok=True)
        base = contacts(root, spec, progress)
        results = []
        bar = tqdm(todo, desc="benchmark cases", unit="case", disable=not progress)
        for case, nothing in bar:
            kind = "null" if nothing else "described" if described else "case"
            folder = root / f"{kind}_{seed}_{case:03d}"
            truth = make_case(folder, base, spec, case, seed, pairs, strength if stratified else None, described,
                              null=nothing)
            t_case = time.perf_counter()
            report, _ = diagnose(load_pairs(folder / "real", folder / "sim"), seed=seed, factor=factor, intervals=0)
            write_json(folder / "report.json", report)
            results.append({"case": case, **truth, **score(truth["hidden"], report),
                            "stopped_at_start": sorted(report.get("stopped_at_start", {})),
                            "seconds": time.perf_counter() - t_case})
            bar.set_postfix(top1=f"{np.mean([r['top1'] for r in results]):.2f}")
    nulls = [r for r in results if r.get("null")]
    results = [r for r in results if not r.get("null")]
    out = summarise(results, seed, pairs, time.perf_counter() - t0)
    out["factor"] = factor
    if null:
        out["null"] = {"cases": len(nulls), "named_nothing": float(np.mean([r["top1"] for r in nulls])),
                       "results": nulls,
                       "what": "cases that hide nothing (the simulated frames with the real camera's noise): "
                               "named_nothing is the share whose ranking is empty"}
    if stratified:
        out.update(stratify(results, strength))
    if described:
        out.update(described=True, per_mechanism=per_mechanism(results))
    return out


def per_mechanism(results: list[dict]) -> dict:
    """Per mechanism of a described run: its cases' strengths, top-1 share and mean share closed."""
    out: dict[str, dict] = {}
    for r in results:
        m = out.setdefault(r["described"], {"stands_for": r["hidden"][0], "strengths": [], "top1": [], "shrink": [],
                                            "ranked_first": []})
        m["strengths"].append(r["strength"])
        m["top1"].append(float(r["top1"]))
        m["shrink"].append(float(r["shrink"]))
        m["ranked_first"].append(r["ranking"][0] if r["ranking"] else None)
    for m in out.values():
        m["top1"] = float(np.mean(m["top1"]))
        m["mean_shrink"] = float(np.mean(m.pop("shrink")))
    return dict(sorted(out.items()))


def stratify(results: list[dict], strength: float) -> dict:
    """Per cell (``cell_name``) and background: cases, top-1 share, mean share closed; the worst
    cell's share closed over the cells whose gap is not mostly noise."""
    cells: dict[str, dict[str, dict]] = {}
    for r in results:
        for effect in r["hidden"]:
            row = cells.setdefault(cell_name(effect, r.get("mechanism")), {})
            c = row.setdefault(r["background"], {"cases": 0, "top1": [], "shrink": [], "shrink_top1": [],
                                                 "noise_share": []})
            c["cases"] += 1
            for key in ("top1", "shrink", "shrink_top1", "noise_share"):
                c[key].append(float(r[key]))
    noise_cells, kept = {}, []
    for effect, row in cells.items():
        for background, c in row.items():
            for key in ("top1", "shrink", "shrink_top1", "noise_share"):
                c[key] = float(np.mean(c[key]))
            if c["noise_share"] >= NOISE_ONLY_SHARE:
                noise_cells[f"{effect} x {background}"] = (
                    f"the estimated sensor-noise MAE floor is {100 * c['noise_share']:.0f}% of the held-out gap")
            else:
                kept.append(c["shrink"])
    worst = min(((e, b, c["shrink"]) for e, row in cells.items() for b, c in row.items()
                 if f"{e} x {b}" not in noise_cells), key=lambda t: t[2], default=None)
    return {"stratified": True, "strength": strength, "backgrounds": list(STRATIFIED_BACKGROUNDS),
            "per_cell": {e: dict(sorted(row.items())) for e, row in sorted(cells.items())},
            "min_cell_shrink": float(min(kept)) if kept else 0.0,
            "min_cell": None if worst is None else f"{worst[0]} x {worst[1]}",
            "noise_cells": noise_cells,
            "cell_definitions": {
                "top1": "share of the cell's cases whose first ranked effect is the hidden one",
                "shrink": "mean share of the held-out masked MAE gap closed by the selected combination",
                "shrink_top1": "mean share closed by the first ranked effect alone",
                "noise_share": "estimated sensor-noise MAE floor / held-out masked MAE gap",
                "min_cell_shrink": f"smallest cell shrink, over cells whose noise_share is below {NOISE_ONLY_SHARE} "
                                   "(noise cannot be predicted, so those gaps cannot close; listed in noise_cells)"}}


def summarise(results: list[dict], seed: int, pairs: int, seconds: float) -> dict:
    per_effect: dict[str, dict] = {}
    for r in results:
        for h in r["hidden"]:
            e = per_effect.setdefault(h, {"cases": 0, "top1": 0, "top3": 0, "shrink": []})
            e["cases"] += 1
            e["top1"] += int(r["top1"])
            e["top3"] += int(r["top3"])
            e["shrink"].append(r["shrink"])
    for e in per_effect.values():
        e["mean_shrink"] = float(np.mean(e.pop("shrink")))
    n = len(results)
    return {
        "cases": n, "seed": seed, "pairs_per_case": pairs,
        "top1": float(np.mean([r["top1"] for r in results])) if n else 0.0,
        "top3": float(np.mean([r["top3"] for r in results])) if n else 0.0,
        "mean_heldout_shrink": float(np.mean([r["shrink"] for r in results])) if n else 0.0,
        "per_effect": dict(sorted(per_effect.items())),
        "failed": [r for r in results if not r["top1"]],
        "results": results,
        "seconds": seconds,
        "definitions": {
            "top1": "share of cases whose first ranked (significant) effect is a hidden one",
            "top3": "share of cases with every hidden effect among the first three ranked",
            "mean_heldout_shrink": "mean over cases of the share of the held-out masked MAE gap closed by the "
                                   "diagnosis' selected combination of effects",
        },
    }


def bench_diagnose(pairs: int = 144, work: str | Path | None = None, progress: bool = True, seed: int = 0) -> dict:
    """Seconds for a full diagnosis (load, every effect, selection, report) of one
    ``pairs``-pair dataset: a benchmark case built from the base protocol."""
    from .diagnose import run
    from .effects import EFFECTS

    spec = default_spec()
    with tempfile.TemporaryDirectory(prefix="tactile-gap-bench-") as tmp:
        root = Path(work) if work is not None else Path(tmp)
        base = contacts(root, spec, progress)
        folder = root / f"bench_{pairs}"
        truth = make_case(folder, base, spec, 0, seed, pairs)
        t0 = time.perf_counter()
        report = run(folder / "real", folder / "sim", folder / "report", seed=seed, progress=progress)
        seconds = time.perf_counter() - t0
    return {"seconds": seconds, "pairs": report["pairs"], "effects": len(EFFECTS),
            "hidden": truth["hidden"], "ranking": report["ranking"],
            "what": "tactile-sim diagnose on one benchmark case: load both datasets, fit and judge every effect, "
                    "forward selection, figures, report.json and report.html"}
