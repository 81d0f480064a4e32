"""One diagnosis put together: the models of a simulated dataset, the fitter on its
training samples, the judge on its held-out ones, and the selection between them
(``diagnose`` runs it and reports it).
"""

from __future__ import annotations

import numpy as np

from scenes.camera import Camera
from scenes.spec import SensorSpec

from . import selection
from .fit import MAX_ITERATIONS, PARAM_RESAMPLES, POLISH_FACTOR, Fit, Fitter
from .judge import Judge, Judged
from .model import FastModel, auto_exposed
from .pairs import Pairs
from .reference_model import ReferenceModel
from .source_basis import SourceBasis


def judging_factor(spec: SensorSpec, film: tuple[int, int]) -> int:
    """The block size that takes the spec's camera images to ``film`` (w, h); 1 when
    blocks of one size do not tile the image into that film."""
    full = Camera.from_spec(spec)
    factor = full.width // int(film[0])
    if factor < 1 or full.width % factor or full.height % factor or full.height // factor != int(film[1]):
        return 1
    return factor


def make_models(pairs: Pairs, renderer: dict, factor: int):
    """(working, judging) models of a simulated dataset: the reference decomposed per
    source (``studies.gap.reference_model``) when the reference rendered it, else the fast
    simulator rebuilt from its settings (``studies.gap.model``).

    The fast model is judged at the images' resolution. The reference model predicts what
    a candidate changes at its basis film only, and its datasets carry Monte Carlo noise
    at every pixel, so it is judged, and fitted, at the basis film (``judging_factor``):
    there the noise it cannot predict is smaller and the detail it does not predict is
    not counted as a gap.
    """
    if renderer.get("renderer") == "pbr":
        spec, profile = unit_of_replay(pairs, renderer)
        basis = SourceBasis(spec, renderer, pairs.depth if pairs.depth is not None else np.zeros((0,)))
        judge = judging_factor(spec, basis.film)
        work = ReferenceModel(spec, renderer, max(factor, judge), basis, profile)
        return work, (ReferenceModel(spec, renderer, judge, basis, profile) if work.factor != judge else work)
    exposure = auto_exposed(pairs.real_meta)
    work = FastModel(pairs.spec, renderer, factor, exposure)
    return work, (FastModel(pairs.spec, renderer, 1, exposure) if factor != 1 else work)


def unit_of_replay(pairs: Pairs, renderer: dict):
    """(the spec the reference rendered, its unit's Profile or None): a replay through a
    unit's profile (``renderer.profile_data``) rendered the unit as the reference takes it
    (``pbr_tactile.profiled.reference_spec``: the fitted layout, the turned LEDs, the
    profile's image circle), not the dataset's recorded spec."""
    data = renderer.get("profile_data")
    if data is None:
        return pairs.spec, None
    from pbr_tactile.profiled import reference_spec
    from scenes.profile import profile_from_dict

    profile = profile_from_dict(data, f"{pairs.sim_dir}/dataset.json renderer.profile_data")
    return reference_spec(profile, pairs.spec), profile


def polish_model(pairs: Pairs, renderer: dict, work):
    """A callable giving the fast model at ``fit.POLISH_FACTOR`` when ``work`` fits coarser
    (``Fitter``'s ``fine``), else None. The reference model is fitted at its basis film
    already, and predicts nothing finer."""
    if not isinstance(work, FastModel) or work.factor <= POLISH_FACTOR:
        return None
    exposure = auto_exposed(pairs.real_meta)
    return lambda: FastModel(pairs.spec, renderer, POLISH_FACTOR, exposure)


