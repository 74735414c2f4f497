"""Recipe fitting (flakedb.match.fit) and the `compare` / `match` commands.

Guards against: {fit: …} fields that leak into recipe validation, are substituted at the wrong path,
or accept bad bounds; a recipe that is valid at the start but not at the bounds going unnoticed
until mid-fit; multi-angle evaluation that disagrees with the colour report at 45° or breaks BSDF
reciprocity at other illumination angles (the E2539 geometries); and, end to end, a fit that
does not recover known loadings from a target made by flakedb itself (the issue's round trip).
"""

import json

import numpy as np
import pytest
import yaml
from click.testing import CliRunner

from flakedb.cli.main import cli
from flakedb.match.fit import (
    find_fit_parameters,
    predict,
    recipe_from_doc,
    substitute,
)
from flakedb.match.targets import E2194_GEOMETRIES, read_target
from flakedb.paint.catalog import load_catalog
from flakedb.paint.recipe import RecipeError
from tests.cases import basecoat_recipe

BASE = basecoat_recipe("two-species", ["{species: metallic, volume_fraction: VF_METALLIC, orientation_alpha: 0.3}",
                                        "{species: cadmium-yellow, volume_fraction: VF_YELLOW}"])
TRUE = {"VF_METALLIC": 0.04, "VF_YELLOW": 0.02}


def _text(**subs):
    t = BASE
    for k, v in subs.items():
        t = t.replace(k, str(v))
    return t


@pytest.fixture(scope="module")
def catalog():
    return load_catalog(None)


def test_fit_parameters_and_substitution(catalog):
    doc = yaml.safe_load(_text(VF_METALLIC="{fit: [0.01, 0.16]}", VF_YELLOW="{fit: [0.0, 0.1], start: 0.03}"))
    ps = find_fit_parameters(doc)
    assert [p.name for p in ps] == ["layers[1].basecoat.particles[0].volume_fraction",
                                    "layers[1].basecoat.particles[1].volume_fraction"]
    assert ps[0].log and ps[0].start == pytest.approx(0.04)          # geometric mean of the bounds
    assert not ps[1].log and ps[1].start == 0.03                     # min = 0: linear
    concrete = substitute(doc, ps, [0.05, 0.01])
    assert doc["layers"][1]["basecoat"]["particles"][0]["volume_fraction"] == {"fit": [0.01, 0.16]}  # untouched
    rec = recipe_from_doc(concrete, catalog=catalog)
    assert [p.volume_fraction for _, p in rec.particles()] == [0.05, 0.01]
    with pytest.raises(RecipeError):                                 # the {fit: …} form is not a recipe
        recipe_from_doc(doc, catalog=catalog)


@pytest.mark.parametrize("field,msg", [
    ("{fit: [0.1, 0.01]}", "min < max"),
    ("{fit: [0.01]}", "min < max"),
    ("{fit: [0.01, 0.1], start: 0.5}", "start"),
    ("{fit: [0.01, 0.1], step: 2}", "unknown key"),
    ("{fit: [0.0, 0.1], scale: log}", "min > 0"),
])
def test_fit_field_errors(field, msg):
    doc = yaml.safe_load(_text(VF_METALLIC=field, VF_YELLOW=0.02))
    with pytest.raises(RecipeError, match=msg):
        find_fit_parameters(doc)


def test_match_refuses_recipe_invalid_at_bounds(catalog):
    from flakedb.match.fit import match
    from flakedb.match.targets import read_target

    doc = yaml.safe_load(_text(VF_METALLIC="{fit: [0.01, 1.5]}", VF_YELLOW=0.02))
    tgt = read_target("illumination_deg,aspecular_deg,L*,a*,b*\n45,15,50,0,0\n")
    with pytest.raises(RecipeError, match="upper bounds"):
        match(doc, tgt, catalog=catalog)


def test_multiangle_matches_report_and_reciprocity(catalog, tmp_path):
    from flakedb.compose.orchestrate import compose

    rec = recipe_from_doc(yaml.safe_load(_text(**TRUE)), catalog=catalog)
    res = compose(rec, tmp_path, catalog=catalog)
    rep = np.array([[r["L"], r["a"], r["b"]] for r in res.report["geometries"]])
    # 15as-45 (light at 15°, view 60° specular side) and 60as45 (light at 60°, view 15°) swap ω_i, ω_o
    geoms = list(E2194_GEOMETRIES) + [(15.0, -45.0), (60.0, 45.0), (15.0, 80.0), (65.0, 80.0)]
    pred = predict(rec, geoms, catalog=catalog)
    assert np.max(np.abs(pred.lab()[:6] - rep)) < 1e-9
    rf = pred.rf
    # reciprocity of f (air on both sides), to the table's interpolation error at n = 16 (measured:
    # 0.5 % of the peak value; a wrong azimuth or μ mapping changes these by tens of %)
    assert np.abs(rf[6] - rf[7]).max() < 0.01 * rf[6].max()
    assert np.abs(rf[8] - rf[9]).max() < 0.01 * rf[8].max()   # illuminator side: 15as80 (view −65°) vs 65as80 (view −15°)
    assert not np.allclose(rf[6], rf[8], rtol=2e-2)
    with pytest.raises(ValueError, match="detector"):
        predict(rec, [(65.0, -50.0)], catalog=catalog)


