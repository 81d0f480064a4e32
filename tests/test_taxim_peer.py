"""Taxim, the peer simulator (studies.compare.taxim): the table's fit recovers a known
table, a ball's height map is a sphere cap, bad input is refused; with the port
installed, a written calibration renders the colours, positions and press depths it was
given."""

from __future__ import annotations

import json

import numpy as np
import pytest

from studies.compare import taxim as tx
from studies.compare import taxim_table as tt

PIXEL_M = 0.1e-3
BALL_M = 1.6e-3  # 16 px
SHAPE = (60, 80)
#: Float64 least squares on noiseless samples, in [0, 1] units.
EXACT = 1e-9


def _known_table(bins: int, shape, rng: np.random.Generator) -> np.ndarray:
    """Random coefficients whose change stays within ±0.3 over the frame: weights of
    [u², v², uv, u, v, 1] with u, v the position as a share of the frame, turned into
    weights of the pixel's (column, row)."""
    h, w = shape
    scaled = rng.uniform(-0.05, 0.05, (bins, bins, 3, 6))
    return scaled * np.array([1 / w ** 2, 1 / h ** 2, 1 / (w * h), 1 / w, 1 / h, 1.0])


def _synthetic_presses(coeffs, no_contact, n, rng, radius_px=15.0):
    """Presses made with the table: background + lookup inside each (clipped) circle."""
    h, w = no_contact.shape[:2]
    bg = tt.background(no_contact)
    centres = np.stack([rng.integers(18, w - 18, n), rng.integers(18, h - 18, n)], axis=1).astype(float)
    frames = np.repeat(no_contact[None], n, axis=0)
    for i, c in enumerate(centres):
        theta, phi, inside = tt.press_angles(c, radius_px, BALL_M / PIXEL_M, (h, w))
        frames[i][inside] = (bg + tt.lookup(coeffs, theta, phi))[inside]
    return frames, centres, np.full(n, radius_px)


def test_background_of_a_uniform_frame_is_the_frame():
    f0 = np.full(SHAPE + (3,), 0.4)
    np.testing.assert_allclose(tt.background(f0), f0, atol=1e-12)


def test_fit_recovers_a_known_table():
    rng = np.random.default_rng(7)
    bins = 8
    coeffs = _known_table(bins, SHAPE, rng)
    no_contact = np.full(SHAPE + (3,), 0.5)
    frames, centres, radii = _synthetic_presses(coeffs, no_contact, 20, rng)
    assert frames.min() >= 0 and frames.max() <= 1
    table = tt.fit_polytable(no_contact, frames, centres, radii, PIXEL_M, BALL_M, bins=bins)

    fitted = table["fitted"]
    assert fitted.sum() > bins * bins // 2
    assert np.all(table["presses"][fitted] >= tt.MIN_PRESSES)
    # Compare what each fitted bin predicts over the whole frame (weights of x² and 1 differ in scale).
    rows, cols = np.mgrid[:SHAPE[0], :SHAPE[1]].astype(float)
    features = np.stack([cols ** 2, rows ** 2, cols * rows, cols, rows, np.ones_like(cols)], -1)
    got = np.einsum("hwf,bcf->bhwc", features, table["coeffs"][fitted])
    want = np.einsum("hwf,bcf->bhwc", features, coeffs[fitted])
    assert np.abs(got - want).max() < EXACT
    # And it reproduces the presses it was fitted on.
    for frame, c in zip(frames[:3], centres[:3]):
        theta, phi, inside = tt.press_angles(c, radii[0], BALL_M / PIXEL_M, SHAPE)
        remade = table["background"] + tt.lookup(table["coeffs"], theta, phi)
        assert np.abs(remade - frame)[inside].max() < EXACT


def test_unfitted_bins_take_their_nearest_fitted_bin():
    rng = np.random.default_rng(3)
    bins = 8
    no_contact = np.full(SHAPE + (3,), 0.5)
    frames, centres, radii = _synthetic_presses(_known_table(bins, SHAPE, rng), no_contact, 12, rng)
    table = tt.fit_polytable(no_contact, frames, centres, radii, PIXEL_M, BALL_M, bins=bins)
    fitted = table["fitted"]
    assert not fitted.all()
    done = np.argwhere(fitted)
    for i, j in np.argwhere(~fitted):
        distance = np.hypot(*(done - (i, j)).T)
        nearest = done[distance == distance.min()]
        assert any(np.array_equal(table["coeffs"][i, j], table["coeffs"][a, b]) for a, b in nearest)


