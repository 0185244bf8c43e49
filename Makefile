# dvr_perception: one-command set-up, tests, demo and benchmark.
#
#   make demo    set up everything, then render the phantom into demo_out/
#   make test    set up everything, then ruff check, ruff format --check, pytest
#   make bench   benchmark JSON for the phantom, engine and cthead at 512x512 (benchmarks/bench/)
#   make docs    the manual (Sphinx) into docs/_build/html, warnings as errors
#   make optimiser-figures  benchmarks/optimizer_acceptance.json (the manual's optimiser table)
#   make readme-image       docs/images/readme_before_after.png (the README's image)
#   make renderer-figures   benchmarks/check_renderer.jsonl (the manual's image-agreement table)
#   make report  regenerate benchmarks/REPORT.md (the paper's experiments; REPORT_ARGS=--quick)
#   make scale   benchmarks/scale.json: time and memory against volume size, MPI ranks
#   make paraview-setup   ParaView, Xvfb and .pvdeps/ for the plugin and `dvr-perception pvbatch`;
#                         prints the plugin file to load (`dvr-perception paraview-plugin`)
#   make paraview-macros  the DVR Perception toolbar (macros) into ParaView's user macro folder
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
BENCH_REPEAT ?= 5
README_IMAGE_ARGS ?= --size 384
OPTIMISER_DATASETS ?= phantom,engine,cthead,lidc_chest,tooth,neghip,bonsai
APT_PACKAGES := libegl1 libegl-mesa0 libgl1-mesa-dri libosmesa6
# Web app (issue 7): its browser tests drive Debian's Chromium with playwright (never
# `playwright install`, which downloads a browser).
BROWSER_APT_PACKAGES := chromium

# ParaView (issue 6): Debian's ParaView 5.11 renders only under Xvfb.  Its pvpython gets the
# core's dependencies from $(PVDEPS) (pip --target with ParaView's numpy 1.24 left in place:
# --no-deps and the pins of $(PVDEPS_REQ)); never the venv, whose VTK would crash pvpython.
PVDEPS ?= .pvdeps
PVDEPS_REQ := dvr_perception/paraview/pvdeps-requirements.txt
PVDEPS_STAMP := $(PVDEPS)/.dvr-perception-installed
# openmpi-bin: the MPI test (mpiexec -n 2 pvbatch); gcc + libc6-dev: the pvserver test builds
# a small LD_PRELOAD shim that keeps pvserver on loopback.
PV_APT_PACKAGES := paraview python3-paraview xvfb xauth openmpi-bin gcc libc6-dev

# Render headless through EGL when there is no X display.
ifeq ($(strip $(DISPLAY)),)
export VTK_DEFAULT_OPENGL_WINDOW ?= vtkEGLRenderWindow
endif

.PHONY: help setup system-deps browser-deps paraview-setup paraview-macros paraview-system test lint demo bench report scale clean docs readme-image optimiser-figures renderer-figures

help:
	@echo "targets: demo, test, docs, bench, report, setup, paraview-setup, lint, clean"

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

browser-deps:
	@if command -v chromium >/dev/null 2>&1 || [ -x /usr/bin/chromium ]; then exit 0; fi; \
	if [ "$$(id -u)" = 0 ] && command -v apt-get >/dev/null 2>&1; then \
	  echo "setup: installing $(BROWSER_APT_PACKAGES) (browser tests of the web app)"; \
	  export DEBIAN_FRONTEND=noninteractive; \
	  apt-get update && apt-get install -y $(BROWSER_APT_PACKAGES); \
	else \
	  echo "setup: chromium is not installed; the web-app browser tests will skip" \
	    "(install it as root: apt-get install -y $(BROWSER_APT_PACKAGES))" >&2; \
	  case "$${CI:-}" in 1|true|yes) exit 1;; esac; \
	fi

$(STAMP): pyproject.toml
	@test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install -e '.[dev]'
	@touch $(STAMP)

paraview-setup: setup paraview-system $(PVDEPS_STAMP)
	@$(BIN)/dvr-perception paraview-plugin

# The DVR Perception toolbar (issue 19): the macros of dvr_perception/paraview/macros in
# ParaView's user macro folder (~/.config/ParaView/Macros); ParaView shows them on its Macro
# Toolbar at start-up.
paraview-macros: setup
	$(BIN)/dvr-perception paraview-plugin --install-macros

paraview-system:
	@missing=""; \
	command -v pvpython >/dev/null 2>&1 && command -v pvbatch >/dev/null 2>&1 \
	  || missing=" paraview python3-paraview"; \
	command -v xvfb-run >/dev/null 2>&1 || missing="$$missing xvfb"; \
	command -v xauth >/dev/null 2>&1 || missing="$$missing xauth"; \
	command -v mpiexec >/dev/null 2>&1 || missing="$$missing openmpi-bin"; \
	command -v cc >/dev/null 2>&1 || missing="$$missing gcc"; \
	[ -e /usr/include/stdio.h ] || missing="$$missing libc6-dev"; \
	if [ -z "$$missing" ]; then exit 0; fi; \
	if [ "$$(id -u)" = 0 ] && command -v apt-get >/dev/null 2>&1; then \
	  echo "paraview-setup: installing$$missing"; \
	  export DEBIAN_FRONTEND=noninteractive; \
	  apt-get update && apt-get install -y $(PV_APT_PACKAGES); \
	else \
	  echo "paraview-setup: ParaView is not installed (missing:$$missing); the ParaView" \
	    "tests will skip and 'dvr-perception pvbatch' will not run." >&2; \
	  echo "paraview-setup: install it as root: apt-get install -y $(PV_APT_PACKAGES)" >&2; \
	  case "$${CI:-}" in 1|true|yes) exit 1;; esac; \
	fi

