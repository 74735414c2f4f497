"""Store and build faults (issue 13): a broken `latest`, a chunk replaced by a directory, leftovers
of a killed build, a disk that fills up, a killed worker process, a killed parent: each one clear
line (no traceback), stored data intact, and a rerun that resumes."""

import errno
import os
import shutil
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import psutil
import pytest
from click.testing import CliRunner

from flakedb.cli.main import cli
from flakedb.pipelines.build import build, make_request
from flakedb.pipelines.progress import BuildProgress
from flakedb.store import versions as st


def _request(**kw):
    args = dict(species=["cadmium-yellow"], n=8, wavelength_nm=[450.0, 550.0, 650.0], channel_block=1)
    args.update(kw)
    return make_request(**args)


@pytest.fixture(scope="module")
def built(tmp_path_factory):
    url = str(tmp_path_factory.mktemp("faults") / "store")
    res = build(_request(), url, scheduler="sync")
    assert res["status"] == "built"
    return url, res


def _copy(built, tmp_path):
    url = str(tmp_path / "store")
    shutil.copytree(built[0], url)
    return url


def _no_traceback(r):
    assert "Traceback" not in r.output and r.exception is None or isinstance(r.exception, SystemExit), r.output


@pytest.mark.parametrize("kind", ["not-json", "directory", "list"])
def test_broken_latest_is_a_clear_error(built, tmp_path, kind):
    url = _copy(built, tmp_path)
    latest = Path(url) / "latest"
    latest.unlink()
    if kind == "not-json":
        latest.write_text("garbage{")
    elif kind == "directory":
        latest.mkdir()
    else:
        latest.write_text("[1, 2]")
    with pytest.raises(st.StoreError, match="`latest` is unreadable|not a version hash"):
        st.read_latest(url)
    r = CliRunner().invoke(cli, ["verify", url])
    assert r.exit_code == 1 and "latest" in r.output
    _no_traceback(r)
    r = CliRunner().invoke(cli, ["compose", "--help"])
    assert r.exit_code == 0


def test_chunk_replaced_by_a_directory_is_reported(built, tmp_path):
    url = _copy(built, tmp_path)
    key = "species/cadmium-yellow/c_ext_um2/c/0"
    p = Path(url) / "versions" / built[1]["version"] / key
    p.unlink()
    p.mkdir()
    r = CliRunner().invoke(cli, ["verify", url])
    assert r.exit_code == 1 and f"{key}: unreadable" in r.output
    _no_traceback(r)
    with pytest.raises(st.StoreIntegrityError, match="unreadable"):
        st.open_version(url)


def test_tmp_leftover_does_not_break_verify_all(built, tmp_path):
    url = _copy(built, tmp_path)
    (Path(url) / "versions" / ".tmp-0123456789abcdef-999-deadbeef" / "grid").mkdir(parents=True)
    assert st.verify_store(url, all_versions=True) == []
    r = CliRunner().invoke(cli, ["verify", url, "--all"])
    assert r.exit_code == 0, r.output


def test_disk_full_during_build_is_one_line_and_resumes(tmp_path, monkeypatch):
    url = str(tmp_path / "store")
    real = st.run_task
    calls = []

    def full(u, plan, task):
        calls.append(task.id)
        if len(calls) == 1:
            raise OSError(errno.ENOSPC, "No space left on device", str(Path(u) / "versions" / "x"))
        return real(u, plan, task)

    monkeypatch.setattr(st, "run_task", full)
    args = ["build", "--store", url, "--n", "8", "--species", "cadmium-yellow", "--range-nm", "450",
            "650", "--step-nm", "100", "--workers", "1"]
    r = CliRunner().invoke(cli, args)
    assert r.exit_code == 1, r.output
    assert "No space left on device" in r.output and "free some space" in r.output
    _no_traceback(r)
    assert len(r.output.strip().splitlines()[-1]) < 300
    monkeypatch.setattr(st, "run_task", real)
    r = CliRunner().invoke(cli, args)
    assert r.exit_code == 0 and "built" in r.output, r.output
    assert st.verify_store(url, all_versions=True) == []


