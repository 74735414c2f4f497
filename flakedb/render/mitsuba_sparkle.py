"""Sparkle for other renderers: the documented shader parameter set and a Mitsuba 3 glint layer
(docs/texture.md §7).  :mod:`flakedb.render.mitsuba` (the ``measured`` export) is not touched: this
is a separate route that sits on top of it.

* :func:`shader_parameters`: per flake species the statistics a glint shader needs (number per mm²,
  log-normal diameters, Beckmann α, depth range, sRGB flake colour against the flake cosine) and,
  for an observer, the model's glint rate N_g and flake luminance factor β_ss on the (θ_h, θ_d) grid of
  :mod:`flakedb.render.sparkle` — enough to implement Jakob et al. 2014-style discrete glints with
  flakedb's counts, or to check a shader's counts against flakedb's.
* :func:`flake_map`: a periodic texture (texels of a given physical size) of the flakes one sees
  from above: per texel the top-most flake's *binder* normal, its diameter and index; flakes drawn
  from the recipe's statistics (Poisson centres, log-normal diameters, Beckmann normals; the hidden
  ones are overwritten by the ones above).  :func:`flake_normal_map` is its (normal, coverage) part.
* :func:`glint_layer`: the per-texel inputs of a normal-mapped, narrow ``roughconductor`` that
  reproduces the flakes' glints seen through the smooth coat (docs/texture.md §7):

  - **normal** (:func:`apparent_normals`): the *apparent air facet* of a binder flake of tilt θ_b,
    the half-vector in air of the ray pair it mirrors for a view along the panel normal: tilt
    θ_a = ½ asin(η sin 2θ_b), same azimuth.  Exact (by reciprocity) whenever the view *or* the light
    is along the normal — the instrument presets (camera at 0°) — for any light angle; off that,
    :func:`mapping_error_deg` gives the angle between the mapped and the true air half-vector.
    Flakes with η sin 2θ_b ≥ 1 send a normal-incidence beam into total internal reflection: they
    never glint toward a normal view (gain 0; their light stays in the ``measured`` BSDF).
  - **gain** (the conductor's ``specular_reflectance``): T_in(μ_l) T_out(1) R(c) c with
    c = cos θ_b, μ_l = cos 2θ_a — the flake's mirror reflection through the coat, normalised so that
    the layer's area mean under a directional source equals the model's flake luminance factor β_ss
    (docs/texture.md eq. S3; derivation in §7; tested).
  - **alpha** (Beckmann, per texel): the lobe whose half-maximum region in air half-vector space
    holds as many flake normals as the model's φ ≥ ½ region (eq. S2: π d½²/(4c) in binder normal
    space, d½ from the source ⊗ diffraction disc of the flake's own diameter, §2):
    α² = J d½²/(4c ln 2), J = c η² μ_l'/(μ_l cos θ_a) the binder-normal → air-half-vector area ratio.
    So the glint *count* per mm² is the model's to first order in the cone sizes.
* :func:`blend_weight`: the ``blendbsdf`` weight s = β_ss/M (the flakes' share of the paint's
  luminance factor M at the design geometry); the glint texture's gain is divided by s, so the
  blend (1 − s)·measured + s·(glints/s) keeps the large-area mean of the ``measured``-only render
  to the accuracy of the glint layer's β_ss (measured in tests/texture/test_mitsuba_sparkle.py).
* :func:`material_xml`: a Mitsuba 3 XML file (``<include>`` it in a scene) with that material.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from flakedb.colour.colorimetry import XYZ_to_linear_sRGB, reflectance_to_XYZ
from flakedb.render.sparkle import HALF_GRID_DEG, TILT_GRID_DEG, glint_tables
from flakedb.texture.model import (
    GLINT_FRACTION,
    coat_transmittance,
    cone_solid_angle,
    diffraction_radius,
    lens_area,
    sparkle_indices,
)

#: Flake cosines of the colour table of :func:`shader_parameters`.
COLOUR_COS = np.linspace(0.2, 1.0, 9)
#: Beckmann α of the texels without an exiting flake (their gain is 0: any value will do).
ALPHA_NONE = 0.05
#: Nodes of the d½(r_small/r_big) table of :func:`half_max_offset` (linear interpolation between them).
N_HALF_MAX = 129
#: Names of the Mitsuba route's files for a recipe NAME (docs/texture.md §7).
FILES = {"normals": "{name}.flakes.exr", "alpha": "{name}.glint_alpha.exr", "gain": "{name}.glint_gain.exr",
         "params": "{name}.sparkle.json", "xml": "{name}.sparkle.xml"}


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


def flake_map(stack, size, texel_um, seed=0) -> dict:
    """The top-most flakes seen from above on a periodic (size, size) grid of ``texel_um`` texels, first
    flake species: ``normal`` (size, size, 3) binder normals (z where none), ``coverage`` (0/1),
    ``diameter_um``, ``depth_um`` (0 where none), ``flake_id`` (−1 where none; an index into the drawn flakes).

    Every visible texel of a flake carries that flake's normal and diameter:

    >>> from flakedb.texture.model import FlakeLayer, TextureStack
    >>> c = np.linspace(0.0, 1.0, 5)
    >>> f = FlakeLayer("al", 0.0, 10.0, 2e-4, 15.0, 1.3, 0.3, 0.2, c, np.full((1, 5), 0.9), np.zeros((1, 5)))
    >>> m = flake_map(TextureStack(1.5, np.array([1.0]), (f,)), 64, 2.0, seed=1)
    >>> ids = m["flake_id"]
    >>> k = ids[ids >= 0][0]
    >>> bool(np.ptp(m["normal"][ids == k], axis=0).max() == 0), bool(np.all((ids >= 0) == (m["coverage"] > 0)))
    (True, True)
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
    ids = np.full((size, size), -1, np.int64)
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
        ids[gj[m], gi[m]] = i
    nrm = np.stack([st * np.cos(ph), st * np.sin(ph), ct], axis=-1)
    seen = ids >= 0
    normal = np.zeros((size, size, 3))
    normal[..., 2] = 1.0
    normal[seen] = nrm[ids[seen]]
    k = np.maximum(ids, 0)
    return {"normal": normal, "coverage": seen.astype(float), "diameter_um": np.where(seen, D[k], 0.0),
            "depth_um": np.where(seen, z[k], 0.0), "flake_id": ids}


