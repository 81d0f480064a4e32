"""How far the re-weighted photon pass reaches: its time, its agreement with re-traced
renders, and its effective sample size at the gap diagnosis' grid values.

The gap diagnosis' reference model re-renders each tap's per-source basis
(``pbr_tactile.basis.emitter_basis``) at every grid value of ``absorption_per_m``,
``scattering_per_m`` and ``coating_albedo`` (``studies.gap.physical.GRIDS``). Those change
only how much light survives a path, so one traced render can be re-weighted to all of
them (``pbr_tactile.reweight``). On the default GelTip, with the diagnosis' basis
settings (film 80x60, ``spp`` camera samples per pass, 2 passes, the core leak's sources,
``no_contact_runs`` no-contact runs), this measures:

- ``timing``: one basis of a contact traced alone, with the K grid variants re-weighted
  in the same call, and each variant traced on its own: on a first contact (``cold``: the
  sensor's no-contact runs are traced and cached too) and on a second one (``warm``:
  they are read). Wall and CPU seconds (the CPU is shared; its seconds are steadier).
  Of the variants traced alone, ``retraced_sample`` of them are timed and the rest
  extrapolated from their mean, as stated in the results.
- ``agreement``: each variant's re-weighted basis against one traced at the variant with
  another seed (``agreement_passes`` passes, no no-contact runs): per pixel and source
  z = difference over the root of the two variances of the mean, each variance map
  smoothed over SMOOTH_PX pixels (inside the image circle) so that it is read with many
  degrees of freedom; the mean z^2 (1 where both agree within their error), the share of
  |z| > 3, the ratio of the two images' totals per source, and the ratio of their
  variances (the re-weighted over the re-traced: how much noisier the re-weighting is)
  beside each variant's Kish ESS ratio (``pbr_tactile.reweight.kish_ratio``), from which
  ``MIN_ESS_RATIO`` is chosen.

    python -m studies.reweight --out reweight [--photons 65536 --runs 4 --passes 4]
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import tempfile
import time
from pathlib import Path

import numpy as np

# The basis' film and settings, as the diagnosis renders it (one home: ``source_basis``),
# and the candidates it re-weights.
from studies.gap.source_basis import BASIS_FILM as FILM
from studies.gap.source_basis import BASIS_NO_CONTACT_RUNS as NO_CONTACT_RUNS
from studies.gap.source_basis import BASIS_PASSES as PASSES
from studies.gap.source_basis import BASIS_SPP as SPP
from studies.gap.source_basis import LEAK_BASIS
from studies.gap.source_basis import REWEIGHTED as CANDIDATES

#: Pixels (u, v) of the camera where the two contacts are pressed (a 4 mm sphere, 1.5 mm).
CONTACTS = ((350, 220), (250, 200))
SPHERE_RADIUS_M = 4e-3
PRESS_M = 1.5e-3
#: Photons per source per pass of the measured renders (a quarter of the basis' own
#: ``BASIS_PHOTONS``, as the diagnosis' earlier measurements used).
PHOTONS = 1 << 16
#: Variants traced on their own and timed (the rest extrapolated from their mean).
RETRACED_SAMPLE = 2
#: Passes of the agreement's renders (the variance of a mean of 2 passes is read too
#: loosely for a z test).
AGREEMENT_PASSES = 4
#: Each variance map is smoothed over this many pixels a side before z is formed.
SMOOTH_PX = 5


def grid_variants(spec, effects) -> tuple[np.ndarray, list[str]]:
    """(K, 3) the diagnosis' grid values of CANDIDATES, each with the others at ``effects``,
    the identity left out; and each row's name=value."""
    from pbr_tactile.reweight import PARAMETERS
    from studies.gap.physical import physical_catalogue

    _, _, grids = physical_catalogue(spec, effects)
    base = np.array([getattr(effects, p) for p in PARAMETERS], np.float64)
    rows, names = [], []
    for name in CANDIDATES:
        for value in grids[name]["values"]:
            if value == getattr(effects, name):
                continue
            row = base.copy()
            row[PARAMETERS.index(name)] = value
            rows.append(row)
            names.append(f"{name}={value:g}")
    return np.array(rows), names


def _timed(call):
    wall, cpu = time.perf_counter(), time.process_time()
    out = call()
    return out, {"wall_s": round(time.perf_counter() - wall, 2), "cpu_s": round(time.process_time() - cpu, 2)}


