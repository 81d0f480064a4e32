"""Phong shading of the membrane under guided LED light (the paper's illumination model)."""

from __future__ import annotations

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


def shade(
    P: np.ndarray,
    N: np.ndarray,
    L: np.ndarray,
    leds: tuple[LED, ...] | list[LED],
    material: Material,
    background: np.ndarray,
) -> np.ndarray:
    """I = k_a i_a B + sum_m (k_d,m (L_m . N) + k_s,m (R_m . V)^alpha) colour_m.

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
    (3, ...) linear RGB, not clipped.
    """
    if len(L) != len(leds):
        raise ValueError(f"L holds {len(L)} light fields for {len(leds)} LEDs")
    V = P * (-1 / np.sqrt(_dot(P, P)))
    NV = _dot(N, V)
    I = (material.ambient * background).astype(P.dtype, copy=True)
    for L_m, led in zip(L, leds):
        LN = np.maximum(_dot(L_m, N), 0)
        RV = 2 * LN * NV - _dot(L_m, V)
        if material.clamp_specular:
            RV = np.maximum(RV, 0)
        I_m = led.k_d * LN + led.k_s * _power(RV, material.shininess)
        for c in range(3):
            I[c] += I_m * P.dtype.type(led.colour[c])
    return I
