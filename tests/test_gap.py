"""The sim-to-real gap diagnosis: paired datasets, metrics, effects, fitting, report, CLI."""

from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path

import numpy as np
import pytest
import trimesh

from scenes.camera import Camera, reference_depth
from scenes.cli import main
from scenes.contact import press
from scenes.dataset import DatasetError, DatasetWriter, read_samples, write_sample_files
from studies.gap import effects as fx
from studies.gap import metrics
from studies.gap.benchmark import score
from studies.gap.model import FastModel
from studies.gap.pairs import load_pairs, split
from studies.gap.regions import region_names
from studies.gap.report import headline

PROTOCOL = {"name": "test", "taps": 16}
#: Contact pixels spread over the image: on the axis, the tip, the body, near the LEDs.
PIXELS = [(320, 240), (250, 200), (400, 300), (200, 330), (460, 180), (150, 240), (320, 90), (320, 400),
          (520, 260), (120, 150), (380, 420), (260, 120)]


@pytest.fixture(scope="module")
def contacts(spec, mesh, camera):
    """Depth maps of spheres and a cylinder pressed 1.5 mm into the membrane."""
    ref, _ = reference_depth(mesh, camera)
    shapes = [trimesh.primitives.Sphere(radius=0.004), trimesh.creation.cylinder(radius=0.003, height=0.01)]
    out = []
    for i, pixel in enumerate(PIXELS):
        out.append(press(ref, camera, mesh, shapes[i % 2], pixel, 0.0015))
    return np.stack(out)


def write_dataset(root: Path, source: str, spec, images, depths=None, protocol=PROTOCOL, renderer=None,
                  objects=("sphere", "cylinder")) -> Path:
    meta = {"source": source, "sensor": dataclasses.asdict(spec),
            "protocol": {"name": protocol["name"], "seed": None, "taps": len(images)},
            "renderer": renderer or {"renderer": "phong", "field": "plane", "background": "none", "rectify": False},
            "image_size": [images.shape[2], images.shape[1]]}
    writer = DatasetWriter(root, meta, protocol)
    for i, image in enumerate(images):
        sid = f"{i:06d}_{objects[i % len(objects)]}"
        files = write_sample_files(root, sid, image, None if depths is None else depths[i])
        writer.append({"id": sid, "object": objects[i % len(objects)], "path": i // 4, "position": i % 4,
                       "tap_index": i, "measured_depth": 0.0015, **files})
    return root


@pytest.fixture(scope="module")
def injector(spec):
    from studies.gap.inject import Injector

    return Injector(spec, field="plane", background="solid")


@pytest.fixture(scope="module")
def sim_images(injector, contacts):
    return np.stack([injector.render(d) for d in contacts])


@pytest.fixture(scope="module")
def sim_dir(tmp_path_factory, spec, sim_images, contacts):
    renderer = {"renderer": "phong", "field": "plane", "background": "solid", "rectify": False}
    return write_dataset(tmp_path_factory.mktemp("gap") / "sim", "sim", spec, sim_images, contacts, renderer=renderer)


def real_dataset(root: Path, spec, injector, contacts, effects: list) -> Path:
    rng = np.random.default_rng(0)
    images = np.stack([injector.render(d, effects, rng) for d in contacts])
    return write_dataset(root, "real", spec, images)


# --- metrics ------------------------------------------------------------------------------


def test_improvement_is_significant_only_when_it_is():
    rng = np.random.default_rng(1)
    before = rng.uniform(0.05, 0.06, 30)
    better = metrics.improvement(before, before * 0.5, "mae")
    assert better["significant"] and better["share"] == pytest.approx(0.5, rel=1e-6)
    noise = metrics.improvement(before, before + rng.normal(0, 0.005, 30), "mae")
    assert not noise["significant"] or noise["low"] < 0.002
    worse = metrics.improvement(before, before * 1.2, "mae")
    assert not worse["significant"] and worse["share"] < 0
    assert metrics.improvement(np.full(5, 20.0), np.full(5, 25.0), "psnr")["mean"] == pytest.approx(5.0)


# --- effects, analytic ----------------------------------------------------------------------


