"""Reading a store: its complete versions, ``latest``, verification of checksums and completeness, and
:class:`StoreVersion`, the open version compose reads kernel factors from (docs/store.md "Reading").
"""

from __future__ import annotations

import itertools
import json
import math
import posixpath
from dataclasses import dataclass

import numpy as np

from flakedb.rt.scattering.stored import FlakeFactors
from flakedb.store.compress import (
    ORDER_CHUNK,
)
from flakedb.store.errors import StoreError, StoreIntegrityError  # noqa: F401  (re-exported)
from flakedb.store.fs import (
    MAX_ARRAY_CHUNKS,
    VERSION_RE,
    cat,
    check_version_name,
    is_local_path,
    open_fs,
    read_json,
    sha256,
    version_state,
    version_url,
)
from flakedb.store.plain import PlainArray, PlainGroup
from flakedb.store.plan import (
    BECKMANN,
    FORMAT_VERSION,
    Task,
    default_store,
    res_key,
    schema_problems,
)
from flakedb.store.write import all_chunk_keys, stray_templates


def complete_versions(url) -> list[str]:
    """The store's complete versions, ``latest`` first, then the others newest first (by the time
    their ``complete`` marker was written; a version of another store format is listed too, and
    refused when opened).

    >>> import tempfile
    >>> complete_versions(tempfile.mkdtemp())                    # an empty folder holds no version
    []
    """
    fs, root = open_fs(url)
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
    fs, root = open_fs(url)
    p = posixpath.join(root, "latest")
    if not fs.exists(p):
        return None
    try:
        version = read_json(fs, p)["version"]
    except (OSError, ValueError, UnicodeDecodeError, KeyError, TypeError) as exc:
        raise StoreError(f"{url}: `latest` is unreadable ({type(exc).__name__}: {exc}); it must be a JSON file "
                         f'{{"version": "<hash>"}} (hint: remove it and rerun `flakedb build` with the same '
                         f"inputs, which rewrites it)") from None
    return check_version_name(url, version, "`latest` names version")


def verify_version(url, version, only=None, deferred=None, sums_out=None) -> list[str]:
    """Problems of one version: completeness, schema, every file's sha256.  Empty list = sound.

    ``only``: path prefixes (e.g. ``species/metallic/n32/a0.25/``): hash only the files under them
    (and the version's top-level files) — what a compose reads.  ``deferred``: a predicate on a file
    key; those files are not hashed here (their checksum must be recorded) but left to the reader,
    which hashes each one before it reads it (:meth:`StoreVersion.verify`).  ``sums_out``: a dict that
    receives the recorded checksums (key → sha256) of the files selected."""
    fs, root = open_fs(url)
    if not isinstance(version, str) or not VERSION_RE.match(version):
        return [f"version {version!r:.80}: not a version hash (hex digits); it would point outside versions/"]
    vroot = posixpath.join(root, "versions", version)
    where = f"versions/{version}"
    if version_state(url, version) == "absent":
        return [f"{where}: no such version (no metadata in zarr.json)"]
    problems = []
    try:
        meta = read_json(fs, posixpath.join(vroot, "zarr.json")).get("attributes", {})
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
        complete = read_json(fs, posixpath.join(vroot, "complete"))
        cs_bytes = cat(fs, posixpath.join(vroot, "checksums.json"))
        sums = json.loads(cs_bytes.decode("utf-8"))
    except (OSError, ValueError, UnicodeDecodeError) as exc:
        return problems + [f"{where}: complete / checksums.json unreadable ({exc})"]
    problems += [f"{where}: {p}" for p in schema_problems(complete, "complete")]
    problems += [f"{where}: {p}" for p in schema_problems(sums, "checksums")]
    if complete.get("checksums_sha256") != sha256(cs_bytes):
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
    for key in all_chunk_keys(selected):
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
            got = sha256(cat(fs, p))
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
            zj = read_json(fs, posixpath.join(vroot, path, "zarr.json"))
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
    fs, root = open_fs(url)
    if not fs.exists(root):
        return [f"{url}: no such store"]
    problems = []
    latest = None
    lp = posixpath.join(root, "latest")
    if fs.exists(lp):
        try:
            doc = read_json(fs, lp)
            problems += [f"latest: {p}" for p in schema_problems(doc, "latest")]
            latest = doc.get("version") if isinstance(doc, dict) else None
            if latest is not None and not (isinstance(latest, str) and VERSION_RE.match(latest)):
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
        if is_local_path(str(url)):   # strays a killed build left (kill -9, a crash; issue 38)
            for name, stale in stray_templates(vdir):
                if stale:
                    problems.append(f"versions/{name}: a stray template left by an interrupted build (its process "
                                    f"is gone); `flakedb build` removes it, or remove it by hand")
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
    fs, root = open_fs(url)
    try:  # through the safe reader first: zarr would block on a FIFO or read a device without end
        read_json(fs, posixpath.join(root, "versions", version, "zarr.json"))
    except (OSError, ValueError, UnicodeDecodeError) as exc:
        raise StoreError(f"{url}: versions/{version}/zarr.json is unreadable "
                         f"({getattr(exc, 'strerror', None) or exc}); rebuild with `flakedb build`") from None
    # read without zarr (flakedb.store.plain: zarr's import is a fifth of a compose); zarr opens any array of
    # another layout
    g = PlainGroup(fs, posixpath.join(root, "versions", version), version_url(url, version))
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


