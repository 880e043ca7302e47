# lfgraph: `make demo` and `make test` each create .venv if missing and install the project into it.
PYTHON ?= python3
VENV ?= .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.lfgraph-installed

.PHONY: demo test test-fast bench lint screenshots clean

$(STAMP): pyproject.toml
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -e '.[test]'
	touch $(STAMP)

demo: $(STAMP)
	$(BIN)/lfgraph demo

test: $(STAMP)
	$(BIN)/ruff check lfgraph tests benchmarks
	$(BIN)/pytest -q

# the quick subset for local work (no sweeps, renders or end-to-end CLI runs); `make test` and CI run everything
test-fast: $(STAMP)
	$(BIN)/ruff check lfgraph tests benchmarks
	$(BIN)/pytest -q -m "not slow"

bench: $(STAMP)
	$(BIN)/python benchmarks/run_all.py

# opt-in (not part of `test`): the README's pictures in docs/images/; needs the Debian package chromium
screenshots: $(STAMP)
	$(BIN)/python scripts/screenshots.py --out docs/images

lint: $(STAMP)
	$(BIN)/ruff check lfgraph tests benchmarks

clean:
	rm -rf $(VENV) out .pytest_cache .ruff_cache
