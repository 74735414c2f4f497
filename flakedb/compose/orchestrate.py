"""Compose a recipe into files: DIR/NAME.bsdf, DIR/NAME.h5 and DIR/NAME.json (the I/O edge).

:func:`compose` = :func:`flakedb.paint.mapping.build_paint` (physics mapping) → :func:`flakedb.paint.mapping.solve_paint`
(adding-doubling) → :func:`flakedb.bsdf.convert.stack_to_table` (the solver's blocks on the file's full node set) →
:func:`flakedb.appearance.report.colour_report` → :func:`write_outputs`.

The files
---------
* ``NAME.bsdf``: the Fourier file (docs/bsdf-format.md) with 1 channel (mono, or every channel equal) or
  3 (linear sRGB, stored as Y, R, B).  A spectral paint is converted to RGB by integrating its
  coefficient spectra against the CIE 1931 2° observer under D65 and mapping to white-normalised
  linear sRGB (:func:`flakedb.colour.colorimetry.spectra_to_rgb_mode`); the map is linear, so it applies
  coefficient by coefficient.  A smooth coat's first-surface mirror reflection is not in the table:
  it is recorded in the metadata as ``delta=fresnel``, ``delta_eta=η`` (docs/bsdf-format.md, "Carrying a
  smooth clear coat's mirror reflection").  Also in the metadata: recipe name, flakedb version,
  mode, n, and ``store``: ``none: computed directly``, or the store URL and version the species'
  reflectance functions came from (``--store``; compressed or raw).
* ``NAME.h5``: the full-precision table (every channel — all spectral bands — every order, float64)
  with the delta term, the recipe text, the flakedb version, ``store_version`` (``"none: computed
  directly"`` or the store version's hash, with ``store_url`` and ``raw``) and what compose derived
  (loadings, solver info).
* ``NAME.json``: the colour report (:mod:`flakedb.appearance.report`).

Node layout and transmission blocks: :mod:`flakedb.bsdf.convert`.  The reader's Catmull–Rom integral over
the unscattered-beam spike of a transmissive table is not exact (measured: albedo + transmittance
1.12 instead of 1 at normal incidence for an index-matched flake slab at n = 16); paints (with a
primer) have no transmission and are not affected.

No half-written outputs: the output plan is checked before any computation (:func:`output_plan`,
:mod:`flakedb.outputs`: the directory writable, no name taken by a directory, no output onto an input),
the three files are written into a temporary directory inside it and moved into place together only
when all three are complete (a failed move puts the previous files back); on any error, a signal
included, nothing is left.  ``inputs`` of :func:`compose`: ``(path, label)`` pairs no output may replace.
"""

from __future__ import annotations

import json
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

import flakedb.bsdf as bsdf_files  # the module, so a test can replace its writers
from flakedb.appearance.report import ASPECULAR_DEG, eval_table, multiangle_geometry, texture_ground
from flakedb.bsdf.h5file import encode_chunks_early, preload_h5py
from flakedb.colour import gamut
from flakedb.colour.colorimetry import spectra_to_rgb_matrix
from flakedb.outputs import OutputPlan
from flakedb.paint.texture_inputs import texture_report, texture_report_grounded
from flakedb.solve.pipeline import STORE_NONE, solve_reported
from flakedb.texture.instruments import PRESETS as TEXTURE_OBSERVERS

#: Order truncation of the ``.bsdf`` (flakedb.bsdf.write_bsdf): 0 keeps every order up to the last
#: non-zero coefficient, so the file evaluates to the solver's values at the nodes to float32
#: precision (docs/bsdf-format.md: "A writer is right when … evaluation at the quadrature nodes returns
#: the solver's BSDF to float32 precision").  layerlab's rule (2e-3 relative tail) changed values by
#: up to 1e-3 of the largest in a test paint; an opaque paint fills only the reflection quadrant, so
#: the full file is small (n = 64, 128 orders, RGB: ≈ 1.6 MB).
BSDF_TRUNCATION = 0.0