def test_optics_functions_analytic():
    f, centre = 240.0, (239.5, 319.5)
    # six stretches of 0.2 in r: the first's log fall-off 1, the third's 0.5
    v = fx.vignette((480, 640), f, centre, [1.0, 0.0, 0.5, 0.0, 0.0, 0.0], 1.2)
    assert v[240, 320] == pytest.approx(1.0, abs=2e-2)  # half a pixel off the centre
    assert v[240, 320 + 120] == pytest.approx(math.exp(-1.25), rel=1e-2)  # r = 0.5: half the third
    assert v[240, 320 + 240] == pytest.approx(math.exp(-1.5), rel=1e-3)  # r = 1, past the third
    assert np.all(np.diff(v[240, 320:]) <= 0)  # monotone outwards
    assert fx.vignette_length(np.ones((480, 640), bool), f) == pytest.approx(
        math.hypot(319.5, 239.5) / f + fx.VIGNETTE_CENTRE_PX / f)
    grid = fx.source_coordinates((480, 640), f, centre, None, None)
    assert np.allclose(grid[0], np.arange(480)[:, None]) and np.allclose(grid[1], np.arange(640)[None])
    shifted = fx.source_coordinates((480, 640), f, centre,
                                    {"du_px": 3.0, "dv_px": -2.0, "rotation_rad": 0.0, "scale": 1.0}, None)
    assert np.allclose(shifted[1] - grid[1], 3.0) and np.allclose(shifted[0] - grid[0], -2.0)
    pincushion = fx.source_coordinates((480, 640), f, centre, None, {"k1": 0.1, "k2": 0.0})
    # pixel (row 240, col 560) of the real image, r_d from the centre (239.5, 319.5), looks
    # at r_u in the simulated one: r_d = r_u (1 + k1 r_u^2) (Brown, as the reference's lens)
    dv, du = pincushion[0][240, 560] - 239.5, pincushion[1][240, 560] - 319.5
    r_u, r_d = math.hypot(du, dv) / f, math.hypot(0.5, 240.5) / f
    assert r_u * (1 + 0.1 * r_u**2) == pytest.approx(r_d, abs=1e-6) and du / dv == pytest.approx(240.5 / 0.5)
    img = np.random.default_rng(0).random((1, 48, 64, 3)).astype(np.float32)
    assert np.allclose(fx.resample(img, fx.source_coordinates((48, 64), 60.0, (23.5, 31.5), None, None)), img)
    assert np.allclose(fx.camera_response(img, np.eye(3), 0.0, 1.0), img)
    assert np.allclose(fx.camera_response(img, np.eye(3), 0.0, 2.0), np.sqrt(img), atol=1e-6)
    # A source over elevations 0.2 (1 -+ 0.3): a band (0, 10] hides all of it, (0, 0.2] half.
    assert fx.shadow_factor(np.zeros(3), np.array([0.0, 10.0, 0.2]), 0.2, 1.0).tolist() == pytest.approx([1, 0, 0.5])


@pytest.mark.parametrize("k1, k2", [(0.2, 0.05), (-0.2, 0.0), (-0.45, 0.0)])
def test_the_catalogues_lens_is_the_references_lens(camera, k1, k2):
    """One lens convention: the fast catalogue's lens_distortion resamples an image as the
    reference's sensor.distort does, at the same k1 and k2 (a pincushion, a barrel, and a
    barrel folding inside the frame, black past the fold in both)."""
    from pbr_tactile.sensor import distort

    h, w = 120, 160
    v, u = np.mgrid[0:h, 0:w]
    image = np.stack([0.5 + 0.4 * np.sin(u / 9.0), 0.5 + 0.4 * np.cos(v / 7.0), 0.3 + 0.002 * u], -1).astype(np.float32)
    s = h / camera.height
    coords = fx.source_coordinates((h, w), camera.f * s, (camera.cy * s, camera.cx * s), None, {"k1": k1, "k2": k2})
    catalogue, reference = fx.resample(image[None], coords)[0], distort(image, camera, k1, k2)
    # where both read the image (at its edge OpenCV blends in the black border, scipy not)
    inner = (coords[0] >= 0) & (coords[0] <= h - 1) & (coords[1] >= 0) & (coords[1] <= w - 1)
    assert inner.mean() > 0.15 and np.abs(catalogue - reference)[inner].max() < 0.01
    assert np.abs(catalogue - image)[inner].mean() > 0.02  # the lens did move the image
    assert np.abs(catalogue - reference).mean() < 0.002
    if k1 < -0.4:  # the fold at r_d 0.54 f: the corners see nothing in either
        assert catalogue[0, 0].max() == reference[0, 0].max() == 0.0


def test_camera_response_is_a_colour_matrix_an_offset_and_a_curve():
    """out = clip(C in + o)^(1/gamma) with any 3x3 C: it mixes, darkens and brightens."""
    params = {"gain_r": 0.6, "gain_g": 0.5, "gain_b": 1.2, "mix_rg": -0.2, "mix_rb": 0.1, "mix_gr": 0.3,
              "mix_gb": 0.0, "mix_br": -0.1, "mix_bg": 0.05, "offset": -0.02, "gamma": 2.0}
    C = fx.colour_matrix(params)
    assert np.allclose(C, [[0.6, -0.2, 0.1], [0.3, 0.5, 0.0], [-0.1, 0.05, 1.2]])
    pixel = np.array([[[[0.5, 0.4, 0.3]]]], np.float32)
    by_hand = [math.sqrt(0.6 * 0.5 - 0.2 * 0.4 + 0.1 * 0.3 - 0.02), math.sqrt(0.3 * 0.5 + 0.5 * 0.4 - 0.02),
               math.sqrt(min(-0.1 * 0.5 + 0.05 * 0.4 + 1.2 * 0.3 - 0.02, 1.0))]
    assert fx.camera_response(pixel, C, -0.02, 2.0)[0, 0, 0].tolist() == pytest.approx(by_hand, abs=1e-6)
    identity = {p.name: p.identity for p in fx.catalogue(3, 5.0)["camera_response"].params}
    assert np.array_equal(fx.colour_matrix(identity), np.eye(3)) and identity["offset"] == 0.0
    darker = fx.camera_response(pixel, 0.5 * np.eye(3), 0.0, 1.0)
    assert darker[0, 0, 0].tolist() == pytest.approx([0.25, 0.2, 0.15])


