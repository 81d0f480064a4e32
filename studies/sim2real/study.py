"""The study: Real2Real, Sim2Sim and Sim2Real, and what the diagnosed effects do to it.

Stages, each cached under ``DIR`` and resumed (``run``):

1. ``DIR/real``: the "real" data, a virtual-rig capture of the base protocol (all 8
   indenters, 144 taps) whose camera is the physically based reference (or a given
   capture, ``capture=``): the real driver's code path, a gap to the fast path that is
   physics, not formulas;
2. ``DIR/replay_<field>``: the fast path's replay of the capture with each light field
   and the capture's background; the field whose replay is nearest the capture (MAE over
   the image circle) is the best field, beside the published plane field;
3. ``DIR/diagnosis``: ``tactile-sim diagnose`` of the capture against the plane field's
   replay: the effects to add, fitted;
4. ``DIR/sim_<protocol>_<field>``: the fast path's base and extended protocols (all 8
   indenters) with the capture's background (``studies.sim2real.plugin``);
5. ``DIR/runs/<model>/<settings tag>/<run>.json``: one trained model each, evaluated
   (``Run``, ``Study.run_path``);
6. ``DIR/results.json``, ``DIR/tables.md``, ``DIR/transfer.png``.

Evaluation, as the paper's: seeded 80/20 splits stratified by indenter. Real2Real trains
on the capture's 80 % and tests on its 20 %; Sim2Sim trains on a simulated protocol's 80 %
and tests on its 20 %; Sim2Real tests that same model on the capture's 20 % of the same
seed, the R2R test set (and, for the figures, on all 144 taps). Localisation predicts the
contact's pixel; its error is the distance on the membrane, in mm, between the point that
pixel sees through the camera model and the tap's contact point (``data.MembraneLookup``).
The cropped patch is ``patch_px`` square at the arrays' resolution, centred on the
contact's pixel.
"""

from __future__ import annotations

import hashlib
import json
import math
import time
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import numpy as np

from phong_reference.bake import METHODS
from scenes.dataset import atomic_write_bytes, atomic_write_json, npy_bytes, read_meta, read_samples
from scenes.images import block_mean
from scenes.indenters import INDENTERS

from . import augment, data
from .learn import Training, need, train

#: The light fields whose replays pick the best one, the published plane field first.
FIELDS = ("plane",) + tuple(m for m in METHODS if m != "plane")
PROTOCOLS = ("base", "extended")
INPUTS = ("full", "patch")
TASKS = ("classification", "localisation")
#: The paper's Tables 2 and 3: accuracy (%) and localisation error (mm).
PAPER = {
    "r2r": {"base": {"full": {"accuracy": 64.3, "localisation_mm": 8.4}, "patch": {"accuracy": 35.7}}},
    "s2s": {"base": {"full": {"accuracy": 75.0, "localisation_mm": 3.7}, "patch": {"accuracy": 96.4}},
            "extended": {"full": {"accuracy": 100.0, "localisation_mm": 5.4}, "patch": {"accuracy": 100.0}}},
    "s2r": {"base": {"full": {"accuracy": 42.8, "localisation_mm": 11.8}, "patch": {"accuracy": 14.3}},
            "extended": {"full": {"accuracy": 50.0, "localisation_mm": 13.3}, "patch": {"accuracy": 32.1}}},
}


