"""How visible a capture's contacts are: the reference's contact contrast under physical
settings, beside the fast path's, for taps of a study's capture.

The study's classifiers sit at chance on the reference's virtual capture because its
contacts barely show. This measures that, and whether any physical setting of the
reference (``pbr_tactile.effects.Effects``: paint albedo, a clear elastomer, the photon
kernel, ...) makes them show. Each tap is rendered by the reference's photon estimator
from the fast path's replay depth (the same contact), with the no-contact frame of the
same seed beside it (common random numbers), and exposed as a dataset is
(``pbr_tactile.plugin``: the frame's 99.5th percentile inside the image circle at 0.8).

``contact_contrast`` scores a tap: the mean |image - frame| (channels averaged, [0, 1])
over the dent and its rim, over the image circle far from it (the noise the contact is
seen through), and the first relative to the frame's brightness there::

    python -m studies.sim2real.visibility --study DIR --taps 000003_dots,000020_sphere \\
        --setting default= --setting albedo_0.3=coating_albedo=0.3 --out visibility.json
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
from scipy import ndimage

from scenes.camera import CONTACT_EPS_M, Camera
from scenes.dataset import atomic_write_json, read_samples
from scenes.images import read_rgb

from . import data

#: The contact region: the touched pixels grown by this many pixels (the dent's rim).
RIM_PX = 6
#: "Far" is the image circle beyond this many pixels of the touched ones.
FAR_PX = 60


def contact_contrast(image: np.ndarray, frame: np.ndarray, touched: np.ndarray, mask: np.ndarray,
                     rim_px: int = RIM_PX, far_px: int = FAR_PX) -> dict:
    """(H, W, 3) image and no-contact frame in [0, 1], (H, W) bool touched pixels and
    image circle -> {"contact", "far", "relative", "peak"}: the mean |image - frame|
    (channels averaged) over the touched pixels grown by ``rim_px`` inside the circle,
    over the circle beyond ``far_px`` of them, the first over the frame's mean there, and
    its 95th percentile over the contact."""
    image, frame = np.asarray(image, np.float64), np.asarray(frame, np.float64)
    if image.shape != frame.shape or image.ndim != 3 or image.shape[:2] != touched.shape:
        raise ValueError(f"image {image.shape}, frame {frame.shape} and touched {touched.shape} must be (H, W, 3), "
                         "(H, W, 3) and (H, W)")
    if not touched.any():
        raise ValueError("touched marks no pixel: a tap without contact has no contrast")
    region = ndimage.binary_dilation(touched, iterations=rim_px) & mask
    far = mask & ~ndimage.binary_dilation(touched, iterations=far_px)
    change = np.abs(image - frame).mean(axis=-1)
    bright = frame.mean(axis=-1)[region].mean()
    return {"contact": float(change[region].mean()), "far": float(change[far].mean()) if far.any() else None,
            "relative": float(change[region].mean() / bright) if bright > 0 else None,
            "peak": float(np.percentile(change[region], 95))}


def measure(replay: str | Path, taps: list[str], settings: dict[str, list[str]], photons: int = 1 << 18,
            passes: int = 2, camera_spp: int = 16, film=(320, 240), kernel_radius_mm: float = 0.75,
            seed: int = 0) -> dict:
    """The contact contrast of each tap of a fast-path replay (its depth maps and images)
    rendered by the reference under each named list of ``Effects`` settings, and the
    fast path's own (the replay's image against its background)."""
    from skimage.transform import resize

    from pbr_tactile.effects import Effects
    from pbr_tactile.plugin import EXPOSURE_LEVEL, EXPOSURE_PERCENTILE
    from pbr_tactile.render import RenderSettings, reference
    from scenes.geometry import membrane_mesh
    from scenes.rig import tap_depths

    replay = Path(replay)
    spec = data.dataset_spec(replay)
    camera = Camera.from_spec(spec)
    by_id = {s["id"]: s for s in read_samples(replay)}
    missing = [t for t in taps if t not in by_id]
    if missing:
        raise ValueError(f"taps {missing} are not samples of {replay}")
    paths = {t: replay / "depth" / f"{t}.npy" for t in taps}
    absent = [str(p) for p in paths.values() if not p.exists()]
    if absent:
        raise ValueError(f"{absent[0]} is missing: the replay must keep its depth maps")
    mesh = membrane_mesh(spec)
    rig = tap_depths(spec, (), mesh)
    ref, _ = next(rig)  # the no-contact depth D_ref
    rig.close()
    depths = {t: np.load(p) for t, p in paths.items()}
    touched = {t: np.abs(d - ref) > CONTACT_EPS_M for t, d in depths.items()}
    frame = read_rgb(replay / "background.png", camera.shape)
    out = {"fast_path": {}, "settings": {}}
    for t in taps:
        image = read_rgb(replay / by_id[t]["image"], camera.shape)
        out["fast_path"][t] = contact_contrast(image, frame, touched[t], camera.mask)
    width, height = film
    for name, items in settings.items():
        effects = Effects().with_settings(items)
        kw = RenderSettings(spp=camera_spp * passes, width=width, height=height, seed=seed, passes=passes,
                            photons=photons, kernel_radius=kernel_radius_mm * 1e-3, inscatter="fluence")
        t0 = time.perf_counter()

        def shot(depth):
            est = reference(depth, ref, mesh, spec, camera, effects, kw)
            return resize(est.mean, camera.shape, order=1, mode="edge", preserve_range=True)

        still = shot(None)
        gain = EXPOSURE_LEVEL / np.percentile(still[camera.mask], EXPOSURE_PERCENTILE)
        rows = {t: contact_contrast(np.clip(gain * shot(np.where(touched[t], depths[t], ref)), 0, 1),
                                    np.clip(gain * still, 0, 1), touched[t], camera.mask) for t in taps}
        out["settings"][name] = {"effects": items, "exposure_gain": float(gain), "taps": rows,
                                 "seconds": time.perf_counter() - t0}
    fast = np.mean([r["contact"] for r in out["fast_path"].values()])
    for row in out["settings"].values():
        row["fast_path_over_this"] = float(fast / np.mean([r["contact"] for r in row["taps"].values()]))
    out["render"] = {"photons": photons, "passes": passes, "camera_spp": camera_spp, "film": list(film),
                     "kernel_radius_mm": kernel_radius_mm, "seed": seed}
    out["what"] = ("per tap: the mean |image - no-contact frame| ([0, 1], channels averaged) over the dent and "
                   f"its rim ({RIM_PX} px), over the image circle beyond {FAR_PX} px of it (far), the first over "
                   "the frame's brightness there (relative), and its 95th percentile (peak); fast_path_over_this: "
                   "the fast path's mean contact change over this setting's")
    return out


def _setting(text: str) -> tuple[str, list[str]]:
    name, sep, rest = text.partition("=")
    if not sep or not name:
        raise argparse.ArgumentTypeError(f"--setting {text!r}: expected NAME=[EFFECT=VALUE[;EFFECT=VALUE...]]")
    return name, [item for item in rest.split(";") if item]


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m studies.sim2real.visibility", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--study", required=True, help="the study's folder (its replay_plane replays the capture)")
    p.add_argument("--taps", required=True, help="comma-separated sample ids of the capture")
    p.add_argument("--setting", type=_setting, action="append", required=True,
                   help="NAME=EFFECT=VALUE;EFFECT=VALUE... (pbr_tactile.effects.Effects; NAME= alone: the defaults)")
    p.add_argument("--photons", type=int, default=1 << 18)
    p.add_argument("--passes", type=int, default=2)
    p.add_argument("--kernel-radius-mm", type=float, default=0.75)
    p.add_argument("--out", required=True, help="the JSON written")
    a = p.parse_args(argv)
    doc = measure(Path(a.study) / "replay_plane", a.taps.split(","), dict(a.setting), photons=a.photons,
                  passes=a.passes, kernel_radius_mm=a.kernel_radius_mm)
    atomic_write_json(Path(a.out), doc)
    for name, row in doc["settings"].items():
        cells = ", ".join(f"{t} {r['contact']:.4f} (far {r['far']:.4f})" for t, r in row["taps"].items())
        print(f"{name}: {cells}; the fast path's is {row['fast_path_over_this']:.0f} times this")
    return 0


if __name__ == "__main__":
    sys.exit(main())
