"""The rig's safety envelope: where the indenter may go, checked before anything is sent.

Three limits, each from the rig's layout or the sensor's spec:

- the build volume: every head position lies within the printer's reach
  (``RigLayout.travel``, printer coordinates ``[0, travel]``);
- the bed: no part of the indenter goes below the bed's top (:data:`BED_TOP_M`, world z);
- the membrane: the indenter presses into the membrane at most the spec's safe depth
  (``scenes.protocol_checks.max_safe_depth_m``: the membrane's thickness, past which it would
  press on the glass core) and only on a press; on every other move it stays
  :data:`CLEARANCE_M` clear of it.

A move is checked along its whole straight path, sampled every :data:`SWEEP_STEP_M`, with
the indenter's mesh at each sample. How far an indenter vertex is inside the membrane is
measured against the membrane's nearest vertex along that vertex's normal: on a mesh
whose vertices are :math:`h` apart, on a surface of radius :math:`R`, this errs by about
:math:`h^2 / 8R` (a few micrometres on the GelTip), and it stays right on a membrane
open at its base, where an inside/outside test does not.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from scipy.spatial import cKDTree

from scenes.errors import TactileSimError
from scenes.kinematics import RigLayout, indenter_to_world, sensor_to_world

#: The indenter keeps at least this far from the membrane except while pressing, metres.
CLEARANCE_M = 0.001
#: World z of the bed's top (the MuJoCo rig's bed is a 4 mm half-thick box at z = 0).
BED_TOP_M = 0.004
#: Moves are checked at samples this far apart along their path, metres.
SWEEP_STEP_M = 0.001
#: A press may go this much past the spec's safe depth, to the envelope's own error
#: (the nearest-vertex estimate above), metres.
DEPTH_TOLERANCE_M = 2e-5
#: Vertices farther than this from the membrane's nearest vertex are not measured, metres.
NEAR_M = 0.01


class EnvelopeError(TactileSimError, ValueError):
    """A move that would leave the safety envelope; nothing was sent."""


@dataclass
class SafetyEnvelope:
    """The envelope of one rig and sensor.

    Parameters
    ----------
    layout : RigLayout, the rig's geometry and the printer's reach.
    membrane : trimesh.Trimesh, the membrane in the sensor frame, metres.
    indenters : name -> (V, 3) the indenter meshes' vertices, metres (feature along +z).
    max_indentation_m : the deepest press allowed (``max_safe_depth_m(spec)``).
    """

    layout: RigLayout
    membrane: object
    indenters: dict[str, np.ndarray]
    max_indentation_m: float
    clearance_m: float = CLEARANCE_M
    bed_top_m: float = BED_TOP_M
    _tree: cKDTree = field(init=False, repr=False)

    def __post_init__(self):
        if not (math.isfinite(self.max_indentation_m) and self.max_indentation_m > 0):
            raise ValueError(f"max_indentation_m must be > 0 metres, got {self.max_indentation_m!r}")
        self._points = np.asarray(self.membrane.vertices, dtype=np.float64)
        self._normals = np.asarray(self.membrane.vertex_normals, dtype=np.float64)
        self._tree = cKDTree(self._points)
        centre = self._points.mean(axis=0)
        self._centre, self._radius = centre, float(np.linalg.norm(self._points - centre, axis=1).max())
        self.indenters = {name: np.asarray(v, dtype=np.float64) for name, v in self.indenters.items()}

    @classmethod
    def for_sensor(cls, spec, membrane, indenters: dict[str, np.ndarray], layout: RigLayout = RigLayout(),
                   **kwargs) -> SafetyEnvelope:
        """The envelope of a sensor spec: its safe depth is the deepest press."""
        from scenes.protocol_checks import max_safe_depth_m

        return cls(layout, membrane, indenters, max_safe_depth_m(spec), **kwargs)

    # ----------------------------------------------------------------- measures

    def indenter_in_world(self, name: str, head, pitch: float) -> np.ndarray:
        """(V, 3) the indenter's vertices in the world frame, metres."""
        if name not in self.indenters:
            raise EnvelopeError(f"indenter {name!r} is not in the envelope; it has {sorted(self.indenters)}")
        R, t = indenter_to_world(head, pitch, self.layout)
        return self.indenters[name] @ R.T + t

    def indentation(self, name: str, head, pitch: float, roll: float, world: np.ndarray | None = None) -> float:
        """How deep the indenter is in the membrane, metres: > 0 inside, < 0 the gap to it
        (at most ``NEAR_M`` is measured: ``-NEAR_M`` means farther). ``world``: its
        vertices (:meth:`indenter_in_world`), when already at hand."""
        world = self.indenter_in_world(name, head, pitch) if world is None else world
        points = (world - np.asarray(self.layout.sensor_origin)) @ sensor_to_world(roll)
        near = np.linalg.norm(points - self._centre, axis=1) < self._radius + NEAR_M
        if not near.any():
            return -NEAR_M
        points = points[near]
        distance, nearest = self._tree.query(points, distance_upper_bound=NEAR_M)
        found = np.isfinite(distance)
        if not found.any():
            return -NEAR_M
        nearest = nearest[found]
        depth = np.einsum("ij,ij->i", self._points[nearest] - points[found], self._normals[nearest])
        return float(max(depth.max(), -NEAR_M))

    # ----------------------------------------------------------------- checks

    def check_head(self, head, where: str) -> None:
        """EnvelopeError unless the head position (3,) world metres is in the printer's reach."""
        head = np.asarray(head, dtype=np.float64)
        if head.shape != (3,) or not np.all(np.isfinite(head)):
            raise EnvelopeError(f"{where}: head position must be 3 finite metres, got {head.tolist()}")
        travel = self.layout.travel
        for axis, value, (lo, hi) in zip("xyz", head, travel):
            if not lo - 1e-9 <= value <= hi + 1e-9:
                printer = self.layout.printer_position(head)
                raise EnvelopeError(
                    f"{where}: the head would go to {axis} = {value:.4f} m (printer {axis.upper()}"
                    f"{printer['xyz'.index(axis)] * 1e3:.1f} mm), outside the build volume "
                    f"[{lo:.4f}, {hi:.4f}] m")

    def check_pose(self, name: str, head, pitch: float, roll: float, where: str, press: bool = False) -> float:
        """EnvelopeError unless the indenter at this pose is in the envelope; returns its
        indentation (metres, :meth:`indentation`)."""
        self.check_head(head, where)
        world = self.indenter_in_world(name, head, pitch)
        lowest = float(world[:, 2].min())
        if lowest < self.bed_top_m:
            raise EnvelopeError(f"{where}: the {name} indenter would reach z = {lowest * 1e3:.1f} mm, below the bed's "
                                f"top at {self.bed_top_m * 1e3:.1f} mm")
        depth = self.indentation(name, head, pitch, roll, world)
        if press:
            if depth > self.max_indentation_m + DEPTH_TOLERANCE_M:
                raise EnvelopeError(
                    f"{where}: the {name} indenter would press {depth * 1e3:.3f} mm into the membrane, deeper "
                    f"than the safe {self.max_indentation_m * 1e3:.3f} mm (the membrane's thickness)")
        elif depth > -self.clearance_m:
            what = f"{depth * 1e3:.3f} mm into" if depth > 0 else f"{-depth * 1e3:.3f} mm from"
            raise EnvelopeError(f"{where}: the {name} indenter would come {what} the membrane on a move that is not "
                                f"a press (it must stay {self.clearance_m * 1e3:.1f} mm clear)")
        return depth

    def check_move(self, name: str, start, end, pitch: float, roll: float, where: str, press: bool = False) -> None:
        """EnvelopeError unless every point of the straight move from ``start`` to ``end``
        (head positions, world metres) keeps the indenter in the envelope. On a press only
        its end may touch the membrane, at most the safe depth in."""
        start, end = np.asarray(start, dtype=np.float64), np.asarray(end, dtype=np.float64)
        self.check_head(start, where)
        self.check_head(end, where)
        length = float(np.linalg.norm(end - start))
        samples = max(int(math.ceil(length / SWEEP_STEP_M)), 1)
        for k in range(samples + 1):
            head = start + (end - start) * (k / samples)
            self.check_pose(name, head, pitch, roll, where, press=press)
