"""Taxim, the example-based peer simulator, on a capture's presses.

Taxim (Si and Yuan, RA-L 2022; Robo-Touch/Taxim) renders a tactile image from a height
map by looking up, per pixel, a colour change in a table indexed by the surface normal's
slope θ and direction φ, each bin holding a quadratic in the pixel's position, and adding
the processed no-contact frame. The table is fitted from real presses of a ball of known
size. We render with the pip port ``taxim`` (Tim Schneider's JAX/PyTorch port, MIT;
extra ``peers``) and fit its table from a capture's own presses:

- ``studies.compare.taxim_table.fit_polytable`` fits the table (Taxim's
  ``Calibration/polyTableCalib.py``, on every pixel of every press; its deviations from
  Taxim are said there);
- :func:`write_calibration` writes a folder the port reads; :func:`shipped_folder` is the
  port's own (fitted on 48 presses of another session of the same sensor design).
- :class:`TaximPeer` renders height maps or ball presses with a calibration folder and,
  optionally, the capture's own no-contact frame as background; :func:`render_presses` is
  the one-off form.

Images are RGB floats in [0, 1], as the project reads 8-bit frames (value / 255, no
transfer curve: Taxim works on the camera's 8-bit values). The port's files are 8-bit BGR
and 0-255 units, with ``grad_r`` and ``grad_b`` swapped (Taxim fitted ``grad_r`` to stored
channel 0, blue; the port renders ``grad_b`` as red): :func:`write_calibration` writes
them so that the port renders the right colours.
"""

from __future__ import annotations

import json
import math
import shutil
import tempfile
from pathlib import Path

import numpy as np
from scipy import ndimage

from .taxim_table import (BACKGROUND_MIXING, BACKGROUND_SIGMA_PX, blurred, checked_centres, checked_image, checked_point,
                          checked_positive, checked_shape, checked_size, fit_polytable)

#: The port's simulator parameters (taxim 1.4.1, ``calib/gelsight/params.json``): every
#: ``*_rel`` value is a share of the rendered image's (width, height), so they hold at any
#: size; :func:`write_calibration` replaces ``initial_frame_sigma_rel`` by the fit's.
SIMULATOR_PARAMS = {
    "initial_frame_sigma_rel": [0.078125, 0.10416666666666667],
    "diff_threshold": 5,
    "frame_mixing_percentage": BACKGROUND_MIXING,
    "shadow_step_rel": [0.001953125, 0.0026041666666666665],
    "discretize_precision": 0.1,
    "height_precision": 0.1,
    "fan_angle": 0.1,
    "fan_precision": 0.05,
    "contact_scale": 0.4,
    "deform_pyramid_sigma_rel": [
        [0.04765625, 0.02421875, 0.012499999999999999, 0.00546875, 0.003125, 0.0017187500000000002],
        [0.06354166666666666, 0.03229166666666667, 0.016666666666666666, 0.007291666666666667,
         0.004166666666666667, 0.0022916666666666667]],
    "deform_final_sigma_rel": [0.003125, 0.004166666666666667],
    "shadow_blur_sigma_rel": [0.0017187500000000002, 0.0022916666666666667],
    "shadow_attachment_kernel_size_rel": [0.0078125, 0.010416667],
}
#: The shadow table's ray directions, radians (Taxim's ``generateShadowMasks``: 0 to 6.2).
SHADOW_DIRECTIONS = np.round(np.arange(63) * 0.1, 10)
INSTALL_HINT = "pip install 'tactile-sim[peers]' (the taxim package and a JAX backend: pip install taxim==1.4.1 jax)"


# ----------------------------------------------------------------------------- the port's files

def _to_bgr8(image: np.ndarray) -> np.ndarray:
    """RGB [0, 1] float to the port's 8-bit BGR (cv2.imread order)."""
    return np.round(np.clip(image, 0, 1) * 255).astype(np.uint8)[..., ::-1].copy()


