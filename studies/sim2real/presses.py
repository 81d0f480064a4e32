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
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .augment import TRAININGS, Augmenter, diagnosed_params

MODELS = ("filter", "cnn")
#: Simulated presses by default.
SIM_PRESSES = 1200
#: The simulated presses' centres may lie this far outside the fitted presses' box, px.
SPREAD_PX = 4.0
#: Simulated presses held out of the training, for Sim2Sim.
SIM_HELDOUT = 0.2
#: The filter's desired response: a Gaussian of this width at the centre, px.
SIGMA_PX = 1.5
#: The filter's ridge, as a share of the training images' mean spectral power.
FILTER_RIDGE = 1e-2
#: The filter's width and ridge each training chooses among, by the median localisation
#: error on the capture's fitted half (real presses a calibration already fitted; the
#: held-out half stays unseen).
FILTER_SIGMAS_PX = (1.5, 3.0)
FILTER_RIDGES = (1e-1, 1.0, 10.0)
#: Zero padding of the images before the Fourier transform, px each side (no wrap-around).
PAD_PX = 24
#: The depth regression's window: (2 PATCH_PX + 1) pixels a side, about the centre.
PATCH_PX = 12


@dataclass
class Presses:
    """Press images and what they are: ``images`` (N, h, w, 3) uint8, each one's
    no-contact frame ``frames`` (N, h, w, 3) uint8, ``centres`` (N, 2) px (u, v),
    ``depths`` (N,) metres, and ``indentation`` (N, h, w) metres (D_ref - D, simulated
    presses only)."""

    images: np.ndarray
    frames: np.ndarray
    centres: np.ndarray
    depths: np.ndarray
    indentation: np.ndarray | None = None

    def differences(self) -> np.ndarray:
        """(N, h, w, 3) float32: each image less its no-contact frame, in [0, 1] units."""
        return (self.images.astype(np.float32) - self.frames.astype(np.float32)) / np.float32(255.0)

    def subset(self, pick) -> "Presses":
        return Presses(self.images[pick], self.frames[pick], self.centres[pick], self.depths[pick],
                       None if self.indentation is None else self.indentation[pick])


def sample_presses(centres: np.ndarray, depths: np.ndarray, count: int, seed: int, shape: tuple[int, int],
                   margin_px: float = SPREAD_PX) -> tuple[np.ndarray, np.ndarray]:
    """``count`` simulated presses like the fitted ones (module doc): (centres (count, 2)
    px, depths (count,) metres), seeded."""
    centres, depths = np.asarray(centres, np.float64), np.asarray(depths, np.float64)
    if centres.ndim != 2 or centres.shape[1] != 2 or len(centres) == 0 or depths.shape != (len(centres),):
        raise ValueError(f"centres must be (N, 2) px and depths (N,) metres, N > 0; got {centres.shape} and "
                         f"{depths.shape}")
    if count < 1:
        raise ValueError(f"count must be >= 1 simulated presses, got {count}")
    rng = np.random.default_rng(seed)
    h, w = shape
    lo = np.maximum(centres.min(axis=0) - margin_px, [0.0, 0.0])
    hi = np.minimum(centres.max(axis=0) + margin_px, [w - 1.0, h - 1.0])
    return rng.uniform(lo, hi, (count, 2)), rng.uniform(depths.min(), depths.max(), count)


# --- the correlation filter --------------------------------------------------------------


def _spectra(diffs: np.ndarray) -> np.ndarray:
    """(N, 3, H', W'/2 + 1) complex: each difference image's channels, zero padded."""
    padded = np.pad(np.asarray(diffs, np.float32), ((0, 0), (PAD_PX, PAD_PX), (PAD_PX, PAD_PX), (0, 0)))
    return np.fft.rfft2(padded.transpose(0, 3, 1, 2), axes=(2, 3))


def _targets(centres: np.ndarray, shape: tuple[int, int], sigma_px: float = SIGMA_PX) -> np.ndarray:
    """(N, H', W'/2 + 1) complex: the desired responses' spectra, Gaussians at the centres."""
    h, w = shape[0] + 2 * PAD_PX, shape[1] + 2 * PAD_PX
    v, u = np.mgrid[:h, :w]
    out = []
    for cu, cv in np.asarray(centres, np.float64) + PAD_PX:
        out.append(np.exp(-((u - cu) ** 2 + (v - cv) ** 2) / (2 * sigma_px**2)))
    return np.fft.rfft2(np.asarray(out, np.float32), axes=(1, 2))


