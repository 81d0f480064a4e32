"""Studies built on the simulator: the sim-to-real gap's diagnosis (``gap``), comparisons with
real captures and peers (``compare``), Sim2Real learning (``sim2real``), design sweeps
(``design``), the published figures reproduced, and the benchmarks of real presses.

The public modules are listed in ``__all__``; import each by its name (``from studies import
x`` or ``studies.x``). Nothing is imported here, so importing one module loads no other.
"""

__all__ = [
    "compare", "dent_profile", "design", "field_agreement", "gap", "layout_figure", "light_paths",
    "markers", "path_classes", "pbr_field_comparison", "real_background_gap",
    "reproduce_published", "reweight", "sim2real", "tiles",
]
