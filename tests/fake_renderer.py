"""A tiny renderer plugin for tests of dataset generation (``generate(..., renderer=
tests.fake_renderer)``; no entry point needed: ``get_renderer("tests.fake_renderer")``
loads it by its module path).

It has the optional parts of the plugin interface (``scenes.renderers``) that dataset
generation uses: ``shared`` (``SharesInputs``: an array large enough that Ray keeps it
in its object store rather than inline in each task) and ``render_sample``
(``SampleRenderer``) with extra arrays and record fields saying where the sample was
rendered and what shared input the worker received.
"""

from __future__ import annotations

import os
import time
from pathlib import Path

import numpy as np

#: The dataset's ``source`` (scenes.dataset.SOURCES).
SOURCE = "sim"
#: float32 values of the shared array: 1 MiB, above Ray's 100 KiB limit for inline arguments.
SHARED_SIZE = 1 << 18
#: Image brightness per metre of indentation, so that a 1 mm dent is plainly visible.
GAIN_PER_M = 200.0


def shared_array() -> np.ndarray:
    return np.arange(SHARED_SIZE, dtype=np.float32)


def prepare(spec, mesh, camera, options: dict) -> dict:
    return {"renderer": "fake", **options}


def shared(spec, mesh, camera, options: dict) -> np.ndarray:
    return shared_array()


def node_id() -> str | None:
    """The Ray node this process runs on, or None outside Ray."""
    try:
        import ray
    except ImportError:
        return None
    return ray.get_runtime_context().get_node_id() if ray.is_initialized() else None


#: How long a sample waits at the ``meet`` barrier for the other nodes, seconds.
MEET_TIMEOUT_S = 60.0


def meet(folder: str, nodes: int, timeout: float = MEET_TIMEOUT_S) -> None:
    """Wait until samples have started on ``nodes`` distinct Ray nodes (each leaves its
    node's id in ``folder``), or ``timeout`` s: a busy node then holds its one CPU, so the
    scheduler must send the queued taps to the others. Without it, quick fake taps all
    finished on the first node while the second node's worker was still starting."""
    folder = Path(folder)
    (folder / f"node-{node_id()}").touch()
    end = time.monotonic() + timeout
    while len(list(folder.glob("node-*"))) < nodes and not (folder / "gave-up").exists():
        if time.monotonic() > end:  # once: later samples do not wait again
            (folder / "gave-up").touch()
        time.sleep(0.05)


class FakeRenderer:
    def __init__(self, ref_depth: np.ndarray, shared: np.ndarray, meet: dict | None = None):
        self.ref_depth = np.asarray(ref_depth, np.float32)
        self.shared_sum = float(np.sum(shared, dtype=np.float64))
        self.meet = meet

    @property
    def no_contact(self) -> np.ndarray:
        return np.full((*self.ref_depth.shape, 3), 0.5, np.float32)

    def render(self, depth: np.ndarray) -> np.ndarray:
        dent = np.clip(self.ref_depth - depth, 0.0, None)
        return np.clip(0.5 + GAIN_PER_M * dent, 0.0, 1.0)[..., None].repeat(3, axis=2)

    def render_sample(self, depth: np.ndarray) -> dict:
        if self.meet:
            meet(self.meet["folder"], self.meet["nodes"])
        image = self.render(depth)
        return {
            "image": image,
            "arrays": {"linear": 2.0 * image, "variance": np.full_like(image, 1e-4)},
            "record": {"node": node_id(), "pid": os.getpid(), "shared_sum": self.shared_sum},
        }


def make_renderer(spec, mesh, camera, ref_depth, options: dict, shared=None) -> FakeRenderer:
    if shared is None:
        raise ValueError("the fake renderer defines shared(), so it must be given shared=")
    return FakeRenderer(ref_depth, shared, options.get("meet"))
