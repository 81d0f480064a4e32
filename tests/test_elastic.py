"""The membrane's elastic models: the layer model against analytic answers, on the GelTip,
and the fast path seeing the same surface as the reference."""

from __future__ import annotations

import math

import numpy as np
import pytest
import trimesh
from scipy import special

from scenes.camera import reference_depth
from scenes.contact import press, surface_point
from scenes.elastic import (
    MIN_GAP_M,
    MODELS,
    MembraneLayer,
    layer_length,
    penetration,
    solve_layer,
)
from scenes.shapes import family
from scenes.spec import Elastic

#: The plate's distance from the camera, metres, and its half-width.
PLATE_Z_M = 0.02
PLATE_HALF_M = 0.006
#: Grid step of the plate, metres (a sixth of the layer's decay length).
PLATE_STEP_M = 0.125e-3


@pytest.fixture(scope="module")
def plate():
    """A flat membrane facing the camera at z = PLATE_Z_M, outward normal +z (away from it)."""
    n = round(2 * PLATE_HALF_M / PLATE_STEP_M) + 1
    x = np.linspace(-PLATE_HALF_M, PLATE_HALF_M, n)
    X, Y = np.meshgrid(x, x)
    V = np.column_stack([X.ravel(), Y.ravel(), np.full(X.size, PLATE_Z_M)])
    idx = np.arange(n * n).reshape(n, n)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel()
    F = np.vstack([np.c_[a, b, c], np.c_[b, d, c]])
    mesh = trimesh.Trimesh(V, F, process=False)
    if mesh.face_normals[:, 2].mean() < 0:
        mesh.invert()
    return mesh


def test_models_are_named():
    assert MODELS == ("published", "layer", "bonded")


def test_the_decay_length_is_vlasovs(spec):
    h = spec.membrane.radius - spec.membrane.core_radius
    assert layer_length(spec) == pytest.approx(h / math.sqrt(12.0))  # nu = 0.5
    soft = spec.replace(elastic=Elastic(poisson_ratio=0.2))
    assert layer_length(soft) == pytest.approx(h * math.sqrt(0.8 / 6.0))
    # Under each point of a membrane whose thickness varies (scenes.body).
    np.testing.assert_allclose(layer_length(spec, np.array([h, h / 2])), [h, h / 2] / np.sqrt(12.0))


def _sphere_on_plate(d: float, R: float, l: float) -> tuple[float, float]:
    """The axisymmetric Pasternak layer under a rigid sphere of radius R pressed d:
    w = delta(r) = d - (R - sqrt(R^2 - r^2)) on the contact disc r < c, A K0(r / l) beyond,
    with w and w' continuous at c. Returns (c, A)."""
    from scipy import optimize

    def delta(r):
        return d - (R - np.sqrt(R**2 - r**2))

    def mismatch(c):  # w'/w from inside minus from outside, at r = c
        return -c / np.sqrt(R**2 - c**2) / delta(c) + special.k1(c / l) / (l * special.k0(c / l))

    reach = np.sqrt(R**2 - (R - d) ** 2)  # where the rigid sphere leaves the plate
    c = optimize.brentq(mismatch, 1e-6, reach * (1 - 1e-9))
    return c, delta(c) / special.k0(c / l)


def test_a_sphere_on_a_plate_matches_the_analytic_layer(plate, spec, camera):
    """Smooth contact: the contact radius and the displacement everywhere agree with the
    semi-analytic axisymmetric solution."""
    from scenes.contact import sphere_depth

    layer = MembraneLayer(plate, spec, camera, edge=None)
    ref = np.full(camera.shape, PLATE_Z_M)
    R, d = 0.004, 1.0e-3
    depth = np.minimum(ref, sphere_depth(np.array([0.0, 0.0, PLATE_Z_M - d + R]), R, camera))
    result = layer.deformation(depth, ref)
    length = float(layer.length[0])  # a uniform layer
    assert np.all(layer.length == length)
    c, A = _sphere_on_plate(d, R, length)
    r = np.hypot(*plate.vertices[:, :2].T)
    exact = np.where(r < c, d - (R - np.sqrt(R**2 - np.minimum(r, R) ** 2)), A * special.k0(np.maximum(r, 1e-9) / length))
    near = r < 5 * length + c
    assert np.abs(result.displacement[near] - exact[near]).max() < 0.02 * d
    # Displacement is along the (here +z) normal only, inwards; the membrane touches the
    # sphere on the contact disc and lies off it beyond.
    moved = result.vertices - plate.vertices
    assert np.allclose(moved[:, :2], 0.0) and (moved[:, 2] <= 1e-15).all()
    touching = np.abs(result.displacement - result.penetration) < 1e-9
    assert np.abs(r[touching & (result.penetration > 0)].max() - c) < 2 * PLATE_STEP_M


