"""Traps of issue #37 on the export side, each a test that failed on the code before the fix.

- The exported glTF sphere had no UVs and no tangents: no texture, normal or flake map could be placed.
- `flakedb info` refused the .gltf / .glb and .usda files flakedb itself writes ("not a file kind flakedb
  knows").
"""

import base64
import json

import numpy as np
import pytest
from click.testing import CliRunner

from flakedb.cli.main import cli
from flakedb.export.gltf import uv_sphere, write_gltf
from flakedb.export.openpbr import OpenPBRFit
from flakedb.export.usd import write_usda

FIT = OpenPBRFit((0.8, 0.5, 0.2), 1.0, 0.3, 1.5, 0.0)


def _accessor(doc, blob, i):
    a = doc["accessors"][i]
    v = doc["bufferViews"][a["bufferView"]]
    n = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4}[a["type"]]
    dt = {5126: np.float32, 5125: np.uint32}[a["componentType"]]
    return np.frombuffer(blob, dt, count=a["count"] * n, offset=v["byteOffset"]).reshape(a["count"], n)


def test_gltf_sphere_has_uvs_and_a_consistent_tangent_frame(tmp_path):
    """Every triangle: the tangent (w = 1) is the direction of ∂P/∂u and cross(N, T)·w the direction of
    ∂P/∂v, both computed from the triangle's own positions and UVs (glTF 2.0 §3.7.2.1)."""
    p = write_gltf(tmp_path / "s.gltf", FIT, "s")
    doc = json.loads(p.read_text())
    blob = base64.b64decode(doc["buffers"][0]["uri"].split(",", 1)[1])
    attr = doc["meshes"][0]["primitives"][0]["attributes"]
    assert {"TEXCOORD_0", "TANGENT"} <= set(attr)
    P, N = _accessor(doc, blob, attr["POSITION"]).astype(float), _accessor(doc, blob, attr["NORMAL"]).astype(float)
    UV, T = _accessor(doc, blob, attr["TEXCOORD_0"]).astype(float), _accessor(doc, blob, attr["TANGENT"]).astype(float)
    idx = _accessor(doc, blob, doc["meshes"][0]["primitives"][0]["indices"]).reshape(-1, 3)
    assert np.all((UV >= 0) & (UV <= 1)) and np.allclose(T[:, 3], 1.0)
    np.testing.assert_allclose(np.linalg.norm(T[:, :3], axis=1), 1.0, atol=1e-6)
    np.testing.assert_allclose(np.sum(T[:, :3] * N, axis=1), 0.0, atol=1e-6)        # tangent ⟂ normal
    # per triangle: dP = [dP/du dP/dv] dUV  ->  solve for the two derivative vectors
    e1, e2 = P[idx[:, 1]] - P[idx[:, 0]], P[idx[:, 2]] - P[idx[:, 0]]
    d1, d2 = UV[idx[:, 1]] - UV[idx[:, 0]], UV[idx[:, 2]] - UV[idx[:, 0]]
    det = d1[:, 0] * d2[:, 1] - d1[:, 1] * d2[:, 0]
    dPdu = (e1 * d2[:, 1:2] - e2 * d1[:, 1:2]) / det[:, None]
    dPdv = (e2 * d1[:, 0:1] - e1 * d2[:, 0:1]) / det[:, None]
    c = idx[:, 0]
    t_mean = T[idx, :3].mean(axis=1)
    b_mean = (np.cross(N[idx], T[idx, :3]) * T[idx, 3:4]).mean(axis=1)
    cos_t = np.sum(t_mean * dPdu, 1) / (np.linalg.norm(t_mean, axis=1) * np.linalg.norm(dPdu, axis=1))
    cos_b = np.sum(b_mean * dPdv, 1) / (np.linalg.norm(b_mean, axis=1) * np.linalg.norm(dPdv, axis=1))
    assert cos_t.min() > 0.99 and cos_b.min() > 0.99, (cos_t.min(), cos_b.min(), c.size)
    pos, _, _ = uv_sphere()
    assert len(P) == len(pos)


@pytest.mark.parametrize("suffix", [".gltf", ".glb", ".usda"])
def test_info_reads_what_flakedb_exports(suffix, tmp_path):
    path = tmp_path / f"silver{suffix}"
    (write_usda if suffix == ".usda" else write_gltf)(path, FIT, "silver")
    r = CliRunner().invoke(cli, ["info", str(path)])
    assert r.exit_code == 0, r.output
    if suffix == ".usda":
        assert "UsdPreviewSurface" in r.output and "metallic = 1" in r.output
    else:
        assert "baseColor [0.8, 0.5, 0.2, 1.0]" in r.output and "TEXCOORD_0" in r.output
    js = json.loads(CliRunner().invoke(cli, ["info", "--json", str(path)]).output)
    assert js["kind"] == ("usda" if suffix == ".usda" else "gltf")
    # something else that starts like JSON is still refused in one line
    (tmp_path / "x.json").write_text('{"not": "gltf"}')
    r = CliRunner().invoke(cli, ["info", str(tmp_path / "x.json")])
    assert r.exit_code != 0 and "Traceback" not in r.output and "glTF 2.0" in r.output


def test_usd_sphere_has_texture_coordinates(tmp_path):
    """USD reads the layer with primvars:st on every vertex (USD's t up: the top of the sphere at t = 1)."""
    pxr = pytest.importorskip("pxr")
    from pxr import Usd, UsdGeom

    path = write_usda(tmp_path / "s.usda", FIT, "s")
    stage = Usd.Stage.Open(str(path))
    mesh = UsdGeom.Mesh(stage.GetPrimAtPath("/s/sphere"))
    st = UsdGeom.PrimvarsAPI(mesh).GetPrimvar("st")
    assert st and st.GetInterpolation() == "vertex"
    v, p = np.array(st.Get()), np.array(mesh.GetPointsAttr().Get())
    assert v.shape == (len(p), 2)
    top = p[:, 1] > 0.999
    assert np.allclose(v[top, 1], 1.0) and np.all((v >= 0) & (v <= 1)) and pxr is not None
