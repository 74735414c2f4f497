"""The build plan of a store version: what a request asks for, its content hash (the version's name), its tasks and
their chunks, and the version's metadata (docs/store.md).  Pure: no file, no Zarr.
"""

from __future__ import annotations

import hashlib
import itertools
import json
import os
import sys
from dataclasses import dataclass, field
from pathlib import Path

import jsonschema
import numpy as np

from flakedb import __version__
from flakedb.paint.catalog import catalog_distribution, optical_entry
from flakedb.paint.components import FLAKE_C_TOL
from flakedb.resources import SCHEMAS_DIR
from flakedb.rt.scattering.microflake import flake_distribution
from flakedb.rt.scattering.stored import RANK_TOL
from flakedb.store.compress import (
    LEGENDRE_STORE_DEGREE,
    ORDER_CHUNK,
    store_nodes,
)
from flakedb.store.errors import StoreError, StoreIntegrityError  # noqa: F401  (re-exported)

FORMAT = "flakedb-store"


FORMAT = "flakedb-store"
FORMAT_VERSION = 2


FORMAT_VERSION = 2
DEFAULT_STORE = "./flakedb-store"


def default_store() -> str:
    """``$FLAKEDB_STORE`` or ``./flakedb-store``."""
    return os.environ.get("FLAKEDB_STORE") or DEFAULT_STORE


def schema_path() -> Path:
    return SCHEMAS_DIR / "store.schema.json"


def _schema():
    return json.loads(schema_path().read_text(encoding="utf-8"))


def schema_problems(doc, definition) -> list[str]:
    """Violations of ``schemas/store.schema.json#/$defs/<definition>`` as 'path: message' lines."""
    schema = _schema()
    sub = {"$schema": schema["$schema"], "$defs": schema["$defs"], "$ref": f"#/$defs/{definition}"}
    v = jsonschema.Draft202012Validator(sub)
    return [f"{definition}.{'.'.join(str(p) for p in e.absolute_path) or '<root>'}: {e.message}"
            for e in sorted(v.iter_errors(doc), key=lambda e: list(map(str, e.absolute_path)))]


def content_hash(inputs: dict) -> str:
    """sha256 (hex) of the sorted-key, compact JSON of ``inputs``: the same inputs name the same version.

    >>> content_hash({"n": [32], "species": ["metallic"]}) == content_hash({"species": ["metallic"], "n": [32]})
    True
    >>> len(content_hash({})), content_hash({"n": [32]}) == content_hash({"n": [64]})
    (64, False)
    """
    text = json.dumps(inputs, sort_keys=True, separators=(",", ":"), ensure_ascii=True, allow_nan=False)
    return hashlib.sha256(text.encode("utf-8")).hexdigest()


def _alpha_key(alpha) -> str:
    return f"a{float(alpha):.6g}"


#: The flake orientation distribution of factors keyed by α alone: every version written before the
#: distribution became part of the key reads as Beckmann (flakedb.rt.scattering.microflake.DEFAULT_DISTRIBUTION).
BECKMANN = "beckmann"


def _flake_key(alpha, distribution=BECKMANN) -> str:
    """The store key of a flake's factors at (α, distribution): ``a<α>`` for Beckmann (the layout of every
    older version), ``<distribution>/a<α>`` otherwise."""
    return _alpha_key(alpha) if distribution == BECKMANN else f"{distribution}/{_alpha_key(alpha)}"


def _orientations(request, k) -> dict:
    """Flake species ``k``'s orientations to project, distribution (its canonical name,
    :data:`flakedb.rt.scattering.microflake.FLAKE_DISTRIBUTIONS`: parameters included, so factors of different
    shapes or mixtures get different keys) → sorted α's: the request's Beckmann ``alphas`` and
    ``distribution_alphas``, else the catalogue's α in the catalogue's distribution."""
    out = {}
    for a in request.alphas.get(k) or []:
        out.setdefault(BECKMANN, set()).add(float(a))
    for d, v in (request.distribution_alphas.get(k) or {}).items():
        for a in v:  # the registry's canonical name: the key a recipe's (recipe_distribution) will ask for
            out.setdefault(flake_distribution(d).name, set()).add(float(a))
    if not out:
        entry = request.species[k]
        out[catalog_distribution(entry)] = {float(entry["orientation_alpha"]["value"])}
    return {d: sorted(v) for d, v in sorted(out.items())}


