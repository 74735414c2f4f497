"""The solver's result as the file's table: the one stack → :class:`~flakedb.bsdf.table.BSDFTable`
conversion (compose, the Monte Carlo tests and the benchmarks all go through it).

Node layout (conventions: μ > 0 travels down): the table's nodes are ``[-x_h … -x_1,
x_1 … x_h]`` with x the solver's air-side nodes.  Reflection from above (incident μ_i = +x_j,
outgoing μ_o = −x_k) holds ``f_l(x_j → x_k) · x_k``, the coefficients of f·|μ_o|
(docs/bsdf-format.md, "Evaluation").  An opaque paint has nothing else.  A transmissive stack whose
binder side uses the air-side nodes (index-matched, or under a rough top) also fills transmission
from above (+x_j → +x_k) and reflection and transmission from below, from the solver's other
blocks, in basic radiance: the file's ``eta`` tells a renderer to scale transmitted values by η² or
1/η² (docs/bsdf-format.md, "Renderer mapping").  The unscattered transmitted beam stays in the
transmission blocks as the solver carries it (the attenuated identity: a spike on the quadrature
diagonal, in every order), as layerlab's files do.  An opaque paint's table is given as its
reflection quadrant alone (:attr:`BSDFTable.reflection_only`).
"""

from __future__ import annotations

import numpy as np

from flakedb.bsdf.table import BSDFTable
from flakedb.conventions import fourier_weight


def stack_to_table(stack, channels=None, eta=None, alpha=None, delta="auto", metadata=None) -> BSDFTable:
    """:class:`BSDFTable` of a solved stack (:class:`flakedb.rt.adding.stack.StackBSDF`).

    ``channels``: names (default by count, :class:`BSDFTable`); ``eta``: the header's relative index
    (default the stack's); ``alpha``: the top's Beckmann roughness (informational; default the solved stack's
    ``top_alpha``); ``delta``: the
    analytic mirror term (``"auto"``: ``{"kind": "fresnel", "eta": η}`` when the stack has a smooth
    top's delta term, else None); ``metadata``: str → JSON-able.

    A white furnace: a lossless slab over a white primer under a smooth coat.  The table carries the
    diffuse part, the coat's mirror reflection F(θ) travels as the delta term; together they return all
    the light (to the Catmull-Rom integration of the table's albedo, 2e-4 at n = 16):

    >>> import flakedb
    >>> from flakedb.optics.fresnel import fresnel_dielectric
    >>> from flakedb.rt.scattering.media import PhaseMedium
    >>> from flakedb.rt.adding.stack import Lambertian, Slab, Smooth, SolverSettings
    >>> slab = Slab(2.0, PhaseMedium(sigma_t_per_um=1.0, albedo=1.0, phase=("hg", 0.6)))
    >>> table = stack_to_table(flakedb.solve_stack(Smooth(1.5), [slab], Lambertian(1.0), SolverSettings(n=16)))
    >>> table.delta, table.n
    ({'kind': 'fresnel', 'eta': 1.5}, 16)
    >>> down = table.mu > 0
    >>> total = table.albedo()[0, down] + fresnel_dielectric(table.mu[down], 1.5).R
    >>> bool(np.all(np.abs(total - 1.0) < 1e-3))
    True
    """
    x = np.asarray(stack.x, float)
    h = x.size
    n = 2 * h
    if eta is None:
        eta = stack.eta
    if alpha is None:
        alpha = getattr(stack, "top_alpha", 0.0)
    if isinstance(delta, str) and delta == "auto":
        delta = {"kind": "fresnel", "eta": float(stack.eta)} if stack.delta_F is not None else None
    kw = dict(mu=np.concatenate([-x[::-1], x]), eta=float(eta), alpha=(float(alpha), 0.0), delta=delta,
              metadata=dict(metadata or {}), channels=None if channels is None else tuple(channels))
    if stack.Ttb is None:  # an opaque paint: the reflection quadrant alone
        C = stack.Rt.shape[1] if channels is None else len(channels)
        return BSDFTable(reflection=_reflection_quadrant(stack.Rt, x, stack.w, C), **kw)
    # a transmissive stack: all four quadrants
    if stack.x_in is None or stack.x_in.shape != x.shape or not np.allclose(stack.x_in, x, rtol=0, atol=1e-14):
        raise ValueError("a transmissive table needs the same nodes above and below (index-matched stack)")
    blocks = {b: stack.f_coefficients(b) for b in ("Rt", "Ttb", "Rb", "Tbt")}
    C = max(b.shape[1] for b in blocks.values()) if channels is None else len(channels)
    L = max(b.shape[0] for b in blocks.values())

    def block(name, up_going):
        """(C, h_i, h_o, L) of f·|μ_o|; ``up_going``: outgoing nodes in the table's order for μ_o < 0
        (−x_{h−1} … −x_0, reversed), else +x_0 … +x_{h−1}.  Written in place (no (L, C, h, h) temporary)."""
        f = blocks[name]                                   # (L_b, C|1, h_o, h_i)
        xo = x[::-1] if up_going else x
        if up_going:
            f = f[:, :, ::-1]
        grey = f.shape[1] == 1 or f.strides[1] == 0       # one channel for all (a grey stack solved once)
        if grey:
            f = f[:, :1]
        v = np.zeros((1 if grey else C, h, h, L))
        np.multiply(f, xo[None, None, :, None], out=np.transpose(v[..., : f.shape[0]], (3, 0, 2, 1)))
        return np.broadcast_to(v, (C, h, h, L)) if grey else v

    coeffs = np.zeros((C, n, n, L))
    lo, hi = slice(0, h), slice(h, n)  # table indices of −x_{h−1} … −x_0 and of +x_0 … +x_{h−1}
    coeffs[:, hi, lo] = block("Rt", True)
    coeffs[:, hi, hi] = block("Ttb", False)
    coeffs[:, lo, hi] = block("Rb", False)[:, ::-1]   # incident −x_j: rows reversed too
    coeffs[:, lo, lo] = block("Tbt", True)[:, ::-1]
    return BSDFTable(coeffs=coeffs, **kw)


def _reflection_quadrant(S, x, w, C):
    """The reflection quadrant (C, h_i, h_o, L) of an opaque stack's R^t ``S`` (L, C|1, h_o, h_i):
    f·|μ_o| = S_l[o, i] |μ_o| / (c_l w_i μ_i) (conventions), outgoing nodes reversed (the table's −x
    order), written straight into the table's layout a few incident nodes at a time (a cache-blocked
    transpose: one pass, one array).  A grey stack solved once (a channel-broadcast R^t) stays one
    channel, broadcast to C."""
    grey = S.shape[1] > 1 and S.strides[1] == 0
    if grey:
        S = S[:, :1]
    L, Cs, h, _ = S.shape
    f2d = (x[::-1][:, None] / (w * x)[None, :]) / fourier_weight(1)   # |μ_o| / (c_l w_i μ_i), l ≥ 1
    v = np.empty((Cs, h, h, L))
    Sr = S[:, :, ::-1]
    for i0 in range(0, h, 8):                                      # 8 incident nodes: one cache line of S
        i1 = min(h, i0 + 8)
        blk = v[:, i0:i1]
        np.multiply(np.transpose(Sr[..., i0:i1], (1, 3, 2, 0)), f2d[:, i0:i1].T[None, :, :, None], out=blk)
        blk[..., 0] *= fourier_weight(1) / fourier_weight(0)      # c_0 = 2π
    return np.broadcast_to(v, (C,) + v.shape[1:]) if grey else v
