"""Each catalogue species' optics (R, T of flakes; Mie optics of pigments) per wavelength.

A *species* is one entry of the catalogue, or one member of a sweep (``expand_sweeps``).  Kinds:

* ``interference_flake``: a symmetric thin-film platelet, ``coating`` (outside → in) + ``substrate``
  + ``coating`` reversed, embedded in the binder.  R(c, λ) and T(c, λ) come from the transfer-matrix
  method (:func:`flakedb.optics.thinfilm.flake_reflectance_transmittance`, Born & Wolf §1.6),
  unpolarised, with c = |ω·m| the cosine between the light and the flake normal *in the binder*.
  ``substrate.coherence: incoherent``: the substrate's round trips add in power, the coatings stay
  coherent (:func:`flakedb.optics.thinfilm.incoherent_substrate_flake`), the phase-averaged limit of
  a substrate whose thickness varies by many λ / (2 n).
  A film may carry ``thickness_rel_sd``: its thickness varies from flake to flake (log-normal, that
  relative standard deviation), and R, T are the ensemble's averages (:func:`film_spreads`).
* ``mirror_flake``: R = albedo (constant or a spectrum, linearly interpolated in λ), T = 0
  (docs/model.md §3, Jakob et al. 2010's opaque flakes).
* ``pigment``: spheres with a log-normal number distribution of diameters; Mie optics per particle
  from :func:`flakedb.optics.mie.lognormal_pigment` (Du 2004), relative index m = N / n_binder
  (conventions).
* ``tinter``: a colourant known by its optics per unit volume fraction, not by a material and a size
  (made by ``flakedb calibrate`` from drawdowns, or from published Kubelka–Munk K and S,
  :mod:`flakedb.optics.kubelka_munk`): σ_a/φ and σ_s/φ spectra [1/µm] (:func:`tinter_coefficients`)
  and a Henyey–Greenstein mean cosine g.

The catalogue file itself (reading, validation, sweeps) is :mod:`flakedb.paint.catalog`; the plot
behind ``flakedb species show`` is :func:`flakedb.render.plots.plot_optics`.  This module also holds
the text report of ``species show`` so that the command stays a thin wrapper.
"""

from __future__ import annotations

import numpy as np

from flakedb.optics.mie import default_n_quad, lognormal_pigment
from flakedb.optics.thinfilm import flake_reflectance_transmittance as tmm_flake
from flakedb.optics.thinfilm import incoherent_substrate_flake
from flakedb.optics.thinfilm import thin_film_thickness_average
from flakedb.paint.catalog import TINTER_TABLES, get_species, load_catalog
from flakedb.paint.materials import material_density_g_cm3, material_info, refractive_index

#: Angles of incidence in the binder (degrees) and wavelengths (nm) of ``species show``'s table.
SHOW_ANGLES_DEG = (0.0, 30.0, 60.0, 80.0)
SHOW_WAVELENGTHS_NM = (450.0, 550.0, 650.0)


def film_stack(entry: dict) -> tuple[list[str], np.ndarray]:
    """Materials and thicknesses (nm) of an interference flake, top to bottom, substrate in the middle."""
    if entry["kind"] != "interference_flake":
        raise ValueError(f"film_stack: a {entry['kind']} has no film stack")
    outer = [(f["material"], float(f["thickness_nm"]["value"])) for f in entry["coating"]]
    layers = outer + [(entry["substrate"]["material"], float(entry["substrate"]["thickness_nm"]["value"]))] + outer[::-1]
    return [m for m, _ in layers], np.array([d for _, d in layers])


