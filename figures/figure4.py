"""Reproduce the paper's Figure 4 (mean relative error vs rank, SVD and NMF):
``python -m figures.figure4 [--n 64] [--m 64] [--nmf-iter 200]`` → docs/figures/figure4.{png,json}."""

import argparse
import json
import time
from pathlib import Path

import numpy as np

from flakedb.paint import catalog as cat
from flakedb.paint import species as sp
from flakedb.store.compress import (
    FIGURE4_SPECIES,
    MRE_THRESHOLD,
    figure4_table,
    sample_reflectance,
    storage_bytes,
)


def figure4(out_dir="docs/figures", species=FIGURE4_SPECIES, wavelength_nm=550.0, n=64, m=64,
            ranks=range(1, 13), nmf_iter=500, catalog=None):
    """Reproduce the paper's Figure 4 (mean relative error vs rank, SVD and NMF) on catalogue species
    at one wavelength (nm) on the (n, n, m) grid.  Writes ``figure4.png`` (matplotlib Agg) and
    ``figure4.json`` (the table and its parameters) into ``out_dir``; returns the table dict."""
    import matplotlib  # lazy: matplotlib takes ~0.3 s to import; only plotting needs it

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt  # lazy: matplotlib takes ~0.3 s to import; only plotting needs it

    catalog = catalog if catalog is not None else cat.load_catalog()
    allsp = cat.expand_sweeps(catalog)
    wl = np.array([float(wavelength_nm)])
    nb = sp.binder_index(catalog, wl)
    R_by = {name: sample_reflectance(allsp[name], wl, nb, n, m)[0] for name in species}
    table = figure4_table(R_by, ranks, nmf_iter=nmf_iter)
    table.update({"n": int(n), "m": int(m), "wavelength_nm": float(wavelength_nm), "nmf_iter": int(nmf_iter),
                  "error_definition": f"mean over entries with R > {MRE_THRESHOLD:g}·max R of |R − R̂|/R",
                  "storage_paper_setup": storage_bytes(200, 200, 8)})
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    fig, ax = plt.subplots(figsize=(6.4, 4.2))
    styles = {"sqrt_svd": "-o", "svd": "--s", "nmf": ":^"}
    labels = {"sqrt_svd": "√R SVD (paper)", "svd": "SVD of R", "nmf": "NMF"}
    for k, (name, rows) in enumerate(table["errors"].items()):
        for meth, st in styles.items():
            ax.semilogy(table["ranks"], np.maximum(rows[meth], 1e-16), st, color=f"C{k}", ms=3,
                        label=f"{name}: {labels[meth]}")
    ax.set_xlabel("rank r")
    ax.set_ylabel("mean relative error")
    ax.set_title(f"Figure 4 reproduction: n = {n}, m = {m}, λ = {wavelength_nm:g} nm")
    ax.legend(fontsize=6, ncol=2)
    fig.tight_layout()
    fig.savefig(out / "figure4.png", dpi=130)
    plt.close(fig)
    (out / "figure4.json").write_text(json.dumps(table, indent=1, sort_keys=True) + "\n", encoding="utf-8")
    return table


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--n", type=int, default=64)
    ap.add_argument("--m", type=int, default=64)
    ap.add_argument("--nmf-iter", type=int, default=200)
    ap.add_argument("--wavelength-nm", type=float, default=550.0)
    ap.add_argument("--out", default="docs/figures")
    a = ap.parse_args(argv)
    t0 = time.perf_counter()
    table = figure4(a.out, n=a.n, m=a.m, nmf_iter=a.nmf_iter, wavelength_nm=a.wavelength_nm)
    for name, rows in table["errors"].items():
        for meth, errs in rows.items():
            print(f"{name:16s} {meth:9s} " + " ".join(f"{e:.1e}" for e in errs))
    print(f"written to {a.out}/figure4.png, figure4.json in {time.perf_counter() - t0:.1f} s")


if __name__ == "__main__":
    main()
