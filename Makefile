# cellcal — two commands for a newcomer: `make demo` and `make test`.
PYTHON ?= $(shell command -v python3.11 || command -v python3)
VENV   := .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.installed

.PHONY: demo demo-registration test check lint types unit bench clean

# Every extra but the one PyGObject is in (it builds against Debian's packages: $(ARAVIS)
# below installs them, then `.[all,dev]`): the suite needs them all (pyproject.toml).
EXTRAS := dev,ur,modbus,abb,opencv,urdf,service,report,fleet
$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -e '.[$(EXTRAS)]'
	touch $(STAMP)

# Aravis, for the `aravis` camera backend and the GigE Vision camera twin: Debian's
# packages (gcc, libc6-dev, python3-dev: PyGObject is built from source; not aravis-tools,
# which pulls in GTK), then PyGObject from the `cameras` extra. Without root or
# password-less sudo scripts/debs.sh prints one line saying what to run, and make carries
# on: the Aravis tests then skip with that reason. Then every extra, `.[all,dev]` (the
# `cameras` extra's PyGObject the last missing). The stamp is only made once it all works.
ARAVIS_DEBS := libaravis-0.8-0 gir1.2-aravis-0.8 libgirepository1.0-dev libcairo2-dev \
	pkg-config gcc libc6-dev python3-dev
ARAVIS := $(VENV)/.aravis
ARAVIS_OK := $(BIN)/python -c 'import gi; gi.require_version("Aravis", "0.8")' 2>/dev/null
$(ARAVIS): $(STAMP)
	@if $(ARAVIS_OK); then touch $@; exit 0; fi; \
	scripts/debs.sh cameras "the aravis tests skip" $(ARAVIS_DEBS) || exit 0; \
	if $(BIN)/python -m pip install --quiet -e '.[all,dev]' && $(ARAVIS_OK); then touch $@; \
	else echo "cameras: PyGObject<3.51 does not build or import here (see above; until fixed the aravis tests skip)"; fi

# The service's test tools from Debian: chromium and chromium-driver for the status page
# in a headless browser (selenium, in the dev extra, drives it), systemd's
# systemd-analyze for the unit file. Same rules as above: one line when it cannot.
TOOLS_DEBS := chromium chromium-driver systemd
TOOLS := $(VENV)/.service-tools
$(TOOLS): $(STAMP)
	@scripts/debs.sh "service test tools" "the browser and unit-file tests skip" \
	  $(TOOLS_DEBS) && touch $@ || true

# The fleet's tests start a PostgreSQL server of their own (initdb in a temporary folder,
# a loopback port): Debian's postgresql. Same rules: one line when it cannot.
PG_DEBS := postgresql
PG := $(VENV)/.postgresql
$(PG): $(STAMP)
	@scripts/debs.sh "PostgreSQL" "the fleet tests skip" $(PG_DEBS) && touch $@ || true

T4 := --src cellcal/data/paper_table4_station1.csv --dst cellcal/data/paper_table4_station2.csv

# The demo writes outside the checkout: into the user's data directory (make demo DEMO=DIR
# elsewhere), as cellcal's own defaults do.
DEMO ?= $(or $(XDG_DATA_HOME),$(HOME)/.local/share)/cellcal/demo

demo: $(STAMP) $(ARAVIS)
	@echo "== cellcal demo: a whole campaign on the bundled simulated cell (config/mock-cell.toml):"
	@echo "   KR 5 arc with seeded kinematic errors, laser tracker + photogrammetry rig, the paper's"
	@echo "   80-pose cube with 7 s dwell and 20 samples per pose, on a simulated clock."
	@echo "   It writes into $(DEMO)/ (DEMO=DIR: elsewhere)."
	@mkdir -p "$(DEMO)"
	$(BIN)/cellcal run --mock --db "$(DEMO)/demo.db" --report "$(DEMO)/report"
	@echo "== the report: open $(DEMO)/report/index.html in a browser (offline, self-contained)"

