"""Hostile stores and store URLs (issue 25): odd --store URLs, a `latest` that points outside
versions/, declared array shapes that disagree (or ask for 10¹² chunks) are clear errors or listed
problems: exit status 1-2, one line, no "internal error", no hang."""

import json
import shutil
from pathlib import Path

import pytest

from flakedb.pipelines.build import build, make_request
from flakedb.store import versions as st
from tests.cases import run_cli

RECIPE = """\
flakedb: 1
name: store-hostile
spectral: {mode: spectral, range_nm: [450, 650], step_nm: 20}
resolution: 8
layers:
  - clearcoat: {thickness_um: 40, ior: 1.5}
  - basecoat:
      thickness_um: 10
      ior: 1.5
      particles:
        - species: cadmium-yellow
          volume_fraction: 0.05
  - primer: {albedo: 0.5}
"""


def _run(args, bound=60):
    return run_cli(args, bound)


def _clean(r, *words, codes=(1, 2)):
    assert r.exit_code in codes, r.output
    assert "Traceback" not in r.output and "internal error" not in r.output, r.output
    for w in words:
        assert w in r.output, r.output
    return r.output


@pytest.fixture(scope="module")
def built(tmp_path_factory):
    url = str(tmp_path_factory.mktemp("hostile") / "store")
    res = build(make_request(species=["cadmium-yellow"], n=8, wavelength_nm=[450.0, 550.0, 650.0], channel_block=1),
                url, scheduler="sync")
    return url, res["version"]


def _copy(built, tmp_path):
    url = str(tmp_path / "store")
    shutil.copytree(built[0], url, symlinks=True)
    return url


@pytest.mark.parametrize("url,words", [
    ("nosuchproto://bucket/store", "not a store path or URL fsspec knows"),
    ("s3x://bucket/store", "not a store path or URL"),
    ("", "an empty store path or URL"),
    ("file://", "an empty store path or URL"),
])
def test_odd_store_urls_are_clear_errors(tmp_path, url, words):
    rec = tmp_path / "r.yaml"
    rec.write_text(RECIPE)
    _clean(_run(["compose", rec, "--store", url, "--out", tmp_path / "o"]), words)
    _clean(_run(["compare", rec, "--store", url, "--write-csv", tmp_path / "p.csv"]), words)
    if url:  # verify and build read an empty --store as "the default store"
        _clean(_run(["verify", url]), words)
        _clean(_run(["build", "--store", url, "--species", "cadmium-yellow", "--n", "8", "--dry-run"]), words)
    assert not (tmp_path / "o").exists() and not (tmp_path / "p.csv").exists()


@pytest.mark.parametrize("name", ["../../../etc", "/etc", "versions/../x", "ABC", "0" * 7])
def test_latest_pointing_outside_versions_is_refused(built, tmp_path, name):
    url = _copy(built, tmp_path)
    (Path(url) / "latest").write_text(json.dumps({"version": name}))
    with pytest.raises(st.StoreError, match="not a version hash"):
        st.read_latest(url)
    with pytest.raises(st.StoreError, match="not a version hash"):
        st.open_version(url)
    r = _run(["verify", url])
    _clean(r, "not a version hash", codes=(1,))
    rec = tmp_path / "r.yaml"
    rec.write_text(RECIPE)
    _clean(_run(["compose", rec, "--store", url, "--out", tmp_path / "o"]), codes=(2,))
    assert not (tmp_path / "o").exists()


def test_a_declared_shape_of_a_trillion_chunks_is_a_problem_not_a_hang(built, tmp_path):
    url = _copy(built, tmp_path)
    vroot = Path(url) / "versions" / built[1]
    zj = vroot / "zarr.json"
    doc = json.loads(zj.read_text())
    path = next(iter(doc["attributes"]["arrays"]))
    doc["attributes"]["arrays"][path]["shape"] = [10 ** 12] + doc["attributes"]["arrays"][path]["shape"][1:]
    zj.write_text(json.dumps(doc))
    problems = st.verify_version(url, built[1])
    assert any("the limit is" in p and path in p for p in problems), problems
    _clean(_run(["verify", url], bound=30), path, codes=(1,))


def test_an_array_whose_zarr_json_disagrees_with_the_metadata(built, tmp_path):
    url = _copy(built, tmp_path)
    vroot = Path(url) / "versions" / built[1]
    meta = json.loads((vroot / "zarr.json").read_text())["attributes"]["arrays"]
    path = next(iter(meta))
    azj = vroot / path / "zarr.json"
    doc = json.loads(azj.read_text())
    doc["shape"] = [s * 1000 for s in doc["shape"]]
    azj.write_text(json.dumps(doc))
    problems = st.verify_version(url, built[1])
    assert any("the array's zarr.json declares shape" in p for p in problems), problems


def test_bad_version_names_in_verify_version(built):
    assert st.verify_version(built[0], "../x") == [
        "version '../x': not a version hash (hex digits); it would point outside versions/"]
    with pytest.raises(st.StoreError, match="not a version hash"):
        st.open_version(built[0], version="../../x")


def test_build_refuses_a_directory_that_is_not_a_store(tmp_path):
    d = tmp_path / "documents"
    d.mkdir()
    (d / "latest").mkdir()            # the user's own folder named latest
    (d / "notes.txt").write_text("mine")
    _clean(_run(["build", "--store", d, "--species", "cadmium-yellow", "--n", "8", "--range-nm", "450", "650",
                 "--step-nm", "100"]), "not a flakedb store", codes=(2,))
    assert sorted(p.name for p in d.iterdir()) == ["latest", "notes.txt"]


@pytest.mark.parametrize("kind", ["fifo", "zero"])
def test_a_special_file_as_version_metadata_is_an_error_not_a_hang(built, tmp_path, kind):
    import os
    url = _copy(built, tmp_path)
    zj = Path(url) / "versions" / built[1] / "zarr.json"
    zj.unlink()
    if kind == "fifo":
        os.mkfifo(zj)
    else:
        os.symlink("/dev/zero", zj)
    with pytest.raises(st.StoreError, match="not a regular file"):
        st.open_version(url)
    _clean(_run(["verify", url], bound=30), "not a regular file", codes=(1,))
    rec = tmp_path / "r.yaml"
    rec.write_text(RECIPE)
    _clean(_run(["compose", rec, "--store", url, "--out", tmp_path / "o"], bound=30), "not a regular file")
