# Set-up and checks. `make demo` and `make test` each create the virtual environment first.
PYTHON ?= python3
VENV ?= .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: demo test lint clean

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

# pytest exits 5 when a selection collects no tests; that is not a failure here.
test: lint
	$(BIN)/python -m pytest -q tests || [ $$? -eq 5 ]

clean:
	rm -rf $(VENV) demo-output .pytest_cache .ruff_cache
