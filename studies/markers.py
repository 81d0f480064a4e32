"""Do printed marker dots matter? The public GelSight presses with dots drawn on them.

Many users' units carry a grid of printed dots (``scenes.markers``); the shared presses
do not. This study draws dots on them, written unlike anything either renderer or the
calibration models (a dark disc that keeps ``1 - DARK`` of the light, on a square grid,
each dot carried outward under a press by a lateral displacement that peaks at the
contact's rim), and runs the fast path's whole chain three ways:

- ``clean``: the presses as published;
- ``kept``: the dotted presses as they are;
- ``kept_clean_depths``: the same, each press given the clean import's depth (what the
  dots do to the calibration and the comparison alone, not to the rims);
- ``inpainted``: the dotted presses with their dots found and filled
  (``tactile-sim import --markers inpaint``).

Each is imported (its rims and depths from its own frames; an import that refuses a
press is recorded with its reason), the fast path calibrated on
its fitted half (``calibrate --fast-only``), and the calibrated fast path compared on the
held-out presses twice: with the frames the calibration saw (what a user of the dotted
unit reads) and with the clean frames at the clean presses' depths (how good the
calibration it gave really is). The JSON holds each contact MAE, the depths' median
difference from the clean import's and the calibration's held-out change R^2.

``python -m studies.markers --json markers.json [--work DIR]`` (about 15 minutes here).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import shutil
import tempfile
import time
from pathlib import Path

import numpy as np

#: The grid of dots (estimates within the range marker gels print: GelSight Mini's 7 x 9
#: dots over its 18.6 x 14.3 mm are 2 mm apart; DIGIT's printed sets 1 to 2 mm): their
#: spacing and diameter, mm, the share of light a dot takes, and how far a dot at the
#: contact's rim moves outward, mm.
SPACING_MM = 1.5
DOT_MM = 0.5
DARK = 0.7
SHIFT_MM = 0.15


def draw_markers(archive, pixel_m: float, spacing_mm: float = SPACING_MM, dot_mm: float = DOT_MM,
                 dark: float = DARK, shift_mm: float = SHIFT_MM):
    """``archive`` (``scenes.press_sets.Archive``) with dots drawn on every frame (module
    doc): on the no-contact frame at the grid, on a press's frame each dot carried outward
    from the annotated centre by shift(r) = SHIFT (r / a) exp((1 - (r / a)^2) / 2), a its
    annotated radius (the most, SHIFT, at the rim). Dots are antialiased discs."""
    h, w = archive.no_contact.shape[:2]
    v, u = np.mgrid[:h, :w].astype(np.float64)
    step, radius = spacing_mm * 1e-3 / pixel_m, dot_mm * 1e-3 / pixel_m / 2
    gu, gv = np.meshgrid(np.arange(step / 2, w, step), np.arange(step / 2, h, step))
    grid = np.stack([gu.ravel(), gv.ravel()], axis=1)

    def dotted(image, centres):
        cover = np.zeros((h, w))
        for cu, cv in centres:
            cover = np.maximum(cover, np.clip(radius + 0.5 - np.hypot(u - cu, v - cv), 0.0, 1.0))
        return image * (1.0 - dark * cover[..., None])

    frames = np.empty_like(archive.frames)
    for i, ((cu, cv), a) in enumerate(zip(archive.centres_px, archive.radii_px)):
        d = grid - (cu, cv)
        r = np.hypot(*d.T)
        s = shift_mm * 1e-3 / pixel_m * (r / a) * np.exp((1 - (r / a) ** 2) / 2)
        moved = grid + d * (s / np.maximum(r, 1e-9))[:, None]
        frames[i] = dotted(archive.frames[i], moved)
    return dataclasses.replace(archive, no_contact=dotted(archive.no_contact, grid), frames=frames,
                               notes={**archive.notes, "markers_drawn": {"spacing_mm": spacing_mm, "dot_mm": dot_mm,
                                                                         "dark": dark, "shift_mm": shift_mm}})


def _contact_mae(table: dict) -> dict:
    rows = [r for r in table["rows"] if r["method"] == "fast"]
    return {"mean": rows[0]["contact"]["mae"]["mean"], "low": rows[0]["contact"]["mae"]["low"],
            "high": rows[0]["contact"]["mae"]["high"], "strength_median": rows[0]["strength"]["median"]}


def run(json_path, work=None, archive=None, progress: bool = False) -> dict:
    """The study (module doc); writes and returns the JSON."""
    from pbr_tactile.calibrate_capture import calibrate_capture
    from phong_reference import plugin as phong
    from scenes.dataset import atomic_write_json, read_samples
    from scenes.imports import import_capture, open_set
    from scenes.markers import remove_markers
    from scenes.profile import load_profile
    from scenes.reference_data import require_taxim_archive
    from scenes.replay import read_capture
    from studies.compare.run import compare

    archive = Path(archive) if archive is not None else require_taxim_archive()
    clean, spec, ball, pixel, _ = open_set(archive)
    marked = draw_markers(clean, pixel)
    f0, frames, found = remove_markers(marked.no_contact, marked.frames, pixel)
    inpainted = dataclasses.replace(marked, no_contact=f0, frames=frames)
    keep = work is not None
    work = Path(work) if keep else Path(tempfile.mkdtemp(prefix="markers-"))
    t0 = time.perf_counter()
    out = {"archive": str(archive), "markers": marked.notes["markers_drawn"], "found": found, "variants": {}}
    try:
        depths = {}
        for name, variant in (("clean", clean), ("kept", marked), ("kept_clean_depths", marked),
                              ("inpainted", inpainted)):
            capture = work / name / "capture"
            if name == "kept_clean_depths":
                variant = dataclasses.replace(variant, depths_m=depths["clean"])
            try:
                import_capture(variant, capture, spec, ball, pixel,
                               depth="given" if name == "kept_clean_depths" else "profile")
            except ValueError as exc:
                out["variants"][name] = {"import_error": str(exc)}
                continue
            depths[name] = np.array([r["measured_depth"] for r in read_samples(capture)])
            cal = work / name / "calibrated"
            calibrate_capture(capture, cal, phong.calibrate, fast_taps=0, fast_only=True, progress=progress)
            profile = cal / "profile.toml"
            field = load_profile(profile, read_capture(capture).spec).phong["field"]
            common = {"profile": profile, "reference": False, "heldout": True, "bootstrap": 2000, "fields": (field,),
                      "progress": progress}
            own = compare(capture, work / name / "compare_own", **common)
            truth = own if name == "clean" else compare(work / "clean" / "capture", work / name / "compare_clean",
                                                        **common)
            report = json.loads((cal / "report.json").read_text())
            out["variants"][name] = {
                "contact_mae_own_frames": _contact_mae(own), "contact_mae_clean_frames": _contact_mae(truth),
                "depth_median_abs_diff_mm": float(np.median(np.abs(depths[name] - depths["clean"])) * 1e3),
                "change_r2_heldout": report["fast_path"]["taps"]["heldout"]["change_r2"]}
        out["seconds"] = time.perf_counter() - t0
        atomic_write_json(Path(json_path), out)
        return out
    finally:
        if not keep:
            shutil.rmtree(work, ignore_errors=True)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m studies.markers", description=__doc__.splitlines()[0])
    p.add_argument("--json", required=True, metavar="OUT.json")
    p.add_argument("--work", metavar="DIR", help="keep the captures, profiles and tables here")
    p.add_argument("--archive", metavar="A", help="the set of presses (default: the public GelSight set)")
    args = p.parse_args(argv)
    out = run(args.json, args.work, args.archive)
    print(json.dumps({k: {m: v.get(m) for m in ("contact_mae_own_frames", "contact_mae_clean_frames",
                                                "depth_median_abs_diff_mm", "import_error")}
                      for k, v in out["variants"].items()}, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
