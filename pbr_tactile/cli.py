"""Subcommands of the physically based reference: reference."""

from __future__ import annotations

import argparse
import functools
from pathlib import Path

import numpy as np

from .fluence import INSCATTER


def _pixel(value: str) -> tuple[float, float]:
    """``U,V`` in pixels -> (u, v), for ``--at``."""
    try:
        u, v = (float(x) for x in value.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected U,V in pixels (column,row), e.g. 350,220; got {value!r}") from None
    return u, v


def _check_contact_args(args, parser: argparse.ArgumentParser | None = None) -> None:
    """The contact is DEPTH.npy, or --indenter with either --pose or --at and --depth-mm.

    Errors go through ``parser.error`` (usage, exit 2), or raise ValueError without a parser.
    """
    def fail(message: str):
        if parser is not None:
            parser.error(message)
        raise ValueError(message)

    at_options = [name for name, value in (("--depth-mm", args.depth_mm), ("--spin-deg", args.spin_deg))
                  if value is not None]
    if args.indenter is None:
        given = [name for name, value in (("--pose", args.pose), ("--at", args.at)) if value is not None]
        if given + at_options:
            fail(f"{', '.join(given + at_options)}: only with --indenter NAME_OR_PATH, not with DEPTH.npy")
    elif args.pose is None and args.at is None:
        fail("--indenter needs a pose: --pose POSE.npy, or --at U,V --depth-mm D")
    elif args.at is not None and args.depth_mm is None:
        fail("--at needs --depth-mm D, how deep the indenter presses along the surface normal")
    elif args.pose is not None and at_options:
        fail(f"{', '.join(at_options)}: only with --at, not with --pose")


def _contact_depth(args, ref, mesh, camera):
    """The contact depth map of --indenter at --pose, or pressed in at --at."""
    from scenes.contact import press
    from scenes.indenters import indenter

    from .contact import check_pose, contact_depth

    pose = None
    if args.pose is not None:
        try:
            pose = np.load(args.pose, allow_pickle=False)
        except (OSError, ValueError) as exc:
            raise ValueError(f"pose {args.pose} could not be read as .npy: {exc}") from None
        pose = check_pose(pose, f"pose {args.pose}")
    shape = indenter(args.indenter, units=args.indenter_units)
    if pose is not None:
        return contact_depth(shape, camera, ref, pose)
    spin = np.radians(args.spin_deg or 0.0)
    return press(ref, camera, mesh, shape, args.at, args.depth_mm * 1e-3, spin)


def cmd_reference(args, parser: argparse.ArgumentParser | None = None) -> int:
    from tqdm import tqdm

    from scenes.camera import Camera, check_depth, reference_depth
    from scenes.body import checked_membrane
    from scenes.images import srgb, write_rgb
    from scenes.spec_read import load_spec

    from .effects import Effects
    from .render import RenderSettings, reference

    _check_contact_args(args, parser)
    spec = load_spec(args.spec)
    profile = None
    if args.profile:
        from scenes.profile import load_profile

        from .profiled import profile_effects, reference_spec

        if args.estimator != "photons":
            raise ValueError("--profile needs the photon estimator (it renders one image per source)")
        profile = load_profile(args.profile, spec)
        spec = reference_spec(profile, spec)  # the unit's LEDs, laid out and turned as fitted
        effects = profile_effects(profile, args.effect)
    else:
        effects = Effects().with_settings(args.effect or [])
    camera = Camera.from_spec(spec)
    mesh = checked_membrane(spec)

    def npy(path, what):
        try:
            return check_depth(np.load(path, allow_pickle=False), camera, f"{what} {path}")
        except (OSError, ValueError) as exc:
            if isinstance(exc, ValueError) and what in str(exc):
                raise
            raise ValueError(f"{what} {path} could not be read as .npy: {exc}") from None

    ref = npy(args.ref_depth, "ref depth") if args.ref_depth else reference_depth(mesh, camera)[0]
    depth = _contact_depth(args, ref, mesh, camera) if args.indenter else npy(args.depth, "depth file")
    bar = tqdm(total=args.passes, desc="rendering", unit="pass")

    def progress(done, total):
        bar.update(done - bar.n)

    settings = RenderSettings(spp=args.spp, width=args.width, height=args.height, seed=args.seed,
                              variant=args.variant, passes=args.passes, estimator=args.estimator,
                              photons=args.photons, kernel_radius=args.kernel_radius_mm * 1e-3,
                              no_contact_runs=args.no_contact_runs, per_source=profile is not None,
                              inscatter=args.inscatter)
    est = reference(depth, ref, mesh, spec, camera, effects, settings, progress=progress)
    bar.close()
    out = output_paths(args.out)
    out["linear"].parent.mkdir(parents=True, exist_ok=True)
    np.save(out["linear"], est.mean)
    np.save(out["variance"], est.variance)
    if profile is not None:
        from .profiled import profiled_image
        from .scene import led_sources

        names = [s["name"] for s in led_sources(spec, effects)]
        write_rgb(out["image"], profiled_image(est.mean, names, profile, camera))
        print(f"wrote {out['linear']} (linear, one channel per source: {', '.join(names)}), {out['variance'].name} "
              f"and {out['image'].name} (the calibrated camera's image, profile {args.profile})")
        return 0
    h, w = est.mean.shape[:2]
    circle = camera.scaled(w, h).mask  # the spec's image circle: the lens draws nothing outside it
    scale = float(np.percentile(est.mean[circle], 99.5)) or 1.0
    write_rgb(out["image"], srgb(est.mean / scale) * circle[..., None])
    rel = np.nanmedian(est.relative_error[est.mean > 0]) if (est.mean > 0).any() else float("nan")
    print(f"wrote {out['linear']} (linear), {out['variance'].name} and {out['image'].name} (sRGB, scaled by "
          f"1/{scale:.3g}); median relative standard error {rel:.1%} at {est.spp} spp")
    return 0


#: Suffixes of the reference's own outputs, dropped from an --out stem that ends in one.
OUTPUT_SUFFIXES = (".npy", ".png")


def output_paths(stem: str) -> dict[str, Path]:
    """The files of ``reference --out STEM``: STEM.npy, STEM_variance.npy, STEM.png.

    The stem is kept whole, dots and all (``s_0.5`` gives ``s_0.5.npy``), except that a
    stem ending in one of the outputs' own suffixes (``frame.npy``, ``frame.png``) loses
    it: the user named one of the files, so all three sit beside it rather than becoming
    ``frame.npy.npy``.
    """
    stem = str(stem)
    if stem.lower().endswith(OUTPUT_SUFFIXES):
        stem = stem[: -len(".npy")]
    return {"linear": Path(stem + ".npy"), "variance": Path(stem + "_variance.npy"), "image": Path(stem + ".png")}


def cmd_bench_pbr(args) -> int:
    import json

    from scenes.dataset import atomic_write_json
    from scenes.spec_read import load_spec

    from .bench import bench_pbr

    results = bench_pbr(load_spec(args.spec), photons=args.photons, camera_spp=args.camera_spp,
                        volpath_spp=args.volpath_spp, no_contact_runs=args.no_contact_runs)
    atomic_write_json(Path(args.json), results)
    print(json.dumps({k: results[k] for k in ("seconds_to_2pct", "fluence_seconds_to_2pct", "volpath_seconds_to_2pct",
                                              "speedup", "fluence_speedup", "variant")}))
    return 0


def cmd_bench_solids(args) -> int:
    import json

    from scenes.dataset import atomic_write_json
    from scenes.body import checked_membrane
    from scenes.indenters import INDENTERS
    from scenes.protocol import base_protocol, extended_protocol
    from scenes.spec_read import load_spec

    from .protocol_check import check_protocol

    spec = load_spec(args.spec)
    mesh = checked_membrane(spec)
    if args.protocol == "base":
        protocol = base_protocol(spec, mesh, INDENTERS)
    else:
        protocol = extended_protocol(spec, mesh, INDENTERS, seed=args.protocol_seed)
    summary = check_protocol(spec, protocol, sample=args.sample, seed=args.seed, edge=args.edge_mm * 1e-3,
                             progress=True)
    atomic_write_json(Path(args.json), summary)
    print(json.dumps({k: summary[k] for k in ("protocol", "taps", "built", "median_build_seconds", "seconds")}))
    for r in summary["refused"]:
        print(f"refused: tap {r['tap_index']} ({r['object']}): {r['error']}")
    return 0 if not summary["refused"] else 1


def register(registry) -> None:
    from scenes.commands import non_negative_int, positive_int
    from scenes.indenters import INDENTERS

    p = registry.command("reference", cmd_reference, "render one frame with the physically based reference (Mitsuba 3)")
    p.set_defaults(func=functools.partial(cmd_reference, parser=p))  # its contact options depend on each other
    p.epilog = ("the contact, exactly one of: DEPTH.npy; --indenter NAME_OR_PATH --pose POSE.npy; "
                "--indenter NAME_OR_PATH --at U,V --depth-mm D [--spin-deg S]")
    source = p.add_mutually_exclusive_group(required=True)
    source.add_argument("depth", nargs="?", metavar="DEPTH.npy", help="(H, W) float contact depth map, metres, planar z")
    source.add_argument("--indenter", metavar="NAME_OR_PATH",
                        help=f"contact an indenter instead: {', '.join(INDENTERS)}, or a closed mesh file")
    p.add_argument("--indenter-units", choices=["mm", "m"], default="mm", help="units of an --indenter mesh file")
    place = p.add_mutually_exclusive_group()
    place.add_argument("--pose", metavar="POSE.npy",
                       help="(4, 4) rigid transform, metres, from the indenter's frame (+z towards the membrane) "
                       "to the sensor (camera) frame")
    place.add_argument("--at", type=_pixel, metavar="U,V",
                       help="press the indenter in where the camera sees pixel (U, V), along the surface normal")
    p.add_argument("--depth-mm", type=float, metavar="D", help="with --at: indentation depth, millimetres")
    p.add_argument("--spin-deg", type=float, metavar="S", help="with --at: turn about the normal, degrees (default 0)")
    p.add_argument("--ref-depth", metavar="REF.npy", help="no-contact depth D_ref (default: ray cast from the mesh)")
    p.add_argument("--spec", metavar="TOML")
    p.add_argument("--spp", type=int, default=64, help="samples per pixel in all")
    p.add_argument("--passes", type=int, default=4, help="independent passes, for the variance estimate")
    p.add_argument("--width", type=int, help="film width (default: the camera's)")
    p.add_argument("--height", type=int, help="film height (default: the camera's)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--estimator", choices=["photons", "volpath"], default="photons",
                   help="photons (two-pass, fast) or volpath (brute force)")
    p.add_argument("--photons", type=int, default=1 << 20, help="photons per LED per pass")
    p.add_argument("--inscatter", choices=list(INSCATTER), default="fluence",
                   help="photons: the light the elastomer scatters towards the camera, read from the photons' "
                        "fluence on a voxel grid (default: less noise, faster) or by split camera paths (the old "
                        "estimator)")
    p.add_argument("--effect", action="append", metavar="NAME=VALUE",
                   help="set one physical effect of pbr_tactile.effects.Effects, e.g. contact_shadow=false or "
                        "scattering_per_m=0 (repeatable)")
    p.add_argument("--kernel-radius-mm", type=float, default=0.75,
                   help="radius of the photon density estimate, mm (bias ~ r^2, noise ~ 1/r)")
    p.add_argument("--no-contact-runs", type=non_negative_int, default=0, metavar="M",
                   help="for a contact: its photon map as the sensor's cached no-contact map (M runs per pass) "
                        "plus the contact's change; the first contact of a sensor fills the cache, later ones "
                        "cost the same with less noise, most of all away from the contact (default 0: off)")
    p.add_argument("--variant", help="Mitsuba variant (default: $TACTILE_SIM_MI_VARIANT, then the fallback chain)")
    p.add_argument("--profile", metavar="PROFILE.toml",
                   help="render as the calibrated sensor of this profile (tactile-sim calibrate): its effects, LED "
                        "gains, alignment and camera response; --effect settings apply on top")
    p.add_argument("--out", required=True,
                   help="output stem: writes STEM.npy, STEM_variance.npy and STEM.png (the stem is kept whole, dots "
                        "and all; a stem ending in .npy or .png drops that suffix)")

    p = registry.bench("pbr", cmd_bench_pbr, "reference: seconds to 2 %% noise at 320x240, photons (split and fluence) vs volpath")
    p.add_argument("--spec", metavar="TOML")
    p.add_argument("--photons", type=int, default=1 << 20, help="photons per LED per pass")
    p.add_argument("--camera-spp", type=int, default=16, help="camera samples per pixel per pass (photons)")
    p.add_argument("--volpath-spp", type=int, default=16)
    p.add_argument("--no-contact-runs", type=non_negative_int, default=8, metavar="M",
                   help="time a contact with the sensor's no-contact runs cached (M per pass; the cold first run "
                        "is reported too); 0: plain photon maps")

    p = registry.bench("solids", cmd_bench_solids,
                       "does the reference build every tap of a protocol? elastomer solids from MuJoCo captures")
    p.add_argument("--spec", metavar="TOML")
    p.add_argument("--protocol", choices=["base", "extended"], default="extended")
    p.add_argument("--protocol-seed", type=int, default=0, help="seed of the extended protocol's perturbations")
    p.add_argument("--sample", type=positive_int, metavar="N",
                   help="check a seeded sample of N taps (default: every tap)")
    p.add_argument("--seed", type=int, default=0, help="seed of the sample")
    p.add_argument("--edge-mm", type=float, default=0.25, help="refined edge of the membrane, mm (the reference's)")

    from .gpu_run import add_run_arguments, cmd_merge, cmd_run, cmd_wheels

    what = ("the reference's benches on the GPU (cuda_ad_spectral), each budgeted, in one JSON "
            "(pbr_tactile/gpu_run.py); without a CUDA device it says so and exits 0")
    p = registry.bench("gpu", cmd_run, what)
    add_run_arguments(p)
    p = registry.command("gpu", lambda args: p.print_help() or 2,
                         "the reference's benches on a GPU machine: the wheels it needs, the run, the merge "
                         "with a CPU run (docs/gpu.md)")
    steps = p.add_subparsers(dest="step", metavar="STEP")
    step = steps.add_parser("wheels", help="here: the wheel set the GPU machine needs, into --dir")
    step.add_argument("--dir", default=".whl", help="the wheel folder (default .whl; git must ignore it)")
    step.add_argument("--repo", default=".", help="the repository to build the project's wheel from (default .)")
    step.add_argument("--no-gl", action="store_true", help="leave out the GL loaders' Debian packages")
    step.add_argument("--jobs", type=int, default=2, help="processes rewriting wheels (default 2)")
    step.set_defaults(func=cmd_wheels)
    step = steps.add_parser("run", help="on the GPU machine: " + what)
    step.add_argument("--json", required=True, metavar="PATH", help="where to write the run's JSON")
    add_run_arguments(step)
    step.set_defaults(func=cmd_run)
    step = steps.add_parser("merge", help="two runs' JSONs (GPU, CPU) side by side in one")
    step.add_argument("gpu", metavar="GPU.json")
    step.add_argument("cpu", metavar="CPU.json")
    step.add_argument("--json", required=True, metavar="PATH")
    step.set_defaults(func=cmd_merge)
