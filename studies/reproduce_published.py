"""Reproduce the authors' published GelTip renders with our fast path.

The authors rendered the six depth maps ``sim_depth/0..5.npy`` with each of their four
baked light fields (``reference_renders/<method>.png``, six 640x480 panels each). This
study renders the same depth maps with OUR ``phong_reference.render.Renderer``, fed with

* their fields, prepared as their code prepared them (``NOTES.md``): Gaussian blur 25x25
  (sigma 4.1 px) at 160x120, bilinear resize to 640x480, no renormalisation, and
  rectification (projection onto the tangent plane of the undeformed surface and
  renormalisation) for plane, geodesic and transport but not linear;
* our own fields, as our renderer uses them (baked at 640x480 on our generated mesh);
* our own fields baked at 160x120 and prepared exactly as theirs, which separates the
  fields' directions from the published preparation.

Every other setting is the published one (``NOTES.md``) or an evidence-based finding that
the study itself measures and prints (``evidence``):

* rectification uses the Sobel normals of ``bkg.npy`` (our ``normals`` of the
  back-projected D_ref), which reproduces the reference to one 8-bit step;
* the background is the BT.601 luma of ``real/bkg.png``, rounded to 8 bits, divided by
  255 (not 225: the reference's untouched pixels are 0.500 x luma, not 0.567 x);
* the reference PNGs are NOT multiplied by the r = 240 px circle mask (the linear fields'
  blurred glow lights ~46k px outside it), so the comparison renders the whole frame;
* 8-bit conversion truncates (``astype(uint8)``), as the background's pixels show.

With these, their fields reproduce every published panel to one 8-bit step, except on the
frame's top and bottom rows: there OpenCV's Sobel (border BORDER_REFLECT_101) gives
dP/dv = 0, hence no normal and no LED light, while our ``normals`` replicates the edge and
lights them. That is a few hundred pixels, at most 2.5e-4 of MAE.

Run ``python -m studies.reproduce_published [--out DIR]``.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from PIL import Image
from scipy import ndimage
from skimage.metrics import peak_signal_noise_ratio
from skimage.transform import resize

from phong_reference.bake import METHODS, bake
from scenes.elastic import deform
from phong_reference.normals import normals
from phong_reference.render import Renderer, light_vectors, rectify_vectors, render
from scenes.camera import Camera, back_project
from scenes.geometry import membrane_mesh
from scenes.images import read_rgb, write_rgb
from scenes.reference_data import REFERENCE_ENV, require_reference_dir
from scenes.spec import Material, SensorSpec
from scenes.spec_read import default_spec

#: Resolution (H, W) of the authors' baked fields, px.
BAKED_SHAPE = (120, 160)
#: Number of 640x480 panels side by side in each reference PNG.
N_PANELS = 6

#: The published field blur: OpenCV's GaussianBlur with a 25x25 kernel and sigma 0, which
#: OpenCV turns into 0.3 ((25 - 1) / 2 - 1) + 0.8 = 4.1 px. Border: OpenCV's default
#: BORDER_REFLECT_101, scipy's 'mirror'.
FIELD_BLUR_SIGMA_PX = 4.1
FIELD_BLUR_RADIUS_PX = 12
FIELD_BLUR_MODE = "mirror"

#: Which fields were rectified (NOTES.md).
RECTIFIED = {"linear": False, "plane": True, "geodesic": True, "transport": True}

#: reference_renders settings (NOTES.md): pure blue on field 0, red on 1, green on 2.
FIELD_COLOURS = ((0.0, 0.0, 1.0), (1.0, 0.0, 0.0), (0.0, 1.0, 0.0))
K_D = 0.5  # i_d of every LED
K_S = 0.1  # i_s of every LED
AMBIENT = 0.5  # i_a
SHININESS = 100.0  # alpha
#: The paper dataset divided the real background by 225 (NOTES.md); the reference renders
#: evidently used 255 (see ``evidence``).
BACKGROUND_DIVISOR = 255.0

#: The issue's goal: MAE at most 1 % of full scale for every method.
MAE_GOAL = 0.01
#: One 8-bit step, as a fraction of full scale.
LSB = 1.0 / 255.0
#: Gain applied to |difference| images so that one-step errors are visible.
DIFF_GAIN = 10.0
#: Panel shown in the summary figure (a sphere pressed in, off-centre).
FIGURE_PANEL = 3
#: Pixels farther than this from any contact are "untouched" in the evidence fits, px.
UNTOUCHED_MARGIN_PX = 40


# --------------------------------------------------------------------------------------
# Loading the published data (read in place, never copied).


def load_published_fields(reference_dir: Path, method: str) -> np.ndarray:
    """The authors' baked fields of one method: (3, 120, 160, 3) float64 propagation
    directions (geodesic ones are not unit: one mesh edge long)."""
    if method not in METHODS:
        raise ValueError(f"method must be one of {METHODS}, got {method!r}")
    fields = np.stack(
        [np.load(Path(reference_dir) / "light_fields" / f"{method}_160x120_field_{i}.npy") for i in range(3)]
    )
    if fields.shape != (3,) + BAKED_SHAPE + (3,):
        raise ValueError(f"{method} fields must be (3, 120, 160, 3), got {fields.shape}")
    return fields


def load_depths(reference_dir: Path) -> tuple[np.ndarray, np.ndarray]:
    """D_ref (480, 640) and the six contact depth maps (6, 480, 640), float32 metres."""
    sim = Path(reference_dir) / "sim_depth"
    ref_depth = np.load(sim / "bkg.npy")
    depths = np.stack([np.load(sim / f"{k}.npy") for k in range(N_PANELS)])
    return ref_depth, depths


def read_panels(reference_dir: Path, name: str, shape: tuple[int, int]) -> np.ndarray:
    """The six panels of ``reference_renders/<name>.png``: (6, H, W, 3) float32 in [0, 1]."""
    h, w = shape
    strip = read_rgb(Path(reference_dir) / "reference_renders" / f"{name}.png", (h, N_PANELS * w))
    return np.stack([strip[:, k * w : (k + 1) * w] for k in range(N_PANELS)])


def grey_background(
    reference_dir: Path, shape: tuple[int, int], divisor: float = BACKGROUND_DIVISOR
) -> np.ndarray:
    """The reference renders' background: the real no-contact image in greyscale.

    PIL's "L" conversion is the ITU-R 601-2 luma (0.299 R + 0.587 G + 0.114 B) rounded
    to 8 bits, as OpenCV's RGB2GRAY. Returns (H, W, 3) float32; the real image is already
    circle-masked.
    """
    path = Path(reference_dir) / "real" / "bkg.png"
    with Image.open(path) as im:
        grey = np.asarray(im.convert("L"), dtype=np.float32)
    if grey.shape != tuple(shape):
        raise ValueError(f"{path} must be {shape[1]}x{shape[0]} px, got {grey.shape[1]}x{grey.shape[0]}")
    return np.repeat((grey / np.float32(divisor))[..., None], 3, axis=-1)


# --------------------------------------------------------------------------------------
# The published preparation of the fields and settings.


def blur_fields(fields: np.ndarray) -> np.ndarray:
    """The published blur of (M, h, w, 3) fields, per component (no renormalisation)."""
    sigma = (0.0, FIELD_BLUR_SIGMA_PX, FIELD_BLUR_SIGMA_PX, 0.0)
    return ndimage.gaussian_filter(
        fields, sigma, truncate=FIELD_BLUR_RADIUS_PX / FIELD_BLUR_SIGMA_PX, mode=FIELD_BLUR_MODE
    )


def prepare_fields(
    fields: np.ndarray,
    shape: tuple[int, int],
    rectify_normals: np.ndarray | None = None,
    *,
    blur: bool = True,
    renormalise: bool = False,
) -> np.ndarray:
    """Light vectors L_m from baked fields, as the published code loaded them.

    Parameters
    ----------
    fields : (M, h, w, 3) float, propagation directions (any length).
    shape : (H, W) of the render, px.
    rectify_normals : (3, H, W) unit normals to rectify onto (channel-first, as the fast
        path holds them), or None for no rectification.
    blur, renormalise : the published code blurred and did not renormalise (diagnostics).

    Returns
    -------
    (M, 3, H, W) float32 light vectors L_m = -field, channel-first as ``render`` takes them.
    """
    fields = np.asarray(fields, dtype=np.float64)
    if fields.ndim != 4 or fields.shape[-1] != 3:
        raise ValueError(f"fields must be (M, h, w, 3) float, got {fields.shape}")
    if rectify_normals is not None and rectify_normals.shape != (3,) + tuple(shape):
        raise ValueError(f"rectify_normals must be {(3,) + tuple(shape)}, got {rectify_normals.shape}")
    if blur:
        fields = blur_fields(fields)
    # skimage's bilinear resize maps pixel centres as OpenCV's INTER_LINEAR and clamps
    # at the edge as it does.
    fields = np.stack(
        [resize(f, tuple(shape), order=1, mode="edge", anti_aliasing=False, preserve_range=True) for f in fields]
    )
    L = -fields.transpose(0, 3, 1, 2)
    if renormalise:
        n = np.linalg.norm(L, axis=1, keepdims=True)
        L = np.divide(L, n, out=np.zeros_like(L), where=n > 0)
    if rectify_normals is not None:
        L = rectify_vectors(L, np.asarray(rectify_normals, dtype=np.float64))
    return np.ascontiguousarray(L, dtype=np.float32)


def sobel_normals(depth: np.ndarray, camera: Camera) -> np.ndarray:
    """Our fast path's Sobel normals of a depth map, (3, H, W) float64, channel-first."""
    N, _ = normals(back_project(np.asarray(depth, dtype=np.float64), camera, channels_first=True))
    return N


