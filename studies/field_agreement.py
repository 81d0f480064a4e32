"""Agreement of our baked light fields with the authors' published ones, in degrees.

Bakes our four fields at the authors' 160x120 on our generated membrane mesh and, per
method and LED, reports the angle between our propagation direction and theirs
(``light_fields/<method>_160x120_field_<i>.npy``) at the pixels inside their r = 60 px
mask where both are valid. Their geodesic field is one mesh edge long, not unit, so both
are normalised first. A second pair of columns compares the tangent parts: theirs (and,
for linear, ours too, which is not tangent) projected onto our undeformed surface's
tangent plane and renormalised; our plane, geodesic and transport fields are tangent
already, so for them only theirs changes.

Run ``python -m studies.field_agreement``.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from phong_reference.bake import METHODS, bake
from phong_reference.tangent import angle_deg, tangent_unit
from scenes.camera import Camera
from scenes.geometry import membrane_mesh
from scenes.reference_data import REFERENCE_ENV, require_reference_dir
from scenes.spec import SensorSpec
from scenes.spec_read import default_spec

from .reproduce_published import BAKED_SHAPE, load_published_fields

#: Radius of the authors' field mask at 160x120, px. OpenCV's circle centred on the
#: integer pixel (W / 2, H / 2) = (80, 60), not on our principal point (79.5, 59.5): that
#: circle is exactly the non-zero set of their linear and geodesic fields.
PUBLISHED_MASK_RADIUS_PX = 60
#: Below this length a (projected) vector has no direction.
MIN_NORM = 1e-12


def published_mask(shape: tuple[int, int] = BAKED_SHAPE, radius: float = PUBLISHED_MASK_RADIUS_PX) -> np.ndarray:
    """(H, W) bool: the authors' circle, centred on pixel (W // 2, H // 2)."""
    h, w = shape
    v, u = np.mgrid[0:h, 0:w]
    return (u - w // 2) ** 2 + (v - h // 2) ** 2 <= radius**2


def unit(v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(..., 3) -> unit vectors (zero where undefined) and the (...) mask where defined."""
    n = np.linalg.norm(v, axis=-1, keepdims=True)
    ok = n[..., 0] > MIN_NORM
    return np.divide(v, n, out=np.zeros_like(v, dtype=np.float64), where=n > MIN_NORM), ok


def led_agreement(ours: np.ndarray, our_valid: np.ndarray, theirs: np.ndarray, normals: np.ndarray,
                  mask: np.ndarray, project_ours: bool) -> dict[str, float]:
    """Angular difference of one LED's fields (H, W, 3) inside ``mask`` where both are valid."""
    if ours.shape != theirs.shape or ours.shape[:2] != mask.shape:
        raise ValueError(
            f"fields must be (H, W, 3) of the mask's shape {mask.shape}, got {ours.shape} and {theirs.shape}"
        )
    a, ok_a = unit(ours)
    b, ok_b = unit(theirs)
    both = mask & our_valid & ok_a & ok_b
    raw = angle_deg(a, b)[both]
    ta, ok_ta = tangent_unit(np.asarray(ours, np.float64), normals) if project_ours else (a, ok_a)
    tb, ok_tb = tangent_unit(np.asarray(theirs, np.float64), normals)
    both_t = both & ok_ta & ok_tb
    projected = angle_deg(ta, tb)[both_t]
    return {
        "pixels": int(both.sum()),
        "mean_deg": float(raw.mean()),
        "median_deg": float(np.median(raw)),
        "p95_deg": float(np.percentile(raw, 95)),
        "tangent_mean_deg": float(projected.mean()),
        "tangent_median_deg": float(np.median(projected)),
        "their_median_abs_dot_n": float(np.median(np.abs(np.einsum("...i,...i->...", b, normals))[both])),
        "our_median_abs_dot_n": float(np.median(np.abs(np.einsum("...i,...i->...", a, normals))[both])),
    }


def method_agreement(reference_dir: Path, method: str, mesh, camera: Camera, spec: SensorSpec) -> list[dict]:
    """Per-LED agreement of one method (ours baked at ``camera``, 160x120)."""
    ours = bake(mesh, camera, spec.leds, method)
    theirs = load_published_fields(reference_dir, method)
    mask = published_mask(camera.shape)
    normals = np.asarray(ours.normals, dtype=np.float64)
    return [
        led_agreement(ours.fields[i], ours.valid[i], theirs[i], normals, mask, project_ours=method == "linear")
        for i in range(len(theirs))
    ]


def run(reference_dir: Path, spec: SensorSpec | None = None, methods=METHODS) -> dict:
    spec = spec or default_spec()
    camera = Camera.from_spec(spec).scaled(BAKED_SHAPE[1], BAKED_SHAPE[0])
    mesh = membrane_mesh(spec)
    results = {}
    for method in methods:
        try:
            results[method] = method_agreement(reference_dir, method, mesh, camera, spec)
        except Exception as exc:  # a baker still being written must not hide the others
            results[method] = {"error": f"{type(exc).__name__}: {exc}"}
    return results


def print_report(results: dict) -> None:
    head = (f"{'method':<10} {'LED':>3} {'pixels':>7} {'mean°':>7} {'median°':>8} {'p95°':>6}  "
            f"{'tan mean°':>9} {'tan med°':>8}  {'|th.N|':>6} {'|our.N|':>7}")
    print(head)
    print("-" * len(head))
    for method, rows in results.items():
        if isinstance(rows, dict):
            print(f"{method:<10} failed: {rows['error']}")
            continue
        for i, r in enumerate(rows):
            print(f"{method:<10} {i:>3} {r['pixels']:>7} {r['mean_deg']:7.3f} {r['median_deg']:8.3f} "
                  f"{r['p95_deg']:6.2f}  {r['tangent_mean_deg']:9.3f} {r['tangent_median_deg']:8.3f}  "
                  f"{r['their_median_abs_dot_n']:6.3f} {r['our_median_abs_dot_n']:7.3f}")
    print("Angles between unit propagation directions inside the authors' r=60 px mask (160x120);\n"
          "tan: theirs (and ours for linear) projected onto our tangent plane first; |.N|: median\n"
          "|unit field . our surface normal|.")


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--reference", type=Path,
                        help=f"the authors' data (default ${REFERENCE_ENV} or ../shared/data/geltip_reference)")
    parser.add_argument("--json", type=Path, help="also write the numbers here")
    args = parser.parse_args(argv)
    try:
        args.reference = require_reference_dir(args.reference)
    except FileNotFoundError as exc:
        parser.error(f"{exc}; or pass --reference")
    results = run(args.reference)
    print_report(results)
    if args.json:
        args.json.write_text(json.dumps(results, indent=2))
    return results


if __name__ == "__main__":
    main()
