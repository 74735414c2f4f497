"""Mitsuba 3 integration: export to the ``measured`` plugin's tensor file, and a ``flakedb`` BSDF plugin.

Two ways to render a flakedb Fourier file (``.bsdf`` or ``.h5``, :mod:`flakedb.bsdf`) in Mitsuba 3
(tested with 3.9.1; ``shared/design/renderers.md`` has the facts this builds on):

1. :func:`export_measured` writes an RGL "tensor file" for Mitsuba's built-in ``measured`` BSDF
   (Dupuy & Jakob 2018).  Fast in every variant, but reflection from the front side only, and the
   smooth coat's mirror term (the ``delta`` of the file) **cannot be carried**: it is dropped and
   the summary says how much albedo that loses (``F(θ_i; η)``, 4 % at normal incidence for η = 1.5).
2. :func:`register` registers a Python BSDF plugin, ``{"type": "flakedb", "filename": ...}``, that
   evaluates the file with flakedb's reader (exact, no resampling), importance-samples it with the
   reader's ``sample``, and adds the mirror term back as a delta lobe.

Mitsuba is imported inside the functions, so this module imports without it.  The render check
of renderers.md (a sphere under a constant environment) is :func:`furnace_sphere_scene` and
:func:`furnace_sphere_prediction`.

Direction mapping (docs/bsdf-format.md, "Renderer mapping")
------------------------------------------------------
Mitsuba's local frame has z = the outward normal; in ``eval(ctx, si, wo)`` ``si.wi`` points to the
camera and ``wo`` to the light, both away from the surface, and the value returned is f · cos θ_o.
With the file's conventions (:mod:`flakedb.conventions`)::

    mu_i = cos θ(wi),   mu_o = -cos θ(wo),   phi_d = π - (φ(wo) - φ(wi))

and the file's value f·|mu_o| is exactly Mitsuba's f · cos θ_o.  The series is even in phi_d, so
only ``cos(φ(wo) - φ(wi))`` matters (:func:`file_coordinates`).  Front-side reflection only
(``cos θ(wi) > 0``, ``cos θ(wo) > 0``); a table's transmission entries are not rendered.

The ``measured`` tensor file (what :func:`measured_tensors` builds)
-------------------------------------------------------------------
The plugin parameterises the half vector m by ``u = (sqrt(2 θ_m / π), (φ_m - φ_i + π) / 2π)``; its
value at a direction pair is a bilinear lookup, at u, of a grid with vertices at ``k / (n - 1)``,
linearly interpolated in θ_i between the ``theta_i`` slices.  The construction (renderers.md, "a
construction that worked"):

* isotropic: ``phi_i = [0]``; ``jacobian = 0`` (so ``ndf``/``sigma`` are unused, 2 x 2 ones);
* identity ``vndf`` (all ones): the grid is indexed directly by half-vector coordinates;
* ``rgb[0, t, c, j, k]`` (or ``spectra[0, t, λ, j, k]``) = f · cos θ_o at θ_i = ``theta_i[t]``,
  ``u = (k/(n-1), j/(n-1))``: j runs over φ_m, k over θ_m (0 where wo or wi·m is below the horizon),
  from the file's evaluation clamped to >= 0;
* ``luminance[0, t, j, k]`` = Y(f cos θ_o) · J + floor with the plugin's Jacobian
  ``J = max(2π² u_x sin θ_m, 1e-6) · 4 (wi·m)``, so that the plugin's
  ``pdf = luminance density x vndf density / J`` is proportional to f cos θ_o; the floor
  (``floor`` x the slice's mean) keeps sampling alive wherever the bilinear value may be > 0.

Y is the luminance of linear sRGB (0.212671, 0.715160, 0.072169); for a spectral export the
sampling channel is the mean over wavelengths (flakedb's own sampling channel of a spectral file).

The plugin (what :func:`register` registers)
--------------------------------------------
* ``eval`` = the table's f·|mu_o| (every channel clamped to >= 0, as pbrt-v3 does); ``pdf`` = the
  reader's ``pdf`` times the probability of choosing the tabulated lobe;
* ``sample``: with the mirror term present (``delta = {"kind": "fresnel", "eta": η}``), the delta
  lobe is chosen with probability ``F / (F + A(mu_i))`` (F the Fresnel reflectance at the coat,
  A the tabulated albedo of the sampling channel, 2π·cdf(mu_i)[N-1]), flagged ``DeltaReflection``
  (component 0); the tabulated lobe is ``GlossyReflection`` (component 1, or 0 without delta).
* the work is done by compiled kernels (numba) built around the reader's own compiled evaluation
  and sampling kernels of :mod:`flakedb.bsdf` (tested equal to ``FourierBSDF.eval``/``pdf``/
  ``sample``): one compiled call per Mitsuba call.  Scalar variants make one Python call per sample
  (~0.1-0.2 ms a camera sample: keep scalar renders small); JIT variants (``llvm_ad_rgb``) call once
  per wavefront: render inside :func:`evaluated_mode` (symbolic loops and calls off), because the
  plugin needs evaluated arrays (the plugin raises a clear error in symbolic mode).
* colours: in RGB variants (``scalar_rgb``, ``llvm_ad_rgb``) an RGB or mono file as is, a spectral
  HDF5 file converted to white-normalised linear sRGB (CIE 1931 / D65, as ``flakedb compose`` makes
  its ``.bsdf``); in spectral variants a mono file, or a spectral HDF5 file linear in wavelength
  between its channels (clamped beyond them).  Every channel is clamped to >= 0 (pbrt-v3 does the
  same): an out-of-gamut colour whose table has negative sRGB values renders brighter than its
  flakedb albedo says.
"""

from __future__ import annotations

import contextlib
import math
import os
import re
import struct
import weakref
from pathlib import Path

import numba
import numpy as np