def _neutral_shadow_table() -> np.ndarray:
    """(3, 63, 1) object: one ray step of +inf per channel and direction. The port loads a
    shadow table whatever it renders; this one never darkens (it takes a minimum)."""
    table = np.empty((3, len(SHADOW_DIRECTIONS), 1), dtype=object)
    for index in np.ndindex(table.shape):
        table[index] = [math.inf]
    return table


def write_calibration(folder, table: dict, no_contact: np.ndarray, gel_map_px: np.ndarray, pixel_m: float,
                      width: int, height: int, shadow_from=None) -> Path:
    """Write a calibration folder the port reads (``taxim.Taxim(calib_folder=...)``).

    Parameters
    ----------
    folder : where to write (created; existing calibration files are replaced).
    table : :func:`fit_polytable`'s result.
    no_contact : (height, width, 3) float, RGB in [0, 1], the frame without contact; the
        port blurs and mixes it into its background (:func:`background`).
    gel_map_px : (Hg, Wg) float, the undeformed gel's height in pixels of size ``pixel_m``,
        larger toward the object (Taxim's ``gelmap``; any resolution, the port resizes it).
        For the Taxim set at 160x120: its 640x480 ``gelmap.npy`` / 4.
    pixel_m : a pixel's size on the gel at (width, height), metres (the table's).
    width, height : the frames' size the table was fitted at, pixels: the port evaluates
        the polynomial at (column, row) scaled to this size.
    shadow_from : a folder holding a Taxim ``shadowTable.npz`` to copy (e.g.
        :func:`shipped_folder`), or None: shadows off (a neutral table is written,
        since the port loads one whatever it renders).

    Returns
    -------
    Path of the folder: ``polycalib.npz`` (``grad_r``/``grad_g``/``grad_b`` (B, B, 6) in
    0-255 units, red and blue swapped as the port expects; ``bins``), ``params.json``,
    ``gelmap.npy`` (float32), ``dataPack.npz`` (``f0`` (height, width, 3) uint8 BGR) and
    ``shadowTable.npz``.
    """
    if not isinstance(table, dict) or "coeffs" not in table:
        raise ValueError(f"table must be fit_polytable's dict, got {type(table).__name__}")
    coeffs = np.asarray(table["coeffs"], dtype=np.float64)
    if coeffs.ndim != 4 or coeffs.shape[0] != coeffs.shape[1] or coeffs.shape[2:] != (3, 6) \
            or not np.all(np.isfinite(coeffs)):
        raise ValueError(f"table['coeffs'] must be finite (B, B, 3, 6), got {coeffs.shape}")
    width, height = checked_size("width", width, 3), checked_size("height", height, 3)
    if tuple(table.get("shape", (height, width))) != (height, width):
        raise ValueError(f"width x height must be the size the table was fitted at, {table['shape'][1]}x"
                         f"{table['shape'][0]}, got {width}x{height}")
    pixel_m = checked_positive("pixel_m", pixel_m)
    if "pixel_m" in table and not math.isclose(pixel_m, table["pixel_m"], rel_tol=1e-9):
        raise ValueError(f"pixel_m must be the table's pixel ({table['pixel_m']:g} m: its slopes were fitted "
                         f"with it), got {pixel_m:g}")
    f0 = checked_image("no_contact", no_contact, (height, width, 3))
    gel = np.asarray(gel_map_px)
    if gel.ndim != 2 or gel.dtype.kind not in "iuf" or min(gel.shape) < 2 or not np.all(np.isfinite(gel)):
        raise ValueError(f"gel_map_px must be (Hg, Wg) finite heights in pixels, got {gel.shape} {gel.dtype}")
    shadow = None
    if shadow_from is not None:
        shadow = Path(shadow_from) / "shadowTable.npz"
        if not shadow.is_file():
            raise ValueError(f"shadow_from must be a folder holding shadowTable.npz, got {shadow_from}")
    sigma_px = checked_positive("table['sigma_px']", table.get("sigma_px", BACKGROUND_SIGMA_PX))

    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    # 0-255 units; the port reads grad_b as red and grad_r as blue (Taxim's BGR fit).
    grads = np.moveaxis(coeffs, 2, 0) * 255.0
    np.savez(folder / "polycalib.npz", bins=np.int64(coeffs.shape[0]), grad_r=grads[2], grad_g=grads[1],
             grad_b=grads[0])
    params = {"simulator": {**SIMULATOR_PARAMS, "initial_frame_sigma_rel": [sigma_px / width, sigma_px / height]},
              "sensor": {"pixmm": pixel_m * 1e3, "num_bins": int(coeffs.shape[0]), "h": height, "w": width}}
    (folder / "params.json").write_text(json.dumps(params, indent=2))
    np.save(folder / "gelmap.npy", gel.astype(np.float32))
    np.savez(folder / "dataPack.npz", f0=_to_bgr8(f0))
    if shadow is not None:
        shutil.copyfile(shadow, folder / "shadowTable.npz")
    else:
        np.savez(folder / "shadowTable.npz", shadowDirections=SHADOW_DIRECTIONS, shadowTable=_neutral_shadow_table())
    return folder


