"""Every command's failure path (issue 13): one line, exit status 2 for bad input and 1 otherwise,
no traceback unless --debug, no partial outputs, no empty directories the command created, limits
checked before any work with the limit in the message."""

import os
import subprocess
import sys
from pathlib import Path

import pytest
from click.testing import CliRunner

import flakedb.compose.orchestrate as orch
import flakedb.solve.pipeline as pipeline
from flakedb.cli.main import cli
from flakedb.render import mitsuba as fm
from flakedb.render import preview
from flakedb.store import versions as st
from tests.cases import small_mono_recipe

RECIPE = small_mono_recipe("fail-test")


def _recipe(tmp_path, text=RECIPE):
    p = tmp_path / "r.yaml"
    p.write_text(text)
    return p


def _run(args):
    return CliRunner().invoke(cli, args)


def _no_work(monkeypatch):
    """Make the heavy work fail loudly: a refusal must come before it."""
    def work(*a, **k):
        raise AssertionError("the work started before the input was refused")

    for mod, name in ((pipeline, "build_paint"), (pipeline, "solve_paint"), (preview, "render_sphere"),
                      (fm, "measured_tensors"), (st, "write_template")):
        monkeypatch.setattr(mod, name, work)


@pytest.fixture()
def no_work(monkeypatch):
    _no_work(monkeypatch)


def _clean(r, code):
    assert r.exit_code == code, r.output
    assert "Traceback" not in r.output
    assert r.output.startswith("Error: ") or "\nError: " in r.output


def test_failed_compose_leaves_no_directory_it_created(tmp_path, monkeypatch):
    def broken(*a, **k):
        raise RuntimeError("solver exploded")

    monkeypatch.setattr(pipeline, "solve_paint", broken)
    out = tmp_path / "a" / "b" / "out"
    r = _run(["compose", str(_recipe(tmp_path)), "--out", str(out)])
    _clean(r, 1)
    assert "internal error: RuntimeError: solver exploded" in r.output and "--debug" in r.output
    assert not (tmp_path / "a").exists()
    r = _run(["--debug", "compose", str(_recipe(tmp_path)), "--out", str(out)])
    assert isinstance(r.exception, RuntimeError)


def test_failed_compose_keeps_an_existing_directory_and_its_files(tmp_path, monkeypatch):
    out = tmp_path / "out"
    out.mkdir()
    (out / "keep.txt").write_text("x")
    monkeypatch.setattr(pipeline, "solve_paint", lambda *a, **k: (_ for _ in ()).throw(MemoryError()))
    r = _run(["compose", str(_recipe(tmp_path)), "--out", str(out)])
    _clean(r, 1)
    assert "out of memory" in r.output
    assert sorted(p.name for p in out.iterdir()) == ["keep.txt"]


@pytest.mark.parametrize("cmd", ["compose", "render", "export-mitsuba"])
def test_unwritable_output_refused_before_the_work(tmp_path, cmd, monkeypatch):
    target = "/proc/flakedb-nope/out"
    if cmd == "compose":
        _no_work(monkeypatch)
        args = ["compose", str(_recipe(tmp_path)), "--out", target]
    else:
        src = tmp_path / "o"
        r = _run(["compose", str(_recipe(tmp_path)), "--out", str(src)])
        assert r.exit_code == 0, r.output
        f = str(src / "fail-test.bsdf")
        _no_work(monkeypatch)
        args = ["render", f, "--out", target, "--size", "512", "--spp", "64"] if cmd == "render" else \
            ["export-mitsuba", f, "--out", target + "/x.bsdf"]
    r = _run(args)
    _clean(r, 2)
    assert "cannot create files" in r.output


@pytest.mark.parametrize("args,words", [
    (["compose", "R", "--n", "100000"], ["--n 100000", "8 ≤ n ≤ 512"]),
    (["compose", "R", "--n", "0"], ["8 ≤ n ≤ 512"]),
    (["build", "--n", "100000", "--dry-run", "--store", "S"], ["--n 100000", "8 ≤ n ≤ 512"]),
    (["build", "--n", "0", "--dry-run", "--store", "S"], ["8 ≤ n ≤ 512", "the range compose accepts"]),
    (["export-mitsuba", "F", "--out", "O/x.bsdf", "--res", "100000"], ["--res 100000", "8 ≤ res ≤ 512"]),
    (["export-mitsuba", "F", "--out", "O/x.bsdf", "--res", "0"], ["--res 0", "8 ≤ res ≤ 512"]),
    (["export-mitsuba", "F", "--out", "O/x.bsdf", "--n-theta", "100000"], ["4 ≤ n_theta ≤ 256"]),
])
def test_size_limits_are_stated_before_the_work(tmp_path, args, words, no_work):
    subst = {"R": str(_recipe(tmp_path)), "S": str(tmp_path / "store"), "F": str(tmp_path / "missing.bsdf"),
             "O/x.bsdf": str(tmp_path / "O" / "x.bsdf")}
    r = _run([subst.get(a, a) for a in args])
    _clean(r, 2)
    for w in words:
        assert w in r.output, r.output
    assert not (tmp_path / "store").exists() and not (tmp_path / "O").exists()


@pytest.mark.parametrize("text,words", [
    (RECIPE.replace("name: fail-test", 'name: "fail-test\\n"'), ["name:", "U+000A"]),
    (RECIPE.replace("name: fail-test", "name: fail-test\nname: other"), ["duplicate key 'name'"]),
    (RECIPE.replace("albedo: 0.9", "albedo: .nan"), ["custom.albedo", "not a finite number"]),
    (RECIPE.replace("flakedb: 1", 'flakedb: "1"'), ["not the number 1"]),
    (RECIPE.replace("name: fail-test", "name: " + "x" * 100_000), ["at most 100"]),
])
def test_bad_recipes_exit_2_with_one_clear_line(tmp_path, text, words, no_work):
    out = tmp_path / "out"
    r = _run(["compose", str(_recipe(tmp_path, text)), "--out", str(out)])
    _clean(r, 2)
    for w in words:
        assert w in r.output
    assert len(r.output) < 600 and not out.exists()


def test_no_traceback_from_the_real_entry_point(tmp_path):
    env = {**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[2])}
    latest = tmp_path / "store" / "latest"
    latest.mkdir(parents=True)
    r = subprocess.run([sys.executable, "-m", "flakedb", "verify", str(tmp_path / "store")], capture_output=True,
                       text=True, env=env, timeout=120)
    assert r.returncode == 1 and "Traceback" not in r.stderr and "latest" in r.stderr
