"""Angle-dependent colour in production materials: a coat, a Lambert term and a few GGX lobes whose
RGB colours are a table indexed by angle, fitted to a paint's exact BSDF over the hemisphere.

The car-paint industry carries effect paints this way (X-Rite AxF, CPA2: a few Cook-Torrance lobes
and a BRDF colour table indexed by angles, under a clear coat).  What a renderer's shader can index
by decides the table's axes: in Cycles' and EEVEE's node trees (and in a MaterialX graph of standard
nodes) the shading point knows its normal N and view direction ω_v, never the light's, so the half
vector and θ_d of AxF's table are not available there.  This model therefore indexes by the view
cosine μ_v = N·ω_v and leaves the light dependence to the lobes (what AxF-style Cycles
implementations do)::

    f(ω_v, ω_l) = F_c(μ_v) δ(ω_l - mirror(ω_v))  +  C_0(μ_v) / π  +  Σ_{k=1..K} C_k(μ_v) L_k(ω_v, ω_l)
                  +  Σ_{r=1..R} C_{K+r}(μ_v) B_r(ω_v, ω_l),

    L_k = D(h; α_k) G2(ω_v, ω_l; α_k) / (4 μ_v μ_l),    B_r = D(h·ω_v; α_r) G2(1, ω_v·ω_l; α_r) / (4 μ_l),

with F_c the smooth coat's dielectric Fresnel reflectance (the file's ``delta``, carried exactly, left
out of the fit; Born & Wolf §1.5.2), D the GGX distribution and G2 the height-correlated Smith
masking-shadowing (Heitz 2014, eq. 99): Cycles' Glossy BSDF with GGX and no Fresnel
(:func:`flakedb.export.blender.ggx_lobe_height_correlated`), so that the model is what the Blender
node group renders, term for term.  B_r (:func:`retro_lobe`) is the same Glossy BSDF with its shading normal
set to the view direction: a backscatter lobe, peaked at ω_l = ω_v.  At one view cosine every L_k is
largest towards the mirror direction, so no mixture of them with view-indexed colours can make a
geometry on the light's side (E2194's aspecular 75°, 110°) redder than one of the same μ_v across the
normal (15°), as the particle pearlescent is; B_r can.  Nor can it make aspecular 75° darker than 2.1e-3 of
aspecular 15° (:func:`ggx_route_floor`), as a bare Beckmann metal under the coat needs; where that leaves the
GGX fit above the target, the MaterialX graph adds a tilted lobe T (:func:`tilted_lobe`: the same Glossy BSDF
about a normal tilted from N away from ω_v, built from N and ω_v; :func:`fit_cpa_materialx`) coloured by one
more table row (the Cycles node group takes Beckmann lobes instead: :func:`fit_cpa_cycles`).  Each C_k is linear RGB, piecewise linear in μ_v between
``n_table`` equally spaced nodes μ_j = j / (n_table - 1): row k of the colour table (an image of
(K + 1) rows x n_table columns, read with linear interpolation at pixel centres).  Nothing
multiplies a lobe by a function of the light direction, so the coat's transmission at the light end,
(1 - F_c(μ_l)), the refraction of the flakes' lobes by the coat and every light-side colour change
are approximated by the K + 1 lobe shapes with view-dependent weights.  The model is not reciprocal
(the exact BSDF is); it is evaluated with ω_v the camera's side, as renderers do.

The fit (:func:`fit_cpa`)
------------------------
For fixed roughnesses (α_1..α_K) the model is linear in the (K + 1) n_table colours per channel, so
they have a non-negative least-squares solution (Lawson-Hanson, :func:`scipy.optimize.nnls`) of
the weighted residual over

* a hemisphere sample set: Gauss-Legendre nodes in μ_v and μ_l on (0, 1), midpoints in φ_d on
  (0, π) (f is even in φ_d), weight ``w_q μ_v μ_l`` (the cosine-weighted difference), times the
  perceptual factor ``R^(-4/3)`` of CIELAB's cube root linearised at the sample's reflectance factor
  R = π mean(f) (floored at :data:`R_FLOOR`), so that the fit spends its freedom where ΔE00 is judged;
* the colour geometries of ASTM E2194 (45° illumination) and E2539 (15°), weighted
  :data:`GEOMETRY_WEIGHT` times the hemisphere's total, in ΔL*-like units as in
  :func:`flakedb.export.openpbr.fit_openpbr`;
* a small second-difference penalty along μ_v (:data:`SMOOTHNESS`: the table stays smooth where no
  sample falls, e.g. towards μ_v = 0).

The GGX subsets of :data:`ALPHA_GRID` (every K-subset) are ranked by their weighted residual (without
backscatter lobes); for each in turn, the backscatter α of least residual is taken from
:data:`RETRO_ALPHA_GRID` and :data:`MINIMAX_PASSES` reweightings of the E2194 geometries towards their
worst ΔE00 are run; the first subset whose best pass meets :data:`E2194_TARGET` is kept (the
hemisphere's best among those that meet the issue's target), else the one of least E2194 worst.

Reported: ΔE00 (CIEDE2000, D65 / 2°, the file's white-normalised linear sRGB) at every E2194 and
E2539 geometry, and over the hemisphere sample set (median, 95th percentile, max, for both
directions within 70° of the normal and over all of it), with the cosine-weighted relative BSDF
difference.  Measurements per paint: docs/renderers.md.
"""

from __future__ import annotations

import itertools
import math
import struct
import zlib
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
from scipy.optimize import minimize, nnls
from scipy.sparse import csr_matrix

from flakedb.atomic import atomic_path
from flakedb.colour.tolerance import delta_E_2000
from flakedb.export.blender import GLOSSY_LOBES, ggx_lobe_height_correlated, sphere_normals, sun_disk
from flakedb.export.materialx_glsl import compensated_lobe_colours
from flakedb.export.openpbr import colour_grid, cosine_weighted_difference, exact_rgb, file_directions
from flakedb.match.fit import channels_to_Lab, geometry_directions
from flakedb.match.targets import E2194_GEOMETRIES, E2539_EXTRA
from flakedb.optics.fresnel import fresnel_dielectric_real