def test_a_flat_punch_on_a_plate_decays_as_the_bessel_solution(plate, spec, camera):
    """Sharp contact: w = d under a flat punch of radius a and d K0(r / l) / K0(a / l)
    beyond. The decay is the analytic one; the amplitude is low by the O(h) snapping of
    the punch's sharp edge to the mesh and the pixels (14 % at h = 0.125 mm here)."""
    layer = MembraneLayer(plate, spec, camera, edge=None)
    ref = np.full(camera.shape, PLATE_Z_M)
    a, d = 1.5e-3, 1.0e-3
    # The punch's face, at z = PLATE_Z_M - d, in the pixels whose rays meet it.
    P = (PLATE_Z_M - d) * camera.rays
    depth = np.where(np.hypot(P[..., 0], P[..., 1]) <= a, PLATE_Z_M - d, ref)
    result = layer.deformation(depth, ref)
    r = np.hypot(*plate.vertices[:, :2].T)
    l = float(layer.length[0])
    assert np.allclose(result.displacement[r < a - 2 * PLATE_STEP_M], d, atol=1e-9)

    def mean_at(radius):
        return result.displacement[np.abs(r - radius) < PLATE_STEP_M / 2].mean()

    for r1, r2 in ((a + l, a + 2 * l), (a + 2 * l, a + 4 * l)):
        exact = special.k0(r1 / l) / special.k0(r2 / l)
        assert mean_at(r1) / mean_at(r2) == pytest.approx(exact, rel=0.03)
    assert mean_at(a + l) == pytest.approx(d * special.k0((a + l) / l) / special.k0(a / l), rel=0.2)


def test_the_layer_solver_meets_its_optimality_conditions(rng):
    """min 1/2 w^T K w, w >= obstacle: w >= obstacle, K w >= 0, and K w = 0 where w > obstacle."""
    n = 60
    K = (np.diag(np.full(n, 2.2)) - np.diag(np.ones(n - 1), 1) - np.diag(np.ones(n - 1), -1))
    obstacle = np.full(n, -np.inf)
    obstacle[20:30] = rng.uniform(0.5, 1.0, 10)
    obstacle[24] = 0.1  # a dip the membrane bridges
    w = solve_layer(K, obstacle)
    Kw = K @ w
    assert (w >= obstacle - 1e-12).all()
    assert (Kw >= -1e-9).all()
    free = w > obstacle + 1e-9
    assert np.abs(Kw[free]).max() < 1e-9
    assert w[24] > obstacle[24] + 0.1  # bridged, not pulled into the dip


def test_penetration_of_a_sphere_on_the_tip_matches_the_geometry(spec, mesh, camera):
    """A sphere pressed on the apex reaches, along each inward normal of the tip, exactly
    as far as the two spheres' geometry says."""
    ref = reference_depth(mesh, camera)[0]
    r, d = 0.004, 0.0015
    apex = (camera.mask_cx or camera.cx, camera.mask_cy or camera.cy)
    depth = press(ref, camera, mesh, trimesh.primitives.Sphere(radius=r), apex, d)
    R = spec.membrane.radius
    tip = np.array([0.0, 0.0, family(spec.membrane.shape).tube(spec.membrane).apex_z - R])  # centre of the hemispherical tip
    point, normal = surface_point(mesh, camera, apex)
    S = point - normal * (d - r)  # the indenter's centre
    layer = MembraneLayer(mesh, spec, camera)
    V = layer.vertices
    u = (V - tip) / np.linalg.norm(V - tip, axis=1, keepdims=True)
    on_tip = np.abs(np.linalg.norm(V - tip, axis=1) - R) < 1e-5
    got = penetration(V, layer.normals, depth, ref, camera)
    # Exact: the larger s with |tip + (R - s) u - S| = r.
    q = tip + R * u - S
    b = np.einsum("ij,ij->i", q, u)
    disc = b**2 - (np.einsum("ij,ij->i", q, q) - r**2)
    exact = np.where(disc > 0, b + np.sqrt(np.maximum(disc, 0)), 0.0)
    # Where the exit point is seen two pixels or more inside the contact (at its rim the
    # sphere meets the membrane at ~50 deg, so a pixel spans 0.2 mm of penetration).
    from scipy import ndimage

    from scenes.camera import project

    core = ndimage.binary_erosion(depth < ref - 1e-6, iterations=2)
    uv = np.round(project(V - exact[:, None] * u, camera)).astype(int)
    seen = np.zeros(len(V), bool)
    ok = (uv[:, 0] >= 0) & (uv[:, 0] < camera.width) & (uv[:, 1] >= 0) & (uv[:, 1] < camera.height)
    seen[ok] = core[uv[ok, 1], uv[ok, 0]]
    inside = on_tip & (exact > 0) & seen
    assert inside.sum() > 500
    assert np.abs(got[inside] - exact[inside]).max() < 0.02e-3
    assert got[on_tip & (exact == 0)].max() < 0.05e-3


