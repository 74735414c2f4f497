"""``flakedb match`` fits the orientation shape fields (issue #35 item 3): any numeric recipe field may be
``{fit: [min, max]}``, so the Student-t ``orientation_shape`` and a mixture's ``weight`` are free parameters.

Guards against a shape field that does not reach the prediction (the fit would not move it) and against a
fit that cannot tell a tail shape from the measured angles: a synthetic target made from known values
is recovered from a start far off.
"""


import pytest
import yaml
from click.testing import CliRunner

from flakedb.cli.main import cli
from tests.cases import basecoat_recipe

BASE = basecoat_recipe("shape", ["{species: metallic, volume_fraction: 0.04, orientation_alpha: 0.2, ORIENT}"],
                       resolution=32)


@pytest.mark.slow
@pytest.mark.parametrize("true, fit, get, expect", [
    ("orientation_distribution: student_t, orientation_shape: 1.8",
     "orientation_distribution: student_t, orientation_shape: {fit: [1.5, 30], start: 6}",
     lambda p: p["orientation_shape"], 1.8),
    ("orientation_mixture: {weight: 0.3, orientation_alpha: 0.6, orientation_distribution: ggx}",
     "orientation_mixture: {weight: {fit: [0.02, 0.9], start: 0.08}, orientation_alpha: 0.6, orientation_distribution: ggx}",
     lambda p: p["orientation_mixture"]["weight"], 0.3),
], ids=["student_t-shape", "mixture-weight"])
def test_match_recovers_the_shape(tmp_path, true, fit, get, expect):
    (tmp_path / "true.yaml").write_text(BASE.replace("ORIENT", true))
    target = tmp_path / "target.csv"
    r = CliRunner().invoke(cli, ["compare", str(tmp_path / "true.yaml"), "--write-csv", str(target),
                                 "--geometries", "e2539"])
    assert r.exit_code == 0, r.output
    (tmp_path / "base.yaml").write_text(BASE.replace("ORIENT", fit))
    out = tmp_path / "out"
    r = CliRunner().invoke(cli, ["match", str(tmp_path / "base.yaml"), "--target", str(target), "--out", str(out)])
    assert r.exit_code == 0, r.output
    fitted = yaml.safe_load((out / "shape-fitted.yaml").read_text())
    assert get(fitted["layers"][1]["basecoat"]["particles"][0]) == pytest.approx(expect, rel=0.05)
