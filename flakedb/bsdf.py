"""Fourier BSDF files: the layerlab / Mitsuba 0.6 / pbrt-v3 ``.bsdf`` file and flakedb's HDF5 file.

Writer, reader, evaluation and importance sampling of the tabulated BSDF described in
``shared/design/bsdf-format.md`` (called "the spec" below).  Conventions are those of
:mod:`flakedb.conventions` and of the file, which agree: ``mu > 0`` travels down into the paint,
reflection seen from above is ``mu_i > 0, mu_o < 0``, ``phi_d = 0`` is mirror reflection and
``phi_d = π`` retro-reflection.  Every quantity stored and returned here is the cosine series of
**f · |mu_o|** (BSDF in 1/sr times the outgoing cosine), ``value(phi_d) = Σ_k a_k cos(k phi_d)``.

What this module provides
-------------------------
* :class:`BSDFTable` -- what the solver hands over: nodes ``mu`` (n,), coefficients
  ``coeffs[c, i, o, l]`` (C, n, n, L) of f·|mu_o|, ``eta``, ``alpha``, ``delta``, ``metadata``.
* :func:`write_bsdf` / :func:`read_bsdf` -- the 64-byte-header Fourier file (float32, channels
  stored as Y, R, B), byte layout exactly per the spec.
* :func:`write_h5` / :func:`read_h5` -- the full-precision result (float64, every order, any number
  of channels, e.g. spectral), same evaluation code.
* :func:`open_bsdf` -- dispatch on the file's magic bytes.
* :class:`FourierBSDF` -- ``eval``, ``pdf``, ``sample``, ``series``, ``albedo``,
  ``albedo_nodes``, ``to_table``.

Evaluation (spec, "Evaluation")
-------------------------------
Catmull-Rom weights over the file nodes (including the two zero nodes) for ``mu_i`` and ``mu_o``
(:func:`catmull_rom_weights`), the 4 x 4 neighbouring coefficient vectors blended with the product
weights, and the cosine series summed.  Arguments outside ``[nodes[0], nodes[-1]]`` (or NaN) give 0,
as in layerlab and pbrt-v3 -- so a table must have a node at mu = 1 (the writer warns otherwise).
Two implementations give the same numbers: a compiled (numba) loop over points that touches only
each entry's K_e coefficients (default, ~1 µs per point on the reference car paint), and a plain
vectorised numpy reference (``method="numpy"``) that gathers the 16 coefficient vectors padded to
the chunk's largest order, in chunks of bounded memory.  Coefficients are held in float64 in the
file's sparse layout (entry-contiguous, channel-major), so one compiled kernel serves both files.

Clamping (``clamp=`` of :meth:`FourierBSDF.eval`): ``"layerlab"`` (default) reproduces layerlab's
``BSDFStorage::eval`` -- the reference reader of the spec: the result is 0 where the blended
order-0 coefficient of the sampling channel (Y) is exactly 0 (no data), a single-channel result is
clamped to >= 0, and three-channel results are *not* clamped (layerlab's ``result.clamp()``
discards its return value, so small negative ringing values survive; the reference data confirms
this).  ``"all"`` clamps every channel to >= 0 (pbrt-v3).  ``"none"`` returns the raw series.

Colour
------
A three-channel ``.bsdf`` stores Y, R, B with ``Y = 0.212671 R + 0.715160 G + 0.072169 B`` per
coefficient; ``eval`` returns R, G, B rebuilt with the spec's ``G = 1.39829 Y - 0.100913 B -
0.297375 R`` (what every renderer does), a mono file returns its channel repeated three times (as
layerlab's reader does).  :meth:`FourierBSDF.to_table` inverts the writer's formula exactly,
``G = (Y - 0.212671 R - 0.072169 B) / 0.715160``, so read -> write reproduces the file's floats.
An HDF5 file returns its channels as stored (C of them).

Importance sampling (pbrt-v3 ``SampleCatmullRom2D`` + ``SampleFourier``)
-------------------------------------------------------------------------
The *sampling channel* is Y for a ``.bsdf`` (file channel 0), the luminance of R, G, B for an RGB
HDF5 file, the single channel of a mono file and the channel mean of any other HDF5 file.  Its
order-0 coefficients ``a0[i, o]`` and their Catmull-Rom prefix integrals ``cdf[i, o]`` (spec,
"cdf") define the density of ``mu_o``; ``phi_d`` then follows the Fourier series of that channel,
inverted with Newton-bisection on ``[0, π]`` and mirrored to ``[π, 2π)`` for ``u2 >= 1/2``.  The
resulting density per steradian of ``(mu_o, phi_d)`` is

    pdf(mu_i, mu_o, phi_d) = max(0, f_s·|mu_o|) / (2π · cdf(mu_i)[N-1])          (spec, "pdf")

with ``cdf(mu_i)`` the cdf rows blended with the ``mu_i`` Catmull-Rom weights; it is exact where
the tabulated series is non-negative.  ``sample`` returns ``weight = f·|mu_o| / pdf`` per output
channel, so ``E[weight] = albedo(mu_i)`` (reflectance + transmittance).

``.bsdf`` metadata text (the trailing ``nMetadataBytes``)
--------------------------------------------------------
UTF-8, ``key=value`` lines separated by ``\\n``, no terminator.  Keys match
``[A-Za-z_][A-Za-z0-9_.-]*``.  A value is written raw when it is a one-line string that does not
parse as JSON (``delta=fresnel``, ``recipe=silver metallic``), otherwise as one-line JSON
(``delta_eta=1.5``, ``n_nodes=100``, ``wavelength_nm=[450, 550, 650]``, ``tag="1.5"``); the reader
tries JSON first and falls back to the raw string, so every JSON-able value round-trips.  Lines
that are not ``key=value`` (e.g. layerlab's free-text description) are collected, in order, into
the key ``"text"``; a ``"text"`` entry is written back raw after the key=value lines when none of
its lines looks like ``key=...``.  The smooth coat's first-surface mirror term (spec, "Carrying a
smooth clear coat's mirror reflection") is written first as ``delta=<kind>`` followed by
``delta_<field>=<value>`` for its other fields, i.e. ``delta=fresnel`` and ``delta_eta=1.5`` for
``{"kind": "fresnel", "eta": 1.5}``; the reader puts it back into :attr:`FourierBSDF.delta`.
The writer adds nothing else: the caller puts the recipe name and flakedb version in ``metadata``.

HDF5 layout (``format = "flakedb-fourier-bsdf"``, ``format_version = 1``)
------------------------------------------------------------------------
Root attributes: ``format``, ``format_version``, ``flakedb_version``, ``eta``, ``alpha`` (2,),
``channels`` (JSON list of names), ``delta`` (JSON object or ``null``), ``metadata`` (JSON object:
the table's metadata merged with ``extra_metadata``).  Datasets: ``mu`` float64 (n,) -- the
solver's nodes without the zero nodes; ``coeffs`` float64 (C, n, n, L), every order, chunked per
(channel, incident node), shuffle + gzip(1); ``albedo`` float64 (C, n), the Catmull-Rom albedo of
each channel at each incident node (derived, for inspection).  The reader inserts the two zero
nodes exactly as the ``.bsdf`` writer does, so both files evaluate identically up to float32.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import re
import struct
import tempfile
import warnings
from pathlib import Path
from typing import Any

import numba
import numpy as np

__all__ = [
    "BSDFTable",
    "BSDFFileError",
    "FourierBSDF",
    "write_bsdf",
    "read_bsdf",
    "write_h5",
    "read_h5",
    "open_bsdf",
    "catmull_rom_weights",
    "catmull_rom_cdf",
    "insert_zero_nodes",
    "format_metadata",
    "parse_metadata",
    "bsdf_file_size",
    "TRUNCATION_DEFAULT",
]

#: The spec's (layerlab's) truncation rule: keep orders until the tail sum is <= this times |a_0|.
TRUNCATION_DEFAULT = 2e-3

#: Y from linear R, G, B (spec, "colour") and the readers' G from Y, R, B.
RGB_TO_Y = (0.212671, 0.715160, 0.072169)
G_FROM_YRB = (1.39829, -0.297375, -0.100913)  # coefficients of Y, R, B

_MAGIC_BSDF = b"SCATFUN"
_MAGIC_H5 = b"\x89HDF\r\n\x1a\n"
_VERSION = 1
_FLAGS_BSDF = 1
_FLAGS_EXTRAPOLATED = 2
_HEADER = struct.Struct("<7sBIIIIIIIIIfff8x")  # 64 bytes, spec table
assert _HEADER.size == 64

H5_FORMAT = "flakedb-fourier-bsdf"
H5_FORMAT_VERSION = 1

_KEY_RE = re.compile(r"^[A-Za-z_][A-Za-z0-9_.\-]*$")
_KEY_LINE_RE = re.compile(r"^[A-Za-z_][A-Za-z0-9_.\-]*=")

# Reassociation lets LLVM vectorise the coefficient dot products; NaN/inf semantics are kept
# (the range checks rely on NaN comparing false).
_FASTMATH = {"reassoc", "contract", "nsz", "arcp"}

# Bound on the number of floats of one evaluation chunk's blended coefficient block.
_CHUNK_FLOATS = 1 << 21


class BSDFFileError(ValueError):
    """A BSDF file that cannot be read: missing, truncated, corrupt or unsupported."""


# --------------------------------------------------------------------------------------------
# The solver's table
# --------------------------------------------------------------------------------------------
@dataclasses.dataclass
class BSDFTable:
    """A tabulated azimuthally-isotropic BSDF as the solver produces it.

    Attributes
    ----------
    mu : float64 (n,)
        Quadrature nodes (cosines, conventions), ascending, ``[-x_h … -x_1, x_1 … x_h]`` with
        ``0 < x_1 < … < x_h <= 1``, n = 2h even, no node at 0.
    coeffs : float64 (C, n, n, L)
        ``coeffs[c, i, o, l]``: cosine-series coefficient ``l`` of **f · |mu_o|** [1/sr] for
        incident node ``mu[i]``, outgoing node ``mu[o]``, channel ``c`` (``a_0`` is the mean over
        ``phi_d``; no quadrature weights, no extra 1/π).  C = 1 (mono) or 3 (linear R, G, B) for
        ``.bsdf``; any C for HDF5.
    eta : float
        Relative index eta_below / eta_above of the whole stack (header field; renderers scale
        transmitted radiance with it).
    alpha : (float, float)
        Beckmann-equivalent roughness of the top and bottom surfaces (informational).
    delta : dict or None
        The smooth coat's first-surface mirror term, e.g. ``{"kind": "fresnel", "eta": 1.5}``:
        ``F(theta_i; eta)`` times a delta in the mirror direction, *not* in ``coeffs``.
    metadata : dict
        str -> JSON-able (recipe name, flakedb version, ...).
    channels : tuple of str or None
        Channel names; default ``("R", "G", "B")`` for C = 3, ``("mono",)`` for C = 1,
        ``("c0", "c1", …)`` otherwise.
    """

    mu: np.ndarray
    coeffs: np.ndarray
    eta: float = 1.0
    alpha: tuple = (0.0, 0.0)
    delta: dict | None = None
    metadata: dict = dataclasses.field(default_factory=dict)
    channels: tuple | None = None

    def __post_init__(self):
        self.mu = np.asarray(self.mu, dtype=np.float64)
        self.coeffs = np.asarray(self.coeffs, dtype=np.float64)
        mu, c = self.mu, self.coeffs
        if mu.ndim != 1 or mu.size < 2 or mu.size % 2:
            raise ValueError(f"BSDFTable.mu must be a 1-D array of even length n = 2h >= 2, got shape {mu.shape}")
        h = mu.size // 2
        if not (np.all(np.isfinite(mu)) and np.all(np.diff(mu) > 0)):
            raise ValueError("BSDFTable.mu must be finite and strictly ascending")
        if not (mu[h - 1] < 0 < mu[h] and mu[-1] <= 1.0 and mu[0] >= -1.0):
            raise ValueError(
                f"BSDFTable.mu must be [-x_h … -x_1, x_1 … x_h] in [-1, 1] with no node at 0; "
                f"got mu[h-1] = {mu[h - 1]!r}, mu[h] = {mu[h]!r}, range [{mu[0]!r}, {mu[-1]!r}]")
        if not np.allclose(mu[:h], -mu[h:][::-1], rtol=0, atol=1e-12):
            raise ValueError("BSDFTable.mu must be symmetric: mu[:h] == -mu[h:][::-1] (one rule per hemisphere)")
        if c.ndim != 4 or c.shape[1] != mu.size or c.shape[2] != mu.size or c.shape[3] < 1 or c.shape[0] < 1:
            raise ValueError(f"BSDFTable.coeffs must have shape (C, n, n, L) with n = {mu.size}, got {c.shape}")
        if not np.all(np.isfinite(c)):
            raise ValueError("BSDFTable.coeffs contains NaN or inf")
        self.eta = float(self.eta)
        if not (math.isfinite(self.eta) and self.eta > 0):
            raise ValueError(f"BSDFTable.eta must be a positive finite relative index, got {self.eta!r}")
        alpha = tuple(float(a) for a in np.atleast_1d(self.alpha))
        if len(alpha) != 2:
            raise ValueError(f"BSDFTable.alpha must hold 2 roughness values (top, bottom), got {self.alpha!r}")
        self.alpha = alpha
        if self.delta is not None:
            _check_delta(self.delta)
            self.delta = dict(self.delta)
        self.metadata = dict(self.metadata or {})
        if self.channels is None:
            self.channels = _default_channels(c.shape[0])
        self.channels = tuple(str(s) for s in self.channels)
        if len(self.channels) != c.shape[0]:
            raise ValueError(f"BSDFTable.channels names {len(self.channels)} channels, coeffs has {c.shape[0]}")

    @property
    def n(self) -> int:
        return self.mu.size

    @property
    def n_channels(self) -> int:
        return self.coeffs.shape[0]

    def albedo(self) -> np.ndarray:
        """(C, n): ``2π ∫ a_0(mu_i, mu_o) dmu_o`` per channel and incident node, with the spec's
        Catmull-Rom integral over the file nodes (zero nodes inserted).  For the Y channel of a
        written ``.bsdf`` this is ``2π·cdf[i][N-1]``."""
        nodes = insert_zero_nodes(self.mu)
        h = self.n // 2
        a0 = self.coeffs[..., 0]                                    # (C, n_i, n_o)
        v = np.zeros(a0.shape[:2] + (nodes.size,))
        v[..., :h] = a0[..., :h]
        v[..., h + 2:] = a0[..., h:]
        return 2.0 * np.pi * catmull_rom_cdf(nodes, v)[..., -1]


def _default_channels(c: int) -> tuple:
    if c == 3:
        return ("R", "G", "B")
    if c == 1:
        return ("mono",)
    return tuple(f"c{k}" for k in range(c))


def _check_delta(delta):
    if not isinstance(delta, dict) or "kind" not in delta:
        raise ValueError(f"delta must be None or a dict with a 'kind', e.g. {{'kind': 'fresnel', 'eta': 1.5}}; got {delta!r}")
    if delta["kind"] == "fresnel":
        eta = delta.get("eta")
        if not (isinstance(eta, (int, float)) and math.isfinite(eta) and eta > 0):
            raise ValueError(f"delta {{'kind': 'fresnel'}} needs a positive relative index 'eta', got {eta!r}")
    for k in delta:
        if not _KEY_RE.match(f"delta_{k}"):
            raise ValueError(f"delta field name {k!r} is not a valid metadata key")


# --------------------------------------------------------------------------------------------
# Catmull-Rom machinery (spec: "Evaluation" step 1 and "cdf")
# --------------------------------------------------------------------------------------------
def insert_zero_nodes(mu: np.ndarray) -> np.ndarray:
    """``[-x_h … -x_1, x_1 … x_h]`` -> the file's ``[-x_h … -x_1, 0, 0, x_1 … x_h]`` (N = n + 2)."""
    mu = np.asarray(mu)
    h = mu.size // 2
    return np.concatenate([mu[:h], np.zeros(2, dtype=mu.dtype), mu[h:]])


