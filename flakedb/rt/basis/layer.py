"""Scattering matrices of layers, the adding equations and doubling (paper eq. 3–4, docs/model.md §4).

A :class:`Layer` holds, for every Fourier order l and spectral channel c, the four blocks

* ``Rt``  (top reflection):       down-going light entering at the top → up-going light leaving the top,
* ``Ttb`` (top → bottom):         down-going at the top → down-going leaving the bottom,
* ``Rb``  (bottom reflection):    up-going entering at the bottom → down-going leaving the bottom,
* ``Tbt`` (bottom → top):         up-going entering at the bottom → up-going leaving the top,

each of shape (L, C, h_out, h_in) indexed ``[l, c, o, i]`` by the *positive* cosines of the
quadrature of the side the light leaves (o) and enters (i).  The normalisation is the one of
:mod:`flakedb.conventions` ("Scattering matrices"): a block maps the cosine-series coefficients of
(basic) radiance on the nodes, so an empty layer is exactly the identity and the adding equations
are plain matrix products.  Channel axes of size 1 broadcast.

Everything is batched over (L, C): one LAPACK call per step, no Python loop over orders or channels.
"""

from dataclasses import dataclass

import numpy as np

from flakedb.conventions import fourier_weight
from flakedb.rt.common.jobs import thread_pool


@dataclass
class Layer:
    """The four blocks of a layer (above).  A symmetric layer's bottom blocks may be its top ones
    (the same arrays): blocks are never written in place."""

    Rt: np.ndarray
    Ttb: np.ndarray
    Rb: np.ndarray
    Tbt: np.ndarray

    @property
    def n_orders(self):
        return self.Rt.shape[0]

    def truncated(self, L):
        """The first ``L`` orders (no copy)."""
        return Layer(self.Rt[:L], self.Ttb[:L], self.Rb[:L], self.Tbt[:L])


def identity_layer(L, h, C=1):
    """An empty layer: R = 0, T = I in every order."""
    eye = np.broadcast_to(np.eye(h), (L, C, h, h)).copy()
    zero = np.zeros((L, C, h, h))
    return Layer(zero, eye, zero.copy(), eye.copy())


def pad_orders(a, L):
    """Pad a block (orders on axis 0) with zero orders up to L: for blocks that are genuinely zero
    beyond their own order count (an order-limited interface, a stack truncated at its order count)."""
    if a.shape[0] >= L:
        return a
    pad = np.zeros((L - a.shape[0],) + a.shape[1:])
    return np.concatenate([a, pad], axis=0)


def solve_regular(A, B):
    """``np.linalg.solve(A, B)`` for the adding equations' A = I − R1 R2, where a row of A that vanishes
    exactly gets a unit diagonal first.  Such a row is a direction totally reflected on both sides of a
    binder that holds no slab (between a smooth top and a less dense binder, or between two inner
    interfaces, docs/model.md §4 "Inner interface"): nothing enters it (its row of B and its column in
    the transmissions around it are 0), so the unit diagonal only keeps the solve regular and changes
    no result."""
    dead = ~np.any(A, axis=-1)
    if dead.any():
        A = A + dead[..., :, None] * np.eye(A.shape[-1])
    return np.linalg.solve(A, B)


