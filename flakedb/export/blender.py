"""The fitted material as a Blender Principled BSDF (Blender 4.x / 5.x input names), and a Cycles
render of a sphere under a sun that the tests compare with flakedb's own preview.

* :func:`material_script` -- a Python script that builds the material in the open Blender file
  (``blender --python NAME.blender.py`` or the Text Editor's Run Script): ``Base Color``,
  ``Metallic``, ``Roughness`` (perceptual, α = r²), ``IOR`` = the fit's index relative to the
  coat (Cycles 5.0.1 is closer to the fit with it than with OpenPBR's ``specular_ior`` = relative x
  coat index: a Cycles sphere of a model-made file agrees with the model to ≤ 3.6 ΔE00 against
  5-7 at 7 pixels, measured; so Cycles does not divide by the coat index here), ``Specular Tint`` = ``specular_color``
  (Blender tints F0 only, the fit tints the whole Fresnel curve), ``Specular IOR Level`` 0.5 (the
  index as is; 0 when the fit has no base lobe), ``Coat Weight`` 1,
  ``Coat Roughness``, ``Coat IOR`` (untinted coat), ``Thin Film Thickness`` [nm] / ``Thin Film IOR`` of the
  equivalent film in air (:meth:`flakedb.export.openpbr.OpenPBRFit.film_relative_to_air`: Cycles
  puts the film in air; measured on a 300 nm film: Cycles vs the model ≤ 3.2 ΔE00 at 7 pixels this
  way, 6.4 with the film's own values).  The fit is kept in the material's custom
  property ``flakedb_fit`` (JSON).
* :func:`render_cycles_sphere` -- runs Blender's ``bpy`` (the optional extra ``flakedb[blender]``)
  in a **separate process** (``bpy`` is a 300 MB module that replaces the interpreter's state; it
  also pins numpy < 2 in its metadata, and flakedb's own numpy is not touched): the unit sphere, an
  orthographic camera along −z covering ``[-extent, extent]²`` (the frame of
  :mod:`flakedb.render.preview`), a black world and a sun of the given irradiance and angular
  radius, Cycles on the CPU, no denoising, the Standard view transform (linear Rec.709 = linear sRGB
  pixels).  A sun of strength E [W/m²] gives a white Lambertian plane facing it the radiance E/π,
  the convention of :class:`flakedb.render.preview.Sun` (checked by the test against a diffuse
  sphere).
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
from flakedb.export.openpbr import OpenPBRFit, evaluate


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


_RENDER = _BUILD + '''
import json, math, sys
import bpy
from mathutils import Vector

a = json.loads(open(sys.argv[-1]).read())
bpy.ops.wm.read_factory_settings(use_empty=True)
sc = bpy.context.scene
sc.render.engine = "CYCLES"
sc.cycles.device = "CPU"
sc.cycles.samples = a["samples"]
sc.cycles.use_denoising = False
sc.cycles.seed = 1
sc.cycles.max_bounces = 4
sc.render.resolution_x = sc.render.resolution_y = a["size"]
sc.render.resolution_percentage = 100
sc.render.threads_mode = "FIXED"
sc.render.threads = a["threads"]
sc.view_settings.view_transform = "Standard"
sc.view_settings.look = "None"
sc.view_settings.exposure = 0.0
sc.view_settings.gamma = 1.0
sc.render.film_transparent = False
w = bpy.data.worlds.new("black"); sc.world = w; w.use_nodes = True
w.node_tree.nodes["Background"].inputs[1].default_value = 0.0
bpy.ops.mesh.primitive_uv_sphere_add(segments=128, ring_count=64, radius=1.0)
ob = bpy.context.object
bpy.ops.object.shade_smooth()
ob.data.materials.append(build_material(bpy, "flakedb_fit", {k: (tuple(v) if isinstance(v, list) else v)
                                                             for k, v in a["inputs"].items()}, "{}"))
cam = bpy.data.cameras.new("cam"); cam.type = "ORTHO"; cam.ortho_scale = 2.0 * a["extent"]
co = bpy.data.objects.new("cam", cam); sc.collection.objects.link(co); co.location = (0.0, 0.0, 4.0); sc.camera = co
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
open(a["out"], "w").write(json.dumps({"pixels": rows[::-1], "blender": bpy.app.version_string}))  # row 0 at the top
'''


def bpy_available(python: str | None = None) -> tuple[bool, str]:
    """(whether ``python`` (default: this interpreter) can import bpy, the reason if not)."""
    python = python or sys.executable
    try:
        r = subprocess.run([python, "-c", "import bpy; print(bpy.app.version_string)"], capture_output=True,
                           text=True, timeout=300)
    except (OSError, subprocess.TimeoutExpired) as e:
        return False, f"cannot run {python}: {e}"
    if r.returncode != 0:
        last = (r.stderr.strip().splitlines() or ["?"])[-1]
        return False, f"bpy is not importable by {python} ({last}); pip install 'flakedb[blender]'"
    return True, r.stdout.strip().splitlines()[-1]


def render_cycles_sphere(fit: OpenPBRFit, *, size: int = 32, samples: int = 16, direction=(0.0, 0.0, 1.0),
                         irradiance: float = 1.0, half_angle_deg: float = 2.0, extent: float = 1.05,
                         threads: int = 1, python: str | None = None, timeout: float = 600.0) -> dict:
    """Render the fitted material on the unit sphere in Cycles (module docstring) in a subprocess of
    ``python`` (default: this interpreter).  Returns {"image": (size, size, 3) float64 linear sRGB,
    row 0 at the top, "blender": version}.  Raises RuntimeError with Blender's last lines on failure."""
    d = np.asarray(direction, float)
    d = d / np.linalg.norm(d)
    with tempfile.TemporaryDirectory(prefix="flakedb-cycles-") as tmp:
        t = Path(tmp)
        args = {"size": int(size), "samples": int(samples), "threads": int(threads), "extent": float(extent),
                "irradiance": float(irradiance), "half_angle_deg": float(half_angle_deg),
                "direction": d.tolist(), "inputs": {k: list(v) if isinstance(v, tuple) else v
                                                    for k, v in principled_inputs(fit).items()},
                "exr": str(t / "render.exr"), "out": str(t / "pixels.json")}
        (t / "args.json").write_text(json.dumps(args))
        (t / "render.py").write_text(_RENDER)
        env = dict(os.environ, PYTHONNOUSERSITE="1")
        r = subprocess.run([python or sys.executable, str(t / "render.py"), str(t / "args.json")],
                           capture_output=True, text=True, timeout=timeout, cwd=tmp, env=env)
        if r.returncode != 0 or not (t / "pixels.json").exists():
            tail = "\n".join((r.stdout + r.stderr).strip().splitlines()[-8:])
            raise RuntimeError(f"the Cycles render failed (exit {r.returncode}):\n{tail}")
        out = json.loads((t / "pixels.json").read_text())
    return {"image": np.asarray(out["pixels"], dtype=np.float64), "blender": out["blender"]}


