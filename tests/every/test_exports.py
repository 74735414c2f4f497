"""Every catalogue species through every export route (issue #35; docs/renderers.md): the openpbr route (MaterialX
OpenPBR, USD, glTF / GLB, Blender script) and the cpa route (`flakedb export-cpa`: PNG table, MaterialX graph,
Blender node group, JSON fit) with the glint layer the texture model designs from the recipe's flakes.  Each file
is read back by its own library and validated (MaterialX's document validation against its standard library and
GLSL generation, USD's stage, pygltflib), carries no NaN or infinity, colours and the table (16-bit values in two 8-bit planes) lie in [0, 1],
and the exported paint's directional albedo at normal incidence is ≤ 1 (file and fit: energy conservation).

The fits depend on a species only through its BSDF, so the fast tier designs and writes the glint layer of every
species (from its recipe; the cpa fit of the carrier paint, made once, stands in for the species' own) and the slow
tier runs both routes end to end on the own tiny BSDF of two species per kind (`kind_representatives`; 4-13 s each:
all species took 200 s of a CI pass for the same code paths).

Guards against: a species whose BSDF or glint layer makes a route write NaN, an invalid document, an albedo > 1,
or a colour out of range; a flake-less species (pigment, tinter) whose paint cannot be exported.
"""

from __future__ import annotations

import functools
import json
import math
from pathlib import Path

import numpy as np
import pytest
import yaml

from flakedb.compose.orchestrate import compose
from flakedb.export import cpa, registry, sparkle
from flakedb.export.registry import export_cpa, export_openpbr
from flakedb.export.sparkle import SparkleLayer
from flakedb.paint.texture_inputs import texture_stack
from flakedb.texture.instruments import Observer
from flakedb.texture.model import sparkle_indices
from tests.every.cases import CARRIER, SPECIES, document, kind_representatives, particle, recipe_of, tiny


def _strict_json(text):
    def bad(c):
        raise AssertionError(f"{c} in an exported JSON")
    return json.loads(text, parse_constant=bad)


def _finite(obj, where):
    if isinstance(obj, bool) or obj is None or isinstance(obj, str):
        return
    if isinstance(obj, (int, float)):
        assert math.isfinite(obj), where
    elif isinstance(obj, dict):
        for k, v in obj.items():
            _finite(v, f"{where}.{k}")
    elif isinstance(obj, (list, tuple)):
        for i, v in enumerate(obj):
            _finite(v, f"{where}[{i}]")


@functools.lru_cache(maxsize=1)
def _mtlx_library():
    """MaterialX's standard libraries, loaded once per session."""
    import MaterialX as mx

    lib = mx.createDocument()
    mx.loadLibraries(mx.getDefaultDataLibraryFolders(), mx.getDefaultDataSearchPath(), lib)
    return lib


def _mtlx_valid(path, material=None):
    mx = pytest.importorskip("MaterialX", reason="materialx not installed (pip install 'flakedb[materialx]')")
    doc = mx.createDocument()
    mx.readFromXmlFile(doc, str(path))
    if material is not None:   # validation and GLSL generation of the graph (tests/mtlx_glsl.py)
        from tests.mtlx_glsl import validated_glsl
        assert len(validated_glsl(doc, material, "every")) > 1000
        return doc
    doc.importLibrary(_mtlx_library())
    ok, msg = doc.validate()
    assert ok, msg
    return doc


def _check_sparkle(d):
    sp = d["sparkle"]
    _finite(sp, "sparkle")
    assert 0.0 <= sp["share"] <= 1.0 and 0.0 < sp["occupancy"] <= 1.0
    assert sp["cell_um"] > 0 and sp["glint_alpha"] > 0 and sp["lobe_alpha"] > 0 and sp["lobe"] >= 1
    assert sp["node_inputs"]["cells_per_uv"] > 0


def _check_cpa(res, name, glsl=True):
    files = res["files"]
    d = _strict_json(Path(files["fit"]).read_text())
    _finite(d, "cpa")
    px = cpa.read_table_png(Path(files["image"]).read_bytes())
    assert np.all(np.isfinite(px)) and px.min() >= 0.0 and px.max() <= 1.0
    _mtlx_valid(files["materialx"], f"M_{name}" if glsl else None)
    compile(Path(files["blender"]).read_text(encoding="utf-8"), files["blender"], "exec")
    return d


def _albedo_at_most_one(fit):
    a = fit["error"]["albedo_0deg"]
    assert max(a["file"]) <= 1.0 and max(a["fit"]) <= 1.0 and min(a["file"]) >= 0.0 and min(a["fit"]) >= 0.0, a


@pytest.fixture(scope="module")
def carrier_fit(tmp_path_factory):
    """The cpa route run once on the carrier paint: its fit and the carrier's BSDF."""
    root = tmp_path_factory.mktemp("carrier")
    res = compose(recipe_of(document([particle(CARRIER)], name="carrier")), root / "c")
    out = export_cpa(res.paths["bsdf"], root / "e", name="carrier")
    return res.paths["bsdf"], cpa.CPAFit.from_dict(_strict_json(Path(out["files"]["fit"]).read_text()))


