#!/usr/bin/env bash
# Blender's bpy (Cycles as a Python module) in a virtual environment of its own, for the Cycles test
# (tests/export/test_renderers.py::test_cycles_matches_preview).  `make test` runs it through
# `make blender-venv`; it never fails the build.
#
#   tools/blender_venv.sh [PYTHON] [VENV]
#
# PYTHON  a CPython 3.11 (default: python3.11 on PATH, else python3 if it is 3.11): bpy 5.0.1 has wheels
#         for CPython 3.11 only.
# VENV    the environment to make (default: .venv-blender, git-ignored).
#
# Why its own environment: bpy pins numpy < 2 in its metadata, so installing it next to flakedb
# would downgrade flakedb's numpy.  The render script imports only bpy, mathutils and the standard
# library, so the environment holds nothing else (bpy's own requirements: numpy 1.26, ...).
# Download ~375 MB (the bpy wheel), ~1 GB installed; measured 25 s on a fast link.
#
# Success writes VENV/.installed; failure (no Python 3.11, no network, no wheel for this platform)
# writes VENV/UNAVAILABLE with the reason (the test skips with it) and VENV/.installed as well, so
# that a second `make test` does not try again: remove VENV to retry.
# FLAKEDB_BLENDER_PYTHON set: the test uses that interpreter, and nothing is installed.
set -uo pipefail
PYTHON=${1:-python3.11}
VENV=${2:-.venv-blender}
BPY_SPEC="bpy==5.0.1"          # the Cycles version the test's prediction and tolerances were checked with

if [ -n "${FLAKEDB_BLENDER_PYTHON:-}" ]; then
  echo "blender-venv: FLAKEDB_BLENDER_PYTHON=$FLAKEDB_BLENDER_PYTHON is used; nothing installed"
  exit 0
fi

unavailable() {
  mkdir -p "$VENV"
  printf '%s\n' "$1" > "$VENV/UNAVAILABLE"
  touch "$VENV/.installed"
  echo "blender-venv: $1 (the Cycles test will skip; remove $VENV to retry)"
  exit 0
}

if ! command -v "$PYTHON" >/dev/null 2>&1 && [ "$PYTHON" = python3.11 ] && command -v python3 >/dev/null 2>&1; then
  PYTHON=python3                 # no python3.11 on PATH: python3 may be one (checked next)
fi
if ! command -v "$PYTHON" >/dev/null 2>&1; then
  unavailable "no $PYTHON on PATH ($BPY_SPEC needs CPython 3.11; make BLENDER_PY=/path/to/python3.11)"
fi
version=$("$PYTHON" -c 'import sys; print("%d.%d" % sys.version_info[:2])' 2>/dev/null)
if [ "$version" != "3.11" ]; then
  unavailable "$PYTHON is Python ${version:-?}, $BPY_SPEC needs CPython 3.11 (make BLENDER_PY=/path/to/python3.11)"
fi
rm -f "$VENV/UNAVAILABLE"
if ! [ -x "$VENV/bin/python" ]; then
  "$PYTHON" -m venv "$VENV" || unavailable "$PYTHON -m venv $VENV failed"
fi
start=$(date +%s)
if ! log=$("$VENV/bin/python" -m pip install --disable-pip-version-check --retries 2 --timeout 60 --quiet "$BPY_SPEC" 2>&1); then
  unavailable "pip install $BPY_SPEC failed: $(printf '%s' "$log" | tail -n 1)"
fi
if ! "$VENV/bin/python" -c "import bpy" >/dev/null 2>&1; then
  unavailable "$BPY_SPEC installed but 'import bpy' fails: $("$VENV/bin/python" -c 'import bpy' 2>&1 | tail -n 1)"
fi
touch "$VENV/.installed"
echo "blender-venv: $BPY_SPEC in $VENV ($(( $(date +%s) - start )) s)"
