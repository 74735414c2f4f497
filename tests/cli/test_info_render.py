"""`flakedb info` for each file kind, `flakedb render` of a spectral .h5, the sheet and the tone curve,
and compose's progress on stderr (issue 15).

Guards against: info that dumps raw arrays or misses the key facts (paint, channels and colour space,
mirror term, energy/colour/convergence checks) for a .bsdf, an .h5 or a Mitsuba export; an export
not recognised by info; a render that refuses the spectral .h5 compose wrote; a preview that clips
(the demo paint: < 1 % of sphere pixels); a tone curve that is not Narkowicz's; a silent compose.
"""

import json
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from flakedb.cli.main import cli
from flakedb.render import look

RECIPES = Path(__file__).resolve().parents[2] / "flakedb" / "catalog" / "recipes"


@pytest.fixture(scope="module")
def yellow(tmp_path_factory):
    out = tmp_path_factory.mktemp("yellow")
    r = CliRunner().invoke(cli, ["compose", str(RECIPES / "particle-cadmium-yellow.yaml"), "--n", "16",
                                 "--out", str(out)])
    assert r.exit_code == 0, r.output
    return out, r


def test_compose_prints_stages_and_warnings_on_stderr(yellow):
    _, r = yellow
    err = r.stderr if hasattr(r, "stderr") else r.output
    for stage in ("optics:", "projection: layer 1/1", "solve: layer 1/1", "write: done"):
        assert stage in err
    assert "warning: basecoat layer 1" in err
    assert "RGB file: linear sRGB" in r.stdout and "ΔE00" in r.stdout
    assert "flop index (X-Rite): 0 (reverse flop" in r.stdout


def test_info_bsdf_key_lines(yellow):
    out, _ = yellow
    r = CliRunner().invoke(cli, ["info", str(out / "particle-cadmium-yellow.bsdf")])
    assert r.exit_code == 0, r.output
    t = r.output
    assert "paint:         particle-cadmium-yellow" in t
    assert "linear sRGB" in t and "stored Y, R, B" in t
    assert "[ok  ] energy conserved" in t and "[ok  ] no negative channel" in t
    assert "gamut mapping desaturated" in t and "mirror reflection is NOT in the table" in t


def test_info_h5_key_lines_agree_with_compose(yellow):
    out, r0 = yellow
    r = CliRunner().invoke(cli, ["info", str(out / "particle-cadmium-yellow.h5")])
    assert r.exit_code == 0, r.output
    t = r.output
    assert "41 spectral bands 380-780 nm" in t and "full-precision result" in t
    assert "[warn] Fourier orders: 11 kept" in t or "Fourier orders:" in t
    # the warnings info states are the ones compose printed, word for word
    composed = [ln.split("warning: ", 1)[1] for ln in r0.stderr.splitlines() if "warning: " in ln]
    shown = [ln.split("warning: ", 1)[1] for ln in t.splitlines() if "warning: " in ln]
    assert composed and set(composed) == set(shown)
    assert "L*" in t and "b*" in t                          # albedo as a colour, not 41 numbers per row
    assert max(len(ln) for ln in t.splitlines()) < 300       # no wall of numbers
    d = json.loads(CliRunner().invoke(cli, ["info", "--json", str(out / "particle-cadmium-yellow.h5")]).output)
    assert d["kind"] == "h5" and {c["check"] for c in d["checks"]} >= {"energy", "colour", "solver"}


def test_info_mitsuba_export_is_recognised(yellow, tmp_path):
    out, _ = yellow
    r = CliRunner().invoke(cli, ["export-mitsuba", str(out / "particle-cadmium-yellow.bsdf"), "--res", "16",
                                 "--n-theta", "6"])
    assert r.exit_code == 0, r.output
    exported = out / "particle-cadmium-yellow.measured.tensor"
    assert exported.exists()
    r = CliRunner().invoke(cli, ["info", str(exported)])
    assert r.exit_code == 0, r.output
    assert "Mitsuba 3 `measured` tensor file" in r.output and "variant:       rgb" in r.output
    assert "[ok  ] no negative value" in r.output and "6 elevations" in r.output
    d = json.loads(CliRunner().invoke(cli, ["info", "--json", str(exported)]).output)
    assert d["kind"] == "mitsuba-measured" and d["resolution"] == [16, 16]


