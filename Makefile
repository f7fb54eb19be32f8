# Entry points: `make demo` (main job), `make test` (suite), `make bench` (speed table).
# Each target creates .venv and installs pinned dependencies on first use; re-runs are
# fast because installation is keyed on a stamp file newer than every install input.
SHELL := /bin/bash
PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed
PKGS := assist_common assist_sim assist_perception assist_policy assist_bags assist_lab assist_bridge assist_station
PKG_INPUTS := $(foreach p,$(PKGS),ros2_ws/src/$(p)/setup.py ros2_ws/src/$(p)/setup.cfg ros2_ws/src/$(p)/package.xml)
# Nodes in tests run on a private DDS domain so they never meet anyone else's graph.
export ROS_DOMAIN_ID ?= 42
export RMW_IMPLEMENTATION ?= rmw_fastrtps_cpp

.PHONY: venv demo test test-scale lint bench soak colcon clean help browser netns bytecode

help:
	@echo "make demo   - run the simulated landing demo (creates .venv)"
	@echo "make test   - lint, then run the test suite (creates .venv)"
	@echo "make test-scale - the scale and stress checks (several landings in one graph, a starved CPU); CI runs them after make test"
	@echo "make lint   - the style gate: ruff check with ruff.toml"
	@echo "make bench  - print the benchmark table"
	@echo "make soak   - soak test: full assisted graph, 30 min sim time (ASSIST_SOAK_SIM_S=seconds to change)"
	@echo "make colcon - build ros2_ws with colcon into ros2_ws/install"
	@echo "make browser - install Chromium + ChromeDriver (Debian packages) for the pilot station browser test"
	@echo "make netns  - install iproute2 (Debian package) for the network-split test"

venv: $(STAMP)

$(STAMP): requirements.txt $(PKG_INPUTS)
	@test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	$(PY) -m pip install -q -r requirements.txt
	$(PY) -m pip install -q --no-deps $(foreach p,$(PKGS),-e ros2_ws/src/$(p))
	@touch $(STAMP)

demo: $(STAMP)
	$(PY) -m assist_lab.demo

# The pilot station's browser test needs Chromium + ChromeDriver (Debian packages; apt-get as root, else sudo).
browser:
	@command -v chromium >/dev/null && command -v chromedriver >/dev/null || { \
	  SUDO=$$( [ "$$(id -u)" -eq 0 ] || echo sudo ); \
	  $$SUDO apt-get update && $$SUDO apt-get install -y chromium chromium-driver; }

# The network-split test needs iproute2 (ip netns, veth, tc netem; TUN devices where the kernel has no netem).
netns:
	@command -v ip >/dev/null && command -v tc >/dev/null || { \
	  SUDO=$$( [ "$$(id -u)" -eq 0 ] || echo sudo ); \
	  $$SUDO apt-get update && $$SUDO apt-get install -y iproute2; }

# The style gate (ruff.toml); make test runs it first, so CI does too.
lint: $(STAMP)
	$(VENV)/bin/ruff check .

# Two worker processes (TEST_WORKERS), a test file per worker at a time, in the order conftest.py sets (the slow
# files first, longest first; xdist would otherwise put the files with the most tests first); each worker has its
# own DDS domains. The scale and stress checks (marker `scale`) have their own target; .ci/run runs both.
# Bytecode is written even where the environment says not to (PYTHONDONTWRITEBYTECODE): the sources are compiled
# once before the workers start, so each worker's collection and each of the hundreds of node and tool processes
# the tests start reads them instead of compiling them again, and pytest keeps its rewritten test modules.
TEST_WORKERS ?= 2
bytecode: $(STAMP)
	$(PY) -m compileall -q -j 0 ros2_ws/src tests bench > /dev/null

test: $(STAMP) browser netns lint bytecode
	PYTHONDONTWRITEBYTECODE= $(PY) -m pytest -n $(TEST_WORKERS) --dist loadfile --no-loadscope-reorder -m "not scale"

test-scale: $(STAMP) bytecode
	PYTHONDONTWRITEBYTECODE= $(PY) -m pytest -p no:cacheprovider -m scale

bench: $(STAMP)
	$(PY) -m bench

# Not part of `make test`: the full assisted graph for ASSIST_SOAK_SIM_S seconds of sim time (default 30 min).
soak: $(STAMP)  # ASSIST_SOAK_RTF=2: a real-time factor the graph keeps up with (default 0)
	ASSIST_SOAK_SIM_S=$${ASSIST_SOAK_SIM_S:-1800} $(PY) -m pytest -s -p no:cacheprovider tests/faults/test_soak_assisted_graph.py

colcon: $(STAMP)
	cd ros2_ws && ../$(VENV)/bin/colcon build --symlink-install --event-handlers console_direct-

clean:
	rm -rf $(VENV) ros2_ws/build ros2_ws/install ros2_ws/log
