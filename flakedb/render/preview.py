"""Preview renderer: a unit sphere of a tabulated Fourier BSDF under an environment and a sun.

Pure numerics (arrays in, an image out); the files are written by :mod:`flakedb.render.imageio` and the
command is ``flakedb render`` (:mod:`flakedb.cli.render`).

Scene
-----
World frame: the camera looks down ``-z`` (orthographic, every camera ray travels along
``(0, 0, -1)``), the image shows ``[-extent, extent]²`` of the ``xy`` plane (row 0 at
``y = +extent``, column 0 at ``x = -extent``), and ``+y`` is "up" for the environment.  The unit
sphere sits at the origin; the shading normal at an image point ``(x, y)`` inside the unit disk is
``n = (x, y, sqrt(1 - x² - y²))`` and the view direction is ``wi = (0, 0, 1)``, so the pixel's view
cosine is ``mu_i = n_z``.  The sphere is convex and alone: there is no shadowing.

Radiance ``L(d)`` is indexed by the direction ``d`` *towards* where the light comes from
(:class:`Environment`, :class:`Sun`); a background pixel shows ``L((0, 0, -1))``.  The sun is a
disk of angular radius ``half_angle`` whose radiance *adds* to the environment's inside the disk.

Mapping to the file (docs/bsdf-format.md, "Renderer mapping")
--------------------------------------------------------
With the local frame ``(s, t, n)`` of the shading point, ``wi`` towards the camera and ``wo``
towards the light (both pointing away from the surface, azimuths ``φ_i``, ``φ_o``):
``mu_i = cos θ(wi)``, ``mu_o = -cos θ(wo)`` (< 0: reflection), ``phi_d = π - (φ_o - φ_i)``
(``phi_d = 0`` is the mirror direction, conventions).  :meth:`FourierBSDF.eval` returns
``f · |mu_o|``, so the reflected radiance is

    L_r(wi) = ∫ f·|mu_o|(mu_i, mu_o, phi_d) L(wo) dω_o  +  F(mu_i; η) L(mirror(wi))

where the second term is the smooth coat's first-surface delta reflection (``delta`` of the file,
``{"kind": "fresnel", "eta": η}``; ``F`` from :func:`flakedb.optics.fresnel.fresnel_dielectric`),
added exactly.  Single scattering: the table already holds every bounce inside the paint.

Estimator (per pixel sample)
----------------------------
* **BSDF sample** (:meth:`FourierBSDF.sample`, the file's CDF): ``weight · [L_env(wo) +
  w_b · L_sun(wo)]`` where ``weight = f·|mu_o| / p_b`` and ``w_b = p_b² / (p_b² + p_s²)`` (power
  heuristic, Veach 1997 eq. 9.13); samples that transmit (``mu_o > 0``) carry nothing.
* **Sun sample** (uniform in the disk's cone, ``p_s = 1 / Ω``, ``Ω = 2π(1 - cos half_angle)``):
  ``f·|mu_o| · L_sun / p_s · w_s``, ``w_s = p_s² / (p_s² + p_b²)``, ``p_b`` from
  :meth:`FourierBSDF.pdf`; zero where the sampled direction is below the local horizon.
* **Delta**: ``F(mu_i; η) · [L_env(r) + L_sun(r)]`` with ``r = 2 (n·wi) n - wi``, no sampling.

Both sampled strategies use ``eval(…, clamp="none")`` (what ``sample``'s weight divides), so they
estimate the same integral.  Under a constant environment ``L`` without a sun the expected pixel is
``L · (albedo_R(mu_i) + F(mu_i))`` (the furnace test of renderers.md), with ``albedo_R`` the
reflection part of :meth:`FourierBSDF.albedo`.

A pixel's ``spp`` samples are stratified per dimension (pixel position, the two BSDF and the two sun
uniforms; Latin hypercube).  Work is split into row tiles; each tile draws its random numbers from
``np.random.default_rng([seed, tile])``, so an image depends on ``seed`` and ``tile_rows`` only,
never on the number of threads.  Tiles run on a thread pool: the BSDF kernels are compiled with
``nogil`` and the numpy glue releases the GIL for large arrays.
"""

