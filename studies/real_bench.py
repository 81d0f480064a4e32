"""``tactile-sim bench real``: a real capture of ball presses, end to end.

One command runs what the public GelSight presses are for (issue "real contacts, end to
end"), on the shared set by default or on another unit's set of the same layout:

1. ``import``: the archive as a capture dataset (``scenes.imports``);
2. ``calibrate``: the fast path alone on the capture's fitted half (its even presses;
   ``--fast-only``, every press: the LED constants, places and spread per light field),
   and the reference (its profile, from the no-contact frame and ``--reference-taps`` of
   the presses, fitted and judged in turn);
3. ``compare --heldout``: both renderers, uncalibrated (every light field and
   background, the reference on ``--reference-presses`` of the held-out presses) and
   calibrated, with Taxim beside them (``--peers taxim``: its shipped calibration and a
   refit on the fitted half), on the held-out presses: MAE, SSIM and PSNR over the frame
   and the contact, the contact strength;
4. ``diagnose --split alternate``: the capture against the calibrated fast path's replay
   of it (the reference's with ``--reference-diagnosis``, which renders for an hour here);
5. the sim-to-real localisation study (``studies.sim2real.presses``).

It writes the goals' figures (module doc of the issue): ``contact_strength.phong`` and
``.pbr`` (the calibrated renderers' median over the held-out presses of simulated over
real), ``contact_mae.phong``, ``.pbr`` and ``.taxim`` (the mean over them of the
contact's MAE; ``taxim`` is the refit on the same fitted half, ``taxim_shipped`` the
shipped table), ``localisation_mm.none``, ``.randomised`` and ``.diagnosed`` (the
median error on the real held-out presses, each model calibrated by its constant offset
on the real fitted half; ``localisation_mm_no_offset`` the same without it), and ``seconds`` (import, both calibrations
and the comparisons together), each with its interval and what it was measured on, and
the per-stage seconds. Each renderer's figure in ``detail`` carries its ``contrast``
(``studies.compare.run.contrast_budget``): its strength split per channel into the
camera's share (the level ratio), the light's (the relative-change ratio) and what no
camera fitted to the no-contact image can change (the change over the frame's spread).
"""

from __future__ import annotations

import contextlib
import functools
import json
import os
import shutil
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

#: The reference's share of the work, by default: grid points of its calibration (one),
#: taps it fits and judges, and held-out presses it renders. The grid's point is a clear
#: elastomer: GelSights cast clear silicone under their paint (Yuan et al. 2017), and
#: Agarwal et al.'s physically based GelSight has no scattering medium; the default
#: effects' 50 /m of scattering is the GelTip's estimate. The absorption is the default's.
REFERENCE_GRID = ("absorption_per_m=20", "scattering_per_m=0")
REFERENCE_TAPS = 6
REFERENCE_PRESSES = 4
#: Simulated presses of the localisation study.
LOCALISATION_PRESSES = 1200


def _row(table: dict, method: str, **match) -> dict | None:
    for r in table["rows"]:
        if r["method"] == method and all(r.get(k) == v for k, v in match.items()):
            return r
    return None


def _paired(a: dict, b: dict, scope: str = "contact") -> dict:
    """Mean of per-press MAE differences a - b over the presses both rows scored, with a
    95 % bootstrap interval (``scenes.image_stats.bootstrap_interval``)."""
    from scenes.image_stats import bootstrap_interval

    ia, ib = {i: k for k, i in enumerate(a["ids"])}, {i: k for k, i in enumerate(b["ids"])}
    common = [i for i in a["ids"] if i in ib]
    diff = np.array([a["per_tap"][scope]["mae"][ia[i]] - b["per_tap"][scope]["mae"][ib[i]] for i in common])
    return {**bootstrap_interval(diff), "presses": len(common)}


def _fresh_cache(folder: Path):
    """Renders and bases cached in ``folder`` (emptied first) for the duration: a run of
    the reference's calibration that reuses nothing of another's."""
    from unittest import mock

    from scenes.cache import CACHE_ENV

    shutil.rmtree(folder, ignore_errors=True)
    folder.mkdir(parents=True)
    return mock.patch.dict(os.environ, {CACHE_ENV: str(folder)})


