"""Blind validation of the diagnosis on physics: effects hidden in the reference itself.

Each case is a "real" capture of the virtual rig (``rig.capture.capture``: the printer,
servo and camera twins, so through the driver's code path) whose camera is the reference
with one or two physical effects (fields of ``pbr_tactile.effects.Effects``) at hidden
values drawn from ``HIDDEN``; its simulated counterpart is the reference's replay of the
same taps at the defaults with another seed (``scenes.replay.replay``), so that
its Monte Carlo noise is its own. Cases on the same taps share that replay (and, through
the basis cache, every per-source render of the diagnosis). The diagnosis sees only the
two folders and is scored as the formula benchmark scores it (``benchmark.score``):
top-1, top-3, the held-out share closed, and per effect.

``pairing="fast"`` is the realistic pairing instead: what a user with a real sensor and
the fast path has. The fast path is calibrated (``calibrate_capture``, with taps) to a
capture of the same taps without hidden effects, which takes the renderers' difference
at the defaults out; each case's capture is then diagnosed against the fast path's
replay of it with that profile (the fast path's ``scenes.replay.replay``), with
the fast catalogue. A case is scored on the hidden effects' counterparts in that
catalogue (``physical.COUNTERPARTS``), and each case reports how much the counterpart
closes per region of the image circle. What the calibrated fast path leaves on the capture
it was calibrated to is in every case's gap too (``residual``); a case whose gap is mostly
that residual (``RESIDUAL_SHARE``) is listed in ``below_residual``, and ``above_residual``
scores the others. A reference case's gap holds both renders' Monte Carlo noise, which no
candidate closes; a case whose gap is mostly that noise is listed in ``below_noise`` in
the same way, and ``above_noise`` scores the others. That noise is measured: the gap, as
the diagnosis judges it, between a capture of the same taps without hidden effects
(``root/clean``) and the replay (``measured_floor``); the renders' variance maps give only
a lower bound of it (their photon map's neighbouring pixels are not independent).

Which physics can be hidden (``HIDDEN``): the Effects switches a capture can be rendered
with (``rig run --effect``), and where the unit the camera twin renders differs from the
spec its capture records (``rig run --unit``, ``rig.virtual.UNIT``): the membrane's
compliance, the elastomer's Poisson ratio (the layer's spread), the LEDs' peaks, and the
unit's own camera (its white balance, its seat in the tube, its focus), which the twin
applies to the image it renders as a physical camera would (``rig.virtual.unit_image``: a
defocus disc, a rigid motion of the picture, gains), not by the diagnosis's image models.
The twin's unit also has LEDs of another bin (their powers one by one, which the
capture's exposure rule does not undo unless all change alike). A leak's cone is hidden
with a leak (``WITH``): without one it changes nothing. The coating's gloss and the
sensor's noise are candidates of the diagnosis that no case hides (``NOT_HIDDEN`` says
why).
"""

from __future__ import annotations

import json
import math
import time
from pathlib import Path

import numpy as np

