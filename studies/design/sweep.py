"""The designs of a sweep: a sensor spec with one or two of its design parameters varied.

A design parameter is one of

- a parameter of the membrane's shape family (``scenes.shapes.DEFAULTS``, for example the
  thumb's ``pad_flatness`` or the paw's ``toe_height``), in its SI unit;
- ``thickness``: the elastomer's thickness over the derived core, metres;
- ``led_height``: the z of every LED in the camera frame, metres (the LED ring's height
  along the finger).

Every design has its LEDs seated on its own membrane, as the shipped specs seat them:
each LED keeps its azimuth about the camera's axis and its height, and moves along the
ray from the axis to where that ray meets the membrane. A shape that grows or shrinks
thus keeps its LEDs at its edge. A sensor whose LEDs are laid out in groups inside the
tube (``[[led_groups]]``) cannot be swept: the fast path lights LEDs on the membrane.

Each design's spec goes through ``scenes.spec_read.spec_from_dict`` and its body through
``scenes.body.sensor_body``, so a design outside a family's bounds, one the camera
cannot see whole, or one whose elastomer is too thin is refused with that check's own
words (``Design.refused``) and the sweep goes on.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np
import trimesh

from scenes.shapes import DEFAULTS, family
from scenes.spec import SensorSpec
from scenes.spec_read import spec_from_dict

#: Design parameters every sensor has, besides its family's shape parameters.
COMMON = ("thickness", "led_height")
#: Most values swept per design parameter, and most parameters per sweep.
MAX_VALUES = 12
MAX_PARAMETERS = 2


@dataclass(frozen=True)
class Design:
    """One point of a sweep.

    values : parameter -> value, SI units.
    spec : the sensor, or None when refused.
    refused : why the design cannot be built (None: it can).
    """

    values: tuple[tuple[str, float], ...]
    spec: SensorSpec | None
    refused: str | None = None

    @property
    def label(self) -> str:
        return ", ".join(f"{k} = {v:.4g}" for k, v in self.values)


def parameters(spec: SensorSpec) -> tuple[str, ...]:
    """The design parameters a sensor can sweep."""
    return tuple(DEFAULTS.get(spec.membrane.shape, {})) + COMMON


def check_sweep(spec: SensorSpec, sweep: Mapping[str, Sequence[float]]) -> dict[str, tuple[float, ...]]:
    """The sweep, checked: one or two known parameters, each with 1 to MAX_VALUES distinct
    finite values."""
    if spec.led_groups:
        raise ValueError(f"sensor {spec.name!r} lays its LEDs out in groups inside the tube ([[led_groups]]); the "
                         "fast path lights LEDs on the membrane, so its designs cannot be scored")
    if family(spec.membrane.shape).PARAMETERS is None:
        raise ValueError(f"sensor {spec.name!r} is a mesh file: only a shape family (scenes.shapes) has parameters "
                         f"to sweep, besides {', '.join(COMMON)}; sweep those, or describe the shape as a family")
    if not 1 <= len(sweep) <= MAX_PARAMETERS:
        raise ValueError(f"sweep must vary 1 to {MAX_PARAMETERS} parameters, got {len(sweep)}")
    known = parameters(spec)
    out = {}
    for name, values in sweep.items():
        if name not in known:
            raise ValueError(f"sweep parameter {name!r} is not one of sensor {spec.name!r}'s: {', '.join(known)}")
        values = tuple(float(v) for v in values)
        if not 1 <= len(values) <= MAX_VALUES or len(set(values)) != len(values):
            raise ValueError(f"sweep parameter {name!r} needs 1 to {MAX_VALUES} distinct values, got {list(values)}")
        if not all(math.isfinite(v) for v in values):
            raise ValueError(f"sweep parameter {name!r} has a value that is not a finite number: {list(values)}")
        out[name] = values
    return out


def parse_sweep(text: str) -> tuple[str, tuple[float, ...]]:
    """``NAME=V1,V2,...`` or ``NAME=START:STOP:COUNT`` (COUNT values, ends included)."""
    name, sep, rest = text.partition("=")
    if not sep or not name.strip() or not rest.strip():
        raise ValueError(f"expected NAME=V1,V2,... or NAME=START:STOP:COUNT, got {text!r}")
    try:
        if ":" in rest:
            start, stop, count = rest.split(":")
            if int(count) < 1 or int(count) != float(count):
                raise ValueError(count)
            values = tuple(float(v) for v in np.linspace(float(start), float(stop), int(count)))
        else:
            values = tuple(float(v) for v in rest.split(","))
    except ValueError:
        raise ValueError(f"expected NAME=V1,V2,... or NAME=START:STOP:COUNT (COUNT a whole number >= 1), "
                         f"got {text!r}") from None
    return name.strip(), values


def seat_leds(leds: list[dict], mesh: trimesh.Trimesh, where: str) -> list[dict]:
    """Spec tables of LEDs moved along the ray from the camera's axis, at their azimuth
    and height, onto the membrane ``mesh``."""
    origins = np.array([[0.0, 0.0, led["position"][2]] for led in leds])
    azimuths = np.array([math.atan2(led["position"][1], led["position"][0]) for led in leds])
    directions = np.stack([np.cos(azimuths), np.sin(azimuths), np.zeros(len(leds))], axis=1)
    hits, rays, _ = mesh.ray.intersects_location(origins, directions, multiple_hits=False)
    out = [dict(led) for led in leds]
    for hit, ray in zip(hits, rays):
        out[ray]["position"] = [float(c) for c in hit]
    missed = sorted(set(range(len(leds))) - set(rays.tolist()))
    if missed:
        raise ValueError(f"{where}: LEDs {[leds[i]['name'] for i in missed]} at heights "
                         f"{[round(leds[i]['position'][2], 6) for i in missed]} m meet no membrane: the membrane "
                         "spans no such height")
    return out


def design(spec: SensorSpec, values: Mapping[str, float]) -> Design:
    """The sensor with the design parameters set, its LEDs seated on its membrane."""
    from scenes.body import sensor_body
    from scenes.geometry import membrane_mesh

    values = tuple(values.items())
    where = f"design {', '.join(f'{k} = {v:.4g}' for k, v in values)}"
    data = spec.to_dict()
    params = dict(data["membrane"].get("params", []))
    for name, value in values:
        if name == "thickness":
            data["membrane"]["thickness"] = value
        elif name == "led_height":
            for led in data["leds"]:
                led["position"][2] = value
        else:
            params[name] = value
    if params:
        data["membrane"]["params"] = params
    try:
        shaped = spec_from_dict(data, where)
        data["leds"] = seat_leds(data["leds"], membrane_mesh(shaped), where)
        seated = spec_from_dict(data, where)
        sensor_body(seated)
    except ValueError as exc:
        return Design(values, None, str(exc))
    return Design(values, seated)


def designs(spec: SensorSpec, sweep: Mapping[str, Sequence[float]]) -> list[Design]:
    """Every combination of the sweep's values (the first parameter slowest)."""
    sweep = check_sweep(spec, sweep)
    names = list(sweep)
    return [design(spec, dict(zip(names, combo))) for combo in itertools.product(*sweep.values())]
