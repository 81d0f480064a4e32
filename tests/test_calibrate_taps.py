"""Calibration from taps (pbr_tactile.calibrate_taps): analytic cases with a synthetic
basis and synthetic contact changes; the dataset loader's refusals."""

from __future__ import annotations

import dataclasses
import json
import math

import numpy as np
import pytest

from pbr_tactile import calibrate as cal
from pbr_tactile import calibrate_taps as ct
from pbr_tactile import image_fit as imf
from pbr_tactile import image_model as im
from pbr_tactile import real_image as ri
from scenes import captures
from scenes.dataset import DatasetError
from tests.fake_basis import each_variant_traced


def _synthetic(camera, h=60, w=80):
    """A basis of smooth per-source images (each LED lights the rim near its azimuth, its
    leak the middle ring) and a contact-change maker: a dent at (rho, phi) on the
    membrane, lit from each LED's side (brighter on the side facing it, darker away)."""
    v, u = np.mgrid[0:h, 0:w].astype(float)
    s = h / camera.height
    cx, cy = (camera.cx + 0.5) * s - 0.5, (camera.cy + 0.5) * s - 0.5
    radius = camera.mask_radius_px * s
    rho, phi = np.hypot(u - cx, v - cy) / radius, np.arctan2(v - cy, u - cx)
    azimuths = (0.0, 2.1, 4.2)
    images, names = [], []
    for m, a in enumerate(azimuths):
        images.append((0.1 + rho**2) * (1.2 + np.cos(phi - a)) ** 2)
        images.append(np.exp(-((rho - 0.5) / 0.2) ** 2) * (1.1 + np.cos(phi - a)))
        names += [f"led{m}", f"led{m}_leak"]
    basis = np.stack(images, -1)

    def change(r0, phi0, turns=(0.0, 0.0, 0.0)):
        x0, y0 = cx + r0 * radius * math.cos(phi0), cy + r0 * radius * math.sin(phi0)
        blob = np.exp(-((u - x0) ** 2 + (v - y0) ** 2) / (2 * 2.5**2))
        out = []
        for a, turn in zip(azimuths, turns):
            # the dent's slope facing the LED brightens, the far one darkens: it turns with the LED
            dx, dy = math.cos(a + 4 * turn), math.sin(a + 4 * turn)
            lit = blob * (0.6 + 0.25 * ((u - x0) * dx + (v - y0) * dy) / 2.5)
            out += [lit * basis.mean(), 0.3 * lit * basis.mean()]
        return np.stack(out, -1)

    return basis, np.array(names), change


@pytest.mark.slow
def test_taps_recover_the_membranes_turn_that_one_image_cannot(camera):
    A, names, change = _synthetic(camera)
    circle = (321.0, 241.0, 236.0)
    model = im.ImageModel(A, names, camera, circle)
    # azimuths with a non-zero mean: one image sees only rotation + azimuth per LED
    truth = im.Nonlinear(rotation_rad=0.7, led_azimuth_rad=(0.12, 0.05, 0.16), leak=(0.3, 0.5, 0.2), scale=1.0,
                          shift_px=(0.0, 0.0), vignetting=(-0.3, 0.0), gamma=1.8)
    gains = np.array([[0.5, 0.2, 0.6], [0.1, 0.4, 0.5], [0.3, 0.1, 0.9]]) * 0.6
    offset, sat = (0.01, 0.02, 0.0), (1.0, 1.0, 1.0)
    real = model.render(truth, gains, offset, sat)
    sector = ri.sector_index(real.shape[:2], (40, 30))
    train = (sector % 2 == 0) & model.inside
    alone = imf.ImageFitter(model, real, train).search(rotations=6)
    assert alone.converged
    # without taps the membrane's turn is off by the azimuths' mean (0.11 rad)
    assert abs(math.remainder(alone.nl.tied().rotation_rad - 0.7, 2 * math.pi / 3)) > 0.08

    places = [(0.3, 0.2), (0.6, 1.4), (0.45, 2.9), (0.7, -1.9), (0.25, -0.6), (0.55, 0.9)]
    views, d = [], ct.AZIMUTH_STEP_RAD
    for p in places:
        # the real tap: the contact lit by the LEDs where they truly are
        tap = model.render(truth, gains, offset, sat, change=change(*p, truth.led_azimuth_rad))
        # the model: the change at -d, 0, +d as tap_changes renders it
        minus, zero, plus = (change(*p, (a, a, a)) for a in (-d, 0.0, d))
        views.append(imf.TapView(zero, tap, captures.contact_region(tap, real, model.inside),
                                 slope=(plus - minus) / (2 * d), curve=(plus - 2 * zero + minus) / (2 * d * d)))
    assert all(v.pixels.sum() >= captures.MIN_REGION for v in views)
    fitted = captures.split(len(views))
    fit = ct.fit_with_taps(model, real, train, [v for v, f in zip(views, fitted) if f], alone, common_turn=False)
    assert fit.converged
    assert abs(math.remainder(fit.nl.rotation_rad - 0.7, 2 * math.pi)) < 0.01
    np.testing.assert_allclose(fit.nl.led_azimuth_rad, truth.led_azimuth_rad, atol=0.02)
    held = ct.tap_scores(model, fit, [v for v, f in zip(views, fitted) if not f], real)
    before = ct.tap_scores(model, alone, [v for v, f in zip(views, fitted) if not f], real)
    assert held["change_r2"]["g"] > 0.99 and before["change_r2"]["g"] < 0.9
    # without the change's dependence on the azimuths the held-out taps are worse
    flat = [dataclasses.replace(v, slope=None, curve=None) for v in views]
    fit_flat = ct.fit_with_taps(model, real, train, [v for v, f in zip(flat, fitted) if f], alone, common_turn=False)
    held_flat = ct.tap_scores(model, fit_flat, [v for v, f in zip(flat, fitted) if not f], real)
    assert held_flat["mae"]["g"] > 10 * held["mae"]["g"]
    assert held["mae"]["g"] < 0.2 * before["mae"]["g"]


