"""Plots: a species' R and T against angle and wavelength (``flakedb species show``, the demo)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from flakedb.atomic import atomic_path
from flakedb.colour.colorimetry import spectra_to_rgb_mode, spectral_grid
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


def plot_multiangle(path, geometries, lab, lab_target=None, wavelength_nm=None, reflectance=None,
                    target_reflectance=None, target_wavelength_nm=None, title="", conditions="") -> Path:
    """A colour engineer's figure of one paint (and its target) at multi-angle geometries, written
    atomically to ``path`` (PNG, PDF or SVG by its suffix); returns the path.

    Panels: L*, a*, b* against the aspecular angle, one line per illumination angle, the target as
    open markers; the a*b* colour travel (the points joined in aspecular order, the first marked);
    and, when ``reflectance`` (G, W) on ``wavelength_nm`` is given, the reflectance factor curves per
    geometry (target dashed).  ``geometries`` (G, 2): (illumination_deg, aspecular_deg); ``lab`` /
    ``lab_target`` (G, 3).
    """
    from matplotlib.backends.backend_agg import (
        FigureCanvasAgg,  # lazy: matplotlib takes ~0.3 s to import; only plotting needs it
    )
    from matplotlib.figure import Figure  # lazy: matplotlib takes ~0.3 s to import; only plotting needs it

    path = Path(path)
    fmt = PLOT_FORMATS.get(path.suffix.lower())
    if fmt is None:
        raise ValueError(f"{path}: a plot is written as {', '.join(PLOT_FORMATS)} (by the file's suffix)")
    g = np.asarray(geometries, float).reshape(-1, 2)
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
    for c, (name, ax) in enumerate(zip(("L*", "a*", "b*"), axes[0, :3])):
        for il in illums:
            sel = np.flatnonzero(g[:, 0] == il)
            sel = sel[np.argsort(g[sel, 1])]
            ax.plot(g[sel, 1], lab[sel, c], "-o", ms=4, color=colours[il], label=f"predicted, {il:g}° illum.")
            if lt is not None:
                ax.plot(g[sel, 1], lt[sel, c], "s", ms=7, mfc="none", color=colours[il],
                        label=f"target, {il:g}° illum.")
        ax.set(xlabel="aspecular angle (°)", ylabel=name, title=f"{name} vs aspecular angle")
        ax.grid(alpha=0.3)
    axes[0, 0].legend(fontsize=7)
    ax = axes[0, 3]
    for il in illums:
        sel = np.flatnonzero(g[:, 0] == il)
        sel = sel[np.argsort(g[sel, 1])]
        ax.plot(lab[sel, 1], lab[sel, 2], "-o", ms=4, color=colours[il], label=f"predicted, {il:g}°")
        ax.plot(lab[sel[0], 1], lab[sel[0], 2], "*", ms=12, color=colours[il])
        if lt is not None:
            ax.plot(lt[sel, 1], lt[sel, 2], "s", ms=7, mfc="none", color=colours[il], label=f"target, {il:g}°")
        for k in sel:
            ax.annotate(f"{g[k, 1]:g}", (lab[k, 1], lab[k, 2]), fontsize=6, xytext=(3, 3), textcoords="offset points")
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
        for k in range(g.shape[0]):
            line = ax.plot(wl, R[k], label=f"{g[k, 0]:g}as{g[k, 1]:g}")[0]
            if target_reflectance is not None:
                twl = wl if target_wavelength_nm is None else np.asarray(target_wavelength_nm, float)
                ax.plot(twl, np.asarray(target_reflectance, float)[k], "--", color=line.get_color())
        ax.set(xlabel="wavelength (nm)", ylabel="reflectance factor",
               title="reflectance factor per geometry" + (" (target dashed)" if target_reflectance is not None else ""))
        ax.grid(alpha=0.3)
        ax.legend(ncol=6, fontsize=7)
    fig.suptitle(title + (f"  ({conditions})" if conditions else ""))
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as f:
            fig.savefig(f, format=fmt, dpi=110)
    return path