def test_render_accepts_the_spectral_h5_and_makes_a_sheet(yellow, tmp_path):
    out, _ = yellow
    # the .h5 and .bsdf of one paint would both write particle-cadmium-yellow.exr: refused (issue 25)
    r = CliRunner().invoke(cli, ["render", str(out / "particle-cadmium-yellow.h5"), str(out / "particle-cadmium-yellow.bsdf"),
                                 "--size", "24", "--spp", "4", "--out", str(tmp_path)])
    assert r.exit_code == 2 and "same file" in r.output and not list(tmp_path.iterdir()), r.output
    rgb = tmp_path / "in" / "yellow-rgb.bsdf"
    rgb.parent.mkdir()
    rgb.write_bytes((out / "particle-cadmium-yellow.bsdf").read_bytes())
    r = CliRunner().invoke(cli, ["render", str(out / "particle-cadmium-yellow.h5"), str(rgb),
                                 "--size", "24", "--spp", "4", "--out", str(tmp_path)])
    assert r.exit_code == 0, r.output
    assert (tmp_path / "sheet.png").exists() and "ACES filmic" in r.output
    from flakedb.render.imageio import read_exr
    a = read_exr(tmp_path / "particle-cadmium-yellow.exr")
    assert a.shape == (24, 24, 3)
    from PIL import Image
    with Image.open(tmp_path / "sheet.png") as im:
        assert im.size == (24 * 2 + 8, 24)


def test_filmic_curve_and_auto_exposure():
    x = np.array([0.0, 0.18, 1.0, look.FILMIC_WHITE, 100.0])
    y = look.aces_filmic(x)
    assert y[0] == 0 and y[-1] == 1 and y[3] == pytest.approx(1.0, abs=1e-12)
    assert y[1] == pytest.approx(0.18 * (2.51 * 0.18 + 0.03) / (0.18 * (2.43 * 0.18 + 0.59) + 0.14))
    assert np.all(np.diff(y) >= 0)
    img = np.full((4, 4, 3), 2.0)
    assert look.auto_exposure(img) * 2.0 == pytest.approx(look.KEY, rel=1e-3)


def test_softbox_studio_has_no_hard_horizon():
    env = look.softbox_studio()
    el = np.radians(np.linspace(-5, 5, 201))
    d = np.stack([np.zeros_like(el) + 0.0, np.sin(el), -np.cos(el)], axis=-1)      # behind the camera-less side
    L = env(d)[:, 1]
    assert np.abs(np.diff(L)).max() < 0.02                                        # smooth across 0°
    assert env(np.array([0.0, 1.0, 0.0]))[1] > 3 * env(np.array([0.0, -1.0, 0.0]))[1]


@pytest.mark.slow
def test_demo_paint_render_at_defaults_clips_under_one_percent(tmp_path):
    r = CliRunner().invoke(cli, ["compose", str(RECIPES / "tri-coat-pearl-white.yaml"), "--out", str(tmp_path),
                                 "--quiet"])
    assert r.exit_code == 0, r.output
    r = CliRunner().invoke(cli, ["render", str(tmp_path / "tri-coat-pearl-white.bsdf"), "--out", str(tmp_path)])
    assert r.exit_code == 0, r.output
    from PIL import Image

    from flakedb.render.imageio import read_exr
    from flakedb.render.preview import DEFAULT_EXTENT
    with Image.open(tmp_path / "tri-coat-pearl-white.png") as im:
        png = np.asarray(im)
    size = png.shape[0]
    c = (np.arange(size) + 0.5) / size * 2 * DEFAULT_EXTENT - DEFAULT_EXTENT
    inside = (c[None, :] ** 2 + c[:, None] ** 2) < 0.98
    clipped = np.any(png[inside] == 255, axis=-1).mean()
    assert clipped < 0.01
    assert read_exr(tmp_path / "tri-coat-pearl-white.exr").shape == (size, size, 3)


def test_info_dispatches_every_file_kind_of_the_registry(tmp_path):
    """Issue #34: the file-kind registry held magic bytes only and `flakedb info` dispatched kinds again (the
    glTF and USD files flakedb writes were recognised inside info, outside the registry).  Every kind of
    flakedb.bsdf.dispatch.FILE_KINDS has exactly one info route, and a file is described by its kind's route."""
    from flakedb.bsdf.dispatch import FILE_KINDS, file_kind
    from flakedb.cli import info as info_mod
    from flakedb.export import openpbr as op
    from flakedb.export.gltf import write_gltf
    from flakedb.export.usd import write_usda

    assert set(info_mod.INFO_ROUTES) == set(FILE_KINDS)
    fit = op.OpenPBRFit((0.5, 0.5, 0.5), 0.0, 0.5, 1.5, 0.0)
    write_usda(tmp_path / "x.usda", fit, "x")
    write_gltf(tmp_path / "x.glb", fit, "x")
    write_gltf(tmp_path / "x.gltf", fit, "x")
    for name, kind in (("x.usda", "usda"), ("x.glb", "glb"), ("x.gltf", "gltf")):
        assert file_kind(tmp_path / name) == kind
        d = info_mod.describe(tmp_path / name)
        assert d["kind"] in ("gltf", "usda"), d
