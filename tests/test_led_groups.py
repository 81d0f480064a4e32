"""LED groups: arcs of LEDs in the sensor spec (scenes.spec), how the reference's
calibration renders and fits them (pbr_tactile.calibrate), analytic cases first."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from pbr_tactile import basis as bs
from pbr_tactile import image_fit as imf
from pbr_tactile import image_model as im
from pbr_tactile import real_image as ri
from scenes.image_stats import r2
from scenes.spec import GLASS_IOR, GLASS_WALL_M
from scenes.spec_read import default_spec, load_spec, spec_from_dict

SPEC_2023 = "scenes/sensors/geltip_2023.toml"


def _group(**change) -> dict:
    group = {"name": "red", "count": 6, "arc_centre_rad": 0.5, "arc_span_rad": 2 * math.pi / 3,
             "ring_radius": 0.0105, "height": -0.012, "colour": [1.0, 0.0, 0.0], "k_d": 0.9, "k_s": 0.1,
             "peak_nm": 625.0, "fwhm_nm": 20.0}
    return {**group, **change}


def _data(*groups, leds=()) -> dict:
    return {"name": "arcs", "leds": list(leds), "led_groups": list(groups)}


# -- the spec ------------------------------------------------------------------------------

def test_a_group_lays_its_leds_evenly_along_its_arc():
    spec = spec_from_dict(_data(_group(count=6, arc_centre_rad=0.5, arc_span_rad=2 * math.pi / 3, tilt_rad=0.2)))
    assert [led.name for led in spec.leds] == [f"red{j}" for j in range(6)]
    azimuths = np.array([math.atan2(led.position[1], led.position[0]) for led in spec.leds])
    step = (2 * math.pi / 3) / 6
    np.testing.assert_allclose(np.diff(azimuths), step, atol=1e-12)
    assert np.mean(azimuths) == pytest.approx(0.5)
    for led, a in zip(spec.leds, azimuths):
        assert math.hypot(*led.position[:2]) == pytest.approx(0.0105)
        assert led.position[2] == -0.012 and led.group == "red"
        # aimed up the tube, tilted outwards in its own radial plane
        d = np.array(led.direction)
        assert np.linalg.norm(d) == pytest.approx(1.0)
        assert d[2] == pytest.approx(math.cos(0.2))
        assert math.atan2(d[1], d[0]) == pytest.approx(a)


def test_a_full_ring_repeats_no_led_and_one_led_sits_at_the_centre():
    ring = spec_from_dict(_data(_group(count=4, arc_span_rad=2 * math.pi, arc_centre_rad=0.0)))
    xy = np.array([led.position[:2] for led in ring.leds])
    gaps = np.linalg.norm(xy - np.roll(xy, 1, axis=0), axis=1)
    np.testing.assert_allclose(gaps, gaps[0])  # four LEDs a quarter-turn apart, none doubled
    one = spec_from_dict(_data(_group(count=1, arc_centre_rad=1.0)))
    assert math.atan2(one.leds[0].position[1], one.leds[0].position[0]) == pytest.approx(1.0)


def test_single_leds_and_groups_mix_single_ones_first():
    single = {"name": "blue", "position": [0.012, 0.0, 0.0], "direction": [0, 0, 1], "colour": [0, 0, 1],
              "k_d": 0.9, "k_s": 0.1}
    spec = spec_from_dict(_data(_group(count=2), leds=[single]))
    assert [led.name for led in spec.leds] == ["blue", "red0", "red1"]
    assert spec.leds[0].group is None and spec.group_of("red").count == 2


@pytest.mark.parametrize("change, message", [
    ({"count": 0}, "count must be at least 1"),
    ({"arc_span_rad": math.radians(361.0)}, "at most the whole ring, 360 deg"),
    ({"arc_span_rad": -0.1}, "arc_span_rad must be in"),
    ({"ring_radius": 0.009 - GLASS_WALL_M / 2, "height": 0.0}, "inside the glass wall"),
    ({"ring_radius": 10.5}, "look like millimetres"),
    ({"tilt_rad": 2.0}, "tilt_rad"),
    ({"colour": [2.0, 0.0, 0.0]}, "colour must be linear RGB"),
])
def test_a_bad_group_is_refused_naming_it(change, message):
    with pytest.raises(ValueError, match=message) as err:
        spec_from_dict(_data(_group(**change)), source="s.toml")
    assert "led_groups[0]" in str(err.value)


def test_names_must_be_unique_and_some_led_must_exist():
    with pytest.raises(ValueError, match="unique, repeated: red"):
        spec_from_dict(_data(_group(), _group()))
    with pytest.raises(ValueError, match=r"at least one \[\[leds\]\] or \[\[led_groups\]\]"):
        spec_from_dict({"name": "dark"})


def test_a_ring_under_the_glass_wall_is_accepted():
    """Below the membrane's base the wall is not there: the real unit's LEDs shine into
    its end from underneath."""
    spec = spec_from_dict(_data(_group(ring_radius=0.009 - GLASS_WALL_M / 2, height=-0.012)))
    assert len(spec.leds) == 6


# -- the basis and the image model -----------------------------------------------------------

def test_the_basis_renders_one_led_per_group_at_its_arcs_centre():
    spec = spec_from_dict(_data(_group(name="red", arc_centre_rad=0.5), _group(name="green", arc_centre_rad=2.6,
                                                                                 count=3)))
    rendered, arcs, spans, unit, share = bs.basis_layout(spec)
    assert len(rendered.leds) == 2 and rendered.led_groups == ()
    assert math.atan2(rendered.leds[1].position[1], rendered.leds[1].position[0]) == pytest.approx(2.6)
    assert [len(a) for a in arcs] == [6, 3] and spans == pytest.approx((2 * math.pi / 3,) * 2)
    assert unit.tolist() == [0] * 6 + [1] * 3
    np.testing.assert_allclose(share[:6], spec.group_of("red").offsets())
    plain = default_spec()
    same, none, no_spans, unit, share = bs.basis_layout(plain)
    assert same is plain and none is None and no_spans == () and unit.tolist() == [0, 1, 2] and not share.any()


def _led_image(rho, phi, azimuth, kappa=6.0):
    """An LED's grey image: bright at the rim near its own azimuth (a von Mises lobe
    sharp enough that the LEDs' spread along the arc shows)."""
    return (0.05 + rho**2) * np.exp(kappa * (np.cos(phi - azimuth) - 1.0))


