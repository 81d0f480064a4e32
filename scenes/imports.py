"""Published captures imported as capture datasets of the project's own format.

A public set of real tactile images of presses with known geometry (a ball of known
size, each press's annotated centre and radius) becomes a capture dataset
(``docs/dataset-format.md``, ``source: "real"``) as the rig would have written it: the
no-contact frame as ``background.png``, each press a sample with its indenter, its tap in
``protocol.json`` and the rig's ``measured_pose`` that presses it. Every command that takes
a capture (``dataset --replay``, ``compare``, ``calibrate``, ``diagnose``) then works on it.

A format is one small reader (:data:`FORMATS`): a function from the archive's path to an
:class:`Archive` (frames as linear RGB in [0, 1], centres and radii in pixels). The rest
is the same for every format (:func:`import_capture`):

- the camera: the sensor spec's, at the frames' size (``SensorSpec.at_resolution``) with
  its field of view set so that a pixel spans ``pixel_m`` on the membrane where the
  optical axis meets it (a distortion-free pinhole; the spec's lens otherwise, refused
  where its pixel differs);
- each press's contact point: where the camera's ray through the annotated centre meets
  the membrane; its approach along the membrane's normal there, as the protocols press;
- each press's depth d = R - sqrt(R^2 - a^2) for a ball of radius R whose contact circle
  has radius a. With ``depth="profile"`` (the default) a is fitted from the image: the
  radius at which the press's change from the no-contact frame, averaged round the
  annotated centre, peaks (:func:`contact_edge_px`): a ball's rim is where the membrane is
  steepest, and a lit membrane's change grows with its slope. ``rim_share`` k (default 1)
  says the change peaks at k of the contact's radius instead, a = peak / k: the project's
  renderers peak inside their own balls' rims (at 0.73 to 0.84 of them on this set), and
  a rim past the ball's radius is then set to RIM_CAP of it, its record saying so
  (``contact_radius_capped``). With ``depth="radius"`` a is
  the annotated radius, which a published annotation may draw round the visible ring
  instead (the Taxim set's 17 px circles are 2.1 mm at 0.1245 mm a pixel, wider than its
  2 mm ball: that mode refuses them). With ``depth="elastic"`` the rim fitted to the image
  is taken as the edge of the elastic contact the spec's membrane makes (the ``bonded``
  model of ``scenes.elastic_solid``, its elastomer's thickness and Poisson's ratio): the
  depth is the one at which the ball leaves a contact that wide on that layer
  (``ball_depth_for_contact``), deeper than the chord's, since an elastic contact is
  narrower than the ball's footprint. With ``depth="fitted"`` the layer and depths are
  those a joint fit to the presses found (``fit``: the report of
  ``phong_reference.elastic_fit``): each press it gave a depth keeps it (its fitted
  presses' own, the others' by its rule), any other press gets the fitted model's
  rim-to-depth relation (``relation_mm``) times the fit's share k, held at its ball limit.

The Taxim format (``taxim``, :func:`read_taxim`) is the calibration data pack of the
Taxim simulator (Si and Yuan, RA-L 2022; Robo-Touch/Taxim, ``calibs/dataPack*.npz``): an
``.npz`` (or a folder holding exactly one ``dataPack*.npz``) with ``f0`` (H, W, 3) uint8,
the no-contact frame; ``imgs`` (N, H, W, 3) uint8, one frame per press; ``touch_center``
(N, 2), each press's annotated centre in pixels as (x = column, y = row); ``touch_radius``
(N,), its annotated radius in pixels; and optionally ``names`` (N,). The frames are stored
as OpenCV reads them, BGR: the reader turns them to RGB.
"""

from __future__ import annotations

import hashlib
import math
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .dataset import DatasetError, DatasetWriter, read_samples, sample_id, write_sample_files
from .image_stats import ring_profile

#: Defaults of each format: the sensor spec, the ball's diameter (metres) and the pixel's
#: size on the membrane (metres) of the set the format was published with.
TAXIM = "taxim"
DEFAULTS = {TAXIM: {"spec": Path(__file__).with_name("sensors") / "gelsight.toml", "ball_m": 4.0e-3,
                    "pixel_m": 0.1245e-3}}
