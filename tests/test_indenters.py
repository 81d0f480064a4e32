"""Indenters: the paper's eight objects built from parameters, and mesh files loaded as extra ones."""

from __future__ import annotations

import math

import numpy as np
import pytest
import trimesh
from hypothesis import given, settings
from hypothesis import strategies as st

from scenes.indenters import (
    BASE_HEIGHT_M,
    BASE_SIDE_M,
    CIRCLE_SEGMENTS,
    INDENTERS,
    ConeParams,
    CylinderParams,
    DotsParams,
    IndentedPrismParams,
    OpenCylinderParams,
    PacmanParams,
    RandomParams,
    SphereParams,
    indenter,
    indenter_params,
    load_indenter,
    make_indenter,
)

pytest.importorskip("manifold3d", reason="building indenters needs the manifold boolean engine")

MM = 1e-3
#: Bounds of every paper indenter, metres.
ENVELOPE = np.array([[-8, -8, 0], [8, 8, 20]]) * MM
#: Box faces are exact; this only absorbs float round-off, metres.
BOUNDS_TOL_M = 1e-9
#: A 64-gon's area falls short of its circle's by 1 - sin(2 pi / n) n / (2 pi) = 0.16 %.
POLYGON_REL_TOL = 1.0 - math.sin(2 * math.pi / CIRCLE_SEGMENTS) * CIRCLE_SEGMENTS / (2 * math.pi) + 1e-4
#: A ray hitting a flat face lands on it up to round-off, metres.
FLAT_HIT_TOL_M = 1e-9
#: A 5120-face icosphere of 5 mm radius lies inside its sphere by up to ~4 um (the
#: sagitta of 0.2 mm facets), more along a slanted vertical ray: 10 um covers 55 deg.
SPHERE_HIT_TOL_M = 10e-6
#: Our height maps against the published objects': mean |dz| over the footprint, metres
#: (only pixels on polygonal rims differ; there a ray may hit the top or the base).
PUBLISHED_MEAN_DZ_M = 0.05 * MM
BASE_VOLUME = BASE_SIDE_M**2 * BASE_HEIGHT_M
TOP = 20 * MM


@pytest.fixture(scope="module")
def built():
    return {name: make_indenter(name) for name in INDENTERS}


def height_at(mesh: trimesh.Trimesh, xy) -> np.ndarray:
    """z of the first hit of vertical rays cast down at (K, 2) points, metres; nan on a miss."""
    xy = np.atleast_2d(np.asarray(xy, dtype=np.float64))
    origins = np.c_[xy, np.full(len(xy), 1.0)]
    down = np.tile([0.0, 0.0, -1.0], (len(xy), 1))
    _, ray, loc = mesh.ray.intersects_id(origins, down, multiple_hits=False, return_locations=True)
    z = np.full(len(xy), np.nan)
    z[ray] = loc[:, 2]
    return z


# --- Every paper indenter -----------------------------------------------------------


@pytest.mark.parametrize("name", INDENTERS)
def test_paper_indenter_is_a_closed_solid_in_the_envelope(built, name):
    mesh = built[name]
    assert mesh.is_watertight
    assert mesh.is_winding_consistent
    assert mesh.volume > BASE_VOLUME  # the base plus a feature, wound outward
    np.testing.assert_allclose(mesh.bounds, ENVELOPE, atol=BOUNDS_TOL_M)
    # The feature reaches the envelope's top, and nothing but the base is below it.
    above = mesh.vertices[:, 2] > BASE_HEIGHT_M + BOUNDS_TOL_M
    assert mesh.vertices[above, 2].max() == pytest.approx(TOP, abs=BOUNDS_TOL_M)


def test_cylinder_volume_and_top_face_are_a_circle_of_radius_3mm(built):
    mesh, r, h = built["cylinder"], 3 * MM, 10 * MM
    assert mesh.volume - BASE_VOLUME == pytest.approx(math.pi * r**2 * h, rel=POLYGON_REL_TOL)
    top = (mesh.face_normals[:, 2] > 1 - 1e-9) & (mesh.triangles_center[:, 2] > TOP - BOUNDS_TOL_M)
    assert mesh.area_faces[top].sum() == pytest.approx(math.pi * r**2, rel=POLYGON_REL_TOL)


