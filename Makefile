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

demo: $(STAMP)
	@echo "== cellcal registration demo: the paper's Table 4 (two laser-tracker stations, 5 common points)"
	@for m in svd quaternion three-point rodrigues small-angle line; do \
		$(BIN)/cellcal register --method $$m \
			--src cellcal/data/paper_table4_station1.csv \
			--dst cellcal/data/paper_table4_station2.csv || exit $$?; \
		echo; \
	done

lint: $(STAMP)
	$(BIN)/ruff check cellcal tests benchmarks
	$(BIN)/ruff format --check cellcal tests benchmarks

types: $(STAMP)
	$(BIN)/mypy cellcal

unit: $(STAMP)
	$(BIN)/pytest -q

test: lint types unit

bench: $(STAMP)
	$(BIN)/python benchmarks/registration.py

clean:
	rm -rf $(VENV) .pytest_cache .mypy_cache .ruff_cache .hypothesis
