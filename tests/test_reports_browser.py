"""The HTML reports of compare and diagnose, opened in headless Chromium: the page loads,
every figure in the report's folder is shown, and no image is broken.

No browser driver is needed: a copy of report.html beside it (so relative figure paths
resolve) gets a script that, once the page and its images have loaded, writes a JSON
verdict into the DOM; ``chromium --headless --dump-dom`` prints the DOM and the test reads
the verdict. Needs the Debian package ``chromium`` (.ci/setup installs it).
"""

from __future__ import annotations

import html
import json
import re
import shutil
import subprocess
from pathlib import Path

import pytest

#: Seconds of the page's virtual time Chromium waits for loads before dumping the DOM.
VIRTUAL_TIME_BUDGET_MS = 5000
#: Seconds before the browser is given up on.
TIMEOUT_S = 60
VERDICT = re.compile(r'<pre id="verdict">(.*?)</pre>', re.S)
PROBE = """<script>
window.addEventListener("load", () => {
  const images = Array.from(document.images).map(i => ({src: i.getAttribute("src"), complete: i.complete,
                                                       width: i.naturalWidth, height: i.naturalHeight}));
  const verdict = {title: document.title, headings: document.querySelectorAll("h1, h2").length, images: images};
  const pre = document.createElement("pre");
  pre.id = "verdict";
  pre.textContent = JSON.stringify(verdict);
  document.body.appendChild(pre);
});
</script>"""


@pytest.fixture(scope="session")
def chromium() -> str:
    """The browser's path, or skip (first, before any report is built)."""
    for name in ("chromium", "chromium-browser", "google-chrome"):
        path = shutil.which(name)
        if path:
            return path
    pytest.skip("no headless Chromium here (Debian: apt-get install --no-install-recommends chromium; .ci/setup "
                "installs it)")


def open_in_browser(chromium: str, report: Path, tmp_path: Path) -> dict:
    """The verdict of ``report`` (an HTML file) loaded in headless Chromium."""
    probe = report.with_name(f"_probe_{report.name}")
    text = report.read_text()
    assert "</body>" in text, f"{report} has no </body>"
    probe.write_text(text.replace("</body>", PROBE + "</body>", 1))
    try:
        done = subprocess.run([chromium, "--headless=new", "--no-sandbox", "--disable-gpu", "--no-first-run",
                               f"--user-data-dir={tmp_path / 'chromium'}",
                               f"--virtual-time-budget={VIRTUAL_TIME_BUDGET_MS}", "--dump-dom", probe.as_uri()],
                              capture_output=True, text=True, timeout=TIMEOUT_S, check=False)
    finally:
        probe.unlink()
    found = VERDICT.search(done.stdout)
    assert found, f"no verdict in the page (exit {done.returncode}); stderr: {done.stderr[-2000:]}"
    return json.loads(html.unescape(found.group(1)))


def check_figures(verdict: dict, folder: Path, title: str) -> None:
    assert verdict["title"] == title and verdict["headings"] > 1
    shown = {i["src"] for i in verdict["images"]}
    figures = {p.name for p in folder.glob("*.png")}
    assert figures and shown == figures, f"shown {sorted(shown)}, in the folder {sorted(figures)}"
    broken = [i for i in verdict["images"] if not (i["complete"] and i["width"] > 0 and i["height"] > 0)]
    assert not broken, broken


def test_compare_report_shows_every_figure(chromium, compare_result, tmp_path):
    _, out = compare_result
    check_figures(open_in_browser(chromium, out / "report.html", tmp_path), out, "Table 1: simulation against the rig")


def test_diagnose_report_shows_every_figure(chromium, diagnose_report, tmp_path):
    check_figures(open_in_browser(chromium, diagnose_report / "report.html", tmp_path), diagnose_report,
                  "Sim-to-real gap diagnosis")


def test_a_broken_figure_is_caught(chromium, compare_result, tmp_path):
    """The check can fail: a report whose figure is missing is refused."""
    _, out = compare_result
    copy = shutil.copytree(out, tmp_path / "copy", ignore=shutil.ignore_patterns("renders"))
    (copy / "examples.png").rename(copy / "moved.png")
    verdict = open_in_browser(chromium, copy / "report.html", tmp_path)
    broken = [i["src"] for i in verdict["images"] if not (i["complete"] and i["width"] > 0)]
    assert broken == ["examples.png"]
    with pytest.raises(AssertionError):
        check_figures(verdict, copy, "Table 1: simulation against the rig")