from __future__ import annotations

import dataclasses
import math
import os
import time
from concurrent.futures import ThreadPoolExecutor, as_completed

import numpy as np

from flakedb.optics.fresnel import fresnel_dielectric

__all__ = [
    "Environment",
    "Sun",
    "RenderResult",
    "render_sphere",
    "check_renderable",
    "studio_environment",
    "studio_sun",
    "constant_environment",
    "orthonormal_basis",
    "DEFAULT_SPP",
    "DEFAULT_EXTENT",
]

#: Samples per pixel of ``flakedb render`` (a 256² smooth-coated preview in well under 30 s on 2 cores).
DEFAULT_SPP = 32
#: Half-width of the orthographic view in sphere radii (a small margin around the unit sphere).
DEFAULT_EXTENT = 1.05
#: Camera ray direction (propagation) and the view direction towards the camera.
CAMERA_DIR = np.array([0.0, 0.0, -1.0])
VIEW_DIR = np.array([0.0, 0.0, 1.0])
#: Sample points per tile (bounds memory: ~25 float64 arrays of this length per tile in flight).
_TILE_POINTS = 1 << 16
#: The largest float64 below 1.
_ONE_MINUS = float(np.nextafter(1.0, 0.0))


def _rgb(v, name) -> tuple:
    a = np.broadcast_to(np.asarray(v, dtype=np.float64), (3,))
    if not np.all(np.isfinite(a)) or np.any(a < 0):
        raise ValueError(f"{name} must be finite and >= 0 (a scalar or R, G, B), got {v!r}")
    return tuple(float(x) for x in a)


def _unit(v, name) -> tuple:
    a = np.asarray(v, dtype=np.float64).reshape(3)
    norm = float(np.linalg.norm(a))
    if not (np.isfinite(norm) and norm > 0):
        raise ValueError(f"{name} must be a non-zero finite 3-vector, got {v!r}")
    return tuple(float(x) for x in a / norm)


def orthonormal_basis(n):
    """Tangents ``(s, t)`` with ``(s, t, n)`` right-handed and orthonormal, for unit ``n`` (..., 3).

    Branchless construction of Duff et al. 2017 ("Building an orthonormal basis, revisited"),
    continuous except across ``n_z = 0``.

    >>> n = np.array([[0.0, 0.0, 1.0], [0.6, 0.0, 0.8], [0.0, -1.0, 0.0]])
    >>> s, t = orthonormal_basis(n)
    >>> bool(np.allclose(np.cross(s, t), n, rtol=0, atol=1e-15)), bool(np.allclose((s * n).sum(-1), 0.0, rtol=0, atol=1e-15))
    (True, True)
    """
    n = np.asarray(n, dtype=np.float64)
    x, y, z = n[..., 0], n[..., 1], n[..., 2]
    sign = np.where(z >= 0, 1.0, -1.0)
    a = -1.0 / (sign + z)
    b = x * y * a
    s = np.stack([1.0 + sign * x * x * a, sign * b, -sign * x], axis=-1)
    t = np.stack([b, sign + y * y * a, -y], axis=-1)
    return s, t


