# dvr_perception: one-command set-up, tests, demo and benchmark.
#
#   make demo    set up everything, then render the phantom into demo_out/
#   make test    set up everything, then ruff check, ruff format --check, pytest
#   make bench   benchmark JSON for the phantom, engine and cthead at 512x512
#
# "setup" installs the EGL/Mesa system libraries VTK needs to render off-screen (with apt-get,
# when run as root and they are missing), creates $(VENV) and installs the package with its
# dev extras.  Reruns skip both steps when nothing changed.

SHELL := /bin/bash
PYTHON ?= python3
VENV ?= .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.dvr-perception-installed
DATA ?= ../shared/data
BENCH_SIZE ?= 512
APT_PACKAGES := libegl1 libegl-mesa0 libgl1-mesa-dri libosmesa6

# Render headless through EGL when there is no X display.
ifeq ($(strip $(DISPLAY)),)
export VTK_DEFAULT_OPENGL_WINDOW ?= vtkEGLRenderWindow
endif

.PHONY: help setup system-deps test lint demo bench clean

help:
	@echo "targets: demo, test, bench, setup, lint, clean"

setup: system-deps $(STAMP)

system-deps:
	@if ! command -v dpkg-query >/dev/null 2>&1; then \
	  echo "setup: not a Debian system; make sure EGL/OSMesa and python3-venv are installed"; \
	  exit 0; \
	fi; \
	missing=""; \
	for p in $(APT_PACKAGES); do \
	  dpkg-query -W -f='$${Status}' $$p 2>/dev/null | grep -q "install ok installed" \
	    || missing="$$missing $$p"; \
	done; \
	if ! command -v $(PYTHON) >/dev/null 2>&1 \
	   || ! $(PYTHON) -c "import ensurepip, venv" >/dev/null 2>&1; then \
	  missing="$$missing python3 python3-venv"; \
	fi; \
	if [ -z "$$missing" ]; then exit 0; fi; \
	if [ "$$(id -u)" = 0 ] && command -v apt-get >/dev/null 2>&1; then \
	  echo "setup: installing system packages:$$missing"; \
	  export DEBIAN_FRONTEND=noninteractive; \
	  apt-get update && apt-get install -y --no-install-recommends $$missing; \
	else \
	  echo "setup: missing system packages:$$missing" >&2; \
	  echo "setup: install them as root, e.g. sudo apt-get install -y --no-install-recommends$$missing" >&2; \
	  exit 1; \
	fi

$(STAMP): pyproject.toml
	@test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install -e '.[dev]'
	@touch $(STAMP)

lint: setup
	$(BIN)/ruff check .
	$(BIN)/ruff format --check .

test: lint
	$(BIN)/pytest

demo: setup
	$(BIN)/dvr-perception demo --out demo_out

bench: setup
	$(BIN)/dvr-perception bench phantom --size $(BENCH_SIZE) --json
	$(BIN)/dvr-perception bench $(DATA)/engine.nhdr --size $(BENCH_SIZE) --json
	$(BIN)/dvr-perception bench $(DATA)/cthead.nhdr --size $(BENCH_SIZE) --json

clean:
	rm -rf demo_out bench_out .pytest_cache build
