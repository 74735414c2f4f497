"""flakedb.process: the allocator setting the command line applies (and its opt-out)."""

import ctypes.util
import platform

import pytest

from flakedb.process import tune_allocator


def test_opt_out_leaves_the_allocator_alone(monkeypatch):
    monkeypatch.setenv("FLAKEDB_MALLOC_TUNING", "0")
    assert tune_allocator() is False


@pytest.mark.skipif(platform.system() != "Linux" or platform.libc_ver()[0] != "glibc", reason="glibc's mallopt")
def test_applied_on_glibc(monkeypatch):
    monkeypatch.delenv("FLAKEDB_MALLOC_TUNING", raising=False)
    assert ctypes.util.find_library("c")
    assert tune_allocator() is True
