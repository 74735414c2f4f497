"""Glints in the preview: the sun's sparkle drawn from the texture model at the image's pixel scale
(docs/texture.md §6 "Rendering").

The smooth BSDF already holds the mean of every flake's mirror reflection (the flakes' single-
reflection term, π f_ss, docs/texture.md eq. S3).  Per sphere pixel this module takes the model's
expected glint count λ = N_g · (pixel footprint on the panel) and that mean luminance factor β_ss at
the pixel's local light/view geometry, draws a Poisson number K of glints from a generator seeded by
(seed, row) alone — so the glints do not depend on the sample count, the tiles or the threads — and
replaces the mean flake radiance L_ss = β_ss · E_sun/π by K glints of energy L_ss/λ each: the smooth BSDF
minus the part the glints carry plus the glints (:func:`sparkle_image`, which also bounds L_ss by what
the render holds and draws each glint as a small normalised spot; :func:`sparkle_layer` is the plain
additive (K/λ − 1) · L_ss).  E[K/λ] = 1, so the image's mean over a large area equals the smooth render's
(Poisson error 1/√Σλ; measured in tests/texture/test_render.py and tests/render/test_sparkle_image.py).

Scale: the sphere's diameter in mm (``sphere_diameter_mm``) gives each pixel a footprint; the camera
is an :class:`flakedb.texture.instruments.Observer` with that spot and an aperture (a 3 mm pupil at
``viewing_distance_m``).  Geometry: the model is tabulated for in-plane light/view pairs on a grid
of binder half-vector tilt θ_h and half-angle θ_d; a pixel's (θ_h, θ_d) picks the in-plane pair with
the same values (an out-of-plane pair differs only in the paths' attenuation).  Glint colour: the
flake's own R(c) at c = cos θ_d converted to linear sRGB (CIE 1931 2°, D65), times the sun's colour.
"""

from __future__ import annotations

import numpy as np

from flakedb.colour.colorimetry import XYZ_to_linear_sRGB, reflectance_to_XYZ
from flakedb.texture.instruments import Observer
from flakedb.texture.model import sparkle_indices

#: Grid of the tabulated model: binder half-vector tilt θ_h and half-angle θ_d (degrees).
TILT_GRID_DEG = np.linspace(0.0, 40.0, 17)
HALF_GRID_DEG = np.linspace(0.0, 40.0, 9)


def _air_angle(theta_b_deg, eta):
    s = np.sin(np.radians(theta_b_deg)) * eta
    return np.degrees(np.arcsin(np.clip(s, -1.0, 1.0))), s < 1.0


def glint_tables(stack, observer_spot_um, aperture_rad, sun_half_angle_deg):
    """(glints per µm², β_ss) on the (θ_h, θ_d) grid (17, 9): in-plane pairs in the binder
    l' = θ_h + θ_d, v' = θ_h − θ_d (a negative angle is the view on the light's side: mirrored)."""
    n_g = np.zeros((TILT_GRID_DEG.size, HALF_GRID_DEG.size))
    b_ss = np.zeros_like(n_g)
    for i, th in enumerate(TILT_GRID_DEG):
        for j, td in enumerate(HALF_GRID_DEG):
            lb, vb = th + td, td - th  # polar angles of l' (light side) and v' (opposite side)
            la, ok1 = _air_angle(lb, stack.eta)
            va, ok2 = _air_angle(abs(vb), stack.eta)
            if not (ok1 and ok2) or la >= 89.0 or va >= 80.0 or vb < 0:
                continue  # view on the light's side: not an in-plane opposite pair; left 0 (rare on a sphere)
            obs = Observer("render", observer_spot_um, aperture_rad, sun_half_angle_deg, (float(la),), float(va))
            r = sparkle_indices(stack, obs, float(la))
            n_g[i, j] = r["glints_per_mm2"] * 1e-6 if r["sparkle"] else 0.0
            b_ss[i, j] = r["flake_luminance_factor"] if r["sparkle"] else 0.0
    return n_g, b_ss


def _bilinear(table, xg, yg, x, y):
    ix = np.clip(np.searchsorted(xg, x) - 1, 0, xg.size - 2)
    iy = np.clip(np.searchsorted(yg, y) - 1, 0, yg.size - 2)
    tx = np.clip((x - xg[ix]) / (xg[ix + 1] - xg[ix]), 0.0, 1.0)
    ty = np.clip((y - yg[iy]) / (yg[iy + 1] - yg[iy]), 0.0, 1.0)
    return ((1 - tx) * (1 - ty) * table[ix, iy] + tx * (1 - ty) * table[ix + 1, iy]
            + (1 - tx) * ty * table[ix, iy + 1] + tx * ty * table[ix + 1, iy + 1])