#: Hidden effects and the ranges their values are drawn from (the defaults are
#: ``Effects()``'s and the spec's): a core leak as the paper proposes it; absorption and
#: scattering of pigmented and clouded silicones (a few to a few hundred per metre); a
#: coating that reflects less; the contact's own shadow off; lens fall-off and distortion
#: of small board lenses; flat-white LEDs; an ideal camera response; a membrane that
#: takes 15-22 % more or less of the commanded press than the model; a more compressible
#: elastomer (Poisson ratio 0.25-0.4 for 0.5); LEDs of another bin (every peak 8-20 nm
#: off, either way); a camera whose white balance differs by 10-30 % per channel, either
#: way; a camera seated 2-6 px off in each direction and turned 0.01-0.04 rad (either
#: way); a lens defocused to a blur disc of 1.5-3.5 px radius (at the camera's 640x480);
#: a core leak guided up the glass wall, in a cone of 0.25-0.45 rad about the tube's axis
#: (total internal reflection holds within about 0.33); LEDs of another bin, each 20-45 %
#: brighter or dimmer than the spec's.
HIDDEN = {
    "core_light_leak": (0.15, 0.5),
    "absorption_per_m": (60.0, 110.0),
    "scattering_per_m": (130.0, 240.0),
    "coating_albedo": (0.62, 0.72),
    "contact_shadow": False,
    "vignetting": (0.3, 0.6),
    "lens_distortion": (0.12, 0.25),  # |k1|, either sign; k2 = 0
    "led_spectra": False,
    "camera_response": False,
    "membrane_compliance": (0.15, 0.22),  # |compliance - 1|, either sign
    "layer_spread": (0.25, 0.4),
    "led_peak_shift": (8.0, 20.0),  # nm, every LED, either sign
    "camera_gains": (0.1, 0.3),  # |gain - 1| per channel, each either sign
    "alignment": ((2.0, 6.0), (0.01, 0.04)),  # |du|, |dv| px; |turn| rad; each either sign
    "blur": (1.5, 3.5),  # px, the defocus disc's radius
    "core_leak_cone_rad": (0.25, 0.45),  # rad; with a leak (WITH)
    "led_power": (0.2, 0.45),  # |power - 1| per LED, each either sign
}
#: Hidden effects that change nothing alone, and the one each is hidden with (its value
#: drawn from its own range) where the case does not hide that already.
WITH = {"core_leak_cone_rad": "core_light_leak"}
#: Hidden effects that another hidden one's candidate carries, scored through it: against
#: a simulation without a leak the leak's cone is fitted with a leak fraction of its own
#: (``physical.physical_catalogue``), so it names the leak too, and a Lambertian leak
#: cannot match a leak aimed up the tube.
CARRIED_BY = {"core_light_leak": "core_leak_cone_rad"}
#: Hidden effects drawn as an offset of either sign from their default (value: the default).
EITHER_SIDE = {"membrane_compliance": 1.0, "led_peak_shift": 0.0}
#: Hidden effects that are the twin's unit (``rig run --unit``), not Effects switches.
UNIT_HIDDEN = ("membrane_compliance", "layer_spread", "led_peak_shift", "camera_gains", "alignment", "blur",
               "led_power")
#: Candidates no case hides, and why.
NOT_HIDDEN = {
    "coating_gloss": "a glossy coating needs the volpath estimator, about 10 times slower than photons at the same "
                     "noise",
    "sensor_noise": "noise is estimated, not predicted",
}
#: Chance that a case after the first pass over HIDDEN hides two effects.
TWO_EFFECTS = 0.4
#: The taps of every case: the issue's example (12 taps of the base protocol's sphere and cone).
OBJECTS = "sphere,cone"
TAPS = 12
#: The rendering of both sides: film, noise target, passes, photons.
RENDER = {"film": "160x120", "target_rse": "0.1", "max_passes": "4", "photons": str(1 << 18)}
#: The replay's seed (the captures use the renderer's default, 0).
SIM_SEED = 1000
#: The simulated sides a case can be diagnosed against: the reference's replay, or the
#: fast path's replay with a profile calibrated to a capture without hidden effects.
PAIRINGS = ("reference", "fast")
#: Taps of that capture the fast path's calibration uses (``calibrate_capture``'s ``taps``).
CALIBRATION_TAPS = 10
#: A case is below its floor when what no candidate can close is at least this share of
#: its held-out gap, so that the hidden effect makes at most a fifth of it: for the fast
#: pairing, what the calibrated fast path leaves on the capture it was calibrated to; for
#: the reference pairing, the two renders' Monte Carlo noise.
RESIDUAL_SHARE = 0.8


def draw(case: int, seed: int, cases: int | None = None) -> dict[str, object]:
    """The hidden effects of one case of ``cases`` and their values: every effect of
    ``HIDDEN`` once in a seeded order, spread over the first cases (where there are fewer
    cases than effects, a case hides each ``cases``-th of that order, so every effect is
    hidden; None: one case per effect), then one or two at random; each with what it
    needs (``WITH``)."""
    names = list(HIDDEN)
    order = [str(n) for n in np.random.default_rng(seed).permutation(names)]
    rng = np.random.default_rng([seed, case])
    first = len(order) if cases is None else max(1, min(int(cases), len(order)))
    if case < first:
        chosen = order[case::first]
    else:
        count = 2 if rng.random() < TWO_EFFECTS else 1
        chosen = [str(n) for n in rng.choice(names, size=count, replace=False)]
    chosen += [WITH[n] for n in chosen if n in WITH and WITH[n] not in chosen]
    out = {}
    for name in chosen:
        spec = HIDDEN[name]
        if isinstance(spec, bool):
            out[name] = spec
        elif name == "lens_distortion":
            k1 = float(rng.uniform(*spec)) * _side(rng)
            out[name] = (round(k1, 4), 0.0)
        elif name in ("camera_gains", "led_power"):  # per channel; per LED of the default spec
            out[name] = tuple(round(1.0 + _side(rng) * float(rng.uniform(*spec)), 4) for _ in range(_count(name)))
        elif name == "alignment":
            (shift, turn) = spec
            out[name] = (round(_side(rng) * float(rng.uniform(*shift)), 3),
                         round(_side(rng) * float(rng.uniform(*shift)), 3),
                         round(_side(rng) * float(rng.uniform(*turn)), 4))
        elif name in EITHER_SIDE:
            out[name] = round(EITHER_SIDE[name] + _side(rng) * float(rng.uniform(*spec)), 4)
        else:
            out[name] = round(float(rng.uniform(*spec)), 4)
    return out


