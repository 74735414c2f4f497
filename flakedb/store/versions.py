"""The versioned Zarr v3 store of compressed flake reflectance functions (docs/model.md §5, issue #5).

Layout (``STORE`` a local directory or any fsspec URL)::

    STORE/latest                          JSON {"version": <hash>}, replaced atomically (temp + rename)
    STORE/versions/<hash>/                one immutable version, a Zarr v3 group
        zarr.json                         group attributes = the metadata (schemas/store.schema.json#/$defs/metadata)
        wavelength_nm                     (W,) vacuum wavelength, nm
        grid/n<N>_m<M>/mu                 (n_mu,) cosines: the solver's full inside node set for n nodes in
                                          air and the top index ``eta_top`` (flakedb.store.compress.grid_nodes;
                                          conventions: μ > 0 travels down)
        grid/n<N>_m<M>/phi_d              (m,) φ_d = π k/(m−1), rad (0 forward)
        species/<name>/n<N>_m<M>/U_pairs  (W, n_mu², k) row i·n_mu + o ↔ (mu[i], mu[o]); see flakedb.store.compress
        species/<name>/n<N>_m<M>/V_pairs  (W, k, m) φ factor on phi_d
        species/<name>/n<N>_m<M>/fourier  (W, k, m) its cosine coefficients, orders 0 … m−1
        species/<name>/n<N>_m<M>/singular_values      (W, r) of √R
        species/<name>/n<N>_m<M>/mean_relative_error  (W,) of R̂ against R on the grid
        species/<name>/n<N>_m<M>/raw      (W, n_mu, n_mu, m) R itself (only with ``store_raw``)
        tasks/<task>.json                 one per finished task: sha256 of every chunk it wrote
        checksums.json                    every chunk and zarr.json of the version with its sha256
        complete                          written last, after every task finished

A version is named by :func:`content_hash` of its inputs (catalogue entries, optical-data file
checksums, grid, rank, wavelengths, flakedb version): the same inputs give the same name, so a
rebuild with unchanged inputs finds the complete version and does nothing.  The build order
(rechunker / pangeo-forge style): the template (all arrays and the metadata) is written first, then
one task per (species, resolution, channel block) fills its chunk-aligned region and records the
checksums of the chunks it wrote (so any task can be re-run, and a resumed build runs only the
tasks without a record), then :func:`finalize` writes ``checksums.json`` and ``complete``, and
:func:`publish` moves ``latest``.  An interrupted build leaves ``latest`` on the previous version.

The top interface (``eta_top``, issue #6: compose reads the store).  The solver projects a medium's
kernel on its nodes *inside the binder*; below a smooth coat of index η those are the Snell image
of the air-side Radau nodes plus nodes in the TIR range, not the Radau set.  A version built with
``eta_top = η`` samples R on exactly that node set (:func:`flakedb.store.compress.grid_nodes`), and
evaluates the species' optics with the binder index η (constant over wavelength): a recipe has one
index for its coat and basecoats (``flakedb.paint.recipe``), which is the flakes' and pigments' embedding
index in :mod:`flakedb.paint.mapping`.  η = 1 is an index-matched stack (plain Radau nodes, embedding
index 1).  ``eta_top`` None keeps the catalogue binder's dispersion and the plain Radau nodes (no
compose can use such a version directly unless its stack has no smooth coat).

This module holds the planning (pure), the per-task work and the readers; Dask lives in
``flakedb/pipelines/build.py``.
"""

from __future__ import annotations

import hashlib
import itertools
import json
import os
import posixpath
import shutil
import sys
import uuid
from dataclasses import dataclass, field
from pathlib import Path

import fsspec
import jsonschema
import numpy as np
import zarr

from flakedb import __version__
from flakedb.paint import species as sp
from flakedb.resources import SCHEMAS_DIR
from flakedb.rt.fourier import cosine_coefficients
from flakedb.rt.stored import StoredReflectance
from flakedb.store.compress import (
    DEFAULT_N_TABLE,
    fourier_factors,
    grid_nodes,
    mean_relative_error,
    reconstruct,
    sample_reflectance,
    sqrt_svd_compress,
)

FORMAT = "flakedb-store"
FORMAT_VERSION = 1
DEFAULT_STORE = "./flakedb-store"