def test_press_angles_are_the_sphere_normals():
    theta, phi, inside = tt.press_angles((40.0, 30.0), 20.0, 16.0, SHAPE)
    assert theta[30, 40] == 0 and inside[30, 40]
    # 8 px right of the centre on a 16 px ball: arcsin(1/2); the normal leans toward -x.
    assert theta[30, 48] == pytest.approx(np.pi / 6)
    assert phi[30, 48] == pytest.approx(np.pi) or phi[30, 48] == pytest.approx(-np.pi)
    assert phi[22, 40] == pytest.approx(np.pi / 2)  # 8 px up (row - 8): -dy = +8
    # The circle is clipped to the ball: 20 px asked, 16 px kept.
    assert inside[30, 55] and not inside[30, 56]


def test_bin_indices_span_the_table():
    i_theta, i_phi = tt.bin_indices(np.array([0.0, np.pi / 2]), np.array([-np.pi, np.pi]), 80)
    assert list(i_theta) == [0, 79] and list(i_phi) == [0, 79]


def test_ball_height_map_is_a_sphere_cap():
    hm = tx.ball_height_map((40.0, 30.0), BALL_M, PIXEL_M, SHAPE)
    assert hm.shape == SHAPE
    assert hm[30, 40] == 0 and hm.min() == 0
    # 8 px = 0.8 mm from the centre of a 1.6 mm ball: R - sqrt(R² - r²).
    assert hm[30, 48] == pytest.approx(1.6 - np.sqrt(1.6 ** 2 - 0.8 ** 2))
    # Outside the silhouette the ball is out of reach: its equator.
    assert hm[30, 70] == pytest.approx(1.6) and hm.max() == pytest.approx(1.6)


def test_write_calibration_writes_the_ports_files(tmp_path):
    rng = np.random.default_rng(0)
    coeffs = _known_table(4, SHAPE, rng)
    no_contact = np.full(SHAPE + (3,), 0.5)
    no_contact[..., 0] = 1.0  # red, to see the channel order
    table = {"coeffs": coeffs, "sigma_px": 12.5, "shape": SHAPE, "pixel_m": PIXEL_M}
    folder = tx.write_calibration(tmp_path / "cal", table, no_contact, np.zeros((12, 16)), PIXEL_M, 80, 60)
    poly = np.load(folder / "polycalib.npz")
    # The port reads grad_b as red and grad_r as blue.
    np.testing.assert_allclose(poly["grad_b"], coeffs[..., 0, :] * 255)
    np.testing.assert_allclose(poly["grad_r"], coeffs[..., 2, :] * 255)
    assert int(poly["bins"]) == 4
    f0 = np.load(folder / "dataPack.npz")["f0"]
    assert f0.dtype == np.uint8 and f0.shape == SHAPE + (3,) and f0[0, 0, 2] == 255 and f0[0, 0, 0] == 128
    params = json.loads((folder / "params.json").read_text())
    assert params["sensor"] == {"pixmm": pytest.approx(0.1), "num_bins": 4, "h": 60, "w": 80}
    assert params["simulator"]["initial_frame_sigma_rel"] == [12.5 / 80, 12.5 / 60]
    shadows = np.load(folder / "shadowTable.npz", allow_pickle=True)
    assert shadows["shadowTable"].shape == (3, 63, 1)


# ----------------------------------------------------------------------------- bad input

def _good():
    no_contact = np.full(SHAPE + (3,), 0.5)
    frames = np.repeat(no_contact[None], 2, axis=0)
    return dict(no_contact=no_contact, frames=frames, centres_px=np.array([[40.0, 30.0], [30.0, 20.0]]),
                radii_px=np.array([15.0, 15.0]), pixel_m=PIXEL_M, ball_radius_m=BALL_M)


@pytest.mark.parametrize("key, value, says", [
    ("no_contact", np.full(SHAPE + (3,), 128, np.uint8), "no_contact must be"),
    ("no_contact", np.full(SHAPE + (3,), 1.5), "no_contact must hold"),
    ("frames", np.full((2,) + SHAPE, 0.5), "frames must be"),
    ("frames", np.full((2, 10, 10, 3), 0.5), "frames must be"),
    ("centres_px", np.zeros((3, 2)), "centres_px must be"),
    ("centres_px", np.array([[np.nan, 1.0], [1.0, 1.0]]), "centres_px must be"),
    ("radii_px", np.array([15.0, -1.0]), "radii_px must be"),
    ("pixel_m", 0.0, "pixel_m must be"),
    ("ball_radius_m", float("nan"), "ball_radius_m must be"),
])
def test_fit_refuses_bad_input(key, value, says):
    args = _good()
    args[key] = value
    with pytest.raises(ValueError, match=says):
        tt.fit_polytable(**args)


