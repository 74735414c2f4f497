"""Colour differences and tolerances (flakedb.colour.tolerance) and the target CSV (flakedb.match.targets).

Guards against: a CIEDE2000 that departs from Sharma et al.'s published test pairs or from
colour-science's ``delta_E`` (hue wrap-around, achromatic pairs); residual components whose squares
do not add up to ΔE00²; signed ΔH* with the wrong sign or size; a 10° observer / F11 / A integration
that differs from colour-science's own 1 nm integration; a white that is not L* = 100; a metamerism
index that is not zero for a pair differing by a scale factor, or that misses a metameric pair;
tolerance schemes that pass what they should fail; a CSV reader that accepts inconsistent or
unreadable targets, or does not read back what the writer wrote.
"""

import colour
import numpy as np
import pytest

from flakedb.colour.colorimetry import spectral_grid
from flakedb.colour.colorimetry import tristimulus_weights as weights_2deg_d65
from flakedb.colour.tolerance import (
    PerAngleLimits,
    WeightedLCH,
    ciede2000_residuals,
    delta_E_2000,
    lab_differences,
    metamerism_index,
    reflectance_to_Lab,
    reflectance_to_XYZ,
    tristimulus_weights,
)
from flakedb.match.targets import (
    E2194_GEOMETRIES,
    E2539_GEOMETRIES,
    TargetError,
    format_target,
    read_target,
)

# Sharma, Wu & Dalal, Color Res. Appl. 30, 21 (2005), Table 1: pairs 1, 2, 3, 7, 17, 25 (L*a*b* 1, 2, ΔE00)
SHARMA = [
    ((50.0, 2.6772, -79.7751), (50.0, 0.0, -82.7485), 2.0425),
    ((50.0, 3.1571, -77.2803), (50.0, 0.0, -82.7485), 2.8615),
    ((50.0, 2.8361, -74.0200), (50.0, 0.0, -82.7485), 3.4412),
    ((50.0, 0.0, 0.0), (50.0, -1.0, 2.0), 2.3669),
    ((50.0, 2.5, 0.0), (73.0, 25.0, -18.0), 27.1492),
    ((60.2574, -34.0099, 36.2677), (60.4626, -34.1751, 39.4387), 1.2644),
]


@pytest.mark.parametrize("l1,l2,de", SHARMA)
def test_ciede2000_sharma_pairs(l1, l2, de):
    assert delta_E_2000(l1, l2) == pytest.approx(de, abs=5e-5)
    assert delta_E_2000(l2, l1) == pytest.approx(de, abs=5e-5)  # symmetric


def test_ciede2000_agrees_with_colour_science():
    rng = np.random.default_rng(7)
    a = rng.uniform([0, -100, -100], [100, 100, 100], (3000, 3))
    b = a + rng.normal(0, 4, a.shape)
    b[:200, 1:] = 0.0                      # achromatic samples
    b[200:400, 1:] = -a[200:400, 1:]       # opposite hues (wrap-around branches)
    ours = delta_E_2000(a, b)
    ref = colour.delta_E(a, b, method="CIE 2000")
    assert np.max(np.abs(ours - ref)) < 1e-10
    e = ciede2000_residuals(a, b)
    assert np.allclose(np.sum(e * e, axis=-1), ref**2, rtol=1e-10, atol=1e-20)


def test_lab_differences():
    ref = np.array([[60.0, 20.0, 10.0], [50.0, 10.0, 0.0]])
    smp = np.array([[61.0, 18.0, 14.0], [50.0, 0.0, 10.0]])
    d = lab_differences(ref, smp)
    assert np.allclose(d["dL"] ** 2 + d["dC"] ** 2 + d["dH"] ** 2, d["dE_ab"] ** 2)
    # second pair: same chroma 10, hue 0° → 90°: ΔC = 0, ΔH = +2·10·sin 45° (positive: hue angle grows)
    assert d["dC"][1] == pytest.approx(0.0, abs=1e-12)
    assert d["dH"][1] == pytest.approx(2 * 10 * np.sin(np.radians(45)))
    assert lab_differences(smp, ref)["dH"][1] == pytest.approx(-d["dH"][1])


def test_weights_2deg_d65_are_the_colour_reports():
    wl = spectral_grid((380, 780), 10)
    assert np.array_equal(tristimulus_weights(wl, "2", "D65"), weights_2deg_d65(wl))