#: Columns of the colour table (nodes in μ_v) and number of GGX lobes.
N_TABLE = 32
N_LOBES = 3
#: GGX α searched for the lobes (every N_LOBES-subset of it).
ALPHA_GRID = (0.03, 0.06, 0.11, 0.18, 0.28, 0.42, 0.65)
#: Backscatter lobes (:func:`retro_lobe`): how many, and the GGX α searched for them.
N_RETRO = 1
RETRO_ALPHA_GRID = (0.18, 0.28, 0.42, 0.65, 1.0)
#: Tilted lobes (:func:`tilted_lobe`, MaterialX's route where GGX lobes about N miss the target): the (α, k)
#: searched.  k = 0.304 centres the lobe on ASTM E2194's aspecular 15° at its view (μ_v = cos 30°).
TILT_GRID = tuple((a, k) for a in (0.03, 0.06, 0.11) for k in (0.15, 0.304, 0.45))
#: Energy (:func:`energy_capped`): points per table interval at which the albedo is held ≤ 1 (its nodes and
#: N_ENERGY_SUB − 1 between), and the half-vector quadrature of :func:`lobe_albedos` (Gauss-Legendre nodes in
#: the lobe's CDF u, midpoints in φ).
N_ENERGY_SUB = 4
N_ALBEDO_U = 48
N_ALBEDO_PHI = 48
#: Hemisphere sample set of the fit: Gauss-Legendre nodes in μ_v and μ_l, midpoints in φ_d.
N_MU_FIT = 16
N_PHI_FIT = 24
#: Exponent p of the hemisphere's perceptual weight R^(-p) (4/3: CIELAB's cube root linearised).
PERCEPTUAL_EXPONENT = 4.0 / 3.0
#: Reflectance factor below which the perceptual weight R^(-4/3) stops growing.
R_FLOOR = 0.01
#: The colour geometries' total weight relative to the hemisphere's.
GEOMETRY_WEIGHT = 1.0
#: Weight of an E2539 (15° illumination) geometry relative to an E2194 one.
E2539_SHARE = 0.2
#: Weight of the second-difference penalty along μ_v, relative to the data's mean diagonal.
SMOOTHNESS = 1e-2
#: Reweightings of the E2194 geometries towards the worst ΔE00.
MINIMAX_PASSES = 8
#: The issue's target: worst ΔE00 at the E2194 geometries.  The lobe subsets are tried in order of their
#: residual (at most MAX_SUBSETS of them) until one's minimax meets it.
E2194_TARGET = 2.0
MAX_SUBSETS = 35
#: Largest view / light angle of the "within 70°" hemisphere statistics.
HEMISPHERE_STAT_DEG = 70.0


@dataclass
class CPAFit:
    """The fitted material.

    table (K + 1, n_table, 3) linear RGB colours: row 0 the Lambert term's, row k the lobe of
    α = ``alphas[k - 1]`` (roughness √α) of ``distribution`` (a key of
    :data:`flakedb.export.blender.GLOSSY_LOBES`: ``"ggx"``, or ``"beckmann"`` for the Cycles node group only);
    column j at μ_v = j / (n_table - 1).  coat_ior: the smooth coat's index (1: no coat mirror).  error: what the
    fit costs (module docstring).  The backscatter lobes (``retro_alphas``) are GGX whatever ``distribution``; so
    are the tilted lobes (``tilted``: (α, k) pairs of :func:`tilted_lobe`, the table's last rows)."""

    table: np.ndarray
    alphas: tuple
    coat_ior: float
    source: str = ""
    error: dict = field(default_factory=dict)
    retro_alphas: tuple = ()
    distribution: str = "ggx"
    tilted: tuple = ()

    @property
    def n_table(self) -> int:
        return int(self.table.shape[1])

    def to_dict(self) -> dict:
        return {"model": "flakedb.export.cpa: coat mirror + Lambert + GGX lobes, RGB colours indexed by N.V",
                "alphas": [float(a) for a in self.alphas], "roughness": [float(math.sqrt(a)) for a in self.alphas],
                "retro_alphas": [float(a) for a in self.retro_alphas],
                "retro_roughness": [float(math.sqrt(a)) for a in self.retro_alphas],
                "distribution": self.distribution,
                "tilted": [[float(a), float(k)] for a, k in self.tilted],
                "coat_ior": float(self.coat_ior), "n_table": self.n_table, "source": self.source,
                "table": np.round(self.table, 7).tolist(), "error": self.error}

    @classmethod
    def from_dict(cls, d) -> CPAFit:
        return cls(np.asarray(d["table"], float), tuple(float(a) for a in d["alphas"]), float(d["coat_ior"]),
                   d.get("source", ""), dict(d.get("error", {})), tuple(float(a) for a in d.get("retro_alphas", ())),
                   str(d.get("distribution", "ggx")), tuple((float(a), float(k)) for a, k in d.get("tilted", ())))


# --------------------------------------------------------------------------------------------
# The model
# --------------------------------------------------------------------------------------------
def hat_weights(mu_v, n_table: int) -> np.ndarray:
    """(P, n_table) weights of linear interpolation between the nodes μ_j = j / (n_table - 1) at
    ``mu_v`` (clipped to [0, 1]): what an image texture read with linear interpolation at pixel
    centres returns.  Rows sum to 1; a node is returned exactly, a midpoint half and half.

    >>> hat_weights([0.0, 0.5, 1.0, 0.25], 3).tolist()
    [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [0.5, 0.5, 0.0]]
    """
    x = np.clip(np.asarray(mu_v, float).ravel(), 0.0, 1.0) * (n_table - 1)
    j = np.minimum(np.floor(x).astype(int), n_table - 2)
    t = x - j
    H = np.zeros((x.size, n_table))
    H[np.arange(x.size), j] = 1.0 - t
    H[np.arange(x.size), j + 1] = t
    return H


def retro_lobe(mu_l, cos_vl, alpha) -> np.ndarray:
    """The backscatter lobe [1/sr]: Cycles' Glossy BSDF (GGX, F = 1) whose shading normal is the view
    direction ω_v, seen through the true normal.  Its closure, with N' = ω_v (N'·ω_v = 1, N'·ω_l =
    ``cos_vl`` = ω_v·ω_l, half vector h·ω_v = sqrt((1 + cos_vl) / 2)), returns ``D G2 / (4 cos_vl)``
    times the cosine cos_vl to its own normal; the radiance under a light is that, so the BRDF about the
    true normal is ``D G2 / (4 μ_l)`` (zero where μ_l ≤ 0 or cos_vl ≤ 0).  It peaks at retro-reflection
    (ω_l = ω_v) and, unlike a GGX lobe about N, tells apart two geometries of one view cosine that
    differ by the side of the light (E2194's aspecular 15° and 75°)."""
    mu_l, cos_vl = np.asarray(mu_l, float), np.asarray(cos_vl, float)
    ok = (mu_l > 0) & (cos_vl > 0)
    c = np.clip(cos_vl, 1e-12, 1.0)
    f = ggx_lobe_height_correlated(1.0, c, np.sqrt(0.5 * (1.0 + c)), alpha) * c / np.clip(mu_l, 1e-12, None)
    return np.where(ok, f, 0.0)


def tilted_cosines(mu_v, mu_l, cos_h, cos_vl, k):
    """(N'·ω_v, N'·ω_l, N'·h) of the tilted normal N' = (N (1 + k μ_v²) − k μ_v ω_v) / n of :func:`tilted_lobe`,
    n = |N (1 + k μ_v²) − k μ_v ω_v| = sqrt(1 + k² μ_v² (1 − μ_v²)), from the cosines the model knows
    (ω_v·h = sqrt((1 + ω_v·ω_l) / 2)).  N' is N tilted in the plane of N and ω_v, away from ω_v for k > 0, by
    τ with tan τ = k μ_v sin θ_v (0 at normal and at grazing view); N'·ω_v = μ_v (1 − k sin²θ_v) / n > 0 for
    |k| < 1.

    >>> [round(float(x), 12) for x in tilted_cosines(0.6, 0.8, 0.9, 0.3, 0.0)]
    [0.6, 0.8, 0.9]
    """
    mu_v, mu_l, cos_h, cos_vl = (np.asarray(x, float) for x in (mu_v, mu_l, cos_h, cos_vl))
    a = 1.0 + k * mu_v * mu_v
    b = k * mu_v
    n = np.sqrt(1.0 + k * k * mu_v * mu_v * (1.0 - mu_v * mu_v))
    v_h = np.sqrt(np.clip(0.5 * (1.0 + cos_vl), 0.0, 1.0))
    return (a * mu_v - b) / n, (a * mu_l - b * cos_vl) / n, (a * cos_h - b * v_h) / n


