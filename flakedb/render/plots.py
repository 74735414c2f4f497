"""Plots: a species' R and T against angle and wavelength (``flakedb species show``, the demo)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from flakedb.atomic import atomic_path
from flakedb.colour.colorimetry import spectra_to_rgb_mode, spectral_grid
from flakedb.colour.geometry import as_geometry_array
from flakedb.colour.geometry import label as _geometry_label
from flakedb.paint.catalog import TINTER_TABLES, get_species, load_catalog
from flakedb.paint.species import (
    SHOW_ANGLES_DEG,
    binder_index,
    flake_reflectance_transmittance,
    pigment_optics,
    tinter_coefficients,
)


def plot_optics(name: str, out_dir, catalog: dict | None = None) -> Path:
    """Write ``out_dir/NAME-optics.png`` (written to a temporary name, then renamed); returns the path.

    Flakes: R and T spectra at the show angles, and the flake's reflected and transmitted colour
    (RGB mode of :mod:`flakedb.colour.colorimetry`, sRGB-encoded, clipped for display only) versus angle.
    Pigments: C_ext, C_sca, single-scattering albedo and g versus wavelength.

    >>> import tempfile
    >>> path = plot_optics("gray-mirror", tempfile.mkdtemp())
    >>> path.name, path.read_bytes()[:4] == bytes([0x89]) + b"PNG"
    ('gray-mirror-optics.png', True)
    """
    from matplotlib.backends.backend_agg import (
        FigureCanvasAgg,  # lazy: matplotlib takes ~0.3 s to import; only plotting needs it
    )
    from matplotlib.figure import Figure  # lazy: matplotlib takes ~0.3 s to import; only plotting needs it

    catalog = catalog if catalog is not None else load_catalog()
    entry = get_species(name, catalog)
    wl = spectral_grid((380, 780), 5)
    nb = binder_index(catalog, wl)
    fig = Figure(figsize=(11, 4.2), layout="constrained")
    FigureCanvasAgg(fig)
    if entry["kind"] == "pigment":
        p = pigment_optics(entry, wl, nb)
        ax1, ax2 = fig.subplots(1, 2)
        ax1.plot(wl, p.c_ext_um2, label="C_ext")
        ax1.plot(wl, p.c_sca_um2, label="C_sca")
        ax1.set(xlabel="wavelength (nm)", ylabel="cross-section per particle (µm²)", title=f"{name}: Mie, log-normal")
        ax1.legend()
        ax2.plot(wl, p.c_sca_um2 / p.c_ext_um2, label="albedo C_sca/C_ext")
        ax2.plot(wl, p.g, label="asymmetry g")
        ax2.set(xlabel="wavelength (nm)", ylim=(-0.05, 1.05), title="single scattering")
        ax2.legend()
    elif entry["kind"] == "tinter":
        lo = max(entry[k]["wavelength_nm"][0] for k in TINTER_TABLES)
        hi = min(entry[k]["wavelength_nm"][-1] for k in TINTER_TABLES)
        wt = wl[(wl >= lo) & (wl <= hi)]
        a, s = tinter_coefficients(entry, wt)
        ax1, ax2 = fig.subplots(1, 2)
        ax1.semilogy(wt, a, label="σ_a / φ")
        ax1.semilogy(wt, s, label="σ_s / φ")
        ax1.set(xlabel="wavelength (nm)", ylabel="per unit volume fraction (1/µm)", title=f"{name}: tinter")
        ax1.legend()
        ax2.plot(wt, s / np.maximum(a + s, 1e-300), label="albedo σ_s/σ_t")
        ax2.axhline(entry["asymmetry_g"]["value"], color="C1", label="HG g")
        ax2.set(xlabel="wavelength (nm)", ylim=(-0.05, 1.05), title="single scattering")
        ax2.legend()
    else:
        import colour  # lazy: colour-science takes ~0.5 s to import (it pulls matplotlib)

        angles = np.asarray(SHOW_ANGLES_DEG)
        R, T = flake_reflectance_transmittance(entry, wl, np.cos(np.radians(angles)), nb)
        ax1, ax2 = fig.subplots(1, 2, width_ratios=[3, 2])
        for j, a in enumerate(angles):
            line = ax1.plot(wl, R[:, j], label=f"R {a:g}°")[0]
            ax1.plot(wl, T[:, j], ls="--", color=line.get_color(), label=f"T {a:g}°")
        ax1.set(xlabel="wavelength (nm)", ylabel="R, T (unpolarised)", ylim=(-0.02, 1.02),
                title=f"{name}: flake in {catalog['binder']['material']}")
        ax1.legend(ncol=2, fontsize=7)
        strip_deg = np.linspace(0.0, 85.0, 18)
        Rs, Ts = flake_reflectance_transmittance(entry, wl, np.cos(np.radians(strip_deg)), nb)
        rgb = np.stack([spectra_to_rgb_mode(Rs.T, wl), spectra_to_rgb_mode(Ts.T, wl)])  # (2, angles, 3)
        img = np.clip(colour.cctf_encoding(np.clip(rgb, 0.0, 1.0)), 0.0, 1.0)
        ax2.imshow(img, aspect="auto", extent=(strip_deg[0] - 2.5, strip_deg[-1] + 2.5, 1.5, -0.5))
        ax2.set(yticks=[0, 1], yticklabels=["R", "T"], xlabel="angle of incidence in the binder (°)",
                title="colour vs angle (D65, sRGB)")
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    final = out_dir / f"{name}-optics.png"
    with atomic_path(final) as tmp:
        with open(tmp, "wb") as f:
            fig.savefig(f, format="png", dpi=110)
    return final


#: Formats :func:`plot_multiangle` writes, by the path's suffix.
PLOT_FORMATS = {".png": "png", ".pdf": "pdf", ".svg": "svg"}
#: Curve colours of :func:`geometry_colours`: CIELAB lightness of even / odd entries, chroma, first hue [°].
CURVE_LIGHTNESS = (48.0, 66.0)
CURVE_CHROMA = 55.0
CURVE_HUE0_DEG = 20.0


def geometry_colours(count) -> np.ndarray:
    """``count`` distinct curve colours (count, 3), sRGB in [0, 1]: hues evenly spaced around CIELAB's hue
    circle at chroma :data:`CURVE_CHROMA`, lightness alternating between :data:`CURVE_LIGHTNESS` (so
    neighbours differ in lightness too), clipped to the sRGB gamut.  One colour per geometry, never the
    cycle of ten that gave 45as-15 and 15as80 the same blue (tests: every pair ≥ 10 ΔE00 apart for up
    to 12 geometries)."""
    import colour  # lazy: colour-science takes ~0.5 s to import (it pulls matplotlib)

    k = np.arange(int(count))
    h = np.radians(CURVE_HUE0_DEG + 360.0 * k / max(int(count), 1))
    L = np.where(k % 2 == 0, *CURVE_LIGHTNESS)
    lab = np.stack([L, CURVE_CHROMA * np.cos(h), CURVE_CHROMA * np.sin(h)], axis=-1)
    return np.clip(colour.XYZ_to_sRGB(colour.Lab_to_XYZ(lab)), 0.0, 1.0).reshape(-1, 3)


def geometry_label(geometry) -> str:
    """``45as15``, ``45as25az90``: the instrument's name of a geometry (:func:`flakedb.colour.geometry.label`)."""
    return _geometry_label(geometry)


