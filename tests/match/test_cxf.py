"""CxF3 targets (flakedb.match.cxf).

The files here are written by hand from the CxF3 core schema (CxF3_Core.xsd 3.0.018: Object /
ColorValues / ReflectanceSpectrum and ColorCIELab; ColorSpecification / MeasurementSpec /
GeometryChoice / MultiAngle / BRDFAngle; WavelengthRange; TristimulusSpec), not by a flakedb writer.
Guards against: spectra put at the wrong geometry or wavelength, percent/fraction confusion, CIELab
read under the wrong conditions, a value silently given to one of several BRDFAngles, out-of-plane
angles accepted, several objects read as one, entity-expansion bombs, and a CxF target that
`compare` reads differently from the same data as CSV.
"""

import textwrap

import numpy as np
import pytest
from click.testing import CliRunner

from flakedb.cli.main import cli
from flakedb.match.cxf import load_target, read_cxf_target
from flakedb.match.targets import TargetError, read_target
from tests.cases import basecoat_recipe

NS = 'xmlns:cc="http://colorexchangeformat.com/CxF3-core"'


def spec(sid, angles, start=400, inc=20, tristimulus=None):
    """A ColorSpecification with one BRDFAngle per (notation, illum, aspec[, azimuth])."""
    brdf = "".join(
        f'<cc:BRDFAngle Notation="{a[0]}"><cc:IlluminationAngle>{a[1]}</cc:IlluminationAngle>'
        f'<cc:Aspecular>{a[2]}</cc:Aspecular>' + (f"<cc:Azimuth>{a[3]}</cc:Azimuth>" if len(a) > 3 else "")
        + "</cc:BRDFAngle>" for a in angles)
    ts = ""
    if tristimulus:
        ts = (f"<cc:TristimulusSpec><cc:Illuminant>{tristimulus[1]}</cc:Illuminant>"
              f"<cc:Observer>{tristimulus[0]}</cc:Observer><cc:Method>E308_Table5</cc:Method></cc:TristimulusSpec>")
    wr = f'<cc:WavelengthRange StartWL="{start}" Increment="{inc}"/>' if start is not None else ""
    return (f'<cc:ColorSpecification Id="{sid}">{ts}<cc:MeasurementSpec>'
            f"<cc:MeasurementType>Spectrum_Reflectance</cc:MeasurementType>"
            f"<cc:GeometryChoice><cc:MultiAngle>{brdf}</cc:MultiAngle></cc:GeometryChoice>{wr}"
            f"</cc:MeasurementSpec></cc:ColorSpecification>")


def cxf(objects, specs):
    return textwrap.dedent(f"""\
        <?xml version="1.0" encoding="UTF-8"?>
        <cc:CxF {NS}>
          <cc:FileInformation><cc:Creator>flakedb test</cc:Creator></cc:FileInformation>
          <cc:Resources>
            <cc:ObjectCollection>{objects}</cc:ObjectCollection>
            <cc:ColorSpecificationCollection>{specs}</cc:ColorSpecificationCollection>
          </cc:Resources>
        </cc:CxF>
        """).encode()


def obj(name, values):
    return (f'<cc:Object ObjectType="Standard" Name="{name}" Id="{name}-id">'
            f"<cc:CreationDate>2026-12-01T00:00:00Z</cc:CreationDate><cc:ColorValues>{values}</cc:ColorValues>"
            f"</cc:Object>")


def refl(sid, values, name=None):
    nm = f' Name="{name}"' if name else ""
    return f'<cc:ReflectanceSpectrum ColorSpecification="{sid}"{nm}>{" ".join(f"{v:.6g}" for v in values)}</cc:ReflectanceSpectrum>'


def lab(sid, L, a, b, name=None):
    nm = f' Name="{name}"' if name else ""
    return f'<cc:ColorCIELab ColorSpecification="{sid}"{nm}><cc:L>{L}</cc:L><cc:A>{a}</cc:A><cc:B>{b}</cc:B></cc:ColorCIELab>'


WL = np.arange(400.0, 701.0, 20.0)                     # 16 values from StartWL 400, Increment 20
R1 = 0.2 + 0.5 * (WL - 400) / 300                        # distinct spectra per geometry
R2 = 0.6 - 0.4 * (WL - 400) / 300
R3 = np.full(WL.size, 0.35)
GEOMS = [("45as15", 45, 15), ("45as110", 45, 110), ("15as-45", 15, -45)]


def one_angle_per_spec():
    specs = "".join(spec(f"CS{i}", [g]) for i, g in enumerate(GEOMS))
    values = refl("CS1", R2) + refl("CS0", R1) + refl("CS2", R3)   # file order differs from the spec order
    return cxf(obj("panel", values), specs)


