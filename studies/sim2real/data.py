"""The study's datasets as arrays: images at a working resolution, and every label.

A dataset folder (``docs/dataset-format.md``: a capture of the rig, a replay, or a
simulated protocol) becomes one ``Arrays``: its 8-bit images averaged over
``factor`` x ``factor`` blocks (kept as 8-bit: averaging adds less than the quantisation
it removes), each sample's indenter (its index in ``scenes.indenters.INDENTERS``), the
contact point on the undeformed membrane and its pixel through the camera model, the tap's
row, position and replica, and, for the compact fast-path datasets
(``studies.sim2real.plugin``), the indentation map the effects re-render from.

Reading 23,040 PNGs takes minutes, so ``load`` keeps each dataset's arrays in a cache
file keyed by its ``dataset.json`` and sample count, written atomically.
"""

from __future__ import annotations

import hashlib
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, fields
from pathlib import Path

import numpy as np

from scenes.camera import Camera, project
from scenes.dataset import DatasetError, load_sample, read_meta, read_samples, sha256_json
from scenes.files import atomic_write_bytes
from scenes.images import block_mean, read_rgb
from scenes.indenters import INDENTERS
from scenes.spec import SensorSpec
from scenes.spec_read import spec_from_dict

#: Bump when what ``load`` stores changes, so old cache files are not read.
CACHE_VERSION = 1


@dataclass
class Arrays:
    """One dataset, sample-aligned.

    images : (N, h, w, 3) uint8 at 1/``factor`` of the camera's resolution.
    labels : (N,) int, the indenter's index in ``INDENTERS``.
    pixel : (N, 2) float32, the contact point's (u, v) in full-resolution pixels.
    point : (N, 3) float32, the contact point on the undeformed membrane, metres.
    path, position, replica : (N,) int, the tap's row, its contact along it, its copy.
    indentation : (N, h, w) float32 D_ref - D block means, metres, or None.
    ids : (N,) str.
    """

    images: np.ndarray
    labels: np.ndarray
    pixel: np.ndarray
    point: np.ndarray
    path: np.ndarray
    position: np.ndarray
    replica: np.ndarray
    ids: np.ndarray
    indentation: np.ndarray | None
    factor: int

    def __len__(self) -> int:
        return len(self.labels)

    def take(self, index) -> "Arrays":
        index = np.asarray(index)
        return Arrays(**{f.name: (getattr(self, f.name)[index] if isinstance(getattr(self, f.name), np.ndarray)
                                  else getattr(self, f.name)) for f in fields(self)})


def aligned(arrays: Arrays, ids: np.ndarray, what: str) -> Arrays:
    """``arrays`` in the order of ``ids`` (a replay's samples finish in any order), refusing
    a set whose ids are not those."""
    where = {str(i): k for k, i in enumerate(arrays.ids)}
    missing = [str(i) for i in ids if str(i) not in where]
    if missing or len(where) != len(ids):
        raise DatasetError(f"{what}: its samples are not the capture's (missing {missing[:3]}, "
                           f"{len(where)} samples against {len(ids)})")
    return arrays.take([where[str(i)] for i in ids])


def dataset_spec(root: str | Path) -> SensorSpec:
    return spec_from_dict(read_meta(root)["sensor"], source=f"{root}/dataset.json sensor")


def _key(root: Path, count: int, factor: int) -> str:
    meta = (root / "dataset.json").read_bytes()
    return hashlib.sha256(meta + f"|{count}|{factor}|{CACHE_VERSION}".encode()).hexdigest()[:20]


def load(root: str | Path, factor: int = 4, cache: str | Path | None = None, workers: int = 2,
         progress: bool = False) -> Arrays:
    """The arrays of a dataset folder at 1/``factor`` of its camera's resolution.

    cache : a folder for the arrays' cache file (``<folder name>-<key>.npz``); None: none.
    Refuses, naming the sample, an object that is not one of the paper's 8 indenters and
    a stored indentation of another resolution.
    """
    root = Path(root)
    meta = read_meta(root)
    records = read_samples(root)
    if not records:
        raise DatasetError(f"{root} has no samples")
    path = None
    if cache is not None:
        path = Path(cache) / f"{root.name}-{_key(root, len(records), factor)}.npz"
        if path.exists():
            with np.load(path, allow_pickle=False) as z:
                data = {k: z[k] for k in z.files}
            ind = data.pop("indentation")
            return Arrays(**data, indentation=None if ind.size == 0 else ind, factor=factor)
    spec = spec_from_dict(meta["sensor"], source=f"{root}/dataset.json sensor")
    camera = Camera.from_spec(spec)
    h, w = camera.height // factor, camera.width // factor
    if camera.height % factor or camera.width % factor:
        raise ValueError(f"factor {factor} does not divide {root}'s {camera.width}x{camera.height} images")
    for r in records:
        if r.get("object") not in INDENTERS:
            raise DatasetError(f"{root}: sample {r.get('id')}: object {r.get('object')!r} is not one of the "
                               f"indenters {', '.join(INDENTERS)}")
    has_ind = all("indentation" in r for r in records)

    def one(r: dict):
        image, _ = load_sample(root, r, camera.shape)
        small = np.clip(np.rint(block_mean(image, factor) * 255.0), 0, 255).astype(np.uint8)
        ind = None
        if has_ind:
            ind = np.load(root / r["indentation"], allow_pickle=False)
            if ind.shape != (h, w):
                raise DatasetError(f"{root}: sample {r['id']}: indentation is {ind.shape}, expected {(h, w)} "
                                   f"(factor {factor})")
        return small, ind

    from tqdm import tqdm

    with ThreadPoolExecutor(max_workers=workers) as pool:
        out = list(tqdm(pool.map(one, records), total=len(records), desc=f"read {root.name}", disable=not progress))
    point = np.array([r["contact_point"] for r in records], np.float64)
    arrays = Arrays(
        images=np.stack([o[0] for o in out]),
        labels=np.array([INDENTERS.index(r["object"]) for r in records], np.int64),
        pixel=project(point, camera).astype(np.float32),
        point=point.astype(np.float32),
        path=np.array([r.get("path", -1) for r in records], np.int64),
        position=np.array([r.get("position", -1) for r in records], np.int64),
        replica=np.array([r.get("replica", 0) for r in records], np.int64),
        ids=np.array([r["id"] for r in records]),
        indentation=np.stack([o[1] for o in out]).astype(np.float32) if has_ind else None,
        factor=factor,
    )
    if path is not None:
        import io

        buf = io.BytesIO()
        np.savez(buf, **{f.name: getattr(arrays, f.name) for f in fields(arrays)
                         if f.name not in ("indentation", "factor")},
                 indentation=arrays.indentation if arrays.indentation is not None else np.zeros(0, np.float32))
        atomic_write_bytes(path, buf.getvalue())
    return arrays