@dataclass(frozen=True)
class Settings:
    """What the study trains, and on what.

    model : ``learn.MODELS``; seeds : splits and initialisations per run; factor : the
    arrays' block size (4: 160x120 of a 640x480 camera); full_block : the full-image input
    averaged again by this (2: 80x60); patch_px : the patch's side at the arrays'
    resolution (32: 128 full-resolution pixels, about 11 mm of the GelTip's membrane);
    extended_taps : a seeded subset of the extended protocol's taps (None: all 23,040);
    trainings : which of ``augment.TRAININGS`` the simulated sets are trained with;
    inputs, tasks : which of ``INPUTS`` and ``TASKS`` are run (a subset: a costly model on
    the cells that matter); difference : the networks see each image's difference from
    its set's no-contact frame, as shown with the same effects, over its RMS in the image
    circle (``difference``), instead of the image as published.
    """

    model: str = "cnn"
    seeds: int = 3
    factor: int = 4
    full_block: int = 2
    patch_px: int = 32
    extended_taps: int | None = None
    trainings: tuple[str, ...] = augment.TRAININGS
    training: Training = field(default_factory=Training)
    workers: int = 2
    inputs: tuple[str, ...] = INPUTS
    tasks: tuple[str, ...] = TASKS
    difference: bool = False

    def to_dict(self) -> dict:
        return {**asdict(self), "training": self.training.to_dict(), "trainings": list(self.trainings),
                "inputs": list(self.inputs), "tasks": list(self.tasks)}

    @property
    def stem(self) -> str:
        """What the outputs are called: ``results.json`` etc. for the default model, else
        ``results-<model>.json``, so a costly model's subset sits beside the default's; with
        difference inputs ``-difference`` follows."""
        return ("" if self.model == "cnn" else f"-{self.model}") + ("-difference" if self.difference else "")


@dataclass(frozen=True)
class Run:
    """One trained model: trained on ``train_set`` (``real`` or ``<protocol>_<field>``)
    with ``training`` (``augment.TRAININGS``), for ``task`` from ``input``, seed ``seed``."""

    train_set: str
    training: str
    input: str
    task: str
    seed: int

    @property
    def name(self) -> str:
        return f"{self.train_set}-{self.training}-{self.input}-{self.task}-{self.seed}"


# --- data -------------------------------------------------------------------------------

def _cli(argv: list[str]) -> None:
    from scenes.cli import main

    status = main([str(a) for a in argv])
    if status:
        raise RuntimeError(f"tactile-sim {' '.join(map(str, argv[:2]))} failed with status {status}")


def complete(root: Path, taps: int | None = None) -> bool:
    """Whether a dataset folder holds all its protocol's taps."""
    if not (root / "dataset.json").exists():
        return False
    want = read_meta(root)["protocol"]["taps"] if taps is None else taps
    return len(read_samples(root)) >= want


def ensure_capture(out: Path, spec: str | None, progress: bool, profile: str | None = None) -> dict:
    """The virtual-rig capture (stage 1); returns its one-time cost, kept in
    ``DIR/capture_cost.json``: the seconds spent rendering it and the frames rendered."""
    real = out / "real"
    ledger = out / "capture_cost.json"
    cost = json.loads(ledger.read_text()) if ledger.exists() else {"seconds": 0.0, "frames": 0, "calls": 0}
    if not complete(real):
        before = len(read_samples(real)) if (real / "dataset.json").exists() else 0
        t0 = time.perf_counter()
        argv = ["rig", "run", "--printer", "twin", "--servos", "twin", "--camera", "twin", "--renderer", "pbr",
                "--protocol", "base", "--objects", "all", "--out", real, "--yes"]
        argv += ([] if spec is None else ["--spec", spec]) + ([] if profile is None else ["--profile", profile])
        _cli(argv + ([] if progress else ["--quiet"]))
        cost = {"seconds": cost["seconds"] + time.perf_counter() - t0,
                "frames": cost["frames"] + len(read_samples(real)) - before, "calls": cost["calls"] + 1}
        atomic_write_json(ledger, cost)
    return {**cost, "what": "wall seconds of the capture's rendering calls made by this study (a capture resumed "
                            "adds up), and the frames they rendered"}


def ensure_replays(out: Path, real: Path, fields: tuple[str, ...], progress: bool) -> dict[str, Path]:
    """The fast path's replay of the capture with each light field (stage 2)."""
    replays = {}
    for f in fields:
        root = out / f"replay_{f}"
        if not complete(root, len(read_samples(real))):
            _cli(["dataset", "--replay", real, "--renderer", "phong", "--field", f, "--background",
                  real / "background.png", "--out", root] + ([] if progress else ["--quiet"]))
        replays[f] = root
    return replays


def field_gaps(real: data.Arrays, replays: dict[str, data.Arrays], mask: np.ndarray) -> dict:
    """Each replay's MAE to the capture over the image circle, per sample then averaged,
    at the arrays' resolution ([0, 1] units)."""
    out = {}
    for f, sim in replays.items():
        sim = data.aligned(sim, real.ids, f"the {f} replay")
        diff = np.abs(sim.images.astype(np.float32) - real.images.astype(np.float32)) / 255.0
        out[f] = float(diff[:, mask].mean())
    return out


