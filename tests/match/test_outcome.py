"""A match's outcome (flakedb.match.fit: MatchResult.reached / at_bound / outcome; `flakedb match`'s exit status).

Guards against: a fit that stops far from an unreachable target and still exits 0 without saying so
(the issue's "max ΔE00 8.2 with exit 0"); a parameter pinned at its bound going unnamed; a reachable
target reported as not reached.
"""

import json

import numpy as np
import pytest
import yaml
from click.testing import CliRunner

from flakedb.cli.main import cli
from flakedb.colour.tolerance import PerAngleLimits
from flakedb.match.fit import match, predict, recipe_from_doc
from flakedb.match.targets import E2194_GEOMETRIES, format_target, read_target
from tests.match.test_fit import TRUE, _text


@pytest.fixture(scope="module")
def target_text():
    pred = predict(recipe_from_doc(yaml.safe_load(_text(**TRUE))), E2194_GEOMETRIES)
    return format_target(pred.geometries, reflectance=pred.rf, wavelength_nm=pred.wavelength_nm, name="true")


def test_unreachable_target_exits_nonzero_and_names_the_bound(tmp_path, target_text):
    """Yellow may not exceed 0.004 (the truth is 0.02): the fit ends at that bound, misses the tolerance,
    says so, names the bound, still writes the best fit, and exits 1."""
    (tmp_path / "t.csv").write_text(target_text)
    (tmp_path / "base.yaml").write_text(_text(VF_METALLIC=TRUE["VF_METALLIC"], VF_YELLOW="{fit: [0.001, 0.004]}"))
    out = tmp_path / "out"
    r = CliRunner().invoke(cli, ["match", str(tmp_path / "base.yaml"), "--target", str(tmp_path / "t.csv"),
                                 "--out", str(out), "--max-evaluations", "8"])
    assert r.exit_code == 1, r.output
    last = r.output.strip().splitlines()[-1]
    assert last.startswith("target NOT reached") and "volume_fraction at its upper bound 0.004" in last, last
    rep = json.loads((out / "two-species-match.json").read_text())
    assert rep["reached"] is False and rep["at_bound"][0]["side"] == "upper"
    assert not all(rep["passed"]) and (out / "two-species-fitted.yaml").is_file()


def test_reachable_target_is_reached(target_text):
    """The same target with the truth inside the bounds: reached, exit status 0 semantics, no bound named."""
    doc = yaml.safe_load(_text(VF_METALLIC=TRUE["VF_METALLIC"], VF_YELLOW="{fit: [0.005, 0.08], start: 0.01}"))
    res = match(doc, read_target(target_text), tolerance=PerAngleLimits(default=0.2))
    assert res.reached and not res.at_bound and res.outcome.startswith("target reached"), res.outcome
    assert res.values[0] == pytest.approx(TRUE["VF_YELLOW"], rel=0.02)
    assert np.all(res.de_fit <= 0.2)


def test_match_over_several_targets(tmp_path, target_text):
    """Two targets in one command: one reachable within the bounds (yellow 0.003), one not (0.02); one fit
    each into OUT/<target>/, a summary table, exit 1 because one is not reached."""
    d = tmp_path / "targets"
    d.mkdir()
    (d / "far.csv").write_text(target_text)
    near = recipe_from_doc(yaml.safe_load(_text(VF_METALLIC=TRUE["VF_METALLIC"], VF_YELLOW=0.003)))
    pred = predict(near, E2194_GEOMETRIES)
    (d / "near.csv").write_text(format_target(pred.geometries, reflectance=pred.rf, wavelength_nm=pred.wavelength_nm))
    (tmp_path / "base.yaml").write_text(_text(VF_METALLIC=TRUE["VF_METALLIC"], VF_YELLOW="{fit: [0.001, 0.004]}"))
    out = tmp_path / "out"
    r = CliRunner().invoke(cli, ["match", str(tmp_path / "base.yaml"), "--target", str(d), "--out", str(out),
                                 "--max-evaluations", "8"])
    assert r.exit_code == 1 and "1 of 2 target(s) reached" in r.output, r.output
    near_rep = json.loads((out / "near" / "two-species-match.json").read_text())
    far_rep = json.loads((out / "far" / "two-species-match.json").read_text())
    assert near_rep["reached"] and not far_rep["reached"]
    assert near_rep["parameters"][0]["fitted"] == pytest.approx(0.003, rel=0.02)
