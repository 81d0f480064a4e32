"""Which light field brings the fast Phong path closest to physically guided light?

For each contact (eight base-protocol taps, one per paper indenter, captured on the MuJoCo
rig at the protocol's 2 mm; on the GelTip, four analytic indenters pressed as in
``tactile-sim demo`` and the six published depth maps ``sim_depth/0..5.npy`` where they
stay out of the glass; on any other membrane, taps drawn per class of region instead,
see below), at its real depth, this study renders the fast path
(``phong_reference``) with each baked light field (linear, plane, geodesic, transport)
and compares it with the physically based reference (``pbr_tactile.render.reference``,
photon estimator). The metrics are MAE, SSIM and PSNR (``skimage.metrics``), with
bootstrap 95 % confidence intervals over contacts. The study names the field with the
lowest mean contact-change MAE. It gives a paired bootstrap interval on each other
field's difference from that field, and one on that field's difference from predicting
no change.

Sensors of any shape, and where each field fails
------------------------------------------------
The paper's claim is that fields which follow the membrane (plane, geodesic, transport)
model guided light on a curved membrane better than straight lines (linear). A new shape
tests it where the membrane bends both ways. ``--spec`` takes any sensor; on a membrane
other than a capsule, the contacts are the eight base taps plus ``surface_taps``: the
extended protocol's contact points, classed by the membrane's principal curvatures there
(``scenes.curvature``: convex, cylindrical, flat, saddle, trough, concave), up to
SURFACE_PER_CLASS per class, spread over each class by farthest-point sampling, each
pressed by the rig along the local normal. Every contact records the class of the point
it presses. Two tables then say where each field fails:

* **by pixel** (``region_errors``): every reference pixel near a contact sees a point of
  the undeformed membrane of some class (``pixel_regions``). Per field and class, the
  calibrated change's |error| summed over those pixels, divided by the |reference
  change| there, which is the error of predicting no change. Below 1 the field tracks
  the contact on that kind of surface; at or above 1 it does no better than no change.
  The interval resamples contacts. ``failures`` lists, per field, the classes whose whole
  interval lies at or above 1 (fails), below 1 (tracks), or straddles it (unclear).
* **by contact** (``contact_region_table``): the change MAE over the contacts that press
  on each class, beside the no-change baseline's, with the paired interval of their
  difference.

How the two renderers are made comparable
-----------------------------------------
The fast path gives display values in [0, 1]: the Phong sum plus an ambient background,
clipped. The reference gives linear radiance through the camera's spectral response, with
Monte Carlo noise. Here is what the study does so that the two can be compared.

* **Geometry.** Both renderers see the same deformed membrane: our generated mesh, with
  D_ref = ``scenes.camera.reference_depth``, dented by the elastic layer model
  (``scenes.elastic.MembraneLayer``). The reference builds its elastomer solid from it;
  the fast path renders the depth map of the same deformed surface (``Renderer(...,
  layer=...)``), not the published smoothing. Each published map is moved onto our
  membrane as D = D_ref − (bkg − D_published); its indentation is measured against the
  authors' ``bkg.npy``, which differs from our D_ref by at most 0.16 mm. A rig capture is
  moved onto D_ref the same way, by its indentation against the rig's own no-contact
  capture (``rig_contacts``).
* **Real depth.** Every contact is rendered at its own depth. The published spheres reach
  7.9–12.4 mm along the camera ray, through the 2.5 mm membrane and into the glass; the
  layer model refuses them (as ``scenes.protocol.validate`` refuses a tap deeper than the
  membrane), and the JSON lists them under ``skipped`` with the reason.
* **Resolution.** The fast path renders the full 640x480 camera, so its elastic smoothing
  and Sobel normals work at their native pixel scale. Its image is then area-averaged
  down to the reference's film (``skimage.transform.downscale_local_mean``). That is what
  the film's box reconstruction filter does, so the film must divide 640x480 by an
  integer factor.
* **Mask.** Both images are set to zero outside the camera's image circle, and all
  statistics are taken inside it (``Camera.scaled(W, H).mask``).
* **Background.** The fast path renders with no background (``make_background("none")``).
  Only the LED terms are compared. A background is a per-pixel constant, and the
  calibration below would partly absorb it.
* **Reference scale.** Every reference frame is divided by the 99.5th percentile of the
  no-contact reference inside the mask (all channels). Full frames then have data_range 1
  for PSNR and SSIM, and MAE is a fraction of that level.
* **Reliable pixels.** The photon estimator leaves rare single-pass spikes. At 160x120
  with 2^18 photons, about 1 % of the pixels in the circle reach up to 35 times the
  p99.5 level, and they carry half of the full frame's sum of squares. Any pixel whose
  standard error, in any frame, exceeds ``MAX_STANDARD_ERROR`` (0.5) times the median of
  the no-contact frame is left out of the fits, the metrics and the percentile, for
  every field alike. The JSON reports the share left out as ``unreliable_share``.
* **Calibration.** A gain (at least 0) and an offset per channel map each fast-path
  field's image onto the reference. The gain converts units, so it must never turn the
  fast path's brightening into a darkening: a field whose contact signal anticorrelates
  with the reference gets gain 0, which predicts no change. The gain is **not** fitted
  on the no-contact frame. For the tangent fields (plane, geodesic, transport), L_m is
  perpendicular to N on the undeformed membrane, so max(0, L_m·N) = 0 and their
  no-contact image is nearly black (mean about 0.003, std about 0.002). A gain fitted to
  that frame fits noise and comes out at 25–160. The study reports that fit as
  ``no_contact_calibration``, as a diagnostic. Instead, contact k is calibrated
  leave-one-out:
  * the gain is the least-squares slope through the origin of the reference's contact
    changes against the field's, over every contact except k (``fit_gain``), so the
    contact signal sets it;
  * the offset then matches the no-contact frame.

  A joint affine fit on all the frames would not do. The no-contact image covers every
  pixel, and its structure differs from the reference's, so that structure would set
  the gain (for the tangent fields, to 0) instead of the contacts. Each field gets its
  best linear calibration, and the contact it is scored on never enters it.
* **Three kinds of metric.**
  * *full*: the calibrated fast frame against the reference frame.
  * *change*: (contact − no-contact) over the whole mask, which is what tactile learning
    uses. The offset cancels here.
  * *contact*: the same change, but only on the pixels within one pixel (the Sobel
    stencil) of where the deformed surface's depth changes. Farther out, the fast
    path's change is exactly zero for every field, so *change* dilutes the differences
    between fields by the contact's share of the mask, and *contact* does not. This kind
    also reports Pearson's r between the field's uncalibrated change and the
    reference's, which needs no calibration at all.

  For the change kinds, SSIM and PSNR use as data_range the peak-to-peak of the
  reference's own change inside the mask, so they measure agreement relative to the
  contact signal. MAE stays in the same units as for full frames. The field that wins is
  the one with the lowest mean *change* MAE. A paired bootstrap (resampling contacts,
  differences per contact) says whether it is separated from the others, and whether it
  beats the **no-change baseline**, which predicts zero change. A field that does not
  beat that baseline does not track the contact.
* **Reference noise.** The reference is an estimate. For full frames, ``noise_mae`` is the
  MAE that a perfect fast path would score from the noise alone: √(2/π) σ, averaged over
  the mask, with σ² the estimator's variance of the mean. Every frame is rendered with
  the same seed, and these common random numbers cancel much of the noise in change
  images, so for changes the noise is measured instead: the mean |reference change| far
  from the contact. That includes any real far-field change, such as a shadow cast along
  the membrane, which every field misses alike.
* **Known limits.** The fast path clips at 1. With the spec's Table 1 settings, the linear
  field saturates much of the blue channel, and no affine map undoes that. It is part of
  what is measured. The reference uses ``Effects()``, the full physical model with no
  sensor-side effects.

Reference renders cost tens of seconds to minutes each at 320x240. Each one is cached
in ``--out/reference_cache`` as a .npy file of (mean, variance), and written atomically.
The file is keyed by contact name, resolution and photon count, plus a hash of
everything else the frame depends on. That hash includes the source of
``pbr_tactile``, so a change to the estimator renders the frame again. ``--quick`` renders two analytic contacts at 64x48 with 2^14 photons in two
passes: enough to exercise every step in well under a minute, but too noisy to rank the
fields.

Run ``python -m studies.pbr_field_comparison --out DIR [--spec TOML --surface N --width W
--height H --photons N --quick]``. It writes ``pbr_field_comparison.json``, ``summary.md``, ``metrics.png`` and
``grid_<contact>.png``, and ``regions.png`` when some class of region is reached by two
contacts. The published contacts are used when ``$GELTIP_REFERENCE`` (or
``../shared/data/geltip_reference``) holds the data; without it, the run uses only the
analytic contacts and says so.
"""

