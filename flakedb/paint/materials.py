"""Complex refractive indices N = n + i k of the catalogue's materials (k >= 0, see conventions).

The tables and their citations live in ``catalog/materials/`` (index: ``materials.yaml``, choices and
caveats: ``README.md``).  Data: the refractiveindex.info database (CC0 1.0), M. N. Polyanskiy,
Sci. Data 11, 94 (2024), doi:10.1038/s41597-023-02898-2, plus each data set's own publication.

Rules, stated once here and in the index:

* Interpolation.  ``nk_linear_in_wavelength``: n and k linear in vacuum wavelength (dense tables of
  dielectrics, formula tables on a 1 nm grid).  ``eps_linear_in_energy``: ε1 = n² − k² and ε2 = 2nk
  linear in photon energy E = hc/λ, then N = sqrt(ε) on the principal branch (n >= 0, k >= 0 when
  ε2 >= 0).  The second one is used for metals and sparse absorbing tables (Al, Rakić 1995: about
  0.12 eV steps), as the optical-constants README asks: interpolating in energy / ε follows the
  smooth Drude–Lorentz shape of the dielectric function, whereas linear-in-nm interpolation of a
  metal's n and k between points 40 nm apart is not an approximation of anything physical.
* Extrapolation only where ``materials.yaml`` names an explicit rule and range: ``formula`` (the
  source's own dispersion formula, refractiveindex.info formula types 1, 2 and 4, with k = 0) or
  ``hold_end_value`` (n and k of the nearest table end, for flat, sparse data such as soot).  Anything else
  outside a table raises ``ValueError`` naming the material, the wavelength and the table's range.
* Derived materials (``combine``) mix dielectric functions: ε = Σ w_i ε_i (a randomly oriented
  uniaxial powder: ε = (2 ε_o + ε_e)/3).

The only I/O is reading the shipped CSV/YAML once (cached); evaluation is vectorised numpy.
"""

from __future__ import annotations

import copy
import functools
import os
from pathlib import Path

import numpy as np
import yaml

from flakedb.resources import MATERIALS_DIR

#: hc in eV·nm (CODATA 2018: h c = 1239.841984 eV nm); converts vacuum wavelength to photon energy.
HC_EV_NM = 1239.841984

INTERPOLATIONS = ("nk_linear_in_wavelength", "eps_linear_in_energy")
#: Explicit extrapolation rules of materials.yaml (module docstring).
EXTRAPOLATIONS = ("formula", "hold_end_value")


def materials_dir() -> Path:
    """Folder holding the optical-constant tables (``$FLAKEDB_MATERIALS_DIR`` overrides it)."""
    env = os.environ.get("FLAKEDB_MATERIALS_DIR")
    if env:
        return Path(env)
    return MATERIALS_DIR


#: libyaml's safe loader when present: materials.yaml parses in 0.8 ms instead of 15 ms (a compose reads it once).
YAML_LOADER = getattr(yaml, "CSafeLoader", yaml.SafeLoader)


@functools.lru_cache(maxsize=None)
def _index() -> dict:
    path = materials_dir() / "materials.yaml"
    with open(path, encoding="utf-8") as f:
        doc = yaml.load(f, Loader=YAML_LOADER)  # a safe loader: libyaml's or PyYAML's SafeLoader
    mats = doc.get("materials") if isinstance(doc, dict) else None
    if not isinstance(mats, dict) or not mats:
        raise ValueError(f"{path}: expected a top-level 'materials:' mapping")
    return mats


def material_names() -> list[str]:
    """Names accepted by :func:`refractive_index`, sorted."""
    return sorted(_index())


def _entry(material: str) -> dict:
    mats = _index()
    if material not in mats:
        raise ValueError(f"unknown material {material!r}; known materials: {', '.join(sorted(mats))}")
    return mats[material]


