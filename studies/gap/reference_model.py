"""The physically based reference decomposed per light source, so that the diagnosis can
fit its physical effects (the candidates of ``studies.gap.physical``).

The image is linear in each emitter's power and the transport is grey, so each tap is
rendered once per source (``pbr_tactile.basis.emitter_basis``: each LED, and its leak
into the glass core, per unit flux) at a low film, and

    linear(theta) = sum_m p_m [(1 - f) B_m + f B_m,leak] (x) r_m(spectrum, camera)

with p_m the LED powers, f the core leak fraction and r_m (3,) the film's response to
LED m's spectrum (``pbr_tactile.render.source_response``). Powers, the leak and the
spectra cost no render. The medium (absorption, scattering), the coating, the contact's
shadow and the mechanics change the transport itself: each is rendered at the points of
a small grid (``GRIDS``, always through the simulation's own value), with the same seed
as the identity (common random numbers), on the taps the fit uses and, once fitted, on
the held-out taps at the grid points around the fitted value; between grid points the
per-source images are interpolated (geometrically for the medium's coefficients, whose
effect is close to exponential, linearly otherwise), and several re-rendered effects add
their changes.

A prediction of the real image is, as for the fast model (``studies.gap.model``),

    pred = image_stages(sim + up(M(theta) - M(identity)))

with M = clip(exposure_gain linear) the reference's image at the basis' film, ``up`` a
bilinear resampling to the working resolution, and the image stages (lens distortion and
vignetting as the reference applies them, ``pbr_tactile.sensor``; the unit's alignment,
blur and camera response) acting on the whole image.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from scenes.camera import Camera
from scenes.image_stats import low_passed_variance, mae_floor
from scenes.images import block_mean
from scenes.spec import SensorSpec

from . import effects as fx
from .optics import optics, working_cameras
from .physical import EXPOSURE, FAST_MODELS, UNPREDICTABLE_FIELDS, physical_catalogue
from .smoothing import LEAK_SMOOTH_PX, axially_smoothed, smoothed_change
from .source_basis import NO_CONTACT, SourceBasis

#: The reference model fits and judges its images low-passed by a Gaussian of this many
#: basis-film pixels (``ReferenceModel.compared``). The renders' Monte Carlo noise is
#: near white at the film's pixels; no candidate predicts it, but any that resamples the
#: simulation smooths its share: on the 12-case physical benchmark (seed 0), in four cases
#: whose gap was 85 to 97 % that noise, alignment closed 6 to 7 % of it, each time at about
#: (0.03, -0.1) px and 0.012 rad, and came first over a hidden compliance of 0.84 (and a
#: layer spread, a contact shadow, a 3 px defocus). A Gaussian of one pixel keeps what
#: the candidates change (a dent spans several film pixels, the LEDs' glow and the image
#: circle many), cuts white noise's MAE to about 0.28 of it, and leaves little for a
#: sub-pixel shift to smooth. The photon map's noise is not white (its kernel spans
#: neighbouring pixels: two renders of the same physics differ by 0.0037 there, against
#: 0.0024 from their variance maps as if independent), and a little more smoothing cuts
#: it further: on that benchmark's 17-effect draw, sigma 1 and 1.25 both ranked a hidden
#: effect first in 11 of 12 cases (all but the one whose gap is all noise), held-out
#: shrink 0.742 and 0.755; on a hidden leak of 0.3 they closed 49.3 % and 53.5 %. At 2,
#: on the earlier draw, the contact shadow lost its first place.
COMPARED_SIGMA_FILM_PX = 1.25
#: Above this condition number of the LEDs' responses (3 x 3), a change of the light's
#: colours is not applied to the simulated image as a colour matrix (``colour_matrix``)
#: but taken from the basis.
MAX_RESPONSE_CONDITION = 100.0
#: Fits of physical effects use at most this many training taps (each costs its renders).
#: With 4 and the grid at 2^16 photons (against 8 at the basis' 2^18), cases 0-3 of the
#: physical benchmark (seed 0) lost the hidden contact shadow's and scattering's first
#: place (absorption came first), and the shadow closed 6 % of its gap instead of 16 %.
FIT_TAPS = 8
#: Of the re-rendered candidates (each costs a render per held-out tap to judge), only
#: this many, those with the lowest training loss, are judged on the held-out taps; the
#: rest are reported as screened out (``selection.singles``). On a 36-pair capture, each
#: one judged costs 18 renders (about 6 minutes on 2 cores).
JUDGED_RENDERS = 2
#: Where more re-rendered candidates must trace their grid than ``JUDGED_RENDERS``, each
#: is fitted first on this many of the fit's taps (a screen: its grid traced on those
#: taps and the no-contact frame only), and only the ``JUDGED_RENDERS`` best there, by
#: the share of their training loss they remove, are fitted on all ``FIT_TAPS`` and
#: judged (``selection.singles``). On the 36-pair physical bench a grid value traced
#: again on 8 taps and the no-contact frame took 7 to 8 minutes, about 33 s a tap.
SCREEN_TAPS = 2
#: The capture's exposures every fit of a physical candidate is started from (the rule's,
#: and a third less or more): with the range above, a hidden LED peak shift of 18 nm
#: (with an absorption of 76 per m) started at the rule's alone was fitted at (3, -30, 6)
#: nm.
EXPOSURE_STARTS = (1.0, 0.7, 1.4)
#: The candidates that change only the light's colours (each LED's power and the film's
#: response to it), not where it goes: ``ReferenceModel.colour_matrix``.
COLOUR_FIELDS = ("led_power", "led_peak_shift", "led_spectra", "camera_response")
#: Candidates a unit's profile stands for (its per-LED gains and leak): not applicable to a
#: replay through one.
PROFILED_LIGHT = COLOUR_FIELDS + ("core_light_leak", "core_leak_cone_rad")


def _level(image: np.ndarray, mask: np.ndarray) -> float:
    """The exposure rule's level of a no-contact image: its EXPOSURE_PERCENTILE inside
    ``mask`` (``pbr_tactile.plugin``)."""
    from pbr_tactile.plugin import EXPOSURE_PERCENTILE

    return float(np.percentile(image[mask], EXPOSURE_PERCENTILE))


def _without_exposure(params: dict) -> dict:
    """``params`` without the capture's own exposure (``EXPOSURE``)."""
    return {k: {n: v for n, v in p.items() if n != EXPOSURE.name} for k, p in params.items()}


