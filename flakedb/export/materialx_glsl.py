"""What MaterialX's own GLSL renderer draws for the ``.mtlx`` of :mod:`flakedb.export.materialx`:
the ``open_pbr_surface`` node graph of MaterialX 1.39 (``libraries/bxdf/open_pbr_surface.mtlx``,
``NG_open_pbr_surface_surfaceshader``) as its GLSL closures evaluate it
(``libraries/pbrlib/genglsl``: ``mx_dielectric_bsdf``, ``mx_generalized_schlick_bsdf``,
``mx_oren_nayar_diffuse_bsdf``, ``mx_layer_bsdf``, ``mx_add_bsdf``; ``lib/mx_microfacet_specular.glsl``;
``lib/mx_environment_fis.glsl``), written out in numpy for the inputs flakedb writes
(:func:`flakedb.export.materialx.openpbr_inputs`: no transmission, subsurface, fuzz or emission,
``base_diffuse_roughness`` 0, ``coat_darkening`` 0, ``coat_color`` 1, isotropic roughness).

For one light direction ω_l (``CLOSURE_TYPE_REFLECTION``; a ``directional_light`` of ``intensity`` E
adds ``E · response``, lights/genglsl/mx_directional_light.glsl) each closure returns its
``response`` (f cos θ_l) and a ``throughput`` that the ``layer`` node multiplies into the layer
below (``response = top + throughput · base``, mx_layer_bsdf.glsl)::

    L = E [ coat + t_c(μ_v) ( (1 - m) (spec + t_s(μ_v) c μ_l / π) + m metal ) ]

    lobe(F)  = D(h; α) F G2(μ_l, μ_v; α) comp / (4 μ_v),   comp = 1 + F (1 - E_ss(μ_v)) / E_ss(μ_v)
    coat     = lobe(F(cos θ_d; η_c)) at α_c = r_c²;   t_c = 1 - A(μ_v, α_c; F0(η_c), 1) comp
    spec     = s · lobe(F(cos θ_d; η_s)) at α = r_e²;  t_s = 1 - A(μ_v, α; F0(η_s), 1) comp
    metal    = lobe(F_82(cos θ_d; c, s)) at α = r_e²

with D the GGX distribution (``mx_ggx_NDF``), G2 the height-correlated Smith term
(``mx_ggx_smith_G2``, Heitz 2014 eqs. 72 and 99), F the exact unpolarised dielectric Fresnel
(``mx_fresnel_dielectric``), F_82 the Hoffman / Kutz F82-tint Schlick curve
(``mx_fresnel_hoffman_schlick``, exponent 5, F90 = 1), A = F0 a + F90 b MaterialX's rational fit
of the GGX albedo (``mx_ggx_dir_albedo_analytic``: its default ``DIRECTIONAL_ALBEDO_METHOD`` 0),
E_ss = A(μ_v, α; 1, 1) (``mx_ggx_energy_compensation``, Turquin 2019: the comp factor uses the
closure's own F, at cos θ_d for a light, at μ_v for the environment), α clamped to
[1e-8, 1] (``M_FLOAT_EPS``), the diffuse the energy-compensated Oren-Nayar at roughness 0
(exactly Lambert: its multiple-scattering term is ``c² · 1e-8``).  The node graph's inputs:
with a coat, the base's relative index is η_s = ``specular_ior / coat_ior`` (its inverse below 1:
the spec's TIR fix; flakedb writes ``specular_ior = n_s η_c``, so η_s = n_s) and its roughness
r_e = min(1, r⁴ + 2 r_c⁴)^¼ (the coat's roughening); without one (``coat_weight`` 0), η_s =
``specular_ior`` and r_e = r.  So ``coat_weight = 0`` alone changes the base:
:func:`uncoated_inputs` also rewrites those two inputs, which leaves the base exactly as it was.

Where MaterialX differs from the fitted model (:func:`flakedb.export.openpbr.evaluate`): the coat's
and the dielectric lobe's albedo scaling at the view end only (the model: both ends), taken from
the rational fit A and not from F(μ_v) (at α_c → 0, A(μ; F0, 1) - F(μ; 1.5) = +0.0025 at μ = 1),
and the energy compensation ``comp`` on every lobe (the model: single scattering).

The uniform environment (``CLOSURE_TYPE_INDIRECT``, a latlong map of radiance L, filtered
importance sampling with ``$envRadianceSamples`` samples of the GGX visible-normal distribution,
spherical-Fibonacci points): a lobe returns ``L comp Σ_i F(v·h_i) G2(μ_l,i, μ_v) / (G1(μ_v) N)``
(:func:`fis_lobe_uniform`); the coat's own reflection of the uniform sky is that at α_c
with F(·; η_c): at α_c = 1e-8 it is F(μ_v; η_c) comp to float precision.
"""

