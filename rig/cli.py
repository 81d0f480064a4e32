"""``tactile-sim rig``: run a tapping protocol on the real rig or its twins, or serve twins.

::

    tactile-sim rig run --printer /dev/ttyUSB0 --servos /dev/ttyACM0 --camera 0 \\
        --protocol base --objects sphere --out DIR
    tactile-sim rig run --printer twin --servos twin --camera twin --renderer pbr \\
        --profile P.toml --out DIR          # the virtual rig
    tactile-sim rig run --protocol base --objects sphere --out DIR --dry-run
                                            # print the command stream, open nothing
    tactile-sim rig twin                    # serve a printer twin and a servo twin
"""

from __future__ import annotations

import functools
import sys
import time

TWIN = "twin"


def _layout(path: str | None):
    from scenes.kinematics import RigLayout

    from scenes.spec_read import read_toml

    if path is None:
        return RigLayout()
    data = read_toml(path, "--layout")
    return RigLayout.from_dict(data.get("layout", data), where=f"--layout {path}")


def _protocol(args, spec):
    from dataclasses import replace

    from scenes.commands import object_names
    from scenes.protocol import make_protocol
    from scenes.body import checked_membrane

    protocol = make_protocol(args.protocol, spec, checked_membrane(spec), object_names(args.objects), seed=args.seed)
    if args.limit:
        protocol = replace(protocol, taps=protocol.taps[: args.limit])
    return protocol


def _alignment_hook(spec, options: dict):
    """After the background: ``rig.capture.alignment_hook`` (the profile's alignment when
    one is given, else a registration against the fast path's no-contact image)."""
    from scenes.renderers import get_renderer

    from .capture import alignment_hook

    profile = options.get("profile")
    return alignment_hook(spec, None if profile else get_renderer("phong"), profile)


#: The devices of ``rig run``, by argument: given unless ``--dry-run``, which opens none.
DEVICES = ("printer", "servos", "camera")


def cmd_run(args, parser=None) -> int:
    """``tactile-sim rig run``. ``parser`` (the subcommand's) reports missing devices as
    argparse reports a missing argument; without it they are a ValueError."""
    from scenes.commands import renderer_options
    from scenes.spec_read import load_spec

    from .session import Devices, prepare

    missing = [f"--{name}" for name in DEVICES if getattr(args, name) is None]
    if missing and not args.dry_run:
        message = f"the following arguments are required without --dry-run: {', '.join(missing)}"
        if parser is not None:
            parser.error(message)
        raise ValueError(message)
    spec = load_spec(args.spec)
    layout = _layout(args.layout)
    protocol = _protocol(args, spec)
    options = renderer_options(args)
    twins = [name for name in ("printer", "servos") if getattr(args, name) == TWIN]
    virtual = args.camera == TWIN
    if virtual and len(twins) < 2:
        raise ValueError("--camera twin renders the MuJoCo rig that the twins move: give --printer twin and "
                         "--servos twin too")
    if options and not virtual:
        raise ValueError(f"renderer options ({', '.join(sorted(options))}) are for --camera twin only")
    unit = _unit(args.unit or [])
    if unit and not virtual:
        raise ValueError("--unit is for --camera twin only: a real sensor is the unit it is")
    after_background = None if args.no_alignment else _alignment_hook(spec, options)
    if virtual and not args.dry_run:
        from scenes.renderers import get_renderer

        from .capture import capture

        summary = capture(args.out, spec, protocol, get_renderer(args.renderer), options, layout, unit,
                          after_background, progress=not args.quiet)  # SessionAborted: scenes.cli reports it
        print(f"{summary['samples']} samples in {args.out} ({summary['new']} new, {summary['seconds']:.1f} s)")
        return 0
    source_meta = {"rig": {"virtual": virtual, "printer": args.printer, "servos": args.servos}}
    session = prepare(args.out, spec, protocol, layout, source_meta=source_meta, after_background=after_background)
    if args.dry_run:
        for device, line in session.stream():
            print(f"{device}: {line}")
        print(f"# {len(session.todo)} of {len(protocol.taps)} taps to do; every move is inside the envelope; "
              "nothing was sent", file=sys.stderr)
        return 0
    from contextlib import ExitStack

    from .marlin import MarlinPrinter
    from .servos import ServoBoard

    with ExitStack() as stack:
        rig = None
        if twins:  # a twin or two with the real camera (the virtual rig's whole capture is rig.capture's)
            from scenes.renderers import get_renderer

            from .virtual import VirtualRig

            renderer = get_renderer(args.renderer)
            rig = stack.enter_context(VirtualRig(spec, protocol.objects, renderer, options, layout, unit=unit))
        printer_port = rig.printer.port if args.printer == TWIN else args.printer
        servo_port = rig.servos.port if args.servos == TWIN else args.servos
        printer = stack.enter_context(MarlinPrinter(printer_port, args.baud))
        servos = stack.enter_context(ServoBoard(servo_port, args.servo_baud))
        from .camera import open_camera

        camera = stack.enter_context(open_camera(args.camera, settle_s=args.settle))
        mount = rig.mount if rig is not None else _ask_to_mount(args.yes)
        devices = Devices(printer, servos, camera, mount, 0.0 if args.servos == TWIN else args.servo_settle)
        summary = session.run(devices, progress=not args.quiet)  # SessionAborted: scenes.cli reports it
    print(f"{summary['samples']} samples in {args.out} ({summary['new']} new, {summary['seconds']:.1f} s)")
    return 0


