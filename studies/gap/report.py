"""report.json, figures and report.html of a diagnosis."""

from __future__ import annotations

import html
import math
from pathlib import Path

import numpy as np

from scenes.files import atomic_write_bytes, write_json
from scenes.images import pyplot, save_figure

from .judge import MIN_RANK_SHARE
from .regions import CHANNELS, REGIONS


def _bars(ax, items: dict, title: str, key: str = "mae") -> None:
    names = [k for k, v in items.items() if v.get("samples", 0)]
    means = [items[k][key]["mean"] for k in names]
    lo = [items[k][key]["mean"] - items[k][key]["low"] for k in names]
    hi = [items[k][key]["high"] - items[k][key]["mean"] for k in names]
    ax.bar(range(len(names)), means, yerr=[lo, hi], capsize=3, color="#5b7fbd")
    ax.set_xticks(range(len(names)), names, rotation=30, ha="right", fontsize=8)
    ax.set_title(title, fontsize=9)
    ax.set_ylabel("MAE (fraction of full scale)", fontsize=8)


def figures(out: Path, report: dict, artefacts: dict) -> dict[str, str]:
    """Write the report's figures; returns {name: file name}."""
    plt = pyplot()
    out.mkdir(parents=True, exist_ok=True)
    files = {}
    maps, mask = artefacts["maps"], artefacts["mask"]

    fig, axes = plt.subplots(1, 5, figsize=(20, 3.6))
    im = axes[0].imshow(np.where(mask, maps["mean_abs"].mean(-1), np.nan), cmap="magma")
    axes[0].set_title("mean |real - sim| (all channels)", fontsize=9)
    fig.colorbar(im, ax=axes[0], fraction=0.04)
    for labels_name, colour in zip(artefacts["labels"], ("#ffffff", "#00ffff", "#ffff00", "#ff00ff")):
        axes[0].contour(artefacts["labels"][labels_name], levels=[0.5], colors=colour, linewidths=0.6)
    limit = float(np.nanmax(np.abs(maps["mean"][mask]))) or 1e-3
    for c, name in enumerate(CHANNELS):
        im = axes[1 + c].imshow(np.where(mask, maps["mean"][..., c], np.nan), cmap="RdBu_r", vmin=-limit, vmax=limit)
        axes[1 + c].set_title(f"mean real - sim, {name}", fontsize=9)
        fig.colorbar(im, ax=axes[1 + c], fraction=0.04)
    im = axes[4].imshow(np.where(mask, maps["spread"].mean(-1), np.nan), cmap="viridis")
    axes[4].set_title("spread of real - sim over samples", fontsize=9)
    fig.colorbar(im, ax=axes[4], fraction=0.04)
    for ax in axes:
        ax.axis("off")
    files["maps"] = save_figure(fig, out / "gap_maps.png", dpi=80).name

    w = report["where"]
    parts = [(w["regions"], "by region (tip: white, body: cyan, near LEDs: yellow)"),
             (w["contact"], "contact vs no contact"), (w["channels"], "by colour channel"),
             (w["depth"], "by contact depth")]
    parts = [(items, title) for items, title in parts if any(v.get("samples", 0) for v in items.values())]
    fig, axes = plt.subplots(1, len(parts), figsize=(4.2 * len(parts), 3.4), squeeze=False)
    for ax, (items, title) in zip(axes[0], parts):
        _bars(ax, items, title)
    files["split"] = save_figure(fig, out / "gap_split.png", dpi=80).name

    fig, axes = plt.subplots(1, 2, figsize=(14, 3.6))
    for ax, key, title in ((axes[0], "per_object", "masked MAE per object"),
                           (axes[1], "per_position", "masked MAE per tap position")):
        groups = report["gap"][key]["masked"]["mae"]
        names = list(groups)
        ax.bar(range(len(names)), [groups[n]["mean"] for n in names], color="#5b7fbd")
        ax.set_xticks(range(len(names)), names, rotation=60, ha="right", fontsize=7)
        ax.set_title(title, fontsize=9)
    files["groups"] = save_figure(fig, out / "gap_groups.png", dpi=80).name

    eff = report["effects"]
    if eff:
        names = sorted(eff, key=lambda n: -eff[n]["heldout"]["improvement"]["masked"]["mae"]["share"])
        imp = [eff[n]["heldout"]["improvement"]["masked"]["mae"] for n in names]
        fig, ax = plt.subplots(figsize=(9, 0.4 * len(names) + 1.2))
        y = np.arange(len(names))[::-1]
        share = np.array([i["share"] for i in imp]) * 100
        err = np.array([[i["share"] - i["share_low"], i["share_high"] - i["share"]] for i in imp]).T * 100
        colours = ["#2a9d5b" if eff[n]["significant"] else "#b0b0b0" for n in names]
        ax.barh(y, share, xerr=err, color=colours, capsize=3)
        ax.set_yticks(y, names, fontsize=8)
        ax.axvline(0, color="k", lw=0.6)
        ax.set_xlabel("share of the held-out masked MAE gap closed, % (95% CI); grey: not significant", fontsize=8)
        files["effects"] = save_figure(fig, out / "effects.png", dpi=80).name

    sel = report["selection"]
    if sel:
        before = report["gap"]["heldout"]["masked"]["mae"]
        points = [before] + [s["heldout"]["after"]["masked"]["mae"] for s in sel]
        labels = ["simulator"] + ["+ " + s["added"] for s in sel]
        fig, ax = plt.subplots(figsize=(1.6 * len(points) + 2, 3.2))
        ax.errorbar(range(len(points)), [p["mean"] for p in points],
                    yerr=[[p["mean"] - p["low"] for p in points], [p["high"] - p["mean"] for p in points]],
                    marker="o", capsize=3)
        ax.set_xticks(range(len(points)), labels, fontsize=8, rotation=20, ha="right")
        ax.set_ylabel("held-out masked MAE", fontsize=8)
        ax.set_ylim(bottom=0)
        files["selection"] = save_figure(fig, out / "selection.png", dpi=80).name

    ex = artefacts.get("examples")
    if ex is not None and len(ex["ids"]):
        rows = len(ex["ids"])
        fig, axes = plt.subplots(rows, 5, figsize=(15, 2.4 * rows), squeeze=False)
        for r in range(rows):
            panels = [ex["real"][r], ex["sim"][r], ex["model"][r], np.abs(ex["real"][r] - ex["sim"][r]),
                      np.abs(ex["real"][r] - ex["model"][r])]
            titles = ["real", "simulated", "with selected effects", "|real - sim|", "|real - with effects|"]
            for c, (img, title) in enumerate(zip(panels, titles)):
                axes[r, c].imshow(np.clip(img * (4 if c >= 3 else 1), 0, 1))
                axes[r, c].set_title(f"{ex['ids'][r]}: {title}" if c == 0 else title + (" (x4)" if c >= 3 else ""),
                                     fontsize=8)
                axes[r, c].axis("off")
        files["examples"] = save_figure(fig, out / "examples.png", dpi=70).name
    return files