def peak(response: np.ndarray) -> tuple[float, float]:
    """The (u, v) of a response map's maximum, refined by a parabola through its
    neighbours along each axis."""
    v, u = np.unravel_index(int(np.argmax(response)), response.shape)

    def refine(a: float, b: float, c: float) -> float:
        curve = a - 2 * b + c
        return float(np.clip(0.5 * (a - c) / curve, -0.5, 0.5)) if curve < 0 else 0.0

    du = refine(response[v, u - 1], response[v, u], response[v, u + 1]) if 0 < u < response.shape[1] - 1 else 0.0
    dv = refine(response[v - 1, u], response[v, u], response[v + 1, u]) if 0 < v < response.shape[0] - 1 else 0.0
    return u + du, v + dv


def _patches(diffs: np.ndarray, centres: np.ndarray) -> np.ndarray:
    """(N, (2 PATCH_PX + 1)^2 * 3) the |change| about each centre (zero outside the frame)."""
    size = 2 * PATCH_PX + 1
    padded = np.pad(np.abs(np.asarray(diffs, np.float32)), ((0, 0), (PATCH_PX, PATCH_PX), (PATCH_PX, PATCH_PX),
                                                             (0, 0)))
    out = np.empty((len(diffs), size * size * 3), np.float32)
    for i, (u, v) in enumerate(np.rint(np.asarray(centres)).astype(int)):
        u = int(np.clip(u, 0, diffs.shape[2] - 1))
        v = int(np.clip(v, 0, diffs.shape[1] - 1))
        out[i] = padded[i, v:v + size, u:u + size].ravel()
    return out


