"""``tactile-sim diagnose`` and ``tactile-sim bench diagnose``."""

from __future__ import annotations

import argparse
import json
import sys

from scenes.commands import add_quiet_argument, non_negative_int, positive_int

from . import effects as fx
from .physical_benchmark import PAIRINGS


def _hidden(text: str) -> tuple[str, ...] | None:
    """--hidden: 'all', or effects and mechanisms written unlike the catalogue."""
    from .unlike import MECHANISMS

    if text == "all":
        return None
    names = tuple(n.strip() for n in text.split(",") if n.strip())
    effects = [n for n in names if n not in MECHANISMS]
    return (_effects(",".join(effects)) if effects or not names else ()) + tuple(n for n in names if n in MECHANISMS)


def _effects(text: str) -> tuple[str, ...] | None:
    if text == "all":
        return None
    names = tuple(n.strip() for n in text.split(",") if n.strip())
    from .physical import candidate_names

    physical = candidate_names()
    unknown = [n for n in names if n not in fx.EFFECTS and n not in physical]
    if unknown or not names:
        raise argparse.ArgumentTypeError(f"effects must be 'all' or a comma-separated list of the fast model's effects "
                                         f"({', '.join(fx.EFFECTS)}) or, for a simulation the reference rendered, "
                                         f"its own ({', '.join(n for n in physical if n not in fx.EFFECTS)}); "
                                         f"unknown: {', '.join(unknown) or '(none given)'}")
    return names


def _fraction(text: str) -> float:
    value = float(text)
    if not 0 < value < 1:
        raise argparse.ArgumentTypeError(f"must be a fraction in (0, 1), got {text}")
    return value


def cmd_diagnose(args) -> int:
    if args.real == "benchmark":
        return cmd_benchmark(args)
    if args.sim is None or args.out is None:
        print("tactile-sim diagnose: error: give REAL_DIR SIM_DIR --out REPORT_DIR "
              "(or 'diagnose benchmark --cases N --seed S --json PATH')", file=sys.stderr)
        return 2
    from .diagnose import run
    from .report import headline

    report = run(args.real, args.sim, args.out, heldout_fraction=args.heldout, seed=args.seed, factor=args.factor,
                 effects=args.effects, progress=not args.quiet, split_by=args.split,
                 **({} if args.intervals is None else {"intervals": args.intervals}))
    for line in headline(report):
        print(line)
    print(f"wrote {args.out}/report.html and {args.out}/report.json")
    return 0


def cmd_benchmark(args) -> int:
    if args.json is None:
        print("tactile-sim diagnose benchmark: error: --json PATH is required", file=sys.stderr)
        return 2
    if args.hidden is not None and not args.stratified:
        print("tactile-sim diagnose benchmark: error: --hidden needs --stratified", file=sys.stderr)
        return 2
    if args.described and (args.stratified or args.physical):
        print("tactile-sim diagnose benchmark: error: --described is a benchmark of its own, not with --stratified "
              "or --physical", file=sys.stderr)
        return 2
    if args.pairing != "reference" and not args.physical:
        print("tactile-sim diagnose benchmark: error: --pairing needs --physical", file=sys.stderr)
        return 2
    if args.physical:
        if args.stratified:
            print("tactile-sim diagnose benchmark: error: --physical and --stratified are separate benchmarks",
                  file=sys.stderr)
            return 2
        from pathlib import Path

        from .physical_benchmark import run_physical_benchmark
        from scenes.files import write_json

        result = run_physical_benchmark(cases=args.cases, seed=args.seed, work=args.work, progress=not args.quiet,
                                        factor=args.factor, pairing=args.pairing)
        write_json(Path(args.json), result)
        print(json.dumps({k: result[k] for k in ("cases", "top1", "top3", "mean_heldout_shrink", "seconds",
                                                 "never_hidden", "below_residual", "above_residual", "below_noise",
                                                 "above_noise") if k in result},
                         indent=1))
        return 0
    from .benchmark import run_benchmark

    result = run_benchmark(cases=args.cases, seed=args.seed, work=args.work, pairs=args.pairs,
                           progress=not args.quiet, factor=args.factor, stratified=args.stratified,
                           hidden=args.hidden, described=args.described, null=args.null)
    from pathlib import Path

    from scenes.files import write_json

    write_json(Path(args.json), result)
    keys = ("cases", "top1", "top3", "mean_heldout_shrink") + (("per_mechanism",) if args.described else ()) + (
        ("min_cell_shrink", "min_cell", "noise_cells") if args.stratified else ())
    shown = {k: result[k] for k in keys}
    if "null" in result:
        shown["null"] = {k: result["null"][k] for k in ("cases", "named_nothing")}
    print(json.dumps(shown, indent=1))
    if result["failed"]:
        print(f"failed cases: {', '.join(str(c['case']) for c in result['failed'])}")
    return 0


