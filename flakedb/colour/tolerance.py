"""Colour differences and tolerances at multi-angle geometries: pure functions on arrays.

What is computed (docs/colour-tolerances.md states the sources and the formulas once)
------------------------------------------------------------------------------------
* **Colorimetry with a stated observer and illuminant** (always passed: no default here, the product's
  defaults live in :mod:`flakedb.colour.settings`).  ``observer`` "2" (CIE 1931 2°) or "10" (CIE 1964 10°), ``illuminant`` "D65", "A", "F11" (colour-science's ``FL11``) or any other
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
* **Formulas** (``--formula``; :data:`FORMULAS`, :func:`parse_formula` → :class:`Formula`): ΔE00 with
  k_L:k_C:k_H, ΔE94 (graphic arts / textiles), CMC(l:c), DIN99 (graphic arts / textiles) and ΔE*ab, each
  as three residual components e with |e| = ΔE; each equals colour-science's ``colour.delta_E`` (the
  registry names its method) on Sharma's test pairs (tested).  :func:`shade_words` words a difference
  as QC reports do ("lighter, less yellow, greener"); :func:`lch` gives C*ab and h_ab.
* **Tolerances**: per-geometry ΔE limits in a formula (:class:`PerAngleLimits`), and the weighted
  ΔL*/ΔC*/ΔH* form (:class:`WeightedLCH`: per geometry
  ΔE_w = √((ΔL*/δL)² + (ΔC*/δC)² + (ΔH*/δH)²), pass when ΔE_w ≤ 1) with tolerances supplied by the
  user; docs/colour-tolerances.md says why no DIN 6175-2 / AUDI2000 coefficient table is shipped.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from flakedb.colour import colorimetry
from flakedb.colour.cie_tables import ILLUMINANT_DOMAIN_NM
from flakedb.colour.colorimetry import XYZ_to_Lab, ciede2000_terms
from flakedb.colour.geometry import key as geometry_key

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


def tristimulus_weights(wavelength_nm, observer, illuminant) -> np.ndarray:
    """Weights (W, 3): XYZ = Σ_j ρ_j W[j], Y column summing to 1 (module docstring).  Read-only, cached."""
    return colorimetry.tristimulus_weights(wavelength_nm, illuminant_name(illuminant), observer_name(observer))


def reflectance_to_XYZ(values, wavelength_nm, observer, illuminant) -> np.ndarray:
    """XYZ (..., 3), Y = 1 for the perfect white, of reflectance factors (..., W) on ``wavelength_nm`` (W,) nm."""
    v = np.asarray(values, float)
    W = tristimulus_weights(wavelength_nm, observer, illuminant)
    if v.shape[-1] != W.shape[0]:
        raise ValueError(f"values' last axis has {v.shape[-1]} samples, the grid {W.shape[0]}")
    return v @ W


def white_XYZ(wavelength_nm, observer, illuminant) -> np.ndarray:
    """XYZ of the perfect white diffuser integrated on this grid (Y = 1)."""
    return tristimulus_weights(wavelength_nm, observer, illuminant).sum(axis=0)


def reflectance_to_Lab(values, wavelength_nm, observer, illuminant) -> np.ndarray:
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
    """Residual components e (..., 3) with Σ e² = ΔE00² (module docstring: the Cholesky split), k = 1."""
    return _residuals_cie2000(lab_ref, lab_sample, (1.0, 1.0, 1.0))


def delta_E_2000(lab_ref, lab_sample) -> np.ndarray:
    """CIEDE2000 ΔE00 (Sharma et al. 2005, eq. 22), k_L = k_C = k_H = 1; arrays (..., 3) broadcast."""
    e = ciede2000_residuals(lab_ref, lab_sample)
    return np.sqrt(np.sum(e * e, axis=-1))


def metamerism_index(reflectance_ref, reflectance_sample, wavelength_nm, observer, reference_illuminant,
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
    >>> float(metamerism_index(np.full(wl.size, 0.5), np.full(wl.size, 0.5), wl, "2", "D65"))
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
# Colour-difference formulas (the --formula registry)
# ----------------------------------------------------------------------------------------------
#
# Every formula is written as three residual components e (..., 3) whose Euclidean norm is its ΔE,
# so a least-squares fit minimises Σ ΔE² with a smooth residual and the reported value is the norm
# of the same components.  Each equals colour-science's ``colour.delta_E(method=…)`` (the registry's
# ``method`` and ``colour_kwargs``) on Sharma, Wu & Dalal's (2005) test pairs to 1e-10 (tested) for
# every parameter setting colour-science offers.


def _lch(lab):
    lab = np.asarray(lab, float)
    return lab[..., 0], np.hypot(lab[..., 1], lab[..., 2]), np.arctan2(lab[..., 2], lab[..., 1])


def _dL_dC_dH(lab_ref, lab_sample):
    """ΔL*, ΔC*ab and signed ΔH*ab = 2√(C₁C₂) sin(Δh/2) (CIE 15:2004; ΔH² = Δa² + Δb² − ΔC² exactly)."""
    L1, C1, h1 = _lch(lab_ref)
    L2, C2, h2 = _lch(lab_sample)
    dh = np.angle(np.exp(1j * (h2 - h1)))
    return L2 - L1, C2 - C1, 2.0 * np.sqrt(C1 * C2) * np.sin(dh / 2.0), L1, C1, h1


def _residuals_cie1976(lab_ref, lab_sample, factors):
    """ΔE*ab (CIE 15:2004): e = (ΔL*, Δa*, Δb*)."""
    return np.asarray(lab_sample, float) - np.asarray(lab_ref, float)


def _residuals_cie1994(lab_ref, lab_sample, factors):
    """ΔE*94 (CIE 116-1995): e = (ΔL*/(k_L S_L), ΔC*/(k_C S_C), ΔH*/(k_H S_H)), S_L = 1, S_C = 1 + K₁C*₁,
    S_H = 1 + K₂C*₁ with C*₁ the reference's chroma; graphic arts k_L = 1, K₁ = 0.045, K₂ = 0.015;
    ``textiles`` (factors (2,)): k_L = 2, K₁ = 0.048, K₂ = 0.014 (colour-science's ``textiles=True``)."""
    textiles = factors == (2.0,)
    kL, K1, K2 = (2.0, 0.048, 0.014) if textiles else (1.0, 0.045, 0.015)
    dL, dC, dH, _, C1, _ = _dL_dC_dH(lab_ref, lab_sample)
    return np.stack([dL / kL, dC / (1.0 + K1 * C1), dH / (1.0 + K2 * C1)], axis=-1)


def _residuals_cmc(lab_ref, lab_sample, factors):
    """CMC(l:c) (F. J. J. Clarke, R. McDonald, B. Rigg, J. Soc. Dyers Colour. 100, 128 (1984); BS 6923):
    e = (ΔL*/(l S_L), ΔC*/(c S_C), ΔH*/S_H) with S_L, S_C, S_H of the reference (L*₁, C*₁, h₁)."""
    l, c = factors
    dL, dC, dH, L1, C1, h1 = _dL_dC_dH(lab_ref, lab_sample)
    SL = np.where(L1 < 16.0, 0.511, 0.040975 * L1 / (1.0 + 0.01765 * L1))
    SC = 0.0638 * C1 / (1.0 + 0.0131 * C1) + 0.638
    hd = np.degrees(h1) % 360.0
    T = np.where((hd >= 164.0) & (hd <= 345.0), 0.56 + np.abs(0.2 * np.cos(np.radians(hd + 168.0))),
                 0.36 + np.abs(0.4 * np.cos(np.radians(hd + 35.0))))
    C4 = C1**4
    F = np.sqrt(C4 / (C4 + 1900.0))
    SH = SC * (F * T + 1.0 - F)
    return np.stack([dL / (l * SL), dC / (c * SC), dH / SH], axis=-1)


def _residuals_cie2000(lab_ref, lab_sample, factors):
    """CIEDE2000 with parametric factors k_L:k_C:k_H (Sharma et al. 2005, eq. 22): the Cholesky split
    of the module docstring applied to (ΔL'/(k_L S_L), ΔC'/(k_C S_C), ΔH'/(k_H S_H))."""
    kL, kC, kH = factors
    x, y, z, RT = ciede2000_terms(lab_ref, lab_sample)
    x, y, z = x / kL, y / kC, z / kH
    return np.stack([x, y + 0.5 * RT * z, np.sqrt(1.0 - 0.25 * RT * RT) * z], axis=-1)


def _residuals_din99(lab_ref, lab_sample, factors):
    """ΔE99 (DIN 6176:2001): the Euclidean difference of colour-science's DIN99 coordinates
    (``colour.Lab_to_DIN99`` with k_E, k_CH; ``textiles``, factors (2,), is k_E = 2, k_CH = 0.5)."""
    import colour  # lazy: only this formula needs colour-science at run time (~0.5–1.5 s import)

    kE, kCH = (2.0, 0.5) if factors == (2.0,) else (1.0, 1.0)
    return colour.Lab_to_DIN99(np.asarray(lab_sample, float), kE, kCH) - colour.Lab_to_DIN99(
        np.asarray(lab_ref, float), kE, kCH)


@dataclass(frozen=True)
class _FormulaKind:
    label: str
    method: str                 # colour-science's DELTA_E_METHODS name
    factor_names: tuple         # what "name:f1:f2…" sets
    default_factors: tuple
    residuals: object           # (lab_ref, lab_sample, factors) -> e (..., 3)
    colour_kwargs: object       # factors -> colour.delta_E keyword arguments, None where colour-science has none
    textiles: bool = False      # "name:textiles" selects factors (2,)


def _textiles_kwargs(f):
    return {"textiles": f == (2.0,)}


#: The formulas of ``--formula`` (key → kind); :func:`parse_formula` reads "key[:f1[:f2…]]".
FORMULAS = {
    "de00": _FormulaKind("dE00", "CIE 2000", ("kL", "kC", "kH"), (1.0, 1.0, 1.0), _residuals_cie2000,
                         lambda f: ({"textiles": f == (2.0, 1.0, 1.0)} if f in ((1.0, 1.0, 1.0), (2.0, 1.0, 1.0))
                                    else None)),
    "de94": _FormulaKind("dE94", "CIE 1994", (), (1.0,), _residuals_cie1994, _textiles_kwargs, textiles=True),
    "cmc": _FormulaKind("dE CMC", "CMC", ("l", "c"), (2.0, 1.0), _residuals_cmc, lambda f: {"l": f[0], "c": f[1]}),
    "din99": _FormulaKind("dE99", "DIN99", (), (1.0,), _residuals_din99, _textiles_kwargs, textiles=True),
    "deab": _FormulaKind("dE*ab", "CIE 1976", (), (), _residuals_cie1976, lambda f: {}),
}


@dataclass(frozen=True)
class Formula:
    """A colour-difference formula of :data:`FORMULAS` with its parametric factors."""

    key: str = "de00"
    factors: tuple = (1.0, 1.0, 1.0)

    @property
    def kind(self) -> _FormulaKind:
        return FORMULAS[self.key]

    @property
    def label(self) -> str:
        """e.g. "dE00", "dE00(2:1:1)", "dE CMC(2:1)", "dE94 textiles"."""
        k = self.kind
        if k.textiles:
            return k.label + (" textiles" if self.factors == (2.0,) else "")
        if self.key == "de00" and self.factors == k.default_factors:
            return k.label
        return k.label + ("(" + ":".join(f"{v:g}" for v in self.factors) + ")" if self.factors else "")

    def residuals(self, lab_ref, lab_sample) -> np.ndarray:
        """Components e (..., 3) with |e| = ΔE of this formula (sample against reference)."""
        return self.kind.residuals(lab_ref, lab_sample, self.factors)

    def delta_E(self, lab_ref, lab_sample) -> np.ndarray:
        """ΔE (...,) of this formula, sample against reference (arrays (..., 3) broadcast)."""
        e = self.residuals(lab_ref, lab_sample)
        return np.sqrt(np.sum(e * e, axis=-1))


#: The default formula of compare and match.
DE00 = Formula()


def parse_formula(text) -> Formula:
    """``de00``, ``de00:kL:kC:kH``, ``de94``, ``de94:textiles``, ``cmc`` (2:1), ``cmc:l:c``, ``din99``,
    ``din99:textiles``, ``deab`` → :class:`Formula`; ValueError naming the forms otherwise.

    >>> parse_formula("cmc:1:1").label, parse_formula("de00:2:1:1").label, parse_formula("DE94:textiles").label
    ('dE CMC(1:1)', 'dE00(2:1:1)', 'dE94 textiles')
    """
    forms = ("de00, de00:kL:kC:kH (e.g. de00:2:1:1), de94, de94:textiles, cmc (= cmc:2:1), cmc:l:c "
             "(e.g. cmc:1:1), din99, din99:textiles, deab")
    parts = str(text).strip().lower().split(":")
    kind = FORMULAS.get(parts[0])
    if kind is None:
        raise ValueError(f"formula {text!r}: use one of {forms}")
    rest = parts[1:]
    if not rest:
        return Formula(parts[0], kind.default_factors)
    if kind.textiles and rest == ["textiles"]:
        return Formula(parts[0], (2.0,))
    try:
        values = tuple(float(v) for v in rest)
    except ValueError:
        values = ()
    if len(values) != len(kind.factor_names) or not values or not all(math.isfinite(v) and v > 0 for v in values):
        raise ValueError(f"formula {text!r}: {parts[0]} takes "
                         + (f"{len(kind.factor_names)} factor(s) {':'.join(kind.factor_names)}, each a finite "
                            f"number > 0" if kind.factor_names else "no factors" + (" (or :textiles)" if kind.textiles else ""))
                         + f"; the forms are {forms}")
    return Formula(parts[0], values)


#: Components of a shade description below this (CIELAB units) are not named: a policy, about the
#: 0.05 resolution of a two-decimal report, not a standard.
SHADE_MIN_DIFFERENCE = 0.05


def shade_words(lab_ref, lab_sample, min_difference=SHADE_MIN_DIFFERENCE) -> list:
    """How the sample differs from the reference, as QC reports word it ("lighter, less yellow, greener").

    Per geometry (arrays (..., 3) → a list of strings, row-major over the leading axes): ΔL* > 0
    "lighter", < 0 "darker"; on a* and b*, "less red" / "less green" / "less yellow" / "less blue" when
    the sample stays on the reference's side of the axis nearer to neutral, else the direction
    ("redder", "greener", "yellower", "bluer"); components with |Δ| < ``min_difference`` are left out
    ("same" when all are).

    >>> shade_words([60.0, -5.0, 30.0], [61.0, -6.0, 27.0])
    ['lighter, greener, less yellow']
    """
    r = np.atleast_2d(np.asarray(lab_ref, float)).reshape(-1, 3)
    s = np.broadcast_to(np.asarray(lab_sample, float), np.broadcast_shapes(np.shape(lab_ref), np.shape(lab_sample)))
    s = s.reshape(-1, 3)
    r = np.broadcast_to(r, s.shape)
    out = []
    for (L1, a1, b1), (L2, a2, b2) in zip(r, s):
        words = []
        if abs(L2 - L1) >= min_difference:
            words.append("lighter" if L2 > L1 else "darker")
        for v1, v2, pos, neg in ((a1, a2, "red", "green"), (b1, b2, "yellow", "blue")):
            if abs(v2 - v1) < min_difference:
                continue
            toward_neutral = v1 != 0 and v1 * v2 >= 0 and abs(v2) < abs(v1)
            if toward_neutral:
                words.append(f"less {pos if v1 > 0 else neg}")
            else:
                words.append({"red": "redder", "green": "greener", "yellow": "yellower", "blue": "bluer"}[
                    pos if v2 > v1 else neg])
        out.append(", ".join(words) or "same")
    return out


def lch(lab) -> np.ndarray:
    """CIELAB (..., 3) → (L*, C*ab, h_ab in degrees [0, 360)) (..., 3) (CIE 15:2004)."""
    L, C, h = _lch(lab)
    return np.stack([L, C, np.degrees(h) % 360.0], axis=-1)


# ----------------------------------------------------------------------------------------------
# Tolerance schemes
# ----------------------------------------------------------------------------------------------

Geometry = tuple  # (illumination_deg, aspecular_deg[, azimuth_deg]): flakedb.colour.geometry


def _key(g) -> tuple:
    return geometry_key(g)


@dataclass
class PerAngleLimits:
    """ΔE limits per geometry in a colour-difference ``formula`` (:class:`Formula`, default ΔE00):
    ``limits`` maps (illumination_deg, aspecular_deg) → max ΔE; geometries not listed get ``default``.
    A policy the user states, not a standard."""

    default: float = 1.0
    limits: dict = field(default_factory=dict)
    formula: Formula = DE00
    name: str = ""

    def __post_init__(self):
        if not self.name:
            self.name = ("CIEDE2000" if self.formula == DE00 else self.formula.label) + " per-angle limits"

    def limit(self, geometry) -> float:
        return float(self.limits.get(_key(geometry), self.default))

    def residuals(self, lab_ref, lab_sample) -> np.ndarray:
        """The formula's residual components (..., 3), |e| = ΔE: what a fit to this scheme minimises."""
        return self.formula.residuals(lab_ref, lab_sample)

    def evaluate(self, geometries, lab_ref, lab_sample) -> dict:
        """Per geometry: ``value`` (ΔE of the formula), ``limit``, ``passed``; and ``passed_all``, ``formula``."""
        de = self.formula.delta_E(lab_ref, lab_sample)
        lim = np.array([self.limit(g) for g in geometries])
        ok = de <= lim
        return {"scheme": self.name, "formula": self.formula.label, "value": de, "limit": lim, "passed": ok,
                "passed_all": bool(np.all(ok))}


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
