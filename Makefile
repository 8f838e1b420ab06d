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

# the benchmark suite (docs/benchmarks.md): every script of benchmarks/ in turn, each writing
# benchmarks/results/NAME.json. QUICK=1: each at toy size on corpora it builds, into
# benchmarks/results/quick/ (never committed), BENCH_JOBS of them at a time (timings of a quick
# run mean nothing), each one's output in benchmarks/results/quick/NAME.log
BENCHMARKS = $(filter-out __init__ common,$(basename $(notdir $(wildcard benchmarks/*.py))))
BENCH_JOBS ?= 2
# the longest quick runs start first, so the last ones to finish are short
BENCH_QUICK_FIRST = sbc train_speed posterior scaling calibration_budget
bench: $(STAMP)
ifdef QUICK
	PYTHONPATH=. $(PY) -c "from benchmarks.common import bench_corpus, bench_model; bench_corpus('test', True); bench_model(True)"
	$(MAKE) --no-print-directory -k -j $(BENCH_JOBS) $(addprefix bench-quick-,$(BENCH_QUICK_FIRST) \
		$(filter-out $(BENCH_QUICK_FIRST),$(sort $(BENCHMARKS))))
else
	for b in $(sort $(BENCHMARKS)); do echo "== benchmarks/$$b.py"; PYTHONPATH=. $(PY) benchmarks/$$b.py || exit 1; done
endif

bench-quick-%:
	@echo "== benchmarks/$*.py --quick"
	@PYTHONPATH=. OMP_NUM_THREADS=1 $(PY) benchmarks/$*.py --quick > benchmarks/results/quick/$*.log 2>&1 \
		|| { tail -n 30 benchmarks/results/quick/$*.log; echo "benchmarks/$*.py --quick failed"; exit 1; }

lint: $(STAMP)
	$(VENV)/bin/ruff check bayes_talk tests benchmarks

clean-venv:
	rm -rf $(VENV)