@pytest.mark.parametrize("observer,cmfs", [("10", "CIE 1964 10 Degree Standard Observer"),
                                           ("2", "CIE 1931 2 Degree Standard Observer")])
@pytest.mark.parametrize("illuminant,sd_name", [("F11", "FL11"), ("A", "A"), ("D65", "D65")])
def test_observer_illuminant_against_colour_integration(observer, cmfs, illuminant, sd_name):
    shape = colour.SpectralShape(380, 780, 1)
    wl = spectral_grid((380, 780), 1)
    sds = list(colour.SDS_COLOURCHECKERS["ColorChecker N Ohta"].values())[:6]
    R = np.array([sd.copy().align(shape).values for sd in sds])
    ours = reflectance_to_XYZ(R, wl, observer, illuminant)
    cm = colour.MSDS_CMFS[cmfs].copy().align(shape)
    il = colour.SDS_ILLUMINANTS[sd_name].copy().align(shape)
    ref = np.array([colour.sd_to_XYZ(sd.copy().align(shape), cm, il, method="Integration") for sd in sds]) / 100
    assert np.max(np.abs(ours - ref)) < 1e-9
    white = reflectance_to_Lab(np.ones(wl.size), wl, observer, illuminant)
    assert np.allclose(white, [100.0, 0.0, 0.0], atol=1e-10)


def test_metamerism_index():
    wl = spectral_grid((400, 700), 10)
    rng = np.random.default_rng(3)
    R1 = np.clip(0.4 + 0.2 * np.sin(wl / 37.0), 0, 1)
    assert metamerism_index(R1, R1, wl, "2", "D65") == pytest.approx(0.0, abs=1e-12)
    assert metamerism_index(R1, 0.8 * R1, wl, "2", "D65") == pytest.approx(0.0, abs=1e-9)  # scale: corrected away
    # a metameric pair under D65 / 2°: add a "metameric black" (orthogonal to the D65 weights)
    W = tristimulus_weights(wl, "2", "D65")
    v = rng.normal(size=wl.size)
    black = v - W @ np.linalg.lstsq(W, v, rcond=None)[0]
    R2 = R1 + 0.1 * black / np.abs(black).max()
    assert delta_E_2000(reflectance_to_Lab(R1, wl, "2", "D65"), reflectance_to_Lab(R2, wl, "2", "D65")) < 1e-9
    mi = metamerism_index(R1, R2, wl, "2", "D65", "A")
    plain = delta_E_2000(reflectance_to_Lab(R1, wl, "2", "A"), reflectance_to_Lab(R2, wl, "2", "A"))
    assert mi > 0.1 and mi == pytest.approx(plain, rel=1e-6)


def test_per_angle_limits_and_weighted_lch():
    g = [(45.0, 15.0), (45.0, 45.0)]
    ref = np.array([[60.0, 5.0, 5.0], [40.0, 5.0, 5.0]])
    smp = ref + [[1.0, 0.0, 0.0], [1.0, 0.0, 0.0]]
    ev = PerAngleLimits(default=0.5, limits={(45, 15): 2.0}).evaluate(g, ref, smp)
    assert list(ev["passed"]) == [True, False] and not ev["passed_all"]
    # hand computation: ΔL* = 1 against δL = 2 → 0.5; against δL = 0.8 → 1.25
    ev = WeightedLCH({(45, 15): (2.0, 1.0, 1.0), (45, 45): (0.8, 1.0, 1.0)}).evaluate(g, ref, smp)
    assert np.allclose(ev["value"], [0.5, 1.25]) and list(ev["passed"]) == [True, False]
    with pytest.raises(ValueError, match="no tolerance"):
        WeightedLCH({(45, 15): (1, 1, 1)}).evaluate(g, ref, smp)


# ----------------------------------------------------------------------------------------------
# target CSV
# ----------------------------------------------------------------------------------------------


def test_geometry_sets():
    from flakedb.appearance.report import ASPECULAR_DEG, ILLUMINATION_DEG

    assert E2194_GEOMETRIES == tuple((ILLUMINATION_DEG, a) for a in ASPECULAR_DEG)
    assert len(E2539_GEOMETRIES) == 11
    for th, asp in E2539_GEOMETRIES:        # every detector within the hemisphere, none at the specular
        assert abs(th - asp) < 90 and asp != 0


