"""Colour-difference formulas of ``--formula`` (flakedb.colour.tolerance.FORMULAS) and the shade words.

Guards against: a formula whose residual components do not add up (in squares) to colour-science's own
``colour.delta_E(method=…)`` on Sharma, Wu & Dalal's (2005) published test pairs, in either order
(CIE 1994 and CMC are asymmetric: the reference's chroma and hue set the weights) and for every
parametric setting colour-science offers (CMC l:c, textiles); a CIEDE2000 that leaves Sharma's
published ΔE00 values; parametric factors k_L:k_C:k_H applied to the wrong term; a formula string
parsed into something other than what was written; shade words with the wrong direction; and a
``--formula`` that compare or match ignore.
"""

from pathlib import Path

import colour
import numpy as np
import pytest

from flakedb.colour.tolerance import (
    DE00,
    FORMULAS,
    Formula,
    PerAngleLimits,
    lch,
    parse_formula,
    shade_words,
)
from tests.tolerances import ulps

DATA = np.loadtxt(Path(__file__).parent / "data" / "sharma2005_ciede2000_pairs.txt", comments="#")
LAB1, LAB2, DE00_PUBLISHED = DATA[:, 0:3], DATA[:, 3:6], DATA[:, 6]
#: ΔE² of two implementations: each squared term is a few dozen roundings of inputs ≤ 100 in magnitude
#: (ΔH² = Δa² + Δb² − ΔC² in colour-science cancels terms of size |Lab|²), so they agree to a few
#: hundred ulps of |Lab|_max² = 1e4.
DE2_TOL = float(ulps(256, 100.0**2))

SETTINGS = [("deab", ()), ("de94", (1.0,)), ("de94", (2.0,)), ("cmc", (2.0, 1.0)), ("cmc", (1.0, 1.0)),
            ("cmc", (1.4, 0.7)), ("din99", (1.0,)), ("din99", (2.0,)), ("de00", (1.0, 1.0, 1.0)),
            ("de00", (2.0, 1.0, 1.0))]


def test_every_setting_colour_science_offers_is_tested():
    assert {k for k, _ in SETTINGS} == set(FORMULAS)


@pytest.mark.parametrize("key,factors", SETTINGS)
def test_formula_agrees_with_colour_science_on_sharma_pairs(key, factors):
    f = Formula(key, factors)
    kwargs = FORMULAS[key].colour_kwargs(factors)
    for a, b in ((LAB1, LAB2), (LAB2, LAB1)):           # both orders: 1994 and CMC are not symmetric
        ref = colour.delta_E(a, b, method=FORMULAS[key].method, **kwargs)
        ours = f.delta_E(a, b)
        assert np.max(np.abs(ours**2 - ref**2)) <= DE2_TOL, (key, factors, np.max(np.abs(ours - ref)))
        e = f.residuals(a, b)
        assert e.shape == a.shape


def test_ciede2000_published_values():
    """Sharma et al. 2005, Table 1: all 34 pairs to the table's 4 decimals, both orders."""
    np.testing.assert_allclose(DE00.delta_E(LAB1, LAB2), DE00_PUBLISHED, atol=5e-5)
    np.testing.assert_allclose(DE00.delta_E(LAB2, LAB1), DE00_PUBLISHED, atol=5e-5)


def test_ciede2000_parametric_factors():
    """eq. 22: ΔE00 is homogeneous of degree −1 in (k_L, k_C, k_H); k_L scales only the lightness term
    (a pair differing in L* alone), k_C and k_H only the chroma / hue terms (a pair at equal L*)."""
    base = DE00.delta_E(LAB1, LAB2)
    np.testing.assert_allclose(Formula("de00", (3.0, 3.0, 3.0)).delta_E(LAB1, LAB2), base / 3.0, rtol=1e-13)
    light = np.array([[50.0, 10.0, 10.0]]), np.array([[53.0, 10.0, 10.0]])
    d = DE00.delta_E(*light)
    assert Formula("de00", (2.0, 5.0, 7.0)).delta_E(*light) == pytest.approx(d / 2.0, rel=1e-13)
    same_L = LAB1[:6], LAB2[:6]                          # pairs 1–6 share L* = 50
    np.testing.assert_allclose(Formula("de00", (9.0, 1.0, 1.0)).delta_E(*same_L), DE00.delta_E(*same_L), rtol=1e-13)
    assert np.all(Formula("de00", (1.0, 2.0, 1.0)).delta_E(*same_L) < DE00.delta_E(*same_L))


