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

    Returns ``B, C, p_a, p_e, phase`` with a leading polarisation axis (0: s, 1: p) on B, C, p_a,
    p_e (shape (2, W, A)) and ``phase = Σ δ_j`` (shape (W, A)), see the module docstring.
    """
    W, A = wl.shape[0], cos.shape[0]
    k0 = (2.0 * np.pi / wl)[:, None]  # 1/nm, (W, 1)
    cos_c = cos[None, :]
    shape = (2, W, A)
    m11 = np.ones(shape, complex)
    m12 = np.zeros(shape, complex)
    m21 = np.zeros(shape, complex)
    m22 = np.ones(shape, complex)
    phase = np.zeros((W, A), complex)
    for j in range(d.shape[0]):  # a loop over the few films; everything inside is vectorised
        N = n[:, j][:, None]  # (W, 1)
        N2 = N * N
        q = normal_wavevector(N, n_a, cos_c)  # (W, A), Im q >= 0
        delta = k0 * d[j] * q
        phase = phase + delta
        z = 2j * delta  # Re z <= 0
        ex = np.expm1(z)
        small = np.abs(z) < 1e-6  # E(z) = expm1(z)/z by its Taylor series there (error < 1e-25)
        z_safe = np.where(small, 1.0, z)
        E = np.where(small, 1.0 + z * (0.5 + z / 6.0), ex / z_safe)
        a = 1.0 + 0.5 * ex  # e^{iδ} cos δ
        g = np.stack([q, q / N2])  # admittances p_j for s, p
        b = -1j * k0 * d[j] * E * np.stack([np.ones_like(N2), N2])  # e^{iδ}(-i sin δ / p_j)
        c = -0.5 * g * ex  # e^{iδ}(-i p_j sin δ)
        m11, m12, m21, m22 = (m11 * a + m12 * c, m11 * b + m12 * a, m21 * a + m22 * c, m21 * b + m22 * a)
    p_a_s = n_a.real * cos_c  # (W, A) real
    p_a = np.stack([p_a_s, cos_c / n_a.real])
    q_e = normal_wavevector(n_e, n_a, cos_c)
    p_e = np.stack([q_e, q_e / (n_e * n_e)])
    B = m11 + m12 * p_e
    C = m21 + m22 * p_e
    return B, C, p_a, p_e, phase


def _solve(B, C, p_a):
    """r and the denominator D = B p_a + C, with the invisible-stack limit where D == 0."""
    D = B * p_a + C
    invisible = D == 0  # only at p_a == 0 (grazing) on a stack invisible there: limit r = 0
    D_safe = np.where(invisible, 1.0, D)
    r = np.where(invisible, 0.0, (B * p_a - C) / D_safe)
    return r, D_safe, invisible


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
    B, C, p_a, p_e, phase = _stack(n, d, wl, cos, n_a, n_e)
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