#: How a press's depth is found (module doc).
DEPTH_METHODS = ("profile", "radius", "elastic", "fitted")
#: The profile's radial bins, pixels, and where its peak is sought: this share of the
#: ball's radius in pixels, at least and at most.
PROFILE_BIN_PX = 0.5
PROFILE_SEARCH = (0.3, 1.5)
#: A rim that ``rim_share`` puts past the ball's radius is set to this share of it.
RIM_CAP = 0.995
#: A profile bin needs this many pixels to count (bins near the centre hold few).
PROFILE_MIN_PIXELS = 4
#: The apex's pixel may differ from ``pixel_m`` by this share for a lens that cannot be
#: rescaled (distorted or not a pinhole) before the spec is refused.
PIXEL_TOLERANCE = 0.01


@dataclass(frozen=True)
class Archive:
    """A published capture as a format reader returns it.

    no_contact : (H, W, 3) float64, linear RGB in [0, 1], the frame without contact.
    frames : (N, H, W, 3) float64, likewise, one per press.
    centres_px : (N, 2) float64, each press's annotated centre (u = column, v = row), px.
    radii_px : (N,) float64, each press's annotated radius, px.
    names : (N,) the presses' names in the archive.
    path : where it was read from.
    notes : what the reader did (e.g. the channel order it turned).
    """

    no_contact: np.ndarray
    frames: np.ndarray
    centres_px: np.ndarray
    radii_px: np.ndarray
    names: tuple[str, ...]
    path: str
    notes: dict = field(default_factory=dict)


def _npz_file(path: Path, pattern: str) -> Path:
    if path.is_dir():
        found = sorted(path.glob(pattern))
        if len(found) != 1:
            raise ValueError(f"archive {path}: a folder must hold exactly one {pattern}, found "
                             f"{[p.name for p in found] or 'none'}")
        return found[0]
    if not path.is_file():
        raise FileNotFoundError(f"archive {path} does not exist")
    return path


def read_taxim(path: str | Path) -> Archive:
    """Read a Taxim calibration data pack (module doc); ValueError naming the archive and
    the key for anything missing or malformed."""
    path = _npz_file(Path(path), "dataPack*.npz")
    try:
        pack = np.load(path, allow_pickle=False)
    except (OSError, ValueError, EOFError) as exc:
        raise ValueError(f"archive {path} is not a readable .npz: {exc}") from None
    where = f"archive {path}"
    keys = set(pack.files)
    if "f0" not in keys:
        raise ValueError(f"{where} has no no-contact frame (key 'f0'); a capture needs one")
    for key in ("imgs", "touch_center", "touch_radius"):
        if key not in keys:
            raise ValueError(f"{where} has no {key!r}; a Taxim data pack has f0, imgs, touch_center and touch_radius")

    def array(key):
        try:
            return pack[key]
        except ValueError as exc:  # an object array (pickled): frames of unequal size, or Python objects
            raise ValueError(f"{where}: {key} is not one regular array ({exc}); frames of unequal size or Python "
                             "objects are not read") from None

    f0, imgs = array("f0"), array("imgs")
    for key, value, rank in (("f0", f0, 3), ("imgs", imgs, 4)):
        if value.dtype != np.uint8 or value.ndim != rank or value.shape[-1] != 3:
            want = "(H, W, 3)" if rank == 3 else "(N, H, W, 3)"
            raise ValueError(f"{where}: {key} must be {want} uint8 (8-bit BGR), got {value.shape} {value.dtype}")
    if imgs.shape[1:3] != f0.shape[:2]:
        raise ValueError(f"{where}: frames of unequal size: the presses are {imgs.shape[2]}x{imgs.shape[1]} px, the "
                         f"no-contact frame f0 {f0.shape[1]}x{f0.shape[0]} px")
    names = [str(n) for n in array("names")] if "names" in keys else [f"press_{i}" for i in range(len(imgs))]
    # Taxim's frames come from cv2.imread: BGR.
    return Archive(no_contact=f0[..., ::-1] / 255.0, frames=imgs[..., ::-1] / 255.0,
                   centres_px=np.asarray(array("touch_center"), np.float64),
                   radii_px=np.asarray(array("touch_radius"), np.float64), names=tuple(names[:len(imgs)]),
                   path=str(path.resolve()), notes={"channels": "stored BGR (OpenCV), turned to RGB"})


#: Format name -> reader.
FORMATS: dict[str, Callable[[str | Path], Archive]] = {TAXIM: read_taxim}


