"""The fast path's LED constants fitted to a unit's taps.

Without clipping, the fast path's change under a contact (``phong_reference.profiled``)
is linear in a_m = k_d,m colour_m and b_m = k_s,m colour_m for a fixed shininess alpha:

    I_t(p) - I_0(p) = align( sum_m a_m [(L_m . N_t) - (L_m . N_0)](p)
                                  + b_m [(R_m . V)_t^alpha - (R_m . V)_0^alpha](p) )

The terms are the fast path's own (the calibrated unit's LEDs, fields and alignment),
rendered with unit coefficients, up to three LEDs at a time, each in its own colour
channel, with no background (so nothing clips). Against
the real change (a real tap minus the real no-contact capture, in image units: the fast
path has no camera response), each channel's a_mc, b_mc are fitted by non-negative
least squares on the fitted taps' contact regions, for each shininess of SHININESS.
The best alpha's coefficients are then put in the Phong model's form: colour_m = a_m /
max(a_m), k_d,m = max(a_m), and k_s,m the least-squares scale of colour_m to b_m. The
held-out taps judge that form (``scenes.captures.split``), against the spec's constants
("before").

A field whose light leaves each LED's own place (``linear``: straight rays) depends on
where the LEDs are, which a spec often only estimates; :func:`fit_led_places` searches
each LED's place too (its height and its distance from the axis, on PLACE_HEIGHTS_M x
PLACE_RADII about the spec's, then refined off the grid in halving steps), fitting the
constants at every candidate on the fitted taps, and reports the places it found.
"""

from __future__ import annotations

import dataclasses

import numpy as np
from scipy import optimize

from scenes.camera import Camera
from scenes.captures import RealTaps, split
from scenes.elastic import MembraneLayer
from scenes.profile import Profile
from scenes.spec import SensorSpec

from . import environment
from .profiled import ProfiledRenderer

#: The coefficient an environment term is rendered with alone (``_environment_terms``), on
#: the background: its change (terms of a few units at most) stays far from where the
#: image clips, at 0 and at 1.
ENVIRONMENT_PROBE = 1e-3
#: The environment's terms are fitted with a ridge of this share of each term's energy.
ENVIRONMENT_RIDGE = 1e-3
#: The shininess values searched.
SHININESS = (5.0, 10.0, 20.0, 50.0, 100.0, 200.0)
#: Each LED's place searched (:func:`fit_led_places`): its height moved along the camera's
#: axis by these, metres (negative: towards the camera, under a pad's plate), and its
#: distance from the axis scaled by these.
PLACE_HEIGHTS_M = (0.0, -2e-3, -4e-3, -8e-3, -16e-3, -24e-3)
PLACE_RADII = (1.0, 1.25, 1.5, 2.0)
#: Every combination of the LEDs' candidates is tried where there are at most this many;
#: otherwise one LED moves at a time, from each candidate shared by all, for at most
#: PLACE_SWEEPS sweeps.
PLACE_EXHAUSTIVE = 20000
PLACE_SWEEPS = 4
#: Then each LED's place is refined off the grid: its height by these metres and its
#: distance's scale by these, halved each round.
PLACE_REFINE_STEPS = (1e-3, 0.125)
PLACE_REFINE_ROUNDS = 3
#: A refining move is kept where it lowers the loss by more than this share of the
#: change's energy (less is the renders' rounding).
PLACE_REFINE_GAIN = 1e-6


def _changes(spec: SensorSpec, ref_depth: np.ndarray, L: np.ndarray, profile: Profile, depths, layer,
             leds: list[dict], shininess: float, environment_coefficients: np.ndarray | None = None,
             ambient: float | None = None) -> np.ndarray:
    """(T, H, W, 3) the fast path's change per tap for the given LED constants and, where
    given, the environment's coefficients (``phong_reference.environment``). Without an
    environment, on no background (its ambient 0: a change above it does not clip); with
    one, on the profile's background (ambient 1: the environment's change may be
    negative), as the calibrated unit renders; ``ambient`` chooses."""
    if ambient is None:
        ambient = 0.0 if environment_coefficients is None else 1.0
    phong = {k: v for k, v in profile.phong.items() if k != "environment"}
    phong = {**phong, "ambient": ambient, "leds": leds, "shininess": shininess,
             **({} if environment_coefficients is None else {"environment": environment.entry(
                 environment_coefficients)})}
    renderer = ProfiledRenderer(spec, ref_depth, L, dataclasses.replace(profile, phong=phong), layer)
    return np.stack([renderer.render(d) - renderer.base for d in depths])


