"""Random streams keyed by a path's identity, so that two renders of one seed share their walks.

``splitmix`` hashes integers (a seed, a photon's number, a copy's) into 64-bit identities
and ``sampler_seed`` into Mitsuba sampler seeds; ``Rng`` gives each Dr.Jit lane the PCG32
stream of its photon's or camera ray's identity, whichever lane it lands in (common
random numbers between a contact and the no-contact frame).
"""

from __future__ import annotations

import typing

import numpy as np

from .transport import owned


def splitmix(*parts: np.ndarray) -> np.ndarray:
    """A 64-bit hash (SplitMix64 steps) of integer arrays, element-wise."""
    with np.errstate(over="ignore"):
        h = np.zeros(np.broadcast(*parts).shape, dtype=np.uint64)
        for part in parts:
            h = (h ^ np.asarray(part).astype(np.uint64)) + np.uint64(0x9E3779B97F4A7C15)
            h = (h ^ (h >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
            h = (h ^ (h >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
            h = h ^ (h >> np.uint64(31))
    return h


def sampler_seed(*parts: int) -> int:
    """One 32-bit sampler seed from several integers (pass, batch)."""
    return int(splitmix(*(np.uint64(p % (1 << 64)) for p in parts)) & np.uint64(0xFFFFFFFF))


class Rng:
    """Per-lane random streams keyed by a 64-bit identity, not by lane position.

    A photon (or camera ray) keeps its own stream whichever lane it lands in, so two
    renders with the same seed (a contact and the no-contact frame) trace the same
    walks wherever the geometry is the same: common random numbers, which keep the
    noise of a contact's change image down to the paths the contact actually changed.
    Offers the two sampler methods the walks use, and travels as Dr.Jit loop state.
    """

    DRJIT_STRUCT: typing.ClassVar[dict] = {"pcg": object}

    def __init__(self, mi=None, identity: np.ndarray | None = None):
        if mi is None:
            return
        import drjit as dr

        n = len(identity)
        # PCG32 adds arange(n) to both words; take it back so only the identity counts.
        offset = dr.arange(mi.UInt64, n)
        state = owned(mi.UInt64, splitmix(identity, np.uint64(1)))
        sequence = owned(mi.UInt64, splitmix(identity, np.uint64(2)))
        self.pcg = mi.PCG32(n, state - offset, sequence - offset)

    def next_1d(self, active=True):
        return self.pcg.next_float32(active)

    def next_2d(self, active=True):
        import mitsuba as mi

        return mi.Point2f(self.pcg.next_float32(active), self.pcg.next_float32(active))