def test_a_fit_finds_each_groups_centre_and_span(camera):
    """The sensor is drawn LED by LED from formulas (no rotated basis); the model sees one
    image per group at its arc's spec centre, and recovers each arc's centre and span."""
    h, w = 60, 80
    v, u = np.mgrid[0:h, 0:w].astype(float)
    s = h / camera.height
    cx, cy = (camera.cx + 0.5) * s - 0.5, (camera.cy + 0.5) * s - 0.5
    rho, phi = np.hypot(u - cx, v - cy) / (camera.mask_radius_px * s), np.arctan2(v - cy, u - cx)
    centres, count = (0.3, 0.3 + 2.1, 0.3 + 4.2), 5
    spec_span, true_span, true_turn = 1.6, (1.1, 1.9, 1.4), (0.15, -0.1, 0.05)
    offsets = (np.arange(count) + 0.5) / count - 0.5
    A = np.stack([_led_image(rho, phi, c) for c in centres], -1)
    names = np.array([f"led{m}" for m in range(3)])
    gains = np.array([[0.5, 0.05, 0.02], [0.03, 0.45, 0.05], [0.05, 0.1, 0.5]]) * 0.35
    linear = sum(_led_image(rho, phi, c + t + span * o)[..., None] * g
                 for c, t, span, g in zip(centres, true_turn, true_span, gains) for o in offsets)
    real = np.clip(linear + 0.01, 0, 1) ** (1 / 2.0)
    circle = (camera.cx, camera.cy, camera.mask_radius_px)  # turns stay inside the frame
    model = im.ImageModel(A, names, camera, circle, [offsets] * 3, (spec_span,) * 3)
    sector = ri.sector_index((h, w), (cx, cy))
    train, test = (sector % 2 == 0) & model.inside, (sector % 2 == 1) & model.inside
    fitter = imf.ImageFitter(model, real, train, leak=False)
    fit = fitter.fit(model.start(), max_evaluations=600)
    pred = model.render(fit.nl, fit.gains, fit.offset, (1.0, 1.0, 1.0))
    assert min(r2(pred[..., c], real[..., c], test) for c in range(3)) > 0.99
    turns = fit.nl.rotation_rad + np.array(fit.nl.led_azimuth_rad)
    np.testing.assert_allclose(turns, true_turn, atol=0.03)
    np.testing.assert_allclose(fit.nl.span_rad, true_span, rtol=0.05)
    # each arc held at the spec's span (its LEDs summed once, each group only turned):
    # the same image is not reached
    rigid = im.ImageModel(model.warped(model.start()), names, camera, circle)
    held = imf.ImageFitter(rigid, real, train, leak=False).fit(rigid.start(), max_evaluations=600)
    assert held.loss > 5 * fit.loss


