"""flakedb.store.versions + flakedb/pipelines/build.py: guards against a distributed build that writes different bytes
than the serial one, an interrupted build that breaks `latest` or cannot be resumed, corrupted chunks
that verify or the reader let through, a rebuild of unchanged inputs that recomputes, a content hash
that depends on dict order or ignores an input, and stored factors that do not give R."""

import json
import os
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from flakedb.cli.main import cli
from flakedb.pipelines.build import build, make_request
from flakedb.store import versions as st

SPECIES = ["pearlescent", "cadmium-yellow"]


def _request(**kw):
    args = dict(species=SPECIES, n=8, wavelength_nm=[450.0, 550.0, 650.0], channel_block=2)
    args.update(kw)
    return make_request(**args)


def _checksums(url, version):
    return json.loads((Path(url) / "versions" / version / "checksums.json").read_text())["files"]


@pytest.fixture(scope="module")
def serial(tmp_path_factory):
    url = str(tmp_path_factory.mktemp("serial") / "store")
    req = _request(store_raw=True)
    res = build(req, url, scheduler="sync")
    # one flake task per shipped α (catalogue and recipes) + 2 pigment blocks (3 bands, channel_block 2)
    n_flake = len(req.alphas["pearlescent"]) + sum(len(a) for a in req.distribution_alphas.get("pearlescent", {}).values())
    assert res["status"] == "built" and res["tasks_run"] == res["tasks_total"] == n_flake + 2
    return url, req, res


def test_content_hash_is_deterministic_and_sensitive():
    a, b = _request(), _request(species=list(reversed(SPECIES)))
    assert st.plan_build(a).version == st.plan_build(b).version
    assert st.plan_build(_request(rank_tol=1e-3)).version != st.plan_build(a).version
    assert st.plan_build(_request(alphas={"pearlescent": [0.2]})).version != st.plan_build(a).version
    changed = dict(a.species)
    changed["pearlescent"] = json.loads(json.dumps(changed["pearlescent"]))
    changed["pearlescent"]["coating"][0]["thickness_nm"]["value"] += 1
    assert st.content_hash({**a.inputs(), "species": changed}) != st.plan_build(a).version


def test_reader_values(serial):
    """Adapted to the format-2 readers (issue #11): the stored factors reproduce the direct projection
    of the flake's kernel on the stored nodes, the pigment's moments its Mie phase function."""
    from flakedb.paint import species as sp
    from flakedb.rt.scattering.media import FlakeMedium
    from flakedb.rt.scattering.microflake import FlakeOptics
    from flakedb.rt.adding.stack import project_medium
    from flakedb.rt.scattering.stored import StoredFlakeMedium
    from flakedb.store.compress import store_nodes

    url, req, res = serial
    v = st.open_version(url)
    assert v.version == res["version"] and v.species == sorted(SPECIES)
    assert st.schema_problems(v.metadata, "metadata") == []
    np.testing.assert_array_equal(v.wavelength_nm, [450.0, 550.0, 650.0])
    x, w = v.grid(8)
    np.testing.assert_array_equal(x, store_nodes(8)[0])
    f = v.flake_factors("pearlescent", 8, 0.25)
    assert f.U.shape[0] == 3 and np.all(np.isfinite(f.sigma_t))
    from flakedb.paint.components import adaptive_flake_optics
    e = req.species["pearlescent"]
    nb = sp.binder_index({"binder": req.binder}, np.array([450.0, 550.0, 650.0]))
    c, R, T, _ = adaptive_flake_optics(lambda cc: sp.flake_reflectance_transmittance(e, np.array([450.0, 550.0, 650.0]), cc, nb))
    direct, _ = project_medium(FlakeMedium(0.25, FlakeOptics(c, R, T), 1.0), x, w, 1e-5, 16, renormalize=False)
    stored, _ = project_medium(StoredFlakeMedium(f, 1.0, np.eye(3)), x, w, 1e-5, 16, renormalize=False)
    L = max(direct.n_orders, stored.n_orders)
    a, b = direct.blocks(0, L), stored.blocks(0, L)
    scale = max(np.abs(a[0]).max(), np.abs(a[1]).max())
    assert max(np.abs(a[0] - b[0]).max(), np.abs(a[1] - b[1]).max()) <= 1e-5 * scale
    pig = v.pigment("cadmium-yellow")
    assert pig["legendre_moments"].shape[0] == 3 and np.allclose(pig["legendre_moments"][:, 0], 1.0)
    assert np.all(pig["c_sca_um2"] <= pig["c_ext_um2"])
    with pytest.raises(st.StoreError, match="no species"):
        v.pigment("titanium-white")