def published_spec(spec: SensorSpec, colours=FIELD_COLOURS) -> SensorSpec:
    """``spec`` with the reference renders' lights and material (LED m lit by field m)."""
    leds = tuple(
        dataclasses.replace(led, colour=colour, k_d=K_D, k_s=K_S) for led, colour in zip(spec.leds, colours)
    )
    return spec.replace(
        leds=leds, material=Material(ambient=AMBIENT, shininess=SHININESS, clamp_specular=False)
    )


def unmasked(camera: Camera) -> Camera:
    """``camera`` whose circle mask covers the whole frame (the reference PNGs are unmasked)."""
    return dataclasses.replace(camera, mask_radius_px=math.hypot(camera.width, camera.height))


def to_8bit(image: np.ndarray, how: str = "floor") -> np.ndarray:
    """Quantise [0, 1] floats as the published code saved them ("floor": astype(uint8))."""
    x = np.clip(image, 0.0, 1.0) * 255.0
    if how == "floor":
        return np.floor(x) / 255.0
    if how == "round":
        return np.rint(x) / 255.0
    if how == "none":
        return image
    raise ValueError(f"how must be 'floor', 'round' or 'none', got {how!r}")


# --------------------------------------------------------------------------------------
# Comparison.


def compare(expected: np.ndarray, actual: np.ndarray) -> dict[str, float]:
    """Errors of ``actual`` against ``expected``, both float in [0, 1], same shape (..., H, W, 3).

    mae and max_abs are fractions of full scale; mae_field holds the MAE of the channel
    each LED field lights (field m: ``FIELD_COLOURS[m]``); max_inner leaves out the frame's
    outermost row and column of pixels; psnr in dB (skimage.metrics; it has no MAE).
    """
    expected, actual = np.asarray(expected, np.float64), np.asarray(actual, np.float64)
    if expected.shape != actual.shape:
        raise ValueError(f"expected and actual must have the same shape, got {expected.shape} and {actual.shape}")
    err = np.abs(actual - expected)
    with np.errstate(divide="ignore"):
        psnr = peak_signal_noise_ratio(expected, actual, data_range=1.0)
    per_channel = err.reshape(-1, 3).mean(axis=0)
    return {
        "mae": float(err.mean()),
        "mae_field": [float(per_channel[int(np.argmax(c))]) for c in FIELD_COLOURS],
        "max_abs": float(err.max()),
        "max_inner": float(err[..., 1:-1, 1:-1, :].max()),
        "psnr_db": float(psnr),
    }