from __future__ import annotations

import argparse
import dataclasses
import hashlib
import math
import sys
import time
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import trimesh
from scipy import ndimage, stats
from scipy.optimize import lsq_linear
from skimage.metrics import peak_signal_noise_ratio, structural_similarity
from skimage.transform import downscale_local_mean
from tqdm import tqdm

from phong_reference.background import make_background
from phong_reference.bake import METHODS, bake_all
from phong_reference.render import Renderer, light_vectors
from scenes.cache import make_key
from scenes.camera import Camera, back_project, cast_rays, check_depth, reference_depth
from scenes.contact import press
from scenes.curvature import (CLASSES, CURVATURE_RADIUS_M, FLAT_RADIUS_M, classify, principal_curvatures,
                              vertex_curvatures)
from scenes.dataset import atomic_write_bytes, atomic_write_json, npy_bytes
from scenes.elastic import MembraneLayer
from scenes.geometry import membrane_mesh
from scenes.images import pyplot, srgb
from scenes.indenters import INDENTERS
from scenes.reference_data import REFERENCE_ENV, require_reference_dir
from scenes.spec import SensorSpec, load_spec

from .reproduce_published import N_PANELS, load_depths

#: Analytic contacts, as ``tactile-sim demo`` presses them (phong_reference/cli.py):
#: name -> (indenter, contact pixel offset (du, dv) from the principal point at 640x480 px,
#: indentation depth in metres). All are pressed with spin 0.3 rad.
ANALYTIC = {
    "sphere_tip": (lambda: trimesh.primitives.Sphere(radius=0.004), (20, -10), 0.0015),
    "sphere_side": (lambda: trimesh.primitives.Sphere(radius=0.003), (-150, 60), 0.0012),
    "box_edge": (lambda: trimesh.creation.box((0.004, 0.004, 0.004)), (90, 110), 0.001),
    "cylinder": (lambda: trimesh.creation.cylinder(radius=0.002, height=0.006), (60, -150), 0.0015),
}
PRESS_SPIN_RAD = 0.3
PUBLISHED = tuple(f"published_{k}" for k in range(N_PANELS))
NO_CONTACT = "no_contact"

#: Base-protocol taps: (object, row, position), one per paper indenter, alternating a tip
#: tap at 30 deg and a cylinder tap 9 mm behind the tip (scenes.protocol.base_protocol).
BASE_TAPS = tuple((name, 0, 1 if k % 2 == 0 else 4) for k, name in enumerate(INDENTERS))
BASE = tuple(f"base_{name}_r{row}p{position}" for name, row, position in BASE_TAPS)

#: On a membrane other than the GelTip's capsule, contacts are drawn from the extended
#: protocol's points, up to this many per class of region (``surface_taps``): five, the
#: fewest for which the study's bootstrap intervals mean something.
SURFACE_PER_CLASS = 5

#: The reference is normalised by this percentile of its no-contact frame inside the mask.
REFERENCE_PERCENTILE = 99.5
#: Reference pixels whose standard error exceeds this fraction of the no-contact frame's
#: median are left out of every fit and metric (see ``reliable_pixels``).
MAX_STANDARD_ERROR = 0.5
METRICS = ("mae", "ssim", "psnr_db")
#: full frames; contact change over the mask; contact change near the contact only.
KINDS = ("full", "change", "contact")
CHANGE_KINDS = ("change", "contact")
#: Calibration-free: Pearson's r of the field's contact change with the reference's, near
#: the contact (reported with the "contact" kind).
CORRELATION = "pearson_r"
#: The criterion that names the best field: lowest mean contact-change MAE.
CRITERION = ("change", "mae")
#: E|e| = sqrt(2/pi) sigma for zero-mean Gaussian noise e.
HALF_NORMAL_MEAN = math.sqrt(2.0 / math.pi)

CONFIDENCE = 0.95
N_RESAMPLES = 9999
#: Fewer contacts than this and the conclusion says the intervals mean little.
MIN_CONTACTS_FOR_CI = 5

#: Bump when what a cached reference holds changes.
CACHE_VERSION = 1
CACHE_FOLDER = "reference_cache"
JSON_NAME = "pbr_field_comparison.json"


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
QUICK_CONTACTS = ("sphere_tip", "box_edge")


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


# --------------------------------------------------------------------------------------
# Contacts: depth maps on our membrane, at an indentation the reference accepts.


def analytic_contacts(
    mesh: trimesh.Trimesh, camera: Camera, ref_depth: np.ndarray, names=tuple(ANALYTIC)
) -> dict[str, np.ndarray]:
    """The analytic contacts: name -> (H, W) float32 depth, metres, planar z."""
    unknown = set(names) - set(ANALYTIC)
    if unknown:
        raise ValueError(f"analytic contacts must be among {sorted(ANALYTIC)}, got {sorted(unknown)}")
    out = {}
    for name in names:
        make, (du, dv), depth_m = ANALYTIC[name]
        out[name] = press(ref_depth, camera, mesh, make(), (camera.cx + du, camera.cy + dv), depth_m,
                          spin=PRESS_SPIN_RAD)
    return out


def published_contacts(reference_dir: Path, ref_depth: np.ndarray, names=PUBLISHED) -> dict[str, np.ndarray]:
    """The published depth maps moved onto our membrane: D_ref − max(0, bkg − D).

    ref_depth : (480, 640) float, metres, our D_ref.  Returns name -> (480, 640) float32.
    """
    unknown = set(names) - set(PUBLISHED)
    if unknown:
        raise ValueError(f"published contacts must be among {list(PUBLISHED)}, got {sorted(unknown)}")
    bkg, depths = load_depths(reference_dir)
    if bkg.shape != ref_depth.shape:
        raise ValueError(f"ref_depth must be {bkg.shape} like the published maps, got {ref_depth.shape}")
    return {
        name: (ref_depth - np.clip(bkg - depths[PUBLISHED.index(name)], 0.0, None)).astype(np.float32)
        for name in names
    }


def base_taps(spec: SensorSpec, mesh: trimesh.Trimesh, names=BASE) -> dict:
    """The named base-protocol taps: name -> ``scenes.protocol.Tap``."""
    from scenes.protocol import base_protocol

    unknown = set(names) - set(BASE)
    if unknown:
        raise ValueError(f"base contacts must be among {list(BASE)}, got {sorted(unknown)}")
    wanted = {BASE_TAPS[BASE.index(n)]: n for n in names}
    return {wanted[(t.object, t.row, t.position)]: t for t in base_protocol(spec, mesh, INDENTERS).taps
            if (t.object, t.row, t.position) in wanted}


