"""Fit candidate effects' parameters on training samples.

Each effect's parameters are fitted by bounded quasi-Newton (scipy's L-BFGS-B on
parameters scaled to [0, 1]) minimising a smooth mean absolute error between the real
images and the predicted ones over the training samples, at the working resolution (the
held-out judgement, ``studies.gap.judge``, is an MAE too: a squared error would let an
effect trade many small errors for a few large ones and win the fit while losing the
judgement). Fits start from the best of a few starting points (``studies.gap.starts``):
closed-form ones where the effect is linear in its parameters for a fixed exponent (the
colour matrix per gamma, vignetting coefficients), registration for shifts and rotations,
small grids where the loss has several basins. A fit that leaves most of the training
gap without having moved from its start (a kink or flat spot where finite-difference
gradients mislead L-BFGS-B) probes a step either side of it along each parameter and
restarts from the best probe, and its status says so. A fit's parameters get bootstrap intervals
over the training samples (``Fitter.intervals``).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np
from scipy import optimize

from .pairs import Pairs
from .samples import areas_at, fit_subset

#: At most this many L-BFGS-B iterations per fit.
MAX_ITERATIONS = 100
#: The fitted loss: mean of sqrt(e^2 + eps^2) - eps (Charbonnier), an MAE that is smooth
#: within one 8-bit level of zero.
LOSS_EPS = 1.0 / 255
#: A fit "stopped at its start" when no scaled parameter moved by more than this ...
STUCK_MOVE = 0.01
#: ... while it still leaves more than this share of the training loss.
STUCK_LEFT = 0.5
#: A stuck fit probes this far (scaled units) either side of its start along each
#: parameter, and restarts L-BFGS-B from the best probe that beats it.
PROBE_STEP = 0.05
#: A stuck fit's loss is "flat" at its start when no probe changes it by this share of the gap.
FLAT_SHARE = 1e-5
#: At most this many probe-and-restart rounds.
PROBE_ROUNDS = 3
#: A move's polish (``Fitter._polish``): its parameters and the first simplex's steps in
#: their units (px, rad), and at most this many loss evaluations.
POLISH_STEPS = {"du_px": 0.25, "dv_px": 0.25, "rotation_rad": 0.001}
POLISH_EVALUATIONS = 150
#: A move fitted coarser than this factor is polished again at it (``Fitter.fine``): at a
#: quarter of the images' size, a turn's loss on a solid frame has a false minimum.
POLISH_FACTOR = 2
#: Fits stop when an iteration lowers the loss by less than this fraction.
FTOL = 1e-4
#: Fits use at most this many training samples (an even spread over objects): a few
#: parameters per effect need no more, and it bounds the time of a diagnosis.
MAX_FIT_SAMPLES = 32
#: Bootstrap resamples of the training samples behind each reported parameter interval
#: (each one Newton step from the fit, nearly free once its finite differences are taken).
PARAM_RESAMPLES = 200
#: The parameter intervals' finite-difference step, scaled units (as the fits' own).
INTERVAL_STEP = 1e-3
#: A Hessian eigenvalue below this share of the largest marks a direction the training
#: samples do not pin: the intervals' Newton steps leave it alone.
INTERVAL_FLOOR = 1e-6
#: Parameter intervals are reported for this many of the best-ranked single effects.
INTERVAL_EFFECTS = 2


@dataclass
class Fit:
    """One fitted effect or combination."""

    effects: tuple[str, ...]
    params: dict
    train_mse: float
    train_mse_before: float
    evaluations: int
    seconds: float
    train_loss: float = float("nan")  # the fitted loss (smooth MAE), after
    train_loss_before: float = float("nan")  # and before
    #: how the search ended: optimizer, message, iterations, start_loss, moved (largest
    #: scaled parameter change from the start), stopped_at_start, retried, note
    status: dict = field(default_factory=dict)  # and screened: why it was not judged (``selection.screened``)


class Fitter:
    """The training samples of one pair of datasets at ``model``'s working resolution, and
    effects fitted on them.

    model : the working model (``FastModel`` or ``ReferenceModel``); pairs : the matched
    datasets; train : boolean mask over them (fits use at most ``MAX_FIT_SAMPLES`` of
    them, or the model's own ``max_fit_samples``, an even spread over objects); seed : the
    spread's and the parameter intervals' bootstrap's; fine : None, or a callable giving
    the same kind of model at ``POLISH_FACTOR``, finer than ``model``, on which a move's
    shift and turn are polished last (``_polish_fine``; built when first needed);
    samples : at most this many of ``train`` instead (the screen of a reference model's
    re-rendered candidates: ``selection.singles``).
    """

    def __init__(self, model, pairs: Pairs, train: np.ndarray, seed: int = 0, fine=None, samples: int | None = None):
        self.work = model
        self._fine_model, self._fine = fine, None
        self._pairs, self._train = pairs, train
        self.catalogue = model.catalogue
        self.names = model.names
        self.seed = seed
        count = samples or model.max_fit_samples or MAX_FIT_SAMPLES
        self.train_index = fit_subset(pairs, np.flatnonzero(train), count, seed)
        self.real_w = model.working_images(pairs.real[self.train_index])
        self.sim_w = model.working_images(pairs.sim[self.train_index])
        self.depth_w = None if pairs.depth is None else model.working_depth(pairs.depth[self.train_index])
        self.mask_w = model.mask
        # Samples that are parts of one image (pairs.extra["areas"], (N, H, W) bool) are
        # compared only there.
        areas = pairs.extra.get("areas")
        weights = np.broadcast_to(self.mask_w, (len(self.train_index),) + self.mask_w.shape).astype(np.float32)
        if areas is not None:
            weights = weights * areas_at(model, np.asarray(areas, bool))[self.train_index]
        self._registrations: dict[str, dict] = {}  # effect -> {kind: registration.Registration}
        r, c = np.nonzero(weights.any(axis=0))
        self.box = (slice(r.min(), r.max() + 1), slice(c.min(), c.max() + 1))
        self.box_mask = weights[(slice(None),) + self.box][..., None]
        self._box_count = float(self.box_mask.sum()) * 3
        # What fits compare: the model's ``compared`` images (the reference's, low-passed).
        self._compared_w = model.compared
        self._real_w_compared = self._compared_w(self.real_w)
        self.train_mse_before = self._mse(self.sim_w)
        self.train_loss_before = self._loss(self.sim_w)

    def _mse(self, pred: np.ndarray) -> float:
        rows, cols = self.box
        err = self._compared_w(pred)[:, rows, cols] - self._real_w_compared[:, rows, cols]
        err *= self.box_mask
        return float(np.einsum("nhwc,nhwc->", err, err, dtype=np.float64)) / self._box_count

    def _loss(self, pred: np.ndarray) -> float:
        """The fitted loss: the smooth MAE (``LOSS_EPS``) over the training samples' circle."""
        return float(self._sample_losses(pred).sum()) / self._box_count

    def predict_train(self, params: dict) -> np.ndarray:
        return self.work.predict(self.sim_w, self.depth_w, params, keys=self.train_index)

    def train_loss(self, params: dict) -> float:
        """The fitted loss (``_loss``) of the training samples predicted with ``params``."""
        return self._loss(self.predict_train(params))

    def _space(self, names: tuple[str, ...]):
        plist = [(name, p) for name in names for p in self.catalogue[name].params]
        low = np.array([p.low for _, p in plist])
        high = np.array([p.high for _, p in plist])

        def to_params(z: np.ndarray) -> dict:
            x = low + np.clip(z, 0, 1) * (high - low)
            out: dict = {name: {} for name in names}
            for (name, p), value in zip(plist, x):
                out[name][p.name] = float(value)
            return out

        def to_z(params: dict) -> np.ndarray:
            x = np.array([params[name][p.name] for name, p in plist])
            return (x - low) / (high - low)

        return plist, to_params, to_z

    def starts(self, name: str) -> list[dict]:
        """Starting points of one effect's fit (the best of them is refined): ``starts.starts``."""
        from .starts import starts

        return starts(self, name)

    def registrations(self, name: str = "misalignment") -> dict:
        """The closed-form registrations (``studies.gap.registration``) of the real training
        frames on the simulated ones, kept per effect: "frame" compares the whole images
        (the image circle moves with them: ``frame_share`` 1), "membrane" what the fixed
        background does not explain (image - ``FastModel.fixed``) inside the circle (the
        membrane moving under a fixed circle: ``frame_share`` 0); each compares the
        per-pixel median of the frames, which the contacts, each somewhere else, do not
        move. "contacts" fits the move to where each pair's contact lies in the real and
        the simulated frame: where only the contacts turn with the frame (a solid
        background in a round circle), they show its turn."""
        if name in self._registrations:
            return self._registrations[name]
        from .registration import grey, register, register_contacts, representative

        camera, factor = self.work.camera, self.work.factor
        centre = (camera.cy, camera.cx)
        real, what = representative(self.real_w)
        sim, _ = representative(self.sim_w)
        found = {"frame": register(real, sim, None, factor, centre, what)}
        found["contacts"] = register_contacts(grey(self.real_w), grey(self.sim_w), factor, centre)
        if "frame_share" in {p.name for p in self.catalogue[name].params}:
            fixed = self.work.fixed.mean(axis=-1)
            inside = self.work.circle > 0.999
            found["membrane"] = register(np.where(inside, real - fixed, 0.0), np.where(inside, sim - fixed, 0.0),
                                         inside, factor, centre, what)
        self._registrations[name] = found
        return found

    def closed_moves(self, base: dict, name: str) -> dict[str, dict]:
        """Each closed-form registration's move (``registrations``; zero for an unreliable
        one) on ``base``, shifts held inside the bounds: {kind: params}."""
        limit = next(p.high for p in self.catalogue[name].params if p.name == "du_px") - 1.0  # px, inside the bounds
        out = {}
        for kind, reg in self.registrations(name).items():
            move = {k: float(np.clip(v, -limit, limit)) if k != "rotation_rad" else v for k, v in reg.params().items()}
            share = 0.0 if kind == "membrane" else 1.0
            out[kind] = {**base, **move, **({"frame_share": share} if "frame_share" in base else {})}
        return out

    def fit(self, names: tuple[str, ...], start: dict | None = None, free: tuple[str, ...] | None = None,
            max_iterations: int = MAX_ITERATIONS) -> Fit:
        """Fit the effects ``names`` on the training samples.

        start : parameters to start from (default: each effect's own starting points,
            ``starts``, for a single effect; the identity otherwise).
        free : the effects whose parameters are fitted (default: all of ``names``); the
            others keep their ``start`` values.
        """
        t0 = time.perf_counter()
        names = tuple(n for n in self.names if n in names)
        free = names if free is None else tuple(n for n in names if n in free)
        fixed = {n: dict(start[n]) for n in names if n not in free} if start is not None else {}
        plist, to_params, to_z = self._space(free)
        count = [0]
        scale = max(self.train_loss_before, 1e-12)

        def loss(z: np.ndarray) -> float:
            count[0] += 1
            # Relative to the gap before, so that L-BFGS-B's tolerances (relative to
            # max(|f|, 1)) mean a share of the gap.
            return self._loss(self.predict_train({**fixed, **to_params(z)})) / scale

        candidates = []
        if start is not None and all(n in start for n in free):
            candidates.append({n: dict(start[n]) for n in free})
        if len(free) == 1 and (start is None or free[0] not in start):
            candidates += [{free[0]: s} for s in self.starts(free[0])]
        if not candidates:
            candidates.append({n: dict(start[n]) if start and n in start else dict(self.catalogue[n].identity)
                               for n in free})
        scored = sorted(((loss(to_z(c)), i) for i, c in enumerate(candidates)), key=lambda t: t[0])
        z0 = np.clip(to_z(candidates[scored[0][1]]), 0.0, 1.0)
        bounds = [(0.0, 1.0)] * len(plist)
        res = optimize.minimize(loss, z0, method="L-BFGS-B", bounds=bounds,
                                options={"maxiter": max_iterations, "eps": 1e-3, "ftol": FTOL})
        x, value, moved = np.asarray(res.x), float(res.fun), float(np.abs(res.x - z0).max(initial=0.0))
        status = {"optimizer": "L-BFGS-B", "message": str(res.message), "iterations": int(res.nit),
                  "start_loss": scored[0][0] * scale, "moved": moved, "stopped_at_start": False, "retried": False}
        if moved < STUCK_MOVE and value > STUCK_LEFT and len(x):
            status["start_value"] = value
            x, value, status = self._unstick(loss, x, value, bounds, max_iterations, status)
            status.pop("start_value")
        fine = None
        if len(free) == 1 and any(p.name in POLISH_STEPS for _, p in plist):
            x, value = self._polish(loss, x, value, plist, status)
            fine = self.fine()
        if fine is not None:  # the finer loss chooses between the fit, its best start and the registrations
            x, fine_value = self._polish_fine(fine, free[0], fixed, plist, to_params, to_z, x, z0, status)
            params = {**fixed, **to_params(x)}
            train_loss, worse = self.train_loss(params), fine_value > 1.0
        else:
            if value > scored[0][0]:  # never worse than its best start (closed-form ones included)
                x, value = z0, scored[0][0]
                status["note"] = "the search ended above its best start, which is reported instead"
            params, train_loss = {**fixed, **to_params(x)}, value * scale
            worse = train_loss > self.train_loss_before
        if worse:  # never worse than leaving the effects out (on the finer loss, where it polished)
            params = {n: dict(self.catalogue[n].identity) for n in names}
            train_loss = self.train_loss_before
            status["note"] = "no point found better than leaving the effect out; reported at its identity"
        mse = self._mse(self.predict_train(params))
        moved = [n for n in free if n in self._registrations]
        if len(free) == 1 and moved:  # the closed-form registrations the fit started from, beside its result
            status["registration"] = {kind: reg.to_dict() for kind, reg in self._registrations[moved[0]].items()}
        return Fit(names, params, mse, self.train_mse_before, count[0], time.perf_counter() - t0,
                   train_loss, self.train_loss_before, status)

    def intervals(self, fit: Fit, resamples: int = PARAM_RESAMPLES, confidence: float = 0.95) -> dict:
        """Bootstrap intervals of a fit's parameters: {effect: {param: [low, high]}}.

        Each resample draws the training samples with replacement; its parameters are one
        Newton step from the fit on that resample's loss, whose gradient and Hessian are
        sums of per-sample ones, measured once by finite differences (``INTERVAL_STEP``,
        scaled units) around the fit: 1 + 2P + P(P - 1) / 2 evaluations for P parameters,
        whatever the number of resamples (a refit per resample cost about P + 1
        evaluations per iteration each: most of a diagnosis). The step of the training
        samples themselves (the fit stops at a looser tolerance) is the reference: each
        draw's offset from it is added to the fitted value. A parameter at a bound (within
        the step) is held there; directions the training samples do not pin (a Hessian
        eigenvalue below ``INTERVAL_FLOOR`` of the largest) get no step."""
        names = fit.effects
        plist, to_params, to_z = self._space(names)
        if not plist or resamples < 2:
            return {}
        low = np.array([p.low for _, p in plist])
        high = np.array([p.high for _, p in plist])
        z0 = np.clip(to_z(fit.params), 0.0, 1.0)
        h = INTERVAL_STEP
        free = np.flatnonzero((z0 >= h) & (z0 <= 1.0 - h))
        draws = np.zeros((resamples, len(plist)))
        if free.size:
            def sums(dz: dict) -> np.ndarray:  # per-sample loss sums at z0 + h sum(e_j)
                z = z0.copy()
                for j, sign in dz.items():
                    z[j] += sign * h
                return self._sample_losses(self.predict_train(to_params(z)))

            f0 = sums({})
            up = {j: sums({j: 1.0}) for j in free}
            down = {j: sums({j: -1.0}) for j in free}
            F = free.size
            grad = np.stack([(up[j] - down[j]) / (2 * h) for j in free], axis=1)  # (n, F)
            hess = np.zeros((len(f0), F, F))
            for a, j in enumerate(free):
                hess[:, a, a] = (up[j] + down[j] - 2 * f0) / (h * h)
                for b in range(a + 1, F):
                    k = free[b]
                    hess[:, a, b] = hess[:, b, a] = (sums({j: 1.0, k: 1.0}) - up[j] - up[k] + f0) / (h * h)
            counts = self._sample_counts()
            rng = np.random.default_rng(self.seed)
            n = len(f0)

            def newton(weights: np.ndarray) -> np.ndarray:
                total = float(weights @ counts)
                g = weights @ grad / total
                H = np.tensordot(weights, hess, axes=1) / total
                values, vectors = np.linalg.eigh(0.5 * (H + H.T))
                keep = values > INTERVAL_FLOOR * max(float(values.max()), 1e-300)
                return -(vectors[:, keep] @ ((vectors[:, keep].T @ g) / values[keep]))

            reference = newton(np.ones(n))
            for i in range(resamples):
                weights = np.bincount(rng.integers(0, n, n), minlength=n).astype(np.float64)
                draws[i, free] = newton(weights) - reference
        fitted = low + z0 * (high - low)
        values = np.clip(fitted + draws * (high - low), low, high)
        tail = 100 * (1 - confidence) / 2
        lo, hi = np.percentile(values, [tail, 100 - tail], axis=0)
        out: dict = {name: {} for name in names}
        for (name, p), a, b in zip(plist, lo, hi):
            out[name][p.name] = [float(a), float(b)]
        return out

    def _sample_losses(self, pred: np.ndarray) -> np.ndarray:
        """(N,) each training sample's sum of the fitted loss over its circle (``_loss``'s
        numerator, per sample)."""
        rows, cols = self.box
        err = self._compared_w(pred)[:, rows, cols] - self._real_w_compared[:, rows, cols]
        err *= err
        err /= np.sqrt(err + np.float32(LOSS_EPS * LOSS_EPS)) + np.float32(LOSS_EPS)
        err *= self.box_mask
        return err.sum(axis=(1, 2, 3), dtype=np.float64)

    def _sample_counts(self) -> np.ndarray:
        """(N,) the values each training sample's loss sums (3 per pixel of its circle)."""
        return 3.0 * self.box_mask.sum(axis=(1, 2, 3), dtype=np.float64)

    def _polish(self, loss, x: np.ndarray, value: float, plist: list, status: dict) -> tuple[np.ndarray, float]:
        """A move's shift and turn polished by Nelder-Mead (scipy) from where L-BFGS-B
        stopped, the other parameters held: L-BFGS-B's finite differences step a turn by
        0.36 degrees (``eps`` of a range of 2 pi), more than the last tenths of a pixel at
        the rim that a registered frame still differs by, and it stops there. Its simplex
        starts ``POLISH_STEPS`` away (physical units); kept only where it lowers the loss."""
        moving = [i for i, (_, p) in enumerate(plist) if p.name in POLISH_STEPS]
        span = np.array([plist[i][1].high - plist[i][1].low for i in moving])
        steps = np.array([POLISH_STEPS[plist[i][1].name] for i in moving]) / span

        def sub(y: np.ndarray) -> float:
            z = x.copy()
            z[moving] = np.clip(y, 0.0, 1.0)
            return loss(z)

        simplex = np.vstack([x[moving]] + [x[moving] + np.eye(len(moving))[k] * steps[k] for k in range(len(moving))])
        res = optimize.minimize(sub, x[moving], method="Nelder-Mead",
                                options={"initial_simplex": simplex, "maxfev": POLISH_EVALUATIONS,
                                         "xatol": 0.05 * float(steps.min()), "fatol": FTOL * value})
        if float(res.fun) >= value:
            return x, value
        out = x.copy()
        out[moving] = np.clip(res.x, 0.0, 1.0)
        status["polished"] = {"method": "Nelder-Mead", "evaluations": int(res.nfev),
                              "loss_share": float(res.fun) / max(value, 1e-30)}
        return out, float(res.fun)

    def fine(self) -> Fitter | None:
        """The training samples at the finer ``fine`` model (the same samples), or None."""
        if self._fine is None and self._fine_model is not None:
            self._fine = Fitter(self._fine_model(), self._pairs, self._train, self.seed)
            if not np.array_equal(self._fine.train_index, self.train_index):
                raise RuntimeError("the finer model chose other training samples than the working one")
        return self._fine

    def _polish_fine(self, fine: Fitter, name: str, fixed: dict, plist: list, to_params, to_z, x: np.ndarray,
                     z0: np.ndarray, status: dict) -> tuple[np.ndarray, float]:
        """A move polished on the same training samples at ``fine``'s finer resolution. A
        coarse working resolution blurs a contact's few pixels: on a solid frame, whose
        round circle does not show a turn, a turn of 1.1 degrees fitted at a quarter of
        the images' size found a false minimum at 0.3 (the finer loss has one minimum, at
        the truth). The polish starts from the best, on the finer loss, of the working
        fit, its best start and each closed-form registration with the fit's other
        parameters. Returns (x, the finer loss relative to leaving the effect out)."""
        scale = max(fine.train_loss_before, 1e-12)

        def loss(z: np.ndarray) -> float:
            return fine._loss(fine.predict_train({**fixed, **to_params(z)})) / scale

        fitted = to_params(x)[name]
        starts = {"fit": x, "best start": z0}
        for kind, move in self.closed_moves(fitted, name).items():
            starts[f"registration ({kind})"] = np.clip(to_z({name: move}), 0.0, 1.0)
        values = {kind: loss(z) for kind, z in starts.items()}
        first = min(values, key=values.get)
        polished = status.pop("polished", None)
        out, value = self._polish(loss, starts[first], values[first], plist, status)
        status["fine"] = {"factor": int(fine.work.factor), "start": first,
                          "starts": {k: float(v) for k, v in values.items()},
                          "polished": status.pop("polished", None), "loss_share": value}
        if polished is not None:
            status["polished"] = polished
        return out, value

    def _unstick(self, loss, x: np.ndarray, value: float, bounds, max_iterations: int, status: dict):
        """A fit stopped at its start leaving most of the gap: probe ``PROBE_STEP`` either
        side along each parameter; from the best probe that beats the start, L-BFGS-B
        again (at most ``PROBE_ROUNDS`` times). Returns (x, value, status)."""
        z0 = x.copy()
        status.update(stopped_at_start=True, retried=True)
        first = None
        for _ in range(PROBE_ROUNDS):
            probes = [np.clip(x + sign * PROBE_STEP * np.eye(len(x))[i], 0.0, 1.0)
                      for i in range(len(x)) for sign in (-1.0, 1.0)]
            values = [loss(z) for z in probes]
            first = values if first is None else first
            best = int(np.argmin(values))
            if values[best] >= value:
                break
            res = optimize.minimize(loss, probes[best], method="L-BFGS-B", bounds=bounds,
                                    options={"maxiter": max_iterations, "eps": 1e-3, "ftol": FTOL})
            x, value = (np.asarray(res.x), float(res.fun)) if res.fun < values[best] else (probes[best], values[best])
            status["iterations"] += int(res.nit)
            status["message"] = str(res.message)
        status["moved"] = float(np.abs(x - z0).max())
        # Why it stopped: the probes around the start say whether the loss is flat there
        # (the effect does not reach the compared pixels, or only clipped ones) or rises.
        spread = float(np.max(np.abs(np.array(first) - status["start_value"]))) if first else 0.0
        status["why"] = "flat" if spread < FLAT_SHARE else "local optimum"
        if status["moved"] < STUCK_MOVE and status["why"] == "flat":
            status["note"] = (f"L-BFGS-B stopped at its start, leaving {100 * value:.0f}% of the training loss; the "
                              f"loss is flat there: no point {PROBE_STEP} (scaled) either side along any parameter "
                              f"changes it by {100 * FLAT_SHARE:g}% of the gap (the effect does not reach the compared "
                              "pixels, or only where the image is clipped)")
        elif status["moved"] < STUCK_MOVE:
            status["note"] = (f"L-BFGS-B stopped at its start, leaving {100 * value:.0f}% of the training loss; no "
                              f"point {PROBE_STEP} (scaled) either side along any parameter is better: a local optimum")
        else:
            status["optimizer"] = "L-BFGS-B, restarted from probes"
            status["note"] = (f"L-BFGS-B stopped at its start; restarted from a probe {PROBE_STEP} (scaled) away, it "
                              f"left {100 * value:.0f}% of the training loss")
        return x, value, status
