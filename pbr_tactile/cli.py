"""Subcommands of the physically based reference: reference."""

from __future__ import annotations

from pathlib import Path

import numpy as np


def srgb(linear: np.ndarray) -> np.ndarray:
    """Linear [0, 1] -> sRGB-encoded [0, 1] (IEC 61966-2-1), for viewing only."""
    x = np.clip(linear, 0.0, 1.0)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1 / 2.4) - 0.055)


def cmd_reference(args) -> int:
    from tqdm import tqdm

    from scenes.camera import Camera, check_depth, reference_depth
    from scenes.geometry import membrane_mesh
    from scenes.images import write_rgb
    from scenes.spec import load_spec

    from .effects import Effects
    from .render import reference

    spec = load_spec(args.spec)
    camera = Camera.from_spec(spec)
    mesh = membrane_mesh(spec)

    def npy(path, what):
        try:
            return check_depth(np.load(path, allow_pickle=False), camera, f"{what} {path}")
        except (OSError, ValueError) as exc:
            if isinstance(exc, ValueError) and what in str(exc):
                raise
            raise ValueError(f"{what} {path} could not be read as .npy: {exc}") from None

    depth = npy(args.depth, "depth file")
    ref = npy(args.ref_depth, "ref depth") if args.ref_depth else reference_depth(mesh, camera)[0]
    bar = tqdm(total=args.passes, desc="rendering", unit="pass")

    def progress(done, total):
        bar.update(done - bar.n)

    est = reference(depth, ref, mesh, spec, camera, Effects(), spp=args.spp, width=args.width, height=args.height,
                    seed=args.seed, variant=args.variant, progress=progress, passes=args.passes,
                    estimator=args.estimator, photons=args.photons)
    bar.close()
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    np.save(out.with_suffix(".npy"), est.mean)
    np.save(out.with_name(out.stem + "_variance.npy"), est.variance)
    mask = np.ones(est.mean.shape[:2], bool)
    scale = float(np.percentile(est.mean[mask], 99.5)) or 1.0
    write_rgb(out.with_suffix(".png"), srgb(est.mean / scale))
    rel = np.nanmedian(est.relative_error[est.mean > 0]) if (est.mean > 0).any() else float("nan")
    print(f"wrote {out.with_suffix('.npy')} (linear), _variance.npy and .png (sRGB, scaled by 1/{scale:.3g}); "
          f"median relative standard error {rel:.1%} at {est.spp} spp")
    return 0


def cmd_bench_pbr(args) -> int:
    import json

    from scenes.spec import load_spec

    from .bench import bench_pbr

    from scenes.dataset import atomic_write_json

    results = bench_pbr(load_spec(args.spec), photons=args.photons, volpath_spp=args.volpath_spp)
    atomic_write_json(Path(args.json), results)
    print(json.dumps({k: results[k] for k in ("seconds_to_2pct", "volpath_seconds_to_2pct", "speedup", "variant")}))
    return 0


def register(registry) -> None:
    p = registry.command("reference", cmd_reference, "render one frame with the physically based reference (Mitsuba 3)")
    p.add_argument("depth", metavar="DEPTH.npy", help="(H, W) float contact depth map, metres, planar z")
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
    p.add_argument("--variant", help="Mitsuba variant (default: $TACTILE_SIM_MI_VARIANT, then the fallback chain)")
    p.add_argument("--out", required=True, help="output stem: writes STEM.npy, STEM_variance.npy and STEM.png")

    p = registry.bench("pbr", cmd_bench_pbr, "reference: seconds to 2 %% noise at 320x240, photons vs volpath")
    p.add_argument("--spec", metavar="TOML")
    p.add_argument("--photons", type=int, default=1 << 18, help="photons per LED per pass")
    p.add_argument("--volpath-spp", type=int, default=16)
