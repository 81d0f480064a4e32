"""Fit where the reference's light enters, its aim and its beam to a real unit's no-contact image.

The LEDs' layout (``scenes.layout``: per LED its entry, place, aim and beam, bounded by
the unit's housing) sets how evenly and from where the membrane is lit, which no gain,
offset or response of the camera fitted afterwards can change. Here it is searched
against the real no-contact frame and the training presses' contact regions, through the
calibration's own image model (``pbr_tactile.image_model``, the camera held where
``known_alignment`` says; the presses as ``pbr_tactile.calibrate_taps`` fits them, the
LEDs turned as one ring) on the even angular sectors, at a small film and photon count.
Each source's transport is independent of the others' places, so any LED's images (its
no-contact image and its presses') can be swapped between renders of different layouts:

1. every start (the spec's layout; the glass' edge; the fast path's calibrated places
   carried over as LEDs under the glass; a coarse grid under the glass: ``starts``) is
   rendered without contact and fitted; the physical starts and the grid's SCREENED best
   also render the presses and are fitted with them, the presses weighing PRESS_SHARE of
   the loss;
2. LED by LED, each takes whichever of those starts' images lowers the fitted loss (less
   the basis' own Monte Carlo noise, ``image_fit.debiased``) by more than MIN_GAIN;
3. a pattern search then moves one parameter at a time (``scenes.layout.FREE``), every
   LED's by +step in one render and by -step in another; each LED in turn takes the move
   that lowers the loss, and a parameter that moves no LED has its step halved, down to
   its smallest.

Why a search and not Dr.Jit's derivatives: the light pass (``pbr_tactile.photons``)
deposits photons on the coating through scatter-adds behind a weight window that splits
and roulettes them, and an emitter's place moves which faces its photons reach
(visibility): a derivative through it needs the boundary terms of a moving emitter and
a differentiable window, which the estimator does not have. A render costs 3 s at the
search's film, so a few dozen are affordable; a search seeded from two physical layouts
is the alternative the issue names.
"""

from __future__ import annotations

import dataclasses
import math
import time
from dataclasses import dataclass

import numpy as np

from scenes.camera import Camera
from scenes.body import sensor_body
from scenes.captures import MIN_REGION, split
from scenes.images import block_mean
from scenes.layout import FREE, PARAMETERS, LEDLayout, layout_bounds, layout_of, tube_frame, with_layout
from scenes.spec import SensorSpec

from .basis import emitter_basis
from .calibrate_taps import film_views
from .effects import Effects
from .image_fit import ImageFitter, debiased
from .image_model import ImageModel
from .real_image import check_real, film_factor, film_sectors, image_circle

#: The search's film (px) and photons per LED: a render in about 3 s on 2 cores.
SEARCH_FILM = (80, 60)
SEARCH_PHOTONS = 1 << 16
SEARCH_SPP = 16
#: Each parameter's first step and smallest step (PARAMETERS' units: m, m, rad, rad).
STEPS = {"radius_m": (3e-3, 0.5e-3), "height_m": (3e-3, 0.5e-3), "aim_rad": (0.3, 0.05),
         "beam_half_angle_rad": (0.3, 0.05)}
