"""The blind benchmark's described mechanisms (studies.gap.described): every one visible and
growing with strength, each against its analytic form, bad input refused, determinism, and
its independence from the rest of studies.gap."""

import ast
import math
import sys
from pathlib import Path

import numpy as np
import pytest

from studies.gap import described
from studies.gap.described import (
    BACKGROUNDS,
    DESCRIPTIONS,
    MECHANISMS,
    PARAM_NAMES,
    Described,
    camera_response,
    defocus_blur,
    division_maps,
    falloff_gain,
    fade_gain,
    mix_matrix,
    pillbox_kernel,
    sample_params,
    seat_matrix,
    softened_depth,
)

ROOT = Path(__file__).resolve().parents[1]

#: The catalogue's effects a mechanism may stand for.
CATALOGUE = {"camera_response", "path_attenuation", "vignetting", "blur_noise", "misalignment",
             "lens_distortion", "membrane_compliance"}
#: "Clearly visible": mean absolute change inside the image circle, linear RGB.
MIN_VISIBLE = 0.002


@pytest.fixture(scope="module")
def injector(spec, ref):
    return Described(spec, ref)


@pytest.fixture(scope="module")
def textured(camera):
    """A mid-grey image with structure (so that a blur or a warp shows), per-channel phases."""
    v, u = np.mgrid[0 : camera.height, 0 : camera.width]
    planes = [0.5 + 0.15 * np.sin(2 * np.pi * u / 23 + k) * np.cos(2 * np.pi * v / 17 + 2 * k) for k in range(3)]
    return np.stack(planes, axis=-1).astype(np.float32)


@pytest.fixture(scope="module")
def contact(camera, ref):
    """(depth, render): a 1.5 mm Gaussian dent, and a fake simulator whose image brightens
    with indentation (0.2 per mm)."""
    v, u = np.mgrid[0 : camera.height, 0 : camera.width]
    dent = 0.0015 * np.exp(-((u - 400.0) ** 2 + (v - 200.0) ** 2) / (2 * 30.0**2))
    depth = (ref - dent).astype(np.float32)

    def render(d):
        return np.repeat(np.clip(0.5 + 200.0 * (ref - d), 0.0, 1.0)[..., None], 3, axis=-1).astype(np.float32)

    return depth, render


def _plain(mechanism, textured, contact):
    depth, render = contact
    return render(depth) if mechanism == "soft_membrane" else textured


def _change(injector, mechanism, strength, seed, textured, contact):
    depth, render = contact
    plain = _plain(mechanism, textured, contact)
    out = injector.apply(plain, mechanism, sample_params(mechanism, strength, np.random.default_rng(seed)),
                         depth=depth, render=render)
    return out, float(np.abs(out - plain)[injector.camera.mask].mean())


# --- The tables -----------------------------------------------------------------------------

def test_tables_cover_every_mechanism():
    assert set(DESCRIPTIONS) == set(BACKGROUNDS) == set(PARAM_NAMES) == set(MECHANISMS)
    assert set(MECHANISMS.values()) <= CATALOGUE
    assert len(set(MECHANISMS.values())) == len(MECHANISMS)  # one mechanism per effect
    assert set(BACKGROUNDS.values()) <= {"solid", "real", "none"}
    assert all(len(text) > 80 for text in DESCRIPTIONS.values())


@pytest.mark.parametrize("mechanism", sorted(MECHANISMS))
def test_sample_params_keys_and_determinism(mechanism):
    a = sample_params(mechanism, 0.5, np.random.default_rng(7))
    b = sample_params(mechanism, 0.5, np.random.default_rng(7))
    assert a == b
    assert tuple(a) == PARAM_NAMES[mechanism]
    assert all(isinstance(v, float) and math.isfinite(v) for v in a.values())


def test_sample_params_draw_signs_and_directions():
    gammas = {sample_params("gamma_mix_gains", 0.5, np.random.default_rng(s))["gamma"] > 1 for s in range(20)}
    lambdas = {sample_params("barrel_lens", 0.5, np.random.default_rng(s))["lambda"] > 0 for s in range(20)}
    turns = {sample_params("seat_offset", 0.5, np.random.default_rng(s))["rotation_deg"] > 0 for s in range(20)}
    assert gammas == lambdas == turns == {True, False}


