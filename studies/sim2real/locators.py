"""Press locators: a correlation filter, a small CNN and a constant offset, each mapping
difference images to press centres (px) and depths (metres)."""

from __future__ import annotations

import numpy as np

from .press_data import Presses

MODELS = ("filter", "cnn")
#: The filter's desired response: a Gaussian of this width at the centre, px.
SIGMA_PX = 1.5
#: The filter's ridge, as a share of the training images' mean spectral power.
FILTER_RIDGE = 1e-2
#: Zero padding of the images before the Fourier transform, px each side (no wrap-around).
PAD_PX = 24
#: The depth regression's window: (2 PATCH_PX + 1) pixels a side, about the centre.
PATCH_PX = 12


def _spectra(diffs: np.ndarray) -> np.ndarray:
    """(N, 3, H', W'/2 + 1) complex: each difference image's channels, zero padded."""
    padded = np.pad(np.asarray(diffs, np.float32), ((0, 0), (PAD_PX, PAD_PX), (PAD_PX, PAD_PX), (0, 0)))
    return np.fft.rfft2(padded.transpose(0, 3, 1, 2), axes=(2, 3))


def _targets(centres: np.ndarray, shape: tuple[int, int], sigma_px: float = SIGMA_PX) -> np.ndarray:
    """(N, H', W'/2 + 1) complex: the desired responses' spectra, Gaussians at the centres."""
    h, w = shape[0] + 2 * PAD_PX, shape[1] + 2 * PAD_PX
    v, u = np.mgrid[:h, :w]
    out = []
    for cu, cv in np.asarray(centres, np.float64) + PAD_PX:
        out.append(np.exp(-((u - cu) ** 2 + (v - cv) ** 2) / (2 * sigma_px**2)))
    return np.fft.rfft2(np.asarray(out, np.float32), axes=(1, 2))


def peak(response: np.ndarray) -> tuple[float, float]:
    """The (u, v) of a response map's maximum, refined by a parabola through its
    neighbours along each axis."""
    v, u = np.unravel_index(int(np.argmax(response)), response.shape)

    def refine(a: float, b: float, c: float) -> float:
        curve = a - 2 * b + c
        return float(np.clip(0.5 * (a - c) / curve, -0.5, 0.5)) if curve < 0 else 0.0

    du = refine(response[v, u - 1], response[v, u], response[v, u + 1]) if 0 < u < response.shape[1] - 1 else 0.0
    dv = refine(response[v - 1, u], response[v, u], response[v + 1, u]) if 0 < v < response.shape[0] - 1 else 0.0
    return u + du, v + dv


def _patches(diffs: np.ndarray, centres: np.ndarray) -> np.ndarray:
    """(N, (2 PATCH_PX + 1)^2 * 3) the |change| about each centre (zero outside the frame)."""
    size = 2 * PATCH_PX + 1
    padded = np.pad(np.abs(np.asarray(diffs, np.float32)), ((0, 0), (PATCH_PX, PATCH_PX), (PATCH_PX, PATCH_PX),
                                                             (0, 0)))
    out = np.empty((len(diffs), size * size * 3), np.float32)
    for i, (u, v) in enumerate(np.rint(np.asarray(centres)).astype(int)):
        u = int(np.clip(u, 0, diffs.shape[2] - 1))
        v = int(np.clip(v, 0, diffs.shape[1] - 1))
        out[i] = padded[i, v:v + size, u:u + size].ravel()
    return out