def ensure_sim(out: Path, name: str, field_name: str, background: Path, settings: Settings, spec,
               objects: tuple[str, ...], progress: bool) -> Path:
    """A simulated protocol (stage 4) of ``objects`` into ``DIR/sim_<name>_<field>``."""
    from dataclasses import replace

    from scenes.body import checked_membrane
    from scenes.commands import make_protocol
    from scenes.generate import generate

    root = out / f"sim_{name}_{field_name}"
    protocol = make_protocol(name, spec, checked_membrane(spec), objects, seed=0)
    if name == "extended" and settings.extended_taps is not None and settings.extended_taps < len(protocol.taps):
        keep = np.sort(np.random.default_rng(0).choice(len(protocol.taps), settings.extended_taps, replace=False))
        protocol = replace(protocol, taps=tuple(protocol.taps[i] for i in keep))
    if not complete(root, len(protocol.taps)):
        generate(root, spec, protocol, renderer="studies.sim2real.plugin",
                 options={"field": field_name, "background": str(background), "depth_factor": settings.factor},
                 workers=settings.workers, progress=progress)
    return root


# --- inputs -----------------------------------------------------------------------------

def full_inputs(images: np.ndarray, block: int, chunk: int = 1024) -> np.ndarray:
    """The full-image input: (N, h, w, 3) uint8 averaged over ``block`` blocks (in chunks:
    23,040 images in float would take 5 GB)."""
    if block == 1:
        return images
    return np.concatenate([np.clip(np.rint(block_mean(images[i:i + chunk].astype(np.float32), block, (1, 2))), 0, 255)
                           .astype(np.uint8) for i in range(0, len(images), chunk)])


def patches(images: np.ndarray, pixel: np.ndarray, factor: int, size: int, fill: int = 0) -> np.ndarray:
    """(N, size, size, 3) crops centred on each contact's pixel (full-resolution (u, v),
    ``pixel``) at the arrays' resolution (1/``factor``), ``fill`` outside the image."""
    n, h, w, _ = images.shape
    pad = size
    padded = np.pad(images, ((0, 0), (pad, pad), (pad, pad), (0, 0)), constant_values=fill)
    out = np.empty((n, size, size, 3), np.uint8)
    centre = (np.asarray(pixel, np.float64) + 0.5) / factor - 0.5  # full-res pixel centre -> array pixels
    for i in range(n):
        c0 = int(math.floor(centre[i, 0] - size / 2 + 0.5)) + pad
        r0 = int(math.floor(centre[i, 1] - size / 2 + 0.5)) + pad
        c0, r0 = min(max(c0, 0), w + pad), min(max(r0, 0), h + pad)
        out[i] = padded[i, r0:r0 + size, c0:c0 + size]
    return out


#: Difference inputs are stored as uint8 DIFFERENCE_ZERO + DIFFERENCE_SCALE z (``difference``).
DIFFERENCE_ZERO = 128
DIFFERENCE_SCALE = 8.0


def difference(images: np.ndarray, frames: np.ndarray, mask: np.ndarray, chunk: int = 1024) -> np.ndarray:
    """(N, h, w, 3) uint8 images and their no-contact frames ((h, w, 3), or one per image)
    -> uint8 DIFFERENCE_ZERO + DIFFERENCE_SCALE z, clipped, z = (image - frame) over its
    RMS inside the image circle ``mask`` (h, w), zero outside it.

    Scaled per image, the input keeps the contact's shape and drops its strength, which a
    simulator may get wrong by an order of magnitude (``visibility``); an image equal to
    its frame gives z = 0."""
    images = np.asarray(images)
    frames = np.asarray(frames)
    if images.ndim != 4 or frames.shape[-3:] != images.shape[1:] or frames.ndim not in (3, 4) or (
            frames.ndim == 4 and len(frames) != len(images)):
        raise ValueError(f"frames {frames.shape} must be one (h, w, 3) frame or one per image of {images.shape}")
    if mask.shape != images.shape[1:3]:
        raise ValueError(f"mask {mask.shape} must be the images' (h, w) {images.shape[1:3]}")
    out = np.empty_like(images, dtype=np.uint8)
    for i in range(0, len(images), chunk):
        f = frames if frames.ndim == 3 else frames[i:i + chunk]
        d = images[i:i + chunk].astype(np.float32) - f.astype(np.float32)
        d *= mask[None, :, :, None]
        rms = np.sqrt((d ** 2).sum(axis=(1, 2, 3)) / (3.0 * mask.sum()))
        z = d / np.maximum(rms, 1e-6)[:, None, None, None]
        out[i:i + chunk] = np.clip(np.rint(DIFFERENCE_ZERO + DIFFERENCE_SCALE * z), 0, 255)
    return out


