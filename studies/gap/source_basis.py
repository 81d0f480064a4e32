"""Per-tap, per-source images of the physically based reference at a low film
(``pbr_tactile.basis.emitter_basis``: each LED, and its leak into the glass core, per unit
flux), rendered on demand for the identity or a re-rendered candidate at a grid point,
and kept.

The candidates that change only how much light survives a path, not the path (the
elastomer's absorption and scattering, the paint's albedo: ``REWEIGHTED``), are not
traced again at their grid points: each tap's identity render re-weights its own photons
to every grid point of them in the same call (perturbation Monte Carlo,
``pbr_tactile.reweight``). A grid point whose re-weighting is not valid (its Kish
effective-sample-size ratio below ``pbr_tactile.reweight.MIN_ESS_RATIO``: far from the
traced value its variance grows too large) is traced again, and ``reweighting`` says
which and why, as it says which candidates' points cannot be re-weighted at all (a
glossy paint's albedo, scattering where the simulation has none). Only a candidate that
moves the geometry or the light's places (the membrane's mechanics, the leak's cone) is
always traced again."""

from __future__ import annotations

import dataclasses
import time

import numpy as np

from pbr_tactile.reweight import PARAMETERS
from scenes.camera import CONTACT_EPS_M, Camera, reference_depth
from scenes.geometry import membrane_mesh
from scenes.spec import SensorSpec

#: The basis renders: film (a quarter of the default dataset film a side), camera samples
#: per pixel per pass, passes; photons per LED per pass and no-contact runs per pass are
#: the simulated dataset's (these where it records none). At 2^16 photons and no runs,
#: the basis put a 0.3 core leak's change in the bright rings 2-3 times above what the
#: dataset renderer's own no-contact frames show, so a leak of 0.3 was fitted at 0.16; at
#: the dataset's 2^18 photons and 4 runs the fit's loss is lowest at 0.25-0.3. Measured on
#: 2 cores: one per-source render of a contact takes about 8 s at 2^16 photons and no
#: runs, 18-22 s at 2^18 and 4 runs.
BASIS_FILM = (80, 60)
BASIS_PHOTONS = 1 << 18
BASIS_SPP = 16
BASIS_PASSES = 2
BASIS_NO_CONTACT_RUNS = 4
#: The basis is rendered with this core leak fraction, so that each LED's leak has its
#: own image (per unit flux, the fraction only weights it).
LEAK_BASIS = 0.5
#: ``SourceBasis.images``' key of the sensor without contact (its exposure's reference).
NO_CONTACT = -1
#: Candidates that change only a contact.
MECHANICS = ("membrane_compliance", "layer_spread")
#: Candidates re-weighted from the identity's photons.
REWEIGHTED = PARAMETERS
#: Candidates that change only the leaks' light (each LED's leak into the glass core): at
#: their grid points the leak sources alone are traced, with the random numbers they have
#: in the identity's render, and the LEDs' own columns are the identity's (their photons
#: walk the same either way), which halves such a render's photons.
LEAKS_ONLY = ("core_leak_cone_rad",)


