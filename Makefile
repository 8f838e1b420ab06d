# Two commands are the whole set-up on a fresh machine: `make demo` and `make test`.
# Each creates .venv and installs the pinned packages when they are missing.
PYTHON ?= python3
VENV   ?= .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed-stamp

.PHONY: demo test bench lint clean-venv

$(STAMP): pyproject.toml
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --disable-pip-version-check -e '.[dev,articulatory]'
	touch $(STAMP)

venv: $(STAMP)

demo: $(STAMP)
	$(PY) -m bayes_talk.cli demo --out demo_out

test: $(STAMP)
	$(PY) -m pytest -q tests
	$(PY) -m pytest -q --nbmake --nbmake-timeout=600 notebooks   # executes every notebook

bench: $(STAMP)
	mkdir -p benchmarks/results
	for b in benchmarks/*.py; do $(PY) $$b || exit 1; done

lint: $(STAMP)
	$(VENV)/bin/ruff check bayes_talk tests benchmarks

clean-venv:
	rm -rf $(VENV)
