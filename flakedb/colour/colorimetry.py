"""Colour from spectra: CIE 1931 2° XYZ, linear sRGB, CIELAB, CIEDE2000, and the paper's RGB mode.

The CIE tables are colour-science's (``colour.MSDS_CMFS``: CIE 1931 2° and CIE 1964 10° observers,
360–830 nm at 1 nm; ``colour.SDS_ILLUMINANTS``: D65 and A 300–780 nm, FL11 380–780 nm at 5 nm,
CIE 15:2004), evaluated at the integration nodes with the interpolator colour-science attaches to each
table (Sprague 1880 for the CMFs, linear for the illuminants as CIE 15 recommends).  Nothing is
hand-copied.  The **default path** does not import colour-science (it takes 0.5–1.5 s to import:
issue 11): for the 2° and 10° observers, illuminants D65, A and FL11 and grids whose fine nodes (below)
are integer nm, the values colour-science returns at those nodes are read from
:mod:`flakedb.colour.cie_tables` (generated from colour-science by ``tools/make_cie_tables.py``), the
grid → fine-node map is :func:`flakedb.colour.sprague.sprague_matrix` (CIE 167:2005), the sRGB matrix
is computed from the IEC 61966-2-1 primaries (:func:`srgb_matrices`), and CIELAB and CIEDE2000 are
implemented here; each equals colour-science's result to ≤ 1e-12 (relative; tests/colour/, measured
7e-16).  Every other case (another illuminant or observer, fine nodes off the integer nm) runs the
colour-science code, :func:`tristimulus_weights_colour_science`.  docs/colorimetry.md.

Normalisation and integration (stated once, used everywhere here)
-----------------------------------------------------------------
For a reflectance-type spectrum ρ(λ) (reflectance, transmittance, a BSDF value times π: anything
that is 1 for a perfect white) sampled on a uniform grid λ_j,

    X = k Σ_f S(λ_f) x̄(λ_f) ρ(λ_f),   (Y, Z likewise),   k = 1 / Σ_f S(λ_f) ȳ(λ_f),

the CIE 15:2004 §7 weighted sum, taken on fine nodes λ_f that split each grid step into
ceil(step / 1 nm) equal parts (the grid itself when its step is 1 nm).  ρ is carried from the grid
to the fine nodes by Sprague (1880) interpolation (:func:`flakedb.colour.sprague.sprague_matrix`, the
method CIE 167:2005 recommends for uniform data, equal to colour's ``SpragueInterpolator``).  Since that
interpolation is linear in ρ, the whole thing is one weighted sum on the grid, X = Σ_j W_j ρ_j,
with weights W (:func:`tristimulus_weights`) computed once per grid.  **Y = 1 for the perfect white
diffuser** (colour-science's own functions return Y = 100: divide theirs by 100), and the white's
XYZ is the same on every grid with the same end points.  At 1 nm (and on a 5 nm grid for data
that are natively 5 nm) this is exactly ``colour.sd_to_XYZ(..., method="Integration")``.  Measured
on the 24 ColorChecker spectra (``tests/test_colorimetry.py``): max ΔE00 0.084 on a 10 nm grid and
0.106 on a 20 nm grid against the 1 nm integration (colour's own ASTM E308 tables: 0.079 and 0.120).

Accepted grids: 1-D, strictly increasing, uniform, step 1–20 nm, inside both tables' domains
(for D65: 360–780 nm).

RGB mode (paper §5: flake R and T are converted to RGB *before* the solve)
---------------------------------------------------------------------------
``spectra_to_rgb_mode`` maps a spectrum to linear sRGB and then divides each channel by the linear
sRGB of the perfect white on the same grid.  A spectrally flat value c therefore maps to exactly
(c, c, c); because the map is linear, R + T = 1 for every λ gives R_rgb + T_rgb = (1, 1, 1) exactly,
so a non-absorbing flake stays non-absorbing in RGB mode.  (Without the division the white would be
off by up to 4e-4: D65's integrated chromaticity differs from sRGB's rounded white point
(0.3127, 0.3290) in the fifth decimal, and the standard's XYZ→RGB matrix has 4 decimals.)  Saturated spectra outside the sRGB gamut give channels < 0
or > 1; they are returned as they are, never clipped.
"""

from __future__ import annotations

import functools

import numpy as np

from flakedb.colour import cie_tables
from flakedb.colour.sprague import sprague_matrix

CMFS_NAME = "CIE 1931 2 Degree Standard Observer"