def _unit_terms(spec, ref_depth, L, profile, depths, layer, kind: str, shininess: float) -> np.ndarray:
    """(M, T, H, W) each LED's diffuse (``kind`` "k_d") or specular ("k_s") change alone,
    with a unit coefficient: three LEDs per render, each in its own colour channel."""
    M = len(spec.leds)
    out = np.zeros((M, len(depths)) + np.shape(ref_depth), np.float32)
    for first in range(0, M, 3):
        group = range(first, min(first + 3, M))
        leds = [{"k_d": float(kind == "k_d" and j in group), "k_s": float(kind == "k_s" and j in group),
                 "colour": [float(j - first == c) for c in range(3)] if j in group else [0.0, 0.0, 0.0]}
                for j in range(M)]
        change = _changes(spec, ref_depth, L, profile, depths, layer, leds, shininess)
        for j in group:
            out[j] = change[..., j - first]
    return out


def _environment_terms(spec, ref_depth, L, profile, depths, layer) -> np.ndarray:
    """(len(environment.TERMS), T, H, W, 3) each environment term's change alone
    (``phong_reference.environment``) per unit coefficient in every channel, the LEDs
    dark, through the whole profiled renderer (its alignment's move included)."""
    dark = [{"k_d": 0.0, "k_s": 0.0, "colour": [0.0, 0.0, 0.0]} for _ in spec.leds]
    K = len(environment.TERMS)
    out = np.zeros((K, len(depths)) + np.shape(ref_depth) + (3,), np.float32)
    for k in range(K):
        unit = np.zeros((K, 3), np.float32)
        unit[k] = ENVIRONMENT_PROBE  # small and on the background, so that neither sign clips
        out[k] = _changes(spec, ref_depth, L, profile, depths, layer, dark, spec.material.shininess, unit)
    return out / ENVIRONMENT_PROBE


def fit_terms(spec: SensorSpec, ref_depth: np.ndarray, L: np.ndarray, profile: Profile, depths, layer,
              real: np.ndarray, regions: np.ndarray, shininess=SHININESS,
              with_environment: bool = True) -> tuple[list[dict], float, float, np.ndarray | None]:
    """The LED constants that fit the changes ``real`` (T, H, W, 3) of taps ``depths`` (T,
    H, W) best over ``regions`` (T, H, W) (module doc): (the Phong model's LED constants,
    the shininess, the least squares' summed squared residual, the environment's
    coefficients (len(environment.TERMS), 3) or None), each channel's coefficients by
    non-negative least squares (an environment term's sign is free: it enters as itself
    and its negative), the best shininess of ``shininess``. ``with_environment``: fit the
    environment's terms (``phong_reference.environment``) beside the LEDs'."""
    best = None
    D = _unit_terms(spec, ref_depth, L, profile, depths, layer, "k_d", spec.material.shininess)
    E = _environment_terms(spec, ref_depth, L, profile, depths, layer)[:, regions] if with_environment else None
    M = len(spec.leds)
    for alpha in shininess:
        S = _unit_terms(spec, ref_depth, L, profile, depths, layer, "k_s", alpha)
        X = np.concatenate([D[:, regions], S[:, regions]]).T  # (N, 2M)
        coef, loss = np.zeros((2 * M, 3)), 0.0
        signed = None if E is None else np.zeros((len(E), 3))
        for c in range(3):
            if E is None:
                coef[:, c], res = optimize.nnls(X, real[regions][:, c])
            else:
                Ec = E[..., c].T  # (N, K)
                # a light ridge on the environment's terms: collinear ones (a frame lit evenly makes
                # each "lit" term its plain one's multiple) stay small instead of cancelling
                ridge = np.diag(np.sqrt(ENVIRONMENT_RIDGE * len(Ec) * np.mean(Ec * Ec, axis=0)) + 1e-12)
                A = np.concatenate([np.concatenate([X, Ec, -Ec], axis=1),
                                    np.concatenate([np.zeros((len(E), 2 * M)), ridge, -ridge], axis=1)])
                both, res = optimize.nnls(A, np.concatenate([real[regions][:, c], np.zeros(len(E))]))
                coef[:, c] = both[:2 * M]
                signed[:, c] = both[2 * M:2 * M + len(E)] - both[2 * M + len(E):]
            loss += res**2
        if best is None or loss < best[0]:
            best = (loss, alpha, coef, signed)
    loss, alpha, coef, signed = best
    return phong_form(coef[:M], coef[M:]), float(alpha), float(loss), signed


