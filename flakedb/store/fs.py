"""A store's files: URLs of versions, JSON documents written atomically, checksums, and a version's
state (docs/store.md "Layout").

A store is any fsspec URL.  Reading a local directory needs none of fsspec: its import (with asyncio, its
caching and compression registries) is 25–30 ms of a 0.7 s whole-process compose, so :func:`open_fs` reads a
plain local path through :class:`LocalFiles` (the few calls a reader makes, on ``os``) and imports fsspec only
for a URL or for writing (``writable=True``: a build, a repair).
"""

from __future__ import annotations

import datetime
import errno
import hashlib
import json
import os
import posixpath
import re
import uuid
from pathlib import Path

from flakedb.safeio import FileTooLargeError, read_limited
from flakedb.store.errors import StoreError, StoreIntegrityError  # noqa: F401  (re-exported)

#: A version name: the content hash (hex) that :func:`plan_build` makes; nothing else is read as one.
VERSION_RE = re.compile(r"^[0-9a-f]{8,128}$")


#: Largest store file read whole (a chunk, a zarr.json, checksums.json) [bytes].
MAX_STORE_FILE_BYTES = 512 * 1024 ** 2


#: Most chunks one stored array may declare (a catalogue build has at most a few thousand).
MAX_ARRAY_CHUNKS = 1_000_000


class LocalFiles:
    """The reading calls of an fsspec filesystem that a store reader makes, for a local directory, on ``os``
    (module docstring): ``exists``, ``ls(path, detail=False)``, ``modified``, ``size``, ``cat_file``, with the
    values fsspec's ``LocalFileSystem`` gives (paths absolute, posix, as :func:`local_root` makes them).
    Nothing here writes: :func:`open_fs` with ``writable=True`` gives fsspec's own."""

    protocol = ("file", "local")

    @staticmethod
    def exists(path):
        return os.path.exists(path)  # a dangling symlink is absent, as fsspec's info() that follows it

    @staticmethod
    def ls(path, detail=False):
        if detail:
            raise NotImplementedError("LocalFiles.ls lists names only (detail=False)")
        if not os.path.isdir(path):
            if not os.path.exists(path):
                raise FileNotFoundError(errno.ENOENT, os.strerror(errno.ENOENT), path)
            return [path]
        with os.scandir(path) as it:
            return [posixpath.join(path, e.name) for e in it]

    @staticmethod
    def modified(path):
        return datetime.datetime.fromtimestamp(os.stat(path).st_mtime, tz=datetime.UTC)

    @staticmethod
    def size(path):
        return os.stat(path).st_size

    @staticmethod
    def cat_file(path):
        return read_limited(path, MAX_STORE_FILE_BYTES)


def local_root(text):
    """The root fsspec's ``LocalFileSystem`` makes of a plain local path: ``~`` expanded, a relative path
    joined to the working directory (a leading ``./`` or ``.`` dropped), trailing ``/`` removed.

    >>> local_root("/tmp/store/"), local_root("~/s") == os.path.expanduser("~/s")
    ('/tmp/store', True)
    >>> local_root("./s") == os.getcwd() + "/s"
    True
    """
    path = str(text)
    if path.startswith("~"):
        path = os.path.expanduser(path)
    elif not path.startswith("/"):
        path = path[2:] if path.startswith("./") else ("" if path == "." else path)
        path = f"{os.getcwd()}/{path}"
    return path.rstrip("/") or "/"


def is_local_path(text) -> bool:
    """A plain local path on a POSIX system, read without fsspec: no URL scheme (``://``), no fsspec chain
    (``::``) and none of the ``file:`` / ``local:`` prefixes fsspec's LocalFileSystem strips (those go to fsspec).

    >>> [is_local_path(t) for t in ("store", "/tmp/s", "my:store", "file:/tmp/s", "local:/s", "s3://b/s")]
    [True, True, True, False, False, False]
    """
    return (os.sep == "/" and "://" not in text and "::" not in text
            and not text.startswith(("file:", "local:")))


