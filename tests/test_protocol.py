"""Tapping protocols: rig conventions, contacts on the membrane mesh, the base and extended
sets, JSON round trips and validation."""

from __future__ import annotations

import collections
import dataclasses
import json
import math

import numpy as np
import pytest

from scenes import kinematics as K
from scenes import meridian as M
from scenes import protocol as P
from scenes import protocol_checks as C
from scenes import taps as T
from scenes.shapes import family
from scenes.shapes.revolve import revolve

#: The eight indenters of the paper (scenes.indenters.INDENTERS), spelt out so this test
#: does not depend on that module.
OBJECTS = ("dots", "sphere", "indented_prism", "cylinder", "open_cylinder", "cone", "pacman", "random")
#: Rotations and conventions are exact up to float rounding.
EXACT = 1e-12
#: Tip points away from the junction. Derived: the mesh's chords sag h^2 / (8 R) = 3 um
#: (h = 0.5 mm edges, R = 11.5 mm) and its interpolated normals are off by ~0.05 deg, of
#: order (h / R)^2 rad, which is 10 um along the arc: 13 um in all (seen: <= 12 um). 25 um
#: is twice that, and a twentieth of an edge, which a point snapped to the wrong vertex or
#: ring would be off by.
TIP_POINT_TOLERANCE_M = 2.5e-5
#: The junction (and the cylinder points measured from it): interpolated vertex normals
#: blur the tip/cylinder kink over one mesh ring (0.43 mm), and a point's position along
#: the arc follows its normal there (seen: <= 50 um). Why 0.1 mm: a quarter of that ring,
#: so a point placed a whole ring off (the failure) is four times past it.
JUNCTION_POINT_TOLERANCE_M = 1e-4
#: Smooth normals against the analytic ones.
NORMAL_TOLERANCE_RAD = math.radians(0.5)
#: An extended contact is re-projected along its (tilted) approach from the tangent plane,
#: which can move it slightly more than the shift itself.
REPROJECTION_SLACK_M = 5e-5


def capsule(spec):
    """Analytic GelTip: radius, z of the tip junction, hemisphere centre."""
    m = spec.membrane
    z_top = m.base_z + m.cylinder_length
    return m.radius, z_top, np.array([0.0, 0.0, z_top])


def capsule_distance(spec, points):
    """Distance (N,) metres from points (N, 3) to the analytic capsule surface."""
    R, z_top, c = capsule(spec)
    r = np.hypot(points[:, 0], points[:, 1])
    return np.where(points[:, 2] > z_top, np.abs(np.linalg.norm(points - c, axis=1) - R), np.abs(r - R))


def capsule_normal(spec, points):
    R, z_top, c = capsule(spec)
    radial = points * [1.0, 1.0, 0.0]
    n = np.where((points[:, 2] > z_top)[:, None], points - c, radial)
    return n / np.linalg.norm(n, axis=1, keepdims=True)


def angle_between(a, b):
    a = a / np.linalg.norm(a, axis=-1, keepdims=True)
    b = b / np.linalg.norm(b, axis=-1, keepdims=True)
    return 2.0 * np.arcsin(np.clip(0.5 * np.linalg.norm(a - b, axis=-1), 0.0, 1.0))


@pytest.fixture(scope="module")
def base(spec, mesh):
    return P.base_protocol(spec, mesh, OBJECTS)


@pytest.fixture(scope="module")
def extended(spec, mesh):
    return P.extended_protocol(spec, mesh, OBJECTS, seed=0)


# --- Conventions --------------------------------------------------------------------


def test_sensor_to_world_is_a_right_handed_rotation_with_the_documented_columns():
    M = K.SENSOR_TO_WORLD_AT_ROLL0
    assert np.allclose(M.T @ M, np.eye(3), atol=EXACT)
    assert np.linalg.det(M) == pytest.approx(1.0, abs=EXACT)
    x_s, y_s, z_s = M.T
    assert np.allclose(x_s, [0, -1, 0]) and np.allclose(y_s, [0, 0, -1]) and np.allclose(z_s, [1, 0, 0])
    rolls = np.linspace(-np.pi, 2 * np.pi, 13)
    R = K.sensor_to_world(rolls)
    assert R.shape == (13, 3, 3)
    assert np.allclose(np.linalg.det(R), 1.0, atol=EXACT)
    assert np.allclose(np.einsum("nij,nkj->nik", R, R), np.eye(3), atol=EXACT)
    # Rolling turns the sensor about its own axis, which stays along world +X.
    assert np.allclose(R @ [0.0, 0.0, 1.0], [1.0, 0.0, 0.0], atol=EXACT)
    assert np.allclose(K.sensor_to_world(0.7), M @ K._rz(np.float64(0.7)), atol=EXACT)


