"""Judge fitted effects on the held-out samples.

A fit (``studies.gap.fit``) is judged on held-out samples only, at the judging model's
resolution (the images' own, except for a reference model: its basis film,
``studies.gap.diagnosis.make_models``): the paired improvement of each sample's MAE,
SSIM and PSNR over the simulator as it is (or over another judged fit), with bootstrap
confidence intervals (``metrics.improvement``). A fit explains part of the gap only if
its MAE improvement is significant (its interval above 0) and large enough
(``Judged.explains``).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from scenes import image_stats
from scenes.images import block_mean

from . import effects as fx
from . import metrics
from .fit import Fit
from .pairs import Pairs
from .samples import areas_at, contact_at

#: Ranking metric: the masked MAE (the image circle; the black border holds no signal).
RANK_BY = ("masked", "mae")
#: A single effect is ranked (named as a cause) only if it also closes at least this share
#: of the held-out gap less its sensor-noise floor: a candidate that closes 0.2 % of it,
#: however surely, explains nothing, and the Answer then says that nothing does.
MIN_RANK_SHARE = 0.05


@dataclass
class Judged:
    """A fit judged on the held-out samples."""

    fit: Fit
    after: dict  # image_stats.per_sample of the prediction
    improvement: dict = field(default_factory=dict)  # {full|masked: {metric: improvement}}
    #: the held-out MAE it must remove to be named (``Judge.min_gain``); 0: any
    min_gain: float = 0.0

    @property
    def significant(self) -> bool:
        return self.improvement[RANK_BY[0]][RANK_BY[1]]["significant"]

    @property
    def gain(self) -> float:
        return self.improvement[RANK_BY[0]][RANK_BY[1]]["mean"]

    @property
    def share(self) -> float:
        """The share of the held-out gap it closes (``RANK_BY``)."""
        return self.improvement[RANK_BY[0]][RANK_BY[1]]["share"]

    @property
    def explains(self) -> bool:
        """Whether it is named as a cause: significant, and removing at least ``min_gain``
        of the held-out MAE, and at least ``MIN_RANK_SHARE`` of the gap where no
        ``min_gain`` was set."""
        if self.min_gain > 0:
            return self.significant and self.gain >= self.min_gain
        return self.significant and self.share >= MIN_RANK_SHARE


class Judge:
    """The held-out samples of one pair of datasets at ``model``'s resolution, and fits
    judged on them.

    model : the judging model (``FastModel`` or ``ReferenceModel``); pairs : the matched
    datasets; heldout : boolean mask over them; regions : the image circle's regions
    ({name: (H, W) bool} at the images' size, default ``regions.region_labels``): held-out
    samples are also judged in each (their own scopes beside "full" and "masked"), unless
    samples are parts of one image; seed : the bootstrap intervals'.
    """

    def __init__(self, model, pairs: Pairs, heldout: np.ndarray, regions: dict[str, np.ndarray] | None = None,
                 seed: int = 0):
        self.model = model
        self.seed = seed
        self.heldout_index = np.flatnonzero(heldout)
        # Samples that are parts of one image (pairs.extra["areas"], (N, H, W) bool) are
        # compared only there.
        areas = pairs.extra.get("areas")
        self.areas_h = None if areas is None else areas_at(model, np.asarray(areas, bool)[self.heldout_index])
        self.real_h = model.working_images(pairs.real[self.heldout_index])
        self.sim_h = model.working_images(pairs.sim[self.heldout_index])
        self.depth_h = None if pairs.depth is None else pairs.depth[self.heldout_index]
        self.mask = model.mask
        self.regions_h = None
        if areas is None:
            if regions is None:
                from .regions import region_labels

                regions = region_labels(pairs.spec)
            judged = {name: (block_mean(np.asarray(r, np.float32), model.factor) >= 0.5) & self.mask
                      for name, r in regions.items()}
            self.regions_h = {name: r for name, r in judged.items() if r.any()}
        # Each held-out tap's contact region: what a tactile sensor's user looks at first.
        self.contact_h = None if areas is not None else contact_at(model, pairs, self.heldout_index)
        self._real_h_compared = model.compared(self.real_h)
        self.before = image_stats.per_sample(self._real_h_compared, model.compared(self.sim_h), self.mask,
                                             areas=self.areas_h, regions=self.regions_h, contact=self.contact_h)
        # What a candidate must remove to be named: MIN_RANK_SHARE of the part of the
        # held-out gap that is not sensor noise (which no prediction removes), so that a
        # gap mostly of noise does not hide the effect behind the rest.
        gap = float(np.mean(self.before[RANK_BY[0]][RANK_BY[1]]))
        self.noise_floor = fx.noise_std(self.real_h - self.sim_h, self.mask) * float(np.sqrt(2 / np.pi))
        self.min_gain = MIN_RANK_SHARE * max(gap - self.noise_floor, 0.0) or 1e-12

    def predict(self, params: dict) -> np.ndarray:
        """(N, h, w, 3) the held-out samples predicted with the effects in ``params``."""
        return self.model.predict(self.sim_h, self.depth_h, params, keys=self.heldout_index)

    def judge(self, fit: Fit, against: dict | None = None, complete: bool | None = True) -> Judged:
        """Held-out metrics of a fit and their paired improvement over ``against`` (an
        ``image_stats.per_sample`` result; default: the simulator as it is). ``complete=False``
        measures MAE and PSNR only (no SSIM, most of the time), for trials that are only
        compared; None adds SSIM only where the fit explains part of the gap
        (``Judged.explains``), as the single candidates are judged."""
        pred = self.model.compared(self.predict(fit.params))
        if complete is None:
            quick = self._judged(fit, pred, against, False)
            return self._judged(fit, pred, against, True) if quick.explains else quick
        return self._judged(fit, pred, against, complete)

    def _judged(self, fit: Fit, pred: np.ndarray, against: dict | None, complete: bool) -> Judged:
        after = image_stats.per_sample(self._real_h_compared, pred, self.mask, ssim=complete,
                                       areas=self.areas_h, regions=self.regions_h, contact=self.contact_h)
        against = self.before if against is None else against
        names = image_stats.METRICS if complete else ("mae", "psnr")
        # a region of the image circle is judged on the MAE it closes only: its bootstrap
        # intervals cost as much as the whole circle's, and nothing reads the others
        improvement = {k: {m: metrics.improvement(against[k][m], after[k][m], m, seed=self.seed)
                           for m in (names if k in image_stats.SCOPES else ("mae",))} for k in after}
        return Judged(fit, after, improvement, min_gain=self.min_gain)

    def unjudged(self, fit: Fit, why: str) -> Judged:
        """A fit left unjudged (``selection.screened``): reported as closing nothing, never
        significant."""
        fit.status["screened"] = why
        improvement = {k: {m: metrics.improvement(self.before[k][m], self.before[k][m], m, seed=self.seed)
                           for m in (image_stats.METRICS if k in image_stats.SCOPES else ("mae",))}
                       for k in self.before}
        return Judged(fit, self.before, improvement)

    def noise(self, params: dict) -> float:
        """Sensor noise estimated from the held-out residual of a prediction."""
        return fx.noise_std(self.real_h - self.predict(params), self.mask)
