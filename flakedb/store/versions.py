"""The versioned Zarr v3 store of projected, compressed kernel factors (docs/model.md §5, issues #5, #11;
docs/store.md).

Layout (``STORE`` a local directory or any fsspec URL)::

    STORE/latest                              JSON {"version": <hash>}, replaced atomically (temp + rename)
    STORE/versions/<hash>/                    one immutable version, a Zarr v3 group
        zarr.json                             group attributes = the metadata (schemas/store.schema.json)
        wavelength_nm                         (W,) vacuum wavelength, nm
        grid/n<N>/x, grid/n<N>/w              (h,) the solver's positive inside nodes and weights for n
                                              nodes in air below the top interface ``eta_top``
        species/<flake>/n<N>/a<α>/U           (W, r) spectral factor (SVD of R(c) across wavelength);
                                              Beckmann flakes (paper eq. 5) at a<α>, flakes of another
                                              orientation distribution D at <D>/a<α> (e.g. ggx/a0.2)
        species/<flake>/n<N>/a<α>/V           (r, L, 2, h, h) float32 projected basis kernels per unit
                                              loading: [rank, order, (K_T, K_R), outgoing, incident],
                                              chunked by ORDER_CHUNK orders
        species/<flake>/n<N>/a<α>/sigma_t     (W, h) σ_t per unit aρ at the nodes (and sigma_s,
                                              projected_area (h,) for opaque flakes)
        species/<pigment>/c_ext_um2, c_sca_um2, mean_volume_um3   (W,) ensemble Mie optics
        species/<pigment>/legendre_moments    (W, K + 1) χ_k of the phase function (χ_0 = 1)
        tasks/<task>.json                     one per finished task: sha256 of every chunk it wrote
                                              (and the arrays it sized: U, V)
        checksums.json                        every chunk and zarr.json of the version with its sha256
        complete                              written last, after every task finished

So compose performs no azimuthal projection: a flake's kernel in the recipe's channels is
(loading · map @ U) @ V, a pigment's the addition theorem on its moments (flakedb/rt/stored.py).

A version is named by :func:`content_hash` of its inputs (catalogue entries, optical-data file
checksums, node counts, α's, wavelengths, tolerances, flakedb version): the same inputs give the same
name, so a rebuild with unchanged inputs finds the complete version and does nothing.  The build
order (rechunker / pangeo-forge style): the template (fixed-shape arrays and the metadata) is written
first, then one task per (flake species, n, α) or (pigment, wavelength block) fills its region —
a flake task creates its U and V, whose rank and order count come from the data — and records the
checksums of the chunks it wrote (so any task can be re-run, and a resumed build runs only the tasks
without a record), then :func:`finalize` writes ``checksums.json`` and ``complete``, and
:func:`publish` moves ``latest``.  An interrupted build leaves ``latest`` on the previous version.
Versions of an older format (:data:`FORMAT_VERSION`) are refused with "rebuild with flakedb build".

The top interface (``eta_top``): the solver projects a medium's kernel on its nodes *inside the
binder*; below a smooth coat of index η those are the Snell image of the air-side Radau nodes plus
nodes in the TIR range.  A version built with ``eta_top = η`` projects on exactly that node set and
evaluates the species' optics with the binder index η (a recipe has one index for its coat and
basecoats).  η = 1 is an index-matched stack; ``eta_top`` None keeps the catalogue binder's
dispersion and the plain Radau nodes.

This module holds the planning (pure), the per-task work and the readers; Dask lives in
``flakedb/pipelines/build.py``.
"""

from __future__ import annotations

import errno
import hashlib
import itertools
import json
import math
import os
import posixpath
import re
import shutil
import sys
import uuid
from dataclasses import dataclass, field
from pathlib import Path

import fsspec
import jsonschema
import numpy as np
import zarr
from fsspec.implementations.local import LocalFileSystem

from flakedb import __version__
from flakedb.paint import species as sp
from flakedb.paint.mapping import FLAKE_C_TOL
from flakedb.resources import SCHEMAS_DIR
from flakedb.rt.stored import RANK_TOL, FlakeFactors
from flakedb.safeio import FileTooLargeError, read_limited
from flakedb.store.compress import (
    LEGENDRE_STORE_DEGREE,
    ORDER_CHUNK,
    flake_task,
    pigment_task,
    store_nodes,
)
from flakedb.store.errors import StoreError, StoreIntegrityError  # noqa: F401  (re-exported)

FORMAT = "flakedb-store"
FORMAT_VERSION = 2
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
    "complete_versions",
    "verify_store",
    "open_version",
    "StoreVersion",
]


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


def _alpha_key(alpha) -> str:
    return f"a{float(alpha):.6g}"