def _switch_response(spec: SensorSpec, led_spectra: bool, camera_response: bool) -> np.ndarray:
    """(M, 3) the film's response to each LED of ``spec`` per unit flux, with the two
    switches of the light's colours."""
    from pbr_tactile.effects import Effects
    from pbr_tactile.render import source_response
    from pbr_tactile.scene import led_sources

    effects = Effects(core_light_leak=0.0, led_spectra=led_spectra, camera_response=camera_response)
    return np.asarray(source_response(led_sources(spec, effects), effects), np.float64)


class ReferenceModel:
    """The reference of a ``pbr`` dataset at 1/``factor`` of its resolution, with the
    candidates of ``physical_catalogue``; the interface of ``studies.gap.model.FastModel``
    (``predict``, ``optics``, ``catalogue``, ``mask``), so ``studies.gap.fit`` fits either.

    basis : the shared ``SourceBasis`` (the working and the full-resolution model use one).
    """

    kind = "pbr"
    ties_to_simplest = True  # ``selection.rank``

    def __init__(self, spec: SensorSpec, renderer: dict, factor: int, basis: SourceBasis, profile=None):
        self.spec = spec
        self.profile = profile  # a replay through a unit's profile is imaged by its camera (``image``)
        self.renderer = renderer
        self.factor = int(factor)
        self.full_camera, self.camera = working_cameras(spec, self.factor)
        self.mask = self.camera.mask
        # The reference draws no image circle: an alignment moves the whole frame.
        self.circle = np.ones(self.camera.shape, np.float32)
        self.fixed = np.zeros(self.camera.shape + (3,), np.float32)
        self.basis = basis
        self.catalogue, self.kinds, self.grids = physical_catalogue(spec, basis.effects, spec.elastic.sigma_px)
        self.names = tuple(self.catalogue)
        self.stages = {n: e.stage for n, e in self.catalogue.items()}
        self.aliases = dict(FAST_MODELS)
        self.max_fit_samples = FIT_TAPS
        self.judged_renders = JUDGED_RENDERS
        self.screen_taps = SCREEN_TAPS
        self._responses: dict = {}
        self._unshifted: dict = {}  # the film's response to the spec's own LEDs, by switch (``responses``)
        self._plain: dict = {}  # M(identity) by sample
        self._rendered: dict = {}  # the basis' images with their leaks smoothed (``rendered``)
        self._level = None  # the identity's exposure level (``exposure``)
        self._exposures: dict = {}  # exposure gain by parameters (at most 17 kept)
        self._film_exposures: dict = {}  # the last image-stage effects' exposure ratio
        self._film = Camera.from_spec(spec).scaled(*basis.film)  # the basis' own camera

    # --- the FastModel interface ---------------------------------------------------------

    def working_images(self, images: np.ndarray) -> np.ndarray:
        return block_mean(np.asarray(images, np.float32), self.factor, (1, 2))

    def working_depth(self, depth: np.ndarray) -> np.ndarray:
        return depth  # renders read the full-resolution contacts by sample (``SourceBasis``)

    def compared(self, images: np.ndarray) -> np.ndarray:
        """(N, H, W, 3) images as the diagnosis fits and judges them: low-passed by a
        Gaussian of ``COMPARED_SIGMA_FILM_PX`` basis-film pixels per channel."""
        from scipy import ndimage

        sigma = self.compared_sigma_px
        return ndimage.gaussian_filter(np.asarray(images, np.float32), (0, sigma, sigma, 0), mode="nearest")

    @property
    def compared_sigma_px(self) -> float:
        """``COMPARED_SIGMA_FILM_PX`` in this model's pixels."""
        return COMPARED_SIGMA_FILM_PX * self.camera.shape[1] / self.basis.film[0]

    def not_applicable(self, pairs) -> dict[str, str]:
        out = {}
        if self.profile is not None:
            for name in PROFILED_LIGHT:
                if name in self.kinds:
                    out[name] = ("the simulated dataset was rendered through a calibrated unit's profile, whose "
                                 "per-LED gains and leak stand for the LEDs' powers, colours and leak")
        if pairs.depth is None:
            for name, kind in self.kinds.items():
                if kind in ("linear", "render", "bool-render", "bool-linear"):
                    out.setdefault(name, "the simulated dataset has no depth maps to re-render its contacts from")
        for name, why in UNPREDICTABLE_FIELDS.items():
            out.setdefault(name, why)
        for name, kind in self.kinds.items():
            if kind == "unpredictable":
                out.setdefault(name, f"Effects.{name} is not a number or a switch; it cannot be fitted")
        if self.basis.gain is None and self.profile is None:
            for name, kind in self.kinds.items():
                if kind not in ("fast", "image"):
                    out.setdefault(name, "the simulated dataset records no exposure_gain")
        if self.renderer.get("estimator", "photons") == "photons" and "coating_gloss" in self.kinds:
            out.setdefault("coating_gloss", "a glossy coating needs the volpath estimator, and the simulated dataset "
                                            "was rendered with photons (which needs a diffuse coating)")
        if any(led.peak_nm is None or led.fwhm_nm is None for led in self.spec.leds):
            for name in ("led_peak_shift", "led_spectra", "camera_response"):
                out.setdefault(name, "the sensor spec gives no LED peak_nm / fwhm_nm")
        return out

    def rerendered(self, name: str) -> bool:
        """Whether candidate ``name`` is evaluated from basis renders at its grid points."""
        return self.kinds[name] in ("render", "bool-render")

    def costly(self, name: str) -> bool:
        """Whether judging candidate ``name`` renders every held-out tap anew: a re-rendered
        candidate, unless each tap's identity render re-weights its photons to all of its
        grid points (``SourceBasis``: none of them traced again so far)."""
        if not self.rerendered(name):
            return False
        basis = self.basis
        reweighted = {n for n, _ in basis.variants}
        retraced = {key.split("=")[0] for key in basis.reweighting.get("retraced", {})}
        return name not in reweighted or name in retraced

    def starts(self, name: str) -> list[dict]:
        """Starting points of one candidate's fit: every grid point of a re-rendered one,
        both ends of a switch, a few values of the others, each at ``EXPOSURE_STARTS``
        (the fit goes on from the best of them)."""
        identity = self.catalogue[name].identity
        exposures = EXPOSURE_STARTS if EXPOSURE.name in identity else (None,)
        return [{**identity, **start, **({} if e is None else {EXPOSURE.name: e})}
                for start in self._starts(name) for e in exposures]

    def _starts(self, name: str) -> list[dict]:
        kind, base = self.kinds[name], dict(self.catalogue[name].identity)
        if kind == "render":  # a leak's cone with its own fraction starts from a leak
            own = {"fraction": 0.3} if "fraction" in base else {}
            return [{"value": v, **own} for v in self.grids[name]["values"]]
        if kind.startswith("bool-"):
            return [{"on": 0.0}, {"on": 1.0}]
        if name == "core_light_leak":
            return [base] + [{"fraction": f} for f in (0.1, 0.3, 0.6) if f != base["fraction"]]
        if name == "led_power":
            return [base] + [{k: s for k in base} for s in (0.7, 1.4)]
        if name == "led_peak_shift":
            return [base] + [{k: s for k in base} for s in (-10.0, 10.0)]
        if name == "vignetting":
            return [base] + [{"strength": s} for s in (0.2, 0.5)]
        if name == "lens_distortion":
            return [{**base, "k1": k} for k in (-0.2, -0.1, 0.0, 0.1, 0.2)]
        return [base]

    def optics(self, images: np.ndarray, params: dict) -> np.ndarray:
        """The image stages in ``params`` applied to (N, H, W, 3) images: the reference's
        lens distortion and vignetting (relative to the simulation's), then the unit's
        alignment, blur and camera response (the fast model's stages)."""
        from pbr_tactile import sensor

        out = np.asarray(images, np.float32)
        if "lens_distortion" in params:
            p = params["lens_distortion"]
            k0 = self.basis.effects.lens_distortion
            if (p["k1"], p["k2"]) != tuple(k0):
                out = np.stack([sensor.distort(sensor.distort(im, self.full_camera, -k0[0], -k0[1]),
                                               self.full_camera, p["k1"], p["k2"]) if any(k0) else
                                sensor.distort(im, self.full_camera, p["k1"], p["k2"]) for im in out])
        if "vignetting" in params:
            s, s0 = params["vignetting"]["strength"], self.basis.effects.vignetting
            if s != s0:
                one = np.ones(self.camera.shape + (1,), np.float32)
                ratio = sensor.vignetting(one, self.full_camera, s) / np.maximum(
                    sensor.vignetting(one, self.full_camera, s0), 1e-6)
                out = out * ratio[None]
        fast = {self.aliases[k]: v for k, v in params.items() if k in self.aliases}
        if "misalignment" in fast:
            fast["misalignment"] = {**fast["misalignment"], "frame_share": 1.0}
        return optics(out, fast, self.camera, self.factor, self.fixed, self.circle)

    def predict(self, sim: np.ndarray, depth, params: dict, keys=None) -> np.ndarray:
        """Predicted real images (N, H, W, 3) from simulated ones (sample ``keys``, indices
        into the dataset), with the candidates in ``params``."""
        physical = {k: v for k, v in params.items() if self.kinds[k] not in ("fast", "image")
                    and v != self.catalogue[k].identity}
        out = np.asarray(sim, np.float32)
        if physical:
            if keys is None:
                raise ValueError("the reference model predicts samples by key")
            out = out.copy()
            A = self.colour_matrix(physical)
            for i, key in enumerate(keys):
                if A is not None:
                    out[i] = self._recoloured(out[i], int(key), physical, A)
                    continue
                if key not in self._plain:
                    self._plain[key] = self.image(int(key), {})
                change = self.image(int(key), physical) - self._plain[key]
                out[i] += self._resized(change)
            out = np.clip(out, 0.0, 1.0)
        image_params = {k: v for k, v in params.items() if self.kinds[k] in ("fast", "image")}
        if not image_params:
            return out
        out = self.optics(out, image_params)
        film = {k: v for k, v in params.items() if self.kinds[k] == "image" and v != self.catalogue[k].identity}
        if film:  # the reference's own lens: its capture is exposed after it, by the rule and its own exposure
            scale = fx.exposure_scale(film)
            if self.basis.gain is not None:  # a unit's profile sets its camera once: no exposure rule to follow
                scale *= self._film_exposure(film, physical)
            out = np.clip(out * np.float32(scale), 0.0, 1.0)
        return out

    def basis_noise(self, keys) -> dict | None:
        """The basis' own Monte Carlo noise, as the diagnosis compares images: the MAE
        floor (sqrt(2 / pi) sigma per pixel, averaged over the film's image circle) of
        the identity image of each of ``keys`` already rendered, its per-source variances
        weighted by the dataset's exposure and colours, at the basis film and low-passed
        by ``COMPARED_SIGMA_FILM_PX`` (``compared``), pixels taken as independent (the
        photon map's are not, so it is a lower bound). None when none is rendered."""
        rendered = set(self.basis.rendered_keys())
        keys = [int(k) for k in keys if int(k) in rendered]
        if not keys or self.profile is not None:  # through a profile's camera the noise is not linear in it
            return None
        weight = (float(self.basis.gain) * self.colour({})) ** 2  # (S, 3)
        area = self._film.mask
        floors = []
        for key in keys:
            variance = np.tensordot(self.basis.variance(key), weight, axes=([2], [0]))
            floors.append(mae_floor(low_passed_variance(variance, COMPARED_SIGMA_FILM_PX), area))
        return {"mae_floor": float(np.mean(floors)), "mae_floor_max": float(np.max(floors)), "taps": len(keys),
                "photons": self.basis.photons, "spp": self.basis.spp, "passes": self.basis.passes,
                "inscatter": self.basis.inscatter}

    def _recoloured(self, sim: np.ndarray, key: int, physical: dict, A: np.ndarray) -> np.ndarray:
        """One simulated image (h, w, 3) with the ``physical`` candidates, before clipping:
        K sim + up(M(theta) - clip(g K linear(identity))), with K = g_c A / g the light's
        colours (``colour_matrix``) at the exposure they alone would have.

        The colours act on the simulated image itself, so that they add none of the
        basis' Monte Carlo noise; what else changes (the spread's re-rendered candidates,
        the leak, the exposure they bring and the capture's own) comes from the basis as a
        difference, so that the simulation's own noise is not scaled by that exposure.
        Measured on the physical benchmark: with every change taken from the basis,
        camera_gains beat camera_response off and led_spectra off; with the simulated
        image scaled by the whole exposure, an absorption of 98 per m (the rule's gain 3.4
        times higher) was fitted at 66."""
        gain = float(self.basis.gain)
        colours = {k: v for k, v in physical.items() if k in COLOUR_FIELDS}
        K = (self.exposure(colours, self.colour(colours)) / gain if colours else 1.0) * A
        identity = np.tensordot(self.sources(key, {}), self.colour({}), axes=([2], [0]))
        change = self.image(key, physical) - np.clip(np.tensordot(identity, gain * K, axes=([2], [1])), 0.0, 1.0)
        return np.tensordot(sim, K.astype(np.float32), axes=([2], [1])) + self._resized(change.astype(np.float32))

    def _film_exposure(self, film: dict, physical: dict) -> float:
        """The exposure rule's gain ratio for the reference's image-stage effects
        (vignetting, lens distortion) in ``film``: the no-contact frame (with the
        ``physical`` candidates) at its 99.5th percentile inside the image circle, before
        and after them."""
        key = repr((film, physical))
        if key not in self._film_exposures:
            before = self._resized(self.image(NO_CONTACT, physical))
            after = self.optics(before[None], _without_exposure(film))[0]
            ratio = _level(before, self.camera.mask) / max(_level(after, self.camera.mask), 1e-12)
            self._film_exposures = {key: float(ratio)}
        return self._film_exposures[key]

    # --- the reference per source ----------------------------------------------------------

    def _resized(self, image: np.ndarray) -> np.ndarray:
        if image.shape[:2] == self.camera.shape:
            return image
        from skimage.transform import resize

        return resize(image, self.camera.shape, order=1, mode="edge", anti_aliasing=False,
                      preserve_range=True).astype(np.float32)

    def sources(self, key: int, params: dict) -> np.ndarray:
        """(h, w, S) tap ``key``'s per-source images with the re-rendered candidates in
        ``params``: each one's change from the identity (``interpolated``), smoothed
        (``smoothed_change``), added; the leaks' images smoothed (``rendered``)."""
        base = self.rendered(key)
        out = base.copy()
        for name, p in params.items():
            if self.rerendered(name):
                value = float(p[self.catalogue[name].params[0].name])
                out += smoothed_change(self.interpolated(key, name, value), base)
        return np.maximum(out, 0.0)

    def rendered(self, key: int, name: str | None = None, value: float | None = None) -> np.ndarray:
        """``SourceBasis.images`` with each leak's image smoothed (``LEAK_SMOOTH_PX``), kept:
        a fit reads the same few renders many times."""
        tag = (int(key), name, None if value is None else float(value))
        if tag not in self._rendered:
            image = self.basis.images(key, name, value)
            from pbr_tactile.basis import is_leak

            leak = is_leak(self.basis.names)
            if leak.any():
                image = image.copy()
                image[..., leak] = axially_smoothed(image[..., leak], (self._film.cx, self._film.cy), LEAK_SMOOTH_PX)
            self._rendered[tag] = image
        return self._rendered[tag]

    def interpolated(self, key: int, name: str, value: float) -> np.ndarray:
        """(h, w, S) tap ``key``'s per-source images with re-rendered candidate ``name`` at
        ``value``, interpolated between its grid points (clipped to the grid)."""
        base = self.rendered(key)
        grid = self.grids[name]
        values = np.asarray(grid["values"])
        value = float(np.clip(value, values[0], values[-1]))
        j = int(np.clip(np.searchsorted(values, value), 1, len(values) - 1))
        a, b = values[j - 1], values[j]
        t = 0.0 if b == a else (value - a) / (b - a)
        # A grid point of no weight is not rendered (a fit at the identity, or at a grid point).
        at = a if t == 0.0 else b if t == 1.0 else None
        if at is not None:
            return (self.rendered(key, name, at) if at != self._identity_value(name) else base).astype(np.float32)
        A = self.rendered(key, name, a) if a != self._identity_value(name) else base
        B = self.rendered(key, name, b) if b != self._identity_value(name) else base
        image = (1 - t) * A + t * B
        if grid.get("interpolation") == "geometric":  # where both are lit; linear where either is dark
            tiny = np.float32(1e-6 * max(float(base.max()), 1e-12))
            lit = np.minimum(A, B) > tiny
            image[lit] = np.exp((1 - t) * np.log(A[lit]) + t * np.log(B[lit]))
        return image.astype(np.float32)

    def _identity_value(self, name: str) -> float:
        return float(self.catalogue[name].identity[self.catalogue[name].params[0].name])

    def responses(self, shifts: tuple[float, ...], spectra: float, camera: float) -> np.ndarray:
        """(M, 3) the film's response to each LED's light per unit flux, its peak shifted by
        ``shifts`` nm; ``spectra`` and ``camera`` blend Effects.led_spectra and
        Effects.camera_response off (0) and on (1).

        Each combination of the two switches is blended at the identity's total response
        (the exposure rule ignores a total): the ideal camera's response is about 60 times
        smaller than the real one's, so a plain blend put most of a switch's change in its
        first thousandth, and L-BFGS-B stopped there, leaving the exposure unfitted."""
        key = (tuple(round(s, 9) for s in shifts), spectra, camera)
        if key in self._responses:
            return self._responses[key]
        leds = tuple(dataclasses.replace(led, peak_nm=led.peak_nm + s) if s else led
                     for led, s in zip(self.spec.leds, shifts))
        spec = self.spec.replace(leds=leds) if any(shifts) else self.spec

        def unshifted(on_s: bool, on_c: bool) -> np.ndarray:  # four at most: kept
            if (on_s, on_c) not in self._unshifted:
                self._unshifted[on_s, on_c] = _switch_response(self.spec, on_s, on_c)
            return self._unshifted[on_s, on_c]

        identity = unshifted(bool(self.catalogue["led_spectra"].identity["on"]),
                             bool(self.catalogue["camera_response"].identity["on"]))
        out = 0.0
        for on_s, w_s in ((True, spectra), (False, 1.0 - spectra)):
            for on_c, w_c in ((True, camera), (False, 1.0 - camera)):
                if w_s * w_c == 0:
                    continue
                total = unshifted(on_s, on_c).sum()  # unshifted: a shift keeps its own change
                shifted = unshifted(on_s, on_c) if spec is self.spec else _switch_response(spec, on_s, on_c)
                out = out + w_s * w_c * shifted * (identity.sum() / total)
        self._responses[key] = np.asarray(out, np.float64)
        return self._responses[key]

    def _light(self, params: dict) -> tuple[np.ndarray, np.ndarray, float]:
        """The light of ``params``: (M,) LED powers, (M, 3) the film's response to each
        LED, and the core leak fraction (each at the identity where ``params`` has none; a leak
        cone's own fraction where it has one and core_light_leak is not in ``params``)."""
        n = len(self.spec.leds)
        p = {name: params.get(name, self.catalogue[name].identity) for name in
             ("core_light_leak", "led_power", "led_peak_shift", "led_spectra", "camera_response")
             if name in self.catalogue}
        power = np.array([p["led_power"][f"power_{m}"] for m in range(n)], np.float64)
        shifts = tuple(p["led_peak_shift"][f"shift_nm_{m}"] for m in range(n))
        R = self.responses(shifts, p["led_spectra"]["on"], p["camera_response"]["on"])
        fraction = p["core_light_leak"]["fraction"]
        cone = params.get("core_leak_cone_rad", {})
        if "fraction" in cone and "core_light_leak" not in params:  # a leak of its own (``physical_catalogue``)
            fraction = cone["fraction"]
        return power, R, float(fraction)

    def colour(self, params: dict) -> np.ndarray:
        """(S, 3) each source's share in each channel with ``params``."""
        from pbr_tactile.basis import is_leak, led_of_source

        power, R, fraction = self._light(params)
        if self.basis.names is None:
            self.basis.images(NO_CONTACT)  # the basis' source names
        led = led_of_source(self.basis.names)
        weight = np.array([power[m] * (fraction if leak else 1.0 - fraction)
                           for leak, m in zip(is_leak(self.basis.names), led)])
        return weight[:, None] * R[led]

    def colour_matrix(self, params: dict) -> np.ndarray | None:
        """(3, 3) A with linear(theta) = A linear(identity) wherever the light's spread is
        the identity's, or None where no such matrix is exact.

        The transport is grey, so a pixel's linear colour is sum_m s_m r_m, with s_m the
        light of LED m (and of its leak) that reaches it and r_m (3,) the film's response
        to LED m. Powers, spectra and the camera's response change only p_m r_m; with as
        many LEDs as channels and r invertible, s = (R_0^T)^-1 linear and
        A = R^T diag(p) (R_0^T)^-1. Applied to the simulated image itself, a prediction
        of these carries none of the basis' Monte Carlo noise."""
        if self.profile is not None:  # the profile's camera is not linear
            return None
        power0, R0, _ = self._light({})
        if R0.shape != (3, 3) or np.linalg.cond(R0) > MAX_RESPONSE_CONDITION:
            return None
        power, R, _ = self._light(params)
        return R.T @ np.diag(power / power0) @ np.linalg.inv(R0.T)

    def image(self, key: int, params: dict) -> np.ndarray:
        """(h, w, 3) M(theta) of tap ``key`` at the film: clip(exposure_gain linear); through
        a unit's profile, its camera's image of the per-source light
        (``pbr_tactile.profiled.profiled_image``)."""
        if self.profile is not None:
            from pbr_tactile.profiled import profiled_image

            linear = self.sources(key, params) * np.float32(fx.exposure_scale(params))
            return profiled_image(linear, self.basis.names, self.profile, self.full_camera).astype(np.float32)
        colour = self.colour(params)
        linear = np.tensordot(self.sources(key, params), colour, axes=([2], [0]))  # (h, w, 3)
        return np.clip(fx.exposure_scale(params) * self.exposure(params, colour) * linear, 0.0, 1.0).astype(np.float32)

    def exposure(self, params: dict, colour: np.ndarray) -> float:
        """The dataset's exposure gain with ``params``: a reference dataset sets its one
        exposure from its own no-contact frame (``pbr_tactile.plugin``: its
        EXPOSURE_PERCENTILE inside the image circle to EXPOSURE_LEVEL), so a capture whose
        physics differ is exposed differently: g(theta) = g(identity) level(identity) /
        level(theta), the levels from the no-contact per-source images."""

        def level(p: dict, c: np.ndarray) -> float:
            return _level(np.tensordot(self.sources(NO_CONTACT, p), c, axes=([2], [0])), self._film.mask)

        if not params:
            return float(self.basis.gain)
        if self._level is None:
            self._level = level({}, self.colour({}))
        key = repr(_without_exposure(params))  # one exposure for every tap of a prediction, whatever EXPOSURE
        if key not in self._exposures:
            if len(self._exposures) > 16:
                self._exposures.clear()
            self._exposures[key] = float(self.basis.gain * self._level / max(level(params, colour), 1e-30))
        return self._exposures[key]
