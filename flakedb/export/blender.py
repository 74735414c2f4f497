"""The fitted material as a Blender Principled BSDF (Blender 4.x / 5.x input names), and a Cycles
render of a sphere under a sun that the tests compare with flakedb's own preview.

* :func:`material_script` -- a Python script that builds the material in the open Blender file
  (``blender --python NAME.blender.py`` or the Text Editor's Run Script): ``Base Color``,
  ``Metallic``, ``Roughness`` (perceptual, α = r²), ``IOR`` = the fit's index relative to the
  coat (Cycles evaluates the base's lobe in air, under an unrefracting coat, so this is the model's
  lobe Fresnel F(cos θ_d; n_s) itself; OpenPBR's ``specular_ior`` = relative x coat index is no
  closer to the exact paints: 5.0 / 10.8 ΔE00 against 5.2 / 9.6 for cadmium yellow / pearlescent,
  :func:`principled_sun_image` against the preview, docs/renderers.md), ``Specular Tint`` =
  ``specular_color`` (Blender tints F0 only, the fit tints the whole Fresnel curve), ``Specular IOR
  Level`` 0.5 (the index as is; 0 when the fit has no base lobe), ``Coat Weight`` 1,
  ``Coat Roughness``, ``Coat IOR`` (untinted coat), ``Thin Film Thickness`` [nm] / ``Thin Film IOR`` of the
  equivalent film in air (:meth:`flakedb.export.openpbr.OpenPBRFit.film_relative_to_air`: Cycles
  puts the film in air; on a 300 nm film of index 2.3 Cycles is ≤ 3.3 ΔE00 from the model at the
  test's 7 pixels this way, 11.1 with the film's own values).  The fit is kept in the material's
  custom property ``flakedb_fit`` (JSON).
* :func:`render_cycles_sphere` -- runs Blender's ``bpy`` (the optional extra ``flakedb[blender]``)
  in a **separate process** (``bpy`` is a 375 MB wheel that replaces the interpreter's state; it
  also pins numpy < 2 in its metadata, and flakedb's own numpy is not touched): the unit sphere, an
  orthographic camera along −z covering ``[-extent, extent]²`` (the frame of
  :mod:`flakedb.render.preview`), a black world and a sun of the given irradiance and angular
  radius, Cycles on the CPU, no denoising, a pixel filter 0.01 px wide (Cycles' narrowest: every
  sample at its pixel's centre, like the preview with ``jitter=False`` and the images below), the
  Standard view transform (linear Rec.709 = linear sRGB pixels).  A sun of strength E [W/m²] gives a white Lambertian plane facing it the radiance E/π,
  the convention of :class:`flakedb.render.preview.Sun` (checked by the test against a diffuse
  sphere).  ``python`` names the interpreter that has bpy: bpy pins numpy < 2 and is built for
  CPython 3.11 only, so it is best kept in an environment of its own (``make blender-venv`` makes
  ``.venv-blender`` for the tests); the render script imports nothing but bpy, ``mathutils`` and the
  standard library, so that environment needs neither flakedb nor its dependencies.
* :func:`principled_sun_image` -- what Cycles 5.0's Principled BSDF renders for those inputs, in
  numpy (its layering, Fresnel and masking as the Cycles kernel evaluates them), beside
  :func:`model_sun_image` (the fitted model itself): the difference between the two is what the
  Blender route costs on top of the fit, and the test checks Cycles against the first to within
  its Monte Carlo noise.
"""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

from flakedb.atomic import atomic_path
from flakedb.export.materialx import safe_name
from flakedb.export.openpbr import OpenPBRFit, evaluate, film_fresnel_rgb
from flakedb.optics.fresnel import fresnel_dielectric


def principled_inputs(fit: OpenPBRFit) -> dict:
    """Principled BSDF input name -> value (module docstring).

    An uncoated fit turns Cycles' coat off, and the film moved into air keeps its optical thickness:

    >>> coated = OpenPBRFit((0.8, 0.5, 0.2), 1.0, 0.3, 1.5, 0.1, thin_film_thickness_nm=300.0, thin_film_ior=2.0)
    >>> bare = OpenPBRFit((0.8, 0.5, 0.2), 1.0, 0.3, 1.0, 0.1)
    >>> p = principled_inputs(coated)
    >>> p["Coat Weight"], principled_inputs(bare)["Coat Weight"], round(p["Thin Film Thickness"] * p["Thin Film IOR"], 9)
    (1.0, 0.0, 600.000000000)
    """
    c = tuple(float(x) for x in fit.base_color)
    return {
        "Base Color": c + (1.0,),
        "Metallic": float(fit.base_metalness),
        "Roughness": float(fit.specular_roughness),
        "IOR": float(fit.specular_ior_relative) if fit.specular_ior_relative > 1.0 else 1.5,
        "Specular IOR Level": 0.5 if fit.specular_ior_relative > 1.0 else 0.0,     # 0.5: F0 of the IOR as is
        "Specular Tint": tuple(float(x) for x in fit.specular_color) + (1.0,),
        "Coat Weight": 1.0 if fit.coat_ior > 1.0 else 0.0,
        "Coat Roughness": float(fit.coat_roughness),
        "Coat IOR": float(fit.coat_ior) if fit.coat_ior > 1.0 else 1.5,
        "Coat Tint": (1.0, 1.0, 1.0, 1.0),
        "Thin Film Thickness": float(fit.film_relative_to_air()[0]),       # nm; 0 = none
        "Thin Film IOR": float(max(fit.film_relative_to_air()[1], 1.0)),
    }


_BUILD = '''
def build_material(bpy, name, inputs, fit_json):
    """Create (or replace) material `name`: a Principled BSDF with `inputs`."""
    old = bpy.data.materials.get(name)
    if old is not None:
        bpy.data.materials.remove(old)
    m = bpy.data.materials.new(name)
    m.use_nodes = True
    p = m.node_tree.nodes["Principled BSDF"]
    p.distribution = "GGX"          # single-scattering GGX, as fitted (Blender's default adds multiple scattering)
    for k, v in inputs.items():
        p.inputs[k].default_value = v
    m["flakedb_fit"] = fit_json
    return m
'''


def material_script(fit: OpenPBRFit, name: str) -> str:
    """A standalone Blender script building the fitted material (module docstring)."""
    n = safe_name(name)
    return (f'"""flakedb export-openpbr: the fitted Principled BSDF of {name} (run inside Blender)."""\n'
            f"import bpy\n{_BUILD}\n"
            f"INPUTS = {principled_inputs(fit)!r}\n"
            f"FIT = {json.dumps(json.dumps(fit.to_dict()))}\n"
            f"material = build_material(bpy, {('flakedb_' + n)!r}, INPUTS, FIT)\n"
            f"for ob in bpy.context.selected_objects:          # assign to the selection, if any\n"
            f"    if ob.type == 'MESH':\n"
            f"        ob.data.materials.clear()\n"
            f"        ob.data.materials.append(material)\n")


def write_material_script(path, fit: OpenPBRFit, name: str) -> Path:
    path = Path(path)
    with atomic_path(path, suffix="") as tmp:
        Path(tmp).write_text(material_script(fit, name), encoding="utf-8")
    return path


#: The render script's parts (run by :func:`run_bpy_script` in the bpy interpreter; they import only
#: bpy, mathutils and the standard library): ``SCENE_SETUP_SCRIPT`` (Cycles settings, the world), an object
#: part, ``CAMERA_SUN_RENDER_SCRIPT`` (camera, sun, render, pixels out).  ``INFO`` is a dict the object part
#: may fill; it comes back as the result's ``info``.
SCENE_SETUP_SCRIPT = '''
import json, math, sys
import bpy
from mathutils import Vector

a = json.loads(open(sys.argv[-1]).read())
INFO = {}
bpy.ops.wm.read_factory_settings(use_empty=True)
sc = bpy.context.scene
sc.render.engine = "CYCLES"
sc.cycles.device = "CPU"
sc.cycles.samples = a["samples"]
sc.cycles.use_denoising = False
sc.cycles.use_adaptive_sampling = a["adaptive_sampling"]     # Blender's default: on (noise threshold 0.01)
sc.cycles.seed = a["seed"]
sc.cycles.max_bounces = 4
sc.cycles.filter_width = a["filter_width"]
sc.render.resolution_x = sc.render.resolution_y = a["size"]
sc.render.resolution_percentage = 100
sc.render.threads_mode = "FIXED"
sc.render.threads = a["threads"]
sc.view_settings.view_transform = "Standard"
sc.view_settings.look = "None"
sc.view_settings.exposure = 0.0
sc.view_settings.gamma = 1.0
sc.render.film_transparent = False
w = bpy.data.worlds.new("world"); sc.world = w; w.use_nodes = True
w.node_tree.nodes["Background"].inputs[0].default_value = (1.0, 1.0, 1.0, 1.0)
w.node_tree.nodes["Background"].inputs[1].default_value = a.get("world_radiance", 0.0)
'''

