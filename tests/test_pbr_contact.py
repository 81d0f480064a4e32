"""A contact given as an indenter mesh and a pose: its depth map, the dented elastomer, bad
input, the self-intersection check, and the reference command's contact options.

None of this needs Mitsuba: the elastomer is trimesh and numpy, and the command's renderer
is replaced by a stub that keeps the depth map it was given.
"""

from __future__ import annotations

import functools

import numpy as np
import pytest
import trimesh

from pbr_tactile.contact import (
    check_indenter,
    check_pose,
    contact_depth,
    contact_elastomer,
)
from pbr_tactile.membrane import (
    check_closed,
    check_crossings,
    crossing_faces,
    elastomer,
)
from pbr_tactile.solid import Elastomer
from scenes.cli import main
from scenes.contact import press, surface_point
from scenes.shapes import family

EDGE = 0.5e-3  # m, refined edge: coarse enough for fast tests
RADIUS = 0.004  # m, sphere indenter
PIXEL = (350, 220)
DEPTH = 0.0015  # m, indentation



@pytest.fixture(scope="module")
def sphere_pose(mesh, camera):
    """The pose that puts a sphere centred on its origin where ``press`` puts it."""
    point, normal = surface_point(mesh, camera, PIXEL)
    pose = np.eye(4)
    pose[:3, 3] = point + normal * (RADIUS - DEPTH)
    return pose


def icosphere() -> trimesh.Trimesh:
    return trimesh.creation.icosphere(subdivisions=5, radius=RADIUS)


def rotation(angle: float, axis) -> np.ndarray:
    return trimesh.transformations.rotation_matrix(angle, axis)


# --- Analytic ---------------------------------------------------------------------------


def test_a_sphere_on_the_axis_reaches_the_commanded_depth(camera, ref, spec):
    pose = np.eye(4)
    pose[2, 3] = family(spec.membrane.shape).tube(spec.membrane).apex_z + RADIUS - DEPTH
    depth = contact_depth(trimesh.primitives.Sphere(radius=RADIUS), camera, ref, pose)
    # The pixels nearest the axis see the sphere's lowest point, tip_z - 1.5 mm; they are
    # half a pixel off the axis, x = 0.13 mm there, which lifts the hit by x^2 / 2r = 2 um.
    assert depth[239:241, 319:321].min() == pytest.approx(family(spec.membrane.shape).tube(spec.membrane).apex_z - DEPTH, abs=3e-6)
    assert depth.dtype == np.float32 and np.all(depth <= ref)


def test_a_posed_sphere_gives_the_depth_map_of_press(mesh, camera, ref, sphere_pose):
    pressed = press(ref, camera, mesh, trimesh.primitives.Sphere(radius=RADIUS), PIXEL, DEPTH)
    exact = contact_depth(trimesh.primitives.Sphere(radius=RADIUS), camera, ref, sphere_pose)
    assert np.allclose(exact, pressed, rtol=0, atol=1e-9)
    # A triangulated sphere, turned about its centre: within the facets' sagitta,
    # r (1 - cos 1.15 deg) = 0.8 um, which grows where the rays graze the sphere.
    turned = sphere_pose @ rotation(0.7, [1.0, 2.0, 3.0])
    meshed = contact_depth(icosphere(), camera, ref, turned)
    contact = pressed < ref
    assert np.abs(meshed - pressed)[contact].mean() < 1.5e-6
    assert np.abs(meshed - pressed).max() < 5e-6


def test_a_posed_mesh_and_mesh_with_pose_agree(camera, ref, sphere_pose):
    posed = icosphere()
    posed.apply_transform(sphere_pose)
    assert np.array_equal(contact_depth(posed, camera, ref), contact_depth(icosphere(), camera, ref, sphere_pose))


def test_the_dented_solid_is_watertight_and_the_same_as_from_the_depth_map(mesh, spec, camera, ref, sphere_pose):
    solid = contact_elastomer(mesh, spec, camera, icosphere(), sphere_pose, ref, edge=EDGE)
    closed = solid.solid()
    assert closed.is_watertight and closed.is_winding_consistent
    flat = elastomer(mesh, spec, camera, edge=EDGE).solid()
    assert 0 < flat.volume - closed.volume < 0.05 * flat.volume  # the dent takes volume away
    same = elastomer(mesh, spec, camera, contact_depth(icosphere(), camera, ref, sphere_pose), ref, edge=EDGE)
    assert np.array_equal(solid.outer.vertices, same.outer.vertices)


# --- Bad input --------------------------------------------------------------------------


