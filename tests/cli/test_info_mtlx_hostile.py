"""`flakedb info` on damaged flakedb MaterialX documents (.cpa.mtlx of export-cpa, .mtlx of export-openpbr).

Guards against: a truncated document or an invalid fit attribute failing with a message that does not name the
file; a fit attribute that is JSON but not the fit (a list, a number, nesting deeper than the parser's recursion,
NaN, fields of the wrong type or missing) ending in an 'internal error' after half the summary was printed; a
huge attribute taking minutes and printing millions of numbers.  Each must be one error naming the file (and the
field), a non-zero exit, nothing printed before it."""

import html
import json

import numpy as np
import pytest
from click.testing import CliRunner

from flakedb.cli.main import cli
from flakedb.export.materialx import cpa_mtlx_text

GOOD = {"alphas": [0.11, 0.28, 0.65], "retro_alphas": [0.42], "tilted": [[0.03, 0.304]], "coat_ior": 1.5,
        "n_table": 32, "source": "paint.bsdf", "distribution": "ggx",
        "error": {"worst_dE00_E2194": 1.2, "worst_dE00_E2539": 3.4, "cosine_weighted_difference": 0.05}}


def _cpa_doc(tmp_path, fit_json: str, name="x.cpa.mtlx"):
    """A .cpa.mtlx as export-cpa writes it, its flakedb_cpa attribute holding ``fit_json`` (raw text)."""
    text = cpa_mtlx_text("x.cpa.png", [1.0] * 5, [0.11, 0.28, 0.65], 1.5, 32, "x", "{}", retro_alphas=(0.42,))
    text = text.replace('flakedb_cpa="{}"', f'flakedb_cpa="{html.escape(fit_json, quote=True)}"')
    assert fit_json == "{}" or 'flakedb_cpa="{}"' not in text
    p = tmp_path / name
    p.write_text(text)
    return p


def _info(path, *args):
    return CliRunner().invoke(cli, ["info", str(path), *args])


def test_a_good_cpa_document_is_described(tmp_path):
    """The reference for the refusals below: the same document with a well-formed fit is printed."""
    r = _info(_cpa_doc(tmp_path, json.dumps(GOOD)))
    assert r.exit_code == 0, r.output
    assert "ggx α 0.11, 0.28, 0.65; backscatter α 0.42; 1 tilted lobe(s)" in r.output
    assert "worst ΔE00 1.20 (E2194 geometries)" in r.output


BAD_FITS = {
    "not json": ("{not json", "not valid JSON"),
    "a list": ("[1, 2]", "not a JSON object"),
    "a number": ("3", "not a JSON object"),
    "nested deeper than the parser": ("[" * 100_000 + "]" * 100_000, "not valid JSON"),
    "NaN": (json.dumps(dict(GOOD, alphas=[0.1])).replace("0.1", "NaN"), "not valid JSON"),
    "alphas a number": (json.dumps(dict(GOOD, alphas=0.1)), "alphas"),
    "alphas of strings": (json.dumps(dict(GOOD, alphas=["a"])), "alphas"),
    "too many alphas": (json.dumps(dict(GOOD, alphas=[0.1] * 100_000)), "alphas"),
    "tilted a number": (json.dumps(dict(GOOD, tilted=5)), "tilted"),
    "tilted not pairs": (json.dumps(dict(GOOD, tilted=[0.1, 0.2])), "tilted"),
    "materialx a list": (json.dumps(dict(GOOD, materialx=[1])), "materialx"),
    "error value null": (json.dumps(dict(GOOD, error=dict(GOOD["error"], worst_dE00_E2194=None))), "worst_dE00_E2194"),
    "error key missing": (json.dumps(dict(GOOD, error={"x": 1})), "worst_dE00_E2194"),
    "coat_ior a string": (json.dumps(dict(GOOD, coat_ior="1.5")), "coat_ior"),
    "source with control characters": (json.dumps(dict(GOOD, source="\x1b[31mred\nnext")), "source"),
}