def _run_figures(folder: Path, table: dict | None) -> dict:
    """One run of the reference's calibration and comparison: its no-contact image's
    held-out R^2 per channel, and the calibrated reference's contact MAE and strength on
    the held-out presses."""
    report = folder / "report.json"
    r2 = json.loads(report.read_text()).get("heldout_r2") if report.is_file() else None
    row = _row(table, "reference") if table is not None else None
    return {"heldout_r2": r2, "contact_mae": row["contact"]["mae"]["mean"] if row else None,
            "strength_median": row["strength"]["median"] if row else None}


#: Three runs of one calibration agree when their held-out R^2 lie within this in every
#: channel and their contact MAE within this share of its mean (issue "the reference lit
#: as the real unit is").
AGREE_R2 = 0.03
AGREE_MAE_SHARE = 0.05


def _spread(runs: list[dict]) -> dict:
    """The runs' spread: the range of the held-out R^2 per channel, of the contact MAE
    (also over its mean) and of the strength, and whether they agree (AGREE_R2,
    AGREE_MAE_SHARE)."""
    done = [r for r in runs if r["heldout_r2"] is not None and r["contact_mae"] is not None]
    if len(done) < 2:
        return {"runs": len(done), "agree": None, "why": "fewer than two runs finished"}
    r2 = {ch: max(r["heldout_r2"][ch] for r in done) - min(r["heldout_r2"][ch] for r in done) for ch in "rgb"}
    mae = [r["contact_mae"] for r in done]
    share = (max(mae) - min(mae)) / float(np.mean(mae))
    strength = [r["strength_median"] for r in done]
    return {"runs": len(done), "heldout_r2_range": r2, "contact_mae_range": max(mae) - min(mae),
            "contact_mae_range_share": share, "strength_range": max(strength) - min(strength),
            "agree": bool(max(r2.values()) <= AGREE_R2 and share <= AGREE_MAE_SHARE),
            "rule": f"held-out R^2 within {AGREE_R2} in every channel, contact MAE within {AGREE_MAE_SHARE:.0%}"}


def _layout_report(path: Path) -> dict | None:
    """The reference calibration's fitted layout (its report's ``layout``: the starts'
    losses, the layout found, renders and seconds), or None where it fitted none."""
    if not path.is_file():
        return None
    layout = json.loads(path.read_text()).get("layout")
    return None if layout is None else {k: v for k, v in layout.items() if k != "steps"}


def _figure(row: dict | None) -> dict | None:
    if row is None:
        return None
    return {"label": row["label"], "presses": row["taps"], "contact_mae": row["contact"]["mae"],
            "strength_median": row["strength"]["median"],
            "strength_mean": {k: row["strength"][k] for k in ("mean", "low", "high")},
            "full_mae": row["full"]["mae"], "contrast": row.get("contrast")}


