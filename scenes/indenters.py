"""Indenters: the eight printed objects of the GelTip paper, built from parameters, or any mesh file.

Every paper indenter shares one local frame, in metres: a base block
``BASE_SIDE_M`` x ``BASE_SIDE_M`` centred on x = y = 0, from z = 0 to
``BASE_HEIGHT_M``, and a feature on top of it, at most ``MAX_FEATURE_HEIGHT_M``
tall. +z is the side that touches the membrane (see
:func:`scenes.contact.pose_indenter`). The dimensions were measured on the
objects the authors published (Gomes, Paoletti, Luo, "Beyond Flat GelSight
Sensors"); each shape's are the defaults of a small frozen dataclass, so a
variant is one keyword away::

    make_indenter("cone")                        # the paper's cone
    make_indenter("cone", top_radius=0.0)        # a sharp one
    make_indenter("random", seed=3)              # another seeded relief
    indenter("my_part.stl")                      # any closed mesh, mm by default
    indenter("ball_4mm")                         # a 4 mm ball (any diameter: ball_<D>mm)

The published objects also have a mounting pocket cut from below into the base;
the in-sensor camera never sees that side, so the base here is solid.

Building needs the manifold engine of trimesh's booleans (``pip install manifold3d``).
"""

from __future__ import annotations

import dataclasses
import math
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import trimesh

from .shapes.mesh import UNIT_SCALE, read_mesh_file, validate_mesh

#: The paper's objects, by the names used here. "indented_prism" is the published
#: ``dot_in``, "open_cylinder" the published ``cylinder_shell``.
INDENTERS = ("dots", "sphere", "indented_prism", "cylinder", "open_cylinder", "cone", "pacman", "random")
#: Balls of any diameter, by name: ``ball_<diameter in mm>mm`` (:func:`ball_name`), e.g. the
#: 4 mm ball that pressed the public GelSight's calibration set (Taxim), "ball_4mm". Each
#: is the sphere indenter's build with that radius, its top at the envelope's top.
BALL_PREFIX, BALL_SUFFIX = "ball_", "mm"

#: Side of the square base block, metres.
BASE_SIDE_M = 16e-3
#: Height of the base block, metres: the feature starts at this z.
BASE_HEIGHT_M = 10e-3
#: Tallest feature above the base, metres: every paper indenter ends at z = 20 mm.
MAX_FEATURE_HEIGHT_M = 10e-3
#: The balls' diameters a name may give, metres: the base block holds up to 16 mm.
BALL_DIAMETER_BOUNDS_M = (0.5e-3, BASE_SIDE_M)

#: Facets per full circle of every round part: the polygon's area is
#: sin(2 pi / n) n / (2 pi) = 0.9984 of the circle's.
CIRCLE_SEGMENTS = 64
#: Icosphere subdivisions of the sphere indenter (5120 faces) and of the small
#: domes and dimples (320 faces).
SPHERE_SUBDIVISIONS = 4
SMALL_SPHERE_SUBDIVISIONS = 2
#: Features reach this far down into the base, metres, so that no boolean meets
#: a coplanar face (the part inside the base vanishes in the union).
_OVERLAP_M = 1e-3

#: Declared "m" but larger than this, metres: the file is in millimetres.
MAX_INDENTER_EXTENT_M = 0.5
#: Declared "mm" but smaller than this, millimetres: the file is in metres.
MIN_INDENTER_EXTENT_MM = 0.1


# --- Parameters ---------------------------------------------------------------------
# Every length in metres, every angle in radians; defaults are the published objects.


def _check(params, name: str, value: float, lo: float, hi: float, lo_open: bool = True) -> None:
    """Raise a ValueError naming ``Class.field`` when value is outside (lo, hi]."""
    ok = (value > lo if lo_open else value >= lo) and value <= hi and math.isfinite(value)
    if not ok:
        bracket = "(" if lo_open else "["
        raise ValueError(
            f"{type(params).__name__}.{name} must be in {bracket}{lo:g}, {hi:g}], got {value!r}"
        )


