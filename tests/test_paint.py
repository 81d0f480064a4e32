"""The membrane's paint (``pbr_tactile.paint``): one BRDF for volpath and the photon estimator."""

from __future__ import annotations

import math

import numpy as np
import pytest

from pbr_tactile.effects import Effects
from pbr_tactile.paint import Paint

PAINTS = [Paint(0.85, 1.0, 0.15), Paint(0.6, 0.5, 0.3), Paint(0.4, 0.2, 0.8)]


def _mitsuba():
    mi = pytest.importorskip("mitsuba", reason="Mitsuba 3 is not installed (pip install '.[pbr]')")
    from pbr_tactile.variant import choose_variant

    try:
        mi = choose_variant()
    except Exception as exc:  # noqa: BLE001 - any variant failure is a skip reason here
        pytest.skip(f"no usable Mitsuba variant: {exc}")
    if not mi.variant().startswith(("llvm_", "cuda_")):
        pytest.skip(f"the paint's lobe is evaluated in a vectorised variant, got {mi.variant()}")
    import drjit as dr

    return mi, dr


def _directions(rng, n):
    v = rng.normal(size=(n, 3))
    v[:, 2] = np.abs(v[:, 2]) + 0.05
    return v / np.linalg.norm(v, axis=1, keepdims=True)


@pytest.mark.parametrize("paint", PAINTS)
def test_the_lobe_the_photons_evaluate_is_the_bsdf_volpath_renders(paint):
    """Paint.glossy_cos plus the diffuse lobe against Mitsuba's own evaluation of
    Paint.mitsuba(), from both sides of the surface (twosided)."""
    mi, dr = _mitsuba()
    rng = np.random.default_rng(1)
    wi, wo = _directions(rng, 64), _directions(rng, 64)
    wo[:16] = wi[:16] * [-1, -1, 1] + 0.05 * rng.normal(size=(16, 3))  # near the mirror direction
    wo[:, 2] = np.abs(wo[:, 2]) + 0.01
    wo /= np.linalg.norm(wo, axis=1, keepdims=True)
    bsdf = mi.load_dict(paint.mitsuba())
    for side in (1.0, -1.0):
        si = dr.zeros(mi.SurfaceInteraction3f, len(wi))
        si.n = mi.Normal3f(0.0, 0.0, side)
        si.sh_frame = mi.Frame3f(mi.Normal3f(0.0, 0.0, 1.0))
        if mi.is_spectral:
            si.wavelengths = dr.full(mi.Spectrum, 550.0, len(wi))
        flip = np.array([1.0, 1.0, side])
        si.wi = mi.Vector3f(*(wi * flip).T.astype(np.float32))
        theirs = np.asarray(bsdf.eval(mi.BSDFContext(), si, mi.Vector3f(*(wo * flip).T.astype(np.float32))))[0]
        normal = mi.Vector3f(0.0, 0.0, side)
        lobe = paint.glossy_cos(mi, dr, normal, mi.Vector3f(*(wi * flip).T.astype(np.float32)),
                                mi.Vector3f(*(wo * flip).T.astype(np.float32)))
        ours = paint.gloss * np.asarray(lobe) + paint.diffuse / math.pi * wo[:, 2]
        np.testing.assert_allclose(ours, theirs, rtol=2e-4, atol=1e-7)


@pytest.mark.parametrize("paint", PAINTS)
def test_a_sampled_flake_direction_carries_the_lobes_albedo(paint):
    """E[weight] of Paint.sample_glossy is the lobe's directional albedo, the quadrature
    of glossy_cos over the hemisphere, at three angles of incidence."""
    mi, dr = _mitsuba()
    n = 1 << 18
    rng = np.random.default_rng(2)
    normal = mi.Vector3f(0.0, 0.0, 1.0)
    # Quadrature on a (theta, phi) grid, fine near the pole where the lobe can be sharp.
    t = np.linspace(0, 1, 801)[1:] - 1 / 1600
    theta = 0.5 * math.pi * t**2
    phi = (np.arange(400) + 0.5) * 2 * math.pi / 400
    T, P = np.meshgrid(theta, phi, indexing="ij")
    d_omega = (np.sin(T) * (math.pi * t[:, None] / 800) * (2 * math.pi / 400)).ravel()
    out = np.c_[(np.sin(T) * np.cos(P)).ravel(), (np.sin(T) * np.sin(P)).ravel(), np.cos(T).ravel()]
    for incidence in (0.1, 0.8, 1.3):
        wi = np.array([math.sin(incidence), 0.0, math.cos(incidence)], np.float32)
        u = mi.Point2f(*rng.random((2, n)).astype(np.float32))
        d, weight = paint.sample_glossy(mi, dr, normal, mi.Vector3f(*[np.full(n, c, np.float32) for c in wi]), u)
        weight = np.asarray(weight)
        assert np.all(weight >= 0) and np.all(weight <= paint.albedo + 1e-6)
        assert np.all(np.asarray(d.z)[weight > 0] > 0)
        lobe = np.asarray(paint.glossy_cos(mi, dr, normal, mi.Vector3f(*[np.full(len(out), c, np.float32) for c in wi]),
                                           mi.Vector3f(*out.T.astype(np.float32))))
        albedo = float((lobe * d_omega).sum())
        assert weight.mean() == pytest.approx(albedo, rel=0.01, abs=4 * weight.std() / math.sqrt(n))


