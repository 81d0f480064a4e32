"""``tactile-sim calibrate``: fit a sensor profile to real captures, and its report."""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np


def real_background(real: str | None, background_only: str | None) -> tuple[Path, str]:
    """The no-contact image to calibrate from, and what it is: ``--background-only
    IMAGE``, or REAL a capture dataset (``source: "real"``) with its background.png."""
    if (real is None) == (background_only is None):
        raise ValueError("give exactly one of REAL (a capture dataset directory) or --background-only IMAGE")
    if background_only is not None:
        return Path(background_only), "one no-contact image"
    folder = Path(real)
    meta = folder / "dataset.json"
    if not meta.exists():
        raise FileNotFoundError(f"REAL {folder} is not a dataset: it has no dataset.json (for a single image use "
                                "--background-only IMAGE)")
    try:
        source = json.loads(meta.read_text()).get("source")
    except json.JSONDecodeError as exc:
        raise ValueError(f"REAL {meta} is not valid JSON: {exc}") from None
    if source != "real":
        raise ValueError(f"REAL {folder} has source {source!r}; calibration needs captures of a real sensor "
                         "(source: \"real\")")
    background = folder / "background.png"
    if not background.exists():
        raise ValueError(f"REAL {folder} has no background.png: calibration needs the sensor's no-contact capture")
    return background, f"the background of capture dataset {folder}"


def capture_spec(real: str):
    """The sensor a capture dataset records (its dataset.json), which a calibration of it
    takes when no --spec is given: an imported capture's camera is the set's own."""
    from scenes.dataset import read_meta
    from scenes.spec import spec_from_dict

    meta = read_meta(real)
    try:
        return spec_from_dict(meta["sensor"], f"REAL {real}/dataset.json sensor")
    except (KeyError, TypeError) as exc:
        raise ValueError(f"REAL {real}/dataset.json has no usable sensor spec: {exc!r}") from None


