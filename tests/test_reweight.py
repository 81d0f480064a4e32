"""Perturbation Monte Carlo (``pbr_tactile.reweight``): the photon pass re-weighted to other
media and paints. By hand first (the factor, the Kish ratio, the checks); then exactly on
the GelTip's walks (the traced values give the traced flux; switching scattering or the
paint off keeps exactly the paths without them; a straight path is scaled by exp(-d L)
with L its length); then statistically against walks traced at each variant with their
own seeds (those two, about 20-25 s each here, are marked slow); and the variance rule
that flags a variant too far from the traced one."""

from __future__ import annotations

import tempfile

import numpy as np
import pytest
from scipy import stats

from pbr_tactile.effects import Effects
from pbr_tactile.reweight import (
    MIN_ESS_RATIO,
    Perturbation,
    kish_ratio,
    path_factor_np,
    valid,
)

#: Each statistical comparison's false-alarm probability (fixed seeds: a failure is a
#: regression, not bad luck, but the bounds are set as if they were not fixed).
FALSE_ALARM = 1e-3


def test_a_perturbation_is_checked_by_name(mesh, spec, camera):
    with pytest.raises(ValueError, match=r"perturb must be \(K, 3\) variants of \(absorption_per_m, "
                                         r"scattering_per_m, coating_albedo\) with K >= 1, got shape \(2,\)"):
        Perturbation(np.array([1.0, 2.0]))
    with pytest.raises(ValueError, match=r"got shape \(0, 3\)"):
        Perturbation(np.zeros((0, 3)))
    with pytest.raises(ValueError, match=r"perturb's coating_albedo must be within Effects' range \[0, 1\], "
                                         r"got \[1.2\]"):
        Perturbation([[20.0, 50.0, 1.2]])
    with pytest.raises(ValueError, match=r"perturb's absorption_per_m must be within .* got \[-1.0\]"):
        Perturbation([[-1.0, 50.0, 0.8]])
    with pytest.raises(ValueError, match=r"got \[nan\]"):
        Perturbation([[20.0, np.nan, 0.8]])
    p = Perturbation.of([[10.0, 50.0, 0.85]])
    assert Perturbation.of(p) is p and len(p) == 1 and p.key() == [[10.0, 50.0, 0.85]]
    with pytest.raises(ValueError, match=r"scattering_per_m \[30.0\] cannot be re-weighted from a traced medium "
                                         r"without scattering"):
        Perturbation([[20.0, 30.0, 0.8]]).coefficients(20.0, 0.0, 0.85)
    with pytest.raises(ValueError, match=r"coating_albedo \[0.5\] cannot be re-weighted from a black traced paint"):
        Perturbation([[20.0, 0.0, 0.5]]).coefficients(20.0, 0.0, 0.0)
    # a variant without scattering, or with a black paint, is fine: its factor is 0 past the event
    c = Perturbation([[70.0, 0.0, 0.0]]).coefficients(70.0, 50 / 70, 0.85)
    assert c[0, 0] == -np.inf and c[0, 1] == 0.0 and c[0, 2] == -np.inf
    # to and from Effects: the three columns, the other fields the traced ones'
    traced = Effects(core_light_leak=0.5)
    variants = Perturbation([[10.0, 50.0, 0.85], [20.0, 90.0, 0.6]]).effects(traced)
    assert variants[1] == Effects(core_light_leak=0.5, scattering_per_m=90.0, coating_albedo=0.6)
    np.testing.assert_array_equal(Perturbation.of_effects(variants).values, [[10.0, 50.0, 0.85], [20.0, 90.0, 0.6]])
    from pbr_tactile.render import RenderSettings, reference

    with pytest.raises(ValueError, match=r"perturb \(re-weighted variants\) needs the photon estimator"):
        reference(None, None, mesh, spec, camera, Effects(), RenderSettings(estimator="volpath"),
                  perturb=[[10.0, 50.0, 0.85]])


