"""The gap benchmark's injector: plain renders untouched, every effect visible, physical
order, determinism, bad input refused, and the effects' analytic limits."""

import dataclasses
import math
from pathlib import Path

import numpy as np
import pytest
import trimesh

from phong_reference.background import make_background
from phong_reference.plugin import PhongDatasetRenderer
from scenes.contact import press
from scenes.elastic import deform
from scenes.spec import LED, Elastic
from studies.gap import inject, inject_image, inject_light
from studies.gap.inject import EFFECTS, Injection, Injector

ROOT = Path(__file__).resolve().parents[1]

#: "Clearly visible": mean absolute change over the measured region, linear RGB.
MIN_VISIBLE = 0.01


@pytest.fixture(scope="module")
def injector(spec):
    return Injector(spec)


@pytest.fixture(scope="module")
def solid_injector(spec):
    return Injector(spec, background="solid")


def _sphere(injector, pixel, radius, depth):
    cam = injector.camera
    return press(injector.ref_depth, cam, injector.mesh, trimesh.primitives.Sphere(radius=radius),
                 (cam.cx + pixel[0], cam.cy + pixel[1]), depth)


@pytest.fixture(scope="module")
def contacts(injector):
    """2 mm sphere contacts: near the axis, off the axis (where the optics bend and dim
    most), and two 1.5 mm bumps in a row (the outer one shadows the inner one's lit side)."""
    return {
        "axis": _sphere(injector, (30, -20), 0.004, 0.002),
        "off_axis": _sphere(injector, (130, 60), 0.004, 0.002),
        "pair": np.minimum(_sphere(injector, (50, 0), 0.002, 0.0015), _sphere(injector, (95, 0), 0.002, 0.0015)),
    }


def _region(injector, depth):
    """Where the membrane moved: the contact region."""
    return deform(depth, injector.ref_depth, injector.spec.elastic) < injector.ref_depth - 1e-6


# --- the plain render --------------------------------------------------------------------


@pytest.mark.parametrize("background", ["none", "solid"])
def test_no_injection_is_exactly_the_dataset_renderer(spec, mesh, camera, contacts, injector, solid_injector,
                                                      background):
    other = injector if background == "none" else solid_injector
    plugin = PhongDatasetRenderer(spec, mesh, camera, other.ref_depth, {"field": "plane", "background": background})
    for depth in contacts.values():
        expected = plugin.render(depth)
        assert np.array_equal(other.render(depth), expected)
        assert np.array_equal(other.render(depth, [], rng=None), expected)
    no_contact = other.ref_depth + 1e-7  # rasterisation noise: no contact, as the plugin says
    assert np.array_equal(other.render(no_contact), plugin.render(no_contact))


def test_array_background_matches_its_name(spec, camera, contacts, solid_injector):
    array = Injector(spec, background=make_background("solid", camera))
    assert np.array_equal(array.render(contacts["axis"]), solid_injector.render(contacts["axis"]))


# --- every effect ------------------------------------------------------------------------

#: The contact each effect is measured on: the optics act off the axis, the shadow needs
#: a second bump (a single convex imprint's lit side faces the light, with nothing between).
CONTACT_OF = {"vignetting": "off_axis", "lens_distortion": "off_axis", "contact_shadow": "pair"}


@pytest.mark.parametrize("effect", EFFECTS)
def test_each_effect_is_visible_when_weak_and_grows_with_strength(injector, contacts, effect):
    depth = contacts[CONTACT_OF.get(effect, "axis")]
    region = _region(injector, depth)
    plain = injector.render(depth)
    change = []
    for strength in (0.0, 1.0):
        injection = injector.sample(effect, np.random.default_rng(3), strength)
        image = injector.render(depth, [injection], rng=np.random.default_rng(4))
        assert image.shape == plain.shape and image.dtype == np.float32
        assert 0.0 <= image.min() and image.max() <= 1.0
        change.append(float(np.abs(image - plain)[region].mean()))
    assert change[0] >= MIN_VISIBLE, f"{effect} at strength 0 changes the contact by {change[0]:.4f}"
    assert change[1] > change[0], f"{effect}: strength 1 ({change[1]:.4f}) not above strength 0 ({change[0]:.4f})"


