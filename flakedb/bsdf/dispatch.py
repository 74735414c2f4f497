"""Open a BSDF file of either kind, recognised by its magic bytes."""

from __future__ import annotations

from pathlib import Path

from flakedb.bsdf.evaluator import FourierBSDF
from flakedb.bsdf.fourier_file import MAGIC_BSDF, read_bsdf
from flakedb.bsdf.h5file import MAGIC_H5, read_h5
from flakedb.bsdf.table import BSDFFileError
from flakedb.safeio import read_head


def open_bsdf(path) -> FourierBSDF:
    """Open a ``.bsdf`` or flakedb HDF5 BSDF file, recognised by its magic bytes."""
    path = Path(path)
    try:
        magic = read_head(path, 8)   # a regular file only: a FIFO would block, a device never ends
    except FileNotFoundError:
        raise BSDFFileError(f"{path}: no such file") from None
    except OSError as e:
        raise BSDFFileError(f"{path}: cannot read ({e.strerror})") from None
    if magic[:7] == MAGIC_BSDF:
        return read_bsdf(path)
    if magic == MAGIC_H5:
        return read_h5(path)
    raise BSDFFileError(f"{path}: neither a Fourier .bsdf (SCATFUN) nor an HDF5 file (first bytes {magic!r})")
