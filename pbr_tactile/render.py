"""The physically based reference, depth map to image, as one chain:

    image = render(load(geltip_scene(write_meshes(elastomer(membrane, depth, ref)))))

1. ``elastomer``: the membrane refined, dented by the elastic layer model
   (scenes.elastic) and closed into the elastomer solid (pbr_tactile.membrane);
2. ``write_meshes`` and ``geltip_scene``: the scene as a plain dict (pbr_tactile.scene);
3. ``load``: the one call of ``mi.load_dict``, after ``to_mitsuba`` turns the dict's plain
   transforms and points into Mitsuba objects;
4. ``render_photons`` (photons from the LEDs to the coating, pbr_tactile.photons; their
   density, pbr_tactile.density; then camera rays, pbr_tactile.camera_pass) or ``render``
   (brute-force volpath): Monte Carlo estimates in independent passes (pbr_tactile.estimate:
   ``run_passes``, a fixed number or until the noise over the contact region,
   ``contact_rse`` over ``contact_region``, meets a target), giving the mean image and a
   per-pixel variance of that mean.
"""

from __future__ import annotations

import tempfile
from collections import OrderedDict
from dataclasses import dataclass, replace

import numpy as np

from scenes.camera import Camera, lens_resample
from scenes.spec import SensorSpec

from .effects import Effects
from .estimate import MAX_PASSES, Control, Estimate, check_passes, contact_region, run_passes
from .fluence import INSCATTER
from .membrane import ElastomerBuilder, _kept, shared_builder
from .paint import Paint
from .reweight import Perturbation, VariantEstimates, kish_ratio, variant_media
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


def load(scene: dict, variant: str | None = None, keep: bool = False):
    """The Mitsuba scene object of a plain scene dict (the one place that loads).

    keep : keep the loaded scene (the last KEPT_SCENES) and return it again for the same
        dict whose mesh files have the same size and modification time: the undeformed
        membrane's scene, which every contact loads (0.6 s a load on the GelTip).
    """
    mi = choose_variant(variant)
    if not keep:
        return mi, mi.load_dict(to_mitsuba(scene, mi))
    import os

    from scenes.cache import make_key

    files = sorted(v["filename"] for v in scene.values() if isinstance(v, dict) and "filename" in v)
    stamps = [[f, os.stat(f).st_size, os.stat(f).st_mtime_ns] for f in files]
    key = make_key(mi.variant(), scene, stamps)
    return mi, _kept(_scenes, key, lambda: mi.load_dict(to_mitsuba(scene, mi)), KEPT_SCENES)


#: Loaded scenes ``load(keep=True)`` keeps, the most recently used.
KEPT_SCENES = 2
_scenes: OrderedDict = OrderedDict()


def render(scene: dict, spp: int = 64, passes: int = 4, seed: int = 0, variant: str | None = None,
           progress=None, target_rse: float | None = None, region: np.ndarray | None = None,
           max_passes: int = MAX_PASSES) -> Estimate:
    """Brute-force volpath in independent passes of spp // passes samples each.

    The variance of the mean is the sample variance across passes divided by their
    number (passes >= 2), so every estimate carries its own error bar. With target_rse,
    ``passes`` is the fewest and more passes of the same size follow until the noise
    over ``region`` meets it (``run_passes``).
    """
    check_passes(passes, target_rse, max_passes)
    if spp < passes:
        raise ValueError(f"spp ({spp}) must be >= passes ({passes})")
    mi, loaded = load(scene, variant)
    per = spp // passes

    def one_pass(k: int) -> np.ndarray:
        return np.array(mi.render(loaded, spp=per, seed=seed * 7919 + k), dtype=np.float64)[..., :3]

    return run_passes(one_pass, per, passes, target_rse, region, max_passes, progress)


#: The full physical model (Effects is frozen: one shared default).
FULL_MODEL = Effects()
#: Default kernel radius of the photon density estimate, m (pbr_tactile.density.irradiance).
KERNEL_RADIUS_M = 0.75e-3