_HALF = BASE_SIDE_M / 2


@dataclass(frozen=True)
class DotsParams:
    """A square plateau with small hemispherical domes on a ring (published ``dots``)."""

    plateau_side: float = 14e-3  # side of the square plateau, m
    plateau_height: float = 9e-3  # plateau top above the base, m (domes add dome_radius)
    dome_radius: float = 1e-3  # radius of each hemispherical dome, m
    ring_radius: float = 3e-3  # distance of the dome centres from the axis, m
    count: int = 5  # number of domes, the first on -x, evenly spaced

    def __post_init__(self):
        _check(self, "plateau_side", self.plateau_side, 0, BASE_SIDE_M)
        _check(self, "dome_radius", self.dome_radius, 0, self.plateau_side / 2)
        _check(self, "plateau_height", self.plateau_height, 0, MAX_FEATURE_HEIGHT_M - self.dome_radius)
        _check(self, "ring_radius", self.ring_radius, 0, self.plateau_side / 2 - self.dome_radius, lo_open=False)
        if not (isinstance(self.count, int) and self.count >= 1):
            raise ValueError(f"DotsParams.count must be an int >= 1, got {self.count!r}")


@dataclass(frozen=True)
class SphereParams:
    """A sphere whose top is the top of the envelope, on a short neck (published ``sphere``).

    The published sphere (radius 5 mm, centre 5 mm above the base) would touch the
    base at a single point; a neck of ``neck_fraction * radius`` joins them into one solid.
    A larger sphere is clipped by the base.
    """

    radius: float = 5e-3  # m
    neck_fraction: float = 0.5  # neck radius / sphere radius (published: 2.5 mm / 5 mm)
    height: float = 10e-3  # top of the sphere above the base, m

    def __post_init__(self):
        _check(self, "height", self.height, 0, MAX_FEATURE_HEIGHT_M)
        _check(self, "radius", self.radius, 0, min(_HALF, (BASE_HEIGHT_M + self.height) / 2))
        _check(self, "neck_fraction", self.neck_fraction, 0, 1 - 1e-3)


@dataclass(frozen=True)
class IndentedPrismParams:
    """A square prism with a spherical dimple in its top (published ``dot_in``)."""

    side: float = 8e-3  # m
    height: float = 10e-3  # m
    dimple_width: float = 4e-3  # diameter of the dimple's rim, m
    dimple_depth: float = 2e-3  # m, at most width / 2 (a hemisphere)

    def __post_init__(self):
        _check(self, "side", self.side, 0, BASE_SIDE_M)
        _check(self, "height", self.height, 0, MAX_FEATURE_HEIGHT_M)
        _check(self, "dimple_width", self.dimple_width, 0, self.side * (1 - 1e-3))
        _check(self, "dimple_depth", self.dimple_depth, 0, min(self.height, self.dimple_width / 2))

    @property
    def dimple_radius(self) -> float:
        """Radius of the sphere that cuts the dimple, m: (a^2 + h^2) / (2 h)."""
        a, h = self.dimple_width / 2, self.dimple_depth
        return (a * a + h * h) / (2 * h)


@dataclass(frozen=True)
class CylinderParams:
    """A solid round cylinder (published ``cylinder``)."""

    radius: float = 3e-3  # m
    height: float = 10e-3  # m

    def __post_init__(self):
        _check(self, "radius", self.radius, 0, _HALF)
        _check(self, "height", self.height, 0, MAX_FEATURE_HEIGHT_M)


@dataclass(frozen=True)
class OpenCylinderParams:
    """A tube, open at the top down to the base (published ``cylinder_shell``)."""

    outer_radius: float = 3.5e-3  # m
    wall: float = 0.8e-3  # m
    height: float = 10e-3  # m

    def __post_init__(self):
        _check(self, "outer_radius", self.outer_radius, 0, _HALF)
        _check(self, "wall", self.wall, 0, self.outer_radius * (1 - 1e-3))
        _check(self, "height", self.height, 0, MAX_FEATURE_HEIGHT_M)


