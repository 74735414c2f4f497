"""Compose a recipe into files: DIR/NAME.bsdf, DIR/NAME.h5 and DIR/NAME.json (the I/O edge).

:func:`compose` = :func:`flakedb.paint.mapping.build_paint` (physics mapping) → :func:`flakedb.paint.mapping.solve_paint`
(adding-doubling) → :func:`flakedb.bsdf.convert.stack_to_table` (the solver's blocks on the file's full node set) →
:func:`flakedb.compose.report.colour_report` → :func:`write_outputs`.

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
* ``NAME.json``: the colour report (:mod:`flakedb.compose.report`).

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
import os
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

import flakedb.bsdf as bsdf_files  # the module, so a test can replace its writers
from flakedb import __version__
from flakedb.bsdf.convert import stack_to_table
from flakedb.bsdf.h5file import preload_h5py
from flakedb.bsdf.table import ENERGY_SLACK, energy_albedo
from flakedb.colour import gamut
from flakedb.colour.colorimetry import spectra_to_rgb_matrix
from flakedb.compose.report import (
    ASPECULAR_DEG,
    colour_report,
    discretisation_error,
    eval_table,
    multiangle_geometry,
    second_solve_n,
    texture_ground,
)
from flakedb.compose.store_context import StoreContext
from flakedb.conventions import fourier_weight
from flakedb.outputs import OutputError, OutputPlan, check_output_dir  # noqa: F401  (moved; re-exported)
from flakedb.process import memory_budget_bytes
from flakedb.paint.mapping import (
    AUTO_REFINE_STEPS,
    auto_colour_target,
    build_paint,
    catalog_species,
    refine_auto_n,
    resolve_node_count,
    solve_paint,
)
from flakedb.paint.texture_inputs import texture_report, texture_report_grounded
from flakedb.store import versions as st
from flakedb.texture.instruments import PRESETS as TEXTURE_OBSERVERS

#: Order truncation of the ``.bsdf`` (flakedb.bsdf.write_bsdf): 0 keeps every order up to the last
#: non-zero coefficient, so the file evaluates to the solver's values at the nodes to float32
#: precision (docs/bsdf-format.md: "A writer is right when … evaluation at the quadrature nodes returns
#: the solver's BSDF to float32 precision").  layerlab's rule (2e-3 relative tail) changed values by
#: up to 1e-3 of the largest in a test paint; an opaque paint fills only the reflection quadrant, so
#: the full file is small (n = 64, 128 orders, RGB: ≈ 1.6 MB).
BSDF_TRUNCATION = 0.0
#: What the outputs record as the store version until the precomputed store (issue #5) exists.
STORE_NONE = "none: computed directly"


def output_plan(out_dir, name, inputs=()) -> OutputPlan:
    """The plan of compose's outputs DIR/NAME.{bsdf,h5,json} (:class:`flakedb.outputs.OutputPlan`): refused
    before any work when a name is taken by a directory, is one of ``inputs`` (``(path, label)``), or
    the directory cannot be written.

    >>> import tempfile
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
    if c.shape[0] > 1:
        scale = max(np.abs(c).max(), 1e-300)
        if all(np.abs(c[k] - c[0]).max() <= 1e-12 * scale for k in range(1, c.shape[0])):
            c = c[:1]
            channels = ("mono",)
    return table.replace(stored=np.ascontiguousarray(c), channels=channels)


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
    if mode == "spectral":
        c = np.einsum("bk,b...->k...", gamut.spectra_to_space_matrix(wl, space), c)
    else:
        c = np.einsum("jk,j...->k...", gamut.rgb_mode_to_space_matrix(wl, space), c)
    w = gamut.luminance_weights(wl, space)
    mapped, s = gamut.desaturate_to_gamut(c, w)
    before = table.replace(stored=c, channels=("R", "G", "B"))
    after = table.replace(stored=np.ascontiguousarray(mapped), channels=("R", "G", "B"))
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


