"""The exported ``.usda`` rendered by a real USD consumer: Blender 5.0.1's USD importer
(``bpy.ops.wm.usd_import``), then Cycles, in the scene of :func:`flakedb.export.blender.render_cycles_sphere`
(the unit sphere's frame, an orthographic camera along −z over ``[-extent, extent]²``, a sun of the
given irradiance and angular radius, a uniform world of the given radiance, CPU, no denoising, pixel
centres, linear sRGB) but with adaptive sampling off (every pixel gets ``samples``, so that the
test's Monte Carlo bounds hold), in a subprocess of the bpy interpreter (the script imports only bpy and the
standard library; flakedb imports nothing from bpy).

What Blender 5.0.1's importer makes of the file (:func:`render_cycles_usd` returns it, read from
the imported scene; ``tests/export/test_usd_cycles.py`` checks it):

* the ``Mesh`` sphere with its ``normals`` as custom normals (within 3.5e-4 of the exact radial
  normals: Blender stores them as 16-bit pairs), the up axis Y turned to Blender's Z (a 90° rotation
  about x, immaterial for a sphere), and the bound material.  A ``Sphere`` gprim (what
  :mod:`flakedb.export.usd` wrote before) becomes a 92-vertex mesh **without its material**: the
  importer's shape reader binds none, so the coat and everything else was lost on this route;
* ``UsdPreviewSurface`` → one Principled BSDF: ``diffuseColor`` → Base Color, ``metallic`` →
  Metallic, ``roughness`` → Roughness (both perceptual, α = r²), ``ior`` → IOR, ``clearcoat`` → Coat
  Weight, ``clearcoatRoughness`` → Coat Roughness; Coat IOR stays 1.5 (UsdPreviewSurface's fixed coat
  index), Specular IOR Level 0.5 (F0 of IOR as is), Specular Tint white (with
  ``useSpecularWorkflow = 1`` the importer would put ``specularColor`` there, but keep Metallic:
  not the specification's specular workflow, so the exporter does not use it), no thin film, and the
  distribution Blender's default **Multiscatter GGX** (the Blender-script route sets single-scatter
  GGX, as fitted): :func:`flakedb.export.blender.principled_sun_image` with
  ``distribution="MULTI_GGX"`` states what Cycles renders of it.

:func:`imported_fit` turns the imported Principled inputs back into the :class:`OpenPBRFit` whose
:func:`~flakedb.export.blender.principled_inputs` they are, and :func:`usd_route_fit` states, from
the fit alone, what the USD route leaves of it (the fit with the lobe's tint white, no film and a
coat of index 1.5): the test checks that the two agree.
"""

from __future__ import annotations

import json
import re
from pathlib import Path

from flakedb.atomic import atomic_path
from flakedb.export.blender import (
    CAMERA_SUN_RENDER_SCRIPT,
    SCENE_SETUP_SCRIPT,
    render_args,
    run_bpy_script,
)
from flakedb.export.openpbr import OpenPBRFit
from flakedb.export.usd import usd_ior

#: The object part of the render script (:func:`flakedb.export.blender.run_bpy_script`): import the
#: file as it is, and report the meshes and the materials Blender made (every Principled input that
#: is not linked, each node and link)
_USD_IMPORT = '''
res = bpy.ops.wm.usd_import(filepath=a["usda"])
INFO["import"] = sorted(res)


def plain(v):
    try:
        return [float(x) for x in v]
    except TypeError:
        return v if isinstance(v, (bool, int, float, str)) else str(v)


INFO["objects"] = []
for ob in bpy.data.objects:
    if ob.type != "MESH":
        continue
    me = ob.data
    INFO["objects"].append({
        "name": ob.name, "vertices": len(me.vertices), "faces": len(me.polygons),
        "custom_normals": bool(me.has_custom_normals),
        "radius": [min(v.co.length for v in me.vertices), max(v.co.length for v in me.vertices)],
        "materials": [s.material.name if s.material else None for s in ob.material_slots]})
INFO["materials"] = {}
for m in bpy.data.materials:
    d = {"nodes": [[n.bl_idname, n.name] for n in m.node_tree.nodes] if m.node_tree else [],
         "links": [[l.from_node.name, l.from_socket.name, l.to_node.name, l.to_socket.name]
                   for l in m.node_tree.links] if m.node_tree else []}
    for n in (m.node_tree.nodes if m.node_tree else []):
        if n.bl_idname == "ShaderNodeBsdfPrincipled":
            d["distribution"] = n.distribution
            d["inputs"] = {i.name: plain(i.default_value) for i in n.inputs
                           if not i.is_linked and hasattr(i, "default_value")}
            d["linked"] = [i.name for i in n.inputs if i.is_linked]
    INFO["materials"][m.name] = d
'''