from flakedb import __version__
from flakedb.atomic import atomic_path
from flakedb.bsdf import catmull_rom_cdf, catmull_rom_weights, open_bsdf
from flakedb.bsdf.kernels import compiled as compiled_kernels
from flakedb.bsdf.table import G_FROM_YRB
from flakedb.colour.colorimetry import spectra_to_rgb_mode
from flakedb.colour.gamut import desaturate_points
from flakedb.optics.fresnel import fresnel_dielectric
from flakedb.safeio import FileTooLargeError, read_limited

# the reader's compiled kernels, by name: this module's own compiled kernels call them
cr_weights_1 = compiled_kernels().cr_weights_1
sample_kernel = compiled_kernels().sample_kernel
series_kernel = compiled_kernels().series_kernel

__all__ = [
    "MeasuredExportError",
    "file_coordinates",
    "direction_from_file",
    "reflectance_albedo",
    "delta_reflectance",
    "channel_wavelengths",
    "measured_tensors",
    "write_tensor_file",
    "read_tensor_file",
    "export_measured",
    "register",
    "evaluated_mode",
    "llvm_library",
    "LLVM_LIBRARY_DEFAULT",
    "furnace_sphere_scene",
    "furnace_sphere_prediction",
    "RES_DEFAULT",
    "N_THETA_DEFAULT",
]

#: Half-vector grid resolution n of the measured export (renderers.md: n = 96 gave 0.09 % eval error).
RES_DEFAULT = 96
#: Number of incident elevations theta_i in the measured export (over [0°, 90°], denser at grazing).
N_THETA_DEFAULT = 24
#: Largest half-vector grid and θ_i count of an export: the evaluation holds ~10 float64 arrays of
#: n_theta × res² entries (res 512, 24 θ_i: ≈ 0.5 GB); res 100000 would ask for 74.5 GiB.
RES_MAX = 512
N_THETA_MAX = 256
#: Largest tensor file :func:`read_tensor_file` reads [bytes].
TENSOR_FILE_MAX_BYTES = 4 * 1024 ** 3
#: The luminance floor of the measured export, as a fraction of each slice's mean.
FLOOR_DEFAULT = 1e-3
#: Where Debian's libllvm19 puts the library the ``llvm_ad_*`` variants need (renderers.md).
LLVM_LIBRARY_DEFAULT = "/usr/lib/x86_64-linux-gnu/libLLVM.so.19.1"

