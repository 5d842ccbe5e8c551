# Robotics (RCM + FIROS): developer entry points. Everything ROS-related runs with /usr/bin first on PATH
# and /usr/bin/python3 (README.md, "Working on it": the PATH trap).

SHELL := /bin/bash
PYTHON := /usr/bin/python3
export PATH := /usr/bin:/bin:/usr/sbin:/sbin:$(PATH)
WS := build/rcmp_ws
OVERLAY := $(WS)/devel/setup.bash
PYTEST_ARGS ?=
DEMO_ARGS ?=

.PHONY: help deps build test test-fast compat demo demo-hosts bench dist clean

help:
	@echo "make demo   - start a master and a robot on this machine (loopback) and pair them"
	@echo "make demo-hosts - a master and two robots, each in a network namespace, over the platform's own VPN"
	@echo "                  (options of either demo: ./run demo-hosts DEMO_ARGS='--console-port 8090')"
	@echo "make test   - install what the tests need, build the catkin workspace, run every test"
	@echo "make compat - the compatibility matrix: each supported system's Python and libraries (tox.ini)"
	@echo "make deps   - apt-get install the toolchain (idempotent, needs root)"
	@echo "make build  - build the catkin workspace $(WS) (robotics_msgs, rcm, firos)"
	@echo "make bench  - run the benchmarks and write docs/PERFORMANCE.md"
	@echo "make bench-NAME - run one benchmark (bench/bench_NAME.py), e.g. make bench-fleet"
	@echo "make dist   - build every distribution zip into dist/ (create_robotics_pkg)"

deps:
	bash scripts/install-deps.sh

build: $(OVERLAY)

$(OVERLAY): $(shell find robotics_msgs rcm firos demo tests/ros_pkgs -name package.xml -o -name CMakeLists.txt -o -name '*.msg' -o -name '*.srv' 2>/dev/null)
	bash scripts/build-workspace.sh $(WS)

test: deps build
	bash scripts/run-tests.sh $(PYTEST_ARGS)

compat: deps build
	bash scripts/compat/matrix.sh

test-fast: build
	bash scripts/run-tests.sh -m 'not slow' $(PYTEST_ARGS)

demo: deps build
	bash scripts/with-overlay.sh $(PYTHON) -m demo.run_demo $(DEMO_ARGS)

demo-hosts: deps build
	bash scripts/with-overlay.sh $(PYTHON) -m demo.run_demo_hosts $(DEMO_ARGS)

bench: deps build
	bash scripts/with-overlay.sh $(PYTHON) -m bench.run_all

bench-%: deps build
	bash scripts/with-overlay.sh $(PYTHON) -m bench.run_all $*

dist:
	for what in "" master robot firos rcm_driver robotics_msgs demo; do ./create_robotics_pkg $$what -o dist || exit 1; done

clean:
	rm -rf build
