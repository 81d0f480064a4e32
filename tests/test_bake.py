"""Baking through the dispatcher: caching, validation of LEDs, meshes and methods."""

import dataclasses

import numpy as np
import pytest
import trimesh

from phong_reference.bake import bake
from phong_reference.sources import snap_leds
from scenes.cache import CACHE_ENV, cache_dir
from scenes.camera import Camera


@pytest.fixture(autouse=True)
def own_cache(tmp_path, monkeypatch):
    """Each test an empty cache of its own: these count and corrupt its entries, which the
    user's cache (or another test worker's entries in it) must not see."""
    monkeypatch.setenv(CACHE_ENV, str(tmp_path / "cache"))


def _entries(method):
    return sorted(cache_dir().glob(f"fields-{method}-*.npz"))


def test_cache_is_keyed_by_content_not_by_object(mesh, spec, small_camera):
    before = set(_entries("linear"))
    a = bake(mesh, small_camera, spec.leds, "linear")
    # A new but equal camera object, after the first one was used, hits the same entry.
    b = bake(mesh, Camera(**{f.name: getattr(small_camera, f.name) for f in dataclasses.fields(small_camera)}),
             spec.leds, "linear")
    assert len(set(_entries("linear")) - before) == 1
    assert np.array_equal(a.fields, b.fields)
    moved = [dataclasses.replace(spec.leds[0], position=(0.0119, 0.0, 0.0))] + list(spec.leds[1:])
    bake(mesh, small_camera, moved, "linear")
    assert len(set(_entries("linear")) - before) == 2


def test_corrupt_cache_entry_is_rebuilt(mesh, spec, small_camera):
    good = bake(mesh, small_camera, spec.leds, "linear")
    for path in _entries("linear"):
        path.write_bytes(b"PK\x03\x04 garbage")
    with pytest.warns(UserWarning, match="rebuilding"):
        again = bake(mesh, small_camera, spec.leds, "linear")
    assert np.array_equal(good.fields, again.fields)


def test_linear_fields_are_unit_and_point_away_from_the_led(mesh, spec, small_camera):
    lf = bake(mesh, small_camera, spec.leds, "linear")
    ok = lf.valid[0]
    assert np.allclose(np.linalg.norm(lf.fields[0][ok], axis=-1), 1, atol=1e-6)
    P = lf.depth[..., None] * small_camera.rays
    away = P - np.array(spec.leds[0].position)
    assert np.all(np.einsum("hwi,hwi->hw", lf.fields[0], away)[ok] > 0)


def test_bad_bake_inputs(mesh, spec, small_camera):
    with pytest.raises(ValueError, match="method must be one of"):
        bake(mesh, small_camera, spec.leds, "spline")
    far = [dataclasses.replace(spec.leds[0], position=(0.05, 0.0, 0.0))]
    with pytest.raises(ValueError, match="from the membrane mesh"):
        snap_leds(mesh, far)
    with pytest.raises(ValueError, match="from the membrane mesh"):
        bake(mesh, small_camera, far, "geodesic", use_cache=False)
    broken = trimesh.Trimesh(np.array(mesh.vertices), mesh.faces, process=False)
    broken.vertices[0] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        bake(broken, small_camera, spec.leds, "linear")
    with pytest.raises(ValueError, match="at least one LED"):
        snap_leds(mesh, [])
