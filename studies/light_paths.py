"""Study: what carries light to where the camera sees it in the real GelTip?

The paper concludes that much of it travels through the glass core. Here the reference
is calibrated to the one real no-contact image (``pbr_tactile.calibrate``) with each
light-path mechanism on and off, and the held-out R^2 (odd angular sectors, with
bootstrap intervals over them) says which mechanisms the image needs:

- ``full``: every mechanism, absorption and scattering searched on the default grid;
- ``no_leak``: no light into the glass core (the leak fixed at 0);
- ``no_scattering``: a clear elastomer (scattering 0), absorption searched;
- ``no_absorption``: a lossless elastomer (absorption 0), scattering searched;
- ``guided_only``: neither scattering nor the core leak: light reaches the coating only
  straight from the LEDs or guided by reflection in the membrane.

With ``--structures``, the sensor's build is varied too (a sensor spec with LED groups,
such as ``scenes/sensors/geltip_2023.toml``), each structure calibrated with every
mechanism on (``full``):

- ``spec``: the spec as it is;
- ``simulation_camera``: the published simulation's 90-degree pinhole instead of the
  spec's field of view;
- ``leds_in_elastomer``: the groups on the published simulation's ring (12 mm, in the
  camera's plane), which puts each LED in the elastomer wall;
- ``leds_under_wall``: the groups under the glass wall's end (its light guided up the
  wall from its foot);
- ``lambertian_leds``: no beam: each LED Lambertian;
- ``point_leds``: one LED per group at its arc's centre, as the published simulation.

One geometric check goes with them: the real image's lit sectors share a sharp circular
edge (``real_edge``), and the one circle a capsule's membrane has about the axis is its
dome's junction; each build's row gives where its camera, and the lens its calibration
fitted, see that junction (``junction_rho``, refraction through the glass and the
elastomer included).

Coating gloss needs the volumetric path tracer (the photon estimator needs a diffuse
coating), whose per-source basis this study does not render: it is reported as untested.

Run: ``python -m studies.light_paths --out DIR [--width 160 --spec TOML --structures
NAME,... --grid NAME=V1,V2,... --bootstrap B]``; writes ``DIR/<variant>/`` (the
calibration outputs) and ``DIR/summary.json``, ``DIR/summary.md``.
"""

from __future__ import annotations

import argparse
import dataclasses
import math
from pathlib import Path

#: Each variant: (grid of effects, leak on).
VARIANTS = {
    "full": ({"absorption_per_m": (5.0, 20.0, 80.0), "scattering_per_m": (10.0, 50.0, 250.0)}, True),
    "no_leak": ({"absorption_per_m": (5.0, 20.0, 80.0), "scattering_per_m": (10.0, 50.0, 250.0)}, False),
    "no_scattering": ({"absorption_per_m": (5.0, 20.0, 80.0), "scattering_per_m": (0.0,)}, True),
    "no_absorption": ({"absorption_per_m": (0.0,), "scattering_per_m": (10.0, 50.0, 250.0)}, True),
    "guided_only": ({"absorption_per_m": (5.0, 20.0, 80.0), "scattering_per_m": (0.0,)}, False),
}
UNTESTED = {"coating_gloss": "needs the volumetric path tracer, whose per-source basis is not rendered here"}
#: The published simulation's LED ring: radius and height in the camera frame, m.
PUBLISHED_RING_M = (0.012, 0.0)


