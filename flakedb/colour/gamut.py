"""RGB working spaces and gamut mapping of tabulated BSDFs (docs/gamut.md).

Working spaces
--------------
A file's RGB is *white-normalised linear* RGB of one of :data:`RGB_SPACES`: XYZ (D65, CIE 1931 2°,
Y = 1 white, :mod:`flakedb.colour.colorimetry`) → the space's linear RGB (colour-science's
``XYZ_to_RGB`` with the space's primaries; Bradford adaptation from D65 to the space's white where
they differ, i.e. ACEScg's ≈D60) → divided per channel by the RGB of the perfect white integrated
on the same grid, so that a spectrally flat value c is exactly (c, c, c) in every space (the rule
of :func:`flakedb.colour.colorimetry.spectra_to_rgb_mode`, which is ``space="srgb"`` here,
bit for bit).  Each map is linear, so it applies coefficient by coefficient.

Gamut mapping (luminance-preserving desaturation, per node pair)
----------------------------------------------------------------
A saturated paint (a cadmium yellow, a deep red, an interference colour) has chromaticities outside
the triangle of the file's primaries; its linear RGB then holds negative channels, which renderers
clamp, so they no longer render what flakedb computed.  :func:`desaturate_to_gamut` moves each out-
of-gamut colour towards the neutral of the **same luminance** along the straight line in linear RGB,

    c'_k = Y + s (c_k − Y),    Y = Σ_k w_k c_k,    0 ≤ s ≤ 1,                       (G1)

the "desaturation towards the achromatic axis at constant luminance" of gamut clipping (Morovič,
*Color Gamut Mapping*, Wiley 2008, ch. 10, straight-line chroma clipping towards a point on the
lightness axis; CIE 156:2004 guidelines).  An additive mixture with a neutral moves the chromaticity
along the line to the white point, so the dominant wavelength (hue, in that sense) and Y are kept
exactly; only excitation purity drops, and only as far as needed.  ``s`` is the largest value that
makes every channel ≥ 0, for one node pair (μ_i, μ_o) at a time, taken over the pair's order-0
coefficient (its azimuthal mean, what the albedo integrates) and its values at ``n_phi`` azimuths
φ_d ∈ [0, π] where the luminance is > 0 (where Y ≤ 0 the series rings and no desaturation can help;
readers clamp such values).  The same ``s`` multiplies every Fourier coefficient of the pair, so
(G1) is linear in the series and the mapped value at every φ_d is the mapped colour of the value.

Properties (tested in tests/colour/test_gamut.py):

* **Luminance kept**: Y' = Y for every coefficient (Σ w_k = 1), so the sampling channel, its
  albedo and the energy balance of luminance are unchanged.
* **Reciprocal**: ``s`` is symmetrised over reciprocal node pairs, s(μ_i, μ_o) = s(−μ_o, −μ_i)
  (the smaller of the two), and (G1) with a common s is a linear map of the channels, so every
  reciprocity relation of the table (conventions: f(μ_i, μ_o) = f(−μ_o, −μ_i), and the η² rule for
  transmission, whose factor is the same in every channel) holds after the map as before it.
* **Energy-bounded**: c'_k lies between c_k and Y, so c'_k ≤ max(c_k, Y) and each channel's albedo
  is at most Σ_o w_o max(c_k, Y)(μ_i, μ_o); for the deficient channel of a saturated colour (blue
  of a yellow: c_k < Y everywhere) that is ≤ the luminance albedo ≤ 1, and a channel above Y only
  decreases.  The mapped table's largest channel albedo is recorded (compose) and tested ≤ 1 on
  the catalogue.
* In-gamut pairs are not changed (s = 1).

What it costs is measured, not assumed: :func:`mapping_delta_e` gives the CIEDE2000 difference
between the unmapped colour (the true colour: the unmapped RGB is an exact linear image of the
spectral XYZ) and the mapped one.
"""

from __future__ import annotations

import functools

import numpy as np

from flakedb.colour.colorimetry import (
    XYZ_to_Lab,
    XYZ_to_linear_sRGB,
    delta_E_2000,
    spectra_to_rgb_matrix,
    tristimulus_weights,
    white_XYZ,
)

#: Working spaces: option name -> (colour-science name, description recorded in the metadata).
RGB_SPACES = {
    "srgb": ("sRGB", "linear sRGB (IEC 61966-2-1 primaries, D65), white-normalised"),
    "rec2020": ("ITU-R BT.2020", "linear Rec.2020 (ITU-R BT.2020 primaries, D65), white-normalised"),
    "acescg": ("ACEScg", "linear ACEScg (AP1 primaries, ACES white ~D60; Bradford from D65), white-normalised"),
}
#: What the metadata records as the gamut mapping method.
GAMUT_METHOD = ("luminance-preserving desaturation per node pair: c' = Y + s (c - Y), one s for every Fourier "
                "coefficient of a pair and its reciprocal pair (Morovic 2008 ch. 10 straight-line chroma clipping "
                "to the neutral axis; docs/gamut.md)")
