# The two commands of the README: `make demo` and `make test`. Both set up their environment.
SHELL := /bin/bash
VENV ?= $(CURDIR)/.venv
BIN = $(VENV)/bin
PYTEST_ARGS ?=

.PHONY: env test demo lint clean

env:
	@VENV=$(VENV) scripts/setup_env.sh > /dev/null

test: env
	$(BIN)/python -m pytest $(PYTEST_ARGS)

demo: env
	$(BIN)/python -m semfeat_ros.tools.demo --out out/demo

lint: env
	$(BIN)/ruff check .

clean:
	rm -rf build install log out .pytest_cache
