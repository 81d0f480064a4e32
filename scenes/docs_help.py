"""Write the ``tactile-sim`` commands' argparse help as markdown pages under ``docs/cli/``.

The pages are built from the parser the command line itself uses
(:func:`scenes.cli.build_parser`, every plugin's subcommands included), so they cannot
drift from it: ``tests/test_docs.py`` builds them again in memory and compares. After a
change to any command's options or help text, regenerate them with one command::

    python3 -m scenes.docs_help

One page per command and subcommand (``docs/cli/diagnose.md``, ``docs/cli/bench-pbr.md``,
``docs/cli/rig-run.md``), and ``docs/cli/index.md`` listing them. Usage lines are wrapped
at :data:`WIDTH` columns whatever the terminal, so the pages do not depend on who made
them; they do depend on argparse's formatting, which changes between Python versions, so
the index records the version that made them (:data:`PYTHON`).
"""

from __future__ import annotations

import argparse
import copy
import functools
import sys
from pathlib import Path

from .cli import build_parser

#: Columns the usage lines are wrapped at, whatever the terminal.
WIDTH = 100

#: The Python version (major.minor) whose argparse formatted the committed pages.
PYTHON = f"{sys.version_info.major}.{sys.version_info.minor}"

#: Where the pages go, relative to the repository root.
CLI_DIR = Path("docs") / "cli"

#: The hand-written guide of a command's first word, relative to ``docs/cli/``.
GUIDE = "../commands/{}.md"

GENERATED_NOTE = (
    "<!-- Generated from the command's argparse parser by `python3 -m scenes.docs_help`; "
    "do not edit: change the help text in the code and regenerate. -->"
)


def _subparsers(parser: argparse.ArgumentParser) -> argparse._SubParsersAction | None:
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            return action
    return None


def command_parsers(parser: argparse.ArgumentParser, path: tuple[str, ...] = ()):
    """Every subcommand below ``parser``, depth first in the parser's order.

    Returns
    -------
    list of (tuple of str, argparse.ArgumentParser, str)
        The command's words after ``tactile-sim`` (``("rig", "run")``), its parser and its
        one-line help as listed by its parent.
    """
    found = []
    subparsers = _subparsers(parser)
    if subparsers is None:
        return found
    formatter = _formatter(parser)
    helps = {choice.dest: formatter._expand_help(choice) for choice in subparsers._choices_actions if choice.help}
    for name, sub in subparsers.choices.items():
        words = path + (name,)
        found.append((words, sub, helps.get(name, "")))
        found.extend(command_parsers(sub, words))
    return found


def page_name(words: tuple[str, ...]) -> str:
    """The page of a command under ``docs/cli/``: ``("rig", "run")`` -> ``rig-run.md``."""
    return "-".join(words) + ".md"


def _formatter(parser: argparse.ArgumentParser) -> argparse.HelpFormatter:
    return parser.formatter_class(prog=parser.prog, width=WIDTH)


def _usage(parser: argparse.ArgumentParser) -> str:
    fixed = copy.copy(parser)
    fixed.formatter_class = functools.partial(parser.formatter_class, width=WIDTH)
    return fixed.format_usage().strip()


def _text(text: str) -> str:
    """Help text as one markdown paragraph: whitespace collapsed, no raw HTML."""
    return " ".join(text.split()).replace("<", "&lt;").replace(">", "&gt;")


def _cell(text: str) -> str:
    """Help text made safe for one markdown table cell."""
    return _text(text).replace("|", "\\|")


def _invocation(parser: argparse.ArgumentParser, action: argparse.Action) -> str:
    formatter = _formatter(parser)
    if not action.option_strings:
        return formatter._metavar_formatter(action, action.dest)(1)[0]
    if action.nargs == 0:
        return ", ".join(action.option_strings)
    args = formatter._format_args(action, formatter._get_default_metavar_for_optional(action))
    return ", ".join(action.option_strings) + " " + args


