"""Renderer directions <-> a Fourier file's ``(mu_i, mu_o, phi_d)``, and what a file holds per output
channel (reflection albedo, the smooth coat's mirror term, spectral channels, the map to linear sRGB).

The mapping (docs/bsdf-format.md, "Renderer mapping"): Mitsuba's local frame has z = the outward
normal; ``wi`` points to the camera and ``wo`` to the light, both away from the surface::

    mu_i = cos θ(wi),   mu_o = -cos θ(wo),   phi_d = π - (φ(wo) - φ(wi))

and the file's value f·|mu_o| is exactly Mitsuba's f · cos θ_o.
"""

from __future__ import annotations

import re
import weakref

import numpy as np

from flakedb.bsdf import catmull_rom_cdf, catmull_rom_weights
from flakedb.bsdf.table import G_FROM_YRB
from flakedb.colour.colorimetry import spectra_to_rgb_mode
from flakedb.optics.fresnel import fresnel_dielectric

#: Y of linear sRGB (docs/bsdf-format.md, "colour").
RGB_TO_Y = np.array([0.212671, 0.715160, 0.072169])
_CHANNEL_NM = re.compile(r"^\s*([0-9]+(?:\.[0-9]*)?)\s*nm\s*$")


class MeasuredExportError(ValueError):
    """A Fourier file that cannot be exported as asked (e.g. spectral from an RGB file)."""



# --------------------------------------------------------------------------------------------
# Geometry: renderer directions <-> the file's (mu_i, mu_o, phi_d)
# --------------------------------------------------------------------------------------------
def file_coordinates(wi, wo):
    """``(mu_i, mu_o, phi_d)`` of local-frame directions ``wi`` (to the camera) and ``wo`` (to the
    light), both (..., 3) unit vectors pointing away from the surface, z the outward normal.

    ``mu_i = wi_z``, ``mu_o = -wo_z``, ``phi_d = π - (φ_o - φ_i)`` folded into [0, π] (the file's
    series is even in phi_d), conventions and docs/bsdf-format.md.  phi_d [rad].
    """
    wi = np.asarray(wi, dtype=np.float64)
    wo = np.asarray(wo, dtype=np.float64)
    si = np.hypot(wi[..., 0], wi[..., 1])
    so = np.hypot(wo[..., 0], wo[..., 1])
    den = si * so
    cos_dphi = np.where(den > 0, (wi[..., 0] * wo[..., 0] + wi[..., 1] * wo[..., 1])
                        / np.where(den > 0, den, 1.0), 1.0)
    phi_d = np.pi - np.arccos(np.clip(cos_dphi, -1.0, 1.0))
    return wi[..., 2], -wo[..., 2], phi_d


def direction_from_file(wi, mu_o, phi_d):
    """The local-frame direction wo (..., 3) of outgoing cosine ``mu_o`` and azimuth difference
    ``phi_d`` [rad] (file conventions) for the camera direction ``wi`` (..., 3): the inverse of
    :func:`file_coordinates` (``φ_o = φ_i + π - phi_d``, ``wo_z = -mu_o``).

    >>> wi, wo = np.array([0.6, 0.0, 0.8]), np.array([-0.3, 0.4, np.sqrt(0.75)])
    >>> mu_i, mu_o, phi_d = file_coordinates(wi, wo)
    >>> round(float(mu_i), 12), bool(0.0 <= phi_d <= np.pi), bool(np.allclose(direction_from_file(wi, mu_o, phi_d), wo))
    (0.800000000000, True, True)
    """
    wi = np.asarray(wi, dtype=np.float64)
    mu_o = np.asarray(mu_o, dtype=np.float64)
    phi_o = np.arctan2(wi[..., 1], wi[..., 0]) + np.pi - np.asarray(phi_d, dtype=np.float64)
    s = np.sqrt(np.maximum(0.0, 1.0 - mu_o * mu_o))
    return np.stack([s * np.cos(phi_o), s * np.sin(phi_o), -mu_o], axis=-1)


# --------------------------------------------------------------------------------------------
# What a file holds, per output channel
# --------------------------------------------------------------------------------------------
def _stored_to_eval(b) -> np.ndarray:
    """(Cs, Cout) matrix from the reader's stored channels to what ``eval`` returns."""
    if b.kind == "bsdf":
        if b.n_channels == 1:
            return np.ones((1, 3))
        gy, gr, gb = G_FROM_YRB
        return np.array([[0.0, gy, 0.0], [1.0, gr, 0.0], [0.0, gb, 1.0]])   # rows Y, R, B
    return np.eye(b.n_channels)


