"""The real dents, measured: each press's change in rings about its centre, and what it
says about how far the gel sinks outside the contact.

For each press of a capture (a dataset of presses with their no-contact frame, as
``tactile-sim import`` writes one), the change |I - I0| averaged over the channels is
averaged in rings BIN_PX wide about the press's centre (its annotated centre, else where
its depth map sinks deepest; ``scenes.image_stats.ring_profile``). Radii are in mm on the
membrane: a pixel at the centre spans the no-contact depth there over the focal length.
Of each profile:

- ``rim_mm``: where the change peaks, refined by a parabola (``scenes.imports.
  contact_edge_px``, the import's own rim), and ``contact_mm``, the radius of the disc the
  capture's depth map presses (its pressed area's equivalent radius): where the renderers
  put the contact's edge;
- ``floor``: the change far from the press (the median of the rings from FAR_SHARE times
  the rim out), the camera's drift and compression noise;
- ``half_mm`` and ``tenth_mm``: how far beyond the rim the change above the floor falls
  to a half and a tenth of the rim's;
- the tail, between the rim and where it reaches a tenth: least squares fits in log
  space of an exponential decay A exp(-(r - rim) / l), the layer model's far field
  (``scenes.elastic``), and of a power A (rim / r)^n (an elastic half-space's surface
  falls as 1 / r, its slope, which shades, as 1 / r^2): ``decay_mm`` l and ``power`` n,
  each with its rms misfit in log space, and ``better``, which fits better.

The summary gives each figure's median over the presses, and its mean with a bootstrap
interval (``scenes.image_stats.bootstrap_interval``), and the profile over the rim's
radius (``normalised``: the median and quartiles at each share of the real press's rim,
so that every set is read at the same places on the membrane). With ``sims``
(datasets of the same presses, rendered, as ``compare`` writes them: samples with the
capture's ids), each is measured alike at the capture's centres, beside it, on the
presses they all have.

    python -m studies.dent_profile CAPTURE --out DIR [--sim NAME=DATASET ...]
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

import numpy as np

from scenes.image_stats import bootstrap_interval, ring_profile

#: Ring width, px.
BIN_PX = 1.0
#: The floor is the change's median beyond this share of the rim.
FAR_SHARE = 2.5
#: The normalised profile's shares of the rim.
SHARES = np.round(np.arange(0.1, 2.51, 0.1), 2)
#: A ring counts with this many pixels in the frame.
MIN_PIXELS = 4
#: Figures summarised over the presses.
FIGURES = ("rim_mm", "contact_mm", "floor", "peak", "half_mm", "tenth_mm", "decay_mm", "power", "decay_rms",
           "power_rms")


def _beyond(radius: np.ndarray, above: np.ndarray, rim: float, level: float) -> float:
    """How far beyond ``rim`` the profile ``above`` (its rim's value 1) first falls to
    ``level``, linearly between rings; NaN if it does not within the profile."""
    out = np.flatnonzero((radius > rim) & np.isfinite(above))
    for a, b in zip(out[:-1], out[1:]):
        if above[b] <= level:
            if above[a] <= level:
                return float(radius[a] - rim) if radius[a] > rim else 0.0
            t = (above[a] - level) / (above[a] - above[b])
            return float(radius[a] + t * (radius[b] - radius[a]) - rim)
    return math.nan


def _tail_fits(radius: np.ndarray, above: np.ndarray, rim: float, end: float) -> dict:
    """The exponential's decay length and the power's exponent fitted to the tail (module
    doc): each a line with a free intercept in log space over the rings between ``rim``
    and ``rim + end`` (log y against r - rim, and against log(r / rim)), ``*_rms`` the rms
    of its residual in log space."""
    pick = (radius > rim) & (radius <= rim + end) & np.isfinite(above) & (above > 0)
    out = {"decay_mm": math.nan, "power": math.nan, "decay_rms": math.nan, "power_rms": math.nan, "better": None}
    if pick.sum() < 3:
        return out
    r, log_y = radius[pick], np.log(above[pick])
    for x, slope_name, rms_name, scale in ((r - rim, "decay_mm", "decay_rms", lambda b: -1.0 / b),
                                           (np.log(r / rim), "power", "power_rms", lambda b: -b)):
        slope, intercept = np.polyfit(x, log_y, 1)
        if slope < 0:
            out[slope_name] = float(scale(slope))
            out[rms_name] = float(np.sqrt(np.mean((intercept + slope * x - log_y) ** 2)))
    if np.isfinite(out["decay_rms"]) and np.isfinite(out["power_rms"]):
        out["better"] = "exponential" if out["decay_rms"] < out["power_rms"] else "power"
    return out


def press_profile(image: np.ndarray, no_contact: np.ndarray, centre_px, pixel_mm: float, rim_px: float,
                  contact_px: float | None = None, unit_mm: float | None = None) -> dict:
    """One press's figures (module doc): ``image`` and ``no_contact`` (H, W, 3) in [0, 1],
    its centre (u, v) px, a pixel's size mm, its rim ``rim_px`` (``contact_edge_px``), the
    depth map's contact radius px (None: not known) and the radius the ``normalised``
    profile is read in shares of, mm (None: its own rim). Returns the figures and the
    profile (``radius_mm``, ``change``)."""
    image, no_contact = np.asarray(image, np.float64), np.asarray(no_contact, np.float64)
    if image.shape != no_contact.shape or image.ndim != 3 or image.shape[-1] != 3:
        raise ValueError(f"a press's image {image.shape} and its no-contact frame {no_contact.shape} must both be "
                         "(H, W, 3)")
    if not (pixel_mm > 0 and rim_px > 0):
        raise ValueError(f"a pixel's size ({pixel_mm}) and the rim's radius ({rim_px} px) must be > 0")
    change = np.abs(image - no_contact).mean(axis=2)
    radius_px, profile, _ = ring_profile(change, centre_px, BIN_PX, min_pixels=MIN_PIXELS)
    radius = radius_px * pixel_mm
    rim = rim_px * pixel_mm
    far = np.isfinite(profile) & (radius_px >= FAR_SHARE * rim_px)
    floor = float(np.median(profile[far])) if far.any() else 0.0
    peak = float(np.interp(rim, radius[np.isfinite(profile)], profile[np.isfinite(profile)]))
    above = (profile - floor) / max(peak - floor, 1e-12)
    tenth = _beyond(radius, above, rim, 0.1)
    out = {"rim_mm": rim, "contact_mm": math.nan if contact_px is None else contact_px * pixel_mm,
           "floor": floor, "peak": peak, "half_mm": _beyond(radius, above, rim, 0.5), "tenth_mm": tenth}
    out.update(_tail_fits(radius, above, rim, tenth if np.isfinite(tenth) else (FAR_SHARE - 1) * rim))
    out["normalised"] = np.interp(SHARES * (rim if unit_mm is None else unit_mm), radius[np.isfinite(profile)], above[np.isfinite(profile)],
                                  right=np.nan).tolist()
    out["radius_mm"], out["change"] = radius.tolist(), profile.tolist()
    return out


def capture_presses(folder: str | Path):
    """(spec, camera, RealTaps of every press, ball radius m) of a capture dataset."""
    from pbr_tactile.calibrate_capture import capture_spec
    from scenes.camera import Camera
    from scenes.captures import load_real_taps
    from scenes.dataset import read_meta, read_samples

    spec = capture_spec(str(folder))
    camera = Camera.from_spec(spec)
    if not camera.is_pinhole:  # a pixel's size on the membrane is read as depth over focal length
        raise ValueError(f"CAPTURE {folder}: its camera is a {camera.projection} lens with distortion (k1 {camera.k1}, "
                         f"k2 {camera.k2}); the study reads a pixel's size as a pinhole's")
    meta = read_meta(folder)
    ball_mm = (meta.get("import") or {}).get("ball_mm")
    if ball_mm is None:
        raise ValueError(f"CAPTURE {folder}/dataset.json states no import.ball_mm: measure an imported capture "
                         "(tactile-sim import)")
    taps = load_real_taps(folder, spec, camera, len(read_samples(folder)))
    return spec, camera, taps, float(ball_mm) * 1e-3 / 2


def centres_px(taps) -> np.ndarray:
    """(T, 2) each press's centre: its annotated disc's, else its depth's deepest point."""
    from pbr_tactile.layout_fit import press_centres

    deepest = press_centres(taps)
    if taps.discs is None:
        return deepest
    discs = np.asarray(taps.discs, np.float64)
    return np.where(np.isfinite(discs[:, :2]), discs[:, :2], deepest)


def measure(folder: str | Path, sims: dict[str, str | Path] | None = None) -> dict:
    """The study (module doc) of the capture ``folder`` and, at its centres and rims'
    search, the datasets ``sims`` ({name: folder}) of the same presses."""
    from scenes.camera import CONTACT_EPS_M
    from scenes.dataset import load_sample, read_samples
    from scenes.images import read_rgb
    from scenes.imports import contact_edge_px

    spec, camera, taps, ball_m = capture_presses(folder)
    shape = (camera.height, camera.width)
    records = {name: {r["id"]: r for r in read_samples(sim)} for name, sim in (sims or {}).items()}
    keep = [k for k, i in enumerate(taps.ids) if all(i in rec for rec in records.values())]
    if not keep:
        raise ValueError(f"the datasets {', '.join(f'{n}={s}' for n, s in sims.items())} have none of the presses "
                         f"of CAPTURE {folder} (no sample ids in common)")
    taps = taps.subset(keep)
    centres = centres_px(taps)
    ref = np.asarray(taps.ref_depth, np.float64)
    sets = {"real": (taps.images, read_rgb(Path(folder) / "background.png", shape))}
    for name, sim in (sims or {}).items():
        images = np.stack([load_sample(sim, records[name][i], shape)[0] for i in taps.ids])
        sets[name] = (images, read_rgb(Path(sim) / "background.png", shape))
    # each press's pixel at its centre, mm, and the disc its depth map presses, px: the same for every set
    geometry = []
    for k in range(len(taps.ids)):
        u, v = (int(round(c)) for c in centres[k])
        v, u = min(max(v, 0), ref.shape[0] - 1), min(max(u, 0), ref.shape[1] - 1)
        pressed = (ref - np.asarray(taps.depths[k], np.float64)) > CONTACT_EPS_M
        geometry.append((ref[v, u] / camera.f * 1e3, math.sqrt(pressed.sum() / math.pi) if pressed.any() else None))
    out = {"capture": str(folder), "presses": len(taps.ids), "ball_radius_mm": ball_m * 1e3, "bin_px": BIN_PX,
           "shares_of_rim": SHARES.tolist(), "sets": {}}
    for name, (images, no_contact) in sets.items():
        rows = []
        real_rims = {r["id"]: r["rim_mm"] for r in out["sets"].get("real", {}).get("presses", []) if "rim_mm" in r}
        for k, tap_id in enumerate(taps.ids):
            pixel_mm, contact_px = geometry[k]
            ball_px = ball_m * 1e3 / pixel_mm
            try:
                rim_px = contact_edge_px(images[k], no_contact, centres[k], ball_px)
            except ValueError as exc:
                rows.append({"id": tap_id, "skipped": str(exc)})
                continue
            rows.append({"id": tap_id, **press_profile(images[k], no_contact, centres[k], pixel_mm, rim_px,
                                                       contact_px, real_rims.get(tap_id))})
        out["sets"][name] = {"presses": rows, "summary": summarise(rows)}
    return out


def summarise(rows: list[dict]) -> dict:
    """Each figure's median with a bootstrap interval over the presses that have it, the
    tail's better fit by count, and the normalised profile's median and quartiles."""
    measured = [r for r in rows if "skipped" not in r]
    out = {"measured": len(measured), "skipped": len(rows) - len(measured)}
    for name in FIGURES:
        values = np.array([r[name] for r in measured], np.float64)
        values = values[np.isfinite(values)]
        out[name] = ({"median": float(np.median(values)), "n": int(len(values)), **bootstrap_interval(values)}
                     if len(values) else {"median": None, "n": 0})
    out["better"] = {k: sum(r["better"] == k for r in measured) for k in ("exponential", "power")}
    table = np.array([r["normalised"] for r in measured], np.float64) if measured else np.empty((0, len(SHARES)))
    with np.errstate(all="ignore"):
        out["normalised"] = {q: [None if not np.isfinite(x) else float(x)
                                 for x in (np.nanpercentile(table, p, axis=0) if len(table) else
                                           np.full(len(SHARES), np.nan))]
                             for q, p in (("p25", 25), ("median", 50), ("p75", 75))}
    return out


def figure(result: dict, path: Path) -> None:
    """The normalised profiles' medians and quartiles, one line per set."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    shares = np.asarray(result["shares_of_rim"])
    fig, ax = plt.subplots(figsize=(6.0, 3.6), dpi=120)
    for name, data in result["sets"].items():
        n = data["summary"]["normalised"]
        med = np.array([np.nan if x is None else x for x in n["median"]], np.float64)
        lo = np.array([np.nan if x is None else x for x in n["p25"]], np.float64)
        hi = np.array([np.nan if x is None else x for x in n["p75"]], np.float64)
        (line,) = ax.plot(shares, med, label=f"{name} ({data['summary']['measured']} presses)")
        ax.fill_between(shares, lo, hi, color=line.get_color(), alpha=0.2)
    ax.axvline(1.0, color="0.5", lw=0.8, ls=":")
    ax.axhline(0.0, color="0.5", lw=0.8)
    ax.set_xlabel("radius / the real press's rim (where its change peaks)")
    ax.set_ylabel("change above the floor / the rim's")
    ax.set_title("the dents' profiles: median and quartiles over the presses")
    ax.legend(frameon=False, fontsize=8)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m studies.dent_profile", description=__doc__.splitlines()[0])
    p.add_argument("capture", metavar="CAPTURE", help="a capture dataset of presses (tactile-sim import)")
    p.add_argument("--out", required=True, metavar="DIR")
    p.add_argument("--sim", action="append", default=[], metavar="NAME=DATASET",
                   help="a dataset of the same presses, rendered, measured beside the capture")
    args = p.parse_args(argv)
    sims = {}
    for item in args.sim:
        name, sep, folder = item.partition("=")
        if not sep or not name or not folder:
            p.error(f"--sim takes NAME=DATASET, got {item!r}")
        sims[name] = folder
    result = measure(args.capture, sims)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "dent_profile.json").write_text(json.dumps(result, indent=1))
    figure(result, out / "dent_profile.png")
    for name, data in result["sets"].items():
        s = data["summary"]
        fmt = lambda k: "n/a" if s[k]["median"] is None else f"{s[k]['median']:.3g}"  # noqa: E731
        print(f"{name}: {s['measured']} presses; rim {fmt('rim_mm')} mm, contact {fmt('contact_mm')} mm; half "
              f"{fmt('half_mm')} mm and a tenth {fmt('tenth_mm')} mm beyond the rim; tail: decay {fmt('decay_mm')} mm "
              f"(rms {fmt('decay_rms')}), power {fmt('power')} (rms {fmt('power_rms')}); better: {s['better']}")
    print(f"wrote {out / 'dent_profile.json'} and {out / 'dent_profile.png'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