def output_plan(out_dir, name, inputs=()) -> OutputPlan:
    """The plan of compose's outputs DIR/NAME.{bsdf,h5,json} (:class:`flakedb.outputs.OutputPlan`): refused
    before any work when a name is taken by a directory, is one of ``inputs`` (``(path, label)``), or
    the directory cannot be written.

    >>> import tempfile
    >>> from flakedb.outputs import OutputError
    >>> d = Path(tempfile.mkdtemp())
    >>> (d / "paint.h5").mkdir()                        # a directory where an output goes
    >>> [p.name for p, _ in output_plan(d, "paint").outputs]
    ['paint.bsdf', 'paint.h5', 'paint.json']
    >>> try:
    ...     output_plan(d, "paint").check()
    ... except OutputError as e:
    ...     print(str(e).replace(str(d), "D").split(";")[0])
    output NAME.h5 D/paint.h5: a directory is in its place
    >>> sorted(p.name for p in d.iterdir())             # nothing written
    ['paint.h5']
    """
    plan = OutputPlan()
    plan.add_dir(out_dir)
    for path, label in inputs:
        plan.add_input(path, label)
    for ext in OUTPUT_SUFFIXES:
        plan.in_dir(out_dir, f"{name}{ext}", f"output NAME{ext}")
    return plan


#: compose's outputs, in the order they are moved into place.
OUTPUT_SUFFIXES = (".bsdf", ".h5", ".json")


def table_to_file_channels(table, mode, wavelength_nm=None):
    """The ``.bsdf`` version of a full table: linear sRGB (3 channels) or mono when every channel is
    equal (to 1e-12 relative).  Spectral → RGB by :func:`flakedb.colour.colorimetry.spectra_to_rgb_mode`
    applied coefficient by coefficient (it is linear).  A reflection-only table stays one (its
    quadrant alone is mapped)."""
    c = table.stored
    if mode == "spectral":
        M = spectra_to_rgb_matrix(wavelength_nm)                         # (B, 3)
        c = np.einsum("bk,b...->k...", M, c)
        channels = ("R", "G", "B")
    elif mode == "rgb":
        channels = ("R", "G", "B")
    else:
        channels = ("mono",)
    if c.shape[0] > 1 and (c.strides[0] == 0 or _channels_equal(c)):  # stride 0: one channel for all
        c = c[:1]
        channels = ("mono",)
    return table.replace(stored=np.ascontiguousarray(c), channels=channels)


def _channels_equal(c, rtol=1e-12):
    """Whether every channel of ``c`` (C, ...) equals the first to ``rtol`` of the largest |value|, one
    channel at a time (no temporary of the whole array)."""
    scale = max(abs(float(c.max())), abs(float(c.min())), 1e-300)
    return all(np.abs(c[k] - c[0]).max() <= rtol * scale for k in range(1, c.shape[0]))


def _plus_zero(c):
    """``c + 0.0`` (every -0.0 made +0.0, all else bit for bit): what the channel map's einsum gives for the identity
    (RGB mode to sRGB), without a copy of ``c`` when it holds no -0.0 (the usual case)."""
    return c + 0.0 if np.any(c.view(np.int64) == np.iinfo(np.int64).min) else c


