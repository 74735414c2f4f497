"""flakedb's full-precision HDF5 BSDF file (float64, every order, any channels): writer and reader."""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np

from flakedb import __version__
from flakedb.atomic import atomic_path
from flakedb.bsdf.evaluator import FourierBSDF, table_evaluator
from flakedb.bsdf.limits import (
    MAX_CHANNELS,
    MAX_NODES,
    MAX_ORDERS,
    check_alpha,
    check_bytes,
    check_count,
    check_eta,
    check_values,
)
from flakedb.bsdf.table import BSDFFileError, BSDFTable

#: An HDF5 file's first eight bytes.
MAGIC_H5 = b"\x89HDF\r\n\x1a\n"
H5_FORMAT = "flakedb-fourier-bsdf"
H5_FORMAT_VERSION = 1


# --------------------------------------------------------------------------------------------
# HDF5
# --------------------------------------------------------------------------------------------
def write_h5(path, table: BSDFTable, extra_metadata: dict | None = None) -> dict:
    """Write the full-precision table (float64, every order, all channels) to HDF5, atomically.

    ``extra_metadata`` (e.g. ``{"recipe_text": …, "store_version": …}``) is merged over
    ``table.metadata``; ``flakedb_version`` is always recorded.  Layout in the package docstring (:mod:`flakedb.bsdf`).
    Returns ``{"size": bytes, "n_channels": C, "max_order": L}``.
    """
    if not isinstance(table, BSDFTable):
        raise TypeError("write_h5 expects a BSDFTable")
    md = dict(table.metadata)
    md.update(extra_metadata or {})
    md_json = json.dumps(md, sort_keys=True, allow_nan=False, default=_json_default)
    C, n, L = table.n_channels, table.n, table.n_orders
    with atomic_path(path) as tmp:
        import h5py  # lazy: h5py takes 50 ms to import; only the .h5 file needs it

        with h5py.File(tmp, "w") as f:
            f.attrs["format"] = H5_FORMAT
            f.attrs["format_version"] = H5_FORMAT_VERSION
            f.attrs["flakedb_version"] = __version__
            f.attrs["eta"] = float(table.eta)
            f.attrs["alpha"] = np.asarray(table.alpha, dtype=np.float64)
            f.attrs["channels"] = json.dumps(list(table.channels))
            f.attrs["delta"] = json.dumps(table.delta)
            f.attrs["metadata"] = md_json
            f.create_dataset("mu", data=table.mu)
            if table.reflection_only:  # the reflection quadrant written alone; the rest is the fill value 0
                d = f.create_dataset("coeffs", shape=(C, n, n, L), dtype="f8", chunks=(1, 1, n, L), shuffle=True,
                                     compression="gzip", compression_opts=1, fillvalue=0.0)
                d[:, n // 2:, : n // 2, :] = table.live_quadrant()
            else:
                f.create_dataset("coeffs", data=table.coeffs, chunks=(1, 1, n, L), shuffle=True,
                                 compression="gzip", compression_opts=1)
            f.create_dataset("albedo", data=table.albedo())
        size = os.path.getsize(tmp)
    return {"size": size, "n_channels": C, "max_order": L}


def _json_default(o):
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, np.generic):
        return o.item()
    raise TypeError(f"metadata value {o!r} is not JSON-able")


