"""Calibrate a sensor profile to a real capture: the whole run of ``tactile-sim calibrate``.

``calibrate_capture`` reads the capture (or one no-contact image), fits the reference's
profile (``calibrate.calibrate_background``) or the fast path's alone
(``calibrate.calibrate_fast``), and writes the profile and its report
(``write_outputs``); the command line parses arguments and calls it, and so do studies.
"""

from __future__ import annotations

import dataclasses
import json
import time
from pathlib import Path
from typing import Callable

import numpy as np

#: ``calibrate_capture``'s defaults: the command line's (``tactile-sim calibrate``).
WIDTH = 160
PHOTONS = 1 << 18
SPP = 32
BOOTSTRAP = 16


def real_background(real: str | None, background_only: str | None) -> tuple[Path, str]:
    """The no-contact image to calibrate from, and what it is: ``--background-only
    IMAGE``, or REAL a capture dataset (``source: "real"``) with its background.png."""
    if (real is None) == (background_only is None):
        raise ValueError("give exactly one of REAL (a capture dataset directory) or --background-only IMAGE")
    if background_only is not None:
        return Path(background_only), "one no-contact image"
    folder = Path(real)
    meta = folder / "dataset.json"
    if not meta.exists():
        raise FileNotFoundError(f"REAL {folder} is not a dataset: it has no dataset.json (for a single image use "
                                "--background-only IMAGE)")
    try:
        source = json.loads(meta.read_text()).get("source")
    except json.JSONDecodeError as exc:
        raise ValueError(f"REAL {meta} is not valid JSON: {exc}") from None
    if source != "real":
        raise ValueError(f"REAL {folder} has source {source!r}; calibration needs captures of a real sensor "
                         "(source: \"real\")")
    background = folder / "background.png"
    if not background.exists():
        raise ValueError(f"REAL {folder} has no background.png: calibration needs the sensor's no-contact capture")
    return background, f"the background of capture dataset {folder}"


def capture_spec(real: str):
    """The sensor a capture dataset records (its dataset.json), which a calibration of it
    takes when no --spec is given: an imported capture's camera is the set's own."""
    from scenes.dataset import read_meta
    from scenes.spec_read import spec_from_dict

    meta = read_meta(real)
    try:
        return spec_from_dict(meta["sensor"], f"REAL {real}/dataset.json sensor")
    except (KeyError, TypeError) as exc:
        raise ValueError(f"REAL {real}/dataset.json has no usable sensor spec: {exc!r}") from None


