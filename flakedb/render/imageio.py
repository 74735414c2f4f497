"""Writing rendered images: OpenEXR (linear RGB float32) and PNG (sRGB-encoded 8-bit), atomically.

Both writers write to a temporary file in the target's directory and ``os.replace`` it onto the
target, so a reader never sees a half-written image and a failed write leaves nothing behind.

* :func:`write_exr` / :func:`read_exr` -- scanline OpenEXR, channels R, G, B as FLOAT (32-bit),
  ZIP compression, via the ``OpenEXR`` 3.x Python bindings.  Values are stored exactly
  (read -> equal float32).
* :func:`srgb_encode` -- the IEC 61966-2-1 transfer function (linear [0, 1] -> encoded [0, 1]).
* :func:`to_srgb8` / :func:`write_png` -- exposure (in stops), clip to [0, 1], sRGB-encode, round
  to 8 bits, RGB PNG via Pillow (matplotlib's image backend).
"""

from __future__ import annotations

import io
from pathlib import Path

import numpy as np

from flakedb.atomic import atomic_write

__all__ = ["write_exr", "read_exr", "srgb_encode", "to_srgb8", "write_png"]


def _check_rgb(rgb, name="image") -> np.ndarray:
    rgb = np.asarray(rgb)
    if rgb.ndim != 3 or rgb.shape[2] != 3 or rgb.shape[0] < 1 or rgb.shape[1] < 1:
        raise ValueError(f"{name} must be an (height, width, 3) RGB array, got shape {rgb.shape}")
    return rgb


def _atomic_write(path, write_tmp) -> Path:
    """Call ``write_tmp(tmp_path)`` on a temporary file next to ``path``, then rename it onto
    ``path`` (:func:`flakedb.atomic.atomic_write`; the temporary keeps the target's suffix)."""
    return atomic_write(path, write_tmp)


def write_exr(path, rgb) -> Path:
    """Write linear RGB ``rgb`` (H, W, 3) as a float32 scanline OpenEXR file (ZIP), atomically.

    Row 0 is the top of the image.  Returns the path."""
    import OpenEXR  # lazy: image codec only where images are written

    data = np.ascontiguousarray(_check_rgb(rgb), dtype=np.float32)
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}

    def write(tmp):
        # through memory: the binding takes a path only as UTF-8 text, so a folder whose name is not (a byte
        # 0xff, which the file system allows) failed with "use write(path: str)"; the bytes are written by Python
        buf = io.BytesIO()
        with OpenEXR.File(header, {"RGB": data}) as f:
            f.write(buf)
        Path(tmp).write_bytes(buf.getvalue())

    return _atomic_write(path, write)


def read_exr(path) -> np.ndarray:
    """Read an RGB OpenEXR file into a float32 (H, W, 3) array.

    A float32 image survives the round trip bit for bit (EXR is the renderer's linear format):

    >>> import tempfile
    >>> image = np.linspace(0.0, 2.0, 24, dtype=np.float32).reshape(2, 4, 3)
    >>> path = Path(tempfile.mkdtemp()) / "tiny.exr"
    >>> _ = write_exr(path, image)
    >>> back = read_exr(path)
    >>> back.dtype, back.shape, bool(np.array_equal(back, image))
    (dtype('float32'), (2, 4, 3), True)
    """
    import OpenEXR  # lazy: image codec only where images are written

    with open(path, "rb") as stream, OpenEXR.File(stream) as f:   # a stream: any file name (see write_exr)
        ch = f.channels()
        if "RGB" not in ch:
            raise ValueError(f"{path}: no R, G, B channels (has {sorted(ch)})")
        return np.asarray(ch["RGB"].pixels, dtype=np.float32)


def srgb_encode(linear) -> np.ndarray:
    """sRGB transfer function (IEC 61966-2-1): ``12.92 x`` for ``x <= 0.0031308``, else
    ``1.055 x^(1/2.4) - 0.055``.  Input clipped to [0, 1]; output in [0, 1]."""
    x = np.clip(np.asarray(linear, dtype=np.float64), 0.0, 1.0)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1.0 / 2.4) - 0.055)


def to_srgb8(rgb, exposure: float = 0.0) -> np.ndarray:
    """Linear RGB -> 8-bit sRGB: scale by ``2**exposure`` [stops], clip, encode, round.
    NaN counts as 0."""
    x = np.nan_to_num(np.asarray(rgb, dtype=np.float64), nan=0.0, posinf=1.0, neginf=0.0)
    return np.round(255.0 * srgb_encode(x * 2.0 ** float(exposure))).astype(np.uint8)


def write_png(path, rgb, exposure: float = 0.0) -> Path:
    """Write linear RGB ``rgb`` (H, W, 3) as an 8-bit sRGB PNG (see :func:`to_srgb8`), atomically."""
    from PIL import Image  # lazy: image codec only where images are written

    img = Image.fromarray(np.ascontiguousarray(to_srgb8(_check_rgb(rgb), exposure)))  # (H, W, 3) uint8 -> RGB

    def write(tmp):
        img.save(tmp, format="PNG")

    return _atomic_write(path, write)