def structure(spec, name: str):
    """The sensor ``spec`` with one structural change (module doc); a ValueError for a
    structure the spec cannot take (one without LED groups)."""
    if name == "spec":
        return spec
    if name == "simulation_camera":
        return spec.replace(camera=dataclasses.replace(spec.camera, fov_y=math.pi / 2))
    if not spec.led_groups:
        raise ValueError(f"structure {name!r} varies LED groups; sensor {spec.name!r} has none")
    change = {
        "leds_in_elastomer": dict(ring_radius=PUBLISHED_RING_M[0], height=PUBLISHED_RING_M[1]),
        "lambertian_leds": dict(beam_half_angle_rad=None),
        "point_leds": dict(count=1),
    }
    if name == "leds_under_wall":  # under the glass tube's wall: a body known in closed form
        from scenes.shapes import family

        m = spec.membrane
        tube = family(m.shape).tube(m)
        if tube is None:
            raise ValueError(f"structure 'leds_under_wall' seats the LEDs under the glass tube's wall; sensor "
                             f"{spec.name!r}'s {m.shape!r} membrane has no tube known in closed form")
        change[name] = dict(ring_radius=tube.core_radius - m.glass_wall / 2, height=tube.base_z - 1e-3)
    if name not in change:
        raise ValueError(f"unknown structure {name!r}; one of {', '.join(STRUCTURES)}")
    from scenes.spec_read import with_led_groups

    return with_led_groups(spec, [dataclasses.replace(g, **change[name]) for g in spec.led_groups])


STRUCTURES = ("spec", "simulation_camera", "leds_in_elastomer", "leds_under_wall", "lambertian_leds", "point_leds")


def variant_grid(name: str, grid: dict | None = None) -> dict:
    """The effects grid a variant searches: its own (``VARIANTS``), or ``grid`` with the
    variant's switched-off effects (a single 0) kept off."""
    own = VARIANTS[name][0]
    if grid is None:
        return own
    return {**grid, **{k: v for k, v in own.items() if tuple(v) == (0.0,)}}


#: The real image's radial edges are looked for between these shares of the circle's
#: radius (the tip's bright spot and the rim's fall are not membrane structure).
EDGE_BAND = (0.1, 0.9)


def radial_edges(image, circle: tuple[float, float, float], sectors: int = 24, samples: int = 100):
    """Per angular sector of the image circle (``circle`` (cx, cy, radius) px), the radius
    (as a share of the circle's) where the summed channels rise most steeply outwards, and
    that rise over one tenth of the radius; two (sectors,) arrays. Sector k spans
    [k, k + 1) 2 pi / sectors from +u towards +v."""
    import numpy as np
    from scipy import ndimage
    from skimage.transform import warp_polar

    image = np.asarray(image, np.float64)
    grey = image.sum(axis=2) if image.ndim == 3 else image
    if len(circle) != 3 or not all(math.isfinite(float(c)) for c in circle) or not circle[2] > 0:
        raise ValueError(f"radial_edges: circle must be (cx, cy, radius) px with radius > 0, got {circle!r}")
    cx, cy, radius = (float(c) for c in circle)
    per = 8  # angles averaged per sector
    rho = np.arange(samples) / samples  # warp_polar's radii, as shares of the circle's
    polar = warp_polar(grey, center=(cy, cx), radius=radius, output_shape=(sectors * per, samples), order=1,
                       mode="edge").reshape(sectors, per, samples).mean(axis=1)
    slope = np.gradient(ndimage.gaussian_filter1d(polar, 1.5, axis=1), axis=1) * samples / 10
    band = (rho >= EDGE_BAND[0]) & (rho <= EDGE_BAND[1])
    at = np.argmax(np.where(band, slope, -np.inf), axis=1)
    return rho[at], slope[np.arange(sectors), at]


