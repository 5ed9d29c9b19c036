# youbot_fdi: two commands do all the setup on a fresh Debian/Ubuntu machine with Python 3.11+:
#   make demo    run the main job (youbot-fdi demo)
#   make test    run the tests
#   make check   lint (ruff) and the fast unit tests of the core, under a minute: between edits
# Both create .venv first (make venv): the package in editable mode, the ROS 2 Jazzy wheels from
# PyPI, the test tools and every optional extra. Re-running is quick when nothing changed.

PYTHON ?= python3
VENV ?= .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed
PYTEST_ARGS ?=

# ROS 2 discovery stays on this machine (Fast DDS multicasts off every interface by default),
# and every run gets its own domain so parallel runs do not see each other.
export ROS_AUTOMATIC_DISCOVERY_RANGE := LOCALHOST
export ROS_DOMAIN_ID ?= $(shell $(PYTHON) -c 'import os; print(os.getpid() % 100 + 1)')
export ROS_PYTHON_CHECK_FIELDS := 1
export MPLBACKEND := Agg

.PHONY: venv demo test check lint bench clean

venv: $(STAMP)

$(STAMP): setup.py setup.cfg package.xml
	@test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -e '.[all]'
	@touch $(VENV)/COLCON_IGNORE
	@touch $@

demo: venv
	$(BIN)/youbot-fdi demo

test: venv
	$(BIN)/python -m pytest $(PYTEST_ARGS)

lint: venv
	$(BIN)/ruff check youbot_fdi test

check: lint
	$(BIN)/python -m pytest -q -m fast $(PYTEST_ARGS)

clean:
	rm -rf $(VENV) build install log out .pytest_cache .hypothesis