def surface_taps(spec: SensorSpec, mesh: trimesh.Trimesh, per_class: int = SURFACE_PER_CLASS, seed: int = 0) -> dict:
    """Taps spread over the kinds of region the membrane has: name -> ``scenes.protocol.Tap``.

    The extended protocol's nominal contact points (its rows x contacts, the same for
    every indenter) are classed by the membrane's curvature there
    (``scenes.curvature``). From each class, up to ``per_class`` points are picked,
    spread over it: a random first one, then each time the point farthest from those
    picked (farthest-point sampling), so that a class made of separate patches (a paw's
    waist and the valleys between its toes) has each patch tapped. Each point is tapped
    by an indenter drawn in turn from a shuffled INDENTERS, with one
    np.random.Generator seeded by ``seed`` for both draws. A point is
    tapped perpendicular to the membrane at the protocol's depth, as the rig presses it.
    Names read ``surface_<class>_<indenter>_r<row>p<position>``.
    """
    from scenes.protocol import extended_protocol

    if not isinstance(per_class, int) or isinstance(per_class, bool) or per_class < 1:
        raise ValueError(f"per_class must be an integer >= 1, got {per_class!r}")
    protocol = extended_protocol(spec, mesh, INDENTERS, replicas=1)
    points = {}  # one entry per distinct point (every row starts at the apex)
    for t in protocol.taps:
        points.setdefault(tuple(np.round(np.asarray(t.point) * 1e7).astype(int)), (t.row, t.position, t.point))
    rows, positions, xyz = zip(*points.values())
    classes = classify(principal_curvatures(mesh, np.array(xyz)))
    by_key = {(t.object, t.row, t.position): t for t in protocol.taps}
    rng = np.random.default_rng(seed)
    objects = list(rng.permutation(INDENTERS))
    out = {}
    xyz = np.array(xyz)
    for cls in CLASSES:
        members = np.flatnonzero(classes == cls)
        if len(members) == 0:
            continue
        picked = [int(rng.choice(members))]
        while len(picked) < min(per_class, len(members)):
            gap = np.linalg.norm(xyz[members, None] - xyz[picked][None], axis=-1).min(axis=1)
            picked.append(int(members[np.argmax(gap)]))
        for i in picked:
            obj = objects[len(out) % len(objects)]
            out[f"surface_{cls}_{obj}_r{rows[i]}p{positions[i]}"] = by_key[(obj, rows[i], positions[i])]
    return out


def rig_contacts(spec: SensorSpec, mesh: trimesh.Trimesh, taps: dict, ref_depth: np.ndarray) -> dict[str, np.ndarray]:
    """Taps captured on the MuJoCo rig, moved onto the ray-cast D_ref: name -> (H, W)
    float32 depth, metres.

    The rig's depth camera and the ray caster see the membrane up to ~0.1 mm apart (the
    rig's z-buffer and its own meshing), so a raw capture against the ray-cast D_ref would
    dent the membrane everywhere by that much. Each capture's indentation is measured
    against the rig's own no-contact capture instead, dropped where it is within
    ``scenes.camera.CONTACT_EPS_M`` (as the dataset renderers drop it), and applied to the
    ray-cast D_ref: D = D_ref - indentation.

    taps : name -> ``scenes.protocol.Tap``.  ref_depth : (H, W), the ray-cast D_ref.
    """
    from scenes.camera import CONTACT_EPS_M
    from scenes.rig import tap_depths

    names = {id(t): n for n, t in taps.items()}
    captures = tap_depths(spec, list(taps.values()), mesh)
    rig_ref, _ = next(captures)
    out = {}
    for depth, tap in captures:
        indentation = rig_ref.astype(np.float64) - depth
        indentation = np.where(indentation > CONTACT_EPS_M, indentation, 0.0)
        out[names[id(tap)]] = (ref_depth - indentation).astype(np.float32)
    return out


def contact_points(depths: dict[str, np.ndarray], ref_depth: np.ndarray, camera: Camera, taps: dict) -> dict:
    """Where each contact presses on the undeformed membrane: name -> (3,) metres.

    A tap's own contact point; for any other contact, the surface point under its
    deepest pixel (largest D_ref - D).
    """
    points = {}
    for name, depth in depths.items():
        if name in taps:
            points[name] = np.asarray(taps[name].point, dtype=np.float64)
        else:
            v, u = np.unravel_index(np.argmax(np.where(np.isfinite(depth), ref_depth - depth, -np.inf)), depth.shape)
            points[name] = back_project(ref_depth, camera)[v, u].astype(np.float64)
    return points


def pixel_regions(mesh: trimesh.Trimesh, camera: Camera) -> np.ndarray:
    """(h, w) str: the class of region (``scenes.curvature.CLASSES``) of the membrane point
    each pixel of ``camera`` sees, from the curvatures at the mesh's vertices interpolated
    to the hit; "" where the ray misses the membrane."""
    samples = cast_rays(mesh, camera)
    k = samples.interpolate(mesh, vertex_curvatures(mesh))
    return samples.scatter(classify(k).astype(object), fill="").astype(str)


def refusal(depth: np.ndarray, ref_depth: np.ndarray, build) -> str | None:
    """Why the reference cannot build the contact's elastomer (None: it can).

    build : a ``pbr_tactile.membrane.ElastomerBuilder`` of the membrane.
    """
    check_depth(depth, build.layer.camera)
    try:
        build(depth, ref_depth)
    except ValueError as exc:  # through the glass core
        return str(exc)
    return None


# --------------------------------------------------------------------------------------
# The two renderers, at the reference's resolution.


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
    from pbr_tactile.render import reference

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
    est = reference(depth, None if depth is None else ref_depth, mesh, spec, camera, effects, spp=settings.spp,
                    width=settings.width, height=settings.height, seed=settings.seed, passes=settings.passes,
                    estimator="photons", photons=settings.photons, progress=progress)
    if path is not None:
        atomic_write_bytes(path, npy_bytes(np.stack([est.mean, est.variance]).astype(np.float32)))
    return est.mean, est.variance, False


# --------------------------------------------------------------------------------------
# Calibration and metrics (arrays in, arrays out).


def fit_affine(fast: np.ndarray, ref: np.ndarray, mask: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per-channel gain >= 0 and offset minimising |gain fast + offset − ref|² inside the mask.

    The gain is bounded at 0 because the map converts units: it must not turn the fast
    path's brightening into a darkening (a field whose contact signal anticorrelates with
    the reference gets gain 0, i.e. predicts no change).

    fast, ref : (..., h, w, 3) frames; mask : (h, w) bool.  Returns gain (3,), offset (3,).
    """
    if fast.shape != ref.shape or fast.shape[-1] != 3 or fast.shape[-3:-1] != mask.shape:
        raise ValueError(f"fast and ref must be (..., h, w, 3) with mask (h, w), got {fast.shape}, {ref.shape}, "
                         f"{mask.shape}")
    x, y = fast[..., mask, :].reshape(-1, 3), ref[..., mask, :].reshape(-1, 3)
    gain, offset = np.empty(3), np.empty(3)
    for c in range(3):
        A = np.stack([x[:, c], np.ones(len(x))], axis=1).astype(np.float64)
        fit = lsq_linear(A, y[:, c].astype(np.float64), bounds=([0.0, -np.inf], [np.inf, np.inf]))
        gain[c], offset[c] = fit.x
    return gain, offset


def fit_gain(change_fast: np.ndarray, change_ref: np.ndarray, region: np.ndarray) -> np.ndarray:
    """Per-channel gain >= 0 minimising |gain change_fast − change_ref|² over the region.

    change_fast, change_ref : (..., h, w, 3) contact changes; region : (h, w) bool.
    A least-squares line through the origin, clipped at 0 (the exact bounded solution
    for one parameter). Returns (3,).
    """
    if change_fast.shape != change_ref.shape or change_fast.shape[-3:-1] != region.shape:
        raise ValueError(f"change_fast and change_ref must be (..., h, w, 3) with region (h, w), got "
                         f"{change_fast.shape}, {change_ref.shape}, {region.shape}")
    f = change_fast[..., region, :].reshape(-1, 3).astype(np.float64)
    r = change_ref[..., region, :].reshape(-1, 3).astype(np.float64)
    ff = (f * f).sum(axis=0)
    return np.where(ff > 0, np.clip((f * r).sum(axis=0) / np.where(ff > 0, ff, 1.0), 0.0, None), 0.0)


def leave_one_out_calibration(fast: np.ndarray, ref: np.ndarray, region: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Calibration of each contact k from the other contacts and the no-contact frame.

    The gain (>= 0) is fitted to the contact changes of every contact but k
    (``fit_gain``), so that it is set by the contact signal and not by the no-contact
    image; the offset then matches the no-contact frame in the least-squares sense.

    fast, ref : (1 + K, h, w, 3), frame 0 without contact; region : (h, w) bool.
    Returns gains, offsets (K, 3).
    """
    K = len(fast) - 1
    if K < 2:
        raise ValueError(f"leave-one-out calibration needs at least 2 contacts, got {K}")
    change_fast, change_ref = fast[1:] - fast[:1], ref[1:] - ref[:1]
    gains = np.stack([fit_gain(np.delete(change_fast, k, axis=0), np.delete(change_ref, k, axis=0), region)
                      for k in range(K)])
    offsets = np.stack([(ref[0][region] - g * fast[0][region]).mean(axis=0) for g in gains])
    return gains, offsets


