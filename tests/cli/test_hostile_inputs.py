"""Hostile inputs for every reader, through the commands (issue 25): special files (a FIFO would hang,
a symlink to /dev/zero is endless), HDF5 files that point elsewhere (external storage, external
links, virtual datasets), metadata of the wrong type, YAML bombs in a match base or a catalogue,
values inside the old schema that break the physics (4.9e-324 µm, a 40 GiB pigment, a 10⁹-member
sweep), oversized targets.  Each is refused with exit status 1-2, one line naming the file / field /
option, no traceback, no "internal error", no hang, nothing written."""

import os
import socket
from pathlib import Path

import h5py
import numpy as np
import pytest

import flakedb.compose.orchestrate as orch
import flakedb.solve.pipeline as pipeline
from flakedb.bsdf.fourier_file import write_bsdf
from flakedb.bsdf.h5file import write_h5
from flakedb.bsdf.table import BSDFTable
from flakedb.paint.catalog import default_catalog_path
from flakedb.render import mitsuba as fm
from flakedb.render import preview
from flakedb.safeio import FileTooLargeError, NotRegularFileError, read_limited
from flakedb.store import versions as st
from tests.cases import run_cli, small_mono_recipe

RECIPE = small_mono_recipe("hostile")

PIGMENT = """\
flakedb: 1
name: hostile-pigment
spectral: {{mode: spectral}}
resolution: 16
layers:
  - clearcoat: {{thickness_um: 40, ior: 1.5}}
  - basecoat:
      thickness_um: 200
      ior: 1.5
      particles:
        - species: cadmium-yellow
          volume_fraction: 0.05
{extra}  - primer: {{albedo: 0.5}}
"""

TARGET = "illumination_deg,aspecular_deg,L*,a*,b*\n45,15,80,5,60\n45,45,70,4,50\n"

#: Longest a refusal may take [s] (generous: the 2-core CI machine; a hang is minutes or forever).
BOUND_S = 60


def _run(args, bound=BOUND_S):
    return run_cli(args, bound)


@pytest.fixture()
def no_work(monkeypatch):
    def work(*a, **k):
        raise AssertionError("the work started before the input was refused")

    for mod, name in ((pipeline, "build_paint"), (pipeline, "solve_paint"), (preview, "render_sphere"),
                      (fm, "measured_tensors"), (st, "write_template")):
        monkeypatch.setattr(mod, name, work)


def _clean(r, *words, codes=(2,)):
    assert r.exit_code in codes, r.output
    assert "Traceback" not in r.output and "internal error" not in r.output, r.output
    assert r.output.startswith("Error: ") or "\nError: " in r.output, r.output
    for w in words:
        assert w in r.output, r.output
    return r.output


def _table(c0=0.05):
    x = np.array([0.2, 0.5, 0.8, 1.0])
    mu = np.concatenate([-x[::-1], x])
    c = np.zeros((1, mu.size, mu.size, 2))
    c[..., 0] = c0
    return BSDFTable(mu=mu, coeffs=c, eta=1.5)


# --- the safe reader ------------------------------------------------------------------------------
@pytest.fixture()
def specials(tmp_path):
    """A FIFO, a symlink to /dev/zero, a socket and a directory, each named like an input file."""
    d = {}
    d["fifo"] = tmp_path / "fifo.yaml"
    os.mkfifo(d["fifo"])
    d["zero"] = tmp_path / "zero.yaml"
    os.symlink("/dev/zero", d["zero"])
    d["socket"] = tmp_path / "sock.yaml"
    s = socket.socket(socket.AF_UNIX)
    s.bind(str(d["socket"]))
    d["dir"] = tmp_path / "dir.yaml"
    d["dir"].mkdir()
    yield d
    s.close()


@pytest.mark.parametrize("kind", ["fifo", "zero", "socket", "dir"])
def test_read_limited_refuses_what_is_not_a_regular_file(specials, kind):
    with pytest.raises(NotRegularFileError) as ei:
        read_limited(specials[kind], 1000)
    assert "not a regular file" in ei.value.strerror


