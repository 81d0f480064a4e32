"""Subcommands of the scenes package: the MuJoCo rig (scene), datasets, and their bench;
and the options that other packages' subcommands share (``add_*_arguments``).

Part of the command-line layer: it looks renderers up by name (``scenes.renderers.
get_renderer``) and passes the plugin into dataset generation."""

from __future__ import annotations

import json
import os
import tempfile
import time
from pathlib import Path

import numpy as np

from .elastic import MODELS
from .protocol import make_protocol
from .renderers import RENDERER_OPTIONS
from .spec_read import load_spec


def object_names(value: str) -> tuple[str, ...]:
    """``--objects``: ``all`` (every indenter) or a comma-separated list of indenter names or
    STL paths, as a tuple."""
    from .indenters import INDENTERS

    if value == "all":
        return INDENTERS
    names = tuple(n.strip() for n in value.split(",") if n.strip())
    if not names:
        raise ValueError("--objects must be 'all' or a comma-separated list of indenter names or STL paths")
    return names


def _rig(args, tap_index: int | None = 0):
    from .body import checked_membrane
    from .indenters import indenter
    from .rig import Rig, rig_scene

    spec = load_spec(args.spec)
    mesh = checked_membrane(spec)
    name = args.object
    rig = Rig(rig_scene(spec, {name: indenter(name)}, membrane=mesh), spec)
    if tap_index is not None:
        protocol = make_protocol("base", spec, mesh, (name,))
        rig.press(protocol.taps[tap_index % len(protocol.taps)])
    return rig


def cmd_scene(args) -> int:
    if args.action == "export":
        from .body import checked_membrane
        from .indenters import indenter
        from .rig import rig_scene

        spec = load_spec(args.spec)
        objects = object_names(args.object)
        scene = rig_scene(spec, {name: indenter(name) for name in objects}, membrane=checked_membrane(spec))
        path = scene.export(args.output)
        print(f"wrote {path}; open it with: python -m mujoco.viewer --mjcf {path}")
        return 0
    if args.action == "snapshot":
        from .images import write_rgb

        rig = _rig(args, args.tap)
        write_rgb(args.output, rig.snapshot(args.width, args.height))
        rig.close()
        print(f"wrote {args.output}")
        return 0
    if args.action == "view":
        if not os.environ.get("DISPLAY") and not os.environ.get("WAYLAND_DISPLAY"):
            raise ValueError("scene view needs a display (DISPLAY is unset); use 'scene snapshot -o PNG' headless")
        os.environ.setdefault("MUJOCO_GL", "glfw")
        import mujoco.viewer

        rig = _rig(args, args.tap)
        mujoco.viewer.launch(rig.model, rig.data)
        return 0
    raise ValueError(f"unknown scene action {args.action!r}")


