# Two commands do everything on a fresh machine with Python >= 3.11 and make:
#   make demo   -- create .venv if missing, install, run the main experiments into results/
#   make test   -- create .venv if missing, install with test extras, run the whole suite
PYTHON ?= python3
VENV   := .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed

.PHONY: demo test bench venv clean

$(PY):
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip

$(STAMP): $(PY) pyproject.toml
	$(PY) -m pip install --quiet -e ".[test]"
	touch $(STAMP)

venv: $(STAMP)

demo: $(STAMP)
	$(PY) -m experiments.section_6_1 --out results/section_6_1
	$(PY) -m experiments.section_6_2 --out results/section_6_2
	$(PY) -m experiments.posture_tracking --out results/posture_tracking

test: $(STAMP)
	$(PY) -m pytest -q -n auto --dist loadfile

bench: $(STAMP)
	$(PY) -m experiments.benchmark --out results/benchmark

clean:
	rm -rf results .pytest_cache
