"""The study's figures: ``metrics.png``, ``regions.png`` and ``grid_<contact>.png``."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from scenes.curvature import CLASSES
from scenes.images import pyplot, srgb

from .metrics import KINDS, METRICS


def metrics_figure(path: Path, results: dict) -> Path:
    """Bars of each metric per field (mean over contacts) with bootstrap CI error bars."""
    plt = pyplot()
    methods = list(results["table"])
    fig, axes = plt.subplots(len(KINDS), len(METRICS), figsize=(4.2 * len(METRICS), 3.4 * len(KINDS)))
    x = np.arange(len(methods))
    for i, kind in enumerate(KINDS):
        for j, metric in enumerate(METRICS):
            ax = axes[i, j]
            cells = [results["table"][m][kind][metric] for m in methods]
            means = np.array([c["mean"] for c in cells])
            err = np.array([[c["mean"] - c["ci_low"] for c in cells], [c["ci_high"] - c["mean"] for c in cells]])
            colours = ["tab:orange" if m == results["best"] else "tab:blue" for m in methods]
            ax.bar(x, means, yerr=err, capsize=4, color=colours, alpha=0.85)
            for k, c in enumerate(cells):
                ax.plot(np.full(len(c["values"]), x[k]), c["values"], "k.", ms=3, alpha=0.5)
            if metric == "mae" and kind != "contact":
                floor = results["noise_mae"]["full" if kind == "full" else "change_far"]["mean"]
                ax.axhline(floor, color="grey", ls="--", lw=1, label="reference noise")
            if kind == "change":
                base = results["baseline_no_change"][kind][metric]["mean"]
                ax.axhline(base, color="tab:red", ls=":", lw=1.2, label="no-change baseline")
            if ax.get_legend_handles_labels()[0]:
                ax.legend(fontsize=7, loc="lower right")
            ax.set_xticks(x, methods)
            ax.set_title(f"{kind}: {metric}")
    fig.suptitle(f"fast path vs PBR reference ({results['confidence']:.0%} bootstrap CI over "
                 f"{len(results['contacts'])} contacts; dots: contacts)")
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return path


def region_figure(path: Path, results: dict, regions: np.ndarray) -> Path:
    """Left: the class of region each film pixel sees. Right: each field's pixel error
    ratio per class (1: no better than predicting no change), with its interval."""
    from matplotlib.colors import ListedColormap

    plt = pyplot()
    fig, (left, right) = plt.subplots(1, 2, figsize=(10, 3.8), gridspec_kw={"width_ratios": [1, 1.4]})
    present = [c for c in CLASSES if (regions == c).any()]
    index = np.full(regions.shape, np.nan)
    for j, c in enumerate(present):
        index[regions == c] = j
    cmap = ListedColormap([f"C{CLASSES.index(c)}" for c in present])
    left.imshow(index, cmap=cmap, vmin=-0.5, vmax=len(present) - 0.5, interpolation="nearest")
    for j, c in enumerate(present):
        left.plot([], [], "s", color=f"C{CLASSES.index(c)}", label=c)
    left.legend(fontsize=7, loc="lower right")
    left.set_axis_off()
    left.set_title("class of region seen by each pixel", fontsize=9)
    table = results["pixel_regions"]["ratio"]
    classes = [c for c in CLASSES if any(c in t for t in table.values())]
    width = 0.8 / max(1, len(table))
    for m, (method, rows) in enumerate(table.items()):
        x = np.array([k for k, c in enumerate(classes) if c in rows], dtype=float) + (m - (len(table) - 1) / 2) * width
        cells = [rows[c] for c in classes if c in rows]
        err = np.array([[c["ratio"] - c["ci_low"] for c in cells], [c["ci_high"] - c["ratio"] for c in cells]])
        right.bar(x, [c["ratio"] for c in cells], width, yerr=err, capsize=3, label=method, alpha=0.85)
    right.axhline(1.0, color="tab:red", ls=":", lw=1.2, label="no change")
    right.set_xticks(range(len(classes)), classes)
    right.set_ylabel("|error| / |reference change| near the contacts")
    right.legend(fontsize=7)
    right.set_title("where each field fails (below 1: tracks the contact)", fontsize=9)
    fig.suptitle(f"{results['sensor']}: light fields by class of region")
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return path


def grid_figure(path: Path, name: str, ref0: np.ndarray, refk: np.ndarray, fast: dict, k: int, mask: np.ndarray,
                per_contact: dict) -> Path:
    """Reference and each calibrated field for one contact: frames (sRGB for viewing) on
    top, contact change (mean over channels) below."""
    plt = pyplot()
    cols = ["reference"] + list(fast)
    fig, axes = plt.subplots(2, len(cols), figsize=(2.8 * len(cols), 5.0), squeeze=False)
    change_ref = (refk - ref0).mean(axis=-1)
    vmax = float(np.abs(change_ref[mask]).max()) or 1.0
    for j, col in enumerate(cols):
        if col == "reference":
            frame, change, title = refk, change_ref, "PBR reference"
        else:
            frames, gains, offsets = fast[col]
            g, o = gains[k - 1], offsets[k - 1]
            frame = np.where(mask[..., None], g * frames[k] + o, 0.0)
            change = (g * (frames[k] - frames[0])).mean(axis=-1)
            m = per_contact[col][k - 1]
            title = f"{col}\nchange MAE {m['change']['mae']:.4f}, SSIM {m['change']['ssim']:.2f}"
        axes[0, j].imshow(srgb(frame))
        axes[0, j].set_title(title, fontsize=8)
        axes[1, j].imshow(np.where(mask, change, np.nan), cmap="RdBu_r", vmin=-vmax, vmax=vmax)
    for ax in axes.ravel():
        ax.set_axis_off()
    fig.suptitle(f"{name}: calibrated frames (top), contact change, mean of channels (bottom, ±{vmax:.3f})")
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return path
