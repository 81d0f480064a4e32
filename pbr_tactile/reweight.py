"""Perturbation Monte Carlo: the photon pass re-weighted to other media and paints instead of traced again.

The light pass (``pbr_tactile.photons.deposits``) traces each photon with the elastomer's
extinction sigma_t = sigma_a + sigma_s and albedo sigma_s / sigma_t, and the paint's albedo
rho. Its weight follows implicit capture: a free flight of length t is sampled with pdf
sigma_t exp(-sigma_t t) (a scattering event) or passes the next surface at distance d with
probability exp(-sigma_t d), while the path's contribution is sigma_s exp(-sigma_t t) for
the event (times the phase function, which the sampled direction cancels) and
exp(-sigma_t d) for the crossing. The weight's factor is therefore sigma_s / sigma_t at
each scattering event and 1 at each crossing; each paint bounce multiplies it by rho
(its cosine-weighted direction cancels the rest of the Lambertian BRDF). Fresnel events,
the interfaces and the LEDs' emission do not depend on (sigma_a, sigma_s, rho).

A path traced at (sigma_a, sigma_s, rho) with total length L in the elastomer, n scattering
events in it and m paint bounces has, under (sigma_a', sigma_s', rho'), the contribution
of the traced one times (the perturbation Monte Carlo factor, Hayakawa et al. 2001):

    f = (sigma_s' / sigma_s)^n exp(-(sigma_t' - sigma_t) L) (rho' / rho)^m          (1)

while its sampling pdf is unchanged: the walk is the traced one. A deposit w b (weight w,
barycentric share b) therefore becomes w b f, and a track w l (``pbr_tactile.fluence``: a
segment of length l, scored at one point drawn uniformly along it) becomes w l f(L_u),
with L_u the elastomer length up to that point (E[l f(L0 + u l)] over u ~ U(0, 1) is the
integral of f along the segment, which the variant's track-length estimate needs).

Why it stays unbiased: every other factor of the weight is a Russian-roulette or
splitting correction (1 / survival probability, 1 / copies), and those decisions depend
on the traced weight only. Conditioned on the path, each correction's expectation is 1
whatever f is, so E[sum w f] is the integral of the variant's contribution over the
traced pdf's support. That support covers the variant's wherever the traced medium
scatters when the variant does (sigma_s > 0 if sigma_s' > 0) and the traced paint
reflects when the variant's does (rho > 0 if rho' > 0); ``Perturbation.coefficients``
refuses the rest. Re-weighting draws no random numbers: the same seed gives the same
walks with and without variants. The only bias shared with the traced estimate is the
bounce cap (``pbr_tactile.photons.PHOTON_MAX_DEPTH``), which truncates both.

Unbiased is not low variance: f spreads the deposits' weights, most where the variant is
far from the traced values (f grows as exp(|delta sigma_t| L) along long paths with
sigma_t' < sigma_t; (sigma_s' / sigma_s)^n weights the many-event paths). Kish's
effective sample size of the deposits, (sum w f)^2 / sum (w f)^2, over the same for f = 1
(``ess_ratio``) says how many of the traced deposits the variant effectively keeps; below
``MIN_ESS_RATIO`` a variant is reported as not valid (trace it again).

A glossy paint (``pbr_tactile.paint``: a diffuse base and a GGX flake lobe) keeps the
medium's variants: its flake lobe's map (``pbr_tactile.photons.GlossyView``) is a sum of
the arrivals' weights times the lobe's BRDF towards the camera, which f scales as it
scales the flux. Its albedo's variants are refused: a bounce off the flake lobe carries
G1 in place of rho (``_paint_direction``), so (rho' / rho)^m would have to count the
diffuse lobe's bounces alone (trace each glossy paint's albedo again).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .effects import RANGES, Effects
from .estimate import Estimate

#: The variant parameters, one column each of a perturbation's (K, 3) array.
PARAMETERS = ("absorption_per_m", "scattering_per_m", "coating_albedo")
#: A variant whose Kish effective-sample-size ratio (``kish_ratio``) falls below this for
#: any source is reported as not valid. Measured on the GelTip's diagnosis basis (80x60
#: film, 2^16 photons, a contact; ``studies.reweight``, docs/results/reweight.md): every
#: grid variant down to a ratio of 0.17 agreed with its re-traced basis within their
#: errors (mean z^2 0.99-1.05), one at 0.001 did not (totals off by up to 31 %); the
#: variance grew as about 1 / ratio over the re-traced one's (4.6x at 0.17-0.28, 2.3x at
#: 0.41-0.45). 0.3 keeps a valid variant's variance within about 3x of tracing it again;
#: it lies between the valid grid values (0.41 and above) and scattering 110 (0.17).
MIN_ESS_RATIO = 0.3
#: Ratios of the traced to the variant coefficient this close to 1 count as equal (the
#: traced sigma_s is sigma_t times the albedo, off by an ulp from the effect's value).
SAME = 1e-12


@dataclass(frozen=True)
class Perturbation:
    """K variants of the light pass's medium and paint, each re-weighted from one traced walk.

    values : (K, 3) float64, per variant (absorption_per_m sigma_a', 1/m;
        scattering_per_m sigma_s', 1/m; coating_albedo rho', -), PARAMETERS' order.
    """

    values: np.ndarray

    def __post_init__(self):
        values = np.array(self.values, np.float64)  # a copy: it is made read-only below
        if values.ndim != 2 or values.shape[1] != len(PARAMETERS) or len(values) == 0:
            raise ValueError(f"perturb must be (K, 3) variants of ({', '.join(PARAMETERS)}) with K >= 1, got shape "
                             f"{np.shape(self.values)}")
        for column, name in enumerate(PARAMETERS):
            low, high = RANGES[name]
            bad = ~(np.isfinite(values[:, column]) & (values[:, column] >= low) & (values[:, column] <= high))
            if bad.any():
                raise ValueError(f"perturb's {name} must be within Effects' range [{low:g}, {high:g}], got "
                                 f"{values[bad, column].tolist()}")
        values.flags.writeable = False
        object.__setattr__(self, "values", values)

    @classmethod
    def of(cls, value) -> Perturbation:
        """A Perturbation, or one of a (K, 3) array-like."""
        return value if isinstance(value, Perturbation) else cls(np.asarray(value, np.float64))

    @classmethod
    def of_effects(cls, effects: list[Effects]) -> Perturbation:
        """The variants' columns read from Effects (their other fields are the caller's to match)."""
        return cls(np.array([[getattr(e, name) for name in PARAMETERS] for e in effects], np.float64))

    def __len__(self) -> int:
        return len(self.values)

    def key(self) -> list:
        """What a render depends on, for cache keys."""
        return self.values.tolist()

    def effects(self, traced: Effects) -> list[Effects]:
        """Each variant as the traced Effects with its three values."""
        from dataclasses import replace

        return [replace(traced, **{name: float(v) for name, v in zip(PARAMETERS, row)}) for row in self.values]

    def coefficients(self, sigma_t: float, albedo: float, rho: float, gloss: float = 0.0) -> np.ndarray:
        """(K, 3) float64 the exponents of equation (1) per variant, against the traced
        sigma_t (1/m), albedo (-) and paint albedo rho (-): ln(sigma_s' / sigma_s) per
        scattering event (-inf where sigma_s' = 0), sigma_t' - sigma_t (1/m) per metre in
        the elastomer, ln(rho' / rho) per paint bounce (-inf where rho' = 0).

        Refuses variants the traced walk cannot represent: scattering where the traced
        medium has none, a reflecting paint where the traced one is black, another paint
        albedo where the traced paint is glossy (``gloss`` > 0: module doc)."""
        sigma_s = sigma_t * albedo if sigma_t > 0 else 0.0
        sa, ss, rr = self.values.T
        out = np.zeros((len(self), 3))
        if sigma_s <= 0 and np.any(ss > 0):
            raise ValueError(f"perturb: scattering_per_m {ss[ss > 0].tolist()} cannot be re-weighted from a traced "
                             f"medium without scattering (its walks never scatter); trace it again")
        other_paint = np.abs(rr - rho) > SAME
        if gloss > 0 and np.any(other_paint):
            raise ValueError(f"perturb: coating_albedo {rr[other_paint].tolist()} cannot be re-weighted from a glossy "
                             f"traced paint (coating_gloss {gloss:g}: a flake bounce does not scale with the albedo); "
                             f"trace it again")
        if rho <= 0 and np.any(rr > 0):
            raise ValueError(f"perturb: coating_albedo {rr[rr > 0].tolist()} cannot be re-weighted from a black "
                             f"traced paint (its photons end on the paint); trace it again")
        with np.errstate(divide="ignore"):
            out[:, 0] = np.log(ss / sigma_s) if sigma_s > 0 else 0.0
            out[:, 2] = np.log(rr / rho) if rho > 0 else 0.0
        out[:, 1] = (sa + ss) - sigma_t
        for column in (0, 2):
            out[np.abs(out[:, column]) < SAME, column] = 0.0
        out[np.abs(out[:, 1]) < SAME * max(sigma_t, 1.0), 1] = 0.0
        return out


def path_factor(dr, coefficient, length, scatters, bounces):
    """Dr.Jit: equation (1)'s f for one variant, from its ``coefficients`` row (three
    scalars: ln(sigma_s' / sigma_s), sigma_t' - sigma_t 1/m, ln(rho' / rho)) and a lane's
    elastomer ``length`` L (Float, m), scattering events n and paint bounces m (UInt32).
    A count of 0 contributes 1 whatever its coefficient (0^0 = 1 where the variant has no
    scattering or a black paint). The values enter the kernel as opaque scalars, so that
    other variants of the same shape reuse it."""
    Float = type(length)
    log_s, delta_t, log_rho = (float(c) for c in coefficient)
    exponent = -dr.opaque(Float, delta_t) * length
    if log_s != 0.0:
        exponent += dr.select(scatters > 0, dr.opaque(Float, log_s) * Float(scatters), 0.0)
    if log_rho != 0.0:
        exponent += dr.select(bounces > 0, dr.opaque(Float, log_rho) * Float(bounces), 0.0)
    return dr.exp(exponent)


def path_factor_np(coefficient, length, scatters, bounces) -> np.ndarray:
    """NumPy twin of ``path_factor`` (float64), for checks."""
    log_s, delta_t, log_rho = (float(c) for c in coefficient)
    length, scatters, bounces = (np.asarray(a, np.float64) for a in (length, scatters, bounces))
    with np.errstate(invalid="ignore"):
        exponent = -delta_t * length + np.where(scatters > 0, log_s * scatters, 0.0) \
            + np.where(bounces > 0, log_rho * bounces, 0.0)
    return np.exp(exponent)


def kish_ratio(moments: np.ndarray) -> np.ndarray:
    """(K, S) each variant's Kish effective sample size over the traced deposits' own.

    moments : (K + 1, S, 2) per row (the traced walk first, f = 1, then each variant) and
        source, the deposits' sum of w f and of (w f)^2 (``Reweighted.moments``).
    ESS = (sum w f)^2 / sum (w f)^2; a source with no deposits gives 1 (nothing to
    re-weight), a variant whose deposits are all 0 gives 0.
    """
    m = np.asarray(moments, np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        ess = np.where(m[..., 1] > 0, m[..., 0] ** 2 / m[..., 1], 0.0)
        ratio = np.where(ess[:1] > 0, ess[1:] / ess[:1], 1.0)
    return ratio


@dataclass(frozen=True)
class Reweighted:
    """The light pass's deposits under each variant of a ``Perturbation``.

    flux : (K, S, V) float64 (K, S, PATH_CLASSES, V with classes) flux per unit flux
        emitted, as ``deposits`` returns the traced one; track : (K, S, N) m per unit flux
        emitted with a fluence grid, else None; moments : (K + 1, S, 2) the deposits'
        sum of w f and of (w f)^2, the traced walk's (f = 1) first (``kish_ratio``);
        lobe : (K, S, V) a glossy paint's flake-lobe flux (``GlossyView.flux``) under
        each variant, else None.
    """

    flux: np.ndarray
    track: np.ndarray | None
    moments: np.ndarray
    lobe: np.ndarray | None = None

    @property
    def ess_ratio(self) -> np.ndarray:
        """(K, S) each variant's Kish effective sample size over the traced one's."""
        return kish_ratio(self.moments)


def valid(ess_ratio: np.ndarray, threshold: float = MIN_ESS_RATIO) -> np.ndarray:
    """(K,) bool: the variants whose ESS ratio (K, S) is at least ``threshold`` for every source."""
    return np.all(np.asarray(ess_ratio) >= threshold, axis=-1)


@dataclass(frozen=True)
class VariantEstimates:
    """A render and its variants (``pbr_tactile.render.render_photons(perturb=)``).

    traced : the Estimate at the traced effects; variants : one Estimate per variant, from
    the same passes (each variant's variance across passes is its own Monte Carlo
    error); perturbation : the variants; ess_ratio : (K, S) the Kish ratio over every
    deposit the render used (``kish_ratio``); valid : (K,) bool, ``valid(ess_ratio)``.
    """

    traced: Estimate
    variants: tuple[Estimate, ...]
    perturbation: Perturbation
    ess_ratio: np.ndarray

    @property
    def valid(self) -> np.ndarray:
        return valid(self.ess_ratio)


def variant_media(perturbation: Perturbation) -> list[tuple[float, float, float]]:
    """(sigma_t' 1/m, albedo', rho') per variant, as the walks take them."""
    out = []
    for sa, ss, rho in perturbation.values:
        sigma_t = float(sa + ss)
        out.append((sigma_t, float(ss / sigma_t) if sigma_t > 0 else 0.0, float(rho)))
    return out