def add(top, bottom):
    """Stack ``top`` above ``bottom`` (paper eq. 4, docs/model.md §4), with solves instead of inverses.

        T^tb = T2^tb (I − R1^b R2^t)^{-1} T1^tb
        R^t  = R1^t + T1^bt R2^t (I − R1^b R2^t)^{-1} T1^tb
        T^bt = T1^bt (I − R2^t R1^b)^{-1} T2^bt
        R^b  = R2^b + T2^tb R1^b (I − R2^t R1^b)^{-1} T2^bt

    Both layers must have the same number of orders (the caller pads with :func:`pad_orders`
    only for blocks that are genuinely zero beyond their order count, i.e. interfaces and media
    carry their own diagonal direct terms in every order).

    Adding an empty layer (:func:`identity_layer`) above or below a layer leaves it unchanged:

    >>> rng = np.random.default_rng(0)
    >>> X = Layer(*(rng.uniform(0.0, 0.2, (2, 1, 3, 3)) for _ in range(4)))     # (L, C, h, h) blocks
    >>> for Y in (add(identity_layer(2, 3), X), add(X, identity_layer(2, 3))):
    ...     print(all(np.allclose(getattr(Y, b), getattr(X, b), rtol=0, atol=1e-15) for b in ("Rt", "Ttb", "Rb", "Tbt")))
    True
    True
    """
    h = top.Rb.shape[-1]
    eye = np.eye(h)
    A = eye - top.Rb @ bottom.Rt  # (L, C, h, h)
    X = solve_regular(A, top.Ttb)  # (I − R1b R2t)^{-1} T1tb
    Ttb = bottom.Ttb @ X
    Rt = top.Rt + top.Tbt @ (bottom.Rt @ X)
    B = eye - bottom.Rt @ top.Rb
    Y = solve_regular(B, bottom.Tbt)
    Tbt = top.Tbt @ Y
    Rb = bottom.Rb + bottom.Ttb @ (top.Rb @ Y)
    return Layer(Rt, Ttb, Rb, Tbt)


def add_reflection_only(top, bottom_Rt):
    """Top reflection of ``top`` over an opaque bottom with top reflection ``bottom_Rt``.

    The first line of :func:`add`'s equations only: R^t = R1^t + T1^bt R2^t (I − R1^b R2^t)^{-1} T1^tb.
    """
    h = top.Rb.shape[-1]
    A = np.eye(h) - top.Rb @ bottom_Rt
    X = solve_regular(A, top.Ttb)
    return top.Rt + top.Tbt @ (bottom_Rt @ X)


#: Bytes of one matrix stack that :func:`_double_symmetric_serial` doubles at a time: the chunk's
#: working arrays stay in cache across all doublings, and the block inverse's calls are shared by
#: enough matrices that two threads do not wait on each other (measured at h = 69, 256 matrices, 8
#: doublings: 512 KiB 25.3 / 30.9 GFLOP/s on one / two threads, 2 MiB 24.5 / 38.1).
DOUBLING_CHUNK_BYTES = 2**21
#: Below this size :func:`_block_inverse` inverts with LAPACK (``np.linalg.inv``).
BLOCK_INVERSE_LEAF = 16
#: :func:`_solve_near_identity` solves a matrix again with LAPACK's pivoted solve when its probe residual
#: max|A (X v) − B v| exceeds this times max|B| · Σ|v|.
BLOCK_INVERSE_RESIDUAL = 1e-14


def _block_inverse(A):
    """Inverses of a stack of matrices by 2 × 2 block recursion on the Schur complement, without
    pivoting: inv(A) = [[B + C S⁻¹ D, −C S⁻¹], [−S⁻¹ D, S⁻¹]], B = A11⁻¹, C = B A12, D = A21 B,
    S = A22 − A21 C (Golub & Van Loan, *Matrix Computations*, 4th ed., §3.2.11): nearly all the work is
    batched matrix products.  For matrices near the identity only (:func:`_solve_near_identity`)."""
    n = A.shape[-1]
    if n <= BLOCK_INVERSE_LEAF:
        return np.linalg.inv(A)
    m = n // 2
    B = _block_inverse(A[..., :m, :m])
    C = B @ A[..., :m, m:]
    Si = _block_inverse(A[..., m:, m:] - A[..., m:, :m] @ C)
    D = A[..., m:, :m] @ B
    out = np.empty_like(A)
    np.matmul(C, Si, out=out[..., :m, m:])
    np.negative(out[..., :m, m:], out=out[..., :m, m:])
    np.matmul(Si, D, out=out[..., m:, :m])
    np.negative(out[..., m:, :m], out=out[..., m:, :m])
    np.matmul(out[..., :m, m:], D, out=out[..., :m, :m])
    np.subtract(B, out[..., :m, :m], out=out[..., :m, :m])
    out[..., m:, m:] = Si
    return out


