"""The joint fit of the bonded layer and the presses' depths (phong_reference.elastic_fit),
the import at its depths, the fast path calibrated and rendered under it, and Taxim's own
depth setting chosen on the fitted half (studies.compare.taxim.choose_rim_share)."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from phong_reference import elastic_fit as ef


def test_the_layer_chosen_is_the_least_summed_loss_and_its_bootstrap_spreads_with_the_presses():
    rng = np.random.default_rng(0)
    # three candidates over 40 presses: the second is best by a clear margin on every press
    clear = np.stack([np.full(40, 0.05), np.full(40, 0.03), np.full(40, 0.06)]) + rng.normal(0, 1e-3, (3, 40))
    best, boot = ef.choose(clear, rng, 500)
    assert best == 1 and np.all(boot == 1)
    # two candidates that tie on average, each better on half the presses: resamplings disagree
    tied = np.stack([np.r_[np.full(20, 0.02), np.full(20, 0.04)], np.r_[np.full(20, 0.04), np.full(20, 0.02)]])
    tied += rng.normal(0, 1e-4, tied.shape)
    _, boot = ef.choose(tied, rng, 500)
    assert 0.2 < np.mean(boot == 0) < 0.8


def test_a_parabola_s_least_is_found_between_its_neighbours():
    x = np.array([0.8, 0.9, 1.0, 1.1, 1.2])
    y = (x - 0.97) ** 2 + 1.0
    assert ef._parabola_min(x, y, 2) == pytest.approx(0.97)
    # a least beyond the neighbours is held at them; a flat or concave triple keeps the middle
    assert ef._parabola_min(x, (x - 0.5) ** 2, 1) == pytest.approx(0.8)
    assert ef._parabola_min(x, -(x - 1.0) ** 2, 2) == pytest.approx(1.0)
    assert ef.interval(np.arange(101.0), 0.9) == pytest.approx([5.0, 95.0])


def test_a_rim_s_depth_at_a_share():
    from scenes.imports import RIM_CAP, ball_depth, rim_depth

    R, pixel = 2e-3, 0.1245e-3
    d, capped = rim_depth(13.5, pixel, R)
    assert d == pytest.approx(ball_depth(13.5 * pixel, R)) and not capped
    d, capped = rim_depth(13.5, pixel, R, 0.9)
    assert d == pytest.approx(ball_depth(15.0 * pixel, R)) and not capped
    d, capped = rim_depth(15.5, pixel, R, 0.9)  # past the ball: set to RIM_CAP of it, and said
    assert capped and d == pytest.approx(ball_depth(RIM_CAP * R, R))


#: A model's rim-to-depth relation as a joint fit reports it: [depths, rims] mm.
RELATION_MM = [[0.5, 1.0, 1.5, 1.9], [1.0, 1.4, 1.7, 1.9]]


def _fit_report(k=0.9, h=5e-3, nu=0.49, depths=None):
    depths = depths or {"frame_0.jpg": 1.234}
    return {"elastic": {"model": "bonded", "thickness_m": h, "poisson_ratio": nu}, "depth_share": {"k": k},
            "ball_limit_m": 1.96e-3, "relation_mm": RELATION_MM,
            "presses": [{"name": n, "depth_mm": d, "fitted": True} for n, d in depths.items()]}


def test_an_import_at_fitted_depths_keeps_the_fitted_and_gives_the_rest_the_rule(tmp_path):
    pytest.importorskip("ContactMechanics", reason="the elastic solid model needs the contact extra")
    from scenes import imports, press_sets
    from scenes.dataset import read_meta, read_samples
    from test_import_capture import run_import, write_pack

    pack = write_pack(tmp_path / "dataPack.npz")
    pixel = press_sets.DEFAULTS["taxim"]["pixel_m"]
    summary = run_import(tmp_path, pack, out="fitted", depth="fitted", fit=_fit_report())
    assert summary["depth"] == "fitted"
    assert read_meta(tmp_path / "fitted")["import"]["elastic_fit"] == {
        "thickness_m": 5e-3, "poisson_ratio": 0.49, "depth_share": 0.9, "fitted_presses": 1}
    for r in read_samples(tmp_path / "fitted"):
        if r["source_name"] == "frame_0.jpg":
            assert r["measured_depth"] == pytest.approx(1.234e-3) and r["depth_source"] == "fitted"
        else:
            a = r["contact_edge_px"] * pixel * 1e3
            rule = min(0.9 * np.interp(a * a, np.square(RELATION_MM[1]), RELATION_MM[0]) * 1e-3, 1.96e-3)
            assert r["measured_depth"] == pytest.approx(rule, rel=1e-9) and r["depth_source"] == "rule"
    with pytest.raises(ValueError, match="takes the joint fit's report"):
        run_import(tmp_path, pack, out="bad1", depth="fitted")
    with pytest.raises(ValueError, match="takes the joint fit's report"):
        run_import(tmp_path, pack, out="bad2", depth="elastic", fit=_fit_report())
    with pytest.raises(ValueError, match="relation_mm must be"):
        run_import(tmp_path, pack, out="bad6", depth="fitted", fit={**_fit_report(), "relation_mm": [[1.0]]})
    with pytest.raises(ValueError, match="must hold elastic.thickness_m"):
        run_import(tmp_path, pack, out="bad3", depth="fitted", fit={"elastic": {}})
    with pytest.raises(ValueError, match="Poisson's ratio must lie in"):
        run_import(tmp_path, pack, out="bad4", depth="fitted", fit=_fit_report(nu=0.7))
    twice = write_pack(tmp_path / "twice.npz", names=np.array(["a.jpg", "a.jpg", "b.jpg"]))
    with pytest.raises(ValueError, match="names repeat"):
        run_import(tmp_path, twice, out="bad5", depth="fitted", fit=_fit_report())
    assert not any((tmp_path / f"bad{i}").exists() for i in range(1, 7))


def test_a_profile_s_elastic_entry_is_the_dent_it_renders_with(tmp_path):
    pytest.importorskip("ContactMechanics", reason="the elastic solid model needs the contact extra")
    from phong_reference.plugin import elastic_layer, make_layer, options_from
    from scenes.camera import Camera
    from scenes.elastic_solid import BondedLayer
    from scenes.spec_read import load_spec

    from test_import_capture import GELSIGHT

    spec = load_spec(GELSIGHT).at_resolution(80, 60)
    camera = Camera.from_spec(spec)
    layer = elastic_layer({"model": "bonded", "thickness_m": 5e-3, "poisson_ratio": 0.3}, spec, camera)
    assert isinstance(layer, BondedLayer) and (layer.thickness, layer.poisson) == (5e-3, 0.3)
    for bad, match in (({"model": "layer", "thickness_m": 5e-3, "poisson_ratio": 0.3}, "must be 'bonded'"),
                       ({"model": "bonded", "poisson_ratio": 0.3}, "must hold model, thickness_m"),
                       ({"model": "bonded", "thickness_m": -1.0, "poisson_ratio": 0.3}, "thickness must be"),
                       ({"model": "bonded", "thickness_m": 5e-3, "poisson_ratio": 0.6}, "Poisson's ratio")):
        with pytest.raises(ValueError, match=match):
            elastic_layer(bad, spec, camera)

    class Profile:
        phong = {"elastic": {"model": "bonded", "thickness_m": 4e-3, "poisson_ratio": 0.45}}

    # a profile's model is used where the options name none; a name given wins
    assert options_from({"profile": "p.toml"})["elastic_model"] is None
    assert options_from({"profile": "p.toml", "elastic": "published"})["elastic_model"] == "published"
    assert make_layer(None, Profile(), spec, None, camera).thickness == 4e-3
    assert make_layer(None, None, spec, None, camera) is None
    assert make_layer("published", Profile(), spec, None, camera) is None


def test_calibrate_refuses_an_elastic_fit_that_is_not_one(tmp_path):
    from pbr_tactile.calibrate_cli import elastic_entry

    path = tmp_path / "fit.json"
    path.write_text(json.dumps(_fit_report()))
    assert elastic_entry(path) == {"model": "bonded", "thickness_m": 5e-3, "poisson_ratio": 0.49}
    path.write_text("{not json")
    with pytest.raises(ValueError, match="not a joint fit's report"):
        elastic_entry(path)
    with pytest.raises(ValueError, match="not a joint fit's report"):
        elastic_entry(tmp_path / "missing.json")


class _DepthPeer:
    """A stand-in for Taxim: each press's disc is lit by how far its depth is from 1.1 mm."""

    def render_presses(self, centres, depths, ball_radius_m, pixel_m, shape):
        from scenes.captures import contact_disc

        out = np.zeros((len(centres),) + tuple(shape) + (3,))
        for i, (c, d) in enumerate(zip(centres, depths)):
            out[i][contact_disc(shape, c, 10.0)] = 0.5 + 100.0 * abs(d - 1.1e-3)
        return out


