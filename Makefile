# Two commands do everything on a fresh machine with Python >= 3.11 and make:
#   make demo   -- create .venv if missing, install, run section 6.1 and its position-grid sweep into results/
#   make test   -- create .venv if missing, install with the test, cli and docs extras, then ruff (lint and
#                  format), the documentation build (warnings as errors, tutorials executed), the whole suite
#   make docs   -- the documentation site into docs/_build/html
PYTHON ?= python3
VENV   := .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed
SPHINX := $(PY) docs/build.py

.PHONY: demo test lint docs bench venv clean

$(PY):
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip

$(STAMP): $(PY) pyproject.toml
	$(PY) -m pip install --quiet -e ".[test,cli,docs]"
	touch $(STAMP)

venv: $(STAMP)

demo: $(STAMP)
	$(PY) -m paper.section_6_1 --out results/section_6_1
	$(VENV)/bin/wmrjax sweep section_6_1_position_grid --out results/sweeps/section_6_1_position_grid

test: lint docs
	$(PY) -m pytest -q -n auto --dist loadfile

lint: $(STAMP)
	$(PY) -m ruff check .
	$(PY) -m ruff format --check .

# -W: a warning fails the build; the tutorials execute in it (two readers), their outputs cached in
# docs/_build/.jupyter_cache until their code changes; docs/build.py builds once more after the one
# failure that is not the docs' own (two notebook kernels that took one port)
docs: $(STAMP)
	$(SPHINX)

bench: $(STAMP)
	$(PY) -m benchmarks.benchmark --out results/benchmark

clean:
	rm -rf results .pytest_cache docs/_build