def _solve_near_identity(A, B):
    """X = A⁻¹ B for the doubling's A = I − R R.  R is a passive layer's reflection, so A is close to
    the identity and elimination needs no pivoting; the block inverse's batched products run near the
    matmul rate where LAPACK's pivoted solve of 69 × 69 systems with 69 right-hand sides reaches about a
    sixth of it (its triangular solves: docs/model.md §4, "Doubling").  Every matrix is checked with one
    probe vector v (two matrix-vector products): where max|A (X v) − B v| > ``BLOCK_INVERSE_RESIDUAL``
    · max|B| · Σ|v|, or anything is not finite, that matrix is solved again by ``np.linalg.solve``
    (partial pivoting).  Each matrix's result depends on that matrix alone (chunking and threads do not
    change a bit)."""
    X = _block_inverse(A) @ B
    v = (np.cos(np.arange(1, B.shape[-1] + 1) * 0.7548776662466927) + 1.5)[:, None]  # fixed, entries in [0.5, 2.5]
    res = np.abs(A @ (X @ v) - B @ v).max(axis=(-2, -1))
    bad = ~(res <= BLOCK_INVERSE_RESIDUAL * np.abs(B).max(axis=(-2, -1)) * np.abs(v).sum())
    if bad.any():
        X[bad] = np.linalg.solve(A[bad], B[bad])
    return X


