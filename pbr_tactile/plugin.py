"""The physically based reference as a dataset renderer plugin (entry point ``tactile_sim.renderers``).

Every sample is rendered to a noise target: passes are added until the RMS relative
standard error over the contact region (``pbr_tactile.render.contact_region``) is at most
``target_rse``. Contacts use the no-contact control variate (``pbr_tactile.nocontact``):
``prepare``, which runs once on the driver, renders the no-contact frame with every pass
a contact may use, which fills the sensor's no-contact photon cache and sets the
dataset's one exposure; ``shared`` hands the deposits (a dict of arrays) to the workers,
which then trace only each contact's own photons, with no disk shared between them.

Every sample uses the same seeds, so the contacts share random numbers with the
no-contact frame and with each other (common random numbers: far from a contact a
sample's noise is the no-contact frame's, the same in every sample). The image itself
is estimated against the frame too (``pbr_tactile.render.Control``): each contact pass
minus the frame's pass of the same seed, plus the frame's mean, which has
CONTROL_SPP_FACTOR times more camera samples. Measured on three base taps at 320x240
(8 passes each), this cut the per-pass RMS error over the contact region from 0.127 to
0.085 (dots), 0.079 to 0.046 (sphere) and 0.071 to 0.038 (cylinder), mostly by
cancelling the rare, bright camera samples that see an LED through the glass.

The camera reads the light the elastomer scatters towards it from the photons' fluence
(option ``inscatter``, default "fluence"; ``pbr_tactile.fluence``) instead of splitting
its paths at the first scattering event ("split", the estimator before it): those LED
samples are then not drawn at all, the camera pass costs a fifth, and the fluence of a
pass is formed from the no-contact cache as its photon map is.

With a calibrated unit's profile (option ``profile``, a ``profile.toml`` of ``tactile-sim
calibrate``) the scene is the unit's (``Profile.sensor_spec``: its LEDs turned, its image
circle) with the profile's effects (``calibrate.profile_effects``, then the option
``effects`` on top), every pass is rendered one grey image per source (the frame and its
control variate too), and each image is the unit's camera applied to them
(``calibrate.profiled_image``: the fitted gains, alignment, response and clipping)
instead of the dataset's exposure; ``linear`` and ``variance`` then hold one channel per
source.
"""

from __future__ import annotations

import dataclasses
import math
import time

import numpy as np

from scenes.camera import CONTACT_EPS_M, Camera, check_depth
from scenes.spec import SensorSpec

from .camera_pass import CAMERA_PASS_VERSION
from .effects import Effects
from .estimate import MIN_PASSES, Control, Estimate, contact_rse
from .fluence import INSCATTER
from .membrane import shared_builder
from .nocontact import CACHE_VERSION
from .render import RenderSettings, reference

#: The dataset's ``source`` (scenes.dataset.SOURCES) for this renderer.
SOURCE = "pbr"
#: Options and their defaults (timed on 2 cores for the fewest seconds to 5 % noise).
#: A dataset's first run renders the no-contact frame with every pass a contact may
#: use, each with no_contact_runs + 1 no-contact runs: 8 passes and 4 runs keep that
#: one-time cost near 3 minutes at 2^18 photons (16 and 8 took 20 at 2^19). With the
#: fluence lookup a contact reaches 5 % in 2-3 passes at 2^18 photons (median contact
#: RSE 0.040 on the benchmark's 16 taps; 2^19 gave 0.029, all at 2 passes, at twice the
#: photon cost: ``tactile-sim bench dataset --renderer pbr``).
DEFAULTS = {
    "target_rse": 0.05,
    "max_passes": 8,
    "effects": [],
    "estimator": "photons",
    "inscatter": "fluence",
    "photons": 1 << 18,
    "camera_spp": 16,
    "kernel_radius_mm": 0.75,
    "no_contact_runs": 4,
    "film": [320, 240],
    "seed": 0,
    "profile": None,
    "led_power": None,
    "elastic": None,
}
#: The no-contact frame's EXPOSURE_PERCENTILE inside the image circle maps to this value.
EXPOSURE_LEVEL = 0.8
EXPOSURE_PERCENTILE = 99.5
#: Bump when the cached no-contact frame (scenes.cache "pbr-dataset-frame") changes meaning.
FRAME_VERSION = 4
#: Cache entries of the frame that hold no-contact deposits start with this.
DEPOSIT_PREFIX = "deposit_"
#: Cache entries of the frame that hold its control variate (pbr_tactile.render.Control).
CONTROL_PREFIX = "control_"
#: The control's mean adds this many times camera_spp camera samples to each pass of the
#: no-contact frame. Its variance is in every contact's error, and the camera side holds
#: the frame's rare bright samples (LEDs seen through the glass): measured on three base
#: taps at 320x240, the 8-pass frame alone put 0.022-0.050 of RMS error into the contact
#: regions (a 5 % target leaves little beside it).
CONTROL_SPP_FACTOR = 4
RESAMPLING = ("bilinear (skimage.transform.resize, order 1) from the film to the camera's size; the variance is "
              "resampled the same way, which bounds the resampled mean's variance from above whatever the "
              "correlation between film pixels (Jensen: var(sum w_i x_i) <= sum w_i var(x_i))")


