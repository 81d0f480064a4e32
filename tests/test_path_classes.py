"""Path classes of the photon pass (``deposits(classes=True)``) and the study that reads
them (``studies.path_classes``): the classes add up to the untagged pass, walk for walk;
a class whose event is switched off gets nothing; the shares' arithmetic by hand."""

from __future__ import annotations

import tempfile

import numpy as np
import pytest

from pbr_tactile.photons import PATH_CLASSES, PATH_EVENTS, path_class_events


def test_a_class_is_the_set_of_its_events():
    assert PATH_CLASSES == 2 ** len(PATH_EVENTS) == 16
    assert path_class_events(0) == ()
    assert path_class_events(1 | 4) == ("glass", "scattered")
    assert path_class_events(PATH_CLASSES - 1) == PATH_EVENTS
    for bad in (-1, PATH_CLASSES):
        with pytest.raises(ValueError, match=r"a path class must be in \[0, 16\)"):
            path_class_events(bad)


@pytest.fixture(scope="module")
def paint(mesh, spec, camera, photon_mi):
    """The default GelTip's undeformed scene, loaded, and its photon sources."""
    mi = photon_mi
    from pbr_tactile.effects import Effects
    from pbr_tactile.membrane import ElastomerBuilder
    from pbr_tactile.photons import sources_from
    from pbr_tactile.render import load
    from pbr_tactile.scene import geltip_scene, led_sources, write_meshes

    solid = ElastomerBuilder(mesh, spec, camera, 1e-3)()
    effects = Effects()
    with tempfile.TemporaryDirectory() as folder:
        scene = geltip_scene(write_meshes(solid, folder), spec, camera, effects, 8, 6, spp=1)
        loaded = load(scene, mi.variant())[1]
    return mi, loaded, sources_from(led_sources(spec, effects)), effects


def test_the_classes_add_up_to_the_untagged_pass_walk_for_walk(paint):
    from pbr_tactile.density import coating_areas
    from pbr_tactile.photons import deposits, weight_window

    mi, scene, srcs, fx = paint
    args = (mi, scene, srcs, fx.sigma_t, fx.albedo, fx.coating_albedo, 1 << 12)
    plain = deposits(*args, seed=3)
    tagged = deposits(*args, seed=3, classes=True)
    assert tagged.shape == (len(srcs), PATH_CLASSES, plain.shape[1])
    np.testing.assert_allclose(tagged.sum(axis=1), plain, rtol=1e-4, atol=1e-9 * plain.max())
    # with a weight window, split photons carry their class into the next generation
    area = coating_areas(scene)
    window = weight_window(plain / area, area, 1 << 12)
    plain_w = deposits(*args, seed=4, window=window)
    tagged_w = deposits(*args, seed=4, window=window, classes=True)
    np.testing.assert_allclose(tagged_w.sum(axis=1), plain_w, rtol=1e-4, atol=1e-9 * plain_w.max())
    # every class's flux is a sum of deposits, and some light arrives straight from an LED
    totals = tagged_w.sum(axis=(0, 2))
    assert totals[0] > 0 and all(totals[k] >= 0 for k in range(PATH_CLASSES))


def test_a_class_whose_event_cannot_happen_gets_nothing(paint):
    from pbr_tactile.photons import PAINTED, SCATTERED, deposits

    mi, scene, srcs, fx = paint
    clear = deposits(mi, scene, srcs, 0.0, fx.albedo, fx.coating_albedo, 1 << 12, seed=1, classes=True)
    scattered = [k for k in range(PATH_CLASSES) if k & SCATTERED]
    assert clear[:, scattered].sum() == 0 and clear.sum() > 0
    black = deposits(mi, scene, srcs, fx.sigma_t, fx.albedo, 0.0, 1 << 12, seed=1, classes=True)
    painted = [k for k in range(PATH_CLASSES) if k & PAINTED]
    assert black[:, painted].sum() == 0 and black.sum() > 0
    # the default GelTip's LEDs sit in the elastomer: some light reaches the paint straight
    assert clear[:, 0].sum() > 0