@pytest.mark.parametrize("strength", [0.0, 1.0])
def test_sample_params_ranges(strength):
    rng = np.random.default_rng(3)
    i = int(strength)
    p = sample_params("gamma_mix_gains", strength, rng)
    assert abs(p["gamma"] - 1) == pytest.approx(described.GAMMA_DEVIATION[i])
    assert all(abs(p[k]) <= described.MIX_OFFDIAGONAL_BOUND[i] for k in p if k.startswith("mix_"))
    assert all(abs(p[k] - 1) <= described.GAIN_DEVIATION_BOUND[i] for k in p if k.startswith("gain_"))
    p = sample_params("seat_offset", strength, rng)
    assert math.hypot(p["shift_x_px"], p["shift_y_px"]) == pytest.approx(described.SEAT_SHIFT_PX[i])
    assert abs(p["rotation_deg"]) == pytest.approx(described.SEAT_ROTATION_DEG[i])
    p = sample_params("lens_falloff", strength, rng)
    assert p["focal_scale"] == pytest.approx(described.FALLOFF_FOCAL_SCALE[i])
    assert math.hypot(p["axis_dx_px"], p["axis_dy_px"]) <= described.FALLOFF_AXIS_OFFSET_PX
    assert abs(sample_params("barrel_lens", strength, rng)["lambda"]) == pytest.approx(described.DIVISION_LAMBDA[i])
    assert sample_params("defocus", strength, rng)["radius_px"] == pytest.approx(described.DEFOCUS_RADIUS_PX[i])
    assert sample_params("axial_fade", strength, rng)["mu_per_m"] == pytest.approx(described.FADE_MU_PER_M[i])
    assert sample_params("soft_membrane", strength, rng)["factor"] == pytest.approx(described.SOFT_FACTOR[i])


# --- Every mechanism ------------------------------------------------------------------------

@pytest.mark.parametrize("mechanism", sorted(MECHANISMS))
def test_every_mechanism_visible_in_range(injector, mechanism, textured, contact):
    plain = _plain(mechanism, textured, contact)
    before = plain.copy()
    out, change = _change(injector, mechanism, 0.5, 1, textured, contact)
    assert out.shape == plain.shape and out.dtype == np.float32
    assert out.min() >= 0.0 and out.max() <= 1.0 and np.isfinite(out).all()
    assert change > MIN_VISIBLE, f"{mechanism}: mean |change| {change:.4f}"
    np.testing.assert_array_equal(plain, before)  # the input is not written to


@pytest.mark.parametrize("mechanism", sorted(MECHANISMS))
def test_strength_grows_the_change(injector, mechanism, textured, contact):
    for seed in (0, 1, 2):
        weak = _change(injector, mechanism, 0.0, seed, textured, contact)[1]
        strong = _change(injector, mechanism, 1.0, seed, textured, contact)[1]
        assert MIN_VISIBLE / 2 < weak < strong, f"{mechanism} seed {seed}: {weak:.4f} vs {strong:.4f}"


# --- Each against its analytic form ---------------------------------------------------------

def test_gamma_mix_gains_on_a_constant_image(injector, camera):
    colour = np.array([0.3, 0.5, 0.7])
    image = np.broadcast_to(colour, camera.shape + (3,)).astype(np.float32)
    p = {"gamma": 1.3, "mix_rg": 0.05, "mix_rb": -0.02, "mix_gr": 0.08, "mix_gb": 0.0, "mix_br": -0.07,
         "mix_bg": 0.03, "gain_r": 1.1, "gain_g": 0.9, "gain_b": 1.2}
    out = injector.apply(image, "gamma_mix_gains", p)
    # By hand: gamma first, then the mix (row: output), then the gains, then clip.
    c = [x**1.3 for x in colour]
    r = 1.1 * (c[0] + 0.05 * c[1] - 0.02 * c[2])
    g = 0.9 * (0.08 * c[0] + c[1] + 0.0 * c[2])
    b = 1.2 * (-0.07 * c[0] + 0.03 * c[1] + c[2])
    expected = np.clip([r, g, b], 0, 1)
    np.testing.assert_allclose(out[0, 0], expected, rtol=1e-6)
    np.testing.assert_allclose(out, np.broadcast_to(expected, out.shape), rtol=1e-6)
    assert mix_matrix(p)[2, 0] == -0.07 and mix_matrix(p)[0, 0] == 1.0


def test_camera_response_clips_and_is_identity_at_rest():
    image = np.random.default_rng(0).random((5, 7, 3)).astype(np.float32)
    np.testing.assert_allclose(camera_response(image, 1.0, np.eye(3), np.ones(3)), image, atol=1e-7)
    bright = camera_response(image, 1.0, np.eye(3), np.full(3, 10.0))
    assert bright.max() == 1.0
    with pytest.raises(ValueError, match="gamma"):
        camera_response(image, 0.0, np.eye(3), np.ones(3))


