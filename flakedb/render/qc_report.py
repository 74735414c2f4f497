"""The one-page QC report of a paint against its target (``flakedb report``): a PDF page and a PNG of it.

:class:`QCPage` holds the numbers (arrays, no recipe or file); :func:`qc_figure` draws them on one
A4-landscape matplotlib Figure (Agg canvas); :func:`write_qc_report` writes that figure as a one-page
PDF (``PdfPages``, the target and verdict in its metadata) and as a PNG of the same page.

Panels: L*, a*, b* against the aspecular angle (predicted, the target joined and named, and the
tolerance band: the range of that coordinate alone, the others at the target, within the geometry's
limit in the chosen formula, :func:`flakedb.colour.bands.coordinate_bands`); ΔE per geometry against
its limit (bars red where it fails); the a*b* travel with geometry labels that do not collide
(:func:`flakedb.render.plots.place_labels`); the reflectance factor per geometry (spectral predictions; the
target dashed when it is spectral), one colour per geometry (:func:`flakedb.render.plots.geometry_colours`);
the texture indices; the verdict: PASS / FAIL, the worst geometry, and the shade words per geometry.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from flakedb.colour.geometry import as_geometry_array
from flakedb.render.plots import freeze_layout, geometry_colours, geometry_label, label_travel

#: The page: A4 landscape [inches].
PAGE_INCHES = (11.69, 8.27)
#: Resolution of the PNG [dots per inch].
PNG_DPI = 110


@dataclass
class QCPage:
    """What one QC page shows (module docstring).  Arrays: ``geometries`` (G, 2) = (illumination_deg,
    aspecular_deg); ``lab`` / ``lab_target`` (G, 3); ``de`` / ``limit`` (G,) in ``formula``; ``passed`` (G,);
    ``band`` (G, 3, 2): steps (t₋, t₊) of L*, a*, b* from the target within the limit; ``shade`` (G,) words;
    spectra (G, W) on their grids or None; ``texture``: rows {index, unit, predicted, target, tolerance,
    passed} (target / tolerance / passed None when the target has no texture columns)."""

    recipe: str
    target: str
    geometries: np.ndarray
    lab: np.ndarray
    lab_target: np.ndarray
    formula: str
    de: np.ndarray
    limit: np.ndarray
    passed: np.ndarray
    band: np.ndarray
    shade: list
    conditions: str = ""
    wavelength_nm: np.ndarray | None = None
    reflectance: np.ndarray | None = None
    target_wavelength_nm: np.ndarray | None = None
    target_reflectance: np.ndarray | None = None
    texture: list = field(default_factory=list)
    texture_note: str = ""
    notes: list = field(default_factory=list)

    @property
    def texture_passed(self) -> bool:
        return all(r["passed"] is not False for r in self.texture)

    @property
    def verdict(self) -> str:
        """"PASS" when every geometry is within its limit and every texture index with a target within its
        tolerance, else "FAIL"."""
        return "PASS" if bool(np.all(self.passed)) and self.texture_passed else "FAIL"

    @property
    def worst(self) -> int:
        """Index of the geometry with the largest ΔE / limit (the largest ΔE where a limit is 0)."""
        de, lim = np.asarray(self.de, float), np.asarray(self.limit, float)
        ratio = np.where(lim > 0, de / np.where(lim > 0, lim, 1.0), np.where(de > 0, np.inf, 0.0))
        return int(np.argmax(ratio))

    def summary(self) -> str:
        """The verdict line.

        >>> g = np.array([[45.0, 15.0], [45.0, 110.0]])
        >>> page = QCPage("silver", "A-17", g, np.zeros((2, 3)), np.zeros((2, 3)), "dE00", np.array([0.4, 2.5]),
        ...               np.array([1.0, 2.0]), np.array([True, False]), np.zeros((2, 3, 2)), ["same", "darker"])
        >>> page.summary()
        'FAIL: 1 of 2 geometries outside their dE00 limits; worst 45as110: dE00 2.50 > 2.00 (darker)'
        """
        w = self.worst
        g = self.geometries[w]
        n_fail = int(np.sum(~np.asarray(self.passed, bool)))
        op = "<=" if self.passed[w] else ">"
        line = (f"{self.verdict}: {n_fail} of {len(self.passed)} geometries outside their {self.formula} limits; "
                f"worst {geometry_label(g)}: {self.formula} {self.de[w]:.2f} {op} {self.limit[w]:.2f} "
                f"({self.shade[w]})")
        t_fail = [r["index"] for r in self.texture if r["passed"] is False]
        if t_fail:
            line += f"; texture outside tolerance: {', '.join(t_fail)}"
        return line


def qc_figure(page: QCPage):
    """The report page as a matplotlib Figure on an Agg canvas (module docstring)."""
    from matplotlib.backends.backend_agg import (
        FigureCanvasAgg,  # lazy: matplotlib takes ~0.3 s to import; only plotting needs it
    )
    from matplotlib.figure import Figure  # lazy: matplotlib takes ~0.3 s to import; only plotting needs it

    g = as_geometry_array(page.geometries)
    lab, lt = np.asarray(page.lab, float), np.asarray(page.lab_target, float)
    if not (np.all(np.isfinite(lab)) and np.all(np.isfinite(lt))):
        raise ValueError("qc_figure: L*a*b* values must be finite")
    band = np.asarray(page.band, float)
    fig = Figure(figsize=PAGE_INCHES, layout="constrained")
    FigureCanvasAgg(fig)
    grid = fig.add_gridspec(3, 4, height_ratios=[1.0, 1.0, 0.95])
    illums = sorted(set(g[:, 0].tolist()), reverse=True)
    ill_col = {il: f"C{k}" for k, il in enumerate(illums)}
    for c, name in enumerate(("L*", "a*", "b*")):
        ax = fig.add_subplot(grid[0, c])
        for il in illums:
            oop = np.flatnonzero((g[:, 0] == il) & (g[:, 2] != 0.0))   # out of plane: points, not curves
            if oop.size:
                ax.plot(g[oop, 1], lt[oop, c], "v", ms=6, mfc="none", color=ill_col[il])
                ax.plot(g[oop, 1], lab[oop, c], "^", ms=4.5, color=ill_col[il],
                        label=f"predicted, {il:g}° out of plane")
            sel = np.flatnonzero((g[:, 0] == il) & (g[:, 2] == 0.0))
            sel = sel[np.argsort(g[sel, 1])]
            x = g[sel, 1]
            ax.fill_between(x, lt[sel, c] + band[sel, c, 0], lt[sel, c] + band[sel, c, 1], color=ill_col[il],
                            alpha=0.15, lw=0, label=f"tolerance, {il:g}°")
            ax.plot(x, lt[sel, c], "--s", ms=5, mfc="none", lw=1.0, color=ill_col[il],
                    label=f"{page.target}, {il:g}°")
            ax.plot(x, lab[sel, c], "-o", ms=3.5, color=ill_col[il], label=f"predicted, {il:g}°")
        ax.set(xlabel="aspecular angle (°)", ylabel=name, title=f"{name} vs aspecular angle")
        ax.title.set_fontsize(9)
        ax.tick_params(labelsize=7)
        ax.xaxis.label.set_fontsize(8)
        ax.grid(alpha=0.3)
        if c == 0:
            ax.legend(fontsize=6)
    # ΔE per geometry against its limit
    ax = fig.add_subplot(grid[0, 3])
    x = np.arange(g.shape[0])
    ok = np.asarray(page.passed, bool)
    ax.bar(x, page.de, color=np.where(ok, "#4c9a5b", "#c8453c"), width=0.7, label=page.formula)
    ax.plot(x, page.limit, "_", ms=16, mew=2, color="0.1", label="limit")
    ax.set_xticks(x, [geometry_label(v) for v in g], rotation=60, fontsize=6)
    ax.set(ylabel=page.formula, title=f"{page.formula} per geometry vs limit")
    ax.title.set_fontsize(9)
    ax.tick_params(axis="y", labelsize=7)
    ax.legend(fontsize=6)
    ax.grid(alpha=0.3, axis="y")
    # a*b* travel
    ax_ab = fig.add_subplot(grid[1, 0])
    for il in illums:
        oop = np.flatnonzero((g[:, 0] == il) & (g[:, 2] != 0.0))
        if oop.size:
            ax_ab.plot(lt[oop, 1], lt[oop, 2], "v", ms=6, mfc="none", color=ill_col[il])
            ax_ab.plot(lab[oop, 1], lab[oop, 2], "^", ms=4.5, color=ill_col[il])
        sel = np.flatnonzero((g[:, 0] == il) & (g[:, 2] == 0.0))
        sel = sel[np.argsort(g[sel, 1])]
        ax_ab.plot(lt[sel, 1], lt[sel, 2], "--s", ms=5, mfc="none", lw=1.0, color=ill_col[il],
                   label=f"{page.target}, {il:g}°")
        ax_ab.plot(lab[sel, 1], lab[sel, 2], "-o", ms=3.5, color=ill_col[il], label=f"predicted, {il:g}°")
    ax_ab.axhline(0, color="0.7", lw=0.8)
    ax_ab.axvline(0, color="0.7", lw=0.8)
    ax_ab.set(xlabel="a*", ylabel="b*", title="a*b* travel")
    ax_ab.title.set_fontsize(9)
    ax_ab.tick_params(labelsize=7)
    ax_ab.set_aspect("equal", adjustable="datalim")
    ax_ab.legend(fontsize=6)
    # spectra per geometry
    ax = fig.add_subplot(grid[1, 1:])
    if page.reflectance is not None:
        cols = geometry_colours(g.shape[0])
        for k in range(g.shape[0]):
            ax.plot(page.wavelength_nm, page.reflectance[k], color=cols[k], lw=1.2, label=geometry_label(g[k]))
            if page.target_reflectance is not None:
                ax.plot(page.target_wavelength_nm, page.target_reflectance[k], "--", lw=1.0, color=cols[k])
        ax.set(xlabel="wavelength (nm)", ylabel="reflectance factor",
               title="reflectance factor per geometry" + (f" ({page.target} dashed)"
                                                          if page.target_reflectance is not None else ""))
        ax.legend(ncol=6, fontsize=6, loc="upper left")
        ax.grid(alpha=0.3)
    else:
        ax.axis("off")
        ax.text(0.5, 0.5, "no spectra: the prediction is not spectral", ha="center", va="center", fontsize=9)
        ax.set_title("reflectance factor per geometry")
    ax.title.set_fontsize(9)
    ax.tick_params(labelsize=7)
    # verdict, shade words and texture
    ax = fig.add_subplot(grid[2, :2])
    ax.axis("off")
    colour = "#2e7d3a" if page.verdict == "PASS" else "#b3261e"
    ax.text(0.0, 1.0, page.verdict, fontsize=22, weight="bold", color=colour, va="top", transform=ax.transAxes)
    w = page.worst
    lines = [f"worst geometry {geometry_label(g[w])}: {page.formula} {page.de[w]:.2f} (limit {page.limit[w]:.2f})",
             f"{int(np.sum(~ok))} of {len(ok)} geometries outside their limits", ""]
    wl = max([8] + [len(geometry_label(v)) for v in g])   # out-of-plane names are longer
    lines += [f"{geometry_label(v):>{wl}}  {d:5.2f} / {lim:4.2f}  {'ok ' if p else 'NO '} {s}"
              for v, d, lim, p, s in zip(g, page.de, page.limit, ok, page.shade)]
    ax.text(0.0, 0.78, "\n".join(lines), fontsize=6.5, family="monospace", va="top", transform=ax.transAxes)
    ax = fig.add_subplot(grid[2, 2:])
    ax.axis("off")
    ax.set_title("texture indices", fontsize=9, loc="left")
    if page.texture:
        rows = [f"{'index':<22} {'predicted':>10} {'target':>10} {'tolerance':>9}  ok"]
        for r in page.texture:
            p = "n/a" if r["predicted"] is None else f"{r['predicted']:.4g}"
            t = "-" if r.get("target") is None else f"{r['target']:.4g}"
            tol = "-" if r.get("tolerance") is None else f"{r['tolerance']:.3g}"
            okt = "-" if r.get("passed") is None else ("yes" if r["passed"] else "NO")
            rows.append(f"{r['index']:<22} {p:>10} {t:>10} {tol:>9}  {okt}")
        text = "\n".join(rows)
    else:
        text = page.texture_note or "no texture indices"
    if page.texture and page.texture_note:
        text += "\n" + page.texture_note
    ax.text(0.0, 0.95, text, fontsize=6.5, family="monospace", va="top", transform=ax.transAxes, wrap=True)
    if page.notes:
        ax.text(0.0, 0.0, "\n".join(page.notes), fontsize=6, va="bottom", transform=ax.transAxes, wrap=True)
    fig.suptitle(f"QC report: {page.recipe} vs {page.target}" + (f"  ({page.conditions})" if page.conditions else ""),
                 fontsize=11)
    freeze_layout(fig)
    label_travel(ax_ab, g, lab, lt)
    return fig


def write_qc_report(page: QCPage, pdf_path, png_path) -> tuple:
    """Write the page as a one-page PDF (``pdf_path``; Title / Subject / Keywords metadata: the recipe and
    target, the verdict line, the target's name) and as a PNG (``png_path``, :data:`PNG_DPI`); the paths
    are written as given (the caller stages them: :class:`flakedb.outputs.OutputPlan`).  Returns the figure
    and the two paths."""
    from matplotlib.backends.backend_pdf import PdfPages  # lazy: matplotlib is only needed for plotting

    fig = qc_figure(page)
    meta = {"Title": f"flakedb QC report: {page.recipe} vs {page.target}", "Subject": page.summary(),
            "Keywords": page.target, "Creator": "flakedb report"}
    with PdfPages(Path(pdf_path), metadata=meta) as pdf:
        pdf.savefig(fig)
    fig.savefig(Path(png_path), format="png", dpi=PNG_DPI)
    return fig, Path(pdf_path), Path(png_path)
