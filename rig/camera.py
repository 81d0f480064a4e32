"""Capture the rig's camera images (OpenCV): frames of a camera device, a video file or a
folder of images, each as (H, W, 3) float32 RGB in [0, 1].

:func:`open_camera` opens a source by what it is given:

- a device index (``0`` or ``"0"``): ``cv2.VideoCapture(index)``. On opening, it reads and
  drops ``warmup_frames`` frames, so that auto-exposure and white balance settle first.
  :meth:`RigCamera.settle` waits ``settle_s`` (for the membrane to come to rest after a
  move) and then drops the ``STALE_FRAMES`` frames the driver buffered meanwhile, so that
  the next grab is taken after the wait, not before it.
- a video file: ``cv2.VideoCapture(path)``, one frame per grab.
- a folder of images (``IMAGE_SUFFIXES``), sorted by name (zero-pad numbered names), one
  per grab, read with :func:`scenes.images.read_rgb`.

A video or a folder is a recording: it drops no frames unless ``warmup_frames`` says so,
and its ``settle`` only waits (0 s unless ``settle_s`` says otherwise). 8-bit values map to
[0, 1] by a division by 255, as :mod:`scenes.images` maps files (the camera's output
values; no sRGB transfer). ``size`` resizes every frame (``cv2.INTER_AREA``) to the
simulated camera's (width, height).

Every failure is a :class:`CameraError` naming the source and what was expected; bad
arguments are ``ValueError``\\ s naming the argument.
"""

from __future__ import annotations

import glob
import math
import time
import warnings
from pathlib import Path
from typing import Self

import numpy as np

from scenes.errors import TactileSimError

#: Image files a folder source reads, by suffix (any case).
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff")
#: Frames a device drops on opening: about 1 s at 30 fps, for auto-exposure and white
#: balance to settle.
WARMUP_FRAMES = 30
#: A device's wait in ``settle``, seconds: the membrane comes to rest after a move.
SETTLE_S = 0.5
#: Frames a device drops after that wait: OpenCV's V4L2 backend queues 4 buffers
#: (``DEFAULT_V4L_BUFFERS``), filled before or during the wait.
STALE_FRAMES = 4
#: A device's reads of one frame before it is given up (each read blocks until a frame
#: comes or the driver's own timeout passes).
READ_TRIES = 3


class CameraError(TactileSimError, RuntimeError):
    """A camera source that does not open, or gives no frame."""


