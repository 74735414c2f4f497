"""Reproduce the paper's figures (Ergun et al., Figures 4-7) into docs/figures/ (issue #7).

``python -m figures.figures [--only fig4,fig5,fig6,fig7] [--quick] [--out docs/figures]``

A pipeline at the edge: it drives the core (:func:`flakedb.compose.orchestrate.compose`,
:func:`flakedb.render.preview.render_sphere`, :func:`flakedb.appearance.report.colour_report`,
:func:`flakedb.reference.montecarlo.simulate`, :func:`figures.figure4.figure4`) and only lays out and writes
what they return.  Every number in ``docs/figures/README.md`` is written by :func:`write_readme`
from the figure JSON files, which this module writes from the computed results.

Figures
-------
* **fig4**: :func:`figures.figure4.figure4` (figures/figure4.py's defaults: n = m = 64, 200 NMF sweeps).
* **fig5**: the six ``catalog/recipes/fig5-*.yaml`` paints (opaque / translucent TiO₂-coated flakes
  on black, gray, white primers) composed at ``n`` nodes with ``step_nm`` bands, rendered as spheres
  (studio environment + sun), plus the in-plane luminance BSDF at 45° incidence and the directional
  albedo versus incident angle.
* **fig6**: solver versus the independent Monte Carlo reference (:mod:`flakedb.reference.montecarlo`) for a
  pigment paint and a mirror-flake paint.  Both are turned into the same binned table (per incident
  solver node: BSDF·|μ_o| averaged over |μ_o| × φ_d bins — the MC estimates it by counting, the solver's
  table is integrated over the same bins by :func:`flakedb.reference.montecarlo.bin_average`) and rendered by the
  same deterministic sphere shader (:func:`render_binned`), so the images differ only by the two
  BSDFs; PSNR over the sphere's pixels.  The MC runs as two independent halves, so its own noise
  level is measured too.  The paper's raw / compressed columns: a store of the two species is built
  (:func:`flakedb.pipelines.build.build`, the recipes' 380–780 nm grid, the coat's η, n = ``fig6_n``; one version with
  the flakes' spectral SVD untruncated (``--raw``), one at the default truncation) into the temporary directory, timed (the "compression" time),
  and each paint is composed three times — directly, from the store's raw samples, from its
  compressed factors — and all three are shaded like the MC reference.
* **fig7**: the eight ``catalog/recipes/fig7-*.yaml`` paints (TiO₂ 70–140 nm) as spheres, with the
  colour report's CIELAB at 15° and 45° aspecular per thickness and the hue angle versus thickness.

Outputs are written atomically (temporary file + ``os.replace``); intermediate paint files go to a
temporary directory that is removed.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import shutil
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import yaml

import flakedb.reference.montecarlo as mc
from flakedb.atomic import atomic_write
from flakedb.bsdf import open_bsdf
from flakedb.compose.orchestrate import compose
from flakedb.appearance.report import (
    channels_to_XYZ,
    directional_albedo,
    eval_table,
    reference_white,
)
from flakedb.optics.fresnel import fresnel_dielectric
from flakedb.paint.mapping import catalog_species
from flakedb.paint.recipe import parse_recipe
from flakedb.pipelines.build import build, make_request
from flakedb.reference.montecarlo import bin_average, binned_reflectance
from flakedb.render.imageio import srgb_encode, to_srgb8
from flakedb.render.preview import (
    CAMERA_DIR,
    VIEW_DIR,
    orthonormal_basis,
    render_sphere,
    studio_environment,
    studio_sun,
)
from flakedb.rt.scattering import media as rm
from flakedb.rt.adding import stack as rs
from flakedb.store import versions as st
from figures.figure4 import figure4

ROOT = Path(__file__).resolve().parents[1]
RECIPES = ROOT / "flakedb" / "catalog" / "recipes"
FIGURES = ("fig4", "fig5", "fig6", "fig7")

#: Settings of a full run (``make figures``) and of ``--quick`` (tests, smoke).
FULL = {"n": 32, "step_nm": 20, "size": 160, "spp": 32, "fig4": {"n": 64, "m": 64, "nmf_iter": 200},
        "fig6_n": 32, "fig6_paths": 100_000, "fig6_size": 160, "fig6_bins": (16, 16)}
QUICK = {"n": 16, "step_nm": 20, "size": 40, "spp": 4, "fig4": {"n": 12, "m": 12, "nmf_iter": 10},
         "fig6_n": 16, "fig6_paths": 6_000, "fig6_size": 40, "fig6_bins": (8, 8)}

FIG5_PAINTS = [(op, pr) for op in ("opaque", "translucent") for pr in ("black", "gray", "white")]
FIG7_THICKNESS_NM = tuple(range(70, 141, 10))
FIG6_PAINTS = (("pigment", "particle-cadmium-yellow"), ("mirror flakes", "particle-gray-mirror"))
#: Thread count for the preview renderer (the machine this runs on has 2 cores).
THREADS = min(2, len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1))


# --------------------------------------------------------------------------------------------
# Writing (atomic)
# --------------------------------------------------------------------------------------------
def _atomic(path, write):
    """``write(tmp)`` then rename onto ``path`` (:func:`flakedb.atomic.atomic_write`)."""
    return atomic_write(path, write)


def write_json(path, obj):
    def w(tmp):
        with open(tmp, "w", encoding="utf-8") as fh:
            json.dump(obj, fh, indent=1, allow_nan=False)
            fh.write("\n")
    return _atomic(path, w)


def save_fig(fig, path, dpi=110):
    import matplotlib.pyplot as plt  # lazy: matplotlib takes ~0.3 s to import; only plotting needs it

    _atomic(path, lambda tmp: fig.savefig(tmp, dpi=dpi, format="png"))
    plt.close(fig)


def _plt():
    import matplotlib  # lazy: matplotlib takes ~0.3 s to import; only plotting needs it

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt  # lazy: matplotlib takes ~0.3 s to import; only plotting needs it

    return plt


# --------------------------------------------------------------------------------------------
# Compose + render helpers
# --------------------------------------------------------------------------------------------
def load_variant(name, step_nm=None, mode=None):
    """The catalogue recipe ``name`` with its spectral step (and mode) overridden; returns (Recipe, changes)."""
    path = RECIPES / f"{name}.yaml"
    doc = yaml.safe_load(path.read_text(encoding="utf-8"))
    changes = {}
    sp = dict(doc.get("spectral") or {})
    if step_nm is not None and sp.get("step_nm") != step_nm:
        changes["spectral.step_nm"] = [sp.get("step_nm"), step_nm]
        sp["step_nm"] = step_nm
    if mode is not None and sp.get("mode") != mode:
        changes["spectral.mode"] = [sp.get("mode"), mode]
        sp["mode"] = mode
    doc["spectral"] = sp
    text = yaml.safe_dump(doc, sort_keys=False)
    return parse_recipe(text, source=f"{path} ({changes or 'as is'})"), changes


def compose_render(name, cfg, work, log, render=True, mode=None):
    """Compose catalogue recipe ``name`` (cfg's n and bands) into ``work`` and render its sphere.

    Returns dict(recipe, result, bsdf, image, seconds)."""
    rec, changes = load_variant(name, step_nm=cfg["step_nm"] if mode is None else None, mode=mode)
    t0 = time.perf_counter()
    res = compose(rec, work, n=cfg["n"] if mode is None else cfg["fig6_n"])
    t_comp = time.perf_counter() - t0
    out = {"recipe": rec, "changes": changes, "result": res, "compose_s": t_comp}
    if render:
        bsdf = open_bsdf(res.paths["bsdf"])
        rr = render_sphere(bsdf, studio_environment(), studio_sun(), size=cfg["size"], spp=cfg["spp"], seed=0,
                           threads=THREADS)
        out.update(bsdf=bsdf, image=rr.image, render_s=rr.seconds)
    log(f"  {name}: compose {t_comp:.1f} s" + (f", render {out['render_s']:.1f} s" if render else ""))
    return out


def sphere_grid(images, titles, rows, cols, suptitle, row_labels=None, col_labels=None, cell=2.1):
    """A matplotlib figure of sphere images (linear RGB, sRGB-encoded for display)."""
    plt = _plt()
    fig, axes = plt.subplots(rows, cols, figsize=(cell * cols + 0.4, cell * rows + 0.6), squeeze=False)
    for k, ax in enumerate(axes.ravel()):
        ax.set_xticks([])
        ax.set_yticks([])
        for s in ax.spines.values():
            s.set_visible(False)
        if k < len(images) and images[k] is not None:
            ax.imshow(to_srgb8(images[k]), interpolation="nearest")
        if k < len(titles):
            ax.set_title(titles[k], fontsize=8)
    if row_labels:
        for r, lab in enumerate(row_labels):
            axes[r, 0].set_ylabel(lab, fontsize=9)
    if col_labels:
        for c, lab in enumerate(col_labels):
            axes[0, c].set_title(lab + ("\n" + titles[c] if c < len(titles) and titles[c] else ""), fontsize=8)
    fig.suptitle(suptitle, fontsize=10)
    fig.tight_layout()
    return fig


def _white(mode, wl):
    return reference_white(mode, wl)


def luminance(values, paint):
    """Y (white = 1) of reflectance-type values (..., C) in the paint's channels."""
    return channels_to_XYZ(values, paint.mode, paint.wavelength_nm)[..., 1] / _white(paint.mode, paint.wavelength_nm)[1]


def inplane_slice(result, theta_i_deg=45.0, theta_o_deg=None):
    """Luminance reflectance factor π·f (Y) in the plane of incidence: θ_o > 0 on the specular side
    (φ_d = 0), θ_o < 0 towards the illuminator (φ_d = π).  Tabulated part (no mirror delta)."""
    th = np.arange(-85.0, 85.1, 1.0) if theta_o_deg is None else np.asarray(theta_o_deg, float)
    mu_i = math.cos(math.radians(theta_i_deg))
    mu_o = -np.cos(np.radians(np.abs(th)))
    phi = np.where(th >= 0, 0.0, np.pi)
    f_cos = eval_table(result.table, np.full(th.shape, mu_i), mu_o, phi)
    rf = np.pi * f_cos / np.abs(mu_o)[:, None]
    return th, luminance(rf, result.paint)


def albedo_curve(result, theta_deg=None):
    """(θ_i, total Y, tabulated Y): directional albedo from the solver's nodes
    (:func:`flakedb.appearance.report.directional_albedo`), mirror term included in the total."""
    th = np.arange(0.0, 86.0, 5.0) if theta_deg is None else np.asarray(theta_deg, float)
    st, paint = result.stack, result.paint
    delta_eta = paint.eta if paint.delta else None
    tot, tab, _ = directional_albedo(st.x, st.albedo(include_delta=False), th, delta_eta)
    return th, luminance(tot, paint), luminance(tab, paint)


def _lab_rows(report):
    return {f"{r['aspecular_deg']:g}": {"L": r["L"], "a": r["a"], "b": r["b"],
                                       "hue_deg": float(math.degrees(math.atan2(r["b"], r["a"])) % 360.0),
                                       "chroma": float(math.hypot(r["a"], r["b"]))}
            for r in report["geometries"]}


def _settings(cfg, keys):
    return {k: cfg[k] for k in keys}


# --------------------------------------------------------------------------------------------
# Figure 4
# --------------------------------------------------------------------------------------------
def fig4(out, cfg, log):
    """Reuse :func:`figures.figure4.figure4`, written into a temporary directory then moved in."""
    p = cfg["fig4"]
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(dir=out, prefix=".figure4."))
    try:
        table = figure4(tmp, n=p["n"], m=p["m"], nmf_iter=p["nmf_iter"])
        for f in ("figure4.json", "figure4.png"):
            os.chmod(tmp / f, 0o644)
            os.replace(tmp / f, out / f)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    r8 = {name: {m: rows[m][table["ranks"].index(8)] for m in rows} for name, rows in table["errors"].items()}
    log("  rank-8 mean relative error: " + ", ".join(f"{k} {v['sqrt_svd']:.1e}" for k, v in r8.items()))
    return table