def species_density_g_cm3(entry: dict) -> tuple[float | None, str | None]:
    """(density in g/cm³, its source) of a species; (None, None) where none applies.

    The entry's own ``density_g_cm3`` when it states one (a pigment grade's measured density);
    otherwise, for an interference flake whose films all have a bulk density in materials.yaml, the
    thickness-weighted mean over :func:`film_stack` (a platelet's mass per volume; exact for a
    uniform stack, so a sweep member gets its own).

    >>> rho, src = species_density_g_cm3(get_species("metallic"))   # 0.2 µm MgF2 | 0.3 µm Al | 0.2 µm MgF2
    >>> round(rho, 4), round((2 * 0.2 * 3.15 + 0.3 * 2.70) / 0.7, 4)
    (2.9571, 2.9571)
    """
    if "density_g_cm3" in entry:
        return float(entry["density_g_cm3"]["value"]), entry["density_g_cm3"]["source"]
    if entry["kind"] != "interference_flake":
        return None, None
    mats, d_nm = film_stack(entry)
    rho = [material_density_g_cm3(m) for m in mats]
    if any(r is None for r in rho):
        return None, None
    parts = sorted(set(mats))
    src = ("thickness-weighted mean over the film stack; " +
           "; ".join(f"{m}: {material_density_g_cm3(m):g} g/cm³ ({material_info(m)['density_source']})" for m in parts))
    return float(np.dot(rho, d_nm) / d_nm.sum()), src


def _field_sources(node, path=""):
    """``(field path, source)`` of every ``{value, source}`` field of a catalogue entry, films included."""
    if isinstance(node, dict):
        if "value" in node and "source" in node:
            yield path, node["source"]
            return
        for k, v in node.items():
            yield from _field_sources(v, f"{path}.{k}" if path else k)
    elif isinstance(node, list):
        for i, v in enumerate(node):
            yield from _field_sources(v, f"{path}[{i}]")


def species_record(name: str, entry: dict) -> dict:
    """The ``species list --json`` row of one species: name, kind, description, colour_index (None
    where no Colour Index name applies), density_g_cm3 and its source (:func:`species_density_g_cm3`),
    source (the entry's own provenance; for a pigment without one, its material's citation) and, for
    a pigment, material, number-median diameter, gsd and grade."""
    rho, rho_src = species_density_g_cm3(entry)
    src = entry.get("source")
    if src is None and entry["kind"] == "pigment":
        src = material_info(entry["material"]).get("citation")
    if src is None:  # an entry whose provenance is stated field by field ({value, source}): those sources
        src = "; ".join(f"{k}: {' '.join(str(v).split())}" for k, v in _field_sources(entry)) or None
    row = {"name": name, "kind": entry["kind"], "description": entry["description"],
           "colour_index": entry.get("colour_index"), "density_g_cm3": rho, "density_source": rho_src,
           "source": src}
    if entry["kind"] == "pigment":
        row.update(material=entry["material"], median_diameter_um=float(entry["median_diameter_um"]["value"]),
                   gsd=float(entry["gsd"]["value"]), grade=entry.get("grade"))
    return row
def film_spreads(entry: dict) -> tuple[np.ndarray, np.ndarray]:
    """The thickness distribution of an interference flake's films, per film of :func:`film_stack`:
    ``(groups (F,), rel_sd (F,))`` for :func:`flakedb.optics.thinfilm.thin_film_thickness_average`.

    ``rel_sd`` is each film's ``thickness_rel_sd`` (0 when absent: every flake alike).  Two variables:
    every coating film of a flake shares one (group 0: both faces and all layers of a flake's coating
    are thicker or thinner together, as a flake's share of a batch deposition is; an assumption, which
    keeps a multilayer's average one-dimensional), the substrate has its own (group 1).
    """
    nc = len(entry["coating"])
    groups = np.array([0] * nc + [1] + [0] * nc)
    sd = [float(f.get("thickness_rel_sd", {"value": 0.0})["value"]) for f in entry["coating"]]
    sub = float(entry["substrate"].get("thickness_rel_sd", {"value": 0.0})["value"])
    return groups, np.array(sd + [sub] + sd[::-1])


def substrate_is_incoherent(entry: dict) -> bool:
    """Whether an interference flake's substrate is incoherent (``substrate.coherence``; absent: coherent)."""
    return entry["substrate"].get("coherence", {"value": "coherent"})["value"] == "incoherent"


def binder_index(catalog: dict, wavelength_nm) -> np.ndarray:
    """Real index of the catalogue's binder at ``wavelength_nm`` (its k is 0 in the shipped data)."""
    N = refractive_index(catalog["binder"]["material"], wavelength_nm)
    return N.real


