"""Mie scattering by homogeneous spheres (Du 2004) and log-normal pigment ensembles.

Conventions are those of :mod:`flakedb.conventions`: complex index ``N = n + i k`` with ``k >= 0``
absorbing (time dependence ``exp(-i ω t)``, Bohren & Huffman's convention), relative index
``m = N_particle / n_binder`` and size parameter ``x = 2π r n_binder / λ_vacuum``; a phase function
is a function of ``mu = cos Θ`` between propagation directions (``mu = 1`` forward) in 1/sr.

Algorithm (H. Du, "Mie-scattering calculation", Appl. Opt. 43, 1951–1956 (2004))
-------------------------------------------------------------------------------
Du writes the Lorenz–Mie coefficients with the ratio ``r_n(z) = ψ_{n-1}(z) / ψ_n(z)`` of Riccati–Bessel
functions (``ψ_n(z) = z j_n(z)``) instead of ``ψ_n(mx)`` itself, which overflows like ``exp(|Im mx|)``
(the logarithmic derivative is ``A_n = ψ_n'/ψ_n = r_n − n/z``)::

    a_n = [F_n ψ_n(x) − ψ_{n-1}(x)] / [F_n ξ_n(x) − ξ_{n-1}(x)],   F_n = r_n(mx)/m + n (1 − 1/m²) / x
    b_n = [G_n ψ_n(x) − ψ_{n-1}(x)] / [G_n ξ_n(x) − ξ_{n-1}(x)],   G_n = m r_n(mx)

(Bohren & Huffman 1983, eq. 4.88 with ``D_n = A_n``; ``ξ_n = ψ_n − i χ_n = x h_n^(1)(x)``).
``r_n(mx)`` comes from the downward recurrence ``r_{n-1} = (2n−1)/z − 1/r_n`` (stable for every
complex ``z``), started at ``n* = max(N, |z| + 4.05 |z|^{1/3} + 16)`` from the value of the continued
fraction ``r_{n*} = (2n*+1)/z − 1/((2n*+3)/z − …)`` evaluated by the modified Lentz method (Lentz,
Appl. Opt. 15, 668 (1976); Thompson & Barnett, J. Comput. Phys. 64, 490 (1986)).  Du starts the same
recurrence at an index chosen from Kapteyn's inequality with ``1/r = 0``; the continued fraction gives
the exact start instead, at a place where it converges in a few dozen steps.

Dividing numerator and denominator by ``ξ_n(x)`` leaves only ratios, so that nothing overflows for
any ``x > 0`` and ``|m|`` (this module's own extension of Du's idea to the ``x`` functions)::

    a_n = T_n (F_n − R_n) / (F_n − Q_n),   b_n = T_n (G_n − R_n) / (G_n − Q_n)
    R_n = ψ_{n-1}(x)/ψ_n(x)   (downward recurrence, as r_n)
    Q_n = ξ_{n-1}(x)/ξ_n(x) = 1 / ((2n−1)/x − Q_{n-1}),  Q_0 = i   (upward: ξ is the dominant solution)
    T_n = ψ_n(x)/ξ_n(x) = T_{n-1} Q_n / R_n,              T_0 = i sin(x) e^{−ix}

Efficiencies (Bohren & Huffman eqs. 4.61, 4.62 and p. 120–122)::

    Q_ext  = (2/x²) Σ (2n+1) Re(a_n + b_n)  = Q_sca + Q_abs
    Q_sca  = (2/x²) Σ (2n+1) (|a_n|² + |b_n|²)
    Q_abs  = (2/x²) Σ (2n+1) [Re a_n − |a_n|² + Re b_n − |b_n|²], each order computed without
             cancellation as (from the Wronskian ψ_n χ_n' − ψ_n' χ_n = −1, A_n = A_n(mx))
             Re a_n − |a_n|² =  Im(m A_n*) / (|ξ_n|² |m ξ_n'/ξ_n − A_n|²)
             Re b_n − |b_n|² = −Im(m A_n)  / (|ξ_n|² |ξ_n'/ξ_n − m A_n|²)
             with ``1/|ξ_n|² = Π_k |Q_k|²`` and ``ξ_n'/ξ_n = Q_n − n/x``.  Summing Re(a_n + b_n)
             directly loses everything for small, weakly absorbing spheres (Re a_n ≈ |a_n|² ≪ |a_n|);
             this way Q_ext = Q_sca exactly for k = 0 and Q_abs keeps full relative accuracy.
    Q_back = |Σ (2n+1) (−1)^n (a_n − b_n)|² / x²  (= 4 |S_1(180°)|² / x²; Bohren & Huffman's Q_b,
             the backscattering cross-section over πr², i.e. 4π times the differential cross-section
             at 180° over πr² — *not* divided by 4π)
    g      = (4 / (x² Q_sca)) Σ [ n(n+2)/(n+1) Re(a_n a*_{n+1} + b_n b*_{n+1}) + (2n+1)/(n(n+1)) Re(a_n b*_n) ]

Amplitudes (Bohren & Huffman eq. 4.74)::

    S_1(μ) = Σ (2n+1)/(n(n+1)) (a_n π_n(μ) + b_n τ_n(μ))
    S_2(μ) = Σ (2n+1)/(n(n+1)) (a_n τ_n(μ) + b_n π_n(μ))

with π_n, τ_n from the upward recurrences of Bohren & Huffman eq. 4.47.  In this (exp(−iωt)) convention
``Re S(0°) = x² Q_ext / 4`` (optical theorem) and, e.g., ``S_1(0°) = 55.8066 + 9.75810i`` for
``m = 0.75, x = 10`` (Du 2004, Table 2); Wiscombe's MIEV0 and ``miepython.S1_S2`` print the complex
conjugate (exp(+iωt)); miepython's ``coefficients`` are ours.

Size-averaged phase function
----------------------------
A pigment's phase function is a weighted sum over its size nodes q of ``|S_1|² + |S_2|²``
(:func:`lognormal_pigment`).  Expanding the squares of the two series and summing over q first::

    Σ_q w_q (|S_1|² + |S_2|²) = Σ_{n,n'} c_n c_n' [U_nn' (π_n π_n' + τ_n τ_n') + V_nn' (π_n τ_n' + τ_n π_n')]
    U_nn' = Σ_q w_q Re(a_n a*_n' + b_n b*_n'),   V_nn' = Σ_q w_q Re(a_n b*_n' + b_n a*_n'),   c_n = (2n+1)/(n(n+1))

(coefficients of a node beyond its own series length are 0).  The angles then meet N² products per band
instead of Q·N terms (Q ≈ 650 nodes, N ≲ 90 orders for a catalogue pigment at 41 bands):
:func:`size_averaged_phase`.  The two forms differ by rounding only (tests/optics/test_mie.py bounds it by
Higham's sum bound; docs/fit-speed.md has the measured differences and times).

Number of terms
---------------
Wiscombe's count ``x + 4.05 x^{1/3} + 2`` leaves relative errors up to 2.3e-6 in ``Q_back`` (and
3e-10 in ``Q_ext``; measured for |m| ≤ 14, x ≤ 1e4) at large ``x``.  The default here,
:func:`default_n_terms` = ``⌊x + 8 x^{1/3}⌋ + 10``, goes on until the terms are far below double precision: beyond ``n ≈ x`` the coefficients decay like
``|ψ_n(x)/ξ_n(x)| ≈ exp(−(4/3) s^{3/2}) / 2`` with ``s = (n + ½ − x)(2/x)^{1/3}`` (Airy asymptotics);
``8 x^{1/3}`` gives ``s ≈ 10``, i.e. terms ~1e-19 of the leading ones, and the ``+ 10`` covers small
``x`` (``a_n ∝ x^{2n+1}``).  Measured: the first omitted term is below 3e-20 of the largest one for
``|m|`` up to 14 and ``x`` from 1e-3 to 1e4; ``tests/test_mie.py`` checks the terms and that 200 more
orders change no result by more than 1e-13 relative.
"""

