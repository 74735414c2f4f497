"""The output plan (issue 25): every command resolves its outputs before any work and refuses, exit
status 2 with nothing changed on disk, an output that is an input, two outputs that are one file, a
path where a file name "in --out" is asked for, and a name taken by a directory; outputs land
together or not at all; stale temporary entries of a killed run are removed (only ours, only old)."""

import hashlib
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

import flakedb.compose.orchestrate as orch
import flakedb.solve.pipeline as pipeline
from flakedb import outputs
from flakedb.bsdf.fourier_file import write_bsdf
from flakedb.bsdf.h5file import write_h5
from flakedb.bsdf.table import BSDFTable
from flakedb.cli.main import cli
from flakedb.match import fit as cm
from flakedb.match.batch import texture_table_path
from flakedb.outputs import OutputError, OutputPlan, sweep_stale, temp_prefix
from flakedb.render import mitsuba as fm
from flakedb.render import preview
from flakedb.store import versions as st
from tests.cases import small_mono_recipe

RECIPE = small_mono_recipe("plan-test")

BASE = """\
flakedb: 1
name: plan-base
spectral: {mode: spectral, range_nm: [400, 700], step_nm: 20}
resolution: 16
layers:
  - clearcoat: {thickness_um: 40, ior: 1.5}
  - basecoat:
      thickness_um: 10
      ior: 1.5
      particles:
        - species: cadmium-yellow
          volume_fraction: {fit: [0.01, 0.1]}
  - primer: {albedo: 0.5}
"""

TARGET = """\
illumination_deg,aspecular_deg,L*,a*,b*
45,15,80,5,60
45,45,70,4,50
"""


def _run(args):
    return CliRunner().invoke(cli, [str(a) for a in args])


@pytest.fixture()
def no_work(monkeypatch):
    """The heavy work fails loudly: a refusal must come before it."""
    def work(*a, **k):
        raise AssertionError("the work started before the output plan was refused")

    for mod, name in ((pipeline, "build_paint"), (pipeline, "solve_paint"), (preview, "render_sphere"),
                      (fm, "measured_tensors"), (fm, "export_measured"), (st, "write_template"),
                      (cm, "match"), (cm, "predict")):
        monkeypatch.setattr(mod, name, work)
    import flakedb.cli.compare as cmp
    monkeypatch.setattr(cmp, "predict", work)


def _snapshot(d):
    """Every path under ``d`` with the sha256 of its bytes (directories as None)."""
    out = {}
    for p in sorted(Path(d).rglob("*")):
        out[str(p.relative_to(d))] = None if p.is_dir() else hashlib.sha256(p.read_bytes()).hexdigest()
    return out


def _refused(r, *words):
    assert r.exit_code == 2, r.output
    assert "Traceback" not in r.output and "internal error" not in r.output, r.output
    for w in words:
        assert w in r.output, r.output


def _table():
    x = np.array([0.2, 0.5, 0.8, 1.0])
    mu = np.concatenate([-x[::-1], x])
    c = np.zeros((1, mu.size, mu.size, 2))
    c[..., 0] = 0.05
    return BSDFTable(mu=mu, coeffs=c, eta=1.5)


@pytest.fixture()
def paint(tmp_path):
    d = tmp_path / "in"
    d.mkdir()
    write_bsdf(d / "p.bsdf", _table())
    write_h5(d / "p.h5", _table())
    return d


# --- the five data-loss cases -------------------------------------------------------------------
def test_export_mitsuba_onto_its_input_is_refused(paint, no_work):
    before = _snapshot(paint)
    _refused(_run(["export-mitsuba", paint / "p.bsdf", "--out", paint / "p.bsdf"]), "is the input FILE")
    # the same file by another spelling, and through a symlink
    _refused(_run(["export-mitsuba", paint / "p.bsdf", "--out", paint / ".." / "in" / "p.bsdf"]), "is the input")
    os.symlink(paint / "p.bsdf", paint.parent / "link.bsdf")
    _refused(_run(["export-mitsuba", paint / "p.bsdf", "--out", paint.parent / "link.bsdf"]), "is the input")
    os.link(paint / "p.bsdf", paint.parent / "hard.bsdf")
    _refused(_run(["export-mitsuba", paint / "p.bsdf", "--out", paint.parent / "hard.bsdf"]), "is the input")
    assert _snapshot(paint) == before