def test_poses_that_are_not_rigid_are_refused():
    good = rotation(0.3, [0, 0, 1])
    good[:3, 3] = [0.001, 0.0, 0.04]
    assert check_pose(good.tolist()).dtype == np.float64  # any (4, 4) of numbers
    with pytest.raises(ValueError, match=r"pose must be a \(4, 4\) homogeneous transform, got shape \(3, 4\)"):
        check_pose(good[:3])
    with pytest.raises(ValueError, match="array of numbers"):
        check_pose("identity")
    nan = good.copy()
    nan[0, 3] = np.nan
    with pytest.raises(ValueError, match="1 NaN or infinite"):
        check_pose(nan)
    for bad in (good @ np.diag([2.0, 2.0, 2.0, 1.0]), good @ trimesh.transformations.shear_matrix(
            0.2, [1, 0, 0], [0, 0, 0], [0, 0, 1])):
        with pytest.raises(ValueError, match=r"must be rigid: R\^T R differs from I"):
            check_pose(bad)
    with pytest.raises(ValueError, match=r"det \+1, got -1"):
        check_pose(good @ np.diag([1.0, 1.0, -1.0, 1.0]))
    projective = good.copy()
    projective[3, 2] = 0.1
    with pytest.raises(ValueError, match=r"last row must be \[0, 0, 0, 1\]"):
        check_pose(projective)
    mm = good.copy()
    mm[:3, 3] *= 1000
    with pytest.raises(ValueError, match="looks like millimetres"):
        check_pose(mm)


def test_bad_indenter_meshes_are_refused(camera, ref, sphere_pose):
    holed = icosphere()
    holed.update_faces(np.arange(1, len(holed.faces)))
    with pytest.raises(ValueError, match=r"indenter: mesh is not watertight \(3 edges bound a single face\)"):
        contact_depth(holed, camera, ref, sphere_pose)
    mm = icosphere()
    mm.apply_scale(1000)
    with pytest.raises(ValueError, match="looks like millimetres"):
        check_indenter(mm)
    nan = trimesh.Trimesh(np.asarray(icosphere().vertices), icosphere().faces, process=False)
    nan.vertices[0] = np.nan
    with pytest.raises(ValueError, match="1 vertices are NaN"):
        check_indenter(nan)
    with pytest.raises(TypeError, match="must be a trimesh.Trimesh"):
        check_indenter(np.zeros((3, 3)))
    with pytest.raises(ValueError, match=r"pose must be rigid"):
        contact_depth(icosphere(), camera, ref, sphere_pose @ np.diag([1.0, 1.0, 1.001, 1.0]))


def test_an_indenter_around_the_camera_or_out_of_reach(camera, ref):
    with pytest.raises(ValueError, match="contains the camera"):
        contact_depth(icosphere(), camera, ref, np.eye(4))
    far = np.eye(4)
    far[2, 3] = 0.5
    with pytest.warns(UserWarning, match="does not reach the membrane"):
        assert np.array_equal(contact_depth(icosphere(), camera, ref, far), ref)


# --- Self-intersection ------------------------------------------------------------------


def test_crossing_triangles_are_found_and_neighbours_are_not():
    flat = [[-1.0, -1.0, 0.0], [1.0, -1.0, 0.0], [0.0, 1.0, 0.0]]
    upright = [[0.0, -0.5, -1.0], [0.0, -0.5, 1.0], [0.0, 2.0, 0.0]]
    crossing = trimesh.Trimesh(flat + upright, [[0, 1, 2], [3, 4, 5]], process=False)
    assert crossing_faces(crossing).tolist() == [0, 1]
    raised = trimesh.Trimesh(flat + [[x, y, z + 1.5] for x, y, z in upright], [[0, 1, 2], [3, 4, 5]], process=False)
    assert crossing_faces(raised).tolist() == []
    # A fan of faces meeting at shared edges and a shared corner never crosses itself.
    assert crossing_faces(trimesh.creation.icosphere(subdivisions=1)).tolist() == []
    # Only pairs with a moved face are tested, and either face of a crossing pair finds it.
    assert crossing_faces(crossing, [1]).tolist() == [0, 1] == crossing_faces(crossing, [0]).tolist()
    assert crossing_faces(crossing, []).tolist() == []


def test_the_faces_that_moved_find_every_crossing_that_all_pairs_find():
    """A sphere with a patch pushed through its far side: testing the pairs with a moved
    face finds what testing all pairs finds (the broad phase only drops pairs whose
    bounding spheres do not meet)."""
    sphere = trimesh.creation.icosphere(subdivisions=4)
    V = np.array(sphere.vertices)
    patch = V[:, 2] > 0.9
    V[patch, 2] -= 1.95  # through the sphere, out of its bottom
    pushed = trimesh.Trimesh(V, sphere.faces, process=False)
    moved = np.flatnonzero(patch[sphere.faces].any(axis=1))
    every = crossing_faces(pushed)
    assert len(every) > 0
    np.testing.assert_array_equal(crossing_faces(pushed, moved), every)