class RigCamera:
    """An open source of frames (use :func:`open_camera`): ``grab``, ``settle``,
    ``describe``, ``close``; a context manager."""

    def __init__(self, kind: str, name: str, *, capture=None, paths: tuple[Path, ...] = (),
                 frame_size: tuple[int, int] | None = None, size: tuple[int, int] | None = None,
                 settle_s: float = 0.0, warmup_frames: int = 0):
        self.kind = kind  # "device", "video" or "folder"
        self.name = name  # what was opened: the index, or the path
        self.size = size  # (w, h) of the frames returned; None: as they come
        self.settle_s = settle_s
        self.warmup_frames = warmup_frames
        self.frames_read = 0  # frames taken from the source, dropped ones included
        self._capture = capture  # cv2.VideoCapture of a device or a video
        self._paths = paths  # a folder's images
        self._frame_size = frame_size  # (w, h) the source gives; None until a frame tells
        self._warned_aspect = False
        try:
            self._drop(warmup_frames)
        except BaseException:
            self.close()
            raise

    def grab(self) -> np.ndarray:
        """The next frame: (H, W, 3) float32 RGB in [0, 1], (W, H) the ``size`` asked for,
        else the source's."""
        self._check_open()
        if self.kind == "folder":
            return self._resized(self._read_image())
        return self._resized(_rgb(self._read_frame()))

    def settle(self) -> None:
        """Wait ``settle_s`` seconds; a device then drops ``STALE_FRAMES`` buffered frames,
        so that the next grab is taken after the wait."""
        self._check_open()
        time.sleep(self.settle_s)
        if self.kind == "device":
            self._drop(STALE_FRAMES)

    def describe(self) -> dict:
        """What was captured from, JSON-ready (for a dataset.json)."""
        out = {"kind": self.kind, "source": self.name,
               "frame_size_px": list(self._frame_size) if self._frame_size else None,
               "size_px": list(self.size or self._frame_size or ()) or None,
               "warmup_frames": self.warmup_frames, "settle_s": self.settle_s}
        if self.kind == "device":  # left in its automatic mode, settled on opening (``warmup_frames``)
            out["exposure"] = "auto"
        if self.kind == "folder":
            out["images"] = len(self._paths)
        elif self._capture is not None:
            import cv2

            out["backend"] = _backend(self._capture)
            if self.kind == "video":
                out["frame_count"] = int(self._capture.get(cv2.CAP_PROP_FRAME_COUNT))
                out["fps"] = float(self._capture.get(cv2.CAP_PROP_FPS))
        return out

    def close(self) -> None:
        """Release the device or file (again: nothing)."""
        if self._capture is not None:
            self._capture.release()
        self._capture, self._paths = None, ()

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    # -- reading ---------------------------------------------------------------------------

    def _check_open(self) -> None:
        if self._capture is None and not self._paths:
            raise CameraError(f"{self._label()} is closed")

    def _label(self) -> str:
        return f"camera {self.name}" if self.kind == "device" else f"{self.kind} {self.name}"

    def _read_frame(self) -> np.ndarray:
        """The next frame of a device or video, as OpenCV gives it (BGR)."""
        tries = READ_TRIES if self.kind == "device" else 1
        for _ in range(tries):
            ok, frame = self._capture.read()
            if ok and frame is not None:
                self.frames_read += 1
                return frame
        raise self._no_frame()

    def _read_image(self) -> np.ndarray:
        from scenes.images import read_rgb

        if self.frames_read >= len(self._paths):
            raise self._no_frame()
        path = self._paths[self.frames_read]
        try:
            image = read_rgb(path)
        except (OSError, ValueError) as exc:
            raise CameraError(f"folder {self.name}: {exc}") from None
        self.frames_read += 1
        return image

    def _drop(self, n: int) -> None:
        """Take ``n`` frames and throw them away (a device without decoding them)."""
        for _ in range(n):
            if self.kind == "device":
                if not any(self._capture.grab() for _ in range(READ_TRIES)):
                    raise self._no_frame()
                self.frames_read += 1
            elif self.kind == "folder":
                self._read_image()
            else:
                self._read_frame()

    def _no_frame(self) -> CameraError:
        if self.kind == "device":
            return CameraError(f"camera {self.name} returned no frame after {READ_TRIES} tries ({self.frames_read} "
                               "read before); expected a running camera: is another program using it, or was it "
                               "unplugged?")
        if self.kind == "folder":
            return CameraError(f"folder {self.name} has no more images (read {self.frames_read} of "
                               f"{len(self._paths)})")
        return CameraError(f"video {self.name} has no more frames (read {self.frames_read})")

    def _resized(self, rgb: np.ndarray) -> np.ndarray:
        """Check the frame's size against the source's, and resize it to ``size``."""
        h, w = rgb.shape[:2]
        if self._frame_size is None:
            self._frame_size = (w, h)
        if self.size is None:
            if (w, h) != self._frame_size:
                raise CameraError(f"{self._label()}: frame {self.frames_read} is {w}x{h} px, the source's earlier "
                                  f"ones {self._frame_size[0]}x{self._frame_size[1]}; expected one size (or pass "
                                  "size= to resize every frame)")
            return rgb
        if (w, h) == self.size:
            return rgb
        import cv2

        if not self._warned_aspect and abs(w * self.size[1] - h * self.size[0]) > 0.01 * w * self.size[1]:
            warnings.warn(f"{self._label()}: resizing {w}x{h} px frames to {self.size[0]}x{self.size[1]} changes "
                          "their aspect ratio", stacklevel=3)
            self._warned_aspect = True
        return cv2.resize(rgb, self.size, interpolation=cv2.INTER_AREA)


