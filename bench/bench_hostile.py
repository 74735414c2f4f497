"""Refusal times of hostile inputs (issue 13: "a clear error before any heavy work, within a second";
see bench/run.py for the BENCHMARKS protocol).  Each run must end in the refusal; the time is how
long the user waits for the one-line error.

* ``refuse/recipe-1MB+``: a recipe above the 1 MB limit (a 43 MB recipe once took 296 s).
* ``refuse/alias-bomb``: a 10⁷-node alias bomb inside a typed field (once 95 s, then MemoryError).
* ``refuse/table-10001``: a phase table one entry above the 10 000-point limit (parse + schema).
* ``refuse/h5-512GiB``: an HDF5 file of a few KB declaring a 512 GiB coefficient array.
"""

import tempfile
from pathlib import Path

import numpy as np

BASE = """\
flakedb: 1
name: hostile
spectral: {mode: mono}
layers:
  - basecoat:
      thickness_um: 15
      ior: 1.5
      particles:
        - custom: {kind: medium, albedo: 0.9, phase: PHASE}
          optical_depth: 1.0
  - primer: {albedo: 0.5}
"""


def _refuses(text):
    from flakedb.paint.recipe import RecipeError, parse_recipe

    try:
        parse_recipe(text)
    except RecipeError:
        return
    raise AssertionError("not refused")


def _bomb():
    lines = ["a0: &a0 [1, 1, 1, 1, 1, 1, 1, 1, 1, 1]"]
    lines += [f"a{i}: &a{i} [" + ", ".join([f"*a{i - 1}"] * 10) + "]" for i in range(1, 7)]
    return "\n".join(lines) + "\n" + BASE.replace("thickness_um: 15", "thickness_um: *a6").replace("PHASE", "isotropic")


def _table():
    v = ", ".join(["0.5"] * 10_001)
    c = ", ".join(f"{-1 + 2 * i / 10_000:.6f}" for i in range(10_001))
    return BASE.replace("PHASE", f"{{table: {{cos_theta: [{c}], value: [{v}]}}}}")


def _h5_setup():
    import h5py

    from flakedb.bsdf.h5file import write_h5
    from flakedb.bsdf.table import BSDFTable

    x = np.array([0.5, 1.0])
    mu = np.concatenate([-x[::-1], x])
    p = Path(tempfile.mkdtemp()) / "huge.h5"
    write_h5(p, BSDFTable(mu=mu, coeffs=np.full((1, 4, 4, 1), 0.1)))
    with h5py.File(p, "r+") as f:
        del f["mu"], f["coeffs"]
        f.create_dataset("mu", shape=(2048,), dtype="f8")
        f.create_dataset("coeffs", shape=(16, 2048, 2048, 1024), dtype="f8", chunks=(1, 1, 8, 8))
    return p


def _h5_run(p):
    from flakedb.bsdf import BSDFFileError, open_bsdf

    try:
        open_bsdf(p)
    except BSDFFileError:
        return
    raise AssertionError("not refused")


BENCHMARKS = [
    ("refuse/recipe-1MB+", lambda: BASE.replace("PHASE", "isotropic") + "#" + "x" * 1_000_001 + "\n", _refuses,
     {"bytes": 1_000_100}),
    ("refuse/alias-bomb", _bomb, _refuses, {"expanded_nodes": 10 ** 7}),
    ("refuse/table-10001", _table, _refuses, {"points": 10_001}),
    ("refuse/h5-512GiB", _h5_setup, _h5_run, {"declared_GiB": 512}),
]
