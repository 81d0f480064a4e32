"""Study: which unmodelled effects explain the one real GelTip capture we have?

The real no-contact image (``real/bkg.png`` of the published data) is diagnosed against
the fast path's no-contact image of the default GelTip with no background (the light
field as a parameter: the default "plane", and "linear"). There is one image, so the
diagnosis' samples are parts of it: the image circle cut into ``SECTORS`` equal angular
sectors about its centre, alternate sectors for fitting and for judging. "Held-out"
therefore means other parts of the same capture, not other captures.

Run: ``python -m studies.real_background_gap --out DIR [--fields plane,linear]``; it writes
one full diagnosis report per field (``DIR/<field>/report.html``), ``DIR/summary.json``
and ``DIR/summary.md``.
"""

from __future__ import annotations

import argparse
import math
from pathlib import Path

import numpy as np

from scenes.camera import Camera
from scenes.files import write_json
from scenes.images import read_rgb
from scenes.reference_data import REFERENCE_ENV, require_reference_dir
from scenes.spec import SensorSpec
from scenes.spec_read import default_spec

from .gap.diagnose import diagnose
from .gap.effects import EFFECTS
from .gap.fit import PARAM_RESAMPLES
from .gap.model import FastModel
from .gap.pairs import Pairs
from .gap.report import write_report

#: Angular sectors of the image circle; even ones fit, odd ones judge.
SECTORS = 12
#: Effects that act only where a contact deforms the membrane: a no-contact image cannot test them.
CONTACT_ONLY = ("membrane_compliance", "elastic_spread", "contact_shadow")

LIMITS = [
    ("One capture, no contact: membrane_compliance, elastic_spread and contact_shadow act only on contacts and "
    "cannot be tested at all; their 'not significant' here means 'untestable', not 'absent'."),
    ("Held-out samples are other sectors of the same image, so the intervals measure how well an effect fitted on "
    "half of the circle carries to the other half, not to other captures, days or sensors."),
    "With six held-out sectors the bootstrap intervals rest on six numbers: wide and only roughly calibrated.",
    ("Noise cannot be told apart from fixed texture of the paint in a single frame; the noise estimate is an upper "
    "bound on temporal noise."),
    ("Effects that change colour over the whole image (camera_response, led_spectrum, core_light_leak's per-LED "
    "amplitudes) can stand in for each other on one image; their ranking among themselves is weak evidence."),
    ("The published image is already aligned to the simulation by hand (rotated 192 degrees, scaled 1.15, shifted "
    "-20 px), so misalignment measures what that alignment left."),
]


def sector_areas(camera: Camera, sectors: int = SECTORS) -> np.ndarray:
    """(sectors, H, W) bool: equal angular sectors of the image circle about its centre."""
    v, u = np.mgrid[0:camera.height, 0:camera.width]
    cx = camera.cx if camera.mask_cx is None else camera.mask_cx
    cy = camera.cy if camera.mask_cy is None else camera.mask_cy
    angle = np.mod(np.arctan2(v - cy, u - cx), 2 * math.pi)
    index = np.minimum((angle / (2 * math.pi) * sectors).astype(int), sectors - 1)
    return np.stack([(index == k) & camera.mask for k in range(sectors)])


def pairs_for(real: np.ndarray, spec: SensorSpec, field: str, reference_dir: Path) -> Pairs:
    """The one real image against the fast path's no-contact image, as sector samples."""
    renderer = {"renderer": "phong", "field": field, "background": "none", "rectify": False}
    model = FastModel(spec, renderer, 1)
    sim = model.physical(model.ref, {})
    areas = sector_areas(model.camera)
    n = len(areas)
    records = [{"id": f"sector_{k:02d}", "object": f"sector {k}", "path": 0, "position": k,
                "measured_depth": 0.0} for k in range(n)]
    meta = {"renderer": renderer, "source": "sim"}
    return Pairs(reference_dir / "real", Path(f"fast path, {field} field, no background"), {"source": "real"}, meta,
                 [r["id"] for r in records], records, np.repeat(real[None], n, 0).astype(np.float32),
                 np.repeat(sim[None], n, 0).astype(np.float32),
                 np.repeat(model.ref[None], n, 0).astype(np.float32), spec, {"areas": areas})