#: Y of linear sRGB (docs/bsdf-format.md, "colour").
_RGB_TO_Y = np.array([0.212671, 0.715160, 0.072169])
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
    :func:`file_coordinates` (``φ_o = φ_i + π - phi_d``, ``wo_z = -mu_o``)."""
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


def _rgb_matrix(b) -> np.ndarray:
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


# --------------------------------------------------------------------------------------------
# The measured export
# --------------------------------------------------------------------------------------------
def _half_vector_grid(theta_i, res):
    """``(wi (T, 1, 1, 3), wo (T, n, n, 3), J (T, n, n), valid (T, n, n))`` at the plugin's grid
    vertices (j over φ_m, k over θ_m) for incident elevations ``theta_i`` [rad], phi_i = 0: the
    mirror direction ``wo = 2 (wi·m) m - wi`` of each half vector m, the plugin's Jacobian J, and
    whether wi·m, wo_z and wi_z are all > 0."""
    u = np.linspace(0.0, 1.0, res)
    theta_m = u * u * (np.pi / 2)
    phi_m = (2 * u - 1) * np.pi
    st, ct = np.sin(theta_m), np.cos(theta_m)
    m = np.stack(np.broadcast_arrays(np.cos(phi_m)[:, None] * st[None, :],
                                     np.sin(phi_m)[:, None] * st[None, :],
                                     ct[None, :]), axis=-1)                   # (n_j, n_k, 3)
    wi = np.stack([np.sin(theta_i), np.zeros_like(theta_i), np.cos(theta_i)], axis=-1)[:, None, None, :]
    d = np.sum(wi * m[None], axis=-1)                                         # (T, n, n)
    wo = 2 * d[..., None] * m[None] - wi
    valid = (d > 0) & (wo[..., 2] > 0) & (wi[..., 2] > 0)
    J = np.maximum(2 * np.pi ** 2 * u[None, None, :] * st[None, None, :], 1e-6) * 4 * d
    return wi, wo, J, valid


def check_export_size(res, n_theta):
    """Refuse a half-vector grid ``res`` or θ_i count ``n_theta`` outside the allowed ranges."""
    if not (8 <= int(res) <= RES_MAX):
        raise MeasuredExportError(f"res = {res} is outside the allowed range 8 ≤ res ≤ {RES_MAX} half-vector "
                                  f"vertices per axis (default {RES_DEFAULT})")
    if not (4 <= int(n_theta) <= N_THETA_MAX):
        raise MeasuredExportError(f"n_theta = {n_theta} is outside the allowed range 4 ≤ n_theta ≤ {N_THETA_MAX} "
                                  f"incident elevations (default {N_THETA_DEFAULT})")


def measured_tensors(b, variant: str = "rgb", res: int = RES_DEFAULT, n_theta: int = N_THETA_DEFAULT,
                     floor: float = FLOOR_DEFAULT, description: str | None = None) -> dict:
    """The fields of a ``measured`` tensor file for the FourierBSDF ``b`` (module docstring).

    ``variant="rgb"``: an ``rgb`` field (R, G, B; a mono file repeated, a spectral file mapped to
    white-normalised linear sRGB).  ``variant="spectral"``: ``spectra`` + ``wavelengths`` [nm]
    from an HDF5 file with spectral channels; refused (MeasuredExportError) for RGB or mono files.
    ``res``: half-vector grid vertices per axis (n >= 8); ``n_theta``: θ_i slices over [0, π/2]
    (>= 4) at ``θ = π/2 (t + t(1-t)/2)`` for t uniform on [0, 1] (three times denser at grazing
    incidence than at normal incidence: the paint changes fastest with θ_i there).  ``floor``:
    the luminance floor as a fraction of each slice's mean.  Returns a dict of numpy arrays in the
    file's dtypes (and ``"description"`` as str), ready for :func:`write_tensor_file`.
    """
    if variant not in ("rgb", "spectral"):
        raise MeasuredExportError(f"variant must be 'rgb' or 'spectral', got {variant!r}")
    res, n_theta = int(res), int(n_theta)
    check_export_size(res, n_theta)
    wl = channel_wavelengths(b)
    if variant == "spectral":
        if wl is None:
            what = "mono" if b.n_channels == 1 else ", ".join(b.channels)
            raise MeasuredExportError(
                f"{b.path}: a spectral export needs a flakedb .h5 file with spectral channels (e.g. "
                f"'450nm', …); this file holds {what}. Export it with variant 'rgb', or compose the "
                f"paint in spectral mode and export its .h5.")
        order = np.argsort(wl)
        mix = np.eye(b.n_channels)[:, order]              # eval channels -> ascending wavelengths
        lum_w = np.full(b.n_channels, 1.0 / b.n_channels)
    else:
        mix = _rgb_matrix(b)
        lum_w = _RGB_TO_Y
    t = np.linspace(0.0, 1.0, n_theta)
    theta_i = np.pi / 2 * (t + 0.5 * t * (1 - t))        # 1.5x the mean step at 0°, 0.5x at 90°
    wi, wo, J, valid = _half_vector_grid(theta_i, res)
    mu_i, mu_o, phi_d = file_coordinates(np.broadcast_to(wi, wo.shape), wo)
    vals = np.zeros(valid.shape + (mix.shape[1],))
    if variant == "rgb" and wl is not None:
        # a spectral file's out-of-sRGB colours: desaturated at constant luminance (docs/gamut.md), not clamped
        vals[valid] = desaturate_points(b.eval(mu_i[valid], mu_o[valid], phi_d[valid], clamp="none") @ mix, lum_w)
    else:
        vals[valid] = b.eval(mu_i[valid], mu_o[valid], phi_d[valid], clamp="all") @ mix
    vals = np.maximum(vals, 0.0)                          # (T, n_j, n_k, C)
    lum = (vals @ lum_w) * J
    mean = lum.mean(axis=(1, 2), keepdims=True)
    lum = lum + floor * np.where(mean > 0, mean, 1.0)
    data = np.ascontiguousarray(np.moveaxis(vals, -1, 1)[None], dtype=np.float32)   # (1, T, C, n, n)
    if description is None:
        src = b.path.name if b.path is not None else "table"
        description = f"flakedb export of {src}"
    fields = {
        "description": description,
        "jacobian": np.zeros(1, dtype=np.uint8),
        "theta_i": theta_i.astype(np.float32),
        "phi_i": np.zeros(1, dtype=np.float32),
        "ndf": np.ones((2, 2), dtype=np.float32),
        "sigma": np.ones((2, 2), dtype=np.float32),
        "vndf": np.ones((1, n_theta, 2, 2), dtype=np.float32),
        "luminance": np.ascontiguousarray(lum[None], dtype=np.float32),
    }
    if variant == "spectral":
        fields["spectra"] = data
        fields["wavelengths"] = np.sort(wl).astype(np.float32)
    else:
        fields["rgb"] = data
    return fields


_TENSOR_DTYPES = {np.dtype(np.uint8): 1, np.dtype(np.int8): 2, np.dtype(np.uint16): 3, np.dtype(np.int16): 4,
                  np.dtype(np.uint32): 5, np.dtype(np.int32): 6, np.dtype(np.uint64): 7, np.dtype(np.int64): 8,
                  np.dtype(np.float16): 9, np.dtype(np.float32): 10, np.dtype(np.float64): 11}


def write_tensor_file(path, fields: dict, align: int = 8) -> int:
    """Write an RGL/Mitsuba "tensor file" (the layout of ``mitsuba.python.tensor_io``), atomically.

    Header: ``tensor_file\\0``, version (1, 0) as two u8, u32 field count; per field: u16 name
    length, name, u16 ndim, u8 dtype code, u64 data offset, ndim x u64 shape; then each field's
    data, C order, little-endian, at an ``align``-byte boundary.  ``str`` values are stored as u8.
    Returns the file size [bytes].
    """
    arrays = {}
    for k, v in fields.items():
        a = np.frombuffer(v.encode("utf-8"), dtype=np.uint8) if isinstance(v, str) else np.ascontiguousarray(v)
        if a.dtype not in _TENSOR_DTYPES:
            raise ValueError(f"tensor field {k!r}: unsupported dtype {a.dtype}")
        arrays[k] = a.astype(a.dtype.newbyteorder("<"), copy=False)
    head = bytearray(b"tensor_file\0" + struct.pack("<BBI", 1, 0, len(arrays)))
    slots = {}
    for k, a in arrays.items():
        name = k.encode("utf-8")
        head += struct.pack("<H", len(name)) + name + struct.pack("<HB", a.ndim, _TENSOR_DTYPES[a.dtype])
        slots[k] = len(head)
        head += struct.pack("<Q", 0) + struct.pack("<" + "Q" * a.ndim, *a.shape)
    pos = len(head)
    offsets = {}
    for k, a in arrays.items():
        pos = (pos + align - 1) // align * align
        offsets[k] = pos
        struct.pack_into("<Q", head, slots[k], pos)
        pos += a.nbytes
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)

    with atomic_path(path, suffix="") as tmp:
        with open(tmp, "wb") as fh:
            fh.write(head)
            for k, a in arrays.items():
                fh.write(b"\0" * (offsets[k] - fh.tell()))
                fh.write(a.tobytes())
            size = fh.tell()
    return size


def read_tensor_file(path) -> dict:
    """Read a tensor file written by :func:`write_tensor_file` (or ``tensor_io``): name -> array.

    Checks what it reads (header, field count, dtype codes, shapes and offsets inside the file,
    finite floating-point values) and raises :class:`MeasuredExportError` naming the file and the
    field otherwise."""
    codes = {v: k for k, v in _TENSOR_DTYPES.items()}
    path = Path(path)

    def bad(what):
        return MeasuredExportError(f"{path}: {what}; not a valid tensor file (corrupt or truncated)")

    try:
        raw = read_limited(path, TENSOR_FILE_MAX_BYTES)   # a regular file, at most the limit read
    except FileTooLargeError as e:
        raise MeasuredExportError(f"{path}: {e.size} bytes or more; the limit is {TENSOR_FILE_MAX_BYTES} bytes") from None
    except OSError as e:
        raise MeasuredExportError(f"{path}: cannot read ({e.strerror})") from None
    if raw[:12] != b"tensor_file\0" or raw[12:14] != b"\x01\x00":
        raise MeasuredExportError(f"{path}: not a version 1.0 tensor file")
    try:
        (count,) = struct.unpack_from("<I", raw, 14)
        if count > 1024:
            raise bad(f"field count {count} is outside the allowed range 0 ≤ count ≤ 1024")
        pos = 18
        out = {}
        for _ in range(count):
            (ln,) = struct.unpack_from("<H", raw, pos)
            name = raw[pos + 2:pos + 2 + ln].decode("utf-8")
            pos += 2 + ln
            ndim, code = struct.unpack_from("<HB", raw, pos)
            (off,) = struct.unpack_from("<Q", raw, pos + 3)
            if ndim > 16 or code not in codes:
                raise bad(f"field {name!r}: ndim {ndim} / dtype code {code} is not supported")
            shape = struct.unpack_from("<" + "Q" * ndim, raw, pos + 11)
            pos += 11 + 8 * ndim
            dt = codes[code].newbyteorder("<")
            count_el = int(np.prod(shape, dtype=object))
            if off + count_el * dt.itemsize > len(raw):
                raise bad(f"field {name!r}: shape {tuple(shape)} at offset {off} runs past the end of the "
                          f"{len(raw)}-byte file")
            a = np.frombuffer(raw, dt, count_el, off).reshape(shape)
            if a.dtype.kind == "f" and not np.all(np.isfinite(a)):
                raise bad(f"field {name!r} holds NaN or infinite values")
            out[name] = a
    except struct.error as e:
        raise bad(f"header ends early ({e})") from None
    except UnicodeDecodeError:
        raise bad("a field name is not UTF-8") from None
    return out


def export_measured(src, out, variant: str = "rgb", res: int = RES_DEFAULT, n_theta: int = N_THETA_DEFAULT,
                    floor: float = FLOOR_DEFAULT) -> dict:
    """Export the Fourier file ``src`` (``.bsdf`` or ``.h5``) to a Mitsuba 3 ``measured`` file ``out``.

    Returns a JSON-able summary: ``out``, ``size`` [bytes], ``variant``, ``res``, ``n_theta``,
    ``channels``, and ``dropped``: what the format cannot hold, with the albedo it loses at a few
    incident angles: the mirror term (``delta_albedo``: F(θ_i; η)) and any transmission
    (``transmitted_albedo``: total minus reflected albedo of the table).
    """
    check_export_size(res, n_theta)
    b = open_bsdf(src)
    desc = (f"flakedb {__version__} export of {Path(src).name}: front-side reflection, "
            f"res {res}, {n_theta} theta_i; the mirror term delta={b.delta} is not included")
    fields = measured_tensors(b, variant, res, n_theta, floor, description=desc)
    for k, v in fields.items():
        if isinstance(v, np.ndarray) and v.dtype.kind == "f" and not np.all(np.isfinite(v)):
            raise MeasuredExportError(f"{src}: the export's {k!r} field has non-finite values; nothing written")
    theta = np.array([0.0, 30.0, 45.0, 60.0, 75.0, 85.0])
    mu = np.cos(np.radians(theta))
    refl = reflectance_albedo(b, mu)
    trans = np.maximum(b.albedo(mu) - refl, 0.0)
    dropped = {"theta_i_deg": theta.tolist()}
    if b.delta is not None:
        dropped["delta"] = b.delta
        dropped["delta_albedo"] = delta_reflectance(b.delta, mu).tolist()
    if np.max(trans) > 1e-6 * max(np.max(refl), 1e-300):
        dropped["transmitted_albedo"] = trans.tolist()
    data = fields.get("rgb", fields.get("spectra"))
    size = write_tensor_file(out, fields)  # last: a failure above leaves no file
    return {"out": str(out), "size": size, "variant": variant, "res": res, "n_theta": n_theta,
            "channels": ["R", "G", "B"] if variant == "rgb" else fields["wavelengths"].tolist(),
            "shape": list(data.shape), "reflected_albedo": refl.tolist(), "dropped": dropped}


# --------------------------------------------------------------------------------------------
# The Python plugin
# --------------------------------------------------------------------------------------------
def llvm_library() -> str | None:
    """The libLLVM the ``llvm_ad_*`` variants should use: ``$DRJIT_LIBLLVM_PATH`` when it names an
    existing file, else Debian's libLLVM 19 (:data:`LLVM_LIBRARY_DEFAULT`) when present, else None.
    (Older libLLVMs on this image make Dr.Jit abort the process, renderers.md.)"""
    p = os.environ.get("DRJIT_LIBLLVM_PATH")
    if p and os.path.isfile(p):
        return p
    return LLVM_LIBRARY_DEFAULT if os.path.isfile(LLVM_LIBRARY_DEFAULT) else None


@contextlib.contextmanager
def evaluated_mode():
    """Turn Dr.Jit's symbolic loops and calls off (restored on exit) so that the ``flakedb`` plugin
    receives evaluated arrays in JIT variants (it calls numpy).  Not needed in scalar variants."""
    import drjit as dr  # lazy: optional renderer (test extra), large import

    flags = (dr.JitFlag.SymbolicLoops, dr.JitFlag.SymbolicCalls)
    old = [dr.flag(f) for f in flags]
    try:
        for f in flags:
            dr.set_flag(f, False)
        yield
    finally:
        for f, v in zip(flags, old):
            dr.set_flag(f, v)


def _fresnel_unpolarised(c, eta):
    """Unpolarised Fresnel reflectance of light arriving from above (relative index eta = n_below /
    n_above > 0) at cosine ``c`` in (0, 1] (Born & Wolf §1.5.2; equals
    ``flakedb.optics.fresnel.fresnel_dielectric(c, eta).R``, checked by the tests)."""
    if eta == 1.0:
        return 0.0
    ct2 = 1.0 - (1.0 - c * c) / (eta * eta)
    if ct2 <= 0.0:
        return 1.0
    ct = math.sqrt(ct2)
    rs = (c - eta * ct) / (c + eta * ct)
    rp = (eta * c - ct) / (eta * c + ct)
    return 0.5 * (rs * rs + rp * rp)


# The plugin's compiled kernels (numba) around the reader's own compiled evaluation
# (``series_kernel``), sampling (``sample_kernel``) and Catmull-Rom weights: a scalar Mitsuba call
# costs one compiled call instead of dozens of small numpy operations.
_fresnel_1 = numba.njit(cache=True, nogil=True)(_fresnel_unpolarised)


@numba.njit(cache=True, nogil=True)
def _choice_1(nodes, cdf, mu_i, delta_eta, delta_on, glossy_on, w):
    """(F, p_delta) at mu_i > 0: the mirror term's reflectance and its sampling probability."""
    F = _fresnel_1(min(mu_i, 1.0), delta_eta) if (delta_eta > 0.0 and delta_on) else 0.0
    if not glossy_on:
        return F, 1.0 if F > 0.0 else 0.0
    n = nodes.size
    off = cr_weights_1(nodes, mu_i, w)
    A = 0.0
    if off != -n:
        for a in range(4):
            if w[a] != 0.0:
                A += w[a] * cdf[off + a, n - 1]
    A = max(2.0 * np.pi * A, 0.0)
    return F, (F / (F + A) if F + A > 0.0 else 0.0)


