"""What the BSDF readers accept (issue 13): the limits and the value checks shared by the
``.bsdf`` and HDF5 readers (:mod:`flakedb.bsdf.fourier_file`, :mod:`flakedb.bsdf.h5file`).

A reader checks header fields and array shapes against these limits *before* it allocates
anything, then every value it read (finite, of a sane magnitude), and refuses with a
:class:`~flakedb.bsdf.table.BSDFFileError` naming the file and the field.
"""

from __future__ import annotations

import math

import numpy as np

from flakedb.bsdf.table import BSDFFileError

#: Largest node count N of a file (n = 2048 quadrature nodes + 2 zero nodes; compose writes n ≤ 512).
MAX_NODES = 2050
#: Largest number of channels (an HDF5 file may hold every spectral band: 1 nm over 360-830 nm is 471).
MAX_CHANNELS = 1024
#: Largest Fourier order count L.
MAX_ORDERS = 4096
#: Largest coefficient data a reader loads [bytes] (2 GiB).
MAX_COEFF_BYTES = 2 * 1024 ** 3
#: Largest |value| of a coefficient or cdf entry: a Beckmann lobe of alpha 1e-3 peaks near 3e5,
#: so 1e12 is far above any physical table and far below float32's 3.4e38.
MAX_MAGNITUDE = 1e12


def check_count(path, field, value, lo, hi, what=""):
    """Refuse an integer header field outside ``lo ≤ value ≤ hi``.

    >>> check_count("paint.bsdf", "nChannels", 3, 1, 3)
    >>> check_count("paint.bsdf", "nChannels", 4, 1, 3, "1 or 3")
    Traceback (most recent call last):
    ...
    flakedb.bsdf.table.BSDFFileError: paint.bsdf: nChannels = 4 is outside the allowed range 1 ≤ nChannels ≤ 3 (1 or 3); the file is corrupt or not supported
    """
    if not (lo <= value <= hi):
        raise BSDFFileError(f"{path}: {field} = {value} is outside the allowed range {lo} ≤ {field} ≤ {hi}"
                            + (f" ({what})" if what else "") + "; the file is corrupt or not supported")


def check_bytes(path, field, nbytes):
    """Refuse an array of more than :data:`MAX_COEFF_BYTES` before it is allocated."""
    if nbytes > MAX_COEFF_BYTES:
        raise BSDFFileError(f"{path}: {field} declares {nbytes / 2**30:.1f} GiB; the limit is "
                            f"{MAX_COEFF_BYTES / 2**30:.0f} GiB (the file is corrupt or far larger than any "
                            f"paint needs)")


def check_values(path, field, a, lo=-MAX_MAGNITUDE, hi=MAX_MAGNITUDE):
    """Refuse NaN, ±inf and values outside ``[lo, hi]`` in ``a`` (naming the first bad index)."""
    a = np.asarray(a)
    bad = ~np.isfinite(a)
    if bad.any():
        k = tuple(int(i) for i in np.unravel_index(int(np.argmax(bad)), a.shape))
        raise BSDFFileError(f"{path}: {field}{list(k)} is {a[k]}; every value must be finite (the file is corrupt)")
    out = (a < lo) | (a > hi)
    if out.any():
        k = tuple(int(i) for i in np.unravel_index(int(np.argmax(out)), a.shape))
        raise BSDFFileError(f"{path}: {field}{list(k)} = {a[k]:.6g} is outside the allowed range "
                            f"{lo:g} ≤ value ≤ {hi:g} (the file is corrupt)")


def check_eta(path, eta):
    """The relative index must be finite and > 0."""
    if not (math.isfinite(eta) and eta > 0):
        raise BSDFFileError(f"{path}: eta = {eta} must be a finite relative index > 0 (the file is corrupt)")


def check_alpha(path, alpha):
    """The roughness fields must be finite and ≥ 0."""
    if not all(math.isfinite(a) and a >= 0 for a in alpha):
        raise BSDFFileError(f"{path}: alpha = {tuple(alpha)} must be two finite values ≥ 0 (the file is corrupt)")