def _count(name: str) -> int:
    """How many values a per-channel or per-LED hidden effect has."""
    from scenes.spec_read import default_spec

    return len(default_spec().leds) if name == "led_power" else 3


def _side(rng) -> float:
    return float(rng.choice([-1.0, 1.0]))


def capture_settings(hidden: dict) -> tuple[list[str], dict]:
    """What ``hidden`` sets on the virtual rig: the Effects switches as the renderer's
    ``effects`` option (``NAME=VALUE`` settings, ``pbr_tactile.effects.Effects.with_settings``)
    and the twin's unit (``UNIT_HIDDEN``; ``rig.virtual.unit_spec``'s {name: float or tuple})."""
    effects, unit = [], {}
    for name, value in hidden.items():
        if name in UNIT_HIDDEN:
            unit[name] = tuple(float(v) for v in value) if isinstance(value, tuple) else float(value)
        else:
            text = (("true" if value else "false") if isinstance(value, bool) else
                    ",".join(str(v) for v in value) if isinstance(value, tuple) else str(value))
            effects.append(f"{name}={text}")
    return effects, unit


def render_options(**more) -> dict:
    """The reference's options for RENDER and ``more`` (renderer option keys), in the
    command line's order (``scenes.renderers.RENDERER_OPTIONS``)."""
    from scenes.renderers import RENDERER_OPTIONS

    width, height = (int(x) for x in RENDER["film"].split("x"))
    options = {"film": [width, height], "target_rse": float(RENDER["target_rse"]),
               "max_passes": int(RENDER["max_passes"]), "photons": int(RENDER["photons"]), **more}
    return {key: options[key] for key in RENDERER_OPTIONS if key in options}


def _workers() -> int:
    """The replay's worker processes: ``tactile-sim dataset``'s default."""
    import os

    return min(2, os.cpu_count() or 1)


def capture(folder: Path, hidden: dict, progress: bool = False, taps: int = TAPS) -> Path:
    """The case's "real" capture: the virtual rig (``rig.capture.capture``) with the
    reference as its camera, the first ``taps`` taps of the base protocol on OBJECTS."""
    from dataclasses import replace

    from pbr_tactile import plugin as pbr
    from phong_reference import plugin as phong
    from rig.capture import alignment_hook, capture as run_rig
    from scenes.body import checked_membrane
    from scenes.protocol import make_protocol
    from scenes.spec_read import load_spec

    spec = load_spec(None)
    protocol = make_protocol("base", spec, checked_membrane(spec), tuple(OBJECTS.split(",")), seed=0)
    if taps:
        protocol = replace(protocol, taps=protocol.taps[:taps])
    effects, unit = capture_settings(hidden)
    options = render_options(**({"effects": effects} if effects else {}))
    run_rig(folder, spec, protocol, pbr, options, unit=unit,
            alignment=alignment_hook(spec, phong, who="studies.gap.physical_benchmark"), progress=progress)
    return folder


def replay(capture_dir: Path, folder: Path, progress: bool = False) -> Path:
    """The simulated side: the reference at its defaults, replaying the capture's taps."""
    from pbr_tactile import plugin as pbr
    from scenes.replay import read_capture, replay as render_replay

    render_replay(read_capture(capture_dir), folder, pbr, render_options(seed=SIM_SEED), workers=_workers(),
                  progress=progress)
    return folder