def test_taxim_s_rim_share_is_the_one_that_fits_the_fitted_presses_best():
    from scenes.captures import contact_disc
    from scenes.imports import ball_depth
    from studies.compare.taxim import choose_rim_share, share_depths

    R, pixel = 2e-3, 0.1245e-3
    # rims at 0.85 of the contact whose chord is 1.1 mm deep
    a = math.sqrt(R * R - (R - 1.1e-3) ** 2)
    edge = 0.85 * a / pixel
    presses = {"centres": np.array([[40.0, 30.0], [80.0, 60.0]]), "radii": np.array([10.0, 10.0]),
               "edges": np.array([edge, edge]), "ball_radius_m": R, "pixel_m": pixel}
    assert share_depths(presses, 0.85) == pytest.approx([1.1e-3, 1.1e-3])
    assert share_depths(presses, 1.0) == pytest.approx([ball_depth(edge * pixel, R)] * 2)
    real = np.zeros((2, 90, 120, 3))
    for i, c in enumerate(presses["centres"]):
        real[i][contact_disc((90, 120), c, 10.0)] = 0.5
    share, losses = choose_rim_share(_DepthPeer(), presses, real, np.zeros((90, 120, 3)))
    assert share == 0.85 and losses[0.85] == pytest.approx(0.0, abs=1e-12)
    assert all(v > 0 for k, v in losses.items() if k != 0.85)