def catmull_rom_weights(nodes: np.ndarray, x) -> tuple[np.ndarray, np.ndarray]:
    """Catmull-Rom interpolation weights of ``x`` over ascending ``nodes`` (pbrt-v3 / layerlab).

    Returns ``(offset, weights)``: ``offset`` int64 of x's shape and ``weights`` (..., 4) on nodes
    ``offset … offset+3``.  Interval ``idx`` = largest node <= x, clamped to [0, N-2]
    (``offset = idx - 1``); ``u = (x - x_idx)/(x_{idx+1} - x_idx)``; Hermite basis with
    finite-difference tangents scaled by ``(x_{idx+1}-x_idx)/(x_{idx+1}-x_{idx-1})`` on the left and
    ``(x_{idx+1}-x_idx)/(x_{idx+2}-x_idx)`` on the right, one-sided at the ends.  Weights falling
    outside the node range are 0 (and their index is then irrelevant).  For x outside
    ``[nodes[0], nodes[-1]]`` or NaN all weights are 0.  With the duplicated zero node, x >= 0
    always lands in an interval right of both zeros and x < 0 left of them, so the zero-width
    interval is never used.
    """
    nodes = np.asarray(nodes, dtype=np.float64)
    n = nodes.size
    x = np.asarray(x, dtype=np.float64)
    valid = (x >= nodes[0]) & (x <= nodes[-1])
    xc = np.where(valid, x, nodes[0])
    idx = np.clip(np.searchsorted(nodes, xc, side="right") - 1, 0, n - 2)
    x0 = nodes[idx]
    x1 = nodes[idx + 1]
    width = x1 - x0
    t = (xc - x0) / width
    t2 = t * t
    t3 = t2 * t
    w = np.zeros(x.shape + (4,))
    w[..., 1] = 2 * t3 - 3 * t2 + 1
    w[..., 2] = -2 * t3 + 3 * t2
    d0 = t3 - 2 * t2 + t
    d1 = t3 - t2
    left = idx > 0
    f0 = width / np.where(left, x1 - nodes[np.maximum(idx - 1, 0)], 1.0)
    w[..., 0] = np.where(left, -d0 * f0, 0.0)
    w[..., 2] += np.where(left, d0 * f0, d0)
    w[..., 1] -= np.where(left, 0.0, d0)
    right = idx + 2 < n
    f1 = width / np.where(right, nodes[np.minimum(idx + 2, n - 1)] - x0, 1.0)
    w[..., 3] = np.where(right, d1 * f1, 0.0)
    w[..., 1] -= np.where(right, d1 * f1, d1)
    w[..., 2] += np.where(right, 0.0, d1)
    w *= valid[..., None]
    return idx - 1, w


