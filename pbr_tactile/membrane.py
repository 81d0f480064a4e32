"""The deformed membrane rebuilt as a closed elastomer solid, from a contact depth map.

The outer surface is the membrane refined and deformed by the elastic layer model
(scenes.elastic.MembraneLayer: every vertex moves along its inward normal, conforming to
the indenter where it touches and never entering the glass core). The elastomer is the
closed solid between that surface and the glass core (the undeformed surface offset
inwards by the membrane's thickness), closed at the base by a ring.
"""

from __future__ import annotations

import dataclasses
import gc
from collections import OrderedDict

import numpy as np
import trimesh
from scipy import spatial

from scenes.camera import Camera
from scenes.elastic import LAYER_EDGE_M, MembraneLayer
from scenes.geometry import crossing_faces
from scenes.spec import SensorSpec

from .fluence import GRID_VERSION, SUBSAMPLES, VOXEL_M, FluenceGrid, fluence_grid
from .scene import write_meshes
from .solid import Elastomer

#: A face whose normal turns by more than this has folded over (turned its back on where
#: it faced), radians.
MAX_FACE_TURN_RAD = np.radians(90.0)
#: Dented solids an ElastomerBuilder keeps, the most recently used: the diagnosis renders
#: each tap again at every grid point of its re-rendered candidates, and deforming and
#: checking a contact (the crossing test) took 1.9 s of a 20 s render.
KEPT_SOLIDS = 48


