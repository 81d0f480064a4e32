"""Light guided up the glass wall: the directional core leak (Effects.core_leak_cone_rad).

Cheap checks: the option's range and default (off, renders unchanged), the sources it
makes, the photon sources' validation and cache keys, the guiding angle it is documented
with, the cone sampling of the photon pass, and that its light reaches the tip.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from pbr_tactile.effects import RANGES, Effects
from pbr_tactile.photons import Source, sources_from
from pbr_tactile.scene import IOR_SILICONE, LEAK_AXIS, led_sources
from scenes.spec import GLASS_IOR


def test_the_directional_leak_is_off_by_default_and_bounded():
    assert Effects().core_leak_cone_rad == 0.0
    assert RANGES["core_leak_cone_rad"] == (0.0, math.pi / 2)
    assert Effects(core_leak_cone_rad=math.pi / 2).core_leak_cone_rad == math.pi / 2
    for bad in (-0.1, math.pi / 2 + 1e-6, math.nan, math.inf):
        with pytest.raises(ValueError, match=r"Effects\.core_leak_cone_rad must be in \[0, 1\.5708\]"):
            Effects(core_leak_cone_rad=bad)
    assert Effects().with_settings(["core_leak_cone_rad=0.33"]).core_leak_cone_rad == 0.33


def test_off_the_sources_are_lambertian_spheres_as_before(spec):
    for effects in (Effects(), Effects(core_light_leak=0.5), Effects(core_leak_cone_rad=0.7)):
        for src in led_sources(spec, effects):
            assert src["cone_axis"] is None and src["cone_half_angle_rad"] == 0.0
    # the photon pass's sources and their cache keys are the ones of before
    srcs = sources_from(led_sources(spec, Effects(core_light_leak=0.5)))
    assert all(not s.directional and s.key() == (s.name, s.centre, s.radius, s.in_elastomer) for s in srcs)


def test_on_only_the_leaks_aim_up_the_tube(spec):
    effects = Effects(core_light_leak=0.5, core_leak_cone_rad=0.4)
    sources = led_sources(spec, effects)
    assert len(sources) == 2 * len(spec.leds)
    for src in sources:
        if src["name"].endswith("_leak"):
            assert src["cone_axis"] == LEAK_AXIS == (0.0, 0.0, 1.0) and src["cone_half_angle_rad"] == 0.4
            assert not src["in_elastomer"]
        else:
            assert src["cone_axis"] is None
    srcs = sources_from(sources)
    leak = [s for s in srcs if s.directional]
    assert len(leak) == len(spec.leds)
    # the cone is part of what the light pass (and its no-contact cache) depends on
    assert leak[0].key()[-2:] == ((0.0, 0.0, 1.0), 0.4)
    other = sources_from(led_sources(spec, Effects(core_light_leak=0.5, core_leak_cone_rad=0.5)))
    assert {s.key() for s in srcs if s.directional}.isdisjoint({s.key() for s in other if s.directional})


def test_a_photon_source_refuses_a_bad_cone():
    base = dict(centre=(0.0, 0.0, 0.0), radius=1e-3, peak_nm=None, fwhm_nm=None, scale=1.0, in_elastomer=False,
                name="s")
    with pytest.raises(ValueError, match="cone_axis must be a unit 3-vector"):
        Source(**base, cone_axis=(0.0, 0.0, 2.0), cone_half_angle_rad=0.3)
    with pytest.raises(ValueError, match=r"cone_half_angle_rad must be in \(0, pi\]"):
        Source(**base, cone_axis=(0.0, 0.0, 1.0), cone_half_angle_rad=0.0)
    assert Source(**base, cone_axis=(0.0, 0.0, 1.0), cone_half_angle_rad=0.3).directional


def test_the_documented_guiding_angle():
    """The wall guides light by total internal reflection at the glass-elastomer interface
    (the weaker of its two) within asin(n_s / n_g) of the normal: ~19 deg = 0.33 rad of
    the axis, as the Effects doc says; and light coupled in through the tube's flat end
    from air travels within asin(1 / n_g) ~ 42 deg of the axis."""
    guided = math.pi / 2 - math.asin(IOR_SILICONE / GLASS_IOR)
    assert guided == pytest.approx(0.33, abs=0.005)
    assert math.asin(1.0 / GLASS_IOR) == pytest.approx(math.radians(42.2), abs=0.005)


def test_the_volpath_scene_refuses_the_directional_leak(mesh, spec, camera):
    pytest.importorskip("mitsuba", reason="Mitsuba 3 is not installed (pip install '.[pbr]')")
    from pbr_tactile.render import RenderSettings, reference

    with pytest.raises(ValueError, match="core_leak_cone_rad"):
        reference(None, None, mesh, spec, camera, Effects(core_light_leak=0.5, core_leak_cone_rad=0.3),
                  RenderSettings(estimator="volpath", spp=2, passes=2, width=8, height=6))


def test_photons_leave_within_the_cone_uniformly_and_lambertian_ones_by_cosine(photon_mi):
    mi = photon_mi
    import drjit as dr

    from pbr_tactile.photons import _LAMBERTIAN, _start_direction

    n = 1 << 16
    rng = np.random.default_rng(0)
    u = mi.Point2f(mi.Float(rng.random(n)), mi.Float(rng.random(n)))
    axis = np.array([0.3, -0.4, math.sqrt(1 - 0.25)])
    normal = mi.Vector3f(*[mi.Float(np.full(n, a)) for a in axis])
    for half in (0.33, 0.73, math.pi / 2):
        d = _start_direction(mi, dr, normal, mi.Float(np.full(n, math.cos(half))), u)
        cos = np.stack([np.asarray(d[k]) for k in range(3)], -1) @ axis
        assert cos.min() >= math.cos(half) - 1e-5
        # uniform in solid angle: cos uniform on [cos(half), 1]
        assert cos.mean() == pytest.approx((1 + math.cos(half)) / 2, abs=3e-3)
    d = _start_direction(mi, dr, normal, mi.Float(np.full(n, _LAMBERTIAN)), u)
    cos = np.stack([np.asarray(d[k]) for k in range(3)], -1) @ axis
    assert cos.min() >= -1e-6 and cos.mean() == pytest.approx(2 / 3, abs=3e-3)


def test_the_guided_leak_lights_the_tip_more_than_the_lambertian_one(mesh, spec, camera, photon_mi):
    """Photon deposits of each leak on the no-contact coating: aimed up the wall inside
    its guiding cone, far more of its flux lands on the dome than a Lambertian leak's."""
    mi = photon_mi
    from pbr_tactile.membrane import ElastomerBuilder
    from pbr_tactile.density import coating_vertices
    from pbr_tactile.photons import deposits, sources_from
    from pbr_tactile.render import load
    import tempfile

    from pbr_tactile.scene import geltip_scene, write_meshes

    solid = ElastomerBuilder(mesh, spec, camera, 1e-3)()
    junction = spec.membrane.base_z + spec.membrane.cylinder_length
    share = {}
    for cone in (0.0, 0.33):
        effects = Effects(core_light_leak=1.0, core_leak_cone_rad=cone)
        with tempfile.TemporaryDirectory() as folder:
            scene = geltip_scene(write_meshes(solid, folder), spec, camera, effects, 8, 6, spp=1)
            loaded = load(scene, mi.variant())[1]
            srcs = sources_from(led_sources(spec, effects))
            flux = deposits(mi, loaded, srcs, effects.sigma_t, effects.albedo, effects.coating_albedo, 1 << 12)
            z = coating_vertices(loaded)[:, 2]
        assert np.isfinite(flux).all() and (flux >= 0).all() and flux.sum() > 0
        share[cone] = float(flux[:, z > junction].sum() / flux.sum())
    assert share[0.33] > 2 * share[0.0]