#: Azimuth samples per node pair at which channels are made non-negative (besides the order-0 mean).
N_PHI_DEFAULT = 64


def check_space(space: str) -> str:
    if space not in RGB_SPACES:
        raise ValueError(f"rgb space {space!r}: use one of {', '.join(RGB_SPACES)}")
    return space


@functools.lru_cache(maxsize=8)
def _xyz_to_space(space: str) -> np.ndarray:
    """A (3, 3) with rgb = XYZ @ A (not white-normalised)."""
    check_space(space)
    if space == "srgb":
        return XYZ_to_linear_sRGB(np.eye(3))
    import colour  # lazy: colour-science takes ~0.5 s to import (it pulls matplotlib)

    cs = colour.RGB_COLOURSPACES[RGB_SPACES[space][0]]
    d65 = colour.CCS_ILLUMINANTS["CIE 1931 2 Degree Standard Observer"]["D65"]
    cat = None if np.allclose(cs.whitepoint, d65, atol=1e-4) else "Bradford"
    A = colour.XYZ_to_RGB(np.eye(3), cs, illuminant=d65, chromatic_adaptation_transform=cat,
                          apply_cctf_encoding=False)
    return np.asarray(A, dtype=float)


def _space_white(space, wavelength_nm):
    return white_XYZ(wavelength_nm) @ _xyz_to_space(space)


def spectra_to_space_matrix(wavelength_nm, space: str = "srgb") -> np.ndarray:
    """(W, 3): spectra @ M = white-normalised linear RGB of ``space`` (module docstring).  For
    ``"srgb"`` exactly :func:`flakedb.colour.colorimetry.spectra_to_rgb_matrix`."""
    if check_space(space) == "srgb":
        return spectra_to_rgb_matrix(wavelength_nm)
    W = tristimulus_weights(wavelength_nm)
    return (W @ _xyz_to_space(space)) / _space_white(space, wavelength_nm)[None, :]


def space_to_XYZ_matrix(wavelength_nm, space: str = "srgb") -> np.ndarray:
    """(3, 3): XYZ (Y = 1 white on this grid) = rgb @ B for white-normalised rgb of ``space``."""
    A = _xyz_to_space(check_space(space))
    return _space_white(space, wavelength_nm)[:, None] * np.linalg.inv(A)


def rgb_mode_to_space_matrix(wavelength_nm, space: str = "srgb") -> np.ndarray:
    """(3, 3): white-normalised linear sRGB (the paper's RGB mode) @ T = white-normalised ``space``."""
    if check_space(space) == "srgb":
        return np.eye(3)
    A = _xyz_to_space(space)
    return space_to_XYZ_matrix(wavelength_nm, "srgb") @ A / _space_white(space, wavelength_nm)[None, :]


def luminance_weights(wavelength_nm, space: str = "srgb") -> np.ndarray:
    """(3,) w with Y = rgb @ w for white-normalised rgb of ``space``; Σ w = Y(white) = 1."""
    return space_to_XYZ_matrix(wavelength_nm, space)[:, 1]


def _pair_values(c, n_phi):
    """Order-0 coefficient and values at n_phi azimuths in [0, π]: (C, ..., 1 + n_phi)."""
    L = c.shape[-1]
    phi = np.linspace(0.0, np.pi, int(n_phi))
    cos = np.cos(np.arange(L)[:, None] * phi[None, :])            # (L, P)
    return np.concatenate([c[..., :1], c @ cos], axis=-1)


#: How far inside the gamut (G1) stops, as a fraction of the luminance Y: a channel mapped to the gamut's edge is
#: left at GAMUT_MARGIN·Y, not 0.  The .bsdf stores R, Y, B as float32 and readers rebuild
#: G = (Y − 0.212671 R − 0.072169 B) / 0.715160 (flakedb.bsdf), whose rounding reaches ≈ 3 float32 ulps of Y / 0.715
#: (≈ 3e-7 Y): with the earlier 1e-9 a green mapped to 0 read back as −2.3e-9 (`red-solid`, spectral, n = 16).
#: 2⁻²⁰ ≈ 9.5e-7 covers it; the colour moves by that fraction of the way to grey (ΔE00 ≪ 1e-3).
GAMUT_MARGIN = 2.0 ** -20


