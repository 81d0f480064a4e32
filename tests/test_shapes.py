"""Parametric membrane shapes (the analytic families of scenes.shapes.form): each family's
analytic map first, then its meshes, at the defaults and at the corners of BOUNDS."""

import inspect
import itertools
import math

import numpy as np
import pytest
import trimesh
from scipy.spatial import cKDTree

from scenes import shapes
from scenes.shapes import capsule, form, paw
from scenes.meridian import meridian
from scenes.spec import MembraneSpec

BASE_Z = -0.010  # m, the GelTip's: the camera (origin) sits 10 mm above the base
EDGE = 0.5e-3  # m, the default mesh edge
COARSE_EDGE = 1.0e-3  # m, for the corners of BOUNDS
ROLLS = np.linspace(0.0, math.pi, 5)
#: Distances below this are rounding, metres.
TOL_M = 1e-9


def corners(family):
    names = list(shapes.BOUNDS[family])
    return [dict(zip(names, c)) for c in itertools.product(*(shapes.BOUNDS[family][n] for n in names))]


#: The corners of BOUNDS whose meshes are checked: all low, all high and each
#: guarantee's closest call on the analytic surface (``diagnose`` over every corner), one
#: letter per parameter in BOUNDS' order, l(ow) or h(igh).
MESH_CORNERS = {
    "capsule": ["ll", "lh", "hl", "hh"],
    "thumb": ["llllll", "hhhhhh",
              "lllhlh",  # the least convex radius (3.8 mm): narrow, shallow, a tall leaning tip
              "llhlll",  # the least star cosine (0.14): the longest, seen from the base
              "hlllll"],  # the widest (30 mm)
    "paw": ["llllll", "hhhhhh",
            "llhhhl",  # the least concave radius (4.5 mm): 5 tall toes far from the axis
            "llhhll",  # the least convex radius (3.2 mm): 5 tall toes near the axis
            "lhlllh"],  # the least star cosine (0.095) and clearance (8 mm): long, deep waist
}


def corner(family, pattern):
    return {n: shapes.BOUNDS[family][n]["lh".index(c)] for n, c in zip(shapes.BOUNDS[family], pattern, strict=True)}


def cases():
    out = [(f, {}, EDGE) for f in shapes.ANALYTIC]
    out += [(f, corner(f, c), COARSE_EDGE) for f in shapes.ANALYTIC for c in MESH_CORNERS[f]]
    return [pytest.param(f, p, e, id=f"{f}-" + ("defaults" if not p else "-".join(f"{v:g}" for v in p.values())))
            for f, p, e in out]


def edge_curvatures(mesh):
    """Per vertex, the least and greatest normal curvature (1/m, convex positive) along
    its edges: 2 n_i . (p_i - p_j) / |p_i - p_j|^2, exact on a sphere."""
    e, V, N = mesh.edges_unique, mesh.vertices, mesh.vertex_normals
    d = V[e[:, 1]] - V[e[:, 0]]
    l2 = (d * d).sum(1)
    k = np.stack([-2 * (N[e[:, 0]] * d).sum(1) / l2, 2 * (N[e[:, 1]] * d).sum(1) / l2], axis=1)
    kmin, kmax = np.full(len(V), np.inf), np.full(len(V), -np.inf)
    for side in (0, 1):
        np.minimum.at(kmin, e[:, side], k[:, side])
        np.maximum.at(kmax, e[:, side], k[:, side])
    return kmin, kmax


def capped(mesh):
    """The mesh closed by a fan over its base loop, wound with the mesh."""
    loops = mesh.outline().entities
    loop = np.asarray(loops[0].points)
    loop = loop[:-1] if loop[0] == loop[-1] else loop
    V = np.vstack([mesh.vertices, mesh.vertices[loop].mean(axis=0)])
    cap = np.c_[loop, np.roll(loop, -1), np.full(len(loop), len(V) - 1)]
    closed = trimesh.Trimesh(V, np.vstack([mesh.faces, cap]), process=False)
    if not closed.is_winding_consistent:
        closed = trimesh.Trimesh(V, np.vstack([mesh.faces, cap[:, ::-1]]), process=False)
    return closed