def test_up_in_sensor_faces_world_up_at_every_roll():
    rolls = np.linspace(0.0, 2 * np.pi, 17)
    up = K.up_in_sensor(rolls)
    assert np.allclose(up, np.stack([-np.sin(rolls), -np.cos(rolls), np.zeros_like(rolls)], 1), atol=EXACT)
    assert np.allclose(np.einsum("nij,nj->ni", K.sensor_to_world(rolls), up), [0.0, 0.0, 1.0], atol=EXACT)
    assert np.allclose(K.up_in_sensor(0.0), [0.0, -1.0, 0.0], atol=EXACT)  # -y_s is up at roll 0
    assert np.allclose(K.up_in_sensor(np.pi / 2), [-1.0, 0.0, 0.0], atol=EXACT)


def test_indenter_axis_and_pitch_for_normal():
    assert np.allclose(K.indenter_axis(0.0), [0.0, 0.0, -1.0], atol=EXACT)  # hangs down
    assert np.allclose(K.indenter_axis(np.pi / 2), [-1.0, 0.0, 0.0], atol=EXACT)  # at the apex
    # The apex faces +X: pitch pi/2; the top of the cylinder faces +Z: pitch 0.
    assert K.pitch_for_normal([1.0, 0.0, 0.0]) == pytest.approx(np.pi / 2, abs=EXACT)
    assert K.pitch_for_normal([0.0, 0.0, 1.0]) == pytest.approx(0.0, abs=EXACT)
    a = np.linspace(0.0, np.pi / 2, 7)
    n = np.stack([np.cos(a), np.zeros_like(a), np.sin(a)], 1)
    pitch = K.pitch_for_normal(n)
    assert np.allclose(pitch, np.pi / 2 - a, atol=EXACT)
    assert np.allclose(K.indenter_axis(pitch), -n, atol=EXACT)


def test_pitch_for_normal_refuses_normals_the_servo_cannot_face():
    with pytest.raises(ValueError, match="XZ plane"):
        K.pitch_for_normal([0.0, 1.0, 1.0])
    with pytest.raises(ValueError, match="non-zero"):
        K.pitch_for_normal([0.0, 0.0, 0.0])
    with pytest.raises(ValueError, match=r"\(3,\)"):
        K.pitch_for_normal([1.0, 0.0])


def test_normal_in_sensor_is_realised_by_roll_and_pitch():
    rng = np.random.default_rng(7)
    roll, pitch = rng.uniform(0, np.pi, 50), rng.uniform(-0.2, np.pi / 2 + 0.2, 50)
    n = K.normal_in_sensor(roll, pitch)
    up = K.up_in_sensor(roll)
    assert np.allclose(n, np.cos(pitch)[:, None] * up + np.sin(pitch)[:, None] * [0, 0, 1], atol=EXACT)
    world = np.einsum("nij,nj->ni", K.sensor_to_world(roll), n)
    assert np.allclose(world, -K.indenter_axis(pitch), atol=EXACT)


# --- Meridians --------------------------------------------------------------------------


