"""Writing a store version: the Zarr template, one task's arrays and its record, the checksums and ``complete``,
then ``latest`` (docs/store.md "Building"); every step can be re-run safely.
"""

from __future__ import annotations

import json
import os
import posixpath
import re
import shutil
import time
import uuid

import numpy as np

from flakedb.outputs import STALE_AGE_S, pid_alive, temp_host
from flakedb.paint import species as sp
from flakedb.store.compress import (
    ORDER_CHUNK,
    flake_task,
    pigment_task,
    store_nodes,
)
from flakedb.store.errors import StoreError, StoreIntegrityError  # noqa: F401  (re-exported)
from flakedb.store.fs import open_fs, read_json, sha256, version_state, version_url, write_json
from flakedb.store.plan import BuildPlan, Task, chunk_keys, metadata, res_key, schema_problems, task_chunk_keys



#: The chunks' compressors: none.  zarr's default (zstd level 0) kept 84 % of the bytes of a 3-species
#: n = 100 store (172 of 206 MB: SVD factors are dense floats) and its decoding was ~45 ms of a ~0.8 s
#: whole-process compose; uncompressed chunks are read into their array with no copy
#: (flakedb/store/plain.py, which still decodes the zstd chunks of stores written before).
COMPRESSORS = None

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
    fs, root = open_fs(url, writable=True)
    local = "file" in (fs.protocol if isinstance(fs.protocol, (tuple, list)) else (fs.protocol,))
    final = posixpath.join(root, "versions", plan.version)
    if local:
        # Build the template privately and rename it into place: two builds starting at once
        # cannot clear or interleave each other's template (the loser's rename fails, it uses the
        # winner's).  A leftover partial template (interrupted before the rename) never exists.

        vdir = posixpath.join(root, "versions")
        os.makedirs(vdir, exist_ok=True)
        remove_stale_templates(vdir)   # templates of builds killed before their rename (kill -9, a crash)
        tmp = posixpath.join(vdir, f".tmp-{plan.version[:16]}-{template_owner()}-{uuid.uuid4().hex[:8]}")
        try:
            _fill_template(tmp, plan, meta)
        except BaseException:   # disk full, a signal: no half template left in versions/
            shutil.rmtree(tmp, ignore_errors=True)
            raise
        try:
            os.rename(tmp, final)
        except OSError:
            shutil.rmtree(tmp, ignore_errors=True)
            if version_state(url, plan.version) == "absent":
                raise
            return False
        return True
    _fill_template(version_url(url, plan.version), plan, meta)
    return True


#: A private template's name: ``.tmp-<version[:16]>-<host>.<pid>-<8 hex>`` (the host written by builds since
#: issue 38; a name without it is an older build's, whose owner cannot be told).
TEMPLATE_RE = re.compile(r"^\.tmp-[0-9a-f]{1,16}-(?:(?P<host>[A-Za-z0-9-]+)\.)?(?P<pid>\d+)-[0-9a-f]{1,8}$")


def template_owner() -> str:
    """``HOST.PID`` of this process, as a private template's name carries it."""
    return f"{temp_host()}.{os.getpid()}"


def stray_templates(versions_dir) -> list[tuple[str, bool]]:
    """``(name, stale)`` of every private template (``.tmp-…``) in a local ``versions_dir``: stale when it is
    this host's and its process is gone, or older than :data:`flakedb.outputs.STALE_AGE_S` (another host's,
    or an older build's name without the host); a template of a build still running is not stale."""
    try:
        entries = list(os.scandir(versions_dir))
    except OSError:
        return []
    out = []
    now = time.time()
    for e in entries:
        m = TEMPLATE_RE.match(e.name)
        if not m:
            continue
        try:
            age = now - e.stat(follow_symlinks=False).st_mtime
        except OSError:
            continue
        if m.group("host") == temp_host():
            stale = int(m.group("pid")) != os.getpid() and not pid_alive(int(m.group("pid")))
        else:
            stale = age > STALE_AGE_S
        out.append((e.name, stale))
    return out


def remove_stale_templates(versions_dir) -> list[str]:
    """Remove the stale private templates of :func:`stray_templates` (a symlink as a link); returns their names."""
    removed = []
    for name, stale in stray_templates(versions_dir):
        if not stale:
            continue
        p = os.path.join(versions_dir, name)
        if os.path.islink(p):
            os.unlink(p)
        else:
            shutil.rmtree(p, ignore_errors=True)
        if not os.path.lexists(p):
            removed.append(name)
    return removed


