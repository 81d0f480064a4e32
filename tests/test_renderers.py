"""The renderer plugin interface (scenes.renderers): what each plugin offers, the
registry's lookup by name and its refusals, and the deprecated lookup below the command line."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from scenes.renderers import (
    Calibrates,
    RendererPlugin,
    SharesInputs,
    build_renderer,
    check_plugin,
    get_renderer,
    renderers,
)

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture
def fake(monkeypatch):
    monkeypatch.syspath_prepend(str(ROOT))
    from tests import fake_renderer

    return fake_renderer


def test_the_registry_names_both_renderers_and_loads_each_by_name():
    import pbr_tactile.plugin
    import phong_reference.plugin

    assert {"phong", "pbr"} <= set(renderers()) and list(renderers()) == sorted(renderers())
    assert get_renderer("phong") is phong_reference.plugin
    assert get_renderer("pbr") is pbr_tactile.plugin


def test_both_renderers_satisfy_the_protocol_and_state_their_optional_parts(fake):
    phong, pbr = get_renderer("phong"), get_renderer("pbr")
    for plugin in (phong, pbr, fake):
        assert isinstance(plugin, RendererPlugin)
    assert (phong.SOURCE, pbr.SOURCE, fake.SOURCE) == ("sim", "pbr", "sim")
    # the reference shares its no-contact frame with the workers; the fast path calibrates
    assert isinstance(pbr, SharesInputs) and not isinstance(pbr, Calibrates)
    assert isinstance(phong, Calibrates) and not isinstance(phong, SharesInputs)
    assert isinstance(fake, SharesInputs)


def test_a_plugin_not_registered_loads_by_its_module_path(fake):
    assert get_renderer("tests.fake_renderer") is fake


def test_unknown_renderers_are_refused_by_name():
    with pytest.raises(ValueError, match=r"renderer must be one of \[.*'pbr', 'phong'.*\] or an importable module "
                                         r"path 'package.module', got 'teapot'"):
        get_renderer("teapot")
    with pytest.raises(ValueError, match=r"renderer 'no_such.plugin' is not an importable module"):
        get_renderer("no_such.plugin")
    with pytest.raises(ValueError, match=r"renderer 'json.decoder' must be a renderer plugin .*got json.decoder, "
                                         r"which lacks SOURCE, prepare, make_renderer"):
        get_renderer("json.decoder")  # a module, but no plugin


def test_check_plugin_refuses_a_name_and_an_object_that_is_no_plugin():
    with pytest.raises(ValueError, match=r"renderer must be a renderer plugin .*got the name 'phong'; the command "
                                         r"line looks one up by name"):
        check_plugin("phong")

    class Half:
        SOURCE = "sim"

        def prepare(self, spec, mesh, camera, options):
            return {}

    with pytest.raises(ValueError, match=r"got Half, which lacks make_renderer"):
        check_plugin(Half())


def test_build_renderer_gives_shared_only_where_there_is_a_value():
    calls = []

    def without_shared(*args):
        calls.append(args)
        return "renderer"

    def with_shared(*args, shared=None):
        calls.append((args, shared))
        return "renderer"

    assert build_renderer(without_shared, 1, 2, 3, 4, {}) == "renderer"  # a plugin that shares nothing
    assert build_renderer(with_shared, 1, 2, 3, 4, {}, shared="inputs") == "renderer"
    assert calls == [(1, 2, 3, 4, {}), ((1, 2, 3, 4, {}), "inputs")]


def test_a_job_refuses_a_renderer_name(spec):
    """Below the command line a renderer is an object, never a name: a job given one says
    what it wants instead."""
    from scenes.generate import Job

    with pytest.raises(ValueError, match="make_renderer"):
        Job(spec, "phong", {}, ("sphere",))


def test_a_job_takes_the_plugins_make_renderer_not_the_plugin(spec):
    import phong_reference.plugin
    from scenes.generate import Job

    with pytest.raises(ValueError, match="make_renderer must be a renderer plugin's make_renderer function, got "
                                         "<module 'phong_reference.plugin'"):
        Job(spec, phong_reference.plugin, {}, ("sphere",))



# --- the contract: a renderer uses the spec and camera it is handed --------------------------

def _narrower(camera):
    """The camera with its image circle at 0.7 of its radius: not the spec's own."""
    import dataclasses

    return dataclasses.replace(camera, mask_radius_px=camera.mask_radius_px * 0.7)


def test_the_fast_path_renders_with_the_camera_it_is_handed(spec, mesh, camera, ref):
    """No profile: the image is the handed camera's, its circle included (the spec's own
    camera would light the ring between the two circles)."""
    from phong_reference import plugin

    narrow = _narrower(camera)
    ring = camera.mask & ~narrow.mask
    images = {}
    for handed in (camera, narrow):
        plugin.prepare(spec, mesh, handed, {})
        images[handed is narrow] = plugin.make_renderer(spec, mesh, handed, ref, {}).no_contact
    assert images[True].shape == narrow.shape + (3,)
    assert images[False][ring].any() and not images[True][ring].any()
    assert np.array_equal(images[True][narrow.mask], images[False][narrow.mask])