_ALBEDO_ROWS: "weakref.WeakKeyDictionary" = weakref.WeakKeyDictionary()   # FourierBSDF -> (N, Cout)


def reflectance_albedo(b, mu_i) -> np.ndarray:
    """Directional albedo of **reflection** (outgoing mu_o < 0 only) at incident cosine ``mu_i``,
    per ``eval`` channel: ``2π ∫_{-1}^{0} a_0(mu_i, mu_o) dmu_o`` (..., Cout), without the delta term.

    The same Catmull-Rom integral as :meth:`flakedb.bsdf.FourierBSDF.albedo` (which integrates over
    both hemispheres, reflection + transmission), stopped at the first zero node.  For an opaque
    paint the two agree.
    """
    N = b.n_nodes
    h = (N - 2) // 2                         # index of the first zero node
    cache = _ALBEDO_ROWS.get(b)
    if cache is None:
        rows = np.zeros((N, b.n_channels))
        for s in range(0, N, 16):           # a_0 at every node pair, in blocks of incident rows
            mi_ = b.nodes[s:s + 16]
            a0 = b.series(mi_[:, None], b.nodes[None, :h + 1])[..., 0]      # (r, h+1, Cs)
            rows[s:s + 16] = catmull_rom_cdf(b.nodes[:h + 1], np.moveaxis(a0, 1, -1))[..., -1]
        cache = 2.0 * np.pi * rows @ _stored_to_eval(b)                     # (N, Cout)
        _ALBEDO_ROWS[b] = cache
    off, w = catmull_rom_weights(b.nodes, np.asarray(mu_i, dtype=np.float64))
    idx = np.clip(off[..., None] + np.arange(4), 0, N - 1)
    return np.einsum("...a,...ac->...c", w, cache[idx])


def delta_reflectance(delta, mu_i) -> np.ndarray:
    """Reflectance of the mirror term ``delta`` at incident cosine ``mu_i`` (> 0, light from above):
    ``F(mu_i; eta)`` for ``{"kind": "fresnel", "eta": η}`` (unpolarised, flakedb.optics.fresnel),
    0 for no delta.  Raises ValueError for a kind this module does not know."""
    mu_i = np.asarray(mu_i, dtype=np.float64)
    if delta is None:
        return np.zeros_like(mu_i)
    if delta.get("kind") != "fresnel":
        raise ValueError(f"unknown mirror term {delta!r}: flakedb.render.mitsuba knows kind = 'fresnel'")

    return np.where(mu_i > 0, fresnel_dielectric(np.clip(mu_i, 0.0, 1.0), float(delta["eta"])).R, 0.0)


def channel_wavelengths(b) -> np.ndarray | None:
    """Wavelengths [nm] of a spectral file's channels, or None when the channels are not spectral.

    From the metadata ``wavelength_nm`` when it has one entry per channel, else from channel names
    like ``"450nm"`` (what ``flakedb compose`` writes).
    """
    wl = b.metadata.get("wavelength_nm") if isinstance(b.metadata, dict) else None
    if wl is not None and np.size(wl) == b.n_channels and b.kind == "h5":
        return np.asarray(wl, dtype=np.float64)
    m = [_CHANNEL_NM.match(str(c)) for c in b.channels]
    if b.kind == "h5" and len(m) > 1 and all(m):
        return np.array([float(x.group(1)) for x in m])
    return None


def rgb_matrix(b) -> np.ndarray:
    """(Cout, 3): ``eval`` channels -> linear sRGB (identity for RGB, repeat for mono, the white-
    normalised CIE 1931 / D65 map of :func:`flakedb.colour.colorimetry.spectra_to_rgb_mode` for spectra)."""
    chans = tuple(b.channels)
    if b.kind == "bsdf" or chans == ("R", "G", "B"):
        return np.eye(3)
    if len(chans) == 1:
        return np.ones((1, 3))
    wl = channel_wavelengths(b)
    if wl is None:
        raise MeasuredExportError(
            f"{b.path}: channels {chans} are neither R, G, B, mono nor wavelengths (e.g. '450nm'); "
            f"cannot convert to RGB")

    order = np.argsort(wl)
    try:
        m = spectra_to_rgb_mode(np.eye(len(chans))[:, order], wl[order])      # (C, 3)
    except ValueError as e:
        raise MeasuredExportError(f"{b.path}: cannot convert its spectral channels {chans} to RGB ({e}); "
                                  f"export with variant 'spectral' instead") from None
    return m