def test_the_factor_by_hand():
    """f = (s'/s)^n exp(-(t' - t) L) (r'/r)^m, from the coefficients; a count of 0 gives
    1 whatever its coefficient; Dr.Jit's and NumPy's agree."""
    fx = Effects()
    p = Perturbation([[10.0, 100.0, 0.425], [fx.absorption_per_m, fx.scattering_per_m, fx.coating_albedo],
                      [fx.sigma_t, 0.0, 0.0]])
    c = p.coefficients(fx.sigma_t, fx.albedo, fx.coating_albedo)
    np.testing.assert_allclose(c[0], [np.log(2.0), 40.0, np.log(0.5)], rtol=1e-12)
    assert np.all(c[1] == 0.0)  # the traced values: exactly 1, though sigma_t albedo is off by an ulp
    L, n, m = np.array([0.0, 0.01, 0.02, 0.03]), np.array([0, 1, 2, 0]), np.array([0, 0, 1, 3])
    np.testing.assert_allclose(path_factor_np(c[0], L, n, m), 2.0**n * np.exp(-40.0 * L) * 0.5**m, rtol=1e-12)
    assert np.all(path_factor_np(c[1], L, n, m) == 1.0)
    np.testing.assert_array_equal(path_factor_np(c[2], L, n, m), [1.0, 0.0, 0.0, 0.0])
    mi = pytest.importorskip("mitsuba", reason="Mitsuba 3 is not installed (pip install '.[pbr]')")
    from pbr_tactile.reweight import path_factor
    from pbr_tactile.variant import VariantError, choose_variant

    try:
        mi = choose_variant()
    except VariantError as exc:
        pytest.skip(str(exc))
    if not mi.variant().startswith(("llvm_", "cuda_")):
        pytest.skip("Dr.Jit's factor needs a vectorised variant")
    import drjit as dr

    for row in c:
        got = path_factor(dr, row, mi.Float(L), mi.UInt32(n), mi.UInt32(m))
        np.testing.assert_allclose(np.asarray(got), path_factor_np(row, L, n, m), rtol=1e-6)


def test_kish_ratio_by_hand():
    # weights (1, 1, 1, 1): ESS 4; f = (1, 1, 0, 0): ESS 2; f = (2, 1, 1, 0): 16 / 6
    w = np.ones(4)
    rows = [w, w * [1, 1, 0, 0], w * [2, 1, 1, 0], np.zeros(4)]
    moments = np.array([[[r.sum(), (r**2).sum()]] for r in rows])
    np.testing.assert_allclose(kish_ratio(moments)[:, 0], [0.5, (16 / 6) / 4, 0.0])
    assert kish_ratio(np.zeros((2, 1, 2)))[0, 0] == 1.0  # no deposits: nothing to re-weight
    np.testing.assert_array_equal(valid(np.array([[0.9, MIN_ESS_RATIO], [0.9, MIN_ESS_RATIO * 0.99]])),
                                  [True, False])


@pytest.fixture(scope="module")
def lit(mesh, spec, camera, photon_mi):
    """The default GelTip's undeformed scene (1 mm edges), loaded; its photon sources; a
    coarse fluence grid; and the coating's vertex positions and areas."""
    from pbr_tactile.density import coating_areas, coating_vertices
    from pbr_tactile.membrane import ElastomerBuilder
    from pbr_tactile.photons import sources_from
    from pbr_tactile.render import load
    from pbr_tactile.scene import geltip_scene, led_sources, write_meshes

    mi = photon_mi
    effects = Effects()
    build = ElastomerBuilder(mesh, spec, camera, 1e-3)
    with tempfile.TemporaryDirectory() as folder:
        scene = geltip_scene(write_meshes(build(), folder), spec, camera, effects, 8, 6, spp=1)
        loaded = load(scene, mi.variant())[1]
    grid = build.grid(voxel=2e-3)
    return mi, loaded, sources_from(led_sources(spec, effects)), grid, coating_vertices(loaded), coating_areas(loaded)