@pytest.mark.slow
def test_the_common_turn_ties_the_leds_and_recovers_the_rings_turn(camera):
    """Calibration's default with taps: one turn of the LED ring against the membrane."""
    A, names, change = _synthetic(camera)
    model = im.ImageModel(A, names, camera, (321.0, 241.0, 236.0))
    truth = im.Nonlinear(rotation_rad=-0.4, led_azimuth_rad=(0.1, 0.1, 0.1), leak=(0.3, 0.5, 0.2), scale=1.0,
                          shift_px=(0.0, 0.0), vignetting=(-0.3, 0.0), gamma=1.8)
    gains = np.array([[0.5, 0.2, 0.6], [0.1, 0.4, 0.5], [0.3, 0.1, 0.9]]) * 0.6
    real = model.render(truth, gains, (0.0, 0.0, 0.0), (1.0, 1.0, 1.0))
    train = (ri.sector_index(real.shape[:2], (40, 30)) % 2 == 0) & model.inside
    alone = imf.ImageFitter(model, real, train).search(rotations=6)
    d, views = ct.AZIMUTH_STEP_RAD, []
    for p in [(0.3, 0.2), (0.45, 2.9), (0.25, -0.6)]:
        tap = model.render(truth, gains, (0.0, 0.0, 0.0), (1.0, 1.0, 1.0), change=change(*p, truth.led_azimuth_rad))
        minus, zero, plus = (change(*p, (a, a, a)) for a in (-d, 0.0, d))
        views.append(imf.TapView(zero, tap, captures.contact_region(tap, real, model.inside),
                                 slope=(plus - minus) / (2 * d), curve=(plus - 2 * zero + minus) / (2 * d * d)))
    fit = ct.fit_with_taps(model, real, train, views, alone)
    assert fit.converged and len(set(fit.nl.led_azimuth_rad)) == 1
    assert abs(math.remainder(fit.nl.rotation_rad + 0.4, 2 * math.pi)) < 0.01
    assert fit.nl.led_azimuth_rad[0] == pytest.approx(0.1, abs=0.01)