@pytest.mark.parametrize("roll", [0.0, 0.3, np.pi / 4, np.pi / 2, 2.0, np.pi])
def test_meridian_matches_the_analytic_capsule(spec, mesh, roll):
    R, z_top, c = capsule(spec)
    mer = M.meridian(mesh, roll)
    up = K.up_in_sensor(roll)
    # In the plane, on the up side, from the apex to the open base.
    assert np.abs(mer.points @ mer.plane_normal).max() < EXACT
    assert (mer.points @ up).min() >= -EXACT
    assert np.allclose(mer.points[0], [0.0, 0.0, family(spec.membrane.shape).tube(spec.membrane).apex_z], atol=EXACT)
    assert mer.points[-1, 2] == pytest.approx(spec.membrane.base_z, abs=EXACT)
    assert mer.length == pytest.approx(np.pi / 2 * R + spec.membrane.cylinder_length, abs=1e-4)
    assert np.all(np.diff(mer.arc) > 0)

    a = np.radians([0.0, 10.0, 30.0, 45.0, 60.0, 75.0])
    p, n = M.point_at_angle(mer, a)
    exact = c + R * (np.sin(a)[:, None] * up + np.cos(a)[:, None] * [0, 0, 1])
    assert np.linalg.norm(p - exact, axis=1).max() < TIP_POINT_TOLERANCE_M
    assert np.allclose(n, (exact - c) / R, atol=EXACT)

    p, n = M.point_at_angle(mer, np.pi / 2)
    assert np.linalg.norm(p[0] - (c + R * up)) < JUNCTION_POINT_TOLERANCE_M
    assert np.allclose(n[0], up, atol=EXACT)
    assert M.junction_arc(mer) == pytest.approx(np.pi / 2 * R, abs=JUNCTION_POINT_TOLERANCE_M)

    back = np.array([0.009, 0.018, 0.03])
    p, n = M.point_behind_junction(mer, back)
    exact = R * up + (z_top - back)[:, None] * [0, 0, 1]
    assert np.linalg.norm(p - exact, axis=1).max() < JUNCTION_POINT_TOLERANCE_M
    assert angle_between(n, np.broadcast_to(up, n.shape)).max() < NORMAL_TOLERANCE_RAD


def test_meridian_of_another_shape_an_ellipsoidal_tip():
    """Any membrane shape: a cylinder closed by a half-ellipse with semi-axes A (radial)
    and B (axial). At the ellipse point (A sin t, z0 + B cos t) the normal makes
    atan((B / A) tan t) with the axis."""
    A, B, z0, base = 0.01, 0.016, 0.02, -0.01
    t = np.linspace(np.pi / 2, 0.0, 200)
    profile = np.vstack([[A, base], np.stack([A * np.sin(t), z0 + B * np.cos(t)], 1)])
    mesh = revolve(profile, 0.0005)
    roll = 1.1
    mer = M.meridian(mesh, roll)
    up = K.up_in_sensor(roll)
    alpha = np.radians([0.0, 20.0, 45.0, 70.0])
    tt = np.arctan(A / B * np.tan(alpha))
    exact = A * np.sin(tt)[:, None] * up + (z0 + B * np.cos(tt))[:, None] * [0, 0, 1]
    p, _ = M.point_at_angle(mer, alpha)
    assert np.linalg.norm(p - exact, axis=1).max() < 2 * TIP_POINT_TOLERANCE_M
    # The junction may move towards the apex by the meridian's radius of curvature
    # there, B^2 / A, times the junction's angle tolerance (0.22 mm here).
    p, _ = M.point_behind_junction(mer, 0.01)
    junction_tolerance = B**2 / A * M.JUNCTION_ANGLE_TOLERANCE_RAD
    assert np.linalg.norm(p[0] - (A * up + [0, 0, z0 - 0.01])) < junction_tolerance


def test_meridian_refuses_bad_input(mesh):
    import trimesh

    with pytest.raises(ValueError, match="roll must be finite"):
        M.meridian(mesh, float("nan"))
    box = trimesh.creation.box((0.01, 0.01, 0.01))
    box.apply_translation([0.0, 0.05, 0.0])
    with pytest.raises(ValueError, match="misses the membrane"):
        M.meridian(box, np.pi / 2)  # the plane y = 0
    box.apply_translation([0.05, -0.05, 0.0])
    with pytest.raises(ValueError, match="never crosses the sensor axis"):
        M.meridian(box, np.pi / 2)
    mer = M.meridian(mesh, 0.0)
    with pytest.raises(ValueError, match=r"angle must be in \[0, pi/2\]"):
        M.arc_at_angle(mer, 2.0)
    with pytest.raises(ValueError, match="arc must be in"):
        M.point_at_arc(mer, mer.length + 0.001)


# --- Base protocol ---------------------------------------------------------------------


def test_base_protocol_has_18_taps_per_object_on_three_paths(base):
    assert base.name == "base" and base.seed is None
    assert len(base) == 18 * len(OBJECTS) == 144
    assert base.objects == OBJECTS
    assert [t.index for t in base.taps] == list(range(144))
    for obj in OBJECTS:
        taps = [t for t in base.taps if t.object == obj]
        assert len(taps) == 18
        rolls = collections.Counter(round(math.degrees(t.sensor_roll), 9) for t in taps)
        assert rolls == {0.0: 6, 90.0: 6, 180.0: 6}
        assert sorted((t.row, t.position) for t in taps) == [(r, p) for r in range(3) for p in range(6)]
    assert all(t.depth == P.TAP_DEPTH_M == 0.002 and t.spin == 0.0 and t.replica == 0 for t in base.taps)


