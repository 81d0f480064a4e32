"""``tactile-sim compare``: the paper's Table 1 on a capture of the rig."""

from __future__ import annotations

import argparse
import os

from scenes.commands import add_quiet_argument, add_renderer_arguments, positive_int, renderer_options

from .run import BACKGROUNDS, REFERENCE_TAPS


def _names(text: str) -> tuple[str, ...]:
    names = tuple(n.strip() for n in text.split(",") if n.strip())
    if not names:
        raise argparse.ArgumentTypeError(f"expected a comma-separated list, got {text!r}")
    return names


def cmd_compare(args) -> int:
    from phong_reference.bake import METHODS

    from . import report
    from .run import compare

    options = renderer_options(args)
    profile = options.pop("profile", None)
    result = compare(args.capture, args.out, profile=profile, options=options, taps=args.taps, heldout=args.heldout,
                     reference_taps=args.reference_taps, fields=args.fields or METHODS, backgrounds=args.backgrounds,
                     reference=not args.no_reference, peers=args.peers or (), bootstrap=args.bootstrap, seed=args.seed, workers=args.workers,
                     progress=not args.quiet)
    print(report.markdown(result))
    print(f"wrote {args.out}/table.json, table.md and report.html")
    return 0


def register(registry) -> None:
    p = registry.command("compare", cmd_compare,
                         "the paper's Table 1 on a capture of the rig (source 'real'): its taps rendered at their "
                         "measured poses by the fast path (each light field and background) and the physically "
                         "based reference, MAE/SSIM/PSNR full frame, in the image circle and over each tap's "
                         "contact with bootstrap intervals, and the contact strength, simulated over real "
                         "(CAPTURE_DIR --out DIR)")
    p.add_argument("capture", metavar="CAPTURE_DIR", help="a capture of the rig (docs/dataset-format.md)")
    p.add_argument("--out", required=True, metavar="DIR",
                   help="where table.json, table.md, report.html, figures and renders/ go (renders resume)")
    p.add_argument("--taps", type=positive_int, help="the fast path's taps, spread evenly over the capture (default all)")
    p.add_argument("--heldout", action="store_true",
                   help="only the capture's judged half (its odd samples), the taps a calibration from it holds out")
    p.add_argument("--reference-taps", type=positive_int, default=REFERENCE_TAPS,
                   help=f"the reference's taps, spread evenly over the fast path's (default {REFERENCE_TAPS}: it "
                        "takes minutes per tap)")
    p.add_argument("--no-reference", action="store_true", help="leave the physically based reference out")
    p.add_argument("--peers", type=_names, help="peer simulators scored beside ours (taxim: Taxim with its shipped "
                                               "calibration and refitted on the capture's fitted half; an imported "
                                               "set of ball presses, pip install '.[peers]')")
    p.add_argument("--fields", type=_names, help="the fast path's light fields (default all: linear, plane, geodesic, "
                                                 "transport)")
    p.add_argument("--backgrounds", type=_names,
                   help=f"the fast path's backgrounds, some of {', '.join(BACKGROUNDS)} (default all; real is the "
                        "capture's background.png); not with --profile, whose background is the unit's")
    p.add_argument("--bootstrap", type=positive_int, default=2000, help="bootstrap resamples of the taps (default 2000)")
    p.add_argument("--seed", type=int, default=0, help="seed of the bootstrap (default 0)")
    p.add_argument("--workers", type=positive_int, default=min(2, os.cpu_count() or 1))
    add_quiet_argument(p)
    add_renderer_arguments(p, skip=("field", "background"))