def test_debug_flag_shows_the_traceback(tmp_path, monkeypatch):
    def boom(*a, **k):
        raise RuntimeError("boom")

    monkeypatch.setattr(st, "run_task", boom)
    args = ["build", "--store", str(tmp_path / "s"), "--n", "8", "--species", "cadmium-yellow",
            "--range-nm", "450", "650", "--step-nm", "100"]
    r = CliRunner().invoke(cli, args)
    assert r.exit_code == 1 and "internal error: RuntimeError: boom" in r.output and "--debug" in r.output
    r = CliRunner().invoke(cli, ["--debug"] + args)
    assert isinstance(r.exception, RuntimeError)


def test_progress_lines_in_a_log_and_a_bar_on_a_terminal():
    import io

    log = io.StringIO()
    bar = BuildProgress(40, stream=log, tty=False)
    for _ in range(40):
        bar.update(1)
    bar.close()
    lines = log.getvalue().splitlines()
    assert len(lines) == 5 and "\r" not in log.getvalue()   # start, 25/50/75 %, end (100 % is the end line)
    assert lines[0] == "build: 40 task(s) to run" and lines[-1].startswith("build: 40/40 tasks done in")
    tty = io.StringIO()
    bar = BuildProgress(4, stream=tty, tty=True)
    for _ in range(4):
        bar.update(1)
    bar.close()
    assert "\r" in tty.getvalue() and "4/4 tasks 100%" in tty.getvalue() and tty.getvalue().endswith("\n")


def test_build_progress_goes_to_stderr_not_stdout(tmp_path):
    env = {**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[2])}
    r = subprocess.run([sys.executable, "-m", "flakedb", "build", "--store", str(tmp_path / "s"), "--n", "8", "--species", "cadmium-yellow", "--range-nm", "450", "650", "--step-nm", "100"],
                       capture_output=True, text=True, env=env, timeout=300)
    assert r.returncode == 0, r.stderr
    assert "tasks done" not in r.stdout and "\r" not in r.stdout and r.stdout.startswith("built")
    assert "build: 1 task(s) to run" in r.stderr and "\r" not in r.stderr  # not a TTY: summary lines


def _killer(stop, once):
    """Kill spawned worker processes of this process as they appear (``once``: only the first)."""
    me = psutil.Process()
    killed = []
    while not stop.is_set():
        for c in me.children(recursive=True):
            try:
                cmd = " ".join(c.cmdline())
            except psutil.Error:
                continue
            if "spawn_main" in cmd and c.pid not in killed:
                c.kill()
                killed.append(c.pid)
                if once:
                    return
        time.sleep(0.02)


@pytest.mark.slow
def test_killed_worker_is_retried(tmp_path):
    url = str(tmp_path / "store")
    stop = threading.Event()
    t = threading.Thread(target=_killer, args=(stop, True), daemon=True)
    t.start()
    try:
        res = build(_request(), url, scheduler="processes", workers=1)
    finally:
        stop.set()
    assert res["status"] == "built" and st.verify_store(url, all_versions=True) == []


@pytest.mark.slow
def test_workers_that_keep_dying_stop_the_build_clearly_and_it_resumes(tmp_path):
    url = str(tmp_path / "store")
    stop = threading.Event()
    t = threading.Thread(target=_killer, args=(stop, False), daemon=True)
    t.start()
    try:
        with pytest.raises(st.StoreError, match="a worker process died.*rerun `flakedb build`"):
            build(_request(), url, scheduler="processes", workers=1)
    finally:
        stop.set()
        t.join()
    assert build(_request(), url, scheduler="processes", workers=1)["status"] == "built"


def _cmdline(proc):
    """A child's command line, or [] when it ended (or is a zombie) between listing and reading."""
    try:
        return proc.cmdline()
    except (psutil.NoSuchProcess, psutil.ZombieProcess, psutil.AccessDenied):
        return []


