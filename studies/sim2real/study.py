"""The trained models of one study folder: ``Study`` keeps its sets' arrays, their images as
trained with each training, the networks' inputs, and each run trained and evaluated.

Evaluation, as the paper's: seeded 80/20 splits stratified by indenter. Real2Real trains
on the capture's 80 % and tests on its 20 %; Sim2Sim trains on a simulated protocol's 80 %
and tests on its 20 %; Sim2Real tests that same model on the capture's 20 % of the same
seed, the R2R test set (and, for the figures, on all 144 taps). Localisation predicts the
contact's pixel; its error is the distance on the membrane, in mm, between the point that
pixel sees through the camera model and the tap's contact point (``data.MembraneLookup``).
"""

from __future__ import annotations

import hashlib
import json
import time
from dataclasses import asdict
from pathlib import Path

import numpy as np

from scenes.dataset import atomic_write_json, npy_bytes, read_meta
from scenes.files import atomic_write_bytes

from . import augment, data
from .features import DIFFERENCE_SCALE, DIFFERENCE_ZERO, difference, inputs, targets
from .learn import train
from .plan import Run, Settings


class Study:
    """The cached datasets, arrays and runs of one ``DIR`` (``pipeline.run`` builds them)."""

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