def catmull_rom_cdf(nodes: np.ndarray, values: np.ndarray) -> np.ndarray:
    """Prefix integrals of the Catmull-Rom spline through ``(nodes, values[..., :])`` (spec, "cdf").

    ``out[..., 0] = 0``, ``out[..., k+1] = out[..., k] + w((v_k + v_{k+1})/2 + (d0 - d1)/12)``
    with ``w = x_{k+1} - x_k``, ``d0 = w (v_{k+1} - v_{k-1})/(x_{k+1} - x_{k-1})`` (``v_{k+1} - v_k``
    on the first interval) and ``d1 = w (v_{k+2} - v_k)/(x_{k+2} - x_k)`` (``v_{k+1} - v_k`` on the
    last).  Exact for functions linear between the nodes.  Vectorised over leading axes; the sum is
    sequential along the last axis (as layerlab's ``integrate1D``).
    """
    x = np.asarray(nodes, dtype=np.float64)
    v = np.asarray(values, dtype=np.float64)
    n = x.size
    if v.shape[-1] != n or n < 2:
        raise ValueError(f"values must end in an axis of {n} node values, got shape {v.shape}")
    w = np.diff(x)
    vk, vk1 = v[..., :-1], v[..., 1:]
    slope_one = vk1 - vk
    if n > 2:
        centred = (v[..., 2:] - v[..., :-2]) / (x[2:] - x[:-2])   # D_j, j = 1 … n-2
        d0 = np.concatenate([slope_one[..., :1], w[1:] * centred], axis=-1)
        d1 = np.concatenate([w[:-1] * centred, slope_one[..., -1:]], axis=-1)
    else:
        d0 = d1 = slope_one
    seg = w * ((vk + vk1) * 0.5 + (d0 - d1) * (1.0 / 12.0))
    out = np.zeros(v.shape)
    np.cumsum(seg, axis=-1, out=out[..., 1:])
    return out


# --------------------------------------------------------------------------------------------
# Metadata text
# --------------------------------------------------------------------------------------------
def _format_value(v) -> str:
    if isinstance(v, str) and "\n" not in v and "\r" not in v:
        try:
            json.loads(v)
        except (ValueError, TypeError):
            return v
    if isinstance(v, np.generic):
        v = v.item()
    if isinstance(v, np.ndarray):
        v = v.tolist()
    return json.dumps(v, ensure_ascii=False, separators=(", ", ": "), allow_nan=False)


def _parse_value(s: str):
    try:
        return json.loads(s)
    except ValueError:
        return s


def format_metadata(metadata: dict, delta: dict | None = None) -> str:
    """The ``.bsdf`` metadata text for ``metadata`` and the mirror term ``delta`` (module docstring)."""
    metadata = dict(metadata or {})
    lines = []
    clash = [k for k in metadata if k == "delta" or (isinstance(k, str) and k.startswith("delta_"))]
    if clash:
        raise ValueError(f"metadata keys {clash} are reserved for the mirror term; pass it as table.delta")
    if delta is not None:
        _check_delta(delta)
        lines.append(f"delta={_format_value(delta['kind'])}")
        lines += [f"delta_{k}={_format_value(v)}" for k, v in delta.items() if k != "kind"]
    text = metadata.pop("text", None)
    for k, v in metadata.items():
        if not isinstance(k, str) or not _KEY_RE.match(k):
            raise ValueError(f"metadata key {k!r} must match [A-Za-z_][A-Za-z0-9_.-]*")
        lines.append(f"{k}={_format_value(v)}")
    if text is not None:
        if isinstance(text, str) and not any(_KEY_LINE_RE.match(ln) for ln in text.split("\n")):
            lines.append(text)
        else:
            lines.append(f"text={_format_value(text)}")
    return "\n".join(lines)


def parse_metadata(text: str) -> tuple[dict, dict | None]:
    """Inverse of :func:`format_metadata`: ``(metadata, delta)``; free-text lines go to ``"text"``."""
    md: dict[str, Any] = {}
    free = []
    if text:
        for line in text.split("\n"):
            if _KEY_LINE_RE.match(line):
                k, v = line.split("=", 1)
                md[k] = _parse_value(v)
            else:
                free.append(line)
    if free:
        md["text"] = "\n".join(free) if "text" not in md else md["text"] + "\n" + "\n".join(free)
    delta = None
    if "delta" in md:
        delta = {"kind": md.pop("delta")}
        for k in [k for k in md if k.startswith("delta_")]:
            delta[k[len("delta_"):]] = md.pop(k)
    return md, delta


# --------------------------------------------------------------------------------------------
# The .bsdf writer
# --------------------------------------------------------------------------------------------
def bsdf_file_size(n_nodes: int, n_coeffs: int, n_metadata_bytes: int, n_parameters: int = 0,
                   n_parameter_values: int = 0, n_bases: int = 1) -> int:
    """The spec's size formula [bytes]: 64 + 4 (N + nP + nPV + N²·nBases + 2N² + nCoeffs) + nMeta."""
    nn = n_nodes * n_nodes
    return 64 + 4 * (n_nodes + n_parameters + n_parameter_values + nn * n_bases + 2 * nn + n_coeffs) + n_metadata_bytes