def gamut_safe_file_channels(table, mode, wavelength_nm=None, space="srgb"):
    """The ``.bsdf`` version of a full table, gamut-safe: ``(file_table, gamut_info)``.

    Spectral channels → white-normalised linear RGB of ``space`` (:func:`flakedb.colour.gamut.spectra_to_space_matrix`;
    ``"srgb"`` is :func:`table_to_file_channels`' map), RGB-mode channels (white-normalised linear sRGB) → ``space``
    (:func:`flakedb.colour.gamut.rgb_mode_to_space_matrix`), then out-of-gamut node pairs desaturated at constant
    luminance (:func:`flakedb.colour.gamut.desaturate_to_gamut`, docs/gamut.md), so the file holds no negative
    channel at any node pair's order-0 coefficient nor at its sampled azimuths where the luminance is > 0.
    A mono paint is returned as :func:`table_to_file_channels` makes it (``gamut_info`` None).

    ``gamut_info`` (JSON-able) records the space, the method, how many reflection node pairs were
    mapped, the largest CIEDE2000 the mapping costs (over the mapped reflection node pairs' order-0
    colour as reflectance factor π a_0 / |μ_o|, the directional albedo per incident node, and the
    report's multi-angle geometries) and the largest channel albedo before and after.
    """
    gamut.check_space(space)
    if mode == "mono":
        return table_to_file_channels(table, mode, wavelength_nm), None
    # a reflection-only table (an opaque paint) is mapped on its reflection quadrant alone: the other
    # quadrants are zero and in gamut, and the reciprocal partner of a reflection pair is a reflection
    # pair (desaturation_factors' symmetrisation stays inside the quadrant)
    c = table.stored
    wl = np.asarray(wavelength_nm, float)
    M = gamut.spectra_to_space_matrix(wl, space) if mode == "spectral" else gamut.rgb_mode_to_space_matrix(wl, space)
    w = gamut.luminance_weights(wl, space)
    m = M.sum(axis=0)  # a grey value v maps to v m_k in channel k
    if c.shape[0] > 1 and c.strides[0] == 0 and np.all(m > 0) and np.ptp(m) <= 1e-12 * m.max():
        # a grey table (one channel for all, stride 0: a grey stack solved once) maps to the grey v m_0 (the einsum
        # below gives v m_k, equal to 1e-12: table_to_file_channels makes it mono); every channel has the sign of
        # its luminance, so (G1) leaves it as it is (s = 1): one channel mapped, nothing to desaturate
        v = c[:1] if m[0] == 1.0 else c[:1] * m[0]
        c = mapped = np.broadcast_to(v, (3,) + c.shape[1:])
        s = np.ones(c.shape[1:3])
    else:
        c = _plus_zero(c) if M.shape == (3, 3) and np.array_equal(M, np.eye(3)) else np.einsum("jk,j...->k...", M, c)
        mapped, s = gamut.desaturate_to_gamut(c, w)
    before = table.replace(stored=c, channels=("R", "G", "B"))
    after = table.replace(stored=mapped if mapped.strides[0] == 0 else np.ascontiguousarray(mapped),
                          channels=("R", "G", "B"))
    h = table.n // 2
    if not table.reflection_only:  # light from above, reflected: the same quadrant of the full table
        c, mapped, s = c[:, h:, :h], mapped[:, h:, :h], s[h:, :h]
    changed = s < 1.0
    mu_o = np.abs(table.mu[:h])[None, :]
    de_pairs = 0.0
    if changed.any():
        rf = np.pi * c[..., 0] / mu_o                          # (3, h, h) reflectance factor
        rf2 = np.pi * mapped[..., 0] / mu_o
        de_pairs = float(np.max(gamut.mapping_delta_e(rf[:, changed].T, rf2[:, changed].T, wl, space)))
    a_before, a_after = before.albedo()[:, h:], after.albedo()[:, h:]
    de_albedo = float(np.max(gamut.mapping_delta_e(a_before.T, a_after.T, wl, space)))
    geo = [multiangle_geometry(g) for g in ASPECULAR_DEG]
    mi, mo, ph = (np.array([g[k] for g in geo]) for k in range(3))
    rg1 = np.pi * eval_table(before, mi, mo, ph) / np.abs(mo)[:, None]
    rg2 = np.pi * eval_table(after, mi, mo, ph) / np.abs(mo)[:, None]
    de_geo = gamut.mapping_delta_e(rg1, rg2, wl, space)
    info = {
        "rgb_space": gamut.RGB_SPACES[space][1], "rgb_space_key": space,
        "method": gamut.GAMUT_METHOD,
        "pairs_mapped": int(changed.sum()), "pairs_reflection": int(h * h),
        "min_desaturation_factor": float(s.min()),
        "max_dE00": max(de_pairs, de_albedo, float(de_geo.max())),
        "max_dE00_node_pairs": de_pairs, "max_dE00_albedo": de_albedo,
        "dE00_geometries": {f"{g:g}": float(d) for g, d in zip(ASPECULAR_DEG, de_geo)},
        "min_channel_before": float(c[..., 0].min()),
        "min_channel_after": float(mapped[..., 0].min()),
        "max_channel_albedo_before": float(a_before.max()), "max_channel_albedo_after": float(a_after.max()),
        "min_channel_albedo_before": float(a_before.min()), "min_channel_albedo_after": float(a_after.min()),
    }
    file_table = table_to_file_channels(after, "rgb")
    file_table.metadata.update({
        "rgb_space": info["rgb_space"], "gamut_mapping": gamut.GAMUT_METHOD,
        "gamut_pairs_mapped": info["pairs_mapped"], "gamut_max_dE00": round(info["max_dE00"], 4),
    })
    return file_table, info


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