# --- Parameters -------------------------------------------------------------------------


def test_every_parameter_has_a_default_bounds_a_unit_and_a_documented_meaning():
    assert shapes.ANALYTIC == tuple(shapes.DEFAULTS) == tuple(shapes.BOUNDS) == tuple(shapes.UNITS)
    for family in shapes.ANALYTIC:
        source = inspect.getsource(shapes.family(family)).splitlines()
        assert set(shapes.DEFAULTS[family]) == set(shapes.BOUNDS[family]) == set(shapes.UNITS[family])
        assert shapes.check_params(family, {}) == shapes.DEFAULTS[family]
        for name, (lo, hi) in shapes.BOUNDS[family].items():
            assert lo < hi and lo <= shapes.DEFAULTS[family][name] <= hi
            # The `#:` comment above the default names its unit.
            entry = f'"{name}": {shapes.DEFAULTS[family][name]}'
            line = next(i for i, s in enumerate(source) if s.strip().startswith(entry))
            assert source[line - 1].strip().startswith(f"#: {shapes.UNITS[family][name]},")


@pytest.mark.parametrize("family", shapes.ANALYTIC)
def test_every_corner_and_sample_of_bounds_keeps_the_guarantees(family):
    """check_params measures each shape's analytic surface (diagnose): every corner of
    BOUNDS, and points inside, pass it, with the margins it is built for."""
    rng = np.random.default_rng(3)
    bounds = shapes.BOUNDS[family]
    inside = [{n: float(rng.uniform(lo, hi)) for n, (lo, hi) in bounds.items()} for _ in range(8)]
    for p in inside:
        if "toes" in p:
            p["toes"] = float(round(p["toes"]))
    for p in corners(family) + inside:
        assert shapes.check_params(family, p) == p  # raises where a guarantee fails


def test_diagnose_measures_the_defaults_margins():
    for family in shapes.ANALYTIC:
        d = shapes.diagnose(family, {})
        assert d.min_concave_radius >= 4 * form.MIN_CONCAVE_RADIUS_M
        assert d.min_convex_radius >= 1.5 * form.MIN_CONVEX_RADIUS_M
        assert d.star_cosine >= 4 * form.STAR_MIN_COSINE
        assert d.clearance >= form.MIN_CORE_CLEARANCE_M + 0.5e-3
        assert d.width == pytest.approx(0.023, abs=TOL_M)
        assert (d.saddle_share > 0.05) == (family == "paw")
    assert shapes.diagnose("capsule", {}).min_concave_radius == math.inf


@pytest.mark.parametrize("family, params, match", [
    ("bone", {}, r"membrane\.params: unknown shape family 'bone'; expected one of capsule, thumb, paw"),
    ("thumb", {"radius": 0.01}, r"unknown parameter 'radius' for a 'thumb' membrane; expected some of width, depth"),
    ("thumb", {"width": "wide"}, r"membrane\.params\.width must be a number \(metres\), got 'wide'"),
    ("thumb", {"width": None}, r"membrane\.params\.width must be a number"),
    ("paw", {"toes": True}, r"membrane\.params\.toes must be a number"),
    ("thumb", {"depth": float("nan")}, r"membrane\.params\.depth must be finite \(metres\), got nan"),
    ("paw", {"radius": float("inf")}, r"membrane\.params\.radius must be finite"),
    ("paw", {"toes": 3.5}, r"membrane\.params\.toes must be a whole number, got 3\.5"),
    ("thumb", {"width": 23.0}, r"membrane\.params\.width = 23 m is outside its bounds \[0\.021, 0\.03\] m \(metres\)"),
    ("paw", {"toe_spread": 1.2},
     r"membrane\.params\.toe_spread = 1\.2 rad is outside its bounds \[0\.6, 0\.8\] rad \(radians\)"),
    ("capsule", {"radius": 0.005}, r"membrane\.params\.radius = 0\.005 m is outside its bounds"),
    ("thumb", {"pad_flatness": -0.1}, r"pad_flatness = -0\.1 is outside its bounds \[0, 0\.8\] \(dimensionless\)"),
])
def test_check_params_names_the_bad_input(family, params, match):
    with pytest.raises(ValueError, match=match):
        shapes.check_params(family, params, "membrane.params")


