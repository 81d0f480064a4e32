"""table.json, table.md, figures and report.html of a comparison.

Figures are PNG files beside report.html, referenced by relative paths, as the gap
diagnosis's report does (``studies.gap.report``).
"""

from __future__ import annotations

import html
from pathlib import Path

import numpy as np

from scenes.files import atomic_write_bytes, write_json
from scenes.images import pyplot, save_figure

from . import table

#: Gain of the |difference| panels, so that small errors show.
DIFF_GAIN = 4.0


def figures(out: Path, result: dict, examples: dict, mask: np.ndarray) -> dict[str, str]:
    """Write the figures; returns {name: file name}."""
    plt = pyplot()
    files = {}
    rows = result["rows"]

    scopes = table.scopes_of(rows)
    fig, axes = plt.subplots(1, len(scopes), figsize=(6 * len(scopes), 0.35 * len(rows) + 1.6), squeeze=False)
    y = np.arange(len(rows))[::-1]
    colour = {"reference": "#c0504d", "peer": "#9bbb59"}
    for ax, scope in zip(axes[0], scopes):
        ci = [r[scope]["mae"] for r in rows]
        mean = np.array([c["mean"] for c in ci])
        err = np.array([[c["mean"] - c["low"], c["high"] - c["mean"]] for c in ci]).T
        ax.barh(y, mean, xerr=err, color=[colour.get(r["method"], "#5b7fbd") for r in rows], capsize=3)
        ax.set_yticks(y, [r["label"] for r in rows], fontsize=8)
        ax.set_xlabel(f"MAE, {table.SCOPE_NAMES[scope]} (mean, 95% CI over taps)", fontsize=8)
    files["metrics"] = save_figure(fig, out / "metrics.png", dpi=80).name

    maps = examples["mean_abs"]
    cols = min(4, len(maps))
    n_rows = -(-len(maps) // cols)
    fig, axes = plt.subplots(n_rows, cols, figsize=(3.2 * cols, 2.6 * n_rows), squeeze=False)
    top = max(float(np.nanmax(m)) for m in maps.values()) or 1e-3
    for ax, (label, m) in zip(axes.ravel(), maps.items()):
        im = ax.imshow(np.where(mask, m, np.nan), cmap="magma", vmin=0, vmax=top)
        ax.set_title(label, fontsize=7)
        fig.colorbar(im, ax=ax, fraction=0.04)
    for ax in axes.ravel():
        ax.axis("off")
    fig.suptitle("mean |real - simulated| over taps, all channels", fontsize=9)
    files["error_maps"] = save_figure(fig, out / "error_maps.png", dpi=80).name

    shown = examples["ids"]
    if shown:
        fast = result["best_fast"]
        reference = next((r["label"] for r in rows if r["method"] == "reference"), None)
        panels = [("real", examples["real"]), (fast, examples["images"][fast])]
        if reference is not None:
            panels.append((reference, examples["images"][reference]))
        diffs = [(f"|real - {label.split(':')[0]}| (x{DIFF_GAIN:g})", np.abs(examples["real"] - images))
                 for label, images in panels[1:]]
        columns = panels + diffs
        fig, axes = plt.subplots(len(shown), len(columns), figsize=(2.8 * len(columns), 2.3 * len(shown)),
                                 squeeze=False)
        for r, sid in enumerate(shown):
            for c, (title, images) in enumerate(columns):
                gain = DIFF_GAIN if c >= len(panels) else 1.0
                axes[r, c].imshow(np.clip(images[r] * gain, 0, 1))
                axes[r, c].set_title(f"{sid}: {title}" if c == 0 else title, fontsize=7)
                axes[r, c].axis("off")
        files["examples"] = save_figure(fig, out / "examples.png", dpi=80).name
    return files


def markdown(result: dict) -> str:
    """table.md: the table over the fast path's taps, and over the reference's when fewer."""
    text = [f"# Table 1 on {result['capture']}", "",
            f"Mean over taps [{result['confidence']:.0%} bootstrap interval, {result['bootstrap']} resamples of the "
            f"taps, seed {result['seed']}]. Full frame as published (black border included); image circle: "
            f"masked to the lens' circle ({result['mask']['pixels']} px). MAE as a fraction of full scale; PSNR "
            "capped at 100 dB. Alignment " + result["alignment"]["note"] + ".", "",
            table.markdown(result["rows"], f"All taps ({len(result['taps'])} for the fast path, "
                                           f"{len(result['reference_taps'])} for the reference)")]
    if result["on_reference_taps"]:
        text += ["", table.markdown(result["on_reference_taps"],
                                    f"On the reference's {len(result['reference_taps'])} taps only")]
    text += [f"\nPeer {name} not scored: {status['why']}" for name, status in (result.get("peers") or {}).items()
             if not status.get("ran")]
    return "\n".join(text)


def _html_table(rows: list[dict]) -> str:
    head = "".join(f"<th>{html.escape(h)}</th>" for h in table.header(rows))
    body = "".join("<tr>" + "".join(f"<td>{html.escape(c)}</td>" for c in table.cells(r, rows)) + "</tr>"
                   for r in rows)
    return f"<table><tr>{head}</tr>{body}</table>"


def render_html(result: dict, files: dict[str, str]) -> str:
    captions = {"metrics": "MAE per method, full frame and image circle (reference in red)",
                "error_maps": "Where each method errs: mean |real - simulated| over its taps, in the image circle",
                "examples": "Examples: real, the best fast-path variant, the reference, and their errors"}
    figs = "".join(f'<figure><img src="{html.escape(name)}" alt="{html.escape(key)}" style="max-width:100%">'
                   f"<figcaption>{html.escape(captions.get(key, key))}</figcaption></figure>"
                   for key, name in files.items())
    subset = ""
    if result["on_reference_taps"]:
        subset = (f"<h2>On the reference's {len(result['reference_taps'])} taps</h2>"
                  + _html_table(result["on_reference_taps"]))
    unscored = "".join(f"<p>Peer {html.escape(name)} not scored: {html.escape(status['why'])}</p>"
                       for name, status in (result.get("peers") or {}).items() if not status.get("ran"))
    return f"""<!doctype html><html><head><meta charset="utf-8"><title>Table 1: simulation against the rig</title>
<style>body{{font-family:sans-serif;max-width:1250px;margin:auto;padding:1em}}table{{border-collapse:collapse;margin:.5em 0}}
td,th{{border:1px solid #ccc;padding:3px 6px;font-size:13px}}th{{background:#eee}}figure{{margin:1em 0}}</style></head><body>
<h1>Table 1: simulation against the rig</h1>
<p>Capture <code>{html.escape(result['capture'])}</code>: {len(result['taps'])} taps for the fast path,
{len(result['reference_taps'])} for the reference, each rendered at the rig's measured pose.
Profile: {html.escape(str(result['profile']))}. Alignment {html.escape(result['alignment']['note'])}.
Best fast-path variant (image circle MAE): <b>{html.escape(result['best_fast'])}</b>.</p>
<p>Mean over taps [{result['confidence']:.0%} bootstrap interval over taps, {result['bootstrap']} resamples, seed
{result['seed']}]. Full frame as published, and masked to the lens' image circle.</p>
<h2>All taps</h2>{_html_table(result['rows'])}{subset}{unscored}
<h2>Figures</h2>{figs}
<p>Finished in {result['seconds']:.1f} s.</p></body></html>
"""


def write_report(out: Path, result: dict, examples: dict, mask: np.ndarray) -> None:
    """table.json, table.md, report.html and the figures into ``out``."""
    out.mkdir(parents=True, exist_ok=True)
    files = figures(out, result, examples, mask)
    write_json(out / "table.json", result)
    atomic_write_bytes(out / "table.md", markdown(result).encode())
    atomic_write_bytes(out / "report.html", render_html(result, files).encode())