@numba.njit(cache=True, nogil=True)
def _coordinates_kernel(wi, wo, mu_i, mu_o, phi):
    """file_coordinates (module function) per point; NaN where not front-side reflection."""
    for p in range(wi.shape[0]):
        si = math.sqrt(wi[p, 0] * wi[p, 0] + wi[p, 1] * wi[p, 1])
        so = math.sqrt(wo[p, 0] * wo[p, 0] + wo[p, 1] * wo[p, 1])
        c = 1.0
        if si * so > 0.0:
            c = min(1.0, max(-1.0, (wi[p, 0] * wo[p, 0] + wi[p, 1] * wo[p, 1]) / (si * so)))
        ok = wi[p, 2] > 0.0 and wo[p, 2] > 0.0
        mu_i[p] = wi[p, 2] if ok else np.nan
        mu_o[p] = -wo[p, 2] if ok else np.nan
        phi[p] = np.pi - math.acos(c)


@numba.njit(cache=True, nogil=True)
def _eval_pdf_kernel(nodes, cdf, flat, start, order, cs, mix, sflat, sstart, wi, wo, delta_eta,
                     delta_on, glossy_on, out_val, out_pdf):
    """out_val (P, Cout) = max(0, f·|mu_o|) per channel (FourierBSDF.eval, clamp="all"),
    out_pdf (P,) = (1 - p_delta) · FourierBSDF.pdf; 0 outside front-side reflection."""
    P = wi.shape[0]
    n = nodes.size
    mu_i = np.empty(P)
    mu_o = np.empty(P)
    phi = np.empty(P)
    _coordinates_kernel(wi, wo, mu_i, mu_o, phi)
    if not glossy_on:
        mu_i[:] = np.nan
    vals = np.zeros((P, cs))
    a0 = np.zeros((P, cs))
    fs = np.zeros((P, 1))
    a0s = np.zeros((P, 1))
    series_kernel(nodes, flat, start, order, cs, mu_i, mu_o, phi, vals, a0)
    series_kernel(nodes, sflat, sstart, order, 1, mu_i, mu_o, phi, fs, a0s)
    w = np.zeros(4)
    for p in range(P):
        for j in range(mix.shape[1]):
            s = 0.0
            for c in range(cs):
                s += vals[p, c] * mix[c, j]
            out_val[p, j] = max(s, 0.0)
        out_pdf[p] = 0.0
        if not (mu_i[p] > 0.0) or a0s[p, 0] == 0.0:
            continue
        off = cr_weights_1(nodes, mu_i[p], w)
        norm = 0.0
        for a in range(4):
            if w[a] != 0.0:
                norm += w[a] * cdf[off + a, n - 1]
        if norm > 0.0:
            F, pd = _choice_1(nodes, cdf, mu_i[p], delta_eta, delta_on, True, w)
            out_pdf[p] = (1.0 - pd) * max(fs[p, 0], 0.0) / (2.0 * np.pi * norm)