_PRINCIPLED_SPHERE_SCRIPT = '''
bpy.ops.mesh.primitive_uv_sphere_add(segments=128, ring_count=64, radius=1.0)
ob = bpy.context.object
bpy.ops.object.shade_smooth()
ob.data.materials.append(build_material(bpy, "flakedb_fit", {k: (tuple(v) if isinstance(v, list) else v)
                                                             for k, v in a["inputs"].items()}, "{}"))
'''

CAMERA_SUN_RENDER_SCRIPT = '''
cam = bpy.data.cameras.new("cam"); cam.type = "ORTHO"; cam.ortho_scale = 2.0 * a["extent"]
co = bpy.data.objects.new("cam", cam); sc.collection.objects.link(co); co.location = (0.0, 0.0, 4.0); sc.camera = co
if a["irradiance"] > 0.0:
    ld = bpy.data.lights.new("sun", "SUN"); ld.energy = a["irradiance"]; ld.angle = 2.0 * math.radians(a["half_angle_deg"])
    lo = bpy.data.objects.new("sun", ld); sc.collection.objects.link(lo)
    lo.rotation_euler = Vector(a["direction"]).to_track_quat("Z", "Y").to_euler()
sc.render.image_settings.file_format = "OPEN_EXR"
sc.render.image_settings.color_depth = "32"
sc.render.filepath = a["exr"]
bpy.ops.render.render(write_still=True)
img = bpy.data.images.load(a["exr"])
n = a["size"]
px = list(img.pixels)
rows = [[px[(r * n + c) * 4:(r * n + c) * 4 + 3] for c in range(n)] for r in range(n)]
open(a["out"], "w").write(json.dumps({"pixels": rows[::-1], "blender": bpy.app.version_string,  # row 0 at the top
                                      "info": INFO}))
'''

_RENDER = _BUILD + SCENE_SETUP_SCRIPT + _PRINCIPLED_SPHERE_SCRIPT + CAMERA_SUN_RENDER_SCRIPT


def bpy_available(python: str | None = None) -> tuple[bool, str]:
    """(whether ``python`` (default: this interpreter) can import bpy, the reason if not)."""
    python = _interpreter(python)
    try:
        r = subprocess.run([python, "-c", "import bpy; print(bpy.app.version_string)"], check=False,
                           capture_output=True, text=True, timeout=300)
    except (OSError, subprocess.TimeoutExpired) as e:
        return False, f"cannot run {python}: {e}"
    if r.returncode != 0:
        last = (r.stderr.strip().splitlines() or ["?"])[-1]
        return False, (f"bpy is not importable by {python} ({last}); install it into a Python 3.11 environment "
                       f"of its own (pip install bpy; it pins numpy < 2) and pass that interpreter")
    return True, r.stdout.strip().splitlines()[-1]


def _interpreter(python: str | None) -> str:
    """``python`` as a path the render subprocess (run in a temporary folder) can start: a relative
    path is made absolute, a bare name is left to the PATH."""
    if not python:
        return sys.executable
    return os.path.abspath(python) if os.sep in python else python


def render_args(*, size: int, samples: int, direction, irradiance: float, half_angle_deg: float, extent: float,
                threads: int, seed: int, filter_width_px: float, world_radiance: float = 0.0,
                adaptive_sampling: bool = True) -> dict:
    """The arguments of the render script's scene, camera and sun (:data:`SCENE_SETUP_SCRIPT`,
    :data:`CAMERA_SUN_RENDER_SCRIPT`; module docstring): ``direction`` normalised, a uniform world of
    radiance ``world_radiance`` (0: black; 1 is a white furnace), no sun when ``irradiance`` is 0;
    ``adaptive_sampling`` is Blender's default (on: Cycles stops sampling a pixel once its noise
    estimate is below 0.01, so ``samples`` is a maximum); off, every pixel gets ``samples``."""
    d = np.asarray(direction, float)
    d = d / np.linalg.norm(d)
    return {"size": int(size), "samples": int(samples), "seed": int(seed), "threads": int(threads),
            "filter_width": float(filter_width_px), "extent": float(extent), "irradiance": float(irradiance),
            "half_angle_deg": float(half_angle_deg), "direction": d.tolist(), "world_radiance": float(world_radiance),
            "adaptive_sampling": bool(adaptive_sampling)}


def run_bpy_script(script: str, args: dict, *, python: str | None = None, timeout: float = 600.0,
                   files: dict | None = None) -> dict:
    """Run a render ``script`` (ending with :data:`CAMERA_SUN_RENDER_SCRIPT`) in a subprocess of ``python``
    (default: this interpreter) with ``args`` (JSON; ``exr`` and ``out`` are added: paths in a temporary
    folder), ``files`` {name: text} written beside it first (their paths are added to ``args`` under
    their names).  Returns {"image": (size, size, 3) float64 linear sRGB, row 0 at the top, "blender":
    version, "info": what the script put in ``INFO``}.  Raises RuntimeError with Blender's last lines
    on failure."""
    with tempfile.TemporaryDirectory(prefix="flakedb-cycles-") as tmp:
        t = Path(tmp)
        args = dict(args, exr=str(t / "render.exr"), out=str(t / "pixels.json"))
        for name, text in (files or {}).items():
            (t / name).write_text(text, encoding="utf-8")
            args[name] = str(t / name)
        (t / "args.json").write_text(json.dumps(args))
        (t / "render.py").write_text(script)
        env = dict(os.environ, PYTHONNOUSERSITE="1")
        r = subprocess.run([_interpreter(python), str(t / "render.py"), str(t / "args.json")],
                           check=False, capture_output=True, text=True, timeout=timeout, cwd=tmp, env=env)
        if r.returncode != 0 or not (t / "pixels.json").exists():
            tail = "\n".join((r.stdout + r.stderr).strip().splitlines()[-8:])
            raise RuntimeError(f"the Cycles render failed (exit {r.returncode}):\n{tail}")
        out = json.loads((t / "pixels.json").read_text())
    return {"image": np.asarray(out["pixels"], dtype=np.float64), "blender": out["blender"], "info": out["info"]}


def render_cycles_sphere(fit: OpenPBRFit, *, size: int = 32, samples: int = 16, direction=(0.0, 0.0, 1.0),
                         irradiance: float = 1.0, half_angle_deg: float = 2.0, extent: float = 1.05,
                         threads: int = 1, seed: int = 1, filter_width_px: float = 0.01, python: str | None = None,
                         timeout: float = 600.0) -> dict:
    """Render the fitted material on the unit sphere in Cycles (module docstring) in a subprocess of
    ``python`` (default: this interpreter), ``samples`` per pixel with Cycles' sampling ``seed``.
    Returns {"image": (size, size, 3) float64 linear sRGB, row 0 at the top, "blender": version}.
    Raises RuntimeError with Blender's last lines on failure."""
    args = render_args(size=size, samples=samples, direction=direction, irradiance=irradiance,
                       half_angle_deg=half_angle_deg, extent=extent, threads=threads, seed=seed,
                       filter_width_px=filter_width_px)
    args["inputs"] = {k: list(v) if isinstance(v, tuple) else v for k, v in principled_inputs(fit).items()}
    out = run_bpy_script(_RENDER, args, python=python, timeout=timeout)
    return {"image": out["image"], "blender": out["blender"]}


def sphere_normals(size: int, extent: float):
    """Normals (size, size, 3) of the unit sphere at the pixel centres of the orthographic frame of
    :func:`render_cycles_sphere` (row 0 at the top, camera along -z), and the mask of pixels on it."""
    x = -extent + (np.arange(size) + 0.5) * 2 * extent / size
    X, Y = np.meshgrid(x, x[::-1])
    r2 = X * X + Y * Y
    return np.stack([X, Y, np.sqrt(np.clip(1 - r2, 0, 1))], axis=-1), r2 < 1


