"""The reference rendered as a calibrated unit: a profile's effects, and its per-source
images turned into the unit's image by the profile's gains, alignment and camera."""

from __future__ import annotations

import dataclasses

import numpy as np

from scenes.camera import Camera
from scenes.profile import Profile
from scenes.spec import SensorSpec

from .basis import BASIS_EFFECTS
from .effects import Effects
from .image_model import ImageModel, Nonlinear

def profile_effects(profile: Profile, settings: list[str] | None = None) -> Effects:
    """The reference's effects of a profile (with the leak sources the basis needs),
    then ``settings`` (NAME=VALUE) on top."""
    fitted = {k: v for k, v in profile.reference.get("effects", {}).items()}
    try:
        effects = dataclasses.replace(Effects(), **fitted)
    except TypeError as exc:
        raise ValueError(f"profile reference.effects: {exc}") from None
    effects = effects.with_settings([f"{k}={v}" for k, v in BASIS_EFFECTS.items()])
    return effects.with_settings(settings or [])


def reference_spec(profile: Profile, spec: SensorSpec) -> SensorSpec:
    """``spec`` as the reference renders this unit: its LEDs laid out as the calibration
    fitted them (``reference.layout``, ``scenes.layout``; none: the spec's), then turned
    and its image circle set as for every renderer (``Profile.sensor_spec``)."""
    from scenes.layout import layout_from_dicts, with_layout

    profile.check(spec)
    layout = profile.reference.get("layout")
    if layout is not None:
        spec = with_layout(spec, layout_from_dicts(layout, spec, "profile reference.layout"))
    return profile.sensor_spec(spec)


def profiled_image(per_source: np.ndarray, names, profile: Profile, camera: Camera) -> np.ndarray:
    """(h, w, S) per-source linear images (``reference`` with ``RenderSettings(per_source=True)``) of
    ``profile.sensor_spec``, whose LEDs are already turned, with ``profile_effects``) ->
    (h, w, 3) the calibrated sensor's image in [0, 1]."""
    ref = profile.reference
    try:
        gains = np.asarray(ref["led_gains"], np.float64)
        leds = len(ref["led_leak"])
        k1 = camera.k1 if profile.alignment.distortion is None else profile.alignment.distortion[0]
        nl = Nonlinear(profile.alignment.rotation_rad, (0.0,) * leds, tuple(ref["led_leak"]),
                       profile.alignment.scale, profile.alignment.shift_px, profile.camera.vignetting,
                       profile.camera.gamma, k1=float(k1))
    except KeyError as exc:
        raise ValueError(f"the profile has no reference.{exc.args[0]}: it was not calibrated for the reference") from None
    model = ImageModel(per_source, names, camera, profile.camera.image_circle)
    if gains.shape != (model.leds, 3) or len(nl.led_azimuth_rad) != model.leds or len(nl.leak) != model.leds:
        raise ValueError(f"the profile's reference tables are for {gains.shape[0]} LEDs, the render has {model.leds}")
    return model.render(nl, gains, profile.camera.offset, profile.camera.saturation)
