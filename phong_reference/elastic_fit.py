"""The bonded layer's thickness and Poisson's ratio and each press's depth, fitted
together to a capture's fitted presses with the fast path's shading.

A real capture records no depths; it records each press's rim, the radius at which its
change peaks (``scenes.imports.contact_edge_px``). Each candidate layer has its own
rim-to-depth relation: the fast path, its dent the layer's (``scenes.elastic_solid``),
presses the ball at RELATION_SHARES of its radius and the rim of each render is measured
as a real one is (``Presses.rim_relation``; the elastic contact's own edge lies inside
that rim). So each candidate gives every press a depth, with no share of the rim guessed,
and is judged by how well the fast path, with the layer's dents at those depths, fits
the fitted presses' changes (its LED constants refitted by non-negative least squares,
the relation measured again with them, RELATION_PASSES times; its lights' places held at
the calibrated profile's):

1. every (h, nu) of THICKNESSES_M x RATIOS is scored by each fitted press's MAE over its
   contact region; the layer is the one whose summed loss is least, and its interval
   the range of the layers that bootstrap resamplings of the presses choose (BOOTSTRAP);
2. at that layer and those constants, each fitted press's depth is then fitted alone: its
   loss at DEPTH_FACTORS of the rim's depth, refined by a parabola through the least and
   its neighbours. A press whose least lies at either end is flagged, not extended;
3. the held-out presses get their depths by a rule that never sees their render: the
   layer's rim-to-depth relation times k, the median over the fitted presses of their
   fitted depth over the rim's (with its bootstrap interval).

A press whose depth reaches past the layer's thickness would press the ball onto the
support: it is flagged (``reaches_support``), never capped. A depth past DEPTH_LIMIT of the
ball's radius is held there, and flagged (``held_at_ball_limit``).
"""

from __future__ import annotations

import dataclasses
import json
import time
from pathlib import Path

import numpy as np

#: The layers searched: thickness h (m) and Poisson's ratio nu.
THICKNESSES_M = (1.5e-3, 2.5e-3, 3.5e-3, 5e-3, 7e-3)
RATIOS = (0.3, 0.4, 0.49)
#: Each fitted press's depth is searched at these shares of its rim's depth.
DEPTH_FACTORS = (0.7, 0.775, 0.85, 0.925, 1.0, 1.075, 1.15, 1.225, 1.3)
#: The depths, as shares of the ball's radius, at which the model's rim is measured
#: (``Presses.rim_relation``), and the passes of relation and constants per layer.
RELATION_SHARES = (0.15, 0.25, 0.35, 0.45, 0.55, 0.65, 0.75, 0.85, 0.95)
RELATION_PASSES = 2
#: No depth goes past this share of the ball's radius (a deeper one is held there and
#: flagged, ``held_at_ball_limit``): the deepest the contact relation is tabulated at
#: (``scenes.elastic_solid.DEPTH_SHARES``), and past the radius a ball has no depth map a
#: peer can draw.
DEPTH_LIMIT = 0.98
#: Bootstrap resamplings of the fitted presses for the intervals.
BOOTSTRAP = 2000
#: The intervals' coverage.
COVERAGE = 0.95


def _press_losses(pred: np.ndarray, real: np.ndarray, regions: np.ndarray) -> np.ndarray:
    """(T,) each press's MAE of the change over its region, channels pooled."""
    return np.array([float(np.abs(p[r] - y[r]).mean()) if r.any() else np.nan
                     for p, y, r in zip(pred, real, regions)])


def _parabola_min(x: np.ndarray, y: np.ndarray, k: int) -> float:
    """The least of a parabola through (x, y) at k - 1, k, k + 1 (k inside), kept between
    its neighbours."""
    (x0, x1, x2), (y0, y1, y2) = x[k - 1:k + 2], y[k - 1:k + 2]
    denom = (x0 - x1) * (x0 - x2) * (x1 - x2)
    a = (x2 * (y1 - y0) + x1 * (y0 - y2) + x0 * (y2 - y1)) / denom
    b = (x2 * x2 * (y0 - y1) + x1 * x1 * (y2 - y0) + x0 * x0 * (y1 - y2)) / denom
    return float(np.clip(-b / (2 * a), x0, x2)) if a > 0 else float(x1)


