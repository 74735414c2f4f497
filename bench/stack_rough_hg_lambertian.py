"""Whole-process benchmark of issue #11's layerlab comparison: rough coat (Beckmann α 0.1, η 1.5) /
Henyey–Greenstein slab (g 0.7, albedo 0.95, τ 2) / Lambertian 0.5, RGB, n = 200, solved and written
as a Fourier ``.bsdf``.  Run as a process (``python bench/stack_rough_hg_lambertian.py [n] [out] [colour]``)
and time it from outside; layerlab took 2.5 s for the same stack on the 2-core machine (issue #11).

The stack is grey (every channel the same), so flakedb solves one channel and spreads it
(docs/model.md §4, "Channels").  ``colour`` (third argument) makes the channels differ (slab albedo
0.95 / 0.9 / 0.8, primer 0.5 / 0.4 / 0.3): three channels solved, to show what the grey case saves."""

import os
import sys
import tempfile

from flakedb.bsdf import write_bsdf
from flakedb.process import available_threads, tune_allocator
from flakedb.bsdf.convert import stack_to_table
from flakedb.rt.scattering.media import PhaseMedium
from flakedb.rt.adding.stack import Lambertian, Rough, Slab, SolverSettings, solve_stack


def main(n=200, out=None, colour=False):
    tune_allocator()  # as the command line does (flakedb/process.py); FLAKEDB_MALLOC_TUNING=0 to compare
    albedo, primer = ([0.95, 0.9, 0.8], [0.5, 0.4, 0.3]) if colour else ([0.95] * 3, [0.5] * 3)
    slab = Slab(2.0, PhaseMedium(sigma_t_per_um=[1.0] * 3, albedo=albedo, phase=("hg", 0.7)))
    s = solve_stack(Rough(1.5, 0.1), [slab], Lambertian(primer),
                    SolverSettings.product(n, threads=available_threads()))
    out = out or os.path.join(tempfile.gettempdir(), "flakedb-bench-rough-hg-lambertian.bsdf")
    write_bsdf(out, stack_to_table(s))
    return s


if __name__ == "__main__":
    main(int(sys.argv[1]) if len(sys.argv) > 1 else 200, sys.argv[2] if len(sys.argv) > 2 else None,
         len(sys.argv) > 3 and sys.argv[3] == "colour")
