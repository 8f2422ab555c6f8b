# Two commands on a fresh machine: `make demo` and `make test`.
# Both create (or reuse) .venv and install what they need.
PYTHON ?= python3
VENV   := .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed
# torch first and pinned: on this machine torch==2.13.0 resolves to the CPU wheel on disk
# (a bare `torch` would pull a multi-GB CUDA build).  The package itself states a range.
TORCH_PIN ?= torch==2.13.0
PIP := $(PY) -m pip --disable-pip-version-check
# Blender's cloth engine: the `bpy` wheel (GPL-3; CPython 3.11 only; pins numpy<2) lives in its
# own environment inside .venv, which the engine starts as a worker (docs/simulator.md).
BPY_ENV := $(VENV)/bpy
BPY_PIN ?= bpy==5.0.1
# where a bpy wheel exists, `make test` fails (not skips) the Blender tests if it is missing
EXPECT_BLENDER := $(shell $(PYTHON) -c "import platform, sys; print(int(sys.version_info[:2] == (3, 11) and platform.machine() in ('x86_64', 'AMD64', 'arm64')))" 2>/dev/null)
PYTEST_ARGS ?=

VIEWER := build/viewer/viewer.bundle.js
# Debian packages for headless rendering (EGL for VTK) and the viewer test (chromium)
APT_PKGS ?= libegl1 libgl1-mesa-dri chromium

.PHONY: install system-deps demo test test-slow bench-layers clean

install: $(STAMP) system-deps $(VIEWER)

$(STAMP): setup.cfg pyproject.toml Makefile
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PIP) install -q --upgrade pip setuptools wheel
	$(PIP) install -q "$(TORCH_PIN)"
	$(PIP) install -q -e ".[dev,human,smpl,ray,viz]"
	# torch-scatter compiles against the installed torch (~4 min once; pip caches the wheel)
	$(PIP) install -q --no-build-isolation "torch-scatter>=2.1,<3"
	@if [ "$(EXPECT_BLENDER)" = "1" ]; then \
	  test -x $(BPY_ENV)/bin/python || $(PYTHON) -m venv $(BPY_ENV); \
	  $(BPY_ENV)/bin/python -m pip --disable-pip-version-check install -q "$(BPY_PIN)"; \
	else \
	  echo "note: no bpy wheel for this Python/platform: the Blender engine is not installed (the torch engine still works)"; \
	fi
	touch $(STAMP)

# apt packages, each only when missing; without root or apt-get: a note, no failure
# (renders and the viewer test then skip and say why)
system-deps:
	@missing=""; for p in $(APT_PKGS); do dpkg -s $$p >/dev/null 2>&1 || missing="$$missing $$p"; done; \
	if [ -z "$$missing" ]; then exit 0; fi; \
	if [ "$$(id -u)" = 0 ] && command -v apt-get >/dev/null 2>&1; then \
		apt-get update -q && DEBIAN_FRONTEND=noninteractive apt-get install -y -q --no-install-recommends $$missing; \
	else echo "note: not root or no apt-get; install$$missing yourself for headless renders (EGL) and the HTML viewer test (chromium)"; fi

# the HTML viewer's script: three.js from npm bundled by esbuild (outside the package source)
$(VIEWER): viewer/viewer.js viewer/package.json viewer/package-lock.json
	@if command -v npm >/dev/null 2>&1; then \
		mkdir -p build/viewer && cp viewer/package.json viewer/package-lock.json viewer/viewer.js build/viewer/ && \
		cd build/viewer && npm ci --no-audit --no-fund --loglevel=error && \
		npx esbuild viewer.js --bundle --format=iife --minify --outfile=viewer.bundle.js --log-level=warning; \
	else echo "note: npm not found; the HTML viewer (garmentgnn.viz.viewer) needs build/viewer/viewer.bundle.js (apt-get install npm, then make install)"; fi

# The main demo: every layer learns a mesh operator; then the reference simulator
# generates the `tiny` dataset, GarTrans is trained on it and predicts the held-out
# motion: metrics vs LBS and demo_out/gartrans_demo.{mp4,gif,png} (simulated / GarTrans / LBS
# side by side, coloured by per-vertex error).
demo: install
	$(PY) examples/layer_demo.py
	$(PY) examples/train_demo.py --out demo_out

# The linter first (ruff, configured in pyproject.toml), then the suite without the tests
# marked `slow`, with torch-scatter; then the tests of the code that scatters (the layers,
# the models, the baselines) again with torch-scatter hidden (PyG's native scatter path);
# last, the tests marked `float_sensitive` under two other MKL code paths (~20 s each), so
# a comparison that holds on this CPU's path only fails here too, not on a user's CPU.
# The tests marked `slow` (minutes each: Blender and Ray end to end, training through the
# CLI and the bench, the committed checkpoint's row) run with `make test-slow`.
SCATTER_TESTS := tests/test_nn_*.py tests/test_sat_conv.py tests/test_layers_contract.py \
	tests/test_baseline_layers.py tests/test_model.py tests/test_model_inference.py \
	tests/test_baselines.py
test: install
	$(PY) -m ruff check src tests benchmarks examples
	GARMENTGNN_EXPECT_SCATTER=1 GARMENTGNN_EXPECT_BLENDER=$(EXPECT_BLENDER) $(PY) -m pytest -m "not slow" $(PYTEST_ARGS)
	GARMENTGNN_NO_SCATTER=1 $(PY) -m pytest -q -m "not slow" $(SCATTER_TESTS) $(PYTEST_ARGS)
	for path in AVX2 COMPATIBLE; do \
	  MKL_CBWR=$$path $(PY) -m pytest -q -m "float_sensitive and not slow" $(PYTEST_ARGS) || exit 1; \
	done

test-slow: install
	GARMENTGNN_EXPECT_SCATTER=1 GARMENTGNN_EXPECT_BLENDER=$(EXPECT_BLENDER) $(PY) -m pytest -m slow $(PYTEST_ARGS)

bench-layers: $(STAMP)
	$(PY) benchmarks/layers.py

clean:
	rm -rf $(VENV) build *.egg-info src/*.egg-info
