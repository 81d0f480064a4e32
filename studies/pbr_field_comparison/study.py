"""Which light field brings the fast Phong path closest to physically guided light?

For each contact (eight base-protocol taps, one per paper indenter, captured on the MuJoCo
rig at the protocol's 2 mm; on the GelTip, four analytic indenters pressed as in
``tactile-sim demo`` and the six published depth maps ``sim_depth/0..5.npy`` where they
stay out of the glass; on any other membrane, taps drawn per class of region instead,
see below), at its real depth, this study renders the fast path
(``phong_reference``) with each baked light field (linear, plane, geodesic, transport)
and compares it with the physically based reference (``pbr_tactile.render.reference``,
photon estimator). The metrics are MAE, SSIM and PSNR (``skimage.metrics``), with
bootstrap 95 % confidence intervals over contacts. The study names the field with the
lowest mean contact-change MAE. It gives a paired bootstrap interval on each other
field's difference from that field, and one on that field's difference from predicting
no change.

Sensors of any shape, and where each field fails
------------------------------------------------
The paper's claim is that fields which follow the membrane (plane, geodesic, transport)
model guided light on a curved membrane better than straight lines (linear). A new shape
tests it where the membrane bends both ways. ``--spec`` takes any sensor; on a membrane
other than a capsule, the contacts are the eight base taps plus ``surface_taps``: the
extended protocol's contact points, classed by the membrane's principal curvatures there
(``scenes.curvature``: convex, cylindrical, flat, saddle, trough, concave), up to
SURFACE_PER_CLASS per class, spread over each class by farthest-point sampling, each
pressed by the rig along the local normal. Every contact records the class of the point
it presses. Two tables then say where each field fails:

* **by pixel** (``region_errors``): every reference pixel near a contact sees a point of
  the undeformed membrane of some class (``pixel_regions``). Per field and class, the
  calibrated change's |error| summed over those pixels, divided by the |reference
  change| there, which is the error of predicting no change. Below 1 the field tracks
  the contact on that kind of surface; at or above 1 it does no better than no change.
  The interval resamples contacts. ``failures`` lists, per field, the classes whose whole
  interval lies at or above 1 (fails), below 1 (tracks), or straddles it (unclear).
* **by contact** (``contact_region_table``): the change MAE over the contacts that press
  on each class, beside the no-change baseline's, with the paired interval of their
  difference.

How the two renderers are made comparable
-----------------------------------------
The fast path gives display values in [0, 1]: the Phong sum plus an ambient background,
clipped. The reference gives linear radiance through the camera's spectral response, with
Monte Carlo noise. Here is what the study does so that the two can be compared.

* **Geometry.** Both renderers see the same deformed membrane: our generated mesh, with
  D_ref = ``scenes.camera.reference_depth``, dented by the elastic layer model
  (``scenes.elastic.MembraneLayer``). The reference builds its elastomer solid from it;
  the fast path renders the depth map of the same deformed surface (``Renderer(...,
  layer=...)``), not the published smoothing. Each published map is moved onto our
  membrane as D = D_ref − (bkg − D_published); its indentation is measured against the
  authors' ``bkg.npy``, which differs from our D_ref by at most 0.16 mm. A rig capture is
  moved onto D_ref the same way, by its indentation against the rig's own no-contact
  capture (``rig_contacts``).
* **Real depth.** Every contact is rendered at its own depth. The published spheres reach
  7.9–12.4 mm along the camera ray, through the 2.5 mm membrane and into the glass; the
  layer model refuses them (as ``scenes.protocol_checks.validate`` refuses a tap deeper than the
  membrane), and the JSON lists them under ``skipped`` with the reason.
* **Resolution.** The fast path renders the full 640x480 camera, so its elastic smoothing
  and Sobel normals work at their native pixel scale. Its image is then area-averaged
  down to the reference's film (``skimage.transform.downscale_local_mean``). That is what
  the film's box reconstruction filter does, so the film must divide 640x480 by an
  integer factor.
* **Mask.** Both images are set to zero outside the camera's image circle, and all
  statistics are taken inside it (``Camera.scaled(W, H).mask``).
* **Background.** The fast path renders with no background (``make_background("none")``).
  Only the LED terms are compared. A background is a per-pixel constant, and the
  calibration below would partly absorb it.
* **Reference scale.** Every reference frame is divided by the 99.5th percentile of the
  no-contact reference inside the mask (all channels). Full frames then have data_range 1
  for PSNR and SSIM, and MAE is a fraction of that level.
* **Reliable pixels.** The photon estimator leaves rare single-pass spikes. At 160x120
  with 2^18 photons, about 1 % of the pixels in the circle reach up to 35 times the
  p99.5 level, and they carry half of the full frame's sum of squares. Any pixel whose
  standard error, in any frame, exceeds ``MAX_STANDARD_ERROR`` (0.5) times the median of
  the no-contact frame is left out of the fits, the metrics and the percentile, for
  every field alike. The JSON reports the share left out as ``unreliable_share``.
* **Calibration.** A gain (at least 0) and an offset per channel map each fast-path
  field's image onto the reference. The gain converts units, so it must never turn the
  fast path's brightening into a darkening: a field whose contact signal anticorrelates
  with the reference gets gain 0, which predicts no change. The gain is **not** fitted
  on the no-contact frame. For the tangent fields (plane, geodesic, transport), L_m is
  perpendicular to N on the undeformed membrane, so max(0, L_m·N) = 0 and their
  no-contact image is nearly black (mean about 0.003, std about 0.002). A gain fitted to
  that frame fits noise and comes out at 25–160. The study reports that fit as
  ``no_contact_calibration``, as a diagnostic. Instead, contact k is calibrated
  leave-one-out:
  * the gain is the least-squares slope through the origin of the reference's contact
    changes against the field's, over every contact except k (``fit_gain``), so the
    contact signal sets it;
  * the offset then matches the no-contact frame.

  A joint affine fit on all the frames would not do. The no-contact image covers every
  pixel, and its structure differs from the reference's, so that structure would set
  the gain (for the tangent fields, to 0) instead of the contacts. Each field gets its
  best linear calibration, and the contact it is scored on never enters it.
* **Three kinds of metric.**
  * *full*: the calibrated fast frame against the reference frame.
  * *change*: (contact − no-contact) over the whole mask, which is what tactile learning
    uses. The offset cancels here.
  * *contact*: the same change, but only on the pixels within one pixel (the Sobel
    stencil) of where the deformed surface's depth changes. Farther out, the fast
    path's change is exactly zero for every field, so *change* dilutes the differences
    between fields by the contact's share of the mask, and *contact* does not. This kind
    also reports Pearson's r between the field's uncalibrated change and the
    reference's, which needs no calibration at all.

  For the change kinds, SSIM and PSNR use as data_range the peak-to-peak of the
  reference's own change inside the mask, so they measure agreement relative to the
  contact signal. MAE stays in the same units as for full frames. The field that wins is
  the one with the lowest mean *change* MAE. A paired bootstrap (resampling contacts,
  differences per contact) says whether it is separated from the others, and whether it
  beats the **no-change baseline**, which predicts zero change. A field that does not
  beat that baseline does not track the contact.
* **Reference noise.** The reference is an estimate. For full frames, ``noise_mae`` is the
  MAE that a perfect fast path would score from the noise alone: √(2/π) σ, averaged over
  the mask, with σ² the estimator's variance of the mean. Every frame is rendered with
  the same seed, and these common random numbers cancel much of the noise in change
  images, so for changes the noise is measured instead: the mean |reference change| far
  from the contact. That includes any real far-field change, such as a shadow cast along
  the membrane, which every field misses alike.
* **Known limits.** The fast path clips at 1. With the spec's Table 1 settings, the linear
  field saturates much of the blue channel, and no affine map undoes that. It is part of
  what is measured. The reference uses ``Effects()``, the full physical model with no
  sensor-side effects.

Reference renders cost tens of seconds to minutes each at 320x240. Each one is cached
in ``--out/reference_cache`` as a .npy file of (mean, variance), and written atomically.
The file is keyed by contact name, resolution and photon count, plus a hash of
everything else the frame depends on. That hash includes the source of
``pbr_tactile``, so a change to the estimator renders the frame again. ``--quick`` renders two analytic contacts at 64x48 with 2^14 photons in two
passes: enough to exercise every step in well under a minute, but too noisy to rank the
fields.

Run ``python -m studies.pbr_field_comparison --out DIR [--spec TOML --surface N --width W
--height H --photons N --quick]``. It writes ``pbr_field_comparison.json``, ``summary.md``, ``metrics.png`` and
``grid_<contact>.png``, and ``regions.png`` when some class of region is reached by two
contacts. The published contacts are used when ``$GELTIP_REFERENCE`` (or
``../shared/data/geltip_reference``) holds the data; without it, the run uses only the
analytic contacts and says so.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import time
import warnings
from pathlib import Path

import numpy as np
from tqdm import tqdm

from scenes.camera import Camera, reference_depth
from scenes.curvature import CLASSES, classify, principal_curvatures
from scenes.dataset import atomic_write_json
from scenes.geometry import membrane_mesh
from scenes.reference_data import REFERENCE_ENV, require_reference_dir
from scenes.shapes import family
from scenes.spec import SensorSpec
from scenes.spec_read import load_spec

from .calibration import fit_affine, leave_one_out_calibration
from .contacts import (ANALYTIC, BASE, NO_CONTACT, PUBLISHED, QUICK_CONTACTS, SURFACE_PER_CLASS, analytic_contacts,
                       base_taps, contact_points, published_contacts, refusal, rig_contacts, surface_taps)
from .figures import grid_figure, metrics_figure, region_figure
from .frames import CACHE_FOLDER, QUICK, Settings, check_settings, fast_frames, reference_frame
from .metrics import contact_metrics, far_from_contact, no_change_metrics, noise_floor, reliable_pixels
from .regions import contact_region_table, failures, pixel_regions, region_errors
from .report import markdown, print_report
from .summary import CONFIDENCE, N_RESAMPLES, bootstrap_mean, conclusion, summarise

#: The reference is normalised by this percentile of its no-contact frame inside the mask.
REFERENCE_PERCENTILE = 99.5

JSON_NAME = "pbr_field_comparison.json"


def run(out: Path, settings: Settings = Settings(), contacts: tuple[str, ...] | None = None,
        reference_dir: Path | None = None, spec: SensorSpec | None = None, surface: int | None = None) -> dict:
    """Render, compare and summarise; writes the JSON, Markdown and figures into ``out``.

    contacts : names from BASE, ANALYTIC and PUBLISHED (default: all base and analytic ones,
        plus the published ones when ``reference_dir`` holds the data and the sensor is
        the published capsule).
    spec : the sensor (default: the embedded GelTip); any shape (``scenes.body``).
    """
    t_start = time.perf_counter()
    spec = load_spec(None) if spec is None else spec
    published = family(spec.membrane.shape).PUBLISHED  # the published GelTip's contacts and data apply
    if not published:
        if contacts is not None and set(contacts) & set(PUBLISHED):
            raise ValueError(f"the published depth maps are the GelTip's; sensor {spec.name!r} is a "
                             f"{spec.membrane.shape!r}: drop {sorted(set(contacts) & set(PUBLISHED))}")
        reference_dir = None
    camera = Camera.from_spec(spec)
    check_settings(settings, camera)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    mesh = membrane_mesh(spec)
    if surface is None:
        surface = 0 if published else SURFACE_PER_CLASS
    taps = surface_taps(spec, mesh, surface, settings.seed) if surface else {}
    if contacts is None:
        contacts = ((BASE + tuple(ANALYTIC) + (PUBLISHED if reference_dir is not None else ()))
                    if published else BASE) + tuple(taps)
    known = list(BASE) + list(ANALYTIC) + list(PUBLISHED) + list(taps)
    unknown = set(contacts) - set(known)
    if unknown or len(set(contacts)) < 2:
        raise ValueError(f"contacts must be >= 2 distinct names from {known} (surface_* with surface >= 1), "
                         f"got {list(contacts)}")
    wanted_published = tuple(c for c in contacts if c in PUBLISHED)
    if wanted_published and reference_dir is None:
        raise ValueError(f"contacts {list(wanted_published)} need the published data (set ${REFERENCE_ENV})")
    ref_depth = reference_depth(mesh, camera)[0]
    raw = analytic_contacts(mesh, camera, ref_depth, tuple(c for c in contacts if c in ANALYTIC))
    if wanted_published:
        raw.update(published_contacts(reference_dir, ref_depth, wanted_published))
    taps = {**base_taps(spec, mesh, tuple(c for c in contacts if c in BASE)),
            **{n: t for n, t in taps.items() if n in contacts}}
    if taps:
        raw.update(rig_contacts(spec, mesh, taps, ref_depth))

    from pbr_tactile.membrane import shared_builder

    # The builder the reference renders with: the solids checked here are not built twice.
    build = shared_builder(mesh, spec, camera)
    depths, info, skipped = {}, {}, {}
    for name in tqdm(contacts, desc="contacts the reference builds", unit="contact"):
        why = refusal(raw[name], ref_depth, build)
        if why is not None:
            skipped[name] = why
            warnings.warn(f"{name}: the reference refuses it at its real depth ({why}); dropped", stacklevel=2)
            continue
        depths[name] = raw[name]
        source = ("published" if name in PUBLISHED else "base protocol" if name in BASE
                  else "analytic" if name in ANALYTIC else "surface")
        info[name] = {"source": source, "max_indentation_m": float((ref_depth - depths[name]).max()),
                      "max_displacement_m": float(build.layer.deformation(depths[name], ref_depth).displacement.max())}
    points = contact_points(depths, ref_depth, camera, taps)
    k = principal_curvatures(mesh, np.array([points[n] for n in depths])) if depths else np.zeros((0, 2))
    for n, kn, cls in zip(depths, k, classify(k)):
        info[n].update(point_m=points[n].tolist(), curvatures_per_m=kn.tolist(), region=str(cls))
    names = list(depths)
    if len(names) < 2:
        raise ValueError(f"fewer than 2 contacts left to compare ({names}); dropped: {skipped}")

    shape = (settings.height, settings.width)
    mask = camera.scaled(settings.width, settings.height).mask
    means, variances, cached = [], [], {}
    t_ref = time.perf_counter()
    with tqdm([NO_CONTACT] + names, desc="reference renders", unit="contact") as bar:
        for name in bar:
            bar.set_postfix_str(name)

            def progress(done, total, name=name):
                bar.set_postfix_str(f"{name}: pass {done}/{total}")

            mean, var, hit = reference_frame(name, depths.get(name), ref_depth, mesh, spec, camera, settings,
                                             out / CACHE_FOLDER, progress)
            means.append(mean)
            variances.append(var)
            cached[name] = hit
    seconds_reference = time.perf_counter() - t_ref
    mean = np.stack(means)
    variance = np.stack(variances)
    region = mask & reliable_pixels(mean, variance, mask)
    scale = float(np.percentile(mean[0][region], REFERENCE_PERCENTILE))
    if not scale > 0:
        raise ValueError(f"the no-contact reference is black inside the mask (p{REFERENCE_PERCENTILE} = {scale})")
    ref = np.where(mask[..., None], mean / scale, 0.0)

    # Pixels near each contact: within the Sobel pixel of where the deformed surface's depth
    # changes; farther out, the fast path's change is exactly zero.
    layer = build.layer
    far = np.stack([far_from_contact(layer.depth(depths[n], ref_depth), ref_depth, shape, 1) for n in names])
    near = mask & ~far
    far &= region

    fast = fast_frames(spec, camera, mesh, ref_depth, [ref_depth] + [depths[n] for n in names], shape, layer)
    per_contact, calibration, no_contact_fit, calibrated = {}, {}, {}, {}
    tiled = lambda v: np.tile(v, (len(names), 1))
    for method, frames in fast.items():
        frames = np.where(mask[..., None], frames, 0.0)
        gains, offsets = leave_one_out_calibration(frames, ref, region)
        per_contact[method] = contact_metrics(frames, ref, gains, offsets, mask, region, near)
        calibration[method] = {"gain": gains.tolist(), "offset": offsets.tolist()}
        g0, o0 = fit_affine(frames[:1], ref[:1], region)
        briefed = contact_metrics(frames, ref, tiled(g0), tiled(o0), mask, region, near)
        no_contact_fit[method] = {"gain": g0.tolist(), "offset": o0.tolist(),
                                  "fast_std_no_contact": frames[0][region].std(axis=0).tolist(),
                                  "change_mae_mean": float(np.mean([c["change"]["mae"] for c in briefed]))}
        calibrated[method] = (frames, gains, offsets)
    no_change = no_change_metrics(ref, mask, region, near)
    summary = summarise(per_contact, settings.seed, no_change)
    regions_px = pixel_regions(mesh, camera.scaled(settings.width, settings.height))
    scored = near & region[None]
    change_ref = ref[1:] - ref[:1]
    pixel_table = {
        method: region_errors(gains[:, None, None, :] * (frames[1:] - frames[:1]), change_ref, scored, regions_px,
                              settings.seed)
        for method, (frames, gains, _) in calibrated.items()
    }
    region_summary = {
        "pixels_in_circle": {c: int(((regions_px == c) & region).sum()) for c in CLASSES
                             if ((regions_px == c) & region).any()},
        "ratio": pixel_table,
        "by_contact": contact_region_table(per_contact, no_change, [info[n]["region"] for n in names],
                                           settings.seed),
    }
    contacts_k = range(1, len(names) + 1)
    noise = {
        "full": bootstrap_mean([noise_floor(variance[k], scale, region) for k in contacts_k], settings.seed),
        "change_far": bootstrap_mean([float(np.abs(ref[k] - ref[0])[far[k - 1]].mean()) if far[k - 1].any() else 0.0
                                      for k in contacts_k], settings.seed),
    }
    results = {
        "question": "which light field brings the fast Phong path closest to the physically based reference",
        "sensor": spec.name,
        "settings": dataclasses.asdict(settings),
        "confidence": CONFIDENCE,
        "n_resamples": N_RESAMPLES,
        "contact_names": names,  # the order of every per-contact "values" list
        "contacts": info,
        "skipped": skipped,
        "reference_scale": scale,
        "reference_percentile": REFERENCE_PERCENTILE,
        "unreliable_share": float(1.0 - region.sum() / mask.sum()),
        "reference_cached": cached,
        "noise_mae": noise,
        "pixel_regions": region_summary,
        "per_contact": {m: dict(zip(names, rows)) for m, rows in per_contact.items()},
        "calibration": calibration,
        "no_contact_calibration": no_contact_fit,
        **summary,
        "seconds_reference": seconds_reference,
        "seconds_total": time.perf_counter() - t_start,
    }
    results["failures"] = failures(results)
    results["conclusion"] = conclusion(results)
    atomic_write_json(out / JSON_NAME, results)
    (out / "summary.md").write_text(markdown(results))
    metrics_figure(out / "metrics.png", results)
    if any(results["pixel_regions"]["ratio"].values()):
        region_figure(out / "regions.png", results, regions_px)
    for k, name in enumerate(names, start=1):
        grid_figure(out / f"grid_{name}.png", name, ref[0], ref[k], calibrated, k, mask, per_contact)
    return results


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(prog="python -m studies.pbr_field_comparison",
                                     description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, required=True, help="results, figures and the reference cache go here")
    parser.add_argument("--quick", action="store_true",
                        help=f"{QUICK.width}x{QUICK.height}, {QUICK.photons} photons, {QUICK.passes} passes, "
                             f"contacts {', '.join(QUICK_CONTACTS)} (a smoke run; too noisy to rank)")
    parser.add_argument("--width", type=int, help=f"reference film width, px (default {Settings.width})")
    parser.add_argument("--height", type=int, help=f"reference film height, px (default {Settings.height})")
    parser.add_argument("--photons", type=int, help=f"photons per LED per pass (default {Settings.photons})")
    parser.add_argument("--passes", type=int, help=f"independent passes (default {Settings.passes})")
    parser.add_argument("--spp", type=int, help=f"camera samples per pixel in all (default {Settings.spp})")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--contacts", nargs="+", metavar="NAME",
                        help=f"any of {', '.join(list(BASE) + list(ANALYTIC) + list(PUBLISHED))} (default: all available)")
    parser.add_argument("--spec", type=Path, help="sensor spec TOML (default: the embedded GelTip); any shape")
    parser.add_argument("--surface", type=int, metavar="N",
                        help=f"taps drawn per class of region, named surface_* (default {SURFACE_PER_CLASS} on a "
                             "membrane other than a capsule, else 0); with --contacts, only those named are used")
    parser.add_argument("--reference", type=Path,
                        help=f"the published data (default ${REFERENCE_ENV} or ../shared/data/geltip_reference)")
    args = parser.parse_args(argv)
    base = QUICK if args.quick else Settings()
    given = {k: getattr(args, k) for k in ("width", "height", "photons", "passes", "spp") if getattr(args, k)}
    settings = dataclasses.replace(base, seed=args.seed, **given)
    try:
        reference_dir, missing = require_reference_dir(args.reference), None
    except FileNotFoundError as exc:
        reference_dir, missing = None, exc
    contacts = tuple(args.contacts) if args.contacts else (QUICK_CONTACTS if args.quick else None)
    if missing is not None and not args.quick:
        print(f"{missing}; analytic contacts only", file=sys.stderr)
    try:
        results = run(args.out, settings, contacts, reference_dir, load_spec(args.spec) if args.spec else None,
                      args.surface)
    except ValueError as exc:
        parser.error(str(exc))
    print_report(results)
    print(f"wrote {args.out / JSON_NAME}, summary.md and figures ({results['seconds_total']:.0f} s)")
    return results
