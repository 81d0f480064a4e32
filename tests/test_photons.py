"""The photon estimator's pieces: density kernel, weight window, film response."""

from __future__ import annotations

import numpy as np
import pytest

from pbr_tactile.density import density_kernel, irradiance
from pbr_tactile.photons import weight_window
from pbr_tactile.spectra import CAMERA_BANDS_NM, WAVELENGTHS_NM, film_response, gaussian


def _plane_grid(spacing=0.25e-3, n=41):
    u = (np.arange(n) - n // 2) * spacing
    x, y = np.meshgrid(u, u)
    return np.c_[x.ravel(), y.ravel(), np.zeros(x.size)], np.full(x.size, spacing**2)


def test_kernel_density_is_exact_for_linear_irradiance_away_from_the_edge():
    positions, area = _plane_grid()
    E_true = 100.0 + 3e4 * positions[:, 0] - 2e4 * positions[:, 1]  # 1/m^2, linear
    flux = (E_true * area)[None]
    K = density_kernel(positions, 0.75e-3)
    E = irradiance(flux, area, K)[0]
    inner = np.all(np.abs(positions[:, :2]) < 4e-3, axis=1)
    assert np.allclose(E[inner], E_true[inner], rtol=1e-9)
    assert np.allclose(irradiance(flux, area, density_kernel(positions, 0.0))[0], E_true)


def test_kernel_weights_every_pair_within_the_radius_seams_included():
    rng = np.random.default_rng(1)
    positions = rng.uniform(0, 3e-3, size=(300, 3))
    positions[1] = positions[0]  # a seam: two vertices at one point
    radius = 1e-3
    d = np.linalg.norm(positions[:, None] - positions[None], axis=-1)
    brute = np.where(d <= radius, 1.0 - (d / radius) ** 2, 0.0)
    K = density_kernel(positions, radius)
    np.testing.assert_allclose(K.toarray(), brute, atol=1e-12)
    assert K[0, 1] == K[1, 0] == 1.0
    assert density_kernel(positions.copy(), radius) is K  # kept: the same positions ask again
    assert density_kernel(positions + 1e-9, radius) is not K


def test_a_dented_kernel_is_its_undeformed_kernel_changed_where_vertices_moved():
    """density_kernel(like=): only the moved vertices' rows and columns are computed again,
    and the kernel is the one computed from scratch, entry for entry (seams that moved
    together, and pairs of two moved vertices, included)."""
    rng = np.random.default_rng(2)
    flat = rng.uniform(0, 3e-3, size=(400, 3))
    flat[1] = flat[0]  # a seam
    radius = 1e-3
    K0 = density_kernel(flat, radius)
    dented = flat.copy()
    moved = np.linalg.norm(flat - 1.5e-3, axis=1) < 1e-3
    moved[:2] = True
    dented[moved] -= rng.uniform(0, 4e-4, size=(moved.sum(), 3))
    dented[1] = dented[0]
    assert 20 < moved.sum() < 380
    again = density_kernel(dented, radius, like=(flat, K0))
    from pbr_tactile import density

    density._KERNELS.clear()  # a fresh computation, not the kept one
    scratch = density_kernel(dented, radius)
    assert again is not scratch and (again != scratch).nnz == 0
    assert again.nnz == scratch.nnz
    assert density_kernel(flat.copy(), radius, like=(flat, K0)).nnz == K0.nnz  # nothing moved


def test_kernel_density_averages_noise_down_as_one_over_radius():
    rng = np.random.default_rng(0)
    positions, area = _plane_grid(n=61)
    flux = rng.poisson(20.0, size=(1, len(area))) * 1.0  # counts: relative noise 1/sqrt(20)
    inner = np.all(np.abs(positions[:, :2]) < 4e-3, axis=1)
    noise = [irradiance(flux, area, density_kernel(positions, r))[0][inner].std() for r in (0.5e-3, 1.0e-3)]
    # Epanechnikov over ~pi r^2 / spacing^2 vertices: twice the radius, about half the noise.
    assert 0.3 < noise[1] / noise[0] < 0.65


def test_weight_window_sets_the_deposit_density_analytically():
    area = np.full(4, 1e-6)
    pilot = np.array([[1000.0, 100.0, 10.0, 0.0]])
    # Exponent 1: the deposit density E / w is the same wherever the pilot saw light.
    w = weight_window(pilot, area, photons=1000, deposits_per_photon=2.0, exponent=1.0)
    density = pilot[0, :3] / w[0, :3]
    assert np.allclose(density, density[0]) and density[0] == pytest.approx(2.0 * 1000 / area.sum())
    assert w[0, 3] > 0  # an unlit vertex still gets a positive (finite) target
    # The default, 1/2: density ~ sqrt(E), so 10x the light gets sqrt(10)x the deposits
    # and a photon from the brightest vertex is only sqrt(100) = 10x the dimmest's target.
    w = weight_window(pilot, area, photons=1000, deposits_per_photon=2.0)
    density = pilot[0, :3] / w[0, :3]
    assert np.allclose(density[:-1] / density[1:], np.sqrt(10.0))
    assert w[0, 0] / w[0, 2] == pytest.approx(10.0)
    # Exponent 0: one weight everywhere, the light-weighted mean's.
    w = weight_window(pilot, area, photons=1000, deposits_per_photon=2.0, exponent=0.0)
    assert np.allclose(w, w[0, 0])


def test_film_response_follows_specfilm_convention_analytically():
    flat = np.ones_like(WAVELENGTHS_NM)
    # A flat unit spectrum gives each channel the area under its Gaussian: FWHM * 1.0645.
    expected = [1.0645 * fwhm for _, fwhm in CAMERA_BANDS_NM.values()]
    assert np.allclose(film_response(flat), expected, rtol=2e-3)
    red = film_response(gaussian(630.0, 20.0))
    assert red[0] > 10 * red[1] > 0 and red[2] < 1e-3 * red[0]


def test_film_response_matches_mitsuba_films(scalar_mi):
    from pbr_tactile.effects import Effects
    from pbr_tactile.render import to_mitsuba
    from pbr_tactile.scene import _film
    from pbr_tactile.spectra import mitsuba_spectrum
    from scenes.camera import Camera
    from scenes.spec_read import load_spec

    mi = scalar_mi
    camera = Camera.from_spec(load_spec())
    led = 2.0 * gaussian(530.0, 30.0)
    for response in (True, False):
        scene = {"type": "scene", "integrator": {"type": "path"},
                 "sensor": {"type": "perspective", "fov": 10, "film": _film(camera, Effects(camera_response=response), 8, 8),
                            "sampler": {"type": "independent", "sample_count": 1024}},
                 "wall": {"type": "rectangle", "flip_normals": True,
                          "to_world": mi.ScalarTransform4f().translate([0, 0, 5]).scale(10),
                          "emitter": {"type": "area", "radiance": mitsuba_spectrum(led)}}}
        img = np.array(mi.render(mi.load_dict(to_mitsuba(scene, mi)))).reshape(-1, 3)
        mean, se = img.mean(0), img.std(0, ddof=1) / np.sqrt(len(img))
        expected = film_response(led, response)
        assert np.all(np.abs(mean - expected) < 5 * se + 1e-3 * np.abs(expected).max()), (response, mean, expected)


def test_contact_rse_is_unbiased_with_two_passes():
    """The bench's noise figure: with 2 passes, the mean of per-pixel standard errors
    reads about 0.8 of the truth; the RMS of the per-pixel variance does not."""
    from pbr_tactile.estimate import Estimate, contact_rse

    rng = np.random.default_rng(0)
    mu, sigma = 2.0, 0.1  # each pass: 5 % noise; the mean of 2 passes: 5 % / sqrt(2)
    passes = [mu + sigma * rng.standard_normal((200, 200, 3)) for _ in range(2)]
    est = Estimate.from_passes(passes, spp=2)
    region = np.ones((200, 200), dtype=bool)
    truth = sigma / np.sqrt(2) / mu
    assert contact_rse(est, region) == pytest.approx(truth, rel=0.02)
    naive = float(np.mean(est.relative_error[region]))
    assert naive < 0.85 * truth  # what the bench used to report


def test_no_contact_cache_needs_at_least_one_run():
    from pbr_tactile.nocontact import NoContact

    with pytest.raises(ValueError, match="no-contact runs must be >= 1, got 0"):
        NoContact(None, None, [], runs=0)


def test_a_test_on_the_scalar_variant_switches_it_back_after_it(photon_mi):
    """``scalar_mi``'s switch restores the variant it found: the photon pass' tests that
    follow run on their vectorised variant whatever order the tests run in."""
    from conftest import switched_variant

    before = photon_mi.variant()
    with switched_variant("scalar_spectral") as mi:
        assert mi.variant() == "scalar_spectral"
    assert photon_mi.variant() == before != "scalar_spectral"
