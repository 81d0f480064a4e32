"""Two datasets of one tapping protocol, matched sample by sample: a real capture and its
simulated counterpart (the dataset format of ``docs/dataset-format.md``).

Everything that would make a comparison meaningless is refused with an error that names
the dataset and the sample: different protocols or sensors' image sizes, samples present
in one dataset only, missing or unreadable images, images of the wrong size, depth maps
of the wrong shape or with NaNs, an empty dataset, and a split with nothing on one side.
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from scenes.dataset import DatasetError, read_meta, read_samples
from scenes.images import read_rgb
from scenes.spec import SensorSpec
from scenes.spec_read import spec_from_dict


@dataclass
class Pairs:
    """Real and simulated images of the same taps.

    ids : sample ids, in the simulated dataset's order.
    records : the simulated dataset's sample records (object, path, position, depths).
    real, sim : (N, H, W, 3) float32 linear RGB in [0, 1].
    depth : (N, H, W) float32 metres (planar z), from the simulated dataset; None when it
        has none.
    spec : the simulated dataset's sensor.
    """

    real_dir: Path
    sim_dir: Path
    real_meta: dict
    sim_meta: dict
    ids: list[str]
    records: list[dict]
    real: np.ndarray
    sim: np.ndarray
    depth: np.ndarray | None
    spec: SensorSpec
    extra: dict = field(default_factory=dict)

    def __len__(self) -> int:
        return len(self.ids)

    @property
    def shape(self) -> tuple[int, int]:
        """(H, W) of every image."""
        return tuple(self.real.shape[1:3])

    def subset(self, index) -> Pairs:
        """The pairs at ``index`` (indices or a boolean mask), sharing the metadata."""
        index = np.flatnonzero(index) if np.asarray(index).dtype == bool else np.asarray(index, dtype=int)
        return Pairs(self.real_dir, self.sim_dir, self.real_meta, self.sim_meta, [self.ids[i] for i in index],
                     [self.records[i] for i in index], self.real[index], self.sim[index],
                     None if self.depth is None else self.depth[index], self.spec, dict(self.extra))


def _protocol_identity(meta: dict) -> tuple:
    protocol = meta.get("protocol") or {}
    return protocol.get("name"), protocol.get("sha256")


def check_compatible(real_meta: dict, sim_meta: dict, real_dir: Path, sim_dir: Path) -> None:
    """Refuse datasets of different protocols or image sizes, naming both."""
    if _protocol_identity(real_meta) != _protocol_identity(sim_meta):
        raise DatasetError(
            f"{real_dir} and {sim_dir} follow different protocols "
            f"(real: {_protocol_identity(real_meta)}, sim: {_protocol_identity(sim_meta)}); "
            "a diagnosis compares the same taps, so both must come from one protocol"
        )
    if list(real_meta.get("image_size", [])) != list(sim_meta.get("image_size", [])):
        raise DatasetError(
            f"{real_dir} has {real_meta.get('image_size')} px images and {sim_dir} has "
            f"{sim_meta.get('image_size')}; the two datasets must have the same image size"
        )


def _first(ids: list[str]) -> str:
    """The first five of ``ids``, for a message."""
    return ", ".join(ids[:5]) + (" ..." if len(ids) > 5 else "")


def _match(real_records: list[dict], sim_records: list[dict], real_dir: Path, sim_dir: Path):
    if not sim_records:
        raise DatasetError(f"{sim_dir} holds no samples (samples.jsonl is empty or missing)")
    if not real_records:
        raise DatasetError(f"{real_dir} holds no samples (samples.jsonl is empty or missing)")
    real_by_id = {r["id"]: r for r in real_records}
    sim_ids = [r["id"] for r in sim_records]
    only_sim = [i for i in sim_ids if i not in real_by_id]
    only_real = sorted(set(real_by_id) - set(sim_ids))
    for where, missing, other in ((real_dir, only_sim, sim_dir), (sim_dir, only_real, real_dir)):
        if missing:
            raise DatasetError(f"{where} lacks {len(missing)} sample(s) that {other} has: {_first(missing)}")
    return [real_by_id[i] for i in sim_ids]


def _read_image(root: Path, record: dict, shape: tuple[int, int]) -> np.ndarray:
    name = record.get("image")
    if not name:
        raise DatasetError(f"{root}: sample {record['id']} has no image file in its record")
    path = root / name
    if not path.is_file():
        raise DatasetError(f"{root}: sample {record['id']}: image {name} is missing")
    try:
        return read_rgb(path, shape)
    except ValueError as exc:
        raise DatasetError(f"{root}: sample {record['id']}: {exc}") from None


def _read_depth(root: Path, record: dict, shape: tuple[int, int]) -> np.ndarray:
    try:
        depth = np.load(root / record["depth"], allow_pickle=False)
    except (OSError, ValueError) as exc:
        raise DatasetError(f"{root}: sample {record['id']}: depth {record['depth']} is unreadable: {exc}") from None
    if depth.shape != shape or depth.dtype.kind != "f":
        raise DatasetError(f"{root}: sample {record['id']}: depth {record['depth']} must be {shape} float metres, "
                           f"got {depth.shape} {depth.dtype}")
    if not np.isfinite(depth).all() or (depth <= 0).any():
        raise DatasetError(f"{root}: sample {record['id']}: depth {record['depth']} has non-finite or "
                           "non-positive values; expected planar z-depth in metres > 0")
    return depth.astype(np.float32, copy=False)


def _only(records: list[dict], ids: set[str], root: Path) -> list[dict]:
    """The records of ``ids``; DatasetError naming those ``root`` lacks."""
    missing = sorted(ids - {r["id"] for r in records})
    if missing:
        raise DatasetError(f"{root} lacks {len(missing)} of the sample(s) asked for: {_first(missing)}")
    return [r for r in records if r["id"] in ids]


def load_pairs(real_dir: str | Path, sim_dir: str | Path, progress=None, ids=None) -> Pairs:
    """Read a real dataset and its simulated counterpart, matched by sample id, in the
    protocol's order.

    progress : optional callable(done, total) for a progress bar.
    ids : the samples to pair, which both datasets must hold (a replay of some of a
        capture's presses); None: every sample, and both must hold the same ones.
    """
    real_dir, sim_dir = Path(real_dir), Path(sim_dir)
    real_meta, sim_meta = read_meta(real_dir), read_meta(sim_dir)
    check_compatible(real_meta, sim_meta, real_dir, sim_dir)
    sim_records, real_records = read_samples(sim_dir), read_samples(real_dir)
    if ids is not None:
        ids = {str(i) for i in ids}
        if not ids:
            raise ValueError("ids must name at least one sample, got none")
        sim_records, real_records = _only(sim_records, ids, sim_dir), _only(real_records, ids, real_dir)
    # in the protocol's order, not the order the samples finished in (parallel workers finish in any
    # order), so that a diagnosis of the same datasets is the same every run
    sim_records = sorted(sim_records, key=lambda r: (r.get("tap_index", 0), str(r["id"])))
    real_records = _match(real_records, sim_records, real_dir, sim_dir)
    width, height = (int(v) for v in sim_meta["image_size"])
    shape = (height, width)
    try:
        spec = spec_from_dict(sim_meta["sensor"], source=f"{sim_dir}/dataset.json sensor")
    except (KeyError, ValueError, TypeError) as exc:
        raise DatasetError(f"{sim_dir}/dataset.json has no usable sensor spec: {exc}") from None

    n = len(sim_records)
    real = np.empty((n,) + shape + (3,), np.float32)
    sim = np.empty_like(real)
    has_depth = all(r.get("depth") for r in sim_records)
    depth = np.empty((n,) + shape, np.float32) if has_depth else None

    def load(i: int) -> None:
        real[i] = _read_image(real_dir, real_records[i], shape)
        sim[i] = _read_image(sim_dir, sim_records[i], shape)
        if depth is not None:
            depth[i] = _read_depth(sim_dir, sim_records[i], shape)

    with ThreadPoolExecutor(max_workers=4) as pool:
        for done, _ in enumerate(pool.map(load, range(n)), start=1):
            if progress is not None:
                progress(done, n)
    return Pairs(real_dir, sim_dir, real_meta, sim_meta, [r["id"] for r in sim_records], sim_records, real, sim,
                 depth, spec)


def split(pairs: Pairs, heldout_fraction: float = 0.5, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Boolean masks (train, held-out) over the samples, stratified by object.

    Each object's samples are shuffled with ``seed`` and ``heldout_fraction`` of them
    (rounded, at least one when an object has two or more) are held out, so every object
    appears on both sides where it can. An empty side is an error.
    """
    if not 0 < heldout_fraction < 1:
        raise ValueError(f"heldout_fraction must be in (0, 1), got {heldout_fraction}")
    rng = np.random.default_rng(seed)
    objects = np.array([str(r.get("object", "")) for r in pairs.records])
    heldout = np.zeros(len(pairs), bool)
    for obj in sorted(set(objects)):
        members = np.flatnonzero(objects == obj)
        rng.shuffle(members)
        k = round(heldout_fraction * len(members))
        if len(members) >= 2:
            k = min(max(k, 1), len(members) - 1)
        heldout[members[:k]] = True
    train = ~heldout
    for name, side in (("training", train), ("held-out", heldout)):
        if not side.any():
            raise DatasetError(
                f"the {name} split of {pairs.real_dir} / {pairs.sim_dir} is empty ({len(pairs)} sample(s), "
                f"held-out fraction {heldout_fraction}); a diagnosis needs at least one sample on each side"
            )
    return train, heldout