class SourceBasis:
    """Per-tap, per-source images of the reference at a low film, rendered on demand and
    kept (on disk too, by ``emitter_basis``'s cache).

    spec, renderer : the simulated dataset's sensor and renderer settings; depth : (N, H,
    W) its contacts' planar depth, metres.
    """

    def __init__(self, spec: SensorSpec, renderer: dict, depth: np.ndarray, film=BASIS_FILM,
                 photons: int | None = None, spp: int = BASIS_SPP, passes: int = BASIS_PASSES, seed: int = 1,
                 use_cache: bool = True, no_contact_runs: int | None = None, reweight: bool = True):
        from pbr_tactile.effects import Effects

        self.spec = spec
        self.camera = Camera.from_spec(spec)
        self.mesh = membrane_mesh(spec)
        self.ref = reference_depth(self.mesh, self.camera)[0].astype(np.float32)
        self.depth = depth
        given = dict(renderer.get("effects") or {})
        if "lens_distortion" in given:
            given["lens_distortion"] = tuple(given["lens_distortion"])
        self.effects = Effects(**given)
        self.gain = renderer.get("exposure_gain")
        self.film = tuple(int(v) for v in film)
        # The dataset's own photon count and no-contact runs unless given: the exposure and
        # the leak's share of the image both moved with them (see BASIS_PHOTONS).
        self.photons = int(photons or renderer.get("photons") or BASIS_PHOTONS)
        self.no_contact_runs = int(renderer.get("no_contact_runs", BASIS_NO_CONTACT_RUNS)
                                   if no_contact_runs is None else no_contact_runs)
        self.spp, self.passes, self.seed = spp, passes, seed
        # The camera's in-scattered light as the dataset found it (the fluence lookup, the
        # reference's default, where it records none).
        self.inscatter = renderer.get("inscatter") or "fluence"
        self.use_cache = use_cache
        self._images: dict = {}
        self._variances: dict = {}  # the variance of each image's mean, by the same tags
        self.names: list[str] | None = None  # the sources, in the basis' order (from the first render)
        self.renders = 0  # basis renders made here (not read from memory)
        self.seconds = 0.0
        self.cost: dict[str, dict] = {}  # per candidate: renders and seconds
        # The grid points re-weighted from each identity render ((name, value) rows), and
        # which candidates' are not and why.
        self.variants: list[tuple[str, float]] = []
        self.reweighting: dict = {"on": False, "why": "switched off"}
        if reweight:
            self._plan_variants()

    def _plan_variants(self) -> None:
        """The grid points of ``REWEIGHTED`` (``studies.gap.physical``'s grids) other than
        the identity, each with the other parameters at the simulation's values."""
        from .physical import physical_catalogue

        # Not re-weighted, and why: a glossy paint's albedo (a flake bounce does not scale
        # with it); scattering where the simulation's medium has none, a paint albedo where
        # its paint is black (its walks never scatter, or end on the paint).
        e = self.effects
        why = {"coating_albedo": f"the paint is glossy (coating_gloss {e.coating_gloss:g}): a flake bounce does "
                                 "not scale with its albedo" if e.coating_gloss > 0 else
                                 "the paint is black: its photons end on it" if e.coating_albedo <= 0 else None,
               "scattering_per_m": "the medium does not scatter: its walks never do" if e.scattering_per_m <= 0
                                   else None}
        not_reweighted = {n: f"{w}; its grid points are traced" for n, w in why.items() if w}
        names = [n for n in REWEIGHTED if n not in not_reweighted]
        grids = physical_catalogue(self.spec, self.effects)[2]
        self.variants = [(name, float(v)) for name in names if name in grids
                         for v in grids[name]["values"] if float(v) != float(getattr(self.effects, name))]
        self.reweighting = {"on": True, "variants": [f"{n}={v:g}" for n, v in self.variants],
                            **({"not_reweighted": not_reweighted} if not_reweighted else {}),
                            "retraced": {}, "seconds": 0.0, "renders": 0,
                            "what": "grid points of the absorption, scattering and paint albedo re-weighted from each "
                                    "tap's identity photons (perturbation Monte Carlo); retraced: the points whose "
                                    "Kish ESS ratio (lowest source, first tap it fell short on) was below the "
                                    "validity bound, traced again"}

    def _rows(self) -> np.ndarray:
        from pbr_tactile.reweight import PARAMETERS

        base = np.array([getattr(self.effects, p) for p in PARAMETERS], np.float64)
        rows = np.repeat(base[None], len(self.variants), axis=0)
        for k, (name, value) in enumerate(self.variants):
            rows[k, PARAMETERS.index(name)] = value
        return rows

    def variant(self, name: str | None, value: float | None):
        """(spec, effects, depth scale) of the identity (name None) or of candidate
        ``name`` at grid ``value``."""
        effects = dataclasses.replace(self.effects, core_light_leak=LEAK_BASIS)
        spec, scale = self.spec, 1.0
        if name == "membrane_compliance":
            scale = float(value)
        elif name == "layer_spread":
            spec = spec.replace(elastic=dataclasses.replace(spec.elastic, poisson_ratio=float(value)))
        elif name is not None:
            current = getattr(effects, name)
            effects = dataclasses.replace(effects, **{name: bool(value >= 0.5) if isinstance(current, bool)
                                                      else float(value)})
        return spec, effects, scale

    def images(self, key: int, name: str | None = None, value: float | None = None) -> np.ndarray:
        """(h, w, S) float32: tap ``key``'s per-source images per unit flux at the film
        (``NO_CONTACT``: the sensor without contact), for the identity or candidate
        ``name`` at grid ``value``."""
        if key == NO_CONTACT and name in MECHANICS:
            name = value = None  # the membrane's mechanics change nothing without a contact
        tag = (int(key), name, None if value is None else float(value))
        if tag in self._images:
            return self._images[tag]
        reweighted = (name is None or (name, None if value is None else float(value)) in self.variants)
        if self.variants and reweighted and (int(key), None, None) not in self._images:
            self._render(key, None, None, perturb=True)  # the identity and its re-weighted grid points
            if tag in self._images:
                return self._images[tag]
        return self._render(key, name, value)

    def _render(self, key: int, name: str | None, value: float | None, perturb: bool = False) -> np.ndarray:
        """Render tap ``key``'s basis for the identity or ``name`` at ``value`` and keep it;
        with ``perturb``, the identity's, re-weighted to ``self.variants`` too (those valid
        are kept under their own tags)."""
        from pbr_tactile.basis import emitter_basis, is_leak

        tag = (int(key), name, None if value is None else float(value))
        spec, effects, scale = self.variant(name, value)
        depth = self.ref if key == NO_CONTACT else np.asarray(self.depth[key], np.float32)
        touched = np.abs(depth - self.ref) > CONTACT_EPS_M
        contact = {}
        if touched.any():
            depth = np.where(touched, depth, self.ref)
            if scale != 1.0:
                depth = (self.ref - scale * (self.ref - depth)).astype(np.float32)
            contact = {"depth": depth, "ref_depth": self.ref}
        only = None
        if name in LEAKS_ONLY:
            plain = self.images(key)  # the identity (first: its LEDs' columns stand for this point's)
            only = [int(k) for k in np.flatnonzero(is_leak(self.names))]
        t0 = time.perf_counter()
        rows = self._rows() if perturb else None
        basis = emitter_basis(spec, self.mesh, self.camera, effects, self.film, photons=self.photons, spp=self.spp,
                              passes=self.passes, seed=self.seed, use_cache=self.use_cache,
                              no_contact_runs=self.no_contact_runs, inscatter=self.inscatter, perturb=rows,
                              only=only, **contact)
        seconds = time.perf_counter() - t0
        self.renders += 1
        self.seconds += seconds
        cost = self.cost.setdefault(name or "identity", {"renders": 0, "seconds": 0.0})
        cost["renders"] += 1
        cost["seconds"] += seconds
        if perturb:
            self.reweighting["renders"] += 1
            self.reweighting["seconds"] += seconds
            ess = np.asarray(basis["ess_ratio"]).min(axis=1)
            for k, (n, v) in enumerate(self.variants):
                if basis["valid"][k]:
                    self._images[(int(key), n, v)] = np.asarray(basis["variant_mean"][k], np.float32)
                    self._variances[(int(key), n, v)] = np.asarray(basis["variant_variance"][k], np.float32)
                else:
                    self.reweighting["retraced"].setdefault(f"{n}={v:g}", {"tap": int(key), "ess_ratio": float(ess[k])})
        names = [str(n) for n in basis["names"]]
        image, variance = np.asarray(basis["mean"], np.float32), np.asarray(basis["variance"], np.float32)
        if only is not None:  # the leaks' columns into the identity's
            expected = [self.names[k] for k in only]
            if names != expected:
                raise ValueError(f"the leaks rendered alone are {names}, not the basis' {expected}")
            leaks, leak_variance = image, variance
            image, variance = plain.copy(), self.variance(key).copy()
            image[..., only], variance[..., only] = leaks, leak_variance
        elif self.names is None:
            self.names = names
        elif names != self.names:
            raise ValueError(f"the basis' sources changed between renders ({self.names} against {names})")
        self._images[tag] = image
        self._variances[tag] = variance
        return image

    def rendered_keys(self) -> list[int]:
        """The taps whose identity images are rendered (no contact included)."""
        return sorted(key for key, name, _ in self._images if name is None)

    def variance(self, key: int) -> np.ndarray:
        """(h, w, S) the variance of tap ``key``'s identity images (``images``' mean),
        from the passes of its render; the tap must be rendered."""
        return self._variances[(int(key), None, None)]