#: The flake orientation distribution of factors keyed by α alone: every version written before the
#: distribution became part of the key reads as Beckmann (flakedb.rt.microflake.DEFAULT_DISTRIBUTION).
BECKMANN = "beckmann"


def _flake_key(alpha, distribution=BECKMANN) -> str:
    """The store key of a flake's factors at (α, distribution): ``a<α>`` for Beckmann (the layout of every
    older version), ``<distribution>/a<α>`` otherwise."""
    return _alpha_key(alpha) if distribution == BECKMANN else f"{distribution}/{_alpha_key(alpha)}"


def _orientations(request, k) -> dict:
    """Flake species ``k``'s orientations to project, distribution → sorted α's: the request's Beckmann
    ``alphas`` and ``distribution_alphas``, else the catalogue's α in the catalogue's distribution."""
    out = {}
    for a in request.alphas.get(k) or []:
        out.setdefault(BECKMANN, set()).add(float(a))
    for d, v in (request.distribution_alphas.get(k) or {}).items():
        for a in v:
            out.setdefault(str(d), set()).add(float(a))
    if not out:
        entry = request.species[k]
        out[entry.get("orientation_distribution", BECKMANN)] = {float(entry["orientation_alpha"]["value"])}
    return {d: sorted(v) for d, v in sorted(out.items())}