@numba.njit(cache=True, nogil=True)
def _plugin_sample_kernel(nodes, cdf, a0s_nodes, sflat, sstart, flat, start, order, cs, mix, wi, s1, s2,
                          delta_eta, delta_on, glossy_on, out_wo, out_w, out_pdf, out_delta):
    """Choose the delta lobe with probability F / (F + A), else FourierBSDF.sample; out_w is
    the weight (value / pdf, >= 0), out_pdf the density (or the discrete probability of the
    delta lobe), out_delta 1 where the delta lobe was chosen.  0 where nothing is sampled."""
    P = wi.shape[0]
    mu_i = np.full(P, np.nan)
    pds = np.zeros(P)
    w = np.zeros(4)
    for p in range(P):
        out_delta[p] = 0
        out_pdf[p] = 0.0
        for j in range(out_w.shape[1]):
            out_w[p, j] = 0.0
        if not wi[p, 2] > 0.0:
            continue
        F, pd = _choice_1(nodes, cdf, wi[p, 2], delta_eta, delta_on, glossy_on, w)
        if s1[p] < pd:
            out_delta[p] = 1
            out_wo[p, 0] = -wi[p, 0]
            out_wo[p, 1] = -wi[p, 1]
            out_wo[p, 2] = wi[p, 2]
            out_pdf[p] = pd
            for j in range(out_w.shape[1]):
                out_w[p, j] = F / pd
        elif glossy_on and pd < 1.0:
            mu_i[p] = wi[p, 2]
            pds[p] = pd
    mu_o = np.zeros(P)
    phi = np.zeros(P)
    wt = np.zeros((P, mix.shape[1]))
    pdf = np.zeros(P)
    u1 = np.ascontiguousarray(s2[:, 0])
    u2 = np.ascontiguousarray(s2[:, 1])
    sample_kernel(nodes, cdf, a0s_nodes, sflat, sstart, flat, start, order, cs, mix, mu_i,
                   u1, u2, mu_o, phi, wt, pdf)
    for p in range(P):
        if not (mu_i[p] > 0.0):
            continue
        s = math.sqrt(max(0.0, 1.0 - mu_o[p] * mu_o[p]))
        ph = math.atan2(wi[p, 1], wi[p, 0]) + np.pi - phi[p]
        out_wo[p, 0] = s * math.cos(ph)
        out_wo[p, 1] = s * math.sin(ph)
        out_wo[p, 2] = -mu_o[p]
        if pdf[p] > 0.0 and mu_o[p] < 0.0:
            out_pdf[p] = (1.0 - pds[p]) * pdf[p]
            for j in range(out_w.shape[1]):
                out_w[p, j] = max(wt[p, j], 0.0) / (1.0 - pds[p])


