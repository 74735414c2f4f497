"""Store-backed compose timings (issue #6; see bench/run.py for the BENCHMARKS protocol).

Per catalogue particle (the ``catalog/recipes/particle-*.yaml`` paints: one species over a gray
primer under a smooth 1.5 coat), in the paper's RGB mode (the recipes' spectral block replaced by
``mode: rgb`` integrated over 400–700 nm every 20 nm, 16 bands, which is ``flakedb build``'s default
grid) at n = 32 (the lower end of auto_resolution; 41 spectral bands at n = 64 would take minutes per
run on the shared 2-core machine), m = 33, rank r = 8:

* ``stored/compress/<particle>``: building that species' store version (16 bands, ``--eta-top 1.5``,
  raw samples too) into a fresh directory: sampling R on the solver's inside grid (n_mu = 56 nodes),
  the √R SVD and Fourier factors, chunk writes, checksums (the paper's Table 1 "Compression": 13–27 s
  per particle at n = m = 200, one RGB set).
* ``stored/compose-{direct,raw,compressed}/<particle>``: the whole ``flakedb.compose.orchestrate.compose`` (optics,
  adding-doubling, table, colour report, three files) computing the optics directly, or reading R from
  the store (raw DCT-I series, or the compressed factors; checksums verified on open).  The paper's
  Table 1 "Adding-doubling": 5.4–12.5 s raw, 2.8–6.2 s compressed at n = m = 200.  Extra columns:
  the stages, and the store runs' max |Δf|/max f at the nodes and CIEDE2000 of the report's colours
  against the direct compose.
"""

import re
import shutil
import tempfile
from pathlib import Path

import numpy as np

RECIPES = Path(__file__).resolve().parents[1] / "catalog" / "recipes"
PARTICLES = ("metallic", "pearlescent", "gray-mirror", "cadmium-yellow", "iron-black")
N, M, RANK = 32, 33, 8
RANGE_NM, STEP_NM = (400.0, 700.0), 20.0
ETA = 1.5
_STORE = {}


def _recipe(particle):
    from flakedb.paint.recipe import parse_recipe

    text = (RECIPES / f"particle-{particle}.yaml").read_text(encoding="utf-8")
    text = re.sub(r"(?m)^spectral:.*$", f"spectral: {{mode: rgb, range_nm: [{RANGE_NM[0]:g}, {RANGE_NM[1]:g}], "
                  f"step_nm: {STEP_NM:g}}}", text)
    text = re.sub(r"(?m)^resolution:.*$", f"resolution: {N}", text)
    return parse_recipe(text, f"particle-{particle} (rgb, n = {N})")


def _request(species):
    from flakedb.colour.colorimetry import spectral_grid
    from flakedb.pipelines.build import make_request

    return make_request(species=list(species), n=N, m=M, rank=RANK, wavelength_nm=spectral_grid(RANGE_NM, STEP_NM),
                        store_raw=True, eta_top=ETA)


def _shared_store():
    """One store with every particle (built once per process, untimed)."""
    if "url" not in _STORE:
        from flakedb.pipelines.build import build

        url = str(Path(tempfile.mkdtemp(prefix="flakedb-bench-stored-")) / "store")
        build(_request(PARTICLES), url, scheduler="sync")
        _STORE["url"] = url
    return _STORE["url"]


def _compress_setup(particle):
    def setup():
        return _request([particle])

    return setup


def _compress_run(req):
    from flakedb.pipelines.build import build

    d = tempfile.mkdtemp(prefix="flakedb-bench-compress-")
    try:
        res = build(req, str(Path(d) / "store"), scheduler="sync")
    finally:
        shutil.rmtree(d, ignore_errors=True)
    return {"tasks": res["tasks_run"]}


def _compose_setup(particle, kind):
    def setup():
        from flakedb.compose.orchestrate import compose

        rec = _recipe(particle)
        url = _shared_store() if kind != "direct" else None
        ref = None
        if kind != "direct":
            with tempfile.TemporaryDirectory(prefix="flakedb-bench-") as out:
                ref = compose(rec, out)  # the direct compose, for the difference columns
        return rec, url, ref

    return setup


def _compose_run(kind):
    def run(arg):
        from flakedb.colour.colorimetry import delta_E_2000
        from flakedb.compose.orchestrate import compose

        rec, url, ref = arg
        with tempfile.TemporaryDirectory(prefix="flakedb-bench-") as out:
            res = compose(rec, out, store=url, raw=(kind == "raw"))
        extra = {f"stage_{k}_s": v for k, v in res.timings_s.items()}
        extra["orders"] = res.stack.info.get("orders")
        if ref is not None:
            phi = np.linspace(0.0, np.pi, 9)
            fa, fb = res.stack.eval_nodes(phi), ref.stack.eval_nodes(phi)
            lab = lambda r: np.array([[g["L"], g["a"], g["b"]] for g in r.report["geometries"]])
            extra["max_rel_f_diff_vs_direct"] = float(np.abs(fa - fb).max() / np.abs(fb).max())
            extra["dE00_max_vs_direct"] = float(delta_E_2000(lab(res), lab(ref)).max())
        return extra

    return run


_META = {"n": N, "m": M, "rank": RANK, "mode": "rgb", "bands": int((RANGE_NM[1] - RANGE_NM[0]) / STEP_NM) + 1,
         "eta_top": ETA}

BENCHMARKS = [
    (f"stored/compress/{p} n={N} m={M} r={RANK} 16 bands", _compress_setup(p), _compress_run,
     {**_META, "paper_table1_compression_s": "13-27 (n = m = 200)"})
    for p in PARTICLES
] + [
    (f"stored/compose-{kind}/{p} n={N} rgb", _compose_setup(p, kind), _compose_run(kind),
     {**_META, "optics": kind,
      "paper_table1_adding_doubling_s": {"direct": None, "raw": "5.4-12.5", "compressed": "2.8-6.2"}[kind]})
    for p in PARTICLES for kind in ("direct", "raw", "compressed")
]
