"""Press images and what they are: a capture's real presses, simulated presses sampled like
them and rendered, and the trainings' replays of them (``studies.sim2real.presses``)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .augment import TRAININGS, Augmenter

#: The simulated presses' centres may lie this far outside the fitted presses' box, px.
SPREAD_PX = 4.0


@dataclass
class Presses:
    """Press images and what they are: ``images`` (N, h, w, 3) uint8, each one's
    no-contact frame ``frames`` (N, h, w, 3) uint8, ``centres`` (N, 2) px (u, v),
    ``depths`` (N,) metres, and ``indentation`` (N, h, w) metres (D_ref - D, simulated
    presses only)."""

    images: np.ndarray
    frames: np.ndarray
    centres: np.ndarray
    depths: np.ndarray
    indentation: np.ndarray | None = None

    def differences(self) -> np.ndarray:
        """(N, h, w, 3) float32: each image less its no-contact frame, in [0, 1] units."""
        return (self.images.astype(np.float32) - self.frames.astype(np.float32)) / np.float32(255.0)

    def subset(self, pick) -> "Presses":
        return Presses(self.images[pick], self.frames[pick], self.centres[pick], self.depths[pick],
                       None if self.indentation is None else self.indentation[pick])


def sample_presses(centres: np.ndarray, depths: np.ndarray, count: int, seed: int, shape: tuple[int, int],
                   margin_px: float = SPREAD_PX) -> tuple[np.ndarray, np.ndarray]:
    """``count`` simulated presses like the fitted ones (module doc): (centres (count, 2)
    px, depths (count,) metres), seeded."""
    centres, depths = np.asarray(centres, np.float64), np.asarray(depths, np.float64)
    if centres.ndim != 2 or centres.shape[1] != 2 or len(centres) == 0 or depths.shape != (len(centres),):
        raise ValueError(f"centres must be (N, 2) px and depths (N,) metres, N > 0; got {centres.shape} and "
                         f"{depths.shape}")
    if count < 1:
        raise ValueError(f"count must be >= 1 simulated presses, got {count}")
    rng = np.random.default_rng(seed)
    h, w = shape
    lo = np.maximum(centres.min(axis=0) - margin_px, [0.0, 0.0])
    hi = np.minimum(centres.max(axis=0) + margin_px, [w - 1.0, h - 1.0])
    return rng.uniform(lo, hi, (count, 2)), rng.uniform(depths.min(), depths.max(), count)


def real_presses(capture, ids) -> Presses:
    """A capture's presses ``ids``: its images, its no-contact frame, annotated centres and
    imported depths."""
    from scenes.dataset import read_samples
    from scenes.images import read_rgb, to_uint8

    by_id = {r["id"]: r for r in read_samples(capture.root)}
    shape = (capture.spec.camera.height, capture.spec.camera.width)
    images = np.stack([to_uint8(read_rgb(capture.root / by_id[i]["image"], shape)) for i in ids])
    frame = to_uint8(read_rgb(capture.root / "background.png", shape))
    missing = [i for i in ids if "contact_center_px" not in by_id[i]]
    if missing:
        raise ValueError(f"capture {capture.root}: presses {missing[:3]} have no annotated centre "
                         "(contact_center_px): an imported set of presses is needed")
    return Presses(images, np.broadcast_to(frame, images.shape).copy(),
                   np.array([by_id[i]["contact_center_px"] for i in ids], np.float64),
                   np.array([by_id[i]["measured_depth"] for i in ids], np.float64))


def simulate(capture, centres: np.ndarray, depths: np.ndarray, profile, field: str, out: Path, workers: int = 2,
             progress: bool = True) -> tuple[Presses, dict]:
    """Simulated presses of the capture's ball at ``centres`` (px) and ``depths`` (m),
    pressed on the rig and rendered by the calibrated fast path into the dataset ``out``
    (resumable): (the presses, the dataset's renderer settings)."""
    from phong_reference import plugin as phong
    from scenes.camera import Camera, reference_depth
    from scenes.dataset import load_sample, read_meta, read_samples
    from scenes.generate import generate
    from scenes.geometry import membrane_mesh
    from scenes.images import read_rgb, to_uint8
    from scenes.imports import press_tap
    from scenes.protocol import Protocol

    spec = capture.spec
    mesh = membrane_mesh(spec)
    camera = Camera.from_spec(spec)
    obj = capture.objects[0]
    taps = tuple(press_tap(i, obj, spec, mesh, camera, c, float(d)) for i, (c, d) in enumerate(zip(centres, depths)))
    options = {"field": field, **({"profile": str(profile)} if profile is not None else {"background": "none"})}
    generate(out, spec, Protocol(name="sim-presses", taps=taps), phong, options, workers=workers, progress=progress)
    records = {r["id"]: r for r in read_samples(out)}
    shape = camera.shape
    ref = reference_depth(mesh, camera)[0].astype(np.float32)
    images, indentation = [], []
    from scenes.dataset import sample_id

    for tap in taps:
        image, depth = load_sample(out, records[sample_id(tap.index, tap.object)], shape)
        images.append(to_uint8(image))
        delta = ref - np.asarray(depth, np.float32)
        delta[np.abs(delta) <= 1e-6] = 0.0
        indentation.append(delta)
    frame = to_uint8(read_rgb(Path(out) / "background.png", shape))
    images = np.stack(images)
    return (Presses(images, np.broadcast_to(frame, images.shape).copy(), np.asarray(centres, np.float64),
                    np.asarray(depths, np.float64), np.stack(indentation)), read_meta(out)["renderer"])


def moved_centres(centres: np.ndarray, params: dict, camera) -> np.ndarray:
    """(N, 2) where the image effects in ``params`` that move pixels (misalignment, lens
    distortion: ``studies.gap.effects.source_coordinates``) show a press the simulation
    shows at ``centres`` (u, v): the output pixel that samples it, found on the map's grid
    and refined by its local Jacobian. Unchanged where ``params`` moves nothing."""
    from studies.gap.effects import source_coordinates

    mis, dist = params.get("misalignment"), params.get("lens_distortion")
    centres = np.asarray(centres, np.float64)
    if mis is None and dist is None:
        return centres
    coords = source_coordinates(camera.shape, camera.f, (camera.cy, camera.cx), mis, dist)  # (row, col) sampled
    src = np.stack([coords[1], coords[0]], axis=-1)  # (H, W, 2) as (u, v)
    du = np.gradient(src, axis=1)  # d source / d output u
    dv = np.gradient(src, axis=0)
    out = np.empty_like(centres)
    for k, s in enumerate(centres):
        v, u = np.unravel_index(int(np.argmin(((src - s) ** 2).sum(axis=2))), src.shape[:2])
        J = np.stack([du[v, u], dv[v, u]], axis=1)  # columns: per output u, per output v
        step = np.linalg.lstsq(J, s - src[v, u], rcond=None)[0]
        out[k] = (u + step[0], v + step[1])
    return out


def trained_on(training: str, sim: Presses, augmenter: Augmenter | None, params: dict, seed: int) -> Presses:
    """The simulated presses as ``training`` shows them (module doc): images and frames
    with the same effects, and each press's centre where its effects show it
    (:func:`moved_centres`)."""
    if training == "none":
        return sim
    if augmenter is None:
        raise ValueError(f"training {training!r} needs the diagnosis' fast model")
    frame = sim.frames[0]
    camera = augmenter.model.camera
    if training == "diagnosed":
        images = augmenter.apply(sim.images, sim.indentation, params)
        zero = np.zeros((1,) + frame.shape[:2], np.float32)
        frames = np.broadcast_to(augmenter.apply(frame[None], zero, params)[0], images.shape).copy()
        centres = moved_centres(sim.centres, params, camera)
    elif training == "randomised":
        images = augmenter.randomised(sim.images, sim.indentation, seed)
        frames = augmenter.randomised_frames(frame, len(images), seed)
        draws = augmenter.draws(len(images), seed)
        centres = np.concatenate([moved_centres(sim.centres[i:i + 1], draws[i], camera) for i in range(len(images))])
    else:
        raise ValueError(f"training must be one of {TRAININGS}, got {training!r}")
    return Presses(images, frames, centres, sim.depths, sim.indentation)