def cmd_bench(args) -> int:
    from pathlib import Path

    from scenes.files import write_json

    if args.physical:
        from .physical_benchmark import bench_physical

        result = bench_physical(pairs=args.pairs or 36, work=args.work, progress=not args.quiet)
        write_json(Path(args.json), result)
        print(json.dumps({k: result[k] for k in ("seconds", "setup_seconds", "pairs", "first", "hidden_share_closed")}))
        return 0
    from .benchmark import bench_diagnose

    result = bench_diagnose(pairs=args.pairs or 144, work=args.work, progress=not args.quiet)
    write_json(Path(args.json), result)
    print(json.dumps({k: result[k] for k in ("seconds", "pairs", "effects")}))
    return 0


def register(registry) -> None:
    p = registry.command("diagnose", cmd_diagnose,
                         "sim-to-real gap diagnosis: where the gap lies, which unmodelled effect causes it, how far "
                         "it shrinks on held-out samples (REAL_DIR SIM_DIR --out DIR), or its blind benchmark "
                         "(benchmark --cases N --seed S --json PATH)")
    p.add_argument("real", metavar="REAL_DIR", help="the real dataset (or 'benchmark')")
    p.add_argument("sim", metavar="SIM_DIR", nargs="?", help="its simulated counterpart (same protocol)")
    p.add_argument("--out", metavar="REPORT_DIR", help="where report.html, report.json and figures go")
    p.add_argument("--heldout", type=_fraction, default=0.5, help="share of samples held out (default 0.5)")
    p.add_argument("--seed", type=int, default=0, help="split seed (benchmark: case seed)")
    p.add_argument("--split", choices=("stratified", "alternate"), default="stratified",
                   help="stratified (default: --heldout of each object's samples at random) or alternate (the "
                        "capture's odd samples held out, as a calibration from it holds them out)")
    p.add_argument("--factor", type=positive_int, default=2,
                   help="fits run at 1/FACTOR of the image resolution (default 2); results are measured at full size")
    p.add_argument("--effects", type=_effects, default=None, help="'all' (default) or a comma-separated subset")
    p.add_argument("--intervals", type=non_negative_int, default=None,
                   help="bootstrap resamples behind the best-ranked effects' parameter intervals, each one Newton "
                        "step from the fit (default: studies.gap.fit.PARAM_RESAMPLES; 0: none)")
    add_quiet_argument(p)
    p.add_argument("--cases", type=positive_int, default=20, help="benchmark: number of cases (default 20)")
    p.add_argument("--pairs", type=positive_int, default=48, help="benchmark: pairs per case (default 48)")
    p.add_argument("--work", metavar="DIR", default=None, help="benchmark: keep the case datasets here")
    p.add_argument("--json", metavar="PATH", default=None, help="benchmark: where to write the results")
    p.add_argument("--stratified", action="store_true",
                   help="benchmark: every effect alone on every background (none, solid, real) at strength 0.5, "
                        "then each mechanism written unlike the catalogue (studies/gap/unlike.py) on its background, "
                        "at least one case per cell (--cases below 41 means 41); adds per_cell and min_cell_shrink")
    p.add_argument("--null", type=non_negative_int, default=0,
                   help="benchmark: this many cases more that hide nothing (the simulated frames with the real "
                        "camera's noise), on the backgrounds none, solid, real in turn; a correct diagnosis names "
                        "nothing (adds null.named_nothing)")
    p.add_argument("--described", action="store_true",
                   help="benchmark: the mechanisms written from prose descriptions by a hand that had not read the "
                        "catalogue (studies/gap/described.py), each on its background, in turn at strengths 0.5, 0, "
                        "1, 0.25, 0.75; adds per_mechanism")
    p.add_argument("--physical", action="store_true",
                   help="benchmark: hide physical effects in the reference (the virtual rig's camera) and diagnose "
                        "them against the reference's replay (studies/gap/physical_benchmark.py)")
    p.add_argument("--pairing", choices=PAIRINGS, default=PAIRINGS[0],
                   help="benchmark --physical: diagnose each capture against the reference's replay (default), or "
                        "against the fast path's replay with a profile calibrated to a capture without hidden effects "
                        "(what a user with a real sensor and the fast path has; scored on the fast catalogue's "
                        "counterparts, with the share each closes per region)")
    p.add_argument("--hidden", type=_hidden, default=None,
                   help="benchmark --stratified: only the cells hiding these effects, or written unlike the "
                        "catalogue for them, or these mechanisms of studies/gap/unlike.py (frame_move, ...; "
                        "comma-separated; default all); each case keeps its index and seed from the full run")
    b = registry.bench("diagnose", cmd_bench, "seconds for a full diagnosis of a 144-pair dataset with every effect")
    b.add_argument("--pairs", type=positive_int, default=None,
                   help="pairs (default 144, the base protocol; with --physical 36, its two objects' taps)")
    b.add_argument("--physical", action="store_true",
                   help="a reference capture with a hidden leak (the virtual rig's camera) against the reference's "
                        "replay: the physical candidates and their basis renders "
                        "(studies/gap/physical_benchmark.py bench_physical)")
    b.add_argument("--work", metavar="DIR", default=None, help="keep the datasets here")
    add_quiet_argument(b)
