"""Every effect of the reference at each end of its accepted range either renders a finite
image or is refused with a ValueError that names it; outside the range, Effects refuses it."""

from __future__ import annotations

import math
from dataclasses import fields, replace

import numpy as np
import pytest

from pbr_tactile.effects import RANGES, Effects

#: Stands in for an open (infinite) end of a range in the renders.
LARGE = 1e4
#: Effects that act on the rendered image (pbr_tactile.sensor), not on the scene.
SENSOR_SIDE = ("vignetting", "lens_distortion", "sensor_noise")
#: A tiny render: 16x12 film, 2 passes of 1 sample.
TINY = {"spp": 2, "passes": 2, "width": 16, "height": 12}
#: A coarse elastomer (metres per edge): Mitsuba loads it quickly.
COARSE_EDGE_M = 1e-3


def _bounds() -> list:
    cases = []
    for f in fields(Effects):
        if f.type == "bool":
            values = [False, True]
        else:
            values = [v if math.isfinite(v) else math.copysign(LARGE, v) for v in RANGES[f.name]]
            if isinstance(getattr(Effects(), f.name), tuple):
                values = [(v, v) for v in values]
        cases += [pytest.param(f.name, v, id=f"{f.name}={v}") for v in values]
    return cases


def test_every_numeric_effect_has_a_range_and_outside_it_is_refused():
    numeric = {f.name for f in fields(Effects) if f.type != "bool"}
    assert numeric == set(RANGES)
    for name, (low, high) in RANGES.items():
        outside = [math.nan, math.inf, -math.inf] + [v for v in (low - 1, high + 1) if math.isfinite(v)]
        for v in outside:
            value = (v, 0.0) if isinstance(getattr(Effects(), name), tuple) else v
            with pytest.raises(ValueError, match=rf"Effects\.{name} must be (in \[|finite)"):
                Effects(**{name: value})


@pytest.fixture(scope="module")
def tiny_render(mesh, spec, camera):
    """effects -> a tiny volpath render (scalar variant) of the no-contact sensor; renders
    differing only in sensor-side effects share one, those applied as ``reference`` does."""
    pytest.importorskip("mitsuba", reason="Mitsuba 3 is not installed (pip install '.[pbr]')")
    from pbr_tactile.membrane import ElastomerBuilder
    from pbr_tactile.render import RenderSettings, reference, sensor_effects

    solids = ElastomerBuilder(mesh, spec, camera, COARSE_EDGE_M)
    renders = {}

    def render(effects: Effects):
        scene_side = replace(effects, **{n: getattr(Effects(), n) for n in SENSOR_SIDE})
        if scene_side not in renders:
            renders[scene_side] = reference(None, None, mesh, spec, camera, scene_side,
                                            RenderSettings(estimator="volpath", variant="scalar_spectral", **TINY),
                                            solids=solids)
        return sensor_effects(renders[scene_side], camera, effects)

    return render


@pytest.mark.parametrize("name, value", _bounds())
def test_each_effect_at_its_bounds_renders_or_is_refused_by_name(tiny_render, name, value):
    try:
        est = tiny_render(Effects(**{name: value}))
    except ValueError as exc:
        assert name in str(exc), f"{name}={value} was refused without naming it: {exc}"
        return
    assert est.mean.shape == (TINY["height"], TINY["width"], 3)
    assert np.isfinite(est.mean).all() and (est.variance >= 0).all()


@pytest.mark.slow  # 15 to 22 s alone on 2 cores
def test_all_led_power_into_the_core_renders_with_photons(mesh, spec, camera):
    """core_light_leak = 1: only the leak emitters in the glass (the LEDs in the
    elastomer have no power left and are left out), with the default estimator."""
    pytest.importorskip("mitsuba", reason="Mitsuba 3 is not installed (pip install '.[pbr]')")
    from pbr_tactile.membrane import ElastomerBuilder
    from pbr_tactile.render import RenderSettings, reference
    from pbr_tactile.scene import led_sources
    from pbr_tactile.variant import VariantError, choose_variant

    sources = led_sources(spec, Effects(core_light_leak=1.0))
    assert len(sources) == len(spec.leds) and not any(s["in_elastomer"] for s in sources)
    with pytest.raises(ValueError, match="led_power must be a finite radiance scale > 0, got 0.0"):
        led_sources(spec, Effects(), led_power=0.0)
    try:
        if not choose_variant().variant().startswith(("llvm_", "cuda_")):
            pytest.skip("the photon estimator needs a vectorised variant (apt-get install libllvm19)")
    except VariantError as exc:
        pytest.skip(str(exc))
    est = reference(None, None, mesh, spec, camera, Effects(core_light_leak=1.0), RenderSettings(photons=1 << 8, **TINY),
                    solids=ElastomerBuilder(mesh, spec, camera, COARSE_EDGE_M))
    assert np.isfinite(est.mean).all() and est.mean.max() > 0  # the core's light reaches the camera