# --------------------------------------------------------------------------------------------
# Lights
# --------------------------------------------------------------------------------------------
@dataclasses.dataclass(frozen=True)
class Environment:
    """Distant environment radiance ``L(d)`` [relative radiance units, linear RGB].

    ``kind="constant"``: ``L = radiance`` everywhere.  ``kind="studio"``: with ``c = d·up``, a sky
    dome ``horizon + (zenith - horizon) · sqrt(c)`` for ``c >= 0`` (bright overhead, soft towards the
    horizon) and a dimmer ground ``ground · (1 - ground_falloff · |c|)`` below, blended with a
    smoothstep over ``|c| < horizon_blur`` so that no radiance edge sits exactly at the horizon.
    """

    kind: str = "studio"
    radiance: tuple = (0.5, 0.5, 0.5)
    zenith: tuple = (1.0, 1.02, 1.08)
    horizon: tuple = (0.55, 0.57, 0.62)
    ground: tuple = (0.16, 0.15, 0.14)
    ground_falloff: float = 0.5
    horizon_blur: float = 0.03
    up: tuple = (0.0, 1.0, 0.0)

    def __post_init__(self):
        if self.kind not in ("constant", "studio"):
            raise ValueError(f"Environment.kind must be 'constant' or 'studio', got {self.kind!r}")
        for name in ("radiance", "zenith", "horizon", "ground"):
            object.__setattr__(self, name, _rgb(getattr(self, name), f"Environment.{name}"))
        object.__setattr__(self, "up", _unit(self.up, "Environment.up"))
        if not (0 <= self.ground_falloff <= 1 and 0 < self.horizon_blur < 1):
            raise ValueError("Environment.ground_falloff must be in [0, 1] and horizon_blur in (0, 1)")

    def __call__(self, d) -> np.ndarray:
        """Radiance towards unit directions ``d`` (..., 3) -> (..., 3)."""
        d = np.asarray(d, dtype=np.float64)
        if self.kind == "constant":
            return np.broadcast_to(np.asarray(self.radiance), d.shape).copy()
        c = np.clip(d @ np.asarray(self.up), -1.0, 1.0)[..., None]
        zen, hor, gnd = (np.asarray(v) for v in (self.zenith, self.horizon, self.ground))
        sky = hor + (zen - hor) * np.sqrt(np.maximum(c, 0.0))
        ground = gnd * (1.0 - self.ground_falloff * np.maximum(-c, 0.0))
        u = np.clip((c + self.horizon_blur) / (2.0 * self.horizon_blur), 0.0, 1.0)
        b = u * u * (3.0 - 2.0 * u)
        return ground + b * (sky - ground)


def constant_environment(radiance=0.5) -> Environment:
    """A constant environment (the furnace of renderers.md: radiance 0.5)."""
    return Environment(kind="constant", radiance=radiance)


def studio_environment() -> Environment:
    """The default "studio": bright soft sky dome over a dim ground, +y up."""
    return Environment(kind="studio")


@dataclasses.dataclass(frozen=True)
class Sun:
    """A distant disk light: unit ``direction`` towards its centre, uniform ``radiance`` (linear
    RGB) inside the cone of angular radius ``half_angle_deg``.

    Its irradiance on a plane facing it is ``E = L π sin²(half_angle)`` (and ``E cos θ`` on a
    plane tilted by θ while the whole disk is above that plane's horizon)."""

    direction: tuple
    radiance: tuple
    half_angle_deg: float = 2.0

    def __post_init__(self):
        object.__setattr__(self, "direction", _unit(self.direction, "Sun.direction"))
        object.__setattr__(self, "radiance", _rgb(self.radiance, "Sun.radiance"))
        if not (0 < self.half_angle_deg < 90):
            raise ValueError(f"Sun.half_angle_deg must be in (0, 90), got {self.half_angle_deg!r}")

    @classmethod
    def from_irradiance(cls, direction, irradiance, half_angle_deg: float = 2.0) -> "Sun":
        """The sun whose normal-incidence irradiance is ``irradiance``: ``L = E / (π sin²α)``."""
        s2 = math.sin(math.radians(half_angle_deg)) ** 2
        e = np.asarray(_rgb(irradiance, "Sun irradiance"))
        return cls(direction, tuple(e / (math.pi * s2)), half_angle_deg)

    @property
    def cos_half_angle(self) -> float:
        return math.cos(math.radians(self.half_angle_deg))

    @property
    def one_minus_cos(self) -> float:
        """``1 - cos(half_angle)`` without cancellation (``2 sin²(α/2)``)."""
        return 2.0 * math.sin(math.radians(self.half_angle_deg) / 2.0) ** 2

    @property
    def solid_angle(self) -> float:
        """Ω = 2π (1 - cos half_angle) [sr]."""
        return 2.0 * math.pi * self.one_minus_cos

    @property
    def irradiance(self) -> np.ndarray:
        """Normal-incidence irradiance ``L π sin²α`` (3,)."""
        return np.asarray(self.radiance) * math.pi * math.sin(math.radians(self.half_angle_deg)) ** 2

    def contains(self, d) -> np.ndarray:
        """Whether unit directions ``d`` (..., 3) point into the disk."""
        return np.asarray(d) @ np.asarray(self.direction) >= self.cos_half_angle

    def radiance_at(self, d) -> np.ndarray:
        """``L_sun`` where ``d`` is inside the disk, else 0: (..., 3)."""
        return self.contains(d)[..., None] * np.asarray(self.radiance)

    def sample(self, u1, u2) -> np.ndarray:
        """Directions uniform in the cone (pdf ``1 / solid_angle`` per steradian): (..., 3)."""
        c = np.asarray(self.direction)
        s, t = orthonormal_basis(c)
        one_minus = np.asarray(u1) * self.one_minus_cos
        cos_t = 1.0 - one_minus
        sin_t = np.sqrt(np.maximum(one_minus * (2.0 - one_minus), 0.0))
        phi = 2.0 * np.pi * np.asarray(u2)
        return ((sin_t * np.cos(phi))[..., None] * s + (sin_t * np.sin(phi))[..., None] * t
                + cos_t[..., None] * c)