def open_fs(url, writable=False):
    """``(filesystem, root)`` of a store URL; an unknown scheme, a protocol whose package is missing or a
    malformed URL is a :class:`StoreError` in words (not an internal error).  A plain local path, unless
    ``writable``, is read through :class:`LocalFiles` (module docstring); everything else through fsspec."""
    text = str(url)
    if not text.strip() or re.fullmatch(r"[A-Za-z][A-Za-z0-9+.-]*://+", text.strip()) or "\0" in text:
        raise StoreError(f"--store {url!r}: an empty store path or URL (hint: give a directory, e.g. --store "
                         f"flakedb-store, or a URL such as s3://bucket/store)")
    if not writable and is_local_path(text):
        return LocalFiles(), local_root(text)
    import fsspec  # lazy: 25–30 ms to import (module docstring); a local store is read without it

    try:
        return fsspec.core.url_to_fs(text)
    except ImportError as exc:
        raise StoreError(f"--store {url}: this URL's protocol needs a package that is not installed ({exc}) "
                         f"(hint: install the package the message names)") from None
    except (ValueError, TypeError, KeyError) as exc:
        scheme = str(url).split("://", 1)[0] if "://" in str(url) else ""
        raise StoreError(f"--store {url}: not a store path or URL fsspec knows ({'scheme ' + repr(scheme) + ': ' if scheme else ''}"
                         f"{exc}) (hint: a local directory, or file://, s3://, gs://, memory://...)") from None


def check_version_name(url, version, where="version"):
    """Refuse a version name that is not a content hash (``latest`` pointing at ``../..``, a path).

    >>> check_version_name("store", "0123abcd")
    '0123abcd'
    >>> check_version_name("store", "../../etc")
    Traceback (most recent call last):
    ...
    flakedb.store.errors.StoreError: store: version '../../etc' is not a version hash (hex digits); ...
    """
    if not isinstance(version, str) or not VERSION_RE.match(version):
        raise StoreError(f"{url}: {where} {version!r:.80} is not a version hash (hex digits); it would point outside "
                         f"versions/ (hint: remove `latest` and rerun `flakedb build` with the same inputs, which "
                         f"rewrites it)")
    return version


def cat(fs, path, limit=MAX_STORE_FILE_BYTES) -> bytes:
    """The bytes of one store file, at most ``limit``: on a local store a regular file only
    (:func:`flakedb.safeio.read_limited`: a chunk symlinked to /dev/zero or a FIFO is refused, not read
    until memory runs out); elsewhere its size is checked first."""
    if _is_local(fs):
        try:
            return read_limited(path, limit)
        except FileTooLargeError as exc:
            raise OSError(errno.EFBIG, f"more than the limit of {limit:,} bytes for one store file", path) from exc
    size = fs.size(path)
    if size is not None and size > limit:
        raise OSError(errno.EFBIG, f"{size:,} bytes, more than the limit of {limit:,} for one store file", path)
    return fs.cat_file(path)


def _is_local(fs) -> bool:
    """Whether ``fs`` is a local filesystem (:class:`LocalFiles`, or fsspec's ``LocalFileSystem``: protocol
    ``file``), without importing fsspec."""
    protocol = getattr(fs, "protocol", ())
    return "file" in ((protocol,) if isinstance(protocol, str) else tuple(protocol))


def _join(url, *parts):
    url = str(url).rstrip("/")
    return posixpath.join(url, *parts) if "://" in url else str(Path(url).joinpath(*parts))


def version_url(url, version):
    return _join(url, "versions", version)


def read_json(fs, path):
    return json.loads(cat(fs, path, 64 * 1024 ** 2).decode("utf-8"))


def write_json(fs, path, doc):
    """Write a JSON document whole: to a temporary name, then renamed (a reader never sees half of it);
    ``fs`` from :func:`open_fs` with ``writable=True``."""
    fs.makedirs(posixpath.dirname(path), exist_ok=True)
    tmp = posixpath.join(posixpath.dirname(path), f".tmp-{uuid.uuid4().hex}")
    fs.pipe_file(tmp, (json.dumps(doc, indent=1, sort_keys=True) + "\n").encode("utf-8"))
    fs.mv(tmp, path)


def sha256(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def version_state(url, version) -> str:
    """'absent', 'partial' (template written, not complete) or 'complete'."""
    fs, root = open_fs(url)
    base = posixpath.join(root, "versions", version)
    if fs.exists(posixpath.join(base, "complete")):
        return "complete"
    zj = posixpath.join(base, "zarr.json")
    try:
        if fs.exists(zj) and "version" in (read_json(fs, zj).get("attributes") or {}):
            return "partial"  # the metadata goes in last when the template is written
    except (OSError, ValueError, UnicodeDecodeError, AttributeError, TypeError) as exc:
        raise StoreError(f"{url}: versions/{version}/zarr.json is unreadable "
                         f"({getattr(exc, 'strerror', None) or exc}); remove that version or rebuild it") from None
    return "absent"