def desaturation_factors(coeffs, w, n_phi: int = N_PHI_DEFAULT, rows: int = 16) -> np.ndarray:
    """s (n, n) of (G1) for a table's coefficients (3, n, n, L) in a space with luminance weights
    ``w``: the largest s in [0, 1] making every channel ≥ 0 at the pair's order-0 coefficient and at
    ``n_phi`` azimuths where Y > 0, then symmetrised over reciprocal pairs (i, o) ↔ (n−1−o, n−1−i)
    (the nodes are symmetric, mu[n−1−k] = −mu[k]).  Vectorised over pairs, in blocks of ``rows``
    incident nodes (bounded memory)."""
    c = np.asarray(coeffs, dtype=float)
    if c.ndim != 4 or c.shape[0] != 3 or c.shape[1] != c.shape[2]:
        raise ValueError(f"coeffs must have shape (3, n, n, L), got {c.shape}")
    w = np.asarray(w, dtype=float)
    n, L = c.shape[1], c.shape[3]
    s = np.ones((n, n))
    margin = 4.0 * L * np.finfo(float).eps  # the rounding of Σ_l a_l cos(l φ) and of the tail sum below
    for r0 in range(0, n, rows):
        blk = c[:, r0:r0 + rows]
        a0, tail = blk[..., 0], np.abs(blk[..., 1:]).sum(axis=-1)
        if np.all(a0 - tail > margin * (a0 + tail)):
            continue  # a_0 > Σ_{l≥1} |a_l| in every channel: no value is negative at any φ, s = 1 (as evaluated)
        v = _pair_values(blk, n_phi)                                # (3, r, n, P)
        Y = np.einsum("k,k...->...", w, v)                          # (r, n, P)
        neg = (v < 0) & (Y > 0)[None]
        with np.errstate(divide="ignore", invalid="ignore"):
            # Y - v > Y > 0 where neg; GAMUT_MARGIN below the zero crossing (a file's rebuilt G stays >= 0)
            bound = np.where(neg, (1.0 - GAMUT_MARGIN) * Y[None] / (Y[None] - v), 1.0)
        s[r0:r0 + rows] = np.clip(bound.min(axis=(0, 3)), 0.0, 1.0)
    s = np.minimum(s, s[::-1, ::-1].T)
    return s


def desaturate_to_gamut(coeffs, w, n_phi: int = N_PHI_DEFAULT):
    """Apply (G1): returns (mapped coeffs (3, n, n, L), s (n, n)).  The luminance Σ w_k c_k of every
    coefficient is unchanged; pairs already in gamut (s = 1) are returned unchanged (``coeffs`` itself when
    every pair is)."""
    c = np.asarray(coeffs, dtype=float)
    if np.array_equal(c[0], c[1]) and np.array_equal(c[0], c[2]):
        # a grey table: every channel equals Y / Σw with Σw = 1 > 0, so none is negative where Y > 0
        return c, np.ones(c.shape[1:3])
    s = desaturation_factors(c, w, n_phi)
    # in-gamut pairs bit for bit (Y + (c - Y) may differ from c in the last place); (G1) on the others only
    mapped = s < 1.0
    if not mapped.any():
        return c, s
    out = c.copy()
    cm = c[:, mapped]                                                # (3, m, L)
    Y = np.einsum("k,k...->...", np.asarray(w, float), cm)           # (m, L)
    out[:, mapped] = Y[None] + s[mapped][None, :, None] * (cm - Y[None])
    return out, s


def mapping_delta_e(rgb_before, rgb_after, wavelength_nm, space: str = "srgb") -> np.ndarray:
    """CIEDE2000 (CIELAB relative to the white on this grid) between reflectance-type colours given
    as white-normalised RGB of ``space`` (..., 3), before and after the gamut mapping."""
    B = space_to_XYZ_matrix(wavelength_nm, space)
    white = white_XYZ(wavelength_nm)
    lab1 = XYZ_to_Lab(np.asarray(rgb_before, float) @ B, white=white)
    lab2 = XYZ_to_Lab(np.asarray(rgb_after, float) @ B, white=white)
    return delta_E_2000(lab1, lab2)


def desaturate_points(rgb, w) -> np.ndarray:
    """(G1) applied to independent colours (..., 3) (e.g. a measured-BSDF grid, one s per value):
    the largest s in [0, 1] making every channel ≥ 0 where Y > 0; a value with Y ≤ 0 becomes 0.

    An out-of-gamut colour (a negative channel) is moved towards the grey of its own luminance Y until
    it is in gamut; Y is kept:

    >>> w = luminance_weights(np.arange(380.0, 781.0, 10.0))
    >>> rgb = np.array([0.6, 0.3, -0.1])
    >>> out = desaturate_points(rgb, w)
    >>> bool(np.all(out >= 0)), bool(np.isclose(out @ w, rgb @ w, rtol=1e-9, atol=0))
    (True, True)
    """
    v = np.asarray(rgb, dtype=float)
    Y = v @ np.asarray(w, float)
    with np.errstate(divide="ignore", invalid="ignore"):
        bound = np.where((v < 0) & (Y[..., None] > 0), (1.0 - GAMUT_MARGIN) * Y[..., None] / (Y[..., None] - v), 1.0)
    s = np.clip(bound.min(axis=-1), 0.0, 1.0)
    out = Y[..., None] + s[..., None] * (v - Y[..., None])
    return np.where(Y[..., None] > 0, np.maximum(out, 0.0), 0.0)