def test_read_limited_reads_at_most_limit_plus_one(tmp_path, monkeypatch):
    p = tmp_path / "f"
    p.write_bytes(b"x" * 100)
    assert read_limited(p, 100) == b"x" * 100
    with pytest.raises(FileTooLargeError):
        read_limited(p, 99)
    # a file whose stat lies (size 0, like /proc files): the read itself stops at limit + 1
    real_fstat = os.fstat
    monkeypatch.setattr(os, "fstat", lambda fd: os.stat_result((*real_fstat(fd)[:6], 0, *real_fstat(fd)[7:])))
    seen = []
    real_read = os.read
    monkeypatch.setattr(os, "read", lambda fd, n: (seen.append(n), real_read(fd, n))[1])
    with pytest.raises(FileTooLargeError):
        read_limited(p, 10)
    assert sum(seen) <= 11


def test_read_limited_reads_a_file_whole_in_one_read(tmp_path, monkeypatch):
    """A regular file is read with one call for its size and one more byte (then EOF), its bytes unchanged, not in
    1 MiB pieces joined (a copy of every store chunk)."""
    p = tmp_path / "f"
    data = os.urandom(3 * 2**20 + 17)
    p.write_bytes(data)
    seen = []
    real_read = os.read
    monkeypatch.setattr(os, "read", lambda fd, n: (seen.append(n), real_read(fd, n))[1])
    assert read_limited(p, 2**30) == data
    assert seen[0] == len(data) + 1 and len(seen) == 2


@pytest.mark.parametrize("kind", ["fifo", "zero"])
def test_every_reader_refuses_special_files(specials, tmp_path, kind, no_work):
    bad = specials[kind]
    rec = tmp_path / "r.yaml"
    rec.write_text(RECIPE)
    tgt = tmp_path / "t.csv"
    tgt.write_text(TARGET)
    cxf = tmp_path / f"{kind}.cxf"
    os.symlink(bad, cxf)
    out = tmp_path / "out"
    cases = [
        ["compose", bad, "--out", out],
        ["compose", rec, "--catalog", bad, "--out", out],
        ["info", bad],
        ["render", bad, "--out", out],
        ["export-mitsuba", bad, "--out", out / "x.tensor"],
        ["compare", rec, "--target", bad],
        ["compare", rec, "--target", cxf],
        ["match", bad, "--target", tgt, "--out", out],
        ["build", "--recipe", bad, "--dry-run", "--store", tmp_path / "store"],
    ]
    for args in cases:
        text = _clean(_run(args), "not a regular file", codes=(1, 2))
        assert str(bad) in text or str(cxf) in text, text
    assert not out.exists()


def test_a_store_chunk_linked_to_dev_zero_is_a_problem_not_a_hang(tmp_path):
    from flakedb.pipelines.build import build, make_request
    url = str(tmp_path / "store")
    build(make_request(species=["cadmium-yellow"], n=8, wavelength_nm=[450.0, 550.0, 650.0], channel_block=1), url,
          scheduler="sync")
    chunk = next(p for p in Path(url).rglob("c/*") if p.is_file())
    chunk.unlink()
    os.symlink("/dev/zero", chunk)
    r = _run(["verify", url])
    assert r.exit_code == 1 and "not a regular file" in r.output and "Traceback" not in r.output, r.output


# --- HDF5 that reads other files ----------------------------------------------------------------
def _h5_pointing_elsewhere(path, how, target):
    write_h5(path, _table())
    with h5py.File(path, "r+") as f:
        shape, dtype = f["coeffs"].shape, f["coeffs"].dtype
        del f["coeffs"]
        if how == "external":
            f.create_dataset("coeffs", shape=shape, dtype=dtype, external=[(str(target), 0, h5py.h5f.UNLIMITED)])
        elif how == "link":
            other = Path(path).with_name("other.h5")
            with h5py.File(other, "w") as g:
                g.create_dataset("coeffs", data=np.zeros(shape))
            f["coeffs"] = h5py.ExternalLink(str(other), "/coeffs")
        else:
            layout = h5py.VirtualLayout(shape=shape, dtype=dtype)
            other = Path(path).with_name("other.h5")
            with h5py.File(other, "w") as g:
                g.create_dataset("c", data=np.zeros(shape))
            layout[...] = h5py.VirtualSource(str(other), "c", shape=shape)
            f.create_virtual_dataset("coeffs", layout)


