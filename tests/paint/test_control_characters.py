"""flakedb.paint.checks' control-character scan (one regular expression) finds exactly Unicode's Cc characters,
the set its character-by-character message loop names."""

import sys
import unicodedata

from flakedb.paint.checks import _CONTROL, value_problems


def test_control_pattern_is_unicode_cc():
    cc = {c for c in range(sys.maxunicode + 1) if unicodedata.category(chr(c)) == "Cc"}
    found = {c for c in range(sys.maxunicode + 1) if _CONTROL.fullmatch(chr(c))}
    assert found == cc and len(cc) == 65


def test_every_control_character_is_reported_and_text_is_not():
    for c in (0x00, 0x09, 0x0A, 0x1F, 0x7F, 0x85, 0x9F):
        out = value_problems({"name": f"a{chr(c)}b"})
        assert out and f"U+{c:04X} at position 1" in out[0]
    assert value_problems({"name": "é — ü ∑ \u00a0\u2028 \ufeff", "description": "two\nlines\tok"}) == []
