"""The elastic solid contact model (scenes.elastic_solid) against closed forms.

Hertz's contact of a ball on an elastic half-space (the model without a thickness, the
limit of a thick layer): the contact's radius sqrt(R d), the load 4/3 E* sqrt(R) d^1.5
and the surface outside the contact, u(r) = d / pi ((2 - r^2/a^2) asin(a/r) + sqrt(r^2/a^2
- 1)) (Johnson, Contact Mechanics, 3.42). An incompressible bonded layer keeps its volume
and bulges; a compressible one does not; a thinner layer is stiffer.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

pytest.importorskip("ContactMechanics", reason="the elastic solid model needs the contact extra "
                    "(pip install -e '.[contact]')")

from scenes.elastic_solid import BondedLayer, check_material, solve  # noqa: E402

R, D = 2.0e-3, 0.2e-3  # a 4 mm ball pressed 0.2 mm


def _ball(n: int, pixel: float):
    x = (np.arange(n) - n / 2 + 0.5) * pixel
    r = np.hypot(*np.meshgrid(x, x, indexing="ij"))
    return D - r * r / (2 * R), r


def test_a_ball_on_a_half_space_makes_hertz_s_contact():
    pixel = 0.1e-3
    delta, r = _ball(96, pixel)
    young, nu = 1.0e6, 0.5
    c = solve(delta, pixel, None, nu, young)
    a = math.sqrt(R * D)
    assert math.sqrt(c.contact.sum() * pixel * pixel / math.pi) == pytest.approx(a, abs=pixel / 2)
    assert c.load_n == pytest.approx(4 / 3 * young / (1 - nu * nu) * math.sqrt(R) * D**1.5, rel=0.01)
    out = r > 1.2 * a  # the surface outside the contact sinks as Hertz's does
    q = r[out] / a
    hertz = D / math.pi * ((2 - q * q) * np.arcsin(1 / q) + np.sqrt(q * q - 1))
    assert np.max(np.abs(c.u[out] - hertz)) < 2e-3 * D
    assert c.u[48, 48] == pytest.approx(D - (0.05e-3 * math.sqrt(2)) ** 2 / (2 * R), rel=1e-3)  # conforms inside


def test_an_incompressible_layer_keeps_its_volume_and_bulges():
    pixel = 0.1e-3
    delta, r = _ball(120, pixel)
    pushed = solve(delta, pixel, 2.5e-3, 0.3).u.clip(min=0).sum() * pixel * pixel
    tight = solve(delta, pixel, 2.5e-3, 0.5)
    # to a few parts in 10^3 (the ratio is held INCOMPRESSIBLE_MARGIN under 0.5)
    assert abs(tight.volume_m3) < 3e-3 * tight.u.clip(min=0).sum() * pixel * pixel
    assert tight.u.min() < -0.01 * D  # the bulge round the contact
    loose = solve(delta, pixel, 2.5e-3, 0.3)
    assert loose.volume_m3 > 0.5 * pushed  # a compressible layer loses volume


def test_a_thinner_layer_is_stiffer_and_the_half_space_the_softest():
    pixel = 0.1e-3
    delta, _ = _ball(120, pixel)
    loads = [solve(delta, pixel, h, 0.5, 1.0e6).load_n for h in (2.5e-3, 5e-3, None)]
    assert loads[0] > loads[1] > loads[2]


def _press(spec, where=(80.0, 60.0), depth_m=1.0e-3):
    """``spec`` at 160x120: its camera, mesh, no-contact depth, and a 4 mm ball pressed
    ``depth_m`` where the camera sees ``where`` (the frame's centre by default)."""
    import trimesh

    from scenes.camera import Camera, reference_depth
    from scenes.contact import press
    from scenes.geometry import membrane_mesh

    spec = spec.at_resolution(160, 120)
    camera, mesh = Camera.from_spec(spec), membrane_mesh(spec)
    ref = reference_depth(mesh, camera)[0]
    return spec, camera, mesh, ref, press(ref, camera, mesh, trimesh.primitives.Sphere(radius=2e-3), where, depth_m)


def _gelsight_press():
    from scenes.spec import SENSORS_DIR
    from scenes.spec_read import load_spec

    return _press(load_spec(SENSORS_DIR / "gelsight.toml"))


def _bonded(spec, camera, depth, ref):
    """(the deformed depth, the pixels the ball touches, those it reaches, the layer's window)."""
    layer = BondedLayer(spec, camera)
    out = layer.depth(depth, ref)
    contact, window = layer.solved(depth, ref)
    touching = np.zeros(np.shape(ref), bool)
    touching[window] = contact.contact
    return out, touching, ref - depth > 0, window


def test_the_fast_path_s_surface_from_a_press_on_the_gelsight():
    spec, camera, mesh, ref, depth = _gelsight_press()
    out, touching, pressed, _ = _bonded(spec, camera, depth, ref)
    # where the ball presses the surface is the ball's (within the solver's tolerance);
    # where the ball's footprint reaches past that contact the surface sinks below the
    # ball (the elastic contact is narrower than the geometric one, as Hertz's a^2 = R d
    # is half the chord's 2 R d); around it it sinks less the further it is, and an
    # incompressible gel rises somewhere
    assert touching.sum() > 0.5 * pressed.sum() and not (touching & ~pressed).any()
    assert np.allclose(out[touching], depth[touching], atol=2e-6)
    assert np.all(out[pressed] <= depth[pressed] + 2e-6)
    sunk = ref - out
    v, u = np.mgrid[:120, :160]
    ring = lambda lo, hi: sunk[(np.hypot(u - 80, v - 60) >= lo) & (np.hypot(u - 80, v - 60) < hi) & ~pressed]  # noqa: E731
    # (at 1 mm into a 2.5 mm incompressible gel: 225, 91 and 24 um down 1.5 to 2.0 mm from
    # the centre, then up by 53 um at 3.4 mm)
    assert ring(12, 14).mean() > ring(14, 16).mean() > ring(16, 18).mean() > 0
    assert ring(24, 30).mean() < -10e-6


def test_bad_layers_and_maps_are_refused_by_name():
    for thickness, nu, match in ((0.0, 0.5, "thickness"), (-1e-3, 0.3, "thickness"), (2e-3, 0.6, "Poisson"),
                                 (2e-3, -0.1, "Poisson"), (2e-3, float("nan"), "Poisson")):
        with pytest.raises(ValueError, match=match):
            check_material(thickness, nu)
    with pytest.raises(ValueError, match="finite"):
        solve(np.full((8, 8), np.nan), 1e-4, 2e-3, 0.5)
    with pytest.raises(ValueError, match="pixel"):
        solve(np.zeros((8, 8)), 0.0, 2e-3, 0.5)
    from types import SimpleNamespace as NS

    cored = NS(name="cored", membrane=NS(elastomer_thickness=None), elastic=NS(poisson_ratio=0.5))
    with pytest.raises(ValueError, match="states none"):
        BondedLayer(cored, None)
    with pytest.raises(ValueError, match="Poisson"):
        BondedLayer(cored, None, thickness=2e-3, poisson=0.7)


def test_a_press_on_the_geltip_s_curved_membrane():
    """The GelTip's tube (11.5 mm, a 2.5 mm elastomer) pressed on its side by a 4 mm ball
    0.6 mm deep: the surface is the ball's where it touches and never past it, sinks round
    the contact, less the further, and the contact's area is close to the flat layer's
    under the same ball (the tangent plane's approximation of a contact small beside the
    tube)."""
    from scenes.elastic_solid import ball_contact_radius
    from scenes.spec_read import default_spec

    where = (130.0, 60.0)  # on the tube's side, seen obliquely
    spec, camera, mesh, ref, depth = _press(default_spec(), where, 0.6e-3)
    out, touching, pressed, window = _bonded(spec, camera, depth, ref)
    assert touching.any() and not (touching & ~pressed).any()
    assert np.allclose(out[touching], depth[touching]) and np.all(out[pressed] <= depth[pressed] + 1e-9)
    assert np.all(out[window] - ref[window] <= 0.2e-3)  # the bulge stays small
    # the contact's area on the surface, from its pixels' footprints, against the flat layer's
    rays = camera.rays_channels_first
    P = ref * rays
    du, dv = np.gradient(P, axis=2), np.gradient(P, axis=1)
    area = np.linalg.norm(np.cross(du, dv, axis=0), axis=0)
    radius = math.sqrt(area[touching].sum() / math.pi)
    flat = ball_contact_radius(0.6e-3, 2e-3, spec.membrane.elastomer_thickness, spec.elastic.poisson_ratio)
    assert radius == pytest.approx(flat, rel=0.15)
    # round the contact the surface sinks, less the further from it (along the surface)
    sunk = (ref - out)[window]
    far = np.linalg.norm(P[(slice(None),) + window] - P[:, int(where[1]), int(where[0])][:, None, None], axis=0)
    outside = ~pressed[window]
    near = sunk[outside & (far > 1.2 * flat) & (far < 1.6 * flat)].mean()
    further = sunk[outside & (far > 2.0 * flat) & (far < 2.6 * flat)].mean()
    assert near > further and near > 20e-6


@pytest.mark.slow  # 15 to 22 s alone on 2 cores
def test_a_ball_s_depth_from_its_elastic_contact():
    from scenes.elastic_solid import DEPTH_SHARES, ball_contact_radius, ball_depth_for_contact

    R = 2e-3
    # on the half-space a shallow ball is Hertz's: a^2 = R d (the sphere is its paraboloid)
    assert ball_contact_radius(0.1e-3, R, None, 0.5) == pytest.approx(math.sqrt(R * 0.1e-3), rel=0.03)
    assert ball_depth_for_contact(math.sqrt(R * 0.15e-3), R, None, 0.5) == pytest.approx(0.15e-3, rel=0.03)
    # a thin bonded layer is stiffer: the same contact is made by a shallower press
    a = 1.2e-3
    assert ball_depth_for_contact(a, R, 2.5e-3, 0.5) < ball_depth_for_contact(a, R, None, 0.5)
    # the chord through a contact that wide is shallower still: an elastic contact is
    # narrower than the ball's footprint
    assert ball_depth_for_contact(a, R, 2.5e-3, 0.5) > R - math.sqrt(R * R - a * a)
    widest = ball_contact_radius(DEPTH_SHARES[-1] * R, R, 2.5e-3, 0.5)
    with pytest.raises(ValueError, match="outside what a ball"):
        ball_depth_for_contact(1.01 * widest, R, 2.5e-3, 0.5)
    assert ball_depth_for_contact(1.01 * widest, R, 2.5e-3, 0.5, cap=True) == pytest.approx(DEPTH_SHARES[-1] * R)


def test_an_import_takes_the_rim_as_the_elastic_contact_s_edge(tmp_path):
    from scenes import press_sets
    from scenes.dataset import read_meta, read_samples
    from scenes.elastic_solid import ball_depth_for_contact
    from test_import_capture import run_import, write_pack

    pack = write_pack(tmp_path / "dataPack.npz")  # rings peaking 13.5 px from their centres
    R, pixel = press_sets.DEFAULTS["taxim"]["ball_m"] / 2, press_sets.DEFAULTS["taxim"]["pixel_m"]
    run_import(tmp_path, pack, out="chord")
    chord = {r["id"]: r for r in read_samples(tmp_path / "chord")}
    summary = run_import(tmp_path, pack, out="elastic", depth="elastic")
    assert summary["depth"] == "elastic" and summary["rims_capped"] == 0
    assert read_meta(tmp_path / "elastic")["import"]["depth"] == "elastic"
    for r in read_samples(tmp_path / "elastic"):
        edge = r["contact_edge_px"]
        assert edge == pytest.approx(chord[r["id"]]["contact_edge_px"])
        assert r["measured_depth"] == pytest.approx(ball_depth_for_contact(edge * pixel, R, 2.5e-3, 0.5), rel=1e-9)
        assert r["measured_depth"] > chord[r["id"]]["measured_depth"] and r["contact_radius_capped"] is False


def test_the_reference_s_membrane_takes_the_bonded_dent():
    """The reference's refined membrane dented by the bonded model: every vertex the ball
    reaches is on it, and every vertex near the press sinks as the fast path's surface
    does at the vertex's pixel (the same solve read at the vertices), except that it never
    rises: the reference leaves the bulge out."""
    from scipy import ndimage

    from scenes.camera import project
    from scenes.elastic import MembraneLayer

    spec, camera, mesh, ref, depth = _gelsight_press()
    solver = BondedLayer(spec, camera)
    membrane = MembraneLayer(mesh, spec, camera, bonded=solver)
    bonded = membrane.deformation(depth, ref)
    reached = bonded.penetration > 1e-6
    assert reached.sum() > 100 and np.all(bonded.displacement[reached] >= bonded.penetration[reached] - 1e-12)
    assert np.all(bonded.displacement >= 0)
    sink = ref - solver.depth(depth, ref)  # the fast path's, along the view (head-on: the normal)
    uv = project(membrane.vertices, camera)
    near = np.hypot(uv[:, 0] - 80, uv[:, 1] - 60) < 30
    fast = ndimage.map_coordinates(sink, [uv[near, 1], uv[near, 0]], order=1)
    np.testing.assert_allclose(bonded.displacement[near], np.clip(fast, 0, None), atol=8e-6)
    assert (fast < -20e-6).any() and np.all(bonded.displacement[near][fast < 0] < 8e-6)


def test_the_reference_s_elastic_option():
    from pbr_tactile.plugin import elastic_option

    assert elastic_option(None) is None and elastic_option("layer") is None
    assert elastic_option("bonded") == {"model": "bonded", "thickness_m": None, "poisson_ratio": None}
    assert elastic_option({"model": "bonded", "thickness_m": 5e-3, "poisson_ratio": 0.45}) == {
        "model": "bonded", "thickness_m": 5e-3, "poisson_ratio": 0.45}
    for bad, match in (("published", "must be 'layer', 'bonded'"), ({"model": "bonded"}, "thickness_m and"),
                       ({"model": "bonded", "thickness_m": 5e-3, "poisson_ratio": 0.55}, "Poisson")):
        with pytest.raises(ValueError, match=match):
            elastic_option(bad)
