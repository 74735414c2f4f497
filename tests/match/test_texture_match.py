"""Matching with texture (issue #22 item 6): texture columns in targets, `compare` beside ΔE00, `match` fitting
flake size and loading to colour and sparkle together (flakedb.match.texture, docs/colour-matching.md "Texture").

Guards against: texture columns misread (a value per panel given on several rows, out-of-range values, the
wrong column order after the texture columns are taken out); compare reporting something other than the texture
model's numbers, or passing a recipe whose sparkle is off; a pigment-only paint silently compared as if it
sparkled; a fit whose texture residual is missing or wrong (the flake diameter does not enter the mean BSDF,
docs/texture.md §6, so only the texture can determine it: without the residual the diameter stays where it
started); texture tolerances that do not count in "reached".
"""

import json

import numpy as np
import pytest
import yaml

from flakedb.match.fit import match, predict, recipe_from_doc
from flakedb.match.targets import (
    E2194_GEOMETRIES,
    TargetError,
    format_target,
    read_target,
)
from flakedb.match.texture import (
    DEFAULT_TEXTURE_TOLERANCE,
    predict_texture,
    texture_tolerances,
)
from flakedb.paint.texture_inputs import texture_report
from flakedb.resources import RECIPES_DIR
from flakedb.texture.instruments import PRESETS
from tests.cases import basecoat_recipe, run_cli

BASE = basecoat_recipe("tex-match", ["{species: metallic, volume_fraction: VF, orientation_alpha: 0.2, diameter_um: DM}",
                                      "{species: cadmium-yellow, volume_fraction: 0.01}"], resolution=12)
TRUE_VF, TRUE_DM = 0.03, 24.0
COLUMNS = ["sparkle_area_15", "sparkle_area_45", "sparkle_intensity_15", "sparkle_intensity_45", "graininess"]


def _text(vf, dm):
    return BASE.replace("VF", str(vf)).replace("DM", str(dm))


@pytest.fixture(scope="module")
def truth():
    """The true recipe's prediction and texture columns, and the target text with and without them."""
    rec = recipe_from_doc(yaml.safe_load(_text(TRUE_VF, TRUE_DM)))
    pred = predict(rec, E2194_GEOMETRIES)
    tex, _ = predict_texture(rec, COLUMNS, ground=pred.ground)
    colour = format_target(pred.geometries, reflectance=pred.rf, wavelength_nm=pred.wavelength_nm, name="true")
    both = format_target(pred.geometries, reflectance=pred.rf, wavelength_nm=pred.wavelength_nm, name="true",
                         texture=tex)
    return {"prediction": pred, "texture": tex, "colour": colour, "both": both}


def test_texture_columns_read_write(truth):
    """The writer's columns come back (values to the 9 digits written, colour unchanged); a value given once or
    repeated is the panel's; bad values, disagreeing rows, unknown observers are refused naming the column."""
    t = read_target(truth["both"])
    assert list(t.texture) == COLUMNS and t.texture_observer == "byk-mac-like"
    for k, v in truth["texture"].items():
        assert t.texture[k] == pytest.approx(v, rel=1e-8)                  # %.9g
    assert np.array_equal(t.reflectance, read_target(truth["colour"]).reflectance)  # columns not shifted
    assert read_target(truth["colour"]).texture == {}
    head = "illumination_deg,aspecular_deg,L*,a*,b*,sparkle_area_15,graininess\n"
    t2 = read_target(head + "45,15,50,0,0,0.002,\n45,45,40,0,0,0.002,0.8\n")
    assert t2.texture == {"sparkle_area_15": 0.002, "graininess": 0.8} and t2.lab.tolist() == [[50, 0, 0], [40, 0, 0]]
    for text, msg in [(head + "45,15,50,0,0,0.002,0.8\n45,45,40,0,0,0.003,\n", "rows disagree"),
                      (head + "45,15,50,0,0,1.5,0.8\n", "at most 1"),
                      (head + "45,15,50,0,0,0.1,-1\n", ">= 0"),
                      (head + "45,15,50,0,0,0.1,\n", "graininess has no value"),
                      (head.replace("_15", "_89") + "45,15,50,0,0,0.1,1\n", "[0, 89)"),
                      ("# texture_observer: eagle\n" + head + "45,15,50,0,0,0.1,1\n", "texture_observer")]:
        with pytest.raises(TargetError, match=msg.replace("[", r"\[").replace(")", r"\)")):
            read_target(text)


