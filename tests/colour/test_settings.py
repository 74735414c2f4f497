"""The colour conditions and their defaults (flakedb.colour.settings), and the report built on them.

Guards against: a default named in two places drifting apart; an RGB-mode paint silently reported
under an observer its channels do not have; the colour report ignoring the observer, illuminant or
geometry set it is given.
"""

import numpy as np
import pytest

from flakedb.colour import settings as cs
from flakedb.colour.tolerance import reflectance_to_Lab
from flakedb.compose.orchestrate import compose
from flakedb.match import targets
from tests.compose.test_orchestrate import recipe


def test_defaults_in_one_place():
    assert (cs.DEFAULT_OBSERVER, cs.DEFAULT_ILLUMINANT, cs.DEFAULT_GEOMETRY_SET) == ("10", "D65", "e2194")
    assert targets.GEOMETRY_SETS is cs.GEOMETRY_SETS and targets.E2539_GEOMETRIES is cs.E2539_GEOMETRIES
    assert set(cs.FLOP_GEOMETRIES) <= set(cs.E2194_GEOMETRIES) <= set(cs.E2539_GEOMETRIES)
    assert cs.resolve() == cs.ColourSettings("10", "D65", "e2194")
    assert cs.resolve("2deg", "A", "E2539").label == "A/2°" and len(cs.resolve(geometry_set="e2539").geometries) == 11
    assert targets.read_target("illumination_deg,aspecular_deg,L*,a*,b*\n45,15,50,1,2\n").observer == cs.DEFAULT_OBSERVER


def test_rgb_mode_has_d65_2_only():
    r = cs.resolve(mode="rgb")
    assert (r.observer, r.illuminant) == ("2", "D65") and "linear sRGB" in r.note
    assert cs.resolve("2", "D65", mode="rgb").note == ""
    for obs, ill in (("10", None), (None, "A")):
        with pytest.raises(ValueError, match="spectral mode"):
            cs.resolve(obs, ill, mode="rgb")
    with pytest.raises(ValueError, match="geometry set 'e9999'"):
        cs.resolve(geometry_set="e9999")
    with pytest.raises(ValueError, match="observer '4'"):
        cs.resolve("4")


def test_report_uses_the_settings(tmp_path):
    """A spectral primer (a reddish ramp) reported under 10°/D65 (the default), 2°/A and the E2539 set:
    each row is the closed-form colour of the primer's spectrum under those conditions."""
    wl = np.arange(400.0, 701.0, 20.0)
    spec = 0.1 + 0.7 * (wl - 400) / 300
    r = recipe([{"primer": {"spectrum": {"wavelength_nm": wl.tolist(), "value": spec.tolist()}}}],
               mode="spectral", n=16)
    for settings, obs, ill, rows in ((None, "10", "D65", 6), (cs.resolve("2", "A", "e2539"), "2", "A", 11)):
        rep = compose(r, tmp_path, colour_settings=settings).report
        lab = reflectance_to_Lab(spec, wl, obs, ill)
        assert (rep["observer"], rep["illuminant"], len(rep["geometries"])) == (obs, ill, rows)
        for g in rep["geometries"]:
            np.testing.assert_allclose([g["L"], g["a"], g["b"]], lab, atol=1e-9)
    assert {g["illumination_deg"] for g in rep["geometries"]} == {15.0, 45.0}
    rgb = recipe([{"primer": {"color": "white"}}], mode="rgb", n=16)
    assert "linear sRGB" in compose(rgb, tmp_path).report["colour_note"]
    with pytest.raises(ValueError, match="spectral mode"):
        compose(rgb, tmp_path, colour_settings=cs.resolve("10"))