def test_axial_fade_follows_the_height(injector, camera, ref):
    image = np.full(camera.shape + (3,), 0.5, np.float32)
    mu, z0 = 30.0, described.FADE_START_M
    gain = injector.apply(image, "axial_fade", {"mu_per_m": mu, "z0_m": z0})[..., 0] / 0.5
    z = injector.axial_z
    on = camera.mask
    # z is the no-contact surface's camera-frame z: for a planar depth, the depth itself.
    np.testing.assert_allclose(z[on], ref[on], rtol=1e-6)
    low, high = on & (z <= z0), on & (z > z0)
    assert low.sum() > 1000 and high.sum() > 1000
    np.testing.assert_array_equal(gain[low], 1.0)
    np.testing.assert_array_equal(gain[~on], 1.0)  # off the membrane: untouched
    np.testing.assert_allclose(gain[high], np.exp(-mu * (z[high] - z0)), rtol=1e-5)
    order = np.argsort(z[high])
    assert np.all(np.diff(gain[high][order]) <= 1e-7) and gain[high].min() < 0.6


def test_fade_gain_is_one_off_the_membrane():
    z = np.array([np.nan, 0.01, 0.02, 0.03])
    np.testing.assert_allclose(fade_gain(z, 20.0, 0.02), [1.0, 1.0, 1.0, math.exp(-0.2)])


def test_lens_falloff_is_cos4_about_its_axis(injector, camera):
    image = np.full(camera.shape + (3,), 0.8, np.float32)
    dx, dy = 0.5, -2.5  # puts the axis on pixel (320, 237)
    p = {"focal_scale": 1.2, "axis_dx_px": dx, "axis_dy_px": dy}
    gain = injector.apply(image, "lens_falloff", p)[..., 1] / 0.8
    au, av = int(camera.cx + dx), int(camera.cy + dy)
    assert gain[av, au] == pytest.approx(1.0, abs=1e-6)
    assert gain.max() == pytest.approx(1.0, abs=1e-6)
    row = gain[av, au:]
    assert np.all(np.diff(row) < 0)
    column = gain[av::-1, au]
    assert np.all(np.diff(column) < 0)
    theta = math.atan(100.0 / (1.2 * camera.f))
    assert gain[av, au + 100] == pytest.approx(math.cos(theta) ** 4, rel=1e-5)
    assert falloff_gain((3, 3), (1.0, 1.0), 10.0)[1, 1] == 1.0


def test_defocus_preserves_a_constant_and_spreads_a_dot_over_the_disc(injector, camera):
    flat = np.full(camera.shape + (3,), 0.37, np.float32)
    np.testing.assert_allclose(injector.apply(flat, "defocus", {"radius_px": 3.0}), flat, atol=1e-6)
    for radius in (1.5, 2.5, 4.0):
        dot = np.zeros((41, 41), np.float32)
        dot[20, 20] = 1.0
        out = defocus_blur(dot, radius)
        assert out.sum() == pytest.approx(1.0, rel=1e-5)
        area = out.sum() / out.max()  # the disc's pixel area: its coverage, peak 1
        assert area == pytest.approx(math.pi * radius**2, rel=0.02)
        v, u = np.nonzero(out > 0)
        assert np.hypot(u - 20, v - 20).max() <= radius + 0.75  # nothing beyond the disc
        # Round: as wide across as down.
        np.testing.assert_allclose(out, out.T, atol=1e-7)
    assert pillbox_kernel(0.0).shape == (1, 1)


def test_defocus_keeps_channels_apart(injector, camera):
    image = np.zeros(camera.shape + (3,), np.float32)
    image[240, 320, 1] = 1.0
    out = injector.apply(image, "defocus", {"radius_px": 2.0})
    assert out[..., 0].max() == 0.0 and out[..., 2].max() == 0.0 and out[..., 1].sum() == pytest.approx(1.0, rel=1e-5)


def _centroid(image):
    v, u = np.mgrid[0 : image.shape[0], 0 : image.shape[1]]
    w = image.sum()
    return float((u * image).sum() / w), float((v * image).sum() / w)


