"""The Sim2Real learning study (studies/sim2real): its data, effects, scoring, models and
the whole pipeline on a slice (scikit-learn's ridge, which CI has; the torch models skip
without torch, saying why)."""

from __future__ import annotations

import importlib.util
import json
import math
from dataclasses import replace

import numpy as np
import pytest

from scenes.camera import project
from scenes.indenters import INDENTERS
from studies.sim2real import augment, data, features, pipeline, plan, study, summary
from studies.sim2real.learn import Training, need, train
from studies.sim2real.plan import Run, Settings

TORCH = importlib.util.find_spec("torch") is not None
needs_torch = pytest.mark.skipif(not TORCH, reason="torch is not installed (pip install '.[sim2real]')")
needs_sklearn = pytest.mark.skipif(importlib.util.find_spec("sklearn") is None,
                                   reason="scikit-learn is not installed (pip install '.[learn]')")


# --- analytic pieces ----------------------------------------------------------------------

def test_split_is_stratified_seeded_and_disjoint():
    labels = np.repeat(np.arange(8), 18)
    train_a, test_a = data.split(labels, 3)
    train_b, test_b = data.split(labels, 3)
    assert np.array_equal(test_a, test_b) and np.array_equal(train_a, train_b)
    assert not set(train_a) & set(test_a) and len(train_a) + len(test_a) == len(labels)
    assert np.bincount(labels[test_a]).tolist() == [4] * 8  # round(0.2 * 18) of each indenter
    assert not np.array_equal(data.split(labels, 4)[1], test_a)


def test_patches_are_centred_on_the_contact_and_padded_off_the_image():
    images = np.zeros((2, 120, 160, 3), np.uint8)
    images[0, 60, 100] = 255  # array pixel (row 60, col 100) = full-res centre (4 * 100 + 1.5, 4 * 60 + 1.5)
    pixel = np.array([[401.5, 241.5], [0.0, 0.0]])
    out = features.patches(images, pixel, 4, 32)
    assert out.shape == (2, 32, 32, 3)
    assert out[0, 16, 16, 0] == 255 and out[0].sum() == 3 * 255
    images[1] = 7
    corner = features.patches(images, pixel, 4, 32)[1]
    assert corner[:15, :15].max() == 0 and corner[17:, 17:].min() == 7  # zero outside the image


def test_full_inputs_average_blocks():
    images = np.arange(2 * 4 * 4 * 3, dtype=np.uint8).reshape(2, 4, 4, 3)
    out = features.full_inputs(images, 2)
    assert out.shape == (2, 2, 2, 3)
    assert out[0, 0, 0, 0] == round(np.mean(images[0, :2, :2, 0]))


def test_membrane_lookup_inverts_the_camera_model(spec, camera):
    from scenes.camera import cast_rays
    from scenes.geometry import membrane_mesh

    lookup = data.MembraneLookup(spec)
    samples = cast_rays(membrane_mesh(spec), camera)
    rng = np.random.default_rng(0)
    points = samples.points[rng.choice(len(samples.points), 200, replace=False)]
    back = lookup(project(points, camera))
    error = np.linalg.norm(back - points, axis=1)
    assert np.median(error) < 0.1e-3 and error.max() < 0.5e-3  # half a pixel on the membrane
    # a pixel off the image circle is moved onto the membrane, not left in the void
    far = lookup(np.array([[0.0, 0.0]]))[0]
    assert np.isfinite(far).all() and far[2] > 0


