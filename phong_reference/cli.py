"""Subcommands of the fast path: demo, bake, render, bench phong, bench bake."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
from tqdm import tqdm

from scenes.camera import Camera, check_depth
from scenes.body import checked_membrane
from scenes.images import write_rgb
from scenes.reference_data import reference_dir
from scenes.shapes import family
from scenes.shapes.mesh import load_mesh
from scenes.spec_read import load_spec

from .bake import METHODS, bake_all


def _sensor(args):
    spec = load_spec(args.spec)
    mesh = load_mesh(args.mesh, units=args.units) if getattr(args, "mesh", None) else checked_membrane(spec)
    return spec, mesh, Camera.from_spec(spec)


def _add_sensor_args(p: argparse.ArgumentParser, mesh: bool = True,
                     spec_help: str = "sensor spec (default: the embedded GelTip)") -> None:
    p.add_argument("--spec", metavar="TOML", help=spec_help)
    if mesh:
        p.add_argument("--mesh", metavar="PATH", help="membrane mesh (STL/OBJ/PLY) in the camera frame, any shape")
        p.add_argument("--units", choices=["m", "mm"], default="m", help="units of --mesh (default m)")


def _methods(name: str) -> tuple[str, ...]:
    return METHODS if name == "all" else (name,)


def cmd_bake(args) -> int:
    from .figures import field_figure

    spec, mesh, camera = _sensor(args)
    fields, seconds = bake_all(mesh, camera, spec.leds, _methods(args.field))
    for method, lf in fields.items():
        share = lf.valid[:, camera.mask].mean()
        print(f"{method:9s} {seconds[method]:7.2f} s  valid {share:6.1%} of the image circle")
        if args.out:
            out = Path(args.out)
            out.mkdir(parents=True, exist_ok=True)
            np.savez_compressed(out / f"{method}_fields.npz", fields=lf.fields, valid=lf.valid, depth=lf.depth, normals=lf.normals)
            field_figure(mesh, lf, spec.leds, camera, out / f"{method}_fields.png")
    if args.out:
        print(f"wrote fields and figures to {args.out}")
    return 0


def _background(kind: str, camera):
    from .background import make_background

    return make_background(kind, camera)


def _profile(args, spec):
    """The calibrated unit's profile of ``--profile``, checked against the spec, or None."""
    if not getattr(args, "profile", None):
        return None
    if getattr(args, "background", None):
        raise ValueError("give --background or --profile, not both: the profile's background term is the "
                         "calibrated unit's (phong.background)")
    from scenes.profile import load_profile

    from .profiled import profile_background

    profile = load_profile(args.profile, spec)
    profile_background(profile, Camera.from_spec(spec))  # refuse a profile without the fast path's table
    return profile


def cmd_render(args) -> int:
    from .render import Renderer

    spec, mesh, camera = _sensor(args)
    try:
        depth = np.load(args.depth, allow_pickle=False)
    except (OSError, ValueError) as exc:
        raise ValueError(f"depth file {args.depth} could not be read as .npy: {exc}") from None
    check_depth(depth, camera, f"depth file {args.depth}")
    profile = _profile(args, spec)
    unit = spec if profile is None else profile.sensor_spec(spec)
    fields = bake_all(mesh, camera, unit.leds, (args.field,))[0][args.field]
    if args.ref_depth:
        ref = check_depth(np.load(args.ref_depth, allow_pickle=False), camera, f"ref depth {args.ref_depth}")
    else:
        ref = fields.depth
    from .render import light_vectors

    if profile is not None:
        from .profiled import ProfiledRenderer

        renderer = ProfiledRenderer(spec, ref, light_vectors(fields, args.rectify), profile, field=args.field)
    else:
        renderer = Renderer(spec, camera, ref, light_vectors(fields, args.rectify),
                            _background(args.background or "none", camera))
    image = renderer.render(depth)
    write_rgb(args.output, image)
    print(f"wrote {args.output}")
    return 0


#: The contact of the demo's sheet of every sensor (``--spec all``).
SHEET_CONTACT = "sphere_side"


