"""Fault injection (issue 25): a signal arrives while compose is writing its outputs.  SIGTERM and
SIGHUP clean up as SIGINT does: no temporary entry and no partial output is left in --out, the files
that were there are unchanged, and the exit status says which signal ended the run."""

import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from flakedb.process import TERMINATING_SIGNALS, Terminated, install_signal_handlers
from tests.cases import basecoat_recipe, small_mono_recipe

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
    assert code == 128 + sig, text                                      # Ctrl-C too (issue 38): 130, not 1
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


# --- issue 38: signals while a compiled kernel runs, in match --------------------------------------------
def test_a_signal_inside_a_kernel_call_is_raised_when_the_call_returns():
    """The handler's exception is held while the main thread is inside a numba call (raised there it became
    "SystemError: CPUDispatcher(...) returned a result with an exception set", or a segmentation fault) and
    raised, as Terminated, when the call returns; outside a kernel call it is raised at once."""
    from flakedb.interrupts import deferred

    old = {s: signal.getsignal(s) for s in TERMINATING_SIGNALS}
    steps = []
    try:
        install_signal_handlers()
        with pytest.raises(Terminated) as ei:
            with deferred():
                os.kill(os.getpid(), signal.SIGTERM)
                time.sleep(0.2)                  # the handler has run by now, and held its exception
                steps.append("the kernel call returned")
        assert steps == ["the kernel call returned"] and ei.value.signum == signal.SIGTERM
    finally:
        for s, h in old.items():
            signal.signal(s, h)


def test_a_signal_reported_by_a_kernel_as_systemerror_exits_128_plus_signum(tmp_path, monkeypatch):
    import flakedb.solve.pipeline as orch
    from tests.cases import run_cli

    def kernel(*a, **k):
        try:
            raise Terminated(signal.SIGHUP)
        except Terminated as t:
            raise SystemError("CPUDispatcher(<function _scatter_kernel>) returned a result with an exception set") from t

    monkeypatch.setattr(orch, "solve_paint", kernel)
    (tmp_path / "r.yaml").write_text(RECIPE)
    r = run_cli(["compose", tmp_path / "r.yaml", "--out", tmp_path / "out"])
    assert r.exit_code == 128 + signal.SIGHUP, r.output
    assert "internal error" not in r.output and "SIGHUP" in r.output
    assert not (tmp_path / "out").exists() or not list((tmp_path / "out").iterdir())


MATCH_BASE = basecoat_recipe("sig-match", ["{species: cadmium-yellow, volume_fraction: {fit: [0.01, 0.2]}}"])
MATCH_TARGET = "illumination_deg,aspecular_deg,L*,a*,b*\n45,15,85,5,80\n45,45,80,4,75\n45,110,78,3,70\n"
MATCH_OUTPUTS = sorted(["sig-match-fitted.yaml", "sig-match-match.json", "sig-match-prediction.csv", "sig-match.bsdf",
                        "sig-match.h5", "sig-match.json"])