def studio_sun() -> Sun:
    """The default key light: from the upper left, in front, irradiance 3 (about the sky's
    irradiance on an upward-facing plane), 2° angular radius, slightly warm."""
    return Sun.from_irradiance(direction=(-0.45, 0.65, 0.6), irradiance=(3.0, 2.9, 2.75), half_angle_deg=2.0)


# --------------------------------------------------------------------------------------------
# Rendering
# --------------------------------------------------------------------------------------------
@dataclasses.dataclass
class RenderResult:
    """``image`` float32 (size, size, 3) linear RGB, row 0 at the top; ``coverage`` float32
    (size, size), the fraction of a pixel's samples that hit the sphere; ``seconds`` of wall time;
    ``settings`` (dict) of what was rendered."""

    image: np.ndarray
    coverage: np.ndarray
    seconds: float
    settings: dict


def check_renderable(bsdf) -> tuple:
    """``(delta_eta or None, output channels 1 or 3)`` of ``bsdf``; raises ValueError with the
    reason when the preview cannot render it (an unknown delta kind, neither 1 nor 3 channels)."""
    return _delta_fresnel(bsdf), _output_channels(bsdf)


def _delta_fresnel(bsdf):
    """The file's delta term as ``eta`` (or None).  Only ``{"kind": "fresnel"}`` is defined."""
    delta = bsdf.delta
    if delta is None:
        return None
    if delta.get("kind") != "fresnel":
        raise ValueError(f"{bsdf.path}: unknown delta term {delta!r}; the preview renderer knows "
                         "only {'kind': 'fresnel', 'eta': η} (docs/bsdf-format.md)")
    return float(delta["eta"])


def _output_channels(bsdf) -> int:
    ch = tuple(bsdf.channels)
    if len(ch) == 3 or len(ch) == 1:
        return len(ch)
    raise ValueError(f"{bsdf.path}: the preview renders RGB or mono files; this one has {len(ch)} "
                     f"channels {ch}. Compose it with RGB channels to preview it.")