class _Core:
    """The plugin's numpy side, independent of Mitsuba: methods take (P, 3) direction arrays.

    Evaluation and sampling run in the compiled kernels above, around the reader's own; the
    reader's arrays are taken from the :class:`flakedb.bsdf.FourierBSDF` here, in one place.
    """

    def __init__(self, path, variant: str, use_delta: bool = True):
        self.b = b = open_bsdf(path)
        self.delta = b.delta if use_delta else None
        delta_reflectance(self.delta, 1.0)                      # refuse unknown kinds early
        self.delta_eta = float(self.delta["eta"]) if self.delta is not None else 0.0
        self.spectral = "spectral" in variant
        wl = channel_wavelengths(b)
        chans = tuple(b.channels)
        if self.spectral:
            if wl is not None:
                order = np.argsort(wl)
                self.wavelengths, self.mix = wl[order], np.eye(b.n_channels)[:, order]
            elif len(chans) == 1 or (b.kind == "bsdf" and b.n_channels == 1):
                self.wavelengths, self.mix = None, np.eye(len(chans))[:, :1]
            else:
                raise ValueError(f"{path}: the {variant} variant renders mono or spectral files; this file "
                                 f"holds {', '.join(chans)}. Use an RGB variant (scalar_rgb, llvm_ad_rgb).")
        else:
            self.wavelengths = None
            try:                                   # R, G, B; mono; spectral -> linear sRGB (D65)
                self.mix = _rgb_matrix(b)
            except MeasuredExportError as e:
                raise ValueError(f"{e}. In {variant}, the plugin renders R, G, B, mono, or spectral files "
                                 f"on a 1-20 nm grid (converted to linear sRGB)") from None
        # the reader's arrays (FourierBSDF internals: sparse coefficients, sampling channel, mix)
        self._eval_args = (b.nodes, b.cdf, b._flat, b._start, b.order, b.n_channels, b._mix, b._sflat, b._sstart)
        self._sample_args = (b.nodes, b.cdf, b._a0s, b._sflat, b._sstart, b._flat, b._start, b.order,
                             b.n_channels, b._mix)
        self._cout = b._mix.shape[1]

    def _colour(self, vals, wavelengths):
        """(P, Cout) reader channels -> (P, 3) RGB, or (P, n_λ) at ``wavelengths`` (P, n_λ) [nm];
        clamped to >= 0 after the mix (a spectral -> sRGB map has negative entries)."""
        out = np.maximum(vals @ self.mix, 0.0)
        if wavelengths is None:
            return out
        if self.wavelengths is None:
            return np.repeat(out[:, :1], wavelengths.shape[1], axis=1)
        wl = self.wavelengths
        x = np.clip(wavelengths, wl[0], wl[-1])
        j = np.clip(np.searchsorted(wl, x, side="right") - 1, 0, wl.size - 2)
        t = (x - wl[j]) / (wl[j + 1] - wl[j])
        rows = np.arange(out.shape[0])[:, None]
        return (1 - t) * out[rows, j] + t * out[rows, j + 1]

    def eval_pdf(self, wi, wo, wavelengths=None, delta_on=True, glossy_on=True):
        """(f·cos θ_o (P, C), pdf (P,)) of the tabulated lobe, 0 outside front-side reflection."""
        wi = np.ascontiguousarray(wi, dtype=np.float64).reshape(-1, 3)
        wo = np.ascontiguousarray(wo, dtype=np.float64).reshape(-1, 3)
        vals = np.empty((wi.shape[0], self._cout))
        pdf = np.empty(wi.shape[0])
        _eval_pdf_kernel(*self._eval_args, wi, wo, self.delta_eta, bool(delta_on), bool(glossy_on), vals, pdf)
        return self._colour(vals, wavelengths), pdf

    def sample(self, wi, s1, s2, wavelengths=None, delta_on=True, glossy_on=True):
        """Sample wo: returns (wo (P, 3), weight (P, C), pdf (P,), is_delta (P,) bool, ok (P,) bool)."""
        wi = np.ascontiguousarray(wi, dtype=np.float64).reshape(-1, 3)
        P = wi.shape[0]
        wo = np.zeros((P, 3))
        weight = np.empty((P, self._cout))
        pdf = np.empty(P)
        is_delta = np.empty(P, dtype=np.uint8)
        s1 = np.ascontiguousarray(s1, dtype=np.float64).reshape(-1)
        s2 = np.ascontiguousarray(s2, dtype=np.float64).reshape(-1, 2)
        _plugin_sample_kernel(*self._sample_args, wi, s1, s2, self.delta_eta, bool(delta_on), bool(glossy_on),
                              wo, weight, pdf, is_delta)
        ok = (pdf > 0) & (wo[:, 2] > 0)
        weight[~ok] = 0.0
        return wo, self._colour(weight, wavelengths), pdf, is_delta.astype(bool), ok