def tilted_lobe(mu_v, mu_l, cos_h, cos_vl, alpha, k) -> np.ndarray:
    """A tilted lobe [1/sr]: Cycles' Glossy BSDF / MaterialX's ``generalized_schlick_bsdf`` (GGX, F = 1) whose
    shading normal is N' of :func:`tilted_cosines` (built in the graph from N and ω_v), seen through the true
    normal: the closure returns ``D(N'·h) G2(N'·ω_v, N'·ω_l) / (4 N'·ω_v)`` (its N'·ω_l cancelled), which is
    the radiance under a light of irradiance 1, so the BRDF about N is that over μ_l (zero where μ_l ≤ 0 or
    N'·ω_l ≤ 0); k = 0 is the GGX lobe about N.  Tilted away from the view (k > 0) its peak moves from the
    mirror direction towards the normal's side of it: at μ_v = cos 30° and k = 0.304 the lobe is centred on
    the half vector of ASTM E2194's aspecular 15° (45° light), and aspecular 75°, which shares that view
    cosine and so every table colour, is 45° from N' (a D ratio of 4 α⁴ / (1 + α²)², 3e-6 at α 0.03, where
    a GGX lobe about N gives at least 2.1e-3: :func:`ggx_route_floor`)."""
    nv, nl, nh = tilted_cosines(mu_v, mu_l, cos_h, cos_vl, k)
    mu_l = np.asarray(mu_l, float)
    ok = (mu_l > 0) & (nl > 0) & (nv > 0)
    f = ggx_lobe_height_correlated(nv, np.clip(nl, 1e-12, 1.0), nh, alpha) * np.clip(nl, 1e-12, 1.0) / np.clip(mu_l, 1e-12, None)
    return np.where(ok, f, 0.0)


def lobe_basis(mu_v, mu_l, cos_h, alphas, retro_alphas=(), cos_vl=None, distribution: str = "ggx",
               tilted=()) -> np.ndarray:
    """(P, 1 + K + R + T) the model's lobe shapes [1/sr] without colour: 1/π, the lobes of ``distribution``
    (:data:`flakedb.export.blender.GLOSSY_LOBES`: Cycles' Glossy BSDF with GGX or Beckmann, F = 1), the
    backscatter lobes of :func:`retro_lobe` and the tilted lobes of :func:`tilted_lobe` (``tilted``: (α, k)
    pairs; ``cos_vl`` = ω_v·ω_l needed when ``retro_alphas`` or ``tilted``)."""
    lobe = GLOSSY_LOBES[distribution]
    cols = [np.full(np.shape(mu_v), 1.0 / np.pi)]
    cols += [lobe(mu_v, mu_l, cos_h, a) for a in alphas]
    cols += [retro_lobe(mu_l, cos_vl, a) for a in retro_alphas]
    cols += [tilted_lobe(mu_v, mu_l, cos_h, cos_vl, a, k) for a, k in tilted]
    return np.stack(cols, axis=-1)


def lobe_albedos(mu_v, alphas, retro_alphas=(), distribution: str = "ggx", tilted=()) -> np.ndarray:
    """(1 + K + R + T, V) the directional albedo ∫ B μ_l dω_l of each column of :func:`lobe_basis` at the view
    cosines ``mu_v`` (V,): 1 for the Lambert term; for a lobe about the axis m (N, ω_v for a backscatter lobe,
    N' of :func:`tilted_cosines` for a tilted one) the half vector h is drawn from D_α(m·h)(m·h) (GGX's: tan²θ_h =
    α² u / (1 − u)) on :data:`N_ALBEDO_U` Gauss nodes in u × :data:`N_ALBEDO_PHI` midpoints in φ, ω_l the
    mirror of ω_v about h (dω_l = 4 (ω_v·h) dω_h), so that the narrowest lobe is resolved as well as the widest.
    Each is ≤ 1 (F = 1, a lobe of unit albedo at most)."""
    mu = np.clip(np.asarray(mu_v, float), 0.0, 1.0)
    x, wx = np.polynomial.legendre.leggauss(N_ALBEDO_U)
    u, wu = 0.5 * (x + 1.0), 0.5 * wx
    phi = (np.arange(N_ALBEDO_PHI) + 0.5) * 2.0 * np.pi / N_ALBEDO_PHI
    v = np.stack([np.sqrt(1.0 - mu * mu), np.zeros_like(mu), mu], -1)                      # (V, 3)
    lobe = GLOSSY_LOBES[distribution]
    cols = [(a, np.broadcast_to([0.0, 0.0, 1.0], v.shape), lambda m, ml, ch, cvl, a=a: lobe(m, ml, ch, a)) for a in alphas]
    cols += [(a, v, lambda m, ml, ch, cvl, a=a: retro_lobe(ml, cvl, a)) for a in retro_alphas]
    for a, k in tilted:
        nt = np.stack([-k * mu * v[:, 0], np.zeros_like(mu), np.ones_like(mu)], -1)   # N (1 + kμ²) − kμ ω_v
        nt /= np.linalg.norm(nt, axis=-1, keepdims=True)
        cols.append((a, nt, lambda m, ml, ch, cvl, a=a, k=k: tilted_lobe(m, ml, ch, cvl, a, k)))
    out = [np.ones(mu.shape)]
    for a, m, f in cols:
        t2 = a * a * u / (1.0 - u)
        ct = 1.0 / np.sqrt(1.0 + t2)
        st = np.sqrt(t2) * ct
        hl = np.stack([st[:, None] * np.cos(phi), st[:, None] * np.sin(phi), np.broadcast_to(ct[:, None], (u.size, phi.size))], -1)
        e1 = np.stack([m[:, 2], np.zeros_like(mu), -m[:, 0]], -1)                         # ⊥ m in the plane of N, ω_v
        h = (hl[None, ..., :1] * e1[:, None, None] + hl[None, ..., 1:2] * np.array([0.0, 1.0, 0.0])
             + hl[None, ..., 2:] * m[:, None, None])                                      # (V, U, Φ, 3)
        vh = np.einsum("vupi,vi->vup", h, v)
        wl = 2.0 * vh[..., None] * h - v[:, None, None]
        ml, cvl = wl[..., 2], np.einsum("vupi,vi->vup", wl, v)
        pdf = a * a / (np.pi * (ct * ct * (a * a - 1.0) + 1.0) ** 2) * ct                  # D(m·h)(m·h), (U,)
        ok = (vh > 0) & (ml > 0)
        val = f(np.broadcast_to(mu[:, None, None], ml.shape), np.where(ok, ml, 1.0), h[..., 2], cvl)
        g = np.where(ok, val * ml * 4.0 * vh, 0.0) / pdf[None, :, None]
        out.append(np.einsum("vup,u->v", g, wu) / N_ALBEDO_PHI)
    return np.stack(out)


