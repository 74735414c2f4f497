"""flakedb.store.fs.LocalFiles: a local store is read without fsspec (its import is 25–30 ms of a whole-process
compose), with the values fsspec's LocalFileSystem gives for every call a reader makes, and fsspec still
serves URLs and every write."""

import os
import posixpath
import subprocess
import sys
from pathlib import Path

import fsspec
import pytest
from fsspec.implementations.local import LocalFileSystem

from flakedb.pipelines.build import build, make_request
from flakedb.store.fs import LocalFiles, local_root, open_fs


@pytest.fixture(scope="module")
def store(tmp_path_factory):
    url = str(tmp_path_factory.mktemp("localfs") / "store")
    req = make_request(species=["cadmium-yellow"], n=8, wavelength_nm=[450.0, 650.0])
    return url, build(req, url, scheduler="sync")["version"]


def test_every_reading_call_matches_fsspec(store):
    url, version = store
    fs, root = open_fs(url)
    ref, ref_root = fsspec.core.url_to_fs(url)
    assert isinstance(fs, LocalFiles) and isinstance(ref, LocalFileSystem) and root == ref_root
    paths = [root, posixpath.join(root, "latest"), posixpath.join(root, "nothing-here")]
    paths += [str(p) for p in Path(root, "versions", version).rglob("*")][:60]
    assert len(paths) > 20
    for p in paths:
        assert fs.exists(p) == ref.exists(p), p
        if not ref.exists(p):
            with pytest.raises(FileNotFoundError):
                fs.ls(p)
            continue
        assert sorted(fs.ls(p, detail=False)) == sorted(ref.ls(p, detail=False)), p
        assert fs.modified(p) == ref.modified(p), p
        if os.path.isfile(p):
            assert fs.size(p) == ref.size(p) and fs.cat_file(p) == ref.cat_file(p), p


def test_dangling_links_are_absent_as_in_fsspec(tmp_path):
    (tmp_path / "target").write_text("x")
    (tmp_path / "dangling").symlink_to(tmp_path / "nowhere")
    (tmp_path / "link").symlink_to(tmp_path / "target")
    fs, root = open_fs(str(tmp_path))
    ref = LocalFileSystem()
    for name in ("dangling", "link", "target"):
        p = posixpath.join(root, name)
        assert fs.exists(p) == ref.exists(p), name
    with pytest.raises(FileNotFoundError):
        fs.ls(posixpath.join(root, "dangling"))
    assert sorted(fs.ls(root)) == sorted(ref.ls(root, detail=False))
    assert fs.modified(posixpath.join(root, "link")) == ref.modified(posixpath.join(root, "link"))


@pytest.mark.parametrize("path", ["/tmp/s/", "rel/store", "./rel", ".", "~/store", "/", "my:store"])
def test_local_root_is_fsspecs(path):
    assert local_root(path) == fsspec.core.url_to_fs(path)[1]


def test_urls_and_writes_go_through_fsspec(tmp_path):
    assert isinstance(open_fs(str(tmp_path), writable=True)[0], LocalFileSystem)
    assert isinstance(open_fs(f"file://{tmp_path}")[0], LocalFileSystem)
    for prefix in ("file:", "local:"):  # the prefixes fsspec strips: the same root as fsspec's
        fs, root = open_fs(f"{prefix}{tmp_path}")
        assert isinstance(fs, LocalFileSystem) and root == str(tmp_path)
    assert type(open_fs("memory://flakedb-test-store")[0]).__name__ == "MemoryFileSystem"


def test_reading_a_local_store_imports_no_fsspec(store):
    url, _ = store
    code = ("import sys; from flakedb.store.read import open_version; v = open_version(sys.argv[1]); "
            "v.group['wavelength_nm'][:]; assert 'fsspec' not in sys.modules, 'fsspec imported'")
    run = subprocess.run([sys.executable, "-c", code, url], capture_output=True, text=True, check=False)
    assert run.returncode == 0, run.stderr[-2000:]
