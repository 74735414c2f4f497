"""Sparkle for other renderers: the documented shader parameter set and a flake normal-map texture for
Mitsuba 3 (docs/texture.md §7).  :mod:`flakedb.render.mitsuba` (the ``measured`` export) is not
touched: this is a separate route that sits on top of it.

* :func:`shader_parameters`: per flake species the statistics a glint shader needs (number per mm²,
  log-normal diameters, Beckmann α, depth range, sRGB flake colour against the flake cosine) and,
  for an observer, the model's glint rate N_g and flake luminance factor β_ss on the (θ_h, θ_d) grid of
  :mod:`flakedb.render.sparkle` — enough to implement Jakob et al. 2014-style discrete glints with
  flakedb's counts, or to check a shader's counts against flakedb's.
* :func:`flake_normal_map`: a periodic texture (texels of a given physical size) of the flakes one
  sees from above: per texel the top-most flake's normal (x, y, z), and a coverage flag; flakes drawn
  from the recipe's statistics (Poisson centres, log-normal diameters, Beckmann normals; the hidden
  ones are overwritten by the ones above).  In Mitsuba 3, use it as the ``normalmap`` of a narrow
  ``roughconductor`` (α = the beam spread of docs/texture.md §2) blended (``blendbsdf``, weight = the
  coverage channel × the flake share) over the ``measured`` flakedb BSDF; the snippet is in
  docs/texture.md §7.  That blend is an approximation (its mean is not renormalised to the BSDF).
"""

from __future__ import annotations

import numpy as np

from flakedb.colour.colorimetry import XYZ_to_linear_sRGB, reflectance_to_XYZ
from flakedb.render.sparkle import HALF_GRID_DEG, TILT_GRID_DEG, glint_tables

#: Flake cosines of the colour table of :func:`shader_parameters`.
COLOUR_COS = np.linspace(0.2, 1.0, 9)


def shader_parameters(stack, spot_um, aperture_rad, source_half_angle_deg) -> dict:
    """The documented parameter set (module docstring), JSON-able; units in the keys."""
    species = []
    for f in stack.flakes:
        R = f.reflectance(COLOUR_COS)  # (C, 9)
        if stack.wavelength_nm is not None and R.shape[0] > 1:
            rgb = np.maximum(XYZ_to_linear_sRGB(reflectance_to_XYZ(R.T, stack.wavelength_nm)), 0.0).tolist()
        else:
            rgb = np.repeat(R.mean(axis=0)[:, None], 3, axis=1).tolist()
        species.append({"name": f.name, "flakes_per_mm2": f.areal_density_per_um2 * 1e6,
                        "diameter_median_um": f.diameter_median_um, "diameter_gsd": f.diameter_gsd,
                        "orientation_alpha_beckmann": f.alpha, "flake_thickness_um": f.flake_thickness_um,
                        "depth_um": [f.z_top_um, f.z_top_um + f.thickness_um],
                        "flake_cos": COLOUR_COS.tolist(), "flake_linear_srgb": rgb})
    n_g, b_ss = glint_tables(stack, spot_um, aperture_rad, source_half_angle_deg)
    return {"model": "flakedb docs/texture.md", "binder_ior": stack.eta, "species": species,
            "observer": {"spot_um": spot_um, "aperture_half_angle_rad": aperture_rad,
                         "source_half_angle_deg": source_half_angle_deg},
            "grid": {"theta_h_binder_deg": TILT_GRID_DEG.tolist(), "theta_d_binder_deg": HALF_GRID_DEG.tolist()},
            "glints_per_mm2": (n_g * 1e6).tolist(), "flake_luminance_factor": b_ss.tolist(),
            "definitions": {"glints_per_mm2": "flakes at least half as bright as an aligned surface flake (§3.3)",
                            "flake_luminance_factor": "pi f_ss of the flakes' mirror reflections (§3.4, eq. S3)"}}


def flake_normal_map(stack, size, texel_um, seed=0):
    """(size, size, 4) float32 periodic texture: top-most flake normal (x, y, z) in [−1, 1] and a
    coverage flag (1 where a flake is seen from above), of the first flake species (module docstring).

    Unit normals, and a covered fraction near the Poisson value 1 − exp(−N_A ⟨A⟩) (131 flakes here: a few
    per cent of statistical scatter):

    >>> from flakedb.texture.model import FlakeLayer, TextureStack
    >>> c = np.linspace(0.0, 1.0, 5)
    >>> f = FlakeLayer("al", 0.0, 10.0, 2e-4, 15.0, 1.0, 0.3, 0.2, c, np.full((1, 5), 0.9), np.zeros((1, 5)))
    >>> m = flake_normal_map(TextureStack(1.5, np.array([1.0]), (f,)), 128, 2.0, seed=0)
    >>> poisson = 1.0 - np.exp(-f.areal_density_per_um2 * f.mean_area_um2())
    >>> m.shape, bool(np.allclose(np.linalg.norm(m[..., :3], axis=-1), 1.0, atol=1e-6)), bool(abs(m[..., 3].mean() - poisson) < 0.05)
    ((128, 128, 4), True, True)
    """
    f = stack.flakes[0]
    rng = np.random.default_rng([int(seed), 0x7E])
    L = size * float(texel_um)
    n = rng.poisson(f.areal_density_per_um2 * L * L)
    x, y = rng.random(n) * L, rng.random(n) * L
    z = f.z_top_um + rng.random(n) * f.thickness_um
    D = f.diameter_median_um * np.exp(np.log(f.diameter_gsd) * rng.standard_normal(n))
    tan2 = -(f.alpha**2) * np.log1p(-rng.random(n))
    ct = 1.0 / np.sqrt(1.0 + tan2)
    st = np.sqrt(tan2) * ct
    ph = 2.0 * np.pi * rng.random(n)
    out = np.zeros((size, size, 4), np.float32)
    out[..., 2] = 1.0
    c = (np.arange(size) + 0.5) * texel_um
    for i in np.argsort(-z):  # deepest first: the flakes above overwrite the ones they hide
        r = 0.5 * D[i]
        i0, i1 = int(np.floor((x[i] - r) / texel_um)), int(np.floor((x[i] + r) / texel_um))
        j0, j1 = int(np.floor((y[i] - r) / texel_um)), int(np.floor((y[i] + r) / texel_um))
        ii = np.arange(i0, i1 + 1)
        jj = np.arange(j0, j1 + 1)
        dx = (c[ii % size] + (ii - ii % size) * texel_um) - x[i]
        dy = (c[jj % size] + (jj - jj % size) * texel_um) - y[i]
        m = (dx[:, None] ** 2 + dy[None, :] ** 2) <= r * r
        if not m.any():
            continue
        gi, gj = np.meshgrid(ii % size, jj % size, indexing="ij")
        out[gj[m], gi[m]] = (st[i] * np.cos(ph[i]), st[i] * np.sin(ph[i]), ct[i], 1.0)
    return out