def run(json_path, archive=None, spec=None, ball_mm=None, pixel_mm=None, work=None, reference: bool = True,
        reference_diagnosis: bool = False, localisation: bool = True, quiet: bool = True,
        rim_share: float | None = None, grid: tuple[str, ...] = REFERENCE_GRID, camera_known: bool = True,
        reference_presses: int = REFERENCE_PRESSES, fit_layout: bool = False, runs: int = 1,
        depth: str | None = None, diagnosis_on: bool = True, fmt: str | None = None, turn: str | None = None,
        markers: str | None = None, diagnosis_presses: int | None = None) -> dict:
    """The benchmark (module doc); writes and returns the JSON. ``archive``: any set of
    presses ``tactile-sim import`` reads (a Taxim pack, or a folder of presses), with its
    ``fmt``, ``spec``, ``ball_mm``, ``pixel_mm``, ``turn`` and ``markers`` as given, else as its records
    beside it say, else the format's defaults (``scenes.imports.open_set``). ``grid``: the reference
    calibration's grid (``calibrate --grid``); ``camera_known``: its alignment held at the
    spec's camera (``calibrate --camera-known``: the public set's spec is written from its
    camera's record), else searched; ``reference_presses``: the held-out presses the
    reference renders, spread evenly over them (all when it is at least their count), so
    that a strength near a goal's bound can be confirmed on more than the default's few;
    ``fit_layout``: the reference's calibration fits its LEDs' layout first
    (``calibrate --fit-layout``), from the spec's, the fast path's fitted places (its
    calibration's report) and a coarse grid under the plate, on the no-contact frame and
    the presses, with each LED's gains through its film response (``--spectral-gains``) and
    the camera's response held to a webcam's (``--webcam-response``);
    ``depth``: how the import gives each press its depth (``tactile-sim import --depth``;
    default: the set's own where it gives every press one, else ``profile``:
    ``elastic``, from the spec's layer, gives ours and Taxim the same physical depths;
    ``fitted``: the bonded layer and the fitted half's depths fitted together
    (``phong_reference.elastic_fit``, from the spec's layer's depths and the fast path
    calibrated at them), the capture imported again at those depths, the fast path
    calibrated under that layer; Taxim's ``refit_share`` row chooses its own depth
    setting, a rim share, on the fitted half);
    ``diagnosis_on``: diagnose the capture against the calibrated fast path's replay (the
    localisation study needs it); ``diagnosis_presses``: the calibrated reference's replay
    and its diagnosis (``reference_diagnosis``) take this many presses, spread evenly over
    the capture (all when None or at least their count: each is a reference render at the
    capture's size, about a minute and a half here);
    ``runs``: the reference's calibration and its calibrated comparison run this many times,
    each from an empty cache (every render anew, the same seeds), and the JSON's
    ``reference_runs`` holds each run's figures and their spread (``_spread``)."""
    if isinstance(reference_presses, bool) or not isinstance(reference_presses, (int, np.integer)) \
            or reference_presses < 1:
        raise ValueError(f"reference_presses must be a whole number >= 1, got {reference_presses!r}")
    if diagnosis_presses is not None and (isinstance(diagnosis_presses, bool) or not isinstance(
            diagnosis_presses, (int, np.integer)) or diagnosis_presses < 4):
        raise ValueError(f"diagnosis_presses must be a whole number >= 4 (half are held out), got {diagnosis_presses!r}")
    if isinstance(runs, bool) or not isinstance(runs, (int, np.integer)) or runs < 1:
        raise ValueError(f"runs must be a whole number >= 1, got {runs!r}")
    if localisation and not diagnosis_on:
        raise ValueError("the localisation study uses the diagnosis: --no-diagnosis needs --no-localisation")
    if runs > 1 and not reference:
        raise ValueError("runs repeats the reference's calibration: it needs the reference (no --no-reference)")
    from pbr_tactile.calibrate_capture import calibrate_capture
    from phong_reference import plugin as phong
    from scenes.errors import REPORTED
    from scenes.settings import name_values
    from scenes.dataset import atomic_write_json
    from scenes.imports import default_depth, import_capture, open_set
    from scenes.reference_data import require_taxim_archive
    from studies.compare.run import compare
    from studies.gap.report import headline

    archive = Path(archive) if archive is not None else require_taxim_archive()
    pressed, unit_spec, ball_m, pixel_m, settled = open_set(archive, fmt, spec=spec, ball_mm=ball_mm,
                                                            pixel_mm=pixel_mm, turn=turn, markers=markers)
    depth = depth or default_depth(pressed)
    keep = work is not None
    work = Path(work) if keep else Path(tempfile.mkdtemp(prefix="bench-real-"))
    work.mkdir(parents=True, exist_ok=True)
    seconds, t_all = {}, time.perf_counter()

    def stage(name, fn):
        t0 = time.perf_counter()
        value = fn()
        seconds[name] = time.perf_counter() - t0
        return value

    try:
        capture = work / "capture"
        def import_as(folder, how, fit=None):
            return import_capture(pressed, folder, unit_spec, ball_m, pixel_m, fmt=settled["format"],
                                  rim_share=1.0 if rim_share is None else rim_share, depth=how, fit=fit)

        fast_profile = work / "calibrated_fast" / "profile.toml"
        depth_fit, fast_fit = None, phong.calibrate
        if depth == "fitted":
            # the layer and the fitted half's depths fitted together, from the spec's layer's depths and the
            # fast path calibrated at them; then the capture anew at the fitted depths
            from phong_reference.elastic_fit import fit as fit_elastic

            first = work / "capture_spec_layer"
            stage("import_spec_layer", lambda: import_as(first, "elastic"))
            stage("calibrate_fast_spec_layer", lambda: calibrate_capture(
                first, work / "calibrated_fast_spec_layer", phong.calibrate, fast_taps=0, fast_only=True,
                progress=not quiet))
            depth_fit = stage("fit_elastic", lambda: fit_elastic(
                first, work / "calibrated_fast_spec_layer" / "profile.toml", work / "elastic_fit.json",
                progress=None if quiet else print))
            fast_fit = functools.partial(phong.calibrate, elastic=depth_fit["elastic"])
        stage("import", lambda: import_as(capture, depth, depth_fit))
        stage("calibrate_fast", lambda: calibrate_capture(capture, fast_profile.parent, fast_fit,
                                                          fast_taps=0, fast_only=True, progress=not quiet))
        ref_profile = work / "calibrated_reference" / "profile.toml"

        def calibrate_reference(folder: Path):
            try:
                calibrate_capture(capture, folder, phong.calibrate, taps=REFERENCE_TAPS, bootstrap=4,
                                  grid=name_values(list(grid), "--grid", "NAME=V1,V2,..."),
                                  camera_known=camera_known, progress=not quiet, fit_layout=fit_layout,
                                  layout_seed=fast_profile.parent / "report.json" if fit_layout else None,
                                  spectral_gains=fit_layout, webcam=fit_layout)
            except REPORTED as exc:  # the comparisons go on without the calibrated reference
                print(f"bench real: the reference's calibration failed: {exc}", file=sys.stderr)

        fresh = _fresh_cache(work / "cache_run0") if runs > 1 else contextlib.nullcontext()
        if reference:
            with fresh:
                stage("calibrate_reference", lambda: calibrate_reference(ref_profile.parent))
        from scenes.profile import load_profile
        from scenes.replay import read_capture

        unit = read_capture(capture)
        field = load_profile(fast_profile, unit.spec).phong["field"]
        common = {"heldout": True, "bootstrap": 2000, "progress": not quiet}
        raw = stage("compare_uncalibrated", lambda: compare(
            capture, work / "compare_uncalibrated", reference=reference, reference_taps=int(reference_presses),
            peers=("taxim",), **common))
        fast = stage("compare_calibrated_fast", lambda: compare(
            capture, work / "compare_calibrated_fast", profile=fast_profile, reference=False, **common))
        ref = None
        if reference and ref_profile.is_file():
            with fresh:
                ref = stage("compare_calibrated_reference", lambda: compare(
                    capture, work / "compare_calibrated_reference", profile=ref_profile, fields=(field,),
                    reference=True, reference_taps=int(reference_presses), **common))
        core = sum(seconds.values())
        repeats = [{**_run_figures(ref_profile.parent, ref),
                    "seconds": seconds.get("calibrate_reference", 0.0) + seconds.get("compare_calibrated_reference", 0.0)}
                   ] if runs > 1 else []
        for k in range(1, runs):
            folder = work / f"calibrated_reference_run{k}"
            with _fresh_cache(work / f"cache_run{k}"):
                t0 = time.perf_counter()
                calibrate_reference(folder)
                again = compare(capture, work / f"compare_calibrated_reference_run{k}", profile=folder / "profile.toml",
                                fields=(field,), reference=True, reference_taps=int(reference_presses),
                                **common) if (folder / "profile.toml").is_file() else None
                repeats.append({**_run_figures(folder, again), "seconds": time.perf_counter() - t0})

        from scenes.replay import replay
        from studies.gap.diagnose import run as diagnose

        replayed = work / "replay_calibrated_fast"
        if diagnosis_on:
            stage("replay_calibrated_fast", lambda: replay(unit, replayed, phong, {"field": field,
                                                                                    "profile": str(fast_profile)},
                                                           workers=2, progress=not quiet))
        diagnosis = stage("diagnose_fast", lambda: diagnose(capture, replayed, work / "diagnosis_fast",
                                                           progress=not quiet, split_by="alternate")) \
            if diagnosis_on else None
        diagnosis_ref = None
        if reference_diagnosis and ref_profile.is_file():
            from pbr_tactile import plugin as pbr

            replayed_ref = work / "replay_calibrated_reference"
            from studies.compare.run import spread

            replayed_ids = spread(unit.ids, diagnosis_presses)
            stage("replay_calibrated_reference", lambda: replay(unit, replayed_ref, pbr,
                                                                {"profile": str(ref_profile)},
                                                                ids=replayed_ids, workers=1, progress=not quiet))
            try:
                diagnosis_ref = stage("diagnose_reference", lambda: diagnose(
                    capture, replayed_ref, work / "diagnosis_reference", progress=not quiet, split_by="alternate",
                    ids=replayed_ids))
            except REPORTED as exc:  # the replay and every other figure are kept; the JSON says why
                print(f"bench real: the diagnosis against the reference's replay failed: {exc}", file=sys.stderr)
                diagnosis_ref = {"error": str(exc)}
        loc = None
        if localisation:
            from studies.sim2real.presses import run as localise

            loc = stage("localisation", lambda: localise(
                capture, work / "localisation", fast_profile, field, work / "diagnosis_fast" / "report.json",
                LOCALISATION_PRESSES, progress=not quiet))

        fast_row = _row(fast, "fast", field=field)
        ref_row = _row(ref, "reference") if ref is not None else None
        taxim = _row(raw, "peer", variant="refit")
        taxim_share = _row(raw, "peer", variant="refit_share")
        shipped = _row(raw, "peer", variant="shipped")
        out = {
            "archive": str(archive), "set": settled, "presses": len(unit.ids), "heldout": len(raw["taps"]),
            "reference_calibration": {"grid": list(grid), "camera_known": camera_known, "fit_layout": fit_layout,
                                      "spectral_gains": fit_layout, "webcam_response": fit_layout,
                                      "layout": _layout_report(ref_profile.parent / "report.json")}
            if reference else None,
            "import": unit.meta.get("import"),
            "contact_strength": {"phong": fast_row["strength"]["median"] if fast_row else None,
                                 "pbr": ref_row["strength"]["median"] if ref_row else None},
            "contact_mae": {"phong": fast_row["contact"]["mae"]["mean"] if fast_row else None,
                            "pbr": ref_row["contact"]["mae"]["mean"] if ref_row else None,
                            "taxim": taxim["contact"]["mae"]["mean"] if taxim else None,
                            "taxim_shipped": shipped["contact"]["mae"]["mean"] if shipped else None,
                            "taxim_share": taxim_share["contact"]["mae"]["mean"] if taxim_share else None},
            "change_r2": json.loads((fast_profile.parent / "report.json").read_text())["fast_path"]["taps"]["heldout"][
                "change_r2"],
            "change_r2_what": "the calibrated fast path's held-out presses' change R^2 over their contact regions, per "
                              "channel (its calibration's report)",
            "depth_fit": None if depth_fit is None else {
                k: depth_fit[k] for k in ("elastic", "intervals", "record", "depth_share", "depth_median_m",
                                          "depth_median_interval_m", "depth_interval_median_width_m",
                                          "reaches_support", "shares_at_search_end", "loss_at_rim_depths",
                                          "loss_at_fitted_depths", "seconds")},
            "localisation_mm": ({k: loc["results"].get(f"filter/{k}", {}).get("real", {}).get("localisation_mm_median")
                                 for k in ("none", "randomised", "diagnosed")} if loc else None),
            "localisation_mm_no_offset": ({k: loc["results"].get(f"filter/{k}", {}).get("real_no_offset", {}).get(
                "localisation_mm_median") for k in ("none", "randomised", "diagnosed")} if loc else None),
            "reference_runs": {"runs": repeats, "spread": _spread(repeats)} if repeats else None,
            "seconds": core,
            "seconds_what": "import, both calibrations and the comparisons together (the goal's 20 minutes)",
            "stage_seconds": seconds, "total_seconds": time.perf_counter() - t_all,
            "detail": {
                "calibrated": {"phong": _figure(fast_row), "pbr": _figure(ref_row)},
                "uncalibrated": {"phong_best": _figure(min((r for r in raw["rows"] if r["method"] == "fast"),
                                                          key=lambda r: r["contact"]["mae"]["mean"])),
                                 "pbr": _figure(_row(raw, "reference"))},
                "taxim": {"refit": _figure(taxim), "shipped": _figure(shipped), "peers": raw.get("peers")},
                "phong_minus_taxim_contact_mae": _paired(fast_row, taxim) if fast_row and taxim else None,
                "phong_minus_taxim_share_contact_mae": _paired(fast_row, taxim_share) if fast_row and taxim_share
                else None,
                "taxim_share": _figure(taxim_share),
                "pbr_minus_taxim_contact_mae": _paired(ref_row, taxim) if ref_row and taxim else None,
                "field": field,
                "reference_presses": ref["reference_taps"] if ref else [],
                "diagnosis_fast": None if diagnosis is None else {"answer": headline(diagnosis),
                                                                  "explained": diagnosis["explained"]},
                "diagnosis_reference": diagnosis_ref if diagnosis_ref is None or "error" in diagnosis_ref else {
                    "answer": headline(diagnosis_ref),
                    "explained": diagnosis_ref["explained"], "pairs": diagnosis_ref["pairs"],
                    "ranking": diagnosis_ref["ranking"]},
                "localisation": None if loc is None else {
                    **{k: {"real": v.get("real", {}).get("localisation_mm_median_ci"),
                           "real_mean": v.get("real", {}).get("localisation_mm_mean"),
                           "depth": v.get("real", {}).get("depth_error_mm_median_abs"),
                           "sim": v.get("sim", {}).get("localisation_mm_median"), "chosen": v.get("chosen"),
                           "bias_px": v.get("real", {}).get("bias_px"), "offset_px": v.get("offset_px"),
                           "real_no_offset": v.get("real_no_offset", {}).get("localisation_mm_median_ci"),
                           "bias_px_no_offset": v.get("real_no_offset", {}).get("bias_px"),
                           "real_unbiased": v.get("real", {}).get("localisation_mm_median_unbiased")}
                       for k, v in loc["results"].items()}, "paired": loc.get("paired"),
                    "real2real": (loc.get("real2real") or {}).get("real", {}).get("localisation_mm_median_ci"),
                    "appearance": loc.get("appearance")},
            },
            "work": str(work) if keep else None,
        }
        atomic_write_json(Path(json_path), out)
        return out
    finally:
        if not keep:
            shutil.rmtree(work, ignore_errors=True)


