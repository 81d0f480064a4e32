"""``tactile-sim calibrate``: fit a sensor profile to real captures, and its report."""

from __future__ import annotations

from pathlib import Path

from .calibrate_capture import calibrate_capture


def cmd_calibrate(args) -> int:
    if args.real == "benchmark":
        return cmd_benchmark(args)
    for name in ("cases", "json"):
        if getattr(args, name) is not None:
            raise ValueError(f"--{name} is an option of 'tactile-sim calibrate benchmark'")
    if args.out is None:
        raise ValueError("calibrate needs --out DIR")
    fit = fast_path_fit()
    if args.elastic_fit is not None:
        if not args.fast_only:
            raise ValueError("--elastic-fit calibrates the fast path under the fitted layer: give --fast-only")
        fit = fast_path_fit(elastic_entry(args.elastic_fit))
    result = calibrate_capture(args.real, args.out, fit, background_only=args.background_only,
                               spec=args.spec, taps=args.taps, fast_taps=args.fast_taps,
                               grid=_grid(args.grid) if args.grid else None, bootstrap=args.bootstrap,
                               camera_known=args.camera_known, fast_only=args.fast_only, no_leak=args.no_leak,
                               width=args.width, photons=args.photons, spp=args.spp, seed=args.seed,
                               progress=not args.quiet, fit_layout=args.fit_layout, layout_seed=args.layout_seed,
                               spectral_gains=args.spectral_gains, webcam=args.webcam_response)
    paths, report = result["paths"], result["report"]
    wrote = f"; wrote {', '.join(str(p) for p in paths.values())}"
    if args.fast_only:
        fast = report["fast_path"]["taps"]
        print("fast path: background held-out R^2 " + ", ".join(f"{ch} {report['heldout_r2'][ch]:.3f}" for ch
                                                                  in "rgb")
              + f"; LED constants of the {fast['field']} field, held-out change R^2 "
              + ", ".join(f"{ch} {fast['heldout']['change_r2'][ch]:.3f}" for ch in "rgb") + wrote)
        return 0
    r2 = report["heldout_r2"]
    print("held-out R^2 " + ", ".join(f"{ch} {r2[ch]:.3f}{' (saturated)' if report['saturated'][ch] else ''}"
                                      for ch in "rgb") + wrote)
    if not report["converged"]:
        print(f"tactile-sim calibrate: the fit did not converge (loss {report['loss']:.4g} from "
              f"{report['start_loss']:.4g}); no profile written, see {paths['report']}")
        return 1
    return 0


def cmd_benchmark(args) -> int:
    """``tactile-sim calibrate benchmark``: blind recovery on virtual sensors."""
    from tqdm import tqdm

    from scenes.camera import Camera
    from scenes.dataset import atomic_write_json
    from scenes.geometry import membrane_mesh
    from scenes.spec_read import load_spec

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
    from scenes.spec_read import load_spec

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


def fast_path_fit(elastic: dict | None = None):
    """The fast path's fit of its LED constants to a unit's taps (its renderer plugin's
    ``calibrate``), which a calibration with taps writes into the profile; with
    ``elastic``, under that elastic model (``{"model": "bonded", "thickness_m",
    "poisson_ratio"}``). Looked up by name: this package imports no other renderer, and
    only the command line chooses one."""
    import functools

    from scenes.renderers import Calibrates, get_renderer

    phong = get_renderer("phong")
    if not isinstance(phong, Calibrates):
        raise ValueError("the renderer 'phong' offers no calibrate (scenes.renderers.Calibrates)")
    return phong.calibrate if elastic is None else functools.partial(phong.calibrate, elastic=elastic)


def elastic_entry(path) -> dict:
    """The elastic model a joint fit's report (``tactile-sim fit-elastic``) found: its
    ``elastic`` entry; ValueError naming the file where it has none."""
    import json

    try:
        entry = json.loads(Path(path).read_text())["elastic"]
        return {"model": str(entry["model"]), "thickness_m": float(entry["thickness_m"]),
                "poisson_ratio": float(entry["poisson_ratio"])}
    except (OSError, json.JSONDecodeError, KeyError, TypeError, ValueError) as exc:
        raise ValueError(f"--elastic-fit {path}: not a joint fit's report with elastic.model, thickness_m and "
                         f"poisson_ratio ({type(exc).__name__}: {exc})") from None


def _grid(items: list[str]) -> dict:
    from scenes.settings import name_values

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
    p.add_argument("--elastic-fit", metavar="FIT.json",
                   help="with --fast-only: fit the fast path under the bonded layer a joint fit found (tactile-sim "
                        "fit-elastic's report), instead of the published smoothing; the profile records it")
    p.add_argument("--fast-taps", type=int, metavar="N",
                   help="taps of REAL the fast path's LED constants are fitted (and judged) on, fitted and judged in "
                        "turn from its even and odd samples (0: all; default: the reference's --taps): the fast path "
                        "renders many taps in the time the reference renders one")
    p.add_argument("--fit-layout", action="store_true",
                   help="fit the LEDs' layout first (where each LED's light enters: under the glass, its edge or "
                        "beside the elastomer; its place, aim and beam, within the spec's [housing]) to the "
                        "no-contact image, and calibrate the reference laid out so (pbr_tactile.layout_fit)")
    p.add_argument("--layout-seed", metavar="REPORT.json",
                   help="with --fit-layout: a --fast-only calibration's report.json, whose fitted LED places are "
                        "one of the layout search's starts (as LEDs under the glass)")
    p.add_argument("--spectral-gains", action="store_true",
                   help="each LED's light reaches the camera's channels through its spectrum under the camera's "
                        "filters (one power per LED, one white balance per channel) instead of a free gain per LED "
                        "and channel")
    p.add_argument("--webcam-response", action="store_true",
                   help="hold the camera's response to a webcam's: its exponent 1.8 to 2.6 (sRGB's 2.2) and its "
                        "black level at most 0.1, instead of an exponent of 0.5 to 3 and any offset")
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
