"""The OpenPBR fit's accuracy on catalogue paints and the OpenPBR pieces it evaluates
(flakedb.export.openpbr).

Guards against: a fit whose worst ΔE00 at the ASTM E2194 geometries exceeds the issue-23 goal (≤ 2)
for the solid catalogue paint, or that silently starts meeting it for metallic silver (strict xfail:
docs/renderers.md then states a stale number); a metal Fresnel that is not OpenPBR's F82-tint
formula; a diffuse base that is not albedo-scaled under the dielectric lobe (energy above 1).
"""

from pathlib import Path

import numpy as np
import pytest

import flakedb
from flakedb.bsdf import open_bsdf
from flakedb.compose.orchestrate import compose
from flakedb.export import openpbr as op
from flakedb.paint.recipe import load_recipe

RECIPES = Path(flakedb.__file__).parent / "catalog" / "recipes"
#: The issue-23 goal for metallic and solid paints: worst ΔE00 at the E2194 geometries.
GOAL_DE00 = 2.0


def composed_fit(name, tmp_path):
    """Compose the catalogue recipe ``name`` at its own settings and fit it (what
    ``flakedb export-openpbr`` does)."""
    table = compose(load_recipe(RECIPES / f"{name}.yaml"), tmp_path).table
    b = open_bsdf(tmp_path / f"{name}.bsdf")
    assert b.delta is not None and table is not None          # smooth clear coat: the delta is carried exactly
    return op.fit_openpbr(b)


@pytest.mark.slow
def test_solid_paint_meets_the_goal(tmp_path):
    """Cadmium yellow (a solid paint): worst ΔE00 ≤ 2 at the six E2194 geometries (measured 1.48;
    the plain least squares, ``minimax_passes=1``, reaches 2.06 and fails this bound)."""
    fit = composed_fit("particle-cadmium-yellow", tmp_path)
    assert fit.error["worst_dE00_E2194"] <= GOAL_DE00, fit.error["dE00_E2194"]


@pytest.mark.slow
@pytest.mark.xfail(strict=True, reason="metallic silver: one GGX lobe (what OpenPBR's metal has) cannot follow the "
                   "Beckmann flake lobe seen through the coat (flat top, fast fall); measured 7.3, docs/renderers.md")
def test_metallic_paint_meets_the_goal(tmp_path):
    fit = composed_fit("metallic-silver", tmp_path)
    assert fit.error["worst_dE00_E2194"] <= GOAL_DE00, fit.error["dE00_E2194"]


def test_metal_fresnel_is_openpbr_f82():
    """OpenPBR 1.1, Metal section: F82 = F_Schlick(μ) − μ(1−μ)^6 / (μ̄(1−μ̄)^6) · (1 − s) F_Schlick(μ̄),
    μ̄ = 1/7, written out here independently; equal to rounding (a few ulp of 1)."""
    rng = np.random.default_rng(7)
    mu = rng.uniform(0, 1, 200)
    c, s = rng.uniform(0, 1, (2, 200))
    def schlick(m):
        return c + (1 - c) * (1 - m) ** 5

    mb = 1 / 7
    want = schlick(mu) - mu * (1 - mu) ** 6 / (mb * (1 - mb) ** 6) * (1 - s) * schlick(mb)
    P, Q, K = op.metal_f82_terms(mu)
    np.testing.assert_allclose(c * P + Q + s * K * (c * (1 - op.F82_Q) + op.F82_Q), want, rtol=0, atol=1e-14)
    # and the model evaluates it: a pure metal without coat, lobe factor divided out
    fit = op.OpenPBRFit((0.9, 0.6, 0.3), 1.0, 0.5, 1.0, 0.0, specular_color=(0.2, 0.5, 1.0))
    wi, wo = op.file_directions(np.array([0.3]), np.array([-0.8]), np.array([0.4]))
    lobe, cd = op.ggx_lobe(wi, wo, 0.25)
    P, Q, K = op.metal_f82_terms(cd)
    sc, cc = np.array(fit.specular_color), np.array(fit.base_color)
    f82 = cc * P[:, None] + Q[:, None] + sc * K[:, None] * (cc * (1 - op.F82_Q) + op.F82_Q)
    np.testing.assert_allclose(op.evaluate(fit, np.array([0.3]), np.array([-0.8]), np.array([0.4])),
                               f82 * lobe[:, None], rtol=1e-12)


def test_diffuse_under_the_lobe_is_albedo_scaled():
    """A white dielectric base (c = 1, s = 1, no metal, no coat): the reciprocal albedo scaling
    gives the closed-form albedo E(μ) + (1 − E(μ))(1 − E_avg), E_avg = 2 ∫ E μ dμ (≤ 1: energy);
    without the scaling it would be E(μ) + 1.  Quadrature: fit_albedo's 48 x 96 nodes and E_avg's
    64 Gauss nodes of a smooth function; tolerance 2e-3 ≫ the tabulation of E on 33 cosines
    (linear interpolation, measured < 5e-4)."""
    r, n_s = 0.6, 3.0
    fit = op.OpenPBRFit((1.0, 1.0, 1.0), 0.0, r, 1.0, 0.0, specular_color=(1.0, 1.0, 1.0), specular_ior_relative=n_s)
    x, w = np.polynomial.legendre.leggauss(64)
    x, w = 0.5 * (x + 1), 0.5 * w
    e_avg = 2 * np.sum(w * x * op.specular_albedo(x, r ** 2, n_s))
    for mu in (1.0, 0.6, 0.2):
        e = op.specular_albedo(np.array([mu]), r ** 2, n_s)[0]
        np.testing.assert_allclose(op.fit_albedo(fit, mu), e + (1 - e) * (1 - e_avg), atol=2e-3)
        assert np.all(op.fit_albedo(fit, mu) <= 1.0)
