"""The ``tactile-sim bench tiles`` command."""

from __future__ import annotations

import json

from .disk import CAPTION, parse_objects
from .bench import PHOTONS, run


def cmd_bench_tiles(args) -> int:
    out = run(args.json, args.tiles, objects=parse_objects(args.object), reference=not args.no_reference,
              photons=args.photons, quiet=args.quiet, effects=tuple(args.effects or ()), images_dir=args.images,
              elastic=args.elastic)
    keys = ("object", "depth_mm", "strength_ratio", "shape_corr")
    summary = {k: {key: t[key] for key in keys} for k, t in out["tiles"].items()}
    print(json.dumps(summary, indent=1))
    print(f"wrote {args.json}")
    return 0


def register(registry) -> None:
    from scenes.commands import add_quiet_argument
    from scenes.elastic import MODELS

    p = registry.bench("tiles", cmd_bench_tiles, "recover the GelTip figure's contacts from the published "
                       "simulations and score the reference and the fast path on the real tiles")
    p.add_argument("--tiles", metavar="DIR", help="the tiles (default: the shared data's real_contacts, "
                                                  "../shared/data/geltip_reference/real_contacts)")
    p.add_argument("--object", action="append", metavar="K=NAME",
                   help="column K's object (default the caption's: " + ", ".join(
                       f"{k}={n}" for k, n in enumerate(CAPTION)) + ")")
    p.add_argument("--no-reference", action="store_true", help="the fast path only (no physically based reference)")
    p.add_argument("--photons", type=int, default=PHOTONS, metavar="N",
                   help=f"the reference's photons per pass (default {PHOTONS})")
    p.add_argument("--effects", action="append", metavar="NAME=V",
                   help="a reference effect (pbr_tactile.effects.Effects; repeatable; default: its defaults), e.g. "
                        "coating_albedo=0.4")
    p.add_argument("--images", metavar="DIR",
                   help="write each column's real and simulated changes side by side there (colK_recovered.png, "
                        "colK_at_real_place.png: real tile, its change, region, then per renderer its no-contact "
                        "tile and change through the real camera's exposure; grey is no change)")
    p.add_argument("--elastic", choices=MODELS, default="published",
                   help="the dent both renderers draw (default: the fast path's published smoothing, the reference's "
                        "layer model; bonded: the bonded layer in both)")
    add_quiet_argument(p)