def _window(lit, effects, photons):
    """A weight window from a pilot, as ``render_photons`` makes it: splitting and roulette."""
    from pbr_tactile.photons import deposits, weight_window

    mi, scene, srcs, _, _, area = lit
    pilot = deposits(mi, scene, srcs, effects.sigma_t, effects.albedo, effects.coating_albedo, photons // 8, seed=99)
    return weight_window(pilot / area, area, photons)


def test_the_traced_values_give_the_traced_deposits_and_the_same_walks(lit):
    """f = 1 at the traced values: the variant's flux and tracks are the traced ones, its
    ESS ratio 1; and what deposits returns beside the variants is what it returns without
    them (re-weighting draws no random numbers), splits and roulette included."""
    from pbr_tactile.photons import deposits

    mi, scene, srcs, grid, _, _ = lit
    fx = Effects()
    args = (mi, scene, srcs, fx.sigma_t, fx.albedo, fx.coating_albedo, 1 << 11)
    window = _window(lit, fx, 1 << 11)
    plain, track = deposits(*args, seed=3, window=window, grid=grid)
    (again, again_track), rw = deposits(*args, seed=3, window=window, grid=grid,
                                        perturb=[[fx.absorption_per_m, fx.scattering_per_m, fx.coating_albedo],
                                                 [10.0, 50.0, 0.85]])
    assert rw.flux.shape == (2, *plain.shape) and rw.track.shape == (2, *track.shape)
    tolerance = {"rtol": 1e-5, "atol": 1e-7}  # atomic sums in another order
    np.testing.assert_allclose(again, plain, **tolerance)
    np.testing.assert_allclose(again_track, track, **tolerance)
    np.testing.assert_allclose(rw.flux[0], plain, **tolerance)
    np.testing.assert_allclose(rw.track[0], track, **tolerance)
    np.testing.assert_allclose(rw.ess_ratio[0], 1.0, rtol=1e-4)
    assert np.all(rw.flux[1].sum(axis=1) > plain.sum(axis=1))  # less absorption, more light
    # without a grid: a pair (flux, Reweighted) with no tracks
    flux, rw = deposits(*args, seed=3, perturb=[[10.0, 50.0, 0.85]])
    assert flux.shape == plain.shape and rw.track is None and rw.moments.shape == (2, len(srcs), 2)


def test_sources_traced_alone_walk_as_they_do_among_the_whole_list(lit):
    """``deposits(streams=)``: sources traced alone with their places in the whole list
    deposit what they deposit traced with it (the same random numbers, splits and
    roulette included), so a render of the sources a change touches pairs with the
    others' render (``emitter_basis(only=)``). Without their places they walk otherwise."""
    from pbr_tactile.photons import deposits

    mi, scene, srcs, grid, _, _ = lit
    fx = Effects()
    window = _window(lit, fx, 1 << 11)
    medium = (fx.sigma_t, fx.albedo, fx.coating_albedo, 1 << 11)
    whole, track = deposits(mi, scene, srcs, *medium, seed=3, window=window, grid=grid)
    part = [1, len(srcs) - 1]
    alone, alone_track = deposits(mi, scene, [srcs[k] for k in part], *medium, seed=3, window=window[part], grid=grid,
                                  streams=part)
    tolerance = {"rtol": 1e-5, "atol": 1e-7}  # atomic sums in another order
    np.testing.assert_allclose(alone, whole[part], **tolerance)
    np.testing.assert_allclose(alone_track, track[part], **tolerance)
    elsewhere = deposits(mi, scene, [srcs[k] for k in part], *medium, seed=3, window=window[part])
    assert not np.allclose(elsewhere, whole[part], rtol=1e-2)
    with pytest.raises(ValueError, match=r"streams must be 2 distinct non-negative source places, got \[1, 1\]"):
        deposits(mi, scene, [srcs[k] for k in part], *medium, seed=3, streams=[1, 1])


def test_a_render_of_some_sources_refuses_places_it_cannot_take(mesh, spec, camera):
    """``reference(only=)`` and ``emitter_basis(only=)`` name the sources by their places in
    ``led_sources``' list: repeated or missing places, and a render that is not per source
    by photons, are refused before anything is traced."""
    from pbr_tactile.basis import emitter_basis
    from pbr_tactile.render import RenderSettings, reference
    from pbr_tactile.scene import led_sources

    count = len(led_sources(spec, Effects()))
    per_source = RenderSettings(per_source=True)
    for only in ([0, 0], [count], []):
        with pytest.raises(ValueError, match=rf"only must name distinct places among the {count} sources, got "):
            reference(None, None, mesh, spec, camera, Effects(), per_source, only=only)
    with pytest.raises(ValueError, match=r"only \(a subset of the sources\) needs the photon estimator and "
                                         r"per_source images"):
        reference(None, None, mesh, spec, camera, Effects(), RenderSettings(), only=[0])
    with pytest.raises(ValueError, match=r"only must name distinct places"):
        emitter_basis(spec, mesh, camera, Effects(), (8, 6), use_cache=False, only=[count + 2])


def test_switching_scattering_or_the_paint_off_keeps_exactly_the_paths_without_them(lit):
    """With path classes (``deposits(classes=True)``): a variant of the same sigma_t with
    no scattering has f = 1 on paths that did not scatter and 0 on the rest, so its flux
    is the traced flux of the classes without a scattering event, class for class; a black
    paint keeps the classes without a paint bounce. With the weight window's splits: the
    copies carry their path's counts."""
    from pbr_tactile.photons import PAINTED, PATH_CLASSES, SCATTERED, deposits

    mi, scene, srcs, _, _, _ = lit
    fx = Effects()
    window = _window(lit, fx, 1 << 11)
    tagged, rw = deposits(mi, scene, srcs, fx.sigma_t, fx.albedo, fx.coating_albedo, 1 << 11, seed=5,
                          window=window, classes=True,
                          perturb=[[fx.sigma_t, 0.0, fx.coating_albedo], [fx.absorption_per_m, fx.scattering_per_m,
                                                                          0.0]])
    scattered = np.array([bool(k & SCATTERED) for k in range(PATH_CLASSES)])
    painted = np.array([bool(k & PAINTED) for k in range(PATH_CLASSES)])
    tolerance = {"rtol": 1e-5, "atol": 1e-7}
    np.testing.assert_allclose(rw.flux[0][:, ~scattered], tagged[:, ~scattered], **tolerance)
    assert np.all(rw.flux[0][:, scattered] == 0.0) and tagged[:, scattered].sum() > 0
    np.testing.assert_allclose(rw.flux[1][:, ~painted], tagged[:, ~painted], **tolerance)
    assert np.all(rw.flux[1][:, painted] == 0.0) and tagged[:, painted].sum() > 0


def test_a_straight_path_is_scaled_by_its_absorption_along_its_length(lit, spec):
    """Traced without a medium, one photon per LED: its first deposit (class 0, straight
    from the LED in the elastomer to the paint) re-weighted to absorption d is exp(-d L),
    the same at the face's 3 vertices, with L its straight length: between the hit's
    distance from the LED's centre less and plus its radius."""
    from pbr_tactile.photons import deposits

    mi, scene, srcs, _, positions, _ = lit
    d = 100.0
    seen = 0
    for seed in range(12):
        tagged, rw = deposits(mi, scene, srcs, 0.0, 0.0, 0.85, 1, seed=seed, classes=True, perturb=[[d, 0.0, 0.85]])
        for s, src in enumerate(srcs):
            at = np.flatnonzero(tagged[s, 0] > 0)
            if len(at) == 0:
                continue  # this photon met the glass first
            seen += 1
            b = tagged[s, 0, at]  # weight 1: the barycentric shares
            assert b.sum() == pytest.approx(1.0, abs=1e-5) and len(at) <= 3
            ratio = rw.flux[0, s, 0, at] / b
            np.testing.assert_allclose(ratio, ratio[0], rtol=1e-5)
            length = -np.log(ratio[0]) / d
            hit = b @ positions[at]
            r = np.linalg.norm(hit - np.asarray(src.centre))
            assert r - src.radius * 1.001 - 1e-6 <= length <= r + src.radius * 1.001 + 1e-6, (length, r, src.radius)
    assert seen >= 12


def _bands(values: np.ndarray, count: int) -> np.ndarray:
    """(count, len(values)) bool: the values split into ``count`` bands of equal counts."""
    edges = np.quantile(values, np.linspace(0, 1, count + 1))
    band = np.clip(np.searchsorted(edges, values, side="right") - 1, 0, count - 1)
    return np.arange(count)[:, None] == band[None]


#: The variants re-weighted from Effects() (absorption 20/m, scattering 50/m, paint 0.85) and
#: compared with walks traced at each: two values of each parameter around the traced one.
VARIANTS = np.array([[10.0, 50.0, 0.85], [40.0, 50.0, 0.85], [20.0, 30.0, 0.85], [20.0, 90.0, 0.85],
                     [20.0, 50.0, 0.75], [20.0, 50.0, 0.95]])


@pytest.mark.slow
def test_reweighted_maps_and_fluence_agree_with_walks_traced_at_each_variant(lit):
    """For each of VARIANTS, the coating's flux and the tracks summed over regions (bands
    along the tube's axis, per LED) agree with walks traced at the variant, each from
    8 independent seeds. Per region, Welch's t of the two means (variances across the
    runs); a region fails beyond the t quantile at FALSE_ALARM over all regions and
    variants (Bonferroni), and the mean t^2 over a variant's regions must stay under 2.5
    (a t of 14 degrees of freedom has E[t^2] = 1.17). The test sees wrong factors: the
    traced walk itself (f = 1) fails it against each absorption and paint variant, and a
    scattering variant re-weighted without its (sigma_s' / sigma_s)^n (the absorption
    variant of the same sigma_t' - sigma_t) fails against its traced walks (the
    scattering coefficient alone changes the coating's light by a few per cent: the two
    terms of its factor nearly cancel)."""
    from pbr_tactile.photons import deposits

    mi, scene, srcs, grid, positions, _ = lit
    fx, photons, runs = Effects(), 1 << 11, 8
    window = _window(lit, fx, photons)
    coating_bands = _bands(positions[:, 2], 8)
    centres = grid.origin[2] + (np.arange(grid.shape[2]) + 0.5) * grid.voxel
    z = np.broadcast_to(centres, grid.shape).ravel()
    inside = grid.volume.ravel() > 0
    voxel_bands = _bands(z[inside], 6)

    def regions(flux, track):  # (S, regions): flux per coating band, then tracks per voxel band
        return np.concatenate([flux @ coating_bands.T, track[:, inside] @ voxel_bands.T], axis=1)

    # Each scattering variant's sigma_t' - sigma_t as an absorption change: its factor without (s' / s)^n.
    scattering = [k for k, v in enumerate(VARIANTS) if v[1] != fx.scattering_per_m]
    wrong = np.array([[fx.absorption_per_m + VARIANTS[k, 1] - fx.scattering_per_m, fx.scattering_per_m,
                       fx.coating_albedo] for k in scattering])
    reweighted, traced = [], []
    for run in range(runs):
        (flux, track), rw = deposits(mi, scene, srcs, fx.sigma_t, fx.albedo, fx.coating_albedo, photons,
                                     seed=1000 + run, window=window, grid=grid, perturb=np.r_[VARIANTS, wrong])
        traced.append(regions(flux, track))
        reweighted.append([regions(f, t) for f, t in zip(rw.flux, rw.track)])
    reweighted, traced = np.asarray(reweighted), np.asarray(traced)  # (runs, K + wrong, S, R), (runs, S, R)
    reweighted, without_n = reweighted[:, :len(VARIANTS)], reweighted[:, len(VARIANTS):]
    retraced = []
    for k, (sa, ss, rho) in enumerate(VARIANTS):
        e = Effects(absorption_per_m=sa, scattering_per_m=ss, coating_albedo=rho)
        retraced.append([regions(*deposits(mi, scene, srcs, e.sigma_t, e.albedo, rho, photons, seed=2000 + run,
                                           window=window, grid=grid)) for run in range(runs)])
    retraced = np.moveaxis(np.asarray(retraced), 1, 0)  # (runs, K, S, R)

    def welch(a, b):
        se = np.sqrt(a.var(axis=0, ddof=1) / len(a) + b.var(axis=0, ddof=1) / len(b))
        return (a.mean(axis=0) - b.mean(axis=0)) / se

    t = welch(reweighted, retraced)  # (K, S, R)
    bound = stats.t.ppf(1 - FALSE_ALARM / (2 * t.size), 2 * runs - 2)
    mean_t2 = np.mean(t.reshape(len(VARIANTS), -1) ** 2, axis=1)
    print(f"max |t| per variant {np.round(np.abs(t).reshape(len(VARIANTS), -1).max(axis=1), 2)} (bound "
          f"{bound:.2f}); mean t^2 {np.round(mean_t2, 2)}")
    assert np.all(np.abs(t) < bound)
    assert np.all(mean_t2 < 2.5)
    untouched = welch(np.repeat(traced[:, None], len(VARIANTS), axis=1), retraced)
    untouched = np.mean(untouched.reshape(len(VARIANTS), -1) ** 2, axis=1)
    without_n = np.mean(welch(without_n, retraced[:, scattering]).reshape(len(scattering), -1) ** 2, axis=1)
    print(f"mean t^2 of f = 1 {np.round(untouched, 1)}; of scattering without (s'/s)^n {np.round(without_n, 1)}")
    others = [k for k in range(len(VARIANTS)) if k not in scattering]
    assert np.all(untouched[others] > 10.0) and np.all(without_n > 10.0)


def test_a_variant_far_from_the_traced_one_is_not_valid(lit):
    """The ESS rule: near variants keep most of the traced deposits' effective sample
    size; twenty times the absorption keeps far less than MIN_ESS_RATIO."""
    from pbr_tactile.photons import deposits

    mi, scene, srcs, _, _, _ = lit
    fx = Effects()
    photons = 1 << 11
    _, rw = deposits(mi, scene, srcs, fx.sigma_t, fx.albedo, fx.coating_albedo, photons, seed=7,
                     window=_window(lit, fx, photons), perturb=[[10.0, 50.0, 0.85], [20.0, 50.0, 0.95],
                                                                [400.0, 50.0, 0.85]])
    print(f"ESS ratios {np.round(rw.ess_ratio, 3)}")
    np.testing.assert_array_equal(valid(rw.ess_ratio), [True, True, False])


def test_a_glossy_paints_lobe_is_reweighted_with_the_medium_and_its_albedo_refused(lit):
    """A glossy paint's flake-lobe flux is re-weighted as the flux is (its arrivals' weights
    times f): at the traced values it is the traced lobe, with less absorption it grows.
    Its albedo is refused: a flake bounce does not scale with it."""
    from pbr_tactile.camera_pass import camera_views
    from pbr_tactile.paint import Paint
    from pbr_tactile.photons import GlossyView, deposits
    from pbr_tactile.render import render_photons

    mi, scene, srcs, _, vertices, _ = lit
    fx = Effects()
    seen = camera_views(mi, scene)
    args = (mi, scene, srcs, fx.sigma_t, fx.albedo, Paint(fx.coating_albedo, 0.5, 0.3), 1 << 11)
    alone, view = GlossyView(seen.toward, seen.normal), GlossyView(seen.toward, seen.normal)
    plain = deposits(*args, seed=3, glossy=alone)
    flux, rw = deposits(*args, seed=3, glossy=view, perturb=[[fx.absorption_per_m, fx.scattering_per_m,
                                                                fx.coating_albedo], [5.0, 50.0, fx.coating_albedo]])
    tolerance = {"rtol": 1e-5, "atol": 1e-7}  # atomic sums in another order
    np.testing.assert_allclose(flux, plain, **tolerance)
    np.testing.assert_allclose(view.flux, alone.flux, **tolerance)
    assert rw.lobe.shape == (2, len(srcs), len(vertices)) and alone.flux.sum() > 0
    np.testing.assert_allclose(rw.lobe[0], alone.flux, **tolerance)
    np.testing.assert_allclose(rw.flux[0], plain, **tolerance)
    assert np.all(rw.lobe[1].sum(axis=1) > alone.flux.sum(axis=1))  # less absorption, more light in the lobe too
    with pytest.raises(ValueError, match=r"coating_albedo \[0.6\] cannot be re-weighted from a glossy traced paint "
                                         r"\(coating_gloss 0.5: a flake bounce does not scale with the albedo\)"):
        deposits(*args, seed=3, glossy=view, perturb=[[10.0, 50.0, 0.6]])
    with pytest.raises(ValueError, match=r"from a glossy traced paint \(coating_gloss 0.5"):
        render_photons({}, [], Effects(coating_gloss=0.5), perturb=[[20.0, 50.0, 0.6]])
    # without the lobe's view, no lobe is re-weighted
    assert deposits(*args, seed=3, perturb=[[5.0, 50.0, fx.coating_albedo]])[1].lobe is None


def test_a_control_or_a_medium_without_scattering_is_refused_with_variants():
    from pbr_tactile.render import render_photons

    fx = Effects()
    with pytest.raises(ValueError, match=r"perturb cannot be combined with a control variate"):
        render_photons({}, [], fx, control_spp=4, perturb=[[10.0, 50.0, 0.85]])
    with pytest.raises(ValueError, match="cannot be re-weighted from a traced medium without scattering"):
        render_photons({}, [], Effects(scattering_per_m=0.0), perturb=[[10.0, 50.0, 0.85]])


@pytest.mark.slow
@pytest.mark.parametrize("gloss", [0.0, 1.0])
def test_a_bases_variants_agree_with_bases_rendered_at_each_variant(mesh, spec, camera, ref, pressed, monkeypatch,
                                                                    photon_mi, gloss):
    """The diagnosis' render (``emitter_basis`` of a contact, with no-contact runs and the
    fluence): each variant's basis agrees with a basis rendered at its effects with
    another seed, pixel by pixel and source by source (z = difference over the root of the
    two variances of the mean, from the passes: few |z| > 3 and a mean z^2 near a t's),
    while the traced basis, against the same renders, is far off where the variant
    changes the image (absorption, paint). The identity is the basis
    rendered without variants (the same walks), and is cached under its own key too. A
    small film, few photons and 2 mm voxels: the test is of the plumbing (maps, fluence,
    no-contact runs, a camera pass per variant); the deposits' statistics are tested
    above. A glossy paint (its flake lobe's map re-weighted too) has the medium's variants
    only."""
    from pbr_tactile import render
    from pbr_tactile.basis import emitter_basis
    from pbr_tactile.membrane import ElastomerBuilder

    class CoarseVoxels(ElastomerBuilder):
        def grid(self, depth=None, ref_depth=None, voxel=2e-3):
            return super().grid(depth, ref_depth, voxel)

    passes = 6
    kw = dict(film=(16, 12), photons=1 << 11, spp=4, passes=passes, depth=pressed, ref_depth=ref,
              solids=CoarseVoxels(mesh, spec, camera, 1e-3), no_contact_runs=1)
    variants = np.array([[40.0, 50.0, 0.85], [20.0, 90.0, 0.85], [20.0, 50.0, 0.75]])[:2 if gloss else 3]
    paint = Effects(coating_gloss=gloss, coating_roughness=0.3)
    got = emitter_basis(spec, mesh, camera, paint, seed=1, perturb=variants, **kw)
    n_src, n_var = got["mean"].shape[-1], len(variants)
    assert got["variant_mean"].shape == (n_var, 12, 16, n_src) and got["ess_ratio"].shape == (n_var, n_src)
    np.testing.assert_array_equal(got["perturb"], variants)
    # absorption and paint keep most of the deposits' ESS; scattering 90 (1.8x) less
    near = [0] if gloss else [0, 2]
    assert np.all(got["valid"][near]) and np.all(got["ess_ratio"][near] > 0.7)
    assert np.all(got["ess_ratio"][1] < 0.9)
    plain = emitter_basis(spec, mesh, camera, paint, seed=1, use_cache=False, **kw)
    np.testing.assert_allclose(got["mean"], plain["mean"], rtol=1e-4, atol=1e-6 * plain["mean"].max())

    def no_render(*args, **kwargs):
        raise AssertionError("rendered again")

    with monkeypatch.context() as patched:
        patched.setattr(render, "reference", no_render)
        np.testing.assert_array_equal(emitter_basis(spec, mesh, camera, paint, seed=1, **kw)["mean"],
                                      got["mean"])
    # Without contact the maps are the no-contact runs' alone: a variant at the traced
    # values is the traced basis (f = 1, the same camera pass).
    flat = emitter_basis(spec, mesh, camera, paint, seed=1, use_cache=False, perturb=[[20.0, 50.0, 0.85]],
                         **{**kw, "depth": None, "ref_depth": None, "passes": 2})
    np.testing.assert_allclose(flat["variant_mean"][0], flat["mean"], rtol=1e-4, atol=1e-6 * flat["mean"].max())
    np.testing.assert_allclose(flat["ess_ratio"], 1.0, rtol=1e-3)
    z, off = [], []
    for k, (sa, ss, rho) in enumerate(variants):
        e = Effects(absorption_per_m=sa, scattering_per_m=ss, coating_albedo=rho, coating_gloss=gloss,
                    coating_roughness=0.3)
        again = emitter_basis(spec, mesh, camera, e, seed=2, use_cache=False, **kw)
        lit = (again["mean"] > 0) & (got["variant_mean"][k] > 0)
        assert lit.mean() > 0.5
        z.append(((got["variant_mean"][k] - again["mean"]) / np.sqrt(got["variant_variance"][k]
                                                                      + again["variance"]))[lit])
        off.append(((got["mean"] - again["mean"]) / np.sqrt(got["variance"] + again["variance"]))[lit])
    mean_z2, off_z2 = (np.array([np.mean(a**2) for a in zs]) for zs in (z, off))
    over_3 = np.array([np.mean(np.abs(a) > 3) for a in z])
    print(f"ESS ratios {np.round(got['ess_ratio'], 3).tolist()}; mean z^2 {np.round(mean_z2, 2)}, share |z| > 3 "
          f"{np.round(over_3, 4)}; the traced basis' mean z^2 {np.round(off_z2, 2)}")
    # Each z's variances are read from 6 passes a side: |z| > 3 about 1.5 % of the time
    # (Student's t of ~10 degrees of freedom), E[z^2] about 1.25; the bounds allow for the
    # pixels' correlation (they share each pass's maps).
    assert np.all(over_3 < 0.05) and np.all(mean_z2 < 2.5)
    # The scattering coefficient barely changes the image; the others are seen.
    assert off_z2[0] > 4.0 and (gloss or off_z2[2] > 4.0)


def test_the_calibrations_grid_traces_one_basis_and_retraces_what_is_not_valid():
    """``basis.grid_bases``: a grid of the medium's values is traced once, at its middle
    point, and re-weighted to the others; a point short of the ESS bound is traced
    again; a grid of anything else, a glossy paint, or a grid whose middle point cannot
    represent the others (no scattering) traces each point, as before."""
    import dataclasses

    from pbr_tactile.basis import grid_bases

    calls = []

    def basis_at(effects, perturb=None):
        calls.append((effects.absorption_per_m, effects.scattering_per_m, None if perturb is None else len(perturb)))
        mean = np.full((2, 2, 1), effects.absorption_per_m)
        out = {"mean": mean, "variance": mean / 10, "names": np.array(["led0"]), "response": np.ones((1, 3))}
        if perturb is not None:
            values = np.asarray(perturb)
            out.update(variant_mean=np.stack([np.full((2, 2, 1), v[0] + 1000) for v in values]),
                       variant_variance=np.stack([np.full((2, 2, 1), 1.0) for _ in values]),
                       ess_ratio=np.where(values[:, 1:2] > 100, 0.05, 0.9), valid=values[:, 1] <= 100)
        return out

    base = Effects()
    points = [{"absorption_per_m": a, "scattering_per_m": s} for a in (5.0, 20.0, 80.0) for s in (10.0, 50.0, 250.0)]
    bases, report = grid_bases(points, base, basis_at)
    assert calls[0] == (20.0, 50.0, 9)  # the middle point, with every point's variant
    assert sorted(calls[1:]) == [(5.0, 250.0, None), (20.0, 250.0, None), (80.0, 250.0, None)]  # not valid
    assert report["traced"] == {"absorption_per_m": 20.0, "scattering_per_m": 50.0}
    assert set(report["retraced"]) == {f"absorption_per_m={a:g}, scattering_per_m=250" for a in (5, 20, 80)}
    assert all(v == pytest.approx(0.05) for v in report["retraced"].values())
    assert len(report["reweighted"]) == 5
    for point, basis in zip(points, bases):
        if point["scattering_per_m"] == 250.0:  # traced again: its own effects
            assert basis["mean"].flat[0] == point["absorption_per_m"]
        elif point == report["traced"]:
            assert basis["mean"].flat[0] == 20.0
        else:  # re-weighted: the variant's
            assert basis["mean"].flat[0] == point["absorption_per_m"] + 1000
    # anything but the medium and the paint's albedo, or a glossy paint's albedo: each point traced
    glossy = dataclasses.replace(base, coating_gloss=0.3)
    for grid, paint in (([{"absorption_per_m": 5.0, "core_light_leak": 0.1}, {"absorption_per_m": 20.0,
                                                                              "core_light_leak": 0.1}], base),
                        ([{"coating_albedo": 0.6}, {"coating_albedo": 0.85}], glossy)):
        calls.clear()
        bases, report = grid_bases(grid, paint, basis_at)
        assert report is None and len(calls) == len(grid) and all(c[2] is None for c in calls)
    # a glossy paint's medium is re-weighted
    calls.clear()
    bases, report = grid_bases(points[:2], glossy, basis_at)
    assert report is not None and calls[0][2] == 2 and len(calls) == 1
    # nothing scatters anywhere: absorption alone is re-weighted
    calls.clear()
    bases, report = grid_bases([{"scattering_per_m": 0.0}, {"scattering_per_m": 0.0, "absorption_per_m": 9.0}], base,
                               basis_at)
    assert report is not None and calls[0][2] == 2 and len(calls) == 1
    # a walk without scattering cannot stand for one with it: the scattering point is traced
    calls.clear()
    bases, report = grid_bases([{"scattering_per_m": 0.0}, {"scattering_per_m": 22.0}], base, basis_at)
    assert calls[0] == (base.absorption_per_m, 22.0, 2)
