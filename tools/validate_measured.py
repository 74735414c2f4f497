"""Validation against measured paints (docs/validation.md): measured BRDF files (MERL .binary, RGL .bsdf;
flakedb.match.measured) -> targets at the E2194 and E2539 geometries -> `match` from a base of catalogue species
with physically bounded free parameters (tools/validation/*.yaml) -> a per-geometry ΔE00 table.  MERL may not be
redistributed: give your own copy.  The RGL paints' targets ship in tools/validation/targets/.

Usage: python tools/validate_measured.py OUT_DIR FILE|TARGET.csv [...] [--n N] [--max-nfev K] [--base NAME.yaml]
       [--start FIELD=VALUE ...]   (a free parameter's start, FIELD the last part of its path, e.g.
                                    coating_thickness_nm[1]=550 orientation_alpha=0.1)
The base is chosen by the file's name (KINDS below: silver, gold, pearl, colour-shift, blue metallic, with the
RGL database's names of its car paints), or given with --base (a file in tools/validation/); paints of a kind
with no base are reported as not attempted, with the reason.  Writes OUT_DIR/<name>.csv (target), OUT_DIR/<name>-fitted.yaml and prints a
Markdown table (ΔE00 at the start and after the fit, per geometry) and the fit's outcome sentence."""
import sys
from pathlib import Path

import numpy as np
import yaml

from flakedb.match.fit import find_fit_parameters, match
from flakedb.match.measured import MeasuredError, measured_target
from flakedb.match.targets import E2539_GEOMETRIES, read_target, write_target
from flakedb.paint.catalog import load_catalog

BASES = Path(__file__).resolve().parent / "validation"
#: name fragment -> base recipe, or the reason no base exists
KINDS = (("silver", "silver-tio2.yaml"), ("ilm_l3_37_metallic", "silver-tio2.yaml"), ("gold", "gold.yaml"),
         ("pearl", "pearl.yaml"), ("color-changing", "colour-shift.yaml"), ("colour-shift", "colour-shift.yaml"),
         ("irid_flake_paint", "colour-shift.yaml"), ("cc_", "colour-shift-fabry-perot.yaml"),
         ("blue", "blue-metallic.yaml"),
         ("ilm_solo_m_68", "blue-metallic.yaml"),
         ("red", "no red-metallic base yet (the organic reds are KM-derived tinters, docs/colourants.md; a base "
                 "of Al flakes with quinacridone-red or pyrrole-red is not written)"))


def base_for(name):
    for frag, what in KINDS:
        if frag in name:
            return what
    return ("no base recipe for this kind of paint (name must contain silver, gold, pearl, color-changing, blue "
            "or an RGL car paint's name; or give --base)")


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
    forced = None
    if "--base" in argv:
        i = argv.index("--base"); forced = argv[i + 1]; del argv[i:i + 2]
    if "--max-nfev" in argv:
        i = argv.index("--max-nfev"); max_nfev = int(argv[i + 1]); del argv[i:i + 2]
    starts = {}
    while "--start" in argv:
        i = argv.index("--start")
        field, _, value = argv[i + 1].partition("=")
        starts[field] = float(value)
        del argv[i:i + 2]
    if len(argv) < 2:
        print(__doc__, file=sys.stderr)
        return 2
    out = Path(argv[0])
    for f in argv[1:]:                            # every --start names a free parameter of its base, before writing
        base = forced or base_for(Path(f).stem)
        if not base.endswith(".yaml"):
            continue
        free = [p.name.rsplit(".", 1)[-1] for p in find_fit_parameters(
            yaml.safe_load((BASES / base).read_text(encoding="utf-8")))]
        unknown = sorted(set(starts) - set(free))
        if unknown:
            print(f"error: --start {', '.join(unknown)}: not a free parameter of {base} (its free parameters: "
                  f"{', '.join(free)}; hint: give the last part of the parameter's path)", file=sys.stderr)
            return 2
    out.mkdir(parents=True, exist_ok=True)
    cat = load_catalog(None)
    g = np.asarray(E2539_GEOMETRIES, float)
    for f in argv[1:]:
        name = Path(f).stem
        base = forced or base_for(name)
        if not base.endswith(".yaml"):
            print(f"## {name}\n\nnot attempted: {base}\n")
            continue
        if Path(f).suffix.lower() == ".csv":      # a target already made (tools/validation/targets/)
            csv = f
        else:
            try:
                m = measured_target(f, g)
            except MeasuredError as e:
                print(f"error: {e}", file=sys.stderr)
                return 2
            csv = write_target(out / f"{name}.csv", g, lab=m.lab, reflectance=m.reflectance,
                               wavelength_nm=m.wavelength_nm, observer="2", illuminant="D65", name=name,
                               notes=m.notes)
        doc = yaml.safe_load((BASES / base).read_text(encoding="utf-8"))
        for p in find_fit_parameters(doc):
            if p.name.rsplit(".", 1)[-1] in starts:
                node = doc
                for k in p.path[:-1]:
                    node = node[k]
                node[p.path[-1]]["start"] = starts[p.name.rsplit(".", 1)[-1]]
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