def _figure(images: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = [name for name in ("real", "before", "after", "fast_path") if name in images]
    residuals = [name for name in ("after", "fast_path") if name in images]
    fig, axes = plt.subplots(3, len(names) + len(residuals), figsize=(3.5 * (len(names) + len(residuals)), 9))
    for c, ch in enumerate("rgb"):
        for k, name in enumerate(names):
            axes[c, k].imshow(images[name][..., c], vmin=0, vmax=1, cmap="gray")
            axes[c, k].set_title(f"{name.replace('_', ' ')} ({ch})")
        for k, name in enumerate(residuals, start=len(names)):
            diff = np.where(images["judged"][..., c], images[name][..., c] - images["real"][..., c], np.nan)
            im = axes[c, k].imshow(diff, vmin=-0.2, vmax=0.2, cmap="RdBu_r")
            axes[c, k].set_title(f"{name.replace('_', ' ')} - real, held out ({ch})", fontsize=9)
            fig.colorbar(im, ax=axes[c, k])
    for ax in axes.ravel():
        ax.axis("off")
    fig.tight_layout()
    fig.savefig(path, dpi=80)
    plt.close(fig)


def _fast_path_html(fast: dict | None) -> str:
    if not fast:
        return ""
    rows = "".join(f"<tr><td>{ch}</td><td>{fast['solid']['heldout_r2'][ch]:.3f}</td><td>{fast['heldout_r2'][ch]:.3f}"
                   f"</td><td>{fast['solid']['heldout_mae'][ch]:.4f}</td><td>{fast['heldout_mae'][ch]:.4f}</td></tr>"
                   for ch in "rgb")
    return (f"<h2>The fast path's background term</h2><p>{fast['background_model']}; the same split.</p>"
            f"<table border=1><tr><th>channel</th><th>held-out R² solid colour</th><th>smooth model</th>"
            f"<th>MAE solid</th><th>smooth</th></tr>{rows}</table>")


def _taps_html(report: dict) -> str:
    taps = report.get("taps")
    if not taps:
        return ""
    fast = (report.get("fast_path") or {}).get("taps")

    def row(name, scores):
        return (f"<tr><td>{name}</td>" + "".join(f"<td>{scores['change_r2'].get(ch, float('nan')):.3f}</td>"
                                                  for ch in "rgb")
                + "".join(f"<td>{scores['mae'].get(ch, float('nan')):.4f}</td>" for ch in "rgb") + "</tr>")

    rows = [row("reference, from the image alone", taps["heldout_before_taps"]),
            row("reference, with taps", taps["heldout"])]
    if fast:
        rows += [row("fast path, the spec's LED constants", fast["heldout_before"]),
                 row(f"fast path, fitted (shininess {fast['shininess']:g})", fast["heldout"])]
    return (f"<h2>Taps</h2><p>Fitted: {', '.join(taps['fitted'])}; judged: {', '.join(taps['judged']) or 'none'}; "
            f"without a visible contact: {', '.join(taps['without_contact']) or 'none'}. {taps['split']}.</p>"
            "<table border=1><tr><th>held-out taps</th><th>change R² r</th><th>g</th><th>b</th><th>MAE r</th>"
            f"<th>g</th><th>b</th></tr>{''.join(rows)}</table>")


def write_outputs(calibration, out: Path, what: str) -> dict[str, Path]:
    """report.json, report.html, residual images and figure; profile.toml only for a
    converged fit."""
    from scenes.dataset import atomic_write_json
    from scenes.images import write_rgb
    from scenes.profile import write_profile

    out.mkdir(parents=True, exist_ok=True)
    report = {"data": what, **calibration.report}
    images = calibration.images
    np.save(out / "residual.npy", (images["after"] - images["real"]).astype(np.float32))
    write_rgb(out / "after.png", images["after"])
    write_rgb(out / "before.png", images["before"])
    write_rgb(out / "residual.png", np.clip(0.5 + 2.5 * (images["after"] - images["real"]), 0, 1))
    _figure(images, out / "residuals_figure.png")
    paths = {"report": out / "report.json", "html": out / "report.html"}
    if calibration.report["converged"]:
        paths["profile"] = write_profile(calibration.profile, out / "profile.toml")
    report["profile"] = str(paths["profile"]) if "profile" in paths else None
    atomic_write_json(paths["report"], report)
    rows = "".join(f"<tr><td>{ch}</td><td>{report['heldout_r2_before'][ch]:.3f}</td><td>{report['heldout_r2'][ch]:.3f}"
                   f"</td><td>{report['heldout_mae_before'][ch]:.4f}</td><td>{report['heldout_mae'][ch]:.4f}</td>"
                   f"<td>{'yes' if report['saturated'][ch] else 'no'}</td></tr>" for ch in "rgb")
    status = ("converged" if report["converged"] else
              "<b>did NOT converge: no profile was written</b>")
    paths["html"].write_text(
        f"<html><head><meta charset='utf-8'><title>Calibration</title></head><body><h1>Calibration of the reference</h1>"
        f"<p>From {what}. Fit {status}; {report['split']}.</p>"
        f"<table border=1><tr><th>channel</th><th>held-out R² before</th><th>after</th><th>MAE before</th>"
        f"<th>after</th><th>saturated</th></tr>{rows}</table>"
        f"<p>Best effects on the grid: {report['best_effects']}</p>{_fast_path_html(report.get('fast_path'))}"
        f"{_taps_html(report)}"
        f"<p>Not identifiable from this data:</p><ul>{''.join(f'<li>{x}</li>' for x in report['not_identifiable'])}</ul>"
        f"<img src='residuals_figure.png'></body></html>")
    return paths



def layout_seed_places(path: str | Path) -> list:
    """The fast path's fitted LED places (L, 3), m, camera frame, from its calibration's
    report.json: its chosen field's (``fast_path.taps.places.places_m``), else those of
    the field that fitted them (``fast_path.taps.by_field.<field>.places``: a field
    chosen for its constants, the geodesic one, keeps the unit's places); ValueError
    naming the file otherwise."""
    path = Path(path)
    try:
        taps = json.loads(path.read_text())["fast_path"]["taps"]
        fitted = [taps] + [v for _, v in sorted((taps.get("by_field") or {}).items()) if "places" in v]
        places = next((t["places"]["places_m"] for t in fitted if "places" in t), None)
        if places is None:
            raise KeyError("places")
    except FileNotFoundError:
        raise FileNotFoundError(f"--layout-seed {path}: no such file (a fast-path calibration's report.json)") from None
    except (json.JSONDecodeError, KeyError, TypeError, AttributeError) as exc:
        raise ValueError(f"--layout-seed {path}: not a fast-path calibration's report.json with fitted LED places "
                         f"(fast_path.taps.places.places_m, or a field's in fast_path.taps.by_field): {exc!r}") from None
    return places


def _fit_layout(image, spec, mesh, camera, grid: dict, layout_seed, seed: int, camera_known: bool, leak: bool,
                progress: bool, taps=None, spectral_gains: bool = False, webcam: bool = False):
    """The layout's fit (``pbr_tactile.layout_fit``) at the grid's first point, on the
    no-contact image and the fitted half of ``taps``."""
    from .basis import BASIS_EFFECTS
    from .effects import Effects
    from .layout_fit import fit_layout

    point = {name: float(values[0]) for name, values in grid.items()}
    effects = dataclasses.replace(Effects().with_settings([f"{k}={v}" for k, v in BASIS_EFFECTS.items()]), **point)
    places = None if layout_seed is None else layout_seed_places(layout_seed)
    say = (lambda text: print(f"layout: {text}", flush=True)) if progress else None
    return fit_layout(image, spec, mesh, camera, effects, fast_places_m=places, taps=taps, seed=seed,
                      known_alignment=camera_known, leak=leak, progress=say, spectral_gains=spectral_gains,
                      webcam=webcam)


def calibrate_capture(real: str | Path | None, out: str | Path, fast_path_fit: Callable, *,
                      background_only: str | Path | None = None, spec: str | Path | None = None,
                      taps: int | None = None, fast_taps: int | None = None, grid: dict | None = None,
                      bootstrap: int = BOOTSTRAP, camera_known: bool = False, fast_only: bool = False,
                      no_leak: bool = False, width: int = WIDTH, photons: int = PHOTONS, spp: int = SPP,
                      seed: int = 0, progress: bool = True, fit_layout: bool = False,
                      layout_seed: str | Path | None = None, spectral_gains: bool = False,
                      webcam: bool = False) -> dict:
    """Calibrate to the capture dataset ``real`` (or the no-contact image
    ``background_only``) and write the outputs in ``out`` (``write_outputs``); returns
    ``{"paths": {name: Path}, "report": dict}`` (the report's ``converged``: whether a
    profile was written).

    Parameters
    ----------
    fast_path_fit : the fast path's fit of its LED constants to taps (its renderer
        plugin's ``calibrate``, ``scenes.renderers.Calibrates``).
    spec : the sensor's TOML (default: ``real``'s own, as its dataset.json records it; the
        default spec for ``background_only``).
    taps : taps of ``real`` used, spread over it (default and at most ``MAX_TAPS``; 0: its
        no-contact image only).
    fast_taps : taps the fast path's LED constants are fitted on (0: all; None: ``taps``').
    grid : effects searched and their values, {name: values} (default ``calibrate.GRID``).
    fast_only : calibrate the fast path alone (needs taps), no render of the reference.
    no_leak : the leak into the glass core fixed at 0.
    width : film width of the basis renders, pixels (height: 3/4 of it).
    photons, spp : photons per LED and camera samples per pixel per pass of a basis render.
    fit_layout : fit the LEDs' layout (where their light enters, their aim and beam:
        ``pbr_tactile.layout_fit``) to the no-contact image first, at the grid's first
        point, and calibrate the reference laid out so (the profile's
        ``reference.layout``); the fast path's fit keeps the spec's LEDs.
    spectral_gains : each LED's light reaches the channels through its spectrum under the
        camera's filters (one power per LED, one white balance per channel), not a free
        gain per LED and channel (``pbr_tactile.image_model``).
    webcam : the camera's response exponent and black level held to a webcam's
        (``pbr_tactile.image_model.WEBCAM_GAMMA``, ``WEBCAM_BLACK``).
    layout_seed : a fast-path calibration's report.json (``--fast-only``), whose fitted
        LED places are one of the layout search's starts.
    """
    from tqdm import tqdm

    from scenes.camera import Camera
    from scenes.captures import MAX_TAPS, load_real_taps
    from scenes.dataset import read_samples
    from scenes.geometry import membrane_mesh
    from scenes.images import read_rgb
    from scenes.spec_read import load_spec

    from .calibrate import GRID, calibrate_background, calibrate_fast

    if layout_seed is not None and not fit_layout:
        raise ValueError("--layout-seed seeds the layout's fit: give --fit-layout too")
    real = None if real is None else str(real)
    path, what = real_background(real, None if background_only is None else str(background_only))
    spec = load_spec(spec) if spec is not None or real is None else capture_spec(real)
    camera = Camera.from_spec(spec)
    image = read_rgb(path)
    grid = GRID if not grid else grid
    count = MAX_TAPS if taps is None else taps
    if not 0 <= count <= MAX_TAPS:
        raise ValueError(f"--taps must be in [0, {MAX_TAPS}], got {count}")
    real_taps = fitted_fast = None
    if real is not None and count:
        real_taps = load_real_taps(real, spec, camera, count)
        what += f" and {len(real_taps.ids)} of its taps"
        if fast_taps is not None:
            fitted_fast = load_real_taps(real, spec, camera, fast_taps or len(read_samples(real)))
            what += f" ({len(fitted_fast.ids)} for the fast path)"
    elif taps or fast_taps is not None:
        raise ValueError("--taps and --fast-taps need REAL, a capture dataset (--background-only has no taps)")
    bar = tqdm(desc="calibrating", unit="grid point", disable=not progress)

    def advance(done, total):
        bar.total = total
        bar.update(done - bar.n)

    t0 = time.perf_counter()
    if fast_only:
        if real_taps is None:
            raise ValueError("--fast-only fits the fast path's LED constants to taps: give REAL, a capture dataset")
        cal = calibrate_fast(image, spec, membrane_mesh(spec), camera, fitted_fast or real_taps, fast_path_fit,
                             seed=seed)
        what += ", the fast path alone"
    else:
        mesh = membrane_mesh(spec)
        laid_out, fast_fit, layout = spec, fast_path_fit, None
        held = None
        if fit_layout:
            from .layout_fit import presses_pin

            # every press of the capture's fitted half may pin the layout (it renders a few of
            # them, the furthest apart), not only the taps the calibration renders
            every = None if real is None else load_real_taps(real, spec, camera, len(read_samples(real)))
            pinned, why = presses_pin(every, camera)
            if pinned:
                layout = _fit_layout(image, spec, mesh, camera, grid, layout_seed, seed, camera_known, not no_leak,
                                     progress, every, spectral_gains, webcam)
                laid_out = layout.spec
                what += ", its LEDs' layout fitted"
                fitted_material = layout.report.get("material", {}).get("fitted", {})
                if fitted_material:
                    # the reference is calibrated in the paint and clarity fitted with the layout
                    grid = {**grid, **{name: (value,) for name, value in fitted_material.items()}}
                    what += " with its paint and clarity"

                def fast_fit(_spec, *rest):  # the fast path's own LEDs are the spec's
                    return fast_path_fit(spec, *rest)
            else:
                held = {"fitted": False, "why": why, "held": "every LED's entry, place, aim and beam at the spec's"}
                print(f"calibrate: the LEDs' layout is not fitted, {why}; held at the spec's", flush=True)
        cal = calibrate_background(image, laid_out, mesh, camera, film=(width, width * 3 // 4),
                                   grid=grid, photons=photons, spp=spp, seed=seed, bootstrap=bootstrap,
                                   leak=not no_leak, progress=advance, taps=real_taps, fast_path_fit=fast_fit,
                                   fast_taps=fitted_fast, camera_known=camera_known, spectral_gains=spectral_gains,
                                   webcam=webcam)
        if layout is not None:
            from scenes.layout import layout_to_dicts

            cal.profile = dataclasses.replace(cal.profile, reference={**cal.profile.reference,
                                                                      "layout": layout_to_dicts(layout.layout)})
            cal.report["layout"] = {"fitted": True, **layout.report}
        elif held is not None:
            cal.report["layout"] = held
    bar.close()
    cal.report["seconds"] = time.perf_counter() - t0
    return {"paths": write_outputs(cal, Path(out), what), "report": cal.report}
