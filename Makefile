# Two commands for a newcomer: `make run` and `make test`.
PYTHON ?= python3
VENV   := .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed
OUT    ?= results

.PHONY: run test test-fast bench venv net clean

$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -e '.[test]'
	$(PY) -m experiments.warm  # compiles the numba kernels once per install (minutes; says so)
	touch $(STAMP)

venv: $(STAMP)

## make run: the main experiment, one hour of the Turin-like arterial under TLR and VSR, and their comparison report
run: $(STAMP)
	$(VENV)/bin/coloc run experiments/arterial_tlr.toml --out $(OUT)/arterial_tlr --workers 1
	$(VENV)/bin/coloc run experiments/arterial_vsr.toml --out $(OUT)/arterial_vsr --workers 1
	$(VENV)/bin/coloc report $(OUT)/arterial_tlr $(OUT)/arterial_vsr --out $(OUT)/compare
	@echo "Open $(OUT)/compare/report.html (per-run reports: $(OUT)/arterial_tlr/report.html, $(OUT)/arterial_vsr/report.html)"

## make test: the whole test suite, slow tests included, on two processes (pytest-xdist; a test file stays on one
## process, so its module fixtures are built once)
test: $(STAMP)
	$(PY) -m pytest -q -n 2 --dist loadfile

test-fast: $(STAMP)
	$(PY) -m pytest -q -n 2 --dist loadfile -m "not slow"

bench: $(STAMP)
	$(PY) bench/coupled_vs_sumo.py

## make net: rebuild sumo_nets/arterial from its plain XML sources (deterministic)
net: $(STAMP)
	$(PY) -m couplers.net.build sumo_nets/arterial

clean:
	rm -rf $(VENV) $(OUT)