from __future__ import annotations

import numpy as np

from flakedb.export.openpbr import OpenPBRFit
from flakedb.optics.fresnel import fresnel_dielectric_real

#: MaterialX's ``M_FLOAT_EPS`` (stdlib/genglsl/lib/mx_math.glsl): the smallest α and cosine.
M_FLOAT_EPS = 1e-8
#: ``mx_fresnel_hoffman_schlick``: the F82 cosine 1/7.
F82_COS = 1.0 / 7.0
#: ``mx_golden_ratio_sequence``
GOLDEN_RATIO = 1.6180339887498948


def ggx_dir_albedo_analytic(mu, alpha, F0, F90):
    """MaterialX's rational fit of the GGX directional albedo, ``F0 a + F90 b``
    (``mx_ggx_dir_albedo_analytic``, mx_microfacet_specular.glsl), broadcasting; μ = cos θ_v."""
    x, y = np.asarray(mu, float), np.asarray(alpha, float)
    x2, y2 = x * x, y * y
    c = np.array([[0.1003, 0.9345, 1.0, 1.0], [-0.6303, -2.323, -1.765, 0.2281], [9.748, 2.229, 8.263, 15.94],
                  [-2.038, -3.748, 11.53, -55.83], [29.34, 1.424, 28.96, 13.08], [-8.245, -0.7684, -7.507, 41.26],
                  [-26.44, 1.436, -36.11, 54.9], [19.99, 0.2913, 15.86, 300.2], [-5.448, 0.6286, 33.37, -285.1]])
    terms = [np.ones_like(x * y), x, y, x * y, x2, y2, x2 * y, x * y2, x2 * y2]
    r = [sum(t * c[k, j] for k, t in enumerate(terms)) for j in range(4)]
    a, b = np.clip(r[0] / r[2], 0.0, 1.0), np.clip(r[1] / r[3], 0.0, 1.0)
    return F0 * a + F90 * b


def ior_to_f0(ior):
    """``mx_ior_to_f0``: ((n - 1) / (n + 1))²."""
    return ((np.asarray(ior, float) - 1.0) / (np.asarray(ior, float) + 1.0)) ** 2


def fresnel_hoffman_schlick(cos_theta, F0, F82, F90=1.0, exponent=5.0):
    """``mx_fresnel_hoffman_schlick`` (Hoffman 2023, the F82-tint curve): cos θ (...,), F0/F82/F90 (3,) → (..., 3)."""
    x = np.clip(np.asarray(cos_theta, float), 0.0, 1.0)[..., None]
    F0, F82, F90 = (np.asarray(v, float) * np.ones(3) for v in (F0, F82, F90))
    factor = 1.0 / (F82_COS * (1.0 - F82_COS) ** 6)
    a = (F0 + (F90 - F0) * (1.0 - F82_COS) ** exponent) * (1.0 - F82) * factor
    return F0 + (F90 - F0) * (1.0 - x) ** exponent - a * x * (1.0 - x) ** 6


def ggx_ndf(cos_h, alpha):
    """``mx_ggx_NDF`` for an isotropic α: 1 / (π α² (sin²θ_h / α² + cos²θ_h)²)."""
    c2 = np.asarray(cos_h, float) ** 2
    return 1.0 / (np.pi * alpha * alpha * ((1.0 - c2) / (alpha * alpha) + c2) ** 2)


def smith_G1(mu, alpha):
    """``mx_ggx_smith_G1`` (Walter et al. 2007 eq. 34)."""
    m2 = np.asarray(mu, float) ** 2
    return 2.0 / (1.0 + np.sqrt(1.0 + alpha * alpha * (1.0 - m2) / m2))


def smith_G2(mu_l, mu_v, alpha):
    """``mx_ggx_smith_G2``: height-correlated Smith masking-shadowing (Heitz 2014 eqs. 72, 99)."""
    a2 = alpha * alpha
    ll = np.sqrt(a2 + (1.0 - a2) * mu_l * mu_l)
    lv = np.sqrt(a2 + (1.0 - a2) * mu_v * mu_v)
    return 2.0 * mu_l * mu_v / (ll * mu_v + lv * mu_l)


