"""Accuracy in the user's units (issue 26 item 3): ``resolution: {colour_error: ΔE00}`` chooses n from the
measured ΔE00(n, 2n) envelopes (flakedb/solve/resolution.py, docs/resolution.md "colour_error"), and compose
states the estimated ΔE00 of its own discretisation from a second solve at n/2 or 3n/4."""

from pathlib import Path

import numpy as np
import pytest
import yaml

from flakedb.colour.colorimetry import delta_E_2000
from flakedb.compose.orchestrate import compose
from flakedb.solve.resolution import (
    DISCRETISATION_ORDER,
    SECOND_SOLVE_HALF_FROM,
    second_solve_n,
    AUTO_COLOUR_MAX_N,
    AUTO_TARGETS,
    FLAKE_COLOUR_ERROR,
    METAL_COLOUR_ERROR,
    METAL_LOBE_ERROR,
    auto_resolution,
)
from flakedb.paint.recipe import RecipeError, load_recipe, parse_recipe, repo_root

RECIPES = repo_root() / "catalog" / "recipes"


def _with(path, resolution, rgb=False):
    d = yaml.safe_load((RECIPES / path).read_text(encoding="utf-8"))
    d["resolution"] = resolution
    if rgb:  # the paper's RGB mode: 3 channels instead of 41 bands, the same discretisation
        d["spectral"] = {"mode": "rgb"}
    return parse_recipe(yaml.safe_dump(d))


def _labs(report):
    return np.array([[g["L"], g["a"], g["b"]] for g in report["geometries"]])


def test_colour_error_takes_the_measured_envelopes():
    """A metal base takes the smallest measured n whose ΔE00 against the converged answer meets the target;
    flakes h·α_f (ΔE00(n, 2n)); the
    default auto carries colour_error 0.1 (AUTO_TARGETS) and a recipe's own target replaces it; an
    unreachable target is refused naming the measurement."""
    n0, why0 = auto_resolution(load_recipe(RECIPES / "coated-aluminium.yaml"))
    n_default = next(x for x, e in METAL_COLOUR_ERROR if e <= AUTO_TARGETS["colour_error"])
    assert n0 == n_default == 176 and "colour_error ≤ 0.1" in why0 and "converged" in why0
    target = 0.2
    n, why = auto_resolution(_with("coated-aluminium.yaml", {"colour_error": target}))
    n_table = next(x for x, e in METAL_COLOUR_ERROR if e <= target)
    n_lobe = next(x for x, e in METAL_LOBE_ERROR if e <= AUTO_TARGETS["lobe_error"])
    assert n == max(n_lobe, n_table) and "colour_error ≤ 0.2" in why and n < n0
    n, why = auto_resolution(_with("metallic-silver.yaml", {"colour_error": 0.1}))
    x = next(x for x, e in FLAKE_COLOUR_ERROR if e <= 0.1)
    assert n >= 2 * int(np.ceil(x / 0.2 - 1e-9)) and "flakes α = 0.2" in why
    assert auto_resolution(load_recipe(RECIPES / "metallic-silver.yaml"))[0] == n
    assert auto_resolution(_with("coated-aluminium.yaml", {"colour_error": 0.05}))[0] == 256  # 0.038 against the limit
    with pytest.raises(RecipeError, match=r"colour_error 0.05 for this stack is not reachable: the smallest "
                                          r"measured ΔE00 is 0.053"):
        auto_resolution(_with("particle-titanium-white.yaml", {"colour_error": 0.05}))


def test_default_colour_target_is_bounded_in_cost():
    """Below the measured metal roughness the colour rule scales n as 0.1/α: the default target stops at
    AUTO_COLOUR_MAX_N and says so; a recipe's own colour_error goes on to the measured n (or AUTO_MAX_N)."""
    d = yaml.safe_load((RECIPES / "coated-aluminium.yaml").read_text(encoding="utf-8"))
    next(layer for layer in d["layers"] if "metal" in layer)["metal"]["roughness"] = 0.05
    rec = parse_recipe(yaml.safe_dump(d))
    n, why = auto_resolution(rec)
    assert n == AUTO_COLOUR_MAX_N and "default colour_error stops at" in why
    d["resolution"] = {"colour_error": 0.1}
    n_own, _ = auto_resolution(parse_recipe(yaml.safe_dump(d)))
    assert n_own == 2 * 176 > n