__all__ = [
    "StoreError",
    "StoreIntegrityError",
    "BuildRequest",
    "Task",
    "BuildPlan",
    "content_hash",
    "plan_build",
    "default_store",
    "version_state",
    "write_template",
    "pending_tasks",
    "run_task",
    "finalize",
    "publish",
    "read_latest",
    "verify_version",
    "verify_store",
    "open_version",
    "StoreVersion",
]


class StoreError(RuntimeError):
    """The store cannot give what was asked (no version, incomplete version, unknown species)."""


class StoreIntegrityError(StoreError):
    """The stored bytes do not match their recorded checksums, or the metadata breaks the schema."""


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


# --------------------------------------------------------------------------------------------
# Planning (pure)
# --------------------------------------------------------------------------------------------


def content_hash(inputs: dict) -> str:
    """sha256 (hex) of the sorted-key, compact JSON of ``inputs``."""
    text = json.dumps(inputs, sort_keys=True, separators=(",", ":"), ensure_ascii=True, allow_nan=False)
    return hashlib.sha256(text.encode("utf-8")).hexdigest()


@dataclass(frozen=True)
class BuildRequest:
    """Everything a build depends on (all of it enters the content hash).

    ``species``: name → catalogue entry (as :func:`flakedb.paint.catalog.expand_sweeps` gives it);
    ``binder``: the catalogue's binder entry; ``material_checksums``: optical-data file name → sha256;
    ``resolutions``: (n, m) pairs; ``rank`` r of the √R SVD; ``wavelength_nm``: channels (nm);
    ``channel_block``: channels per task (and per chunk); ``store_raw``: also store R itself;
    ``n_table``: table nodes of R(c) / p(cos Θ) (flakedb.store.compress.sample_reflectance);
    ``eta_top``: relative index of the paint's smooth top interface (module docstring): the μ grid
    is the solver's inside node set below it and the optics use it as the binder index; None: plain
    Radau nodes and the catalogue binder's index.
    """

    species: dict
    binder: dict
    material_checksums: dict
    resolutions: tuple
    rank: int
    wavelength_nm: tuple
    channel_block: int = 4
    store_raw: bool = False
    n_table: int = DEFAULT_N_TABLE
    eta_top: float | None = None

    def inputs(self) -> dict:
        return {
            "format": FORMAT,
            "format_version": FORMAT_VERSION,
            "flakedb_version": __version__,
            "species": {k: self.species[k] for k in sorted(self.species)},
            "binder": self.binder,
            "material_checksums": dict(sorted(self.material_checksums.items())),
            "resolutions": [[int(n), int(m)] for n, m in self.resolutions],
            "rank": int(self.rank),
            "wavelength_nm": [float(w) for w in self.wavelength_nm],
            "channel_block": int(self.channel_block),
            "store_raw": bool(self.store_raw),
            "n_table": int(self.n_table),
            "eta_top": None if self.eta_top is None else float(self.eta_top),
        }


@dataclass(frozen=True)
class Task:
    """One unit of work: species × resolution × channel block [c0, c1)."""

    species: str
    n: int
    m: int
    c0: int
    c1: int

    @property
    def id(self) -> str:
        return f"{self.species}/n{self.n}_m{self.m}/ch{self.c0:04d}-{self.c1:04d}"

    @property
    def record_name(self) -> str:
        return "tasks/" + self.id.replace("/", "__") + ".json"


@dataclass(frozen=True)
class BuildPlan:
    """The pure plan: version name, inputs, tasks and arrays (path → shape, chunks, dtype)."""

    version: str
    inputs: dict
    tasks: tuple
    arrays: dict = field(default_factory=dict)

    def nbytes(self) -> int:
        return int(sum(np.prod(a["shape"]) * np.dtype(a["dtype"]).itemsize for a in self.arrays.values()))

    def describe(self) -> str:
        lines = [f"version {self.version}", f"{len(self.tasks)} tasks (species × resolution × channel block)",
                 f"{len(self.arrays)} arrays, {self.nbytes() / 2**20:.2f} MiB uncompressed"]
        for path, a in self.arrays.items():
            if path.startswith("species/") and path.endswith(("U_pairs", "raw")):
                lines.append(f"  {path}: shape {tuple(a['shape'])}, chunks {tuple(a['chunks'])}, {a['dtype']}")
        return "\n".join(lines)