def albedo_spectrum(entry: dict, wavelength_nm) -> np.ndarray:
    """A mirror flake's albedo at ``wavelength_nm`` (W,): constant, or linear in λ inside its table."""
    wl = np.atleast_1d(np.asarray(wavelength_nm, dtype=float))
    a = entry["albedo"]
    if "wavelength_nm" not in a:
        return np.full(wl.shape, float(a["value"]))
    x, y = np.asarray(a["wavelength_nm"], float), np.asarray(a["value"], float)
    if wl.min() < x[0] or wl.max() > x[-1]:
        raise ValueError(f"albedo spectrum covers {x[0]:g}-{x[-1]:g} nm; asked {wl.min():g}-{wl.max():g} nm")
    return np.interp(wl, x, y)


def flake_reflectance_transmittance(entry: dict, wavelength_nm, cos_theta, n_binder):
    """(R, T) of a flake species, each (W, A), unpolarised.

    ``wavelength_nm`` (W,) vacuum wavelengths in nm; ``cos_theta`` (A,) the cosine between the light
    and the flake normal in the binder; ``n_binder`` scalar or (W,), real.  Interference flakes:
    transfer-matrix method on :func:`film_stack`, averaged over the films' thickness distributions where the
    entry has them (:func:`film_spreads`, :func:`flakedb.optics.thinfilm.thin_film_thickness_average`);
    mirror flakes: R = albedo, T = 0.

    A lossless pearlescent flake (TiO2 on mica) reflects or transmits all light; the aluminium core of
    the metallic flake transmits none:

    >>> from flakedb.paint.catalog import TINTER_TABLES, get_species, load_catalog
    >>> catalog = load_catalog()
    >>> wl, c = np.array([450.0, 550.0, 650.0]), np.array([0.2, 0.6, 1.0])
    >>> R, T = flake_reflectance_transmittance(get_species("pearlescent", catalog), wl, c, binder_index(catalog, wl))
    >>> R.shape, bool(np.allclose(R + T, 1.0, rtol=0, atol=1e-12))
    ((3, 3), True)
    >>> R, T = flake_reflectance_transmittance(get_species("metallic", catalog), wl, c, binder_index(catalog, wl))
    >>> bool(np.all(T < 1e-12)), bool(np.all((0.7 < R) & (R < 0.95)))
    (True, True)
    """
    wl = np.atleast_1d(np.asarray(wavelength_nm, dtype=float))
    cos = np.atleast_1d(np.asarray(cos_theta, dtype=float))
    if entry["kind"] == "interference_flake":
        mats, d_nm = film_stack(entry)
        n_films = np.stack([refractive_index(m, wl) for m in mats], axis=1)  # (W, F)
        groups, sd = film_spreads(entry)
        if substrate_is_incoherent(entry):  # coherent coatings, the substrate's round trips in power
            nc = len(entry["coating"])
            rt = incoherent_substrate_flake(n_films[:, :nc], d_nm[:nc], n_films[:, nc], d_nm[nc], wl, cos, n_binder,
                                            coating_rel_sd=sd[:nc], substrate_rel_sd=sd[nc])
        elif np.any(sd > 0):  # an ensemble of flakes whose films vary: the powers average
            rt = thin_film_thickness_average(n_films, d_nm, sd, wl, cos, n_binder, None, groups=groups)
        else:
            rt = tmm_flake(n_films, d_nm, wl, cos, n_binder)
        return rt.R, rt.T
    if entry["kind"] == "mirror_flake":
        R = np.broadcast_to(albedo_spectrum(entry, wl)[:, None], (wl.size, cos.size)).copy()
        return R, np.zeros_like(R)
    raise ValueError(f"a {entry['kind']} is not a flake; use pigment_optics")


def pigment_n_quad(entry: dict, wavelength_nm, n_binder) -> int:
    """The size-quadrature node count :func:`pigment_optics` uses for these wavelengths together
    (:func:`flakedb.optics.mie.default_n_quad` at the largest π n_binder / λ)."""
    wl = np.atleast_1d(np.asarray(wavelength_nm, dtype=float))
    nb = np.broadcast_to(np.asarray(n_binder, dtype=float), wl.shape)
    return default_n_quad(float(np.max(np.pi * nb / (wl * 1e-3))), float(entry["median_diameter_um"]["value"]),
                          float(entry["gsd"]["value"]))


