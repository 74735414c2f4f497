"""Export a Fourier file to Mitsuba 3's built-in ``measured`` BSDF (an RGL tensor file).

The plugin parameterises the half vector m by ``u = (sqrt(2 θ_m / π), (φ_m - φ_i + π) / 2π)``; its
value at a direction pair is a bilinear lookup, at u, of a grid with vertices at ``k / (n - 1)``,
linearly interpolated in θ_i between the ``theta_i`` slices.  The construction:

* isotropic: ``phi_i = [0]``; ``jacobian = 0`` (so ``ndf``/``sigma`` are unused, 2 x 2 ones);
* identity ``vndf`` (all ones): the grid is indexed directly by half-vector coordinates;
* ``rgb[0, t, c, j, k]`` (or ``spectra[0, t, λ, j, k]``) = scale · f · cos θ_o at θ_i = ``theta_i[t]``,
  ``u = (k/(n-1), j/(n-1))``: j runs over φ_m, k over θ_m (0 where wo or wi·m is below the horizon),
  from the file's evaluation clamped to >= 0;
* ``luminance[0, t, j, k]`` = Y(f cos θ_o) · J + floor with the plugin's Jacobian
  ``J = max(2π² u_x sin θ_m, 1e-6) · 4 (wi·m)``, so that the plugin's
  ``pdf = luminance density x vndf density / J`` is proportional to f cos θ_o; the floor
  (``floor`` x the slice's mean) keeps sampling alive wherever the bilinear value may be > 0.

Y is the luminance of linear sRGB; for a spectral export the sampling channel is the mean over
wavelengths.  ``scale`` (default 1) multiplies the stored values only: the coated route
(:mod:`flakedb.render.mitsuba.coated`) writes the table at scale 2 to blend it half-and-half with
the coat's mirror.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from flakedb import __version__
from flakedb.bsdf import open_bsdf
from flakedb.colour.gamut import desaturate_points
from flakedb.render.mitsuba.directions import (RGB_TO_Y, MeasuredExportError, channel_wavelengths,
                                               delta_reflectance, file_coordinates, reflectance_albedo,
                                               rgb_matrix)
from flakedb.render.mitsuba.tensor import write_tensor_file

#: Half-vector grid resolution n of the measured export (renderers.md: n = 96 gave 0.09 % eval error).
RES_DEFAULT = 96
#: Number of incident elevations theta_i in the measured export (over [0°, 90°], denser at grazing).
N_THETA_DEFAULT = 24
#: Largest half-vector grid and θ_i count of an export: the evaluation holds ~10 float64 arrays of
#: n_theta × res² entries (res 512, 24 θ_i: ≈ 0.5 GB); res 100000 would ask for 74.5 GiB.
RES_MAX = 512
N_THETA_MAX = 256
#: The luminance floor of the measured export, as a fraction of each slice's mean.
FLOOR_DEFAULT = 1e-3


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
    """Refuse a half-vector grid ``res`` or θ_i count ``n_theta`` outside the allowed ranges.

    >>> check_export_size(RES_DEFAULT, N_THETA_DEFAULT)
    >>> check_export_size(4, N_THETA_DEFAULT)
    Traceback (most recent call last):
    ...
    flakedb.render.mitsuba.directions.MeasuredExportError: res = 4 is outside the allowed range 8 ≤ res ≤ 512 half-vector vertices per axis (default 96)
    """
    if not (8 <= int(res) <= RES_MAX):
        raise MeasuredExportError(f"res = {res} is outside the allowed range 8 ≤ res ≤ {RES_MAX} half-vector "
                                  f"vertices per axis (default {RES_DEFAULT})")
    if not (4 <= int(n_theta) <= N_THETA_MAX):
        raise MeasuredExportError(f"n_theta = {n_theta} is outside the allowed range 4 ≤ n_theta ≤ {N_THETA_MAX} "
                                  f"incident elevations (default {N_THETA_DEFAULT})")


def measured_tensors(b, variant: str = "rgb", res: int = RES_DEFAULT, n_theta: int = N_THETA_DEFAULT,
                     floor: float = FLOOR_DEFAULT, description: str | None = None, scale: float = 1.0) -> dict:
    """The fields of a ``measured`` tensor file for the FourierBSDF ``b`` (module docstring).

    ``variant="rgb"``: an ``rgb`` field (R, G, B; a mono file repeated, a spectral file mapped to
    white-normalised linear sRGB).  ``variant="spectral"``: ``spectra`` + ``wavelengths`` [nm]
    from an HDF5 file with spectral channels; refused (MeasuredExportError) for RGB or mono files.
    ``res``: half-vector grid vertices per axis (n >= 8); ``n_theta``: θ_i slices over [0, π/2]
    (>= 4) at ``θ = π/2 (t + t(1-t)/2)`` for t uniform on [0, 1] (three times denser at grazing
    incidence than at normal incidence: the paint changes fastest with θ_i there).  ``floor``:
    the luminance floor as a fraction of each slice's mean.  ``scale``: a factor on the stored values
    (> 0; 2 for the coated route, module docstring).  Returns a dict of numpy arrays in the
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
        mix = rgb_matrix(b)
        lum_w = RGB_TO_Y
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
    vals = vals * float(scale)                            # stored values only; the sampling map is relative
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



def export_measured(src, out, variant: str = "rgb", res: int = RES_DEFAULT, n_theta: int = N_THETA_DEFAULT,
                    floor: float = FLOOR_DEFAULT, scale: float = 1.0, description: str | None = None) -> dict:
    """Export the Fourier file ``src`` (``.bsdf`` or ``.h5``) to a Mitsuba 3 ``measured`` file ``out``.

    Returns a JSON-able summary: ``out``, ``size`` [bytes], ``variant``, ``res``, ``n_theta``,
    ``channels``, and ``dropped``: what the format cannot hold, with the albedo it loses at a few
    incident angles: the mirror term (``delta_albedo``: F(θ_i; η)) and any transmission
    (``transmitted_albedo``: total minus reflected albedo of the table).
    """
    check_export_size(res, n_theta)
    b = open_bsdf(src)
    desc = description or (f"flakedb {__version__} export of {Path(src).name}: front-side reflection, "
            f"res {res}, {n_theta} theta_i; the mirror term delta={b.delta} is not included")
    if not (np.isfinite(scale) and scale > 0):
        raise MeasuredExportError(f"scale = {scale} must be a finite number > 0")
    fields = measured_tensors(b, variant, res, n_theta, floor, description=desc, scale=scale)
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