def energy_compensation(mu_v, alpha, F):
    """``mx_ggx_energy_compensation``: 1 + F (1 - E_ss) / E_ss, E_ss = A(μ_v, α; 1, 1)."""
    Ess = ggx_dir_albedo_analytic(mu_v, alpha, 1.0, 1.0)
    Ess = Ess[..., None] if np.ndim(F) > np.ndim(Ess) else Ess
    return 1.0 + F * (1.0 - Ess) / Ess


def closure_inputs(fit: OpenPBRFit, coat: bool = True) -> dict:
    """The closure inputs the node graph derives from the written inputs (module docstring):
    coat_weight, η_c, α_c, η_s, α (of r_e), m, c, s; ``coat=False``: the uncoated file of
    :func:`uncoated_inputs`, whose base is the same.

    >>> k = closure_inputs(OpenPBRFit((0.5, 0.5, 0.5), 0.0, 0.4, 1.5, 0.0, specular_ior_relative=3.0))
    >>> round(k["eta_s"], 12), round(k["alpha"], 12), k["coat_weight"]
    (3.0, 0.16, 1.0)
    """
    cw = 1.0 if (coat and fit.coat_ior > 1.0) else 0.0
    r, rc = float(fit.specular_roughness), float(fit.coat_roughness)
    r_e = min(1.0, (2.0 * rc ** 4 + r ** 4) ** 0.25) if fit.coat_ior > 1.0 else r
    eta_s = float(fit.specular_ior) / max(float(fit.coat_ior), 1.0) if fit.coat_ior > 1.0 else float(fit.specular_ior)
    eta_s = eta_s if eta_s > 1.0 else (1.0 / eta_s if eta_s > 0 else 1.0)
    return {"coat_weight": cw, "eta_c": float(fit.coat_ior), "alpha_c": float(np.clip(rc * rc, M_FLOAT_EPS, 1.0)),
            "eta_s": eta_s, "alpha": float(np.clip(r_e * r_e, M_FLOAT_EPS, 1.0)), "m": float(fit.base_metalness),
            "c": np.asarray(fit.base_color, float), "s": np.asarray(fit.specular_color, float)}


def uncoated_inputs(specular_ior: float, coat_ior: float, specular_roughness: float, coat_roughness: float) -> dict:
    """The ``open_pbr_surface`` inputs that remove the coat of a coated document and keep its base as
    it was under the coat: ``coat_weight`` 0, ``specular_ior`` = η_s (the index the base had relative
    to the coat, the node graph's TIR fix included) and ``specular_roughness`` = r_e (the roughness
    the coat gave it) (module docstring).

    >>> uncoated_inputs(4.5, 1.5, 0.4, 0.0) == {"coat_weight": 0.0, "specular_ior": 3.0, "specular_roughness": 0.4}
    True
    """
    ratio = specular_ior / coat_ior
    eta_s = ratio if ratio > 1.0 else coat_ior / specular_ior
    r_e = min(1.0, 2.0 * coat_roughness ** 4 + specular_roughness ** 4) ** 0.25
    return {"coat_weight": 0.0, "specular_ior": float(eta_s), "specular_roughness": float(r_e)}


def _lobe(mu_v, mu_l, cos_h, cos_d, alpha, F):
    """``response`` of a GGX reflection closure (f cos θ_l) and its ``comp``: F (..., 3)."""
    comp = energy_compensation(mu_v, alpha, F)
    D = ggx_ndf(cos_h, alpha)
    G = smith_G2(mu_l, mu_v, alpha)
    return (D * G / (4.0 * mu_v))[..., None] * F * comp, comp


