"""The LEDs' layout as parameters (scenes.layout) and where the reference emits each entry.

Cheap checks: a spec's layout read back, the housing's and the entry's bounds refused
with one line naming them, a profile's layout table, and where the reference puts an LED
that enters by a flat sensor's plate edge, under it or beside it. One analytic check
(Mitsuba's vectorised variant): light entering a flat plate's edge reaches the pad as
Fresnel's law and total internal reflection say.
"""

from __future__ import annotations

import dataclasses
import math
import tomllib

import numpy as np
import pytest

from scenes.layout import (
    CLEARANCE_M,
    FREE,
    LEDLayout,
    check_layout,
    glass_floor,
    layout_bounds,
    layout_from_dicts,
    layout_of,
    layout_to_dicts,
    with_layout,
)
from scenes.spec import SENSORS_DIR, Housing
from scenes.spec_read import load_spec, read_sensor_file, spec_from_dict


@pytest.fixture(scope="module")
def gelsight():
    return load_spec(SENSORS_DIR / "gelsight.toml")


def test_a_spec_s_layout_reads_back_as_the_same_leds(gelsight):
    layout = layout_of(gelsight)
    assert [p.entry for p in layout] == ["beside"] * 3  # above the plate's lowest point
    again = with_layout(gelsight, layout)
    for a, b in zip(gelsight.leds, again.leds):
        np.testing.assert_allclose(a.position, b.position, atol=1e-12)
        np.testing.assert_allclose(a.direction, b.direction, atol=1e-6)  # the file states 7 digits
        assert (a.name, a.colour, a.peak_nm) == (b.name, b.colour, b.peak_nm) and b.entry == "beside"
    # every LED aims across the pad at the axis: a right angle from +z, inwards
    assert [p.aim_rad for p in layout] == pytest.approx([math.pi / 2] * 3)
    # an LED under the plate's lowest point is read as entering from under it
    low = dataclasses.replace(gelsight.leds[0], position=(0.01, 0.0, glass_floor(gelsight) - 2 * CLEARANCE_M))
    assert layout_of(gelsight.replace(leds=(low,) + gelsight.leds[1:]))[0].entry == "under"


def test_the_glass_floor_is_the_plate_s_rim_underside(gelsight):
    """The domed pad's plate is its core moved down a glass wall along the membrane's
    normals: its lowest point lies under the rim, (thickness + wall) cos(rim slope) under
    the rim's plane."""
    params = dict(gelsight.membrane.params)
    slope = math.asin(params["radius"] / params["dome_radius"])
    expected = gelsight.membrane.base_z - (gelsight.membrane.thickness + gelsight.membrane.glass_wall) * math.cos(slope)
    assert glass_floor(gelsight) == pytest.approx(expected, abs=2e-5)


def test_a_layout_outside_the_housing_is_refused_with_its_bound(gelsight):
    housed = gelsight.replace(housing=Housing(radius=0.030, floor_z=0.005))
    base = LEDLayout("under", 0.0, 0.015, 0.015, 0.3, math.radians(40))
    check_layout(housed, [base] * 3)
    cases = [
        (dict(radius_m=0.035), r"LED 'red' \(under\): radius_m = 0.035 is outside \[0, 0.03\] \(the housing's radius\)"),
        (dict(height_m=0.004), r"height_m = 0.004 is outside \[0.005, 0.0216.*\] \(the housing's floor and the glass' "
                               r"lowest point\)"),
        (dict(height_m=0.025), r"height_m = 0.025 is outside"),
        (dict(aim_rad=2.0), r"aim_rad = 2 is outside \[-1.5708, 1.5708\]"),
        (dict(beam_half_angle_rad=0.01), r"beam_half_angle_rad = 0.01 is outside \[0.0872665, 1.5708\]"),
    ]
    for change, message in cases:
        with pytest.raises(ValueError, match=message):
            check_layout(housed, [dataclasses.replace(base, **change)] + [base] * 2)
    # an entry that enters where the body is has no height to bound
    check_layout(housed, [dataclasses.replace(base, entry="edge", height_m=0.025)] * 3)
    assert FREE["edge"] == ("aim_rad", "beam_half_angle_rad")
    with pytest.raises(ValueError, match="one LEDLayout per LED"):
        check_layout(housed, [base])
    with pytest.raises(ValueError, match="layout entry must be one of beside, edge, under"):
        LEDLayout("above", 0.0, 0.01, 0.01, 0.0, None)
    assert layout_bounds(housed, "under")["radius_m"][:2] == (0.0, 0.030)


