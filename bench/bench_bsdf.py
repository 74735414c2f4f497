"""Fourier .bsdf timings (see bench/run.py for the BENCHMARKS protocol).

On layerlab's ``carpaint_rgb_n100.bsdf`` (N = 102 nodes, 3 channels, up to 266 orders):
- eval of 1e5 random (mu_i, mu_o, phi_d), uniform in [-1, 1]² x [0, 2π), compiled kernel;
- the same with the plain numpy reference path on 1e4 points (compare best_s / n_points);
- pdf of the same 1e5 points;
- importance sampling of 1e5 directions, mu_i uniform in (0, 1] (light from above);
- reading the file, and writing it back (read -> BSDFTable -> write_bsdf, default truncation).
A renderer (pbrt-v3, Mitsuba 0.6) does one such eval per shading point; layerlab's C++/AVX reader is
the comparison point a user has in mind.
"""

import os
import tempfile

import numpy as np

from flakedb.bsdf import read_bsdf, write_bsdf

FILE = os.environ.get("FLAKEDB_BSDF_BENCH_FILE",
                      os.path.join(os.path.dirname(__file__), "..", "..", "shared", "data", "bsdf-files",
                                   "carpaint_rgb_n100.bsdf"))
if not os.path.exists(FILE):
    FILE = "/work/shared/data/bsdf-files/carpaint_rgb_n100.bsdf"
N_POINTS = 100_000
N_NUMPY = 10_000


def _points(n, seed=0):
    rng = np.random.default_rng(seed)
    return rng.uniform(-1, 1, n), rng.uniform(-1, 1, n), rng.uniform(0, 2 * np.pi, n)


def _setup_eval():
    return read_bsdf(FILE), _points(N_POINTS)


def _run_eval(arg):
    b, (mi, mo, ph) = arg
    v = b.eval(mi, mo, ph)
    return {"mean_f_cos_R": float(v[:, 0].mean())}


def _setup_eval_numpy():
    return read_bsdf(FILE), _points(N_NUMPY)


def _run_eval_numpy(arg):
    b, (mi, mo, ph) = arg
    v = b.eval(mi, mo, ph, method="numpy")
    return {"mean_f_cos_R": float(v[:, 0].mean())}


def _run_pdf(arg):
    b, (mi, mo, ph) = arg
    return {"mean_pdf": float(b.pdf(mi, mo, ph).mean())}


def _setup_sample():
    rng = np.random.default_rng(1)
    return read_bsdf(FILE), 1.0 - rng.random(N_POINTS), rng.random(N_POINTS), rng.random(N_POINTS)


def _run_sample(arg):
    b, mi, u1, u2 = arg
    _, _, w, _ = b.sample(mi, u1, u2)
    return {"mean_weight_R": float(w[:, 0].mean())}


def _run_read(path):
    b = read_bsdf(path)
    return {"n_coeffs": b.n_coeffs}


def _setup_write():
    return read_bsdf(FILE).to_table(), os.path.join(tempfile.gettempdir(), "flakedb-bench-bsdf-write.bsdf")


def _run_write(arg):
    table, out = arg
    info = write_bsdf(out, table)
    return {"size_bytes": info["size"]}


_META = {"file": os.path.basename(FILE), "nodes": 102, "channels": 3, "max_order": 266}

BENCHMARKS = [
    ("bsdf.eval.random_1e5.carpaint_rgb_n100", _setup_eval, _run_eval,
     {**_META, "n_points": N_POINTS, "method": "numba"}),
    ("bsdf.eval_numpy.random_1e4.carpaint_rgb_n100", _setup_eval_numpy, _run_eval_numpy,
     {**_META, "n_points": N_NUMPY, "method": "numpy"}),
    ("bsdf.pdf.random_1e5.carpaint_rgb_n100", _setup_eval, _run_pdf, {**_META, "n_points": N_POINTS}),
    ("bsdf.sample.1e5.carpaint_rgb_n100", _setup_sample, _run_sample,
     {**_META, "n_points": N_POINTS, "mu_i": "uniform (0, 1]"}),
    ("bsdf.read.carpaint_rgb_n100", lambda: FILE, _run_read, {**_META, "size_bytes": os.path.getsize(FILE)}),
    ("bsdf.write.carpaint_rgb_n100", _setup_write, _run_write, {**_META, "truncation": 2e-3}),
]