#: Candidate label offsets of :func:`place_labels` [points]: radii, and directions (counter-clockwise from +x).
LABEL_RADII_PT = (4.0, 9.0, 15.0, 22.0, 30.0)
LABEL_DIRECTIONS_DEG = (45.0, -45.0, 135.0, -135.0, 0.0, 180.0, 90.0, -90.0)
#: Half-size of the box kept free around every labelled point [points] (its marker).
LABEL_MARKER_PT = 3.0


def _overlap(a, b) -> float:
    """Overlap area of two matplotlib Bboxes (display units); 0 when they only touch or are apart."""
    w = min(a.x1, b.x1) - max(a.x0, b.x0)
    h = min(a.y1, b.y1) - max(a.y0, b.y0)
    return w * h if w > 0 and h > 0 else 0.0


def place_labels(ax, xy, texts, fontsize=6, color="0.15") -> list:
    """Annotate the points ``xy`` (N, 2, data units) of ``ax`` with ``texts`` so that no two labels and no
    label and a marker overlap, as the renderer measures them; returns the annotations.

    Greedy: each label takes the first offset of :data:`LABEL_RADII_PT` × :data:`LABEL_DIRECTIONS_DEG`
    whose text box (``get_window_extent`` with the figure's renderer) overlaps no label already placed, no
    point's marker box (:data:`LABEL_MARKER_PT`) and neither the axes' legend nor its title; when none is free, the
    least-overlapping one.  The
    layout must be final: call it after the figure's layout is drawn and frozen (:func:`freeze_layout`),
    since the offsets are in points from data positions that a later layout would move."""
    from matplotlib.transforms import Bbox  # lazy: matplotlib takes ~0.3 s to import; only plotting needs it

    renderer = ax.figure.canvas.get_renderer()
    pts = ax.transData.transform(np.asarray(xy, float).reshape(-1, 2))
    m = LABEL_MARKER_PT * ax.figure.dpi / 72.0
    taken = [Bbox.from_extents(x - m, y - m, x + m, y + m) for x, y in pts]
    if ax.get_legend() is not None:   # the legend is drawn over the axes: keep the labels off it too
        taken.append(ax.get_legend().get_window_extent(renderer))
    if ax.get_title():
        taken.append(ax.title.get_window_extent(renderer))
    out = []
    for (x, y), text, p in zip(np.asarray(xy, float).reshape(-1, 2), texts, pts):
        best = None
        for r in LABEL_RADII_PT:
            for d in LABEL_DIRECTIONS_DEG:
                dx, dy = r * np.cos(np.radians(d)), r * np.sin(np.radians(d))
                ha = "left" if dx > 0.5 else "right" if dx < -0.5 else "center"
                va = "bottom" if dy > 0.5 else "top" if dy < -0.5 else "center"
                ann = ax.annotate(text, (x, y), xytext=(dx, dy), textcoords="offset points", fontsize=fontsize,
                                  ha=ha, va=va, color=color, annotation_clip=False)
                box = ann.get_window_extent(renderer)
                cost = sum(_overlap(box, t) for t in taken)
                if best is None or cost < best[0]:
                    if best is not None:
                        best[1].remove()
                    best = (cost, ann, box)
                else:
                    ann.remove()
                if cost == 0.0:
                    break
            if best[0] == 0.0:
                break
        taken.append(best[2])
        out.append(best[1])
    return out