#: A move is kept when it lowers the debiased loss by more than this share.
MIN_GAIN = 0.01
#: Starts of the coarse grid whose presses are rendered and fitted, the best by the
#: no-contact fit (the physical starts' always are).
SCREENED = 3
#: Training presses the search fits (the fitted half's, spread over it).
SEARCH_TAPS = 3
#: The presses' share of the search's loss, the frame's training pixels the rest. Each
#: pixel alike, three presses' contact regions were a few percent of the loss at 80x60,
#: and the search chose LEDs under the plate that fit the frame and halved the contacts.
#: At an equal share, on the public GelSight's presses, the spec's LEDs beside the pad
#: and the search's mixed layout are within 3 % of each other less their noise (0.00640
#: and 0.00619), LEDs under the plate alone further (0.00674); before the noise is taken
#: off, the spec's scored best (0.00666 against 0.00711 and 0.00753).
PRESS_SHARE = 0.5
#: Presses that pin a layout: at least this many on the fitted half, their contacts'
#: centres spread over at least this share of the frame's height (presses in one place
#: see each LED from one side only).
MIN_PRESSES = 2
MIN_PRESS_SPREAD = 0.25
#: Passes over the parameters at most. On the public GelSight's presses (3 of them in the
#: loss) four passes moved one LED's aim once, in the first, in 139 renders and 22
#: minutes on a shared 2-core machine: the starts and their combination carry the fit.
ROUNDS = 1
#: The paint and the elastomer's clarity, fitted with the layout where presses are given
#: (``pbr_tactile.effects.Effects`` names): each one's search bounds, first step and
#: smallest step. The roughness stays at 0.1 or more: a narrower lobe is not resolved by
#: the search's photons. On the public GelSight's presses at the spec's LEDs (80x60, 3
#: presses), gloss 0 / 0.3 / 0.5 / 0.8 (roughness 0.3; 0.15 for 0.8) gave a loss of
#: 0.0064 / 0.0059 / 0.0063 / 0.034 and contacts 0.62 / 0.68 / 0.74 / 1.09 of the real's:
#: the paint sets how strongly a dent shades, which no gain of the image model can.
MATERIAL = {"coating_gloss": (0.0, 1.0, 0.2, 0.05), "coating_roughness": (0.1, 0.6, 0.1, 0.025),
            "scattering_per_m": (0.0, 250.0, 40.0, 10.0)}
#: What the fit holds at the record, and why.
MATERIAL_HELD = {"coating_albedo": "it scales every LED's light alike, as the image model's gains do: "
                                   "the images cannot tell it from the LEDs' powers",
                 "absorption_per_m": "held at the calibration grid's point: of the clarity the search fits "
                                     "the scattering, which spreads the light that shades a dent; the "
                                     "absorption dims light as it crosses the pad, as the LEDs' places do"}
#: Passes over the material's parameters at most.
MATERIAL_ROUNDS = 2


@dataclass
class LayoutFit:
    """What ``fit_layout`` found: the layout, the spec laid out by it, the start it came
    from, the report (JSON-able: every start's and step's loss, renders, seconds) and the
    effects it was fitted with (the paint and clarity fitted where presses were given:
    MATERIAL)."""

    layout: tuple[LEDLayout, ...]
    spec: SensorSpec
    start: str
    report: dict
    effects: Effects | None = None


def fast_path_layout(spec: SensorSpec, places_m, beam_half_angle_rad: float = math.radians(60.0)
                     ) -> tuple[LEDLayout, ...]:
    """The fast path's calibrated LED places (camera frame, m; its profile report's
    ``fast_path.taps.places.places_m``) as LEDs under the glass, each aimed at the
    membrane's apex with a ``beam_half_angle_rad`` beam, moved into their bounds
    (``scenes.layout.layout_bounds``: a place above the glass' lowest point goes down to it)."""
    layout = []
    tube = tube_frame(spec, np.asarray(sensor_body(spec).membrane.vertices))
    apex = float(tube[np.argmin(np.hypot(tube[:, 0], tube[:, 1])), 2])
    bounds = layout_bounds(spec, "under")
    for p in tube_frame(spec, places_m):
        radius = float(np.clip(math.hypot(p[0], p[1]), *bounds["radius_m"][:2]))
        height = float(np.clip(p[2], *bounds["height_m"][:2]))
        aim = math.atan2(radius, apex - height)
        layout.append(LEDLayout("under", math.atan2(p[1], p[0]), radius, height, aim, beam_half_angle_rad))
    return tuple(layout)


