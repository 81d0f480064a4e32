"""Geodesic and transport light fields: analytic surfaces first, then the published fields."""

from __future__ import annotations

import math

import numpy as np
import pytest
import trimesh

from phong_reference.bake import bake
from phong_reference.geodesic import GeodesicBaker, bake_geodesic
from phong_reference.sources import Sources
from phong_reference.transport import TransportBaker, bake_transport
from phong_reference.tangent import angle_deg
from scenes.camera import SurfaceSamples
from scenes.shapes.capsule import profile as capsule_profile
from scenes.shapes.revolve import revolve

#: Test surfaces: radius and triangle edge, metres (small meshes, ~1-3k vertices).
R = 0.010
EDGE = 0.001

#: Geodesic distance vs the analytic one: relative, plus an absolute floor in metres.
#: Derived: the mesh's faces are chords, so an exact polyhedral geodesic over an arc of
#: angle EDGE / R is shorter than the arc by (EDGE / R)^2 / 24 = 4.2e-4 (the cylinder gave
#: 4e-4; the hemisphere, curved both ways and unevenly triangulated, 1.2e-3). The failure
#: guarded is a distance along mesh edges (Dijkstra), longer by up to 2 / sqrt(3) - 1 =
#: 15 % on a triangle lattice; 0.5 % is 12 times the chords' shortfall and a thirtieth of
#: that. The floor, a tenth of an edge, is where a relative error has no meaning (within
#: ATOL / RTOL = 20 edges of the source); a source or a distance one vertex off is a whole
#: edge off (seen: 0.03 mm).
DISTANCE_RTOL = 0.005
DISTANCE_ATOL = 0.1 * EDGE

#: Largest angle between a baked direction and the analytic one, degrees, beyond two
#: edges from the source. Why 3: the baker's direction is the vertex-averaged gradient of
#: the exact distance; the piecewise-constant face gradient it improves on errs by
#: O(EDGE / d) (phong_reference.geodesic), of order 0.4 rad across one face at the nearest
#: samples compared (d = COMPARE_FROM_EDGES edges), and a sign error by 180. The averaged
#: gradient's worst samples, at those distances, gave 1.4 (cylinder) and 1.8 (hemisphere).
GEODESIC_ANGLE_TOL_DEG = 3.0

#: Samples this far from the source, in edges, are compared (the baker refuses closer).
COMPARE_FROM_EDGES = 2.5

#: Azimuths within this of the cylinder's cut locus (dphi = ±pi), radians, are skipped.
CUT_MARGIN = 0.3

#: Transported +z on a cylinder: largest angle to +z, degrees. Analytic answer 0: a
#: cylinder is flat (zero Gaussian curvature), so transport along any path keeps +z. Why 1:
#: a transport that followed the mesh's facets, not the smooth surface, turns with each
#: face's normal, EDGE / R = 5.7 deg between neighbouring faces, and one that followed the
#: geodesics' own direction turns by up to 90; 1 is a sixth of one face's turn (seen: 0.27).
TRANSPORT_ANGLE_TOL_DEG = 1.0

#: Unit length and tangency of baked float32 fields.
UNIT_TOL = 1e-5
TANGENT_TOL = 1e-5

#: On the hemispherical tip, the mean cosine between two LEDs' transported fields stays
#: below this. Why 0.8: the failure is fields that lost their signs, which coincide (cosine
#: ~1); the analytic fields point away from LEDs 120 deg apart, cosine -1/2 at the pole,
#: rising towards 1 near the rim where all run up the meridian (seen: a mean of 0.58 over
#: polar angles below 60 deg). 0.8 lies between, nearer the failure, so a field that is
#: right over most of the cap passes.
TIP_MAX_MEAN_COSINE = 0.8

#: Mean angle between our geodesic field and the authors' one, degrees, per LED. Theirs
#: is the chord of the last path segment, ending at the vertex nearest the pixel, so it is
#: quantised to the mesh and not tangent: a chord l long on a surface of radius R leaves
#: the tangent at its end by l / (2 R), 2.5 deg for l = 1 mm on the GelTip's 11.5 mm (seen:
#: 2.8, 2.1, 2.8). Why 5: twice that chord tilt, far below a field with its sign lost
#: (180 deg: the published transport's failure, reported below).
GEODESIC_REFERENCE_MAX_MEAN_DEG = 5.0