def model_sun_image(fit: OpenPBRFit, size: int = 32, direction=(0.0, 0.0, 1.0), irradiance: float = 1.0,
                    extent: float = 1.05) -> np.ndarray:
    """(size, size, 3) image of the fitted **model** (:func:`flakedb.export.openpbr.evaluate`) on the
    unit sphere under a point sun of ``irradiance`` along ``direction``, at pixel centres, in the frame
    of :func:`render_cycles_sphere` (row 0 at the top): ``L = f(ω_v, ω_sun) cos θ_sun E`` where the
    sun is above the local horizon, 0 elsewhere (the coat's delta does not reach a pixel centre)."""
    d = np.asarray(direction, float)
    d = d / np.linalg.norm(d)
    N, on = sphere_normals(size, extent)
    mu_v, mu_s = N[..., 2], N @ d
    tv = np.array([0.0, 0.0, 1.0]) - N * mu_v[..., None]             # tangent parts of view and sun
    ts = d - N * mu_s[..., None]
    den = np.linalg.norm(tv, axis=-1) * np.linalg.norm(ts, axis=-1)
    cos_dphi = np.where(den > 0, np.sum(tv * ts, axis=-1) / np.where(den > 0, den, 1.0), 1.0)
    phi_d = np.pi - np.arccos(np.clip(cos_dphi, -1.0, 1.0))           # file convention: 0 = mirror side
    ok = on & (mu_s > 0) & (mu_v > 0)
    img = np.zeros((size, size, 3))
    img[ok] = evaluate(fit, mu_v[ok], -mu_s[ok], phi_d[ok]) * (mu_s[ok] * irradiance)[:, None]
    return img


# --------------------------------------------------------------------------------------------
# What Cycles renders for principled_inputs (Cycles 5.0, GGX single scattering)
# --------------------------------------------------------------------------------------------
#: Cosines at which the lobe averages of :func:`ggx_lobe_averages` are tabulated (denser towards grazing)
_MU_TABLE = np.linspace(0.0, 1.0, 33) ** 0.5
_MU_TABLE[0] = 1e-3
_MU_TABLE.flags.writeable = False


def _F0(n):
    """Normal-incidence reflectance ``((n - 1) / (n + 1))²`` of a dielectric of relative index n."""
    return ((n - 1.0) / (n + 1.0)) ** 2


def smith_lambda(a2, mu):
    """GGX's Smith Λ(μ) = (sqrt(1 + α² tan²θ) - 1) / 2 (Heitz 2014, eq. 72), ``a2`` = α²."""
    mu = np.clip(mu, 1e-12, 1.0)
    return 0.5 * (np.sqrt(1.0 + a2 * (1.0 / (mu * mu) - 1.0)) - 1.0)


def ggx_lobe_height_correlated(mu_v, mu_l, cos_h, alpha):
    """``D G2 / (4 μ_v μ_l)`` [1/sr] of GGX with the height-correlated Smith masking-shadowing
    ``G2 = 1 / (1 + Λ(μ_v) + Λ(μ_l))`` (Heitz 2014, eq. 99: Cycles' ``bsdf_G``; the fitted model uses
    the separable ``G1 G1``), D the GGX distribution of :func:`flakedb.export.openpbr.ggx_lobe`;
    ``cos_h`` = cos θ_h of the half vector, ``alpha`` = roughness²."""
    a2 = max(float(alpha), 1e-3) ** 2
    ch = np.clip(cos_h, 1e-12, 1.0)
    D = a2 / (np.pi * (ch * ch * (a2 - 1.0) + 1.0) ** 2)
    G2 = 1.0 / (1.0 + smith_lambda(a2, mu_v) + smith_lambda(a2, mu_l))
    return D * G2 / (4.0 * np.clip(mu_v, 1e-12, 1.0) * np.clip(mu_l, 1e-12, 1.0))


def beckmann_lambda(a2, mu):
    """Beckmann's Smith Λ(μ) in Walter et al. 2007's rational approximation (eq. 27; Heitz 2014, below
    eq. 69), as Cycles evaluates it (``bsdf_lambda_from_sqr_alpha_tan_n``): with a = 1 / (α tan θ),
    Λ = (1 - 1.259 a + 0.396 a²) / (3.535 a + 2.181 a²) for a < 1.6 (α² tan²θ ≥ 0.39), else 0; ``a2`` = α²."""
    mu = np.clip(mu, 1e-12, 1.0)
    s = a2 * np.maximum(1.0 / (mu * mu) - 1.0, 0.0)                    # α² tan²θ
    a = 1.0 / np.sqrt(np.maximum(s, 1e-30))
    lam = ((0.396 * a - 1.259) * a + 1.0) / ((2.181 * a + 3.535) * a)
    return np.where(s < 0.39, 0.0, lam)


def beckmann_lobe_height_correlated(mu_v, mu_l, cos_h, alpha):
    """``D G2 / (4 μ_v μ_l)`` [1/sr] of Beckmann's distribution ``D = exp(-tan²θ_h / α²) / (π α² cos⁴θ_h)``
    with the height-correlated Smith ``G2 = 1 / (1 + Λ(μ_v) + Λ(μ_l))`` of :func:`beckmann_lambda`:
    Cycles' Glossy BSDF with distribution Beckmann (``bsdf_D``, ``bsdf_G`` of
    ``intern/cycles/kernel/closure/bsdf_microfacet.h``; no Fresnel, no energy compensation),
    ``alpha`` = roughness²."""
    a2 = max(float(alpha), 1e-3) ** 2
    c2 = np.clip(cos_h, 1e-12, 1.0) ** 2
    D = np.exp(-(1.0 - c2) / (c2 * a2)) / (np.pi * a2 * c2 * c2)
    G2 = 1.0 / (1.0 + beckmann_lambda(a2, mu_v) + beckmann_lambda(a2, mu_l))
    return D * G2 / (4.0 * np.clip(mu_v, 1e-12, 1.0) * np.clip(mu_l, 1e-12, 1.0))


#: Cycles' Glossy BSDF distributions that the ``cpa`` node group's lobes can take: name -> its lobe [1/sr]
#: (the node's ``distribution`` is the name upper-cased).
GLOSSY_LOBES = {"ggx": ggx_lobe_height_correlated, "beckmann": beckmann_lobe_height_correlated}


def fresnel_blend(cos_d, n):
    """Cycles' blend factor of its "generalized Schlick" Fresnel in the real-Fresnel mode that the
    Principled BSDF uses (exponent -IOR): ``s = (F(cos θ_d; n) - F0) / (1 - F0)`` clipped to [0, 1],
    so that ``F = f0 + (1 - f0) s`` is the dielectric Fresnel for ``f0 = F0`` and a tinted ``f0``
    tints normal incidence only (``intern/cycles/kernel/closure/bsdf_microfacet.h``, ``microfacet_fresnel``)."""
    F0 = _F0(n)
    R = fresnel_dielectric(np.clip(np.asarray(cos_d, float), 1e-9, 1.0), n).R
    return np.clip((R - F0) / (1.0 - F0), 0.0, 1.0)