def junction_rho(spec, lens=None) -> float:
    """Where the spec's camera sees the painted surface's ring at the dome's junction, as a
    share of the image circle's radius: the ray from the camera refracted into the glass
    and the elastomer (Snell, in the plane through the axis), through the spec's lens, or
    ``lens`` (a Camera: a calibration's, ``Alignment.lens``). Only for a body known in
    closed form (its family's ``tube``: a capsule), whose junction is a ring about the
    camera's axis."""
    import numpy as np
    from scipy import optimize

    from pbr_tactile.scene import IOR_AIR, IOR_SILICONE
    from scenes.camera import Camera, lens_radius
    from scenes.shapes import family

    m = spec.membrane
    tube = family(m.shape).tube(m)
    if tube is None:
        raise ValueError(f"junction_rho: sensor {spec.name!r} is a {m.shape!r}, not a capsule")
    z_junction = tube.junction_z
    inner, glass, paint = tube.core_radius - m.glass_wall, tube.core_radius, tube.radius

    def height(theta):  # where the ray at theta off the axis meets the painted surface
        c = math.cos(theta)
        t_glass = math.asin(IOR_AIR * c / m.glass_ior)
        t_elastomer = math.asin(IOR_AIR * c / IOR_SILICONE)
        return inner / math.tan(theta) + (glass - inner) * math.tan(t_glass) + (paint - glass) * math.tan(t_elastomer)

    theta = optimize.brentq(lambda t: height(t) - z_junction, 1e-4, math.pi / 2 - 1e-4)
    camera = Camera.from_spec(spec) if lens is None else lens
    r = camera.f * float(lens_radius(np.array(theta), camera.k1, camera.k2, camera.projection))
    return r / camera.mask_radius_px


def real_edge(image, circle: tuple[float, float, float]) -> dict:
    """The real image's circular edge (``radial_edges``): its radius's median and range
    over the sectors whose rise is at least half the steepest (where light shows it)."""
    import numpy as np

    rho, rise = radial_edges(image, circle)
    lit = rise >= 0.5 * rise.max()
    return {"rho_median": float(np.median(rho[lit])), "rho_range": [float(rho[lit].min()), float(rho[lit].max())],
            "sectors": int(lit.sum()), "of": int(len(rho))}


