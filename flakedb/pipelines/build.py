"""The precompute build (issue #5): catalogue → plan → Zarr template → one Dask task per
(species, resolution, channel block) → finalize → publish ``latest``.

Only wiring lives here: the plan, the per-task work and the store format are in
:mod:`flakedb.store.versions` and :mod:`flakedb.store.compress`.  Executors are interchangeable: the synchronous
scheduler, local threads / processes, or a ``dask.distributed`` client; every one writes the same
bytes (tests/test_store.py).
"""

from __future__ import annotations

import hashlib
import time
from pathlib import Path

from flakedb.colour.colorimetry import spectral_grid
from flakedb.paint import catalog as cat
from flakedb.paint.materials import materials_dir
from flakedb.store import versions as st
from flakedb.store.compress import DEFAULT_N_TABLE

DEFAULT_N = (32,)
DEFAULT_RANK = 8
DEFAULT_RANGE_NM = (400.0, 700.0)
DEFAULT_STEP_NM = 20.0
#: top interface index of ``flakedb build``: the catalogue's paints have a smooth 1.5 clear coat.
DEFAULT_ETA_TOP = 1.5


def material_checksums() -> dict:
    """sha256 of every optical-data file shipped in catalog/materials (name → hex)."""
    d = Path(materials_dir())
    return {p.name: hashlib.sha256(p.read_bytes()).hexdigest() for p in sorted(d.iterdir()) if p.is_file()}


def make_request(species=None, n=DEFAULT_N, m=None, rank=DEFAULT_RANK, wavelength_nm=None, channel_block=4,
                 store_raw=False, catalog_path=None, n_table=None, eta_top=None) -> st.BuildRequest:
    """A :class:`flakedb.store.versions.BuildRequest` from the catalogue (default: every species, sweeps
    included).  ``n``: node counts (one resolution each, m = n unless ``m`` is given);
    ``wavelength_nm``: default 400–700 nm every 20 nm; ``eta_top``: the paints' smooth top index
    (None: plain Radau grid and the catalogue binder's index; see :mod:`flakedb.store.versions`)."""
    catalog = cat.load_catalog(catalog_path)
    allsp = cat.expand_sweeps(catalog)
    names = list(allsp) if not species else list(species)
    unknown = [s for s in names if s not in allsp]
    if unknown:
        raise ValueError(f"unknown species {', '.join(unknown)}; known: {', '.join(allsp)}")
    ns = (int(n),) if isinstance(n, int) else tuple(int(x) for x in n)
    wl = spectral_grid(DEFAULT_RANGE_NM, DEFAULT_STEP_NM) if wavelength_nm is None else wavelength_nm
    return st.BuildRequest(
        species={s: allsp[s] for s in names}, binder=catalog["binder"], material_checksums=material_checksums(),
        resolutions=tuple((x, int(m) if m else x) for x in ns), rank=int(rank),
        wavelength_nm=tuple(float(w) for w in wl), channel_block=int(channel_block), store_raw=bool(store_raw),
        n_table=int(n_table or DEFAULT_N_TABLE), eta_top=None if eta_top is None else float(eta_top))


def _execute(url, plan, tasks, scheduler, workers, client, progress):
    import dask  # lazy: Dask only where a build runs

    graph = [dask.delayed(st.run_task, pure=False)(url, plan, t, dask_key_name=f"task-{t.id}") for t in tasks]
    if client is not None or (scheduler and "://" in str(scheduler)):
        from distributed import Client  # lazy: Dask only where a build runs
        from distributed import progress as dprogress  # lazy: Dask only where a build runs

        own = client is None
        client = client or Client(scheduler)
        try:
            futures = client.compute(graph)
            if progress:
                dprogress(futures)
            return client.gather(futures)
        finally:
            if own:
                client.close()
    kwargs = {"scheduler": scheduler or "threads"}
    if workers:
        kwargs["num_workers"] = int(workers)
    if progress:
        from dask.diagnostics import ProgressBar  # lazy: Dask only where a build runs

        with ProgressBar():
            return dask.compute(*graph, **kwargs)
    return dask.compute(*graph, **kwargs)


def build(request: st.BuildRequest, store=None, scheduler=None, workers=None, client=None, progress=False,
          max_tasks=None, publish=True) -> dict:
    """Build (or reuse) the version of ``request`` in ``store`` and point ``latest`` at it.

    ``scheduler``: 'threads' (default), 'processes', 'sync', or a ``tcp://`` address of a
    dask.distributed scheduler; ``client``: an existing distributed Client (wins over scheduler);
    ``workers``: local worker count.  ``max_tasks``: run at most that many pending tasks and stop
    before finalizing (a deliberately partial build: what an interruption leaves; used by tests).
    Returns ``{version, status ('reused' | 'built' | 'partial'), tasks_run, tasks_total, seconds}``.
    """
    url = str(store or st.default_store())
    t0 = time.perf_counter()
    plan = st.plan_build(request)
    out = {"version": plan.version, "tasks_total": len(plan.tasks), "store": url}
    if st.version_state(url, plan.version) == "complete":
        if publish and st.read_latest(url) != plan.version:
            st.publish(url, plan.version)
        return {**out, "status": "reused", "tasks_run": 0, "seconds": time.perf_counter() - t0}
    st.write_template(url, plan)
    todo = st.pending_tasks(url, plan)
    if max_tasks is not None:
        todo = todo[: int(max_tasks)]
    if todo:
        _execute(url, plan, todo, scheduler, workers, client, progress)
    if st.pending_tasks(url, plan):
        return {**out, "status": "partial", "tasks_run": len(todo), "seconds": time.perf_counter() - t0}
    st.finalize(url, plan)
    if publish:
        st.publish(url, plan.version)
    return {**out, "status": "built", "tasks_run": len(todo), "seconds": time.perf_counter() - t0}
