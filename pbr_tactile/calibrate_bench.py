"""Blind recovery benchmark of calibration: virtual sensors with hidden parameters.

Each case draws a virtual sensor: the reference's physical effects from the calibration
grid's values (the basis is rendered on that grid, so recovery measures the search, not
interpolation between grid points), and the camera and alignment parameters from the
stated ranges below. Its no-contact image is rendered with another seed than the
calibration's basis (so its Monte Carlo noise is its own), at the camera's size, and
calibrated from without its values.

Scoring, per identifiable parameter:
- positive quantities (gamma, scale, the lens' illumination at the circle's edge V(1),
  each LED's leak fraction where it is at least LEAK_MIN, each LED's gains relative to
  the brightest gain, the grid's effects): |fit - true| / true;
- zero-centred ones (rotation, shift): |fit - true| / the half-width of their range.
With gains free per LED, LEDs whose images differ only by a turn can swap: the rotation
is known modulo 2 pi / L and the LEDs' parameters up to that renaming, so scoring first
finds the renaming (the one that best matches the rotation).

``heldout_mae_over_noise``: the MAE on the held-out sectors over the virtual image's own
Monte Carlo noise (its standard error, carried through the camera's response).
"""

from __future__ import annotations

import math
import time

import numpy as np

from .calibrate import (
    BASIS_EFFECTS,
    GRID,
    ImageModel,
    Nonlinear,
    calibrate_background,
    emitter_basis,
)
from .effects import Effects

#: Ranges the hidden values are drawn from (uniform).
RANGES = {
    "rotation_rad": (-math.pi / 3, math.pi / 3),
    "led_azimuth_rad": (-0.15, 0.15),
    "leak": (0.0, 0.6),
    "scale": (0.9, 1.1),
    "shift_px": (-15.0, 15.0),
    "edge_illumination": (0.35, 1.0),
    "gamma": (1.6, 2.6),
    "gain": (0.2, 1.0),
}
#: Leak fractions below this are scored as absent, not relatively.
LEAK_MIN = 0.1
#: The virtual image's seed differs from the basis' by this.
SEED_OFFSET = 1000


def draw(rng: np.random.Generator, leds: int, grid: dict) -> tuple[Nonlinear, np.ndarray, dict]:
    """Hidden nonlinear parameters, gains (L, 3) and grid effects of one virtual sensor."""
    u = lambda name, n=None: rng.uniform(*RANGES[name], n)  # noqa: E731
    edge = u("edge_illumination")
    nl = Nonlinear(float(u("rotation_rad")), tuple(u("led_azimuth_rad", leds)), tuple(u("leak", leds)),
                   float(u("scale")), tuple(u("shift_px", 2)), (float(edge - 1.0), 0.0), float(u("gamma")))
    gains = u("gain", (leds, 3))
    effects = {name: float(rng.choice(values)) for name, values in grid.items()}
    return nl, gains, effects


def _errors(fit: dict, nl: Nonlinear, gains: np.ndarray, effects: dict, leds: int) -> dict[str, float]:
    """Relative error per scored parameter (module doc)."""
    turn = 2 * math.pi / leds
    d = fit["rotation_rad"] - nl.tied().rotation_rad  # the fit reports the tied rotation
    k = min(range(leds), key=lambda shift: abs(math.remainder(d - shift * turn, 2 * math.pi)))
    rot_err = abs(math.remainder(d - k * turn, 2 * math.pi))
    perm = [(j + k) % leds for j in range(leds)]  # fitted LED j sits where true LED j + k does
    half = lambda name: (RANGES[name][1] - RANGES[name][0]) / 2  # noqa: E731
    out = {"rotation_rad": rot_err / half("rotation_rad"),
           "gamma": abs(fit["gamma"] - nl.gamma) / nl.gamma,
           "scale": abs(fit["scale"] - nl.scale) / nl.scale,
           "shift_px": float(np.max(np.abs(np.subtract(fit["shift_px"], nl.shift_px)))) / half("shift_px"),
           "edge_illumination": abs(sum(fit["vignetting"]) - sum(nl.vignetting)) / (1 + sum(nl.vignetting))}
    fitted_gains = np.asarray(fit["led_gains"])
    rel_fit = fitted_gains / fitted_gains.max()
    rel_true = gains / gains.max()
    for j, true in enumerate(perm):
        leak_true, leak_fit = nl.leak[true], fit["led_leak"][j]
        out[f"led{true}_leak"] = abs(leak_fit - leak_true) / max(leak_true, LEAK_MIN)
        for c, ch in enumerate("rgb"):
            out[f"led{true}_gain_{ch}"] = abs(rel_fit[j, c] - rel_true[true, c]) / rel_true[true, c]
    for name, value in effects.items():
        out[name] = abs(fit["effects"][name] - value) / value if value else abs(fit["effects"][name])
    return out


