"""Published captures imported as capture datasets of the project's own format.

A public set of real tactile images of presses with known geometry (a ball of known
size, each press's annotated centre and radius) becomes a capture dataset
(``docs/dataset-format.md``, ``source: "real"``) as the rig would have written it: the
no-contact frame as ``background.png``, each press a sample with its indenter, its tap in
``protocol.json`` and the rig's ``measured_pose`` that presses it. Every command that takes
a capture (``dataset --replay``, ``compare``, ``calibrate``, ``diagnose``) then works on it.

A set of presses is read as an ``Archive`` (``scenes.press_sets``: a Taxim pack or a
folder of presses; frames as linear RGB in [0, 1], centres and radii in pixels). The
rest is the same for every format (:func:`import_capture`):

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
"""

from __future__ import annotations

import dataclasses
import hashlib
import math
from pathlib import Path

import numpy as np

from .dataset import DatasetError, DatasetWriter, read_samples, sample_id, write_sample_files
from .image_stats import ring_profile
from .press_sets import (DEFAULTS, FOLDER_OPTIONS, FORMATS, MARKERS, TAXIM, Archive, check_archive, guess_format,
                         orientation_turn, read_folder, read_set_records, read_taxim, turn_archive)

#: How a press's depth is found (module doc).
DEPTH_METHODS = ("profile", "radius", "elastic", "fitted", "given")
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


def frames_spec(spec, width: int, height: int):
    """(the spec's sensor with a camera of ``width`` x ``height`` pixels, how it was set).

    Frames of the camera's aspect: ``SensorSpec.at_resolution``. Frames of another aspect
    (a portrait frame from a landscape camera, or any other crop): the camera's sensor is
    set from the frames: a pinhole of the frames' size whose pixel count is the spec's
    times s^2 (focal length s times the spec's, in pixels), its principal point and image
    circle moved to the frames' centre (an image circle that covered the spec's frame
    covers the new one), the published smoothing's Gaussian scaled by s. A lens with
    distortion is refused (turn the frames instead: ``turn_archive``)."""
    c = spec.camera
    if abs(width * c.height - height * c.width) <= 1e-9 * width * c.height:
        return spec.at_resolution(width, height), "the spec's camera at the frames' size"
    if not (isinstance(width, int) and isinstance(height, int) and width >= 2 and height >= 2):
        raise ValueError(f"a camera's size must be whole pixels, at least 2x2, got {width!r}x{height!r}")
    if c.projection != "pinhole" or any(c.distortion):
        raise ValueError(f"{width}x{height} frames have another aspect than the {c.width}x{c.height} camera of sensor "
                         f"{spec.name!r}, whose {c.projection} lens with distortion {list(c.distortion)} cannot be set "
                         "from them; turn the frames (--turn) or give a spec whose camera has the frames' aspect")
    s = math.sqrt(width * height / (c.width * c.height))
    f = c.height / 2 / math.tan(c.fov_y / 2) * s
    old = ((c.width - 1) / 2, (c.height - 1) / 2)
    new = ((width - 1) / 2, (height - 1) / 2)

    def moved(point):
        return None if point is None else tuple(n + (p - o) * s for p, o, n in zip(point, old, new))

    covered = c.mask_radius_px >= 0.5 * math.hypot(c.width - 1, c.height - 1) and c.mask_center_px in (None, old)
    camera = dataclasses.replace(
        c, width=width, height=height, fov_y=2 * math.atan(height / 2 / f),
        mask_radius_px=0.5 * math.hypot(width, height) if covered else c.mask_radius_px * s,
        mask_center_px=None if c.mask_center_px is None else new if covered else moved(c.mask_center_px),
        principal_point_px=moved(c.principal_point_px))
    elastic = dataclasses.replace(spec.elastic, sigma_px=spec.elastic.sigma_px * s,
                                  radius_px=max(1, int(round(spec.elastic.radius_px * s))))
    return spec.replace(camera=camera, elastic=elastic), (
        f"the camera's sensor set from the {width}x{height} frames (the spec's is {c.width}x{c.height}: "
        f"focal length {s:.4g} of its, in pixels)")


def _axis_distance(scaled) -> tuple[float, object]:
    """(how far from the camera, m, its optical axis meets the membrane of ``scaled``, its Camera)."""
    from .camera import Camera
    from .contact import surface_point
    from .geometry import membrane_mesh

    camera = Camera.from_spec(scaled)
    point, _ = surface_point(membrane_mesh(scaled), camera, (camera.cx, camera.cy))
    return float(point[2]), camera


def spec_pixel_m(spec, width: int, height: int) -> float:
    """A pixel's size on the membrane, metres, where the optical axis of the spec's camera,
    at ``width`` x ``height`` (:func:`frames_spec`), meets it: the folder format's default
    pixel size."""
    z, camera = _axis_distance(frames_spec(spec, width, height)[0])
    return z / camera.f