@pytest.mark.slow
def test_taps_choose_the_grid_point_one_image_cannot(camera, spec, monkeypatch):
    """Two grid points whose no-contact images are the same but whose contacts shade
    differently: the no-contact fit cannot rank them, the taps choose the true one."""
    pytest.importorskip("mitsuba")
    A, names, change = _synthetic(camera)
    basis = {"mean": A, "variance": np.zeros_like(A), "names": names, "response": np.ones((len(names), 3))}
    monkeypatch.setattr(cal, "emitter_basis", each_variant_traced(lambda *args, **kwargs: basis))
    places = [(0.3, 0.2), (0.6, 1.4), (0.45, 2.9), (0.7, -1.9)]

    def changes(spec_, mesh, camera_, effects, film, taps, *args, **kwargs):
        # at the wrong point the contact's shading is half as strong
        k = 1.0 if effects.scattering_per_m == 50.0 else 0.5
        stack = np.stack([k * change(*places[int(i[1:])]) for i in taps.ids])
        return {"change": stack, "slope": np.zeros_like(stack), "curve": np.zeros_like(stack)}

    monkeypatch.setattr(ct, "tap_changes", changes)
    model = im.ImageModel(A, names, camera, None)
    truth = im.Nonlinear(rotation_rad=0.7, led_azimuth_rad=(0.0, 0.0, 0.0), leak=(0.3, 0.5, 0.2), scale=1.0,
                          shift_px=(0.0, 0.0), vignetting=(-0.3, 0.0), gamma=1.8)
    gains = np.array([[0.5, 0.2, 0.6], [0.1, 0.4, 0.5], [0.3, 0.1, 0.9]]) * 0.6
    k = camera.height // A.shape[0]
    up = lambda image: np.repeat(np.repeat(image, k, axis=0), k, axis=1)  # noqa: E731
    real = up(model.render(truth, gains, (0.0, 0.0, 0.0), (1.0, 1.0, 1.0)))
    images = np.stack([up(model.render(truth, gains, (0.0, 0.0, 0.0), (1.0, 1.0, 1.0), change=change(*p)))
                       for p in places])
    depths = np.zeros(images.shape[:3])
    taps = captures.RealTaps(images, depths, depths[0], [f"t{i}" for i in range(len(places))])
    grid = {"absorption_per_m": (20.0,), "scattering_per_m": (10.0, 50.0)}
    result = cal.calibrate_background(real, spec, None, camera, film=(A.shape[1], A.shape[0]), grid=grid,
                                      bootstrap=0, taps=taps)
    # without taps the two points tie and the first would be kept
    losses = [g["loss"] for g in result.report["grid"]]
    assert abs(losses[0] - losses[1]) <= 1e-9 * max(losses)
    assert result.report["best_effects"] == {"absorption_per_m": 20.0, "scattering_per_m": 50.0}
    joint = result.report["taps"]["grid"]
    assert [g["effects"]["scattering_per_m"] for g in joint] == [10.0, 50.0]
    assert joint[1]["loss"] < 0.1 * joint[0]["loss"]


def test_tap_changes_without_azimuths_and_with_known_changes_render_less(spec, monkeypatch):
    calls = []

    def basis(unit, mesh, camera, effects, film, *args, depth=None, **kwargs):
        calls.append(depth is not None)
        value = 0.0 if depth is None else float(depth.mean())
        return {"mean": np.full((3, 4, 2), value), "names": np.array(["led0", "led0_leak"])}

    monkeypatch.setattr(ct, "emitter_basis", basis)
    depths = np.stack([np.full((6, 8), d) for d in (1.0, 2.0, 3.0)])
    taps = captures.RealTaps(np.zeros((3, 6, 8, 3)), depths, np.zeros((6, 8)), ["a", "b", "c"])
    no_contact = basis(None, None, None, None, None)
    calls.clear()
    flat = ct.tap_changes(spec, None, None, None, (4, 3), taps, no_contact, 1, 1, 1, 0, azimuths=False)
    assert flat["slope"] is None and flat["curve"] is None and calls == [True] * 3
    np.testing.assert_allclose(flat["change"][:, 0, 0, 0], [1.0, 2.0, 3.0])
    calls.clear()
    known = {1: np.full((3, 4, 2), 7.0)}
    full = ct.tap_changes(spec, None, None, None, (4, 3), taps, no_contact, 1, 1, 1, 0, known=known)
    # two turned no-contact bases, three taps at each turn, less the one known at zero
    assert calls.count(True) == 8 and calls.count(False) == 2
    assert full["change"][1, 0, 0, 0] == 7.0 and full["slope"].shape == (3, 3, 4, 2)


def test_contact_region_ignores_noise_and_finds_the_dent():
    rng = np.random.default_rng(0)
    bg = np.full((30, 40, 3), 0.5)
    tap = bg + rng.normal(0, 0.005, bg.shape)
    inside = np.ones((30, 40), bool)
    assert not captures.contact_region(tap, bg, inside).any()
    tap[10:14, 20:25] += 0.1
    region = captures.contact_region(tap, bg, inside)
    assert region[10:14, 20:25].all() and region.sum() < 120