def _film_size(value: str) -> list[int]:
    """``WxH`` in pixels -> [W, H], for ``--film``."""
    import argparse

    try:
        width, height = (int(x) for x in value.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected WxH in pixels, e.g. 320x240; got {value!r}") from None
    return [width, height]


def renderer_options(args) -> dict:
    """The renderer options given on a command line (``add_renderer_arguments``): only
    those given, as each renderer refuses the options it does not take."""
    return {key: getattr(args, attr) for key, attr in RENDERER_OPTIONS.items()
            if getattr(args, attr, None) is not None}


#: Arguments of the dataset command that a replay takes from the capture instead.
REPLAY_TAKES = {"spec": "--spec", "protocol": "--protocol", "objects": "--objects", "seed": "--seed"}


def cmd_dataset(args) -> int:
    from .generate import generate
    from .body import checked_membrane
    from .renderers import get_renderer

    if args.replay is not None:
        return cmd_replay(args)
    spec = load_spec(args.spec)
    protocol = make_protocol(args.protocol or "base", spec, checked_membrane(spec), object_names(args.objects or "all"),
                             seed=args.seed or 0)
    if args.limit:
        from dataclasses import replace

        protocol = replace(protocol, taps=protocol.taps[: args.limit])
    summary = generate(args.out, spec, protocol, get_renderer(args.renderer), renderer_options(args),
                       workers=args.workers, progress=not args.quiet, executor=args.executor, address=args.address)
    where = f"Ray cluster at {args.address}" if args.address else f"{summary['workers']} {args.executor} workers"
    print(f"{summary['samples']} samples in {args.out} ({summary['new']} new, {summary['seconds']:.1f} s, {where})")
    return 0


def cmd_replay(args) -> int:
    """``tactile-sim dataset --replay CAPTURE_DIR``: the capture's taps at their measured poses."""
    from .renderers import get_renderer
    from .replay import read_capture, replay

    given = [flag for attr, flag in REPLAY_TAKES.items() if getattr(args, attr) is not None]
    if given:
        raise ValueError(f"--replay takes the sensor and the taps from CAPTURE_DIR (its dataset.json and "
                         f"protocol.json); drop {', '.join(given)}")
    capture = read_capture(args.replay)
    ids = capture.ids[: args.limit] if args.limit else None
    summary = replay(capture, args.out, get_renderer(args.renderer), renderer_options(args), ids=ids,
                     workers=args.workers, progress=not args.quiet, executor=args.executor, address=args.address)
    print(f"{summary['samples']} samples of {args.replay} replayed in {args.out} ({summary['new']} new, "
          f"{summary['seconds']:.1f} s)")
    return 0


def cmd_import(args) -> int:
    """``tactile-sim import FORMAT ARCHIVE --out DIR``: a published capture, or a folder of
    presses, as a capture dataset."""
    from .imports import default_depth, import_capture, open_set

    columns = None
    if args.columns:
        columns = {}
        for item in args.columns:
            role, sep, name = item.partition("=")
            if not sep or not role.strip() or not name.strip():
                raise ValueError(f"--columns {item!r}: expected ROLE=NAME, e.g. x=cx")
            columns[role.strip()] = name.strip()
    archive, spec, ball, pixel, how = open_set(
        args.archive, args.format, spec=args.spec, ball_mm=args.ball_mm, pixel_mm=args.pixel_mm, turn=args.turn,
        table=args.table, no_contact=args.no_contact, columns=columns, channels=args.channels, markers=args.markers)
    depth = args.depth or default_depth(archive)
    if (depth == "fitted") != (args.depth_fit is not None):
        raise ValueError("--depth fitted takes --depth-fit FIT.json (the joint fit's report), and only it does")
    fit = None
    if args.depth_fit is not None:
        try:
            fit = json.loads(Path(args.depth_fit).read_text())
        except (OSError, json.JSONDecodeError) as exc:
            raise ValueError(f"--depth-fit {args.depth_fit}: not a readable JSON ({exc})") from None
    summary = import_capture(archive, args.out, spec, ball, pixel, depth=depth, fmt=how["format"],
                             rim_share=args.rim_share, fit=fit)
    d = summary["depth_mm"]
    rims = (f", rims at {summary['rim_share']:g} of the contact's radius, {summary['rims_capped']} capped at the ball's"
            if summary["rim_share"] != 1.0 else
            f", {summary['rims_capped']} rims wider than the deepest press the layer was solved at, given its depth"
            if summary["depth"] in ("elastic", "fitted") else "")
    settled = "; ".join(f"{k} from {v}" for k, v in sorted(how["from"].items()))
    turned = f"; frames turned {how['turn_deg']} deg clockwise with their centres" if how["turn_deg"] else ""
    if how["markers"] == "inpaint":
        m = archive.notes["markers"]
        turned += (f"; marker dots inpainted ({m['no_contact_share']:.1%} of the no-contact frame, a median "
                   f"{m['frame_share_median']:.1%} of each press's)")
    print(f"{summary['presses']} presses of {args.archive} ({how['format']}, sensor {spec.name}: {settled}{turned}) "
          f"in {args.out} ({summary['object']}, depth by {summary['depth']}{rims}: median {d['median']:.3f} mm, "
          f"{d['min']:.3f} to {d['max']:.3f} mm; {summary['camera']})")
    return 0


def positive_int(text: str) -> int:
    """A whole number >= 1 on the command line (an argparse ``type``), e.g. ``--taps``."""
    import argparse

    try:
        value = int(text)
    except ValueError:
        value = 0
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be a whole number >= 1, got {text}")
    return value


def non_negative_int(text: str) -> int:
    """A whole number >= 0 on the command line (an argparse ``type``), e.g. ``--limit``."""
    import argparse

    try:
        value = int(text)
    except ValueError:
        value = -1
    if value < 0:
        raise argparse.ArgumentTypeError(f"expected a whole number >= 0, got {text!r}")
    return value


def add_limit_argument(p) -> None:
    """``--limit N``: only the first N taps of the protocol (0, the default: all); read it
    back as ``args.limit``."""
    p.add_argument("--limit", type=non_negative_int, default=0, metavar="N", help="only the first N taps (0: all)")


def add_quiet_argument(p) -> None:
    """``--quiet``: no progress bars on stderr; read it back as ``args.quiet`` (pass
    ``progress=not args.quiet``)."""
    p.add_argument("--quiet", action="store_true", help="no progress bars")


def add_renderer_arguments(p, skip: tuple[str, ...] = ()) -> None:
    """The renderers' options (``RENDERER_OPTIONS``) as arguments of ``p``, but those in
    ``skip`` (option keys); read them back with ``renderer_options``."""
    arguments = {
        "field": (("--field",), {"help": "phong: light field (default plane)"}),
        "background": (("--background",), {"help": "phong: none (default), solid, or a no-contact image path"}),
        "rectify": (("--rectify",), {"action": "store_true", "default": None,
                                     "help": "phong: rectify the light vectors"}),
        "elastic": (("--elastic",), {"choices": MODELS, "help": "phong: the membrane model, published (the paper's "
                                     "smoothing, default), layer (the elastic layer the pbr renderer deforms, so "
                                     "both renderers see one surface) or bonded (an elastic solid of the elastomer's "
                                     "thickness bonded to its support, flat membranes; needs the contact extra)"}),
        "target_rse": (("--target-rse",), {"type": float, "metavar": "R", "help": "pbr: add passes until the RMS "
                                           "relative standard error over the contact is at most R (default 0.05)"}),
        "max_passes": (("--max-passes",), {"type": int, "metavar": "N",
                                           "help": "pbr: at most N passes per sample (default 16)"}),
        "effects": (("--effect",), {"action": "append", "metavar": "NAME=VALUE",
                                    "help": "pbr: set one physical effect of pbr_tactile.effects.Effects "
                                            "(repeatable)"}),
        "estimator": (("--estimator",), {"help": "pbr: photons (default) or volpath"}),
        "inscatter": (("--inscatter",), {"help": "pbr: how the photon estimator's camera finds the light the "
                                         "elastomer scatters towards it: fluence (default; read from the photons' "
                                         "fluence on a voxel grid) or split (camera paths split and traced on)"}),
        "photons": (("--photons",), {"type": int, "help": "pbr: photons per LED per pass"}),
        "camera_spp": (("--camera-spp",), {"type": int, "help": "pbr: camera samples per pixel per pass"}),
        "kernel_radius_mm": (("--kernel-radius-mm",), {"type": float,
                                                       "help": "pbr: radius of the photon density estimate, mm"}),
        "no_contact_runs": (("--no-contact-runs",), {"type": int, "metavar": "M", "help": "pbr: no-contact photon "
                                                     "runs per pass in the cached no-contact map (0: off)"}),
        "profile": (("--profile",), {"metavar": "PROFILE.toml",
                                     "help": "render the calibrated unit of this profile (tactile-sim calibrate)"}),
        "film": (("--film",), {"type": _film_size, "metavar": "WxH",
                               "help": "pbr: render at WxH (the camera's aspect) and resample to the camera's size"}),
        "seed": (("--render-seed",), {"type": int, "metavar": "S",
                                      "help": "pbr: the renderer's random seed (default 0); another seed gives the "
                                              "same images with Monte Carlo noise of their own"}),
    }
    for key, (flags, kwargs) in arguments.items():
        if key not in skip:
            p.add_argument(*flags, **kwargs)


def bench_dataset(spec, workers: int = 2, objects=None, frames: int = 48, executor: str = "local",
                  address: str | None = None) -> dict:
    """Frames per second of base-protocol dataset generation, end to end, plus the parts.

    With ``executor="ray"`` the same protocol also runs on Ray (a local cluster of
    ``workers`` CPUs, or the one at ``address``), reported under ``ray`` with the ratio
    ``ray_over_local`` of end-to-end frames per second.
    """
    from .camera import Camera
    from .executors import make_executor
    from .generate import Job, TapRunner, generate
    from .body import checked_membrane
    from .indenters import INDENTERS
    from .renderers import get_renderer

    make_executor(executor, workers, address)  # bad input fails before the first run
    mesh = checked_membrane(spec)
    protocol = make_protocol("base", spec, mesh, tuple(objects or INDENTERS))
    phong = get_renderer("phong")
    options = {"field": "plane", "background": "none"}
    with tempfile.TemporaryDirectory() as tmp:
        # The parts, in one process: depth capture and rendering per frame.
        worker = TapRunner(Job(spec, phong.make_renderer, options, tuple(protocol.objects)))
        taps = protocol.taps[:frames]
        depth_ms, render_ms, depths = [], [], []
        worker.capture(taps[0])
        for tap in taps:
            t0 = time.perf_counter()
            depths.append(worker.capture(tap))
            depth_ms.append((time.perf_counter() - t0) * 1e3)
        for depth in depths:
            t0 = time.perf_counter()
            worker.renderer.render(depth)
            render_ms.append((time.perf_counter() - t0) * 1e3)
        worker.close()
        # End to end: the real command path into a fresh folder.
        summary = generate(Path(tmp) / "ds", spec, protocol, phong, options, workers=workers, progress=False)
        on_ray = None
        if executor == "ray":
            on_ray = generate(Path(tmp) / "ray", spec, protocol, phong, options, workers=workers, progress=False,
                              executor="ray", address=address)
    camera = Camera.from_spec(spec)
    results = {
        "frames_per_second": summary["new"] / summary["seconds"],
        "workers": workers,
        "steady_frames_per_second": summary["steady_frames_per_second"],
        "start_up_seconds": summary["start_up_seconds"],
        "ms_per_depth_frame": float(np.median(depth_ms)),
        "ms_per_render": float(np.median(render_ms)),
        "samples": summary["new"],
        "seconds": summary["seconds"],
        "protocol": "base",
        "resolution": [camera.width, camera.height],
        "renderer": "phong, plane field, no background; PNG + depth .npy written per sample",
        "cpus": os.cpu_count(),
        "note": "frames_per_second is end to end (worker start-up, rig compilation, capture, rendering, "
        "file writes); steady_frames_per_second leaves out the start-up, as a long run sees it",
        "executor": "local",
    }
    if on_ray is not None:
        fps = on_ray["new"] / on_ray["seconds"]
        results["ray"] = {
            "frames_per_second": fps,
            "steady_frames_per_second": on_ray["steady_frames_per_second"],
            "start_up_seconds": on_ray["start_up_seconds"],
            "seconds": on_ray["seconds"],
            "cluster": address or f"local, {workers} CPUs",
        }
        results["ray_over_local"] = fps / results["frames_per_second"]
        steady = (on_ray["steady_frames_per_second"], summary["steady_frames_per_second"])
        results["ray_over_local_steady"] = steady[0] / steady[1] if all(steady) else None
    return results


#: The slow renderers' bench slice of the base protocol, the same every time: four objects,
#: each at two tip and two cylinder taps, (row, position) on its paths.
SLICE_OBJECTS = ("sphere", "cylinder", "dots", "pacman")
SLICE_TAPS = ((0, 1), (1, 2), (2, 4), (0, 5))


def bench_dataset_slice(spec, renderer: str, options: dict, workers: int = 1, executor: str = "local",
                        address: str | None = None) -> dict:
    """Frames per hour of the renderer called ``renderer`` (``scenes.renderers.get_renderer``)
    on the fixed base-protocol slice (SLICE_OBJECTS x SLICE_TAPS), through ``generate`` as
    the dataset command runs it.

    The renderer's one-time preparation (``prepare``: for pbr the no-contact frame, which
    fills the no-contact photon cache) is timed apart, in a fresh cache; the runs then
    find it warm, as every run of a dataset after its first does. With ``executor="ray"``
    the slice runs on Ray too, into another folder, and ``ray_over_local`` compares
    end-to-end frames per hour.
    """
    from dataclasses import replace

    from .cache import CACHE_ENV
    from .camera import Camera
    from .dataset import read_samples
    from .executors import make_executor
    from .generate import generate
    from .body import checked_membrane
    from .renderers import get_renderer

    make_executor(executor, workers, address)  # bad input fails before any work
    mesh = checked_membrane(spec)
    camera = Camera.from_spec(spec)
    protocol = make_protocol("base", spec, mesh, SLICE_OBJECTS)
    taps = tuple(t for t in protocol.taps if (t.row, t.position) in SLICE_TAPS)
    protocol = replace(protocol, taps=taps)
    results = {"renderer": renderer, "options": options, "taps": len(taps), "objects": list(SLICE_OBJECTS),
               "workers": workers, "cpus": os.cpu_count()}
    with tempfile.TemporaryDirectory() as tmp:
        old = os.environ.get(CACHE_ENV)
        os.environ[CACHE_ENV] = str(Path(tmp) / "cache")
        try:
            t0 = time.perf_counter()
            plugin = get_renderer(renderer)
            settings = plugin.prepare(spec, mesh, camera, options)
            results["prepare_seconds"] = time.perf_counter() - t0
            results["settings"] = settings
            runs = {"local": None} if executor == "local" else {"local": None, "ray": address}
            for name, where in runs.items():
                root = Path(tmp) / name
                summary = generate(root, spec, protocol, plugin, options, workers=workers, progress=True,
                                   executor=name, address=where)
                records = read_samples(root)
                rse = [r["contact_rse"] for r in records if r.get("contact_rse") is not None]
                seconds = [r["seconds"] for r in records if "seconds" in r]
                steady = summary["steady_frames_per_second"]
                results[name] = {
                    "frames_per_hour": 3600 * summary["new"] / summary["seconds"],
                    "steady_frames_per_hour": 3600 * steady if steady else None,
                    "seconds": summary["seconds"], "start_up_seconds": summary["start_up_seconds"],
                    "samples": summary["new"], "refused": len(taps) - len(records),
                    "contact_rse_median": float(np.median(rse)) if rse else None,
                    "contact_rse_max": float(np.max(rse)) if rse else None,
                    "render_seconds_median": float(np.median(seconds)) if seconds else None,
                    "passes": [r.get("passes") for r in records],
                }
        finally:
            if old is None:
                os.environ.pop(CACHE_ENV, None)
            else:
                os.environ[CACHE_ENV] = old
    local = results["local"]
    film = settings.get("film", [camera.width, camera.height])
    results.update({"frames_per_hour": local["frames_per_hour"], "contact_rse_median": local["contact_rse_median"],
                    "refused": local["refused"], "resolution": film,
                    "ray_over_local": results["ray"]["frames_per_hour"] / local["frames_per_hour"]
                    if "ray" in results else None})
    return results


def cmd_bench_dataset(args) -> int:
    from .dataset import atomic_write_json

    spec = load_spec(args.spec)
    if args.renderer != "phong":
        options = renderer_options(args)
        results = bench_dataset_slice(spec, args.renderer, options, workers=args.workers or 1,
                                      executor=args.executor, address=args.address)
        atomic_write_json(Path(args.json), results)
        keys = ("frames_per_hour", "contact_rse_median", "refused", "resolution", "workers", "ray_over_local",
                "prepare_seconds")
        print(json.dumps({k: results[k] for k in keys}))
        return 0
    results = bench_dataset(spec, workers=args.workers or min(2, os.cpu_count() or 1), executor=args.executor,
                            address=args.address)
    atomic_write_json(Path(args.json), results)
    keys = ("frames_per_second", "workers", "ms_per_depth_frame", "ms_per_render", "ray_over_local")
    print(json.dumps({k: results[k] for k in keys if k in results}))
    return 0


def register(registry) -> None:
    p = registry.command("scene", cmd_scene, "the MuJoCo tapping rig: view it, snapshot it headless, or export its XML")
    p.add_argument("action", choices=["view", "snapshot", "export"])
    p.add_argument("--spec", metavar="TOML")
    p.add_argument("--object", default="sphere",
                   help="indenter name or STL path (default sphere); export takes 'all' or a comma list")
    p.add_argument("--tap", type=int, default=0, help="base-protocol tap to show (default 0)")
    p.add_argument("-o", "--output", default="rig_snapshot.png", help="PNG (snapshot) or folder (export)")
    p.add_argument("--width", type=int, default=1280)
    p.add_argument("--height", type=int, default=960)

    p = registry.command("dataset", cmd_dataset, "run a tapping protocol in MuJoCo and render a dataset (resumable), "
                         "or replay a capture of the rig at its measured poses (--replay)")
    p.add_argument("--replay", metavar="CAPTURE_DIR",
                   help="render the capture's samples (source 'real') with the rig at each one's measured_pose, its "
                        "sensor, protocol and sample ids, so that 'diagnose CAPTURE_DIR OUT' pairs them")
    p.add_argument("--spec", metavar="TOML")
    p.add_argument("--protocol", choices=["base", "extended"], help="base (default) or extended")
    p.add_argument("--objects", help="'all' (default) or comma-separated indenter names / STL paths")
    p.add_argument("--seed", type=int, help="seed of the extended protocol's perturbations (default 0)")
    p.add_argument("--renderer", default="phong", help="phong (the fast path) or pbr (the physically based reference)")
    add_renderer_arguments(p)
    p.add_argument("--workers", type=int, default=min(2, os.cpu_count() or 1))
    add_limit_argument(p)
    add_quiet_argument(p)
    p.add_argument("--executor", default="local",
                   help="local (processes on this machine, default) or ray (a Ray cluster; only this process "
                        "writes files)")
    p.add_argument("--address", metavar="HOST:PORT",
                   help="ray: the head of a running Ray cluster (default: start one here with --workers CPUs)")
    p.add_argument("--out", required=True, metavar="DIR")

    from .imports import DEPTH_METHODS
    from .press_sets import CHANNELS, COLUMNS, DEFAULTS, FORMATS, MARKERS, NO_CONTACT_NAMES, SET_RECORDS, TURNS

    p = registry.command("import", cmd_import, "import a set of real presses with known geometry (a published "
                         "archive, or a folder of images and a table) as a capture dataset that replay, compare, "
                         "calibrate and diagnose take")
    p.add_argument("format", choices=sorted(FORMATS), help="the archive's format (taxim: a Taxim calibration pack; "
                   "folder: a folder of PNG or JPEG frames, a no-contact frame and a CSV or JSON table of the "
                   "presses, docs/dataset-format.md)")
    p.add_argument("archive", metavar="ARCHIVE", help="the archive: a file, or a folder holding one; or the folder of "
                   f"presses. Its records ({SET_RECORDS} in the folder, or X.toml beside X.npz) give any option not "
                   "given here")
    p.add_argument("--out", required=True, metavar="DIR", help="the capture dataset's folder (new or empty, or the "
                   "same import's to complete it)")
    p.add_argument("--spec", metavar="TOML", help="the unit's sensor spec: a TOML, or a shipped sensor's name "
                   f"(digit, gelsight_mini, ...; default: the set's records', else {DEFAULTS['taxim']['spec'].name})")
    p.add_argument("--ball-mm", type=float, metavar="D", help="the ball's diameter, mm, for presses whose table "
                   f"gives none (taxim default {DEFAULTS['taxim']['ball_m'] * 1e3:g}; a folder has none)")
    p.add_argument("--pixel-mm", type=float, metavar="P", help="a pixel's size on the membrane at the frames' "
                   f"resolution, mm (taxim default {DEFAULTS['taxim']['pixel_m'] * 1e3:g}; a folder's: the spec's "
                   "camera's at the frames' size, where its axis meets the membrane)")
    p.add_argument("--turn", choices=[str(t) for t in TURNS] + ["auto"],
                   help="turn the frames, and their annotated centres with them, this many degrees clockwise (auto: "
                        "a quarter turn when their orientation is not the spec camera's); default 0: frames of "
                        "another aspect than the spec's camera set its sensor instead")
    p.add_argument("--table", metavar="FILE", help="folder: the press table (default: the folder's one .csv or .json)")
    p.add_argument("--no-contact", metavar="FILE", help="folder: the no-contact frame (default: the one named "
                   + ", ".join(NO_CONTACT_NAMES) + " with .png or .jpg)")
    p.add_argument("--columns", action="append", metavar="ROLE=NAME",
                   help="folder: a table column's name for a role (" + ", ".join(f"{k} (default {v})" for k, v in
                                                                         COLUMNS.items()) + "); repeat for more")
    p.add_argument("--channels", choices=CHANNELS, help="folder: how the images store their channels (default rgb, "
                   "as PNG and JPEG files are written by all but OpenCV)")
    p.add_argument("--markers", choices=MARKERS, help="printed marker dots on the membrane: keep them (default) or "
                   "find each frame's and fill them from around them (inpaint, scenes.markers)")
    p.add_argument("--depth", choices=DEPTH_METHODS,
                   help="each press's depth from its contact rim fitted to the image (profile, the default unless "
                        "the table gives every press's depth), from "
                        "its annotated radius (radius), or from that rim taken as the edge of the elastic contact "
                        "the spec's membrane makes (elastic: the bonded layer, needs the contact extra), or from a "
                        "joint fit of the layer and the presses' depths (fitted, with --depth-fit: tactile-sim "
                        "fit-elastic's report), or the table's own (given, the default where it gives every press's)")
    p.add_argument("--depth-fit", metavar="FIT.json",
                   help="with --depth fitted: the joint fit's report (its layer, share and fitted presses' depths)")
    p.add_argument("--rim-share", type=float, default=1.0, metavar="K",
                   help="with --depth profile: the share of the contact's radius at which a press's change peaks "
                        "(default 1: at the rim); the contact's radius is the peak's over K, at most the ball's")

    p = registry.bench("dataset", cmd_bench_dataset, "frames per second of base-protocol dataset generation")
    p.add_argument("--spec", metavar="TOML")
    p.add_argument("--renderer", default="phong",
                   help="phong (default: the whole base protocol) or another renderer plugin, e.g. pbr: frames per "
                        "hour on a fixed 16-tap slice of 4 objects")
    # the renderer's own options (pbr: --target-rse R, --inscatter, --photons N, ...), as the dataset command takes them
    add_renderer_arguments(p, skip=("field", "background", "rectify", "elastic"))
    p.add_argument("--workers", type=int,
                   help="local processes or Ray CPUs (default 2 for phong, 1 for pbr, which uses both cores)")
    p.add_argument("--executor", default="local",
                   help="local (default), or ray: run on Ray as well and report ray_over_local")
    p.add_argument("--address", metavar="HOST:PORT", help="ray: a running cluster's head (default: a local one)")
