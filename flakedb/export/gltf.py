"""The fitted material on a sphere as glTF 2.0 (``.gltf`` with the buffer embedded, or binary ``.glb``).

Material: ``pbrMetallicRoughness`` (baseColorFactor = the fitted base colour, metallicFactor,
roughnessFactor = the perceptual roughness r, α = r²), ``KHR_materials_clearcoat`` (factor 1, the
coat roughness; its index is fixed at 1.5 by the extension), ``KHR_materials_ior`` (the base's
dielectric index: glTF has no index relative to the coat, so the fit's relative index is written)
and ``KHR_materials_specular`` (specularColorFactor = the fit's specular colour, which glTF applies
to F0 only; specularFactor 0 when the fit has no base lobe).  A fitted thin
film is ``KHR_materials_iridescence`` (factor 1; the extension's film is in air, so the equivalent
film of :meth:`flakedb.export.openpbr.OpenPBRFit.film_relative_to_air`; thickness minimum =
maximum).
The fit and its error are in the material's ``extras.flakedb_fit``.  Written with the standard
library only; the tests read it back with ``pygltflib`` and render it in three.js
(``tools/gltf_lit.py``, ``tests/export/test_gltf_lit.py``).

:func:`threejs_sun_image` states in numpy what three.js r187's ``MeshPhysicalMaterial`` (the
material its ``GLTFLoader`` makes of these extensions) renders of the file under one
``DirectionalLight``, and :func:`threejs_coat_fresnel` the Fresnel its clearcoat uses.
"""

from __future__ import annotations

import base64
import json
import struct
from pathlib import Path

import numpy as np

from flakedb.atomic import atomic_path
from flakedb.export.blender import ggx_lobe_averages, sphere_normals
from flakedb.export.openpbr import OpenPBRFit

EXTENSIONS = ["KHR_materials_clearcoat", "KHR_materials_ior", "KHR_materials_specular"]


def uv_sphere(segments: int = 48, rings: int = 24):
    """(positions (V, 3) float32, normals (V, 3) float32, indices (I,) uint32) of a unit UV sphere."""
    th = np.linspace(0.0, np.pi, rings + 1)
    ph = np.linspace(0.0, 2 * np.pi, segments + 1)
    T, P = np.meshgrid(th, ph, indexing="ij")
    pos = np.stack([np.sin(T) * np.cos(P), np.cos(T), np.sin(T) * np.sin(P)], axis=-1).reshape(-1, 3)
    idx = []
    w = segments + 1
    for r in range(rings):
        for s in range(segments):
            a, b = r * w + s, (r + 1) * w + s
            if r > 0:
                idx += [a, a + 1, b]      # counter-clockwise seen from outside
            if r < rings - 1:
                idx += [a + 1, b + 1, b]
    pos = pos.astype(np.float32)
    return pos, pos.copy(), np.asarray(idx, dtype=np.uint32)


def uv_sphere_texcoords(segments: int = 48, rings: int = 24):
    """(uv (V, 2) float32, tangents (V, 4) float32) of :func:`uv_sphere`'s vertices (same order).

    ``u = φ / 2π`` (around +y, one seam column duplicated), ``v = θ / π`` (0 at the top, +y: glTF's UV
    origin is the image's top left); the tangent is the unit ``∂P/∂u`` direction ``(−sin φ, 0, cos φ)``
    (defined at the poles too) with ``w = +1``: glTF's bitangent ``cross(N, T) · w`` is then the unit
    ``∂P/∂v`` direction ``(cos θ cos φ, −sin θ, cos θ sin φ)`` (glTF 2.0 §3.7.2.1), so a map in (u, v)
    is placed consistently with its tangent frame."""
    th = np.linspace(0.0, np.pi, rings + 1)
    ph = np.linspace(0.0, 2 * np.pi, segments + 1)
    T, P = np.meshgrid(th, ph, indexing="ij")
    uv = np.stack([P / (2 * np.pi), T / np.pi], axis=-1).reshape(-1, 2)
    tan = np.stack([-np.sin(P), np.zeros_like(P), np.cos(P), np.ones_like(P)], axis=-1).reshape(-1, 4)
    return uv.astype(np.float32), tan.astype(np.float32)