def check_archive(archive: Archive) -> None:
    """Refuse an archive whose arrays disagree, or a press whose centre lies outside the
    frame or whose radius is not a positive number: ValueError naming the press."""
    where = f"archive {archive.path}"
    frames, f0 = np.asarray(archive.frames), np.asarray(archive.no_contact)
    if f0.ndim != 3 or f0.shape[-1] != 3:
        raise ValueError(f"{where}: the no-contact frame must be (H, W, 3), got {f0.shape}")
    if frames.ndim != 4 or frames.shape[1:] != f0.shape:
        raise ValueError(f"{where}: frames of unequal size: presses {frames.shape[1:]} against the no-contact "
                         f"frame's {f0.shape}")
    n = len(frames)
    if n == 0:
        raise ValueError(f"{where} holds no presses")
    centres, radii = np.asarray(archive.centres_px), np.asarray(archive.radii_px)
    if centres.shape != (n, 2) or radii.shape != (n,) or len(archive.names) != n:
        raise ValueError(f"{where}: {n} frames need {n} centres (N, 2), radii (N,) and names; got {centres.shape}, "
                         f"{radii.shape} and {len(archive.names)}")
    h, w = f0.shape[:2]
    for i, ((u, v), r) in enumerate(zip(centres, radii)):
        name = f"{where}: press {i} ({archive.names[i]})"
        if not (np.isfinite(u) and np.isfinite(v) and 0 <= u <= w - 1 and 0 <= v <= h - 1):
            raise ValueError(f"{name}: its centre ({u:g}, {v:g}) px lies outside the {w}x{h} frame "
                             "((x = column, y = row) in pixels was expected)")
        if not (np.isfinite(r) and r > 0):
            raise ValueError(f"{name}: its radius must be a positive number of pixels, got {r!r}")


def contact_edge_px(frame: np.ndarray, no_contact: np.ndarray, centre_px, ball_radius_px: float) -> float:
    """The radius, px, at which a press's change peaks round its centre (module doc).

    The mean over channels of |frame - no_contact| is averaged over rings PROFILE_BIN_PX
    wide about ``centre_px`` (u, v), and the peak sought between PROFILE_SEARCH times the
    ball's radius in pixels, refined by a parabola through its neighbours. ValueError when
    the peak lies at either end of the search (no rim inside it).
    """
    change = np.abs(np.asarray(frame, np.float64) - np.asarray(no_contact, np.float64)).mean(axis=2)
    lo, hi = PROFILE_SEARCH[0] * ball_radius_px, PROFILE_SEARCH[1] * ball_radius_px
    radius, profile, _ = ring_profile(change, centre_px, PROFILE_BIN_PX, (int(hi / PROFILE_BIN_PX) + 2) * PROFILE_BIN_PX,
                                      PROFILE_MIN_PIXELS)
    search = np.flatnonzero((radius >= lo) & (radius <= hi) & np.isfinite(profile))
    if len(search) < 3:
        raise ValueError(f"the press at ({centre_px[0]:g}, {centre_px[1]:g}) px has too little of its ring inside "
                         "the frame to find its rim")
    k = search[np.argmax(profile[search])]
    if k in (search[0], search[-1]):
        raise ValueError(f"the press at ({centre_px[0]:g}, {centre_px[1]:g}) px changes the image most at "
                         f"{radius[k]:.1f} px from its centre, at the end of the search ({lo:.1f} to {hi:.1f} px for a "
                         f"ball {ball_radius_px:.1f} px in radius): no rim found")
    a, b, c = profile[k - 1], profile[k], profile[k + 1]
    curve = a - 2 * b + c
    shift = 0.5 * (a - c) / curve if curve < 0 else 0.0
    return float(radius[k] + np.clip(shift, -0.5, 0.5) * PROFILE_BIN_PX)


def ball_depth(contact_radius_m: float, ball_radius_m: float) -> float:
    """The depth, metres, at which a ball of ``ball_radius_m`` leaves a contact circle of
    ``contact_radius_m``: R - sqrt(R^2 - a^2); ValueError for a circle the ball cannot
    leave (a >= R)."""
    a, R = float(contact_radius_m), float(ball_radius_m)
    if not 0 < a < R:
        raise ValueError(f"a contact circle {a * 1e3:.3g} mm in radius is larger than a ball {R * 1e3:.3g} mm in radius "
                         "allows (a < R)")
    return R - math.sqrt(R * R - a * a)


