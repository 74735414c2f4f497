"""Coherent thin-film stacks by the characteristic-matrix (transfer-matrix) method.

Born & Wolf, *Principles of Optics*, 7th ed., §1.6.2-1.6.3: a film ``j`` of complex index ``N_j``
and thickness ``d_j`` has the characteristic matrix

    M_j = [[cos δ_j,          -(i / p_j) sin δ_j],
           [-i p_j sin δ_j,    cos δ_j          ]],     δ_j = k0 d_j q_j,   k0 = 2π / λ_vacuum,

with ``q_j = N_j cos θ_j = sqrt(N_j² - β²)`` (``β = n_ambient sin θ``, Snell's invariant) and the
admittance ``p_j = q_j`` (s, TE) or ``p_j = q_j / N_j²`` (p, TM, magnetic-field amplitudes).  The
stack is ``M = M_1 M_2 ... M_F`` (film 1 faces the ambient) and, with ``B = m11 + m12 p_e``,
``C = m21 + m22 p_e`` (B&W §1.6.3),

    r = (B p_a - C) / (B p_a + C),      t = 2 p_a / (B p_a + C),

``p_a``, ``p_e`` the admittances of the ambient and exit media.  The power transmittance (with the
``Re(n cos θ)`` factors, for s and p alike) is ``T = |t|² Re(p_e) / p_a``; ``A = 1 - R - T``.

Numerical stability.  ``cos δ`` and ``sin δ`` overflow for thick absorbing films (``Im δ`` of a 1 µm
Al film is ~ 90).  Each ``M_j`` is therefore multiplied by ``exp(i δ_j)`` (``|exp(i δ_j)| <= 1``
because ``Im q_j >= 0`` is chosen: the matrix is even in ``q_j``, so either branch is exact), which
makes every element a bounded function of ``z = 2 i δ_j`` (``Re z <= 0``):

    e^{iδ} cos δ = 1 + expm1(z)/2,   e^{iδ}(-i sin δ / p) = -i k0 d E(z) · {1, N²},
    e^{iδ}(-i p sin δ) = -p expm1(z)/2,         E(z) = expm1(z)/z (E(0) = 1),

(the ``{1, N²}`` factor for s, p).  ``r`` is a ratio and does not see the scale; ``t`` and ``T``
carry it as ``exp(i Σ δ_j)``, which underflows gracefully to 0.  The ``E(z)`` form removes the
``sin δ / q`` singularity at ``q = 0`` (a film at its own critical angle).  Unlike the interface
(Rouard / Airy) recursion, no interface coefficient appears between films, so there is no pole
inside the stack; ``B p_a + C`` vanishes only at exactly grazing incidence (``p_a = 0``) on a
stack that is invisible there (e.g. no films and ``n_exit == n_ambient``), where the limit
``R = 0, T = 1`` is returned.  Grazing incidence otherwise gives ``r = -1`` (to rounding), and total
internal reflection into the exit medium gives ``T = 0`` exactly (``Re p_e = 0``).

Conventions: :mod:`flakedb.conventions` (``N = n + ik``, ``k >= 0`` absorbing, ``exp(-iωt)``),
which are also those of S. Byrnes' ``tmm`` package; wavelengths are vacuum wavelengths in nm and
film thicknesses are in nm.  Amplitude coefficients follow :mod:`flakedb.optics.fresnel`.
"""

from typing import NamedTuple

import numpy as np

from flakedb.optics.fresnel import normal_wavevector

__all__ = [
    "ThinFilmRT",
    "ThinFilmAmplitudes",
    "FlakeRT",
    "thin_film_transfer_matrix",
    "thin_film_amplitudes",
    "flake_reflectance_transmittance",
    "lognormal_thickness_nodes",
    "thickness_nodes_needed",
    "thin_film_thickness_average",
    "incoherent_substrate_flake",
]


class ThinFilmRT(NamedTuple):
    """Power reflectance / transmittance / absorptance of a stack, each of shape (W, A)."""

    R_s: np.ndarray
    R_p: np.ndarray
    T_s: np.ndarray
    T_p: np.ndarray
    R: np.ndarray  #: unpolarised (R_s + R_p) / 2
    T: np.ndarray  #: unpolarised (T_s + T_p) / 2
    A: np.ndarray  #: unpolarised absorptance 1 - R - T (0 up to rounding for lossless stacks)


class ThinFilmAmplitudes(NamedTuple):
    """Complex electric-field amplitude coefficients of a stack, each of shape (W, A).

    Same conventions as ``tmm.coh_tmm``'s ``r`` and ``t`` (and :func:`fresnel_amplitudes` for a
    single interface); ``t`` is referred to the exit side of the last interface.
    """

    r_s: np.ndarray
    r_p: np.ndarray
    t_s: np.ndarray
    t_p: np.ndarray


class FlakeRT(NamedTuple):
    """Unpolarised reflectance and transmittance of a flake embedded in its binder, shape (W, A)."""

    R: np.ndarray
    T: np.ndarray


