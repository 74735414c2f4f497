"""Reading a store version's arrays without importing zarr (docs/store.md "Reading").

zarr 3 takes 0.1–0.2 s to import (its asynchronous API, codec registry and buffer machinery), a fifth of
a whole ``flakedb compose`` from a store, which reads a few arrays of the layout flakedb's own writer
makes (:mod:`flakedb.store.write`): Zarr v3 arrays (the Zarr v3 core specification,
https://zarr-specs.readthedocs.io/en/latest/v3/core/index.html) on a ``regular`` chunk grid with the
``default`` chunk-key encoding (separator ``/``: ``c/i/j/…``), little-endian ``bytes`` and optionally
``zstd`` (decoded by numcodecs, zarr's own zstd, imported only when a chunk needs it).  Every chunk
is the full chunk shape (edge chunks padded, as the specification says); a chunk that is absent holds
the fill value.  An array with anything else in its metadata (other codecs, sharding, a transpose,
another key encoding) is opened with zarr instead (:class:`PlainGroup`), so every valid store reads.

Files are read with :func:`flakedb.store.fs.cat` (a regular file of bounded size on a local store).
"""

from __future__ import annotations

import posixpath

import numpy as np

from flakedb.store.errors import StoreIntegrityError
from flakedb.store.fs import cat, read_json

#: The data types the plain reader takes (Zarr v3 core data types of fixed size).
DTYPES = {"bool": "?", "int8": "i1", "int16": "<i2", "int32": "<i4", "int64": "<i8", "uint8": "u1",
          "uint16": "<u2", "uint32": "<u4", "uint64": "<u8", "float32": "<f4", "float64": "<f8"}
#: Zarr v3's JSON spellings of non-finite fill values.
SPECIAL_FILLS = {"NaN": np.nan, "Infinity": np.inf, "-Infinity": -np.inf}


class Unsupported(Exception):
    """An array whose metadata the plain reader does not take (the caller opens it with zarr)."""


def plain_layout(meta: dict) -> tuple:
    """(shape, chunks, dtype, fill, zstd) of a Zarr v3 array's metadata (its ``zarr.json``) if it is one the
    plain reader takes, else :class:`Unsupported` naming what is not.

    >>> meta = {"zarr_format": 3, "node_type": "array", "shape": [16, 11], "data_type": "float64",
    ...         "chunk_grid": {"name": "regular", "configuration": {"chunk_shape": [16, 8]}},
    ...         "chunk_key_encoding": {"name": "default", "configuration": {"separator": "/"}}, "fill_value": "NaN",
    ...         "codecs": [{"name": "bytes", "configuration": {"endian": "little"}}, {"name": "zstd"}]}
    >>> plain_layout(meta)
    ((16, 11), (16, 8), dtype('float64'), nan, True)
    >>> plain_layout(dict(meta, codecs=[{"name": "sharding_indexed"}]))
    Traceback (most recent call last):
    ...
    flakedb.store.plain.Unsupported: codecs ['sharding_indexed']
    """
    if meta.get("zarr_format") != 3 or meta.get("node_type") != "array":
        raise Unsupported("not a Zarr v3 array")
    grid = meta.get("chunk_grid", {})
    if grid.get("name") != "regular":
        raise Unsupported(f"chunk grid {grid.get('name')!r}")
    keys = meta.get("chunk_key_encoding", {})
    if keys.get("name") != "default" or keys.get("configuration", {}).get("separator", "/") != "/":
        raise Unsupported(f"chunk key encoding {keys!r}")
    if meta.get("data_type") not in DTYPES:
        raise Unsupported(f"data type {meta.get('data_type')!r}")
    codecs = [c.get("name") for c in meta.get("codecs", [])]
    if codecs not in (["bytes"], ["bytes", "zstd"]):
        raise Unsupported(f"codecs {codecs}")
    dtype = np.dtype(DTYPES[meta["data_type"]])
    if dtype.itemsize > 1 and meta["codecs"][0].get("configuration", {}).get("endian", "little") != "little":
        raise Unsupported("big-endian bytes")
    fill = meta.get("fill_value", 0)
    fill = SPECIAL_FILLS.get(fill, fill) if isinstance(fill, str) else fill
    if isinstance(fill, str):
        raise Unsupported(f"fill value {fill!r}")
    shape = tuple(int(s) for s in meta["shape"])
    chunks = tuple(int(c) for c in grid["configuration"]["chunk_shape"])
    if len(chunks) != len(shape) or any(c < 1 for c in chunks):
        raise Unsupported(f"chunk shape {chunks} for shape {shape}")
    return shape, chunks, dtype, fill, codecs[-1] == "zstd"


