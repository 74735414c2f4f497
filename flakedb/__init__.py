"""flakedb: predict a car paint's BSDF from its composition.

Translucent micro-flake radiative transfer (Ergun et al.), solved by adding-doubling in a Fourier
basis (docs/model.md).  Conventions: :mod:`flakedb.conventions`.  The package is layered in tiers
(README, "Layout"): kernels (``optics``, ``rt``, ``colour``, ``reference``), domain and storage
(``paint``, ``store``, ``bsdf``, ``render``), edges (``compose``, ``match``, ``pipelines``, ``cli``).

The main entry points are importable from here:

* :func:`load_recipe` / :func:`parse_recipe` — a recipe (YAML) → :class:`flakedb.paint.recipe.Recipe`;
* :func:`compose_recipe` — a recipe → ``.bsdf``, ``.h5`` and colour report in a directory
  (:func:`flakedb.compose.orchestrate.compose`);
* :func:`solve_stack` — a stack of interfaces, slabs and a primer → its BSDF (the solver);
* :func:`open_bsdf` — read a ``.bsdf`` or ``.h5`` file and evaluate it.

A white furnace: a lossless Henyey–Greenstein slab over a white Lambertian primer returns all light.

>>> import flakedb
>>> from flakedb.rt.scattering.media import PhaseMedium
>>> from flakedb.rt.adding.stack import Lambertian, Slab, Smooth, SolverSettings
>>> slab = Slab(2.0, PhaseMedium(sigma_t_per_um=1.0, albedo=1.0, phase=("hg", 0.6)))
>>> paint = flakedb.solve_stack(Smooth(1.5), [slab], Lambertian(1.0), SolverSettings(n=16))
>>> albedo = paint.albedo()      # (channels, incident nodes), the mirror term included
>>> bool(abs(albedo - 1.0).max() < 1e-9)
True

Composing a recipe into files:

>>> import tempfile
>>> recipe = flakedb.parse_recipe('''
... flakedb: 1
... name: doc-example
... spectral: {mode: mono}
... resolution: 16
... layers:
...   - basecoat:
...       thickness_um: 10
...       ior: 1.0
...       particles:
...         - custom: {kind: medium, name: grey, albedo: 0.5, phase: isotropic}
...           optical_depth: 1.0
...   - primer: {color: white}
... ''')
>>> out = flakedb.compose_recipe(recipe, tempfile.mkdtemp())
>>> sorted(out.paths)
['bsdf', 'h5', 'json']
>>> bsdf = flakedb.open_bsdf(out.paths["bsdf"])
>>> bool(0.0 < bsdf.albedo(0.8)[0] < 1.0)
True
"""

import importlib

__version__ = "0.1.0"

#: name → (module, attribute) of the entry points (``compose_recipe``, not ``compose``: that name is the
#: ``flakedb.compose`` subpackage); imported on first use (PEP 562), so that importing a kernel
#: (``flakedb.rt.basis.quadrature``) does not import the whole package.
_ENTRY_POINTS = {
    "load_recipe": ("flakedb.paint.recipe", "load_recipe"),
    "parse_recipe": ("flakedb.paint.recipe", "parse_recipe"),
    "compose_recipe": ("flakedb.compose.orchestrate", "compose"),
    "solve_stack": ("flakedb.rt.adding.stack", "solve_stack"),
    "open_bsdf": ("flakedb.bsdf", "open_bsdf"),
}

__all__ = ["__version__", *_ENTRY_POINTS]


def __getattr__(name):
    if name in _ENTRY_POINTS:
        module, attr = _ENTRY_POINTS[name]
        return getattr(importlib.import_module(module), attr)
    raise AttributeError(f"module 'flakedb' has no attribute {name!r}")