def test_unchanged_inputs_do_no_work(serial):
    url, req, res = serial
    files = [p for p in Path(url).rglob("*") if p.is_file() and p.name != "latest"]
    before = {p: p.stat().st_mtime_ns for p in files}
    again = build(req, url, scheduler="sync")
    assert again["status"] == "reused" and again["tasks_run"] == 0 and again["version"] == res["version"]
    assert {p: p.stat().st_mtime_ns for p in files} == before


def test_distributed_build_is_bit_for_bit_the_serial_build(serial, tmp_path):
    from distributed import Client, LocalCluster

    url, req, res = serial
    url2 = str(tmp_path / "dist")
    with LocalCluster(n_workers=2, processes=True, threads_per_worker=1, dashboard_address=None) as cluster, \
            Client(cluster) as client:
        res2 = build(req, url2, client=client)
    assert res2["status"] == "built" and res2["version"] == res["version"]
    assert _checksums(url2, res2["version"]) == _checksums(url, res["version"])  # every chunk, byte for byte
    a, b = st.open_version(url), st.open_version(url2)
    fa, fb = a.flake_factors("pearlescent", 8, 0.25), b.flake_factors("pearlescent", 8, 0.25)
    assert np.array_equal(fa.U, fb.U) and np.array_equal(fa.read(0, fa.n_orders), fb.read(0, fb.n_orders))
    for k, x in a.pigment("cadmium-yellow").items():
        assert np.array_equal(x, b.pigment("cadmium-yellow")[k])


def test_interrupted_build_keeps_latest_and_resumes(serial, tmp_path):
    url = str(tmp_path / "store")
    old = build(_request(wavelength_nm=[500.0, 600.0]), url, scheduler="sync")
    req = _request()
    part = build(req, url, scheduler="threads", workers=2, max_tasks=1)
    assert part["status"] == "partial" and part["tasks_run"] == 1
    assert st.read_latest(url) == old["version"]
    assert st.open_version(url).version == old["version"]  # the previous version stays readable
    assert st.verify_store(url) == []
    problems = st.verify_version(url, part["version"])
    assert len(problems) == 1 and f"incomplete build (1 of {part['tasks_total']} tasks done)" in problems[0]
    with pytest.raises(st.StoreError, match="partial"):
        st.open_version(url, part["version"])
    # a task killed mid-way: garbage in one of its chunks, no record; the rerun overwrites it
    plan = st.plan_build(req)
    pending = st.pending_tasks(url, plan)
    key = st.task_chunk_keys(plan, pending[0])[0]
    chunk = Path(url) / "versions" / plan.version / key
    chunk.parent.mkdir(parents=True, exist_ok=True)
    chunk.write_bytes(b"half-written")
    done = build(req, url, scheduler="threads", workers=2)
    assert done["status"] == "built" and done["tasks_run"] == part["tasks_total"] - 1
    assert st.read_latest(url) == done["version"] and st.verify_store(url, all_versions=True) == []
    # resumed = built in one go (the serial fixture has the same inputs except store_raw)
    fresh = str(tmp_path / "fresh")
    build(req, fresh, scheduler="sync")
    assert _checksums(url, done["version"]) == _checksums(fresh, done["version"])