def rim_depth(edge_px: float, pixel_m: float, ball_radius_m: float, rim_share: float = 1.0) -> tuple[float, bool]:
    """(the depth, m, whose chord meets the contact that ``edge_px`` is ``rim_share`` of,
    whether that contact lay past RIM_CAP of the ball's radius and was set to it; only a
    share under 1 caps) for a rim ``edge_px`` px at ``pixel_m`` m a pixel (module doc)."""
    contact_px = edge_px / rim_share
    capped = bool(rim_share != 1.0 and contact_px > RIM_CAP * ball_radius_m / pixel_m)
    if capped:
        contact_px = RIM_CAP * ball_radius_m / pixel_m
    return ball_depth(contact_px * pixel_m, ball_radius_m), capped


def capture_spec(spec, width: int, height: int, pixel_m: float):
    """The spec's sensor with a camera of the frames' size whose pixel spans ``pixel_m``
    metres where its optical axis meets the membrane (module doc); returns (spec, note)."""
    import dataclasses

    from .camera import Camera
    from .contact import surface_point
    from .geometry import membrane_mesh
    from .spec import spec_from_dict

    if not (isinstance(pixel_m, (int, float)) and math.isfinite(pixel_m) and 0 < pixel_m < 0.01):
        raise ValueError(f"pixel size must be a length in metres, > 0 and under 10 mm, got {pixel_m!r}")
    scaled = spec.at_resolution(width, height)
    camera = Camera.from_spec(scaled)
    point, _ = surface_point(membrane_mesh(scaled), camera, (camera.cx, camera.cy))
    z = float(point[2])
    now = z / camera.f
    if camera.is_pinhole:
        fov_y = 2 * math.atan(height / 2 * pixel_m / z)
        scaled = spec_from_dict(scaled.replace(camera=dataclasses.replace(scaled.camera, fov_y=fov_y)).to_dict(),
                                f"sensor {spec.name!r} at {width}x{height}")
        return scaled, (f"fov_y set to {fov_y:.6g} rad so that a pixel spans {pixel_m * 1e3:.6g} mm where the optical "
                        f"axis meets the membrane, {z * 1e3:.4g} mm from the camera (the spec's gave "
                        f"{now * 1e3:.6g} mm)")
    if abs(now / pixel_m - 1) > PIXEL_TOLERANCE:
        raise ValueError(f"sensor {spec.name!r}: its {spec.camera.projection} lens with distortion "
                         f"{list(spec.camera.distortion)} sees {now * 1e3:.5g} mm a pixel at {width}x{height}, not "
                         f"{pixel_m * 1e3:.5g} mm; give a spec whose camera matches the set")
    return scaled, f"the spec's lens kept: {now * 1e3:.6g} mm a pixel where its axis meets the membrane"


def press_tap(index: int, obj: str, spec, mesh, camera, centre_px, depth_m: float):
    """The tap that presses ``obj`` ``depth_m`` metres into the membrane where the camera
    sees ``centre_px`` (u, v): its point where the ray through that pixel meets the
    membrane, aimed along the membrane's normal there (as the protocols press), its servo
    angles those aims need. ValueError where the press would reach the glass under the
    elastomer (or the ray misses the membrane)."""
    from .contact import surface_point
    from .kinematics import normal_in_sensor
    from .protocol import _aim
    from .protocol_checks import max_safe_depth_m
    from .taps import Tap

    point, normal = surface_point(mesh, camera, tuple(float(c) for c in centre_px))
    safe = float(max_safe_depth_m(spec, point[None], mesh)[0])
    if depth_m >= safe:
        raise ValueError(f"a press {depth_m * 1e3:.3g} mm deep would reach the plate under the {safe * 1e3:.3g} mm "
                         "elastomer")
    roll, pitch = (float(a[0]) for a in _aim(normal[None]))
    return Tap(index=index, object=obj, row=0, position=index, replica=0, sensor_roll=roll, indenter_pitch=pitch,
               point=tuple(point), normal=tuple(normal_in_sensor(roll, pitch)), depth=float(depth_m))


