"""R^t of an opaque stack solved in blocks of Fourier orders (8, 16, then up to where the decay predicts the
tolerance is met, :func:`flakedb.rt.adding.orders.next_block_end`) bottom-up with reflection-only adding, until
the BSDF's dropped tail is within the order tolerance (docs/orders.md).

:class:`OrderBlocks` holds what one solve needs (the body's parts, the bottom, the top); its
:meth:`OrderBlocks.solve` runs the loop.  The specular part R_s of the stack (docs/model.md
"Specular paths and the pole") is taken out of every block before the decay is measured, so the
order count follows the scattered light.
"""

import numpy as np

from flakedb.conventions import fourier_weight
from flakedb.rt.boundaries import interface as itf
from flakedb.rt.basis.layer import pad_orders
from flakedb.rt.adding.orders import (
    MIN_ORDERS_CHECKED,
    next_block_end,
    order_tail,
    reflection_over,
)
from flakedb.rt.adding.parts import order_range

#: First block of orders solved by the order choice; the next ends at 16 (the criterion is not accepted before,
#: :data:`flakedb.rt.adding.orders.MIN_ORDERS_CHECKED`), later ones where the decay measured so far predicts the tolerance
#: is met (at least 4 orders more, at most double: :func:`flakedb.rt.adding.orders.next_block_end`).  Blocks of 8 rather
#: than one of 16 halve the eigen-solutions' temporaries (docs/orders.md: the bench's 3-species basecoat, the
#: solve's process peak 266 → 191 MB, the same 16 orders solved).
FIRST_ORDER_BLOCK = 8
#: Orders of the body solved while a rough top is built in the background (before the stack's order count is
#: known): ``body_orders`` clipped to this range.
OVERLAP_ORDERS = (16, 64)