def energy_capped(fit: CPAFit, albedos=None) -> CPAFit:
    """``fit`` with its table columns scaled down (per channel) where the model's directional albedo
    F_c(μ_v) + Σ_k C_k(μ_v) A_k(μ_v) (A_k :func:`lobe_albedos`, F_c the coat's Fresnel) would exceed 1 at a node
    or at :data:`N_ENERGY_SUB` − 1 points between two (the colours are linear between nodes): first each node on
    its own, then each interval's two columns together, in order (scaling a column only lowers its neighbours'
    intervals).  The least-squares fit has no energy constraint: a lobe narrower than the fit's samples can take
    a colour of several (an albedo of 4.8 for a coated near-mirror, measured).  ``albedos``: lobe_albedos at
    the points (precomputed)."""
    n, sub = fit.n_table, N_ENERGY_SUB
    mu = np.linspace(0.0, 1.0, (n - 1) * sub + 1)
    A = lobe_albedos(mu, fit.alphas, fit.retro_alphas, fit.distribution, fit.tilted) if albedos is None else albedos
    room = 1.0 - (fresnel_dielectric_real(mu, fit.coat_ior) if fit.coat_ior != 1.0 else 0.0 * mu)
    table = np.array(fit.table, float)
    S = np.einsum("rjc,rj->jc", table, A[:, ::sub])                                       # each node's albedo
    table *= np.where(S > room[::sub, None], room[::sub, None] / np.maximum(S, 1e-300), 1.0)[None]
    H = hat_weights(mu, n)
    for j in range(n - 1):
        q = slice(j * sub, (j + 1) * sub + 1)
        S = np.einsum("qj,rjc,rq->qc", H[q, j:j + 2], table[:, j:j + 2], A[:, q])
        ratio = np.max(np.where(room[q, None] > 0, S / np.maximum(room[q, None], 1e-300), 0.0), axis=0)
        table[:, j:j + 2] /= np.maximum(ratio, 1.0)
    return replace(fit, table=table)


def _half_cos(wv, wl):
    h = wv + wl
    return h[..., 2] / np.linalg.norm(h, axis=-1)


def evaluate_cpa(fit: CPAFit, mu_i, mu_o, phi_d) -> np.ndarray:
    """f (..., 3) [1/sr] of the model (no delta) at the file's coordinates (ω_i the light, ω_o, with
    ``mu_o < 0``, the view: :func:`flakedb.export.openpbr.file_directions`)."""
    wl, wv = file_directions(mu_i, mu_o, phi_d)
    return _eval_dirs(fit, wv, wl)


def _eval_dirs(fit: CPAFit, wv, wl):
    mu_v, mu_l = wv[..., 2], wl[..., 2]
    shape = mu_v.shape
    B = lobe_basis(mu_v.ravel(), mu_l.ravel(), _half_cos(wv, wl).ravel(), fit.alphas, fit.retro_alphas,
                   np.sum(wv * wl, axis=-1).ravel(), fit.distribution, fit.tilted)          # (P, 1+K+R+T)
    H = hat_weights(mu_v, fit.n_table)                                                        # (P, n)
    C = np.einsum("pj,kjc->pkc", H, fit.table)                                               # (P, K+1, 3)
    return np.einsum("pk,pkc->pc", B, C).reshape(shape + (3,))


def cpa_sun_image(fit: CPAFit, size: int = 32, direction=(0.0, 0.0, 1.0), irradiance: float = 1.0,
                  half_angle_deg: float = 2.0, extent: float = 1.05) -> np.ndarray:
    """(size, size, 3) image of the model on the unit sphere under a sun of ``irradiance`` and angular
    radius ``half_angle_deg`` (:func:`flakedb.export.blender.sun_disk`), at pixel centres, in the frame
    of :func:`flakedb.export.blender.render_cycles_sphere` (row 0 at the top): what the node group
    (:func:`flakedb.export.blender.cpa_material_script`) renders in Cycles, the coat's mirror aside
    (it reaches no pixel centre off the sun's highlight)."""
    N, on = sphere_normals(size, extent)
    ok = on & (N[..., 2] > 0)
    Nk = N[ok]
    # local frame per pixel: z = N, x along the view's tangent part
    v = np.array([0.0, 0.0, 1.0])
    out = np.zeros((len(Nk), 3))
    dirs, wts = sun_disk(direction, half_angle_deg)
    mu_v = Nk[:, 2]
    for l, wt in zip(dirs, wts):
        mu_l = Nk @ l
        h = (l + v) / np.linalg.norm(l + v)
        B = lobe_basis(mu_v, mu_l, Nk @ h, fit.alphas, fit.retro_alphas, np.full(mu_v.shape, l @ v), fit.distribution,
                       fit.tilted)
        C = np.einsum("pj,kjc->pkc", hat_weights(mu_v, fit.n_table), fit.table)
        f = np.einsum("pk,pkc->pc", B, C)
        out += np.where((mu_l > 0)[:, None], f * (wt * np.maximum(mu_l, 0.0) * irradiance)[:, None], 0.0)
    img = np.zeros((size, size, 3))
    img[ok] = out
    return img


def _sun_pixels(size, extent, direction, half_angle_deg):
    """Pixel normals on the sphere, and per sun-disk node (its direction, weight) the file coordinates
    (mu_i = light, mu_o = -view, phi_d) of every pixel: the frame of :func:`cpa_sun_image`."""
    N, on = sphere_normals(size, extent)
    ok = on & (N[..., 2] > 0)
    Nk = N[ok]
    mu_v = Nk[:, 2]
    tv = np.array([0.0, 0.0, 1.0]) - Nk * mu_v[:, None]
    nodes = []
    for l, wt in zip(*sun_disk(direction, half_angle_deg)):
        mu_l = Nk @ l
        tl = l - Nk * mu_l[:, None]
        den = np.linalg.norm(tv, axis=-1) * np.linalg.norm(tl, axis=-1)
        cos_dphi = np.where(den > 0, np.sum(tv * tl, axis=-1) / np.where(den > 0, den, 1.0), 1.0)
        nodes.append((mu_l, -mu_v, np.pi - np.arccos(np.clip(cos_dphi, -1.0, 1.0)), wt))
    return ok, nodes


def sun_image(f_of, size: int = 32, direction=(0.0, 0.0, 1.0), irradiance: float = 1.0, half_angle_deg: float = 2.0,
              extent: float = 1.05) -> np.ndarray:
    """(size, size, 3) image ``L = E Σ_k w_k f(ω_v, ω_k) μ_k`` over the sun disk's nodes
    (:func:`flakedb.export.blender.sun_disk`) at pixel centres, in the frame of
    :func:`flakedb.export.blender.render_cycles_sphere`, of ``f_of(mu_i, mu_o, phi_d)`` (..., 3) in
    the file's coordinates (light = ω_i): with :func:`flakedb.export.openpbr.exact_rgb` it is the
    exact paint's image, deterministic (flakedb's preview of the same scene without its Monte Carlo
    noise), the coat's delta aside; with :func:`evaluate_cpa` the model's (:func:`cpa_sun_image`)."""
    ok, nodes = _sun_pixels(size, extent, direction, half_angle_deg)
    out = np.zeros((int(ok.sum()), 3))
    for mu_l, mu_o, phi_d, wt in nodes:
        lit = mu_l > 0
        if np.any(lit):
            out[lit] += f_of(mu_l[lit], mu_o[lit], phi_d[lit]) * (wt * mu_l[lit] * irradiance)[:, None]
    img = np.zeros((size, size, 3))
    img[ok] = out
    return img


