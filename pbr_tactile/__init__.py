"""The spectral reference: the sensor rendered physically by Mitsuba 3 (photons through the
elastomer, its paint and the glass), the reference's calibration to a real unit, and the
renderer plugin that makes datasets with it (``plugin``).

The public modules are listed in ``__all__``; import each by its name (``from pbr_tactile import
x`` or ``pbr_tactile.x``). Nothing is imported here, so importing one module loads no other.
"""

__all__ = [
    "basis", "bench", "calibrate", "calibrate_bench", "calibrate_capture", "calibrate_taps",
    "camera_pass", "contact", "density", "effects", "estimate", "fast_background", "fluence",
    "gpu_run", "gpu_wheels", "image_fit", "image_model", "layout_fit", "membrane", "nocontact", "paint", "photons",
    "plugin", "profiled", "protocol_check", "real_image", "render", "reweight", "scene", "sensor",
    "solid", "spectra", "streams", "transport", "variant",
]
