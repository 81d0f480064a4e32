"""The physically based reference, depth map to image, as one chain:

    image = render(load(geltip_scene(write_meshes(elastomer(membrane, depth, ref)))))

1. ``elastomer``: the membrane refined, displaced to the elastically smoothed depth and
   closed into the elastomer solid (pbr_tactile.membrane);
2. ``write_meshes`` and ``geltip_scene``: the scene as a plain dict (pbr_tactile.scene);
3. ``load``: the one call of ``mi.load_dict``, after ``to_mitsuba`` turns the dict's plain
   transforms and points into Mitsuba objects;
4. ``render_photons`` (photons from the LEDs to the coating, then camera rays; see
   pbr_tactile.photons) or ``render`` (brute-force volpath): Monte Carlo estimates in
   independent passes, giving the mean image and a per-pixel variance of that mean.
"""

from __future__ import annotations

import tempfile
from dataclasses import dataclass

import numpy as np

from scenes.camera import Camera
from scenes.spec import SensorSpec

from .effects import Effects
from .membrane import elastomer
from .scene import geltip_scene, led_sources, write_meshes
from .variant import choose_variant


def to_mitsuba(value, mi):
    """Plain scene dict -> what ``mi.load_dict`` takes (transforms and points)."""
    if isinstance(value, dict):
        if "look_at" in value:
            la = value["look_at"]
            return mi.ScalarTransform4f().look_at(origin=la["origin"], target=la["target"], up=la["up"])
        out = {}
        for k, v in value.items():
            if k == "center" and isinstance(v, list):
                out[k] = mi.ScalarPoint3f(*v)
            elif isinstance(v, dict) and v.get("type") == "rgb":
                out[k] = {"type": "rgb", "value": mi.ScalarColor3f(*v["value"])}
            else:
                out[k] = to_mitsuba(v, mi)
        return out
    return value


def load(scene: dict, variant: str | None = None):
    """The Mitsuba scene object of a plain scene dict (the one place that loads)."""
    mi = choose_variant(variant)
    return mi, mi.load_dict(to_mitsuba(scene, mi))


@dataclass(frozen=True)
class Estimate:
    """A Monte Carlo image: mean (H, W, 3) float32 linear, and the variance of that mean."""

    mean: np.ndarray
    variance: np.ndarray
    spp: int

    @classmethod
    def from_passes(cls, images: list[np.ndarray], spp: int) -> "Estimate":
        """Mean of independent pass images and the variance of that mean."""
        stack = np.stack(images)
        return cls(stack.mean(axis=0).astype(np.float32),
                   (stack.var(axis=0, ddof=1) / len(images)).astype(np.float32), spp)

    @property
    def relative_error(self) -> np.ndarray:
        """Per-pixel standard error over the mean (inf where the mean is 0)."""
        with np.errstate(divide="ignore", invalid="ignore"):
            return np.sqrt(self.variance) / self.mean


def render(scene: dict, spp: int = 64, passes: int = 4, seed: int = 0, variant: str | None = None,
           progress=None) -> Estimate:
    """Render ``passes`` independent passes of spp/passes samples each.

    The variance of the mean is the sample variance across passes divided by their
    number (passes >= 2), so every estimate carries its own error bar.
    """
    if passes < 2:
        raise ValueError(f"passes must be >= 2 for a variance estimate, got {passes}")
    if spp < passes:
        raise ValueError(f"spp ({spp}) must be >= passes ({passes})")
    mi, loaded = load(scene, variant)
    per = spp // passes
    images = []
    for k in range(passes):
        img = np.array(mi.render(loaded, spp=per, seed=seed * 7919 + k), dtype=np.float64)
        images.append(img[..., :3])
        if progress is not None:
            progress(k + 1, passes)
    return Estimate.from_passes(images, per * passes)


#: Default kernel radius of the photon density estimate, m (pbr_tactile.photons.irradiance).
KERNEL_RADIUS_M = 0.75e-3


