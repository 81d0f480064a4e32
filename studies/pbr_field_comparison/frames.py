"""The study's frames from both renderers, at the reference's resolution.

``fast_frames``: the fast path (``phong_reference``) with each baked light field, no
background, area-averaged down to the reference's film (``downsample``).
``reference_frame``: the physically based reference (``pbr_tactile.render.reference``,
photon estimator), cached on disk. ``Settings``: the reference's resolution and Monte
Carlo budget.
"""

from __future__ import annotations

import dataclasses
import hashlib
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import trimesh
from skimage.transform import downscale_local_mean

from phong_reference.background import make_background
from phong_reference.bake import METHODS, bake_all
from phong_reference.render import Renderer, light_vectors
from scenes.cache import make_key
from scenes.camera import Camera
from scenes.dataset import npy_bytes
from scenes.files import atomic_write_bytes
from scenes.elastic import MembraneLayer
from scenes.spec import SensorSpec

#: Bump when what a cached reference holds changes.
CACHE_VERSION = 1
CACHE_FOLDER = "reference_cache"


@dataclass(frozen=True)
class Settings:
    """Resolution and Monte Carlo budget of the reference renders."""

    width: int = 320  # px, reference film
    height: int = 240  # px
    photons: int = 1 << 20  # photons per LED per pass
    passes: int = 4  # independent passes (>= 2, for the variance)
    spp: int = 64  # camera samples per pixel in all passes together
    seed: int = 0  # of every reference frame (common random numbers) and the bootstrap


#: ``--quick``: every step, in well under a minute.
QUICK = Settings(width=64, height=48, photons=1 << 14, passes=2, spp=8)


def check_settings(settings: Settings, camera: Camera) -> Settings:
    """Validate the reference film against the depth camera; returns ``settings``."""
    fx, fy = camera.width / settings.width, camera.height / settings.height
    if settings.width < 1 or settings.height < 1 or fx != fy or fx != int(fx):
        raise ValueError(
            f"width x height must divide the camera's {camera.width}x{camera.height} by one integer factor "
            f"(e.g. 320x240, 64x48), got {settings.width}x{settings.height}"
        )
    if settings.passes < 2:
        raise ValueError(f"passes must be >= 2 for a variance estimate, got {settings.passes}")
    if settings.photons < 1 or settings.spp < settings.passes:
        raise ValueError(f"photons must be >= 1 and spp >= passes, got photons={settings.photons}, spp={settings.spp}")
    return settings


def downsample(image: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """Area average of (H, W, 3) to (h, w, 3), as a box-filtered film pixel integrates."""
    fy, fx = image.shape[0] // shape[0], image.shape[1] // shape[1]
    if (fy * shape[0], fx * shape[1]) != image.shape[:2]:
        raise ValueError(f"image must be an integer multiple of {shape}, got {image.shape[:2]}")
    return downscale_local_mean(image, (fy, fx, 1)).astype(np.float32)


def fast_frames(
    spec: SensorSpec, camera: Camera, mesh: trimesh.Trimesh, ref_depth: np.ndarray, depths: list[np.ndarray],
    shape: tuple[int, int], layer: MembraneLayer,
) -> dict[str, np.ndarray]:
    """The fast path's frames with each field, no background, area-averaged to ``shape``.

    depths : K (H, W) contact depth maps, metres, deformed by ``layer`` (the surface the
    reference renders).  Returns method -> (K, h, w, 3) float32, [0, 1].
    """
    fields, _ = bake_all(mesh, camera, spec.leds, METHODS)
    background = make_background("none", camera)
    renderers = {method: Renderer(spec, camera, ref_depth, light_vectors(fields[method]), background, layer=layer)
                 for method in METHODS}
    # Each contact with every field in turn: the layer solves it once (it keeps its last ones).
    frames = [{m: downsample(r.render(d), shape) for m, r in renderers.items()} for d in depths]
    return {method: np.stack([f[method] for f in frames]) for method in METHODS}


def reference_code_digest() -> str:
    """Hash of the reference renderer's source and Mitsuba's version, so that cached
    frames are rendered again when the estimator changes (it has no version number)."""
    from importlib.metadata import PackageNotFoundError, version

    import pbr_tactile

    h = hashlib.sha256()
    for path in sorted(Path(pbr_tactile.__file__).parent.glob("*.py")):
        h.update(path.name.encode() + b"\0" + path.read_bytes())
    try:
        h.update(version("mitsuba").encode())
    except PackageNotFoundError:
        pass
    return h.hexdigest()[:16]


def reference_frame(
    name: str,
    depth: np.ndarray | None,
    ref_depth: np.ndarray,
    mesh: trimesh.Trimesh,
    spec: SensorSpec,
    camera: Camera,
    settings: Settings,
    cache: Path | None = None,
    progress=None,
) -> tuple[np.ndarray, np.ndarray, bool]:
    """One reference frame (depth None: no contact), from the cache when it holds it.

    Returns mean (h, w, 3) float32 linear, the variance of that mean, and whether it was
    read from the cache.
    """
    from pbr_tactile.effects import Effects
    from pbr_tactile.render import RenderSettings, reference

    effects = Effects()
    shape = (settings.height, settings.width)
    path = None
    if cache is not None:
        key = make_key("pbr_field_comparison", CACHE_VERSION, name, depth if depth is not None else "none", ref_depth,
                       spec.digest(), effects.to_dict(), dataclasses.asdict(settings), reference_code_digest())
        path = Path(cache) / f"{name}_{settings.width}x{settings.height}_{settings.photons}ph_{key}.npy"
        if path.exists():
            try:
                stack = np.load(path, allow_pickle=False)
                if stack.shape == (2,) + shape + (3,) and np.isfinite(stack).all():
                    return stack[0], stack[1], True
            except (OSError, ValueError) as exc:
                warnings.warn(f"cached reference {path} is unreadable ({exc}); rendering it again", stacklevel=2)
    est = reference(depth, None if depth is None else ref_depth, mesh, spec, camera, effects,
                    RenderSettings(spp=settings.spp, width=settings.width, height=settings.height, seed=settings.seed,
                                   passes=settings.passes, estimator="photons", photons=settings.photons),
                    progress=progress)
    if path is not None:
        atomic_write_bytes(path, npy_bytes(np.stack([est.mean, est.variance]).astype(np.float32)))
    return est.mean, est.variance, False
