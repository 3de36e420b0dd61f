# The two commands a newcomer needs: `make demo` and `make test`. Both set up everything themselves.
PY := .venv/bin/python
PYTEST := $(PY) -m pytest
RENDERERS ?= 1

.PHONY: setup demo test test-unit test-contract test-e2e bench clean

setup:
	@bash deploy/bootstrap.sh

demo: setup
	$(PY) -m deploy.demo --renderers $(RENDERERS)

test: setup
	$(PYTEST) -q tests

test-unit: setup
	$(PYTEST) -q tests/unit

test-contract: setup
	$(PYTEST) -q tests/contract

test-e2e: setup
	$(PYTEST) -q tests/e2e

bench: setup
	$(PY) -m bench

clean:
	rm -rf runs .pytest_cache
