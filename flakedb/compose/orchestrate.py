"""Compose a recipe into files: DIR/NAME.bsdf, DIR/NAME.h5 and DIR/NAME.json (the I/O edge).

:func:`compose` = :func:`flakedb.paint.mapping.build_paint` (physics mapping) → :func:`flakedb.paint.mapping.solve_paint`
(adding-doubling) → :func:`flakedb.bsdf.convert.stack_to_table` (the solver's blocks on the file's full node set) →
:func:`flakedb.compose.report.colour_report` → :func:`write_outputs`.

The files
---------
* ``NAME.bsdf``: the Fourier file (bsdf-format.md) with 1 channel (mono, or every channel equal) or
  3 (linear sRGB, stored as Y, R, B).  A spectral paint is converted to RGB by integrating its
  coefficient spectra against the CIE 1931 2° observer under D65 and mapping to white-normalised
  linear sRGB (:func:`flakedb.colour.colorimetry.spectra_to_rgb_mode`); the map is linear, so it applies
  coefficient by coefficient.  A smooth coat's first-surface mirror reflection is not in the table:
  it is recorded in the metadata as ``delta=fresnel``, ``delta_eta=η`` (bsdf-format.md, "Carrying a
  smooth clear coat's mirror reflection").  Also in the metadata: recipe name, flakedb version,
  mode, n, and ``store``: ``none: computed directly``, or the store URL and version the species'
  reflectance functions came from (``--store``; compressed or raw).
* ``NAME.h5``: the full-precision table (every channel — all spectral bands — every order, float64)
  with the delta term, the recipe text, the flakedb version, ``store_version`` (``"none: computed
  directly"`` or the store version's hash, with ``store_url`` and ``raw``) and what compose derived
  (loadings, solver info).
* ``NAME.json``: the colour report (:mod:`flakedb.compose.report`).

Node layout and transmission blocks: :mod:`flakedb.bsdf.convert`.  The reader's Catmull–Rom integral over
the unscattered-beam spike of a transmissive table is not exact (measured: albedo + transmittance
1.12 instead of 1 at normal incidence for an index-matched flake slab at n = 16); paints (with a
primer) have no transmission and are not affected.

No half-written outputs: the output directory is checked before any computation
(:func:`check_output_dir`), the three files are written into a temporary directory inside it and
moved into place (``os.replace``) only when all three are complete; on any error nothing is left.
"""

from __future__ import annotations

import dataclasses
import json
import os
import shutil
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

import flakedb.bsdf as bsdf_files  # the module, so a test can replace its writers
from flakedb import __version__
from flakedb.bsdf.convert import stack_to_table
from flakedb.colour.colorimetry import spectra_to_rgb_matrix
from flakedb.compose.report import colour_report
from flakedb.compose.store_context import StoreContext
from flakedb.paint.mapping import auto_resolution, build_paint, catalog_species, solve_paint
from flakedb.store import versions as st

#: Order truncation of the ``.bsdf`` (flakedb.bsdf.write_bsdf): 0 keeps every order up to the last
#: non-zero coefficient, so the file evaluates to the solver's values at the nodes to float32
#: precision (bsdf-format.md: "A writer is right when … evaluation at the quadrature nodes returns
#: the solver's BSDF to float32 precision").  layerlab's rule (2e-3 relative tail) changed values by
#: up to 1e-3 of the largest in a test paint; an opaque paint fills only the reflection quadrant, so
#: the full file is small (n = 64, 128 orders, RGB: ≈ 1.6 MB).
BSDF_TRUNCATION = 0.0
#: What the outputs record as the store version until the precomputed store (issue #5) exists.
STORE_NONE = "none: computed directly"


class OutputError(ValueError):
    """The output directory cannot be written."""


def check_output_dir(out_dir) -> Path:
    """Refuse an output directory that cannot be created or written, before any computation.

    Creates nothing: checks that ``out_dir`` is a writable directory, or that its nearest existing
    ancestor is a writable directory (it will be created when the files are written).
    """
    p = Path(out_dir)
    if p.exists():
        if not p.is_dir():
            raise OutputError(f"--out {out_dir}: exists and is not a directory (hint: choose a directory path)")
        if not os.access(p, os.W_OK | os.X_OK):
            raise OutputError(f"--out {out_dir}: directory is not writable (hint: choose a directory you can write)")
        return p
    anc = p.absolute().parent
    while not anc.exists():
        anc = anc.parent
    if not anc.is_dir():
        raise OutputError(f"--out {out_dir}: {anc} is not a directory, so {out_dir} cannot be created")
    if not os.access(anc, os.W_OK | os.X_OK):
        raise OutputError(f"--out {out_dir}: cannot create it, {anc} is not writable "
                          f"(hint: choose a directory you can write)")
    return p