from __future__ import annotations

import threading
from typing import NamedTuple

import numpy as np

from flakedb.interrupts import deferred

__all__ = [
    "MieEfficiencies",
    "LognormalPigment",
    "mie",
    "mie_Du2004",
    "amplitude",
    "phase_function",
    "lognormal_pigment",
    "default_n_terms",
    "default_n_quad",
    "wiscombe_n_terms",
    "PHASE_NORMS",
]

#: Largest size parameter accepted (a guard against unit mistakes such as a diameter in nm where µm
#: was meant); the algorithm itself is tested up to x = 1e4.
X_MAX = 1.0e6

#: Phase-function normalisations of :func:`phase_function`, each defined by what it integrates to
#: over the sphere (∫ p dΩ).
PHASE_NORMS = {
    "sphere": "1 (units 1/sr; the convention of flakedb.conventions)",
    "albedo": "the single-scattering albedo Q_sca / Q_ext (1/sr)",
    "qsca": "the scattering efficiency Q_sca (1/sr)",
    "4pi": "4π (dimensionless, the astrophysics convention)",
}


class MieEfficiencies(NamedTuple):
    """Result of :func:`mie`: dimensionless efficiencies (cross-section / πr²) and the asymmetry
    parameter, arrays of the broadcast shape of ``m`` and ``x``."""

    qext: np.ndarray  #: extinction efficiency Q_ext
    qsca: np.ndarray  #: scattering efficiency Q_sca
    qback: np.ndarray  #: backscattering efficiency Q_b = 4|S_1(180°)|²/x² (Bohren & Huffman)
    g: np.ndarray  #: asymmetry parameter <cos Θ> (0 where Q_sca = 0)


class LognormalPigment(NamedTuple):
    """Result of :func:`lognormal_pigment`: per-particle optics averaged over the number distribution."""

    c_ext_um2: np.ndarray  #: mean extinction cross-section per particle, µm², shape (W,)
    c_sca_um2: np.ndarray  #: mean scattering cross-section per particle, µm², shape (W,)
    g: np.ndarray  #: asymmetry parameter of the ensemble (C_sca-weighted mean of g), shape (W,)
    mean_volume_um3: float  #: mean particle volume, µm³ (closed form (π/6) d_med³ exp(9 ln²(gsd)/2))
    phase_function: np.ndarray | None  #: C_sca-weighted phase function, 1/sr, shape (W, M); None without mu


# ----------------------------------------------------------------------------------------------
# numba kernels (sequential recurrences over the order n; loops over inputs inside the kernel)
# ----------------------------------------------------------------------------------------------

#: The functions compiled by numba (:func:`_compile_kernels`), callers after callees.
_KERNELS = ("_cf_ratio", "_ratio_down", "_coefficients", "_efficiencies", "_scatter_kernel", "_coefficient_table_kernel",
            "_phase_moments_kernel", "_angular_kernel")
_compiled = False
#: Held while the kernels are replaced: compose's texture thread and its solve may both reach a first Mie
#: evaluation at once (a pigment without a store), and a second replacement would wrap a dispatcher again
#: (numba: "a jit decorator was called on an already jitted function").
_COMPILE_LOCK = threading.Lock()