def sources_at(mesh: trimesh.Trimesh, points, direction=(0.0, 0.0, 1.0)) -> Sources:
    """Sources at the vertices nearest given points, all emitting along one direction."""
    points = np.atleast_2d(np.asarray(points, dtype=np.float64))
    vertices = np.array([int(np.argmin(np.linalg.norm(mesh.vertices - p, axis=1))) for p in points])
    normals = np.asarray(mesh.vertex_normals)[vertices]
    directions = np.tile(np.asarray(direction, dtype=np.float64), (len(points), 1))
    return Sources(np.asarray(mesh.vertices)[vertices], vertices, directions, normals)


@pytest.fixture(scope="module")
def cylinder():
    """Open cylinder of radius R from z = 0 to 40 mm."""
    return revolve(np.array([[R, 0.0], [R, 0.04]]), EDGE)


@pytest.fixture(scope="module")
def hemisphere():
    """Hemisphere of radius R about the origin, open at z = 0, pole at z = R."""
    theta = np.linspace(0.0, math.pi / 2, 65)
    profile = np.stack([R * np.cos(theta), R * np.sin(theta)], axis=1)
    profile[-1, 0] = 0.0
    return revolve(profile, EDGE)


@pytest.fixture(scope="module")
def capsule():
    """Cylinder 20 mm long from z = 0, closed by a hemispherical tip centred at z = 20 mm."""
    return revolve(capsule_profile(R, 0.02, 0.0), EDGE)


def cylinder_coords(points: np.ndarray, source: np.ndarray):
    """(dphi in (-pi, pi], dz) of points about a source on the z-axis cylinder."""
    phi0 = math.atan2(source[1], source[0])
    phi = np.arctan2(points[:, 1], points[:, 0])
    dphi = (phi - phi0 + np.pi) % (2 * np.pi) - np.pi
    return dphi, points[:, 2] - source[2]


# --- geodesic: analytic ---------------------------------------------------------------


def test_cylinder_geodesic_distance_is_unrolled_arc_length(cylinder):
    V = np.asarray(cylinder.vertices)
    src = sources_at(cylinder, [R, 0.0, 0.01])
    d = GeodesicBaker(cylinder).distance(int(src.vertices[0]))
    dphi, dz = cylinder_coords(V, src.positions[0])
    unrolled = np.hypot(R * dphi, dz)
    away = np.abs(dphi) < np.pi - CUT_MARGIN
    np.testing.assert_allclose(d[away], unrolled[away], rtol=DISTANCE_RTOL, atol=DISTANCE_ATOL)
    assert d[int(src.vertices[0])] == 0.0


def test_cylinder_geodesic_direction_is_unrolled_straight_line(cylinder, rng):
    src = sources_at(cylinder, [R, 0.0, 0.01])
    phi = rng.uniform(-np.pi, np.pi, 3000)
    z = rng.uniform(0.001, 0.039, 3000)
    samples = SurfaceSamples.at_points(cylinder, np.stack([R * np.cos(phi), R * np.sin(phi), z], axis=1))
    fields, valid = bake_geodesic(cylinder, samples, src)

    P = samples.points
    dphi, dz = cylinder_coords(P, src.positions[0])
    phi = np.arctan2(P[:, 1], P[:, 0])
    e_phi = np.stack([-np.sin(phi), np.cos(phi), np.zeros_like(phi)], axis=1)
    expected = R * dphi[:, None] * e_phi + dz[:, None] * np.array([0.0, 0.0, 1.0])  # unrolled chord
    check = (np.hypot(R * dphi, dz) > COMPARE_FROM_EDGES * EDGE) & (np.abs(dphi) < np.pi - CUT_MARGIN)
    assert valid[0, check].all()
    err = angle_deg(fields[0, check], expected[check])
    assert err.max() < GEODESIC_ANGLE_TOL_DEG, f"max angle error {err.max():.2f} deg"


