"""Sensor files that name a base file (scenes.spec_read.read_sensor_file): tables override the
base's key by key, named LEDs merge by name, another shape leaves the base's behind, and
a missing base or a cycle is refused naming the files."""

import tomllib
from pathlib import Path

import pytest

from scenes.spec import DEFAULT_SPEC_PATH
from scenes.spec_read import load_spec, read_sensor_file, spec_from_dict

SENSORS = Path(__file__).resolve().parents[1] / "scenes" / "sensors"


def _base() -> dict:
    return tomllib.loads(DEFAULT_SPEC_PATH.read_text())


def _write(folder: Path, name: str, text: str) -> Path:
    path = folder / name
    path.write_text(text)
    return path


def test_the_default_spec_is_the_shipped_geltip_and_the_others_name_it():
    assert DEFAULT_SPEC_PATH == SENSORS / "geltip.toml"
    assert "base" not in _base()
    for name in ("geltip_2023", "thumb", "paw"):
        assert tomllib.loads((SENSORS / f"{name}.toml").read_text())["base"] == "geltip.toml", name


def test_a_file_overrides_its_base_key_by_key(tmp_path):
    _write(tmp_path, "geltip.toml", DEFAULT_SPEC_PATH.read_text())
    path = _write(tmp_path, "wide.toml", '''
base = "geltip.toml"
name = "wide"
[camera]
fov_y = 2.0
[membrane]
base_z = -0.012
[[leds]]
name = "led1"
position = [-0.006, 0.0105, 0.0]
[[leds]]
name = "extra"
position = [0.0, 0.0, -0.001]
direction = [0.0, 0.0, 1.0]
colour = [1.0, 1.0, 1.0]
k_d = 0.5
k_s = 0.1
''')
    expected = _base()
    expected["name"] = "wide"
    expected["camera"]["fov_y"] = 2.0
    expected["membrane"]["base_z"] = -0.012
    expected["leds"][1]["position"] = [-0.006, 0.0105, 0.0]
    expected["leds"].append({"name": "extra", "position": [0.0, 0.0, -0.001], "direction": [0.0, 0.0, 1.0],
                             "colour": [1.0, 1.0, 1.0], "k_d": 0.5, "k_s": 0.1})
    assert read_sensor_file(path) == expected
    spec = load_spec(path)
    assert spec == spec_from_dict(expected, str(path))
    assert [led.name for led in spec.leds] == ["led0", "led1", "led2", "extra"]
    assert spec.leds[1].colour == load_spec().leds[1].colour  # the rest of led1 is the base's


def test_an_empty_array_drops_the_bases_and_a_chain_of_bases_resolves_in_order(tmp_path):
    _write(tmp_path, "geltip.toml", DEFAULT_SPEC_PATH.read_text())
    (tmp_path / "sub").mkdir()
    _write(tmp_path / "sub", "middle.toml", 'base = "../geltip.toml"\nname = "middle"\n[camera]\nfov_y = 2.0\n')
    top = _write(tmp_path, "top.toml", '''
base = "sub/middle.toml"
name = "top"
leds = []
[[led_groups]]
name = "ring"
count = 4
arc_centre_rad = 0.0
arc_span_rad = 6.283185307179586
ring_radius = 0.0065
height = -0.003
colour = [1.0, 1.0, 1.0]
k_d = 0.9
k_s = 0.1
''')
    spec = load_spec(top)
    assert spec.name == "top" and spec.camera.fov_y == 2.0 and spec.membrane == load_spec().membrane
    assert [led.name for led in spec.leds] == ["ring0", "ring1", "ring2", "ring3"]


def test_another_shape_keeps_none_of_the_bases_shape_keys(tmp_path):
    """The shipped thumb names the capsule GelTip as its base: it inherits base_z and
    mesh_edge, not radius, cylinder_length or core_radius (which a thumb refuses)."""
    data = read_sensor_file(SENSORS / "thumb.toml")
    assert set(data["membrane"]) == {"shape", "base_z", "thickness", "mesh_edge", "params"}
    assert data["membrane"]["base_z"] == _base()["membrane"]["base_z"]
    # And a paw over the thumb keeps none of the thumb's parameters.
    path = _write(tmp_path, "paw.toml", f'base = "{SENSORS / "thumb.toml"}"\nname = "p"\n[membrane]\nshape = "paw"\n')
    assert read_sensor_file(path)["membrane"] == {"shape": "paw", "base_z": -0.010, "thickness": 0.0025,
                                                  "mesh_edge": 0.0005}


def test_a_bases_mesh_paths_are_relative_to_the_base(tmp_path):
    (tmp_path / "meshes").mkdir()
    _write(tmp_path / "meshes", "base.toml", 'name = "m"\n[membrane]\nshape = "mesh"\nmesh_path = "skin.stl"\n'
                                              'thickness = 0.0025\n')
    path = _write(tmp_path, "top.toml", 'base = "meshes/base.toml"\nname = "top"\n')
    assert read_sensor_file(path)["membrane"]["mesh_path"] == str((tmp_path / "meshes" / "skin.stl").resolve())


def test_a_missing_base_names_the_file_that_names_it(tmp_path):
    path = _write(tmp_path, "orphan.toml", 'base = "nowhere.toml"\nname = "orphan"\n')
    with pytest.raises(FileNotFoundError, match=r"sensor spec .*orphan\.toml: its base .*nowhere\.toml does not exist"):
        load_spec(path)


@pytest.mark.parametrize("base", [3, "", ["geltip.toml"]])
def test_a_base_that_names_no_file_is_refused(tmp_path, base):
    path = _write(tmp_path, "odd.toml", f"base = {base!r}\n".replace("'", '"'))
    with pytest.raises(ValueError, match=r"odd\.toml: base must name a sensor file \(relative to this one\), got "):
        read_sensor_file(path)


def test_a_cycle_of_bases_is_refused(tmp_path):
    _write(tmp_path, "a.toml", 'base = "b.toml"\nname = "a"\n')
    _write(tmp_path, "b.toml", 'base = "a.toml"\nname = "b"\n')
    with pytest.raises(ValueError, match=r"b\.toml: base 'a\.toml' makes a cycle: .*a\.toml -> .*b\.toml -> .*a\.toml"):
        load_spec(tmp_path / "a.toml")
    _write(tmp_path, "self.toml", 'base = "./self.toml"\nname = "self"\n')
    with pytest.raises(ValueError, match="makes a cycle"):
        load_spec(tmp_path / "self.toml")


def test_a_dict_that_names_a_base_is_refused():
    data = _base()
    data["base"] = "geltip.toml"
    with pytest.raises(ValueError, match=r"test: base = 'geltip\.toml' names a base file.*load_spec"):
        spec_from_dict(data, "test")