def test_a_groups_contact_change_moves_with_the_membrane_alone(camera):
    """A tap's change is rendered with every LED of a group where it sits (already summed
    along the arc): the model moves it with the membrane, neither turned by the group's
    azimuth nor summed along its arc again, while the no-contact image is."""
    h, w = 30, 40
    v, u = np.mgrid[0:h, 0:w].astype(float)
    s = h / camera.height
    cx, cy = (camera.cx + 0.5) * s - 0.5, (camera.cy + 0.5) * s - 0.5
    rho, phi = np.hypot(u - cx, v - cy) / (camera.mask_radius_px * s), np.arctan2(v - cy, u - cx)
    offsets = (np.arange(4) + 0.5) / 4 - 0.5
    A = _led_image(rho, phi, 0.4)[..., None]
    change = np.exp(-((u - 25.0) ** 2 + (v - 12.0) ** 2) / 8.0)[..., None]
    model = im.ImageModel(A, np.array(["led0"]), camera, None, [offsets], (1.2,))
    nl = dataclasses.replace(model.start(), led_azimuth_rad=(0.3,))
    falloff = model.falloff(nl)
    np.testing.assert_allclose(model.tap_design(change, nl) - model.design(nl), change * falloff[..., None],
                               atol=1e-12)
    arc = sum(model.moved(A[..., 0], nl, t) for t in model.turns(nl, 0))
    np.testing.assert_allclose(model.design(nl)[..., 0], arc * falloff, atol=1e-12)
    turned = dataclasses.replace(nl, rotation_rad=0.5)  # the membrane's turn moves the change
    moved = model.moved(change[..., 0], turned, 0.0) * model.falloff(turned)
    np.testing.assert_allclose(model.tap_design(change, turned) - model.design(turned), moved[..., None], atol=1e-12)


# -- where the reference emits from ----------------------------------------------------------