def test_a_spec_refuses_an_led_outside_its_housing_and_a_bad_entry():
    data = read_sensor_file(SENSORS_DIR / "gelsight.toml")
    data["housing"] = {"radius": 0.020}
    with pytest.raises(ValueError, match=r"LED 'red': 23.20 mm from the axis is outside the housing, whose radius is "
                                         r"20.00 mm \(\[housing\] radius\)"):
        spec_from_dict(data, "test.toml")
    data["housing"] = {"radius": 0.030, "floor_z": 0.027}
    with pytest.raises(ValueError, match=r"z = 26.74 mm is below the housing's floor at z = 27.00 mm"):
        spec_from_dict(data, "test.toml")
    data["housing"] = {"radius": 0.030, "depth": 0.01}
    with pytest.raises(ValueError, match="unknown keys depth"):
        spec_from_dict(data, "test.toml")
    data["housing"] = {"radius": 0.030}
    data["leds"][0]["entry"] = "through"
    with pytest.raises(ValueError, match=r"leds\[0\].entry must be one of beside, edge, under"):
        spec_from_dict(data, "test.toml")
    data["leds"][0]["entry"] = "edge"
    spec = spec_from_dict(data, "test.toml")
    assert spec.leds[0].entry == "edge" and spec.housing == Housing(radius=0.030)
    assert spec_from_dict(spec.to_dict(), "again") == spec


def test_a_profile_s_layout_table_reads_back_checked(gelsight):
    layout = tuple(LEDLayout("under", p.azimuth_rad, 0.012, 0.015, 0.2, math.radians(50)) for p in layout_of(gelsight))
    data = layout_to_dicts(layout)
    assert tomllib.loads("\n".join(f"{k} = {v!r}" for k, v in data[0].items())) == data[0]
    assert layout_from_dicts(data, gelsight) == layout
    with pytest.raises(ValueError, match=r"profile reference.layout must be a list of one table per LED \(3\)"):
        layout_from_dicts(data[:2], gelsight, "profile reference.layout")
    with pytest.raises(ValueError, match=r"layout\[1\]: expected entry, azimuth_rad"):
        layout_from_dicts([data[0], {"entry": "under"}, data[2]], gelsight)
    far = [dict(d, height_m=0.03) for d in data]
    with pytest.raises(ValueError, match=r"layout: layout of LED 'red' \(under\): height_m = 0.03 is outside"):
        layout_from_dicts(far, gelsight)


def test_the_reference_emits_each_entry_where_it_enters(gelsight):
    """Under: in the air where the LED sits, its beam about its aim. Edge: inside the
    plate, WALL_FOOT_M in from the middle of its rim face at the LED's azimuth, the beam
    refracted into the acrylic (a Lambertian LED fills its critical cone). Beside: in the
    middle of the elastomer at its edge (as every GelSight LED of the shipped spec)."""
    from pbr_tactile.scene import ENTRY_PLACES, WALL_FOOT_M, glass_edges, led_places, led_sources
    from scenes.body import sensor_body

    own = layout_of(gelsight)
    under = LEDLayout("under", own[0].azimuth_rad, 0.012, 0.018, 0.4, math.radians(30))
    edge = dataclasses.replace(own[1], entry="edge", beam_half_angle_rad=None)
    spec = with_layout(gelsight, (under, edge, own[2]))
    assert led_places(spec) == [ENTRY_PLACES[e] for e in ("under", "edge", "beside")] == ["tube", "wall_end",
                                                                                          "elastomer"]
    sources = led_sources(spec)
    np.testing.assert_allclose(sources[0]["centre"], under.position(), atol=1e-12)
    np.testing.assert_allclose(sources[0]["cone_axis"], under.direction(), atol=1e-12)
    assert sources[0]["cone_half_angle_rad"] == pytest.approx(math.radians(30)) and not sources[0]["in_elastomer"]
    # the edge LED: inside the plate, between the core's rim and the underside's, 1 mm in
    body = sensor_body(spec)
    loop = body.base_loop
    core = np.asarray(body.core.vertices)[loop]
    under_side = core - spec.membrane.glass_wall * body.normals[loop]
    centre = np.asarray(sources[1]["centre"])
    k = int(np.argmin(np.linalg.norm(0.5 * (core + under_side) - centre, axis=1)))
    rim_r = math.hypot(*(0.5 * (core[k] + under_side[k]))[:2])
    assert rim_r - math.hypot(*centre[:2]) == pytest.approx(WALL_FOOT_M * math.cos(math.asin(0.022 / 0.050)), rel=0.05)
    assert under_side[k][2] < centre[2] < core[k][2]
    assert sources[1]["cone_half_angle_rad"] == pytest.approx(math.asin(1 / spec.membrane.glass_ior))
    points, normals = glass_edges(spec)
    np.testing.assert_allclose(np.linalg.norm(normals, axis=1), 1.0, atol=1e-9)
    assert np.dot(normals[1][:2], -np.asarray(centre[:2])) > 0  # into the plate, towards the axis
    assert sources[2]["in_elastomer"] and sources[2]["cone_axis"] is None


