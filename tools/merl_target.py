"""Measured MERL BRDFs -> flakedb match targets at the ASTM E2194 and E2539 in-plane geometries
(docs/validation.md).  The MERL database may not be redistributed: point this at your own copy, and keep
the targets it writes out of the repository.

Usage: python tools/merl_target.py OUT_DIR FILE.binary [FILE.binary ...]
Writes OUT_DIR/<name>.csv (L*a*b* under D65 / 2°, flakedb.match.merl's sRGB reading of MERL's RGB) for each
file and prints L*, a*, b* per geometry and the X-Rite flop index."""
import sys
from pathlib import Path

import numpy as np

from flakedb.appearance.report import flop_index_standard
from flakedb.colour.settings import FLOP_GEOMETRIES
from flakedb.match.merl import MerlError, merl_target, read_merl
from flakedb.match.targets import E2539_GEOMETRIES, write_target


def main(argv):
    if len(argv) < 2:
        print(__doc__, file=sys.stderr)
        return 2
    out = Path(argv[0])
    out.mkdir(parents=True, exist_ok=True)
    g = np.asarray(E2539_GEOMETRIES, float)
    for f in argv[1:]:
        try:
            table = read_merl(f)
        except MerlError as e:
            print(f"error: {e}", file=sys.stderr)
            return 2
        name = Path(f).name.removesuffix(".binary")
        R, lab = merl_target(table, g)
        if np.isnan(lab).any():
            bad = [tuple(x) for x in g[np.isnan(lab).any(axis=1)]]
            print(f"error: {f}: no measured value at geometries {bad}", file=sys.stderr)
            return 2
        notes = {"source": f"MERL BRDF database (Matusik et al., ACM TOG 22(3) 2003), file {Path(f).name}; "
                           "in-plane nearest-bin lookup, R = pi f_r, RGB read as linear sRGB (flakedb.match.merl)",
                 "licence": "MERL database terms: research use, no redistribution; do not commit this file"}
        path = write_target(out / f"{name}.csv", g, lab=lab, observer="2", illuminant="D65", name=name, notes=notes)
        _, flop = merl_target(table, np.asarray(FLOP_GEOMETRIES, float))
        print(f"{name}: {path}; flop index {flop_index_standard(*flop[:, 0]):.1f}")
        for (ti, asp), (L, a, b) in zip(g, lab):
            print(f"  {ti:>4g}as{asp:<5g} L* {L:7.2f}  a* {a:6.2f}  b* {b:6.2f}")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