def image_metrics(expected: np.ndarray, actual: np.ndarray, mask: np.ndarray, data_range: float,
                  region: np.ndarray | None = None) -> dict[str, float]:
    """MAE, SSIM and PSNR (dB) of (h, w, 3) images over a region of the mask.

    Both images are set to zero outside ``mask`` (h, w) bool; the metrics average over
    ``region`` (h, w) bool (default: the mask). SSIM is the mean of skimage's SSIM map
    (7x7 window) over the region.
    """
    region = mask if region is None else region
    if expected.shape != actual.shape or expected.shape[:2] != mask.shape or region.shape != mask.shape:
        raise ValueError(f"expected and actual must be (h, w, 3) with mask and region (h, w), got {expected.shape}, "
                         f"{actual.shape}, {mask.shape}, {region.shape}")
    if not data_range > 0:
        raise ValueError(f"data_range must be > 0, got {data_range}")
    if not region.any():
        raise ValueError("region must hold at least one pixel")
    e = np.where(mask[..., None], expected, 0.0).astype(np.float64)
    a = np.where(mask[..., None], actual, 0.0).astype(np.float64)
    _, ssim_map = structural_similarity(e, a, channel_axis=-1, data_range=data_range, full=True)
    return {
        "mae": float(np.abs(a - e)[region].mean()),
        "ssim": float(ssim_map[region].mean()),
        "psnr_db": float(peak_signal_noise_ratio(e[region], a[region], data_range=data_range)),
    }


def change_metrics(change_ref: np.ndarray, change_pred: np.ndarray, mask: np.ndarray, region: np.ndarray,
                   near: np.ndarray) -> dict:
    """Metrics of a predicted contact change (h, w, 3) over the region ("change") and over
    its pixels near the contact ("contact"); data_range: the reference change's span."""
    span = float(np.ptp(change_ref[region]))
    span = span if span > 0 else 1.0
    return {"change": image_metrics(change_ref, change_pred, mask, span, region),
            "contact": image_metrics(change_ref, change_pred, mask, span, near & region)}


def contact_metrics(
    fast: np.ndarray, ref: np.ndarray, gains: np.ndarray, offsets: np.ndarray, mask: np.ndarray,
    region: np.ndarray, near: np.ndarray,
) -> list[dict]:
    """Full-frame and change metrics of each contact for one field.

    fast, ref : (1 + K, h, w, 3), frame 0 without contact, ref normalised.
    gains, offsets : (K, 3), the calibration of each contact.
    mask : (h, w) bool, the image circle; region : (h, w) bool, where the metrics average.
    near : (K, h, w) bool, pixels near each contact (see ``far_from_contact``).
    """
    out = []
    for k in range(1, len(fast)):
        g, o = gains[k - 1], offsets[k - 1]
        change = fast[k] - fast[0]
        out.append({
            "full": image_metrics(ref[k], g * fast[k] + o, mask, 1.0, region),
            **change_metrics(ref[k] - ref[0], g * change, mask, region, near[k - 1]),
        })
        out[-1]["contact"][CORRELATION] = pearson(change[near[k - 1] & region], (ref[k] - ref[0])[near[k - 1] & region])
    return out


def pearson(a: np.ndarray, b: np.ndarray) -> float:
    """Pearson's r of two equally shaped arrays, all values pooled; 0 when either is constant
    (a field that predicts no change has no correlation with the reference's)."""
    a, b = np.ravel(a).astype(np.float64), np.ravel(b).astype(np.float64)
    if a.shape != b.shape or a.size < 2:
        raise ValueError(f"a and b must hold the same number (>= 2) of values, got {a.size} and {b.size}")
    if a.std() == 0 or b.std() == 0:
        return 0.0
    return float(np.corrcoef(a, b)[0, 1])


def no_change_metrics(ref: np.ndarray, mask: np.ndarray, region: np.ndarray, near: np.ndarray) -> list[dict]:
    """Change metrics of the baseline that predicts no change at all, per contact.

    ref : (1 + K, h, w, 3), frame 0 without contact.  A field that does not beat this
    baseline does not track the contact.
    """
    return [change_metrics(ref[k] - ref[0], np.zeros_like(ref[k]), mask, region, near[k - 1])
            for k in range(1, len(ref))]