def _fresnel(cos_i: np.ndarray, eta: float) -> np.ndarray:
    """Unpolarised Fresnel reflectance from a medium of index n_1 into one of n_2, eta =
    n_1 / n_2, at incidence cosines ``cos_i``; 1 beyond the critical angle."""
    sin_t2 = eta**2 * (1 - cos_i**2)
    cos_t = np.sqrt(np.clip(1 - sin_t2, 0.0, None))
    rs = (eta * cos_i - cos_t) / (eta * cos_i + cos_t)
    rp = (cos_i - eta * cos_t) / (cos_i + eta * cos_t)
    return np.where(sin_t2 >= 1, 1.0, 0.5 * (rs**2 + rp**2))


def _sphere_hit(p, d, centre, radius) -> float:
    """The nearest positive distance along the ray p + t d to a sphere; inf if none."""
    o = p - centre
    b = float(np.dot(o, d))
    disc = b * b - (float(np.dot(o, o)) - radius * radius)
    if disc < 0:
        return math.inf
    roots = [t for t in (-b - math.sqrt(disc), -b + math.sqrt(disc)) if t > 1e-12]
    return min(roots) if roots else math.inf


def _edge_light_reaching_the_pad(start, axis, half_angle, centre, paint_r, gel, wall, rim_r, n_glass, n_gel,
                                 n: int = 60) -> float:
    """The share of a uniform cone of light (about ``axis``, ``half_angle``) leaving
    ``start`` inside a domed plate, a spherical shell about ``centre`` between radii
    ``paint_r - gel - wall`` (its underside, on air) and ``paint_r - gel`` (its top, under
    a clear gel), that first reaches the black paint on the gel (the sphere ``paint_r``):
    each ray bounces between the plate's faces, leaving into the gel by Fresnel's
    transmission at the top (then straight to the paint) and into the air below; past
    ``rim_r`` from the axis (the plate's and the gel's black rims) it is lost. A
    midpoint rule over the cone's solid angle, n x 2n directions."""
    axis = np.asarray(axis, np.float64) / np.linalg.norm(axis)
    centre = np.asarray(centre, np.float64)
    top, bottom = paint_r - gel, paint_r - gel - wall
    u = np.cross(axis, [0.0, 0.0, 1.0])
    u /= np.linalg.norm(u)
    v = np.cross(axis, u)
    c = 1 - (np.arange(n) + 0.5) / n * (1 - math.cos(half_angle))  # uniform in cos about the axis
    phi = (np.arange(2 * n) + 0.5) / (2 * n) * 2 * math.pi
    C, P = np.meshgrid(c, phi, indexing="ij")
    S = np.sqrt(1 - C**2)
    rays = (C[..., None] * axis + S[..., None] * (np.cos(P)[..., None] * u + np.sin(P)[..., None] * v)).reshape(-1, 3)
    total = 0.0
    for d in rays:
        p, carried = np.asarray(start, np.float64), 1.0
        for _ in range(200):
            t_top, t_bottom = _sphere_hit(p, d, centre, top), _sphere_hit(p, d, centre, bottom)
            up = t_top < t_bottom
            p = p + min(t_top, t_bottom) * d
            if carried < 1e-6 or not math.isfinite(min(t_top, t_bottom)) or math.hypot(p[0], p[1]) > rim_r:
                break
            normal = (p - centre) / np.linalg.norm(p - centre) * (1 if up else -1)  # out of the plate
            cos_i = float(np.dot(d, normal))
            eta = n_glass / (n_gel if up else 1.0)
            T = 1 - float(_fresnel(np.array(cos_i), eta))
            if up and T > 0:
                tangent = eta * (d - cos_i * normal)
                into = tangent + math.sqrt(max(0.0, 1 - float(np.dot(tangent, tangent)))) * normal
                at = p + _sphere_hit(p, into, centre, paint_r) * into
                if math.hypot(at[0], at[1]) <= rim_r:
                    total += carried * T
            carried *= 1 - T
            d = d - 2 * cos_i * normal
    return total / len(rays)


