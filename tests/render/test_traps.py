"""Traps of issue #37 on the render side, each a test that failed on the code before the fix.

- The Mitsuba coated export's .json named its tensor by a bare file name: ``mi.load_dict`` resolves that
  against the working directory, so it loaded only from the tensor's own folder.
- The coated export's tensor holds the table at x2 (one half of a blendbsdf); `flakedb info` on it said
  'use {"type": "measured", "filename": ...}', which renders twice too bright.
- `flakedb render --sparkle a.yaml --sparkle b.yaml` failed for the whole sheet when one recipe had no flakes.
- `flakedb texture` on a .bsdf said "not UTF-8 text" instead of asking for the recipe.
"""

import json

import numpy as np
import pytest
from click.testing import CliRunner

from flakedb.bsdf import open_bsdf, write_bsdf
from flakedb.cli.main import cli
from flakedb.render import mitsuba as fm
from flakedb.render.imageio import read_exr
from flakedb.resources import RECIPES_DIR
from tests.render.test_mitsuba import synthetic_table
from tests.render.test_preview import _lambertian


@pytest.fixture(scope="module")
def coated(tmp_path_factory):
    d = tmp_path_factory.mktemp("coated")
    write_bsdf(d / "paint.bsdf", synthetic_table(h=12))
    s = fm.export_coated(d / "paint.bsdf", d / "paint.measured.tensor", res=16, n_theta=6)
    return d, s


def test_coated_json_loads_from_another_directory(coated, tmp_path, monkeypatch):
    mi = pytest.importorskip("mitsuba")
    mi.set_variant("scalar_rgb")
    d, s = coated
    bsdf = json.loads((d / "paint.measured.tensor.json").read_text())
    monkeypatch.chdir(tmp_path)                      # anywhere but the tensor's folder
    loaded = mi.load_dict(bsdf)                      # failed: "paint.measured.tensor" not found
    si = mi.SurfaceInteraction3f()
    si.wi = mi.Vector3f(0.0, 0.0, 1.0)
    value = loaded.eval(mi.BSDFContext(), si, mi.Vector3f(0.3, 0.0, np.sqrt(1 - 0.09)))
    assert np.all(np.array(value) > 0)
    assert 'value="' + str((d / "paint.measured.tensor").resolve()) + '"' in (d / "paint.measured.tensor.xml").read_text()


def test_info_on_the_doubled_tensor_says_to_use_the_blend(coated):
    d, s = coated
    assert s["bsdf"]["type"] == "blendbsdf"
    r = CliRunner().invoke(cli, ["info", str(d / "paint.measured.tensor")])
    assert r.exit_code == 0, r.output
    assert '{"type": "measured"' not in r.output                    # the old advice: twice too bright
    assert "NOT alone" in r.output and "x2" in r.output and "paint.measured.tensor.json" in r.output
    js = json.loads(CliRunner().invoke(cli, ["info", "--json", str(d / "paint.measured.tensor")]).output)
    assert js["scale"] == 2.0 and js["use"]["json_present"]
    # a bare export (--no-coat) is at x1 and may be used alone
    fm.export_measured(d / "paint.bsdf", d / "bare.tensor", res=16, n_theta=6)
    js = json.loads(CliRunner().invoke(cli, ["info", "--json", str(d / "bare.tensor")]).output)
    assert js["scale"] == 1.0 and js["use"]["type"] == "measured"


@pytest.mark.slow
def test_sparkle_sheet_with_a_flake_free_paint(tmp_path):
    """metallic silver's glints beside cadmium yellow (no flakes): both images, the flake-free one the
    smooth render under the same light (the sun on, as for every sparkle image of the run)."""
    _lambertian(tmp_path / "a.bsdf", albedo=(0.5, 0.5, 0.5))
    _lambertian(tmp_path / "b.bsdf", albedo=(0.6, 0.4, 0.1))
    r = CliRunner().invoke(cli, ["render", str(tmp_path / "a.bsdf"), str(tmp_path / "b.bsdf"), "--out",
                                 str(tmp_path / "o"), "--size", "32", "--sparkle",
                                 str(RECIPES_DIR / "metallic-silver.yaml"), "--sparkle",
                                 str(RECIPES_DIR / "particle-cadmium-yellow.yaml")])
    assert r.exit_code == 0, r.output
    assert "no flakes" in r.output
    smooth = CliRunner().invoke(cli, ["render", str(tmp_path / "b.bsdf"), "--out", str(tmp_path / "s"), "--size",
                                      "32", "--sun"])
    assert smooth.exit_code == 0, smooth.output
    np.testing.assert_array_equal(read_exr(tmp_path / "o" / "b-particle-cadmium-yellow.exr"),
                                  read_exr(tmp_path / "s" / "b.exr"))
    assert (tmp_path / "o" / "a-metallic-silver.exr").exists() and (tmp_path / "o" / "sheet.png").exists()
    # one flake-free recipe for all files: still refused (nothing at all to draw)
    r = CliRunner().invoke(cli, ["render", str(tmp_path / "a.bsdf"), "--out", str(tmp_path / "x"), "--size", "16",
                                 "--sparkle", str(RECIPES_DIR / "particle-cadmium-yellow.yaml")])
    assert r.exit_code != 0 and "no flakes" in r.output


def test_texture_on_a_bsdf_asks_for_the_recipe(tmp_path):
    _lambertian(tmp_path / "paint.bsdf")
    r = CliRunner().invoke(cli, ["texture", str(tmp_path / "paint.bsdf")])
    assert r.exit_code != 0 and "Traceback" not in r.output
    assert "not UTF-8" not in r.output
    assert "not a recipe" in r.output and "YAML" in r.output
    assert open_bsdf(tmp_path / "paint.bsdf").n_channels == 3       # the file itself is fine
