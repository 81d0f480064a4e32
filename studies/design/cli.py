"""``tactile-sim design``: sweep a sensor's design parameters, score them with the fast
path, check the best and the worst with the reference, and report."""

from __future__ import annotations

import argparse
from pathlib import Path

from scenes.commands import add_quiet_argument, positive_int

from .loop import FIELD, INDENTER, REFERENCE_TAPS, STANDARD_DEPTH_M


def _sweep(text: str):
    from .sweep import parse_sweep

    try:
        return parse_sweep(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def cmd_design(args) -> int:
    from scenes.spec_read import load_spec
    from studies.pbr_field_comparison.frames import Settings

    from . import report
    from .loop import run

    names = [name for name, _ in args.sweep]
    if len(set(names)) != len(names):
        raise ValueError(f"--sweep names a parameter twice: {names}")
    settings = Settings(width=args.width, height=args.height, photons=args.photons, passes=args.passes, spp=args.spp)
    data = run(load_spec(args.spec), dict(args.sweep), Path(args.out), field=args.field, indenter=args.indenter,
               taps=args.taps, reference=not args.no_reference, reference_taps=args.reference_taps,
               settings=settings, progress=not args.quiet, depth=args.depth * 1e-3)
    print(report.markdown(data))
    print(f"wrote {args.out}/design.json, summary.md, sweep.png, maps.png and check.png")
    return 0


def register(registry) -> None:
    from phong_reference.bake import METHODS
    from scenes.indenters import INDENTERS

    p = registry.command("design", cmd_design,
                         "sweep one or two design parameters of a sensor (a shape family's, thickness, led_height), "
                         "score each design's standard taps with the fast path (contrast per mm in camera-noise units, "
                         "its spread, dead taps), check the best and the worst with the physically based reference, "
                         "and write a report with images (--spec TOML --sweep NAME=START:STOP:COUNT --out DIR)")
    p.add_argument("--spec", metavar="TOML", help="sensor spec (default: the embedded GelTip)")
    p.add_argument("--sweep", type=_sweep, action="append", required=True, metavar="NAME=VALUES",
                   help="a design parameter and its values, NAME=V1,V2,... or NAME=START:STOP:COUNT; once or twice")
    p.add_argument("--out", required=True, metavar="DIR", help="where design.json, summary.md and the figures go")
    p.add_argument("--field", choices=METHODS, default=FIELD, help=f"the fast path's light field (default {FIELD})")
    p.add_argument("--indenter", choices=INDENTERS, default=INDENTER,
                   help=f"the standard tap's indenter (default {INDENTER})")
    p.add_argument("--depth", type=float, default=STANDARD_DEPTH_M * 1e3, metavar="MM",
                   help=f"the standard tap's depth along the normal, mm (default {STANDARD_DEPTH_M * 1e3:g})")
    p.add_argument("--taps", type=positive_int, help="standard taps per design, spread over the extended protocol's 80 "
                                                  "(default all)")
    p.add_argument("--no-reference", action="store_true", help="leave the reference check out")
    p.add_argument("--reference-taps", type=positive_int, default=REFERENCE_TAPS,
                   help=f"taps the reference renders per checked design (default {REFERENCE_TAPS}; about a minute "
                        "a frame on 2 cores)")
    p.add_argument("--width", type=positive_int, default=160, help="reference film width, px (default 160)")
    p.add_argument("--height", type=positive_int, default=120, help="reference film height, px (default 120)")
    p.add_argument("--photons", type=positive_int, default=1 << 18, help="photons per LED per pass (default 2^18)")
    p.add_argument("--passes", type=positive_int, default=4, help="independent passes (default 4)")
    p.add_argument("--spp", type=positive_int, default=32, help="camera samples per pixel in all (default 32)")
    add_quiet_argument(p)
