"""A whole paint stack solved by adding-doubling: top interface, slabs, bottom (docs/model.md §1, §4).

    air | top interface (none, smooth or rough dielectric) | slab … slab | bottom (Lambertian,
    rough conductor or none)

:func:`solve_stack` builds every component's scattering matrices on a common quadrature and number
of Fourier orders, doubles the slabs and adds everything.  The result, :class:`StackBSDF`, holds the
BSDF of the stack seen from above (and the transmission blocks when the stack is not opaque), the
analytic delta term of a smooth top, and evaluates them.

The concepts live in their own modules: the stack's parts and settings (:mod:`flakedb.rt.adding.components`),
the result (:mod:`flakedb.rt.adding.stack_bsdf`), medium kernels (:mod:`flakedb.rt.scattering.medium_projection`), the
body's slabs and inner interfaces as solver parts (:mod:`flakedb.rt.adding.parts`), the specular paths and the
pole (:mod:`flakedb.rt.adding.specular`), the opaque order loop (:mod:`flakedb.rt.adding.order_blocks`) and spectral
channels (:mod:`flakedb.rt.adding.channels`).  This module joins them; its names are the public interface.
"""

import functools
from concurrent.futures import Future

import numpy as np
from threadpoolctl import threadpool_limits

from flakedb.rt.boundaries import interface as itf
from flakedb.rt.adding.channels import (
    bottom_subset,
    bytes_per_channel,
    distinct_channels,
    expand_channels,
    n_channels,
    solve_in_channel_groups,
)
from flakedb.rt.adding.components import (  # noqa: F401  (the public interface of the solver)
    ORDER_TOL,
    InnerRough,
    InnerSmooth,
    Lambertian,
    Rough,
    RoughConductor,
    Slab,
    Smooth,
    SolverSettings,
)
from flakedb.rt.common.jobs import SharedJobs, thread_pool
from flakedb.rt.basis.layer import Layer, add, add_reflection_only, identity_layer, pad_orders
from flakedb.rt.scattering.media import channel_subset
from flakedb.rt.scattering.medium_projection import (  # noqa: F401
    CAPPED_TAIL,
    DampedKernel,
    legendre_moments,
    medium_kernel_blocks,
    project_medium,
)
from flakedb.rt.adding.order_blocks import FIRST_ORDER_BLOCK, OrderBlocks  # noqa: F401
from flakedb.rt.adding.orders import reflection_over
from flakedb.rt.adding.parts import SmoothInnerPart, binder_chain, build_parts, layer_orders, near_matched
from flakedb.rt.basis.quadrature import default_tir_nodes, radau_hemisphere
from flakedb.rt.adding.specular import pole_index, smoothed_specular, specular_reflection, under_smooth, zero_pole_orders
from flakedb.rt.adding.stack_bsdf import StackBSDF  # noqa: F401

#: Memory the solver may use for one group of spectral channels (bytes); channels are independent,
#: so a large problem is solved in groups of channels that fit (``SolverSettings.memory_budget_bytes``
#: overrides; compose takes it from ``$FLAKEDB_MEMORY_BUDGET``).
MEMORY_BUDGET_BYTES = 4 * 2**30
#: The solver's stated peak-memory estimate per channel (:func:`flakedb.rt.adding.channels.bytes_per_channel`).
_bytes_per_channel = bytes_per_channel


