"""The gap benchmark's injector (``studies.gap.inject``): the light, per LED. Other Phong
constants and LED spectra, the light each LED's layer adds, absorption along a path, LED
light leaking across the glass core, and the contact's shadow: rays from the imprint's
surface towards each LED, occluded by the deformed membrane. Arrays in, arrays out; each
effect in its own way, never the diagnosis' models.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import trimesh

from pbr_tactile.spectra import film_response, gaussian
from phong_reference.phong import shade
from scenes.spec import LED, Material


#: Out-of-band transmission of a Bayer colour filter, as a share of the LED's strongest
#: channel: without it the ratio R_c(peak + delta) / R_c(peak) of a channel deep in the
#: Gaussian tail (the blue response to a red LED) reaches 50.
FILTER_FLOOR = 0.02

#: contact_shadow: shadow rays start this far along their direction, m (Embree is float32).
SHADOW_RAY_OFFSET_M = 1e-5

#: contact_shadow: an occluder must come this much closer than the undeformed membrane, m.
SHADOW_TOLERANCE_M = 5e-5

#: contact_shadow: the light is an extended source: elevations beta times these, averaged.
SHADOW_SOFT_ELEVATIONS = (0.7, 0.9, 1.1, 1.3)


def gloss(leds: tuple[LED, ...], material: Material, delta_k_s: float,
          shininess: float) -> tuple[tuple[LED, ...], Material]:
    """A glossier coating: every LED's k_s raised by ``delta_k_s``, Phong alpha set to ``shininess``."""
    if not shininess > 0:
        raise ValueError(f"shininess must be > 0, got {shininess}")
    leds = tuple(dataclasses.replace(led, k_s=led.k_s + float(delta_k_s)) for led in leds)
    return leds, dataclasses.replace(material, shininess=float(shininess))


def spectral_ratio(peak_nm: float, fwhm_nm: float, shift_nm: float) -> np.ndarray:
    """(3,) camera RGB response to an LED whose peak moved by ``shift_nm``, over the original.

    R_c = film_response(gaussian(peak, fwhm)) through the camera's bands, plus an
    out-of-band floor of ``FILTER_FLOOR`` times the original's strongest channel.
    """
    before = film_response(gaussian(peak_nm, fwhm_nm))
    after = film_response(gaussian(peak_nm + shift_nm, fwhm_nm))
    floor = FILTER_FLOOR * before.max()
    return (after + floor) / (before + floor)


def shift_spectra(leds: tuple[LED, ...], shifts_nm, intensities) -> tuple[LED, ...]:
    """LEDs whose emission peaks moved: colour_m * R(peak + delta_m) / R(peak) * intensity_m.

    shifts_nm, intensities : (M,) per LED, nm and -.  An LED without ``peak_nm`` and
    ``fwhm_nm`` in the spec keeps its colour (only the intensity factor applies).
    """
    out = []
    for led, shift, gain in zip(leds, shifts_nm, intensities, strict=True):
        ratio = np.ones(3)
        if led.peak_nm is not None and led.fwhm_nm is not None:
            ratio = spectral_ratio(led.peak_nm, led.fwhm_nm, float(shift))
        colour = tuple(float(c) for c in np.asarray(led.colour) * ratio * float(gain))
        peak = None if led.peak_nm is None else led.peak_nm + float(shift)
        out.append(dataclasses.replace(led, colour=colour, peak_nm=peak))
    return tuple(out)


def led_layers(P: np.ndarray, N: np.ndarray, L: np.ndarray, leds: tuple[LED, ...], material: Material) -> np.ndarray:
    """Each LED's own Phong term I_m, without the ambient background.

    P, N : (3, H, W) points (metres) and camera-facing unit normals; L : (M, 3, H, W) unit
    light vectors.  Returns (M, 3, H, W), P's dtype, linear RGB, not clipped.
    """
    dark = dataclasses.replace(material, ambient=0.0)
    zeros = np.zeros_like(P)
    return np.stack([shade(P, N, L[m : m + 1], [led], dark, zeros) for m, led in enumerate(leds)])