def _fmt(ci: dict, scale: float = 1.0, digits: int = 4) -> str:
    return f"{ci['mean'] * scale:.{digits}f} [{ci['low'] * scale:.{digits}f}, {ci['high'] * scale:.{digits}f}]"


def _params(entry: dict, name: str) -> str:
    """An effect's fitted parameters, each with its bootstrap interval where it has one."""
    bounds = entry.get("param_intervals", {}).get(name, {})
    return ", ".join(f"{k} = {v:.4g}" + (f" [{bounds[k][0]:.4g}, {bounds[k][1]:.4g}]" if k in bounds else "")
                     for k, v in entry["params"][name].items())


def registration_line(entry: dict) -> str:
    """What the closed-form registration found before a moving effect's fit started from
    it (``studies.gap.registration``), beside what the fit found; "" for other effects."""
    found = entry.get("fit_status", {}).get("registration")
    if not found:
        return ""
    (_, fitted), = entry["params"].items()
    parts = []
    for kind, r in found.items():
        if r["reliable"]:
            how = f", correlation {r['correlation']:.3f}" if r.get("correlation") is not None else ""
            parts.append(f"{kind} ({r['frames']}): turn {r['rotation_deg']:+.2f} deg, shift ({r['du_px']:+.1f}, "
                         f"{r['dv_px']:+.1f}) px{how}")
        else:
            parts.append(f"{kind} ({r['frames']}): {r['reason']}")
    return ("Registration before the fit: " + "; ".join(parts)
            + f". The fit: turn {math.degrees(fitted['rotation_rad']):+.2f} deg, shift ({fitted['du_px']:+.1f}, "
              f"{fitted['dv_px']:+.1f}) px" + (f", scale {fitted['scale']:.4f}" if "scale" in fitted else "") + ".")