def test_report_states_its_discretisation_from_a_second_solve(tmp_path):
    """The report's estimate is max ΔE00(n', n) over the report geometries (n' = 3n/4, even) times
    (1 − 2^−p)/(r^p − 1): the same as two composes at n' and n (a change of either solve, of n' or of the
    factor fails it)."""
    rec = _with("fig5-translucent-gray.yaml", 24, rgb=True)
    res = compose(rec, tmp_path / "a")
    d = res.report["discretisation"]
    assert d["n"] == 24 and d["n_second"] == 18 and "n = 18" in d["method"]
    second = compose(rec, tmp_path / "b", n=18)
    dE = delta_E_2000(_labs(second.report), _labs(res.report))
    np.testing.assert_allclose(d["dE00_second_vs_n"], dE, rtol=1e-9, atol=1e-12)
    p, r = DISCRETISATION_ORDER, 24 / 18
    assert d["estimate_dE00"] == pytest.approx(dE.max() * (1 - 2**-p) / (r**p - 1), rel=1e-12)


def test_second_solve_is_even_for_every_allowed_n():
    """n' is even, at least 8 and below n for every allowed n ≥ 16 (n = 30 asked for n/2 = 15 and failed): 3n/4
    below SECOND_SOLVE_HALF_FROM (n/2 is pre-asymptotic at small n), n/2 from it on (3n/4's estimate fell below
    the true error there: test_report_estimate_bounds_the_true_error_at_n_200)."""
    for n in range(16, 513, 2):
        n2 = second_solve_n(n)
        assert n2 % 2 == 0 and 8 <= n2 < n
        if n < SECOND_SOLVE_HALF_FROM:
            assert abs(n2 - 0.75 * n) <= 1  # 3n/8 rounded, times 2
        else:
            assert abs(n2 - 0.5 * n) <= 1
    assert second_solve_n(200) == 100 and second_solve_n(64) == 48


@pytest.mark.slow
def test_report_estimate_bounds_the_true_error_at_n_200(tmp_path):
    """The report's estimate of ΔE00(n, 2n) on issue 34's bench stack (rough α 0.1 coat / HG slab / Lambertian,
    RGB, n = 200) is at least the measured ΔE00(200, 400) and within 1.5× of it (measured: 0.0731 against 0.0599;
    the 3n/4 second solve's estimate was 0.0573, below it: bench/estimate_accuracy.json)."""
    rec = load_recipe(Path(__file__).resolve().parents[2] / "bench" / "recipes" / "rough-hg-lambertian-rgb.yaml")
    a = compose(rec, tmp_path / "n200")
    b = compose(rec, tmp_path / "n400", n=400)
    true = delta_E_2000(_labs(a.report), _labs(b.report)).max()
    est = a.report["discretisation"]["estimate_dE00"]
    assert true <= est <= 1.5 * true, (est, true)
    assert a.n == 200 and a.report["discretisation"]["n_second"] == 100


@pytest.mark.slow
def test_colour_error_is_met_between_auto_and_twice_auto(tmp_path):
    """fig5-translucent-black (the worst stack without flakes or metal in the catalogue) with colour_error
    0.1: ΔE00(auto, 2·auto) ≤ 0.1 at every report geometry (RGB mode; measured in spectral mode 0.053)."""
    rec = _with("fig5-translucent-black.yaml", {"colour_error": 0.1}, rgb=True)
    n, _ = auto_resolution(rec)
    a = compose(rec, tmp_path / "a")
    b = compose(rec, tmp_path / "b", n=2 * n)
    assert a.n == n and delta_E_2000(_labs(a.report), _labs(b.report)).max() <= 0.1