def test_class_shares_by_hand():
    from studies.path_classes import class_shares, event_shares

    V = 4
    area = np.ones(V)
    e_0 = np.zeros((PATH_CLASSES, V))
    e_0[0] = 1.0  # straight light, 1 per vertex
    e_0[5] = 3.0  # through the glass and scattered, 3 per vertex
    e_c = e_0.copy()
    e_c[0, :2] = 2.0  # the contact doubles the straight light on the region's first two vertices
    e_c[5, 0] = 2.0  # and takes 1 of the other class's off the first
    region = np.array([True, True, True, False])
    got = class_shares(e_0, e_c, area, region)
    assert got["whole"][0] == pytest.approx(0.25) and got["whole"][5] == pytest.approx(0.75)
    assert got["region"][0] == pytest.approx(0.25)
    # over the region's light (12): net +2 straight and -1 scattered
    assert got["signed"][0] == pytest.approx(2 / 12) and got["signed"][5] == pytest.approx(-1 / 12)
    assert got["absolute"][0] == pytest.approx(2 / 12) and got["absolute"][5] == pytest.approx(1 / 12)
    # over each class's own light in the region (3 and 9)
    assert got["relative"][0] == pytest.approx(2 / 3) and got["relative"][5] == pytest.approx(1 / 9)
    # the paint shows the sum: vertex 0 changes by +1 - 1 = 0, vertex 1 by +1
    assert got["contrast"] == pytest.approx(1 / 12) and got["net"] == pytest.approx(1 / 12)
    events = event_shares(got["absolute"])
    assert events["none"] == pytest.approx(2 / 12) and events["glass"] == pytest.approx(1 / 12)
    assert events["scattered"] == pytest.approx(1 / 12) and events["paint"] == 0.0
    with pytest.raises(ValueError, match=r"e_0 and e_c must be \(K, V\)"):
        class_shares(e_0, e_c[:, :3], area, region)


def test_the_geltip_contacts_sit_on_its_tip_dome_and_body(spec, camera, mesh):
    from scenes.camera import back_project, reference_depth
    from studies.path_classes import contact_pixels

    ref, _ = reference_depth(mesh, camera)
    pixels = contact_pixels(spec, camera, ref)
    assert set(pixels) == {"tip", "dome", "body"}
    assert pixels["tip"] == (camera.cx, camera.cy)
    z = {k: back_project(ref, camera)[int(round(v)), int(round(u)), 2] for k, (u, v) in pixels.items()}
    junction = spec.membrane.base_z + spec.membrane.cylinder_length
    assert z["tip"] > z["dome"] > junction > z["body"]


def test_a_bad_setting_is_refused_by_name_before_any_trace():
    from studies.path_classes import measure

    with pytest.raises(ValueError, match=r"effect setting 'paint_albedo=0.5': expected NAME=VALUE"):
        measure(photons=8, seeds=1, settings=["paint_albedo=0.5"])
    with pytest.raises(ValueError, match=r"Effects.coating_gloss must be in \[0, 1\], got 1.5"):
        measure(photons=8, seeds=1, settings=["coating_gloss=1.5"])


def test_bad_counts_and_sensors_are_refused_by_name(tmp_path, capsys):
    from studies.path_classes import main, measure

    with pytest.raises(ValueError, match=r"photons and seeds must be >= 1, got 0 and 2"):
        measure(photons=0, seeds=2)
    with pytest.raises(SystemExit):
        main(["--out", str(tmp_path), "--sensors", "geltip,paw"])
    assert "--sensors must be some of geltip, gelsight, got paw" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(["--out", str(tmp_path), "--sensors", "geltip,gelsight", "--spec", "any.toml"])
    assert "--spec replaces the spec of one sensor" in capsys.readouterr().err
    assert not any(tmp_path.iterdir())


def test_source_contrasts_by_hand():
    """Two LEDs brighten opposite vertices of a region: each source's own contrast is
    large while their summed change cancels, as two coloured channels would show it."""
    from studies.path_classes import class_shares, source_contrasts

    area = np.array([1.0, 1.0, 2.0])
    region = np.array([True, True, False])
    e_0 = np.array([[1.0, 1.0, 5.0], [2.0, 2.0, 5.0]])
    e_c = np.array([[1.5, 0.5, 9.0], [1.0, 3.0, 5.0]])
    got = source_contrasts(e_0, e_c, area, region)
    # source 0: |+0.5| + |-0.5| over 2; source 1: |+1| + |-1| over 4; the vertex outside is not counted
    np.testing.assert_allclose(got, [0.5, 0.5])
    summed = class_shares(e_0, e_c, area, region)  # the two sources as two classes of one light
    # summed, vertex 0 changes by +0.5 - 1 and vertex 1 by -0.5 + 1: a third of either source's
    assert summed["contrast"] == pytest.approx((abs(0.5 - 1) + abs(-0.5 + 1)) / 6)
    one = source_contrasts(e_0[:1], e_0[:1] + np.array([[0.0, 0.0, 1.0]]), area, region)
    assert one[0] == 0.0
    assert np.isnan(source_contrasts(np.zeros((1, 3)), np.ones((1, 3)), area, region)[0])
    with pytest.raises(ValueError, match=r"e_0 and e_c must be \(S, V\)"):
        source_contrasts(e_0, e_c[:, :2], area, region)
