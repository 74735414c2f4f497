"""Independent Monte Carlo reference for the plane-parallel paint stack (docs/model.md §7 item 2).

It solves the same radiative-transfer problem as the adding-doubling solver (:mod:`flakedb.rt`) by
tracing photon paths, and shares no code with it except the definition of the rough interfaces'
multiple-scattering split (below, "Energy compensation").  Conventions: :mod:`flakedb.conventions`
(propagation directions, ``mu > 0`` travels down, ``phi_d = 0`` forward/mirror, ``π`` backscatter,
``eta = eta_below / eta_above``, phase functions normalised to 1 over the sphere in 1/sr).

The problem
-----------
Air (index 1) above; a top interface (``None``: index-matched, :class:`Smooth`, :class:`Rough`);
one or more :class:`Slab` s of the binder, whose real index is the ``eta`` of the top interface
(1 when the top is ``None``) unless a slab states its own ``eta``: between slabs of different index a
smooth inner interface reflects (Fresnel, total internal reflection included) or refracts (Snell),
drawn with probability F as at the top, or, where the lower slab states a roughness ``alpha``, a rough
dielectric interface samples a microfacet normal as the rough top does; a bottom (:class:`Lambertian`
inside the binder at the bottom of the last slab, :class:`RoughConductor`, a Beckmann microfacet metal
there, or ``None``: light leaving the last slab is
counted as transmitted into a half-space of the binder's index).  Each slab holds zero or more media
whose extinctions and kernels add:

* :class:`PhaseMedium` — direction-independent σ_t with a phase function (:class:`Isotropic`,
  :class:`HenyeyGreenstein`, :class:`VonMisesFisher`, :class:`TabulatedPhase`); per-channel σ_t,
  albedo and phase parameters.
* :class:`FlakeMedium` — translucent micro-flakes (paper eq. 2, docs/model.md §3): normals with the
  Beckmann density D(m) = exp(−tan²θ/α²)/(2π α² |cos θ|³) on the sphere (paper eq. 5), or
  (``distribution="ggx"``) the GGX density D(m) = α²/(2π |cos θ|³ (α² + tan²θ)²), reflectance
  R(c) and transmittance T(c) of c = |ω·m|; or Student-t slopes (``distribution="student_t(γ)"``,
  D = (1 + tan²θ/(α²(γ−1)))^{−γ}/(2π α² |cos θ|³), Ribardière et al. 2017), or a two-population
  mixture ``"mix(first,w,second,α₂)"`` (simulated as two flake components with aρ split (1 − w) : w).

How flakes are simulated (without σ_t(μ) quadrature, so independently of the solver)
--------------------------------------------------------------------------------------
Delta tracking with the majorant aρ (valid since |ω·m| ≤ 1), added to the other components' σ_t:
at a tentative collision a flake normal m ~ D is drawn in closed form (Beckmann tan²θ = −α² ln(1−u),
GGX tan²θ = α² u/(1−u); Student-t as a Gamma scale mixture of Beckmann normals,
tan²θ = α²(γ−1) E/G with E ~ Exp(1), G ~ Gamma(γ−1), no inverse CDF); the
collision is a real encounter with probability |ω·m| (else a null collision); the light then
passes undeviated with probability T(c), otherwise it is reflected specularly, ω' = ω − 2(ω·m)m,
**with its weight multiplied by R(c)/(1 − T(c))** (absorption carried by weights, no termination).
This realises σ_t(ω) = aρ∫(1−T)|ω·m|D dm and the kernel (aρ/4) R(|ω'·h|)(D(h)+D(−h)) of docs/model.md §3.
Phase media also carry absorption by weights (w ← w·albedo); low weights are Russian-rouletted
(survival 1/10 below ``rr_threshold``), which is unbiased.  A non-absorbing problem therefore has
zero-variance energy bookkeeping: every path leaves with its starting weight.

Interfaces
----------
* :class:`Smooth`: unpolarised Fresnel, refraction and total internal reflection both ways.  The
  first-surface mirror reflection F(θ_i) is carried **analytically** (``Result.specular``); every
  path enters with weight 1 − F(θ_i).  Inside, reflection vs refraction is chosen with probability F.
* :class:`Rough`: Walter et al. 2007 microfacet dielectric, Beckmann D, separable Smith G with the
  exact Beckmann G1 (erf form), reflection and transmission both ways.  Normals are drawn from
  D(m)|m·n| (Walter eq. 35), branch chosen with probability F(i·m), weight Walter eq. 41.  This
  single-scattering microfacet model is not energy conserving (it loses the masked/shadowed part:
  1.36 % of the incident power for a white Lambertian under α = 0.1, η = 1.5 at μ_i = 0.6, where
  light meets the interface ~2.5 times); with ``energy_compensation=False`` the loss is tallied as
  ``Result.interface_loss``.  There is no delta term for a rough top.
* Energy compensation (default; docs/rough-interfaces.md): the single-scattering albedos E_a(μ)
  (light from the air) and E_b(μ) (from the binder) are tabulated here by a 192 × 192 tensor
  quadrature of the kernel's own expected weight (:func:`flakedb.reference.kernels.single_scatter_albedo`).
  At each hit the single-scattering event is taken with probability E(μ_i) (weight divided by it),
  otherwise the compensation lobe with weight 1: from the air it reflects with probability r_a/g_a
  (μ_o ∝ μ_o r_a) or enters the binder (μ_o ∝ μ_o t_b); from the binder it leaves with probability
  t_b/g_b (μ_o ∝ μ_o t_a) or reflects (μ_o ∝ μ_o r_b); φ uniform (g = 1 − E).  The split r, t is the
  solver's definition, imported on purpose (:func:`flakedb.rt.boundaries.microfacet.multiple_scattering_escape`,
  :func:`flakedb.rt.boundaries.microfacet.balance_split`): this Monte Carlo checks the solver's transport and
  discretisation with the same lobe; the lobe itself is checked against the explicit random walk of
  :mod:`flakedb.reference.microsurface`.  A rough conductor bottom's lobe is taken with probability
  1 − E₁(μ_i) (E₁ its albedo with F ≡ 1), weight a(μ_i)/(1 − E₁(μ_i)), μ_o ∝ μ_o a(μ_o), with a the
  solver's (:func:`flakedb.rt.boundaries.microfacet.conductor_compensation`).

Estimators
----------
For light incident from the air with ``mu_i`` (φ_i = 0), per spectral channel c (channels are
simulated one after another with the *same* random streams — common random numbers — so a channel
of a multi-channel problem equals the same problem with that channel alone, bit for bit):

* ``albedo`` = ``specular`` + ``diffuse_albedo``: fraction of incident power leaving the top
  (``diffuse_albedo`` is everything but the analytic first-surface delta; its standard error is
  ``albedo_se``).
* ``transmittance`` = ``transmittance_direct`` (never scattered or reflected: the delta term of the
  transmission) + scattered; ``transmittance_se``, ``transmittance_direct_se``.
* Binned (when ``mu_edges``/``phi_edges`` are given): for bins of |μ_o| (``mu_edges``, ascending in
  [0, 1]) × φ_d (``phi_edges``, ascending in [0, π], the bin standing for ±φ_d together):
  ``reflectance_binned[c, i, j]`` = (fraction of incident power leaving the top into the bin,
  excluding the specular delta) / (solid angle of the bin, 2 Δ|μ| Δφ) in 1/sr.  For a tabulated BSDF
  f this equals ∫_bin f |μ_o| dω / ∫_bin dω = (1/(Δ|μ| Δφ)) ∫∫ f |μ_o| d|μ_o| dφ_d, which
  :func:`bin_average` computes by quadrature.  ``transmittance_binned`` is the same for the scattered
  transmission (directions in the bottom half-space, |μ| of the binder-side direction).
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from flakedb.reference import kernels as _k
from flakedb.rt.boundaries import microfacet as _mf

__all__ = [
    "Isotropic",
    "HenyeyGreenstein",
    "VonMisesFisher",
    "TabulatedPhase",
    "PhaseMedium",
    "FlakeMedium",
    "Slab",
    "Smooth",
    "Rough",
    "Lambertian",
    "RoughConductor",
    "Problem",
    "Result",
    "simulate",
    "directional_albedo",
    "binned_reflectance",
    "bin_average",
    "flake_ndf_Beckmann",
    "flake_ndf_GGX",
    "compensation_table",
    "sample_vmf_cosines",
]

#: number of independent RNG streams (path batches); fixed so results depend on seed and n_paths only
N_BATCHES = 64
#: Russian roulette threshold on the path weight (relative to a start weight of 1)
RR_THRESHOLD = 1e-3
#: paths interacting more often than this are counted as lost (``Result.n_lost``; should be 0)
MAX_EVENTS = 10_000_000


# ----------------------------------------------------------------------------------------------
# problem description
# ----------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Isotropic:
    """Isotropic phase function p = 1/(4π) sr⁻¹."""


@dataclass(frozen=True)
class HenyeyGreenstein:
    """Henyey–Greenstein phase function p(cos Θ) = (1−g²)/(4π (1+g²−2g cos Θ)^{3/2}) sr⁻¹.

    ``g``: mean cosine (scalar or per channel (C,)), g > 0 forward scattering (cos Θ = ω_in·ω_out).
    """

    g: Any


@dataclass(frozen=True)
class VonMisesFisher:
    """von Mises–Fisher phase function p(cos Θ) = κ/(4π sinh κ) exp(κ cos Θ) sr⁻¹ (Fisher 1953),
    sampled by exact inversion of its CDF (:func:`flakedb.reference.kernels.sample_vmf_cos`).

    ``kappa``: concentration κ ≥ 0 (scalar or per channel (C,)); κ = 0 is isotropic.
    """

    kappa: Any


@dataclass(frozen=True)
class TabulatedPhase:
    """Tabulated phase function p(cos Θ) in 1/sr, linearly interpolated in cos Θ.

    ``cos_theta``: strictly increasing grid from −1 to 1; ``value``: p at the nodes, (n,) or (C, n),
    normalised to 1 over the sphere (2π ∫ p dcosΘ = 1).  The piecewise-linear interpolant is
    renormalised exactly (trapezoid rule) and sampled by inverting its CDF exactly; a table whose
    trapezoid normalisation is off by more than 1 % is refused.
    """

    cos_theta: Any
    value: Any


@dataclass(frozen=True)
class PhaseMedium:
    """A direction-independent medium component: extinction ``sigma_t_per_um`` (1/µm), single-
    scattering ``albedo`` (both scalars or per channel (C,)) and a ``phase`` function
    (:class:`Isotropic`, :class:`HenyeyGreenstein`, :class:`VonMisesFisher`, :class:`TabulatedPhase`;
    the solver-style specs ``"isotropic"``, ``("hg", g)``, ``("vmf", kappa)`` and
    ``("table", cos_theta, value)`` are accepted too)."""

    sigma_t_per_um: Any
    albedo: Any
    phase: Any = Isotropic()


@dataclass(frozen=True)
class FlakeMedium:
    """Translucent micro-flakes (paper eq. 2, docs/model.md §3).

    ``a_rho_per_um``: flake area × number density aρ (1/µm; scalar or (C,)); ``alpha``: roughness of
    the flake normals' density ``distribution`` ("beckmann": paper eq. 5; "ggx": :func:`flake_ndf_GGX`;
    "student_t(γ)": Student-t slopes; "mix(first,w,second,α₂)": two populations, :func:`_flake_populations`);
    ``R_table``, ``T_table``: flake reflectance and
    transmittance as functions of c = |ω·m| — without ``c_grid``: constants (scalar or (C,)); with
    ``c_grid`` (n,): tables (n,) or (C, n), or scalars (constant), linearly interpolated in c.  ``c_grid`` must run from 0 to 1; R, T ≥ 0, R + T ≤ 1.
    """

    a_rho_per_um: Any
    alpha: float
    R_table: Any
    T_table: Any = 0.0
    c_grid: Any = None
    distribution: str = "beckmann"


@dataclass(frozen=True)
class Slab:
    """A slab of binder of thickness ``thickness_um`` (µm) holding the media in ``media`` (which add).
    ``eta``: the binder's real index relative to the air above (None: the top interface's); where two
    neighbouring slabs differ, a smooth inner interface separates them (module docstring).
    ``alpha``: the Beckmann roughness of the interface between this slab and the one above it (0: smooth;
    > 0: a rough dielectric, Walter et al. 2007 single scattering, sampled as the rough top is; ignored
    for the first slab, whose top is the stack's top interface)."""

    thickness_um: float
    media: tuple = ()
    eta: float | None = None
    alpha: float = 0.0


@dataclass(frozen=True)
class Smooth:
    """Smooth dielectric top interface, ``eta`` = n_binder / n_air (real, > 0)."""

    eta: float


@dataclass(frozen=True)
class Rough:
    """Rough dielectric top interface (Walter et al. 2007, Beckmann, roughness ``alpha`` > 0),
    ``eta`` = n_binder / n_air.  ``energy_compensation`` (default): the masked/shadowed energy is
    returned by the reciprocal multiple-scattering lobe (module docstring); False: single scattering."""

    eta: float
    alpha: float
    energy_compensation: bool = True


@dataclass(frozen=True)
class Lambertian:
    """Lambertian primer at the bottom of the last slab, inside the binder; ``albedo`` scalar or (C,)."""

    albedo: Any


@dataclass(frozen=True)
class RoughConductor:
    """Beckmann microfacet metal at the bottom of the last slab (Walter et al. 2007 reflection with
    the conductor Fresnel factor, separable Smith G, exact Beckmann G1): complex index ``N`` = n + ik
    of the metal relative to vacuum (scalar or (C,)); it is divided by the binder's index.  The
    masked/shadowed part and the metal's absorption are both lost (counted in ``absorbed``) unless
    ``energy_compensation`` (default) adds the multiple-scattering lobe of
    :func:`flakedb.rt.boundaries.microfacet.conductor_compensation` (docs/rough-interfaces.md)."""

    N: Any
    alpha: float
    energy_compensation: bool = True


@dataclass(frozen=True)
class Problem:
    """The stack: ``slabs`` (top to bottom), ``top`` interface (None, :class:`Smooth`, :class:`Rough`),
    ``bottom`` (None or :class:`Lambertian`).  See the module docstring."""

    slabs: tuple
    top: Any = None
    bottom: Any = None

    @property
    def eta_binder(self) -> float:
        """Real index of the binder relative to the air above (1 with an index-matched top)."""
        return 1.0 if self.top is None else float(self.top.eta)

    def slab_eta(self) -> np.ndarray:
        """Each slab's binder index relative to the air (``Slab.eta``, default :attr:`eta_binder`)."""
        return np.array([self.eta_binder if sl.eta is None else float(sl.eta) for sl in self.slabs], dtype=float)

    def slab_alpha(self) -> np.ndarray:
        """The roughness of the interface at the top of each slab (``Slab.alpha``; entry 0 unused)."""
        return np.array([0.0] + [float(sl.alpha) for sl in self.slabs[1:]], dtype=float)

    @property
    def n_channels(self) -> int:
        """Number of spectral channels C, from the broadcast of every per-channel parameter."""
        return _n_channels(self)


# ----------------------------------------------------------------------------------------------
# result
# ----------------------------------------------------------------------------------------------


@dataclass
class Result:
    """Monte Carlo estimates for one incident direction; arrays have a leading channel axis (C,).

    See the module docstring for the definitions.  ``*_se`` are one-sigma standard errors of the
    mean over paths.  ``absorbed`` = 1 − albedo − transmittance − interface_loss (estimate).
    """

    mu_i: float
    n_paths: int
    seed: int
    albedo: np.ndarray
    albedo_se: np.ndarray
    specular: np.ndarray
    diffuse_albedo: np.ndarray
    transmittance: np.ndarray
    transmittance_se: np.ndarray
    transmittance_direct: np.ndarray
    transmittance_direct_se: np.ndarray
    interface_loss: np.ndarray
    interface_loss_se: np.ndarray
    absorbed: np.ndarray
    n_lost: np.ndarray
    events_per_path: np.ndarray
    mu_edges: np.ndarray | None = None
    phi_edges: np.ndarray | None = None
    reflectance_binned: np.ndarray | None = None
    reflectance_binned_se: np.ndarray | None = None
    transmittance_binned: np.ndarray | None = None
    transmittance_binned_se: np.ndarray | None = None
    max_scattering_orders: int | None = None
    extra: dict = field(default_factory=dict)


# ----------------------------------------------------------------------------------------------
# validation and packing
# ----------------------------------------------------------------------------------------------


def _arr(x):
    return np.asarray(x, dtype=float)


def _per_channel_sizes(problem):
    """Yield (path, C) for every parameter that carries a channel axis."""
    for si, slab in enumerate(problem.slabs):
        for mi, m in enumerate(slab.media):
            p = f"slabs[{si}].media[{mi}]"
            if isinstance(m, PhaseMedium):
                for name in ("sigma_t_per_um", "albedo"):
                    a = _arr(getattr(m, name))
                    if a.ndim == 1:
                        yield f"{p}.{name}", a.shape[0]
                ph = _normalise_phase(m.phase, p)
                if isinstance(ph, HenyeyGreenstein) and _arr(ph.g).ndim == 1:
                    yield f"{p}.phase.g", _arr(ph.g).shape[0]
                if isinstance(ph, VonMisesFisher) and _arr(ph.kappa).ndim == 1:
                    yield f"{p}.phase.kappa", _arr(ph.kappa).shape[0]
                if isinstance(ph, TabulatedPhase) and _arr(ph.value).ndim == 2:
                    yield f"{p}.phase.value", _arr(ph.value).shape[0]
            elif isinstance(m, FlakeMedium):
                a = _arr(m.a_rho_per_um)
                if a.ndim == 1:
                    yield f"{p}.a_rho_per_um", a.shape[0]
                for name in ("R_table", "T_table"):
                    t = _arr(getattr(m, name))
                    if (m.c_grid is None and t.ndim == 1) or (m.c_grid is not None and t.ndim == 2):
                        yield f"{p}.{name}", t.shape[0]
    if isinstance(problem.bottom, Lambertian) and _arr(problem.bottom.albedo).ndim == 1:
        yield "bottom.albedo", _arr(problem.bottom.albedo).shape[0]
    if isinstance(problem.bottom, RoughConductor) and np.ndim(problem.bottom.N) == 1:
        yield "bottom.N", len(problem.bottom.N)


def _n_channels(problem):
    sizes = list(_per_channel_sizes(problem))
    cs = {c for _, c in sizes}
    if len(cs) > 1:
        raise ValueError(
            "per-channel parameters disagree on the number of channels: "
            + ", ".join(f"{p} has {c}" for p, c in sizes)
            + "; give every per-channel array the same length (or a scalar for all channels)."
        )
    return cs.pop() if cs else 1


def _normalise_phase(ph, path):
    if isinstance(ph, (Isotropic, HenyeyGreenstein, VonMisesFisher, TabulatedPhase)):
        return ph
    if isinstance(ph, str) and ph == "isotropic":
        return Isotropic()
    if isinstance(ph, tuple) and len(ph) == 2 and ph[0] == "hg":
        return HenyeyGreenstein(ph[1])
    if isinstance(ph, tuple) and len(ph) == 2 and ph[0] == "vmf":
        return VonMisesFisher(ph[1])
    if isinstance(ph, tuple) and len(ph) == 3 and ph[0] == "table":
        return TabulatedPhase(ph[1], ph[2])
    raise ValueError(
        f"{path}.phase = {ph!r} is not a phase function; use Isotropic(), HenyeyGreenstein(g), "
        "VonMisesFisher(kappa), TabulatedPhase(cos_theta, value) (or 'isotropic', ('hg', g), ('vmf', kappa), "
        "('table', cos_theta, value))."
    )


def _pick(x, c, path, base_ndim=0):
    """Channel c of a parameter that is either channel-independent (ndim == base_ndim) or (C, ...)."""
    a = _arr(x)
    if a.ndim == base_ndim:
        return a
    if a.ndim == base_ndim + 1:
        return a[c]
    raise ValueError(f"{path} has shape {a.shape}; expected {base_ndim}-d (all channels) or {base_ndim + 1}-d (per channel).")


def _check_range(v, lo, hi, path, what):
    v = np.asarray(v, dtype=float)
    if not np.all(np.isfinite(v)) or np.any(v < lo) or np.any(v > hi):
        raise ValueError(f"{path} = {v} is outside [{lo}, {hi}] ({what}).")


def _validate(problem):
    if not isinstance(problem, Problem):
        raise TypeError("problem must be a flakedb.reference.montecarlo.Problem")
    if len(problem.slabs) == 0:
        raise ValueError("Problem.slabs is empty; give at least one Slab(thickness_um, media).")
    top = problem.top
    if top is not None and not isinstance(top, (Smooth, Rough)):
        raise ValueError(f"top = {top!r}; use None (index-matched), Smooth(eta) or Rough(eta, alpha).")
    if top is not None and not (np.isfinite(top.eta) and top.eta > 0):
        raise ValueError(f"top.eta = {top.eta}; it must be a positive real n_binder / n_air.")
    if isinstance(top, Rough) and not (0 < top.alpha <= 2):
        raise ValueError(f"top.alpha = {top.alpha}; the Beckmann roughness must be in (0, 2] (use Smooth for 0).")
    if problem.bottom is not None and not isinstance(problem.bottom, (Lambertian, RoughConductor)):
        raise ValueError(f"bottom = {problem.bottom!r}; use None (index-matched half-space), Lambertian(albedo) "
                         "or RoughConductor(N, alpha).")
    if isinstance(problem.bottom, RoughConductor):
        N = np.atleast_1d(np.asarray(problem.bottom.N, dtype=complex))
        if not (np.all(np.isfinite(N)) and np.all(N.real > 0) and np.all(N.imag >= 0)):
            raise ValueError(f"bottom.N = {problem.bottom.N!r}; need n > 0 and k >= 0.")
        if not (0 < problem.bottom.alpha <= 2):
            raise ValueError(f"bottom.alpha = {problem.bottom.alpha}; the Beckmann roughness must be in (0, 2].")
    if isinstance(problem.bottom, Lambertian):
        _check_range(problem.bottom.albedo, 0.0, 1.0, "bottom.albedo", "an albedo")
    for si, slab in enumerate(problem.slabs):
        if not isinstance(slab, Slab):
            raise ValueError(f"slabs[{si}] = {slab!r} is not a Slab")
        if not (np.isfinite(slab.thickness_um) and slab.thickness_um > 0):
            raise ValueError(f"slabs[{si}].thickness_um = {slab.thickness_um}; it must be > 0 µm.")
        if slab.eta is not None and not (np.isfinite(slab.eta) and slab.eta > 0):
            raise ValueError(f"slabs[{si}].eta = {slab.eta}; it must be a positive real index relative to the air.")
        if not (np.isfinite(slab.alpha) and 0.0 <= slab.alpha <= 2.0):
            raise ValueError(f"slabs[{si}].alpha = {slab.alpha}; a Beckmann roughness in [0, 2] (0: smooth).")
        for mi, m in enumerate(slab.media):
            p = f"slabs[{si}].media[{mi}]"
            if isinstance(m, PhaseMedium):
                _check_range(m.sigma_t_per_um, 0.0, np.inf, f"{p}.sigma_t_per_um", "an extinction in 1/µm")
                _check_range(m.albedo, 0.0, 1.0, f"{p}.albedo", "a single-scattering albedo")
                ph = _normalise_phase(m.phase, p)
                if isinstance(ph, HenyeyGreenstein):
                    _check_range(ph.g, -0.999999, 0.999999, f"{p}.phase.g", "the HG mean cosine, |g| < 1")
                if isinstance(ph, VonMisesFisher):
                    _check_range(ph.kappa, 0.0, 1e8, f"{p}.phase.kappa", "the vMF concentration, κ ≥ 0")
                if isinstance(ph, TabulatedPhase):
                    _phase_table(ph, 0, p)  # raises on a bad table
            elif isinstance(m, FlakeMedium):
                _check_range(m.a_rho_per_um, 0.0, np.inf, f"{p}.a_rho_per_um", "aρ in 1/µm")
                if not (0 < m.alpha <= 10):
                    raise ValueError(f"{p}.alpha = {m.alpha}; the flake Beckmann roughness must be in (0, 10].")
            else:
                raise ValueError(f"{p} = {m!r}; use PhaseMedium or FlakeMedium.")
    C = _n_channels(problem)
    for c in range(C):
        for si, slab in enumerate(problem.slabs):
            for mi, m in enumerate(slab.media):
                if isinstance(m, FlakeMedium):
                    _flake_table(m, c, f"slabs[{si}].media[{mi}]")
    return C


def _phase_table(ph, c, path):
    x = _arr(ph.cos_theta)
    v = _pick(ph.value, c, f"{path}.phase.value", base_ndim=1)
    if x.ndim != 1 or x.shape != v.shape or x.size < 2:
        raise ValueError(f"{path}.phase: cos_theta {x.shape} and value {v.shape} must be 1-d of equal length >= 2.")
    if abs(x[0] + 1) > 1e-12 or abs(x[-1] - 1) > 1e-12 or np.any(np.diff(x) <= 0):
        raise ValueError(f"{path}.phase.cos_theta must increase strictly from -1 to 1.")
    if np.any(v < 0) or not np.all(np.isfinite(v)):
        raise ValueError(f"{path}.phase.value must be finite and >= 0.")
    norm = 2 * np.pi * np.trapezoid(v, x)
    if abs(norm - 1) > 1e-2:
        raise ValueError(
            f"{path}.phase: 2π ∫ p dcosΘ = {norm:.6g} (trapezoid on the table), not 1; pass p in 1/sr "
            "normalised to 1 over the sphere (conventions), or refine the table."
        )
    q = 2 * np.pi * v / norm  # pdf in cos Θ, ∫ q dx = 1 with the trapezoid rule
    cdf = np.concatenate([[0.0], np.cumsum(0.5 * (q[1:] + q[:-1]) * np.diff(x))])
    cdf /= cdf[-1]
    return x, q, cdf


def _flake_table(m, c, path):
    if m.c_grid is None:
        R = float(_pick(m.R_table, c, f"{path}.R_table"))
        T = float(_pick(m.T_table, c, f"{path}.T_table"))
        grid = np.array([0.0, 1.0])
        R = np.array([R, R])
        T = np.array([T, T])
    else:
        grid = _arr(m.c_grid)
        if grid.ndim != 1 or grid.size < 2 or abs(grid[0]) > 1e-12 or abs(grid[-1] - 1) > 1e-12 or np.any(np.diff(grid) <= 0):
            raise ValueError(f"{path}.c_grid must increase strictly from 0 to 1 (cosines c = |ω·m|).")
        R, T = (_arr(getattr(m, name)) for name in ("R_table", "T_table"))
        R = np.broadcast_to(R if R.ndim == 0 else _pick(R, c, f"{path}.R_table", base_ndim=1), grid.shape).astype(float)
        T = np.broadcast_to(T if T.ndim == 0 else _pick(T, c, f"{path}.T_table", base_ndim=1), grid.shape).astype(float)
    if np.any(R < 0) or np.any(T < 0) or np.any(R + T > 1 + 1e-9):
        bad = np.argmax((R < 0) | (T < 0) | (R + T > 1 + 1e-9))
        raise ValueError(
            f"{path}: R = {R[bad]:.6g}, T = {T[bad]:.6g} at c = {grid[bad]:.4g} (channel {c}); flakes need "
            "R, T >= 0 and R + T <= 1 (energy conservation, docs/model.md §3)."
        )
    return grid, R, np.minimum(T, 1.0)


def _split_top(text):
    out, depth, start = [], 0, 0
    for i, ch in enumerate(text):
        depth += (ch == "(") - (ch == ")")
        if ch == "," and depth == 0:
            out.append(text[start:i])
            start = i + 1
    return out + [text[start:]]


def _flake_populations(distribution, alpha, path):
    """The flake populations of a ``distribution`` name, [(component code, weight, α, shape)], parsed here
    (not by the solver's registry): ``beckmann``, ``ggx``, ``student_t(γ)`` (γ > 1) and
    ``mix(first, w, second, α₂)`` (weight 1 − w of ``first`` at α, w of ``second`` at α₂)."""
    name = str(distribution).replace(" ", "").lower()
    fixed = {"beckmann": _k.COMP_FLAKE, "ggx": _k.COMP_FLAKE_GGX}
    try:
        if name in fixed:
            return [(fixed[name], 1.0, alpha, 0.0)]
        if name.startswith("student_t(") and name.endswith(")"):
            g = float(name[len("student_t("):-1])
            if not g > 1.0 or not math.isfinite(g):
                raise ValueError(f"the shape must be finite and > 1, got {g}")
            return [(_k.COMP_FLAKE_STUDENT_T, 1.0, alpha, g)]
        if name.startswith("mix(") and name.endswith(")"):
            first, w, second, a2 = _split_top(name[4:-1])
            w, a2 = float(w), float(a2)
            if not 0.0 < w < 1.0:
                raise ValueError(f"the weight must be in (0, 1), got {w}")
            pops = [(t, (1.0 - w) * q, a, g) for t, q, a, g in _flake_populations(first, alpha, path)]
            return pops + [(t, w * q, a, g) for t, q, a, g in _flake_populations(second, a2, path)]
    except ValueError as exc:
        raise ValueError(f"{path}: {distribution!r}: {exc}") from None
    raise ValueError(f"{path}: {distribution!r} is not one of beckmann, ggx, student_t(γ), mix(first,w,second,α₂)")


def _pack(problem, c):
    """Flatten channel c of the problem into the kernel's arrays."""
    z = [0.0]
    sigma_bar, comp_start = [], [0]
    ctype, csig, calb, cg, calpha, coff, cn = [], [], [], [], [], [], []
    tab = []
    for si, slab in enumerate(problem.slabs):
        z.append(z[-1] + float(slab.thickness_um))
        sb = 0.0
        for mi, m in enumerate(slab.media):
            p = f"slabs[{si}].media[{mi}]"
            if isinstance(m, PhaseMedium):
                sig = float(_pick(m.sigma_t_per_um, c, f"{p}.sigma_t_per_um"))
                alb = float(_pick(m.albedo, c, f"{p}.albedo"))
                ph = _normalise_phase(m.phase, p)
                g, off, n = 0.0, 0, 0
                if isinstance(ph, Isotropic):
                    t = _k.COMP_ISOTROPIC
                elif isinstance(ph, HenyeyGreenstein):
                    t = _k.COMP_HG
                    g = float(_pick(ph.g, c, f"{p}.phase.g"))
                elif isinstance(ph, VonMisesFisher):
                    t = _k.COMP_VMF
                    g = float(_pick(ph.kappa, c, f"{p}.phase.kappa"))  # the kernel reads κ from comp_g
                else:
                    t = _k.COMP_TABLE
                    x, q, cdf = _phase_table(ph, c, p)
                    off, n = len(tab), len(x)
                    tab.extend(x)
                    tab.extend(q)
                    tab.extend(cdf)
                a = 0.0
            else:
                sig_all = float(_pick(m.a_rho_per_um, c, f"{p}.a_rho_per_um"))
                grid, R, T = _flake_table(m, c, p)
                off, n = len(tab), len(grid)
                tab.extend(grid)
                tab.extend(R)
                tab.extend(T)
                # one component per population (a mixture's extinctions add: aρ split by the weights)
                for t, weight, a, g in _flake_populations(m.distribution, float(m.alpha), f"{p}.distribution"):
                    sig = sig_all * weight
                    if sig == 0.0:
                        continue
                    for lst, val in ((ctype, t), (csig, sig), (calb, 0.0), (cg, g), (calpha, a), (coff, off),
                                     (cn, n)):
                        lst.append(val)
                    sb += sig
                continue
            if sig == 0.0:
                continue
            ctype.append(t)
            csig.append(sig)
            calb.append(alb)
            cg.append(g)
            calpha.append(a)
            coff.append(off)
            cn.append(n)
            sb += sig
        sigma_bar.append(sb)
        comp_start.append(len(ctype))
    if not tab:
        tab = [0.0]
    i64 = np.int64
    return dict(
        z_edges=np.array(z), sigma_bar=np.array(sigma_bar), comp_start=np.array(comp_start, dtype=i64),
        comp_type=np.array(ctype, dtype=i64), comp_sigma=np.array(csig, dtype=float),
        comp_albedo=np.array(calb, dtype=float), comp_g=np.array(cg, dtype=float),
        comp_alpha=np.array(calpha, dtype=float), comp_off=np.array(coff, dtype=i64),
        comp_n=np.array(cn, dtype=i64), tab=np.array(tab, dtype=float),
    )


def sample_vmf_cosines(kappa, n, seed):
    """``n`` scattering cosines cos Θ drawn from the von Mises–Fisher phase function with
    concentration ``kappa`` by the sampler the tracer uses (:func:`flakedb.reference.kernels.sample_vmf_cos`),
    from ``numpy.random.default_rng(seed)`` uniforms (for testing the sampler against the pdf)."""
    u = np.random.default_rng(seed).random(int(n))
    return _k.sample_vmf_cos_array(float(kappa), u)


def sample_student_t_flake_normals(alpha, shape, n, seed):
    """``n`` upper-hemisphere flake normals (n, 3) with Student-t slopes drawn by the tracer's sampler
    (:func:`flakedb.reference.kernels._sample_student_t_flake_normal`, a Gamma scale mixture), seeded as
    :func:`simulate` seeds its streams (for testing the sampler against the density)."""
    state = np.random.SeedSequence(int(seed)).generate_state(4, dtype=np.uint64)
    state[0] |= np.uint64(1)  # xoshiro state must be non-zero
    return _k.sample_student_t_normals_array(float(alpha), float(shape), int(n), state)


def _edges(edges, hi, name):
    e = _arr(edges)
    if e.ndim != 1 or e.size < 2 or np.any(np.diff(e) <= 0) or e[0] < 0 or e[-1] > hi + 1e-12:
        raise ValueError(
            f"{name} = {edges!r}: need >= 2 strictly increasing edges in [0, {hi:.6g}]"
            + (" (edges of |mu_o| = cos θ_o; reflected mu_o < 0 is binned by its absolute value)" if name == "mu_edges" else "")
            + "."
        )
    return e


#: μ grid of the compensation tables, μ_k = (k/K)² (dense at grazing, where E changes fastest)
MS_TABLE_K = 384
#: Gauss–Legendre nodes per dimension of the tables' quadrature
MS_TABLE_QUAD = 192


def compensation_table(eta_rel, alpha, white=False):
    """The compensation table of a rough interface: (μ grid, E on the grid, CDF of μ(1 − E) over the
    intervals, Z = ∫ μ (1 − E) dμ); ``white``: a rough reflector with F ≡ 1 (the conductor's E₁)."""
    E, cdf, Z = _ms_row(float(eta_rel), float(alpha), bool(white))
    return (np.arange(MS_TABLE_K + 1) / MS_TABLE_K) ** 2, E.copy(), cdf.copy(), Z


@functools.lru_cache(maxsize=64)
def _ms_row(eta_rel, alpha, white):
    """(E on the grid, CDF of μ(1 − E) over the intervals, ∫ μ (1 − E) dμ) for one table row."""
    grid = (np.arange(MS_TABLE_K + 1) / MS_TABLE_K) ** 2
    x, w = np.polynomial.legendre.leggauss(MS_TABLE_QUAD)
    E = _k.single_scatter_albedo(grid, float(eta_rel), float(alpha), bool(white), 0.5 * (x + 1.0), 0.5 * w)
    g = np.clip(1.0 - E, 0.0, None)
    W = 0.5 * (g[1:] + g[:-1]) * 0.5 * np.diff(grid**2)
    Z = float(W.sum())
    cdf = np.cumsum(W) / Z if Z > 0 else np.linspace(1.0 / len(W), 1.0, len(W))
    cdf[-1] = 1.0
    return E, cdf, Z


def _cdf_rows(grid, h):
    """CDF over the intervals [μ_k, μ_{k+1}] of the pdf ∝ μ h(μ) (trapezoid in μ², as :func:`_ms_row`)."""
    W = 0.5 * (h[1:] + h[:-1]) * 0.5 * np.diff(grid**2)
    Z = float(W.sum())
    cdf = np.cumsum(W) / Z if Z > 0 else np.linspace(1.0 / len(W), 1.0, len(W))
    cdf[-1] = 1.0
    return cdf


def _flux_weights(grid):
    """m_k with Σ m_k h(μ_k) = ∫ μ h dμ by the trapezoid rule in μ² (the weights of :func:`_cdf_rows`)."""
    t = grid**2
    w = np.zeros_like(t)
    w[1:] += 0.5 * np.diff(t)
    w[:-1] += 0.5 * np.diff(t)
    return 0.5 * w


@functools.lru_cache(maxsize=32)
def _dielectric_split(eta, alpha):
    """The lobe's split on the table grid, (r_a, t_a, r_b, t_b) over the kernel's own g = 1 − E: the
    solver's definition (:func:`flakedb.rt.boundaries.microfacet.multiple_scattering_escape` minus the single-
    scattering R, T of :func:`flakedb.rt.boundaries.microfacet.microfacet_albedo`, made reciprocal by
    :func:`flakedb.rt.boundaries.microfacet.balance_split` on this grid's flux weights): shared on purpose, so
    that the Monte Carlo samples the lobe the solver defines (the random walk of
    :mod:`flakedb.reference.microsurface` is the independent check of the lobe)."""
    grid = (np.arange(MS_TABLE_K + 1) / MS_TABLE_K) ** 2
    mu = np.maximum(grid, 1e-4)
    Ea, _, _ = _ms_row(eta, alpha, False)
    Eb, _, _ = _ms_row(1.0 / eta, alpha, False)
    ga, gb = np.clip(1.0 - Ea, 0.0, None), np.clip(1.0 - Eb, 0.0, None)
    Ra, _ = _mf.microfacet_albedo(mu, eta, alpha)
    _, Tb = _mf.microfacet_albedo(mu, 1.0 / eta, alpha)
    Pa, Pb = _mf.multiple_scattering_escape(mu, mu, eta, alpha)
    m = _flux_weights(grid)
    r_a, t_a, r_b, t_b, _ = _mf.balance_split(m, ga, np.clip(Pa - Ra[0], 0.0, ga), m, gb,
                                              np.clip(Pb - Tb[0], 0.0, gb), eta)
    return r_a, t_a, r_b, t_b


def _conductor_lobe(N, alpha, E1):
    """The conductor lobe's a(μ) on the table grid (the solver's definition, as
    :func:`flakedb.rt.boundaries.microfacet.conductor_compensation`: a = P_F / P_1 − R_F, at most 1 − E₁)."""
    grid = (np.arange(MS_TABLE_K + 1) / MS_TABLE_K) ** 2
    mu = np.maximum(grid, 1e-4)
    F = _mf.conductor_fresnel(np.array([N]))
    white = lambda c: np.ones((1,) + np.shape(c))
    RF, _ = _mf.microfacet_albedo(mu, 1.0, alpha, fresnel=F)
    P1 = _mf.conductor_multiple_scattering(mu, alpha, white)[0]
    PF = _mf.conductor_multiple_scattering(mu, alpha, F)[0]
    return np.clip(np.minimum(PF / P1 - RF[0], 1.0 - E1), 0.0, None)


def _ms_tables(problem, c):
    """The kernel's compensation arrays (ms_grid, ms_E, ms_cdf, ms_par) for channel c."""
    grid = (np.arange(MS_TABLE_K + 1) / MS_TABLE_K) ** 2
    E = np.zeros((6, MS_TABLE_K + 1))
    cdf = np.ones((5, MS_TABLE_K))
    par = np.zeros(4)
    top, bot = problem.top, problem.bottom
    if isinstance(top, Rough) and top.energy_compensation:
        eta = float(top.eta)
        E[0], _, _ = _ms_row(eta, float(top.alpha), False)
        E[1], _, _ = _ms_row(1.0 / eta, float(top.alpha), False)
        r_a, t_a, r_b, t_b = _dielectric_split(eta, float(top.alpha))
        with np.errstate(divide="ignore", invalid="ignore"):
            E[3] = np.where(r_a + t_a > 0, r_a / (r_a + t_a), 1.0)
            E[4] = np.where(r_b + t_b > 0, t_b / (r_b + t_b), 0.0)
        cdf[0], cdf[1], cdf[3], cdf[4] = (_cdf_rows(grid, h) for h in (r_a, r_b, t_a, t_b))
        par[0] = 1.0
    if isinstance(bot, RoughConductor) and bot.energy_compensation:
        E[2], _, _ = _ms_row(1.0, float(bot.alpha), True)
        Nc = np.atleast_1d(np.asarray(bot.N, dtype=complex))
        Nc = complex(Nc[0] if Nc.size == 1 else Nc[c]) / problem.slab_eta()[-1]
        a = _conductor_lobe(Nc, float(bot.alpha), E[2])
        with np.errstate(divide="ignore", invalid="ignore"):
            E[5] = np.where(E[2] < 1.0, a / np.maximum(1.0 - E[2], 1e-300), 0.0)
        cdf[2] = _cdf_rows(grid, a)
        par[2] = 1.0
    return grid, E, cdf, par


def _fresnel_scalar(cos_i, eta):
    """Unpolarised Fresnel reflectance (the same closed form the kernels use), for the delta term."""
    return float(_k.fresnel_unpolarized(float(cos_i), float(eta)))


def flake_ndf_Beckmann(cos_theta, alpha):
    """The paper's flake normal density on the sphere (eq. 5), in 1/sr:
    D(m) = exp(−tan²θ/α²) / (2π α² |cos θ|³); symmetric under m → −m, ∫_sphere D dm = 1."""
    c = np.abs(np.asarray(cos_theta, dtype=float))
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        tan2 = (1.0 - c * c) / (c * c)
        d = np.exp(-tan2 / alpha**2) / (2 * np.pi * alpha**2 * c**3)
    return np.where(c > 0, d, 0.0)


def flake_ndf_GGX(cos_theta, alpha):
    """The GGX (Trowbridge–Reitz) flake normal density on the sphere, in 1/sr:
    D(m) = α² / (2π |cos θ|³ (α² + tan²θ)²); symmetric under m → −m, ∫_sphere D dm = 1."""
    c = np.abs(np.asarray(cos_theta, dtype=float))
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        tan2 = (1.0 - c * c) / (c * c)
        d = alpha**2 / (2 * np.pi * c**3 * (alpha**2 + tan2) ** 2)
    return np.where(c > 0, d, 0.0)


# ----------------------------------------------------------------------------------------------
# public API
# ----------------------------------------------------------------------------------------------


def simulate(problem, mu_i, n_paths, seed, mu_edges=None, phi_edges=None, *, max_scattering_orders=None,
             rr_threshold=RR_THRESHOLD):
    """Trace ``n_paths`` paths per channel for light incident from the air at ``mu_i`` = cos θ_i ∈ (0, 1].

    ``seed`` (int) fixes the random streams (results depend on ``seed`` and ``n_paths`` only).
    ``mu_edges`` (edges of |μ|, in [0, 1]) and ``phi_edges`` (edges of φ_d, in [0, π]) switch on the
    binned estimators (give both, or neither: a missing one defaults to a single bin over its range).
    ``max_scattering_orders``: keep only paths with at most this many volume scattering events
    (phase-function scatterings and flake reflections; interface and primer events do not count) —
    e.g. 1 gives the single-scattering solution; None = all orders (the weight of truncated paths
    is counted in ``Result.absorbed``).  Returns a :class:`Result`.
    """
    mu_i = float(mu_i)
    if not (0.0 < mu_i <= 1.0):
        raise ValueError(f"mu_i = {mu_i}; the incident cosine must be in (0, 1] (light travelling down).")
    n_paths = int(n_paths)
    if n_paths < 2:
        raise ValueError(f"n_paths = {n_paths}; need at least 2 paths for a standard error.")
    C = _validate(problem)
    binned = mu_edges is not None or phi_edges is not None
    me = _edges([0.0, 1.0] if mu_edges is None else mu_edges, 1.0, "mu_edges")
    pe = _edges([0.0, np.pi] if phi_edges is None else phi_edges, np.pi, "phi_edges")
    max_orders = -1 if max_scattering_orders is None else int(max_scattering_orders)

    top = problem.top
    eta = problem.eta_binder
    top_type = _k.TOP_NONE if top is None else (_k.TOP_SMOOTH if isinstance(top, Smooth) else _k.TOP_ROUGH)
    top_alpha = float(top.alpha) if isinstance(top, Rough) else 0.0
    F_i = _fresnel_scalar(mu_i, eta) if top_type == _k.TOP_SMOOTH else 0.0
    w_start = 1.0 - F_i

    n_b = min(N_BATCHES, n_paths)
    counts = np.full(n_b, n_paths // n_b, dtype=np.int64)
    counts[: n_paths % n_b] += 1
    seeds = np.random.SeedSequence(int(seed)).generate_state(4 * n_b, dtype=np.uint64).reshape(n_b, 4)
    seeds[np.all(seeds == 0, axis=1), 0] = np.uint64(0x9E3779B97F4A7C15)  # xoshiro state must be non-zero

    N = float(n_paths)

    def mean_se(s, s2):
        m = s / N
        var = max(s2 / N - m * m, 0.0)
        return m, math.sqrt(var / (N - 1.0))

    out = {k: np.zeros(C) for k in ("R", "Rse", "T", "Tse", "Td", "Tdse", "L", "Lse", "lost", "ev")}
    nmu, nphi = me.size - 1, pe.size - 1
    rb, rbse, tb, tbse = (np.zeros((C, nmu, nphi)) for _ in range(4))
    dmu = np.diff(me)[:, None]
    dphi = np.diff(pe)[None, :]
    omega = 2.0 * dmu * dphi  # solid angle of each (±φ) bin
    for c in range(C):
        bot_n, bot_k, bot_alpha = 1.0, 0.0, 1.0
        if isinstance(problem.bottom, Lambertian):
            bot_type, bot_alb = _k.BOTTOM_LAMBERT, float(_pick(problem.bottom.albedo, c, "bottom.albedo"))
        elif isinstance(problem.bottom, RoughConductor):
            Nc = np.atleast_1d(np.asarray(problem.bottom.N, dtype=complex))
            Nc = complex(Nc[0] if Nc.size == 1 else Nc[c]) / problem.slab_eta()[-1]
            bot_type, bot_alb = _k.BOTTOM_ROUGH_CONDUCTOR, 1.0
            bot_n, bot_k, bot_alpha = Nc.real, Nc.imag, float(problem.bottom.alpha)
        else:
            bot_type, bot_alb = _k.BOTTOM_NONE, 0.0
        pk = _pack(problem, c)
        ms_grid, ms_E, ms_cdf, ms_par = _ms_tables(problem, c)
        scal, rbin, tbin = _k.simulate_kernel(
            counts, seeds, mu_i, np.int64(top_type), eta, top_alpha, np.int64(bot_type), bot_alb, bot_n, bot_k,
            bot_alpha,
            pk["z_edges"], pk["sigma_bar"], pk["comp_start"], pk["comp_type"], pk["comp_sigma"],
            pk["comp_albedo"], pk["comp_g"], pk["comp_alpha"], pk["comp_off"], pk["comp_n"], pk["tab"],
            w_start, me, pe, np.int64(max_orders), np.int64(MAX_EVENTS), float(rr_threshold),
            ms_grid, ms_E, ms_cdf, ms_par, problem.slab_eta(), problem.slab_alpha())
        t = scal.sum(axis=0)
        out["R"][c], out["Rse"][c] = mean_se(t[_k.S_R], t[_k.S_R2])
        out["Td"][c], out["Tdse"][c] = mean_se(t[_k.S_TDIR], t[_k.S_TDIR2])
        out["T"][c], out["Tse"][c] = mean_se(t[_k.S_T] + t[_k.S_TDIR], t[_k.S_T2] + t[_k.S_TDIR2])
        out["L"][c], out["Lse"][c] = mean_se(t[_k.S_LOSS], t[_k.S_LOSS2])
        out["lost"][c] = t[_k.S_LOST]
        out["ev"][c] = t[_k.S_EVENTS] / N
        for src, dst, dse in ((rbin, rb, rbse), (tbin, tb, tbse)):
            s = src.sum(axis=0)
            m = s[..., 0] / N
            var = np.maximum(s[..., 1] / N - m * m, 0.0)
            dst[c] = m / omega
            dse[c] = np.sqrt(var / (N - 1.0)) / omega

    spec = np.full(C, F_i)
    res = Result(
        mu_i=mu_i, n_paths=n_paths, seed=int(seed),
        albedo=spec + out["R"], albedo_se=out["Rse"], specular=spec, diffuse_albedo=out["R"],
        transmittance=out["T"], transmittance_se=out["Tse"],
        transmittance_direct=out["Td"], transmittance_direct_se=out["Tdse"],
        interface_loss=out["L"], interface_loss_se=out["Lse"],
        absorbed=1.0 - spec - out["R"] - out["T"] - out["L"],
        n_lost=out["lost"].astype(np.int64), events_per_path=out["ev"],
        max_scattering_orders=max_scattering_orders,
    )
    if binned:
        res.mu_edges, res.phi_edges = me, pe
        res.reflectance_binned, res.reflectance_binned_se = rb, rbse
        res.transmittance_binned, res.transmittance_binned_se = tb, tbse
    return res


def directional_albedo(problem, mu_i, n_paths, seed, **kw):
    """Reflectance albedo R(μ_i) (with the specular delta separately), transmittance T(μ_i), errors.

    Same as :func:`simulate` without bins; returns the :class:`Result`.
    """
    return simulate(problem, mu_i, n_paths, seed, **kw)


def binned_reflectance(problem, mu_i, n_paths, seed, mu_edges, phi_edges, **kw):
    """BSDF × |μ_o| averaged over (|μ_o|, φ_d) bins of outgoing directions in air, in 1/sr.

    ``Result.reflectance_binned[c, i, j]`` = (power fraction into the bin, both ±φ_d, specular delta
    excluded) / (2 Δ|μ| Δφ); compare with :func:`bin_average` of f|μ_o| from a tabulated BSDF.
    """
    return simulate(problem, mu_i, n_paths, seed, mu_edges, phi_edges, **kw)


def bin_average(f_cos, mu_edges, phi_edges, n_quad=16):
    """Bin averages (1/(Δ|μ| Δφ)) ∫∫ f_cos(|μ|, φ_d) d|μ| dφ_d by Gauss–Legendre (n_quad² nodes per bin).

    ``f_cos(mu_abs, phi_d)`` is the BSDF times |μ_o| (vectorised, arrays of equal shape in, out).
    For a φ_d-even BSDF this is exactly what :func:`binned_reflectance` estimates.  Returns (n_mu, n_phi).

    A white Lambertian BSDF (f·|μ| = |μ|/π) over the half range φ_d ∈ [0, π] carries half its albedo 1;
    the rule is exact for it, bin by bin:

    >>> mu_edges, phi_edges = np.linspace(0.0, 1.0, 5), np.linspace(0.0, np.pi, 3)
    >>> avg = bin_average(lambda mu, phi: mu / np.pi, mu_edges, phi_edges)
    >>> avg.shape, round(float(np.sum(avg * np.outer(np.diff(mu_edges), np.diff(phi_edges)))), 12)
    ((4, 2), 0.5)
    >>> bool(np.allclose(avg[:, 0], 0.5 * (mu_edges[1:] + mu_edges[:-1]) / np.pi, rtol=1e-13, atol=0))
    True
    """
    me = _edges(mu_edges, 1.0, "mu_edges")
    pe = _edges(phi_edges, np.pi, "phi_edges")
    x, w = np.polynomial.legendre.leggauss(int(n_quad))
    mu = 0.5 * (me[:-1, None] + me[1:, None]) + 0.5 * np.diff(me)[:, None] * x[None, :]  # (nmu, q)
    ph = 0.5 * (pe[:-1, None] + pe[1:, None]) + 0.5 * np.diff(pe)[:, None] * x[None, :]  # (nphi, q)
    M = mu[:, None, :, None]
    P = ph[None, :, None, :]
    M, P = np.broadcast_arrays(M, P)
    vals = np.asarray(f_cos(M, P), dtype=float)
    return 0.25 * np.einsum("ijab,a,b->ij", vals, w, w)
