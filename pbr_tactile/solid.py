"""The elastomer solid: the three surfaces that together bound it (:class:`Elastomer`).

Built from a contact by ``pbr_tactile.membrane`` and written as scene meshes by
``pbr_tactile.scene.write_meshes``.
"""

from __future__ import annotations

from dataclasses import dataclass

import trimesh


@dataclass(frozen=True)
class Elastomer:
    """The elastomer as three surfaces that together bound a closed solid.

    outer : the painted outer surface, deformed; normals point out of the elastomer.
    inner : the interface with the glass core; normals point out of the elastomer (into
        the glass).
    base : the ring that closes the bottom; normals point down, out of the elastomer.
    thickness : the membrane's least thickness, metres (``scenes.body``).
    """

    outer: trimesh.Trimesh
    inner: trimesh.Trimesh
    base: trimesh.Trimesh
    thickness: float

    def solid(self) -> trimesh.Trimesh:
        """The three surfaces welded into one closed mesh."""
        mesh = trimesh.util.concatenate([self.outer, self.inner, self.base])
        mesh.merge_vertices(merge_tex=True, merge_norm=True)  # weld by position alone
        return mesh