def _figure(images: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = [name for name in ("real", "before", "after", "fast_path") if name in images]
    residuals = [name for name in ("after", "fast_path") if name in images]
    fig, axes = plt.subplots(3, len(names) + len(residuals), figsize=(3.5 * (len(names) + len(residuals)), 9))
    for c, ch in enumerate("rgb"):
        for k, name in enumerate(names):
            axes[c, k].imshow(images[name][..., c], vmin=0, vmax=1, cmap="gray")
            axes[c, k].set_title(f"{name.replace('_', ' ')} ({ch})")
        for k, name in enumerate(residuals, start=len(names)):
            diff = np.where(images["judged"][..., c], images[name][..., c] - images["real"][..., c], np.nan)
            im = axes[c, k].imshow(diff, vmin=-0.2, vmax=0.2, cmap="RdBu_r")
            axes[c, k].set_title(f"{name.replace('_', ' ')} - real, held out ({ch})", fontsize=9)
            fig.colorbar(im, ax=axes[c, k])
    for ax in axes.ravel():
        ax.axis("off")
    fig.tight_layout()
    fig.savefig(path, dpi=80)
    plt.close(fig)


def _fast_path_html(fast: dict | None) -> str:
    if not fast:
        return ""
    rows = "".join(f"<tr><td>{ch}</td><td>{fast['solid']['heldout_r2'][ch]:.3f}</td><td>{fast['heldout_r2'][ch]:.3f}"
                   f"</td><td>{fast['solid']['heldout_mae'][ch]:.4f}</td><td>{fast['heldout_mae'][ch]:.4f}</td></tr>"
                   for ch in "rgb")
    return (f"<h2>The fast path's background term</h2><p>{fast['background_model']}; the same split.</p>"
            f"<table border=1><tr><th>channel</th><th>held-out R² solid colour</th><th>smooth model</th>"
            f"<th>MAE solid</th><th>smooth</th></tr>{rows}</table>")


def _taps_html(report: dict) -> str:
    taps = report.get("taps")
    if not taps:
        return ""
    fast = (report.get("fast_path") or {}).get("taps")

    def row(name, scores):
        return (f"<tr><td>{name}</td>" + "".join(f"<td>{scores['change_r2'].get(ch, float('nan')):.3f}</td>"
                                                  for ch in "rgb")
                + "".join(f"<td>{scores['mae'].get(ch, float('nan')):.4f}</td>" for ch in "rgb") + "</tr>")

    rows = [row("reference, from the image alone", taps["heldout_before_taps"]),
            row("reference, with taps", taps["heldout"])]
    if fast:
        rows += [row("fast path, the spec's LED constants", fast["heldout_before"]),
                 row(f"fast path, fitted (shininess {fast['shininess']:g})", fast["heldout"])]
    return (f"<h2>Taps</h2><p>Fitted: {', '.join(taps['fitted'])}; judged: {', '.join(taps['judged']) or 'none'}; "
            f"without a visible contact: {', '.join(taps['without_contact']) or 'none'}. {taps['split']}.</p>"
            "<table border=1><tr><th>held-out taps</th><th>change R² r</th><th>g</th><th>b</th><th>MAE r</th>"
            f"<th>g</th><th>b</th></tr>{''.join(rows)}</table>")


def write_outputs(calibration, out: Path, what: str) -> dict[str, Path]:
    """report.json, report.html, residual images and figure; profile.toml only for a
    converged fit."""
    from scenes.dataset import atomic_write_json
    from scenes.images import write_rgb
    from scenes.profile import write_profile

    out.mkdir(parents=True, exist_ok=True)
    report = {"data": what, **calibration.report}
    images = calibration.images
    np.save(out / "residual.npy", (images["after"] - images["real"]).astype(np.float32))
    write_rgb(out / "after.png", images["after"])
    write_rgb(out / "before.png", images["before"])
    write_rgb(out / "residual.png", np.clip(0.5 + 2.5 * (images["after"] - images["real"]), 0, 1))
    _figure(images, out / "residuals_figure.png")
    paths = {"report": out / "report.json", "html": out / "report.html"}
    if calibration.report["converged"]:
        paths["profile"] = write_profile(calibration.profile, out / "profile.toml")
    report["profile"] = str(paths["profile"]) if "profile" in paths else None
    atomic_write_json(paths["report"], report)
    rows = "".join(f"<tr><td>{ch}</td><td>{report['heldout_r2_before'][ch]:.3f}</td><td>{report['heldout_r2'][ch]:.3f}"
                   f"</td><td>{report['heldout_mae_before'][ch]:.4f}</td><td>{report['heldout_mae'][ch]:.4f}</td>"
                   f"<td>{'yes' if report['saturated'][ch] else 'no'}</td></tr>" for ch in "rgb")
    status = ("converged" if report["converged"] else
              "<b>did NOT converge: no profile was written</b>")
    paths["html"].write_text(
        f"<html><head><meta charset='utf-8'><title>Calibration</title></head><body><h1>Calibration of the reference</h1>"
        f"<p>From {what}. Fit {status}; {report['split']}.</p>"
        f"<table border=1><tr><th>channel</th><th>held-out R² before</th><th>after</th><th>MAE before</th>"
        f"<th>after</th><th>saturated</th></tr>{rows}</table>"
        f"<p>Best effects on the grid: {report['best_effects']}</p>{_fast_path_html(report.get('fast_path'))}"
        f"{_taps_html(report)}"
        f"<p>Not identifiable from this data:</p><ul>{''.join(f'<li>{x}</li>' for x in report['not_identifiable'])}</ul>"
        f"<img src='residuals_figure.png'></body></html>")
    return paths


def cmd_calibrate(args) -> int:
    if args.real == "benchmark":
        return cmd_benchmark(args)
    for name in ("cases", "json"):
        if getattr(args, name) is not None:
            raise ValueError(f"--{name} is an option of 'tactile-sim calibrate benchmark'")
    if args.out is None:
        raise ValueError("calibrate needs --out DIR")
    from tqdm import tqdm

    from scenes.camera import Camera
    from scenes.geometry import membrane_mesh
    from scenes.images import read_rgb
    from scenes.spec import load_spec

    from .calibrate import GRID, calibrate_background
    from scenes.captures import MAX_TAPS, load_real_taps
    from scenes.dataset import read_samples

    path, what = real_background(args.real, args.background_only)
    spec = load_spec(args.spec) if args.spec is not None or args.real is None else capture_spec(args.real)
    camera = Camera.from_spec(spec)
    real = read_rgb(path)
    grid = GRID if not args.grid else _grid(args.grid)
    taps = None
    count = MAX_TAPS if args.taps is None else args.taps
    if not 0 <= count <= MAX_TAPS:
        raise ValueError(f"--taps must be in [0, {MAX_TAPS}], got {count}")
    fast_taps = None
    if args.real is not None and count:
        taps = load_real_taps(args.real, spec, camera, count)
        what += f" and {len(taps.ids)} of its taps"
        if args.fast_taps is not None:
            fast_taps = load_real_taps(args.real, spec, camera, args.fast_taps or len(read_samples(args.real)))
            what += f" ({len(fast_taps.ids)} for the fast path)"
    elif args.taps or args.fast_taps is not None:
        raise ValueError("--taps and --fast-taps need REAL, a capture dataset (--background-only has no taps)")
    bar = tqdm(desc="calibrating", unit="grid point", disable=args.quiet)

    def progress(done, total):
        bar.total = total
        bar.update(done - bar.n)

    t0 = time.perf_counter()
    if args.fast_only:
        if taps is None:
            raise ValueError("--fast-only fits the fast path's LED constants to taps: give REAL, a capture dataset")
        from .calibrate import calibrate_fast

        cal = calibrate_fast(real, spec, membrane_mesh(spec), camera, fast_taps or taps, fast_path_fit(),
                             seed=args.seed)
        bar.close()
        cal.report["seconds"] = time.perf_counter() - t0
        paths = write_outputs(cal, Path(args.out), what + ", the fast path alone")
        fast = cal.report["fast_path"]["taps"]
        print("fast path: background held-out R^2 " + ", ".join(f"{ch} {cal.report['heldout_r2'][ch]:.3f}" for ch
                                                                  in "rgb")
              + f"; LED constants of the {fast['field']} field, held-out change R^2 "
              + ", ".join(f"{ch} {fast['heldout']['change_r2'][ch]:.3f}" for ch in "rgb")
              + f"; wrote {', '.join(str(p) for p in paths.values())}")
        return 0
    cal = calibrate_background(real, spec, membrane_mesh(spec), camera, film=(args.width, args.width * 3 // 4),
                               grid=grid, photons=args.photons, spp=args.spp, seed=args.seed,
                               bootstrap=args.bootstrap, leak=not args.no_leak, progress=progress, taps=taps,
                               fast_path_fit=fast_path_fit(), fast_taps=fast_taps, camera_known=args.camera_known)
    bar.close()
    cal.report["seconds"] = time.perf_counter() - t0
    paths = write_outputs(cal, Path(args.out), what)
    r2 = cal.report["heldout_r2"]
    print("held-out R^2 " + ", ".join(f"{ch} {r2[ch]:.3f}{' (saturated)' if cal.report['saturated'][ch] else ''}"
                                      for ch in "rgb") + f"; wrote {', '.join(str(p) for p in paths.values())}")
    if not cal.report["converged"]:
        print(f"tactile-sim calibrate: the fit did not converge (loss {cal.report['loss']:.4g} from "
              f"{cal.report['start_loss']:.4g}); no profile written, see {paths['report']}")
        return 1
    return 0


def cmd_benchmark(args) -> int:
    """``tactile-sim calibrate benchmark``: blind recovery on virtual sensors."""
    from tqdm import tqdm

    from scenes.camera import Camera
    from scenes.dataset import atomic_write_json
    from scenes.geometry import membrane_mesh
    from scenes.spec import load_spec

    from .calibrate import GRID
    from .calibrate_bench import benchmark

    if args.json is None:
        raise ValueError("calibrate benchmark needs --json PATH")
    cases = 6 if args.cases is None else args.cases
    if cases < 1:
        raise ValueError(f"--cases must be >= 1, got {cases}")
    spec = load_spec(args.spec)
    camera = Camera.from_spec(spec)
    bar = tqdm(total=cases, desc="virtual sensors", unit="case", disable=args.quiet)
    # written after every case, so a stopped run keeps the cases it finished
    write = lambda summary: atomic_write_json(Path(args.json), {**summary, "cases_requested": cases})  # noqa: E731
    result = benchmark(spec, membrane_mesh(spec), camera, cases=cases, seed=args.seed,
                       film=(args.width, args.width * 3 // 4), grid=_grid(args.grid) if args.grid else GRID,
                       photons=args.photons, spp=args.spp, progress=lambda done, total: bar.update(done - bar.n),
                       taps=0 if args.taps is None else args.taps, on_case=write, fast_path_fit=fast_path_fit())
    bar.close()  # the last case's summary, the result, is already written
    print(f"median relative error {result['median_relative_error']:.3f}, share within 10 % "
          f"{result['share_within_10pct']:.2f} over {cases} cases; wrote {args.json}")
    return 0


def cmd_bench_calibrate(args) -> int:
    """``tactile-sim bench calibrate``: seconds to calibrate from one no-contact image."""
    from scenes.camera import Camera
    from scenes.dataset import atomic_write_json
    from scenes.geometry import membrane_mesh
    from scenes.spec import load_spec

    from .calibrate_bench import benchmark

    spec = load_spec(args.spec)
    camera = Camera.from_spec(spec)
    result = benchmark(spec, membrane_mesh(spec), camera, cases=1, seed=args.seed, cold=True, taps=args.taps,
                       fast_path_fit=fast_path_fit())
    out = {"seconds": result["seconds_per_case"], "what": f"one no-contact image and {args.taps} taps of a virtual "
           "sensor, default grid, basis and tap renders not cached (cold), bootstrap off; the seconds of calibration "
           "only (not of rendering the virtual sensor)", "taps": args.taps,
           "median_relative_error": result["median_relative_error"], "tap_mae_over_noise": result["tap_mae_over_noise"]}
    atomic_write_json(Path(args.json), out)
    print(f"calibrated in {out['seconds']:.0f} s; wrote {args.json}")
    return 0


def fast_path_fit():
    """The fast path's fit of its LED constants to a unit's taps (its renderer plugin's
    ``calibrate``), which a calibration with taps writes into the profile. Looked up by
    name: this package imports no other renderer, and only the command line chooses one."""
    from scenes.renderers import Calibrates, get_renderer

    phong = get_renderer("phong")
    if not isinstance(phong, Calibrates):
        raise ValueError("the renderer 'phong' offers no calibrate (scenes.renderers.Calibrates)")
    return phong.calibrate


def _grid(items: list[str]) -> dict:
    from scenes.commands import name_values

    return name_values(items, "--grid", "NAME=V1,V2,... (an effect and its values)")


def register(registry) -> None:
    from scenes.commands import add_quiet_argument

    p = registry.command("calibrate", cmd_calibrate,
                         "fit a sensor profile (profile.toml) of the physically based reference to real captures")
    p.add_argument("real", nargs="?", metavar="REAL",
                   help="a capture dataset (source: real) with background.png, or 'benchmark' (see below)")
    p.add_argument("--background-only", metavar="IMAGE", help="calibrate from one no-contact image instead")
    p.add_argument("--out", metavar="DIR", help="writes profile.toml, report.json, report.html, "
                                                               "residual images")
    p.add_argument("--spec", metavar="TOML", help="the sensor (default: REAL's own, as its dataset.json records it; "
                   "the GelTip for --background-only)")
    p.add_argument("--width", type=int, default=160, help="film width of the basis renders (height: 3/4 of it)")
    p.add_argument("--photons", type=int, default=1 << 18, help="photons per LED per pass of each basis render")
    p.add_argument("--spp", type=int, default=32, help="camera samples per pixel per pass of each basis render")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--bootstrap", type=int, default=16, help="bootstrap resamples of the training sectors")
    p.add_argument("--grid", action="append", metavar="NAME=V1,V2,...",
                   help="effects searched and their values (repeatable; default absorption_per_m and "
                        "scattering_per_m on 3 values each)")
    p.add_argument("--no-leak", action="store_true", help="no light into the glass core (the leak fixed at 0)")
    p.add_argument("--camera-known", action="store_true",
                   help="the real camera is the spec's (a spec written from the unit's own camera record, as "
                        "gelsight.toml): hold the membrane's rotation, scale, shift and lens there instead of "
                        "searching them (pbr_tactile.image_model)")
    p.add_argument("--taps", type=int, help="taps of REAL used, spread over it (default and at most 10; 0: its "
                                           "no-contact image only); with REAL = benchmark: virtual taps per sensor "
                                           "(default 0)")
    p.add_argument("--fast-only", action="store_true",
                   help="calibrate the fast path alone (its background term and LED constants per light field, "
                        "seconds): no render of the reference, whose profile table stays empty")
    p.add_argument("--fast-taps", type=int, metavar="N",
                   help="taps of REAL the fast path's LED constants are fitted (and judged) on, fitted and judged in "
                        "turn from its even and odd samples (0: all; default: the reference's --taps): the fast path "
                        "renders many taps in the time the reference renders one")
    p.add_argument("--cases", type=int, help="with REAL = benchmark: virtual sensors to recover (default 6)")
    p.add_argument("--json", metavar="PATH", help="with REAL = benchmark: where to write its results")
    add_quiet_argument(p)
    p.epilog = ("'tactile-sim calibrate benchmark --cases N --seed S --json PATH' runs the blind recovery benchmark "
                "on virtual sensors with hidden parameters instead (pbr_tactile.calibrate_bench)")

    p = registry.bench("calibrate", cmd_bench_calibrate,
                       "seconds to calibrate the reference from one no-contact image and taps")
    p.add_argument("--spec", metavar="TOML")
    p.add_argument("--taps", type=int, default=10, help="virtual taps (default 10)")
    p.add_argument("--seed", type=int, default=0)