def ggx_lobe_averages(roughness: float, mu_v, n: float, n_u: int = 48, n_phi: int = 48):
    """``(s̄, E)`` at view cosines ``mu_v`` of the height-correlated GGX lobe of perceptual roughness r
    (α = r²): E(μ) = ∫ D G2 / (4 μ) dω_l, its single-scattering albedo with F = 1, and s̄(μ) the
    average of :func:`fresnel_blend` over that lobe, ``∫ s D G2 / (4 μ) dω_l / E``: what Cycles
    tabulates as ``ggx_gen_schlick_ior_s`` (16³ Monte Carlo nodes in r, μ and
    ``sqrt((n - 1)/(n + 1))``; ``intern/cycles/app/cycles_precompute.cpp``) and ``ggx_E``, computed
    here by quadrature over the half vector with GGX's own measure ``D cos θ_h dω_h = du dφ / 2π``,
    ``tan²θ_h = α² u / (1 - u)`` (Walter et al. 2007, eq. 35; as :func:`flakedb.export.openpbr.specular_albedo`),
    ``dω_l = 4 (ω_v·h) dω_h``, Gauss-Legendre in u and midpoints in φ.  r = 0 is the mirror:
    s̄ = s(μ), E = 1.  Tabulated at :data:`_MU_TABLE` and interpolated linearly.

    A mirror's average is the Fresnel blend at the view angle; a rough lobe keeps E < 1:

    >>> s, E = ggx_lobe_averages(0.0, np.array([0.5]), 1.5)
    >>> bool(np.isclose(s[0], fresnel_blend(0.5, 1.5))), float(E[0])
    (True, 1.0)
    >>> s, E = ggx_lobe_averages(0.5, np.array([1.0]), 1.5)
    >>> bool(0.9 < E[0] < 1.0), bool(0.0 < s[0] < 0.05)
    (True, True)
    """
    mu_v = np.asarray(mu_v, float)
    if roughness <= 0.0:
        return fresnel_blend(mu_v, n), np.ones_like(mu_v)
    a2 = max(float(roughness) ** 2, 1e-3) ** 2
    x, w = np.polynomial.legendre.leggauss(n_u)
    u, w = 0.5 * (x + 1.0), 0.5 * w
    phi = (np.arange(n_phi) + 0.5) * 2.0 * np.pi / n_phi
    ch = 1.0 / np.sqrt(1.0 + a2 * u / (1.0 - u))
    sh = np.sqrt(np.clip(1.0 - ch * ch, 0.0, 1.0))
    h = np.stack(np.broadcast_arrays(sh[:, None] * np.cos(phi), sh[:, None] * np.sin(phi), ch[:, None]), axis=-1)
    mu = _MU_TABLE
    v = np.stack([np.sqrt(1.0 - mu * mu), np.zeros_like(mu), mu], axis=-1)              # (M, 3)
    vh = np.einsum("mk,upk->mup", v, h)
    mu_l = 2.0 * vh * h[None, ..., 2] - mu[:, None, None]                              # (ω_l)_z, ω_l = 2(v·h)h - v
    ok = (vh > 0.0) & (mu_l > 0.0)
    # f μ_l dω_l = D G2 / (4 μ_v μ_l) μ_l 4 (v·h) dω_h = [G2 (v·h) / (μ_v cos θ_h)] D cos θ_h dω_h
    g = np.where(ok, vh / (mu[:, None, None] * ch[None, :, None])
                 / (1.0 + smith_lambda(a2, mu)[:, None, None] + smith_lambda(a2, mu_l)), 0.0)
    E = np.einsum("u,mup->m", w, g) / n_phi
    S = np.einsum("u,mup->m", w, g * fresnel_blend(vh, n)) / n_phi
    s_bar = S / np.where(E > 0, E, 1.0)
    x_v = np.clip(mu_v, mu[0], 1.0)
    return np.interp(x_v, mu, s_bar), np.interp(x_v, mu, E)


def sun_disk(direction, half_angle_deg: float, n_rings: int = 3, n_azimuth: int = 8):
    """Directions (K, 3) inside a sun's cone of angular radius ``half_angle_deg`` and weights (K,)
    summing to 1 for its irradiance: a disk of uniform radiance E / (π sin²θ_s) (Cycles' sun and
    :class:`flakedb.render.preview.Sun`) gives ``L = E Σ_k w_k f(ω_k) (N·ω_k) / cos θ'_k`` (θ' from the
    sun's axis), as ∫_cone cos θ' dω = π sin²θ_s: Gauss-Legendre in u = sin²θ' (cos θ' dω = du dφ / 2),
    midpoints in φ."""
    d = np.asarray(direction, float)
    d = d / np.linalg.norm(d)
    s2 = math.sin(math.radians(half_angle_deg)) ** 2
    x, w = np.polynomial.legendre.leggauss(n_rings)
    u = 0.5 * (x + 1.0) * s2
    phi = (np.arange(n_azimuth) + 0.5) * 2.0 * np.pi / n_azimuth
    st, ct = np.sqrt(u), np.sqrt(1.0 - u)
    a = np.cross(d, [1.0, 0.0, 0.0] if abs(d[0]) < 0.9 else [0.0, 1.0, 0.0])
    a = a / np.linalg.norm(a)
    b = np.cross(d, a)
    dirs = (ct[:, None, None] * d + st[:, None, None] * (np.cos(phi)[None, :, None] * a
                                                         + np.sin(phi)[None, :, None] * b)).reshape(-1, 3)
    wts = np.repeat(0.5 * w / n_azimuth, n_azimuth) / ct.repeat(n_azimuth)   # weights of f (N·ω) / cos θ'
    return dirs, wts


def real_fresnel_Fss(n: float) -> float:
    """Cycles' fit of the cosine-weighted hemispherical average ``∫ 2μ F(μ; n) dμ`` of the dielectric
    Fresnel for n ≥ 1, ``(n - 1) / (4.08567 + 1.00071 n)`` (Kulla & Conty 2017; Cycles'
    ``bsdf_microfacet_setup_fresnel_generalized_schlick`` and the coat)."""
    return (n - 1.0) / (4.08567 + 1.00071 * n)


def ggx_energy_compensation(roughness: float, mu_v, Fss, n: float = 1.5):
    """``(boost, E)``: the factor ``1 + F_ms (1 - E) / E`` by which Cycles' energy-preserving GGX
    scales a lobe of perceptual roughness r at view cosines ``mu_v`` (P,), and E(μ_v) its albedo with
    F = 1 (:func:`ggx_lobe_averages`), where ``F_ms = F_ss E_avg / (1 - F_ss (1 - E_avg))``, ``E_avg =
    ∫ 2μ E(μ) dμ`` (16-node Gauss-Legendre) and ``Fss`` the lobe's average Fresnel, a scalar or (3,)
    per channel (Kulla & Conty 2017, appendix; Cycles' ``microfacet_ggx_preserve_energy``, which
    multiplies the closure's weight by ``E (1 + F_ms (1 - E)/E)`` and its evaluation by 1/E).
    Returns boost (P,) or (P, 3) and E (P,); r = 0: no compensation (boost 1, E 1).

    A white lobe (F_ss = 1) gets all its missing energy back, E boost = 1:

    >>> b, E = ggx_energy_compensation(0.6, np.array([0.3, 0.9]), 1.0)
    >>> bool(np.allclose(b * E, 1.0)), bool(np.all(E < 1))
    (True, True)
    """
    mu_v = np.asarray(mu_v, float)
    _, E = ggx_lobe_averages(roughness, mu_v, n)
    if roughness <= 0.0:
        return np.ones(mu_v.shape + np.shape(Fss)), E
    x, wx = np.polynomial.legendre.leggauss(16)
    mu_q = 0.5 * (x + 1.0)
    E_avg = float(np.sum(0.5 * wx * 2.0 * mu_q * ggx_lobe_averages(roughness, mu_q, n)[1]))
    Fss = np.asarray(Fss, float)
    F_ms = Fss * E_avg / (1.0 - Fss * (1.0 - E_avg))
    return 1.0 + np.multiply.outer((1.0 - E) / E, F_ms), E


