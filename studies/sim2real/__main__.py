"""``python -m studies.sim2real --out DIR``: the Sim2Real learning study (``pipeline.run``)."""

from __future__ import annotations

import argparse
import json
import sys

from scenes.commands import positive_int

from .augment import TRAININGS
from .learn import MODELS, Training
from .pipeline import run
from .plan import FIELDS, INPUTS, PROTOCOLS, TASKS, Settings


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m studies.sim2real", description=__doc__)
    p.add_argument("--out", required=True, help="the study's folder (datasets, runs, results.json); resumed")
    p.add_argument("--capture", help="an existing capture of the base protocol to use as the real data "
                                     "(default: render one on the virtual rig with the reference, DIR/real)")
    p.add_argument("--spec", help="sensor spec TOML of the capture rendered here (default: the GelTip)")
    p.add_argument("--model", choices=MODELS, default="cnn", help="resnet18 (as published), cnn (default) or ridge")
    p.add_argument("--seeds", type=positive_int, default=3)
    p.add_argument("--epochs", type=positive_int, default=Training.epochs)
    p.add_argument("--batches-per-epoch", type=positive_int, default=Training.batches_per_epoch)
    p.add_argument("--batch", type=positive_int, default=Training.batch)
    p.add_argument("--factor", type=positive_int, default=4, help="the arrays' block size (default 4: 160x120)")
    p.add_argument("--full-block", type=positive_int, default=2, help="the full image's further block (default 2)")
    p.add_argument("--patch-px", type=positive_int, default=32, help="the patch's side at the arrays' resolution")
    p.add_argument("--extended-taps", type=positive_int, help="a seeded subset of the extended protocol's taps")
    p.add_argument("--protocols", default=",".join(PROTOCOLS), help="simulated protocols (default base,extended)")
    p.add_argument("--fields", default=",".join(FIELDS), help="light fields whose replays pick the best one")
    p.add_argument("--trainings", default=",".join(TRAININGS), help="none,randomised,diagnosed (default all)")
    p.add_argument("--inputs", default=",".join(INPUTS), help="full,patch (default both)")
    p.add_argument("--tasks", default=",".join(TASKS), help="classification,localisation (default both)")
    p.add_argument("--difference", action="store_true",
                   help="the networks see each image's difference from its set's no-contact frame (shown with the "
                        "same effects), over its RMS in the image circle, instead of the image; writes "
                        "results-difference.json etc.")
    p.add_argument("--workers", type=positive_int, default=2)
    p.add_argument("--quiet", action="store_true")
    args = p.parse_args(argv)
    split = lambda v: tuple(x.strip() for x in v.split(",") if x.strip())  # noqa: E731
    trainings = split(args.trainings)
    bad = sorted(set(trainings) - set(TRAININGS)) + sorted(set(split(args.protocols)) - set(PROTOCOLS)) \
        + sorted(set(split(args.fields)) - set(FIELDS)) + sorted(set(split(args.inputs)) - set(INPUTS)) \
        + sorted(set(split(args.tasks)) - set(TASKS))
    if bad:
        p.error(f"unknown values {bad}: trainings are {TRAININGS}, protocols {PROTOCOLS}, fields {FIELDS}, "
                f"inputs {INPUTS}, tasks {TASKS}")
    settings = Settings(model=args.model, seeds=args.seeds, factor=args.factor, full_block=args.full_block,
                        patch_px=args.patch_px, extended_taps=args.extended_taps,
                        trainings=tuple(dict.fromkeys(("none",) + trainings)),
                        training=Training(batch=args.batch, batches_per_epoch=args.batches_per_epoch,
                                          epochs=args.epochs), workers=args.workers,
                        inputs=split(args.inputs), tasks=split(args.tasks), difference=args.difference)
    try:
        doc = run(args.out, settings, capture=args.capture, spec=args.spec, fields=split(args.fields),
                  protocols=split(args.protocols), progress=not args.quiet)
    except (ValueError, RuntimeError, FileNotFoundError) as exc:
        print(f"studies.sim2real: error: {exc}", file=sys.stderr)
        return 1
    print(json.dumps(doc["gap_closed"], indent=1)[:4000])
    return 0


if __name__ == "__main__":
    sys.exit(main())
