"""The rig's image capture: folders of PNGs and video files read frame by frame in order,
RGB (not OpenCV's BGR) in [0, 1], warm-up and settle dropping frames, resizing, and a clear
CameraError for every source that does not open or runs out. A device is stood in for by
a fake ``cv2.VideoCapture`` (this machine has no camera) and, for the error, by an index
that does not exist."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

cv2 = pytest.importorskip("cv2", reason="OpenCV is not installed (pip install '.[rig]')")

from rig import camera as rc
from rig.camera import CameraError, open_camera
from scenes.images import write_rgb

#: MJPG is lossy: a flat 8-bit frame comes back within a few levels.
VIDEO_TOLERANCE = 6 / 255
#: Frames of the test sources.
FRAMES = 5
W, H = 64, 48


def _frame(i: int) -> np.ndarray:
    """Frame i: flat, its green level telling i, red high and blue low (so BGR is caught)."""
    rgb = np.empty((H, W, 3), np.float32)
    rgb[..., 0], rgb[..., 1], rgb[..., 2] = 200 / 255, (40 * i) / 255, 20 / 255
    return rgb


@pytest.fixture
def folder(tmp_path):
    path = tmp_path / "frames"
    for i in range(FRAMES):
        write_rgb(path / f"{i:03d}.png", _frame(i))
    (path / "notes.txt").write_text("not an image")
    return path


@pytest.fixture
def video(tmp_path):
    path = tmp_path / "taps.avi"
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 10.0, (W, H))
    assert writer.isOpened(), "OpenCV cannot write MJPG .avi here"
    for i in range(FRAMES):
        writer.write(cv2.cvtColor(np.rint(_frame(i) * 255).astype(np.uint8), cv2.COLOR_RGB2BGR))
    writer.release()
    return path


class FakeDevice:
    """A stand-in for ``cv2.VideoCapture(index)``: frame n (from 1) is flat at level n in
    blue (OpenCV's first channel), so a frame says how many were taken before it; ``dead``
    opens and gives none."""

    opened: list[FakeDevice] = []

    def __init__(self, index, dead: bool = False):
        self.index, self.dead, self.taken, self.released = index, dead, 0, False
        FakeDevice.opened.append(self)

    def isOpened(self):
        return True

    def grab(self):
        if self.dead:
            return False
        self.taken += 1
        return True

    def read(self):
        if not self.grab():
            return False, None
        frame = np.zeros((H, W, 3), np.uint8)
        frame[..., 0] = self.taken
        return True, frame

    def get(self, prop):
        return {cv2.CAP_PROP_FRAME_WIDTH: W, cv2.CAP_PROP_FRAME_HEIGHT: H}.get(prop, 0.0)

    def getBackendName(self):
        return "FAKE"

    def release(self):
        self.released = True


@pytest.fixture
def fake_device(monkeypatch):
    FakeDevice.opened = []
    monkeypatch.setattr(cv2, "VideoCapture", FakeDevice)
    return FakeDevice


# -- folders and videos ------------------------------------------------------------------------

def test_folder_gives_its_images_in_name_order_then_says_it_ran_out(folder):
    with open_camera(folder) as cam:
        frames = [cam.grab() for _ in range(FRAMES)]
        with pytest.raises(CameraError, match=rf"folder .*frames has no more images \(read {FRAMES} of {FRAMES}\)"):
            cam.grab()
    for i, frame in enumerate(frames):
        assert frame.dtype == np.float32 and frame.shape == (H, W, 3)
        np.testing.assert_allclose(frame, _frame(i), atol=0.5 / 255)  # 8-bit files, exact levels


def test_video_round_trips_in_order_and_rgb(video):
    with open_camera(str(video)) as cam:
        for i in range(FRAMES):
            frame = cam.grab()
            assert frame.dtype == np.float32 and frame.shape == (H, W, 3)
            assert 0.0 <= frame.min() and frame.max() <= 1.0
            np.testing.assert_allclose(frame.mean(axis=(0, 1)), _frame(i)[0, 0], atol=VIDEO_TOLERANCE)
        with pytest.raises(CameraError, match=rf"video .*taps.avi has no more frames \(read {FRAMES}\)"):
            cam.grab()


def test_a_pure_red_frame_comes_back_red(tmp_path):
    red = np.zeros((H, W, 3), np.float32)
    red[..., 0] = 1.0
    write_rgb(tmp_path / "red" / "0.png", red)
    path = tmp_path / "red.avi"
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 10.0, (W, H))
    writer.write(cv2.cvtColor(np.rint(red * 255).astype(np.uint8), cv2.COLOR_RGB2BGR))
    writer.release()
    for source in (tmp_path / "red", path):
        with open_camera(source) as cam:
            r, g, b = cam.grab().mean(axis=(0, 1))
        assert r > 1 - VIDEO_TOLERANCE and g < VIDEO_TOLERANCE and b < VIDEO_TOLERANCE, (source, r, g, b)


def test_files_drop_no_frames_unless_told(folder, video):
    for source in (folder, video):
        with open_camera(source) as cam:
            assert cam.frames_read == 0
            cam.settle()  # a recording's settle only waits (0 s)
            np.testing.assert_allclose(cam.grab()[0, 0], _frame(0)[0, 0], atol=VIDEO_TOLERANCE)
        with open_camera(source, warmup_frames=3) as cam:
            assert cam.frames_read == 3
            np.testing.assert_allclose(cam.grab()[0, 0], _frame(3)[0, 0], atol=VIDEO_TOLERANCE)
    with pytest.raises(CameraError, match=r"no more images \(read 5 of 5\)"):
        open_camera(folder, warmup_frames=FRAMES + 1)


def test_resize_to_the_simulated_camera(folder):
    with open_camera(folder, size=(W // 2, H // 2)) as cam:
        frame = cam.grab()
        description = cam.describe()
    assert frame.shape == (H // 2, W // 2, 3) and frame.dtype == np.float32
    np.testing.assert_allclose(frame, _frame(0)[: H // 2, : W // 2], atol=1e-6)  # flat: INTER_AREA keeps it
    assert description["frame_size_px"] == [W, H] and description["size_px"] == [W // 2, H // 2]
    with open_camera(folder, size=(W, W)) as cam, pytest.warns(UserWarning, match="aspect ratio"):
        assert cam.grab().shape == (W, W, 3)


def test_a_folder_of_mixed_sizes_needs_a_size(tmp_path):
    write_rgb(tmp_path / "0.png", _frame(0))
    write_rgb(tmp_path / "1.png", _frame(1)[:20])
    with open_camera(tmp_path) as cam:
        cam.grab()
        with pytest.raises(CameraError, match=r"frame 2 is 64x20 px, the source's earlier ones 64x48"):
            cam.grab()
    with open_camera(tmp_path, size=(W, H)) as cam, pytest.warns(UserWarning, match="aspect ratio"):
        assert cam.grab().shape == cam.grab().shape == (H, W, 3)


def test_describe_is_json_ready(folder, video):
    with open_camera(folder) as cam:
        folder_description = cam.describe()
    with open_camera(video) as cam:
        video_description = cam.describe()
    assert folder_description == {"kind": "folder", "source": str(folder), "frame_size_px": [W, H],
                                  "size_px": [W, H], "warmup_frames": 0, "settle_s": 0.0, "images": FRAMES}
    assert video_description["kind"] == "video" and video_description["frame_count"] == FRAMES
    assert video_description["frame_size_px"] == [W, H] and video_description["backend"]
    json.dumps([folder_description, video_description])


# -- devices ---------------------------------------------------------------------------------

def test_device_warms_up_and_settles_on_fresh_frames(fake_device):
    with open_camera("0", warmup_frames=5, settle_s=0.0) as cam:
        device = fake_device.opened[-1]
        assert device.index == 0 and device.taken == 5
        frame = cam.grab()
        assert frame[0, 0].tolist() == pytest.approx([0.0, 0.0, 6 / 255])  # BGR: level in blue
        cam.settle()
        assert cam.grab()[0, 0, 2] == pytest.approx((6 + rc.STALE_FRAMES + 1) / 255)
        assert cam.describe()["kind"] == "device" and cam.describe()["backend"] == "FAKE"
        assert cam.describe()["exposure"] == "auto"  # the diagnosis fits the capture's exposure then
    assert device.released
    with open_camera(0, settle_s=0.0):  # the defaults: a device warms up
        assert fake_device.opened[-1].taken == rc.WARMUP_FRAMES


def test_a_device_that_gives_no_frame(monkeypatch):
    monkeypatch.setattr(cv2, "VideoCapture", lambda index: FakeDevice(index, dead=True))
    FakeDevice.opened = []
    with pytest.raises(CameraError, match=rf"camera 0 returned no frame after {rc.READ_TRIES} tries"):
        open_camera(0)
    assert FakeDevice.opened[-1].released  # a failed warm-up does not leave it open
    with open_camera(0, warmup_frames=0) as cam:
        with pytest.raises(CameraError, match=r"camera 0 returned no frame"):
            cam.grab()


def test_a_device_that_does_not_exist():
    with pytest.raises(CameraError, match=r"camera 99 did not open .*expected a connected camera"):
        open_camera(99)


# -- errors ----------------------------------------------------------------------------------

def test_sources_that_do_not_open(tmp_path):
    with pytest.raises(CameraError, match=r"does not exist; expected a device index, a video file or a folder"):
        open_camera(tmp_path / "missing.avi")
    (tmp_path / "empty").mkdir()
    (tmp_path / "empty" / "readme.txt").write_text("no images")
    with pytest.raises(CameraError, match=r"folder .*empty has no images; expected files named \*.png"):
        open_camera(tmp_path / "empty")
    (tmp_path / "text.avi").write_text("not a video")
    with pytest.raises(CameraError, match=r"video .*text.avi could not be opened by OpenCV; expected a video file"):
        open_camera(tmp_path / "text.avi")


def test_closed_sources_say_so(folder):
    cam = open_camera(folder)
    cam.close()
    cam.close()
    with pytest.raises(CameraError, match="is closed"):
        cam.grab()


@pytest.mark.parametrize("kwargs, message", [
    ({"warmup_frames": -1}, "warmup_frames must be an int >= 0"),
    ({"warmup_frames": 1.5}, "warmup_frames must be an int >= 0"),
    ({"settle_s": math.nan}, "settle_s must be a finite number >= 0"),
    ({"settle_s": -0.1}, "settle_s must be a finite number >= 0"),
    ({"size": (640,)}, r"size must be \(width, height\)"),
    ({"size": (640, 0)}, r"size must be \(width, height\)"),
])
def test_bad_arguments_name_themselves(folder, kwargs, message):
    with pytest.raises(ValueError, match=message):
        open_camera(folder, **kwargs)


@pytest.mark.parametrize("source, message", [(-1, "device index must be >= 0"), (True, "source must be"),
                                             (None, "source must be"), (2.5, "source must be")])
def test_bad_sources_name_themselves(source, message):
    with pytest.raises(ValueError, match=message):
        open_camera(source)
