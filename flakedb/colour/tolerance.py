"""Colour differences and tolerances at multi-angle geometries: pure functions on arrays.

What is computed (docs/colour-tolerances.md states the sources and the formulas once)
------------------------------------------------------------------------------------
* **Colorimetry with a selectable observer and illuminant.**  ``observer`` "2" (CIE 1931 2°) or
  "10" (CIE 1964 10°), ``illuminant`` "D65", "A", "F11" (colour-science's ``FL11``) or any other
  name in ``colour.SDS_ILLUMINANTS``.  The weights are built exactly as
  :func:`flakedb.colorimetry.tristimulus_weights` builds its D65 / 2° ones (CIE 15:2004 §7 weighted
  sum on ≤ 1 nm nodes, the spectrum carried there by Sprague interpolation, Y = 1 for the perfect
  white); for the 2° observer they are the same numbers (tested).  CIELAB is relative to the
  perfect white integrated on the same grid, so a perfect white is exactly (100, 0, 0).
* **CIELAB differences** (CIE 15:2004, CIELAB colour differences): ΔL*, ΔC*ab, ΔH*ab = 2 √(C*₁ C*₂) sin(Δh/2) (signed,
  positive when the sample's hue angle is larger), ΔE*ab; ΔL*² + ΔC*² + ΔH*² = ΔE*ab² exactly.
* **CIEDE2000** (Sharma, Wu & Dalal 2005, Color Res. Appl. 30, 21, eqs. 1–22; CIE 142-2001),
  k_L = k_C = k_H = 1, written as three residual components e with |e|² = ΔE00²:
  e = (ΔL'/S_L, ΔC'/S_C + R_T ΔH'/(2 S_H), √(1 − R_T²/4) ΔH'/S_H).  Since |R_T| ≤ 2 sin 60° < 2
  the last factor is real; the split is the Cholesky factor of ΔE00²'s quadratic form.  A least-
  squares fit on e minimises Σ ΔE00² with a smooth residual (ΔE00 itself has a kink at zero).
  ΔE00 = |e| agrees with ``colour.delta_E(method="CIE 2000")`` (tested) and with Sharma's test pairs.
* **Metamerism index, change in illuminant** (CIE 15:2004, special metamerism index): ΔE00 of
  the pair under a test illuminant, after the multiplicative correction of the sample's test-
  illuminant XYZ by the ratio of the pair's reference-illuminant XYZ (X'₂ = X₂ X₁ʳ/X₂ʳ, Y, Z
  alike), which makes a pair that differs only by a scale factor exactly non-metameric.
* **Tolerances**: per-geometry ΔE00 limits (:class:`PerAngleLimits`), and the weighted
  ΔL*/ΔC*/ΔH* form (:class:`WeightedLCH`: per geometry
  ΔE_w = √((ΔL*/δL)² + (ΔC*/δC)² + (ΔH*/δH)²), pass when ΔE_w ≤ 1) with tolerances supplied by the
  user; docs/colour-tolerances.md says why no DIN 6175-2 / AUDI2000 coefficient table is shipped.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from flakedb.colour import colorimetry
from flakedb.colour.cie_tables import ILLUMINANT_DOMAIN_NM
from flakedb.colour.colorimetry import XYZ_to_Lab, ciede2000_terms

#: Observer names accepted → colour-science's colour matching functions.
OBSERVERS = {"2": "CIE 1931 2 Degree Standard Observer", "10": "CIE 1964 10 Degree Standard Observer"}
#: Short illuminant names → colour-science's names (others are passed through).
ILLUMINANT_ALIASES = {"F11": "FL11", "F2": "FL2", "F7": "FL7"}


def observer_name(observer) -> str:
    """colour-science's CMF name of ``observer`` ("2" / "10", also 2, 10, "2deg", "10°")."""
    key = str(observer).strip().lower().replace("deg", "").replace("°", "").strip()
    if key.endswith(".0"):
        key = key[:-2]
    if key not in OBSERVERS:
        raise ValueError(f"observer {observer!r}: use 2 (CIE 1931 2°) or 10 (CIE 1964 10°)")
    return OBSERVERS[key]


def illuminant_name(illuminant) -> str:
    """colour-science's SPD name of ``illuminant`` (D65, A, F11 → FL11, …); the tables flakedb carries
    (:data:`flakedb.colour.cie_tables.ILLUMINANT_DOMAIN_NM`) are known without importing colour-science."""
    name = ILLUMINANT_ALIASES.get(str(illuminant).upper(), str(illuminant))
    if name in ILLUMINANT_DOMAIN_NM:
        return name
    import colour  # lazy: colour-science takes ~0.5 s to import (it pulls matplotlib)

    if name not in colour.SDS_ILLUMINANTS:
        raise ValueError(f"illuminant {illuminant!r} is not in colour-science's tables "
                         f"(e.g. D65, A, F11, D50)")
    return name


