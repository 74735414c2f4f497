"""Measured BRDFs -> flakedb match targets at the ASTM E2194 and E2539 in-plane geometries (docs/validation.md).
Reads every format of flakedb.match.measured: MERL (.binary; may not be redistributed: keep its targets out of
the repository) and the RGL material database (.bsdf, RGB version; CC0).

Usage: python tools/merl_target.py OUT_DIR FILE [FILE ...]
Writes OUT_DIR/<name>.csv for each file, with its source and licence: L*a*b* under D65 / 2° for RGB files (read as
linear sRGB), spectral reflectance factors 380-780 nm for an RGL spectral file; prints L*, a*, b* (D65 / 2°) per
geometry and the X-Rite flop index."""
import sys
from pathlib import Path

import numpy as np

from flakedb.appearance.report import flop_index_standard
from flakedb.colour.settings import FLOP_GEOMETRIES
from flakedb.colour.tolerance import reflectance_to_Lab
from flakedb.match.measured import MeasuredError, measured_target
from flakedb.match.targets import E2539_GEOMETRIES, write_target


def main(argv):
    if len(argv) < 2:
        print(__doc__, file=sys.stderr)
        return 2
    out = Path(argv[0])
    g = np.asarray(E2539_GEOMETRIES, float)
    gf = np.asarray(FLOP_GEOMETRIES, float)
    done = []
    for f in argv[1:]:
        try:
            done.append((f, measured_target(f, np.vstack([g, gf]))))
        except MeasuredError as e:
            print(f"error: {e}", file=sys.stderr)
            return 2
    out.mkdir(parents=True, exist_ok=True)
    for f, m in done:
        name = Path(f).stem
        refl = None if m.reflectance is None else m.reflectance[:len(g)]
        lab = None if m.lab is None else m.lab[:len(g)]
        path = write_target(out / f"{name}.csv", g, lab=lab, reflectance=refl, wavelength_nm=m.wavelength_nm,
                            observer="2", illuminant="D65", name=name, notes=m.notes)
        # spectral: CIELAB through the target reader's own colorimetry
        labs = m.lab if m.lab is not None else reflectance_to_Lab(m.reflectance, m.wavelength_nm, "2", "D65")
        lab, flop = labs[:len(g)], labs[len(g):]
        print(f"{name}: {path}; flop index {flop_index_standard(*flop[:, 0]):.1f}")
        for (ti, asp), (L, a, b) in zip(g, lab):
            print(f"  {ti:>4g}as{asp:<5g} L* {L:7.2f}  a* {a:6.2f}  b* {b:6.2f}")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
