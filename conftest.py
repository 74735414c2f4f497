"""pytest set-up shared by the tests and the package's doctests (pyproject.toml collects both)."""

import tempfile

import pytest
from _pytest.doctest import DoctestItem


@pytest.fixture(autouse=True)
def _doctest_temporary_folder(request, monkeypatch):
    """A doctest's ``tempfile.mkdtemp()`` lands in pytest's own temporary folder for the test (which
    pytest prunes after a few runs), so the examples leave nothing in the system's temporary folder."""
    if isinstance(request.node, DoctestItem):
        monkeypatch.setattr(tempfile, "tempdir", str(request.getfixturevalue("tmp_path")))
