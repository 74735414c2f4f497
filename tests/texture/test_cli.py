"""`flakedb texture`: the table, --json, a pigment-only paint, a wrong custom observer (one line, exit 2), and one
number per paint: its report is compose's ``texture`` section (issue #36: metallic silver's graininess was 0.556
here and 0.695 in compose's JSON, the contrast at 15° 367 and 549: this command grounded the indices on the
flakes' own mean, compose on the BSDF)."""

import json
from pathlib import Path

from click.testing import CliRunner

from flakedb.cli.main import cli
from flakedb.resources import PACKAGE_DIR

RECIPES = Path(PACKAGE_DIR) / "catalog" / "recipes"


def test_texture_table_and_json():
    r = CliRunner().invoke(cli, ["texture", str(RECIPES / "metallic-silver.yaml"), "--observer", "byk-mac-like",
                                 "--flakes-only"])
    assert r.exit_code == 0, r.output
    assert "glints/mm²" in r.output and "graininess" in r.output and "byk-mac-like" in r.output
    r = CliRunner().invoke(cli, ["texture", str(RECIPES / "metallic-silver.yaml"), "--json", "--flakes-only"])
    rep = json.loads(r.output)
    assert rep["sparkle"] is True and {o["observer"] for o in rep["observers"]} == {"byk-mac-like", "person-1m", "person-3m"}
    rows = rep["observers"][0]["directional"]
    assert [x["light_deg"] for x in rows] == [15.0, 45.0, 75.0]
    assert all(x["glints_per_mm2"] > 0 and 0 < x["sparkle_area_fraction"] < 1 for x in rows)
    # fewer glints as the light moves away from the specular direction of a normal view
    assert rows[0]["glints_per_mm2"] > rows[1]["glints_per_mm2"] > rows[2]["glints_per_mm2"]


def test_pigment_only_and_bad_observer():
    r = CliRunner().invoke(cli, ["texture", str(RECIPES / "particle-titanium-white.yaml"), "--flakes-only"])
    assert r.exit_code == 0 and "no flakes: no sparkle" in r.output
    r = CliRunner().invoke(cli, ["texture", str(RECIPES / "metallic-silver.yaml"), "--spot-um", "0"])
    assert r.exit_code == 2 and "--spot-um" in r.output and "0.1" in r.output and "Traceback" not in r.output


def test_a_layer_beyond_the_models_crossing_sums_is_not_predicted_and_says_why(tmp_path):
    """A 5000 µm basecoat of pearlescent flakes at 19 %: a path crosses ~1 700 transmitting flakes, and the
    crossing-count sums asked for 153 GiB (a compose then failed with nothing written).  The texture report now
    says it predicts nothing and why (flakedb.texture.model.MAX_COMBINATIONS), and `flakedb texture` exits 0."""
    from flakedb.paint.recipe import parse_recipe
    from flakedb.paint.texture_inputs import texture_report
    from flakedb.texture.instruments import PRESETS

    text = ("flakedb: 1\nname: thick-pearl\nspectral: {mode: rgb}\nresolution: 16\nlayers:\n"
            "  - clearcoat: {thickness_um: 40, ior: 1.5, roughness: 0}\n"
            "  - basecoat: {thickness_um: 5000, ior: 1.5, particles: [{species: pearlescent, volume_fraction: 0.19}]}\n"
            "  - primer: {color: black}\n")
    rep = texture_report(parse_recipe(text), list(PRESETS.values()))
    assert rep["sparkle"] is False and rep["observers"] == []
    assert "not predicted" in rep["summary"] and "crossing combinations" in rep["summary"]
    (tmp_path / "r.yaml").write_text(text)
    res = CliRunner().invoke(cli, ["texture", str(tmp_path / "r.yaml"), "--flakes-only"])
    assert res.exit_code == 0, res.output
    assert "not predicted" in res.output


SMALL = """flakedb: 1
name: small-silver
spectral: {mode: spectral, range_nm: [400, 700], step_nm: 20}
resolution: 16
layers:
  - clearcoat: {thickness_um: 30, ior: 1.5, roughness: 0}
  - basecoat:
      thickness_um: 12
      ior: 1.5
      particles:
        - {species: metallic, volume_fraction: 0.06, orientation_alpha: 0.2}
  - primer: {color: gray}
"""


def test_texture_is_composes_texture_section(tmp_path):
    """One number per paint: `flakedb texture --json` prints exactly compose's JSON ``texture`` section (the same
    solve grounds both), and --flakes-only differs from it (its ground is the flakes' own mean), so the
    comparison can fail."""
    rec = tmp_path / "small-silver.yaml"
    rec.write_text(SMALL)
    r = CliRunner().invoke(cli, ["compose", str(rec), "--out", str(tmp_path / "out"), "--quiet"])
    assert r.exit_code == 0, r.output
    composed = json.loads((tmp_path / "out" / "small-silver.json").read_text())["texture"]
    r = CliRunner().invoke(cli, ["texture", str(rec), "--json"])
    assert r.exit_code == 0, r.output
    assert json.loads(r.output) == composed
    assert composed["observers"][0]["diffuse"]["ground"] == "bsdf"
    r = CliRunner().invoke(cli, ["texture", str(rec), "--json", "--flakes-only"])
    fast = json.loads(r.output)["observers"][0]["diffuse"]
    assert fast["ground"] == "flakes" and fast["graininess"] != composed["observers"][0]["diffuse"]["graininess"]
