# Multiscale Camera: development targets.
#
#   make build    stage and pack the extension: dist/multiscale_camera-<version>-<platform>.zip
#   make test     build, then run tests/ (unit, blender, e2e, tools) with $(BLENDER), in
#                 TEST_WORKERS pytest-xdist workers (default 2: 12 to 14 min in one, 9 in two)
#   make test-quick  the tests marked neither slow nor e2e: no build, about a minute
#   make samples  write sample_blends/*.blend
#   make demo     install the linux zip in a throwaway user folder, render demo.blend to out/
#   make demo-anim  render sample_blends/dolly.blend at 160x90 to out/dolly.mp4 (FFmpeg)
#   make bench    speed and accuracy: solver, every method, the renderer, the Cycles hand-off,
#                 volume ray casting, the dolly's fields frame after frame: bench/*.json
#   make bench-1080  the default build (AUTO, STANDARD) on every bench rig at 1920x1080,
#                 forced SCALAR_FIELD on the 1000x and turned rigs: bench/methods_1920x1080.json
#   make bench-preview  AUTO at PREVIEW on every bench rig at 480x270:
#                 bench/methods_480x270_preview.json
#   make lint     ruff (its checks and its format) and the import contracts
#                 (pyproject.toml, [tool.importlinter])
#   make fuzz     the core on 500 random rigs (tests/unit/test_fuzz_core.py, profile "full");
#                 make test runs its bounded profile
#   make e2e-real the extension in real Blender 5.2 and 4.3, screenshots to docs/images/
#   make e2e-timing  Compute Field and render of the demo: real 5.2 window against -b
#
# BLENDER defaults to tools/blender (Blender's command line on the bpy wheel);
# point it at a real Blender to run the same tests there.

SHELL := bash
.DEFAULT_GOAL := build
.DELETE_ON_ERROR:

PYTHON311 := $(shell command -v python3.11)
VENV := .venv
PY := $(VENV)/bin/python
# The import contracts of pyproject.toml: the core imports no other layer and no bpy, and
# its stages import only the stages below them; io imports the core at most, adapters
# the core and io, render no ui.
LINT_IMPORTS := $(VENV)/bin/lint-imports --no-logo
VENV_STAMP := $(VENV)/.stamp
BPY_SCRIPTS := $(VENV)/lib/python3.11/site-packages/bpy/5.0/scripts
BLENDER_EXT := $(PY) $(BPY_SCRIPTS)/addons_core/bl_pkg/cli/blender_ext.py
# Blender's own tag list, the one `blender --command extension build` checks against.
VALID_TAGS := --valid-tags $(BPY_SCRIPTS)/modules/_bpy_internal/extensions/tags.py

BLENDER ?= $(CURDIR)/tools/blender
export BLENDER
# pytest-xdist workers of `make test` (0: in pytest's own process); the worker processes
# a test starts come on top.
TEST_WORKERS ?= 2