def gltf_document(fit: OpenPBRFit, name: str):
    """(glTF JSON dict, binary buffer bytes) of the sphere (positions, normals, UVs, tangents) with the
    fitted material."""
    pos, nrm, idx = uv_sphere()
    uv, tan = uv_sphere_texcoords()
    blob = pos.tobytes() + nrm.tobytes() + idx.tobytes() + uv.tobytes() + tan.tobytes()
    c = [float(x) for x in fit.base_color]
    mat = {
        "name": str(name),
        "pbrMetallicRoughness": {"baseColorFactor": c + [1.0], "metallicFactor": float(fit.base_metalness),
                                 "roughnessFactor": float(fit.specular_roughness)},
        "extensions": {
            "KHR_materials_clearcoat": {"clearcoatFactor": 1.0 if fit.coat_ior > 1.0 else 0.0,
                                        "clearcoatRoughnessFactor": float(fit.coat_roughness)},
            # glTF's base index is against air, not the coat: the fit's relative index
            "KHR_materials_ior": {"ior": float(max(fit.specular_ior_relative, 1.0))},
            "KHR_materials_specular": {"specularFactor": 1.0 if fit.specular_ior_relative > 1.0 else 0.0,
                                       "specularColorFactor": [float(x) for x in fit.specular_color]},
        },
        "extras": {"flakedb_fit": fit.to_dict()},
    }
    used = list(EXTENSIONS)
    if fit.thin_film_thickness_nm > 0:
        t, n_f = (float(x) for x in fit.film_relative_to_air())        # glTF's film is in air
        mat["extensions"]["KHR_materials_iridescence"] = {
            "iridescenceFactor": 1.0, "iridescenceIor": max(n_f, 1.0),
            "iridescenceThicknessMinimum": t, "iridescenceThicknessMaximum": t}   # no texture: the maximum is used
        used.append("KHR_materials_iridescence")
    n_pos = pos.nbytes
    doc = {
        "asset": {"version": "2.0", "generator": "flakedb export-openpbr"},
        "extensionsUsed": used,
        "scene": 0, "scenes": [{"nodes": [0]}],
        "nodes": [{"mesh": 0, "name": str(name)}],
        "meshes": [{"primitives": [{"attributes": {"POSITION": 0, "NORMAL": 1, "TEXCOORD_0": 3, "TANGENT": 4},
                                    "indices": 2, "material": 0}]}],
        "materials": [mat],
        "buffers": [{"byteLength": len(blob)}],
        "bufferViews": [
            {"buffer": 0, "byteOffset": 0, "byteLength": n_pos, "target": 34962},
            {"buffer": 0, "byteOffset": n_pos, "byteLength": nrm.nbytes, "target": 34962},
            {"buffer": 0, "byteOffset": 2 * n_pos, "byteLength": idx.nbytes, "target": 34963},
            {"buffer": 0, "byteOffset": 2 * n_pos + idx.nbytes, "byteLength": uv.nbytes, "target": 34962},
            {"buffer": 0, "byteOffset": 2 * n_pos + idx.nbytes + uv.nbytes, "byteLength": tan.nbytes,
             "target": 34962},
        ],
        "accessors": [
            {"bufferView": 0, "componentType": 5126, "count": len(pos), "type": "VEC3",
             "min": pos.min(axis=0).tolist(), "max": pos.max(axis=0).tolist()},
            {"bufferView": 1, "componentType": 5126, "count": len(nrm), "type": "VEC3"},
            {"bufferView": 2, "componentType": 5125, "count": len(idx), "type": "SCALAR"},
            {"bufferView": 3, "componentType": 5126, "count": len(uv), "type": "VEC2"},
            {"bufferView": 4, "componentType": 5126, "count": len(tan), "type": "VEC4"},
        ],
    }
    return doc, blob


def write_gltf(path, fit: OpenPBRFit, name: str) -> Path:
    """``.glb`` (binary: header, JSON chunk, BIN chunk, each 4-byte aligned; glTF 2.0 §4.4) when the
    suffix is ``.glb``, else a ``.gltf`` with the buffer as a base64 data URI.

    Read back without ``pygltflib``: the GLB header's magic, version and total length, and the material
    of the JSON chunk:

    >>> import struct, tempfile
    >>> fit = OpenPBRFit((0.8, 0.5, 0.2), 1.0, 0.3, 1.5, 0.0)
    >>> b = write_gltf(Path(tempfile.mkdtemp()) / "silver.glb", fit, "silver").read_bytes()
    >>> magic, version, length = struct.unpack("<4sII", b[:12])
    >>> n_json, kind = struct.unpack("<I4s", b[12:20])
    >>> mat = json.loads(b[20:20 + n_json])["materials"][0]
    >>> magic, version, length == len(b), kind, mat["pbrMetallicRoughness"]["baseColorFactor"]
    (b'glTF', 2, True, b'JSON', [0.8, 0.5, 0.2, 1.0])
    >>> OpenPBRFit.from_dict(mat["extras"]["flakedb_fit"]) == fit
    True
    """
    path = Path(path)
    doc, blob = gltf_document(fit, name)
    with atomic_path(path, suffix="") as tmp:
        if path.suffix.lower() == ".glb":
            js = json.dumps(doc, separators=(",", ":")).encode("utf-8")
            js += b" " * (-len(js) % 4)
            bin_ = blob + b"\0" * (-len(blob) % 4)
            total = 12 + 8 + len(js) + 8 + len(bin_)
            data = (struct.pack("<III", 0x46546C67, 2, total) + struct.pack("<II", len(js), 0x4E4F534A) + js
                    + struct.pack("<II", len(bin_), 0x004E4942) + bin_)
            Path(tmp).write_bytes(data)
        else:
            doc["buffers"][0]["uri"] = "data:application/octet-stream;base64," + base64.b64encode(blob).decode("ascii")
            Path(tmp).write_text(json.dumps(doc, indent=1) + "\n", encoding="utf-8")
    return path


