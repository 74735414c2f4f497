"""`flakedb texture` per catalogue recipe (issue 22: ≤ 1 s each): the report of every observer preset
(recipe → flake statistics and optics → indices), the recipe already parsed; one row for the whole
catalogue (the slowest recipe is recorded)."""

import time
from pathlib import Path

from flakedb.paint.recipe import load_recipe
from flakedb.paint.texture_inputs import texture_report
from flakedb.resources import PACKAGE_DIR
from flakedb.texture.instruments import PRESETS


def _setup():
    paths = sorted((Path(PACKAGE_DIR) / "catalog" / "recipes").glob("*.yaml"))
    return [load_recipe(p) for p in paths]


def _run(recipes):
    per, cpu = {}, {}
    for r in recipes:
        t0, c0 = time.perf_counter(), time.process_time()
        texture_report(r, list(PRESETS.values()))
        per[r.name], cpu[r.name] = time.perf_counter() - t0, time.process_time() - c0
    worst = max(per, key=per.get)
    worst_cpu = max(cpu, key=cpu.get)
    return {"recipes": len(per), "slowest_recipe": worst, "slowest_s": per[worst],
            "mean_s": sum(per.values()) / len(per), "slowest_cpu_recipe": worst_cpu,
            "slowest_cpu_s": cpu[worst_cpu], "mean_cpu_s": sum(cpu.values()) / len(cpu)}


BENCHMARKS = [
    ("texture: every catalogue recipe, 3 observer presets", _setup, _run,
     {"what": "flakedb.paint.texture_inputs.texture_report per recipe (target <= 1 s each)"}),
]