def test_light_functions_analytic():
    P = np.zeros((3, 1, 2))
    P[:, 0, 0] = (0.0, 0.0, 0.01)
    P[:, 0, 1] = (0.0, 0.0, 0.02)
    N = np.zeros_like(P)
    N[2] = -1.0
    k = fx.leak_kernel(P, N, (0.0, 0.0, 0.0), length_m=0.01)
    assert k[0].tolist() == pytest.approx([0.5, 0.2])  # 1 / (1 + (d / l)^2), cos = 1
    # Beer-Lambert at 100 per metre: each stretch of a 60 mm profile has depth 100 x its length
    kept = fx.fade(fx.fade_ramps(np.array([0.0, 0.01, 0.025]), 0.06), [6.0 / fx.FADE_KNOTS] * fx.FADE_KNOTS)
    assert kept.tolist() == pytest.approx([1.0, math.exp(-1.0), math.exp(-2.5)], rel=1e-5)
    colours = np.eye(3)
    same = fx.spectral_colours(colours, [465, 625, 525], [25, 20, 35], [0, 0, 0], [1, 2, 1], floor=0.05)
    assert np.allclose(same, np.diag([1, 2, 1]))
    # A red LED 15 nm bluer: a pure Gaussian blue band's tail grows tenfold; the filter's
    # out-of-band floor keeps the blue response near what it was.
    bare = fx.spectral_colours(np.ones((1, 3)), [625], [20], [-15], [1])[0]
    floored = fx.spectral_colours(np.ones((1, 3)), [625], [20], [-15], [1], floor=0.02)[0]
    assert bare[2] > 5 and 1.0 < floored[2] < 1.5
    assert floored[0] == pytest.approx(bare[0], rel=0.05)  # the in-band red barely feels the floor
    ref = np.full((4, 4), 0.03)
    depth = ref - 0.001
    assert np.allclose(fx.compliant_depth(ref, depth, 1.0), depth)
    assert np.allclose(fx.compliant_depth(ref, depth, 0.5), ref - 0.0005)


def _flat_membrane(box_rows, box_cols, height_m, ridge_cols=None, ridge_m=0.0):
    """A flat membrane 20 mm in front of a 40 x 80 px camera (f = 100 px), and a box
    ``height_m`` high pushed towards the camera over ``box_rows`` x ``box_cols``; an
    undeformed ridge ``ridge_m`` high over ``ridge_cols`` if given."""
    h, w, f = 40, 80, 100.0
    camera = (f, (w - 1) / 2, (h - 1) / 2)
    v, u = np.mgrid[0:h, 0:w]
    rays = np.stack([(u - camera[1]) / f, (v - camera[2]) / f, np.ones((h, w))]).astype(np.float32)
    ref = np.full((h, w), 0.02, np.float32)
    if ridge_cols is not None:
        ref[:, ridge_cols] -= ridge_m
    depth = ref.copy()
    depth[box_rows, box_cols] -= height_m
    L = np.zeros((1, 3, h, w), np.float32)
    L[0, 0] = 1.0  # the LED lies towards +x (increasing columns)
    inward = np.zeros((3, h, w), np.float32)
    inward[2] = -1.0  # towards the camera
    return depth, ref, rays, camera, L, inward, np.ones((h, w), bool)


def test_shadow_band_of_a_box_on_a_flat_membrane():
    """Light from +x at a low elevation: a 0.4 mm box (columns 50-59, 0.2 mm per px)
    hides the light below atan(0.4 / s) from a point s mm before it, on the side away
    from the LED, and nothing on the LED's side or beside it."""
    depth, ref, rays, camera, L, inward, where = _flat_membrane(slice(15, 25), slice(50, 60), 0.0004)
    low, high = fx.occlusion_band(depth, ref, rays, camera, L, inward, where, 1e-5)
    for col in (30, 40, 45):
        s = (49.5 - col) * 0.0002
        assert low[0, 20, col] == 0.0
        assert high[0, 20, col] == pytest.approx(math.atan(0.0004 / s), rel=0.15), col
    assert np.all(high[0, :, 62:] == 0.0)  # the LED's side of the box
    assert np.all(high[0, 30:, :48] == 0.0)  # beside it: the light passes the box by
    kept = fx.shadow_factor(low, high, 0.05, 0.8)
    assert kept[0, 20, 40] == pytest.approx(0.2) and kept[0, 20, 70] == 1.0
    # The undeformed membrane rising more steeply first (a ridge, columns 42-44, 0.5 mm):
    # light low enough to meet the box has come off the ridge; only light above the
    # ridge's elevation and below the box's is blocked, none of it for the column behind.
    depth, ref, rays, camera, L, inward, where = _flat_membrane(slice(15, 25), slice(50, 60), 0.0009,
                                                                slice(42, 45), 0.0005)
    low, high = fx.occlusion_band(depth, ref, rays, camera, L, inward, where, 1e-5)
    # From column 30 the ridge rises to atan(0.5 / 2.3) = 0.21 rad, the box to atan(0.9 / 3.9) = 0.23.
    assert 0.15 < low[0, 20, 30] < high[0, 20, 30] < 0.25
    assert fx.shadow_factor(low, high, 0.05, 1.0)[0, 20, 30] == 1.0


def test_catalogue_names_and_identity(spec):
    cat = fx.catalogue(len(spec.leds), spec.elastic.sigma_px)
    assert tuple(cat) == fx.EFFECTS == ("core_light_leak", "path_attenuation", "membrane_compliance",
                                        "elastic_spread", "coating_gloss", "contact_shadow", "camera_response",
                                        "vignetting", "lens_distortion", "misalignment", "blur_noise",
                                        "led_spectrum")
    for effect in cat.values():
        for p in effect.params:
            assert p.low <= p.identity <= p.high, (effect.name, p.name)


# --- the decomposed simulator --------------------------------------------------------------