def _require_port():
    """The port's package and JAX, or ImportError saying how to install them."""
    try:
        import jax  # noqa: F401  (the port's backend)
        import taxim
        from taxim.taxim_jax import TaximJax
    except ImportError as exc:
        raise ImportError(f"Taxim's port is not installed ({exc}): {INSTALL_HINT}") from None
    return taxim, TaximJax


def shipped_folder() -> Path:
    """The port's own calibration folder (``taxim/calib/gelsight``: 125 bins, 640x480,
    0.0295 mm pixels, fitted on 48 presses of another recording session); ImportError
    with the install command when the port or JAX is missing."""
    taxim, _ = _require_port()
    return Path(taxim.CALIB_GELSIGHT)


# ----------------------------------------------------------------------------- height maps

def ball_height_map(centre_px, ball_radius_m: float, pixel_m: float, shape: tuple[int, int]) -> np.ndarray:
    """A ball's height map in Taxim's convention, touching the gel's apex height.

    Parameters
    ----------
    centre_px : (2,) float, the ball's centre (x = column, y = row), pixels.
    ball_radius_m : metres.
    pixel_m : a pixel's size on the gel, metres.
    shape : (H, W).

    Returns
    -------
    (H, W) float64, millimetres: the ball's distance from the plane of the gel's highest
    point, smaller toward the camera (``taxim.TaximImpl.render``): R - sqrt(R² - r²), 0
    under the centre, and R (the ball's equator) outside its silhouette, where the port
    sees no object within reach of the gel.
    """
    h, w = checked_shape(shape)
    centre = checked_point("centre_px", centre_px)
    radius_mm = checked_positive("ball_radius_m", ball_radius_m) * 1e3
    pixel_mm = checked_positive("pixel_m", pixel_m) * 1e3
    rows, cols = np.mgrid[:h, :w].astype(np.float64)
    r2 = ((cols - centre[0]) ** 2 + (rows - centre[1]) ** 2) * pixel_mm ** 2
    return np.where(r2 < radius_mm ** 2, radius_mm - np.sqrt(np.maximum(radius_mm ** 2 - r2, 0)), radius_mm)


