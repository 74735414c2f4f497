"""Glints in the preview: the sun's sparkle drawn from the texture model at the image's pixel scale
(docs/texture.md §6 "Rendering").

The smooth BSDF already holds the mean of every flake's mirror reflection (the flakes' single-
reflection term, π f_ss, docs/texture.md eq. S3).  Per sphere pixel this module takes the model's
expected glint count λ = N_g · (pixel footprint on the panel) and that mean luminance factor β_ss at
the pixel's local light/view geometry, draws a Poisson number K of glints from a generator seeded by
(seed, row) alone — so the glints do not depend on the sample count, the tiles or the threads — and
adds (K/λ − 1) · β_ss · E_sun/π to the smooth render: the smooth BSDF minus the part the glints carry
plus the glints.  E[K/λ] = 1, so the image's mean over a large area equals the smooth render's
(Poisson error 1/√Σλ; measured in tests/texture/test_render.py).

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
    ``wavelength_nm`` attached for the glint colour)."""
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
    with np.errstate(invalid="ignore", divide="ignore"):
        ratio = np.where(lam > 0, K / np.where(lam > 0, lam, 1.0), 1.0)
    layer = (ratio - 1.0)[..., None] * L_ss
    live = lam > 0
    Ls = L_ss.sum(axis=-1)
    return layer, {"sum_lambda": float(lam.sum()), "glints": int(K.sum()), "pixel_mm": pix_mm,
                   "glint_radiance_sum": float(Ls.sum()),  # Σ over pixels and channels of β_ss E cos/π
                   "sigma_layer_sum": float(np.sqrt(np.sum(Ls[live] ** 2 / lam[live]))),  # Poisson σ of Σ layer
                   "aperture_rad": aperture, "sphere_diameter_mm": sphere_diameter_mm}