def test_a_single_imprint_shadows_only_the_background(injector, solid_injector, contacts):
    """Tangent light lights the slopes facing an LED, and nothing of a lone convex imprint
    stands between them and it; the background (no-contact guided light) is shadowed."""
    depth = contacts["axis"]
    region = _region(injector, depth)
    shadow = injector.sample("contact_shadow", np.random.default_rng(0), 0.0)
    assert np.abs(injector.render(depth, [shadow]) - injector.render(depth))[region].mean() < 0.002
    plain, shadowed = solid_injector.render(depth), solid_injector.render(depth, [shadow])
    assert np.all(shadowed <= plain + 1e-6)
    assert (plain - shadowed)[region].mean() > MIN_VISIBLE


@pytest.mark.parametrize("effect", EFFECTS)
def test_sampled_parameters_stay_in_their_ranges(injector, effect):
    rng = np.random.default_rng(11)
    for _ in range(5):
        injection = injector.sample(effect, rng)
        assert injection.effect == effect and 0.0 <= injection.strength <= 1.0
        assert all(math.isfinite(v) for v in injection.params.values())
        p = injection.params
        if effect == "elastic_spread":
            assert 2.0 <= p["sigma_px"] <= 3.5 or 7.0 <= p["sigma_px"] <= 11.0
        elif effect == "membrane_compliance":
            assert 0.4 <= p["depth_scale"] <= 0.85
        elif effect == "misalignment":
            assert 1.0 - 1e-9 <= math.hypot(p["shift_x_px"], p["shift_y_px"]) <= 6.0 + 1e-9
            assert math.radians(0.2) - 1e-12 <= abs(p["rotation"]) <= math.radians(2.0) + 1e-12
        elif effect == "lens_distortion":
            assert 0.05 <= abs(p["k1"]) <= 0.25 and abs(p["k2"]) <= 0.3 * abs(p["k1"])
        elif effect == "camera_response":
            assert 0.75 <= p["gamma_enc"] <= 0.9 or 1.15 <= p["gamma_enc"] <= 1.5
            assert p["gain_g"] == 1.0 and all(0.8 <= p[f"gain_{c}"] <= 1.25 for c in "rb")
        elif effect == "led_spectrum":
            shifts = [v for k, v in p.items() if k.startswith("peak_shift_nm_")]
            assert len(shifts) == len(injector.spec.leds) and all(5 <= abs(s) <= 25 for s in shifts)


# --- physical order ----------------------------------------------------------------------


@pytest.mark.parametrize("pair", [
    ("path_attenuation", "membrane_compliance"),
    ("contact_shadow", "coating_gloss"),
    ("vignetting", "misalignment"),
    ("blur_noise", "camera_response"),
    ("lens_distortion", "led_spectrum"),
])
def test_two_effects_in_either_order_give_the_same_image(injector, contacts, pair):
    depth = contacts["pair"]
    a, b = (injector.sample(effect, np.random.default_rng(5), 0.5) for effect in pair)
    ab = injector.render(depth, [a, b], rng=np.random.default_rng(6))
    ba = injector.render(depth, [b, a], rng=np.random.default_rng(6))
    assert np.array_equal(ab, ba)
    assert not np.array_equal(ab, injector.render(depth, [a], rng=np.random.default_rng(6)))


def test_optics_then_sensor_in_physical_order(injector, contacts):
    """Misalignment, then vignetting (fixed to the lens), then the camera's response."""
    depth = contacts["off_axis"]
    rng = np.random.default_rng(8)
    shift, vig, resp = (injector.sample(e, rng, 0.7) for e in ("misalignment", "vignetting", "camera_response"))
    cam = injector.camera
    p, q, r = shift.params, vig.params, resp.params
    expected = inject_image.misalign(injector.render(depth), p["shift_x_px"], p["shift_y_px"], p["rotation"],
                               (cam.cx, cam.cy))
    expected = inject_image.vignette(expected, (cam.cx + q["centre_dx_px"], cam.cy + q["centre_dy_px"]), q["focal_px"],
                               q["exponent"])
    C = np.array([[0.0, r["crosstalk_rg"], r["crosstalk_rb"]], [r["crosstalk_gr"], 0.0, r["crosstalk_gb"]],
                  [r["crosstalk_br"], r["crosstalk_bg"], 0.0]])
    C += np.diag(1.0 - C.sum(axis=1))
    expected = inject_image.respond(expected, r["gamma_enc"], [r["gain_r"], r["gain_g"], r["gain_b"]], C)
    got = injector.render(depth, [resp, vig, shift])
    assert np.allclose(got, np.clip(expected, 0, 1), atol=1e-6)