def inputs(arrays: data.Arrays, images: np.ndarray, kind: str, settings: Settings) -> np.ndarray:
    if kind == "full":
        return full_inputs(images, settings.full_block)
    if kind == "patch":
        return patches(images, arrays.pixel, arrays.factor, settings.patch_px,
                       fill=DIFFERENCE_ZERO if settings.difference else 0)
    raise ValueError(f"input must be one of {INPUTS}, got {kind!r}")


def targets(arrays: data.Arrays, task: str, size: tuple[int, int]) -> np.ndarray:
    """Classification: the one-hot indenter; localisation: the contact's pixel over the
    full image's (width, height), in [0, 1]."""
    if task == "classification":
        return np.eye(len(INDENTERS), dtype=np.float32)[arrays.labels]
    if task == "localisation":
        return (arrays.pixel / np.asarray(size, np.float32)).astype(np.float32)
    raise ValueError(f"task must be one of {TASKS}, got {task!r}")


# --- the study --------------------------------------------------------------------------

class Study:
    """The cached datasets, arrays and runs of one ``DIR`` (``run`` builds them)."""

    def __init__(self, out: str | Path, settings: Settings = Settings(), progress: bool = True):
        self.out = Path(out)
        self.settings = settings
        self.progress = progress
        self.cache = self.out / "cache"
        self.sets: dict[str, data.Arrays] = {}
        self.images: dict[tuple[str, str], np.ndarray] = {}
        self.augmenters: dict[str, augment.Augmenter] = {}
        self.params: dict = {}
        self.roots: dict[str, Path] = {}
        self._lookup = None
        self._inputs: dict[tuple[str, str, str], np.ndarray] = {}

    def add(self, name: str, root: Path) -> data.Arrays:
        self.roots[name] = root
        self.sets[name] = data.load(root, self.settings.factor, self.cache, self.settings.workers,
                                    progress=self.progress)
        self.images[(name, "none")] = self.sets[name].images
        return self.sets[name]

    @property
    def lookup(self) -> data.MembraneLookup:
        if self._lookup is None:
            self._lookup = data.MembraneLookup(data.dataset_spec(self.roots["real"]))
        return self._lookup

    def training_images(self, name: str, training: str) -> np.ndarray:
        """A simulated set's images as trained with ``training`` (cached on disk)."""
        key = (name, training)
        if key in self.images:
            return self.images[key]
        arrays = self.sets[name]
        root = self.roots[name]
        meta = read_meta(root)
        tag = data.sha({"set": meta, "n": len(arrays), "params": self.params if training == "diagnosed" else None,
                        "training": training, "factor": arrays.factor})
        path = self.cache / f"{name}-{training}-{tag}.npy"
        if path.exists():
            images = np.load(path, allow_pickle=False)
        else:
            aug = self._augmenter(name)
            t0 = time.perf_counter()
            if training == "diagnosed":
                images = np.concatenate([aug.apply(arrays.images[i:i + 256], arrays.indentation[i:i + 256],
                                                   self.params) for i in range(0, len(arrays), 256)])
            elif training == "randomised":
                images = aug.randomised(arrays.images, arrays.indentation, seed=0)
            else:
                raise ValueError(f"training must be one of {augment.TRAININGS}, got {training!r}")
            atomic_write_bytes(path, npy_bytes(images))
            atomic_write_json(path.with_suffix(".json"), {"seconds": time.perf_counter() - t0, "images": len(images)})
        self.images[key] = images
        return images

    def frames(self, name: str, training: str) -> np.ndarray:
        """A set's no-contact frame as shown with ``training``: (h, w, 3) uint8, or one
        per image for ``randomised`` (each image's own draw, cached on disk)."""
        plain = data.frame(self.roots[name], self.sets[name].factor)
        if training == "none":
            return plain
        if training == "diagnosed":
            return self._augmenter(name).apply(plain[None], np.zeros((1,) + plain.shape[:2], np.float32),
                                               self.params)[0]
        if training != "randomised":
            raise ValueError(f"training must be one of {augment.TRAININGS}, got {training!r}")
        arrays = self.sets[name]
        tag = data.sha({"set": read_meta(self.roots[name]), "n": len(arrays), "training": training,
                        "factor": arrays.factor, "frame": hashlib.sha256(plain.tobytes()).hexdigest()})
        path = self.cache / f"{name}-{training}-frames-{tag}.npy"
        if path.exists():
            return np.load(path, allow_pickle=False)
        frames = self._augmenter(name).randomised_frames(plain, len(arrays), seed=0)
        atomic_write_bytes(path, npy_bytes(frames))
        return frames

    def _augmenter(self, name: str) -> augment.Augmenter:
        if name not in self.augmenters:
            root = self.roots[name]
            self.augmenters[name] = augment.Augmenter(data.dataset_spec(root), read_meta(root)["renderer"],
                                                      self.sets[name].factor)
        return self.augmenters[name]

    @property
    def mask(self) -> np.ndarray:
        """The image circle at the arrays' resolution."""
        return data.circle(self.roots["real"], self.settings.factor)

    def inputs(self, name: str, training: str, kind: str) -> np.ndarray:
        """A set's network inputs (``INPUTS``) as trained with ``training``, kept; with
        ``Settings.difference``, from each image's difference from its frame."""
        key = (name, training, kind)
        if key not in self._inputs:
            images = self.training_images(name, training)
            if self.settings.difference:
                images = difference(images, self.frames(name, training), self.mask)
            self._inputs[key] = inputs(self.sets[name], images, kind, self.settings)
        return self._inputs[key]

    def run_path(self, run: Run) -> Path:
        """Where ``run``'s result is kept: ``runs/<model>/<tag>/<run>.json``, the tag a digest
        of the settings a model depends on (so other epochs, resolutions or subsets of the
        extended protocol train anew), a diagnosed run's name also carrying a digest of the
        fitted effects it was trained with."""
        s = self.settings
        tag = data.sha({"factor": s.factor, "full_block": s.full_block, "patch_px": s.patch_px,
                        "extended_taps": s.extended_taps, "training": s.training.to_dict(),
                        **({"difference": [DIFFERENCE_ZERO, DIFFERENCE_SCALE]} if s.difference else {})})[:10]
        name = run.name + (f"-{data.sha(self.params)[:8]}" if run.training == "diagnosed" else "")
        return self.out / "runs" / s.model / tag / f"{name}.json"

    def evaluate(self, run: Run, real_all: bool = True) -> dict:
        """Train ``run``'s model and evaluate it (cached, ``run_path``)."""
        path = self.run_path(run)
        if path.exists():
            return json.loads(path.read_text())
        s = self.settings
        tr_set = self.sets[run.train_set]
        real = self.sets["real"]
        tr_idx, te_idx = data.split(tr_set.labels, run.seed)
        r_tr, r_te = data.split(real.labels, run.seed)
        size = (real.images.shape[2] * real.factor, real.images.shape[1] * real.factor)
        x = self.inputs(run.train_set, run.training, run.input)
        y = targets(tr_set, run.task, size)
        model = train(s.model, x[tr_idx], y[tr_idx], run.seed, s.training)
        result = {"run": asdict(run), "model": s.model, "train_samples": int(len(tr_idx)),
                  "seconds": model.seconds, "steps": model.steps}
        x_plain = self.inputs(run.train_set, "none", run.input)
        x_real = self.inputs("real", "none", run.input)
        tests = {"own": (tr_set, x_plain[te_idx], te_idx), "real": (real, x_real[r_te], r_te)}
        if real_all and run.train_set != "real":
            tests["real_all"] = (real, x_real, np.arange(len(real)))
        for which, (arrays, xt, idx) in tests.items():
            pred = model.predict(xt)
            result[which] = self._score(arrays, idx, pred, run.task, size)
        path.parent.mkdir(parents=True, exist_ok=True)
        atomic_write_json(path, result)
        return result

    def _score(self, arrays: data.Arrays, idx: np.ndarray, pred: np.ndarray, task: str, size) -> dict:
        ids = [str(i) for i in arrays.ids[idx]]
        if task == "classification":
            guess = pred.argmax(axis=1)
            return {"accuracy": float(100.0 * np.mean(guess == arrays.labels[idx])), "ids": ids,
                    "true": arrays.labels[idx].tolist(), "predicted": guess.tolist()}
        pixel = pred * np.asarray(size, np.float32)
        error = 1000.0 * np.linalg.norm(self.lookup(pixel) - arrays.point[idx], axis=1)
        return {"localisation_mm": float(error.mean()), "ids": ids, "error_mm": error.tolist(),
                "pixel": pixel.tolist()}