def test_base_taps_match_the_analytic_capsule(spec, base):
    R, z_top, c = capsule(spec)
    angles = np.radians([0.0, 30.0, 60.0, 90.0])
    for t in base.taps:
        up = K.up_in_sensor(t.sensor_roll)
        point, normal = np.array(t.point), np.array(t.normal)
        if t.position < 4:
            a = angles[t.position]
            exact = c + R * (np.sin(a) * up + np.cos(a) * np.array([0.0, 0.0, 1.0]))
            tol = TIP_POINT_TOLERANCE_M if t.position < 3 else JUNCTION_POINT_TOLERANCE_M
            assert t.indenter_pitch == pytest.approx(np.pi / 2 - a, abs=EXACT)
        else:
            exact = R * up + np.array([0.0, 0.0, z_top - (0.009, 0.018)[t.position - 4]])
            tol = JUNCTION_POINT_TOLERANCE_M
            assert t.indenter_pitch == pytest.approx(0.0, abs=NORMAL_TOLERANCE_RAD)
        assert np.linalg.norm(point - exact) < tol, (t, exact)
        # Unit, outward, perpendicular to the membrane.
        assert np.linalg.norm(normal) == pytest.approx(1.0, abs=EXACT)
        assert angle_between(normal, capsule_normal(spec, point[None])[0]) < NORMAL_TOLERANCE_RAD
    # The apex tap hangs the indenter horizontally, straight at the tip (pitch pi/2).
    apex = [t for t in base.taps if t.position == 0]
    assert all(np.allclose(t.normal, [0.0, 0.0, 1.0], atol=EXACT) for t in apex)


def test_base_protocol_refuses_bad_objects(spec, mesh):
    with pytest.raises(ValueError, match="objects"):
        P.base_protocol(spec, mesh, "sphere")
    with pytest.raises(ValueError, match="repeat"):
        P.base_protocol(spec, mesh, ("sphere", "sphere"))


# --- Extended protocol ---------------------------------------------------------------


def test_extended_protocol_size(extended):
    assert extended.name == "extended" and extended.seed == 0
    assert len(extended) == 5 * 16 * 36 * len(OBJECTS) == 23040
    counts = collections.Counter(t.object for t in extended.taps)
    assert counts == {obj: 2880 for obj in OBJECTS}
    assert [t.index for t in extended.taps] == list(range(len(extended)))
    rows = collections.Counter((t.row, t.position, t.replica) for t in extended.taps)
    assert len(rows) == 5 * 16 * 36 and set(rows.values()) == {len(OBJECTS)}


def test_extended_samples_are_all_different_poses(extended):
    """The published extended set had its perturbations off, so most samples repeated."""
    keys = [t.pose_key() for t in extended.taps]
    assert len(set(keys)) == len(keys)
    # Not only the object name: the poses themselves differ within each object.
    for obj in OBJECTS[:2]:
        poses = {k[1:] for k in keys if k[0] == obj}
        assert len(poses) == 2880


def test_extended_points_lie_on_the_membrane(spec, mesh, extended):
    points = np.array([t.point for t in extended.taps])
    normals = np.array([t.normal for t in extended.taps])
    # Independent of the mesh: within the chord sag of the analytic capsule.
    assert capsule_distance(spec, points).max() < 1e-5
    assert np.allclose(np.linalg.norm(normals, axis=1), 1.0, atol=EXACT)
    tilt = angle_between(normals, capsule_normal(spec, points))
    assert tilt.max() < C.MAX_APPROACH_TILT_RAD
    # In view: clear of the base by the margin.
    assert points[:, 2].min() > spec.membrane.base_z + P.EXTENDED_BASE_MARGIN_M - P.POSITION_JITTER_M
    C.validate(extended, spec, mesh)