def _reference_row(species):
    """The texture model's row at the glint layer's reference geometry (flakedb.export.sparkle)."""
    stack, _ = texture_stack(tiny(species))
    obs = Observer("every", sparkle.REFERENCE_SPOT_UM, sparkle.REFERENCE_APERTURE_RAD, sparkle.REFERENCE_SOURCE_DEG,
                   light_deg=(sparkle.REFERENCE_LIGHT_DEG,), view_deg=0.0)
    return sparkle_indices(stack, obs, sparkle.REFERENCE_LIGHT_DEG)


def _sparkle_export(bsdf, out, rec_path, species, name="paint"):
    """export-cpa with the recipe's glint layer where the texture model predicts sparkle at the reference geometry
    (the layer's count is then the model's: above the fixed threshold, or for flakes that never reach it, above
    their own kind's); where it predicts none, the route refuses with the model's reason and writes nothing."""
    row = _reference_row(species)
    if not row["sparkle"]:
        with pytest.raises(ValueError, match="no sparkle layer to build") as exc:
            export_cpa(bsdf, out, name=name, sparkle_recipe=rec_path)
        assert row["no_sparkle_reason"] in str(exc.value)
        assert not Path(out).exists() or not any(Path(out).iterdir())
        return None, row
    res = export_cpa(bsdf, out, name=name, sparkle_recipe=rec_path)
    return res, row


@pytest.mark.parametrize("species", SPECIES)
def test_every_species_glint_layer_exports(species, carrier_fit, tmp_path, monkeypatch):
    """The cpa route with each species' recipe as the sparkle recipe (the texture model's glint layer), the carrier's
    fit standing in for the species' own (the fit reads only the BSDF: the slow test below fits each)."""
    bsdf, fit = carrier_fit
    rec_path = tmp_path / f"{species}.yaml"
    rec_path.write_text(yaml.safe_dump(document([particle(species)], name=f"every-{species}"), sort_keys=False))
    monkeypatch.setattr(registry, "fit_cpa", lambda b, source=None: fit)
    res, row = _sparkle_export(bsdf, tmp_path / "out", rec_path, species)
    if res is None:
        return
    d = _check_cpa(res, "paint", glsl=False)   # validated; GLSL generated in the slow test
    _check_sparkle(d)
    assert d["sparkle"]["lobe"] <= len(fit.alphas)
    ref = d["sparkle"]["reference"]
    want = row["glints_per_mm2_above_threshold"] or row["glints_per_mm2"]
    assert ref["glints_per_mm2_above_threshold"] == pytest.approx(want, rel=1e-12)
    # the calibration: the layer's own count above the reference threshold is the model's
    layer = SparkleLayer.from_dict(d["sparkle"])
    colour_Y = float(sparkle.Y_WEIGHTS @ np.asarray(fit.table, float)[layer.lobe, -1])
    n = sparkle.layer_glints_per_mm2(layer, colour_Y, ref["light_deg"], ref["source_half_angle_deg"],
                                     ref["glint_threshold_luminance_factor"])
    assert n == pytest.approx(want, rel=1e-9)


@pytest.mark.slow
@pytest.mark.parametrize("species", kind_representatives())
def test_every_kind_exports_end_to_end(species, tmp_path):
    rec = tiny(species)
    rec_path = tmp_path / f"{species}.yaml"
    rec_path.write_text(yaml.safe_dump(document([particle(species)], name=f"every-{species}"), sort_keys=False))
    res = compose(rec, tmp_path / "c")
    bsdf = res.paths["bsdf"]
    op = export_openpbr(bsdf, tmp_path / "openpbr", name="paint")
    f = op["fit"]
    _finite(f, "openpbr")
    _albedo_at_most_one(f)
    for k in ("base_color", "specular_color"):
        assert all(0.0 <= c <= 1.0 for c in f[k]), (k, f[k])
    files = op["files"]
    _mtlx_valid(files["materialx"])
    pytest.importorskip("pxr", reason="usd-core not installed (pip install 'flakedb[usd]')")
    from pxr import Usd

    stage = Usd.Stage.Open(files["usd"])
    assert stage and _strict_json(stage.GetRootLayer().customLayerData["flakedb_fit"])["error"] == f["error"]
    pygltflib = pytest.importorskip("pygltflib", reason="pygltflib not installed (pip install 'flakedb[gltf]')")
    for kind in ("gltf", "glb"):
        g = pygltflib.GLTF2().load(files[kind])
        base = g.materials[0].pbrMetallicRoughness.baseColorFactor
        assert all(math.isfinite(c) and 0.0 <= c <= 1.0 for c in base), base
    compile(Path(files["blender"]).read_text(encoding="utf-8"), files["blender"], "exec")
    c, _ = _sparkle_export(bsdf, tmp_path / "cpa", rec_path, species)
    if c is None:   # no sparkle predicted: the route without the glint layer
        c = export_cpa(bsdf, tmp_path / "cpa", name="paint")
    d = _check_cpa(c, "paint")
    if "sparkle" in d:
        _check_sparkle(d)
    if "albedo_0deg" in d.get("error", {}):
        _albedo_at_most_one(d)