# --------------------------------------------------------------------------------------------
# The fit
# --------------------------------------------------------------------------------------------
def fit_samples(n_mu: int = N_MU_FIT, n_phi: int = N_PHI_FIT, n_view: int = 2 * N_TABLE):
    """(mu_i (light), mu_o (< 0, view), phi_d, weight) flat arrays of the hemisphere sample set
    (module docstring): ``n_view`` midpoints in μ_v (two per table interval, so that every table
    column is seen by data), Gauss-Legendre nodes in μ_l, midpoints in φ_d on (0, π); weights sum
    to ∫∫ dμ_i dμ_o dφ over φ in (0, 2π) = 2π."""
    x, w = np.polynomial.legendre.leggauss(n_mu)
    x, w = 0.5 * (x + 1), 0.5 * w
    v = (np.arange(n_view) + 0.5) / n_view
    phi = (np.arange(n_phi) + 0.5) * np.pi / n_phi
    MI, MO, PH = np.meshgrid(x, v, phi, indexing="ij")
    W = (w[:, None, None] * np.full(n_view, 1.0 / n_view)[None, :, None]) * np.full(n_phi, 2 * np.pi / n_phi)[None, None, :]
    return MI.ravel(), -MO.ravel(), PH.ravel(), W.ravel()


def _second_difference(n_table: int, n_rows: int) -> np.ndarray:
    d = np.zeros((n_table - 2, n_table))
    for j in range(n_table - 2):
        d[j, j:j + 3] = (1.0, -2.0, 1.0)
    return np.kron(np.eye(n_rows), d)


def _nnls_gram(G, b, n_table, n_rows, lam):
    """argmin_{c ≥ 0} c^T G c - 2 b^T c + lam |D c|² via the Cholesky factor of the regularised Gram."""
    D = _second_difference(n_table, n_rows)
    s = np.sqrt(np.mean(np.diag(G).reshape(n_rows, n_table), axis=1))      # each row's own scale
    s = np.repeat(s, n_table)
    A = G + lam * (s[:, None] * (D.T @ D) * s[None, :]) + 1e-12 * np.diag(s * s)
    R = np.linalg.cholesky(A).T                                   # A = R^T R
    z = np.linalg.solve(R.T, b)
    c, _ = nnls(R, z, maxiter=50 * len(G))
    return c