def starts(spec: SensorSpec, fast_places_m=None, coarse: bool = True) -> dict[str, tuple[LEDLayout, ...]]:
    """The search's starts: ``spec`` (its own layout), ``edge`` (each LED's light into the
    glass' edge at its azimuth, aimed across, Lambertian), given the fast path's
    calibrated places ``fast_path`` (``fast_path_layout``), and with ``coarse`` a coarse
    grid of LEDs under the glass across the housing (``under_grid``)."""
    own = layout_of(spec)
    out = {"spec": own,
           "edge": tuple(dataclasses.replace(p, entry="edge", aim_rad=math.pi / 2, beam_half_angle_rad=None)
                         for p in own)}
    if fast_places_m is not None:
        out["fast_path"] = fast_path_layout(spec, fast_places_m)
    if coarse:
        out.update(under_grid(spec, own))
    return out


#: The coarse grid of LEDs under the glass (``under_grid``): distances from the axis as
#: shares of the glass' reach (its base loop's mean radius), aims (rad) and beams (rad).
UNDER_RADII = (0.35, 0.65, 0.95)
UNDER_AIMS = (0.0, math.radians(35.0))
UNDER_BEAMS = (math.radians(30.0), math.radians(60.0))


def under_grid(spec: SensorSpec, own) -> dict[str, tuple[LEDLayout, ...]]:
    """Starts with every LED under the glass at its own azimuth, CLEARANCE_M under the
    glass' lowest point (or the housing's floor), at each of UNDER_RADII x UNDER_AIMS x
    UNDER_BEAMS, named ``under_r<share>_a<deg>_b<deg>``."""
    body = sensor_body(spec)
    loop = tube_frame(spec, np.asarray(body.membrane.vertices)[body.base_loop])
    reach = float(np.hypot(loop[:, 0], loop[:, 1]).mean())
    bounds = layout_bounds(spec, "under")
    height = bounds["height_m"][1]
    out = {}
    for share in UNDER_RADII:
        radius = float(np.clip(share * reach, *bounds["radius_m"][:2]))
        for aim in UNDER_AIMS:
            for beam in UNDER_BEAMS:
                name = f"under_r{share:g}_a{math.degrees(aim):.0f}_b{math.degrees(beam):.0f}"
                out[name] = tuple(LEDLayout("under", p.azimuth_rad, radius, height, aim, beam) for p in own)
    return out


def press_centres(taps) -> np.ndarray:
    """(T, 2) each press's centre (u, v) px: where its depth map sinks deepest under the
    no-contact one."""
    sunk = np.asarray(taps.ref_depth, np.float64)[None] - np.asarray(taps.depths, np.float64)
    v, u = np.unravel_index(np.argmax(sunk.reshape(len(sunk), -1), axis=1), sunk.shape[1:])
    return np.stack([u, v], axis=1).astype(np.float64)


def _farthest(points: np.ndarray, count: int) -> np.ndarray:
    """Indices of ``count`` of ``points`` (N, 2) spread as far apart as a greedy
    farthest-point pick from the first makes them, in their order."""
    pick = [0]
    while len(pick) < min(count, len(points)):
        gap = np.min(np.linalg.norm(points[:, None] - points[pick][None], axis=-1), axis=1)
        pick.append(int(np.argmax(gap)))
    return np.array(sorted(pick))


def presses_pin(taps, camera: Camera) -> tuple[bool, str]:
    """Whether the fitted half of ``taps`` (``scenes.captures.RealTaps``; None: no presses)
    can pin a layout (MIN_PRESSES, MIN_PRESS_SPREAD), and why (one line)."""
    if taps is None:
        return False, "no presses: a layout needs presses to pin it"
    fitted = np.flatnonzero(split(len(taps.ids)))
    if len(fitted) < MIN_PRESSES:
        return False, f"{len(fitted)} fitted press(es), fewer than {MIN_PRESSES}"
    centres = press_centres(taps)[fitted]
    spread = float(np.max(np.linalg.norm(centres[:, None] - centres[None], axis=-1)))
    if spread < MIN_PRESS_SPREAD * camera.height:
        return False, (f"the {len(fitted)} fitted presses lie within {spread:.0f} px of each other, under "
                       f"{MIN_PRESS_SPREAD:g} of the frame's {camera.height} px: all in one place")
    return True, f"{len(fitted)} fitted presses spread over {spread:.0f} px"