def write_outputs(out_dir, name, table, file_table, report, h5_metadata, plan=None, h5_chunks=None):
    """Write DIR/NAME.bsdf, .h5, .json all-or-nothing (module docstring): checked by ``plan`` (default
    :func:`output_plan`), written into a staging directory, moved in together
    (:meth:`flakedb.outputs.OutputPlan.staged`).  ``h5_chunks``: the ``.h5``'s chunks already being encoded
    (:func:`flakedb.bsdf.h5file.encode_chunks_early`), or None.  Returns (paths, bsdf summary)."""
    plan = (plan or output_plan(out_dir, name)).check()
    out = Path(out_dir)
    final = {"bsdf": out / f"{name}.bsdf", "h5": out / f"{name}.h5", "json": out / f"{name}.json"}
    with plan.staged() as stage:
        summary = bsdf_files.write_bsdf(stage.path(final["bsdf"]), file_table, truncation=BSDF_TRUNCATION)
        bsdf_files.write_h5(stage.path(final["h5"]), table, h5_metadata,
                            **({} if h5_chunks is None else {"encoded": h5_chunks}))
        with open(stage.path(final["json"]), "w", encoding="utf-8") as fh:
            json.dump(report, fh, indent=1, allow_nan=False)
            fh.write("\n")
    return {k: str(v) for k, v in final.items()}, summary


def compose(recipe, out_dir, n=None, raw=False, catalog=None, log=None, store=None, verify=True,
            rgb_space="srgb", progress=None, allow_unphysical=False, colour_settings=None, inputs=()) -> ComposeResult:
    """Compose ``recipe`` (a :class:`flakedb.paint.recipe.Recipe`) into ``out_dir``; see the module docstring.

    ``n`` overrides the recipe's resolution; ``log`` (callable taking a line) reports progress.
    ``colour_settings``: the colour report's observer, illuminant and geometry set
    (:class:`flakedb.colour.settings.ColourSettings`; None: the defaults for the paint's mode).
    ``store``: None (species optics computed directly from the catalogue), a store URL or an open
    :class:`flakedb.store.versions.StoreVersion`: the catalogue species' reflectance functions come from its
    latest complete version (checksums verified first with ``verify``; compressed factors, or the
    raw samples with ``raw``).  A recipe without catalogue species does not open the store.  The solve, its
    checks and the table are :func:`solve_recipe`'s (a problem raises :class:`UnphysicalResultError` before
    anything is written, or with ``allow_unphysical`` becomes a loud warning).  Raises
    :class:`flakedb.store.versions.StoreError` (:class:`~flakedb.store.versions.StoreIntegrityError` for a corrupted
    store) before writing anything.
    """
    plan = output_plan(out_dir, recipe.name, inputs).check()  # before any work
    gamut.check_space(rgb_space)
    progress = progress or (lambda stage, detail: None)
    with ThreadPoolExecutor(max_workers=1, thread_name_prefix="flakedb-texture") as pool:
        return _compose(recipe, out_dir, n, raw, catalog, log, store, verify, rgb_space, progress, allow_unphysical,
                        colour_settings, plan, pool)