def _double_symmetric_serial(R, T, times):
    """:func:`double_symmetric` on one thread.  The (L, C) batch is doubled in chunks of
    ``DOUBLING_CHUNK_BYTES // (8 h²)`` matrices, all ``times`` doublings per chunk, in place in
    preallocated buffers (``np.matmul(..., out=)``): the same LAPACK/BLAS calls on the same matrices as
    the whole-batch form, so the result is bit-identical to it, without streaming the batch through
    memory in every step (measured in bench/bench_rt_core.py, ``_doubling_rate``)."""
    times = int(times)
    if times <= 0:
        return R, T
    shape = np.broadcast_shapes(R.shape, T.shape)
    h = shape[-1]
    Rout = np.array(np.broadcast_to(R, shape), dtype=float, order="C")
    Tout = np.array(np.broadcast_to(T, shape), dtype=float, order="C")
    Rf, Tf = Rout.reshape((-1, h, h)), Tout.reshape((-1, h, h))
    N = Rf.shape[0]
    k = max(1, min(N, DOUBLING_CHUNK_BYTES // (8 * h * h)))
    A, Y, Z = (np.empty((k, h, h)) for _ in range(3))
    idx = np.arange(h)
    for s in range(0, N, k):
        e = min(N, s + k)
        r, t, a, y, z = Rf[s:e], Tf[s:e], A[:e - s], Y[:e - s], Z[:e - s]
        for _ in range(times):
            np.matmul(r, r, out=a)  # A = I − R R
            np.negative(a, out=a)
            a[:, idx, idx] += 1.0
            x = _solve_near_identity(a, t)  # X = (I − R R)⁻¹ T
            np.matmul(r, x, out=y)
            np.matmul(t, y, out=z)
            r += z  # R' = R + T R X
            np.matmul(t, x, out=y)
            t[...] = y  # T' = T X
    return Rout, Tout


def double_symmetric(R, T, times, threads=1):
    """Double a top/bottom-symmetric layer ``times`` times (R^t = R^b = R, T^tb = T^bt = T).

    add(S, S) for a symmetric S: X = (I − R R)^{-1} T; T' = T X; R' = R + T R X.  One solve and
    three products per doubling.  Orders and channels are independent: with ``threads`` > 1 the
    (L, C) batch is split into that many parts doubled in parallel threads (numpy's LAPACK and BLAS
    calls release the GIL; the caller keeps BLAS itself at one thread per call, see
    :func:`flakedb.rt.adding.stack.solve_stack`).  The result is bit-identical to the serial one.
    """
    L, C = R.shape[:2]
    threads = int(threads)
    if threads <= 1 or times <= 0 or L * C < 2 * threads:
        return _double_symmetric_serial(R, T, times)
    Rf = R.reshape((L * C,) + R.shape[2:])
    Tf = np.broadcast_to(T, R.shape).reshape(Rf.shape)
    parts = np.array_split(np.arange(L * C), threads)
    pool = thread_pool(threads, "flakedb-slab")
    futs = [pool.submit(_double_symmetric_serial, Rf[p[0]:p[-1] + 1], Tf[p[0]:p[-1] + 1], times) for p in parts]
    res = [f.result() for f in futs]
    return (np.concatenate([r for r, _ in res]).reshape(R.shape),
            np.concatenate([t for _, t in res]).reshape(R.shape))


def thin_slab_diamond(x, w, sigma_t, K_T, K_R, dz_um, l0=0):
    """Symmetric scattering matrices of a thin homogeneous slab by the diamond (trapezoid) start.

    Parameters
    ----------
    x, w : (h,) positive quadrature nodes and weights of the medium's hemisphere rule.
    sigma_t : (C, h) extinction σ_t(μ) in 1/µm at the nodes (even in μ).
    K_T : (L, C, h, h) cosine coefficients k_l of the scattering kernel σ_s f_p (1/(µm·sr)) for
        down-going → down-going light, indexed [l, c, o, i] by the positive cosines.
    K_R : (L, C, h, h) the same for down-going → up-going light.
        The medium is assumed symmetric under z → −z (true for flake normal densities with
        D(m) = D(−m) and for phase-function media), so up→up = K_T and up→down = K_R.
    dz_um : slice thickness in µm.
    l0 : the Fourier order of the first entry of K_T, K_R (blocks of orders l0 … l0 + L − 1).

    The radiative transfer equation for order l on the nodes reads (z down, paper eq. 1 and 3)
        dI⁺/dz = −α I⁺ + β I⁻,   −dI⁻/dz = −α I⁻ + β I⁺,
    with α = M⁻¹(Σ_t − c_l K_T W), β = M⁻¹ c_l K_R W, M = diag(μ), W = diag(w).  Integrating
    both across the slice with the trapezoid rule ("diamond" initialisation, Wiscombe 1976) and
    solving the two-point problem gives R = (G₁ − G₂)/2 and T = (G₁ + G₂)/2 with
    G₁ = (I + a − b)⁻¹(I − a + b), G₂ = (I + a + b)⁻¹(I − a − b), a = α Δz/2, b = β Δz/2.
    The trapezoid rule keeps every linear invariant of the ODE, so a conservative medium conserves
    flux exactly; the error is O(Δz³) per slice (second order overall; measured in the tests).
    """
    L = K_T.shape[0]
    h = len(x)
    cl = fourier_weight(np.arange(l0, l0 + L))[:, None, None, None]
    inv_mu = (1.0 / x)[:, None]  # rows: outgoing node
    a = (0.5 * dz_um) * inv_mu * (-cl * K_T * w[None, :])
    diag = (0.5 * dz_um) * sigma_t / x  # (C, h)
    idx = np.arange(h)
    a = np.broadcast_to(a, np.broadcast_shapes(a.shape, (L, diag.shape[0], h, h))).copy()
    a[..., idx, idx] += diag[None]
    b = (0.5 * dz_um) * inv_mu * (cl * K_R * w[None, :])
    eye = np.eye(h)
    G1 = np.linalg.solve(eye + a - b, eye - a + b)
    G2 = np.linalg.solve(eye + a + b, eye - a - b)
    return 0.5 * (G1 - G2), 0.5 * (G1 + G2)


def slice_doublings(thickness_um, sigma_t_max_per_um, slice_tau=2.0**-7):
    """Number of doublings n so that the first slice has optical thickness ≤ ``slice_tau``.

    The slice thickness is thickness / 2ⁿ.  The diamond start is second order: measured on an HG
    slab (τ = 2, g = 0.7, albedo 0.9, n = 32) against slice τ = 2⁻²⁰, the albedo error is 1.2e-5,
    7.5e-7, 4.7e-8, 2.9e-9 for first-slice τ = 2⁻⁴, 2⁻⁶, 2⁻⁸, 2⁻¹⁰ (16× per two doublings).  The
    default 2⁻⁷ (≈ 2e-7) sits well below the angular discretisation error.  Tested in
    tests/test_rt_solver.py (``test_pure_absorber_direct_beam_and_doubling_convergence``).
    """
    tau = float(thickness_um) * float(sigma_t_max_per_um)
    if tau <= slice_tau:
        return 0
    return int(np.ceil(np.log2(tau / slice_tau)))


def eigen_slab(x, w, sigma_t, K_T, K_R, thickness_um, l0=0):
    """Symmetric R, T of a homogeneous slab from the eigenvectors of the discrete-ordinate equations
    (the exact solution of the equations :func:`thin_slab_diamond` integrates; docs/model.md §4,
    "Homogeneous slabs").

    With α, β as in :func:`thin_slab_diamond` (dI⁺/dz = −α I⁺ + β I⁻, dI⁻/dz = α I⁻ − β I⁺), a
    solution (G⁺, G⁻) e^{−kz} has u = G⁺ + G⁻ an eigenvector of (α + β)(α − β) with eigenvalue k²
    and G⁺ − G⁻ = k (α + β)⁻¹ u.  A reciprocal kernel (K symmetric) makes √(wμ)-scaled α ± β
    symmetric: with S± = M^{−1/2}(Σ − c_l D(K_T ∓ K_R)D)M^{−1/2} (D = diag √w, M = diag μ) and
    S₊ = L Lᵀ, the eigenproblem is the symmetric Lᵀ S₋ L z = k² z (one batched ``eigh``); u = V⁻¹ L z
    and (α + β)⁻¹ u = V⁻¹ L⁻ᵀ z with V = diag √(wμ).  The slab's modes decaying from the top,
    (G⁺, G⁻) e^{−kz}, and from the bottom, (G⁻, G⁺) e^{−k(d−z)}, meet the boundary conditions
    (incident light at the top, none from below) through the sum and difference of their amplitudes:

        R = (Y₁ + Y₂)/2,  T = (Y₁ − Y₂)/2,
        Y₁ = [U(1+E) − kP(1−E)] [U(1+E) + kP(1−E)]⁻¹,
        Y₂ = [U(1−E)/k − P(1+E)] [U(1−E)/k + P(1+E)]⁻¹,

    with U, P the columns u, (α + β)⁻¹ u, E = diag e^{−kd}: only decaying exponentials, and
    (1 − E)/k = d (1 − e^{−kd})/(kd) finite at k = 0, so thick slabs and conservative media
    (k = 0 at order 0) need no special case.  Raises ``np.linalg.LinAlgError`` when S₊ is not
    positive definite (not a physical medium); :func:`homogeneous_slab` then doubles instead.
    Cost: one ``eigh``, one Cholesky and three solves per (order, channel), independent of the
    thickness — doubling needs a solve and three products per doubling (7–14 for paint layers).
    """
    L, h = K_T.shape[0], K_T.shape[-1]
    C = max(K_T.shape[1], K_R.shape[1], np.atleast_2d(sigma_t).shape[0])
    K_T = np.broadcast_to(K_T, (L, C, h, h))
    K_R = np.broadcast_to(K_R, (L, C, h, h))
    d = float(thickness_um)
    cl = fourier_weight(np.arange(l0, l0 + L))[:, None, None, None]
    sw = np.sqrt(w)
    sig = np.broadcast_to(np.atleast_2d(sigma_t), (C, h))
    outer = (sw / np.sqrt(x))[:, None] * (sw / np.sqrt(x))[None, :]  # D M^{−1/2} on both sides
    KT = cl * K_T * outer
    KR = cl * K_R * outer
    idx = np.arange(h)
    Sp = KR - KT
    Sm = -(KT + KR)
    Sp[..., idx, idx] += sig / x
    Sm[..., idx, idx] += sig / x
    Lc = np.linalg.cholesky(0.5 * (Sp + np.swapaxes(Sp, -1, -2)))
    lam, Z = np.linalg.eigh(np.swapaxes(Lc, -1, -2) @ (0.5 * (Sm + np.swapaxes(Sm, -1, -2))) @ Lc)
    k = np.sqrt(np.clip(lam, 0.0, None))  # (L, C, h)
    vinv = (1.0 / np.sqrt(w * x))[:, None]
    U = vinv * (Lc @ Z)
    P = vinv * np.linalg.solve(np.swapaxes(Lc, -1, -2), Z)
    kd = k * d
    E = np.exp(-kd)
    with np.errstate(divide="ignore", invalid="ignore"):
        one_minus_E_over_k = d * np.where(kd > 1e-8, -np.expm1(-kd) / kd, 1.0 - 0.5 * kd)
    Ep, Em = (1.0 + E)[..., None, :], (1.0 - E)[..., None, :]
    kP = k[..., None, :] * P
    Uk = U * one_minus_E_over_k[..., None, :]

    def right_solve(num, den):  # num · den⁻¹
        return np.swapaxes(np.linalg.solve(np.swapaxes(den, -1, -2), np.swapaxes(num, -1, -2)), -1, -2)

    Y1 = right_solve(U * Ep - kP * Em, U * Ep + kP * Em)
    Y2 = right_solve(Uk - P * Ep, Uk + P * Ep)
    return 0.5 * (Y1 + Y2), 0.5 * (Y1 - Y2)


#: Largest relative asymmetry max|K − Kᵀ| / max|K| of a kernel block that :func:`eigen_slab` accepts
#: (it symmetrises; stored float32 factors are symmetric to ~1e-7); beyond it the slab is doubled.
EIGEN_SYMMETRY_TOL = 1e-6


def _kernel_range(K_T, K_R):
    """[max K_T, min K_T, max K_R, min K_R] (a NaN propagates)."""
    return np.array([K_T.max(), K_T.min(), K_R.max(), K_R.min()])


def _symmetric_kernels(K_T, K_R, extent=None):
    """max |K − Kᵀ| ≤ EIGEN_SYMMETRY_TOL · max |K| over both blocks (``extent``: their
    :func:`_kernel_range` if known).  K − Kᵀ is antisymmetric, so its largest entry is its largest
    magnitude (no abs pass); one buffer serves both differences."""
    extent = _kernel_range(K_T, K_R) if extent is None else extent
    scale = np.max(np.append(np.abs(extent), 1e-300))  # np.max: a NaN propagates
    buf = np.empty(np.broadcast_shapes(K_T.shape, K_R.shape))
    asym = []
    for K in (K_T, K_R):
        np.subtract(K, np.swapaxes(K, -1, -2), out=buf)
        asym.append(buf.max())
    return bool(np.max(asym) <= EIGEN_SYMMETRY_TOL * scale)


def _eigen_slab_threads(x, w, sigma_t, K_T, K_R, thickness_um, l0, threads):
    """:func:`eigen_slab` split over ``threads`` threads by orders, or by channels when there are
    fewer orders than 2 × threads (LAPACK releases the GIL; BLAS runs one thread per call)."""
    L = K_T.shape[0]
    C = max(K_T.shape[1], K_R.shape[1], np.atleast_2d(sigma_t).shape[0])
    threads = int(threads)
    if threads <= 1 or max(L, C) < 2 * threads:
        return eigen_slab(x, w, sigma_t, K_T, K_R, thickness_um, l0)
    pool = thread_pool(threads, "flakedb-slab")
    if L >= 2 * threads:
        parts = [p for p in np.array_split(np.arange(L), threads) if p.size]
        futs = [pool.submit(eigen_slab, x, w, sigma_t, K_T[p[0]:p[-1] + 1], K_R[p[0]:p[-1] + 1], thickness_um,
                            l0 + int(p[0])) for p in parts]
        axis = 0
    else:
        sig = np.broadcast_to(np.atleast_2d(sigma_t), (C, len(x)))
        K_T = np.broadcast_to(K_T, (L, C) + K_T.shape[2:])
        K_R = np.broadcast_to(K_R, (L, C) + K_R.shape[2:])
        parts = [p for p in np.array_split(np.arange(C), threads) if p.size]
        futs = [pool.submit(eigen_slab, x, w, sig[p[0]:p[-1] + 1], K_T[:, p[0]:p[-1] + 1], K_R[:, p[0]:p[-1] + 1],
                            thickness_um, l0) for p in parts]
        axis = 1
    res = [f.result() for f in futs]
    return np.concatenate([r for r, _ in res], axis=axis), np.concatenate([t for _, t in res], axis=axis)


def homogeneous_slab(x, w, sigma_t, K_T, K_R, thickness_um, slice_tau=2.0**-7, l0=0, threads=1, method="eigen"):
    """A homogeneous slab of the given thickness: by default the exact eigen-solution of its
    discrete-ordinate equations (:func:`eigen_slab`); with ``method="doubling"`` (or when the kernel
    is not reciprocal to :data:`EIGEN_SYMMETRY_TOL`, or the eigen-solution fails or is not finite)
    a diamond start and symmetric doubling (second order in the slice, :func:`slice_doublings`).

    Orders whose kernel vanishes (beyond the kernel's own count) carry only the direct beam, whose
    transmission exp(−σ_t Δz/μ) is diagonal and exact; they are not stored (the caller pads).
    Returns a :class:`Layer` with L = K_T.shape[0] orders (orders l0 … l0 + L − 1); ``threads``:
    parallel threads over orders (eigen) or over the (orders, channels) batch (doubling).
    """
    sigma_t = np.atleast_2d(sigma_t)
    extent = _kernel_range(K_T, K_R) if K_T.size and K_R.size else np.zeros(4)
    if np.all(extent == 0.0):  # a pure absorber: the exact diagonal attenuation
        C = max(sigma_t.shape[0], K_T.shape[1])
        return direct_only_orders(x, sigma_t, thickness_um, K_T.shape[0], C)
    if method not in ("eigen", "doubling"):
        raise ValueError(f"method = {method!r}: 'eigen' or 'doubling'")
    if method == "eigen" and _symmetric_kernels(K_T, K_R, extent):
        try:
            with np.errstate(over="ignore", under="ignore"):
                R, T = _eigen_slab_threads(x, w, sigma_t, K_T, K_R, thickness_um, l0, threads)
            # a sum is finite only if every entry is (NaN and ±inf propagate; R, T are bounded, so a
            # finite sum does not overflow): one reduction instead of an isfinite pass per block
            if np.isfinite(R.sum() + T.sum()):
                return Layer(R, T, R, T)  # symmetric: bottom blocks are the top ones (never written in place)
        except np.linalg.LinAlgError:
            pass
    n = slice_doublings(thickness_um, sigma_t.max(), slice_tau)
    dz = thickness_um / 2.0**n
    R, T = thin_slab_diamond(x, w, sigma_t, K_T, K_R, dz, l0)
    R, T = double_symmetric(R, T, n, threads)
    return Layer(R, T, R, T)


def direct_only_orders(x, sigma_t, thickness_um, L, C):
    """Blocks of orders with no scattering: R = 0, T = diag(exp(−σ_t d / μ)).  Shape (L, C, h, h).

    The direct beam is the same in every order and up and down: the blocks are read-only broadcast
    views of one (1, C, h, h) transmission and one zero block (no memory per order)."""
    sigma_t = np.broadcast_to(np.atleast_2d(sigma_t), (C, len(x)))
    h = len(x)
    t = np.exp(-sigma_t * thickness_um / x)  # (C, h)
    T = np.zeros((1, C, h, h))
    idx = np.arange(h)
    T[..., idx, idx] = t[None]
    T = np.broadcast_to(T, (L, C, h, h))
    R = np.broadcast_to(np.zeros((1, 1, h, h)), (L, C, h, h))
    return Layer(R, T, R, T)


def extend_orders(layer, L, x=None, sigma_t=None, thickness_um=None):
    """Extend a layer to L orders.  For a medium slab, orders beyond its kernel's count are pure
    attenuation (pass ``x``, ``sigma_t``, ``thickness_um``); for an interface that is not
    order-limited the caller must build all orders itself."""
    L0 = layer.n_orders
    if L0 >= L:
        return layer.truncated(L)
    C = layer.Rt.shape[1]
    if sigma_t is None:
        raise ValueError("extend_orders needs the medium's sigma_t and thickness for the direct orders")
    extra = direct_only_orders(x, sigma_t, thickness_um, L - L0, max(C, np.atleast_2d(sigma_t).shape[0]))

    def cat(a, b):
        shape = np.broadcast_shapes(a.shape[1:], b.shape[1:])
        return np.concatenate([np.broadcast_to(a, a.shape[:1] + shape), np.broadcast_to(b, b.shape[:1] + shape)])

    return Layer(cat(layer.Rt, extra.Rt), cat(layer.Ttb, extra.Ttb), cat(layer.Rb, extra.Rb), cat(layer.Tbt, extra.Tbt))