def register(name: str = "flakedb"):
    """Register the ``flakedb`` BSDF plugin with Mitsuba 3 for the **current** variant (call after
    ``mi.set_variant``) and return its class.  Scene usage::

        {"type": "flakedb", "filename": "paint.bsdf"}          # optional: "delta": False

    Properties: ``filename`` (a ``.bsdf`` or flakedb ``.h5``), ``delta`` (bool, default True: add
    the file's smooth-coat mirror term back as a delta lobe).  See the module docstring.
    """
    import drjit as dr  # lazy: optional renderer (test extra), large import
    import mitsuba as mi  # lazy: optional renderer (test extra), large import

    variant = mi.variant()
    if variant is None:
        raise RuntimeError("call mi.set_variant(...) before flakedb.render.mitsuba.register()")
    jit = dr.is_jit_v(mi.Float)
    Flags = mi.BSDFFlags
    i_types = (int(Flags.GlossyReflection), int(Flags.DeltaReflection))

    # Conversions between Mitsuba values and numpy arrays of P points: one point in scalar
    # variants (kept cheap: each costs a few µs per call), a wavefront in JIT variants.
    if jit:
        def vec(v, n=None):
            cols = [np.asarray(c, dtype=np.float64).reshape(-1) for c in (v.x, v.y, v.z)]
            n = max([c.size for c in cols] + [n or 1])
            return np.stack([np.broadcast_to(c, (n,)) for c in cols], axis=-1)

        def arr(x, n, dtype=np.float64):
            return np.broadcast_to(np.asarray(x, dtype=dtype).reshape(-1), (n,)).copy()

        def out_spec(vals):
            return mi.Spectrum(*[mi.Float(np.ascontiguousarray(vals[:, k], dtype=np.float32))
                                 for k in range(vals.shape[1])])

        def out_float(x):
            return mi.Float(np.ascontiguousarray(x, dtype=np.float32))

        def out_vec(w):
            return mi.Vector3f(*[mi.Float(np.ascontiguousarray(w[:, k], dtype=np.float32)) for k in range(3)])
    else:
        def vec(v, n=None):
            return np.array([[v.x, v.y, v.z]])

        def arr(x, n, dtype=np.float64):
            return np.array([x], dtype=dtype)

        def out_spec(vals):
            return mi.Spectrum(*vals[0].tolist())

        def out_float(x):
            return float(x[0])

        def out_vec(w):
            return mi.Vector3f(*w[0].tolist())

    class FlakedbBSDF(mi.BSDF):
        """flakedb's Fourier BSDF file, evaluated and sampled by flakedb's reader."""

        def __init__(self, props):
            mi.BSDF.__init__(self, props)
            fname = props["filename"]
            path = str(mi.file_resolver().resolve(str(fname)))
            use_delta = bool(props["delta"]) if "delta" in props else True
            self.core = _Core(path, variant, use_delta)
            self.path = path
            glossy = Flags.GlossyReflection | Flags.FrontSide
            comps = []
            if self.core.delta is not None:
                comps.append(Flags.DeltaReflection | Flags.FrontSide)
            comps.append(glossy)
            self.i_delta = 0 if self.core.delta is not None else None
            self.i_glossy = len(comps) - 1
            self.m_components = comps
            flags = comps[0]
            for c in comps[1:]:
                flags = flags | c
            self.m_flags = flags

        # -- helpers ------------------------------------------------------------------------------
        def _enabled(self, ctx):
            d = self.i_delta is not None and ctx.is_enabled(Flags.DeltaReflection, self.i_delta)
            g = ctx.is_enabled(Flags.GlossyReflection, self.i_glossy)
            return bool(d), bool(g)

        def _check_mode(self):
            if jit and dr.flag(dr.JitFlag.SymbolicScope):
                raise RuntimeError(
                    "the flakedb BSDF plugin calls numpy, which cannot run while Dr.Jit records a "
                    f"symbolic kernel: in {variant}, render inside `with flakedb.render.mitsuba.evaluated_mode():`")

        def _wavelengths(self, si, n):
            if not self.core.spectral:
                return None
            w = si.wavelengths
            return np.stack([arr(w[k], n) for k in range(len(w))], axis=-1)

        # -- the BSDF interface -------------------------------------------------------------------
        def eval_pdf(self, ctx, si, wo, active=True):
            self._check_mode()
            d, g = self._enabled(ctx)
            wo_ = vec(wo)
            wi_ = vec(si.wi, wo_.shape[0])
            if wo_.shape[0] != wi_.shape[0]:
                wo_ = vec(wo, wi_.shape[0])
            n = wi_.shape[0]
            vals, pdf = self.core.eval_pdf(wi_, wo_, self._wavelengths(si, n), d, g)
            if active is not True:
                off = ~arr(active, n, bool)
                vals[off] = 0.0
                pdf[off] = 0.0
            return out_spec(vals), out_float(pdf)

        def eval(self, ctx, si, wo, active=True):
            return self.eval_pdf(ctx, si, wo, active)[0]

        def pdf(self, ctx, si, wo, active=True):
            return self.eval_pdf(ctx, si, wo, active)[1]

        def sample(self, ctx, si, sample1, sample2, active=True):
            self._check_mode()
            d, g = self._enabled(ctx)
            n = max(vec(si.wi).shape[0], np.size(np.asarray(sample1)) if jit else 1)
            wi = vec(si.wi, n)
            s2 = np.stack([arr(sample2.x, n), arr(sample2.y, n)], axis=-1)
            wo, weight, pdf, is_delta, ok = self.core.sample(wi, arr(sample1, n), s2, self._wavelengths(si, n), d, g)
            if active is not True:
                ok &= arr(active, n, bool)
            weight[~ok] = 0.0
            pdf[~ok] = 0.0
            if jit:
                bs = dr.zeros(mi.BSDFSample3f, n)
                bs.sampled_type = mi.UInt32(np.where(is_delta, i_types[1], i_types[0]).astype(np.uint32))
                bs.sampled_component = mi.UInt32(np.where(is_delta, self.i_delta or 0,
                                                          self.i_glossy).astype(np.uint32))
            else:
                bs = mi.BSDFSample3f()
                bs.sampled_type = i_types[1] if is_delta[0] else i_types[0]
                bs.sampled_component = (self.i_delta or 0) if is_delta[0] else self.i_glossy
            bs.wo = out_vec(wo)
            bs.pdf = out_float(pdf)
            bs.eta = 1.0
            return bs, out_spec(weight)

        def traverse(self, callback):
            pass

        def to_string(self):
            return f"FlakedbBSDF[filename={self.path!r}, delta={self.core.delta}]"

    mi.register_bsdf(name, lambda props: FlakedbBSDF(props))
    return FlakedbBSDF