def test_a_membrane_pushed_through_the_glass_core_intersects_itself(mesh, spec, camera):
    flat = elastomer(mesh, spec, camera, edge=EDGE)
    point, _ = surface_point(flat.outer, camera, PIXEL)
    V = np.array(flat.outer.vertices)
    patch = np.linalg.norm(V - point, axis=1) < 1.5e-3
    V[patch] -= 1.5 * flat.thickness * np.asarray(flat.outer.vertex_normals)[patch]
    changed = np.flatnonzero(patch[flat.outer.faces].any(axis=1))
    check_crossings(flat, changed)  # the undeformed solid is sound there
    bad = Elastomer(trimesh.Trimesh(V, flat.outer.faces, process=False), flat.inner, flat.base, flat.thickness)
    check_closed(bad)  # the other checks pass it
    with pytest.raises(ValueError, match="intersects itself at .* faces"):
        check_crossings(bad, changed)


def test_a_torn_membrane_is_not_watertight(mesh, spec, camera):
    flat = elastomer(mesh, spec, camera, edge=EDGE)
    torn = flat.outer.copy()
    torn.update_faces(np.arange(1, len(torn.faces)))
    with pytest.raises(ValueError, match="not watertight"):
        check_closed(Elastomer(torn, flat.inner, flat.base, flat.thickness))


# --- The reference command --------------------------------------------------------------


class Rendered(Exception):
    """Raised by the stub renderer, carrying the depth map it was given."""


@pytest.fixture
def stub_render(monkeypatch):
    import tqdm

    import pbr_tactile.render

    def reference(depth, ref_depth, *args, **kwargs):
        raise Rendered(depth, ref_depth)

    monkeypatch.setattr(pbr_tactile.render, "reference", reference)
    monkeypatch.setattr(tqdm, "tqdm", functools.partial(tqdm.tqdm, disable=True))  # the stub never closes it


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        ([], "one of the arguments DEPTH.npy --indenter is required"),
        (["d.npy", "--indenter", "sphere"], "not allowed with argument DEPTH.npy"),
        (["--indenter", "sphere"], "--indenter needs a pose"),
        (["--indenter", "sphere", "--at", "1,2", "--pose", "p.npy", "--depth-mm", "1"], "not allowed with"),
        (["--indenter", "sphere", "--at", "1,2"], "--at needs --depth-mm"),
        (["--indenter", "sphere", "--at", "350"], "expected U,V in pixels"),
        (["--indenter", "sphere", "--pose", "p.npy", "--depth-mm", "1"], "--depth-mm: only with --at"),
        (["d.npy", "--pose", "p.npy"], "--pose: only with --indenter"),
        (["d.npy", "--spin-deg", "10"], "--spin-deg: only with --indenter"),
        (["d.npy", "--no-contact-runs", "-1"], "expected a whole number >= 0, got '-1'"),
        (["d.npy", "--no-contact-runs", "many"], "expected a whole number >= 0, got 'many'"),
    ],
)
def test_reference_needs_exactly_one_contact(argv, message, capsys):
    with pytest.raises(SystemExit) as exit_info:
        main(["reference", *argv, "--out", "x"])
    assert exit_info.value.code == 2
    assert message in capsys.readouterr().err


def test_reference_presses_an_indenter_mesh_file(tmp_path, stub_render, mesh, camera, ref):
    path = tmp_path / "ball_mm.stl"
    ball = icosphere()
    ball.apply_scale(1000)
    ball.export(path)
    with pytest.raises(Rendered) as rendered:
        main(["reference", "--indenter", str(path), "--at", "350,220", "--depth-mm", "1.5", "--out", "x"])
    depth, _ = rendered.value.args
    assert np.allclose(depth, press(ref, camera, mesh, icosphere(), PIXEL, DEPTH), rtol=0, atol=1e-6)


def test_reference_presses_a_paper_indenter_by_name(stub_render, mesh, camera, ref):
    pytest.importorskip("manifold3d", reason="building indenters needs the manifold boolean engine")
    from scenes.indenters import make_indenter

    with pytest.raises(Rendered) as rendered:
        main(["reference", "--indenter", "cone", "--at", "350,220", "--depth-mm", "1", "--spin-deg", "30",
              "--out", "x"])
    depth, _ = rendered.value.args
    assert np.array_equal(depth, press(ref, camera, mesh, make_indenter("cone"), PIXEL, 1e-3, np.radians(30.0)))


def test_reference_takes_a_pose_file(tmp_path, stub_render, camera, ref, sphere_pose, capsys):
    path = tmp_path / "ball.stl"
    icosphere().export(path)
    np.save(tmp_path / "pose.npy", sphere_pose)
    with pytest.raises(Rendered) as rendered:
        main(["reference", "--indenter", str(path), "--indenter-units", "m", "--pose", str(tmp_path / "pose.npy"),
              "--out", "x"])
    depth, _ = rendered.value.args
    assert np.allclose(depth, contact_depth(icosphere(), camera, ref, sphere_pose), rtol=0, atol=1e-6)
    np.save(tmp_path / "scaled.npy", sphere_pose @ np.diag([2.0, 2.0, 2.0, 1.0]))
    assert main(["reference", "--indenter", str(path), "--pose", str(tmp_path / "scaled.npy"), "--out", "x"]) == 1
    assert "must be rigid" in capsys.readouterr().err
