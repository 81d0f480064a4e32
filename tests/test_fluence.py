"""The elastomer's fluence grid and the camera's in-scattered light read from it."""

from __future__ import annotations

import time

import numpy as np
import pytest
import trimesh

from pbr_tactile.effects import Effects
from pbr_tactile.fluence import MIN_FRACTION, FluenceGrid, fluence_grid


def test_the_grid_measures_a_shells_volume_voxel_by_voxel():
    """A tube wall (annulus) 2.5 mm thick, about the GelTip's elastomer: the voxels' summed
    elastomer volume is the wall's, and no voxel holds more than its own volume."""
    shell = trimesh.creation.annulus(r_min=9e-3, r_max=11.5e-3, height=20e-3, sections=256)
    grid = fluence_grid(shell, voxel=0.5e-3)
    exact = np.pi * (11.5e-3**2 - 9e-3**2) * 20e-3
    assert grid.volume.sum() == pytest.approx(exact, rel=0.01)
    assert grid.volume.max() <= grid.voxel**3 * (1 + 1e-12) and grid.volume.min() >= 0
    # Voxels well inside the wall are whole, those well inside the bore empty.
    centre = grid.origin + (np.argwhere(np.ones(grid.shape, bool)) + 0.5) * grid.voxel
    radius = np.hypot(centre[:, 0], centre[:, 1]).reshape(grid.shape)
    middle = np.abs(centre[:, 2].reshape(grid.shape)) < 9e-3
    assert np.all(grid.volume[(radius > 9.5e-3) & (radius < 11e-3) & middle] == grid.voxel**3)
    assert np.all(grid.volume[radius < 8.5e-3] == 0)


def test_a_local_change_remeasures_only_the_voxels_it_overlaps():
    shell = trimesh.creation.annulus(r_min=9e-3, r_max=11.5e-3, height=20e-3, sections=128)
    grid = fluence_grid(shell, voxel=0.5e-3)
    dented = shell.copy()
    moved = dented.vertices[:, 0] > 11.4e-3  # the outer wall's vertices on +x
    dented.vertices[moved, 0] -= 1e-3
    # The change: every face with a moved vertex, before and after.
    changed = np.unique(shell.faces[moved[shell.faces].any(axis=1)])
    corners = np.concatenate([shell.vertices[changed], dented.vertices[changed]])
    bounds = np.array([corners.min(0), corners.max(0)])
    local = fluence_grid(dented, like=grid, within=bounds)
    whole = fluence_grid(dented, voxel=0.5e-3)
    assert np.array_equal(local.volume, whole.volume)
    # The dent only took material away: measuring only the voxels that had some is the same.
    assert np.array_equal(fluence_grid(dented, like=grid, within=bounds, shrinks=True).volume, whole.volume)
    # A change outside the grid changes nothing.
    assert np.array_equal(fluence_grid(dented, like=grid, within=bounds + 1.0).volume, grid.volume)
    assert local.volume.sum() < grid.volume.sum()
    # Each moved face's own box (before and after) instead of their bounds: the voxels no
    # box meets keep their volumes, and the grid is the same.
    faces = shell.faces[moved[shell.faces].any(axis=1)]
    both = np.concatenate([shell.vertices[faces], dented.vertices[faces]], axis=1)
    boxes = np.stack([both.min(axis=1), both.max(axis=1)], axis=1)
    assert np.array_equal(fluence_grid(dented, like=grid, within=boxes, shrinks=True).volume, whole.volume)
    # A box that holds a voxel's corner on its face re-measures that voxel's neighbours too.
    corner = grid.origin + np.array([30, 24, 20]) * grid.voxel
    met = fluence_grid(dented, like=grid, within=np.array([[corner, corner]]))
    assert np.array_equal(met.volume, grid.volume)  # nothing there moved: measured again, the same
    with pytest.raises(ValueError, match="within"):
        fluence_grid(dented, like=grid)
    with pytest.raises(ValueError, match=r"within must be \(2, 3\) bounds or \(K, 2, 3\) boxes"):
        fluence_grid(dented, like=grid, within=np.zeros((3, 3)))


def test_bad_grids_are_refused():
    box = trimesh.creation.box((1e-2, 1e-2, 1e-2))
    with pytest.raises(ValueError, match="voxel"):
        fluence_grid(box, voxel=0.0)
    open_box = box.copy()
    open_box.update_faces(np.arange(len(box.faces)) > 0)
    with pytest.raises(ValueError, match="watertight"):
        fluence_grid(open_box)


