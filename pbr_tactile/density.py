"""The photon estimator's density estimate: irradiance at coating vertices from deposits.

Per LED m, the irradiance per unit emitted flux e_m at each coating vertex is the
deposited flux (``pbr_tactile.photons.deposits``) over the area within a kernel of stated
radius (``irradiance`` with ``density_kernel``: photon mapping's estimate, bias of order
radius^2, consistent as the radius goes to 0). The maps are indexed by the coating mesh's
vertices (``coating_vertices``, their areas ``coating_areas``).
"""

from __future__ import annotations

import hashlib

import numpy as np

from .transport import coating_buffers, shape_named


def coating_areas(scene) -> np.ndarray:
    """(V,) area attributed to each coating vertex, m^2 (a third of each adjacent face)."""
    import mitsuba as mi

    return coating_buffers(mi, scene).vertex_area


def coating_vertices(scene) -> np.ndarray:
    """(V, 3) positions of the coating mesh's vertices, metres."""
    return np.asarray(shape_named(scene, "coating").vertex_positions_buffer()).reshape(-1, 3)


def density_kernel(positions: np.ndarray, radius: float, like: tuple | None = None):
    """The (V, V) sparse Epanechnikov weights w_ij = 1 - (|x_i - x_j| / radius)^2 over a
    ball of the given radius (m); radius = 0 gives the identity.

    Vertices at the same position (a seam) weigh 1, like the diagonal. The last
    KERNEL_MEMO kernels are kept by the positions' bytes: every contact of a sensor
    asks again for the undeformed membrane's.

    like : (positions, kernel) of the same vertices before some of them moved (a contact's
        dent): only the moved vertices' rows and columns are computed again; the
        kernel is the one computed from scratch, entry for entry.
    """
    from scipy.sparse import csr_matrix, identity
    from scipy.spatial import cKDTree

    positions = np.ascontiguousarray(positions, dtype=np.float64)
    n = len(positions)
    if radius <= 0:
        return identity(n, format="csr")
    key = (hashlib.sha1(positions.tobytes()).hexdigest(), n, float(radius))
    if key in _KERNELS:
        _KERNELS[key] = _KERNELS.pop(key)  # the most recently used is kept longest
        return _KERNELS[key]

    def weights(i, j):
        return 1.0 - np.sum(np.square(positions[i] - positions[j]), axis=1) / radius**2

    if like is not None and len(like[0]) == n:
        old = like[1].tocoo()
        moved = np.any(positions != np.asarray(like[0], np.float64), axis=1)
        near = cKDTree(positions).query_ball_point(positions[moved], radius, return_sorted=False)
        rows = np.repeat(np.flatnonzero(moved), [len(k) for k in near])  # every pair with a moved vertex
        cols = np.concatenate(near).astype(np.int64) if len(near) else np.zeros(0, np.int64)
        w = weights(rows, cols)
        keep = ~moved[old.row] & ~moved[old.col]
        mirror = ~moved[cols]  # pairs of two moved vertices came from both their queries
        rows, cols, w = (np.concatenate([old.row[keep], rows, cols[mirror]]),
                         np.concatenate([old.col[keep], cols, rows[mirror]]),
                         np.concatenate([old.data[keep], w, w[mirror]]))
    else:
        pairs = cKDTree(positions).query_pairs(radius, output_type="ndarray")  # i < j
        w = weights(pairs[:, 0], pairs[:, 1])
        rows = np.concatenate([pairs[:, 0], pairs[:, 1], np.arange(n)])
        cols = np.concatenate([pairs[:, 1], pairs[:, 0], np.arange(n)])
        w = np.concatenate([w, w, np.ones(n)])
    kernel = csr_matrix((w, (rows, cols)), shape=(n, n))
    _KERNELS[key] = kernel
    while len(_KERNELS) > KERNEL_MEMO:
        _KERNELS.pop(next(iter(_KERNELS)))
    return kernel


#: Density kernels kept by ``density_kernel`` (each about 60 MB on the default GelTip mesh),
#: the most recently used.
KERNEL_MEMO = 2
_KERNELS: dict = {}


def irradiance(flux: np.ndarray, vertex_area: np.ndarray, kernel) -> np.ndarray:
    """Irradiance from deposited flux: E_i = sum_j w_ij Phi_j / sum_j w_ij A_j.

    That is the area-weighted mean irradiance over the kernel's ball around x_i: exact
    for irradiance linear over the ball, so its bias is of order radius^2 times the
    irradiance's curvature (photon mapping's density estimate, consistent as the radius
    goes to 0), while its variance falls as 1 / radius^2.

    flux : (S, V) deposited flux per vertex; vertex_area (V,) m^2; kernel from
    ``density_kernel``.
    """
    return (kernel @ flux.T).T / (kernel @ vertex_area)