def test_phong_terms_by_hand_and_shade_composes_them():
    """On the axis, N = V = (0, 0, -1): light at angle t from N gives L . N = cos t and
    R . V = 2 cos t - cos t = cos t; from behind the surface L . N clamps to 0 and
    R . V = -L . V = -cos t. shade is exactly the composition of those terms."""
    from phong_reference.phong import compose, led_intensities, shade, shading_terms
    from scenes.spec import LED, Material

    t = np.array([0.0, 0.6, 2.0])  # the last comes from behind the surface: clamped to 0
    P = np.tile(np.array([0.0, 0.0, 0.02], np.float32)[:, None], (1, 3))
    N = np.tile(np.array([0.0, 0.0, -1.0], np.float32)[:, None], (1, 3))
    L = np.stack([np.sin(t), 0 * t, -np.cos(t)]).astype(np.float32)[None]
    background = np.full((3, 3), 0.2, np.float32)
    material = Material(ambient=0.5, shininess=3.0)
    terms = shading_terms(P, N, L, material, background)
    cos = np.maximum(np.cos(t), 0)
    RV = np.abs(np.cos(t))
    assert terms.LN[0] == pytest.approx(cos, abs=1e-6) and terms.RV[0] == pytest.approx(RV, abs=1e-6)
    assert terms.specular[0] == pytest.approx(RV**3, abs=1e-6) and terms.ambient == pytest.approx(0.1)
    assert terms.LN.dtype == np.float32
    led = LED("l", (0, 0, 0), (0, 0, 1), (1.0, 0.5, 0.25), k_d=0.9, k_s=0.3)
    composed = compose(led_intensities(terms, [0.9], [0.3]), [led.colour], terms.ambient)
    assert np.array_equal(composed, shade(P, N, L, [led], material, background))
    assert composed[:, 1] == pytest.approx(0.1 + (0.9 * cos[1] + 0.3 * cos[1] ** 3) * np.array([1, 0.5, 0.25]))


def test_model_shades_with_the_fast_paths_own_terms(spec, contacts):
    """The diagnosis' model takes its per-LED terms from phong_reference, not a copy."""
    from phong_reference.phong import shading_terms

    model = FastModel(spec, {"field": "plane", "background": "solid"}, factor=4)
    g = model.geometry(model.working_depth(contacts[:1])[0])
    expected = shading_terms(g["P"], g["N"], model.L, spec.material, model.B.transpose(2, 0, 1))
    for got, want in zip(g["terms"], expected):
        assert np.array_equal(got, want)


def test_model_reproduces_the_fast_path_and_identity_changes_nothing(spec, sim_images, contacts):
    model = FastModel(spec, {"field": "plane", "background": "solid"}, factor=1)
    for i in (0, 3):
        assert np.abs(model.physical(contacts[i], {}) - sim_images[i]).max() < 1e-5
    cat = model.catalogue
    sim = np.round(sim_images[:2] * 255) / 255
    for name in fx.EFFECTS:
        pred = model.predict(sim, contacts[:2], {name: cat[name].identity}, keys=[0, 1])
        assert np.abs(pred - sim).max() < 1e-5, name
    changed = model.predict(sim, contacts[:2], {"membrane_compliance": {"scale": 0.5}}, keys=[0, 1])
    assert np.abs(changed - sim).max() > 0.05


def test_an_auto_exposed_capture_fits_every_candidate_with_its_exposure(spec, sim_images, contacts):
    """A camera that sets its own exposure scales the whole image when an effect changes
    the frame's brightness: every candidate but camera_response (which has gains) is then
    fitted with that gain, and its prediction is scaled by it."""
    from studies.gap.model import auto_exposed

    assert auto_exposed({"renderer": {"camera": {"kind": "device", "exposure": "auto"}}})
    assert not auto_exposed({"renderer": {"camera": {"kind": "twin", "exposure": "fixed"}}})
    assert not auto_exposed({"renderer": {"renderer": "phong"}}) and not auto_exposed({})
    plain = FastModel(spec, {"field": "plane", "background": "solid"}, factor=4)
    model = FastModel(spec, {"field": "plane", "background": "solid"}, factor=4, exposure=True)
    assert model.ties_to_simplest and not plain.ties_to_simplest
    for name, effect in model.catalogue.items():
        names = [p.name for p in effect.params]
        assert ("exposure" in names) == (name != "camera_response"), name
        assert names[:len(plain.catalogue[name].params)] == [p.name for p in plain.catalogue[name].params]
    sim = model.working_images(np.round(sim_images[:2] * 255) / 255) * np.float32(0.4)
    depth = model.working_depth(contacts[:2])
    vignetting = model.catalogue["vignetting"].identity
    assert vignetting["exposure"] == 1.0
    same = model.predict(sim, depth, {"vignetting": vignetting})
    assert np.abs(same - sim).max() < 1e-6
    brighter = model.predict(sim, depth, {"vignetting": {**vignetting, "exposure": 2.0}})
    assert np.allclose(brighter, np.clip(2 * sim, 0, 1), atol=1e-6)
    # in a combination the capture's exposure is one gain: the product of the effects' own
    both = {"vignetting": {**vignetting, "exposure": 1.5},
            "blur_noise": {**model.catalogue["blur_noise"].identity, "exposure": 1.2}}
    assert fx.exposure_scale(both) == pytest.approx(1.8)