def fit_cpa(b, n_lobes: int = N_LOBES, n_table: int = N_TABLE, alpha_grid=ALPHA_GRID, source: str = "",
            minimax_passes: int = MINIMAX_PASSES, n_retro: int = N_RETRO, retro_grid=RETRO_ALPHA_GRID,
            max_subsets: int = MAX_SUBSETS, distribution: str = "ggx", n_tilt: int = 0,
            tilt_grid=None, e2539_share: float = E2539_SHARE) -> CPAFit:
    """Fit :class:`CPAFit` to the FourierBSDF ``b`` (module docstring) and measure its error; the K lobes
    of ``distribution`` (a key of :data:`flakedb.export.blender.GLOSSY_LOBES`), and ``n_tilt`` tilted lobes
    (:func:`tilted_lobe`) whose (α, k) are searched over ``tilt_grid`` (default :data:`TILT_GRID`; in order of
    residual, each with its backscatter α of least residual, until one meets the target, as the GGX subsets); ``e2539_share``: an E2539 geometry's weight relative to an E2194 one."""
    if distribution not in GLOSSY_LOBES:
        raise ValueError(f"fit_cpa: distribution {distribution!r} is not one of {sorted(GLOSSY_LOBES)}")
    if b.delta is not None:
        if b.delta.get("kind") != "fresnel":
            raise ValueError(f"fit_cpa: the file's delta kind {b.delta.get('kind')!r} is not carried "
                             f"(only 'fresnel', a smooth coat's mirror)")
        coat_ior = float(b.delta["eta"])
    else:
        coat_ior = 1.0                                    # a rough coat is in the table: the lobes fit it
    mi, mo, ph, wq = fit_samples()
    geoms = np.asarray(E2194_GEOMETRIES + E2539_EXTRA, float)
    gi, go, gp = geometry_directions(geoms)
    n45 = len(E2194_GEOMETRIES)
    y_h, y_g = exact_rgb(b, mi, mo, ph), exact_rgb(b, gi, go, gp)
    wl_nm = colour_grid(b)
    lab_g = channels_to_Lab(np.pi * y_g, "rgb", wl_nm)
    R_h = np.maximum(np.pi * y_h.mean(axis=1), R_FLOOR)
    W_h = wq * mi * np.abs(mo) * R_h ** (-PERCEPTUAL_EXPONENT)
    W_h = W_h / W_h.sum()
    R_g = np.maximum(np.pi * y_g.mean(axis=1), R_FLOOR)
    W_g0 = R_g ** (-4.0 / 3.0)
    W_g0 = GEOMETRY_WEIGHT * W_g0 / W_g0.sum()
    Y = np.r_[y_h, y_g]
    alpha_grid = tuple(float(a) for a in alpha_grid)
    retro_grid = tuple(float(a) for a in retro_grid) if n_retro else ()
    tilt_grid = tuple((float(a), float(k)) for a, k in (TILT_GRID if tilt_grid is None else tilt_grid)) if n_tilt else ()
    # The design is (lobe shape B_pa) x (interpolation weight H_j(μ_v,p)), and the samples share few
    # distinct μ_v: the Gram blocks Σ_p W B_pa B_pc H_j H_k = Σ_v H_vj H_vk M_v,ac with M_v = Σ_{p at v}
    # W B_a B_c, so each pass sums over the samples once and each subset is assembled from (U, K, K).
    MI, MO, PH = np.r_[mi, gi], np.r_[mo, go], np.r_[ph, gp]
    wl_dir, wv_dir = file_directions(MI, MO, PH)
    B_all = lobe_basis(wv_dir[..., 2], wl_dir[..., 2], _half_cos(wv_dir, wl_dir), alpha_grid, retro_grid,
                       np.sum(wv_dir * wl_dir, axis=-1), distribution, tilt_grid)                  # (P, 1 + A + R + T)
    A_all = lobe_albedos(np.linspace(0.0, 1.0, (n_table - 1) * N_ENERGY_SUB + 1), alpha_grid, retro_grid,
                         distribution, tilt_grid)                                        # energy_capped's, every column
    uniq, inv = np.unique(wv_dir[..., 2], return_inverse=True)
    H_u = hat_weights(uniq, n_table)                                                               # (U, n)
    S = csr_matrix((np.ones(len(inv)), (inv, np.arange(len(inv)))), shape=(len(uniq), len(inv)))   # sample -> μ_v
    n_rows = n_lobes + 1 + n_retro + (n_tilt if tilt_grid else 0)
    index = {("ggx", a): i + 1 for i, a in enumerate(alpha_grid)}
    index.update({("retro", a): i + 1 + len(alpha_grid) for i, a in enumerate(retro_grid)})
    index.update({("tilt", t): i + 1 + len(alpha_grid) + len(retro_grid) for i, t in enumerate(tilt_grid)})

    def moments(W):
        """M_v,ac, Σ_p W B_pa H_j y_p (as (U, K, 3) before H) and Σ W y² per channel."""
        WB = W[:, None] * B_all
        M = (S @ (WB[:, :, None] * B_all[:, None, :]).reshape(len(W), -1)).reshape(len(uniq), *B_all.shape[1:] * 2)
        BY = (S @ (WB[:, :, None] * Y[:, None, :]).reshape(len(W), -1)).reshape(len(uniq), B_all.shape[1], 3)
        return M, BY, np.sum(W[:, None] * Y * Y, axis=0)

    def solve_subset(lobes, mom):
        M, BY, yy = mom
        alphas, retro, tilt = lobes
        ks = [0] + [index["ggx", a] for a in alphas] + [index["retro", a] for a in retro] + [index["tilt", t] for t in tilt]
        n_rows = len(ks)
        G = np.einsum("vj,vac,vk->ajck", H_u, M[:, ks][:, :, ks], H_u).reshape(n_rows * n_table, n_rows * n_table)
        XYs = np.einsum("vj,vac->ajc", H_u, BY[:, ks]).reshape(n_rows * n_table, 3)
        c = np.stack([_nnls_gram(G, XYs[:, k], n_table, n_rows, SMOOTHNESS) for k in range(3)], axis=-1)
        r = float(np.sum(yy - 2.0 * np.sum(c * XYs, axis=0) + np.einsum("mk,mn,nk->k", c, G, c)))
        return c, r

    def passes(lobes, mom0):
        """MINIMAX_PASSES reweightings of the E2194 geometries for ``lobes``: ((E2194 worst, all worst), fit) of
        the best pass."""
        u = np.r_[np.ones(n45), np.full(len(geoms) - n45, e2539_share)]
        best = None
        for p in range(max(int(minimax_passes), 1)):
            mom = mom0 if p == 0 else moments(np.r_[W_h, W_g0 * u])
            c, _ = solve_subset(lobes, mom)
            fit = CPAFit(c.reshape(n_rows, n_table, 3), lobes[0], coat_ior, source, retro_alphas=lobes[1],
                         distribution=distribution, tilted=lobes[2])
            ks = [0] + [index["ggx", a] for a in lobes[0]] + [index["retro", a] for a in lobes[1]] + [index["tilt", t] for t in lobes[2]]
            fit = energy_capped(fit, A_all[ks])
            de = delta_E_2000(channels_to_Lab(np.pi * evaluate_cpa(fit, gi, go, gp), "rgb", wl_nm), lab_g)
            key = (float(de[:n45].max()), float(de.max()))
            if best is None or key < best[0]:
                best = (key, fit)
            u[:n45] = u[:n45] * (de[:n45] / max(de[:n45].max(), 1e-12)) ** 2 + 1e-3      # towards E2194's minimax
            u[:n45] = u[:n45] * n45 / u[:n45].sum()
        return best

    def minimax(ggx, mom0):
        """For the GGX subset, each choice of tilted lobes (none without ``n_tilt``) with the backscatter α of
        least residual, in order of residual: :func:`passes` until one meets E2194_TARGET, else the least
        E2194 worst."""
        choices = {}
        for r in itertools.combinations(retro_grid, n_retro):
            for t in itertools.combinations(tilt_grid, n_tilt if tilt_grid else 0):
                res = solve_subset((ggx, r, t), mom0)[1]
                if t not in choices or res < choices[t][0]:
                    choices[t] = (res, (ggx, r, t))
        best = None
        for _, lobes in sorted(choices.values(), key=lambda c: c[0]):
            cand = passes(lobes, mom0)
            if best is None or max(cand[0][0], E2194_TARGET) < max(best[0][0], E2194_TARGET):
                best = cand
            if best[0][0] <= E2194_TARGET:
                break
        return best

    # GGX subsets in order of their residual; the first whose minimax meets E2194_TARGET is kept (the
    # hemisphere's best among those that meet it), else the one with the least E2194 worst
    mom0 = moments(np.r_[W_h, W_g0 * np.r_[np.ones(n45), np.full(len(geoms) - n45, e2539_share)]])
    ranked = sorted(itertools.combinations(alpha_grid, n_lobes), key=lambda s: solve_subset((s, (), ()), mom0)[1])
    best = None
    for ggx in ranked[:max(int(max_subsets), 1)]:
        cand = minimax(ggx, mom0)
        if best is None or max(cand[0][0], E2194_TARGET) < max(best[0][0], E2194_TARGET):
            best = cand
        if best[0][0] <= E2194_TARGET:
            break
    fit = best[1]
    fit.error = cpa_error(b, fit)
    return fit


def fit_cpa_cycles(b, ggx_fit: CPAFit | None = None, **kw) -> CPAFit:
    """The fit for the Cycles / EEVEE node group: ``ggx_fit`` (:func:`fit_cpa`, GGX lobes: what MaterialX's
    ``generalized_schlick_bsdf`` can draw, its only distribution), or, where that misses
    :data:`E2194_TARGET`, the fit with Beckmann lobes (Cycles' Glossy BSDF offers the distribution) when its
    worst E2194 ΔE00 is lower.  A Beckmann lobe's tail falls as exp(-tan²θ_h / α²), GGX's as a power, which
    is what a bare Beckmann metal under the coat needs (docs/renderers.md, coated aluminium)."""
    if ggx_fit is None:
        ggx_fit = fit_cpa(b, **kw)
    if ggx_fit.error["worst_dE00_E2194"] <= E2194_TARGET:
        return ggx_fit
    beck = fit_cpa(b, distribution="beckmann", **kw)
    return beck if beck.error["worst_dE00_E2194"] < ggx_fit.error["worst_dE00_E2194"] else ggx_fit


def fit_cpa_materialx(b, ggx_fit: CPAFit | None = None, **kw) -> CPAFit:
    """The fit for the MaterialX graph: ``ggx_fit`` (:func:`fit_cpa`), or, where that misses
    :data:`E2194_TARGET`, the fit with one tilted lobe added (:func:`tilted_lobe`: a GGX
    ``generalized_schlick_bsdf`` whose normal the graph tilts from N away from ω_v; (α, k) from
    :data:`TILT_GRID`) when its worst E2194 ΔE00 is lower.  That fit gives the E2539 geometries no weight
    (``e2539_share`` 0): at the normal view (μ_v = 1, where N' = N) E2194's aspecular 45° and E2539's
    aspecular 15° share a table column with half vectors 22.5° and 7.5° from N, and no mix of GGX lobes about N
    makes the first less than (sin 7.5° / sin 22.5°)⁴ = 0.0135 of the second (a bare Beckmann metal's is
    smaller: coated-aluminium 0.0083), so weighting both leaves E2194's 45° above the target; E2194 is the
    issue's target (measured E2539 worst in docs/renderers.md).  A Beckmann lobe, Cycles' answer
    (:func:`fit_cpa_cycles`), is not among MaterialX 1.39's distributions."""
    if ggx_fit is None:
        ggx_fit = fit_cpa(b, **kw)
    if ggx_fit.error["worst_dE00_E2194"] <= E2194_TARGET:
        return ggx_fit
    tilted = fit_cpa(b, n_tilt=1, e2539_share=0.0, **kw)
    return tilted if tilted.error["worst_dE00_E2194"] < ggx_fit.error["worst_dE00_E2194"] else ggx_fit