def materialx_response(fit: OpenPBRFit, N, l, v=(0.0, 0.0, 1.0), coat: bool = True) -> np.ndarray:
    """The closure tree's ``response`` (f cos θ_l, (..., 3)) at unit normals N (..., 3) for a light
    towards ``l`` and the viewer towards ``v`` (module docstring); 0 where the light is below the
    horizon (MaterialX clamps μ_l to 1e-8 there: a response below 1e-7)."""
    k = closure_inputs(fit, coat)
    N = np.asarray(N, float)
    l = np.asarray(l, float) / np.linalg.norm(l)
    v = np.asarray(v, float) / np.linalg.norm(v)
    mu_v = np.clip(N @ v, M_FLOAT_EPS, 1.0)
    mu_l_raw = N @ l
    mu_l = np.clip(mu_l_raw, M_FLOAT_EPS, 1.0)
    h = (l + v) / np.linalg.norm(l + v)
    cos_h = np.clip(N @ h, 0.0, 1.0)
    cos_d = np.clip(np.dot(v, h), M_FLOAT_EPS, 1.0) * np.ones_like(mu_v)
    # base: dielectric lobe tinted s over Lambert c (layer), mixed with the F82 metal
    F_s = np.repeat(fresnel_dielectric_real(cos_d, k["eta_s"])[..., None], 3, -1)
    spec, comp_s = _lobe(mu_v, mu_l, cos_h, cos_d, k["alpha"], F_s)
    t_s = 1.0 - ggx_dir_albedo_analytic(mu_v, k["alpha"], ior_to_f0(k["eta_s"]), 1.0)[..., None] * comp_s
    diffuse = k["c"] * (mu_l / np.pi)[..., None]
    dielectric = spec * k["s"] + t_s * diffuse
    metal, _ = _lobe(mu_v, mu_l, cos_h, cos_d, k["alpha"], fresnel_hoffman_schlick(cos_d, k["c"], k["s"]))
    base = (1.0 - k["m"]) * dielectric + k["m"] * metal
    out = base
    if k["coat_weight"] > 0:
        F_c = np.repeat(fresnel_dielectric_real(cos_d, k["eta_c"])[..., None], 3, -1)
        lobe_c, comp_c = _lobe(mu_v, mu_l, cos_h, cos_d, k["alpha_c"], F_c)
        t_c = 1.0 - ggx_dir_albedo_analytic(mu_v, k["alpha_c"], ior_to_f0(k["eta_c"]), 1.0)[..., None] * comp_c
        out = lobe_c + t_c * base
    return np.where((mu_l_raw > 0)[..., None], out, 0.0)


def materialx_sun_image(fit: OpenPBRFit, size: int = 32, direction=(0.0, 0.0, 1.0), irradiance: float = 1.0,
                        extent: float = 1.05, coat: bool = True) -> np.ndarray:
    """(size, size, 3) image that MaterialX's GLSL renderer draws of the ``.mtlx`` on the unit sphere
    under one ``directional_light`` of ``intensity`` = ``irradiance`` towards ``direction``, no
    environment, viewed along -z (orthographic), at pixel centres in the frame of
    :func:`flakedb.export.blender.render_cycles_sphere` (row 0 at the top); ``coat=False``: the
    uncoated file (:func:`uncoated_inputs`).  Raises ValueError for a fit with a thin film
    (MaterialX's Airy Fresnel, ``mx_fresnel_airy``, is not written out here).

    A white diffuse sphere (no lobe: η_s = 1, F0 = 0): E cos θ / π, less the 0.1 % that the lobe's
    throughput takes even at F0 = 0 (MaterialX passes F90 = 1 to the albedo fit, whose b term at
    α = 1 is 1e-3):

    >>> img = materialx_sun_image(OpenPBRFit((1.0, 1.0, 1.0), 0.0, 1.0, 1.0, 0.0), size=8, extent=1.0)
    >>> mu = np.sqrt(1 - 2 * 0.125 ** 2)
    >>> t_s = 1 - ggx_dir_albedo_analytic(mu, 1.0, 0.0, 1.0)
    >>> bool(np.allclose(img[3:5, 3:5], mu / np.pi * t_s, rtol=1e-12)), round(float(t_s), 4)
    (True, 0.999)
    """
    if fit.thin_film_thickness_nm > 0:
        raise ValueError("materialx_sun_image: a fit with a thin film (MaterialX's mx_fresnel_airy is not modelled)")
    x = -extent + (np.arange(size) + 0.5) * 2 * extent / size
    X, Y = np.meshgrid(x, x[::-1])
    r2 = X * X + Y * Y
    on = r2 < 1
    N = np.stack([X, Y, np.sqrt(np.clip(1 - r2, 0, 1))], axis=-1)
    img = np.zeros((size, size, 3))
    img[on] = materialx_response(fit, N[on], direction, coat=coat) * irradiance
    return img


def coat_throughput(fit: OpenPBRFit, mu_v) -> np.ndarray:
    """t_c(μ_v) of the coat in the uniform environment (``CLOSURE_TYPE_INDIRECT``: comp at F(μ_v)):
    what the coat's ``layer`` passes of the base's environment response (module docstring)."""
    k = closure_inputs(fit, coat=True)
    mu = np.clip(np.asarray(mu_v, float), M_FLOAT_EPS, 1.0)
    if k["coat_weight"] == 0:
        return np.ones_like(mu)
    F = fresnel_dielectric_real(mu, k["eta_c"])
    comp = energy_compensation(mu, k["alpha_c"], F)
    return 1.0 - ggx_dir_albedo_analytic(mu, k["alpha_c"], ior_to_f0(k["eta_c"]), 1.0) * comp


