"""Advice for an unreached target (flakedb.match.advice; `flakedb match`'s advice lines and JSON record).

Guards against: advice that names a direction a free parameter can move (the projection not orthogonal to
the sensitivities), hue words pointing the wrong way round the hue circle, a parameter at its bound counted
as free, species ranked by anything but the direction that is out of reach (on a synthetic target made with
a red pigment the base does not have, the red pigment must come first), and an "unknown species" message
that does not mention --catalog.
"""

import json
from types import SimpleNamespace

import numpy as np
import pytest
import yaml
from click.testing import CliRunner

from flakedb.cli.main import cli
from flakedb.match.advice import advise, direction_words, unreachable_part
from flakedb.match.targets import E2194_GEOMETRIES, format_target
from tests.match.test_fit import _text
from tests.tolerances import gamma

G = np.asarray(E2194_GEOMETRIES, float)


def test_unreachable_part_is_orthogonal_to_every_sensitivity():
    rng = np.random.default_rng(3)
    S = rng.normal(size=(6, 3, 2))
    r = rng.normal(size=(6, 3))
    rp = unreachable_part(r, S)
    A = S.reshape(18, 2)
    bound = 8 * gamma(18) * np.abs(A).T @ np.abs(r.ravel())        # the rounding of the products, twice over
    assert np.all(np.abs(A.T @ rp.ravel()) <= bound)
    np.testing.assert_allclose(unreachable_part(rp, S), rp, atol=1e-12)          # a projection: idempotent
    np.testing.assert_array_equal(unreachable_part(r, S[:, :, :0]), r)          # no parameter: all of it
    # a residual in the span is reachable: nothing left
    assert np.abs(unreachable_part((A @ [0.3, -2.0]).reshape(6, 3), S)).max() < 1e-12


@pytest.mark.parametrize("lab, step, words", [
    ([50.0, 30.0, 0.0], [0.0, 0.0, 3.0], "hue toward yellow"),     # red, turned counter-clockwise
    ([50.0, 30.0, 0.0], [0.0, 0.0, -3.0], "hue toward blue"),
    ([50.0, 0.0, 30.0], [0.0, -3.0, 0.0], "hue toward green"),     # yellow: +h is toward green
    ([50.0, 0.0, 30.0], [0.0, 3.0, 0.0], "hue toward red"),
    ([50.0, -20.0, -20.0], [0.0, 2.0, -2.0], "hue toward blue"),   # h = 225°: +h is toward 270°
    ([50.0, 0.0, 30.0], [2.0, 0.0, -4.0], "lighter, less chroma"),
    ([50.0, 0.5, 0.5], [0.0, 3.0, -0.2], "redder"),                # near neutral: a*, b* words
    ([30.0, -0.8, 4.3], [-10.0, 18.0, 8.0], "darker, redder, yellower"),   # a step across the neutral axis
])
def test_direction_words(lab, step, words):
    assert direction_words([lab], [step]) == [words]


def _fake(residual_hue=True, bounded=False):
    """A MatchResult-like record: one parameter moving L* only at every geometry (and, with ``bounded``, a
    second one at its bound that moves a*); the target differs in L* and in a* (a red hue the free parameter
    does not have)."""
    lab_fit = np.column_stack([60.0 - 0.2 * G[:, 1], np.zeros(len(G)), 20.0 + 0 * G[:, 1]])
    S = np.zeros((len(G), 3, 2 if bounded else 1))
    S[:, 0, 0] = 30.0
    if bounded:
        S[:, 1, 1] = 10.0 * np.where(G[:, 1] < 30, 6.0, 1.0)   # the bounded one would move the missing a*
    lab_t = lab_fit + np.column_stack([np.full(len(G), 2.0), np.where(G[:, 1] < 30, 6.0, 1.0) * residual_hue,
                                       np.zeros(len(G))])
    params = [SimpleNamespace(name="a"), SimpleNamespace(name="b")][:S.shape[2]]
    return SimpleNamespace(lab_target=lab_t, lab_fit=lab_fit, sensitivities=S, params=params, geometries=G,
                           at_bound=[("b", "upper", 0.1)] if bounded else [], fitted_doc={"layers": []}, n=16,
                           observer="10", illuminant="D65")


