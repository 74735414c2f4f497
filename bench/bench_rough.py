"""Rough-interface benchmarks (issue 12): building the rough dielectric coat's scattering matrices by
flux-cell integration (flakedb.rt.boundaries.microfacet) against the former node-sampled projection, and the
rough conductor base.  Accuracy is in tests/test_rough_energy.py; here only the time."""

import os
import subprocess
import sys
import tempfile
import time

from flakedb.rt.boundaries import interface as itf
from flakedb.rt.basis.quadrature import radau_hemisphere


def _coat(n, alpha, scheme):
    def setup():
        return radau_hemisphere(n // 2)

    def run(q):
        fn = itf.rough_dielectric if scheme == "cells" else itf.rough_dielectric_point_sampled
        layer, _ = fn(q, q, 1.5, alpha, max_orders=2 * n)
        return {"orders": int(layer.n_orders)}

    return (f"rough coat interface ({scheme}), alpha={alpha}, n={n}", setup, run,
            {"n": n, "alpha": alpha, "eta": 1.5, "scheme": scheme, "what": "four blocks, all orders"})


def _conductor(n, alpha):
    def setup():
        return radau_hemisphere(n // 2)

    def run(q):
        Rt, _ = itf.rough_conductor(q, [0.18 + 2.3j, 0.9 + 6.1j, 1.1 + 7.0j], alpha, max_orders=2 * n)
        return {"orders": int(Rt.shape[0])}

    return (f"rough conductor base, alpha={alpha}, n={n}, 3 channels", setup, run,
            {"n": n, "alpha": alpha, "channels": 3})


def _compile_package():
    """Byte-compile the package once, as an installed wheel is (pip writes the .pyc files): a
    whole-process time should not include compiling flakedb's sources, which happens on every run
    where PYTHONDONTWRITEBYTECODE is set (this machine sets it)."""
    import compileall

    import flakedb

    compileall.compile_dir(os.path.dirname(flakedb.__file__), quiet=1)


def _whole_stack(n=200, write=True, colour=False):
    """The rough / HG / Lambertian stack at n RGB as a whole process, as issue #11 measured it:
    import + interface + solve + the Fourier ``.bsdf`` written (``bench/stack_rough_hg_lambertian.py``,
    threads = the core count, as compose runs; BLAS one thread per call inside the solve).
    ``write=False``: the earlier row (``python -c`` import + solve, no file, one thread), kept to
    compare with the previous results.  ``colour``: the same stack with different channels (three
    solved; the issue's stack is grey and is solved once).  Reports the child's CPU seconds too."""
    here = os.path.dirname(os.path.abspath(__file__))

    def setup():
        _compile_package()
        return None

    def run(_):
        if write:
            cmd = [sys.executable, os.path.join(here, "stack_rough_hg_lambertian.py"), str(n),
                   os.path.join(tempfile.gettempdir(), "flakedb-bench-whole.bsdf")] + (["colour"] if colour else [])
        else:
            cmd = [sys.executable, "-c", (
                "import numpy as np; from flakedb.rt.adding.stack import Rough, Slab, Lambertian, SolverSettings, solve_stack; "
                "from flakedb.rt.scattering.media import PhaseMedium; "
                "slab = Slab(2.0, PhaseMedium(np.ones(3), np.full(3, 0.95), ('hg', np.full(3, 0.7)))); "
                f"solve_stack(Rough(1.5, 0.1), [slab], Lambertian(np.full(3, 0.5)), SolverSettings.product({n}))")]
        env = dict(os.environ, OPENBLAS_NUM_THREADS="1", MKL_NUM_THREADS="1",
                   PYTHONPATH=os.pathsep.join([os.path.dirname(here), os.environ.get("PYTHONPATH", "")]))
        t0 = time.perf_counter()
        p = subprocess.Popen(cmd, env=env)
        _, status, usage = os.wait4(p.pid, 0)
        wall = time.perf_counter() - t0
        if status != 0:
            raise RuntimeError(f"{cmd} exited with status {status}")
        # (no peak RSS here: a forked child's ru_maxrss starts at the bench process's own high-water mark)
        return {"process_s": wall, "process_cpu_s": usage.ru_utime + usage.ru_stime}

    what = ("process: import + interface + solve + .bsdf written, threads = cores, order_tol 1e-4, package byte-compiled"
            if write else "python -c import + interface + solve (no file), one thread, order_tol 1e-4, package byte-compiled")
    name = f"whole process{' (solve + .bsdf)' if write else ''}: rough 0.1 / HG / Lambertian, RGB, n={n}"
    if colour:
        name += ", channels differ"
    return (name, setup, run, {"n": n, "channels": 3, "distinct_channels": 3 if colour else 1, "what": what,
                               "layerlab_s": 2.5, "target_s": 0.8})


def _auto_stack(alpha, slab=True):
    """Solve (all orders, order_tol 1e-4) of a rough coat [/ HG g 0.7 slab] / diffuse primer at the n that
    ``resolution: auto`` picks (docs/resolution.md), mono."""
    import yaml

    from flakedb.paint.mapping import build_paint, solve_paint
    from flakedb.solve.resolution import auto_resolution
    from flakedb.paint.recipe import parse_recipe

    layers = [{"clearcoat": {"thickness_um": 40, "ior": 1.5, "roughness": alpha}}]
    if slab:
        layers.append({"basecoat": {"thickness_um": 10, "ior": 1.5, "particles": [
            {"custom": {"kind": "medium", "name": "hg", "albedo": 0.9, "phase": {"hg": 0.7}}, "optical_depth": 1.0}]}})
    layers.append({"primer": {"albedo": 0.5}})
    rec = parse_recipe(yaml.safe_dump({"flakedb": 1, "name": "b", "spectral": {"mode": "mono"},
                                       "resolution": "auto", "layers": layers}))
    n, _ = auto_resolution(rec)

    def setup():
        return build_paint(rec)

    def run(paint):
        st = solve_paint(paint, n)
        return {"n": n, "orders": int(st.info.get("orders", 0))}

    return (f"auto stack: rough {alpha}{' / HG' if slab else ''} / diffuse, n={n}", setup, run,
            {"alpha": alpha, "n": n, "slab": slab})


BENCHMARKS = [_auto_stack(0.3), _auto_stack(0.1), _auto_stack(0.05), _auto_stack(0.02), _coat(200, 0.1, "cells"), _coat(200, 0.1, "points"), _coat(64, 0.1, "cells"),
              _coat(64, 0.1, "points"), _coat(64, 0.02, "cells"), _coat(64, 0.01, "cells"), _conductor(64, 0.1),
              _whole_stack(200, write=False), _whole_stack(200), _whole_stack(200, colour=True)]