def write_outputs(out_dir, name, table, file_table, report, h5_metadata, plan=None):
    """Write DIR/NAME.bsdf, .h5, .json all-or-nothing (module docstring): checked by ``plan`` (default
    :func:`output_plan`), written into a staging directory, moved in together
    (:meth:`flakedb.outputs.OutputPlan.staged`).  Returns (paths, bsdf summary)."""
    plan = (plan or output_plan(out_dir, name)).check()
    out = Path(out_dir)
    final = {"bsdf": out / f"{name}.bsdf", "h5": out / f"{name}.h5", "json": out / f"{name}.json"}
    with plan.staged() as stage:
        summary = bsdf_files.write_bsdf(stage.path(final["bsdf"]), file_table, truncation=BSDF_TRUNCATION)
        bsdf_files.write_h5(stage.path(final["h5"]), table, h5_metadata)
        with open(stage.path(final["json"]), "w", encoding="utf-8") as fh:
            json.dump(report, fh, indent=1, allow_nan=False)
            fh.write("\n")
    return {k: str(v) for k, v in final.items()}, summary


class UnphysicalResultError(ValueError):
    """The solved BSDF fails :func:`check_physical` (compose writes nothing)."""


#: A passive stack may not reflect more than 1 + ALBEDO_SLACK of the incident flux.
ALBEDO_SLACK = 1e-3
#: Negative cosine-weighted BSDF values below −NEGATIVE_SLACK × its maximum are errors.  Measured
#: (2026-12-01, 181 azimuths, product settings): every catalogue recipe at n = 16, 32 and auto ≥ −2.4e-5
#: (coated aluminium; all others ≥ 0); mirror flakes α 0.05–0.15 at n 32–48 ≥ −3.3e-5, also with every
#: order kept; rough coats α 0.02–0.3 over white or an HG slab, n 32–128, ≥ −9e-6 (Jackson-filtered
#: where the 2n cap binds, docs/rough-interfaces.md "Positivity"); a medium kernel cut by the cap
#: (perfect mirror flakes α 0.15 in air at n 32 rang to −3.5 %) is Jackson-filtered the same way
#: (flakedb.rt.medium_projection.damp_if_capped): −2.4e-5.  So the threshold is 1e-3, 30× the worst measured value.
NEGATIVE_SLACK = 1e-3


def check_physical(stack, n_phi=37):
    """Problems of a solved (passive) stack, as one-line strings (empty: none).

    * directional albedo (table + delta) above 1 + :data:`ALBEDO_SLACK` at any node and channel;
    * a negative cosine-weighted BSDF f μ_i μ_o (node pairs × ``n_phi`` azimuths in [0, π]) below
      −:data:`NEGATIVE_SLACK` × its maximum;
    * the order choice did not converge (``info['order_converged']`` False) or the rough interface's
      energy scaling failed (non-finite values).
    """
    problems = []
    A = stack.albedo()
    if not np.all(np.isfinite(A)) or not np.all(np.isfinite(stack.Rt)):
        return ["the BSDF has non-finite values (solver failure)"]
    amax = float(A.max())
    if amax > 1.0 + ALBEDO_SLACK:
        c, i = np.unravel_index(int(np.argmax(A)), A.shape)
        problems.append(f"albedo {amax:.6f} > 1 + {ALBEDO_SLACK:g} at θ_i = {np.degrees(np.arccos(stack.x[i])):.1f}° "
                        f"(channel {c}) for a passive stack")
    gmax, gmin = _bsdf_range(stack, np.linspace(0.0, np.pi, n_phi))
    if gmax > 0 and gmin < -NEGATIVE_SLACK * gmax:
        problems.append(f"negative BSDF value: f·μ_i·μ_o = {gmin:.3g} (max {gmax:.3g}, allowed down to "
                        f"−{NEGATIVE_SLACK:g} × max)")
    if stack.info.get("order_converged") is False:
        problems.append(f"Fourier orders did not converge (dropped tail {stack.info.get('order_tail', float('nan')):.2g} "
                        f"> order_tol {stack.info.get('order_tol')})")
    return problems


#: Channels per block of :func:`_bsdf_range` (issue 26 item 5: the whole (L, C, h, h) coefficient array
#: and its f copy held 1.15 GB each for a rough 0.1 coat over 41 bands at n = 200, 351 orders).
CHECK_CHANNEL_BLOCK = 4


