"""Phong shading of the membrane under guided LED light (the paper's illumination model)."""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from scenes.spec import LED, Material


def _power(x: np.ndarray, alpha: float) -> np.ndarray:
    """x ** alpha, by repeated squaring when alpha is a small whole number."""
    if alpha == int(alpha) and 0 < alpha <= 1024:
        a, out, base = int(alpha), None, x
        while a:
            if a & 1:
                out = base if out is None else out * base
            a >>= 1
            if a:
                base = base * base
        return out
    return np.power(np.maximum(x, 0), alpha)


def _dot(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


class PhongTerms(NamedTuple):
    """The per-LED terms of the Phong model that ``shade`` composes (paper's notation).

    LN : (M, ...) diffuse term max(L_m . N, 0).
    RV : (M, ...) R_m . V, clamped at 0 when the material says so.
    specular : (M, ...) (R_m . V)^alpha.
    ambient : (3, ...) the ambient (background) term k_a i_a B, linear RGB.
    """

    LN: np.ndarray
    RV: np.ndarray
    specular: np.ndarray
    ambient: np.ndarray


def shading_terms(P: np.ndarray, N: np.ndarray, L: np.ndarray, material: Material,
                  background: np.ndarray) -> PhongTerms:
    """The terms of I = k_a i_a B + sum_m (k_d,m (L_m . N) + k_s,m (R_m . V)^alpha) colour_m.

    With R_m = 2 (L_m . N) N - L_m and V = -P / |P| (the view vector), and L_m . N clamped
    at 0 (Phong, as in the paper's equation for I_m).  R_m . V is expanded as
    2 (L_m . N)(N . V) - L_m . V, which saves forming R_m.  Vector images are
    channel-first: component first, then any pixel shape.

    Parameters
    ----------
    P : (3, ...) surface points, metres, camera frame.
    N : (3, ...) unit normals facing the camera.
    L : (M, 3, ...) unit light vectors L_m (towards where the light comes from), zero
        where the LED's light does not reach.
    background : (3, ...) linear RGB in [0, 1].

    Returns
    -------
    PhongTerms, in P's dtype.
    """
    V = P * (-1 / np.sqrt(_dot(P, P)))
    NV = _dot(N, V)
    LN, RV, specular = [], [], []
    for L_m in L:
        LN_m = np.maximum(_dot(L_m, N), 0)
        RV_m = 2 * LN_m * NV - _dot(L_m, V)
        if material.clamp_specular:
            RV_m = np.maximum(RV_m, 0)
        LN.append(LN_m)
        RV.append(RV_m)
        specular.append(_power(RV_m, material.shininess))
    ambient = (material.ambient * background).astype(P.dtype, copy=True)
    return PhongTerms(_stack(LN, P), _stack(RV, P), _stack(specular, P), ambient)


def _stack(planes: list[np.ndarray], P: np.ndarray) -> np.ndarray:
    return np.stack(planes) if planes else np.zeros((0,) + P.shape[1:], P.dtype)


def led_intensities(terms: PhongTerms, k_d, k_s) -> np.ndarray:
    """I_m = k_d,m (L_m . N) + k_s,m (R_m . V)^alpha: (M, ...), the terms' dtype.

    k_d, k_s : (M,) per-LED diffuse and specular coefficients.
    """
    # Python floats, so that the float32 terms stay float32.
    I = [float(kd) * LN + float(ks) * sp for LN, sp, kd, ks in zip(terms.LN, terms.specular, k_d, k_s, strict=True)]
    return np.stack(I) if I else terms.LN.copy()


def compose(I: np.ndarray, colours, ambient: np.ndarray) -> np.ndarray:
    """ambient + sum_m I_m colour_m: (M, ...) intensities, (M, 3) colours, (3, ...)
    ambient -> (3, ...) linear RGB in ambient's dtype, not clipped."""
    out = ambient.copy()
    dtype = out.dtype.type
    for I_m, colour in zip(I, colours):
        for c in range(3):
            out[c] += I_m * dtype(colour[c])
    return out


def shade(
    P: np.ndarray,
    N: np.ndarray,
    L: np.ndarray,
    leds: tuple[LED, ...] | list[LED],
    material: Material,
    background: np.ndarray,
) -> np.ndarray:
    """I = k_a i_a B + sum_m (k_d,m (L_m . N) + k_s,m (R_m . V)^alpha) colour_m.

    ``compose(led_intensities(shading_terms(...)))``: see ``shading_terms`` for the
    terms and the shapes of P, N, L (M, 3, ...) and background (3, ...).

    Returns
    -------
    (3, ...) linear RGB, not clipped.
    """
    if len(L) != len(leds):
        raise ValueError(f"L holds {len(L)} light fields for {len(leds)} LEDs")
    terms = shading_terms(P, N, L, material, background)
    I = led_intensities(terms, [led.k_d for led in leds], [led.k_s for led in leds])
    return compose(I, [led.colour for led in leds], terms.ambient)