@dataclass(frozen=True)
class Settings:
    """How to prepare and render one method; the defaults are the published ones."""

    rectify: str = "published"  # "published" (RECTIFIED), "none" or "all"
    rectify_normals: str = "sobel"  # "sobel" of D_ref, "mesh" (our baked), "deformed" per panel
    blur: bool = True
    renormalise: bool = False
    background_divisor: float = BACKGROUND_DIVISOR
    colours: tuple = FIELD_COLOURS
    masked: bool = False
    quantise: str = "floor"


#: One deviation at a time from the chosen settings, to show each one is needed.
VARIANTS = {
    "chosen": Settings(),
    "masked r=240 (NOTES)": Settings(masked=True),
    "background /225": Settings(background_divisor=225.0),
    "R, B swapped (BGR)": Settings(colours=tuple(c[::-1] for c in FIELD_COLOURS)),
    "no blur": Settings(blur=False),
    "renormalised": Settings(renormalise=True),
    "no rectification": Settings(rectify="none"),
    "rectify all": Settings(rectify="all"),
    "rectify: our mesh N": Settings(rectify_normals="mesh"),
    "rectify: deformed N": Settings(rectify_normals="deformed"),
    "8-bit by rounding": Settings(quantise="round"),
    "no 8-bit step": Settings(quantise="none"),
}