def cmd_bench_real(args) -> int:
    out = run(args.json, args.archive, args.spec, args.ball_mm, args.pixel_mm, args.work,
              reference=not args.no_reference, reference_diagnosis=args.reference_diagnosis,
              localisation=not args.no_localisation, quiet=args.quiet, rim_share=args.rim_share, depth=args.depth,
              grid=tuple(args.grid) if args.grid else REFERENCE_GRID, camera_known=not args.search_alignment,
              reference_presses=args.reference_presses, fit_layout=args.fit_layout, runs=args.runs,
              diagnosis_on=not args.no_diagnosis, fmt=args.format, turn=args.turn, markers=args.markers,
              diagnosis_presses=args.diagnosis_presses)
    print(json.dumps({k: out[k] for k in ("contact_strength", "contact_mae", "localisation_mm",
                                          "localisation_mm_no_offset", "seconds")}, indent=1))
    print(f"wrote {args.json}")
    return 0


def register(registry) -> None:
    from scenes.commands import add_quiet_argument, positive_int

    p = registry.bench("real", cmd_bench_real, "a real capture of ball presses end to end: import, both calibrations, "
                       "compare with Taxim, the diagnosis and sim-to-real localisation on the held-out presses")
    from scenes.press_sets import FORMATS, MARKERS, TURNS

    p.add_argument("--archive", metavar="A", help="the set of presses: any archive or folder tactile-sim import "
                   "reads, its records (set.toml in a folder, X.toml beside X.npz) giving what is not given here "
                   "(default: the public GelSight set, ../shared/data/real_gelsight_taxim)")
    p.add_argument("--format", choices=sorted(FORMATS), help="the archive's format (default: its records', else "
                   "taxim for a .npz or a folder holding one dataPack*.npz, else folder)")
    p.add_argument("--spec", metavar="TOML", help="the unit's sensor spec, a TOML or a shipped sensor's name (default: "
                   "the set's records', else the format's: gelsight.toml)")
    p.add_argument("--ball-mm", type=float, metavar="D", help="the ball's diameter, mm (default: the set's records', "
                   "else the table's, else taxim's 4)")
    p.add_argument("--pixel-mm", type=float, metavar="P", help="a pixel's size on the gel, mm (default: the set's "
                   "records', else taxim's 0.1245, else the spec camera's at the frames' size)")
    p.add_argument("--turn", choices=[str(t) for t in TURNS] + ["auto"],
                   help="turn the frames and their centres this many degrees clockwise (tactile-sim import --turn)")
    p.add_argument("--markers", choices=MARKERS, help="printed marker dots: keep (default) or inpaint (tactile-sim "
                   "import --markers)")
    p.add_argument("--depth", choices=("profile", "elastic", "fitted", "given"),
                   help="how the import gives each press its depth (tactile-sim import's --depth; elastic: the rim "
                        "is the edge of the elastic contact the spec's layer makes, the same depths for every model; "
                        "fitted: the bonded layer and the fitted half's depths fitted together (tactile-sim "
                        "fit-elastic) and the fast path calibrated under that layer; given: the set's own; default: "
                        "given where the set gives every press's depth, else profile)")
    p.add_argument("--rim-share", type=float, metavar="K", help="the import's share of a contact's radius at which "
                   "its change peaks (default 1: tactile-sim import's --rim-share)")
    p.add_argument("--work", metavar="DIR", help="keep every dataset, profile and report here (default: a temporary "
                                                 "folder, removed)")
    p.add_argument("--no-reference", action="store_true", help="leave the physically based reference out")
    p.add_argument("--grid", action="append", metavar="NAME=V1,V2,...",
                   help="the reference calibration's grid (calibrate --grid; default "
                        + " ".join(REFERENCE_GRID) + ")")
    p.add_argument("--search-alignment", action="store_true",
                   help="search the reference's alignment to the camera (rotation, scale, shift, lens) instead of "
                        "holding it at the spec's (calibrate --camera-known; the public set's spec is written from "
                        "its camera's record): for a unit whose spec's camera is an estimate")
    p.add_argument("--reference-presses", type=positive_int, default=REFERENCE_PRESSES, metavar="N",
                   help=f"held-out presses the reference renders, spread evenly over them (default "
                        f"{REFERENCE_PRESSES}; each takes about a minute and a half here; all when N is at least "
                        "their count)")
    p.add_argument("--fit-layout", action="store_true",
                   help="the reference's calibration fits its LEDs' layout first (calibrate --fit-layout, seeded "
                        "with the fast path's fitted LED places)")
    p.add_argument("--runs", type=positive_int, default=1, metavar="N",
                   help="run the reference's calibration and its calibrated comparison N times, each from an empty "
                        "cache, and write their figures and spread (reference_runs)")
    p.add_argument("--reference-diagnosis", action="store_true",
                   help="also diagnose the capture against the calibrated reference's replay (about an hour here)")
    p.add_argument("--diagnosis-presses", type=positive_int, metavar="N",
                   help="with --reference-diagnosis: replay and diagnose N of the presses, spread evenly over the "
                        "capture (default all; each is a reference render at the capture's size, about a minute and "
                        "a half here)")
    p.add_argument("--no-localisation", action="store_true", help="leave the localisation study out")
    p.add_argument("--no-diagnosis", action="store_true",
                   help="leave the diagnosis of the fast path's replay out (with --no-localisation, which uses it)")
    add_quiet_argument(p)