class OrderBlocks:
    """One opaque solve.  ``parts``: the body top to bottom (:mod:`flakedb.rt.adding.parts`); ``q_bottom``,
    ``albedo``: the Lambertian primer's rule and albedo, or ``Rc``: a rough conductor bottom's R^t (all its
    orders); ``through_top(R, l0, l1)``: R^t of the top over a body of reflection R (orders l0 … l1 − 1);
    ``top_rt``: for a rough top, a function returning its R^t (L_top, 1, h, h) once built: where the body
    reflects nothing, the stack's R^t is that block, and the result is written into it when the shapes
    allow and ``top_rt_writable`` (the solver's own array, not one shared by channel groups).
    ``threads()``: the threads a slab solve may use now; ``h_out``, ``h_in``: air-side and top-binder
    node counts; ``specular``: R_s (C, h, h) to take out of every order, or None.


    The order choice, through :func:`flakedb.rt.adding.stack.solve_stack`: the kept orders' dropped tail is within
    the tolerance, and fewer orders are kept than the cap 2n allows.

    >>> from flakedb.rt.adding.components import Lambertian, Rough, Slab, SolverSettings
    >>> from flakedb.rt.scattering.media import PhaseMedium
    >>> from flakedb.rt.adding.stack import solve_stack
    >>> b = solve_stack(Rough(1.5, 0.3), [Slab(10.0, PhaseMedium(0.5, 0.9, ("hg", 0.7)))], Lambertian(0.5),
    ...                 SolverSettings.product(n=16))
    >>> L, decay = b.info["orders"], b.info["order_decay"]
    >>> b.n_orders == L < 32, b.info["order_converged"], sum(decay[L:]) <= b.info["order_tol"]
    (True, True, True)
    """

    def __init__(self, parts, s, through_top, h_out, h_in, q_bottom=None, albedo=None, Rc=None, top_rt=None,
                 top_rt_writable=True, threads=lambda: 1, specular=None):
        self.parts, self.s, self.through_top = parts, s, through_top
        self.h_out, self.h_in = h_out, h_in
        self.q_bottom, self.albedo, self.Rc = q_bottom, albedo, Rc
        self.top_rt, self.top_rt_writable, self.threads = top_rt, top_rt_writable, threads
        self.specular = specular
        self.L_report = 0

    def _over(self, R, l0, l1):
        """The body's parts added bottom-up over R (None: black), orders l0 … l1 − 1; a slab without
        kernel orders here over a black bottom reflects nothing (the bottom stays black, no blocks built)."""
        n = len(self.parts)
        for k, part in enumerate(reversed(self.parts)):
            if not (R is None and part.dark_from(l0)):
                R = reflection_over(part.block(l0, l1, self.threads()), R)
            self.s.report("solve", layer=n - k, layers=n, orders=(l0, l1), of=self.L_report)
        return R

    def body(self, l0, l1):
        """The body's reflection R^t (on the top binder's rule) of orders l0 … l1 − 1, None where it
        reflects nothing."""
        if self.Rc is not None:  # a rough conductor bottom carries orders of its own
            return self._over(pad_orders(self.Rc, max(l1, self.Rc.shape[0]))[l0:l1], l0, l1)
        R = None
        if l0 == 0:  # the Lambertian primer has order 0 only: its adding runs for that order alone
            R = self._over(itf.lambertian(self.q_bottom, self.albedo, 1).Rt, 0, 1)
            l0 = 1
        if l1 <= l0:
            return R
        Rr = self._over(None, l0, l1)
        if Rr is None:  # the body reflects nothing in these orders
            if R is None:
                return None
            Rr = np.zeros((l1 - l0, 1, self.h_in, self.h_in))
        if R is None:
            return Rr
        shape = np.broadcast_shapes(R.shape[1:], Rr.shape[1:])
        return np.concatenate([np.broadcast_to(R, R.shape[:1] + shape), np.broadcast_to(Rr, Rr.shape[:1] + shape)])

    def stack_block(self, R, l0, l1):
        """(R^t of the stack for orders l0 … l1 − 1, the top's own array when it is that block as it is)."""
        if R is not None:
            Rt = self.through_top(R, l0, l1)
            if self.specular is not None:
                Rt = Rt - self.specular[None]
            return Rt, None
        if self.top_rt is not None:  # a black body: the top's own reflection (no blocks built, no solve)
            own = self.top_rt()
            return order_range(own, l0, l1), own
        return np.broadcast_to(np.zeros((1, 1, self.h_out, self.h_out)), (l1 - l0, 1, self.h_out, self.h_out)), None

    def _grow(self, out, Rt, l0, L_max):
        """The result array for orders 0 … L_max − 1 able to hold ``Rt``'s channels: ``out`` itself, the
        rough top's R^t (written in place: block l is read before order l is written), or a new array
        holding the orders solved so far."""
        if out is not None and np.broadcast_shapes(out.shape[1:], Rt.shape[1:]) == out.shape[1:]:
            return out
        shape = Rt.shape[1:] if out is None else np.broadcast_shapes(out.shape[1:], Rt.shape[1:])
        trt = self.top_rt() if self.top_rt is not None else None
        if (trt is not None and self.top_rt_writable and trt.shape[0] >= L_max and trt.shape[1:] == shape
                and l0 == 0 and self.specular is None):
            return trt
        grown = np.empty((L_max,) + shape)
        if out is not None:
            grown[:l0] = out[:l0]
        return grown

    def decay(self, Rt, l0, l1):
        """max over channels and node pairs of the cosine-weighted BSDF f μ_i μ_o = S_l μ_o / (c_l w_i) of
        orders l0 … l1 − 1 (conventions; reciprocal: the flux a coefficient carries per unit projected
        solid angle, so grazing pairs, where f of a rough coat grows as 1/(μ_i μ_o), do not dictate the
        order count: docs/orders.md)."""
        flux = self.x_out[:, None] / self.w_out[None, :]
        amax = np.empty(l1 - l0)
        for c0 in range(0, l1 - l0, FIRST_ORDER_BLOCK):  # a few orders at a time
            g = np.abs(Rt[c0:c0 + FIRST_ORDER_BLOCK])
            g *= flux
            amax[c0:c0 + FIRST_ORDER_BLOCK] = g.reshape(g.shape[0], -1).max(axis=1)
        return amax / fourier_weight(np.arange(l0, l1))

    def solve(self, x_out, w_out, L_max, body_orders=None):
        """Run the order loop.  ``L_max``: the stack's order count, or a function returning it; with
        ``body_orders`` (not None: a top built in the background) the body's first orders, ``body_orders``
        clipped to :data:`OVERLAP_ORDERS`, are solved before it is called.  Returns (R^t (L', C, h, h) of the scattered light,
        info)."""
        s = self.s
        self.x_out, self.w_out = x_out, w_out
        first = None
        if callable(L_max) and body_orders is None:  # no top built in the background: nothing to overlap
            L_max = L_max()
        elif callable(L_max):  # the body's first block does not need the top: solve it while the top is built
            lo, hi = OVERLAP_ORDERS
            self.L_report = L_first = min(s.order_cap, max(lo, min(body_orders or 0, hi)))
            first = self.body(0, L_first)
            L_max = L_max()
        self.L_report = L_max
        out, a = None, []  # out: R^t of the orders solved so far, (L_max, C, h, h) filled block by block
        l0, f0max, done = 0, None, False
        L_keep, tail = 1, 0.0
        while l0 < L_max:
            l1 = next_block_end(a, L_max, s.order_tol, FIRST_ORDER_BLOCK) if a else min(L_max, FIRST_ORDER_BLOCK)
            if first is not None and l0 < first.shape[0]:  # orders are independent: blocks inside the solved ones
                l1 = min(l1, first.shape[0])
                R = first[l0:l1]
            else:
                R = self.body(l0, l1)
            Rt, own = self.stack_block(R, l0, l1)
            out = self._grow(out, Rt, l0, L_max)
            if own is None or out is not own:
                out[l0:l1] = Rt
            amax = self.decay(Rt, l0, l1)
            if f0max is None:
                f0max = float(amax[0])
            a.extend((amax / (f0max if f0max > 0 else 1.0)).tolist())
            l0 = l1
            L_keep, tail, done = order_tail(a, L_max, s.order_tol, min_orders=MIN_ORDERS_CHECKED)
            if done:
                break
        solved = max(l0, 0 if first is None else first.shape[0])  # the overlapped first block may go further
        info = {"orders": int(L_keep), "orders_solved": int(solved), "orders_available": int(L_max),
                "order_tol": float(s.order_tol), "order_tail": float(tail), "order_converged": bool(done),
                "order_decay": [float(v) for v in a]}
        return out[:L_keep], info