def runs(settings: Settings, sim_sets: list[str], augmented_sets: list[str]) -> list[Run]:
    """Every run of the study: R2R, each simulated set without effects (S2S and S2R), and
    the plane field's sets with each other training."""
    out = []
    for seed in range(settings.seeds):
        for inp in settings.inputs:
            for task in settings.tasks:
                if task == "localisation" and inp == "patch":
                    continue  # a patch centred on the contact gives its place away
                out.append(Run("real", "none", inp, task, seed))
                out += [Run(s, "none", inp, task, seed) for s in sim_sets]
                out += [Run(s, t, inp, task, seed) for s in augmented_sets for t in settings.trainings if t != "none"]
    return out


# --- summaries --------------------------------------------------------------------------

def interval(values: list[float], confidence: float = 0.95) -> dict:
    """Mean, and Student's t interval of the mean over seeds."""
    from scipy import stats

    v = np.asarray(values, np.float64)
    mean = float(v.mean())
    if len(v) < 2:
        return {"mean": mean, "interval": [mean, mean], "seeds": v.tolist()}
    half = float(stats.t.ppf(0.5 + confidence / 2, len(v) - 1) * v.std(ddof=1) / math.sqrt(len(v)))
    return {"mean": mean, "interval": [mean - half, mean + half], "seeds": v.tolist()}