def test_csv_round_trip_lab_and_spectral():
    g = np.array(E2194_GEOMETRIES)
    lab = np.array([[70.0 - 5 * i, 1.0 + i, -3.0 + 0.5 * i] for i in range(6)])
    t = read_target(format_target(g, lab=lab, observer="10", illuminant="A"))
    assert t.observer == "10" and t.illuminant == "A" and not t.spectral
    assert np.allclose(t.lab, lab, atol=1e-6) and np.array_equal(t.geometries, g)
    with pytest.raises(TargetError, match="needs spectral"):
        t.lab_under("2", "D65")
    wl = spectral_grid((400, 700), 20)
    R = np.linspace(0.1, 0.6, 6)[:, None] * (1 + 0.3 * np.sin(wl / 50.0))[None, :]
    t = read_target(format_target(g, reflectance=R, wavelength_nm=wl))
    assert t.spectral and np.allclose(t.reflectance, R, rtol=1e-8)
    assert np.allclose(t.lab_under("10", "F11"), reflectance_to_Lab(R, wl, "10", "F11"))
    # percent
    text = "# reflectance: percent\nillumination_deg,aspecular_deg," + ",".join(f"R_{w:g}" for w in wl) + "\n"
    text += "\n".join(f"{a:g},{b:g}," + ",".join(f"{100 * v:.10g}" for v in r) for (a, b), r in zip(g, R)) + "\n"
    assert np.allclose(read_target(text).reflectance, R)


@pytest.mark.parametrize("text,msg", [
    ("illumination_deg,aspecular_deg,L*,a*,b*\n", "no geometry rows"),
    ("aspecular_deg,illumination_deg,L*,a*,b*\n45,15,1,2,3\n", "must start with"),
    ("illumination_deg,aspecular_deg,L*,a*,b*,gloss\n45,15,1,2,3,4\n", "unknown column"),
    ("illumination_deg,aspecular_deg\n45,15\n", "no colour columns"),
    ("illumination_deg,aspecular_deg,L*,a*,b*\n45,140,1,2,3\n", "within ±90"),
    ("illumination_deg,aspecular_deg,L*,a*,b*\n45,0,1,2,3\n", "specular"),
    ("illumination_deg,aspecular_deg,L*,a*,b*\n45,15,1,2\n", "4 values"),
    ("illumination_deg,aspecular_deg,L*,a*,b*\n45,15,1,2,x\n", "not a number"),
    ("illumination_deg,aspecular_deg,L*,a*,b*\n45,15,1,2,3\n45,15,1,2,3\n", "twice"),
    ("illumination_deg,aspecular_deg,R_400,R_425,R_430\n45,15,0.1,0.2,0.3\n", "uniform"),
    ("# observer: 7\nillumination_deg,aspecular_deg,L*,a*,b*\n45,15,1,2,3\n", "observer"),
])
def test_csv_errors(text, msg):
    with pytest.raises(TargetError, match=msg):
        read_target(text)


def test_csv_inconsistent_lab_and_spectra_refused():
    wl = spectral_grid((400, 700), 20)
    R = np.full((1, wl.size), 0.5)
    text = format_target([(45.0, 15.0)], reflectance=R, wavelength_nm=wl)
    lab = reflectance_to_Lab(R, wl, "10", "D65")[0]   # format_target's default conditions
    bad = text.replace(f"{lab[0]:.6f}", f"{lab[0] + 1:.6f}")
    assert bad != text
    with pytest.raises(TargetError, match="disagree"):
        read_target(bad)


def test_observer_conditions_are_always_stated():
    """Issue #34: the observer-aware functions here defaulted to the 2° observer while the product's default is
    10° (flakedb.colour.settings.DEFAULT_OBSERVER), under names that colorimetry's 2°-only functions also use: a
    call that forgot its conditions was silently 2°.  They now take the observer and illuminant explicitly."""
    import inspect

    from flakedb.colour import tolerance

    for fn in (tolerance.tristimulus_weights, tolerance.reflectance_to_XYZ, tolerance.white_XYZ,
               tolerance.reflectance_to_Lab, tolerance.metamerism_index):
        params = inspect.signature(fn).parameters
        for name in ("observer", "illuminant", "reference_illuminant"):
            if name in params:
                assert params[name].default is inspect.Parameter.empty, (fn.__name__, name)

