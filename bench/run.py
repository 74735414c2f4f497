"""`make bench`: run every benchmark in bench/bench_*.py and write bench/results.json.

A benchmark module defines ``BENCHMARKS``: a list of ``(name, setup, run, meta)`` where ``setup()``
returns the argument passed to ``run(arg)`` (untimed), ``run`` is timed (best of ``repeat``), and
``meta`` is a dict of what is being measured (sizes, units, the paper's number for comparison).
Timings live here and never in pass/fail tests.
"""

import argparse
import importlib.util
import json
import os
import platform
import sys
import time
from pathlib import Path


def _versions():
    out = {"python": sys.version.split()[0]}
    for mod in ("numpy", "scipy", "numba", "dask", "zarr", "colour", "h5py"):
        try:
            out[mod] = __import__(mod).__version__
        except Exception:  # a missing optional package is recorded, not fatal
            out[mod] = None
    from flakedb import __version__

    out["flakedb"] = __version__
    return out


def _machine():
    info = {"platform": platform.platform(), "processor": platform.processor(), "cpu_count": os.cpu_count()}
    try:
        with open("/proc/cpuinfo") as fh:
            for line in fh:
                if line.startswith("model name"):
                    info["cpu_model"] = line.split(":", 1)[1].strip()
                    break
    except OSError:
        pass
    return info


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--out", default="bench/results.json")
    ap.add_argument("--only", default=None, help="substring filter on benchmark names")
    ap.add_argument("--skip", default=None, help="substring filter: skip benchmarks whose name has it")
    ap.add_argument("--merge", default=None, help="a results.json whose benchmarks are kept (merged in)")
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--long", type=float, default=20.0, help="seconds above which a benchmark is timed once")
    args = ap.parse_args()
    here = Path(__file__).parent
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    results = []
    if args.merge:
        results.extend(json.loads(Path(args.merge).read_text())["benchmarks"])

    def write():  # after every benchmark, so an interrupted run keeps what it measured
        from flakedb.atomic import atomic_write_text

        latest = {r["name"]: r for r in results}  # a benchmark measured in this run replaces a merged one
        kept = [latest[r["name"]] for i, r in enumerate(results) if r["name"] not in
                {q["name"] for q in results[:i]}]
        doc = {"created": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()), "machine": _machine(),
               "versions": _versions(), "benchmarks": kept}
        atomic_write_text(out, json.dumps(doc, indent=2))

    for path in sorted(here.glob("bench_*.py")):
        spec = importlib.util.spec_from_file_location(path.stem, path)
        mod = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(mod)
        for name, reason in getattr(mod, "SKIPPED", ()):  # rows a module cannot run here (a missing tool)
            if (args.only and args.only not in name) or (args.skip and args.skip in name):
                continue
            results.append({"name": name, "module": path.name, "skipped": reason})
            print(f"{name:60s} skipped: {reason}", flush=True)
        for name, setup, run, meta in mod.BENCHMARKS:
            if (args.only and args.only not in name) or (args.skip and args.skip in name):
                continue
            try:
                arg = setup()
                # The first run is a warm-up (JIT compilation, caches).  A benchmark whose first run
                # takes longer than --long seconds is not run again: that run is its measurement
                # (compilation is a negligible part of it), so `make bench` stays affordable on 2 cores.
                t0 = time.perf_counter()
                extra = run(arg)
                first = time.perf_counter() - t0
                times = [first] if first > args.long else []
                for _ in range(0 if times else args.repeat):
                    t0 = time.perf_counter()
                    extra = run(arg)
                    times.append(time.perf_counter() - t0)
            except Exception as e:  # a broken benchmark is recorded, the others still run
                results.append({"name": name, "module": path.name, "error": f"{type(e).__name__}: {e}"})
                print(f"{name:60s} FAILED: {type(e).__name__}: {e}", flush=True)
                write()
                continue
            row = {"name": name, "module": path.name, "best_s": min(times), "times_s": times, **meta}
            if isinstance(extra, dict):
                row.update(extra)
            results.append(row)
            print(f"{name:60s} {min(times):10.4f} s", flush=True)
            write()
    write()
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
