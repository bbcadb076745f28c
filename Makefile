# cellcal — two commands for a newcomer: `make demo` and `make test`.
PYTHON ?= $(shell command -v python3.11 || command -v python3)
VENV   := .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.installed

.PHONY: demo demo-registration test lint types unit bench clean

$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -e '.[dev]'
	touch $(STAMP)

T4 := --src cellcal/data/paper_table4_station1.csv --dst cellcal/data/paper_table4_station2.csv

demo: $(STAMP)
	@echo "== cellcal demo: a whole campaign on the bundled simulated cell (config/mock-cell.toml):"
	@echo "   KR 5 arc with seeded kinematic errors, laser tracker + photogrammetry rig, the paper's"
	@echo "   80-pose cube with 7 s dwell and 20 samples per pose, on a simulated clock."
	$(BIN)/cellcal run --mock --db demo.db

demo-registration: $(STAMP)
	@echo "== the paper's Table 4 (one laser tracker at two stations, 5 common points)"
	@$(BIN)/cellcal register $(T4)
	@$(BIN)/cellcal register $(T4) --method line --line-a P1,P2 --line-b P2,P3
	@$(BIN)/cellcal register $(T4) --method three-point

lint: $(STAMP)
	$(BIN)/ruff check cellcal tests benchmarks
	$(BIN)/ruff format --check cellcal tests benchmarks

types: $(STAMP)
	$(BIN)/mypy cellcal

# UR's own RTDE client is not on PyPI: its release 2.7.0 is unpacked from the OpenUr
# wheel (pinned by hash) for the UR twin's tests; without network they skip.
UR_CLIENT := $(VENV)/ur-rtde-client/rtde/rtde.py
$(UR_CLIENT): | $(STAMP)
	@$(BIN)/python tests/mocks/ur_official_client.py $(VENV)/ur-rtde-client

unit: $(STAMP) $(UR_CLIENT)
	$(BIN)/pytest -q

test: lint types unit

bench: $(STAMP)
	$(BIN)/python -m pip install --quiet -e '.[bench]'
	$(BIN)/python benchmarks/registration.py
	$(BIN)/python benchmarks/calibration.py
	$(BIN)/python benchmarks/campaign.py

clean:
	rm -rf $(VENV) .pytest_cache .mypy_cache .ruff_cache .hypothesis
