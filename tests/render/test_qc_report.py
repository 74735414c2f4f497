"""The one-page QC report (flakedb.render.qc_report, `flakedb report`).

Guards against: a PDF that does not open (no page tree, a broken cross-reference table, more than one page),
a PNG that is not the page, a page that does not show the target (its points, its name) or the verdict,
tolerance bands drawn somewhere else than target ± band, and outputs written half (one file without the
other) or over an input.
"""

import numpy as np
import pytest
import yaml
from click.testing import CliRunner
from PIL import Image

from flakedb.cli.main import cli
from flakedb.colour.bands import coordinate_bands
from flakedb.colour.settings import E2194_GEOMETRIES
from flakedb.colour.tolerance import PerAngleLimits, parse_formula, shade_words
from flakedb.render.qc_report import PAGE_INCHES, PNG_DPI, QCPage, qc_figure, write_qc_report
from tests.render.pdf_text import pdf_structure, pdf_texts

G = np.asarray(E2194_GEOMETRIES, float)
WL = np.arange(400.0, 701.0, 20.0)


def _page(shift=(1.2, 0.3, -0.4), formula="de00", texture=()):
    asp = G[:, 1]
    lt = np.stack([70.0 - 0.35 * asp, 1.0 + 0.03 * asp, 20.0 - 0.1 * asp], axis=-1)
    lab = lt + np.asarray(shift) * np.linspace(0.2, 1.0, len(G))[:, None]
    f = parse_formula(formula)
    ev = PerAngleLimits(default=1.0, limits={(45.0, 110.0): 2.0}, formula=f).evaluate(G, lt, lab)
    R = np.array([0.3 + 0.1 * np.sin(WL / 60.0 + k) for k in range(len(G))])
    return QCPage(recipe="silver", target="A-17", geometries=G, lab=lab, lab_target=lt, formula=ev["formula"],
                  de=ev["value"], limit=ev["limit"], passed=ev["passed"], band=coordinate_bands(f, lt, ev["limit"]),
                  shade=shade_words(lt, lab), conditions="D65/10°", wavelength_nm=WL, reflectance=R,
                  target_wavelength_nm=WL, target_reflectance=0.95 * R, texture=list(texture))


def test_pdf_opens_with_one_page_and_shows_target_and_verdict(tmp_path):
    page = _page()
    assert page.verdict == "FAIL"
    fig, pdf, png = write_qc_report(page, tmp_path / "r.pdf", tmp_path / "r.png")
    s = pdf_structure(pdf.read_bytes())
    assert s["pages"] == 1 and len(s["kids"]) == 1
    np.testing.assert_allclose(s["mediabox"][0], [0, 0, 72 * PAGE_INCHES[0], 72 * PAGE_INCHES[1]], atol=0.01)
    assert s["info"]["Title"] == "flakedb QC report: silver vs A-17" and s["info"]["Subject"] == page.summary()
    texts = "\n".join(pdf_texts(pdf.read_bytes()))
    w = page.worst
    assert "FAIL" in texts and "QC report: silver vs A-17" in texts and "A-17, 45°" in texts
    assert f"worst geometry 45as{G[w, 1]:g}: dE00 {page.de[w]:.2f}" in texts


def test_png_is_the_page(tmp_path):
    """The PNG decodes to the page's size at PNG_DPI and is, pixel for pixel, the figure drawn at that
    resolution."""
    fig, pdf, png = write_qc_report(_page(), tmp_path / "r.pdf", tmp_path / "r.png")
    img = np.asarray(Image.open(png).convert("RGBA"))
    assert img.shape[:2] == (int(PAGE_INCHES[1] * PNG_DPI), int(PAGE_INCHES[0] * PNG_DPI))   # matplotlib truncates
    fig.set_dpi(PNG_DPI)
    fig.canvas.draw()
    np.testing.assert_array_equal(img, np.asarray(fig.canvas.buffer_rgba()))
    assert np.ptp(img[..., :3]) > 0          # not a blank page


def test_page_draws_the_target_its_band_and_the_verdict():
    page = _page()
    fig = qc_figure(page)
    lt, band = page.lab_target, page.band
    for c, name in enumerate(("L*", "a*", "b*")):
        ax = next(a for a in fig.axes if a.get_ylabel() == name and a.get_xlabel() == "aspecular angle (°)")
        line = next(ln for ln in ax.get_lines() if ln.get_label() == "A-17, 45°")
        assert line.get_linestyle() == "--"
        np.testing.assert_array_equal(line.get_ydata(), lt[:, c])          # E2194: 45° only, aspecular order
        poly = ax.collections[0].get_paths()[0].vertices                  # the fill_between band
        for k, x in enumerate(G[:, 1]):
            ys = poly[np.isclose(poly[:, 0], x), 1]
            np.testing.assert_allclose([ys.min(), ys.max()], lt[k, c] + band[k, c], rtol=1e-12)
    ax_de = next(a for a in fig.axes if a.get_title().startswith("dE00 per geometry"))
    heights = [p.get_height() for p in ax_de.patches]
    np.testing.assert_array_equal(heights, page.de)
    texts = [t.get_text() for a in fig.axes for t in a.texts]
    assert "FAIL" in texts
    assert any(f"worst geometry {G[page.worst, 0]:g}as{G[page.worst, 1]:g}" in t for t in texts)
    assert any(page.shade[page.worst] in t for t in texts)