def _truncation_orders(c: np.ndarray, truncation: float) -> np.ndarray:
    """K per entry for one incident row: ``c`` (C, n_o, L) -> int (n_o,).

    Per channel: the smallest j >= 1 with ``Σ_{k>=j} |a_k| <= truncation·|a_0|``; max over
    channels; entries whose coefficients are all exactly 0 get K = 0.  ``truncation = 0`` keeps
    everything up to the last non-zero coefficient.
    """
    a = np.abs(c)
    tail = np.cumsum(a[..., ::-1], axis=-1)[..., ::-1]                 # tail[..., j] = Σ_{k>=j}
    tail_ext = np.concatenate([tail, np.zeros(tail.shape[:-1] + (1,))], axis=-1)
    ok = tail_ext[..., 1:] <= truncation * a[..., :1]                  # ok[..., j-1] for j = 1 … L
    k = np.argmax(ok, axis=-1) + 1                                     # the last one (j = L) is always ok
    k = k.max(axis=0)
    k[~np.any(c != 0, axis=(0, 2))] = 0
    return k


def _file_channels(coeffs_row: np.ndarray) -> np.ndarray:
    """(C, ...) table channels -> (C, ...) file channels: mono unchanged, R, G, B -> Y, R, B."""
    if coeffs_row.shape[0] == 1:
        return coeffs_row
    r, g, b = coeffs_row
    y = RGB_TO_Y[0] * r + RGB_TO_Y[1] * g + RGB_TO_Y[2] * b
    return np.stack([y, r, b])


def _atomic_target(path: Path):
    from flakedb.atomic import temp_beside

    return temp_beside(path, suffix="")


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

    def fidx(t):  # table index -> file index
        return t if t < h else t + 2

    # Pass 1: orders K[i, o] (file indices) and stored Y a_0 (float32) for the cdf.
    K = np.zeros((N, N), dtype=np.int64)
    a0 = np.zeros((N, N), dtype=np.float64)
    for ti in range(n):
        row = table.coeffs[:, ti]                                    # (C, n_o, L)
        i = fidx(ti)
        k = _truncation_orders(row, truncation)
        K[i, :h] = k[:h]
        K[i, h + 2:] = k[h:]
        y0 = _file_channels(row[..., 0])[0].astype(np.float32)       # (n_o,)
        y0 = np.where(k > 0, y0, 0.0)
        a0[i, :h] = y0[:h]
        a0[i, h + 2:] = y0[h:]
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
    header = _HEADER.pack(_MAGIC_BSDF, _VERSION, _FLAGS_BSDF, N, n_coeffs, max_order, C, 1,
                          len(meta_bytes), 0, 0, np.float32(table.eta), np.float32(table.alpha[0]),
                          np.float32(table.alpha[1]))
    size = bsdf_file_size(N, n_coeffs, len(meta_bytes))
    fd, tmp = _atomic_target(path)
    try:
        with os.fdopen(fd, "wb") as fh:
            fh.write(header)
            fh.write(nodes32.astype("<f4").tobytes())
            fh.write(cdf.tobytes())
            fh.write(offsets.tobytes())
            L = table.coeffs.shape[3]
            kk = np.arange(L)
            for ti in range(n):                                      # pass 2: coefficients, row by row
                i = fidx(ti)
                fc = _file_channels(table.coeffs[:, ti]).astype("<f4")   # (C, n_o, L)
                k_row = np.concatenate([K[i, :h], K[i, h + 2:]])
                block = np.transpose(fc, (1, 0, 2))                  # (n_o, C, L)
                mask = np.broadcast_to(kk[None, None, :] < k_row[:, None, None], block.shape)
                o_neg, o_pos = block[:h][mask[:h]], block[h:][mask[h:]]
                fh.write(o_neg.tobytes())
                fh.write(o_pos.tobytes())                            # the zero-node entries hold nothing
            fh.write(meta_bytes)
        if os.path.getsize(tmp) != size:
            raise RuntimeError(f"internal error: wrote {os.path.getsize(tmp)} bytes, spec size is {size}")
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise
    return {"n_nodes": N, "n_coeffs": n_coeffs, "max_order": max_order, "n_channels": C,
            "metadata_bytes": len(meta_bytes), "size": size}


