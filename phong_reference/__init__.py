"""The fast path: the paper's Phong model over baked light fields, about 2.5 ms a frame, and
the renderer plugin that makes datasets with it (``plugin``).

The public modules are listed in ``__all__``; import each by its name (``from phong_reference import
x`` or ``phong_reference.x``). Nothing is imported here, so importing one module loads no other.
"""

__all__ = [
    "background", "bake", "bench", "calibrate", "elastic_fit", "environment", "figures",
    "geodesic", "linear", "normals", "phong", "plane", "plugin", "profiled", "render", "sources",
    "tangent", "transport",
]
