"""The layerlab / Mitsuba 0.6 / pbrt-v3 Fourier ``.bsdf`` file: writer and reader (byte layout per
docs/bsdf-format.md)."""

from __future__ import annotations

import math
import os
import struct
import warnings
from pathlib import Path

import numpy as np

from flakedb.atomic import atomic_path
from flakedb.bsdf.evaluator import FourierBSDF
from flakedb.bsdf.limits import MAX_COEFF_BYTES, MAX_NODES, MAX_ORDERS, check_alpha, check_bytes, check_count, check_eta, check_values
from flakedb.bsdf.metadata import check_delta, check_known_metadata, format_metadata, parse_metadata
from flakedb.bsdf.spline import catmull_rom_cdf, insert_zero_nodes
from flakedb.bsdf.table import G_FROM_YRB, RGB_TO_Y, TRUNCATION_DEFAULT, BSDFFileError, BSDFTable
from flakedb.safeio import FileTooLargeError, read_limited

#: Identifier, version and flags of the .bsdf header (docs/bsdf-format.md, header table).
MAGIC_BSDF = b"SCATFUN"
_VERSION = 1
_FLAGS_BSDF = 1
_FLAGS_EXTRAPOLATED = 2
_HEADER = struct.Struct("<7sBIIIIIIIIIfff8x")  # 64 bytes, spec table
assert _HEADER.size == 64


# --------------------------------------------------------------------------------------------
# The .bsdf writer
# --------------------------------------------------------------------------------------------
def bsdf_file_size(n_nodes: int, n_coeffs: int, n_metadata_bytes: int, n_parameters: int = 0,
                   n_parameter_values: int = 0, n_bases: int = 1) -> int:
    """The spec's size formula [bytes]: 64 + 4 (N + nP + nPV + N²·nBases + 2N² + nCoeffs) + nMeta."""
    nn = n_nodes * n_nodes
    return 64 + 4 * (n_nodes + n_parameters + n_parameter_values + nn * n_bases + 2 * nn + n_coeffs) + n_metadata_bytes


def _truncation_orders(c: np.ndarray, truncation: float) -> np.ndarray:
    """K per entry: ``c`` (C, ..., L) -> int (...) (entries: incident rows × outgoing nodes).

    Per channel: the smallest j >= 1 with ``Σ_{k>=j} |a_k| <= truncation·|a_0|``; max over
    channels; entries whose coefficients are all exactly 0 get K = 0.  ``truncation = 0`` keeps
    everything up to the last non-zero coefficient: K = 1 + the last order ≥ 1 that is non-zero in any
    channel (1 when only a_0 is), found directly (a tail of |a_k| ≥ 0 is > 0 exactly when one of its terms is).
    """
    if truncation == 0:
        nz = np.any(c != 0, axis=0)                                  # (..., L): non-zero in some channel
        L = nz.shape[-1]
        last = np.where(nz[..., 1:].any(axis=-1), L - 1 - np.argmax(nz[..., :0:-1], axis=-1), 0) if L > 1 else 0
        return np.where(nz.any(axis=-1), 1 + last, 0)
    # rev[..., L − 1 − j] = tail[j] = Σ_{k>=j} |a_k|: the sums from the highest order down, accumulated in
    # place in one reversed copy (one array, no second pass of |a|)
    rev = np.abs(c[..., ::-1])
    np.cumsum(rev, axis=-1, out=rev)
    # tails never increase with j (sums of |a_k| ≥ 0, also in floating point), so the first j ≥ 1 with
    # tail[j] ≤ truncation·|a_0| (tail[L] = 0 always is) comes after exactly the j whose tail is above it
    k = 1 + np.count_nonzero(rev[..., :-1] > truncation * np.abs(c[..., :1]), axis=-1)
    k = k.max(axis=0)
    k[rev[..., -1].max(axis=0) == 0] = 0  # all coefficients 0 (a sum of |a_k| is 0 only then)
    return k


#: Table elements (channels × rows × outgoing nodes × orders) the writer handles at once: small enough
#: for the temporaries to stay in cache (measured at n = 200, 352 orders: 0.24 s at 4e6, 0.135 s at 2.5e5).
WRITE_CHUNK_ELEMS = 250_000