def frame(root: str | Path, factor: int = 4) -> np.ndarray:
    """(h, w, 3) uint8: a dataset's no-contact frame (its ``background.png``) at 1/``factor``
    of its camera's resolution, made as ``load`` makes each image."""
    root = Path(root)
    camera = Camera.from_spec(dataset_spec(root))
    path = root / "background.png"
    if not path.exists():
        raise DatasetError(f"{root} has no background.png: difference inputs need the no-contact frame")
    try:
        image = read_rgb(path, camera.shape)
    except ValueError as exc:
        raise DatasetError(f"{root}: background.png: {exc}") from None
    return np.clip(np.rint(block_mean(image, factor) * 255.0), 0, 255).astype(np.uint8)


def circle(root: str | Path, factor: int = 4, share: float = 0.5) -> np.ndarray:
    """(h, w) bool: the blocks of a dataset's image circle, at 1/``factor`` of its camera's
    resolution, more than ``share`` of whose pixels are inside it."""
    camera = Camera.from_spec(dataset_spec(root))
    return block_mean(camera.mask.astype(np.float32), factor) > share


def split(labels: np.ndarray, seed: int, test_share: float = 0.2) -> tuple[np.ndarray, np.ndarray]:
    """(train, test) sample indices: a seeded split stratified by indenter, ``test_share``
    of each indenter's samples (rounded, at least one where it has two) held out."""
    rng = np.random.default_rng(seed)
    train, test = [], []
    for c in np.unique(labels):
        idx = rng.permutation(np.flatnonzero(labels == c))
        k = int(round(test_share * len(idx)))
        k = max(k, 1) if len(idx) > 1 else 0
        test.append(idx[:k])
        train.append(idx[k:])
    return np.sort(np.concatenate(train)), np.sort(np.concatenate(test))


class MembraneLookup:
    """Pixels to points on the undeformed membrane, through the camera model: the camera
    ray through a (u, v) at full resolution meets the membrane at D_ref(u, v) along it
    (the no-contact depth map of ``scenes.camera.reference_depth``); a pixel off the
    membrane is moved to the nearest pixel on it."""

    def __init__(self, spec: SensorSpec):
        from scipy import ndimage

        from scenes.camera import reference_depth
        from scenes.geometry import membrane_mesh

        self.camera = Camera.from_spec(spec)
        depth, valid = reference_depth(membrane_mesh(spec), self.camera)
        valid = valid & self.camera.mask
        self.points = (depth[..., None] * self.camera.rays).astype(np.float64)  # (H, W, 3)
        _, (self.near_v, self.near_u) = ndimage.distance_transform_edt(~valid, return_indices=True)

    def __call__(self, pixel: np.ndarray) -> np.ndarray:
        """(N, 2) (u, v) px -> (N, 3) metres, at the nearest pixel (a pixel is about 0.1 mm
        of the GelTip's membrane)."""
        pixel = np.asarray(pixel, np.float64)
        h, w = self.camera.height, self.camera.width
        u = np.clip(np.rint(pixel[:, 0]), 0, w - 1).astype(int)
        v = np.clip(np.rint(pixel[:, 1]), 0, h - 1).astype(int)
        return self.points[self.near_v[v, u], self.near_u[v, u]]


def describe(root: str | Path) -> dict:
    """What a dataset folder is, for results.json: its path, source, protocol, samples."""
    meta = read_meta(root)
    return {"dir": str(root), "source": meta.get("source"), "protocol": meta.get("protocol", {}).get("name"),
            "samples": len(read_samples(root)), "renderer": {k: v for k, v in (meta.get("renderer") or {}).items()
                                                             if k in ("renderer", "field", "background", "kind")}}


def sha(obj) -> str:
    """A short digest of a JSON-able object (``scenes.dataset.sha256_json``'s first 16)."""
    return sha256_json(obj)[:16]
