"""The precompute build (issue #5): catalogue → plan → Zarr template → one Dask task per
(species, resolution, channel block) → finalize → publish ``latest``.

Only wiring lives here: the plan, the per-task work and the store format are in
:mod:`flakedb.store.versions` and :mod:`flakedb.store.compress`.  Executors are interchangeable: the synchronous
scheduler, local threads / processes, or a ``dask.distributed`` client; every one writes the same
bytes (tests/test_store.py).
"""

from __future__ import annotations

import hashlib
import sys
import time
from pathlib import Path

from flakedb.colour.colorimetry import spectral_grid
from flakedb.paint import catalog as cat
from flakedb.paint import species as sp
from flakedb.paint.mapping import catalog_species
from flakedb.paint.components import particle_entry, recipe_alpha, recipe_distribution, recipe_top_alpha, store_key
from flakedb.solve.resolution import (
    resolve_node_count,
)
from flakedb.paint.materials import materials_dir
from flakedb.paint.recipe import load_recipe
from flakedb.pipelines.progress import BuildProgress
from flakedb.pipelines.workers import MAX_POOL_RESTARTS, process_pool
from flakedb.resources import RECIPES_DIR
from flakedb.rt.scattering.stored import RANK_TOL
from flakedb.store import versions as st

DEFAULT_N = (32,)
#: The default store's wavelengths: 380–780 nm every 5 nm, so every recipe band on a 5, 10 or 20 nm
#: grid from 380 nm is selected exactly (others are interpolated between neighbours, stated in info).
DEFAULT_RANGE_NM = (380.0, 780.0)
DEFAULT_STEP_NM = 5.0
#: top interface index of ``flakedb build``: the catalogue's paints have a smooth 1.5 clear coat.
DEFAULT_ETA_TOP = 1.5


def material_checksums() -> dict:
    """sha256 of every optical-data file shipped in catalog/materials (name → hex)."""
    d = Path(materials_dir())
    return {p.name: hashlib.sha256(p.read_bytes()).hexdigest() for p in sorted(d.iterdir()) if p.is_file()}


def recipe_orientations(recipes) -> dict:
    """Flake species → {orientation distribution: sorted α's} the catalogue flakes of ``recipes`` use
    (:func:`flakedb.paint.components.recipe_distribution`, :func:`flakedb.paint.components.recipe_alpha`)."""
    out = {}
    for rec in recipes:
        for p in catalog_species(rec):
            if p.is_flake:
                out.setdefault(store_key(p), {}).setdefault(recipe_distribution(p), set()).add(recipe_alpha(p))
    return {k: {d: sorted(a) for d, a in sorted(v.items())} for k, v in out.items()}


def _shipped_orientations(catalog=None) -> dict:
    catalog = catalog or sp.load_catalog()
    return recipe_orientations(load_recipe(path, catalog) for path in sorted(Path(RECIPES_DIR).glob("*.yaml")))


def shipped_alphas(catalog=None) -> dict:
    """Flake species → the Beckmann orientation spreads α the shipped recipes (catalog/recipes/) use for
    them (the catalogue's own α or a recipe's ``orientation_alpha``): the default store projects these
    (and :func:`shipped_distribution_alphas`)."""
    return {k: v["beckmann"] for k, v in _shipped_orientations(catalog).items() if "beckmann" in v}


def shipped_distribution_alphas(catalog=None) -> dict:
    """Flake species → {distribution other than Beckmann: α's} the shipped recipes use."""
    out = {k: {d: a for d, a in v.items() if d != "beckmann"} for k, v in _shipped_orientations(catalog).items()}
    return {k: v for k, v in out.items() if v}


