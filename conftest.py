"""pytest set-up shared by the tests and the package's doctests (pyproject.toml collects both)."""

import tempfile

import numpy as np
import pytest
from _pytest.doctest import DoctestItem


@pytest.fixture(autouse=True)
def _doctest_temporary_folder(request, monkeypatch):
    """A doctest's ``tempfile.mkdtemp()`` lands in pytest's own temporary folder for the test (which
    pytest prunes after a few runs), so the examples leave nothing in the system's temporary folder.

    A doctest also prints numpy values in numpy's current format, whatever ran before it in the same
    worker: colour-science switches the whole process to numpy's legacy 1.13 format when it is imported,
    which changes the spacing of printed arrays (``[ 100.,`` for ``[100.,``)."""
    if isinstance(request.node, DoctestItem):
        monkeypatch.setattr(tempfile, "tempdir", str(request.getfixturevalue("tmp_path")))
        with np.printoptions(legacy=False):
            yield
    else:
        yield