def test_light_entering_the_plate_s_edge_reaches_the_pad_as_fresnel_says(photon_mi):
    """A flat GelSight lit through its plate's rim (``entry = "edge"``): light guided by
    total internal reflection in the acrylic leaves it into the gel within the
    glass-to-silicone critical angle, and reaches the pad. The photon estimator's flux on a
    black pad (every deposit a first arrival) against the same plate traced ray by ray
    with Fresnel's law against its spheres, independently of Mitsuba (the dome of 1 m
    matters: a flat plate's sum is 2.3 % lower)."""
    import tempfile

    from pbr_tactile.membrane import ElastomerBuilder
    from pbr_tactile.photons import deposits, sources_from
    from pbr_tactile.render import load
    from pbr_tactile.scene import IOR_SILICONE, geltip_scene, led_sources, write_meshes
    from pbr_tactile.effects import Effects
    from scenes.body import sensor_body
    from scenes.camera import Camera
    from scenes.geometry import membrane_mesh

    data = read_sensor_file(SENSORS_DIR / "gelsight.toml")
    data["membrane"]["params"] = {"radius": 0.016, "dome_radius": 1.0}
    data["membrane"]["mesh_edge"] = 0.001
    data["membrane"]["base_z"] = 0.033
    data["leds"] = [dict(data["leds"][0], entry="edge", position=[0.017, 0.0, 0.030])]
    spec = spec_from_dict(data, "domed pad")
    camera = Camera.from_spec(spec).scaled(16, 12)
    mi = photon_mi
    effects = Effects(scattering_per_m=0.0, absorption_per_m=0.0, coating_albedo=0.0, core_light_leak=0.0)
    solid = ElastomerBuilder(membrane_mesh(spec), spec, camera, 1e-3)()
    with tempfile.TemporaryDirectory() as folder:
        scene = geltip_scene(write_meshes(solid, folder, spec.membrane.glass_wall), spec, camera, effects, 8, 6, spp=1)
        loaded = load(scene, mi.variant())[1]
    sources = led_sources(spec, effects)
    photons = 1 << 17
    flux = deposits(mi, loaded, sources_from(sources), effects.sigma_t, effects.albedo, 0.0, photons, seed=3)
    simulated = float(flux.sum())
    body = sensor_body(spec)
    core = np.asarray(body.core.vertices)[body.base_loop]
    dome = 1.0
    centre = (0.0, 0.0, spec.membrane.base_z + dome - math.sqrt(dome**2 - 0.016**2) - dome)  # the cap's (pad.profile)
    start = np.asarray(sources[0]["centre"]) + sources[0]["radius"] * np.asarray(sources[0]["cone_axis"])
    expected = _edge_light_reaching_the_pad(start, sources[0]["cone_axis"], sources[0]["cone_half_angle_rad"], centre,
                                            dome, spec.membrane.thickness, spec.membrane.glass_wall,
                                            float(np.hypot(core[:, 0], core[:, 1]).mean()), spec.membrane.glass_ior,
                                            IOR_SILICONE)
    # guided light leaves into the gel: a share of the critical cone's, and far from none
    assert 0.2 < expected < 0.9
    sigma = math.sqrt(expected * (1 - expected) / photons)
    # the photons' binomial noise and 1 % for the 1 mm facets (measured: 0.3838 against 0.3808, seed 3)
    assert abs(simulated - expected) < 4 * sigma + 0.01 * expected, (simulated, expected)


@pytest.mark.slow
@pytest.mark.xfail(strict=True, reason="not recovered yet (2026-12-07, 492 s): the fit put the red LED at the plate's "
                   "edge, ['edge', 'under', 'under'], where all three are under it: from the no-contact image and two "
                   "presses the red LED's entry is not identified; the issue's synthetic recovery is open")
