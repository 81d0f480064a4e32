"""The sensors shipped under scenes/sensors/: each loads, its body passes its checks, and
the protocols tap it along its own normals where the rig can reach."""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import numpy as np
import pytest
import trimesh

from scenes.body import sensor_body
from scenes.camera import Camera, project
from scenes.geometry import membrane_mesh
from scenes.kinematics import in_travel, normal_in_sensor, servo_angles
from scenes.protocol import (AIM_SLACK_RAD, BASE_CONTACTS_PER_ROW, BASE_ROLLS_RAD, EXTENDED_CONTACTS_PER_ROW, EXTENDED_ROLLS_RAD,
                             base_protocol, extended_protocol)
from scenes.protocol_checks import validate
from scenes.proximity import closest_faces
from scenes.spec_read import default_spec, load_spec
from scenes.taps import Protocol

SENSORS = Path(__file__).resolve().parents[1] / "scenes" / "sensors"
NEW = ("thumb", "paw")


@pytest.fixture(scope="module", params=NEW)
def sensor(request):
    spec = load_spec(SENSORS / f"{request.param}.toml")
    return spec, membrane_mesh(spec)


def test_every_shipped_sensor_loads_and_its_body_passes():
    for path in sorted(SENSORS.glob("*.toml")):
        spec = load_spec(path)
        body = sensor_body(spec)
        # a pad's gel reaches past the view to its LEDs (it must cover the frame instead)
        assert body.seen_share > (0.1 if spec.membrane.shape == "pad" else 0.5), path.name
        assert spec.membrane.thickness_bounds[0] <= body.min_thickness, path.name


def test_the_new_sensors_are_not_capsules(sensor):
    spec, mesh = sensor
    assert spec.membrane.shape in NEW
    body = sensor_body(spec, mesh)
    # The derived core: 2.5 mm under the membrane, less by chord sag alone.
    assert np.abs(body.thickness - spec.membrane.thickness).max() < 1e-5
    r = np.hypot(*np.asarray(mesh.vertices)[:, :2].T)
    if spec.membrane.shape == "thumb":
        x, y = np.ptp(mesh.vertices[:, 0]), np.ptp(mesh.vertices[:, 1])
        assert x / y > 1.15  # flattened
    else:
        assert r[mesh.vertices[:, 2] < 0.02].min() < spec.membrane.params[4][1] - 5e-4  # the waist


def _tilt(mesh, point, normal) -> np.ndarray:
    """Angles (N,) rad between taps' normals and the membrane's smooth normal there."""
    face, _ = closest_faces(mesh, point)
    bary = np.clip(trimesh.triangles.points_to_barycentric(mesh.triangles[face], point), 0, 1)
    smooth = (mesh.vertex_normals[mesh.faces[face]] * (bary / bary.sum(axis=1, keepdims=True))[..., None]).sum(axis=1)
    smooth /= np.linalg.norm(smooth, axis=1, keepdims=True)
    return np.arccos(np.clip(np.einsum("ij,ij->i", normal, smooth), -1, 1))


def test_servo_angles_invert_the_rigs_normal(rng):
    roll = rng.uniform(-0.2, math.pi + 0.2, 200)
    pitch = rng.uniform(-0.35, math.pi / 2 + 0.35, 200)
    n = normal_in_sensor(roll, pitch)
    r, p = servo_angles(n)
    np.testing.assert_allclose(normal_in_sensor(r, p), n, atol=1e-12)
    assert in_travel(r, p).all()
    # A normal facing +x needs the roll half a turn past its travel and cannot be reached.
    r, p = servo_angles([[1.0, 0.0, 0.0]])
    assert not in_travel(r, p).any()
    with pytest.raises(ValueError, match=r"normal must be finite \(N, 3\)"):
        servo_angles([[np.nan, 0.0, 1.0]])


def test_the_base_protocol_taps_any_shape_along_its_normals_in_view(sensor):
    spec, mesh = sensor
    protocol = base_protocol(spec, mesh, ("sphere", "cylinder"))
    assert len(protocol.taps) == 2 * len(BASE_ROLLS_RAD) * BASE_CONTACTS_PER_ROW
    point = np.array([t.point for t in protocol.taps])
    normal = np.array([t.normal for t in protocol.taps])
    tilt = _tilt(mesh, point, normal)
    # Along the membrane's own normal, but where the servo horns cannot turn that far
    # (the paw's waist faces a little towards the base): then at most AIM_SLACK_RAD off.
    assert np.median(tilt) < 1e-6 and tilt.max() <= AIM_SLACK_RAD + 1e-9
    roll = np.array([t.sensor_roll for t in protocol.taps])
    pitch = np.array([t.indenter_pitch for t in protocol.taps])
    assert in_travel(roll, pitch).all()
    camera = Camera.from_spec(spec)
    u, v = np.round(project(point, camera)).astype(int).T
    assert camera.mask[v, u].all()  # every contact in view
    # Each row runs from the apex down the membrane.
    z = point[: BASE_CONTACTS_PER_ROW, 2]
    assert np.all(np.diff(z) < 0)


