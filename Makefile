# gsrmr: two commands on a fresh machine (Python 3.11, pip, gcc):
#   make demo   set up .venv, then run the main job
#   make test   set up .venv, then lint (ruff), colcon build and run every test once (colcon test, or
#               plain pytest where no ROS 2 launch tooling is available: tools/run_tests.sh), but the
#               `long` ones (soak and overload runs), which `make test-long` runs
# .venv is created or refreshed by tools/bootstrap.sh; a second run reuses it in about a second.

VENV ?= .venv
PY := $(VENV)/bin/python
# Each run gets its own ROS domain and localhost-only discovery (tests pick per-test domains too).
ROS_DOMAIN_ID ?= $(shell echo $$(( $$$$ % 100 + 1 )))
export ROS_DOMAIN_ID
export ROS_AUTOMATIC_DISCOVERY_RANGE ?= LOCALHOST
# The shared test data (the garden scene): tests and benches find it through GSRMR_DATA_DIR.
GSRMR_DATA_DIR ?= $(abspath $(wildcard ../shared/data))
export GSRMR_DATA_DIR
# e.g. PYTEST_ARGS=test/scheduler: one folder of test/ (a package's unit tests, ros, launch, system, project)
PYTEST_ARGS ?=

.PHONY: venv test test-long lint pytest demo bench docs clean

venv:
	@VENV=$(VENV) bash tools/bootstrap.sh

lint: venv
	$(VENV)/bin/ruff check .
	$(VENV)/bin/lint-imports

pytest: venv
	$(PY) -m pytest $(PYTEST_ARGS)

test: venv
	@echo "make test: ROS_DOMAIN_ID=$(ROS_DOMAIN_ID) ROS_AUTOMATIC_DISCOVERY_RANGE=$(ROS_AUTOMATIC_DISCOVERY_RANGE)"
	$(VENV)/bin/ruff check .
	$(VENV)/bin/lint-imports
	@VENV=$(VENV) PYTEST_ARGS="$(PYTEST_ARGS)" bash tools/run_tests.sh

test-long: venv
	@VENV=$(VENV) PYTEST_ARGS="-m long $(PYTEST_ARGS)" bash tools/run_tests.sh

demo: venv
	$(VENV)/bin/gsrmr-demo $(DEMO_ARGS)

# Every performance bench (bench/perf/), each with no arguments, one after the other to the end; the first that fails
# stops it. None needs root or a network namespace. The acceptance runs (bench/acceptance/: whole demo rounds, two
# hosts, given inputs) are run by hand, as their docstrings say.
PERF_BENCHES := $(sort $(wildcard bench/perf/*.py))

bench: venv
	@for b in $(PERF_BENCHES); do echo "== $$b"; t0=$$(date +%s); $(PY) $$b || exit 1; \
		echo "== $$b: $$(( $$(date +%s) - t0 )) s"; done

# The docs tree (README, CHANGELOG, docs/*.md through MyST) and the library's API reference, warnings as errors.
docs: venv
	$(PY) -m sphinx -W --keep-going -E -a -q -b html -c docs . build/docs
	@echo "docs: build/docs/docs/index.html"

clean:
	rm -rf $(VENV) build install log *.egg-info .pytest_cache .ruff_cache
