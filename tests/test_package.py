"""The package as a user gets it: the doctested example of ``flakedb/__init__.py``, and a built wheel
(not an editable install) that carries its catalogue and schemas and composes a recipe from another
directory.  Guards against data found by repository-relative paths (issue #10)."""

import doctest
import glob
import os
import shutil
import subprocess
import sys
import zipfile

import pytest

import flakedb

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def test_package_docstring_example():
    res = doctest.testmod(flakedb, verbose=False)
    assert res.attempted >= 8 and res.failed == 0


@pytest.mark.slow
def test_built_wheel_carries_its_data_and_composes(tmp_path):
    wheel_dir = tmp_path / "wheel"
    # a wheel built the way `pip install .` builds it (isolated build environment)
    subprocess.run([sys.executable, "-m", "pip", "wheel", "--no-deps", "-q", REPO, "-w", str(wheel_dir)],
                   check=True, capture_output=True)
    (whl,) = glob.glob(str(wheel_dir / "flakedb-*.whl"))
    names = set(zipfile.ZipFile(whl).namelist())
    for needed in ("flakedb/catalog/particles.yaml", "flakedb/catalog/materials/materials.yaml",
                   "flakedb/catalog/recipes/tri-coat-pearl-white.yaml", "flakedb/schemas/recipe.schema.json",
                   "flakedb/schemas/catalog.schema.json", "flakedb/schemas/store.schema.json"):
        assert needed in names, needed
    target = tmp_path / "site"
    subprocess.run([sys.executable, "-m", "pip", "install", "--no-deps", "-q", "--target", str(target), whl],
                   check=True, capture_output=True)
    work = tmp_path / "elsewhere"
    work.mkdir()
    shutil.copy(os.path.join(REPO, "flakedb", "catalog", "recipes", "research-hg-slab.yaml"), work / "r.yaml")
    env = dict(os.environ, PYTHONPATH=str(target))
    where = subprocess.run([sys.executable, "-c", "import flakedb; print(flakedb.__file__)"], cwd=work, env=env,
                           check=True, capture_output=True, text=True).stdout.strip()
    assert where.startswith(str(target)), where          # the installed copy, not the checkout
    r = subprocess.run([sys.executable, "-m", "flakedb", "compose", "r.yaml", "--out", "out", "--n", "16"],
                       cwd=work, env=env, capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    assert sorted(os.listdir(work / "out")) == ["research-hg-slab.bsdf", "research-hg-slab.h5", "research-hg-slab.json"]
