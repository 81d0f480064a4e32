"""The interface every shape family implements: the names its module defines, and the
closed-form body some families have.

A family is a module of ``scenes.shapes`` (``capsule``, ``thumb``, ``paw``, ``pad``,
``mesh``), registered by its ``NAME`` in ``scenes.shapes.FAMILIES``. Code that depends on
the membrane's shape asks its family (``scenes.shapes.family(spec.membrane.shape)``) and
never compares the name. A ``membrane`` below is a ``scenes.spec.MembraneSpec``: the
families read its fields; the spec, which checks each membrane through its family,
imports them, not the other way.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Protocol

import numpy as np
import trimesh


@dataclass(frozen=True)
class Tube:
    """A body known in closed form: a round membrane of ``radius`` over a round glass tube of
    ``core_radius`` about the tube's axis, from its base at ``base_z`` up to ``junction_z``,
    closed there by concentric hemispheres; tube frame (the axis along +z), metres.

    The elastomer between is ``radius - core_radius`` thick everywhere (:attr:`thickness`):
    no mesh has to be measured to know the body, the glass' bore or the tip's apex.
    """

    radius: float  # m, the membrane's (painted surface's) radius
    core_radius: float  # m, the glass tube's outer radius
    base_z: float  # m, the membrane's open base
    junction_z: float  # m, where the straight tube meets its hemispherical tip

    @property
    def thickness(self) -> float:
        """The elastomer's thickness, metres: radius - core_radius."""
        return self.radius - self.core_radius

    @property
    def apex_z(self) -> float:
        """z of the tip's apex on the axis, metres."""
        return self.junction_z + self.radius


class Family(Protocol):
    """The names a family's module defines (a module is the implementation: its constants and
    functions, ``membrane`` a ``scenes.spec.MembraneSpec``)."""

    #: The shape's name, as a spec's ``membrane.shape`` gives it.
    NAME: str
    #: The [membrane] table's keys that this family alone takes (another family's membrane
    #: refuses them, and leaves them out when written out).
    TABLE_KEYS: tuple[str, ...]
    #: Where its size and its core come from, for messages.
    SIZE_FROM: str
    CORE_FROM: str
    #: Generated in the tube's frame and seated in the camera frame by the camera's
    #: ``offset_m`` and ``tilt_rad``; otherwise already in the camera frame.
    SEATED: bool
    #: The camera must see gel in every pixel (a flat sensor's pad reaches past the view),
    #: rather than see most of the membrane (``scenes.body``).
    FILLS_VIEW: bool
    #: The published GelTip's shape (Gomes, Paoletti, Luo): the paper's protocol (taps by
    #: angle on the tip and back from its junction with the cylinder), its analytic
    #: contacts and its published depth maps and images apply to it.
    PUBLISHED: bool

    #: Its parameters' names, defaults, bounds and units (``scenes.shapes.params``), or
    #: None for a shape read whole from a file (nothing of it can be varied).
    PARAMETERS: object | None
    #: The parts of the image the gap study reports the gap in, this family's own (the area
    #: near the LEDs, every family's, is carved out of the last): a finger's tip and body, a
    #: flat pad's centre and rim.
    REGIONS: tuple[str, ...]

    def regions(self, membrane, points: np.ndarray, inside: np.ndarray) -> dict[str, np.ndarray]:
        """Boolean (H, W) masks named ``REGIONS`` that split ``inside`` (the image circle)
        between them, from ``points`` (H, W, 3): the undeformed membrane's point seen at
        each pixel, camera frame, metres."""

    def membrane_params(self, params: Mapping[str, float], where: str) -> dict[str, float]:
        """The spec's ``[membrane.params]``, filled with defaults and checked; ValueError naming
        ``where`` for a family that takes none and is given some."""

    def check(self, membrane, where: str) -> None:
        """Refuse, naming ``where``, a parsed membrane that breaks the family's own rules
        (which keys it needs, where its core comes from)."""

    def tube(self, membrane) -> Tube | None:
        """The membrane's body in closed form, or None where only ``scenes.body`` can measure
        it (a core derived by offsetting the membrane, or given as a mesh)."""

    def mesh(self, membrane) -> trimesh.Trimesh:
        """The outer membrane surface, metres, normals out, open at its base: in the tube's
        frame when ``SEATED``, otherwise in the camera frame."""