#: IEC 61966-2-1:1999 §5.1 (sRGB): chromaticities of the red, green, blue primaries and of the D65 white.
SRGB_PRIMARIES_XY = ((0.64, 0.33), (0.30, 0.60), (0.15, 0.06))
SRGB_WHITE_XY = cie_tables.D65_XY_2DEG


def spectral_grid(range_nm=(380, 780), step_nm=10) -> np.ndarray:
    """Uniform wavelength grid in nm, both ends included: ``range_nm[0], range_nm[0] + step_nm, …``.

    Raises ValueError when ``step_nm`` does not divide the range.
    """
    lo, hi = float(range_nm[0]), float(range_nm[1])
    step = float(step_nm)
    if not (step > 0 and hi > lo):
        raise ValueError(f"spectral_grid: need range_nm[1] > range_nm[0] and step_nm > 0, got {range_nm}, {step_nm}")
    n = (hi - lo) / step
    if abs(n - round(n)) > 1e-9:
        raise ValueError(f"spectral_grid: step_nm={step_nm:g} does not divide the range {lo:g}-{hi:g} nm")
    return lo + step * np.arange(int(round(n)) + 1)


def _tables(cmfs_name=CMFS_NAME):
    import colour  # lazy: colour-science takes ~0.5 s to import (it pulls matplotlib)

    return colour.MSDS_CMFS[cmfs_name], colour.SDS_ILLUMINANTS


def check_grid(wavelength_nm) -> np.ndarray:
    wl = np.asarray(wavelength_nm, dtype=float)
    if wl.ndim != 1 or wl.size < 2:
        raise ValueError("wavelength_nm must be a 1-D array of at least two wavelengths (nm)")
    d = np.diff(wl)
    if np.any(d <= 0):
        raise ValueError("wavelength_nm must be strictly increasing")
    step = d.mean()
    if np.max(np.abs(d - step)) > 1e-6 * step:
        raise ValueError(f"wavelength_nm must be uniform (steps range {d.min():g}-{d.max():g} nm)")
    if not (1.0 - 1e-9 <= step <= 20.0 + 1e-9):
        raise ValueError(f"wavelength_nm step is {step:g} nm; colorimetry supports steps of 1-20 nm")
    return wl


def _fine_nodes(wl):
    """Fine nodes: every grid interval split into m = ceil(step / 1 nm) equal parts (<= 1 nm)."""
    step = (wl[-1] - wl[0]) / (wl.size - 1)
    m = int(np.ceil(step - 1e-9))
    return m, np.linspace(wl[0], wl[-1], (wl.size - 1) * m + 1)


def _check_domain(wl, lo, hi, cmfs_name, illuminant):
    if wl[0] < lo - 1e-9 or wl[-1] > hi + 1e-9:
        raise ValueError(
            f"wavelength grid {wl[0]:g}-{wl[-1]:g} nm is outside the {cmfs_name} x {illuminant} "
            f"tables' common domain {lo:g}-{hi:g} nm; nothing is extrapolated"
        )


def _weights_from(H, S, xyz_bar):
    """W = H (S x̄ȳz̄) normalised so the Y column sums to 1; read-only."""
    W = H @ (S[:, None] * xyz_bar)
    W = W / W[:, 1].sum()
    W.setflags(write=False)
    return W


def _weights_native(wl, illuminant, cmfs_name):
    """The weights from :mod:`flakedb.colour.cie_tables` and :func:`flakedb.colour.sprague.sprague_matrix`
    (no colour-science), or None where those do not cover the case: an observer or illuminant that is
    not tabulated there, or fine nodes that are not integer nm (docs/colorimetry.md)."""
    if cmfs_name not in cie_tables.CMFS_1NM or illuminant not in cie_tables.ILLUMINANTS_1NM:
        return None
    c_lo, c_hi = cie_tables.CMFS_DOMAIN_NM[cmfs_name]
    s_lo, s_hi = cie_tables.ILLUMINANT_DOMAIN_NM[illuminant]
    _check_domain(wl, max(c_lo, s_lo), min(c_hi, s_hi), cmfs_name, illuminant)
    m, fine = _fine_nodes(wl)
    if not np.array_equal(fine, np.round(fine)):
        return None
    k = fine.astype(np.int64)
    S = cie_tables.ILLUMINANTS_1NM[illuminant][k - cie_tables.ILLUMINANT_START_NM[illuminant]]
    xyz_bar = cie_tables.CMFS_1NM[cmfs_name][k - cie_tables.CMFS_START_NM[cmfs_name]]
    H = np.eye(wl.size) if m == 1 else _carry_matrix(wl, fine)    # (W, F)
    return _weights_from(H, S, xyz_bar)