def run(out: Path, fields: tuple[str, ...] = ("plane", "linear"), reference_dir: Path | None = None,
        spec: SensorSpec | None = None, intervals: int = PARAM_RESAMPLES) -> dict:
    """Diagnose the real image against each field; ``intervals``: bootstrap resamples
    behind the best effects' parameter intervals (``diagnose``), 0 for none."""
    reference_dir = require_reference_dir(reference_dir)
    path = reference_dir / "real" / "bkg.png"
    if not path.exists():
        raise FileNotFoundError(f"the real no-contact image {path} is missing (set ${REFERENCE_ENV})")
    spec = default_spec() if spec is None else spec
    real = read_rgb(path, (spec.camera.height, spec.camera.width))
    summary = {"image": str(path), "sectors": SECTORS, "limits": LIMITS, "fields": {}}
    for field in fields:
        pairs = pairs_for(real, spec, field, reference_dir)
        train = np.arange(len(pairs)) % 2 == 0
        report, artefacts = diagnose(pairs, sides=(train, ~train), factor=2, intervals=intervals)
        report["study"] = {"what": "one real no-contact image against the fast path's, sectors as samples",
                           "limits": LIMITS, "contact_only_untestable": list(CONTACT_ONLY)}
        write_report(out / field, report, artefacts)
        summary["fields"][field] = {
            "gap_masked_mae": report["gap"]["heldout"]["masked"]["mae"],
            "ranking": report["ranking"],
            "single": {n: {"share": report["effects"][n]["share_closed"]["masked"],
                           "low": report["effects"][n]["heldout"]["improvement"]["masked"]["mae"]["share_low"],
                           "high": report["effects"][n]["heldout"]["improvement"]["masked"]["mae"]["share_high"],
                           "significant": report["effects"][n]["significant"],
                           "params": report["effects"][n]["params"][n]} for n in report["effects"]},
            "selected": report["explained"]["effects"],
            "share_closed": report["explained"]["share_closed"],
            "after_masked_mae": (report["selection"][-1]["heldout"]["after"]["masked"]["mae"]
                                 if report["selection"] else report["gap"]["heldout"]["masked"]["mae"]),
            "noise_std": report["noise"]["std"],
        }
    write_json(out / "summary.json", summary)
    (out / "summary.md").write_text(markdown(summary))
    return summary


def markdown(summary: dict) -> str:
    lines = ["# Which effects explain the real GelTip background?", "",
             (f"Real image: `{summary['image']}`; {summary['sectors']} angular sectors of the image circle, "
             "alternate ones fitted and judged."), ""]
    for field, r in summary["fields"].items():
        g = r["gap_masked_mae"]
        lines += [f"## Fast path with the {field} field, no background", "",
                  f"- Held-out gap: masked MAE {g['mean']:.4f} [{g['low']:.4f}, {g['high']:.4f}].",
                  f"- Ranked (significant) effects: {', '.join(r['ranking']) or 'none'}.",
                  (f"- Selected combination: {' + '.join(r['selected']) or 'none'}, closing "
                  f"{r['share_closed']['masked'] * 100:.1f}% of the held-out gap "
                  f"(MAE after {r['after_masked_mae']['mean']:.4f})."), "",
                  "| effect | share of gap closed alone (95% CI) | significant |", "|---|---|---|"]
        for name in EFFECTS:
            s = r["single"].get(name)
            if s is None:
                continue
            note = " (untestable without contact)" if name in CONTACT_ONLY else ""
            lines.append(f"| {name}{note} | {s['share'] * 100:.1f}% [{s['low'] * 100:.1f}, {s['high'] * 100:.1f}] | "
                         f"{'yes' if s['significant'] else 'no'} |")
        lines.append("")
    lines += ["## What one image can and cannot tell", ""] + [f"- {x}" for x in summary["limits"]]
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--fields", default="plane,linear", help="comma-separated light fields")
    args = parser.parse_args(argv)
    summary = run(args.out, tuple(f for f in args.fields.split(",") if f))
    print(markdown(summary))
    return summary


if __name__ == "__main__":
    main()