@pytest.mark.slow
def test_coated_aluminium_at_auto_is_within_the_target_of_the_converged_answer(tmp_path):
    """Issue 26: coated aluminium at auto within ΔE00 0.1 of the converged answer at every report geometry (RGB
    mode: ΔE00(144, 288) is 0.0949 there and 0.095 in 41 bands).  The limit is n = 512 (the largest allowed) plus
    its own remainder, bounded by ΔE00(384, 512)·512^−p/(384^−p − 512^−p) with p = DISCRETISATION_ORDER (1.5,
    below the 2.06 measured, so the bound is generous); ΔE00 is taken as additive along the error's direction."""
    rec = _with("coated-aluminium.yaml", "auto", rgb=True)
    a = compose(rec, tmp_path / "auto")
    b = compose(rec, tmp_path / "n384", n=384)
    c = compose(rec, tmp_path / "n512", n=512)
    p = DISCRETISATION_ORDER
    remainder = delta_E_2000(_labs(b.report), _labs(c.report)).max() * 512.0**-p / (384.0**-p - 512.0**-p)
    err = delta_E_2000(_labs(a.report), _labs(c.report)) + remainder
    assert a.n == 176 and err.max() <= AUTO_TARGETS["colour_error"], (a.n, err, remainder)
    # and the report's own estimate against the converged answer does not understate it
    assert a.report["discretisation"]["estimate_dE00_converged"] >= err.max() - remainder


#: A stack the measured envelopes do not cover (found by fuzzing compose, issue 26): a 1.77 coat over a 1.8 layer
#: whose top interface is rough (α 0.188, nearly index-matched: a transmitted lobe far narrower than α) over media.
UNCOVERED = """\
flakedb: 1
name: fz164
spectral: {mode: mono}
resolution: auto
layers:
  - clearcoat: {thickness_um: 13.0, ior: 1.77, roughness: 0}
  - basecoat:
      thickness_um: 14.9
      ior: 1.8
      interface_roughness: 0.188
      particles: []
  - basecoat:
      thickness_um: 1.41
      ior: 1.66
      particles:
        - custom: {kind: medium, albedo: 0.786, phase: isotropic}
          optical_depth: 3.4
        - custom: {kind: medium, albedo: 0.789, phase: {hg: 0.48}}
          optical_depth: 0.175
  - primer: {albedo: 0.529}
"""


@pytest.mark.slow
def test_auto_refines_where_its_own_estimate_misses_the_target(tmp_path, monkeypatch):
    """resolution: auto checks its result (flakedb.solve.resolution.refine_auto_n): the envelopes give n = 32, where
    the report's own estimate is ΔE00 2.6; compose solves again (32 → 64 → 96) until the estimate meets 0.1, says
    so in the reason, and the result is within 0.1 of a solve at twice its n (measured, not the estimate).
    The stack's nearly matched rough interface is solved rough here (at n = 32 the product solves it smooth,
    flakedb.rt.adding.parts.near_matched: test_nearly_matched_rough_interface_at_auto_is_within_the_target)."""
    import flakedb.rt.adding.parts as parts

    monkeypatch.setattr(parts, "NEAR_MATCH_FRESNEL", -1.0)
    rec = parse_recipe(UNCOVERED)
    assert auto_resolution(rec)[0] == 32
    a = compose(rec, tmp_path / "auto")
    assert a.n > 32 and "auto refined n 32 →" in a.n_reason
    assert a.report["discretisation"]["estimate_dE00"] <= AUTO_TARGETS["colour_error"]
    b = compose(rec, tmp_path / "twice", n=2 * a.n)
    assert delta_E_2000(_labs(a.report), _labs(b.report)).max() <= AUTO_TARGETS["colour_error"]


@pytest.mark.slow
def test_nearly_matched_rough_interface_at_auto_is_within_the_target(tmp_path):
    """The same stack (1.77 → 1.8 at α 0.188: normal Fresnel 7e-5, transmitted lobe 0.003 rad) at auto: n = 32,
    its rough inner interface solved smooth (flakedb.rt.adding.parts.near_matched), is within ΔE00 0.1 of the rough
    flux-cell solve at n = 96 (where the lobe is resolved and solved rough; measured 0.026), where the rough solve
    at n = 32 was 2.6 off by the report's own estimate."""
    rec = parse_recipe(UNCOVERED)
    a = compose(rec, tmp_path / "auto")
    assert a.n == 32 and a.stack.info["inner_interfaces"][0]["solved_as"].startswith("smooth")
    b = compose(rec, tmp_path / "rough", n=96)
    assert "solved_as" not in b.stack.info["inner_interfaces"][0]
    assert delta_E_2000(_labs(a.report), _labs(b.report)).max() <= 0.1
