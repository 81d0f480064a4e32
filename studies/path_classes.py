"""Where the reference's contact signal comes from: the light on the paint split by the
class of the path that brought it.

The photon pass (``pbr_tactile.photons.deposits(classes=True)``) tags each photon with
the events of its walk (``PATH_EVENTS``: through a glass surface, reflected at one,
scattered in the elastomer, reflected by the paint) and counts each deposit on the
paint in the class of the events before it; class 0 is light straight from an LED. The
camera sees the paint's radiance (rho / pi) E, so a class's share of the irradiance E
on the paint is its share of the paint's image.

For each sensor (the default GelTip, the flat GelSight) and each contact (a sphere of
SPHERE_RADIUS_M pressed CONTACT_DEPTH_M: on the GelTip at its tip, on its dome and on its
body; on the GelSight at the centre), at the reference's default physics
(``pbr_tactile.effects.Effects()``):

- ``no_contact``: each class's share of the no-contact irradiance, over the whole paint
  and over the contact's region (the undeformed paint within REGION_SCALE times the
  contact's Hertzian radius sqrt(2 R d - d^2) of the pressed point);
- over that region, each class's change of the irradiance: net (signed) and absolute,
  over the region's no-contact light and over the class's own (``class_shares``); and
  the contrast the paint shows, the mean |dE| over the mean E0, the sources summed;
- ``source_contrast``: the same contrast of each source's own light (``source_contrasts``),
  and each class's share of a source's region light and its relative change, averaged
  over the sources. This is what the camera sees where each LED has its own colour (the
  GelTip's and the GelSight's do): a contact's strength is the mean over the channels of
  each one's change (``scenes.image_stats.contact_strength``), and LEDs on opposite sides
  brighten opposite flanks of a dent, so their summed change hides most of it (on the
  GelSight's centre at the defaults, 0.03 summed against 0.29 per source).

The contact and the no-contact paint are traced with the same seeds and one weight
window (the undeformed membrane's pilot, as ``render_photons`` sets it), so the two
share their random walks where the dent does not change them; each figure is the mean
over ``seeds`` independent runs with its standard error. The irradiance is the renderer's
density estimate (``irradiance``, the kernel of ``render.KERNEL_RADIUS_M``). Photon noise
adds to an absolute change, so the absolute figures (``of_the_mean``) are taken on the
runs' mean maps, beside ``noise_of_the_mean``: the same figures of half the difference
between the two halves' mean changes, which carries the mean's noise and none of its
signal.
Light the camera sees scattered in the elastomer before it reaches the paint is not on
the paint and not counted here.

    python -m studies.path_classes --out classes [--sensors geltip,gelsight --photons 262144 --seeds 4
        --set coating_albedo=0.5 ...]

``--set`` measures the same with another physical setting (``Effects.with_settings``), so
that a candidate physics is judged by where its contrast comes from.
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
import warnings
from pathlib import Path

import numpy as np

from scenes.press_sets import DEFAULTS as IMPORT_DEFAULTS, TAXIM

#: The indenter: a sphere of this radius (m), pressed this deep (m) along the normal.
SPHERE_RADIUS_M = 2e-3
CONTACT_DEPTH_M = 1e-3
#: The contact's region: the paint within this many Hertzian radii of the pressed point.
REGION_SCALE = 1.5
#: Photons per LED per run, and independent runs.
PHOTONS = 1 << 18
SEEDS = 4
#: The sensors measured: name -> spec path (None: the default GelTip; the flat GelSight is
#: the spec of the public presses' sensor, wherever the command runs from).
SENSORS = {"geltip": None, "gelsight": str(IMPORT_DEFAULTS[TAXIM]["spec"])}
#: The GelTip's contacts: name -> height along its axis above the glass junction, as a
#: share of the membrane's radius (the tip is the image centre).
GELTIP_PLACES = {"tip": None, "dome": 0.5, "body": -1.0}


def contact_pixels(spec, camera, ref: np.ndarray) -> dict[str, tuple[float, float]]:
    """The contacts' pixels (u, v): the flat pad's centre, or on the GelTip its tip (the
    image centre) and, along the image row through the centre, the seen points nearest
    the dome's and the body's heights (GELTIP_PLACES)."""
    from scenes.camera import back_project

    from scenes.shapes import family

    centre = (float(camera.cx), float(camera.cy))
    tube = family(spec.membrane.shape).tube(spec.membrane)
    if tube is None:
        return {"centre": centre}
    points = back_project(ref, camera)
    row = int(round(camera.cy))
    cols = np.arange(int(round(camera.cx)), camera.width)
    z = points[row, cols, 2]
    seen = np.isfinite(z) & (ref[row, cols] > 0)
    junction = tube.junction_z
    out = {}
    for name, share in GELTIP_PLACES.items():
        if share is None:
            out[name] = centre
            continue
        target = junction + share * tube.radius
        k = int(np.argmin(np.where(seen, np.abs(z - target), np.inf)))
        out[name] = (float(cols[k]), float(row))
    return out


def class_shares(e_0: np.ndarray, e_c: np.ndarray, area: np.ndarray, region: np.ndarray) -> dict:
    """One run's figures (module doc) from the no-contact and the contact's per-class
    irradiance (K, V) (sources summed, the renderer's density estimate), the undeformed
    vertex areas (V,) and the region (V,) bool. Over the region, with <x> the
    area-weighted sum and E = sum_k E_k:

    - ``whole``, ``region``: <E0_k> / <E0>, over all the paint and over the region;
    - ``signed``: <dE_k> / <E0>, each class's net change (they sum to the region's);
    - ``absolute``: <|dE_k|> / <E0>, each class's contrast;
    - ``relative``: <|dE_k|> / <E0_k>, how strongly the contact changes the class's own
      light (which class carries the contrast, which dilutes it);
    - ``contrast``: <|dE|> / <E0>, what the paint shows (the classes' changes summed
      before the absolute value), and ``net``: <dE> / <E0>.
    """
    e_0, e_c = np.asarray(e_0, np.float64), np.asarray(e_c, np.float64)
    if e_0.shape != e_c.shape or e_0.ndim != 2 or e_0.shape[1] != len(area) or region.shape != area.shape:
        raise ValueError(f"e_0 and e_c must be (K, V) with V = {len(area)} vertex areas and region flags, got "
                         f"{e_0.shape}, {e_c.shape} and {region.shape}")
    a = area[region]
    d = (e_c - e_0)[:, region] * a
    base_k = (e_0[:, region] * a).sum(axis=1)
    base = base_k.sum()
    whole = (e_0 * area).sum(axis=1)
    return {"whole": whole / whole.sum(), "region": base_k / base, "signed": d.sum(axis=1) / base,
            "absolute": np.abs(d).sum(axis=1) / base,
            "relative": np.divide(np.abs(d).sum(axis=1), base_k, out=np.full(len(e_0), np.nan), where=base_k > 0),
            "contrast": float(np.abs(d.sum(axis=0)).sum() / base), "net": float(d.sum() / base)}


def source_contrasts(e_0: np.ndarray, e_c: np.ndarray, area: np.ndarray, region: np.ndarray) -> np.ndarray:
    """(S,) each source's contrast over the region, <|dE_s|> / <E0_s>, from the no-contact
    and the contact's irradiance per source (S, V) (its classes summed).

    The camera sees each LED in its own colour channel where, as on the GelTip and the
    GelSight, each LED has its own colour, and a contact's strength is the mean over the
    channels of each channel's change (``scenes.image_stats.contact_strength``). LEDs on
    opposite sides brighten opposite flanks of a dent, so the sources' summed change
    (``class_shares``' contrast) cancels much of what each channel shows."""
    e_0, e_c = np.asarray(e_0, np.float64), np.asarray(e_c, np.float64)
    if e_0.shape != e_c.shape or e_0.ndim != 2 or e_0.shape[1] != len(area) or region.shape != area.shape:
        raise ValueError(f"e_0 and e_c must be (S, V) with V = {len(area)} vertex areas and region flags, got "
                         f"{e_0.shape}, {e_c.shape} and {region.shape}")
    a = area[region]
    base = (e_0[:, region] * a).sum(axis=1)
    change = (np.abs(e_c - e_0)[:, region] * a).sum(axis=1)
    return np.divide(change, base, out=np.full(len(e_0), np.nan), where=base > 0)


def event_shares(per_class: np.ndarray) -> dict[str, float]:
    """(K,) a figure per path class -> per event (PATH_EVENTS), its sum over the classes
    whose paths have that event, and ``none`` (class 0, light straight from an LED)."""
    from pbr_tactile.photons import PATH_EVENTS

    per_class = np.asarray(per_class, np.float64)
    out = {"none": float(per_class[0])}
    for bit, event in enumerate(PATH_EVENTS):
        out[event] = float(sum(per_class[k] for k in range(len(per_class)) if k >> bit & 1))
    return out


def _summary(values) -> dict:
    """The runs' mean and standard error, per entry; NaN where a class has no light."""
    values = np.asarray(values, np.float64)
    n = len(values)
    with warnings.catch_warnings():  # a class no photon took is NaN in every run
        warnings.simplefilter("ignore", RuntimeWarning)
        se = np.nanstd(values, axis=0, ddof=1) / np.sqrt(n) if n > 1 else np.zeros(values.shape[1:])
        return {"mean": np.nanmean(values, axis=0).tolist(), "se": np.asarray(se).tolist()}


def measure(spec_path=None, photons: int = PHOTONS, seeds: int = SEEDS, places=None, variant: str | None = None,
            progress: bool = True, settings: list[str] = ()) -> dict:
    """The sensor's figures (module doc): {contact: {...}}, at the default physics or with
    ``settings`` (``Effects.with_settings``: NAME=VALUE, e.g. coating_albedo=0.5)."""
    import trimesh

    from pbr_tactile.effects import Effects
    from pbr_tactile.membrane import ElastomerBuilder
    from pbr_tactile.paint import Paint
    from pbr_tactile.density import coating_areas, coating_vertices, density_kernel, irradiance
    from pbr_tactile.photons import PATH_CLASSES, deposits, sources_from, weight_window
    from pbr_tactile.render import KERNEL_RADIUS_M, load
    from pbr_tactile.scene import geltip_scene, led_sources, write_meshes
    from scenes.camera import Camera, back_project, reference_depth
    from scenes.contact import press
    from scenes.geometry import membrane_mesh
    from scenes.spec_read import default_spec, load_spec

    if photons < 1 or seeds < 1:
        raise ValueError(f"photons and seeds must be >= 1, got {photons} and {seeds}")
    effects = Effects().with_settings(list(settings))
    spec = default_spec() if spec_path is None else load_spec(spec_path)
    camera = Camera.from_spec(spec)
    mesh = membrane_mesh(spec)
    ref, _ = reference_depth(mesh, camera)
    build = ElastomerBuilder(mesh, spec, camera)
    srcs = sources_from(led_sources(spec, effects))
    pixels = contact_pixels(spec, camera, ref)
    if places is not None:
        unknown = set(places) - set(pixels)
        if unknown:
            raise ValueError(f"{spec.name} has contacts {sorted(pixels)}, not {sorted(unknown)}")
        pixels = {k: v for k, v in pixels.items() if k in places}
    points = back_project(ref, camera)
    hertz = float(np.sqrt(2 * SPHERE_RADIUS_M * CONTACT_DEPTH_M - CONTACT_DEPTH_M ** 2))
    out = {}
    with tempfile.TemporaryDirectory(prefix="path-classes-") as folder:
        wall = spec.membrane.glass_wall

        def loaded(solid, name):
            scene = geltip_scene(write_meshes(solid, f"{folder}/{name}", wall), spec, camera, effects, 8, 6, spp=1)
            return load(scene, variant, keep=True)

        mi, flat = loaded(build(), "undeformed")
        if not mi.variant().startswith(("llvm_", "cuda_")):
            raise ValueError(f"the photon pass needs a vectorised (llvm_ or cuda_) variant, got {mi.variant()}")

        def trace(scene, count, seed, window=None):
            return deposits(mi, scene, srcs, effects.sigma_t, effects.albedo, Paint.from_effects(effects), count, seed,
                            window, classes=True)

        area_0 = coating_areas(flat)
        vertices_0 = coating_vertices(flat)
        # The weight window as render_photons sets it: a pilot of an eighth of the photons on
        # the undeformed paint, its density the kernel applied twice.
        kernel_0 = density_kernel(vertices_0, KERNEL_RADIUS_M)
        pilot_flux = trace(flat, max(1, photons // 8), 7919).sum(axis=1)
        window = weight_window(irradiance((kernel_0 @ pilot_flux.T).T, kernel_0 @ area_0, kernel_0), area_0, photons)

        def per_source(flux, area, kernel):  # (S, K, V) flux -> (S, K, V) irradiance
            S, K, V = flux.shape
            return irradiance(flux.reshape(S * K, V), area, kernel).reshape(S, K, V)

        # irradiance is linear in the flux: the sources' summed map (K, V) is their maps' sum
        no_contact_s = [per_source(trace(flat, photons, seed, window), area_0, kernel_0) for seed in range(seeds)]
        no_contact = [e.sum(axis=0) for e in no_contact_s]
        for name, pixel in pixels.items():
            t0 = time.perf_counter()
            depth = press(ref, camera, mesh, trimesh.primitives.Sphere(radius=SPHERE_RADIUS_M), pixel,
                          CONTACT_DEPTH_M)
            _, dented = loaded(build(depth, ref), name)
            vertices_c = coating_vertices(dented)
            if len(vertices_c) != len(vertices_0):
                raise RuntimeError("the dented paint's mesh is not the undeformed one displaced")
            kernel_c = density_kernel(vertices_c, KERNEL_RADIUS_M, like=(vertices_0, kernel_0))
            area_c = coating_areas(dented)
            at = points[int(round(pixel[1])), int(round(pixel[0]))]
            region = np.linalg.norm(vertices_0 - at, axis=1) <= REGION_SCALE * hertz
            contact_s = [per_source(trace(dented, photons, seed, window), area_c, kernel_c) for seed in range(seeds)]
            contact = [e.sum(axis=0) for e in contact_s]
            runs = [class_shares(e0, ec, area_0, region) for e0, ec in zip(no_contact, contact)]
            e0, change = np.mean(no_contact, axis=0), np.mean(contact, axis=0) - np.mean(no_contact, axis=0)
            pooled = class_shares(e0, e0 + change, area_0, region)
            figures = {k: _summary([r[k] for r in runs]) for k in ("whole", "region", "signed", "absolute",
                                                                     "relative", "contrast", "net")}
            entry = {"pixel": list(pixel), "point_m": at.tolist(), "region_vertices": int(region.sum()),
                     "region_radius_m": REGION_SCALE * hertz, **figures,
                     "of_the_mean": {k: np.asarray(pooled[k]).tolist() for k in ("absolute", "relative", "contrast")}}
            s0, sc = np.mean(no_contact_s, axis=0), np.mean(contact_s, axis=0)  # (S, K, V)
            by_source = source_contrasts(s0.sum(axis=1), sc.sum(axis=1), area_0, region)
            # each class of each source: its share of the source's region light and its own relative change
            per = [class_shares(s0[m], sc[m], area_0, region) for m in range(len(srcs))]
            share_sk, rel_sk = np.stack([f["region"] for f in per]), np.stack([f["relative"] for f in per])
            with warnings.catch_warnings():  # a class no source's photons took is NaN
                warnings.simplefilter("ignore", RuntimeWarning)
                relative = np.nanmean(np.where(share_sk > 0, rel_sk, np.nan), axis=0)
            entry["source_contrast"] = {"per_source": by_source.tolist(), "mean": float(np.nanmean(by_source)),
                                        "sources": [src.name for src in srcs],
                                        "class_share": share_sk.mean(axis=0).tolist(),
                                        "class_relative": relative.tolist()}
            if seeds > 1:
                half_s = [np.mean([contact_s[k] - no_contact_s[k] for k in range(h, seeds, 2)], axis=0).sum(axis=1)
                          for h in (0, 1)]
                floor_s = source_contrasts(s0.sum(axis=1), s0.sum(axis=1) + (half_s[0] - half_s[1]) / 2, area_0,
                                           region)
                entry["source_contrast"]["noise"] = float(np.nanmean(floor_s))
                # The mean change's photon noise, from the two halves of the runs: half their difference
                # has the noise of the whole mean and none of its signal.
                half = [np.mean([contact[k] - no_contact[k] for k in range(h, seeds, 2)], axis=0) for h in (0, 1)]
                noise = class_shares(e0, e0 + (half[0] - half[1]) / 2, area_0, region)
                entry["noise_of_the_mean"] = {k: np.asarray(noise[k]).tolist() for k in ("absolute", "contrast")}
            entry["events"] = {"region": event_shares(figures["region"]["mean"]),
                               "absolute": event_shares(entry["of_the_mean"]["absolute"])}
            if "noise_of_the_mean" in entry:
                entry["events"]["noise"] = event_shares(entry["noise_of_the_mean"]["absolute"])
            entry["seconds"] = time.perf_counter() - t0
            out[name] = entry
            if progress:
                floor = entry.get("noise_of_the_mean", {}).get("contrast", float("nan"))
                sc = entry["source_contrast"]
                print(f"{spec.name} {name}: contrast of the runs' mean {pooled['contrast']:.4f} (noise {floor:.4f}), "
                      f"per source {sc['mean']:.4f} (noise {sc.get('noise', float('nan')):.4f}), "
                      f"net {figures['net']['mean']:+.4f} ({time.perf_counter() - t0:.0f} s)", flush=True)
    return {"sensor": spec.name, "spec": spec_path, "photons": photons, "seeds": seeds, "settings": list(settings),
            "classes": PATH_CLASSES, "contacts": out}


def _label(k: int) -> str:
    from pbr_tactile.photons import path_class_events

    events = path_class_events(k)
    return " + ".join(events) if events else "straight from an LED"


def table(results: dict, top: int = 6) -> str:
    """table.md: per sensor and contact, the events' and the leading classes' shares of
    the region's no-contact light and of its contrast (mean +/- se over the runs)."""
    from pbr_tactile.photons import PATH_EVENTS

    lines = ["# Path classes of the light on the paint", ""]
    for sensor in results["sensors"].values():
        lines.append(f"## {sensor['sensor']} ({sensor['photons']} photons per LED, {sensor['seeds']} runs; physics: "
                     f"{', '.join(sensor.get('settings') or []) or 'the defaults'})")
        for name, c in sensor["contacts"].items():
            m, noise = c["of_the_mean"], c.get("noise_of_the_mean", {})
            sc = c["source_contrast"]
            lines += ["", f"### {name}: contrast per source {sc['mean']:.4f} (photon noise {sc.get('noise', np.nan):.4f}; "
                      f"{', '.join(f'{v:.4f}' for v in sc['per_source'])}), sources summed {m['contrast']:.4f} "
                      f"(noise {noise.get('contrast', np.nan):.4f}), net change {c['net']['mean']:+.4f} +/- "
                      f"{c['net']['se']:.4f}", "",
                      "| class (per source) | share of a source's region light | its relative change |", "|---|---|---|"]
            share, rel = np.asarray(sc["class_share"]), np.asarray(sc["class_relative"])
            for k in np.argsort(-share)[:top]:
                lines.append(f"| {_label(int(k))} | {share[k]:.3f} | {rel[k]:.4f} |")
            lines += ["", "Sources summed:", "",
                      "| paths with | share of the region's light | its contrast, <abs dE_k> / <E0> | noise |",
                      "|---|---|---|---|"]
            for event in ("none",) + PATH_EVENTS:
                label = "no event (straight from an LED)" if event == "none" else event
                lines.append(f"| {label} | {c['events']['region'][event]:.3f} | {c['events']['absolute'][event]:.4f} "
                             f"| {c['events'].get('noise', {}).get(event, np.nan):.4f} |")
            lines += ["", "| class | no-contact, whole paint | no-contact, region | net change | contrast | "
                      "relative change |", "|---|---|---|---|---|---|"]
            for k in np.argsort(-np.asarray(c["region"]["mean"]))[:top]:
                cell = [f"{c[f]['mean'][k]:{'+' if f == 'signed' else ''}.4f} +/- {c[f]['se'][k]:.4f}"
                        for f in ("whole", "region", "signed")]
                cell += [f"{m['absolute'][k]:.4f}", f"{m['relative'][k]:.4f}"]
                lines.append(f"| {_label(int(k))} | " + " | ".join(cell) + " |")
        lines.append("")
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m studies.path_classes", description=__doc__.splitlines()[0])
    p.add_argument("--out", required=True, metavar="DIR")
    p.add_argument("--sensors", default=",".join(SENSORS), help=f"some of {', '.join(SENSORS)}")
    p.add_argument("--photons", type=int, default=PHOTONS, help=f"photons per LED per run (default {PHOTONS})")
    p.add_argument("--seeds", type=int, default=SEEDS, help=f"independent runs (default {SEEDS})")
    p.add_argument("--set", action="append", default=[], metavar="EFFECT=VALUE",
                   help="a physical setting instead of its default (pbr_tactile.effects.Effects; repeatable)")
    p.add_argument("--spec", metavar="PATH", help="measure this sensor file instead of the one sensor of --sensors "
                   "(its contacts are that sensor's: a capsule's tip, dome and body, a pad's centre)")
    p.add_argument("--quiet", action="store_true")
    args = p.parse_args(argv)
    names = [s for s in args.sensors.split(",") if s]
    unknown = [s for s in names if s not in SENSORS]
    if unknown:
        p.error(f"--sensors must be some of {', '.join(SENSORS)}, got {', '.join(unknown)}")
    if args.spec is not None and len(names) != 1:
        p.error("--spec replaces the spec of one sensor: give --sensors with one name")
    specs = {s: args.spec if args.spec is not None else SENSORS[s] for s in names}
    from scenes.dataset import atomic_write_json
    from scenes.files import atomic_write_bytes

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    results = {"sensors": {s: measure(specs[s], args.photons, args.seeds, progress=not args.quiet,
                                      settings=args.set) for s in names}}
    atomic_write_json(out / "results.json", results)
    atomic_write_bytes(out / "table.md", table(results).encode())
    print(table(results))
    print(json.dumps({"wrote": [str(out / "results.json"), str(out / "table.md")]}))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
