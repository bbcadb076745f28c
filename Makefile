# cellcal — two commands for a newcomer: `make demo` and `make test`.
PYTHON ?= $(shell command -v python3.11 || command -v python3)
VENV   := .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.installed

.PHONY: demo test lint types unit bench clean

$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -e '.[dev]'
	touch $(STAMP)

T4 := --src cellcal/data/paper_table4_station1.csv --dst cellcal/data/paper_table4_station2.csv

demo: $(STAMP)
	@echo "== cellcal demo: the paper's Table 4 (one laser tracker at two stations, 5 common points)"
	@echo "== least squares (the default):"
	@$(BIN)/cellcal register $(T4)
	@echo
	@echo "== the paper's characteristic-line method, A = P1P2, B = P2P3:"
	@$(BIN)/cellcal register $(T4) --method line --line-a P1,P2 --line-b P2,P3
	@echo
	@echo "== three-point method:"
	@$(BIN)/cellcal register $(T4) --method three-point
	@echo
	@echo "Least squares has the lowest RMS possible on these points; see docs/paper-errata.md."

lint: $(STAMP)
	$(BIN)/ruff check cellcal tests benchmarks
	$(BIN)/ruff format --check cellcal tests benchmarks

types: $(STAMP)
	$(BIN)/mypy cellcal

unit: $(STAMP)
	$(BIN)/pytest -q

test: lint types unit

bench: $(STAMP)
	$(BIN)/python -m pip install --quiet -e '.[bench]'
	$(BIN)/python benchmarks/registration.py
	$(BIN)/python benchmarks/calibration.py

clean:
	rm -rf $(VENV) .pytest_cache .mypy_cache .ruff_cache .hypothesis