def _fill_template(vurl, plan: BuildPlan, meta: dict):
    import zarr  # lazy: zarr takes 0.3-0.8 s to import; a compose without a store never opens one

    g = zarr.open_group(vurl, mode="w")  # also clears a template whose writing was interrupted
    for path, spec in plan.arrays.items():
        g.create_array(path, shape=tuple(spec["shape"]), chunks=tuple(spec["chunks"]), dtype=spec["dtype"],
                       fill_value=np.nan, attributes={"units": spec["units"]}, compressors=COMPRESSORS)
    for t in plan.tasks:  # the group a flake task's own arrays go in exists before any task runs
        if t.is_flake:
            g.require_group(t.prefix)
    g["wavelength_nm"][:] = np.asarray(plan.inputs["wavelength_nm"], dtype=float)
    for n in plan.inputs["resolutions"]:
        x, w = store_nodes(n, plan.inputs.get("eta_top"), plan.inputs.get("top", "smooth"))
        g[f"grid/{res_key(n)}/x"][:] = x
        g[f"grid/{res_key(n)}/w"][:] = w
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
    import zarr  # lazy: zarr takes 0.3-0.8 s to import; a compose without a store never opens one

    data = compute_task(plan.inputs, task)
    info = data.pop("info", {})
    vurl = version_url(url, plan.version)
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
    fs, root = open_fs(url, writable=True)
    vroot = posixpath.join(root, "versions", plan.version)
    chunks = {key: sha256(fs.cat_file(posixpath.join(vroot, key))) for key in task_chunk_keys(plan, task, created)}
    record = {"task": task.id, "version": plan.version, "chunks": chunks, "arrays": created,
              "info": json.loads(json.dumps(info, default=float))}
    write_json(fs, posixpath.join(vroot, task.record_name), record)  # written last: the task is done
    return record


def _sized_array(vurl, path, arr, chunks, attributes):
    """The array a task sizes (U, V): reused when it exists with this shape (a re-run, or the same task
    running in another build at the same time writes the same bytes into it), else (re)created.
    Never deleted while another writer may be hashing it."""
    import zarr  # lazy: zarr takes 0.3-0.8 s to import; a compose without a store never opens one

    try:
        za = zarr.open_array(vurl, path=path, mode="r+")
        if za.shape == arr.shape and za.dtype == arr.dtype and tuple(za.chunks) == tuple(chunks):
            return za
    except (FileNotFoundError, KeyError, ValueError, zarr.errors.NodeNotFoundError, zarr.errors.NodeTypeValidationError):
        pass
    try:
        return zarr.create_array(vurl, name=path, shape=arr.shape, chunks=tuple(chunks), dtype=arr.dtype,
                                 fill_value=np.nan, overwrite=False, attributes=attributes,
                                 compressors=COMPRESSORS)
    except zarr.errors.ContainsArrayError:  # created by a concurrent run of the same task, or another shape
        za = zarr.open_array(vurl, path=path, mode="r+")
        if za.shape == arr.shape and za.dtype == arr.dtype:
            return za
        return zarr.create_array(vurl, name=path, shape=arr.shape, chunks=tuple(chunks), dtype=arr.dtype,
                                 fill_value=np.nan, overwrite=True, attributes=attributes,
                                 compressors=COMPRESSORS)


def pending_tasks(url, plan: BuildPlan) -> list:
    """Tasks of the plan without a record in the version (all of them for a fresh version)."""
    fs, root = open_fs(url, writable=True)
    vroot = posixpath.join(root, "versions", plan.version)
    return [t for t in plan.tasks if not fs.exists(posixpath.join(vroot, t.record_name))]


def all_chunk_keys(arrays: dict):
    """Every chunk key of the arrays of a version's metadata (``{path: {"shape", "chunks"}}``), as
    :func:`flakedb.store.plan.chunk_keys` names them: what ``finalize`` checksums and ``verify`` reads.

    >>> len(all_chunk_keys({"wavelength_nm": {"shape": [81], "chunks": [81]}, "a/V": {"shape": [4, 6], "chunks": [2, 3]}}))
    5
    """
    return [k for path, spec in arrays.items() for k in chunk_keys(path, spec)]


def finalize(url, plan: BuildPlan):
    """After every task: collect the checksums (task records, coordinates, every zarr.json) into
    ``checksums.json``, then write ``complete``.  Refuses when a task record or chunk is missing."""
    fs, root = open_fs(url, writable=True)
    vroot = posixpath.join(root, "versions", plan.version)
    missing = pending_tasks(url, plan)
    if missing:
        raise StoreError(f"cannot finalize {plan.version}: {len(missing)} task(s) not done, e.g. {missing[0].id}")
    sums, sized = {}, {}
    for t in plan.tasks:
        rec = read_json(fs, posixpath.join(vroot, t.record_name))
        sums.update(rec["chunks"])
        sized.update(rec.get("arrays", {}))
    for key in all_chunk_keys(plan.arrays):
        if key not in sums:  # coordinates, written with the template
            sums[key] = sha256(fs.cat_file(posixpath.join(vroot, key)))
    for p in fs.find(vroot):
        if p.endswith("zarr.json"):
            sums[posixpath.relpath(p, vroot)] = sha256(fs.cat_file(p))
    doc = {"version": plan.version, "algorithm": "sha256", "files": dict(sorted(sums.items())),
           "arrays": dict(sorted(sized.items()))}
    write_json(fs, posixpath.join(vroot, "checksums.json"), doc)
    cs = sha256(fs.cat_file(posixpath.join(vroot, "checksums.json")))
    write_json(fs, posixpath.join(vroot, "complete"), {"version": plan.version, "checksums_sha256": cs,
                                                        "n_files": len(sums)})


def publish(url, version):
    """Point ``latest`` at a complete version: write a temporary file, then rename it over ``latest``
    (atomic on a local file system; on object stores a single-object PUT is atomic too)."""
    if version_state(url, version) != "complete":
        raise StoreError(f"refusing to publish version {version}: it is not complete")
    fs, root = open_fs(url, writable=True)
    write_json(fs, posixpath.join(root, "latest"), {"version": version})