@dataclass(frozen=True)
class Context:
    """Everything the renders share: spec, camera, D_ref, depths, normals, background."""

    reference_dir: Path
    spec: SensorSpec
    camera: Camera
    ref_depth: np.ndarray  # (H, W) float32, m, the authors' D_ref
    depths: np.ndarray  # (6, H, W) float32, m
    sobel_normals: np.ndarray  # (3, H, W), Sobel normals of D_ref
    mesh_normals: np.ndarray | None = None  # (3, H, W), our mesh's normals (diagnostics)

    @classmethod
    def load(cls, reference_dir: Path, spec: SensorSpec | None = None, mesh=None) -> "Context":
        """The shared inputs; with ``mesh``, also our baked normals of it."""
        spec = spec or default_spec()
        camera = Camera.from_spec(spec)
        ref_depth, depths = load_depths(reference_dir)
        mesh_normals = None
        if mesh is not None:  # the normals are the same for every method; linear bakes fastest
            baked = bake(mesh, camera, spec.leds, "linear")
            mesh_normals = np.asarray(baked.normals, np.float64).transpose(2, 0, 1)
        N = sobel_normals(ref_depth, camera)
        return cls(Path(reference_dir), spec, camera, ref_depth, depths, N, mesh_normals)


def _do_rectify(method: str, how: str) -> bool:
    return {
        "published": RECTIFIED[method],
        "none": False,
        "all": True,
    }[how]


def render_panels(
    ctx: Context, method: str, fields: np.ndarray, settings: Settings = Settings(), *, baked: bool = True
) -> np.ndarray:
    """Render the six depth maps with ``fields``: (6, H, W, 3) float in [0, 1], quantised.

    fields : (3, h, w, 3) baked fields prepared as published when ``baked``, or
        (3, 3, H, W) light vectors L_m (``light_vectors``) used as they are when not.
    """
    spec = published_spec(ctx.spec, settings.colours)
    camera = ctx.camera if settings.masked else unmasked(ctx.camera)
    background = grey_background(ctx.reference_dir, camera.shape, settings.background_divisor)
    rectify = baked and _do_rectify(method, settings.rectify)
    if rectify and settings.rectify_normals == "deformed":
        # The normals of each deformed surface: one L per panel, so no shared Renderer.
        L0 = prepare_fields(fields, camera.shape, None, blur=settings.blur, renormalise=settings.renormalise)
        out = []
        for depth in ctx.depths:
            N = sobel_normals(deform(depth, ctx.ref_depth, spec.elastic), camera)
            L = rectify_vectors(L0, N).astype(np.float32)
            out.append(render(depth, ctx.ref_depth, camera, spec, L, background))
        return to_8bit(np.stack(out), settings.quantise)
    if baked:
        N = {"sobel": ctx.sobel_normals, "mesh": ctx.mesh_normals}[settings.rectify_normals] if rectify else None
        if rectify and N is None:
            raise ValueError("rectify_normals='mesh' needs a Context loaded with our mesh")
        L = prepare_fields(fields, camera.shape, N, blur=settings.blur, renormalise=settings.renormalise)
    else:
        L = np.asarray(fields, dtype=np.float32)
    renderer = Renderer(spec, camera, ctx.ref_depth, L, background)
    return to_8bit(np.stack([renderer.render(d) for d in ctx.depths]), settings.quantise)


# --------------------------------------------------------------------------------------
# Evidence for the settings that NOTES.md does not fix.