def render_photons(scene: dict, sources: list[dict], effects: Effects, photons: int = 1 << 20, spp: int = 4,
                   passes: int = 4, seed: int = 0, variant: str | None = None, progress=None,
                   kernel_radius: float = KERNEL_RADIUS_M, light_scene: dict | None = None,
                   pilot_scene: dict | None = None, no_contact_runs: int = 0, use_cache: bool = True) -> Estimate:
    """The two-pass photon estimator (pbr_tactile.photons), in independent passes.

    light_scene : the scene the photons are traced in, when it differs from the one the
        camera sees (Effects.contact_shadow off: the undeformed membrane). Its coating
        mesh must have the same vertices, in the same order, as the camera scene's: the
        irradiance maps are carried over vertex by vertex.
    pilot_scene : the scene the pilot pass (which sets the photons' weight window) runs
        in; default the light scene. Giving every contact the undeformed membrane here
        makes the window independent of the contact, so a contact and the no-contact
        frame rendered with the same seed share their random walks wherever the dent
        does not change them (common random numbers: low-noise change images).
    no_contact_runs : with a pilot_scene (the undeformed membrane), estimate each pass's
        map as the sensor's no-contact map plus the contact's change
        (``pbr_tactile.nocontact``): no_contact_runs no-contact runs per pass make that
        map. They are cached on disk (``use_cache``), so only the first contact of a
        sensor traces them; later contacts cost what they did without it, with less
        photon noise (see that module for what was measured). 0: off.

    Each pass traces its own photons and its own camera samples, so the variance across
    passes is that of the whole estimator. kernel_radius (m) is the photon density
    estimate's radius: its bias grows as radius^2 and its variance falls as 1/radius^2.
    The transport is grey, so each source's image is weighted by the film's exact
    response to that source's spectrum (pbr_tactile.spectra.film_response).
    """
    from .photons import (camera_pass, coating_areas, coating_vertices, density_kernel, deposits, irradiance,
                          sources_from, weight_window)
    from .spectra import film_response

    if effects.coating_gloss > 0:
        raise ValueError("the photon estimator needs a diffuse coating (coating_gloss = 0); use volpath")
    if passes < 2:
        raise ValueError(f"passes must be >= 2 for a variance estimate, got {passes}")
    if kernel_radius < 0:
        raise ValueError(f"kernel_radius must be >= 0 m, got {kernel_radius}")
    if no_contact_runs < 0:
        raise ValueError(f"no_contact_runs must be >= 0, got {no_contact_runs}")
    mi, loaded = load(scene, variant)
    if not mi.variant().startswith(("llvm_", "cuda_")):
        raise ValueError(f"the photon estimator needs a vectorised (llvm_ or cuda_) variant, got {mi.variant()}; "
                         "apt-get install libllvm19, or use the volpath estimator")
    def same_mesh(role: str, other: dict | None):
        """The loaded ``other`` scene (``loaded`` when None), checked to share the camera
        scene's coating vertices, in order: maps carry over vertex by vertex."""
        if other is None:
            return loaded
        scene_ = load(other, variant)[1]
        n_other, n_seen = len(coating_vertices(scene_)), len(coating_vertices(loaded))
        if n_other != n_seen:
            raise ValueError(f"{role}'s coating has {n_other} vertices but the camera scene's has {n_seen}: "
                             "both must be the same mesh, displaced")
        return scene_

    lit = same_mesh("light_scene", light_scene)
    srcs = sources_from(sources)
    # Pixel value per unit flux-normalised radiance: pi A_m times the film's response to
    # the source's radiance spectrum (flux = pi A L for a Lambertian sphere).
    response = np.stack([np.pi * 4 * np.pi * s["radius"] ** 2 * film_response(s["spectrum"], effects.camera_response)
                         for s in sources])
    sigma_t, albedo = effects.sigma_t, effects.albedo
    kernel = density_kernel(coating_vertices(lit), kernel_radius)
    area = coating_areas(lit)
    # A pilot pass (an eighth of the photons) sets the weight window that spreads the
    # deposits evenly over the coating. Its density is the kernel applied twice (about
    # 1.4 times as wide): E = K (K Phi) / K (K A).
    pilot_lit = lit if pilot_scene is None else same_mesh("pilot_scene", pilot_scene)
    pilot_kernel, pilot_area = kernel, area
    if pilot_lit is not lit:
        pilot_kernel, pilot_area = density_kernel(coating_vertices(pilot_lit), kernel_radius), coating_areas(pilot_lit)
    no_contact = None
    if no_contact_runs:
        if pilot_scene is None:
            raise ValueError("no_contact_runs needs pilot_scene, the undeformed membrane's scene")
        from .nocontact import NoContact

        no_contact = NoContact(mi, pilot_lit, [[(s.name, s.centre, s.radius, s.in_elastomer) for s in srcs],
                                               sigma_t, albedo, effects.coating_albedo, photons],
                               no_contact_runs, use_cache)
    pilot_seed = seed * 7919 + passes

    def trace(in_scene, count: int, run_seed: int, window_=None):
        return deposits(mi, in_scene, srcs, sigma_t, albedo, effects.coating_albedo, count, run_seed, window_)

    def trace_pilot():
        return trace(pilot_lit, max(1, photons // 8), pilot_seed)

    # With the no-contact cache, the pilot is cached too: it is a no-contact run.
    pilot_flux = trace_pilot() if no_contact is None else no_contact.flux(["pilot", pilot_seed], trace_pilot)
    pilot = irradiance((pilot_kernel @ pilot_flux.T).T, pilot_kernel @ pilot_area, pilot_kernel)
    window = weight_window(pilot, area, photons)
    images = []
    for k in range(passes):
        pass_seed = seed * 7919 + k
        traced = no_contact is None or lit is not pilot_lit  # else E_c = E_0: the map is G
        if traced:
            maps = irradiance(trace(lit, photons, pass_seed, window), area, kernel)
        if no_contact is not None:
            flux_0, flux_g = no_contact.pass_flux(pass_seed, pilot_seed,
                                                  lambda run_seed: trace(pilot_lit, photons, run_seed, window))
            no_contact_map = irradiance(flux_g, pilot_area, pilot_kernel)
            # G plus the contact's change, with the same random numbers.
            maps = no_contact_map + (maps - irradiance(flux_0, pilot_area, pilot_kernel) if traced else 0.0)
        per_source = camera_pass(mi, loaded, srcs, maps, sigma_t, albedo, effects.coating_albedo, spp, pass_seed)
        images.append(per_source @ response)
        if progress is not None:
            progress(k + 1, passes)
    return Estimate.from_passes(images, spp * passes)


def reference(
    depth: np.ndarray | None,
    ref_depth: np.ndarray | None,
    membrane,
    spec: SensorSpec,
    camera: Camera,
    effects: Effects = Effects(),
    spp: int = 64,
    width: int | None = None,
    height: int | None = None,
    seed: int = 0,
    variant: str | None = None,
    progress=None,
    passes: int = 4,
    estimator: str = "photons",
    photons: int = 1 << 20,
    kernel_radius: float = KERNEL_RADIUS_M,
    no_contact_runs: int = 0,
) -> Estimate:
    """Render what the sensor's camera sees for a contact depth map (None: no contact).

    estimator : "photons" (two-pass, converges fast; diffuse coating) or "volpath"
        (Mitsuba's brute-force volumetric path tracer).
    photons : photons per LED per pass, for the photon estimator.
    kernel_radius : the photon density estimate's radius, m (bias ~ radius^2).
    no_contact_runs : for a contact, estimate its photon map as the sensor's cached
        no-contact map plus the contact's change (``pbr_tactile.nocontact``), from this
        many no-contact runs per pass; worth it when rendering many contacts of one
        sensor (the first pays for the cache). 0: off.
    """
    if estimator not in ("photons", "volpath"):
        raise ValueError(f"estimator must be 'photons' or 'volpath', got {estimator!r}")
    if not effects.contact_shadow and estimator != "photons":
        raise ValueError("Effects(contact_shadow=False) needs the photon estimator: volpath cannot trace light "
                         "and camera paths in different geometry")
    if no_contact_runs < 0:
        raise ValueError(f"no_contact_runs must be >= 0, got {no_contact_runs}")
    solid = elastomer(membrane, spec, camera, depth, ref_depth)
    with tempfile.TemporaryDirectory(prefix="tactile-pbr-") as folder:
        meshes = write_meshes(solid, folder)
        scene = geltip_scene(meshes, spec, camera, effects, width, height, spp=spp, seed=seed)
        if estimator == "photons":
            light_scene = flat_scene = None
            if depth is not None:
                # The undeformed membrane sets the photons' weight window for every
                # contact (common random numbers with the no-contact frame) and, with
                # contact_shadow off, is what the light sees: no shadow, no guiding by
                # the dent; only the camera sees it.
                flat = write_meshes(elastomer(membrane, spec, camera), f"{folder}/undeformed")
                flat_scene = geltip_scene(flat, spec, camera, effects, width, height, spp=spp, seed=seed)
                if not effects.contact_shadow:
                    light_scene = flat_scene
            est = render_photons(scene, led_sources(spec, effects), effects, photons=photons,
                                 spp=max(1, spp // passes), passes=passes, seed=seed, variant=variant,
                                 progress=progress, kernel_radius=kernel_radius, light_scene=light_scene,
                                 pilot_scene=flat_scene, no_contact_runs=no_contact_runs if flat_scene else 0)
        else:
            est = render(scene, spp=spp, passes=passes, seed=seed, variant=variant, progress=progress)
    return sensor_effects(est, camera, effects, seed)


def sensor_effects(est: Estimate, camera: Camera, effects: Effects, seed: int = 0) -> Estimate:
    """Lens distortion, vignetting and sensor noise on the estimate (pbr_tactile.sensor).

    The variance stays that of the Monte Carlo estimate, carried through distortion and
    vignetting (a gain g scales it by g^2); sensor noise is part of the image, not of the
    estimator's error.
    """
    from .sensor import add_noise, distort, vignetting

    k1, k2 = effects.lens_distortion
    mean = vignetting(distort(est.mean, camera, k1, k2), camera, effects.vignetting)
    variance = distort(est.variance, camera, k1, k2)
    variance = vignetting(vignetting(variance, camera, effects.vignetting), camera, effects.vignetting)
    mean = add_noise(mean, effects.sensor_noise, np.random.default_rng(seed))
    return Estimate(mean.astype(np.float32), variance.astype(np.float32), est.spp)