def interval(values, coverage: float = COVERAGE) -> list[float]:
    """The central ``coverage`` range of ``values``."""
    tail = (1 - coverage) / 2 * 100
    return [float(np.percentile(values, tail)), float(np.percentile(values, 100 - tail))]


class Presses:
    """A capture's presses as the fit needs them: the fast path's renderer inputs, the
    real changes and regions, each press's rim (m) and tap, and depth maps made anew for
    any depths (the rig pressing each tap that deep)."""

    def __init__(self, capture, profile_path):
        from scenes.camera import Camera
        from scenes.captures import load_real_taps, split
        from scenes.dataset import read_meta, read_samples
        from scenes.geometry import membrane_mesh
        from scenes.images import read_rgb
        from scenes.profile import load_profile
        from scenes.replay import read_capture
        from scenes.taps import Protocol

        from .bake import bake
        from .calibrate import _changes_to_fit
        from .environment import coefficients
        from .plugin import options_from, unit_spec
        from .render import light_vectors

        self.folder = Path(capture)
        unit = read_capture(self.folder)
        self.spec = unit.spec
        self.camera = Camera.from_spec(self.spec)
        self.mesh = membrane_mesh(self.spec)
        meta = read_meta(self.folder).get("import") or {}
        if "ball_mm" not in meta:
            raise ValueError(f"capture {self.folder}: its dataset.json records no import (ball_mm): the layer is fitted "
                             "to imported ball presses")
        self.ball_radius_m = float(meta["ball_mm"]) * 1e-3 / 2
        self.pixel_m = float(meta["pixel_mm"]) * 1e-3
        records = {str(r["id"]): r for r in read_samples(self.folder)}
        taps = load_real_taps(self.folder, self.spec, self.camera, len(records))
        missing = [i for i in taps.ids if "contact_edge_px" not in records[i] or "contact_center_px" not in records[i]]
        if missing:
            raise ValueError(f"capture {self.folder}: presses {missing[:3]} record no contact_edge_px or "
                             "contact_center_px (the rim the import fitted, and the centre): import them again")
        self.taps = taps
        self.fitted = split(len(taps.ids))
        self.centres_px = np.array([records[i]["contact_center_px"] for i in taps.ids], np.float64)
        self.rims_m = np.array([records[i]["contact_edge_px"] for i in taps.ids], np.float64) * self.pixel_m
        protocol = Protocol.from_dict(json.loads((self.folder / "protocol.json").read_text()))
        self.protocol_taps = [protocol.taps[records[i]["tap_index"]] for i in taps.ids]
        self.names = [records[i].get("source_name", i) for i in taps.ids]
        self.background = read_rgb(self.folder / "background.png").astype(np.float64)
        opts = options_from({"field": load_profile(profile_path, self.spec).phong.get("field", "linear"),
                             "profile": str(profile_path)})
        baked, calibrated = unit_spec(self.spec, opts)
        self.field = opts["field"]
        # the profile as the calibration fits it: the background term and, with the published
        # smoothing, its fitted spread; the lights' places are baked into L, the constants refitted
        phong = calibrated.phong.get("fields", {}).get(self.field, calibrated.phong)
        self.constants = (phong.get("leds") or calibrated.phong["leds"],
                          float(phong.get("shininess") or calibrated.phong["shininess"]))
        self.environment = coefficients(phong.get("environment", calibrated.phong.get("environment")))
        self.profile = dataclasses.replace(calibrated, phong={
            **{k: calibrated.phong[k] for k in ("ambient", "background") if k in calibrated.phong},
            **{k: phong[k] for k in ("sigma_px", "radius_px") if k in phong}})
        self.L = light_vectors(bake(self.mesh, self.camera, baked.leds, self.field))
        self.real, self.regions, _ = _changes_to_fit(self.spec, self.profile, taps, self.background,
                                                     "the elastic layer")

    def depth_maps(self, depths_m, which) -> np.ndarray:
        """(len(which), H, W) the depth maps of presses ``which`` (indices) at ``depths_m``."""
        from scenes.rig import tap_depths

        taps = [dataclasses.replace(self.protocol_taps[i], depth=float(d)) for i, d in zip(which, depths_m)]
        replay = tap_depths(self.spec, taps, self.mesh)
        try:
            next(replay)
            return np.stack([d for d, _ in replay]).astype(np.float32)
        finally:
            replay.close()

    def rim_relation(self, layer, leds: list[dict], shininess: float, env=None) -> tuple[np.ndarray, np.ndarray]:
        """The model's rim-to-depth relation: (depths, m, the rims, m, at which the change
        of a press that deep peaks), the press nearest the image's centre rendered with
        ``layer`` and the constants at RELATION_SHARES of the ball's radius and its rim
        measured as the import measures a real one (``contact_edge_px``). A depth whose
        rim cannot be found (too shallow for the search) is left out; the rims are made
        non-decreasing."""
        from scenes.imports import contact_edge_px

        j = int(np.argmin(np.hypot(self.centres_px[:, 0] - self.camera.cx, self.centres_px[:, 1] - self.camera.cy)))
        depths = np.asarray(RELATION_SHARES) * self.ball_radius_m
        maps = self.depth_maps(depths, [j] * len(depths))
        change = self.changes(maps, layer, leds, shininess, env)
        u, v = self.centres_px[j]
        rims, kept = [], []
        for d, c in zip(depths, change):
            try:
                rims.append(contact_edge_px(self.background + c, self.background, (u, v),
                                            self.ball_radius_m / self.pixel_m) * self.pixel_m)
                kept.append(d)
            except ValueError:
                continue
        if len(kept) < 3:
            raise ValueError(f"the model's press at ({u:.1f}, {v:.1f}) px shows a rim at only {len(kept)} of "
                             f"{len(depths)} depths: no rim-to-depth relation")
        return np.array(kept), np.maximum.accumulate(np.array(rims))

    def rim_depths(self, relation) -> tuple[np.ndarray, np.ndarray]:
        """(T,) each press's depth, m, from its rim by a rim-to-depth ``relation``
        (:meth:`rim_relation`), linear in the rim's square between its points, and (T,)
        bool where the rim lies outside them (given the nearest end's depth)."""
        from scenes.elastic_solid import depth_at_radius

        depths, rims = relation
        outside = (self.rims_m < rims[0]) | (self.rims_m > rims[-1])
        return depth_at_radius(self.rims_m, rims, depths), outside

    def layer(self, thickness_m: float, poisson: float):
        from scenes.elastic_solid import BondedLayer

        return BondedLayer(self.spec, self.camera, thickness_m, poisson)

    def changes(self, maps: np.ndarray, layer, leds: list[dict], shininess: float, env=None) -> np.ndarray:
        from .calibrate import _changes

        return _changes(self.spec, self.taps.ref_depth, self.L, self.profile, maps, layer, leds, shininess, env)


