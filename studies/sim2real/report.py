"""The study's tables (``tables.md``) and figure (``transfer.png``), from results.json."""

from __future__ import annotations

import numpy as np

from scenes.images import pyplot
from scenes.indenters import INDENTERS

from .plan import INPUTS, Run
from .summary import PAPER


def _fmt(cell: dict | None, metric: str) -> str:
    if not cell or metric not in cell:
        return "–"
    c = cell[metric]
    lo, hi = c["interval"]
    return f"{c['mean']:.1f} [{lo:.1f}, {hi:.1f}]"


def _paper(kind: str, protocol: str, inp: str, metric: str) -> str:
    v = PAPER.get(kind, {}).get(protocol, {}).get(inp, {}).get(metric)
    return "–" if v is None else f"{v:.1f}"


def tables(doc: dict) -> str:
    """Markdown: the paper's Tables 2 and 3 beside this study's, then the trainings."""
    s = doc["settings"]
    lines = [f"# Sim2Real learning on the virtual rig ({s['model']}, {s['seeds']} seeds, "
             f"{s['training']['steps']} steps of {s['training']['batch']})", "",
             "Mean over seeds [95 % t interval]; the paper's value after the slash.", "",
             "## Table 2: classification accuracy (%) and Table 3: localisation error (mm), plane field", "",
             "| | base, full | extended, full | base, patch | extended, patch | localisation base | "
             "localisation extended |", "|---|---|---|---|---|---|---|"]
    for kind, label in (("r2r", "Real2Real"), ("s2s", "Sim2Sim"), ("s2r", "Sim2Real")):
        row = [label]
        for inp in INPUTS:
            for p in ("base", "extended"):
                row.append(f"{_fmt(doc[kind].get(p, {}).get(inp), 'accuracy')} / {_paper(kind, p, inp, 'accuracy')}")
        for p in ("base", "extended"):
            row.append(f"{_fmt(doc[kind].get(p, {}).get('full'), 'localisation_mm')} / "
                       f"{_paper(kind, p, 'full', 'localisation_mm')}")
        lines.append("| " + " | ".join(row) + " |")
    best = doc["replays"]["best_field"]
    lines += ["", "Replays' MAE to the capture by field: " + ", ".join(
        f"{f} {v:.4f}" for f, v in sorted(doc["replays"]["mae_to_capture"].items(), key=lambda kv: kv[1]))
        + f"; best: {best}.", ""]
    lines += ["## Every simulated set", "", "| set | S2S full | S2R full | S2S patch | S2R patch | S2S loc. | S2R loc. |",
              "|---|---|---|---|---|---|---|"]
    for name in doc["by_set"]["s2s"]:
        a, b = doc["by_set"]["s2s"][name], doc["by_set"]["s2r"][name]
        lines.append(f"| {name} | {_fmt(a['full'], 'accuracy')} | {_fmt(b['full'], 'accuracy')} | "
                     f"{_fmt(a['patch'], 'accuracy')} | {_fmt(b['patch'], 'accuracy')} | "
                     f"{_fmt(a['full'], 'localisation_mm')} | {_fmt(b['full'], 'localisation_mm')} |")
    d = doc["diagnosis"]
    lines += ["", "## Closing the gap: Sim2Real by training (plane field)", "",
              f"Diagnosed effects: {', '.join(d['effects']) or 'none'}.", "",
              "| training | set | accuracy full | accuracy patch | localisation (mm) | gap closed: classification full | "
              "patch | localisation |", "|---|---|---|---|---|---|---|---|"]
    for t, by_set in doc["s2r_by_training"].items():
        for p, cells in by_set.items():
            g = doc["gap_closed"].get(t, {}).get(p, {})

            def share(inp: str, task: str) -> str:
                e = g.get(inp, {}).get(task)
                if not e or e.get("share") is None:
                    return "–"
                iv = e.get("interval")
                return f"{100 * e['share']:.0f} %" + (f" [{100 * iv[0]:.0f}, {100 * iv[1]:.0f}]" if iv else "")

            lines.append(f"| {t} | {p} | {_fmt(cells['full'], 'accuracy')} | {_fmt(cells['patch'], 'accuracy')} | "
                         f"{_fmt(cells['full'], 'localisation_mm')} | {share('full', 'classification')} | "
                         f"{share('patch', 'classification')} | {share('full', 'localisation')} |")
    shown = doc.get("contrast")
    if shown:
        sets = list(shown["per_set"])
        lines += ["", "## How strongly the contacts show", "", shown["what"] + ": contact / elsewhere.", "",
                  "| indenter | " + " | ".join(sets) + " |", "|---" * (len(sets) + 1) + "|"]
        for name in shown["per_set"][sets[0]]:
            lines.append(f"| {name} | " + " | ".join(
                f"{shown['per_set'][s][name]['contact']:.4f} / {shown['per_set'][s][name]['elsewhere']:.4f}"
                for s in sets) + " |")
    return "\n".join(lines) + "\n"


def figure(doc: dict, results: dict, study, path) -> None:
    """Confusion matrices on the capture's taps (every seed's model on all 144) and each
    tap's localisation error on the sensor, for R2R and for S2R by training."""
    plt = pyplot()
    seeds = doc["settings"]["seeds"]
    plane = [s for s in doc["s2r_by_training"].get("none", {})]
    target = f"{plane[-1]}_plane" if plane else None
    panels = [("R2R (held-out taps)", "real", "none", "own")]
    panels += [(f"S2R {target.split('_')[0]}, {t}", target, t, "real_all") for t in doc["s2r_by_training"]] if target else []
    fig, axes = plt.subplots(2, len(panels), figsize=(3.6 * len(panels), 7.0), squeeze=False)
    real = study.sets["real"]
    index = {str(i): k for k, i in enumerate(real.ids)}
    pts = real.point.astype(np.float64)
    azimuth = np.degrees(np.arctan2(pts[:, 1], pts[:, 0]))
    for j, (title, train_set, training, test) in enumerate(panels):
        conf = np.zeros((len(INDENTERS), len(INDENTERS)))
        err_sum, err_n = np.zeros(len(real)), np.zeros(len(real))
        for seed in range(seeds):
            c = results.get(Run(train_set, training, "full", "classification", seed).name)
            if c:
                for t, p in zip(c[test]["true"], c[test]["predicted"]):
                    conf[t, p] += 1
            loc = results.get(Run(train_set, training, "full", "localisation", seed).name)
            if loc:
                for i, e in zip(loc[test]["ids"], loc[test]["error_mm"]):
                    err_sum[index[i]] += e
                    err_n[index[i]] += 1
        rows = conf.sum(axis=1, keepdims=True)
        ax = axes[0, j]
        ax.imshow(np.divide(conf, rows, out=np.zeros_like(conf), where=rows > 0), vmin=0, vmax=1, cmap="viridis")
        ax.set_title(title, fontsize=9)
        ax.set_xticks(range(len(INDENTERS)), INDENTERS, rotation=90, fontsize=6)
        ax.set_yticks(range(len(INDENTERS)), INDENTERS, fontsize=6)
        ax.set_xlabel("predicted", fontsize=7)
        ax = axes[1, j]
        seen = err_n > 0
        sc = ax.scatter(azimuth[seen], 1000 * pts[seen, 2], c=err_sum[seen] / err_n[seen], cmap="magma_r", vmin=0,
                        vmax=15, s=14)
        ax.set_xlabel("azimuth (deg)", fontsize=7)
        ax.set_ylabel("height along the axis (mm)", fontsize=7)
        ax.set_title("localisation error (mm)", fontsize=8)
        fig.colorbar(sc, ax=ax, fraction=0.046)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