# --------------------------------------------------------------------------------------------
# Figure 5
# --------------------------------------------------------------------------------------------
def fig5_data(cfg, log, work, render=True):
    """Compose (and render) the six Figure 5 paints; returns the per-paint records and the raw outputs."""
    recs, raw = [], []
    for op, pr in FIG5_PAINTS:
        r = compose_render(f"fig5-{op}-{pr}", cfg, work, log, render=render)
        res = r["result"]
        th_s, y_s = inplane_slice(res)
        th_a, y_tot, y_tab = albedo_curve(res)
        rep = res.report
        recs.append({
            "name": res.report["name"], "flakes": op, "primer": pr, "n": res.n, "recipe_changes": r["changes"],
            "bands": int(res.paint.wavelength_nm.size),
            "components": [{k: c[k] for k in ("kind", "species", "volume_fraction", "opaque", "orientation_alpha",
                                             "optical_depth_normal", "albedo") if k in c} for c in res.paint.components],
            "albedo_report": [{k: a[k] for k in ("theta_i_deg", "albedo_Y", "tabulated_Y", "mirror")}
                              for a in rep["albedo"]],
            "albedo_curve": {"theta_i_deg": th_a.tolist(), "total_Y": y_tot.tolist(), "diffuse_Y": y_tab.tolist()},
            "slice_45": {"theta_o_deg": th_s.tolist(), "reflectance_factor_Y": y_s.tolist()},
            "lab": _lab_rows(rep), "flop_index": rep["flop_index"],
            "compose_s": r["compose_s"], "render_s": r.get("render_s"),
        })
        raw.append(r)
    return recs, raw


