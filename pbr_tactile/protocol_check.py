"""Every tap of a tapping protocol as an elastomer solid: does the reference render it?

Each tap is pressed on the MuJoCo rig (as dataset generation does), its depth map
captured, and the dented elastomer built (pbr_tactile.membrane.ElastomerBuilder), which
checks that it is closed, does not fold and does not cross itself. A tap whose solid
cannot be built is reported with the error that refused it.
"""

from __future__ import annotations

import time

import numpy as np

from scenes.camera import Camera
from scenes.elastic import LAYER_EDGE_M
from scenes.geometry import membrane_mesh
from scenes.protocol_checks import validate
from scenes.spec import SensorSpec
from scenes.taps import Protocol, Tap

from .membrane import ElastomerBuilder


def sample_taps(protocol: Protocol, count: int, seed: int) -> list[Tap]:
    """A seeded sample of ``count`` distinct taps (all of them when there are fewer), in
    protocol order."""
    if count < 1:
        raise ValueError(f"sample count must be >= 1, got {count}")
    taps = protocol.taps
    if count >= len(taps):
        return list(taps)
    chosen = np.sort(np.random.default_rng(seed).choice(len(taps), size=count, replace=False))
    return [taps[i] for i in chosen]


def check_taps(spec: SensorSpec, taps: list[Tap], edge: float = LAYER_EDGE_M, progress: bool = False) -> list[dict]:
    """Build the elastomer solid of each tap; one record per tap.

    Returns dicts with ``tap_index``, ``object``, ``ok``, ``error`` (None or the message),
    ``max_displacement`` (metres, inwards along the normal), ``deformation_seconds``.
    """
    from tqdm import tqdm

    from scenes.rig import tap_depths

    mesh = membrane_mesh(spec)
    captures = tap_depths(spec, taps, mesh)
    ref, _ = next(captures)
    build = ElastomerBuilder(mesh, spec, Camera.from_spec(spec), edge)
    records = []
    for depth, tap in tqdm(captures, total=len(taps), desc="solids", unit="tap", disable=not progress):
        t0 = time.perf_counter()
        try:
            solid = build(depth, ref)
            error = None
            displacement = float(np.linalg.norm(solid.outer.vertices - build.layer.vertices, axis=1).max())
        except ValueError as exc:
            error, displacement = str(exc), float("nan")
        records.append({"tap_index": tap.index, "object": tap.object, "ok": error is None, "error": error,
                        "max_displacement": displacement, "deformation_seconds": time.perf_counter() - t0})
    return records


def check_protocol(spec: SensorSpec, protocol: Protocol, sample: int | None = None, seed: int = 0,
                   edge: float = LAYER_EDGE_M, progress: bool = False) -> dict:
    """Check a protocol (validated first), or a seeded sample of its taps; a summary dict
    with every tap's record."""
    validate(protocol, spec, membrane_mesh(spec))
    taps = list(protocol.taps) if sample is None else sample_taps(protocol, sample, seed)
    t0 = time.perf_counter()
    records = check_taps(spec, taps, edge, progress)
    seconds = [r["deformation_seconds"] for r in records]
    return {
        "protocol": protocol.name,
        "protocol_seed": protocol.seed,
        "sample_seed": seed if sample is not None else None,
        "taps": len(records),
        "built": sum(r["ok"] for r in records),
        "refused": [r for r in records if not r["ok"]],
        "edge_m": edge,
        "median_build_seconds": float(np.median(seconds)) if seconds else None,
        "seconds": time.perf_counter() - t0,
        "records": records,
    }