def flake_normal_map(stack, size, texel_um, seed=0):
    """(size, size, 4) float32 periodic texture: top-most flake *binder* normal (x, y, z) in [−1, 1] and a
    coverage flag (1 where a flake is seen from above), of the first flake species (:func:`flake_map`).

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
    m = flake_map(stack, size, texel_um, seed)
    return np.concatenate([m["normal"], m["coverage"][..., None]], axis=-1).astype(np.float32)


def apparent_normals(n_binder, eta):
    """Air facet normals of binder flake normals ``n_binder`` (…, 3) seen through a smooth coat of index
    ``eta`` along the panel normal (module docstring): tilt ½ asin(η sin 2θ_b), same azimuth; and the
    mask of the flakes whose normal-incidence mirror beam leaves the coat (η sin 2θ_b < 1).

    A flake tilted 10° in η = 1.5 looks tilted ½ asin(1.5 sin 20°) = 15.4°; one tilted 25° is trapped:

    >>> n = np.array([[np.sin(np.radians(t)), 0.0, np.cos(np.radians(t))] for t in (10.0, 25.0)])
    >>> a, ok = apparent_normals(n, 1.5)
    >>> round(float(np.degrees(np.arccos(a[0, 2]))), 2), ok.tolist()
    (15.4, [True, False])
    """
    n = np.asarray(n_binder, float)
    cz = np.clip(n[..., 2], -1.0, 1.0)
    s2 = 2.0 * cz * np.sqrt(np.maximum(1.0 - cz * cz, 0.0))  # sin 2θ_b
    s = float(eta) * s2
    exits = s < 1.0
    ta = 0.5 * np.arcsin(np.minimum(s, 1.0))
    rxy = np.hypot(n[..., 0], n[..., 1])
    cphi = np.where(rxy > 0, n[..., 0] / np.where(rxy > 0, rxy, 1.0), 1.0)
    sphi = np.where(rxy > 0, n[..., 1] / np.where(rxy > 0, rxy, 1.0), 0.0)
    out = np.stack([np.sin(ta) * cphi, np.sin(ta) * sphi, np.cos(ta)], axis=-1)
    return out, exits


def mapping_error_deg(eta, light_deg, view_deg):
    """Angle (degrees) between the air half-vector normalize(l + v) of an in-plane geometry (light and
    view on opposite sides of the normal) and the apparent normal (:func:`apparent_normals`) of the
    binder flake that mirrors it exactly, h' = normalize(l' + v'): the direction error of the normal
    map off the normal-incidence view; 0 when the view or the light is along the normal."""
    eta = float(eta)

    def d(th, side):
        t = np.radians(th)
        return np.array([side * np.sin(t), 0.0, np.cos(t)])

    def db(th, side):
        sb = np.sin(np.radians(th)) / eta
        return np.array([side * sb, 0.0, np.sqrt(1.0 - sb * sb)])

    hb = db(light_deg, 1.0) + db(view_deg, -1.0)
    hb /= np.linalg.norm(hb)
    ha = d(light_deg, 1.0) + d(view_deg, -1.0)
    ha /= np.linalg.norm(ha)
    a, _ = apparent_normals(hb, eta)
    return float(np.degrees(np.arccos(np.clip(a @ ha, -1.0, 1.0))))


def half_max_offset(r1, r2):
    """d½ (same units) with lens(d½; r1, r2) = ½ lens(0): the half-maximum offset of the beam density
    of a source disc ⊗ diffraction disc (docs/texture.md eq. S1b with a point aperture), by bisection.

    Two equal discs: lens(d)/lens(0) = ½ at d = 0.8079 r (closed form of the equal-disc lens):

    >>> round(float(half_max_offset(np.array([1.0]), np.array([1.0]))[0]), 4)
    0.8079
    """
    r1, r2 = np.broadcast_arrays(np.asarray(r1, float), np.asarray(r2, float))
    big, small = np.maximum(r1, r2), np.minimum(r1, r2)
    q_grid = np.linspace(0.0, 1.0, N_HALF_MAX)
    g = np.empty_like(q_grid)
    for k, q in enumerate(q_grid):  # d½ / r_big on a grid of r_small / r_big, bisection
        if q == 0.0:
            g[k] = 1.0
            continue
        lo, hi = 1.0 - q, 1.0 + q
        half = 0.5 * np.pi * q * q
        for _ in range(48):
            mid = 0.5 * (lo + hi)
            if float(lens_area(np.array([mid]), 1.0, q)[0]) >= half:
                lo = mid
            else:
                hi = mid
        g[k] = 0.5 * (lo + hi)
    return big * np.interp(small / np.where(big > 0, big, 1.0), q_grid, g)


def glint_layer(stack, fmap, source_half_angle_deg, aperture_half_angle_rad) -> dict:
    """Per-texel inputs of the glint layer (module docstring) from a :func:`flake_map`: ``normal``
    (H, W, 3) apparent air normals, ``alpha`` (H, W) Beckmann α, ``gain`` (H, W, 3) linear-sRGB
    specular reflectance (luminance ``gain_y``; ``surface_gain_y`` without the absorbers: an aligned
    surface flake of its kind, the reference of the glint threshold β_peak/2 of docs/texture.md §3.3),
    ``exits`` (H, W): visible flakes whose glints leave the coat toward a normal view.

    The absorbers' extinction along both paths is in the gain; hiding by flakes above on the light
    path is not (a normal map hides on the view path only: the top-most flake).  The aperture enters
    as a wider source (r_s'² + r_a'²; exact for a point aperture)."""
    f = stack.flakes[0]
    eta = float(stack.eta)
    ids = fmap["flake_id"]
    seen = ids >= 0
    _, first, inv = np.unique(ids[seen], return_index=True, return_inverse=True)
    nb = fmap["normal"][seen][first].reshape(-1, 3)
    D = fmap["diameter_um"][seen][first]
    z = fmap["depth_um"][seen][first]
    na, ok = apparent_normals(nb, eta)
    c = nb[:, 2]
    cos_ta = na[:, 2]
    mu_lb = np.clip(2.0 * c * c - 1.0, 1e-6, 1.0)  # cos 2θ_b: the binder light that a normal view glints
    mu_l = np.clip(2.0 * cos_ta**2 - 1.0, 1e-6, 1.0)  # cos 2θ_a in air
    t_in, t_out = coat_transmittance(mu_l, eta), float(coat_transmittance(1.0, eta))
    R = f.reflectance(c)  # (C, n)
    y = np.asarray(stack.y_weights, float)
    surface_y = np.where(ok, t_in * t_out * (y @ R) * c, 0.0)  # unattenuated: the glint threshold's reference
    tau = np.zeros_like(R)  # absorbers (pigments, an absorbing coat) on the two paths, eq. S1's τ
    for a in stack.absorbers:
        seg = np.clip(z - a.z_top_um, 0.0, a.thickness_um)
        tau += np.asarray(a.sigma_per_um, float).reshape(-1, 1) * seg * (1.0 / mu_lb + 1.0)
    R = R * np.exp(-tau)
    gain_y = np.where(ok, t_in * t_out * (y @ R) * c, 0.0)
    if stack.wavelength_nm is not None and R.shape[0] > 1:
        rgb = np.maximum(XYZ_to_linear_sRGB(reflectance_to_XYZ(R.T, stack.wavelength_nm)), 0.0)
    else:
        rgb = np.repeat(R.mean(axis=0)[:, None], 3, axis=1)
    gain = np.where(ok[:, None], (t_in * t_out * c)[:, None] * rgb, 0.0)
    om_sb = float(cone_solid_angle(np.radians(source_half_angle_deg))) * mu_l / (eta * eta * mu_lb)
    om_ab = float(cone_solid_angle(aperture_half_angle_rad)) / (eta * eta)  # view along the normal
    r_s = np.sqrt((om_sb + om_ab) / np.pi)
    d_half = half_max_offset(r_s, diffraction_radius(D, eta))
    J = c * eta * eta * mu_lb / (mu_l * cos_ta)
    alpha = np.where(ok, np.sqrt(J * d_half**2 / (4.0 * c * np.log(1.0 / GLINT_FRACTION))), ALPHA_NONE)
    H, W = ids.shape
    out = {"normal": np.zeros((H, W, 3)), "alpha": np.full((H, W), ALPHA_NONE), "gain": np.zeros((H, W, 3)),
           "gain_y": np.zeros((H, W)), "surface_gain_y": np.zeros((H, W)), "exits": np.zeros((H, W), bool)}
    out["normal"][..., 2] = 1.0
    out["normal"][seen], out["alpha"][seen], out["gain"][seen] = na[inv], alpha[inv], gain[inv]
    out["gain_y"][seen], out["surface_gain_y"][seen], out["exits"][seen] = gain_y[inv], surface_y[inv], ok[inv]
    return out


def blend_weight(stack, observer, light_deg, ground_luminance_factor) -> float:
    """The ``blendbsdf`` weight s = β_ss/M at (light_deg, observer.view_deg): the model's flake luminance
    factor over the paint's luminance factor M (π f_r of the composed BSDF), clipped to (0, 1]; β_ss of the
    first flake species (:func:`first_species`)."""
    b_ss = sparkle_indices(first_species(stack), observer, light_deg)["flake_luminance_factor"]
    return float(np.clip(b_ss / float(ground_luminance_factor), 1e-6, 1.0))


def first_species(stack):
    """The stack with its first flake species only (the one the texture draws; the others, if any,
    stay in the ``measured`` BSDF and their hiding of it is not modelled)."""
    return replace(stack, flakes=stack.flakes[:1])


def material_xml(name, texel_um, size, weight, measured=None) -> str:
    """The Mitsuba 3 material of docs/texture.md §7 as an XML file to ``<include>``: a ``blendbsdf``
    (id ``flakedb_sparkle``, weight ``weight``) of the ``measured`` export ($measured) and the glint
    layer (normal map, per-texel α and gain/weight; textures in $sparkle_dir, default ".": Mitsuba
    resolves relative names against the loaded scene's directory, not the included file's).  The textures tile every ``size · texel_um`` µm:
    give the shape uv = position / that period (its ``to_uv``, or a scaled uv)."""
    f = {k: v.format(name=name) for k, v in FILES.items()}
    measured = measured or f"{name}.measured.tensor"  # `flakedb export-mitsuba NAME.bsdf`'s default name

    def tex(pname, fname):
        return (f'<texture type="bitmap" name="{pname}"><string name="filename" value="$sparkle_dir/{fname}"/>'
                f'<boolean name="raw" value="true"/><string name="filter_type" value="nearest"/></texture>')

    return f"""<scene version="3.0.0">
    <!-- flakedb sparkle material (docs/texture.md §7); texture period {size * texel_um:g} um ({size} texels of {texel_um:g} um) -->
    <default name="measured" value="{measured}"/>
    <default name="sparkle_dir" value="."/>  <!-- the directory of these textures, if not the scene's -->
    <bsdf type="blendbsdf" id="flakedb_sparkle">
        <float name="weight" value="{weight:.9g}"/>
        <bsdf type="measured"><string name="filename" value="$measured"/></bsdf>
        <bsdf type="normalmap">
            {tex("normalmap", f["normals"])}
            <bsdf type="roughconductor">
                <string name="distribution" value="beckmann"/>
                <boolean name="sample_visible" value="true"/>
                <string name="material" value="none"/>
                {tex("alpha", f["alpha"])}
                {tex("specular_reflectance", f["gain"])}
            </bsdf>
        </bsdf>
    </bsdf>
