"""flakedb's full-precision HDF5 BSDF file (float64, every order, any channels): writer and reader."""

from __future__ import annotations

import contextlib
import faulthandler
import json
import os
import signal
import sys
import time
import zlib
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
from flakedb.bsdf.metadata import check_delta, check_known_metadata
from flakedb.bsdf.table import BSDFFileError, BSDFTable
from flakedb.process import available_threads
from flakedb.rt.common.jobs import thread_pool
from flakedb.safeio import check_regular

#: An HDF5 file's first eight bytes.
MAGIC_H5 = b"\x89HDF\r\n\x1a\n"
H5_FORMAT = "flakedb-fourier-bsdf"
H5_FORMAT_VERSION = 1


# --------------------------------------------------------------------------------------------
# HDF5
# --------------------------------------------------------------------------------------------
def preload_h5py() -> None:
    """Import h5py now, for a caller that will write an ``.h5`` later and has a thread to spare (compose runs
    this in its worker beside the solve: the import, 17–23 ms, then is off the write's path)."""
    import h5py  # lazy: h5py takes 17-50 ms to import; only the .h5 file needs it  # noqa: F401


def write_h5(path, table: BSDFTable, extra_metadata: dict | None = None, encoded=None) -> dict:
    """Write the full-precision table (float64, every order, all channels) to HDF5, atomically.

    ``extra_metadata`` (e.g. ``{"recipe_text": …, "store_version": …}``) is merged over
    ``table.metadata``; ``flakedb_version`` is always recorded.  Layout in the package docstring (:mod:`flakedb.bsdf`).
    ``encoded``: :func:`encode_chunks_early` of this table (its chunks compressed while the caller did other
    work), or None; the file is the same either way.
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
            # chunks of half a row (channel, incident node, one hemisphere of outgoing nodes): a reflection
            # quadrant fills its chunks exactly, and the rest of the dataset is never allocated (fill value 0)
            data = table.live_quadrant() if table.reflection_only else table.coeffs
            filters = h5_filters(data)
            d = f.create_dataset("coeffs", shape=(C, n, n, L), dtype="f8", chunks=(1, 1, max(n // 2, 1), L),
                                 fillvalue=0.0, **filters)
            row0 = n // 2 if table.reflection_only else 0  # the reflection quadrant written alone
            if filters and n % 2 == 0:  # compressed by every core, chunk by chunk (write_chunks_deflated)
                write_chunks_deflated(d, data, row0, encoded if encoded is not None and encoded.table is table else None)
            elif table.reflection_only:
                d[:, n // 2:, : n // 2, :] = data
            else:
                d[...] = data
            f.create_dataset("albedo", data=table.albedo())
        size = os.path.getsize(tmp)
    return {"size": size, "n_channels": C, "max_order": L}


#: Compress the coefficients (shuffle + gzip 1) only when at least this fraction of them is exactly 0.
#: Fourier coefficients in float64 do not compress (the 3-species paint's reflection quadrant, 3.5 MB,
#: 96 % non-zero: gzip kept 91 % of it and took 45 ms, 5x the raw write); runs of zeros do (orders beyond
#: a pair's own count, a transmission block that is all zero).
COMPRESS_ZERO_FRACTION = 0.5


def h5_filters(coeffs: np.ndarray) -> dict:
    """The ``create_dataset`` filter keywords for ``coeffs``: shuffle + gzip(1) when at least
    :data:`COMPRESS_ZERO_FRACTION` of its entries are exactly 0, else none (module docstring).

    >>> h5_filters(np.zeros(10)), h5_filters(np.ones(10))
    ({'shuffle': True, 'compression': 'gzip', 'compression_opts': 1}, {})
    """
    c = np.asarray(coeffs)
    c = c[tuple(slice(0, 1) if st == 0 else slice(None) for st in c.strides)]  # a broadcast axis counted once
    zeros = c.size - np.count_nonzero(c)
    if c.size and zeros >= COMPRESS_ZERO_FRACTION * c.size:
        return {"shuffle": True, "compression": "gzip", "compression_opts": 1}
    return {}


#: Chunks encoded per batch by :func:`write_chunks_deflated` (its memory: a batch's compressed bytes).
H5_CHUNK_BATCH = 256


#: zlib's strategy for the coefficient chunks: run-length matches only (``Z_RLE``).  The stream is ordinary
#: deflate (HDF5's filter and any inflater read it); after the shuffle a chunk is byte planes whose runs are the
#: zero tails of orders past each pair's own count, which the full match search (``Z_DEFAULT_STRATEGY``) finds no
#: better, in less time for a few per cent more bytes (docs/compose-overhead.md).
DEFLATE_STRATEGY = zlib.Z_RLE


def shuffle_deflate(chunk) -> bytes:
    """One chunk through the filters :func:`h5_filters` declares, as HDF5 applies them on write: the shuffle
    filter (the k-th byte of every float64 element together: the (N, 8) bytes transposed) then deflate at
    level 1 (zlib's stream, which HDF5's deflate filter reads; strategy :data:`DEFLATE_STRATEGY`).  zlib releases
    the interpreter, so chunks encode on several threads at once.

    >>> import zlib
    >>> x = np.array([1.0, 2.0])
    >>> shuffled = zlib.decompress(shuffle_deflate(x))
    >>> shuffled[:2] == bytes([x.view(np.uint8)[0], x.view(np.uint8)[8]]), len(shuffled)
    (True, 16)
    """
    b = np.ascontiguousarray(np.asarray(chunk, dtype="<f8")).view(np.uint8).reshape(-1, 8)
    z = zlib.compressobj(1, zlib.DEFLATED, zlib.MAX_WBITS, 8, DEFLATE_STRATEGY)
    return z.compress(np.ascontiguousarray(b.T)) + z.flush()


def _chunk_keys(data, h):
    """``(same, keys)`` of :func:`write_chunks_deflated`: whether the channels are one broadcast array (encoded
    once), and the (channel, row, column) of every chunk to encode, in the order they are written."""
    C, a, b, _ = data.shape
    same = C > 1 and data.strides[0] == 0
    return same, [(c, i, j) for c in range(1 if same else C) for i in range(a) for j in range(0, b, h)]


def _encode(data, key, h):
    return shuffle_deflate(data[key[0], key[1], key[2]:key[2] + h])


#: :func:`encode_chunks_early` encodes a table whose stored coefficients hold at most this many bytes (every
#: chunk's compressed bytes are then held until the write: n = 200 grey RGB, 28 MB raw, 7 MB deflated); a larger
#: one is encoded at the write, in batches of :data:`H5_CHUNK_BATCH`.
EARLY_ENCODE_BYTES = 64e6


class EarlyChunks:
    """The coefficient chunks of ``table`` being shuffled and deflated on the ``flakedb-h5`` threads
    (:func:`encode_chunks_early`): ``futures[k]`` the bytes of ``keys[k]``."""

    def __init__(self, table, keys, futures):
        self.table, self.keys, self.futures = table, keys, futures

    def cancel(self):
        for f in self.futures:
            f.cancel()


def encode_chunks_early(table: BSDFTable, threads=None):
    """Start encoding the chunks :func:`write_h5` writes for ``table`` (:func:`shuffle_deflate` on
    :func:`flakedb.process.available_threads` threads, or ``threads``) and return an :class:`EarlyChunks`
    to pass to :func:`write_h5`, so that the deflate runs beside whatever the caller does before the write (compose:
    the file channels' gamut mapping, the report's texture and the ``.bsdf``).  None when :func:`write_h5` would
    not deflate them (:func:`h5_filters`, odd n) or they hold more than :data:`EARLY_ENCODE_BYTES`.

    >>> t = BSDFTable(np.array([-1.0, -0.5, 0.5, 1.0]), reflection=np.zeros((1, 2, 2, 3)), eta=1.0)
    >>> early = encode_chunks_early(t)   # a reflection quadrant of 2 rows, one chunk (2 nodes × 3 orders) each
    >>> early.keys, [f.result() == shuffle_deflate(np.zeros((2, 3))) for f in early.futures]
    ([(0, 0, 0), (0, 1, 0)], [True, True])
    """
    data = table.live_quadrant() if table.reflection_only else table.coeffs
    C, a, b, L = data.shape
    n = table.n
    stored = data.nbytes if data.strides[0] != 0 else data[:1].nbytes
    if n % 2 or not h5_filters(data) or stored > EARLY_ENCODE_BYTES:
        return None
    h = max(n // 2, 1)
    _, keys = _chunk_keys(data, h)
    pool = thread_pool(threads or available_threads(), "flakedb-h5")
    return EarlyChunks(table, keys, [pool.submit(_encode, data, key, h) for key in keys])


def write_chunks_deflated(dataset, data, row0=0, early=None) -> None:
    """``dataset[:, row0:row0 + a, :b, :] = data`` (data (C, a, b, L)) for a dataset of chunks (1, 1, h, L) with
    shuffle + deflate(1) (:func:`h5_filters`), b a multiple of h: every chunk encoded by
    :func:`shuffle_deflate` on the process's threads (``flakedb-h5``, :func:`flakedb.process.available_threads`) and written as it is stored
    (``write_direct_chunk``), in batches of :data:`H5_CHUNK_BATCH`.  h5py's own write ran the filters on one core:
    the cadmium yellow / rough 0.1 coat table at n = 200 (41 bands, 1.15 GB, 72 % zeros) took most of the
    compose's write.  The file is the same HDF5 (same filters declared; h5py and any HDF5 reader decode it).
    Channels that are one array (a broadcast channel axis, stride 0: a grey paint solved once) are encoded once
    and their bytes written for every channel (the encoding is a function of the chunk's values).  ``early``:
    :func:`encode_chunks_early` of the same data with the same chunks, whose bytes are written as they are."""
    C = data.shape[0]
    h = dataset.chunks[2]
    same, keys = _chunk_keys(data, h)
    if early is not None and early.keys == keys:
        batches = [(keys, (f.result() for f in early.futures))]
    else:
        pool = thread_pool(available_threads(), "flakedb-h5")
        batches = ((keys[k0:k0 + H5_CHUNK_BATCH], pool.map(lambda key: _encode(data, key, h), keys[k0:k0 + H5_CHUNK_BATCH]))
                   for k0 in range(0, len(keys), H5_CHUNK_BATCH))
    for batch, encoded in batches:
        for (c, i, j), buf in zip(batch, encoded):
            for cc in (range(C) if same else (c,)):
                dataset.id.write_direct_chunk((cc, row0 + i, j, 0), buf)


def _inflate_unshuffle(buf, shape):
    """The float64 array ``shape`` of one chunk stored by :func:`shuffle_deflate` (or HDF5's shuffle + deflate
    filters), or None when ``buf`` does not inflate to exactly its size (corrupt, or a bomb: inflating stops
    at the chunk's size)."""
    size = int(np.prod(shape)) * 8
    z = zlib.decompressobj()
    try:
        raw = z.decompress(buf, size)
    except zlib.error:
        return None
    if len(raw) != size or not z.eof or z.unconsumed_tail:
        return None
    return np.ascontiguousarray(np.frombuffer(raw, np.uint8).reshape(8, -1).T).view("<f8").reshape(shape)


def _chunk_offsets(dataset) -> list:
    """The offsets of every chunk HDF5 holds for ``dataset``, from its chunk index in one pass (``chunk_iter``:
    4 100 chunks in 0.02 s, where one ``get_chunk_info`` call per chunk took 1.3 s)."""
    ident = dataset.id
    if hasattr(ident, "chunk_iter"):
        out = []
        ident.chunk_iter(lambda info: out.append(tuple(info.chunk_offset)))
        return out
    return [tuple(ident.get_chunk_info(k).chunk_offset) for k in range(ident.get_num_chunks())]


def _stored_in_reflection_quadrant(dataset, offsets=None) -> bool:
    """Whether every chunk HDF5 holds for a (C, n, n, L) dataset of chunks (1, 1, n/2, L) lies in the reflection
    quadrant [:, n/2:, :n/2] (:func:`write_h5` of a reflection-only table: the rest never written, 0): then the
    reader allocates that quadrant only, a quarter of the declared array (a rough coat's 41-band table at n = 200
    declared 4.3 GiB, over :func:`flakedb.bsdf.limits.check_bytes`' 2 GiB, for 1.15 GB of coefficients)."""
    shape, chunks = dataset.shape, dataset.chunks
    if (len(shape) != 4 or chunks is None or shape[1] % 2 or tuple(chunks[:3]) != (1, 1, shape[1] // 2)
            or dataset.fillvalue != 0):
        return False
    h = shape[1] // 2
    offsets = _chunk_offsets(dataset) if offsets is None else offsets
    return len(offsets) > 0 and all(o[1] >= h and o[2] == 0 for o in offsets)


def read_chunks_deflated(dataset, decode=True, threads=None, quadrant=False, offsets=None):
    """The values of a coefficient dataset of :func:`write_h5`'s layout (float64 little-endian, chunks
    (1, 1, h, L) that tile it, fill value 0, the shuffle then the deflate filter and no other), read as stored
    (``read_direct_chunk`` through HDF5's chunk index) and inflated and unshuffled on ``threads`` threads (None:
    :func:`flakedb.process.available_threads`, the process's ``flakedb-h5`` pool; 1: in the caller), chunks never written left 0.  h5py
    inflated on one core: the cadmium yellow / rough 0.1 coat file at n = 200 (1.15 GB of coefficients).
    None when the dataset is not that layout, a chunk's filters were skipped or its place is not on the grid:
    the caller then lets HDF5 read it.  A chunk that does not inflate to exactly its size raises ValueError
    (corrupt; inflating stops at the size, so a deflate bomb allocates nothing more).  ``decode`` False reads
    the stored bytes only and returns an empty array (the crash probe's pass); ``quadrant``
    (:func:`_stored_in_reflection_quadrant`) returns the reflection quadrant (C, n/2, n/2, L) alone; ``offsets``:
    :func:`_chunk_offsets` of the dataset, if known."""
    import h5py  # lazy: h5py takes 17-50 ms to import; only the .h5 file needs it

    shape, chunks = dataset.shape, dataset.chunks
    if (len(shape) != 4 or chunks is None or dataset.dtype.str != "<f8" or chunks[:2] != (1, 1)
            or chunks[3] != shape[3] or shape[2] % chunks[2] or dataset.fillvalue != 0):
        return None
    plist = dataset.id.get_create_plist()
    if [plist.get_filter(i)[0] for i in range(plist.get_nfilters())] != [h5py.h5z.FILTER_SHUFFLE,
                                                                         h5py.h5z.FILTER_DEFLATE]:
        return None
    C, n_i, n_o, L = shape
    h = chunks[2]
    offsets = _chunk_offsets(dataset) if offsets is None else offsets
    count = len(offsets)
    if count > C * n_i * (n_o // h):
        return None
    row0 = n_i // 2 if quadrant else 0
    out = np.zeros((C, n_i - row0, n_o - row0, L) if quadrant else shape) if decode else np.zeros((0,))
    pool = None if threads == 1 else thread_pool(threads or available_threads(), "flakedb-h5")
    for k0 in range(0, count, H5_CHUNK_BATCH):
        places, bufs = [], []
        for k in range(k0, min(count, k0 + H5_CHUNK_BATCH)):
            c, i, j, l0 = offsets[k]
            if l0 != 0 or j % h or not (0 <= c < C and row0 <= i < n_i and 0 <= j < n_o - row0):
                return None
            mask, buf = dataset.id.read_direct_chunk((c, i, j, 0))
            if mask != 0:  # a filter skipped for this chunk
                return None
            places.append((c, i, j))
            bufs.append(buf)
        if not decode:
            continue
        decoded = map(_inflate_unshuffle, bufs, [(h, L)] * len(bufs)) if pool is None else pool.map(
            _inflate_unshuffle, bufs, [(h, L)] * len(bufs))
        for (c, i, j), block in zip(places, decoded):
            if block is None:
                raise ValueError(f"coefficient chunk ({c}, {i}, {j}, 0) does not inflate to its {h * L * 8} bytes")
            out[c, i - row0, j:j + h] = block
    return out


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
    for name, d in (("mu", mu), ("coeffs", coeffs)):
        if d.dtype.kind != "f":
            raise BSDFFileError(f"{path}: dataset {name} has dtype {d.dtype}; expected floating point "
                                f"(the file is corrupt)")


def _own_dataset(f, name, path):
    """Dataset ``name`` of the open file ``f``, refused unless it is a hard link to a dataset whose data
    lives in this file: an external link, HDF5 external storage (raw data in another file, e.g.
    /dev/zero or a text file) or a virtual dataset would read a file the user never named."""
    import h5py  # lazy: only the .h5 file needs it

    link = f.get(name, getlink=True)
    if link is None:
        raise BSDFFileError(f"{path}: no dataset {name!r} (corrupt or incomplete flakedb HDF5 file)")
    if not isinstance(link, h5py.HardLink):
        raise BSDFFileError(f"{path}: dataset {name!r} is a {type(link).__name__} to another location or file; "
                            f"flakedb reads only data stored in the named file")
    d = f[name]
    if not isinstance(d, h5py.Dataset):
        raise BSDFFileError(f"{path}: {name!r} is not a dataset (corrupt or incomplete flakedb HDF5 file)")
    if d.external:
        raise BSDFFileError(f"{path}: dataset {name!r} keeps its data in external file(s) (HDF5 external "
                            f"storage); flakedb reads only data stored in the named file")
    if d.is_virtual:
        raise BSDFFileError(f"{path}: dataset {name!r} is a virtual dataset (its data lives in other files); "
                            f"flakedb reads only data stored in the named file")
    return d


def _attr(f, key, kind, path, required=True):
    """Attribute ``key`` as ``kind`` (str, int or float), refused with its name when missing or of the wrong type."""
    if key not in f.attrs:
        if not required:
            return None
        raise BSDFFileError(f"{path}: attribute {key!r} is missing (corrupt or incomplete flakedb HDF5 file)")
    v = f.attrs[key]
    if isinstance(v, bytes):
        v = v.decode("utf-8", "replace")
    if kind is str:
        if not isinstance(v, str):
            if required:
                raise BSDFFileError(f"{path}: attribute {key!r} must be text, got {type(v).__name__}")
            return repr(v)
        return v
    arr = np.asarray(v)
    if arr.size != 1 or arr.dtype.kind not in ("i", "u", "f") or (kind is int and arr.dtype.kind == "f"):
        raise BSDFFileError(f"{path}: attribute {key!r} must be one {kind.__name__}, got {_short_repr(v)} "
                            f"(the file is corrupt)")
    return kind(arr.reshape(-1)[0])


def _json_attr(f, key, kinds, path):
    """Attribute ``key`` holding JSON text of one of the ``kinds``."""
    text = _attr(f, key, str, path)
    if len(text) > MAX_METADATA_CHARS:
        raise BSDFFileError(f"{path}: attribute {key!r} is {len(text):,} characters; the limit is "
                            f"{MAX_METADATA_CHARS:,}")
    try:
        v = json.loads(text)
    except (ValueError, RecursionError):
        raise BSDFFileError(f"{path}: attribute {key!r} is not valid JSON (the file is corrupt)") from None
    if not isinstance(v, kinds):
        want = " or ".join(k.__name__ for k in (kinds if isinstance(kinds, tuple) else (kinds,)))
        raise BSDFFileError(f"{path}: attribute {key!r} must be a JSON {want}, got {type(v).__name__} "
                            f"(the file is corrupt)")
    return v


def _short_repr(v):
    r = repr(v)
    return r if len(r) <= 40 else r[:37] + "..."


#: Largest JSON attribute (metadata with the recipe text and solver info is ~100 kB).
MAX_METADATA_CHARS = 50_000_000


#: Reading a .h5 first in a forked child (Linux): a corrupt file can crash the HDF5 C library (measured:
#: random byte changes to a 30 kB flakedb .h5 segfaulted h5py), and a crash must be a one-line error, not
#: the end of the process.  Set FLAKEDB_H5_PROBE=0 to read in-process only.
H5_PROBE = os.environ.get("FLAKEDB_H5_PROBE", "1").strip() != "0"
#: The child's time limit [s]: a base plus 20 s per GB of file (a 30 kB file reads in 5 ms); HDF5 loops
#: forever on some corrupt files, so past it the child is killed and the file refused.
H5_PROBE_BASE_S = 10.0


def _crash_probe(path, size):
    """Read ``path`` in a forked child first; BSDFFileError when the child dies of a signal (module
    constant :data:`H5_PROBE`).  The child's own exceptions are ignored here: the real read raises them."""
    if not (H5_PROBE and sys.platform.startswith("linux") and hasattr(os, "fork")):
        return
    pid = os.fork()
    if pid == 0:   # the child: read, exit; never returns into the caller's code
        code = 0
        try:
            faulthandler.disable()   # a crash here is the parent's one-line error, not a dump on the terminal
            devnull = os.open(os.devnull, os.O_WRONLY)
            os.dup2(devnull, 2)
            _read_fields(path, probe=True)
        except BaseException:
            code = 3
        os._exit(code)
    start = time.monotonic()
    deadline = start + H5_PROBE_BASE_S + 20.0 * size / 1e9
    pause = 0.0005
    while True:
        done, status = os.waitpid(pid, os.WNOHANG)
        if done:
            break
        if time.monotonic() > deadline:   # HDF5 loops on some corrupt files: the parent would too
            with contextlib.suppress(OSError):
                os.kill(pid, signal.SIGKILL)
            os.waitpid(pid, 0)
            raise BSDFFileError(f"{path}: the HDF5 library did not finish reading it in {deadline - start:.0f} s "
                                f"(it loops on some corrupt files); the file is corrupt")
        time.sleep(pause)
        pause = min(2 * pause, 0.05)
    if os.WIFSIGNALED(status) and os.WTERMSIG(status) not in (signal.SIGTERM, signal.SIGINT, signal.SIGHUP):
        raise BSDFFileError(f"{path}: the HDF5 library crashed reading it ({signal.Signals(os.WTERMSIG(status)).name}); "
                            f"the file is corrupt")


def _read_fields(path, probe=False):
    """Everything :func:`read_h5` takes from the file, checked as it is read (no external data).  ``probe``
    (:func:`_crash_probe`'s child): the coefficient chunks of flakedb's own layout are read through HDF5's index
    but not inflated (the parent inflates them in Python, :func:`read_chunks_deflated`)."""
    try:
        import h5py  # lazy: h5py takes 50 ms to import; only the .h5 file needs it

        with h5py.File(path, "r") as f:
            fmt = _attr(f, "format", str, path, required=False)
            if fmt != H5_FORMAT:
                raise BSDFFileError(f"{path}: not a flakedb BSDF HDF5 file (format attribute {fmt!r})")
            ver = _attr(f, "format_version", int, path)
            if ver > H5_FORMAT_VERSION:
                raise BSDFFileError(f"{path}: format_version {ver} is newer than this flakedb reads "
                                    f"({H5_FORMAT_VERSION}); upgrade flakedb")
            mu_d, coeffs_d = (_own_dataset(f, name, path) for name in ("mu", "coeffs"))
            _check_shapes(path, mu_d, coeffs_d)   # before anything is allocated
            mu = mu_d[...]
            C, n, _, L = coeffs_d.shape
            # a reflection-only table is read as its quadrant (what write_h5 stored); anything else whole
            offsets = _chunk_offsets(coeffs_d) if coeffs_d.chunks is not None else []
            quadrant = _stored_in_reflection_quadrant(coeffs_d, offsets)
            check_bytes(path, "coeffs", C * n * n * L * 8 // (4 if quadrant else 1))   # before allocating
            coeffs = read_chunks_deflated(coeffs_d, decode=not probe, threads=1 if probe else None,
                                          quadrant=quadrant, offsets=offsets)
            if coeffs is None:  # another layout: HDF5's own filters (in the probe too)
                coeffs = coeffs_d[:, n // 2:, : n // 2, :] if quadrant else coeffs_d[...]
            eta = _attr(f, "eta", float, path)
            alpha = np.asarray(f.attrs["alpha"], dtype=float).reshape(-1) if "alpha" in f.attrs else None
            if alpha is None or alpha.size != 2:
                raise BSDFFileError(f"{path}: attribute alpha must hold two numbers (the file is corrupt)")
            alpha = tuple(float(a) for a in alpha)
            channels = _json_attr(f, "channels", list, path)
            if not channels or not all(isinstance(c, str) and len(c) <= 64 for c in channels):
                raise BSDFFileError(f"{path}: attribute channels must be a JSON list of channel names (the file "
                                    f"is corrupt)")
            channels = tuple(channels)
            delta = _json_attr(f, "delta", (dict, type(None)), path)
            stored = _json_attr(f, "metadata", dict, path)
            written_by = _attr(f, "flakedb_version", str, path)
    except BSDFFileError:
        raise
    except (OSError, KeyError, ValueError, TypeError, AttributeError, RuntimeError) as e:
        raise BSDFFileError(f"{path}: corrupt or incomplete flakedb HDF5 file ({e})") from None
    return ver, mu, coeffs, eta, alpha, channels, delta, stored, written_by, quadrant


def read_h5(path) -> FourierBSDF:
    """Read a file written by :func:`write_h5` into a :class:`FourierBSDF` (float64, channels as
    stored; the zero nodes inserted as in the ``.bsdf``; cdf computed from the sampling channel).

    The HDF5 file gives back the table bit for bit (float64, every channel):

    >>> import tempfile
    >>> from pathlib import Path
    >>> from flakedb.rt.basis.quadrature import gauss_radau_unit
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
    try:
        st = check_regular(path)   # a FIFO would block HDF5's open, a device never ends
    except FileNotFoundError:
        raise BSDFFileError(f"{path}: no such file") from None
    except OSError as e:
        raise BSDFFileError(f"{path}: cannot read ({e.strerror})") from None
    check_bytes(path, "the file", st.st_size)
    _crash_probe(path, st.st_size)
    ver, mu, coeffs, eta, alpha, channels, delta, stored, written_by, quadrant = _read_fields(path)
    check_values(path, "mu", mu, -1.0, 1.0)
    check_values(path, "coeffs", coeffs)
    check_eta(path, eta)
    check_alpha(path, alpha)
    if delta is not None:
        try:
            check_delta(delta)
        except ValueError as e:
            raise BSDFFileError(f"{path}: attribute delta: {e} (the file is corrupt)") from None
    try:
        check_known_metadata(stored)
    except ValueError as e:
        raise BSDFFileError(f"{path}: metadata {e} (the file is corrupt)") from None
    try:
        table = BSDFTable(mu=mu, eta=eta, alpha=alpha, delta=delta, metadata=stored, channels=channels,
                          **({"reflection": coeffs} if quadrant else {"coeffs": coeffs}))
    except ValueError as e:
        raise BSDFFileError(f"{path}: {e} (the file is corrupt)") from None
    # what FourierBSDF.metadata shows: the stored metadata plus who wrote the file, in which format
    return table_evaluator(table, path=path,
                       metadata={**stored, "flakedb_version": written_by, "h5_format_version": ver})