def capture_spec(spec, width: int, height: int, pixel_m: float):
    """The spec's sensor with a camera of the frames' size whose pixel spans ``pixel_m``
    metres where its optical axis meets the membrane (module doc); returns (spec, note)."""
    from .spec_read import spec_from_dict

    if not (isinstance(pixel_m, (int, float)) and math.isfinite(pixel_m) and 0 < pixel_m < 0.01):
        raise ValueError(f"pixel size must be a length in metres, > 0 and under 10 mm, got {pixel_m!r}")
    scaled, how = frames_spec(spec, width, height)
    z, camera = _axis_distance(scaled)
    now = z / camera.f
    if camera.is_pinhole:
        fov_y = 2 * math.atan(height / 2 * pixel_m / z)
        scaled = spec_from_dict(scaled.replace(camera=dataclasses.replace(scaled.camera, fov_y=fov_y)).to_dict(),
                                f"sensor {spec.name!r} at {width}x{height}")
        return scaled, (f"{how}; fov_y set to {fov_y:.6g} rad so that a pixel spans {pixel_m * 1e3:.6g} mm where the optical "
                        f"axis meets the membrane, {z * 1e3:.4g} mm from the camera (the spec's gave "
                        f"{now * 1e3:.6g} mm)")
    if abs(now / pixel_m - 1) > PIXEL_TOLERANCE:
        raise ValueError(f"sensor {spec.name!r}: its {spec.camera.projection} lens with distortion "
                         f"{list(spec.camera.distortion)} sees {now * 1e3:.5g} mm a pixel at {width}x{height}, not "
                         f"{pixel_m * 1e3:.5g} mm; give a spec whose camera matches the set")
    return scaled, f"{how}; the spec's lens kept: {now * 1e3:.6g} mm a pixel where its axis meets the membrane"


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


