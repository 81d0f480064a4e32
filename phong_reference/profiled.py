"""The fast path of a calibrated unit (a ``scenes.profile.Profile``).

    image = clip(align(sum_m I_m colour_m) + k_a i_a B, 0, 1) inside the image circle

- the LEDs are the unit's (``Profile.sensor_spec``: each turned by its fitted azimuth),
  so the light fields are baked for where they are;
- the membrane's shading (``phong_reference.render`` with no background) is moved as the
  real camera sees the membrane (``scenes.profile.align_image``: the fitted rotation,
  scale and shift), and the image circle is the lens' (it does not move);
- the background term is the profile's (``phong.background``, a smooth model fitted to
  the unit's no-contact image, ``scenes.background_model``) times its ``phong.ambient``;
- the LEDs' constants (k_d, k_s, colour) and the shininess are the profile's where it has
  them (``phong.leds``, ``phong.shininess``: fitted to the unit's taps,
  ``phong_reference.calibrate``; ``phong.fields.<field>`` holds those fitted with each
  light field, and the field rendered takes its own), else the spec's;
- a profile fitted to taps composes by change (``phong.composition = "change"``): its
  background term is the unit's whole no-contact image and the LEDs add only what a
  contact changes,

      image = clip(B + align(sum_m (I_m - I_m,0) colour_m), 0, 1)

  (I_m,0 the undeformed membrane's shading): the LED constants are fitted to contacts'
  changes, and a light field whose light is not tangent to the membrane (``linear`` on a
  flat pad) shades the undeformed membrane too, which the background already holds.
"""

from __future__ import annotations

import dataclasses

import numpy as np
from scipy import ndimage

from scenes.background_model import evaluate
from scenes.camera import Camera
from scenes.elastic import MembraneLayer
from scenes.profile import Profile, align_image
from scenes.spec import SensorSpec

from . import environment
from .normals import normals
from .render import Renderer, _changed_box, _grow, _inner, _slices


def profile_background(profile: Profile, camera: Camera, full: Camera | None = None) -> np.ndarray:
    """(H, W, 3) float32: the profile's background term k_a i_a B at ``camera``'s size;
    ``full`` the spec's camera at its own resolution (default ``camera``), in whose
    pixels the image circle is."""
    table = profile.phong.get("background")
    if table is None:
        raise ValueError("the profile has no phong.background table: it was not calibrated for the fast path "
                         "(re-run tactile-sim calibrate)")
    ambient = float(profile.phong.get("ambient", 1.0))
    if not (np.isfinite(ambient) and ambient >= 0):
        raise ValueError(f"profile phong.ambient must be a finite number >= 0, got {ambient}")
    if ambient == 0:
        return np.zeros(camera.shape + (3,), np.float32)
    return ambient * evaluate(table, profile.camera.image_circle, camera.shape, (full or camera).shape)


#: How a profile's fast path composes its image (module doc): the paper's sum, or by change.
COMPOSITIONS = ("sum", "change")


def composition(profile: Profile) -> str:
    """The profile's ``phong.composition`` ("sum" where it has none); ValueError otherwise."""
    value = profile.phong.get("composition", "sum")
    if value not in COMPOSITIONS:
        raise ValueError(f"profile phong.composition must be one of {COMPOSITIONS}, got {value!r}")
    return value