def gel_surface_mm(gel_map_px: np.ndarray, pixmm: float, shape: tuple[int, int]) -> np.ndarray:
    """The undeformed gel's height in the port's frame, at a render's size.

    Parameters
    ----------
    gel_map_px : (Hg, Wg) float, Taxim's ``gelmap``: heights in the calibration's pixels,
        larger toward the object.
    pixmm : the calibration's pixel (``params.json``), mm: one unit of ``gel_map_px``.
    shape : (H, W) of the render.

    Returns
    -------
    (H, W) float64, mm: 0 at the apex, negative elsewhere (toward the camera), resampled
    bilinearly with pixel centres aligned. (The port resizes with ``jax.image.resize``,
    which also averages when shrinking, after a half-pixel blur: on the Taxim set's dome
    at 160x120 that moves the surface by 0.2 µm (median), 2 µm inside the frame and 10 µm
    on its edge, so it is left out.)
    """
    gel = np.asarray(gel_map_px)
    if gel.ndim != 2 or gel.dtype.kind not in "iuf" or min(gel.shape) < 2 or not np.all(np.isfinite(gel)):
        raise ValueError(f"gel_map_px must be (Hg, Wg) finite heights in pixels, got {gel.shape} {gel.dtype}")
    gel = gel.astype(np.float64) * checked_positive("pixmm", pixmm)
    gel -= gel.max()
    h, w = checked_shape(shape)
    rows = (np.arange(h) + 0.5) * gel.shape[0] / h - 0.5
    cols = (np.arange(w) + 0.5) * gel.shape[1] / w - 0.5
    rr, cc = np.meshgrid(rows, cols, indexing="ij")
    return ndimage.map_coordinates(gel, [rr, cc], order=1, mode="nearest")


# ----------------------------------------------------------------------------- the peer

