# mds_ach -- `make run` starts the whole system on the simulated robot, `make test` runs every test.
# Each target (re)creates the virtual environment in .venv when requirements changed.

SHELL := /bin/bash
.SHELLFLAGS := -eo pipefail -c
VENV ?= .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.mds_ach_installed
DEV_STAMP := $(VENV)/.mds_ach_dev_installed
# mds_ach's libach for C clients (libach/): libach.so + ach.h + pkgconfig/ach.pc in the venv prefix
LIBACH := $(VENV)/lib/libach.so.4.0.0
BENCH_STAMP := $(VENV)/.mds_ach_bench_installed
# The ROS interface packages (interfaces/: mds_ach_interfaces, the control_msgs subset), built with rosidl into the
# venv prefix; rebuilt only when a file under interfaces/ (or the build script) changes.
IFACES := $(VENV)/.mds_ach_interfaces_built
IFACES_SRC := $(shell find interfaces -type f -not -name '*~') tools/build-interfaces
export AMENT_PREFIX_PATH := $(abspath $(VENV))
PYTEST_ARGS ?=

.PHONY: all setup dev sysdeps run test bench soak lint clean help

help:
	@echo "make setup  the runtime venv only (what a running system imports; no test tools, no torch)"
	@echo "make dev    setup + the test and tooling dependencies (pytest, ruff, torch for the FK cross-check)"
	@echo "make run    set up if needed, then start the whole system on the simulated robot (Ctrl-C stops it)"
	@echo "make test   set up if needed, then run all tests (inside a private network namespace)"
	@echo "make bench  run every benchmark against its peers (bench/requirements.txt) and print one table"
	@echo "make soak   multi-minute soak, then the adversarial safety scenario at 10 and 100 Hz with CPU hogs (not in make test)"
	@echo "make lint   ruff"

all: setup

setup: $(STAMP) $(LIBACH) $(IFACES)

dev: $(DEV_STAMP)

# pip's resolver then lists the dependencies the --no-deps packages declare (requirements-nodeps.txt) as "not
# installed", under an ERROR header: they are left out on purpose, so exactly those lines are dropped (a version
# conflict, "requires X, but you have Y", still shows).
NODEPS := $(shell sed -E -n 's/^([A-Za-z0-9_.-]+)==.*/\1/p' requirements-nodeps.txt | paste -sd'|')
PIP_NOISE := ^WARNING: Location|^ERROR: pip's dependency resolver does not currently take into account|^($(NODEPS)) [^ ]+ requires [^ ]+, which is not installed\.$$
# pip install -e . also compiles mds_ach/ach/_achfast.c (the optional C fast path of mds_ach.ach) and mds_ach/ach/_shmguard.c
# (the SIGBUS guard for channel mappings) when gcc is there.
$(STAMP): requirements.txt requirements-nodeps.txt setup.py setup.cfg package.xml mds_ach/ach/_achfast.c \
		mds_ach/ach/achcore.h mds_ach/ach/_shmguard.c mds_ach/kinematics/_collfast.c mds_ach/kinematics/_iksearch.c
	@test -x $(PY) || { echo "creating $(VENV) and installing the runtime packages (first run only: a few minutes, the ROS interface packages are compiled once) ..."; \
		python3 -m venv $(VENV); }
	@# setuptools >= 70.1 builds the editable install without the separate wheel package (torch used to pull it in).
	$(PY) -m pip install -q --upgrade pip setuptools==84.2.1 2>&1 | grep -v '^WARNING: Location' || true
	@# A venv from before requirements-nodeps.txt has opencv-python, which shares the cv2 package with the headless
	@# build pinned now: remove it first (a fresh venv skips this).
	@if compgen -G '$(VENV)/lib/python3*/site-packages/opencv_python-*.dist-info' >/dev/null; then \
		$(PY) -m pip uninstall -q -y opencv-python; fi
	$(PY) -m pip install -q -r requirements.txt 2>&1 | { grep -v -E "$(PIP_NOISE)" || true; }
	@# viser, yourdfpy, trimesh, python-fcl without the dependencies they declare but never import for us (opencv's
	@# GUI build, scipy, scikit-image, embreex, Cython...: most of the venv); requirements.txt pins what they import.
	$(PY) -m pip install -q --no-deps -r requirements-nodeps.txt 2>&1 | { grep -v '^WARNING: Location' || true; }
	PYTHONWARNINGS=ignore $(PY) -m pip install -q --no-deps --no-build-isolation -e .
	@$(PY) -c 'from mds_ach import ach; print("mds_ach.ach:", "C fast path" if ach.FAST_AVAILABLE else \
		"pure Python (no C compiler or Python headers: slower; see docs/architecture.md)", \
		"+ SIGBUS guard" if ach.GUARD_AVAILABLE else "(no SIGBUS guard: a truncated channel kills its users)")'
	@touch $@