def test_path_attenuation_of_the_background_dims_it_along_the_sensor(spec):
    """No contact on a solid background: the image is the background term k_a B. Its
    weight makes it keep exp(-w tau(d)), d the path from the LEDs' ring (on the cylinder
    the height above the LEDs, on the tip that plus the arc to it) or the height along the
    axis; without it only the LEDs' light fades and the background stays. The tip dims most."""
    model = FastModel(spec, {"field": "plane", "background": "solid"}, factor=4)
    m = spec.membrane
    apex = m.base_z + m.cylinder_length + 0.5 * math.pi * m.radius  # the LEDs are at z = 0
    # Paths along the edges of near-equilateral triangles zigzag: up to 2 / sqrt(3) times the
    # true geodesic (a constant factor along the axis, which the fitted depths take up), from
    # a ring of vertices up to one edge below the LEDs.
    zigzag = 2 / math.sqrt(3)
    assert apex < model.base_distance[60, 80] < zigzag * (apex + m.mesh_edge)  # the apex, on the axis
    side = (60, 25)  # the cylinder, near its visible end
    height = float(model.ref[side] * model.rays[2][side])
    assert height < model.base_distance[side] < zigzag * (height + m.mesh_edge)
    assert model.axial[side] == pytest.approx(height, abs=1e-6)  # the LEDs sit at z = 0
    assert model.fade_length == pytest.approx(max(model.base_distance.max(), model.axial.max()))
    plain = model.physical(model.ref, {})
    depths = {f"depth_{k}": 0.1 * (k + 1) for k in range(fx.FADE_KNOTS)}
    length, knots = model.fade_length, fx.FADE_KNOTS
    for weight in (0.0, 0.5, 1.0):
        for share in (0.0, 1.0):
            p = {**depths, "axial_share": share, "led_weight": 1.0, "ambient_weight": weight}
            faded = model.physical(model.ref, {"path_attenuation": p})
            for pixel in ((60, 80), side):
                d = (model.axial if share else model.base_distance)[pixel]
                # tau by hand: the whole stretches below d, and the share of the one it ends in
                k, rest = int(d * knots / length), d * knots / length % 1.0
                tau = sum(0.1 * (j + 1) for j in range(min(k, knots))) + (0.1 * (k + 1) * rest if k < knots else 0.0)
                kept = math.exp(-weight * tau)
                assert (faded[pixel] / plain[pixel]).tolist() == pytest.approx([kept] * 3, rel=1e-3)
            if weight:
                assert faded[60, 80].sum() / plain[60, 80].sum() < 0.8 * faded[side].sum() / plain[side].sum()


def test_the_fade_profile_is_monotone_and_beer_lambert_when_even():
    """tau(d) is piecewise linear through its stretches' depths, never falls as d grows,
    stops growing past the last knot, and is mu d (Beer-Lambert) where every depth is alike."""
    length, knots = 0.06, fx.FADE_KNOTS
    d = np.linspace(0.0, 0.08, 161)
    ramps = fx.fade_ramps(d, length)
    assert ramps.shape == (knots, d.size)
    rng = np.random.default_rng(0)
    kept = fx.fade(ramps, rng.uniform(0.0, 2.0, knots))
    assert kept[0] == 1.0 and np.all(np.diff(kept) <= 0.0)
    assert np.all(kept[d >= length] == kept[-1])
    mu = 40.0  # per metre: each stretch of length / knots metres has depth mu length / knots
    even = fx.fade(ramps, [mu * length / knots] * knots)
    inside = d <= length
    assert even[inside] == pytest.approx(np.exp(-mu * d[inside]), rel=1e-5)
    assert fx.fade_distances(np.array(2.0), np.array(4.0), 0.25) == pytest.approx(2.5)


# --- bad input -----------------------------------------------------------------------------


def test_pairs_of_some_samples_take_only_those_from_both(tmp_path, spec, sim_dir, sim_images):
    """A replay of some of a capture's presses (``bench real --diagnosis-presses``) pairs
    with the capture on its own samples only: ``ids`` names them, and each side must hold
    every one."""
    short = write_dataset(tmp_path / "short", "real", spec, sim_images[:5])
    every = [r["id"] for r in read_samples(sim_dir)]
    pairs = load_pairs(sim_dir, short, ids=every[1:4])
    assert pairs.ids == every[1:4] and pairs.real.shape[0] == pairs.sim.shape[0] == 3
    np.testing.assert_array_equal(pairs.real, load_pairs(sim_dir, sim_dir).real[1:4])
    with pytest.raises(DatasetError, match=r"short lacks 2 of the sample\(s\) asked for: 000005_cylinder"):
        load_pairs(sim_dir, short, ids=every[3:7])
    with pytest.raises(ValueError, match="ids must name at least one sample"):
        load_pairs(sim_dir, short, ids=[])


def test_pairs_refuse_bad_datasets(tmp_path, spec, sim_dir, sim_images):
    other = write_dataset(tmp_path / "other", "real", spec, sim_images[:3], protocol={"name": "else", "taps": 3})
    with pytest.raises(DatasetError, match="different protocols"):
        load_pairs(other, sim_dir)
    short = write_dataset(tmp_path / "short", "real", spec, sim_images[:5])
    with pytest.raises(DatasetError, match=r"short lacks 7 sample\(s\).*000005_cylinder"):
        load_pairs(short, sim_dir)
    corrupt = write_dataset(tmp_path / "corrupt", "real", spec, sim_images)
    (corrupt / "images" / "000004_sphere.png").write_bytes(b"not a png")
    with pytest.raises(DatasetError, match="sample 000004_sphere.*could not be read"):
        load_pairs(corrupt, sim_dir)
    missing = write_dataset(tmp_path / "missing", "real", spec, sim_images)
    (missing / "images" / "000002_sphere.png").unlink()
    with pytest.raises(DatasetError, match="sample 000002_sphere: image images/000002_sphere.png is missing"):
        load_pairs(missing, sim_dir)
    small = write_dataset(tmp_path / "small", "real", spec, sim_images[:, ::2, ::2])
    with pytest.raises(DatasetError, match=r"\[320, 240\] px images .* same image size"):
        load_pairs(small, sim_dir)
    wrong = write_dataset(tmp_path / "wrong", "real", spec, sim_images)
    from PIL import Image

    Image.new("RGB", (64, 48)).save(wrong / "images" / "000001_cylinder.png")
    with pytest.raises(DatasetError, match="sample 000001_cylinder.*must be 640x480"):
        load_pairs(wrong, sim_dir)
    with pytest.raises(DatasetError, match="not a dataset"):
        load_pairs(tmp_path / "nowhere", sim_dir)


