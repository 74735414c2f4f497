"""Opaque stacks order by order: reflection-only adding and the number of Fourier orders chosen from
the BSDF's decay (docs/orders.md; docs/model.md §4).

Orders of an azimuthally isotropic stack are independent: order l of the composed matrices depends
only on order l of every layer.  An opaque stack (primer at the bottom) needs only its top reflection
R^t, so it is assembled from the bottom up with the first line of the adding equations (paper eq. 4),

    R^t = R1^t + T1^bt R2^t (I − R1^b R2^t)^{-1} T1^tb,

and the orders can be solved in blocks until the BSDF's cosine coefficients have decayed below a
stated tolerance (:func:`order_tail`).
"""

import numpy as np

from flakedb.rt.basis.layer import solve_regular


def reflection_over(top, bottom_Rt):
    """R^t of ``top`` (a :class:`flakedb.rt.basis.layer.Layer`) over an opaque bottom of reflection
    ``bottom_Rt`` (None: a black bottom, R^t = top.R^t): paper eq. 4's first line, one LU solve.

    An empty layer over a body returns the body's reflection; with a black bottom, the top's own:

    >>> from flakedb.rt.basis.layer import Layer, identity_layer
    >>> Rt = np.random.default_rng(0).uniform(0.0, 0.2, (2, 1, 3, 3))        # (L, C, h, h)
    >>> bool(np.allclose(reflection_over(identity_layer(2, 3), Rt), Rt, rtol=0, atol=1e-15))
    True
    >>> top = Layer(Rt, Rt, Rt, Rt)
    >>> reflection_over(top, None) is Rt
    True
    """
    if bottom_Rt is None:
        return top.Rt
    # orders where the bottom reflects nothing (beyond a slab's kernel orders only the direct beam
    # is left) leave R^t = R1^t: no solve for them
    live = np.any(bottom_Rt, axis=tuple(range(1, bottom_Rt.ndim)))
    if not live.all():
        L = max(top.Rt.shape[0], bottom_Rt.shape[0])
        # channels broadcast; the result lives on the top layer's grid (an inner interface maps two grids)
        shape = np.broadcast_shapes(top.Rt.shape[1:-2], top.Tbt.shape[1:-2], bottom_Rt.shape[1:-2]) + top.Rt.shape[-2:]
        out = np.array(np.broadcast_to(top.Rt, (L,) + shape))
        if live.any():
            idx = np.nonzero(np.broadcast_to(live, (L,)))[0]
            sub = type(top)(*(b if b.shape[0] == 1 else b[idx] for b in (top.Rt, top.Ttb, top.Rb, top.Tbt)))
            out[idx] = reflection_over(sub, bottom_Rt if bottom_Rt.shape[0] == 1 else bottom_Rt[idx])
        return out
    A = -(top.Rb @ bottom_Rt)
    idx = np.arange(A.shape[-1])
    A[..., idx, idx] += 1.0
    X = solve_regular(A, top.Ttb)
    return top.Rt + top.Tbt @ (bottom_Rt @ X)


def reflection_under_smooth(t, F_in, h_tir, bottom_Rt):
    """R^t of a smooth interface over an opaque body of reflection ``bottom_Rt`` (L, C, hi, hi).

    The smooth interface (:func:`flakedb.rt.boundaries.interface.smooth_dielectric`) has R^t = 0 (its mirror
    reflection is the analytic delta term), T^tb[h_tir + j, j] = t_j = 1 − F(x_j), T^bt = (T^tb)ᵀ and
    R^b = diag(F_in): the products with it are row/column selections and scalings, so
    R^t = diag(t) [R2 (I − diag(F_in) R2)^{-1}]_{mapped rows, mapped columns} diag(t) costs one LU
    solve of the inside size with h_out right-hand sides and one h_out × hi × h_out product.
    """
    hi = bottom_Rt.shape[-1]
    A = -(F_in[:, None] * bottom_Rt)
    idx = np.arange(hi)
    A[..., idx, idx] += 1.0
    # X = (I − F R2)^{-1} E_mapped: the mapped columns of the inverse (A X = E)
    E = np.zeros((hi, hi - h_tir))
    E[h_tir + np.arange(hi - h_tir), np.arange(hi - h_tir)] = 1.0
    X = solve_regular(A, np.broadcast_to(E, A.shape[:-1] + E.shape[-1:]))
    R = bottom_Rt[..., h_tir:, :] @ X
    return t[:, None] * R * t[None, :]


def _decay_ratio(a, k):
    """The geometric decay ratio r = (a_{L−1} / a_{L−1−k})^(1/k) of the last ``k`` orders of ``a`` when r < 1 (the
    tail :func:`order_tail` extrapolates and :func:`next_block_end` predicts from), else None (fewer than k + 1
    orders, a zero, no decay)."""
    if a.size <= k or not (a[-1 - k] > 0.0 and a[-1] > 0.0):
        return None
    r = (a[-1] / a[-1 - k]) ** (1.0 / k)
    return float(r) if r < 1.0 else None


