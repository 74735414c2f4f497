"""flakedb.process: the allocator and BLAS-thread settings the command line applies (and their opt-outs)."""

import ctypes.util
import platform

import pytest

from flakedb.process import BLAS_THREAD_VARIABLES, tune_allocator


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


def _blas_threads_of_a_command(tmp_path, **env_vars):
    """The BLAS thread count numpy got in a ``flakedb --version`` process (read by an atexit handler that
    imports numpy after the command ran), with ``env_vars`` added to an environment free of
    :data:`flakedb.process.BLAS_THREAD_VARIABLES`."""
    import os
    import subprocess
    import sys

    probe = tmp_path / "probe.py"
    probe.write_text("import atexit, sys\n"
                     "def report():\n"
                     "    import numpy  # noqa: F401\n"
                     "    from threadpoolctl import threadpool_info\n"
                     "    print('BLAS', max(i['num_threads'] for i in threadpool_info() if i['user_api'] == 'blas'))\n"
                     "atexit.register(report)\n"
                     "from flakedb.cli.main import main\nmain()\n")
    env = {k: v for k, v in os.environ.items() if k not in BLAS_THREAD_VARIABLES}
    env.update(env_vars)
    r = subprocess.run([sys.executable, str(probe), "--version"], capture_output=True, text=True, env=env,
                       timeout=120)
    assert r.returncode == 0, r.stderr
    return int(r.stdout.split("BLAS")[-1])


def test_the_command_line_runs_blas_on_one_thread(tmp_path):
    """flakedb.process.blas_one_thread, called first by main(): numpy's BLAS gets one thread (left at its
    default, OpenBLAS takes one per core and its spinning worker competed with the solve)."""
    assert _blas_threads_of_a_command(tmp_path) == 1


@pytest.mark.skipif((__import__("os").cpu_count() or 1) < 2, reason="OpenBLAS caps its threads at the cores")
def test_a_user_set_blas_thread_count_is_obeyed(tmp_path):
    assert _blas_threads_of_a_command(tmp_path, OPENBLAS_NUM_THREADS="2") == 2


@pytest.mark.skipif((__import__("os").cpu_count() or 1) < 2, reason="OpenBLAS caps its threads at the cores")
def test_omp_num_threads_caps_flakedb_and_the_blas_stays_at_one_thread(tmp_path):
    """OMP_NUM_THREADS alone is flakedb's thread cap (flakedb.process.available_threads); OpenBLAS, which would read
    it when its own variable is unset, still gets one thread, so its threads and flakedb's do not multiply."""
    assert _blas_threads_of_a_command(tmp_path, OMP_NUM_THREADS="2") == 1


def test_a_signal_inside_a_finaliser_is_held_not_printed(tmp_path):
    """A SIGTERM whose Terminated is raised inside a finaliser or weakref callback (CI: during a batch compare's
    clean-up, "Exception ignored in <function WeakValueDictionary...remove>" with a traceback, and the run went on)
    is held for the next kernel call's end, which raises it, and nothing is printed."""
    import subprocess
    import sys

    code = (
        "import signal, sys\n"
        "from flakedb.process import Terminated, install_signal_handlers\n"
        "from flakedb.interrupts import deferred\n"
        "install_signal_handlers()\n"
        "class Finalised:\n"
        "    def __del__(self):\n"
        "        raise Terminated(signal.SIGTERM)\n"
        "x = Finalised()\n"
        "del x\n"
        "print('went on after the finaliser')\n"
        "try:\n"
        "    with deferred():\n"
        "        pass\n"
        "except Terminated as e:\n"
        "    print('raised at the kernel call', e.signum == signal.SIGTERM)\n"
    )
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    assert "Exception ignored" not in r.stderr and "Traceback" not in r.stderr, r.stderr
    assert r.stdout.splitlines() == ["went on after the finaliser", "raised at the kernel call True"], r.stdout