def principled_sun_image(fit: OpenPBRFit, size: int = 32, direction=(0.0, 0.0, 1.0), irradiance: float = 1.0,
                         half_angle_deg: float = 2.0, extent: float = 1.05, distribution: str = "GGX") -> np.ndarray:
    """(size, size, 3) image that Cycles 5.0 renders of :func:`principled_inputs` (``distribution``
    GGX, or ``"MULTI_GGX"``: Blender's default, which the USD importer makes, below) on the unit sphere under a sun of ``irradiance`` and angular radius ``half_angle_deg``
    (:func:`sun_disk`), at pixel centres, in the frame of :func:`render_cycles_sphere`: the Principled
    BSDF as its kernel evaluates it (``intern/cycles/kernel/svm/closure.h``, the Principled branch;
    ``closure/bsdf_microfacet.h``; ``closure/bsdf_util.h``), every lobe in air with
    :func:`ggx_lobe_height_correlated`, for the view ω_v, light ω_l, half vector h, cos θ_d = ω_l·h::

        f = f_coat + w_1 m F_82(c, s; cos θ_d) L  +  w_2 F_s L  +  w_3 c / π,

        w_1 = 1 - A_coat(μ_v),   w_2 = w_1 (1 - m),   w_3 = w_2 (1 - max_k A_s,k(μ_v))

    Each layer takes ``1 - max over channels`` of its albedo estimate **at the view direction only**
    from the layers under it (``closure_layering_weight``); the fitted model takes the coat's
    ``(1 - F_c(μ_i))(1 - F_c(μ_o))`` from all of the base and the untinted lobe's
    ``(1 - E(μ_i))(1 - E(μ_o))`` from the diffuse (:func:`flakedb.export.openpbr.model_terms`).
    Here A_coat = F0(η_c) + (1 - F0(η_c)) s̄(r_c, μ_v) (:func:`ggx_lobe_averages`; F_c(μ_v) for a
    smooth coat, whose delta reaches no pixel centre), times Cycles' energy compensation of a rough
    coat's lobe, ``(1 + F_ms (1 - E)/E) / (1 + (1 - E)/E)`` with ``F_ms = F_ss E_avg / (1 - F_ss (1 - E_avg))``,
    F_ss = (η - 1) / (4.08567 + 1.00071 η) (Kulla & Conty 2017; Cycles applies it to the coat whatever
    the distribution), and the rough coat's lobe ``f_coat = F(cos θ_d; η_c) L_c (1 + F_ms (1 - E)/E)``;
    F_82 the F82-tint metal Fresnel, identical to the model's (Kutz et al. 2021,
    :func:`flakedb.export.openpbr.metal_f82_terms`), clipped to [0, 1]; ``F_s = f0 + (1 - f0) s(cos θ_d)``,
    f0 = F0(n_s) s clipped to [0, 1] (:func:`fresnel_blend`: Specular Tint tints normal incidence
    only; the model's s tints the whole Fresnel curve), A_s = f0 + (1 - f0) s̄(r, μ_v).  With a thin
    film, F_s is the film's reflectance in air (:func:`flakedb.export.openpbr.film_fresnel_rgb` of
    :meth:`~flakedb.export.openpbr.OpenPBRFit.film_relative_to_air`: the exact transfer-matrix
    reflectance where Cycles uses Belcour & Barla's 2017 spectral approximation) scaled per channel
    by ``1 + t (f0 / F0(n_s) - 1)``, t = (1 - F) / (1 - F0(n_s)) clipped, and A_s = F_s(μ_v)
    (Cycles has no table for films).  Raises ValueError for a metallic fit with a thin film (Cycles
    5.0 also puts the film on the metal lobe, with an index estimated from F0 and F82: not modelled).

    ``distribution="MULTI_GGX"`` (Multiscatter GGX) adds Cycles' energy compensation to the metal and
    the dielectric lobe as to a rough coat (:func:`ggx_energy_compensation`): the metal's F82 lobe
    times the boost of ``F_ss = c + (1 - c)/21 - B/126`` (the F82-tint model's average; Cycles'
    ``bsdf_microfacet_setup_fresnel_f82_tint``, clipped to [0, 1]), the dielectric lobe times the
    boost of ``F_ss = f0 + (1 - f0) s_ss``, ``s_ss = (F_ss(n_s) - F0) / (1 - F0)`` clipped
    (:func:`real_fresnel_Fss`; ``..._generalized_schlick``), and its albedo estimate A_s times E boost.

    What is left between this image and Cycles': its Monte Carlo noise, the linear interpolation of
    its 16-node tables, and its spectral film approximation.

    A white diffuse sphere under a sun along the view axis: E cos θ / π at the centre:

    >>> img = principled_sun_image(OpenPBRFit((1.0, 1.0, 1.0), 0.0, 1.0, 1.0, 0.0), size=8, extent=1.0)
    >>> bool(np.allclose(img[3:5, 3:5], np.sqrt(1 - 2 * 0.125 ** 2) / np.pi, rtol=1e-3))
    True
    """
    if distribution not in ("GGX", "MULTI_GGX"):
        raise ValueError(f"principled_sun_image: distribution {distribution!r} is not modelled; use 'GGX' or 'MULTI_GGX'")
    multi = distribution == "MULTI_GGX"
    c = np.clip(np.asarray(fit.base_color, float), 0.0, 1.0)
    s = np.clip(np.asarray(fit.specular_color, float), 0.0, None)
    m, r, n_s = float(fit.base_metalness), float(fit.specular_roughness), float(fit.specular_ior_relative)
    d_air, n_air = fit.film_relative_to_air()
    film = n_s > 1.0 and d_air > 0.1                    # Cycles' THINFILM_THICKNESS_CUTOFF [nm]
    if film and multi:
        raise ValueError("principled_sun_image: a thin film with distribution 'MULTI_GGX' is not modelled "
                         "(Cycles' albedo estimate of a filmed, energy-compensated lobe)")
    if film and m > 0.0:
        raise ValueError(f"principled_sun_image: a metallic fit (base_metalness {m}) with a thin film "
                         f"({fit.thin_film_thickness_nm} nm) is not modelled (Cycles also puts the film on the metal)")
    N, on = sphere_normals(size, extent)
    mu_v = N[..., 2]
    ok = on & (mu_v > 0)
    Nk, mv = N[ok], mu_v[ok]                                                           # (P, 3), (P,)
    w = np.ones_like(mv)
    f_coat = 0.0
    if fit.coat_ior > 1.0:
        nc, rc = float(fit.coat_ior), float(fit.coat_roughness)
        sc, Ec = ggx_lobe_averages(rc, mv, nc)
        boost = np.ones_like(mv)
        if rc > 0.0:
            boost, _ = ggx_energy_compensation(rc, mv, real_fresnel_Fss(nc), nc)
            f_coat = (nc, rc, boost)
        w = w * np.clip(1.0 - (_F0(nc) + (1.0 - _F0(nc)) * sc) * boost / (1.0 + (1.0 - Ec) / Ec), 0.0, 1.0)
    f0 = np.clip(_F0(n_s) * s, 0.0, 1.0)
    if n_s > 1.0 and film:
        F0r = _F0(n_s)

        def film_F(cos):
            F = film_fresnel_rgb(cos, 1.0, n_s, d_air, n_air)
            t = np.clip((1.0 - F) / (1.0 - F0r), 0.0, 1.0)
            return F * (1.0 + t * (f0 / F0r - 1.0))

        A_s = film_F(mv)
    elif n_s > 1.0:
        A_s = f0 + (1.0 - f0) * ggx_lobe_averages(r, mv, n_s)[0][:, None]
    boost_s = boost_m = 1.0
    if multi and n_s > 1.0:
        s_ss = float(np.clip((real_fresnel_Fss(n_s) - _F0(n_s)) / (1.0 - _F0(n_s)), 0.0, 1.0))
        boost_s, E_s = ggx_energy_compensation(r, mv, f0 + (1.0 - f0) * s_ss, n_s)
        A_s = A_s * E_s[:, None] * boost_s
    if multi and m > 0.0:
        f5 = (6.0 / 7.0) ** 5
        B = (c + (1.0 - c) * f5) * (7.0 / (f5 * 6.0 / 7.0)) * (1.0 - np.minimum(s, 1.0))
        boost_m, _ = ggx_energy_compensation(r, mv, np.clip(c + (1.0 - c) / 21.0 - B / 126.0, 0.0, 1.0))
    w_1, w_2 = w, w * (1.0 - m)
    w_3 = w_2 * np.clip(1.0 - A_s.max(axis=-1), 0.0, 1.0) if n_s > 1.0 else w_2
    dirs, wts = sun_disk(direction, half_angle_deg)
    out = np.zeros((len(mv), 3))
    for l, wt in zip(dirs, wts):
        mu_l = Nk @ l
        lit = mu_l > 0
        h = l + np.array([0.0, 0.0, 1.0])
        h = h / np.linalg.norm(h)
        cos_h, cos_d = Nk @ h, float(np.clip(l @ h, 0.0, 1.0))
        L = ggx_lobe_height_correlated(mv, mu_l, cos_h, r * r)
        f = (w_3 / np.pi)[:, None] * c
        if m > 0.0:
            f5 = (6.0 / 7.0) ** 5
            B = (c + (1.0 - c) * f5) * (7.0 / (f5 * 6.0 / 7.0)) * (1.0 - np.minimum(s, 1.0))
            F82 = np.clip(c + (1.0 - c) * (1.0 - cos_d) ** 5 - B * cos_d * (1.0 - cos_d) ** 6, 0.0, 1.0)
            f = f + (w_1 * m * L)[:, None] * F82 * boost_m
        if n_s > 1.0:
            F_s = film_F(np.array([cos_d]))[0] if film else f0 + (1.0 - f0) * fresnel_blend(cos_d, n_s)
            f = f + (w_2 * L)[:, None] * F_s * boost_s
        if f_coat:
            nc, rc, boost = f_coat
            f = f + (fresnel_dielectric(max(cos_d, 1e-9), nc).R * ggx_lobe_height_correlated(mv, mu_l, cos_h, rc * rc)
                     * boost)[:, None]
        out += np.where(lit[:, None], f * (wt * mu_l * irradiance)[:, None], 0.0)
    img = np.zeros((size, size, 3))
    img[ok] = out
    return img


def sun_direction(theta_deg: float, phi_deg: float = 90.0) -> tuple:
    """Unit vector towards a sun at zenith angle ``theta_deg`` from the camera axis (+z) and azimuth
    ``phi_deg`` in the image plane (90 = up)."""
    t, p = math.radians(theta_deg), math.radians(phi_deg)
    return (math.sin(t) * math.cos(p), math.sin(t) * math.sin(p), math.cos(t))


