"""Reading only what the user named (issue 25): regular files only, and at most a limit of bytes.

Every reader of a user-named file (recipe, catalogue, target CSV, CxF3, ``.bsdf``, ``.h5``, Mitsuba
tensor, store files) goes through :func:`check_regular` or :func:`read_limited`:

* the path must name a **regular file**; a symlink is followed only when it ends at one.  A FIFO
  would block the reader forever, a character device (``/dev/zero``, ``/dev/urandom``) never ends
  and reports size 0 to ``stat``, a socket or a directory is not a file;
* :func:`read_limited` opens without blocking (``O_NONBLOCK``, so a FIFO swapped in after the check
  cannot hang the open), checks the *opened* file again with ``fstat``, and reads at most
  ``limit + 1`` bytes, so a file that grows, or lies about its size, is refused and never read
  past its limit.

Errors are :class:`OSError` subclasses with a ``strerror`` in words, so a reader's existing
``except OSError`` (``"cannot read (…)"``) names the file and the reason.
"""

from __future__ import annotations

import errno
import os
import stat
from pathlib import Path


class NotRegularFileError(OSError):
    """The path is not a regular file (FIFO, device, socket, directory, or a symlink to one)."""


class FileTooLargeError(OSError):
    """The file holds more than the reader's limit; ``size`` is what was seen (at least limit + 1)."""

    def __init__(self, path, size, limit):
        super().__init__(errno.EFBIG, f"more than the limit of {limit:,} bytes ({size:,} bytes or more)", str(path))
        self.size = size
        self.limit = limit


_KINDS = ((stat.S_ISFIFO, "a FIFO (named pipe)"), (stat.S_ISCHR, "a character device"),
          (stat.S_ISBLK, "a block device"), (stat.S_ISSOCK, "a socket"), (stat.S_ISDIR, "a directory"))


def kind_of(mode) -> str:
    """What a ``st_mode`` that is not a regular file is, in words."""
    for test, words in _KINDS:
        if test(mode):
            return words
    return "not a regular file"


def _refuse(path, mode):
    via = " (through a symbolic link)" if os.path.islink(path) else ""
    return NotRegularFileError(errno.EINVAL, f"{kind_of(mode)}{via}, not a regular file: flakedb reads only "
                                             f"regular files", str(path))


def check_regular(path) -> os.stat_result:
    """``os.stat`` of ``path`` (symlinks followed) when it is a regular file, else
    :class:`NotRegularFileError`; FileNotFoundError as usual."""
    st = os.stat(path)
    if not stat.S_ISREG(st.st_mode):
        raise _refuse(path, st.st_mode)
    return st


def read_limited(path, limit: int) -> bytes:
    """The bytes of the regular file ``path``, at most ``limit``; :class:`FileTooLargeError` when it
    holds more (only ``limit + 1`` bytes are ever read), :class:`NotRegularFileError` for anything
    that is not a regular file (module docstring).

    >>> import tempfile
    >>> d = tempfile.mkdtemp()
    >>> p = os.path.join(d, "a.txt")
    >>> _ = open(p, "w").write("hello")
    >>> read_limited(p, 5)
    b'hello'
    >>> for bad in ((p, 4), (d, 4)):
    ...     try:
    ...         read_limited(*bad)
    ...     except OSError as e:
    ...         print(type(e).__name__, e.strerror)
    FileTooLargeError more than the limit of 4 bytes (5 bytes or more)
    NotRegularFileError a directory, not a regular file: flakedb reads only regular files
    """
    path = Path(path)
    check_regular(path)   # before open: opening some devices has effects
    fd = os.open(path, os.O_RDONLY | getattr(os, "O_NONBLOCK", 0) | getattr(os, "O_NOCTTY", 0))
    try:
        st = os.fstat(fd)
        if not stat.S_ISREG(st.st_mode):   # swapped after the check
            raise _refuse(path, st.st_mode)
        if st.st_size > limit:
            raise FileTooLargeError(path, st.st_size, limit)
        chunks, total = [], 0
        # the file's size (and one byte more: a file grown past the limit shows) in one read, then 1 MiB pieces
        # for whatever it grew by: no join copy for a file read whole (a store chunk of 6-10 MB: 2 ms each)
        step = min(st.st_size + 1, limit + 1)
        while total <= limit:
            b = os.read(fd, min(step, limit + 1 - total))
            if not b:
                break
            chunks.append(b)
            total += len(b)
            step = 1 << 20
        if total > limit:
            raise FileTooLargeError(path, total, limit)
        return chunks[0] if len(chunks) == 1 else b"".join(chunks)
    finally:
        os.close(fd)


def read_text_limited(path, limit: int, encoding="utf-8") -> str:
    """:func:`read_limited` decoded (UnicodeDecodeError as usual)."""
    return read_limited(path, limit).decode(encoding)


def read_head(path, nbytes: int) -> bytes:
    """The first ``nbytes`` of the regular file ``path`` (fewer when it is shorter), for telling
    formats apart by their magic bytes; refuses what is not a regular file."""
    path = Path(path)
    check_regular(path)
    fd = os.open(path, os.O_RDONLY | getattr(os, "O_NONBLOCK", 0) | getattr(os, "O_NOCTTY", 0))
    try:
        st = os.fstat(fd)
        if not stat.S_ISREG(st.st_mode):
            raise _refuse(path, st.st_mode)
        return os.read(fd, nbytes)
    finally:
        os.close(fd)
