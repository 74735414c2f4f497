"""Which Python interpreter runs Blender's ``bpy`` for the Cycles test (an edge-of-system choice, so
it lives with the tests, not in flakedb): ``$FLAKEDB_BLENDER_PYTHON`` if set, else the repository's
``.venv-blender/bin/python`` if it exists (``make blender-venv``, which ``make test`` runs:
tools/blender_venv.sh), else this interpreter.  bpy pins numpy < 2 and is built for CPython 3.11
only, so it is kept out of flakedb's own environment."""

import os
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
BLENDER_VENV = REPO / ".venv-blender"


def blender_python() -> tuple[str, str]:
    """(the interpreter the Cycles test hands to :func:`flakedb.export.blender.render_cycles_sphere`,
    a note for the skip reason: why ``make blender-venv`` could not install bpy, if it said so)."""
    env = os.environ.get("FLAKEDB_BLENDER_PYTHON", "").strip()
    if env:
        return env, " (FLAKEDB_BLENDER_PYTHON)"
    venv = BLENDER_VENV / "bin" / "python"
    why = BLENDER_VENV / "UNAVAILABLE"
    note = f"; make blender-venv: {why.read_text(encoding='utf-8').strip()}" if why.exists() else (
        "" if venv.exists() else "; no .venv-blender (make blender-venv installs bpy there)")
    return (str(venv) if venv.exists() else sys.executable), note