def test_seat_offset_identity_shift_and_turn(injector, camera, textured):
    still = {"shift_x_px": 0.0, "shift_y_px": 0.0, "rotation_deg": 0.0}
    np.testing.assert_allclose(injector.apply(textured, "seat_offset", still), textured, atol=1e-6)

    image = np.zeros(camera.shape + (3,), np.float32)
    image[200, 300] = 1.0
    out = injector.apply(image, "seat_offset", {"shift_x_px": 7.0, "shift_y_px": -4.0, "rotation_deg": 0.0})
    v, u = np.unravel_index(np.argmax(out[..., 0]), camera.shape)
    assert (u, v) == (307, 196) and out[196, 307, 0] == pytest.approx(1.0, abs=1e-4)

    # A turn about the image centre: a dot 80 px right of it goes counter-clockwise on screen.
    cx, cy = camera.cx, camera.cy
    blob = np.zeros(camera.shape, np.float32)
    blob[int(cy) : int(cy) + 2, int(cx) + 80 : int(cx) + 82] = 1.0  # centred on (cx + 80, cy)
    turned = injector.apply(np.repeat(blob[..., None], 3, -1), "seat_offset",
                            {"shift_x_px": 0.0, "shift_y_px": 0.0, "rotation_deg": 3.0})[..., 0]
    a = math.radians(3.0)
    expected = (cx + 80 * math.cos(a), cy - 80 * math.sin(a))
    np.testing.assert_allclose(_centroid(turned), expected, atol=0.05)

    # Black where nothing maps.
    edge = injector.apply(np.ones_like(textured), "seat_offset", {"shift_x_px": 5.0, "shift_y_px": 0.0,
                                                                   "rotation_deg": 0.0})
    assert edge[:, :4].max() == 0.0 and edge[:, 6:].min() == pytest.approx(1.0)
    m = seat_matrix((0.0, 0.0), (1.0, 2.0), 90.0)
    np.testing.assert_allclose(m @ [1.0, 0.0, 1.0], [1.0, 1.0], atol=1e-12)  # (1, 0) -> (0, -1) + t


def test_barrel_lens_division_model(injector, camera, textured):
    np.testing.assert_allclose(injector.apply(textured, "barrel_lens", {"lambda": 0.0}), textured, atol=1e-6)

    cx, cy, f = camera.cx, camera.cy, camera.f
    for lam in (0.2, -0.2):
        map_u, map_v = division_maps(camera.shape, (cx, cy), f, lam)
        u, v = 500, 100
        r_d = math.hypot(u - cx, v - cy) / f
        scale = 1.0 / (1.0 + lam * r_d**2)
        assert map_u[v, u] == pytest.approx(cx + (u - cx) * scale, abs=1e-3)
        assert map_v[v, u] == pytest.approx(cy + (v - cy) * scale, abs=1e-3)

        # The centre stays put: a block symmetric about it keeps its centroid.
        block = np.zeros(camera.shape + (3,), np.float32)
        block[int(cy) - 1 : int(cy) + 3, int(cx) - 1 : int(cx) + 3] = 1.0
        out = injector.apply(block, "barrel_lens", {"lambda": lam})[..., 0]
        np.testing.assert_allclose(_centroid(out), (cx, cy), atol=1e-3)

        # A dot at r_u in the simulation shows at the r_d that solves r_d / (1 + lam r_d^2) = r_u.
        blob = np.zeros(camera.shape, np.float32)
        blob[int(cy) : int(cy) + 2, int(cx) + 150 : int(cx) + 152] = 1.0  # centred on (cx + 150, cy)
        r_u = 150.0 / f
        r_d = (1 - math.sqrt(1 - 4 * lam * r_u**2)) / (2 * lam * r_u)
        out = injector.apply(np.repeat(blob[..., None], 3, -1), "barrel_lens", {"lambda": lam})[..., 0]
        u, v = _centroid(out)
        assert u == pytest.approx(cx + f * r_d, abs=0.3) and v == pytest.approx(cy, abs=1e-3)
        assert (u > cx + 150) == (lam > 0)  # pincushion pushes outwards, barrel pulls in

    # Beyond a barrel's fold, black.
    corner = injector.apply(np.ones_like(textured), "barrel_lens", {"lambda": -0.5})
    assert corner[0, 0].max() == 0.0 and corner[int(cy), int(cx)].min() == pytest.approx(1.0)


