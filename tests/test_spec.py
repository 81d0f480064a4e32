"""Sensor spec: the embedded GelTip, and bad specs refused with a clear message."""

import dataclasses
import math
import tomllib

import pytest

from scenes.shapes import family
from scenes.spec import DEFAULT_SPEC_PATH
from scenes.spec_read import load_spec, spec_from_dict


def test_default_geltip_matches_the_published_sensor(spec):
    m = spec.membrane
    assert m.radius == pytest.approx(0.0115)
    assert m.cylinder_length + m.radius == pytest.approx(0.0555)
    assert m.radius - m.core_radius == pytest.approx(0.0025)
    assert family(m.shape).tube(m).apex_z == pytest.approx(0.0455)
    assert (spec.camera.width, spec.camera.height) == (640, 480)
    assert spec.camera.fov_y == pytest.approx(math.pi / 2)
    assert len(spec.leds) == 3
    for a, led in enumerate(spec.leds):
        angle = 2 * math.pi * a / 3
        assert led.position == pytest.approx((0.012 * math.cos(angle), 0.012 * math.sin(angle), 0.0))
    assert [round(c * 255) for c in spec.leds[0].colour] == [87, 159, 233]
    assert [led.k_d for led in spec.leds] == [0.95, 0.7, 0.95]
    assert spec.material.ambient == 0.8 and spec.material.shininess == 100


def test_every_line_of_the_toml_names_its_unit():
    for line in DEFAULT_SPEC_PATH.read_text().splitlines():
        if "=" in line and not line.lstrip().startswith("#"):
            assert "#" in line, f"no unit comment on: {line}"


def test_spec_is_frozen_and_hashable(spec):
    # ``SensorSpec`` is a ``@dataclass(frozen=True)``: assignment raises the dataclass'
    # own error, naming the field that was assigned (not any exception at all).
    with pytest.raises(dataclasses.FrozenInstanceError, match="'name'"):
        spec.name = "x"
    with pytest.raises(dataclasses.FrozenInstanceError, match="'radius'"):
        spec.membrane.radius = 1.0
    assert spec.name != "x" and spec.membrane.radius == pytest.approx(0.0115)
    assert spec.digest() == load_spec().digest()
    assert hash(spec) == hash(load_spec())


def _data():
    return tomllib.loads(DEFAULT_SPEC_PATH.read_text())


@pytest.mark.parametrize(
    "edit, message",
    [
        (lambda d: d["membrane"].update(radius=11.5), "millimetres"),
        (lambda d: d["membrane"].update(radius=-0.01), "radius must be > 0"),
        (lambda d: d["membrane"].update(core_radius=0.02), "core_radius"),
        (lambda d: d["membrane"].update(shape="cube"), "membrane.shape"),
        (lambda d: d["camera"].update(fov_y=200.0), "fov_y"),
        (lambda d: d["camera"].update(width="640"), "camera.width must be int"),
        (lambda d: d["leds"][0].update(position=[12.0, 0.0, 0.0]), "millimetres"),
        (lambda d: d["leds"][0].update(position=[0.0, 0.0]), "list of 3"),
        (lambda d: d["leds"][1].update(colour=[197, 226, 241]), "colour must be linear RGB"),
        (lambda d: d["leds"][0].pop("k_d"), "missing key 'k_d'"),
        (lambda d: d.update(leds=[]), "at least one"),
        (lambda d: d["membrane"].update(shape="mesh"), "mesh_path"),
    ],
)
def test_bad_specs_are_refused_naming_the_key(edit, message):
    data = _data()
    edit(data)
    with pytest.raises(ValueError, match=message):
        spec_from_dict(data, "test.toml")


def test_unreadable_spec_files(tmp_path):
    with pytest.raises(FileNotFoundError, match="does not exist"):
        load_spec(tmp_path / "missing.toml")
    bad = tmp_path / "bad.toml"
    bad.write_text("name = [unclosed")
    with pytest.raises(ValueError, match="not valid TOML"):
        load_spec(bad)