def flake_rgb(stack, cos_d):
    """Linear sRGB of the flakes' R at flake cosines ``cos_d`` (…,), normalised to luminance 1 (…, 3).

    A grey flake is white (D65), a flake that reflects only the long wavelengths is yellow-orange, and both
    have luminance 1 (Rec. 709 weights):

    >>> from flakedb.texture.model import FlakeLayer, TextureStack
    >>> c, wl = np.linspace(0.0, 1.0, 5), np.arange(380.0, 781.0, 10.0)
    >>> def rgb(R_short):
    ...     R = np.where(wl[:, None] < 550.0, R_short, 0.9) * np.ones((1, 5))
    ...     f = FlakeLayer("f", 0.0, 10.0, 1e-4, 15.0, 1.3, 0.3, 0.2, c, R, 0.0 * R)
    ...     return flake_rgb(TextureStack(1.5, np.full(wl.size, 1 / wl.size), (f,), wavelength_nm=wl), np.array([1.0]))[0]
    >>> grey, warm = rgb(0.9), rgb(0.2)
    >>> bool(np.allclose(grey, 1.0, atol=1e-3)), bool(warm[0] > warm[1] > warm[2]), round(float(warm @ [0.2126, 0.7152, 0.0722]), 3)
    (True, True, 1.000)
    """
    f = stack.flakes[0]
    R = f.reflectance(np.asarray(cos_d, float))  # (C, …)
    wl = getattr(stack, "wavelength_nm", None)
    if R.shape[0] == 1 or wl is None:
        return np.ones(np.shape(cos_d) + (3,))
    XYZ = reflectance_to_XYZ(np.moveaxis(R, 0, -1), wl)
    rgb = np.maximum(XYZ_to_linear_sRGB(XYZ), 0.0)
    return rgb / np.maximum(XYZ[..., 1:2], 1e-12)


def sparkle_layer(stack, sun, size, extent, *, sphere_diameter_mm=100.0, viewing_distance_m=1.0,
                  pupil_mm=3.0, seed=0, wavelength_nm=None):
    """The additive glint image (size, size, 3) [the preview's radiance units] of the unit sphere of
    :func:`flakedb.render.preview.render_sphere` (orthographic, view +z) under ``sun``, and a dict of
    statistics (Σλ, glints drawn).  ``stack``: :class:`flakedb.texture.model.TextureStack` (with
    ``wavelength_nm`` attached for the glint colour).  Adding it to a render can go below zero where the
    model's β_ss exceeds what the render holds; :func:`sparkle_image` does not."""
    K, lam, L_ss, info = glint_field(stack, sun, size, extent, sphere_diameter_mm=sphere_diameter_mm,
                                     viewing_distance_m=viewing_distance_m, pupil_mm=pupil_mm, seed=seed)
    with np.errstate(invalid="ignore", divide="ignore"):
        ratio = np.where(lam > 0, K / np.where(lam > 0, lam, 1.0), 1.0)
    return (ratio - 1.0)[..., None] * L_ss, info


#: The spot a glint is drawn as: a normalised 3 × 3 binomial kernel (its energy kept, ~2 pixels across),
#: so that one glint reads as a sparkle and not as one hot pixel.
GLINT_KERNEL = np.outer([1.0, 2.0, 1.0], [1.0, 2.0, 1.0]) / 16.0


def sparkle_image(smooth, stack, sun, extent, *, sphere_diameter_mm=100.0, seed=0, kernel=GLINT_KERNEL,
                  reference=None, **kw):
    """The render ``smooth`` (size, size, 3) with the sun's glints, energy-consistent (docs/texture.md §6):

        image = smooth − s·L_ss + spread(K/λ · s·L_ss),   s = min(1, min_c smooth_c / L_ss_c) per pixel

    ``L_ss`` is the model's mean flake radiance at the pixel (:func:`glint_field`); ``s`` lowers it, with
    its colour kept, where the render holds less than that (so nothing is taken that is not there: no
    negative pixel, no clipping, no colour cast from clipping one channel); ``K`` glints of energy
    ``s·L_ss/λ`` each are drawn as ``kernel`` (normalised).  ``E[K/λ] = 1`` so the mean of every region is
    the render's, within the Poisson error √Σ(s L_ss)²/λ.  ``reference``: the image ``s`` is computed from
    (default ``smooth``; a Monte Carlo ``smooth`` passes the deterministic render, so that the glints do not
    change with its noise).  Returns (image, info) with ``info["capped"]``: the fraction of the glints'
    mean that the cap removed."""
    smooth = np.asarray(smooth, dtype=np.float64)
    size = smooth.shape[0]
    K, lam, L_ss, info = glint_field(stack, sun, size, extent, sphere_diameter_mm=sphere_diameter_mm, seed=seed, **kw)
    with np.errstate(invalid="ignore", divide="ignore"):
        ref = smooth if reference is None else np.asarray(reference, dtype=np.float64)
        room = np.where(L_ss > 0, np.maximum(ref, 0.0) / np.where(L_ss > 0, L_ss, 1.0), np.inf)
    scale = np.minimum(1.0, room.min(axis=-1))
    L_cap = L_ss * scale[..., None]
    with np.errstate(invalid="ignore", divide="ignore"):
        per_glint = np.where(lam[..., None] > 0, L_cap / np.where(lam > 0, lam, 1.0)[..., None], 0.0)
    G = K[..., None] * per_glint
    k = np.asarray(kernel, dtype=np.float64)
    k = k / k.sum()
    r = k.shape[0] // 2
    pad = np.pad(G, ((r, r), (r, r), (0, 0)))
    spread = sum(k[i, j] * pad[i:i + size, j:j + size] for i in range(k.shape[0]) for j in range(k.shape[1]))
    image = np.maximum(smooth - L_cap + spread, 0.0)   # max: the cap's rounding (~1e-17), or a Monte Carlo smooth's noise
    total = float(L_ss.sum())
    info = dict(info, capped=(1.0 - float(L_cap.sum()) / total) if total > 0 else 0.0,
                sigma_image_sum=float(np.sqrt(np.sum(np.where(lam > 0, L_cap.sum(-1) ** 2 / np.where(lam > 0, lam, 1.0), 0.0)))))
    return image, info


