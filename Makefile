# rfm: the two commands a user needs are `make demo` and `make test`.
SHELL := /bin/bash
ENV := ros_ws/env.sh
# Tests and demos keep DDS discovery on this machine (no multicast to the network).
LOCAL := ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST
PYTEST_ARGS ?=

.PHONY: setup test test-fast fuzz soak demo bench clean help

help:
	@echo "make demo   - set up everything and run rfm on the bundled demo bag (results: rfm_output/demo)"
	@echo "make test   - set up everything and run the test suite"
	@echo "make test-fast - the suite without the tests marked slow (whole-graph runs, training; ~1 min)"
	@echo "make fuzz   - 10,000 hostile messages and service calls into the three nodes, 5,000 mutated map files"
	@echo "make soak   - an hour of a camera walking round one room, replayed through the graph: growth, memory, autosave time (bench/soak.py)"
	@echo "make setup  - only create .venv and build the ROS workspace (idempotent)"
	@echo "make bench  - the benchmark suite in bench/ (bench/README.md; ~25 min)"
	@echo "make clean  - remove .venv and ros_ws/build|install|log"

setup:
	@ros_ws/bootstrap.sh

test: setup
	@$(LOCAL) $(ENV) python -m pytest tests $(PYTEST_ARGS)

test-fast: setup
	@$(LOCAL) $(ENV) python -m pytest tests -m "not slow" $(PYTEST_ARGS)

fuzz: setup
	@RFM_FUZZ_N=$${RFM_FUZZ_N:-10000} $(LOCAL) $(ENV) python -m pytest tests/fault tests/mapping/test_map_files.py \
		$(PYTEST_ARGS)

soak: setup
	@$(LOCAL) $(ENV) python bench/soak.py

demo: setup
	@$(LOCAL) $(ENV) rfm run --bag bags/demo --output rfm_output/demo --force

bench: setup
	@for b in bench/bench_*.py; do $(LOCAL) $(ENV) python "$$b" || exit 1; done

clean:
	rm -rf .venv ros_ws/build ros_ws/install ros_ws/log rfm_output