def test_fluence_is_the_tracks_over_the_elastomers_volume():
    voxel = 1e-3
    volume = np.array([1.0, 0.5, 0.01, 0.0]).reshape(1, 1, 4) * voxel**3
    grid = FluenceGrid(np.zeros(3), voxel, volume)
    track = np.array([[2e-9, 2e-9, 2e-9, 2e-9]])
    phi = grid.fluence(track)
    assert phi.shape == (1, 4)
    np.testing.assert_allclose(phi[0, :2], [2e-9 / voxel**3, 4e-9 / voxel**3])
    assert phi[0, 2] == pytest.approx(2e-9 / (MIN_FRACTION * voxel**3))  # a sliver: the floor
    assert phi[0, 3] == 0.0  # no elastomer
    with pytest.raises(ValueError, match=r"track must be \(sources, 4\)"):
        grid.fluence(track[:, :3])
    with pytest.raises(ValueError, match="track must be"):
        grid.fluence(track[0])


def test_a_fluence_of_the_wrong_shape_is_refused_before_any_tracing(spec):
    """camera_pass checks the fluence against its sources and grid first: no scene or
    Mitsuba module is touched (both are None here)."""
    from pbr_tactile.camera_pass import camera_pass
    from pbr_tactile.photons import sources_from
    from pbr_tactile.scene import led_sources

    srcs = sources_from(led_sources(spec, Effects()))
    grid = FluenceGrid(np.zeros(3), 1e-3, np.ones((2, 2, 2)) * 1e-9)
    with pytest.raises(ValueError, match=rf"fluence must be \(sources, voxels\) = \({len(srcs)}, 8\)"):
        camera_pass(None, None, srcs, np.zeros((len(srcs), 3)), 70.0, 0.7, 0.85, spp=1,
                    fluence=(grid, np.zeros((len(srcs), 7))))


@pytest.mark.slow
def test_in_scatter_from_the_fluence_agrees_with_the_split_estimator(tmp_path, mesh, spec, camera):
    """The same no-contact frame by both ways of finding the light the elastomer scatters
    towards the camera: split camera paths with next-event estimates, or the photons'
    fluence. Only that part differs (a scattering event is where the two walks part), so
    the frames agree to the fluence grid's bias, and the fluence's has far less noise."""
    pytest.importorskip("mitsuba", reason="Mitsuba 3 is not installed (pip install '.[pbr]')")
    from pbr_tactile.membrane import elastomer
    from pbr_tactile.camera_pass import camera_pass
    from pbr_tactile.density import coating_areas, coating_vertices, density_kernel, irradiance
    from pbr_tactile.estimate import Estimate, contact_rse
    from pbr_tactile.photons import deposits, sources_from
    from pbr_tactile.render import source_response
    from pbr_tactile.scene import geltip_scene, led_sources, write_meshes

    from test_pbr import _vectorised

    effects = Effects()
    solid = elastomer(mesh, spec, camera)
    scene = geltip_scene(write_meshes(solid, tmp_path), spec, camera, effects, 64, 48, spp=4)
    mi, loaded = _vectorised(scene)
    grid = fluence_grid(solid.solid())
    leds = led_sources(spec, effects)
    srcs, response = sources_from(leds), source_response(leds, effects)
    kernel = density_kernel(coating_vertices(loaded), 1.5e-3)
    area = coating_areas(loaded)
    args = (effects.sigma_t, effects.albedo, effects.coating_albedo)
    split, looked_up, seconds = [], [], {"split": 0.0, "fluence": 0.0}
    for k in range(4):
        flux, track = deposits(mi, loaded, srcs, *args, photons=1 << 17, seed=k, grid=grid)
        maps = irradiance(flux, area, kernel)
        t0 = time.perf_counter()
        split.append(camera_pass(mi, loaded, srcs, maps, *args, spp=16, seed=k) @ response)
        t1 = time.perf_counter()
        looked_up.append(camera_pass(mi, loaded, srcs, maps, *args, spp=16, seed=k,
                                     fluence=(grid, grid.fluence(track))) @ response)
        seconds["split"] += t1 - t0
        seconds["fluence"] += time.perf_counter() - t1
    split, looked_up = np.stack(split), np.stack(looked_up)
    circle = camera.scaled(64, 48).mask
    ratio = looked_up.mean(0)[circle].sum(0) / split.mean(0)[circle].sum(0)
    # Each pass's own error over the image circle: the RMS relative error of the mean of
    # the 4 passes, times sqrt(4).
    spread = {name: 2.0 * contact_rse(Estimate.from_passes(list(s), 16), circle)
              for name, s in (("split", split), ("fluence", looked_up))}
    print(f"fluence / split per channel {np.round(ratio, 4)}; per-pass RMS relative error {spread}; "
          f"camera seconds {seconds}")
    np.testing.assert_allclose(ratio, 1.0, atol=0.02)
    assert spread["fluence"] < spread["split"]