def benchmark(spec, mesh, camera, cases: int = 6, seed: int = 0, film: tuple[int, int] = (160, 120),
              grid: dict | None = None, photons: int = 1 << 18, spp: int = 32, progress=None, cold: bool = False) -> dict:
    """Run ``cases`` blind recoveries; returns the benchmark's JSON (see the module doc).
    cold : render every basis afresh (no disk cache), as a first calibration would."""
    grid = GRID if grid is None else grid
    rng = np.random.default_rng(seed)
    per_parameter: dict[str, list[float]] = {}
    mae_over_noise, seconds, r2s = [], [], []
    leds = len(spec.leds)
    for case in range(cases):
        nl, gains, effects = draw(rng, leds, grid)
        fx = Effects().with_settings([f"{k}={v}" for k, v in {**BASIS_EFFECTS, **effects}.items()])
        # the virtual sensor's own render, at the film's size with its own seed (its own noise)
        hidden = emitter_basis(spec, mesh, camera, fx, film, photons, spp, 2, seed + SEED_OFFSET + case,
                               use_cache=not cold)
        circle = (camera.cx, camera.cy, camera.mask_radius_px)
        model = ImageModel(hidden["mean"], hidden["names"], camera, circle)
        design = model.design(nl)
        gains_scaled = gains / np.percentile(design[model.inside].sum(axis=1), 95)
        image = model.render(nl, gains_scaled, (0.0, 0.0, 0.0), (1.0, 1.0, 1.0))
        k = camera.height // film[1]
        real = np.repeat(np.repeat(image, k, axis=0), k, axis=1)
        t0 = time.perf_counter()
        cal = calibrate_background(real, spec, mesh, camera, film=film, grid=grid, photons=photons, spp=spp, seed=seed,
                                   bootstrap=0, use_cache=not cold)
        seconds.append(time.perf_counter() - t0)
        fit = {**cal.report["parameters"], "effects": cal.report["best_effects"]}
        for name, err in _errors(fit, nl, gains_scaled, effects, leds).items():
            per_parameter.setdefault(name, []).append(float(err))
        # the virtual image's Monte Carlo standard error, through the response
        lin = design @ gains_scaled
        var = model.design_variance(hidden["variance"], nl) @ np.square(gains_scaled)
        slope = np.where(lin > 0, np.power(np.maximum(lin, 1e-12), 1 / nl.gamma - 1) / nl.gamma, 0.0)
        noise = float(np.mean(np.sqrt(var * slope**2)[model.inside]))
        mae = float(np.mean([cal.report["heldout_mae"][ch] for ch in "rgb" if not cal.report["saturated"][ch]]))
        mae_over_noise.append(mae / noise if noise > 0 else float("nan"))
        r2s.append(cal.report["heldout_r2"])
        if progress is not None:
            progress(case + 1, cases)
    errors = np.concatenate([np.asarray(v) for v in per_parameter.values()])
    return {
        "cases": cases,
        "seed": seed,
        "median_relative_error": float(np.median(errors)),
        "share_within_10pct": float(np.mean(errors <= 0.10)),
        "per_parameter": {name: {"median": float(np.median(v)), "max": float(np.max(v))}
                          for name, v in per_parameter.items()},
        "heldout_mae_over_noise": float(np.median(mae_over_noise)),
        "heldout_r2": r2s,
        "seconds_per_case": float(np.median(seconds)),
        "scoring": __doc__.split("\n\n", 3)[2],
        "ranges": {k: list(v) for k, v in RANGES.items()},
        "grid": {k: list(v) for k, v in grid.items()},
    }
