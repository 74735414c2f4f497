"""Deterministic preview: the sphere of :mod:`flakedb.render.preview` rendered by quadrature, with no
random numbers (no grain on any paint; the same image for every seed).

Usage: ``render_sphere_quadrature(bsdf, env, sun, size=256)`` -> :class:`flakedb.render.preview.RenderResult`
(linear RGB, the same scene, camera and file mapping as :func:`flakedb.render.preview.render_sphere`).

Method
------
The reflected radiance at a point of normal ``n`` seen from ``v = +z`` is

    L_r(n) = Σ_cells f·|mu_o|(mu_i, mu_o, phi_d) · Ω_cell · E_cell  +  F(mu_i; η) L(mirror(v))

1. **Lights on a grid.**  The environment and the sun are put on a spherical grid whose pole is the view
   axis +z (``N_THETA × N_PHI`` cells, :mod:`flakedb.render.envmap`): ``E`` is each cell's mean radiance
   (``ss × ss`` sub-cells by exact solid angle) and the sun's disk adds its power exactly (equal-solid-angle
   points of the disk binned into cells).  Every light of the studio (soft boxes, sky, ground, sun) is thus
   integrated by the same midpoint rule over 1.4° cells.
2. **The Fourier series per direction.**  For normals at polar angle θ_g from the view (``N_NORMAL`` values
   on [0, 90°]), ``f·|mu_o|`` is evaluated at every cell above the normal's horizon: the file's cosine
   series ``Σ_m a_m(mu_i, mu_o) cos(m phi_d)`` (:meth:`FourierBSDF.series`, interpolated exactly in
   ``mu_i``, linearly on ``N_MU`` values of ``|mu_o|``) summed on a ``phi_d`` grid fine enough for the
   file's highest order (linear interpolation error ``≤ (m h)²/8`` of order m's coefficient), then looked
   up bilinearly at each cell's ``(mu_o, phi_d)`` (from vectors: ``cos phi_d = −(v_t·d_t)/(|v_t||d_t|)``).
3. **Rotation about the view axis is a shift.**  A normal at azimuth φ_n sees the grid rotated by φ_n about
   +z, so its sum is the circular cross-correlation along φ of that kernel with E, summed over rows: one
   FFT per θ_g gives the smooth radiance ``S[θ_g, φ_s]`` at every grid azimuth.
4. **Pixels.**  Each pixel takes ``ss × ss`` fixed sub-pixel positions (no jitter): the smooth part by
   bilinear interpolation of ``S`` in (θ_n, φ_n), the smooth coat's delta reflection of the environment
   exactly (``F(mu_i; η) · L_env(r)``), the background from the environment, and the pixel is their mean
   (anti-aliased silhouette and highlights).  The sun's mirror image, too small for sub-pixel samples, is
   added by its area (:func:`_mirrored_sun`).

Under a constant environment ``L`` the smooth part is ``L Σ_cells f·|mu_o| Ω`` → ``L · albedo_R(mu_i)``
(the furnace); the measured differences from the Monte Carlo renderer are in docs/previews.md.
"""

from __future__ import annotations

import dataclasses
import math
import time

import numpy as np

from flakedb.optics.fresnel import fresnel_dielectric
from flakedb.render.envmap import (LatLongEnvironment, PolarFrame, cell_average, cell_directions, cell_solid_angles,
                                  splat_sun, sun_directions)
from flakedb.render.preview import (CAMERA_DIR, DEFAULT_EXTENT, VIEW_DIR, RenderResult, check_renderable,
                                    studio_environment)

__all__ = ["render_sphere_quadrature", "smooth_radiance_table", "VIEW_FRAME", "N_THETA", "N_PHI", "N_NORMAL",
           "N_MU", "PIXEL_SS"]