def test_compare_write_csv_onto_the_target_is_refused(tmp_path, no_work):
    (tmp_path / "r.yaml").write_text(RECIPE)
    (tmp_path / "t.csv").write_text(TARGET)
    before = _snapshot(tmp_path)
    _refused(_run(["compare", tmp_path / "r.yaml", "--target", tmp_path / "t.csv", "--write-csv", tmp_path / "t.csv"]),
             "--write-csv", "is the input --target")
    _refused(_run(["compare", tmp_path / "r.yaml", "--write-csv", tmp_path / "r.yaml"]), "is the input RECIPE")
    assert _snapshot(tmp_path) == before


def test_compare_table_onto_an_input_is_refused(tmp_path, no_work):
    """--table (and its texture companion) is planned like --write-csv, batch or not: never onto a target,
    a recipe, a --pairs list or a file it names, nor onto --write-csv."""
    (tmp_path / "r.yaml").write_text(RECIPE)
    (tmp_path / "r2.yaml").write_text(RECIPE.replace("plan-test", "plan-test-2"))
    (tmp_path / "t.csv").write_text(TARGET)
    (tmp_path / "pairs.csv").write_text("recipe,target\nr.yaml,t.csv\n")
    before = _snapshot(tmp_path)
    r, r2, t = tmp_path / "r.yaml", tmp_path / "r2.yaml", tmp_path / "t.csv"
    _refused(_run(["compare", r, "--target", t, "--table", t]), "--table", "is the input --target")
    _refused(_run(["compare", r, "--table", r]), "--table", "is the input RECIPE")
    _refused(_run(["compare", r, r2, "--target", t, "--table", t]), "is the input --target")        # a batch
    _refused(_run(["compare", "--pairs", tmp_path / "pairs.csv", "--table", t]), "is the input --target (--pairs)")
    _refused(_run(["compare", "--pairs", tmp_path / "pairs.csv", "--table", tmp_path / "pairs.csv"]),
             "is the input --pairs")
    _refused(_run(["compare", r, "--write-csv", tmp_path / "p.csv", "--table", tmp_path / "p.csv"]),
             "are the same file")
    # the texture rows go to NAME.texture.csv beside the table: that file is an output too
    tex = texture_table_path(tmp_path / "x.csv")
    tex.write_text(TARGET)
    before = _snapshot(tmp_path)
    _refused(_run(["compare", r, "--target", tex, "--table", tmp_path / "x.csv"]), "is the input --target")
    assert _snapshot(tmp_path) == before


def test_export_openpbr_onto_its_input_is_refused(paint, no_work, monkeypatch):
    """export-openpbr writes NAME.mtlx/.usda/.gltf/.glb/.blender.py: a BSDF file named like one of them is its
    input and is refused before the fit; nothing is written."""
    import flakedb.export.registry as reg

    def work(*a, **k):
        raise AssertionError("the fit started before the output plan was refused")

    monkeypatch.setattr(reg, "fit_openpbr", work)
    (paint / "p.glb").write_bytes((paint / "p.bsdf").read_bytes())   # a Fourier .bsdf that is called p.glb
    before = _snapshot(paint)
    _refused(_run(["export-openpbr", paint / "p.glb"]), "is the input FILE")
    assert _snapshot(paint) == before


def test_calibrate_never_writes_over_its_inputs(tmp_path, no_work, monkeypatch):
    """--out-catalog and --report are never the base catalogue (given or the default), the ladder or a panel's
    recipe or target, nor each other; refused before any fit."""
    import flakedb.cli.calibrate as ccal
    from flakedb.paint.catalog import default_catalog_path

    def work(*a, **k):
        raise AssertionError("the fit started before the output plan was refused")

    monkeypatch.setattr(ccal.cal, "calibrate", work)
    (tmp_path / "m.yaml").write_text(RECIPE)
    (tmp_path / "m.csv").write_text(TARGET)
    ladder = tmp_path / "ladder.yaml"
    ladder.write_text("species: cadmium-yellow\nname: cy-lab\npanels:\n  - {recipe: m.yaml, target: m.csv}\n")
    cat = tmp_path / "base.yaml"
    cat.write_bytes(default_catalog_path().read_bytes())
    shipped = hashlib.sha256(default_catalog_path().read_bytes()).hexdigest()
    before = _snapshot(tmp_path)
    _refused(_run(["calibrate", ladder, "--catalog", cat, "--out-catalog", cat]), "--out-catalog", "is the input --catalog")
    _refused(_run(["calibrate", ladder, "--out-catalog", default_catalog_path()]), "is the input --catalog")
    _refused(_run(["calibrate", ladder, "--out-catalog", ladder]), "is the input LADDER")
    _refused(_run(["calibrate", ladder, "--out-catalog", tmp_path / "u.yaml", "--report", tmp_path / "m.csv"]),
             "--report", "is the input panel")
    _refused(_run(["calibrate", ladder, "--out-catalog", tmp_path / "u.yaml", "--report", tmp_path / "u.yaml"]),
             "are the same file")
    assert _snapshot(tmp_path) == before
    assert hashlib.sha256(default_catalog_path().read_bytes()).hexdigest() == shipped