def _compile_kernels():
    """Replace the plain functions named in :data:`_KERNELS` by their numba dispatchers, once, before the first
    Mie evaluation (under :data:`_COMPILE_LOCK`: any thread may be first): numba is imported here, not with the
    module, so a compose whose pigments come from the store (no Mie series) does not pay its 0.3–0.5 s import.
    Compiled code is cached on disk (``cache=True``)."""
    global _compiled
    if _compiled:
        return
    with _COMPILE_LOCK, deferred():   # numba's import, compilation and cache loading with signals held back
        if _compiled:
            return
        from numba import njit  # lazy: importing numba takes 0.3-0.5 s; only a Mie evaluation needs it

        g = globals()
        for name in _KERNELS:  # a kernel's callees are globals, so they are dispatchers before it compiles
            g[name] = njit(cache=True, error_model="numpy")(g[name])
        _compiled = True



def _cf_ratio(z, n):  # pragma: no cover - compiled
    """r_n(z) = ψ_{n-1}(z)/ψ_n(z) from the continued fraction r_n = (2n+1)/z − 1/r_{n+1} (modified Lentz)."""
    tiny = 1e-300
    inv_z = 1.0 / z
    f = (2.0 * n + 1.0) * inv_z
    if f == 0:
        f = tiny * (1.0 + 0.0 * inv_z)
    c = f
    d = 0.0 * f
    k = n + 1
    for _ in range(100_000_000):
        b = (2.0 * k + 1.0) * inv_z
        d = b - d
        if d == 0:
            d = tiny * (1.0 + 0.0 * inv_z)
        c = b - 1.0 / c
        if c == 0:
            c = tiny * (1.0 + 0.0 * inv_z)
        d = 1.0 / d
        delta = c * d
        f = f * delta
        if abs(delta - 1.0) < 4e-16:
            break
        k += 1
    return f


def _ratio_down(z, n_max, out):  # pragma: no cover - compiled
    """Fill out[1..n_max] with r_n(z) = ψ_{n-1}(z)/ψ_n(z) by downward recurrence (Du 2004), CF start."""
    az = abs(z)
    n_hi = max(n_max, int(az + 4.05 * az ** (1.0 / 3.0) + 16.0))
    r = _cf_ratio(z, n_hi)
    if n_hi <= n_max:
        out[n_hi] = r
    for n in range(n_hi, 1, -1):
        r = (2.0 * n - 1.0) / z - 1.0 / r  # r_{n-1}
        if n - 1 <= n_max:
            out[n - 1] = r


def _coefficients(m, x, n_max, a, b, absn, rz, rx):  # pragma: no cover - compiled
    """Mie coefficients a_n, b_n (n = 1..n_max, stored at index n) in ratio form (module docstring).

    Also fills ``absn[n] = Re(a_n) − |a_n|² + Re(b_n) − |b_n|²``, the absorption of order n, from the
    cancellation-free form derived from the Wronskian ψ_n χ_n' − ψ_n' χ_n = −1 (module docstring).
    """
    _ratio_down(m * x, n_max, rz)
    _ratio_down(x, n_max, rx)
    inv_m = 1.0 / m
    inv_mx = inv_m / x
    fac = (1.0 - inv_m * inv_m) / x
    q = 1j
    t = 1j * np.sin(x) * np.exp(-1j * x)
    xi2_inv = 1.0  # 1/|ξ_n(x)|², |ξ_0| = 1
    for n in range(1, n_max + 1):
        q = 1.0 / ((2.0 * n - 1.0) / x - q)
        rn = rx[n]
        t = t * q / rn
        f = rz[n] * inv_m + n * fac
        g = m * rz[n]
        a[n] = t * (f - rn) / (f - q)
        b[n] = t * (g - rn) / (g - q)
        xi2_inv *= q.real * q.real + q.imag * q.imag
        big_a = rz[n] - n * inv_mx  # A_n(mx) = ψ_n'(mx)/ψ_n(mx)
        dq = q - n / x  # ξ_n'(x)/ξ_n(x)
        ma = m * big_a
        da = m * dq - big_a
        db = dq - ma
        abs_a = (m * np.conj(big_a)).imag / (da.real * da.real + da.imag * da.imag)
        abs_b = -ma.imag / (db.real * db.real + db.imag * db.imag)
        absn[n] = xi2_inv * (abs_a + abs_b)


def _efficiencies(a, b, absn, nn, xp, eff, p):  # pragma: no cover - compiled
    """Q_ext, Q_sca, Q_back, g (module docstring) of one sphere from its coefficients (index n, a[nn + 1] = 0)
    into ``eff[:, p]``."""
    s_abs = 0.0
    s_sca = 0.0
    s_back = 0.0 + 0.0j
    s_g = 0.0
    sign = -1.0
    for n in range(1, nn + 1):
        an = a[n]
        bn = b[n]
        cn = 2.0 * n + 1.0
        s_abs += cn * absn[n]
        s_sca += cn * (an.real * an.real + an.imag * an.imag + bn.real * bn.real + bn.imag * bn.imag)
        s_back += sign * cn * (an - bn)
        sign = -sign
        s_g += cn / (n * (n + 1.0)) * (an.real * bn.real + an.imag * bn.imag)
        an1 = a[n + 1]
        bn1 = b[n + 1]
        s_g += n * (n + 2.0) / (n + 1.0) * (
            an.real * an1.real + an.imag * an1.imag + bn.real * bn1.real + bn.imag * bn1.imag
        )
    x2 = xp * xp
    eff[1, p] = 2.0 * s_sca / x2
    eff[0, p] = eff[1, p] + 2.0 * s_abs / x2
    eff[2, p] = (s_back.real * s_back.real + s_back.imag * s_back.imag) / x2
    eff[3, p] = 4.0 * s_g / (x2 * eff[1, p]) if eff[1, p] > 0.0 else 0.0