def profile_constants(profile: Profile, unit: SensorSpec, field: str | None = None) -> SensorSpec:
    """``unit`` with the profile's LED constants and shininess (``phong.leds``,
    ``phong.shininess``, or those fitted with ``field``, ``phong.fields.<field>``) where it
    has them, the LEDs' places fitted with that field (its ``positions``, metres in the
    unit's camera frame: ``phong_reference.calibrate.fit_led_places``) and the published
    smoothing's Gaussian (its ``sigma_px``, ``radius_px``); ValueError naming a malformed
    entry."""
    table = profile.phong
    by_field = table.get("fields") or {}
    if field is not None and field in by_field:
        table = by_field[field]
    positions = table.get("positions")
    if positions is not None:
        array = np.asarray(positions, dtype=np.float64) if isinstance(positions, list) else None
        if array is None or array.shape != (len(unit.leds), 3) or not np.all(np.isfinite(array)) \
                or np.abs(array).max() > 1.0:
            raise ValueError(f"profile phong.fields.{field}.positions must be {len(unit.leds)} places [x, y, z] in "
                             f"metres, got {positions!r}")
        unit = unit.replace(leds=tuple(dataclasses.replace(led, position=tuple(map(float, p)))
                                       for led, p in zip(unit.leds, array)))
    if table.get("sigma_px") is not None:  # the dent's spread fitted with this field
        sigma, radius = table["sigma_px"], table.get("radius_px")
        if not (isinstance(sigma, (int, float)) and np.isfinite(sigma) and sigma > 0 and isinstance(radius, int)
                and radius >= 1):
            raise ValueError(f"profile phong sigma_px and radius_px must be > 0 (pixels, radius whole), got "
                             f"{sigma!r}, {radius!r}")
        unit = unit.replace(elastic=dataclasses.replace(unit.elastic, sigma_px=float(sigma), radius_px=radius))
    leds, shininess = table.get("leds"), table.get("shininess")
    if leds is not None:
        if not isinstance(leds, list) or len(leds) != len(unit.leds):
            raise ValueError(f"profile phong.leds must list {len(unit.leds)} LEDs' constants, got {leds!r}")
        changed = []
        for m, (led, entry) in enumerate(zip(unit.leds, leds)):
            try:
                k_d, k_s = float(entry["k_d"]), float(entry["k_s"])
                colour = tuple(float(c) for c in entry["colour"])
            except (KeyError, TypeError, ValueError):
                raise ValueError(f"profile phong.leds[{m}] must hold k_d, k_s and colour, got {entry!r}") from None
            if not (np.isfinite(k_d) and np.isfinite(k_s) and k_d >= 0 and k_s >= 0):
                raise ValueError(f"profile phong.leds[{m}]: k_d and k_s must be finite and >= 0, got {k_d}, {k_s}")
            if len(colour) != 3 or not all(0.0 <= c <= 1.0 for c in colour):
                raise ValueError(f"profile phong.leds[{m}].colour must be linear RGB in [0, 1], got {colour}")
            changed.append(dataclasses.replace(led, k_d=k_d, k_s=k_s, colour=colour))
        unit = unit.replace(leds=tuple(changed))
    if shininess is not None:
        if not (isinstance(shininess, (int, float)) and np.isfinite(shininess) and shininess > 0):
            raise ValueError(f"profile phong.shininess must be a finite number > 0, got {shininess!r}")
        unit = unit.replace(material=dataclasses.replace(unit.material, shininess=float(shininess)))
    return unit


