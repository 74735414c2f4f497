"""A store's files through fsspec: URLs of versions, JSON documents written atomically, checksums, and a version's
state (docs/store.md "Layout").
"""

from __future__ import annotations

import errno
import hashlib
import json
import posixpath
import re
import uuid
from pathlib import Path

import fsspec
from fsspec.implementations.local import LocalFileSystem

from flakedb.safeio import FileTooLargeError, read_limited
from flakedb.store.errors import StoreError, StoreIntegrityError  # noqa: F401  (re-exported)

#: A version name: the content hash (hex) that :func:`plan_build` makes; nothing else is read as one.
VERSION_RE = re.compile(r"^[0-9a-f]{8,128}$")


#: Largest store file read whole (a chunk, a zarr.json, checksums.json) [bytes].
MAX_STORE_FILE_BYTES = 512 * 1024 ** 2


#: Most chunks one stored array may declare (a catalogue build has at most a few thousand).
MAX_ARRAY_CHUNKS = 1_000_000


def open_fs(url):
    """``(filesystem, root)`` of a store URL; an unknown scheme, a protocol whose package is missing or a
    malformed URL is a :class:`StoreError` in words (not an internal error)."""
    text = str(url)
    if not text.strip() or re.fullmatch(r"[A-Za-z][A-Za-z0-9+.-]*://+", text.strip()) or "\0" in text:
        raise StoreError(f"--store {url!r}: an empty store path or URL (hint: give a directory, e.g. --store "
                         f"flakedb-store, or a URL such as s3://bucket/store)")
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
    if isinstance(fs, LocalFileSystem):
        try:
            return read_limited(path, limit)
        except FileTooLargeError as exc:
            raise OSError(errno.EFBIG, f"more than the limit of {limit:,} bytes for one store file", path) from exc
    size = fs.size(path)
    if size is not None and size > limit:
        raise OSError(errno.EFBIG, f"{size:,} bytes, more than the limit of {limit:,} for one store file", path)
    return fs.cat_file(path)


def _join(url, *parts):
    url = str(url).rstrip("/")
    return posixpath.join(url, *parts) if "://" in url else str(Path(url).joinpath(*parts))


def version_url(url, version):
    return _join(url, "versions", version)


def read_json(fs, path):
    return json.loads(cat(fs, path, 64 * 1024 ** 2).decode("utf-8"))


def write_json(fs, path, doc):
    """Write a JSON document whole: to a temporary name, then renamed (a reader never sees half of it)."""
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
