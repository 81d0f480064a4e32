"""The fast simulator, decomposed so that candidate effects can be added to it.

The fast path renders I = k_a B + sum_m (k_d,m (L_m . N) + k_s,m (R_m . V)^alpha) c_m from
a contact's depth (``phong_reference.render``). ``FastModel`` rebuilds that chain from a
simulated dataset's own settings (sensor, light field, background) at a working
resolution, keeps each sample's geometry and per-LED shading terms, and re-renders with
any set of effects switched on (``studies.gap.effects``).

A prediction of the real image is the simulated image plus what the effects change:

    pred = optics_and_sensor(sim + M(theta) - M(identity))

with M the rebuilt simulator. At the identity it is the simulated image itself, whatever
renderer made it, so the rebuilt chain only has to get the *change* right; that also
lets fits run at a lower working resolution than the one the result is measured at.
"""

from __future__ import annotations

import os
from concurrent.futures import ThreadPoolExecutor

import numpy as np

from phong_reference.background import make_background
from phong_reference.bake import bake
from phong_reference.normals import normals
from phong_reference.phong import compose, led_intensities, shading_terms
from phong_reference.render import light_vectors
from scenes.camera import CONTACT_EPS_M as CONTACT_NOISE_M  # the one contact threshold
from scenes.camera import Camera, cast_rays, reference_depth
from scenes.geometry import membrane_mesh
from scenes.images import block_mean
from scenes.spec import SensorSpec

from . import effects as fx
from .optics import optics, working_cameras


