# Set-up and checks. `make demo`, `make test` and `make docs` each create the virtual environment first.
PYTHON ?= python3
VENV ?= .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: demo test lint docs clean

$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -e '.[dev]'
	touch $(STAMP)

demo: $(STAMP)
	$(BIN)/lfpiv demo --out demo-output

lint: $(STAMP)
	$(BIN)/ruff check .
	$(BIN)/lint-imports

# The user guide into site/, warnings as errors (a broken link, a stale reference, a docstring
# the numpydoc parser cannot read); NO_MKDOCS_2_WARNING quiets the theme's banner about MkDocs 2.
docs: $(STAMP)
	NO_MKDOCS_2_WARNING=1 $(BIN)/mkdocs build --strict --quiet

# pytest exits 5 when a selection collects no tests; that is not a failure here.
test: lint docs
	$(BIN)/python -m pytest -q tests || [ $$? -eq 5 ]

clean:
	rm -rf $(VENV) demo-output site .pytest_cache .ruff_cache