def import_capture(archive: Archive, out: str | Path, spec, ball_m: float | None, pixel_m: float,
                   depth: str = "profile", fmt: str = TAXIM, layout=None, rim_share: float = 1.0,
                   fit: dict | None = None) -> dict:
    """Write ``archive`` as a capture dataset in ``out`` (module doc); returns a summary.

    Parameters
    ----------
    spec : the unit's ``SensorSpec`` (its camera is put at the frames' size and pixel).
    ball_m : the ball's diameter, metres, for every press whose archive records none
        (``Archive.balls_m``); None where every press records its own.
    pixel_m : a pixel's size on the membrane, metres.
    depth : "profile", "radius", "elastic", "fitted" or "given" (module doc). rim_share : the share of the contact's
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
    n = len(archive.frames)
    balls = np.full(n, np.nan) if archive.balls_m is None else np.asarray(archive.balls_m, np.float64)
    if ball_m is not None:
        balls = np.where(np.isnan(balls), float(ball_m), balls)
    if np.isnan(balls).any():
        i = int(np.flatnonzero(np.isnan(balls))[0])
        raise ValueError(f"archive {archive.path}: press {i} ({archive.names[i]}) has no ball diameter in its "
                         "table and none was given (--ball-mm, or ball_mm in the set's records)")
    objects = [ball_name(b) for b in balls]
    if depth == "given":
        given = np.full(n, np.nan) if archive.depths_m is None else np.asarray(archive.depths_m, np.float64)
        if np.isnan(given).any():
            i = int(np.flatnonzero(np.isnan(given))[0])
            raise ValueError(f"archive {archive.path}: press {i} ({archive.names[i]}) records no depth; --depth given "
                             "takes every press's depth from its table")
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise ValueError(f"--out {out} is a file, not a folder")
    if out.is_dir() and any(out.iterdir()) and not (out / "dataset.json").exists():
        raise DatasetError(f"{out} holds files but no dataset; import into an empty or new folder (nothing was "
                           "written)")
    h, w = archive.no_contact.shape[:2]
    unit, camera_note = capture_spec(spec, w, h, pixel_m)
    camera = Camera.from_spec(unit)
    mesh = membrane_mesh(unit)

    if (depth == "fitted") != (fit is not None):
        raise ValueError("depth 'fitted' takes the joint fit's report (fit), and only it does")
    if depth == "fitted" and len(set(archive.names)) != len(archive.names):
        raise ValueError(f"archive {archive.path}: its presses' names repeat, so the joint fit's depths cannot be "
                         "matched to them")
    if depth == "fitted" and len(set(objects)) > 1:
        raise ValueError(f"archive {archive.path}: its presses use balls of {len(set(objects))} sizes; the joint fit's "
                         "relation is for one ball")
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

        def elastic_depth(contact_radius_m: float, R: float) -> float:
            # the fitted model's own rim-to-depth relation times k, as the fit gave its held-out presses
            return min(share * float(depth_at_radius(contact_radius_m, relation[1], relation[0])), limit)

        def deepest(R: float) -> float:
            return limit
    elif depth == "elastic":
        from .elastic_solid import ball_depth_for_contact

        thickness, poisson = unit.membrane.elastomer_thickness, unit.elastic.poisson_ratio

        def elastic_depth(contact_radius_m: float, R: float) -> float:
            return ball_depth_for_contact(contact_radius_m, R, thickness, poisson, cap=True)

        def deepest(R: float) -> float:
            return elastic_depth(math.inf, R)

    taps, fitted, capped = [], [], []
    for i, (centre, radius) in enumerate(zip(archive.centres_px, archive.radii_px)):
        name = f"archive {archive.path}: press {i} ({archive.names[i]})"
        R = balls[i] / 2
        if depth == "radius":
            edge_px = float(radius)
        else:
            try:
                edge_px = contact_edge_px(archive.frames[i], archive.no_contact, centre, R / pixel_m)
            except ValueError as exc:
                if depth != "given":
                    raise ValueError(f"{name}: {exc}") from None
                edge_px = float(radius)  # a given depth needs no rim; the annotation stands in for it
        if depth == "given":
            d = float(given[i])
            capped.append(False)
        elif depth in ("elastic", "fitted"):
            try:
                d = own[archive.names[i]] if archive.names[i] in own else elastic_depth(edge_px * pixel_m, R)
            except ValueError as exc:
                raise ValueError(f"{name}: {exc}") from None
            # a rim wider than the deepest tabulated press leaves is given that depth, and says so
            capped.append(d >= deepest(R))
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
            taps.append(press_tap(i, objects[i], unit, mesh, camera, centre, d))
        except ValueError as exc:
            raise ValueError(f"{name}: {exc}") from None
        fitted.append(edge_px)
    # one name for every format, so that the same presses give the same protocol.json
    protocol = Protocol(name="import", taps=tuple(taps), seed=None)
    validate(protocol, unit, mesh)

    digest = archive.sha256 or _sha256(archive.path)
    kinds = sorted(set(objects), key=objects.index)
    meta = {
        "source": "real",
        "sensor": unit.to_dict(),
        "protocol": {"name": protocol.name, "seed": None, "taps": len(taps), "objects": kinds},
        "image_size": [w, h],
        "image": "8-bit RGB PNG from the camera",
        "depth": "none: a real capture has no depth map",
        "renderer": {"renderer": "camera", "camera": {"kind": "archive", "format": fmt, "sha256": digest,
                                                      **archive.notes}},
        "rig": {"layout": layout.to_dict(), "virtual": False, "printer": None, "servos": None},
        "import": {"format": fmt, "archive": archive.path, "sha256": digest,
                   "ball_mm": balls[0] * 1e3 if len(kinds) == 1 else [float(b) * 1e3 for b in balls],
                   "pixel_mm": pixel_m * 1e3, "depth": depth, "rim_share": rim_share,
                   **({"elastic_fit": {"thickness_m": thickness, "poisson_ratio": poisson, "depth_share": share,
                                       "fitted_presses": len(fitted_names)}} if depth == "fitted" else {}),
                   "rims_capped": int(sum(capped)), "camera": camera_note,
                   "turned_deg": int(archive.notes.get("turned_deg", 0)),
                   "markers": archive.notes.get("markers", "kept"),
                   "poses": "each press's measured_pose is the rig's pose that presses the ball as annotated: on the "
                            "membrane where the camera sees the annotated centre, along its normal, to the depth "
                            "the depth method gives"},
    }
    writer = DatasetWriter(out, meta, protocol.to_dict())
    if not (out / "background.png").exists():
        writer.write_background(archive.no_contact)
    vertices = {k: np.asarray(indenter(k).vertices, np.float64) for k in kinds}
    from .generate import tap_fields

    for tap, edge_px, cap, centre, radius, name in zip(taps, fitted, capped, archive.centres_px, archive.radii_px,
                                                       archive.names):
        sid = sample_id(tap.index, tap.object)
        if sid in writer.done:
            continue
        pose = tap_pose(tap, vertices[tap.object], layout)
        record = {**tap_fields(tap), "commanded_pose": pose, "measured_pose": pose, "measured_depth": tap.depth,
                  "contact_center_px": [float(c) for c in centre], "contact_radius_px": float(radius),
                  "contact_edge_px": edge_px, "source_name": name,
                  **({"contact_radius_capped": cap} if rim_share != 1.0 or depth in ("elastic", "fitted") else {}),
                  **({"depth_source": "fitted" if name in fitted_names else "rule"} if depth == "fitted" else
                     {"depth_source": "given"} if depth == "given" else {})}
        files = write_sample_files(out, sid, archive.frames[tap.index], None)
        writer.append({**record, **files})
    depths = np.array([t.depth for t in taps])
    return {"out": str(out), "presses": len(read_samples(out)), "object": ", ".join(kinds), "depth": depth,
            "rim_share": rim_share, "rims_capped": int(sum(capped)),
            "depth_mm": {"median": float(np.median(depths) * 1e3), "min": float(depths.min() * 1e3),
                         "max": float(depths.max() * 1e3)},
            "camera": camera_note}


def default_depth(archive: Archive) -> str:
    """How an import gives each press its depth when not told: the archive's own depths
    ("given") where it records one for every press, else the rim fitted to each image
    ("profile")."""
    depths = archive.depths_m
    return "given" if depths is not None and not np.isnan(depths).any() else "profile"


def open_set(archive: str | Path, fmt: str | None = None, **given) -> tuple:
    """Read the set of presses at ``archive`` as ``tactile-sim import`` and ``bench real``
    do: (its Archive, turned as asked; the unit's spec; the ball's diameter, m, or None;
    a pixel's size, m; what was settled and from where).

    Each setting (``spec``, ``ball_mm``, ``pixel_mm``, ``turn``, ``markers``, and the folder's ``table``,
    ``no_contact``, ``columns``, ``channels``) comes from ``given`` where it is not None,
    else from the set's records beside it (:func:`read_set_records`), else from the
    format's defaults: Taxim's pack is its published GelSight's; a folder's spec is the
    GelSight's, its pixel size the spec's own at the frames' size (``scenes.spec_read.spec_file``,
    :func:`spec_pixel_m`), its ball none (the table's, or refused). ``turn`` "auto" turns
    the frames a quarter when their orientation is not the spec camera's. ``markers``
    "inpaint" finds each frame's printed marker dots and fills them (``scenes.markers``);
    "keep" (the default) leaves the frames as they are.
    """
    from .spec_read import load_spec, spec_file

    records = read_set_records(archive)
    fmt = fmt or records.get("format") or guess_format(archive)
    if fmt not in FORMATS:
        raise ValueError(f"format must be one of {sorted(FORMATS)}, got {fmt!r}")
    if records.get("format", fmt) != fmt:
        raise ValueError(f"set records {records['records']} say the archive is {records['format']!r}, not {fmt!r}")
    settings = {k: v for k, v in records.items() if k not in ("format", "name", "notes")}
    settings.update({k: ({**settings[k], **v} if k == "columns" and k in settings else v)
                     for k, v in given.items() if v is not None})
    where = {k: ("given" if given.get(k) is not None else f"records {records['records']}")
             for k in settings if k != "records"}
    if fmt == TAXIM:
        extra = sorted(k for k in FOLDER_OPTIONS if k in settings)
        if extra:
            raise ValueError(f"{', '.join(extra)}: options of the folder format, not of a Taxim pack")
        read = read_taxim(archive)
        defaults = DEFAULTS[TAXIM]
    else:
        read = read_folder(archive, settings.get("table"), settings.get("no_contact"), settings.get("columns"),
                           settings.get("channels", "rgb"))
        defaults = {"spec": Path(__file__).with_name("sensors") / "gelsight.toml"}
    source = spec_file(settings["spec"]) if "spec" in settings else defaults["spec"]
    spec = load_spec(source)
    turn = settings.get("turn", 0)
    h, w = read.no_contact.shape[:2]
    if turn == "auto":
        turn = orientation_turn(spec, w, h)
    if isinstance(turn, str):
        try:
            turn = int(turn)
        except ValueError:
            pass
    read = turn_archive(read, turn)
    h, w = read.no_contact.shape[:2]
    if "pixel_mm" in settings:
        pixel = float(settings["pixel_mm"]) * 1e-3
    elif "pixel_m" in defaults:
        pixel, where["pixel_mm"] = defaults["pixel_m"], f"the {fmt} set's default"
    else:
        pixel, where["pixel_mm"] = spec_pixel_m(spec, w, h), f"the spec's camera at {w}x{h}"
    markers = settings.get("markers", "keep")
    if markers not in MARKERS:
        raise ValueError(f"markers must be one of {MARKERS}, got {markers!r}")
    if markers == "inpaint":
        from .markers import remove_markers

        f0, frames, report = remove_markers(read.no_contact, read.frames, pixel)
        read = dataclasses.replace(read, no_contact=f0, frames=frames, notes={**read.notes, "markers": report})
    ball = float(settings["ball_mm"]) * 1e-3 if "ball_mm" in settings else defaults.get("ball_m")
    if "ball_mm" not in settings and ball is not None:
        where["ball_mm"] = f"the {fmt} set's default"
    where.setdefault("spec", f"the {fmt} format's default")
    return read, spec, ball, pixel, {"format": fmt, "spec": str(source), "turn_deg": turn, "markers": markers,
                                     "records": records.get("records"), "from": where}
