# volcap: `make demo` runs the pipeline on generated data, `make test` runs the suite (with the
# lint), `make test-fast` the pure tests and the lint in under two minutes.
# Both build .venv themselves (Debian packages via apt-get, pinned Python packages via pip).

PYTHON ?= python3.11
VENV   := .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.volcap-installed
PACKAGES := $(wildcard src/volcap_*)
DEMO_DIR ?= demo_out

# Large ROS messages: keep glibc from returning multi-MB buffers to the OS after every frame.
export MALLOC_MMAP_THRESHOLD_ := 67108864
export MALLOC_TRIM_THRESHOLD_ := 268435456

.PHONY: venv lint test test-fast demo bench colcon docs clean

venv: $(STAMP)

$(STAMP): requirements.txt constraints.txt Makefile
	@ldconfig -p | grep -q 'libusb-1.0.so.0' || { \
	  echo "installing Debian libusb-1.0-0 (needed by Open3D)"; \
	  apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq libusb-1.0-0; }
	@test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --disable-pip-version-check -r requirements.txt -c constraints.txt
	@# The volcap packages run from src/ in the venv (colcon builds the same tree for a rig).
	@$(PY) -c 'import pathlib, sysconfig; site = pathlib.Path(sysconfig.get_paths()["purelib"]); \
	  (site / "volcap_src.pth").write_text("".join(str(p.resolve()) + "\n" for p in sorted(pathlib.Path("src").glob("volcap_*"))))'
	@# colcon installs bringup's `volcap` console script on a rig; the venv gets the same entry point.
	@printf '#!/bin/sh\nexec "$$(dirname "$$0")/python" -m volcap_bringup.cli "$$@"\n' > $(VENV)/bin/volcap
	@chmod +x $(VENV)/bin/volcap
	@touch $(STAMP)

# Style (ruff) and the package layers (import-linter contracts in .importlinter).
lint: $(STAMP)
	$(VENV)/bin/ruff check .
	$(VENV)/bin/lint-imports

test: lint
	$(PY) -m pytest test

# No ROS nodes, nothing slow: the algorithms, the nodes' decision classes, packaging and docs.
test-fast: lint
	$(PY) -m pytest test -m 'not ros and not slow'

# Regenerates the parameter tables in docs/ from the config dataclasses.
docs: $(STAMP)
	$(PY) -m volcap_bringup.docs

demo: $(STAMP)
	$(VENV)/bin/volcap demo --out $(DEMO_DIR)

bench: $(STAMP)
	$(PY) bench/transport.py
	$(PY) bench/filter.py
	test -d bench_out/calib40 || .venv/bin/volcap synth --out bench_out/calib40 --frames 0 --board-poses 40 --background-frames 0 --seed 5 --quiet
	$(PY) bench/calib.py bench_out/calib40

colcon: $(STAMP)
	$(VENV)/bin/colcon build --base-paths src --build-base build --install-base install

clean:
	rm -rf build install log $(DEMO_DIR) .pytest_cache
