"""Transport light field: each LED's emission direction parallel-transported over the membrane.

Light leaving LED m along the tangent ω_m is carried along the surface without turning
(zero covariant derivative). The vector heat method (Sharp, Soliman, Crane 2019, through
potpourri3d) transports ω_m from the LED's vertex to every vertex with one solve of a
connection Laplacian that is factorised once per mesh.
"""

from __future__ import annotations

import numpy as np
import potpourri3d
import trimesh

from scenes.camera import SurfaceSamples

from .sources import Sources, bake_per_source

#: Bump when the method changes, so cached fields are rebuilt.
VERSION = 1

#: The vector heat method returns vectors of (nearly) unit length. An interpolated
#: vector shorter than this means the vertex vectors of the sample's face disagree by
#: more than ~120 degrees (a singularity of the transported field): invalid, not guessed.
MIN_INTERPOLATED_NORM = 0.5


class TransportBaker:
    """Parallel transport of each LED's tangent emission direction (vector heat method).

    Parameters
    ----------
    mesh : trimesh.Trimesh, metres. The connection Laplacian is built and factorised
        here, once.
    """

    def __init__(self, mesh: trimesh.Trimesh):
        self.mesh = mesh
        V = np.ascontiguousarray(mesh.vertices, dtype=np.float64)
        F = np.ascontiguousarray(mesh.faces, dtype=np.int64)
        self._solver = potpourri3d.MeshVectorHeatSolver(V, F)
        # potpourri3d factorises on the first solve; do it here so bake() only substitutes.
        self._solver.transport_tangent_vector(int(F[0, 0]), [1.0, 0.0])
        # (N, 3) each: per-vertex tangent basis e_x, e_y and normal in which the solver
        # reads and writes 2D tangent vectors.
        self._basis_x, self._basis_y, _ = (np.asarray(b) for b in self._solver.get_tangent_frames())

    def transport(self, vertex: int, direction: np.ndarray) -> np.ndarray:
        """Transport a tangent vector from one vertex to every vertex.

        Parameters
        ----------
        vertex : index of the source vertex.
        direction : (3,) float, the vector at the source (its normal part is ignored).

        Returns
        -------
        (N, 3) float64, the transported unit tangent vector at each vertex, in 3D (the
        normal part of ``direction`` is dropped and the rest normalised), sign kept
        (the 2D coordinates are used as they come, never as magnitudes).
        """
        n = len(self.mesh.vertices)
        if not 0 <= int(vertex) < n:
            raise ValueError(f"vertex must be in [0, {n}), got {vertex}")
        direction = np.asarray(direction, dtype=np.float64)
        if direction.shape != (3,):
            raise ValueError(f"direction must be (3,), got {direction.shape}")
        v = int(vertex)
        xy = np.array([direction @ self._basis_x[v], direction @ self._basis_y[v]])  # ω_m in 2D
        if not np.linalg.norm(xy) > 0:
            raise ValueError(f"direction {direction} has no tangent part at vertex {v}")
        xy /= np.linalg.norm(xy)  # unit, so transported lengths near 1 mean agreement
        uv = np.asarray(self._solver.transport_tangent_vector(v, xy))  # (N, 2)
        return uv[:, :1] * self._basis_x + uv[:, 1:] * self._basis_y

    def bake(self, samples: SurfaceSamples, sources: Sources) -> tuple[np.ndarray, np.ndarray]:
        """Transported emission directions at the samples.

        Returns
        -------
        fields : (L, K, 3) float64, unit propagation directions, tangent to the surface
            at each sample's normal; zero where invalid.
        valid : (L, K) bool, False where the transported vectors of the sample's face
            cancel (norm below ``MIN_INTERPOLATED_NORM``).
        """
        def one(m: int) -> tuple[np.ndarray, np.ndarray]:
            X = self.transport(int(sources.vertices[m]), sources.directions[m])  # (N, 3) transported ω_m per vertex
            x = samples.interpolate(self.mesh, X)  # (K, 3)
            return x, np.isfinite(x).all(axis=1) & (np.linalg.norm(x, axis=1) >= MIN_INTERPOLATED_NORM)

        return bake_per_source(sources, len(self.mesh.vertices), samples.normals, one)


def bake_transport(mesh: trimesh.Trimesh, samples: SurfaceSamples, sources: Sources):
    return TransportBaker(mesh).bake(samples, sources)