@pytest.mark.parametrize("sensor, names", [("geltip", ("tip", "body", "near_leds")),
                                           ("gelsight", ("centre", "rim", "near_leds"))])
def test_the_gap_is_split_into_the_sensors_own_regions(sensor, names):
    """The GelTip's gap by tip, body and near the LEDs; the flat GelSight's by its pad's
    centre and rim, never a tip. The area near the LEDs is the third of the family's last
    region nearest an LED; the regions split the image circle."""
    from scenes.spec_read import load_spec
    from studies.gap.regions import region_labels

    spec = load_spec(Path(__file__).resolve().parents[1] / "scenes" / "sensors" / f"{sensor}.toml")
    spec = spec.at_resolution(160, 120)
    labels = region_labels(spec)
    assert tuple(labels) == region_names(spec) == names
    masks = np.array(list(labels.values()))
    assert np.array_equal(masks.sum(axis=0), Camera.from_spec(spec).mask.astype(int))
    last = labels[names[1]] | labels["near_leds"]
    assert labels["near_leds"].sum() == pytest.approx(last.sum() / 3, abs=0.02 * last.sum())


def test_split_is_stratified_and_refuses_an_empty_side(tmp_path, spec, sim_images, contacts):
    one = write_dataset(tmp_path / "one", "sim", spec, sim_images[:1], contacts[:1])
    pairs = load_pairs(one, one)
    with pytest.raises(DatasetError, match="held-out split .* is empty"):
        split(pairs)
    full = load_pairs(write_dataset(tmp_path / "all", "sim", spec, sim_images, contacts),
                      tmp_path / "all")
    train, heldout = split(full, 0.5, seed=3)
    assert train.sum() == heldout.sum() == 6 and not (train & heldout).any()
    objects = np.array([r["object"] for r in full.records])
    for obj in ("sphere", "cylinder"):
        assert train[objects == obj].sum() == heldout[objects == obj].sum() == 3


# --- the diagnosis, end to end ----------------------------------------------------------


@pytest.mark.slow
@pytest.mark.parametrize("hidden", ["membrane_compliance"])
def test_diagnosis_names_a_hidden_effect(tmp_path, spec, injector, contacts, sim_dir, hidden):
    """A strong hidden effect, injected by the benchmark's own injector, is ranked first
    and most of the held-out gap closes. One contact effect here (30 s a case); the blind
    benchmark (studies/gap/benchmark.py) hides every effect, the camera's response too."""
    rng = np.random.default_rng(5)
    effect = injector.sample(hidden, rng, strength=0.8)
    real = real_dataset(tmp_path / "real", spec, injector, contacts, [effect])
    code = main(["diagnose", str(real), str(sim_dir), "--out", str(tmp_path / "report"), "--quiet",
                 "--intervals", "0"])  # parameter intervals: test_gap_physical (they double this test's time)
    assert code == 0
    report = json.loads((tmp_path / "report" / "report.json").read_text())
    assert report["ranking"][0] == hidden, report["ranking"]
    assert report["effects"][hidden]["share_closed"]["masked"] > 0.5
    assert report["explained"]["share_closed"]["masked"] > 0.5
    # held-out samples are judged per region too: a contact effect closes where contacts are
    closed = report["explained"]["share_closed"]
    names = region_names(spec)  # the GelTip's: its tip, its body, near the LEDs
    assert names == ("tip", "body", "near_leds")
    assert set(names) <= set(closed) and max(closed[r] for r in names) > 0.5
    assert set(names) <= set(report["gap"]["heldout"])
    assert set(report["effects"]) == set(fx.EFFECTS)
    html = (tmp_path / "report" / "report.html").read_text()
    assert hidden in html and "Which effect causes it" in html and "gap closed per region" in html
    assert any("per region:" in line for line in headline(report))
    for name in ("gap_maps.png", "gap_split.png", "effects.png", "examples.png"):
        assert (tmp_path / "report" / name).stat().st_size > 1000


@pytest.mark.slow
def test_diagnosis_without_a_gap_ranks_nothing(tmp_path, sim_dir):
    code = main(["diagnose", str(sim_dir), str(sim_dir), "--out", str(tmp_path / "same"), "--quiet",
                 "--effects", "camera_response,vignetting,led_spectrum"])
    assert code == 0
    report = json.loads((tmp_path / "same" / "report.json").read_text())
    assert report["ranking"] == [] and report["selection"] == []
    assert report["gap"]["heldout"]["masked"]["mae"]["mean"] == 0.0


