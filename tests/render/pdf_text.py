"""A small reader of the PDFs matplotlib writes, for tests (no PDF library is a dependency): the structure
(header, cross-reference table, page tree, media box, document information) and the text of every
``[...] TJ`` operator in the FlateDecode content streams, with matplotlib's kerning numbers dropped."""

import re
import zlib


def pdf_structure(data: bytes) -> dict:
    """{"pages": /Count of the page tree, "kids": page object numbers, "mediabox": [x0, y0, x1, y1] of each page,
    "info": {key: text} of the document information dictionary}; AssertionError when the cross-reference
    table does not point every in-use object at its ``N 0 obj`` (a truncated or corrupt file)."""
    assert data.startswith(b"%PDF-1.") and data.rstrip().endswith(b"%%EOF"), "not a complete PDF"
    start = int(re.findall(rb"startxref\s+(\d+)", data)[-1])
    assert data[start:start + 4] == b"xref", "startxref does not point at the xref table"
    m = re.match(rb"xref\s+(\d+)\s+(\d+)\s+", data[start:])
    first, count = int(m.group(1)), int(m.group(2))
    table = data[start + m.end():start + m.end() + 20 * count]
    objects = {}
    for k in range(count):
        off, gen, kind = table[20 * k:20 * k + 18].split()
        if kind == b"n":
            num = first + k
            assert re.match(rb"%d\s+%d\s+obj" % (num, int(gen)), data[int(off):int(off) + 30]), f"object {num}"
            end = data.index(b"endobj", int(off))
            objects[num] = data[int(off):end]
    trailer = data[start:]
    root = int(re.search(rb"/Root\s+(\d+)\s+0\s+R", trailer).group(1))
    pages_ref = int(re.search(rb"/Pages\s+(\d+)\s+0\s+R", objects[root]).group(1))
    pages = objects[pages_ref]
    assert b"/Type /Pages" in pages
    kids = [int(x) for x in re.findall(rb"(\d+)\s+0\s+R", re.search(rb"/Kids\s*\[([^\]]*)\]", pages).group(1))]
    boxes = []
    for k in kids:
        assert b"/Type /Page" in objects[k]
        box = re.search(rb"/MediaBox\s*\[([^\]]*)\]", objects[k]) or re.search(rb"/MediaBox\s*\[([^\]]*)\]", pages)
        boxes.append([float(v) for v in box.group(1).split()])
    info = {}
    ref = re.search(rb"/Info\s+(\d+)\s+0\s+R", trailer)
    if ref:
        for key, val in re.findall(rb"/(\w+)\s*\(((?:\\.|[^\\)])*)\)", objects[int(ref.group(1))]):
            info[key.decode()] = _unescape(val)
    return {"pages": int(re.search(rb"/Count\s+(\d+)", pages).group(1)), "kids": kids, "mediabox": boxes,
            "info": info}


def _unescape(s: bytes) -> str:
    return re.sub(rb"\\(.)", rb"\1", s).decode("latin-1")


def pdf_texts(data: bytes) -> list:
    """The strings of every ``[...] TJ`` in the FlateDecode streams, each array's pieces joined."""
    out = []
    for s in re.findall(rb"stream\r?\n(.*?)\r?\nendstream", data, re.S):
        try:
            d = zlib.decompress(s)
        except zlib.error:
            continue
        for arr in re.findall(rb"\[(.*?)\]\s*TJ", d, re.S):
            out.append(_unescape(b"".join(re.findall(rb"\(((?:\\.|[^\\)])*)\)", arr))))
    return out