def score_layers(presses: Presses, thicknesses=THICKNESSES_M, ratios=RATIOS, progress=None) -> dict:
    """Step 1 (module doc): per layer, the fitted presses' depths from their rims, the LED
    constants refitted at them, and each fitted press's loss."""
    from .calibrate import fit_terms

    fitted = np.flatnonzero(presses.fitted)
    real, regions = presses.real[fitted], presses.regions[fitted]
    out = []
    for h in thicknesses:
        for nu in ratios:
            layer = presses.layer(h, nu)
            (leds, alpha), env = presses.constants, presses.environment
            for _ in range(RELATION_PASSES):  # the relation with the constants, the constants at its depths
                relation = presses.rim_relation(layer, leds, alpha, env)
                depths, capped = presses.rim_depths(relation)
                maps = presses.depth_maps(depths[fitted], fitted)
                leds, alpha, _, env = fit_terms(presses.spec, presses.taps.ref_depth, presses.L, presses.profile,
                                                maps, layer, real, regions)
            losses = _press_losses(presses.changes(maps, layer, leds, alpha, env), real, regions)
            out.append({"thickness_m": h, "poisson_ratio": nu, "losses": losses, "leds": leds, "shininess": alpha,
                        "environment": env,
                        "relation_mm": [[float(d * 1e3) for d in relation[0]], [float(a * 1e3) for a in relation[1]]],
                        "depths_m": depths, "capped": capped, "layer": layer})
            if progress:
                progress(f"layer h {h * 1e3:g} mm, nu {nu:g}: loss {np.nanmean(losses):.5f}")
    return {"fitted": fitted, "layers": out}


