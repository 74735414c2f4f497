"""The reader object :class:`FourierBSDF`: evaluation, pdf, sampling, albedo of a tabulated Fourier
BSDF (docs/bsdf-format.md, "Evaluation", "pdf"); the compiled loops are in
:mod:`flakedb.bsdf.kernels`."""

from __future__ import annotations

from pathlib import Path
from typing import NamedTuple

import numpy as np

from flakedb.bsdf.kernels import compiled as compiled_kernels
from flakedb.bsdf.spline import catmull_rom_cdf, catmull_rom_weights, insert_zero_nodes
from flakedb.bsdf.table import RGB_TO_Y, BSDFTable
from flakedb.interrupts import deferred

# Bound on the number of floats of one evaluation chunk's blended coefficient block.
_CHUNK_FLOATS = 1 << 21


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


def _sparse_from_quadrant(quadrant, rows, cols, N):
    """``(order, flat, start)`` of :func:`_sparse_from_dense` for a table whose only non-zero block is the
    reflection quadrant (C, h, h, L) at dense ``rows`` × ``cols`` of the (N, N) node grid, without the dense
    array: the other entries hold no order, and within the block the entries run in the same row-major order."""
    q = np.transpose(quadrant, (1, 2, 0, 3))                               # (h, h, C, L), a view
    L = q.shape[-1]
    nz = (q != 0).any(axis=2)                                              # (h, h, L)
    K = np.where(nz.any(axis=-1), L - np.argmax(nz[..., ::-1], axis=-1), 0)
    order = np.zeros((N, N), dtype=K.dtype)
    order[np.ix_(rows, cols)] = K
    start = np.zeros(N * N, dtype=np.int64)
    start[1:] = np.cumsum(order.ravel() * q.shape[2])[:-1]
    flat = np.ascontiguousarray(q[np.broadcast_to(np.arange(L) < K[:, :, None, None], q.shape)], dtype=np.float64)
    return order, flat, start.reshape(N, N)


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


class KernelArrays(NamedTuple):
    """What the compiled kernels read of a :class:`FourierBSDF` (:meth:`FourierBSDF.kernel_arrays`).

    nodes (N,), cdf (N, N), order (N, N) int64, n_channels (stored), flat / start: every stored
    channel in the ``.bsdf`` sparse layout (float64), mix (Cs, Cout): stored -> ``eval`` channels,
    sample_flat / sample_start: the sampling channel alone, sample_a0 (N, N): its order-0 coefficients.
    """

    nodes: np.ndarray
    cdf: np.ndarray
    order: np.ndarray
    n_channels: int
    flat: np.ndarray
    start: np.ndarray
    mix: np.ndarray
    sample_flat: np.ndarray
    sample_start: np.ndarray
    sample_a0: np.ndarray


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

    def kernel_arrays(self) -> "KernelArrays":
        """The arrays the compiled kernels of :mod:`flakedb.bsdf.kernels` take, read-only views: the
        public way for another module's kernels (e.g. the Mitsuba plugin) to evaluate and sample
        this reader without touching its internals."""
        ro = []
        for a in (self.nodes, self.cdf, self.order, self._flat, self._start, self._mix, self._sflat,
                  self._sstart, self._a0s):
            v = a.view()
            v.flags.writeable = False
            ro.append(v)
        nodes, cdf, order, flat, start, mix, sflat, sstart, a0s = ro
        return KernelArrays(nodes=nodes, cdf=cdf, order=order, n_channels=self.n_channels, flat=flat,
                            start=start, mix=mix, sample_flat=sflat, sample_start=sstart, sample_a0=a0s)

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
                if not w.any() or flat.size == 0:  # a file with no coefficients (a black table) adds 0
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
            kernel = compiled_kernels().series_kernel
            with deferred():   # a signal waits for the compiled call (flakedb.interrupts)
                kernel(self.nodes, flat, start, self.order, cd, mi, mo, ph, vals, a0)
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
        kernel = compiled_kernels().sample_kernel
        with deferred():   # a signal waits for the compiled call (flakedb.interrupts)
            kernel(self.nodes, self.cdf, self._a0s, self._sflat, self._sstart, self._flat, self._start, self.order,
                   self.n_channels, self._mix, mi, a1, a2, mu_o, phi, weight, pdf)
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
        # gathered by each pair's offset (a file need not store the pairs contiguously or in order)
        start = self._start.ravel()
        idx = (start[:, None, None] + np.arange(self.n_channels)[None, :, None] * K[:, None, None]
               + np.arange(L)[None, None, :])
        dense[mask] = self._flat[idx[mask]]
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



def table_evaluator(table: BSDFTable, path=None, metadata=None) -> FourierBSDF:
    """A :class:`FourierBSDF` evaluating ``table`` at full precision (zero nodes inserted as in the
    ``.bsdf``; K_e = index of the last non-zero coefficient + 1, so nothing is lost).

    A Lambertian of albedo (0.8, 0.5, 0.2) evaluates to ρ |μ_o| / π and reflects ρ at every incidence:

    >>> from flakedb.rt.basis.quadrature import gauss_radau_unit
    >>> x, _ = gauss_radau_unit(8)
    >>> rho = np.array([0.8, 0.5, 0.2])
    >>> refl = np.broadcast_to((rho[:, None] * x[None, ::-1] / np.pi)[:, None, :, None], (3, 8, 8, 1))
    >>> ev = table_evaluator(BSDFTable(np.concatenate([-x[::-1], x]), reflection=refl))
    >>> bool(np.allclose(ev.eval(0.5, -0.3, 1.0), rho * 0.3 / np.pi, rtol=1e-12, atol=0))
    True
    >>> np.round(ev.albedo(np.array([0.3, 0.9])), 9).tolist()
    [[0.8, 0.5, 0.2], [0.8, 0.5, 0.2]]
    """
    C, n, L = table.n_channels, table.n, table.n_orders
    h = n // 2
    N = n + 2
    nodes = insert_zero_nodes(table.mu)
    sel = np.r_[0:h, h + 2:N]
    if table.reflection_only:  # the quadrant alone: the full (N, N, C, L) array would be 4x the table
        rows, cols = sel[h:], sel[:h]
        order, flat, start = _sparse_from_quadrant(table.stored, rows, cols, N)
    else:
        rows = cols = sel
        dense = np.zeros((N, N, C, L))
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
    a0s[np.ix_(rows, cols)] = np.einsum("cio,c->io", table.stored[..., 0], sw)
    cdf = catmull_rom_cdf(nodes, a0s)
    return FourierBSDF(kind="h5", path=path, nodes=nodes, cdf=cdf, order=order, flat=flat,
                       start=start, n_channels=C, mix=np.eye(C), sample_weights=sw,
                       channels=table.channels, eta=table.eta, alpha=table.alpha, delta=table.delta,
                       metadata=dict(metadata if metadata is not None else table.metadata),
                       n_coeffs=C * n * n * L, table=table)