demo-registration: $(STAMP)
	@echo "== the paper's Table 4 (one laser tracker at two stations, 5 common points)"
	@$(BIN)/cellcal register $(T4)
	@$(BIN)/cellcal register $(T4) --method line --line-a P1,P2 --line-b P2,P3
	@$(BIN)/cellcal register $(T4) --method three-point

lint: $(STAMP)
	$(BIN)/ruff check cellcal tests benchmarks
	$(BIN)/ruff format --check cellcal tests benchmarks
	$(BIN)/lint-imports --no-cache
	$(BIN)/python scripts/check_sql_in_store.py cellcal

types: $(STAMP)
	$(BIN)/mypy cellcal

# UR's own RTDE client is not on PyPI: its release 2.7.0 is unpacked from the OpenUr
# wheel (pinned by hash) for the UR twin's tests; without network they skip.
UR_CLIENT := $(VENV)/ur-rtde-client/rtde/rtde.py
$(UR_CLIENT): | $(STAMP)
	@$(BIN)/python tests/mocks/ur_official_client.py $(VENV)/ur-rtde-client

# Three workers per core (tests/conftest.py: much of the time the tests wait); a test
# file's tests on one worker (they share module fixtures), except the files conftest names in
# SPREAD, whose tests go out one by one; README's examples, then the slow tests (marker slow)
# first, the files of each part in an order fixed by a checksum of their paths (waiting
# tests spread among computing ones). OpenCV and OpenBLAS on one thread per process. The
# 20 slowest are listed at the end.
PARALLEL := -n auto --dist loadfile --no-loadscope-reorder
# Compiled modules (cellcal's, and the tests' rewritten asserts) are kept between processes
# and runs, under .venv/pycache, never beside the sources: every cellcal process a test
# starts would otherwise compile what it imports again (where PYTHONDONTWRITEBYTECODE is
# set, as on some CI machines). A second `make check` is about an eighth faster.
PYCACHE := PYTHONDONTWRITEBYTECODE= PYTHONPYCACHEPREFIX=$(CURDIR)/$(VENV)/pycache
# What the tests import is compiled into it once, by one process, before the first parallel
# run: otherwise its workers, starting together, each compile the same 2000 modules (from a
# fresh clone about 12 s of CPU done six times over). Later changes compile as they come.
WARM := $(VENV)/pycache/.collected
$(WARM): | $(STAMP)
	@$(PYCACHE) $(BIN)/pytest -q --collect-only -p no:cacheprovider > /dev/null 2>&1 \
		&& touch $@ || echo "compiling ahead failed; the test run says why"
unit: $(STAMP) $(UR_CLIENT) $(ARAVIS) $(TOOLS) $(PG) $(WARM)
	$(PYCACHE) $(BIN)/pytest -q $(PARALLEL) --durations=20

test: lint types unit

# The quick check while changing code (about 85 s on 2 cores): lint, types and the tests that
# need no device twin, service or browser.
check: lint types $(WARM)
	$(PYCACHE) $(BIN)/pytest -q $(PARALLEL) -m "not twin and not browser" --durations=10

bench: $(STAMP) $(PG)
	$(BIN)/python -m pip install --quiet -e '.[bench]'
	$(BIN)/python benchmarks/registration.py
	$(BIN)/python benchmarks/calibration.py
	$(BIN)/python benchmarks/pose_selection.py
	$(BIN)/python benchmarks/campaign.py
	$(BIN)/python benchmarks/photogrammetry.py
	$(BIN)/python benchmarks/rig_calibration.py
	$(BIN)/python benchmarks/service.py
	$(BIN)/python benchmarks/startup.py
	$(BIN)/python benchmarks/fleet.py
	$(BIN)/python benchmarks/error_terms.py

clean:
	rm -rf $(VENV) .pytest_cache .mypy_cache .ruff_cache .hypothesis
