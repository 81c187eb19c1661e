# splatcli developer entry points. Override the torch pin, e.g. `make setup TORCH=torch TORCHVISION=torchvision`
# on a CUDA box; torchvision (for the lpips extra) must be the release built for that torch.
PYTHON ?= python3
TORCH ?= torch==2.13.0
TORCHVISION ?= torchvision==0.28.0
# Where torch comes from: pip's default index unless set (PyPI serves Linux the CUDA build;
# https://download.pytorch.org/whl/cpu has the CPU build).
TORCH_INDEX ?=
VENV ?= .venv
BIN := $(VENV)/bin
DEMO ?= demo-project
PYTEST_ARGS ?=
# Test processes (pytest-xdist): one per core, at most 4; each test file stays in one process, so its
# module fixtures are built once. `make test WORKERS=0` runs the suite in this process alone.
WORKERS ?= auto --maxprocesses 4
# (files in the order collected, where tests/conftest.py puts the longest first; xdist's own order is by size)
XDIST = -n $(WORKERS) --dist loadfile --no-loadscope-reorder
# make bench: an OpenSplat checkout for the same-run peer comparison (skipped when empty).
OPENSPLAT_SOURCE ?=
# One torch thread per process unless you say otherwise (docs/guide.md, "Threads").
export OMP_NUM_THREADS ?= 1

.PHONY: setup check test test-fast demo bench clean

$(BIN)/splatcli: pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/pip install -q --upgrade pip
	# torch (and the torchvision built for it) first, pinned, so that nothing else drags in the multi-GB CUDA wheels.
	$(BIN)/pip install -q $(if $(TORCH_INDEX),--index-url $(TORCH_INDEX)) "$(TORCH)" "$(TORCHVISION)"
	$(BIN)/pip install -q -e ".[dev,plots,lpips]"
	@touch $@

setup: $(BIN)/splatcli

# Lint and dead names (configured in pyproject.toml; CI runs this before the tests). Both run, and
# either one's finding fails the target.
check: setup
	@status=0; $(BIN)/ruff check . || status=1; $(BIN)/vulture || status=1; exit $$status

# The whole suite (what CI runs).
test: setup
	$(BIN)/python -m pytest -q $(XDIST) $(PYTEST_ARGS)

# The everyday tier: everything but the tests marked slow (soak, pipelines, data-parallel, end to end, ...).
test-fast: setup
	$(BIN)/python -m pytest -q -m "not slow" $(XDIST) $(PYTEST_ARGS)

demo: setup
	rm -rf $(DEMO)
	$(BIN)/splatcli process sample_data/scene -o $(DEMO)
	$(BIN)/splatcli train $(DEMO) --preset demo
	$(BIN)/splatcli render $(DEMO) --split test
	$(BIN)/splatcli export $(DEMO)
	$(BIN)/splatcli eval $(DEMO) --formats ply,spz,sog,compressed-ply,splat
	@echo ""
	@echo "splat:  $(DEMO)/exports/scene.ply"
	@echo "report: $(DEMO)/reports/eval.md ($(DEMO)/reports/eval.json)"
	@echo "look:   $(BIN)/splatcli view $(DEMO)   (open the URL it prints; Ctrl-C stops it)"

# Each benchmark writes bench/out/<name>.json (command, commit, date, CPU, load, rows) and prints its
# table; none edits the docs.
bench: setup
	$(BIN)/python bench/peers.py --source "$(OPENSPLAT_SOURCE)"
	$(BIN)/python bench/process.py
	$(BIN)/python bench/train.py
	$(BIN)/python bench/step.py bench/out/train/lego/default

clean:
	rm -rf $(VENV) $(DEMO) *.egg-info