def choose(losses: np.ndarray, rng: np.random.Generator, resamples: int = BOOTSTRAP) -> tuple[int, np.ndarray]:
    """(the candidate whose summed loss over presses is least, (resamples,) the one each
    bootstrap resampling of the presses chooses) from ``losses`` (candidates, presses)."""
    losses = np.asarray(losses, np.float64)
    pick = rng.integers(0, losses.shape[1], size=(resamples, losses.shape[1]))
    return int(np.argmin(losses.sum(axis=1))), np.argmin(losses[:, pick].sum(axis=2), axis=0)


def fit_depths(presses: Presses, best: dict, factors=DEPTH_FACTORS) -> dict:
    """Step 2 (module doc): each fitted press's depth at the chosen layer and constants."""
    fitted = np.flatnonzero(presses.fitted)
    factors = np.asarray(factors, np.float64)
    table = np.empty((len(fitted), len(factors)))
    for k, s in enumerate(factors):
        maps = presses.depth_maps(best["depths_m"][fitted] * s, fitted)
        table[:, k] = _press_losses(presses.changes(maps, best["layer"], best["leds"], best["shininess"],
                                                    best["environment"]),
                                    presses.real[fitted], presses.regions[fitted])
    share, at_end = np.empty(len(fitted)), np.zeros(len(fitted), bool)
    for i, row in enumerate(table):
        k = int(np.nanargmin(row))
        at_end[i] = k in (0, len(factors) - 1)
        share[i] = factors[k] if at_end[i] else _parabola_min(factors, row, k)
    return {"factors": factors, "losses": table, "share": share, "at_end": at_end}


