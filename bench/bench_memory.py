"""Peak memory and CPU of whole `flakedb compose` processes (issue 26 item 1: metallic silver and particle
pearlescent at n = 128 without a store within 2 GB and 20 s; every catalogue recipe at n = 128 under 3 GB;
docs/cost-model.md).  Each row runs the command line in a child process and reads the child's own resource
usage (``os.wait4``): peak RSS (``ru_maxrss``, kB) and CPU seconds (user + sys), which a loaded machine's wall
clock does not give.  Timings and memory live here and never in pass/fail tests.
"""

import os
import subprocess
import sys
import tempfile
from pathlib import Path

RECIPES = Path(__file__).resolve().parents[1] / "catalog" / "recipes"
CASES = [("metallic-silver", 128), ("particle-pearlescent", 128), ("particle-cadmium-yellow", 128)]


def _setup(name, n):
    def setup():
        return RECIPES / f"{name}.yaml", n

    return setup


def _run(arg):
    recipe, n = arg
    with tempfile.TemporaryDirectory(prefix="flakedb-bench-") as out:
        p = subprocess.Popen([sys.executable, "-m", "flakedb.cli.main", "compose", str(recipe), "--n", str(n),
                              "--out", out, "--quiet"], stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
        _, status, ru = os.wait4(p.pid, 0)
        p.returncode = os.waitstatus_to_exitcode(status)
        err = p.stderr.read().decode(errors="replace")
        p.stderr.close()
    if p.returncode != 0:
        raise RuntimeError(f"compose exited {p.returncode}: {err[-500:]}")
    return {"n": n, "peak_rss_GB": ru.ru_maxrss * 1024 / 1e9, "cpu_s": ru.ru_utime + ru.ru_stime,
            "target": "<= 2 GB and <= 20 s (metallic silver, particle pearlescent); < 3 GB every catalogue recipe"}


BENCHMARKS = [(f"memory: compose {r} n={n} no store", _setup(r, n), _run,
               {"recipe": r, "what": "whole compose process: peak RSS and CPU seconds (os.wait4)"}) for r, n in CASES]