def test_cli_refuses_bad_arguments(tmp_path, sim_dir, capsys):
    assert main(["diagnose", str(sim_dir)]) == 2
    with pytest.raises(SystemExit):
        main(["diagnose", str(sim_dir), str(sim_dir), "--out", str(tmp_path), "--effects", "sparkle"])
    assert "unknown: sparkle" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(["diagnose", str(sim_dir), str(sim_dir), "--out", str(tmp_path), "--intervals", "-1"])
    assert "--intervals: expected a whole number >= 0, got '-1'" in capsys.readouterr().err
    assert main(["diagnose", str(tmp_path / "nowhere"), str(sim_dir), "--out", str(tmp_path / "r")]) == 1
    assert "is not a dataset" in capsys.readouterr().err
    assert main(["diagnose", "benchmark", "--cases", "1"]) == 2
    assert main(["diagnose", "benchmark", "--json", str(tmp_path / "b.json"), "--hidden", "contact_shadow"]) == 2
    assert "--hidden needs --stratified" in capsys.readouterr().err


def test_benchmark_scoring():
    report = {"ranking": ["vignetting", "blur_noise", "misalignment"],
              "explained": {"effects": ["vignetting"], "share_closed": {"masked": 0.7}},
              "effects": {"vignetting": {"share_closed": {"masked": 0.6}}}}
    s = score(["vignetting"], report)
    assert s["top1"] and s["top3"] and s["shrink"] == 0.7 and s["shrink_top1"] == 0.6
    s = score(["misalignment", "led_spectrum"], report)
    assert not s["top1"] and not s["top3"]
    assert not score(["vignetting"], {**report, "ranking": []})["top1"]


def test_stratified_benchmark_covers_every_cell_and_scores_it():
    from studies.gap.benchmark import (
        STRATIFIED_BACKGROUNDS,
        _draw_stratified,
        stratified_cells,
        stratify,
    )
    from studies.gap.inject import EFFECTS

    from studies.gap.unlike import BACKGROUNDS, MECHANISMS

    cells = stratified_cells()
    written = sum(len(BACKGROUNDS[m]) for m in MECHANISMS)  # a mechanism on each of its backgrounds
    assert len(cells) == len(set(cells)) == len(EFFECTS) * len(STRATIFIED_BACKGROUNDS) + written
    assert cells[:len(EFFECTS)] == [(e, "none", None) for e in EFFECTS]  # the injector's cells keep their index
    assert {(c[2], c[0]) for c in cells[-written:]} == set(MECHANISMS.items())
    assert {c[1] for c in cells if c[2] == "frame_move"} == {"real", "solid"}
    draws = [_draw_stratified(case, case, 100, 10, 0.5) for case in range(len(cells))]
    assert {(d["hidden"][0], d["background"], d["mechanism"]) for d in draws} == set(cells)
    assert all(d["strength"] == 0.5 and len(d["samples"]) == 10 for d in draws)
    results = [{"hidden": ["vignetting"], "background": "none", "top1": True, "shrink": 0.8, "shrink_top1": 0.7,
                "noise_share": 0.0},
               {"hidden": ["vignetting"], "background": "none", "top1": False, "shrink": 0.4, "shrink_top1": 0.3,
                "noise_share": 0.0},
               {"hidden": ["vignetting"], "background": "solid", "top1": True, "shrink": 0.9, "shrink_top1": 0.9,
                "noise_share": 0.0},
               {"hidden": ["blur_noise"], "background": "none", "top1": True, "shrink": 0.1, "shrink_top1": 0.1,
                "noise_share": 0.8},
               {"hidden": ["vignetting"], "background": "none", "mechanism": "dusk", "top1": True, "shrink": 0.65,
                "shrink_top1": 0.65, "noise_share": 0.0}]
    out = stratify(results, 0.5)
    # A mechanism written unlike the catalogue is a cell of its own, scored like the others.
    assert out["per_cell"]["vignetting/dusk"]["none"]["cases"] == 1
    assert out["per_cell"]["vignetting"]["none"] == {"cases": 2, "top1": 0.5, "shrink": pytest.approx(0.6),
                                                     "shrink_top1": pytest.approx(0.5), "noise_share": 0.0}
    assert out["min_cell_shrink"] == pytest.approx(0.6) and out["min_cell"] == "vignetting x none"
    assert list(out["noise_cells"]) == ["blur_noise x none"] and "80%" in out["noise_cells"]["blur_noise x none"]


def test_stratified_cases_keep_their_index_when_filtered():
    from studies.gap.benchmark import stratified_cases, stratified_cells

    cells = stratified_cells()
    assert stratified_cases(40) == list(range(40))
    chosen = stratified_cases(len(cells), ("contact_shadow", "led_spectrum"))
    assert len(chosen) == 6 and {cells[c][0] for c in chosen} == {"contact_shadow", "led_spectrum"}
    assert {cells[c][1] for c in chosen} == {"none", "solid", "real"}
    turned = stratified_cases(len(cells), ("misalignment",))
    assert len(turned) == 6 and cells[turned[3]] == ("misalignment", "real", "frame_turn")
    # A mechanism's name picks its cells alone; three runs' worth of cases give three draws each.
    moved = stratified_cases(3 * len(cells), ("frame_move",))
    assert len(moved) == 6 and {cells[c % len(cells)][1] for c in moved} == {"real", "solid"}
    with pytest.raises(ValueError, match="hidden must be"):
        stratified_cases(36, ("sparkle",))


def test_sector_areas_partition_the_image_circle(camera):
    from studies.real_background_gap import sector_areas

    areas = sector_areas(camera, 12)
    assert areas.shape == (12,) + camera.shape
    assert np.array_equal(areas.sum(axis=0), camera.mask.astype(int))
    sizes = areas.sum(axis=(1, 2))
    assert sizes.min() > 0.95 * sizes.max()