# mds_ach_interfaces + control_msgs (FollowJointTrajectory) into the venv prefix: `from mds_ach_interfaces.msg import
# MuxState` works in every node. Needs cmake and g++ (make sysdeps).
$(IFACES): $(STAMP) $(IFACES_SRC)
	tools/build-interfaces $(VENV)
	@touch $@

# libach.so, ach.h and ach.pc, built from the project's channel code (mds_ach/ach/achcore.h), so C clients build
# with `cc demo.c -I$(VENV)/include -L$(VENV)/lib -lach` or `pkg-config --cflags --libs ach`.
$(LIBACH): libach/libach.c libach/ach.h libach/ach.pc.in libach/Makefile mds_ach/ach/achcore.h
	@test -x $(PY) || python3 -m venv $(VENV)
	$(MAKE) -s -C libach install PREFIX=$(abspath $(VENV))
	@echo "libach: $(abspath $(VENV))/lib/libach.so, include/ach.h, lib/pkgconfig/ach.pc"

# The test and tooling dependencies (requirements-dev.txt: pytest, ruff, torch for the FK cross-check, ...) on top
# of the runtime ones; `make setup` / `make run` never install them.
$(DEV_STAMP): $(STAMP) $(LIBACH) $(IFACES) requirements-dev.txt
	$(PY) -m pip install -q -r requirements.txt -r requirements-dev.txt 2>&1 | { grep -v -E "$(PIP_NOISE)" || true; }
	@touch $@

# ISOLATE=1 (default): the ROS nodes stay in a private network namespace (`mds-ach ros-shell` enters it); channels
# live on the host /dev/shm so that `mds-ach console`, `read` and C clients in other terminals see them.
# ISOLATE=0: no namespace, the nodes join this machine's ROS graph (ROS_DOMAIN_ID from the environment, default 0).
# WORLD=FILE: world objects for the collision gate and the IK node (e.g. WORLD=config/table.yaml, the table enabled).
ISOLATE ?= 1
WORLD ?=
RUN_ARGS = --nocan $(if $(WORLD),--world $(WORLD))
run: $(STAMP) $(LIBACH) $(IFACES)
ifeq ($(ISOLATE),0)
	$(VENV)/bin/mds-ach run $(RUN_ARGS)
else
	MDS_NETNS_SHARE_SHM=1 tools/netns-run $(VENV)/bin/mds-ach run $(RUN_ARGS)
endif

sysdeps:
	@tools/install-system-deps

test: sysdeps $(DEV_STAMP)
	$(VENV)/bin/ruff check .
	$(VENV)/bin/mypy
	tools/netns-run $(PY) -m pytest -q -ra $(PYTEST_ARGS)

# The peers the benchmarks measure ours against (bench/requirements.txt: Pinocchio + coal, iceoryx2, ...), on top of
# the dev venv; never part of the runtime (`make setup`).
$(BENCH_STAMP): $(DEV_STAMP) bench/requirements.txt
	$(PY) -m pip install -q -r bench/requirements.txt 2>&1 | { grep -v '^WARNING: Location' || true; }
	@touch $@

# Set-up cost (make setup into a temporary venv) needs the package registry: measured outside the namespace first.
bench: $(BENCH_STAMP)
	$(PY) -m bench.bench_setup measure $(VENV)/bench-setup.json
	MDS_BENCH_SETUP_RESULT=$(abspath $(VENV))/bench-setup.json tools/netns-run $(PY) -m bench

# The soak (SOAK_MINUTES), then the adversarial safety scenario (bench/adversary.py) for SOAK_ADVERSARY_MINUTES at
# each rate of SOAK_RATES, its second half beside SOAK_HOGS CPU hogs (each report gives the daemon's worst stall
# under them); every report is printed, the target fails if any part fails.
SOAK_MINUTES ?= 3
SOAK_ADVERSARY_MINUTES ?= 10
SOAK_RATES ?= 10 100
SOAK_HOGS ?= 3
soak: $(DEV_STAMP)
	rc=0; tools/netns-run $(PY) -m bench.soak --minutes $(SOAK_MINUTES) || rc=1; \
	for rate in $(SOAK_RATES); do \
		tools/netns-run $(PY) -m bench.adversary --minutes $(SOAK_ADVERSARY_MINUTES) --rate $$rate \
			--hogs $(SOAK_HOGS) || rc=1; \
	done; exit $$rc

lint: $(DEV_STAMP)
	$(VENV)/bin/ruff check .

clean:
	rm -rf build install log .pytest_cache mds_ach/ach/_achfast.*.so mds_ach/ach/_shmguard.*.so \
		mds_ach/kinematics/_collfast.*.so mds_ach/kinematics/_iksearch.*.so
