"""The optics and sensor stages of a diagnosis' models: the fast catalogue's image-level
effects (misalignment, lens distortion, vignetting, blur, the camera's response) applied
to images at a working resolution, and the cameras of that resolution. The fast model
(``studies.gap.model``) and the reference model (``studies.gap.reference_model``) both
end their predictions here.
"""

from __future__ import annotations

import numpy as np

from scenes.camera import Camera
from scenes.spec import SensorSpec

from . import effects as fx


def optics(images: np.ndarray, params: dict, camera: Camera, factor: int, fixed: np.ndarray,
           circle: np.ndarray) -> np.ndarray:
    """The image-level effects in ``params`` (misalignment, lens_distortion, vignetting,
    blur_noise, camera_response; full-resolution pixels) applied to (N, H, W, 3) images
    at ``camera``'s resolution, 1/``factor`` of the full one. ``fixed`` (H, W, 3) and
    ``circle`` (H, W): what stays put when the membrane moves under the lens
    (``effects.misalign_membrane``)."""
    f = camera.f
    centre = (camera.cy, camera.cx)
    out = images
    mis = params.get("misalignment")
    dist = params.get("lens_distortion")
    if mis is not None or dist is not None:
        if mis is not None:
            mis = {**mis, "du_px": mis["du_px"] / factor, "dv_px": mis["dv_px"] / factor}
        coords = fx.source_coordinates(camera.shape, f, centre, mis, dist)
        if mis is not None and mis.get("frame_share", 0.0) < 1.0:
            out = fx.misalign_membrane(out, coords, fixed, circle, mis.get("frame_share", 0.0))
        else:
            out = fx.resample(out, coords)
    if "vignetting" in params:
        p = params["vignetting"]
        c = (centre[0] + p["centre_dv_px"] / factor, centre[1] + p["centre_du_px"] / factor)
        depths = [p[f"depth_{k}"] for k in range(fx.VIGNETTE_KNOTS)]
        out = out * fx.vignette(camera.shape, f, c, depths, fx.vignette_length(camera.mask, f, factor))[None, ..., None]
    if "blur_noise" in params:
        out = fx.blur(out, params["blur_noise"]["sigma_px"] / factor)
    if "camera_response" in params:
        p = params["camera_response"]
        out = fx.camera_response(out, fx.colour_matrix(p), p["offset"], p["gamma"])
    return np.clip(out, fx.ZERO, fx.ONE)  # float32 bounds: numpy clips a float32 array 5x faster


def working_cameras(spec: SensorSpec, factor: int) -> tuple[Camera, Camera]:
    """(the spec's camera, the same at 1/``factor`` of its resolution), refusing a factor
    that does not divide the image."""
    full = Camera.from_spec(spec)
    if full.width % factor or full.height % factor:
        raise ValueError(f"{full.width}x{full.height} px is not divisible by factor {factor}")
    return full, (full if factor == 1 else full.scaled(full.width // factor, full.height // factor))