def _scatter_kernel(m, x, n_terms, order, starts, mu):  # pragma: no cover - compiled
    """Efficiencies of every (m, x) pair p and amplitudes S1, S2 at the angles order[starts[p]:starts[p+1]]."""
    n_pairs = m.shape[0]
    n_out = mu.shape[0]
    eff = np.zeros((4, n_pairs))
    s1_out = np.zeros(n_out, dtype=np.complex128)
    s2_out = np.zeros(n_out, dtype=np.complex128)
    n_big = 1
    for p in range(n_pairs):
        n_big = max(n_big, n_terms[p])
    a = np.zeros(n_big + 2, dtype=np.complex128)
    b = np.zeros(n_big + 2, dtype=np.complex128)
    rz = np.zeros(n_big + 2, dtype=np.complex128)
    rx = np.zeros(n_big + 2, dtype=np.float64)
    absn = np.zeros(n_big + 2, dtype=np.float64)
    max_ang = 0
    for p in range(n_pairs):
        max_ang = max(max_ang, starts[p + 1] - starts[p])
    u_k = np.zeros(max_ang)
    p_prev = np.zeros(max_ang)
    p_cur = np.zeros(max_ang)
    s1r = np.zeros(max_ang)
    s1i = np.zeros(max_ang)
    s2r = np.zeros(max_ang)
    s2i = np.zeros(max_ang)
    for p in range(n_pairs):
        xp = x[p]
        if xp == 0.0 or m[p] == 1.0:
            continue  # a sphere of zero size or matching its surroundings: everything is 0
        nn = n_terms[p]
        _coefficients(m[p], xp, nn, a, b, absn, rz, rx)
        a[nn + 1] = 0.0
        b[nn + 1] = 0.0
        _efficiencies(a, b, absn, nn, xp, eff, p)
        j0 = starts[p]
        j1 = starts[p + 1]
        n_ang = j1 - j0
        if n_ang == 0:
            continue
        # angles of this pair, processed together so that the loop over them vectorises (SIMD)
        for k in range(n_ang):
            u_k[k] = mu[order[j0 + k]]
            p_prev[k] = 0.0
            p_cur[k] = 1.0
            s1r[k] = 0.0
            s1i[k] = 0.0
            s2r[k] = 0.0
            s2i[k] = 0.0
        for n in range(1, nn + 1):
            fn = (2.0 * n + 1.0) / (n * (n + 1.0))
            car = fn * a[n].real
            cai = fn * a[n].imag
            cbr = fn * b[n].real
            cbi = fn * b[n].imag
            c_tau1 = float(n)
            c_tau2 = n + 1.0
            c_pi1 = (2.0 * n + 1.0) / n
            c_pi2 = (n + 1.0) / n
            for k in range(n_ang):
                pc = p_cur[k]
                pp = p_prev[k]
                uk = u_k[k]
                tau = c_tau1 * uk * pc - c_tau2 * pp
                s1r[k] += car * pc + cbr * tau
                s1i[k] += cai * pc + cbi * tau
                s2r[k] += car * tau + cbr * pc
                s2i[k] += cai * tau + cbi * pc
                p_prev[k] = pc
                p_cur[k] = c_pi1 * uk * pc - c_pi2 * pp
        for k in range(n_ang):
            e = order[j0 + k]
            s1_out[e] = s1r[k] + 1j * s1i[k]
            s2_out[e] = s2r[k] + 1j * s2i[k]
    return eff, s1_out, s2_out


def _phase_moments_kernel(m, x, n_terms, weight, n_max):  # pragma: no cover - compiled
    """The efficiencies (4, W·Q) of every (m_w, x_wq) (as :func:`_scatter_kernel`) and the weighted sums over the size nodes q of each band w of the coefficient products (module docstring,
    "Size-averaged phase function"): U[w, n, n'] = Σ_q weight[w, q] Re(a_n a*_n' + b_n b*_n') and
    V[w, n, n'] = Σ_q weight[w, q] Re(a_n b*_n' + b_n a*_n') (index n − 1), for m (W,), x, n_terms, weight (W, Q)."""
    n_w, n_q = x.shape
    eff = np.zeros((4, n_w * n_q))
    u = np.zeros((n_w, n_max, n_max))
    v = np.zeros((n_w, n_max, n_max))
    a = np.zeros(n_max + 2, dtype=np.complex128)
    b = np.zeros(n_max + 2, dtype=np.complex128)
    rz = np.zeros(n_max + 2, dtype=np.complex128)
    rx = np.zeros(n_max + 2, dtype=np.float64)
    absn = np.zeros(n_max + 2, dtype=np.float64)
    ar = np.zeros(n_max)
    ai = np.zeros(n_max)
    br = np.zeros(n_max)
    bi = np.zeros(n_max)
    for w in range(n_w):
        for q in range(n_q):
            xq = x[w, q]
            if xq == 0.0 or m[w] == 1.0:
                continue  # a sphere of zero size or matching its surroundings scatters nothing
            nn = n_terms[w, q]
            _coefficients(m[w], xq, nn, a, b, absn, rz, rx)
            a[nn + 1] = 0.0
            b[nn + 1] = 0.0
            _efficiencies(a, b, absn, nn, xq, eff, w * n_q + q)
            wq = weight[w, q]
            for n in range(nn):
                ar[n] = a[n + 1].real
                ai[n] = a[n + 1].imag
                br[n] = b[n + 1].real
                bi[n] = b[n + 1].imag
            for n in range(nn):
                wan_r = wq * ar[n]
                wan_i = wq * ai[n]
                wbn_r = wq * br[n]
                wbn_i = wq * bi[n]
                for k in range(n + 1):  # the lower triangle; symmetric
                    u[w, n, k] += wan_r * ar[k] + wan_i * ai[k] + wbn_r * br[k] + wbn_i * bi[k]
                    v[w, n, k] += wan_r * br[k] + wan_i * bi[k] + wbn_r * ar[k] + wbn_i * ai[k]
        for n in range(n_max):
            for k in range(n):
                u[w, k, n] = u[w, n, k]
                v[w, k, n] = v[w, n, k]
    return eff, u, v