METRIC = {"classification": "accuracy", "localisation": "localisation_mm"}


def summarise(results: dict[str, dict], settings: Settings, sim_sets: list[str], plane_sets: list[str]) -> dict:
    """results.json's tables from the runs' results (keyed by ``Run.name``)."""
    def cell(train_set: str, training: str, inp: str, test: str) -> dict:
        out = {}
        for task in TASKS:
            got = [results.get(Run(train_set, training, inp, task, s).name, {}).get(test)
                   for s in range(settings.seeds)]
            vals = [g[METRIC[task]] for g in got if g is not None]
            if vals:
                out[METRIC[task]] = interval(vals)
        return out

    def table(test: str, sets: list[str], training: str = "none") -> dict:
        return {name: {inp: cell(name, training, inp, test) for inp in INPUTS} for name in sets}

    r2r = {"base": {inp: cell("real", "none", inp, "own") for inp in INPUTS}}
    by_set = {"s2s": table("own", sim_sets), "s2r": table("real", sim_sets),
              "s2r_all_real_taps": table("real_all", sim_sets)}
    # the published field's tables keyed by protocol, as the paper's
    key = {s: s.split("_", 1)[0] for s in plane_sets}
    s2s = {key[s]: by_set["s2s"][s] for s in plane_sets}
    s2r = {key[s]: by_set["s2r"][s] for s in plane_sets}
    by_training = {t: {key[s]: table("real", [s], t)[s] for s in plane_sets} for t in settings.trainings}
    by_training_all = {t: {key[s]: table("real_all", [s], t)[s] for s in plane_sets} for t in settings.trainings}
    gap = {}
    for t in settings.trainings:
        gap[t] = {}
        for s in plane_sets:
            gap[t][key[s]] = {}
            for inp in INPUTS:
                entry = {}
                for task in TASKS:
                    per_seed = []
                    for seed in range(settings.seeds):
                        names = [Run(s, t, inp, task, seed).name, Run(s, "none", inp, task, seed).name,
                                 Run("real", "none", inp, task, seed).name]
                        if not all(n in results for n in names):
                            continue
                        m = METRIC[task]
                        with_t = results[names[0]]["real"][m]
                        none = results[names[1]]["real"][m]
                        r2r_v = results[names[2]]["own"][m]
                        per_seed.append((with_t, none, r2r_v))
                    if not per_seed:
                        continue
                    a = np.asarray(per_seed)
                    denominator = a[:, 2].mean() - a[:, 1].mean()
                    ratio = float((a[:, 0].mean() - a[:, 1].mean()) / denominator) if denominator else None
                    seeds = [float((w - n) / (r - n)) if r != n else None for w, n, r in per_seed]
                    good = [v for v in seeds if v is not None]
                    entry[task] = {"share": ratio, "per_seed": seeds,
                                   **({"interval": interval(good)["interval"]} if len(good) > 1 else {}),
                                   "what": "(S2R with it - S2R with none) / (R2R - S2R with none), means over "
                                           "seeds; per_seed: the same of each seed's paired runs"}
                gap[t][key[s]][inp] = entry
    return {"r2r": r2r, "s2s": s2s, "s2r": s2r, "by_set": by_set, "s2r_by_training": by_training,
            "s2r_by_training_all_real_taps": by_training_all, "gap_closed": gap, "paper": PAPER}