def timing(spec, mesh, camera, effects, contacts, ref, build, variants, photons, no_contact_runs, sample,
           progress=print) -> dict:
    """Seconds of the basis of each contact: traced alone, with the variants, each variant
    traced alone (``sample`` of them; the rest extrapolated), in a fresh cache."""
    from pbr_tactile.basis import emitter_basis

    out = {}
    kw = dict(photons=photons, spp=SPP, passes=PASSES, seed=1, solids=build, no_contact_runs=no_contact_runs)
    for label, depth in zip(("cold", "warm"), contacts):
        contact = {"depth": depth, "ref_depth": ref}
        row = {}
        _, row["traced"] = _timed(lambda: emitter_basis(spec, mesh, camera, effects, FILM, **kw, **contact))
        progress(f"{label}: traced {row['traced']}")
        _, row["with_variants"] = _timed(lambda: emitter_basis(spec, mesh, camera, effects, FILM, perturb=variants,
                                                               **kw, **contact))
        progress(f"{label}: with {len(variants)} variants {row['with_variants']}")
        each = []
        for sa, ss, rho in variants[:sample]:
            e = dataclasses.replace(effects, absorption_per_m=float(sa), scattering_per_m=float(ss),
                                    coating_albedo=float(rho))
            _, seconds = _timed(lambda: emitter_basis(spec, mesh, camera, e, FILM, **kw, **contact))
            each.append(seconds)
            progress(f"{label}: variant traced alone {seconds}")
        row["retraced_each"] = each
        row["retraced_all_extrapolated"] = {k: round(float(np.mean([s[k] for s in each])) * len(variants), 1)
                                            for k in ("wall_s", "cpu_s")}
        out[label] = row
    return out


def _smoothed(variance: np.ndarray, inside: np.ndarray) -> np.ndarray:
    """The (h, w, S) variance map averaged over SMOOTH_PX pixels a side, inside the circle only."""
    from scipy import ndimage

    size = (SMOOTH_PX, SMOOTH_PX, 1)
    weight = ndimage.uniform_filter(inside[..., None].astype(np.float64), size)
    smoothed = ndimage.uniform_filter(np.where(inside[..., None], variance, 0.0).astype(np.float64), size)
    return np.where(weight > 0, smoothed / np.maximum(weight, 1e-12), 0.0)


def compare(a_mean, a_var, b_mean, b_var, inside) -> dict:
    """Agreement of two (h, w, S) estimates: z statistics, totals' ratio, variances' ratio."""
    lit = inside[..., None] & (a_mean > 0) & (b_mean > 0)
    z = (a_mean - b_mean) / np.sqrt(_smoothed(a_var, inside) + _smoothed(b_var, inside))
    z = z[lit & np.isfinite(z)]
    totals = [float(a_mean[..., s][inside].sum() / b_mean[..., s][inside].sum()) for s in range(a_mean.shape[-1])]
    variances = [float(a_var[..., s][inside].sum() / b_var[..., s][inside].sum()) for s in range(a_mean.shape[-1])]
    return {"mean_z2": round(float(np.mean(z**2)), 3), "mean_z": round(float(np.mean(z)), 3),
            "share_over_3": round(float(np.mean(np.abs(z) > 3)), 4), "pixels": int(z.size),
            "totals_ratio": [round(t, 4) for t in totals], "variance_ratio": [round(v, 3) for v in variances]}


def agreement(spec, mesh, camera, effects, depth, ref, build, variants, names, photons, passes,
              progress=print) -> dict:
    """Each variant re-weighted (seed 1) against traced at it (seed 2), one contact."""
    from pbr_tactile.basis import emitter_basis

    kw = dict(photons=photons, spp=SPP, passes=passes, solids=build, depth=depth, ref_depth=ref, use_cache=False)
    inside = camera.scaled(*FILM).mask
    got, seconds = _timed(lambda: emitter_basis(spec, mesh, camera, effects, FILM, seed=1, perturb=variants, **kw))
    progress(f"agreement: re-weighted render {seconds}")
    rows = {}
    for k, ((sa, ss, rho), name) in enumerate(zip(variants, names)):
        e = dataclasses.replace(effects, absorption_per_m=float(sa), scattering_per_m=float(ss),
                                coating_albedo=float(rho))
        again, seconds = _timed(lambda: emitter_basis(spec, mesh, camera, e, FILM, seed=2, **kw))
        row = compare(got["variant_mean"][k], got["variant_variance"][k], again["mean"], again["variance"], inside)
        row["ess_ratio"] = [round(float(r), 4) for r in got["ess_ratio"][k]]
        row["valid"] = bool(got["valid"][k])
        row["retraced_s"] = seconds
        rows[name] = row
        progress(f"agreement: {name} {row}")
    # The identity against itself re-traced: what z^2 and the variance ratio read at no change.
    again, _ = _timed(lambda: emitter_basis(spec, mesh, camera, effects, FILM, seed=2, **kw))
    rows["identity"] = compare(got["mean"], got["variance"], again["mean"], again["variance"], inside)
    progress(f"agreement: identity {rows['identity']}")
    return rows