def _angular_kernel(mu, n_max):  # pragma: no cover - compiled
    """(2n+1)/(n(n+1)) π_n(μ) and (2n+1)/(n(n+1)) τ_n(μ), n = 1..n_max (rows n − 1), at each μ (M,): the
    upward recurrences of Bohren & Huffman eq. 4.47, as :func:`_scatter_kernel` runs them."""
    n_ang = mu.shape[0]
    pi_c = np.zeros((n_max, n_ang))
    tau_c = np.zeros((n_max, n_ang))
    for k in range(n_ang):
        uk = mu[k]
        pp = 0.0
        pc = 1.0
        for n in range(1, n_max + 1):
            fn = (2.0 * n + 1.0) / (n * (n + 1.0))
            tau = n * uk * pc - (n + 1.0) * pp
            pi_c[n - 1, k] = fn * pc
            tau_c[n - 1, k] = fn * tau
            pn = (2.0 * n + 1.0) / n * uk * pc - (n + 1.0) / n * pp
            pp = pc
            pc = pn
    return pi_c, tau_c


def size_averaged_phase(m, x, weight, mu, n_terms=None):
    """``(efficiencies, phase)``: :func:`mie`'s efficiencies of every (m_w, x_wq) (a :class:`MieEfficiencies` of
    arrays (W, Q)) and Σ_q weight[w, q] (|S_1|² + |S_2|²)(m_w, x_wq; μ) (W, M) for m (W,), x and weight (W, Q),
    μ (M,): the sum over the size nodes taken inside the double series (module docstring, "Size-averaged
    phase function"), so that the angles meet N² products per band instead of Q N terms."""
    m = np.ascontiguousarray(np.asarray(m, dtype=np.complex128))
    x = np.ascontiguousarray(np.asarray(x, dtype=np.float64))
    weight = np.ascontiguousarray(np.broadcast_to(np.asarray(weight, dtype=np.float64), x.shape))
    mb, _, nt, _ = _prepare_mx(m[:, None], x, n_terms)
    nt = np.ascontiguousarray(nt.reshape(x.shape))
    mu = _prepare_mu(mu)
    n_max = int(nt.max())
    _compile_kernels()
    with deferred():   # a signal waits for the compiled call (flakedb.interrupts)
        eff, u, v = _phase_moments_kernel(m, x, nt, weight, n_max)
        pi_c, tau_c = _angular_kernel(np.ascontiguousarray(mu), n_max)
    # Σ_nn' [U_nn' (π_n π_n' + τ_n τ_n') + V_nn' (π_n τ_n' + τ_n π_n')] (the c_n in π_c, τ_c), per band; the
    # bands stacked into the rows of one matrix product each
    n_w, n_ang = u.shape[0], mu.size
    pt = np.concatenate([pi_c, tau_c], axis=1)  # (N, 2M)
    up = (u.reshape(n_w * n_max, n_max) @ pt).reshape(n_w, n_max, 2 * n_ang)
    vt = (v.reshape(n_w * n_max, n_max) @ tau_c).reshape(n_w, n_max, n_ang)
    phase = (np.einsum("wnm,nm->wm", up[:, :, :n_ang], pi_c) + np.einsum("wnm,nm->wm", up[:, :, n_ang:], tau_c)
             + 2.0 * np.einsum("wnm,nm->wm", vt, pi_c))
    return MieEfficiencies(*(e.reshape(x.shape) for e in eff)), phase


def _coefficient_table_kernel(m, x, n_max):  # pragma: no cover - compiled
    """a_n, b_n and the absorption per order for n = 1..n_max of one sphere (testing helper; index 0 is order 1)."""
    a = np.zeros(n_max + 2, dtype=np.complex128)
    b = np.zeros(n_max + 2, dtype=np.complex128)
    rz = np.zeros(n_max + 2, dtype=np.complex128)
    rx = np.zeros(n_max + 2, dtype=np.float64)
    absn = np.zeros(n_max + 2, dtype=np.float64)
    _coefficients(m, x, n_max, a, b, absn, rz, rx)
    return a[1 : n_max + 1].copy(), b[1 : n_max + 1].copy(), absn[1 : n_max + 1].copy()


def _coefficient_table(m, x, n_max):
    """a_n, b_n and the absorption per order for n = 1..n_max of one sphere (testing helper; compiled kernel)."""
    _compile_kernels()
    with deferred():   # a signal waits for the compiled call (flakedb.interrupts)
        return _coefficient_table_kernel(m, x, n_max)


# ----------------------------------------------------------------------------------------------
# input handling
# ----------------------------------------------------------------------------------------------


def wiscombe_n_terms(x):
    """Wiscombe's (1980) series length ``int(x + 4.05 x^{1/3} + 2)`` (about 1e-6 relative accuracy).

    Provided for comparisons (e.g. with miepython, which uses it); not the default here.
    """
    x = np.asarray(x, dtype=np.float64)
    return np.maximum(1, (x + 4.05 * np.cbrt(x) + 2.0).astype(np.int64))


def default_n_terms(x):
    """Series length used by default: ``⌊x + 8 x^{1/3}⌋ + 10`` orders (see the module docstring)."""
    x = np.asarray(x, dtype=np.float64)
    return np.floor(x + 8.0 * np.cbrt(x)).astype(np.int64) + 10