#: The light grid: pole on the view axis (+z), φ from +x towards +y (the image's right and up).
VIEW_FRAME = PolarFrame(pole=(0.0, 0.0, 1.0), ref=(1.0, 0.0, 0.0), side=(0.0, 1.0, 0.0))
#: Light-grid cells in θ and φ (1.41° each).
N_THETA, N_PHI = 128, 256
#: Sub-cells per light-grid cell and axis.
ENV_SS = 2
#: Equal-solid-angle points of the sun disk binned into the grid.
SUN_POINTS = 4096
#: Normal polar angles of the smooth-radiance table (on [0, 90°], 1.41° apart).
N_NORMAL = 65
#: |mu_o| values at which the file's series is interpolated.
N_MU = 129
#: Equal-solid-angle points of the sun disk in its mirror image on the coat.
MIRROR_SUN_POINTS = 16384
#: Sub-pixel positions per pixel and axis.
PIXEL_SS = 2
#: phi_d grid: at least this many points on [0, π], and enough that (order · step) <= PHI_STEP_ORDERS.
MIN_PHI_D, MAX_PHI_D, PHI_STEP_ORDERS = 181, 2049, 0.1


def _phi_d_count(max_order: int) -> int:
    return int(min(MAX_PHI_D, max(MIN_PHI_D, math.ceil(math.pi * max(max_order - 1, 0) / PHI_STEP_ORDERS) + 1)))


def _lobe_coefficients(bsdf, mu_i, mu_abs):
    """a_m of f·|mu_o| at (mu_i[g], −mu_abs[j]) in the output channels: (G, J, Cout, M)."""
    m = max(bsdf.max_order, 1)
    a = bsdf.series(np.repeat(mu_i, mu_abs.size), np.tile(-mu_abs, mu_i.size))        # (G·J, Cs, M)
    a = a.reshape(mu_i.size, mu_abs.size, a.shape[-2], m)
    a = np.einsum("gjsm,so->gjom", a, bsdf.kernel_arrays().mix)
    a[:, mu_abs <= 0] = 0.0                                                         # f·|mu_o| = 0 at grazing
    return a


def smooth_radiance_table(bsdf, E, *, n_normal: int = N_NORMAL, n_mu: int = N_MU):
    """``S`` (n_normal, N_PHI, 3): the reflected radiance without the delta term at normals of polar
    angle ``θ_g = linspace(0, π/2, n_normal)`` from the view and azimuth ``φ_s = s · 2π/N_PHI``, for the
    light grid ``E`` (N_THETA, N_PHI, 3) on :data:`VIEW_FRAME` (module docstring, steps 2-3)."""
    n_theta, n_phi = E.shape[:2]
    theta_g = np.linspace(0.0, 0.5 * np.pi, n_normal)
    mu_i = np.cos(theta_g)
    mu_i[-1] = 0.0
    mu_abs = np.linspace(0.0, 1.0, n_mu)
    A = _lobe_coefficients(bsdf, mu_i, mu_abs)                                      # (G, J, C, M)
    n_pd = _phi_d_count(A.shape[-1])
    phi_d = np.linspace(0.0, np.pi, n_pd)
    cos_m = np.cos(np.arange(A.shape[-1])[:, None] * phi_d[None, :])               # (M, P)
    d = cell_directions(n_theta, n_phi, VIEW_FRAME).reshape(-1, 3)                # (R·Φ, 3)
    dx, dz = d[:, 0].copy(), d[:, 2].copy()
    omega = np.repeat(cell_solid_angles(n_theta, n_phi), n_phi)                    # (R·Φ,)
    E_hat = np.fft.rfft(E, axis=1)                                                  # (R, Φ/2+1, 3)
    S = np.zeros((n_normal, n_phi, 3))                                              # a mono file lit in RGB
    K = np.zeros((n_theta * n_phi, A.shape[2]))
    for g in range(n_normal):
        st, ct = math.sin(theta_g[g]), mu_i[g]
        mu_o = dx * st + dz * ct                                                    # n0 = (sin θ_g, 0, cos θ_g)
        idx = np.flatnonzero(mu_o > 0)
        if idx.size == 0 or not A[g].any():
            continue
        mo, dzi = mu_o[idx], dz[idx]
        table = (A[g].reshape(-1, A.shape[-1]) @ cos_m).reshape(n_mu, -1, n_pd)     # (J, C, P): one BLAS product
        table = np.ascontiguousarray(table.transpose(0, 2, 1)).reshape(n_mu * n_pd, -1)  # (J·P, C)
        den = st * np.sqrt(np.maximum(1.0 - mo * mo, 0.0))
        ok = den > 1e-12
        cphi = np.ones_like(mo)
        cphi[ok] = (ct * mo[ok] - dzi[ok]) / den[ok]
        x = np.minimum(mo, 1.0) * (n_mu - 1)
        y = np.arccos(np.clip(cphi, -1.0, 1.0)) * ((n_pd - 1) / np.pi)
        x0 = np.minimum(x.astype(np.int64), n_mu - 2)
        y0 = np.minimum(y.astype(np.int64), n_pd - 2)
        tx, ty = (x - x0)[:, None], (y - y0)[:, None]
        i00 = x0 * n_pd + y0
        f = ((1 - tx) * ((1 - ty) * table[i00] + ty * table[i00 + 1])
             + tx * ((1 - ty) * table[i00 + n_pd] + ty * table[i00 + n_pd + 1]))    # (cells, C)
        K[:] = 0.0
        K[idx] = f * omega[idx, None]
        K_hat = np.fft.rfft(K.reshape(n_theta, n_phi, -1), axis=1)                  # (R, Φ/2+1, C)
        S[g] = np.fft.irfft(np.sum(np.conj(K_hat) * E_hat, axis=0), n=n_phi, axis=0)
    return S