def run(out: str | Path, width: int = 160, photons: int = 1 << 18, spp: int = 32, bootstrap: int = 8,
        variants: list[str] | None = None, reference: str | Path | None = None, spec_path: str | Path | None = None,
        structures: list[str] | None = None, grid: dict | None = None) -> dict:
    """Calibrate each variant (``variants``, default all), or with ``structures`` each of
    those builds of the ``spec_path`` sensor with every mechanism on; the summary.
    ``grid``: the effects searched instead of each variant's (``variant_grid``)."""
    from pbr_tactile.calibrate import calibrate_background
    from pbr_tactile.calibrate_capture import write_outputs
    from pbr_tactile.real_image import image_circle
    from scenes.camera import Camera
    from scenes.profile import Alignment
    from scenes.dataset import atomic_write_json
    from scenes.geometry import membrane_mesh
    from scenes.images import read_rgb
    from scenes.reference_data import require_reference_dir
    from scenes.shapes import family
    from scenes.spec_read import load_spec

    folder = require_reference_dir(reference)
    base = load_spec(spec_path)
    real = read_rgb(folder / "real" / "bkg.png")
    out = Path(out)
    rows = {}
    runs = ([(name, base, variant_grid(name, grid), VARIANTS[name][1]) for name in variants or list(VARIANTS)]
            if structures is None else
            [(name, structure(base, name), variant_grid("full", grid), VARIANTS["full"][1]) for name in structures])
    for name, spec, grid, leak in runs:
        camera = Camera.from_spec(spec)
        mesh = membrane_mesh(spec)
        cal = calibrate_background(real, spec, mesh, camera, film=(width, width * 3 // 4), grid=grid, photons=photons,
                                   spp=spp, bootstrap=bootstrap, leak=leak)
        write_outputs(cal, out / name, f"real/bkg.png, variant {name}")
        rep = cal.report
        par = rep["parameters"]
        fitted = Alignment(0.0, par["scale"], (0.0, 0.0), distortion=(par["k1"], camera.k2)).lens(camera)
        tube = family(spec.membrane.shape).tube(spec.membrane)
        rows[name] = {"junction_rho": junction_rho(spec) if tube is not None else None,
                      "fitted_junction_rho": junction_rho(spec, fitted) if tube is not None else None,
                      "heldout_r2": rep["heldout_r2"], "heldout_r2_interval": rep["heldout_r2_interval"],
                      "best_effects": rep["best_effects"], "converged": rep["converged"],
                      "led_leak": rep["parameters"]["led_leak"], "led_leak_interval": rep["intervals"].get("led_leak"),
                      "saturated": rep["saturated"], "fov_y_rad": spec.camera.fov_y,
                      "scale": rep["parameters"]["scale"], "gamma": rep["parameters"]["gamma"]}
    circle = image_circle(real)
    edge = real_edge(real, circle) if circle is not None else None
    summary = {"sensor": base.name, "variants": rows, "untested": UNTESTED, "real_edge": edge}
    out.mkdir(parents=True, exist_ok=True)
    atomic_write_json(out / "summary.json", summary)
    lines = ["| variant | R² red [90 % CI] | R² green [90 % CI] | best effects | LED leak | converged | junction's "
             "ρ: spec, fitted lens |", "|---|---|---|---|---|---|---|"]
    for name, row in rows.items():
        r2, ci = row["heldout_r2"], row["heldout_r2_interval"]
        leak = ", ".join(f"{x:.2f}" for x in row["led_leak"])
        lines.append(f"| {name} | {r2['r']:.3f} [{ci['r'][0]:.3f}, {ci['r'][1]:.3f}] | {r2['g']:.3f} "
                     f"[{ci['g'][0]:.3f}, {ci['g'][1]:.3f}] | {row['best_effects']} | {leak} | {row['converged']} | "
                     f"{_rho(row['junction_rho'])}, {_rho(row['fitted_junction_rho'])} |")
    if edge is not None:
        lines += ["", f"The real image's circular edge (`real_edge`): ρ {edge['rho_median']:.3f} (median; "
                  f"{edge['rho_range'][0]:.3f} to {edge['rho_range'][1]:.3f} over {edge['sectors']} of {edge['of']} "
                  "sectors). The dome's junction, where each build's camera and its fitted lens see it, is in the "
                  "table's last column."]
    (out / "summary.md").write_text("\n".join(lines) + "\n")
    return summary


def _rho(value) -> str:
    return "-" if value is None else f"{value:.3f}"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", required=True)
    parser.add_argument("--width", type=int, default=160)
    parser.add_argument("--photons", type=int, default=1 << 18)
    parser.add_argument("--spp", type=int, default=32)
    parser.add_argument("--bootstrap", type=int, default=8)
    parser.add_argument("--variants", help=f"comma-separated subset of {', '.join(VARIANTS)}")
    parser.add_argument("--reference", help="the published data folder (default: scenes.reference_data)")
    parser.add_argument("--spec", help="the sensor spec TOML (default: the published simulation's)")
    parser.add_argument("--structures", help=f"comma-separated builds of the sensor instead: {', '.join(STRUCTURES)}")
    parser.add_argument("--grid", action="append", metavar="NAME=V1,V2,...",
                        help="effects searched instead of each variant's grid (repeatable); a variant's switched-off "
                             "effect stays off")
    args = parser.parse_args(argv)
    variants = args.variants.split(",") if args.variants else None
    for name in variants or []:
        if name not in VARIANTS:
            parser.error(f"unknown variant {name!r}; one of {', '.join(VARIANTS)}")
    structures = args.structures.split(",") if args.structures else None
    for name in structures or []:
        if name not in STRUCTURES:
            parser.error(f"unknown structure {name!r}; one of {', '.join(STRUCTURES)}")
    if structures and variants:
        parser.error("--structures calibrates every mechanism on; it takes no --variants")
    grid = None
    if args.grid:
        from scenes.settings import name_values

        try:
            grid = name_values(args.grid, "--grid", "NAME=V1,V2,... (an effect and its values)")
        except ValueError as exc:
            parser.error(str(exc))
    summary = run(args.out, args.width, args.photons, args.spp, args.bootstrap, variants, args.reference, args.spec,
                  structures, grid)
    print((Path(args.out) / "summary.md").read_text())
    return 0 if summary else 1


if __name__ == "__main__":
    raise SystemExit(main())