# --- determinism -------------------------------------------------------------------------


def test_sampling_and_noise_are_deterministic_with_a_seed(injector, contacts):
    for effect in EFFECTS:
        assert injector.sample(effect, np.random.default_rng(1)) == injector.sample(effect, np.random.default_rng(1))
    noisy = injector.sample("blur_noise", np.random.default_rng(2), 0.3)
    depth = contacts["axis"]
    first = injector.render(depth, [noisy], rng=np.random.default_rng(9))
    assert np.array_equal(first, injector.render(depth, [noisy], rng=np.random.default_rng(9)))
    assert not np.array_equal(first, injector.render(depth, [noisy], rng=np.random.default_rng(10)))
    shadow = injector.sample("contact_shadow", np.random.default_rng(2), 0.3)
    assert np.array_equal(injector.render(contacts["pair"], [shadow]), injector.render(contacts["pair"], [shadow]))


def test_noise_statistics_follow_the_variance_model(rng):
    image = np.full((200, 200, 3), 0.25, np.float32)
    noisy = inject_image.add_noise(image, a=0.002, b=0.005**2, rng=rng)
    assert np.var(noisy - image) == pytest.approx(0.002 * 0.25 + 0.005**2, rel=0.03)


# --- bad input ---------------------------------------------------------------------------


def test_bad_input_is_refused(injector, contacts):
    depth = contacts["axis"]
    rng = np.random.default_rng(0)
    with pytest.raises(ValueError, match="effect must be one of"):
        injector.sample("lens_flare", rng)
    with pytest.raises(ValueError, match="effect must be one of"):
        Injection("lens_flare", 0.5, {})
    for bad in (-0.1, 1.5, float("nan"), "0.5", True):
        with pytest.raises(ValueError, match="strength"):
            injector.sample("vignetting", rng, bad)
        with pytest.raises(ValueError, match="strength"):
            Injection("vignetting", bad, {})
    with pytest.raises(ValueError, match=r"params\['k1'\] must be a finite float"):
        Injection("lens_distortion", 0.5, {"k1": float("nan"), "k2": 0.0})
    with pytest.raises(ValueError, match="rng must be a numpy.random.Generator"):
        injector.sample("vignetting", 42)
    nan = depth.copy()
    nan[100, 100] = np.nan
    with pytest.raises(ValueError, match="depth has 1 NaN"):
        injector.render(nan)
    with pytest.raises(ValueError, match=r"depth must be \(480, 640\) float"):
        injector.render(depth[:, :320])
    with pytest.raises(ValueError, match=r"depth must be \(480, 640\) float"):
        injector.render(np.stack([depth] * 3, axis=-1))
    noise = injector.sample("blur_noise", rng)
    with pytest.raises(ValueError, match="rng must be a numpy.random.Generator for blur_noise"):
        injector.render(depth, [noise])
    with pytest.raises(ValueError, match="twice"):
        injector.render(depth, [noise, noise], rng=rng)
    with pytest.raises(ValueError, match="must hold Injection objects"):
        injector.render(depth, ["vignetting"])
    with pytest.raises(ValueError, match=r"needs params\['k2'\]"):
        injector.render(depth, [Injection("lens_distortion", 0.5, {"k1": 0.1})])
    with pytest.raises(ValueError, match="field must be one of"):
        Injector(injector.spec, field="radial")


def test_injector_imports_nothing_else_from_its_package(absolute_imports):
    own = {"studies.gap.inject", "studies.gap.inject_image", "studies.gap.inject_light"}
    for module in own:
        for name in absolute_imports(ROOT / "studies" / "gap" / f"{module.rsplit('.', 1)[1]}.py"):
            assert not (name == "studies.gap" or name.startswith("studies.gap.")) or name in own, (module, name)


# --- analytic limits ---------------------------------------------------------------------