def _check_shapes(path, mu, coeffs):
    """Refuse datasets whose declared shapes are not (n,) and (C, n, n, L) within the limits of
    :mod:`flakedb.bsdf.limits` (a 57 KB file may declare a 512 GiB array)."""
    if mu.ndim != 1 or coeffs.ndim != 4:
        raise BSDFFileError(f"{path}: datasets mu {mu.shape} and coeffs {coeffs.shape} must be 1-D (n,) and "
                            f"4-D (C, n, n, L); the file is corrupt")
    C, n_i, n_o, L = coeffs.shape
    check_count(path, "mu length n", mu.shape[0], 2, MAX_NODES)
    if (n_i, n_o) != (mu.shape[0], mu.shape[0]):
        raise BSDFFileError(f"{path}: coeffs has shape {coeffs.shape} but mu has {mu.shape[0]} nodes; expected "
                            f"(C, {mu.shape[0]}, {mu.shape[0]}, L) (the file is corrupt)")
    check_count(path, "channels C", C, 1, MAX_CHANNELS)
    check_count(path, "orders L", L, 1, MAX_ORDERS)
    check_bytes(path, "coeffs", C * n_i * n_o * L * 8)
    for name, d in (("mu", mu), ("coeffs", coeffs)):
        if d.dtype.kind != "f":
            raise BSDFFileError(f"{path}: dataset {name} has dtype {d.dtype}; expected floating point "
                                f"(the file is corrupt)")


def read_h5(path) -> FourierBSDF:
    """Read a file written by :func:`write_h5` into a :class:`FourierBSDF` (float64, channels as
    stored; the zero nodes inserted as in the ``.bsdf``; cdf computed from the sampling channel).

    The HDF5 file gives back the table bit for bit (float64, every channel):

    >>> import tempfile
    >>> from pathlib import Path
    >>> from flakedb.rt.quadrature import gauss_radau_unit
    >>> x, _ = gauss_radau_unit(8)
    >>> rho = np.array([0.8, 0.5, 0.2])
    >>> refl = np.broadcast_to((rho[:, None] * x[None, ::-1] / np.pi)[:, None, :, None], (3, 8, 8, 1))
    >>> table = BSDFTable(np.concatenate([-x[::-1], x]), reflection=refl)
    >>> path = Path(tempfile.mkdtemp()) / "lambert.h5"
    >>> _ = write_h5(path, table)
    >>> back = read_h5(path).to_table()
    >>> bool(np.array_equal(back.coeffs, table.coeffs)), back.channels
    (True, ('R', 'G', 'B'))
    """
    path = Path(path)
    if not path.exists():
        raise BSDFFileError(f"{path}: no such file")
    try:
        import h5py  # lazy: h5py takes 50 ms to import; only the .h5 file needs it

        with h5py.File(path, "r") as f:
            fmt = f.attrs.get("format")
            if fmt != H5_FORMAT:
                raise BSDFFileError(f"{path}: not a flakedb BSDF HDF5 file (format attribute {fmt!r})")
            ver = int(f.attrs["format_version"])
            if ver > H5_FORMAT_VERSION:
                raise BSDFFileError(f"{path}: format_version {ver} is newer than this flakedb reads "
                                    f"({H5_FORMAT_VERSION}); upgrade flakedb")
            _check_shapes(path, f["mu"], f["coeffs"])   # before anything is allocated
            mu = f["mu"][...]
            coeffs = f["coeffs"][...]
            eta = float(f.attrs["eta"])
            alpha = tuple(float(a) for a in f.attrs["alpha"])
            channels = tuple(json.loads(f.attrs["channels"]))
            delta = json.loads(f.attrs["delta"])
            stored = json.loads(f.attrs["metadata"])
            written_by = str(f.attrs["flakedb_version"])
    except BSDFFileError:
        raise
    except (OSError, KeyError, ValueError, TypeError, AttributeError) as e:
        raise BSDFFileError(f"{path}: corrupt or incomplete flakedb HDF5 file ({e})") from None
    check_values(path, "mu", mu, -1.0, 1.0)
    check_values(path, "coeffs", coeffs)
    check_eta(path, eta)
    check_alpha(path, alpha)
    try:
        table = BSDFTable(mu=mu, coeffs=coeffs, eta=eta, alpha=alpha, delta=delta, metadata=stored,
                          channels=channels)
    except ValueError as e:
        raise BSDFFileError(f"{path}: {e} (the file is corrupt)") from None
    # what FourierBSDF.metadata shows: the stored metadata plus who wrote the file, in which format
    return table_evaluator(table, path=path,
                       metadata={**stored, "flakedb_version": written_by, "h5_format_version": ver})