@dataclass(frozen=True)
class ConeParams:
    """A cone, truncated at the top (published ``cone``)."""

    base_radius: float = 4e-3  # m
    top_radius: float = 0.5e-3  # m, 0 for a sharp tip
    height: float = 10e-3  # m

    def __post_init__(self):
        _check(self, "base_radius", self.base_radius, 0, _HALF)
        _check(self, "top_radius", self.top_radius, 0, self.base_radius, lo_open=False)
        _check(self, "height", self.height, 0, MAX_FEATURE_HEIGHT_M)


@dataclass(frozen=True)
class PacmanParams:
    """A cylinder with a wedge (the mouth) cut out, opening towards +x (published ``pacman``)."""

    radius: float = 3e-3  # m
    mouth_angle: float = math.radians(70.0)  # full opening of the wedge, radians
    height: float = 10e-3  # m

    def __post_init__(self):
        _check(self, "radius", self.radius, 0, _HALF)
        _check(self, "mouth_angle", self.mouth_angle, 0, math.pi * (1 - 1e-3))
        _check(self, "height", self.height, 0, MAX_FEATURE_HEIGHT_M)


@dataclass(frozen=True)
class RandomParams:
    """Seeded random strokes of round-ended width, extruded (published ``random``).

    Each stroke is a smooth random walk inside the central square of half-side
    ``half_extent``; the first reaches ``height``, the others a seeded fraction of it
    in [``min_height_fraction``, 1] (1 gives one flat top, as the published object).
    """

    strokes: int = 3  # number of strokes
    segments: int = 6  # straight pieces per stroke
    segment_length: float = 1.5e-3  # m
    width: float = 0.8e-3  # stroke width, m
    max_turn: float = math.radians(60.0)  # largest heading change between pieces, radians
    half_extent: float = 4e-3  # strokes stay within |x|, |y| <= this, m
    height: float = 10e-3  # m
    min_height_fraction: float = 0.8

    def __post_init__(self):
        for field in ("strokes", "segments"):
            value = getattr(self, field)
            if not (isinstance(value, int) and value >= 1):
                raise ValueError(f"RandomParams.{field} must be an int >= 1, got {value!r}")
        _check(self, "segment_length", self.segment_length, 0, BASE_SIDE_M)
        _check(self, "half_extent", self.half_extent, 0, _HALF)
        _check(self, "width", self.width, 0, self.half_extent)
        _check(self, "max_turn", self.max_turn, 0, math.pi, lo_open=False)
        _check(self, "height", self.height, 0, MAX_FEATURE_HEIGHT_M)
        _check(self, "min_height_fraction", self.min_height_fraction, 0, 1)


#: The parameter class of each paper indenter; its defaults are the published object.
PARAMS = {
    "dots": DotsParams,
    "sphere": SphereParams,
    "indented_prism": IndentedPrismParams,
    "cylinder": CylinderParams,
    "open_cylinder": OpenCylinderParams,
    "cone": ConeParams,
    "pacman": PacmanParams,
    "random": RandomParams,
}


# --- Building blocks ----------------------------------------------------------------


def _union(meshes: list[trimesh.Trimesh]) -> trimesh.Trimesh:
    return trimesh.boolean.union(meshes, engine="manifold")


def _difference(a: trimesh.Trimesh, b: trimesh.Trimesh) -> trimesh.Trimesh:
    return trimesh.boolean.difference([a, b], engine="manifold")


def _base() -> trimesh.Trimesh:
    """The base block: BASE_SIDE_M square, z from 0 to BASE_HEIGHT_M."""
    box = trimesh.creation.box(extents=(BASE_SIDE_M, BASE_SIDE_M, BASE_HEIGHT_M))
    box.apply_translation((0.0, 0.0, BASE_HEIGHT_M / 2))
    return box