def transmittance(distance: np.ndarray, mu: float) -> np.ndarray:
    """Beer-Lambert: exp(-mu d), distance d in metres, mu in 1/m; same shape."""
    if not mu >= 0:
        raise ValueError(f"mu must be >= 0 1/m, got {mu}")
    return np.exp(-mu * distance)


def core_leak(P: np.ndarray, N: np.ndarray, leds: tuple[LED, ...], gain: float,
              reference_distance: float) -> np.ndarray:
    """Irradiance of LED light that crosses the glass core and meets the membrane from inside.

    Each LED is a point source at its position p_m:
    E = a colour_m max(N . w_m, 0) (r0 / |p_m - P|)^2, with w_m = (p_m - P) / |p_m - P|.

    P : (3, H, W) float, metres, surface points; N : (3, H, W) unit normals facing the
    camera, which sits inside the membrane, so they are the inward normals.
    Returns (3, H, W), P's dtype, linear RGB.
    """
    out = np.zeros_like(P)
    for led in leds:
        to_led = np.asarray(led.position, dtype=P.dtype)[:, None, None] - P  # (3, H, W), metres
        dist2 = (to_led * to_led).sum(axis=0)
        cos = np.maximum((N * to_led).sum(axis=0) / np.sqrt(dist2), 0)
        E = gain * cos * (reference_distance * reference_distance / dist2)
        out += np.asarray(led.colour, dtype=P.dtype)[:, None, None] * E
    return out


def _grid_faces(h: int, w: int) -> np.ndarray:
    """(2 (h - 1)(w - 1), 3) int triangles of an h x w vertex grid, row-major."""
    a = (np.arange(h - 1)[:, None] * w + np.arange(w - 1)[None, :]).ravel()
    return trimesh.geometry.triangulate_quads(np.stack([a, a + 1, a + w + 1, a + w], axis=1))


def deformed_grid(points: np.ndarray, moved: np.ndarray) -> trimesh.Trimesh | None:
    """The deformed part of the surface as a triangle grid: the pixel points P (3, H, W),
    metres, over the bounding box of ``moved`` (H, W) bool grown by one pixel; None if
    nothing moved."""
    box = changed_box(moved, 1)
    if box is None:
        return None
    grid = np.asarray(points[(slice(None),) + box], dtype=np.float64)
    h, w = grid.shape[1:]
    if h < 2 or w < 2:
        return None
    return trimesh.Trimesh(grid.reshape(3, -1).T, _grid_faces(h, w), process=False)


