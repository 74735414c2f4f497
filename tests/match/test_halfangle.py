"""The half-angle test (flakedb.match.halfangle, docs/validation.md §4a): the binder's half angles against Snell's
closed form, the CIELAB inverse, the common-chromaticity bound on cases with known answers, and what it says about
the measured colour-shift paint irid_flake_paint2 against a composed Fabry-Perot flake paint."""

from pathlib import Path

import numpy as np
import pytest
import yaml

from flakedb.colour.colorimetry import Lab_to_XYZ, XYZ_to_Lab, delta_E_2000
from flakedb.match.halfangle import binder_half_angles_deg, common_chromaticity_worst_de00
from flakedb.match.targets import read_target
from tests.tolerances import U

ROOT = Path(__file__).resolve().parents[2]
IRID = ROOT / "tools" / "validation" / "targets" / "irid_flake_paint2_rgb.csv"
#: the E2194 / E2539 geometries whose half vector in the binder is 4.3-5.0° from the light (n = 1.5)
EQUAL_THETA_D = ((45, 75), (45, 110), (15, 15), (15, 45))


def test_half_angles_are_snells_closed_form():
    # in the plane, light at -θ_i' and viewer at +θ_v' (refracted): the half vector lies at (θ_v' - θ_i')/2 and the
    # difference angle is half the angle between them, (θ_i' + θ_v')/2
    rng = np.random.default_rng(5)
    ti = rng.uniform(0, 80, 200)
    gam = rng.uniform(-60, 140, 200)
    tv = ti - gam
    keep = np.abs(tv) < 85
    g = np.stack([ti, gam], axis=1)[keep]
    n = 1.5
    a = np.arcsin(np.sin(np.radians(g[:, 0])) / n)
    b = np.arcsin(np.sin(np.radians(g[:, 0] - g[:, 1])) / n)
    th, td = binder_half_angles_deg(g, n)
    np.testing.assert_allclose(th, np.degrees(np.abs(b - a) / 2), rtol=0, atol=1e-6)   # arccos near 1: ~sqrt(u) rad
    np.testing.assert_allclose(td, np.degrees(np.abs(a + b) / 2), rtol=0, atol=1e-6)
    th0, td0 = binder_half_angles_deg([[45, 0], [15, 0]], n)                           # the specular
    np.testing.assert_allclose(th0, 0, atol=1e-6)
    np.testing.assert_allclose(td0, np.degrees(np.arcsin(np.sin(np.radians([45, 15])) / n)), atol=1e-6)
    _, td4 = binder_half_angles_deg(EQUAL_THETA_D, n)
    assert td4.min() > 4.3 and td4.max() < 5.0


def test_lab_to_xyz_inverts_xyz_to_lab():
    rng = np.random.default_rng(6)
    lab = np.column_stack([rng.uniform(0.5, 120, 300), rng.uniform(-80, 80, 300), rng.uniform(-80, 80, 300)])
    lab[:20, 0] = rng.uniform(0.1, 7.9, 20)                                  # the linear branch of f (L* < 8)
    back = XYZ_to_Lab(Lab_to_XYZ(lab))
    np.testing.assert_allclose(back, lab, rtol=0, atol=1e4 * U * 120)        # cube and cube root of O(1)


def test_common_chromaticity_bound_known_cases():
    # colours of one chromaticity at any lightness: 0; two colours of equal lightness: at most their ΔE00 (taking
    # either one's chromaticity) and more than 0
    xy = np.array([0.25, 0.22])
    Y = np.array([0.02, 0.1, 0.4, 0.9])
    lab = XYZ_to_Lab(Y[:, None] * np.array([xy[0] / xy[1], 1, (1 - xy.sum()) / xy[1]]))
    worst, found = common_chromaticity_worst_de00(lab)
    assert worst < 1e-4
    np.testing.assert_allclose(found, xy, atol=1e-4)
    pair = np.array([[50.0, 20.0, 10.0], [50.0, -15.0, -5.0]])
    worst, _ = common_chromaticity_worst_de00(pair)
    assert 0.3 * delta_E_2000(pair[0], pair[1]) < worst <= delta_E_2000(pair[0], pair[1]) + 1e-6


