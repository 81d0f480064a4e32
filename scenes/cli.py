"""The ``tactile-sim`` command line: a dispatcher whose subcommands are plugins.

Each package registers its subcommands through the ``tactile_sim.commands`` entry point
group (see pyproject.toml), so this module, and ``scenes`` as a whole, never imports a
renderer.
"""

from __future__ import annotations

import argparse
import sys
from importlib.metadata import entry_points

from .errors import REPORTED

ENTRY_POINT_GROUP = "tactile_sim.commands"


class Registry:
    """Where plugins add subcommands, and benchmarks under ``tactile-sim bench``."""

    def __init__(self, commands: argparse._SubParsersAction, benches: argparse._SubParsersAction):
        self._commands = commands
        self._benches = benches

    def command(self, name: str, func, help: str) -> argparse.ArgumentParser:
        parser = self._commands.add_parser(name, help=help, description=help)
        parser.set_defaults(func=func)
        return parser

    def bench(self, name: str, func, help: str) -> argparse.ArgumentParser:
        parser = self._benches.add_parser(name, help=help, description=help)
        parser.add_argument("--json", required=True, metavar="PATH", help="where to write the results")
        parser.set_defaults(func=func)
        return parser


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="tactile-sim", description="Simulate optical tactile sensors of any shape (GelTip and beyond)."
    )
    commands = parser.add_subparsers(dest="command", metavar="COMMAND")
    bench = commands.add_parser("bench", help="measure speed and write JSON", description="Benchmarks.")
    benches = bench.add_subparsers(dest="bench", metavar="BENCH")
    bench.set_defaults(func=lambda args: bench.print_help() or 2)
    registry = Registry(commands, benches)
    for ep in sorted(entry_points(group=ENTRY_POINT_GROUP), key=lambda e: e.name):
        ep.load()(registry)
    return parser




def command_name(parser: argparse.ArgumentParser, args: argparse.Namespace) -> str:
    """The command that ``args`` ran, as the user typed it: ``tactile-sim rig run``."""
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            chosen = action.choices.get(getattr(args, action.dest, None))
            if chosen is not None:
                return command_name(chosen, args)
    return parser.prog


def main(argv: list[str] | None = None) -> int:
    """Run ``tactile-sim`` with ``argv`` (default ``sys.argv[1:]``); returns the exit status.

    The errors in :data:`REPORTED` are printed to stderr in one line naming the command;
    any other exception is a bug and keeps its traceback.
    """
    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "func", None):
        parser.print_help()
        return 2
    try:
        return int(args.func(args) or 0)
    except REPORTED as exc:
        print(f"{command_name(parser, args)}: error: {exc}", file=sys.stderr)
        return 1


if __name__ == "__main__":
    sys.exit(main())