# --------------------------------------------------------------------------------------------
# What three.js (r187, WebGL MeshPhysicalMaterial) renders of the file under a DirectionalLight
# --------------------------------------------------------------------------------------------
#: three.js's minimum perceptual roughness of the base lobe and the clearcoat (lights_physical_fragment)
THREE_MIN_ROUGHNESS = 0.045


def threejs_schlick(f0, f90, cos):
    """three.js's ``F_Schlick`` (common.glsl): ``f0 (1 - w) + f90 w`` with Epic's spherical-Gaussian
    ``w = 2^((-5.55473 c - 6.98316) c)`` in place of Schlick's ``(1 - c)^5`` (≤ 0.006 apart).

    >>> round(float(threejs_schlick(0.04, 1.0, 1.0)), 5), round(float(threejs_schlick(0.04, 1.0, 0.0)), 5)
    (0.04016, 1.0)
    """
    c = np.asarray(cos, float)
    w = np.exp2((-5.55473 * c - 6.98316) * c)
    return np.asarray(f0, float) * (1.0 - w) + np.asarray(f90, float) * w


def threejs_coat_fresnel(mu_v):
    """The clearcoat's Fresnel in three.js: :func:`threejs_schlick` with F0 0.04 (index 1.5, fixed
    by ``KHR_materials_clearcoat``) and F90 1.  It scales everything under the coat by
    ``1 - F(μ_v)`` (the view end only) and, in an environment of uniform radiance L, adds
    ``L (F0 A + B)`` (its DFG table at the coat's roughness ≈ this F for a smooth coat)."""
    return threejs_schlick(0.04, 1.0, mu_v)


def _ggx_V_D(alpha, mu_v, mu_l, cos_h):
    """three.js's ``V_GGX_SmithCorrelated · D_GGX`` (lights_physical_pars): the height-correlated
    Smith visibility ``0.5 / (μ_l sqrt(α² + (1 - α²) μ_v²) + μ_v sqrt(α² + (1 - α²) μ_l²))`` times
    ``α² / (π (cos²θ_h (α² - 1) + 1)²)``; ``alpha`` = perceptual roughness²."""
    a2 = alpha * alpha
    V = 0.5 / np.maximum(mu_l * np.sqrt(a2 + (1 - a2) * mu_v ** 2) + mu_v * np.sqrt(a2 + (1 - a2) * mu_l ** 2), 1e-6)
    return V * a2 / (np.pi * (cos_h ** 2 * (a2 - 1.0) + 1.0) ** 2)