OPENEXR_VERSION := $(shell sed -n 's/^OpenEXR==//p' requirements.txt)
PACKAGE_FILES := $(shell find multiscale_camera -name __pycache__ -prune -o -print 2>/dev/null)
LINUX_ZIP := dist/LINUX_ZIP
# what sample_blends/*.blend are made from
SAMPLE_SCRIPTS := $(wildcard sample_blends/*.py fixtures/*.py fixtures/blender/*.py)
# --python-exit-code acts on the scripts after it, as in Blender.
RUN_SAMPLES := $(BLENDER) -b --factory-startup --python-exit-code 1 \
	--python sample_blends/make_samples.py

.PHONY: venv build test test-quick samples demo demo-anim bench bench-1080 bench-render \
	bench-anim bench-preview lint clean distclean e2e-real \
	e2e-timing fuzz

venv: $(VENV_STAMP)

$(VENV_STAMP): requirements.txt
	@if [ ! -x $(PY) ]; then \
	  if [ -z "$(PYTHON311)" ]; then echo "python3.11 is not on PATH" >&2; exit 1; fi; \
	  echo "$(PYTHON311) -m venv $(VENV)"; $(PYTHON311) -m venv $(VENV); \
	fi
	$(PY) -m pip install --quiet -r requirements.txt
	touch $@

build: $(LINUX_ZIP)

# The zips hold the manifest (plus platforms and wheels), the package's contents at the
# root and the OpenEXR wheels; dist/LINUX_ZIP names the linux-x64 one for tests and demo.
$(LINUX_ZIP): $(VENV_STAMP) blender_manifest.toml tools/stage.py $(PACKAGE_FILES)
	rm -rf dist && mkdir -p dist
	$(PY) tools/stage.py build/stage --openexr $(OPENEXR_VERSION) \
	  --package multiscale_camera --manifest blender_manifest.toml --cache .cache/wheels
	$(BLENDER_EXT) build --source-dir build/stage --output-dir dist --split-platforms $(VALID_TAGS)
	for zip in dist/*.zip; do $(BLENDER_EXT) validate $(VALID_TAGS) "$$zip" || exit 1; done
	ls dist/*-linux_x64.zip > $@
	@echo "linux-x64 zip: $$(cat $@)"

test: build
	$(PY) -m ruff check .
	$(LINT_IMPORTS)
	$(PY) -m pytest -q -n $(TEST_WORKERS) tests

fuzz: venv
	MULTISCALE_FUZZ=full $(PY) -m pytest -q -p no:cacheprovider --hypothesis-show-statistics \
	  tests/unit/test_fuzz_core.py

# The loop while working: neither the slow tests (pyproject.toml's markers) nor those
# that run $(BLENDER) in a subprocess, so no build is needed.
test-quick: venv
	$(PY) -m pytest -q -m "not slow and not e2e" tests

samples: venv
	$(RUN_SAMPLES)

sample_blends/demo.blend: $(SAMPLE_SCRIPTS) | venv
	$(RUN_SAMPLES)

demo: build sample_blends/demo.blend
	rm -rf out/blender-user && mkdir -p out
	BLENDER_USER_RESOURCES=$(CURDIR)/out/blender-user $(BLENDER) -b --factory-startup \
	  --python-exit-code 1 --python tools/demo.py -- \
	  --zip "$$(cat $(LINUX_ZIP))" --blend sample_blends/demo.blend --out out

sample_blends/dolly.blend: $(SAMPLE_SCRIPTS) | venv
	$(BLENDER) -b --factory-startup --python-exit-code 1 \
	  --python sample_blends/make_samples.py -- --only dolly

# The dolly sample, every second frame at 25 % (160x90) and Preview quality (a field
# takes about a minute a frame at High), as an H.264 video; its fields
# (one per frame: the rig moves) stay in out/dolly-cache for the next run.
demo-anim: sample_blends/dolly.blend
	mkdir -p out
	$(BLENDER) -b sample_blends/dolly.blend --python-exit-code 1 --python tools/demo_anim.py \
	  -- --out out/dolly.mp4 --percentage 25 --step 2 --quality PREVIEW --cache out/dolly-cache \
	  --stills out/dolly-stills

# Speed and accuracy figures (minutes, not part of `make test`): the membership solver
# against the paper's explicit diffusion (capped at 8 minutes a size: a capped run gives
# a lower bound on the ratio), then every method at every quality on every bench rig at 480x270
# (the 1000x rig on nested grids takes minutes a build even there), then the
# Cycles hand-off against plain Cycles at 480x270, 64 samples, on the three-camera test
# scene and on the 100k-triangle scene of bench-render (about 3 minutes on 2 cores),
# then volume ray casting of a 256^3 phantom at 1920x1080, the memory guard's estimate
# against measured peaks (bench/memory.json) and the live picture's delay after a
# stroke (bench/live_picture.json, 20 strokes at 480x270).
bench: venv bench-render bench-anim bench-preview
	$(PY) bench/solvers.py --sizes 64 128 256 320 --diffusion-sizes 64 128 --cap 480
	$(PY) bench/methods.py --width 480 --height 270
	$(PY) bench/cycles.py --width 480 --height 270 --samples 64
	$(PY) bench/volume.py --width 1920 --height 1080 --voxels 256
	$(PY) bench/memory.py
	$(PY) bench/live_picture.py --strokes 20

# The dolly sample's fields at 960x540 with AUTO (one method for the shot, measured on
# three of its frames), frames 1-3 built in sequence (each taking what the one before
# left valid) against each built cold, and frame 2 built cold with SCALAR_FIELD for
# reference: bench/anim.json (about 2 minutes).
bench-anim: venv
	$(PY) bench/anim.py --width 960 --height 540 --frames 1 2 3 --quality PREVIEW \
	  --method AUTO --scalar-reference

# The acceptance pass at 1920x1080 (an hour or more on 2 cores): AUTO at STANDARD, the
# properties' defaults, on every rig of bench/methods.py (the demo's and the galleon's
# cameras and masks from fixtures/rigs.py, the numbers their sample files are made from),
# and SCALAR_FIELD as the add-on builds it on the 1000x and turned rigs; a row that takes
# more than BENCH_TIMEOUT seconds is recorded as timed out. Redraws the chart, the
# failure table of docs/methods.md and the acceptance table of docs/performance.md.
BENCH_TIMEOUT ?= 600
bench-1080: venv
	nice -n 10 $(PY) bench/methods.py --plan default --width 1920 --height 1080 \
	  --timeout $(BENCH_TIMEOUT) --out bench/methods_1920x1080.json --docs

# AUTO at PREVIEW on every bench rig at 480x270, the live picture's and the viewport's
# quality: bench/methods_480x270_preview.json and its table in docs/performance.md.
bench-preview: venv
	nice -n 10 $(PY) bench/methods.py --plan preview --width 480 --height 270 \
	  --timeout $(BENCH_TIMEOUT) --out bench/methods_480x270_preview.json --docs

# The renderer on a 100k-triangle scene at 1920x1080: raw BVH rate, engine cast rate,
# render time, cancel latency: bench/render.json.
bench-render: venv
	$(PY) bench/render.py --width 1920 --height 1080 --triangles 100000

# The extension in real Blender 5.2 and 4.3 (../shared/tools/realblender; needs root, and
# builds its chroots on first use): install, render, and a scripted run in a real window
# whose screenshots land in docs/images/. Optional: not part of `make test`.
e2e-real: build sample_blends/demo.blend
	tools/e2e_real/run.sh

# Compute Field and the render of demo.blend in a real Blender 5.2 window and with
# `blender -b` on the same cores: out/e2e-real/timing-*.json. Optional, needs root.
e2e-timing: build sample_blends/demo.blend
	tools/e2e_real/timing.sh

lint: venv
	$(PY) -m ruff check .
	$(PY) -m ruff format --check .
	$(LINT_IMPORTS)

clean:
	rm -rf build dist out .pytest_cache .ruff_cache .import_linter_cache
	find . -path ./$(VENV) -prune -o -name __pycache__ -type d -prune -exec rm -rf {} +

distclean: clean
	rm -rf $(VENV) .cache
