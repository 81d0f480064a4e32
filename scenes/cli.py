"""The ``tactile-sim`` command line: a dispatcher whose subcommands are plugins.

Each package registers its subcommands through the ``tactile_sim.commands`` entry point
group (see pyproject.toml), so this module, and ``scenes`` as a whole, never imports a
renderer.
"""

from __future__ import annotations

import argparse
import sys
from importlib.metadata import entry_points

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


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "func", None):
        parser.print_help()
        return 2
    try:
        return int(args.func(args) or 0)
    except (ValueError, FileNotFoundError) as exc:
        print(f"tactile-sim {args.command}: error: {exc}", file=sys.stderr)
        return 1


if __name__ == "__main__":
    sys.exit(main())