def _bsdf_range(stack, phi):
    """(max, min) of the cosine-weighted BSDF f μ_i μ_o of reflection over the node pairs and azimuths ``phi``,
    a few channels at a time (:data:`CHECK_CHANNEL_BLOCK`), so no copy of the whole coefficient array is made."""
    Rt, x, w = stack.Rt, stack.x, stack.w
    cos = np.cos(np.arange(Rt.shape[0])[:, None] * phi[None, :])  # (L, P)
    # f_l μ_i μ_o = S_l μ_o / (c_l w_i) (conventions; StackBSDF.f_coefficients times μ_i μ_o)
    scale = (x[:, None] / w[None, :])[None, None] / fourier_weight(np.arange(Rt.shape[0]))[:, None, None, None]
    gmax, gmin = -np.inf, np.inf
    C = 1 if Rt.shape[1] > 1 and Rt.strides[1] == 0 else Rt.shape[1]  # channels solved once: one is enough
    for c0 in range(0, C, CHECK_CHANNEL_BLOCK):
        g = np.matmul(np.moveaxis(Rt[:, c0:c0 + CHECK_CHANNEL_BLOCK] * scale, 0, -1), cos)  # (c, o, i, P)
        gmax, gmin = max(gmax, float(g.max())), min(gmin, float(g.min()))
    return gmax, gmin


@dataclass
class SolvedRecipe:
    """A recipe solved through the one path (:func:`solve_recipe`): its solver inputs, the solved stack, the
    full-precision table and what was decided on the way."""

    paint: object
    stack: object
    table: object
    n: int
    n_reason: str
    warnings: list
    timings_s: dict
    version: object = None
    store_label: str = STORE_NONE
    stored: object = None  # the StoreContext the optics came from (None: computed directly)
    before: object = None  # what ``before_solve`` returned (compose: the discretisation's second report)


