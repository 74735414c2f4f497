"""Corrupt BSDF files (issue 13): the readers check what they read (finite values, sane header
fields and magnitudes, consistent shapes before allocating) and refuse with an error naming the
file and the field; the commands then fail with one line and write nothing."""

import struct
from pathlib import Path

import h5py
import numpy as np
import pytest
from click.testing import CliRunner

from flakedb.bsdf import BSDFFileError, open_bsdf
from flakedb.bsdf.fourier_file import write_bsdf
from flakedb.bsdf.h5file import write_h5
from flakedb.bsdf.table import BSDFTable
from flakedb.cli.main import cli
from flakedb.render import mitsuba as fm

X = np.array([0.2, 0.5, 0.8, 1.0])
MU = np.concatenate([-X[::-1], X])
N = MU.size + 2


def _table():
    c = np.zeros((1, MU.size, MU.size, 2))
    c[..., 0] = 0.1
    c[..., 1] = 0.02
    return BSDFTable(mu=MU, coeffs=c, eta=1.5)


@pytest.fixture()
def good(tmp_path):
    p = tmp_path / "good.bsdf"
    write_bsdf(p, _table())
    return p


def _patch(src, dst, offset, fmt, value):
    raw = bytearray(Path(src).read_bytes())
    struct.pack_into(fmt, raw, offset, value)
    Path(dst).write_bytes(bytes(raw))
    return dst


def _refused(path, *words):
    with pytest.raises(BSDFFileError) as ei:
        open_bsdf(path)
    msg = str(ei.value)
    assert msg.startswith(str(path)), msg
    for w in words:
        assert w in msg, msg
    return msg


def _coeff_offset():
    return 64 + 4 * N + 4 * N * N + 8 * N * N


def test_good_file_reads(good):
    assert open_bsdf(good).eta == pytest.approx(1.5)


def test_nan_coefficients_refused(good, tmp_path):
    _refused(_patch(good, tmp_path / "nan.bsdf", _coeff_offset(), "<f", float("nan")), "coefficients", "finite")


def test_huge_coefficients_refused(good, tmp_path):
    _refused(_patch(good, tmp_path / "big.bsdf", _coeff_offset() + 4, "<f", 3e38), "coefficients", "allowed range")


def test_nan_cdf_refused(good, tmp_path):
    _refused(_patch(good, tmp_path / "cdf.bsdf", 64 + 4 * N + 4 * (N + 1), "<f", float("nan")), "cdf", "finite")


@pytest.mark.parametrize("eta", [float("nan"), -1.5, 0.0, float("inf")])
def test_bad_eta_refused(good, tmp_path, eta):
    _refused(_patch(good, tmp_path / "eta.bsdf", 44, "<f", eta), "eta")


def test_all_zero_nodes_refused(good, tmp_path):
    raw = bytearray(Path(good).read_bytes())
    raw[64:64 + 4 * N] = bytes(4 * N)
    p = tmp_path / "zeros.bsdf"
    p.write_bytes(bytes(raw))
    _refused(p, "nodes", "strictly ascending")


def test_huge_node_count_refused(good, tmp_path):
    _refused(_patch(good, tmp_path / "n.bsdf", 12, "<I", 1 << 20), "nNodes", "allowed range")


def _h5(tmp_path, name="t.h5"):
    p = tmp_path / name
    write_h5(p, _table())
    return p


def test_h5_declaring_a_huge_array_is_refused_before_allocating(tmp_path):
    for shape, word in (((1, MU.size, MU.size, 1 << 24), "orders L"), ((1024, 2048, 2048, 64), "GiB")):
        p = _h5(tmp_path)
        with h5py.File(p, "r+") as f:
            del f["mu"], f["coeffs"]
            f.create_dataset("mu", shape=(shape[1],), dtype="f8")
            f.create_dataset("coeffs", shape=shape, dtype="f8", chunks=(1, 1, 8, 8))
        assert p.stat().st_size < 200_000
        _refused(p, word)


@pytest.mark.parametrize("what", ["nan-coeffs", "eta", "shape"])
def test_h5_bad_values_refused_naming_the_field(tmp_path, what):
    p = _h5(tmp_path)
    with h5py.File(p, "r+") as f:
        if what == "nan-coeffs":
            c = f["coeffs"][...]
            c[0, 1, 2, 0] = np.nan
            f["coeffs"][...] = c
        elif what == "eta":
            f.attrs["eta"] = -2.0
        else:
            del f["mu"]
            f.create_dataset("mu", data=np.linspace(-1, 1, 6))
    _refused(p, {"nan-coeffs": "coeffs[0, 1, 2, 0] is nan", "eta": "eta = -2.0", "shape": "mu has 6 nodes"}[what])