def test_a_paint_is_checked_and_its_matte_key_is_its_albedo():
    assert Paint.of(0.5) == Paint(0.5) and Paint.of(Paint(0.5, 0.2)) == Paint(0.5, 0.2)
    assert Paint(0.85).key() == (0.85,) and not Paint(0.85).glossy
    assert Paint(0.8, 0.5, 0.2).key() == (0.8, 0.5, 0.2) and Paint(0.8, 0.5).diffuse == pytest.approx(0.4)
    assert Paint.from_effects(Effects(coating_gloss=0.3, coating_roughness=0.2)) == Paint(0.85, 0.3, 0.2)
    assert Paint(0.8).mitsuba() == {"type": "twosided",
                                    "material": {"type": "diffuse", "reflectance": {"type": "rgb", "value": [0.8] * 3}}}
    for bad, match in (({"albedo": 1.2}, r"paint albedo must be in \[0, 1\], got 1.2"),
                       ({"albedo": 0.5, "gloss": -0.1}, r"paint gloss must be in \[0, 1\], got -0.1"),
                       ({"albedo": 0.5, "roughness": 0.0}, r"paint roughness must be in \[0.001, 1\], got 0.0")):
        with pytest.raises(ValueError, match=match):
            Paint(**bad)
    with pytest.raises(ValueError, match=r"Effects.coating_roughness must be in \[0.001, 1\], got 2"):
        Effects(coating_roughness=2)


@pytest.fixture(scope="module")
def lit(mesh, spec, camera, photon_mi):
    """The default GelTip's undeformed scene, loaded, and its photon sources."""
    import tempfile

    from pbr_tactile.membrane import ElastomerBuilder
    from pbr_tactile.photons import sources_from
    from pbr_tactile.render import load
    from pbr_tactile.scene import geltip_scene, led_sources, write_meshes

    mi = photon_mi
    effects = Effects()
    solid = ElastomerBuilder(mesh, spec, camera, 1e-3)()
    with tempfile.TemporaryDirectory() as folder:
        scene = geltip_scene(write_meshes(solid, folder), spec, camera, effects, 8, 6, spp=1)
        loaded = load(scene, mi.variant())[1]
    return mi, loaded, sources_from(led_sources(spec, effects)), effects