def test_open_cylinder_volume_is_an_annulus_open_down_to_the_base(built):
    mesh, R, w, h = built["open_cylinder"], 3.5 * MM, 0.8 * MM, 10 * MM
    assert mesh.volume - BASE_VOLUME == pytest.approx(math.pi * (R**2 - (R - w) ** 2) * h, rel=POLYGON_REL_TOL)
    z = height_at(mesh, [(0, 0), (R - w / 2, 0), (0, -(R - w / 2))])
    np.testing.assert_allclose(z, [BASE_HEIGHT_M, TOP, TOP], atol=FLAT_HIT_TOL_M)


def test_cone_volume_is_a_frustum_and_its_side_is_straight(built):
    mesh, R, r, h = built["cone"], 4 * MM, 0.5 * MM, 10 * MM
    assert mesh.volume - BASE_VOLUME == pytest.approx(math.pi * h / 3 * (R * R + R * r + r * r), rel=POLYGON_REL_TOL)
    radii = np.array([1.0, 2.0, 3.0]) * MM
    expected = BASE_HEIGHT_M + (R - radii) / (R - r) * h
    # A 64-gon's flat facets sit inside the cone by at most r (1 - cos(pi / 64)).
    sag = R * (1 - math.cos(math.pi / CIRCLE_SEGMENTS)) * h / (R - r)
    np.testing.assert_allclose(height_at(mesh, np.c_[radii, np.zeros(3)]), expected, atol=sag)
    assert height_at(mesh, (0, 0))[0] == pytest.approx(TOP, abs=FLAT_HIT_TOL_M)


def test_pacman_is_a_cylinder_less_a_70_degree_mouth_towards_plus_x(built):
    mesh, r, h, mouth = built["pacman"], 3 * MM, 10 * MM, math.radians(70)
    pie = (1 - mouth / (2 * math.pi)) * math.pi * r * r * h
    assert mesh.volume - BASE_VOLUME == pytest.approx(pie, rel=POLYGON_REL_TOL)
    z = height_at(mesh, [(2 * MM, 0), (-2 * MM, 0), (0, 2 * MM)])
    np.testing.assert_allclose(z, [BASE_HEIGHT_M, TOP, TOP], atol=FLAT_HIT_TOL_M)


def test_sphere_top_is_at_20mm_and_its_surface_is_a_5mm_sphere(built):
    mesh = built["sphere"]
    R, zc = 5 * MM, 15 * MM
    assert mesh.vertices[:, 2].max() == pytest.approx(TOP, abs=BOUNDS_TOL_M)
    x = np.array([0.0, 2.0, 3.0, 4.0]) * MM
    z = height_at(mesh, np.c_[x, np.zeros(4)])
    np.testing.assert_allclose(z, zc + np.sqrt(R * R - x * x), atol=SPHERE_HIT_TOL_M)
    # Outside the sphere's shadow the ray lands on the base.
    assert height_at(mesh, (6 * MM, 0))[0] == pytest.approx(BASE_HEIGHT_M, abs=FLAT_HIT_TOL_M)


def test_indented_prism_top_has_a_hemispherical_dimple(built):
    mesh = built["indented_prism"]
    centre, rim, corner, off = height_at(mesh, [(0, 0), (2.5 * MM, 0), (3.5 * MM, 3.5 * MM), (4.5 * MM, 0)])
    assert centre == pytest.approx(TOP - 2 * MM, abs=SPHERE_HIT_TOL_M)  # 2 mm deep
    assert corner == pytest.approx(TOP, abs=FLAT_HIT_TOL_M)
    assert rim == pytest.approx(TOP, abs=FLAT_HIT_TOL_M)  # 4 mm wide: flat beyond r = 2 mm
    assert off == pytest.approx(BASE_HEIGHT_M, abs=FLAT_HIT_TOL_M)  # 8 mm square prism
    assert IndentedPrismParams().dimple_radius == pytest.approx(2 * MM)


def test_dots_are_five_1mm_domes_on_a_19mm_plateau(built):
    mesh = built["dots"]
    angles = math.pi + 2 * math.pi * np.arange(5) / 5
    domes = 3 * MM * np.c_[np.cos(angles), np.sin(angles)]
    np.testing.assert_allclose(height_at(mesh, domes), TOP, atol=SPHERE_HIT_TOL_M)
    between = [(0, 0), (6.5 * MM, 6.5 * MM), (3 * MM, 0)]
    np.testing.assert_allclose(height_at(mesh, between), 19 * MM, atol=FLAT_HIT_TOL_M)
    assert height_at(mesh, (7.5 * MM, 0))[0] == pytest.approx(BASE_HEIGHT_M, abs=FLAT_HIT_TOL_M)