def threejs_sun_image(fit: OpenPBRFit, size: int = 32, direction=(0.0, 0.0, 1.0), irradiance: float = 1.0,
                      extent: float = 1.05, pixel_size: float | None = None) -> np.ndarray:
    """(size, size, 3) image that three.js r187 renders of :func:`gltf_document` on the unit sphere
    under one ``DirectionalLight`` of intensity ``irradiance`` along ``direction``, no environment,
    at pixel centres in the frame of :func:`flakedb.export.blender.render_cycles_sphere` (row 0 at
    the top), the way its shaders evaluate ``MeshPhysicalMaterial`` (``RE_Direct_Physical``,
    ``BRDF_GGX``, ``BRDF_GGX_Clearcoat``, meshphysical.glsl), with c the base colour, m the
    metalness, s the specular colour, k the specular factor, n the ior and
    F0 = min(((n - 1) / (n + 1))² s, 1) k::

        L = [(1 - F_c(μ_v)) (f_spec + f_diff) + F_c(cos θ_d) V D(α_c)] μ_l E
        f_spec = F(mix(F0, c, m), mix(k, 1, m); cos θ_d) V D(α) (1 + mix(F0, c, m) (1/E_ss(r, μ_v) - 1))
        f_diff = c (1 - m) / π (1 - F(F0, mix(k, 1, m); cos θ_d))

    F = :func:`threejs_schlick`, F_c = :func:`threejs_coat_fresnel`, V D = :func:`_ggx_V_D`, E_ss the
    GGX albedo with F = 1 (three.js reads it from its 16 x 16 DFG table; here
    :func:`flakedb.export.blender.ggx_lobe_averages`), α = r², r = min(max(r_fit, 0.045) + g, 1) and
    α_c likewise from the coat's roughness: three.js adds ``g``, the largest screen-space
    derivative of the normal (``geometryRoughness``), ``pixel_size`` (default 2 extent / size) times
    max(1, |x|/z, |y|/z) on the sphere.  Where the fit and three.js differ: the coat takes
    ``1 - F_c(μ_v)`` at the view end only (the model: both ends) with Schlick's F (the model: the
    exact F(θ; η_c)); the metal is Schlick to the base colour (the model: F82 with the edge tint
    s); the lobe's tint s is on F0 only (the model: the whole Fresnel curve) and the lobe gets the
    multiple-scattering factor; the diffuse is ``1 - F(cos θ_d)`` under the lobe (the model: the
    lobe's albedo at both ends).  Raises ValueError for a fit with a thin film (three.js's
    iridescence, Belcour & Barla 2017, is not modelled here).

    A white diffuse sphere: E cos θ / π:

    >>> img = threejs_sun_image(OpenPBRFit((1.0, 1.0, 1.0), 0.0, 1.0, 1.0, 0.0), size=8, extent=1.0)
    >>> bool(np.allclose(img[3:5, 3:5], np.sqrt(1 - 2 * 0.125 ** 2) / np.pi, rtol=1e-12))
    True
    """
    if fit.thin_film_thickness_nm > 0:
        raise ValueError(f"threejs_sun_image: a fit with a thin film ({fit.thin_film_thickness_nm} nm) is not "
                         f"modelled (three.js's KHR_materials_iridescence)")
    d = np.asarray(direction, float)
    d = d / np.linalg.norm(d)
    N, on = sphere_normals(size, extent)
    mu_v = N[..., 2]
    ok = on & (mu_v > 0)
    Nk, mv = N[ok], mu_v[ok]
    p = 2.0 * extent / size if pixel_size is None else float(pixel_size)
    g = p * np.maximum(1.0, np.abs(Nk[:, :2]).max(axis=1) / mv)
    c = np.asarray(fit.base_color, float)
    m = float(fit.base_metalness)
    n = max(float(fit.specular_ior_relative), 1.0)
    k = 1.0 if fit.specular_ior_relative > 1.0 else 0.0
    F0 = np.minimum(((n - 1) / (n + 1)) ** 2 * np.asarray(fit.specular_color, float), 1.0) * k
    f90 = k + (1.0 - k) * m
    F0b = F0 + (c - F0) * m
    r = np.minimum(max(float(fit.specular_roughness), THREE_MIN_ROUGHNESS) + g, 1.0)
    # E_ss on roughness nodes 0.01 apart, linear in between (E's slope in r is ≤ 1: ≤ 1e-5 off)
    r_nodes = np.arange(np.floor(r.min() / 0.01), np.ceil(r.max() / 0.01) + 1) * 0.01
    E_nodes = np.array([ggx_lobe_averages(float(x), mv, 1.5)[1] for x in r_nodes])       # (R, P)
    j = np.clip(np.searchsorted(r_nodes, r) - 1, 0, max(len(r_nodes) - 2, 0))
    t = np.clip((r - r_nodes[j]) / 0.01, 0.0, 1.0) if len(r_nodes) > 1 else np.zeros_like(r)
    cols = np.arange(len(r))
    E_ss = (1 - t) * E_nodes[j, cols] + t * E_nodes[np.minimum(j + 1, len(r_nodes) - 1), cols]
    msc = 1.0 + F0b[None, :] * (1.0 / E_ss[:, None] - 1.0)
    mu_l = np.clip(Nk @ d, 0.0, 1.0)
    h = d + np.array([0.0, 0.0, 1.0])
    h = h / np.linalg.norm(h)
    cos_h, cos_d = np.clip(Nk @ h, 0.0, 1.0), float(np.clip(h[2], 0.0, 1.0))
    f_spec = threejs_schlick(F0b, f90, cos_d)[None, :] * _ggx_V_D(r * r, mv, mu_l, cos_h)[:, None] * msc
    f_diff = (c * (1.0 - m) / np.pi * (1.0 - threejs_schlick(F0, f90, cos_d)))[None, :]
    f = f_spec + f_diff
    if fit.coat_ior > 1.0:
        rc = np.minimum(max(float(fit.coat_roughness), THREE_MIN_ROUGHNESS) + g, 1.0)
        f = (1.0 - threejs_coat_fresnel(mv))[:, None] * f + (
            threejs_coat_fresnel(cos_d) * _ggx_V_D(rc * rc, mv, mu_l, cos_h))[:, None]
    img = np.zeros((size, size, 3))
    img[ok] = f * (mu_l * irradiance)[:, None]
    return img