def test_gap_closed_is_the_share_of_the_r2r_gap():
    settings = Settings(model="ridge", seeds=2, trainings=("none", "diagnosed"))

    def res(acc, mm, which):
        return {which: {"accuracy": acc}}, {which: {"localisation_mm": mm}}

    results = {}
    values = {("real", "none"): (80.0, 5.0), ("base_plane", "none"): (40.0, 15.0),
              ("base_plane", "diagnosed"): (60.0, 10.0)}
    for seed in range(2):
        for (train_set, training), (acc, mm) in values.items():
            which = "own" if train_set == "real" else "real"
            for inp in plan.INPUTS:
                c, loc = res(acc + seed, mm, which)
                results[Run(train_set, training, inp, "classification", seed).name] = c
                results[Run(train_set, training, inp, "localisation", seed).name] = loc
                if which == "real":
                    results[Run(train_set, training, inp, "classification", seed).name]["own"] = {"accuracy": acc}
                    results[Run(train_set, training, inp, "localisation", seed).name]["own"] = {"localisation_mm": mm}
    s = summary.summarise(results, settings, ["base_plane"], ["base_plane"])
    closed = s["gap_closed"]["diagnosed"]["base"]["full"]
    assert closed["classification"]["share"] == pytest.approx(0.5)  # (60 - 40) / (80 - 40)
    assert closed["localisation"]["share"] == pytest.approx(0.5)  # (10 - 15) / (5 - 15): lower is better
    assert s["gap_closed"]["none"]["base"]["full"]["classification"]["share"] == 0.0
    assert s["s2r_by_training"]["diagnosed"]["base"]["full"]["accuracy"]["mean"] == pytest.approx(60.5)
    assert s["r2r"]["base"]["full"]["localisation_mm"]["mean"] == pytest.approx(5.0)


def test_interval_is_a_t_interval():
    iv = summary.interval([1.0, 2.0, 3.0])
    assert iv["mean"] == 2.0
    assert iv["interval"][1] - 2.0 == pytest.approx(4.302652729911275 * 1.0 / math.sqrt(3))


# --- effects ----------------------------------------------------------------------------------

def test_diagnosed_params_read_the_last_selection_step():
    report = {"selection": [{"params": {"blur_noise": {"sigma_px": 1.0}}},
                            {"params": {"blur_noise": {"sigma_px": 1.2}, "vignetting": {"a": 0.1}}}]}
    assert augment.diagnosed_params(report) == {"blur_noise": {"sigma_px": 1.2}, "vignetting": {"a": 0.1}}
    assert augment.diagnosed_params({"selection": []}) == {}
    with pytest.raises(ValueError, match="params"):
        augment.diagnosed_params({"selection": [{"params": None}]})
    with pytest.raises(ValueError, match="unknown effects"):
        augment.check_effects({"glare": {}})


def test_random_params_stay_in_their_ranges():
    from studies.gap.effects import catalogue

    cat = catalogue(3, 4.0)
    rng = np.random.default_rng(1)
    draws = [augment.random_params(cat, rng) for _ in range(200)]
    assert set(draws[0]) == {n for n, e in cat.items() if e.params}
    for name, effect in cat.items():
        for p in effect.params:
            v = np.array([d[name][p.name] for d in draws])
            assert v.min() >= min(p.low, p.identity) - 1e-12 and v.max() <= max(p.high, p.identity) + 1e-12
            if p.high > p.low:
                assert v.std() > 0  # drawn, not fixed


# --- the compact renderer and the arrays --------------------------------------------------

@pytest.fixture(scope="module")
def sim_pair(tmp_path_factory, spec, mujoco_gl):
    """The same few base taps of two indenters as a compact fast-path dataset and as the
    phong plugin's own."""
    from dataclasses import replace

    from phong_reference import plugin as phong
    from scenes.body import checked_membrane
    from scenes.protocol import make_protocol
    from scenes.generate import generate
    from studies.sim2real import plugin

    protocol = make_protocol("base", spec, checked_membrane(spec), ("sphere", "cone"))
    protocol = replace(protocol, taps=protocol.taps[::3])
    base = tmp_path_factory.mktemp("s2r")
    for name, renderer in (("sim", plugin), ("phong", phong)):
        generate(base / name, spec, protocol, renderer=renderer, options={"field": "plane"}, workers=1,
                 progress=False)
    return base / "sim", base / "phong"


@pytest.fixture(scope="module")
def sim_root(sim_pair):
    return sim_pair[0]


