# Two commands for a fresh machine (see README.md):
#   make demo   reconstruct the bundled sample case into demo-output/
#   make test   run the test suite
# Both create .venv/ with python3 -m venv when it is missing and install what they need; the
# install step runs again only when pyproject.toml changes (stamp file .venv/.sdfcar-installed).

VENV       ?= .venv
PYTHON     ?= python3
PY         := $(VENV)/bin/python
STAMP      := $(VENV)/.sdfcar-installed
# torch is installed first, pinned: resolved freely as a dependency, pip would take the newest
# release, which on Linux is the multi-gigabyte CUDA build even on a CPU-only machine; pinned,
# pip takes the CPU wheel wherever one is offered (a find-links folder, the PyTorch CPU index).
# Override, e.g.: make test TORCH_SPEC="torch==2.13.0 --index-url https://download.pytorch.org/whl/cpu"
TORCH_SPEC ?= "torch==2.13.0"
EXTRAS     ?= headless,dicom,bench,test
# test processes (pytest-xdist); whole test files go to one process, so a module's fixtures are built once
TEST_WORKERS ?= 2

.PHONY: all install test demo clean distclean

all: test

install: $(STAMP)

$(PY):
	$(PYTHON) -m venv $(VENV)

$(STAMP): pyproject.toml | $(PY)
	$(PY) -m pip install $(TORCH_SPEC)
	$(PY) -m pip install -e ".[$(EXTRAS)]"
	touch $@

test: $(STAMP)
	$(PY) -m pytest -q -n $(TEST_WORKERS) --dist loadfile

demo: $(STAMP)
	$(PY) -m SDFCARLib demo --out demo-output --overwrite

clean:
	rm -rf demo-output .pytest_cache build dist *.egg-info
	find SDFCARLib Testing -name __pycache__ -type d -prune -exec rm -rf {} +

# Also removes the environment (the next make reinstalls everything).
distclean: clean
	rm -rf $(VENV)
