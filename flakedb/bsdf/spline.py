"""Catmull-Rom weights and prefix integrals over the file nodes (docs/bsdf-format.md, "Evaluation"
step 1 and "cdf")."""

from __future__ import annotations

import numpy as np


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

    Catmull-Rom reproduces a straight line on uneven nodes, and its integral:

    >>> nodes = np.array([0.0, 0.1, 0.35, 0.5, 0.9, 1.0])
    >>> values = 2 * nodes + 1
    >>> offset, w = catmull_rom_weights(nodes, np.array([0.2, 0.7]))
    >>> [round(float(w[j] @ values[offset[j]:offset[j] + 4]), 12) for j in range(2)]
    [1.4, 2.4]
    >>> round(float(catmull_rom_cdf(nodes, values)[-1]), 12)                    # ∫₀¹ (2x + 1) dx
    2.0
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
# Not-a-knot cubic spline (the colour report's albedo interpolation in μ_i)
# --------------------------------------------------------------------------------------------
def cubic_spline_not_a_knot(x, y, xq) -> np.ndarray:
    """The not-a-knot cubic spline through (``x``, ``y``) evaluated at ``xq``: (len(xq), *y.shape[1:]).

    ``x`` (n,) strictly ascending, n ≥ 4; ``y`` (n, ...) values along axis 0; ``xq`` inside [x_0, x_{n−1}]
    (outside, the end pieces are extended).  The C² piecewise cubic whose third derivative is continuous at
    x_1 and x_{n−2} (de Boor, *A Practical Guide to Splines*, ch. IV "not-a-knot"), from its node slopes
    s_i: interior rows dx_i s_{i−1} + 2(dx_{i−1} + dx_i) s_i + dx_{i−1} s_{i+1} = 3(dx_i m_{i−1} + dx_{i−1} m_i)
    (m_i the secant slopes), the not-a-knot end rows as in scipy's ``CubicSpline(bc_type="not-a-knot")``, which it
    equals to rounding; numpy only, so the colour report does not import scipy.interpolate (0.6 s).
    It reproduces every cubic polynomial exactly.

    >>> x = np.array([0.0, 0.3, 0.5, 0.9, 1.0])
    >>> bool(np.allclose(cubic_spline_not_a_knot(x, x**3 - 2 * x, [0.1, 0.7]), [0.001 - 0.2, 0.343 - 1.4]))
    True
    """
    x = np.asarray(x, float)
    y = np.asarray(y, float)
    n = x.size
    if x.ndim != 1 or n < 4 or y.shape[0] != n or np.any(np.diff(x) <= 0):
        raise ValueError(f"cubic_spline_not_a_knot needs ≥ 4 strictly ascending x and y of the same length, "
                         f"got x {x.shape}, y {y.shape}")
    dx = np.diff(x)
    dxr = dx.reshape((-1,) + (1,) * (y.ndim - 1))
    m = np.diff(y, axis=0) / dxr
    A = np.zeros((n, n))
    b = np.empty_like(y)
    i = np.arange(1, n - 1)
    A[i, i - 1] = dx[1:]
    A[i, i] = 2.0 * (dx[:-1] + dx[1:])
    A[i, i + 1] = dx[:-1]
    b[1:-1] = 3.0 * (dxr[1:] * m[:-1] + dxr[:-1] * m[1:])
    d0 = x[2] - x[0]
    A[0, 0], A[0, 1] = dx[1], d0
    b[0] = ((dx[0] + 2.0 * d0) * dx[1] * m[0] + dx[0] ** 2 * m[1]) / d0
    d1 = x[-1] - x[-3]
    A[-1, -2], A[-1, -1] = d1, dx[-2]
    b[-1] = (dx[-1] ** 2 * m[-2] + (2.0 * d1 + dx[-1]) * dx[-2] * m[-1]) / d1
    s = np.linalg.solve(A, b.reshape(n, -1)).reshape(y.shape)
    xq = np.asarray(xq, float)
    k = np.clip(np.searchsorted(x, xq, side="right") - 1, 0, n - 2)
    t = (xq - x[k]).reshape((-1,) + (1,) * (y.ndim - 1))
    h = dxr[k]
    c2 = (3.0 * m[k] - 2.0 * s[k] - s[k + 1]) / h
    c3 = (s[k] + s[k + 1] - 2.0 * m[k]) / h ** 2
    return y[k] + t * (s[k] + t * (c2 + t * c3))
