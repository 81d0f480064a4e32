"""Light sources of the fast path: LEDs snapped onto the membrane mesh."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import trimesh

from scenes.spec import LED

#: An LED farther than this from the membrane is not "at the membrane's base".
LED_SNAP_TOLERANCE_M = 0.002


@dataclass(frozen=True)
class Sources:
    """LEDs as field sources.

    positions : (L, 3) float64, metres, the LEDs' own positions (camera frame).
    vertices : (L,) int, the mesh vertex nearest each LED, where surface fields start.
    directions : (L, 3) float64, unit emission directions projected onto the tangent
        plane at that vertex (the direction transported by the transport method).
    normals : (L, 3) float64, unit outward surface normal at that vertex.
    """

    positions: np.ndarray
    vertices: np.ndarray
    directions: np.ndarray
    normals: np.ndarray

    def __len__(self) -> int:
        return len(self.vertices)


#: An LED whose light a field takes straight from its own place (``linear``) may sit
#: anywhere within this of the membrane (a sensor's size: farther is a unit mistake).
FREE_SOURCE_TOLERANCE_M = 0.1


def snap_leds(mesh: trimesh.Trimesh, leds: tuple[LED, ...] | list[LED],
              tolerance: float = LED_SNAP_TOLERANCE_M) -> Sources:
    """Snap each LED to its nearest membrane vertex; refuse LEDs farther than ``tolerance``
    metres from the surface (the surface fields start where the LED sits on it)."""
    if len(leds) == 0:
        raise ValueError("leds must hold at least one LED")
    positions = np.array([led.position for led in leds], dtype=np.float64)
    dist, vertices = mesh.kdtree.query(positions)
    for led, d in zip(leds, dist):
        if d > tolerance:
            raise ValueError(
                f"LED {led.name!r} at {led.position} m is {d * 1e3:.2f} mm from the membrane mesh; "
                f"expected within {tolerance * 1e3:g} mm"
                + (" (LEDs sit at the membrane's edge)" if tolerance == LED_SNAP_TOLERANCE_M else "")
            )
    normals = np.asarray(mesh.vertex_normals)[vertices]
    directions = np.array([led.direction for led in leds], dtype=np.float64)
    directions = directions - (directions * normals).sum(axis=1, keepdims=True) * normals
    norm = np.linalg.norm(directions, axis=1)
    for led, n in zip(leds, norm):
        if n < 1e-6:
            raise ValueError(f"LED {led.name!r}: emission direction is normal to the membrane; no tangent part")
    return Sources(positions, np.asarray(vertices), directions / norm[:, None], normals)


def check_sources(sources: Sources, n_vertices: int) -> None:
    """Refuse sources that do not index the mesh (a ValueError naming the bad entry)."""
    vertices = np.asarray(sources.vertices)
    if vertices.ndim != 1 or vertices.dtype.kind not in "iu":
        raise ValueError(f"sources.vertices must be (L,) int, got {vertices.shape} {vertices.dtype}")
    bad = np.flatnonzero((vertices < 0) | (vertices >= n_vertices))
    if len(bad):
        m = int(bad[0])
        raise ValueError(
            f"sources.vertices[{m}] = {int(vertices[m])} is out of range for a mesh of "
            f"{n_vertices} vertices; expected 0 <= index < {n_vertices}"
        )


def bake_per_source(sources: Sources, n_vertices: int, normals: np.ndarray, field_of) -> tuple[np.ndarray, np.ndarray]:
    """A light field baked one source at a time (a baker's ``bake``): ``field_of(m)`` gives
    source m's raw directions at the K samples (K, 3) and where they hold (K,) bool; each
    is projected onto the tangent plane of the samples' unit ``normals`` (K, 3) and made
    unit (``tangent_unit``). Returns fields (L, K, 3), zero where invalid, and valid
    (L, K) bool. The sources are checked against the mesh's ``n_vertices`` first."""
    from .tangent import tangent_unit

    check_sources(sources, n_vertices)
    L, K = len(sources), len(normals)
    fields = np.zeros((L, K, 3))
    valid = np.zeros((L, K), dtype=bool)
    for m in range(L):
        raw, ok = field_of(m)
        t, tangent = tangent_unit(raw, normals)
        ok = ok & tangent
        fields[m, ok] = t[ok]
        valid[m] = ok
    return fields, valid