# --------------------------------------------------------------------------------------------
# The reader object
# --------------------------------------------------------------------------------------------
def _sparse_from_dense(dense: np.ndarray, order: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(N, N, C, L) dense + K (N, N) -> ``(flat, start)`` in the ``.bsdf`` layout (entry e = o + i·N
    contiguous, channel c's coefficient k at ``start[i, o] + c·K + k``), float64."""
    N, _, C, L = dense.shape
    K = order.ravel()
    start = np.zeros(N * N, dtype=np.int64)
    start[1:] = np.cumsum(K * C)[:-1]
    mask = np.broadcast_to(np.arange(L)[None, None, :] < K[:, None, None], (N * N, C, L))
    flat = np.ascontiguousarray(dense.reshape(N * N, C, L)[mask], dtype=np.float64)
    return flat, start.reshape(N, N)


def _channel_flat(flat, start, order, n_channels, weights) -> tuple[np.ndarray, np.ndarray]:
    """The single channel ``Σ_c weights[c] · channel_c`` as its own ``(flat, start)``."""
    K = order.ravel().astype(np.int64)
    st = start.ravel()
    new_start = np.zeros_like(K)
    new_start[1:] = np.cumsum(K)[:-1]
    local = np.arange(int(K.sum())) - np.repeat(new_start, K)
    out = np.zeros(local.size)
    for c in range(n_channels):
        if weights[c] != 0:
            out += weights[c] * flat[np.repeat(st + c * K, K) + local]
    return out, new_start.reshape(order.shape)


class FourierBSDF:
    """A tabulated Fourier BSDF read from a ``.bsdf`` or HDF5 file (see the module docstring).

    Internally every stored channel is kept in the ``.bsdf``'s sparse layout in float64 (``flat``
    plus ``start``/``order``), whatever the file, so one compiled evaluation kernel serves both.

    Attributes
    ----------
    nodes : float64 (N,)        file nodes, zero node twice
    cdf : float64 (N, N)        ``cdf[i, o]``, prefix Catmull-Rom integral of the sampling channel's a_0
    order : int64 (N, N)        K_e, coefficients per channel of entry (incident i, outgoing o)
    offsets : uint32 (N·N, 2) or None   the ``.bsdf`` offset table (None for HDF5)
    coeffs : float32 (nCoeffs,) or None the ``.bsdf`` coefficient block (None for HDF5)
    n_channels : int            stored channels (1 or 3 in a ``.bsdf``: Y, R, B)
    channels : tuple of str     names of what ``eval`` returns per point
    max_order : int             largest K_e
    n_coeffs : int              stored floats (``nCoeffs`` of a ``.bsdf``; C·n·n·L of an HDF5 table)
    eta, alpha, delta, metadata, metadata_text, path, kind ("bsdf" or "h5"), header (dict or None)
    """

    def __init__(self, *, kind, path, nodes, cdf, order, flat, start, n_channels, mix, sample_weights,
                 channels, eta, alpha, delta, metadata, metadata_text="", offsets=None, coeffs=None,
                 header=None, n_coeffs=None, table=None):
        self.kind = kind
        self.path = None if path is None else Path(path)
        self.nodes = np.ascontiguousarray(nodes, dtype=np.float64)
        self.cdf = np.ascontiguousarray(cdf, dtype=np.float64)
        self.order = np.ascontiguousarray(order, dtype=np.int64)
        self.n_channels = int(n_channels)
        self._flat = np.ascontiguousarray(flat, dtype=np.float64)
        self._start = np.ascontiguousarray(start, dtype=np.int64)
        self._mix = np.ascontiguousarray(mix, dtype=np.float64)     # (Cs, Cout)
        self._sample_weights = np.asarray(sample_weights, dtype=np.float64)
        self._sflat, self._sstart = _channel_flat(self._flat, self._start, self.order, self.n_channels,
                                                  self._sample_weights)
        has = self.order > 0
        self._a0 = np.zeros(self.order.shape + (self.n_channels,))   # (N, N, Cs) order-0 coefficients
        for c in range(self.n_channels):
            self._a0[..., c][has] = self._flat[(self._start + c * self.order)[has]]
        self._a0s = np.ascontiguousarray(self._a0 @ self._sample_weights)
        # Catmull-Rom integral of every stored channel's a_0 per incident node: (N, Cs).
        self._int_a0 = catmull_rom_cdf(self.nodes, np.moveaxis(self._a0, 2, 0))[..., -1].T
        self.channels = tuple(channels)
        self.max_order = int(self.order.max(initial=0))
        self.eta = float(eta)
        self.alpha = tuple(float(a) for a in alpha)
        self.delta = delta
        self.metadata = metadata
        self.metadata_text = metadata_text
        self.offsets = offsets
        self.coeffs = coeffs
        self.header = header
        self.n_coeffs = int(n_coeffs if n_coeffs is not None else self._flat.size)
        self._table = table

    @property
    def n_nodes(self) -> int:
        return self.nodes.size

    def __repr__(self):
        return (f"FourierBSDF({self.kind}, N={self.n_nodes}, channels={self.n_channels}, "
                f"max_order={self.max_order}, eta={self.eta:g}, path={str(self.path)!r})")

    # -- the numpy reference path ----------------------------------------------------------------
    def _chunks(self, p: int, m: int):
        step = max(16, _CHUNK_FLOATS // max(1, self.n_channels * m))
        for s in range(0, p, step):
            yield slice(s, min(p, s + step))

    def _blend(self, oi, wi, oo, wo, flat, start, cs, m=None):
        """Blend the 4x4 neighbouring coefficient vectors (spec step 2): -> (P, cs, Mc).

        Each entry's K_e coefficients per channel are gathered from the sparse block and padded
        with zeros to the chunk's largest order ``Mc`` (or ``m``)."""
        N = self.n_nodes
        ii = np.clip(oi[:, None] + np.arange(4), 0, N - 1)                 # (P, 4)
        jj = np.clip(oo[:, None] + np.arange(4), 0, N - 1)
        ww = wi[:, :, None] * wo[:, None, :]                               # (P, 4, 4)
        kk_all = self.order[ii[:, :, None], jj[:, None, :]]
        kmax = int(np.max(np.where(ww != 0, kk_all, 0), initial=0))
        mc = max(kmax, 1) if m is None else max(m, 1)
        k = np.arange(mc)
        ch = np.arange(cs)
        out = np.zeros((oi.size, cs, mc))
        for a in range(4):
            for b in range(4):
                w = ww[:, a, b]
                if not w.any():
                    continue
                K = kk_all[:, a, b]
                st = start[ii[:, a], jj[:, b]]
                idx = st[:, None, None] + ch[None, :, None] * K[:, None, None] + k[None, None, :]
                mask = k[None, None, :] < K[:, None, None]
                out += w[:, None, None] * np.where(mask, flat[np.where(mask, idx, 0)], 0.0)
        return out

    @staticmethod
    def _cos_table(phi, m):
        """cos(k phi) for k < m as (P, m), by the Chebyshev recurrence."""
        c = np.empty((m, phi.size))
        c[0] = 1.0
        if m > 1:
            c1 = np.cos(phi)
            c[1] = c1
            two_c = 2.0 * c1
            for k in range(2, m):
                np.multiply(two_c, c[k - 1], out=c[k])
                c[k] -= c[k - 2]
        return c.T

    @staticmethod
    def _prep(*args):
        arrs = np.broadcast_arrays(*[np.asarray(a, dtype=np.float64) for a in args])
        return arrs[0].shape, [np.ascontiguousarray(a.ravel()) for a in arrs]

    def _series_values(self, mi, mo, ph, sampling, method):
        """The blended series summed at phi: ``(values (P, Cd), a0 (P, Cd))`` for the stored
        channels (Cd = Cs) or the sampling channel (``sampling=True``, Cd = 1)."""
        flat, start, cd = ((self._sflat, self._sstart, 1) if sampling
                           else (self._flat, self._start, self.n_channels))
        vals = np.zeros((mi.size, cd))
        a0 = np.zeros((mi.size, cd))
        if method == "numba":
            _series_kernel(self.nodes, flat, start, self.order, cd, mi, mo, ph, vals, a0)
            return vals, a0
        if method != "numpy":
            raise ValueError("method must be 'numba' or 'numpy'")
        oi, wi = catmull_rom_weights(self.nodes, mi)
        oo, wo = catmull_rom_weights(self.nodes, mo)
        for sl in self._chunks(mi.size, max(self.max_order, 1)):
            a = self._blend(oi[sl], wi[sl], oo[sl], wo[sl], flat, start, cd)          # (P, Cd, Mc)
            vals[sl] = np.einsum("pcm,pm->pc", a, self._cos_table(ph[sl], a.shape[-1]))
            a0[sl] = a[:, :, 0]
        return vals, a0

    # -- public evaluation -----------------------------------------------------------------------
    def series(self, mu_i, mu_o, channels: str = "stored") -> np.ndarray:
        """Interpolated cosine series of f·|mu_o| at ``(mu_i, mu_o)`` (spec steps 1-2).

        ``channels="stored"``: (..., Cs, max_order), the file's channels (Y, R, B for an RGB
        ``.bsdf``; as stored in an HDF5 file); ``"sampling"``: (..., max_order), the sampling
        channel.  Orders beyond an entry's K_e count as 0.
        """
        if channels not in ("stored", "sampling"):
            raise ValueError("channels must be 'stored' or 'sampling'")
        shape, (mi, mo) = self._prep(mu_i, mu_o)
        oi, wi = catmull_rom_weights(self.nodes, mi)
        oo, wo = catmull_rom_weights(self.nodes, mo)
        m = max(self.max_order, 1)
        flat, start, cd = ((self._sflat, self._sstart, 1) if channels == "sampling"
                           else (self._flat, self._start, self.n_channels))
        out = np.empty((mi.size, cd, m))
        for sl in self._chunks(mi.size, m):
            out[sl] = self._blend(oi[sl], wi[sl], oo[sl], wo[sl], flat, start, cd, m)
        if channels == "sampling":
            out = out[:, 0]
        return out.reshape(shape + out.shape[1:])

    def eval(self, mu_i, mu_o, phi_d, clamp: str = "layerlab", method: str = "numba") -> np.ndarray:
        """f·|mu_o| [1/sr] at incident ``mu_i``, outgoing ``mu_o``, azimuth difference ``phi_d`` [rad].

        Arguments broadcast; returns (..., len(channels)): R, G, B for a ``.bsdf`` (mono repeated),
        the stored channels for HDF5.  ``clamp``: ``"layerlab"`` | ``"all"`` | ``"none"`` (module
        docstring).  Out-of-range or NaN cosines give 0.  The smooth coat's delta term is not
        included (see :attr:`delta`).  ``method="numba"`` (default) loops over points in compiled
        code using each entry's own K_e; ``"numpy"`` is the plain vectorised reference (blend the
        16 coefficient vectors padded to the chunk's largest order, then sum), slower, same values.
        """
        if clamp not in ("layerlab", "all", "none"):
            raise ValueError("clamp must be 'layerlab', 'all' or 'none'")
        shape, (mi, mo, ph) = self._prep(mu_i, mu_o, phi_d)
        vals, a0 = self._series_values(mi, mo, ph, False, method)
        res = vals @ self._mix
        if clamp == "all":
            res = np.maximum(res, 0.0)
        elif clamp == "layerlab":
            if self.n_channels == 1:
                res = np.maximum(res, 0.0)
            res[(a0 @ self._sample_weights) == 0] = 0.0
        return res.reshape(shape + (res.shape[-1],))

    def cdf_last(self, mu_i) -> np.ndarray:
        """The blended total ``cdf(mu_i)[N-1]`` = ∫ a_0,s dmu_o of the sampling channel (albedo/2π)."""
        oi, wi = catmull_rom_weights(self.nodes, np.asarray(mu_i, dtype=np.float64))
        N = self.n_nodes
        rows = self.cdf[np.clip(oi[..., None] + np.arange(4), 0, N - 1), N - 1]
        return np.sum(wi * rows, axis=-1)

    def pdf(self, mu_i, mu_o, phi_d, method: str = "numba") -> np.ndarray:
        """Density [1/sr] with which :meth:`sample` draws ``(mu_o, phi_d)`` given ``mu_i``:

        ``max(0, f_s·|mu_o|) / (2π · cdf(mu_i)[N-1])`` (spec), 0 where the blended a_0 of the
        sampling channel is 0 or the total is not positive.
        """
        shape, (mi, mo, ph) = self._prep(mu_i, mu_o, phi_d)
        vals, a0 = self._series_values(mi, mo, ph, True, method)
        f, a0 = vals[:, 0], a0[:, 0]
        norm = self.cdf_last(mi)
        good = (a0 != 0) & (norm > 0)
        out = np.where(good, np.maximum(f, 0.0) / (2.0 * np.pi * np.where(good, norm, 1.0)), 0.0)
        return out.reshape(shape)

    def albedo_nodes(self) -> np.ndarray:
        """``2π·cdf[i][N-1]`` per file node (N,): the sampling channel's albedo (R + T) at each node."""
        return 2.0 * np.pi * self.cdf[:, -1]

    def albedo(self, mu_i) -> np.ndarray:
        """Albedo (reflectance + transmittance) per output channel at incident ``mu_i``: (..., Cout).

        ``2π ∫ a_0(mu_i, mu_o) dmu_o`` per stored channel (Catmull-Rom integral over the nodes,
        blended in mu_i), mapped to the output channels.  Equals ``E[weight]`` of :meth:`sample`.
        """
        mu_i = np.asarray(mu_i, dtype=np.float64)
        oi, wi = catmull_rom_weights(self.nodes, mu_i)
        N = self.n_nodes
        rows = self._int_a0[np.clip(oi[..., None] + np.arange(4), 0, N - 1)]   # (..., 4, Cs)
        return 2.0 * np.pi * np.einsum("...a,...ac->...c", wi, rows) @ self._mix

    def sample(self, mu_i, u1, u2):
        """Importance-sample ``(mu_o, phi_d)`` for incident ``mu_i`` from uniform ``u1`` (-> mu_o)
        and ``u2`` (-> phi_d), broadcast.  Returns ``(mu_o, phi_d, weight, pdf)``:

        * ``mu_o`` (...) from the Catmull-Rom cdf of the blended incident row (pbrt-v3
          ``SampleCatmullRom2D``), ``phi_d`` (...) in [0, 2π) from the sampling channel's Fourier
          series (pbrt-v3 ``SampleFourier``, Newton-bisection on its integral);
        * ``pdf`` (...) [1/sr] as :meth:`pdf`; ``weight`` (..., Cout) = ``eval(…, clamp="none") /
          pdf`` (0 where pdf is 0).  Where ``mu_i`` is out of range or carries no energy,
          everything is 0.
        """
        shape, (mi, a1, a2) = self._prep(mu_i, u1, u2)
        p = mi.size
        mu_o = np.zeros(p)
        phi = np.zeros(p)
        pdf = np.zeros(p)
        weight = np.zeros((p, self._mix.shape[1]))
        _sample_kernel(self.nodes, self.cdf, self._a0s, self._sflat, self._sstart, self._flat,
                       self._start, self.order, self.n_channels, self._mix, mi, a1, a2,
                       mu_o, phi, weight, pdf)
        return (mu_o.reshape(shape), phi.reshape(shape), weight.reshape(shape + (weight.shape[1],)),
                pdf.reshape(shape))

    # -- back to the solver's form ---------------------------------------------------------------
    def to_table(self) -> BSDFTable:
        """The content as a :class:`BSDFTable` (zero nodes removed; Y, R, B -> R, G, B with the exact
        inverse of the writer's formula, so ``write_bsdf(…, truncation=0)`` reproduces the floats)."""
        if self._table is not None:
            return self._table
        N = self.n_nodes
        h = (N - 2) // 2
        keep = np.r_[0:h, h + 2:N]
        L = max(self.max_order, 1)
        K = self.order.ravel()
        dense = np.zeros((N * N, self.n_channels, L))
        mask = np.broadcast_to(np.arange(L)[None, None, :] < K[:, None, None], dense.shape)
        dense[mask] = self._flat
        c = np.transpose(dense.reshape(N, N, self.n_channels, L)[np.ix_(keep, keep)], (2, 0, 1, 3))
        if self.kind == "bsdf" and self.n_channels == 3:
            y, r, b = c
            g = (y - RGB_TO_Y[0] * r - RGB_TO_Y[2] * b) / RGB_TO_Y[1]
            c = np.stack([r, g, b])
            names = ("R", "G", "B")
        else:
            names = ("mono",) if self.kind == "bsdf" else self.channels
        return BSDFTable(mu=self.nodes[keep], coeffs=c, eta=self.eta, alpha=self.alpha,
                         delta=self.delta, metadata=dict(self.metadata), channels=names)


# --------------------------------------------------------------------------------------------
# Compiled kernels (numba): evaluation, and pbrt-v3's SampleCatmullRom2D + SampleFourier.
# All take the sparse float64 layout, so each compiles once (one signature).
# --------------------------------------------------------------------------------------------
@numba.njit(cache=True, nogil=True, error_model="numpy")
def _cr_weights_1(nodes, x, w):
    """Scalar Catmull-Rom weights (as :func:`catmull_rom_weights`); returns the offset, or -N if
    x is out of range / NaN."""
    n = nodes.size
    if not (x >= nodes[0] and x <= nodes[n - 1]):
        return -n
    lo = 0
    hi = n                                        # largest i with nodes[i] <= x
    while hi - lo > 1:
        mid = (lo + hi) >> 1
        if nodes[mid] <= x:
            lo = mid
        else:
            hi = mid
    idx = min(max(lo, 0), n - 2)
    x0 = nodes[idx]
    x1 = nodes[idx + 1]
    width = x1 - x0
    t = (x - x0) / width
    t2 = t * t
    t3 = t2 * t
    w[0] = 0.0
    w[1] = 2 * t3 - 3 * t2 + 1
    w[2] = -2 * t3 + 3 * t2
    w[3] = 0.0
    d0 = t3 - 2 * t2 + t
    d1 = t3 - t2
    if idx > 0:
        f = width / (x1 - nodes[idx - 1])
        w[0] = -d0 * f
        w[2] += d0 * f
    else:
        w[1] -= d0
        w[2] += d0
    if idx + 2 < n:
        f = width / (nodes[idx + 2] - x0)
        w[3] = d1 * f
        w[1] -= d1 * f
    else:
        w[1] -= d1
        w[2] += d1
    return idx - 1


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _interp_row(arr, off, w, col):
    """Σ_a w[a] · arr[off + a, col] over the non-zero weights."""
    s = 0.0
    for a in range(4):
        if w[a] != 0.0:
            s += w[a] * arr[off + a, col]
    return s


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _normal_quantile(p):
    """Inverse standard normal CDF (Acklam's rational approximation, relative error < 1.2e-9)."""
    a0, a1, a2, a3, a4, a5 = (-3.969683028665376e+01, 2.209460984245205e+02, -2.759285104469687e+02,
                              1.383577518672690e+02, -3.066479806614716e+01, 2.506628277459239e+00)
    b0, b1, b2, b3, b4 = (-5.447609879822406e+01, 1.615858368580409e+02, -1.556989798598866e+02,
                          6.680131188771972e+01, -1.328068155288572e+01)
    c0, c1, c2, c3, c4, c5 = (-7.784894002430293e-03, -3.223964580411365e-01, -2.400758277161838e+00,
                              -2.549732539343734e+00, 4.374664141464968e+00, 2.938163982698783e+00)
    d0, d1, d2, d3 = (7.784695709041462e-03, 3.224671290700398e-01, 2.445134137142996e+00,
                      3.754408661907416e+00)
    if p <= 0.0:
        return -np.inf
    if p >= 1.0:
        return np.inf
    if p < 0.02425:
        q = np.sqrt(-2 * np.log(p))
        return (((((c0 * q + c1) * q + c2) * q + c3) * q + c4) * q + c5) / ((((d0 * q + d1) * q + d2) * q + d3) * q + 1)
    if p > 1 - 0.02425:
        q = np.sqrt(-2 * np.log(1 - p))
        return -(((((c0 * q + c1) * q + c2) * q + c3) * q + c4) * q + c5) / ((((d0 * q + d1) * q + d2) * q + d3) * q + 1)
    q = p - 0.5
    r = q * q
    return ((((((a0 * r + a1) * r + a2) * r + a3) * r + a4) * r + a5) * q
            / (((((b0 * r + b1) * r + b2) * r + b3) * r + b4) * r + 1))


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _blend_order(order, oi, oo, wi, wo):
    """Largest coefficient count among the 4 × 4 entries blended at (oi, oo) with non-zero weight."""
    kmax = 0
    for ia in range(4):
        for ob in range(4):
            if wi[ia] * wo[ob] != 0.0:
                kmax = max(kmax, order[oi + ia, oo + ob])
    return kmax


@numba.njit(cache=True, nogil=True, error_model="numpy", fastmath=_FASTMATH)
def _series_kernel(nodes, flat, start, order, cd, mu_i, mu_o, phi, out_val, out_a0):
    """Per point: Σ over the 4x4 neighbouring entries of w · Σ_{k<K_e} a_k cos(k phi) per channel
    (= the blended series summed, the spec's evaluation), and the blended a_0 per channel."""
    n = nodes.size
    wi = np.zeros(4)
    wo = np.zeros(4)
    m = 1
    for i in range(order.shape[0]):
        for o in range(order.shape[1]):
            m = max(m, order[i, o])
    cosk = np.zeros(m)
    for p in range(mu_i.size):
        oi = _cr_weights_1(nodes, mu_i[p], wi)
        oo = _cr_weights_1(nodes, mu_o[p], wo)
        if oi == -n or oo == -n:
            continue
        kmax = _blend_order(order, oi, oo, wi, wo)
        if kmax == 0:
            continue
        c1 = np.cos(phi[p])
        cosk[0] = 1.0
        if kmax > 1:
            cosk[1] = c1
        for k in range(2, kmax):
            cosk[k] = 2.0 * c1 * cosk[k - 1] - cosk[k - 2]
        for ia in range(4):
            for ob in range(4):
                ww = wi[ia] * wo[ob]
                if ww == 0.0:
                    continue
                ke = order[oi + ia, oo + ob]
                if ke == 0:
                    continue
                base = start[oi + ia, oo + ob]
                for c in range(cd):
                    off = base + c * ke
                    s = 0.0
                    for k in range(ke):
                        s += flat[off + k] * cosk[k]
                    out_val[p, c] += ww * s
                    out_a0[p, c] += ww * flat[off]


@numba.njit(cache=True, nogil=True, error_model="numpy", fastmath=_FASTMATH)
def _sample_kernel(nodes, cdf, a0s, sflat, sstart, flat, start, order, cs, mix, mu_i, u1, u2,
                   out_mu, out_phi, out_w, out_pdf):
    n = nodes.size
    cout = mix.shape[1]
    m = 1
    for i in range(order.shape[0]):
        for o in range(order.shape[1]):
            m = max(m, order[i, o])
    wi = np.zeros(4)
    wo = np.zeros(4)
    a_s = np.zeros(m)
    a_c = np.zeros((cs, m))
    vals = np.zeros(cs)
    for p in range(mu_i.size):
        oi = _cr_weights_1(nodes, mu_i[p], wi)
        if oi == -n:
            continue
        maximum = _interp_row(cdf, oi, wi, n - 1)
        if not maximum > 0.0:
            continue
        # -- mu_o: invert the Catmull-Rom cdf of the blended incident row (SampleCatmullRom2D)
        u = min(max(u1[p], 0.0), 1.0) * maximum
        first = 0
        length = n
        while length > 0:
            half = length >> 1
            middle = first + half
            if _interp_row(cdf, oi, wi, middle) <= u:
                first = middle + 1
                length -= half + 1
            else:
                length = half
        idx = min(max(first - 1, 0), n - 2)
        f0 = _interp_row(a0s, oi, wi, idx)
        f1 = _interp_row(a0s, oi, wi, idx + 1)
        x0 = nodes[idx]
        x1 = nodes[idx + 1]
        width = x1 - x0
        if idx > 0:
            d0 = width * (f1 - _interp_row(a0s, oi, wi, idx - 1)) / (x1 - nodes[idx - 1])
        else:
            d0 = f1 - f0
        if idx + 2 < n:
            d1 = width * (_interp_row(a0s, oi, wi, idx + 2) - f0) / (nodes[idx + 2] - x0)
        else:
            d1 = f1 - f0
        u = (u - _interp_row(cdf, oi, wi, idx)) / width
        if f0 != f1:
            t = (f0 - np.sqrt(max(0.0, f0 * f0 + 2 * u * (f1 - f0)))) / (f0 - f1)
        elif f0 != 0.0:
            t = u / f0
        else:
            t = 0.5
        a = 0.0
        b = 1.0
        for _it in range(100):
            if not (t >= a and t <= b):
                t = 0.5 * (a + b)
            F = t * (f0 + t * (0.5 * d0 + t * ((1.0 / 3.0) * (-2 * d0 - d1) + f1 - f0
                                             + t * (0.25 * (d0 + d1) + 0.5 * (f0 - f1)))))
            fh = f0 + t * (d0 + t * (-2 * d0 - d1 + 3 * (f1 - f0) + t * (d0 + d1 + 2 * (f0 - f1))))
            if abs(F - u) < 1e-9 * max(abs(f0), abs(f1), 1e-300) or b - a < 1e-9:
                break
            if F - u < 0:
                a = t
            else:
                b = t
            t -= (F - u) / fh
        mu_o = x0 + width * t
        out_mu[p] = mu_o
        # -- blend the 16 neighbouring entries at (mu_i, mu_o)
        oo = _cr_weights_1(nodes, mu_o, wo)
        if oo == -n:
            continue
        kmax = _blend_order(order, oi, oo, wi, wo)
        if kmax == 0:
            continue
        a_s[:kmax] = 0.0
        a_c[:, :kmax] = 0.0
        for ia in range(4):
            for ob in range(4):
                ww = wi[ia] * wo[ob]
                if ww == 0.0:
                    continue
                ke = order[oi + ia, oo + ob]
                sb = sstart[oi + ia, oo + ob]
                for k in range(ke):
                    a_s[k] += ww * sflat[sb + k]
                base = start[oi + ia, oo + ob]
                for c in range(cs):
                    off = base + c * ke
                    for k in range(ke):
                        a_c[c, k] += ww * flat[off + k]
        if not a_s[0] > 0.0:
            continue
        # -- phi_d: invert the integral of the sampling channel's series (SampleFourier)
        v = u2[p]
        flip = v >= 0.5
        if flip:
            v = 1.0 - 2.0 * (v - 0.5)
        else:
            v *= 2.0
        lo = 0.0
        hi = np.pi
        phi = 0.5 * np.pi
        if kmax > 10 and v > 0.0 and v < 1.0 and a_s[1] > 0.0 and a_s[2] > 0.0:
            # starting guess for peaked lobes (layerlab): a wrapped Gaussian has
            # a_k ∝ exp(-k²σ²/2), so σ² = 2/3 log(a_1/a_2); phi = σ Φ⁻¹(1/2 + v/2)
            var = 2.0 / 3.0 * np.log(a_s[1] / a_s[2])
            if var > 0.0 and np.isfinite(var):
                phi = min(np.pi, _normal_quantile(0.5 + 0.5 * v) * np.sqrt(var))
        fphi = a_s[0]
        for _it in range(100):
            cphi = np.cos(phi)
            sphi = np.sqrt(max(0.0, 1.0 - cphi * cphi))
            c_prev = cphi
            c_cur = 1.0
            s_prev = -sphi
            s_cur = 0.0
            F = a_s[0] * phi
            fphi = a_s[0]
            for k in range(1, kmax):
                s_next = 2 * cphi * s_cur - s_prev
                c_next = 2 * cphi * c_cur - c_prev
                s_prev = s_cur
                s_cur = s_next
                c_prev = c_cur
                c_cur = c_next
                F += a_s[k] / k * s_next
                fphi += a_s[k] * c_next
            F -= v * a_s[0] * np.pi
            if F > 0:
                hi = phi
            else:
                lo = phi
            if abs(F) < 1e-10 * a_s[0] or hi - lo < 1e-10:
                break
            phi -= F / fphi
            if not (phi > lo and phi < hi):
                phi = 0.5 * (lo + hi)
        if flip:
            phi = 2 * np.pi - phi
        out_phi[p] = phi
        pdf = max(0.0, fphi) / (2 * np.pi * maximum)
        out_pdf[p] = pdf
        if pdf <= 0.0:
            continue
        # -- every channel at the sampled direction -> weight = f / pdf
        cphi = np.cos(phi)
        for c in range(cs):
            vals[c] = 0.0
        c_prev = cphi
        c_cur = 1.0
        for k in range(kmax):
            if k > 0:
                c_next = 2 * cphi * c_cur - c_prev
                c_prev = c_cur
                c_cur = c_next
            for c in range(cs):
                vals[c] += a_c[c, k] * c_cur
        for j in range(cout):
            s = 0.0
            for c in range(cs):
                s += vals[c] * mix[c, j]
            out_w[p, j] = s / pdf


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
    try:
        raw = path.read_bytes()
    except FileNotFoundError:
        raise BSDFFileError(f"{path}: no such file") from None
    except OSError as e:
        raise BSDFFileError(f"{path}: cannot read ({e.strerror})") from None
    if len(raw) < 64:
        raise BSDFFileError(f"{path}: truncated header ({len(raw)} bytes, a .bsdf header is 64)")
    (ident, version, flags, N, n_coeffs, max_order, C, n_bases, n_meta, n_par, n_parval,
     eta, alpha0, alpha1) = _HEADER.unpack_from(raw, 0)
    if ident != _MAGIC_BSDF:
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
    if not (np.all(np.isfinite(nodes)) and np.all(np.diff(nodes) >= 0) and nodes[0] >= -1 and nodes[-1] <= 1):
        raise BSDFFileError(f"{path}: nodes are not ascending within [-1, 1]")
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


# --------------------------------------------------------------------------------------------
# HDF5
# --------------------------------------------------------------------------------------------
def write_h5(path, table: BSDFTable, extra_metadata: dict | None = None) -> dict:
    """Write the full-precision table (float64, every order, all channels) to HDF5, atomically.

    ``extra_metadata`` (e.g. ``{"recipe_text": …, "store_version": …}``) is merged over
    ``table.metadata``; ``flakedb_version`` is always recorded.  Layout in the module docstring.
    Returns ``{"size": bytes, "n_channels": C, "max_order": L}``.
    """
    import h5py

    from flakedb import __version__

    if not isinstance(table, BSDFTable):
        raise TypeError("write_h5 expects a BSDFTable")
    md = dict(table.metadata)
    md.update(extra_metadata or {})
    md_json = json.dumps(md, sort_keys=True, allow_nan=False, default=_json_default)
    C, n, _, L = table.coeffs.shape
    fd, tmp = _atomic_target(path)
    os.close(fd)
    try:
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
            f.create_dataset("coeffs", data=table.coeffs, chunks=(1, 1, n, L), shuffle=True,
                             compression="gzip", compression_opts=1)
            f.create_dataset("albedo", data=table.albedo())
        size = os.path.getsize(tmp)
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise
    return {"size": size, "n_channels": C, "max_order": L}


def _json_default(o):
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, np.generic):
        return o.item()
    raise TypeError(f"metadata value {o!r} is not JSON-able")


def read_h5(path) -> FourierBSDF:
    """Read a file written by :func:`write_h5` into a :class:`FourierBSDF` (float64, channels as
    stored; the zero nodes inserted as in the ``.bsdf``; cdf computed from the sampling channel)."""
    import h5py

    path = Path(path)
    if not path.exists():
        raise BSDFFileError(f"{path}: no such file")
    try:
        with h5py.File(path, "r") as f:
            fmt = f.attrs.get("format")
            if fmt != H5_FORMAT:
                raise BSDFFileError(f"{path}: not a flakedb BSDF HDF5 file (format attribute {fmt!r})")
            ver = int(f.attrs["format_version"])
            if ver > H5_FORMAT_VERSION:
                raise BSDFFileError(f"{path}: format_version {ver} is newer than this flakedb reads "
                                    f"({H5_FORMAT_VERSION}); upgrade flakedb")
            mu = f["mu"][...]
            coeffs = f["coeffs"][...]
            eta = float(f.attrs["eta"])
            alpha = tuple(float(a) for a in f.attrs["alpha"])
            channels = tuple(json.loads(f.attrs["channels"]))
            delta = json.loads(f.attrs["delta"])
            stored = json.loads(f.attrs["metadata"])
            written_by = str(f.attrs["flakedb_version"])
    except (OSError, KeyError, ValueError) as e:
        raise BSDFFileError(f"{path}: corrupt or incomplete flakedb HDF5 file ({e})") from None
    table = BSDFTable(mu=mu, coeffs=coeffs, eta=eta, alpha=alpha, delta=delta, metadata=stored,
                      channels=channels)
    # what FourierBSDF.metadata shows: the stored metadata plus who wrote the file, in which format
    return _from_table(table, path=path,
                       metadata={**stored, "flakedb_version": written_by, "h5_format_version": ver})


def _from_table(table: BSDFTable, path=None, metadata=None) -> FourierBSDF:
    """A :class:`FourierBSDF` evaluating ``table`` at full precision (zero nodes inserted as in the
    ``.bsdf``; K_e = index of the last non-zero coefficient + 1, so nothing is lost)."""
    C, n, _, L = table.coeffs.shape
    h = n // 2
    N = n + 2
    nodes = insert_zero_nodes(table.mu)
    dense = np.zeros((N, N, C, L))
    sel = np.r_[0:h, h + 2:N]
    dense[np.ix_(sel, sel)] = np.transpose(table.coeffs, (1, 2, 0, 3))
    nz = (dense != 0).any(axis=2)                                        # (N, N, L)
    order = np.where(nz.any(axis=-1), L - np.argmax(nz[..., ::-1], axis=-1), 0)
    flat, start = _sparse_from_dense(dense, order)
    del dense
    if C == 3 and tuple(table.channels) == ("R", "G", "B"):
        sw = np.array(RGB_TO_Y)
    else:
        sw = np.full(C, 1.0 / C)
    a0s = np.zeros((N, N))
    a0s[np.ix_(sel, sel)] = np.einsum("cio,c->io", table.coeffs[..., 0], sw)
    cdf = catmull_rom_cdf(nodes, a0s)
    return FourierBSDF(kind="h5", path=path, nodes=nodes, cdf=cdf, order=order, flat=flat,
                       start=start, n_channels=C, mix=np.eye(C), sample_weights=sw,
                       channels=table.channels, eta=table.eta, alpha=table.alpha, delta=table.delta,
                       metadata=dict(metadata if metadata is not None else table.metadata),
                       n_coeffs=C * n * n * L, table=table)


def open_bsdf(path) -> FourierBSDF:
    """Open a ``.bsdf`` or flakedb HDF5 BSDF file, recognised by its magic bytes."""
    path = Path(path)
    try:
        with open(path, "rb") as fh:
            magic = fh.read(8)
    except FileNotFoundError:
        raise BSDFFileError(f"{path}: no such file") from None
    except OSError as e:
        raise BSDFFileError(f"{path}: cannot read ({e.strerror})") from None
    if magic[:7] == _MAGIC_BSDF:
        return read_bsdf(path)
    if magic == _MAGIC_H5:
        return read_h5(path)
    raise BSDFFileError(f"{path}: neither a Fourier .bsdf (SCATFUN) nor an HDF5 file (first bytes {magic!r})")
