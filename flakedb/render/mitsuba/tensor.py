"""The RGL / Mitsuba 3 "tensor file" (the layout of ``mitsuba.python.tensor_io``): write atomically,
read with checks.  What Mitsuba's ``measured`` BSDF loads (Dupuy & Jakob 2018)."""

from __future__ import annotations

import struct
from pathlib import Path

import numpy as np

from flakedb.atomic import atomic_path
from flakedb.render.mitsuba.directions import MeasuredExportError
from flakedb.safeio import FileTooLargeError, read_limited

#: Largest tensor file :func:`read_tensor_file` reads [bytes].
TENSOR_FILE_MAX_BYTES = 4 * 1024 ** 3
#: First bytes of a tensor file.
MAGIC_TENSOR = b"tensor_file\0"

_TENSOR_DTYPES = {np.dtype(np.uint8): 1, np.dtype(np.int8): 2, np.dtype(np.uint16): 3, np.dtype(np.int16): 4,
                  np.dtype(np.uint32): 5, np.dtype(np.int32): 6, np.dtype(np.uint64): 7, np.dtype(np.int64): 8,
                  np.dtype(np.float16): 9, np.dtype(np.float32): 10, np.dtype(np.float64): 11}


def write_tensor_file(path, fields: dict, align: int = 8) -> int:
    """Write an RGL/Mitsuba "tensor file" (the layout of ``mitsuba.python.tensor_io``), atomically.

    Header: ``tensor_file\\0``, version (1, 0) as two u8, u32 field count; per field: u16 name
    length, name, u16 ndim, u8 dtype code, u64 data offset, ndim x u64 shape; then each field's
    data, C order, little-endian, at an ``align``-byte boundary.  ``str`` values are stored as u8.
    Returns the file size [bytes].
    """
    arrays = {}
    for k, v in fields.items():
        a = np.frombuffer(v.encode("utf-8"), dtype=np.uint8) if isinstance(v, str) else np.ascontiguousarray(v)
        if a.dtype not in _TENSOR_DTYPES:
            raise ValueError(f"tensor field {k!r}: unsupported dtype {a.dtype}")
        arrays[k] = a.astype(a.dtype.newbyteorder("<"), copy=False)
    head = bytearray(b"tensor_file\0" + struct.pack("<BBI", 1, 0, len(arrays)))
    slots = {}
    for k, a in arrays.items():
        name = k.encode("utf-8")
        head += struct.pack("<H", len(name)) + name + struct.pack("<HB", a.ndim, _TENSOR_DTYPES[a.dtype])
        slots[k] = len(head)
        head += struct.pack("<Q", 0) + struct.pack("<" + "Q" * a.ndim, *a.shape)
    pos = len(head)
    offsets = {}
    for k, a in arrays.items():
        pos = (pos + align - 1) // align * align
        offsets[k] = pos
        struct.pack_into("<Q", head, slots[k], pos)
        pos += a.nbytes
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)

    with atomic_path(path, suffix="") as tmp:
        with open(tmp, "wb") as fh:
            fh.write(head)
            for k, a in arrays.items():
                fh.write(b"\0" * (offsets[k] - fh.tell()))
                fh.write(a.tobytes())
            size = fh.tell()
    return size


def read_tensor_file(path) -> dict:
    """Read a tensor file written by :func:`write_tensor_file` (or ``tensor_io``): name -> array.

    Checks what it reads (header, field count, dtype codes, shapes and offsets inside the file,
    finite floating-point values) and raises :class:`MeasuredExportError` naming the file and the
    field otherwise.

    A round trip (no Mitsuba needed):

    >>> import tempfile
    >>> path = Path(tempfile.mkdtemp()) / "paint.bsdf"
    >>> size = write_tensor_file(path, {"theta_i": np.linspace(0.0, 1.0, 3, dtype=np.float32), "description": "flakedb"})
    >>> back = read_tensor_file(path)
    >>> size == path.stat().st_size, str(back["theta_i"].dtype), back["theta_i"].tolist(), back["description"].tobytes()
    (True, 'float32', [0.0, 0.5, 1.0], b'flakedb')
    """
    codes = {v: k for k, v in _TENSOR_DTYPES.items()}
    path = Path(path)

    def bad(what):
        return MeasuredExportError(f"{path}: {what}; not a valid tensor file (corrupt or truncated)")

    try:
        raw = read_limited(path, TENSOR_FILE_MAX_BYTES)   # a regular file, at most the limit read
    except FileTooLargeError as e:
        raise MeasuredExportError(f"{path}: {e.size} bytes or more; the limit is {TENSOR_FILE_MAX_BYTES} bytes") from None
    except OSError as e:
        raise MeasuredExportError(f"{path}: cannot read ({e.strerror})") from None
    if raw[:12] != b"tensor_file\0" or raw[12:14] != b"\x01\x00":
        raise MeasuredExportError(f"{path}: not a version 1.0 tensor file")
    try:
        (count,) = struct.unpack_from("<I", raw, 14)
        if count > 1024:
            raise bad(f"field count {count} is outside the allowed range 0 ≤ count ≤ 1024")
        pos = 18
        out = {}
        for _ in range(count):
            (ln,) = struct.unpack_from("<H", raw, pos)
            name = raw[pos + 2:pos + 2 + ln].decode("utf-8")
            pos += 2 + ln
            ndim, code = struct.unpack_from("<HB", raw, pos)
            (off,) = struct.unpack_from("<Q", raw, pos + 3)
            if ndim > 16 or code not in codes:
                raise bad(f"field {name!r}: ndim {ndim} / dtype code {code} is not supported")
            shape = struct.unpack_from("<" + "Q" * ndim, raw, pos + 11)
            pos += 11 + 8 * ndim
            dt = codes[code].newbyteorder("<")
            count_el = int(np.prod(shape, dtype=object))
            if off + count_el * dt.itemsize > len(raw):
                raise bad(f"field {name!r}: shape {tuple(shape)} at offset {off} runs past the end of the "
                          f"{len(raw)}-byte file")
            a = np.frombuffer(raw, dt, count_el, off).reshape(shape)
            if a.dtype.kind == "f" and not np.all(np.isfinite(a)):
                raise bad(f"field {name!r} holds NaN or infinite values")
            out[name] = a
    except struct.error as e:
        raise bad(f"header ends early ({e})") from None
    except UnicodeDecodeError:
        raise bad("a field name is not UTF-8") from None
    return out

