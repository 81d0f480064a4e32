"""Sensors of any shape and what happens to them, with no renderer: the sensor spec and its
membrane shapes, the camera and the geometry, the MuJoCo tapping rig and its protocols,
datasets, captures and imports of real presses, replay, and the unit profiles.

Every other package depends on this one and it on none of them (``tests/test_imports.py``).
Its command line (``cli``, ``commands``, ``docs_help``) is imported by no module here.

The public modules are listed in ``__all__``; import each by its name (``from scenes import
x`` or ``scenes.x``). Nothing is imported here, so importing one module loads no other.
"""

__all__ = [
    "background_model", "body", "cache", "camera", "captures", "clearance", "contact", "curvature",
    "dataset", "elastic", "elastic_solid", "errors", "executors", "files", "generate", "geometry",
    "gl", "image_stats", "images", "imports", "indenters", "kinematics", "layout", "markers",
    "meridian", "press_sets", "profile", "protocol", "protocol_checks", "proximity", "reference_data",
    "renderers", "replay", "rig", "settings", "shapes", "spec", "spec_read", "taps",
]