def test_extended_perturbations_stay_within_their_bounds(spec, extended):
    taps = [t for t in extended.taps if t.object == "sphere"]
    nominal = {(t.row, t.position): t for t in taps if t.replica == 0}
    rolls = np.asarray(P.EXTENDED_ROLLS_RAD)
    assert {round(math.degrees(t.sensor_roll), 9) for t in nominal.values()} == {0.0, 45.0, 90.0, 135.0, 180.0}
    d_roll, d_pitch, d_depth, spin, shift = [], [], [], [], []
    for t in taps:
        n = nominal[t.row, t.position]
        if t.replica == 0:
            # Perpendicular, at the nominal depth, no spin.
            assert t.depth == P.TAP_DEPTH_M and t.spin == 0.0 and t.sensor_roll == rolls[t.row]
            surface = capsule_normal(spec, np.array([t.point]))[0]
            assert angle_between(np.array(t.normal), surface) < NORMAL_TOLERANCE_RAD
            continue
        d_roll.append(t.sensor_roll - n.sensor_roll)
        d_pitch.append(t.indenter_pitch - n.indenter_pitch)
        d_depth.append(t.depth - n.depth)
        spin.append(t.spin)
        shift.append(np.linalg.norm(np.subtract(t.point, n.point)))
        assert P.ROLL_RANGE_RAD[0] <= t.sensor_roll <= P.ROLL_RANGE_RAD[1]
        # The servo board (horns 0-180 deg at its boot offsets) refuses a negative pitch.
        assert P.PITCH_RANGE_RAD[0] <= t.indenter_pitch <= P.PITCH_RANGE_RAD[1]
    for values, bound in [
        (d_roll, P.ROLL_JITTER_RAD),
        (d_pitch, P.PITCH_JITTER_RAD),
        (d_depth, P.DEPTH_JITTER_M),
        (spin, P.SPIN_JITTER_RAD),
        (shift, P.POSITION_JITTER_M + REPROJECTION_SLACK_M),
    ]:
        values = np.abs(values)
        assert values.max() <= bound + EXACT
        assert values.max() > 0.8 * bound  # really perturbed, over most of the range
    assert max(d_depth) + P.TAP_DEPTH_M <= C.max_safe_depth_m(spec)


def test_extended_protocol_is_deterministic_for_a_seed(spec, mesh):
    a = P.extended_protocol(spec, mesh, ("cone",), seed=3, replicas=4)
    b = P.extended_protocol(spec, mesh, ("cone",), seed=3, replicas=4)
    c = P.extended_protocol(spec, mesh, ("cone",), seed=4, replicas=4)
    assert a == b
    assert len(a) == 5 * 16 * 4
    differ = [x.pose_key() != y.pose_key() for x, y in zip(a.taps, c.taps)]
    # Replica 0 is the same nominal grid for every seed; every other tap differs.
    assert sum(differ) == len(a) - 5 * 16
    assert all(d == (t.replica > 0) for d, t in zip(differ, a.taps))


def test_extended_protocol_refuses_bad_arguments(spec, mesh):
    with pytest.raises(ValueError, match="replicas"):
        P.extended_protocol(spec, mesh, OBJECTS, replicas=0)
    with pytest.raises(ValueError, match="seed"):
        P.extended_protocol(spec, mesh, OBJECTS, seed=1.5)


# --- JSON ------------------------------------------------------------------------------


def test_json_round_trip(spec, mesh, base):
    assert T.Protocol.from_json(base.to_json()) == base
    ext = P.extended_protocol(spec, mesh, ("pacman", "random"), seed=11, replicas=3)
    again = T.Protocol.from_json(ext.to_json(indent=1))
    assert again == ext and again.seed == 11 and again.objects == ("pacman", "random")
    data = json.loads(ext.to_json())
    assert isinstance(data["taps"][5]["point"], list) and len(data["taps"][5]["point"]) == 3
    tap = ext.taps[5]
    assert T.Tap.from_dict(tap.to_dict()) == tap and hash(tap.pose_key()) == hash(again.taps[5].pose_key())


def _tap_dict(base, **changes):
    data = base.to_dict()
    data["taps"] = data["taps"][:2]
    data["taps"][1].update(changes)
    return data