class TaximPeer:
    """Taxim's port with one calibration, rendering height maps and ball presses.

    Parameters
    ----------
    calib_folder : a Taxim calibration folder (:func:`write_calibration`,
        :func:`shipped_folder`).
    no_contact : (H, W, 3) float, RGB in [0, 1], or None: a no-contact frame that replaces
        the folder's, so that the background is the unit's own (the port blurs and mixes
        it with the folder's parameters, relative to its size).
    with_shadow : render Taxim's shadows (needs a folder with a real shadow table).
    dome_correction : False (default): render as the port does, and as Taxim's published
        renderer does (Robo-Touch/Taxim ``main:OpticalSimulation/simOptical.py``): the
        background plus the table's change for every normal, the dome's slopes off the
        contact included. True: subtract the table's change of the undeformed gel, as
        Taxim's renderer for the 160x120 set does (``real_bg = bg_proc - table(dome)``,
        ``data-collection:renderer/DepthRender.py``). Off the contact the port adds the
        table's low-slope bins (fitted at a press's centre, not on the gel at rest) onto a
        frame that already shows the dome; the correction renders the gel at rest as the
        background, but also takes that change out of the contact.

    The port's simulators are built per pixel size (:meth:`render` tells the port the
    height maps' pixel, so that slopes are physical whatever the folder's pixmm) and
    compile once per image size; both are kept, as is the dome's change per size.
    """

    def __init__(self, calib_folder, no_contact: np.ndarray | None = None, with_shadow: bool = False,
                 dome_correction: bool = False):
        _require_port()
        folder = Path(calib_folder)
        missing = [f for f in ("polycalib.npz", "params.json", "gelmap.npy", "dataPack.npz", "shadowTable.npz")
                   if not (folder / f).is_file()]
        if missing:
            raise ValueError(f"calib_folder must be a Taxim calibration folder, {folder} lacks {missing}")
        self.folder = folder
        self.params = json.loads((folder / "params.json").read_text())
        self.no_contact = None if no_contact is None else checked_image("no_contact", no_contact)
        self.with_shadow = bool(with_shadow)
        self.dome_correction = bool(dome_correction)
        if self.with_shadow:
            shadows = np.load(folder / "shadowTable.npz", allow_pickle=True)["shadowTable"]
            if not any(np.isfinite(v).any() for v in shadows.reshape(-1) if len(v)):
                raise ValueError(f"with_shadow needs a shadow table; {folder}'s is neutral (written without "
                                 "shadow_from)")
        self._gel_map_px = np.load(folder / "gelmap.npy")
        self._simulators: dict[float, object] = {}  # pixmm at the folder's size -> the port's simulator
        self._domes: dict[tuple, np.ndarray] = {}  # (pixmm, H, W) -> the dome's change, (H, W, 3)

    def pixmm(self, pixel_m: float, width: int) -> float:
        """The folder-scale pixel, mm, that makes a ``width``-pixel render's pixel ``pixel_m``."""
        return checked_positive("pixel_m", pixel_m) * 1e3 * width / self.params["sensor"]["w"]

    def _simulator(self, pixmm: float):
        key = round(pixmm, 12)
        if key not in self._simulators:
            _, TaximJax = _require_port()
            params = {"sensor": {"pixmm": pixmm}}
            if self.no_contact is None:
                self._simulators[key] = TaximJax(self.folder, params=params)
            else:
                # The port reads f0 from the folder: give it a copy whose dataPack is ours.
                with tempfile.TemporaryDirectory(prefix="taxim_peer_") as tmp:
                    for name in ("polycalib.npz", "params.json", "gelmap.npy", "shadowTable.npz"):
                        (Path(tmp) / name).symlink_to((self.folder / name).resolve())
                    np.savez(Path(tmp) / "dataPack.npz", f0=_to_bgr8(self.no_contact))
                    self._simulators[key] = TaximJax(Path(tmp), params=params)
        return self._simulators[key]

    def background(self, shape: tuple[int, int]) -> np.ndarray:
        """The background the port adds, (H, W, 3) float64 RGB in [0, 1], at ``shape``.

        The no-contact frame as the port reads it (8-bit), blurred and mixed with the
        folder's parameters at its own size (:func:`background`), resized as the port
        resizes (``jax.image.resize``, linear) when the render's size differs.
        """
        h, w = checked_shape(shape)
        if self.no_contact is not None:
            f0 = _to_bgr8(self.no_contact)[..., ::-1] / 255.0
        else:
            f0 = np.load(self.folder / "dataPack.npz", allow_pickle=True)["f0"][..., ::-1] / 255.0
        sim = self.params["simulator"]
        sigma_cols, sigma_rows = (rel * n for rel, n in zip(sim["initial_frame_sigma_rel"], f0.shape[1::-1]))
        mixing = sim["frame_mixing_percentage"]
        bg = mixing * blurred(f0, sigma_rows, sigma_cols) + (1 - mixing) * f0
        if bg.shape[:2] != (h, w):
            import jax

            bg = np.asarray(jax.image.resize(bg, (h, w, 3), method="linear"), dtype=np.float64)
        return bg

    def _dome(self, pixmm: float, shape: tuple[int, int]) -> np.ndarray:
        """The change the table gives the undeformed gel (the port's render of no object
        minus its background), (H, W, 3)."""
        key = (round(pixmm, 12),) + tuple(shape)
        if key not in self._domes:
            # Any height above the apex (> 0) is out of the gel's reach.
            nothing = np.ones(shape, np.float32)
            rendered = np.asarray(self._simulator(pixmm).render(nothing, with_shadow=self.with_shadow),
                                  dtype=np.float64)
            self._domes[key] = rendered - self.background(shape)
        return self._domes[key]

    def render(self, height_maps_mm: np.ndarray, pixel_m: float) -> np.ndarray:
        """Render height maps as placed (no press_depth shift).

        Parameters
        ----------
        height_maps_mm : (N, H, W) or (H, W) float, millimetres, Taxim's convention
            (:func:`ball_height_map`): 0 at the gel's apex, smaller toward the camera.
        pixel_m : a height-map pixel's size on the gel, metres.

        Returns
        -------
        (N, H, W, 3) or (H, W, 3) float64, RGB in [0, 1].
        """
        maps = np.asarray(height_maps_mm)
        if maps.ndim not in (2, 3) or maps.dtype.kind not in "iuf" or min(maps.shape[-2:]) < 3 \
                or not np.all(np.isfinite(maps)):
            raise ValueError(f"height_maps_mm must be (N, H, W) or (H, W) finite millimetres, got {maps.shape} "
                             f"{maps.dtype}")
        pixmm = self.pixmm(pixel_m, maps.shape[-1])
        images = np.asarray(self._simulator(pixmm).render(maps.astype(np.float32), with_shadow=self.with_shadow),
                            dtype=np.float64)
        if not self.dome_correction:
            return images
        # Taxim's real_bg: the table's change of the gel at rest is not added to a frame that shows it.
        return np.clip(images - self._dome(pixmm, maps.shape[-2:]), 0, 1)

    def press_height_maps(self, centres_px, depths_m, ball_radius_m: float, pixel_m: float,
                          shape: tuple[int, int]) -> np.ndarray:
        """Height maps of balls pressed ``depths_m`` below the gel's surface where they land.

        The gel is domed (``gelmap``): away from the apex its surface lies lower, so a
        ball reaching depth d below it is placed at the gel's height there minus d. (The
        port's ``press_depth`` measures from the apex instead: a press of d there would
        be d - sag deep, and none where the sag exceeds d.) The port still scales its
        contact core (``contact_scale``, the pixels kept undeformed by its blur) by the
        depth below the apex, d + sag: off the apex that core is smaller than at it
        (at the Taxim set's edge presses, sag 0.37 mm, 20 % fewer pixels for d = 1 mm).

        Parameters
        ----------
        centres_px : (N, 2) float, each ball's centre (x = column, y = row), pixels.
        depths_m : (N,) float, metres, each press's depth below the gel's surface there.
        ball_radius_m, pixel_m : metres.
        shape : (H, W).

        Returns
        -------
        (N, H, W) float64, mm, Taxim's convention.
        """
        centres = checked_centres(centres_px)
        depths = np.asarray(depths_m, dtype=np.float64) if np.asarray(depths_m).dtype.kind in "iuf" else None
        if depths is None or depths.shape != (len(centres),) or not np.all(np.isfinite(depths)) \
                or np.any(depths <= 0):
            raise ValueError(f"depths_m must be ({len(centres)},) positive metres, got {np.asarray(depths_m).shape}")
        ball_radius_m = checked_positive("ball_radius_m", ball_radius_m)
        if np.any(depths >= ball_radius_m):
            raise ValueError(f"depths_m must be below the ball's radius {ball_radius_m:g} m, got {depths.max():g}")
        h, w = checked_shape(shape)
        gel = gel_surface_mm(self._gel_map_px, self.pixmm(pixel_m, w), (h, w))
        out = np.empty((len(centres), h, w))
        for i, (centre, depth) in enumerate(zip(centres, depths)):
            # The gel's height under the centre, bilinear between pixel centres.
            surface = ndimage.map_coordinates(gel, [[centre[1]], [centre[0]]], order=1, mode="nearest")[0]
            out[i] = ball_height_map(centre, ball_radius_m, pixel_m, (h, w)) + surface - depth * 1e3
        return out

    def render_presses(self, centres_px, depths_m, ball_radius_m: float, pixel_m: float,
                       shape: tuple[int, int]) -> np.ndarray:
        """Render balls pressed into the gel (:meth:`press_height_maps`).

        centres_px : (N, 2) (x = column, y = row), pixels; depths_m : (N,) metres below the
        gel's surface at each centre; ball_radius_m, pixel_m : metres; shape : (H, W).
        Returns (N, H, W, 3) float64, RGB in [0, 1].
        """
        maps = self.press_height_maps(centres_px, depths_m, ball_radius_m, pixel_m, shape)
        return self.render(maps, pixel_m)