@pytest.mark.parametrize("how,words", [("external", "external storage"), ("link", "ExternalLink"),
                                       ("virtual", "virtual dataset")])
def test_h5_data_from_another_file_is_refused(tmp_path, how, words):
    secret = tmp_path / "secret.txt"
    secret.write_text("TOP-SECRET-" * 1000)
    p = tmp_path / "p.h5"
    _h5_pointing_elsewhere(p, how, "/dev/zero" if how == "external" else secret)
    text = _clean(_run(["info", p]), words, "reads only data stored in the named file")
    assert "TOP-SECRET" not in text
    if how == "external":
        _h5_pointing_elsewhere(p, how, secret)
        for cmd in (["info", p], ["render", p, "--out", tmp_path / "o"], ["export-mitsuba", p]):
            assert "TOP-SECRET" not in _clean(_run(cmd), "external storage")


# --- metadata of the wrong type or missing -----------------------------------------------------
@pytest.mark.parametrize("attr,value,words", [
    ("metadata", "[1, 2]", "attribute 'metadata' must be a JSON dict"),
    ("metadata", '{"wavelength_nm": "red"}', "field wavelength_nm"),
    ("metadata", '{"solver_info": {"orders": 3, "order_converged": true, "order_tail": "big"}}', "solver_info.order_tail"),
    ("metadata", '{"solver_info": [1]}', "field solver_info must be a mapping"),
    ("metadata", '{"warnings": "oops"}', "field warnings"),
    ("metadata", '{"n_nodes": "sixteen"}', "field n_nodes"),
    ("channels", '{"a": 1}', "attribute 'channels'"),
    ("channels", '[1, 2]', "attribute channels must be a JSON list of channel names"),
    ("delta", '{"kind": "fresnel", "eta": "glass"}', "attribute delta"),
    ("delta", "[]", "attribute 'delta'"),
    ("eta", "not a number", "attribute 'eta' must be one float"),
    ("format_version", 1.5, "attribute 'format_version' must be one int"),
    ("alpha", np.zeros(5), "alpha must hold two numbers"),
    ("eta", None, "attribute 'eta' is missing"),
    ("flakedb_version", None, "attribute 'flakedb_version' is missing"),
])
def test_h5_attributes_of_the_wrong_type_are_named(tmp_path, attr, value, words):
    p = tmp_path / "p.h5"
    write_h5(p, _table())
    with h5py.File(p, "r+") as f:
        if value is None:
            del f.attrs[attr]
        else:
            f.attrs[attr] = value
    _clean(_run(["info", p]), words)
    _clean(_run(["info", "--json", p]), words)


@pytest.mark.parametrize("key,value,words", [("delta_eta", "abc", "delta"), ("wavelength_nm", "red", "wavelength_nm"),
                                             ("recipe", "[1, 2]", "field recipe"),
                                             ("gamut_max_dE00", "lots", "gamut_max_dE00")])
def test_bsdf_metadata_of_the_wrong_type_is_named(tmp_path, key, value, words):
    p = tmp_path / "p.bsdf"
    t = _table()
    t.delta = {"kind": "fresnel", "eta": 1.5}
    t.metadata = {"note": "x" * 40}
    write_bsdf(p, t)
    raw = p.read_bytes()
    old = b"note=" + b"x" * 40
    new = f"{key}={value}".encode()
    new = new + b" " * 0
    assert old in raw
    if key == "delta_eta":
        raw = raw.replace(b"delta_eta=1.5", b"delta_eta=abc")
    else:
        pad = len(old) - len(new) - len("\nz=")
        raw = raw.replace(old, new + b"\nz=" + b"y" * pad)
    p.write_bytes(raw)
    _clean(_run(["info", p]), words)


def test_info_exits_non_zero_when_a_check_fails(tmp_path):
    p = tmp_path / "neg.h5"
    write_h5(p, _table(c0=-0.05))            # negative order-0 coefficients: the colour check fails
    r = _run(["info", p])
    assert r.exit_code == 1 and "[FAIL]" in r.output and "check(s) failed: colour" in r.output, r.output
    r = _run(["info", "--json", p])
    assert r.exit_code == 1, r.output
    p = tmp_path / "ok.h5"
    write_h5(p, _table())
    assert _run(["info", p]).exit_code == 0