# --------------------------------------------------------------------------------------------
# The angle-indexed colour table (flakedb.export.cpa) as a Cycles / EEVEE node group
# --------------------------------------------------------------------------------------------
#: Builds the node group and material of :func:`cpa_inputs` (imports only bpy): the colour table is a
#: float image made from the pixels (packed into the .blend, linear, "Non-Color": no view transform),
#: read by one Image Texture per row with linear interpolation and EXTEND at (x, (k + 0.5) / rows),
#: x = μ_v (n - 1) / n + 0.5 / n (the pixel centres of columns 0 and n - 1 at μ_v = 0 and 1),
#: μ_v = N · Incoming (Geometry node); row 0 colours a Diffuse BSDF (roughness 0: Lambert), row k a
#: Glossy BSDF (GGX, single scattering, no Fresnel) of roughness √α_k, the rows after the K lobes a
#: Glossy BSDF whose Normal is the Incoming (view) vector (flakedb.export.cpa.retro_lobe), all added,
#: plus the coat's mirror: a Glossy BSDF of roughness 0 coloured by the Fresnel node of the coat's index.
_CPA_BUILD = '''
def build_sparkle_nodes(N, L, geo, colour, sp):
    """The glint layer of flakedb.export.sparkle in nodes: (glint shader, cell coordinates, the cell's three
    uniform numbers) sockets."""
    def math(op, a, b=None, c=None):
        n = N.new("ShaderNodeMath"); n.operation = op
        for i, v in enumerate((a, b, c)):
            if v is None:
                continue
            if isinstance(v, (int, float)):
                n.inputs[i].default_value = float(v)
            else:
                L.new(v, n.inputs[i])
        return n.outputs[0]
    def vec(op, a, b=None, scale=None):
        n = N.new("ShaderNodeVectorMath"); n.operation = op
        L.new(a, n.inputs[0])
        if b is not None:
            L.new(b, n.inputs[1])
        if scale is not None:
            if isinstance(scale, (int, float)):
                n.inputs["Scale"].default_value = float(scale)
            else:
                L.new(scale, n.inputs["Scale"])
        return n.outputs["Value"] if op in ("DOT_PRODUCT", "LENGTH", "DISTANCE") else n.outputs["Vector"]
    uvm = N.new("ShaderNodeUVMap"); uvm.uv_map = sp["uv_map"]
    cell = vec("FLOOR", vec("SCALE", uvm.outputs["UV"], scale=sp["cells_per_uv"]))
    wn = N.new("ShaderNodeTexWhiteNoise"); wn.noise_dimensions = "3D"
    L.new(cell, wn.inputs["Vector"])
    rgb = N.new("ShaderNodeSeparateColor"); L.new(wn.outputs["Color"], rgb.inputs[0])
    u1, u2, u3 = rgb.outputs[0], rgb.outputs[1], rgb.outputs[2]
    t = math("MULTIPLY", math("SQRT", math("DIVIDE", u1, math("SUBTRACT", 1.0, u1))), sp["lobe_alpha"])
    c = math("INVERSE_SQRT", math("MULTIPLY_ADD", t, t, 1.0))
    s = math("MULTIPLY", t, c)
    phi = math("MULTIPLY", u2, 6.283185307179586)
    n_ = geo.outputs["Normal"]
    tg = N.new("ShaderNodeTangent"); tg.direction_type = "UV_MAP"; tg.uv_map = sp["uv_map"]
    tt = vec("NORMALIZE", vec("SUBTRACT", tg.outputs["Tangent"], vec("SCALE", n_, scale=vec("DOT_PRODUCT", tg.outputs["Tangent"], n_))))
    bb = vec("CROSS_PRODUCT", n_, tt)
    m = vec("ADD", vec("ADD", vec("SCALE", tt, scale=math("MULTIPLY", s, math("COSINE", phi))),
                        vec("SCALE", bb, scale=math("MULTIPLY", s, math("SINE", phi)))), vec("SCALE", n_, scale=c))
    v = geo.outputs["Incoming"]
    mv = vec("DOT_PRODUCT", m, v)
    nv = math("MAXIMUM", vec("DOT_PRODUCT", n_, v), 1e-4)
    mu_l = math("SUBTRACT", math("MULTIPLY", math("MULTIPLY", mv, c), 2.0), nv)
    def lam(a2, mu):                       # GGX Smith Λ(μ) = (sqrt(1 + α² (1/μ² − 1)) − 1) / 2
        mu = math("MAXIMUM", mu, 1e-4)
        return math("MULTIPLY", math("SUBTRACT", math("SQRT", math("MULTIPLY_ADD", math("SUBTRACT", math("POWER", mu, -2.0), 1.0), a2, 1.0)), 1.0), 0.5)
    a2k, a2g = sp["lobe_alpha"] ** 2, sp["glint_alpha"] ** 2
    g2k = math("DIVIDE", 1.0, math("ADD", math("ADD", lam(a2k, nv), lam(a2k, mu_l)), 1.0))
    g2g = math("DIVIDE", 1.0, math("MULTIPLY_ADD", lam(a2g, mv), 2.0, 1.0))
    w = math("DIVIDE", math("MULTIPLY", g2k, mv), math("MULTIPLY", math("MULTIPLY", math("MAXIMUM", c, 1e-4), nv), g2g))
    ok = math("MULTIPLY", math("MULTIPLY", math("GREATER_THAN", mv, 0.0), math("GREATER_THAN", mu_l, 0.0)),
              math("LESS_THAN", u3, sp["occupancy"]))
    gain = math("MULTIPLY", math("MULTIPLY", w, ok), sp["share"] / sp["occupancy"])
    gl = N.new("ShaderNodeBsdfGlossy"); gl.distribution = "GGX"; gl.inputs["Roughness"].default_value = sp["glint_alpha"] ** 0.5
    L.new(vec("SCALE", colour, scale=gain), gl.inputs["Color"])
    L.new(m, gl.inputs["Normal"])
    return gl.outputs[0], cell, wn.outputs["Color"]


def build_cpa_material(bpy, name, inp, fit_json):
    """Create (or replace) material `name` with the node group `name`_cpa (flakedb.export.cpa)."""
    old = bpy.data.materials.get(name)
    if old is not None:
        bpy.data.materials.remove(old)
    rows, n = inp["rows"], inp["n_table"]
    img = bpy.data.images.new(name + "_table", n, rows, alpha=True, float_buffer=True)
    img.colorspace_settings.name = "Non-Color"
    img.pixels.foreach_set(inp["pixels"])
    img.pack()
    g = bpy.data.node_groups.new(name + "_cpa", "ShaderNodeTree")
    g.interface.new_socket("BSDF", in_out="OUTPUT", socket_type="NodeSocketShader")
    N, L = g.nodes, g.links
    geo = N.new("ShaderNodeNewGeometry")
    dot = N.new("ShaderNodeVectorMath"); dot.operation = "DOT_PRODUCT"
    L.new(geo.outputs["Normal"], dot.inputs[0]); L.new(geo.outputs["Incoming"], dot.inputs[1])
    x = N.new("ShaderNodeMath"); x.operation = "MULTIPLY_ADD"
    L.new(dot.outputs["Value"], x.inputs[0])
    x.inputs[1].default_value = (n - 1) / n
    x.inputs[2].default_value = 0.5 / n
    total = None
    def add(a, b):
        if a is None:
            return b
        s = N.new("ShaderNodeAddShader"); L.new(a, s.inputs[0]); L.new(b, s.inputs[1])
        return s.outputs[0]
    sp = inp.get("sparkle")
    for k in range(rows):
        uv = N.new("ShaderNodeCombineXYZ"); L.new(x.outputs[0], uv.inputs["X"]); uv.inputs["Y"].default_value = (k + 0.5) / rows
        tex = N.new("ShaderNodeTexImage"); tex.image = img; tex.interpolation = "Linear"; tex.extension = "EXTEND"
        L.new(uv.outputs[0], tex.inputs["Vector"])
        colour = tex.outputs["Color"]
        if sp is not None and k == sp["lobe"]:
            glint, cell, rnd = build_sparkle_nodes(N, L, geo, colour, sp)
            total = add(total, glint)
            g.interface.new_socket("Cell", in_out="OUTPUT", socket_type="NodeSocketVector")
            g.interface.new_socket("Random", in_out="OUTPUT", socket_type="NodeSocketColor")
            keep = N.new("ShaderNodeVectorMath"); keep.operation = "SCALE"; keep.inputs["Scale"].default_value = 1.0 - sp["share"]
            L.new(colour, keep.inputs[0]); colour = keep.outputs[0]
        n_ggx = len(inp["roughness"])
        if k == 0:
            b = N.new("ShaderNodeBsdfDiffuse"); b.inputs["Roughness"].default_value = 0.0
        elif k <= n_ggx:
            b = N.new("ShaderNodeBsdfGlossy"); b.distribution = inp.get("distribution", "GGX")
            b.inputs["Roughness"].default_value = inp["roughness"][k - 1]
        else:                              # backscatter lobe: the Glossy BSDF about the view direction
            b = N.new("ShaderNodeBsdfGlossy"); b.distribution = "GGX"
            b.inputs["Roughness"].default_value = inp["retro_roughness"][k - 1 - n_ggx]
            L.new(geo.outputs["Incoming"], b.inputs["Normal"])
        L.new(colour, b.inputs["Color"])
        total = add(total, b.outputs[0])
    if inp["coat_ior"] > 1.0:
        fr = N.new("ShaderNodeFresnel"); fr.inputs["IOR"].default_value = inp["coat_ior"]
        c = N.new("ShaderNodeBsdfGlossy"); c.distribution = "GGX"; c.inputs["Roughness"].default_value = 0.0
        L.new(fr.outputs[0], c.inputs["Color"])
        total = add(total, c.outputs[0])
    out = N.new("NodeGroupOutput"); L.new(total, out.inputs[0])
    if sp is not None:
        L.new(cell, out.inputs["Cell"]); L.new(rnd, out.inputs["Random"])
    m = bpy.data.materials.new(name)
    m.use_nodes = True
    nt = m.node_tree
    for node in list(nt.nodes):
        if node.type != "OUTPUT_MATERIAL":
            nt.nodes.remove(node)
    grp = nt.nodes.new("ShaderNodeGroup"); grp.node_tree = g
    nt.links.new(grp.outputs[0], nt.nodes["Material Output"].inputs["Surface"])
    m["flakedb_cpa"] = fit_json
    return m
'''


