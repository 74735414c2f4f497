# flakedb: the two commands a fresh machine needs are `make demo` and `make test`.
PY ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed
OUT ?= out

# Blender's bpy for the Cycles test, in an environment of its own (bpy pins numpy < 2 and is
# CPython 3.11 only): tools/blender_venv.sh; it never fails the build (the test then skips, saying why).
BLENDER_PY ?= python3.11
BLENDER_VENV := .venv-blender
BLENDER_STAMP := $(BLENDER_VENV)/.installed

.PHONY: venv blender-venv demo test test-fast bench figures clean

$(STAMP): pyproject.toml
	test -x $(BIN)/python || $(PY) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -e '.[test]'
	touch $(STAMP)

venv: $(STAMP)

$(BLENDER_STAMP): tools/blender_venv.sh
	tools/blender_venv.sh '$(BLENDER_PY)' '$(BLENDER_VENV)'

blender-venv: $(BLENDER_STAMP)

demo: $(STAMP)
	$(BIN)/python -m flakedb demo --out $(OUT)

test: $(STAMP) $(BLENDER_STAMP)
	$(BIN)/python -m pytest -n 2 -q tests flakedb

test-fast: $(STAMP)
	$(BIN)/python -m pytest -n 2 -q -m 'not slow' tests flakedb

figures: $(STAMP)
	$(BIN)/python -m figures.figures

bench: $(STAMP)
	$(BIN)/python bench/run.py --out bench/results.json

clean:
	rm -rf $(OUT) .pytest_cache