#: Sprague's scheme (CIE 167:2005) needs 6 samples; fewer are carried to the fine nodes linearly.
SPRAGUE_MIN_SAMPLES = 6


def _carry_matrix(wl, fine):
    """(W, F): the grid → fine-node interpolation, Sprague (CIE 167:2005) for ≥ 6 samples, else
    piecewise linear (a 3–5 band grid is too short for Sprague's 6-point stencil; docs/colorimetry.md)."""
    if wl.size >= SPRAGUE_MIN_SAMPLES:
        return sprague_matrix(wl, fine).T
    eye = np.eye(wl.size)
    return np.stack([np.interp(fine, wl, eye[j]) for j in range(wl.size)])


def tristimulus_weights_colour_science(wavelength_nm, illuminant: str = "D65", cmfs_name: str = CMFS_NAME):
    """:func:`tristimulus_weights` computed with colour-science (its tables, its interpolators, its
    ``SpragueInterpolator``): the reference the native path is tested against, and the path for every
    observer, illuminant or grid the native tables do not cover.  Imports colour-science (slow); not cached."""
    wl = check_grid(wavelength_nm)
    cmfs, illuminants = _tables(cmfs_name)
    if illuminant not in illuminants:
        raise ValueError(f"unknown illuminant {illuminant!r}; colour-science knows e.g. D65, A, E")
    sd = illuminants[illuminant]
    _check_domain(wl, max(cmfs.domain[0], sd.domain[0]), min(cmfs.domain[-1], sd.domain[-1]), cmfs_name, illuminant)
    m, fine = _fine_nodes(wl)
    xyz_bar = np.asarray(cmfs[fine], dtype=float)  # colour-science's Sprague interpolation
    S = np.asarray(sd[fine], dtype=float)  # colour-science's interpolator for the illuminant
    # The spectrum is carried from the grid to the fine nodes by an interpolation that is linear in
    # its values, rho_fine = A @ rho_grid, so the weights are W = A.T @ (S xyz_bar)_fine.  A is
    # built column by column by interpolating unit vectors with colour-science's Sprague (1880)
    # interpolator, the one CIE 167:2005 recommends for uniform data (what colour's align uses).
    if m == 1:
        H = np.eye(wl.size)
    elif wl.size < SPRAGUE_MIN_SAMPLES:
        H = _carry_matrix(wl, fine)
    else:
        from colour.algebra import (
            SpragueInterpolator,  # lazy: colour-science takes ~0.5 s to import (it pulls matplotlib)
        )

        eye = np.eye(wl.size)
        H = np.stack([SpragueInterpolator(wl, eye[j])(fine) for j in range(wl.size)])  # (W, F)
    return _weights_from(H, S, xyz_bar)


@functools.lru_cache(maxsize=64)
def _weights_cached(wl_key: tuple, illuminant: str, cmfs_name: str = CMFS_NAME) -> np.ndarray:
    wl = np.asarray(wl_key)
    W = _weights_native(wl, illuminant, cmfs_name)
    return W if W is not None else tristimulus_weights_colour_science(wl, illuminant, cmfs_name)


def tristimulus_weights(wavelength_nm, illuminant: str = "D65", cmfs_name: str = CMFS_NAME) -> np.ndarray:
    """Weights (W, 3) with XYZ = Σ_j ρ_j W[j] (module docstring); the Y column sums to 1.

    ``cmfs_name``: colour-science's name of the observer's colour matching functions (default the
    CIE 1931 2° observer).  Read-only, cached per grid, illuminant and observer.
    """
    wl = check_grid(wavelength_nm)
    return _weights_cached(tuple(wl.tolist()), str(illuminant), str(cmfs_name))


def reflectance_to_XYZ(values, wavelength_nm, illuminant: str = "D65") -> np.ndarray:
    """CIE 1931 2° XYZ of reflectance-type spectra on the last axis (broadcast over leading axes).

    ``values``: (..., W), 1 for a perfect white; ``wavelength_nm``: (W,) uniform grid in nm.
    Returns (..., 3) with Y = 1 for the perfect white diffuser (module docstring: normalisation).
    """
    v = np.asarray(values, dtype=float)
    W = tristimulus_weights(wavelength_nm, illuminant)
    if v.shape[-1:] != (W.shape[0],):
        raise ValueError(f"values' last axis has {v.shape[-1:]} samples, the grid {W.shape[0]}")
    return v @ W


