"""Shape families (scenes.shapes): one registry, every family answering the same questions,
and no code outside the families that compares a shape with a family's name."""

import ast
import dataclasses
from pathlib import Path

import numpy as np
import pytest

from scenes import shapes
from scenes.geometry import membrane_mesh
from scenes.shapes import Tube, capsule, family
from scenes.shapes.interface import MEMBERS
from scenes.spec import MAX_SENSOR_SIZE_M
from scenes.spec_read import default_spec, load_spec, spec_from_dict

ROOT = Path(__file__).resolve().parents[1]
SENSORS = ROOT / "scenes" / "sensors"
#: Packages whose code must ask a shape's family rather than compare its name.
PACKAGES = ("scenes", "phong_reference", "pbr_tactile", "rig", "studies")
#: The one package that may name a family in a comparison: the families'.
FAMILIES_PACKAGE = "scenes/shapes/"


def test_every_family_is_registered_once_by_its_name():
    assert shapes.FAMILIES == ("capsule", "thumb", "paw", "pad", "mesh")
    for name in shapes.FAMILIES:
        module = family(name)
        assert module.NAME == name and module.__name__ == f"scenes.shapes.{name}"
        missing = [m for m in MEMBERS if not hasattr(module, m)]
        assert len(MEMBERS) == 14 and "mesh" in MEMBERS and "regions" in MEMBERS and "PUBLISHED" in MEMBERS
        assert not missing, f"family {name!r} lacks {missing}"
    assert set(shapes.ANALYTIC) <= set(shapes.FAMILIES)
    # Each [membrane] key that one family alone takes belongs to exactly one.
    assert shapes.TABLE_KEYS == {"radius": "capsule", "cylinder_length": "capsule", "core_radius": "capsule",
                                 "mesh_path": "mesh", "core_mesh_path": "mesh", "mesh_transform": "mesh"}


@pytest.mark.parametrize("sensor, names", [("geltip", ("tip", "body")), ("thumb", ("tip", "body")),
                                           ("paw", ("tip", "body")), ("gelsight", ("centre", "rim"))])
def test_each_family_splits_the_image_circle_into_its_own_regions(sensor, names):
    """A finger's tip and body, a flat pad's centre and rim: disjoint, filling the image
    circle. The capsule's tip is what lies beyond its junction; a derived finger's is its
    farthest fifth along the axis; the pad's centre is the half nearest the camera's axis,
    and it has no tip."""
    from scenes.camera import Camera, reference_depth
    from scenes.shapes.interface import CENTRE_SHARE, TIP_SHARE

    spec = load_spec(SENSORS / f"{sensor}.toml").at_resolution(160, 120)
    camera = Camera.from_spec(spec)
    points = reference_depth(membrane_mesh(spec), camera)[0][..., None] * camera.rays
    inside = camera.mask
    f = family(spec.membrane.shape)
    regions = f.regions(spec.membrane, points, inside)
    assert f.REGIONS == names and tuple(regions) == names
    first, rest = (regions[n] for n in names)
    assert not (first & rest).any() and np.array_equal(first | rest, inside) and first.any() and rest.any()
    z, off_axis = points[..., 2], np.hypot(points[..., 0], points[..., 1])
    tube = f.tube(spec.membrane)
    if names[0] == "tip" and tube is not None:
        assert np.array_equal(first, inside & (z >= tube.junction_z))
    elif names[0] == "tip":
        assert first.sum() / inside.sum() == pytest.approx(TIP_SHARE, abs=0.02)
        assert z[first].min() >= z[rest].max()
    else:
        assert first.sum() / inside.sum() == pytest.approx(CENTRE_SHARE, abs=0.02)
        assert off_axis[first].max() <= off_axis[rest].min()
    assert set(shapes.REGIONS) == {"tip", "body", "centre", "rim"}


@pytest.mark.parametrize("name", ["bone", "", None, 3, "Capsule"])
def test_an_unknown_family_is_refused_naming_the_known_ones(name):
    with pytest.raises(ValueError, match=r"membrane\.shape must be one of capsule, thumb, paw, pad, mesh, got "):
        family(name)
    data = default_spec().to_dict()
    data["membrane"]["shape"] = name
    known = r"membrane\.shape must be one of capsule, thumb, paw, pad, mesh" if isinstance(name, str) else \
        r"membrane\.shape must be str"
    with pytest.raises(ValueError, match=r"geltip\.toml: " + known):
        spec_from_dict(data, "geltip.toml")