def _shade(bsdf, env, sun, delta_eta, n, u, nout):
    """Reflected radiance (M, 3) towards ``VIEW_DIR`` at unit normals ``n`` (M, 3), one sample each;
    ``u`` (4, M) uniforms in [0, 1): BSDF sample (u[0] -> mu_o, u[1] -> phi_d), sun sample (u[2:4])."""
    m = n.shape[0]
    out = np.zeros((m, 3))
    if m == 0:
        return out
    s, t = orthonormal_basis(n)
    mu_i = n @ VIEW_DIR                                           # cos θ(wi)
    phi_i = np.arctan2(t @ VIEW_DIR, s @ VIEW_DIR)
    p_s = 1.0 / sun.solid_angle if sun is not None else 0.0

    def to_rgb(v):
        return v if nout == 3 else np.repeat(v, 3, axis=-1)

    # -- BSDF sampling (the file's CDF)
    mu_o, phi_d, weight, p_b = bsdf.sample(mu_i, u[0], u[1])
    ok = (mu_o < 0) & (p_b > 0)
    if ok.any():
        cos_o = -mu_o[ok]
        sin_o = np.sqrt(np.maximum(1.0 - cos_o * cos_o, 0.0))
        phi_o = phi_i[ok] + np.pi - phi_d[ok]
        wo = ((sin_o * np.cos(phi_o))[:, None] * s[ok] + (sin_o * np.sin(phi_o))[:, None] * t[ok]
              + cos_o[:, None] * n[ok])
        radiance = env(wo)
        if sun is not None:
            pb = p_b[ok]
            w_b = pb * pb / (pb * pb + p_s * p_s)
            radiance += sun.radiance_at(wo) * w_b[:, None]
        out[ok] += to_rgb(weight[ok]) * radiance

    # -- sun sampling, MIS with the BSDF's pdf
    if sun is not None and any(sun.radiance):
        wo = sun.sample(u[2], u[3])
        cos_o = np.einsum("ij,ij->i", wo, n)
        up = cos_o > 0
        if up.any():
            wu = wo[up]
            phi_o = np.arctan2(np.einsum("ij,ij->i", wu, t[up]), np.einsum("ij,ij->i", wu, s[up]))
            phi = np.mod(np.pi - (phi_o - phi_i[up]), 2.0 * np.pi)
            mu_o_l = -cos_o[up]
            f = to_rgb(bsdf.eval(mu_i[up], mu_o_l, phi, clamp="none"))
            pb = bsdf.pdf(mu_i[up], mu_o_l, phi)
            w_s = p_s * p_s / (p_s * p_s + pb * pb)
            out[up] += f * np.asarray(sun.radiance)[None, :] * (w_s / p_s)[:, None]

    # -- the smooth coat's delta reflection, exact
    if delta_eta is not None:
        F = fresnel_dielectric(mu_i, delta_eta).R
        r = 2.0 * mu_i[:, None] * n - VIEW_DIR
        radiance = env(r)
        if sun is not None:
            radiance += sun.radiance_at(r)
        out += F[:, None] * radiance
    return out


def _latin_hypercube(rng, dims, shape):
    """(dims, *shape) uniforms in [0, 1): along the last axis (a pixel's samples) each dimension is
    stratified into ``shape[-1]`` equal strata, one sample per stratum, with an independent random
    permutation per dimension and pixel (Latin hypercube; unbiased, lower variance than iid)."""
    spp = shape[-1]
    strata = np.broadcast_to(np.arange(spp, dtype=np.float64), (dims,) + tuple(shape))
    u = (rng.permuted(strata, axis=-1) + rng.random((dims,) + tuple(shape))) / spp
    return np.minimum(u, _ONE_MINUS)                 # (k + r)/spp may round up to 1.0


def _render_rows(bsdf, env, sun, delta_eta, nout, rows, size, spp, extent, jitter, rng):
    """Mean radiance (len(rows), size, 3) and sphere coverage (len(rows), size) of image rows."""
    pix = 2.0 * extent / size
    rr, cc = np.meshgrid(rows, np.arange(size), indexing="ij")              # (R, W)
    shape = rr.shape + (spp,)
    u = _latin_hypercube(rng, 6, shape)
    ox, oy = (u[0], u[1]) if jitter else (np.full(shape, 0.5),) * 2
    x = (-extent + (cc[..., None] + ox) * pix).ravel()
    y = (extent - (rr[..., None] + oy) * pix).ravel()
    r2 = x * x + y * y
    hit = r2 < 1.0
    val = np.empty((x.size, 3))
    background = env(CAMERA_DIR)
    if sun is not None:
        background = background + sun.radiance_at(CAMERA_DIR)
    val[~hit] = background
    n = np.stack([x[hit], y[hit], np.sqrt(1.0 - r2[hit])], axis=-1)
    val[hit] = _shade(bsdf, env, sun, delta_eta, n, u[2:, hit.reshape(shape)], nout)
    return val.reshape(shape + (3,)).mean(axis=2), hit.reshape(shape).mean(axis=2)