def test_fit_refuses_too_few_presses_and_bad_bins():
    with pytest.raises(ValueError, match="no bin was seen by"):
        tt.fit_polytable(**_good())
    with pytest.raises(ValueError, match="bins must be"):
        tt.fit_polytable(**_good(), bins=1)


@pytest.mark.parametrize("args, says", [
    (((40.0,), BALL_M, PIXEL_M, SHAPE), "centre_px must be"),
    (((40.0, 30.0), -1.0, PIXEL_M, SHAPE), "ball_radius_m must be"),
    (((40.0, 30.0), BALL_M, 0.0, SHAPE), "pixel_m must be"),
    (((40.0, 30.0), BALL_M, PIXEL_M, (60,)), "shape must be"),
])
def test_ball_height_map_refuses_bad_input(args, says):
    with pytest.raises(ValueError, match=says):
        tx.ball_height_map(*args)


def test_write_calibration_refuses_bad_input(tmp_path):
    table = {"coeffs": np.zeros((4, 4, 3, 6)), "sigma_px": 50.0, "shape": SHAPE, "pixel_m": PIXEL_M}
    f0 = np.full(SHAPE + (3,), 0.5)
    gel = np.zeros((12, 16))
    with pytest.raises(ValueError, match="table must be"):
        tx.write_calibration(tmp_path, {}, f0, gel, PIXEL_M, 80, 60)
    with pytest.raises(ValueError, match="width x height must be"):
        tx.write_calibration(tmp_path, table, f0, gel, PIXEL_M, 160, 120)
    with pytest.raises(ValueError, match="pixel_m must be the table's"):
        tx.write_calibration(tmp_path, table, f0, gel, 2 * PIXEL_M, 80, 60)
    with pytest.raises(ValueError, match="no_contact must be"):
        tx.write_calibration(tmp_path, table, f0[:10], gel, PIXEL_M, 80, 60)
    with pytest.raises(ValueError, match="gel_map_px must be"):
        tx.write_calibration(tmp_path, table, f0, np.zeros(5), PIXEL_M, 80, 60)
    with pytest.raises(ValueError, match="shadow_from must be"):
        tx.write_calibration(tmp_path, table, f0, gel, PIXEL_M, 80, 60, shadow_from=tmp_path / "nowhere")


# ----------------------------------------------------------------------------- the port

@pytest.fixture(scope="module")
def port():
    pytest.importorskip("jax", reason="Taxim's port needs JAX: pip install 'tactile-sim[peers]'")
    return pytest.importorskip("taxim", reason="Taxim's port is not installed: pip install 'tactile-sim[peers]'")


def test_port_renders_the_tables_colours_at_the_tables_positions(port, tmp_path):
    # The same change in every bin, so only channel order, 0-255 scaling, the positions
    # the polynomial is evaluated at and the background matter.
    coeffs = np.zeros((4, 4, 3, 6))
    coeffs[..., 0, 5] = 0.2          # red +0.2
    coeffs[..., 1, 4] = 0.004        # green grows down the rows
    coeffs[..., 2, 3] = -0.004       # blue falls along the columns
    no_contact = np.full(SHAPE + (3,), 0.4)
    table = {"coeffs": coeffs, "sigma_px": 50.0, "shape": SHAPE, "pixel_m": PIXEL_M}
    folder = tx.write_calibration(tmp_path / "cal", table, no_contact, np.zeros((12, 16)), PIXEL_M, 80, 60)
    image = tx.TaximPeer(folder).render(np.ones(SHAPE), PIXEL_M)
    rows, cols = np.mgrid[:SHAPE[0], :SHAPE[1]]
    f0 = np.round(0.4 * 255) / 255  # the port reads the frame as 8 bits
    want = np.clip(np.stack([f0 + 0.2 + 0 * cols, f0 + 0.004 * rows, f0 - 0.004 * cols], -1), 0, 1)
    assert np.abs(image - want).max() < 1e-5