def test_the_reference_emits_from_where_the_spec_puts_each_led():
    from pbr_tactile.scene import led_beam, led_centres, led_places, led_sources

    m = default_spec().membrane
    inner = m.core_radius - GLASS_WALL_M
    spec = spec_from_dict({"name": "places", "led_groups": [
        _group(name="tube", count=2, ring_radius=inner - 0.5e-3, height=-0.003, beam_half_angle_rad=0.5),
        _group(name="foot", count=2, ring_radius=inner + 0.5e-3, height=m.base_z - 0.002),
        _group(name="ring", count=2, ring_radius=0.012, height=0.0)]})
    assert led_places(spec) == ["tube"] * 2 + ["wall_end"] * 2 + ["elastomer"] * 2
    centres = led_centres(spec)
    r = np.hypot(centres[:, 0], centres[:, 1])
    np.testing.assert_allclose(centres[:2], [led.position for led in spec.leds[:2]])  # in the air, where it is
    np.testing.assert_allclose(r[2:4], m.core_radius - GLASS_WALL_M / 2)  # inside the wall's foot
    assert np.all(centres[2:4, 2] > m.base_z)
    assert np.all((r[4:] > m.core_radius) & (r[4:] < m.radius))  # in the elastomer wall
    # beams: the tube LED's own, the foot's a Lambertian LED's light refracted into glass
    places = led_places(spec)
    assert led_beam(spec.leds[0], places[0]) == ((0.0, 0.0, 1.0), 0.5)
    assert led_beam(spec.leds[2], places[2])[1] == pytest.approx(math.asin(1 / GLASS_IOR))
    assert led_beam(spec.leds[4], places[4]) == (None, 0.0)
    sources = led_sources(spec)
    assert [s["in_elastomer"] for s in sources] == [False] * 4 + [True] * 2
    assert sources[0]["cone_half_angle_rad"] == 0.5 and sources[4]["cone_axis"] is None


def test_a_single_led_inside_the_glass_wall_is_refused():
    led = {"name": "in_glass", "position": [0.0085, 0.0, 0.0], "direction": [0, 0, 1], "colour": [1, 0, 0],
           "k_d": 0.9, "k_s": 0.1}
    with pytest.raises(ValueError, match=r"leds\[0\].position: 8.50 mm from the axis puts the LED inside the glass"):
        spec_from_dict({"name": "bad", "leds": [led]})
    with pytest.raises(ValueError, match="beam_half_angle_rad must be in"):
        spec_from_dict(_data(_group(beam_half_angle_rad=2.0)))


# -- the real unit's spec ----------------------------------------------------------------------

def test_the_real_units_spec_lays_out_three_arcs_of_six():
    from pathlib import Path

    spec = load_spec(Path(__file__).parents[1] / SPEC_2023)
    assert spec.name == "geltip_2023" and [g.name for g in spec.led_groups] == ["blue", "red", "green"]
    assert len(spec.leds) == 18 and {led.group for led in spec.leds} == {"blue", "red", "green"}
    centres = sorted(g.arc_centre_rad for g in spec.led_groups)
    np.testing.assert_allclose(np.diff(centres), 2 * math.pi / 3)  # the crescents' centres, 120 deg apart


def test_a_profile_made_for_the_other_spec_is_refused(tmp_path):
    from pathlib import Path

    from scenes.profile import Alignment, CameraProfile, Profile, load_profile, write_profile

    published = default_spec()
    profile = Profile(sensor=published.name, leds=tuple(led.name for led in published.leds),
                      alignment=Alignment(0.0, 1.0, (0.0, 0.0)), camera=CameraProfile(), fit={"converged": True})
    path = write_profile(profile, tmp_path / "profile.toml")
    with pytest.raises(ValueError, match="is for sensor 'geltip' with LEDs"):
        load_profile(path, load_spec(Path(__file__).parents[1] / SPEC_2023))