def test_advice_names_the_hue_no_free_parameter_has():
    adv = advise(_fake(), candidates=[])
    # the lightness difference is what the free parameter moves: only the hue is left, at the three
    # geometries where it is largest (a* +6 against +1 elsewhere)
    assert adv.direction == [("hue toward red", ["45as-15", "45as15", "45as25"])]
    np.testing.assert_allclose(adv.r_perp[:, 0], 0.0, atol=1e-12)
    line = adv.lines()[0]
    assert line.startswith("advice: no free parameter moves the colour hue toward red at 45as-15, 45as15, 45as25")
    assert not adv.reachable_by_bounded and adv.probed


def test_a_parameter_at_its_bound_is_not_free():
    adv = advise(_fake(bounded=True), candidates=[])
    assert adv.direction and adv.reachable_by_bounded and not adv.probed
    assert "widen their bounds" in adv.lines()[1]


def test_nothing_out_of_reach():
    adv = advise(_fake(residual_hue=False), candidates=[])
    assert not adv.direction and "local minimum" in adv.lines()[0]


@pytest.mark.slow
def test_match_advises_the_species_that_has_the_missing_hue(tmp_path):
    """Target: metallic + iron-oxide-red (0.01); base: metallic + cadmium-yellow (loading fitted).  No yellow
    loading gives the red: match exits 1, says which way is out of reach, and ranks iron-oxide-red first among
    the catalogue colourants it probes, with a loading of the right order (first order: 0.005-0.02)."""
    from flakedb.match.fit import predict, recipe_from_doc

    d = yaml.safe_load(_text(VF_METALLIC=0.04, VF_YELLOW=0.001))
    d["layers"][1]["basecoat"]["particles"][1] = {"species": "iron-oxide-red", "volume_fraction": 0.01}
    p = predict(recipe_from_doc(d), G)
    (tmp_path / "red.csv").write_text(format_target(p.geometries, reflectance=p.rf, wavelength_nm=p.wavelength_nm))
    (tmp_path / "base.yaml").write_text(_text(VF_METALLIC=0.04, VF_YELLOW="{fit: [0.0005, 0.1], start: 0.005}"))
    out = tmp_path / "out"
    r = CliRunner().invoke(cli, ["match", str(tmp_path / "base.yaml"), "--target", str(tmp_path / "red.csv"),
                                 "--out", str(out), "--max-evaluations", "10"])
    assert r.exit_code == 1, r.output
    lines = r.output.splitlines()
    assert lines[-1].startswith("target NOT reached")
    adv_lines = [ln for ln in lines if ln.startswith("advice: ")]
    assert adv_lines[0].startswith("advice: no free parameter moves the colour ")
    assert adv_lines[1].startswith("advice: catalogue species that move it") and "iron-oxide-red (adds" in adv_lines[1]
    rec = json.loads((out / "two-species-match.json").read_text())["advice"]
    top = rec["species"][0]
    assert top["species"] == "iron-oxide-red" and top["cos"] > 0.9, rec["species"]
    assert 0.005 <= top["volume_fraction"] <= 0.02 and "redder" in top["adds"]
    assert "cadmium-yellow" not in [s["species"] for s in rec["species"]]       # already in the recipe


def test_unknown_species_mentions_catalog(tmp_path):
    (tmp_path / "r.yaml").write_text(_text(VF_METALLIC=0.04, VF_YELLOW=0.01).replace("cadmium-yellow", "my-blue"))
    r = CliRunner().invoke(cli, ["compare", str(tmp_path / "r.yaml"), "--write-csv", str(tmp_path / "p.csv")])
    assert r.exit_code == 2 and "unknown species 'my-blue'" in r.output and "--catalog" in r.output, r.output
    r = CliRunner().invoke(cli, ["species", "show", "my-blue"])
    assert r.exit_code == 2 and "--catalog" in r.output, r.output