def _nothing_explains(report: dict) -> str:
    """The Answer's line when no candidate is ranked: none explains the gap, the closest
    ones and what they close, and where the gap lies (the regions, the channels)."""
    line = (f"No candidate explains the gap: none closes a significant share of the held-out gap, at least "
            f"{MIN_RANK_SHARE * 100:.0f}% of what is not sensor noise, with a 95% interval above zero.")
    closes = {n: e["heldout"]["improvement"]["masked"]["mae"] for n, e in report.get("effects", {}).items()}
    best = sorted(closes, key=lambda n: -closes[n]["share"])[:2]
    if best:
        line += " The closest: " + "; ".join(
            f"{n} closes {closes[n]['share'] * 100:.1f}% [{closes[n]['share_low'] * 100:.1f}, "
            f"{closes[n]['share_high'] * 100:.1f}]" for n in best) + "."
    where = report.get("where", {})
    regions = {k: v for k, v in where.get("regions", {}).items() if v.get("samples")}
    if regions:
        line += " The gap lies by region: " + ", ".join(
            f"{k.replace('_', ' ')} MAE {_fmt(v['mae'])}" for k, v in sorted(regions.items(),
                                                                              key=lambda kv: -kv[1]["mae"]["mean"]))
    channels = where.get("channels")
    if isinstance(channels, dict) and channels:
        line += "; by channel: " + ", ".join(f"{c} {_fmt(v['mae']) if isinstance(v, dict) else f'{v:.4f}'}"
                                             for c, v in channels.items())
    return line + "."


