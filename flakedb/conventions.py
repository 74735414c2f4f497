"""The conventions every flakedb module follows, stated once (docs/model.md §2, docs/bsdf-format.md).

Other modules refer to this docstring as "conventions" instead of restating it.

Directions and angles
---------------------
* A direction is the **propagation** direction of light (where it travels), a unit vector.
* ``mu`` is the cosine of the propagation direction against the **downward** axis (into the stack):
  ``mu > 0`` travels down (light arriving from above), ``mu < 0`` travels up (light leaving the top).
  This is the convention of layerlab and of the Fourier ``.bsdf`` file, so the solver's arrays go to
  the file without sign flips.  Reflection seen from above: incident ``mu_i > 0``, outgoing
  ``mu_o < 0``.  In 3-D, a propagation direction is ``(sqrt(1-mu²) cos φ, sqrt(1-mu²) sin φ, -mu)``
  in a frame whose z axis is the surface normal pointing up (out of the paint).
* ``phi_d`` is the difference of the azimuths of the outgoing and incident *propagation*
  directions, ``phi_d = phi_o - phi_i``.  ``phi_d = 0`` is mirror reflection / straight
  transmission (forward scattering); **backscatter (retro-reflection) is phi_d = π**.
  With the graphics convention (both vectors pointing away from the surface), ``phi_d = π − (φ_o − φ_i)``.
* An azimuthally isotropic stack is even in ``phi_d``: ``f(mu_i, mu_o, phi_d) = Σ_l f_l(mu_i, mu_o) cos(l phi_d)``.

Refractive indices
------------------
* Complex index ``N = n + i k`` with ``k >= 0`` absorbing (time dependence ``exp(-i ω t)``).
* ``eta`` of an interface is ``eta_below / eta_above`` (relative index of the medium below the
  interface to the one above it).
* Mie: relative index ``m = N_particle / n_binder``; size parameter ``x = 2π r n_binder / λ_vacuum``.
* Wavelengths are vacuum wavelengths in nm (``wavelength_nm``); lengths in µm (``_um``) unless a
  suffix says otherwise.

Radiance across interfaces
--------------------------
The solver's matrices act on **basic radiance** ``L / η²`` (η the real index of the medium the light
is in).  Basic radiance is conserved by a smooth interface up to the Fresnel transmittance, so
refraction is a plain node-to-node map.  A radiance BSDF for transmission from a medium of index
``η_i`` into one of index ``η_o`` is ``f_radiance = (η_o/η_i)² f_basic``.  Reciprocity (the η² rule,
Veach 1997 eq. 5.14) reads ``f_radiance(i→o)/η_o² = f_radiance(o→i)/η_i²``, i.e.
``f_basic(i→o)/η_i² = f_basic(o→i)/η_o²``.

Scattering matrices (the solver's normalisation)
------------------------------------------------
Quadrature nodes ``mu_j`` with weights ``w_j`` (one rule per hemisphere, no node at 0).  Radiance
is a cosine series in azimuth, ``L(mu, phi) = Σ_l L_l(mu) cos(l phi)``.  A scattering operator acts
order by order as ``L_out,l(mu_o) = Σ_i S_l[o, i] L_in,l(mu_i)`` with

    S_l[o, i] = c_l · w_i · |mu_i| · f_l(mu_i → mu_o),     c_0 = 2π,  c_l = π (l > 0),

where ``f_l`` is the cosine-series coefficient of the BSDF (in 1/sr) in ``phi_d``.  With this
normalisation an empty layer is exactly the identity and the adding equations (paper eq. 4) apply
as plain matrix products.  Stored coefficients (``.bsdf`` files) are those of ``f · |mu_o|`` (no
quadrature weights, no 1/π beyond what f contains).

Phase functions and kernels
---------------------------
A phase function ``p(cos Θ)`` is normalised to integrate to 1 over the sphere (units 1/sr), with
``cos Θ = ω_in · ω_out`` of propagation directions (``cos Θ = 1`` is forward).  A scattering kernel
``k(ω_in → ω_out) = σ_s(ω_in) p(ω_in → ω_out)`` has units 1/(µm·sr).
"""
import numpy as np


def fourier_weight(order):
    """Azimuthal factor c_l of the scattering-matrix normalisation: 2π for l = 0, π otherwise.

    ``order`` may be an int or an integer array; returns float(s).  See the module docstring.

    c_l is ∫₀^{2π} cos²(l φ) dφ:

    >>> phi = np.linspace(0.0, 2 * np.pi, 4097)[:-1]                    # exact for trigonometric polynomials
    >>> [round(float(np.cos(l * phi) @ np.cos(l * phi) * (2 * np.pi / phi.size) / fourier_weight(l)), 12) for l in (0, 1, 5)]
    [1.0, 1.0, 1.0]
    """
    order = np.asarray(order)
    return np.where(order == 0, 2.0 * np.pi, np.pi)
