"""Surfaces of revolution about the z axis with near-equilateral triangles, from an (r, z) profile.

Every generated family (``scenes.shapes``) revolves a profile: the capsule's and the pad's
as they are, the thumb's and the paw's before their map moves each vertex.
"""

from __future__ import annotations

import math

import numpy as np
import trimesh


def _resample_profile(profile: np.ndarray, edge: float) -> np.ndarray:
    """Rings along the profile, spaced by the height of an equilateral triangle."""
    seg = np.linalg.norm(np.diff(profile, axis=0), axis=1)
    s = np.concatenate([[0.0], np.cumsum(seg)])
    n = max(2, int(math.ceil(s[-1] / (edge * math.sqrt(3) / 2))))
    s_new = np.linspace(0.0, s[-1], n + 1)
    return np.stack([np.interp(s_new, s, profile[:, 0]), np.interp(s_new, s, profile[:, 1])], axis=1)


def _zip_rings(a0: int, na: int, ta: float, b0: int, nb: int, tb: float) -> list[tuple[int, int, int]]:
    """Triangulate the strip between two rings of na and nb vertices.

    Ring vertices k sit at angles t + 2 pi k / n; the strip is walked in angle order, so
    rings of different counts join with near-equilateral triangles.
    """
    # Start ring b at the vertex nearest ring a's first angle, unwrapped around it.
    shift = int(round((ta - tb) * nb / (2 * math.pi))) % nb if nb > 1 else 0
    tb0 = tb + 2 * math.pi * shift / nb
    tb0 += 2 * math.pi * round((ta - tb0) / (2 * math.pi))
    i = j = 0
    tris = []
    while i < na or j < nb:
        next_a = ta + 2 * math.pi * (i + 1) / na
        next_b = tb0 + 2 * math.pi * (j + 1) / nb
        ai, ai1 = a0 + i % na, a0 + (i + 1) % na
        bj, bj1 = b0 + (shift + j) % nb, b0 + (shift + j + 1) % nb
        if j >= nb or (i < na and next_a <= next_b):
            tris.append((ai, ai1, bj))
            i += 1
        else:
            if bj1 != bj:  # a pole (nb = 1) takes no b-steps
                tris.append((ai, bj1, bj))
            j += 1
    return tris


def revolve(profile: np.ndarray, edge: float) -> trimesh.Trimesh:
    """Surface of revolution about the z axis with near-equilateral triangles.

    Parameters
    ----------
    profile : (K, 2) float, metres
        (r, z) polyline from the open end to the far end; r = 0 at the end closes it
        with a pole vertex.
    edge : float, metres
        Target triangle edge length.

    Returns
    -------
    trimesh.Trimesh with outward-facing normals, open at the first profile ring.
    """
    profile = np.asarray(profile, dtype=np.float64)
    if profile.ndim != 2 or profile.shape[1] != 2 or len(profile) < 2:
        raise ValueError(f"profile must be (K >= 2, 2) (r, z), got shape {profile.shape}")
    if not np.all(np.isfinite(profile)) or np.any(profile[:, 0] < 0):
        raise ValueError("profile must be finite with r >= 0")
    if not edge > 0:
        raise ValueError(f"edge must be > 0 m, got {edge}")
    rings = _resample_profile(profile, edge)
    vertices, starts, counts, phases = [], [], [], []
    for k, (r, z) in enumerate(rings):
        n = 1 if r < edge * 1e-3 else max(3, int(round(2 * math.pi * r / edge)))
        phase = (k % 2) * math.pi / n
        t = phase + 2 * math.pi * np.arange(n) / n
        starts.append(sum(counts))
        counts.append(n)
        phases.append(phase)
        vertices.append(np.stack([r * np.cos(t), r * np.sin(t), np.full(n, z)], axis=1))
    faces = []
    for k in range(len(rings) - 1):
        faces += _zip_rings(starts[k], counts[k], phases[k], starts[k + 1], counts[k + 1], phases[k + 1])
    mesh = trimesh.Trimesh(np.vstack(vertices), np.array(faces, dtype=np.int64), process=False)
    # The walk above winds counter-clockwise seen from outside when z grows along the
    # profile; flip if the profile runs the other way.
    if rings[-1, 1] < rings[0, 1]:
        mesh.invert()
    return mesh