def test_a_known_layout_is_recovered_from_presses_rendered_with_it(photon_mi):
    """A blind unit: the flat GelSight with its LEDs under the plate, off the search's
    coarse grid (1.5 mm further out, 0.15 rad less aim, a 0.3 rad wider beam than its
    nearest point), its no-contact image and two ball presses rendered with another seed
    and made an image through known powers, white balance, offset and response. The
    layout's fit, on them, finds the LEDs under the plate and each within a few of its
    smallest steps of where they are (a beam 0.3 rad off its start must move)."""
    from pbr_tactile.basis import BASIS_EFFECTS, emitter_basis
    from pbr_tactile.effects import Effects
    from pbr_tactile.image_model import ImageModel, Nonlinear
    from pbr_tactile.layout_fit import SEARCH_FILM, STEPS, UNDER_AIMS, UNDER_BEAMS, fit_layout, under_grid
    from scenes.camera import Camera, reference_depth
    from scenes.captures import RealTaps
    from scenes.contact import press
    from scenes.geometry import membrane_mesh
    import trimesh

    spec = load_spec(SENSORS_DIR / "gelsight.toml").at_resolution(160, 120)
    camera, mesh = Camera.from_spec(spec), membrane_mesh(spec)
    effects = Effects().with_settings([f"{k}={v}" for k, v in BASIS_EFFECTS.items()]
                                      + ["absorption_per_m=20", "scattering_per_m=0"])
    grid = under_grid(spec, layout_of(spec))
    near = grid[f"under_r0.65_a{math.degrees(UNDER_AIMS[1]):.0f}_b{math.degrees(UNDER_BEAMS[0]):.0f}"]
    hidden = tuple(dataclasses.replace(p, radius_m=p.radius_m + 1.5e-3, aim_rad=p.aim_rad - 0.15,
                                       beam_half_angle_rad=p.beam_half_angle_rad + 0.3) for p in near)
    unit = with_layout(spec, hidden)
    ref = reference_depth(mesh, camera)[0]
    depths = np.stack([press(ref, camera, mesh, trimesh.primitives.Sphere(radius=0.002), pixel, 1.0e-3)
                       for pixel in ((55.0, 50.0), (105.0, 72.0))])
    renders = [emitter_basis(unit, mesh, camera, effects, SEARCH_FILM, 1 << 17, 16, 2, seed=11)]
    renders += [emitter_basis(unit, mesh, camera, effects, SEARCH_FILM, 1 << 17, 16, 2, seed=11, depth=d,
                              ref_depth=ref) for d in depths]
    model = ImageModel(renders[0]["mean"], renders[0]["names"], camera, None, known_alignment=True,
                       response=renders[0]["response"])
    gains = np.array([1.0, 0.8, 0.9])[:, None] * model.response * np.array([0.5, 0.4, 0.6])[None, :]
    scale = 0.6 / float(np.percentile(model.warped(model.start()) @ gains, 90))
    nl = dataclasses.replace(Nonlinear.start(3, leak=0.2), gamma=1.8)

    def image(change=None):
        low = model.render(nl, gains * scale, (0.03, 0.03, 0.03), (1, 1, 1), change=change)
        return np.repeat(np.repeat(low, 2, axis=0), 2, axis=1)  # at the camera's 160x120

    real = image()
    taps = RealTaps(np.stack([image(r["mean"] - renders[0]["mean"]) for r in renders[1:]]), depths, ref,
                    ["a", "b"])
    # five starts (the grid's point nearest the truth among them) and one round keep it to
    # minutes: the beam, 0.3 rad off, must move by a whole first step
    starts = ("spec", "edge", "under_r0.65_a35_b30", "under_r0.35_a0_b60", "under_r0.65_a0_b60")
    fit = fit_layout(real, spec, mesh, camera, effects, taps=taps, spectral_gains=True, webcam=True, rounds=1,
                     screened=2, only=starts, material=False)
    assert [p.entry for p in fit.layout] == ["under"] * 3
    for found, truth in zip(fit.layout, hidden):
        assert abs(found.radius_m - truth.radius_m) <= 4 * STEPS["radius_m"][1]
        assert abs(found.aim_rad - truth.aim_rad) <= 4 * STEPS["aim_rad"][1]
        assert abs(found.beam_half_angle_rad - truth.beam_half_angle_rad) <= 4 * STEPS["beam_half_angle_rad"][1]
    assert fit.report["loss"] < fit.report["starts"]["spec"]["loss"]


def test_a_parameter_s_resolution_is_where_its_parabola_rises_by_the_tolerance():
    from pbr_tactile.layout_fit import resolution

    # loss 2 (x - 0.5)^2 + 1, trials 0.1 and 0.3 either side: curvature 4, a rise of 0.02
    # within 0.1 of 0.5
    loss = lambda x: 2 * (x - 0.5) ** 2 + 1.0  # noqa: E731
    r = resolution(0.5, loss(0.5), [{"value": 0.4, "loss": loss(0.4)}, {"value": 0.8, "loss": loss(0.8)}],
                   (0.0, 1.0), 0.02)
    assert r["low"] == pytest.approx(0.4) and r["high"] == pytest.approx(0.6) and r["identified"]
    # at a bound, one side: the vertex taken at the bound, the range clipped to it
    r = resolution(0.0, loss(0.5), [{"value": 0.2, "loss": loss(0.5) + 0.08}], (0.0, 1.0), 0.02)
    assert r["low"] == 0.0 and r["high"] == pytest.approx(0.1) and r["identified"]
    # flat or curving down: nothing pinned, the whole bounds
    for trials in ([{"value": 0.4, "loss": 1.0}, {"value": 0.6, "loss": 1.0}],
                   [{"value": 0.4, "loss": 0.9}, {"value": 0.6, "loss": 0.95}], []):
        r = resolution(0.5, 1.0, trials, (0.0, 1.0), 0.02)
        assert (r["low"], r["high"], r["identified"]) == (0.0, 1.0, False)
    # a range wider than half the bounds is not identified either
    assert not resolution(0.5, 1.0, [{"value": 0.4, "loss": 1.0001}, {"value": 0.6, "loss": 1.0001}],
                          (0.0, 1.0), 0.02)["identified"]