def absorption_factor(spec: dict, wavelength_nm) -> np.ndarray:
    """A pigment's calibrated factor on k (W,): ``spec['value']`` linear in wavelength between its
    ``wavelength_nm`` samples, held at the end values beyond them (schemas/catalog.schema.json)."""
    wl_s = np.asarray(spec["wavelength_nm"], float)
    v = np.asarray(spec["value"], float)
    if wl_s.shape != v.shape or np.any(np.diff(wl_s) <= 0) or np.any(v <= 0):
        raise ValueError("absorption_factor: wavelength_nm must increase and match value in length; values > 0")
    return np.interp(np.asarray(wavelength_nm, float), wl_s, v)


def tinter_coefficients(entry: dict, wavelength_nm) -> tuple[np.ndarray, np.ndarray]:
    """(σ_a/φ, σ_s/φ) of a tinter at ``wavelength_nm`` (W,) each, in 1/µm per unit volume fraction: its
    tables linear in wavelength; a wavelength outside a table raises ValueError (nothing is extrapolated).

    >>> e = {"kind": "tinter", "specific_absorption_per_um": {"wavelength_nm": [400, 700], "value": [2.0, 0.5]},
    ...      "specific_scattering_per_um": {"wavelength_nm": [400, 700], "value": [1.0, 1.0]}}
    >>> [a.tolist() for a in tinter_coefficients(e, [400.0, 550.0])]
    [[2.0, 1.25], [1.0, 1.0]]
    """
    if entry["kind"] != "tinter":
        raise ValueError(f"a {entry['kind']} is not a tinter")
    wl = np.atleast_1d(np.asarray(wavelength_nm, dtype=float))
    out = []
    for key in TINTER_TABLES:
        x, y = np.asarray(entry[key]["wavelength_nm"], float), np.asarray(entry[key]["value"], float)
        if wl.min() < x[0] - 1e-9 or wl.max() > x[-1] + 1e-9:
            raise ValueError(f"{key} covers {x[0]:g}-{x[-1]:g} nm; asked {wl.min():g}-{wl.max():g} nm")
        out.append(np.interp(wl, x, y))
    return out[0], out[1]


def pigment_optics(entry: dict, wavelength_nm, n_binder, mu=None, n_quad=None):
    """Per-particle Mie optics of a pigment species per wavelength (number-weighted log-normal).

    A calibrated entry's ``absorption_factor`` multiplies the material's k (:func:`absorption_factor`).
    Returns :class:`flakedb.optics.mie.LognormalPigment`: ``c_ext_um2``, ``c_sca_um2`` (µm² per
    particle), ``g``, ``mean_volume_um3`` and, with ``mu`` (cos Θ, (M,)), the phase function (W, M).
    ``n_quad``: the size quadrature's node count (default: from the shortest wavelength given,
    :func:`flakedb.optics.mie.default_n_quad`; the store passes the one of its whole grid so that a
    wavelength block gets the nodes a compose of all bands gets).
    """
    if entry["kind"] != "pigment":
        raise ValueError(f"a {entry['kind']} is not a pigment; use flake_reflectance_transmittance")

    wl = np.atleast_1d(np.asarray(wavelength_nm, dtype=float))
    nb = np.broadcast_to(np.asarray(n_binder, dtype=float), wl.shape)
    N = refractive_index(entry["material"], wl)
    if "absorption_factor" in entry:  # a calibration's spectral factor on k (flakedb.match.calibrate)
        N = N.real + 1j * N.imag * absorption_factor(entry["absorption_factor"], wl)
    m = N / nb
    return lognormal_pigment(
        m, wl, nb, float(entry["median_diameter_um"]["value"]), float(entry["gsd"]["value"]), mu=mu, n_quad=n_quad
    )


# --- report and plot (``flakedb species show``, the demo) -------------------------------------