def reliable_pixels(mean: np.ndarray, variance: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """(h, w) bool: pixels whose reference estimate is trustworthy in every frame.

    mean, variance : (F, h, w, 3), the estimates and the variances of their means. A pixel
    is left out when, in any frame and channel, its standard error exceeds
    MAX_STANDARD_ERROR times the median of the first frame inside the mask: the photon
    estimator's rare single-pass spikes, which would otherwise dominate MSE and the
    normalising percentile.
    """
    level = float(np.median(mean[0][mask]))
    if not level > 0:
        raise ValueError(f"the reference is black inside the mask (median {level})")
    error = np.sqrt(np.clip(variance, 0.0, None)).max(axis=(0, -1))
    return error <= MAX_STANDARD_ERROR * level


def far_from_contact(depth: np.ndarray, ref_depth: np.ndarray, shape: tuple[int, int], margin_px: float) -> np.ndarray:
    """(h, w) bool: reference pixels farther than ``margin_px`` (depth-camera px) from any
    pixel where the depth map differs from D_ref."""
    touched = downsample(np.repeat((depth != ref_depth)[..., None], 3, axis=-1).astype(np.float32), shape)[..., 0] > 0
    factor = depth.shape[0] / shape[0]
    return ~ndimage.binary_dilation(touched, iterations=max(1, math.ceil(margin_px / factor)))


def bootstrap_mean(values, seed: int, confidence: float = CONFIDENCE, n_resamples: int = N_RESAMPLES) -> dict:
    """Mean over contacts and its percentile-bootstrap interval (contacts resampled).

    The percentile method, not BCa, because BCa is undefined for two contacts.
    """
    values = np.asarray(values, dtype=np.float64)
    if values.ndim != 1 or len(values) < 2 or not np.isfinite(values).all():
        raise ValueError(f"values must be >= 2 finite numbers, got {values!r}")
    if np.ptp(values) == 0:  # every resample gives the same mean
        lo = hi = float(values[0])
    else:
        res = stats.bootstrap((values,), np.mean, confidence_level=confidence, n_resamples=n_resamples,
                              method="percentile", rng=np.random.default_rng(seed))
        lo, hi = float(res.confidence_interval.low), float(res.confidence_interval.high)
    return {"mean": float(values.mean()), "ci_low": lo, "ci_high": hi, "values": values.tolist()}


def summarise(per_contact: dict[str, list[dict]], seed: int, no_change: list[dict]) -> dict:
    """Per field, kind and metric: mean over contacts with its bootstrap CI; the best field
    by CRITERION, with paired bootstrap CIs of every other field's difference from it, and
    of the no-change baseline's difference from it (``no_change``: its per-contact change
    metrics, from ``no_change_metrics``)."""
    table = {
        method: {kind: {m: bootstrap_mean([c[kind][m] for c in rows], seed) for m in METRICS} for kind in KINDS}
        for method, rows in per_contact.items()
    }
    for method, rows in per_contact.items():
        table[method]["contact"][CORRELATION] = bootstrap_mean([c["contact"][CORRELATION] for c in rows], seed)
    kind, metric = CRITERION
    best = min(table, key=lambda f: table[f][kind][metric]["mean"])
    best_values = np.array(table[best][kind][metric]["values"])
    differences = {
        f: bootstrap_mean(np.array(table[f][kind][metric]["values"]) - best_values, seed)
        for f in table if f != best
    }
    baseline = {k: {m: bootstrap_mean([c[k][m] for c in no_change], seed) for m in METRICS} for k in CHANGE_KINDS}
    lower_better = {"mae": True, "ssim": False, "psnr_db": False}
    best_by = {
        f"{k}_{m}": (min if lower_better[m] else max)(table, key=lambda f, k=k, m=m: table[f][k][m]["mean"])
        for k in KINDS for m in METRICS
    }
    distinct = all(d["ci_low"] > 0 for d in differences.values())
    versus_baseline = bootstrap_mean(np.array(baseline[kind][metric]["values"]) - best_values, seed)
    return {"table": table, "best": best, "criterion": f"{kind} {metric}", "best_minus_others": differences,
            "best_by_metric": best_by, "best_is_distinct": distinct, "baseline_no_change": baseline,
            "no_change_minus_best": versus_baseline, "best_beats_no_change": versus_baseline["ci_low"] > 0}


def region_errors(change_pred: np.ndarray, change_ref: np.ndarray, pixels: np.ndarray, regions: np.ndarray,
                  seed: int, confidence: float = CONFIDENCE, n_resamples: int = N_RESAMPLES) -> dict:
    """Where a predicted contact change goes wrong, by class of region of the membrane.

    change_pred, change_ref : (K, h, w, 3), the calibrated prediction and the reference.
    pixels : (K, h, w) bool, the pixels each contact is scored on (near it, reliable).
    regions : (h, w) str, the class of the membrane point each pixel sees (``pixel_regions``).

    For each class c and contact k, e_k sums |pred - ref| over k's pixels of class c and
    b_k sums |ref|, the error of predicting no change there. The ratio sum(e) / sum(b) is
    below 1 where the prediction tracks the contact and at or above 1 where it does no
    better than no change. Its percentile-bootstrap interval resamples contacts (the
    pairs (e_k, b_k)). Returns class -> {"ratio", "ci_low", "ci_high", "pixels",
    "contacts"}, for the classes that at least 2 contacts reach with some signal (b > 0).
    """
    if change_pred.shape != change_ref.shape or change_pred.shape[:3] != pixels.shape or pixels.shape[1:] != regions.shape:
        raise ValueError(f"change_pred, change_ref (K, h, w, 3), pixels (K, h, w) and regions (h, w) must agree, got "
                         f"{change_pred.shape}, {change_ref.shape}, {pixels.shape}, {regions.shape}")
    error = np.abs(change_pred - change_ref).sum(axis=-1)
    signal = np.abs(change_ref).sum(axis=-1)
    out = {}
    for cls in CLASSES:
        where = pixels & (regions == cls)[None]
        e, b = (np.where(where, error, 0.0).sum(axis=(1, 2)), np.where(where, signal, 0.0).sum(axis=(1, 2)))
        reached = b > 0
        if reached.sum() < 2:
            continue
        e, b = e[reached], b[reached]
        ratio = lambda e, b, axis=-1: e.sum(axis=axis) / b.sum(axis=axis)  # noqa: E731
        if np.ptp(e / b) == 0:
            lo = hi = float(ratio(e, b))
        else:
            res = stats.bootstrap((e, b), ratio, paired=True, vectorized=True, confidence_level=confidence,
                                  n_resamples=n_resamples, method="percentile", rng=np.random.default_rng(seed))
            lo, hi = float(res.confidence_interval.low), float(res.confidence_interval.high)
        out[cls] = {"ratio": float(ratio(e, b)), "ci_low": lo, "ci_high": hi, "pixels": int(where.sum()),
                    "contacts": int(reached.sum())}
    return out


def contact_region_table(per_contact: dict[str, list[dict]], no_change: list[dict], regions: list[str],
                         seed: int) -> dict:
    """Change MAE per field over the contacts of each class of region (that of the point
    each contact presses), next to the no-change baseline's, with bootstrap intervals;
    and, per field, the paired interval of (no change - field): above 0, the field beats
    predicting no change on those contacts. Classes with fewer than 2 contacts are left out.

    per_contact : field -> per-contact metrics; no_change : the baseline's; regions : the
    class of each contact, in the same order.
    """
    out = {}
    for cls in CLASSES:
        idx = [k for k, r in enumerate(regions) if r == cls]
        if len(idx) < 2:
            continue
        base = np.array([no_change[k]["change"]["mae"] for k in idx])
        row = {"contacts": len(idx), "no_change": bootstrap_mean(base, seed)}
        for method, rows in per_contact.items():
            mae = np.array([rows[k]["change"]["mae"] for k in idx])
            row[method] = {"mae": bootstrap_mean(mae, seed), "no_change_minus_field": bootstrap_mean(base - mae, seed)}
        out[cls] = row
    return out


def failures(results: dict) -> dict[str, dict[str, list[str]]]:
    """Per field, the classes of region where it fails (its pixel error ratio's interval
    lies at or above 1: no better than predicting no change), where it tracks the
    contact (the interval lies below 1), and where the numbers cannot tell."""
    out = {}
    for method, table in results["pixel_regions"]["ratio"].items():
        out[method] = {
            "fails": [c for c, r in table.items() if r["ci_low"] >= 1.0],
            "tracks": [c for c, r in table.items() if r["ci_high"] < 1.0],
            "unclear": [c for c, r in table.items() if r["ci_low"] < 1.0 <= r["ci_high"]],
        }
    return out


def noise_floor(variance: np.ndarray, scale: float, mask: np.ndarray) -> float:
    """MAE a perfect estimate would score from noise of variance (h, w, 3) alone."""
    return float(HALF_NORMAL_MEAN * np.sqrt(np.clip(variance, 0, None))[mask].mean() / scale)


# --------------------------------------------------------------------------------------
# The study.


def run(out: Path, settings: Settings = Settings(), contacts: tuple[str, ...] | None = None,
        reference_dir: Path | None = None, spec: SensorSpec | None = None, surface: int | None = None) -> dict:
    """Render, compare and summarise; writes the JSON, Markdown and figures into ``out``.

    contacts : names from BASE, ANALYTIC and PUBLISHED (default: all base and analytic ones,
        plus the published ones when ``reference_dir`` holds the data and the sensor is
        the published capsule).
    spec : the sensor (default: the embedded GelTip); any shape (``scenes.body``).
    """
    t_start = time.perf_counter()
    spec = load_spec(None) if spec is None else spec
    if spec.membrane.shape != "capsule":
        if contacts is not None and set(contacts) & set(PUBLISHED):
            raise ValueError(f"the published depth maps are the GelTip's; sensor {spec.name!r} is a "
                             f"{spec.membrane.shape!r}: drop {sorted(set(contacts) & set(PUBLISHED))}")
        reference_dir = None
    camera = Camera.from_spec(spec)
    check_settings(settings, camera)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    mesh = membrane_mesh(spec)
    if surface is None:
        surface = 0 if spec.membrane.shape == "capsule" else SURFACE_PER_CLASS
    taps = surface_taps(spec, mesh, surface, settings.seed) if surface else {}
    if contacts is None:
        contacts = ((BASE + tuple(ANALYTIC) + (PUBLISHED if reference_dir is not None else ()))
                    if spec.membrane.shape == "capsule" else BASE) + tuple(taps)
    known = list(BASE) + list(ANALYTIC) + list(PUBLISHED) + list(taps)
    unknown = set(contacts) - set(known)
    if unknown or len(set(contacts)) < 2:
        raise ValueError(f"contacts must be >= 2 distinct names from {known} (surface_* with surface >= 1), "
                         f"got {list(contacts)}")
    wanted_published = tuple(c for c in contacts if c in PUBLISHED)
    if wanted_published and reference_dir is None:
        raise ValueError(f"contacts {list(wanted_published)} need the published data (set ${REFERENCE_ENV})")
    ref_depth = reference_depth(mesh, camera)[0]
    raw = analytic_contacts(mesh, camera, ref_depth, tuple(c for c in contacts if c in ANALYTIC))
    if wanted_published:
        raw.update(published_contacts(reference_dir, ref_depth, wanted_published))
    taps = {**base_taps(spec, mesh, tuple(c for c in contacts if c in BASE)),
            **{n: t for n, t in taps.items() if n in contacts}}
    if taps:
        raw.update(rig_contacts(spec, mesh, taps, ref_depth))

    from pbr_tactile.membrane import shared_builder

    # The builder the reference renders with: the solids checked here are not built twice.
    build = shared_builder(mesh, spec, camera)
    depths, info, skipped = {}, {}, {}
    for name in tqdm(contacts, desc="contacts the reference builds", unit="contact"):
        why = refusal(raw[name], ref_depth, build)
        if why is not None:
            skipped[name] = why
            warnings.warn(f"{name}: the reference refuses it at its real depth ({why}); dropped", stacklevel=2)
            continue
        depths[name] = raw[name]
        source = ("published" if name in PUBLISHED else "base protocol" if name in BASE
                  else "analytic" if name in ANALYTIC else "surface")
        info[name] = {"source": source, "max_indentation_m": float((ref_depth - depths[name]).max()),
                      "max_displacement_m": float(build.layer.deformation(depths[name], ref_depth).displacement.max())}
    points = contact_points(depths, ref_depth, camera, taps)
    k = principal_curvatures(mesh, np.array([points[n] for n in depths])) if depths else np.zeros((0, 2))
    for n, kn, cls in zip(depths, k, classify(k)):
        info[n].update(point_m=points[n].tolist(), curvatures_per_m=kn.tolist(), region=str(cls))
    names = list(depths)
    if len(names) < 2:
        raise ValueError(f"fewer than 2 contacts left to compare ({names}); dropped: {skipped}")

    shape = (settings.height, settings.width)
    mask = camera.scaled(settings.width, settings.height).mask
    means, variances, cached = [], [], {}
    t_ref = time.perf_counter()
    with tqdm([NO_CONTACT] + names, desc="reference renders", unit="contact") as bar:
        for name in bar:
            bar.set_postfix_str(name)

            def progress(done, total, name=name):
                bar.set_postfix_str(f"{name}: pass {done}/{total}")

            mean, var, hit = reference_frame(name, depths.get(name), ref_depth, mesh, spec, camera, settings,
                                             out / CACHE_FOLDER, progress)
            means.append(mean)
            variances.append(var)
            cached[name] = hit
    seconds_reference = time.perf_counter() - t_ref
    mean = np.stack(means)
    variance = np.stack(variances)
    region = mask & reliable_pixels(mean, variance, mask)
    scale = float(np.percentile(mean[0][region], REFERENCE_PERCENTILE))
    if not scale > 0:
        raise ValueError(f"the no-contact reference is black inside the mask (p{REFERENCE_PERCENTILE} = {scale})")
    ref = np.where(mask[..., None], mean / scale, 0.0)

    # Pixels near each contact: within the Sobel pixel of where the deformed surface's depth
    # changes; farther out, the fast path's change is exactly zero.
    layer = build.layer
    far = np.stack([far_from_contact(layer.depth(depths[n], ref_depth), ref_depth, shape, 1) for n in names])
    near = mask & ~far
    far &= region

    fast = fast_frames(spec, camera, mesh, ref_depth, [ref_depth] + [depths[n] for n in names], shape, layer)
    per_contact, calibration, no_contact_fit, calibrated = {}, {}, {}, {}
    tiled = lambda v: np.tile(v, (len(names), 1))
    for method, frames in fast.items():
        frames = np.where(mask[..., None], frames, 0.0)
        gains, offsets = leave_one_out_calibration(frames, ref, region)
        per_contact[method] = contact_metrics(frames, ref, gains, offsets, mask, region, near)
        calibration[method] = {"gain": gains.tolist(), "offset": offsets.tolist()}
        g0, o0 = fit_affine(frames[:1], ref[:1], region)
        briefed = contact_metrics(frames, ref, tiled(g0), tiled(o0), mask, region, near)
        no_contact_fit[method] = {"gain": g0.tolist(), "offset": o0.tolist(),
                                  "fast_std_no_contact": frames[0][region].std(axis=0).tolist(),
                                  "change_mae_mean": float(np.mean([c["change"]["mae"] for c in briefed]))}
        calibrated[method] = (frames, gains, offsets)
    no_change = no_change_metrics(ref, mask, region, near)
    summary = summarise(per_contact, settings.seed, no_change)
    regions_px = pixel_regions(mesh, camera.scaled(settings.width, settings.height))
    scored = near & region[None]
    change_ref = ref[1:] - ref[:1]
    pixel_table = {
        method: region_errors(gains[:, None, None, :] * (frames[1:] - frames[:1]), change_ref, scored, regions_px,
                              settings.seed)
        for method, (frames, gains, _) in calibrated.items()
    }
    region_summary = {
        "pixels_in_circle": {c: int(((regions_px == c) & region).sum()) for c in CLASSES
                             if ((regions_px == c) & region).any()},
        "ratio": pixel_table,
        "by_contact": contact_region_table(per_contact, no_change, [info[n]["region"] for n in names],
                                           settings.seed),
    }
    contacts_k = range(1, len(names) + 1)
    noise = {
        "full": bootstrap_mean([noise_floor(variance[k], scale, region) for k in contacts_k], settings.seed),
        "change_far": bootstrap_mean([float(np.abs(ref[k] - ref[0])[far[k - 1]].mean()) if far[k - 1].any() else 0.0
                                      for k in contacts_k], settings.seed),
    }
    results = {
        "question": "which light field brings the fast Phong path closest to the physically based reference",
        "sensor": spec.name,
        "settings": dataclasses.asdict(settings),
        "confidence": CONFIDENCE,
        "n_resamples": N_RESAMPLES,
        "contact_names": names,  # the order of every per-contact "values" list
        "contacts": info,
        "skipped": skipped,
        "reference_scale": scale,
        "reference_percentile": REFERENCE_PERCENTILE,
        "unreliable_share": float(1.0 - region.sum() / mask.sum()),
        "reference_cached": cached,
        "noise_mae": noise,
        "pixel_regions": region_summary,
        "per_contact": {m: dict(zip(names, rows)) for m, rows in per_contact.items()},
        "calibration": calibration,
        "no_contact_calibration": no_contact_fit,
        **summary,
        "seconds_reference": seconds_reference,
        "seconds_total": time.perf_counter() - t_start,
    }
    results["failures"] = failures(results)
    results["conclusion"] = conclusion(results)
    atomic_write_json(out / JSON_NAME, results)
    (out / "summary.md").write_text(markdown(results))
    metrics_figure(out / "metrics.png", results)
    if any(results["pixel_regions"]["ratio"].values()):
        region_figure(out / "regions.png", results, regions_px)
    for k, name in enumerate(names, start=1):
        grid_figure(out / f"grid_{name}.png", name, ref[0], ref[k], calibrated, k, mask, per_contact)
    return results


def conclusion(results: dict) -> str:
    """The answer in words, with the caveats the numbers call for."""
    kind, metric = CRITERION
    best = results["best"]
    cell = results["table"][best][kind][metric]
    n = len(cell["values"])
    text = (f"{best} has the lowest mean contact-change MAE ({cell['mean']:.4f}, {results['confidence']:.0%} CI "
            f"{cell['ci_low']:.4f} to {cell['ci_high']:.4f}, n = {n} contacts)")
    if results["best_is_distinct"]:
        text += "; the paired bootstrap separates it from every other field"
    else:
        close = [f for f, d in results["best_minus_others"].items() if d["ci_low"] <= 0]
        text += f"; the paired bootstrap does not separate it from {', '.join(close)}"
    base = results["baseline_no_change"][kind][metric]["mean"]
    if results["best_beats_no_change"]:
        text += f", and it beats predicting no change (MAE {base:.4f})."
    else:
        text += (f", but it does not clearly beat predicting no change (MAE {base:.4f}), so no field is shown "
                 "to track the reference's contact signal at these settings.")
    if n < MIN_CONTACTS_FOR_CI:
        text += f" With {n} contacts the intervals are not meaningful: this is a smoke run."
    where = []
    for method, f in results.get("failures", {}).items():
        if f["fails"] or f["tracks"]:
            parts = ([f"fails on {', '.join(f['fails'])}"] if f["fails"] else []) + (
                [f"tracks on {', '.join(f['tracks'])}"] if f["tracks"] else [])
            where.append(f"{method} {' and '.join(parts)}")
    if where:
        text += (" By region (error near the contacts over that of predicting no change, interval over contacts): "
                 + "; ".join(where) + ".")
    return text


# --------------------------------------------------------------------------------------
# Reports and figures.


def _cell(c: dict, digits: int) -> str:
    return f"{c['mean']:.{digits}f} [{c['ci_low']:.{digits}f}, {c['ci_high']:.{digits}f}]"


def markdown(results: dict) -> str:
    s = results["settings"]
    digits = {"mae": 4, "ssim": 3, "psnr_db": 2}
    lines = [
        "# Fast-path light fields against the physically based reference",
        "",
        (f"Reference: photon estimator, {s['width']}x{s['height']}, {s['photons']} photons per LED per pass, "
         f"{s['passes']} passes, {s['spp']} spp, seed {s['seed']}; normalised by its no-contact "
         f"p{results['reference_percentile']} = {results['reference_scale']:.4g}. "
         f"Mean over {len(results['contacts'])} contacts with {results['confidence']:.0%} percentile-bootstrap "
         "intervals (contacts resampled). Change = contact − no-contact. Calibration: per-channel gain >= 0 from "
         "the other contacts' changes, offset from the no-contact frame (see the study's docstring). "
         f"Unreliable reference pixels left out: {results['unreliable_share']:.1%} of the circle."),
        "",
        "| field | " + " | ".join(f"{k} {m}" for k in KINDS for m in METRICS) + f" | contact {CORRELATION} |",
        "|---|" + "---|" * (len(KINDS) * len(METRICS) + 1),
    ]
    for method, row in results["table"].items():
        mark = " **(best)**" if method == results["best"] else ""
        lines.append(f"| {method}{mark} | " + " | ".join(_cell(row[k][m], digits[m]) for k in KINDS for m in METRICS)
                     + f" | {_cell(row['contact'][CORRELATION], 2)} |")
    b, n = results["baseline_no_change"], results["noise_mae"]
    lines += [
        "| no change (baseline) | | | | "
        + " | ".join(_cell(b[k][m], digits[m]) for k in CHANGE_KINDS for m in METRICS) + " | |",
        f"| reference noise (MAE) | {_cell(n['full'], 4)} | | | {_cell(n['change_far'], 4)} | | | | | | |",
        "",
        ("Reference noise: full, sqrt(2/pi) x the estimator's standard error; change, the mean |reference change| "
         "farther than a pixel from where the deformed surface moved (noise left by common random numbers, plus any real "
         "far-field change, which every field misses alike)."),
        "",
        f"**Conclusion.** {results['conclusion']}",
        "",
        "Best by each metric: " + ", ".join(f"{k}: {v}" for k, v in results["best_by_metric"].items()) + ".",
        "",
        f"Paired differences from {results['best']} in {results['criterion']} (other − best): "
        + ", ".join(f"{f} {_cell(d, 4)}" for f, d in results["best_minus_others"].items()) + ".",
        "",
        ("| contact | source | region | principal curvatures (1/m) | max indentation along the camera ray (mm) "
         "| max displacement along the normal (mm) |"),
        "|---|---|---|---|---|---|",
    ]
    for name, c in results["contacts"].items():
        k = ", ".join(f"{v:.0f}" for v in c["curvatures_per_m"])
        lines.append(f"| {name} | {c['source']} | {c['region']} | {k} | {c['max_indentation_m'] * 1e3:.2f} | "
                     f"{c['max_displacement_m'] * 1e3:.2f} |")
    if results["skipped"]:
        lines += ["", "Refused at their real depth: " + "; ".join(f"{k}: {v}" for k, v in results["skipped"].items())]
    lines += region_markdown(results)
    lines += ["", "Calibrated on the no-contact frame alone instead (diagnostic; degenerate for tangent fields):",
              "", "| field | gain (R, G, B) | fast no-contact std | change MAE |", "|---|---|---|---|"]
    for method, c in results["no_contact_calibration"].items():
        lines.append(f"| {method} | {', '.join(f'{g:.3g}' for g in c['gain'])} | "
                     f"{', '.join(f'{v:.4f}' for v in c['fast_std_no_contact'])} | {c['change_mae_mean']:.4f} |")
    return "\n".join(lines) + "\n"


def region_markdown(results: dict) -> list[str]:
    """The tables of where each field fails, by class of region (empty when none)."""
    regions = results.get("pixel_regions")
    if not regions or not any(regions["ratio"].values()):
        return []
    classes = [c for c in CLASSES if any(c in t for t in regions["ratio"].values())]
    lines = ["", "## Where each field fails, by class of region", "",
             ("Classes by the principal curvatures of the undeformed membrane over a "
              f"{CURVATURE_RADIUS_M * 1e3:g} mm ball (``scenes.curvature``: flat within 1/{FLAT_RADIUS_M * 1e3:g} mm). "
              "Pixel ratio: the calibrated change's |error| summed over the pixels near the contacts that see that "
              "class, over the |reference change| there (the error of predicting no change); below 1 the field "
              "tracks the contact, at or above 1 it does no better than no change. Interval: contacts resampled."),
             "", "| field | " + " | ".join(f"{c} ({regions['pixels_in_circle'].get(c, 0)} px in circle)"
                                           for c in classes) + " |",
             "|---|" + "---|" * len(classes)]
    for method, table in regions["ratio"].items():
        cells = [f"{table[c]['ratio']:.2f} [{table[c]['ci_low']:.2f}, {table[c]['ci_high']:.2f}] "
                 f"({table[c]['contacts']} contacts)" if c in table else "" for c in classes]
        lines.append(f"| {method} | " + " | ".join(cells) + " |")
    by_contact = regions["by_contact"]
    if by_contact:
        methods = list(results["table"])
        lines += ["", ("Change MAE over the contacts that press on each class (the class at the contact point), "
                       "and no change − field (above 0: the field beats predicting no change there):"), "",
                  "| class | contacts | no change | " + " | ".join(methods) + " |",
                  "|---|---|---|" + "---|" * len(methods)]
        for cls, row in by_contact.items():
            cells = [f"{_cell(row[m]['mae'], 4)}; {_cell(row[m]['no_change_minus_field'], 4)}" for m in methods]
            lines.append(f"| {cls} | {row['contacts']} | {_cell(row['no_change'], 4)} | " + " | ".join(cells) + " |")
    return lines


def metrics_figure(path: Path, results: dict) -> Path:
    """Bars of each metric per field (mean over contacts) with bootstrap CI error bars."""
    plt = pyplot()
    methods = list(results["table"])
    fig, axes = plt.subplots(len(KINDS), len(METRICS), figsize=(4.2 * len(METRICS), 3.4 * len(KINDS)))
    x = np.arange(len(methods))
    for i, kind in enumerate(KINDS):
        for j, metric in enumerate(METRICS):
            ax = axes[i, j]
            cells = [results["table"][m][kind][metric] for m in methods]
            means = np.array([c["mean"] for c in cells])
            err = np.array([[c["mean"] - c["ci_low"] for c in cells], [c["ci_high"] - c["mean"] for c in cells]])
            colours = ["tab:orange" if m == results["best"] else "tab:blue" for m in methods]
            ax.bar(x, means, yerr=err, capsize=4, color=colours, alpha=0.85)
            for k, c in enumerate(cells):
                ax.plot(np.full(len(c["values"]), x[k]), c["values"], "k.", ms=3, alpha=0.5)
            if metric == "mae" and kind != "contact":
                floor = results["noise_mae"]["full" if kind == "full" else "change_far"]["mean"]
                ax.axhline(floor, color="grey", ls="--", lw=1, label="reference noise")
            if kind == "change":
                base = results["baseline_no_change"][kind][metric]["mean"]
                ax.axhline(base, color="tab:red", ls=":", lw=1.2, label="no-change baseline")
            if ax.get_legend_handles_labels()[0]:
                ax.legend(fontsize=7, loc="lower right")
            ax.set_xticks(x, methods)
            ax.set_title(f"{kind}: {metric}")
    fig.suptitle(f"fast path vs PBR reference ({results['confidence']:.0%} bootstrap CI over "
                 f"{len(results['contacts'])} contacts; dots: contacts)")
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return path


def region_figure(path: Path, results: dict, regions: np.ndarray) -> Path:
    """Left: the class of region each film pixel sees. Right: each field's pixel error
    ratio per class (1: no better than predicting no change), with its interval."""
    from matplotlib.colors import ListedColormap

    plt = pyplot()
    fig, (left, right) = plt.subplots(1, 2, figsize=(10, 3.8), gridspec_kw={"width_ratios": [1, 1.4]})
    present = [c for c in CLASSES if (regions == c).any()]
    index = np.full(regions.shape, np.nan)
    for j, c in enumerate(present):
        index[regions == c] = j
    cmap = ListedColormap([f"C{CLASSES.index(c)}" for c in present])
    left.imshow(index, cmap=cmap, vmin=-0.5, vmax=len(present) - 0.5, interpolation="nearest")
    for j, c in enumerate(present):
        left.plot([], [], "s", color=f"C{CLASSES.index(c)}", label=c)
    left.legend(fontsize=7, loc="lower right")
    left.set_axis_off()
    left.set_title("class of region seen by each pixel", fontsize=9)
    table = results["pixel_regions"]["ratio"]
    classes = [c for c in CLASSES if any(c in t for t in table.values())]
    width = 0.8 / max(1, len(table))
    for m, (method, rows) in enumerate(table.items()):
        x = np.array([k for k, c in enumerate(classes) if c in rows], dtype=float) + (m - (len(table) - 1) / 2) * width
        cells = [rows[c] for c in classes if c in rows]
        err = np.array([[c["ratio"] - c["ci_low"] for c in cells], [c["ci_high"] - c["ratio"] for c in cells]])
        right.bar(x, [c["ratio"] for c in cells], width, yerr=err, capsize=3, label=method, alpha=0.85)
    right.axhline(1.0, color="tab:red", ls=":", lw=1.2, label="no change")
    right.set_xticks(range(len(classes)), classes)
    right.set_ylabel("|error| / |reference change| near the contacts")
    right.legend(fontsize=7)
    right.set_title("where each field fails (below 1: tracks the contact)", fontsize=9)
    fig.suptitle(f"{results['sensor']}: light fields by class of region")
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return path


def grid_figure(path: Path, name: str, ref0: np.ndarray, refk: np.ndarray, fast: dict, k: int, mask: np.ndarray,
                per_contact: dict) -> Path:
    """Reference and each calibrated field for one contact: frames (sRGB for viewing) on
    top, contact change (mean over channels) below."""
    plt = pyplot()
    cols = ["reference"] + list(fast)
    fig, axes = plt.subplots(2, len(cols), figsize=(2.8 * len(cols), 5.0), squeeze=False)
    change_ref = (refk - ref0).mean(axis=-1)
    vmax = float(np.abs(change_ref[mask]).max()) or 1.0
    for j, col in enumerate(cols):
        if col == "reference":
            frame, change, title = refk, change_ref, "PBR reference"
        else:
            frames, gains, offsets = fast[col]
            g, o = gains[k - 1], offsets[k - 1]
            frame = np.where(mask[..., None], g * frames[k] + o, 0.0)
            change = (g * (frames[k] - frames[0])).mean(axis=-1)
            m = per_contact[col][k - 1]
            title = f"{col}\nchange MAE {m['change']['mae']:.4f}, SSIM {m['change']['ssim']:.2f}"
        axes[0, j].imshow(srgb(frame))
        axes[0, j].set_title(title, fontsize=8)
        axes[1, j].imshow(np.where(mask, change, np.nan), cmap="RdBu_r", vmin=-vmax, vmax=vmax)
    for ax in axes.ravel():
        ax.set_axis_off()
    fig.suptitle(f"{name}: calibrated frames (top), contact change, mean of channels (bottom, ±{vmax:.3f})")
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return path


def print_report(results: dict) -> None:
    print(markdown(results))


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, required=True, help="results, figures and the reference cache go here")
    parser.add_argument("--quick", action="store_true",
                        help=f"{QUICK.width}x{QUICK.height}, {QUICK.photons} photons, {QUICK.passes} passes, "
                             f"contacts {', '.join(QUICK_CONTACTS)} (a smoke run; too noisy to rank)")
    parser.add_argument("--width", type=int, help=f"reference film width, px (default {Settings.width})")
    parser.add_argument("--height", type=int, help=f"reference film height, px (default {Settings.height})")
    parser.add_argument("--photons", type=int, help=f"photons per LED per pass (default {Settings.photons})")
    parser.add_argument("--passes", type=int, help=f"independent passes (default {Settings.passes})")
    parser.add_argument("--spp", type=int, help=f"camera samples per pixel in all (default {Settings.spp})")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--contacts", nargs="+", metavar="NAME",
                        help=f"any of {', '.join(list(BASE) + list(ANALYTIC) + list(PUBLISHED))} (default: all available)")
    parser.add_argument("--spec", type=Path, help="sensor spec TOML (default: the embedded GelTip); any shape")
    parser.add_argument("--surface", type=int, metavar="N",
                        help=f"taps drawn per class of region, named surface_* (default {SURFACE_PER_CLASS} on a "
                             "membrane other than a capsule, else 0); with --contacts, only those named are used")
    parser.add_argument("--reference", type=Path,
                        help=f"the published data (default ${REFERENCE_ENV} or ../shared/data/geltip_reference)")
    args = parser.parse_args(argv)
    base = QUICK if args.quick else Settings()
    given = {k: getattr(args, k) for k in ("width", "height", "photons", "passes", "spp") if getattr(args, k)}
    settings = dataclasses.replace(base, seed=args.seed, **given)
    try:
        reference_dir, missing = require_reference_dir(args.reference), None
    except FileNotFoundError as exc:
        reference_dir, missing = None, exc
    contacts = tuple(args.contacts) if args.contacts else (QUICK_CONTACTS if args.quick else None)
    if missing is not None and not args.quick:
        print(f"{missing}; analytic contacts only", file=sys.stderr)
    try:
        results = run(args.out, settings, contacts, reference_dir, load_spec(args.spec) if args.spec else None,
                      args.surface)
    except ValueError as exc:
        parser.error(str(exc))
    print_report(results)
    print(f"wrote {args.out / JSON_NAME}, summary.md and figures ({results['seconds_total']:.0f} s)")
    return results


if __name__ == "__main__":
    main()