def _as_index(name, value, W):
    """A real or complex index given as a scalar or per wavelength, returned as complex (W, 1)."""
    arr = np.asarray(value)
    if arr.ndim == 0:
        arr = np.broadcast_to(arr, (W,))
    if arr.shape != (W,):
        raise ValueError(f"{name} must be a scalar or have shape (W,) = ({W},), got shape {arr.shape}.")
    arr = arr.astype(complex)
    if np.any(~np.isfinite(arr)):
        raise ValueError(f"{name} contains non-finite values.")
    if np.any(arr.imag < 0):
        raise ValueError(
            f"{name} has k < 0: flakedb uses N = n + ik with k >= 0 absorbing (flakedb.conventions)."
        )
    if np.any(arr == 0):
        raise ValueError(f"{name} contains a zero refractive index; every index must have |N| > 0.")
    return arr[:, None]


def _prepare(n_films, d_films_nm, wavelength_nm, cos_theta, n_ambient, n_exit):
    """Validated ``n (W, F), d (F,), wl (W,), cos (A,), n_a (W, 1), n_e (W, 1)`` (complex indices)."""
    wl = np.atleast_1d(np.asarray(wavelength_nm, dtype=float))
    if wl.ndim != 1 or np.any(~(wl > 0)) or np.any(~np.isfinite(wl)):
        raise ValueError("wavelength_nm must be a 1-D array (W,) of finite vacuum wavelengths > 0 in nm.")
    W = wl.shape[0]
    cos = np.atleast_1d(np.asarray(cos_theta, dtype=float))
    if cos.ndim != 1:
        raise ValueError(f"cos_theta must be a 1-D array (A,), got shape {cos.shape}.")
    if np.any(~np.isfinite(cos)) or np.any(cos < 0) or np.any(cos > 1 + 1e-12):
        raise ValueError(
            "cos_theta must lie in [0, 1]: it is the cosine of the angle of incidence in the ambient "
            "medium (light always enters from the ambient side; reverse the stack for the other side)."
        )
    # Clip rounding above 1; flush cosines below 1e-150 to 0 (grazing): this changes R and T by
    # O(cos), far below double precision, and keeps subnormal numbers out of complex divisions.
    cos = np.where(cos < 1e-150, 0.0, np.minimum(cos, 1.0))
    d = np.atleast_1d(np.asarray(d_films_nm, dtype=float))
    if d.ndim != 1 or np.any(~np.isfinite(d)) or np.any(d < 0):
        raise ValueError("d_films_nm must be a 1-D array (F,) of finite thicknesses >= 0 in nm.")
    F = d.shape[0]
    n = np.asarray(n_films)
    if n.ndim == 1:
        n = np.broadcast_to(n, (W, n.shape[0]))
    if n.shape != (W, F):
        raise ValueError(
            f"n_films must have shape (F,) = ({F},) or (W, F) = ({W}, {F}) to match d_films_nm and "
            f"wavelength_nm, got shape {np.shape(n_films)}."
        )
    n = n.astype(complex)
    if np.any(~np.isfinite(n)):
        raise ValueError("n_films contains non-finite values.")
    if np.any(n.imag < 0):
        j = int(np.nonzero((n.imag < 0).any(axis=0))[0][0])
        raise ValueError(
            f"n_films[:, {j}] has k < 0: flakedb uses N = n + ik with k >= 0 absorbing "
            "(flakedb.conventions); pass the complex conjugate."
        )
    if np.any(n == 0):
        raise ValueError("n_films contains a zero refractive index; every index must have |N| > 0.")
    n_a = _as_index("n_ambient", n_ambient, W)
    if np.any(n_a.imag != 0) or np.any(n_a.real <= 0):
        raise ValueError("n_ambient must be real and > 0 (light enters from a transparent binder).")
    n_e = n_a if n_exit is None else _as_index("n_exit", n_exit, W)
    return n, d, wl, cos, n_a, n_e


def _stack(n, d, wl, cos, n_a, n_e):
    """Scaled characteristic-matrix product and the ambient/exit admittances.

    ``d`` is (F,) (one thickness per film) or (F, K) (K thicknesses per film: the nodes of
    :func:`thin_film_thickness_average`, a K axis between the wavelength and angle axes).

    Returns ``B, C, p_a, p_e, phase`` with a leading polarisation axis (0: s, 1: p) on B, C, p_a,
    p_e (shape (2, W, A), or (2, W, K, A)) and ``phase = Σ δ_j`` (shape (W, A) or (W, K, A)), see the
    module docstring.
    """
    m, phase = _product(n, d, wl, cos, n_a)
    return _close(m, wl, cos, n_a, n_e, d.ndim - 1) + (phase,)