_RENDER_USD = SCENE_SETUP_SCRIPT + _USD_IMPORT + CAMERA_SUN_RENDER_SCRIPT


def render_cycles_usd(usda_path, *, size: int = 32, samples: int = 16, direction=(0.0, 0.0, 1.0),
                      irradiance: float = 1.0, half_angle_deg: float = 2.0, extent: float = 1.05,
                      world_radiance: float = 0.0, threads: int = 1, seed: int = 1, filter_width_px: float = 0.01,
                      python: str | None = None, timeout: float = 600.0) -> dict:
    """Import ``usda_path`` with Blender's USD importer and render it in Cycles (module docstring),
    ``samples`` per pixel with Cycles' sampling ``seed``, a sun of ``irradiance`` [W/m²] along
    ``direction`` (none when 0) and a uniform world of radiance ``world_radiance``.  Returns
    {"image": (size, size, 3) float64 linear sRGB, row 0 at the top, "blender": version, "objects":
    [the imported meshes: name, vertices, faces, custom_normals, radius [min, max], materials],
    "materials": {name: {"distribution", "inputs" (Principled BSDF input -> value), "linked",
    "nodes", "links"}}, "import": the operator's result}.  Raises RuntimeError with Blender's last
    lines on failure, FileNotFoundError when the file is missing."""
    p = Path(usda_path)
    if not p.is_file():
        raise FileNotFoundError(f"render_cycles_usd: no such file {p} (write one with flakedb export-openpbr)")
    args = render_args(size=size, samples=samples, direction=direction, irradiance=irradiance,
                       half_angle_deg=half_angle_deg, extent=extent, threads=threads, seed=seed,
                       filter_width_px=filter_width_px, world_radiance=world_radiance, adaptive_sampling=False)
    args["usda"] = str(p.resolve())
    out = run_bpy_script(_RENDER_USD, args, python=python, timeout=timeout)
    info = out["info"]
    return {"image": out["image"], "blender": out["blender"], "objects": info["objects"],
            "materials": info["materials"], "import": info["import"]}


def sphere_material(render: dict) -> dict:
    """The imported material (an entry of ``render["materials"]``) of the one imported mesh of
    :func:`render_cycles_usd`'s result; ValueError naming what is missing otherwise (no mesh, several,
    a mesh without a material: what a ``Sphere`` gprim becomes, or a material without a Principled BSDF)."""
    obs = render["objects"]
    if len(obs) != 1:
        raise ValueError(f"sphere_material: Blender imported {len(obs)} meshes ({[o['name'] for o in obs]}); "
                         f"the exported .usda holds one sphere")
    mats = [m for m in obs[0]["materials"] if m]
    if not mats:
        raise ValueError(f"sphere_material: Blender's importer bound no material to the mesh {obs[0]['name']!r} "
                         f"({obs[0]['vertices']} vertices): a UsdGeom.Sphere gprim loses its binding in Blender "
                         f"5.0's importer; write the sphere as a Mesh (flakedb.export.usd)")
    m = render["materials"][mats[0]]
    if "inputs" not in m:
        raise ValueError(f"sphere_material: material {mats[0]!r} has no Principled BSDF (nodes {m['nodes']}); "
                         f"import with import_usd_preview (Blender's default)")
    return m