def solve_stack(top, slabs, bottom, settings=None, channels=None):
    """Solve the stack; returns a :class:`StackBSDF`.

    ``top``: None (index-matched, no interface), :class:`Smooth` or :class:`Rough`.
    ``slabs``: list of :class:`Slab` (and :class:`InnerSmooth` / :class:`InnerRough` between them).
    ``bottom``: :class:`Lambertian`, :class:`RoughConductor` or None (transmission into a half-space
    of the binder's index).  ``channels``: number of spectral channels (inferred from the components
    when None).

    Channels are independent: when the estimated memory (:func:`flakedb.rt.adding.channels.bytes_per_channel`)
    of all of them together exceeds the budget (``settings.memory_budget_bytes``, default
    ``MEMORY_BUDGET_BYTES``), the channels are solved in groups and the results joined (orders padded
    to the largest count).

    A lossless stack (a non-absorbing forward-scattering slab over a white primer, under a smooth coat)
    reflects all the light at every incidence; an absorbing slab does not:

    >>> from flakedb.rt.scattering.media import PhaseMedium
    >>> coat, primer, s = Smooth(1.5), Lambertian(1.0), SolverSettings(n=16)
    >>> lossless = solve_stack(coat, [Slab(10.0, PhaseMedium(0.5, 1.0, ("hg", 0.7)))], primer, s)
    >>> grey = solve_stack(coat, [Slab(10.0, PhaseMedium(0.5, 0.8, ("hg", 0.7)))], primer, s)
    >>> bool(np.allclose(lossless.albedo(), 1.0, rtol=0, atol=1e-12)), bool(np.all(grey.albedo() < 0.9))
    (True, True)
    """
    s = settings or SolverSettings()
    # small batched matrices: one BLAS thread per call (measured: the batched doubling of 100 × 100
    # blocks ran 4.4× slower with OpenBLAS at 2 threads than at 1 on a 2-core machine); parallelism,
    # if any, is over the batch (``settings.threads``)
    with threadpool_limits(limits=1, user_api="blas"):
        return _solve_stack_grouped(top, slabs, bottom, s, channels)