class Diagnosis:
    """Fitting, judging and selecting effects on one pair of datasets: a facade over
    ``fit.Fitter`` (``fitter``), ``judge.Judge`` (``judging``) and ``selection``.

    pairs : the matched datasets; train, heldout : boolean masks over them;
    factor : the working resolution of fits (1/factor of the images');
    effects : the names to consider (default: every one that applies);
    regions : the image circle's regions ({name: (H, W) bool} at the images' size,
        default ``regions.region_labels``): held-out samples are also judged in each
        (their own scopes beside "full" and "masked"), unless samples are parts of one image.
    """

    def __init__(self, pairs: Pairs, train: np.ndarray, heldout: np.ndarray, factor: int = 2,
                 effects: tuple[str, ...] | None = None, seed: int = 0, progress=None,
                 regions: dict[str, np.ndarray] | None = None):
        self.pairs = pairs
        self.seed = seed
        self.progress = progress
        renderer = dict(pairs.sim_meta.get("renderer") or {})
        self.work, self.full = make_models(pairs, renderer, factor)
        self.catalogue = self.work.catalogue
        self.names = self.work.names
        self.not_applicable = self.work.not_applicable(pairs)
        wanted = self.names if effects is None else tuple(effects)
        unknown = [e for e in wanted if e not in self.names]
        if unknown:
            raise ValueError(f"unknown effect(s) {unknown}; the {self.work.kind} model's catalogue has "
                             f"{list(self.names)}")
        self.effects = tuple(e for e in wanted if e not in self.not_applicable)
        self.fitter = Fitter(self.work, pairs, train, seed, fine=polish_model(pairs, renderer, self.work))
        self.judging = Judge(self.full, pairs, heldout, regions, seed)
        self.train_index = self.fitter.train_index
        self.heldout_index = self.judging.heldout_index
        self.before = self.judging.before  # the held-out metrics of the simulator as it is
        self.noise_floor = self.judging.noise_floor
        self.min_gain = self.judging.min_gain
        self.first_pair: Judged | None = None  # the pair ranked first, if one was (``rank``)
        self._screen: Fitter | None = None  # the fit's taps cut to the screen's (``screen``)

    def fit(self, names: tuple[str, ...], start: dict | None = None, free: tuple[str, ...] | None = None,
            max_iterations: int = MAX_ITERATIONS) -> Fit:
        """``Fitter.fit``."""
        return self.fitter.fit(names, start, free, max_iterations)

    def judge(self, fit: Fit, against: dict | None = None, complete: bool | None = True) -> Judged:
        """``Judge.judge``."""
        return self.judging.judge(fit, against, complete)

    def intervals(self, fit: Fit, resamples: int = PARAM_RESAMPLES, confidence: float = 0.95) -> dict:
        """``Fitter.intervals``."""
        return self.fitter.intervals(fit, resamples, confidence)

    def noise(self, params: dict) -> float:
        """``Judge.noise``."""
        return self.judging.noise(params)

    def singles(self) -> dict[str, Judged]:
        """``selection.singles`` of the effects considered."""
        return selection.singles(self.effects, self.fit, self.judge, self.judging.unjudged, self.work, self.progress,
                                 self.screen if getattr(self.work, "screen_taps", None) else None)

    def screen(self, names: tuple[str, ...]) -> Fit:
        """``names`` fitted on the working model's ``screen_taps`` of the fit's taps (a
        reference model's screen of its re-rendered candidates: ``selection.singles``)."""
        if self._screen is None:
            taps = np.zeros(len(self.pairs), bool)
            taps[self.train_index] = True
            self._screen = Fitter(self.work, self.pairs, taps, self.seed, samples=self.work.screen_taps)
        return self._screen.fit(names)

    def rank(self, singles: dict[str, Judged]) -> list[str]:
        """``selection.rank``; the pair it ranks first, if any, is kept as ``first_pair``."""
        sizes = {n: selection.size(self.catalogue[n]) for n in singles}
        ranked, self.first_pair = selection.rank(singles, self.before, sizes, self.work.ties_to_simplest, self.fit,
                                                 self.judge, self.seed)
        return ranked

    def select(self, singles: dict[str, Judged], ranked: list[str] | None = None) -> list[Judged]:
        """``selection.forward`` from ``ranked`` (default: ``rank``'s)."""
        ranked = self.rank(singles) if ranked is None else ranked
        return selection.forward(singles, ranked, self.first_pair, self.before, self.fit, self.judge,
                                 self.fitter.train_loss)
