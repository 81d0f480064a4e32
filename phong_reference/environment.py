"""The light a calibrated unit's membrane receives besides its LEDs' direct beams, and the
gel's thinning under a press: terms of the fast path's change that its LEDs' Phong terms
cannot make.

Two physical effects change a real press's image where the LEDs' Phong terms do not:

- **Light from everywhere else.** A real membrane is also lit by the plate's glow, the
  housing and the light scattered back from the gel. Seen from the membrane this is a
  distant environment, and a Lambertian surface's irradiance under any distant light is
  captured, to a few per cent, by the spherical harmonics of its normal up to order 2
  (Ramamoorthi and Hanrahan, "An efficient representation for irradiance environment
  maps", SIGGRAPH 2001). Its change under a contact is sum_k c_k [Y_k(N_t) - Y_k(N_0)]
  over the eight terms of orders 1 and 2 (order 0 cancels), per colour channel, with
  signed c_k. The environment's strength also follows how brightly the frame is lit
  where the press is, so each term appears twice: alone and scaled by the no-contact
  image B_c(p) there ("lit").
- **The gel's thinning.** Where the membrane is pressed the gel between the plate and
  the paint is thinner by u (mm), and the light that crosses it is attenuated and
  scattered less: to first order a change e_c u, and e'_c u B_c(p), signed per channel.

So each channel's change gains TERMS, linear in its coefficients: they are fitted with the
LEDs' constants (``phong_reference.calibrate.fit_terms``) and kept in the profile's
``phong.environment`` (``coefficients``: one row of three per term, in TERMS' order).
The paper's model has none of them; a profile without the entry renders without them.
"""

from __future__ import annotations

import numpy as np

#: The order-1 and order-2 real spherical harmonics of a unit normal (x, y, z), as
#: polynomials (their constant factors are in the fitted coefficients).
HARMONICS = ("x", "y", "z", "xy", "yz", "xz", "xx-yy", "3zz-1")
#: Every term of the change, in the order of a profile's coefficients.
TERMS = tuple(HARMONICS) + tuple(f"{h} lit" for h in HARMONICS) + ("thinning", "thinning lit")


def harmonics(N: np.ndarray) -> np.ndarray:
    """(8, ...) the HARMONICS of unit normals N (3, ...)."""
    x, y, z = N[0], N[1], N[2]
    return np.stack([x, y, z, x * y, y * z, x * z, x * x - y * y, 3 * z * z - 1])


def terms(N_t: np.ndarray, N_0: np.ndarray, u_m: np.ndarray, lit: np.ndarray) -> np.ndarray:
    """(len(TERMS), 3, h, w) each term's change (module doc) for the pressed normals N_t
    and the untouched N_0 (3, h, w), the surface's displacement u_m (h, w), metres, and the
    no-contact image ``lit`` (3, h, w) there."""
    dY = harmonics(N_t) - harmonics(N_0)
    u = np.asarray(u_m, np.float32) * 1e3  # mm: coefficients of a useful size
    n = len(HARMONICS)
    out = np.empty((len(TERMS), 3) + np.shape(u), np.float32)
    out[:n] = dY[:, None]
    out[n:2 * n] = dY[:, None] * lit[None]
    out[2 * n] = u[None]
    out[2 * n + 1] = u[None] * lit
    return out


def change(coefficients: np.ndarray, T: np.ndarray) -> np.ndarray:
    """(3, h, w) the change of TERMS' values ``T`` (len(TERMS), 3, h, w) with
    ``coefficients`` (len(TERMS), 3)."""
    return np.einsum("kc,kchw->chw", coefficients, T, optimize=True).astype(np.float32)


def coefficients(entry) -> np.ndarray | None:
    """(len(TERMS), 3) float32 from a profile's ``phong.environment`` entry (None: none);
    ValueError naming a malformed one."""
    if entry is None:
        return None
    try:
        names, values = entry["terms"], np.asarray(entry["coefficients"], np.float64)
    except (KeyError, TypeError, ValueError):
        raise ValueError(f"profile phong.environment must hold terms and coefficients, got {entry!r}") from None
    if list(names) != list(TERMS) or values.shape != (len(TERMS), 3) or not np.all(np.isfinite(values)):
        raise ValueError(f"profile phong.environment must give {len(TERMS)} terms {list(TERMS)} with three finite "
                         f"coefficients each, got terms {names!r} and coefficients of shape {values.shape}")
    return values.astype(np.float32)


def entry(values: np.ndarray) -> dict:
    """A profile's ``phong.environment`` entry for coefficients (len(TERMS), 3)."""
    return {"terms": list(TERMS), "coefficients": [[float(v) for v in row] for row in np.asarray(values)]}
