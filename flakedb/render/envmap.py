"""Environments as images: spherical (θ, φ) grids of radiance, the lat-long EXR layout, and the
rasterisation of an analytic environment and a sun disk onto such a grid.  Pure numerics (arrays in,
arrays out); :mod:`flakedb.render.imageio` reads and writes the EXR files.

Grids
-----
A :class:`PolarFrame` (``pole``, ``ref``, ``side``: orthonormal) spans the grid: a direction at polar
angle θ from ``pole`` and azimuth φ is ``d = sinθ cosφ ref + sinθ sinφ side + cosθ pole``.  A grid of
``n_theta × n_phi`` cells has cell ``(r, c)`` over ``θ ∈ [r, r+1]·π/n_theta`` and ``φ ∈ [c, c+1]·2π/n_phi``,
solid angle ``Ω_r = (2π/n_phi)(cos θ_r − cos θ_{r+1})`` (exact; ``Σ Ω = 4π``).

* :data:`LATLONG` is the lat-long ("equirectangular") layout of Mitsuba 3's ``envmap`` with an identity
  ``to_world``: row 0 looks up (+y), ``u = atan2(d_x, −d_z)/2π`` (mod 1) left to right, ``v = acos(d_y)/π``
  top to bottom, i.e. pole +y, ref −z, side +x.  An image ``(H, W, 3)`` with ``W = 2H`` is such a grid.
* The preview's own grid (:mod:`flakedb.render.quadrature`) has its pole on the view axis +z.

A cell's value is the **mean radiance over the cell** (:func:`cell_average`: ``ss × ss`` sub-cells
weighted by their exact solid angle), so that ``Σ Ω_r E[r, c]`` is the environment's integral to the
sub-cell quadrature's accuracy; a sun disk, much smaller than a smooth environment's features, is added
by :func:`splat_sun`: ``n_points`` equal-solid-angle directions of the disk each deposit ``L Ω_sun /
n_points`` of power, shared bilinearly between the four nearest cell centres (so the power's centroid in
(θ, φ) stays where the point is), and the grid carries the sun's power exactly.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

__all__ = ["PolarFrame", "LATLONG", "LatLongEnvironment", "cell_solid_angles", "cell_directions",
           "grid_coordinates", "cell_average", "splat_sun", "sun_directions", "rasterise_latlong"]


@dataclasses.dataclass(frozen=True)
class PolarFrame:
    """Orthonormal ``pole`` (θ = 0), ``ref`` (φ = 0) and ``side`` (φ = π/2) of a spherical grid."""

    pole: tuple
    ref: tuple
    side: tuple

    def matrix(self) -> np.ndarray:
        """Rows ref, side, pole: world -> grid-local coordinates."""
        return np.array([self.ref, self.side, self.pole], dtype=np.float64)


#: Mitsuba 3 ``envmap`` lat-long layout (module docstring).
LATLONG = PolarFrame(pole=(0.0, 1.0, 0.0), ref=(0.0, 0.0, -1.0), side=(1.0, 0.0, 0.0))


def cell_solid_angles(n_theta: int, n_phi: int) -> np.ndarray:
    """Ω_r [sr] of one cell of row r (n_theta,): ``(2π/n_phi)(cos θ_r − cos θ_{r+1})``.  The cells tile the
    sphere: n_phi Σ_r Ω_r = 4π, and rows mirrored about the equator have equal cells.

    >>> om = cell_solid_angles(64, 128)
    >>> bool(abs(128 * om.sum() - 4 * np.pi) < 1e-12), bool(np.allclose(om, om[::-1]))
    (True, True)
    """
    edges = np.linspace(0.0, np.pi, n_theta + 1)
    return (2.0 * np.pi / n_phi) * (np.cos(edges[:-1]) - np.cos(edges[1:]))


def _directions(theta, phi, frame: PolarFrame) -> np.ndarray:
    st = np.sin(theta)
    local = np.stack(np.broadcast_arrays(st * np.cos(phi), st * np.sin(phi), np.cos(theta)), axis=-1)
    return local @ frame.matrix()


def cell_directions(n_theta: int, n_phi: int, frame: PolarFrame) -> np.ndarray:
    """Unit directions (n_theta, n_phi, 3) of the cell centres (θ and φ at the cells' middles)."""
    theta = (np.arange(n_theta) + 0.5) * np.pi / n_theta
    phi = (np.arange(n_phi) + 0.5) * 2.0 * np.pi / n_phi
    return _directions(theta[:, None], phi[None, :], frame)


def grid_coordinates(d, frame: PolarFrame):
    """(θ in [0, π], φ in [0, 2π)) of unit directions ``d`` (..., 3) in ``frame``."""
    local = np.asarray(d, dtype=np.float64) @ frame.matrix().T
    theta = np.arccos(np.clip(local[..., 2], -1.0, 1.0))
    phi = np.mod(np.arctan2(local[..., 1], local[..., 0]), 2.0 * np.pi)
    return theta, phi


def cell_average(env, n_theta: int, n_phi: int, frame: PolarFrame, ss: int = 4) -> np.ndarray:
    """Mean radiance of ``env`` (callable, unit directions (..., 3) -> (..., 3)) over each cell:
    (n_theta, n_phi, 3), from ``ss × ss`` sub-cells per cell (midpoints in θ and φ), each weighted by its
    exact solid angle (a constant environment gives that constant exactly)."""
    ss = max(1, int(ss))
    m_t, m_p = n_theta * ss, n_phi * ss
    edges = np.linspace(0.0, np.pi, m_t + 1)
    w = np.cos(edges[:-1]) - np.cos(edges[1:])                                # sub-row solid angle / dφ
    theta = 0.5 * (edges[:-1] + edges[1:])
    phi = (np.arange(m_p) + 0.5) * 2.0 * np.pi / m_p
    out = np.empty((n_theta, n_phi, 3))
    rows = max(1, (1 << 19) // m_p)                                           # bounded memory
    for r0 in range(0, n_theta, max(1, rows // ss)):
        r1 = min(n_theta, r0 + max(1, rows // ss))
        sl = slice(r0 * ss, r1 * ss)
        L = np.asarray(env(_directions(theta[sl, None], phi[None, :], frame)), dtype=np.float64)
        L = L * w[sl, None, None]
        L = L.reshape(r1 - r0, ss, n_phi, ss, 3).sum(axis=(1, 3))
        out[r0:r1] = L / (w[sl].reshape(r1 - r0, ss).sum(axis=1)[:, None, None] * ss)
    return out


def sun_directions(sun, n_points: int) -> np.ndarray:
    """``n_points`` directions (n, 3) inside ``sun``'s disk, each standing for an equal solid angle
    ``Ω_sun / n``: rings equal in ``cos θ`` (midpoints) at the golden-angle azimuths (Vogel's spiral)."""
    k = np.arange(int(n_points)) + 0.5
    one_minus = k / n_points * sun.one_minus_cos
    cos_t = 1.0 - one_minus
    sin_t = np.sqrt(np.maximum(one_minus * (2.0 - one_minus), 0.0))
    az = k * math.pi * (3.0 - math.sqrt(5.0))
    c = np.asarray(sun.direction, dtype=np.float64)
    a = np.array([1.0, 0.0, 0.0]) if abs(c[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    s = np.cross(c, a)
    s /= np.linalg.norm(s)
    t = np.cross(c, s)
    return ((sin_t * np.cos(az))[:, None] * s + (sin_t * np.sin(az))[:, None] * t + cos_t[:, None] * c)


def splat_sun(grid, sun, frame: PolarFrame, n_points: int = 4096) -> np.ndarray:
    """``grid`` (n_theta, n_phi, 3) of mean cell radiance with ``sun``'s power added (module docstring):
    a new array; ``Σ Ω_r · added = L_sun Ω_sun`` exactly."""
    out = np.array(grid, dtype=np.float64, copy=True)
    if sun is None or not any(sun.radiance):
        return out
    n_theta, n_phi = out.shape[:2]
    theta, phi = grid_coordinates(sun_directions(sun, n_points), frame)
    # bilinear splat between the four nearest cell centres: the power's centroid stays at each point
    y = np.clip(theta / np.pi * n_theta - 0.5, 0.0, n_theta - 1.0)
    x = phi / (2.0 * np.pi) * n_phi - 0.5
    r0 = np.minimum(np.floor(y).astype(np.int64), max(n_theta - 2, 0))
    ty = y - r0
    x0f = np.floor(x)
    tx = x - x0f
    c0 = np.mod(x0f.astype(np.int64), n_phi)
    c1 = np.mod(c0 + 1, n_phi)
    count = np.zeros((n_theta, n_phi))
    for r, c, w in ((r0, c0, (1 - ty) * (1 - tx)), (r0, c1, (1 - ty) * tx), (r0 + 1, c0, ty * (1 - tx)),
                    (r0 + 1, c1, ty * tx)):
        np.add.at(count, (np.minimum(r, n_theta - 1), c), w)
    omega = cell_solid_angles(n_theta, n_phi)
    out += (count * (sun.solid_angle / n_points) / omega[:, None])[..., None] * np.asarray(sun.radiance)
    return out


def rasterise_latlong(env, sun=None, width: int = 1024, ss: int = 4, sun_points: int = 16384) -> np.ndarray:
    """The lat-long image (width/2, width, 3) float32 of ``env`` plus ``sun`` (the HDR environment
    ``flakedb render --write-environment`` writes): mean radiance per pixel (:func:`cell_average`, then
    :func:`splat_sun`)."""
    width = int(width)
    if width < 4 or width % 2:
        raise ValueError(f"lat-long width must be even and >= 4, got {width}")
    grid = cell_average(env, width // 2, width, LATLONG, ss)
    return splat_sun(grid, sun, LATLONG, sun_points).astype(np.float32)


@dataclasses.dataclass(frozen=True, eq=False)
class LatLongEnvironment:
    """Radiance from a lat-long image ``image`` (H, W, 3), :data:`LATLONG` layout, bilinear between
    pixel centres (wrapping in φ, clamped at the poles).  ``source``: where it came from (a file name)."""

    image: np.ndarray
    source: str = ""
    kind: str = "latlong"

    def __post_init__(self):
        img = np.asarray(self.image, dtype=np.float64)
        if img.ndim != 3 or img.shape[2] != 3 or img.shape[0] < 2 or img.shape[1] < 2:
            raise ValueError(f"a lat-long environment is an (H, W, 3) image with H, W >= 2; got shape {img.shape}")
        if not np.all(np.isfinite(img)) or np.any(img < 0):
            raise ValueError("a lat-long environment must hold finite radiance >= 0 in every pixel")
        object.__setattr__(self, "image", img)

    def __call__(self, d) -> np.ndarray:
        h, w = self.image.shape[:2]
        theta, phi = grid_coordinates(d, LATLONG)
        y = np.clip(theta / np.pi * h - 0.5, 0.0, h - 1.0)
        x = phi / (2.0 * np.pi) * w - 0.5
        y0 = np.minimum(np.floor(y).astype(np.int64), h - 2)
        ty = (y - y0)[..., None]
        x0f = np.floor(x)
        tx = (x - x0f)[..., None]
        x0 = np.mod(x0f.astype(np.int64), w)
        x1 = np.mod(x0 + 1, w)
        im = self.image
        return ((1 - ty) * ((1 - tx) * im[y0, x0] + tx * im[y0, x1])
                + ty * ((1 - tx) * im[y0 + 1, x0] + tx * im[y0 + 1, x1]))

    def settings(self) -> dict:
        return {"kind": self.kind, "source": self.source, "shape": list(self.image.shape)}