def table_to_file_channels(table, mode, wavelength_nm=None):
    """The ``.bsdf`` version of a full table: linear sRGB (3 channels) or mono when every channel is
    equal (to 1e-12 relative).  Spectral → RGB by :func:`flakedb.colour.colorimetry.spectra_to_rgb_mode`
    applied coefficient by coefficient (it is linear)."""
    c = table.coeffs
    if mode == "spectral":
        M = spectra_to_rgb_matrix(wavelength_nm)                         # (B, 3)
        c = np.einsum("bk,b...->k...", M, c)
        channels = ("R", "G", "B")
    elif mode == "rgb":
        channels = ("R", "G", "B")
    else:
        channels = ("mono",)
    if c.shape[0] > 1:
        scale = max(np.abs(c).max(), 1e-300)
        if all(np.abs(c[k] - c[0]).max() <= 1e-12 * scale for k in range(1, c.shape[0])):
            c = c[:1]
            channels = ("mono",)
    return dataclasses.replace(table, coeffs=np.ascontiguousarray(c), channels=channels)


@dataclass
class ComposeResult:
    paths: dict
    report: dict
    n: int
    n_reason: str
    timings_s: dict
    bsdf_summary: dict
    warnings: list = field(default_factory=list)
    paint: object = None
    stack: object = None
    table: object = None