def test_check_params_refuses_a_combination_that_breaks_a_guarantee(monkeypatch):
    # Widen the bounds: the analytic check still refuses what they used to keep out.
    monkeypatch.setitem(shapes.BOUNDS["paw"], "toe_height", (0.0, 0.01))
    with pytest.raises(ValueError, match=r"'paw' membrane with .*toe_height=0\.004.*concave radius of curvature is "
                                         r"3\.2\d? mm, under MIN_CONCAVE_RADIUS_M = 4 mm"):
        shapes.check_params("paw", {"toe_height": 0.004})
    monkeypatch.setitem(shapes.BOUNDS["paw"], "waist_depth", (0.0, 0.01))
    with pytest.raises(ValueError, match=r"waist_depth=0\.005.*comes 6\.5 mm from the core's axis, under "
                                         r"MIN_CORE_CLEARANCE_M = 8 mm"):
        shapes.check_params("paw", {"waist_depth": 0.005})
    monkeypatch.setitem(shapes.BOUNDS["thumb"], "tip_lean", (0.0, 0.02))
    with pytest.raises(ValueError, match=r"tip_lean=0\.01.*not star-shaped from the axis"):
        shapes.check_params("thumb", {"tip_lean": 0.01})
    monkeypatch.setitem(shapes.BOUNDS["capsule"], "radius", (0.008, 0.03))
    with pytest.raises(ValueError, match=r"radius=0\.021.*42 mm wide, not under MAX_WIDTH_M = 40 mm"):
        shapes.check_params("capsule", {"radius": 0.021})


def test_shape_mesh_refuses_bad_edges_and_bases():
    with pytest.raises(ValueError, match=r"edge must be in \(0, 0\.004\] m, got 0\.5 \(millimetres\?"):
        shapes.shape_mesh("paw", {}, BASE_Z, 0.5)
    with pytest.raises(ValueError, match="edge must be in"):
        shapes.shape_mesh("paw", {}, BASE_Z, 0.0)
    with pytest.raises(ValueError, match="base_z must be finite"):
        shapes.shape_mesh("paw", {}, float("nan"), EDGE)
    with pytest.raises(ValueError, match=r"membrane: unknown parameter 'toe'"):
        shapes.shape_mesh("paw", {"toe": 3}, BASE_Z, EDGE)


# --- Analytic surfaces --------------------------------------------------------------------


def test_capsule_curvatures_are_one_over_its_radius():
    """The finite-difference curvatures, on a surface known by hand: a cylinder (0, 1/R)
    and a hemisphere (1/R, 1/R)."""
    r = 0.0115
    p, n, k = shapes.principal_curvatures("capsule", {"radius": r})
    body = p[:, 2] < 0.044 - TOL_M
    assert np.allclose(k[body], [0.0, 1 / r], atol=1e-3)
    assert np.allclose(k[~body], 1 / r, rtol=1e-5)
    # Normals point out: along the radius from the axis (body) or from the tip's centre.
    centre = np.c_[np.zeros((len(p), 2)), np.minimum(p[:, 2], 0.044)]
    assert np.allclose(n, (p - centre) / r, atol=1e-6)


