# Two commands are the whole set-up on a fresh machine: `make demo` and `make test`.
# Each creates .venv and installs the pinned packages when they are missing: pyproject.toml
# holds lower bounds, constraints.txt the exact versions. PIP_ARGS adds pip options, e.g.
# PIP_ARGS='--extra-index-url https://download.pytorch.org/whl/cpu' for CPU-only torch.
PYTHON ?= python3
VENV   ?= .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed-stamp
PIP_ARGS ?=
# test processes (pytest-xdist): tests and notebooks are spread over this many workers;
# TEST_WORKERS=0 runs them in the calling process, one after another
TEST_WORKERS ?= 2
# one pytest run for both, the notebooks (each a minute or more) first, so they start at
# once and the short tests fill the workers' gaps around them; worksteal: an idle worker
# takes tests queued for the other instead of waiting at the end (ignored with -n 0)
TEST_DIST ?= worksteal
# BLAS/OpenMP threads per test process: with two workers on two cores, one each (two each
# would put four threads on two cores, each small kernel waiting for its second thread:
# 810 -> 630 CPU-s and 416 -> 322 s on a quiet 2-core machine, session 17). Tests that are
# about threads set their own counts (gp/threads.torch_threads).
TEST_THREADS ?= 1

.PHONY: demo test bench lint clean-venv

$(STAMP): pyproject.toml constraints.txt
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --disable-pip-version-check -c constraints.txt $(PIP_ARGS) -e '.[dev,articulatory]'
	touch $(STAMP)

venv: $(STAMP)

demo: $(STAMP)
	$(PY) -m bayes_talk.app.cli demo --out demo_out

test: $(STAMP)
	OMP_NUM_THREADS=$(TEST_THREADS) MKL_NUM_THREADS=$(TEST_THREADS) OPENBLAS_NUM_THREADS=$(TEST_THREADS) $(PY) -m pytest -q -n $(TEST_WORKERS) --dist $(TEST_DIST) --nbmake --nbmake-timeout=600 notebooks tests   # tests/ and every notebook executed

bench: $(STAMP)
	mkdir -p benchmarks/results
	for b in benchmarks/*.py; do $(PY) $$b || exit 1; done

lint: $(STAMP)
	$(VENV)/bin/ruff check bayes_talk tests benchmarks

clean-venv:
	rm -rf $(VENV)
