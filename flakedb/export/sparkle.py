"""Sparkle in the angle-indexed material (:mod:`flakedb.export.cpa`): one GGX lobe of the fit, or a share
of it, realised as discrete glints, so that the smooth part carries what the glints do not and the
large-area mean is the smooth material's.

The layer (what the Blender node group and the MaterialX graph evaluate, term for term)
---------------------------------------------------------------------------------------
The surface is cut into square cells of side ``cell_um`` in world units (the UV map in metres; one
cell = one flake seen from above: at the loadings of effect paints the flakes one sees form a mosaic,
docs/texture.md).  Each cell draws three uniform numbers (u₁, u₂, u₃) from its integer cell coordinates,
holds a flake when u₃ < f (the occupancy), and draws a normal m in the tangent frame (T, B, N) from lobe k's GGX distribution weighted by
projected area, p(m) = D_k(m) (m·N) (Walter et al. 2007, eq. 35–36)::

    tan θ_m = α_k √(u₁ / (1 − u₁)),  φ_m = 2π u₂.

An occupied cell's BSDF is lobe k's colour share over the occupancy, β C_k(μ_v) / f, times a narrow GGX lobe (Cycles' Glossy BSDF,
α_g) about m, times the weight

    W(m, ω_v) = G2_k(ω_v, ω_l*) (m·ω_v) / ((m·N) (N·ω_v) G2_g(m·ω_v, m·ω_v)),  ω_l* = 2 (m·ω_v) m − ω_v,

and the smooth lobe k keeps (1 − β) C_k.  Why W: a cell of normal m under a directional light returns
the radiance E D_g(h; m) G2_g / (4 m·ω_v) (the Glossy BSDF with the shading normal m); averaged over
cells (m ~ p) and with α_g → 0 this is E D_k(h) (h·N) G2_g / (4 h·ω_v), while the smooth lobe gives
E D_k(h) G2_k / (4 N·ω_v).  The ratio depends on m and ω_v only once h = m, the one normal that lights
a narrow lobe, so W evaluated at the mirror direction ω_l* of the cell makes the cells' mean the
smooth lobe's, to O((α_g/α_k)² ln(α_k/α_g)) (the narrow lobe's width and its GGX tail).  The mean of the
whole material is then the smooth material's (measured in numpy and in Cycles: tests/export/test_sparkle.py,
docs/renderers.md).

Parameters from the texture model (:func:`flakedb.texture.model.sparkle_indices`)
-------------------------------------------------------------------------------
* α_g, a glint's width: the flake's diffraction.  A circular flake of diameter D (area A) sends a fraction
  A / λ'² of its reflected power per steradian along its mirror direction (the Airy pattern's peak; λ' = λ/η
  in the binder); per unit half-vector solid angle that is 4 A / λ'² (dω_o = 4 cos θ_d dω_h), and mapped to
  air (half-vector slopes × η, paraxial: solid angles × η²) 4 A / λ².  The GGX lobe of the same peak,
  D(0) = 1 / (π α_g²), has ``α_g = λ / (π D)`` (λ in air: 555 nm,
  :data:`flakedb.texture.instruments.DIFFRACTION_WAVELENGTH_NM`; D the median diameter): 0.011 for 16 µm
  flakes.  The source's size is the renderer's light.
* the lobe k: the fitted lobe whose α is nearest the air image of the flake spread, η α_flake (a binder
  slope s is seen in air as η s for small tilts, docs/texture.md §3.1), among the lobes with colour at
  normal view (a fitted lobe can be black there, and then holds no glint to split off).
* the share β: the model's ``flake_luminance_factor`` (the flakes' single mirror reflections, the part
  of the BSDF the glints are) over lobe k's luminance factor π C_k,Y L_k at the reference geometry, at
  most 1: the glints carry the flakes' single reflection, the rest of lobe k stays smooth.
* the cell size: the one free number, chosen so that the layer's expected count of glints above the
  model's fixed luminance threshold (``glint_threshold_luminance_factor``) is the model's
  ``glints_per_mm2_above_threshold`` at the reference geometry (light polar angle, view along the
  normal, source half-angle: :func:`layer_glints_per_mm2`).  Flakes that sparkle but never reach the fixed
  threshold (interference pearls, R 0.1–0.4, whose aligned peak is below half an R = 1 flake's) are
  calibrated the same way on the model's kind-relative count ``glints_per_mm2`` above half their own
  aligned median-diameter flake's ``peak_luminance_factor`` (``reference["threshold"]``: "fixed" or
  "relative"; the model counts each diameter against its own peak, the layer against the median's).  Elsewhere the layer predicts its own count
  from its own normals and widths; the tests compare it with the model at other lights and sources.
* the occupancy f = β Y(C_k) / Y_flake (at most 1), Y_flake = R(c) T_in T_out of an aligned surface flake:
  an occupied cell is as bright as a flake, so the glints reach the model's threshold as flakes do.

All vectors are in the tangent frame (N = +z); every function is vectorised over leading axes.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import numpy as np

from flakedb.export.blender import ggx_lobe_height_correlated, smith_lambda, sun_disk
from flakedb.paint.texture_inputs import texture_stack
from flakedb.texture.instruments import DIFFRACTION_WAVELENGTH_NM, Observer
from flakedb.texture.model import GLINT_FRACTION, directional_geometry, sparkle_indices

#: Rec. 709 / sRGB luminance weights of linear RGB (the cpa table's channels).
Y_WEIGHTS = np.array([0.2126, 0.7152, 0.0722])
#: Half-width of the normal grid of :func:`glint_fraction`, in units of (source half-angle / 2 + α_g): the
#: glinting region is inside it (the narrow lobe falls as (α_g/θ)⁴ beyond α_g).
GRID_REACH = 4.0
#: Grid points per side of :func:`glint_fraction` and sun rings × azimuths (convergence in the tests).
GRID_N = 161
SUN_RINGS, SUN_AZIMUTHS = 6, 16


@dataclass(frozen=True)
class SparkleLayer:
    """The glint layer of a cpa material (module docstring): ``lobe`` (1..K) the fitted lobe it realises,
    ``share`` β of that lobe's colour moved into the glints, ``cell_um`` the side of a cell (µm, world),
    ``lobe_alpha`` α_k and ``glint_alpha`` α_g (GGX, air), ``occupancy`` f the fraction of cells that hold
    a flake (the others hold no glint; a flake's colour is divided by f), ``reference`` the texture model's
    numbers and geometry the layer was parameterised from."""

    lobe: int
    share: float
    cell_um: float
    lobe_alpha: float
    glint_alpha: float
    occupancy: float
    reference: dict

    @property
    def cells_per_mm2(self) -> float:
        return 1e6 / self.cell_um ** 2

    def to_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, d) -> SparkleLayer:
        return cls(int(d["lobe"]), float(d["share"]), float(d["cell_um"]), float(d["lobe_alpha"]),
                   float(d["glint_alpha"]), float(d["occupancy"]), dict(d.get("reference", {})))


def glint_alpha(diameter_um: float, wavelength_nm: float = DIFFRACTION_WAVELENGTH_NM) -> float:
    """GGX α (air) of one flake's glint: α_g = λ / (π D), the lobe whose peak density equals the flake's
    Airy peak (module docstring).  A 16 µm flake at 550 nm, and its lobe's peak D(0) = 1/(π α²):

    >>> a = glint_alpha(16.0, 550.0)
    >>> round(a, 5), bool(np.isclose(float(ggx_D(1.0, a)), 1.0 / (np.pi * a * a)))
    (0.01094, True)
    """
    return float(wavelength_nm) * 1e-3 / (math.pi * float(diameter_um))


def ggx_D(cos_m, alpha):
    """GGX normal distribution D(m) [1/sr] at cos θ_m (Walter et al. 2007, eq. 33)."""
    a2 = float(alpha) ** 2
    c2 = np.clip(cos_m, 0.0, 1.0) ** 2
    return np.where(np.asarray(cos_m) > 0, a2 / (np.pi * (c2 * (a2 - 1.0) + 1.0) ** 2), 0.0)


def sample_normals(u1, u2, alpha):
    """Normals (..., 3) of GGX α with density D(m) (m·N) from uniform ``u1``, ``u2`` in [0, 1) (the cells'
    random numbers; module docstring)."""
    u1 = np.asarray(u1, float)
    t = float(alpha) * np.sqrt(u1 / (1.0 - u1))
    c = 1.0 / np.sqrt(1.0 + t * t)
    s = t * c
    p = 2.0 * np.pi * np.asarray(u2, float)
    return np.stack([s * np.cos(p), s * np.sin(p), c], axis=-1)


def _dot(a, b):
    return np.sum(a * b, axis=-1)


def cell_weight(m, v, lobe_alpha: float, glint_alpha_: float):
    """W(m, ω_v) of the module docstring (0 where the mirror direction is below the surface or m faces
    away from the view)."""
    mv = _dot(m, v)
    mn = m[..., 2]
    nv = v[..., 2] if np.ndim(v) > 1 else v[2]
    mu_l = 2.0 * mv * mn - nv
    ok = (mv > 0) & (mu_l > 0) & (mn > 0)
    a2k, a2g = float(lobe_alpha) ** 2, float(glint_alpha_) ** 2
    g2k = 1.0 / (1.0 + smith_lambda(a2k, nv) + smith_lambda(a2k, np.where(ok, mu_l, 1.0)))
    g2g = 1.0 / (1.0 + 2.0 * smith_lambda(a2g, np.where(ok, mv, 1.0)))
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(ok, g2k * mv / (np.maximum(mn, 1e-12) * nv * g2g), 0.0)


def glint_radiance(m, v, light_dir, half_angle_deg: float, glint_alpha_: float):
    """L / E of a cell of normal m (unit colour, W = 1) under a sun of irradiance E (normal to its beam)
    and angular radius ``half_angle_deg`` about ``light_dir``: Σ over the sun's disk of
    D_g(h; m) G2_g / (4 m·ω_v) (Cycles' Glossy BSDF with the shading normal m times m·ω_l;
    :func:`flakedb.export.blender.sun_disk`'s quadrature)."""
    dirs, wts = sun_disk(light_dir, half_angle_deg, SUN_RINGS, SUN_AZIMUTHS)
    a2 = float(glint_alpha_) ** 2
    mv = _dot(m, v)[..., None]
    h = dirs + np.asarray(v, float)
    h = h / np.linalg.norm(h, axis=-1, keepdims=True)
    mh = np.einsum("...c,kc->...k", m, h)
    ml = np.einsum("...c,kc->...k", m, dirs)
    D = ggx_D(mh, glint_alpha_)
    G2 = 1.0 / (1.0 + smith_lambda(a2, np.clip(mv, 1e-12, 1)) + smith_lambda(a2, np.clip(ml, 1e-12, 1)))
    # sun_disk's weights multiply f (m·ω) = D G2 / (4 m·ω_v) (the shading normal's cosine cancels):
    f_cos = np.where((ml > 0) & (mv > 0) & (dirs[:, 2] > 0), D * G2 / (4.0 * np.clip(mv, 1e-12, 1)), 0.0)
    return np.einsum("...k,k->...", f_cos, wts)


def layer_luminance_factor(m, v, light_dir, half_angle_deg: float, layer: SparkleLayer, colour_Y: float):
    """Luminance factor π L_Y / (E μ_l) of occupied cells of normal m (any leading shape): the glint's share
    of lobe k of luminance ``colour_Y`` (= Y of C_k(μ_v)) over the occupancy, times W and :func:`glint_radiance`."""
    d = np.asarray(light_dir, float)
    d = d / np.linalg.norm(d)
    w = cell_weight(m, np.asarray(v, float), layer.lobe_alpha, layer.glint_alpha)
    return np.pi * layer.share / layer.occupancy * colour_Y * w * glint_radiance(m, v, d, half_angle_deg, layer.glint_alpha) / d[2]


def _frame(h):
    a = np.cross(h, [1.0, 0.0, 0.0] if abs(h[0]) < 0.9 else [0.0, 1.0, 0.0])
    a /= np.linalg.norm(a)
    return a, np.cross(h, a)


def glint_fraction(layer: SparkleLayer, colour_Y: float, light_deg: float, half_angle_deg: float,
                   threshold: float, n: int = GRID_N) -> float:
    """Probability that an occupied cell's luminance factor is ≥ ``threshold`` for a view along the normal and a sun
    at ``light_deg`` (in the x–z plane) of angular radius ``half_angle_deg``: ∫ p(m) [β(m) ≥ threshold] dΩ_m
    on an n × n grid of normals m = normalize(h₀ + a e₁ + b e₂) about the mirror normal h₀ (dΩ = da db /
    (1 + a² + b²)^{3/2})."""
    v = np.array([0.0, 0.0, 1.0])
    t = math.radians(light_deg)
    ld = np.array([math.sin(t), 0.0, math.cos(t)])
    h0 = (ld + v) / np.linalg.norm(ld + v)
    e1, e2 = _frame(h0)
    r = GRID_REACH * (0.5 * math.radians(half_angle_deg) + layer.glint_alpha)
    x = (np.arange(n) + 0.5) / n * 2.0 * r - r
    A, B = np.meshgrid(x, x, indexing="ij")
    q = h0 + A[..., None] * e1 + B[..., None] * e2
    m = q / np.linalg.norm(q, axis=-1, keepdims=True)
    dA = (2.0 * r / n) ** 2 / (1.0 + A * A + B * B) ** 1.5
    p = ggx_D(m[..., 2], layer.lobe_alpha) * m[..., 2]
    beta = layer_luminance_factor(m, v, ld, half_angle_deg, layer, colour_Y)
    return float(np.sum(p * dA * (beta >= threshold)))


def layer_glints_per_mm2(layer: SparkleLayer, colour_Y: float, light_deg: float, half_angle_deg: float,
                         threshold: float) -> float:
    """Expected cells per mm² at or above ``threshold`` (luminance factor): cells per mm² × occupancy ×
    :func:`glint_fraction`."""
    return layer.cells_per_mm2 * layer.occupancy * glint_fraction(layer, colour_Y, light_deg, half_angle_deg, threshold)


def lobe_luminance_factor(colour_Y: float, lobe_alpha: float, light_deg: float) -> float:
    """π C_Y L_k of a fitted GGX lobe (:func:`flakedb.export.blender.ggx_lobe_height_correlated`) for a view
    along the normal and a directional light at ``light_deg``."""
    t = math.radians(light_deg)
    return float(np.pi * colour_Y * ggx_lobe_height_correlated(1.0, math.cos(t), math.cos(0.5 * t), lobe_alpha))


def design_layer(table, alphas, *, eta: float, flake_alpha: float, diameter_um: float, flake_Y: float,
                 model_row: dict, light_deg: float, half_angle_deg: float) -> SparkleLayer:
    """The layer of a cpa fit (``table`` (K + 1, n, 3), ``alphas``) parameterised from the texture model
    (module docstring): ``model_row`` a :func:`flakedb.texture.model.sparkle_indices` row for a view along
    the normal and a source of ``half_angle_deg`` at ``light_deg`` (the reference geometry), ``eta`` the
    coat's index, ``flake_alpha`` and ``diameter_um`` the flakes' spread and median diameter, ``flake_Y`` the
    luminance of an aligned surface flake's mirror reflection through the coat (R(c) T_in T_out), which
    sets the occupancy f = β Y(C_k) / flake_Y (at most 1): an occupied cell is as bright as that flake.  Raises
    ValueError (with the numbers) when the model predicts no glints there or the layer's brightest cell
    cannot reach the model's threshold."""
    count = float(model_row.get("glints_per_mm2_above_threshold", 0.0))
    threshold = float(model_row.get("glint_threshold_luminance_factor", 0.0))
    basis = "fixed"
    if model_row.get("sparkle") and count <= 0.0 and model_row.get("glints_per_mm2", 0.0) > 0.0:
        # flakes that sparkle but never reach the fixed threshold (a pearl's R of 0.1-0.4 against the R = 1 flake
        # the threshold is half of): the model's own count, flakes at least GLINT_FRACTION as bright as an aligned
        # surface flake of their kind, with that kind's threshold (the median diameter's peak; module docstring)
        count = float(model_row["glints_per_mm2"])
        threshold = GLINT_FRACTION * float(model_row["peak_luminance_factor"])
        basis = "relative"
    if not model_row.get("sparkle") or count <= 0.0:
        raise ValueError(f"the texture model predicts no glints above its threshold at light {light_deg:g}° "
                         f"({model_row.get('no_sparkle_reason') or 'count 0'}): no sparkle layer to build")
    alphas = [float(a) for a in alphas]
    target = float(eta) * float(flake_alpha)
    Y = np.asarray(table, float)[1:, -1] @ Y_WEIGHTS                         # each lobe's C_k at μ_v = 1 (view along N)
    # the nearest lobe in α that carries colour along the view (a fit may leave a lobe black there: no glints)
    lit = [j for j in range(len(alphas)) if Y[j] > 0.0] or list(range(len(alphas)))
    k = 1 + min(lit, key=lambda j: abs(math.log(alphas[j] / target)))
    colour_Y = float(Y[k - 1])
    lobe_lf = lobe_luminance_factor(colour_Y, alphas[k - 1], light_deg)
    share = float(min(1.0, model_row["flake_luminance_factor"] / lobe_lf)) if lobe_lf > 0 else 0.0
    ag = glint_alpha(diameter_um)
    occ = float(min(1.0, share * colour_Y / float(flake_Y))) if share > 0 else 1.0
    ref = {"light_deg": float(light_deg), "view_deg": 0.0, "source_half_angle_deg": float(half_angle_deg),
           "glints_per_mm2_above_threshold": count, "glint_threshold_luminance_factor": threshold,
           "threshold": basis,
           "flake_luminance_factor": float(model_row["flake_luminance_factor"]),
           "lobe_luminance_factor": lobe_lf, "diameter_um": float(diameter_um), "flake_alpha": float(flake_alpha),
           "flake_Y": float(flake_Y), "eta": float(eta)}
    unit = SparkleLayer(k, share, 1e3, alphas[k - 1], ag, occ, ref)       # 1 cell per mm²
    frac = glint_fraction(unit, colour_Y, light_deg, half_angle_deg, ref["glint_threshold_luminance_factor"])
    if frac <= 0.0:
        peak = float(layer_luminance_factor(np.array([0.0, 0.0, 1.0]) if light_deg == 0 else
                                            _mirror_normal(light_deg), np.array([0.0, 0.0, 1.0]),
                                            _light(light_deg), half_angle_deg, unit, colour_Y))
        raise ValueError(f"the glint layer's brightest cell (luminance factor {peak:.4g}: lobe {k}'s share "
                         f"{share:.3g} of Y {colour_Y:.4g}, α_g {ag:.4g}) cannot reach the texture model's threshold "
                         f"{ref['glint_threshold_luminance_factor']:.4g} at light {light_deg:g}°")
    cells = ref["glints_per_mm2_above_threshold"] / (frac * occ)
    return SparkleLayer(k, share, 1e3 / math.sqrt(cells), alphas[k - 1], ag, occ, ref)


def _light(light_deg):
    t = math.radians(light_deg)
    return np.array([math.sin(t), 0.0, math.cos(t)])


def _mirror_normal(light_deg):
    h = _light(light_deg) + np.array([0.0, 0.0, 1.0])
    return h / np.linalg.norm(h)


def node_inputs(layer: SparkleLayer, metres_per_uv: float = 1.0, uv_map: str = "") -> dict:
    """The Blender node group's sparkle inputs (:func:`flakedb.export.blender.cpa_inputs`): the layer's numbers
    and ``cells_per_uv`` = cells per UV unit for a UV map of ``metres_per_uv`` metres per unit (the
    geometry's UVs must be proportional to its surface lengths, in one known unit), ``uv_map`` its name
    ("" = the active one; its tangents give the cells' frame)."""
    return {"lobe": int(layer.lobe), "share": float(layer.share), "occupancy": float(layer.occupancy),
            "lobe_alpha": float(layer.lobe_alpha), "glint_alpha": float(layer.glint_alpha),
            "cells_per_uv": float(metres_per_uv) / (float(layer.cell_um) * 1e-6), "uv_map": str(uv_map)}


#: The reference geometry's defaults (:func:`design_from_recipe`): light polar angle (°), view along the normal,
#: and a source of 10° angular radius (a softbox: the layer's count is calibrated where many flakes glint;
#: the sun's 0.27° gives 1–2 glints per mm² on metallic silver, docs/renderers.md).
REFERENCE_LIGHT_DEG, REFERENCE_SOURCE_DEG = 20.0, 10.0
#: The model's observer for the reference (a pinhole camera: the smallest aperture the model takes; the
#: fixed-threshold count does not depend on the spot).
REFERENCE_APERTURE_RAD, REFERENCE_SPOT_UM = 1e-4, 10.0


def design_from_recipe(table, alphas, recipe, light_deg: float = REFERENCE_LIGHT_DEG,
                       half_angle_deg: float = REFERENCE_SOURCE_DEG) -> SparkleLayer:
    """:func:`design_layer` for a cpa fit of ``recipe``'s paint: the texture model's inputs
    (:func:`flakedb.paint.texture_inputs.texture_stack`), its glint row at the reference geometry
    (:func:`flakedb.texture.model.sparkle_indices`), the flake species with the most flakes per mm² for the
    diameter, spread and the aligned flake's luminance R(c) T_in T_out."""
    stack, _ = texture_stack(recipe)
    if not stack.flakes:
        raise ValueError(f"recipe {recipe.name!r} has no flakes the texture model can use: no sparkle layer")
    obs = Observer("flakedb-export-sparkle", REFERENCE_SPOT_UM, REFERENCE_APERTURE_RAD, float(half_angle_deg),
                   light_deg=(float(light_deg),), view_deg=0.0)
    row = sparkle_indices(stack, obs, float(light_deg))
    f = max(stack.flakes, key=lambda fl: fl.areal_density_per_um2)
    g = directional_geometry(stack.eta, light_deg, 0.0, half_angle_deg, REFERENCE_APERTURE_RAD)
    flake_Y = float(np.asarray(stack.y_weights, float) @ f.reflectance(np.array([g.c]))[:, 0]) * g.t_in * g.t_out
    return design_layer(table, alphas, eta=stack.eta, flake_alpha=f.alpha, diameter_um=f.diameter_median_um,
                        flake_Y=flake_Y, model_row=row, light_deg=light_deg, half_angle_deg=half_angle_deg)