class _Scorer:
    """The fitted loss (less the basis' noise) of a candidate's renders: its no-contact
    basis against the real image's training sectors, and with its presses' renders their
    changes against the real presses' contact regions too (``calibrate_taps``)."""

    def __init__(self, real, camera: Camera, film, known_alignment: bool, leak: bool, taps=None,
                 spectral_gains: bool = False, webcam: bool = False):
        self.film = film
        self.camera = camera
        self.circle = image_circle(real)
        self.r = block_mean(real, film_factor(real.shape, film))
        self.sector = film_sectors(camera, self.circle, film)
        self.known = known_alignment
        self.leak = leak
        self.taps = taps
        self.spectral = spectral_gains
        self.webcam = webcam
        self.fits = 0

    def __call__(self, candidate: dict) -> tuple[float, object]:
        basis = candidate["basis"]
        model = ImageModel(basis["mean"], basis["names"], self.camera, self.circle, known_alignment=self.known,
                           lens=False, response=basis["response"] if self.spectral else None, webcam=self.webcam)
        train = (self.sector % 2 == 0) & model.inside
        fit = ImageFitter(model, self.r, train, leak=self.leak).search()
        views = []
        if candidate.get("taps") is not None and self.taps is not None:
            changes = {"change": np.stack([t["mean"] - basis["mean"] for t in candidate["taps"]]), "slope": None,
                       "curve": None}
            views = [v for v in film_views(self.taps, changes, self.r, model.inside, self.film)
                     if v.pixels.sum() >= MIN_REGION]
            # the presses weigh as much together as the frame's training pixels (PRESS_SHARE)
            views = [dataclasses.replace(v, weight=PRESS_SHARE / (1 - PRESS_SHARE) * float(train.sum())
                                         / (len(views) * float(v.pixels.sum()))) for v in views]
            if views:
                fit = ImageFitter(model, self.r, train, leak=self.leak, taps=views, common_turn=True).fit(fit.nl)
        # the basis' own noise in the loss, weighted as the loss weighs the frame and the
        # presses (``image_fit.debiased`` of each, the no-contact basis' standing for a tap's)
        noise = debiased(fit, model, basis, [train]).noise
        if views:
            pressed = float(np.mean([debiased(fit, model, basis, [v.pixels]).noise for v in views]))
            noise = (1 - PRESS_SHARE) * noise + PRESS_SHARE * pressed
        fit = dataclasses.replace(fit, noise=noise)
        self.fits += 1
        return fit.loss - fit.noise, fit


def _swap(candidate: dict, other: dict, led: int) -> dict:
    """``candidate``'s renders (its no-contact ``basis`` and its presses' ``taps``) with LED
    ``led``'s sources (``led<m>``, ``led<m>_leak``) taken from ``other``'s."""
    names = [str(n) for n in candidate["basis"]["names"]]
    if names != [str(n) for n in other["basis"]["names"]]:
        raise ValueError("fit_layout: renders of one sensor must have the same sources")
    take = np.array([n == f"led{led}" or n == f"led{led}_leak" for n in names])

    def swapped(a: dict, b: dict) -> dict:
        return {**a, "mean": np.where(take, b["mean"], a["mean"]), "variance": np.where(take, b["variance"],
                                                                                          a["variance"])}

    out = {"basis": swapped(candidate["basis"], other["basis"])}
    if candidate.get("taps") is not None:
        out["taps"] = [swapped(a, b) for a, b in zip(candidate["taps"], other["taps"])]
    return out


