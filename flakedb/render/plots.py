"""Plots: a species' R and T against angle and wavelength (``flakedb species show``, the demo)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from flakedb.atomic import atomic_path
from flakedb.colour.colorimetry import spectra_to_rgb_mode, spectral_grid
from flakedb.paint.catalog import get_species, load_catalog
from flakedb.paint.species import SHOW_ANGLES_DEG, binder_index, flake_reflectance_transmittance, pigment_optics


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