def contrast(sets: dict[str, data.Arrays], region_from: data.Arrays, mask: np.ndarray,
             pressed_m: float = 1e-4) -> dict:
    """How strongly each indenter's contact shows in each set: per indenter, the mean
    |image - the set's per-pixel median| ([0, 1] units, channels averaged) over the contact
    (where ``region_from``'s indentation, aligned by sample id, exceeds ``pressed_m``) and
    over the rest of the image circle (the noise a classifier must see the contact
    through)."""
    where = {str(i): k for k, i in enumerate(region_from.ids)}
    out = {}
    for name, a in sets.items():
        x = a.images.astype(np.float32) / 255.0
        change = np.abs(x - np.median(x, axis=0)).mean(axis=-1)
        rows = {}
        for c in np.unique(a.labels):
            contact, rest = [], []
            for i in np.flatnonzero(a.labels == c):
                ind = region_from.indentation[where[str(a.ids[i])]]
                contact.append(float(change[i][ind > pressed_m].mean()))
                rest.append(float(change[i][mask & (ind == 0)].mean()))
            rows[INDENTERS[c]] = {"contact": float(np.mean(contact)), "elsewhere": float(np.mean(rest))}
        out[name] = rows
    return {"per_set": out, "what": "mean |image - per-pixel median of the set| over the contact (the fast path's "
                                    f"base taps' indentation > {pressed_m * 1e3:g} mm) and elsewhere in the image "
                                    "circle, [0, 1] units, channels averaged, at the arrays' resolution"}


# --- the whole study ----------------------------------------------------------------------