def test_compact_dataset_keeps_the_phong_image_and_a_block_indentation(sim_pair, spec, mesh, camera):
    from phong_reference import plugin as phong
    from scenes.dataset import read_meta, read_samples
    from scenes.generate import Job, runner
    from studies.sim2real import plugin

    compact, full = sim_pair
    records = {r["id"]: r for r in read_samples(compact)}
    assert records and all("depth" not in r and r["indentation"].startswith("indentation/") for r in records.values())
    assert not any((compact / "depth").glob("*"))  # the writer makes the folder; nothing goes in it
    assert read_meta(compact)["renderer"]["depth_factor"] == 4
    # the no-contact depth both datasets were rendered against: the same rig's
    ref = runner(Job(spec, phong.make_renderer, {"field": "plane"}, ("sphere", "cone"))).ref_depth
    for r in read_samples(full):
        c = records[r["id"]]
        assert (compact / c["image"]).read_bytes() == (full / r["image"]).read_bytes()  # the phong image
        ind = np.load(compact / c["indentation"])
        assert ind.shape == (camera.height // 4, camera.width // 4) and ind.max() > 0.5e-3  # a pressed contact
        assert np.array_equal(ind, plugin.indentation(np.load(full / r["depth"]), ref, 4))
    with pytest.raises(ValueError, match="depth_factor"):
        plugin.prepare(spec, mesh, camera, {"depth_factor": 0})


def test_indentation_is_the_block_mean_of_the_thresholded_difference():
    from studies.sim2real.plugin import indentation

    ref = np.full((8, 8), 0.02, np.float32)
    depth = ref.copy()
    depth[:4, :4] -= 1e-3  # a 1 mm press over one 4x4 block
    depth[4:, 4:] -= 5e-7  # below the contact threshold: no contact
    out = indentation(depth, ref, 4)
    assert out.shape == (2, 2)
    assert out[0, 0] == pytest.approx(1e-3, rel=1e-3) and out[1, 1] == 0.0 and out[0, 1] == 0.0


def test_arrays_load_labels_pixels_and_cache(sim_root, tmp_path, camera):
    from scenes.dataset import read_samples

    a = data.load(sim_root, 4, cache=tmp_path)
    records = read_samples(sim_root)
    assert len(a) == len(records) and a.images.shape[1:] == (120, 160, 3) and a.images.dtype == np.uint8
    assert [INDENTERS[k] for k in a.labels] == [r["object"] for r in records]
    assert np.allclose(a.pixel, project(np.array([r["contact_point"] for r in records]), camera), atol=1e-3)
    assert a.indentation is not None and a.indentation.shape == (len(a), 120, 160)
    cached = list(tmp_path.glob("*.npz"))
    assert len(cached) == 1
    b = data.load(sim_root, 4, cache=tmp_path)
    assert np.array_equal(a.images, b.images) and np.array_equal(a.indentation, b.indentation)
    assert list(a.ids) == list(b.ids)
    shuffled = a.take(np.arange(len(a))[::-1])
    assert np.array_equal(data.aligned(shuffled, a.ids, "x").images, a.images)
    with pytest.raises(Exception, match="not the capture's"):
        data.aligned(a.take([0]), a.ids, "the replay")


def test_augmenter_applies_fitted_effects_and_none_is_identity(sim_root):
    from scenes.dataset import read_meta

    a = data.load(sim_root, 4)
    aug = augment.Augmenter(data.dataset_spec(sim_root), read_meta(sim_root)["renderer"], 4)
    assert aug.apply(a.images, a.indentation, {}) is a.images
    gains = {"camera_response": {"gain_r": 0.5, "gain_g": 1.0, "gain_b": 1.0, "mix_rg": 0.0, "mix_rb": 0.0,
                                 "mix_gr": 0.0, "mix_gb": 0.0, "mix_br": 0.0, "mix_bg": 0.0, "offset": 0.0,
                                 "gamma": 1.0}}
    out = aug.apply(a.images[:2], a.indentation[:2], gains)
    red, green = out[..., 0].astype(int), out[..., 1].astype(int)
    assert np.abs(red - np.rint(a.images[:2, ..., 0] * 0.5)).max() <= 1
    assert np.abs(green - a.images[:2, ..., 1]).max() <= 1
    # a membrane effect changes the contact only: a softer membrane, a shallower imprint
    soft = aug.apply(a.images[:2], a.indentation[:2], {"membrane_compliance": {"scale": 0.3}})
    changed = np.abs(soft.astype(int) - a.images[:2].astype(int)).max(axis=-1) > 2
    pressed = a.indentation[:2] > 1e-5
    assert changed.any() and changed[~pressed].mean() < 0.01
    rand = aug.randomised(a.images[:3], a.indentation[:3], seed=0)
    assert np.array_equal(rand, aug.randomised(a.images[:3], a.indentation[:3], seed=0))
    assert not np.array_equal(rand, a.images[:3])


# --- models -------------------------------------------------------------------------------

def _blobs(n: int, rng, size=(24, 32)):
    """Images with one bright blob, left or right: a class and a position to learn."""
    h, w = size
    images = np.full((n, h, w, 3), 40, np.uint8)
    labels = rng.integers(0, 2, n)
    pos = np.zeros((n, 2), np.float32)
    for i in range(n):
        c = rng.integers(2, w // 2 - 3) + labels[i] * (w // 2)
        r = rng.integers(3, h - 3)
        images[i, r - 2:r + 3, c - 2:c + 3] = 220
        pos[i] = (c / w, r / h)
    return images, labels, pos


def test_need_names_the_missing_library():
    assert need("nope").startswith("model must be one of")
    if not TORCH:
        assert "torch" in need("cnn") and "sim2real" in need("cnn")


@needs_sklearn
def test_ridge_learns_a_separable_task():
    rng = np.random.default_rng(0)
    x, y, _ = _blobs(300, rng)
    model = train("ridge", x[:200], np.eye(2, dtype=np.float32)[y[:200]], 0)
    assert np.mean(model.predict(x[200:]).argmax(axis=1) == y[200:]) > 0.9


@needs_torch
def test_cnn_learns_class_and_position():
    rng = np.random.default_rng(0)
    x, y, pos = _blobs(400, rng)
    quick = Training(epochs=15)
    model = train("cnn", x[:300], np.eye(2, dtype=np.float32)[y[:300]], 0, quick)
    assert model.steps == 120
    assert np.mean(model.predict(x[300:]).argmax(axis=1) == y[300:]) > 0.9
    loc = train("cnn", x[:300], pos[:300], 0, Training(epochs=40))
    err = np.abs(loc.predict(x[300:]) - pos[300:]).mean()
    assert err < 0.5 * np.abs(pos[300:] - pos[:300].mean(axis=0)).mean()  # better than the mean position


@needs_torch
def test_resnet18_trains_and_predicts_its_outputs():
    pytest.importorskip("torchvision", reason="torchvision is not installed (pip install '.[sim2real]')")
    rng = np.random.default_rng(0)
    x, y, _ = _blobs(16, rng, (32, 32))
    model = train("resnet18", x, np.eye(8, dtype=np.float32)[y], 0, Training(batch=8, batches_per_epoch=1, epochs=2))
    out = model.predict(x[:5])
    assert out.shape == (5, 8) and np.isfinite(out).all()


def test_train_refuses_bad_input():
    if need("ridge"):
        pytest.skip(need("ridge"))
    with pytest.raises(ValueError, match="uint8"):
        train("ridge", np.zeros((4, 8, 8, 3), np.float32), np.zeros((4, 2), np.float32), 0)
    with pytest.raises(ValueError, match="targets must be"):
        train("ridge", np.zeros((4, 8, 8, 3), np.uint8), np.zeros((3, 2), np.float32), 0)
    with pytest.raises(ValueError, match="NaN"):
        train("ridge", np.zeros((4, 8, 8, 3), np.uint8), np.full((4, 2), np.nan, np.float32), 0)


# --- the pipeline on a slice ---------------------------------------------------------------

#: The slices the whole pipeline is run on: the capture's frame (None: the spec's 640x480),
#: the twin's defocus (blur disc radius, px of that frame), the study's settings and the
#: effects the diagnosis fits. "small" is the not-slow suite's: the same stages and checks
#: on a 160x120 capture with the same defocus on the sensor (1.5 px at 640x480 is 0.375 at
#: 160x120), read at full resolution (factor 1), so the arrays, the full input (80x60) and
#: the patch (32 px) are the sizes "full" reads at its factor 4; 12 extended taps, and one
#: effect, the camera's response, for the twin's gains. "full" is the slice at the study's
#: own resolution with the defocus and vignetting candidates too (slow: 155 s on 2 cores, a
#: fifth of the not-slow suite's time when it ran there).
PIPELINE_SLICES = {
    "small": ((160, 120), 0.375, {"factor": 1, "extended_taps": 12}, ("camera_response",)),
    "full": (None, 1.5, {"extended_taps": 48}, ("camera_response", "blur_noise", "vignetting")),
}


def _spec_file(folder, size) -> list[str]:
    """``--spec`` arguments of the default sensor at ``size`` (width, height) px, or none
    for its own size."""
    if size is None:
        return []
    import tomli_w

    from scenes.spec_read import default_spec

    def given(x):  # TOML has no null: a key left unset is left out
        if isinstance(x, dict):
            return {k: given(v) for k, v in x.items() if v is not None}
        return [given(v) for v in x] if isinstance(x, list) else x

    path = folder / "spec.toml"
    path.write_text(tomli_w.dumps(given(default_spec().at_resolution(*size).to_dict())))
    return ["--spec", str(path)]


@needs_sklearn
@pytest.mark.parametrize("slice_name", ["small", pytest.param("full", marks=pytest.mark.slow)])
def test_pipeline_on_a_slice(tmp_path, mujoco_gl, slice_name):
    """A virtual-rig capture (the fast path's twin, with a camera of its own: gains and a
    defocus the diagnosis must find) of two indenters, the study with the ridge model: the
    tables, the figure, results.json; the diagnosed effects bring the simulated images
    towards the capture; a second call resumes without training again."""
    from scenes.cli import main

    size, blur_px, slice_settings, effects = PIPELINE_SLICES[slice_name]
    capture = tmp_path / "capture"
    assert main(["rig", "run", "--printer", "twin", "--servos", "twin", "--camera", "twin", "--renderer", "phong",
                 *_spec_file(tmp_path, size),
                 "--unit", "camera_gains=1.25,0.95,0.8", "--unit", f"blur={blur_px}", "--protocol", "base",
                 "--objects", "sphere,cone", "--out", str(capture), "--yes", "--quiet"]) == 0
    out = tmp_path / "study"
    settings = Settings(model="ridge", seeds=2, **slice_settings)
    args = dict(capture=capture, fields=("plane",), progress=False,
                diagnose_options={"effects": effects, "intervals": 0})
    doc = pipeline.run(out, settings, **args)
    for key in ("r2r", "s2s", "s2r", "s2r_by_training", "gap_closed", "paper", "timing"):
        assert key in doc
    assert set(doc["s2r_by_training"]) == {"none", "randomised", "diagnosed"}
    cell = doc["s2r"]["base"]["full"]
    assert set(cell) == {"accuracy", "localisation_mm"} and len(cell["accuracy"]["seeds"]) == 2
    assert "localisation_mm" not in doc["s2r"]["extended"]["patch"]
    assert json.loads((out / "results-ridge.json").read_text())["gap_closed"] == doc["gap_closed"]
    assert "Real2Real" in (out / "tables-ridge.md").read_text()
    assert (out / "transfer-ridge.png").stat().st_size > 10_000
    assert "camera_response" in doc["diagnosis"]["effects"]
    # the fitted effects bring the simulated base protocol nearer the capture, tap for tap
    s = study.Study(out, settings, progress=False)
    real = s.add("real", capture)
    sim = s.add("base_plane", out / "sim_base_plane")
    s.params = doc["diagnosis"]["params"]
    order = data.aligned(sim, real.ids, "sim").ids
    where = {i: k for k, i in enumerate(sim.ids)}
    idx = [where[i] for i in order]
    before = np.abs(sim.images[idx].astype(float) - real.images.astype(float)).mean()
    after = np.abs(s.training_images("base_plane", "diagnosed")[idx].astype(float) - real.images.astype(float)).mean()
    assert after < 0.7 * before
    runs_dir = out / "runs" / "ridge"
    stamps = {p.name: p.stat().st_mtime_ns for p in runs_dir.glob("*/*.json")}
    assert len(stamps) == doc["timing"]["runs"]
    again = pipeline.run(out, settings, **args)
    assert again["gap_closed"] == doc["gap_closed"]
    assert {p.name: p.stat().st_mtime_ns for p in runs_dir.glob("*/*.json")} == stamps
    # other settings are other models: they do not reuse these runs
    assert s.run_path(Run("real", "none", "full", "classification", 0)).parent != study.Study(
        out, replace(settings, patch_px=settings.patch_px * 2)).run_path(
        Run("real", "none", "full", "classification", 0)).parent
    # difference inputs: their own runs and outputs; a capture's contact shows in its difference
    diff = replace(settings, seeds=1, difference=True, inputs=("full",), tasks=("classification",))
    assert study.Study(out, diff).run_path(Run("real", "none", "full", "classification", 0)).parent != \
        s.run_path(Run("real", "none", "full", "classification", 0)).parent
    ddoc = pipeline.run(out, diff, **args)
    assert (out / "results-ridge-difference.json").exists() and ddoc["settings"]["difference"]
    ds = study.Study(out, diff, progress=False)
    ds.add("real", capture)
    ds.add("base_plane", out / "sim_base_plane")
    ds.params = ddoc["diagnosis"]["params"]
    for name, training in (("real", "none"), ("base_plane", "diagnosed"), ("base_plane", "randomised")):
        x = features.difference(ds.training_images(name, training), ds.frames(name, training), ds.mask)
        pressed = sim.indentation[idx] > 1e-4  # the contacts, tap for tap (the capture's order)
        if name != "real":
            x = x[idx]
        change = np.abs(x.astype(float) - features.DIFFERENCE_ZERO).mean(axis=-1)
        assert change[pressed].mean() > 3 * change[~pressed & ds.mask].mean(), (name, training)


def test_run_refuses_a_capture_that_is_not_real(tmp_path, sim_root):
    if need("ridge"):
        pytest.skip(need("ridge"))
    with pytest.raises(ValueError, match="not a capture"):
        pipeline.run(tmp_path / "s", Settings(model="ridge"), capture=sim_root, progress=False)


def test_runs_cover_the_tables_and_a_subset_only_its_cells():
    every = plan.runs(Settings(seeds=2), ["base_plane", "extended_plane"], ["extended_plane"])
    # per seed: 3 input-task cells (no localisation from a patch) x (real + 2 sets + 2 trainings)
    assert len(every) == 2 * 3 * 5 and len({r.name for r in every}) == len(every)
    assert not any(r.input == "patch" and r.task == "localisation" for r in every)
    few = plan.runs(Settings(seeds=1, inputs=("full",), tasks=("classification",)), ["extended_plane"],
                    ["extended_plane"])
    assert [(r.train_set, r.training) for r in few] == [("real", "none"), ("extended_plane", "none"),
                                                         ("extended_plane", "randomised"),
                                                         ("extended_plane", "diagnosed")]
    assert Settings(model="resnet18").stem == "-resnet18" and Settings().stem == ""


def test_cli_refuses_unknown_values(capsys):
    from studies.sim2real.__main__ import main

    with pytest.raises(SystemExit):
        main(["--out", "x", "--tasks", "segmentation"])
    assert "segmentation" in capsys.readouterr().err


def test_contrast_measures_the_contact_against_the_rest():
    n, h, w = 8, 6, 6
    images = np.full((n, h, w, 3), 100, np.uint8)
    indentation = np.zeros((n, h, w), np.float32)
    for i in range(n):
        images[i, i % 3, i % 3] = 151  # each contact at its own pixel: the median stays the background
        indentation[i, i % 3, i % 3] = 1e-3
    images[:, 5, 5] += np.arange(n, dtype=np.uint8)[:, None]  # "noise" off the contacts
    a = data.Arrays(images=images, labels=np.arange(n) % 2, pixel=np.zeros((n, 2), np.float32),
                    point=np.zeros((n, 3), np.float32), path=np.zeros(n, int), position=np.zeros(n, int),
                    replica=np.zeros(n, int), ids=np.array([f"{i:06d}_x" for i in range(n)]),
                    indentation=indentation, factor=1)
    out = summary.contrast({"set": a}, a, np.ones((h, w), bool))["per_set"]["set"]
    assert set(out) == {INDENTERS[0], INDENTERS[1]}
    assert out[INDENTERS[0]]["contact"] == pytest.approx(51 / 255, rel=1e-5)
    assert 0 < out[INDENTERS[0]]["elsewhere"] < 0.01


def test_load_refuses_an_object_that_is_no_indenter_and_a_wrong_indentation(sim_root, tmp_path):
    import shutil

    from scenes.dataset import DatasetError

    bad = tmp_path / "bad"
    shutil.copytree(sim_root, bad)
    lines = (bad / "samples.jsonl").read_text().splitlines()
    record = json.loads(lines[0])
    (bad / "samples.jsonl").write_text("\n".join([json.dumps({**record, "object": "teapot"})] + lines[1:]) + "\n")
    with pytest.raises(DatasetError, match="teapot"):
        data.load(bad, 4)
    with pytest.raises(DatasetError, match="indentation is"):
        data.load(sim_root, 8)  # the stored maps are 160x120, not 80x60


def test_contact_contrast_scores_the_dent_against_the_far_circle():
    from studies.sim2real.visibility import contact_contrast

    h, w = 80, 80
    frame = np.full((h, w, 3), 0.5)
    touched = np.zeros((h, w), bool)
    touched[10:14, 10:14] = True
    image = frame.copy()
    image[10:14, 10:14] += 0.1  # the dent
    image[70:, 70:, 0] += 0.03  # far off it: noise in one channel
    mask = np.ones((h, w), bool)
    out = contact_contrast(image, frame, touched, mask, rim_px=2, far_px=20)
    grown = 16 + 4 * 4 * 2 + 4  # a 4x4 square grown by 2 in L1 distance (scipy's cross): sides, one per corner
    assert out["contact"] == pytest.approx(0.1 * 16 / grown)
    assert out["relative"] == pytest.approx(out["contact"] / 0.5)
    assert out["peak"] == pytest.approx(0.1)
    assert 0 < out["far"] < 0.01
    with pytest.raises(ValueError, match="no pixel"):
        contact_contrast(image, frame, np.zeros((h, w), bool), mask)
    with pytest.raises(ValueError, match=r"\(H, W, 3\)"):
        contact_contrast(image[..., 0], frame, touched, mask)


def test_difference_scales_each_image_by_its_own_rms_in_the_circle():
    frame = np.full((4, 4, 3), 100, np.uint8)
    images = np.repeat(frame[None], 3, axis=0)
    images[0, 1, 1] = 110  # one pixel 10 brighter in every channel
    images[1, 1, 1] = 200  # the same contact ten times stronger
    mask = np.ones((4, 4), bool)
    mask[3, 3] = False
    images[:, 3, 3] = 0  # outside the circle: ignored
    out = features.difference(images, frame, mask)
    rms = np.sqrt(3 * 10.0 ** 2 / (3 * 15))  # one pixel of 15 inside the circle
    want = features.DIFFERENCE_ZERO + features.DIFFERENCE_SCALE * 10 / rms
    assert np.all(out[0, 1, 1] == np.clip(np.rint(want), 0, 255))
    assert np.array_equal(out[0], out[1])  # strength drops out, shape stays
    assert np.all(out[2] == features.DIFFERENCE_ZERO)  # no contact: zero everywhere
    assert np.all(out[:, 3, 3] == features.DIFFERENCE_ZERO)
    per_image = np.stack([frame, frame, np.full_like(frame, 90)])
    assert not np.all(features.difference(images, per_image, mask)[2] == features.DIFFERENCE_ZERO)
    with pytest.raises(ValueError, match="one per image"):
        features.difference(images, per_image[:2], mask)
    with pytest.raises(ValueError, match="mask"):
        features.difference(images, frame, mask[:3])


def test_patches_pad_with_the_fill():
    images = np.full((1, 8, 8, 3), 200, np.uint8)
    out = features.patches(images, np.array([[0.0, 0.0]]), 1, 4, fill=128)
    assert out[0, 0, 0, 0] == 128 and out[0, -1, -1, 0] == 200


def test_randomised_frames_are_each_draws_no_contact_frame(sim_root):
    from scenes.dataset import read_meta

    arrays = data.load(sim_root, 4)
    aug = augment.Augmenter(data.dataset_spec(sim_root), read_meta(sim_root)["renderer"], 4)
    plain = data.frame(sim_root, 4)
    assert plain.shape == arrays.images.shape[1:] and plain.dtype == np.uint8
    frames = aug.randomised_frames(plain, 3, seed=5)
    draws = aug.draws(3, seed=5)
    zero = np.zeros((1,) + plain.shape[:2], np.float32)
    for i in range(3):
        assert np.array_equal(frames[i], aug.apply(plain[None], zero, draws[i])[0])
    assert not np.array_equal(frames[0], frames[1])  # each image its own draw


def test_bad_input_to_frames_and_visibility_is_refused_by_name(sim_root, tmp_path):
    import argparse
    import shutil

    from scenes.dataset import DatasetError
    from studies.sim2real import visibility

    bare = tmp_path / "bare"
    shutil.copytree(sim_root, bare)
    (bare / "background.png").unlink()
    with pytest.raises(DatasetError, match="no background.png"):
        data.frame(bare)
    with pytest.raises(ValueError, match="not samples"):
        visibility.measure(sim_root, ["000000_teapot"], {"default": []})
    first = json.loads((sim_root / "samples.jsonl").read_text().splitlines()[0])["id"]
    with pytest.raises(ValueError, match="depth maps"):
        visibility.measure(sim_root, [first], {"default": []})  # a compact set keeps no full depth
    assert visibility._setting("clear=scattering_per_m=0;absorption_per_m=0") == (
        "clear", ["scattering_per_m=0", "absorption_per_m=0"])
    assert visibility._setting("default=") == ("default", [])
    with pytest.raises(argparse.ArgumentTypeError, match="NAME="):
        visibility._setting("clear")


@pytest.mark.slow  # 7 s (25 s on busy cores): two sessions on the rig's twins
def test_virtual_capture_writes_what_rig_run_writes(tmp_path, spec, mujoco_gl):
    """The study's capture (``capture.virtual_capture``, the reference's camera there) is the
    rig's own session on the twins: the same folder as ``tactile-sim rig run`` on the twins,
    file for file, here with the fast path's camera on two taps."""
    from phong_reference import plugin as phong
    from scenes.body import checked_membrane
    from scenes.cli import main
    from scenes.protocol import make_protocol
    from studies.sim2real.capture import virtual_capture

    assert main(["rig", "run", "--printer", "twin", "--servos", "twin", "--camera", "twin", "--renderer", "phong",
                 "--protocol", "base", "--objects", "sphere", "--limit", "2", "--out", str(tmp_path / "cli"), "--yes",
                 "--quiet"]) == 0
    protocol = make_protocol("base", spec, checked_membrane(spec), ("sphere",))
    virtual_capture(tmp_path / "py", spec, replace(protocol, taps=protocol.taps[:2]), phong, progress=False)
    files = {p.relative_to(tmp_path / "cli") for p in (tmp_path / "cli").rglob("*") if p.is_file()}
    assert files == {p.relative_to(tmp_path / "py") for p in (tmp_path / "py").rglob("*") if p.is_file()}
    assert json.loads((tmp_path / "py" / "dataset.json").read_text())["alignment"]["method"] == "registration"
    for name in files:
        a, b = (tmp_path / "cli" / name).read_bytes(), (tmp_path / "py" / name).read_bytes()
        assert a.replace(str(tmp_path / "cli").encode(), b"@") == b.replace(str(tmp_path / "py").encode(), b"@"), name