def test_full_compliance_and_no_attenuation_leave_the_image(injector, contacts):
    depth = contacts["axis"]
    assert np.array_equal(inject.comply(depth, injector.ref_depth, 1.0), depth)
    plain = injector.render(depth)
    for injection in (Injection("membrane_compliance", 0.0, {"depth_scale": 1.0}),
                      Injection("path_attenuation", 0.0, {"mu": 0.0}),
                      Injection("core_light_leak", 0.0, {"gain": 0.0, "reference_distance": 0.01}),
                      Injection("led_spectrum", 0.0, {f"{k}_{led.name}": float(k == "intensity")
                                                       for led in injector.spec.leds
                                                       for k in ("peak_shift_nm", "intensity")})):
        # The full-frame chain against the windowed one: equal up to float rounding.
        assert np.allclose(injector.render(depth, [injection]), plain, atol=1e-5), injection.effect


def test_compliance_scales_the_imprint():
    ref = np.full((4, 4), 0.03, np.float32)
    depth = ref - np.float32(0.002)
    assert np.allclose(inject.comply(depth, ref, 0.4), ref - 0.4 * 0.002)


def test_optics_identities(injector, contacts):
    image = injector.render(contacts["off_axis"])
    cam = injector.camera
    assert np.array_equal(inject_image.misalign(image, 0.0, 0.0, 0.0, (cam.cx, cam.cy)), image)
    assert np.array_equal(inject_image.vignette(image, (cam.cx, cam.cy), cam.f, 0.0), image)
    assert np.allclose(inject_image.distort(image, cam, 0.0, 0.0), image, atol=1e-6)
    assert np.allclose(inject_image.respond(image, 1.0, np.ones(3), np.eye(3)), image, atol=1e-7)


def test_vignetting_is_cos_n_of_the_field_angle():
    image = np.ones((5, 401, 3), np.float32)
    out = inject_image.vignette(image, (200.0, 2.0), 100.0, 4.0)
    assert out[2, 200, 0] == pytest.approx(1.0)
    assert out[2, 300, 0] == pytest.approx(math.cos(math.pi / 4) ** 4, rel=1e-6)  # r = f: 45 degrees


def test_misalignment_shifts_by_whole_pixels():
    image = np.zeros((20, 30, 3), np.float32)
    image[5, 7] = 1.0
    out = inject_image.misalign(image, 3.0, -2.0, 0.0, (14.5, 9.5))
    assert out[3, 10, 0] == pytest.approx(1.0) and out.sum() == pytest.approx(3.0)


def test_lens_distortion_moves_points_as_brown_conrady(injector):
    """A pixel of the distorted image looks at the ideal radius r with r (1 + k1 r^2 + k2 r^4)
    equal to its own radius."""
    cam = injector.camera
    k1, k2 = 0.2, -0.04
    map_x, map_y = inject_image.distortion_maps(cam, k1, k2)
    row, col = 239, 500  # distorted radius (500 - 319.5) / f, just off the row of the centre
    r = math.hypot(map_x[row, col] - cam.cx, map_y[row, col] - cam.cy) / cam.f
    assert r * (1 + k1 * r**2 + k2 * r**4) == pytest.approx(math.hypot(col - cam.cx, row - cam.cy) / cam.f, rel=1e-5)
    # Barrel distortion past its fold: the corners see nothing.
    map_x, _ = inject_image.distortion_maps(cam, -0.25, 0.0)
    assert map_x[0, 0] == -1 and map_x[240, 320] == pytest.approx(320.0, abs=1e-3)


def test_camera_response_keeps_grey_grey():
    grey = np.full((2, 2, 3), 0.5, np.float32)
    C = np.array([[0.9, 0.05, 0.05], [0.1, 0.8, 0.1], [0.02, 0.08, 0.9]])
    assert np.allclose(inject_image.respond(grey, 1.25, np.ones(3), C), 0.5 ** (1 / 1.25), atol=1e-6)


def test_core_leak_is_an_inverse_square_point_source():
    led = LED("l", (0.0, 0.0, 0.0), (0, 0, 1), (1.0, 0.5, 0.25), k_d=0.9, k_s=0.1)
    P = np.array([0.0, 0.0, 0.02]).reshape(3, 1, 1)  # 20 mm ahead of the LED
    facing = np.array([0.0, 0.0, -1.0]).reshape(3, 1, 1)  # normal towards the LED
    E = inject_light.core_leak(P, facing, (led,), 0.2, 0.01)[:, 0, 0]
    assert E == pytest.approx(0.2 * np.array([1.0, 0.5, 0.25]) * (0.01 / 0.02) ** 2)
    assert not inject_light.core_leak(P, -facing, (led,), 0.2, 0.01).any()  # lit from behind: nothing