def test_real_taps_refuse_bad_arrays():
    good = dict(images=np.zeros((2, 6, 8, 3)), depths=np.zeros((2, 6, 8)), ref_depth=np.zeros((6, 8)), ids=["a", "b"])
    captures.RealTaps(**good)
    for change, message in [({"images": np.zeros((2, 6, 8))}, r"images must be \(T, H, W, 3\)"),
                            ({"depths": np.zeros((2, 5, 8))}, "must match"),
                            ({"ids": ["a"]}, "1 ids for 2 images"),
                            ({"depths": np.full((2, 6, 8), np.nan)}, "must be finite"),
                            ({"discs": np.zeros((2, 2))}, r"discs must be \(2, 3\)")]:
        with pytest.raises(ValueError, match=message):
            captures.RealTaps(**{**good, **change})


def test_a_real_dataset_without_depth_or_protocol_is_refused(tmp_path, spec, camera):
    from scenes.dataset import DatasetWriter, write_sample_files

    writer = DatasetWriter(tmp_path, {"source": "real", "sensor": dataclasses.asdict(spec), "protocol": {},
                                      "renderer": {}})
    files = write_sample_files(tmp_path, "000000_sphere", np.zeros((camera.height, camera.width, 3)), None, {})
    writer.append({"id": "000000_sphere", "tap_index": 0, "replica": 0, **files})
    with pytest.raises(DatasetError, match="need protocol.json to replay"):
        captures.load_real_taps(tmp_path, spec, camera)
    (tmp_path / "protocol.json").write_text(json.dumps({"version": 1, "name": "x", "seed": 0, "taps": []}))
    with pytest.raises(DatasetError, match="tap_index 0, not a tap of its protocol.json"):
        captures.load_real_taps(tmp_path, spec, camera)


# -- end to end, with Mitsuba and the MuJoCo rig ------------------------------------------------