class ElastomerBuilder:
    """The elastomer solids of one membrane: the undeformed solid is built and checked
    once, each contact only deforms the outer surface and checks what moved, and the
    last ``KEPT_SOLIDS`` contacts' solids are kept.

    Parameters
    ----------
    membrane : the undeformed outer membrane surface, open at its base, camera frame.
    edge : target edge of the refined outer surface, metres.
    elastic : None, the layer model's dent; or the ``bonded`` model's (``{"model": "bonded",
        "thickness_m", "poisson_ratio"}``, either None for the spec's), as the fast path's
        ``BondedLayer`` solves it (its bulge left out).
    """

    def __init__(self, membrane: trimesh.Trimesh, spec: SensorSpec, camera: Camera, edge: float = LAYER_EDGE_M,
                 elastic: dict | None = None):
        bonded = None
        if elastic is not None:  # the bonded layer's dent instead of the layer model's
            from scenes.elastic_solid import BondedLayer

            bonded = BondedLayer(spec, camera, elastic.get("thickness_m"), elastic.get("poisson_ratio"))
        self.layer = MembraneLayer(membrane, spec, camera, edge, bonded=bonded)
        thickness = self.layer.thickness  # under each vertex, from the sensor's body (scenes.body)
        outer = self.layer.mesh
        inner = trimesh.Trimesh(self.layer.vertices - thickness[:, None] * self.layer.normals, outer.faces,
                                process=False)
        inner.invert()  # normals into the glass: out of the elastomer
        self.undeformed = Elastomer(outer, inner, _base_ring(outer, inner), float(thickness.min()))
        check_closed(self.undeformed)
        # The welded solid's faces and where each surface's vertices sit among its
        # vertices: a contact moves only outer vertices, so its solid is the undeformed
        # one with those moved (``solid``), with no welding by position.
        welded = self.undeformed.solid()
        self._faces = np.asarray(welded.faces)
        self._vertices = np.asarray(welded.vertices)
        tree = spatial.cKDTree(self._vertices)
        self._outer_at = tree.query(np.asarray(outer.vertices))[1]
        rest = np.concatenate([np.asarray(inner.vertices), np.asarray(self.undeformed.base.vertices)])
        shared = np.bincount(np.concatenate([self._outer_at, tree.query(rest)[1]]), minlength=len(self._vertices))
        self._welded_to_others = shared[self._outer_at] > 1  # outer vertices the base ring shares
        self._last_solid: tuple = (None, None)
        self._solids: OrderedDict = OrderedDict()  # the last KEPT_SOLIDS dented solids, by contact
        self._grids: OrderedDict = OrderedDict()  # fluence grids, undeformed and dented, by contact and voxel
        self._written: dict = {}  # the undeformed solid's scene meshes, by glass wall

    def __call__(self, depth: np.ndarray | None = None, ref_depth: np.ndarray | None = None) -> Elastomer:
        """The solid dented by a contact depth map D (H, W) metres, with D_ref; None: no contact.

        Raises ValueError when the contact reaches through the glass core, or when the
        deformed surface folds over or crosses itself (checked, not expected). The solid
        has the undeformed one's faces, so it is as closed as that one.
        """
        if depth is None:
            return self.undeformed
        if ref_depth is None:
            raise ValueError("ref_depth is required with a depth map")
        from scenes.cache import make_key

        return _kept(self._solids, make_key(np.asarray(depth), np.asarray(ref_depth)),
                     lambda: self._deformed(depth, ref_depth), KEPT_SOLIDS)

    def solid(self, elastomer: Elastomer) -> trimesh.Trimesh:
        """``elastomer.solid()`` of this builder's undeformed solid or a contact's: the
        undeformed welded solid with the outer vertices moved (the same faces, in the same
        order), or, when a vertex the outer surface shares with the base ring moved, welded
        anew. The last one is kept: the crossing test and the fluence grid read it."""
        if self._last_solid[0] is elastomer:
            return self._last_solid[1]
        outer = np.asarray(elastomer.outer.vertices)
        ours = elastomer.inner is self.undeformed.inner and elastomer.base is self.undeformed.base
        if not ours or len(outer) != len(self._outer_at) or np.any(
                outer[self._welded_to_others] != self.layer.vertices[self._welded_to_others]):
            mesh = elastomer.solid()
        else:
            vertices = self._vertices.copy()
            vertices[self._outer_at] = outer
            mesh = trimesh.Trimesh(vertices, self._faces, process=False)
        self._last_solid = (elastomer, mesh)
        return mesh

    def meshes(self, glass_wall: float) -> dict[str, str]:
        """The undeformed solid's scene meshes (``pbr_tactile.scene.write_meshes``),
        written once into a folder this builder owns and removes when it is collected:
        every contact's render reads them (its pilot, and its light with the contact's
        shadow off), and ``render.load(keep=True)`` keeps them loaded."""
        if glass_wall not in self._written:
            import shutil
            import tempfile
            import weakref

            folder = tempfile.mkdtemp(prefix="tactile-undeformed-")  # one per wall: a load keys on the paths
            weakref.finalize(self, shutil.rmtree, folder, True)
            self._written[glass_wall] = write_meshes(self.undeformed, folder, glass_wall)
        return self._written[glass_wall]

    def grid(self, depth: np.ndarray | None = None, ref_depth: np.ndarray | None = None, voxel: float = VOXEL_M):
        """The ``pbr_tactile.fluence.FluenceGrid`` of the solid of a contact (None: the
        undeformed solid), voxel edge in metres.

        The undeformed grid (12.8 s at 0.5 mm on the GelTip) is measured once and kept on
        disk (``scenes.cache``, keyed by the solid's mesh). A contact's is that grid
        measured again only over the faces its dent moved, before and after they moved,
        and only where there was elastomer (a dent moves the surface inwards, so it only
        takes elastomer away): the grids of all contacts share one origin and shape, so
        their tracks add voxel by voxel.
        """
        from scenes.cache import cached, make_key

        def undeformed():
            mesh = self.undeformed.solid()
            key = make_key(GRID_VERSION, SUBSAMPLES, float(voxel), np.asarray(mesh.vertices), np.asarray(mesh.faces))
            arrays = cached("fluence-grid", key, lambda: _grid_arrays(fluence_grid(mesh, voxel)))
            return FluenceGrid(arrays["origin"], float(arrays["voxel"]), arrays["volume"])

        flat = _kept(self._grids, make_key("undeformed", float(voxel)), undeformed, KEPT_SOLIDS)
        if depth is None:
            return flat
        solid = self(depth, ref_depth)
        new, old = np.asarray(solid.outer.vertices), self.layer.vertices
        faces = np.asarray(solid.outer.faces)
        changed = faces[np.any(new != old, axis=1)[faces].any(axis=1)]
        if not len(changed):
            return flat
        # Each moved face's box, before and after: a point changes sides only where a face
        # swept across it (a dent's faraway vertices move by micrometres, so the boxes
        # cover far less than their bounds).
        corners = np.concatenate([new[changed], old[changed]], axis=1)
        within = np.stack([corners.min(axis=1), corners.max(axis=1)], axis=1)
        return _kept(self._grids, make_key(np.asarray(depth), np.asarray(ref_depth), float(voxel)),
                     lambda: fluence_grid(self.solid(solid), like=flat, within=within, shrinks=True), KEPT_SOLIDS)

    def _deformed(self, depth: np.ndarray, ref_depth: np.ndarray) -> Elastomer:
        try:
            outer = self.layer.surface(depth, ref_depth)
            check_folds(outer, self.undeformed.outer)
            result = Elastomer(outer, self.undeformed.inner, self.undeformed.base, self.undeformed.thickness)
            moved = np.any(np.asarray(outer.vertices) != self.layer.vertices, axis=1)
            check_crossings(result, changed=np.flatnonzero(moved[outer.faces].any(axis=1)),
                            solid_mesh=self.solid(result))
        finally:
            # A trimesh mesh refers to itself (its cache keys on a bound method), so the
            # welded solid of the crossing test and the solids _kept drops, tens of MB each,
            # are freed only by a full collection, which the interpreter seldom runs:
            # `bench solids` grew by about 60 MB a tap and was killed at 14 GB.
            gc.collect()
        return result


def _grid_arrays(grid: FluenceGrid) -> dict[str, np.ndarray]:
    return {"origin": grid.origin, "voxel": np.float64(grid.voxel), "volume": grid.volume}