def _sha256(path: str) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def import_capture(archive: Archive, out: str | Path, spec, ball_m: float, pixel_m: float,
                   depth: str = "profile", fmt: str = TAXIM, layout=None, rim_share: float = 1.0,
                   fit: dict | None = None) -> dict:
    """Write ``archive`` as a capture dataset in ``out`` (module doc); returns a summary.

    Parameters
    ----------
    spec : the unit's ``SensorSpec`` (its camera is put at the frames' size and pixel).
    ball_m : the ball's diameter, metres. pixel_m : a pixel's size on the membrane, metres.
    depth : "profile", "radius" or "elastic" (module doc). rim_share : the share of the contact's
        radius at which a press's change peaks, in (0, 1] (module doc; profile only).
    layout : the rig's ``RigLayout`` the poses are for (default: the project's rig).
    fit : with depth "fitted", the joint fit's report (module doc).

    A folder that holds another capture, or files but no dataset, is refused and left as
    it is; the same import again completes what an interrupted one left (resumable).
    """
    from .camera import Camera
    from .geometry import membrane_mesh
    from .indenters import ball_name, indenter
    from .kinematics import RigLayout, tap_pose
    from .protocol_checks import validate
    from .taps import Protocol

    if depth not in DEPTH_METHODS:
        raise ValueError(f"depth must be one of {DEPTH_METHODS}, got {depth!r}")
    rim_share = float(rim_share)
    if not 0.0 < rim_share <= 1.0:
        raise ValueError(f"rim_share must be in (0, 1], the share of the contact's radius at which its change "
                         f"peaks, got {rim_share:g}")
    if rim_share != 1.0 and depth != "profile":
        raise ValueError(f"rim_share applies to the rim fitted to the image (depth 'profile'), not to {depth!r}")
    layout = layout or RigLayout()
    check_archive(archive)
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise ValueError(f"--out {out} is a file, not a folder")
    if out.is_dir() and any(out.iterdir()) and not (out / "dataset.json").exists():
        raise DatasetError(f"{out} holds files but no dataset; import into an empty or new folder (nothing was "
                           "written)")
    obj = ball_name(ball_m)
    R = ball_m / 2
    h, w = archive.no_contact.shape[:2]
    unit, camera_note = capture_spec(spec, w, h, pixel_m)
    camera = Camera.from_spec(unit)
    mesh = membrane_mesh(unit)

    if (depth == "fitted") != (fit is not None):
        raise ValueError("depth 'fitted' takes the joint fit's report (fit), and only it does")
    if depth == "fitted" and len(set(archive.names)) != len(archive.names):
        raise ValueError(f"archive {archive.path}: its presses' names repeat, so the joint fit's depths cannot be "
                         "matched to them")
    own, fitted_names = {}, set()
    if depth == "fitted":
        from .elastic_solid import check_material, depth_at_radius

        try:
            thickness, poisson = float(fit["elastic"]["thickness_m"]), float(fit["elastic"]["poisson_ratio"])
            share, limit = float(fit["depth_share"]["k"]), float(fit["ball_limit_m"])
            relation = np.asarray(fit["relation_mm"], np.float64) * 1e-3  # (depths, rims)
            own = {p["name"]: float(p["depth_mm"]) * 1e-3 for p in fit["presses"]}
            fitted_names = {p["name"] for p in fit["presses"] if p["fitted"]}
        except (KeyError, TypeError, ValueError):
            raise ValueError("the joint fit's report must hold elastic.thickness_m, elastic.poisson_ratio, "
                             "depth_share.k, ball_limit_m, relation_mm and presses [{name, depth_mm, fitted}] "
                             "(phong_reference.elastic_fit)") from None
        check_material(thickness, poisson)
        if relation.ndim != 2 or relation.shape[0] != 2 or relation.shape[1] < 2:
            raise ValueError(f"the joint fit's relation_mm must be [depths, rims], got shape {relation.shape}")

        def elastic_depth(contact_radius_m: float) -> float:
            # the fitted model's own rim-to-depth relation times k, as the fit gave its held-out presses
            return min(share * float(depth_at_radius(contact_radius_m, relation[1], relation[0])), limit)

        deepest = limit
    elif depth == "elastic":
        from .elastic_solid import ball_depth_for_contact

        thickness, poisson = unit.membrane.elastomer_thickness, unit.elastic.poisson_ratio

        def elastic_depth(contact_radius_m: float) -> float:
            return ball_depth_for_contact(contact_radius_m, R, thickness, poisson, cap=True)

        deepest = elastic_depth(math.inf)

    taps, fitted, capped = [], [], []
    for i, (centre, radius) in enumerate(zip(archive.centres_px, archive.radii_px)):
        name = f"archive {archive.path}: press {i} ({archive.names[i]})"
        if depth == "radius":
            edge_px = float(radius)
        else:
            try:
                edge_px = contact_edge_px(archive.frames[i], archive.no_contact, centre, R / pixel_m)
            except ValueError as exc:
                raise ValueError(f"{name}: {exc}") from None
        if depth in ("elastic", "fitted"):
            try:
                d = own[archive.names[i]] if archive.names[i] in own else elastic_depth(edge_px * pixel_m)
            except ValueError as exc:
                raise ValueError(f"{name}: {exc}") from None
            # a rim wider than the deepest tabulated press leaves is given that depth, and says so
            capped.append(d >= deepest)
        else:
            try:
                d, cap = rim_depth(edge_px, pixel_m, R, rim_share)
                capped.append(cap)
            except ValueError as exc:
                what = "its annotated radius" if depth == "radius" else "the rim fitted to its image"
                raise ValueError(f"{name}: {what}, {edge_px:.2f} px at {pixel_m * 1e3:g} mm a pixel: {exc}"
                                 + ("; --depth profile fits the rim from the image instead" if depth == "radius"
                                    else "")) from None
        try:
            taps.append(press_tap(i, obj, unit, mesh, camera, centre, d))
        except ValueError as exc:
            raise ValueError(f"{name}: {exc}") from None
        fitted.append(edge_px)
    protocol = Protocol(name=f"import-{fmt}", taps=tuple(taps), seed=None)
    validate(protocol, unit, mesh)

    digest = _sha256(archive.path)
    meta = {
        "source": "real",
        "sensor": unit.to_dict(),
        "protocol": {"name": protocol.name, "seed": None, "taps": len(taps), "objects": [obj]},
        "image_size": [w, h],
        "image": "8-bit RGB PNG from the camera",
        "depth": "none: a real capture has no depth map",
        "renderer": {"renderer": "camera", "camera": {"kind": "archive", "format": fmt, "sha256": digest,
                                                      **archive.notes}},
        "rig": {"layout": layout.to_dict(), "virtual": False, "printer": None, "servos": None},
        "import": {"format": fmt, "archive": archive.path, "sha256": digest, "ball_mm": ball_m * 1e3,
                   "pixel_mm": pixel_m * 1e3, "depth": depth, "rim_share": rim_share,
                   **({"elastic_fit": {"thickness_m": thickness, "poisson_ratio": poisson, "depth_share": share,
                                       "fitted_presses": len(fitted_names)}} if depth == "fitted" else {}),
                   "rims_capped": int(sum(capped)), "camera": camera_note,
                   "poses": "each press's measured_pose is the rig's pose that presses the ball as annotated: on the "
                            "membrane where the camera sees the annotated centre, along its normal, to the depth "
                            "the depth method gives"},
    }
    writer = DatasetWriter(out, meta, protocol.to_dict())
    if not (out / "background.png").exists():
        writer.write_background(archive.no_contact)
    vertices = np.asarray(indenter(obj).vertices, np.float64)
    from .generate import tap_fields

    for tap, edge_px, cap, centre, radius, name in zip(taps, fitted, capped, archive.centres_px, archive.radii_px,
                                                       archive.names):
        sid = sample_id(tap.index, tap.object)
        if sid in writer.done:
            continue
        pose = tap_pose(tap, vertices, layout)
        record = {**tap_fields(tap), "commanded_pose": pose, "measured_pose": pose, "measured_depth": tap.depth,
                  "contact_center_px": [float(c) for c in centre], "contact_radius_px": float(radius),
                  "contact_edge_px": edge_px, "source_name": name,
                  **({"contact_radius_capped": cap} if rim_share != 1.0 or depth in ("elastic", "fitted") else {}),
                  **({"depth_source": "fitted" if name in fitted_names else "rule"} if depth == "fitted" else {})}
        files = write_sample_files(out, sid, archive.frames[tap.index], None)
        writer.append({**record, **files})
    depths = np.array([t.depth for t in taps])
    return {"out": str(out), "presses": len(read_samples(out)), "object": obj, "depth": depth,
            "rim_share": rim_share, "rims_capped": int(sum(capped)),
            "depth_mm": {"median": float(np.median(depths) * 1e3), "min": float(depths.min() * 1e3),
                         "max": float(depths.max() * 1e3)},
            "camera": camera_note}