def fit_layout(real: np.ndarray, spec: SensorSpec, mesh, camera: Camera, effects: Effects,
               fast_places_m=None, taps=None, film: tuple[int, int] = SEARCH_FILM, photons: int = SEARCH_PHOTONS,
               spp: int = SEARCH_SPP, passes: int = 2, seed: int = 0, known_alignment: bool = True,
               leak: bool = True, rounds: int = ROUNDS, screened: int = SCREENED, use_cache: bool = True,
               progress=None, only: tuple[str, ...] | None = None, coarse: bool = True,
               spectral_gains: bool = False, webcam: bool = False, material: bool = True) -> LayoutFit:
    """The LEDs' layout that best explains the real no-contact image (H, W, 3) in [0, 1]
    and the presses ``taps`` (``scenes.captures.RealTaps``: SEARCH_TAPS of its fitted half,
    ``scenes.captures.split``, spread as far apart in the image as they go, are rendered;
    None: the image alone), module doc.
    ``effects``: the reference's (with the leak sources the image model fits,
    ``basis.BASIS_EFFECTS``); ``fast_places_m``: (L, 3) the fast path's calibrated LED
    places, a start; ``only``: the starts to try (names of ``starts``), default all;
    ``coarse``: with the grid under the glass; ``spectral_gains``: the image model's gains
    through each LED's film response (``pbr_tactile.image_model``); ``webcam``: the
    camera's response held to a webcam's; ``material``: with presses, the paint and the
    elastomer's clarity (MATERIAL) fitted too (``_material_search``), after the starts'
    combination, which is then made again in the fitted paint; ``progress``: called with a
    line of text per step."""
    real = check_real(real, camera, "the real no-contact image")
    t0 = time.perf_counter()
    chosen_taps = None
    if taps is not None:
        fitted = np.flatnonzero(split(len(taps.ids)))
        chosen_taps = taps.subset(fitted[_farthest(press_centres(taps)[fitted], SEARCH_TAPS)])
    score = _Scorer(real, camera, film, known_alignment, leak, chosen_taps, spectral_gains, webcam)
    renders = 0

    looks = effects  # the paint and clarity the renders use: the record's until fitted

    def render(layout, with_taps: bool = True, effects: Effects | None = None) -> dict:
        nonlocal renders
        laid = with_layout(spec, layout)
        effects = looks if effects is None else effects
        out = {"basis": emitter_basis(laid, mesh, camera, effects, film, photons, spp, passes, seed, use_cache)}
        renders += 1
        if with_taps and chosen_taps is not None:
            out["taps"] = [emitter_basis(laid, mesh, camera, effects, film, photons, spp, passes, seed, use_cache,
                                         depth=depth, ref_depth=chosen_taps.ref_depth) for depth in chosen_taps.depths]
            renders += len(chosen_taps.depths)
        return out

    def say(text):
        if progress is not None:
            progress(text)

    tried = starts(spec, fast_places_m, coarse=coarse)
    if only is not None:
        unknown = sorted(set(only) - set(tried))
        if unknown:
            raise ValueError(f"fit_layout: no start named {', '.join(unknown)} (have {', '.join(tried)})")
        tried = {k: v for k, v in tried.items() if k in only}
    report = {"starts": {}, "steps": [], "film": list(film), "photons": photons, "seed": seed,
              "presses": [] if chosen_taps is None else list(chosen_taps.ids),
              "method": "a search from physical starts (module doc of pbr_tactile.layout_fit), not Dr.Jit's "
                        "derivatives: the light pass has none with respect to an emitter's place"}
    renders_of = {}
    for name, layout in tried.items():
        renders_of[name] = (list(layout), render(layout, with_taps=False))
        loss, _ = score(renders_of[name][1])
        report["starts"][name] = {"image_loss": loss, "layout": [dataclasses.asdict(p) for p in layout]}
        say(f"start {name}: loss {loss:.6g} (no-contact image)")
    # the physical starts always, the grid's best by the image: light that enters beside the
    # pad or by the plate's edge reaches the paint at grazing angles and shades a dent more
    # than light from under it, which the no-contact image alone does not see
    physical = [name for name in ("spec", "edge", "fast_path") if name in renders_of]
    grid = [name for name in sorted(renders_of, key=lambda name: report["starts"][name]["image_loss"])
            if name not in physical]
    kept = physical + grid[:max(1, screened)]
    renders_of = {name: renders_of[name] for name in kept}
    for name in kept:
        if chosen_taps is not None:
            renders_of[name] = (renders_of[name][0], render(renders_of[name][0]))
        report["starts"][name]["loss"] = score(renders_of[name][1])[0]
        say(f"start {name}: loss {report['starts'][name]['loss']:.6g}" + (" with the presses" if chosen_taps else ""))
    start = min(kept, key=lambda name: report["starts"][name]["loss"])
    loss, layout, candidate, chosen = _combine(renders_of, start, report["starts"][start]["loss"], score, say)
    report["combined"] = {"loss": loss, "from": [chosen[m] for m in range(len(layout))]}
    if material and chosen_taps is not None:
        record = {name: getattr(effects, name) for name in MATERIAL}
        loss, looks, candidate, material_steps = _material_search(effects, layout, candidate, loss, score, render,
                                                                  MATERIAL_ROUNDS, say)
        if looks != effects:
            # the kept starts again in the fitted paint, and LED by LED the best of them
            for name in kept:
                renders_of[name] = (renders_of[name][0], render(renders_of[name][0]))
            again = {name: score(renders_of[name][1])[0] for name in kept}
            best = min(again, key=again.get)
            recombined = _combine(renders_of, best, again[best], score, say)
            if recombined[0] < loss:
                loss, layout, candidate, chosen = recombined
            report["combined_again"] = {"starts": again, "loss": loss,
                                        "from": [chosen[m] for m in range(len(layout))]}
        report["material"] = {"fitted": {name: getattr(looks, name) for name in MATERIAL}, "record": record,
                              "steps": material_steps, "held": MATERIAL_HELD,
                              "intervals": material_intervals(material_steps)}
    else:
        report["material"] = {"fitted": {}, "held": {**{name: "no presses: the no-contact frame alone does not pin "
                                                          "how strongly a dent shades" for name in MATERIAL},
                                                     **MATERIAL_HELD}}
    loss, layout, steps = _search(spec, layout, candidate, loss, score, render, rounds, say)
    report["steps"] = steps
    report["intervals"] = layout_intervals(spec, layout, steps, loss)
    layout = tuple(layout)
    report.update({"start": start, "loss": loss, "layout": [dataclasses.asdict(p) for p in layout],
                   "renders": renders, "fits": score.fits, "seconds": time.perf_counter() - t0})
    return LayoutFit(layout, with_layout(spec, layout), start, report, looks)