def _summary5(recs):
    """Numbers the README quotes: diffuse albedo at 45° (Y) per paint and primer spreads."""
    by = {(r["flakes"], r["primer"]): r for r in recs}

    def a45(r, key="tabulated_Y"):
        return next(a[key] for a in r["albedo_report"] if a["theta_i_deg"] == 45.0)

    s = {"diffuse_albedo_Y_45": {f"{op}-{pr}": a45(by[(op, pr)]) for op, pr in FIG5_PAINTS},
         "L_45as": {f"{op}-{pr}": by[(op, pr)]["lab"]["45"]["L"] for op, pr in FIG5_PAINTS},
         "L_15as": {f"{op}-{pr}": by[(op, pr)]["lab"]["15"]["L"] for op, pr in FIG5_PAINTS}}
    for op in ("opaque", "translucent"):
        d = s["diffuse_albedo_Y_45"]
        s[f"{op}_white_minus_black"] = d[f"{op}-white"] - d[f"{op}-black"]
        L = s["L_45as"]
        s[f"{op}_L45_white_minus_black"] = L[f"{op}-white"] - L[f"{op}-black"]
    s["spread_ratio_translucent_over_opaque"] = (s["translucent_white_minus_black"]
                                                 / max(abs(s["opaque_white_minus_black"]), 1e-300))
    return s


def fig5(out, cfg, log):
    plt = _plt()
    with tempfile.TemporaryDirectory(prefix="flakedb-fig5-") as work:
        recs, raw = fig5_data(cfg, log, work)
    imgs = [r["image"] for r in raw]
    titles = [f"A={rec['albedo_report'][3]['tabulated_Y']:.3f}  L*45={rec['lab']['45']['L']:.1f}" for rec in recs]
    fig = sphere_grid(imgs, titles, 2, 3, "Figure 5: TiO₂-coated interference flakes, top opaque, bottom translucent",
                      row_labels=["opaque flakes", "translucent flakes"],
                      col_labels=["black primer", "gray primer", "white primer"])
    save_fig(fig, Path(out) / "figure5.png")

    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(10, 3.8))
    colours = {"black": "k", "gray": "0.5", "white": "C1"}
    for rec in recs:
        ls = "-" if rec["flakes"] == "translucent" else "--"
        lab = f"{rec['flakes']}, {rec['primer']}"
        ax1.semilogy(rec["slice_45"]["theta_o_deg"], np.maximum(rec["slice_45"]["reflectance_factor_Y"], 1e-4),
                     ls, color=colours[rec["primer"]], label=lab)
        ax2.plot(rec["albedo_curve"]["theta_i_deg"], rec["albedo_curve"]["diffuse_Y"], ls,
                 color=colours[rec["primer"]], label=lab)
    ax1.set_xlabel("θ_o (°), in the plane of incidence; > 0: specular side")
    ax1.set_ylabel("π·f, luminance Y (1 = white diffuser)")
    ax1.set_title("BSDF slice at θ_i = 45° (tabulated part)", fontsize=9)
    ax2.set_xlabel("θ_i (°)")
    ax2.set_ylabel("directional albedo Y (without coat mirror term)")
    ax2.set_title("directional albedo", fontsize=9)
    ax2.legend(fontsize=7)
    fig.tight_layout()
    save_fig(fig, Path(out) / "figure5-curves.png")
    data = {"figure": 5, "settings": _settings(cfg, ("n", "step_nm", "size", "spp")), "paints": recs,
            "summary": _summary5(recs),
            "render": "flakedb.render.preview.render_sphere, studio environment + studio sun, seed 0, exposure 0",
            "albedo_definition": "Y (D65, CIE 1931 2°) of the directional albedo; tabulated_Y/diffuse_Y exclude the smooth coat's mirror reflection"}
    write_json(Path(out) / "figure5.json", data)
    return data


# --------------------------------------------------------------------------------------------
# Figure 7
# --------------------------------------------------------------------------------------------
def fig7(out, cfg, log):
    plt = _plt()
    recs, imgs = [], []
    with tempfile.TemporaryDirectory(prefix="flakedb-fig7-") as work:
        for t in FIG7_THICKNESS_NM:
            r = compose_render(f"fig7-pearlescent-tio2-{t:03d}nm", cfg, work, log)
            res = r["result"]
            lab = _lab_rows(res.report)
            recs.append({"thickness_nm": t, "name": res.report["name"], "n": res.n,
                         "bands": int(res.paint.wavelength_nm.size), "recipe_changes": r["changes"],
                         "lab": {g: lab[g] for g in ("15", "45")}, "lab_all": lab,
                         "flop_index": res.report["flop_index"],
                         "albedo_Y_45": next(a["albedo_Y"] for a in res.report["albedo"] if a["theta_i_deg"] == 45.0),
                         "compose_s": r["compose_s"], "render_s": r["render_s"]})
            imgs.append(r["image"])
    titles = [f"{r['thickness_nm']} nm  a*{r['lab']['15']['a']:+.0f} b*{r['lab']['15']['b']:+.0f}" for r in recs]
    fig = sphere_grid(imgs, titles, 2, 4, "Figure 7: silica flakes coated with 70–140 nm TiO₂ (a*, b* at 15° aspecular)")
    save_fig(fig, Path(out) / "figure7.png")

    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(9, 3.6))
    t = [r["thickness_nm"] for r in recs]
    for g, st in (("15", "-o"), ("45", "--s")):
        hue = np.unwrap([r["lab"][g]["hue_deg"] for r in recs], period=360.0)
        hue -= 360.0 * np.floor(hue[0] / 360.0)
        ax1.plot(t, hue, st, label=f"{g}° aspecular")
        ax2.plot([r["lab"][g]["a"] for r in recs], [r["lab"][g]["b"] for r in recs], st, label=f"{g}° aspecular")
    for r in recs:
        ax2.annotate(str(r["thickness_nm"]), (r["lab"]["15"]["a"], r["lab"]["15"]["b"]), fontsize=7)
    ax1.set_xlabel("TiO₂ thickness (nm)")
    ax1.set_ylabel("hue angle h_ab (°, unwrapped)")
    ax1.legend(fontsize=8)
    ax2.axhline(0, color="0.8", lw=0.5)
    ax2.axvline(0, color="0.8", lw=0.5)
    ax2.set_xlabel("a*")
    ax2.set_ylabel("b*")
    ax2.set_title("CIELAB trajectory (45° illumination)", fontsize=9)
    fig.tight_layout()
    save_fig(fig, Path(out) / "figure7-hue.png")
    data = {"figure": 7, "settings": _settings(cfg, ("n", "step_nm", "size", "spp")), "paints": recs,
            "colour": "CIELAB D65/2° at aspecular 15° and 45° (illumination 45°), from the colour report"}
    write_json(Path(out) / "figure7.json", data)
    return data