def make_request(species=None, n=DEFAULT_N, wavelength_nm=None, alphas=None, channel_block=8, store_raw=False,
                 catalog_path=None, eta_top=None, rank_tol=None, recipe=None, top="smooth",
                 distribution_alphas=None, entries=None) -> st.BuildRequest:
    """A :class:`flakedb.store.versions.BuildRequest` from the catalogue (default: every species, sweeps
    included).  ``n``: node counts; ``wavelength_nm``: default 380–780 nm every 5 nm; ``alphas``:
    flake species → Beckmann α's and ``distribution_alphas`` flake species → {distribution: α's}
    (both None: the catalogue's α in the catalogue's distribution and those the shipped recipes use);
    ``eta_top``: the paints' smooth top index (None: plain Radau grid and the catalogue binder's
    index; see :mod:`flakedb.store.versions`); ``rank_tol``: the flakes' spectral SVD truncation;
    ``entries``: more species, key → resolved entry, beside ``species`` (a recipe's species with its own
    films or pigment size, :func:`flakedb.paint.components.store_key`; with ``species`` None only these).

    >>> r = make_request(species=["gray-mirror"], n=16, alphas={"gray-mirror": [0.25]})
    >>> r.resolutions, r.alphas, len(r.wavelength_nm), r.wavelength_nm[0], r.wavelength_nm[-1]
    ((16,), {'gray-mirror': [0.25]}, 81, 380.0, 780.0)
    >>> make_request(species=["grey-mirror"])
    Traceback (most recent call last):
    ...
    ValueError: unknown species grey-mirror; known: metallic, pearlescent, gray-mirror, ...
    """
    catalog = cat.load_catalog(catalog_path)
    allsp = cat.expand_sweeps(catalog)
    entries = dict(entries or {})
    names = list(species or []) if (species or entries) else [s for s in allsp if cat.is_stored(allsp[s])]
    unknown = [s for s in names if s not in allsp]
    if unknown:
        raise ValueError(f"unknown species {', '.join(unknown)}; known: {', '.join(allsp)}")
    direct = [s for s in names if not cat.is_stored(allsp[s])]
    if direct:
        what = ("a grating flake's kernel depends on each band's wavelength (docs/model.md §3)"
                if "grating" in allsp[direct[0]] else "its optics are tabulated, nothing to project")
        raise ValueError(f"species {', '.join(direct)}: a {allsp[direct[0]]['kind']}"
                         f"{' with a grating' if 'grating' in allsp[direct[0]] else ''} is computed directly by compose "
                         f"({what}); leave it out of the build")
    ns = (int(n),) if isinstance(n, int) else tuple(int(x) for x in n)
    wl = spectral_grid(DEFAULT_RANGE_NM, DEFAULT_STEP_NM) if wavelength_nm is None else wavelength_nm
    if alphas is None and distribution_alphas is None:
        ship = _shipped_orientations(catalog) if catalog_path is None else {}
        alphas, distribution_alphas = {}, {}
        for s in names:
            if allsp[s]["kind"] != "pigment":
                orient = {d: set(a) for d, a in ship.get(s, {}).items()}
                orient.setdefault(cat.catalog_distribution(allsp[s]), set()).add(
                    float(allsp[s]["orientation_alpha"]["value"]))
                for d, a in orient.items():
                    if d == "beckmann":
                        alphas[s] = sorted(a)
                    else:
                        distribution_alphas.setdefault(s, {})[d] = sorted(a)
    alphas, distribution_alphas = alphas or {}, distribution_alphas or {}
    clash = sorted(set(entries) & set(allsp))
    if clash:
        raise ValueError(f"entries {', '.join(clash)}: a catalogue species' name; an entry of a recipe's own films or "
                         f"pigment size is named by flakedb.paint.components.store_key")
    species_entries = {**{s: allsp[s] for s in names}, **entries}
    names = list(species_entries)
    return st.BuildRequest(
        species=species_entries, binder=catalog["binder"], material_checksums=material_checksums(),
        resolutions=tuple(ns), wavelength_nm=tuple(float(w) for w in wl),
        alphas={k: [float(a) for a in v] for k, v in alphas.items() if k in names},
        channel_block=int(channel_block), store_raw=bool(store_raw),
        rank_tol=float(rank_tol) if rank_tol is not None else RANK_TOL,
        eta_top=None if eta_top is None else float(eta_top), recipe=recipe, top=str(top),
        distribution_alphas={k: {d: [float(a) for a in v] for d, v in dv.items()}
                             for k, dv in distribution_alphas.items() if k in names})


def request_for_recipe(recipe, n=None, store_raw=False, catalog_path=None) -> st.BuildRequest:
    """Exactly what ``recipe`` needs (``flakedb build --recipe``): its catalogue species, its node
    count (``n`` or the recipe's own: resolution or auto), its flakes' (distribution, α)'s, its
    wavelengths and its binder index as the top interface's (a rough coat: the nodes of a rough top)."""
    n = resolve_node_count(recipe, n)[0]
    parts = catalog_species(recipe)
    if not parts:
        raise ValueError(f"recipe {recipe.name!r} has no catalogue species: it needs no store")
    names = sorted({p.species for p in parts if store_key(p) == p.species})
    # a species whose optics the recipe changes (films, pigment size) is one more species under its own key
    entries = {store_key(p): particle_entry(p) for p in parts if store_key(p) != p.species}
    orient = recipe_orientations([recipe])
    alphas = {k: v["beckmann"] for k, v in orient.items() if "beckmann" in v}
    other = {k: {d: a for d, a in v.items() if d != "beckmann"} for k, v in orient.items()}
    wl = recipe.wavelength_nm if recipe.wavelength_nm is not None else spectral_grid(DEFAULT_RANGE_NM, DEFAULT_STEP_NM)
    return make_request(species=names, entries=entries, n=int(n), wavelength_nm=wl, alphas=alphas,
                        distribution_alphas={k: v for k, v in other.items() if v},
                        store_raw=store_raw, catalog_path=catalog_path, eta_top=float(recipe.binder_ior),
                        recipe=recipe.name, top=recipe_top(recipe))