@pytest.mark.slow
def test_the_joint_fit_recovers_the_layer_and_depths_presses_were_rendered_with(tmp_path, mujoco_gl):
    """Twelve presses rendered by the fast path under a bonded layer 3.5 mm thick with ratio
    0.49 at known depths, packed as Taxim packs them (8-bit), imported at the spec's layer
    (2.5 mm, 0.5), the fast path calibrated on them, and the joint fit run: it finds the
    layer, a share near 1, and the depths."""
    pytest.importorskip("ContactMechanics", reason="the elastic solid model needs the contact extra")
    from pbr_tactile.calibrate_capture import calibrate_capture
    from phong_reference import plugin as phong
    from phong_reference.bake import bake
    from phong_reference.render import Renderer, light_vectors
    from scenes import imports, press_sets
    from scenes.camera import Camera
    from scenes.elastic_solid import BondedLayer
    from scenes.geometry import membrane_mesh
    from scenes.rig import tap_depths
    from scenes.spec_read import load_spec
    from test_import_capture import GELSIGHT

    h_true, nu_true = 3.5e-3, 0.49
    defaults = press_sets.DEFAULTS["taxim"]
    spec = load_spec(GELSIGHT)
    unit, _ = imports.capture_spec(spec, 160, 120, defaults["pixel_m"])
    camera, mesh = Camera.from_spec(unit), membrane_mesh(unit)
    rng = np.random.default_rng(3)
    centres = np.stack([rng.uniform(35, 125, 12), rng.uniform(30, 90, 12)], axis=1)
    depths = rng.uniform(0.7e-3, 1.4e-3, 12)
    taps = [imports.press_tap(i, "ball_4mm", unit, mesh, camera, c, d) for i, (c, d) in enumerate(zip(centres, depths))]
    replay = tap_depths(unit, taps, mesh)
    ref = next(replay)[0]
    maps = [d for d, _ in replay]
    replay.close()
    L = light_vectors(bake(mesh, camera, unit.leds, "linear"))
    renderer = Renderer(unit, camera, ref, L, np.full((120, 160, 3), 0.45, np.float32),
                        BondedLayer(unit, camera, h_true, nu_true))

    def bgr8(a):
        return (np.clip(a, 0, 1) * 255).round().astype(np.uint8)[..., ::-1]

    names = [f"p{i}" for i in range(12)]
    np.savez(tmp_path / "dataPack.npz", f0=bgr8(renderer.render(ref)),
             imgs=np.stack([bgr8(renderer.render(m)) for m in maps]), touch_center=centres,
             touch_radius=np.full(12, 12.0), names=np.array(names))
    imports.import_capture(press_sets.read_taxim(tmp_path / "dataPack.npz"), tmp_path / "capture", spec,
                           defaults["ball_m"], defaults["pixel_m"], depth="elastic")
    calibrate_capture(tmp_path / "capture", tmp_path / "calibrated",
                      lambda *a: phong.calibrate(*a, fields=("linear",)), fast_taps=0, fast_only=True, progress=False)
    report = ef.fit(tmp_path / "capture", tmp_path / "calibrated" / "profile.toml", tmp_path / "fit.json",
                    thicknesses=(1.5e-3, 3.5e-3, 7e-3), ratios=(0.3, 0.49))
    assert report["elastic"] == {"model": "bonded", "thickness_m": h_true, "poisson_ratio": nu_true}
    assert json.loads((tmp_path / "fit.json").read_text())["elastic"] == report["elastic"]
    lo, hi = report["depth_share"]["interval"]
    assert lo <= 1.0 <= hi and abs(report["depth_share"]["k"] - 1) < 0.05
    truth = dict(zip(names, depths))
    errors = {p["name"]: p["depth_mm"] * 1e-3 / truth[p["name"]] - 1 for p in report["presses"]}
    fitted = {p["name"] for p in report["presses"] if p["fitted"]}
    # measured: every press within 8.2 % (the deepest), the median 1.6 %
    assert max(abs(errors[n]) for n in fitted) < 0.1
    assert max(abs(e) for n, e in errors.items() if n not in fitted) < 0.1
    assert np.median(np.abs(list(errors.values()))) < 0.03
    assert report["reaches_support"] == [] and report["loss_at_fitted_depths"] <= report["loss_at_rim_depths"]


def test_the_joint_fit_refuses_layers_out_of_physical_range_before_any_work(tmp_path):
    with pytest.raises(ValueError, match="thickness must be a finite length > 0"):
        ef.fit(tmp_path / "none", tmp_path / "none.toml", thicknesses=(2.5e-3, 0.0))
    with pytest.raises(ValueError, match=r"Poisson's ratio must lie in \[0, 0.5\]"):
        ef.fit(tmp_path / "none", tmp_path / "none.toml", ratios=(0.3, 0.6))
    assert not any(tmp_path.iterdir())