def test_round_trip_recovers_loadings(tmp_path):
    """The issue's done-when: a target made from known loadings; match from loadings off by 3×."""
    (tmp_path / "true.yaml").write_text(_text(**TRUE))
    target = tmp_path / "target.csv"
    r = CliRunner().invoke(cli, ["compare", str(tmp_path / "true.yaml"), "--write-csv", str(target),
                                 "--geometries", "e2539"])
    assert r.exit_code == 0, r.output
    assert read_target(target).spectral
    base = _text(VF_METALLIC="{fit: [0.005, 0.2], start: 0.12}", VF_YELLOW="{fit: [0.002, 0.1], start: 0.006667}")
    (tmp_path / "base.yaml").write_text(base)
    out = tmp_path / "out"
    r = CliRunner().invoke(cli, ["match", str(tmp_path / "base.yaml"), "--target", str(target), "--out", str(out)])
    assert r.exit_code == 0, r.output
    fitted = yaml.safe_load((out / "two-species-fitted.yaml").read_text())
    vf = [p["volume_fraction"] for p in fitted["layers"][1]["basecoat"]["particles"]]
    assert vf == pytest.approx([TRUE["VF_METALLIC"], TRUE["VF_YELLOW"]], rel=0.05)
    rep = json.loads((out / "two-species-match.json").read_text())
    assert max(g["dE00_fit"] for g in rep["geometries"]) <= 0.3
    assert min(g["dE00_start"] for g in rep["geometries"]) > 5.0     # the start really was far off
    for name in ("two-species.bsdf", "two-species.h5", "two-species.json"):
        assert (out / name).is_file()
    # the prediction is a target, and the fitted recipe passes `compare` against the original target
    assert read_target(out / "two-species-prediction.csv").spectral
    r = CliRunner().invoke(cli, ["compare", str(out / "two-species-fitted.yaml"), "--target", str(target),
                                 "--max-de", "0.3", "--metamerism", "A"])
    assert r.exit_code == 0 and "pass" in r.output, r.output
    r = CliRunner().invoke(cli, ["compare", str(tmp_path / "true.yaml").replace("true", "true"), "--target",
                                 str(out / "two-species-prediction.csv"), "--max-de", "0.3"])
    assert r.exit_code == 0, r.output


def test_compare_fails_outside_limits(tmp_path):
    (tmp_path / "r.yaml").write_text(_text(**TRUE))
    tgt = tmp_path / "t.csv"
    tgt.write_text("# observer: 2\n# illuminant: D65\nillumination_deg,aspecular_deg,L*,a*,b*\n45,15,50,0,0\n45,110,20,0,0\n")
    r = CliRunner().invoke(cli, ["compare", str(tmp_path / "r.yaml"), "--target", str(tgt)])
    assert r.exit_code == 1 and "FAIL at 2 geometries" in r.output, r.output
    r = CliRunner().invoke(cli, ["compare", str(tmp_path / "r.yaml"), "--target", str(tgt), "--observer", "10"])
    assert r.exit_code == 2 and "needs spectral" in r.output, r.output


def test_match_composes_through_composes_checks(catalog, monkeypatch):
    """match predicts through compose's own path (issue #21): compose's physical check refuses for it too, and the
    solve gets compose's threads (a second orchestration had skipped both)."""
    from flakedb.solve import pipeline as orchestrate

    rec = recipe_from_doc(yaml.safe_load(_text(**TRUE)), catalog=catalog)
    seen = {}
    real_solve = orchestrate.solve_paint

    def spy(paint, n, **settings):
        seen.update(settings)
        return real_solve(paint, n, **settings)

    monkeypatch.setattr(orchestrate, "solve_paint", spy)
    predict(rec, E2194_GEOMETRIES, catalog=catalog)
    assert seen.get("threads", 1) >= 1 and "memory_budget_bytes" in seen
    monkeypatch.setattr(orchestrate, "check_physical", lambda stack: ["negative BSDF (planted)"])
    with pytest.raises(orchestrate.UnphysicalResultError, match="planted"):
        predict(rec, E2194_GEOMETRIES, catalog=catalog)


def test_rgb_base_against_spectral_target_same_rule_in_compare_and_match(tmp_path):
    """Issue #34: the colour-condition rule (the caller's, else the target's, else the defaults; a spectral target
    gives way to an RGB paint's D65/2°) lives once (flakedb.colour.settings.for_target).  compare accepted an
    RGB-mode recipe against a spectral D65/10° target while match refused the same base ("an RGB-mode paint has
    colours under D65/2° only")."""
    (tmp_path / "true.yaml").write_text(_text(**TRUE))
    target = tmp_path / "target.csv"
    r = CliRunner().invoke(cli, ["compare", str(tmp_path / "true.yaml"), "--write-csv", str(target)])
    assert r.exit_code == 0, r.output
    assert read_target(target).spectral and read_target(target).observer == "10"
    rgb = _text(**TRUE).replace("{mode: spectral, range_nm: [400, 700], step_nm: 20}", "{mode: rgb}")
    (tmp_path / "rgb.yaml").write_text(rgb)
    r = CliRunner().invoke(cli, ["compare", str(tmp_path / "rgb.yaml"), "--target", str(target), "--max-de", "50"])
    assert r.exit_code == 0 and "2° observer" in r.output, r.output
    base = rgb.replace("volume_fraction: 0.02", "volume_fraction: {fit: [0.01, 0.04], start: 0.02}")
    (tmp_path / "base.yaml").write_text(base)
    r = CliRunner().invoke(cli, ["match", str(tmp_path / "base.yaml"), "--target", str(target),
                                 "--out", str(tmp_path / "fit"), "--max-de", "50"])
    assert "D65/2° only" not in r.output and r.exit_code == 0, r.output