def _dot(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


def auto_exposed(meta: dict) -> bool:
    """Whether a dataset's camera set its own exposure (``renderer.camera.exposure`` is
    "auto" in its dataset.json: ``rig.camera``'s devices and the virtual rig's reference)."""
    camera = (meta.get("renderer") or {}).get("camera")
    return isinstance(camera, dict) and camera.get("exposure") == "auto"


class FastModel:
    """The fast simulator of a dataset's sensor and renderer settings at 1/``factor`` of
    the dataset's resolution.

    spec : the sensor; renderer : the dataset's renderer settings (``field``,
    ``background``, ``rectify``); factor : integer downsampling of the working resolution;
    exposure : the real camera sets its own exposure, so every candidate without gains
    of its own is fitted with the capture's exposure (``effects.with_exposure``).
    """

    kind = "fast"
    names = fx.EFFECTS
    stages = fx.STAGES
    aliases: dict = {}
    max_fit_samples = None  # the diagnosis' own cap
    judged_renders = None  # every candidate is judged on the held-out samples (none renders there)

    def __init__(self, spec: SensorSpec, renderer: dict, factor: int = 1, exposure: bool = False):
        # A dataset rendered for a calibrated unit (``--profile``) records its profile: the
        # chain is then the unit's (phong_reference.profiled): its LEDs (and their fitted
        # constants, where the profile has them) and image circle,
        # its background term, and the membrane's shading moved by its alignment.
        self.profile = None
        if renderer.get("profile_data") is not None:
            from dataclasses import replace

            from phong_reference.profiled import profile_constants
            from scenes.profile import profile_from_dict

            self.profile = profile_from_dict(renderer["profile_data"], "the simulated dataset's profile")
            spec = profile_constants(self.profile, self.profile.sensor_spec(spec), renderer.get("field", "plane"))
            spec = spec.replace(material=replace(spec.material, ambient=1.0))  # k_a is in the profile's B
        self.spec = spec
        # A profile fitted to taps composes by change (phong_reference.profiled): its
        # background is the unit's whole no-contact image, the LEDs add what a contact changes.
        from phong_reference.profiled import composition

        self.by_change = self.profile is not None and composition(self.profile) == "change"
        self.factor = int(factor)
        self.full_camera, self.camera = working_cameras(spec, self.factor)
        full = self.full_camera
        self.mesh = membrane_mesh(spec)
        field = renderer.get("field", "plane")
        fields = bake(self.mesh, self.camera, spec.leds, field)
        self.ref = fields.depth.astype(np.float32)
        # (3, H, W) unit inward normals of the undeformed membrane (0 off it): the guided
        # light's elevation is measured from its tangent plane.
        self.inward = np.ascontiguousarray(-np.asarray(fields.normals, np.float32).transpose(2, 0, 1))
        self.full_ref = self.ref if self.factor == 1 else reference_depth(self.mesh, full)[0].astype(np.float32)
        self.L = light_vectors(fields, bool(renderer.get("rectify", False)))
        background = str(renderer.get("background", "none"))
        self.B = _background(background, full, self.camera, self.factor, self.profile)
        self._B = np.ascontiguousarray(self.B.transpose(2, 0, 1))  # (3, H, W), for the Phong terms
        self.mask = self.camera.mask
        # (H, W) share of each pixel inside the lens's image circle, and (H, W, 3) what the
        # ambient term k_a B puts in a simulated image: both stay put under a misalignment.
        self.circle = block_mean(full.mask.astype(np.float32), self.factor)
        full_B = self.B if self.factor == 1 else _background(background, full, full, 1, self.profile)
        ambient = np.clip(spec.material.ambient * full_B, 0.0, 1.0) * full.mask[..., None]
        self.fixed = block_mean(ambient.astype(np.float32), self.factor)
        self.rays = self.camera.rays_channels_first
        self.colours = np.array([led.colour for led in spec.leds], np.float64)
        self.k_d = np.array([led.k_d for led in spec.leds], np.float32)
        self.k_s = np.array([led.k_s for led in spec.leds], np.float32)
        self.led_positions = np.array([led.position for led in spec.leds], np.float64)
        self.sigma_px = float(spec.elastic.sigma_px)
        self.truncate = spec.elastic.radius_px / spec.elastic.sigma_px
        self.catalogue = fx.catalogue(len(spec.leds), self.sigma_px)
        # With the capture's exposure every candidate holds a gain, and camera_response's
        # 11 parameters then mimic a physical change nearly as well as its own model: the
        # ranking's tie rule (``selection.rank``) puts the simplest of the tied best first.
        self.ties_to_simplest = bool(exposure)
        if exposure:
            self.catalogue = fx.with_exposure(self.catalogue)
        self._geodesic = None
        self._base_distance = None
        self._fade_length = None
        self._fade_cache = None  # (parameters, fades) of the last path_attenuation asked for
        self._samples = None  # where the camera's rays meet the membrane (scenes.camera.cast_rays)
        self._cache: dict[int, dict] = {}

    def not_applicable(self, pairs) -> dict[str, str]:
        """{effect: why} for the effects this model cannot fit on ``pairs``."""
        out = {}
        renderer = dict(pairs.sim_meta.get("renderer") or {})
        if pairs.depth is None:
            for name in fx.EFFECTS:
                if fx.STAGES[name] in ("membrane", "light"):
                    out[name] = "the simulated dataset has no depth maps to re-render its contacts from"
        if renderer.get("renderer", "phong") != "phong":
            for name in fx.EFFECTS:
                if fx.STAGES[name] in ("membrane", "light"):
                    out.setdefault(name, f"the simulated dataset was not rendered by the fast path "
                                         f"(renderer {renderer.get('renderer')!r}), so it cannot be re-rendered")
        if any(led.peak_nm is None or led.fwhm_nm is None for led in self.spec.leds):
            out.setdefault("led_spectrum", "the sensor spec gives no LED peak_nm / fwhm_nm")
        return out

    # --- inputs -------------------------------------------------------------------------

    def working_depth(self, depth: np.ndarray) -> np.ndarray:
        """(N, H, W) full-resolution depth maps -> working resolution: the indentation
        D_ref - D is averaged over pixel blocks, so no-contact pixels stay at D_ref."""
        delta = self.full_ref[None] - np.asarray(depth, np.float32)
        delta[np.abs(delta) <= CONTACT_NOISE_M] = 0.0
        return self.ref[None] - block_mean(delta, self.factor, (1, 2))

    def working_images(self, images: np.ndarray) -> np.ndarray:
        return block_mean(np.asarray(images, np.float32), self.factor, (1, 2))

    def compared(self, images: np.ndarray) -> np.ndarray:
        """Images as the diagnosis fits and judges them: the images themselves (the
        reference model low-passes its own, ``ReferenceModel.compared``)."""
        return images

    @property
    def geodesic(self) -> np.ndarray:
        """(M, H, W) path length over the undeformed membrane from each LED, metres, at
        every pixel of the image circle (0 elsewhere).

        Shortest paths along the mesh's edges (scipy's Dijkstra): on a mesh of near-
        equilateral triangles they run a few per cent longer than true geodesics, a
        constant factor that the fitted absorption coefficient takes up.
        """
        if self._geodesic is None:
            from phong_reference.sources import FREE_SOURCE_TOLERANCE_M, snap_leds

            # from the membrane's point nearest each LED (a calibrated unit's may sit off it,
            # under a pad's plate: phong_reference.calibrate.fit_led_places)
            sources = np.asarray(snap_leds(self.mesh, self.spec.leds, FREE_SOURCE_TOLERANCE_M).vertices).reshape(-1)
            self._geodesic = np.stack([self._surface_distance([v]) for v in sources])
        return self._geodesic

    @property
    def base_distance(self) -> np.ndarray:
        """(H, W) path length over the undeformed membrane from the LEDs' ring, metres: from
        the nearest point of the membrane at or below the LEDs' height along the sensor's
        axis (the camera's z), the way the guided light that the background term stands
        for has come (it enters all round the base); 0 off the image circle. On the
        GelTip's cylinder it is the height above the LEDs, on its tip that plus the arc."""
        if self._base_distance is None:
            z = np.asarray(self.mesh.vertices)[:, 2]
            plane = float(np.mean([led.position[2] for led in self.spec.leds]))
            below = np.flatnonzero(z <= plane)
            if below.size == 0:  # the membrane starts above its LEDs: from its lowest edge
                below = np.flatnonzero(z <= z.min() + self.spec.membrane.mesh_edge)
            self._base_distance = self._surface_distance(below)
        return self._base_distance

    @property
    def axial(self) -> np.ndarray:
        """(H, W) float32 the undeformed membrane's height along the sensor's axis (the
        camera's z) above the LEDs' plane, metres, >= 0; 0 off the image circle."""
        plane = float(np.mean([led.position[2] for led in self.spec.leds]))
        return (np.maximum(self.ref - plane, 0.0) * self.mask).astype(np.float32)

    @property
    def fade_length(self) -> float:
        """The longest distance the image circle holds, over the membrane from the LEDs'
        ring or along the axis, metres: ``path_attenuation``'s profile spans [0, this]."""
        if self._fade_length is None:
            self._fade_length = max(float(self.base_distance.max()), float(self.axial.max()), 1e-3)
        return self._fade_length

    def fades(self, p: dict) -> tuple[np.ndarray, np.ndarray]:
        """``path_attenuation`` at parameters ``p``: the light left of each LED's own term
        (M, H, W) and of the background term (H, W) (``effects.fade``); the last is kept,
        since every sample of one evaluation asks for the same."""
        key = tuple(sorted(p.items()))
        cached = self._fade_cache
        if cached is not None and cached[0] == key:
            return cached[1]
        depths = [p[f"depth_{k}"] for k in range(fx.FADE_KNOTS)]
        s, axial, length = p["axial_share"], self.axial, self.fade_length
        own = fx.fade(fx.fade_ramps(fx.fade_distances(self.geodesic, axial[None], s), length),
                      np.float32(p["led_weight"]) * np.asarray(depths, np.float32))
        background = fx.fade(fx.fade_ramps(fx.fade_distances(self.base_distance, axial, s), length),
                             np.float32(p["ambient_weight"]) * np.asarray(depths, np.float32))
        out = (own.astype(np.float32), background.astype(np.float32))
        self._fade_cache = (key, out)
        return out

    def _surface_distance(self, sources) -> np.ndarray:
        """(H, W) float32 shortest path along the mesh's edges from the nearest of the
        ``sources`` (vertex indices), metres, at each pixel of the image circle (scipy's
        Dijkstra, interpolated over the faces the camera's rays meet)."""
        from scipy.sparse import coo_matrix
        from scipy.sparse.csgraph import dijkstra

        edges = np.asarray(self.mesh.edges_unique)
        n = len(self.mesh.vertices)
        graph = coo_matrix((np.asarray(self.mesh.edges_unique_length), (edges[:, 0], edges[:, 1])), shape=(n, n))
        distance = dijkstra(graph.tocsr(), directed=False, indices=np.asarray(sources), min_only=True)
        if self._samples is None:
            self._samples = cast_rays(self.mesh, self.camera)
        return self._samples.scatter(self._samples.interpolate(self.mesh, distance).astype(np.float32))

    # --- the chain ----------------------------------------------------------------------

    def geometry(self, depth: np.ndarray, scale: float = 1.0, sigma_px: float | None = None) -> dict:
        """Deformed surface of one working-resolution depth map, and its shading terms.

        scale : membrane_compliance; sigma_px : elastic_spread (full-resolution pixels).
        Returns P, N (3, H, W), delta = D_ref - D_def (H, W), and ``terms``, the Phong
        terms of the fast path itself (``phong_reference.phong.shading_terms``: per LED
        the clamped L_m . N, R_m . V and (R_m . V)^alpha, (M, H, W); and k_a B, (3, H, W)).
        """
        D = fx.compliant_depth(self.ref, depth, scale) if scale != 1.0 else depth
        sigma = (self.sigma_px if sigma_px is None else sigma_px) / self.factor
        D_def = fx.elastic_deform(D, self.ref, sigma, self.truncate).astype(np.float32, copy=False)
        P = D_def[None] * self.rays
        N, _ = normals(P)
        terms = shading_terms(P, N, self.L, self.spec.material, self._B)
        return {"P": P, "N": N, "delta": (self.ref - D_def).astype(np.float32), "terms": terms}

    def _base_geometry(self, key: int, depth: np.ndarray) -> dict:
        g = self._cache.get(key)
        if g is None:
            g = self._cache[key] = self.geometry(depth)
        return g

    def _occlusion(self, g: dict) -> tuple[np.ndarray, np.ndarray]:
        """(low, high) (M, H, W): the elevations of each LED's light the deformed membrane
        blocks (``effects.occlusion_band``), which the shadow's parameters do not change."""
        if "occlusion" not in g:
            D_def = self.ref - g["delta"]
            g["occlusion"] = fx.occlusion_band(D_def, self.ref, self.rays, (self.camera.f, self.camera.cx, self.camera.cy),
                                               self.L, self.inward, self.mask, CONTACT_NOISE_M)
        return g["occlusion"]

    def _leak(self, g: dict, length_m: float) -> np.ndarray:
        if "leak_terms" not in g:  # |N . w| and d^2 per LED, which the length does not change
            cos, d2 = [], []
            for p in self.led_positions:
                D = g["P"] - p.reshape(3, 1, 1).astype(np.float32)
                dd = _dot(D, D)
                d2.append(dd)
                cos.append(np.abs(_dot(g["N"], D)) / np.sqrt(np.maximum(dd, 1e-18)))
            g["leak_terms"] = (np.stack(cos).astype(np.float32), np.stack(d2).astype(np.float32))
        cos, d2 = g["leak_terms"]
        return fx.leak_kernel_from(cos, d2, length_m)

    def physical(self, depth: np.ndarray, params: dict, key: int | None = None) -> np.ndarray:
        """The simulator's image (H, W, 3) of one working-resolution depth map with the
        membrane and light effects in ``params`` ({effect: {param: value}})."""
        membrane = {k: params[k] for k in ("membrane_compliance", "elastic_spread") if k in params}
        if membrane or key is None:
            g = self.geometry(depth, membrane.get("membrane_compliance", {}).get("scale", 1.0),
                              membrane.get("elastic_spread", {}).get("sigma_px"))
        else:
            g = self._base_geometry(key, depth)
        if not self.spec.material.clamp_specular:  # unclamped specular, as the published code had it
            raise ValueError("the diagnosis needs clamp_specular = true in the sensor's material")
        I, ambient, colours = self._lit(g, params)
        if self.profile is None:
            image = compose(I.astype(np.float32, copy=False), colours, ambient.astype(np.float32, copy=False))
            image = image.transpose(1, 2, 0)
        else:  # the membrane's shading moves with the unit's alignment, its background does not
            shading = compose(I.astype(np.float32, copy=False), colours, np.zeros_like(ambient, np.float32))
            image = self._aligned(np.clip(shading, 0.0, 1.0).transpose(1, 2, 0)) + ambient.transpose(1, 2, 0)
            if self.by_change:  # less the undeformed membrane's shading under the same effects
                I0, _, colours0 = self._lit(self._base_geometry(-1, self.ref), params)
                shading0 = compose(I0.astype(np.float32, copy=False), colours0, np.zeros_like(ambient, np.float32))
                image = image - self._aligned(np.clip(shading0, 0.0, 1.0).transpose(1, 2, 0))
        return np.clip(image, fx.ZERO, fx.ONE) * self.mask[..., None]

    def _lit(self, g: dict, params: dict) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(I (M, H, W), the ambient term (3, H, W), the LEDs' colours (M, 3)) of a deformed
        surface's shading terms ``g`` with the light effects in ``params``."""
        terms = g["terms"]
        I = led_intensities(terms, self.k_d, self.k_s)  # (M, H, W), I_m of the fast path
        if "coating_gloss" in params:
            p = params["coating_gloss"]
            I = I + p["k_g"] * np.power(terms.RV, p["shininess"])
        ambient = terms.ambient
        if "contact_shadow" in params:
            p = params["contact_shadow"]
            kept = fx.shadow_factor(*self._occlusion(g), p["elevation_rad"], p["darkness"])  # (M, H, W)
            I = I * kept
            # k_a B stands for the no-contact guided light of every LED: it loses each LED's
            # share, weighted by what that LED puts in each channel, k_d,m c_m.
            weight = (self.k_d[:, None] * self.colours).astype(np.float32)  # (M, 3)
            share = np.tensordot(weight.T, kept, axes=1) / np.maximum(weight.sum(axis=0), 1e-12)[:, None, None]
            ambient = ambient * self._aligned(share.transpose(1, 2, 0), fill=1.0).transpose(2, 0, 1)
        if "path_attenuation" in params:
            own, background = self.fades(params["path_attenuation"])
            I = I * own
            # the background's guided light, from the LEDs' ring
            ambient = ambient * self._aligned(background[..., None], fill=1.0)[..., 0]
        colours = self.colours
        if "led_spectrum" in params:
            p = params["led_spectrum"]
            n = len(self.spec.leds)
            colours = fx.spectral_colours(colours, [led.peak_nm for led in self.spec.leds],
                                          [led.fwhm_nm for led in self.spec.leds],
                                          [p[f"shift_nm_{m}"] for m in range(n)], [p[f"power_{m}"] for m in range(n)],
                                          p.get("filter_floor", 0.0))
        if "core_light_leak" in params:
            p = params["core_light_leak"]
            amplitude = np.array([p[f"amplitude_{m}"] for m in range(len(self.spec.leds))], np.float32)
            I = I + amplitude[:, None, None] * self._leak(g, p["length_m"])
        return I, ambient, colours

    def _aligned(self, image: np.ndarray, fill: float = 0.0) -> np.ndarray:
        """(H, W, C) membrane-frame values as the unit's camera sees them (its profile's
        alignment); unchanged without a profile."""
        if self.profile is None:
            return image
        from scenes.profile import align_image

        return align_image(image, self.profile.alignment, self.full_camera, fill).astype(np.float32)

    def optics(self, images: np.ndarray, params: dict) -> np.ndarray:
        """The optics and sensor effects in ``params`` applied to (N, H, W, 3) images."""
        return optics(images, params, self.camera, self.factor, self.fixed, self.circle)

    def predict(self, sim: np.ndarray, depth: np.ndarray | None, params: dict, keys=None) -> np.ndarray:
        """Predicted real images (N, H, W, 3) from simulated ones and their working-
        resolution depth maps, with the effects in ``params``.

        keys : per-sample cache keys (ints) for the no-effect geometry; None: no cache.
        """
        physical = [k for k in params if fx.STAGES[k] in ("membrane", "light")]
        out = np.asarray(sim, np.float32)
        if physical:
            if depth is None:
                raise ValueError(f"the effects {physical} change the simulated contact and need its depth maps; "
                                 "the simulated dataset has none")
            out = out.copy()
            chosen = {k: params[k] for k in physical}

            def one(i: int) -> None:
                key = None if keys is None else int(keys[i])
                out[i] += self.physical(depth[i], chosen, key) - self._plain(depth[i], key)

            # numpy and scipy release the GIL in the heavy operations: samples in threads.
            with ThreadPoolExecutor(max_workers=os.cpu_count() or 1) as pool:
                list(pool.map(one, range(len(out))))
        scale = fx.exposure_scale(params)
        return self.optics(out * np.float32(scale) if scale != 1.0 else out, params)

    def _plain(self, depth: np.ndarray, key: int | None) -> np.ndarray:
        if key is None:
            return self.physical(depth, {}, None)
        g = self._base_geometry(key, depth)
        if "plain" not in g:
            g["plain"] = self.physical(depth, {}, key)
        return g["plain"]


def _background(kind: str, full: Camera, camera: Camera, factor: int, profile=None) -> np.ndarray:
    if profile is not None:
        from phong_reference.profiled import profile_background

        return profile_background(profile, camera, full)
    if kind in ("none", "solid"):
        return make_background(kind, camera)
    try:
        image = make_background(kind, full)
    except (FileNotFoundError, ValueError) as exc:
        raise ValueError(f"the simulated dataset's background {kind!r} cannot be read here ({exc}); the "
                         "diagnosis re-renders with it") from None
    return block_mean(image, factor)