def test_spectra_one_brdfangle_per_specification():
    t = read_cxf_target(one_angle_per_spec())
    assert t.spectral and t.name == "panel"
    np.testing.assert_array_equal(t.wavelength_nm, WL)
    by_geom = {tuple(g): r for g, r in zip(t.geometries.tolist(), t.reflectance)}
    np.testing.assert_allclose(by_geom[(45.0, 15.0)], R1, atol=1e-6)
    np.testing.assert_allclose(by_geom[(45.0, 110.0)], R2, atol=1e-6)
    np.testing.assert_allclose(by_geom[(15.0, -45.0)], R3, atol=1e-6)
    # the same numbers as a CSV target give the same colour (one Target structure, one colorimetry)
    rows = [f"{g[0]:g},{g[1]:g}," + ",".join(f"{v:.6g}" for v in r) for g, r in zip(t.geometries, t.reflectance)]
    csv = "illumination_deg,aspecular_deg," + ",".join(f"R_{w:g}" for w in WL) + "\n" + "\n".join(rows) + "\n"
    t_csv = read_target(csv)
    for obs, ill in (("2", "D65"), ("10", "A")):
        np.testing.assert_allclose(t.lab_under(obs, ill), t_csv.lab_under(obs, ill), atol=1e-9)


def test_several_brdfangles_matched_by_name_and_lab_conditions():
    specs = spec("MA", GEOMS, start=None, tristimulus=("10_Degree", "A"))
    values = lab("MA", 61.0, 2.0, 30.0, "45as110") + lab("MA", 80.0, 1.0, 20.0, "45as15") + lab("MA", 70, -1, 25, "15as-45")
    t = read_cxf_target(cxf(obj("std", values), specs))
    assert not t.spectral and t.observer == "10" and t.illuminant == "A"
    by_geom = {tuple(g): v for g, v in zip(t.geometries.tolist(), t.lab)}
    assert by_geom[(45.0, 110.0)].tolist() == [61.0, 2.0, 30.0]
    assert by_geom[(45.0, 15.0)].tolist() == [80.0, 1.0, 20.0]
    with pytest.raises(TargetError, match="needs spectral"):   # CIELab values are facts under 10° / A only
        t.lab_under("2", "D65")


@pytest.mark.parametrize("case, message", [
    ("unnamed", "Name None is none of their Notations"),
    ("azimuth", "azimuth_deg 90 puts the detector at 97.05° from the normal"),
    ("two_objects", "2 objects have multi-angle values"),
    ("no_grid", "no MeasurementSpec/WavelengthRange"),
    ("bad_increment", "Increment 3 nm"),
    ("not_cxf", "not CxF in the CxF3 namespace"),
    ("bomb", "DOCTYPE / ENTITY declaration"),
    ("specular", "specular direction"),
    ("lab_without_conditions", "without TristimulusSpec"),
])
def test_refusals(case, message):
    if case == "unnamed":
        data = cxf(obj("p", lab("MA", 50, 0, 0)), spec("MA", GEOMS, tristimulus=("2_Degree", "D65")))
    elif case == "azimuth":
        # an out-of-plane geometry is read (tests/colour/test_geometry.py); one whose detector is below the surface is not
        data = cxf(obj("p", refl("S", R1)), spec("S", [("45as100az90", 45, 100, 90)]))
    elif case == "two_objects":
        data = cxf(obj("a", refl("S", R1)) + obj("b", refl("S", R2)), spec("S", [GEOMS[0]]))
    elif case == "no_grid":
        data = cxf(obj("p", refl("S", R1)), spec("S", [GEOMS[0]], start=None))
    elif case == "bad_increment":
        data = cxf(obj("p", refl("S", R1)), spec("S", [GEOMS[0]], inc=3))
    elif case == "not_cxf":
        data = b'<?xml version="1.0"?><CxF xmlns="http://example.com/other"/>'
    elif case == "bomb":
        ents = '<!ENTITY a0 "xxxxxxxxxx">' + "".join(f'<!ENTITY a{i} "{("&a%d;" % (i - 1)) * 10}">' for i in range(1, 10))
        data = f'<?xml version="1.0"?><!DOCTYPE cc:CxF [{ents}]><cc:CxF {NS}><cc:Resources>&a9;</cc:Resources></cc:CxF>'.encode()
    elif case == "specular":
        data = cxf(obj("p", refl("S", R1)), spec("S", [("45as0", 45, 0)]))
    else:
        data = cxf(obj("p", lab("S", 50, 0, 0)), spec("S", [GEOMS[0]]))
    with pytest.raises(TargetError, match=message):
        read_cxf_target(data)


def test_object_choice(tmp_path):
    data = cxf(obj("a", refl("S", R1)) + obj("b", refl("S", R2)), spec("S", [GEOMS[0]]))
    np.testing.assert_allclose(read_cxf_target(data, "b").reflectance[0], R2, atol=1e-6)
    np.testing.assert_allclose(read_cxf_target(data, "a-id").reflectance[0], R1, atol=1e-6)   # by Id too
    with pytest.raises(TargetError, match="no object named 'c'"):
        read_cxf_target(data, "c")
    p = tmp_path / "t.cxf"
    p.write_bytes(data)
    assert load_target(p, object_name="b").name == "b"
    with pytest.raises(TargetError, match="only a .cxf target"):
        load_target(tmp_path / "t.csv", object_name="b")