def shadow_visibility(
    points: np.ndarray,
    light: np.ndarray,
    inward: np.ndarray,
    occluder: trimesh.Trimesh,
    membrane: trimesh.Trimesh,
    elevation: float,
    where: np.ndarray | None = None,
) -> np.ndarray:
    """Share of each LED's guided light that the deformed membrane lets through.

    Light arrives along the tangent L_m (towards the LED) tilted by the elevation beta
    towards the camera side: w = cos(beta) t_m + sin(beta) n, with t_m the part of L_m
    in the undeformed tangent plane (unit) and n the undeformed inward normal. A point is
    shadowed when the ray from it along w meets the deformed surface (``occluder``)
    before it would meet the undeformed ``membrane``: on the GelTip's concave inside,
    light at elevation beta has come off the membrane a chord 2 R sin(beta) away, so only
    nearer occluders count. The source is extended: beta times each of
    ``SHADOW_SOFT_ELEVATIONS``, averaged.

    points : (K, 3) float, metres, the receiving (deformed) surface points.
    light : (M, K, 3) float, light vectors L_m there; zero where the LED's light does not reach.
    inward : (K, 3) float, unit inward normals of the undeformed membrane there.
    occluder : the deformed part of the membrane, metres (``deformed_grid``).
    membrane : the undeformed membrane mesh, metres.
    elevation : beta, rad, in (0, pi / 2).
    where : (M, K) bool, the points whose light matters (the others are not traced and
        count as lit); default all.

    Returns (M, K) float64 in [0, 1], 1 fully lit.
    """
    if not 0 < elevation < math.pi / 2:
        raise ValueError(f"elevation must be in (0, pi/2) rad, got {elevation}")
    points = np.asarray(points, dtype=np.float64)
    n = np.asarray(inward, dtype=np.float64)
    centre = occluder.bounds.mean(axis=0)  # bounding sphere of the occluder, for culling
    radius = 0.5 * float(np.linalg.norm(np.ptp(occluder.bounds, axis=0))) + SHADOW_RAY_OFFSET_M
    visible = np.ones(light.shape[:2])
    for m in range(len(light)):
        idx = np.arange(len(points)) if where is None else np.flatnonzero(where[m])
        L_m = np.asarray(light[m, idx], dtype=np.float64)
        t = L_m - (L_m * n[idx]).sum(axis=1, keepdims=True) * n[idx]
        norm = np.linalg.norm(t, axis=1)
        # No tangent light, or an occluder behind the point (away from the light): lit.
        keep = (norm > 1e-6) & (((centre - points[idx]) * t).sum(axis=1) > -radius * norm)
        idx, t = idx[keep], t[keep] / norm[keep, None]
        # Every ray of the point lies in the plane through it spanned by t and n: an
        # occluder off that plane is missed at any elevation.
        side = np.cross(t, n[idx])
        keep = np.abs(((centre - points[idx]) * side).sum(axis=1)) < radius
        idx, t = idx[keep], t[keep]
        if idx.size == 0:
            continue
        share = np.zeros(idx.size)
        for factor in SHADOW_SOFT_ELEVATIONS:
            beta = min(elevation * factor, math.pi / 2 - 1e-3)
            dirs = math.cos(beta) * t + math.sin(beta) * n[idx]
            origins = points[idx] + SHADOW_RAY_OFFSET_M * dirs
            # Only rays whose line passes the occluder's bounding sphere, ahead, can hit it.
            to_c = centre - origins
            along = (to_c * dirs).sum(axis=1)
            near = (along > -radius) & ((to_c * to_c).sum(axis=1) - along**2 < radius**2)
            hit = np.zeros(idx.size, dtype=bool)
            if near.any():
                hit[near] = _occluded(occluder, membrane, origins[near], dirs[near])
            share += ~hit
        visible[m, idx] = share / len(SHADOW_SOFT_ELEVATIONS)
    return visible


def _first_hit(mesh: trimesh.Trimesh, origins: np.ndarray, dirs: np.ndarray) -> np.ndarray:
    """(K,) distance to each ray's first hit, metres; inf where it misses."""
    _, ray, loc = mesh.ray.intersects_id(origins, dirs, multiple_hits=False, return_locations=True)
    t = np.full(len(origins), np.inf)
    t[ray] = np.einsum("ij,ij->i", np.asarray(loc) - origins[ray], dirs[ray])
    return t


def _occluded(surface: trimesh.Trimesh, membrane: trimesh.Trimesh, origins: np.ndarray, dirs: np.ndarray) -> np.ndarray:
    hit = _first_hit(surface, origins, dirs)
    occluded = np.isfinite(hit)
    if occluded.any():
        idx = np.flatnonzero(occluded)
        occluded[idx] = hit[idx] < _first_hit(membrane, origins[idx], dirs[idx]) - SHADOW_TOLERANCE_M
    return occluded


def changed_box(changed: np.ndarray, margin: int) -> tuple[slice, slice] | None:
    """Slices of the bounding box of ``changed`` (H, W) bool grown by ``margin`` px; None if empty."""
    rows = np.flatnonzero(changed.any(axis=1))
    if rows.size == 0:
        return None
    cols = np.flatnonzero(changed.any(axis=0))
    h, w = changed.shape
    return (slice(max(int(rows[0]) - margin, 0), min(int(rows[-1]) + 1 + margin, h)),
            slice(max(int(cols[0]) - margin, 0), min(int(cols[-1]) + 1 + margin, w)))