def solve_recipe(recipe, n=None, raw=False, catalog=None, log=None, store=None, verify=True, progress=None,
                 allow_unphysical=False, generator="flakedb compose", n_reason=None, on_stored=None,
                 before_solve=None) -> SolvedRecipe:
    """Recipe → checked solution → full-precision table: the one orchestration that compose and match share.

    The node count from :func:`flakedb.paint.mapping.resolve_node_count` (``n`` > the recipe's > auto; ``n_reason``
    replaces the reason, for auto's refinement);
    ``store``: None, a store URL or an open :class:`flakedb.store.versions.StoreVersion` (checked against the
    recipe, its checksums verified with ``verify``); the solve with every core and the memory budget
    (``FLAKEDB_MEMORY_BUDGET`` bytes, else the solver's default); the result checked by
    :func:`check_physical` (a problem raises :class:`UnphysicalResultError`, or with ``allow_unphysical``
    becomes a warning) and the solver's convergence notes (:func:`solver_warnings`) added to the warnings.
    ``on_stored``: called with the open :class:`StoreContext` (None without a store) before the optics are
    built (compose starts the texture model there, to run beside the solve).  ``before_solve``: called with
    ``(paint, n, version)`` after the optics are built and before the solve, its result kept as ``before``
    (compose makes its discretisation's second solve there: :func:`second_report`).
    """
    log = log or (lambda s: None)
    progress = progress or (lambda stage, detail: None)
    n_used, reason = resolve_node_count(recipe, n)
    reason = n_reason or reason  # auto's refinement (compose) names its own reason
    warnings = list(recipe.warnings)
    t = {}
    version = stored = None
    store_label = STORE_NONE
    if store is not None and catalog_species(recipe):
        t0 = time.perf_counter()
        if isinstance(store, st.StoreVersion):
            version, stored = store, StoreContext.for_recipe(store, recipe, n_used, raw)
        else:
            stored = StoreContext.open_for_recipe(str(store), recipe, n_used, raw)
            version = stored.version
        if verify:  # the checksums of every file this recipe reads, V's order chunks as read (docs/store.md)
            version.verify(stored.prefixes(recipe))
        t["store_open"] = time.perf_counter() - t0
        store_label = f"{version.url} version {version.version} ({'raw' if raw else 'compressed'})"
        log(f"store: {store_label}, opened{' and verified' if verify else ''} in {t['store_open']:.2f} s")
    if on_stored is not None:
        on_stored(stored)
    t0 = time.perf_counter()
    progress("optics", {"start": True})
    paint = build_paint(recipe, catalog, stored=stored)
    t["optics"] = time.perf_counter() - t0
    log(f"optics: {len(paint.components)} component(s), {paint.n_channels} channel(s) ({paint.mode}), "
        f"{t['optics']:.2f} s")
    progress("optics", {"seconds": t["optics"], "channels": paint.n_channels})
    before = None if before_solve is None else before_solve(paint, n_used, version)
    t0 = time.perf_counter()
    stack = solve_paint(paint, n_used, memory_budget_bytes=memory_budget_bytes(),  # units parsed (flakedb.process)
                        threads=os.cpu_count() or 1, progress=progress)
    t["solve"] = time.perf_counter() - t0
    log(f"solve: n = {n_used} ({reason}), {stack.info.get('orders')} Fourier orders, {t['solve']:.2f} s")
    problems = check_physical(stack)
    if problems and not allow_unphysical:
        raise UnphysicalResultError(
            f"recipe {recipe.name}: unphysical result at n = {n_used}: " + "; ".join(problems)
            + "; nothing written.  Raise the resolution (--n) or rerun with --allow-unphysical to write it anyway.")
    for p in problems:
        warnings.append(f"UNPHYSICAL RESULT (written because of --allow-unphysical): {p}")
    solver_notes = solver_warnings(stack.info, n_used)
    for w in solver_notes:
        progress("warning", {"message": w})
    warnings += solver_notes
    md = {"recipe": recipe.name, "flakedb_version": __version__, "mode": paint.mode, "n_nodes": n_used,
          "store": store_label, "generator": generator}
    if recipe.description:
        md["description"] = " ".join(str(recipe.description).split())
    flakes = {c["path"]: c["orientation_distribution"] for c in paint.components if "orientation_distribution" in c}
    if flakes:  # the flakes' normal distribution (flakedb.rt.microflake.FLAKE_DISTRIBUTIONS), by recipe path
        md["flake_distributions"] = flakes
    t0 = time.perf_counter()
    table = stack_to_table(stack, paint.channels, paint.eta, None, paint.delta, md)  # α from the solved stack
    t["table"] = time.perf_counter() - t0
    # what `flakedb info` checks on the written file (issue 38), for an opaque paint (primer or metal base): a table
    # with transmission (a research stack without a bottom) holds the unscattered beam as a one-node spike that
    # the Catmull-Rom integral overshoots (an index-matched HG slab: 1.033 at n = 16 where the quadrature's is 1)
    written = float(energy_albedo(table).max()) if table.reflection_only else 0.0
    if written > 1.0 + ENERGY_SLACK:
        problem = (f"the written table's albedo reaches {written:.4f} > 1 + {ENERGY_SLACK:g} (the Catmull-Rom integral "
                   f"over its {table.n} nodes that renderers and `flakedb info` use; the solver's own albedo "
                   f"{float(stack.albedo().max()):.4f}): a lobe narrower than the node spacing (a metal or coat "
                   f"roughness near 0.01, aligned flakes)")
        if not allow_unphysical:
            raise UnphysicalResultError(
                f"recipe {recipe.name}: unphysical result at n = {n_used}: {problem}; nothing written.  Raise the "
                f"resolution (--n), make the narrowest surface rougher, or rerun with --allow-unphysical to write it "
                f"anyway.")
        warnings.append(f"UNPHYSICAL RESULT (written because of --allow-unphysical): {problem}")
    return SolvedRecipe(paint=paint, stack=stack, table=table, n=n_used, n_reason=reason, warnings=warnings,
                        timings_s=t, version=version, store_label=store_label, stored=stored, before=before)