def _whole(options: dict, name: str, minimum: int) -> int:
    value = options[name]
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < minimum:
        raise ValueError(f"option {name} must be a whole number >= {minimum}, got {value!r}")
    return int(value)


def _real(options: dict, name: str, minimum: float, strict: bool) -> float:
    value = options[name]
    ok = isinstance(value, (int, float, np.number)) and not isinstance(value, bool) and math.isfinite(value)
    if not ok or value < minimum or (strict and value == minimum):
        raise ValueError(f"option {name} must be a finite number {'>' if strict else '>='} {minimum:g}, got {value!r}")
    return float(value)


def default_film(camera: Camera) -> list[int]:
    """The film a camera renders at by default: DEFAULTS' height (240 rows: half the
    GelTip's), or the camera's own where it has fewer, at the camera's aspect ratio."""
    height = min(camera.height, DEFAULTS["film"][1])
    width = camera.width * height // camera.height
    return [width, height] if width * camera.height == height * camera.width else [camera.width, camera.height]


def _film(value, camera: Camera) -> tuple[int, int]:
    expected = (f"option film must be [width, height] in pixels with the camera's aspect ratio, at most "
                f"{camera.width}x{camera.height} (e.g. [{camera.width // 2}, {camera.height // 2}])")
    try:
        width, height = value
        ok = all(isinstance(v, (int, np.integer)) and not isinstance(v, bool) for v in (width, height))
    except (TypeError, ValueError):
        ok = False
    if not ok:
        raise ValueError(f"{expected}, got {value!r}")
    if not (0 < width <= camera.width and 0 < height <= camera.height) or width * camera.height != height * camera.width:
        raise ValueError(f"{expected}, got {width}x{height}")
    return int(width), int(height)


