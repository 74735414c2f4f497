"""Compiled kernels (numba) of :class:`flakedb.bsdf.evaluator.FourierBSDF` and the Mitsuba export:
evaluation, and pbrt-v3's SampleCatmullRom2D + SampleFourier.  All take the sparse float64
layout, so each compiles once (one signature).

The functions below are plain Python; :func:`compiled` imports numba and compiles them on first use
(cached on disk), so that a process that writes files but evaluates nothing (solve → ``.bsdf``) does
not pay numba's import (~0.2 s of a 1–2 s run).  Call them as ``compiled().series_kernel(…)``."""

from __future__ import annotations

import threading
import types

import numpy as np

from flakedb.interrupts import deferred

#: name -> extra numba options of the kernels :func:`compiled` compiles (filled by :func:`_kernel`).
_KERNELS: dict = {}


def _kernel(**options):
    """Register a function for :func:`compiled` (numba's ``njit(cache=True, nogil=True,
    error_model="numpy", **options)``); the function itself is returned unchanged."""
    def register(fn):
        _KERNELS[fn.__name__] = options
        return fn
    return register


#: The compiled kernels once :func:`compiled` has run, and the lock that makes it run once (the
#: preview's tile threads may all evaluate first at the same moment).
_COMPILED: list = []
_COMPILE_LOCK = threading.Lock()


def compiled() -> types.SimpleNamespace:
    """The kernels compiled by numba, as attributes (``compiled().series_kernel``).  The first call
    imports numba and replaces this module's functions by their compiled dispatchers, so that the
    kernels calling each other call compiled code (numba resolves those names when it compiles).

    The compiled scalar Catmull-Rom weights are those of the numpy reference:

    >>> from flakedb.bsdf.spline import catmull_rom_weights
    >>> nodes = np.array([0.0, 0.1, 0.35, 0.5, 0.9, 1.0])
    >>> w = np.zeros(4)
    >>> offset = compiled().cr_weights_1(nodes, 0.7, w)
    >>> ref_offset, ref_w = catmull_rom_weights(nodes, 0.7)
    >>> bool(offset == ref_offset), bool(np.allclose(w, ref_w, rtol=1e-14, atol=1e-15))
    (True, True)
    >>> compiled().cr_weights_1(nodes, 1.5, w)                                 # outside the nodes: -N
    -6
    """
    if _COMPILED:
        return _COMPILED[0]
    with _COMPILE_LOCK, deferred():   # numba's import, compilation and cache loading with signals held back
        if not _COMPILED:
            import numba  # lazy: numba takes ~0.2 s to import; solving and writing a file need no compiled kernel

            g = globals()
            for name, options in _KERNELS.items():
                g[name] = numba.njit(cache=True, nogil=True, error_model="numpy", **options)(g[name])
            # the dispatchers themselves (the Mitsuba plugin's own compiled kernels call them); Python callers hold
            # signals back around a call (flakedb.interrupts.deferred, as FourierBSDF does)
            _COMPILED.append(types.SimpleNamespace(**{name: g[name] for name in _KERNELS}))
    return _COMPILED[0]


# Reassociation lets LLVM vectorise the coefficient dot products; NaN/inf semantics are kept
# (the range checks rely on NaN comparing false).
_FASTMATH = {"reassoc", "contract", "nsz", "arcp"}


# --------------------------------------------------------------------------------------------
# Compiled kernels (numba): evaluation, and pbrt-v3's SampleCatmullRom2D + SampleFourier.
# All take the sparse float64 layout, so each compiles once (one signature).
# --------------------------------------------------------------------------------------------
@_kernel()
def cr_weights_1(nodes, x, w):
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


@_kernel()
def _interp_row(arr, off, w, col):
    """Σ_a w[a] · arr[off + a, col] over the non-zero weights."""
    s = 0.0
    for a in range(4):
        if w[a] != 0.0:
            s += w[a] * arr[off + a, col]
    return s


@_kernel()
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


@_kernel()
def _blend_order(order, oi, oo, wi, wo):
    """Largest coefficient count among the 4 × 4 entries blended at (oi, oo) with non-zero weight."""
    kmax = 0
    for ia in range(4):
        for ob in range(4):
            if wi[ia] * wo[ob] != 0.0:
                kmax = max(kmax, order[oi + ia, oo + ob])
    return kmax


@_kernel(fastmath=_FASTMATH)
def series_kernel(nodes, flat, start, order, cd, mu_i, mu_o, phi, out_val, out_a0):
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
        oi = cr_weights_1(nodes, mu_i[p], wi)
        oo = cr_weights_1(nodes, mu_o[p], wo)
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


@_kernel(fastmath=_FASTMATH)
def sample_kernel(nodes, cdf, a0s, sflat, sstart, flat, start, order, cs, mix, mu_i, u1, u2,
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
        oi = cr_weights_1(nodes, mu_i[p], wi)
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
        oo = cr_weights_1(nodes, mu_o, wo)
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