def cpa_error(b, fit: CPAFit, n_mu: int = 16, n_phi: int = 24) -> dict:
    """ΔE00 at the E2194 and E2539 geometries and over a hemisphere grid (module docstring), and the
    cosine-weighted relative BSDF difference."""
    wl_nm = colour_grid(b)
    out = {"colour": "CIEDE2000, D65 / 2 deg, white-normalised linear sRGB"}
    for name, geoms in (("E2194", E2194_GEOMETRIES), ("E2539", E2194_GEOMETRIES + E2539_EXTRA)):
        g = np.asarray(geoms, float)
        gi, go, gp = geometry_directions(g)
        de = delta_E_2000(channels_to_Lab(np.pi * evaluate_cpa(fit, gi, go, gp), "rgb", wl_nm),
                          channels_to_Lab(np.pi * exact_rgb(b, gi, go, gp), "rgb", wl_nm))
        out[f"dE00_{name}"] = [{"illumination_deg": float(i), "aspecular_deg": float(a), "dE00": float(d)}
                               for (i, a), d in zip(g, de)]
        out[f"worst_dE00_{name}"] = float(np.max(de))
    # an independent grid (not the fit's nodes): midpoints in θ, so no node is shared
    th = (np.arange(n_mu) + 0.5) * (np.pi / 2) / n_mu
    phi = (np.arange(n_phi) + 0.5) * np.pi / n_phi
    TI, TO, PH = np.meshgrid(th, th, phi, indexing="ij")
    mi, mo, ph = np.cos(TI).ravel(), -np.cos(TO).ravel(), PH.ravel()
    f_fit, f_ex = evaluate_cpa(fit, mi, mo, ph), exact_rgb(b, mi, mo, ph)
    de = delta_E_2000(channels_to_Lab(np.pi * f_fit, "rgb", wl_nm), channels_to_Lab(np.pi * f_ex, "rgb", wl_nm))
    inner = (TI.ravel() <= math.radians(HEMISPHERE_STAT_DEG)) & (TO.ravel() <= math.radians(HEMISPHERE_STAT_DEG))
    for key, sel in (("hemisphere", np.ones_like(inner)), ("hemisphere_70deg", inner)):
        out[f"dE00_{key}"] = {"median": float(np.median(de[sel])), "p95": float(np.percentile(de[sel], 95)),
                              "max": float(np.max(de[sel]))}
    w = np.sin(TI).ravel() * np.sin(TO).ravel()                  # dμ = sin θ dθ on the midpoint grid
    out["cosine_weighted_difference"] = cosine_weighted_difference(f_fit, f_ex, mi, mo, w)
    return out


# --------------------------------------------------------------------------------------------
# The colour table as an image
# --------------------------------------------------------------------------------------------
def materialx_fit(fit: CPAFit) -> CPAFit:
    """The fit with the colours the MaterialX graph must carry (:func:`flakedb.export.materialx.cpa_mtlx_text`):
    MaterialX's GLSL ``generalized_schlick_bsdf`` multiplies its lobe by its energy compensation
    ``1 + F (1 - E_ss(μ_v, α)) / E_ss`` (Turquin 2019; absent from Cycles' Glossy BSDF and from this model), so
    lobe k's column j holds the F whose compensated value is the model's colour at μ_j
    (:func:`flakedb.export.materialx_glsl.compensated_lobe_colours`; a backscatter lobe's closure has the view
    direction for its normal, so its N·V is 1 at every column; a tilted lobe's is N'·V of :func:`tilted_cosines`
    at μ_j); the Lambert row is unchanged.  Exact at
    the table's nodes; between them the renderer interpolates F linearly (measured effect in docs/renderers.md).
    MaterialX's lobes are GGX only: a fit of another distribution is refused (ValueError)."""
    if fit.distribution != "ggx":
        raise ValueError(f"materialx_fit: the fit's lobes are {fit.distribution!r}; MaterialX 1.39's "
                         f"generalized_schlick_bsdf has GGX only: fit with distribution='ggx'")
    mu = np.linspace(0.0, 1.0, fit.n_table)
    table = fit.table.copy()
    for k, a in enumerate(fit.alphas, start=1):
        table[k] = compensated_lobe_colours(fit.table[k], mu, a)
    for k, a in enumerate(fit.retro_alphas, start=1 + len(fit.alphas)):   # normal = ω_v: its N·V is 1
        table[k] = compensated_lobe_colours(fit.table[k], np.ones_like(mu), a)
    for k, (a, tilt) in enumerate(fit.tilted, start=1 + len(fit.alphas) + len(fit.retro_alphas)):   # N'·V
        table[k] = compensated_lobe_colours(fit.table[k], tilted_cosines(mu, mu, mu, mu, tilt)[0], a)
    return replace(fit, table=table)


def table_image(fit: CPAFit) -> tuple:
    """(pixels (K + 1, n_table, 3) in [0, 1], row 0 = table row 0 = the image's **bottom** row as
    renderers index it; scale (K + 1,) per row): row k's colours are ``pixels[k] * scale[k]``, each row
    scaled to its largest value so that 16-bit storage (:func:`table_planes`) keeps 5 significant digits of
    every row."""
    scale = np.maximum(fit.table.reshape(fit.table.shape[0], -1).max(axis=1), 1e-12)
    return np.clip(fit.table / scale[:, None, None], 0.0, 1.0), scale


def png_bytes(values, bit_depth: int = 16) -> bytes:
    """An RGB PNG (ISO/IEC 15948: signature, IHDR, one zlib IDAT, IEND; filter 0 per row) of the integers
    ``values`` (H, W, 3) in [0, 2**bit_depth - 1] (``bit_depth`` 8 or 16), row 0 written **last** (the bottom
    row, as renderers index textures)."""
    if bit_depth not in (8, 16):
        raise ValueError(f"png_bytes: bit depth {bit_depth}, not 8 or 16")
    v = np.asarray(values)[::-1]
    h, w, _ = v.shape
    q = np.clip(v, 0, 2 ** bit_depth - 1).astype(">u2" if bit_depth == 16 else np.uint8)
    raw = b"".join(b"\x00" + row.tobytes() for row in q)

    def chunk(kind, data):
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF)

    return (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", w, h, bit_depth, 2, 0, 0, 0))
            + chunk(b"IDAT", zlib.compress(raw, 9)) + chunk(b"IEND", b""))


def png16_bytes(pixels) -> bytes:
    """A 16-bit RGB PNG (:func:`png_bytes`) of ``pixels`` (H, W, 3) in [0, 1], values ``round(65535 x)``."""
    return png_bytes(np.round(np.clip(np.asarray(pixels, float), 0.0, 1.0) * 65535.0).astype(np.int64), 16)


