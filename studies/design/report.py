"""The design loop's report: Markdown and figures from ``studies.design.loop.run``'s results."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from scenes.camera import Camera, project
from scenes.images import pyplot, srgb

from .score import SCORE_PERCENTILE, VISIBLE_SNR


def _per_mm(v: float) -> str:
    return f"{v * 1e-3:.1f}"


def markdown(data: dict) -> str:
    lines = [
        f"# Design sweep of {data['sensor']} ({data['family']})",
        "",
        (f"Each design: {data['taps_per_design']} standard taps ({data['indenter']}, "
         f"{data['tap_depth_m'] * 1e3:g} mm along the normal, the extended protocol's nominal points) on the MuJoCo "
         f"rig, rendered by the fast path ({data['field']} field, elastic layer model, no background). Contrast: the "
         "p95 over a tap's changed pixels of the largest channel's change in units of the real camera's noise, per "
         f"mm of depth. Score: its p{SCORE_PERCENTILE:g} over the taps. Dead: contrast under {VISIBLE_SNR:g}."),
        "",
        "| design | score (/mm) | median (/mm) | p90 (/mm) | evenness | dead taps | fast path (s) | reference: dark share "
        "| reference: light evenness | reference: p99.5 radiance |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for i, d in enumerate(data["designs"]):
        mark = " **best**" if i == data["best"] else " *worst*" if i == data["worst"] else ""
        if d["refused"] is not None:
            lines.append(f"| {d['label']} | refused: {d['refused']} | | | | | | | | |")
            continue
        s = d["score"]
        reach = d.get("reference_reach")
        lit = (f"{reach['dark_share']:.1%} | {reach['evenness']:.3f} | {reach['p99_5']:.4g}" if reach else " | | ")
        lines.append(f"| {d['label']}{mark} | {_per_mm(s['score'])} | {_per_mm(s['median'])} | {_per_mm(s['p90'])} | "
                     f"{s['evenness']:.2f} | {s['dead_share']:.0%} | {d['seconds']:.1f} | {lit} |")
    if data["reference_settings"] is not None:
        lines += ["", (f"Reference columns: its no-contact frame of each design; dark share = membrane pixels under "
                       f"{data['dark_fraction']:.0%} of the frame's p99.5 (largest channel), light evenness = p10 over "
                       "p99.5. The fast path's fields carry no falloff of light, so only the reference can show a "
                       "dead zone that distance or a bend leaves dark.")]
    check = data["reference_check"]
    if check is not None:
        st = data["reference_settings"]
        b, w = data["designs"][data["best"]]["label"], data["designs"][data["worst"]]["label"]
        lines += [
            "",
            f"## The reference on the best ({b}) and the worst ({w})",
            "",
            (f"Physically based reference (photon estimator, {st['width']}x{st['height']}, {st['photons']} photons "
             f"per LED per pass, {st['passes']} passes): contrast = p95 of the largest channel's |change| in linear "
             "radiance over the pixels the fast path's tap changes; noise = the same far from the contact. Ratios are "
             "best over worst within one renderer (a renderer's own units cancel)."),
            "",
            "| tap (row, position) | fast best / worst | reference best / worst | reference noise best / worst | "
            "fast ratio | reference ratio | agree |",
            "|---|---|---|---|---|---|---|",
        ]
        for r in check["taps"]:
            ratio = lambda v: "n/a" if v is None else f"{v:.2f}"  # noqa: E731
            lines.append(f"| {r['tap']} ({r['row']}, {r['position']}) | {r['fast_best']:.1f} / {r['fast_worst']:.1f} | "
                         f"{r['reference_best']:.4g} / {r['reference_worst']:.4g} | {r['reference_noise_best']:.3g} / "
                         f"{r['reference_noise_worst']:.3g} | {ratio(r['fast_ratio'])} | {ratio(r['reference_ratio'])} "
                         f"| {r['agrees']} |")
        med = lambda v: "n/a" if v is None else f"{v:.2f}"  # noqa: E731
        lines += ["", (f"The reference agrees with the fast path's ranking on {check['agreeing_taps']} of "
                       f"{len(check['taps'])} taps; median ratio fast {med(check['median_fast_ratio'])}, reference "
                       f"{med(check['median_reference_ratio'])}.")]
    lines += ["", f"Ranking, best first: {'; '.join(data['ranking'])}.", "",
              f"Total {data['seconds']:.0f} s."]
    return "\n".join(lines) + "\n"


def sweep_figure(path: Path, data: dict) -> Path:
    """Score, median and p90 against the first parameter (one line per value of the second)."""
    plt = pyplot()
    names = list(data["sweep"])
    fig, (ax, ax2) = plt.subplots(1, 2, figsize=(10, 3.8))
    second = data["sweep"][names[1]] if len(names) > 1 else [None]
    for j, v2 in enumerate(second):
        rows = [d for d in data["designs"] if d["refused"] is None and (v2 is None or d["values"][names[1]] == v2)]
        x = [d["values"][names[0]] for d in rows]
        tag = "" if v2 is None else f" ({names[1]} = {v2:.4g})"
        colour = f"C{j}"
        ax.plot(x, [d["score"]["score"] * 1e-3 for d in rows], "o-", color=colour, label=f"score (p10){tag}")
        ax.fill_between(x, [d["score"]["score"] * 1e-3 for d in rows], [d["score"]["p90"] * 1e-3 for d in rows],
                        color=colour, alpha=0.15)
        ax.plot(x, [d["score"]["median"] * 1e-3 for d in rows], "--", color=colour, label=f"median{tag}")
        ax2.plot(x, [d["score"]["dead_share"] for d in rows], "o-", color=colour, label=f"dead taps{tag}")
    ax.set_xlabel(names[0])
    ax.set_ylabel("contrast per mm (camera noise units)")
    ax.legend(fontsize=7)
    ax2.set_xlabel(names[0])
    ax2.set_ylabel("share of dead taps")
    ax2.set_ylim(-0.02, 1.02)
    fig.suptitle(f"{data['sensor']}: {data['field']} field, {data['taps_per_design']} {data['indenter']} taps per design "
                 "(band: p10 to p90)")
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return path


def _shown(frame: np.ndarray) -> np.ndarray:
    """A frame scaled for viewing: its 99.5th percentile to 1 (a tangent field's no-contact
    frame is nearly black)."""
    top = float(np.percentile(frame, 99.5))
    return np.clip(frame / top, 0.0, 1.0) if top > 0 else frame


def maps_figure(path: Path, data: dict, candidates, evaluated: dict) -> Path:
    """Each design's no-contact frame with its taps, coloured by contrast per mm; dead taps
    crossed."""
    plt = pyplot()
    shown = [i for i in evaluated]
    cols = min(4, max(1, len(shown)))
    rows = int(np.ceil(len(shown) / cols)) or 1
    fig, axes = plt.subplots(rows, cols, figsize=(3.4 * cols, 3.0 * rows), squeeze=False)
    vmax = max(d["score"]["p90"] for d in data["designs"] if d["refused"] is None) * 1e-3 or 1.0
    for ax, i in zip(axes.ravel(), shown):
        camera = Camera.from_spec(candidates[i].spec)
        taps = data["designs"][i]["taps"]
        uv = project(np.array([t["point"] for t in taps]), camera)
        c = np.array([t["contrast"] / t["depth_m"] * 1e-3 for t in taps])
        dead = np.array([t["contrast"] < VISIBLE_SNR for t in taps])
        ax.imshow(srgb(_shown(evaluated[i]["no_contact"])))
        sc = ax.scatter(uv[~dead, 0], uv[~dead, 1], c=c[~dead], cmap="viridis", vmin=0, vmax=vmax, s=14)
        ax.scatter(uv[dead, 0], uv[dead, 1], marker="x", color="red", s=14)
        mark = " (best)" if i == data["best"] else " (worst)" if i == data["worst"] else ""
        ax.set_title(f"{data['designs'][i]['label']}{mark}", fontsize=7)
    for ax in axes.ravel():
        ax.set_axis_off()
    fig.colorbar(sc, ax=axes.ravel().tolist(), shrink=0.6, label="contrast per mm (noise units); x: dead")
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return path


def check_figure(path: Path, data: dict, evaluated: dict, check: dict | None) -> Path:
    """The best and the worst design: fast-path frames of the checked taps, and the
    reference's when it ran."""
    plt = pyplot()
    roles = (("best", data["best"]), ("worst", data["worst"]))
    kept = sorted(evaluated[data["best"]]["kept"])
    images = check["images"] if check else None
    n_rows = 2 * (2 if images else 1)
    fig, axes = plt.subplots(n_rows, 1 + len(kept), figsize=(2.6 * (1 + len(kept)), 2.3 * n_rows), squeeze=False)
    r = 0
    for role, i in roles:
        ev = evaluated[i]
        axes[r, 0].imshow(srgb(_shown(ev["no_contact"])))
        axes[r, 0].set_title(f"{role}: fast, no contact", fontsize=7)
        for j, k in enumerate(kept, start=1):
            axes[r, j].imshow(srgb(ev["kept"][k][1]))
            axes[r, j].set_title(f"tap {k}: {ev['taps'][k]['contrast']:.0f} x noise", fontsize=7)
        r += 1
        if images:
            by_tap = {t["tap"]: t for t in images[role]}
            first = next(iter(by_tap.values()))
            scale = float(np.percentile(first["no_contact"], 99.5)) or 1.0
            axes[r, 0].imshow(srgb(np.clip(first["no_contact"] / scale, 0, 1)))
            axes[r, 0].set_title(f"{role}: reference, no contact", fontsize=7)
            for j, k in enumerate(kept, start=1):
                if k in by_tap:
                    axes[r, j].imshow(srgb(np.clip(by_tap[k]["frame"] / scale, 0, 1)))
                    axes[r, j].set_title(f"tap {k} (reference)", fontsize=7)
            r += 1
    for ax in axes.ravel():
        ax.set_axis_off()
    fig.suptitle(f"{data['sensor']}: best {data['designs'][data['best']]['label']}; "
                 f"worst {data['designs'][data['worst']]['label']}", fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return path