def freeze_layout(fig) -> None:
    """Draw ``fig`` once so its layout engine places the axes, then switch the engine off: positions stay
    as drawn (what :func:`place_labels` needs before it measures)."""
    fig.draw_without_rendering()
    fig.set_layout_engine("none")


def multiangle_figure(geometries, lab, lab_target=None, wavelength_nm=None, reflectance=None,
                      target_reflectance=None, target_wavelength_nm=None, title="", conditions="",
                      target_name="target"):
    """The figure of :func:`plot_multiangle` (a matplotlib Figure on an Agg canvas, not written)."""
    from matplotlib.backends.backend_agg import (
        FigureCanvasAgg,  # lazy: matplotlib takes ~0.3 s to import; only plotting needs it
    )
    from matplotlib.figure import Figure  # lazy: matplotlib takes ~0.3 s to import; only plotting needs it

    g = as_geometry_array(geometries)
    lab = np.asarray(lab, float)
    lt = None if lab_target is None else np.asarray(lab_target, float)
    if not (np.all(np.isfinite(lab)) and (lt is None or np.all(np.isfinite(lt)))):
        raise ValueError("plot_multiangle: L*a*b* values must be finite")
    spectra = reflectance is not None
    fig = Figure(figsize=(15, 8.2) if spectra else (15, 4.6), layout="constrained")
    FigureCanvasAgg(fig)
    axes = fig.subplots(2 if spectra else 1, 4, squeeze=False)
    illums = sorted(set(g[:, 0].tolist()), reverse=True)
    colours = {il: f"C{k}" for k, il in enumerate(illums)}
    tname = target_name or "target"
    for c, (name, ax) in enumerate(zip(("L*", "a*", "b*"), axes[0, :3])):
        for il in illums:
            sel = np.flatnonzero((g[:, 0] == il) & (g[:, 2] == 0.0))
            sel = sel[np.argsort(g[sel, 1])]
            ax.plot(g[sel, 1], lab[sel, c], "-o", ms=4, color=colours[il], label=f"predicted, {il:g}° illum.")
            if lt is not None:
                ax.plot(g[sel, 1], lt[sel, c], "--s", ms=7, mfc="none", lw=1.0, color=colours[il],
                        label=f"{tname}, {il:g}° illum.")
            oop = np.flatnonzero((g[:, 0] == il) & (g[:, 2] != 0.0))   # out of plane: points, not a curve
            if oop.size:
                ax.plot(g[oop, 1], lab[oop, c], "^", ms=6, color=colours[il],
                        label=f"predicted, {il:g}° illum., out of plane")
                if lt is not None:
                    ax.plot(g[oop, 1], lt[oop, c], "v", ms=8, mfc="none", color=colours[il],
                            label=f"{tname}, {il:g}° illum., out of plane")
        ax.set(xlabel="aspecular angle (°)", ylabel=name, title=f"{name} vs aspecular angle")
        ax.grid(alpha=0.3)
    axes[0, 0].legend(fontsize=7)
    ax = axes[0, 3]
    for il in illums:
        sel = np.flatnonzero((g[:, 0] == il) & (g[:, 2] == 0.0))
        sel = sel[np.argsort(g[sel, 1])]
        if sel.size:
            ax.plot(lab[sel, 1], lab[sel, 2], "-o", ms=4, color=colours[il], label=f"predicted, {il:g}°")
            ax.plot(lab[sel[0], 1], lab[sel[0], 2], "*", ms=12, color=colours[il])
            if lt is not None:
                ax.plot(lt[sel, 1], lt[sel, 2], "--s", ms=7, mfc="none", lw=1.0, color=colours[il],
                        label=f"{tname}, {il:g}°")
        oop = np.flatnonzero((g[:, 0] == il) & (g[:, 2] != 0.0))
        if oop.size:
            ax.plot(lab[oop, 1], lab[oop, 2], "^", ms=6, color=colours[il], label=f"predicted, {il:g}° out of plane")
            if lt is not None:
                ax.plot(lt[oop, 1], lt[oop, 2], "v", ms=8, mfc="none", color=colours[il],
                        label=f"{tname}, {il:g}° out of plane")
    ax.axhline(0, color="0.7", lw=0.8)
    ax.axvline(0, color="0.7", lw=0.8)
    ax.set(xlabel="a*", ylabel="b*", title="colour travel (★ = smallest aspecular)")
    ax.set_aspect("equal", adjustable="datalim")
    ax.legend(fontsize=7)
    if spectra:
        wl = np.asarray(wavelength_nm, float)
        R = np.asarray(reflectance, float)
        gs = axes[1, 0].get_gridspec()
        for a in axes[1, :]:
            a.remove()
        ax = fig.add_subplot(gs[1, :])
        cols = geometry_colours(g.shape[0])
        for k in range(g.shape[0]):
            ax.plot(wl, R[k], color=cols[k], label=geometry_label(g[k]))
            if target_reflectance is not None:
                twl = wl if target_wavelength_nm is None else np.asarray(target_wavelength_nm, float)
                ax.plot(twl, np.asarray(target_reflectance, float)[k], "--", color=cols[k])
        ax.set(xlabel="wavelength (nm)", ylabel="reflectance factor",
               title="reflectance factor per geometry" + (f" ({tname} dashed)" if target_reflectance is not None
                                                          else ""))
        ax.grid(alpha=0.3)
        ax.legend(ncol=6, fontsize=7)
    fig.suptitle(title + (f"  ({conditions})" if conditions else ""))
    freeze_layout(fig)
    label_travel(axes[0, 3], g, lab, lt)
    return fig


