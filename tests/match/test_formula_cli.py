"""``--formula`` on `compare` and `match` (flakedb.colour.tolerance.FORMULAS through the command line).

Guards against: a --formula that compare parses but does not use (the table's ΔE must be
colour-science's ``delta_E`` of the table's own L*a*b* in that formula, and pass/fail must follow it);
a match whose fit still minimises ΔE00 when another formula was asked for (its first cost must be the
sum of squares of the asked formula's ΔE at the start); a malformed --formula that is not refused with
the forms.
"""

import csv
import json

import colour
import numpy as np
import pytest
from click.testing import CliRunner

from flakedb.cli.main import cli
from tests.match.test_fit import TRUE, _text

TARGET = ("# observer: 10\n# illuminant: D65\nillumination_deg,aspecular_deg,L*,a*,b*\n"
          "45,15,66,5,27\n45,45,60,5.5,33\n45,110,53,4,68\n")


@pytest.fixture()
def pair(tmp_path):
    (tmp_path / "r.yaml").write_text(_text(**TRUE))
    (tmp_path / "t.csv").write_text(TARGET)
    return tmp_path / "r.yaml", tmp_path / "t.csv"


@pytest.mark.parametrize("text,method,kwargs", [("cmc:1:1", "CMC", {"l": 1, "c": 1}), ("deab", "CIE 1976", {}),
                                                ("de94:textiles", "CIE 1994", {"textiles": True}),
                                                ("din99", "DIN99", {})])
def test_compare_formula(pair, tmp_path, text, method, kwargs):
    recipe, target = pair
    table = tmp_path / f"{text.replace(':', '_')}.csv"
    r = CliRunner().invoke(cli, ["compare", str(recipe), "--target", str(target), "--formula", text, "--max-de", "1.5",
                                 "--table", str(table)])
    rows = list(csv.DictReader(table.open()))
    lab_t = np.array([[float(x[k]) for k in ("L_target", "a_target", "b_target")] for x in rows])
    lab = np.array([[float(x[k]) for k in ("L", "a", "b")] for x in rows])
    de = np.array([float(x["dE"]) for x in rows])
    ref = colour.delta_E(lab_t, lab, method=method, **kwargs)
    np.testing.assert_allclose(de, ref, atol=2e-4)          # the table's 4 decimals of L*a*b* and of ΔE
    assert [x["passed"] == "True" for x in rows] == list(ref <= 1.5)
    assert r.exit_code == (0 if np.all(ref <= 1.5) else 1), r.output
    assert {x["formula"] for x in rows} == {("dE CMC(1:1)", "dE*ab", "dE94 textiles", "dE99")[
        ["cmc:1:1", "deab", "de94:textiles", "din99"].index(text)]}
    assert "C*" in r.output and "h°" in r.output


def test_compare_formula_refused(pair):
    recipe, target = pair
    r = CliRunner().invoke(cli, ["compare", str(recipe), "--target", str(target), "--formula", "cmc:2"])
    assert r.exit_code == 2 and "--formula: formula 'cmc:2': cmc takes 2 factor(s) l:c" in r.output, r.output
    assert "Traceback" not in r.output


def test_match_fits_in_the_formula(pair, tmp_path):
    recipe, target = pair
    base = tmp_path / "base.yaml"
    base.write_text(_text(VF_METALLIC="{fit: [0.01, 0.1], start: 0.02}", VF_YELLOW=TRUE["VF_YELLOW"]))
    out = tmp_path / "out"
    r = CliRunner().invoke(cli, ["match", str(base), "--target", str(target), "--out", str(out), "--formula", "deab",
                                 "--max-de", "3", "--max-evaluations", "3"])
    assert r.exit_code in (0, 1), r.output
    rep = json.loads((out / "two-species-match.json").read_text())
    assert rep["formula"] == "dE*ab" and rep["tolerance"] == "dE*ab per-angle limits"
    lab_t = np.array([g["lab_target"] for g in rep["geometries"]])
    lab_s = np.array([g["lab_start"] for g in rep["geometries"]])
    lab_f = np.array([g["lab_fit"] for g in rep["geometries"]])
    de_ab = colour.delta_E(lab_t, lab_f, method="CIE 1976")
    np.testing.assert_allclose([g["dE_fit"] for g in rep["geometries"]], de_ab, rtol=1e-12)
    # the fit's first cost is Σ ΔE*ab² at the start (the residual is the formula's, not ΔE00's)
    cost0 = float(np.sum(colour.delta_E(lab_t, lab_s, method="CIE 1976") ** 2))
    assert rep["history"][0]["cost"] == pytest.approx(cost0, rel=1e-10)
    assert rep["history"][0]["cost"] != pytest.approx(float(np.sum(colour.delta_E(lab_t, lab_s, method="CIE 2000") ** 2)),
                                                      rel=1e-3)
    assert rep["reached"] == bool(np.all(de_ab <= 3))
    assert all(len(g["LCh_fit"]) == 3 and g["shade_fit"] for g in rep["geometries"])