def cpa_inputs(table, alphas, coat_ior: float, sparkle: dict | None = None, retro_alphas=(),
               distribution: str = "ggx") -> dict:
    """The node group's inputs (:data:`_CPA_BUILD`) from a colour table (rows, n, 3) of linear RGB
    (:class:`flakedb.export.cpa.CPAFit`), the lobes' GGX α and the coat's index: ``pixels`` the RGBA
    float image, row k = table row k (Blender's row 0 is the image's bottom), ``roughness`` = √α
    (Cycles squares its Roughness input); ``sparkle``: the glint layer's node inputs
    (:func:`flakedb.export.sparkle.node_inputs`), or None for the smooth material; ``retro_alphas``: the
    backscatter lobes' GGX α (rows 1 + K ..., :func:`flakedb.export.cpa.retro_lobe`), ``retro_roughness``
    = √α; ``distribution``: the K lobes' (a key of :data:`GLOSSY_LOBES`; the Glossy node's, upper-cased)."""
    if distribution not in GLOSSY_LOBES:
        raise ValueError(f"cpa_inputs: distribution {distribution!r} is not one of {sorted(GLOSSY_LOBES)}")
    t = np.asarray(table, float)
    if t.shape[0] != 1 + len(alphas) + len(retro_alphas):
        raise ValueError(f"cpa_inputs: the table has {t.shape[0]} rows, not 1 + {len(alphas)} lobes + "
                         f"{len(retro_alphas)} backscatter lobes")
    rgba = np.concatenate([t, np.ones(t.shape[:2] + (1,))], axis=-1)
    return {"rows": int(t.shape[0]), "n_table": int(t.shape[1]), "pixels": [float(v) for v in rgba.ravel()],
            "roughness": [float(math.sqrt(a)) for a in alphas], "coat_ior": float(coat_ior),
            "retro_roughness": [float(math.sqrt(a)) for a in retro_alphas],
            "distribution": distribution.upper(),
            **({"sparkle": dict(sparkle)} if sparkle is not None else {})}


def cpa_material_script(table, alphas, coat_ior: float, name: str, fit_json: str = "{}",
                        sparkle: dict | None = None, retro_alphas=(), distribution: str = "ggx") -> str:
    """A standalone Blender script building the angle-indexed material (``blender --python``), with the glint
    layer when ``sparkle`` (:func:`flakedb.export.sparkle.node_inputs`) is given."""
    n = safe_name(name)
    return (f'"""flakedb export: the angle-indexed colour-table material of {name} (run inside Blender;\n'
            f'Cycles and EEVEE).  flakedb.export.cpa: coat mirror + Lambert + {distribution} lobes coloured by N.V."""\n'
            f"import bpy\n{_CPA_BUILD}\n"
            + (f"# sparkle: the glint cells are in the UV map {sparkle['uv_map'] or '(the active one)'!s}, read as "
               f"{sparkle['cells_per_uv']:.6g} cells per UV unit: the UVs must be proportional to lengths on the surface\n"
               if sparkle else "")
            + f"INPUTS = {cpa_inputs(table, alphas, coat_ior, sparkle, retro_alphas, distribution)!r}\n"
            f"FIT = {json.dumps(fit_json)}\n"
            f"material = build_cpa_material(bpy, {('flakedb_cpa_' + n)!r}, INPUTS, FIT)\n"
            f"for ob in bpy.context.selected_objects:          # assign to the selection, if any\n"
            f"    if ob.type == 'MESH':\n"
            f"        ob.data.materials.clear()\n"
            f"        ob.data.materials.append(material)\n")


_CPA_SPHERE_SCRIPT = '''
bpy.ops.mesh.primitive_uv_sphere_add(segments=128, ring_count=64, radius=1.0)
ob = bpy.context.object
bpy.ops.object.shade_smooth()
ob.data.materials.append(build_cpa_material(bpy, "flakedb_cpa", a["cpa"], "{}"))
'''

_CPA_RENDER = _CPA_BUILD + SCENE_SETUP_SCRIPT + _CPA_SPHERE_SCRIPT + CAMERA_SUN_RENDER_SCRIPT


def render_cycles_cpa_sphere(table, alphas, coat_ior: float, *, retro_alphas=(), distribution: str = "ggx",
                             size: int = 32, samples: int = 16,
                             direction=(0.0, 0.0, 1.0), irradiance: float = 1.0, half_angle_deg: float = 2.0,
                             extent: float = 1.05, threads: int = 1, seed: int = 1, filter_width_px: float = 0.01,
                             python: str | None = None, timeout: float = 600.0) -> dict:
    """:func:`render_cycles_sphere` with the angle-indexed node group (:func:`cpa_inputs`) instead of
    the Principled BSDF.  Returns {"image": (size, size, 3) linear sRGB, row 0 at the top, "blender"}."""
    args = render_args(size=size, samples=samples, direction=direction, irradiance=irradiance,
                       half_angle_deg=half_angle_deg, extent=extent, threads=threads, seed=seed,
                       filter_width_px=filter_width_px)
    args["cpa"] = cpa_inputs(table, alphas, coat_ior, retro_alphas=retro_alphas, distribution=distribution)
    out = run_bpy_script(_CPA_RENDER, args, python=python, timeout=timeout)
    return {"image": out["image"], "blender": out["blender"]}


#: A large plane whose normal makes the E2194-style in-plane geometry with the camera (+z, orthographic)
#: and a sun: for a view at x = aspecular - illumination from the normal (x > 0 on the light's side), the
#: plane is turned by -x about y (normal (-sin x, 0, cos x)) and the sun sits at illumination - x from the
#: camera axis in the x-z plane; every pixel then sees the same (ω_v, ω_l).  One render per geometry, the
#: image mean per channel out.
_GEOMETRY_SCRIPT = '''
bpy.ops.mesh.primitive_plane_add(size=40.0)
ob = bpy.context.object
if "cpa" in a:
    ob.data.materials.append(build_cpa_material(bpy, "flakedb_cpa", a["cpa"], "{}"))
else:
    ob.data.materials.append(build_material(bpy, "flakedb_fit", {k: (tuple(v) if isinstance(v, list) else v)
                                                                 for k, v in a["inputs"].items()}, "{}"))
cam = bpy.data.cameras.new("cam"); cam.type = "ORTHO"; cam.ortho_scale = 0.5
co = bpy.data.objects.new("cam", cam); sc.collection.objects.link(co); co.location = (0.0, 0.0, 4.0); sc.camera = co
ld = bpy.data.lights.new("sun", "SUN"); ld.energy = 1.0; ld.angle = 2.0 * math.radians(a["half_angle_deg"])
lo = bpy.data.objects.new("sun", ld); sc.collection.objects.link(lo)
sc.render.image_settings.file_format = "OPEN_EXR"
sc.render.image_settings.color_depth = "32"
means = []
for illum, x in a["geometries"]:
    ob.rotation_euler = (0.0, -math.radians(x), 0.0)
    t = math.radians(illum - x)
    lo.rotation_euler = Vector((math.sin(t), 0.0, math.cos(t))).to_track_quat("Z", "Y").to_euler()
    sc.render.filepath = a["exr"]
    bpy.ops.render.render(write_still=True)
    img = bpy.data.images.load(a["exr"], check_existing=False)
    px = list(img.pixels)
    n = len(px) // 4
    means.append([sum(px[c::4]) / n for c in range(3)])
    bpy.data.images.remove(img)
open(a["out"], "w").write(json.dumps({"pixels": [], "blender": bpy.app.version_string, "info": {"means": means}}))
'''