def label_travel(ax, geometries, lab, lab_target=None) -> list:
    """The geometry labels of an a*b* travel panel (:func:`place_labels`): each predicted point by its
    aspecular angle (``45as15`` when there are several illumination angles), and the target's points by
    the same names (the legend names the target); returns the annotations."""
    g = as_geometry_array(geometries)
    several = len(set(g[:, 0].tolist())) > 1
    names = [geometry_label(x) if several or x[2] != 0.0 else f"{x[1]:g}°" for x in g]
    xy = [np.asarray(lab, float)[:, 1:]]
    texts = list(names)
    if lab_target is not None:
        xy.append(np.asarray(lab_target, float)[:, 1:])
        texts += names
    return place_labels(ax, np.concatenate(xy), texts)


def plot_multiangle(path, geometries, lab, lab_target=None, wavelength_nm=None, reflectance=None,
                    target_reflectance=None, target_wavelength_nm=None, title="", conditions="",
                    target_name="target") -> Path:
    """A colour engineer's figure of one paint (and its target) at multi-angle geometries, written
    atomically to ``path`` (PNG, PDF or SVG by its suffix); returns the path.

    Panels: L*, a*, b* against the aspecular angle, one line per illumination angle, the target
    (``target_name``, in the legends) as open markers joined by a dashed line; the a*b* colour travel (the
    points joined in aspecular order, the first marked, every point labelled with its geometry without
    overlap: :func:`place_labels`); and, when ``reflectance`` (G, W) on ``wavelength_nm`` is given, the
    reflectance factor curves per geometry, each its own colour (:func:`geometry_colours`; target dashed).
    ``geometries`` (G, 2): (illumination_deg, aspecular_deg), or (G, 3) with azimuths (out-of-plane geometries
    are drawn as unjoined triangles at their aspecular angle); ``lab`` / ``lab_target`` (G, 3).
    """
    path = Path(path)
    fmt = PLOT_FORMATS.get(path.suffix.lower())
    if fmt is None:
        raise ValueError(f"{path}: a plot is written as {', '.join(PLOT_FORMATS)} (by the file's suffix)")
    fig = multiangle_figure(geometries, lab, lab_target, wavelength_nm, reflectance, target_reflectance,
                            target_wavelength_nm, title, conditions, target_name)
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as f:
            fig.savefig(f, format=fmt, dpi=110)
    return path