def _search(spec: SensorSpec, layout: list, candidate: dict, loss: float, score, render, rounds: int, say):
    """The pattern search of the module doc from ``layout`` (its renders ``candidate``,
    its ``loss``): (the loss, the layout, the steps' records)."""
    steps = {name: STEPS[name][0] for name in PARAMETERS}
    records = []
    for round_ in range(rounds):
        moved_any = False
        for name in PARAMETERS:
            movable = [m for m, p in enumerate(layout) if name in FREE[p.entry]]
            if not movable or steps[name] < STEPS[name][1]:
                continue
            k = PARAMETERS.index(name)
            trials = {}
            for sign in (1.0, -1.0):
                trial = []
                for p in layout:
                    v = p.vector()
                    low, high, _ = layout_bounds(spec, p.entry)[name]
                    v[k] = float(np.clip(v[k] + sign * steps[name], low, high))
                    trial.append(p.with_vector(v))
                trials[sign] = (trial, render(trial))
            moved, tried = [], {}
            for m in movable:
                tried[m] = {"from": float(layout[m].vector()[k]), "loss": loss, "trials": []}
                for sign, (trial, other) in trials.items():
                    if np.allclose(trial[m].vector(), layout[m].vector()):
                        continue
                    swapped = _swap(candidate, other, m)
                    value, _ = score(swapped)
                    tried[m]["trials"].append({"value": float(trial[m].vector()[k]), "loss": value})
                    if value < loss - MIN_GAIN * abs(loss):
                        loss, candidate = value, swapped
                        layout[m] = trial[m]
                        moved.append((m, sign))
                        break
            records.append({"round": round_, "parameter": name, "step": steps[name], "loss": loss,
                            "moved": [{"led": spec.leds[m].name, "by": sign * steps[name]} for m, sign in moved],
                            "leds": {spec.leds[m].name: t for m, t in tried.items()}})
            say(f"round {round_} {name} step {steps[name]:.4g}: loss {loss:.6g}, moved {len(moved)} LEDs")
            if moved:
                moved_any = True
            else:
                steps[name] /= 2
        if not moved_any and all(steps[n] < STEPS[n][1] for n in PARAMETERS if any(n in FREE[p.entry] for p in layout)):
            break
    return loss, layout, records