#: The fewest orders solved before :func:`order_tail` may declare the series converged (unless all L_max are): the
#: decay of orders 12–15 is seen before the geometric estimate is trusted, as the former 16-then-doubling blocks
#: saw it.  A weak, slowly decaying lobe under a fast-falling broad one (narrow flakes at a low loading beside a
#: pigment) shows only there: a = max(0.35^l, 2e-5 · 0.95^l) stopped at 12 solved orders keeps 10 with a true
#: dropped tail of 2.6e-4, 2.5× a tolerance of 1e-4 (tests/rt/test_orders.py).
MIN_ORDERS_CHECKED = 16


def next_block_end(a, L_max, tol, block, k=4, min_orders=MIN_ORDERS_CHECKED):
    """End of the next block of orders to solve after the L = len(``a``) solved, whose decay ``a`` did not
    yet meet :func:`order_tail`'s criterion (docs/orders.md): where the geometric tail that
    :func:`order_tail` extrapolates from the last ``k`` orders (ratio r < 1) predicts the criterion holds,
    i.e. L_keep + 1 with L_keep the first order whose extrapolated tail a_{L−1} r^(L_keep−L+1)/(1 − r) is
    ≤ ``tol``, at least ``k`` orders more (the next estimate then rests on new orders only) and at most
    double the count solved (or ``block`` orders in all, the first block's size), and at least ``min_orders`` in
    all (before that the criterion is not accepted).  Without a decaying estimate (fewer than k + 1 orders,
    r ≥ 1, a zero) or without a positive finite ``tol``: doubling.  Never beyond ``L_max``.

    Orders are independent, so solving fewer orders changes none of them; only the count solved does.

    >>> a = [1.0, 0.24, 0.09, 0.037, 0.016, 0.0059, 0.0029, 0.00098]     # r ≈ 0.40 over the last 4
    >>> next_block_end(a, 200, 1e-4, 16, min_orders=0)                    # L_keep 11 predicted
    12
    >>> next_block_end(a, 200, 1e-4, 8)                                   # not accepted before 16
    16
    >>> next_block_end(a[:3], 200, 1e-4, 16), next_block_end([1.0] * 8, 200, 1e-4, 16)
    (16, 16)
    """
    a = np.asarray(a, dtype=float)
    L = a.size
    L_max = int(L_max)
    grow = min(L_max, max(int(block), 2 * L))
    floor = min(L_max, int(min_orders))
    r = _decay_ratio(a, k)
    if r is None or not (np.isfinite(tol) and tol > 0.0):
        return max(grow, floor)
    # a_{L-1} r^m / (1 − r) ≤ tol for the tail from order L − 1 + m
    m = max(1, int(np.ceil(np.log(tol * (1.0 - r) / a[-1]) / np.log(r))))
    return max(floor, min(grow, max(L + k, L + m)))


def order_tail(a, L_max, tol, k=4, min_orders=0):
    """Choose the number of orders from the decay of the BSDF's coefficients (docs/orders.md).

    ``a`` (L,): a_l = max over channels and node pairs of |f_l| / max |f_0| for the orders solved so
    far; ``L_max``: the order beyond which every coefficient is exactly zero (the components' own
    order counts); ``tol``: the budget for the dropped tail Σ_{l≥L'} a_l (which bounds the change of
    f at any azimuth relative to the BSDF's maximum, since max f ≥ max f_0).

    The unsolved tail l ≥ L is estimated from the last ``k`` orders: geometric with the measured
    ratio r when r < 1, and never more than (L_max − L) times their largest value (decreasing
    coefficients).  Returns ``(L_keep, tail, done)``: the smallest L' with
    Σ_{L'≤l<L} a_l + estimate ≤ tol, the tail bound of that choice, and whether the criterion holds
    (False: solve more orders; always False with fewer than ``min_orders`` solved, unless all L_max are:
    :data:`MIN_ORDERS_CHECKED` in the solver).
    """
    a = np.asarray(a, dtype=float)
    L = a.size
    if L >= L_max:
        est = 0.0
    else:
        last = a[-k:] if L >= k else a
        flat = float(last.max()) * (L_max - L)
        est = flat
        r = _decay_ratio(a, k)
        if r is not None:
            est = min(flat, float(a[-1]) * r / (1.0 - r))
    tails = np.concatenate([np.flip(np.cumsum(np.flip(a))), [0.0]]) + est  # tails[l] = Σ_{j≥l} a_j + est
    ok = np.nonzero(tails <= tol)[0]
    if len(ok) == 0 or L < min(int(min_orders), int(L_max)):
        return L, float(tails[-1]), False
    L_keep = max(1, int(ok[0]))
    return L_keep, float(tails[L_keep]), True