class CorrelationLocator:
    """The ``filter`` model (module doc): ``fit(diffs, centres, depths)``, then
    ``predict(diffs) -> (centres (N, 2) px, depths (N,) metres)``."""

    def __init__(self, ridge: float = FILTER_RIDGE, sigma_px: float = SIGMA_PX):
        self.ridge = float(ridge)
        self.sigma_px = float(sigma_px)
        self.filter = None
        self.shape = None
        self.depth_model = None

    def fit(self, diffs: np.ndarray, centres: np.ndarray, depths: np.ndarray, batch: int = 64) -> "CorrelationLocator":
        from sklearn.linear_model import Ridge

        diffs = np.asarray(diffs, np.float32)
        if diffs.ndim != 4 or diffs.shape[-1] != 3 or len(diffs) != len(centres) or len(diffs) != len(depths):
            raise ValueError(f"diffs must be (N, h, w, 3) with N centres and depths, got {diffs.shape}, "
                             f"{np.shape(centres)}, {np.shape(depths)}")
        self.shape = diffs.shape[1:3]
        A = b = None
        for i in range(0, len(diffs), batch):
            X = _spectra(diffs[i:i + batch])  # (n, 3, H, W')
            G = _targets(centres[i:i + batch], self.shape, self.sigma_px)  # (n, H, W')
            a = np.einsum("nchw,ndhw->hwcd", np.conj(X), X)
            c = np.einsum("nchw,nhw->hwc", np.conj(X), G)
            A, b = (a, c) if A is None else (A + a, b + c)
        lam = self.ridge * float(np.mean(np.real(np.einsum("hwcc->hw", A)))) / 3
        self.filter = np.linalg.solve(A + lam * np.eye(3), b[..., None])[..., 0]  # (H, W', 3): conj(H) per channel
        found = self._centres(diffs)
        self.depth_model = Ridge(alpha=1.0).fit(_patches(diffs, found), np.asarray(depths, np.float64) * 1e3)
        return self

    def response(self, diffs: np.ndarray) -> np.ndarray:
        """(N, h, w) the filter's response to each difference image."""
        X = _spectra(diffs)
        R = np.einsum("hwc,nchw->nhw", self.filter, X)
        h, w = self.shape
        full = np.fft.irfft2(R, s=(h + 2 * PAD_PX, w + 2 * PAD_PX), axes=(1, 2))
        return full[:, PAD_PX:PAD_PX + h, PAD_PX:PAD_PX + w]

    def _centres(self, diffs: np.ndarray, batch: int = 64) -> np.ndarray:
        out = []
        for i in range(0, len(diffs), batch):
            out += [peak(r) for r in self.response(diffs[i:i + batch])]
        return np.array(out, np.float64).reshape(-1, 2)

    def predict(self, diffs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        if self.filter is None:
            raise RuntimeError("the locator is not fitted")
        diffs = np.asarray(diffs, np.float32)
        if diffs.shape[1:] != (*self.shape, 3):
            raise ValueError(f"diffs must be (N, {self.shape[0]}, {self.shape[1]}, 3), got {diffs.shape}")
        centres = self._centres(diffs)
        return centres, self.depth_model.predict(_patches(diffs, centres)) * 1e-3


class CNNLocator:
    """The ``cnn`` model (module doc), on the differences scaled to 8 bits about 128."""

    def __init__(self, seed: int = 0):
        self.seed = seed
        self.trained = None
        self.shape = None

    @staticmethod
    def _inputs(diffs: np.ndarray) -> np.ndarray:
        return np.clip(np.rint(128 + 255 * np.asarray(diffs)), 0, 255).astype(np.uint8)

    def fit(self, diffs: np.ndarray, centres: np.ndarray, depths: np.ndarray) -> "CNNLocator":
        from . import learn

        self.shape = diffs.shape[1:3]
        h, w = self.shape
        targets = np.c_[np.asarray(centres) / [w, h], np.asarray(depths) * 1e3].astype(np.float32)
        self.trained = learn.train("cnn", self._inputs(diffs), targets, self.seed)
        return self

    def predict(self, diffs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        h, w = self.shape
        out = self.trained.predict(self._inputs(diffs))
        return out[:, :2] * [w, h], out[:, 2] * 1e-3


class Offset:
    """A locator calibrated on real presses by a constant: ``model``'s centres less
    ``offset_px`` (u, v), its mean error (predicted less annotated) on the presses it was
    calibrated on (:meth:`fitted`). The depth is the model's own.

    This takes out a convention shared by every simulated training: where the
    annotations put a press's centre relative to where its image puts it (module doc).
    It is two numbers fitted on the real fitted half, which the width and ridge are
    already chosen on; the model itself sees simulated presses only."""

    def __init__(self, model, offset_px=(0.0, 0.0)):
        self.model = model
        self.offset_px = np.asarray(offset_px, np.float64).reshape(2)

    @classmethod
    def fitted(cls, model, presses: "Presses") -> "Offset":
        """``model`` less its mean centre error on ``presses``."""
        centres, _ = model.predict(presses.differences())
        return cls(model, np.mean(centres - presses.centres, axis=0))

    def predict(self, diffs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        centres, depths = self.model.predict(diffs)
        return centres - self.offset_px, depths


def locator(model: str, seed: int = 0):
    """A new model of ``model`` (MODELS); RuntimeError naming what to install where it needs
    what is absent."""
    if model == "filter":
        return CorrelationLocator()
    if model == "cnn":
        from . import learn

        why = learn.need("cnn")
        if why:
            raise RuntimeError(why)
        return CNNLocator(seed)
    raise ValueError(f"model must be one of {MODELS}, got {model!r}")