# --------------------------------------------------------------------------------------------
# Figure 6: solver vs Monte Carlo reference
# --------------------------------------------------------------------------------------------
def paint_to_mc_problem(paint):
    """The :class:`flakedb.reference.montecarlo.Problem` of a :class:`flakedb.paint.mapping.Paint` (same media, same
    numbers; the Monte Carlo samples them independently of the solver)."""
    def media(m):
        if isinstance(m, rm.Mixture):
            return [x for c in m.components for x in media(c)]
        if isinstance(m, rm.PhaseMedium):
            return [mc.PhaseMedium(m.sigma_t_per_um, m.albedo, m.phase)]
        if isinstance(m, rm.FlakeMedium):
            o = m.optics
            return [mc.FlakeMedium(m.a_rho_per_um, m.alpha, np.asarray(o.R), np.asarray(o.T), c_grid=np.asarray(o.c))]
        raise TypeError(f"no Monte Carlo counterpart for {type(m).__name__}")

    if paint.top is None:
        top = None
    elif isinstance(paint.top, rs.Smooth):
        top = mc.Smooth(paint.top.eta)
    else:
        top = mc.Rough(paint.top.eta, paint.top.alpha)
    bottom = None if paint.bottom is None else mc.Lambertian(np.asarray(paint.bottom.albedo))
    return mc.Problem(tuple(mc.Slab(s.thickness_um, tuple(media(s.medium))) for s in paint.slabs), top=top,
                      bottom=bottom)


def solver_binned(table, x_nodes, mu_edges, phi_edges, n_quad=6):
    """(C, h, nμ, nφ): the table's f·|μ_o| averaged over the bins, per incident node (bin_average)."""
    C = table.coeffs.shape[0]
    out = np.zeros((C, len(x_nodes), len(mu_edges) - 1, len(phi_edges) - 1))
    for j, x in enumerate(x_nodes):
        cache = {}

        def fc(M, P, c):
            if "v" not in cache:
                cache["v"] = eval_table(table, np.full(M.shape, x), -M, P)
            return cache["v"][..., c]

        for c in range(C):
            out[c, j] = bin_average(lambda M, P: fc(M, P, c), mu_edges, phi_edges, n_quad=n_quad)
    return out