@pytest.mark.parametrize("as_json", [False, True])
@pytest.mark.parametrize("case", sorted(BAD_FITS))
def test_a_damaged_fit_attribute_is_one_error_naming_the_file(tmp_path, case, as_json):
    text, what = BAD_FITS[case]
    p = _cpa_doc(tmp_path, text)
    r = _info(p, *(["--json"] if as_json else []))
    assert r.exit_code == 2, (case, r.exit_code, r.output[:400])
    first = r.output.splitlines()[0]
    assert first.startswith(f"Error: {p}:"), (case, r.output[:400])   # nothing printed before the error
    assert what in first and "internal error" not in r.output and "Traceback" not in r.output, (case, first)
    assert len(first) < 400, (case, len(first))


def test_a_truncated_or_oversized_document_names_the_file(tmp_path):
    """A document cut in half (the XML parser's 'unclosed token' alone named no file) and one over the size
    limit (a 100 MB attribute took 100 s and printed 20 million numbers) are one error naming the file."""
    from flakedb.export import materialx

    full = _cpa_doc(tmp_path, json.dumps(GOOD), "full.cpa.mtlx").read_text()
    cut = tmp_path / "cut.cpa.mtlx"
    cut.write_text(full[: len(full) // 2])
    r = _info(cut)
    assert r.exit_code == 2 and r.output.startswith(f"Error: {cut}: "), r.output[:400]
    assert "not well-formed XML" in r.output.splitlines()[0]
    big = _cpa_doc(tmp_path, json.dumps(dict(GOOD, source="s" * (materialx.MTLX_MAX_BYTES + 10))), "big.cpa.mtlx")
    r = _info(big)
    assert r.exit_code == 2 and r.output.startswith(f"Error: {big}: "), r.output[:400]
    assert str(materialx.MTLX_MAX_BYTES) in r.output.splitlines()[0]


def test_a_damaged_openpbr_fit_is_one_error_naming_the_file(tmp_path):
    """The export-openpbr document goes through the same reader: a fit without its parameters is refused."""
    p = _cpa_doc(tmp_path, "{}", "o.mtlx")
    p.write_text(p.read_text().replace('flakedb_cpa="{}"', 'flakedb_fit="{&quot;base_color&quot;: [1, 2]}"'))
    r = _info(p)
    assert r.exit_code == 2 and r.output.startswith(f"Error: {p}: "), r.output[:400]
    assert "base_color" in r.output.splitlines()[0] and "internal error" not in r.output


def test_a_black_paint_exports_strict_json_that_info_reads(tmp_path):
    """export-cpa of a black paint (a black primer under the coat: the table is 0) wrote
    cosine_weighted_difference NaN (0/0) into the fit, which is not JSON (json.loads without NaN refuses it) and
    which `flakedb info` now refuses: a black fit of a black paint differs by 0."""
    from flakedb.export.openpbr import cosine_weighted_difference

    z = np.zeros((4, 3))
    assert cosine_weighted_difference(z, z, np.ones(4), -np.ones(4), np.ones(4)) == 0.0
    assert np.isnan(cosine_weighted_difference(z + 1, z, np.ones(4), -np.ones(4), np.ones(4)))
    rec = tmp_path / "black.yaml"
    rec.write_text("flakedb: 1\nname: black\nspectral: {mode: spectral, range_nm: [380, 780], step_nm: 20}\n"
                   "layers:\n  - clearcoat: {thickness_um: 40, ior: 1.5, roughness: 0}\n  - primer: {albedo: 0}\n")
    r = CliRunner().invoke(cli, ["compose", str(rec), "--n", "16", "--out", str(tmp_path)])
    assert r.exit_code == 0, r.output
    r = CliRunner().invoke(cli, ["export-cpa", str(tmp_path / "black.bsdf"), "--json"])
    assert r.exit_code == 0, r.output
    json.loads(r.output, parse_constant=lambda c: pytest.fail(f"{c} in export-cpa's JSON"))
    r = _info(tmp_path / "black.cpa.mtlx")
    assert r.exit_code == 0, r.output
    assert "cosine-weighted BSDF difference 0.0 %" in r.output