@pytest.mark.slow
def test_killing_the_parent_ends_its_workers(tmp_path):
    env = {**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[2])}
    p = subprocess.Popen([sys.executable, "-m", "flakedb", "build", "--store", str(tmp_path / "s"), "--processes",
                          "--workers", "2", "--n", "64", "--species", "pearlescent"],
                         env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    parent = psutil.Process(p.pid)
    deadline = time.time() + 120
    workers = []
    while time.time() < deadline and not workers:
        workers = [c for c in parent.children(recursive=True) if "spawn_main" in " ".join(_cmdline(c))]
        time.sleep(0.1)
    assert workers, "no worker processes started"
    everyone = parent.children(recursive=True)
    os.kill(p.pid, signal.SIGKILL)
    p.wait()
    gone, alive = psutil.wait_procs(everyone, timeout=10)
    for a in alive:
        a.kill()
    assert not alive, f"still running after the parent was killed: {[_cmdline(a) for a in alive]}"


def test_a_killed_builds_template_is_reported_and_swept(built, tmp_path):
    """issue 38: a template left by a build killed with SIGKILL (its process gone) made `verify --all` say OK and
    stayed after a rebuild; verify now reports it, and the next build removes it."""
    from flakedb.outputs import temp_host
    from flakedb.store.write import remove_stale_templates

    url = _copy(built, tmp_path)
    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()
    stray = Path(url) / "versions" / f".tmp-0123456789abcdef-{temp_host()}.{dead.pid}-deadbeef"
    (stray / "grid").mkdir(parents=True)
    mine = Path(url) / "versions" / f".tmp-0123456789abcdef-{temp_host()}.{os.getpid()}-cafef00d"
    mine.mkdir()                                     # a build still running: never reported or removed
    problems = st.verify_store(url, all_versions=True)
    assert len(problems) == 1 and stray.name in problems[0] and "interrupted build" in problems[0], problems
    r = CliRunner().invoke(cli, ["verify", url, "--all"])
    assert r.exit_code != 0 and stray.name in r.output, r.output
    assert remove_stale_templates(str(Path(url) / "versions")) == [stray.name]
    assert not stray.exists() and mine.exists()
    assert st.verify_store(url, all_versions=True) == []


def test_a_template_whose_writing_fails_is_removed(tmp_path, monkeypatch):
    """issue 38: a disk-full error while the private template was written left versions/.tmp-… behind."""
    from flakedb.store import write as sw

    real = sw._fill_template

    def full(vurl, plan, meta):
        real(vurl, plan, meta)
        raise OSError(errno.ENOSPC, "No space left on device", vurl)

    monkeypatch.setattr(sw, "_fill_template", full)
    url = str(tmp_path / "store")
    args = ["build", "--store", url, "--n", "8", "--species", "cadmium-yellow", "--range-nm", "450", "650",
            "--step-nm", "100", "--workers", "1"]
    r = CliRunner().invoke(cli, args)
    assert r.exit_code == 1 and "No space left on device" in r.output, r.output
    assert [p.name for p in (Path(url) / "versions").iterdir()] == []


def test_the_plan_is_one_node_of_the_graph_not_traversed_per_task(tmp_path, monkeypatch):
    """The build's graph holds the plan once, untraversed (flakedb.pipelines.build._execute): passed inline to each
    task, dask walked its nested inputs (the catalogue's entries) once per task looking for collections
    (≈ 160 000 items, 1.2 s of building the graph for the default catalogue's 39 tasks).  Counted here through
    dask's own walker: a few calls per task, not thousands; every task gets the very plan object and the build is
    complete."""
    dd = sys.modules[__import__("dask.delayed").delayed.__module__]  # the module (dask.delayed the name is the function)

    calls = [0]
    walk = dd.unpack_collections

    def counting(*a, **k):
        calls[0] += 1
        return walk(*a, **k)

    monkeypatch.setattr(dd, "unpack_collections", counting)
    seen = []
    run = st.run_task

    def spy(url, plan, task):
        seen.append(plan)
        return run(url, plan, task)

    monkeypatch.setattr(st, "run_task", spy)
    res = build(_request(), str(tmp_path / "s"), scheduler="sync", workers=1)
    assert res["status"] == "built" and len(seen) == res["tasks_run"] == 3
    assert all(p is seen[0] for p in seen)
    assert calls[0] < 100 * len(seen), calls[0]  # 78 (26 per task: the task and url); inline: 975