def _unit(settings: list[str]) -> dict:
    """``--unit NAME=VALUE[,VALUE...]`` settings as {name: float or tuple}; checked by
    ``rig.virtual.unit_spec``."""
    from scenes.settings import name_values

    parsed = name_values(settings, "--unit", "NAME=VALUE or NAME=VALUE,VALUE,... with numbers")
    return {name: values[0] if len(values) == 1 else values for name, values in parsed.items()}


def _ask_to_mount(yes: bool):
    def mount(name: str) -> None:
        if yes:
            print(f"mount the {name} indenter (assumed done: --yes)", file=sys.stderr)
            return
        input(f"Mount the {name} indenter on the pitch servo, then press Enter... ")

    return mount


def cmd_twin(args) -> int:
    from .twins.printer import PrinterTwin
    from .twins.servos import ServoTwin

    with PrinterTwin() as printer, ServoTwin() as servos:
        print(f"printer twin: {printer.port}")
        print(f"servo twin: {servos.port}", flush=True)
        deadline = time.monotonic() + args.seconds if args.seconds else None
        try:
            while deadline is None or time.monotonic() < deadline:
                time.sleep(0.1)
        except KeyboardInterrupt:
            pass
    return 0


def register(registry) -> None:
    from scenes.commands import add_limit_argument, add_quiet_argument, add_renderer_arguments

    from .marlin import DEFAULT_BAUD
    from .servos import DEFAULT_BAUD as SERVO_BAUD
    from .session import SERVO_SETTLE_S
    from .virtual import UNIT

    p = registry.command("rig", lambda args: p.print_help() or 2, "drive the tapping rig (real or virtual)")
    actions = p.add_subparsers(dest="action", metavar="ACTION")
    run = actions.add_parser("run", help="run a protocol and write a capture dataset (resumable)",
                             description="Run a tapping protocol on the rig and write a capture dataset "
                                         "(source real). Run it again on the same --out to resume.")
    run.set_defaults(func=functools.partial(cmd_run, parser=run))  # --dry-run decides which devices are needed
    run.add_argument("--printer", metavar="PORT|twin",
                     help="the Marlin printer's serial port (optional with --dry-run)")
    run.add_argument("--servos", metavar="PORT|twin", help="the servo board's serial port (optional with --dry-run)")
    run.add_argument("--camera", metavar="INDEX|VIDEO|FOLDER|twin",
                     help="an OpenCV device index, a video file, a folder of images, or twin (render the MuJoCo rig); "
                          "optional with --dry-run")
    run.add_argument("--spec", metavar="TOML")
    run.add_argument("--layout", metavar="TOML", help="the rig's layout (scenes.kinematics.RigLayout keys)")
    run.add_argument("--protocol", choices=["base", "extended"], default="base")
    run.add_argument("--objects", default="sphere", help="'all' or comma-separated indenter names")
    run.add_argument("--seed", type=int, default=0, help="seed of the extended protocol's perturbations")
    add_limit_argument(run)
    run.add_argument("--out", required=True, metavar="DIR")
    run.add_argument("--dry-run", action="store_true",
                     help="print the command stream; open no device (--printer, --servos and --camera optional)")
    run.add_argument("--baud", type=int, default=DEFAULT_BAUD, help="the printer's baud rate")
    run.add_argument("--servo-baud", type=int, default=SERVO_BAUD, help="the servo board's baud rate")
    run.add_argument("--servo-settle", type=float, default=SERVO_SETTLE_S, metavar="S",
                     help="seconds the servos get to turn")
    run.add_argument("--settle", type=float, default=0.5, metavar="S", help="the camera's settle time before a frame")
    run.add_argument("--yes", action="store_true", help="do not wait for Enter when an indenter must be mounted")
    run.add_argument("--no-alignment", action="store_true", help="do not register the background against the sim")
    add_quiet_argument(run)
    run.add_argument("--renderer", default="phong", help="--camera twin: phong (the fast path) or pbr (the reference)")
    run.add_argument("--unit", action="append", metavar="NAME=VALUE",
                     help="--camera twin: the sensor the twin renders differs from the recorded spec (hidden in "
                          "virtual.json): " + "; ".join(f"{k}: {v}" for k, v in UNIT.items()))
    add_renderer_arguments(run)
    twin = actions.add_parser("twin", help="serve a printer twin and a servo twin on ptys; print their ports",
                              description="Serve a Marlin printer twin and a servo board twin on pseudo-terminals "
                                          "until Ctrl-C.")
    twin.set_defaults(func=cmd_twin)
    twin.add_argument("--seconds", type=float, default=0.0, help="stop after this long (0: until Ctrl-C)")