def _material_search(effects: Effects, layout, candidate: dict, loss: float, score, render, rounds: int, say):
    """The pattern search of the paint and clarity (MATERIAL) at ``layout`` (its renders
    ``candidate`` in ``effects``, its ``loss``): each parameter in turn is rendered at
    +step and -step (within its bounds); the better is kept where it lowers the loss by
    more than MIN_GAIN, else the step is halved, down to its smallest. Returns (the loss,
    the effects, their renders, the steps' records)."""
    steps = {name: first for name, (_, _, first, _) in MATERIAL.items()}
    records = []
    for round_ in range(rounds):
        moved_any = False
        for name, (low, high, _, smallest) in MATERIAL.items():
            if steps[name] < smallest:
                continue
            here = float(getattr(effects, name))
            trials = []
            for sign in (1.0, -1.0):
                value = float(np.clip(here + sign * steps[name], low, high))
                if math.isclose(value, here):
                    continue
                trial = dataclasses.replace(effects, **{name: value})
                rendered = render(layout, effects=trial)
                trials.append((score(rendered)[0], value, trial, rendered))
            records.append({"round": round_, "parameter": name, "step": steps[name], "from": here, "loss": loss,
                            "trials": [{"value": value, "loss": value_loss} for value_loss, value, _, _ in trials]})
            best = min(trials, key=lambda t: t[0], default=None)
            if best is not None and best[0] < loss - MIN_GAIN * abs(loss):
                loss, _, effects, candidate = best
                moved_any = True
            else:
                steps[name] /= 2
            records[-1]["to"] = float(getattr(effects, name))
            say(f"material round {round_} {name} step {records[-1]['step']:.4g}: loss {loss:.6g}, "
                f"{name} {records[-1]['to']:.4g}")
        if not moved_any and all(steps[n] < MATERIAL[n][3] for n in MATERIAL):
            break
    return loss, effects, candidate, records