@pytest.mark.parametrize(
    "mutate, message",
    [
        (lambda b: "{not json", "could not be parsed"),
        (lambda b: json.dumps([1, 2]), "must be a JSON object"),
        (lambda b: json.dumps({**b.to_dict(), "taps": {}}), "protocol.taps must be a list"),
        (lambda b: json.dumps({**b.to_dict(), "version": 2}), "version"),
        (lambda b: json.dumps({**b.to_dict(), "extra": 1}), "unknown keys"),
        (lambda b: json.dumps(_tap_dict(b, point=[0.0, 0.01])), r"taps\[1\]\.point must be a list of 3"),
        (lambda b: json.dumps(_tap_dict(b, normal="up")), r"taps\[1\]\.normal"),
        (lambda b: json.dumps(_tap_dict(b, depth=True)), r"taps\[1\]\.depth must be a finite number"),
        (lambda b: json.dumps(_tap_dict(b, depth=None)), r"taps\[1\]\.depth"),
        (lambda b: _json_nan(b), r"taps\[1\]\.sensor_roll must be a finite number"),
        (lambda b: json.dumps(_tap_dict(b, row=-1)), r"taps\[1\]\.row must be an integer"),
        (lambda b: json.dumps(_tap_dict(b, index=7)), r"taps\[1\]\.index must be 1"),
        (lambda b: json.dumps(_tap_dict(b, object="")), r"taps\[1\]\.object"),
        (lambda b: json.dumps(_without(b, "depth")), r"taps\[1\] is missing 'depth'"),
    ],
)
def test_corrupt_json_is_refused_with_a_clear_message(base, mutate, message):
    with pytest.raises(ValueError, match=message):
        T.Protocol.from_json(mutate(base))


def _json_nan(base):
    return json.dumps(_tap_dict(base, sensor_roll=float("nan")))  # json writes NaN


def _without(base, key):
    data = _tap_dict(base)
    del data["taps"][1][key]
    return data


# --- Validation ---------------------------------------------------------------------------


def _with_tap(protocol, i, **changes):
    taps = list(protocol.taps)
    taps[i] = dataclasses.replace(taps[i], **changes)
    return dataclasses.replace(protocol, taps=tuple(taps))


def test_validate_accepts_the_generated_protocols(spec, mesh, base):
    C.validate(base, spec, mesh)
    assert C.max_safe_depth_m(spec) == pytest.approx(spec.membrane.radius - spec.membrane.core_radius)


def test_validate_refuses_a_tap_deeper_than_the_membrane(spec, mesh, base):
    too_deep = C.max_safe_depth_m(spec) + 1e-4
    bad = _with_tap(base, 22, depth=too_deep)
    t = bad.taps[22]
    named = rf"tap 22 \(object '{t.object}', row {t.row}, position {t.position}, replica 0\)"
    with pytest.raises(ValueError, match=named + ".*glass core"):
        C.validate(bad, spec, mesh)
    with pytest.raises(ValueError, match="depth must be > 0"):
        C.validate(_with_tap(base, 3, depth=0.0), spec, mesh)


def test_validate_refuses_a_tap_off_the_membrane(spec, mesh, base):
    t = base.taps[9]
    lifted = tuple(np.add(t.point, 0.001 * np.array(t.normal)))
    with pytest.raises(ValueError, match=r"tap 9 .*1\.000 mm from the membrane.*miss the sensor"):
        C.validate(_with_tap(base, 9, point=lifted), spec, mesh)
    # Beside the sensor: the approach misses it altogether.
    with pytest.raises(ValueError, match="tap 0 .*misses the membrane"):
        C.validate(_with_tap(base, 0, point=(0.05, 0.0, 0.0)), spec, mesh)


def test_validate_refuses_an_inward_normal(spec, mesh, base):
    for i in (0, 5, 10):  # apex, cylinder, tip
        flipped = tuple(-np.array(base.taps[i].normal))
        with pytest.raises(ValueError, match=rf"tap {i} .*points into the membrane"):
            C.validate(_with_tap(base, i, normal=flipped), spec, mesh)


def test_validate_refuses_bad_normals_and_servo_angles(spec, mesh, base):
    t = base.taps[7]
    with pytest.raises(ValueError, match="unit vector"):
        C.validate(_with_tap(base, 7, normal=tuple(2 * np.array(t.normal))), spec, mesh)
    with pytest.raises(ValueError, match="point the indenter"):
        C.validate(_with_tap(base, 7, indenter_pitch=t.indenter_pitch + 0.05), spec, mesh)
    # A grazing approach, realised by the servos, at the apex.
    pitch = np.pi / 2 - math.radians(30.0)
    grazing = tuple(K.normal_in_sensor(t.sensor_roll, pitch))
    bad = _with_tap(base, 0, indenter_pitch=pitch, normal=grazing, point=base.taps[0].point)
    with pytest.raises(ValueError, match="tap 0 .*30.00 deg off the membrane normal"):
        C.validate(bad, spec, mesh)