def model_sun_image(fit: OpenPBRFit, size: int = 32, direction=(0.0, 0.0, 1.0), irradiance: float = 1.0,
                    extent: float = 1.05) -> np.ndarray:
    """(size, size, 3) image of the fitted **model** (:func:`flakedb.export.openpbr.evaluate`) on the
    unit sphere under a point sun of ``irradiance`` along ``direction``, at pixel centres, in the frame
    of :func:`render_cycles_sphere` (row 0 at the top): ``L = f(ω_v, ω_sun) cos θ_sun E`` where the
    sun is above the local horizon, 0 elsewhere (the coat's delta does not reach a pixel centre)."""
    d = np.asarray(direction, float)
    d = d / np.linalg.norm(d)
    x = -extent + (np.arange(size) + 0.5) * 2 * extent / size
    X, Y = np.meshgrid(x, x[::-1])
    r2 = X * X + Y * Y
    N = np.stack([X, Y, np.sqrt(np.clip(1 - r2, 0, 1))], axis=-1)
    mu_v, mu_s = N[..., 2], N @ d
    tv = np.array([0.0, 0.0, 1.0]) - N * mu_v[..., None]             # tangent parts of view and sun
    ts = d - N * mu_s[..., None]
    den = np.linalg.norm(tv, axis=-1) * np.linalg.norm(ts, axis=-1)
    cos_dphi = np.where(den > 0, np.sum(tv * ts, axis=-1) / np.where(den > 0, den, 1.0), 1.0)
    phi_d = np.pi - np.arccos(np.clip(cos_dphi, -1.0, 1.0))           # file convention: 0 = mirror side
    ok = (r2 < 1) & (mu_s > 0) & (mu_v > 0)
    img = np.zeros((size, size, 3))
    img[ok] = evaluate(fit, mu_v[ok], -mu_s[ok], phi_d[ok]) * (mu_s[ok] * irradiance)[:, None]
    return img


def sun_direction(theta_deg: float, phi_deg: float = 90.0) -> tuple:
    """Unit vector towards a sun at zenith angle ``theta_deg`` from the camera axis (+z) and azimuth
    ``phi_deg`` in the image plane (90 = up)."""
    t, p = math.radians(theta_deg), math.radians(phi_deg)
    return (math.sin(t) * math.cos(p), math.sin(t) * math.sin(p), math.cos(t))