def test_hemisphere_geodesics_are_great_circles(hemisphere, rng):
    V = np.asarray(hemisphere.vertices)
    elevation = math.radians(30.0)
    src = sources_at(hemisphere, [R * math.cos(elevation), 0.0, R * math.sin(elevation)])
    s = src.positions[0] / np.linalg.norm(src.positions[0])  # unit direction of the source

    d = GeodesicBaker(hemisphere).distance(int(src.vertices[0]))
    u = V / np.linalg.norm(V, axis=1, keepdims=True)
    np.testing.assert_allclose(d, R * np.arccos(np.clip(u @ s, -1, 1)), rtol=DISTANCE_RTOL, atol=DISTANCE_ATOL)

    # Uniform on the cap z in (0.02 R, R).
    z = rng.uniform(0.02, 0.999, 3000)
    az = rng.uniform(-np.pi, np.pi, 3000)
    points = R * np.stack([np.sqrt(1 - z**2) * np.cos(az), np.sqrt(1 - z**2) * np.sin(az), z], axis=1)
    samples = SurfaceSamples.at_points(hemisphere, points)
    fields, valid = bake_geodesic(hemisphere, samples, src)
    p = samples.points / np.linalg.norm(samples.points, axis=1, keepdims=True)
    expected = (p @ s)[:, None] * p - s  # great circle from s, at p, heading away from s
    check = R * np.arccos(np.clip(p @ s, -1, 1)) > COMPARE_FROM_EDGES * EDGE
    assert valid[0, check].all()
    err = angle_deg(fields[0, check], expected[check])
    assert err.max() < GEODESIC_ANGLE_TOL_DEG, f"max angle error {err.max():.2f} deg"


def test_geodesic_is_invalid_at_the_source(cylinder):
    src = sources_at(cylinder, [R, 0.0, 0.01])
    samples = SurfaceSamples.at_points(cylinder, src.positions)
    fields, valid = bake_geodesic(cylinder, samples, src)
    assert not valid.any()
    assert np.all(fields == 0.0)


# --- transport: analytic --------------------------------------------------------------


def test_cylinder_transport_keeps_plus_z(cylinder, rng):
    src = sources_at(cylinder, [R, 0.0, 0.01], direction=(0.0, 0.0, 1.0))
    phi = rng.uniform(-np.pi, np.pi, 2000)
    z = rng.uniform(0.001, 0.039, 2000)
    samples = SurfaceSamples.at_points(cylinder, np.stack([R * np.cos(phi), R * np.sin(phi), z], axis=1))
    fields, valid = bake_transport(cylinder, samples, src)
    assert valid.all()
    err = angle_deg(fields[0], np.array([0.0, 0.0, 1.0]))
    assert err.max() < TRANSPORT_ANGLE_TOL_DEG, f"max angle to +z {err.max():.2f} deg"


def test_transport_keeps_signs_on_the_tip(capsule, rng):
    """Three LEDs on the rim emitting +z: over the tip they point away from their LED."""
    azimuths = 2 * np.pi * np.arange(3) / 3
    src = sources_at(capsule, np.stack([R * np.cos(azimuths), R * np.sin(azimuths), np.zeros(3)], axis=1))
    z = rng.uniform(0.5, 0.999, 2000)  # polar angle < 60 deg
    az = rng.uniform(-np.pi, np.pi, 2000)
    tip = np.stack([R * np.sqrt(1 - z**2) * np.cos(az), R * np.sqrt(1 - z**2) * np.sin(az), 0.02 + R * z], axis=1)
    fields, valid = TransportBaker(capsule).bake(SurfaceSamples.at_points(capsule, tip), src)
    for a, b in [(0, 1), (0, 2), (1, 2)]:
        both = valid[a] & valid[b]
        cos = (fields[a, both] * fields[b, both]).sum(axis=1).mean()
        assert cos < TIP_MAX_MEAN_COSINE, f"LEDs {a} and {b}: mean cosine {cos:.3f} on the tip"

    # At the pole each field points across, away from its LED; above the LED it is +z.
    pole_and_above = SurfaceSamples.at_points(capsule, [[0.0, 0.0, 0.02 + R], [R, 0.0, 0.015]])
    fields, valid = TransportBaker(capsule).bake(pole_and_above, src)
    assert valid.all()
    away = -np.stack([np.cos(azimuths), np.sin(azimuths), np.zeros(3)], axis=1)
    assert angle_deg(fields[:, 0], away).max() < 5.0
    assert angle_deg(fields[0, 1], np.array([0.0, 0.0, 1.0])) < TRANSPORT_ANGLE_TOL_DEG


