"""The published model: their baked fields and the paper dataset's settings, rendered as
published."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .disk import BACKGROUNDS

#: The paper dataset's settings (NOTES.md, "Paper dataset (Table 1)"): i_a, the divisor
#: of the real background image, and the solid background's colour.
PAPER_AMBIENT = 0.8
PAPER_BACKGROUND_DIVISOR = 225.0
PAPER_SOLID_COLOUR = (0.6, 0.5, 0.96)
#: Their membrane, in the camera frame, metres (MANIFEST.txt).
PAPER_MESH = Path("meshes") / "sensor" / "160x120_aligned_mesh.stl"


def paper_spec(spec, background: str):
    """``spec`` (the GelTip's: Table 1's LEDs) with the paper dataset's material for a
    background label: i_a = PAPER_AMBIENT (times 255 / PAPER_BACKGROUND_DIVISOR for
    ``realbg``, whose image is read as /255) and R.V not clamped."""
    from scenes.spec import Material

    if background not in BACKGROUNDS:
        raise ValueError(f"background must be one of {', '.join(BACKGROUNDS)}, got {background!r}")
    ambient = PAPER_AMBIENT * (255.0 / PAPER_BACKGROUND_DIVISOR if background == "realbg" else 1.0)
    return spec.replace(material=Material(ambient=ambient, shininess=spec.material.shininess, clamp_specular=False))


def paper_background(reference_dir: Path, background: str, camera) -> np.ndarray:
    """The background image B of a background label, (H, W, 3) float32 in [0, 1]."""
    from scenes.images import read_rgb

    if background == "nonebg":
        return np.zeros(camera.shape + (3,), np.float32)
    if background == "solidbg":
        return np.broadcast_to(np.asarray(PAPER_SOLID_COLOUR, np.float32), camera.shape + (3,)).copy()
    if background == "realbg":
        return read_rgb(Path(reference_dir) / "real" / "bkg.png", camera.shape)
    raise ValueError(f"background must be one of {', '.join(BACKGROUNDS)}, got {background!r}")


@dataclass
class PaperModel:
    """The published model's shared inputs: the spec, camera, their D_ref (H, W) m, their
    membrane mesh, the Sobel normals of D_ref (3, H, W) and the folder of their data."""

    reference_dir: Path
    spec: object
    camera: object
    ref_depth: np.ndarray
    mesh: object
    normals: np.ndarray
    _renderers: dict = field(default_factory=dict)

    @classmethod
    def load(cls, reference_dir: Path) -> "PaperModel":
        from scenes.camera import Camera
        from scenes.shapes.mesh import load_mesh
        from scenes.spec_read import default_spec
        from studies.reproduce_published import sobel_normals

        spec = default_spec()
        camera = Camera.from_spec(spec)
        ref_depth = np.load(Path(reference_dir) / "sim_depth" / "bkg.npy")
        mesh = load_mesh(Path(reference_dir) / PAPER_MESH, "m")
        return cls(Path(reference_dir), spec, camera, ref_depth, mesh, sobel_normals(ref_depth, camera))

    def renderer(self, method: str, background: str):
        """Their model with one field and background label (a ``phong_reference`` Renderer)."""
        key = (method, background)
        if key not in self._renderers:
            from phong_reference.render import Renderer
            from studies.reproduce_published import RECTIFIED, load_published_fields, prepare_fields

            L = prepare_fields(load_published_fields(self.reference_dir, method), self.camera.shape,
                               self.normals if RECTIFIED[method] else None)
            self._renderers[key] = Renderer(paper_spec(self.spec, background), self.camera, self.ref_depth, L,
                                            paper_background(self.reference_dir, background, self.camera))
        return self._renderers[key]


def published(image: np.ndarray) -> np.ndarray:
    """A render as the published code saved it (8-bit, truncated: ``to_8bit``)."""
    from studies.reproduce_published import to_8bit

    return to_8bit(image)