#: Builders ``shared_builder`` keeps, the most recently used.
KEPT_BUILDERS = 4
_builders: OrderedDict = OrderedDict()


def shared_builder(membrane: trimesh.Trimesh, spec: SensorSpec, camera: Camera,
                   edge: float = LAYER_EDGE_M, elastic: dict | None = None) -> ElastomerBuilder:
    """The ElastomerBuilder of this membrane, kept across calls: building one refines and
    checks the membrane and ray-casts the glass core's depth map (about 1.6 s of an
    80x60 render's 5.7 s here). Keyed by the mesh, the camera, the refinement and the
    spec's membrane and elastic layer, which are all a builder reads (so a spec whose
    LEDs alone differ shares one)."""
    from scenes.cache import make_key

    key = make_key(np.asarray(membrane.vertices), np.asarray(membrane.faces), dataclasses.asdict(spec.membrane),
                   dataclasses.asdict(spec.elastic), dataclasses.asdict(camera), edge, elastic)
    return _kept(_builders, key, lambda: ElastomerBuilder(membrane, spec, camera, edge, elastic), KEPT_BUILDERS)


def _kept(store: OrderedDict, key: str, build, size: int):
    """``store[key]``, built by ``build()`` when missing; ``store`` keeps the ``size``
    most recently used."""
    value = store.pop(key) if key in store else build()
    store[key] = value
    while len(store) > size:
        store.popitem(last=False)
    return value


def elastomer(
    membrane: trimesh.Trimesh,
    spec: SensorSpec,
    camera: Camera,
    depth: np.ndarray | None = None,
    ref_depth: np.ndarray | None = None,
    edge: float = LAYER_EDGE_M,
) -> Elastomer:
    """One-off: the elastomer solid of a membrane, dented by a contact depth map D (H, W)
    metres with D_ref, or undeformed (None); see ElastomerBuilder."""
    return ElastomerBuilder(membrane, spec, camera, edge)(depth, ref_depth)


def check_folds(deformed: trimesh.Trimesh, undeformed: trimesh.Trimesh) -> None:
    """Refuse a deformed surface with a face turned by more than MAX_FACE_TURN_RAD."""
    turn = np.einsum("ij,ij->i", deformed.face_normals, undeformed.face_normals)
    folded = turn < np.cos(MAX_FACE_TURN_RAD) - 1e-12
    if folded.any():
        raise ValueError(
            f"the deformed membrane folds over itself at {int(folded.sum())} faces (a face normal turns by more "
            f"than {np.degrees(MAX_FACE_TURN_RAD):.0f} deg)"
        )


def _base_ring(outer: trimesh.Trimesh, inner: trimesh.Trimesh) -> trimesh.Trimesh:
    """Quads joining the open boundary loop of the outer surface to the inner one's."""
    loops = outer.outline().entities
    if len(loops) != 1:
        raise ValueError(f"the membrane must have exactly one open boundary (its base), got {len(loops)}")
    loop = np.asarray(loops[0].points)
    if loop[0] == loop[-1]:
        loop = loop[:-1]
    n = len(loop)
    V = np.vstack([outer.vertices[loop], inner.vertices[loop]])
    a, b = np.arange(n), (np.arange(n) + 1) % n
    faces = np.vstack([np.c_[a, b, n + b], np.c_[a, n + b, n + a]])
    ring = trimesh.Trimesh(V, faces, process=False)
    # Orient the ring to face away from the solid, towards the membrane's open side.
    outward = outer.vertices[loop].mean(axis=0) - outer.vertices.mean(axis=0)
    if np.dot(ring.face_normals.mean(axis=0), outward) < 0:
        ring.invert()
    return ring


def check_closed(solid: Elastomer) -> None:
    """The three surfaces must weld into a watertight, consistently wound solid of
    positive volume."""
    mesh = solid.solid()
    if not mesh.is_watertight:
        raise ValueError("the elastomer is not watertight (the membrane's base loop did not close)")
    if not mesh.is_winding_consistent:
        raise ValueError("the elastomer's surfaces are not consistently wound")
    if mesh.volume <= 0:
        raise ValueError("the elastomer's normals point inwards (negative volume)")


def check_crossings(solid: Elastomer, changed: np.ndarray | None = None, solid_mesh=None) -> None:
    """The solid must not intersect itself.

    changed : (K,) int, indices of the outer faces that moved (the solid lists the outer
        faces first); only pairs with one of them are tested. None tests every pair,
        which takes seconds on a finely refined membrane.
    solid_mesh : ``solid.solid()``, when already welded (``ElastomerBuilder.solid``).
    """
    crossed = crossing_faces(solid.solid() if solid_mesh is None else solid_mesh, changed)
    if len(crossed):
        raise ValueError(
            f"the elastomer intersects itself at {len(crossed)} faces: the deformed membrane passes through "
            "itself or through the glass core"
        )
