"""A shape family's parameters: their names, defaults, bounds and units, and their check.

A spec's ``[membrane.params]`` table names some of a family's parameters, in SI units;
:meth:`Parameters.check` fills the rest with their defaults and refuses, naming the
input, an unknown name, a value that is not a finite number (or not whole, where it must
be) and one outside its bounds. A family checks what its shape needs beyond that itself
(``scenes.shapes.form.check_form``, ``scenes.shapes.pad.check_params``).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

#: How messages name each unit.
UNIT_WORDS = {"m": "metres", "rad": "radians", "-": "dimensionless"}
UNIT_SUFFIX = {"m": " m", "rad": " rad", "-": ""}


@dataclass(frozen=True, eq=False)
class Parameters:
    """One family's parameters.

    family : the family's name, as a spec's ``membrane.shape`` gives it.
    defaults : name -> value, SI units: every parameter, in the order messages list them.
    bounds : name -> (low, high), the same units, both included.
    units : name -> "m", "rad" or "-" (dimensionless).
    whole : names whose values must be whole numbers.

    The mappings are the family module's own (``DEFAULTS``, ``BOUNDS``, ``UNITS``), held,
    not copied.
    """

    family: str
    defaults: Mapping[str, float]
    bounds: Mapping[str, tuple[float, float]]
    units: Mapping[str, str]
    whole: tuple[str, ...] = ()

    def fill(self, params: Mapping[str, float], where: str) -> dict[str, float]:
        """Defaults filled in; names known and values finite numbers (whole where needed),
        not checked against the bounds (so that shapes beyond them can be measured)."""
        if not isinstance(params, Mapping):
            raise ValueError(f"{where}: parameters must be a mapping of name to number, got {type(params).__name__}")
        out = dict(self.defaults)
        for name, value in params.items():
            if name not in self.defaults:
                raise ValueError(f"{where}: unknown parameter {name!r} for a {self.family!r} membrane; expected some "
                                 f"of {', '.join(self.defaults)}")
            what = UNIT_WORDS[self.units[name]]
            if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, float, np.integer, np.floating)):
                raise ValueError(f"{where}.{name} must be a number ({what}), got {value!r}")
            value = float(value)
            if not math.isfinite(value):
                raise ValueError(f"{where}.{name} must be finite ({what}), got {value}")
            if name in self.whole and value != round(value):
                raise ValueError(f"{where}.{name} must be a whole number, got {value}")
            out[name] = value
        return out

    def check(self, params: Mapping[str, float], where: str) -> dict[str, float]:
        """:meth:`fill`, and every value within its bounds: name -> float, every parameter."""
        out = self.fill(params, where)
        for name, (lo, hi) in self.bounds.items():
            if not lo <= out[name] <= hi:
                unit = UNIT_SUFFIX[self.units[name]]
                raise ValueError(f"{where}.{name} = {out[name]:g}{unit} is outside its bounds [{lo:g}, {hi:g}]{unit} "
                                 f"({UNIT_WORDS[self.units[name]]}) for a {self.family!r} membrane")
        return out