def _file_channels(coeffs_row: np.ndarray) -> np.ndarray:
    """(C, ...) table channels -> (C, ...) file channels: mono unchanged, R, G, B -> Y, R, B."""
    if coeffs_row.shape[0] == 1:
        return coeffs_row
    r, g, b = coeffs_row
    y = RGB_TO_Y[0] * r + RGB_TO_Y[1] * g + RGB_TO_Y[2] * b
    return np.stack([y, r, b])


def _file_coefficients(src: np.ndarray, K: np.ndarray, grey: bool) -> np.ndarray:
    """The file's coefficients of a chunk of entries, float32 in file order: ``src`` (C, rows, n_o, L) table
    coefficients, ``K`` (rows, n_o) the entries' orders; entry by entry (row-major), each file channel's
    K_e orders after the previous channel's.  Only the coefficients the file keeps are read (the median
    entry of the n = 200 benchmark keeps 12 of 350 orders): they are gathered, turned into the file's
    channels by :func:`_file_channels`' products (Y, R, B from R, G, B) and cast, the same values as
    converting every order.  ``grey``: every channel the same array (a broadcast): read once."""
    C, L = src.shape[0], src.shape[-1]
    k = K.ravel()
    total = int(k.sum())
    starts = np.repeat(np.cumsum(k) - k, k)                        # per kept coefficient: its entry's start
    order = np.arange(total) - starts                               # … and its order
    flat = np.repeat(np.arange(k.size) * L, k) + order              # in the chunk's (entries, L)
    chans = [np.take(src[c].reshape(-1), flat) for c in range(1 if grey else C)]
    if C == 3:
        r, g, b = chans * 3 if grey else chans
        chans = [RGB_TO_Y[0] * r + RGB_TO_Y[1] * g + RGB_TO_Y[2] * b, r, b]
    out = np.empty(total * C, dtype="<f4")
    pos = C * starts + order
    kk = np.repeat(k, k)
    for c, v in enumerate(chans):
        out[pos + c * kk] = v                                       # channel c's orders after channel c − 1's
    return out


