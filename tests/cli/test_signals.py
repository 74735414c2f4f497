"""Fault injection (issue 25): a signal arrives while compose is writing its outputs.  SIGTERM and
SIGHUP clean up as SIGINT does: no temporary entry and no partial output is left in --out, the files
that were there are unchanged, and the exit status says which signal ended the run."""

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from flakedb.process import TERMINATING_SIGNALS, Terminated, install_signal_handlers
from tests.cases import small_mono_recipe

RECIPE = small_mono_recipe("sig-test")

#: Runs `flakedb compose` with the .h5 writer stalled after it wrote its (temporary) file: the .bsdf
#: and the .h5 are then half of a set in the staging directory when the signal comes.
SCRIPT = """
import os, signal, sys, time
# the tested signals at their defaults: a suite run under nohup, or as a background job of a
# non-interactive shell, hands SIGHUP / SIGINT down ignored, and compose keeps an ignored signal ignored
# (flakedb.process.install_signal_handlers), so the run would never end
signal.signal(signal.SIGTERM, signal.SIG_DFL)
signal.signal(signal.SIGHUP, signal.SIG_DFL)
signal.signal(signal.SIGINT, signal.default_int_handler)
import flakedb.bsdf as bf
real = bf.write_h5
def stalled(path, *a, **k):
    r = real(path, *a, **k)
    open(os.environ["FLAKEDB_TEST_MARK"], "w").write(str(path))
    time.sleep(120)
    return r
bf.write_h5 = stalled
from flakedb.cli.main import main
sys.argv = ["flakedb", "compose", sys.argv[1], "--out", sys.argv[2], "--quiet"]
main()
"""


def _interrupted_compose(tmp_path, sig):
    recipe = tmp_path / "r.yaml"
    recipe.write_text(RECIPE)
    out = tmp_path / "out"
    out.mkdir()
    (out / "sig-test.json").write_text("the previous colour report")
    (out / "notes.txt").write_text("the user's own file")
    mark = tmp_path / "mark"
    env = dict(os.environ, FLAKEDB_TEST_MARK=str(mark), PYTHONPATH=os.pathsep.join(sys.path))
    proc = subprocess.Popen([sys.executable, "-c", SCRIPT, str(recipe), str(out)], env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        t0 = time.monotonic()
        while not mark.exists():
            assert proc.poll() is None, proc.communicate()
            assert time.monotonic() - t0 < 120, "compose never reached the write"
            time.sleep(0.05)
        staged = Path(mark.read_text())
        assert staged.exists() and staged.parent.parent == out        # a partial set is on disk now
        proc.send_signal(sig)
        so, se = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    return proc.returncode, so + se, out


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGHUP, signal.SIGINT], ids=["TERM", "HUP", "INT"])
def test_a_signal_during_the_write_leaves_nothing(tmp_path, sig):
    code, text, out = _interrupted_compose(tmp_path, sig)
    assert "Traceback" not in text, text
    assert sorted(p.name for p in out.iterdir()) == ["notes.txt", "sig-test.json"], text
    assert (out / "sig-test.json").read_text() == "the previous colour report"
    if sig == signal.SIGINT:
        assert code == 1 and "Aborted" in text, text                    # click's Ctrl-C
    else:
        assert code == 128 + sig, text
        assert signal.Signals(sig).name in text and "temporary files removed" in text, text


def test_handlers_raise_terminated_in_the_main_thread():
    old = {s: signal.getsignal(s) for s in TERMINATING_SIGNALS}
    try:
        assert install_signal_handlers()
        with pytest.raises(Terminated) as ei:
            os.kill(os.getpid(), signal.SIGTERM)
            time.sleep(1)
        assert ei.value.signum == signal.SIGTERM and isinstance(ei.value, KeyboardInterrupt)
        # a second signal during the clean-up is ignored, not a second exception in the middle of it
        assert signal.getsignal(signal.SIGTERM) is signal.SIG_IGN
    finally:
        for s, h in old.items():
            signal.signal(s, h)


def test_an_ignored_sighup_stays_ignored():
    old = {s: signal.getsignal(s) for s in TERMINATING_SIGNALS}
    try:
        signal.signal(signal.SIGHUP, signal.SIG_IGN)        # what nohup does
        install_signal_handlers()
        assert signal.getsignal(signal.SIGHUP) is signal.SIG_IGN
    finally:
        for s, h in old.items():
            signal.signal(s, h)