def test_verdict_and_worst():
    near = _page(shift=(0.05, 0.02, 0.0))
    assert near.verdict == "PASS" and near.summary().startswith("PASS: 0 of 6")
    far = _page()
    ratio = far.de / far.limit
    assert far.worst == int(np.argmax(ratio)) and far.summary().startswith("FAIL")
    tex = [{"index": "graininess", "predicted": 0.5, "target": 0.2, "tolerance": 0.02, "passed": False}]
    assert _page(shift=(0.05, 0.02, 0.0), texture=tex).verdict == "FAIL"
    tex_free = [{"index": "graininess", "predicted": 0.5, "target": None, "tolerance": None, "passed": None}]
    assert _page(shift=(0.05, 0.02, 0.0), texture=tex_free).verdict == "PASS"


@pytest.fixture(scope="module")
def paint(tmp_path_factory):
    from flakedb.match.fit import predict, recipe_from_doc
    from flakedb.match.targets import write_target
    from tests.match.test_fit import _text

    d = tmp_path_factory.mktemp("report")
    doc = yaml.safe_load(_text(VF_METALLIC=0.04, VF_YELLOW=0.02))
    (d / "r.yaml").write_text(yaml.safe_dump(doc))
    (d / "lab" / "panels").mkdir(parents=True)
    for stem, vf in (("A-17", 0.026), ("same", 0.02)):
        p = predict(recipe_from_doc(yaml.safe_load(_text(VF_METALLIC=0.04, VF_YELLOW=vf))), G)
        write_target(d / "lab" / "panels" / f"{stem}.csv", p.geometries, reflectance=p.rf,
                     wavelength_nm=p.wavelength_nm)
    return d


@pytest.mark.slow
def test_report_command_writes_pdf_and_png(paint, tmp_path):
    out = tmp_path / "qc"
    r = CliRunner().invoke(cli, ["report", str(paint / "r.yaml"), "--target", str(paint / "lab" / "panels" / "A-17.csv"),
                                 "--out", str(out), "--formula", "cmc"])
    assert r.exit_code == 1, r.output                      # the verdict is FAIL: exit 1, the report written
    assert "FAIL" in r.output and "dE CMC(2:1)" in r.output
    assert sorted(p.name for p in out.iterdir()) == ["two-species--A-17-qc.pdf", "two-species--A-17-qc.png"]
    data = (out / "two-species--A-17-qc.pdf").read_bytes()
    assert pdf_structure(data)["pages"] == 1
    texts = "\n".join(pdf_texts(data))
    assert "QC report: two-species vs A-17" in texts and "panels" not in texts
    assert "dE CMC(2:1) per geometry vs limit" in texts and "sparkle_area_15" in texts
    same = CliRunner().invoke(cli, ["report", str(paint / "r.yaml"), "--target",
                                    str(paint / "lab" / "panels" / "same.csv"), "--out", str(out)])
    assert same.exit_code == 0 and "PASS: 0 of 6" in same.output, same.output


def test_report_outputs_all_or_none(paint, tmp_path):
    """A directory in the PNG's place: refused before any work, exit 2, the PDF not written either; an --out
    that is a file: refused."""
    out = tmp_path / "qc"
    (out / "two-species--A-17-qc.png").mkdir(parents=True)
    r = CliRunner().invoke(cli, ["report", str(paint / "r.yaml"), "--target", str(paint / "lab" / "panels" / "A-17.csv"),
                                 "--out", str(out)])
    assert r.exit_code == 2 and "a directory is in its place" in r.output, r.output
    assert sorted(p.name for p in out.iterdir()) == ["two-species--A-17-qc.png"]
    (tmp_path / "f").write_text("x")
    r = CliRunner().invoke(cli, ["report", str(paint / "r.yaml"), "--target", str(paint / "lab" / "panels" / "A-17.csv"),
                                 "--out", str(tmp_path / "f")])
    assert r.exit_code == 2 and "is a file" in r.output, r.output


def test_report_failing_midway_leaves_nothing(paint, tmp_path, monkeypatch):
    """The PDF written, then the PNG fails: neither file appears and no temporary entry is left (staged outputs)."""
    import flakedb.cli.report as report_cli

    def half(page, pdf_path, png_path):
        pdf_path.write_bytes(b"%PDF-1.4 half")
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(report_cli, "write_qc_report", half)
    out = tmp_path / "qc"
    r = CliRunner().invoke(cli, ["report", str(paint / "r.yaml"), "--target", str(paint / "lab" / "panels" / "A-17.csv"),
                                 "--out", str(out)])
    assert r.exit_code != 0 and "No space left on device" in r.output, r.output
    assert not out.exists() or not any(out.iterdir())
