"""Mitsuba variant selection: one environment variable, then a fallback chain.

``TACTILE_SIM_MI_VARIANT`` names a variant; unset, the first that works of
cuda_ad_spectral -> llvm_ad_spectral -> scalar_spectral is used. Dr.Jit's LLVM backend
needs LLVM 19 (LLVM 16's JIT crashes on "Cannot select fminimum"), found here or via
DRJIT_LIBLLVM_PATH; it must be located before Dr.Jit is first imported.
"""

from __future__ import annotations

import glob
import os
import warnings

from scenes.errors import TactileSimError

VARIANT_ENV = "TACTILE_SIM_MI_VARIANT"
FALLBACK = ("cuda_ad_spectral", "llvm_ad_spectral", "scalar_spectral")
#: Set by ``any_variant`` when no variant is set yet: built into every Mitsuba, no JIT backend.
ANY_VARIANT = "scalar_spectral"
#: The Debian package that provides a working LLVM for Dr.Jit.
LLVM_PACKAGE = "libllvm19"
LLVM_GLOBS = ("/usr/lib/*-linux-gnu/libLLVM.so.19*", "/usr/lib/*-linux-gnu/libLLVM-19.so", "/usr/lib/llvm-19/lib/libLLVM*.so*")


class VariantError(TactileSimError, RuntimeError):
    """No usable Mitsuba variant, or an unknown one was asked for."""


def find_llvm() -> str | None:
    """Path of LLVM 19's shared library: DRJIT_LIBLLVM_PATH, else Debian's location."""
    path = os.environ.get("DRJIT_LIBLLVM_PATH")
    if path:
        return path if os.path.exists(path) else None
    for pattern in LLVM_GLOBS:
        found = sorted(glob.glob(pattern))
        if found:
            return found[0]
    return None


def _mitsuba():
    llvm = find_llvm()
    if llvm and "DRJIT_LIBLLVM_PATH" not in os.environ:
        os.environ["DRJIT_LIBLLVM_PATH"] = llvm
    try:
        import drjit as dr
        import mitsuba as mi
    except ImportError as exc:
        raise VariantError(f"Mitsuba 3 is not installed ({exc}); pip install '.[pbr]'") from None
    return mi, dr


def _usable(name: str, mi, dr) -> str | None:
    """None if the variant can run here, else why not."""
    if name not in mi.variants():
        return f"not built into this Mitsuba ({', '.join(mi.variants())})"
    if name.startswith("cuda_") and not dr.has_backend(dr.JitBackend.CUDA):
        return "no CUDA device"
    if name.startswith("llvm_"):
        if find_llvm() is None:
            return f"LLVM 19 not found: apt-get install {LLVM_PACKAGE} (or set DRJIT_LIBLLVM_PATH)"
        if not dr.has_backend(dr.JitBackend.LLVM):
            return f"Dr.Jit could not load LLVM from {os.environ.get('DRJIT_LIBLLVM_PATH')}; apt-get install {LLVM_PACKAGE}"
    return None


def any_variant():
    """The ``mitsuba`` module with some variant set, for helpers whose results do not
    depend on it (colour matching functions, colour-space conversions): the variant
    already set, else ANY_VARIANT. A variant already set is never changed."""
    mi, _ = _mitsuba()
    if not mi.variant():
        mi.set_variant(ANY_VARIANT)
    return mi


def choose_variant(name: str | None = None):
    """Set and return the Mitsuba variant: ``name``, else $TACTILE_SIM_MI_VARIANT, else
    the first usable of FALLBACK. Returns the ``mitsuba`` module."""
    mi, dr = _mitsuba()
    wanted = name or os.environ.get(VARIANT_ENV)
    if wanted:
        if wanted not in mi.variants():
            raise VariantError(f"unknown Mitsuba variant {wanted!r}; this Mitsuba has {', '.join(mi.variants())}")
        why = _usable(wanted, mi, dr)
        if why:
            raise VariantError(f"Mitsuba variant {wanted!r} cannot run here: {why}")
        mi.set_variant(wanted)
        return mi
    reasons = []
    for candidate in FALLBACK:
        why = _usable(candidate, mi, dr)
        if why is None:
            if candidate == FALLBACK[-1] and reasons:
                warnings.warn(f"using the slow {candidate} ({'; '.join(reasons)})", stacklevel=2)
            mi.set_variant(candidate)
            return mi
        reasons.append(f"{candidate}: {why}")
    raise VariantError("no usable Mitsuba variant: " + "; ".join(reasons))