def open_camera(source: int | str | Path, *, warmup_frames: int | None = None, settle_s: float | None = None,
                size: tuple[int, int] | None = None) -> RigCamera:
    """Open a frame source (see the module doc).

    Parameters
    ----------
    source : a device index (int >= 0, or its digits), a video file or a folder of images.
    warmup_frames : frames dropped on opening; None: ``WARMUP_FRAMES`` for a device, 0 for
        a video or folder.
    settle_s : seconds ``settle`` waits; None: ``SETTLE_S`` for a device, 0 for a video or
        folder.
    size : (width, height) px every frame is resized to; None: as the source gives them.

    Returns
    -------
    RigCamera, open (close it, or use it in a ``with`` block).
    """
    if warmup_frames is not None and (not isinstance(warmup_frames, (int, np.integer))
                                      or isinstance(warmup_frames, bool) or warmup_frames < 0):
        raise ValueError(f"warmup_frames must be an int >= 0 (frames), got {warmup_frames!r}")
    if settle_s is not None and (not isinstance(settle_s, (int, float, np.integer, np.floating))
                                 or isinstance(settle_s, bool) or not (math.isfinite(settle_s) and settle_s >= 0)):
        raise ValueError(f"settle_s must be a finite number >= 0 (seconds), got {settle_s!r}")
    if size is not None:
        if (not isinstance(size, (tuple, list)) or len(size) != 2
                or not all(isinstance(v, (int, np.integer)) and not isinstance(v, bool) and v > 0 for v in size)):
            raise ValueError(f"size must be (width, height) in pixels, two ints > 0, got {size!r}")
        size = (int(size[0]), int(size[1]))
    index = _device_index(source)
    if index is not None:
        return _open_device(index, warmup_frames, settle_s, size)
    path = Path(source)
    if not path.exists():
        raise CameraError(f"camera source {str(path)!r} does not exist; expected a device index, a video file or a "
                          "folder of images")
    warmup, settle = warmup_frames or 0, settle_s or 0.0
    if path.is_dir():
        paths = tuple(sorted((p for p in path.iterdir() if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES),
                             key=lambda p: p.name))
        if not paths:
            raise CameraError(f"folder {path} has no images; expected files named *{', *'.join(IMAGE_SUFFIXES)}")
        return RigCamera("folder", str(path), paths=paths, frame_size=_image_size(paths[0]), size=size,
                         settle_s=settle, warmup_frames=warmup)
    cv2 = _cv2()
    capture = cv2.VideoCapture(str(path))
    if not capture.isOpened():
        capture.release()
        raise CameraError(f"video {path} could not be opened by OpenCV; expected a video file it reads (such as "
                          ".avi or .mp4)")
    return RigCamera("video", str(path), capture=capture, frame_size=_capture_size(capture), size=size,
                     settle_s=settle, warmup_frames=warmup)


def _open_device(index: int, warmup_frames: int | None, settle_s: float | None,
                 size: tuple[int, int] | None) -> RigCamera:
    cv2 = _cv2()
    capture = cv2.VideoCapture(index)
    if not capture.isOpened():
        capture.release()
        found = ", ".join(sorted(glob.glob("/dev/video*"))) or "none"
        raise CameraError(f"camera {index} did not open (cv2.VideoCapture({index})); expected a connected camera "
                          f"at that index (video devices here: {found})")
    return RigCamera("device", str(index), capture=capture, frame_size=_capture_size(capture), size=size,
                     settle_s=SETTLE_S if settle_s is None else float(settle_s),
                     warmup_frames=WARMUP_FRAMES if warmup_frames is None else int(warmup_frames))


def _device_index(source) -> int | None:
    """The device index ``source`` names, None for a path; a ValueError for anything else."""
    if isinstance(source, bool):
        raise ValueError(f"source must be a device index, a video file or a folder of images, got {source!r}")
    if isinstance(source, (int, np.integer)):
        if source < 0:
            raise ValueError(f"source device index must be >= 0, got {source}")
        return int(source)
    if isinstance(source, str) and source.strip().isdigit():
        return int(source)
    if isinstance(source, (str, Path)) and str(source):
        return None
    raise ValueError(f"source must be a device index, a video file or a folder of images, got {source!r}")


def _rgb(frame: np.ndarray) -> np.ndarray:
    """An OpenCV frame (BGR, BGRA or grey; 8 or 16 bit) -> (H, W, 3) float32 RGB in [0, 1]."""
    frame = np.asarray(frame)
    scale = 1.0 / np.iinfo(frame.dtype).max if frame.dtype.kind == "u" else 1.0
    if frame.ndim == 2:
        frame = frame[..., None].repeat(3, axis=-1)
    else:
        frame = frame[..., 2::-1]  # BGR(A) -> RGB
    return np.ascontiguousarray(frame, dtype=np.float32) * np.float32(scale)


def _capture_size(capture) -> tuple[int, int] | None:
    """(w, h) a capture says its frames are; None when it does not say."""
    import cv2

    w, h = int(capture.get(cv2.CAP_PROP_FRAME_WIDTH)), int(capture.get(cv2.CAP_PROP_FRAME_HEIGHT))
    return (w, h) if w > 0 and h > 0 else None


def _image_size(path: Path) -> tuple[int, int] | None:
    """(w, h) of an image file from its header; None when it cannot be read (the grab says why)."""
    from PIL import Image

    try:
        with Image.open(path) as im:
            return im.size
    except (OSError, ValueError):
        return None


def _backend(capture) -> str:
    import cv2

    try:
        return str(capture.getBackendName())
    except cv2.error:  # a backend without a name
        return "unknown"


def _cv2():
    try:
        import cv2
    except ImportError:
        raise ImportError("the rig's camera needs OpenCV: pip install 'tactile-sim[rig]' "
                          "(opencv-python-headless)") from None
    return cv2