def calibrated_fast_path(root: Path, progress: bool = False) -> Path:
    """The fast path's profile (``root/profile/profile.toml``), calibrated to a capture of
    the benchmark's taps without hidden effects (``root/clean``); both kept and reused."""
    from pbr_tactile.calibrate_capture import calibrate_capture
    from phong_reference import plugin as phong

    clean = capture(root / "clean", {}, progress)
    profile = root / "profile" / "profile.toml"
    if not profile.is_file():
        report = calibrate_capture(clean, profile.parent, phong.calibrate, taps=CALIBRATION_TAPS,
                                   progress=progress)["report"]
        if not report["converged"]:
            raise RuntimeError(f"the fast path's calibration to {clean} did not converge; see {profile.parent}")
    return profile


def fast_replay(capture_dir: Path, profile: Path, folder: Path, progress: bool = False) -> Path:
    """The realistic pairing's simulated side: the fast path of the calibrated unit,
    replaying the capture's taps."""
    from phong_reference import plugin as phong
    from scenes.replay import read_capture, replay as render_replay

    render_replay(read_capture(capture_dir), folder, phong, {"profile": str(profile)}, workers=_workers(),
                  progress=progress)
    return folder


def measured_floor(root: Path, sim: Path, seed: int, factor: int, progress: bool = False) -> float:
    """The renders' Monte Carlo floor of every reference case's gap: the held-out gap, as
    the diagnosis judges it, between a capture of the benchmark's taps without hidden
    effects (``root/clean``, kept and reused) and the replay ``sim``."""
    from .diagnose import heldout_gap
    from .pairs import load_pairs

    return heldout_gap(load_pairs(capture(root / "clean", {}, progress), sim), seed=seed, factor=factor)


def counterparts(hidden) -> list[str]:
    """The fast catalogue's counterparts of hidden physical effects, each once."""
    from .physical import COUNTERPARTS

    return list(dict.fromkeys(COUNTERPARTS[name] for name in hidden))


def score_physical(hidden: dict, report: dict, floor: float | None = None) -> dict:
    """``benchmark.score`` of a case, on the hidden effects themselves for a reference
    diagnosis and on their counterparts for a fast one; with the fitted values, and for a
    fast one what each counterpart closes per region of the image circle. ``floor``: the
    measured Monte Carlo floor of a reference case's gap (``measured_floor``); None: the
    lower bound from the renders' variance maps."""
    from .benchmark import score

    fast = report.get("model") == "fast"
    names = counterparts(hidden) if fast else [n for n in hidden if CARRIED_BY.get(n) not in hidden]
    out = score(names, report)
    out["gap"] = float(report["gap"]["heldout"]["masked"]["mae"]["mean"])
    # a reference candidate's own value where it has one parameter of its name (else all of them)
    out["fitted"] = {name: report["effects"][name]["params"] if fast else
                     report["effects"][name]["params"].get(name, report["effects"][name]["params"])
                     for name in names if name in report["effects"]}
    chosen = report["selection"][-1]["params"] if report.get("selection") else {}
    out["fitted_in_selection"] = {name: chosen[name].get(name, chosen[name]) for name in names if name in chosen}
    if fast:
        out["counterparts"] = names
        out["closes"] = {name: report["effects"][name]["share_closed"] for name in names if name in report["effects"]}
        out["selection_closes"] = report["explained"]["share_closed"]
    else:  # the capture is rendered as the replay is, so its noise is the replay's: the difference's is sqrt(2) x
        mc = report.get("noise", {}).get("monte_carlo")  # absent where the replay kept no variance: not set apart
        out["noise_floor_bound"] = math.sqrt(2.0) * mc["judged"]["mae_floor"]["sim"] if mc else None
        floor = out["noise_floor_bound"] if floor is None else float(floor)
        out["noise_floor"] = floor
        out["noise_floor_share"] = 0.0 if floor is None else floor / out["gap"] if out["gap"] > 0 else float("inf")
    return out