def fit(capture, profile_path, out=None, thicknesses=THICKNESSES_M, ratios=RATIOS, factors=DEPTH_FACTORS,
        seed: int = 0, progress=None) -> dict:
    """The joint fit (module doc) on ``capture``'s fitted presses, with the fast path's
    calibrated ``profile_path`` (its field and lights' places); writes ``out`` (a JSON,
    where given) and returns it: the layer, k, every press's depth (``depths_m``, by
    sample id: fitted presses their own, held-out ones the rule's) and the intervals."""
    from scenes.elastic_solid import check_material
    from scenes.protocol_checks import max_safe_depth_m

    for h in thicknesses:
        check_material(h, 0.0)
    for nu in ratios:
        check_material(None, nu)
    t0 = time.perf_counter()
    presses = Presses(capture, profile_path)
    rng = np.random.default_rng(seed)
    scored = score_layers(presses, thicknesses, ratios, progress)
    layers, fitted = scored["layers"], scored["fitted"]
    losses = np.array([c["losses"] for c in layers])
    best_k, boot = choose(losses, rng)
    best = layers[best_k]
    h_boot = np.array([layers[k]["thickness_m"] for k in boot])
    nu_boot = np.array([layers[k]["poisson_ratio"] for k in boot])
    depths = fit_depths(presses, best, factors)
    rim = best["depths_m"]
    k_share = float(np.median(depths["share"]))
    k_boot = np.median(rng.choice(depths["share"], size=(BOOTSTRAP, len(fitted))), axis=1)
    final = rim * k_share
    final[fitted] = rim[fitted] * depths["share"]
    # a ball pressed past its own radius has no depth map a peer can draw (its sphere's
    # cap): those depths are held at the deepest the relation was solved at, and flagged
    deepest = DEPTH_LIMIT * presses.ball_radius_m
    past_ball = final > deepest
    final = np.minimum(final, deepest)
    held = np.flatnonzero(~presses.fitted)
    all_boot = np.median(rng.choice(final, size=(BOOTSTRAP, len(final))), axis=1)
    # each press's depth under each resampling's layer and k (a fitted press keeps its share)
    shares = np.empty((BOOTSTRAP, len(final)))
    shares[:] = k_boot[:, None]
    shares[:, fitted] = depths["share"]
    per_press = np.minimum(np.array([layers[b]["depths_m"] for b in boot]) * shares, deepest)
    widths = np.diff(np.percentile(per_press, [(1 - COVERAGE) / 2 * 100, (1 + COVERAGE) / 2 * 100], axis=0),
                     axis=0)[0]
    points = np.array([t.point for t in presses.protocol_taps])
    safe = max_safe_depth_m(presses.spec, points, presses.mesh)
    support = np.minimum(safe, best["thickness_m"])
    reaches = final >= support
    ids = presses.taps.ids
    record = presses.spec.membrane.elastomer_thickness, presses.spec.elastic.poisson_ratio
    h_int, nu_int = interval(h_boot), interval(nu_boot)
    report = {
        "what": "the bonded layer's thickness and Poisson's ratio and each press's depth, fitted together to the "
                "capture's fitted presses with the fast path's shading (phong_reference.elastic_fit)",
        "capture": str(presses.folder), "profile": str(profile_path), "field": presses.field,
        "elastic": {"model": "bonded", "thickness_m": best["thickness_m"], "poisson_ratio": best["poisson_ratio"]},
        "relation_mm": best["relation_mm"],
        "relation_what": "the chosen layer's rim-to-depth relation: [depths, rims] mm (Presses.rim_relation)",
        "intervals": {"thickness_m": h_int, "poisson_ratio": nu_int,
                      "rule": f"the layers {BOOTSTRAP} bootstrap resamplings of the fitted presses choose, central "
                              f"{COVERAGE:.0%}"},
        "record": {"thickness_m": record[0], "poisson_ratio": record[1],
                   "thickness_agrees": bool(record[0] is not None and h_int[0] <= record[0] <= h_int[1]),
                   "ratio_agrees": bool(nu_int[0] <= record[1] <= nu_int[1])},
        "depth_share": {"k": k_share, "interval": interval(k_boot),
                        "rule": "held-out presses: the layer's rim-to-depth relation times k, the median over the "
                                "fitted presses of their fitted depth over their rim's"},
        "depths_m": {i: float(d) for i, d in zip(ids, final)},
        "depth_median_m": float(np.median(final)), "depth_median_interval_m": interval(all_boot),
        "depth_median_interval_width_m": float(np.diff(interval(all_boot))[0]),
        "depth_interval_median_width_m": float(np.median(widths)),
        "depth_interval_rule": f"each press's depth under the layer and k of each of {BOOTSTRAP} bootstrap resamplings "
                               "of the fitted presses (a fitted press keeps its own share), central "
                               f"{COVERAGE:.0%}; the median over presses of its width",
        "fitted_presses": [ids[i] for i in fitted], "heldout_presses": [ids[i] for i in held],
        "presses": [{"id": ids[i], "name": presses.names[i], "rim_mm": float(presses.rims_m[i] * 1e3),
                     "rim_depth_mm": float(rim[i] * 1e3), "depth_mm": float(final[i] * 1e3),
                     "depth_interval_mm": [float(np.percentile(per_press[:, i], (1 - COVERAGE) / 2 * 100) * 1e3),
                                           float(np.percentile(per_press[:, i], (1 + COVERAGE) / 2 * 100) * 1e3)],
                     "fitted": bool(presses.fitted[i]), "rim_past_table": bool(best["capped"][i]),
                     "reaches_support": bool(reaches[i]), "held_at_ball_limit": bool(past_ball[i]),
                     **({"share": float(depths["share"][j]), "share_at_search_end": bool(depths["at_end"][j])}
                        if presses.fitted[i] else {})}
                    for j, i in [(int(np.searchsorted(fitted, i)), i) for i in range(len(ids))]],
        "reaches_support": [ids[i] for i in np.flatnonzero(reaches)],
        "held_at_ball_limit": [ids[i] for i in np.flatnonzero(past_ball)],
        "ball_limit_m": deepest,
        "shares_at_search_end": int(depths["at_end"].sum()),
        "layers": [{"thickness_m": c["thickness_m"], "poisson_ratio": c["poisson_ratio"],
                    "loss": float(np.nanmean(c["losses"])), "shininess": c["shininess"],
                    "chosen_by_bootstrap": float(np.mean(boot == k))} for k, c in enumerate(layers)],
        "loss_at_rim_depths": float(np.nanmean(best["losses"])),
        "loss_at_fitted_depths": float(np.nanmean(np.nanmin(depths["losses"], axis=1))),
        "seconds": time.perf_counter() - t0,
    }
    if out is not None:
        from scenes.dataset import atomic_write_json

        atomic_write_json(Path(out), report)
    return report