def help_page(words: tuple[str, ...], parser: argparse.ArgumentParser, summary: str) -> str:
    """The markdown page of one command: its description, usage and a table of its arguments."""
    formatter = _formatter(parser)
    lines = [f"# `tactile-sim {' '.join(words)}`", "", GENERATED_NOTE, ""]
    description = parser.description or summary
    if description:
        lines += [_text(description), ""]
    lines += [f"What it does, in full, and what it measured: [{words[0]}]({GUIDE.format(words[0])}).", ""]
    lines += ["```text", _usage(parser), "```", ""]
    subparsers = _subparsers(parser)
    if subparsers is not None:
        lines += ["| subcommand | what it does |", "|---|---|"]
        for choice in subparsers._choices_actions:
            sub_words = words + (choice.dest,)
            text = formatter._expand_help(choice) if choice.help else ""
            lines.append(f"| [`{' '.join(sub_words)}`]({page_name(sub_words)}) | {_cell(text)} |")
        lines.append("")
    for group in parser._action_groups:
        rows = []
        for action in group._group_actions:
            if action.help == argparse.SUPPRESS or isinstance(action, argparse._SubParsersAction):
                continue
            if isinstance(action, argparse._HelpAction):
                continue
            text = formatter._expand_help(action) if action.help else ""
            invocation = _invocation(parser, action).replace("|", "\\|")
            rows.append(f"| `{invocation}` | {_cell(text)} |")
        if rows:
            lines += [f"| {group.title} | |", "|---|---|", *rows, ""]
    return "\n".join(lines).rstrip("\n") + "\n"


def index_page(commands) -> str:
    """``docs/cli/index.md``: every command, its one-line help and its page."""
    lines = [
        "# `tactile-sim` command reference",
        "",
        GENERATED_NOTE,
        "",
        "Every command's options, exactly as its `--help` gives them. What each command does in",
        "full, with the numbers it measured, is in its guide under `docs/commands/`, listed in",
        "[the README](../../README.md#commands).",
        "",
        f"Formatted by Python {PYTHON}'s argparse.",
        "",
        "| command | what it does |",
        "|---|---|",
    ]
    for words, _, summary in commands:
        lines.append(f"| [`tactile-sim {' '.join(words)}`]({page_name(words)}) | {_cell(summary)} |")
    return "\n".join(lines) + "\n"


def render_pages(parser: argparse.ArgumentParser | None = None) -> dict[str, str]:
    """Every page, keyed by its path relative to the repository root (``docs/cli/dataset.md``)."""
    parser = build_parser() if parser is None else parser
    commands = command_parsers(parser)
    pages = {str(CLI_DIR / "index.md"): index_page(commands)}
    for words, sub, summary in commands:
        pages[str(CLI_DIR / page_name(words))] = help_page(words, sub, summary)
    return pages


def write_pages(root: Path, pages: dict[str, str]) -> list[str]:
    """Write ``pages`` under ``root`` and remove any other page in ``docs/cli/``.

    Returns the paths written or removed, relative to ``root``.
    """
    changed = []
    folder = root / CLI_DIR
    folder.mkdir(parents=True, exist_ok=True)
    for stale in sorted(folder.glob("*.md")):
        rel = str(stale.relative_to(root))
        if rel not in pages:
            stale.unlink()
            changed.append(rel)
    for rel, text in pages.items():
        path = root / rel
        if not path.exists() or path.read_text(encoding="utf-8") != text:
            path.write_text(text, encoding="utf-8")
            changed.append(rel)
    return changed


def main(argv: list[str] | None = None) -> int:
    """``python3 -m scenes.docs_help [--root DIR]``: regenerate ``docs/cli/``."""
    parser = argparse.ArgumentParser(prog="python3 -m scenes.docs_help", description=main.__doc__)
    parser.add_argument("--root", type=Path, default=Path(__file__).resolve().parents[1],
                        help="the repository root (default: the one holding this module)")
    args = parser.parse_args(argv)
    changed = write_pages(args.root, render_pages())
    for rel in changed:
        print(rel)
    print(f"{len(changed)} page(s) of {CLI_DIR} changed", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