def _prepare_mx(m, x, n_terms):
    m = np.asarray(m, dtype=np.complex128)
    x = np.asarray(x, dtype=np.float64)
    if not np.all(np.isfinite(m)):
        raise ValueError("mie: the relative index m must be finite")
    if np.any(m.imag < 0):
        raise ValueError(
            "mie: Im(m) < 0 found; flakedb uses N = n + ik with k >= 0 absorbing (flakedb.conventions). "
            "If your data use n - ik, pass np.conj(m)."
        )
    if np.any(m == 0):
        raise ValueError("mie: m = 0 is not a material; use a large |m| (e.g. 1e3j) for a perfect conductor")
    if not np.all(np.isfinite(x)) or np.any(x < 0):
        raise ValueError("mie: the size parameter x = 2π r n_binder / λ must be finite and >= 0")
    if np.any(x > X_MAX):
        raise ValueError(
            f"mie: size parameter x = {x.max():.3g} > {X_MAX:g}; check the units "
            "(diameters in µm, wavelengths in nm: x = π d_um n_binder / (wavelength_nm / 1000))"
        )
    shape = np.broadcast_shapes(m.shape, x.shape)
    mb = np.ascontiguousarray(np.broadcast_to(m, shape).ravel())
    xb = np.ascontiguousarray(np.broadcast_to(x, shape).ravel())
    if n_terms is None:
        nt = default_n_terms(xb)
    else:
        nt_in = np.asarray(n_terms)
        if not np.issubdtype(nt_in.dtype, np.integer) or np.any(nt_in < 1):
            raise ValueError("mie: n_terms must be a positive integer (or None for default_n_terms(x))")
        nt = np.ascontiguousarray(np.broadcast_to(nt_in, shape).ravel().astype(np.int64))
    return mb, xb, nt, shape


def _prepare_mu(mu):
    mu = np.asarray(mu, dtype=np.float64)
    if not np.all(np.isfinite(mu)) or np.any(np.abs(mu) > 1.0 + 1e-12):
        raise ValueError("mie: mu = cos(scattering angle) must lie in [-1, 1]")
    return np.clip(mu, -1.0, 1.0)


def _run(m, x, mu, n_terms):
    """Shared driver: efficiencies per (m, x) pair and, if mu is given, S1, S2 on broadcast(m, x, mu)."""
    mb, xb, nt, shape_mx = _prepare_mx(m, x, n_terms)
    n_pairs = mb.size
    if mu is None:
        order = np.zeros(0, dtype=np.int64)
        starts = np.zeros(n_pairs + 1, dtype=np.int64)
        mu_flat = np.zeros(0)
        shape = shape_mx
        idx = None
    else:
        mu = _prepare_mu(mu)
        shape = np.broadcast_shapes(shape_mx, mu.shape)
        idx = np.broadcast_to(np.arange(n_pairs, dtype=np.int64).reshape(shape_mx), shape).ravel()
        mu_flat = np.ascontiguousarray(np.broadcast_to(mu, shape).ravel())
        order = np.argsort(idx, kind="stable").astype(np.int64)
        starts = np.zeros(n_pairs + 1, dtype=np.int64)
        np.cumsum(np.bincount(idx, minlength=n_pairs), out=starts[1:])
    _compile_kernels()
    with deferred():   # a signal waits for the compiled call (flakedb.interrupts)
        eff, s1, s2 = _scatter_kernel(mb, xb, nt, order, starts, mu_flat)
    return eff, s1, s2, shape_mx, shape, idx


# ----------------------------------------------------------------------------------------------
# public API
# ----------------------------------------------------------------------------------------------


def mie_Du2004(m, x, n_terms=None):
    """Mie efficiencies of homogeneous spheres (Du 2004; formulas in the module docstring).

    Parameters
    ----------
    m : complex array_like
        Relative complex index ``N_particle / n_binder`` with ``Im(m) >= 0`` absorbing
        (:mod:`flakedb.conventions`).  Tested for ``|m|`` up to ``|10 + 10i|``.
    x : float array_like
        Size parameter ``2π r n_binder / λ_vacuum`` (dimensionless, ``0 <= x``, tested up to 1e4).
    n_terms : int array_like, optional
        Number of series orders; default :func:`default_n_terms` (converged to double precision).

    Returns
    -------
    MieEfficiencies
        ``qext, qsca, qback, g`` (dimensionless) of the broadcast shape of ``m`` and ``x``.
        ``Q_back = |Σ(2n+1)(−1)^n (a_n − b_n)|² / x²`` (Bohren & Huffman's Q_b).  A sphere that does
        not scatter (``x = 0`` or ``m = 1``) gets ``g = 0``.

    Examples
    --------
    A small sphere scatters as a Rayleigh dipole, Q_sca → (8/3) x⁴ |(m² − 1)/(m² + 2)|²; a large one removes
    twice its geometric cross-section (the extinction paradox, Q_ext → 2):

    >>> m, x = 1.5, 0.01
    >>> rayleigh = 8 / 3 * x**4 * abs((m * m - 1) / (m * m + 2)) ** 2
    >>> round(float(mie_Du2004(m, x).qsca / rayleigh), 4)
    1.0
    >>> round(float(mie_Du2004(1.5, 1000.0).qext), 1)
    2.0
    """
    eff, _, _, shape_mx, _, _ = _run(m, x, None, n_terms)
    return MieEfficiencies(*(eff[i].reshape(shape_mx)[()] for i in range(4)))


#: Alias of :func:`mie_Du2004`.
mie = mie_Du2004


def amplitude(m, x, mu, n_terms=None):
    """Scattering amplitudes ``S_1, S_2`` (Bohren & Huffman eq. 4.74) at ``cos Θ = mu``.

    ``m``, ``x`` and ``mu`` broadcast together (numpy rules): e.g. ``m`` and ``x`` of shape (W, 1) and
    ``mu`` of shape (M,) give (W, M).  The coefficients of each distinct (m, x) element are computed
    once.  Convention exp(−iωt): ``Re S_1(1) = Re S_2(1) = x² Q_ext / 4`` (optical theorem); Wiscombe's
    MIEV0 and miepython print the complex conjugate.  Dimensionless (the far field is
    ``E_s ∝ S e^{ikr} / (−ikr)``).

    Returns
    -------
    (S1, S2) : complex ndarrays of the broadcast shape.
    """
    if mu is None:
        raise ValueError("amplitude: mu (cosine of the scattering angle) is required")
    _, s1, s2, _, shape, _ = _run(m, x, mu, n_terms)
    return s1.reshape(shape)[()], s2.reshape(shape)[()]