def render_cycles_geometries(geometries, *, inputs: dict | None = None, cpa: dict | None = None, size: int = 8,
                             samples: int = 256, half_angle_deg: float = 0.5, threads: int = 1, seed: int = 1,
                             python: str | None = None, timeout: float = 600.0) -> np.ndarray:
    """Reflectance factors π f (G, 3) that Cycles renders at in-plane ``geometries`` (G, 2) =
    (illumination°, aspecular°) (ASTM E2194's convention, :func:`flakedb.match.fit.geometry_directions`):
    a plane seen orthographically under a sun of irradiance 1 (:data:`_GEOMETRY_SCRIPT`), the image mean
    L = f μ_l divided by μ_l = cos(illumination), times π.  The material is the Principled BSDF of
    ``inputs`` (:func:`principled_inputs`) or the node group of ``cpa`` (:func:`cpa_inputs`)."""
    g = np.asarray(geometries, float)
    if g.ndim != 2 or g.shape[1] != 2:
        raise ValueError(f"render_cycles_geometries: in-plane geometries (G, 2) only, got shape {g.shape}")
    args = render_args(size=size, samples=samples, direction=(0, 0, 1), irradiance=1.0, half_angle_deg=half_angle_deg,
                       extent=1.0, threads=threads, seed=seed, filter_width_px=1.0, adaptive_sampling=False)
    args["geometries"] = [[float(i), float(asp - i)] for i, asp in g]
    if cpa is not None:
        args["cpa"] = cpa
    else:
        args["inputs"] = {k: list(v) if isinstance(v, tuple) else v for k, v in inputs.items()}
    out = run_bpy_script(_BUILD + _CPA_BUILD + SCENE_SETUP_SCRIPT + _GEOMETRY_SCRIPT, args, python=python, timeout=timeout)
    return np.pi * np.asarray(out["info"]["means"], float) / np.cos(np.radians(g[:, :1]))


#: A square patch (UV = position in metres, so the glint cells are in world units), seen from +z by an
#: orthographic camera covering ``side_m`` metres, turned by ``view_deg`` about y (its normal (sin x, 0, cos x):
#: the view at x from the normal on the patch's −u side; wider by 1 / cos x so that it fills the frame), under a
#: sun at ``light_deg`` from the patch's normal on its +u side (in the patch's frame: view (−sin x, 0, cos x),
#: light (sin θ, 0, cos θ)).  Two renders: the material (radiance), then, when ``cells`` is set, the node
#: group's ``Cell`` output as an emission of strength 1 (the integer cell coordinates at every pixel centre).
#: Pixels out as raw float32 RGBA files (row 0 at the bottom, Blender's order).
_PATCH_SCRIPT = """
import array
x = math.radians(a["view_deg"])
size = a["side_m"] / math.cos(x)
bpy.ops.mesh.primitive_plane_add(size=size)
ob = bpy.context.object
ob.rotation_euler = (0.0, x, 0.0)
me = ob.data
uvl = me.uv_layers.active
for lp in me.loops:
    co = me.vertices[lp.vertex_index].co
    uvl.data[lp.index].uv = (co.x + 0.5 * size, co.y + 0.5 * size)
mat = build_cpa_material(bpy, "flakedb_cpa", a["cpa"], "{}")
me.materials.append(mat)
cam = bpy.data.cameras.new("cam"); cam.type = "ORTHO"; cam.ortho_scale = a["side_m"]
co = bpy.data.objects.new("cam", cam); sc.collection.objects.link(co); co.location = (0.0, 0.0, 1.0); sc.camera = co
ld = bpy.data.lights.new("sun", "SUN"); ld.energy = 1.0; ld.angle = 2.0 * math.radians(a["half_angle_deg"])
lo = bpy.data.objects.new("sun", ld); sc.collection.objects.link(lo)
t = x + math.radians(a["light_deg"])
lo.rotation_euler = Vector((math.sin(t), 0.0, math.cos(t))).to_track_quat("Z", "Y").to_euler()
sc.render.image_settings.file_format = "OPEN_EXR"
sc.render.image_settings.color_depth = "32"
def shoot(path):
    sc.render.filepath = a["exr"]
    bpy.ops.render.render(write_still=True)
    img = bpy.data.images.load(a["exr"], check_existing=False)
    buf = array.array("f", [0.0]) * (a["size"] * a["size"] * 4)
    img.pixels.foreach_get(buf)
    open(path, "wb").write(buf.tobytes())
    bpy.data.images.remove(img)
shoot(a["radiance_raw"])
if a["cells"]:
    nt = mat.node_tree
    grp = [n for n in nt.nodes if n.type == "GROUP"][0]
    em = nt.nodes.new("ShaderNodeEmission"); em.inputs["Strength"].default_value = 1.0
    nt.links.new(em.outputs[0], nt.nodes["Material Output"].inputs["Surface"])
    sc.cycles.samples = 1
    ld.energy = 0.0
    for socket, path in (("Cell", a["cells_raw"]), ("Random", a["random_raw"])):
        nt.links.new(grp.outputs[socket], em.inputs["Color"])
        shoot(path)
open(a["out"], "w").write(json.dumps({"pixels": [], "blender": bpy.app.version_string, "info": {}}))
"""


def render_cycles_patch(cpa: dict, *, side_m: float, size: int, light_deg: float, half_angle_deg: float,
                        view_deg: float = 0.0, samples: int = 16, cells: bool = False, filter_width_px: float = 0.01, threads: int = 2,
                        seed: int = 1, python: str | None = None, timeout: float = 600.0) -> dict:
    """Render the node group of ``cpa`` (:func:`cpa_inputs`, with or without its sparkle layer) on a flat
    square patch (UV = position in metres) seen at ``view_deg`` from its normal by an orthographic camera
    covering ``side_m`` metres, ``size`` px, under a sun of irradiance 1 and angular radius ``half_angle_deg`` at
    ``light_deg`` from the normal on the other side (:data:`_PATCH_SCRIPT`), black world, ``samples`` per pixel (no adaptive sampling), every sample at
    its pixel's centre (``filter_width_px`` 0.01) unless a wider filter is asked for.  Returns {"image":
    (size, size, 3) radiance, linear sRGB, row 0 at the top; when ``cells``, "cells": (size, size, 2) integer
    cell coordinates and "random": (size, size, 3) the cell's uniform numbers (u₁, u₂, u₃) at the pixel
    centres; "blender": version}."""
    args = render_args(size=size, samples=samples, direction=(0, 0, 1), irradiance=1.0, half_angle_deg=half_angle_deg,
                       extent=1.0, threads=threads, seed=seed, filter_width_px=filter_width_px, adaptive_sampling=False)
    with tempfile.TemporaryDirectory(prefix="flakedb-patch-") as tmp:
        args.update(cpa=cpa, side_m=float(side_m), light_deg=float(light_deg), view_deg=float(view_deg), cells=bool(cells),
                    radiance_raw=str(Path(tmp) / "radiance.raw"), cells_raw=str(Path(tmp) / "cells.raw"),
                    random_raw=str(Path(tmp) / "random.raw"))
        out = run_bpy_script(_CPA_BUILD + SCENE_SETUP_SCRIPT + _PATCH_SCRIPT, args, python=python, timeout=timeout)

        def read(p):
            return np.fromfile(p, dtype="<f4").reshape(size, size, 4)[::-1, :, :3].astype(np.float64)

        res = {"image": read(args["radiance_raw"]), "blender": out["blender"]}
        if cells:
            res["cells"] = np.rint(read(args["cells_raw"])[..., :2]).astype(np.int64)
            res["random"] = read(args["random_raw"])
    return res