def table(results: dict) -> str:
    lines = ["| variant | ESS ratio (min over sources) | variance ratio (median) | mean z^2 | share |z| > 3 | "
             "totals ratio (min, max) | valid |", "|---|---|---|---|---|---|---|"]
    for name, row in results.get("agreement", {}).items():
        ess = min(row["ess_ratio"]) if "ess_ratio" in row else 1.0
        lines.append(f"| {name} | {ess:.3f} | {np.median(row['variance_ratio']):.2f} | {row['mean_z2']:.2f} | "
                     f"{row['share_over_3']:.4f} | {min(row['totals_ratio']):.3f}, {max(row['totals_ratio']):.3f} | "
                     f"{row.get('valid', '')} |")
    timing_ = results.get("timing", {})
    if timing_:
        lines += ["", "| contact | traced | with variants | each variant traced | all variants traced (extrapolated) |",
                  "|---|---|---|---|---|"]
        for label, row in timing_.items():
            lines.append(f"| {label} | {row['traced']} | {row['with_variants']} | {row['retraced_each']} | "
                         f"{row['retraced_all_extrapolated']} |")
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m studies.reweight", description=__doc__.splitlines()[0])
    p.add_argument("--out", required=True, metavar="DIR")
    p.add_argument("--photons", type=int, default=PHOTONS, help=f"photons per source per pass (default {PHOTONS})")
    p.add_argument("--runs", type=int, default=NO_CONTACT_RUNS, help="no-contact runs per pass of the timed "
                   f"renders (default {NO_CONTACT_RUNS})")
    p.add_argument("--passes", type=int, default=AGREEMENT_PASSES, help="passes of the agreement's renders "
                   f"(default {AGREEMENT_PASSES})")
    p.add_argument("--sample", type=int, default=RETRACED_SAMPLE, help="variants traced alone and timed "
                   f"(default {RETRACED_SAMPLE})")
    p.add_argument("--skip", choices=("timing", "agreement"), action="append", default=[])
    args = p.parse_args(argv)
    import os

    import trimesh

    from pbr_tactile.effects import Effects
    from pbr_tactile.membrane import ElastomerBuilder
    from pbr_tactile.reweight import MIN_ESS_RATIO
    from scenes.camera import Camera, reference_depth
    from scenes.contact import press
    from scenes.dataset import atomic_write_json
    from scenes.files import atomic_write_bytes
    from scenes.geometry import membrane_mesh
    from scenes.spec_read import default_spec

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    spec = default_spec()
    mesh, camera = membrane_mesh(spec), Camera.from_spec(spec)
    ref = reference_depth(mesh, camera)[0].astype(np.float32)
    contacts = [press(ref, camera, mesh, trimesh.primitives.Sphere(radius=SPHERE_RADIUS_M), pixel, PRESS_M)
                .astype(np.float32) for pixel in CONTACTS]
    effects = Effects(core_light_leak=LEAK_BASIS)
    variants, names = grid_variants(spec, effects)
    results = {"settings": {"film": FILM, "photons": args.photons, "spp": SPP, "passes": PASSES,
                            "no_contact_runs": args.runs, "agreement_passes": args.passes, "variants": names,
                            "min_ess_ratio": MIN_ESS_RATIO, "effects": dataclasses.asdict(effects)}}
    with tempfile.TemporaryDirectory(prefix="reweight-cache-") as cache:
        os.environ["TACTILE_SIM_CACHE"] = cache  # a fresh cache: the first contact is cold
        build = ElastomerBuilder(mesh, spec, camera)
        build.grid()  # the undeformed fluence grid, measured once, outside the timings
        if "timing" not in args.skip:
            results["timing"] = timing(spec, mesh, camera, effects, contacts, ref, build, variants, args.photons,
                                       args.runs, args.sample)
            atomic_write_json(out / "results.json", results)
        if "agreement" not in args.skip:
            results["agreement"] = agreement(spec, mesh, camera, effects, contacts[1], ref, build, variants, names,
                                             args.photons, args.passes)
    atomic_write_json(out / "results.json", results)
    atomic_write_bytes(out / "table.md", table(results).encode())
    print(table(results))
    print(json.dumps({"wrote": [str(out / "results.json"), str(out / "table.md")]}))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