def test_random_is_reproducible_per_seed_and_differs_between_seeds():
    a, b, c = make_indenter("random", seed=7), make_indenter("random", seed=7), make_indenter("random", seed=8)
    np.testing.assert_array_equal(a.vertices, b.vertices)
    np.testing.assert_array_equal(a.faces, b.faces)
    assert a.volume != pytest.approx(c.volume, rel=1e-6)
    # The seed is used by random only.
    np.testing.assert_array_equal(make_indenter("cone", seed=1).vertices, make_indenter("cone", seed=2).vertices)


@settings(max_examples=8, deadline=None)
@given(seed=st.integers(0, 2**31 - 1))
def test_random_relief_is_a_closed_solid_inside_its_square_for_any_seed(seed):
    mesh = make_indenter("random", seed=seed)
    p = RandomParams()
    assert mesh.is_watertight and mesh.is_winding_consistent and mesh.volume > BASE_VOLUME
    feature = mesh.vertices[mesh.vertices[:, 2] > BASE_HEIGHT_M + BOUNDS_TOL_M]
    assert np.abs(feature[:, :2]).max() <= p.half_extent + BOUNDS_TOL_M
    assert feature[:, 2].max() == pytest.approx(TOP, abs=BOUNDS_TOL_M)
    # Seen from above, every stroke top is flat between the lowest allowed height and 20 mm.
    xs = np.linspace(-p.half_extent, p.half_extent, 81)
    z = height_at(mesh, np.stack(np.meshgrid(xs, xs), axis=-1).reshape(-1, 2))
    tops = z[z > BASE_HEIGHT_M + BOUNDS_TOL_M]
    assert len(tops) > 0
    assert tops.min() >= BASE_HEIGHT_M + p.min_height_fraction * p.height - BOUNDS_TOL_M


def test_matches_the_published_objects_seen_from_the_membrane(built, reference_dir):
    """Top-down height maps against the authors' STLs (in mm, read in place)."""
    published = {"indented_prism": "dot_in", "open_cylinder": "cylinder_shell"}
    xs = (np.arange(64) + 0.5) * 0.25 * MM - 8 * MM
    grid = np.stack(np.meshgrid(xs, xs), axis=-1).reshape(-1, 2)
    for name in INDENTERS[:-1]:  # the published random relief is one draw of its own
        ref = trimesh.load(reference_dir / "meshes" / "objects" / f"{published.get(name, name)}.stl")
        ref.apply_scale(MM)
        dz = np.abs(height_at(built[name], grid) - height_at(ref, grid))
        assert dz.mean() < PUBLISHED_MEAN_DZ_M, name


# --- Parameters ---------------------------------------------------------------------


def test_parameters_make_variants():
    thin = make_indenter("cylinder", radius=2 * MM, height=5 * MM)
    assert thin.bounds[1, 2] == pytest.approx(15 * MM)
    assert thin.volume - BASE_VOLUME == pytest.approx(math.pi * (2 * MM) ** 2 * 5 * MM, rel=POLYGON_REL_TOL)
    sharp = make_indenter("cone", top_radius=0.0)
    assert sharp.is_watertight and height_at(sharp, (0, 0))[0] == pytest.approx(TOP, abs=FLAT_HIT_TOL_M)
    assert indenter_params("dots", count=3) == DotsParams(count=3)


@pytest.mark.parametrize(
    "make",
    [
        lambda: CylinderParams(radius=9 * MM),  # wider than the base
        lambda: ConeParams(top_radius=5 * MM),  # top wider than the base of the cone
        lambda: OpenCylinderParams(wall=4 * MM),
        lambda: PacmanParams(mouth_angle=math.pi),
        lambda: SphereParams(neck_fraction=1.0),
        lambda: SphereParams(radius=11 * MM),  # wider than the base
        lambda: IndentedPrismParams(dimple_width=9 * MM),
        lambda: DotsParams(count=0),
        lambda: RandomParams(height=11 * MM),  # above the 20 mm envelope
        lambda: CylinderParams(height=float("nan")),
    ],
)
def test_bad_parameters_name_the_field(make):
    with pytest.raises(ValueError, match=r"Params\.\w+ must be"):
        make()


