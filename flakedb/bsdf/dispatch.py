"""File kinds, recognised by their first bytes (not by the extension), in one registry.

:data:`FILE_KINDS` maps a kind to its magic bytes and what it is; :func:`file_kind` names the kind
of a file, :func:`open_bsdf` opens the two Fourier kinds.  ``flakedb info``, ``flakedb render`` and
the exporters all go through here (the Mitsuba tensor, the MaterialX document and the glTF / USD scenes
are read by their own modules).  A new kind is one entry here and one describer in ``flakedb info``'s
route table (:data:`flakedb.cli.info.INFO_ROUTES`, which a test holds to this registry).
"""

from __future__ import annotations

from pathlib import Path

from flakedb.bsdf.evaluator import FourierBSDF
from flakedb.bsdf.fourier_file import MAGIC_BSDF, read_bsdf
from flakedb.bsdf.h5file import MAGIC_H5, read_h5
from flakedb.bsdf.table import BSDFFileError
from flakedb.safeio import read_head

#: kind -> (magic bytes at offset 0, description).  Checked in order; the first match wins.
FILE_KINDS = {
    "bsdf": (MAGIC_BSDF, "Fourier .bsdf (layerlab / Mitsuba 0.6 / pbrt-v3)"),
    "h5": (MAGIC_H5, "flakedb HDF5 BSDF"),
    "tensor": (b"tensor_file\0", "Mitsuba 3 `measured` tensor file (RGL)"),
    "materialx": (b"<?xml", "MaterialX document (flakedb export-openpbr)"),
    "glb": (b"glTF", "glTF 2.0 binary (flakedb export-openpbr)"),
    "usda": (b"#usda", "USD text layer (flakedb export-openpbr)"),
    "gltf": (b"{", "glTF 2.0 JSON (flakedb export-openpbr)"),
}
#: Kinds :func:`open_bsdf` opens (Fourier tables).
FOURIER_KINDS = {"bsdf": read_bsdf, "h5": read_h5}
_HEAD = max(len(m) for m, _ in FILE_KINDS.values())


def _head(path) -> bytes:
    try:
        return read_head(path, _HEAD)   # a regular file only: a FIFO would block, a device never ends
    except FileNotFoundError:
        raise BSDFFileError(f"{path}: no such file") from None
    except IsADirectoryError:
        raise BSDFFileError(f"{path}: is a directory, not a file") from None
    except OSError as e:
        raise BSDFFileError(f"{path}: cannot read ({e.strerror})") from None


def file_kind(path) -> str:
    """The kind (a key of :data:`FILE_KINDS`) of the file at ``path``, by its first bytes; raises
    BSDFFileError naming the file when it is unreadable or of no known kind."""
    head = _head(path)
    for kind, (magic, _) in FILE_KINDS.items():
        if head[:len(magic)] == magic:
            return kind
    known = "; ".join(f"{d} ({m!r})" for m, d in FILE_KINDS.values())
    raise BSDFFileError(f"{path}: not a file kind flakedb knows (first bytes {head[:8]!r}); it knows: {known}")


def open_bsdf(path) -> FourierBSDF:
    """Open a ``.bsdf`` or flakedb HDF5 BSDF file, recognised by its magic bytes.

    A file that is neither kind is refused in one line naming its first bytes:

    >>> import tempfile
    >>> path = Path(tempfile.mkdtemp()) / "notes.bsdf"
    >>> _ = path.write_bytes(b"hello")
    >>> open_bsdf(path)
    Traceback (most recent call last):
    ...
    flakedb.bsdf.table.BSDFFileError: .../notes.bsdf: neither a Fourier .bsdf (SCATFUN) nor an HDF5 file (first bytes b'hello')
    """
    path = Path(path)
    head = _head(path)
    for kind, reader in FOURIER_KINDS.items():
        magic = FILE_KINDS[kind][0]
        if head[:len(magic)] == magic:
            return reader(path)
    raise BSDFFileError(f"{path}: neither a Fourier .bsdf (SCATFUN) nor an HDF5 file (first bytes {head[:8]!r})")