@dataclass(frozen=True)
class RenderSettings:
    """How ``reference`` estimates an image: what its cost and noise depend on, not what it
    shows (the sensor, the contact, the effects and the light are ``reference``'s own
    arguments). Checked when made; ValueError naming the setting.

    spp : samples per pixel in ``passes`` passes (spp // passes per pass).
    width, height : the film, px (None: the camera's).
    seed : the passes' seeds start here. variant : the Mitsuba variant (None: the default).
    passes : independent passes, or with target_rse the fewest.
    estimator : "photons" (two-pass, converges fast; matte or glossy paint) or "volpath"
        (Mitsuba's brute-force volumetric path tracer).
    photons : photons per LED per pass, for the photon estimator.
    kernel_radius : the photon density estimate's radius, m (bias ~ radius^2).
    no_contact_runs : estimate the photon map as the sensor's cached no-contact map plus
        the contact's change (``pbr_tactile.nocontact``), from this many no-contact runs
        per pass; worth it when rendering many contacts of one sensor (the first pays for
        the cache). Without contact the map is the cached no-contact map alone: a
        no-contact frame rendered with the contacts' seed and pass cap fills the cache
        they use. 0: off.
    target_rse : add passes of the same size until the RMS relative standard error over
        the contact region (``contact_region``: the dent and its rim; without contact
        the image circle) is at most this, or ``max_passes`` are done (``run_passes``).
    control_spp : camera samples per pixel of this render as a control variate for the
        contacts after it (``render_photons``; photons only).
    per_source : one grey image per source of ``led_sources(spec, effects)`` instead of
        RGB (``render_photons``; photons only).
    inscatter : how the photon estimator's camera finds the light its scattering events
        in the elastomer receive: "fluence" (the default: read it from the photons'
        fluence on the solid's voxel grid, ``pbr_tactile.fluence``; less noise, and the
        camera pass costs a fifth) or "split" (trace SCATTER_SPLIT paths on from the
        first event, with next-event estimates of the LEDs: the estimator before it).
    """

    spp: int = 64
    width: int | None = None
    height: int | None = None
    seed: int = 0
    variant: str | None = None
    passes: int = 4
    estimator: str = "photons"
    photons: int = 1 << 20
    kernel_radius: float = KERNEL_RADIUS_M
    no_contact_runs: int = 0
    target_rse: float | None = None
    max_passes: int = MAX_PASSES
    control_spp: int = 0
    per_source: bool = False
    inscatter: str = "fluence"

    def __post_init__(self):
        if self.estimator not in ("photons", "volpath"):
            raise ValueError(f"estimator must be 'photons' or 'volpath', got {self.estimator!r}")
        if self.no_contact_runs < 0:
            raise ValueError(f"no_contact_runs must be >= 0, got {self.no_contact_runs}")
        check_passes(self.passes, self.target_rse, self.max_passes)
        if self.inscatter not in INSCATTER:
            raise ValueError(f"inscatter must be one of {', '.join(map(repr, INSCATTER))}, got {self.inscatter!r}")
        if self.control_spp and self.estimator != "photons":
            raise ValueError("a control variate (control, control_spp) needs the photon estimator")
        if self.per_source and self.estimator != "photons":
            raise ValueError("per_source images need the photon estimator")


#: Stream of a control's extra camera samples (no pass seed maps to it).
CONTROL_STREAM = 0xC0C0


def source_response(sources: list[dict], effects: Effects) -> np.ndarray:
    """(S, 3): the pixel value per unit flux-normalised radiance of each source (see
    ``led_sources``): pi A_m times the film's response to the source's radiance spectrum
    (flux = pi A L for a Lambertian sphere)."""
    from .spectra import film_response

    return np.stack([np.pi * 4 * np.pi * s["radius"] ** 2 * film_response(s["spectrum"], effects.camera_response)
                     for s in sources])