def _slices(sel, shape) -> list:
    """Normalise an index of basic slices (``:``, ``a:b``, ``...``; step 1) to one (start, stop) per axis."""
    sel = sel if isinstance(sel, tuple) else (sel,)
    if any(s is Ellipsis for s in sel):
        i = sel.index(Ellipsis)
        sel = sel[:i] + (slice(None),) * (len(shape) - len(sel) + 1) + sel[i + 1:]
    sel = sel + (slice(None),) * (len(shape) - len(sel))
    if len(sel) != len(shape) or not all(isinstance(s, slice) for s in sel):
        raise IndexError(f"the plain reader takes slices only, not {sel!r}")
    out = []
    for s, n in zip(sel, shape):
        a, b, step = s.indices(n)
        if step != 1:
            raise IndexError(f"the plain reader takes step 1 only, not {s!r}")
        out.append((a, max(a, b)))
    return out


class PlainArray:
    """A read-only Zarr v3 array of :func:`plain_layout`'s kind: ``shape``, ``chunks``, ``dtype``, ``attrs``
    and basic slicing (``a[:]``, ``a[:, 0:16]``), as :class:`zarr.Array` has them."""

    def __init__(self, fs, path, meta):
        self.fs, self.path = fs, path
        self.shape, self.chunks, self.dtype, self.fill_value, self._zstd = plain_layout(meta)
        self.attrs = dict(meta.get("attributes", {}))
        #: ``check(path, data, error)``, called with each chunk's file bytes (None: no file; ``error``: the OSError
        #: that kept it from being read) before they are decoded, or None: the reader's integrity check on the
        #: bytes it decodes, one read per chunk (:meth:`flakedb.store.read.StoreVersion.flake_factors`); it raises
        #: to refuse them
        self.check = None

    def _chunk(self, idx) -> np.ndarray | None:
        key = posixpath.join(self.path, "c", *map(str, idx))
        data = error = None
        try:
            data = cat(self.fs, key)
        except FileNotFoundError:
            pass
        except OSError as exc:
            if self.check is None:
                raise
            error = exc
        if self.check is not None:
            self.check(key, data, error)
        if data is None:
            return None
        if self._zstd:
            from numcodecs.zstd import (
                Zstd,  # lazy: only a zstd-compressed chunk needs it (zarr's own decoder)
            )

            data = Zstd().decode(data)
        size = int(np.prod(self.chunks)) * self.dtype.itemsize
        if len(data) != size:
            raise StoreIntegrityError(f"{key}: {len(data)} bytes decoded where a chunk of shape {self.chunks} "
                                      f"holds {size}; the store is corrupt (delete the version and rebuild)")
        return np.frombuffer(data, self.dtype).reshape(self.chunks)

    def __getitem__(self, sel) -> np.ndarray:
        box = _slices(sel, self.shape)
        out = np.full([b - a for a, b in box], self.fill_value, self.dtype)
        ranges = [range(a // c, -(-b // c)) for (a, b), c in zip(box, self.chunks)]
        for idx in np.ndindex(*[len(r) for r in ranges]) if out.size else ():
            cidx = [r[i] for r, i in zip(ranges, idx)]
            chunk = self._chunk(cidx)
            if chunk is None:
                continue
            src, dst = [], []
            for (a, b), c, k in zip(box, self.chunks, cidx):
                lo, hi = max(a, k * c), min(b, (k + 1) * c)
                src.append(slice(lo - k * c, hi - k * c))
                dst.append(slice(lo - a, hi - a))
            out[tuple(dst)] = chunk[tuple(src)]
        return out


class PlainGroup:
    """A read-only Zarr v3 group: ``attrs`` and ``group[path]`` → :class:`PlainGroup` or an array
    (:class:`PlainArray`, or a :class:`zarr.Array` for an array the plain reader does not take)."""

    def __init__(self, fs, root, url, path=""):
        self.fs, self.root, self.url, self.path = fs, root, url, path
        self.attrs = dict(read_json(fs, posixpath.join(root, path, "zarr.json")).get("attributes", {}))

    def __getitem__(self, key):
        path = posixpath.join(self.path, key) if self.path else key
        try:
            meta = read_json(self.fs, posixpath.join(self.root, path, "zarr.json"))
        except FileNotFoundError:
            raise KeyError(path) from None
        if meta.get("node_type") == "group":
            return PlainGroup(self.fs, self.root, self.url, path)
        try:
            return PlainArray(self.fs, posixpath.join(self.root, path), meta)
        except Unsupported:
            import zarr  # lazy: only an array of a layout flakedb does not write needs zarr itself

            return zarr.open_array(self.url, path=path, mode="r")