def resolution(value: float, loss: float, trials: list[dict], bounds: tuple[float, float],
               tolerance: float) -> dict:
    """The range of a parameter at ``value`` (its ``loss``) within which a parabola through
    its ``trials`` ({"value", "loss"} either side; one side: the parabola's vertex at
    ``value``, as at a bound) rises by less than ``tolerance``: the values the fit cannot
    tell apart. ``identified``: the loss curves up and the range is within ``bounds`` and
    under half their span. Returns {"value", "low", "high", "identified"}."""
    low, high = bounds
    out = {"value": value, "low": low, "high": high, "identified": False}
    sides = {math.copysign(1.0, t["value"] - value): t for t in trials if not math.isclose(t["value"], value)}
    if not sides:
        return out
    if len(sides) == 2:
        (a, la), (b, lb) = [(abs(sides[s]["value"] - value), sides[s]["loss"] - loss) for s in (-1.0, 1.0)]
        # the parabola through (-a, la), (0, 0), (b, lb): its second derivative
        curvature = 2.0 * (la * b + lb * a) / (a * b * (a + b))
    else:
        (t,) = sides.values()
        curvature = 2.0 * (t["loss"] - loss) / (t["value"] - value) ** 2
    if curvature <= 0:
        return out
    half = math.sqrt(2.0 * tolerance / curvature)
    out.update(low=max(low, value - half), high=min(high, value + half))
    out["identified"] = bool(out["high"] - out["low"] < 0.5 * (high - low)
                             and (out["low"] > low or out["high"] < high))
    return out


def material_intervals(records: list[dict]) -> dict:
    """Each material parameter's ``resolution`` from its last step's trials, the loss and
    tolerance (MIN_GAIN of it: the search's own) those of that step. A parameter moved at
    its last step has no trials around its value: it is reported unidentified."""
    out = {}
    for name, r in {r["parameter"]: r for r in records}.items():
        bounds = MATERIAL[name][:2]
        if not math.isclose(r["to"], r["from"]):
            out[name] = {"value": r["to"], "low": bounds[0], "high": bounds[1], "identified": False}
            continue
        out[name] = resolution(r["from"], r["loss"], r["trials"], bounds, MIN_GAIN * abs(r["loss"]))
    return out


def layout_intervals(spec: SensorSpec, layout, records: list[dict], loss: float) -> dict:
    """Each LED's free parameters' ``resolution`` (``{led: {parameter: ...}}``) from the
    last step at which that LED did not move (its trials either side; MIN_GAIN of
    ``loss`` the tolerance). A parameter moved at its last step has no trials around its
    value: it is reported unidentified."""
    out = {}
    for m, p in enumerate(layout):
        led = spec.leds[m].name
        bounds = layout_bounds(spec, p.entry)
        out[led] = {}
        for name in FREE[p.entry]:
            mine = [r for r in records if r["parameter"] == name and led in r.get("leds", {})]
            value = float(p.vector()[PARAMETERS.index(name)])
            if not mine or not math.isclose(mine[-1]["leds"][led]["from"], value):
                out[led][name] = {"value": value, "low": bounds[name][0], "high": bounds[name][1],
                                  "identified": False}
                continue
            last = mine[-1]["leds"][led]
            out[led][name] = resolution(value, last["loss"], last["trials"], bounds[name][:2], MIN_GAIN * abs(loss))
    return out


def _combine(renders_of: dict, start: str, loss: float, score, say, sweeps: int = 2):
    """Each LED's images from whichever start's renders fit best with the others' (module
    doc: sources are independent), LED by LED from ``start``'s, ``sweeps`` times over the
    LEDs: (the loss, the layout, the renders, each LED's start's name)."""
    layout, candidate = list(renders_of[start][0]), renders_of[start][1]
    chosen = {m: start for m in range(len(layout))}
    for sweep in range(sweeps):
        changed = False
        for m in range(len(layout)):
            for name, (other_layout, other) in renders_of.items():
                if name == chosen[m]:
                    continue
                swapped = _swap(candidate, other, m)
                value, _ = score(swapped)
                if value < loss - MIN_GAIN * abs(loss):
                    loss, candidate, layout[m], chosen[m], changed = value, swapped, other_layout[m], name, True
        say(f"combined, sweep {sweep}: loss {loss:.6g} ({', '.join(chosen[m] for m in range(len(layout)))})")
        if not changed:
            break
    return loss, layout, candidate, chosen