class CorrelationLocator:
    """The ``filter`` model (module doc): ``fit(diffs, centres, depths)``, then
    ``predict(diffs) -> (centres (N, 2) px, depths (N,) metres)``."""

    def __init__(self, ridge: float = FILTER_RIDGE, sigma_px: float = SIGMA_PX):
        self.ridge = float(ridge)
        self.sigma_px = float(sigma_px)
        self.filter = None
        self.shape = None
        self.depth_model = None

    def fit(self, diffs: np.ndarray, centres: np.ndarray, depths: np.ndarray, batch: int = 64) -> "CorrelationLocator":
        from sklearn.linear_model import Ridge

        diffs = np.asarray(diffs, np.float32)
        if diffs.ndim != 4 or diffs.shape[-1] != 3 or len(diffs) != len(centres) or len(diffs) != len(depths):
            raise ValueError(f"diffs must be (N, h, w, 3) with N centres and depths, got {diffs.shape}, "
                             f"{np.shape(centres)}, {np.shape(depths)}")
        self.shape = diffs.shape[1:3]
        A = b = None
        for i in range(0, len(diffs), batch):
            X = _spectra(diffs[i:i + batch])  # (n, 3, H, W')
            G = _targets(centres[i:i + batch], self.shape, self.sigma_px)  # (n, H, W')
            a = np.einsum("nchw,ndhw->hwcd", np.conj(X), X)
            c = np.einsum("nchw,nhw->hwc", np.conj(X), G)
            A, b = (a, c) if A is None else (A + a, b + c)
        lam = self.ridge * float(np.mean(np.real(np.einsum("hwcc->hw", A)))) / 3
        self.filter = np.linalg.solve(A + lam * np.eye(3), b[..., None])[..., 0]  # (H, W', 3): conj(H) per channel
        found = self._centres(diffs)
        self.depth_model = Ridge(alpha=1.0).fit(_patches(diffs, found), np.asarray(depths, np.float64) * 1e3)
        return self

    def response(self, diffs: np.ndarray) -> np.ndarray:
        """(N, h, w) the filter's response to each difference image."""
        X = _spectra(diffs)
        R = np.einsum("hwc,nchw->nhw", self.filter, X)
        h, w = self.shape
        full = np.fft.irfft2(R, s=(h + 2 * PAD_PX, w + 2 * PAD_PX), axes=(1, 2))
        return full[:, PAD_PX:PAD_PX + h, PAD_PX:PAD_PX + w]

    def _centres(self, diffs: np.ndarray, batch: int = 64) -> np.ndarray:
        out = []
        for i in range(0, len(diffs), batch):
            out += [peak(r) for r in self.response(diffs[i:i + batch])]
        return np.array(out, np.float64).reshape(-1, 2)

    def predict(self, diffs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        if self.filter is None:
            raise RuntimeError("the locator is not fitted")
        diffs = np.asarray(diffs, np.float32)
        if diffs.shape[1:] != (*self.shape, 3):
            raise ValueError(f"diffs must be (N, {self.shape[0]}, {self.shape[1]}, 3), got {diffs.shape}")
        centres = self._centres(diffs)
        return centres, self.depth_model.predict(_patches(diffs, centres)) * 1e-3


class CNNLocator:
    """The ``cnn`` model (module doc), on the differences scaled to 8 bits about 128."""

    def __init__(self, seed: int = 0):
        self.seed = seed
        self.trained = None
        self.shape = None

    @staticmethod
    def _inputs(diffs: np.ndarray) -> np.ndarray:
        return np.clip(np.rint(128 + 255 * np.asarray(diffs)), 0, 255).astype(np.uint8)

    def fit(self, diffs: np.ndarray, centres: np.ndarray, depths: np.ndarray) -> "CNNLocator":
        from . import learn

        self.shape = diffs.shape[1:3]
        h, w = self.shape
        targets = np.c_[np.asarray(centres) / [w, h], np.asarray(depths) * 1e3].astype(np.float32)
        self.trained = learn.train("cnn", self._inputs(diffs), targets, self.seed)
        return self

    def predict(self, diffs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        h, w = self.shape
        out = self.trained.predict(self._inputs(diffs))
        return out[:, :2] * [w, h], out[:, 2] * 1e-3


class Offset:
    """A locator calibrated on real presses by a constant: ``model``'s centres less
    ``offset_px`` (u, v), its mean error (predicted less annotated) on the presses it was
    calibrated on (:meth:`fitted`). The depth is the model's own.

    This takes out a convention shared by every simulated training: where the
    annotations put a press's centre relative to where its image puts it (module doc).
    It is two numbers fitted on the real fitted half, which the width and ridge are
    already chosen on; the model itself sees simulated presses only."""

    def __init__(self, model, offset_px=(0.0, 0.0)):
        self.model = model
        self.offset_px = np.asarray(offset_px, np.float64).reshape(2)

    @classmethod
    def fitted(cls, model, presses: "Presses") -> "Offset":
        """``model`` less its mean centre error on ``presses``."""
        centres, _ = model.predict(presses.differences())
        return cls(model, np.mean(centres - presses.centres, axis=0))

    def predict(self, diffs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        centres, depths = self.model.predict(diffs)
        return centres - self.offset_px, depths


def locator(model: str, seed: int = 0):
    """A new model of ``model`` (MODELS); RuntimeError naming what to install where it needs
    what is absent."""
    if model == "filter":
        return CorrelationLocator()
    if model == "cnn":
        from . import learn

        why = learn.need("cnn")
        if why:
            raise RuntimeError(why)
        return CNNLocator(seed)
    raise ValueError(f"model must be one of {MODELS}, got {model!r}")


# --- the presses -------------------------------------------------------------------------


def real_presses(capture, ids) -> Presses:
    """A capture's presses ``ids``: its images, its no-contact frame, annotated centres and
    imported depths."""
    from scenes.dataset import read_samples
    from scenes.images import read_rgb, to_uint8

    by_id = {r["id"]: r for r in read_samples(capture.root)}
    shape = (capture.spec.camera.height, capture.spec.camera.width)
    images = np.stack([to_uint8(read_rgb(capture.root / by_id[i]["image"], shape)) for i in ids])
    frame = to_uint8(read_rgb(capture.root / "background.png", shape))
    missing = [i for i in ids if "contact_center_px" not in by_id[i]]
    if missing:
        raise ValueError(f"capture {capture.root}: presses {missing[:3]} have no annotated centre "
                         "(contact_center_px): an imported set of presses is needed")
    return Presses(images, np.broadcast_to(frame, images.shape).copy(),
                   np.array([by_id[i]["contact_center_px"] for i in ids], np.float64),
                   np.array([by_id[i]["measured_depth"] for i in ids], np.float64))


def simulate(capture, centres: np.ndarray, depths: np.ndarray, profile, field: str, out: Path, workers: int = 2,
             progress: bool = True) -> tuple[Presses, dict]:
    """Simulated presses of the capture's ball at ``centres`` (px) and ``depths`` (m),
    pressed on the rig and rendered by the calibrated fast path into the dataset ``out``
    (resumable): (the presses, the dataset's renderer settings)."""
    from scenes.camera import Camera, reference_depth
    from scenes.dataset import load_sample, read_meta, read_samples
    from scenes.generate import generate
    from scenes.geometry import membrane_mesh
    from scenes.images import read_rgb, to_uint8
    from scenes.imports import press_tap
    from scenes.protocol import Protocol

    spec = capture.spec
    mesh = membrane_mesh(spec)
    camera = Camera.from_spec(spec)
    obj = capture.objects[0]
    taps = tuple(press_tap(i, obj, spec, mesh, camera, c, float(d)) for i, (c, d) in enumerate(zip(centres, depths)))
    options = {"field": field, **({"profile": str(profile)} if profile is not None else {"background": "none"})}
    generate(out, spec, Protocol(name="sim-presses", taps=taps), "phong", options, workers=workers, progress=progress)
    records = {r["id"]: r for r in read_samples(out)}
    shape = camera.shape
    ref = reference_depth(mesh, camera)[0].astype(np.float32)
    images, indentation = [], []
    from scenes.dataset import sample_id

    for tap in taps:
        image, depth = load_sample(out, records[sample_id(tap.index, tap.object)], shape)
        images.append(to_uint8(image))
        delta = ref - np.asarray(depth, np.float32)
        delta[np.abs(delta) <= 1e-6] = 0.0
        indentation.append(delta)
    frame = to_uint8(read_rgb(Path(out) / "background.png", shape))
    images = np.stack(images)
    return (Presses(images, np.broadcast_to(frame, images.shape).copy(), np.asarray(centres, np.float64),
                    np.asarray(depths, np.float64), np.stack(indentation)), read_meta(out)["renderer"])


def moved_centres(centres: np.ndarray, params: dict, camera) -> np.ndarray:
    """(N, 2) where the image effects in ``params`` that move pixels (misalignment, lens
    distortion: ``studies.gap.effects.source_coordinates``) show a press the simulation
    shows at ``centres`` (u, v): the output pixel that samples it, found on the map's grid
    and refined by its local Jacobian. Unchanged where ``params`` moves nothing."""
    from studies.gap.effects import source_coordinates

    mis, dist = params.get("misalignment"), params.get("lens_distortion")
    centres = np.asarray(centres, np.float64)
    if mis is None and dist is None:
        return centres
    coords = source_coordinates(camera.shape, camera.f, (camera.cy, camera.cx), mis, dist)  # (row, col) sampled
    src = np.stack([coords[1], coords[0]], axis=-1)  # (H, W, 2) as (u, v)
    du = np.gradient(src, axis=1)  # d source / d output u
    dv = np.gradient(src, axis=0)
    out = np.empty_like(centres)
    for k, s in enumerate(centres):
        v, u = np.unravel_index(int(np.argmin(((src - s) ** 2).sum(axis=2))), src.shape[:2])
        J = np.stack([du[v, u], dv[v, u]], axis=1)  # columns: per output u, per output v
        step = np.linalg.lstsq(J, s - src[v, u], rcond=None)[0]
        out[k] = (u + step[0], v + step[1])
    return out


def trained_on(training: str, sim: Presses, augmenter: Augmenter | None, params: dict, seed: int) -> Presses:
    """The simulated presses as ``training`` shows them (module doc): images and frames
    with the same effects, and each press's centre where its effects show it
    (:func:`moved_centres`)."""
    if training == "none":
        return sim
    if augmenter is None:
        raise ValueError(f"training {training!r} needs the diagnosis' fast model")
    frame = sim.frames[0]
    camera = augmenter.model.camera
    if training == "diagnosed":
        images = augmenter.apply(sim.images, sim.indentation, params)
        zero = np.zeros((1,) + frame.shape[:2], np.float32)
        frames = np.broadcast_to(augmenter.apply(frame[None], zero, params)[0], images.shape).copy()
        centres = moved_centres(sim.centres, params, camera)
    elif training == "randomised":
        images = augmenter.randomised(sim.images, sim.indentation, seed)
        frames = augmenter.randomised_frames(frame, len(images), seed)
        draws = augmenter.draws(len(images), seed)
        centres = np.concatenate([moved_centres(sim.centres[i:i + 1], draws[i], camera) for i in range(len(images))])
    else:
        raise ValueError(f"training must be one of {TRAININGS}, got {training!r}")
    return Presses(images, frames, centres, sim.depths, sim.indentation)


#: Bootstrap resamples of the presses behind the medians' intervals.
RESAMPLES = 4000


def median_ci(values, seed: int = 0) -> dict:
    """The median of per-press values with a 95 % percentile bootstrap interval (presses
    resampled, seeded): {median, low, high}."""
    values = np.asarray(values, np.float64)
    rng = np.random.default_rng(seed)
    draws = np.median(values[rng.integers(0, len(values), (RESAMPLES, len(values)))], axis=1)
    low, high = np.percentile(draws, [2.5, 97.5])
    return {"median": float(np.median(values)), "low": float(low), "high": float(high)}


def errors(model, presses: Presses, pixel_m: float) -> dict:
    """Per press: the localisation error (mm) and the depth error (mm, signed: predicted
    less labelled) of ``model`` on ``presses``; their medians, the localisation's with its
    interval, and its mean."""
    centres, depths = model.predict(presses.differences())
    loc = np.linalg.norm(centres - presses.centres, axis=1) * pixel_m * 1e3
    bias = np.mean(centres - presses.centres, axis=0)
    return {"localisation_mm": loc.tolist(), "depth_error_mm": ((depths - presses.depths) * 1e3).tolist(),
            "localisation_mm_median": float(np.median(loc)), "localisation_mm_median_ci": median_ci(loc),
            "localisation_mm_mean": float(np.mean(loc)),
            "bias_px": bias.tolist(),
            "localisation_mm_median_unbiased": float(np.median(np.linalg.norm(centres - presses.centres - bias, axis=1))
                                                     * pixel_m * 1e3),
            "depth_error_mm_median_abs": float(np.median(np.abs(depths - presses.depths)) * 1e3)}


#: The Real2Real reference's filter: the default width and this ridge, fixed, since the
#: real fitted half it trains on cannot also choose them.
REAL2REAL_RIDGE = 1.0


def real2real(fit_real: Presses, real: Presses, pixel_m: float) -> dict:
    """The filter trained on the capture's real fitted half and tested on its held-out
    presses (``errors``): how consistently the annotations place the presses' own images,
    a floor the simulated trainings are measured against, not a sim-to-real result."""
    model = CorrelationLocator(REAL2REAL_RIDGE, SIGMA_PX).fit(fit_real.differences(), fit_real.centres,
                                                              fit_real.depths)
    return {"sigma_px": SIGMA_PX, "ridge": REAL2REAL_RIDGE, "real": errors(model, real, pixel_m)}


def ring_radii(presses: Presses, ball_radius_px: float) -> np.ndarray:
    """(N,) px: where each press's change, averaged round its labelled centre, peaks
    (``scenes.imports.contact_edge_px``, the import's rim); NaN where no rim is found."""
    from scenes.imports import contact_edge_px

    out = np.full(len(presses.images), np.nan)
    for k in range(len(out)):
        try:
            out[k] = contact_edge_px(presses.images[k], presses.frames[k], presses.centres[k], ball_radius_px)
        except ValueError:
            pass
    return out


def appearance(real: Presses, sim: Presses, ball_radius_px: float) -> dict:
    """How the simulated presses' images differ from the real ones in size: the median
    radius at which each press's change peaks round its centre (``ring_radii``), real and
    simulated, and their ratio (a simulated dent smaller than the real one teaches a
    localiser a template of the wrong size)."""
    r_real, r_sim = ring_radii(real, ball_radius_px), ring_radii(sim, ball_radius_px)
    med_real, med_sim = float(np.nanmedian(r_real)), float(np.nanmedian(r_sim))
    return {"ring_px_real": med_real, "ring_px_sim": med_sim, "sim_over_real": med_sim / med_real,
            "found": {"real": int(np.isfinite(r_real).sum()), "sim": int(np.isfinite(r_sim).sum())}}


def paired(a: dict, b: dict) -> dict:
    """Two trainings' localisation on the same real presses, press by press: the median of
    a - b (mm) with its interval, and the share of presses a localises better."""
    d = np.asarray(a["real"]["localisation_mm"]) - np.asarray(b["real"]["localisation_mm"])
    return {**median_ci(d), "a_better_share": float(np.mean(d < 0))}


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
    from scenes.dataset import atomic_write_bytes, atomic_write_json
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
