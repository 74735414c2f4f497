"""Store compose against direct compose for every catalogue recipe at its own settings (issue #11):
``python bench/store_accuracy.py [--out bench/store_accuracy.json] [--store DIR]``.

Builds the default store (`flakedb build`: every species, 380–780 nm every 5 nm, n = 32, η 1.5, the
catalogue's α and those the recipes use) unless ``--store`` names one, then composes each recipe in
catalog/recipes/ with catalogue species directly and from the store and records the CIEDE2000 of the
six report angles, max |Δf| / max f at the nodes (φ_d at 9 azimuths), the compose times and the
flakes' spectral ranks.  Acceptance: ΔE00 ≤ 0.05 and |Δf| ≤ 1e-3 max f for every recipe.
"""

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from flakedb.colour.colorimetry import delta_E_2000  # noqa: E402
from flakedb.compose.orchestrate import compose  # noqa: E402
from flakedb.paint.mapping import catalog_species  # noqa: E402
from flakedb.paint.recipe import load_recipe  # noqa: E402
from flakedb.pipelines.build import DEFAULT_ETA_TOP, build, make_request  # noqa: E402
from flakedb.resources import RECIPES_DIR  # noqa: E402


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--out", default="bench/store_accuracy.json")
    ap.add_argument("--store", default=None)
    ap.add_argument("--only", default=None)
    a = ap.parse_args()
    work = Path(tempfile.mkdtemp(prefix="flakedb-store-accuracy-"))
    url = a.store or str(work / "store")
    t0 = time.perf_counter()
    res = build(make_request(eta_top=DEFAULT_ETA_TOP), url, scheduler="threads")
    t_build = time.perf_counter() - t0
    print(f"store {url}: {res['status']} ({res['tasks_total']} tasks) in {t_build:.0f} s", flush=True)
    lab = lambda r: np.array([[g["L"], g["a"], g["b"]] for g in r.report["geometries"]])
    rows = []
    for path in sorted(RECIPES_DIR.glob("*.yaml")):
        if a.only and a.only not in path.stem:
            continue
        rec = load_recipe(path)
        if not catalog_species(rec):
            continue
        t0 = time.perf_counter()
        d = compose(rec, work / "d")
        td = time.perf_counter() - t0
        t0 = time.perf_counter()
        s = compose(rec, work / "s", store=url)
        ts = time.perf_counter() - t0
        phi = np.linspace(0.0, np.pi, 9)
        fd, fs = d.stack.eval_nodes(phi), s.stack.eval_nodes(phi)
        row = {"recipe": path.stem, "n": d.n, "bands": int(d.paint.n_channels),
               "dE00_max": float(delta_E_2000(lab(s), lab(d)).max()),
               "max_rel_f_diff": float(np.abs(fs - fd).max() / np.abs(fd).max()),
               "direct_s": td, "store_s": ts, "direct_solve_s": d.timings_s["solve"], "store_solve_s": s.timings_s["solve"],
               "orders": s.stack.info.get("orders")}
        row["ok"] = row["dE00_max"] <= 0.05 and row["max_rel_f_diff"] <= 1e-3
        rows.append(row)
        print(json.dumps(row), flush=True)
    out = {"store_build_s": t_build, "store": url, "recipes": rows,
           "all_ok": all(r["ok"] for r in rows)}
    Path(a.out).write_text(json.dumps(out, indent=1) + "\n")
    print(f"all ok: {out['all_ok']}; wrote {a.out}")


if __name__ == "__main__":
    main()