@dataclass(frozen=True)
class BuildRequest:
    """Everything a build depends on (all of it enters the content hash).

    ``species``: name → catalogue entry (as :func:`flakedb.paint.catalog.expand_sweeps` gives it);
    ``binder``: the catalogue's binder entry; ``material_checksums``: optical-data file name → sha256;
    ``resolutions``: node counts n in air; ``wavelength_nm``: the store's wavelengths (nm);
    ``alphas``: flake species → the Beckmann spreads α to project for; ``distribution_alphas``: flake
    species → {distribution: α's} for other flake orientation distributions (e.g. ``{"ggx": [0.2]}``,
    :data:`flakedb.rt.scattering.microflake.FLAKE_DISTRIBUTIONS`); a species in neither: the catalogue's α in the
    catalogue's distribution (``orientation_distribution``, default Beckmann);
    ``channel_block``: pigment wavelengths per task (and per chunk); ``store_raw``: keep the spectral
    SVD at its numerical rank (no truncation: ``compose --raw``); ``rank_tol``: otherwise its
    truncation (:data:`flakedb.rt.scattering.stored.RANK_TOL`); ``projection_tol``: the solver's φ-projection
    tolerance (:class:`flakedb.rt.adding.stack.SolverSettings` ``tol``); ``legendre_degree``: the largest
    Legendre degree of the pigments' phase moments; ``eta_top``: relative index of the paint's smooth
    top interface (module docstring): the nodes are the solver's inside nodes below it and the optics
    use it as the binder index; None or 1: plain Radau nodes (no / a rough interface) with the
    catalogue binder's index (None) or index 1; ``recipe``: the recipe name of a ``--recipe`` build.
    """

    species: dict
    binder: dict
    material_checksums: dict
    resolutions: tuple
    wavelength_nm: tuple
    alphas: dict = field(default_factory=dict)
    channel_block: int = 8
    store_raw: bool = False
    rank_tol: float = RANK_TOL
    projection_tol: float = 1e-5
    legendre_degree: int = LEGENDRE_STORE_DEGREE
    eta_top: float | None = None
    recipe: str | None = None
    #: "rough": the nodes of a rough top (plain Gauss–Radau inside as in air) with the optics at
    #: ``eta_top``; "smooth" (default): the Snell-mapped nodes below a smooth top of ``eta_top``
    top: str = "smooth"
    distribution_alphas: dict = field(default_factory=dict)

    def inputs(self) -> dict:
        flakes = [k for k in sorted(self.species) if self.species[k]["kind"] != "pigment"]
        alphas, other = {}, {}
        for k in flakes:
            for d, v in _orientations(self, k).items():
                if d == BECKMANN:
                    alphas[k] = v
                else:
                    other.setdefault(k, {})[d] = v
        return {
            "format": FORMAT,
            "format_version": FORMAT_VERSION,
            "flakedb_version": __version__,
            "species": {k: optical_entry(self.species[k]) for k in sorted(self.species)},   # hashes kept
            "binder": optical_entry(self.binder),
            "material_checksums": dict(sorted(self.material_checksums.items())),
            "resolutions": sorted({int(n) for n in self.resolutions}),
            "wavelength_nm": [float(w) for w in self.wavelength_nm],
            "alphas": alphas,
            "channel_block": int(self.channel_block),
            "store_raw": bool(self.store_raw),
            "rank_tol": None if self.store_raw else float(self.rank_tol),
            "projection_tol": float(self.projection_tol),
            "legendre_degree": int(self.legendre_degree),
            "flake_c_tol": FLAKE_C_TOL,
            "eta_top": None if self.eta_top is None else float(self.eta_top),
            "recipe": self.recipe,
            # only a rough top is recorded, so the versions of smooth-top requests keep their hashes
            **({"top": "rough"} if self.top == "rough" else {}),
            # only other distributions than Beckmann are recorded: Beckmann-only requests keep their hashes
            **({"distribution_alphas": other} if other else {}),
        }