# --- one strict YAML loader ---------------------------------------------------------------------
BOMB = "a: &a [x, x, x, x, x, x, x, x, x]\n" + "".join(
    f"{c}: &{c} [" + ", ".join([f"*{p}"] * 9) + "]\n" for p, c in zip("abcdefgh", "bcdefghi"))


def test_match_reads_its_base_with_the_strict_loader(tmp_path, no_work):
    tgt = tmp_path / "t.csv"
    tgt.write_text(TARGET)
    (tmp_path / "bomb.yaml").write_text(BOMB)
    _clean(_run(["match", tmp_path / "bomb.yaml", "--target", tgt, "--out", tmp_path / "o"], bound=20), "aliases")
    (tmp_path / "dup.yaml").write_text(RECIPE + "name: again\n")
    _clean(_run(["match", tmp_path / "dup.yaml", "--target", tgt, "--out", tmp_path / "o"]), "duplicate key 'name'")
    assert not (tmp_path / "o").exists()


@pytest.mark.parametrize("edit,words", [
    (lambda t: t + "\nbomb: " + "[" * 5000 + "]" * 5000 + "\n", "nesting is too deep|YAML"),
    (lambda t: t + "\n" + BOMB.replace("a:", "z1:").replace("&a", "&za").replace("*a", "*za"), "aliases"),
    (lambda t: t + "\nversion: 2\n", "duplicate key 'version'"),
    (lambda t: t + "\nwhen: 2024-13-45\n", "YAML value error"),
    (lambda t: t.replace("value: 0.36", "value: .nan", 1), "not a finite number"),
    (lambda t: t + "\n  : [unclosed\n", "YAML syntax error at line"),
])
def test_catalogue_files_get_the_recipe_loader_and_checks(tmp_path, no_work, edit, words):
    text = default_catalog_path().read_text()
    assert "value: 0.36" in text
    cat = tmp_path / "cat.yaml"
    cat.write_text(edit(text))
    rec = tmp_path / "r.yaml"
    rec.write_text(RECIPE)
    import re
    out = _clean(_run(["compose", rec, "--catalog", cat, "--out", tmp_path / "o"], bound=30), codes=(2,))
    assert re.search(words, out), out
    assert str(cat) in out


# --- physical bounds ------------------------------------------------------------------------------
@pytest.mark.parametrize("extra,words", [
    ("          median_diameter_um: 4.9e-324\n", "median_diameter_um: value 5e-324 is outside the allowed range"),
    ("          median_diameter_um: 1.0e-300\n", "median_diameter_um: value 1e-300 is outside"),
    ("          median_diameter_um: 50\n          gsd: 2.5\n", "particles[0].median_diameter_um = 50 µm with"),
    ("          gsd: 3\n", "catalogue particles.cadmium-yellow.median_diameter_um = 0.36 µm with"),
])
def test_pigment_sizes_are_bounded_and_their_cost_named(tmp_path, no_work, extra, words):
    rec = tmp_path / "r.yaml"
    rec.write_text(PIGMENT.format(extra=extra))
    out = _clean(_run(["compose", rec, "--out", tmp_path / "o"], bound=30), words)
    if "GiB" in out:
        assert "--n does not change this" in out and "use a smaller --n" not in out
        assert "the limit is 8 GiB" in out


def test_flake_diameter_and_catalogue_bounds(tmp_path, no_work):
    text = default_catalog_path().read_text()
    cat = tmp_path / "cat.yaml"
    cat.write_text(text.replace("value: 0.36", "value: 1.0e-300", 1))
    rec = tmp_path / "r.yaml"
    rec.write_text(RECIPE)
    _clean(_run(["compose", rec, "--catalog", cat, "--out", tmp_path / "o"]), "median_diameter_um.value",
           "below 5 nm the bulk optical constants")
    assert "stop: 140" in text
    cat.write_text(text.replace("step: 10", "step: 1", 1).replace("start: 70", "start: 1", 1).replace(
        "stop: 140", "stop: 100000", 1))
    _clean(_run(["species", "list", "--catalog", cat]), "members; the limit is 1000")