def render_presses(calib_folder, centres_px, depths_m, ball_radius_m: float, pixel_m: float,
                   shape: tuple[int, int], no_contact: np.ndarray | None = None, with_shadow: bool = False,
                   dome_correction: bool = False) -> np.ndarray:
    """One-off :meth:`TaximPeer.render_presses`: (N, H, W, 3) float64 RGB in [0, 1]."""
    peer = TaximPeer(calib_folder, no_contact=no_contact, with_shadow=with_shadow, dome_correction=dome_correction)
    return peer.render_presses(centres_px, depths_m, ball_radius_m, pixel_m, shape)


#: The peer's variants a comparison renders: Taxim's shipped calibration, one fitted on the
#: capture's own fitted half at the capture's depths, and that one at its own depth setting.
VARIANTS = ("shipped", "refit", "refit_share")
#: The rim shares among which ``refit_share`` chooses Taxim's depth setting on the fitted
#: half (``scenes.imports.rim_depth``: each press's depth is the chord's for a contact
#: whose radius is its rim over the share).
RIM_SHARES = (0.55, 0.6, 0.65, 0.7, 0.75, 0.8, 0.85, 0.9, 0.95, 1.0)


def capture_presses(capture, ids) -> dict:
    """What Taxim needs of a capture's presses ``ids``: (N, 2) annotated centres (px),
    (N,) annotated radii (px), (N,) depths (metres: each sample's ``measured_depth``), the
    ball's radius and the pixel's size (metres: the import's ``ball_mm`` and ``pixel_mm``).
    ValueError saying what is missing where the capture is no imported set of ball presses."""
    from scenes.indenters import ball_diameter

    block = capture.meta.get("import") or {}
    by_id = {r["id"]: r for r in capture.records}
    records = [by_id[i] for i in ids]
    objects = {r.get("object") for r in records}
    diameters = {ball_diameter(o) for o in objects}
    if None in diameters or len(diameters) != 1 or "pixel_mm" not in block:
        raise ValueError("Taxim renders presses of one ball at annotated places: the capture must be an imported set "
                         f"(tactile-sim import) of ball presses, got objects {sorted(map(str, objects))} and "
                         f"{'an' if block else 'no'} import block")
    if not all("contact_center_px" in r and "contact_radius_px" in r for r in records):
        raise ValueError("Taxim needs each press's annotated centre and radius (contact_center_px, contact_radius_px)")
    return {"centres": np.array([r["contact_center_px"] for r in records], np.float64),
            "radii": np.array([r["contact_radius_px"] for r in records], np.float64),
            "depths": np.array([r["measured_depth"] for r in records], np.float64),
            "edges": np.array([r.get("contact_edge_px", np.nan) for r in records], np.float64),
            "ball_radius_m": diameters.pop() / 2, "pixel_m": float(block["pixel_mm"]) * 1e-3}