def phase_function(m, x, mu, norm="sphere", n_terms=None):
    """Unpolarised Mie phase function ``p(mu) = (|S_1|² + |S_2|²) / (2π x² Q_sca)`` in 1/sr.

    ``m``, ``x`` and ``mu = cos Θ`` (``mu = 1`` forward) broadcast as in :func:`amplitude`.
    ``norm`` selects what ``p`` integrates to over the sphere (``∫ p dΩ``), see :data:`PHASE_NORMS`:

    * ``"sphere"`` (default): 1 — the phase function of :mod:`flakedb.conventions`;
    * ``"albedo"``: ``Q_sca / Q_ext``;
    * ``"qsca"``: ``Q_sca``, i.e. ``(|S_1|² + |S_2|²) / (2π x²)`` = dC_sca/dΩ / (πr²);
    * ``"4pi"``: 4π (dimensionless).

    Raises ValueError for a sphere that does not scatter (``x = 0`` or ``m = 1``) unless ``norm="qsca"``.
    """
    if norm not in PHASE_NORMS:
        raise ValueError(f"phase_function: norm={norm!r}; choose one of {sorted(PHASE_NORMS)}")
    eff, s1, s2, _, shape, idx = _run(m, x, mu, n_terms)
    xb = np.broadcast_to(np.asarray(x, dtype=np.float64), np.broadcast_shapes(np.shape(m), np.shape(x))).ravel()
    x_e = xb[idx]
    with np.errstate(divide="ignore", invalid="ignore"):
        p_qsca = (np.abs(s1) ** 2 + np.abs(s2) ** 2) / (2.0 * np.pi * x_e**2)
    p_qsca = np.where(x_e > 0, p_qsca, 0.0)
    if norm == "qsca":
        p = p_qsca
    else:
        qsca = eff[1][idx]
        if np.any(qsca <= 0):
            raise ValueError(
                f"phase_function: norm={norm!r} needs a sphere that scatters, but Q_sca = 0 "
                "(x = 0 or m = 1) for some inputs; use norm='qsca' for the unnormalised function"
            )
        p = p_qsca / qsca
        if norm == "albedo":
            p = p * (qsca / eff[0][idx])
        elif norm == "4pi":
            p = p * (4.0 * np.pi)
    return p.reshape(shape)[()]


#: Default node spacing of the size quadrature, in size parameter, at the upper edge of the bulk of the
#: C_sca-weighted distribution (see :func:`lognormal_pigment`): finer than the Mie ripple (Δx ≈ 1).
_DX_QUAD = 0.15


def _lognormal_range(sigma, n_sigma):
    """Integration range in u = ln(d/d_med): ``[−n_sigma σ, n_sigma σ + 6σ²]``.

    ``6σ²`` is where the integrand of the steepest moment in use peaks (Rayleigh scattering,
    C_sca ∝ d⁶, shifts the d⁶-weighted log-normal by 6σ²; geometric optics, C ∝ d², by 2σ²), so every
    moment up to d⁶ is covered to ``n_sigma`` standard deviations on both sides.
    """
    return -n_sigma * sigma, n_sigma * sigma + 6.0 * sigma**2


def _lognormal_nodes(median_diameter_um, sigma, n_quad, n_sigma):
    """Nodes d_i (µm) and weights w_i of the number-weighted log-normal: trapezoidal rule in u = ln(d/d_med).

    The weights include the normal density of u (σ = ln gsd) and are not renormalised: their sum is
    1 − (mass outside the range) (≈ 1 − 3e-7 at n_sigma = 5).  The trapezoidal rule is spectrally
    accurate for smooth integrands that are negligible at both ends (Trefethen & Weideman, SIAM Rev. 56,
    385 (2014)) and, unlike Gauss–Legendre, spaces its nodes evenly, which is what the Mie ripple needs.
    """
    if sigma == 0.0:
        return np.array([median_diameter_um]), np.array([1.0])
    if n_quad < 2:
        raise ValueError("lognormal_pigment: n_quad must be >= 2 for gsd > 1")
    lo, hi = _lognormal_range(sigma, n_sigma)
    u = np.linspace(lo, hi, n_quad)
    w = np.full(n_quad, (hi - lo) / (n_quad - 1))
    w[0] *= 0.5
    w[-1] *= 0.5
    w *= np.exp(-0.5 * (u / sigma) ** 2) / (np.sqrt(2.0 * np.pi) * sigma)
    return median_diameter_um * np.exp(u), w


def default_n_quad(k_max_um, median_diameter_um, gsd, n_sigma=5.0):
    """Default node count of :func:`lognormal_pigment`'s size quadrature.

    ``max(128, ⌈(u_hi − u_lo) x_ref / 0.15⌉ + 1)`` with ``x_ref = k_max d_med exp(3σ + 6σ²)`` the size
    parameter (``k_max = π n_binder / λ`` largest over the bands, 1/µm) at the upper edge of the bulk of
    the most size-weighted integrand: nodes 0.15 apart in x there, finer than the Mie ripple.
    """
    sigma = float(np.log(gsd))
    if sigma == 0.0:
        return 1
    lo, hi = _lognormal_range(sigma, n_sigma)
    x_ref = float(k_max_um) * float(median_diameter_um) * np.exp(3.0 * sigma + 6.0 * sigma**2)
    return max(128, int(np.ceil((hi - lo) * x_ref / _DX_QUAD)) + 1)


