"""Spectra of the physically based reference: LED emission and the camera's RGB response."""

from __future__ import annotations

import numpy as np

#: Wavelength grid of every spectrum, nanometres (Mitsuba's visible range).
WAVELENGTHS_NM = np.arange(360.0, 831.0, 5.0)

#: A webcam CMOS sensor's red, green and blue responses, as Gaussians (peak, FWHM) in nm:
#: typical of Bayer colour filters on silicon.
CAMERA_BANDS_NM = {"red": (600.0, 80.0), "green": (535.0, 90.0), "blue": (460.0, 70.0)}


def gaussian(peak_nm: float, fwhm_nm: float, wavelengths: np.ndarray = WAVELENGTHS_NM) -> np.ndarray:
    """A unit-peak Gaussian spectrum sampled at ``wavelengths``."""
    if not fwhm_nm > 0:
        raise ValueError(f"fwhm_nm must be > 0, got {fwhm_nm}")
    sigma = fwhm_nm / (2.0 * np.sqrt(2.0 * np.log(2.0)))
    return np.exp(-0.5 * ((wavelengths - peak_nm) / sigma) ** 2)


def mitsuba_spectrum(values: np.ndarray, wavelengths: np.ndarray = WAVELENGTHS_NM) -> dict:
    """An irregular Mitsuba spectrum dict."""
    return {
        "type": "irregular",
        "wavelengths": ", ".join(f"{w:g}" for w in wavelengths),
        "values": ", ".join(f"{v:.6g}" for v in values),
    }


def led_spectrum(peak_nm: float | None, fwhm_nm: float | None, real: bool = True) -> np.ndarray:
    """Relative spectral power of an LED (unit peak); flat (white) when ``real`` is off."""
    if not real:
        return np.ones_like(WAVELENGTHS_NM)
    if peak_nm is None or fwhm_nm is None:
        raise ValueError("the LED has no spectrum: set peak_nm and fwhm_nm in the sensor spec")
    return gaussian(peak_nm, fwhm_nm)


def film_response(radiance: np.ndarray, camera_response: bool = True,
                  wavelengths: np.ndarray = WAVELENGTHS_NM) -> np.ndarray:
    """(3,) pixel value the reference's film records for a constant spectral radiance.

    ``radiance`` is sampled at ``wavelengths`` and, like every spectrum handed to
    Mitsuba, read as piecewise linear. With the camera's response (``specfilm``) channel
    c records int S_c(lambda) L(lambda) dlambda, S_c the CAMERA_BANDS_NM curve; without
    it (``hdrfilm``), linear sRGB of the CIE 1931 XYZ integrals times Mitsuba's
    CIE_Y normalisation. Both are Mitsuba's own conventions, so an image assembled from
    this matches a Mitsuba render of the same light in expectation, without sampling
    wavelengths (pbr_tactile.camera_pass.camera_pass).
    """
    fine = np.linspace(wavelengths[0], wavelengths[-1], 20 * (len(wavelengths) - 1) + 1)
    L = np.interp(fine, wavelengths, radiance)
    if camera_response:
        return np.array([np.trapezoid(np.interp(fine, wavelengths, gaussian(peak, fwhm)) * L, fine)
                         for peak, fwhm in CAMERA_BANDS_NM.values()])
    from .variant import any_variant

    mi = any_variant()
    xyz_bar = np.array([np.asarray(mi.cie1931_xyz(float(w))).ravel() for w in fine])
    xyz = np.trapezoid(xyz_bar * L[:, None], fine, axis=0) * mi.MI_CIE_Y_NORMALIZATION
    return np.asarray(mi.xyz_to_srgb(mi.ScalarColor3f(*xyz))).ravel()