def test_port_renders_a_press_with_the_fits_normals(port, tmp_path):
    # A table whose change depends on the normal: what the port renders inside the
    # contact's core (kept undeformed by its blur) is what lookup predicts there.
    bins = 12
    i_theta, i_phi = np.meshgrid(np.arange(bins), np.arange(bins), indexing="ij")
    theta = (i_theta + 0.5) * 0.5 * np.pi / (bins - 1)
    phi = (i_phi + 0.5) * 2 * np.pi / (bins - 1) - np.pi
    coeffs = np.zeros((bins, bins, 3, 6))
    coeffs[..., 0, 5] = 0.3 * np.sin(theta) * np.cos(phi)
    coeffs[..., 1, 5] = 0.3 * np.sin(theta) * np.sin(phi)
    coeffs[..., 2, 5] = 0.3 * np.sin(theta)
    no_contact = np.full(SHAPE + (3,), 0.5)
    table = {"coeffs": coeffs, "sigma_px": 50.0, "shape": SHAPE, "pixel_m": PIXEL_M}
    folder = tx.write_calibration(tmp_path / "cal", table, no_contact, np.zeros((12, 16)), PIXEL_M, 80, 60)
    peer = tx.TaximPeer(folder, no_contact=no_contact)
    depth_m = 0.8e-3
    image = peer.render_presses([[40.0, 30.0]], [depth_m], BALL_M, PIXEL_M, SHAPE)[0]
    contact_px = np.sqrt(BALL_M ** 2 - (BALL_M - depth_m) ** 2) / PIXEL_M
    t, p, core = tt.press_angles((40.0, 30.0), 0.6 * contact_px, BALL_M / PIXEL_M, SHAPE)
    predicted = np.clip(tt.background(no_contact) + tt.lookup(coeffs, t, p), 0, 1)
    # The port reads the frame as 8 bits (0.5 -> 128/255); a pixel may land one 8° bin
    # over after the port's half-pixel blur. A mirrored direction (φ -> -φ) scores 0.044.
    assert np.abs(image - predicted)[core].mean() < 0.01


def test_presses_are_placed_below_the_gel_where_they_land(port, tmp_path):
    # A domed gel, (r/20)² px (r in px, 0.1 mm px) below its apex at (40, 30): the ball's
    # lowest point is the gel's height under it minus the depth.
    rows, cols = np.mgrid[:SHAPE[0], :SHAPE[1]]
    dome = 10.0 - ((cols - 40) ** 2 + (rows - 30) ** 2) / 400
    table = {"coeffs": np.zeros((4, 4, 3, 6)), "sigma_px": 50.0, "shape": SHAPE, "pixel_m": PIXEL_M}
    folder = tx.write_calibration(tmp_path / "cal", table, np.full(SHAPE + (3,), 0.5), dome, PIXEL_M, 80, 60)
    peer = tx.TaximPeer(folder)
    maps = peer.press_height_maps([[40.0, 30.0], [10.0, 30.0]], [0.5e-3, 0.5e-3], BALL_M, PIXEL_M, SHAPE)
    assert maps[0].min() == pytest.approx(-0.5) and maps[0][30, 40] == maps[0].min()
    assert maps[1].min() == pytest.approx(-(30 / 20) ** 2 * 0.1 - 0.5)  # 30 px out: 0.225 mm down
    np.testing.assert_allclose(tx.gel_surface_mm(dome, 0.1, SHAPE), (dome - 10) * 0.1, atol=1e-12)


def test_peer_refuses_bad_input(port, tmp_path):
    with pytest.raises(ValueError, match="calib_folder must be"):
        tx.TaximPeer(tmp_path)
    table = {"coeffs": np.zeros((4, 4, 3, 6)), "sigma_px": 50.0, "shape": SHAPE, "pixel_m": PIXEL_M}
    folder = tx.write_calibration(tmp_path / "cal", table, np.full(SHAPE + (3,), 0.5), np.zeros((12, 16)),
                                  PIXEL_M, 80, 60)
    with pytest.raises(ValueError, match="with_shadow needs a shadow table"):
        tx.TaximPeer(folder, with_shadow=True)
    with pytest.raises(ValueError, match="no_contact must be"):
        tx.TaximPeer(folder, no_contact=np.zeros(SHAPE))
    peer = tx.TaximPeer(folder)
    with pytest.raises(ValueError, match="height_maps_mm must be"):
        peer.render(np.zeros((4,)), PIXEL_M)
    with pytest.raises(ValueError, match="depths_m must be"):
        peer.render_presses([[40.0, 30.0]], [-1e-3], BALL_M, PIXEL_M, SHAPE)
    with pytest.raises(ValueError, match="depths_m must be below"):
        peer.render_presses([[40.0, 30.0]], [2e-3], BALL_M, PIXEL_M, SHAPE)
    with pytest.raises(ValueError, match="centres_px must be"):
        peer.render_presses([40.0, 30.0], [1e-3], BALL_M, PIXEL_M, SHAPE)


def test_shipped_folder_is_the_ports(port):
    folder = tx.shipped_folder()
    assert (folder / "polycalib.npz").is_file()
    assert json.loads((folder / "params.json").read_text())["sensor"]["w"] == 640
