"""Headless OpenGL platform for MuJoCo rendering: EGL, else OSMesa, chosen before import."""

from __future__ import annotations

import ctypes.util
import os

from .errors import TactileSimError

#: Debian packages that provide each platform.
PACKAGES = {
    "egl": "libegl1 libegl-mesa0 libgl1-mesa-dri",
    "osmesa": "libosmesa6",
}
_LIBRARIES = {"egl": "EGL", "osmesa": "OSMesa"}


class GLPlatformError(TactileSimError, RuntimeError):
    """No usable headless OpenGL platform."""


def missing_message(platform: str | None = None) -> str:
    wanted = [platform] if platform in PACKAGES else list(PACKAGES)
    options = "; or ".join(f"{p.upper()}: apt-get install {PACKAGES[p]}" for p in wanted)
    return f"no headless OpenGL platform for MuJoCo rendering ({options}); or set MUJOCO_GL"


def choose_gl(find_library=ctypes.util.find_library) -> str:
    """Set MUJOCO_GL (if unset) to the first platform whose library is present.

    Must run before ``import mujoco``. Returns the platform name; raises
    GLPlatformError naming the Debian packages when neither EGL nor OSMesa is found.
    """
    chosen = os.environ.get("MUJOCO_GL")
    if chosen:
        lib = _LIBRARIES.get(chosen.lower())
        if lib is not None and find_library(lib) is None:
            raise GLPlatformError(f"MUJOCO_GL={chosen} but lib{lib} is missing; " + missing_message(chosen.lower()))
        return chosen
    for platform, lib in _LIBRARIES.items():
        if find_library(lib) is not None:
            os.environ["MUJOCO_GL"] = platform
            if platform == "osmesa":
                os.environ.setdefault("PYOPENGL_PLATFORM", "osmesa")
            return platform
    raise GLPlatformError(missing_message())


def import_mujoco():
    """``import mujoco`` with a headless platform chosen first."""
    choose_gl()
    import mujoco

    return mujoco
