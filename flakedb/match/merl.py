"""Measured isotropic BRDFs in the MERL format read at multi-angle instrument geometries: a measured
paint becomes a :mod:`flakedb.match.targets` target (docs/validation.md).

The MERL BRDF database (W. Matusik, H. Pfister, M. Brand, L. McMillan, "A Data-Driven Reflectance
Model", ACM Trans. Graph. 22(3), 759-769, 2003) holds 100 isotropic materials, among them the car and
effect paints ``silver-metallic-paint``, ``silver-metallic-paint2``, ``gold-metallic-paint``,
``gold-metallic-paint2``/``3``, ``pearl-paint``, ``blue-metallic-paint``/``2``, ``red-metallic-paint``,
``color-changing-paint1``/``2``/``3``.  Its licence allows research use but not redistribution, so no
MERL number ships with flakedb: :func:`read_merl` reads a file from the path the user gives.

File layout (MERL's reference reader ``BRDFRead.cpp``, read here and not copied)
--------------------------------------------------------------------------------
Three little-endian int32 ``(n_θh, n_θd, n_φd)`` (90, 90, 180 in the database), then 3 × n doubles
(n = n_θh n_θd n_φd), the red, green and blue planes one after the other, each C-ordered
``[θh, θd, φd]``.  A value times the channel's scale (1/1500, 1.15/1500, 1.66/1500) is the BRDF f_r
[1/sr]; negative values mark directions that were not measured.

Rusinkiewicz half/difference coordinates (S. Rusinkiewicz, "A New Change of Variables for Efficient
BRDF Representation", EGWR 1998): h = (ω_i + ω_o)/|ω_i + ω_o|, θ_h = arccos h_z, φ_h = atan2(h_y, h_x);
the difference vector d is ω_i rotated by −φ_h about z, then by −θ_h about y; θ_d = arccos d_z,
φ_d = atan2(d_y, d_x).  Bins (the reference reader's, generalised to the header's sizes): θ_h index
⌊√(θ_h / (π/2)) n_θh⌋ (finer near the specular), θ_d index ⌊θ_d / (π/2) n_θd⌋, φ_d folded to [0, π)
by reciprocity (φ_d + π for φ_d < 0) and indexed ⌊φ_d / π n_φd⌋, each clamped to its range; the value
is the bin's (nearest-bin lookup, as the reference reader, no interpolation).

In-plane instrument geometry (ASTM E2194 / E2539 names, :mod:`flakedb.match.targets`): light at θ_i in
the x–z plane, ω_i = (sin θ_i, 0, cos θ_i); detector at θ_v = θ_i − γ for aspecular angle γ,
ω_o = (−sin θ_v, 0, cos θ_v) (on the light's side when θ_v < 0).  In this plane θ_h = |γ|/2 and
θ_d = |θ_i − γ/2| (tested against the vector construction).  The instrument reads the reflectance
factor R = π f_r (collimated light, small detector aperture; docs/colour-matching.md).

Colour of MERL's RGB (the approximation, :func:`merl_rgb_to_lab`)
-----------------------------------------------------------------
MERL's three channels come from a camera with colour filters, not from spectra, and the camera's
spectral sensitivities are not published with the data.  Read here as linear sRGB (IEC 61966-2-1
primaries, D65 white, the CIE 1931 2° observer), the reading every renderer that loads MERL makes:
XYZ = M_sRGB · R_rgb, then CIELAB under D65 / 2°.  The target is therefore written for the 2°
observer and D65 (what the conversion is exact for, given the sRGB reading), not converted to 10°.
Exact for neutral colours (r = g = b gives a* = b* = 0, L* = 116 R^(1/3) − 16); for chromatic paints
the camera-to-sRGB error is unknown and is the conversion's stated limitation (docs/validation.md
gives its size on the catalogue's own spectra: how far an RGB-only reading of a paint is from its
spectral CIELAB).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from flakedb.colour.colorimetry import SRGB_PRIMARIES_XY, SRGB_WHITE_XY, XYZ_to_Lab, normalised_primary_matrix
from flakedb.colour.geometry import as_geometry_array, view_vector

#: MERL's channel scale factors (red, green, blue): stored value × scale = f_r [1/sr].
MERL_SCALE = np.array([1.0 / 1500.0, 1.15 / 1500.0, 1.66 / 1500.0])
#: Header sizes of the MERL database's files (θ_h, θ_d, φ_d bins).
MERL_DIMS = (90, 90, 180)
#: Most bins accepted from a header (the database's are 1.46 million; 16 million is a 384 MB file).
MAX_MERL_BINS = 16_000_000

__all__ = ["MERL_DIMS", "MERL_SCALE", "MerlError", "half_diff", "in_plane_directions", "merl_bins",
           "merl_lookup", "merl_rgb_to_lab", "merl_target", "read_merl", "write_merl"]


class MerlError(ValueError):
    """A MERL file that cannot be read (the message names the file and what is wrong)."""


def in_plane_directions(geometries_deg):
    """Unit vectors (ω_i, ω_o), each (G, 3), of geometries (G, 2) = (θ_i, aspecular γ) [deg]:
    ω_i = (sin θ_i, 0, cos θ_i), ω_o = (−sin θ_v, 0, cos θ_v) with θ_v = θ_i − γ (module docstring); (G, 3)
    geometries with an azimuth give ω_o out of the plane (:func:`flakedb.colour.geometry.view_vector`,
    mirrored in x: here the light is on the +x side)."""
    g = as_geometry_array(geometries_deg)
    ti = np.radians(g[:, 0])
    zero = np.zeros_like(ti)
    v = view_vector(g[:, 0], g[:, 1], g[:, 2])
    return (np.stack([np.sin(ti), zero, np.cos(ti)], axis=-1),
            np.stack([-v[:, 0], v[:, 1], v[:, 2]], axis=-1))


def half_diff(wi, wo):
    """Rusinkiewicz (θ_h, φ_h, θ_d, φ_d) [rad] of unit direction pairs (..., 3) (module docstring)."""
    wi, wo = np.asarray(wi, dtype=float), np.asarray(wo, dtype=float)
    h = wi + wo
    h = h / np.linalg.norm(h, axis=-1, keepdims=True)
    th = np.arccos(np.clip(h[..., 2], -1.0, 1.0))
    ph = np.arctan2(h[..., 1], h[..., 0])
    c, s = np.cos(-ph), np.sin(-ph)                      # rotate ω_i by −φ_h about z
    x1, y1, z1 = c * wi[..., 0] - s * wi[..., 1], s * wi[..., 0] + c * wi[..., 1], wi[..., 2]
    c, s = np.cos(-th), np.sin(-th)                      # then by −θ_h about y
    x2, y2, z2 = c * x1 + s * z1, y1, -s * x1 + c * z1
    return th, ph, np.arccos(np.clip(z2, -1.0, 1.0)), np.arctan2(y2, x2)


def merl_bins(theta_h, theta_d, phi_d, dims=MERL_DIMS):
    """Integer bin indices (i_θh, i_θd, i_φd) of half/difference angles [rad] in a table of ``dims``
    (module docstring: square-root spacing in θ_h, uniform in θ_d, φ_d folded to [0, π))."""
    nh, nd, nphi = dims
    th = np.maximum(np.asarray(theta_h, dtype=float), 0.0)
    ih = np.clip(np.floor(np.sqrt(th / (np.pi / 2.0)) * nh), 0, nh - 1).astype(int)
    idd = np.clip(np.floor(np.asarray(theta_d, dtype=float) / (np.pi / 2.0) * nd), 0, nd - 1).astype(int)
    p = np.asarray(phi_d, dtype=float)
    p = np.where(p < 0.0, p + np.pi, p)
    ip = np.clip(np.floor(p / np.pi * nphi), 0, nphi - 1).astype(int)
    return ih, idd, ip


def merl_lookup(table, wi, wo):
    """BRDF f_r [1/sr], (..., 3) RGB, of a MERL ``table`` (3, n_θh, n_θd, n_φd) already scaled by
    :data:`MERL_SCALE`, at direction pairs (..., 3); NaN where the bin was not measured (negative)."""
    th, _, td, pd = half_diff(wi, wo)
    ih, idd, ip = merl_bins(th, td, pd, table.shape[1:])
    v = np.moveaxis(table[:, ih, idd, ip], 0, -1)
    return np.where(v < 0.0, np.nan, v)


def merl_rgb_to_lab(rgb):
    """CIELAB (D65, CIE 1931 2°) of reflectance factors read as linear sRGB (..., 3) (module docstring):
    XYZ = M · rgb with the unrounded normalised primary matrix of IEC 61966-2-1's primaries and D65 white
    (white rgb = 1 → Y = 1, exactly D65, so r = g = b is a* = b* = 0), then CIE 15 L*a*b*.

    >>> [round(float(v), 6) + 0.0 for v in merl_rgb_to_lab([1.0, 1.0, 1.0])]     # the white point
    [100.0, 0.0, 0.0]
    >>> [round(float(v), 1) + 0.0 for v in merl_rgb_to_lab([0.18, 0.18, 0.18])]  # a neutral grey (CIE 15 L*)
    [49.5, 0.0, 0.0]
    """
    M = normalised_primary_matrix(SRGB_PRIMARIES_XY, SRGB_WHITE_XY)
    xyz = np.einsum("ij,...j->...i", M, np.asarray(rgb, dtype=float))
    return XYZ_to_Lab(xyz, white="D65")


def read_merl(path):
    """The MERL file at ``path`` as f_r [1/sr], shape (3, n_θh, n_θd, n_φd) (RGB planes, scaled by
    :data:`MERL_SCALE`; negative = not measured, kept).  Refuses a file whose size is not the header's."""
    p = Path(path)
    try:
        size = p.stat().st_size
        with p.open("rb") as fh:
            head = np.frombuffer(fh.read(12), dtype="<i4")
            if head.size != 3 or np.any(head <= 0) or int(np.prod(head.astype(np.int64))) > MAX_MERL_BINS:
                raise MerlError(f"{p}: not a MERL BRDF file (header {head.tolist()}: three positive bin counts, "
                                f"at most {MAX_MERL_BINS} bins, expected, e.g. {list(MERL_DIMS)})")
            n = int(np.prod(head.astype(np.int64)))
            if size != 12 + 3 * 8 * n:
                raise MerlError(f"{p}: {size} bytes, but its header {head.tolist()} needs {12 + 24 * n}; "
                                "the file is truncated or not a MERL BRDF")
            data = np.frombuffer(fh.read(), dtype="<f8").reshape(3, *head.tolist())
    except OSError as e:
        raise MerlError(f"{p}: cannot be read ({e.strerror or e})") from None
    return data * MERL_SCALE[:, None, None, None]


def write_merl(path, table):
    """Write f_r (3, n_θh, n_θd, n_φd) [1/sr] in the MERL layout (divided by :data:`MERL_SCALE`): used to
    make synthetic test files; :func:`read_merl` reads it back."""
    table = np.asarray(table, dtype=float)
    raw = table / MERL_SCALE[:, None, None, None]
    with Path(path).open("wb") as fh:
        fh.write(np.asarray(table.shape[1:], dtype="<i4").tobytes())
        fh.write(np.ascontiguousarray(raw, dtype="<f8").tobytes())


def merl_target(table, geometries_deg):
    """(reflectance factors R = π f_r (G, 3) RGB, L*a*b* (G, 3) D65 / 2°) of a scaled MERL ``table`` at
    in-plane geometries (G, 2) (θ_i, aspecular) [deg]."""
    wi, wo = in_plane_directions(geometries_deg)
    R = np.pi * merl_lookup(table, wi, wo)
    return R, merl_rgb_to_lab(R)