#: Every name a family's module defines: Family's constants and functions.
MEMBERS = tuple(Family.__annotations__) + tuple(n for n, v in vars(Family).items() if callable(v) and n[0] != "_")


#: A finger without a closed-form tip: its tip is this top share of the visible membrane
#: along the sensor's axis.
TIP_SHARE = 0.2
#: A flat pad's centre: this share of the visible membrane nearest the camera's axis.
CENTRE_SHARE = 0.5


def tip_and_body(points: np.ndarray, inside: np.ndarray, start_z: float | None = None) -> dict[str, np.ndarray]:
    """A finger's ``regions``: its tip, where the membrane seen lies at or beyond
    ``start_z`` along the axis (None: the top ``TIP_SHARE`` of the visible membrane), and its
    body, the rest of ``inside``."""
    z = points[..., 2]
    start = np.quantile(z[inside], 1.0 - TIP_SHARE) if start_z is None else start_z
    tip = inside & (z >= start)
    return {"tip": tip, "body": inside & ~tip}


def centre_and_rim(points: np.ndarray, inside: np.ndarray) -> dict[str, np.ndarray]:
    """A flat pad's ``regions``: its centre, the ``CENTRE_SHARE`` of the visible membrane
    nearest the camera's axis, and its rim, the rest of ``inside``."""
    off_axis = np.hypot(points[..., 0], points[..., 1])
    centre = inside & (off_axis <= np.quantile(off_axis[inside], CENTRE_SHARE))
    return {"centre": centre, "rim": inside & ~centre}


def no_params(params: Mapping[str, float], family: str, size_from: str, where: str) -> dict[str, float]:
    """A family that takes no [membrane.params]: none, or ValueError naming ``where``."""
    if params:
        raise ValueError(f"{where}: a {family!r} membrane takes no [membrane.params] (its size is {size_from}); drop "
                         f"{', '.join(map(str, params))}")
    return {}


def needs_thickness(membrane, where: str, core_mesh: bool = False) -> None:
    """Refuse a membrane whose core is derived (or, with ``core_mesh``, given as a mesh)
    that states neither its elastomer's thickness nor, where allowed, its core's mesh, or
    both."""
    if membrane.thickness is None and membrane.core_mesh_path is None:
        raise ValueError(f"{where}: a {membrane.shape!r} membrane needs its elastomer's thickness (thickness, metres)"
                         + (" or its core's mesh (core_mesh_path)" if core_mesh else ""))
    if membrane.thickness is not None and membrane.core_mesh_path is not None:
        raise ValueError(f"{where}: give thickness or core_mesh_path, not both")


def derived_core(check_params: Callable[[Mapping[str, float], str], dict[str, float]],
                 shape_mesh: Callable[[Mapping[str, float], float, float], trimesh.Trimesh]) -> tuple:
    """The interface's ``membrane_params``, ``check``, ``tube`` and ``mesh`` of a family
    whose ``[membrane.params]`` are checked by ``check_params(params, where)``, whose mesh is
    ``shape_mesh(params, base_z, edge)`` in the tube frame, and whose core is derived from
    the elastomer's thickness (so it has no closed-form tube: ``scenes.body`` measures it).
    The thumb, the paw and the pad are such families."""

    def membrane_params(params: Mapping[str, float], where: str) -> dict[str, float]:
        return check_params(params, where)

    def check(membrane, where: str) -> None:
        needs_thickness(membrane, where)

    def tube(membrane) -> None:
        return None

    def mesh(membrane) -> trimesh.Trimesh:
        return shape_mesh(dict(membrane.params), membrane.base_z, membrane.mesh_edge)

    return membrane_params, check, tube, mesh