def headline(report: dict) -> list[str]:
    """The answer in a few sentences."""
    lines = []
    untested = report.get("not_applicable", {})
    if untested:
        lines.append(f"Not every candidate could be tested: {len(untested)} of {len(report.get('catalogue', {}))} were "
                     f"not ({', '.join(untested)}), so the answer below is limited to the rest; a cause among the "
                     "untested ones would show as the tested effects that mimic it best, or as no effect. Why each "
                     "was not tested is listed under 'Which effect causes it'.")
    screened = report.get("screened", {})
    if screened:
        lines.append(f"{len(screened)} re-rendered candidates ({', '.join(screened)}) were fitted on the training taps "
                     "but not judged on the held-out taps: their training loss was higher than the best re-rendered "
                     "ones', and judging each would cost a render per held-out tap. They are listed as closing "
                     "nothing, so a cause among them could show only through the effects that mimic it.")
    model = report.get("model", "fast")
    lines.append("The candidates are the physical effects of the reference that rendered the simulation (re-rendered "
                 "per light source)." if model == "pbr" else
                 "The candidates are the fast path's effect models, added to its rendering chain.")
    gap = report["gap"]["heldout"]
    judged = report.get("settings", {}).get("judged_at")
    at = (f", judged at {judged[0]}x{judged[1]} ({report['settings']['judged_at_why']})"
          if judged and judged != report.get("image_size") else "")
    lines.append(f"Held-out gap: masked MAE {_fmt(gap['masked']['mae'])}, SSIM {_fmt(gap['masked']['ssim'], digits=3)}, "
                 f"PSNR {_fmt(gap['masked']['psnr'], digits=1)} dB (full frame MAE {_fmt(gap['full']['mae'])}){at}.")
    regions = {k: v for k, v in report["where"]["regions"].items() if v.get("samples")}
    if regions:
        worst = max(regions, key=lambda k: regions[k]["mae"]["mean"])
        lines.append(f"The error is largest in the {worst.replace('_', ' ')} region "
                     f"(MAE {_fmt(regions[worst]['mae'])}).")
    contact = report["where"].get("contact", {})
    if contact.get("contact", {}).get("samples") and contact.get("no_contact", {}).get("samples"):
        lines.append(f"Contact areas: MAE {_fmt(contact['contact']['mae'])}; elsewhere {_fmt(contact['no_contact']['mae'])}.")
    if report["ranking"]:
        top = report["ranking"][0]
        share = report["effects"][top]["heldout"]["improvement"]["masked"]["mae"]
        params = _params(report["effects"][top], top)
        counterpart = report.get("catalogue", {}).get(top, {}).get("counterpart")
        lines.append(f"The effect that explains most of it is {top}{f' ({params})' if params else ''}: it closes "
                     f"{share['share'] * 100:.1f}% [{share['share_low'] * 100:.1f}, {share['share_high'] * 100:.1f}] "
                     "of the held-out gap on its own."
                     + (f" Its counterpart in the fast path's catalogue is {counterpart}." if counterpart else ""))
        registered = registration_line(report["effects"][top])
        if registered:
            lines.append(registered)
        pair = report.get("first_pair")
        if pair:
            share = pair["heldout"]["improvement"]["masked"]["mae"]
            fitted = "; ".join(f"{n}: {_params(pair, n)}" for n in pair["effects"])
            lines.append(f"It is ranked first with {report['ranking'][1]}: together ({pair['parameters']} parameters; "
                         f"{fitted}) they close {share['share'] * 100:.1f}% [{share['share_low'] * 100:.1f}, "
                         f"{share['share_high'] * 100:.1f}], as much as {pair['instead_of']} "
                         f"({pair['instead_of_parameters']} parameters) alone, and more than either alone.")
        lines += _contact_lines(report, top)
    else:
        lines.append(_nothing_explains(report))
    if report["selection"]:
        last = report["selection"][-1]
        by_region = _by_region(last["share_closed"])
        lines.append(f"Together, {' + '.join(last['effects'])} close {last['share_closed']['masked'] * 100:.1f}% of it "
                     f"(held-out masked MAE {_fmt(last['heldout']['after']['masked']['mae'])})"
                     + (f"; per region: {by_region}" if by_region else "")
                     + (f"; over the contacts: {last['share_closed']['contact'] * 100:.1f}%"
                        if "contact" in last["share_closed"] else "") + ".")
    mc = report["noise"].get("monte_carlo")
    if mc is not None:
        mc = mc.get("judged", mc)  # at the resolution the held-out gap is judged at
        floor = mc.get("mae_floor_difference", max(mc["mae_floor"].values()))
        share = floor / max(gap["masked"]["mae"]["mean"], 1e-12)
        lines.append(f"Monte Carlo noise of the renders ({' and '.join(report['noise']['monte_carlo']['sides'])}, from "
                     f"their variance maps) alone makes an MAE of about {floor:.4f}"
                     f"{' (at least: its pixels are taken as independent)' if 'factor' in mc else ''}, {share * 100:.0f}% "
                     "of the held-out gap: no effect can close that part, and one that smooths the simulation (blur) "
                     "closes the simulation's share of it.")
    if report["noise"]["std"] > 0:
        lines.append(f"Estimated sensor noise: {report['noise']['std']:.4f} (an MAE floor of about "
                     f"{report['noise']['mae_floor']:.4f} that no effect can remove).")
    return lines


def _disagree(improvement: dict) -> bool:
    """Whether a candidate's share of the gap closed over the contacts and over the whole
    image circle disagree: their 95 % intervals do not overlap."""
    if "contact" not in improvement:
        return False
    c, m = improvement["contact"]["mae"], improvement["masked"]["mae"]
    return c["share_high"] < m["share_low"] or c["share_low"] > m["share_high"]