def test_a_contacts_grid_is_its_undeformed_grid_measured_again_where_it_moved(tmp_path, monkeypatch, mesh, spec,
                                                                              camera, ref, pressed):
    """ElastomerBuilder.grid: the undeformed grid is kept on disk, and a contact's equals
    the dented solid measured again everywhere, on the same voxels (coarse 2 mm voxels:
    the test is of what is re-measured, not of the voxel size)."""
    from pbr_tactile.membrane import ElastomerBuilder

    monkeypatch.setenv("TACTILE_SIM_CACHE", str(tmp_path / "cache"))
    build = ElastomerBuilder(mesh, spec, camera)
    flat = build.grid(voxel=2e-3)
    dented = build.grid(pressed, ref, voxel=2e-3)
    assert dented.shape == flat.shape and np.array_equal(dented.origin, flat.origin)
    everywhere = fluence_grid(build(pressed, ref).solid(), like=flat, within=np.array([[-1.0] * 3, [1.0] * 3]))
    np.testing.assert_array_equal(dented.volume, everywhere.volume)
    assert dented.volume.sum() < flat.volume.sum()  # the dent took elastomer away, and added none
    assert np.all(dented.volume <= flat.volume)
    assert build.grid(voxel=2e-3) is flat and build.grid(pressed, ref, voxel=2e-3) is dented  # kept
    # The contact's solid, its outer vertices moved in the undeformed welded solid, is the
    # one welding by position gives: the same triangles, in the same order, and closed.
    solid = build(pressed, ref)
    moved, welded = build.solid(solid), solid.solid()
    np.testing.assert_array_equal(moved.triangles, welded.triangles)
    assert moved.is_watertight and build.solid(solid) is moved
    # Another builder of the same membrane reads the undeformed grid from the disk cache.
    assert len(list((tmp_path / "cache").glob("fluence-grid-*.npz"))) == 1
    again = ElastomerBuilder(mesh, spec, camera).grid(voxel=2e-3)
    np.testing.assert_array_equal(again.volume, flat.volume)
    np.testing.assert_array_equal(again.origin, flat.origin)


def test_fluence_settings_are_checked_before_any_work(mesh, spec, camera):
    from pbr_tactile.plugin import options_from
    from pbr_tactile.render import RenderSettings, reference, render_photons

    with pytest.raises(ValueError, match="inscatter must be one of 'split', 'fluence', got 'voxels'"):
        reference(None, None, mesh, spec, camera, Effects(), RenderSettings(inscatter="voxels"))
    with pytest.raises(ValueError, match="option inscatter must be one of 'split', 'fluence', got 'nee'"):
        options_from({"inscatter": "nee"}, camera)
    assert options_from({}, camera)["inscatter"] == "fluence"
    a = FluenceGrid(np.zeros(3), 1e-3, np.ones((2, 2, 2)))
    b = FluenceGrid(np.full(3, 1e-3), 1e-3, np.ones((2, 2, 2)))
    with pytest.raises(ValueError, match="fluence_grids must share one origin, voxel and shape"):
        render_photons({}, [], Effects(), fluence_grids=(a, b))


