"""The light-path study's settings (studies.light_paths): what each run searches, and its
geometric check of the dome's junction against the real image's edge."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from pbr_tactile import scene
from scenes.camera import Camera
from scenes.spec_read import default_spec, load_spec
from studies import light_paths as lp


def test_a_given_grid_replaces_each_variants_own_and_keeps_its_switched_off_effects_off():
    grid = {"absorption_per_m": (5.0,), "scattering_per_m": (250.0,)}
    assert lp.variant_grid("full") == lp.VARIANTS["full"][0]
    assert lp.variant_grid("full", grid) == grid
    assert lp.variant_grid("no_scattering", grid) == {"absorption_per_m": (5.0,), "scattering_per_m": (0.0,)}
    assert lp.variant_grid("no_absorption", grid) == {"absorption_per_m": (0.0,), "scattering_per_m": (250.0,)}
    assert lp.variant_grid("guided_only", grid)["scattering_per_m"] == (0.0,)


def test_a_malformed_grid_is_refused_naming_it(capsys):
    with pytest.raises(SystemExit):
        lp.main(["--out", "unused", "--grid", "absorption_per_m=a,b"])
    assert "--grid 'absorption_per_m=a,b': expected NAME=V1,V2" in capsys.readouterr().err


def test_the_edge_is_found_where_the_brightness_steps_up_in_each_lit_sector():
    h, w, circle = 240, 320, (160.0, 120.0, 110.0)
    v, u = np.mgrid[0:h, 0:w].astype(float)
    rho = np.hypot(u - circle[0], v - circle[1]) / circle[2]
    phi = np.mod(np.arctan2(v - circle[1], u - circle[0]), 2 * math.pi)
    lit = phi < math.pi  # a step at rho 0.42 on one half, a smooth ramp on both
    grey = 0.3 + 0.2 * rho + np.where(lit & (rho > 0.42), 0.3, 0.0)
    image = np.repeat(grey[..., None], 3, axis=2) / 3
    found, rise = lp.radial_edges(image, circle, sectors=8)
    assert np.allclose(found[:4], 0.42, atol=0.015)
    assert rise[:4].min() > 5 * rise[4:].max()
    edge = lp.real_edge(image, circle)
    assert edge["sectors"] == edge["of"] // 2 and abs(edge["rho_median"] - 0.42) < 0.015


def test_the_junction_is_seen_through_the_glass_as_snell_bends_the_ray():
    spec = default_spec()
    m, camera = spec.membrane, Camera.from_spec(spec)
    z = m.base_z + m.cylinder_length
    # with every index 1 (a thought experiment the spec would refuse) the ray is straight
    plain = spec.replace(membrane=dataclasses.replace(m, glass_ior=1.0))
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(scene, "IOR_SILICONE", 1.0)
        straight = lp.junction_rho(plain)
    assert straight == pytest.approx(camera.f * m.radius / z / camera.mask_radius_px, rel=1e-9)
    # refraction bends the ray towards the wall's normal: the junction is seen nearer the axis
    bent = lp.junction_rho(spec)
    assert bent < 0.8 * straight
    # a wider lens puts it nearer the centre, and so does a calibrated lens with a smaller scale
    wide = spec.replace(camera=dataclasses.replace(spec.camera, fov_y=math.radians(135.0)))
    assert lp.junction_rho(wide) < 0.5 * bent
    half = dataclasses.replace(camera, f=camera.f / 2)
    assert lp.junction_rho(spec, half) == pytest.approx(bent / 2, rel=1e-9)


def test_the_junction_needs_a_capsule():
    spec = load_spec("scenes/sensors/geltip_2023.toml")
    assert 0.05 < lp.junction_rho(spec) < 0.2
    meshed = spec.replace(membrane=dataclasses.replace(spec.membrane, shape="mesh"))
    with pytest.raises(ValueError, match="not a capsule"):
        lp.junction_rho(meshed)


def test_a_malformed_circle_is_refused_naming_it():
    image = np.zeros((60, 80, 3))
    for circle in ((40.0, 30.0), (40.0, 30.0, 0.0), (40.0, float("nan"), 20.0)):
        with pytest.raises(ValueError, match="circle must be"):
            lp.radial_edges(image, circle)