def _product(n, d, wl, cos, n_a):
    """The scaled matrices ``(m11, m12, m21, m22)`` of the films' product ``M_1 … M_F``, each (2, W, [K,] A),
    and ``Σ δ_j`` (W, [K,] A); ``d`` (F,) or (F, K) as :func:`_stack`.  F = 0 gives the identity."""
    W, A = wl.shape[0], cos.shape[0]
    extra = d.shape[1:]  # () or (K,)
    one = (1,) * len(extra)
    k0 = (2.0 * np.pi / wl).reshape((W,) + one + (1,))  # 1/nm
    cos_c = cos.reshape((1,) + one + (A,))
    n_a = n_a.reshape((W,) + one + (1,))
    shape = (2, W) + extra + (A,)
    m11 = np.ones(shape, complex)
    m12 = np.zeros(shape, complex)
    m21 = np.zeros(shape, complex)
    m22 = np.ones(shape, complex)
    phase = np.zeros(shape[1:], complex)
    for j in range(d.shape[0]):  # a loop over the few films; everything inside is vectorised
        N = n[:, j].reshape((W,) + one + (1,))
        N2 = N * N
        q = normal_wavevector(N, n_a, cos_c)  # (W, 1.., A), Im q >= 0: independent of the thickness
        kd = k0 * d[j].reshape(extra + (1,))  # (W, K.., 1)
        delta = kd * q
        phase = phase + delta
        z = 2j * delta  # Re z <= 0
        ex = np.expm1(z)
        small = np.abs(z) < 1e-6  # E(z) = expm1(z)/z by its Taylor series there (error < 1e-25)
        z_safe = np.where(small, 1.0, z)
        E = np.where(small, 1.0 + z * (0.5 + z / 6.0), ex / z_safe)
        a = 1.0 + 0.5 * ex  # e^{iδ} cos δ
        g = np.stack([q, q / N2])  # admittances p_j for s, p
        b = -1j * kd * E * np.stack([np.ones_like(N2), N2])  # e^{iδ}(-i sin δ / p_j)
        c = -0.5 * g * ex  # e^{iδ}(-i p_j sin δ)
        m11, m12, m21, m22 = _matmul((m11, m12, m21, m22), (a, b, c, a))
    return (m11, m12, m21, m22), phase


def _matmul(m, f):
    """The 2×2 product ``m f`` of matrices given as (11, 12, 21, 22) element arrays (broadcast)."""
    m11, m12, m21, m22 = m
    f11, f12, f21, f22 = f
    return m11 * f11 + m12 * f21, m11 * f12 + m12 * f22, m21 * f11 + m22 * f21, m21 * f12 + m22 * f22


def _close(m, wl, cos, n_a, n_e, n_extra):
    """``B, C, p_a, p_e`` (B&W §1.6.3) of a product ``m`` (:func:`_product`) with ``n_extra`` node axes."""
    W, A = wl.shape[0], cos.shape[0]
    one = (1,) * n_extra
    cos_c = cos.reshape((1,) + one + (A,))
    n_a = n_a.reshape((W,) + one + (1,))
    n_e = n_e.reshape((W,) + one + (1,))
    p_a_s = n_a.real * cos_c  # real
    p_a = np.stack([p_a_s, cos_c / n_a.real])
    q_e = normal_wavevector(n_e, n_a, cos_c)
    p_e = np.stack([q_e, q_e / (n_e * n_e)])
    m11, m12, m21, m22 = m
    return m11 + m12 * p_e, m21 + m22 * p_e, p_a, p_e


def _solve(B, C, p_a):
    """r and the denominator D = B p_a + C, with the invisible-stack limit where D == 0."""
    D = B * p_a + C
    invisible = D == 0  # only at p_a == 0 (grazing) on a stack invisible there: limit r = 0
    D_safe = np.where(invisible, 1.0, D)
    r = np.where(invisible, 0.0, (B * p_a - C) / D_safe)
    return r, D_safe, invisible


def _power(n, d, wl, cos, n_a, n_e):
    """:class:`ThinFilmRT` of validated inputs (:func:`_prepare`); ``d`` (F,) or (F, K) (then each array is (W, K, A))."""
    return _power_of(*_stack(n, d, wl, cos, n_a, n_e))


def _power_of(B, C, p_a, p_e, phase):
    """:class:`ThinFilmRT` from :func:`_stack`'s ``B, C, p_a, p_e, phase``."""
    r, D, invisible = _solve(B, C, p_a)
    R_pol = np.abs(r) ** 2
    # T = |2 p_a e^{iΣδ} / D|² Re(p_e) / p_a, written without dividing by p_a (0 at grazing).
    atten = np.exp(-2.0 * phase.imag)  # |e^{iΣδ}|², <= 1; underflows to 0 for opaque stacks
    absD = np.abs(D)  # split the division: |D|² alone can underflow when cos_theta ~ 1e-160
    T_pol = np.where(invisible, 1.0, 4.0 * (p_a / absD) * (p_e.real / absD) * atten)
    T_pol = np.maximum(T_pol, 0.0)  # Re p_e >= 0 analytically; guard -0.0 from rounding
    R_s, R_p = R_pol[0], R_pol[1]
    T_s, T_p = T_pol[0], T_pol[1]
    R = 0.5 * (R_s + R_p)
    T = 0.5 * (T_s + T_p)
    return ThinFilmRT(R_s, R_p, T_s, T_p, R, T, 1.0 - R - T)