def test_match_never_writes_over_its_base(tmp_path, monkeypatch, no_work):
    (tmp_path / "t.csv").write_text(TARGET)
    # a base named like the fitted recipe it would write: refused before any work
    (tmp_path / "plan-base-fitted.yaml").write_text(BASE)
    before = _snapshot(tmp_path)
    _refused(_run(["match", tmp_path / "plan-base-fitted.yaml", "--target", tmp_path / "t.csv", "--out", tmp_path]),
             "is the input BASE")
    assert _snapshot(tmp_path) == before
    # the base where it lives, --out .: the plan passes (the fit starts), and the base is not an output
    (tmp_path / "plan-base-fitted.yaml").unlink()
    (tmp_path / "plan-base.yaml").write_text(BASE)
    before = _snapshot(tmp_path)
    monkeypatch.chdir(tmp_path)
    r = _run(["match", "plan-base.yaml", "--target", "t.csv", "--out", "."])
    assert r.exit_code == 1 and "the work started" in r.output, r.output   # got past the plan to the fit
    assert _snapshot(tmp_path) == before
    plan = orch.output_plan(".", "plan-base", [("plan-base.yaml", "BASE")])
    assert all(p.name != "plan-base.yaml" for p, _ in plan.outputs)


def test_render_two_files_of_one_paint_is_refused(paint, tmp_path, no_work):
    out = tmp_path / "out"
    _refused(_run(["render", paint / "p.bsdf", paint / "p.h5", "--out", out]), "p.exr", "same file")
    _refused(_run(["render", paint / "p.bsdf", paint / "p.bsdf", "--out", out]), "same file")
    assert not out.exists()


def test_compose_with_one_output_name_blocked_changes_nothing(tmp_path, no_work):
    (tmp_path / "r.yaml").write_text(RECIPE)
    out = tmp_path / "out"
    out.mkdir()
    (out / "plan-test.h5").write_text("old h5")
    (out / "plan-test.json").write_text("old json")
    (out / "plan-test.bsdf").mkdir()           # a directory where the .bsdf goes
    before = _snapshot(out)
    r = _run(["compose", tmp_path / "r.yaml", "--out", out])
    _refused(r, "plan-test.bsdf", "a directory is in its place")
    assert ".tmp" not in r.output             # the error names the real output, not a temporary path
    assert _snapshot(out) == before


def test_render_sheet_must_be_a_file_name_in_out(paint, tmp_path, no_work):
    out = tmp_path / "out"
    for bad in ("../x.png", "/tmp/x.png", "..", "sub/x.png"):
        _refused(_run(["render", paint / "p.bsdf", "--sheet", bad, "--out", out]), "--sheet", "plain file name")
    assert not out.exists() and not (tmp_path / "x.png").exists()


def test_outputs_land_together_or_not_at_all(tmp_path, monkeypatch):
    """A move that fails half-way puts back the files already moved: the old set stays whole."""
    out = tmp_path / "out"
    out.mkdir()
    for k in ("a", "b", "c"):
        (out / k).write_text(f"old {k}")
    plan = OutputPlan()
    for k in ("a", "b", "c"):
        plan.in_dir(out, k, "output")
    real = os.replace
    calls = []

    def flaky(src, dst):
        calls.append(dst)
        if Path(dst).name == "c" and ".tmp" not in str(dst):
            raise OSError(28, "No space left on device", str(dst))
        return real(src, dst)

    monkeypatch.setattr(os, "replace", flaky)
    with pytest.raises(OSError):
        with plan.check().staged() as stage:
            for k in ("a", "b", "c"):
                stage.path(out / k).write_text(f"new {k}")
    monkeypatch.setattr(os, "replace", real)
    assert {k: (out / k).read_text() for k in "abc"} == {"a": "old a", "b": "old b", "c": "old c"}
    assert sorted(p.name for p in out.iterdir()) == ["a", "b", "c"]   # no staging directory left
    # and a normal commit moves all three
    with plan.staged() as stage:
        for k in ("a", "b", "c"):
            stage.path(out / k).write_text(f"new {k}")
    assert {k: (out / k).read_text() for k in "abc"} == {"a": "new a", "b": "new b", "c": "new c"}