def write_bsdf(path, table: BSDFTable, truncation: float = TRUNCATION_DEFAULT) -> dict:
    """Write ``table`` as a Fourier ``.bsdf`` file (spec layout), atomically.

    Parameters
    ----------
    path : str or Path
        Target file; written to a temporary file in the same directory, then ``os.replace``-d.
    table : BSDFTable
        C = 1 or 3 channels (R, G, B are stored as Y, R, B).
    truncation : float
        Relative tail bound of the per-entry truncation (spec rule, default 2e-3, evaluated on the
        table's channels).  ``0`` keeps every order up to the last non-zero coefficient.

    Returns a summary dict: ``n_nodes``, ``n_coeffs``, ``max_order``, ``n_channels``,
    ``metadata_bytes``, ``size`` [bytes].

    Layout: nodes with the two zero nodes inserted (N = n + 2), entries touching a zero node have
    K = 0, entries contiguous in e = o + i·N, channel c's coefficient k of entry e at
    ``offset + c·K_e + k``, cdf from the stored (float32) Y order-0 coefficients integrated over the
    float64 nodes.

    Examples
    --------
    A round trip of a grey Lambertian (albedo 0.5): the file evaluates f·|μ_o| = 0.5 |μ_o| / π at any
    pair of directions, to float32:

    >>> import tempfile
    >>> from flakedb.rt.basis.quadrature import gauss_radau_unit
    >>> x, _ = gauss_radau_unit(8)
    >>> refl = np.broadcast_to((0.5 * x[::-1] / np.pi)[None, None, :, None], (1, 8, 8, 1))
    >>> path = Path(tempfile.mkdtemp()) / "grey.bsdf"
    >>> _ = write_bsdf(path, BSDFTable(np.concatenate([-x[::-1], x]), reflection=refl, metadata={"recipe": "grey"}))
    >>> b = read_bsdf(path)
    >>> b.kind, b.metadata["recipe"], bool(np.allclose(b.eval(0.5, -0.3, 1.0), 0.5 * 0.3 / np.pi, rtol=1e-6, atol=0))
    ('bsdf', 'grey', True)
    """
    if not isinstance(table, BSDFTable):
        raise TypeError("write_bsdf expects a BSDFTable")
    C = table.n_channels
    if C not in (1, 3):
        raise ValueError(f"a .bsdf file holds 1 or 3 channels (mono or R, G, B), the table has {C}; "
                         f"write spectral results with write_h5 and convert to RGB first")
    if C == 3 and tuple(table.channels) != ("R", "G", "B"):
        raise ValueError(f"a 3-channel .bsdf stores linear R, G, B (as Y, R, B); the table's channels are "
                         f"{table.channels}. Convert to linear RGB first (or use write_h5).")
    truncation = float(truncation)
    if not (truncation >= 0 and math.isfinite(truncation)):
        raise ValueError(f"truncation must be a finite number >= 0, got {truncation!r}")
    n = table.n
    h = n // 2
    N = n + 2
    if table.mu[-1] != 1.0:
        warnings.warn(f"write_bsdf: the largest node is mu = {table.mu[-1]!r} < 1; every reader (layerlab, "
                      f"pbrt-v3, flakedb) returns 0 for |mu| beyond it, normal incidence included. Use a "
                      f"rule with a node at mu = 1 (Gauss-Radau / Gauss-Lobatto).", stacklevel=2)
    nodes32 = insert_zero_nodes(table.mu).astype(np.float32)
    if not np.all(np.diff(nodes32[:h + 1]) > 0) or not np.all(np.diff(nodes32[h + 1:]) > 0):
        raise ValueError("the nodes are not strictly ascending in float32; use fewer nodes")

    # the rows (incident nodes) and outgoing entries that can hold coefficients: all of them, or for a
    # reflection-only table (an opaque paint) the incident mu > 0 rows and outgoing mu < 0 entries
    # (its reflection quadrant, read without building the full coefficient array);
    # rows are handled in chunks of bounded memory, vectorised within a chunk
    if table.reflection_only:
        src, row0, o_sl = table.live_quadrant(), h, slice(0, h)   # src row r is table row h + r
    else:
        src, row0, o_sl = table.coeffs, 0, slice(0, n)
    src_o = slice(None) if table.reflection_only else o_sl
    L = table.n_orders
    step = max(1, WRITE_CHUNK_ELEMS // (C * (o_sl.stop - o_sl.start) * L))
    chunks = [slice(r0, min(r0 + step, src.shape[1])) for r0 in range(0, src.shape[1], step)]

    # Pass 1: orders K[i, o] and stored Y a_0 (float32) for the cdf, in table indices
    Kt = np.zeros((n, n), dtype=np.int64)
    a0t = np.zeros((n, n), dtype=np.float64)
    grey = C > 1 and src.strides[0] == 0  # one channel spread to all (a grey stack): truncate it once
    for r in chunks:
        c = src[:, r, src_o]                                         # (C, rows, n_o, L)
        k = _truncation_orders(c[:1] if grey else c, truncation)
        t = slice(row0 + r.start, row0 + r.stop)
        Kt[t, o_sl] = k
        a0t[t, o_sl] = np.where(k > 0, _file_channels(c[..., 0])[0].astype(np.float32), 0.0)
    fi = np.concatenate([np.arange(h), np.arange(h + 2, N)])        # table index -> file index
    K = np.zeros((N, N), dtype=np.int64)
    a0 = np.zeros((N, N), dtype=np.float64)
    K[np.ix_(fi, fi)] = Kt
    a0[np.ix_(fi, fi)] = a0t
    n_coeffs = int(K.sum() * C)
    if n_coeffs >= 2**32:
        raise ValueError(f"{n_coeffs} coefficients do not fit the file's u32 count; raise truncation or use fewer nodes")
    max_order = int(K.max())
    offsets = np.zeros((N * N, 2), dtype="<u4")
    sizes = (K * C).ravel()
    offsets[1:, 0] = np.cumsum(sizes)[:-1]
    offsets[:, 1] = K.ravel()
    # Integrate over the float64 nodes, as layerlab does (its cdf uses the solver's double nodes),
    # the stored float32 a_0 values: 2π·cdf[i][N-1] is then the table's albedo to float32 precision.
    cdf = catmull_rom_cdf(insert_zero_nodes(table.mu), a0).astype("<f4")    # (N_i, N_o)
    meta_bytes = format_metadata(table.metadata, table.delta).encode("utf-8")
    header = _HEADER.pack(MAGIC_BSDF, _VERSION, _FLAGS_BSDF, N, n_coeffs, max_order, C, 1,
                          len(meta_bytes), 0, 0, np.float32(table.eta), np.float32(table.alpha[0]),
                          np.float32(table.alpha[1]))
    size = bsdf_file_size(N, n_coeffs, len(meta_bytes))
    with atomic_path(path, suffix="") as tmp:
        with open(tmp, "wb") as fh:
            fh.write(header)
            fh.write(nodes32.astype("<f4").tobytes())
            fh.write(cdf.tobytes())
            fh.write(offsets.tobytes())
            for r in chunks:                                         # pass 2: coefficients, in file order
                fh.write(_file_coefficients(src[:, r, src_o], Kt[row0 + r.start:row0 + r.stop, o_sl], grey).tobytes())
            fh.write(meta_bytes)
        if os.path.getsize(tmp) != size:
            raise RuntimeError(f"internal error: wrote {os.path.getsize(tmp)} bytes, spec size is {size}")
    return {"n_nodes": N, "n_coeffs": n_coeffs, "max_order": max_order, "n_channels": C,
            "metadata_bytes": len(meta_bytes), "size": size}



# --------------------------------------------------------------------------------------------
# The .bsdf reader
# --------------------------------------------------------------------------------------------
def read_bsdf(path) -> FourierBSDF:
    """Read a Fourier ``.bsdf`` file (spec layout) into a :class:`FourierBSDF`.

    Checks the identifier, version 1, the BSDF flag (the harmonic-extrapolation flag is refused),
    nBases = 1, no parameters, the exact file size, ascending nodes, the two empty zero nodes and
    offsets inside the coefficient block (contiguity is not required, as in layerlab and pbrt-v3);
    raises :class:`BSDFFileError` naming what is wrong otherwise.  Coefficients are kept as read
    (:attr:`FourierBSDF.coeffs`, float32) and as float64 for evaluation.
    """
    path = Path(path)
    try:  # a regular file only (no FIFO / device), never more than the limit read
        raw = read_limited(path, MAX_COEFF_BYTES)
    except FileTooLargeError as e:
        check_bytes(path, "the file", e.size)
        raise
    except FileNotFoundError:
        raise BSDFFileError(f"{path}: no such file") from None
    except OSError as e:
        raise BSDFFileError(f"{path}: cannot read ({e.strerror})") from None
    if len(raw) < 64:
        raise BSDFFileError(f"{path}: truncated header ({len(raw)} bytes, a .bsdf header is 64)")
    (ident, version, flags, N, n_coeffs, max_order, C, n_bases, n_meta, n_par, n_parval,
     eta, alpha0, alpha1) = _HEADER.unpack_from(raw, 0)
    if ident != MAGIC_BSDF:
        raise BSDFFileError(f"{path}: not a Fourier .bsdf file (identifier {ident!r}, expected b'SCATFUN')")
    if version != _VERSION:
        raise BSDFFileError(f"{path}: unsupported .bsdf version {version} (only version 1 exists)")
    if flags & _FLAGS_EXTRAPOLATED or not flags & _FLAGS_BSDF:
        raise BSDFFileError(f"{path}: flags = {flags}; only flags = 1 (a BSDF without harmonic extrapolation) is supported")
    if n_bases != 1 or n_par != 0 or n_parval != 0:
        raise BSDFFileError(f"{path}: textured/parametrised files (nBases = {n_bases}, nParameters = {n_par}) are not supported")
    if C not in (1, 3):
        raise BSDFFileError(f"{path}: nChannels = {C}; a .bsdf holds 1 or 3 channels")
    if N < 4 or N % 2:
        raise BSDFFileError(f"{path}: nNodes = {N} must be even and >= 4 (n + 2 with the two zero nodes)")
    check_count(path, "nNodes", N, 4, MAX_NODES)
    check_count(path, "nMaxOrder", max_order, 0, MAX_ORDERS)
    check_eta(path, float(eta))
    check_alpha(path, (float(alpha0), float(alpha1)))
    expect = bsdf_file_size(N, n_coeffs, n_meta)
    if len(raw) != expect:
        raise BSDFFileError(f"{path}: file is {len(raw)} bytes, the header implies {expect}; it is truncated or corrupt")
    pos = 64
    nodes = np.frombuffer(raw, "<f4", N, pos).astype(np.float64)
    pos += 4 * N
    cdf = np.frombuffer(raw, "<f4", N * N, pos).reshape(N, N).astype(np.float64)
    pos += 4 * N * N
    offsets = np.frombuffer(raw, "<u4", 2 * N * N, pos).reshape(N * N, 2).copy()
    pos += 8 * N * N
    coeffs = np.frombuffer(raw, "<f4", n_coeffs, pos).copy()
    pos += 4 * n_coeffs
    meta_text = raw[pos:pos + n_meta].decode("utf-8", errors="replace")
    h = (N - 2) // 2
    if not (np.all(np.isfinite(nodes)) and np.all(np.diff(nodes[:h + 1]) > 0) and np.all(np.diff(nodes[h + 1:]) > 0)
            and nodes[0] >= -1 and nodes[-1] <= 1):
        raise BSDFFileError(f"{path}: nodes are not strictly ascending within [-1, 1] (apart from the two zero "
                            f"nodes); the file is corrupt")
    inner = np.r_[nodes[:h], nodes[h + 2:]]
    if not (inner[h - 1] < 0 < inner[h] and np.allclose(inner[:h], -inner[h:][::-1], rtol=0, atol=1e-12)):
        raise BSDFFileError(f"{path}: nodes are not one rule mirrored in both hemispheres (negative half = minus "
                            f"the positive half, no node at 0 apart from the two zero nodes); the file is corrupt")
    check_values(path, "cdf", cdf)
    check_values(path, "coefficients", coeffs)
    K = offsets[:, 1].astype(np.int64)
    start = offsets[:, 0].astype(np.int64)
    ends = start + K * C
    if K.max(initial=0) > max_order or ends.max(initial=0) > n_coeffs:
        raise BSDFFileError(f"{path}: offset table points outside the coefficient block (or exceeds nMaxOrder = {max_order})")
    h = (N - 2) // 2
    Kq = K.reshape(N, N)
    if nodes[h] != 0 or nodes[h + 1] != 0 or Kq[h].any() or Kq[h + 1].any() or Kq[:, h].any() or Kq[:, h + 1].any():
        raise BSDFFileError(f"{path}: the two middle nodes must be 0 and hold no coefficients (spec, 'nodes')")
    metadata, delta = parse_metadata(meta_text)
    try:
        if delta is not None:
            check_delta(delta)
        check_known_metadata(metadata)
    except ValueError as e:
        raise BSDFFileError(f"{path}: metadata {e} (the file is corrupt)") from None
    if C == 3:
        g = np.array(G_FROM_YRB)
        mix = np.array([[0.0, g[0], 0.0], [1.0, g[1], 0.0], [0.0, g[2], 1.0]])   # Y, R, B -> R, G, B
    else:
        mix = np.ones((1, 3))
    header = {"identifier": ident.decode("ascii"), "version": version, "flags": flags, "nNodes": N,
              "nCoeffs": n_coeffs, "nMaxOrder": max_order, "nChannels": C, "nBases": n_bases,
              "nMetadataBytes": n_meta, "nParameters": n_par, "nParameterValues": n_parval,
              "eta": eta, "alpha": (alpha0, alpha1)}
    return FourierBSDF(kind="bsdf", path=path, nodes=nodes, cdf=cdf, order=Kq, flat=coeffs,
                       start=start.reshape(N, N), n_channels=C, mix=mix, sample_weights=np.eye(C)[0],
                       channels=("R", "G", "B"), eta=eta, alpha=(alpha0, alpha1), delta=delta, metadata=metadata,
                       metadata_text=meta_text, offsets=offsets, coeffs=coeffs, header=header,
                       n_coeffs=n_coeffs)
