# casmag: make targets. `make demo` and `make test` create the virtual environment themselves.
PYTHON ?= python3
VENV   ?= .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed

.DEFAULT_GOAL := help
.PHONY: help install demo test test-all lint clean

help: ## List the targets
	@grep -E '^[a-zA-Z_-]+:.*## ' $(MAKEFILE_LIST) | awk -F':.*## ' '{printf "  %-10s %s\n", $$1, $$2}'

$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -e '.[dev]'
	touch $(STAMP)

install: $(STAMP) ## Create .venv and install casmag with its test tools

demo: $(STAMP) ## Solve the paper's base case; writes results/demo/ (table, figures)
	$(VENV)/bin/casmag run problems/paper/base.yaml --out results/demo
	$(VENV)/bin/casmag report results/demo --out results/demo/table.md
	@cat results/demo/table.md

test: $(STAMP) ## Run the test suite (under 10 minutes)
	$(PY) -m pytest -q

lint: $(STAMP) ## ruff check and format check
	$(VENV)/bin/ruff check casmag tests
	$(VENV)/bin/ruff format --check casmag tests

clean: ## Remove the environment and caches
	rm -rf $(VENV) .pytest_cache .ruff_cache build *.egg-info
