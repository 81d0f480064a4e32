"""The study's contacts: depth maps on our membrane, and whether the reference accepts them.

Four kinds, each a name -> (H, W) float32 depth map, metres, planar z: the analytic
contacts pressed as ``tactile-sim demo`` presses them (``analytic_contacts``), the
published depth maps moved onto our membrane (``published_contacts``), and taps captured
on the MuJoCo rig (``rig_contacts``): the base protocol's (``base_taps``) or taps spread
over each class of region of the membrane (``surface_taps``). ``refusal`` says why the
reference cannot build a contact's elastomer at its real depth.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import trimesh

from scenes.camera import Camera, back_project, check_depth
from scenes.contact import press
from scenes.curvature import CLASSES, classify, principal_curvatures
from scenes.indenters import INDENTERS
from scenes.spec import SensorSpec

from ..reproduce_published import N_PANELS, load_depths

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

#: ``--quick``'s contacts (its settings: ``frames.QUICK``).
QUICK_CONTACTS = ("sphere_tip", "box_edge")


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
    """The named base-protocol taps: name -> ``scenes.taps.Tap``."""
    from scenes.protocol import base_protocol

    unknown = set(names) - set(BASE)
    if unknown:
        raise ValueError(f"base contacts must be among {list(BASE)}, got {sorted(unknown)}")
    wanted = {BASE_TAPS[BASE.index(n)]: n for n in names}
    return {wanted[(t.object, t.row, t.position)]: t for t in base_protocol(spec, mesh, INDENTERS).taps
            if (t.object, t.row, t.position) in wanted}


def surface_taps(spec: SensorSpec, mesh: trimesh.Trimesh, per_class: int = SURFACE_PER_CLASS, seed: int = 0) -> dict:
    """Taps spread over the kinds of region the membrane has: name -> ``scenes.taps.Tap``.

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

    taps : name -> ``scenes.taps.Tap``.  ref_depth : (H, W), the ray-cast D_ref.
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