def test_the_extended_protocol_on_any_shape(sensor):
    spec, mesh = sensor
    protocol = extended_protocol(spec, mesh, ("sphere",), seed=1, replicas=3)
    assert len(protocol.taps) == len(EXTENDED_ROLLS_RAD) * EXTENDED_CONTACTS_PER_ROW * 3
    nominal = [t for t in protocol.taps if t.replica == 0]
    tilt = _tilt(mesh, np.array([t.point for t in nominal]), np.array([t.normal for t in nominal]))
    assert np.median(tilt) < 1e-6 and tilt.max() <= AIM_SLACK_RAD + 1e-9


def test_a_tap_the_rig_cannot_reach_is_refused():
    spec = default_spec()
    mesh = membrane_mesh(spec)
    good = base_protocol(spec, mesh, ("sphere",)).taps[4]  # on the cylinder
    # The same height on the +x side, where the normal faces +x: the roll servo would have
    # to turn half a turn past its travel.
    point = (float(np.hypot(good.point[0], good.point[1])), 0.0, good.point[2])
    roll, pitch = servo_angles([[1.0, 0.0, 0.0]])
    tap = dataclasses.replace(good, index=0, point=point, normal=(1.0, 0.0, 0.0), sensor_roll=float(roll[0]),
                              indenter_pitch=float(pitch[0]))
    with pytest.raises(ValueError, match="the rig cannot reach it"):
        validate(Protocol(name="custom", taps=(tap,), seed=None), spec, mesh)


@pytest.mark.slow
def test_a_capsule_described_as_a_mesh_renders_as_the_parametric_one(tmp_path):
    """The issue's goal: the fast path's images of a capsule read from a mesh file (in
    millimetres, placed by a transform, triangulated apart: 0.7 mm edges against 0.5 mm)
    agree with the parametric capsule's to MAE <= 0.5 % in the image circle, every field,
    with and without a contact."""
    import tomllib

    from phong_reference.background import make_background
    from phong_reference.bake import bake
    from phong_reference.render import light_vectors, render
    from scenes.camera import reference_depth
    from scenes.contact import press
    from scenes.shapes.capsule import mesh as capsule_mesh
    from scenes.spec import DEFAULT_SPEC_PATH
    from scenes.spec_read import spec_from_dict

    width = 160
    data = tomllib.loads(DEFAULT_SPEC_PATH.read_text())
    data["camera"].update(width=width, height=width * 3 // 4, mask_radius_px=width * 3 / 8,
                          mask_center_px=[width / 2, width * 3 / 8])
    parametric = spec_from_dict(data, "parametric")
    other = capsule_mesh(dataclasses.replace(parametric.membrane, mesh_edge=0.0007))
    other.apply_translation([0.0, 0.0, 0.05])  # the file's own frame
    other.apply_scale(1e3)
    other.export(tmp_path / "capsule_mm.stl")
    place = np.eye(4)
    place[2, 3] = -0.05
    data["membrane"] = {"shape": "mesh", "mesh_path": str(tmp_path / "capsule_mm.stl"), "mesh_units": "mm",
                        "mesh_transform": place.tolist(), "thickness": 0.0025}
    as_mesh = spec_from_dict(data, "as_mesh")
    camera = Camera.from_spec(parametric)
    ball = trimesh.creation.icosphere(subdivisions=3, radius=0.004)
    background = make_background("solid", camera)
    meshes = [membrane_mesh(parametric), membrane_mesh(as_mesh)]
    assert len(meshes[1].vertices) < 0.6 * len(meshes[0].vertices)
    for method in ("linear", "plane", "geodesic", "transport"):
        images = []
        for spec, mesh in zip((parametric, as_mesh), meshes):
            L = light_vectors(bake(mesh, camera, spec.leds, method, use_cache=False))
            ref = reference_depth(mesh, camera)[0]
            dent = press(ref, camera, mesh, ball, (0.6 * width, 0.3 * width), 0.0015)
            images.append([render(d, ref, camera, spec, L, background) for d in (ref, dent)])
        for k in range(2):
            mae = float(np.abs(images[0][k] - images[1][k])[camera.mask].mean())
            assert mae <= 0.005, (method, k, mae)


def test_every_shipped_sensor_is_written_out_and_read_back_the_same():
    """Datasets record their sensor as SensorSpec.to_dict in JSON; a non-capsule's table
    leaves out the capsule's keys, which its spec refuses."""
    import json

    from scenes.spec_read import spec_from_dict

    for path in sorted(SENSORS.glob("*.toml")):
        spec = load_spec(path)
        data = json.loads(json.dumps(spec.to_dict()))
        assert spec_from_dict(data, path.name) == spec
        if spec.membrane.shape != "capsule":
            assert "radius" not in data["membrane"] and data["membrane"]["params"]
