"""`flakedb texture`: the table, --json, a pigment-only paint, a wrong custom observer (one line, exit 2)."""

import json
from pathlib import Path

from click.testing import CliRunner

from flakedb.cli.main import cli
from flakedb.resources import PACKAGE_DIR

RECIPES = Path(PACKAGE_DIR) / "catalog" / "recipes"


def test_texture_table_and_json():
    r = CliRunner().invoke(cli, ["texture", str(RECIPES / "metallic-silver.yaml"), "--observer", "byk-mac-like"])
    assert r.exit_code == 0, r.output
    assert "glints/mm²" in r.output and "graininess" in r.output and "byk-mac-like" in r.output
    r = CliRunner().invoke(cli, ["texture", str(RECIPES / "metallic-silver.yaml"), "--json"])
    rep = json.loads(r.output)
    assert rep["sparkle"] is True and {o["observer"] for o in rep["observers"]} == {"byk-mac-like", "person-1m", "person-3m"}
    rows = rep["observers"][0]["directional"]
    assert [x["light_deg"] for x in rows] == [15.0, 45.0, 75.0]
    assert all(x["glints_per_mm2"] > 0 and 0 < x["sparkle_area_fraction"] < 1 for x in rows)
    # fewer glints as the light moves away from the specular direction of a normal view
    assert rows[0]["glints_per_mm2"] > rows[1]["glints_per_mm2"] > rows[2]["glints_per_mm2"]


def test_pigment_only_and_bad_observer():
    r = CliRunner().invoke(cli, ["texture", str(RECIPES / "particle-titanium-white.yaml")])
    assert r.exit_code == 0 and "no flakes: no sparkle" in r.output
    r = CliRunner().invoke(cli, ["texture", str(RECIPES / "metallic-silver.yaml"), "--spot-um", "0"])
    assert r.exit_code == 2 and "--spot-um" in r.output and "0.1" in r.output and "Traceback" not in r.output