def run(out: str | Path, settings: Settings = Settings(), capture: str | Path | None = None, spec: str | None = None,
        fields: tuple[str, ...] = FIELDS, protocols: tuple[str, ...] = PROTOCOLS, diagnose_args: tuple = (),
        progress: bool = True) -> dict:
    """Run (or resume) the study into ``out``; returns results.json's content.

    capture : an existing capture of the base protocol (``source: "real"``) to use instead
        of rendering ``DIR/real``; spec : the sensor spec TOML of a capture rendered here.
    fields : the light fields whose replays pick the best one (plane is always one).
    diagnose_args : extra arguments of ``tactile-sim diagnose``.
    """
    why = need(settings.model)
    if why:
        raise RuntimeError(why)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    seconds = {}
    if capture is None:
        cost = ensure_capture(out, spec, progress)
        real_root = out / "real"
    else:
        real_root = Path(capture)
        meta = read_meta(real_root)
        if meta.get("source") != "real":
            raise ValueError(f"{real_root} is not a capture (source {meta.get('source')!r}, expected 'real')")
        cost = {"seconds": 0.0, "frames": 0, "given": str(real_root)}
    study = Study(out, settings, progress)
    real = study.add("real", real_root)
    fields = tuple(dict.fromkeys(("plane",) + tuple(fields)))
    t0 = time.perf_counter()
    replays = ensure_replays(out, real_root, fields, progress)
    seconds["replays"] = time.perf_counter() - t0
    mask = data.circle(real_root, settings.factor)
    gaps = field_gaps(real, {f: data.load(r, settings.factor, study.cache, settings.workers) for f, r in replays.items()},
                      mask)
    best = min(gaps, key=gaps.get)
    t0 = time.perf_counter()
    report_path = out / "diagnosis" / "report.json"
    if not report_path.exists():
        _cli(["diagnose", real_root, replays["plane"], "--out", out / "diagnosis"] + list(diagnose_args)
             + ([] if progress else ["--quiet"]))
    seconds["diagnosis"] = time.perf_counter() - t0
    report = json.loads(report_path.read_text())
    study.params = augment.diagnosed_params(report)
    augment.check_effects(study.params)
    t0 = time.perf_counter()
    spec_obj = data.dataset_spec(real_root)
    objects = tuple(read_meta(real_root)["protocol"]["objects"])  # the capture's indenters
    sim_sets, plane_sets = [], []
    for p in protocols:
        for f in dict.fromkeys(("plane", best)):
            name = f"{p}_{f}"
            study.add(name, ensure_sim(out, p, f, real_root / "background.png", settings, spec_obj, objects,
                                       progress))
            sim_sets.append(name)
            if f == "plane":
                plane_sets.append(name)
    seconds["simulated_datasets_and_arrays"] = time.perf_counter() - t0
    todo = runs(settings, sim_sets, plane_sets)
    t0 = time.perf_counter()
    for t in settings.trainings:
        for s in plane_sets:
            if t != "none":
                study.training_images(s, t)
    seconds["effects"] = time.perf_counter() - t0
    from tqdm import tqdm

    t0 = time.perf_counter()
    results = {}
    for r in tqdm(todo, desc="runs", unit="run", disable=not progress):
        results[r.name] = study.evaluate(r)
    seconds["runs"] = time.perf_counter() - t0
    summary = summarise(results, settings, sim_sets, plane_sets)
    shown = None
    if "base_plane" in study.sets:
        inside = data.circle(real_root, settings.factor, share=0.99)
        base = study.sets["base_plane"]
        # the trained images too: how far each training brings the contacts' strength to the capture's
        trained = {"base_plane" + ("" if t == "none" else f" {t}"):
                   replace(base, images=study.training_images("base_plane", t))
                   for t in dict.fromkeys(("none",) + tuple(settings.trainings))}
        if set(map(str, real.ids)) == set(map(str, base.ids)):
            trained = {"real": real, **{k: data.aligned(v, real.ids, "the base protocol") for k, v in trained.items()}}
        shown = contrast(trained, base, inside)
    train_seconds = [v["seconds"] for v in results.values()]
    effects_cost = {p.stem: json.loads(p.read_text()) for p in study.cache.glob("*.json")}
    doc = {
        "settings": settings.to_dict(),
        "data": {name: data.describe(root) for name, root in study.roots.items()},
        "capture_cost": cost,
        "replays": {"fields": list(fields), "mae_to_capture": gaps, "best_field": best},
        "diagnosis": {"report": str(report_path), "effects": list(study.params),
                      "params": study.params,
                      "share_closed": (report.get("explained") or {}).get("share_closed")},
        **summary,
        "contrast": shown,
        "timing": {"this_call_seconds": seconds, "runs": len(results),
                   "train_seconds_total": float(sum(train_seconds)),
                   "train_seconds_median": float(np.median(train_seconds)) if train_seconds else None,
                   "effects_images": effects_cost},
    }
    stem = settings.stem
    atomic_write_json(out / f"results{stem}.json", doc)
    from .report import figure, tables

    (out / f"tables{stem}.md").write_text(tables(doc))
    figure(doc, results, study, out / f"transfer{stem}.png")
    return doc