@dataclass(frozen=True)
class BuildRequest:
    """Everything a build depends on (all of it enters the content hash).

    ``species``: name → catalogue entry (as :func:`flakedb.paint.catalog.expand_sweeps` gives it);
    ``binder``: the catalogue's binder entry; ``material_checksums``: optical-data file name → sha256;
    ``resolutions``: node counts n in air; ``wavelength_nm``: the store's wavelengths (nm);
    ``alphas``: flake species → the Beckmann spreads α to project for; ``distribution_alphas``: flake
    species → {distribution: α's} for other flake orientation distributions (e.g. ``{"ggx": [0.2]}``,
    :data:`flakedb.rt.microflake.FLAKE_DISTRIBUTIONS`); a species in neither: the catalogue's α in the
    catalogue's distribution (``orientation_distribution``, default Beckmann);
    ``channel_block``: pigment wavelengths per task (and per chunk); ``store_raw``: keep the spectral
    SVD at its numerical rank (no truncation: ``compose --raw``); ``rank_tol``: otherwise its
    truncation (:data:`flakedb.rt.stored.RANK_TOL`); ``projection_tol``: the solver's φ-projection
    tolerance (:class:`flakedb.rt.stack.SolverSettings` ``tol``); ``legendre_degree``: the largest
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
            "species": {k: self.species[k] for k in sorted(self.species)},
            "binder": self.binder,
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


def _res_key(n):
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
        arrays[f"grid/{_res_key(n)}/x"] = {"shape": [h], "chunks": [h], "dtype": "float64", "units": "1"}
        arrays[f"grid/{_res_key(n)}/w"] = {"shape": [h], "chunks": [h], "dtype": "float64", "units": "1"}
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


def _chunk_keys(path, spec):
    """Every chunk key (relative to the version root) of an array."""
    grid = [range(-(-s // c)) for s, c in zip(spec["shape"], spec["chunks"])]
    return [f"{path}/c/" + "/".join(map(str, idx)) for idx in itertools.product(*grid)]


def _task_chunk_keys(plan: BuildPlan, task: Task, extra_arrays=None):
    """The chunks a task writes: its fixed arrays' chunks (a pigment: its channel block's) and those of
    the arrays it created (``extra_arrays``)."""
    cb = plan.inputs["channel_block"]
    out = []
    for path, spec in plan.arrays.items():
        if path.startswith(task.prefix + "/") and path.count("/") == task.prefix.count("/") + 1:
            if task.is_flake:
                out += _chunk_keys(path, spec)
            else:
                rest = "/".join(["0"] * (len(spec["shape"]) - 1))
                out.append(f"{path}/c/{task.c0 // cb}" + (f"/{rest}" if rest else ""))
    for path, spec in (extra_arrays or {}).items():
        out += _chunk_keys(path, spec)
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
                       + ("and no smooth top interface: Gauss-Radau, n/2 (flakedb.rt.quadrature)"
                          if eta in (None, 1.0) else
                          f"below a rough top interface (binder index eta_top = {eta:g}): the air-side "
                          "Gauss-Radau rule, n/2 nodes (flakedb.rt.quadrature)"
                          if plan.inputs.get("top") == "rough" else
                          f"below a smooth top interface of relative index eta_top = {eta:g}: the Snell image of "
                          "the n/2 air-side Gauss-Radau nodes plus default_tir_nodes(n/2, eta_top) Gauss-Legendre "
                          "nodes in the TIR range (flakedb.rt.quadrature.snell_mapped_quadrature)")),
                 "w": "the weights of that hemisphere rule",
                 "orders": "cosine orders 0..L-1 of phi_d, L <= 2n (the solver's order cap), chunked by "
                           f"{ORDER_CHUNK} orders"},
        "units": {"wavelength_nm": "nm", "x": "1", "V": "1/(um sr) per 1/um", "sigma": "1/um per 1/um"},
        "inputs": plan.inputs,
        "tasks": [t.id for t in plan.tasks],
        "arrays": plan.arrays,
        "provenance": {"created_by": f"flakedb {__version__} (flakedb.store.versions)", "python": sys.version.split()[0],
                       "numpy": np.__version__, "zarr": zarr.__version__},
    }


# --------------------------------------------------------------------------------------------
# Byte-level access through fsspec
# --------------------------------------------------------------------------------------------


#: A version name: the content hash (hex) that :func:`plan_build` makes; nothing else is read as one.
_VERSION_RE = re.compile(r"^[0-9a-f]{8,128}$")
#: Largest store file read whole (a chunk, a zarr.json, checksums.json) [bytes].
MAX_STORE_FILE_BYTES = 512 * 1024 ** 2
#: Most chunks one stored array may declare (a catalogue build has at most a few thousand).
MAX_ARRAY_CHUNKS = 1_000_000


def _fs(url):
    """``(filesystem, root)`` of a store URL; an unknown scheme, a protocol whose package is missing or a
    malformed URL is a :class:`StoreError` in words (not an internal error)."""
    text = str(url)
    if not text.strip() or re.fullmatch(r"[A-Za-z][A-Za-z0-9+.-]*://+", text.strip()) or "\0" in text:
        raise StoreError(f"--store {url!r}: an empty store path or URL (hint: give a directory, e.g. --store "
                         f"flakedb-store, or a URL such as s3://bucket/store)")
    try:
        return fsspec.core.url_to_fs(text)
    except ImportError as exc:
        raise StoreError(f"--store {url}: this URL's protocol needs a package that is not installed ({exc}) "
                         f"(hint: install the package the message names)") from None
    except (ValueError, TypeError, KeyError) as exc:
        scheme = str(url).split("://", 1)[0] if "://" in str(url) else ""
        raise StoreError(f"--store {url}: not a store path or URL fsspec knows ({'scheme ' + repr(scheme) + ': ' if scheme else ''}"
                         f"{exc}) (hint: a local directory, or file://, s3://, gs://, memory://...)") from None


def check_version_name(url, version, where="version"):
    """Refuse a version name that is not a content hash (``latest`` pointing at ``../..``, a path)."""
    if not isinstance(version, str) or not _VERSION_RE.match(version):
        raise StoreError(f"{url}: {where} {version!r:.80} is not a version hash (hex digits); it would point outside "
                         f"versions/ (hint: remove `latest` and rerun `flakedb build` with the same inputs, which "
                         f"rewrites it)")
    return version


def _cat(fs, path, limit=MAX_STORE_FILE_BYTES) -> bytes:
    """The bytes of one store file, at most ``limit``: on a local store a regular file only
    (:func:`flakedb.safeio.read_limited`: a chunk symlinked to /dev/zero or a FIFO is refused, not read
    until memory runs out); elsewhere its size is checked first."""
    if isinstance(fs, LocalFileSystem):
        try:
            return read_limited(path, limit)
        except FileTooLargeError as exc:
            raise OSError(errno.EFBIG, f"more than the limit of {limit:,} bytes for one store file", path) from exc
    size = fs.size(path)
    if size is not None and size > limit:
        raise OSError(errno.EFBIG, f"{size:,} bytes, more than the limit of {limit:,} for one store file", path)
    return fs.cat_file(path)


def _join(url, *parts):
    url = str(url).rstrip("/")
    return posixpath.join(url, *parts) if "://" in url else str(Path(url).joinpath(*parts))


def _version_url(url, version):
    return _join(url, "versions", version)


def _read_json(fs, path):
    return json.loads(_cat(fs, path, 64 * 1024 ** 2).decode("utf-8"))


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
    try:
        if fs.exists(zj) and "version" in (_read_json(fs, zj).get("attributes") or {}):
            return "partial"  # the metadata goes in last when the template is written
    except (OSError, ValueError, UnicodeDecodeError, AttributeError, TypeError) as exc:
        raise StoreError(f"{url}: versions/{version}/zarr.json is unreadable "
                         f"({getattr(exc, 'strerror', None) or exc}); remove that version or rebuild it") from None
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
    for t in plan.tasks:  # the group a flake task's own arrays go in exists before any task runs
        if t.is_flake:
            g.require_group(t.prefix)
    g["wavelength_nm"][:] = np.asarray(plan.inputs["wavelength_nm"], dtype=float)
    for n in plan.inputs["resolutions"]:
        x, w = store_nodes(n, plan.inputs.get("eta_top"), plan.inputs.get("top", "smooth"))
        g[f"grid/{_res_key(n)}/x"][:] = x
        g[f"grid/{_res_key(n)}/w"][:] = w
    g.attrs.update(meta)  # the group's zarr.json is written last: its presence marks the template


def compute_task(request_inputs: dict, task: Task) -> dict:
    """The numbers of one task (pure): name → array (and ``info``, the compression record)."""
    entry = request_inputs["species"][task.species]
    wl_all = np.asarray(request_inputs["wavelength_nm"], dtype=float)
    wl = wl_all if task.is_flake else wl_all[task.c0:task.c1]
    eta_top = request_inputs.get("eta_top")
    # the binder index of the optics: the paint's one index below the top interface when eta_top is
    # given (module docstring), else the catalogue binder's dispersion
    nb = np.full(wl.shape, float(eta_top)) if eta_top is not None else sp.binder_index(
        {"binder": request_inputs["binder"]}, wl)
    if task.is_flake:
        return flake_task(entry, wl, nb, task.n, task.alpha, eta_top, request_inputs["rank_tol"],
                          request_inputs["projection_tol"], request_inputs.get("top", "smooth"), task.distribution)
    nb_all = np.full(wl_all.shape, float(eta_top)) if eta_top is not None else sp.binder_index(
        {"binder": request_inputs["binder"]}, wl_all)
    # the size quadrature of the whole grid (the log-normal Mie nodes follow the shortest wavelength):
    # every block, and a compose of any bands starting at the grid's first, gets the same nodes
    return pigment_task(entry, wl, nb, request_inputs["legendre_degree"],
                        n_quad=sp.pigment_n_quad(entry, wl_all, nb_all))


def run_task(url, plan: BuildPlan, task: Task) -> dict:
    """Compute one task, write its arrays (a flake task creates U and V, sized by its rank and orders),
    record its chunks' sha256; returns the record.  Safe to re-run: it overwrites exactly its own
    chunks and arrays and its own record."""
    data = compute_task(plan.inputs, task)
    info = data.pop("info", {})
    vurl = _version_url(url, plan.version)
    created = {}
    for name, arr in data.items():
        path = f"{task.prefix}/{name}"
        if path in plan.arrays:
            za = zarr.open_array(vurl, path=path, mode="r+")
            if task.is_flake:
                za[...] = arr
            else:
                za[task.c0:task.c1] = arr
        else:  # U (W, r) and V (r, L, 2, h, h): shapes from the data
            chunks = list(arr.shape) if name != "V" else [arr.shape[0], ORDER_CHUNK] + list(arr.shape[2:])
            chunks[1 if name == "V" else 0] = min(chunks[1 if name == "V" else 0], arr.shape[1 if name == "V" else 0])
            spec = {"shape": list(arr.shape), "chunks": chunks, "dtype": str(arr.dtype), "units": "see metadata"}
            za = _sized_array(vurl, path, arr, chunks, {"units": spec["units"], "info": info})
            za[...] = arr
            created[path] = spec
    fs, root = _fs(url)
    vroot = posixpath.join(root, "versions", plan.version)
    chunks = {key: _sha256(fs.cat_file(posixpath.join(vroot, key))) for key in _task_chunk_keys(plan, task, created)}
    record = {"task": task.id, "version": plan.version, "chunks": chunks, "arrays": created,
              "info": json.loads(json.dumps(info, default=float))}
    _write_json(fs, posixpath.join(vroot, task.record_name), record)  # written last: the task is done
    return record


def _sized_array(vurl, path, arr, chunks, attributes):
    """The array a task sizes (U, V): reused when it exists with this shape (a re-run, or the same task
    running in another build at the same time writes the same bytes into it), else (re)created.
    Never deleted while another writer may be hashing it."""
    try:
        za = zarr.open_array(vurl, path=path, mode="r+")
        if za.shape == arr.shape and za.dtype == arr.dtype and tuple(za.chunks) == tuple(chunks):
            return za
    except (FileNotFoundError, KeyError, ValueError, zarr.errors.NodeNotFoundError, zarr.errors.NodeTypeValidationError):
        pass
    try:
        return zarr.create_array(vurl, name=path, shape=arr.shape, chunks=tuple(chunks), dtype=arr.dtype,
                                 fill_value=np.nan, overwrite=False, attributes=attributes)
    except zarr.errors.ContainsArrayError:  # created by a concurrent run of the same task, or another shape
        za = zarr.open_array(vurl, path=path, mode="r+")
        if za.shape == arr.shape and za.dtype == arr.dtype:
            return za
        return zarr.create_array(vurl, name=path, shape=arr.shape, chunks=tuple(chunks), dtype=arr.dtype,
                                 fill_value=np.nan, overwrite=True, attributes=attributes)


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
    sums, sized = {}, {}
    for t in plan.tasks:
        rec = _read_json(fs, posixpath.join(vroot, t.record_name))
        sums.update(rec["chunks"])
        sized.update(rec.get("arrays", {}))
    for key in _all_chunk_keys(plan.arrays):
        if key not in sums:  # coordinates, written with the template
            sums[key] = _sha256(fs.cat_file(posixpath.join(vroot, key)))
    for p in fs.find(vroot):
        if p.endswith("zarr.json"):
            sums[posixpath.relpath(p, vroot)] = _sha256(fs.cat_file(p))
    doc = {"version": plan.version, "algorithm": "sha256", "files": dict(sorted(sums.items())),
           "arrays": dict(sorted(sized.items()))}
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


def complete_versions(url) -> list[str]:
    """The store's complete versions, ``latest`` first, then the others newest first (by the time
    their ``complete`` marker was written; a version of another store format is listed too, and
    refused when opened)."""
    fs, root = _fs(url)
    vdir = posixpath.join(root, "versions")
    if not fs.exists(vdir):
        return []
    found = []
    for p in fs.ls(vdir, detail=False):
        v = posixpath.basename(p.rstrip("/"))
        if v.startswith(".") or version_state(url, v) != "complete":
            continue
        try:
            t = fs.modified(posixpath.join(vdir, v, "complete")).timestamp()
        except (OSError, NotImplementedError, AttributeError):
            t = 0.0
        found.append((t, v))
    ordered = [v for _, v in sorted(found, key=lambda tv: (-tv[0], tv[1]))]
    try:
        latest = read_latest(url)
    except StoreError:
        latest = None
    if latest in ordered:
        ordered.remove(latest)
        ordered.insert(0, latest)
    return ordered


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
    return check_version_name(url, version, "`latest` names version")


# --------------------------------------------------------------------------------------------
# Verification and reading
# --------------------------------------------------------------------------------------------


def verify_version(url, version, only=None, deferred=None, sums_out=None) -> list[str]:
    """Problems of one version: completeness, schema, every file's sha256.  Empty list = sound.

    ``only``: path prefixes (e.g. ``species/metallic/n32/a0.25/``): hash only the files under them
    (and the version's top-level files) — what a compose reads.  ``deferred``: a predicate on a file
    key; those files are not hashed here (their checksum must be recorded) but left to the reader,
    which hashes each one before it reads it (:meth:`StoreVersion.verify`).  ``sums_out``: a dict that
    receives the recorded checksums (key → sha256) of the files selected."""
    fs, root = _fs(url)
    if not isinstance(version, str) or not _VERSION_RE.match(version):
        return [f"version {version!r:.80}: not a version hash (hex digits); it would point outside versions/"]
    vroot = posixpath.join(root, "versions", version)
    where = f"versions/{version}"
    if version_state(url, version) == "absent":
        return [f"{where}: no such version (no metadata in zarr.json)"]
    problems = []
    try:
        meta = _read_json(fs, posixpath.join(vroot, "zarr.json")).get("attributes", {})
    except (OSError, ValueError, UnicodeDecodeError) as exc:
        return [f"{where}/zarr.json: unreadable ({exc})"]
    if meta.get("format_version") != FORMAT_VERSION:
        return [f"{where}: store format {meta.get('format_version')} (this flakedb reads format {FORMAT_VERSION}: "
                "projected kernel factors); rebuild with `flakedb build`"]
    problems += [f"{where}: {p}" for p in schema_problems(meta, "metadata")]
    if meta.get("version") != version:
        problems.append(f"{where}: metadata names version {meta.get('version')!r}")
    if not fs.exists(posixpath.join(vroot, "complete")):
        done = sum(fs.exists(posixpath.join(vroot, "tasks/" + t.replace("/", "__") + ".json")) for t in meta.get("tasks", []))
        problems.append(f"{where}: incomplete build ({done} of {len(meta.get('tasks', []))} tasks done); "
                        "rerun `flakedb build` with the same inputs to finish it")
        return problems
    try:
        complete = _read_json(fs, posixpath.join(vroot, "complete"))
        cs_bytes = _cat(fs, posixpath.join(vroot, "checksums.json"))
        sums = json.loads(cs_bytes.decode("utf-8"))
    except (OSError, ValueError, UnicodeDecodeError) as exc:
        return problems + [f"{where}: complete / checksums.json unreadable ({exc})"]
    problems += [f"{where}: {p}" for p in schema_problems(complete, "complete")]
    problems += [f"{where}: {p}" for p in schema_problems(sums, "checksums")]
    if complete.get("checksums_sha256") != _sha256(cs_bytes):
        problems.append(f"{where}/checksums.json: sha256 differs from the one recorded in `complete`")
    if meta.get("format_version") != FORMAT_VERSION:
        return problems
    files = sums.get("files", {})
    if only is not None:
        files = {k: v for k, v in files.items() if "/" not in k or any(k.startswith(p) for p in only)}
    arrays = {**meta.get("arrays", {}), **sums.get("arrays", {})}
    selected = {p: a for p, a in arrays.items() if only is None or any(p.startswith(q) for q in only)}
    shape_problems = _array_problems(fs, vroot, where, selected, meta.get("arrays", {}))
    if shape_problems:   # before any chunk key is listed: a declared shape of 10^12 would take forever
        return problems + shape_problems
    for key in _all_chunk_keys(selected):
        if key not in files:
            problems.append(f"{where}/{key}: chunk has no recorded checksum")
    if sums_out is not None:
        sums_out.update(files)
    for key, expected in files.items():
        if deferred is not None and deferred(key):
            continue
        p = posixpath.join(vroot, key)
        if not fs.exists(p):
            problems.append(f"{where}/{key}: missing")
            continue
        try:
            got = _sha256(_cat(fs, p))
        except OSError as exc:  # e.g. a chunk replaced by a directory, a FIFO, a link to /dev/zero
            problems.append(f"{where}/{key}: unreadable ({exc.strerror or type(exc).__name__})")
            continue
        if got != expected:
            problems.append(f"{where}/{key}: sha256 {got[:16]}… != recorded {expected[:16]}… (corrupted)")
    return problems


def _array_problems(fs, vroot, where, arrays, declared) -> list[str]:
    """Problems of the arrays a version declares: shapes and chunks that are lists of positive integers
    (at most :data:`MAX_ARRAY_CHUNKS` chunks), the same in the version's metadata, its checksums and
    the array's own zarr.json (a mismatch would make a reader allocate or list the wrong size)."""
    out = []
    for path, spec in arrays.items():
        shape, chunks = (spec.get("shape"), spec.get("chunks")) if isinstance(spec, dict) else (None, None)
        ok = (isinstance(shape, list) and isinstance(chunks, list) and len(shape) == len(chunks) >= 1
              and all(isinstance(v, int) and not isinstance(v, bool) and v > 0 for v in shape + chunks))
        if not ok:
            out.append(f"{where}/{path}: shape {shape!r:.60} / chunks {chunks!r:.60} must be lists of positive "
                       f"integers of one length")
            continue
        n_chunks = math.prod(-(-s // c) for s, c in zip(shape, chunks))
        if n_chunks > MAX_ARRAY_CHUNKS:
            out.append(f"{where}/{path}: shape {shape} in chunks {chunks} is {n_chunks:,} chunks; the limit is "
                       f"{MAX_ARRAY_CHUNKS:,} (corrupted metadata)")
            continue
        d = declared.get(path)
        if isinstance(d, dict) and (d.get("shape") != shape or d.get("chunks") != chunks):
            out.append(f"{where}/{path}: checksums.json declares shape {shape} / chunks {chunks}, the version's "
                       f"metadata {d.get('shape')} / {d.get('chunks')} (corrupted)")
            continue
        try:
            zj = _read_json(fs, posixpath.join(vroot, path, "zarr.json"))
        except FileNotFoundError:
            out.append(f"{where}/{path}/zarr.json: missing")
            continue
        except (OSError, ValueError, UnicodeDecodeError) as exc:
            out.append(f"{where}/{path}/zarr.json: unreadable ({getattr(exc, 'strerror', None) or exc})")
            continue
        zshape = zj.get("shape") if isinstance(zj, dict) else None
        grid = (zj.get("chunk_grid") or {}).get("configuration", {}) if isinstance(zj, dict) else {}
        zchunks = grid.get("chunk_shape") if isinstance(grid, dict) else None
        if zshape != shape or (zchunks is not None and zchunks != chunks):
            out.append(f"{where}/{path}: the array's zarr.json declares shape {zshape!r:.60} / chunks {zchunks!r:.60}, "
                       f"the version's metadata {shape} / {chunks} (corrupted; hint: rebuild with `flakedb build`)")
    return out


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
            if latest is not None and not (isinstance(latest, str) and _VERSION_RE.match(latest)):
                problems.append(f"latest: names {latest!r:.80}, not a version hash; it would point outside versions/")
                latest = None
        except (OSError, ValueError, UnicodeDecodeError) as exc:
            problems.append(f"latest: unreadable ({getattr(exc, 'strerror', None) or exc})")
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

    With ``verify`` (default) every file's sha256 is checked against ``checksums.json`` first (a list
    of path prefixes: only the files under them, :func:`verify_version` ``only``) and a
    :class:`StoreIntegrityError` lists what does not match; an incomplete version raises
    :class:`StoreError`, a version of another store format too ("rebuild with flakedb build").
    """
    url = url if url is not None else default_store()
    if version is None:
        version = read_latest(url)
        if version is None:
            raise StoreError(f"{url}: no published version (no `latest`); run `flakedb build --store {url}`")
    check_version_name(url, version)
    state = version_state(url, version)
    if state != "complete":
        raise StoreError(f"{url}: version {version} is {state}; rerun `flakedb build` with the same inputs to finish it")
    fs, root = _fs(url)
    try:  # through the safe reader first: zarr would block on a FIFO or read a device without end
        _read_json(fs, posixpath.join(root, "versions", version, "zarr.json"))
    except (OSError, ValueError, UnicodeDecodeError) as exc:
        raise StoreError(f"{url}: versions/{version}/zarr.json is unreadable "
                         f"({getattr(exc, 'strerror', None) or exc}); rebuild with `flakedb build`") from None
    g = zarr.open_group(_version_url(url, version), mode="r")
    fmt = dict(g.attrs).get("format_version")
    if fmt != FORMAT_VERSION:
        raise StoreError(f"{url}: version {version[:12]} has store format {fmt}; this flakedb reads format "
                         f"{FORMAT_VERSION} (projected kernel factors, issue #11): rebuild with `flakedb build "
                         f"--store {url}` (or `flakedb build --recipe RECIPE --store {url}`)")
    sv = StoreVersion(str(url), version, g, dict(g.attrs))
    if verify:
        sv.verify(verify if isinstance(verify, (list, tuple)) else None)
    return sv


def _integrity_error(url, version, problems):
    return StoreIntegrityError(
        f"{url}: version {version} failed verification ({len(problems)} problem(s)); delete "
        f"versions/{version} and rebuild:\n  " + "\n  ".join(problems[:20]))


def _is_order_chunk(key) -> bool:
    """Whether a file key is a chunk of a flake's V (orders on axis 1, :data:`ORDER_CHUNK` per chunk)."""
    return "/V/c/" in key


def _order_chunk_keys(path, shape, chunks, c0, c1):
    """Keys of the chunks of array ``path`` holding order chunks c0 … c1 − 1 (axis 1), every other axis whole."""
    grid = [range(-(-s // c)) for s, c in zip(shape, chunks)]
    grid[1] = range(c0, min(c1, len(grid[1])))
    return [f"{path}/c/" + "/".join(map(str, idx)) for idx in itertools.product(*grid)]


@dataclass
class StoreVersion:
    """A read-only view of one complete version (:func:`open_version`)."""

    url: str
    version: str
    group: object
    metadata: dict
    #: recorded sha256 of the files still to be hashed when first read (:meth:`verify`); None: no checks
    pending_checksums: dict | None = None

    def verify(self, prefixes=None):
        """Check this version's files under ``prefixes`` (None: all) against ``checksums.json``:
        everything now except the flakes' V order chunks, which are hashed as the solver first reads
        each one (a compose reads the first 16–32 of up to 2n orders; hashing all of V cost more
        than the solve at n = 100).  Raises :class:`StoreIntegrityError` (now or at that read)."""
        sums = {}
        problems = verify_version(self.url, self.version, only=prefixes, deferred=_is_order_chunk, sums_out=sums)
        if problems:
            raise _integrity_error(self.url, self.version, problems)
        self.pending_checksums = {k: v for k, v in sums.items() if _is_order_chunk(k)}

    def _verify_chunks(self, keys):
        if self.pending_checksums is None:
            return
        fs, root = _fs(self.url)
        problems = []
        for key in keys:
            expected = self.pending_checksums.get(key)
            if expected is None:
                continue
            try:
                got = _sha256(_cat(fs, posixpath.join(root, "versions", self.version, key)))
            except OSError as exc:
                problems.append(f"versions/{self.version}/{key}: unreadable ({exc.strerror or type(exc).__name__})")
                continue
            if got != expected:
                problems.append(f"versions/{self.version}/{key}: sha256 {got[:16]}… != recorded {expected[:16]}… "
                                "(corrupted)")
                continue
            del self.pending_checksums[key]
        if problems:
            raise _integrity_error(self.url, self.version, problems)

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
    def top(self) -> str:
        """"rough" for a version built for rough top interfaces (plain Radau nodes inside), else "smooth"."""
        return self.metadata["inputs"].get("top", "smooth")

    @property
    def resolutions(self) -> list[int]:
        return [int(n) for n in self.metadata["inputs"]["resolutions"]]

    @property
    def raw(self) -> bool:
        """Whether the flakes' spectral SVD was kept at its numerical rank (``flakedb build --raw``)."""
        return bool(self.metadata["inputs"]["store_raw"])

    def alphas(self, species, distribution=BECKMANN) -> list[float]:
        """The α's the flake ``species`` was projected for in ``distribution`` (a version that records no
        distribution holds Beckmann flakes only)."""
        inp = self.metadata["inputs"]
        if distribution == BECKMANN:
            return [float(a) for a in inp["alphas"].get(species, [])]
        return [float(a) for a in inp.get("distribution_alphas", {}).get(species, {}).get(distribution, [])]

    def distributions(self, species) -> list[str]:
        """The flake orientation distributions ``species`` was projected for (each with some α)."""
        inp = self.metadata["inputs"]
        out = [BECKMANN] if inp["alphas"].get(species) else []
        return out + sorted(inp.get("distribution_alphas", {}).get(species, {}))

    def _check(self, species, n=None, alpha=None, distribution=BECKMANN):
        if species not in self.species:
            raise StoreError(f"version {self.version} has no species {species!r}; it has {', '.join(self.species)}")
        if n is not None and int(n) not in self.resolutions:
            raise StoreError(f"version {self.version} has no resolution n = {n}; it has {self.resolutions}")
        if alpha is not None and not any(abs(a - float(alpha)) <= 1e-12 for a in self.alphas(species, distribution)):
            raise StoreError(f"version {self.version} has {species!r} in the {distribution} distribution at α "
                             f"{self.alphas(species, distribution)}, not {alpha:g}")

    def grid(self, n):
        """(x, w) (h,) the positive inside nodes and weights of resolution n."""
        self._check(self.species[0], n)
        g = self.group[f"grid/{_res_key(n)}"]
        return g["x"][:], g["w"][:]

    def flake_prefix(self, species, n, alpha, distribution=BECKMANN) -> str:
        return Task(species, int(n), float(alpha), distribution=distribution).prefix

    def flake_factors(self, species, n, alpha, distribution=BECKMANN) -> FlakeFactors:
        """The stored factors of a flake species at (n, α, orientation ``distribution``)
        (:class:`flakedb.rt.stored.FlakeFactors`); V is read lazily, a chunk of :data:`ORDER_CHUNK`
        orders at a time, as the solver asks."""
        self._check(species, n, alpha, distribution)
        p = self.flake_prefix(species, n, alpha, distribution)
        g = self.group[p]
        V = g["V"]
        cache = {}

        def read(l0, l1):
            c0, c1 = l0 // ORDER_CHUNK, -(-l1 // ORDER_CHUNK)
            key = (c0, c1)
            if key not in cache:
                self._verify_chunks(_order_chunk_keys(f"{p}/V", V.shape, V.chunks, c0, c1))
                cache.clear()
                cache[key] = V[:, c0 * ORDER_CHUNK: c1 * ORDER_CHUNK]
            return cache[key][:, l0 - c0 * ORDER_CHUNK: l1 - c0 * ORDER_CHUNK]

        x, _ = self.grid(n)
        dist = "" if distribution == BECKMANN else f" {distribution}"
        return FlakeFactors(x, g["U"][:], read, int(V.shape[1]), g["sigma_t"][:], g["sigma_s"][:],
                            g["projected_area"][:],
                            f"store {self.url} version {self.version[:12]} {species} n = {n}{dist} α = {alpha:g}",
                            distribution)

    def flake_info(self, species, n, alpha, distribution=BECKMANN) -> dict:
        """The compression record of a flake task (rank, singular values, error bound, storage ratio)."""
        self._check(species, n, alpha, distribution)
        return dict(self.group[f"{self.flake_prefix(species, n, alpha, distribution)}/U"].attrs.get("info", {}))

    def pigment(self, species) -> dict:
        """``c_ext_um2``, ``c_sca_um2``, ``mean_volume_um3`` (W,) and ``legendre_moments`` (W, K + 1)."""
        self._check(species)
        g = self.group[f"species/{species}"]
        return {k: g[k][:] for k in ("c_ext_um2", "c_sca_um2", "mean_volume_um3", "legendre_moments")}