def evidence(ctx: Context) -> dict[str, float]:
    """Measurements on the reference PNGs themselves that fix the open settings.

    * background: slope of the reference against the 8-bit luma of the real image on
      pixels far from every contact, in the plane render (whose rectified fields light
      the untouched membrane almost not at all); i_a / 255 = 0.5 / 255 per step, i_a / 225
      would be 0.567 / 255;
    * mask: reference pixels lit outside the r = 240 px circle (linear render);
    * edge rows: share of the frame's top and bottom rows that hold only the ambient term
      in the linear render (OpenCV's Sobel border leaves no normal there; see above).
    """
    camera = ctx.camera
    plane = read_panels(ctx.reference_dir, "plane", camera.shape)
    linear = read_panels(ctx.reference_dir, "linear", camera.shape)
    grey = grey_background(ctx.reference_dir, camera.shape, 255.0)[..., 0]
    untouched = ndimage.binary_erosion(
        (ctx.depths == ctx.ref_depth).all(axis=0), iterations=UNTOUCHED_MARGIN_PX
    ) & camera.mask
    slope, intercept = np.polyfit(grey[untouched], plane[0, ..., 1][untouched], 1)
    lit = (linear > 0).any(axis=(0, -1))
    ambient_only = to_8bit(AMBIENT * grey)  # what a pixel holds when no LED lights it

    def share_ambient_only(rows: list[int]) -> float:
        inside = camera.mask[rows]
        return float((linear[:, rows] == ambient_only[rows][None, ..., None])[:, inside].mean())

    h = camera.height
    return {
        "background_slope": float(slope),
        "background_intercept_8bit": float(intercept * 255),
        "lit_outside_circle_px": int((lit & ~camera.mask).sum()),
        "edge_rows_ambient_only": share_ambient_only([0, h - 1]),
        "next_rows_ambient_only": share_ambient_only([1, h - 2]),
    }


# --------------------------------------------------------------------------------------
# The study.


def run(reference_dir: Path, out: Path | None = None, diagnostics: bool = True) -> dict:
    spec = default_spec()
    mesh = membrane_mesh(spec)
    ctx = Context.load(reference_dir, spec, mesh)
    camera = ctx.camera
    small = camera.scaled(BAKED_SHAPE[1], BAKED_SHAPE[0])
    results: dict = {"evidence": evidence(ctx), "methods": {}, "variants": {}}
    images: dict = {}
    for method in METHODS:
        expected = read_panels(reference_dir, method, camera.shape)
        theirs = load_published_fields(reference_dir, method)
        ours = bake(mesh, camera, spec.leds, method)
        ours_small = bake(mesh, small, spec.leds, method)
        rendered = {
            "their fields": render_panels(ctx, method, theirs),
            "our fields": render_panels(ctx, method, light_vectors(ours), baked=False),
            "ours, published prep": render_panels(ctx, method, ours_small.fields),
        }
        results["methods"][method] = {
            name: {
                **compare(expected, img),
                "worst_panel_mae": max(compare(e, i)["mae"] for e, i in zip(expected, img)),
            }
            for name, img in rendered.items()
        }
        images[method] = (expected, rendered)
        if diagnostics:
            results["variants"][method] = {
                name: compare(expected, render_panels(ctx, method, theirs, settings))["mae"]
                for name, settings in VARIANTS.items()
                if not (method == "linear" and settings.rectify_normals != "sobel")
            }
    if out is not None:
        write_outputs(Path(out), images, results)
    return results