@pytest.mark.slow
def test_real_background_study(tmp_path, reference_dir):
    """The one real capture: the light leaking through the core explains most of it."""
    from studies.real_background_gap import run

    # without the parameter intervals: their two bootstrap refits cost most of the run (test_gap_physical checks them)
    summary = run(tmp_path, fields=("plane",), reference_dir=reference_dir, intervals=0)
    plane = summary["fields"]["plane"]
    assert plane["ranking"] and plane["ranking"][0] == "core_light_leak"
    assert plane["share_closed"]["masked"] > 0.5
    for name in ("membrane_compliance", "elastic_spread", "contact_shadow"):
        assert not plane["single"][name]["significant"]
    assert (tmp_path / "plane" / "report.html").exists() and "cannot tell" in (tmp_path / "summary.md").read_text()


def test_the_answer_names_candidates_whose_image_and_contact_shares_disagree():
    from studies.gap.report import _contact_lines

    def imp(masked, contact):
        return {"masked": {"mae": dict(zip(("share", "share_low", "share_high"), masked))},
                "contact": {"mae": dict(zip(("share", "share_low", "share_high"), contact))}}

    report = {"gap_contact": {"mae": {"mean": 0.05, "low": 0.04, "high": 0.06}},
              "effects": {"camera_response": {"heldout": {"improvement": imp((0.5, 0.4, 0.6), (0.05, -0.02, 0.1))}},
                          "blur_noise": {"heldout": {"improvement": imp((0.1, 0.05, 0.15), (0.12, 0.08, 0.2))}}}}
    lines = _contact_lines(report, "camera_response")
    assert lines[0].startswith("Over the contacts alone camera_response closes 5.0% [-2.0, 10.0]")
    assert "disagree (95% intervals apart) on camera_response (50% [40, 60] of the image circle's gap, 5% [-2, 10] of " \
           "the contacts')" in lines[1] and "blur_noise" not in lines[1]
    report["effects"]["camera_response"]["heldout"]["improvement"] = imp((0.5, 0.4, 0.6), (0.45, 0.3, 0.6))
    assert len(_contact_lines(report, "camera_response")) == 1  # they agree: no second line


def test_a_sure_but_tiny_closure_explains_nothing_and_the_answer_says_so():
    """A candidate whose held-out improvement is significant but closes 0.2 % of the gap
    is not named as a cause; with nothing ranked, the Answer says that nothing explains
    the gap, gives the closest candidates' shares and where the gap lies."""
    from studies.gap.judge import MIN_RANK_SHARE, Judged
    from studies.gap.report import headline

    def judged(share: float, significant: bool) -> Judged:
        mae = {"significant": significant, "mean": share * 0.1, "share": share, "share_low": share / 2,
               "share_high": share * 2}
        return Judged(fit=None, after={}, improvement={"masked": {"mae": mae}})

    assert not judged(0.002, True).explains
    assert not judged(0.4, False).explains
    assert judged(MIN_RANK_SHARE, True).explains and judged(0.4, True).explains
    # a gap mostly of sensor noise: the bar is a share of the rest (here 0.002 of MAE removed)
    noisy = judged(0.02, True)
    noisy.min_gain = 0.001
    assert noisy.explains
    noisy.min_gain = 0.003
    assert not noisy.explains
    mae = {"mean": 0.05, "low": 0.04, "high": 0.06}
    effect = {"heldout": {"improvement": {"masked": {"mae": {"share": 0.002, "share_low": 0.001,
                                                              "share_high": 0.003}}}}}
    report = {"gap": {"heldout": {"masked": {"mae": mae, "ssim": mae, "psnr": mae}, "full": {"mae": mae}}},
              "where": {"regions": {"tip": {"samples": 4, "mae": {**mae, "mean": 0.09}},
                                    "body": {"samples": 4, "mae": mae}},
                        "channels": {"r": {"mae": mae}}},
              "ranking": [], "selection": [], "effects": {"misalignment": effect},
              "noise": {"std": 0.0, "mae_floor": 0.0}}
    text = " ".join(headline(report))
    assert "No candidate explains the gap" in text
    assert "misalignment closes 0.2%" in text
    assert text.index("tip MAE") < text.index("body MAE")  # the worst region first


def test_described_cases_take_each_mechanism_in_turn_at_spread_strengths(tmp_path, sim_dir, capsys):
    """The benchmark of mechanisms written from prose: every mechanism once at strength
    0.5 before any comes again, then at 0 and 1; a case keeps its mechanism and strength
    whatever the run's length; and it is a benchmark of its own."""
    from studies.gap.benchmark import described_cases, run_benchmark
    from studies.gap.described import MECHANISMS

    n = len(MECHANISMS)
    cases = described_cases(3 * n)
    assert [m for m, _ in cases[:n]] == list(MECHANISMS) == [m for m, _ in cases[n:2 * n]]
    assert {s for _, s in cases[:n]} == {0.5} and {s for _, s in cases[n:2 * n]} == {0.0}
    assert {s for _, s in cases[2 * n:]} == {1.0}
    assert described_cases(n + 2)[:n + 1] == described_cases(n + 1)
    with pytest.raises(ValueError, match="separate benchmarks"):
        run_benchmark(cases=1, stratified=True, described=True, progress=False)
    assert main(["diagnose", "benchmark", "--described", "--stratified", "--json", str(tmp_path / "b.json")]) == 2
    assert "--described" in capsys.readouterr().err
