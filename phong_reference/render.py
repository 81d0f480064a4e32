"""The fast path, depth map to tactile image, as one chain:

    image = shade(normals(back_project(deform(depth, ref), camera)), L, material, background)

1. ``deform``: elastic smoothing D_def = min(D, D_ref - G * (D_ref - D)) (the published
   model), or, given a ``scenes.elastic.MembraneLayer``, the depth map of the membrane
   deformed as an elastic layer: the surface the physically based reference renders;
2. ``back_project``: the point cloud P of D_def (planar z-depth, pinhole camera);
3. ``normals``: N from Sobel derivatives of P, facing the camera;
4. ``shade``: Phong per LED with the baked light field, L_m = -field;
5. background: k_a i_a B, then the sensor's circle mask and clipping to [0, 1].

``render`` is that chain on the whole frame. ``Renderer`` gives the same image faster: a
contact changes D_def only within the Gaussian's reach of where D differs from D_ref, so
it keeps the no-contact image and re-renders only that window.

Inside the chain, vector images (points, normals, light vectors) are channel-first,
(3, H, W), so that each component is a contiguous plane; images in and out are (H, W, 3).
"""

from __future__ import annotations

import numpy as np

from scenes.camera import Camera, back_project, check_depth
from scenes.elastic import MembraneLayer, deform, smooth
from scenes.spec import SensorSpec

from .background import check_background
from .bake import LightFields
from .normals import normals
from .phong import shade
from .tangent import tangent_unit


def light_vectors(fields: LightFields, rectify: bool = False) -> np.ndarray:
    """L_m = -field for each LED, channel-first: (M, 3, H, W) float32.

    rectify : project onto the tangent plane of the undeformed surface and renormalise
        (the published code did this for the plane, geodesic and transport fields; our
        baked surface fields are tangent already, so it matters for linear only).
    """
    L = -np.asarray(fields.fields, dtype=np.float32).transpose(0, 3, 1, 2)
    if rectify:
        L = rectify_vectors(L, np.asarray(fields.normals, dtype=np.float32).transpose(2, 0, 1))
    return np.ascontiguousarray(L)


def rectify_vectors(L: np.ndarray, N: np.ndarray) -> np.ndarray:
    """Project (M, 3, H, W) vectors onto the planes normal to N (3, H, W); renormalise."""
    return tangent_unit(L, N[None], axis=1)[0]