def share_depths(presses: dict, share: float) -> np.ndarray:
    """(N,) m, each press's depth at rim share ``share`` (``scenes.imports.rim_depth``),
    from ``capture_presses``' rims."""
    from scenes.imports import rim_depth

    return np.array([rim_depth(e, presses["pixel_m"], presses["ball_radius_m"], share)[0] for e in presses["edges"]])


def choose_rim_share(peer, fitted: dict, real_fitted: np.ndarray, no_contact: np.ndarray,
                     shares=RIM_SHARES) -> tuple[float, dict]:
    """(the share of ``shares`` whose depths give the least mean contact MAE over the
    fitted presses ``fitted`` (``capture_presses``), their real frames ``real_fitted``,
    {share: that MAE}): Taxim's depth setting chosen on the fitted half alone."""
    from scenes.captures import contact_disc

    h, w = no_contact.shape[:2]
    discs = np.stack([contact_disc((h, w), c, r) for c, r in zip(fitted["centres"], fitted["radii"])])
    losses = {}
    for share in shares:
        images = peer.render_presses(fitted["centres"], share_depths(fitted, share), fitted["ball_radius_m"],
                                     fitted["pixel_m"], (h, w))
        losses[float(share)] = float(np.mean([np.abs(im[d] - y[d]).mean() for im, y, d in
                                              zip(images, real_fitted, discs)]))
    return min(losses, key=losses.get), losses