def mc_binned(problem, x_nodes, n_paths, seed, mu_edges, phi_edges):
    """Two independent half runs per incident node: binned reflectance (2, C, h, nμ, nφ), diffuse
    albedo (2, C, h) and its standard error (2, C, h)."""
    B, A, S = [], [], []
    for half in range(2):
        b, a, s = [], [], []
        for j, x in enumerate(x_nodes):
            r = binned_reflectance(problem, float(x), n_paths // 2, seed + 1000 * half + j, mu_edges, phi_edges)
            b.append(r.reflectance_binned)
            a.append(r.diffuse_albedo)
            s.append(r.albedo_se)
        B.append(np.stack(b, axis=1))
        A.append(np.stack(a, axis=1))
        S.append(np.stack(s, axis=1))
    return np.stack(B), np.stack(A), np.stack(S)


def render_binned(B, x_nodes, mu_edges, phi_edges, env, sun, delta_eta, size, extent=1.05, chunk=1024):
    """Deterministic sphere shader of a binned RGB reflectance table B (3, h, nμ, nφ) (the same
    camera and lights as :mod:`flakedb.render.preview`): per pixel centre, B linearly interpolated in μ_i
    between the nodes, each bin (both ±φ_d halves) lit by the environment at its centre direction
    times its solid angle Δ|μ|Δφ, the sun by the bin it falls into, plus the exact coat mirror term.
    Returns linear RGB (size, size, 3) and the sphere mask."""
    me, pe = np.asarray(mu_edges, float), np.asarray(phi_edges, float)
    mc_, pc = 0.5 * (me[1:] + me[:-1]), 0.5 * (pe[1:] + pe[:-1])
    dom = np.diff(me)[:, None] * np.diff(pe)[None, :]                         # (K, L), per ± half
    x = np.asarray(x_nodes, float)
    pix = 2.0 * extent / size
    cc, rr = np.meshgrid(np.arange(size), np.arange(size))
    px = -extent + (cc + 0.5) * pix
    py = extent - (rr + 0.5) * pix
    r2 = px * px + py * py
    hit = r2 < 1.0
    img = np.empty((size, size, 3))
    bg = env(CAMERA_DIR) + (sun.radiance_at(CAMERA_DIR) if sun is not None else 0.0)
    img[~hit] = bg
    n_all = np.stack([px[hit], py[hit], np.sqrt(1.0 - r2[hit])], axis=-1)
    vals = np.zeros((n_all.shape[0], 3))
    sin_o, cos_o = np.sqrt(1.0 - mc_ ** 2), mc_
    for a in range(0, n_all.shape[0], chunk):
        n = n_all[a:a + chunk]
        s, t = orthonormal_basis(n)
        mu_i = n @ VIEW_DIR
        phi_i = np.arctan2(t @ VIEW_DIR, s @ VIEW_DIR)
        j = np.clip(np.searchsorted(x, mu_i) - 1, 0, x.size - 2)
        w = np.clip((mu_i - x[j]) / (x[j + 1] - x[j]), 0.0, 1.0)
        Bp = (1 - w)[:, None, None, None] * np.moveaxis(B[:, j], 1, 0) + w[:, None, None, None] * np.moveaxis(B[:, j + 1], 1, 0)
        # Bp (P, 3, K, L)
        acc = np.zeros((n.shape[0], 3))
        for sign in (1.0, -1.0):
            phi_o = phi_i[:, None] + np.pi - sign * pc[None, :]                 # (P, L)
            d = (sin_o[None, :, None, None] * np.cos(phi_o)[:, None, :, None] * s[:, None, None, :]
                 + sin_o[None, :, None, None] * np.sin(phi_o)[:, None, :, None] * t[:, None, None, :]
                 + cos_o[None, :, None, None] * n[:, None, None, :])           # (P, K, L, 3)
            Le = env(d)
            acc += np.einsum("pckl,pklc,kl->pc", Bp, Le, dom)
        if sun is not None:
            sd = np.asarray(sun.direction)
            co = n @ sd
            up = co > 0
            phi_o = np.arctan2(t @ sd, s @ sd)
            pd = np.mod(np.pi - (phi_o - phi_i), 2 * np.pi)
            pd = np.where(pd > np.pi, 2 * np.pi - pd, pd)
            k = np.clip(np.searchsorted(me, co) - 1, 0, mc_.size - 1)
            l = np.clip(np.searchsorted(pe, pd) - 1, 0, pc.size - 1)
            bsun = Bp[np.arange(n.shape[0]), :, k, l]                            # (P, 3)
            acc += up[:, None] * bsun * (np.asarray(sun.radiance) * sun.solid_angle)[None, :]
        if delta_eta is not None:
            F = fresnel_dielectric(mu_i, delta_eta).R
            rdir = 2.0 * mu_i[:, None] * n - VIEW_DIR
            Lr = env(rdir) + (sun.radiance_at(rdir) if sun is not None else 0.0)
            acc += F[:, None] * Lr
        vals[a:a + chunk] = acc
    img[hit] = vals
    return img, hit


def psnr(a, b, mask):
    """PSNR (dB) of sRGB-encoded images (values in [0, 1], clipped) over the masked pixels."""
    d = srgb_encode(a)[mask] - srgb_encode(b)[mask]
    mse = float(np.mean(d * d))
    return float("inf") if mse == 0 else float(10.0 * math.log10(1.0 / mse))


def _finite(v):
    return v if math.isfinite(v) else None


def fig6_store(names, cfg, work, log):
    """Build the Figure 6 store (both species, the recipes' grid, n = fig6_n) in ``work``: an untruncated
    (``raw``) and a default (``compressed``) version; returns ({kind: open StoreVersion}, build record)."""
    recs = [load_variant(nm, mode="rgb")[0] for nm in names]
    wl, eta = recs[0].wavelength_nm, float(recs[0].binder_ior)
    for r in recs[1:]:
        if not (np.array_equal(r.wavelength_nm, wl) and float(r.binder_ior) == eta):
            raise ValueError("the Figure 6 paints need one wavelength grid and binder index to share a store")
    species = [p.species for r in recs for p in catalog_species(r)]
    url = str(Path(work) / "store")
    t0 = time.perf_counter()
    versions, ranks = {}, {}
    for kind in ("raw", "compressed"):  # two versions: untruncated spectral SVD (--raw) and the default
        req = make_request(species=species, n=cfg["fig6_n"], wavelength_nm=wl, store_raw=kind == "raw", eta_top=eta)
        res = build(req, url, scheduler="threads", workers=THREADS)
        versions[kind] = st.open_version(url, res["version"], verify=True)
        ranks[kind] = {f"{s}": [versions[kind].flake_info(s, cfg["fig6_n"], a).get("rank")
                                for a in versions[kind].alphas(s)] for s in species if versions[kind].alphas(s)}
    t_build = time.perf_counter() - t0
    log(f"  store: {len(species)} species, n = {cfg['fig6_n']}, {len(wl)} bands, flake spectral ranks {ranks}: "
        f"built in {t_build:.1f} s")
    return versions, {"species": species, "n": cfg["fig6_n"], "flake_ranks": ranks,
                      "bands": len(wl), "range_nm": [float(wl[0]), float(wl[-1])],
                      "eta_top": eta, "version": versions["compressed"].version, "tasks": res["tasks_total"],
                      "build_s": t_build}


def fig6_case(label, name, cfg, work, log, store=None):
    r = compose_render(name, cfg, work, log, render=False, mode="rgb")
    res = r["result"]
    paint, stack = res.paint, res.stack
    problem = paint_to_mc_problem(paint)
    nmu, nphi = cfg["fig6_bins"]
    mu_edges, phi_edges = np.linspace(0.0, 1.0, nmu + 1), np.linspace(0.0, np.pi, nphi + 1)
    x = np.asarray(stack.x)
    t0 = time.perf_counter()
    Bmc, Amc, Smc = mc_binned(problem, x, cfg["fig6_paths"], 7, mu_edges, phi_edges)
    t_mc = time.perf_counter() - t0
    t0 = time.perf_counter()
    Bs = solver_binned(res.table, x, mu_edges, phi_edges)
    t_bin = time.perf_counter() - t0
    env, sun = studio_environment(), studio_sun()
    eta = paint.eta if paint.delta else None
    size = cfg["fig6_size"]
    ref, mask = render_binned(Bmc.mean(axis=0), x, mu_edges, phi_edges, env, sun, eta, size)
    half_a, _ = render_binned(Bmc[0], x, mu_edges, phi_edges, env, sun, eta, size)
    half_b, _ = render_binned(Bmc[1], x, mu_edges, phi_edges, env, sun, eta, size)
    sol, _ = render_binned(Bs, x, mu_edges, phi_edges, env, sun, eta, size)
    p_sol = psnr(ref, sol, mask)
    p_halves = psnr(half_a, half_b, mask)
    stored, images = {}, {"direct": sol}
    for kind in (("raw", "compressed") if store is not None else ()):
        t0 = time.perf_counter()
        sres = compose(r["recipe"], Path(work) / kind, n=cfg["fig6_n"], store=store[kind], raw=kind == "raw")
        t_c = time.perf_counter() - t0
        if not np.array_equal(np.asarray(sres.stack.x), x):
            raise AssertionError("store-backed compose solved on other incident nodes than the direct one")
        Bk = solver_binned(sres.table, x, mu_edges, phi_edges)
        images[kind], _ = render_binned(Bk, x, mu_edges, phi_edges, env, sun, eta, size)
        stored[kind] = {"psnr_vs_mc_db": psnr(ref, images[kind], mask), "compose_s": t_c,
                        "albedo_max_abs_diff_vs_direct": float(np.abs(sres.stack.albedo(include_delta=False)
                                                                      - stack.albedo(include_delta=False)).max())}
        log(f"  {label}: store {kind}: PSNR vs MC {stored[kind]['psnr_vs_mc_db']:.1f} dB, compose {t_c:.1f} s")
    # albedo: solver (tabulated, at its nodes) vs MC diffuse albedo (both halves together)
    a_sol = stack.albedo(include_delta=False)                     # (C, h)
    a_mc = Amc.mean(axis=0)
    se = np.sqrt((Smc ** 2).sum(axis=0)) / 2.0
    z = np.abs(a_sol - a_mc) / np.maximum(se, 1e-300)
    rel = np.abs(a_sol - a_mc) / np.maximum(np.abs(a_mc), 1e-12)
    rec = {
        "label": label, "recipe": name, "mode": paint.mode, "n": res.n, "recipe_changes": r["changes"],
        "components": [{k: c[k] for k in ("kind", "species", "volume_fraction", "orientation_alpha",
                                         "optical_depth", "optical_depth_normal", "albedo") if k in c}
                       for c in paint.components],
        "mc_paths_per_node": cfg["fig6_paths"], "incident_nodes_mu": x.tolist(), "bins": [nmu, nphi],
        "psnr_solver_vs_mc_db": p_sol, "psnr_mc_half_vs_half_db": p_halves,
        "store": stored,
        "psnr_store_raw_vs_mc_db": stored["raw"]["psnr_vs_mc_db"] if stored else None,
        "psnr_store_compressed_vs_mc_db": stored["compressed"]["psnr_vs_mc_db"] if stored else None,
        # None: the two images are bit-identical (infinite PSNR; JSON has no infinity)
        "psnr_compressed_vs_raw_db": _finite(psnr(images["raw"], images["compressed"], mask)) if stored else None,
        "psnr_store_raw_vs_direct_db": _finite(psnr(sol, images["raw"], mask)) if stored else None,
        "psnr_mc_noise_limit_db": p_halves + 10 * math.log10(4.0),
        "albedo_solver": a_sol.tolist(), "albedo_mc": a_mc.tolist(), "albedo_mc_se": se.tolist(),
        "albedo_max_abs_diff": float(np.abs(a_sol - a_mc).max()), "albedo_max_rel_diff": float(rel.max()),
        "albedo_max_sigma": float(z.max()), "albedo_mean_sigma": float(z.mean()),
        "seconds": {"compose": r["compose_s"], "mc": t_mc, "solver_bins": t_bin},
    }
    log(f"  {label}: PSNR solver vs MC {p_sol:.1f} dB (MC half vs half {p_halves:.1f} dB); "
        f"albedo max |Δ| {rec['albedo_max_abs_diff']:.4f} ({rec['albedo_max_sigma']:.1f} σ); MC {t_mc:.0f} s")
    return rec, ref, images, mask


def fig6(out, cfg, log):
    plt = _plt()
    recs, rows = [], []
    with tempfile.TemporaryDirectory(prefix="flakedb-fig6-") as work:
        store, store_rec = fig6_store([nm for _, nm in FIG6_PAINTS], cfg, Path(work) / "build", log)
        for label, name in FIG6_PAINTS:
            rec, ref, images, mask = fig6_case(label, name, cfg, Path(work) / name, log, store=store)
            recs.append(rec)
            rows.append((ref, images, mask))
    fig, axes = plt.subplots(2, 5, figsize=(11.6, 5.4))
    for k, ((ref, images, mask), rec) in enumerate(zip(rows, recs)):
        diff = np.clip(8.0 * np.abs(srgb_encode(ref) - srgb_encode(images["compressed"])), 0, 1) * mask[..., None]
        panels = [(srgb_encode(ref), f"Monte Carlo reference\n(MC halves: {rec['psnr_mc_half_vs_half_db']:.1f} dB)"),
                  (srgb_encode(images["direct"]), f"solver, direct optics\nPSNR {rec['psnr_solver_vs_mc_db']:.1f} dB"),
                  (srgb_encode(images["raw"]), f"store, untruncated\nPSNR {rec['psnr_store_raw_vs_mc_db']:.1f} dB"),
                  (srgb_encode(images["compressed"]), "store, compressed\n"
                   f"PSNR {rec['psnr_store_compressed_vs_mc_db']:.1f} dB "
                   + ("(= raw)" if rec['psnr_compressed_vs_raw_db'] is None
                      else f"(vs raw {rec['psnr_compressed_vs_raw_db']:.1f})")),
                  (diff, "|compressed − MC| × 8")]
        for c, (im, title) in enumerate(panels):
            ax = axes[k, c]
            ax.set_xticks([])
            ax.set_yticks([])
            if im is not None:
                ax.imshow(im, interpolation="nearest")
            ax.set_title(title, fontsize=7.5)
        axes[k, 0].set_ylabel(rec["label"], fontsize=9)
    fig.suptitle("Figure 6: solver vs path-traced Monte Carlo reference (same binned shader)", fontsize=10)
    fig.tight_layout()
    save_fig(fig, Path(out) / "figure6.png")
    data = {"figure": 6, "settings": _settings(cfg, ("fig6_n", "fig6_paths", "fig6_size", "fig6_bins")),
            "paints": recs,
            "psnr_definition": "10 log10(1/MSE) of sRGB-encoded (clipped [0, 1]) pixel values over the sphere's pixels",
            "noise_limit_definition": "PSNR of the two independent MC halves + 10 log10(4): the PSNR an exact "
                                      "solver would reach against the full MC reference, limited by MC noise",
            "shader": "figures.figures.render_binned (deterministic; the same for every image)",
            "store": store_rec,
            "compression_definition": "store build (flakedb.pipelines.build.build: sampling R on the grid, sqrt-SVD "
                                      "compression, raw samples kept) of both species, wall-clock seconds"}
    write_json(Path(out) / "figure6.json", data)
    return data


# --------------------------------------------------------------------------------------------
# README (every number from the JSON files)
# --------------------------------------------------------------------------------------------
def _load(out, k):
    p = Path(out) / f"figure{k}.json"
    return json.loads(p.read_text()) if p.exists() else None


def write_readme(out):
    """docs/figures/README.md from the figure JSON files present in ``out``."""
    L = ["# The paper's figures (Ergun et al.), reproduced",
         "",
         "Generated by `make figures` (`python -m figures.figures`; `--only fig5,fig7`, `--quick`). "
         "This file is written by `figures.figures.write_readme` from the `figure*.json` next to it: "
         "every number below comes from those files. Paint parameters that the paper does not give "
         "(loadings, layer thicknesses, primer colours, flake spreads) are the catalogue's stated "
         "assumptions (`catalog/particles.yaml`, `catalog/recipes/`), so shapes and trends, not pixel "
         "values, are what compares with the paper.", ""]
    f4 = _load(out, 4)
    if f4:
        i8 = f4["ranks"].index(8) if 8 in f4["ranks"] else len(f4["ranks"]) - 1
        r = f4["ranks"][i8]
        L += ["## Figure 4: compression error versus rank (`figure4.png`, `figure4.json`)", "",
              f"Mean relative error of the reflectance table R (n = {f4['n']}, m = {f4['m']}, "
              f"{f4['wavelength_nm']:g} nm) reconstructed from rank r, for the paper's √R SVD, a plain SVD and "
              f"NMF ({f4['nmf_iter']} sweeps). At r = {r}, the paper's choice:", "",
              "| species | √R SVD | SVD | NMF |", "|---|---|---|---|"]
        for name, rows in f4["errors"].items():
            L.append(f"| {name} | {rows['sqrt_svd'][i8]:.2e} | {rows['svd'][i8]:.2e} | {rows['nmf'][i8]:.2e} |")
        L += ["", "As in the paper, the error falls steeply with r and SVD-based compression beats NMF.", ""]
    f5 = _load(out, 5)
    if f5:
        s = f5["summary"]
        st = f5["settings"]
        d, Lm = s["diffuse_albedo_Y_45"], s["L_45as"]
        L += ["## Figure 5: opaque versus translucent interference flakes (`figure5.png`, `figure5-curves.png`, `figure5.json`)", "",
              "Spheres of the six `fig5-*` recipes (pearlescent TiO₂-on-silica flakes, 3 % by volume, 15 µm "
              "basecoat, smooth clear coat); top row opaque flakes (T = 0, the Jakob 2010 flakes), bottom row "
              "translucent flakes (R and T of the transfer-matrix film); primers black, gray, white. "
              f"Composed at n = {st['n']}, {st['step_nm']} nm bands; rendered {st['size']}² px, {st['spp']} spp, "
              "studio environment + sun. `figure5-curves.png`: the luminance BSDF in the plane of incidence at "
              "θ_i = 45°, and the directional albedo versus θ_i (without the coat's mirror term).", "",
              "Diffuse directional albedo Y at θ_i = 45° and L* at 45° aspecular:", "",
              "| flakes | black | gray | white | white − black (albedo) | white − black (L*45) |", "|---|---|---|---|---|---|"]
        for op in ("opaque", "translucent"):
            L.append(f"| {op} | {d[op + '-black']:.3f} / {Lm[op + '-black']:.1f} | {d[op + '-gray']:.3f} / "
                     f"{Lm[op + '-gray']:.1f} | {d[op + '-white']:.3f} / {Lm[op + '-white']:.1f} | "
                     f"{s[op + '_white_minus_black']:+.4f} | {s[op + '_L45_white_minus_black']:+.1f} |")
        L += ["", f"What translucency changes: with opaque flakes the primer is reached only by light that "
              f"passes between the flakes, so it matters little (white − black diffuse albedo "
              f"{s['opaque_white_minus_black']:+.4f}, L*45 {s['opaque_L45_white_minus_black']:+.1f}); translucent "
              f"flakes also pass on what they transmit, which the primer returns through them, so the primer "
              f"shows through: white − black {s['translucent_white_minus_black']:+.4f} "
              f"(L*45 {s['translucent_L45_white_minus_black']:+.1f}), "
              f"{s['spread_ratio_translucent_over_opaque']:.1f}× the opaque spread. Over a white primer the "
              "transmitted (complementary) colour mixes with the reflected interference colour. This is the effect the paper's Figure 5 shows (opaque row much alike "
              "across primers, translucent row lightening from black to white); the paper gives no numbers.", ""]
    f6 = _load(out, 6)
    if f6:
        st = f6["settings"]
        L += ["## Figure 6: solver (direct, store raw, store compressed) versus Monte Carlo reference "
              "(`figure6.png`, `figure6.json`)", "",
              "The paper compares path-traced spheres (Rayleigh pigments, Jakob mirror flakes) with its model "
              "on raw and on compressed data. Here: `particle-cadmium-yellow` (Mie pigment) and "
              f"`particle-gray-mirror` (mirror flakes) in RGB mode, solver at n = {st['fig6_n']}; the independent "
              f"Monte Carlo simulator (`flakedb.reference.montecarlo`) traces {st['fig6_paths']:,} paths per incident solver node "
              f"into {st['fig6_bins'][0]}×{st['fig6_bins'][1]} (|μ_o|, φ_d) bins; the solver's table is averaged over "
              "the same bins; all images are shaded by the same deterministic sphere shader (`render_binned`), "
              "so they differ only by the BSDFs. PSNR over the sphere's pixels of the sRGB-encoded images; "
              "the MC is run as two independent halves, which measures its own noise.", ""]
        sr = f6.get("store")
        if sr:
            L += [f"Each paint is composed three times: with the species' optics computed directly, and from a "
                  f"store (`flakedb.pipelines.build`) of both species built for this figure — {sr['bands']} bands "
                  f"{sr['range_nm'][0]:g}–{sr['range_nm'][1]:g} nm, n = {sr['n']}, "
                  f"η_top = {sr['eta_top']:g}, flake spectral SVD ranks {sr['flake_ranks']} — read untruncated (`--raw`) and as "
                  f"truncated factors. Building that store (projecting the kernels once, two versions, "
                  f"{sr['tasks']} tasks) took {sr['build_s']:.1f} s.", ""]
        L += ["| paint | PSNR direct vs MC | store raw vs MC | store compressed vs MC | compressed vs raw | "
              "MC noise limit | max diffuse-albedo \\|Δ\\| (R, G, B; all nodes) | max \\|Δ\\|/σ_MC | mean \\|Δ\\|/σ_MC |",
              "|---|---|---|---|---|---|---|---|---|"]

        def db(v):
            return "identical" if v is None else f"{v:.1f} dB"

        for p in f6["paints"]:
            L.append(f"| {p['label']} | {db(p['psnr_solver_vs_mc_db'])} | {db(p.get('psnr_store_raw_vs_mc_db'))} | "
                     f"{db(p.get('psnr_store_compressed_vs_mc_db'))} | {db(p.get('psnr_compressed_vs_raw_db'))} | "
                     f"{db(p['psnr_mc_noise_limit_db'])} | {p['albedo_max_abs_diff']:.4f} | "
                     f"{p['albedo_max_sigma']:.1f} | {p['albedo_mean_sigma']:.2f} |")
        L += ["", "The noise limit is the PSNR an exact solver would reach against this MC reference "
              "(PSNR of the two MC halves + 6.02 dB); a solver PSNR close to it means the remaining "
              "difference is mostly Monte Carlo noise. The albedo columns compare the directly composed "
              "solver's diffuse albedo at its incident nodes with the MC's (both halves, σ_MC its standard "
              "error) over all nodes and channels; from noise alone the mean |Δ|/σ would be "
              f"{math.sqrt(2 / math.pi):.2f}."]
        if sr:
            dr = max(p["store"]["raw"]["albedo_max_abs_diff_vs_direct"] for p in f6["paints"])
            dc = max(p["store"]["compressed"]["albedo_max_abs_diff_vs_direct"] for p in f6["paints"])
            cr = [p["psnr_compressed_vs_raw_db"] for p in f6["paints"]]
            far = all(v is None or v > p["psnr_mc_noise_limit_db"] + 20 for v, p in zip(cr, f6["paints"]))
            L += ["", ("Raw and compressed store data give the same pictures as the direct optics to far below the "
                       "MC noise" if far else "Store data versus direct optics")
                  + ": compressed versus raw "
                  + ", ".join(f"{db(v)} ({p['label']})" for v, p in zip(cr, f6["paints"]))
                  + "; store raw versus direct "
                  + ", ".join(f"{db(p['psnr_store_raw_vs_direct_db'])} ({p['label']})" for p in f6["paints"])
                  + (" (the gray mirror's R(c) = 0.5 depends on neither angle nor wavelength: rank 1 holds it "
                     "exactly)" if any(p["label"] == "mirror flakes" and (p["psnr_compressed_vs_raw_db"] is None
                                                                          or p["psnr_compressed_vs_raw_db"] > 150)
                                       for p in f6["paints"]) else "")
                  + f"; largest diffuse-albedo difference from the direct compose {dr:.1e} (raw), "
                  f"{dc:.1e} (compressed). Compose times (s): "
                  + "; ".join(f"{p['label']} direct {p['seconds']['compose']:.2f}, raw "
                              f"{p['store']['raw']['compose_s']:.2f}, compressed {p['store']['compressed']['compose_s']:.2f}"
                              for p in f6["paints"]) + "."]
        L.append("")
    f7 = _load(out, 7)
    if f7:
        st = f7["settings"]
        L += ["## Figure 7: TiO₂ coating thickness 70–140 nm (`figure7.png`, `figure7-hue.png`, `figure7.json`)", "",
              "Spheres of the `fig7-*` recipes (silica flakes with 70…140 nm TiO₂, 4 %, black primer), "
              f"n = {st['n']}, {st['step_nm']} nm bands; CIELAB from the colour report (45° illumination):", "",
              "| TiO₂ (nm) | L*, a*, b* at 15° | hue 15° | L*, a*, b* at 45° | hue 45° |", "|---|---|---|---|---|"]
        for p in f7["paints"]:
            a, b = p["lab"]["15"], p["lab"]["45"]
            L.append(f"| {p['thickness_nm']} | {a['L']:.1f}, {a['a']:+.1f}, {a['b']:+.1f} | {a['hue_deg']:.0f}° | "
                     f"{b['L']:.1f}, {b['a']:+.1f}, {b['b']:+.1f} | {b['hue_deg']:.0f}° |")
        travel = {g: float(np.ptp(np.unwrap([p["lab"][g]["hue_deg"] for p in f7["paints"]], period=360.0)))
                  for g in ("15", "45")}
        L += ["", f"The interference colour runs around the hue circle as the film thickens: from 70 to 140 nm "
              f"the hue turns by {travel['15']:.0f}° at 15° and {travel['45']:.0f}° at 45° aspecular "
              "(yellow → orange → magenta → violet → blue → cyan → green in `figure7.png`); the paper shows "
              "the same sweep as images only, with no colour values to compare with; the 45° colour lags the 15° one, the "
              "angle-dependent colour travel of pearlescent paint (`figure7-hue.png`).", ""]
    L += ["## Timing", ""]
    tp = Path(out) / "timing.json"
    if tp.exists():
        t = json.loads(tp.read_text())
        L.append("Last full run: " + ", ".join(f"{k} {v:.0f} s" for k, v in t["seconds"].items())
                 + f"; total {t['total_s']:.0f} s on {t['cpus']} CPU(s).")
    L.append("")
    text = "\n".join(L)
    _atomic(Path(out) / "README.md", lambda tmp: Path(tmp).write_text(text, encoding="utf-8"))


# --------------------------------------------------------------------------------------------
FUNCS = {"fig4": fig4, "fig5": fig5, "fig6": fig6, "fig7": fig7}


def run(only=FIGURES, quick=False, out="docs/figures", log=print):
    cfg = QUICK if quick else FULL
    secs = {}
    results = {}
    t_all = time.perf_counter()
    for f in only:
        log(f"{f} ({'quick' if quick else 'full'}):")
        t0 = time.perf_counter()
        results[f] = FUNCS[f](out, cfg, log)
        secs[f] = time.perf_counter() - t0
        log(f"{f}: {secs[f]:.1f} s")
    total = time.perf_counter() - t_all
    if not quick and set(only) == set(FIGURES):
        write_json(Path(out) / "timing.json", {"seconds": secs, "total_s": total, "cpus": THREADS})
    write_readme(out)
    return results, secs


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--only", default=",".join(FIGURES), help="comma-separated subset of " + ",".join(FIGURES))
    ap.add_argument("--quick", action="store_true", help="small settings (tests, smoke)")
    ap.add_argument("--out", default=str(ROOT / "docs" / "figures"))
    a = ap.parse_args(argv)
    only = [s.strip() for s in a.only.split(",") if s.strip()]
    bad = [s for s in only if s not in FIGURES]
    if bad:
        ap.error(f"unknown figure(s) {bad}; choose from {', '.join(FIGURES)}")
    t0 = time.perf_counter()
    run(only, a.quick, a.out)
    print(f"figures {','.join(only)} written to {a.out} in {time.perf_counter() - t0:.1f} s")


if __name__ == "__main__":
    sys.exit(main())