def read_table(path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Read a ``wavelength_nm,n,k`` CSV with a ``#`` header; returns (wavelength_nm, n, k), sorted."""
    rows = []
    header_seen = False
    with open(path, encoding="utf-8") as f:
        for line in f:
            s = line.strip()
            if not s or s.startswith("#"):
                continue
            if not header_seen:
                if s.replace(" ", "") != "wavelength_nm,n,k":
                    raise ValueError(f"{path}: expected the column line 'wavelength_nm,n,k', got {s!r}")
                header_seen = True
                continue
            rows.append([float(v) for v in s.split(",")])
    data = np.asarray(rows, dtype=float)
    if data.ndim != 2 or data.shape[1] != 3 or len(data) < 2:
        raise ValueError(f"{path}: expected at least two rows of three numbers")
    order = np.argsort(data[:, 0])
    data = data[order]
    if np.any(np.diff(data[:, 0]) <= 0):
        raise ValueError(f"{path}: wavelengths are not strictly increasing")
    return data[:, 0], data[:, 1], data[:, 2]


@functools.lru_cache(maxsize=None)
def material_table(material: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The table points (wavelength_nm, n, k) of a tabulated material, after the k_min clip.

    Read-only arrays.  Raises ValueError for derived (``combine``) materials, which have no table.
    """
    e = _entry(material)
    if "file" not in e:
        raise ValueError(f"material {material!r} is derived ('combine'); it has no table of its own")
    wl, n, k = read_table(materials_dir() / e["file"])
    if "k_min" in e:
        k = np.maximum(k, float(e["k_min"]))
    lo, hi = (float(v) for v in e["valid_range_nm"])
    if not (np.isclose(wl[0], lo) and np.isclose(wl[-1], hi)):
        raise ValueError(
            f"material {material!r}: materials.yaml says valid_range_nm [{lo}, {hi}] but "
            f"{e['file']} covers [{wl[0]}, {wl[-1]}] nm; fix the index"
        )
    if np.any(k < 0):
        raise ValueError(f"material {material!r}: negative k in {e['file']}; set k_min in materials.yaml")
    for a in (wl, n, k):
        a.setflags(write=False)
    return wl, n, k


def material_info(material: str) -> dict:
    """The index entry of a material (file, citation, valid range, rules), as a new dict."""
    return copy.deepcopy(_entry(material))


def material_density_g_cm3(material: str) -> float | None:
    """Bulk density of ``material`` in g/cm³ from materials.yaml (``density_g_cm3``), None where the
    index gives none (cited by ``density_source`` there)."""
    d = _entry(material).get("density_g_cm3")
    return None if d is None else float(d)


def dispersion_formula_n(formula_type: int, coefficients, wavelength_nm) -> np.ndarray:
    """Real index n from a refractiveindex.info dispersion formula (its 'Dispersion formulas.pdf').

    L is the wavelength in µm, C the coefficients as stored in the database:

    * type 1 (Sellmeier):   n² − 1 = C1 + Σ_i C_{2i} L² / (L² − C_{2i+1}²)
    * type 2 (Sellmeier-2): n² − 1 = C1 + Σ_i C_{2i} L² / (L² − C_{2i+1})
    * type 4:               n² = C1 + C2 L^C3 / (L² − C4^C5) + C6 L^C7 / (L² − C8^C9)
                                 + Σ_{j>=10, step 2} C_j L^C_{j+1}

    Schott N-BK7 (Sellmeier, refractiveindex.info type 2) has n_d = 1.5168 at the helium d line, 587.56 nm:

    >>> bk7 = [0, 1.03961212, 0.00600069867, 0.231792344, 0.0200179144, 1.01046945, 103.560653]
    >>> round(float(dispersion_formula_n(2, bk7, 587.56)), 4)
    1.5168
    """
    c = [float(v) for v in coefficients]
    L = np.asarray(wavelength_nm, dtype=float) / 1000.0
    L2 = L * L
    if formula_type in (1, 2):
        n2 = 1.0 + c[0] + np.zeros_like(L)
        for i in range(1, len(c) - 1, 2):
            pole = c[i + 1] ** 2 if formula_type == 1 else c[i + 1]
            n2 = n2 + c[i] * L2 / (L2 - pole)
    elif formula_type == 4:
        c = c + [0.0] * max(0, 9 - len(c))
        n2 = c[0] + np.zeros_like(L)
        for a, p, b, q in ((c[1], c[2], c[3], c[4]), (c[5], c[6], c[7], c[8])):
            if a != 0.0:
                n2 = n2 + a * L**p / (L2 - b**q)
        for j in range(9, len(c) - 1, 2):
            n2 = n2 + c[j] * L ** c[j + 1]
    else:
        raise ValueError(f"dispersion formula type {formula_type} is not implemented (types 1, 2, 4 are)")
    return np.sqrt(n2)


def _interp_table(material, wl_q, wl, n, k, rule):
    if rule == "nk_linear_in_wavelength":
        return np.interp(wl_q, wl, n) + 1j * np.interp(wl_q, wl, k)
    if rule == "eps_linear_in_energy":
        e_tab = HC_EV_NM / wl[::-1]
        eps_tab = ((n + 1j * k) ** 2)[::-1]
        e_q = HC_EV_NM / wl_q
        eps = np.interp(e_q, e_tab, eps_tab.real) + 1j * np.interp(e_q, e_tab, eps_tab.imag)
        return np.sqrt(eps)
    raise ValueError(f"material {material!r}: unknown interpolation {rule!r}; use one of {INTERPOLATIONS}")


def _out_of_range_error(material, wl_bad, lo, hi, extra=""):
    return ValueError(
        f"material {material!r}: wavelength {wl_bad:g} nm is outside its table's range "
        f"[{lo:g}, {hi:g}] nm{extra}; materials.yaml gives no extrapolation rule for it: "
        f"ask inside the range or add an explicit rule (and its reason) to catalog/materials/materials.yaml"
    )


def refractive_index(material: str, wavelength_nm) -> np.ndarray:
    """Complex refractive index N = n + i k (k >= 0) of ``material`` at vacuum wavelengths in nm.

    ``wavelength_nm``: scalar or array (any shape); returns a complex array of the same shape.
    Interpolation / extrapolation / mixing rules: module docstring and ``catalog/materials``.
    Raises ValueError for an unknown material or a wavelength outside the table's range where no
    explicit extrapolation rule applies.
    """
    e = _entry(material)
    wl_q = np.asarray(wavelength_nm, dtype=float)
    if not np.all(np.isfinite(wl_q)) or np.any(wl_q <= 0):
        raise ValueError(f"material {material!r}: wavelengths must be finite and > 0 nm")
    if "combine" in e:
        eps = np.zeros(wl_q.shape, dtype=complex)
        for part in e["combine"]:
            eps = eps + float(part["weight"]) * refractive_index(part["material"], wl_q) ** 2
        N = np.sqrt(eps)
        return N.real + 1j * np.abs(N.imag)

    wl, n, k = material_table(material)
    lo, hi = wl[0], wl[-1]
    inside = (wl_q >= lo) & (wl_q <= hi)
    N = np.empty(wl_q.shape, dtype=complex)
    N[inside] = _interp_table(material, wl_q[inside], wl, n, k, e["interpolation"])
    outside = ~inside
    if np.any(outside):
        ext = e.get("extrapolation")
        if ext is None:
            raise _out_of_range_error(material, wl_q[outside].flat[0], lo, hi)
        elo, ehi = (float(v) for v in ext["range_nm"])
        ok = outside & (wl_q >= elo) & (wl_q <= ehi)
        bad = outside & ~ok
        if np.any(bad):
            raise _out_of_range_error(
                material, wl_q[bad].flat[0], lo, hi,
                extra=f" and outside its extrapolation range [{elo:g}, {ehi:g}] nm",
            )
        if ext["rule"] == "formula":
            f = e["formula"]
            N[ok] = dispersion_formula_n(int(f["type"]), f["coefficients"], wl_q[ok]) + 0j
        elif ext["rule"] == "hold_end_value":
            N[ok] = np.where(wl_q[ok] < lo, n[0] + 1j * k[0], n[-1] + 1j * k[-1])
        else:
            raise ValueError(f"material {material!r}: unknown extrapolation rule {ext['rule']!r}; "
                             f"use one of {EXTRAPOLATIONS}")
    return N.real + 1j * np.maximum(N.imag, 0.0)