def test_measured_colour_shift_paint_changes_hue_at_equal_theta_d():
    # irid_flake_paint2 at the four geometries of θ_d' 4.3-5.0°: purple, green, yellow, cyan (h 308°, 156°, 87°,
    # 212°); no one chromaticity comes within 15 ΔE00 of all four (measured 15.70): a specular-flake paint, whose
    # single reflection there has one spectrum, is that far from it
    t = read_target(IRID)
    idx = [int(np.flatnonzero((t.geometries[:, 0] == a) & (t.geometries[:, 1] == b))[0]) for a, b in EQUAL_THETA_D]
    worst, _ = common_chromaticity_worst_de00(t.lab[idx])
    assert worst > 15.0


@pytest.mark.slow
def test_a_fabry_perot_paint_keeps_one_chromaticity_at_equal_theta_d():
    # the premise in flakedb itself: a composed Fabry-Perot flake paint (10 % flakes, α 0.3, Cr 5 nm, MgF2 380 nm,
    # black primer; n = 16) gives these four geometries one chromaticity to within 0.95 ΔE00 (measured; 0.3-0.95
    # over four recipes of 2-15 % flakes, α 0.3-0.6, MgF2 380-750 nm): the multiply scattered light is the rest
    from flakedb.match.fit import find_fit_parameters, predict, recipe_from_doc, substitute
    from flakedb.paint.catalog import load_catalog
    cat = load_catalog(None)
    doc = yaml.safe_load((ROOT / "tools" / "validation" / "colour-shift-fabry-perot.yaml").read_text(encoding="utf-8"))
    params = find_fit_parameters(doc)
    names = [p.name.rsplit(".", 1)[-1] for p in params]
    vals = dict(zip(names, [0.10, 0.3, 3.0, 5.0, 380.0, 0.03, 0.005]))
    assert list(vals) == ["volume_fraction", "orientation_alpha", "orientation_shape", "coating_thickness_nm[0]",
                          "coating_thickness_nm[1]", "coating_thickness_rel_sd", "albedo"]
    rec = recipe_from_doc(substitute(doc, params, list(vals.values())), catalog=cat)
    lab = predict(rec, np.array(EQUAL_THETA_D, float), n=16, catalog=cat).lab()
    assert lab[:, 0].min() > 10                     # the flakes' light reaches all four (not a black paint)
    worst, _ = common_chromaticity_worst_de00(lab)
    assert worst < 2.0


@pytest.mark.slow
def test_two_spectra_bound_known_case_and_the_measured_paint():
    # colours mixed from two lights of known xy in four proportions: the segment between them holds all four (the
    # bound is ~0, limited by the 201-point segment); the measured paint's four θ_d' ≈ 4.5° colours cannot all be
    # mixtures of two spectra to better than 8 ΔE00 (local-search estimate 8.27 with 40 starts, docs §4a)
    from flakedb.match.halfangle import two_spectra_worst_de00
    a, b = np.array([0.45, 0.41]), np.array([0.20, 0.18])
    ua = np.array([a[0] / a[1], 1, (1 - a.sum()) / a[1]])
    ub = np.array([b[0] / b[1], 1, (1 - b.sum()) / b[1]])
    t = np.array([0.1, 0.35, 0.6, 0.9])[:, None]
    Y = np.array([0.05, 0.2, 0.4, 0.7])[:, None]
    lab = XYZ_to_Lab(Y * (t * ua + (1 - t) * ub))
    worst, _ = two_spectra_worst_de00(lab, starts=10)
    assert worst < 0.2
    assert common_chromaticity_worst_de00(lab)[0] > 10                  # one chromaticity cannot do it
    tgt = read_target(IRID)
    idx = [int(np.flatnonzero((tgt.geometries[:, 0] == g0) & (tgt.geometries[:, 1] == g1))[0]) for g0, g1 in EQUAL_THETA_D]
    worst, _ = two_spectra_worst_de00(tgt.lab[idx], starts=10)
    assert worst > 8.0