def imported_fit(material: dict) -> OpenPBRFit:
    """The :class:`OpenPBRFit` whose :func:`flakedb.export.blender.principled_inputs` are the
    Principled BSDF inputs Blender imported (``material`` = :func:`sphere_material`'s): Base Color →
    base colour, Metallic, Roughness, IOR → the lobe's relative index (none when Specular IOR Level is 0),
    Specular Tint → specular colour, Coat Weight 1 → a coat of Coat IOR and Coat Roughness (0 → none),
    Thin Film Thickness [nm] / IOR → the film in air (moved back into the coat of index Coat IOR, the
    inverse of :meth:`OpenPBRFit.film_relative_to_air`).  Raises ValueError for what
    :func:`~flakedb.export.blender.principled_sun_image` does not model: a linked input, a Coat Weight
    other than 0 or 1, a Specular IOR Level other than 0 or 0.5, a coat tint.

    The inverse of principled_inputs:

    >>> from flakedb.export.blender import principled_inputs
    >>> fit = OpenPBRFit((0.8, 0.5, 0.2), 0.3, 0.4, 1.5, 0.1, specular_color=(0.3, 0.5, 0.8), specular_ior_relative=2.0)
    >>> back = imported_fit({"inputs": {k: list(v) if isinstance(v, tuple) else v
    ...                                 for k, v in principled_inputs(fit).items()}, "linked": []})
    >>> back == fit
    True
    """
    p, linked = material["inputs"], material.get("linked", [])
    used = ("Base Color", "Metallic", "Roughness", "IOR", "Specular IOR Level", "Specular Tint", "Coat Weight",
            "Coat Roughness", "Coat IOR", "Coat Tint", "Thin Film Thickness", "Thin Film IOR")
    bad = [k for k in linked if k in used]
    if bad:
        raise ValueError(f"imported_fit: inputs {bad} are linked to other nodes; only constant inputs are modelled")
    cw, level = float(p["Coat Weight"]), float(p["Specular IOR Level"])
    if cw not in (0.0, 1.0):
        raise ValueError(f"imported_fit: Coat Weight {cw} is neither 0 nor 1 (principled_sun_image models a full coat)")
    if level not in (0.0, 0.5):
        raise ValueError(f"imported_fit: Specular IOR Level {level} is neither 0 nor 0.5")
    if cw and any(abs(float(x) - 1.0) > 1e-6 for x in p["Coat Tint"][:3]):
        raise ValueError(f"imported_fit: Coat Tint {p['Coat Tint'][:3]} is not white (not modelled)")
    n_c = float(p["Coat IOR"]) if cw else 1.0
    d_air, n_air = float(p["Thin Film Thickness"]), float(p["Thin Film IOR"])
    return OpenPBRFit(base_color=tuple(float(x) for x in p["Base Color"][:3]),
                      base_metalness=float(p["Metallic"]), specular_roughness=float(p["Roughness"]),
                      coat_ior=n_c, coat_roughness=float(p["Coat Roughness"]),
                      specular_color=tuple(float(x) for x in p["Specular Tint"][:3]),
                      specular_ior_relative=float(p["IOR"]) if level else 1.0,
                      thin_film_thickness_nm=d_air / (n_c if cw else 1.0),
                      thin_film_ior=n_air * (n_c if cw else 1.0) if d_air > 0 else 1.5)


def usd_route_fit(fit: OpenPBRFit) -> OpenPBRFit:
    """What the ``.usda`` route leaves of ``fit`` in a UsdPreviewSurface consumer that reads it as
    Blender does (module docstring): the lobe's tint white (for a metal: no F82 edge tint), no thin
    film, the coat's index 1.5 (Blender's Coat IOR), the base's index the written ``ior``
    (:func:`flakedb.export.usd.usd_ior`: the coat's index on a coated fit; 1 means no dielectric lobe).
    Render it with ``distribution="MULTI_GGX"`` for Blender."""
    return OpenPBRFit(base_color=tuple(float(x) for x in fit.base_color), base_metalness=float(fit.base_metalness),
                      specular_roughness=float(fit.specular_roughness),
                      coat_ior=1.5 if fit.coat_ior > 1.0 else 1.0, coat_roughness=float(fit.coat_roughness),
                      specular_color=(1.0, 1.0, 1.0),
                      specular_ior_relative=usd_ior(fit))


_CLEARCOAT = re.compile(r"(float inputs:clearcoat = )([-+0-9.eE]+)")


def with_clearcoat(usda_path, out_path, clearcoat: float) -> Path:
    """A copy of an exported ``.usda`` with UsdPreviewSurface's ``inputs:clearcoat`` set to
    ``clearcoat`` (the test's coat-off render and its bite); ValueError when the file does not hold
    exactly one such input."""
    text = Path(usda_path).read_text(encoding="utf-8")
    new, k = _CLEARCOAT.subn(lambda m: f"{m.group(1)}{float(clearcoat):g}", text)
    if k != 1:
        raise ValueError(f"with_clearcoat: {usda_path} holds {k} 'float inputs:clearcoat' inputs, not 1")
    out = Path(out_path)
    with atomic_path(out, suffix="") as tmp:
        Path(tmp).write_text(new, encoding="utf-8")
    return out


def read_usda_fit(usda_path) -> OpenPBRFit:
    """The fit stored in an exported ``.usda``'s ``customLayerData`` (``flakedb_fit``), read as text."""
    for line in Path(usda_path).read_text(encoding="utf-8").splitlines():
        if "string flakedb_fit = " in line:
            return OpenPBRFit.from_dict(json.loads(json.loads(line.split(" = ", 1)[1])))
    raise ValueError(f"read_usda_fit: {usda_path} has no flakedb_fit in its customLayerData "
                     f"(not written by flakedb export-openpbr)")