def render_photons(scene: dict, sources: list[dict], effects: Effects, photons: int = 1 << 20, spp: int = 4,
                   passes: int = 4, seed: int = 0, variant: str | None = None, progress=None,
                   kernel_radius: float = KERNEL_RADIUS_M, light_scene: dict | None = None,
                   pilot_scene: dict | None = None, no_contact_runs: int = 0, use_cache: bool = True,
                   target_rse: float | None = None, region: np.ndarray | None = None, max_passes: int = MAX_PASSES,
                   no_contact_memo: dict | None = None, control: Control | None = None,
                   control_spp: int = 0, per_source: bool = False, fluence_grids: tuple | None = None,
                   perturb=None, streams=None):
    """The two-pass photon estimator (pbr_tactile.photons, module doc), in independent passes.

    spp : camera samples per pixel of one pass.
    passes : how many passes, or with target_rse the fewest: passes are added until the
        RMS relative standard error over ``region`` is at most target_rse, or
        ``max_passes`` are done (``run_passes``).
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
        photon noise (see that module for what was measured). 0: off. When pilot_scene
        is the camera's scene itself (a no-contact frame), each pass's map is the
        cached no-contact map alone.
    no_contact_memo : a dict of no-contact deposits by cache key, read before the disk
        cache and given every deposit used (``pbr_tactile.nocontact.NoContact``): pass an
        empty dict to collect them, or collected ones to render with no disk cache.
    control : the no-contact frame as an image-level control variate (``Control``,
        ``run_passes``), rendered with this seed, spp and pass cap.
    control_spp : > 0: return this render as a Control too (``Estimate.control``): the
        pass images as traced, and a mean that adds control_spp camera samples per pass
        (same photon map, other camera random numbers), the camera side being where a
        frame's rare bright samples are (LEDs seen through the glass).
    per_source : return one grey image per source instead of RGB: the mean is (H, W, S),
        ``sources``' order, per unit flux of each, before the film's response. The RGB
        image is that times ``source_response(sources, effects)`` (S, 3): the transport
        is linear in each source's power and grey, so a source's power and spectrum act
        only through its row (what calibration fits).
    fluence_grids : (the light scene's grid, the pilot scene's grid), ``FluenceGrid``s
        of one origin, voxel and shape (``ElastomerBuilder.grid``): the camera reads the
        light its scattering events receive from the photons' fluence (``pbr_tactile.
        fluence``) instead of splitting its paths there. Each pass's fluence is formed as
        its map is (with the no-contact cache: phi_G + phi_c - phi_0). None: split.
    perturb : a ``pbr_tactile.reweight.Perturbation`` or its (K, 3) array of variants
        (absorption_per_m, scattering_per_m, coating_albedo): each pass's photons are also
        re-weighted to each variant (``pbr_tactile.reweight``), whose maps and fluence are
        formed as the traced ones are (the no-contact runs carry the variants too, under
        their own cache key), and whose image is a camera pass with the variant's own
        sigma_t, albedo and paint (the pass's seed). Returns a
        ``pbr_tactile.reweight.VariantEstimates`` then: the traced Estimate (what this
        returns without it, for the same seed), one Estimate per variant from the same
        passes, and the variants' Kish ESS ratios over every deposit used. Not with a
        control variate (``control``, ``control_spp``); with a glossy paint, the medium's
        variants only (its flake lobe's map re-weighted as the flux is).
    streams : (S,) each source's place in a longer list of sources whose render this
        one stands beside (``pbr_tactile.photons.deposits``): its photons walk as they do
        there, so a render of the few sources a change touches pairs with the others'
        render of the whole list (common random numbers). None: 0 .. S - 1.

    The pilot's seed follows the last pass's (``passes``, or ``max_passes`` with a
    target), so a pass never shares its random numbers with the pilot, and every render
    of a seed and pass cap shares one pilot (and no-contact cache).

    Each pass traces its own photons and its own camera samples, so the variance across
    passes is that of the whole estimator. kernel_radius (m) is the photon density
    estimate's radius: its bias grows as radius^2 and its variance falls as 1/radius^2.
    The transport is grey, so each source's image is weighted by the film's exact
    response to that source's spectrum (pbr_tactile.spectra.film_response).
    """
    from .camera_pass import camera_pass, camera_views
    from .density import coating_areas, coating_vertices, density_kernel, irradiance
    from .photons import GlossyView, deposits, sources_from, weight_window
    from .streams import sampler_seed
    check_passes(passes, target_rse, max_passes)
    if kernel_radius < 0:
        raise ValueError(f"kernel_radius must be >= 0 m, got {kernel_radius}")
    if no_contact_runs < 0:
        raise ValueError(f"no_contact_runs must be >= 0, got {no_contact_runs}")
    if control_spp < 0:
        raise ValueError(f"control_spp must be >= 0, got {control_spp}")
    perturbation = None
    if perturb is not None:
        perturbation = Perturbation.of(perturb)
        if control is not None or control_spp:
            raise ValueError("perturb cannot be combined with a control variate (control, control_spp): the "
                             "control is the traced effects' no-contact frame, not the variants'")
        # refused before tracing (a glossy paint's albedo among them)
        perturbation.coefficients(effects.sigma_t, effects.albedo, effects.coating_albedo, effects.coating_gloss)
    grid_lit = grid_pilot = None
    if fluence_grids is not None:
        grid_lit, grid_pilot = fluence_grids
        if grid_lit.shape != grid_pilot.shape or grid_lit.voxel != grid_pilot.voxel or \
                not np.array_equal(grid_lit.origin, grid_pilot.origin):
            raise ValueError("fluence_grids must share one origin, voxel and shape (a contact's grid is its "
                             "undeformed grid re-measured where it moved: ElastomerBuilder.grid)")
    mi, loaded = load(scene, variant)
    if not mi.variant().startswith(("llvm_", "cuda_")):
        raise ValueError(f"the photon estimator needs a vectorised (llvm_ or cuda_) variant, got {mi.variant()}; "
                         "apt-get install libllvm19, or use the volpath estimator")
    def same_mesh(role: str, other: dict | None):
        """The loaded ``other`` scene (``loaded`` when None or the camera's scene), checked
        to share the camera scene's coating vertices, in order: maps carry over vertex by
        vertex."""
        if other is None or other is scene:
            return loaded
        scene_ = load(other, variant, keep=True)[1]
        n_other, n_seen = len(coating_vertices(scene_)), len(coating_vertices(loaded))
        if n_other != n_seen:
            raise ValueError(f"{role}'s coating has {n_other} vertices but the camera scene's has {n_seen}: "
                             "both must be the same mesh, displaced")
        return scene_

    lit = same_mesh("light_scene", light_scene)
    srcs = sources_from(sources)
    response = np.eye(len(sources)) if per_source else source_response(sources, effects)
    sigma_t, albedo = effects.sigma_t, effects.albedo
    paint = Paint.from_effects(effects)
    area = coating_areas(lit)
    # A pilot pass (an eighth of the photons) sets the weight window that spreads the
    # deposits evenly over the coating. Its density is the kernel applied twice (about
    # 1.4 times as wide): E = K (K Phi) / K (K A).
    pilot_lit = lit if pilot_scene is None else same_mesh("pilot_scene", pilot_scene)
    if pilot_lit is lit:
        kernel = pilot_kernel = density_kernel(coating_vertices(lit), kernel_radius)
        pilot_area = area
    else:
        # The undeformed membrane's kernel first: a contact's is it, changed where the dent moved.
        flat = coating_vertices(pilot_lit)
        pilot_kernel, pilot_area = density_kernel(flat, kernel_radius), coating_areas(pilot_lit)
        kernel = density_kernel(coating_vertices(lit), kernel_radius, like=(flat, pilot_kernel))
    # A glossy paint's lobe map weighs each arrival towards where the camera sees its
    # vertex from: the contact's camera scene's views, and the undeformed scene's for the
    # no-contact runs (they differ only where the dent moved).
    view = view_0 = None
    if paint.glossy:
        view = camera_views(mi, loaded)
        view_0 = view if pilot_lit is loaded else camera_views(mi, pilot_lit)
    no_contact = None
    if no_contact_runs:
        if pilot_scene is None:
            raise ValueError("no_contact_runs needs pilot_scene, the undeformed membrane's scene")
        from .nocontact import NoContact

        # The views to 3 decimals: the last bits of their atomic sums vary from run to run.
        viewed = [] if view_0 is None else [np.round(view_0.toward, 3), np.round(view_0.normal, 3)]
        # The variants' runs are their own entries (the traced parts too: one run holds both).
        varied = [] if perturbation is None else ["perturb", perturbation.key()]
        varied += [] if streams is None else ["streams", [int(k) for k in streams]]
        no_contact = NoContact(mi, pilot_lit, [[s.key() for s in srcs],
                                               sigma_t, albedo, *paint.key(), photons, *viewed, *varied],
                               no_contact_runs, use_cache, no_contact_memo, grid_pilot)
    pilot_seed = seed * 7919 + (passes if target_rse is None else max_passes)
    parts = ("flux",) + (() if grid_lit is None else ("track",)) + (() if view is None else ("lobe",))
    if perturbation is not None:  # the variants' flux (K, S, V), tracks (K, S, N), deposit moments, lobe (K, S, V)
        parts += ("variant_flux",) + (() if grid_lit is None else ("variant_track",)) + ("moments",) \
            + (() if view is None else ("variant_lobe",))

    def trace(in_scene, count: int, run_seed: int, window_=None, grid=None, seen=None, reweigh=True):
        """The deposits' parts: flux, the tracks with a grid, the lobe's flux with a view;
        with variants (``reweigh``), theirs."""
        lobe = None if seen is None else GlossyView(seen.toward, seen.normal)
        varied = perturbation if reweigh else None
        out = deposits(mi, in_scene, srcs, sigma_t, albedo, paint, count, run_seed, window_, grid, glossy=lobe,
                       perturb=varied, streams=streams)
        if varied is not None:
            out, reweighted = out
        out = (out,) if grid is None else tuple(out)
        out += () if lobe is None else (lobe.flux,)
        if varied is not None:
            out += (reweighted.flux,) + (() if grid is None else (reweighted.track,)) + (reweighted.moments,) \
                + (() if lobe is None else (reweighted.lobe,))
        return out

    def trace_pilot():
        return trace(pilot_lit, max(1, photons // 8), pilot_seed, reweigh=False)[0]

    # With the no-contact cache, the pilot is cached too: it is a no-contact run.
    pilot_flux = trace_pilot() if no_contact is None else no_contact.flux(["pilot", pilot_seed], trace_pilot)["flux"]
    pilot = irradiance((pilot_kernel @ pilot_flux.T).T, pilot_kernel @ pilot_area, pilot_kernel)
    window = weight_window(pilot, area, photons)
    traced = no_contact is None or lit is not pilot_lit  # else E_c = E_0: the map is G

    def no_contact_run(run_seed: int):
        """A no-contact run's parts, as NoContact takes them (one array where there is one)."""
        out = trace(pilot_lit, photons, run_seed, window, grid_pilot, view_0)
        return out[0] if len(out) == 1 else out

    def one_pass(k: int) -> np.ndarray:
        pass_seed = seed * 7919 + k
        phi = lobe_map = None
        # Per variant: its maps, fluence and lobe maps, formed as the traced ones are.
        variant_maps, variant_phi, variant_lobe = [None] * len(media), [None] * len(media), [None] * len(media)
        if traced:
            got = dict(zip(parts, trace(lit, photons, pass_seed, window, grid_lit, view)))
            maps = irradiance(got["flux"], area, kernel)
            if grid_lit is not None:
                phi = grid_lit.fluence(got["track"])
            if view is not None:
                lobe_map = irradiance(got["lobe"], area, kernel)
            for v in range(len(media)):
                variant_maps[v] = irradiance(got["variant_flux"][v], area, kernel)
                if grid_lit is not None:
                    variant_phi[v] = grid_lit.fluence(got["variant_track"][v])
                if view is not None:
                    variant_lobe[v] = irradiance(got["variant_lobe"][v], area, kernel)
            if media:
                moments.append(got["moments"])
        if no_contact is not None:
            same, runs = no_contact.pass_flux(pass_seed, pilot_seed, no_contact_run, parts)

            def map_of(deposited):
                return irradiance(deposited, pilot_area, pilot_kernel)

            # G plus the contact's change, with the same random numbers.
            maps = map_of(runs["flux"]) + (maps - map_of(same["flux"]) if traced else 0.0)
            if grid_pilot is not None:
                phi = grid_pilot.fluence(runs["track"]) + (phi - grid_pilot.fluence(same["track"]) if traced else 0.0)
            if view is not None:
                lobe_map = map_of(runs["lobe"]) + (lobe_map - map_of(same["lobe"]) if traced else 0.0)
            for v in range(len(media)):
                variant_maps[v] = map_of(runs["variant_flux"][v]) + (
                    variant_maps[v] - map_of(same["variant_flux"][v]) if traced else 0.0)
                if grid_pilot is not None:
                    variant_phi[v] = grid_pilot.fluence(runs["variant_track"][v]) + (
                        variant_phi[v] - grid_pilot.fluence(same["variant_track"][v]) if traced else 0.0)
                if view is not None:
                    variant_lobe[v] = map_of(runs["variant_lobe"][v]) + (
                        variant_lobe[v] - map_of(same["variant_lobe"][v]) if traced else 0.0)
            if media:
                moments.append(runs["moments"])
        fluence = None if phi is None else (grid_lit, phi)
        image = camera_pass(mi, loaded, srcs, maps, sigma_t, albedo, paint, spp, pass_seed,
                            fluence=fluence, glossy_maps=lobe_map) @ response
        # Each variant's camera pass: its own medium and paint, the pass's seed.
        for v, (sigma_t_v, albedo_v, rho_v) in enumerate(media):
            variant_images[v].append(camera_pass(
                mi, loaded, srcs, variant_maps[v], sigma_t_v, albedo_v, replace(paint, albedo=rho_v), spp, pass_seed,
                fluence=None if variant_phi[v] is None else (grid_lit, variant_phi[v]),
                glossy_maps=variant_lobe[v]) @ response)
        if not control_spp:
            return image
        as_traced.append(image)
        more = camera_pass(mi, loaded, srcs, maps, sigma_t, albedo, paint, control_spp,
                           sampler_seed(pass_seed, CONTROL_STREAM), fluence=fluence, glossy_maps=lobe_map) @ response
        return (spp * image + control_spp * more) / (spp + control_spp)

    as_traced: list[np.ndarray] = []
    media = [] if perturbation is None else variant_media(perturbation)  # (sigma_t, albedo, rho) per variant
    variant_images: list[list[np.ndarray]] = [[] for _ in media]
    moments: list[np.ndarray] = []  # the deposits' moments of every trace the passes used
    est = run_passes(one_pass, spp, passes, target_rse, region, max_passes, progress, control)
    if control_spp:
        est = replace(est, spp=est.spp + control_spp * est.passes,
                      control=Control(np.stack(as_traced).astype(np.float32), est.mean, est.variance))
    if perturbation is None:
        return est
    return VariantEstimates(est, tuple(Estimate.from_passes(images, spp * len(images)) for images in variant_images),
                            perturbation, kish_ratio(np.sum(np.asarray(moments, np.float64), axis=0)))


def reference(
    depth: np.ndarray | None,
    ref_depth: np.ndarray | None,
    membrane,
    spec: SensorSpec,
    camera: Camera,
    effects: Effects = FULL_MODEL,
    settings: RenderSettings = RenderSettings(),
    *,
    led_power=1.0,
    perturb=None,
    control: Control | None = None,
    solids: ElastomerBuilder | None = None,
    no_contact_memo: dict | None = None,
    only=None,
    progress=None,
):
    """Render what the sensor's camera sees for a contact depth map (None: no contact),
    estimated as ``settings`` say (``RenderSettings``).

    led_power : each LED's radiance scale, one for all or one per LED (``led_sources``).
    perturb : variants of (absorption_per_m, scattering_per_m, coating_albedo) re-weighted
        from the same photons (``render_photons``; photons only): returns a
        ``pbr_tactile.reweight.VariantEstimates``, each estimate through the sensor effects.
    control : the no-contact frame as a control variate for this contact (see
        ``render_photons``; photons only).
    solids : the membrane's ElastomerBuilder, kept across contacts (it refines the
        membrane and checks its undeformed solid once); None: ``shared_builder``'s.
    no_contact_memo : see ``render_photons``.
    only : the places of the sources to render in ``led_sources``' list (photons and
        per_source only): the image holds those sources, each traced with the random
        numbers it has in a render of the whole list (``render_photons``' streams), so
        it pairs with that render where a change touches only them (a leak's cone).
    """
    s = settings
    if not effects.contact_shadow and s.estimator != "photons":
        raise ValueError("Effects(contact_shadow=False) needs the photon estimator: volpath cannot trace light "
                         "and camera paths in different geometry")
    if effects.core_leak_cone_rad > 0 and effects.core_light_leak > 0 and s.estimator != "photons":
        raise ValueError("Effects(core_leak_cone_rad > 0) needs the photon estimator: the scene's emitters are "
                         "Lambertian spheres, and only the photon pass aims the leak's light up the tube")
    if control is not None and s.estimator != "photons":
        raise ValueError("a control variate (control, control_spp) needs the photon estimator")
    if perturb is not None and s.estimator != "photons":
        raise ValueError("perturb (re-weighted variants) needs the photon estimator")
    sources = led_sources(spec, effects, led_power)
    if only is not None:
        only = tuple(int(k) for k in only)
        if s.estimator != "photons" or not s.per_source:
            raise ValueError("only (a subset of the sources) needs the photon estimator and per_source images")
        if not only or len(set(only)) != len(only) or not all(0 <= k < len(sources) for k in only):
            raise ValueError(f"only must name distinct places among the {len(sources)} sources, got {list(only)}")
        sources = [sources[k] for k in only]
    spp, width, height, seed, variant, passes = s.spp, s.width, s.height, s.seed, s.variant, s.passes
    estimator, target_rse, max_passes, inscatter = s.estimator, s.target_rse, s.max_passes, s.inscatter
    region = None if target_rse is None else contact_region(depth, ref_depth, camera, width, height)
    targets = {"target_rse": target_rse, "region": region, "max_passes": max_passes}
    build = solids if solids is not None else shared_builder(membrane, spec, camera)
    solid = build(depth, ref_depth)
    with tempfile.TemporaryDirectory(prefix="tactile-pbr-") as folder:
        meshes = write_meshes(solid, folder, spec.membrane.glass_wall)
        scene = geltip_scene(meshes, spec, camera, effects, width, height, spp=spp, seed=seed, led_power=led_power)
        if estimator == "photons":
            light_scene = flat_scene = None
            if depth is not None:
                # The undeformed membrane sets the photons' weight window for every
                # contact (common random numbers with the no-contact frame) and, with
                # contact_shadow off, is what the light sees: no shadow, no guiding by
                # the dent; only the camera sees it.
                flat = build.meshes(spec.membrane.glass_wall)
                flat_scene = geltip_scene(flat, spec, camera, effects, width, height, spp=spp, seed=seed,
                                          led_power=led_power)
                if not effects.contact_shadow:
                    light_scene = flat_scene
            elif s.no_contact_runs:
                flat_scene = scene  # the no-contact frame: its map is the cached one
            grids = None
            if inscatter == "fluence":
                flat_grid = build.grid()
                grids = (build.grid(depth, ref_depth) if light_scene is None else flat_grid, flat_grid)
            est = render_photons(scene, sources, effects, photons=s.photons,
                                 spp=max(1, spp // passes), passes=passes, seed=seed, variant=variant,
                                 progress=progress, kernel_radius=s.kernel_radius, light_scene=light_scene,
                                 pilot_scene=flat_scene, no_contact_runs=s.no_contact_runs if flat_scene else 0,
                                 no_contact_memo=no_contact_memo, control=control, control_spp=s.control_spp,
                                 per_source=s.per_source, fluence_grids=grids, perturb=perturb, streams=only,
                                 **targets)
        else:
            est = render(scene, spp=spp, passes=passes, seed=seed, variant=variant, progress=progress, **targets)
    if isinstance(est, VariantEstimates):
        return replace(est, traced=sensor_effects(est.traced, camera, effects, seed),
                       variants=tuple(sensor_effects(e, camera, effects, seed) for e in est.variants))
    return sensor_effects(est, camera, effects, seed)


def sensor_effects(est: Estimate, camera: Camera, effects: Effects, seed: int = 0) -> Estimate:
    """The camera's lens, then lens distortion, vignetting and sensor noise on the
    estimate (pbr_tactile.sensor).

    Mitsuba renders the lens' pinhole cover (``Camera.pinhole_cover``; the camera itself
    where it is a centred pinhole), which ``lens_resample`` reads into the lens' pixels.
    The variance stays that of the Monte Carlo estimate, carried through distortion and
    vignetting (a gain g scales it by g^2); sensor noise is part of the image, not of the
    estimator's error.
    """
    from .sensor import add_noise, distort, vignetting

    lens = camera.scaled(est.mean.shape[1], est.mean.shape[0])
    cover = lens.pinhole_cover()
    if cover is not lens:
        est = replace(est, mean=lens_resample(est.mean, lens, cover), variance=lens_resample(est.variance, lens, cover))
    k1, k2 = effects.lens_distortion
    mean = vignetting(distort(est.mean, camera, k1, k2), camera, effects.vignetting)
    variance = distort(est.variance, camera, k1, k2)
    variance = vignetting(vignetting(variance, camera, effects.vignetting), camera, effects.vignetting)
    mean = add_noise(mean, effects.sensor_noise, np.random.default_rng(seed))
    return replace(est, mean=mean.astype(np.float32), variance=variance.astype(np.float32))