def options_from(options: dict, camera: Camera) -> dict:
    """Validated options, defaults filled in: effects as an Effects, film as (width, height)."""
    unknown = sorted(set(options) - set(DEFAULTS))
    if unknown:
        raise ValueError(f"the pbr renderer takes no option {', '.join(unknown)}; its options are "
                         f"{', '.join(DEFAULTS)}")
    given = {**DEFAULTS, **options}
    opts = {
        "target_rse": _real(given, "target_rse", 0.0, strict=True),
        "max_passes": _whole(given, "max_passes", MIN_PASSES),
        "photons": _whole(given, "photons", 1),
        "camera_spp": _whole(given, "camera_spp", 1),
        "kernel_radius_mm": _real(given, "kernel_radius_mm", 0.0, strict=False),
        "no_contact_runs": _whole(given, "no_contact_runs", 0),
        "film": _film(given["film"] if "film" in options else default_film(camera), camera),
        "seed": _whole(given, "seed", 0),
    }
    estimator = given["estimator"]
    if estimator not in ("photons", "volpath"):
        raise ValueError(f"option estimator must be 'photons' or 'volpath', got {estimator!r}")
    opts["estimator"] = estimator
    if given["inscatter"] not in INSCATTER:
        raise ValueError(f"option inscatter must be one of {', '.join(map(repr, INSCATTER))}, "
                         f"got {given['inscatter']!r}")
    opts["inscatter"] = given["inscatter"]
    settings = given["effects"]
    if isinstance(settings, str) or not all(isinstance(item, str) for item in settings):
        raise ValueError(f"option effects must be a list of NAME=VALUE strings, got {settings!r}")
    try:
        effects = Effects().with_settings(list(settings))
    except ValueError as exc:
        raise ValueError(f"option effects: {exc}") from None
    if estimator == "volpath" and not effects.contact_shadow:
        raise ValueError("option effects: contact_shadow=false needs estimator photons")
    opts["effects"] = effects
    opts["effect_settings"] = list(settings)
    profile = given["profile"]
    if profile is not None and not isinstance(profile, str):
        raise ValueError(f"option profile must be the path of a profile.toml, got {profile!r}")
    if profile is not None and estimator != "photons":
        raise ValueError("option profile needs estimator photons (it renders one image per source)")
    opts["profile"] = profile
    power = given["led_power"]
    if power is not None and (isinstance(power, str) or not isinstance(power, (list, tuple))):
        raise ValueError(f"option led_power must be a list of each LED's radiance scale, got {power!r}")
    if power is not None and profile is not None:
        raise ValueError("option led_power cannot go with a profile (the profile's gains are its LEDs' powers)")
    opts["led_power"] = None if power is None else list(power)
    opts["elastic"] = elastic_option(given["elastic"])
    return opts


def elastic_option(value) -> dict | None:
    """The dent the reference renders: None or "layer", the layer model's; "bonded", the
    bonded layer's with the spec's thickness and ratio; or a joint fit's entry
    ``{"model": "bonded", "thickness_m", "poisson_ratio"}``. ValueError naming anything else."""
    if value is None or value == "layer":
        return None
    if value == "bonded":
        return {"model": "bonded", "thickness_m": None, "poisson_ratio": None}
    if isinstance(value, dict) and value.get("model") == "bonded":
        from scenes.elastic_solid import check_material

        try:
            thickness, poisson = float(value["thickness_m"]), float(value["poisson_ratio"])
        except (KeyError, TypeError, ValueError):
            raise ValueError(f"option elastic must give thickness_m and poisson_ratio, got {value!r}") from None
        check_material(thickness, poisson)
        return {"model": "bonded", "thickness_m": thickness, "poisson_ratio": poisson}
    raise ValueError(f"option elastic must be 'layer', 'bonded' or a bonded layer's entry {{model, thickness_m, "
                     f"poisson_ratio}}, got {value!r}")


def _led_power(spec: SensorSpec, opts: dict):
    """The LEDs' radiance scales of validated options (``scene.led_powers``): 1 for each
    LED unless the option gives one per LED."""
    from .scene import led_powers

    return 1.0 if opts["led_power"] is None else led_powers(spec, opts["led_power"])


def unit_of(spec: SensorSpec, camera: Camera, opts: dict):
    """(the spec rendered, its camera, the effects, the Profile or None) of validated
    options: without a profile the spec and camera handed in, as they are
    (``scenes.renderers``' contract); with one, the unit's (module doc)."""
    if opts["profile"] is None:
        return spec, camera, opts["effects"], None
    from scenes.profile import load_profile

    from .profiled import profile_effects, reference_spec

    profile = load_profile(opts["profile"], spec)
    unit = reference_spec(profile, spec)
    try:
        effects = profile_effects(profile, opts["effect_settings"])
    except ValueError as exc:
        raise ValueError(f"option effects: {exc}") from None
    return unit, Camera.from_spec(unit), effects, profile