$(PVDEPS_STAMP): $(PVDEPS_REQ) | $(STAMP) paraview-system
	@if ! command -v pvpython >/dev/null 2>&1; then \
	  echo "paraview-setup: no pvpython, so no $(PVDEPS)/"; exit 0; \
	fi; \
	set -e; \
	echo "paraview-setup: dvr-perception paraview-plugin --install-deps (pip install --no-deps --target $(PVDEPS) -r $(PVDEPS_REQ))"; \
	rm -rf $(PVDEPS); \
	DVR_PERCEPTION_PVDEPS="$(abspath $(PVDEPS))" $(BIN)/dvr-perception paraview-plugin --install-deps >/dev/null; \
	env -u VTK_DEFAULT_OPENGL_WINDOW PYTHONPATH="$(CURDIR)/dvr_perception/paraview/pvsite" \
	  DVR_PERCEPTION_PVDEPS="$(abspath $(PVDEPS))" pvpython -c \
	  "import dvr_perception._paraview_compat as c; c.setup(); import dvr_perception.filters, \
	  numpy, scipy, skimage, numba, pydicom, nibabel, libjpeg, openjpeg; print('paraview-setup: pvpython imports numpy', \
	  numpy.__version__, 'scipy', scipy.__version__, 'scikit-image', skimage.__version__, \
	  'numba', numba.__version__)"; \
	touch $(PVDEPS_STAMP)

lint: setup
	$(BIN)/ruff check .
	$(BIN)/ruff format --check .

# the manual builds after the tests, so that the gallery's scripts find numba's kernels cached
test: lint browser-deps paraview-setup
	$(BIN)/pytest
	@$(MAKE) --no-print-directory docs

# the manual: user guide, API reference from the docstrings, gallery (its scripts run), the
# figures read from benchmarks/*.json; warnings are errors
docs: setup
	$(BIN)/sphinx-build -W --keep-going -q -b html docs docs/_build/html
	@echo "docs: docs/_build/html/index.html"

# benchmarks/check_renderer.jsonl: the manual's image-agreement table (our engine against VTK's
# CPU ray caster, unshaded and shaded, and against the PyVista display; 256x256, three views)
renderer-figures: setup
	@set -e; out=benchmarks/check_renderer.jsonl; : > $$out.tmp; \
	for v in phantom $(DATA)/engine.nhdr $(DATA)/cthead.nhdr $(DATA)/tooth.nhdr; do \
	  for view in 0,0 40,30 120,0; do \
	    for mode in --no-shade --shade "--against plotter"; do \
	      r=$$($(BIN)/dvr-perception check-renderer $$v --size 256 --view=$$view $$mode \
	           --out-dir build/check_renderer --json); \
	      echo "{\"view\": \"$$view\", \"mode\": \"$$mode\", \"result\": $$r}" >> $$out.tmp; \
	    done; \
	  done; \
	done; mv $$out.tmp $$out; echo "renderer-figures: wrote $$out"

# the README's before/after image, made by the command the README names beside it
readme-image: setup
	$(BIN)/dvr-perception optimize $(DATA)/cthead.nhdr $(README_IMAGE_ARGS) --out build/readme_image
	cp build/readme_image/before_after.png docs/images/readme_before_after.png

demo: setup
	$(BIN)/dvr-perception demo --out demo_out

# benchmarks/bench/NAME.json: the manual's speed table (docs/guide/figures.md) reads them
bench: setup
	@mkdir -p benchmarks/bench
	@set -e; for v in phantom $(DATA)/engine.nhdr $(DATA)/cthead.nhdr; do \
	  n=$$(basename $$v .nhdr); \
	  $(BIN)/dvr-perception bench $$v --size $(BENCH_SIZE) --repeat $(BENCH_REPEAT) --json \
	    > benchmarks/bench/$$n.json.tmp; \
	  mv benchmarks/bench/$$n.json.tmp benchmarks/bench/$$n.json; \
	  echo "bench: wrote benchmarks/bench/$$n.json"; \
	done

# benchmarks/optimizer_acceptance.json: the manual's optimiser table (the whole three-stage run
# with the defaults on the shared volumes at 512x512; about 4 minutes on 2 idle cores)
optimiser-figures: setup
	$(BIN)/python -m dvr_perception.optimize.acceptance --size $(BENCH_SIZE) --data $(DATA) \
	  --datasets $(OPTIMISER_DATASETS) --out build/acceptance
	cp build/acceptance/acceptance.json benchmarks/optimizer_acceptance.json

report: setup
	$(BIN)/dvr-perception report --data $(DATA) --out benchmarks -v $(REPORT_ARGS)

# time and memory against volume size up to 512x512x452, and MPI ranks 1, 2, 4 (~15 min);
# then `dvr-perception report --markdown-only --out benchmarks` puts it into the report
scale: setup
	$(BIN)/python -m benchmarks.scale --data $(DATA) --out benchmarks/scale.json $(SCALE_ARGS)

clean:
	rm -rf demo_out bench_out .pytest_cache build docs/_build docs/api docs/auto_examples
