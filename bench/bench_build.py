"""Precompute timings (issue #5; see bench/run.py for the BENCHMARKS protocol).

* ``compress/<particle>``: per catalogue particle (the paper's Table 1 "Compression" column), one
  spectral channel (550 nm) at n = m = 64: sampling R(μ_i, μ_o, φ_d) on the grid
  (flakedb.store.compress.sample_reflectance, incl. the R(c) / Mie phase table), the √R SVD at r = 8 and the
  Fourier factors.  The paper's grid is n = m = 200; meta carries the storage arithmetic.
* ``build/default-catalogue …``: every species of the default catalogue built into a fresh store at a
  small grid (n = 8, m = 16, 4 channels, 2 per task; the row's ``tasks`` says how many: it grows with the
  catalogue), serially (synchronous scheduler) and with 2 local worker processes.  Includes template,
  checksums, finalize.
"""

import shutil
import tempfile
import uuid

import numpy as np

N = M = 64
RANK = 8
PARTICLES = ("metallic", "pearlescent", "gray-mirror", "cadmium-yellow", "titanium-white", "iron-black")


def _compress_setup(name):
    def setup():
        from flakedb.paint import catalog as cat
        from flakedb.paint import species as sp

        catalog = cat.load_catalog()
        wl = np.array([550.0])
        return cat.get_species(name, catalog), wl, sp.binder_index(catalog, wl)

    return setup


def _compress_run(arg):
    from flakedb.store.compress import (
        fourier_factors,
        mean_relative_error,
        reconstruct,
        sample_reflectance,
        sqrt_svd_compress,
    )

    entry, wl, nb = arg
    R = sample_reflectance(entry, wl, nb, N, M)[0]
    f = sqrt_svd_compress(R, RANK)
    fourier_factors(f.V_pairs)
    return {"mean_relative_error_r8": mean_relative_error(R, reconstruct(f.U_pairs, f.V_pairs))}


def _build_setup():
    from flakedb.pipelines.build import make_request

    req = make_request(n=8, wavelength_nm=[400.0, 500.0, 600.0, 700.0], channel_block=2)
    return req, tempfile.mkdtemp(prefix="flakedb-bench-")


def _build_run(scheduler, workers):
    def run(arg):
        from flakedb.pipelines.build import build

        req, root = arg
        url = f"{root}/{uuid.uuid4().hex}"
        res = build(req, url, scheduler=scheduler, workers=workers)
        shutil.rmtree(url, ignore_errors=True)
        return {"tasks": res["tasks_run"], "status": res["status"]}

    return run


def _storage_meta():
    from flakedb.store.compress import storage_bytes

    return storage_bytes(200, 200, RANK)


BENCHMARKS = [
    (f"compress/{p} n=m={N} r={RANK} 1 channel", _compress_setup(p), _compress_run,
     {"n": N, "m": M, "rank": RANK, "channels": 1, "paper_grid": "n = m = 200", "paper_storage": _storage_meta()})
    for p in PARTICLES
] + [
    ("build/default-catalogue n=8 4ch serial", _build_setup, _build_run("sync", None),
     {"n": 8, "m": 16, "channels": 4, "scheduler": "sync", "workers": 1}),
    ("build/default-catalogue n=8 4ch 2-processes", _build_setup, _build_run("processes", 2),
     {"n": 8, "m": 16, "channels": 4, "scheduler": "processes", "workers": 2}),
]