def test_geodesic_distance_along_the_cylinder_is_the_height(injector):
    """Straight above an LED on the GelTip's cylinder, the geodesic is the generator."""
    maps = injector._geodesic_maps()
    led = injector.spec.leds[0]
    R = injector.spec.membrane.radius
    vertices = np.asarray(injector.mesh.vertices)
    vertex = vertices[np.argmin(np.linalg.norm(vertices - led.position, axis=1))]
    for z in (0.015, 0.025):
        point = np.array([R, 0.0, z])
        u = injector.camera.f * point[0] / z + injector.camera.cx
        v = injector.camera.f * point[1] / z + injector.camera.cy
        d = maps[0, round(v), round(u)]
        assert d == pytest.approx(np.linalg.norm(point - vertex), abs=3e-4)
    assert inject_light.transmittance(np.array([0.0, 0.02]), 50.0) == pytest.approx([1.0, math.exp(-1.0)])


def test_shadow_of_a_box_on_a_flat_membrane():
    """Light along +x at elevation beta over a flat floor; a 1 mm box 1.5 mm ahead shadows
    the points whose ray towards the light stays below its top, elevation by elevation."""
    floor = trimesh.Trimesh([[-0.05, -0.05, 0], [0.05, -0.05, 0], [0.05, 0.05, 0], [-0.05, 0.05, 0]],
                            [[0, 1, 2], [0, 2, 3]], process=False)
    box = trimesh.creation.box(extents=(0.001, 0.004, 0.001))
    box.apply_translation((0.002, 0.0, 0.0005))  # near face at x = 1.5 mm, top at 1 mm
    x = np.linspace(-0.012, 0.001, 27)
    points = np.stack([x, np.zeros_like(x), np.zeros_like(x)], axis=1)
    light = np.tile([1.0, 0.0, 0.0], (1, len(x), 1))
    up = np.tile([0.0, 0.0, 1.0], (len(x), 1))
    beta = math.radians(10)
    vis = inject_light.shadow_visibility(points, light, up, box, floor, beta)[0]
    expected = np.mean([(0.0015 - x) * math.tan(beta * f) > 0.001 for f in inject_light.SHADOW_SOFT_ELEVATIONS], axis=0)
    near_edge = np.any([np.abs((0.0015 - x) * math.tan(beta * f) - 0.001) < 2e-5
                        for f in inject_light.SHADOW_SOFT_ELEVATIONS], axis=0)
    assert np.array_equal(vis[~near_edge], expected[~near_edge])
    assert vis.min() == 0.0 and vis.max() == 1.0
    # With the undeformed membrane in the way first, the light came off it: no shadow.
    wall = trimesh.creation.box(extents=(1e-4, 0.1, 0.1))
    wall.apply_translation((0.0008, 0.0, 0.0))
    before = x < 0.0005
    assert np.all(inject_light.shadow_visibility(points[before], light[:, before], up[before], box, wall, beta) == 1.0)


def test_gloss_and_spectrum_change_the_spec_as_documented(spec):
    leds, material = inject_light.gloss(spec.leds, spec.material, 0.3, 12.0)
    assert [led.k_s for led in leds] == pytest.approx([led.k_s + 0.3 for led in spec.leds])
    assert material == dataclasses.replace(spec.material, shininess=12.0)
    assert inject_light.spectral_ratio(465.0, 25.0, 0.0) == pytest.approx(np.ones(3))
    shifted = inject_light.shift_spectra(spec.leds, [10.0, 0.0, 0.0], [1.0, 1.1, 1.0])
    assert shifted[1].colour == pytest.approx(tuple(1.1 * c for c in spec.leds[1].colour))
    blue_to_green = inject_light.spectral_ratio(465.0, 25.0, 10.0)  # a blue LED moved towards green
    assert blue_to_green[1] > 1.0 > blue_to_green[2]
    assert inject.spread_elastic(Elastic(), 10.0) == Elastic(sigma_px=10.0, radius_px=54)
