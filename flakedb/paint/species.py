"""The particle catalogue (``catalog/particles.yaml``) and each species' optics.

A *species* is one entry of the catalogue, or one member of a sweep (``expand_sweeps``).  Kinds:

* ``interference_flake``: a symmetric thin-film platelet, ``coating`` (outside → in) + ``substrate``
  + ``coating`` reversed, embedded in the binder.  R(c, λ) and T(c, λ) come from the transfer-matrix
  method (:func:`flakedb.optics.thinfilm.flake_reflectance_transmittance`, Born & Wolf §1.6),
  unpolarised, with c = |ω·m| the cosine between the light and the flake normal *in the binder*.
* ``mirror_flake``: R = albedo (constant or a spectrum, linearly interpolated in λ), T = 0
  (model.md §3, Jakob et al. 2010's opaque flakes).
* ``pigment``: spheres with a log-normal number distribution of diameters; Mie optics per particle
  from :func:`flakedb.optics.mie.lognormal_pigment` (Du 2004), relative index m = N / n_binder
  (conventions).

Catalogue files are YAML validated against ``schemas/catalog.schema.json`` (JSON Schema 2020-12,
no unknown keys), then checked for what a schema cannot say (known materials, a flake's total
thickness equal to its film stack, sweep bases and parameters that exist).  Errors name the entry
and the field (``particles.metallic.coating[0].thickness_nm``) and say what to do.

This module also holds the text report and the plot behind ``flakedb species show`` so that the
command stays a thin wrapper (and the demo can call the same code).
"""

from __future__ import annotations

import copy
import json
import os
import re
from pathlib import Path

import jsonschema
import numpy as np
import yaml

from flakedb.colour.colorimetry import spectra_to_rgb_mode, spectral_grid
from flakedb.optics.mie import default_n_quad, lognormal_pigment
from flakedb.optics.thinfilm import flake_reflectance_transmittance as tmm_flake
from flakedb.paint.materials import material_names, refractive_index
from flakedb.resources import CATALOG_DIR, PACKAGE_DIR, SCHEMAS_DIR

#: Angles of incidence in the binder (degrees) and wavelengths (nm) of ``species show``'s table.
SHOW_ANGLES_DEG = (0.0, 30.0, 60.0, 80.0)
SHOW_WAVELENGTHS_NM = (450.0, 550.0, 650.0)


class CatalogError(ValueError):
    """The catalogue file is invalid; the message lists every problem with its path."""


def repo_root() -> Path:
    """The package folder (holds ``catalog/`` and ``schemas/``, see :mod:`flakedb.resources`)."""
    return PACKAGE_DIR


def default_catalog_path() -> Path:
    """``$FLAKEDB_CATALOG`` if set, else ``catalog/particles.yaml`` of this checkout."""
    env = os.environ.get("FLAKEDB_CATALOG")
    return Path(env) if env else CATALOG_DIR / "particles.yaml"


def schema_path() -> Path:
    return SCHEMAS_DIR / "catalog.schema.json"


def _fmt_path(parts) -> str:
    out = ""
    for p in parts:
        out += f"[{p}]" if isinstance(p, int) else (f".{p}" if out else str(p))
    return out or "(top level)"


def validate_catalog(doc) -> list[str]:
    """All problems of a parsed catalogue as 'path: message' strings (empty list: valid)."""
    with open(schema_path(), encoding="utf-8") as f:
        schema = json.load(f)
    validator = jsonschema.Draft202012Validator(schema)
    problems = []
    for err in sorted(validator.iter_errors(doc), key=lambda e: [str(p) for p in e.absolute_path]):
        errs = [err]
        if err.validator in ("oneOf", "anyOf") and err.context:
            # report the branch that got furthest instead of "is not valid under any of the given schemas"
            errs = [max(err.context, key=lambda e: len(e.absolute_path))]
        for e in errs:
            problems.append(f"{_fmt_path(e.absolute_path)}: {e.message}")
    if problems:
        return problems
    problems += _semantic_problems(doc)
    return problems