def test_thumb_cross_section_is_an_ellipse_with_a_flattened_pad():
    p = shapes.DEFAULTS["thumb"]
    a, b, f = p["width"] / 2, p["depth"] / 2, p["pad_flatness"]
    mesh = shapes.shape_mesh("thumb", p, BASE_Z, EDGE)
    body = mesh.vertices[mesh.vertices[:, 2] < shapes.tip_start_z("thumb", p, BASE_Z) - TOL_M]
    x, y = body[:, 0], body[:, 1]
    back = y >= 0
    # The back (+y) is half an ellipse of semi-axes (a, b).
    assert np.allclose((x[back] / a) ** 2 + (y[back] / b) ** 2, 1.0, atol=1e-9)
    # The pad (-y) follows y = b psi(v), v = -sqrt(1 - (x/a)^2), psi(v) = v + f v^3 (1 + v),
    # so it lies outside the ellipse and is flatter.
    v = -np.sqrt(np.clip(1 - (x[~back] / a) ** 2, 0, 1))
    assert np.allclose(y[~back], b * (v + f * v**3 * (1 + v)), atol=1e-9)
    assert np.all((x[~back] / a) ** 2 + (y[~back] / b) ** 2 >= 1 - 1e-9)
    # Its curvature at the pad's centre is (1 - f) times the back's, b / a^2.
    pts, _, k = shapes.principal_curvatures("thumb", p)
    mid = np.abs(pts[:, 2] - 0.02) < 1e-3
    for side, expected in ((1.0, b / a**2), (-1.0, (1 - f) * b / a**2)):
        centre = mid & (np.abs(pts[:, 0]) < 1e-9) & (np.sign(pts[:, 1]) == side)
        assert centre.any()
        assert np.allclose(k[centre, 1], expected, rtol=1e-4)
        assert np.allclose(k[centre, 0], 0.0, atol=1e-3)


def test_thumb_is_asymmetric_its_apex_leaning_to_the_pad():
    p = shapes.DEFAULTS["thumb"]
    mesh = shapes.shape_mesh("thumb", p, BASE_Z, EDGE)
    extent = np.ptp(mesh.vertices, axis=0)
    assert extent[0] == pytest.approx(p["width"], abs=TOL_M)
    assert extent[1] == pytest.approx(p["depth"], abs=TOL_M)
    assert extent[0] / extent[1] > 1.15
    # The apex (the highest point) is the pole, moved tip_lean towards the pad (-y).
    apex = mesh.vertices[np.argmax(mesh.vertices[:, 2])]
    assert np.allclose(apex, [0.0, -p["tip_lean"], BASE_Z + p["length"]], atol=TOL_M)
    # The tip is no hemisphere: lower than half the width, and flatter on the pad side.
    tip = mesh.vertices[:, 2] - shapes.tip_start_z("thumb", p, BASE_Z)
    assert tip.max() == pytest.approx(p["tip_height"], abs=TOL_M) and tip.max() < p["width"] / 2
    # The axis leaves the membrane behind the apex, on the back side of the pole.
    top = meridian(mesh, 0.0).points[0]
    assert np.hypot(top[0], top[1]) < 1e-6 and top[2] < apex[2] - 1e-5