def test_a_deep_contact_is_capped_above_the_glass_and_a_deeper_one_refused(spec, mesh, camera):
    ref = reference_depth(mesh, camera)[0]
    thickness = spec.membrane.radius - spec.membrane.core_radius
    layer = MembraneLayer(mesh, spec, camera)
    full = press(ref, camera, mesh, trimesh.primitives.Sphere(radius=0.004), (400, 200), thickness)
    result = layer.deformation(full, ref)
    assert result.penetration.max() > thickness - 0.05e-3
    # Solved once: the same maps give the kept answer, which nobody can change in place.
    assert layer.deformation(full.copy(), ref) is result
    assert not result.vertices.flags.writeable and not result.displacement.flags.writeable
    assert result.displacement.max() == pytest.approx(thickness - MIN_GAP_M)
    with pytest.raises(ValueError, match="through the glass core"):
        layer.deformation(press(ref, camera, mesh, trimesh.primitives.Sphere(radius=0.004), (400, 200), 0.0045),
                          ref)
    with pytest.raises(ValueError, match=r"depth must be \(480, 640\) float"):
        layer.deformation(ref[:10], ref)
    nan = ref.copy()
    nan[5, 5] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        layer.deformation(nan, ref)


def test_the_fast_path_renders_the_layer_surface_in_its_window(spec, mesh, camera):
    """Renderer (window) and render (whole frame) agree with the layer model too, and a
    contact changes the image only where the deformed surface's depth changed."""
    from phong_reference.render import Renderer, render

    ref = reference_depth(mesh, camera)[0]
    layer = MembraneLayer(mesh, spec, camera)
    depth = press(ref, camera, mesh, trimesh.primitives.Sphere(radius=0.004), (400, 200), 0.002)
    rng = np.random.default_rng(0)
    L = rng.normal(size=(len(spec.leds), 3) + camera.shape)
    L = (L / np.linalg.norm(L, axis=1, keepdims=True)).astype(np.float32)
    background = np.full(camera.shape + (3,), 0.1, np.float32)
    fast = Renderer(spec, camera, ref, L, background, layer=layer)
    full = render(depth, ref, camera, spec, L, background, layer=layer)
    window = fast.render(depth)
    assert np.abs(window - full).max() < 1e-5
    changed = np.abs(window - fast.base).max(axis=2) > 0
    d_def = layer.depth(depth, ref)
    moved = ndimage_grow(np.abs(d_def - ref) > 0, 2)
    assert changed.any() and not (changed & ~moved).any()


def ndimage_grow(mask: np.ndarray, pixels: int) -> np.ndarray:
    from scipy import ndimage

    return ndimage.binary_dilation(mask, iterations=pixels)


def test_the_poisson_ratio_is_validated():
    import tomllib

    from scenes.spec import DEFAULT_SPEC_PATH
    from scenes.spec_read import spec_from_dict

    data = tomllib.loads(DEFAULT_SPEC_PATH.read_text())
    assert spec_from_dict(data, "test").elastic.poisson_ratio == 0.5
    data["elastic"]["poisson_ratio"] = 0.7
    with pytest.raises(ValueError, match=r"poisson_ratio must be in \[0, 0.5\], got 0.7"):
        spec_from_dict(data, "test")
