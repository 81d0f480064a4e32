"""Where the light enters: a figure of a sensor's LED layouts, the spec's beside a fitted one.

Two views in the tube's frame, millimetres: from above (the pad's rim, the camera's view
of the membrane, each LED's place and its aim), and in each LED's own radial plane
(the membrane, the glass under it, the camera's axis, each LED's place with its aim and
beam's edges). The fitted layout is read from a calibration's profile (``reference.layout``)
or report (``layout.layout``).

    python -m studies.layout_figure --spec scenes/sensors/gelsight.toml --fitted cal/profile.toml --out layout.png
"""

from __future__ import annotations

import argparse
import json
import math
import tomllib
from pathlib import Path

import numpy as np

from scenes.layout import LEDLayout, layout_from_dicts, layout_of
from scenes.spec import SensorSpec
from scenes.spec_read import load_spec


def read_fitted(path: str | Path, spec: SensorSpec) -> tuple[LEDLayout, ...]:
    """The layout a calibration fitted: a profile.toml's ``reference.layout`` or a
    report.json's ``layout.layout``; ValueError naming the file where it has none."""
    path = Path(path)
    data = tomllib.loads(path.read_text()) if path.suffix == ".toml" else json.loads(path.read_text())
    table = (data.get("reference") or {}).get("layout") if path.suffix == ".toml" else (data.get("layout") or {}).get(
        "layout")
    if table is None:
        raise ValueError(f"{path} holds no fitted layout (a profile's reference.layout or a report's layout.layout): "
                         "calibrate with --fit-layout")
    return layout_from_dicts(table, spec, str(path))


def _sections(spec: SensorSpec):
    """The membrane's and the glass' radial sections, (r, z) mm in the tube frame: the
    membrane's vertices, the core's and the glass underside's base-loop points."""
    import trimesh

    from scenes.body import sensor_body

    body = sensor_body(spec)
    to_tube = np.linalg.inv(spec.camera.tube_to_camera())
    outer = trimesh.transform_points(np.asarray(body.membrane.vertices), to_tube)
    core = trimesh.transform_points(np.asarray(body.core.vertices), to_tube)
    under = trimesh.transform_points(np.asarray(body.core.vertices) - spec.membrane.glass_wall * body.normals, to_tube)

    def section(points):
        r = np.hypot(points[:, 0], points[:, 1])
        order = np.argsort(r)
        return r[order] * 1e3, points[order, 2] * 1e3

    return section(outer), section(core), section(under), outer


def figure(spec: SensorSpec, layouts: dict[str, tuple[LEDLayout, ...]], path: str | Path) -> Path:
    """Draw ``layouts`` (name -> layout) of ``spec`` (module doc) and write a PNG."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    (ro, zo), (rc, zc), (ru, zu), outer = _sections(spec)
    fig, (top, side) = plt.subplots(1, 2, figsize=(12, 5.5))
    rim = float(np.hypot(outer[:, 0], outer[:, 1]).max()) * 1e3
    angle = np.linspace(0, 2 * math.pi, 200)
    top.plot(rim * np.cos(angle), rim * np.sin(angle), color="0.5", lw=1, label="the pad's rim")
    apex = float(outer[np.argmin(np.hypot(outer[:, 0], outer[:, 1])), 2]) * 1e3
    half_h = apex * math.tan(spec.camera.fov_y / 2)  # the view on the membrane, about its apex
    half_w = half_h * spec.camera.width / spec.camera.height
    top.plot([-half_w, half_w, half_w, -half_w, -half_w], [-half_h, -half_h, half_h, half_h, -half_h], color="0.4",
             ls="--", lw=0.8, label="the camera's view")
    if spec.housing.radius is not None:
        h = spec.housing.radius * 1e3
        top.plot(h * np.cos(angle), h * np.sin(angle), color="0.75", ls=":", lw=1, label="the housing")
    side.fill_between(ro, zo, np.interp(ro, rc, zc), color="#f2d7b6", label="elastomer")
    side.fill_between(rc, zc, np.interp(rc, ru, zu), color="#cfe3f3", label="glass")
    side.axvline(0, color="0.6", lw=0.8)
    colours = {"red": "#d62728", "green": "#2ca02c", "blue": "#1f77b4"}
    styles = ["o", "^", "s", "D"]
    for k, (name, layout) in enumerate(layouts.items()):
        for led, p in zip(spec.leds, layout):
            c = colours.get(led.name, "k")
            x, y, z = p.position() * 1e3
            d = p.direction()
            marker = dict(marker=styles[k % len(styles)], color=c, mfc="none" if k else c, ms=8, ls="none")
            top.plot(x, y, **marker)
            top.annotate("", (x + 4 * d[0] / max(np.hypot(d[0], d[1]), 1e-9) * math.sin(p.aim_rad),
                              y + 4 * d[1] / max(np.hypot(d[0], d[1]), 1e-9) * math.sin(p.aim_rad)),
                         (x, y), arrowprops=dict(arrowstyle="->", color=c, alpha=0.8 if not k else 0.5))
            r = p.radius_m * 1e3
            side.plot(r, z, **marker)
            beam = math.pi / 2 if p.beam_half_angle_rad is None else p.beam_half_angle_rad
            for edge in (-beam, 0.0, beam) if p.beam_half_angle_rad is not None else (0.0,):
                a = p.aim_rad + edge
                side.plot([r, r - 6 * math.sin(a)], [z, z + 6 * math.cos(a)], color=c, lw=1.2 if edge == 0 else 0.6,
                          ls="-" if not k else "--", alpha=0.9)
        top.plot([], [], marker=styles[k % len(styles)], color="k", mfc="none" if k else "k", ls="none",
                 label=f"{name} ({', '.join(sorted({p.entry for p in layout}))})")
    top.set_aspect("equal")
    top.set_xlabel("x, mm (image right)")
    top.set_ylabel("y, mm (image down)")
    top.set_title("from the camera: where each LED sits and aims")
    top.legend(fontsize=8, loc="upper right")
    side.set_xlabel("distance from the axis, mm (each LED in its own radial plane)")
    side.set_ylabel("z, mm (up the camera's axis)")
    side.set_title("across: the pad, its plate, each LED's aim and beam")
    side.legend(fontsize=8, loc="lower left")
    fig.tight_layout()
    path = Path(path)
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return path


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m studies.layout_figure", description=__doc__.splitlines()[0])
    p.add_argument("--spec", required=True, metavar="TOML", help="the sensor (its LEDs are the spec's layout)")
    p.add_argument("--fitted", action="append", default=[], metavar="FILE",
                   help="a calibration's profile.toml or report.json with a fitted layout (repeatable)")
    p.add_argument("--out", required=True, metavar="PNG")
    args = p.parse_args(argv)
    spec = load_spec(args.spec)
    layouts = {"the spec's": layout_of(spec)}
    for path in args.fitted:
        layouts[f"fitted ({Path(path).parent.name or path})"] = read_fitted(path, spec)
    print(f"wrote {figure(spec, layouts, args.out)}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
