# The two commands of the README:  `make demo`  and  `make test`.
# Each creates the virtual environment .venv/ at the repository root when it is missing and
# installs the project from its own files (pyproject.toml, at the exact versions of
# constraints.txt), plus the one system library that open3d needs to import (libusb-1.0-0,
# Debian package) when the machine lacks it.

PYTHON ?= python3
VENV   := .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.installed
DEMO   := out/demo

.PHONY: setup demo test test-fast lint bench-pairs bench-difficulty bench-tilt clean

$(STAMP): pyproject.toml constraints.txt
	@./.ci/system-deps.sh
	@test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -c constraints.txt -e '.[test,bench]'
	@touch $(STAMP)

setup: $(STAMP)

## Render the default extreme-viewpoint scene and reconstruct it with the extra-affine matcher.
demo: $(STAMP)
	$(BIN)/recon render-scene $(DEMO)/scene --preset corner --seed 0 --overwrite
	$(BIN)/recon run $(DEMO)/scene --out $(DEMO)/recon --overwrite

# Tests run in parallel on up to 4 cores (pytest-xdist); an idle worker takes queued tests from the
# busy one (worksteal), which balances the few long end-to-end runs better than whole files
# (14.6 against 15.8 min on 2 cores) though a module's fixtures may then be computed on both.
XDIST := -n auto --maxprocesses 4 --dist worksteal

## All tests (real data from ../shared/data where present, skipped with a reason otherwise).
test: lint
	$(BIN)/python -m pytest -p no:dash -q $(XDIST)

## ruff (style, imports, bugbear, pyupgrade) on the packages, benchmarks and tests, and mypy on the library packages, as CI runs them.
lint: $(STAMP)
	$(BIN)/ruff check matching recon scenes benchmarks tests
	$(BIN)/mypy

## Everything but the end-to-end runs (tests marked slow, see tests/conftest.py): under a minute.
test-fast: $(STAMP)
	$(BIN)/python -m pytest -p no:dash -q $(XDIST) -m "not slow" --durations=15

bench-pairs: $(STAMP)
	$(BIN)/recon bench pairs ../shared/data --json benchmarks/results/pairs.json

bench-tilt: $(STAMP)
	$(BIN)/recon bench tilt --out out/bench-tilt \
	    --textures procedural:0,procedural:1,../shared/data/oxford/graf/img1.png,../shared/data/hpatches/v_dogman/1.png \
	    --angles 60,70,75,80,83,85 --zooms 0.5,1 --json benchmarks/results/tilt.json

bench-difficulty: $(STAMP)
	$(BIN)/recon bench difficulty --json benchmarks/results/difficulty.json
	cp out/bench-difficulty/difficulty.png benchmarks/results/difficulty.png

clean:
	rm -rf $(VENV) out *.egg-info