def white_XYZ(wavelength_nm, illuminant: str = "D65") -> np.ndarray:
    """XYZ (Y = 1) of the perfect white diffuser integrated on this grid."""
    W = tristimulus_weights(wavelength_nm, illuminant)
    return W.sum(axis=0)


def normalised_primary_matrix(primaries_xy, white_xy) -> np.ndarray:
    """RGB → XYZ matrix N (3, 3), XYZ = N rgb, of an RGB space with these primary and white
    chromaticities (SMPTE RP 177-1993 §3.3): columns are the primaries' XYZ, P_k = (x/y, 1, (1−x−y)/y)_k,
    scaled by s = P⁻¹ W so that rgb = (1, 1, 1) is the white W = (x/y, 1, (1−x−y)/y)_w (Y = 1)."""
    def xyz(xy):
        x, y = (np.asarray(c, dtype=float) for c in np.asarray(xy, dtype=float).T)
        return np.stack([x / y, np.ones_like(x), (1.0 - x - y) / y])

    P = xyz(primaries_xy)                         # (3, 3), column k = primary k
    return P * np.linalg.solve(P, xyz(white_xy))[None, :]


def srgb_matrices() -> tuple[np.ndarray, np.ndarray]:
    """(RGB → XYZ, XYZ → RGB) of IEC 61966-2-1:1999 §5.2 as the standard prints them: the normalised
    primary matrix of its primaries and D65 white rounded to 4 decimals, and the inverse of that rounded
    matrix rounded to 4 decimals (3.2406, −1.5372, −0.4986; …), the pair colour-science's ``sRGB`` uses.
    Computed, not pasted (tested equal to the printed values).  The unrounded inverse would differ by up
    to 2e-4 (relative); the RGB mode's white normalisation removes the rounding's effect on the white."""
    rgb_to_xyz = np.round(normalised_primary_matrix(SRGB_PRIMARIES_XY, SRGB_WHITE_XY), 4)
    return rgb_to_xyz, np.round(np.linalg.inv(rgb_to_xyz), 4)


_XYZ_TO_SRGB = srgb_matrices()[1]
_XYZ_TO_SRGB.setflags(write=False)


def XYZ_to_linear_sRGB(XYZ) -> np.ndarray:
    """Linear (not gamma-encoded) sRGB of D65-relative XYZ (Y = 1 white), IEC 61966-2-1 primaries
    (the standard's 4-decimal XYZ → RGB matrix, :func:`srgb_matrices`).

    No chromatic adaptation (the XYZ are already relative to D65, sRGB's white).  (..., 3) → (..., 3).
    """
    return np.einsum("ij,...j->...i", _XYZ_TO_SRGB, np.asarray(XYZ, dtype=float))


def _lab_f(t):
    """CIE 15:2004 §8.2.1: f(t) = t^(1/3) for t > (24/116)³, else (841/108) t + 16/116."""
    with np.errstate(invalid="ignore"):
        return np.where(t > (24.0 / 116.0) ** 3, np.power(t, 1.0 / 3.0), (841.0 / 108.0) * t + 16.0 / 116.0)


def XYZ_to_Lab(XYZ, white="D65") -> np.ndarray:
    """CIE 1976 L*a*b* (CIE 15:2004 §8.2.1) of XYZ with Y = 1 for white.

    L* = 116 f(Y/Y_n) − 16, a* = 500 [f(X/X_n) − f(Y/Y_n)], b* = 200 [f(Y/Y_n) − f(Z/Z_n)], f as in
    :func:`_lab_f`.  ``white``: "D65" (CIE 15's D65 chromaticity for the 2° observer as colour-science
    tabulates it, (0.3127, 0.3290), Y_n = 1) or an XYZ triple, e.g. :func:`white_XYZ` on the grid the
    spectra were integrated on (then the perfect white is exactly (100, 0, 0)).

    The perfect white diffuser is L* = 100, a* = b* = 0 relative to the white of its own grid:

    >>> wl = spectral_grid()
    >>> (np.round(XYZ_to_Lab(white_XYZ(wl), white=white_XYZ(wl)), 10) + 0.0).tolist()
    [100.0, 0.0, 0.0]
    """
    XYZ = np.asarray(XYZ, dtype=float)
    if isinstance(white, str):
        if white != "D65":
            return _XYZ_to_Lab_colour_science(XYZ, white)
        x, y = cie_tables.D65_XY_2DEG
    else:
        w = np.asarray(white, dtype=float)
        x, y = w[0] / w.sum(), w[1] / w.sum()
        XYZ = XYZ / float(w[1])
    n = (x / y, 1.0, (1.0 - x - y) / y)                              # white (X_n, Y_n, Z_n), Y_n = 1
    fx, fy, fz = (_lab_f(XYZ[..., k] / n[k]) for k in range(3))
    return np.stack([116.0 * fy - 16.0, 500.0 * (fx - fy), 200.0 * (fy - fz)], axis=-1)


