"""Preview renderer timings (see bench/run.py for the BENCHMARKS protocol).

`flakedb render`'s scene: a 256 x 256 sphere under the studio environment with the sun.

- ``preview.render_256.*``: the Monte Carlo renderer (``--method montecarlo``) at the default samples per
  pixel (flakedb.render.preview.DEFAULT_SPP), all available threads.  Target (issue #7): a smooth-coated
  paint in under 30 s on 2 cores.
- ``preview.quadrature_256.*``: the deterministic default (flakedb.render.quadrature, no samples, one
  thread).  Target (issue #37): 256 px in <= 2 s; identical between seeds (tests/render/test_quadrature.py).

- ``preview.render_256.smooth_coat``: a smooth-coated paint composed here by flakedb's solver (coat
  eta = 1.5, 10 µm of an HG g = 0.5 red medium, tau = 3, over a white Lambertian primer; n = 64
  nodes), written as a ``.bsdf`` with its delta term (first-surface Fresnel, added exactly).
- ``preview.render_256.carpaint_rgb_n100``: layerlab's ``carpaint_rgb_n100.bsdf`` (rough coat, up to 266
  Fourier orders, no delta), the expensive case for the file's sampling kernel.
"""

import os
import tempfile

from flakedb.bsdf import open_bsdf, write_bsdf
from flakedb.bsdf.convert import stack_to_table
from flakedb.render import look, preview, quadrature

SIZE = 256
CARPAINT = os.path.join(os.path.dirname(__file__), "..", "..", "shared", "data", "bsdf-files", "carpaint_rgb_n100.bsdf")
if not os.path.exists(CARPAINT):
    CARPAINT = "/work/shared/data/bsdf-files/carpaint_rgb_n100.bsdf"


def _setup_smooth():
    from flakedb.rt.scattering.media import PhaseMedium
    from flakedb.rt.adding.stack import Lambertian, Slab, Smooth, SolverSettings, solve_stack

    med = PhaseMedium(sigma_t_per_um=[0.3, 0.3, 0.3], albedo=[0.95, 0.45, 0.15], phase=("hg", 0.5))
    s = solve_stack(Smooth(1.5), [Slab(10.0, med)], Lambertian([0.8, 0.8, 0.8]), SolverSettings(n=64))
    with tempfile.TemporaryDirectory(prefix="flakedb-bench-preview-") as tmp:   # read into memory
        path = os.path.join(tmp, "smooth_red.bsdf")
        write_bsdf(path, stack_to_table(s, metadata={"recipe": "bench smooth red"}))
        return open_bsdf(path)


def _setup_carpaint():
    return open_bsdf(CARPAINT)


def _run(b):
    r = preview.render_sphere(b, preview.studio_environment(), preview.studio_sun(), size=SIZE,
                              spp=preview.DEFAULT_SPP)
    inside = r.coverage >= 1
    return {"threads": r.settings["threads"], "sphere_mean_rgb": [float(x) for x in r.image[inside].mean(axis=0)],
            "samples": int(inside.sum()) * preview.DEFAULT_SPP}


def _run_quadrature(b):
    r = quadrature.render_sphere_quadrature(b, preview.studio_environment(), preview.studio_sun(), size=SIZE)
    inside = r.coverage >= 1
    return {"sphere_mean_rgb": [float(x) for x in r.image[inside].mean(axis=0)], "pixels": int(inside.sum())}


def _run_quadrature_softbox(b):
    r = quadrature.render_sphere_quadrature(b, look.softbox_studio(), None, size=SIZE)
    inside = r.coverage >= 1
    return {"sphere_mean_rgb": [float(x) for x in r.image[inside].mean(axis=0)], "pixels": int(inside.sum())}


_QMETA = {"size": SIZE, "method": "quadrature", "light_grid": [quadrature.N_THETA, quadrature.N_PHI],
          "normal_grid": quadrature.N_NORMAL, "pixel_ss": quadrature.PIXEL_SS, "target_s": 2.0, "target_cores": 2}

_META = {"size": SIZE, "spp": preview.DEFAULT_SPP, "env": "studio", "sun": True, "target_s": 30.0,
         "target_cores": 2}

BENCHMARKS = [
    ("preview.render_256.smooth_coat", _setup_smooth, _run,
     {**_META, "file": "solver: smooth coat eta 1.5 over red HG slab, n=64"}),
    ("preview.render_256.carpaint_rgb_n100", _setup_carpaint, _run, {**_META, "file": "carpaint_rgb_n100.bsdf"}),
    ("preview.quadrature_256.smooth_coat", _setup_smooth, _run_quadrature,
     {**_QMETA, "env": "studio", "sun": True, "file": "solver: smooth coat eta 1.5 over red HG slab, n=64"}),
    ("preview.quadrature_256.smooth_coat_softbox", _setup_smooth, _run_quadrature_softbox,
     {**_QMETA, "env": "softbox", "sun": False, "file": "solver: smooth coat eta 1.5 over red HG slab, n=64"}),
    ("preview.quadrature_256.carpaint_rgb_n100", _setup_carpaint, _run_quadrature,
     {**_QMETA, "env": "studio", "sun": True, "file": "carpaint_rgb_n100.bsdf"}),
]
