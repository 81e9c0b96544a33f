# volcap: `make demo` runs the pipeline on generated data, `make test` runs the suite (with the
# lint), `make test-fast` the pure tests and the lint in under two minutes.
# Both build .venv themselves (Debian packages via apt-get, pinned Python packages via uv).

PYTHON ?= python3.11
VENV   := .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.volcap-installed
UV_VERSION := 0.13.8
PACKAGES := $(wildcard src/volcap_*)
DEMO_DIR ?= demo_out
WEB_STAMP := web/node_modules/.volcap-installed

# Large ROS messages: keep glibc from returning multi-MB buffers to the OS after every frame.
export MALLOC_MMAP_THRESHOLD_ := 67108864
export MALLOC_TRIM_THRESHOLD_ := 268435456

.PHONY: venv web chromium iptables bytecode lint test test-fast demo bench bench-faults colcon docs clean

venv: $(STAMP)

$(STAMP): requirements.txt constraints.txt tools/tf2_msgs/requirements.txt $(wildcard tools/tf2_msgs/*.*) Makefile
	@ldconfig -p | grep -q 'libusb-1.0.so.0' || { \
	  echo "installing Debian libusb-1.0-0 (needed by Open3D)"; \
	  apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq libusb-1.0-0; }
	@{ command -v cmake && command -v g++ && test -f /usr/include/python3.11/Python.h; } >/dev/null || { \
	  echo "installing Debian cmake, g++, python3.11-dev (to build tf2_msgs)"; \
	  apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq cmake g++ python3.11-dev; }
	@test -x $(PY) || $(PYTHON) -m venv $(VENV)
	@# uv installs the same pins as pip (same index, same resolution) in about a minute from a cold
	@# cache where pip took three: torch's CUDA wheels and Open3D are 8 GB unpacked. It compiles the
	@# bytecode as pip does: with PYTHONDONTWRITEBYTECODE set (as here) every node process would
	@# otherwise compile numpy, torch and rclpy from source (pytest took 15 min 52 s, not 11 min 44 s).
	$(PY) -m pip install -q --disable-pip-version-check uv==$(UV_VERSION)
	$(VENV)/bin/uv pip install -q --native-tls --compile-bytecode --python $(PY) \
	  -r requirements.txt -r tools/tf2_msgs/requirements.txt -c constraints.txt
	@# tf2_msgs (for /tf_static) is on no registry here: build it with the rosidl toolchain into the venv,
	@# whose lib/ the ROS wheels already put on LD_LIBRARY_PATH.
	@echo "building tf2_msgs into $(VENV) with rosidl (under a minute)"
	@rm -rf build/tf2_msgs
	@PATH="$(CURDIR)/$(VENV)/bin:$$PATH" AMENT_PREFIX_PATH="$(CURDIR)/$(VENV)" CMAKE_PREFIX_PATH="$(CURDIR)/$(VENV)" \
	  sh -c 'cmake -S tools/tf2_msgs -B build/tf2_msgs -DCMAKE_INSTALL_PREFIX="$(CURDIR)/$(VENV)" \
	    -DPython3_EXECUTABLE="$(CURDIR)/$(PY)" -DBUILD_TESTING=OFF && cmake --build build/tf2_msgs -j2 \
	    && cmake --install build/tf2_msgs' > build-tf2_msgs.log 2>&1 || { tail -30 build-tf2_msgs.log; exit 1; }
	$(PY) -c 'from tf2_msgs.msg import TFMessage; TFMessage()'
	@# The volcap packages run from src/ in the venv (colcon builds the same tree for a rig).
	@$(PY) -c 'import pathlib, sysconfig; site = pathlib.Path(sysconfig.get_paths()["purelib"]); \
	  (site / "volcap_src.pth").write_text("".join(str(p.resolve()) + "\n" for p in sorted(pathlib.Path("src").glob("volcap_*"))))'
	@# colcon installs bringup's `volcap` console script on a rig; the venv gets the same entry point.
	@printf '#!/bin/sh\nexec "$$(dirname "$$0")/python" -m volcap_bringup.cli "$$@"\n' > $(VENV)/bin/volcap
	@chmod +x $(VENV)/bin/volcap
	@touch $(STAMP)

# The browser player's three.js and the Khronos glTF validator, from npm (web/package-lock.json).
web: $(WEB_STAMP)

$(WEB_STAMP): web/package.json web/package-lock.json
	cd web && npm ci --no-audit --no-fund --loglevel=error
	@touch $@

# Debian's Chromium: the player's tests load it headless (Playwright drives it; no browser download).
chromium:
	@command -v chromium >/dev/null || { \
	  echo "installing Debian chromium (the browser tests)"; \
	  apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq chromium; }

# Debian's iptables: bench/multihost.py drops packets on the link with its `statistic` match.
iptables:
	@command -v iptables >/dev/null || { \
	  echo "installing Debian iptables (bench/multihost.py's packet loss)"; \
	  apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq iptables; }

# The volcap packages' bytecode, compiled ahead (only files changed since recompile): with
# PYTHONDONTWRITEBYTECODE set, as on this project's machines, every node process a test or the
# demo starts would compile them from source again (0.2-0.3 s of each start on 2 cores).
bytecode: $(STAMP)
	@$(PY) -m compileall -q src

# Style (ruff) and the package layers (import-linter contracts in .importlinter).
lint: $(STAMP)
	$(VENV)/bin/ruff check .
	$(VENV)/bin/lint-imports

# Two workers (pytest-xdist), a test file each at a time: most ROS tests wait on discovery and
# the player as much as they compute, so two files at once use both cores (docs/benchmarks.md).
TEST_WORKERS ?= 2

test: lint web chromium bytecode
	$(PY) -m pytest test -n $(TEST_WORKERS) --dist loadfile

# No ROS nodes, nothing slow: the algorithms, the nodes' decision classes, packaging and docs.
test-fast: lint web bytecode
	$(PY) -m pytest test -m 'not ros and not slow' -n $(TEST_WORKERS) --dist loadfile

# Regenerates the parameter tables in docs/ from the config dataclasses.
docs: $(STAMP)
	$(PY) -m volcap_bringup.docs

demo: $(STAMP) web bytecode
	$(VENV)/bin/volcap demo --out $(DEMO_DIR)

bench: $(STAMP)
	$(PY) bench/transport.py
	$(PY) bench/rig_transport.py
	$(PY) bench/filter.py
	test -d bench_out/calib40 || .venv/bin/volcap synth --out bench_out/calib40 --frames 0 --board-poses 40 --background-frames 0 --seed 5 --quiet
	$(PY) bench/calib.py bench_out/calib40

# Recording a rig (write speed, kill -9 and recover) and the graph across two hosts (as root).
bench-faults: $(STAMP) iptables
	$(PY) bench/record.py
	$(PY) bench/multihost.py

colcon: $(STAMP)
	$(VENV)/bin/colcon build --base-paths src --build-base build --install-base install

clean:
	rm -rf build install log $(DEMO_DIR) .pytest_cache