def _prism(side: float, z0: float, z1: float) -> trimesh.Trimesh:
    box = trimesh.creation.box(extents=(side, side, z1 - z0))
    box.apply_translation((0.0, 0.0, (z0 + z1) / 2))
    return box


def _cylinder(radius: float, z0: float, z1: float, xy=(0.0, 0.0)) -> trimesh.Trimesh:
    return trimesh.creation.cylinder(radius, segment=[(*xy, z0), (*xy, z1)], sections=CIRCLE_SEGMENTS)


def _sphere(radius: float, centre, subdivisions: int) -> trimesh.Trimesh:
    """Icosphere turned so that one vertex is its top pole (its top is exactly centre + r)."""
    s = trimesh.creation.icosphere(subdivisions=subdivisions, radius=radius)
    s.apply_transform(trimesh.geometry.align_vectors(s.vertices[0], [0.0, 0.0, 1.0]))
    s.apply_translation(centre)
    return s


def _on_base(*features: trimesh.Trimesh) -> trimesh.Trimesh:
    return _union([_base(), *features])


# --- The eight shapes ---------------------------------------------------------------

_Z0 = BASE_HEIGHT_M - _OVERLAP_M  # where features start, inside the base


def _dots(p: DotsParams, rng) -> trimesh.Trimesh:
    top = BASE_HEIGHT_M + p.plateau_height
    angles = math.pi + 2 * math.pi * np.arange(p.count) / p.count
    centres = np.c_[p.ring_radius * np.cos(angles), p.ring_radius * np.sin(angles), np.full(p.count, top)]
    domes = [_sphere(p.dome_radius, c, SMALL_SPHERE_SUBDIVISIONS) for c in centres]
    return _on_base(_prism(p.plateau_side, _Z0, top), *domes)


def _sphere_on_neck(p: SphereParams, rng) -> trimesh.Trimesh:
    zc = BASE_HEIGHT_M + p.height - p.radius
    ball = _sphere(p.radius, (0.0, 0.0, zc), SPHERE_SUBDIVISIONS)
    if zc <= _Z0:  # a sphere this large sinks into the base: no neck needed
        return _on_base(ball)
    # The neck runs up to the centre: above where it leaves the sphere it is inside it.
    return _on_base(ball, _cylinder(p.neck_fraction * p.radius, _Z0, zc))


def _indented_prism(p: IndentedPrismParams, rng) -> trimesh.Trimesh:
    top = BASE_HEIGHT_M + p.height
    r = p.dimple_radius
    dimple = _sphere(r, (0.0, 0.0, top - p.dimple_depth + r), SMALL_SPHERE_SUBDIVISIONS + 1)
    return _difference(_on_base(_prism(p.side, _Z0, top)), dimple)


def _solid_cylinder(p: CylinderParams, rng) -> trimesh.Trimesh:
    return _on_base(_cylinder(p.radius, _Z0, BASE_HEIGHT_M + p.height))


def _open_cylinder(p: OpenCylinderParams, rng) -> trimesh.Trimesh:
    top = BASE_HEIGHT_M + p.height
    tube = trimesh.creation.annulus(
        p.outer_radius - p.wall, p.outer_radius, segment=[(0, 0, _Z0), (0, 0, top)], sections=CIRCLE_SEGMENTS
    )
    return _on_base(tube)  # the base fills the tube below its top: the hole ends there


def _cone(p: ConeParams, rng) -> trimesh.Trimesh:
    # (r, z) profile revolved about z: a plinth inside the base, then the frustum.
    profile = [(0.0, _Z0), (p.base_radius, _Z0), (p.base_radius, BASE_HEIGHT_M)]
    top = BASE_HEIGHT_M + p.height
    profile += [(p.top_radius, top), (0.0, top)] if p.top_radius > 0 else [(0.0, top)]
    return _on_base(trimesh.creation.revolve(np.array(profile), sections=CIRCLE_SEGMENTS))