def test_compare_reports_texture_beside_de(tmp_path):
    """A target written by `compare --write-csv --with-texture` from a 24 µm recipe: the same recipe passes with
    every difference 0; a 12 µm one has the same colour (ΔE00 0: the diameter does not enter the mean BSDF) but
    fails on texture, with the texture model's own numbers (= `flakedb texture`'s) as the prediction, more and
    fainter glints (smaller flakes); --table writes the rows beside the table; a pigment-only paint says it
    predicts zero sparkle."""
    (tmp_path / "big.yaml").write_text(_text(TRUE_VF, TRUE_DM))
    (tmp_path / "small.yaml").write_text(_text(TRUE_VF, 12))
    tgt = tmp_path / "t.csv"
    r = run_cli(["compare", tmp_path / "big.yaml", "--write-csv", tgt, "--with-texture"])
    assert r.exit_code == 0 and "with texture columns" in r.output, r.output
    t = read_target(tgt)
    assert len(t.texture) == 10
    r = run_cli(["compare", tmp_path / "big.yaml", "--target", tgt])
    assert r.exit_code == 0 and "texture pass" in r.output, r.output
    r = run_cli(["compare", tmp_path / "small.yaml", "--target", tgt, "--table", tmp_path / "tab.csv"])
    assert r.exit_code == 1 and "CIEDE2000 per-angle limits: pass; texture FAIL" in r.output, r.output
    rows = {ln.split()[0]: ln.split() for ln in r.output.splitlines() if ln.split() and ln.split()[0] in t.texture}
    assert set(rows) == set(t.texture)
    small = recipe_from_doc(yaml.safe_load(_text(TRUE_VF, 12)))
    rep = texture_report(small, [PRESETS["byk-mac-like"]])["observers"][0]["directional"]
    for k, row in enumerate(rep):
        a = f"{row['light_deg']:g}"
        pred, target, diff = (float(x) for x in rows[f"sparkle_area_{a}"][1:4])
        assert pred == pytest.approx(row["sparkle_area_fraction"], rel=1e-3)             # printed to 4 digits
        assert target == pytest.approx(t.texture[f"sparkle_area_{a}"], rel=1e-3)
        assert diff == pytest.approx(row["sparkle_area_fraction"] - t.texture[f"sparkle_area_{a}"], rel=1e-3)
        assert float(rows[f"glints_per_mm2_{a}"][3]) > 0 and float(rows[f"sparkle_intensity_{a}"][3]) < 0
    tab = (tmp_path / "tab-texture.csv").read_text().splitlines()
    assert tab[0].startswith("recipe,target,index,unit,predicted,target_value,difference,tolerance,passed")
    assert len(tab) == 11 and sum(ln.endswith("False") for ln in tab) >= 9
    (tmp_path / "small2.yaml").write_text(_text(TRUE_VF, 12).replace("name: tex-match", "name: small"))
    r = run_cli(["compare", tmp_path / "big.yaml", tmp_path / "small2.yaml", "--target", tgt, "--table",
                 tmp_path / "batch.csv"])                                   # a batch: one summary row per pair
    assert r.exit_code == 1 and "1 of 2 pair(s) pass" in r.output, r.output
    assert " 10 ok  yes" in r.output and "10/10 NO  NO" in r.output, r.output
    assert len((tmp_path / "batch-texture.csv").read_text().splitlines()) == 21
    for args, msg in ((["--with-texture"], "give --write-csv"), (["--texture-tolerance", "0"], "finite number > 0")):
        r = run_cli(["compare", tmp_path / "big.yaml", "--target", tgt] + args)
        assert r.exit_code == 2 and msg in r.output, r.output
    r = run_cli(["compare", RECIPES_DIR / "particle-cadmium-yellow.yaml", "--target", tgt])
    assert r.exit_code == 1 and "zero sparkle and graininess predicted" in r.output, r.output
    assert all(float(rows[1]) == 0.0 for rows in (ln.split() for ln in r.output.splitlines())
               if rows and rows[0] in t.texture)