def _res_key(n, m):
    return f"n{int(n)}_m{int(m)}"


def plan_build(request: BuildRequest) -> BuildPlan:
    """Tasks and arrays of a build; pure (no I/O).  Refuses a rank above min(n², m)."""
    W = len(request.wavelength_nm)
    if W < 1:
        raise ValueError("a build needs at least one wavelength (wavelength_nm)")
    cb = int(request.channel_block)
    if cb < 1:
        raise ValueError(f"channel_block must be ≥ 1, got {cb}")
    r = int(request.rank)
    k = r * (r + 1) // 2
    arrays = {"wavelength_nm": {"shape": [W], "chunks": [W], "dtype": "float64", "units": "nm"}}
    tasks = []
    for n, m in request.resolutions:
        nm = len(grid_nodes(n, m, request.eta_top)[0])  # validates n, m, eta_top; n_mu nodes
        if r < 1 or r > min(nm * nm, m):
            raise ValueError(f"rank {r} is outside 1 … min(n_mu², m) = {min(nm * nm, m)} for n = {n}, m = {m}")
        g = f"grid/{_res_key(n, m)}"
        arrays[f"{g}/mu"] = {"shape": [nm], "chunks": [nm], "dtype": "float64", "units": "1"}
        arrays[f"{g}/phi_d"] = {"shape": [m], "chunks": [m], "dtype": "float64", "units": "rad"}
        for name in sorted(request.species):
            p = f"species/{name}/{_res_key(n, m)}"
            arrays[f"{p}/U_pairs"] = {"shape": [W, nm * nm, k], "chunks": [cb, nm * nm, k], "dtype": "float64", "units": "1"}
            arrays[f"{p}/V_pairs"] = {"shape": [W, k, m], "chunks": [cb, k, m], "dtype": "float64", "units": "1"}
            arrays[f"{p}/fourier"] = {"shape": [W, k, m], "chunks": [cb, k, m], "dtype": "float64", "units": "1"}
            arrays[f"{p}/singular_values"] = {"shape": [W, r], "chunks": [cb, r], "dtype": "float64", "units": "1"}
            arrays[f"{p}/mean_relative_error"] = {"shape": [W], "chunks": [cb], "dtype": "float64", "units": "1"}
            if request.store_raw:
                arrays[f"{p}/raw"] = {"shape": [W, nm, nm, m], "chunks": [cb, nm, nm, m], "dtype": "float64", "units": "1"}
            for c0 in range(0, W, cb):
                tasks.append(Task(name, int(n), int(m), c0, min(W, c0 + cb)))
    inputs = request.inputs()
    return BuildPlan(content_hash(inputs), inputs, tuple(tasks), arrays)


