# flakedb: the two commands a fresh machine needs are `make demo` and `make test`.
PY ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed
OUT ?= out

.PHONY: venv demo test test-fast bench figures clean

$(STAMP): pyproject.toml
	test -x $(BIN)/python || $(PY) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -e '.[test]'
	touch $(STAMP)

venv: $(STAMP)

demo: $(STAMP)
	$(BIN)/python -m flakedb demo --out $(OUT)

test: $(STAMP)
	$(BIN)/python -m pytest -n 2 -q tests flakedb

test-fast: $(STAMP)
	$(BIN)/python -m pytest -n 2 -q -m 'not slow' tests flakedb

figures: $(STAMP)
	$(BIN)/python -m figures.figures

bench: $(STAMP)
	$(BIN)/python bench/run.py --out bench/results.json

clean:
	rm -rf $(OUT) .pytest_cache
