"""Validation against measured paints (docs/validation.md): MERL BRDF files -> targets at the E2194 and E2539
geometries -> `match` from a base of catalogue species with physically bounded free parameters
(tools/validation/*.yaml) -> a per-geometry ΔE00 table.  MERL may not be redistributed: give your own copy.

Usage: python tools/validate_measured.py OUT_DIR FILE.binary [FILE.binary ...] [--n N] [--max-nfev K]
The base is chosen by the file's name: silver -> silver.yaml, gold -> gold.yaml, pearl -> pearl.yaml,
color-changing / colour-shift -> colour-shift.yaml; other paints (blue, red metallics) are reported as not
attempted, with the reason.  Writes OUT_DIR/<name>.csv (target), OUT_DIR/<name>-fitted.yaml and prints a
Markdown table (ΔE00 at the start and after the fit, per geometry) and the fit's outcome sentence."""
import sys
from pathlib import Path

import numpy as np
import yaml

from flakedb.match.fit import match
from flakedb.match.merl import MerlError, merl_target, read_merl
from flakedb.match.targets import E2539_GEOMETRIES, read_target, write_target
from flakedb.paint.catalog import load_catalog

BASES = Path(__file__).resolve().parent / "validation"
#: name fragment -> base recipe, or the reason no base exists
KINDS = (("silver", "silver.yaml"), ("gold", "gold.yaml"), ("pearl", "pearl.yaml"),
         ("color-changing", "colour-shift.yaml"), ("colour-shift", "colour-shift.yaml"),
         ("blue", "no blue colourant in the catalogue (phthalocyanine PB15 has no published optical data "
                  "in reach: docs/colourants.md)"),
         ("red", "no organic red in the catalogue (transparent PR101 gives copper, not a red metallic's hue)"))


def base_for(name):
    for frag, what in KINDS:
        if frag in name:
            return what
    return "no base recipe for this kind of paint (name must contain silver, gold, pearl or color-changing)"


def table(res):
    rows = ["| geometry | target L*, a*, b* | fitted L*, a*, b* | ΔE00 start | ΔE00 fit |", "|---|---|---|---|---|"]
    for g, t, f, d0, d1 in zip(res.geometries, res.lab_target, res.lab_fit, res.de_start, res.de_fit):
        rows.append(f"| {g[0]:g}as{g[1]:g} | {t[0]:.1f}, {t[1]:.1f}, {t[2]:.1f} | {f[0]:.1f}, {f[1]:.1f}, {f[2]:.1f} "
                    f"| {d0:.2f} | {d1:.2f} |")
    return "\n".join(rows)


def main(argv):
    n, max_nfev = 32, 40   # n = 32: flop index within 0.03, L* within 0.8 of auto (n = 80) for alpha 0.12 flakes
    if "--n" in argv:
        i = argv.index("--n"); n = int(argv[i + 1]); del argv[i:i + 2]
    if "--max-nfev" in argv:
        i = argv.index("--max-nfev"); max_nfev = int(argv[i + 1]); del argv[i:i + 2]
    if len(argv) < 2:
        print(__doc__, file=sys.stderr)
        return 2
    out = Path(argv[0])
    out.mkdir(parents=True, exist_ok=True)
    cat = load_catalog(None)
    g = np.asarray(E2539_GEOMETRIES, float)
    for f in argv[1:]:
        name = Path(f).name.removesuffix(".binary")
        base = base_for(name)
        if not base.endswith(".yaml"):
            print(f"## {name}\n\nnot attempted: {base}\n")
            continue
        try:
            _, lab = merl_target(read_merl(f), g)
        except MerlError as e:
            print(f"error: {e}", file=sys.stderr)
            return 2
        csv = write_target(out / f"{name}.csv", g, lab=lab, observer="2", illuminant="D65", name=name,
                           notes={"source": f"MERL BRDF database (Matusik et al. 2003), {Path(f).name}",
                                  "licence": "MERL terms: no redistribution; do not commit"})
        doc = yaml.safe_load((BASES / base).read_text(encoding="utf-8"))
        res = match(doc, read_target(csv), n=n, catalog=cat, max_nfev=max_nfev, source=base,
                    log=lambda s: print(s, file=sys.stderr, flush=True))
        (out / f"{name}-fitted.yaml").write_text(yaml.safe_dump(res.fitted_doc, sort_keys=False), encoding="utf-8")
        fitted = ", ".join(f"{p.name} = {v:.4g}" for p, v in zip(res.params, res.values))
        print(f"## {name} (base {base}, n = {res.n}, {res.n_compose} composes)\n\n{table(res)}\n\n"
              f"worst ΔE00 {res.de_fit.max():.2f} at {res.geometries[res.de_fit.argmax()][0]:g}as"
              f"{res.geometries[res.de_fit.argmax()][1]:g}; fitted: {fitted}\n\n{res.outcome}\n", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