def test_compare_reads_a_cxf_target(tmp_path):
    """End to end: the recipe's own prediction, laid out by hand as CxF3, passes `compare` at ΔE00 ≈ 0,
    and a CxF with one geometry's spectrum scaled by 0.9 fails there and only there."""
    recipe = basecoat_recipe("cxf-check", ["{species: metallic, volume_fraction: 0.04, orientation_alpha: 0.3}"])
    (tmp_path / "r.yaml").write_text(recipe)
    r = CliRunner().invoke(cli, ["compare", str(tmp_path / "r.yaml"), "--geometries", "e2194",
                                 "--write-csv", str(tmp_path / "p.csv")])
    assert r.exit_code == 0, r.output
    p = read_target(tmp_path / "p.csv")
    assert np.array_equal(p.wavelength_nm, WL)
    names = [f"{g[0]:g}as{g[1]:g}" for g in p.geometries]
    specs = "".join(spec(f"S{i}", [(nm, g[0], g[1])]) for i, (nm, g) in enumerate(zip(names, p.geometries)))
    for scale, expect in ((1.0, 0), (0.9, 1)):
        values = "".join(refl(f"S{i}", r * (scale if i == 2 else 1.0)) for i, r in enumerate(p.reflectance))
        (tmp_path / "t.cxf").write_bytes(cxf(obj("panel", values), specs))
        r = CliRunner().invoke(cli, ["compare", str(tmp_path / "r.yaml"), "--target", str(tmp_path / "t.cxf"),
                                     "--max-de", "0.05"])
        assert r.exit_code == expect, r.output
        if expect:
            assert "FAIL at 1 geometry" in r.output and f"{p.geometries[2][1]:g}°" in r.output, r.output
    r = CliRunner().invoke(cli, ["compare", str(tmp_path / "r.yaml"), "--target", str(tmp_path / "t.csv"),
                                 "--cxf-object", "panel"])
    assert r.exit_code == 2 and "only a .cxf target" in r.output, r.output


def test_a_10_degree_file_is_read_at_10_degrees(tmp_path):
    """The issue's done-when: a spectral CxF3 file whose TristimulusSpec states the 10° observer (and
    illuminant A) is compared under 10° / A, not at 2° / D65; the caller's choice still overrides, and a
    file that states nothing gets the defaults, recorded as assumed."""
    from flakedb.colour.settings import DEFAULT_ILLUMINANT, DEFAULT_OBSERVER
    from flakedb.colour.tolerance import delta_E_2000, reflectance_to_Lab

    specs = "".join(spec(f"CS{i}", [g], tristimulus=("10_Degree", "A")) for i, g in enumerate(GEOMS))
    data = cxf(obj("panel", refl("CS0", R1) + refl("CS1", R2) + refl("CS2", R3)), specs)
    t = read_cxf_target(data)
    assert (t.observer, t.illuminant) == ("10", "A") and "assumed" not in t.notes
    by_geom = {tuple(g): lab for g, lab in zip(t.geometries.tolist(), t.lab_under())}
    np.testing.assert_allclose(by_geom[(45.0, 15.0)], reflectance_to_Lab(R1, WL, "10", "A"), atol=1e-9)
    # the 2° / D65 colour of this spectrum is visibly different: reading the file at 2° would be noticed
    assert delta_E_2000(reflectance_to_Lab(R1, WL, "10", "A"), reflectance_to_Lab(R1, WL, "2", "D65")) > 1.0
    assert read_cxf_target(data, observer="2").observer == "2"
    # and a 2° file is read at 2° (whatever the default is, each file's own observer is the one used)
    specs2 = "".join(spec(f"CS{i}", [g], tristimulus=("2_Degree", "D65")) for i, g in enumerate(GEOMS))
    t2 = read_cxf_target(cxf(obj("panel", refl("CS0", R1) + refl("CS1", R2) + refl("CS2", R3)), specs2))
    assert (t2.observer, t2.illuminant) == ("2", "D65")
    plain = read_cxf_target(one_angle_per_spec())
    assert (plain.observer, plain.illuminant) == (DEFAULT_OBSERVER, DEFAULT_ILLUMINANT) and "assumed" in plain.notes
    mixed = "".join(spec(f"CS{i}", [g], tristimulus=(("10_Degree", "2_Degree")[i % 2], "D65"))
                    for i, g in enumerate(GEOMS))
    with pytest.raises(TargetError, match="different observers"):
        read_cxf_target(cxf(obj("panel", refl("CS0", R1) + refl("CS1", R2) + refl("CS2", R3)), mixed))
