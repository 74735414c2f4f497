"""Hostile and faulty inputs of issue 38, through the commands: outputs of compare / match / export-openpbr
outside the output plan (a table overwritten by a figure, a target stem '..' writing above --out, --name
../escaped, two targets that get one figure name, a table written before the plot folder is refused),
physically impossible measurements accepted (R = -0.3, duplicate CxF ids, duplicate keys in ladders and
panels), files read with plain ``open`` (FIFO ladders hang), environment variables not parsed, and leftovers
of killed runs.  Each is refused with one line naming the file / option / field, before any work, and
nothing is written."""

import os
from pathlib import Path

import pytest

import flakedb.compose.orchestrate as orch
from flakedb.render import preview
from tests.cases import run_cli, small_mono_recipe

RECIPE = small_mono_recipe("good")
FIT_RECIPE = RECIPE.replace("albedo: 0.5}", "albedo: {fit: [0.2, 0.8]}}")
TARGET = "illumination_deg,aspecular_deg,L*,a*,b*\n45,15,80,5,60\n45,45,70,4,50\n"


@pytest.fixture()
def no_work(monkeypatch):
    def work(*a, **k):
        raise AssertionError("the work started before the input was refused")

    for mod, name in ((orch, "build_paint"), (orch, "solve_paint"), (preview, "render_sphere")):
        monkeypatch.setattr(mod, name, work)


def _clean(r, *words, codes=(2,)):
    assert r.exit_code in codes, r.output
    assert "Traceback" not in r.output and "internal error" not in r.output, r.output
    for w in words:
        assert w in r.output, r.output
    return r.output


def _files(d):
    return sorted(str(p.relative_to(d)) for p in Path(d).rglob("*"))


@pytest.fixture()
def paint(tmp_path):
    (tmp_path / "r.yaml").write_text(RECIPE)
    (tmp_path / "t.csv").write_text(TARGET)
    (tmp_path / "fit.yaml").write_text(FIT_RECIPE)
    return tmp_path


# --- 1. every output in the plan ---------------------------------------------------------------------
def test_compare_table_named_like_a_figure_is_refused_before_work(paint, no_work):
    figs = paint / "out" / "figs"
    figs.mkdir(parents=True)
    r = run_cli(["compare", paint / "r.yaml", "--target", paint / "t.csv", "--table", figs / "good--t.png",
                 "--plot", figs])
    _clean(r, "same file")
    assert _files(paint / "out") == ["figs"]


def test_compare_two_targets_with_one_figure_name_are_refused(paint, no_work):
    d = paint / "panels"
    d.mkdir()
    (d / "a b.csv").write_text(TARGET)
    (d / "a_b.csv").write_text(TARGET)
    r = run_cli(["compare", paint / "r.yaml", "--target", d, "--plot", paint / "figs", "--table", paint / "t.out.csv"])
    _clean(r, "good--a_b.png", "same file")
    assert not (paint / "figs").exists() and not (paint / "t.out.csv").exists()


def test_compare_plot_folder_under_a_file_refused_before_the_table(paint, no_work):
    (paint / "afile").write_text("the user's file")
    r = run_cli(["compare", paint / "r.yaml", "--target", paint / "t.csv", "--table", paint / "table.csv",
                 "--plot", paint / "afile" / "figs"])
    _clean(r, "--plot")
    assert not (paint / "table.csv").exists()


def test_compare_writes_table_and_figures_together(paint):
    r = run_cli(["compare", paint / "r.yaml", "--target", paint / "t.csv", "--table", paint / "o" / "table.csv",
                 "--plot", paint / "o" / "figs"], bound=120)
    _clean(r, codes=(0, 1))
    assert _files(paint / "o") == ["figs", "figs/good--t.png", "table.csv"]


def test_match_target_stem_dotdot_never_writes_above_out(paint, no_work):
    d = paint / "panels"
    d.mkdir()
    (d / "...csv").write_text(TARGET)
    (d / "b.csv").write_text(TARGET)
    out = paint / "work" / "fits"
    out.mkdir(parents=True)
    (paint / "work" / "good.json").write_text("the user's own file")
    r = run_cli(["match", paint / "fit.yaml", "--target", d, "--out", out])
    _clean(r, "'..'", "--target")
    assert _files(paint / "work") == ["fits", "good.json"]
    assert (paint / "work" / "good.json").read_text() == "the user's own file"


def test_a_target_name_with_a_newline_is_a_file_name(paint, no_work):
    weird = paint / "x\nillumination_deg,aspecular_deg,L*,a*,b*\n45,15,1,1,1\n.csv"
    weird.write_text(TARGET)
    r = run_cli(["compare", paint / "r.yaml", "--target", paint / "nothere\nillumination_deg,aspecular_deg,L*,a*,b*"
                 "\n45,15,1,1,1\n.csv"])
    _clean(r, "no such file")


@pytest.mark.parametrize("name", ["../escaped", "/tmp/abs", "a/b", "..", ""])
def test_export_openpbr_name_must_be_a_plain_file_name(tmp_path, name):
    src = tmp_path / "p.bsdf"
    src.write_bytes(b"not read")
    r = run_cli(["export-openpbr", src, "--out", tmp_path / "out", "--name", name])
    _clean(r, "--name")
    assert _files(tmp_path) == ["p.bsdf"]
