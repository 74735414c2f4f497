"""The fitted material as a USD layer (``.usda``, text): a unit sphere bound to a ``UsdPreviewSurface``
material (the USD schema every Hydra delegate renders).  Written as plain text (no usd-core needed to
write); the tests open it with ``usd-core`` (``pxr.Usd``) and render it through Blender's USD importer
in Cycles (:mod:`flakedb.export.usd_render`, ``tests/export/test_usd_cycles.py``).

The sphere is a ``Mesh`` (the 48 x 24 UV sphere of :func:`flakedb.export.gltf.uv_sphere`, exact
vertex normals, texture coordinates ``primvars:st`` = glTF's (u, 1 − v): USD's t runs up), not a ``Sphere`` gprim: Blender 5.0.1's USD importer
tessellates a ``Sphere`` into 92 vertices and **drops its material binding** (its shape reader assigns
no material; the mesh reader does), so a ``Sphere`` rendered in Blender without the fitted material,
coat and all.

UsdPreviewSurface has one index, ``ior``, "to be used for translucent objects and objects with
specular components, including the clearcoat if clearcoat > 0" (the UsdPreviewSurface specification,
openusd.org; MaterialX's ``ND_UsdPreviewSurface_surfaceshader`` takes the coat's F0 from it).  A
coated fit writes the **coat's** index there, so that the mirror every reader draws is the paint's
(``tools/mtlx_lit.py --usd``: with the base's relative index written instead, MaterialX drew no coat on
metallic silver and pearl white, whose lobe index is 1, and a coat of F0 0.25 on the pearlescent's 3);
the base's dielectric lobe then takes that index too (Blender's importer puts ``ior`` on the base and
keeps its coat at 1.5): the fit's own lobe index is lost on this route, as are the lobe's tint
(``specular_color``: the metallic workflow has none) and a fitted thin film.
The fit and its error are stored in the layer's ``customLayerData`` (``flakedb_fit``, JSON)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from flakedb.atomic import atomic_path
from flakedb.export.gltf import uv_sphere, uv_sphere_texcoords
from flakedb.export.materialx import safe_name
from flakedb.export.openpbr import OpenPBRFit


def _vec3_array(a: np.ndarray) -> str:
    """A USD ``point3f[]`` / ``normal3f[]`` value: ``[(x, y, z), ...]`` at float32's 7 digits."""
    return "[" + ", ".join(f"({x:.7g}, {y:.7g}, {z:.7g})" for x, y, z in np.asarray(a, float)) + "]"


def _vec2_array(a: np.ndarray) -> str:
    """A USD ``texCoord2f[]`` value: ``[(s, t), ...]``."""
    return "[" + ", ".join(f"({x:.7g}, {y:.7g})" for x, y in np.asarray(a, float)) + "]"


def usd_ior(fit: OpenPBRFit) -> float:
    """UsdPreviewSurface's ``ior`` for ``fit`` (module docstring): the coat's index when it has a coat, else
    the base lobe's index (≥ 1)."""
    return float(fit.coat_ior) if fit.coat_ior > 1.0 else max(float(fit.specular_ior_relative), 1.0)


def usda_text(fit: OpenPBRFit, name: str) -> str:
    n = safe_name(name)
    pos, nrm, idx = uv_sphere()
    uv, _ = uv_sphere_texcoords()
    uv = uv * np.array([1.0, -1.0]) + np.array([0.0, 1.0])     # USD's st has its origin at the bottom left
    counts = "[" + ", ".join(["3"] * (len(idx) // 3)) + "]"
    indices = "[" + ", ".join(str(int(i)) for i in idx) + "]"
    c = fit.base_color
    fit_json = json.dumps(json.dumps(fit.to_dict(), separators=(",", ":")))    # a quoted USD string
    return f'''#usda 1.0
(
    defaultPrim = "{n}"
    metersPerUnit = 1
    upAxis = "Y"
    customLayerData = {{
        string flakedb_fit = {fit_json}
    }}
)

def Xform "{n}"
{{
    def Mesh "sphere" (
        prepend apiSchemas = ["MaterialBindingAPI"]
    )
    {{
        float3[] extent = [(-1, -1, -1), (1, 1, 1)]
        int[] faceVertexCounts = {counts}
        int[] faceVertexIndices = {indices}
        point3f[] points = {_vec3_array(pos)}
        normal3f[] normals = {_vec3_array(nrm)} (
            interpolation = "vertex"
        )
        texCoord2f[] primvars:st = {_vec2_array(uv)} (
            interpolation = "vertex"
        )
        uniform token subdivisionScheme = "none"
        rel material:binding = </{n}/Looks/M_{n}>
    }}

    def Scope "Looks"
    {{
        def Material "M_{n}"
        {{
            token outputs:surface.connect = </{n}/Looks/M_{n}/PreviewSurface.outputs:surface>

            def Shader "PreviewSurface"
            {{
                uniform token info:id = "UsdPreviewSurface"
                color3f inputs:diffuseColor = ({c[0]:.6g}, {c[1]:.6g}, {c[2]:.6g})
                float inputs:metallic = {fit.base_metalness:.6g}
                float inputs:roughness = {fit.specular_roughness:.6g}
                float inputs:clearcoat = {1.0 if fit.coat_ior > 1.0 else 0.0:g}
                float inputs:clearcoatRoughness = {fit.coat_roughness:.6g}
                float inputs:ior = {usd_ior(fit):.6g}
                int inputs:useSpecularWorkflow = 0
                token outputs:surface
            }}
        }}
    }}
}}
'''


def write_usda(path, fit: OpenPBRFit, name: str) -> Path:
    """Write :func:`usda_text` to ``path`` atomically (temp path, then rename); returns the path.

    Read back without ``pxr``: the default prim and the fit in the layer's ``customLayerData``:

    >>> import tempfile
    >>> fit = OpenPBRFit((0.8, 0.5, 0.2), 1.0, 0.3, 1.5, 0.0, thin_film_thickness_nm=300.0, thin_film_ior=2.0)
    >>> text = write_usda(Path(tempfile.mkdtemp()) / "silver.usda", fit, "1 silver").read_text(encoding="utf-8")
    >>> line = next(ln for ln in text.splitlines() if "string flakedb_fit = " in ln)
    >>> back = OpenPBRFit.from_dict(json.loads(json.loads(line.split(" = ", 1)[1])))
    >>> text.splitlines()[0], 'defaultPrim = "_1_silver"' in text, back == fit
    ('#usda 1.0', True, True)
    """
    path = Path(path)
    with atomic_path(path, suffix="") as tmp:
        Path(tmp).write_text(usda_text(fit, name), encoding="utf-8")
    return path
