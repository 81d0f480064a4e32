"""The tiles benchmark: every column of the figure recovered, rendered and scored
(``tactile-sim bench tiles``; the package doc)."""

from __future__ import annotations

import math
import sys
import time
from pathlib import Path

import numpy as np

from .disk import MATCH_FIELD, TileError, discover, object_of, read_tile
from .frames import CHANGE_LEVEL, changed_region, tile_inside
from .locate import LOCATE_BOUND_PX, locate
from .paper import PaperModel
from .recovery import Contact, contact_centroid, match_report, recover, roll_period
from .rendering import simulated
from .scoring import change_figure, real_alignment, real_no_contact

#: The reference's photons per pass by default (the plugin's default is 2^18).
PHOTONS = 1 << 16


def _clean(obj):
    """JSON-safe: NaN and inf as None, numpy scalars as Python numbers."""
    if isinstance(obj, dict):
        return {str(k): _clean(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_clean(v) for v in obj]
    if isinstance(obj, (np.floating, float)):
        return float(obj) if math.isfinite(obj) else None
    if isinstance(obj, np.integer):
        return int(obj)
    return obj


def _by_renderer(scores: dict, key: str) -> dict:
    return {name: scores.get(name, {}).get(key) for name in ("pbr", "phong")}


def _factors(scores: dict) -> dict:
    """A place's scores beyond the plain strength (``score``): each renderer's ``contrast``
    and ``exposed`` blocks, ``strength_ratio_exposed`` and ``signed_ratio_exposed``
    (``signed_change``) on their own, and what its noise alone reads as strength
    (``noise_strength``, ``noise_floor``)."""
    exposed = _by_renderer(scores, "exposed")
    return {"strength_ratio_exposed": {n: (e or {}).get("strength_ratio") for n, e in exposed.items()},
            "signed_ratio_exposed": {n: (e or {}).get("signed_ratio") for n, e in exposed.items()},
            "contrast": _by_renderer(scores, "contrast"), "exposed": exposed,
            "noise_strength": _by_renderer(scores, "noise_strength")}


def run(json_path, tiles_dir=None, reference_dir=None, objects: dict[int, str] | None = None,
        reference: bool = True, photons: int = PHOTONS, quiet: bool = True, effects: tuple[str, ...] = (),
        images_dir=None, elastic: str = "published") -> dict:
    """The benchmark (module doc): every column of ``tiles_dir`` recovered and scored;
    writes ``json_path`` atomically and returns what it wrote. ``effects``: the
    reference's effects as NAME=VALUE settings (``pbr_tactile.effects.Effects``; none:
    its defaults), to judge a change of its physics on the real tiles. ``images_dir``:
    each column's ``change_figure`` written there, ``colK_recovered.png`` and
    ``colK_at_real_place.png``, and their paths in ``tiles.K.images``. ``elastic``: the
    dent both renderers draw (``scenes.elastic.MODELS``; the fast path's "published" by
    default, the reference's its layer model unless "bonded").

    Besides the recovered tap, each column is scored with the tap moved by the offset
    between the real tile's contact patch and the published tile's (``at_real_place``:
    the figure's real and simulated contacts of a column need not sit at one place)."""
    from scenes.camera import Camera, reference_depth
    from scenes.captures import REGION_DILATION
    from scenes.contact import surface_point
    from scenes.dataset import atomic_write_json
    from scenes.geometry import membrane_mesh
    from scenes.image_stats import contact_strength
    from scenes.images import read_rgb, write_rgb
    from scenes.indenters import indenter, is_indenter
    from scenes.reference_data import require_real_contacts_dir, require_reference_dir
    from scenes.spec_read import default_spec

    from pbr_tactile import plugin as pbr
    from pbr_tactile.effects import Effects
    from phong_reference import plugin as phong

    if effects and not reference:
        raise TileError("--effects sets the reference's physics; it has no use with --no-reference")
    Effects().with_settings(list(effects))  # a bad setting is named before any work
    t_all = time.perf_counter()

    def say(text):
        if not quiet:
            print(text, file=sys.stderr, flush=True)

    tiles_dir = require_real_contacts_dir(tiles_dir)
    columns = discover(tiles_dir)
    names = {k: object_of(k, objects) for k in columns}
    for k, name in names.items():
        if not is_indenter(name):
            raise TileError(f"column {k}: object {name!r} is not an indenter (scenes.indenters.INDENTERS, "
                            "ball_<D>mm or a mesh file)")
    reals = {k: read_tile(c.real) for k, c in columns.items()}
    sims = {k: {f: read_tile(p) for f, (p, _) in c.sims.items()} for k, c in columns.items()}
    reference_dir = require_reference_dir(reference_dir)

    t0 = time.perf_counter()
    model = PaperModel.load(reference_dir)
    real_background = read_rgb(reference_dir / "real" / "bkg.png", model.camera.shape).astype(np.float64)
    alignments = {k: real_alignment(t, real_background) for k, t in reals.items()}
    no_contacts, how = real_no_contact(reals, alignments, real_background)
    spec = default_spec()
    camera = Camera.from_spec(spec)
    mesh = membrane_mesh(spec)
    ours = (reference_depth(mesh, camera)[0], camera, mesh)
    renderers = {}
    phong_options = {} if elastic == "published" else {"elastic": elastic}
    phong.prepare(spec, mesh, camera, phong_options)
    renderers["phong"] = phong.make_renderer(spec, mesh, camera, ours[0], phong_options)
    pbr_options = {"photons": int(photons), **({"effects": list(effects)} if effects else {}),
                   **({"elastic": "bonded"} if elastic == "bonded" else {})}
    pbr_settings = None
    if reference:
        say(f"reference: its no-contact frame at {photons} photons per pass (cached after the first run)")
        pbr_settings = pbr.prepare(spec, mesh, camera, pbr_options)
        renderers["pbr"] = pbr.make_renderer(spec, mesh, camera, ours[0], pbr_options)
    stage_seconds = {"prepare": time.perf_counter() - t0}

    out_tiles = {}
    for k, col in columns.items():
        t_col = time.perf_counter()
        name, shape = names[k], indenter(names[k])
        period = roll_period(name)
        match_path, match_bg = col.sims[MATCH_FIELD]
        say(f"column {k}: {name}, recovered from {match_path.name}")
        t0 = time.perf_counter()
        rec = recover(sims[k][MATCH_FIELD], model.renderer(MATCH_FIELD, match_bg), model.mesh, shape, period,
                      where=str(match_path))
        t_recover = time.perf_counter() - t0
        c = rec.contact
        point, normal = surface_point(model.mesh, model.camera, (c.u, c.v))
        fields = {f: match_report(sims[k][f], model.renderer(f, bg), model.mesh, shape, c)
                  for f, (_, bg) in col.sims.items()}
        say(f"  place ({c.u:.1f}, {c.v:.1f}) px, depth {c.depth_m * 1e3:.2f} mm, roll {math.degrees(c.roll_rad):.1f} "
            f"deg; {MATCH_FIELD} contact MAE {fields[MATCH_FIELD]['mae_contact']:.4f} (no contact "
            f"{fields[MATCH_FIELD]['no_contact_mae_contact']:.4f}), {rec.evaluations} renders, {t_recover:.0f} s")

        real, real_nc, align_real = reals[k], no_contacts[k], alignments[k]
        inside = tile_inside(real.shape[:2], align_real, camera)
        region = changed_region(real, real_nc, inside)
        real_strength = float(contact_strength(real[None], real_nc, region[None])[0])
        figures = {}

        def figure(key: str, kept: dict | None) -> None:
            if kept:
                figures[key] = str(write_rgb(Path(images_dir) / f"col{k}_{key}.png",
                                             change_figure(real, real_nc, region, kept)))

        kept = {} if images_dir is not None else None
        scores, seconds = simulated(c, renderers, shape, ours, real, real_nc, align_real, region, inside, kept)
        figure("recovered", kept)
        for rname, sc in scores.items():
            say(f"  {rname}: strength ratio {sc['strength_ratio']} (exposed {(sc.get('exposed') or {}).get('strength_ratio')}"
                f", signed {(sc.get('exposed') or {}).get('signed_ratio')}, noise alone {sc.get('noise_strength')}), "
                f"shape corr {sc['shape_corr']} "
                f"({seconds.get(rname, 0):.0f} s)")
        try:
            real_centre = contact_centroid(real, real_nc, align_real, camera, str(col.real))
        except TileError:
            real_centre = None
        moved = None
        if real_centre is not None:
            offset = (real_centre[0] - rec.centroid[0], real_centre[1] - rec.centroid[1])
            there = Contact(c.u + offset[0], c.v + offset[1], c.depth_m, c.roll_rad)
            kept = {} if images_dir is not None else None
            moved_scores, moved_seconds = simulated(there, renderers, shape, ours, real, real_nc, align_real, region,
                                                    inside, kept)
            figure("at_real_place", kept)
            moved = {"offset_px": list(offset), "u_px": there.u, "v_px": there.v,
                     "strength_ratio": _by_renderer(moved_scores, "strength_ratio"),
                     "shape_corr": _by_renderer(moved_scores, "shape_corr"),
                     "strength": _by_renderer(moved_scores, "strength"), **_factors(moved_scores),
                     "seconds": {f"render_{n}": v for n, v in moved_seconds.items()}}
            say(f"  at the real contact's place (moved {offset[0]:+.0f}, {offset[1]:+.0f} px): strength ratio "
                f"{moved['strength_ratio']}, shape corr {moved['shape_corr']}")
            found, corr = locate(there, renderers["phong"], shape, ours, real, real_nc, align_real, inside, period)
            found_scores, found_seconds = simulated(found, renderers, shape, ours, real, real_nc, align_real, region,
                                                         inside)
            moved["located"] = {"u_px": found.u, "v_px": found.v, "moved_px": [found.u - there.u, found.v - there.v],
                                "bound_px": LOCATE_BOUND_PX, "roll_deg": None if period is None else
                                math.degrees(found.roll_rad), "phong_change_corr": corr,
                                "strength_ratio": _by_renderer(found_scores, "strength_ratio"),
                                "shape_corr": _by_renderer(found_scores, "shape_corr"),
                                "strength": _by_renderer(found_scores, "strength"), **_factors(found_scores)}
            say(f"  located on the real tile at ({found.u:.0f}, {found.v:.0f}) px (phong's change correlates "
                f"{corr:.2f}): strength ratio {moved['located']['strength_ratio']}, shape corr "
                f"{moved['located']['shape_corr']}")
        out_tiles[k] = {
            "object": name,
            "object_from": "--object" if objects and k in objects else "caption",
            "depth_mm": c.depth_m * 1e3,
            "place": {"u_px": c.u, "v_px": c.v, "point_mm": (point * 1e3).tolist(), "normal": normal.tolist(),
                      "published_patch_u_px": rec.centroid[0], "published_patch_v_px": rec.centroid[1]},
            "roll_deg": None if period is None else math.degrees(c.roll_rad),
            "roll_period_deg": None if period is None else math.degrees(period),
            "match": {"field": MATCH_FIELD, "tile": match_path.name, "mse": rec.mse, "renders": rec.evaluations,
                      "alignment": rec.alignment.to_dict(),
                      **{key: {f: v[key] for f, v in fields.items()}
                         for key in ("mae", "no_contact_mae", "mae_contact", "no_contact_mae_contact")},
                      "by_field": fields},
            "strength_ratio": _by_renderer(scores, "strength_ratio"),
            "shape_corr": _by_renderer(scores, "shape_corr"),
            "strength": {"real": real_strength, **_by_renderer(scores, "strength")},
            **_factors(scores),
            "reference_noise": ({"passes": scores["pbr"].get("passes"), "contact_rse": scores["pbr"].get("contact_rse")}
                                if "pbr" in scores else None),
            "real": {"tile": col.real.name, "region_px": int(region.sum()), "alignment": align_real.to_dict(),
                     "patch_u_px": None if real_centre is None else real_centre[0],
                     "patch_v_px": None if real_centre is None else real_centre[1]},
            "at_real_place": moved,
            "images": figures or None,
            "seconds": {"recover": t_recover, **{f"render_{n}": v for n, v in seconds.items()},
                        "total": time.perf_counter() - t_col},
        }
    pbr_info = None
    if pbr_settings is not None:
        pbr_info = {"options": pbr_options, "effects": list(effects) or "defaults", "film": pbr_settings["film"],
                    "passes": [pbr_settings["min_passes"], pbr_settings["max_passes"]],
                    "target_rse": pbr_settings["target_rse"], "variant": pbr_settings["variant"]}
    out = {
        "tiles_dir": str(tiles_dir),
        "reference_dir": str(reference_dir),
        "columns": sorted(out_tiles),
        "tiles": out_tiles,
        "real_no_contact": how,
        "region": f"mean |real - no-contact| over channels > {CHANGE_LEVEL}, dilated by {REGION_DILATION} px, inside "
                  "the image circle less a px",
        "elastic": elastic,
        "renderers": {"phong": {"options": phong_options, "field": "plane (the plugin's default)", "background": "none"},
                      "pbr": pbr_info},
        "seconds": time.perf_counter() - t_all,
        "stage_seconds": stage_seconds,
    }
    out = _clean(out)
    atomic_write_json(Path(json_path), out)
    return out