def test_the_paint_search_finds_a_loss_s_minimum_and_reports_its_resolution():
    """The material search against a loss written as a sum of parabolas (no render): it
    ends within each parameter's smallest step of the minimum, where no step of that
    size gains MIN_GAIN, and reports each parameter's range around it."""
    from pbr_tactile.effects import Effects
    from pbr_tactile.layout_fit import MATERIAL, MIN_GAIN, _material_search, material_intervals

    truth = {"coating_gloss": 0.43, "coating_roughness": 0.22, "scattering_per_m": 35.0}
    scales = {"coating_gloss": 1.0, "coating_roughness": 2.0, "scattering_per_m": 0.01}

    def score(candidate):
        e = candidate["effects"]
        return 1.0 + sum((scales[n] * (getattr(e, n) - truth[n])) ** 2 for n in truth), None

    calls = []

    def render(layout, effects=None):
        calls.append(effects)
        return {"effects": effects}

    start = Effects(coating_gloss=0.0, coating_roughness=0.3, scattering_per_m=0.0)
    loss, fitted, candidate, records = _material_search(start, None, {"effects": start},
                                                        score({"effects": start})[0], score, render, 6, lambda _: None)
    assert candidate["effects"] is fitted and loss == pytest.approx(score(candidate)[0])
    for name, (low, high, _, smallest) in MATERIAL.items():
        assert abs(getattr(fitted, name) - truth[name]) <= smallest, name
        for sign in (1, -1):
            moved = dataclasses.replace(fitted, **{name: float(np.clip(getattr(fitted, name) + sign * smallest,
                                                                         low, high))})
            assert score({"effects": moved})[0] >= loss - MIN_GAIN * loss
    assert all(low <= getattr(e, n) <= high for e in calls for n, (low, high, _, _) in MATERIAL.items())
    intervals = material_intervals(records)
    assert set(intervals) == set(MATERIAL)
    for name, r in intervals.items():
        assert r["low"] <= getattr(fitted, name) <= r["high"]
        assert r["low"] <= truth[name] + MATERIAL[name][3] and truth[name] - MATERIAL[name][3] <= r["high"]


def test_each_led_s_intervals_come_from_its_last_unmoved_step(gelsight):
    from pbr_tactile.layout_fit import layout_intervals

    layout = layout_of(gelsight)  # beside the pad: aim and beam free
    aim = layout[0].aim_rad
    records = [
        # red's aim moved at the first step, then held at the second: its range is the second's
        {"parameter": "aim_rad", "leds": {"red": {"from": aim - 0.3, "loss": 1.2, "trials": []}}},
        {"parameter": "aim_rad", "leds": {"red": {"from": aim, "loss": 1.0, "trials": [
            {"value": aim - 0.15, "loss": 1.045}]}}},
        # green's aim was tried last from another value (it moved there): not identified
        {"parameter": "aim_rad", "leds": {"green": {"from": aim - 0.15, "loss": 1.0, "trials": []}}},
    ]
    out = layout_intervals(gelsight, layout, records, 1.0)
    assert set(out) == {"red", "green", "blue"} and set(out["red"]) == set(FREE["beside"])
    red = out["red"]["aim_rad"]
    # one side: the parabola 2 x 0.045 / 0.15^2 = 4 per rad^2, a rise of 0.01 within 0.0707 rad
    assert red["identified"] and red["low"] == pytest.approx(aim - math.sqrt(0.005))
    assert red["high"] == pytest.approx(min(aim + math.sqrt(0.005), math.pi / 2))
    for led in ("green", "blue"):
        assert not out[led]["aim_rad"]["identified"]
        assert (out[led]["aim_rad"]["low"], out[led]["aim_rad"]["high"]) == (-math.pi / 2, math.pi / 2)
    assert not out["red"]["beam_half_angle_rad"]["identified"]