</scene>
"""


def mitsuba_route(stack, observer, size=512, texel_um=5.0, ground_luminance_factor=None, seed=0) -> dict:
    """Everything the Mitsuba route writes (docs/texture.md §7), as arrays and text keyed by
    :data:`FILES`: ``normals`` (H, W, 3) = (n_air + 1)/2, ``alpha`` (H, W, 3) α in every channel,
    ``gain`` (H, W, 3) = the glint gain / the blend weight, ``params`` (the parameter set with a
    ``mitsuba`` block: weight, its basis, texel size, design geometry) and ``xml``.

    The weight is :func:`blend_weight` at the observer's first light angle when the paint's luminance
    factor there (``ground_luminance_factor``) is given; otherwise the covered fraction (the mean is then
    not preserved: the block says so)."""
    fmap = flake_map(stack, size, texel_um, seed)
    g = glint_layer(stack, fmap, observer.source_half_angle_deg, observer.aperture_half_angle_rad)
    light = float(observer.light_deg[0])
    b_ss = sparkle_indices(first_species(stack), observer, light)["flake_luminance_factor"]
    if ground_luminance_factor is not None:
        w, basis = blend_weight(stack, observer, light, ground_luminance_factor), "flake share beta_ss/M"
    else:
        w = max(float(fmap["coverage"].mean()), 1e-6)
        basis = ("covered fraction (no ground given: the mean is (1 - w) M + beta_ss, not M; give M for "
                 "w = beta_ss/M)")
    params = shader_parameters(stack, observer.spot_um, observer.aperture_half_angle_rad,
                               observer.source_half_angle_deg)
    params["mitsuba"] = {"blend_weight": w, "weight_basis": basis, "texel_um": float(texel_um), "size": int(size),
                         "period_um": float(size * texel_um), "design_light_deg": light,
                         "design_view_deg": float(observer.view_deg),
                         "ground_luminance_factor": ground_luminance_factor, "design_flake_luminance_factor": b_ss,
                         "trapped_fraction_of_visible_flake_area": float(1.0 - g["exits"].sum() / max(fmap["coverage"].sum(), 1.0)),
                         "files": {k: v.format(name="NAME") for k, v in FILES.items()}}
    return {"normals": 0.5 * (g["normal"] + 1.0), "alpha": np.repeat(g["alpha"][..., None], 3, axis=-1),
            "gain": g["gain"] / w, "weight": w, "params": params, "layer": g, "map": fmap}
