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
        species/<flake>/n<N>/a<α>/V_last_order (r, 2, h, h) float32 = V[:, L − 1], the order compose's
                                              Jackson filter test reads (versions before it lack it)
        species/<flake>/n<N>/a<α>/sigma_t     (W, h) σ_t per unit aρ at the nodes (and sigma_s,
                                              projected_area (h,) for opaque flakes)
        species/<pigment>/c_ext_um2, c_sca_um2, mean_volume_um3   (W,) ensemble Mie optics
        species/<pigment>/legendre_moments    (W, K + 1) χ_k of the phase function (χ_0 = 1)
        tasks/<task>.json                     one per finished task: sha256 of every chunk it wrote
                                              (and the arrays it sized: U, V)
        checksums.json                        every chunk and zarr.json of the version with its sha256
        complete                              written last, after every task finished

So compose performs no azimuthal projection: a flake's kernel in the recipe's channels is
(loading · map @ U) @ V, a pigment's the addition theorem on its moments (flakedb/rt/scattering/stored.py).

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

The parts (issue #21): :mod:`flakedb.store.plan` (request, tasks, metadata: no files),
:mod:`flakedb.store.fs` (fsspec paths, JSON, checksums), :mod:`flakedb.store.write` (template, tasks,
finalize, publish) and :mod:`flakedb.store.read` (versions, verification, :class:`StoreVersion`); this
module re-exports them, so ``from flakedb.store import versions as st`` keeps working, and opens no
Zarr until a store is used:

>>> import sys
>>> from flakedb.store import versions as st
>>> st.FORMAT_VERSION >= 1, callable(st.open_version)
(True, True)
"""

from __future__ import annotations

from flakedb.store.errors import StoreError, StoreIntegrityError  # noqa: F401  (re-exported)
from flakedb.store.fs import (  # noqa: F401  (re-exported)
    MAX_ARRAY_CHUNKS,
    MAX_STORE_FILE_BYTES,
    VERSION_RE,
    cat,
    check_version_name,
    open_fs,
    read_json,
    sha256,
    version_state,
    version_url,
    write_json,
)
from flakedb.store.plan import (  # noqa: F401  (re-exported)
    BECKMANN,
    DEFAULT_STORE,
    FORMAT,
    FORMAT_VERSION,
    BuildPlan,
    BuildRequest,
    Task,
    chunk_keys,
    content_hash,
    default_store,
    metadata,
    plan_build,
    res_key,
    schema_path,
    schema_problems,
    task_chunk_keys,
)
from flakedb.store.read import StoreVersion, complete_versions, open_version, read_latest, verify_store, verify_version  # noqa: F401  (re-exported)
from flakedb.store.write import all_chunk_keys, compute_task, finalize, pending_tasks, publish, run_task, write_template  # noqa: F401  (re-exported)

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