def test_the_light_path_study_varies_the_units_build():
    from pathlib import Path

    from pbr_tactile.scene import led_places
    from studies.light_paths import STRUCTURES, structure

    spec = load_spec(Path(__file__).parents[1] / SPEC_2023)
    built = {name: structure(spec, name) for name in STRUCTURES}
    assert built["spec"] is spec
    assert built["simulation_camera"].camera.fov_y == pytest.approx(math.pi / 2) != spec.camera.fov_y
    assert set(led_places(spec)) == {"tube"}
    assert set(led_places(built["leds_in_elastomer"])) == {"elastomer"}
    assert set(led_places(built["leds_under_wall"])) == {"wall_end"}
    assert all(led.beam_half_angle_rad is None for led in built["lambertian_leds"].leds)
    assert spec.leds[0].beam_half_angle_rad is not None
    points = built["point_leds"]
    assert len(points.leds) == 3 and [led.group for led in points.leds] == ["blue", "red", "green"]
    for led, group in zip(points.leds, spec.led_groups):  # each at its arc's centre
        assert math.atan2(led.position[1], led.position[0]) == pytest.approx(
            math.remainder(group.arc_centre_rad, 2 * math.pi))
    with pytest.raises(ValueError, match="has none"):
        structure(default_spec(), "point_leds")


def test_a_groups_taps_are_rendered_per_led_at_the_fitted_spans_and_summed_per_group(monkeypatch):
    """With LED groups, tap_changes renders each tap and its no-contact counterpart with
    every LED where it sits (the groups spread over the spans given: the no-contact
    fit's), with the basis' photons shared among a unit's LEDs, and sums each LED's
    change, and its leak's, into its group's source."""
    from pbr_tactile import calibrate_taps as ct
    from scenes import captures

    spec = spec_from_dict(_data(_group(name="red", count=4), _group(name="green", arc_centre_rad=2.6, count=2),
                                leds=[{**_group(name="blue"), "position": [0.0, 0.0105, -0.012],
                                       "direction": [0.0, 0.0, 1.0]}]))
    rendered, _, _, unit, _ = bs.basis_layout(spec)
    units = [f"led{m}{kind}" for m in range(len(rendered.leds)) for kind in ("", "_leak")]
    assert unit.tolist() == [0, 1, 1, 1, 1, 2, 2]  # the single LED first, then the groups'
    calls = []

    def basis(spec_, mesh, camera, effects, film, photons, *args, depth=None, **kwargs):
        calls.append((spec_, photons, depth is not None))
        # LED m's image is m + 1, its leak's 10 (m + 1); a tap adds its depth to each
        value = np.repeat(np.arange(1.0, len(spec_.leds) + 1), 2) * np.tile([1.0, 10.0], len(spec_.leds))
        names = [f"led{m}{kind}" for m in range(len(spec_.leds)) for kind in ("", "_leak")]
        return {"mean": np.ones((3, 4, 1)) * (value * (1.0 + (0.0 if depth is None else depth.mean()))),
                "names": np.array(names)}

    monkeypatch.setattr(ct, "emitter_basis", basis)
    taps = captures.RealTaps(np.zeros((2, 6, 8, 3)), np.stack([np.full((6, 8), d) for d in (1.0, 2.0)]),
                             np.zeros((6, 8)), ["a", "b"])
    no_contact = {"mean": np.zeros((3, 4, len(units))), "names": np.array(units)}
    spans = (0.0, 1.0, 0.5)
    out = ct.tap_changes(spec, None, None, None, (4, 3), taps, no_contact, 700, 1, 1, 0, azimuths=False, spans=spans)
    # the no-contact counterpart and both taps, each with all seven LEDs, 700 * 3 / 7 photons each
    assert [(len(c[0].leds), c[1], c[2]) for c in calls] == [(7, 300, False), (7, 300, True), (7, 300, True)]
    drawn = calls[0][0]
    assert [g.arc_span_rad for g in drawn.led_groups] == [1.0, 0.5]
    green = [led for led in drawn.leds if led.group == "green"]
    turn = [math.atan2(led.position[1], led.position[0]) for led in green]
    assert turn == pytest.approx([2.6 - 0.125, 2.6 + 0.125])  # two LEDs over 0.5 rad
    # each unit's change: its LEDs' (m + 1) summed, times the tap's depth; leaks 10 times that
    led_sums = np.array([1.0, 2 + 3 + 4 + 5, 6 + 7])
    expected = np.stack([np.array([s, 10 * s]) for s in led_sums]).ravel()
    assert out["change"].shape == (2, 3, 4, 6)
    np.testing.assert_allclose(out["change"][0, 0, 0], expected * 1.0)
    np.testing.assert_allclose(out["change"][1, 0, 0], expected * 2.0)
    # a unit basis without one of the units' sources is refused, naming the source
    with pytest.raises(ValueError, match=r"source led5 has no unit among the basis. \[.led0., .led0_leak., .led1., "
                                         r".led1_leak.\]"):
        ct.tap_changes(spec, None, None, None, (4, 3), taps, {**no_contact, "names": np.array(units[:4])}, 700, 1,
                       1, 0, azimuths=False, spans=spans)