def thin_film_transfer_matrix(n_films, d_films_nm, wavelength_nm, cos_theta, n_ambient, n_exit=None):
    """Reflectance, transmittance and absorptance of a coherent multilayer (Born & Wolf §1.6).

    Parameters
    ----------
    n_films : array_like, complex, shape (F,) or (W, F)
        Complex indices ``n + ik`` (k >= 0) of the films, top (facing the ambient) to bottom,
        constant or per wavelength.  ``F = 0`` is a bare ambient/exit interface.
    d_films_nm : array_like, shape (F,)
        Physical film thicknesses in nm (>= 0; any thickness, opaque metal films included).
    wavelength_nm : array_like, shape (W,)
        Vacuum wavelengths in nm.
    cos_theta : array_like, shape (A,)
        Cosine of the angle of incidence in the ambient medium, in [0, 1] (0: grazing; values
        below 1e-150 are treated as 0, which changes R and T by less than 1e-150).
    n_ambient : float or array_like (W,)
        Real index of the transparent medium the light comes from (the flake's binder).
    n_exit : None, scalar or array_like (W,), optional
        Index of the semi-infinite exit medium (complex allowed, k >= 0).  Default: ``n_ambient``
        (a flake embedded in its binder).

    Returns
    -------
    ThinFilmRT
        ``R_s, R_p, T_s, T_p, R, T, A``, each of shape (W, A).  ``T`` is the power transmitted into
        the exit medium per unit incident power, ``T = |t|² Re(p_e)/p_a`` (``Re(n cos θ)`` factors
        for s and p; for an absorbing exit medium, the power crossing the last interface).
        ``R + T + A = 1``; ``A`` is 0 to rounding for lossless stacks.  Finite for every input,
        including grazing incidence (``R = 1`` unless the stack is invisible there) and TIR into
        the exit medium (``T = 0``).

    Examples
    --------
    A film of zero thickness is the bare interface (R = 0.04 from air to glass at normal incidence); a
    quarter-wave film of index √1.5 cancels that reflection at its design wavelength:

    >>> rt = thin_film_transfer_matrix([2.0], [0.0], [550.0], [1.0], 1.0, 1.5)
    >>> round(float(rt.R[0, 0]), 12), round(float(rt.T[0, 0]), 12)
    (0.04, 0.96)
    >>> n = 1.5 ** 0.5
    >>> rt = thin_film_transfer_matrix([n], [550.0 / (4 * n)], [550.0], [1.0], 1.0, 1.5)
    >>> round(float(rt.R[0, 0]), 12), round(float(rt.T[0, 0]), 12)
    (0.0, 1.0)
    """
    n, d, wl, cos, n_a, n_e = _prepare(n_films, d_films_nm, wavelength_nm, cos_theta, n_ambient, n_exit)
    return _power(n, d, wl, cos, n_a, n_e)


def thin_film_amplitudes(n_films, d_films_nm, wavelength_nm, cos_theta, n_ambient, n_exit=None):
    """Complex amplitude coefficients ``r_s, r_p, t_s, t_p`` of a multilayer, shape (W, A) each.

    Same arguments and method as :func:`thin_film_transfer_matrix` (Born & Wolf §1.6.3).  The
    p coefficients are electric-field ratios (``t_p = t_H · n_ambient / N_exit``), matching
    :func:`flakedb.optics.fresnel.fresnel_amplitudes` for a bare interface and ``tmm.coh_tmm``.
    """
    n, d, wl, cos, n_a, n_e = _prepare(n_films, d_films_nm, wavelength_nm, cos_theta, n_ambient, n_exit)
    B, C, p_a, p_e, phase = _stack(n, d, wl, cos, n_a, n_e)
    r, D, invisible = _solve(B, C, p_a)
    t = np.where(invisible, 1.0, 2.0 * p_a * np.exp(1j * phase) / D)
    t_p = t[1] * (n_a / n_e)
    return ThinFilmAmplitudes(r[0], r[1], t[0], t_p)


def flake_reflectance_transmittance(n_films, d_films_nm, wavelength_nm, cos_theta, n_binder):
    """Unpolarised R(c, λ) and T(c, λ) of an interference flake embedded in its binder (docs/model.md §3, §6).

    The flake is the film stack ``n_films`` / ``d_films_nm`` (top to bottom, thicknesses in nm) with
    the binder (real index ``n_binder``, scalar or (W,)) on both sides; ``cos_theta`` (A,) is
    ``c = |ω·m|``, the cosine between the light and the flake normal, and ``wavelength_nm`` (W,)
    the vacuum wavelengths.  Returns ``FlakeRT(R, T)`` of shape (W, A), the averages over s and p
    of :func:`thin_film_transfer_matrix`; ``R + T <= 1`` (equality for lossless films).  A flake
    with an opaque metal core (e.g. MgF2 / Al 100+ nm / MgF2) gives ``T ≈ 0`` without overflow.
    Light arriving on the bottom face sees the reversed stack; for a symmetric stack R is the same.
    """
    rt = thin_film_transfer_matrix(n_films, d_films_nm, wavelength_nm, cos_theta, n_binder, None)
    return FlakeRT(rt.R, rt.T)