def _compose(recipe, out_dir, n, raw, catalog, log, store, verify, rgb_space, progress, allow_unphysical,
             colour_settings, plan, pool) -> ComposeResult:
    """:func:`compose`'s body; ``pool`` runs the texture model (it needs neither the resolution nor the BSDF, only
    the store's cross-sections, and is grounded on the BSDF after: :func:`texture_report_grounded`) beside the
    solve, whose numpy and LAPACK calls leave the interpreter free most of the time."""
    observers = list(TEXTURE_OBSERVERS.values())
    texture = []

    def start_texture(stored):
        if not texture:  # once: auto's refinement re-solves at another n, and the texture does not depend on n
            texture.append(pool.submit(texture_report, recipe, observers, None, stored))
            pool.submit(preload_h5py)  # then h5py's import, off the write's path (flakedb.bsdf.h5file)

    rep = solve_reported(recipe, n, raw, catalog, log, store, verify, progress, allow_unphysical, colour_settings,
                         on_stored=start_texture)
    h5_chunks = encode_chunks_early(rep.solved.table)  # the .h5's deflate beside the file channels, texture, .bsdf
    try:
        return _write(recipe, out_dir, raw, rgb_space, progress, plan, observers, texture, rep, h5_chunks)
    finally:
        if h5_chunks is not None:
            h5_chunks.cancel()  # chunks not yet started, when the write failed or was interrupted


def _write(recipe, out_dir, raw, rgb_space, progress, plan, observers, texture, rep, h5_chunks) -> ComposeResult:
    """:func:`compose`'s file channels, metadata, texture report and writes, after the solve and report ``rep``
    (:func:`flakedb.solve.pipeline.solve_reported`)."""
    solved, report, reason, warnings, t = rep.solved, rep.report, rep.n_reason, rep.warnings, rep.timings_s
    paint, stack, table, version, n_used = solved.paint, solved.stack, solved.table, solved.version, solved.n
    progress("write", {"start": True})
    t0 = time.perf_counter()
    file_table, gamut_info = gamut_safe_file_channels(table, paint.mode, paint.wavelength_nm, rgb_space)
    if paint.mode == "spectral" and file_table.channels != ("mono",):
        file_table.metadata["channels_from"] = f"spectral bands -> CIE 1931 2deg / D65 -> {gamut_info['rgb_space']}"
    t["table_report"] = time.perf_counter() - t0 + t.pop("table") + t.pop("report")
    h5_md = {
        "recipe_text": recipe.text, "recipe_source": recipe.source,
        "store_version": STORE_NONE if version is None else version.version,
        "store_url": None if version is None else version.url,
        "species_optics": ("computed directly from the catalogue (flakedb.paint.species); no precomputed store"
                           if version is None else
                           "projected kernel factors of catalogue species from the store (flakes: spectral factor U "
                           f"and projected blocks V{', untruncated' if raw else ''}, sigma_t, sigma_s per unit loading; "
                           "pigments: Mie cross-sections and Legendre moments): no azimuthal projection "
                           "(flakedb.paint.mapping, flakedb.rt.scattering.stored, docs/store.md)"),
        "raw": bool(raw), "n_reason": reason,
        "wavelength_nm": None if paint.wavelength_nm is None else paint.wavelength_nm.tolist(),
        "components": paint.components, "paint_info": paint.info,
        "solver_info": _jsonable(stack.info), "warnings": warnings,
        "albedo_nodes_tabulated": stack.albedo(include_delta=False).tolist(),
        "delta_F_nodes": None if stack.delta_F is None else np.asarray(stack.delta_F).tolist(),
        "timings_s": dict(t),
    }
    report["store"] = solved.store_label
    report["rgb_file"] = gamut_info
    report["formulation"] = [dict(b.formulation, layer=b.path) for b in recipe.basecoats if b.formulation]  # PVC, w/v
    report["warnings"] = list(warnings)
    report["texture"] = texture_report_grounded(texture[0].result(), observers, texture_ground(  # docs/texture.md
        table, paint.mode, paint.wavelength_nm, stack.x, stack.albedo(include_delta=False), paint.eta if paint.delta else None))
    h5_md["rgb_file"] = gamut_info
    t0 = time.perf_counter()
    paths, summary = write_outputs(out_dir, recipe.name, table, file_table, report, h5_md, plan, h5_chunks)
    t["write"] = time.perf_counter() - t0
    progress("write", {"seconds": t["write"], "paths": paths})
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