def test_plan_refusals_name_the_option(tmp_path):
    (tmp_path / "in.csv").write_text("x")
    p = OutputPlan()
    p.add_input(tmp_path / "in.csv", "--target")
    p.add_output(tmp_path / "in.csv", "--write-csv")
    with pytest.raises(OutputError, match="--write-csv .*is the input --target"):
        p.check()
    p = OutputPlan()
    p.add_output(tmp_path / "o", "--out")
    p.add_output(tmp_path / "." / "o", "--sheet")
    with pytest.raises(OutputError, match="are the same file"):
        p.check()
    fifo = tmp_path / "fifo"
    os.mkfifo(fifo)
    p = OutputPlan()
    p.add_output(fifo, "--write-csv")
    with pytest.raises(OutputError, match="special file"):
        p.check()


# --- stale temporary entries of a killed run ------------------------------------------------------
def _dead_pid():
    proc = subprocess.Popen([sys.executable, "-c", "pass"])
    proc.wait()
    return proc.pid


def test_sweep_removes_only_our_stale_entries(tmp_path):
    dead = _dead_pid()
    host = temp_prefix("x").split(outputs.TEMP_TAG + "-")[1].rsplit("-", 2)[0]
    ours_dead = tmp_path / f".paint.bsdf.{outputs.TEMP_TAG}-{host}-{dead}-abc123.tmp"
    ours_dead.mkdir()
    (ours_dead / "paint.bsdf").write_text("partial")
    ours_file = tmp_path / f".paint.json.{outputs.TEMP_TAG}-{host}-{dead}-q1w2e3.tmp.json"
    ours_file.write_text("partial")
    ours_alive = tmp_path / f".paint.h5.{outputs.TEMP_TAG}-{host}-{os.getppid()}-zzz.tmp"   # a running process
    ours_alive.mkdir()
    other_host_new = tmp_path / f".paint.png.{outputs.TEMP_TAG}-otherhost-{dead}-aa.tmp"
    other_host_new.write_text("someone else's, recent")
    other_host_old = tmp_path / f".paint.exr.{outputs.TEMP_TAG}-otherhost-{dead}-bb.tmp"
    other_host_old.write_text("someone else's, two days old")
    old = os.stat(other_host_old).st_mtime - 2 * 86400
    os.utime(other_host_old, (old, old))
    not_ours = tmp_path / ".paint.bsdf.abc123.tmp"   # the user's own, or another program's
    not_ours.write_text("keep")
    target = tmp_path / "elsewhere"
    target.mkdir()
    (target / "precious").write_text("keep")
    link = tmp_path / f".link.{outputs.TEMP_TAG}-{host}-{dead}-ll.tmp"
    link.symlink_to(target)
    removed = sweep_stale(tmp_path)
    assert sorted(removed) == sorted([ours_dead, ours_file, other_host_old, link])
    assert ours_alive.exists() and other_host_new.exists() and not_ours.exists()
    assert (target / "precious").read_text() == "keep"      # a link is removed, never followed


def test_next_run_removes_and_reports_what_a_killed_run_left(tmp_path, monkeypatch):
    out = tmp_path / "out"
    out.mkdir()
    host = temp_prefix("x").split(outputs.TEMP_TAG + "-")[1].rsplit("-", 2)[0]
    stale = out / f".plan-test.bsdf.{outputs.TEMP_TAG}-{host}-{_dead_pid()}-k9k9.tmp"
    stale.mkdir()
    (stale / "plan-test.bsdf").write_bytes(b"partial")
    (tmp_path / "r.yaml").write_text(RECIPE)
    r = _run(["compose", tmp_path / "r.yaml", "--out", out])
    assert r.exit_code == 0, r.output
    assert not stale.exists()
    assert f"removed {stale}" in r.output
    assert sorted(p.name for p in out.iterdir()) == ["plan-test.bsdf", "plan-test.h5", "plan-test.json"]


def test_temporary_names_carry_the_tag(tmp_path):
    from flakedb.atomic import temp_beside
    fd, tmp = temp_beside(tmp_path / "x.csv")
    os.close(fd)
    assert outputs._TEMP_RE.match(Path(tmp).name) and Path(tmp).name.startswith(".x.csv.")