def finish(image: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """(3, H, W) -> (H, W, 3): clip to [0, 1] and apply the sensor's circle mask."""
    out = np.clip(image, 0.0, 1.0)
    out *= mask
    return np.ascontiguousarray(out.transpose(1, 2, 0))


def render(
    depth: np.ndarray,
    ref_depth: np.ndarray,
    camera: Camera,
    spec: SensorSpec,
    L: np.ndarray,
    background: np.ndarray,
    layer: MembraneLayer | None = None,
) -> np.ndarray:
    """Render one tactile image on the whole frame.

    Parameters
    ----------
    depth : (H, W) float, metres, planar z-depth of the contact.
    ref_depth : (H, W) float, metres, the no-contact depth D_ref.
    L : (M, 3, H, W) float32, light vectors per LED (see ``light_vectors``).
    background : (H, W, 3) float32, linear RGB in [0, 1].
    layer : the membrane's elastic layer model (scenes.elastic); None: the published
        smoothing.

    Returns
    -------
    (H, W, 3) float32, linear RGB in [0, 1].
    """
    depth = check_depth(depth, camera).astype(np.float32, copy=False)
    ref_depth = check_depth(ref_depth, camera, "ref_depth").astype(np.float32, copy=False)
    _check_lights(L, camera, spec)
    B = check_background(background, camera).transpose(2, 0, 1)
    if layer is None:
        d_def = deform(depth, ref_depth, spec.elastic)
    else:
        d_def = layer.depth(depth, ref_depth).astype(np.float32)
    P = back_project(d_def, camera, channels_first=True)
    N, _ = normals(P)
    return finish(shade(P, N, L, spec.leds, spec.material, B), camera.mask)


def _check_lights(L: np.ndarray, camera: Camera, spec: SensorSpec) -> None:
    expected = (len(spec.leds), 3) + camera.shape
    if not isinstance(L, np.ndarray) or L.shape != expected or L.dtype != np.float32:
        got = getattr(L, "shape", type(L).__name__), getattr(L, "dtype", "")
        raise ValueError(f"L must be {expected} float32 light vectors, got {got[0]} {got[1]}")


def _changed_box(delta: np.ndarray) -> tuple[int, int, int, int] | None:
    """(r0, r1, c0, c1) bounding the non-zero pixels of an (H, W) map; None if none."""
    rows = np.flatnonzero(delta.any(axis=1))
    if rows.size == 0:
        return None
    cols = np.flatnonzero(delta[rows[0] : rows[-1] + 1].any(axis=0))
    return int(rows[0]), int(rows[-1]) + 1, int(cols[0]), int(cols[-1]) + 1


def _grow(box: tuple[int, int, int, int], margin: int, shape: tuple[int, int]) -> tuple[int, int, int, int]:
    r0, r1, c0, c1 = box
    return max(r0 - margin, 0), min(r1 + margin, shape[0]), max(c0 - margin, 0), min(c1 + margin, shape[1])


def _slices(box) -> tuple[slice, slice]:
    return slice(box[0], box[1]), slice(box[2], box[3])


def _inner(outer, inner_box) -> tuple[slice, slice]:
    """Slices of ``inner_box`` relative to ``outer``."""
    return slice(inner_box[0] - outer[0], inner_box[1] - outer[0]), slice(inner_box[2] - outer[2], inner_box[3] - outer[2])


class Renderer:
    """The fast path with the no-contact work done once.

    Gives the same image as ``render`` (up to float rounding), re-rendering only the
    window that a contact can change: the pixels where D != D_ref, grown by the Gaussian's
    radius (where D_def can change) and by one pixel (the Sobel stencil). With the layer
    model, the window is where the deformed surface's depth differs from D_ref.
    """

    def __init__(
        self,
        spec: SensorSpec,
        camera: Camera,
        ref_depth: np.ndarray,
        L: np.ndarray,
        background: np.ndarray,
        layer: MembraneLayer | None = None,
    ):
        self.spec = spec
        self.layer = layer
        self.camera = camera
        self.ref_depth = check_depth(ref_depth, camera, "ref_depth").astype(np.float32)
        _check_lights(L, camera, spec)
        self.L = L
        self.background = check_background(background, camera)
        self._B = np.ascontiguousarray(self.background.transpose(2, 0, 1))
        self.mask = camera.mask
        self.base = render(self.ref_depth, self.ref_depth, camera, spec, L, self.background, layer)

    @classmethod
    def from_fields(
        cls, spec: SensorSpec, camera: Camera, fields: LightFields, background: np.ndarray, rectify: bool = False
    ) -> "Renderer":
        return cls(spec, camera, fields.depth, light_vectors(fields, rectify), background)

    def deformed(self, depth: np.ndarray) -> np.ndarray:
        """(H, W) float32 metres: the deformed membrane's depth D_def under a contact depth
        map (the published smoothing's, or the layer's), on the whole frame."""
        depth = check_depth(depth, self.camera).astype(np.float32, copy=False)
        if self.layer is None:
            return deform(depth, self.ref_depth, self.spec.elastic).astype(np.float32, copy=False)
        return self.layer.depth(depth, self.ref_depth).astype(np.float32)

    def render(self, depth: np.ndarray) -> np.ndarray:
        """(H, W) float metres -> (H, W, 3) float32 linear RGB in [0, 1]."""
        depth = check_depth(depth, self.camera).astype(np.float32, copy=False)
        shape = self.camera.shape
        if self.layer is None:
            delta = self.ref_depth - depth
            box = _changed_box(delta)
            if box is None:
                return self.base.copy()
            r = self.spec.elastic.radius_px
            changed = _grow(box, r, shape)  # where D_def can differ from D_ref
            support = _grow(box, 2 * r, shape)  # input G needs there, exactly (see deform)
            shaded = _grow(changed, 1, shape)  # where the Sobel normals can change
            stencil = _grow(shaded, 1, shape)  # points the Sobel stencil reads

            # Elastic smoothing on the support window. Beyond `box` delta is 0, so the zero
            # padding implied at the window's inner edges is exact; at image edges the window
            # ends where the image does and the border mode is the same as on the full frame.
            spread = smooth(delta[_slices(support)], self.spec.elastic)
            d_def = self.ref_depth[_slices(stencil)].copy()
            window = _slices(changed)
            d_def[_inner(stencil, changed)] = np.minimum(
                depth[window], self.ref_depth[window] - spread[_inner(support, changed)]
            )
        else:
            full = self.layer.depth(depth, self.ref_depth).astype(np.float32)
            box = _changed_box(self.ref_depth - full)
            if box is None:
                return self.base.copy()
            shaded = _grow(box, 1, shape)
            stencil = _grow(shaded, 1, shape)
            d_def = full[_slices(stencil)]
        P = d_def * self.camera.rays_channels_first[(slice(None),) + _slices(stencil)]
        N, _ = normals(P)
        # The window's own edge rows hold Sobel values with a wrong border unless they are
        # the image's edge, where the full-frame rule applies; keep only `shaded`.
        inner = (slice(None),) + _inner(stencil, shaded)
        out = _slices(shaded)
        I = shade(P[inner], N[inner], self.L[(slice(None), slice(None)) + out], self.spec.leds,
                  self.spec.material, self._B[(slice(None),) + out])
        image = self.base.copy()
        image[out] = finish(I, self.mask[out])
        return image