# --------------------------------------------------------------------------------------------
# The render check (renderers.md, "A render test that proves something")
# --------------------------------------------------------------------------------------------
#: Radiance of the constant environment of the render check.
FURNACE_RADIANCE = 0.5
#: Half-width of the orthographic view, in sphere radii (the unit sphere fills 71 % of the frame).
FURNACE_HALF_WIDTH = 1.05


def furnace_sphere_scene(bsdf: dict, res: int = 64, max_depth: int = 3) -> dict:
    """A Mitsuba 3 scene dict: the unit sphere with material ``bsdf`` under a ``constant``
    environment of radiance :data:`FURNACE_RADIANCE`, seen by an orthographic camera along -z
    whose ``res`` x ``res`` film spans ``±FURNACE_HALF_WIDTH``, box reconstruction filter
    (so a pixel's expected value is the mean radiance over its square), ``path`` integrator.

    Pixel (column c, row r) covers ``x, y`` in ``FURNACE_HALF_WIDTH · [-1 + 2c/res, -1 + 2(c+1)/res]``
    (up to a mirror, irrelevant here): the sphere is radially symmetric.
    """
    import mitsuba as mi  # lazy: optional renderer (test extra), large import

    T = mi.ScalarTransform4f
    cam = T().look_at(origin=[0, 0, 4], target=[0, 0, 0], up=[0, 1, 0]) @ T().scale(
        [FURNACE_HALF_WIDTH, FURNACE_HALF_WIDTH, 1.0])
    return {
        "type": "scene",
        "integrator": {"type": "path", "max_depth": int(max_depth)},
        "sensor": {"type": "orthographic", "to_world": cam, "near_clip": 0.1, "far_clip": 10.0,
                   "film": {"type": "hdrfilm", "width": int(res), "height": int(res), "pixel_format": "rgb",
                            "rfilter": {"type": "box"}},
                   "sampler": {"type": "independent"}},
        "env": {"type": "constant", "radiance": {"type": "rgb", "value": FURNACE_RADIANCE}},
        "sphere": {"type": "sphere", "radius": 1.0, "bsdf": bsdf},
    }


def furnace_sphere_prediction(albedo, res: int = 64, supersample: int = 8):
    """Expected image of :func:`furnace_sphere_scene`: ``(image (res, res, C), mu (res, res), cover
    (res, res))``.

    ``albedo(mu)`` -> (..., C) is the directional albedo (reflection, plus any delta term) at view
    cosine ``mu``.  A point (x, y) of the image plane inside the unit disk sees the sphere at view
    cosine ``mu = sqrt(1 - x² - y²)`` and has expected radiance ``0.5 · albedo(mu)`` (a constant
    environment: the reflected radiance is the environment's times the albedo); outside it sees
    0.5.  Each pixel is the mean over ``supersample²`` points of its square.  ``mu`` is the view
    cosine at each pixel's centre (0 outside), ``cover`` the fraction of the pixel on the sphere.
    """
    L = FURNACE_RADIANCE
    h = FURNACE_HALF_WIDTH
    ss = int(supersample)
    edges = np.linspace(-h, h, res + 1)
    sub = (np.arange(ss) + 0.5) / ss
    x = (edges[:-1, None] + (edges[1] - edges[0]) * sub[None, :]).ravel()       # (res·ss,)
    r2 = x[None, :] ** 2 + x[:, None] ** 2
    inside = r2 < 1.0
    mu = np.sqrt(np.clip(1.0 - r2, 0.0, 1.0))
    a = np.asarray(albedo(mu[inside]), dtype=np.float64)
    C = a.shape[-1]
    val = np.full(r2.shape + (C,), L)
    val[inside] = L * a
    img = val.reshape(res, ss, res, ss, C).mean(axis=(1, 3))
    cover = inside.reshape(res, ss, res, ss).mean(axis=(1, 3))
    xc = 0.5 * (edges[:-1] + edges[1:])
    rc2 = xc[None, :] ** 2 + xc[:, None] ** 2
    return img, np.sqrt(np.clip(1.0 - rc2, 0.0, 1.0)), cover