def render_sphere(bsdf, env: Environment | None = None, sun: Sun | None = None, *, size: int = 256,
                  spp: int = DEFAULT_SPP, seed: int = 0, jitter: bool = True,
                  extent: float = DEFAULT_EXTENT, tile_rows: int | None = None,
                  threads: int | None = None, progress=None) -> RenderResult:
    """Render the unit sphere made of ``bsdf`` (a :class:`flakedb.bsdf.FourierBSDF`).

    Parameters
    ----------
    env : Environment, default :func:`studio_environment`
    sun : Sun or None (no sun)
    size : image width = height [pixels]
    spp : samples per pixel (each: one BSDF sample, one sun sample, the exact delta term)
    seed : random seed (with ``tile_rows`` it fixes the image)
    jitter : pixel positions uniformly jittered inside the pixel (anti-aliasing); ``False`` shades
        every sample at the pixel centre, so each pixel's expectation is that of its centre
    extent : the image covers ``[-extent, extent]²`` [sphere radii]
    tile_rows : rows per work item (default: about 65k sample points per tile)
    threads : worker threads (default: the CPUs this process may use)
    progress : callable(n_rows_done) called from the calling thread as tiles finish

    Returns a :class:`RenderResult`.  Raises ValueError for a delta kind other than ``fresnel`` or
    a file with neither 1 nor 3 output channels.
    """
    size, spp = int(size), int(spp)
    if size < 1 or spp < 1:
        raise ValueError(f"size and spp must be >= 1, got size={size}, spp={spp}")
    if not extent > 0:
        raise ValueError(f"extent must be > 0, got {extent!r}")
    env = studio_environment() if env is None else env
    delta_eta, nout = check_renderable(bsdf)
    if tile_rows is None:
        tile_rows = max(1, _TILE_POINTS // (size * spp))
    tile_rows = int(min(max(1, tile_rows), size))
    if threads is None:
        threads = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
    threads = max(1, int(threads))
    starts = list(range(0, size, tile_rows))
    image = np.zeros((size, size, 3))
    coverage = np.zeros((size, size))

    def work(k):
        rows = np.arange(starts[k], min(starts[k] + tile_rows, size))
        rng = np.random.default_rng([int(seed), k])
        return rows, _render_rows(bsdf, env, sun, delta_eta, nout, rows, size, spp, extent, jitter, rng)

    t0 = time.perf_counter()
    if threads == 1 or len(starts) == 1:
        for k in range(len(starts)):
            rows, (v, c) = work(k)
            image[rows], coverage[rows] = v, c
            if progress is not None:
                progress(rows.size)
    else:
        with ThreadPoolExecutor(max_workers=threads) as pool:
            futures = [pool.submit(work, k) for k in range(len(starts))]
            for fut in as_completed(futures):
                rows, (v, c) = fut.result()
                image[rows], coverage[rows] = v, c
                if progress is not None:
                    progress(rows.size)
    seconds = time.perf_counter() - t0
    settings = {"size": size, "spp": spp, "seed": int(seed), "jitter": bool(jitter), "extent": float(extent),
                "tile_rows": tile_rows, "threads": threads, "environment": dataclasses.asdict(env),
                "sun": None if sun is None else dataclasses.asdict(sun),
                "delta": None if bsdf.delta is None else dict(bsdf.delta),
                "file": None if bsdf.path is None else str(bsdf.path)}
    return RenderResult(image.astype(np.float32), coverage.astype(np.float32), seconds, settings)