def _chunk_keys(path, spec):
    """Every chunk key (relative to the version root) of an array in the plan."""
    grid = [range(-(-s // c)) for s, c in zip(spec["shape"], spec["chunks"])]
    return [f"{path}/c/" + "/".join(map(str, idx)) for idx in itertools.product(*grid)]


def _task_chunk_keys(plan: BuildPlan, task: Task):
    cb = plan.inputs["channel_block"]
    out = []
    for path, spec in plan.arrays.items():
        if path.startswith(f"species/{task.species}/{_res_key(task.n, task.m)}/"):
            rest = "/".join(["0"] * (len(spec["shape"]) - 1))
            out.append(f"{path}/c/{task.c0 // cb}" + (f"/{rest}" if rest else ""))
    return out


def metadata(plan: BuildPlan) -> dict:
    """The version's metadata (group attributes), schema ``$defs/metadata``."""
    return {
        "format": FORMAT,
        "format_version": FORMAT_VERSION,
        "version": plan.version,
        "quantity": ("flake reflectance function R(mu_i, mu_o, phi_d) = R(c), c = |omega_i . h| = "
                     "sqrt((1 - cos Theta)/2); pigments: R = 4 pi albedo p(cos Theta) (paper eq. 8 with a = 2 C_ext); "
                     "dimensionless; compressed as sqrt-SVD pairs R ~= U_pairs @ V_pairs (flakedb.store.compress)"),
        "conventions": "flakedb.conventions: mu > 0 travels down (propagation directions), phi_d = phi_o - phi_i, "
                       "phi_d = 0 forward / mirror reflection; wavelengths in vacuum nm",
        "grid": {"mu": ("the solver's full inside node set [-x_h..-x_1, x_1..x_h] for n nodes in air "
                        + ("and no smooth top interface: Gauss-Radau, n/2 per hemisphere (flakedb.rt.quadrature)"
                           if plan.inputs.get("eta_top") in (None, 1.0) else
                           f"below a smooth top interface of relative index eta_top = {plan.inputs['eta_top']:g}: "
                           "the Snell image of the n/2 air-side Gauss-Radau nodes plus default_tir_nodes(n/2, eta_top) "
                           "Gauss-Legendre nodes in the TIR range (flakedb.rt.quadrature.snell_mapped_quadrature)")),
                 "phi_d": "phi_k = pi k/(m-1), k = 0..m-1", "fourier": "DCT-I cosine coefficients, orders 0..m-1 "
                 "(flakedb.rt.fourier.cosine_coefficients)", "row_order": "U_pairs row i*n_mu + o <-> (mu[i], mu[o]), n_mu = len(mu)"},
        "units": {"wavelength_nm": "nm", "mu": "1", "phi_d": "rad", "R": "1"},
        "inputs": plan.inputs,
        "tasks": [t.id for t in plan.tasks],
        "arrays": plan.arrays,
        "provenance": {"created_by": f"flakedb {__version__} (flakedb.store.versions)", "python": sys.version.split()[0],
                       "numpy": np.__version__, "zarr": zarr.__version__},
    }


# --------------------------------------------------------------------------------------------
# Byte-level access through fsspec
# --------------------------------------------------------------------------------------------


def _fs(url):
    return fsspec.core.url_to_fs(str(url))


def _join(url, *parts):
    url = str(url).rstrip("/")
    return posixpath.join(url, *parts) if "://" in url else str(Path(url).joinpath(*parts))


def _version_url(url, version):
    return _join(url, "versions", version)


def _read_json(fs, path):
    return json.loads(fs.cat_file(path).decode("utf-8"))


def _write_json(fs, path, doc):
    """Write a JSON document whole: to a temporary name, then renamed (a reader never sees half of it)."""
    fs.makedirs(posixpath.dirname(path), exist_ok=True)
    tmp = posixpath.join(posixpath.dirname(path), f".tmp-{uuid.uuid4().hex}")
    fs.pipe_file(tmp, (json.dumps(doc, indent=1, sort_keys=True) + "\n").encode("utf-8"))
    fs.mv(tmp, path)


def _sha256(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def version_state(url, version) -> str:
    """'absent', 'partial' (template written, not complete) or 'complete'."""
    fs, root = _fs(url)
    base = posixpath.join(root, "versions", version)
    if fs.exists(posixpath.join(base, "complete")):
        return "complete"
    zj = posixpath.join(base, "zarr.json")
    if fs.exists(zj) and "version" in _read_json(fs, zj).get("attributes", {}):
        return "partial"  # the metadata goes in last when the template is written
    return "absent"


# --------------------------------------------------------------------------------------------
# Writing: template, tasks, finalize, publish
# --------------------------------------------------------------------------------------------


def write_template(url, plan: BuildPlan):
    """Create the version group, every array (fill NaN) and the metadata; write the coordinates.

    Idempotent: a version whose template exists (a resumed build) is left as it is.
    """

    meta = metadata(plan)
    problems = schema_problems(meta, "metadata")
    if problems:
        raise StoreIntegrityError("metadata breaks schemas/store.schema.json:\n  " + "\n  ".join(problems))
    if version_state(url, plan.version) != "absent":
        return False
    fs, root = _fs(url)
    local = "file" in (fs.protocol if isinstance(fs.protocol, (tuple, list)) else (fs.protocol,))
    final = posixpath.join(root, "versions", plan.version)
    if local:
        # Build the template privately and rename it into place: two builds starting at once
        # cannot clear or interleave each other's template (the loser's rename fails, it uses the
        # winner's).  A leftover partial template (interrupted before the rename) never exists.

        tmp = posixpath.join(root, "versions", f".tmp-{plan.version[:16]}-{os.getpid()}-{uuid.uuid4().hex[:8]}")
        os.makedirs(posixpath.dirname(tmp), exist_ok=True)
        _fill_template(tmp, plan, meta)
        try:
            os.rename(tmp, final)
        except OSError:
            shutil.rmtree(tmp, ignore_errors=True)
            if version_state(url, plan.version) == "absent":
                raise
            return False
        return True
    _fill_template(_version_url(url, plan.version), plan, meta)
    return True


def _fill_template(vurl, plan: BuildPlan, meta: dict):
    g = zarr.open_group(vurl, mode="w")  # also clears a template whose writing was interrupted
    for path, spec in plan.arrays.items():
        g.create_array(path, shape=tuple(spec["shape"]), chunks=tuple(spec["chunks"]), dtype=spec["dtype"],
                       fill_value=np.nan, attributes={"units": spec["units"]})
    g["wavelength_nm"][:] = np.asarray(plan.inputs["wavelength_nm"], dtype=float)
    for n, m in plan.inputs["resolutions"]:
        mu, phi = grid_nodes(n, m, plan.inputs.get("eta_top"))
        g[f"grid/{_res_key(n, m)}/mu"][:] = mu
        g[f"grid/{_res_key(n, m)}/phi_d"][:] = phi
    g.attrs.update(meta)  # the group's zarr.json is written last: its presence marks the template


def compute_task(request_inputs: dict, task: Task) -> dict:
    """The numbers of one task (pure): name → array for the channel block [c0, c1)."""
    entry = request_inputs["species"][task.species]
    wl = np.asarray(request_inputs["wavelength_nm"], dtype=float)[task.c0:task.c1]
    eta_top = request_inputs.get("eta_top")
    # the binder index of the optics: the paint's one index below the top interface when eta_top is
    # given (module docstring), else the catalogue binder's dispersion
    nb = np.full(wl.shape, float(eta_top)) if eta_top is not None else sp.binder_index(
        {"binder": request_inputs["binder"]}, wl)
    R = sample_reflectance(entry, wl, nb, task.n, task.m, n_table=request_inputs["n_table"], eta_top=eta_top)
    nm = R.shape[1]
    r = request_inputs["rank"]
    out = {"U_pairs": [], "V_pairs": [], "fourier": [], "singular_values": [], "mean_relative_error": []}
    for ch in range(R.shape[0]):
        f = sqrt_svd_compress(R[ch], r)
        out["U_pairs"].append(f.U_pairs)
        out["V_pairs"].append(f.V_pairs)
        out["fourier"].append(fourier_factors(f.V_pairs))
        out["singular_values"].append(f.singular_values)
        out["mean_relative_error"].append(mean_relative_error(R[ch], reconstruct(f.U_pairs, f.V_pairs, nm)))
    out = {k: np.asarray(v) for k, v in out.items()}
    if request_inputs["store_raw"]:
        out["raw"] = R
    return out


def run_task(url, plan: BuildPlan, task: Task) -> dict:
    """Compute one task, write its chunk-aligned region, record its chunks' sha256; returns the record.

    Safe to re-run: it overwrites exactly its own chunks and its own record.
    """
    data = compute_task(plan.inputs, task)
    vurl = _version_url(url, plan.version)
    base = f"species/{task.species}/{_res_key(task.n, task.m)}"
    for name, arr in data.items():
        za = zarr.open_array(vurl, path=f"{base}/{name}", mode="r+")
        za[task.c0:task.c1] = arr
    fs, root = _fs(url)
    vroot = posixpath.join(root, "versions", plan.version)
    chunks = {key: _sha256(fs.cat_file(posixpath.join(vroot, key))) for key in _task_chunk_keys(plan, task)}
    record = {"task": task.id, "version": plan.version, "chunks": chunks}
    _write_json(fs, posixpath.join(vroot, task.record_name), record)  # written last: the task is done
    return record


def pending_tasks(url, plan: BuildPlan) -> list:
    """Tasks of the plan without a record in the version (all of them for a fresh version)."""
    fs, root = _fs(url)
    vroot = posixpath.join(root, "versions", plan.version)
    return [t for t in plan.tasks if not fs.exists(posixpath.join(vroot, t.record_name))]


def _all_chunk_keys(arrays: dict):
    return [k for path, spec in arrays.items() for k in _chunk_keys(path, spec)]


def finalize(url, plan: BuildPlan):
    """After every task: collect the checksums (task records, coordinates, every zarr.json) into
    ``checksums.json``, then write ``complete``.  Refuses when a task record or chunk is missing."""
    fs, root = _fs(url)
    vroot = posixpath.join(root, "versions", plan.version)
    missing = pending_tasks(url, plan)
    if missing:
        raise StoreError(f"cannot finalize {plan.version}: {len(missing)} task(s) not done, e.g. {missing[0].id}")
    sums = {}
    for t in plan.tasks:
        sums.update(_read_json(fs, posixpath.join(vroot, t.record_name))["chunks"])
    for key in _all_chunk_keys(plan.arrays):
        if key not in sums:  # coordinates, written with the template
            sums[key] = _sha256(fs.cat_file(posixpath.join(vroot, key)))
    for p in fs.find(vroot):
        if p.endswith("zarr.json"):
            sums[posixpath.relpath(p, vroot)] = _sha256(fs.cat_file(p))
    doc = {"version": plan.version, "algorithm": "sha256", "files": dict(sorted(sums.items()))}
    _write_json(fs, posixpath.join(vroot, "checksums.json"), doc)
    cs = _sha256(fs.cat_file(posixpath.join(vroot, "checksums.json")))
    _write_json(fs, posixpath.join(vroot, "complete"), {"version": plan.version, "checksums_sha256": cs,
                                                        "n_files": len(sums)})


def publish(url, version):
    """Point ``latest`` at a complete version: write a temporary file, then rename it over ``latest``
    (atomic on a local file system; on object stores a single-object PUT is atomic too)."""
    if version_state(url, version) != "complete":
        raise StoreError(f"refusing to publish version {version}: it is not complete")
    fs, root = _fs(url)
    _write_json(fs, posixpath.join(root, "latest"), {"version": version})


def read_latest(url) -> str | None:
    """The version ``latest`` points at, or None when nothing was published."""
    fs, root = _fs(url)
    p = posixpath.join(root, "latest")
    if not fs.exists(p):
        return None
    try:
        version = _read_json(fs, p)["version"]
    except (OSError, ValueError, UnicodeDecodeError, KeyError, TypeError) as exc:
        raise StoreError(f"{url}: `latest` is unreadable ({type(exc).__name__}: {exc}); it must be a JSON file "
                         f'{{"version": "<hash>"}} (hint: remove it and rerun `flakedb build` with the same '
                         f"inputs, which rewrites it)") from None
    if not isinstance(version, str):
        raise StoreError(f"{url}: `latest` names version {version!r}, not a version hash (hint: remove it and rerun "
                         f"`flakedb build`)")
    return version


# --------------------------------------------------------------------------------------------
# Verification and reading
# --------------------------------------------------------------------------------------------


def verify_version(url, version) -> list[str]:
    """Problems of one version: completeness, schema, every file's sha256.  Empty list = sound."""
    fs, root = _fs(url)
    vroot = posixpath.join(root, "versions", version)
    where = f"versions/{version}"
    if version_state(url, version) == "absent":
        return [f"{where}: no such version (no metadata in zarr.json)"]
    problems = []
    try:
        meta = _read_json(fs, posixpath.join(vroot, "zarr.json")).get("attributes", {})
    except (OSError, ValueError, UnicodeDecodeError) as exc:
        return [f"{where}/zarr.json: unreadable ({exc})"]
    problems += [f"{where}: {p}" for p in schema_problems(meta, "metadata")]
    if meta.get("version") != version:
        problems.append(f"{where}: metadata names version {meta.get('version')!r}")
    if not fs.exists(posixpath.join(vroot, "complete")):
        done = sum(fs.exists(posixpath.join(vroot, Task(*_parse_task(t)).record_name)) for t in meta.get("tasks", []))
        problems.append(f"{where}: incomplete build ({done} of {len(meta.get('tasks', []))} tasks done); "
                        "rerun `flakedb build` with the same inputs to finish it")
        return problems
    try:
        complete = _read_json(fs, posixpath.join(vroot, "complete"))
        cs_bytes = fs.cat_file(posixpath.join(vroot, "checksums.json"))
        sums = json.loads(cs_bytes.decode("utf-8"))
    except (OSError, ValueError, UnicodeDecodeError) as exc:
        return problems + [f"{where}: complete / checksums.json unreadable ({exc})"]
    problems += [f"{where}: {p}" for p in schema_problems(complete, "complete")]
    problems += [f"{where}: {p}" for p in schema_problems(sums, "checksums")]
    if complete.get("checksums_sha256") != _sha256(cs_bytes):
        problems.append(f"{where}/checksums.json: sha256 differs from the one recorded in `complete`")
    files = sums.get("files", {})
    for key in _all_chunk_keys(meta.get("arrays", {})):
        if key not in files:
            problems.append(f"{where}/{key}: chunk has no recorded checksum")
    for key, expected in files.items():
        p = posixpath.join(vroot, key)
        if not fs.exists(p):
            problems.append(f"{where}/{key}: missing")
            continue
        try:
            got = _sha256(fs.cat_file(p))
        except OSError as exc:  # e.g. a chunk replaced by a directory
            problems.append(f"{where}/{key}: unreadable ({exc.strerror or type(exc).__name__})")
            continue
        if got != expected:
            problems.append(f"{where}/{key}: sha256 {got[:16]}… != recorded {expected[:16]}… (corrupted)")
    return problems


def _parse_task(task_id):
    name, res, ch = task_id.rsplit("/", 2)
    n, m = res[1:].split("_m")
    c0, c1 = ch[2:].split("-")
    return name, int(n), int(m), int(c0), int(c1)


def verify_store(url, all_versions=False) -> list[str]:
    """Problems of a store: ``latest`` (present, schema, pointing at a complete sound version) and,
    with ``all_versions``, every version under ``versions/``."""
    fs, root = _fs(url)
    if not fs.exists(root):
        return [f"{url}: no such store"]
    problems = []
    latest = None
    lp = posixpath.join(root, "latest")
    if fs.exists(lp):
        try:
            doc = _read_json(fs, lp)
            problems += [f"latest: {p}" for p in schema_problems(doc, "latest")]
            latest = doc.get("version") if isinstance(doc, dict) else None
        except (OSError, ValueError, UnicodeDecodeError) as exc:
            problems.append(f"latest: unreadable ({exc})")
    else:
        problems.append("latest: missing (nothing was published)")
    versions = []
    vdir = posixpath.join(root, "versions")
    if all_versions and fs.exists(vdir):
        versions = sorted(posixpath.basename(p.rstrip("/")) for p in fs.ls(vdir, detail=False))
        # `.tmp-*`: a template being written, or left by a build killed while writing it; not a version
        versions = [v for v in versions if not v.startswith(".")]
    if latest and latest not in versions:
        versions.insert(0, latest)
    for v in versions:
        problems += verify_version(url, v)
    return problems


def open_version(url=None, version=None, verify=True) -> "StoreVersion":
    """Open a complete version for reading (``version`` None: the one ``latest`` points at).

    With ``verify`` (default) every file's sha256 is checked against ``checksums.json`` first and a
    :class:`StoreIntegrityError` lists what does not match; an incomplete version raises
    :class:`StoreError`.
    """
    url = url if url is not None else default_store()
    if version is None:
        version = read_latest(url)
        if version is None:
            raise StoreError(f"{url}: no published version (no `latest`); run `flakedb build --store {url}`")
    state = version_state(url, version)
    if state != "complete":
        raise StoreError(f"{url}: version {version} is {state}; rerun `flakedb build` with the same inputs to finish it")
    if verify:
        problems = verify_version(url, version)
        if problems:
            raise StoreIntegrityError(
                f"{url}: version {version} failed verification ({len(problems)} problem(s)); delete "
                f"versions/{version} and rebuild:\n  " + "\n  ".join(problems[:20]))
    g = zarr.open_group(_version_url(url, version), mode="r")
    return StoreVersion(str(url), version, g, dict(g.attrs))


@dataclass
class StoreVersion:
    """A read-only view of one complete version (:func:`open_version`)."""

    url: str
    version: str
    group: object
    metadata: dict

    @property
    def wavelength_nm(self) -> np.ndarray:
        return self.group["wavelength_nm"][:]

    @property
    def species(self) -> list[str]:
        return sorted(self.metadata["inputs"]["species"])

    @property
    def eta_top(self) -> float | None:
        """The top interface index the version was built for (None: plain Radau nodes, catalogue binder)."""
        return self.metadata["inputs"].get("eta_top")

    @property
    def resolutions(self) -> list[tuple[int, int]]:
        return [tuple(x) for x in self.metadata["inputs"]["resolutions"]]

    def _res(self, n, m):
        if m is None:
            ms = [mm for nn, mm in self.resolutions if nn == n]
            if not ms:
                raise StoreError(f"version {self.version} has no resolution n = {n}; it has {self.resolutions}")
            m = ms[0]
        if (n, m) not in self.resolutions:
            raise StoreError(f"version {self.version} has no resolution (n, m) = ({n}, {m}); it has {self.resolutions}")
        return n, m

    def grid(self, n, m=None):
        """(mu (n,), phi_d (m,)) of a resolution."""
        n, m = self._res(n, m)
        g = self.group[f"grid/{_res_key(n, m)}"]
        return g["mu"][:], g["phi_d"][:]

    def _arr(self, species, n, m, name):
        if species not in self.species:
            raise StoreError(f"version {self.version} has no species {species!r}; it has {', '.join(self.species)}")
        n, m = self._res(n, m)
        path = f"species/{species}/{_res_key(n, m)}/{name}"
        if name == "raw" and not self.metadata["inputs"]["store_raw"]:
            raise StoreError(f"version {self.version} was built without raw data (build with store_raw / --raw)")
        return self.group[path][:]

    def factors(self, species, n, m=None) -> dict:
        """``U_pairs`` (W, n², k), ``V_pairs`` (W, k, m), ``fourier`` (W, k, m), ``singular_values``
        (W, r), ``mean_relative_error`` (W,)."""
        return {k: self._arr(species, n, m, k) for k in
                ("U_pairs", "V_pairs", "fourier", "singular_values", "mean_relative_error")}

    def fourier_coefficients(self, species, n, m=None, raw=False) -> np.ndarray:
        """R's cosine coefficients (W, n_mu, n_mu, m), [ch, i, o, l], orders 0 … m−1: from the compressed
        factors (U_pairs @ fourier), or with ``raw`` the DCT-I of the stored raw R (a version built
        with ``store_raw``)."""
        if raw:
            return cosine_coefficients(self.raw(species, n, m))
        f = self.factors(species, n, m)
        W, nn, _ = f["U_pairs"].shape
        nm = int(round(np.sqrt(nn)))
        return np.matmul(f["U_pairs"], f["fourier"]).reshape(W, nm, nm, -1)

    def reflectance(self, species, n, m=None) -> np.ndarray:
        """The compressed R̂ on the grid, (W, n_mu, n_mu, m)."""
        f = self.factors(species, n, m)
        W, nn, _ = f["U_pairs"].shape
        nm = int(round(np.sqrt(nn)))
        return np.matmul(f["U_pairs"], f["V_pairs"]).reshape(W, nm, nm, -1)

    def raw(self, species, n, m=None) -> np.ndarray:
        """R itself, (W, n_mu, n_mu, m) (only in a version built with ``store_raw``)."""
        return self._arr(species, n, m, "raw")

    def stored_reflectance(self, species, n, m=None, raw=False, channel_index=None, channel_map=None,
                   weights=None):
        """R's series of ``species`` at resolution ``n`` (and ``m``) of this version, as a
        :class:`flakedb.rt.stored.StoredReflectance`; compressed factors by default, the raw samples with ``raw``.

        ``channel_index`` (C,) picks stored wavelengths; ``weights`` (C,) multiplies each picked band
        (a pigment's ρ C_ext); ``channel_map`` (C, K) then maps the bands linearly to K output
        channels (e.g. spectra → RGB).  Order: pick, weight, map.
        """
        mu, _ = self.grid(n, m)
        co = self.fourier_coefficients(species, n, m, raw=raw)  # (W, n_mu, n_mu, L)
        if channel_index is not None:
            co = co[np.asarray(channel_index, dtype=int)]
        if weights is not None:
            co = co * np.asarray(weights, dtype=float)[:, None, None, None]
        if channel_map is not None:
            co = np.tensordot(np.asarray(channel_map, dtype=float), co, axes=([0], [0]))
        what = "raw samples (DCT-I)" if raw else "compressed factors (U_pairs @ fourier)"
        return StoredReflectance(mu, co, f"store {self.url} version {self.version[:12]} species {species} n = {n}: {what}")