def _pacman(p: PacmanParams, rng) -> trimesh.Trimesh:
    top = BASE_HEIGHT_M + p.height
    # The wedge: a convex fan from the axis, reaching past the rim, taller than the cylinder.
    t = np.linspace(-p.mouth_angle / 2, p.mouth_angle / 2, 9)
    fan = np.vstack([[0.0, 0.0], 2 * p.radius * np.c_[np.cos(t), np.sin(t)]])
    pts = np.vstack([np.c_[fan, np.full(len(fan), z)] for z in (_Z0 - _OVERLAP_M, top + _OVERLAP_M)])
    wedge = trimesh.convex.convex_hull(pts)
    return _on_base(_difference(_cylinder(p.radius, _Z0, top), wedge))


def _random_strokes(p: RandomParams, rng: np.random.Generator) -> list[np.ndarray]:
    """Seeded stroke centre-lines: a list of (segments + 1, 2) arrays, metres."""
    limit = p.half_extent - p.width / 2  # centre-lines stay here, so strokes stay in the square
    strokes = []
    for _ in range(p.strokes):
        point = rng.uniform(-limit, limit, size=2)
        heading = rng.uniform(-math.pi, math.pi)
        line = [point]
        for _ in range(p.segments):
            heading += rng.uniform(-p.max_turn, p.max_turn)
            step = p.segment_length * np.array([math.cos(heading), math.sin(heading)])
            nxt = line[-1] + step
            # Bounce off the square's sides: mirror the step and the heading.
            for axis in (0, 1):
                if abs(nxt[axis]) > limit:
                    nxt[axis] = math.copysign(2 * limit, nxt[axis]) - nxt[axis]
                    heading = -heading if axis == 1 else math.pi - heading
            line.append(np.clip(nxt, -limit, limit))
        strokes.append(np.array(line))
    return strokes


def _random(p: RandomParams, rng: np.random.Generator) -> trimesh.Trimesh:
    fractions = np.concatenate([[1.0], rng.uniform(p.min_height_fraction, 1.0, size=p.strokes - 1)])
    pieces = []
    for line, fraction in zip(_random_strokes(p, rng), fractions):
        top = BASE_HEIGHT_M + fraction * p.height
        disc = _cylinder(p.width / 2, _Z0, top)
        for a, b in zip(line[:-1], line[1:]):
            # One round-ended piece: the convex hull of two discs' prisms.
            pieces.append(
                trimesh.convex.convex_hull(
                    np.vstack([disc.vertices + (*a, 0.0), disc.vertices + (*b, 0.0)])
                )
            )
    return _on_base(*pieces)


_BUILDERS = {
    "dots": _dots,
    "sphere": _sphere_on_neck,
    "indented_prism": _indented_prism,
    "cylinder": _solid_cylinder,
    "open_cylinder": _open_cylinder,
    "cone": _cone,
    "pacman": _pacman,
    "random": _random,
}


def _check_name(name: str) -> None:
    if name not in INDENTERS:
        raise ValueError(f"indenter name must be one of {', '.join(INDENTERS)}; got {name!r}")


def indenter_params(name: str, **params):
    """The parameters of a paper indenter: the published defaults with ``params`` replaced.

    Raises a ValueError naming the fields the shape has when a keyword is not one.
    """
    _check_name(name)
    cls = PARAMS[name]
    known = [f.name for f in dataclasses.fields(cls)]
    unknown = sorted(set(params) - set(known))
    if unknown:
        raise ValueError(f"{name!r} has no parameter {', '.join(unknown)}; its parameters are {', '.join(known)}")
    return cls(**params)