def test_soft_membrane_renders_a_shallower_contact(injector, camera, ref):
    v, u = np.mgrid[0 : camera.height, 0 : camera.width]
    dent = 0.002 * np.exp(-((u - 300.0) ** 2 + (v - 260.0) ** 2) / (2 * 25.0**2))
    bulge = 0.0005 * ((u - 150.0) ** 2 + (v - 240.0) ** 2 < 20**2)
    depth = (ref - dent + bulge).astype(np.float32)
    seen = []

    def render(d):
        seen.append(d.copy())
        return np.repeat(d[..., None], 3, axis=-1).astype(np.float32)

    factor = 0.6
    image = render(depth)
    seen.clear()
    out = injector.apply(image, "soft_membrane", {"factor": factor}, depth=depth, render=render)
    assert len(seen) == 1
    passed = seen[0]
    assert passed.shape == camera.shape and passed.dtype == depth.dtype
    r, d = ref.astype(np.float64), depth.astype(np.float64)
    expected = np.where(r - d > 0, r - factor * (r - d), d)
    np.testing.assert_allclose(passed, expected, atol=1e-8)
    dented = dent > 1e-4
    assert np.all(passed[dented] > depth[dented])  # shallower where pressed
    np.testing.assert_array_equal(passed[bulge > 0], depth[bulge > 0])  # a bulge is no imprint
    np.testing.assert_allclose(out[..., 0], passed, atol=1e-7)
    np.testing.assert_allclose(softened_depth(depth, ref, 1.0), depth, atol=1e-9)
    np.testing.assert_allclose(softened_depth(depth, ref, 0.0), np.maximum(depth, ref), atol=1e-9)


# --- Bad input ------------------------------------------------------------------------------

def test_bad_input_is_refused(injector, camera, textured, contact):
    rng = np.random.default_rng(0)
    with pytest.raises(ValueError, match="mechanism must be one of.*gamma_mix_gains"):
        sample_params("sepia", 0.5, rng)
    for strength in (1.5, -0.1, True, float("nan"), "0.5", None):
        with pytest.raises(ValueError, match=r"strength must be a float in \[0, 1\]"):
            sample_params("defocus", strength, rng)
    with pytest.raises(ValueError, match="got 1.5"):
        sample_params("defocus", 1.5, rng)
    with pytest.raises(ValueError, match="rng"):
        sample_params("defocus", 0.5, 3)
    assert sample_params("defocus", 1, rng)["radius_px"] == 4.0  # an int is a real number

    good = {"radius_px": 2.0}
    with pytest.raises(ValueError, match="mechanism must be one of"):
        injector.apply(textured, "sepia", good)
    with pytest.raises(ValueError, match="image"):
        injector.apply(textured[:-1], "defocus", good)
    with pytest.raises(ValueError, match="image"):
        injector.apply(textured[..., :2], "defocus", good)
    with pytest.raises(ValueError, match="image"):
        injector.apply((textured * 255).astype(np.uint8), "defocus", good)
    with pytest.raises(ValueError, match="params"):
        injector.apply(textured, "defocus", {"radius": 2.0})
    with pytest.raises(ValueError, match="params"):
        injector.apply(textured, "defocus", {"radius_px": float("inf")})

    depth, render = contact
    soft = {"factor": 0.5}
    with pytest.raises(ValueError, match="render"):
        injector.apply(textured, "soft_membrane", soft, depth=depth)
    with pytest.raises(ValueError, match="depth"):
        injector.apply(textured, "soft_membrane", soft, render=render)
    with pytest.raises(ValueError, match="depth"):
        injector.apply(textured, "soft_membrane", soft, depth=depth[:-1], render=render)
    with pytest.raises(ValueError, match="render's image"):
        injector.apply(textured, "soft_membrane", soft, depth=depth, render=lambda d: d)


def test_constructor_refuses_a_wrong_reference(spec, ref):
    with pytest.raises(ValueError, match="ref_depth"):
        Described(spec, ref[:-1])
    with pytest.raises(ValueError, match="ref_depth"):
        Described(spec, np.full(ref.shape, np.nan, np.float32))


# --- Written apart ---------------------------------------------------------------------------

def test_imports_nothing_from_studies_gap(absolute_imports):
    names = absolute_imports(ROOT / "studies" / "gap" / "described.py")
    assert not [n for n in names if n == "studies" or n.startswith("studies.")]
    allowed = {"numpy", "scipy", "cv2", "scenes"} | set(sys.stdlib_module_names)
    assert {n.split(".")[0] for n in names} <= allowed


@pytest.mark.parametrize("name", ["effects", "fit", "judge", "selection", "diagnosis", "samples", "optics",
                                  "model", "diagnose"])
def test_the_fitter_never_imports_this_module(name):
    path = ROOT / "studies" / "gap" / f"{name}.py"
    if not path.exists():
        pytest.skip(f"{path.name} is absent")
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.ImportFrom):
            module = node.module or ""
            assert "described" not in module.split(".")
            assert not (module in ("studies.gap", "") and any(a.name == "described" for a in node.names))
        elif isinstance(node, ast.Import):
            assert not any("described" in a.name.split(".") for a in node.names)