def test_presses_in_one_place_or_too_few_do_not_pin_a_layout():
    from pbr_tactile.layout_fit import presses_pin
    from scenes.camera import Camera
    from scenes.captures import RealTaps

    camera = Camera.from_spec(load_spec(SENSORS_DIR / "gelsight.toml").at_resolution(160, 120))
    ref = np.full((120, 160), 0.03)

    def taps(centres):
        depths = np.stack([ref.copy() for _ in centres])
        for d, (u, v) in zip(depths, centres):
            d[v, u] -= 1e-3
        return RealTaps(np.zeros((len(centres), 120, 160, 3)), depths, ref, [str(k) for k in range(len(centres))])

    assert presses_pin(None, camera) == (False, "no presses: a layout needs presses to pin it")
    # the fitted half is the even presses: two of four, 100 px apart, pin it
    ok, why = presses_pin(taps([(30, 30), (0, 0), (130, 30), (0, 0)]), camera)
    assert ok and why == "2 fitted presses spread over 100 px"
    ok, why = presses_pin(taps([(30, 30), (0, 0)]), camera)
    assert not ok and why == "1 fitted press(es), fewer than 2"
    ok, why = presses_pin(taps([(80, 60), (0, 0), (90, 65), (0, 0)]), camera)
    assert not ok and "lie within 11 px of each other, under 0.25 of the frame's 120 px: all in one place" in why


def test_spectral_gains_are_each_led_s_response_times_a_power_and_a_white_balance():
    """Pixels made by known powers p, white balances w and offsets through each LED's
    film response R are solved back to g = p R w exactly, and the free per-channel gains
    of the same pixels are not of that form when the pixels are not."""
    from pbr_tactile.image_model import solve_spectral_gains
    from pbr_tactile.real_image import CLIP_LEVEL

    rng = np.random.default_rng(0)
    X = rng.random((3000, 3))
    R = np.array([[1.0, 0.1, 0.0], [0.13, 1.0, 0.15], [0.0, 0.22, 1.0]])
    p, w, o = np.array([1.0, 0.6, 0.8]), np.array([0.5, 0.7, 0.4]), np.array([0.02, 0.01, 0.03])
    G = p[:, None] * R * w[None, :]
    Y = np.power(X @ G + o, 1 / 2.2)
    g, offset = solve_spectral_gains(X, Y, np.zeros_like(Y, bool), 2.2, R)
    np.testing.assert_allclose(g, G, atol=1e-5)
    np.testing.assert_allclose(offset, o, atol=1e-5)
    # clipped pixels are censored: a prediction above the clip level there costs nothing
    bright = np.power(X @ (2 * G) + o, 1 / 2.2)
    clipped = bright >= CLIP_LEVEL
    assert 0.02 < clipped.mean() < 0.5
    g2, _ = solve_spectral_gains(X, np.minimum(bright, CLIP_LEVEL), clipped, 2.2, R)
    np.testing.assert_allclose(g2, 2 * G, atol=1e-5)
    # gains outside the form are fitted only as far as it allows: the mix has no free cross-talk
    mixed = G.copy()
    mixed[2, 0] = 0.3  # the blue LED in the red channel, which its response does not allow
    g3, _ = solve_spectral_gains(X, np.power(X @ mixed + o, 1 / 2.2), np.zeros_like(Y, bool), 2.2, R)
    assert g3[2, 0] == pytest.approx(0.0, abs=1e-12)


def test_a_webcam_s_response_holds_the_exponent_and_caps_the_black_level():
    """``ImageModel(webcam=True)``: the exponent is searched within WEBCAM_GAMMA, and every
    offset is solved at most WEBCAM_BLACK^gamma (an image value of 0.1 without light),
    exactly as a bounded least squares would (``_nonnegative`` against scipy's)."""
    from scipy import optimize

    from pbr_tactile.image_model import WEBCAM_BLACK, WEBCAM_GAMMA, ImageModel, _nonnegative, solve_gains
    from scenes.camera import Camera

    camera = Camera.from_spec(load_spec(SENSORS_DIR / "gelsight.toml").at_resolution(16, 12))
    names = ["led0", "led0_leak", "led1", "led1_leak", "led2", "led2_leak"]
    basis = np.random.default_rng(0).random((12, 16, 6))
    free, held = ImageModel(basis, names, camera, None), ImageModel(basis, names, camera, None, webcam=True)
    index = free.start().names().index("gamma")
    assert free.bounds(True)[index] == (0.5, 3.0) and held.bounds(True)[index] == WEBCAM_GAMMA
    # a bright floor the gains cannot make: the free offset takes it, the held one stops at the cap
    rng = np.random.default_rng(1)
    X = rng.random((500, 3))
    y = np.power(X @ np.array([0.1, 0.05, 0.02]) + 0.3, 1 / 2.2)
    _, offset = solve_gains(X, y, np.zeros(500, bool), 2.2)
    assert offset == pytest.approx(0.3, abs=1e-9)
    gains, capped = solve_gains(X, y, np.zeros(500, bool), 2.2, black=WEBCAM_BLACK)
    assert capped == pytest.approx(WEBCAM_BLACK**2.2) and np.all(gains >= 0)
    for trial in range(50):
        A, b = rng.random((40, 4)), rng.random(40) * 2
        x = _nonnegative(A, b, 0.1, capped=2)
        ref = optimize.lsq_linear(A, b, bounds=(np.zeros(4), [np.inf, np.inf, 0.1, 0.1])).x
        assert np.sum((A @ x - b) ** 2) <= np.sum((A @ ref - b) ** 2) + 1e-9 and x.min() >= 0 and x[2:].max() <= 0.1


