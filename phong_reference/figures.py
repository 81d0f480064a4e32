"""Figures of the fast path: light fields over the membrane, and contact sheets."""

from __future__ import annotations

from pathlib import Path

import numpy as np

#: Pixel stride of the arrows drawn in a field figure, at 640x480.
ARROW_STRIDE_PX = 28


def _pyplot():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def field_figure(mesh, fields, leds, camera, path: str | Path, stride: int | None = None) -> Path:
    """The light field of each LED as arrows on the membrane (like the paper's figure).

    One 3D panel per LED, showing the membrane and, at a grid of pixels, the direction the
    LED's light travels at that surface point; plus one panel of all LEDs seen from the
    in-sensor camera.
    """
    from mpl_toolkits.mplot3d.art3d import Poly3DCollection

    plt = _pyplot()
    stride = stride or max(2, int(round(ARROW_STRIDE_PX * camera.height / 480)))
    rows, cols = np.mgrid[stride // 2 : camera.height : stride, stride // 2 : camera.width : stride]
    rows, cols = rows.ravel(), cols.ravel()
    points = fields.depth[rows, cols, None] * camera.rays[rows, cols]
    n_led = len(leds)
    fig = plt.figure(figsize=(4.2 * (n_led + 1), 4.6))
    length = 0.0025
    extent = np.ptp(mesh.vertices, axis=0).max()
    for m, led in enumerate(leds):
        ax = fig.add_subplot(1, n_led + 1, m + 1, projection="3d")
        tris = mesh.vertices[mesh.faces]
        ax.add_collection3d(Poly3DCollection(tris, facecolor=(0.45, 0.45, 0.5, 0.12), edgecolor="none"))
        ok = fields.valid[m, rows, cols]
        p, v = points[ok], fields.fields[m, rows[ok], cols[ok]]
        ax.quiver(p[:, 0], p[:, 1], p[:, 2], v[:, 0], v[:, 1], v[:, 2], length=length, normalize=True,
                  color=0.8 * np.clip(led.colour, 0, 1), linewidth=0.9, arrow_length_ratio=0.35)
        ax.scatter(*led.position, color="k", s=30)
        centre = mesh.vertices.mean(axis=0)
        for setter, c in zip((ax.set_xlim, ax.set_ylim, ax.set_zlim), centre):
            setter(c - extent / 2, c + extent / 2)
        ax.set_box_aspect((1, 1, 1), zoom=1.6)
        ax.view_init(elev=20, azim=-60 + 120 * m)
        ax.set_title(f"{fields.method}: {led.name}")
        ax.set_axis_off()
    ax = fig.add_subplot(1, n_led + 1, n_led + 1)
    ax.imshow(np.where(camera.mask, fields.depth, np.nan), cmap="gray")
    for m, led in enumerate(leds):
        ok = fields.valid[m, rows, cols]
        p = points[ok]
        tip = p + 0.0015 * fields.fields[m, rows[ok], cols[ok]]
        du = camera.f * (tip[:, 0] / tip[:, 2] - p[:, 0] / p[:, 2])
        dv = camera.f * (tip[:, 1] / tip[:, 2] - p[:, 1] / p[:, 2])
        ax.quiver(cols[ok], rows[ok], du, dv, color=np.clip(led.colour, 0, 1), angles="xy", scale_units="xy",
                  scale=1.0, width=0.003)
    ax.set_title("seen by the camera (over D_ref)")
    ax.set_axis_off()
    fig.tight_layout()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110, bbox_inches="tight")
    plt.close(fig)
    return path


def contact_sheet(images: dict[tuple[str, str], np.ndarray], path: str | Path, thumb_px: int = 200) -> Path:
    """A grid of images keyed by (row label, column label), written as one PNG."""
    plt = _pyplot()
    row_labels = list(dict.fromkeys(k[0] for k in images))
    col_labels = list(dict.fromkeys(k[1] for k in images))
    h, w = next(iter(images.values())).shape[:2]
    size = thumb_px / 100
    fig, axes = plt.subplots(
        len(row_labels), len(col_labels), figsize=(size * len(col_labels) * w / h + 1.2, size * len(row_labels)),
        squeeze=False,
    )
    for i, r in enumerate(row_labels):
        for j, c in enumerate(col_labels):
            ax = axes[i, j]
            if (r, c) in images:
                ax.imshow(np.clip(images[(r, c)], 0, 1))
            ax.set_xticks([])
            ax.set_yticks([])
            if i == 0:
                ax.set_title(c, fontsize=9)
            if j == 0:
                ax.set_ylabel(r, fontsize=9)
    fig.tight_layout()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path
