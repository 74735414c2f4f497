#!/usr/bin/env bash
# Build layerlab (W. Jakob, github.com/wjakob/layerlab) as a Python extension for one interpreter,
# so that bench/bench_layerlab.py can time it next to flakedb in the same run (issues #11, #26).
#
#   tools/build_layerlab.sh SRC PREFIX [PYTHON]
#
# SRC     a layerlab checkout (its ext/ submodules may be empty: system packages replace them).
#         If SRC does not exist and LAYERLAB_GIT is set to a git dir (bare is fine), HEAD is exported there.
# PREFIX  where layerlab.*.so is installed (then: PYTHONPATH=PREFIX python -c "import layerlab").
# PYTHON  the interpreter to build for (default: python3 on PATH).
#
# Debian 12 packages needed (they replace the ext/ submodules eigen, tbb and pybind11):
#   apt-get install -y --no-install-recommends cmake g++ make pkg-config \
#       libeigen3-dev libfftw3-dev libtbb-dev pybind11-dev
# The header-only submodules ext/tinyformat (github.com/wjakob/tinyformat) and ext/filesystem
# (github.com/wjakob/filesystem) must be present: set TINYFORMAT_GIT / FILESYSTEM_GIT to their git dirs
# to have them exported into SRC/ext, or check the submodules out.
#
# Patches applied to the source (layerlab HEAD 3e5257e, 2017), all in the build system, none in the
# numerics:
#   1. CMakeLists.txt: ext/tbb and ext/pybind11 are not added as subdirectories; the system oneTBB
#      (TBB::tbb) and pybind11 (pybind11Config.cmake) are used instead; Eigen from /usr/include/eigen3.
#   2. -flto is dropped (g++ 12 + pybind11 2.10 link is slow with it on 2 cores; no numeric effect).
#   3. -std=c++14 -> -std=gnu++14: include/layer/math.h uses hexadecimal float literals
#      (0x1.fffffffffffff7p-1), which strict C++14 rejects in g++ 12.
#   4. include/layer/math.h: #include <limits> added (std::numeric_limits; older libstdc++ pulled it in
#      through <algorithm>).
# MAKE_JOBS (default 1) sets make's -j; the build runs under nice.
set -euo pipefail

SRC=${1:?usage: build_layerlab.sh SRC PREFIX [PYTHON]}
PREFIX=${2:?usage: build_layerlab.sh SRC PREFIX [PYTHON]}
PYTHON=${3:-python3}
JOBS=${MAKE_JOBS:-1}

export_git() {  # export_git GITDIR DEST: the HEAD tree of GITDIR into DEST
  mkdir -p "$2"
  git --git-dir="$1" archive HEAD | tar -x -C "$2"
}

if [ ! -e "$SRC/CMakeLists.txt" ]; then
  : "${LAYERLAB_GIT:?$SRC has no layerlab source and LAYERLAB_GIT is not set}"
  export_git "$LAYERLAB_GIT" "$SRC"
fi
for sub in tinyformat filesystem; do
  var="$(echo "$sub" | tr a-z A-Z)_GIT"
  if [ -z "$(ls -A "$SRC/ext/$sub" 2>/dev/null)" ]; then
    : "${!var:?$SRC/ext/$sub is empty: set $var to a git dir of github.com/wjakob/$sub}"
    export_git "${!var}" "$SRC/ext/$sub"
  fi
done

# Patch 1 and 2 (idempotent: applied to a pristine CMakeLists.txt kept as CMakeLists.txt.orig).
cd "$SRC"
[ -e CMakeLists.txt.orig ] || cp CMakeLists.txt CMakeLists.txt.orig
"$PYTHON" - <<'PY'
import re
s = open("CMakeLists.txt.orig").read()
s = s.replace("add_subdirectory(ext/tbb)\nadd_subdirectory(ext/pybind11)",
              "find_package(TBB REQUIRED)\nfind_package(pybind11 CONFIG REQUIRED)")
s = s.replace('set(CMAKE_CXX_FLAGS "${CMAKE_CXX_FLAGS} -flto")', "")
s = s.replace('set(CMAKE_CXX_FLAGS "${CMAKE_CXX_FLAGS} -std=c++14")', 'set(CMAKE_CXX_FLAGS "${CMAKE_CXX_FLAGS} -std=gnu++14")')
s = s.replace("  ext/eigen\n", "  /usr/include/eigen3\n")
s = s.replace("  ext/pybind11/include\n", "").replace("  ext/tbb/include\n", "")
s = s.replace("target_link_libraries(layerlab PRIVATE tbb_static)", "target_link_libraries(layerlab PRIVATE TBB::tbb)")
open("CMakeLists.txt", "w").write(s)
h = "include/layer/math.h"
try:
    m = open(h + ".orig").read()
except FileNotFoundError:
    m = open(h).read()
    open(h + ".orig", "w").write(m)
open(h, "w").write(m.replace("#include <cmath>\n", "#include <cmath>\n#include <limits>\n", 1))
PY

BUILD="$SRC/build-$("$PYTHON" -c 'import sys; print("py%d%d" % sys.version_info[:2])')"
mkdir -p "$BUILD" "$PREFIX"
cmake -S "$SRC" -B "$BUILD" -DCMAKE_BUILD_TYPE=Release \
  -DPYTHON_EXECUTABLE="$("$PYTHON" -c 'import sys; print(sys.executable)')" \
  -DPython_EXECUTABLE="$("$PYTHON" -c 'import sys; print(sys.executable)')"
nice -n 10 make -C "$BUILD" -j"$JOBS"
cp "$BUILD"/layerlab*.so "$PREFIX"/
PYTHONPATH="$PREFIX" "$PYTHON" -c "import layerlab; print('layerlab built:', layerlab.__file__)"