def _frame(spec: SensorSpec, mesh, camera: Camera, opts: dict) -> dict[str, np.ndarray]:
    """The no-contact frame rendered as the contacts are, with all max_passes passes, and
    the no-contact deposits it used (every one a contact may need), cached on disk."""
    from scenes.cache import cached, make_key

    from .variant import choose_variant

    variant = choose_variant().variant()
    if opts["estimator"] == "photons" and not variant.startswith(("llvm_", "cuda_")):
        raise ValueError(f"option estimator: photons needs a vectorised (llvm_ or cuda_) Mitsuba variant, got "
                         f"{variant}; apt-get install libllvm19, or use estimator volpath")
    spec, camera, effects, profile = unit_of(spec, camera, opts)
    power = _led_power(spec, opts)  # checked before any work
    frame_opts = {k: v for k, v in opts.items() if k not in ("target_rse", "effect_settings", "profile")
                  and not (k == "led_power" and v is None)}  # the LEDs' own powers: the keys frames had before
    frame_opts["effects"] = effects.to_dict()  # the frame has every pass; the unit's spec is in the key
    frame_opts["per_source"] = profile is not None
    own = camera == Camera.from_spec(spec)  # the spec's camera is in the spec: keys as before
    key = make_key(FRAME_VERSION, CACHE_VERSION, CAMERA_PASS_VERSION, variant, dataclasses.asdict(spec),
                   np.asarray(mesh.vertices), np.asarray(mesh.faces), frame_opts,
                   *([] if own else [dataclasses.asdict(camera)]))
    width, height = opts["film"]

    def build():
        memo: dict = {}
        photons = opts["estimator"] == "photons"
        settings = RenderSettings(spp=opts["camera_spp"] * opts["max_passes"], width=width, height=height,
                                  seed=opts["seed"], variant=variant, passes=opts["max_passes"],
                                  estimator=opts["estimator"], photons=opts["photons"],
                                  kernel_radius=opts["kernel_radius_mm"] * 1e-3,
                                  no_contact_runs=opts["no_contact_runs"],
                                  control_spp=opts["camera_spp"] * CONTROL_SPP_FACTOR if photons else 0,
                                  per_source=profile is not None, inscatter=opts["inscatter"])
        est = reference(None, None, mesh, spec, camera, effects, settings, led_power=power, no_contact_memo=memo)
        rse = contact_rse(est, camera.scaled(width, height).mask)
        control = {} if est.control is None else {CONTROL_PREFIX + k: getattr(est.control, k)
                                                  for k in ("images", "mean", "variance")}
        return {"mean": est.mean, "variance": est.variance, "rse": np.float64(rse), "spp": np.int64(est.spp),
                "variant": np.array(variant), **control, **{DEPOSIT_PREFIX + k: v for k, v in memo.items()}}

    return cached("pbr-dataset-frame", key, build)


def _shared(spec: SensorSpec, mesh, camera: Camera, opts: dict) -> dict:
    frame = _frame(spec, mesh, camera, opts)
    width, height = opts["film"]
    gain = None  # with a profile, the unit's camera sets the image
    if opts["profile"] is None:
        level = float(np.percentile(frame["mean"][camera.scaled(width, height).mask], EXPOSURE_PERCENTILE))
        if not level > 0:
            raise ValueError("the no-contact frame is black inside the image circle: no exposure can be set")
        gain = float(f"{EXPOSURE_LEVEL / level:.3g}")  # rounded: a re-render differs in its last bits
    return {
        "variant": str(frame["variant"]),
        "exposure_gain": gain,
        "no_contact": {key: frame[key] for key in ("mean", "variance", "rse", "spp")},
        "control": {k[len(CONTROL_PREFIX):]: v for k, v in frame.items() if k.startswith(CONTROL_PREFIX)} or None,
        "deposits": {k[len(DEPOSIT_PREFIX):]: v for k, v in frame.items() if k.startswith(DEPOSIT_PREFIX)},
    }


def shared(spec: SensorSpec, mesh, camera: Camera, options: dict) -> dict:
    """What every worker needs from the driver, picklable: the Mitsuba variant, the
    exposure gain, the no-contact frame and its photon deposits by cache key (arrays)."""
    return _shared(spec, mesh, camera, options_from(options, camera))