def second_report(paint, n, version, colour_settings=None, progress=None):
    """``(n', colour report at n')`` of the discretisation's second solve at n' = :func:`flakedb.compose.report.second_solve_n`
    (≈ 3n/4), or a dict saying why there is none: n < 16, or a store (it holds the species' factors at its own n
    only).  Made before the solve at n (:func:`solve_recipe`'s ``before_solve``), so that its arrays are freed
    before those of n exist: made after, while n's R^t and table were held, it set the compose's peak (cadmium
    yellow under a rough 0.1 coat, 41 bands, n = 200: 3.95 GB, of which 1.6 GB the second solve's)."""
    if version is not None:
        return {"method": "not estimated: species factors from the store exist at n only"}
    if n < 16:
        return {"method": f"not estimated: n = {n} < 16"}
    progress = progress or (lambda stage, detail: None)
    n2 = second_solve_n(n)
    t0 = time.perf_counter()
    progress("discretisation", {"start": True, "n": n2})
    second = solve_paint(paint, n2, memory_budget_bytes=memory_budget_bytes(), threads=os.cpu_count() or 1)
    table = stack_to_table(second.scattered(), paint.channels, paint.eta, None, paint.delta, {})
    x, albedo = second.x, second.albedo(include_delta=False)
    del second  # its R^t, before the report's evaluation
    report = colour_report(table, paint.mode, paint.wavelength_nm, x, albedo, paint.eta if paint.delta else None, "",
                           settings=colour_settings)
    progress("discretisation", {"seconds": time.perf_counter() - t0, "n": n2})
    return n2, report


def discretisation_estimate(solved, report, log=None) -> dict:
    """The estimated ΔE00 of the solve's own discretisation: the report against the second solve at
    n' = :func:`flakedb.compose.report.second_solve_n` (≈ 3n/4; :func:`flakedb.compose.report.discretisation_error`,
    docs/resolution.md) that :func:`second_report` made before the solve (``solved.before``), for n ≥ 16 without
    a store (a store holds the species' factors at its own n only)."""
    n, second = solved.n, solved.before
    if isinstance(second, dict):
        return second
    n2, report_second = second
    est = discretisation_error(report, report_second, n, n2)
    if log:
        log(f"discretisation: estimated dE00(n, 2n) {est['estimate_dE00']:.3f}, at most "
            f"{est['estimate_dE00_converged']:.3f} against the converged answer, at n = {n} (second solve at n = {n2})")
    return est


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

    second_s = []

    def second(paint, n_solve, version):  # the discretisation's second solve, before the solve at n_solve
        t0 = time.perf_counter()
        try:
            return second_report(paint, n_solve, version, colour_settings, progress)
        finally:
            second_s.append(time.perf_counter() - t0)

    solved = solve_recipe(recipe, n, raw, catalog, log, store, verify, progress, allow_unphysical,
                          on_stored=start_texture, before_solve=second)
    auto_reason, refined, spent = solved.n_reason, [], 0.0
    colour_target = auto_colour_target(recipe)[0]
    while True:  # resolution: auto checks its own result (flakedb.paint.mapping.refine_auto_n)
        paint, stack, table, version = solved.paint, solved.stack, solved.table, solved.version
        warnings, t = solved.warnings, solved.timings_s
        progress("write", {"start": True})
        t0 = time.perf_counter()
        # aspecular geometries never hit an inner mirror: its smoothed series kept out of the report (docs/model.md §4)
        report_table = table if stack.specular is None else stack_to_table(
            stack.scattered(), paint.channels, paint.eta, None, paint.delta, dict(table.metadata))
        report = colour_report(report_table, paint.mode, paint.wavelength_nm, stack.x,
                               stack.albedo(include_delta=False), paint.eta if paint.delta else None, recipe.name,
                               settings=colour_settings)
        report["discretisation"] = discretisation_estimate(solved, report, log)
        est = report["discretisation"].get("estimate_dE00")
        if n is not None or recipe.n is not None or est is None:
            break
        n_new, why = refine_auto_n(recipe, solved.n, est)
        if n_new is None or len(refined) >= AUTO_REFINE_STEPS:
            if refined or est > colour_target:
                refined.append(why if n_new is None else f"stopped after {AUTO_REFINE_STEPS} refinements: {why}")
            break
        if log:
            log(why)
        refined.append(why)
        spent += time.perf_counter() - t0 + sum(solved.timings_s.values()) + (second_s[-1] if second_s else 0.0)
        solved = solve_recipe(recipe, n_new, raw, catalog, log, store, verify, progress, allow_unphysical,
                              n_reason=why, before_solve=second)
    n_used = solved.n
    reason = auto_reason if not refined else auto_reason + "; " + "; ".join(refined)
    if refined and est is not None and est > colour_target:
        warnings = list(warnings) + [f"resolution auto: {refined[-1]}"]
    if spent:
        t["refinement"] = spent
    if second_s and second_s[-1] > 0.0:  # the last solve's discretisation solve (earlier ones are in "refinement")
        t["discretisation"] = second_s[-1]
    file_table, gamut_info = gamut_safe_file_channels(table, paint.mode, paint.wavelength_nm, rgb_space)
    if paint.mode == "spectral" and file_table.channels != ("mono",):
        file_table.metadata["channels_from"] = f"spectral bands -> CIE 1931 2deg / D65 -> {gamut_info['rgb_space']}"
    t["table_report"] = time.perf_counter() - t0 + t.pop("table")
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
    report["store"] = solved.store_label
    report["rgb_file"] = gamut_info
    report["warnings"] = list(warnings)
    report["texture"] = texture_report_grounded(texture[0].result(), observers, texture_ground(  # docs/texture.md
        table, paint.mode, paint.wavelength_nm, stack.x, stack.albedo(include_delta=False), paint.eta if paint.delta else None))
    h5_md["rgb_file"] = gamut_info
    t0 = time.perf_counter()
    paths, summary = write_outputs(out_dir, recipe.name, table, file_table, report, h5_md, plan)
    t["write"] = time.perf_counter() - t0
    progress("write", {"seconds": t["write"], "paths": paths})
    return ComposeResult(paths=paths, report=report, n=n_used, n_reason=reason, timings_s=t, bsdf_summary=summary,
                         warnings=warnings, paint=paint, stack=stack, table=table)