# --- the default GelTip ---------------------------------------------------------------


@pytest.mark.parametrize("method", ["geodesic", "transport"])
def test_geltip_fields_are_unit_and_tangent(mesh, small_camera, spec, method):
    fields = bake(mesh, small_camera, spec.leds, method)
    assert fields.fields.shape == (3, 120, 160, 3)
    for m in range(3):
        valid = fields.valid[m]
        assert valid[small_camera.mask].mean() > 0.99
        assert not valid[~small_camera.mask].any()
        f = fields.fields[m][valid].astype(np.float64)
        n = fields.normals[valid].astype(np.float64)
        np.testing.assert_allclose(np.linalg.norm(f, axis=1), 1.0, atol=UNIT_TOL)
        assert np.abs((f * n).sum(axis=1)).max() < TANGENT_TOL


# --- bad input ------------------------------------------------------------------------


@pytest.mark.parametrize("baker", [GeodesicBaker, TransportBaker])
def test_out_of_range_source_vertex_is_refused(cylinder, baker):
    good = sources_at(cylinder, [[R, 0.0, 0.01], [-R, 0.0, 0.01]])
    bad_index = len(cylinder.vertices) + 7
    bad = Sources(good.positions, np.array([good.vertices[0], bad_index]), good.directions, good.normals)
    samples = SurfaceSamples.at_points(cylinder, [[0.0, R, 0.02]])
    with pytest.raises(ValueError, match=rf"sources\.vertices\[1\] = {bad_index} is out of range"):
        baker(cylinder).bake(samples, bad)


def test_distance_refuses_bad_vertex(cylinder):
    with pytest.raises(ValueError, match="vertex"):
        GeodesicBaker(cylinder).distance(-1)


# --- the authors' published fields ----------------------------------------------------


def mean_angle_to_reference(fields, valid, reference, mask) -> float:
    """Mean angle, degrees, inside the mask where both fields are non-zero."""
    ref_norm = np.linalg.norm(reference, axis=-1)
    both = mask & valid & (ref_norm > 0)
    return float(angle_deg(fields[both].astype(np.float64), reference[both]).mean())


def test_geodesic_matches_published_fields(mesh, small_camera, spec, reference_dir):
    ours = bake(mesh, small_camera, spec.leds, "geodesic")
    errors = []
    for m in range(3):
        reference = np.load(reference_dir / "light_fields" / f"geodesic_160x120_field_{m}.npy")
        assert reference.shape == (120, 160, 3)
        errors.append(mean_angle_to_reference(ours.fields[m], ours.valid[m], reference, small_camera.mask))
    print(f"geodesic vs published, mean angle per LED (deg): {np.round(errors, 2).tolist()}")
    assert max(errors) < GEODESIC_REFERENCE_MAX_MEAN_DEG, errors


def test_transport_against_published_fields(mesh, small_camera, spec, reference_dir):
    """Reported, not asserted: the published transport is said to have lost its signs."""
    ours = bake(mesh, small_camera, spec.leds, "transport")
    errors = []
    for m in range(3):
        reference = np.load(reference_dir / "light_fields" / f"transport_160x120_field_{m}.npy")
        errors.append(mean_angle_to_reference(ours.fields[m], ours.valid[m], reference, small_camera.mask))
    print(f"transport vs published, mean angle per LED (deg): {np.round(errors, 2).tolist()}")
    assert np.all(np.isfinite(errors))