def test_unknown_parameter_and_name_are_refused_with_the_known_ones():
    with pytest.raises(ValueError, match="radius.*height"):
        make_indenter("cylinder", diameter=3 * MM)
    with pytest.raises(ValueError, match="dots, sphere, indented_prism"):
        make_indenter("torus")


# --- Mesh files ---------------------------------------------------------------------


def _write(tmp_path, mesh: trimesh.Trimesh, name: str) -> str:
    path = tmp_path / name
    mesh.export(path)
    return str(path)


def test_load_indenter_reads_millimetres_into_metres(tmp_path, built):
    mm = built["cone"].copy()
    mm.apply_scale(1 / MM)
    loaded = load_indenter(_write(tmp_path, mm, "cone.stl"))
    assert loaded.volume == pytest.approx(built["cone"].volume, rel=1e-9)
    np.testing.assert_allclose(loaded.bounds, ENVELOPE, atol=1e-12)
    in_metres = load_indenter(_write(tmp_path, built["cone"], "cone_m.ply"), units="m")
    assert in_metres.volume == pytest.approx(built["cone"].volume, rel=1e-9)


def test_indenter_takes_a_name_or_a_path(tmp_path):
    np.testing.assert_array_equal(indenter("random", seed=3).vertices, make_indenter("random", seed=3).vertices)
    box = trimesh.creation.box(extents=(10, 10, 5))
    assert indenter(_write(tmp_path, box, "box.obj")).volume == pytest.approx(500 * MM**3)
    with pytest.raises(ValueError, match=r"dots, sphere, indented_prism, cylinder.*'no_such_thing'"):
        indenter("no_such_thing")


def test_load_indenter_refuses_an_open_mesh(tmp_path):
    box = trimesh.creation.box(extents=(10, 10, 5))
    open_box = trimesh.Trimesh(box.vertices, box.faces[1:], process=False)
    path = _write(tmp_path, open_box, "open_box.stl")
    with pytest.raises(ValueError, match=r"open_box\.stl.*not watertight.*closed surface"):
        load_indenter(path)


def test_load_indenter_refuses_units_that_do_not_fit(tmp_path):
    box_mm = trimesh.creation.box(extents=(16, 16, 20))
    path = _write(tmp_path, box_mm, "box_mm.stl")
    with pytest.raises(ValueError, match=r"box_mm\.stl.*larger than 0\.5 m.*units='mm'"):
        load_indenter(path, units="m")
    box_m = trimesh.creation.box(extents=(16 * MM, 16 * MM, 20 * MM))
    path = _write(tmp_path, box_m, "box_m.stl")
    with pytest.raises(ValueError, match=r"box_m\.stl.*smaller than 0\.1 mm.*units='m'"):
        load_indenter(path, units="mm")
    with pytest.raises(ValueError, match="units must be 'm' or 'mm', got 'inch'"):
        load_indenter(path, units="inch")


def test_load_indenter_refuses_garbage_empty_and_nan_files(tmp_path):
    garbage = tmp_path / "garbage.stl"
    garbage.write_text("this is not a mesh")
    with pytest.raises(ValueError, match=r"garbage\.stl holds no triangle faces"):
        load_indenter(garbage)
    points = tmp_path / "points.obj"
    points.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\n")
    with pytest.raises(ValueError, match=r"points\.obj holds no triangle faces"):
        load_indenter(points)
    nan = tmp_path / "nan.obj"
    nan.write_text("v 0 0 0\nv 1 0 0\nv nan 1 0\nv 0 0 1\nf 1 2 3\nf 1 4 2\nf 1 3 4\nf 2 4 3\n")
    with pytest.raises(ValueError, match=r"nan\.obj: 1 vertices are NaN"):
        load_indenter(nan)
    with pytest.raises(FileNotFoundError, match="missing.stl"):
        load_indenter(tmp_path / "missing.stl")


def test_load_indenter_turns_an_inside_out_mesh_outward_with_a_warning(tmp_path):
    box = trimesh.creation.box(extents=(10, 10, 5))
    box.invert()
    path = _write(tmp_path, box, "inside_out.stl")
    with pytest.warns(UserWarning, match="inside-out"):
        loaded = load_indenter(path)
    assert loaded.volume == pytest.approx(500 * MM**3)