# --- distributions of film thickness ------------------------------------------------------------

#: Largest W × (nodes × angles) block :func:`thin_film_thickness_average` evaluates at once (the
#: characteristic-matrix product holds ~12 complex arrays of 2 × this size: ~400 MB at 2e6).
THICKNESS_BLOCK_CELLS = 2_000_000
#: The thickness average is the trapezoidal rule in z (d = d_mean exp(σ z − σ²/2), z ~ N(0, 1)) on
#: [−THICKNESS_Z_MAX, THICKNESS_Z_MAX] (the normal's mass outside: 6e-14).  For an integrand that is
#: analytic in z and decays like the Gaussian weight the trapezoidal rule converges geometrically in
#: 1/h (Trefethen & Weideman, SIAM Rev. 56, 385 (2014), §5); Gauss–Hermite converges far more slowly on
#: these oscillating integrands (a 250 nm TiO2 film, relative spread 0.2, normal incidence: 128
#: Gauss–Hermite nodes 5e-6, 121 trapezoid nodes 1.5e-10).  The step, :func:`thickness_nodes_needed`:
#: h = min(THICKNESS_STEP_MAX, 1 / (a e^{3σ})), a the round-trip phase's rate of change per unit z,
#: e^{3σ} its growth out to z = 3; at most THICKNESS_NODES_MAX nodes per variable.  Measured against a
#: 3001-point reference in tests/optics/test_thickness_distribution.py.
THICKNESS_Z_MAX = 7.5
THICKNESS_STEP_MAX = 0.5
THICKNESS_NODES_MAX = 241


def lognormal_thickness_nodes(rel_sd, n_nodes):
    """Quadrature of a log-normal thickness factor of mean 1 and relative standard deviation ``rel_sd``.

    The thickness of a film is ``d = d_mean · f`` with ``f = exp(σ z − σ²/2)``, ``z ~ N(0, 1)`` and
    ``σ² = ln(1 + rel_sd²)`` (so ``E f = 1`` and ``SD f = rel_sd``: ``rel_sd`` is the coefficient of
    variation of the thickness across flakes).  Returns ``(f, w)``, each (n_nodes,): the factors at
    ``n_nodes`` equally spaced z on [−:data:`THICKNESS_Z_MAX`, :data:`THICKNESS_Z_MAX`] and the
    trapezoidal weights ``∝ exp(−z²/2)`` normalised to ``Σ w = 1``, so that
    ``E[g(d)] ≈ Σ w_i g(d_mean f_i)``.  ``rel_sd = 0`` gives the single node ``f = 1``.

    >>> f, w = lognormal_thickness_nodes(0.2, 61)
    >>> round(float(w @ f), 9), round(float(np.sqrt(w @ f**2 - 1)), 9)
    (1.0, 0.2)
    """
    rel_sd = float(rel_sd)
    if not (np.isfinite(rel_sd) and rel_sd >= 0):
        raise ValueError(f"rel_sd must be a finite relative standard deviation >= 0, got {rel_sd!r}")
    if rel_sd == 0:
        return np.ones(1), np.ones(1)
    z, w = _z_nodes(n_nodes)
    return _lognormal_factor(rel_sd, z), w


def _z_nodes(n_nodes):
    """Equally spaced z on [−THICKNESS_Z_MAX, THICKNESS_Z_MAX] and normalised weights ∝ exp(−z²/2)."""
    n_nodes = int(n_nodes)
    if n_nodes < 3:
        raise ValueError(f"n_nodes must be >= 3, got {n_nodes}")
    z = np.linspace(-THICKNESS_Z_MAX, THICKNESS_Z_MAX, n_nodes)
    w = np.exp(-0.5 * z * z)
    return z, w / w.sum()


def _lognormal_factor(rel_sd, z):
    """f = exp(σ z − σ²/2), σ² = ln(1 + rel_sd²), broadcast over rel_sd and z."""
    sigma2 = np.log1p(np.asarray(rel_sd, float) ** 2)
    return np.exp(np.sqrt(sigma2) * z - 0.5 * sigma2)