def describe(name: str, entry: dict) -> str:
    """One paragraph: kind, description and the parameters with units."""
    lines = [f"{name} ({entry['kind']}): {entry['description']}"]
    rho, _ = species_density_g_cm3(entry)
    ident = [f"C.I. {entry['colour_index']}"] if entry.get("colour_index") else []
    ident += [f"density {rho:.4g} g/cm³"] if rho is not None else []
    if "grade" in entry:
        ident.append(f"grade {entry['grade']['name']}" + (f", {entry['grade']['surface_treatment']}"
                                                          if "surface_treatment" in entry["grade"] else ""))
    if ident:
        lines.append("; ".join(ident))
    if entry["kind"] == "interference_flake":
        mats, d = film_stack(entry)
        lines.append("film stack (top to bottom): " + " | ".join(f"{m} {x:g} nm" for m, x in zip(mats, d)))
        if substrate_is_incoherent(entry):
            lines.append("substrate incoherent: its round trips add in power (coatings coherent)")
        groups, sd = film_spreads(entry)
        if np.any(sd > 0):
            lines.append("thickness spread (relative SD, log-normal across flakes): " + ", ".join(
                f"{name} {v:g}" for name, v in zip([f"coating[{i}]" for i in range(len(entry['coating']))]
                                                   + ["substrate"], sd[:len(entry["coating"]) + 1]) if v > 0))
    if entry["kind"] == "mirror_flake":
        a = entry["albedo"]
        lines.append("albedo: " + (f"{a['value']:g} (constant)" if "wavelength_nm" not in a else "spectrum"))
    if entry["kind"] == "tinter":
        lines.append(f"optics per unit volume fraction (no Mie), Henyey-Greenstein g {entry['asymmetry_g']['value']:g}; "
                     f"source: {entry['source']}")
    elif entry["kind"] == "pigment":
        lines.append(
            f"material {entry['material']}, number-median diameter {entry['median_diameter_um']['value']:g} µm, "
            f"gsd {entry['gsd']['value']:g}"
        )
    else:
        lines.append(
            f"diameter {entry['diameter_um']['value']:g} µm, thickness {entry['thickness_um']['value']:g} µm, "
            f"orientation_alpha {entry['orientation_alpha']['value']:g}"
        )
    return "\n".join(lines)


def optics_table(name: str, catalog: dict | None = None, wavelengths_nm=SHOW_WAVELENGTHS_NM,
                 angles_deg=SHOW_ANGLES_DEG) -> str:
    """The text ``flakedb species show`` prints (numbers from the functions above, 6 decimals)."""
    catalog = catalog if catalog is not None else load_catalog()
    entry = get_species(name, catalog)
    wl = np.asarray(wavelengths_nm, dtype=float)
    nb = binder_index(catalog, wl)
    out = [describe(name, entry), f"binder: {catalog['binder']['material']} (n = " +
           ", ".join(f"{n:.4f} at {w:g} nm" for n, w in zip(nb, wl)) + ")"]
    if entry["kind"] == "tinter":
        a, s = tinter_coefficients(entry, wl)
        out.append("per unit volume fraction (sigma / phi), Henyey-Greenstein phase function:")
        out.append(f"{'wavelength_nm':>13} {'sigma_a_um':>12} {'sigma_s_um':>12} {'albedo':>10} {'g':>10}")
        for i, w in enumerate(wl):
            out.append(f"{w:13g} {a[i]:12.6f} {s[i]:12.6f} {s[i] / max(a[i] + s[i], 1e-300):10.6f} "
                       f"{entry['asymmetry_g']['value']:10.6f}")
        return "\n".join(out)
    if entry["kind"] == "pigment":
        p = pigment_optics(entry, wl, nb)
        out.append("per particle, log-normal ensemble (Mie, Du 2004):")
        out.append(f"{'wavelength_nm':>13} {'C_ext_um2':>12} {'C_sca_um2':>12} {'albedo':>10} {'g':>10}")
        for i, w in enumerate(wl):
            out.append(f"{w:13g} {p.c_ext_um2[i]:12.6f} {p.c_sca_um2[i]:12.6f} "
                       f"{p.c_sca_um2[i] / p.c_ext_um2[i]:10.6f} {p.g[i]:10.6f}")
        return "\n".join(out)
    ang = np.asarray(angles_deg, dtype=float)
    R, T = flake_reflectance_transmittance(entry, wl, np.cos(np.radians(ang)), nb)
    head = f"{'wavelength_nm':>13} " + " ".join(f"{a:>9g}°" for a in ang)
    for label, arr in (("R", R), ("T", T)):
        out.append(f"{label} (unpolarised; columns: angle of incidence in the binder):")
        out.append(head)
        for i, w in enumerate(wl):
            out.append(f"{w:13g} " + " ".join(f"{v:10.6f}" for v in arr[i]))
    return "\n".join(out)
