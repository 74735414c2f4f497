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
library only; the tests read it back with ``pygltflib``.
"""

from __future__ import annotations

import base64
import json
import struct
from pathlib import Path

import numpy as np

from flakedb.atomic import atomic_path
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


def gltf_document(fit: OpenPBRFit, name: str):
    """(glTF JSON dict, binary buffer bytes) of the sphere with the fitted material."""
    pos, nrm, idx = uv_sphere()
    blob = pos.tobytes() + nrm.tobytes() + idx.tobytes()
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
        "meshes": [{"primitives": [{"attributes": {"POSITION": 0, "NORMAL": 1}, "indices": 2, "material": 0}]}],
        "materials": [mat],
        "buffers": [{"byteLength": len(blob)}],
        "bufferViews": [
            {"buffer": 0, "byteOffset": 0, "byteLength": n_pos, "target": 34962},
            {"buffer": 0, "byteOffset": n_pos, "byteLength": nrm.nbytes, "target": 34962},
            {"buffer": 0, "byteOffset": 2 * n_pos, "byteLength": idx.nbytes, "target": 34963},
        ],
        "accessors": [
            {"bufferView": 0, "componentType": 5126, "count": len(pos), "type": "VEC3",
             "min": pos.min(axis=0).tolist(), "max": pos.max(axis=0).tolist()},
            {"bufferView": 1, "componentType": 5126, "count": len(nrm), "type": "VEC3"},
            {"bufferView": 2, "componentType": 5125, "count": len(idx), "type": "SCALAR"},
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
