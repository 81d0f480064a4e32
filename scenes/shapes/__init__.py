"""Shape families: every membrane shape a sensor spec can name, one module each, registered here.

- ``capsule``: a cylinder closed by a hemisphere over a round glass tube (the published
  GelTip), sized by the [membrane] table's own keys;
- ``thumb``, ``paw``: fingertip shapes generated from ``[membrane.params]``, over a core
  derived by offsetting the membrane;
- ``pad``: a flat sensor's domed elastomer pad on a clear plate;
- ``mesh``: a membrane read from a mesh file.

Each module answers the same questions (``scenes.shapes.interface.Family``): its
parameters and their check, its mesh, its body in closed form where it has one
(``Tube``), whether the camera seats it, whether the published GelTip's protocol and data
apply. Look a family up by its name with :func:`family`; code that depends on the shape
asks the family and never compares the name.

The capsule, thumb and paw are forms of ``scenes.shapes.form`` (a warped surface of
revolution and its guarantees); :data:`ANALYTIC` names them, and the functions below
measure and mesh them by name.
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np
import trimesh

from . import capsule, mesh, pad, paw, thumb
from .interface import Family, Tube
from .form import GRID, Diagnosis, check_form, diagnose_form, form_curvatures

#: Every family by its name (``membrane.shape``), in the order messages list them.
_REGISTRY = {f.NAME: f for f in (capsule, thumb, paw, pad, mesh)}
FAMILIES = tuple(_REGISTRY)
#: Every family's image regions (``Family.REGIONS``), each once, in the order messages list them.
REGIONS = tuple(dict.fromkeys(name for f in _REGISTRY.values() for name in f.REGIONS))
#: The [membrane] table's keys that one family alone takes -> that family's name.
TABLE_KEYS = {key: f.NAME for f in _REGISTRY.values() for key in f.TABLE_KEYS}
#: The families generated from an analytic form (``scenes.shapes.form``), and their
#: parameters' defaults, bounds and units (each family module's own).
ANALYTIC = ("capsule", "thumb", "paw")
DEFAULTS = {name: _REGISTRY[name].DEFAULTS for name in ANALYTIC}
BOUNDS = {name: _REGISTRY[name].BOUNDS for name in ANALYTIC}
UNITS = {name: _REGISTRY[name].UNITS for name in ANALYTIC}


def family(name: str, where: str = "membrane.shape") -> Family:
    """The family (its module) called ``name``; ValueError naming ``where`` and the known
    names otherwise."""
    if not isinstance(name, str) or name not in _REGISTRY:
        raise ValueError(f"{where} must be one of {', '.join(FAMILIES)}, got {name!r}")
    return _REGISTRY[name]


def _analytic(name, where: str):
    if not isinstance(name, str) or name not in ANALYTIC:
        raise ValueError(f"{where}: unknown shape family {name!r}; expected one of {', '.join(ANALYTIC)}")
    return _REGISTRY[name]


def check_params(family: str, params: Mapping[str, float], where: str = "membrane") -> dict[str, float]:
    """An analytic family's parameters with defaults filled in, checked
    (``scenes.shapes.form.check_form``).

    family : one of ANALYTIC.
    params : name -> number, SI units (see DEFAULTS, UNITS); missing names take defaults.
    where : names the input in messages (e.g. ``"geltip.toml: membrane.params"``).
    """
    f = _analytic(family, where)
    return check_form(f.PARAMETERS, f.form, params, where)


def diagnose(family: str, params: Mapping[str, float], grid: tuple[int, int] = GRID) -> Diagnosis:
    """Measure an analytic family's surface against ``scenes.shapes.form``'s guarantees.

    ``params`` are filled with defaults and checked against the family's names and types,
    not their bounds or the guarantees (this is what :func:`check_params` uses to enforce
    them).
    """
    f = _analytic(family, "membrane")
    return diagnose_form(f.form(f.PARAMETERS.fill(params, "membrane")), grid)


def principal_curvatures(family: str, params: Mapping[str, float],
                         grid: tuple[int, int] = GRID) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Points, outward normals and principal curvatures of an analytic family's surface
    (``scenes.shapes.form.form_curvatures``); defaults are filled in, names and numbers are
    checked but not the bounds, so that shapes beyond them can be measured."""
    f = _analytic(family, "membrane")
    return form_curvatures(f.form(f.PARAMETERS.fill(params, "membrane")), grid)


def tip_start_z(family: str, params: Mapping[str, float], base_z: float) -> float:
    """Where an analytic family's body ends and its tip starts, metres (camera frame): the
    top of the axis segment the membrane keeps ``MIN_CORE_CLEARANCE_M`` from."""
    f = _analytic(family, "membrane")
    return float(base_z) + f.form(f.PARAMETERS.fill(params, "membrane")).z_c


def shape_mesh(family: str, params: Mapping[str, float], base_z: float, edge: float) -> trimesh.Trimesh:
    """The outer membrane surface of an analytic family, in the tube frame.

    Parameters
    ----------
    family : one of ANALYTIC.
    params : name -> number, SI units; checked by :func:`check_params`.
    base_z : float, metres, height of the open base (the tube's axis is +z).
    edge : float, metres, target triangle edge length, in (0, MAX_EDGE_M].

    Returns
    -------
    trimesh.Trimesh, metres: one manifold sheet with outward normals, open at one planar
    boundary loop at z = base_z, closed at the top; near-equilateral triangles of edge
    about ``edge``. The capsule's is ``scenes.shapes.capsule.mesh``'s exactly.
    """
    return _analytic(family, "membrane").shape_mesh(params, base_z, edge)


__all__ = ["ANALYTIC", "BOUNDS", "DEFAULTS", "FAMILIES", "TABLE_KEYS", "UNITS", "Diagnosis", "Family", "Tube",
           "check_params", "diagnose", "family", "principal_curvatures", "shape_mesh", "tip_start_z"]
