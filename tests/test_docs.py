"""The docs cannot drift: the command reference is the parser's, links resolve, and the
README keeps the test command CI runs."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from scenes import docs_help

ROOT = Path(__file__).resolve().parents[1]
REGENERATE = "run `python3 -m scenes.docs_help` and commit docs/cli/"


def markdown_files() -> list[Path]:
    return [ROOT / "README.md", *sorted((ROOT / "docs").rglob("*.md"))]


def test_the_command_reference_is_the_parsers():
    index = (ROOT / docs_help.CLI_DIR / "index.md").read_text(encoding="utf-8")
    made_by = re.search(r"Formatted by Python (\d+\.\d+)'s argparse", index)
    assert made_by, f"docs/cli/index.md does not say which Python made it: {REGENERATE}"
    if made_by.group(1) != docs_help.PYTHON:
        pytest.skip(f"docs/cli/ was formatted by Python {made_by.group(1)}'s argparse, whose help "
                    f"layout differs from this Python {docs_help.PYTHON}'s; CI checks it")
    expected = docs_help.render_pages()
    committed = {str(p.relative_to(ROOT)): p.read_text(encoding="utf-8")
                 for p in sorted((ROOT / docs_help.CLI_DIR).glob("*.md"))}
    stale = sorted(set(committed) - set(expected))
    missing = sorted(set(expected) - set(committed))
    differ = sorted(k for k in set(expected) & set(committed) if expected[k] != committed[k])
    assert not (stale or missing or differ), (
        f"docs/cli/ is out of date with the commands' parsers ({REGENERATE}): "
        f"differ {differ}, missing {missing}, not a command any more {stale}")


def test_every_command_has_a_guide():
    for words, _, _ in docs_help.command_parsers(docs_help.build_parser()):
        guide = ROOT / "docs" / "commands" / f"{words[0]}.md"
        assert guide.is_file(), f"tactile-sim {words[0]} has no guide: write {guide.relative_to(ROOT)}"


def github_anchor(heading: str) -> str:
    """The anchor GitHub gives a heading: lower case, punctuation dropped, spaces to hyphens."""
    text = re.sub(r"[^\w\- ]", "", heading.strip().lower())
    return text.replace(" ", "-")


def anchors(path: Path) -> set[str]:
    found, seen = set(), {}
    for line in strip_code(path.read_text(encoding="utf-8"), spans=False).splitlines():
        match = re.match(r"#{1,6} (.+)", line)
        if match:
            slug = github_anchor(match.group(1))
            n = seen.get(slug, 0)
            seen[slug] = n + 1
            found.add(slug if n == 0 else f"{slug}-{n}")
    return found


def strip_code(text: str, spans: bool = True) -> str:
    """``text`` without fenced code blocks (and, with ``spans``, inline code)."""
    text = re.sub(r"^```.*?^```", "", text, flags=re.S | re.M)
    return re.sub(r"`[^`\n]*`", "", text) if spans else text


def relative_links(path: Path) -> list[str]:
    links = re.findall(r"\]\(([^)\s]+)\)", strip_code(path.read_text(encoding="utf-8")))
    return [link for link in links if not re.match(r"[a-z]+:", link)]


@pytest.mark.parametrize("path", markdown_files(), ids=lambda p: str(p.relative_to(ROOT)))
def test_relative_links_resolve(path):
    broken = []
    for link in relative_links(path):
        target, _, anchor = link.partition("#")
        file = (path.parent / target).resolve() if target else path
        if not file.exists():
            broken.append(f"{link} (no such file)")
        elif anchor and file.suffix == ".md" and anchor not in anchors(file):
            broken.append(f"{link} (no heading with that anchor)")
    assert not broken, f"{path.relative_to(ROOT)} links to what is not there: {broken}"


def test_the_readme_holds_the_test_command_ci_runs():
    run = (ROOT / ".ci" / "run").read_text(encoding="utf-8")
    commands = [line.strip() for line in run.splitlines() if line.strip().startswith("python3 -m pytest")]
    assert len(commands) == 1, f".ci/run should run one pytest command, found {commands}"
    readme = (ROOT / "README.md").read_text(encoding="utf-8")
    blocks = re.findall(r"^```bash\n(.*?)^```", readme, flags=re.S | re.M)
    assert any(commands[0] in block.splitlines() for block in blocks), (
        f"README.md must show CI's test command in a bash block, exactly: {commands[0]}")


def test_the_pages_are_written_where_the_test_reads_them(tmp_path):
    pages = {"docs/cli/index.md": "a\n", "docs/cli/x.md": "b\n"}
    (tmp_path / "docs" / "cli").mkdir(parents=True)
    (tmp_path / "docs" / "cli" / "gone.md").write_text("old")
    changed = docs_help.write_pages(tmp_path, pages)
    assert sorted(changed) == ["docs/cli/gone.md", "docs/cli/index.md", "docs/cli/x.md"]
    assert sorted(p.name for p in (tmp_path / "docs" / "cli").iterdir()) == ["index.md", "x.md"]
    assert docs_help.write_pages(tmp_path, pages) == []