def test_corrupted_chunk_is_reported_and_refused(serial, tmp_path):
    import shutil

    url0, req, res = serial
    url = str(tmp_path / "copy")
    shutil.copytree(url0, url)
    key = "species/cadmium-yellow/legendre_moments/c/0/0"
    p = Path(url) / "versions" / res["version"] / key
    data = bytearray(p.read_bytes())
    data[len(data) // 2] ^= 0xFF
    p.write_bytes(bytes(data))
    r = CliRunner().invoke(cli, ["verify", url])
    assert r.exit_code == 1 and key in r.output and "corrupted" in r.output
    with pytest.raises(st.StoreIntegrityError, match="legendre_moments/c/0/0"):
        st.open_version(url)
    assert CliRunner().invoke(cli, ["verify", url0]).exit_code == 0


def test_cli_dry_run_builds_nothing(tmp_path):
    url = str(tmp_path / "none")
    r = CliRunner().invoke(cli, ["build", "--store", url, "--dry-run", "--n", "8",
                                 "--species", "metallic", "--step-nm", "100"])
    assert r.exit_code == 0, r.output
    # one task per (distribution, α) of metallic that the catalogue and the shipped recipes use (the plan's own count)
    tasks = len(st.plan_build(make_request(species=["metallic"], n=8, wavelength_nm=list(range(380, 781, 100)))).tasks)
    assert tasks >= 2 and f"{tasks} tasks" in r.output and "MiB" in r.output and "absent" in r.output
    assert not os.path.exists(url)
    r = CliRunner().invoke(cli, ["build", "--store", url, "--dry-run", "--n", "7"])
    assert r.exit_code == 2 and "even" in r.output


def test_build_to_an_fsspec_url_round_trips():
    """The store is any fsspec URL: a build into fsspec's in-memory filesystem verifies and reads
    back the same arrays as a local build (guards against local-path assumptions in store I/O)."""
    import numpy as np

    from flakedb.colour.colorimetry import spectral_grid
    from flakedb.pipelines.build import build, make_request
    from flakedb.store import versions as st

    req = make_request(species=["gray-mirror"], n=8, wavelength_nm=spectral_grid((400, 700), 100))
    url = "memory://flakedb-test-fsspec/store"
    assert build(req, url, scheduler="sync", progress=False)["status"] == "built"
    assert st.verify_store(url) == []
    import tempfile

    with tempfile.TemporaryDirectory() as d:
        build(req, d + "/store", scheduler="sync", progress=False)
        for k in ("U", "sigma_t"):
            a = getattr(st.open_version(url).flake_factors("gray-mirror", 8, 0.25), k)
            b = getattr(st.open_version(d + "/store").flake_factors("gray-mirror", 8, 0.25), k)
            np.testing.assert_array_equal(a, b)
        fa = st.open_version(url).flake_factors("gray-mirror", 8, 0.25)
        fb = st.open_version(d + "/store").flake_factors("gray-mirror", 8, 0.25)
        np.testing.assert_array_equal(fa.read(0, fa.n_orders), fb.read(0, fb.n_orders))


def _build_in_process(args):
    url, kw = args
    from flakedb.pipelines.build import build as _build

    return _build(_request(**kw), url, scheduler="sync")["status"]


def test_two_builds_at_once_do_not_corrupt_the_store(serial, tmp_path):
    """Two processes build the same version into one store at the same time (tasks re-run safely:
    chunk-aligned regions, template first), and a third builds another version beside them: every
    version verifies, the common one is byte-identical to the serial build, and `latest` points at
    a complete version."""
    import multiprocessing as mp

    url, req, res = serial
    url2 = str(tmp_path / "shared-store")
    jobs = [(url2, {"store_raw": True}), (url2, {"store_raw": True}), (url2, {"store_raw": False})]
    with mp.get_context("spawn").Pool(3) as pool:
        statuses = pool.map(_build_in_process, jobs)
    assert all(s in ("built", "reused") for s in statuses), statuses
    assert st.verify_store(url2, all_versions=True) == []
    assert _checksums(url2, res["version"]) == _checksums(url, res["version"])
    latest = st.read_latest(url2)
    assert st.version_state(url2, latest) == "complete"


def test_a_format_1_store_is_refused_with_rebuild(serial, tmp_path):
    """A store of the R-sample format (1) is refused with a one-line 'rebuild with flakedb build'
    (issue #11 changed the format; nothing of an old store is read as if it were new)."""
    import shutil

    url0, req, res = serial
    url = str(tmp_path / "old")
    shutil.copytree(url0, url)
    zj = Path(url) / "versions" / res["version"] / "zarr.json"
    doc = json.loads(zj.read_text())
    doc["attributes"]["format_version"] = 1
    zj.write_text(json.dumps(doc))
    with pytest.raises(st.StoreError, match="rebuild with `flakedb build"):
        st.open_version(url)
    assert any("rebuild with `flakedb build`" in p for p in st.verify_store(url))