def cmd_demo(args) -> int:
    if args.spec != "all":
        _demo(args, *_sensor(args), Path(args.out))
        return 0
    from scenes.spec import DEFAULT_SPEC_PATH, SENSORS_DIR

    from .figures import contact_sheet

    if getattr(args, "mesh", None):
        raise SystemExit("tactile-sim demo: --spec all renders the shipped sensors; drop --mesh")
    from .sources import snap_leds

    sheet = {}
    for path in [DEFAULT_SPEC_PATH, *sorted(p for p in SENSORS_DIR.glob("*.toml") if p != DEFAULT_SPEC_PATH)]:
        spec = load_spec(path)
        mesh = checked_membrane(spec)
        try:
            snap_leds(mesh, spec.leds)
        except ValueError as exc:  # a reference-only build: its LEDs are not at the membrane's edge
            print(f"skipping {spec.name!r} ({path.name}): the fast path cannot light it: {exc}")
            continue
        images = _demo(args, spec, mesh, Camera.from_spec(spec), Path(args.out) / spec.name)
        for (row, contact), image in images.items():
            method, background = row.split(" / ")
            if contact == SHEET_CONTACT and background == "solid":
                sheet[(spec.name, method)] = image
    contact_sheet(sheet, Path(args.out) / "contact_sheet.png")
    print(f"wrote every sensor's demo and contact_sheet.png (one row per sensor, {SHEET_CONTACT}, solid "
          f"background) to {args.out}")
    return 0


def _demo(args, spec, mesh, camera, out: Path) -> dict:
    """One sensor's demo in ``out``; returns its contact sheet's images."""
    import trimesh

    from scenes.contact import press

    from .figures import contact_sheet, field_figure
    from .render import Renderer

    (out / "images").mkdir(parents=True, exist_ok=True)
    (out / "depth").mkdir(parents=True, exist_ok=True)
    profile = _profile(args, spec)
    fields, _ = bake_all(mesh, camera, spec.leds, METHODS)
    ref = fields["linear"].depth
    # The contacts' pixels, as offsets from the centre of a 640x480 frame, scaled to this one's
    # width and height (a 240x320 DIGIT frame would put a 150 px offset outside it).
    sx, sy = camera.width / 640, camera.height / 480
    contacts = {
        "sphere_tip": (trimesh.primitives.Sphere(radius=0.004), (camera.cx + 20 * sx, camera.cy - 10 * sy), 0.0015),
        "sphere_side": (trimesh.primitives.Sphere(radius=0.003), (camera.cx - 150 * sx, camera.cy + 60 * sy), 0.0012),
        "box_edge": (trimesh.creation.box((0.004, 0.004, 0.004)), (camera.cx + 90 * sx, camera.cy + 110 * sy), 0.001),
        "cylinder": (trimesh.creation.cylinder(radius=0.002, height=0.006), (camera.cx + 60 * sx, camera.cy - 150 * sy),
                     0.0015),
    }
    depths = {}
    for name, (shape, pixel, depth_m) in tqdm(contacts.items(), desc="pressing contacts", unit="contact"):
        depths[name] = press(ref, camera, mesh, shape, pixel, depth_m, spin=0.3)
        np.save(out / "depth" / f"{name}.npy", depths[name])
    backgrounds = {"none": "none", "solid": "solid"}
    real = Path(args.real_background) if args.real_background else None
    if real is None and family(spec.membrane.shape).PUBLISHED and (published := reference_dir()) is not None:
        real = published / "real" / "bkg.png"  # the published GelTip's own
    if real is not None:
        backgrounds["real"] = str(real)
    else:
        print(f"no real no-contact image of {spec.name!r} (pass --real-background PATH); skipping that background")
    sheet = {}
    if profile is not None:
        backgrounds["profile"] = "profile"
        unit_fields, _ = bake_all(mesh, camera, profile.sensor_spec(spec).leds, METHODS)
    jobs = [(m, b) for m in METHODS for b in backgrounds]
    for method, bkg in tqdm(jobs, desc="rendering", unit="renderer"):
        if bkg == "profile":
            from .profiled import ProfiledRenderer
            from .render import light_vectors

            renderer = ProfiledRenderer(spec, ref, light_vectors(unit_fields[method]), profile, field=method)
        else:
            renderer = Renderer.from_fields(spec, camera, fields[method], _background(backgrounds[bkg], camera))
        for name, depth in depths.items():
            image = renderer.render(depth)
            write_rgb(out / "images" / f"{method}_{bkg}_{name}.png", image)
            sheet[(f"{method} / {bkg}", name)] = image
    contact_sheet(sheet, out / "contact_sheet.png")
    for method, lf in fields.items():
        field_figure(mesh, lf, spec.leds, camera, out / f"fields_{method}.png")
    print(f"wrote {len(sheet)} images, contact_sheet.png and field figures to {out}")
    return sheet