def test_build_step_and_range_are_bounded(tmp_path, no_work):
    _clean(_run(["build", "--step-nm", "0.000001", "--dry-run", "--store", tmp_path / "s"]), "--step-nm", "1 ≤ step ≤ 420")
    _clean(_run(["build", "--step-nm", "nan", "--dry-run", "--store", tmp_path / "s"]), "--step-nm")
    _clean(_run(["build", "--range-nm", "780", "380", "--dry-run", "--store", tmp_path / "s"]), "--range-nm")
    _clean(_run(["build", "--eta-top", "1e300", "--dry-run", "--store", tmp_path / "s"]), "--eta-top")
    _clean(_run(["build", "--alpha", "metallic=1e-300", "--dry-run", "--store", tmp_path / "s"]), "--alpha")
    assert not (tmp_path / "s").exists()


def test_compare_options_are_bounded(tmp_path, no_work):
    rec = tmp_path / "r.yaml"
    rec.write_text(RECIPE)
    tgt = tmp_path / "t.csv"
    tgt.write_text(TARGET)
    _clean(_run(["compare", rec, "--target", tgt, "--max-de", "nan"]), "--max-de")
    _clean(_run(["compare", rec, "--target", tgt, "--limit", "15=-1"]), "--limit 15=-1")
    _clean(_run(["match", rec, "--target", tgt, "--weight", "15=inf", "--out", tmp_path / "o"]), "--weight")


# --- targets ----------------------------------------------------------------------------------------
def test_a_target_of_a_million_geometries_is_refused_at_once(tmp_path, no_work):
    tgt = tmp_path / "big.csv"
    rows = "".join(f"45,{a % 80 - 15},50,1,1\n" for a in range(300))
    tgt.write_text("illumination_deg,aspecular_deg,L*,a*,b*\n" + rows)
    rec = tmp_path / "r.yaml"
    rec.write_text(RECIPE)
    _clean(_run(["compare", rec, "--target", tgt]), "300 geometry rows; the limit is 200")
    tgt.write_text("illumination_deg,aspecular_deg,L*,a*,b*\n" + "45,15,50,1,1\n" * 1_000_000)
    _clean(_run(["compare", rec, "--target", tgt], bound=20), "the limit is 2,000,000 bytes")


@pytest.mark.parametrize("content,words", [
    (b"illumination_deg,aspecular_deg,L*,a*,b*\n45,15,5\x000,1,1\n", "line 2"),
    (b"illumination_deg,aspecular_deg,L*,a*,b*\n45,15,\xff\xfe,1,1\n", "not UTF-8"),
    (b"illumination_deg,aspecular_deg,L*,L*,b*\n45,15,1,1,1\n", "appears twice"),
])
def test_target_csv_bytes_that_break_the_parser(tmp_path, no_work, content, words):
    tgt = tmp_path / "t.csv"
    tgt.write_bytes(content)
    rec = tmp_path / "r.yaml"
    rec.write_text(RECIPE)
    _clean(_run(["compare", rec, "--target", tgt]), words, str(tgt))


def test_cxf_with_a_doctype_is_refused(tmp_path, no_work):
    cxf = tmp_path / "t.cxf"
    cxf.write_text('<?xml version="1.0"?>\n<!DOCTYPE x [<!ENTITY e SYSTEM "file:///etc/passwd">]>\n'
                   '<CxF xmlns="http://colorexchangeformat.com/CxF3-core">&e;</CxF>\n')
    rec = tmp_path / "r.yaml"
    rec.write_text(RECIPE)
    out = _clean(_run(["compare", rec, "--target", cxf]), "DOCTYPE")
    assert "root:" not in out


def test_a_sweep_name_cannot_be_a_path(tmp_path, no_work):
    text = default_catalog_path().read_text()
    cat = tmp_path / "cat.yaml"
    cat.write_text(text.replace('name_format: "pearlescent-tio2-{value:03d}nm"', 'name_format: "../../evil-{value:03d}"'))
    assert cat.read_text() != text
    _clean(_run(["species", "show", "../../evil-070", "--catalog", cat, "--out", tmp_path / "o"]),
           "name_format", "a species name is lower-case letters")
    assert not (tmp_path.parent / "evil-070-optics.png").exists()