def _contact_lines(report: dict, top: str) -> list[str]:
    """What the top candidate closes over the held-out taps' contact regions, beside the
    whole image circle, and each candidate whose two shares disagree (:func:`_disagree`)."""
    improvement = report["effects"][top]["heldout"]["improvement"]
    if "contact" not in improvement:
        return []
    contact = improvement["contact"]["mae"]
    gap = f" (the contacts' held-out MAE {_fmt(report['gap_contact']['mae'])})" if report.get("gap_contact") else ""
    lines = [f"Over the contacts alone {top} closes {contact['share'] * 100:.1f}% [{contact['share_low'] * 100:.1f}, "
             f"{contact['share_high'] * 100:.1f}] of the held-out gap there{gap}."]
    disagree = []
    for name, entry in report["effects"].items():
        imp = entry.get("heldout", {}).get("improvement", {})
        if name not in report.get("screened", {}) and _disagree(imp):
            c, m = imp["contact"]["mae"], imp["masked"]["mae"]
            disagree.append(f"{name} ({m['share'] * 100:.0f}% [{m['share_low'] * 100:.0f}, {m['share_high'] * 100:.0f}]"
                            f" of the image circle's gap, {c['share'] * 100:.0f}% [{c['share_low'] * 100:.0f}, "
                            f"{c['share_high'] * 100:.0f}] of the contacts')")
    if disagree:
        lines.append("The whole image and the contacts disagree (95% intervals apart) on " + "; ".join(disagree)
                     + ": a candidate that closes more of the image's gap than of the contacts' mends the rest of the "
                       "image more than what a press shows.")
    return lines


def _by_region(share_closed: dict) -> str:
    """'12.0% at the tip, ...' of a share_closed entry's region scopes (empty if it has none)."""
    return ", ".join(f"{share_closed[name] * 100:.1f}% {'in the' if name in ('body', 'near_leds') else 'at the'} "
                     f"{name.replace('_', ' ')}" for name in REGIONS if name in share_closed)


def _table(header: list[str], rows: list[list]) -> str:
    head = "".join(f"<th>{html.escape(str(h))}</th>" for h in header)
    body = "".join("<tr>" + "".join(f"<td>{html.escape(str(c))}</td>" for c in row) + "</tr>" for row in rows)
    return f"<table><tr>{head}</tr>{body}</table>"


