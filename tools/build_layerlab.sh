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
#       libeigen3-dev libfftw3-dev libtbb-dev
# and pybind11 >= 2.12 (numpy 2 support; Debian 12's pybind11-dev 2.10 builds a module that calls a null
# numpy C-API slot under numpy 2 and segfaults in the first Layer(...)): the script pip-installs
# "pybind11>=2.12,<3" (headers + CMake config, pure) into PREFIX/pybind11-pkg unless PYBIND11_DIR is set.
# The header-only submodules ext/tinyformat (github.com/wjakob/tinyformat) and ext/filesystem
# (github.com/wjakob/filesystem) must be present: set TINYFORMAT_GIT / FILESYSTEM_GIT to their git dirs
# to have them exported into SRC/ext, or check the submodules out.
#
# Patches applied to the source (layerlab HEAD 3e5257e, 2017), all in the build system, none in the
# numerics:
#   1. CMakeLists.txt: ext/tbb and ext/pybind11 are not added as subdirectories; the system oneTBB
#      (TBB::tbb) and pybind11 2.13 (pybind11Config.cmake) are used instead; Eigen 3.4 from
#      /usr/include/eigen3.
#   2. -flto is dropped (g++ 12 + pybind11 2.10 link is slow with it on 2 cores; no numeric effect).
#   3. -std=c++14 -> -std=gnu++14: include/layer/math.h uses hexadecimal float literals
#      (0x1.fffffffffffff7p-1), which strict C++14 rejects in g++ 12.
#   4. include/layer/math.h: #include <limits> added (std::numeric_limits; older libstdc++ pulled it in
#      through <algorithm>).
#   5. src/py_quad.cpp: py::array(n, ptr) -> py::array_t<Float>(std::vector<ssize_t>{n}, ptr).  With
#      pybind11 2.10 the old call builds an array whose entries all equal the first (quad.gaussLobatto(5)
#      returned [-1, -1, -1, -1, -1]), and every layer built on those nodes is garbage (a segfault in
#      Layer.eval followed).
#   6. src/layer.cpp, setHenyeyGreenstein and setVonMisesFisher (a bug upstream, not a port issue): each
#      parallel chunk appends its local quartet list to the shared one after EVERY node i without
#      clearing it, so a chunk holding k > 1 nodes adds its first node's coefficients k times (its
#      second's k-1 times, ...).  Chunks depend on the TBB partitioner, the thread count and n: on 2 threads
#      an HG g 0.7, albedo 0.95, tau 2 slab had R + T = 0.85 at n = 100 and 120 but 1.07 at n = 140 and
#      5.9 at n = 200 (the isotropic and microfacet setters are unaffected).  Fix: clear the local
#      list after it is appended (quartetsLocal.clear()).
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
q = "src/py_quad.cpp"
try:
    m = open(q + ".orig").read()
except FileNotFoundError:
    m = open(q).read()
    open(q + ".orig", "w").write(m)
new = "py::array_t<Float>(std::vector<ssize_t>{(ssize_t) n}, %s.data())"
m = m.replace("py::array(n, nodes.data())", new % "nodes").replace("py::array(n, weights.data())", new % "weights")
assert "py::array(n," not in m
open(q, "w").write(m)
c = "src/layer.cpp"
try:
    m = open(c + ".orig").read()
except FileNotFoundError:
    m = open(c).read()
    open(c + ".orig", "w").write(m)
old = """                tbb::spin_mutex::scoped_lock lock(mutex);
                quartets.insert(quartets.end(), quartetsLocal.begin(), quartetsLocal.end());
"""
assert m.count(old) == 2, "layer.cpp: the two per-node quartet appends (HG, vMF) not found"
m = m.replace(old, old + "                quartetsLocal.clear();\n")
open(c, "w").write(m)
PY

if [ -z "${PYBIND11_DIR:-}" ]; then
  "$PYTHON" -m pip install --quiet --target "$PREFIX/pybind11-pkg" "pybind11>=2.12,<3"
  PYBIND11_DIR="$PREFIX/pybind11-pkg/pybind11/share/cmake/pybind11"
fi

BUILD="$SRC/build-$("$PYTHON" -c 'import sys; print("py%d%d" % sys.version_info[:2])')"
mkdir -p "$BUILD" "$PREFIX"
cmake -S "$SRC" -B "$BUILD" -DCMAKE_BUILD_TYPE=Release -Dpybind11_DIR="$PYBIND11_DIR" \
  -DPYTHON_EXECUTABLE="$("$PYTHON" -c 'import sys; print(sys.executable)')" \
  -DPython_EXECUTABLE="$("$PYTHON" -c 'import sys; print(sys.executable)')"
nice -n 10 make -C "$BUILD" -j"$JOBS"
cp "$BUILD"/layerlab*.so "$PREFIX"/
# a check that the bindings return what the C++ computed (patch 5): the 3-point Lobatto rule
PYTHONPATH="$PREFIX" "$PYTHON" -c "
import layerlab
x, w = layerlab.quad.gaussLobatto(3)
assert abs(x[0] + 1) < 1e-15 and abs(x[1]) < 1e-15 and abs(x[2] - 1) < 1e-15, x
assert abs(w[0] - 1 / 3) < 1e-15 and abs(w[1] - 4 / 3) < 1e-15, w
print('layerlab built:', layerlab.__file__)"