def thickness_nodes_needed(n_real, d_mean_nm, rel_sd, wavelength_min_nm) -> int:
    """Trapezoid node count for one thickness variable z shared by some films (module constants above).

    ``a = 4π Σ_j n_j d_j σ_j / λ`` is how fast the round-trip phase ``Σ 2 k0 n_j d_j`` of the films
    that z scales changes per unit of z at normal incidence (oblique rays have ``n cos θ < n``), at the
    mean thicknesses and the shortest wavelength; ``n_real``, ``d_mean_nm``, ``rel_sd`` scalars or arrays
    over those films.  No spread: 1 node.
    """
    sigma = np.sqrt(np.log1p(np.asarray(rel_sd, float) ** 2))
    if not np.any(sigma > 0):
        return 1
    a = 4.0 * np.pi * float(np.sum(np.asarray(n_real, float) * np.asarray(d_mean_nm, float) * sigma)) / float(wavelength_min_nm)
    h = min(THICKNESS_STEP_MAX, 1.0 / max(a * np.exp(3.0 * float(np.max(sigma))), 1e-300))
    return int(min(THICKNESS_NODES_MAX, 2 * np.ceil(THICKNESS_Z_MAX / h) + 1))


def thin_film_thickness_average(n_films, d_films_nm, rel_sd, wavelength_nm, cos_theta, n_ambient, n_exit=None,
                                groups=None, n_nodes=None):
    """R, T, A of a multilayer averaged over log-normal distributions of its film thicknesses.

    An ensemble of flakes whose films vary from flake to flake: each reflects coherently
    (:func:`thin_film_transfer_matrix`), the ensemble incoherently, so the powers average:
    ``E[R(d)] = ∫ R(d) p(d) dd``.  Film ``j``'s thickness is ``d_films_nm[j] · exp(σ_j z_g − σ_j²/2)``
    with ``g = groups[j]``, ``σ_j² = ln(1 + rel_sd[j]²)``: log-normal of mean ``d_films_nm[j]`` and
    relative standard deviation ``rel_sd[j]``; films of one group share their ``z_g ~ N(0, 1)`` (they are
    thicker or thinner together: the two copies of a coating on a symmetric flake, the layers deposited
    on one flake), groups are independent.  The expectation is a tensor product of one trapezoidal rule
    in z per group (``n_nodes[g]`` nodes; default :func:`thickness_nodes_needed`), evaluated for all
    nodes, angles and wavelengths at once in blocks of :data:`THICKNESS_BLOCK_CELLS`.

    Parameters are those of :func:`thin_film_transfer_matrix`, with ``d_films_nm`` (F,) the *mean*
    thicknesses; ``rel_sd`` (F,) ≥ 0; ``groups`` (F,) integers ≥ 0 (default ``arange(F)``: every film
    its own variable); ``n_nodes`` an int or one per group.  Returns :class:`ThinFilmRT` of the averages
    (each (W, A)); ``R + T + A = 1`` holds for the average as for each member.
    """
    n, d, wl, cos, n_a, n_e = _prepare(n_films, d_films_nm, wavelength_nm, cos_theta, n_ambient, n_exit)
    F = d.shape[0]
    groups = np.arange(F) if groups is None else np.asarray(groups)
    sd = np.broadcast_to(np.asarray(rel_sd, dtype=float), (F,))
    if groups.shape != (F,) or not np.issubdtype(groups.dtype, np.integer) or (F and groups.min() < 0):
        raise ValueError(f"groups must be (F,) = ({F},) integers >= 0, got {groups!r}")
    if np.any(~np.isfinite(sd)) or np.any(sd < 0):
        raise ValueError(f"rel_sd must be finite relative standard deviations >= 0, got {rel_sd!r}")
    labels = [g for g in np.unique(groups) if np.any(sd[groups == g] > 0)]  # the groups that vary
    if n_nodes is None:
        nn = [thickness_nodes_needed(n.real[:, groups == g].max(axis=0), d[groups == g], sd[groups == g], wl.min())
              for g in labels]
    else:
        nn = [int(n_nodes)] * len(labels) if np.ndim(n_nodes) == 0 else [int(n_nodes[g]) for g in labels]
    rules = [_z_nodes(m) for m in nn]
    # Segments: runs of consecutive films of one group.  A segment's matrix product depends on its group's
    # z only, so it is formed once per node of that group; a node of the tensor product multiplies the
    # segments' products (gathered), instead of re-forming every film at every product node.
    slot = {g: i for i, g in enumerate(labels)}
    cuts = [0] + [j for j in range(1, F) if groups[j] != groups[j - 1]] + [F]
    segments = []
    for a, b in zip(cuts[:-1], cuts[1:]):
        g = int(groups[a]) if F else 0
        z = rules[slot[g]][0] if g in slot else np.zeros(1)
        segments.append((a, b, slot.get(g), d[a:b, None] * _lognormal_factor(sd[a:b, None], z[None, :])))
    shape = tuple(nn)
    K = int(np.prod(shape)) if labels else 1
    wts = np.ones(1)
    for r in rules:  # the product weights in C order of the node multi-index
        wts = np.multiply.outer(wts, r[1]).ravel()
    W, A = wl.size, cos.size
    acc = None
    a_block = max(1, THICKNESS_BLOCK_CELLS // max(1, W * max([1] + nn)))
    for a0 in range(0, A, a_block):  # angle blocks bound the segments' memory
        ca = cos[a0:a0 + a_block]
        Ab = ca.size
        seg_m = [_product(n[:, a:b], D, wl, ca, n_a) for a, b, _, D in segments]  # each (2, W, N_g, Ab)
        per_block = max(1, THICKNESS_BLOCK_CELLS // max(1, W * Ab))
        part_a = None
        for k0 in range(0, K, per_block):  # product-node blocks
            kk = np.arange(k0, min(K, k0 + per_block))
            idx = np.unravel_index(kk, shape) if labels else ()
            m, phase = None, 0.0
            for (a, b, sl, _), (sm, sp) in zip(segments, seg_m):
                take = np.zeros(kk.size, int) if sl is None else idx[sl]
                f = tuple(x[:, :, take] for x in sm)
                m = f if m is None else _matmul(m, f)
                phase = phase + sp[:, take]
            if m is None:  # no films
                m, phase = _product(n, np.zeros((0, kk.size)), wl, ca, n_a)
            rt = _power_of(*_close(m, wl, ca, n_a, n_e, 1), phase)  # each (W, nk, Ab)
            part = [np.einsum("wka,k->wa", np.broadcast_to(x, (W, kk.size, Ab)), wts[kk]) for x in rt]
            part_a = part if part_a is None else [p + q for p, q in zip(part_a, part)]
        acc = part_a if acc is None else [np.concatenate([p, q], axis=1) for p, q in zip(acc, part_a)]
    return ThinFilmRT(*acc)


# --- a thick substrate: coherent coatings, incoherent substrate ----------------------------------


def incoherent_substrate_flake(n_coating, d_coating_nm, n_substrate, d_substrate_nm, wavelength_nm, cos_theta,
                               n_binder, coating_rel_sd=0.0, n_nodes=None, substrate_rel_sd=0.0):
    """R, T, A of a symmetric flake whose substrate is incoherent: coatings coherent, substrate round trips in power.

    The flake is binder | coating (outside → in) | substrate | coating reversed | binder.  Each coating
    is a coherent stack (characteristic matrices, Born & Wolf §1.6.3); the substrate is thick against
    its coherence length (or varies across a flake by much more than λ / (2 n)), so the waves of its
    round trips add in power, the phase-averaged limit of the coherent flake (coherent-incoherent
    method: Katsidis & Siapkas, Appl. Opt. 41, 3978 (2002); Centurioni, Appl. Opt. 44, 7532 (2005)).
    Per polarisation (s and p do not mix in isotropic films), with ``R1, T1`` the coating's
    reflectance and transmittance from the binder into the substrate and ``R1', T1'`` from the
    substrate into the binder (the same coating, met from its inner side at the back face),

        R = R1 + T1 T1' R1' a² / (1 − R1'² a²),     T = T1 T1' a / (1 − R1'² a²),

    ``a = exp(−2 k0 d_s Im q_s)`` the power transmitted by one pass through the substrate
    (``q_s = N_s cos θ_s``, = exp(−4π k d_s / (λ cos θ_s)) for small k); unpolarised R, T are the s, p
    means.  The reversed coating's matrix is the coating's with m11 and m22 exchanged (every film's
    matrix has equal diagonal elements).  The interfaces with the substrate take its real index
    ``Re N_s`` (its k enters through ``a`` only; exact for a lossless substrate, the approximation of
    a weakly absorbing one).  Reciprocity makes ``T1' = T1``; ``R1' = R1`` only for lossless coatings.

    ``n_coating`` (C,) or (W, C), ``d_coating_nm`` (C,) the coating films outside → in (C = 0: a bare
    slab); ``n_substrate`` scalar or (W,), ``d_substrate_nm`` its thickness; ``wavelength_nm`` (W,),
    ``cos_theta`` (A,) and ``n_binder`` as :func:`thin_film_transfer_matrix`.  ``coating_rel_sd``
    (scalar or (C,)): the coating films' log-normal flake-to-flake spreads, driven by one shared z (as a
    group of :func:`thin_film_thickness_average`), averaged in power with ``n_nodes`` trapezoid nodes
    (default :func:`thickness_nodes_needed`).  ``substrate_rel_sd``: a log-normal spread of ``d_s``
    (independent of the coating's); it enters through ``a`` only, so it changes nothing for a lossless
    substrate (skipped there, exactly) and is averaged on :func:`thickness_nodes_needed` nodes (taken
    for an oscillation of index Re N_s: an over-resolution of the smooth absorption) where k > 0.
    Returns :class:`ThinFilmRT` (each (W, A));
    ``R + T + A = 1``, ``A = 0`` to rounding for lossless films and substrate.

    A bare lossless slab is the closed form of its interface reflectance r, ``r + (1 − r)² r / (1 − r²)``:

    >>> rt = incoherent_substrate_flake([], [], 1.6, 2000.0, [550.0], [1.0], 1.5)
    >>> r = (0.1 / 3.1) ** 2
    >>> bool(abs(rt.R[0, 0] - (r + (1 - r) ** 2 * r / (1 - r * r))) < 1e-15), round(float(rt.R[0, 0] + rt.T[0, 0]), 12)
    (True, 1.0)
    """
    n, d, wl, cos, n_b, _ = _prepare(n_coating, d_coating_nm, wavelength_nm, cos_theta, n_binder, None)
    W, A = wl.size, cos.size
    N_s = _as_index("n_substrate", n_substrate, W)  # (W, 1)
    d_s = float(d_substrate_nm)
    if not (np.isfinite(d_s) and d_s >= 0):
        raise ValueError(f"d_substrate_nm must be a finite thickness >= 0 in nm, got {d_substrate_nm!r}")
    sd = np.broadcast_to(np.asarray(coating_rel_sd, dtype=float), d.shape)
    if np.any(~np.isfinite(sd)) or np.any(sd < 0):
        raise ValueError(f"coating_rel_sd must be finite relative standard deviations >= 0, got {coating_rel_sd!r}")
    sd_s = float(substrate_rel_sd)
    if not (np.isfinite(sd_s) and sd_s >= 0):
        raise ValueError(f"substrate_rel_sd must be a finite relative standard deviation >= 0, got {substrate_rel_sd!r}")
    if np.any(sd > 0):
        nn = thickness_nodes_needed(n.real.max(axis=0), d, sd, wl.min()) if n_nodes is None else int(n_nodes)
        z, wts = _z_nodes(nn)
        dk = d[:, None] * _lognormal_factor(sd[:, None], z[None, :])  # (C, K)
    else:
        dk, wts = d[:, None], np.ones(1)
    (m11, m12, m21, m22), phase = _product(n, dk, wl, cos, n_b)  # (2, W, K, A), (W, K, A)
    cos_c = cos.reshape(1, 1, A)
    nb = n_b.reshape(W, 1, 1).real
    ns = N_s.reshape(W, 1, 1)
    p_b = np.stack([nb * cos_c, cos_c / nb])  # binder admittances (s, p), real, (2, W, 1, A)
    q_s = normal_wavevector(ns.real, nb, cos_c)  # real index: real, or imaginary beyond the critical angle
    p_s = np.stack([q_s, q_s / (ns.real * ns.real)])
    atten = np.exp(-2.0 * phase.imag)  # |e^{iΣδ}|² of one coating
    # from the binder into the substrate
    r1, D1, inv1 = _solve(m11 + m12 * p_s, m21 + m22 * p_s, p_b)
    T1 = np.where(inv1, 1.0, 4.0 * (p_b / np.abs(D1)) * (p_s.real / np.abs(D1)) * atten)
    # from the substrate into the binder: the reversed coating (m11 <-> m22), ambient the substrate
    r2, D2, inv2 = _solve(m22 + m12 * p_b, m21 + m11 * p_b, p_s)
    T2 = np.where(inv2, 1.0, 4.0 * (p_s.real / np.abs(D2)) * (p_b / np.abs(D2)) * atten)
    R1, R2 = np.abs(r1) ** 2, np.abs(r2) ** 2
    k0 = (2.0 * np.pi / wl).reshape(W, 1, 1)
    im_q = normal_wavevector(ns, nb, cos_c).imag  # (W, 1, A)
    if sd_s > 0 and np.any(N_s.imag > 0):
        m_s = thickness_nodes_needed(float(N_s.real.max()), d_s, sd_s, wl.min())
        f_s, w_s = _lognormal_factor(sd_s, _z_nodes(m_s)[0]), _z_nodes(m_s)[1]
    else:  # one thickness, or a lossless substrate, whose thickness does not enter
        f_s, w_s = np.ones(1), np.ones(1)
    R_pol = T_pol = 0.0
    for f, w in zip(f_s, w_s):  # substrate nodes (absorbing substrates with a spread only); vectorised inside
        a = np.exp(-2.0 * k0 * (d_s * f) * im_q)  # one pass
        den = 1.0 - (R2 * a) ** 2
        den = np.where(den > 0, den, 1.0)  # R2 a = 1 only where nothing enters the substrate (T1 = T2 = 0)
        R_pol = R_pol + w * (R1 + T1 * T2 * R2 * a * a / den)
        T_pol = T_pol + w * np.maximum(T1 * T2 * a / den, 0.0)
    R_s, R_p, T_s, T_p = (np.einsum("wka,k->wa", np.broadcast_to(x, (W, wts.size, A)), wts)
                          for x in (R_pol[0], R_pol[1], T_pol[0], T_pol[1]))
    R = 0.5 * (R_s + R_p)
    T = 0.5 * (T_s + T_p)
    return ThinFilmRT(R_s, R_p, T_s, T_p, R, T, 1.0 - R - T)
