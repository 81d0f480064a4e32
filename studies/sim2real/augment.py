"""Simulated training images with effects of the gap diagnosis' catalogue applied.

Three ways to train on the fast path's images (``TRAININGS``):

- ``none``: the images as rendered;
- ``diagnosed``: the effects ``tactile-sim diagnose`` selected on the capture against
  the fast path's replay of it, at their fitted values (``report.json``'s last
  ``selection`` step, with the capture's exposure where it was fitted), the same for
  every image;
- ``randomised``: domain randomisation, the common practice: every effect of the
  catalogue on every image, each at a random strength over its range. Per image and
  effect, a point x is drawn uniformly in the effect's parameter box and the effect is
  set to identity + s (x - identity), s uniform in [0, 1] (s = 1 everywhere would put
  every image at the box's extremes as often as near the truth).

Both re-render each image's contact with the diagnosis' own fast model
(``studies.gap.model.FastModel``) from the stored indentation, at the arrays' working
resolution: pred = optics(sim + M(theta) - M(identity)).
"""

from __future__ import annotations

import numpy as np

from studies.gap import effects as fx

TRAININGS = ("none", "randomised", "diagnosed")


def diagnosed_params(report: dict) -> dict:
    """{effect: {param: value}} of a diagnosis report's selected effects (its last
    selection step); {} where it selected none."""
    steps = report.get("selection") or []
    if not steps:
        return {}
    params = steps[-1].get("params")
    if not isinstance(params, dict):
        raise ValueError("the diagnosis report's last selection step has no 'params' object")
    return {name: dict(values) for name, values in params.items()}


def random_params(catalogue: dict, rng: np.random.Generator) -> dict:
    """Every effect of ``catalogue`` with parameters at a random strength over its range
    (module docstring)."""
    out = {}
    for name, effect in catalogue.items():
        if not effect.params:
            continue
        s = rng.uniform()
        out[name] = {p.name: p.identity + s * (rng.uniform(p.low, p.high) - p.identity) for p in effect.params}
    return out


class Augmenter:
    """The diagnosis' fast model of a simulated dataset, re-rendering its images with
    effects at 1/``factor`` of the camera's resolution.

    spec : the sensor; renderer : the simulated dataset's renderer settings (its
    dataset.json ``renderer``: the field, the background).
    """

    def __init__(self, spec, renderer: dict, factor: int):
        from studies.gap.model import FastModel

        self.model = FastModel(spec, renderer, factor, exposure=False)
        self.catalogue = self.model.catalogue

    def apply(self, images: np.ndarray, indentation: np.ndarray | None, params: dict) -> np.ndarray:
        """(N, h, w, 3) uint8 images with ``params`` ({effect: {param: value}}) applied,
        uint8; ``indentation`` (N, h, w) metres, needed by the membrane and light effects."""
        if not params:
            return images
        sim = images.astype(np.float32) / 255.0
        depth = None if indentation is None else (self.model.ref[None] - indentation).astype(np.float32)
        out = self.model.predict(sim, depth, params)
        return np.clip(np.rint(out * 255.0), 0, 255).astype(np.uint8)

    def draws(self, count: int, seed: int) -> list[dict]:
        """The random draws (``random_params``) of ``randomised``'s ``count`` images, in order:
        the seed fixes them."""
        rng = np.random.default_rng(seed)
        return [random_params(self.catalogue, rng) for _ in range(count)]

    def randomised(self, images: np.ndarray, indentation: np.ndarray | None, seed: int) -> np.ndarray:
        """Each image with its own random draw of every effect (``draws``)."""
        draws = self.draws(len(images), seed)
        return self._each(len(images), lambda i: self.apply(
            images[i:i + 1], None if indentation is None else indentation[i:i + 1], draws[i])[0], images.dtype,
            images.shape[1:])

    def randomised_frames(self, frame: np.ndarray, count: int, seed: int) -> np.ndarray:
        """(count, h, w, 3) uint8: the no-contact ``frame`` (h, w, 3) uint8 under each draw
        of ``randomised(images, ..., seed)`` with ``count`` images, so that each image has
        the frame it would have shown without contact."""
        draws = self.draws(count, seed)
        zero = np.zeros((1,) + frame.shape[:2], np.float32)
        return self._each(count, lambda i: self.apply(frame[None], zero, draws[i])[0], frame.dtype, frame.shape)

    @staticmethod
    def _each(count: int, one, dtype, shape) -> np.ndarray:
        import os
        from concurrent.futures import ThreadPoolExecutor

        out = np.empty((count,) + tuple(shape), dtype)

        def put(i: int) -> None:
            out[i] = one(i)

        with ThreadPoolExecutor(max_workers=os.cpu_count() or 1) as pool:  # numpy and OpenCV release the GIL
            list(pool.map(put, range(count)))
        return out


def check_effects(params: dict) -> None:
    """Refuse effect names outside the catalogue."""
    unknown = sorted(set(params) - set(fx.EFFECTS))
    if unknown:
        raise ValueError(f"unknown effects {unknown}; the catalogue has {', '.join(fx.EFFECTS)}")
