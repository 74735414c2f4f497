"""Measured BRDFs of the RGL material database (EPFL; J. Dupuy and W. Jakob, "An Adaptive
Parameterization for Efficient Material Acquisition and Rendering", ACM Trans. Graph. 37(6) 274, 2018,
doi:10.1145/3272127.3275059) read at multi-angle instrument geometries: a measured paint becomes a
:mod:`flakedb.match.targets` target (docs/validation.md).

The database's files (``<name>_rgb.bsdf``, ``<name>_spec.bsdf``) are Mitsuba ``tensor_file``s.  Licence:
"Unless otherwise noted, all material data is licensed under the Creative Commons Zero (CC0) license"
(rgl.epfl.ch/pages/lab/material-database), so measured targets derived from them may ship.

File layout (Mitsuba's ``tensor_file`` v1.0; read here, written again by :func:`write_tensor_file`)
--------------------------------------------------------------------------------------------------
``b"tensor_file\\0"``, version bytes (1, 0), a little-endian uint32 field count, then per field: uint16
name length, the UTF-8 name, uint16 rank, uint8 dtype (1 u8, 2 i8, 3 u16, 4 i16, 5 u32, 6 i32, 7 u64,
8 i64, 9 f16, 10 f32, 11 f64), uint64 byte offset of the data, rank × uint64 shape; the data are C-ordered
little-endian arrays at their offsets.  Fields of a BRDF: ``theta_i`` (n_θ), ``phi_i`` (n_φ; one value for
an isotropic material), ``ndf`` and ``sigma`` (n_φm × n_θm grids over the unit square ``(u_φ, u_θ)``),
``vndf`` and ``luminance`` (n_φ × n_θ × rows × cols), ``rgb`` (n_φ × n_θ × 3 × rows × cols) or
``spectra`` (n_φ × n_θ × n_λ × rows × cols) with ``wavelengths`` [nm], ``jacobian`` (uint8), ``description``.

Evaluation (the paper's §5 and the reference code ``powitacq::BRDF::eval``, github.com/rgl-epfl/brdf-loader,
BSD-3, read here and re-derived, not copied)
-------------------------------------------------------------------------------------------------------
With the half vector ω_m = (ω_i + ω_o)/|ω_i + ω_o| and the unit-square coordinates
u(θ) = √(2θ/π), u(φ) = (φ + π)/(2π) (for an isotropic material φ_m − φ_i, wrapped to [0, 1)):

    f_r(ω_i, ω_o) cos θ_o = R(s; φ_i, θ_i) · D(u_m) / (4 σ(u_i))                         (Dupuy & Jakob eq. 13)

where D is the microfacet density (``ndf``), σ(ω_i) = ∫ D(m) ⟨ω_i·m⟩ dm its projected area (``sigma``), and
R the measured reflectance sampled on a grid in the *warped* square: s = V⁻¹(u_m; φ_i, θ_i) is the inverse
of the visible-normal (VNDF) sampling map, a marginal-then-conditional inversion of the piecewise-bilinear
density ``vndf`` (:func:`vndf_invert`).  ``ndf``, ``sigma`` and R are bilinear in their squares, and every
table is interpolated linearly between its θ_i (and φ_i) slices after normalising each slice (the
reference code's ``Marginal2D``).  The RGB files hold R in linear sRGB, converted by the database from the
measured spectra (negative, out-of-gamut values are clipped to zero on evaluation, as the reference code
does).  The reference code's ``eval`` returns f_r cos θ_o ("Evaluate f_r * cos"); :func:`rgl_brdf` divides
by cos θ_o and returns f_r [1/sr] (tested by reciprocity: f_r(a, b) = f_r(b, a) although the table is
sliced by the first argument only).

In-plane instrument geometry: the conventions of :mod:`flakedb.match.merl` (light at θ_i in the x–z plane,
detector at θ_v = θ_i − γ); the instrument reads R = π f_r.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from flakedb.match.merl import in_plane_directions, merl_rgb_to_lab

__all__ = ["RglBrdf", "RglError", "read_rgl", "read_tensor_file", "rgl_brdf", "rgl_spectral_target", "rgl_target",
           "vndf_invert", "write_tensor_file"]

TENSOR_MAGIC = b"tensor_file\0"
#: Mitsuba Struct::EType codes -> numpy little-endian dtypes
TENSOR_DTYPES = {1: "u1", 2: "i1", 3: "<u2", 4: "<i2", 5: "<u4", 6: "<i4", 7: "<u8", 8: "<i8", 9: "<f2",
                 10: "<f4", 11: "<f8"}
#: Largest field accepted (elements): a spectral 64 × 64 file has 6.4 million.
MAX_FIELD_ELEMENTS = 50_000_000


class RglError(ValueError):
    """A tensor / RGL file that cannot be read (the message names the file and what is wrong)."""


def read_tensor_file(path):
    """Fields of a Mitsuba ``tensor_file`` as {name: numpy array} (module docstring for the layout).
    Refuses a file whose header is not a tensor file or whose fields run past its end."""
    p = Path(path)
    try:
        raw = p.read_bytes()
    except OSError as e:
        raise RglError(f"{p}: cannot be read ({e.strerror or e})") from None
    if raw[:12] != TENSOR_MAGIC or len(raw) < 18:
        raise RglError(f"{p}: not a tensor_file (the RGL database's .bsdf format): header {raw[:12]!r}")
    if raw[12:14] != b"\x01\x00":
        raise RglError(f"{p}: tensor_file version {raw[12]}.{raw[13]}, only 1.0 is known")
    (n_fields,) = struct.unpack_from("<I", raw, 14)
    pos, fields = 18, {}
    try:
        for _ in range(n_fields):
            (nl,) = struct.unpack_from("<H", raw, pos)
            name = raw[pos + 2:pos + 2 + nl].decode("utf-8")
            pos += 2 + nl
            ndim, code, offset = struct.unpack_from("<HBQ", raw, pos)
            pos += 11
            shape = struct.unpack_from("<" + "Q" * ndim, raw, pos)
            pos += 8 * ndim
            if code not in TENSOR_DTYPES:
                raise RglError(f"{p}: field {name!r} has unknown dtype code {code}")
            n = int(np.prod(shape, dtype=np.int64))
            dt = np.dtype(TENSOR_DTYPES[code])
            if n > MAX_FIELD_ELEMENTS or offset + n * dt.itemsize > len(raw):
                raise RglError(f"{p}: field {name!r} {list(shape)} at byte {offset} runs past the file's "
                               f"{len(raw)} bytes; the file is truncated (or a Git LFS pointer)")
            fields[name] = np.frombuffer(raw, dtype=dt, count=n, offset=offset).reshape(shape)
    except (struct.error, UnicodeDecodeError) as e:
        raise RglError(f"{p}: damaged tensor_file header ({e})") from None
    return fields


def write_tensor_file(path, fields, align=8):
    """Write {name: array} as a ``tensor_file`` (each field's data aligned to ``align`` bytes); used for
    synthetic test files.  :func:`read_tensor_file` reads it back:

    >>> import tempfile
    >>> f = Path(tempfile.mkdtemp()) / "t.bsdf"
    >>> write_tensor_file(f, {"theta": np.array([0.0, 0.5], np.float32), "n": np.arange(6, dtype=np.int32).reshape(2, 3)})
    >>> back = read_tensor_file(f)
    >>> back["theta"].tolist(), back["n"].shape, back["n"].dtype.kind
    ([0.0, 0.5], (2, 3), 'i')
    """
    codes = {np.dtype(v).newbyteorder("<"): k for k, v in TENSOR_DTYPES.items()}
    arrs = {k: np.ascontiguousarray(v) for k, v in fields.items()}
    head = len(TENSOR_MAGIC) + 2 + 4 + sum(2 + len(k.encode()) + 11 + 8 * a.ndim for k, a in arrs.items())
    offsets, pos = {}, head
    for k, a in arrs.items():
        pos = -(-pos // align) * align
        offsets[k] = pos
        pos += a.nbytes
    out = bytearray(pos)
    h = bytearray(TENSOR_MAGIC + b"\x01\x00" + struct.pack("<I", len(arrs)))
    for k, a in arrs.items():
        name = k.encode()
        h += struct.pack("<H", len(name)) + name + struct.pack("<HBQ", a.ndim, codes[a.dtype.newbyteorder("<")],
                                                               offsets[k])
        h += struct.pack("<" + "Q" * a.ndim, *a.shape)
        out[offsets[k]:offsets[k] + a.nbytes] = a.astype(a.dtype.newbyteorder("<")).tobytes()
    out[:head] = h
    Path(path).write_bytes(bytes(out))


def _param_corners(values, p):
    """Linear interpolation between parameter slices: (index of the lower slice, weight of the upper) for
    parameter values ``p`` in the sorted slice positions ``values`` (clamped to the end slices, as the
    reference code's find_interval)."""
    values = np.asarray(values, dtype=float)
    if values.size == 1:
        return np.zeros(np.shape(p), dtype=int), np.zeros(np.shape(p))
    i = np.clip(np.searchsorted(values, p, side="right") - 1, 0, values.size - 2)
    w = np.clip((p - values[i]) / (values[i + 1] - values[i]), 0.0, 1.0)
    return i, w


def _slice_lerp(table, i_phi, w_phi, i_th, w_th, *idx):
    """Entries ``table[φ, θ, *idx]`` of tables (n_φ, n_θ, ...) interpolated linearly between the slices
    around each query (N,); ``idx`` are per-query index arrays (N,) into the trailing axes (all trailing
    axes kept when none is given)."""
    j_phi = np.minimum(i_phi + 1, table.shape[0] - 1)
    pad = (1,) * (table.ndim - 2 - len(idx))
    wp, wt = w_phi.reshape(w_phi.shape + pad), w_th.reshape(w_th.shape + pad)
    get = lambda a, b: table[(a, b) + idx]
    lo = get(i_phi, i_th) * (1 - wt) + get(i_phi, i_th + 1) * wt
    hi = get(j_phi, i_th) * (1 - wt) + get(j_phi, i_th + 1) * wt
    return lo * (1 - wp) + hi * wp


def _bilinear(grid, x, y):
    """Bilinear interpolation of a grid (rows, cols) at unit-square points x (columns) and y (rows) in
    [0, 1], the grid's nodes on the square's edges and uniformly between (the reference code's Marginal2D
    eval of an un-normalised table)."""
    rows, cols = grid.shape
    gx, gy = np.asarray(x) * (cols - 1), np.asarray(y) * (rows - 1)
    ix = np.clip(np.floor(gx).astype(int), 0, cols - 2)
    iy = np.clip(np.floor(gy).astype(int), 0, rows - 2)
    fx, fy = gx - ix, gy - iy
    return ((1 - fy) * ((1 - fx) * grid[iy, ix] + fx * grid[iy, ix + 1])
            + fy * ((1 - fx) * grid[iy + 1, ix] + fx * grid[iy + 1, ix + 1]))


def _vndf_cdfs(vndf):
    """Per slice (..., rows, cols): the density normalised to integrate to 1 over the unit square, its
    row-wise (conditional) running integral and the marginal running integral over rows, both by the
    trapezoidal rule of the piecewise-bilinear density, in cell units (the reference code's Marginal2D)."""
    v = np.asarray(vndf, dtype=float)
    cond = np.concatenate([np.zeros(v.shape[:-1] + (1,)),
                           np.cumsum(0.5 * (v[..., 1:] + v[..., :-1]), axis=-1)], axis=-1)
    row_tot = cond[..., -1]
    marg = np.concatenate([np.zeros(v.shape[:-2] + (1,)),
                           np.cumsum(0.5 * (row_tot[..., 1:] + row_tot[..., :-1]), axis=-1)], axis=-1)
    norm = 1.0 / marg[..., -1:]
    return v * norm[..., None], cond * norm[..., None], marg * norm


def vndf_invert(dens, cond, marg, u, i_phi, w_phi, i_th, w_th):
    """Inverse of the VNDF sampling map: the point s in the warped unit square (N, 2) = (x, y) whose image is
    the half-vector coordinates ``u`` (N, 2) = (u_θm, u_φm); tables from :func:`_vndf_cdfs`, interpolated
    between slices.  Marginal-then-conditional inversion of a piecewise-bilinear density:
    s_y = (M(row) + ∫ of the row-interpolated row totals) , s_x = conditional CDF / row total."""
    rows, cols = dens.shape[-2:]
    gx, gy = u[:, 0] * (cols - 1), u[:, 1] * (rows - 1)
    ix = np.minimum(np.floor(gx).astype(int), cols - 2)
    iy = np.minimum(np.floor(gy).astype(int), rows - 2)
    fx, fy = gx - ix, gy - iy
    at = lambda t, *k: _slice_lerp(t, i_phi, w_phi, i_th, w_th, *k)
    c0 = (1 - fy) * at(dens, iy, ix) + fy * at(dens, iy + 1, ix)          # density along x at this y, cell edges
    c1 = (1 - fy) * at(dens, iy, ix + 1) + fy * at(dens, iy + 1, ix + 1)
    sx = fx * (c0 + 0.5 * fx * (c1 - c0))                                 # ∫ within the cell
    sx = sx + (1 - fy) * at(cond, iy, ix) + fy * at(cond, iy + 1, ix)
    last = np.full_like(ix, cols - 1)
    r0, r1 = at(cond, iy, last), at(cond, iy + 1, last)                    # row totals
    sx = sx / ((1 - fy) * r0 + fy * r1)
    sy = fy * (r0 + 0.5 * fy * (r1 - r0)) + at(marg, iy)
    return np.stack([sx, sy], axis=-1)


@dataclass(frozen=True)
class RglBrdf:
    """An RGL measured BRDF, its tables as read (float) and the VNDF tables normalised for inversion."""

    name: str
    description: str
    theta_i: np.ndarray        # [rad], slices
    phi_i: np.ndarray          # [rad], slices (one for isotropic)
    ndf: np.ndarray            # (n_φm, n_θm)
    sigma: np.ndarray          # (n_φm, n_θm)
    vndf: tuple                # (density, conditional, marginal) per slice
    channels: np.ndarray       # (n_φ, n_θ, C, rows, cols): R in the warped square
    wavelengths_nm: np.ndarray | None   # for spectral files; None for RGB (linear sRGB)

    @property
    def isotropic(self):
        return self.phi_i.size <= 2


def read_rgl(path):
    """An RGL ``.bsdf`` file (RGB or spectral) as :class:`RglBrdf`; refuses anisotropic files (17 φ_i slices:
    not needed for in-plane instrument geometries of isotropic paints) and inconsistent shapes."""
    p = Path(path)
    f = read_tensor_file(p)
    need = ("theta_i", "phi_i", "ndf", "sigma", "vndf")
    miss = [k for k in need if k not in f] + ([] if ("rgb" in f or "spectra" in f) else ["rgb or spectra"])
    if miss:
        raise RglError(f"{p}: not an RGL BRDF file (missing fields {miss})")
    chan = f["rgb"] if "rgb" in f else f["spectra"]
    th, ph = f["theta_i"].astype(float), f["phi_i"].astype(float)
    if f["phi_i"].size > 2:
        raise RglError(f"{p}: anisotropic material ({ph.size} φ_i slices); flakedb reads isotropic ones only")
    if (chan.ndim != 5 or chan.shape[:2] != (ph.size, th.size) or f["vndf"].shape[:2] != (ph.size, th.size)
            or f["ndf"].ndim != 2 or f["sigma"].ndim != 2):
        raise RglError(f"{p}: inconsistent RGL field shapes (vndf {f['vndf'].shape}, channels {chan.shape}, "
                       f"theta_i {th.shape}, phi_i {ph.shape})")
    desc = bytes(f["description"]).decode("utf-8", "replace") if "description" in f else ""
    wl = f["wavelengths"].astype(float) if "spectra" in f else None
    return RglBrdf(name=p.name.rsplit(".", 1)[0], description=desc, theta_i=th, phi_i=ph,
                   ndf=f["ndf"].astype(float), sigma=f["sigma"].astype(float), vndf=_vndf_cdfs(f["vndf"]),
                   channels=chan.astype(float), wavelengths_nm=wl)


def _u_theta(theta):
    return np.sqrt(np.maximum(theta, 0.0) * (2.0 / np.pi))


def _u_phi(phi):
    return (phi + np.pi) / (2.0 * np.pi)


def rgl_brdf(brdf, wi, wo, clip=True):
    """f_r [1/sr] of an :class:`RglBrdf` at direction pairs (N, 3) (unit vectors, z the normal), (N, C) over
    its channels (RGB or wavelengths); 0 below the horizon.  Module docstring, eq. 13, divided by cos θ_o.
    ``clip`` sets negative (out-of-gamut) channel values to zero, as the reference code."""
    wi = np.atleast_2d(np.asarray(wi, dtype=float))
    wo = np.atleast_2d(np.asarray(wo, dtype=float))
    wm = wi + wo
    wm = wm / np.linalg.norm(wm, axis=-1, keepdims=True)
    # elevation by the chord (robust near the pole), as the reference code
    elev = lambda d: 2.0 * np.arcsin(np.clip(0.5 * np.sqrt(d[:, 0] ** 2 + d[:, 1] ** 2 + (d[:, 2] - 1) ** 2), 0, 1))
    th_i, ph_i = elev(wi), np.arctan2(wi[:, 1], wi[:, 0])
    th_m, ph_m = elev(wm), np.arctan2(wm[:, 1], wm[:, 0])
    u_i = np.stack([_u_theta(th_i), _u_phi(ph_i)], axis=-1)
    u_m = np.stack([_u_theta(th_m), _u_phi(ph_m - ph_i if brdf.isotropic else ph_m)], axis=-1)
    u_m[:, 1] -= np.floor(u_m[:, 1])
    ip, wp = _param_corners(brdf.phi_i, ph_i)
    it, wt = _param_corners(brdf.theta_i, th_i)
    s = vndf_invert(*brdf.vndf, u_m, ip, wp, it, wt)
    rows, cols = brdf.channels.shape[-2:]
    gx, gy = s[:, 0] * (cols - 1), s[:, 1] * (rows - 1)
    ix = np.clip(np.floor(gx).astype(int), 0, cols - 2)
    iy = np.clip(np.floor(gy).astype(int), 0, rows - 2)
    fx, fy = (gx - ix)[:, None], (gy - iy)[:, None]
    ch = np.moveaxis(brdf.channels, 2, -1)                                 # (n_φ, n_θ, rows, cols, C)
    at = lambda y, x: _slice_lerp(ch, ip, wp, it, wt, y, x)                # (N, C)
    vals = ((1 - fy) * ((1 - fx) * at(iy, ix) + fx * at(iy, ix + 1))
            + fy * ((1 - fx) * at(iy + 1, ix) + fx * at(iy + 1, ix + 1)))
    if clip:
        vals = np.maximum(vals, 0.0)
    D = _bilinear(brdf.ndf, u_m[:, 0], u_m[:, 1])
    sig = _bilinear(brdf.sigma, u_i[:, 0], u_i[:, 1])
    cos_o = wo[:, 2]
    ok = (wi[:, 2] > 0) & (cos_o > 0)
    f = vals * (D / (4.0 * sig * np.where(ok, cos_o, 1.0)))[:, None]
    return np.where(ok[:, None], f, 0.0)


def rgl_target(brdf, geometries_deg):
    """(reflectance factors R = π f_r (G, 3) linear sRGB, L*a*b* (G, 3) D65 / 2°) of an RGB :class:`RglBrdf`
    at in-plane geometries (G, 2) (θ_i, aspecular) [deg]; CIELAB through :func:`flakedb.match.merl.merl_rgb_to_lab`
    (the file's RGB is linear sRGB).  Evaluated without clipping negative channels: the file keeps the
    out-of-gamut values of its spectra's sRGB, so M_sRGB · R is the spectra's XYZ (as far as the database's
    conversion is linear) and CIELAB is computed from it."""
    if brdf.wavelengths_nm is not None:
        raise RglError(f"{brdf.name}: a spectral file; rgl_target takes the RGB version (<name>_rgb.bsdf), "
                       "rgl_spectral_target the spectral one")
    wi, wo = in_plane_directions(geometries_deg)
    R = np.pi * rgl_brdf(brdf, wi, wo, clip=False)
    return R, merl_rgb_to_lab(R)


def rgl_spectral_target(brdf, geometries_deg, wavelength_nm=None):
    """Spectral reflectance factors R = π f_r (G, W) of a spectral :class:`RglBrdf` (``<name>_spec.bsdf``) at
    in-plane geometries (G, 2) [deg], linearly interpolated from the file's wavelengths (195 bins, 358.6-1001.9
    nm, ~3.3 nm apart) to ``wavelength_nm`` (default 380-780 nm every 5 nm, a uniform grid a target CSV takes);
    returns (R, wavelength_nm).  Negative values (measurement noise in dark bins) are kept, as measured."""
    if brdf.wavelengths_nm is None:
        raise RglError(f"{brdf.name}: an RGB file; rgl_spectral_target takes the spectral version (<name>_spec.bsdf)")
    wl = np.arange(380.0, 781.0, 5.0) if wavelength_nm is None else np.asarray(wavelength_nm, dtype=float)
    src = brdf.wavelengths_nm
    if wl.min() < src.min() or wl.max() > src.max():
        raise RglError(f"{brdf.name}: wavelengths {wl.min():g}-{wl.max():g} nm asked, the file covers "
                       f"{src.min():g}-{src.max():g} nm")
    wi, wo = in_plane_directions(geometries_deg)
    R = np.pi * rgl_brdf(brdf, wi, wo, clip=False)                       # (G, n_λ)
    return np.stack([np.interp(wl, src, r) for r in R]), wl