#: Above this, the kernel renormalisation (flakedb.rt.stack.project_medium: σ_s of the discrete kernel made equal to
#: the accurately integrated one) is reported as a warning: the nodes under-resolve the kernel's peaks.
RENORM_WARN = 0.01


def solver_warnings(info, n) -> list:
    """Convergence problems in the solver's ``info`` (:func:`flakedb.rt.stack.solve_stack`), as one-line
    warnings in words: a kernel whose azimuthal projection stopped at its sampling limit before its
    tolerance, a renormalisation larger than :data:`RENORM_WARN`, an order choice that did not converge.
    The same text goes to the terminal, the ``.h5`` (``warnings``) and the colour report."""
    out = []
    groups = info.get("groups") or [info]
    seen = set()
    for g in groups:
        for k in sorted(key for key in g if key.startswith("slab")):
            sl = g[k]
            layer = int(k[4:]) + 1
            if sl.get("converged") is False and ("conv", layer) not in seen:
                seen.add(("conv", layer))
                out.append(f"basecoat layer {layer}: the azimuthal projection of its scattering kernel stopped at "
                           f"{sl.get('n_phi')} azimuth samples before reaching its tolerance (tail "
                           f"{sl.get('tail', 0):.1e}); orders are capped at {sl.get('orders')} for n = {n}: "
                           f"a larger --n resolves narrower lobes")
            dev = sl.get("renorm_max_dev")
            if dev is not None and dev > RENORM_WARN and ("renorm", layer) not in seen:
                seen.add(("renorm", layer))
                out.append(f"basecoat layer {layer}: the kernel was renormalised by up to {100 * dev:.1f}% to "
                           f"conserve its scattering (nodes coarser than its peaks at n = {n}); a larger --n "
                           f"reduces it")
        if g.get("order_converged") is False and "orders" not in seen:
            seen.add("orders")
            out.append(f"Fourier orders: the dropped tail {g.get('order_tail', float('nan')):.1e} is above the "
                       f"tolerance {g.get('order_tol', float('nan')):.0e} at the cap of {g.get('orders_available')} "
                       f"orders (n = {n})")
    return out


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
