"""Reproduce the paper's Figure 4 (mean relative error vs rank, SVD and NMF):
``python -m figures.figure4 [--n 64] [--m 64] [--nmf-iter 200]`` → docs/figures/figure4.{png,json}."""

import argparse
import time

from flakedb.store.compress import figure4


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