def test_the_families_answers():
    spec = default_spec()
    m = spec.membrane
    # The capsule's body is known in closed form; the others are measured (scenes.body).
    assert capsule.tube(m) == Tube(radius=m.radius, core_radius=m.core_radius, base_z=m.base_z,
                                   junction_z=m.base_z + m.cylinder_length)
    assert capsule.tube(m).thickness == m.radius - m.core_radius == m.elastomer_thickness
    assert capsule.tube(m).apex_z == m.base_z + m.cylinder_length + m.radius
    for path in ("thumb", "paw", "gelsight"):
        other = load_spec(SENSORS / f"{path}.toml").membrane
        assert family(other.shape).tube(other) is None and other.elastomer_thickness == other.thickness
    assert [n for n in shapes.FAMILIES if family(n).PUBLISHED] == ["capsule"]
    assert [n for n in shapes.FAMILIES if family(n).FILLS_VIEW] == ["pad"]
    assert [n for n in shapes.FAMILIES if not family(n).SEATED] == ["mesh"]
    # The mesh family reads files with the spec's bound on a plausible sensor.
    assert shapes.mesh.MM_SUSPICION_EXTENT == MAX_SENSOR_SIZE_M


def test_a_family_without_params_refuses_them_and_a_capsule_refuses_a_thickness():
    data = default_spec().to_dict()
    data["membrane"]["params"] = {"radius": 0.01}
    with pytest.raises(ValueError, match=r"membrane\.params: a 'capsule' membrane takes no \[membrane\.params\] \(its "
                                         r"size is radius and cylinder_length\); drop radius"):
        spec_from_dict(data, "test")
    data = default_spec().to_dict()
    data["membrane"]["thickness"] = 0.002
    with pytest.raises(ValueError, match=r"membrane\.thickness: a capsule's thickness is radius - core_radius"):
        spec_from_dict(data, "test")
    data = load_spec(SENSORS / "thumb.toml").to_dict()
    data["membrane"]["cylinder_length"] = 0.03
    with pytest.raises(ValueError, match=r"cylinder_length is for shape = 'capsule', not a 'thumb' membrane, which "
                                         r"takes its size from \[membrane.params\] and its core from thickness"):
        spec_from_dict(data, "test")


def test_the_membrane_mesh_is_the_familys_seated():
    spec = default_spec()
    moved = spec.replace(camera=dataclasses.replace(spec.camera, offset_m=(0.001, 0.0), tilt_rad=(0.02, 0.0)))
    mesh = capsule.mesh(moved.membrane)
    mesh.apply_transform(moved.camera.tube_to_camera())
    assert np.array_equal(membrane_mesh(moved).vertices, mesh.vertices)
    assert np.array_equal(membrane_mesh(spec).vertices, capsule.mesh(spec.membrane).vertices)


def _family_comparisons(path: Path) -> list[int]:
    """Lines of ``path`` that compare something with a family's name ("capsule", "mesh",
    ...: ==, !=, in, not in a literal tuple, list or set that holds one)."""

    def names_family(node) -> bool:
        if isinstance(node, ast.Constant):
            return node.value in shapes.FAMILIES
        if isinstance(node, (ast.Tuple, ast.List, ast.Set)):
            return any(isinstance(e, ast.Constant) and e.value in shapes.FAMILIES for e in node.elts)
        return False

    lines = []
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Compare) and any(names_family(n) for n in [node.left, *node.comparators]):
            lines.append(node.lineno)
        elif isinstance(node, ast.match_case) and names_family(getattr(node.pattern, "value", None)):
            lines.append(node.pattern.lineno)
    return lines


def test_no_module_outside_the_families_compares_a_shape_with_a_familys_name():
    found = {}
    for package in PACKAGES:
        for path in sorted((ROOT / package).rglob("*.py")):
            rel = str(path.relative_to(ROOT))
            lines = _family_comparisons(path)
            if lines and not rel.startswith(FAMILIES_PACKAGE):
                found[rel] = lines
    assert not found, f"ask the shape's family (scenes.shapes.family) instead: {found}"


def test_the_scan_finds_a_comparison(tmp_path):
    path = tmp_path / "branchy.py"
    path.write_text('a = m.shape == "capsule"\nb = "capsule" != m.shape\nc = m.shape in ("pad", "capsule")\n'
                    'd = m.shape == "thumb"\nmatch m.shape:\n    case "capsule":\n        pass\n')
    assert _family_comparisons(path) == [1, 2, 3, 4, 6]