def write_outputs(out_dir, name, table, file_table, report, h5_metadata):
    """Write DIR/NAME.bsdf, .h5, .json all-or-nothing (module docstring).  Returns (paths, bsdf summary)."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(dir=out, prefix=f".{name}.", suffix=".tmp"))
    final = {"bsdf": out / f"{name}.bsdf", "h5": out / f"{name}.h5", "json": out / f"{name}.json"}
    try:
        summary = bsdf_files.write_bsdf(tmp / final["bsdf"].name, file_table, truncation=BSDF_TRUNCATION)
        bsdf_files.write_h5(tmp / final["h5"].name, table, h5_metadata)
        with open(tmp / final["json"].name, "w", encoding="utf-8") as fh:
            json.dump(report, fh, indent=1, allow_nan=False)
            fh.write("\n")
        mask = os.umask(0)
        os.umask(mask)
        for k in ("h5", "json", "bsdf"):  # temp files are 0600: give them the usual umask mode
            os.chmod(tmp / final[k].name, 0o666 & ~mask)
        for k in ("h5", "json", "bsdf"):
            os.replace(tmp / final[k].name, final[k])
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return {k: str(v) for k, v in final.items()}, summary


def compose(recipe, out_dir, n=None, raw=False, catalog=None, log=None, store=None, verify=True) -> ComposeResult:
    """Compose ``recipe`` (a :class:`flakedb.paint.recipe.Recipe`) into ``out_dir``; see the module docstring.

    ``n`` overrides the recipe's resolution; ``log`` (callable taking a line) reports progress.
    ``store``: None (species optics computed directly from the catalogue), a store URL or an open
    :class:`flakedb.store.versions.StoreVersion`: the catalogue species' reflectance functions come from its
    latest complete version (checksums verified first with ``verify``; compressed factors, or the
    raw samples with ``raw``).  A recipe without catalogue species does not open the store.  Raises
    :class:`flakedb.store.versions.StoreError` (:class:`~flakedb.store.versions.StoreIntegrityError` for a corrupted
    store) before writing anything.
    """
    log = log or (lambda s: None)
    check_output_dir(out_dir)
    if n is not None:
        n_used, reason = int(n), "--n"
    elif recipe.n is not None:
        n_used, reason = int(recipe.n), "recipe resolution"
    else:
        n_used, reason = auto_resolution(recipe)
    if n_used % 2 or n_used < 8:
        raise ValueError(f"n = {n_used}: the node count must be even and ≥ 8")
    warnings = list(recipe.warnings)
    if recipe.clearcoat is not None and recipe.clearcoat.roughness > 0 and n_used < 128:
        warnings.append(f"rough coat at n = {n_used} < 128: expect energy errors of several %")
    t = {}

    version = stored = None
    store_label = STORE_NONE
    if store is not None and catalog_species(recipe):
        t0 = time.perf_counter()
        version = store if isinstance(store, st.StoreVersion) else st.open_version(str(store), verify=False)
        stored = StoreContext.for_recipe(version, recipe, n_used, raw)
        if verify:  # the checksums of every file this recipe reads (docs/store.md)
            st.open_version(version.url, version.version, verify=stored.prefixes(recipe))
        t["store_open"] = time.perf_counter() - t0
        store_label = f"{version.url} version {version.version} ({'raw' if raw else 'compressed'})"
        log(f"store: {store_label}, opened{' and verified' if verify else ''} in {t['store_open']:.2f} s")
    t0 = time.perf_counter()
    paint = build_paint(recipe, catalog, stored=stored)
    t["optics"] = time.perf_counter() - t0
    log(f"optics: {len(paint.components)} component(s), {paint.n_channels} channel(s) ({paint.mode}), "
        f"{t['optics']:.2f} s")
    t0 = time.perf_counter()
    budget = os.environ.get("FLAKEDB_MEMORY_BUDGET")
    stack = solve_paint(paint, n_used, memory_budget_bytes=float(budget) if budget else None)
    t["solve"] = time.perf_counter() - t0
    log(f"solve: n = {n_used} ({reason}), {stack.info.get('orders')} Fourier orders, {t['solve']:.2f} s")
    t0 = time.perf_counter()
    md = {"recipe": recipe.name, "flakedb_version": __version__, "mode": paint.mode, "n_nodes": n_used,
          "store": store_label, "generator": "flakedb compose"}
    if recipe.description:
        md["description"] = " ".join(str(recipe.description).split())
    table = stack_to_table(stack, paint.channels, paint.eta, paint.top_alpha, paint.delta, md)
    file_table = table_to_file_channels(table, paint.mode, paint.wavelength_nm)
    if paint.mode == "spectral" and file_table.channels != ("mono",):
        file_table.metadata["channels_from"] = "spectral bands -> CIE 1931 2deg / D65 -> white-normalised linear sRGB"
    report = colour_report(table, paint.mode, paint.wavelength_nm, stack.x, stack.albedo(include_delta=False),
                           paint.eta if paint.delta else None, recipe.name)
    t["table_report"] = time.perf_counter() - t0
    h5_md = {
        "recipe_text": recipe.text, "recipe_source": recipe.source,
        "store_version": STORE_NONE if version is None else version.version,
        "store_url": None if version is None else version.url,
        "species_optics": ("computed directly from the catalogue (flakedb.paint.species); no precomputed store"
                           if version is None else
                           "projected kernel factors of catalogue species from the store (flakes: spectral factor U "
                           f"and projected blocks V{', untruncated' if raw else ''}, sigma_t, sigma_s per unit loading; "
                           "pigments: Mie cross-sections and Legendre moments): no azimuthal projection "
                           "(flakedb.paint.mapping, flakedb.rt.stored, docs/store.md)"),
        "raw": bool(raw), "n_reason": reason,
        "wavelength_nm": None if paint.wavelength_nm is None else paint.wavelength_nm.tolist(),
        "components": paint.components, "paint_info": paint.info,
        "solver_info": _jsonable(stack.info), "warnings": warnings,
        "albedo_nodes_tabulated": stack.albedo(include_delta=False).tolist(),
        "delta_F_nodes": None if stack.delta_F is None else np.asarray(stack.delta_F).tolist(),
        "timings_s": dict(t),
    }
    report["store"] = store_label
    t0 = time.perf_counter()
    paths, summary = write_outputs(out_dir, recipe.name, table, file_table, report, h5_md)
    t["write"] = time.perf_counter() - t0
    return ComposeResult(paths=paths, report=report, n=n_used, n_reason=reason, timings_s=t, bsdf_summary=summary,
                         warnings=warnings, paint=paint, stack=stack, table=table)


def _jsonable(o):
    if isinstance(o, dict):
        return {str(k): _jsonable(v) for k, v in o.items()}
    if isinstance(o, (list, tuple)):
        return [_jsonable(v) for v in o]
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, float) and not np.isfinite(o):
        return str(o)
    return o