def lognormal_pigment(
    m, wavelength_nm, n_binder, median_diameter_um, gsd, mu=None, n_quad=None, n_sigma=5.0, n_terms=None
):
    """Optics of a pigment with a number-weighted log-normal size distribution, per particle.

    The number density of diameters is log-normal: ``ln d ~ Normal(ln d_med, ln² gsd)``.  Averages are
    ``<C> = ∫ C(d) f(d) dd`` (µm² per particle) by the trapezoidal rule in ``u = ln(d/d_med)``
    over ``[−n_sigma σ, n_sigma σ + 6σ²]`` (σ = ln gsd; see :func:`_lognormal_range`,
    :func:`_lognormal_nodes`).

    Parameters
    ----------
    m : complex array_like, shape () or (W,)
        Relative index ``N_particle / n_binder`` per band (**not** the particle's own index),
        ``Im(m) >= 0`` absorbing (:mod:`flakedb.conventions`).
    wavelength_nm : float array_like, shape () or (W,)
        Vacuum wavelengths, nm.
    n_binder : float array_like, shape () or (W,)
        Real index of the binder the particles sit in; size parameter ``x = π d n_binder / λ``.
    median_diameter_um : float
        Median diameter of the number distribution, µm.
    gsd : float
        Geometric standard deviation ``exp(σ)`` (>= 1; 1 is monodisperse).
    mu : float array_like, shape (M,), optional
        ``cos Θ`` at which to return the ensemble phase function.
    n_quad : int, optional
        Quadrature nodes; default :func:`default_n_quad` (nodes 0.15 apart in size parameter where the
        weight is, finer than the Mie ripple).  Measured against 2-4x the nodes: strongly absorbing
        pigments (Im m ≳ 0.1) converge to ~1e-9, weakly absorbing ones (Im m ~ 0.01) to ~1e-5 in the
        cross-sections and ~1e-4 in the phase function; lossless spheres (k = 0) have resonances
        narrower than any affordable grid and converge slowly (~3e-4 in C_sca, up to ~1e-2 in the
        phase function at some angles; see tests/test_mie.py).  Pass a larger n_quad where that matters.
    n_sigma : float
        Half-width of the quadrature range in units of σ (tail mass beyond it ~ 3e-7 at 5).
    n_terms : optional
        Passed to :func:`mie` (default: converged series).

    Returns
    -------
    LognormalPigment
        ``c_ext_um2``, ``c_sca_um2`` (µm², number-averaged), ``g`` (C_sca-weighted), ``mean_volume_um3``
        (closed form ``(π/6) d_med³ exp(4.5 σ²)``) and, when ``mu`` is given, the C_sca-weighted phase
        function ``p(mu) = Σ w C_sca,i p_i(mu) / Σ w C_sca,i`` (1/sr, ∫ p dΩ = 1) of shape (W, M).
    """
    m = np.asarray(m, dtype=np.complex128)
    lam = np.asarray(wavelength_nm, dtype=np.float64)
    nb = np.asarray(n_binder, dtype=np.float64)
    if m.ndim > 1 or lam.ndim > 1 or nb.ndim > 1:
        raise ValueError("lognormal_pigment: m, wavelength_nm and n_binder must be scalars or 1-D (W,)")
    shape = np.broadcast_shapes(m.shape, lam.shape, nb.shape)
    if not np.all(lam > 0) or not np.all(nb > 0):
        raise ValueError("lognormal_pigment: wavelength_nm and n_binder must be > 0")
    d_med = float(median_diameter_um)
    if not d_med > 0:
        raise ValueError(f"lognormal_pigment: median_diameter_um = {median_diameter_um}, must be > 0 (µm)")
    if not gsd >= 1.0:
        raise ValueError(f"lognormal_pigment: gsd = {gsd}, the geometric standard deviation must be >= 1")
    sigma = float(np.log(gsd))
    mW = np.broadcast_to(m, shape).reshape(-1)
    lamW = np.broadcast_to(lam, shape).reshape(-1)
    nbW = np.broadcast_to(nb, shape).reshape(-1)
    k_um = np.pi * nbW / (lamW * 1e-3)  # x = k_um * d_um
    if n_quad is None:
        n_quad = default_n_quad(np.max(k_um), d_med, gsd, n_sigma)
    n_quad = int(n_quad)
    d, w = _lognormal_nodes(d_med, sigma, n_quad, n_sigma)
    area = 0.25 * np.pi * d**2  # µm²
    x = k_um[:, None] * d[None, :]  # (W, Q)
    mm = mW[:, None]
    if mu is None:
        eff = mie(mm, x, n_terms=n_terms)
        qext, qsca, g = eff.qext, eff.qsca, eff.g
        phase = None
    else:
        mu = np.asarray(mu, dtype=np.float64)
        if mu.ndim != 1:
            raise ValueError("lognormal_pigment: mu must be 1-D (M,)")
        # Σ_q w_q area_q p_qsca,q(μ), p_qsca = (|S_1|² + |S_2|²) / (2π x²) (phase_function's "qsca" norm)
        eff, phase = size_averaged_phase(mW, x, (w * area)[None, :] / (2.0 * np.pi * x**2), mu, n_terms)
        qext, qsca, g = eff.qext, eff.qsca, eff.g
    c_ext = (qext * area) @ w
    c_sca = (qsca * area) @ w
    g_mean = (g * qsca * area) @ w / c_sca
    if phase is not None:
        phase = phase / c_sca[:, None]
        phase = phase.reshape(shape + mu.shape)
    mean_volume = np.pi / 6.0 * d_med**3 * np.exp(4.5 * sigma**2)
    return LognormalPigment(
        c_ext.reshape(shape)[()], c_sca.reshape(shape)[()], g_mean.reshape(shape)[()], float(mean_volume), phase
    )