def test_the_layout_figure_reads_a_fitted_layout_and_draws_it(tmp_path, gelsight):
    import json

    from studies.layout_figure import figure, read_fitted

    fitted = tuple(LEDLayout("under", p.azimuth_rad, 0.014, 0.02, 0.6, math.radians(30)) for p in layout_of(gelsight))
    report = tmp_path / "report.json"
    report.write_text(json.dumps({"layout": {"fitted": True, "layout": layout_to_dicts(fitted)}}))
    assert read_fitted(report, gelsight) == fitted
    profile = tmp_path / "profile.toml"
    profile.write_text("[reference]\nled_gains = []\n" + "".join(
        "[[reference.layout]]\n" + "".join(f"{k} = {v!r}\n" for k, v in d.items()) for d in layout_to_dicts(fitted)))
    assert read_fitted(profile, gelsight) == fitted
    (tmp_path / "none.json").write_text(json.dumps({"layout": {"fitted": False}}))
    with pytest.raises(ValueError, match="holds no fitted layout"):
        read_fitted(tmp_path / "none.json", gelsight)
    out = figure(gelsight, {"the spec's": layout_of(gelsight), "fitted": fitted}, tmp_path / "layout.png")
    assert out.stat().st_size > 10_000 and out.read_bytes()[:4] == b"\x89PNG"


def test_the_layout_s_inputs_are_refused_by_name(tmp_path, gelsight):
    """A layout seed that is no fast-path report, a seed without the fit, and a start the
    search does not have: each a clear error naming what was expected."""
    import json

    from pbr_tactile.calibrate_capture import calibrate_capture, layout_seed_places
    from pbr_tactile.layout_fit import fit_layout
    from scenes.camera import Camera

    with pytest.raises(FileNotFoundError, match=r"--layout-seed .*missing.json: no such file \(a fast-path"):
        layout_seed_places(tmp_path / "missing.json")
    bad = tmp_path / "report.json"
    bad.write_text(json.dumps({"fast_path": {"taps": {}}}))
    with pytest.raises(ValueError, match=r"not a fast-path calibration's report.json with fitted LED places"):
        layout_seed_places(bad)
    bad.write_text("{not json")
    with pytest.raises(ValueError, match=r"--layout-seed .*report.json: not a fast-path"):
        layout_seed_places(bad)
    bad.write_text(json.dumps({"fast_path": {"taps": {"places": {"places_m": [[0.02, 0.0, 0.02]] * 3}}}}))
    assert layout_seed_places(bad) == [[0.02, 0.0, 0.02]] * 3
    # a field chosen for its constants that did not move the LEDs: the field that did gives its places
    bad.write_text(json.dumps({"fast_path": {"taps": {"field": "geodesic", "by_field": {
        "geodesic": {"leds": []}, "linear": {"places": {"places_m": [[0.01, 0.0, 0.02]] * 3}}}}}}))
    assert layout_seed_places(bad) == [[0.01, 0.0, 0.02]] * 3
    bad.write_text(json.dumps({"fast_path": {"taps": {"by_field": {"geodesic": {"leds": []}}}}}))
    with pytest.raises(ValueError, match=r"not a fast-path calibration's report.json with fitted LED places"):
        layout_seed_places(bad)
    with pytest.raises(ValueError, match="--layout-seed seeds the layout's fit: give --fit-layout too"):
        calibrate_capture(None, tmp_path / "out", lambda *a: None, background_only=tmp_path / "none.png",
                          layout_seed=bad)
    assert not (tmp_path / "out").exists()
    spec = gelsight.at_resolution(16, 12)
    camera = Camera.from_spec(spec)
    with pytest.raises(ValueError, match=r"fit_layout: no start named nowhere \(have spec, edge, under_r0.35"):
        fit_layout(np.full((12, 16, 3), 0.5), spec, None, camera, None, only=("spec", "nowhere"), film=(16, 12))