@dataclass(frozen=True)
class Task:
    """One unit of work: a flake species at one (n, α, orientation distribution) over every wavelength (the
    spectral SVD needs them all), or a pigment's wavelength block [c0, c1) (n-independent)."""

    species: str
    n: int = 0
    alpha: float = 0.0
    c0: int = 0
    c1: int = 0
    distribution: str = BECKMANN

    @property
    def is_flake(self) -> bool:
        return self.n > 0

    @property
    def id(self) -> str:
        if self.is_flake:
            return f"{self.species}/n{self.n}/{_flake_key(self.alpha, self.distribution)}"
        return f"{self.species}/ch{self.c0:04d}-{self.c1:04d}"

    @property
    def record_name(self) -> str:
        return "tasks/" + self.id.replace("/", "__") + ".json"

    @property
    def prefix(self) -> str:
        if self.is_flake:
            return f"species/{self.species}/n{self.n}/{_flake_key(self.alpha, self.distribution)}"
        return f"species/{self.species}"


@dataclass(frozen=True)
class BuildPlan:
    """The pure plan: version name, inputs, tasks and the arrays whose shape is known before the build
    (path → shape, chunks, dtype); a flake task adds its factors U, V (their rank and order count
    come from the data) and records them."""

    version: str
    inputs: dict
    tasks: tuple
    arrays: dict = field(default_factory=dict)

    def nbytes(self) -> int:
        return int(sum(np.prod(a["shape"]) * np.dtype(a["dtype"]).itemsize for a in self.arrays.values()))

    def describe(self) -> str:
        inp = self.inputs
        lines = [f"version {self.version}",
                 f"{len(self.tasks)} tasks (flake species × n × α, pigment species × wavelength block)",
                 f"{len(inp['wavelength_nm'])} wavelengths {inp['wavelength_nm'][0]:g}-{inp['wavelength_nm'][-1]:g} nm, "
                 f"n {inp['resolutions']}, eta_top {inp['eta_top']}",
                 f"fixed arrays {self.nbytes() / 2**20:.2f} MiB; flake factors U (W, r), V (r, L ≤ 2n, 2, h, h) "
                 f"float32 sized by the data (rank from the spectral SVD at {inp['rank_tol']})"]
        lines += [f"  {t.id}" for t in self.tasks]
        return "\n".join(lines)


def res_key(n):
    return f"n{int(n)}"


def plan_build(request: BuildRequest) -> BuildPlan:
    """Tasks and fixed-shape arrays of a build; pure (no I/O)."""
    inputs = request.inputs()
    W = len(inputs["wavelength_nm"])
    if W < 1:
        raise ValueError("a build needs at least one wavelength (wavelength_nm)")
    cb = int(request.channel_block)
    if cb < 1:
        raise ValueError(f"channel_block must be ≥ 1, got {cb}")
    K = int(inputs["legendre_degree"])
    arrays = {"wavelength_nm": {"shape": [W], "chunks": [W], "dtype": "float64", "units": "nm"}}
    tasks = []
    names = sorted(inputs["species"])
    for n in inputs["resolutions"]:
        x, _ = store_nodes(n, inputs["eta_top"], inputs.get("top", "smooth"))  # validates n, eta_top
        h = x.size
        arrays[f"grid/{res_key(n)}/x"] = {"shape": [h], "chunks": [h], "dtype": "float64", "units": "1"}
        arrays[f"grid/{res_key(n)}/w"] = {"shape": [h], "chunks": [h], "dtype": "float64", "units": "1"}
        for name in names:
            if inputs["species"][name]["kind"] == "pigment":
                continue
            orient = [(BECKMANN, a) for a in inputs["alphas"].get(name, [])]
            orient += [(d, a) for d, v in sorted(inputs.get("distribution_alphas", {}).get(name, {}).items()) for a in v]
            for d, a in orient:
                t = Task(name, int(n), float(a), distribution=d)
                tasks.append(t)
                arrays[f"{t.prefix}/sigma_t"] = {"shape": [W, h], "chunks": [W, h], "dtype": "float64", "units": "1/um per 1/um"}
                arrays[f"{t.prefix}/sigma_s"] = {"shape": [W, h], "chunks": [W, h], "dtype": "float64", "units": "1/um per 1/um"}
                arrays[f"{t.prefix}/projected_area"] = {"shape": [h], "chunks": [h], "dtype": "float64", "units": "1"}
    for name in names:
        if inputs["species"][name]["kind"] != "pigment":
            continue
        p = f"species/{name}"
        arrays[f"{p}/c_ext_um2"] = {"shape": [W], "chunks": [cb], "dtype": "float64", "units": "um2"}
        arrays[f"{p}/c_sca_um2"] = {"shape": [W], "chunks": [cb], "dtype": "float64", "units": "um2"}
        arrays[f"{p}/mean_volume_um3"] = {"shape": [W], "chunks": [cb], "dtype": "float64", "units": "um3"}
        arrays[f"{p}/legendre_moments"] = {"shape": [W, K + 1], "chunks": [cb, K + 1], "dtype": "float64", "units": "1"}
        for c0 in range(0, W, cb):
            tasks.append(Task(name, c0=c0, c1=min(W, c0 + cb)))
    return BuildPlan(content_hash(inputs), inputs, tuple(tasks), arrays)