def _semantic_problems(doc) -> list[str]:
    known = set(material_names())
    out = []

    def check_material(path, name):
        if name not in known:
            out.append(f"{path}: unknown material {name!r}; known: {', '.join(sorted(known))}")

    check_material("binder.material", doc["binder"]["material"])
    for name, e in doc["particles"].items():
        base = f"particles.{name}"
        if e["kind"] == "interference_flake":
            check_material(f"{base}.substrate.material", e["substrate"]["material"])
            for i, film in enumerate(e["coating"]):
                check_material(f"{base}.coating[{i}].material", film["material"])
            total_um = _stack_total_um(e)
            if not np.isclose(e["thickness_um"]["value"], total_um, rtol=1e-6, atol=1e-9):
                out.append(
                    f"{base}.thickness_um: value {e['thickness_um']['value']} µm differs from the film "
                    f"stack's total {total_um:.6g} µm (2 × coating + substrate); make them agree"
                )
        elif e["kind"] == "pigment":
            check_material(f"{base}.material", e["material"])
        elif e["kind"] == "mirror_flake" and "wavelength_nm" in e["albedo"]:
            wl, val = e["albedo"]["wavelength_nm"], e["albedo"]["value"]
            if len(wl) != len(val):
                out.append(f"{base}.albedo: wavelength_nm has {len(wl)} entries, value {len(val)}")
            elif np.any(np.diff(wl) <= 0):
                out.append(f"{base}.albedo.wavelength_nm: must be strictly increasing")
    names = set(doc["particles"])
    for sname, s in (doc.get("sweeps") or {}).items():
        base = f"sweeps.{sname}"
        entry = doc["particles"].get(s["base"])
        if entry is None:
            out.append(f"{base}.base: no particle {s['base']!r}; particles: {', '.join(sorted(names))}")
            continue
        if entry["kind"] != "interference_flake":
            out.append(f"{base}.base: {s['base']!r} is a {entry['kind']}; sweeps step film thicknesses of interference flakes")
            continue
        m = re.fullmatch(r"coating\[(\d+)\]\.thickness_nm", s["parameter"])
        if m and int(m.group(1)) >= len(entry["coating"]):
            out.append(f"{base}.parameter: {s['parameter']} but {s['base']!r} has {len(entry['coating'])} coating film(s)")
        v = s["values_nm"]
        if v["stop"] < v["start"]:
            out.append(f"{base}.values_nm: stop {v['stop']} < start {v['start']}")
        try:
            generated = [s["name_format"].format(value=x) for x in _sweep_values(v)]
        except (ValueError, KeyError, IndexError) as exc:
            out.append(f"{base}.name_format: {s['name_format']!r} does not format an integer value ({exc})")
            continue
        for g in generated:
            if g in names:
                out.append(f"{base}: generated name {g!r} is already used")
            names.add(g)
    return out


def load_catalog(path=None) -> dict:
    """Read and validate a particle catalogue (default :func:`default_catalog_path`).

    Returns the parsed document (a dict with ``version``, ``binder``, ``particles`` and optionally
    ``sweeps``).  Raises :class:`CatalogError` listing every problem as ``path: message``.
    """
    path = Path(path) if path is not None else default_catalog_path()
    with open(path, encoding="utf-8") as f:
        doc = yaml.safe_load(f)
    problems = validate_catalog(doc)
    if problems:
        raise CatalogError(f"{path}: invalid particle catalogue:\n  " + "\n  ".join(problems))
    return doc


def _sweep_values(v) -> list[int]:
    return list(range(int(v["start"]), int(v["stop"]) + 1, int(v["step"])))


def _stack_total_um(entry) -> float:
    return (2 * sum(f["thickness_nm"]["value"] for f in entry["coating"]) + entry["substrate"]["thickness_nm"]["value"]) / 1000.0


