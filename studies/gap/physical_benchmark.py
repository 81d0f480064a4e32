"""Blind validation of the diagnosis on physics: effects hidden in the reference itself.

Each case is a "real" capture of the virtual rig (``tactile-sim rig run`` with the printer,
servo and camera twins, so through the driver's code path) whose camera is the reference
with one or two physical effects (fields of ``pbr_tactile.effects.Effects``) at hidden
values drawn from ``HIDDEN``; its simulated counterpart is the reference's replay of the
same taps at the defaults with another seed (``tactile-sim dataset --replay``), so that
its Monte Carlo noise is its own. Cases on the same taps share that replay (and, through
the basis cache, every per-source render of the diagnosis). The diagnosis sees only the
two folders and is scored as the formula benchmark scores it (``benchmark.score``):
top-1, top-3, the held-out share closed, and per effect.

Which physics can be hidden: the Effects switches a capture can be rendered with
(``HIDDEN``). The membrane's mechanics, the LEDs' powers and spectra and the unit's camera
and alignment are candidates of the diagnosis but are not switches of the virtual rig's
camera yet, so no case hides them (``NOT_HIDDEN`` says why).
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np

#: Hidden effects and the ranges their values are drawn from (the defaults are
#: ``Effects()``'s): a core leak as the paper proposes it; absorption and scattering of
#: pigmented and clouded silicones (a few to a few hundred per metre); a coating that
#: reflects less; the contact's own shadow off; lens fall-off and distortion of small
#: board lenses; flat-white LEDs; an ideal camera response.
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
}
#: Candidates no case hides, and why.
NOT_HIDDEN = {
    "coating_gloss": "a glossy coating needs the volpath estimator, about 10 times slower than photons at the same "
                     "noise",
    "sensor_noise": "noise is estimated, not predicted",
    "core_leak_cone_rad": "it shapes only a core leak, so it is hidden only together with one",
    "membrane_compliance, layer_spread, led_power, led_peak_shift, camera_gains, alignment, blur":
        "not switches of the virtual rig's camera yet (they need a hidden spec or profile that the replay does not "
        "copy)",
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


def draw(case: int, seed: int) -> dict[str, object]:
    """The hidden effects of one case and their values: every effect of ``HIDDEN`` once
    in turn (a seeded order), then one or two at random."""
    names = list(HIDDEN)
    order = [str(n) for n in np.random.default_rng(seed).permutation(names)]
    rng = np.random.default_rng([seed, case])
    if case < len(order):
        chosen = [order[case]]
    else:
        count = 2 if rng.random() < TWO_EFFECTS else 1
        chosen = [str(n) for n in rng.choice(names, size=count, replace=False)]
    out = {}
    for name in chosen:
        spec = HIDDEN[name]
        if isinstance(spec, bool):
            out[name] = spec
        elif name == "lens_distortion":
            k1 = float(rng.uniform(*spec)) * float(rng.choice([-1.0, 1.0]))
            out[name] = (round(k1, 4), 0.0)
        else:
            out[name] = round(float(rng.uniform(*spec)), 4)
    return out


def effect_settings(hidden: dict) -> list[str]:
    """``--effect NAME=VALUE`` arguments of ``hidden``."""
    out = []
    for name, value in hidden.items():
        text = (("true" if value else "false") if isinstance(value, bool) else
                ",".join(str(v) for v in value) if isinstance(value, tuple) else str(value))
        out += ["--effect", f"{name}={text}"]
    return out


def _run(argv: list[str]) -> None:
    from scenes.cli import main

    code = main(argv)
    if code:
        raise RuntimeError(f"tactile-sim {' '.join(argv)} exited {code}")


def capture(folder: Path, hidden: dict, progress: bool = False) -> Path:
    """The case's "real" capture: the virtual rig with the reference as its camera."""
    render = [x for k, v in RENDER.items() for x in (f"--{k.replace('_', '-')}", v)]
    _run(["rig", "run", "--printer", "twin", "--servos", "twin", "--camera", "twin", "--renderer", "pbr", *render,
          *effect_settings(hidden), "--objects", OBJECTS, "--protocol", "base", "--limit", str(TAPS), "--yes",
          "--out", str(folder)] + ([] if progress else ["--quiet"]))
    return folder


def replay(capture_dir: Path, folder: Path, progress: bool = False) -> Path:
    """The simulated side: the reference at its defaults, replaying the capture's taps."""
    render = [x for k, v in RENDER.items() for x in (f"--{k.replace('_', '-')}", v)]
    _run(["dataset", "--replay", str(capture_dir), "--renderer", "pbr", *render, "--render-seed", str(SIM_SEED),
          "--out", str(folder)] + ([] if progress else ["--quiet"]))
    return folder


def score_physical(hidden: dict, report: dict) -> dict:
    from .benchmark import score

    out = score(list(hidden), report)
    fitted = {}
    for name in hidden:
        effect = report["effects"].get(name)
        if effect is not None:
            fitted[name] = effect["params"][name]
    out["fitted"] = fitted
    return out


def run_physical_benchmark(cases: int = 12, seed: int = 0, work: str | Path | None = None, progress: bool = True,
                           factor: int = 2) -> dict:
    """Build ``cases`` cases, diagnose each, and score them (module doc)."""
    import tempfile

    from tqdm import tqdm

    from .benchmark import summarise
    from .diagnose import diagnose
    from .pairs import load_pairs
    from .report import write_json

    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="tactile-gap-physical-") as tmp:
        root = Path(work) if work is not None else Path(tmp)
        root.mkdir(parents=True, exist_ok=True)
        results = []
        sim = root / "sim"
        bar = tqdm(range(cases), desc="physical cases", unit="case", disable=not progress)
        for case in bar:
            hidden = draw(case, seed)
            folder = root / f"case_{seed}_{case:03d}"
            t_case = time.perf_counter()
            capture(folder / "real", hidden)
            t_real = time.perf_counter() - t_case
            replay(root / f"case_{seed}_000" / "real", sim)  # once; then it resumes with nothing to do
            t_diag = time.perf_counter()
            report, _ = diagnose(load_pairs(folder / "real", sim), seed=seed, factor=factor, intervals=0)
            write_json(folder / "report.json", report)
            results.append({"case": case, "hidden": list(hidden), "values": {k: v for k, v in hidden.items()},
                            **score_physical(hidden, report),
                            "seconds": time.perf_counter() - t_case, "capture_seconds": t_real,
                            "diagnosis_seconds": time.perf_counter() - t_diag,
                            "renders": report.get("renders")})
            bar.set_postfix(top1=f"{np.mean([r['top1'] for r in results]):.2f}")
            write_json(root / "partial.json", {"results": results})
    out = summarise(results, seed, TAPS, time.perf_counter() - t0)
    out.update({"physical": True, "hidden_ranges": {k: list(v) if isinstance(v, tuple) else v for k, v in HIDDEN.items()},
                "not_hidden": NOT_HIDDEN, "objects": OBJECTS, "render": RENDER, "sim_seed": SIM_SEED, "factor": factor,
                "hidden_at_least_once": sorted({h for r in results for h in r["hidden"]}),
                "never_hidden": sorted(set(HIDDEN) - {h for r in results for h in r["hidden"]})})
    return out


def main_json(path: str | Path, **kwargs) -> dict:
    from .report import write_json

    result = run_physical_benchmark(**kwargs)
    write_json(Path(path), result)
    return json.loads(Path(path).read_text())