@pytest.mark.slow
def test_a_contact_by_the_fluence_equals_the_split_estimator_inside_and_outside_its_region(
        tmp_path, monkeypatch, mesh, spec, camera, ref, pressed):
    """The dataset's way of rendering a contact (the no-contact control of the photon map,
    ``reference``) with both ways of finding the in-scattered light: per pixel, the two
    images agree within their stated errors (z = difference / its standard error), in the
    contact region and outside it, and the fluence's error is no larger. The split's
    per-pass images are heavy tailed (rare bright samples of LEDs seen through the glass),
    so its variance, read from 6 passes, is loose: the bounds on |z| allow for that."""
    from pbr_tactile.estimate import contact_region, contact_rse
    from pbr_tactile.render import RenderSettings, reference

    from test_pbr import _needs_vectorised_variant

    _needs_vectorised_variant()
    monkeypatch.setenv("TACTILE_SIM_CACHE", str(tmp_path / "cache"))
    width, height = 160, 120
    kw = {"spp": 96, "width": width, "height": height, "passes": 6, "photons": 1 << 17, "no_contact_runs": 2}
    est = {inscatter: reference(pressed, ref, mesh, spec, camera, Effects(),
                                RenderSettings(inscatter=inscatter, seed=3, **kw))
           for inscatter in ("split", "fluence")}
    region = contact_region(pressed, ref, camera, width, height)
    circle = camera.scaled(width, height).mask
    diff = est["fluence"].mean - est["split"].mean
    z = diff / np.sqrt(est["fluence"].variance + est["split"].variance)
    lit = (est["split"].mean > 0) & np.isfinite(z)
    for name, where in (("contact region", region), ("outside", circle & ~region)):
        zs = z[where[..., None] & lit]
        ratio = est["fluence"].mean[where].sum(0) / est["split"].mean[where].sum(0)
        print(f"{name}: {zs.size} pixel-channels, z mean {zs.mean():+.2f}, median |z| {np.median(np.abs(zs)):.2f}, "
              f"|z| > 4 {np.mean(np.abs(zs) > 4):.4f}; fluence / split {np.round(ratio, 4)}")
        assert zs.size > 100
        assert abs(zs.mean()) < 0.3 and np.median(np.abs(zs)) < 1.0
        assert np.mean(np.abs(zs) > 4) < 0.02
        np.testing.assert_allclose(ratio, 1.0, atol=0.02)
    rse = {k: contact_rse(e, region) for k, e in est.items()}
    print(f"contact RSE {rse}")
    # This bright contact's noise is mostly the photon map's, which both share (seen: 0.0621
    # split, 0.0625 fluence); the fluence's gain is on dim contacts and in time. Why 1.1:
    # each RSE is the root of a mean of per-pixel variances read from 6 passes (5 degrees of
    # freedom: relative error sqrt(2 / 5) each), over the region's n > 100 pixel-channels
    # (asserted above), so each is read to about sqrt(2 / 5) / (2 sqrt(n)) < 3.2 %, and their
    # ratio, were they independent, to < 4.5 %: 10 % is over 2 of those, and the shared
    # photon map makes the ratio's error smaller still. A fluence noisier by more fails.
    assert rse["fluence"] < 1.1 * rse["split"]


@pytest.mark.slow
def test_per_source_images_by_the_fluence_make_the_rgb_image(mesh, spec, camera, ref, pressed, monkeypatch, tmp_path):
    """The calibration's and the diagnosis' bases are per-source images rendered with the
    fluence lookup (the default of every reference render): weighted by each source's film
    response they are the RGB image of the same seed, with and without contact (the
    transport is linear in each source's power, and the fluence of a pass is per source)."""
    from pbr_tactile.render import RenderSettings, reference, source_response
    from pbr_tactile.scene import led_sources

    from test_pbr import _needs_vectorised_variant

    _needs_vectorised_variant()
    monkeypatch.setenv("TACTILE_SIM_CACHE", str(tmp_path / "cache"))
    effects = Effects(core_light_leak=0.5)  # the leaks are sources of the basis too
    response = source_response(led_sources(spec, effects), effects)
    for depth in (None, pressed):
        kw = {"spp": 4, "width": 40, "height": 30, "passes": 2, "photons": 1 << 12, "seed": 3, "no_contact_runs": 1}
        contact = () if depth is None else (depth, ref)
        per_source = reference(*(contact or (None, None)), mesh, spec, camera, effects,
                               RenderSettings(per_source=True, **kw))
        rgb = reference(*(contact or (None, None)), mesh, spec, camera, effects, RenderSettings(**kw))
        assert per_source.mean.shape == (30, 40, len(response))
        np.testing.assert_allclose(per_source.mean @ response, rgb.mean, rtol=0, atol=1e-6 * rgb.mean.max())