def make_indenter(name: str, seed: int = 0, **params) -> trimesh.Trimesh:
    """Build one of the paper's indenters from its parameters.

    Parameters
    ----------
    name : one of :data:`INDENTERS`.
    seed : int
        Seeds the relief of ``"random"`` (``np.random.default_rng(seed)``); the other
        shapes ignore it.
    **params
        Fields of the shape's parameter class in :data:`PARAMS` (metres, radians),
        replacing the published defaults, e.g. ``make_indenter("cylinder", radius=2e-3)``.

    Returns
    -------
    trimesh.Trimesh, metres, in the indenter's local frame: base block
    ``BASE_SIDE_M`` square from z = 0 to ``BASE_HEIGHT_M``, feature above it, +z
    towards the membrane. Watertight, outward winding, positive volume.

    Raises
    ------
    ValueError naming the known names for an unknown ``name``, the shape's fields for
    an unknown keyword, and ``Class.field`` with its allowed range for a bad value.
    """
    p = indenter_params(name, **params)
    try:
        import manifold3d  # noqa: F401  (the engine of trimesh's booleans)
    except ImportError as exc:
        raise ImportError("make_indenter needs the manifold boolean engine: pip install manifold3d") from exc
    mesh = _BUILDERS[name](p, np.random.default_rng(seed))
    if not (mesh.is_watertight and mesh.is_winding_consistent and mesh.volume > 0):  # a bug, never input
        raise RuntimeError(f"building indenter {name!r} with {p} gave a mesh that is not a closed solid")
    return mesh


# --- Any mesh file ------------------------------------------------------------------


def check_closed(mesh: trimesh.Trimesh, name: str) -> None:
    """Raise ValueError naming ``name`` unless the mesh is watertight and consistently
    wound: a camera tells an indenter's inside from its outside only on a closed surface."""
    if not mesh.is_watertight:
        open_edges = len(trimesh.grouping.group_rows(mesh.edges_sorted, require_count=1))
        raise ValueError(
            f"{name}: mesh is not watertight ({open_edges} edges bound a single face); "
            "the camera needs a closed surface to tell the indenter's inside from its outside"
        )
    if not mesh.is_winding_consistent:
        raise ValueError(f"{name}: faces are wound inconsistently; fix the mesh's normals")


def load_indenter(path: str | Path, units: str = "mm") -> trimesh.Trimesh:
    """Load any closed mesh (STL, OBJ, PLY, ...) as an indenter, in metres.

    Parameters
    ----------
    path : file readable by trimesh, in the indenter's local frame (+z faces the membrane).
    units : "mm" (the default, as printable parts usually are) or "m", the file's units.
        A size implausible for the declared units is refused, never silently rescaled:
        over ``MAX_INDENTER_EXTENT_M`` when "m" was declared, under
        ``MIN_INDENTER_EXTENT_MM`` when "mm" was.

    Returns
    -------
    trimesh.Trimesh, metres, watertight. A closed mesh wound inside-out is turned
    outward, with a warning.

    Raises
    ------
    FileNotFoundError if the file does not exist; ValueError, naming the file, if it
    cannot be read, holds no faces or non-finite vertices, has implausible units, or
    is not watertight.
    """
    path = Path(path)
    scale = UNIT_SCALE.get(units)
    if scale is None:
        raise ValueError(f"units must be 'm' or 'mm', got {units!r}")
    # Not scenes.shapes.mesh.load_mesh: its 1 m limit is the membrane's rule, and an
    # indenter's unit check must come before it.
    mesh = read_mesh_file(path, "indenter")
    vertices = np.asarray(mesh.vertices, dtype=np.float64)
    if np.isfinite(vertices).all():  # otherwise validate_mesh names the bad vertices
        extent = float(np.max(vertices.max(axis=0) - vertices.min(axis=0)))  # file units
        if units == "m" and extent > MAX_INDENTER_EXTENT_M:
            raise ValueError(
                f"indenter file {path}: extent {extent:g} m is larger than {MAX_INDENTER_EXTENT_M:g} m "
                "for an indenter; it looks like millimetres: load it with units='mm'"
            )
        if units == "mm" and extent < MIN_INDENTER_EXTENT_MM:
            raise ValueError(
                f"indenter file {path}: extent {extent:g} mm is smaller than {MIN_INDENTER_EXTENT_MM:g} mm "
                "for an indenter; it looks like metres: load it with units='m'"
            )
        if extent * scale > MAX_INDENTER_EXTENT_M:
            raise ValueError(
                f"indenter file {path}: extent {extent:g} {units} is larger than "
                f"{MAX_INDENTER_EXTENT_M:g} m, implausible for an indenter"
            )
    # Validate before processing: trimesh's processing silently drops NaN vertices.
    validate_mesh(trimesh.Trimesh(vertices * scale, mesh.faces, process=False), name=f"indenter file {path}")
    mesh = trimesh.Trimesh(vertices * scale, mesh.faces, process=True)
    check_closed(mesh, f"indenter file {path}")
    if mesh.volume < 0:
        warnings.warn(f"indenter file {path}: mesh is wound inside-out; turned outward", stacklevel=2)
        mesh.invert()
    return mesh