def tristimulus_weights(wavelength_nm, observer="2", illuminant="D65") -> np.ndarray:
    """Weights (W, 3): XYZ = Σ_j ρ_j W[j], Y column summing to 1 (module docstring).  Read-only, cached."""
    return colorimetry.tristimulus_weights(wavelength_nm, illuminant_name(illuminant), observer_name(observer))


def reflectance_to_XYZ(values, wavelength_nm, observer="2", illuminant="D65") -> np.ndarray:
    """XYZ (..., 3), Y = 1 for the perfect white, of reflectance factors (..., W) on ``wavelength_nm`` (W,) nm."""
    v = np.asarray(values, float)
    W = tristimulus_weights(wavelength_nm, observer, illuminant)
    if v.shape[-1] != W.shape[0]:
        raise ValueError(f"values' last axis has {v.shape[-1]} samples, the grid {W.shape[0]}")
    return v @ W


def white_XYZ(wavelength_nm, observer="2", illuminant="D65") -> np.ndarray:
    """XYZ of the perfect white diffuser integrated on this grid (Y = 1)."""
    return tristimulus_weights(wavelength_nm, observer, illuminant).sum(axis=0)


def reflectance_to_Lab(values, wavelength_nm, observer="2", illuminant="D65") -> np.ndarray:
    """CIELAB (..., 3) of reflectance factors (..., W), relative to the white on the same grid."""
    return XYZ_to_Lab(reflectance_to_XYZ(values, wavelength_nm, observer, illuminant),
                      white=white_XYZ(wavelength_nm, observer, illuminant))


def XYZ_white_to_Lab(XYZ, white) -> np.ndarray:
    """CIELAB of XYZ (..., 3) relative to the XYZ ``white`` (same scale)."""
    return XYZ_to_Lab(XYZ, white=white)


# ----------------------------------------------------------------------------------------------
# Differences
# ----------------------------------------------------------------------------------------------


def lab_differences(lab_ref, lab_sample) -> dict:
    """CIELAB differences sample − reference (CIE 15:2004), arrays over leading axes.

    Returns dict ``dL``, ``da``, ``db``, ``dC`` (ΔC*ab), ``dH`` (signed ΔH*ab = 2√(C₁C₂) sin(Δh/2)),
    ``dE_ab``, ``dE00`` (:func:`delta_E_2000`), ``C_ref``, ``h_ref_deg``.
    """
    r = np.asarray(lab_ref, float)
    s = np.asarray(lab_sample, float)
    C1 = np.hypot(r[..., 1], r[..., 2])
    C2 = np.hypot(s[..., 1], s[..., 2])
    h1 = np.arctan2(r[..., 2], r[..., 1])
    h2 = np.arctan2(s[..., 2], s[..., 1])
    dh = np.angle(np.exp(1j * (h2 - h1)))  # wrapped to (−π, π]
    d = s - r
    return {
        "dL": d[..., 0], "da": d[..., 1], "db": d[..., 2], "dC": C2 - C1,
        "dH": 2.0 * np.sqrt(C1 * C2) * np.sin(dh / 2.0),
        "dE_ab": np.sqrt(np.sum(d * d, axis=-1)),
        "dE00": delta_E_2000(r, s), "C_ref": C1, "h_ref_deg": np.degrees(h1) % 360.0,
    }


def ciede2000_residuals(lab_ref, lab_sample) -> np.ndarray:
    """Residual components e (..., 3) with Σ e² = ΔE00² (module docstring: the Cholesky split)."""
    x, y, z, RT = ciede2000_terms(lab_ref, lab_sample)
    return np.stack([x, y + 0.5 * RT * z, np.sqrt(1.0 - 0.25 * RT * RT) * z], axis=-1)


def delta_E_2000(lab_ref, lab_sample) -> np.ndarray:
    """CIEDE2000 ΔE00 (Sharma et al. 2005, eq. 22), k_L = k_C = k_H = 1; arrays (..., 3) broadcast."""
    e = ciede2000_residuals(lab_ref, lab_sample)
    return np.sqrt(np.sum(e * e, axis=-1))


