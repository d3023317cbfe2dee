# Two commands do everything on a fresh machine with Python >= 3.11 and make:
#   make demo   -- create .venv if missing, install, run section 6.1 and its position-grid sweep into results/
#   make test   -- create .venv if missing, install with the test, cli and docs extras, run the whole suite
PYTHON ?= python3
VENV   := .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed

.PHONY: demo test bench venv clean

$(PY):
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip

$(STAMP): $(PY) pyproject.toml
	$(PY) -m pip install --quiet -e ".[test,cli,docs]"
	touch $(STAMP)

venv: $(STAMP)

demo: $(STAMP)
	$(PY) -m experiments.section_6_1 --out results/section_6_1
	$(PY) -m experiments.sweep experiments/sweeps/section_6_1_position_grid.toml --out results/sweeps/section_6_1_position_grid

test: $(STAMP)
	$(PY) -m pytest -q -n auto --dist loadfile

bench: $(STAMP)
	$(PY) -m experiments.benchmark --out results/benchmark

clean:
	rm -rf results .pytest_cache