def _mirrored_sun(sun, eta: float, size: int, extent: float, n_points: int = MIRROR_SUN_POINTS) -> np.ndarray:
    """The smooth coat's mirror image of ``sun`` (size, size, 3), each pixel's mean over its area.

    On an orthographic sphere the mirror image of a solid angle dω has image area dω/4 (the half vector
    h = (d + v)/|d + v| has dω_h = dω / (4 h·v), and the image area is h·v dω_h), so ``n_points``
    equal-solid-angle points of the disk each add ``F(h·v; η) L_sun (Ω_sun / n_points) / 4`` of radiance ×
    area to the pixel they land in: exact in the limit, with no sub-pixel sampling of the small disk."""
    d = sun_directions(sun, n_points)
    h = d + VIEW_DIR
    h /= np.linalg.norm(h, axis=-1, keepdims=True)
    pix = 2.0 * extent / size
    col = np.floor((h[:, 0] + extent) / pix).astype(np.int64)
    row = np.floor((extent - h[:, 1]) / pix).astype(np.int64)
    ok = (h[:, 2] > 0) & (col >= 0) & (col < size) & (row >= 0) & (row < size)
    w = fresnel_dielectric(h[ok, 2], eta).R * (sun.solid_angle / n_points / 4.0 / (pix * pix))
    out = np.zeros((size, size))
    np.add.at(out, (row[ok], col[ok]), w)
    return out[..., None] * np.asarray(sun.radiance)


def _env_sub_cells(env, n_phi: int) -> int:
    """Sub-cells per grid cell and axis: ENV_SS, or for a lat-long image about one sample per image pixel
    (at most 8), so that a small bright feature of the image (a sun) keeps its power."""
    if isinstance(env, LatLongEnvironment):
        return int(min(8, max(ENV_SS, math.ceil(env.image.shape[1] / n_phi))))
    return ENV_SS


def _sub_pixel_points(size: int, extent: float, ss: int):
    """(x, y) of the ss×ss fixed sub-pixel positions of every pixel: (size, size, ss·ss) each."""
    pix = 2.0 * extent / size
    off = (np.arange(ss) + 0.5) / ss
    ox, oy = np.meshgrid(off, off, indexing="xy")
    col = np.arange(size)[None, :, None]
    row = np.arange(size)[:, None, None]
    x = -extent + (col + ox.ravel()[None, None, :]) * pix
    y = extent - (row + oy.ravel()[None, None, :]) * pix
    return np.broadcast_arrays(x, y)