def phong_form(a: np.ndarray, b: np.ndarray) -> list[dict]:
    """(M, 3) diffuse and specular coefficients per channel -> the Phong model's LED
    constants [{k_d, k_s, colour}] (module doc)."""
    out = []
    for a_m, b_m in zip(np.asarray(a, np.float64), np.asarray(b, np.float64)):
        k_d = float(a_m.max())
        colour = a_m / k_d if k_d > 0 else (b_m / b_m.max() if b_m.max() > 0 else np.ones(3))
        k_s = float(max(np.dot(b_m, colour) / np.dot(colour, colour), 0.0))
        out.append({"k_d": max(k_d, 0.0), "k_s": k_s, "colour": [float(c) for c in np.clip(colour, 0.0, 1.0)]})
    return out


def _scores(pred: np.ndarray, real: np.ndarray, regions: np.ndarray) -> dict:
    """MAE and R^2 of the change per channel over the taps' contact regions."""
    p, y = pred[regions], real[regions]
    out = {"mae": {}, "change_r2": {}, "pixels": int(regions.sum())}
    for c, ch in enumerate("rgb"):
        total = float(np.sum((y[:, c] - y[:, c].mean()) ** 2))
        out["mae"][ch] = float(np.abs(p[:, c] - y[:, c]).mean()) if len(y) else float("nan")
        out["change_r2"][ch] = float(1 - np.sum((y[:, c] - p[:, c]) ** 2) / total) if total > 0 else float("nan")
    return out


def _changes_to_fit(spec: SensorSpec, profile: Profile, taps: RealTaps, background: np.ndarray, what: str):
    """(the taps' real changes (T, H, W, 3), their contact regions (T, H, W) within the
    unit's image circle, which taps are fitted (T,)); ValueError where no fitted tap shows
    a contact, naming ``what`` cannot be fitted."""
    real = taps.images - background
    regions = taps.regions(background, Camera.from_spec(profile.sensor_spec(spec)).mask)
    fitted = split(len(taps.ids))
    if not regions[fitted].any():
        raise ValueError(f"none of the fitted taps shows a contact in the real images: {what} cannot be fitted")
    return real, regions, fitted


def fit_led_constants(spec: SensorSpec, camera: Camera, ref_depth: np.ndarray, L: np.ndarray, profile: Profile,
                      taps: RealTaps, background: np.ndarray, layer: MembraneLayer | None = None,
                      shininess=SHININESS, with_environment: bool = True) -> tuple[dict, dict]:
    """The fast path's LED constants from a unit's taps (module doc).

    L : light vectors baked for ``profile.sensor_spec(spec)``'s LEDs; taps and background
    at ``camera``'s size. ``with_environment``: fit the environment's terms beside the
    LEDs' (``phong_reference.environment``). Returns (the profile's ``phong`` entries
    ``leds``, ``shininess`` and ``environment``, the report)."""
    background = np.asarray(background, np.float64)
    if background.shape != (camera.height, camera.width, 3) or taps.images.shape[1:] != background.shape:
        raise ValueError(f"taps and background must be {camera.width}x{camera.height} RGB, got "
                         f"{taps.images.shape[1:]} and {background.shape}")
    real, regions, fitted = _changes_to_fit(spec, profile, taps, background, "the fast path's LED constants")
    leds, alpha, _, env = fit_terms(spec, ref_depth, L, profile, taps.depths[fitted], layer, real[fitted],
                                    regions[fitted], shininess, with_environment)
    after = _changes(spec, ref_depth, L, profile, taps.depths, layer, leds, alpha, env)
    own = [{"k_d": led.k_d, "k_s": led.k_s, "colour": list(led.colour)} for led in spec.leds]
    before = _changes(spec, ref_depth, L, profile, taps.depths, layer, own, spec.material.shininess)
    held = ~fitted
    report = {
        "what": "the fast path's LED constants (k_d, k_s, colour per LED; shininess) fitted to the contact changes of "
                "the fitted taps, judged on the held-out ones",
        "shininess_searched": list(shininess), "shininess": alpha, "leds": leds,
        "fit": _scores(after[fitted], real[fitted], regions[fitted]),
        "heldout": _scores(after[held], real[held], regions[held]),
        "heldout_before": _scores(before[held], real[held], regions[held]),
    }
    if env is not None:
        report["environment"] = environment.entry(env)
    return {"leds": leds, "shininess": float(alpha), **({"environment": environment.entry(env)} if env is not None
                                                        else {})}, report