def glint_field(stack, sun, size, extent, *, sphere_diameter_mm=100.0, viewing_distance_m=1.0,
                pupil_mm=3.0, seed=0):
    """Per pixel of the preview's sphere: the glint count ``K`` drawn (size, size), its expectation ``λ``
    (size, size), the flakes' mean radiance ``L_ss`` (size, size, 3) and a dict of statistics
    (module docstring)."""
    pix_mm = 2.0 * extent / size * 0.5 * sphere_diameter_mm
    spot_um = pix_mm * 1e3
    aperture = float(np.arctan(0.5e-3 * pupil_mm / viewing_distance_m))
    n_g, b_ss = glint_tables(stack, spot_um, aperture, sun.half_angle_deg)
    # pixel centres on the sphere
    c = -extent + (np.arange(size) + 0.5) * (2.0 * extent / size)
    X, Y = np.meshgrid(c, -c)
    r2 = X * X + Y * Y
    hit = r2 < 1.0
    n = np.stack([X, Y, np.sqrt(np.clip(1.0 - r2, 0.0, 1.0))], axis=-1)
    v = np.array([0.0, 0.0, 1.0])
    s = np.asarray(sun.direction, float)
    mu_v = n[..., 2]
    mu_l = n @ s
    eta = stack.eta
    # binder directions (tangential components / η) and their half vector in the local frame
    def to_binder(d_dot_n, d):
        t = d[None, None, :] - d_dot_n[..., None] * n
        t = t / eta
        return t + np.sqrt(np.clip(1.0 - np.sum(t * t, -1), 0.0, 1.0))[..., None] * n
    lb, vb = to_binder(mu_l, s), to_binder(mu_v, v)
    h = lb + vb
    h = h / np.maximum(np.linalg.norm(h, axis=-1, keepdims=True), 1e-12)
    th = np.degrees(np.arccos(np.clip(np.sum(h * n, -1), -1, 1)))
    td = np.degrees(np.arccos(np.clip(np.sum(h * lb, -1), -1, 1)))
    ok = hit & (mu_l > 0) & (th <= TILT_GRID_DEG[-1]) & (td <= HALF_GRID_DEG[-1])
    lam = np.where(ok, _bilinear(n_g, TILT_GRID_DEG, HALF_GRID_DEG, th, td), 0.0) * (spot_um**2) / np.maximum(mu_v, 1e-6)
    beta = np.where(ok, _bilinear(b_ss, TILT_GRID_DEG, HALF_GRID_DEG, th, td), 0.0)
    E = np.asarray(sun.irradiance, float)[None, None, :] * np.clip(mu_l, 0.0, None)[..., None]
    L_ss = beta[..., None] * E / np.pi * flake_rgb(stack, np.cos(np.radians(np.where(ok, td, 0.0))))
    L_ss = np.where(ok[..., None], L_ss, 0.0)
    K = np.zeros((size, size))
    for row in range(size):  # one generator per row: independent of spp, tiles and threads
        rng = np.random.default_rng([int(seed), 0x5A, row])
        K[row] = rng.poisson(lam[row])
    live = lam > 0
    Ls = L_ss.sum(axis=-1)
    return K, lam, L_ss, {"sum_lambda": float(lam.sum()), "glints": int(K.sum()), "pixel_mm": pix_mm,
                   "glint_radiance_sum": float(Ls.sum()),  # Σ over pixels and channels of β_ss E cos/π
                   "sigma_layer_sum": float(np.sqrt(np.sum(Ls[live] ** 2 / lam[live]))),  # Poisson σ of Σ layer
                   "aperture_rad": aperture, "sphere_diameter_mm": sphere_diameter_mm}
