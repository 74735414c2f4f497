"""The evaluation kernels are compiled on first use (flakedb.bsdf.kernels.compiled): a process that
only solves and writes does not import numba, and threads that all evaluate first at the same
moment compile once and agree."""

import subprocess
import sys
import textwrap
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]


def _run(code):
    return subprocess.run([sys.executable, "-c", textwrap.dedent(code)], capture_output=True, text=True,
                          cwd=ROOT, env={"PYTHONPATH": str(ROOT), "PATH": "/usr/bin:/bin"}, timeout=300)


def test_writing_a_file_does_not_import_numba_and_first_evaluations_in_threads_agree(tmp_path):
    r = _run(f"""
        import sys, threading
        import numpy as np
        from flakedb.bsdf import BSDFTable, read_bsdf, write_bsdf
        mu = np.array([-1.0, -0.5, 0.5, 1.0])
        c = np.zeros((1, 4, 4, 3)); c[0, 2:, :2] = [0.3, 0.1, 0.02]
        write_bsdf({str(tmp_path / "t.bsdf")!r}, BSDFTable(mu=mu, coeffs=c))
        assert "numba" not in sys.modules, "writing imported numba"
        b = read_bsdf({str(tmp_path / "t.bsdf")!r})
        out, errors = [], []
        def work():
            try:
                out.append(b.eval(np.full(5, 0.7), np.full(5, -0.6), np.linspace(0, 3, 5)))
            except Exception as e:
                errors.append(repr(e))
        ts = [threading.Thread(target=work) for _ in range(8)]
        [t.start() for t in ts]; [t.join() for t in ts]
        assert not errors, errors
        assert len(out) == 8 and all(np.array_equal(o, out[0]) for o in out)
        assert np.all(out[0][:, 0] > 0)
        print("ok")
    """)
    assert r.returncode == 0 and r.stdout.strip() == "ok", r.stderr[-2000:]