def _solve_stack_grouped(top, slabs, bottom, s, channels):
    if s.n % 2 == 0 and s.n >= 2:
        C = int(channels) if channels else n_channels(slabs, bottom)
        distinct = distinct_channels(slabs, bottom, C)
        if distinct is not None:  # channels that scatter identically are solved once
            first, inverse = distinct
            sub_slabs = [sl if isinstance(sl, (InnerSmooth, InnerRough)) else
                         Slab(sl.thickness_um, channel_subset(sl.medium, first)) for sl in slabs]
            res = _solve_stack_grouped(top, sub_slabs, bottom_subset(bottom, first), s, len(first))
            return expand_channels(res, inverse)
        h_out = s.n // 2
        h_in = h_out + (0 if not isinstance(top, Smooth) or top.eta == 1.0 else
                        (s.h_tir if s.h_tir is not None else default_tir_nodes(h_out, top.eta)))
        budget = float(s.memory_budget_bytes or MEMORY_BUDGET_BYTES)
        group = max(1, int(budget // _bytes_per_channel(s.n, h_in, s.order_cap)))
        if C > group:
            return solve_in_channel_groups(_solve_stack, top, slabs, bottom, s, C, group)
    return _solve_stack(top, slabs, bottom, s)


def _submit(n_threads, fn, /, *args, **kw):
    """``fn(*args, **kw)`` in the background thread (:func:`flakedb.rt.common.jobs.thread_pool` "flakedb-solve") when
    ``n_threads`` > 1, else now; a future either way."""
    if int(n_threads) <= 1:
        done = Future()
        done.set_result(fn(*args, **kw))
        return done
    return thread_pool(1, "flakedb-solve").submit(fn, *args, **kw)


class _RoughBuild:
    """One rough top's :func:`flakedb.rt.boundaries.interface.rough_dielectric` ``(layer, info)``, submitted (:func:`_submit`)
    when made.  Its independent parts are :class:`flakedb.rt.common.jobs.SharedJobs` (``parts``) that other threads may
    take.  The background thread is shared by every solve of the process, so a build can wait in its queue behind
    another solve's (compose's discretisation solve, submitted first): :meth:`layer` then builds it in the asking
    thread instead.  Each part is a pure function of its arguments: the layer is the same bit for bit whichever
    thread builds it."""

    def __init__(self, threads, *args, **kw):
        self.parts = SharedJobs()
        self.build = functools.partial(itf.rough_dielectric, *args, jobs=self.parts, **kw)
        self.job = _submit(threads, self.build)

    def done(self):
        return self.job.done()

    def layer(self, threads):
        """``(layer, info)``: built here if the background thread has not started it, else the parts it has not
        reached run here (``threads``: this thread and ``threads`` − 1 workers), then its result."""
        if self.job.cancel():
            job = Future()
            job.set_running_or_notify_cancel()
            try:
                job.set_result(self.build())
            except BaseException as e:
                job.set_exception(e)
            self.job = job
        self.parts.help(threads)
        return self.job.result()


class _Top:
    """The top interface of one solve: None, a smooth top's layer (``smooth1``) and delta, or a rough top
    built (in the background with threads > 1) by :func:`flakedb.rt.boundaries.interface.rough_dielectric`, shared
    through ``top_cache`` by channel groups (read only, never written in place).

    The background build's independent parts are :class:`flakedb.rt.common.jobs.SharedJobs`: the background thread
    takes them in order while the main thread solves the body's first orders (on threads − 1 threads), and the
    main thread, once it needs the top, takes those not yet started (:meth:`rough_layer`, with threads − 2
    workers) instead of waiting idle, or builds the whole top when the background thread has not reached it
    (:class:`_RoughBuild`)."""

    def __init__(self, top, q_out, q_in, s, inner, top_cache):
        self.top, self.s, self.q_out = top, s, q_out
        self.smooth1 = self.delta_F = self.job = self.layer = None
        if isinstance(top, Smooth):
            self.smooth1, self.delta_F = itf.smooth_dielectric(q_out, q_in, top.eta, 1)
        elif isinstance(top, Rough):
            key = None if top_cache is None else (
                q_out.x.tobytes(), q_out.w.tobytes(), q_in.x.tobytes(), q_in.w.tobytes(), float(top.eta),
                float(top.alpha), s.tol, s.order_cap, bool(top.energy_compensation), inner)
            self.job = None if key is None else top_cache.get(key)
            if self.job is None:
                self.job = _RoughBuild(s.threads, q_out, q_in, top.eta, top.alpha, tol=s.tol, max_orders=s.order_cap,
                                       energy_compensation=top.energy_compensation, inner_orders=inner)
                if key is not None:
                    top_cache[key] = self.job

    def busy(self):
        """Whether the rough top is still being built in the background."""
        return self.job is not None and not self.job.done()

    def rough_layer(self):
        """The rough top's layer (:meth:`_RoughBuild.layer`)."""
        if self.layer is None:
            self.layer, _ = self.job.layer(max(1, self.s.threads - 1))
        return self.layer

    def n_orders(self):
        return 0 if self.job is None else self.rough_layer().n_orders

    def block(self, l0, l1):
        """The top's layer of orders l0 … l1 − 1."""
        if isinstance(self.top, Rough):
            return layer_orders(self.rough_layer(), l0, l1)
        sm = self.smooth1
        return Layer(*(np.broadcast_to(b, (l1 - l0,) + b.shape[1:]) for b in (sm.Rt, sm.Ttb, sm.Rb, sm.Tbt)))

    def over(self):
        """``(R, l0, l1) ↦`` R^t of the top over a body of reflection R."""
        if self.top is None:
            return lambda R, l0, l1: R
        if isinstance(self.top, Smooth):
            f = under_smooth(self.smooth1, self.q_out.h)
            return lambda R, l0, l1: f(R)
        return lambda R, l0, l1: reflection_over(self.block(l0, l1), R)


def inner_interface_verdicts(top, inner, n) -> list:
    """The solver's own verdict on each inner interface of a stack solved at ``n`` nodes (product settings):
    for an :class:`InnerRough` solved as a smooth one, :func:`flakedb.rt.adding.parts.near_matched`'s dict, else None
    (an :class:`InnerSmooth` or None entry gives None).  ``inner``: the inner interfaces top to bottom (None
    entries skipped; other items of a slab list ignored).  Cheap: only the binder chain's rules are built, so
    the resolution (:mod:`flakedb.solve.resolution`) asks the very test :func:`flakedb.rt.adding.parts.build_parts`
    applies.

    >>> inner_interface_verdicts(Smooth(1.5), [InnerRough(1.501 / 1.5, 0.03)], 32)[0]["solved_as"]
    'smooth (nearly index-matched)'
    >>> inner_interface_verdicts(Smooth(1.5), [InnerRough(1.6 / 1.5, 0.03), None], 32)
    [None, None]
    """
    items = [it for it in inner if isinstance(it, (InnerSmooth, InnerRough))]
    top, eta = _resolve_top(top)
    chain = binder_chain(top, eta, items, radau_hemisphere(n // 2), SolverSettings.product(n))
    verdicts = [near_matched(float(it.eta), float(it.alpha), chain.rules[b], chain.rules[b + 1])
                if isinstance(it, InnerRough) else None for b, it in enumerate(items)]
    it_v = iter(verdicts)
    return [next(it_v) if isinstance(it, (InnerSmooth, InnerRough)) else None for it in inner]


def _resolve_top(top):
    """``(top, η)``: a smooth top of index 1 is no interface."""
    if isinstance(top, Smooth) and top.eta == 1.0:
        top = None
    if isinstance(top, (Smooth, Rough)):
        return top, top.eta
    if top is None:
        return None, 1.0
    raise TypeError(f"unknown top interface {top!r}")


def _conductor(bottom, q_bottom, eta_binder, s, info):
    """R^t (all its orders) of a rough conductor bottom under the binder of relative index
    ``eta_binder``, or None for another bottom."""
    if not isinstance(bottom, RoughConductor):
        return None
    Rc, cinfo = itf.rough_conductor(q_bottom, np.asarray(bottom.N, dtype=complex) / eta_binder, bottom.alpha,
                                    tol=s.tol, max_orders=s.order_cap, energy_compensation=bottom.energy_compensation)
    info["bottom"] = {k: v for k, v in cinfo.items() if k != "albedo"}
    return Rc


def _solve_stack(top, slabs, bottom, s, top_cache=None):
    if s.n % 2 or s.n < 2:
        raise ValueError(f"the node count n must be even and ≥ 2 (n/2 per hemisphere), got {s.n}")
    q_out = radau_hemisphere(s.n // 2)
    info = {}
    top, eta = _resolve_top(top)
    chain = binder_chain(top, eta, slabs, q_out, s)
    q_in, q_bottom = chain.rules[0], chain.rules[-1]
    parts = build_parts(slabs, chain, s, info)
    eta_binder = eta * float(np.prod([it.eta for it in slabs if isinstance(it, (InnerSmooth, InnerRough))]))
    Rc = _conductor(bottom, q_bottom, eta_binder, s, info)
    L_rest = [0 if Rc is None else Rc.shape[0], 1] + [p.n_orders for p in parts]
    # over an opaque body without a smooth inner interface, the body reflects nothing beyond its components'
    # orders (a slab's direct beam over a black bottom reflects nothing), so a rough top's inner blocks are
    # needed only below max(L_rest); with threads > 1 the top is built while the body's first orders are solved
    smooth_inside = any(isinstance(p, SmoothInnerPart) for p in parts)
    inner = max(L_rest) if bottom is not None and not smooth_inside else None
    tp = _Top(top, q_out, q_in, s, inner if isinstance(top, Rough) else None, top_cache)

    def total_orders():
        """The stack's order count; waits for the rough top (its own order count is part of it)."""
        L_top = tp.n_orders()
        if tp.job is not None:
            info["top"] = {"orders": L_top}
        return min(max([L_top] + L_rest), s.order_cap)

    # the never-scattered paths (a smooth inner interface's mirror seen through a smooth top or none):
    # taken out before the order choice, put back as a Jackson-smoothed series (flakedb.rt.adding.specular)
    Rs = None if isinstance(top, Rough) or not smooth_inside else specular_reflection(
        parts, lambda R: tp.over()(R, 0, 1))
    if bottom is not None and s.order_tol is not None:
        ob = OrderBlocks(parts, s, tp.over(), q_out.h, q_in.h, q_bottom=q_bottom,
                         albedo=None if Rc is not None else bottom.albedo, Rc=Rc,
                         top_rt=(lambda: tp.rough_layer().Rt) if isinstance(top, Rough) else None,
                         top_rt_writable=top_cache is None,
                         threads=lambda: max(1, s.threads - 1) if tp.busy() else s.threads, specular=Rs)
        Rt, oinfo = ob.solve(q_out.x, q_out.w, total_orders, body_orders=(inner or 0) if isinstance(top, Rough) else None)
        info.update(oinfo)
        Rt = _with_specular(Rt, Rs, info, q_out)
        return StackBSDF(x=q_out.x, w=q_out.w, Rt=Rt, eta=eta, delta_F=tp.delta_F, x_in=q_in.x, w_in=q_in.w,
                         info=info, top_alpha=_top_alpha(top), **_specular_fields(Rs, Rt))
    res = _solve_all_orders(parts, bottom, Rc, tp, total_orders(), Rs, q_out, q_in, q_bottom, eta, s, info)
    res.eta_bottom = float(eta_binder)
    res.top_alpha = _top_alpha(top)
    return res


def _top_alpha(top) -> float:
    """The Beckmann roughness of a rough top (0 for a smooth top or none), as the result records it."""
    return float(top.alpha) if isinstance(top, Rough) else 0.0


def _with_specular(Rt, Rs, info, q_out):
    """The scattered R^t (L, C, h, h) plus the specular matrix as a Jackson-smoothed series of the same
    L orders (:func:`flakedb.rt.adding.specular.smoothed_specular`), with the pole's orders l ≥ 1 zero
    (:func:`flakedb.rt.adding.specular.zero_pole_orders`; a copy first where R^t is a read-only view)."""
    L = Rt.shape[0]
    if Rs is not None:
        Rt = Rt + smoothed_specular(Rs, L)
        m = q_out.w * q_out.x
        info["specular"] = {"albedo_max": float((np.einsum("coi,o->ci", Rs, m) / m[None, :]).max()),
                            "smoothing": f"Jackson kernel of {L} orders"}
    if L > 1 and pole_index(q_out.x) is not None and (np.any(Rt[1:, ..., -1, :]) or np.any(Rt[1:, ..., :, -1])):
        if not Rt.flags.writeable:
            Rt = np.array(Rt)
        zero_pole_orders(Rt, q_out.x, q_out.x)
    return Rt


def _solve_all_orders(parts, bottom, Rc, tp, L, Rs, q_out, q_in, q_bottom, eta, s, info):
    """All orders at once (transmissive stacks, or order_tol None): the body's parts added top-down, the
    bottom, then the top; the specular paths of R^t smoothed as in the opaque path."""
    body = None
    for k, part in enumerate(parts):
        layer = part.block(0, L, max(1, s.threads - 1) if tp.busy() else s.threads)
        body = layer if body is None else add(body, layer)
        s.report("solve", layer=k + 1, layers=len(parts), orders=(0, L), of=L)
    if body is None:
        body = identity_layer(L, q_in.h)
    if Rc is not None:
        body = Layer(*_reflection_over(body, pad_orders(Rc, L)))
    elif bottom is not None:
        body = Layer(*_reflection_over(body, itf.lambertian(q_bottom, bottom.albedo, L).Rt))
    whole = body if tp.top is None else add(tp.block(0, L), body)
    info["orders"] = L
    Rt = whole.Rt if Rs is None else whole.Rt - Rs[None]
    opaque = bottom is not None
    return StackBSDF(
        x=q_out.x, w=q_out.w, Rt=_with_specular(Rt, Rs, info, q_out), eta=eta, delta_F=tp.delta_F,
        Ttb=None if opaque else whole.Ttb, Rb=None if opaque else whole.Rb,
        Tbt=None if opaque else whole.Tbt, x_in=q_bottom.x, w_in=q_bottom.w, info=info,
        **_specular_fields(Rs, whole.Rt),
    )


def _specular_fields(Rs, Rt):
    """``specular`` (C, h, h) and ``specular_orders`` (C,) of a :class:`StackBSDF` whose R^t holds R_s smoothed
    over all its orders."""
    if Rs is None:
        return {}
    C = max(Rs.shape[0], Rt.shape[1])
    return {"specular": np.array(np.broadcast_to(Rs, (C,) + Rs.shape[1:])),
            "specular_orders": np.full(C, Rt.shape[0])}


def _reflection_over(layer, bottom_Rt):
    """(Rt, Ttb, Rb, Tbt) of ``layer`` over an opaque bottom: only Rt survives; the others are zero."""
    Rt = add_reflection_only(layer, bottom_Rt)
    return (Rt,) + tuple(np.zeros((1, 1) + blk.shape[-2:]) for blk in (layer.Ttb, layer.Rb, layer.Tbt))