@pytest.mark.slow
def test_calibrate_a_real_dataset_with_taps_end_to_end(tmp_path, spec, camera):
    pytest.importorskip("mitsuba")
    pytest.importorskip("mujoco")
    from pbr_tactile.calibrate_bench import protocol_taps, virtual_taps
    from scenes.profile import turn_leds
    from scenes.cli import main
    from scenes.dataset import DatasetWriter, write_sample_files
    from scenes.geometry import membrane_mesh
    from scenes.profile import load_profile
    from scenes.protocol import base_protocol

    mesh = membrane_mesh(spec)
    film, photons, spp = (80, 60), 1 << 13, 2
    effects = cal.Effects(core_light_leak=0.5)
    taps, depths, ref_depth = protocol_taps(spec, mesh, 4)
    # the two widest contacts (a tip tap is a few pixels at this film)
    widest = sorted(np.argsort([-(d < ref_depth - 1e-6).sum() for d in depths])[:2])
    taps, depths = [taps[i] for i in widest], depths[widest]
    # a "real" sensor: the reference with another seed, its LEDs turned and its membrane too
    truth = im.Nonlinear(0.3, (0.0, 0.0, 0.0), (0.2, 0.2, 0.2), 1.0, (0.0, 0.0), (-0.2, 0.0), 2.0)
    unit = turn_leds(spec, (0.05, -0.05, 0.0))
    basis = cal.emitter_basis(unit, mesh, camera, effects, film, photons, spp, 2, seed=7)
    model = im.ImageModel(basis["mean"], basis["names"], camera, (camera.cx, camera.cy, camera.mask_radius_px))
    gains = np.full((3, 3), 0.5 / np.percentile(basis["mean"], 90))
    background = np.repeat(np.repeat(model.render(truth, gains, (0, 0, 0), (1, 1, 1)), 8, axis=0), 8, axis=1)
    real, _ = virtual_taps(ct.tap_spec(unit), basis["names"], mesh, camera, effects, truth, gains, depths, ref_depth,
                           film, photons, spp, 7, True, ["a", "b"])

    protocol = base_protocol(spec, mesh, ["sphere"])
    index = [protocol.taps.index(t) for t in taps]
    writer = DatasetWriter(tmp_path / "real", {"source": "real", "sensor": dataclasses.asdict(spec),
                                               "protocol": {}, "renderer": {}}, protocol.to_dict())
    writer.write_background(background)
    ids = []
    for k, (image, depth) in enumerate(zip(real.images, depths)):
        sid = f"{k:06d}_sphere"
        # the first with its depth map, the second without (a real capture): replayed on the rig
        files = write_sample_files(writer.root, sid, image, depth if k == 0 else None, {})
        writer.append({"id": sid, "tap_index": index[k], "replica": 0, "object": "sphere", **files})
        ids.append(sid)

    loaded = captures.load_real_taps(writer.root, spec, camera)
    assert loaded.ids == ids
    np.testing.assert_allclose(loaded.depths[1], depths[1], atol=1e-6)  # the replay is the same press
    out = tmp_path / "out"
    code = main(["calibrate", str(writer.root), "--out", str(out), "--width", "80", "--photons", str(photons),
                 "--spp", str(spp), "--bootstrap", "1", "--grid", "absorption_per_m=20", "--grid",
                 "scattering_per_m=50"])
    report = json.loads((out / "report.json").read_text())
    assert report["data"].endswith("and 2 of its taps")
    section = report["taps"]
    assert sorted(section["fitted"] + section["judged"] + section["without_contact"]) == ids
    assert section["fitted"] == ids[:1]
    assert set(section["heldout"]) == {"mae", "change_r2", "pixels"}
    assert code == 0, report  # converged: the profile is written, with the fast path's LED constants
    profile = load_profile(out / "profile.toml", spec)
    assert profile.fit["data"] == "one no-contact image and 2 taps"
    fast = report["fast_path"]["taps"]
    assert len(profile.phong["leds"]) == 3 and profile.phong["shininess"] == fast["shininess"]
    assert set(fast["heldout"]["change_r2"]) == {"r", "g", "b"}
    assert "Taps" in (out / "report.html").read_text()
    assert set(report["heldout_r2"]) == {"r", "g", "b"} and set(report["saturated"]) == {"r", "g", "b"}
    assert (out / "residual.npy").exists() and (out / "residuals_figure.png").exists()
    assert profile.camera.image_circle is not None

    # the profile renders: a frame of the calibrated unit with the reference (one linear
    # image per source) and with the fast path (its fitted LED constants), both cut by the circle
    from scenes.images import read_rgb

    np.save(tmp_path / "ref.npy", ref_depth)
    np.save(tmp_path / "tap.npy", depths[1])
    code = main(["reference", str(tmp_path / "tap.npy"), "--ref-depth", str(tmp_path / "ref.npy"), "--profile",
                 str(out / "profile.toml"), "--width", "40", "--height", "30", "--spp", "2", "--passes", "2",
                 "--photons", "4096", "--out", str(tmp_path / "frame")])
    assert code == 0
    frame = read_rgb(tmp_path / "frame.png")
    assert frame.shape == (30, 40, 3) and frame[15, 20].max() > 0 and frame[0, 0].max() == 0
    assert np.load(tmp_path / "frame.npy").shape == (30, 40, 6)
    assert main(["render", str(tmp_path / "tap.npy"), "--profile", str(out / "profile.toml"), "-o",
                 str(tmp_path / "fast.png")]) == 0
    fast_frame = read_rgb(tmp_path / "fast.png")
    assert fast_frame[0, 0].max() == 0 and fast_frame[240, 320].max() > 0

    # the same dataset's background alone (the fast path's background term is judged beside it)
    code = main(["calibrate", "--background-only", str(writer.root / "background.png"), "--out", str(tmp_path / "bg"),
                 "--width", "80", "--photons", str(photons), "--spp", str(spp), "--bootstrap", "0", "--grid",
                 "absorption_per_m=20", "--grid", "scattering_per_m=50"])
    alone = json.loads((tmp_path / "bg" / "report.json").read_text())
    assert alone["taps"] is None and "taps" not in alone["fast_path"]
    assert alone["fast_path"]["heldout_r2"]["g"] > alone["fast_path"]["solid"]["heldout_r2"]["g"]
    assert code == (0 if alone["converged"] else 1)
    # --taps is refused without a dataset, and out of range
    assert main(["calibrate", "--background-only", str(writer.root / "background.png"), "--taps", "3", "--out",
                 str(out)]) == 1
    assert main(["calibrate", str(writer.root), "--taps", "11", "--out", str(out)]) == 1
