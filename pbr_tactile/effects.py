"""Physical effects of the reference, each a named switch.

The virtual rig and the sim-to-real gap diagnosis turn these on and off; every field is
documented with its unit, and ``Effects()`` is the full physical model.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, fields, replace

#: The accepted range [low, high] of each numeric effect (of each component, for a
#: pair); an infinite end is open: values must be finite. Effects() refuses the rest.
RANGES = {
    "core_light_leak": (0.0, 1.0),
    "core_leak_cone_rad": (0.0, math.pi / 2),
    "absorption_per_m": (0.0, math.inf),
    "scattering_per_m": (0.0, math.inf),
    "coating_gloss": (0.0, 1.0),
    "coating_roughness": (1e-3, 1.0),
    "coating_albedo": (0.0, 1.0),
    "vignetting": (0.0, 1.0),
    "lens_distortion": (-math.inf, math.inf),
    "sensor_noise": (0.0, math.inf),
}


def describe_range(low: float, high: float) -> str:
    """'in [0, 1]', 'finite and >= 0' or 'finite', as error messages say it."""
    if math.isinf(low) and math.isinf(high):
        return "finite"
    if math.isinf(high):
        return f"finite and >= {low:g}"
    return f"in [{low:g}, {high:g}]"


@dataclass(frozen=True)
class Effects:
    """Switches and strengths of the reference's physical effects."""

    #: Fraction of each LED's power emitted straight into the glass core (the paper's
    #: explanation of its real images) instead of into the elastomer; 0 switches it off.
    core_light_leak: float = 0.0
    #: Half-angle, radians, of the cone about the tube's axis (+z, towards the tip) in
    #: which the core leak emits inside the glass wall: light coupled into the wall at the
    #: tube's base at a grazing angle, so that the wall guides it up (total internal
    #: reflection at the glass-elastomer interface holds within asin(n_silicone / n_glass)
    #: ~ 71 deg of its normal, i.e. within ~19 deg = 0.33 rad of the axis). 0: off, the
    #: leak is a Lambertian sphere in the glass as before. Photon estimator only.
    core_leak_cone_rad: float = 0.0
    #: Absorption coefficient sigma_a of the elastomer, 1/m (0: off).
    absorption_per_m: float = 20.0
    #: Scattering coefficient sigma_s of the elastomer, 1/m (0: off).
    scattering_per_m: float = 50.0
    #: Share of the coating's reflectance in a specular flake lobe (``pbr_tactile.paint``):
    #: 0 matte (aluminium powder), towards 1 semi-specular (metal flake).
    coating_gloss: float = 0.0
    #: GGX roughness alpha of that lobe (``pbr_tactile.paint.DEFAULT_ROUGHNESS``, an
    #: estimate); unused while coating_gloss is 0.
    coating_roughness: float = 0.3
    #: Diffuse reflectance (albedo) of the coating, 0-1.
    coating_albedo: float = 0.85
    #: The indentation shadows and redirects the LEDs' light (off: light paths see the
    #: undeformed membrane and only the camera sees the deformed one, as in a shading
    #: model without shadows; photon estimator only).
    contact_shadow: bool = True
    #: LEDs emit their real spectra (off: flat white).
    led_spectra: bool = True
    #: The camera's own spectral response (off: ideal response, CIE-like via sRGB film).
    camera_response: bool = True
    #: Vignetting strength: relative fall-off at the image circle's edge, 0-1
    #: (pbr_tactile.sensor, applied to the rendered image like the two below).
    vignetting: float = 0.0
    #: Radial lens distortion coefficients (k1, k2), normalised by the focal length.
    lens_distortion: tuple[float, float] = (0.0, 0.0)
    #: Sensor noise: standard deviation of additive Gaussian noise, in [0, 1] units.
    sensor_noise: float = 0.0

    def __post_init__(self):
        for name, (low, high) in RANGES.items():
            value = getattr(self, name)
            parts = value if isinstance(value, tuple) else (value,)
            if name == "lens_distortion" and len(parts) != 2:
                raise ValueError(f"Effects.lens_distortion must be a pair (k1, k2), got {value}")
            if not all(math.isfinite(v) and low <= v <= high for v in parts):
                raise ValueError(f"Effects.{name} must be {describe_range(low, high)}, got {value}")

    @property
    def sigma_t(self) -> float:
        """Extinction coefficient of the elastomer, 1/m."""
        return float(self.absorption_per_m + self.scattering_per_m)

    @property
    def albedo(self) -> float:
        """Single-scattering albedo sigma_s / sigma_t of the elastomer (0 without medium)."""
        return float(self.scattering_per_m / self.sigma_t) if self.sigma_t > 0 else 0.0

    def to_dict(self) -> dict:
        return asdict(self)

    def with_settings(self, settings: list[str]) -> Effects:
        """A copy with ``NAME=VALUE`` settings applied, as given on a command line:
        booleans as true/false (on/off, 1/0), numbers as numbers, pairs as ``a,b``."""
        kinds = {f.name: f.type for f in fields(self)}
        changes = {}
        for item in settings:
            name, sep, text = item.partition("=")
            name, text = name.strip(), text.strip()
            if not sep or name not in kinds:
                raise ValueError(f"effect setting {item!r}: expected NAME=VALUE with NAME one of {', '.join(kinds)}")
            kind = str(kinds[name])
            try:
                if kind == "bool":
                    lowered = text.lower()
                    if lowered not in ("true", "false", "on", "off", "1", "0"):
                        raise ValueError
                    changes[name] = lowered in ("true", "on", "1")
                elif kind.startswith("tuple"):
                    changes[name] = tuple(float(x) for x in text.split(","))
                    if len(changes[name]) != len(getattr(self, name)):
                        raise ValueError
                else:
                    changes[name] = float(text)
            except ValueError:
                example = {"bool": "true or false", "float": "a number"}.get(kind, "numbers as a,b")
                raise ValueError(f"effect setting {item!r}: {name} takes {example}") from None
        return replace(self, **changes)
