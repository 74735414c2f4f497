"""The discretisation's second solve beside the solve at n (flakedb.solve.pipeline.solve_reported, issue 34 item 8,
docs/compose-overhead.md), for a paint under a rough coat: it runs on one thread, its rough top built in its own
thread, and gives the estimate that the second solve made first on every core gives, bit for bit.

Guards against: the second solve's rough top taking the solver's background thread ahead of the solve at n (the
solve at n then waited for both tops, one after the other), and a thread count that changes the estimate."""

import os
import textwrap

from flakedb.paint.recipe import parse_recipe
from flakedb.process import available_threads
from flakedb.solve import pipeline, resolution

RECIPE = textwrap.dedent("""\
    flakedb: 1
    name: rough-beside
    spectral: {mode: rgb}
    resolution: 32
    layers:
      - clearcoat: {thickness_um: 40, ior: 1.5, roughness: 0.2}
      - basecoat:
          thickness_um: 10
          ior: 1.5
          particles:
            - custom: {kind: medium, name: hg, albedo: 0.9, phase: {hg: 0.6}}
              optical_depth: 1.5
      - primer: {albedo: 0.5}
    """)


def test_the_second_solve_beside_runs_on_one_thread_and_gives_the_estimate_made_first(monkeypatch):
    solve_paint, seen = pipeline.solve_paint, []

    def recording(paint, n, **kw):
        seen.append((n, kw.get("threads")))
        return solve_paint(paint, n, **kw)

    monkeypatch.setattr(pipeline, "solve_paint", recording)
    rec = parse_recipe(RECIPE)
    beside = pipeline.solve_reported(rec)
    n2 = resolution.second_solve_n(32)
    assert (n2, 1) in seen and (32, 1) not in seen
    seen.clear()
    monkeypatch.setattr(pipeline, "CONCURRENT_SECOND_BYTES", 0.0)  # the large paints' path: first, every core
    first = pipeline.solve_reported(rec)
    assert [t for _, t in seen] == [available_threads()] * 2  # both on every core flakedb may use
    assert beside.report["discretisation"] == first.report["discretisation"]
    assert beside.report["discretisation"]["n_second"] == n2
    assert beside.solved.stack.Rt.tobytes() == first.solved.stack.Rt.tobytes()


def test_a_thread_cap_reaches_every_solve_and_changes_no_bit(monkeypatch):
    """OMP_NUM_THREADS (or FLAKEDB_THREADS) caps the solver's threads: capped at 1, both solves get 1 thread; on two
    CPUs uncapped, 2; the R^t and the discretisation estimate are the same bit for bit (each Fourier order and each
    part of the rough top computed by the same code whichever thread runs it)."""
    solve_paint, seen = pipeline.solve_paint, []

    def recording(paint, n, **kw):
        seen.append(kw.get("threads"))
        return solve_paint(paint, n, **kw)

    monkeypatch.setattr(pipeline, "solve_paint", recording)
    monkeypatch.setattr(pipeline, "CONCURRENT_SECOND_BYTES", 0.0)  # both solves on the threads the cap allows
    monkeypatch.setattr(os, "sched_getaffinity", lambda pid: {0, 1}, raising=False)
    monkeypatch.delenv("FLAKEDB_THREADS", raising=False)
    rec = parse_recipe(RECIPE)
    monkeypatch.setenv("OMP_NUM_THREADS", "1")
    one = pipeline.solve_reported(rec)
    assert seen == [1, 1]
    seen.clear()
    monkeypatch.delenv("OMP_NUM_THREADS")
    two = pipeline.solve_reported(rec)
    assert seen == [2, 2]
    assert one.solved.stack.Rt.tobytes() == two.solved.stack.Rt.tobytes()
    assert one.report["discretisation"] == two.report["discretisation"]