def Lab_to_XYZ(Lab, white="D65") -> np.ndarray:
    """XYZ (Y = 1 for white) of CIE L*a*b* (CIE 15:2004 §8.2.1 inverted), the inverse of :func:`XYZ_to_Lab` for
    a named white: colour-science's ``Lab_to_XYZ`` at that white's chromaticity (2° observer; "D65" is
    ``cie_tables.D65_XY_2DEG``, as in :func:`XYZ_to_Lab`).

    >>> float(np.round(Lab_to_XYZ([100.0, 0.0, 0.0])[1], 12))
    1.0
    """
    import colour  # lazy: colour-science takes ~0.5 s to import (it pulls matplotlib)

    xy = np.asarray(cie_tables.D65_XY_2DEG if white == "D65" else colour.CCS_ILLUMINANTS[CMFS_NAME][white])
    return np.asarray(colour.Lab_to_XYZ(np.asarray(Lab, dtype=float), xy), dtype=float)


def _XYZ_to_Lab_colour_science(XYZ, white):
    import colour  # lazy: colour-science takes ~0.5 s to import (it pulls matplotlib)

    xy = colour.CCS_ILLUMINANTS[CMFS_NAME][white]
    return np.asarray(colour.XYZ_to_Lab(XYZ, xy), dtype=float)


def ciede2000_terms(lab_ref, lab_sample):
    """(ΔL'/S_L, ΔC'/S_C, ΔH'/S_H, R_T) of CIEDE2000 (Sharma et al. 2005, eqs. 1–22), k = 1.

    Arrays (..., 3) broadcast; returns four arrays of the broadcast leading shape.
    """
    r = np.asarray(lab_ref, float)
    s = np.asarray(lab_sample, float)
    L1, a1, b1 = r[..., 0], r[..., 1], r[..., 2]
    L2, a2, b2 = s[..., 0], s[..., 1], s[..., 2]
    Cbar = 0.5 * (np.hypot(a1, b1) + np.hypot(a2, b2))
    c7 = Cbar**7
    G = 0.5 * (1.0 - np.sqrt(c7 / (c7 + 25.0**7)))                      # eq. 4
    a1p, a2p = (1.0 + G) * a1, (1.0 + G) * a2                            # eq. 5
    C1p, C2p = np.hypot(a1p, b1), np.hypot(a2p, b2)                      # eq. 6
    h1p = np.where((a1p == 0) & (b1 == 0), 0.0, np.degrees(np.arctan2(b1, a1p)) % 360.0)   # eq. 7
    h2p = np.where((a2p == 0) & (b2 == 0), 0.0, np.degrees(np.arctan2(b2, a2p)) % 360.0)
    dLp = L2 - L1                                                        # eq. 8
    dCp = C2p - C1p                                                      # eq. 9
    prod = C1p * C2p
    dh = h2p - h1p
    dhp = np.where(prod == 0, 0.0, np.where(dh > 180.0, dh - 360.0, np.where(dh < -180.0, dh + 360.0, dh)))  # eq. 10
    dHp = 2.0 * np.sqrt(prod) * np.sin(np.radians(dhp) / 2.0)            # eq. 11
    Lbp = 0.5 * (L1 + L2)                                                # eq. 12
    Cbp = 0.5 * (C1p + C2p)                                              # eq. 13
    hs = h1p + h2p
    hbp = np.where(prod == 0, hs,
                   np.where(np.abs(h1p - h2p) <= 180.0, 0.5 * hs,
                            np.where(hs < 360.0, 0.5 * (hs + 360.0), 0.5 * (hs - 360.0))))   # eq. 14
    T = (1.0 - 0.17 * np.cos(np.radians(hbp - 30.0)) + 0.24 * np.cos(np.radians(2.0 * hbp))
         + 0.32 * np.cos(np.radians(3.0 * hbp + 6.0)) - 0.20 * np.cos(np.radians(4.0 * hbp - 63.0)))  # eq. 15
    dtheta = 30.0 * np.exp(-(((hbp - 275.0) / 25.0) ** 2))              # eq. 16
    c7p = Cbp**7
    RC = 2.0 * np.sqrt(c7p / (c7p + 25.0**7))                            # eq. 17
    SL = 1.0 + 0.015 * (Lbp - 50.0) ** 2 / np.sqrt(20.0 + (Lbp - 50.0) ** 2)   # eq. 18
    SC = 1.0 + 0.045 * Cbp                                               # eq. 19
    SH = 1.0 + 0.015 * Cbp * T                                           # eq. 20
    RT = -np.sin(np.radians(2.0 * dtheta)) * RC                          # eq. 21
    return dLp / SL, dCp / SC, dHp / SH, RT


