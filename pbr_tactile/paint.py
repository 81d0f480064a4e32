"""The membrane's paint: a diffuse base and a specular flake lobe, one model for every estimator.

GelSight coatings range from matte (aluminium powder) to semi-specular (aluminium or
bronze flake; Yuan et al. 2017, Fig. 4). The paint here is the linear blend of the two
that Mitsuba's ``blendbsdf`` evaluates:

    f(w_i, w_o) = (1 - g) rho / pi + g rho D(h) G(w_i, w_o) / (4 cos(theta_i) cos(theta_o))

with rho the paint's albedo (``Effects.coating_albedo``), g the specular share
(``Effects.coating_gloss``) and D, G the GGX (Trowbridge-Reitz) distribution of the
flakes' normals and its Smith shadowing, of roughness alpha (``Effects.coating_roughness``).
The lobe is a conductor's with a flat reflectance rho (Mitsuba's ``roughconductor`` with
``material = "none"``): flakes are metal, and the transport stays grey.

``Paint.mitsuba`` gives the BSDF volpath renders; ``sample_glossy`` and ``glossy_cos`` give
the same lobe to the photon estimator (``pbr_tactile.photons``), with Mitsuba's own
microfacet distribution, so both estimators integrate one BRDF. The paint is seen from the
elastomer's side; both sides reflect alike (``twosided``).
"""

from __future__ import annotations

from dataclasses import dataclass

#: GGX roughness of the flake lobe where an effect does not set it: an estimate (a
#: semi-specular coating's highlight spans tens of degrees; alpha 0.1 to 0.5).
DEFAULT_ROUGHNESS = 0.3


@dataclass(frozen=True)
class Paint:
    """albedo rho in [0, 1]; gloss g in [0, 1], the lobe's share; roughness alpha > 0."""

    albedo: float
    gloss: float = 0.0
    roughness: float = DEFAULT_ROUGHNESS

    def __post_init__(self):
        for name, value, low, high in (("albedo", self.albedo, 0.0, 1.0), ("gloss", self.gloss, 0.0, 1.0),
                                       ("roughness", self.roughness, 1e-3, 1.0)):
            if not low <= float(value) <= high:
                raise ValueError(f"paint {name} must be in [{low:g}, {high:g}], got {value}")
            # plain floats: a NumPy scalar times a Dr.Jit array would evaluate it inside the photons' loop
            object.__setattr__(self, name, float(value))

    @classmethod
    def of(cls, value) -> Paint:
        """A Paint, or a matte one of albedo ``value`` (a number)."""
        return value if isinstance(value, Paint) else cls(float(value))

    @classmethod
    def from_effects(cls, effects) -> Paint:
        return cls(effects.coating_albedo, effects.coating_gloss, effects.coating_roughness)

    @property
    def glossy(self) -> bool:
        return self.gloss > 0

    @property
    def diffuse(self) -> float:
        """The diffuse lobe's albedo, (1 - g) rho."""
        return (1.0 - self.gloss) * self.albedo

    def key(self) -> tuple:
        """What a render depends on, for cache keys (a matte paint: its albedo, as before)."""
        return (self.albedo,) if not self.glossy else (self.albedo, self.gloss, self.roughness)

    def mitsuba(self) -> dict:
        """The paint as a Mitsuba BSDF dict, reflecting on both sides."""
        grey = {"type": "rgb", "value": [self.albedo] * 3}
        diffuse = {"type": "diffuse", "reflectance": grey}
        if not self.glossy:
            return {"type": "twosided", "material": diffuse}
        flakes = {"type": "roughconductor", "material": "none", "distribution": "ggx", "alpha": self.roughness,
                  "specular_reflectance": grey}
        return {"type": "twosided",
                "material": {"type": "blendbsdf", "weight": self.gloss, "bsdf_0": diffuse, "bsdf_1": flakes}}

    def distribution(self, mi):
        """Mitsuba's GGX distribution of the flakes, sampling visible normals (as roughconductor)."""
        return mi.MicrofacetDistribution(mi.MicrofacetType.GGX, self.roughness, True)

    def sample_glossy(self, mi, dr, normal, wi, u):
        """A direction w_o from the lobe, seen from ``wi`` (unit, pointing away from the
        surface) about ``normal`` (the side ``wi`` is on), and its weight
        rho D G cos(theta_o) / (4 cos(theta_i) pdf(w_o)) = rho G1(w_o): (w_o, weight), the
        weight 0 where w_o falls below the surface."""
        frame = mi.Frame3f(normal)
        local = frame.to_local(wi)
        distr = self.distribution(mi)
        m, _ = distr.sample(local, u)
        out = 2 * dr.dot(local, m) * m - local
        weight = dr.select((out.z > 0) & (local.z > 0), self.albedo * distr.smith_g1(out, m), 0.0)
        return frame.to_world(out), weight

    def glossy_cos(self, mi, dr, normal, wi, wo):
        """The lobe's rho D(h) G(w_i, w_o) / (4 cos(theta_i)): its BRDF times cos(theta_o), 0
        where either direction is below the surface."""
        frame = mi.Frame3f(normal)
        a, b = frame.to_local(wi), frame.to_local(wo)
        h = dr.normalize(a + b)
        distr = self.distribution(mi)
        value = self.albedo * distr.eval(h) * distr.G(a, b, h) / (4 * dr.maximum(a.z, 1e-8))
        return dr.select((a.z > 0) & (b.z > 0), value, 0.0)