def fis_lobe_uniform(mu_v, alpha: float, eta: float, samples: int) -> np.ndarray:
    """A dielectric closure's ``response`` in a uniform environment of radiance 1 (``mx_environment_radiance``
    of lib/mx_environment_fis.glsl with ``samples`` = ``$envRadianceSamples``, times ``comp``): the
    mean over the spherical-Fibonacci points ((i + ½)/N, frac((i + 1) φ)) of the GGX visible normals
    (``mx_ggx_importance_sample_VNDF``, Dupuy & Benyoub 2023) of F(v·h; η) G2(μ_l, μ_v) / G1(μ_v)."""
    mu = np.clip(np.asarray(mu_v, float), M_FLOAT_EPS, 1.0)[..., None]
    V = np.stack([np.sqrt(1 - mu * mu), np.zeros_like(mu), mu], -1)              # (..., 1, 3)
    i = np.arange(samples)
    u1, u2 = (i + 0.5) / samples, np.mod((i + 1.0) * GOLDEN_RATIO, 1.0)
    Vh = V * np.array([alpha, alpha, 1.0])
    Vh = Vh / np.linalg.norm(Vh, axis=-1, keepdims=True)
    phi = 2 * np.pi * u1
    z = (1.0 - u2) * (1.0 + Vh[..., 2]) - Vh[..., 2]
    st = np.sqrt(np.clip(1 - z * z, 0, 1))
    H = np.stack([st * np.cos(phi), st * np.sin(phi), z], -1) + Vh
    H = H * np.array([alpha, alpha, 1.0])
    H[..., 2] = np.maximum(H[..., 2], 0.0)
    H = H / np.linalg.norm(H, axis=-1, keepdims=True)
    vh = np.sum(V * H, -1)
    L = 2 * vh[..., None] * H - V
    mu_l = np.clip(L[..., 2], M_FLOAT_EPS, 1.0)
    F = fresnel_dielectric_real(np.clip(vh, M_FLOAT_EPS, 1.0), eta)
    G = smith_G2(mu_l, mu, alpha)
    radiance = np.sum(F * G, -1) / (smith_G1(mu[..., 0], alpha) * samples)
    F_v = fresnel_dielectric_real(mu[..., 0], eta)
    return radiance * energy_compensation(mu[..., 0], alpha, F_v)


def coat_furnace_reflection(fit: OpenPBRFit, mu_v, samples: int) -> np.ndarray:
    """The coat's own reflection of a uniform sky of radiance 1 in MaterialX (``fis_lobe_uniform`` at
    α_c, η_c); at α_c = 1e-8 it is F(μ_v; η_c) · comp(μ_v)."""
    k = closure_inputs(fit, coat=True)
    if k["coat_weight"] == 0:
        return np.zeros_like(np.asarray(mu_v, float))
    return fis_lobe_uniform(mu_v, k["alpha_c"], k["eta_c"], samples)


def compensated_lobe_colours(colours, mu_v, alpha: float) -> np.ndarray:
    """The ``color0 = color90`` F to give a ``generalized_schlick_bsdf`` (GGX of ``alpha``) so that MaterialX's
    GLSL closure, which multiplies its lobe by F · comp with ``comp = 1 + F (1 - E_ss(μ_v, α)) / E_ss``
    (:func:`energy_compensation`), draws the lobe with the colour ``colours`` C: the non-negative root of
    F + F² x = C, x = (1 - E_ss) / E_ss, i.e. F = (√(1 + 4 x C) - 1) / (2 x) (F = C where x = 0).
    ``colours`` (..., 3) at view cosines ``mu_v`` (...).

    >>> mu, C = np.array([0.2, 0.7, 1.0]), np.array([[0.1, 0.5, 1.2]] * 3)
    >>> F = compensated_lobe_colours(C, mu, 0.42)
    >>> bool(np.allclose(F * energy_compensation(mu[:, None] * np.ones(3), 0.42, F), C, rtol=1e-12)), bool(np.all(F < C))
    (True, True)
    """
    C = np.maximum(np.asarray(colours, float), 0.0)
    Ess = ggx_dir_albedo_analytic(np.clip(np.asarray(mu_v, float), M_FLOAT_EPS, 1.0), alpha, 1.0, 1.0)[..., None]
    x = (1.0 - Ess) / Ess
    safe = np.where(x > 0, x, 1.0)
    return np.where(x > 0, (np.sqrt(1.0 + 4.0 * safe * C) - 1.0) / (2.0 * safe), C)