def test_a_directional_leds_radiance_is_seen_only_inside_its_cone():
    """A beam LED is a sphere of radiance I / (pi r^2) towards its cone and dark outside it:
    as wide as the sphere, the Lambertian sphere's radiance."""
    base = dict(centre=(0.0, 0.0, 0.0), radius=1e-3, peak_nm=None, fwhm_nm=None, scale=1.0, in_elastomer=False,
                name="s")
    lambertian = Source(**base).seen_radiance()
    assert lambertian == pytest.approx(1.0 / (math.pi * 4 * math.pi * 1e-6))
    assert Source(**base, cone_axis=(0.0, 0.0, 1.0), cone_half_angle_rad=math.pi).seen_radiance() == \
        pytest.approx(lambertian)
    narrow = Source(**base, cone_axis=(0.0, 0.0, 1.0), cone_half_angle_rad=0.3).seen_radiance()
    assert narrow == pytest.approx(lambertian * 4 * math.pi / (2 * math.pi * (1 - math.cos(0.3))))


def test_the_camera_sees_a_beam_led_that_faces_it(spec, mesh, photon_mi):
    """Rendered: an LED in the tube 5 mm in front of the camera, its 30 deg beam aimed at the
    lens or away from it. Facing it, the LED outshines the membrane in the pixel it sits
    in; turned away, that pixel is the membrane's (the camera pass used to leave every
    beam LED dark, so a real unit's LEDs never showed in the glass' reflections)."""
    from pbr_tactile.render import RenderSettings, reference
    from scenes.camera import Camera
    from scenes.spec import LED

    camera = Camera.from_spec(spec)
    pixel = {}
    for name, direction in (("facing", (0.0, 0.0, -1.0)), ("away", (0.0, 0.0, 1.0))):
        one = spec.replace(leds=(LED("led", position=(0.0, 0.0, 0.005), direction=direction, colour=(1.0, 1.0, 1.0),
                                     k_d=1.0, k_s=0.0, peak_nm=620.0, fwhm_nm=20.0,
                                     beam_half_angle_rad=math.radians(30)),), led_groups=())
        est = reference(None, None, mesh, one, camera, Effects(),
                        RenderSettings(spp=16, passes=2, width=15, height=11, photons=1 << 14, seed=3))
        pixel[name] = float(est.mean[5, 7].sum())
        assert np.isfinite(est.mean).all()
    assert pixel["facing"] > 10 * pixel["away"] > 0