@pytest.mark.slow
def test_match_fits_diameter_and_loading_to_colour_and_sparkle(truth):
    """Loading and diameter free, started at 1/3 and 1/2 of the truth.  With the texture columns both are
    recovered: the fit stops when every ΔE00 ≤ 0.01 and every index is within 1 % of its 10 % tolerance (0.1 %
    relative), and sparkle intensity moves as D^2.4 here (12 → 24 µm: 250 → 1308), so D is within ~0.05 %;
    asked to 0.5 %.  Colour alone recovers the loading but leaves the diameter at its start, exactly (its
    sensitivities are 0: degenerate), and says the diameter is not determined."""
    doc = yaml.safe_load(_text("{fit: [0.005, 0.1], start: 0.01}", "{fit: [8, 60], start: 12}"))
    res = match(doc, read_target(truth["both"]))
    assert res.reached and not res.undetermined, res.outcome
    vf, dm = res.values
    assert vf == pytest.approx(TRUE_VF, rel=5e-3) and dm == pytest.approx(TRUE_DM, rel=5e-3)
    assert all(abs(r["residual"]) <= 0.01 for r in res.texture_fit) and res.de_fit.max() <= 0.01
    assert all(abs(r["residual"]) > 1 for r in res.texture_start)             # the start really was off in texture
    colour_only = match(doc, read_target(truth["colour"]))
    assert colour_only.reached and colour_only.values[0] == pytest.approx(TRUE_VF, rel=5e-3)
    assert colour_only.values[1] == 12.0 and np.all(colour_only.sensitivities[:, :, 1] == 0.0)
    assert colour_only.undetermined == ["layers[1].basecoat.particles[0].diameter_um"]
    assert "not determined" in colour_only.outcome


@pytest.mark.slow
def test_texture_counts_in_reached(tmp_path, truth):
    """The diameter bounded to [8, 14] µm (truth 24): the sparkle cannot be matched; `match` says which texture
    indices fail and that the diameter is at its upper bound, and exits 1 (the colour alone could be matched;
    the compromise the weights choose raises the loading instead, docs/colour-matching.md "Texture")."""
    (tmp_path / "t.csv").write_text(truth["both"])
    (tmp_path / "base.yaml").write_text(_text("{fit: [0.005, 0.1], start: 0.02}", "{fit: [8, 14]}"))
    out = tmp_path / "out"
    r = run_cli(["match", tmp_path / "base.yaml", "--target", tmp_path / "t.csv", "--out", out,
                 "--max-evaluations", "12"], bound=120)
    assert r.exit_code == 1, r.output
    last = r.output.strip().splitlines()[-1]
    assert last.startswith("target NOT reached") and "texture indices outside tolerance" in last, last
    assert "diameter_um at its upper bound 14" in last, last
    rep = json.loads((out / "tex-match-match.json").read_text())
    assert rep["texture"]["passed"] is False and rep["reached"] is False
    tol = texture_tolerances(read_target(truth["both"]).texture, DEFAULT_TEXTURE_TOLERANCE)
    assert [r["tolerance"] for r in rep["texture"]["indices"]] == pytest.approx(list(tol.values()))
    assert read_target(out / "tex-match-prediction.csv").texture.keys() == set(COLUMNS)