def render_sphere_quadrature(bsdf, env=None, sun=None, *, size: int = 256, extent: float = DEFAULT_EXTENT,
                             pixel_ss: int = PIXEL_SS, n_theta: int = N_THETA, n_phi: int = N_PHI,
                             n_normal: int = N_NORMAL, progress=None) -> RenderResult:
    """The unit sphere of ``bsdf`` under ``env`` (callable radiance, default the studio) and ``sun`` (a
    :class:`flakedb.render.preview.Sun` or None), rendered deterministically (module docstring).

    Returns a :class:`RenderResult` (``coverage``: the fraction of a pixel's sub-pixel positions on the
    sphere).  Raises ValueError for what :func:`flakedb.render.preview.check_renderable` refuses."""
    size, pixel_ss = int(size), int(pixel_ss)
    if size < 1 or pixel_ss < 1:
        raise ValueError(f"size and pixel_ss must be >= 1, got size={size}, pixel_ss={pixel_ss}")
    if not extent > 0:
        raise ValueError(f"extent must be > 0, got {extent!r}")
    env = studio_environment() if env is None else env
    delta_eta, _ = check_renderable(bsdf)
    t0 = time.perf_counter()
    E = splat_sun(cell_average(env, n_theta, n_phi, VIEW_FRAME, _env_sub_cells(env, n_phi)), sun, VIEW_FRAME,
                  SUN_POINTS)
    S = smooth_radiance_table(bsdf, E, n_normal=n_normal)
    image = np.empty((size, size, 3))
    coverage = np.empty((size, size))
    background = np.asarray(env(CAMERA_DIR), dtype=np.float64).reshape(3)
    if sun is not None:
        background = background + sun.radiance_at(CAMERA_DIR)
    rows = max(1, (1 << 18) // (size * pixel_ss * pixel_ss))
    for r0 in range(0, size, rows):
        x, y = _sub_pixel_points(size, extent, pixel_ss)
        x, y = x[r0:r0 + rows], y[r0:r0 + rows]
        r2 = x * x + y * y
        hit = r2 < 1.0
        val = np.broadcast_to(background, hit.shape + (3,)).copy()
        nz = np.sqrt(1.0 - r2[hit])
        theta_n = np.arccos(np.clip(nz, 0.0, 1.0)) * ((n_normal - 1) / (0.5 * np.pi))
        phi_n = np.mod(np.arctan2(y[hit], x[hit]), 2.0 * np.pi) * (n_phi / (2.0 * np.pi))
        g0 = np.minimum(theta_n.astype(np.int64), n_normal - 2)
        tg = (theta_n - g0)[:, None]
        s0f = np.floor(phi_n)
        ts = (phi_n - s0f)[:, None]
        s0 = np.mod(s0f.astype(np.int64), n_phi)
        s1 = np.mod(s0 + 1, n_phi)
        smooth = ((1 - tg) * ((1 - ts) * S[g0, s0] + ts * S[g0, s1])
                  + tg * ((1 - ts) * S[g0 + 1, s0] + ts * S[g0 + 1, s1]))
        if delta_eta is not None:
            n = np.stack([x[hit], y[hit], nz], axis=-1)
            F = fresnel_dielectric(nz, delta_eta).R
            r = 2.0 * nz[:, None] * n - VIEW_DIR
            smooth = smooth + F[:, None] * np.asarray(env(r), dtype=np.float64)   # the sun: _mirrored_sun
        val[hit] = smooth
        image[r0:r0 + rows] = val.mean(axis=2)
        coverage[r0:r0 + rows] = hit.mean(axis=2)
        if progress is not None:
            progress(min(rows, size - r0))
    if delta_eta is not None and sun is not None:
        image += _mirrored_sun(sun, delta_eta, size, extent)
    seconds = time.perf_counter() - t0
    env_settings = env.settings() if hasattr(env, "settings") else (
        dataclasses.asdict(env) if dataclasses.is_dataclass(env) else repr(env))
    settings = {"method": "quadrature", "size": size, "pixel_ss": pixel_ss, "extent": float(extent),
                "light_grid": [n_theta, n_phi], "normal_grid": n_normal, "environment": env_settings,
                "sun": None if sun is None else dataclasses.asdict(sun),
                "delta": None if bsdf.delta is None else dict(bsdf.delta),
                "file": None if bsdf.path is None else str(bsdf.path), "threads": 1}
    return RenderResult(image.astype(np.float32), coverage.astype(np.float32), seconds, settings)
