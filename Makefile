# Every target sets up its own virtual environment from this repository's files
# (pyproject.toml + constraints.txt pin what gets installed), so a fresh machine
# with Python 3.11 only needs `make demo` or `make test`.
PYTHON ?= $(shell command -v python3.11 || command -v python3)
VENV   := .venv
BIN    := $(VENV)/bin
PIP    := $(BIN)/python -m pip install --disable-pip-version-check -q -c constraints.txt
export MPLBACKEND ?= Agg

.PHONY: demo test test-all bench docs docs-notebooks clean

$(BIN)/python:
	$(PYTHON) -m venv $(VENV)

# the tests build the docs site (tests/test_docs.py) and run the Python blocks of
# README.md and docs/ (pytest-markdown-docs), so the docs extra is part of the setup
$(VENV)/.core: pyproject.toml constraints.txt | $(BIN)/python
	$(PIP) -e '.[test,docs]'
	@touch $@

# the peers extra (scipy, numba, casadi) so that every peer of BENCHMARKS.md runs in
# the same `make bench` instead of printing "skipped"
$(VENV)/.bench: $(VENV)/.core
	$(PIP) -e '.[test,bench,peers]'
	@touch $@

# outputs in experiments/out/demo (ignored by git) rather than ./optimal_somersault
demo: $(VENV)/.core
	$(BIN)/nhjax demo --out experiments/out/demo

test: $(VENV)/.core
	$(BIN)/python -m pytest

test-all: $(VENV)/.core
	$(BIN)/python -m pytest -m ""

bench: $(VENV)/.bench
	$(BIN)/nhjax bench

# the site in site/; the notebook pages show the outputs stored in docs/notebooks/
docs: $(VENV)/.core
	NO_MKDOCS_2_WARNING=1 $(BIN)/mkdocs build --strict

# execute notebooks/*.ipynb and store the executed copies (with their figures) in
# docs/notebooks/, which the notebook pages render; run after changing a notebook
# (tests/test_docs.py fails while a copy's code differs from its notebook)
docs-notebooks: $(VENV)/.core
	cd notebooks && MPLBACKEND=module://matplotlib_inline.backend_inline ../$(BIN)/jupyter nbconvert \
	    --to notebook --execute --ExecutePreprocessor.timeout=1800 --output-dir ../docs/notebooks *.ipynb

clean:
	rm -rf $(VENV) experiments/out benchmarks/out site