def prepare(spec: SensorSpec, mesh, camera: Camera, options: dict) -> dict:
    """Validate the options, render (or read from the cache) the no-contact frame, which
    fills the no-contact photon cache and sets the exposure, and return the settings
    recorded in dataset.json's ``renderer``."""
    opts = options_from(options, camera)
    inputs = _shared(spec, mesh, camera, opts)
    width, height = opts["film"]
    photons = opts["estimator"] == "photons"  # only it takes the frame as a control
    unit, _, effects, profile = unit_of(spec, camera, opts)
    if profile is not None:
        from .scene import led_sources

        names = [src["name"] for src in led_sources(unit, effects)]
        unit_settings = {
            "profile": opts["profile"], "profile_data": profile.to_dict(), "effects": effects.to_dict(),
            "exposure_gain": None, "sources": names,
            "exposure": "the calibrated unit's camera (pbr_tactile.profiled.profiled_image of the per-source images: "
                        "the profile's gains, alignment, lens fall-off, response and clipping), no dataset exposure",
            "linear": f"linear/<id>.npy: (H, W, {len(names)}) float32, one grey image per source ({', '.join(names)}) "
                      "per unit flux, at the camera's size; variance/<id>.npy: the variance of that mean"}
    else:
        unit_settings = {}
    return {
        "renderer": "pbr",
        "estimator": opts["estimator"],
        "inscatter": opts["inscatter"] if photons else None,
        "target_rse": opts["target_rse"],
        "noise": "passes are added until the RMS relative standard error over the contact region (the dent and "
                 "its rim; the image circle without contact) is at most target_rse, from min_passes to max_passes"
                 + ("; each contact pass is estimated against the no-contact frame's pass of the same seed (a "
                    "control variate: pass minus frame pass, plus the frame's mean, whose variance is included)"
                    if photons else ""),
        "control_spp_factor": CONTROL_SPP_FACTOR if photons else None,
        "min_passes": MIN_PASSES,
        "max_passes": opts["max_passes"],
        "photons": opts["photons"],
        "camera_spp": opts["camera_spp"],
        "kernel_radius_mm": opts["kernel_radius_mm"],
        "no_contact_runs": opts["no_contact_runs"],
        "seed": opts["seed"],
        **({"led_power": opts["led_power"]} if opts["led_power"] is not None else {}),
        "film": [width, height],
        "resampling": None if (width, height) == (camera.width, camera.height) else
        f"rendered at {width}x{height} (a quarter of the camera time per halving of each side) and resampled "
        f"{RESAMPLING}",
        "effects": opts["effects"].to_dict(),
        "exposure_gain": inputs["exposure_gain"],
        "exposure": f"image = clip(exposure_gain * linear, 0, 1); the gain maps the no-contact frame's "
                    f"{EXPOSURE_PERCENTILE}th percentile inside the image circle to {EXPOSURE_LEVEL}, set once for "
                    "the dataset",
        "linear": "linear/<id>.npy: (H, W, 3) float32 mean radiance in the reference's units (film response to "
                  "LED-flux-normalised radiance), at the camera's size; variance/<id>.npy: the variance of that mean",
        "variant": inputs["variant"],
        **unit_settings,
    }