@pytest.mark.slow
def test_twenty_sigterms_at_random_moments_during_match(tmp_path):
    """issue 38's done-when: SIGTERM at 20 random moments of a running `flakedb match` (a cadmium yellow
    fitted by its Mie series: the compiled kernels run in every compose).  Before: 2 of 10 ended "internal
    error: SystemError: CPUDispatcher(_scatter_kernel)" (exit 1, which also means "target not reached") and
    3 of 20 in a segmentation fault.  Now every run ends 143 with nothing in --out and no temporary entry, or,
    when the signal came after the work, with the complete set of six files."""
    import random

    (tmp_path / "base.yaml").write_text(MATCH_BASE)
    (tmp_path / "t.csv").write_text(MATCH_TARGET)
    rng = random.Random(20261207)
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(sys.path))

    def match(out):
        return _flakedb_under_default_signals(["match", str(tmp_path / "base.yaml"), "--target", str(tmp_path / "t.csv"),
                                               "--out", str(out), "--max-evaluations", "3"])

    duration = _whole_run_seconds(match(tmp_path / "whole"), env)
    codes, interrupted = [], 0
    for k in range(20):
        out = tmp_path / f"out{k}"
        proc = subprocess.Popen(match(out), env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
        time.sleep(max(1.0, rng.uniform(0.2, 0.7) * duration))   # the first (measured) run is the slowest
        proc.send_signal(signal.SIGTERM)
        text, _ = proc.communicate(timeout=120)
        codes.append(proc.returncode)
        left = sorted(p.name for p in out.iterdir()) if out.exists() else []
        if proc.returncode == 143:   # nothing, or (the signal after the last file's rename) the whole set: never a part
            assert left in ([], MATCH_OUTPUTS), (k, left, text)
            interrupted += left == []
            assert "Traceback" not in text and "internal error" not in text, text
        else:   # finished before the signal: the whole set, and the fit's own exit status, or -SIGTERM when the
            # signal came after the work, once flakedb's handler was restored and the default one killed
            assert proc.returncode in (0, 1, -signal.SIGTERM) and left == MATCH_OUTPUTS, \
                (k, proc.returncode, left, text[-2000:])
    assert interrupted >= 12, (interrupted, codes)   # most signals landed inside the work, before any file


def _flakedb_under_default_signals(args) -> list:
    """A ``flakedb`` command line whose SIGTERM / SIGHUP start at the default action (as a shell's child)."""
    return [sys.executable, "-c", "import signal, sys; "
            "[signal.signal(s, signal.SIG_DFL) for s in (signal.SIGTERM, signal.SIGHUP)]; "
            "from flakedb.cli.main import main; sys.argv[0] = 'flakedb'; main()"] + list(args)


def _whole_run_seconds(cmd, env) -> float:
    """Wall seconds of one uninterrupted run of ``cmd`` on this machine now: the signal tests send their signals
    at fractions of it, so that they land inside the work however fast the command has become (fixed 1.5-4 s
    delays all came after a 2-3x faster calibrate)."""
    t0 = time.perf_counter()
    run = subprocess.run(cmd, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, timeout=600)
    assert run.returncode in (0, 1), run.stdout[-2000:]
    return time.perf_counter() - t0


CAL_LADDER = "species: cadmium-yellow\nname: cy-lab\npanels:\n  - {recipe: base.yaml, target: t.csv}\n"


@pytest.mark.slow
@pytest.mark.parametrize("command", ["calibrate", "compare-batch"])
def test_sigterm_during_calibrate_and_a_batch_compare(tmp_path, command):
    """issue 38: calibrate and batch compare end like match under SIGTERM: exit 143, nothing written, no
    temporary entry; or, when the signal came after the work, their complete outputs."""
    import random

    base = MATCH_BASE.replace("{fit: [0.01, 0.2]}", "0.1")
    (tmp_path / "base.yaml").write_text(base)
    (tmp_path / "b2.yaml").write_text(base.replace("name: sig-match", "name: sig-two"))
    (tmp_path / "t.csv").write_text(MATCH_TARGET)
    (tmp_path / "t2.csv").write_text(MATCH_TARGET)
    (tmp_path / "ladder.yaml").write_text(CAL_LADDER)
    out = tmp_path / "out"
    out.mkdir()
    if command == "calibrate":
        args = ["calibrate", str(tmp_path / "ladder.yaml"), "--out-catalog", str(out / "user.yaml"), "--report",
                str(out / "fit.json"), "--max-evaluations", "3"]
        complete = ["fit.json", "user.yaml"]
    else:
        args = ["compare", str(tmp_path / "base.yaml"), str(tmp_path / "b2.yaml"), "--target", str(tmp_path / "t.csv"),
                "--target", str(tmp_path / "t2.csv"), "--table", str(out / "table.csv"), "--plot", str(out / "figs")]
        complete = ["figs", "table.csv"]
    rng = random.Random(38 + len(command))
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(sys.path))
    launch = _flakedb_under_default_signals(args)
    duration = _whole_run_seconds(launch, env)
    codes, interrupted = [], 0
    for _ in range(3):
        for p in out.iterdir():
            shutil.rmtree(p) if p.is_dir() else p.unlink()
        proc = subprocess.Popen(launch, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
        time.sleep(max(1.0, rng.uniform(0.35, 0.8) * duration))
        proc.send_signal(signal.SIGTERM)
        text, _ = proc.communicate(timeout=120)
        codes.append(proc.returncode)
        left = sorted(p.name for p in out.iterdir())
        if proc.returncode == 143:   # nothing, or (the signal after the last file's rename) the whole set: never a part
            assert left in ([], complete), (left, text)
            interrupted += left == []
            assert "internal error" not in text and "Traceback" not in text, text
        else:   # after the work: complete (its exit status, or -SIGTERM as in the match test)
            assert proc.returncode in (0, 1, -signal.SIGTERM) and left == complete, (proc.returncode, left, text[-2000:])
    assert interrupted >= 1, codes   # at least one signal landed inside the work (signals at 35-80 % of it)


def test_a_signal_whose_exception_c_code_replaced_still_exits_128_plus_signum(tmp_path, monkeypatch):
    """A SIGTERM whose Terminated was raised inside numpy C code came back as numpy's own TypeError ("Cannot
    compare structured arrays ...") with no cause: 1 of 20 random SIGTERMs during match ended as "internal error"
    (exit 1).  A run that received a terminating signal exits 128 + its number whatever exception surfaced."""
    from click.testing import CliRunner

    import flakedb.process as proc
    import flakedb.solve.pipeline as pipeline
    from flakedb.cli.main import cli
    from flakedb.resources import RECIPES_DIR

    def replaced(*a, **k):
        proc._RECEIVED.append(15)   # what the handler records before raising Terminated
        raise TypeError("Cannot compare structured arrays unless they have a common dtype.")

    monkeypatch.setattr(proc, "_RECEIVED", [])
    monkeypatch.setattr(pipeline, "solve_paint", replaced)
    r = CliRunner().invoke(cli, ["compose", str(RECIPES_DIR / "particle-cadmium-yellow.yaml"), "--n", "16",
                                 "--out", str(tmp_path / "o")])
    assert r.exit_code == 143 and "internal error" not in r.output, r.output
    assert not (tmp_path / "o").exists() or not any((tmp_path / "o").iterdir())