def render_html(report: dict, files: dict[str, str]) -> str:
    e = report["effects"]
    effect_rows = []
    order = report["ranking"] + [n for n in e if n not in report["ranking"]]
    for n in order:
        imp = e[n]["heldout"]["improvement"]["masked"]
        judged = n not in report.get("screened", {})
        effect_rows.append([
            (report["ranking"].index(n) + 1) if n in report["ranking"] else "-", n,
            f"{imp['mae']['share'] * 100:.1f}% [{imp['mae']['share_low'] * 100:.1f}, {imp['mae']['share_high'] * 100:.1f}]"
            if judged else "not judged (screened out)",
            _fmt(imp["ssim"], digits=4) if judged and "ssim" in imp else "-",
            _fmt(imp["psnr"], digits=2) if judged else "-",
            "yes" if e[n]["significant"] else "no",
            _params(e[n], n)])
    sel_rows = [[i + 1, "+ " + s["added"], " + ".join(s["effects"]), _fmt(s["heldout"]["after"]["masked"]["mae"]),
                 _fmt(s["heldout"]["after"]["masked"]["ssim"], digits=3),
                 _fmt(s["heldout"]["after"]["masked"]["psnr"], digits=1), f"{s['share_closed']['masked'] * 100:.1f}%",
                 f"{s['share_closed']['full'] * 100:.1f}%", _by_region(s["share_closed"]) or "-"]
                for i, s in enumerate(report["selection"])]
    where_rows = []
    for group in ("regions", "contact", "channels", "depth"):
        for name, v in report["where"][group].items():
            if v.get("samples"):
                where_rows.append([group, name, v["samples"], _fmt(v["mae"]), f"{v['signed']:+.4f}", f"{v['spread']:.4f}"])
    gap = report["gap"]
    gap_rows = [[scope, split_name, _fmt(gap[split_name][scope]["mae"]), _fmt(gap[split_name][scope]["ssim"], digits=3),
                 _fmt(gap[split_name][scope]["psnr"], digits=1)]
                for split_name in ("all", "heldout") for scope in ("full", "masked")]
    na = "".join(f"<li><b>{html.escape(k)}</b>: {html.escape(v)}</li>"
                 for k, v in {**report["not_applicable"], **report.get("screened", {})}.items())
    img = "".join(f'<p><img src="{html.escape(f)}" style="max-width:100%"></p>' for f in files.values())
    heads = "".join(f"<li>{html.escape(line)}</li>" for line in headline(report))
    registered = "".join(f"<li><b>{html.escape(n)}</b>: {html.escape(registration_line(e[n]))}</li>" for n in order
                         if registration_line(e[n]))
    return f"""<!doctype html><html><head><meta charset="utf-8"><title>Sim-to-real gap diagnosis</title>
<style>body{{font-family:sans-serif;max-width:1250px;margin:auto;padding:1em}}table{{border-collapse:collapse;margin:.5em 0}}
td,th{{border:1px solid #ccc;padding:3px 6px;font-size:13px}}th{{background:#eee}}</style></head><body>
<h1>Sim-to-real gap diagnosis</h1>
<p>Real: <code>{html.escape(report['real_dir'])}</code>; simulated: <code>{html.escape(report['sim_dir'])}</code>;
{report['pairs']} pairs: {report['split']['train']} in the training split (fits use
{report['split'].get('fit_samples', report['split']['train'])} of them, spread over objects) and
{report['split']['heldout']} held out (stratified by object, seed {report['split']['seed']}). Every "after" number is on held-out samples only.
Intervals are 95% bootstrap intervals over samples.</p>
<h2>Answer</h2><ul>{heads}</ul>
<h2>How big the gap is</h2>{_table(["scope", "samples", "MAE", "SSIM", "PSNR (dB)"], gap_rows)}
<h2>Where it lies</h2>
<p>Per-sample MAE over each area (mean [95% CI]); signed = mean of real - sim; spread = SD of the per-sample MAE.</p>
{_table(["split", "area", "samples", "MAE", "signed", "spread"], where_rows)}
<h2>Which effect causes it</h2>
<p>Each effect fitted alone on the training samples, judged on the held-out ones: the share of the held-out masked MAE
it closes, and the change of SSIM (measured only for those that are ranked: it costs most of a judgement) and PSNR
(positive is better). Only effects that close a significant share of the gap,
at least {MIN_RANK_SHARE:.0%} of what is not sensor noise with a 95% interval above zero, are ranked.</p>
{_table(["rank", "effect", "gap closed (MAE)", "SSIM change", "PSNR change (dB)", "significant", "fitted parameters"], effect_rows)}
{"<p>Not applicable here, or not judged on the held-out samples:</p><ul>" + na + "</ul>" if na else ""}
{"<p>Moves registered in closed form before their fits started (turn counter-clockwise as displayed, shift in "
 "full-resolution pixels, the catalogue's convention):</p><ul>" + registered + "</ul>" if registered else ""}
<h2>How far it shrinks</h2>
<p>Greedy forward selection: each step adds the effect that most improves the jointly fitted combination on the
held-out samples, while that step's improvement is significant.</p>
{_table(["step", "added", "combination", "MAE", "SSIM", "PSNR (dB)", "gap closed (masked)", "gap closed (full frame)",
         "gap closed per region"], sel_rows) if sel_rows else "<p>No effect was selected.</p>"}
<p>Sensor noise estimated from the remaining residual: {report['noise']['std']:.4f}. {html.escape(report['noise']['note'])}.</p>
<h2>Figures</h2>{img}
<p>Finished in {report['seconds']:.1f} s.</p></body></html>
"""


def write_report(out: Path, report: dict, artefacts: dict) -> None:
    """report.json, report.html and the figures into ``out``."""
    out.mkdir(parents=True, exist_ok=True)
    files = figures(out, report, artefacts)
    write_json(out / "report.json", report)
    atomic_write_bytes(out / "report.html", render_html(report, files).encode())