def _gram_nnls(G: np.ndarray, b: np.ndarray) -> np.ndarray:
    """argmin over x >= 0 of x'Gx - 2b'x, for a Gram matrix G = X'X and b = X'y (the
    non-negative least squares of y by X's columns, from their inner products alone)."""
    n = len(b)
    try:
        R = np.linalg.cholesky(G + 1e-12 * np.trace(G) / n * np.eye(n)).T  # G = R'R
    except np.linalg.LinAlgError:
        R = np.linalg.cholesky(G + 1e-9 * max(np.trace(G), 1.0) * np.eye(n)).T
    return optimize.nnls(R, np.linalg.solve(R.T, b))[0]


def moved_leds(leds, dz: float, scale: float) -> tuple:
    """``leds`` each moved ``dz`` metres along the camera's axis and its distance from the
    axis scaled by ``scale`` (its azimuth kept)."""
    return tuple(dataclasses.replace(led, position=(led.position[0] * scale, led.position[1] * scale,
                                                    led.position[2] + dz)) for led in leds)


def fit_led_places(spec: SensorSpec, mesh, camera: Camera, profile: Profile, taps: RealTaps, background: np.ndarray,
                   field: str = "linear", layer: MembraneLayer | None = None) -> tuple[tuple, dict]:
    """Each LED's place for a field whose light leaves it (module doc): (the places, (M, 3)
    metres in the camera frame of ``profile.sensor_spec(spec)``'s LEDs, and the report).

    Every candidate (PLACE_HEIGHTS_M x PLACE_RADII about the unit's place) is baked for
    all LEDs at once (not cached) and its diffuse and specular terms rendered at the
    spec's shininess; then, from the unit's places, one LED at a time moves to the
    candidate whose terms, with the others', fit the fitted taps' changes best, until a
    sweep moves none (at most PLACE_SWEEPS).
    """
    from .bake import bake
    from .render import light_vectors

    unit = profile.sensor_spec(spec)
    real, regions, fitted = _changes_to_fit(spec, profile, taps, np.asarray(background, np.float64),
                                            "the LEDs' places")
    alpha = spec.material.shininess
    candidates = [(dz, r) for dz in PLACE_HEIGHTS_M for r in PLACE_RADII]
    sub = taps.subset(fitted)
    region, change = regions[fitted], real[fitted]
    columns, places = [], []  # per candidate, (M, 2, N): each LED's diffuse and specular term over the regions
    for dz, r in candidates:
        leds = moved_leds(unit.leds, dz, r)
        L = light_vectors(bake(mesh, camera, leds, field, use_cache=False))
        D = _unit_terms(spec, taps.ref_depth, L, profile, sub.depths, layer, "k_d", alpha)
        S = _unit_terms(spec, taps.ref_depth, L, profile, sub.depths, layer, "k_s", alpha)
        columns.append(np.stack([D[:, region], S[:, region]], axis=1).astype(np.float64))
        places.append(np.array([led.position for led in leds]))
    M, K = len(unit.leds), len(candidates)
    # Every term's inner products, once: a trial's least squares is then a 2M x 2M problem.
    flat = np.concatenate(columns).reshape(K * M * 2, -1)  # row (k, m, kind)
    y = change[region]  # (N, 3)
    gram, cross, energy = flat @ flat.T, flat @ y, (y * y).sum(axis=0)

    def loss(choice) -> float:
        rows = np.array([(k * M + m) * 2 + kind for kind in (0, 1) for m, k in enumerate(choice)])
        G, b = gram[np.ix_(rows, rows)], cross[rows]
        total = 0.0
        for c in range(3):
            x = _gram_nnls(G, b[:, c])
            total += float(energy[c] - 2 * x @ b[:, c] + x @ G @ x)
        return total

    start = loss([0] * M)
    sweeps = 0
    if K**M <= PLACE_EXHAUSTIVE:
        import itertools

        choice = list(min(itertools.product(range(K), repeat=M), key=loss))
    else:
        choice = None
        for first in range(K):
            trial_choice, value = [first] * M, loss([first] * M)
            for sweeps in range(1, PLACE_SWEEPS + 1):
                moved = False
                for m in range(M):
                    for k in range(K):
                        trial = trial_choice[:m] + [k] + trial_choice[m + 1:]
                        v = loss(trial)
                        if v < value - 1e-12:
                            value, trial_choice, moved = v, trial, True
                if not moved:
                    break
            if choice is None or value < loss(choice):
                choice = trial_choice
    grid_loss = best = loss(choice)
    # Refined off the grid: each LED's height and distance moved by half the grid's finest
    # steps, then by half that, one LED at a time, a move kept where it lowers the loss.
    offsets = [[candidates[k][0], candidates[k][1]] for k in choice]
    chosen = {m: (columns[k][m], places[k][m]) for m, k in enumerate(choice)}

    def refined_loss(cols) -> float:
        X = np.concatenate([np.stack([cols[m][0] for m in range(M)]), np.stack([cols[m][1] for m in range(M)])]).T
        return float(sum(optimize.nnls(X, y[:, c])[1] ** 2 for c in range(3)))

    best = refined_loss({m: chosen[m][0] for m in range(M)})
    dz, dr = PLACE_REFINE_STEPS
    for _ in range(PLACE_REFINE_ROUNDS):
        moves = [(dz, 0.0), (-dz, 0.0), (0.0, dr), (0.0, -dr)]
        trial_cols, trial_places = [], []
        for mz, mr in moves:  # every LED moved the same way in one bake: each LED's terms are its own
            leds = tuple(moved_leds((led,), offsets[m][0] + mz, offsets[m][1] + mr)[0]
                         for m, led in enumerate(unit.leds))
            L = light_vectors(bake(mesh, camera, leds, field, use_cache=False))
            D = _unit_terms(spec, taps.ref_depth, L, profile, sub.depths, layer, "k_d", alpha)
            S = _unit_terms(spec, taps.ref_depth, L, profile, sub.depths, layer, "k_s", alpha)
            trial_cols.append(np.stack([D[:, region], S[:, region]], axis=1).astype(np.float64))
            trial_places.append(np.array([led.position for led in leds]))
        for m in range(M):
            for j, (mz, mr) in enumerate(moves):
                if offsets[m][1] + mr <= 0:
                    continue
                cols = {i: chosen[i][0] for i in range(M)}
                cols[m] = trial_cols[j][m]
                value = refined_loss(cols)
                if value < best - PLACE_REFINE_GAIN * float(energy.sum()):  # more than rounding
                    best, chosen[m] = value, (trial_cols[j][m], trial_places[j][m])
                    offsets[m] = [offsets[m][0] + mz, offsets[m][1] + mr]
        dz, dr = dz / 2, dr / 2
    positions = tuple(tuple(float(v) for v in chosen[m][1]) for m in range(M))
    report = {
        "what": "each LED's place for the field whose light leaves it, searched on the fitted taps: its height moved "
                f"by {[d * 1e3 for d in PLACE_HEIGHTS_M]} mm along the camera's axis and its distance from the axis "
                f"scaled by {list(PLACE_RADII)}, one LED at a time",
        "field": field, "shininess_searched_at": alpha,
        "search": "every combination" if K**M <= PLACE_EXHAUSTIVE else f"one LED at a time from each of {K} starts",
        "fit_loss": {"at_the_units_places": start, "on_the_grid": grid_loss, "at_the_places_found": best},
        "places_m": [list(p) for p in positions],
        "moved": [{"led": led.name, "height_mm": offsets[m][0] * 1e3, "radius_scale": offsets[m][1],
                   "grid_height_mm": candidates[k][0] * 1e3, "grid_radius_scale": candidates[k][1],
                   "on_the_grid_edge": candidates[k][0] == PLACE_HEIGHTS_M[-1] or candidates[k][1] == PLACE_RADII[-1]}
                  for m, (led, k) in enumerate(zip(unit.leds, choice))],
        "sweeps": sweeps,
    }
    return positions, report