def print_report(results: dict) -> None:
    ev = results["evidence"]
    print("Evidence from the reference PNGs")
    print(f"  background: reference = {ev['background_slope']:.4f} x luma + {ev['background_intercept_8bit']:.2f}/255"
          f"   (i_a/255 -> 0.5000, i_a/225 -> {AMBIENT * 255 / 225:.4f})")
    print(f"  reference pixels lit outside the r=240 circle: {ev['lit_outside_circle_px']} (so not masked)")
    print(f"  top/bottom frame rows inside the circle holding only the ambient term: "
          f"{ev['edge_rows_ambient_only']:.0%} (next rows in: {ev['next_rows_ambient_only']:.0%})")
    print()
    head = (f"{'method':<10} {'fields':<22} {'MAE':>8} {'worst':>8} {'f0 (B)':>8} {'f1 (R)':>8} {'f2 (G)':>8} "
            f"{'max':>7} {'max in':>7} {'PSNR dB':>8}  goal")
    print(head)
    print("-" * len(head))
    for method, rows in results["methods"].items():
        for name, r in rows.items():
            ok = "<= 1%" if r["mae"] <= MAE_GOAL else "> 1%"
            fields = " ".join(f"{m:8.5f}" for m in r["mae_field"])
            print(f"{method:<10} {name:<22} {r['mae']:8.5f} {r['worst_panel_mae']:8.5f} {fields} {r['max_abs']:7.4f} "
                  f"{r['max_inner']:7.4f} {r['psnr_db']:8.2f}  {ok}")
    print("MAE, max: fractions of full scale over all six panels, full 640x480 frame; worst: worst "
          "panel's MAE;\nf0..f2: MAE of the channel each LED field lights; max in: without the frame's "
          f"outermost rows/columns;\none 8-bit step = {LSB:.4f}.")
    if results["variants"]:
        print()
        print("MAE with their fields when one setting deviates from the chosen ones")
        names = list(VARIANTS)
        print(f"{'variant':<24}" + "".join(f"{m:>11}" for m in results["variants"]))
        for name in names:
            cells = [results["variants"][m].get(name) for m in results["variants"]]
            print(f"{name:<24}" + "".join(f"{c:11.5f}" if c is not None else f"{'-':>11}" for c in cells))


def write_outputs(out: Path, images: dict, results: dict) -> None:
    """Expected, ours and |difference| x DIFF_GAIN strips per method, a figure and JSON."""
    out.mkdir(parents=True, exist_ok=True)
    strip = lambda panels: np.concatenate(list(panels), axis=1)  # noqa: E731
    for method, (expected, rendered) in images.items():
        write_rgb(out / f"{method}_expected.png", strip(expected))
        for name, img in rendered.items():
            tag = name.replace(",", "").replace(" ", "_")
            write_rgb(out / f"{method}_{tag}.png", strip(img))
            write_rgb(out / f"{method}_{tag}_diff_x{DIFF_GAIN:g}.png", strip(np.abs(img - expected) * DIFF_GAIN))
    (out / "reproduce_published.json").write_text(json.dumps(results, indent=2))
    figure(out / "reproduce_published.png", images, results)


def figure(path: Path, images: dict, results: dict) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    columns = ["expected", "their fields", "our fields", "ours, published prep"]
    n_cols = 2 * len(columns) - 1
    fig, axes = plt.subplots(len(images), n_cols, figsize=(3.0 * n_cols, 2.5 * len(images)))
    k = FIGURE_PANEL
    for row, (method, (expected, rendered)) in enumerate(images.items()):
        axes[row, 0].imshow(expected[k])
        axes[row, 0].set_title(f"{method}: published")
        for j, name in enumerate(columns[1:]):
            img = rendered[name]
            mae = results["methods"][method][name]["mae"]
            axes[row, 1 + 2 * j].imshow(img[k])
            axes[row, 1 + 2 * j].set_title(f"ours with {name}")
            axes[row, 2 + 2 * j].imshow(np.clip(np.abs(img[k] - expected[k]) * DIFF_GAIN, 0, 1))
            axes[row, 2 + 2 * j].set_title(f"|diff| x{DIFF_GAIN:g}; MAE (6 panels) {mae:.4f}")
    for ax in axes.ravel():
        ax.set_axis_off()
    fig.tight_layout()
    fig.savefig(path, dpi=80)
    plt.close(fig)
    return path


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--reference", type=Path,
                        help=f"the authors' data (default ${REFERENCE_ENV} or ../shared/data/geltip_reference)")
    parser.add_argument("--out", type=Path, help="write expected / ours / difference images, a figure and JSON here")
    parser.add_argument("--no-diagnostics", action="store_true", help="skip the one-setting-at-a-time variants")
    args = parser.parse_args(argv)
    try:
        args.reference = require_reference_dir(args.reference)
    except FileNotFoundError as exc:
        parser.error(f"{exc}; or pass --reference")
    results = run(args.reference, args.out, diagnostics=not args.no_diagnostics)
    print_report(results)
    return results


if __name__ == "__main__":
    main()