def recipe_top(recipe) -> str:
    """"rough" when the recipe's top interface is a rough coat (binder index ≠ 1), else "smooth"."""
    return "rough" if recipe_top_alpha(recipe) > 0 else "smooth"


def _execute(url, plan, tasks, scheduler, workers, client, progress):
    import dask  # lazy: Dask only where a build runs

    # the plan one node of the graph, not traversed: passed as an argument to every task, dask rebuilt its nested
    # inputs (the catalogue's entries) once per task (≈ 160 000 items for the 39 tasks of the default catalogue,
    # 1.2 s of building the graph; 0.01 s so); the tasks only read it
    shared = dask.delayed(plan, traverse=False, pure=False)
    graph = [dask.delayed(st.run_task, pure=False)(url, shared, t, dask_key_name=f"task-{t.id}") for t in tasks]
    bar = BuildProgress(len(tasks)) if progress else None
    try:
        if client is not None or (scheduler and "://" in str(scheduler)):
            return _execute_distributed(graph, scheduler, client, bar)
        kwargs = {"scheduler": scheduler or "threads"}
        if workers:
            kwargs["num_workers"] = int(workers)
        if kwargs["scheduler"] == "processes":
            kwargs["pool"] = process_pool(workers)  # workers end with this process (pipelines/workers.py)
        try:
            with _TaskCallback(bar):
                return dask.compute(*graph, **kwargs)
        finally:
            if "pool" in kwargs:
                kwargs["pool"].shutdown(wait=False, cancel_futures=True)
    finally:
        if bar is not None:
            bar.close()


def _execute_distributed(graph, scheduler, client, bar):
    from distributed import Client, as_completed  # lazy: Dask only where a build runs

    own = client is None
    client = client or Client(scheduler)
    try:
        futures = client.compute(graph)
        for _ in as_completed(futures):
            if bar is not None:
                bar.update(1)
        return client.gather(futures)
    finally:
        if own:
            client.close()


class _TaskCallback:
    """A dask local-scheduler callback counting finished ``task-*`` keys into a :class:`BuildProgress`."""

    def __init__(self, bar):
        from dask.callbacks import Callback  # lazy: Dask only where a build runs

        def posttask(key, result, dsk, state, worker_id):
            name = key if isinstance(key, str) else str(key[0] if isinstance(key, tuple) else key)
            if name.startswith("task-"):
                bar.update(1)

        self._cb = Callback(posttask=posttask) if bar is not None else None

    def __enter__(self):
        if self._cb is not None:
            self._cb.__enter__()
        return self

    def __exit__(self, *exc):
        if self._cb is not None:
            self._cb.__exit__(*exc)
        return False


def _worker_died(exc) -> bool:
    """A lost worker process: a broken local pool, or a dask.distributed KilledWorker.  concurrent.futures.process
    is imported only by a process pool (flakedb.pipelines.workers: 3 ms of every compose otherwise), so a pool that
    broke has it loaded."""
    proc = sys.modules.get("concurrent.futures.process")
    return (proc is not None and isinstance(exc, proc.BrokenProcessPool)) or type(exc).__name__ == "KilledWorker"


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
    n_todo, restarts = len(todo), 0
    while todo:
        try:
            _execute(url, plan, todo, scheduler, workers, client, progress)
            break
        except Exception as exc:  # a killed worker: retry the tasks without a record, then stop clearly
            if not _worker_died(exc):
                raise
            left = st.pending_tasks(url, plan)
            restarts += 1
            if restarts > MAX_POOL_RESTARTS or client is not None or "://" in str(scheduler or ""):
                raise st.StoreError(
                    f"build of version {plan.version[:16]}… stopped: a worker process died ({type(exc).__name__}); "
                    f"{len(plan.tasks) - len(left)} of {len(plan.tasks)} tasks are done and kept (hint: rerun "
                    f"`flakedb build` with the same options to resume; use fewer --workers if memory ran out)") from exc
            if progress:
                print(f"build: a worker process died; restarting the pool for the {len(left)} task(s) left",
                      file=sys.stderr)
            left_ids = {t.id for t in left}
            todo = [t for t in todo if t.id in left_ids]
    if st.pending_tasks(url, plan):
        return {**out, "status": "partial", "tasks_run": n_todo, "seconds": time.perf_counter() - t0}
    st.finalize(url, plan)
    if publish:
        st.publish(url, plan.version)
    return {**out, "status": "built", "tasks_run": n_todo, "seconds": time.perf_counter() - t0}