def test_a_spec_written_out_whole_reads_back_the_same():
    """Datasets record their sensor as dataclasses.asdict in JSON: every LED, the groups'
    own among them, and the optional keys as null."""
    import dataclasses
    import json
    from pathlib import Path

    for spec in (default_spec(), load_spec(Path(__file__).parents[1] / SPEC_2023)):
        data = json.loads(json.dumps(dataclasses.asdict(spec)))
        assert spec_from_dict(data) == spec
    data["leds"][0]["group"] = "violet"
    with pytest.raises(ValueError, match="names no"):
        spec_from_dict(data)


@pytest.mark.slow
def test_a_groups_leds_rendered_each_where_it_sits_sum_to_the_basis_arc(camera):
    """Another mechanism for the same image: the no-contact 2023 unit rendered by the
    reference with all 18 LEDs where they sit (as its taps are: calibrate_taps.tap_spec),
    summed per group (per_unit), against the basis' one LED per group turned along its
    arc (ImageModel._arc). They agree to the Monte Carlo noise (smoothed by 1.5 px), and
    an arc at half the span, which the test would take for the same, does not."""
    pytest.importorskip("mitsuba")
    from pathlib import Path

    from scipy import ndimage

    from pbr_tactile import calibrate_taps as ct
    from pbr_tactile.effects import Effects
    from scenes.camera import Camera
    from scenes.geometry import membrane_mesh

    spec = load_spec(Path(__file__).parents[1] / SPEC_2023)
    unit_camera, mesh = Camera.from_spec(spec), membrane_mesh(spec)
    effects = Effects().with_settings([f"{k}={v}" for k, v in bs.BASIS_EFFECTS.items()])
    film, photons = (80, 60), 1 << 14
    rendered, arcs, spans, _, _ = bs.basis_layout(spec)
    basis = bs.emitter_basis(rendered, mesh, unit_camera, effects, film, photons, 4, 2, seed=3, use_cache=False)
    drawn, share, unit = ct.tap_spec(spec, spans)
    assert len(drawn.leds) == 18 and share == pytest.approx(3 / 18)
    each = bs.emitter_basis(drawn, mesh, unit_camera, effects, film, int(photons * share), 4, 2, seed=3,
                            use_cache=False)
    summed = ct.per_unit(each, unit, basis["names"])
    model = im.ImageModel(basis["mean"], basis["names"], unit_camera,
                          (unit_camera.cx, unit_camera.cy, unit_camera.mask_radius_px), arcs, spans)
    nl, inside = model.start(), model.inside

    def off(image, arc):
        a, b = ndimage.gaussian_filter(image, 1.5), ndimage.gaussian_filter(arc, 1.5)
        return float(np.sqrt(np.mean((a - b)[inside] ** 2) / np.mean(b[inside] ** 2)))

    for k, name in enumerate(basis["names"]):
        turns = np.array(model.turns(nl, model.led[k]))
        arc = model._arc(basis["mean"], k, tuple(turns))
        assert off(summed[..., k], arc) < (0.16 if name.endswith("_leak") else 0.12), name
        if not name.endswith("_leak"):
            assert off(summed[..., k], model._arc(basis["mean"], k, tuple(0.5 * turns))) > 0.18, name