def cmd_bench_phong(args) -> int:
    from .bench import bench_phong, write_json

    results = bench_phong(load_spec(args.spec), frames=args.frames, repeats=args.repeats)
    write_json(args.json, results)
    print(json.dumps({k: results[k] for k in ("ms_per_frame_median", "baseline_ms_per_frame_median", "speedup")}))
    return 0


def cmd_bench_bake(args) -> int:
    from .bench import bench_bake, write_json

    results = bench_bake(load_spec(args.spec))
    write_json(args.json, results)
    print(json.dumps({"seconds": results["seconds"], "seconds_total": results["seconds_total"]}))
    return 0


def cmd_fit_elastic(args) -> int:
    from .elastic_fit import fit

    report = fit(args.capture, args.profile, args.out, progress=None if args.quiet else print)
    e, i = report["elastic"], report["intervals"]
    print(f"bonded layer h {e['thickness_m'] * 1e3:g} mm [{i['thickness_m'][0] * 1e3:g}, "
          f"{i['thickness_m'][1] * 1e3:g}], nu {e['poisson_ratio']:g} [{i['poisson_ratio'][0]:g}, "
          f"{i['poisson_ratio'][1]:g}]; depth share k {report['depth_share']['k']:.3f}; depths median "
          f"{report['depth_median_m'] * 1e3:.3f} mm (per press interval median width "
          f"{report['depth_interval_median_width_m'] * 1e3:.3f} mm); {len(report['reaches_support'])} reach the "
          f"support; wrote {args.out}")
    return 0


def register(registry) -> None:
    from scenes.commands import add_quiet_argument

    p = registry.command("fit-elastic", cmd_fit_elastic,
                         "fit the bonded layer's thickness and Poisson's ratio and each press's depth together to a "
                         "capture's fitted presses, with the fast path's calibrated profile "
                         "(phong_reference.elastic_fit)")
    p.add_argument("capture", metavar="CAPTURE", help="an imported capture of ball presses (tactile-sim import)")
    p.add_argument("--profile", required=True, metavar="PROFILE.toml",
                   help="the fast path calibrated on it (tactile-sim calibrate --fast-only): its field and lights")
    p.add_argument("--out", required=True, metavar="FIT.json", help="the report: the layer, the share k, every "
                   "press's depth (tactile-sim import --depth fitted --depth-fit FIT.json reads it)")
    add_quiet_argument(p)

    p = registry.command("demo", cmd_demo, "bake a sensor's light fields, press contacts and render every field and "
                         "background; --spec all: every shipped sensor, with a sheet of them all")
    _add_sensor_args(p, spec_help="sensor spec (default: the embedded GelTip), or 'all': every shipped sensor "
                                  "(the GelTip and scenes/sensors/*.toml)")
    p.add_argument("--out", default="demo_out", help="output folder (default demo_out)")
    p.add_argument("--real-background", metavar="PNG", help="real no-contact image (default: the published one, if found)")
    p.add_argument("--profile", metavar="PROFILE.toml",
                   help="also render the calibrated unit of this profile (tactile-sim calibrate), as background 'profile'")

    p = registry.command("bake", cmd_bake, "bake light fields (cached) for the sensor or any membrane mesh")
    _add_sensor_args(p)
    p.add_argument("--field", choices=METHODS + ("all",), default="all")
    p.add_argument("--out", metavar="DIR", help="also write the fields (.npz) and a figure of each")

    p = registry.command("render", cmd_render, "render one tactile image from a contact depth map")
    _add_sensor_args(p)
    p.add_argument("depth", metavar="DEPTH.npy", help="(H, W) float depth map, metres, planar z")
    p.add_argument("--field", choices=METHODS, default="plane")
    p.add_argument("--background", default=None, help="none (default), solid, or the path of a no-contact image")
    p.add_argument("--profile", metavar="PROFILE.toml",
                   help="render the calibrated unit of this profile (tactile-sim calibrate): its LEDs, alignment, "
                        "image circle and background term")
    p.add_argument("--ref-depth", metavar="REF.npy", help="no-contact depth D_ref (default: ray cast from the mesh)")
    p.add_argument("--rectify", action="store_true", help="project the field onto the undeformed tangent plane")
    p.add_argument("-o", "--output", required=True, metavar="OUT.png")

    p = registry.bench("phong", cmd_bench_phong, "fast path ms per 640x480 frame against the published model")
    _add_sensor_args(p, mesh=False)
    p.add_argument("--frames", type=int, default=16)
    p.add_argument("--repeats", type=int, default=3)

    p = registry.bench("bake", cmd_bench_bake, "cold-cache bake time of every light field method")
    _add_sensor_args(p, mesh=False)
