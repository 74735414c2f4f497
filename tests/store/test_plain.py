"""flakedb.store.plain: the zarr-free reader compose uses must give zarr's own values for every array of a
built store and any slice of it, fill absent chunks, refuse a chunk of the wrong size, and hand any layout it
does not take (another codec, a transpose) to zarr instead of misreading it."""

import json
import posixpath
from pathlib import Path

import numpy as np
import pytest
import zarr

from flakedb.pipelines.build import build, make_request
from flakedb.store import versions as st
from flakedb.store.errors import StoreIntegrityError
from flakedb.store.fs import open_fs
from flakedb.store.plain import PlainArray, PlainGroup, Unsupported, plain_layout


@pytest.fixture(scope="module")
def store(tmp_path_factory):
    url = str(tmp_path_factory.mktemp("plain") / "store")
    req = make_request(species=["pearlescent", "cadmium-yellow"], n=8, wavelength_nm=[450.0, 550.0, 650.0],
                       channel_block=2)
    res = build(req, url, scheduler="sync")
    return url, res["version"]


def _arrays(vroot):
    for zj in sorted(Path(vroot).rglob("zarr.json")):
        meta = json.loads(zj.read_text())
        if meta.get("node_type") == "array":
            yield str(zj.parent.relative_to(vroot)), meta


def test_every_array_and_slice_reads_as_zarr_reads_it(store):
    url, version = store
    vroot = Path(url) / "versions" / version
    fs, root = open_fs(url)
    g = PlainGroup(fs, posixpath.join(root, "versions", version), st.version_url(url, version))
    z = zarr.open_group(st.version_url(url, version), mode="r")
    assert g.attrs == dict(z.attrs)
    seen = 0
    rng = np.random.default_rng(1)
    for path, meta in _arrays(vroot):
        a, b = g[path], z[path]
        assert isinstance(a, PlainArray), path  # flakedb's writer makes only layouts the plain reader takes
        assert a.shape == b.shape and tuple(a.chunks) == tuple(b.chunks) and a.dtype == b.dtype
        assert a.attrs == dict(b.attrs)
        np.testing.assert_array_equal(a[:], b[:])  # NaN where zarr has NaN (fill) too
        np.testing.assert_array_equal(a[...], b[...])
        for _ in range(5):  # random boxes across chunk edges, empty ones included
            box = tuple(slice(int(lo), int(lo + rng.integers(0, s - lo + 1))) for s in a.shape
                        for lo in [rng.integers(0, s + 1)])
            np.testing.assert_array_equal(a[box], b[box])
        seen += 1
    assert seen >= 6


def test_absent_chunk_is_the_fill_value_and_a_short_chunk_is_refused(store, tmp_path):
    url, version = store
    fs, root = open_fs(url)
    vroot = posixpath.join(root, "versions", version)
    g = PlainGroup(fs, vroot, st.version_url(url, version))
    meta = json.loads((Path(vroot) / "wavelength_nm" / "zarr.json").read_text())
    plain = dict(meta, codecs=[{"name": "bytes", "configuration": {"endian": "little"}}])
    d = tmp_path / "arr"
    (d / "c").mkdir(parents=True)
    a = PlainArray(fs, str(d), plain)
    assert np.all(np.isnan(a[:])) and a[:].shape == tuple(meta["shape"])  # no chunk written: fill (NaN)
    (d / "c" / "0").write_bytes(np.arange(3, dtype="<f8").tobytes()[:-8])
    with pytest.raises(StoreIntegrityError, match="corrupt"):
        a[:]
    (d / "c" / "0").write_bytes(np.arange(3, dtype="<f8").tobytes())
    np.testing.assert_array_equal(a[:], [0.0, 1.0, 2.0])
    assert g["wavelength_nm"][1:2].tolist() == [550.0]


@pytest.mark.parametrize("change", [
    {"codecs": [{"name": "transpose", "configuration": {"order": [0]}}, {"name": "bytes"}]},
    {"codecs": [{"name": "bytes"}, {"name": "gzip", "configuration": {"level": 1}}]},
    {"codecs": [{"name": "bytes", "configuration": {"endian": "big"}}]},
    {"chunk_key_encoding": {"name": "v2", "configuration": {"separator": "."}}},
    {"data_type": "complex128"},
])
def test_other_layouts_are_not_taken(change):
    meta = {"zarr_format": 3, "node_type": "array", "shape": [3], "data_type": "float64",
            "chunk_grid": {"name": "regular", "configuration": {"chunk_shape": [3]}},
            "chunk_key_encoding": {"name": "default", "configuration": {"separator": "/"}},
            "fill_value": "NaN", "codecs": [{"name": "bytes", "configuration": {"endian": "little"}}]}
    assert plain_layout(meta)[:3] == ((3,), (3,), np.dtype("<f8"))
    with pytest.raises(Unsupported):
        plain_layout(dict(meta, **change))


def test_an_array_of_another_layout_is_opened_with_zarr(store, tmp_path):
    """A gzip-compressed array in a version (not what flakedb writes, valid Zarr v3): read by zarr, same values."""
    url, version = store
    vurl = st.version_url(url, version)
    data = np.linspace(0.0, 1.0, 7)
    zarr.create_array(vurl, name="extra_gzip", shape=data.shape, chunks=(3,), dtype="f8",
                      compressors=zarr.codecs.GzipCodec(level=1))[...] = data
    fs, root = open_fs(url)
    a = PlainGroup(fs, posixpath.join(root, "versions", version), vurl)["extra_gzip"]
    assert not isinstance(a, PlainArray)
    np.testing.assert_array_equal(a[:], data)
    with pytest.raises(KeyError):
        PlainGroup(fs, posixpath.join(root, "versions", version), vurl)["no_such_array"]


def test_zstd_chunks_of_earlier_stores_are_decoded(store):
    """Stores written before flakedb.store.write.COMPRESSORS = None hold zstd chunks (zarr's default): the plain
    reader decodes them itself, to zarr's values, edge chunks and NaN fill included."""
    url, version = store
    vurl = st.version_url(url, version)
    data = np.arange(35.0).reshape(5, 7)
    data[4, 6] = np.nan
    zarr.create_array(vurl, name="extra_zstd", shape=data.shape, chunks=(2, 3), dtype="f8", fill_value=np.nan,
                      compressors=zarr.codecs.ZstdCodec(level=0))[...] = data
    fs, root = open_fs(url)
    a = PlainGroup(fs, posixpath.join(root, "versions", version), vurl)["extra_zstd"]
    assert isinstance(a, PlainArray) and a._zstd
    np.testing.assert_array_equal(a[:], data)
    np.testing.assert_array_equal(a[1:4, 2:6], data[1:4, 2:6])