def read_png(data: bytes) -> tuple[np.ndarray, int]:
    """(integer values (H, W, 3), bit depth) of an 8- or 16-bit RGB PNG written by :func:`png_bytes`, row 0 =
    the bottom row.

    >>> v = np.array([[[0, 128, 255]], [[7, 9, 11]]])
    >>> back, depth = read_png(png_bytes(v, 8))
    >>> bool(np.array_equal(back, v)), depth
    (True, 8)
    """
    if data[:8] != b"\x89PNG\r\n\x1a\n":
        raise ValueError("not a PNG file")
    pos, idat, w, h, depth = 8, b"", 0, 0, 0
    while pos < len(data):
        n = struct.unpack(">I", data[pos:pos + 4])[0]
        kind, body = data[pos + 4:pos + 8], data[pos + 8:pos + 8 + n]
        if kind == b"IHDR":
            w, h, depth, ctype = struct.unpack(">IIBB", body[:10])
            if depth not in (8, 16) or ctype != 2:
                raise ValueError(f"PNG bit depth {depth} / colour type {ctype}: only 8- or 16-bit RGB is read")
        elif kind == b"IDAT":
            idat += body
        pos += 12 + n
    nb = depth // 8
    raw = np.frombuffer(zlib.decompress(idat), np.uint8).reshape(h, 1 + w * 3 * nb)
    if np.any(raw[:, 0] != 0):
        raise ValueError("PNG rows with a filter other than 0 are not read")
    q = np.frombuffer(raw[:, 1:].tobytes(), ">u2" if nb == 2 else np.uint8).reshape(h, w, 3)
    return q.astype(np.int64)[::-1], depth


def read_png16(data: bytes) -> np.ndarray:
    """(H, W, 3) float pixels of a 16-bit PNG written by :func:`png16_bytes`, row 0 = the bottom row: the round
    trip is exact to the 16-bit step.

    >>> px = np.array([[[0.0, 0.5, 1.0]], [[0.25, 0.75, 0.125]]])
    >>> bool(np.abs(read_png16(png16_bytes(px)) - px).max() <= 0.5 / 65535)
    True
    """
    q, depth = read_png(data)
    if depth != 16:
        raise ValueError(f"read_png16: the PNG is {depth}-bit")
    return q / 65535.0


def table_planes(pixels) -> np.ndarray:
    """(2 R, n, 3) uint8 of the table's pixels (R, n, 3) in [0, 1] (:func:`table_image`): rows 0 … R − 1 the
    high bytes of q = round(65535 p), rows R … 2R − 1 the low bytes (:data:`flakedb.export.materialx.PLANE_WEIGHTS`)."""
    q = np.round(np.clip(np.asarray(pixels, float), 0.0, 1.0) * 65535.0).astype(np.int64)
    return np.concatenate([q >> 8, q & 255]).astype(np.uint8)


def table_png_bytes(pixels) -> bytes:
    """``NAME.cpa.png``: an 8-bit RGB PNG of :func:`table_planes` of ``pixels`` (R, n, 3) in [0, 1]: 2 R rows."""
    return png_bytes(table_planes(pixels), 8)


def read_table_png(data: bytes) -> np.ndarray:
    """(R, n, 3) the 16-bit table pixels in [0, 1] of a PNG written by :func:`table_png_bytes`: exact to the
    16-bit step."""
    q, depth = read_png(data)
    if depth != 8 or q.shape[0] % 2:
        raise ValueError(f"read_table_png: a {depth}-bit PNG of {q.shape[0]} rows is not a table in two 8-bit planes")
    r = q.shape[0] // 2
    return (256 * q[:r] + q[r:]) / 65535.0


def write_table_png(path, fit: CPAFit) -> Path:
    """The colour table's normalised pixels (:func:`table_image`) as :func:`table_png_bytes` at ``path``."""
    path = Path(path)
    with atomic_path(path, suffix="") as tmp:
        Path(tmp).write_bytes(table_png_bytes(table_image(fit)[0]))
    return path


def quantised(fit: CPAFit) -> CPAFit:
    """The fit with its table as a renderer reads it back from ``NAME.cpa.png`` (16 bits in two 8-bit planes,
    :func:`table_planes`; pixels x scale)."""
    px, scale = table_image(fit)
    return replace(fit, table=np.round(px * 65535.0) / 65535.0 * scale[:, None, None])


# --------------------------------------------------------------------------------------------
# What a GGX route cannot reach
# --------------------------------------------------------------------------------------------
#: Half-vector angles (rad) of ASTM E2194's aspecular 15° and 75° (45° illumination; both seen at μ_v = cos 30°).
THETA_H_15, THETA_H_75 = math.radians(7.5), math.radians(37.5)
#: The least 75° / 15° ratio of a GGX lobe about N: D = α² / (π (α² cos²θ + sin²θ)²) gives
#: ((α² cos²θ_15 + sin²θ_15) / (α² cos²θ_75 + sin²θ_75))², increasing in α, so its infimum is the α → 0 limit
#: (sin 7.5° / sin 37.5°)⁴ = 2.11e-3 (G2 and 1 / (4 μ_v μ_l) are equal at both); the Lambert term gives 1 and the
#: backscatter lobe more than 1.
GGX_MIN_RATIO_75_15 = (math.sin(THETA_H_15) / math.sin(THETA_H_75)) ** 4


def ggx_route_floor(b, ratio: float = GGX_MIN_RATIO_75_15) -> float:
    """A lower bound on the worst ΔE00 (D65 / 2°, the file's linear sRGB) that the GGX route (every lobe GGX
    about N with colours indexed by μ_v, the Lambert term and the backscatter lobes; MaterialX's energy
    compensation is a factor of μ_v, the same at both) can reach at ASTM E2194's aspecular 15° and 75°, which
    share one table column: the route's 75° is at least ``ratio`` times its 15° in each channel
    (:data:`GGX_MIN_RATIO_75_15`), so the best is min over RGB m ≥ 0 at 15° of max(ΔE00(m, exact 15°),
    ΔE00(y, exact 75°)) with y = max(ratio m, exact 75°) per channel (the nearest allowed value channel by
    channel), searched by Nelder-Mead in log m from three starts.  It binds where the exact 75° is below
    ``ratio`` times its 15° (a bare Beckmann metal: coated-aluminium 7.2e-6 gives 5.56); elsewhere it is ~0."""
    g = np.asarray(E2194_GEOMETRIES, float)[[1, 4]]
    wl_nm = colour_grid(b)
    exact = np.pi * exact_rgb(b, *geometry_directions(g))
    lab_exact = channels_to_Lab(np.maximum(exact, 1e-9), "rgb", wl_nm)

    def worst(log_m):
        m = np.exp(log_m)
        lab = channels_to_Lab(np.maximum(np.stack([m, np.maximum(ratio * m, exact[1])]), 1e-9), "rgb", wl_nm)
        return float(delta_E_2000(lab, lab_exact).max())

    return min(minimize(worst, np.log(np.maximum(exact[0], 1e-9) * s), method="Nelder-Mead",
                        options={"xatol": 1e-7, "fatol": 1e-7, "maxiter": 4000}).fun for s in (0.5, 0.8, 1.0))
