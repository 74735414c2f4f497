"""flakedb.process: the allocator setting the command line applies (and its opt-out)."""

import ctypes.util
import platform

import pytest

from flakedb.process import tune_allocator


def test_opt_out_leaves_the_allocator_alone(monkeypatch):
    monkeypatch.setenv("FLAKEDB_MALLOC_TUNING", "0")
    assert tune_allocator() is False


@pytest.mark.skipif(platform.system() != "Linux" or platform.libc_ver()[0] != "glibc", reason="glibc's mallopt")
def test_applied_on_glibc(monkeypatch):
    monkeypatch.delenv("FLAKEDB_MALLOC_TUNING", raising=False)
    assert ctypes.util.find_library("c")
    assert tune_allocator() is True


def test_fast_exit_keeps_every_line_and_file_and_every_failure_status(tmp_path):
    """flakedb.process.fast_exit ends a finished compose without the interpreter's teardown: what it printed
    to a pipe must all arrive (the last line is the timing line), its atexit handlers must run, its three files
    must be complete, and a failing command must keep its own status (the fast exit is for success only)."""
    import json
    import os
    import subprocess
    import sys

    from flakedb.bsdf import open_bsdf, read_h5
    from flakedb.resources import PACKAGE_DIR

    recipe = PACKAGE_DIR / "catalog" / "recipes" / "research-hg-slab.yaml"
    probe = tmp_path / "probe.py"  # an atexit handler registered before the command runs must still run
    probe.write_text("import atexit, sys\nmark = sys.argv.pop()\natexit.register(lambda: open(mark, 'w').write('ran'))\n"
                     "sys.argv = sys.argv[:1] + sys.argv[2:]\nfrom flakedb.cli.main import main\nmain()\n")
    mark = tmp_path / "atexit-ran"
    r = subprocess.run([sys.executable, str(probe), "x", "compose", str(recipe), "--out", str(tmp_path / "out"),
                        "--n", "16", str(mark)], capture_output=True, text=True, env=dict(os.environ), check=False)
    assert r.returncode == 0, r.stderr
    assert r.stdout.rstrip().splitlines()[-1].startswith("time: "), r.stdout[-300:]
    assert mark.read_text() == "ran"
    out = tmp_path / "out"
    assert open_bsdf(out / "research-hg-slab.bsdf").n_nodes > 0 and read_h5(out / "research-hg-slab.h5").n_channels >= 1
    assert json.loads((out / "research-hg-slab.json").read_text())["name"] == "research-hg-slab"
    bad = subprocess.run([sys.executable, "-m", "flakedb", "compose", str(recipe), "--out", str(tmp_path / "o2"),
                          "--n", "15"], capture_output=True, text=True, check=False)
    assert bad.returncode not in (0, None) and "--n" in bad.stderr + bad.stdout