def metamerism_index(reflectance_ref, reflectance_sample, wavelength_nm, observer="2", reference_illuminant="D65",
                     test_illuminant="A") -> np.ndarray:
    """Special metamerism index, change in illuminant (CIE 15:2004), as ΔE00 (...,).

    The sample's XYZ under the test illuminant are corrected multiplicatively by the pair's ratio under
    the reference illuminant (X'₂ = X₂ X₁ʳ / X₂ʳ, likewise Y, Z), then ΔE00 under the test illuminant
    (both relative to its white).  Spectra (..., W) on ``wavelength_nm``.

    A flat (grey) reflectance has CIELAB L* = 100 at factor 1 under any observer and illuminant, and a
    pair of identical spectra is no metameric pair:

    >>> wl = np.arange(380.0, 781.0, 10.0)
    >>> (np.round(reflectance_to_Lab(np.ones(wl.size), wl, observer="10", illuminant="A"), 10) + 0.0).tolist()
    [100.0, 0.0, 0.0]
    >>> float(metamerism_index(np.full(wl.size, 0.5), np.full(wl.size, 0.5), wl))
    0.0
    """
    R1 = np.asarray(reflectance_ref, float)
    R2 = np.asarray(reflectance_sample, float)
    X1r = reflectance_to_XYZ(R1, wavelength_nm, observer, reference_illuminant)
    X2r = reflectance_to_XYZ(R2, wavelength_nm, observer, reference_illuminant)
    X1t = reflectance_to_XYZ(R1, wavelength_nm, observer, test_illuminant)
    X2t = reflectance_to_XYZ(R2, wavelength_nm, observer, test_illuminant)
    with np.errstate(divide="ignore", invalid="ignore"):
        X2c = np.where(X2r > 0, X2t * X1r / X2r, X2t)
    white = white_XYZ(wavelength_nm, observer, test_illuminant)
    return delta_E_2000(XYZ_to_Lab(X1t, white=white), XYZ_to_Lab(X2c, white=white))


# ----------------------------------------------------------------------------------------------
# Tolerance schemes
# ----------------------------------------------------------------------------------------------

Geometry = tuple  # (illumination_deg, aspecular_deg)


def _key(g) -> tuple:
    return (float(g[0]), float(g[1]))


@dataclass
class PerAngleLimits:
    """ΔE00 limits per geometry: ``limits`` maps (illumination_deg, aspecular_deg) → max ΔE00;
    geometries not listed get ``default``.  A policy the user states, not a standard."""

    default: float = 1.0
    limits: dict = field(default_factory=dict)
    name: str = "CIEDE2000 per-angle limits"

    def limit(self, geometry) -> float:
        return float(self.limits.get(_key(geometry), self.default))

    def evaluate(self, geometries, lab_ref, lab_sample) -> dict:
        """Per geometry: ``value`` (ΔE00), ``limit``, ``passed``; and ``passed_all``."""
        de = delta_E_2000(lab_ref, lab_sample)
        lim = np.array([self.limit(g) for g in geometries])
        ok = de <= lim
        return {"scheme": self.name, "value": de, "limit": lim, "passed": ok, "passed_all": bool(np.all(ok))}


@dataclass
class WeightedLCH:
    """Weighted ΔL*/ΔC*/ΔH* tolerances given per geometry.

    Whether DIN 6175-2 or AUDI2000 reduce to this form is not verified (docs/colour-tolerances.md).

    ``tolerances`` maps (illumination_deg, aspecular_deg) → (δL, δC, δH), the allowed ΔL*, ΔC*ab,
    ΔH*ab at that geometry (CIELAB units).  Per geometry ΔE_w = √((ΔL*/δL)² + (ΔC*/δC)² + (ΔH*/δH)²);
    the sample passes a geometry when ΔE_w ≤ 1.  Every target geometry needs an entry.
    """

    tolerances: dict
    name: str = "weighted dL*/dC*/dH* tolerances"

    def evaluate(self, geometries, lab_ref, lab_sample) -> dict:
        d = lab_differences(lab_ref, lab_sample)
        tol = []
        for g in geometries:
            if _key(g) not in {_key(k) for k in self.tolerances}:
                raise ValueError(f"{self.name}: no tolerance for geometry {g} (illumination, aspecular)")
            tol.append(next(v for k, v in self.tolerances.items() if _key(k) == _key(g)))
        tol = np.asarray(tol, float)
        if np.any(tol <= 0):
            raise ValueError(f"{self.name}: tolerances must be > 0")
        val = np.sqrt((d["dL"] / tol[:, 0]) ** 2 + (d["dC"] / tol[:, 1]) ** 2 + (d["dH"] / tol[:, 2]) ** 2)
        ok = val <= 1.0
        return {"scheme": self.name, "value": val, "limit": np.ones_like(val), "passed": ok,
                "passed_all": bool(np.all(ok))}