def run_physical_benchmark(cases: int = 12, seed: int = 0, work: str | Path | None = None, progress: bool = True,
                           factor: int = 2, pairing: str = "reference") -> dict:
    """Build ``cases`` cases, diagnose each against ``pairing``'s simulated side (one of
    ``PAIRINGS``), and score them (module doc)."""
    if pairing not in PAIRINGS:
        raise ValueError(f"pairing must be one of {PAIRINGS}, got {pairing!r}")
    import tempfile

    from tqdm import tqdm

    from .benchmark import summarise
    from .diagnose import diagnose
    from .pairs import load_pairs
    from scenes.files import write_json

    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="tactile-gap-physical-") as tmp:
        root = Path(work) if work is not None else Path(tmp)
        root.mkdir(parents=True, exist_ok=True)
        results = []
        profile = calibrated_fast_path(root) if pairing == "fast" else None
        sim = root / ("sim" if pairing == "reference" else "sim_fast")
        floor = None
        bar = tqdm(range(cases), desc="physical cases", unit="case", disable=not progress)
        for case in bar:
            hidden = draw(case, seed, cases)
            folder = root / f"case_{seed}_{case:03d}"
            t_case = time.perf_counter()
            capture(folder / "real", hidden)
            t_real = time.perf_counter() - t_case
            first = root / f"case_{seed}_000" / "real"  # the taps every case shares
            if pairing == "reference":
                replay(first, sim)  # once; then it resumes with nothing to do
                floor = measured_floor(root, sim, seed, factor) if floor is None else floor
            else:
                fast_replay(first, profile, sim)
            t_diag = time.perf_counter()
            report, _ = diagnose(load_pairs(folder / "real", sim), seed=seed, factor=factor, intervals=0)
            write_json(folder / ("report.json" if pairing == "reference" else "report_fast.json"), report)
            results.append({"case": case, "hidden": list(hidden), "values": {k: v for k, v in hidden.items()},
                            **score_physical(hidden, report, floor),
                            "seconds": time.perf_counter() - t_case, "capture_seconds": t_real,
                            "diagnosis_seconds": time.perf_counter() - t_diag,
                            "renders": report.get("renders")})
            bar.set_postfix(top1=f"{np.mean([r['top1'] for r in results]):.2f}")
            write_json(root / ("partial.json" if pairing == "reference" else f"partial_{pairing}.json"),
                       {"results": results})
        residual = None
        if pairing == "fast" and results:  # the calibrated fast path against the capture it was calibrated to
            clean, _ = diagnose(load_pairs(root / "clean", sim), seed=seed, factor=factor, intervals=0)
            write_json(root / "clean_report_fast.json", clean)
            residual = float(clean["gap"]["heldout"]["masked"]["mae"]["mean"])
    out = summarise(results, seed, TAPS, time.perf_counter() - t0)
    if residual is not None:
        out.update(_against_residual(results, residual, clean["ranking"]))
    elif results:
        out.update(_against_noise(results))
        out["noise_floor"] = {"measured": floor, "what": "held-out masked MAE, as the diagnosis judges it, between "
                              "a capture of the same taps without hidden effects and the replay"}
    out.update({"physical": True, "pairing": pairing,
                "hidden_ranges": HIDDEN,
                "not_hidden": NOT_HIDDEN, "objects": OBJECTS, "render": RENDER, "sim_seed": SIM_SEED, "factor": factor,
                "hidden_at_least_once": sorted({h for r in results for h in r["hidden"]}),
                "never_hidden": sorted(set(HIDDEN) - {h for r in results for h in r["hidden"]})})
    return out


#: What ``bench_physical`` hides: the leak of issue 23's example (a 0.3 share of each
#: LED's light into the glass core).
BENCH_HIDDEN = {"core_light_leak": 0.3}