def delta_E_2000(lab1, lab2) -> np.ndarray:
    """CIEDE2000 colour difference (Sharma, Wu & Dalal 2005, Color Res. Appl. 30, 21, eq. 22;
    CIE 142-2001), k_L = k_C = k_H = 1, arrays (..., 3) broadcast (terms: :func:`ciede2000_terms`).

    Sharma, Wu & Dalal's (2005) first test pair has ΔE00 = 2.0425; a colour has no difference from itself:

    >>> round(float(delta_E_2000([50.0, 2.6772, -79.7751], [50.0, 0.0, -82.7485])), 4)
    2.0425
    >>> float(delta_E_2000([50.0, 2.6772, -79.7751], [50.0, 2.6772, -79.7751]))
    0.0
    """
    tL, tC, tH, RT = ciede2000_terms(lab1, lab2)
    return np.asarray(np.sqrt(tL * tL + tC * tC + tH * tH + RT * tC * tH))


def spectra_to_rgb_matrix(wavelength_nm, illuminant: str = "D65") -> np.ndarray:
    """The one spectral → RGB map of flakedb (the paper's RGB mode), as a matrix M (W, 3):
    white-normalised linear sRGB = spectra @ M.  M = W_xyz A / rgb(white), with W_xyz the
    tristimulus weights and A the XYZ → linear sRGB matrix; a flat spectrum c maps to (c, c, c)
    exactly (module docstring).  It is linear, so it applies to BSDF coefficients one by one."""
    W = tristimulus_weights(wavelength_nm, illuminant)                 # (W, 3) → XYZ
    A = XYZ_to_linear_sRGB(np.eye(3))                                  # XYZ @ A = rgb
    rgb_white = XYZ_to_linear_sRGB(white_XYZ(wavelength_nm, illuminant))
    return (W @ A) / rgb_white[None, :]


def rgb_mode_to_XYZ(rgb, wavelength_nm, illuminant: str = "D65") -> np.ndarray:
    """Inverse of the RGB mode's normalisation: XYZ (Y = 1 white on this grid) of white-normalised
    linear sRGB values (..., 3), so that rgb_mode_to_XYZ(spectra @ M) = spectra' XYZ for every
    spectrum in the span of the sRGB primaries."""
    A = XYZ_to_linear_sRGB(np.eye(3))
    rgb_white = XYZ_to_linear_sRGB(white_XYZ(wavelength_nm, illuminant))
    return (np.asarray(rgb, float) * rgb_white) @ np.linalg.inv(A)


def spectra_to_rgb_mode(values, wavelength_nm, illuminant: str = "D65") -> np.ndarray:
    """The paper's RGB mode: spectra (..., W) → white-normalised linear sRGB (..., 3), by
    :func:`spectra_to_rgb_matrix`.  A flat spectrum c maps to (c, c, c) exactly (``c Σ_b M_bk`` is 1 to rounding
    only, and channels that differ in the last place are solved apart instead of once); see the module docstring
    for why and what it costs.

    >>> wl = spectral_grid()
    >>> spectra_to_rgb_mode(np.full(wl.size, 0.5), wl).tolist()
    [0.5, 0.5, 0.5]
    """
    v = np.asarray(values, dtype=float)
    M = spectra_to_rgb_matrix(wavelength_nm, illuminant)
    if v.shape[-1:] != (M.shape[0],):
        raise ValueError(f"values' last axis has {v.shape[-1:]} samples, the grid {M.shape[0]}")
    flat = np.all(v == v[..., :1], axis=-1, keepdims=True)
    return np.where(flat, v[..., :1], v @ M)