def test_paw_has_convex_toes_saddles_between_them_and_a_concave_waist():
    p = shapes.DEFAULTS["paw"]
    R, L, depth = p["radius"], p["cylinder_length"], p["waist_depth"]
    pts, n, k = shapes.principal_curvatures("paw", p)
    centre = np.array([0.0, 0.0, L])
    u = (pts - centre) / np.linalg.norm(pts - centre, axis=1, keepdims=True)
    tip = pts[:, 2] > L
    d, w = paw.toe_directions(p)
    assert len(d) == p["toes"] and 0 < w < paw.TOE_REACH_RAD - p["toe_spread"] + 1e-12
    # On a toe's crest both curvatures exceed the hemisphere's (1 / R): a convex bump.
    crest = tip & (u @ d[0] > math.cos(0.02))
    assert crest.any() and np.all(k[crest, 0] > 1.2 / R)
    # Halfway between two neighbouring toes, the valley is a saddle: concave across.
    mid = (d[0] + d[1]) / np.linalg.norm(d[0] + d[1])
    valley = tip & (u @ mid > math.cos(0.03))
    assert valley.any() and np.all(k[valley, 0] < -1 / 0.05) and np.all(k[valley, 1] > 0)
    assert shapes.diagnose("paw", p).saddle_share > 0.05
    # The hollow amid the toes, around the apex, is concave both ways on average.
    hollow = tip & (pts[:, 2] > L + R * math.cos(0.1))
    assert k[hollow].mean(axis=1).min() < -1 / 0.1
    # The body is the waist's surface of revolution, r(Z) = R - depth (1 - s^2)^3, whose
    # principal curvatures are -r'' / (1 + r'^2)^(3/2) (concave at the waist) and
    # 1 / (r sqrt(1 + r'^2)).
    h_w, z_w = paw.WAIST_HALF_LENGTH * L, paw.WAIST_CENTRE * L
    body = pts[:, 2] < L
    s = (pts[body, 2] - z_w) / h_w
    inside = np.abs(s) < 1
    s = np.where(inside, s, 1.0)
    r = R - depth * (1 - s**2) ** 3
    dr = depth * 6 * s * (1 - s**2) ** 2 / h_w
    d2r = depth * (6 * (1 - s**2) ** 2 - 24 * s**2 * (1 - s**2)) / h_w**2
    expected = np.sort(np.stack([-d2r / (1 + dr**2) ** 1.5, 1 / (r * np.sqrt(1 + dr**2))], axis=1), axis=1)
    assert np.allclose(k[body], expected, rtol=1e-4, atol=1e-2)
    assert k[body, 0].min() == pytest.approx(-6 * depth / h_w**2, rel=1e-2)


def test_paw_mesh_is_concave_where_the_map_is():
    """The mesh's own curvature (along its edges, from its vertex normals) finds the
    saddles and the least concave radius the analytic surface has."""
    p = shapes.DEFAULTS["paw"]
    mesh = shapes.shape_mesh("paw", p, BASE_Z, EDGE)
    kmin, kmax = edge_curvatures(mesh)
    inner = mesh.vertices[:, 2] > BASE_Z + TOL_M  # the base ring has edges on one side only
    saddle = inner & (kmin < -1 / 0.05) & (kmax > 1 / 0.05)
    assert saddle.sum() > 100
    measured = 1 / -kmin[inner].min()
    assert measured == pytest.approx(shapes.diagnose("paw", p).min_concave_radius, rel=0.1)


def test_capsule_shape_mesh_is_its_membrane_mesh_exactly():
    for r, length, edge in ((0.0115, 0.044, EDGE), (0.009, 0.02, 0.0008)):
        mine = shapes.shape_mesh("capsule", {"radius": r, "cylinder_length": length}, BASE_Z, edge)
        theirs = capsule.mesh(MembraneSpec(radius=r, cylinder_length=length, base_z=BASE_Z, mesh_edge=edge))
        assert np.array_equal(mine.vertices, theirs.vertices)
        assert np.array_equal(mine.faces, theirs.faces)


# --- Meshes ------------------------------------------------------------------------------