def ball_name(diameter_m: float) -> str:
    """The name of a ball indenter of ``diameter_m`` metres, e.g. "ball_4mm" (module doc);
    ValueError outside BALL_DIAMETER_BOUNDS_M."""
    d = float(diameter_m)
    lo, hi = BALL_DIAMETER_BOUNDS_M
    if not (math.isfinite(d) and lo <= d <= hi):
        raise ValueError(f"a ball's diameter must be in [{lo * 1e3:g}, {hi * 1e3:g}] mm, got {d * 1e3:g} mm"
                         + (" (metres were expected, not millimetres?)" if d > hi * 10 else ""))
    return f"{BALL_PREFIX}{round(d * 1e3, 6):g}{BALL_SUFFIX}"


def ball_diameter(name: str) -> float | None:
    """A ball indenter's diameter, metres, from its name (``ball_<D>mm``); None for any
    other name or a diameter out of bounds."""
    name = str(name)
    if not (name.startswith(BALL_PREFIX) and name.endswith(BALL_SUFFIX)):
        return None
    try:
        d = float(name[len(BALL_PREFIX):-len(BALL_SUFFIX)]) * 1e-3
    except ValueError:
        return None
    lo, hi = BALL_DIAMETER_BOUNDS_M
    return d if math.isfinite(d) and lo <= d <= hi and ball_name(d) == name else None


def make_ball(diameter_m: float) -> trimesh.Trimesh:
    """A ball of ``diameter_m`` metres on the sphere indenter's neck, its top at the
    envelope's top (the paper indenters' frame, module doc)."""
    ball_name(diameter_m)  # checks the diameter
    p = SphereParams(radius=float(diameter_m) / 2, height=MAX_FEATURE_HEIGHT_M)
    mesh = _sphere_on_neck(p, None)
    if not (mesh.is_watertight and mesh.is_winding_consistent and mesh.volume > 0):  # a bug, never input
        raise RuntimeError(f"building a ball of {diameter_m * 1e3:g} mm gave a mesh that is not a closed solid")
    return mesh


def is_indenter(name_or_path: str | Path) -> bool:
    """Whether :func:`indenter` takes it: a paper indenter's name, a ball's
    (``ball_<D>mm``) or an existing file."""
    return str(name_or_path) in INDENTERS or ball_diameter(str(name_or_path)) is not None or Path(name_or_path).is_file()


def indenter(name_or_path: str | Path, seed: int = 0, units: str = "mm") -> trimesh.Trimesh:
    """A paper indenter by name (:data:`INDENTERS`), or any mesh file by path, in metres.

    ``seed`` seeds ``"random"``; ``units`` are those of a mesh file (see :func:`load_indenter`).
    """
    if not is_indenter(name_or_path):
        raise ValueError(
            f"indenter must be one of {', '.join(INDENTERS)}, a ball ({BALL_PREFIX}<diameter>{BALL_SUFFIX}, e.g. "
            f"ball_4mm) or an existing mesh file; got {str(name_or_path)!r}"
        )
    if str(name_or_path) in INDENTERS:
        return make_indenter(str(name_or_path), seed=seed)
    if (diameter := ball_diameter(str(name_or_path))) is not None:
        return make_ball(diameter)
    return load_indenter(name_or_path, units=units)