def peer_renders(capture, ids, fitted_ids, real_fitted: np.ndarray, no_contact: np.ndarray,
                 with_shadow: bool = True) -> dict[str, dict]:
    """Taxim's renders of a capture's presses ``ids`` with each of VARIANTS: {variant:
    {"images": (N, H, W, 3), "no_contact": (H, W, 3), "note": str}}.

    ``shipped``: the port's own calibration (another session of the Taxim set's sensor),
    with the capture's no-contact frame as background; ``refit``: a table fitted
    (:func:`fit_polytable`) on the presses ``fitted_ids`` (their real frames
    ``real_fitted``, (K, H, W, 3)) and the shipped gel map and shadow table;
    ``refit_share`` (where every press records its rim, ``contact_edge_px``): the refit at
    the depths of the rim share it fits the fitted presses best with (``choose_rim_share``),
    its own depth setting chosen on the fitted half. Each peer's
    no-contact image is its render of the gel untouched. ImportError where the port or
    JAX is missing; ValueError where the capture is not one it can render
    (:func:`capture_presses`).
    """
    presses = capture_presses(capture, ids)
    fitted = capture_presses(capture, fitted_ids)
    h, w = no_contact.shape[:2]
    shipped = shipped_folder()
    out = {}
    with tempfile.TemporaryDirectory(prefix="taxim_refit_") as tmp:
        table = fit_polytable(no_contact, real_fitted, fitted["centres"], fitted["radii"], presses["pixel_m"],
                              presses["ball_radius_m"])
        # the shipped gel map's heights, in its own pixels (its pixmm), in the capture's
        gel = np.load(shipped / "gelmap.npy") * (float(json.loads((shipped / "params.json").read_text())["sensor"]
                                                       ["pixmm"]) * 1e-3 / presses["pixel_m"])
        folders = {"shipped": shipped,
                   "refit": write_calibration(tmp, table, no_contact, gel, presses["pixel_m"], w, h,
                                              shadow_from=shipped if with_shadow else None)}
        notes = {"shipped": "Taxim's shipped calibration (taxim 1.4.1's calib/gelsight: 48 presses of another session "
                            "of this sensor design), the capture's no-contact frame as background",
                 "refit": f"a table fitted on the capture's {len(fitted_ids)} fitted presses (their real frames), the "
                          "shipped gel map and shadow table"}
        depths = {"shipped": presses["depths"], "refit": presses["depths"]}
        if np.all(np.isfinite(presses["edges"])) and np.all(np.isfinite(fitted["edges"])):
            share, losses = choose_rim_share(TaximPeer(folders["refit"], no_contact=no_contact, with_shadow=with_shadow),
                                             fitted, real_fitted, no_contact)
            folders["refit_share"] = folders["refit"]
            depths["refit_share"] = share_depths(presses, share)
            notes["refit_share"] = (f"the refit, each press's depth the chord's at its rim over {share:g}: the rim share "
                                    f"of {list(RIM_SHARES)} whose fitted presses' contact MAE is least "
                                    f"({', '.join(f'{k:g}: {v:.4f}' for k, v in losses.items())})")
        for variant, folder in folders.items():
            peer = TaximPeer(folder, no_contact=no_contact, with_shadow=with_shadow)
            images = peer.render_presses(presses["centres"], depths[variant], presses["ball_radius_m"],
                                         presses["pixel_m"], (h, w))
            rest = peer.render(np.full((h, w), 10.0), presses["pixel_m"])  # the gel untouched, 10 mm away
            out[variant] = {"images": images.astype(np.float32), "no_contact": rest.astype(np.float32),
                            "note": notes[variant] + ("; shadows on" if with_shadow else "")}
    return out
