"""Atomic file writes: write a temporary file beside the target, then ``os.replace`` it.

Nothing half-written is ever visible under the target's name, and the result gets the ordinary
permissions of a new file (0666 less the process umask), not ``mkstemp``'s 0600.
"""

import contextlib
import os
import tempfile
from pathlib import Path

from flakedb.outputs import temp_prefix


def _new_file_mode():
    umask = os.umask(0)
    os.umask(umask)
    return 0o666 & ~umask


def temp_beside(path, suffix=None):
    """``(fd, tmp)``: an open temporary file in ``path``'s directory (created if needed), named
    ``.NAME.flakedb-tmp-HOST-PID-XXXX.tmpSUFFIX`` (the target's suffix by default: some writers pick the
    format by it; the tag lets :func:`flakedb.outputs.sweep_stale` find what a killed run left)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=temp_prefix(path.name),
                               suffix=".tmp" + (path.suffix if suffix is None else suffix))
    os.fchmod(fd, _new_file_mode())
    return fd, tmp


@contextlib.contextmanager
def atomic_path(path, suffix=None):
    """Context manager: yields the path of a temporary file beside ``path`` to write; when the block
    ends normally the file is renamed onto ``path``, on any error it is removed and the target is
    untouched.  ``suffix`` as in :func:`temp_beside`."""
    fd, tmp = temp_beside(path, suffix)
    os.close(fd)
    try:
        yield tmp
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


def atomic_write(path, write_tmp):
    """Call ``write_tmp(tmp_path)`` on a temporary file beside ``path``, then rename it onto
    ``path``; on any error the temporary file is removed and the target is untouched.

    A round trip, and a failed write that leaves the old file and no temporary file behind:

    >>> import tempfile
    >>> d = Path(tempfile.mkdtemp())
    >>> atomic_write_text(d / "a.txt", "first").read_text()
    'first'
    >>> def fail(tmp):
    ...     Path(tmp).write_text("half")
    ...     raise OSError("disk full")
    >>> atomic_write(d / "a.txt", fail)
    Traceback (most recent call last):
    ...
    OSError: disk full
    >>> (d / "a.txt").read_text(), sorted(p.name for p in d.iterdir())
    ('first', ['a.txt'])
    >>> import shutil; shutil.rmtree(d)
    """
    with atomic_path(path) as tmp:
        write_tmp(tmp)
    return Path(path)


def atomic_write_text(path, text):
    """Write ``text`` (UTF-8) to ``path`` atomically."""
    return atomic_write(path, lambda tmp: Path(tmp).write_text(text, encoding="utf-8"))