def test_a_beam_led_whose_axis_holds_a_negative_zero_renders_as_the_positive_one(spec, mesh, photon_mi):
    """A turned LED's axis can carry -0.0 (scenes.profile.turn_leds). Dr.Jit 1.5 can
    broadcast a literal vector holding -0.0 in place when it is multiplied by a wider array
    (not every such vector is: the shipped 2023 spec's axes hold -0.0 and render), so the
    camera pass' cone axis, kept across the first hit and the walk (twice as wide), broke
    the render ("operands have incompatible sizes"). Same seed: the image of +0.0."""
    from pbr_tactile.render import RenderSettings, reference
    from pbr_tactile.scene import led_sources
    from scenes.camera import Camera
    from scenes.spec import LED

    camera = Camera.from_spec(spec)
    images = []
    for x in (-0.0, 0.0):
        one = spec.replace(leds=(LED("led", position=(0.004, 0.0, -0.002), direction=(x, 0.0, 1.0),
                                     colour=(1.0, 1.0, 1.0), k_d=1.0, k_s=0.0, peak_nm=620.0, fwhm_nm=20.0,
                                     beam_half_angle_rad=math.radians(30)),), led_groups=())
        assert math.copysign(1.0, led_sources(one)[0]["cone_axis"][0]) == math.copysign(1.0, x)
        images.append(reference(None, None, mesh, one, camera, Effects(),
                                RenderSettings(spp=4, passes=2, width=15, height=11, photons=1 << 12, seed=3)).mean)
    np.testing.assert_allclose(images[0], images[1], rtol=1e-5, atol=1e-9)  # (the sign changes roundings)


def test_the_glass_wall_and_its_index_are_the_specs(spec):
    """The tube's wall thickness and refractive index come from the spec: the reference's
    interfaces, the wall's foot where an LED under it emits, and the refraction into it."""
    import dataclasses

    from pbr_tactile.scene import geltip_scene, led_beam, led_centres, led_places
    from scenes.camera import Camera
    from scenes.spec import LED

    thin = spec.replace(membrane=dataclasses.replace(spec.membrane, glass_wall=1e-3, glass_ior=1.52))
    led = dict(direction=(0.0, 0.0, 1.0), colour=(1.0, 0.0, 0.0), k_d=1.0, k_s=0.0)
    # 7.5 mm from the axis: under a 2 mm wall (7 to 9 mm), in the bore of a 1 mm one (8 to 9 mm)
    for sensor, place in ((spec, "wall_end"), (thin, "tube")):
        one = sensor.replace(leds=(LED("a", position=(0.0075, 0.0, -0.011), **led),), led_groups=())
        assert led_places(one) == [place]
    under = thin.replace(leds=(LED("a", position=(0.0085, 0.0, -0.011), **led),), led_groups=())
    assert led_places(under) == ["wall_end"] and led_centres(under)[0][0] == pytest.approx(0.0085)
    assert led_beam(under.leds[0], "wall_end", 1.52)[1] == pytest.approx(math.asin(1 / 1.52))
    scene = geltip_scene({k: "x.ply" for k in ("coating", "core", "base", "glass_inner", "glass_base")}, thin,
                         Camera.from_spec(thin), Effects(), 8, 6)
    assert scene["glass_inner"]["bsdf"]["int_ior"] == 1.52 and scene["core"]["bsdf"]["ext_ior"] == 1.52


@pytest.mark.parametrize("edit, message", [
    (dict(glass_wall=0.009), r"glass_wall \(0.009 m\) must be thinner than the tube's outer radius"),
    (dict(glass_wall=2.0), "looks like millimetres"),
    (dict(glass_wall=-1e-3), "glass_wall must be > 0"),
    (dict(glass_ior=1.0), r"glass_ior must be a glass' refractive index in \[1.3, 2.0\]"),
])
def test_a_glass_that_cannot_be_is_refused(edit, message):
    import tomllib

    from scenes.spec import DEFAULT_SPEC_PATH
    from scenes.spec_read import spec_from_dict

    data = tomllib.loads(DEFAULT_SPEC_PATH.read_text())
    data["membrane"].update(edit)
    with pytest.raises(ValueError, match=message):
        spec_from_dict(data, "test.toml")
