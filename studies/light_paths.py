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
    m = spec.membrane
    change = {
        "leds_in_elastomer": dict(ring_radius=PUBLISHED_RING_M[0], height=PUBLISHED_RING_M[1]),
        "leds_under_wall": dict(ring_radius=m.core_radius - m.glass_wall / 2, height=m.base_z - 1e-3),
        "lambertian_leds": dict(beam_half_angle_rad=None),
        "point_leds": dict(count=1),
    }
    if name not in change:
        raise ValueError(f"unknown structure {name!r}; one of {', '.join(STRUCTURES)}")
    return spec.with_led_groups([dataclasses.replace(g, **change[name]) for g in spec.led_groups])


STRUCTURES = ("spec", "simulation_camera", "leds_in_elastomer", "leds_under_wall", "lambertian_leds", "point_leds")


def variant_grid(name: str, grid: dict | None = None) -> dict:
    """The effects grid a variant searches: its own (``VARIANTS``), or ``grid`` with the
    variant's switched-off effects (a single 0) kept off."""
    own = VARIANTS[name][0]
    if grid is None:
        return own
    return {**grid, **{k: v for k, v in own.items() if tuple(v) == (0.0,)}}


def run(out: str | Path, width: int = 160, photons: int = 1 << 18, spp: int = 32, bootstrap: int = 8,
        variants: list[str] | None = None, reference: str | Path | None = None, spec_path: str | Path | None = None,
        structures: list[str] | None = None, grid: dict | None = None) -> dict:
    """Calibrate each variant (``variants``, default all), or with ``structures`` each of
    those builds of the ``spec_path`` sensor with every mechanism on; the summary.
    ``grid``: the effects searched instead of each variant's (``variant_grid``)."""
    from pbr_tactile.calibrate import calibrate_background
    from pbr_tactile.calibrate_cli import write_outputs
    from scenes.camera import Camera
    from scenes.dataset import atomic_write_json
    from scenes.geometry import membrane_mesh
    from scenes.images import read_rgb
    from scenes.reference_data import require_reference_dir
    from scenes.spec import load_spec

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
        rows[name] = {"heldout_r2": rep["heldout_r2"], "heldout_r2_interval": rep["heldout_r2_interval"],
                      "best_effects": rep["best_effects"], "converged": rep["converged"],
                      "led_leak": rep["parameters"]["led_leak"], "led_leak_interval": rep["intervals"].get("led_leak"),
                      "saturated": rep["saturated"], "fov_y_rad": spec.camera.fov_y,
                      "scale": rep["parameters"]["scale"], "gamma": rep["parameters"]["gamma"]}
    summary = {"sensor": base.name, "variants": rows, "untested": UNTESTED}
    out.mkdir(parents=True, exist_ok=True)
    atomic_write_json(out / "summary.json", summary)
    lines = ["| variant | R² red [90 % CI] | R² green [90 % CI] | best effects | LED leak | converged |",
             "|---|---|---|---|---|---|"]
    for name, row in rows.items():
        r2, ci = row["heldout_r2"], row["heldout_r2_interval"]
        leak = ", ".join(f"{x:.2f}" for x in row["led_leak"])
        lines.append(f"| {name} | {r2['r']:.3f} [{ci['r'][0]:.3f}, {ci['r'][1]:.3f}] | {r2['g']:.3f} "
                     f"[{ci['g'][0]:.3f}, {ci['g'][1]:.3f}] | {row['best_effects']} | {leak} | {row['converged']} |")
    (out / "summary.md").write_text("\n".join(lines) + "\n")
    return summary


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
        from scenes.commands import name_values

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