#: Ranges of V order chunks a flake's reader keeps: the solver reads the first orders, then the last (the Jackson
#: filter's test, flakedb.rt.scattering.medium_projection.damp_if_capped), then the first again; with one kept, the first chunk
#: was read and hashed twice (the 3-species compose: 6 reads of 6.7-9.7 MB instead of 4).
V_CHUNKS_CACHED = 2


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
    #: recorded sha256 of the files hashed as they are read, at every read (:meth:`verify`: the flakes' V order
    #: chunks under the verified prefixes); None: not verified, no checks
    deferred_checksums: dict | None = None

    def verify(self, prefixes=None):
        """Check this version's files under ``prefixes`` (None: all) against ``checksums.json``:
        everything now except the flakes' V order chunks, which are hashed as the solver first reads
        each one (a compose reads the first 16–32 of up to 2n orders; hashing all of V cost more
        than the solve at n = 100).  Raises :class:`StoreIntegrityError` (now or at that read)."""
        sums = {}
        problems = verify_version(self.url, self.version, only=prefixes, deferred=_is_order_chunk, sums_out=sums)
        if problems:
            raise _integrity_error(self.url, self.version, problems)
        self.deferred_checksums = {k: v for k, v in sums.items() if _is_order_chunk(k)}

    def _verify_chunks(self, keys):
        if self.deferred_checksums is None:
            return
        fs, root = open_fs(self.url)
        problems = []
        for key in keys:
            try:
                data, error = cat(fs, posixpath.join(root, "versions", self.version, key)), None
            except FileNotFoundError:
                data, error = None, None
            except OSError as exc:
                data, error = None, exc
            problems += self._checked(key, data, error)
        if problems:
            raise _integrity_error(self.url, self.version, problems)

    def _checked(self, key, data, error=None) -> list[str]:
        """The problems of a deferred chunk's bytes against its recorded checksum (empty: sound): ``data`` None is
        no file, ``error`` the OSError that kept it from being read.  Nothing is checked without verification
        (:attr:`deferred_checksums` None); an order chunk with no recorded checksum is a problem (a key that does
        not match the record would otherwise pass unhashed)."""
        if self.deferred_checksums is None:
            return []
        where = f"versions/{self.version}/{key}"
        expected = self.deferred_checksums.get(key)
        if expected is None:
            return [f"{where}: no recorded checksum (not among the verified files)"] if _is_order_chunk(key) else []
        if error is not None:
            return [f"{where}: unreadable ({getattr(error, 'strerror', None) or type(error).__name__})"]
        if data is None:
            return [f"{where}: unreadable (missing)"]
        got = sha256(data)
        if got != expected:
            return [f"{where}: sha256 {got[:16]}… != recorded {expected[:16]}… (corrupted)"]
        return []

    def _chunk_check(self, vroot):
        """:attr:`flakedb.store.plain.PlainArray.check` for this version's arrays under ``vroot``: the bytes a
        chunk is decoded from are the bytes hashed, at every read (:meth:`verify`)."""
        def check(path, data, error=None):
            problems = self._checked(posixpath.relpath(path, vroot), data, error)
            if problems:
                raise _integrity_error(self.url, self.version, problems)
        return check

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
        g = self.group[f"grid/{res_key(n)}"]
        return g["x"][:], g["w"][:]

    def flake_prefix(self, species, n, alpha, distribution=BECKMANN) -> str:
        return Task(species, int(n), float(alpha), distribution=distribution).prefix

    def flake_factors(self, species, n, alpha, distribution=BECKMANN) -> FlakeFactors:
        """The stored factors of a flake species at (n, α, orientation ``distribution``)
        (:class:`flakedb.rt.scattering.stored.FlakeFactors`); V is read lazily, a chunk of :data:`ORDER_CHUNK`
        orders at a time, as the solver asks."""
        self._check(species, n, alpha, distribution)
        p = self.flake_prefix(species, n, alpha, distribution)
        g = self.group[p]
        V = g["V"]
        cache = {}
        if isinstance(V, PlainArray):  # each chunk checked on the bytes it is decoded from
            V.check = self._chunk_check(self.group.root)
        L = int(V.shape[1])
        try:  # the last order on its own (verified with the version's other small arrays); older versions lack it
            last = g["V_last_order"][:][:, None]
        except KeyError:
            last = None

        def read(l0, l1):
            if last is not None and (l0, l1) == (L - 1, L):  # the Jackson filter's test: 1 order, not a 16-order chunk
                return last
            c0, c1 = l0 // ORDER_CHUNK, -(-l1 // ORDER_CHUNK)
            key = (c0, c1)
            if key not in cache:
                if not isinstance(V, PlainArray):  # zarr reads its own: the files hashed first
                    self._verify_chunks(_order_chunk_keys(f"{p}/V", V.shape, V.chunks, c0, c1))
                if len(cache) >= V_CHUNKS_CACHED:  # the oldest range out
                    del cache[next(iter(cache))]
                cache[key] = V[:, c0 * ORDER_CHUNK: c1 * ORDER_CHUNK]
            return cache[key][:, l0 - c0 * ORDER_CHUNK: l1 - c0 * ORDER_CHUNK]

        x, _ = self.grid(n)
        dist = "" if distribution == BECKMANN else f" {distribution}"
        return FlakeFactors(x, g["U"][:], read, L, g["sigma_t"][:], g["sigma_s"][:],
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