class PbrDatasetRenderer:
    """Depth map -> tactile image with the physically based reference, to a noise target."""

    def __init__(self, spec: SensorSpec, mesh, camera: Camera, ref_depth: np.ndarray, opts: dict, inputs: dict):
        self.ref_depth = check_depth(np.asarray(ref_depth), camera, "ref_depth")
        spec, camera, self.effects, self.profile = unit_of(spec, camera, opts)  # with a profile, the unit's
        self.spec, self.mesh, self.camera, self.opts = spec, mesh, camera, opts
        self.led_power = _led_power(spec, opts)
        if self.profile is not None:
            from .scene import led_sources

            self.names = [src["name"] for src in led_sources(spec, self.effects)]
        self.variant = inputs["variant"]
        self.gain = inputs["exposure_gain"]
        frame = inputs["no_contact"]
        self._frame = Estimate(frame["mean"], frame["variance"], int(frame["spp"]), opts["max_passes"],
                               float(frame["rse"]))
        self._memo = dict(inputs["deposits"])  # read first, then filled by any miss
        self._control = None if inputs["control"] is None else Control(**inputs["control"])
        self._solids = shared_builder(mesh, spec, camera, elastic=opts["elastic"])  # refined, checked once per process

    def camera_size(self, image: np.ndarray) -> np.ndarray:
        """A film-sized (h, w, 3) image at the camera's (H, W, 3), float32 (see RESAMPLING)."""
        if image.shape[:2] == self.camera.shape:
            return np.asarray(image, np.float32)
        from skimage.transform import resize

        return resize(image, self.camera.shape, order=1, mode="edge", anti_aliasing=False,
                      preserve_range=True).astype(np.float32)

    def _image(self, linear: np.ndarray) -> np.ndarray:
        if self.profile is not None:
            from .profiled import profiled_image

            return profiled_image(linear, self.names, self.profile, self.camera).astype(np.float32)
        # the spec's image circle: the lens draws nothing outside it (a profile states its own)
        return (np.clip(self.gain * linear, 0.0, 1.0) * self.camera.mask[..., None]).astype(np.float32)

    @property
    def no_contact(self) -> np.ndarray:
        """(H, W, 3) float32 in [0, 1]: the no-contact frame, at the dataset's exposure."""
        return self._image(self.camera_size(self._frame.mean))

    def render_sample(self, depth: np.ndarray) -> dict:
        """A contact depth map (H, W) float, metres -> image, arrays and record (see
        the module doc and docs/dataset-format.md)."""
        t0 = time.perf_counter()
        depth = check_depth(np.asarray(depth), self.camera)
        touched = np.abs(depth - self.ref_depth) > CONTACT_EPS_M
        if not touched.any():
            est = self._frame  # no contact: the no-contact frame, with every pass
        else:
            opts = self.opts
            width, height = opts["film"]
            settings = RenderSettings(spp=opts["camera_spp"] * MIN_PASSES, width=width, height=height,
                                      seed=opts["seed"], variant=self.variant, passes=MIN_PASSES,
                                      estimator=opts["estimator"], photons=opts["photons"],
                                      kernel_radius=opts["kernel_radius_mm"] * 1e-3,
                                      no_contact_runs=opts["no_contact_runs"], target_rse=opts["target_rse"],
                                      max_passes=opts["max_passes"], per_source=self.profile is not None,
                                      inscatter=opts["inscatter"])
            est = reference(np.where(touched, depth, self.ref_depth), self.ref_depth, self.mesh, self.spec,
                            self.camera, self.effects, settings, led_power=self.led_power, control=self._control,
                            solids=self._solids, no_contact_memo=self._memo)
        linear = self.camera_size(est.mean)
        rse = est.rse if est.rse is not None and math.isfinite(est.rse) else None
        return {
            "image": self._image(linear),
            "arrays": {"linear": linear, "variance": self.camera_size(est.variance)},
            "record": {"contact_rse": rse, "passes": int(est.passes), "spp": int(est.spp),
                       "seconds": time.perf_counter() - t0},
        }

    def render(self, depth: np.ndarray) -> np.ndarray:
        """(H, W, 3) float32 image in [0, 1] of a contact depth map."""
        return self.render_sample(depth)["image"]


def make_renderer(spec: SensorSpec, mesh, camera: Camera, ref_depth: np.ndarray, options: dict,
                  shared: dict | None = None) -> PbrDatasetRenderer:
    """The renderer of one worker; ``shared`` from ``shared()`` on the driver (None:
    read from this machine's cache, which ``prepare`` filled)."""
    opts = options_from(options, camera)
    inputs = shared if shared is not None else _shared(spec, mesh, camera, opts)
    return PbrDatasetRenderer(spec, mesh, camera, ref_depth, opts, inputs)