@pytest.mark.parametrize("key", list(FORMULAS))
def test_residuals_zero_for_identical_and_broadcast(key):
    f = parse_formula(key)
    lab = np.array([[[50.0, 10.0, -10.0]], [[20.0, 0.0, 0.0]]])   # (2, 1, 3) against (3,) broadcast
    assert f.delta_E(lab, lab).shape == (2, 1)
    np.testing.assert_array_equal(f.delta_E(lab, lab), 0.0)
    assert f.delta_E(lab, np.array([50.0, 12.0, -10.0])).shape == (2, 1)


@pytest.mark.parametrize("text,key,factors,label", [
    ("de00", "de00", (1.0, 1.0, 1.0), "dE00"), ("de00:2:1:1", "de00", (2.0, 1.0, 1.0), "dE00(2:1:1)"),
    ("CMC", "cmc", (2.0, 1.0), "dE CMC(2:1)"), ("cmc:1:1", "cmc", (1.0, 1.0), "dE CMC(1:1)"),
    ("de94", "de94", (1.0,), "dE94"), ("de94:textiles", "de94", (2.0,), "dE94 textiles"),
    ("din99:textiles", "din99", (2.0,), "dE99 textiles"), ("deab", "deab", (), "dE*ab"),
])
def test_parse_formula(text, key, factors, label):
    f = parse_formula(text)
    assert (f.key, f.factors, f.label) == (key, factors, label)


@pytest.mark.parametrize("text", ["de2000", "cmc:2", "cmc:2:0", "de00:1:1", "de00:1:nan:1", "deab:2", "cmc:textiles",
                                  "de94:1:1:1"])
def test_parse_formula_refuses(text):
    with pytest.raises(ValueError, match="de00:kL:kC:kH"):
        parse_formula(text)


def test_per_angle_limits_use_the_formula():
    geoms = [(45.0, 15.0), (45.0, 45.0)]
    ref = np.array([[60.0, 20.0, 30.0], [40.0, 10.0, 15.0]])
    smp = ref + np.array([[0.0, 1.0, 0.0], [2.0, 0.0, 0.0]])
    f = parse_formula("cmc:2:1")
    ev = PerAngleLimits(default=1.0, formula=f).evaluate(geoms, ref, smp)
    np.testing.assert_allclose(ev["value"], colour.delta_E(ref, smp, method="CMC", l=2, c=1), rtol=1e-12)
    assert ev["formula"] == "dE CMC(2:1)" and ev["scheme"] == "dE CMC(2:1) per-angle limits"
    assert PerAngleLimits().name == "CIEDE2000 per-angle limits"


def test_shade_words():
    ref = np.array([[60.0, -5.0, 30.0], [60.0, 5.0, -20.0], [50.0, 0.0, 0.0], [50.0, 2.0, 2.0]])
    smp = np.array([[61.0, -6.0, 27.0], [58.0, 7.0, -25.0], [50.01, -1.0, 1.0], [50.0, -1.0, 2.0]])
    assert shade_words(ref, smp) == ["lighter, greener, less yellow", "darker, redder, bluer",
                                     "greener, yellower", "greener"]   # a* crossing 0 is greener, not less red
    assert shade_words([50.0, 10.0, 10.0], [50.0, 0.0, 10.0]) == ["less red"]
    assert shade_words([50.0, 10.0, 10.0], [50.0, 10.0, 10.0]) == ["same"]


def test_lch():
    np.testing.assert_allclose(lch([[50.0, 3.0, 4.0], [20.0, 0.0, -2.0]]), [[50.0, 5.0, np.degrees(np.arctan2(4, 3))],
                                                                         [20.0, 2.0, 270.0]])
    np.testing.assert_allclose(lch([40.0, 10.0, 20.0]), colour.Lab_to_LCHab([40.0, 10.0, 20.0]), rtol=1e-13)
