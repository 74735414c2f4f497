"""CxF3 output (flakedb.match.cxf_write, `compare --write-cxf`).

Guards against: a written file that flakedb's own reader reads differently from the prediction (a
spectrum at the wrong geometry or wavelength, values rounded on the way, CIELab under other
conditions than stated, an RGB-mode paint's colour lost), which `compare` against the file shows as a
ΔE above 0; a file written with values the schema cannot hold (StartWL outside 360–400 nm, a step
the reflectance list does not allow, reflectance outside (−0.1, 3), an illuminant outside its
enumeration), or with elements out of the schema's sequence order; and a --write-cxf over an input.
"""

import csv
import xml.etree.ElementTree as ET

import numpy as np
import pytest
from click.testing import CliRunner

from flakedb.cli.main import cli
from flakedb.colour.settings import E2539_GEOMETRIES
from flakedb.match.cxf import NS, read_cxf_target
from flakedb.match.cxf_write import format_cxf
from flakedb.match.fit import predict
from flakedb.paint.catalog import load_catalog
from flakedb.paint.recipe import parse_recipe
from tests.match.test_fit import TRUE, _text

#: CxF3_Core.xsd 3.0.018's sequences for the elements written (child order within each parent).
SEQUENCES = {
    "CxF": ["FileInformation", "Resources"],
    "FileInformation": ["Creator", "CreationDate", "Description"],
    "Resources": ["ObjectCollection", "ColorSpecificationCollection"],
    "Object": ["CreationDate", "ColorValues"],
    "ColorCIELab": ["L", "A", "B"],
    "ColorSpecification": ["TristimulusSpec", "MeasurementSpec"],
    "TristimulusSpec": ["Illuminant", "Observer", "Method"],
    "MeasurementSpec": ["MeasurementType", "GeometryChoice", "WavelengthRange"],
    "BRDFAngle": ["IlluminationAngle", "Aspecular"],
}


def _local(tag):
    return tag.split("}")[1]


def _compare_table(args, tmp_path):
    table = tmp_path / "table.csv"
    r = CliRunner().invoke(cli, ["compare", *args, "--table", str(table)])
    return r, list(csv.DictReader(table.open())) if table.exists() else []


@pytest.mark.parametrize("mode", ["spectral", "rgb"])
def test_compare_against_the_written_file_is_zero(tmp_path, mode):
    text = _text(**TRUE) if mode == "spectral" else _text(**TRUE).replace("mode: spectral", "mode: rgb")
    (tmp_path / "r.yaml").write_text(text)
    cxf = tmp_path / "p.cxf"
    r = CliRunner().invoke(cli, ["compare", str(tmp_path / "r.yaml"), "--write-cxf", str(cxf), "--geometries", "e2539"])
    assert r.exit_code == 0, r.output
    # the reader gets back exactly what was predicted: geometries, spectra (bit for bit), conditions
    catalog = load_catalog(None)
    pred = predict(parse_recipe(text, catalog=catalog), E2539_GEOMETRIES, catalog=catalog)
    t = read_cxf_target(cxf)
    np.testing.assert_array_equal(t.geometries, np.asarray(E2539_GEOMETRIES))
    obs, ill = ("10", "D65") if mode == "spectral" else ("2", "D65")
    assert (t.observer, t.illuminant, t.name, t.spectral) == (obs, ill, "two-species", mode == "spectral")
    if mode == "spectral":
        np.testing.assert_array_equal(t.reflectance, pred.rf)
        np.testing.assert_array_equal(t.wavelength_nm, pred.wavelength_nm)
    np.testing.assert_array_equal(t.lab_under(obs, ill), pred.lab(obs, ill))
    # compare against it: ΔE exactly 0 at every geometry, so a limit of 0 passes
    r, rows = _compare_table([str(tmp_path / "r.yaml"), "--target", str(cxf), "--max-de", "0"], tmp_path)
    assert r.exit_code == 0, r.output
    assert len(rows) == 11 and all(float(x["dE00"]) == 0.0 for x in rows)
    # the file follows the schema's sequence order and names every value's specification
    root = ET.parse(cxf).getroot()
    for el in root.iter():
        order = SEQUENCES.get(_local(el.tag))
        if order:
            kids = [_local(c.tag) for c in el]
            assert kids == [k for k in order if k in kids], (_local(el.tag), kids)
    ids = {cs.get("Id") for cs in root.iter(f"{{{NS}}}ColorSpecification")}
    assert {v.get("ColorSpecification") for v in root.iter(f"{{{NS}}}ColorCIELab")} == ids
    assert len(ids) == 11


def test_compare_write_cxf_refusals(tmp_path):
    (tmp_path / "r.yaml").write_text(_text(**TRUE))
    r = CliRunner().invoke(cli, ["compare", str(tmp_path / "r.yaml"), "--write-cxf", str(tmp_path / "r.yaml")])
    assert r.exit_code == 2 and "--write-cxf" in r.output and "is the input RECIPE" in r.output, r.output
    (tmp_path / "s.yaml").write_text(_text(**TRUE).replace("range_nm: [400, 700]", "range_nm: [420, 700]").replace(
        "step_nm: 20", "step_nm: 20"))
    out = tmp_path / "s.cxf"
    r = CliRunner().invoke(cli, ["compare", str(tmp_path / "s.yaml"), "--write-cxf", str(out)])
    assert r.exit_code == 2 and "starts at 420 nm" in r.output and "Traceback" not in r.output, r.output
    assert not out.exists()


def test_format_cxf_refuses_what_the_schema_cannot_hold():
    g = [(45.0, 15.0)]
    wl = np.arange(400.0, 701.0, 20.0)
    R = np.full((1, wl.size), 0.5)
    lab = [[50.0, 0.0, 0.0]]
    assert read_cxf_target(format_cxf(g, lab, R, wl)).reflectance.tolist() == R.tolist()
    with pytest.raises(ValueError, match=r"outside CxF3's range \(-0.1, 3\)"):
        format_cxf(g, lab, np.where(wl == 560, 3.2, R), wl)
    with pytest.raises(ValueError, match="step is 15 nm"):
        format_cxf(g, lab, R[:, :11], np.arange(400.0, 551.0, 15.0))
    with pytest.raises(ValueError, match="no CxF3 Illuminant"):
        format_cxf(g, lab, R, wl, illuminant="FL1")
    assert b"<cc:Illuminant>F11</cc:Illuminant>" in format_cxf(g, lab, R, wl, illuminant="FL11")
    with pytest.raises(ValueError, match="L\\* >= 0"):
        format_cxf(g, [[-1.0, 0.0, 0.0]])