def chunk_keys(path, spec):
    """Every chunk key (relative to the version root) of an array."""
    grid = [range(-(-s // c)) for s, c in zip(spec["shape"], spec["chunks"])]
    return [f"{path}/c/" + "/".join(map(str, idx)) for idx in itertools.product(*grid)]


def task_chunk_keys(plan: BuildPlan, task: Task, extra_arrays=None):
    """The chunks a task writes: its fixed arrays' chunks (a pigment: its channel block's) and those of
    the arrays it created (``extra_arrays``)."""
    cb = plan.inputs["channel_block"]
    out = []
    for path, spec in plan.arrays.items():
        if path.startswith(task.prefix + "/") and path.count("/") == task.prefix.count("/") + 1:
            if task.is_flake:
                out += chunk_keys(path, spec)
            else:
                rest = "/".join(["0"] * (len(spec["shape"]) - 1))
                out.append(f"{path}/c/{task.c0 // cb}" + (f"/{rest}" if rest else ""))
    for path, spec in (extra_arrays or {}).items():
        out += chunk_keys(path, spec)
    return out


def metadata(plan: BuildPlan) -> dict:
    """The version's metadata (group attributes), schema ``$defs/metadata``."""
    eta = plan.inputs.get("eta_top")
    return {
        "format": FORMAT,
        "format_version": FORMAT_VERSION,
        "version": plan.version,
        "quantity": ("projected micro-flake kernels per unit loading (paper eq. 2; docs/store.md): flakes "
                     "K_lambda[l, o, i] = sum_r U[lambda, r] V[r, l, block, o, i], block 0 K_T (down->down), 1 K_R "
                     "(down->up), in 1/(um sr) per a_rho = 1/um, with sigma_t, sigma_s (1/um per 1/um) at the nodes; "
                     "pigments: C_ext, C_sca (um^2) and the Legendre moments chi_k of the phase function"),
        "conventions": "flakedb.conventions: mu > 0 travels down (propagation directions), phi_d = phi_o - phi_i, "
                       "phi_d = 0 forward / mirror reflection; wavelengths in vacuum nm",
        "grid": {"x": ("the solver's positive inside nodes for n nodes in air "
                       + ("and no smooth top interface: Gauss-Radau, n/2 (flakedb.rt.basis.quadrature)"
                          if eta in (None, 1.0) else
                          f"below a rough top interface (binder index eta_top = {eta:g}): the air-side "
                          "Gauss-Radau rule, n/2 nodes (flakedb.rt.basis.quadrature)"
                          if plan.inputs.get("top") == "rough" else
                          f"below a smooth top interface of relative index eta_top = {eta:g}: the Snell image of "
                          "the n/2 air-side Gauss-Radau nodes plus default_tir_nodes(n/2, eta_top) Gauss-Legendre "
                          "nodes in the TIR range (flakedb.rt.basis.quadrature.snell_mapped_quadrature)")),
                 "w": "the weights of that hemisphere rule",
                 "orders": "cosine orders 0..L-1 of phi_d, L <= 2n (the solver's order cap), chunked by "
                           f"{ORDER_CHUNK} orders"},
        "units": {"wavelength_nm": "nm", "x": "1", "V": "1/(um sr) per 1/um", "sigma": "1/um per 1/um"},
        "inputs": plan.inputs,
        "tasks": [t.id for t in plan.tasks],
        "arrays": plan.arrays,
        "provenance": {"created_by": f"flakedb {__version__} (flakedb.store.versions)", "python": sys.version.split()[0],
                       "numpy": np.__version__, "zarr": _zarr_version()},
    }


def _zarr_version() -> str:
    """The installed zarr's version (the provenance of a version a build writes)."""
    import importlib.metadata  # lazy: 9 ms (email parsing) of every compose, which reads a store and writes none

    return importlib.metadata.version("zarr")