@pytest.mark.parametrize("cmd", [["info"], ["render", "--size", "8", "--spp", "1"], ["export-mitsuba", "--res", "8"]])
def test_commands_refuse_corrupt_files_with_one_line_and_write_nothing(good, tmp_path, cmd):
    bad = _patch(good, tmp_path / "nan.bsdf", _coeff_offset(), "<f", float("nan"))
    out = tmp_path / "out"
    args = cmd + [str(bad)] + (["--out", str(out)] if cmd[0] == "render" else [])
    if cmd[0] == "export-mitsuba":
        args += ["--out", str(out / "x.bsdf")]
    r = CliRunner().invoke(cli, args)
    assert r.exit_code == 2, r.output
    assert "coefficients" in r.output and "Traceback" not in r.output
    assert not out.exists()


def test_export_of_a_table_without_coefficients_works_and_leaves_nothing_on_failure(tmp_path):
    p = tmp_path / "black.bsdf"
    write_bsdf(p, BSDFTable(mu=MU, coeffs=np.zeros((1, MU.size, MU.size, 1))))
    s = fm.export_measured(p, tmp_path / "black_measured.bsdf", res=8, n_theta=4)
    assert np.all(np.asarray(s["reflected_albedo"]) == 0)
    r = CliRunner().invoke(cli, ["export-mitsuba", str(p), "--out", str(tmp_path / "o" / "m.bsdf"), "--res", "0"])
    assert r.exit_code == 2 and "8 ≤ res ≤ 512" in r.output and not (tmp_path / "o").exists()


def test_tensor_reader_checks_what_it_reads(tmp_path):
    good = tmp_path / "t.bin"
    fm.write_tensor_file(good, {"a": np.arange(6, dtype=np.float32).reshape(2, 3), "description": "x"})
    assert fm.read_tensor_file(good)["a"].shape == (2, 3)
    raw = good.read_bytes()
    (tmp_path / "trunc.bin").write_bytes(raw[:-8])
    with pytest.raises(fm.MeasuredExportError, match="trunc.bin: field 'a'.*runs past the end|trunc.bin: field"):
        fm.read_tensor_file(tmp_path / "trunc.bin")
    nan = tmp_path / "nan.bin"
    fm.write_tensor_file(nan, {"a": np.array([1.0, np.nan], dtype=np.float32)})
    with pytest.raises(fm.MeasuredExportError, match="nan.bin: field 'a' holds NaN"):
        fm.read_tensor_file(nan)
    (tmp_path / "short.bin").write_bytes(raw[:20])
    with pytest.raises(fm.MeasuredExportError, match="short.bin"):
        fm.read_tensor_file(tmp_path / "short.bin")


def _compressed_h5(path):
    """A flakedb .h5 whose coefficients are stored compressed (mostly zeros): the layout read_chunks_deflated
    inflates itself; returns the table written."""
    x = np.array([0.2, 0.5, 0.8, 1.0])
    mu = np.concatenate([-x[::-1], x])
    c = np.zeros((2, 8, 8, 12))
    c[..., 0] = 0.05
    c[:, 4:, :4, 1] = 0.01
    table = BSDFTable(mu=mu, coeffs=c, eta=1.5)
    write_h5(path, table)
    with h5py.File(path, "r") as f:
        assert f["coeffs"].compression == "gzip" and f["coeffs"].id.get_num_chunks() > 0
    return table


@pytest.mark.parametrize("damage", ["garbage", "bomb", "short", "filter-skipped"])
def test_h5_damaged_compressed_chunk(tmp_path, damage):
    """A stored chunk that is not what its filters say: garbage or a truncated stream is refused naming the
    chunk; one that inflates to more than its size (a deflate bomb) is refused without inflating more than the
    chunk's size; a chunk whose filters HDF5 records as skipped is left to HDF5 (read as HDF5 reads it)."""
    import zlib

    p = tmp_path / "c.h5"
    table = _compressed_h5(p)
    size = 4 * 12 * 8  # one chunk (1, 1, 4, 12) of float64
    with h5py.File(p, "r+") as f:
        d = f["coeffs"]
        off = d.id.get_chunk_info(0).chunk_offset
        _, good = d.id.read_direct_chunk(off)
        if damage == "garbage":
            d.id.write_direct_chunk(off, b"\x00not a deflate stream" * 4)
        elif damage == "bomb":
            d.id.write_direct_chunk(off, zlib.compress(bytes(1000 * size), 9))
        elif damage == "short":
            d.id.write_direct_chunk(off, good[: len(good) // 2])
        else:  # the deflate filter skipped: the stored bytes are shuffled but not deflated
            raw = zlib.decompress(good)
            d.id.write_direct_chunk(off, raw, filter_mask=0b10)
    if damage == "filter-skipped":
        t = open_bsdf(p).to_table()
        with h5py.File(p, "r") as f:
            np.testing.assert_array_equal(t.coeffs, f["coeffs"][...])  # what HDF5 itself decodes
        np.testing.assert_array_equal(t.coeffs, table.coeffs)
        return
    with pytest.raises(BSDFFileError, match=r"chunk \(\d+, \d+, \d+, 0\) does not inflate to its 384 bytes"):
        open_bsdf(p)
