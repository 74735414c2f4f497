"""Measured BRDFs -> flakedb match targets at the ASTM E2194 and E2539 in-plane geometries (docs/validation.md).
Reads every format of flakedb.match.measured: MERL (.binary; may not be redistributed: keep its targets out of
the repository) and the RGL material database (.bsdf, RGB version; CC0).

Usage: python tools/merl_target.py OUT_DIR FILE [FILE ...]
Writes OUT_DIR/<name>.csv (L*a*b* under D65 / 2°, the file's RGB read as linear sRGB) for each file, with its
source and licence, and prints L*, a*, b* per geometry and the X-Rite flop index."""
import sys
from pathlib import Path

import numpy as np

from flakedb.appearance.report import flop_index_standard
from flakedb.colour.settings import FLOP_GEOMETRIES
from flakedb.match.measured import MeasuredError, measured_target
from flakedb.match.targets import E2539_GEOMETRIES, write_target


def main(argv):
    if len(argv) < 2:
        print(__doc__, file=sys.stderr)
        return 2
    out = Path(argv[0])
    g = np.asarray(E2539_GEOMETRIES, float)
    done = []
    for f in argv[1:]:
        try:
            _, lab, notes = measured_target(f, g)
            _, flop, _ = measured_target(f, np.asarray(FLOP_GEOMETRIES, float))
        except MeasuredError as e:
            print(f"error: {e}", file=sys.stderr)
            return 2
        done.append((f, lab, notes, flop))
    out.mkdir(parents=True, exist_ok=True)
    for f, lab, notes, flop in done:
        name = Path(f).stem
        path = write_target(out / f"{name}.csv", g, lab=lab, observer="2", illuminant="D65", name=name, notes=notes)
        print(f"{name}: {path}; flop index {flop_index_standard(*flop[:, 0]):.1f}")
        for (ti, asp), (L, a, b) in zip(g, lab):
            print(f"  {ti:>4g}as{asp:<5g} L* {L:7.2f}  a* {a:6.2f}  b* {b:6.2f}")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