class ProfiledRenderer:
    """Depth map -> the calibrated unit's image with the fast path (module doc).

    spec : the sensor spec (not yet the unit's: ``profile.sensor_spec`` is applied here);
    L : (M, 3, H, W) light vectors baked for ``profile.sensor_spec(spec)``'s LEDs.
    """

    def __init__(self, spec: SensorSpec, ref_depth: np.ndarray, L: np.ndarray, profile: Profile,
                 layer: MembraneLayer | None = None, field: str | None = None):
        unit = profile_constants(profile, profile.sensor_spec(spec), field)
        self.by_change = composition(profile) == "change"
        self.profile = profile
        self.camera = Camera.from_spec(unit)  # the unit's image circle
        # The membrane's shading, not yet cut by the circle (the lens cuts it after the move).
        whole = dataclasses.replace(self.camera, mask_radius_px=float(np.hypot(*self.camera.shape)))
        zeros = np.zeros(self.camera.shape + (3,), np.float32)
        self._membrane = Renderer(unit, whole, ref_depth, L, zeros, layer)
        self.ref_depth = self._membrane.ref_depth
        self.background = profile_background(profile, self.camera)
        self._mask = self.camera.mask[..., None]
        self._coords = profile.alignment.sampling(self.camera.shape, self.camera)
        moved = align_image(self._membrane.base, profile.alignment, self.camera)
        self._moved_base = moved if self.by_change else 0.0  # subtracted from every image: only the change adds
        self.base = (np.clip(moved - self._moved_base + self.background, 0.0, 1.0) * self._mask).astype(np.float32)
        # the light from everywhere but the LEDs, and the gel's thinning (phong_reference.environment)
        table = (profile.phong.get("fields") or {}).get(field, profile.phong) if field is not None else profile.phong
        self.environment = environment.coefficients(table.get("environment"))
        if self.environment is not None:
            rays = whole.rays_channels_first
            self._N0 = normals(self.ref_depth * rays)[0]
            # the no-contact image the "lit" terms scale by: the background term at full ambient
            lit = profile_background(dataclasses.replace(profile, phong={**profile.phong, "ambient": 1.0}),
                                     self.camera)
            self._lit = np.ascontiguousarray(lit.transpose(2, 0, 1), np.float32)

    def environment_terms(self, depth: np.ndarray) -> tuple[tuple[slice, slice], np.ndarray] | None:
        """(the window, (len(environment.TERMS), 3, h, w) each term's change there) of a
        contact depth map, in the membrane's frame (before the alignment's move); None
        where the surface does not move."""
        d_def = self._membrane.deformed(depth)
        box = _changed_box(self.ref_depth - d_def)
        if box is None:
            return None
        shape = self.camera.shape
        shaded = _grow(box, 1, shape)
        stencil = _grow(shaded, 1, shape)
        P = d_def[_slices(stencil)] * self._membrane.camera.rays_channels_first[(slice(None),) + _slices(stencil)]
        N = normals(P)[0][(slice(None),) + _inner(stencil, shaded)]
        window = _slices(shaded)
        at = (slice(None),) + window
        return window, environment.terms(N, self._N0[at], self.ref_depth[window] - d_def[window], self._lit[at])

    def _membrane_image(self, depth: np.ndarray) -> np.ndarray:
        """(H, W, 3) the membrane's shading under a contact, with the environment's change."""
        membrane = self._membrane.render(depth)
        if self.environment is None:
            return membrane
        found = self.environment_terms(depth)
        if found is not None:
            window, T = found
            membrane[window] += environment.change(self.environment, T).transpose(1, 2, 0)
        return membrane

    def render(self, depth: np.ndarray) -> np.ndarray:
        """(H, W) float metres -> (H, W, 3) float32 in [0, 1]. Only the window where the
        moved membrane changes is moved again (the rest is the no-contact image)."""
        membrane = self._membrane_image(depth)
        rows = np.flatnonzero(np.any(membrane != self._membrane.base, axis=(1, 2)))
        if rows.size == 0:
            return self.base.copy()
        cols = np.flatnonzero(np.any(membrane[rows[0]:rows[-1] + 1] != self._membrane.base[rows[0]:rows[-1] + 1],
                                     axis=(0, 2)))
        window = self._window((rows[0], rows[-1] + 1, cols[0], cols[-1] + 1))
        if window is None:
            return self.base.copy()
        coords = self._coords[(slice(None),) + window]
        moved = np.stack([ndimage.map_coordinates(membrane[..., c], coords, order=1, mode="constant")
                          for c in range(3)], axis=-1)
        image = self.base.copy()
        if self.by_change:
            moved = moved - self._moved_base[window]
        image[window] = np.clip(moved + self.background[window], 0.0, 1.0) * self._mask[window]
        return image

    def _window(self, box) -> tuple[slice, slice] | None:
        """The output pixels that sample the membrane's changed ``box`` (r0, r1, c0, c1):
        its corners moved by the alignment, grown by two pixels (bilinear reads)."""
        r0, r1, c0, c1 = box
        uo, vo = self.profile.alignment.moved([c0 - 1, c1, c0 - 1, c1], [r0 - 1, r0 - 1, r1, r1], self.camera)
        h, w = self.camera.shape
        top, bottom = max(int(np.floor(vo.min())) - 2, 0), min(int(np.ceil(vo.max())) + 3, h)
        left, right = max(int(np.floor(uo.min())) - 2, 0), min(int(np.ceil(uo.max())) + 3, w)
        if top >= bottom or left >= right:
            return None
        return slice(top, bottom), slice(left, right)