def bench_physical(pairs: int = 36, work: str | Path | None = None, progress: bool = True, seed: int = 0) -> dict:
    """Seconds for one whole diagnosis (``diagnose.run``: load, every physical candidate
    with its basis renders, selection, report) of a ``pairs``-tap reference capture with
    BENCH_HIDDEN against the reference's replay of it. The capture and the replay are
    rendered first and timed apart (``setup_seconds``); with ``work`` they are kept and
    reused, and the basis renders the diagnosis makes are cached there too (a second run
    on the same folder is warm: ``cold`` says which)."""
    import os
    import tempfile
    from unittest import mock

    from scenes.cache import CACHE_ENV

    from .diagnose import run

    if pairs < 4:
        raise ValueError(f"pairs must be >= 4 (two taps to fit and two to judge), got {pairs}")
    with tempfile.TemporaryDirectory(prefix="tactile-gap-bench-physical-") as tmp:
        root = Path(work) if work is not None else Path(tmp)
        root.mkdir(parents=True, exist_ok=True)
        cold = not (root / "cache").exists()
        with mock.patch.dict(os.environ, {CACHE_ENV: str(root / "cache")}):
            t0 = time.perf_counter()
            real = capture(root / f"real_{pairs}", BENCH_HIDDEN, progress, taps=pairs)
            sim = replay(real, root / f"sim_{pairs}", progress)
            setup = time.perf_counter() - t0
            t0 = time.perf_counter()
            report = run(real, sim, root / f"report_{pairs}", seed=seed, progress=progress)
            seconds = time.perf_counter() - t0
    ranking = report.get("ranking", [])
    leak = report.get("effects", {}).get("core_light_leak", {})
    return {"seconds": seconds, "setup_seconds": setup, "pairs": report["pairs"], "cold": cold,
            "hidden": BENCH_HIDDEN, "ranking": ranking, "first": ranking[0] if ranking else None,
            "hidden_share_closed": leak.get("share_closed"), "hidden_fitted": leak.get("params"),
            "renders": report.get("renders"), "model": report.get("model"), "render": RENDER,
            "what": "tactile-sim diagnose of a reference capture (the virtual rig's camera, the hidden leak) against "
                    "the reference's replay of its taps: load, every physical candidate and its per-source basis "
                    "renders, selection, figures, report; the capture and the replay are setup_seconds, apart"}


def _against_residual(results: list[dict], residual: float, ranking: list[str]) -> dict:
    """What the calibrated fast path leaves on the capture it was calibrated to (its
    held-out masked MAE, the same split), each case's gap against it (``residual_share``),
    and the scores over the cases whose hidden effect makes more than
    1 - ``RESIDUAL_SHARE`` of their gap."""
    for r in results:
        r["residual_share"] = residual / r["gap"] if r["gap"] > 0 else float("inf")
    return {"per_region": _per_region(results),
            "residual": {"heldout_masked_mae": residual, "ranking": ranking,
                         "what": "the calibrated fast path against the capture without hidden effects it was "
                                 "calibrated to: what calibration leaves, in every case's gap too"},
            **_split(results, "residual_share", "residual", "calibration residual")}


def _against_noise(results: list[dict]) -> dict:
    """The scores over the reference cases whose gap is more than 1 - ``RESIDUAL_SHARE``
    the hidden effects' own, not the renders' Monte Carlo noise (``noise_floor_share``)."""
    return _split(results, "noise_floor_share", "noise", "renders' Monte Carlo noise floor (measured: the gap "
                  "between a capture without hidden effects and the replay)")


def _split(results: list[dict], share: str, name: str, what: str) -> dict:
    """``below_<name>``: the cases whose ``share`` of their gap is at least
    ``RESIDUAL_SHARE``; ``above_<name>``: the scores of the others."""
    above = [r for r in results if r[share] < RESIDUAL_SHARE]
    return {f"below_{name}": [r["case"] for r in results if r[share] >= RESIDUAL_SHARE],
            f"above_{name}": {"cases": len(above),
                              "top1": float(np.mean([r["top1"] for r in above])) if above else 0.0,
                              "top3": float(np.mean([r["top3"] for r in above])) if above else 0.0,
                              "mean_heldout_shrink": float(np.mean([r["shrink"] for r in above])) if above else 0.0,
                              "what": f"cases whose {what} is below {RESIDUAL_SHARE:.0%} of their held-out gap"}}


def _per_region(results: list[dict]) -> dict:
    """Per hidden effect: the mean share of the held-out gap its counterpart closes alone
    in each scope (masked, and each region of the image circle)."""
    from .physical import COUNTERPARTS

    rows: dict[str, dict[str, list]] = {}
    for r in results:
        for name in r["hidden"]:
            closes = r["closes"].get(COUNTERPARTS[name])
            if closes is not None:
                for scope, share in closes.items():
                    rows.setdefault(name, {}).setdefault(scope, []).append(share)
    return {name: {scope: float(np.mean(v)) for scope, v in row.items() if scope != "full"}
            for name, row in sorted(rows.items())}


def main_json(path: str | Path, **kwargs) -> dict:
    from scenes.files import write_json

    result = run_physical_benchmark(**kwargs)
    write_json(Path(path), result)
    return json.loads(Path(path).read_text())