def expand_sweeps(catalog: dict) -> dict:
    """All species by name: the catalogue's particles plus one entry per sweep value.

    A sweep member is a deep copy of its base with the stepped thickness set (its ``source`` names
    the sweep) and ``thickness_um`` recomputed from the stack, named by the sweep's
    ``name_format`` (e.g. ``pearlescent-tio2-070nm``).  Insertion order: particles, then sweeps.
    """
    out = {name: copy.deepcopy(e) for name, e in catalog["particles"].items()}
    for sname, s in (catalog.get("sweeps") or {}).items():
        base = catalog["particles"][s["base"]]
        for value in _sweep_values(s["values_nm"]):
            e = copy.deepcopy(base)
            src = f"sweep {sname}: {s['source']}"
            m = re.fullmatch(r"coating\[(\d+)\]\.thickness_nm", s["parameter"])
            film = e["coating"][int(m.group(1))] if m else e["substrate"]
            film["thickness_nm"] = {"value": value, "source": src}
            e["thickness_um"] = {"value": _stack_total_um(e), "source": "total of the film stack"}
            e["description"] = f"{base['description']}; {s['parameter']} = {value} nm"
            out[s["name_format"].format(value=value)] = e
    return out


def species_names(catalog: dict | None = None) -> list[str]:
    """Names of every species (particles and sweep members), in catalogue order."""
    return list(expand_sweeps(catalog if catalog is not None else load_catalog()))


def get_species(name: str, catalog: dict | None = None) -> dict:
    """The entry of one species; ValueError listing the known names when there is none."""
    allsp = expand_sweeps(catalog if catalog is not None else load_catalog())
    if name not in allsp:
        raise ValueError(f"unknown species {name!r}; known species: {', '.join(allsp)}")
    return allsp[name]


def film_stack(entry: dict) -> tuple[list[str], np.ndarray]:
    """Materials and thicknesses (nm) of an interference flake, top to bottom, substrate in the middle."""
    if entry["kind"] != "interference_flake":
        raise ValueError(f"film_stack: a {entry['kind']} has no film stack")
    outer = [(f["material"], float(f["thickness_nm"]["value"])) for f in entry["coating"]]
    layers = outer + [(entry["substrate"]["material"], float(entry["substrate"]["thickness_nm"]["value"]))] + outer[::-1]
    return [m for m, _ in layers], np.array([d for _, d in layers])


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
    transfer-matrix method on :func:`film_stack`; mirror flakes: R = albedo, T = 0.
    """
    wl = np.atleast_1d(np.asarray(wavelength_nm, dtype=float))
    cos = np.atleast_1d(np.asarray(cos_theta, dtype=float))
    if entry["kind"] == "interference_flake":
        mats, d_nm = film_stack(entry)
        n_films = np.stack([refractive_index(m, wl) for m in mats], axis=1)  # (W, F)
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


def pigment_optics(entry: dict, wavelength_nm, n_binder, mu=None, n_quad=None):
    """Per-particle Mie optics of a pigment species per wavelength (number-weighted log-normal).

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
    m = refractive_index(entry["material"], wl) / nb
    return lognormal_pigment(
        m, wl, nb, float(entry["median_diameter_um"]["value"]), float(entry["gsd"]["value"]), mu=mu, n_quad=n_quad
    )


# --- report and plot (``flakedb species show``, the demo) -------------------------------------


def describe(name: str, entry: dict) -> str:
    """One paragraph: kind, description and the parameters with units."""
    lines = [f"{name} ({entry['kind']}): {entry['description']}"]
    if entry["kind"] == "interference_flake":
        mats, d = film_stack(entry)
        lines.append("film stack (top to bottom): " + " | ".join(f"{m} {x:g} nm" for m, x in zip(mats, d)))
    if entry["kind"] == "mirror_flake":
        a = entry["albedo"]
        lines.append("albedo: " + (f"{a['value']:g} (constant)" if "wavelength_nm" not in a else "spectrum"))
    if entry["kind"] == "pigment":
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


def plot_optics(name: str, out_dir, catalog: dict | None = None) -> Path:
    """Write ``out_dir/NAME-optics.png`` (written to a temporary name, then renamed); returns the path.

    Flakes: R and T spectra at the show angles, and the flake's reflected and transmitted colour
    (RGB mode of :mod:`flakedb.colour.colorimetry`, sRGB-encoded, clipped for display only) versus angle.
    Pigments: C_ext, C_sca, single-scattering albedo and g versus wavelength.
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
    tmp = out_dir / f".{name}-optics.png.{os.getpid()}.tmp"
    try:
        with open(tmp, "wb") as f:
            fig.savefig(f, format="png", dpi=110)
        os.replace(tmp, final)
    except BaseException:
        if tmp.exists():
            tmp.unlink()
        raise
    return final