@pytest.mark.parametrize("family, params, edge", cases())
def test_mesh_is_an_open_manifold_sheet_with_outward_normals(family, params, edge):
    mesh = shapes.shape_mesh(family, params, BASE_Z, edge)
    V = mesh.vertices
    # No duplicate vertices, no slivers, edges near the target.
    assert len(cKDTree(V).query_pairs(edge * 1e-2)) == 0
    assert mesh.area_faces.min() > 0
    assert np.degrees(trimesh.triangles.angles(mesh.triangles).min()) > 20
    lengths = mesh.edges_unique_length
    assert edge / 2 < lengths.min() and lengths.max() < 2 * edge
    # Manifold: each edge joins two faces, or one on the base loop, the only boundary.
    _, uses = np.unique(np.sort(mesh.edges, axis=1), axis=0, return_counts=True)
    assert set(uses) == {1, 2}
    assert mesh.is_winding_consistent
    loops = mesh.outline().entities
    assert len(loops) == 1
    assert np.all(V[np.unique(loops[0].points), 2] == BASE_Z)
    assert V[:, 2].min() == BASE_Z
    # Closed by its base, it bounds a solid: normals point out.
    closed = capped(mesh)
    assert closed.is_watertight and closed.is_winding_consistent and closed.volume > 0


@pytest.mark.parametrize("family, params, edge", cases())
def test_camera_sees_the_whole_membrane(family, params, edge):
    """Star-shaped from the axis between base_z and base_z + STAR_HEIGHT_M: every face
    faces both ends (then every point between, as the test is linear in the point), and
    the ray from the camera (the origin) to each vertex meets nothing before it."""
    mesh = shapes.shape_mesh(family, params, BASE_Z, edge)
    assert BASE_Z <= 0.0 <= BASE_Z + form.STAR_HEIGHT_M
    for c in (BASE_Z, BASE_Z + form.STAR_HEIGHT_M):
        ray = mesh.triangles_center - [0.0, 0.0, c]
        cosine = np.einsum("ij,ij->i", mesh.face_normals, ray) / np.linalg.norm(ray, axis=1)
        assert cosine.min() > 0
    V = mesh.vertices
    distance = np.linalg.norm(V, axis=1)
    dirs = V / distance[:, None]
    _, ray, loc = mesh.ray.intersects_id(np.zeros_like(dirs), dirs, multiple_hits=False, return_locations=True)
    first = np.full(len(V), np.inf)
    first[ray] = np.einsum("ij,ij->i", loc, dirs[ray])
    assert np.all(first >= distance - 1e-7)


@pytest.mark.parametrize("family, params, edge", cases())
def test_every_section_through_the_axis_is_a_meridian(family, params, edge):
    mesh = shapes.shape_mesh(family, params, BASE_Z, edge)
    top = mesh.vertices[:, 2].max()
    for roll in ROLLS:
        mer = meridian(mesh, roll)
        assert np.hypot(*mer.points[0, :2]) < 1e-6  # from where the axis leaves it...
        assert mer.points[0, 2] > top - 0.003
        assert mer.points[-1, 2] == pytest.approx(BASE_Z, abs=TOL_M)  # ...to the base
        assert np.all(mer.points @ mer.up >= -TOL_M)  # on the up side of the axis
        assert np.all(np.abs(mer.points @ mer.plane_normal) < 1e-8)  # trimesh's section tolerance
        assert np.all(np.diff(mer.arc) > 0)


@pytest.mark.parametrize("family, params, edge", cases())
def test_mesh_keeps_the_core_clearance_width_and_curvature(family, params, edge):
    mesh = shapes.shape_mesh(family, params, BASE_Z, edge)
    V = mesh.vertices
    r = np.hypot(V[:, 0], V[:, 1])
    above = np.maximum(V[:, 2] - shapes.tip_start_z(family, params, BASE_Z), 0.0)
    assert np.hypot(r, above).min() >= form.MIN_CORE_CLEARANCE_M - 1e-7
    assert 2 * r.max() < form.MAX_WIDTH_M
    # Curvature along the edges, a coarse estimate: 15 % slack at the edges used here.
    kmin, kmax = edge_curvatures(mesh)
    inner = V[:, 2] > BASE_Z + TOL_M
    assert -kmin[inner].min() <= 1.15 / form.MIN_CONCAVE_RADIUS_M
    assert kmax[inner].max() <= 1.15 / form.MIN_CONVEX_RADIUS_M
