"""The elastomer's fluence from the photons' tracks: the camera's in-scattered light by lookup.

Light that the elastomer scatters towards the camera at a point x is, for its isotropic
phase, sigma_s / (4 pi) times the fluence phi(x) = integral of L(x, w) over all
directions. The photon pass (``pbr_tactile.photons.deposits``) already carries every path
by which light reaches the elastomer, including those the camera cannot find by path
tracing: an LED seen from a scattering point through the glass core is a small, bright
target behind a smooth interface, which camera rays hit rarely and then with a large
weight. Those rare samples were most of a contact's noise (measured on a GelTip top-row
tap: 1 % of the contact region's pixels held all of the per-pass error).

The fluence is estimated on a voxel grid by the track-length estimator: a photon of
weight w that crosses the elastomer along a segment of length l adds w l at one point
drawn uniformly on the segment, to the voxel that point falls in. Divided by the
elastomer's volume inside the voxel (``FluenceGrid.volume``), that is an unbiased estimate
of the fluence averaged over the voxel's elastomer; reading it at a point is biased by
the fluence's variation across one voxel, as the coating's density estimate is by its
kernel.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

#: The photon estimator's ways of finding the light the elastomer scatters towards the
#: camera (``render.reference``'s inscatter): split camera paths, or this module's lookup.
INSCATTER = ("split", "fluence")
#: Default edge of a fluence voxel, m: a fifth of the GelTip's 2.5 mm elastomer.
VOXEL_M = 0.5e-3
#: Voxels whose elastomer fills less than this fraction of them read the fluence of their
#: elastomer over at least this fraction's volume (a sliver's few tracks would otherwise be
#: divided by a near-zero volume).
MIN_FRACTION = 0.05
#: Points per voxel edge that measure the elastomer's volume in a voxel the surface cuts.
SUBSAMPLES = 4
#: Bump when ``fluence_grid`` measures differently: grids kept on disk then miss.
GRID_VERSION = 1


@dataclass(frozen=True)
class FluenceGrid:
    """A regular grid over the elastomer: ``origin`` (3,) m, the corner of voxel (0, 0, 0);
    ``voxel`` its edge, m; ``volume`` (nx, ny, nz) m^3 of elastomer inside each voxel."""

    origin: np.ndarray
    voxel: float
    volume: np.ndarray

    @property
    def shape(self) -> tuple[int, int, int]:
        return tuple(int(n) for n in self.volume.shape)

    @property
    def size(self) -> int:
        return int(self.volume.size)

    def index(self, mi, p):
        """Dr.Jit: the flat voxel index of points p (Point3f), clamped to the grid."""
        import drjit as dr

        nx, ny, nz = self.shape
        i = [dr.clip(mi.Int32(dr.floor((p[k] - float(self.origin[k])) / self.voxel)), 0, n - 1)
             for k, n in enumerate((nx, ny, nz))]
        return mi.UInt32((i[0] * ny + i[1]) * nz + i[2])

    def fluence(self, track: np.ndarray) -> np.ndarray:
        """(S, N) fluence per unit emitted flux, 1/m^2, from the tracks' (S, N) summed w l,
        m (``deposits(..., grid=)``); 0 in voxels with no elastomer."""
        track = np.asarray(track, np.float64)
        if track.ndim != 2 or track.shape[1] != self.size:
            raise ValueError(f"track must be (sources, {self.size}) for this grid's voxels, got {track.shape}")
        floor = MIN_FRACTION * self.voxel**3
        volume = self.volume.ravel()
        return np.where(volume > 0, track / np.maximum(volume, floor), 0.0)


def fluence_grid(solid, voxel: float = VOXEL_M, like: FluenceGrid | None = None,
                 within: np.ndarray | None = None, shrinks: bool = False) -> FluenceGrid:
    """The grid of a closed solid (``trimesh.Trimesh``, watertight: the elastomer's
    ``Elastomer.solid()``), its voxels' elastomer volume measured by point containment.

    A voxel whose 8 corners are all inside (outside) counts whole (empty); one the surface
    cuts is measured on SUBSAMPLES^3 points. like, within : a grid of the same solid
    before a local change, and where the change lies: (2, 3) bounds, or (K, 2, 3) boxes
    (each face that moved: the box of its corners before and after). Only the voxels a
    box meets, and their neighbours, are measured again (a contact's dent); the rest are
    ``like``'s, and each is measured as it would be in the whole grid. A point's
    containment changes only where a surface swept across it, inside a box, so a voxel
    whose own points and whose neighbours' corners all lie outside every box measures
    what it did. shrinks : the change only took material away (a dent pressed inwards),
    so ``like``'s empty voxels stay empty and are not measured again (every point inside
    the changed solid was inside the old one: the same points measure the same volumes).
    """
    if not (np.isfinite(voxel) and voxel > 0):
        raise ValueError(f"voxel must be a finite edge > 0 m, got {voxel!r}")
    if not solid.is_watertight:
        raise ValueError("the fluence grid needs a closed (watertight) solid")
    if like is None:
        # One empty voxel of margin all round: every voxel's neighbours are in the grid.
        origin = np.asarray(solid.bounds[0], np.float64) - voxel
        shape = tuple(np.ceil((solid.bounds[1] + voxel - origin) / voxel).astype(int))
        volume = np.zeros(shape)
        every = np.argwhere(np.ones(shape, bool))
        volume[tuple(every.T)] = _measure(solid, origin, float(voxel), shape, every)
        return FluenceGrid(origin, float(voxel), volume)
    if within is None:
        raise ValueError("like needs within, the bounds of the change")
    origin, voxel, volume = like.origin, like.voxel, like.volume.copy()
    boxes = np.asarray(within, np.float64)
    if boxes.shape == (2, 3):
        boxes = boxes[None]
    if boxes.ndim != 3 or boxes.shape[1:] != (2, 3):
        raise ValueError(f"within must be (2, 3) bounds or (K, 2, 3) boxes, m, got shape {boxes.shape}")
    met = _met(boxes, origin, voxel, volume.shape)
    if not met.any():
        return FluenceGrid(origin, voxel, volume)
    from scipy import ndimage

    again = np.argwhere(ndimage.binary_dilation(met))  # a neighbour's corners decide an empty voxel's cut
    only = like.volume[tuple(again.T)] > 0 if shrinks else None
    volume[tuple(again.T)] = _measure(solid, origin, voxel, volume.shape, again, only)
    return FluenceGrid(origin, voxel, volume)


def _met(boxes: np.ndarray, origin: np.ndarray, voxel: float, shape) -> np.ndarray:
    """Bool (shape): the voxels whose closed cell meets one of the (K, 2, 3) boxes."""
    n = np.asarray(shape)
    # A point on a face between two voxels belongs to both: widen by a hair.
    first = np.maximum(np.floor((boxes[:, 0] - origin) / voxel - 1e-6).astype(np.int64), 0)
    last = np.minimum(np.floor((boxes[:, 1] - origin) / voxel + 1e-6).astype(np.int64), n - 1)
    keep = np.all(last >= first, axis=1)
    first, last = first[keep], last[keep]
    met = np.zeros(shape, bool)
    if not len(first):
        return met
    span = last - first + 1
    # Boxes a few voxels across (faces): mark each offset at once; larger ones one by one.
    small = np.all(span <= 4, axis=1)
    for offset in np.argwhere(np.ones((4, 4, 4), bool)):
        inside = small & np.all(offset < span, axis=1)
        met[tuple((first[inside] + offset).T)] = True
    for a, b in zip(first[~small], last[~small]):
        met[a[0]:b[0] + 1, a[1]:b[1] + 1, a[2]:b[2] + 1] = True
    return met


def _measure(solid, origin: np.ndarray, voxel: float, shape, voxels: np.ndarray,
             only: np.ndarray | None = None) -> np.ndarray:
    """Elastomer volume, m^3, of the (M, 3) ``voxels`` (indices) of the grid of ``shape``
    at origin, each as in the whole grid; with ``only`` (M,) bool, the others are 0 and
    not measured."""
    n = np.asarray(shape)
    steps = np.array([[0, 0, 0], [1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]])
    # The voxels and their 6 neighbours (an empty voxel beside elastomer is measured too,
    # as ndimage.binary_dilation's cross finds it); none beyond the grid's edge.
    around = voxels[:, None, :] + steps[None]
    inner = np.all((around >= 0) & (around < n), axis=2)
    seen, where = np.unique(np.ravel_multi_index(tuple(around[inner].T), shape), return_inverse=True)
    cube = np.argwhere(np.ones((2, 2, 2), bool))
    corners = np.unravel_index(seen, shape)
    corners = np.stack(corners, -1)[:, None, :] + cube[None]
    lattice, which = np.unique(np.ravel_multi_index(tuple(corners.reshape(-1, 3).T), tuple(n + 1)),
                               return_inverse=True)
    points = origin + np.stack(np.unravel_index(lattice, tuple(n + 1)), -1) * voxel
    inside_seen = solid.contains(points)[which].reshape(-1, 8).sum(axis=1)
    count = np.zeros(inner.shape, np.int64)
    count[inner] = inside_seen[where]
    inside = count[:, 0]
    fraction = (inside == 8).astype(np.float64)
    # The surface can clip a voxel without enclosing any of its corners: measure the empty
    # voxels beside any elastomer too.
    cut = ((inside > 0) & (inside < 8)) | ((inside == 0) & np.any(count[:, 1:] > 0, axis=1))
    if only is not None:
        fraction *= only
        cut &= only
    cut = np.flatnonzero(cut)
    if len(cut):
        offsets = (np.stack(np.meshgrid(*[np.arange(SUBSAMPLES)] * 3, indexing="ij"), -1).reshape(-1, 3) + 0.5)
        points = origin + (voxels[cut][:, None, :] + offsets[None] / SUBSAMPLES) * voxel
        fraction[cut] = solid.contains(points.reshape(-1, 3)).reshape(len(cut), -1).mean(axis=1)
    return fraction * voxel**3