def test_the_lobe_map_weighs_each_arrival_by_the_lobe_towards_the_camera(lit):
    """A glossy paint's lobe map (``deposits(glossy=GlossyView)``) draws no random numbers
    (the maps are the same with and without it); its views are unit directions on the
    elastomer's side; and viewed along each vertex's normal a roughness-1 lobe's map lies
    within the bounds of its analytic BRDF."""
    from pbr_tactile.camera_pass import camera_views
    from pbr_tactile.photons import GlossyView, deposits

    mi, scene, srcs, fx = lit
    paint = Paint(0.6, 0.5, 0.3)
    args = (mi, scene, srcs, fx.sigma_t, fx.albedo, paint, 1 << 11)
    plain = deposits(*args, seed=5)
    view = camera_views(mi, scene)
    lobe = GlossyView(view.toward, view.normal)
    logged = deposits(*args, seed=5, glossy=lobe)
    np.testing.assert_allclose(logged, plain, rtol=1e-5, atol=1e-6 * plain.max())  # the sums' order may differ
    assert lobe.flux.shape == plain.shape and np.all(lobe.flux >= 0) and lobe.flux.sum() > 0
    # Each view is a unit direction on the elastomer's side of its vertex.
    np.testing.assert_allclose(np.linalg.norm(view.toward, axis=1), 1.0, atol=1e-6)
    assert np.mean(np.einsum("ij,ij->i", view.toward, view.normal) > 0) > 0.99
    # Viewed along the normal, a roughness-1 lobe is f(w_i) = rho / (2 pi (1 + cos_i)): D = 1 / pi
    # for every half vector, G1(n) = 1 and G1(w_i) = 2 cos_i / (1 + cos_i). So each vertex's
    # lobe flux lies between rho / (4 pi) and rho / (2 pi) of its flux (arrivals from below
    # a vertex's normal, on a curved face, add nothing).
    rough = Paint(0.6, 0.5, 1.0)
    along = GlossyView(view.normal, view.normal)
    flux = deposits(mi, scene, srcs, fx.sigma_t, fx.albedo, rough, 1 << 11, seed=5, glossy=along)
    assert np.all(along.flux <= flux * rough.albedo / (2 * math.pi) * (1 + 1e-4) + 1e-12)
    assert along.flux.sum() >= 0.99 * flux.sum() * rough.albedo / (4 * math.pi)
    assert along.flux.sum() <= 0.99 * flux.sum() * rough.albedo / (2 * math.pi)
    with pytest.raises(ValueError, match="the glossy view has 3 vertices, the coating"):
        deposits(*args, glossy=GlossyView(np.zeros((3, 3)), np.zeros((3, 3))))
    with pytest.raises(ValueError, match=r"a glossy view needs \(V, 3\) directions and normals"):
        GlossyView(np.zeros((3, 2)), np.zeros((3, 2)))


def test_a_glossy_paint_needs_its_lobe_maps(lit):
    from pbr_tactile.camera_pass import camera_pass

    mi, scene, srcs, fx = lit
    maps = np.zeros((len(srcs), 8))
    with pytest.raises(ValueError, match="a glossy paint's camera pass needs glossy_maps"):
        camera_pass(mi, scene, srcs, maps, fx.sigma_t, fx.albedo, Paint(0.8, 0.5), spp=1)
    with pytest.raises(ValueError, match=r"glossy_maps must be shaped as the maps, \(3, 8\), got \(3, 7\)"):
        camera_pass(mi, scene, srcs, maps, fx.sigma_t, fx.albedo, Paint(0.8, 0.5), spp=1,
                    glossy_maps=np.zeros((3, 7)))


def test_a_glossy_contact_takes_its_lobe_map_from_the_no_contact_runs_too(mesh, spec, camera, ref, tmp_path, photon_mi):
    """The no-contact control variate carries the lobe map as it does the irradiance:
    the runs' deposits hold a lobe part beside the flux, and a render from the memo
    they fill is the same render."""
    from pbr_tactile.membrane import ElastomerBuilder
    from pbr_tactile.render import render_photons
    from pbr_tactile.scene import geltip_scene, led_sources, write_meshes
    from scenes.contact import press
    from scenes.indenters import make_indenter

    pytest.importorskip("manifold3d", reason="building indenters needs the manifold boolean engine")
    effects = Effects(coating_gloss=0.5)
    depth = press(ref, camera, mesh, make_indenter("sphere"), (320, 150), 1.5e-3)
    build = ElastomerBuilder(mesh, spec, camera, 1e-3)

    def scene_of(solid, name):
        return geltip_scene(write_meshes(solid, tmp_path / name), spec, camera, effects, 8, 6, spp=1)

    scene, flat = scene_of(build(depth, ref), "contact"), scene_of(build(), "flat")
    memo: dict = {}
    kwargs = dict(photons=1 << 10, spp=1, passes=2, seed=3, pilot_scene=flat, no_contact_runs=1, use_cache=False)
    first = render_photons(scene, led_sources(spec, effects), effects, no_contact_memo=memo, **kwargs)
    matte_memo: dict = {}
    render_photons(scene, led_sources(spec, Effects()), Effects(), no_contact_memo=matte_memo, **kwargs)
    assert len(memo) > len(matte_memo) > 0  # a lobe part beside each run's flux
    again = render_photons(scene, led_sources(spec, effects), effects, no_contact_memo=memo, **kwargs)
    np.testing.assert_allclose(again.mean, first.mean, rtol=1e-4, atol=1e-6 * first.mean.max())
    assert np.all(np.isfinite(first.mean)) and first.mean.max() > 0
