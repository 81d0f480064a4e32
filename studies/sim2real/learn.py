"""The models and their training, as published: MSE loss, Adadelta, batches of 64.

The paper trains a ResNet-18 for each task and input with Adadelta (learning rate 0.1)
on the mean squared error: against the one-hot indenter for classification, against the
contact's position for localisation; batches of 64, 8 batches an epoch, 100 epochs.
``Training`` holds those settings. Models (``MODELS``):

- ``resnet18``: torchvision's ResNet-18, from scratch (no pretrained weights: none can be
  downloaded here, and the paper's were not published), its output layer sized to the
  task;
- ``cnn``: a small convolutional network (four stride-2 3x3 convolutions of 8, 16, 32 and
  64 channels with batch norm, then two dense layers: flattening, not pooling, keeps where
  the contact is), about 20 times cheaper than the ResNet-18 on the same input;
- ``ridge``: scikit-learn's ridge regression on the pixels, the same MSE objective in
  closed form: the pipeline's model where torch is not installed (the tests on 2 cores).

Images go in as x / 255 - 0.5, channels first. torch and torchvision, and scikit-learn,
are imported only where a model of theirs is trained.
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass

import numpy as np

MODELS = ("resnet18", "cnn", "ridge")


@dataclass(frozen=True)
class Training:
    """The published set-up: batches of ``batch``, ``batches_per_epoch`` an epoch,
    ``epochs``, Adadelta at ``learning_rate``, MSE loss."""

    batch: int = 64
    batches_per_epoch: int = 8
    epochs: int = 100
    learning_rate: float = 0.1
    threads: int = 2

    @property
    def steps(self) -> int:
        return self.batches_per_epoch * self.epochs

    def to_dict(self) -> dict:
        return {**asdict(self), "optimiser": "Adadelta", "loss": "mean squared error", "steps": self.steps}


def need(model: str) -> str | None:
    """Why ``model`` cannot be trained here (a missing library), or None."""
    if model not in MODELS:
        return f"model must be one of {', '.join(MODELS)}, got {model!r}"
    import importlib.util

    missing = [m for m in (("torch", "torchvision") if model == "resnet18" else ("torch",) if model == "cnn"
                           else ("sklearn",)) if importlib.util.find_spec(m) is None]
    if missing:
        extra = "tactile-sim[sim2real]" if model != "ridge" else "scikit-learn"
        return f"model {model!r} needs {', '.join(missing)} (pip install '{extra}')"
    return None


def _torch():
    """torch, with triton hidden where it is not loaded yet.

    torch's optimisers import torch._dynamo on first use, which imports triton when it is
    installed (the PyPI wheel's dependency on Linux), and libtriton carries its own LLVM:
    loaded into a process where Mesa's llvmpipe already runs (MuJoCo's headless EGL, as
    the rig and the dataset driver use it) it segfaults (measured here: ``import triton``
    after one MuJoCo EGL depth frame). These models train on the CPU and compile nothing,
    so triton is marked absent (``sys.modules["triton"] = None``: its import then fails,
    and torch takes it as not installed)."""
    import sys

    if "triton" not in sys.modules:
        sys.modules["triton"] = None
    import torch

    return torch


def _inputs(images: np.ndarray) -> np.ndarray:
    """(N, h, w, 3) uint8 -> (N, 3, h, w) float32 x / 255 - 0.5."""
    x = np.asarray(images, np.float32).transpose(0, 3, 1, 2) / np.float32(255.0)
    return np.ascontiguousarray(x - np.float32(0.5))


def _cnn(outputs: int, shape: tuple[int, int]):
    import torch.nn as nn

    def block(a: int, b: int) -> list:
        return [nn.Conv2d(a, b, 3, stride=2, padding=1, bias=False), nn.BatchNorm2d(b), nn.ReLU(inplace=True)]

    h, w = shape
    for _ in range(4):
        h, w = (h + 1) // 2, (w + 1) // 2
    return nn.Sequential(*block(3, 8), *block(8, 16), *block(16, 32), *block(32, 64), nn.Flatten(),
                         nn.Linear(64 * h * w, 64), nn.ReLU(inplace=True), nn.Linear(64, outputs))


def build(model: str, outputs: int, shape: tuple[int, int]):
    """A torch model of ``outputs`` outputs for (3, h, w) inputs."""
    if model == "resnet18":
        import torchvision

        return torchvision.models.resnet18(weights=None, num_classes=outputs)
    if model == "cnn":
        return _cnn(outputs, shape)
    raise ValueError(f"{model!r} is not a torch model")


class Trained:
    """A trained model: ``predict(images) -> (N, outputs)``, and what training cost."""

    def __init__(self, model: str, net, seconds: float, steps: int):
        self.model, self.net, self.seconds, self.steps = model, net, seconds, steps

    def predict(self, images: np.ndarray, batch: int = 256) -> np.ndarray:
        x = _inputs(images)
        if self.model == "ridge":
            return self.net.predict(x.reshape(len(x), -1)).astype(np.float32)
        torch = _torch()
        self.net.eval()
        out = []
        with torch.no_grad():
            for i in range(0, len(x), batch):
                out.append(self.net(torch.from_numpy(x[i:i + batch])).numpy())
        return np.concatenate(out).astype(np.float32)


def train(model: str, images: np.ndarray, targets: np.ndarray, seed: int, training: Training = Training()
          ) -> Trained:
    """Train ``model`` on (N, h, w, 3) uint8 ``images`` against (N, K) float ``targets``
    with the MSE loss.

    Batches of ``batch`` are drawn in turn from seeded permutations of the training set,
    one after another, ``batches_per_epoch`` to an epoch, so every model sees ``steps *
    batch`` images whatever its training set's size: equal training cost.
    """
    why = need(model)
    if why:
        raise RuntimeError(why)
    images = np.asarray(images)
    targets = np.asarray(targets, np.float32)
    if images.ndim != 4 or images.shape[-1] != 3 or images.dtype != np.uint8:
        raise ValueError(f"images must be (N, h, w, 3) uint8, got {images.shape} {images.dtype}")
    if targets.ndim != 2 or len(targets) != len(images):
        raise ValueError(f"targets must be (N, K) with N = {len(images)}, got {targets.shape}")
    if not np.isfinite(targets).all():
        raise ValueError("targets hold NaN or infinite values")
    t0 = time.perf_counter()
    if model == "ridge":
        from sklearn.linear_model import Ridge

        x = _inputs(images).reshape(len(images), -1)
        net = Ridge(alpha=float(x.shape[1])).fit(x, targets)  # alpha per pixel: a fixed share of the gram's scale
        return Trained(model, net, time.perf_counter() - t0, 0)
    torch = _torch()
    torch.set_num_threads(training.threads)
    torch.manual_seed(seed)
    rng = np.random.default_rng(seed)
    net = build(model, targets.shape[1], images.shape[1:3])
    opt = torch.optim.Adadelta(net.parameters(), lr=training.learning_rate)
    x_all, y_all = _inputs(images), targets
    order, at = rng.permutation(len(x_all)), 0
    net.train()
    for _ in range(training.steps):
        pick = []
        while len(pick) < training.batch:
            take = order[at:at + training.batch - len(pick)]
            pick.extend(take)
            at += len(take)
            if at >= len(order):
                order, at = rng.permutation(len(x_all)), 0
        pick = np.asarray(pick)
        x, y = torch.from_numpy(x_all[pick]), torch.from_numpy(y_all[pick])
        opt.zero_grad(set_to_none=True)
        loss = torch.nn.functional.mse_loss(net(x), y)
        loss.backward()
        opt.step()
    return Trained(model, net, time.perf_counter() - t0, training.steps)
