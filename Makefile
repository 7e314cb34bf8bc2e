# Set-up and go on a fresh Debian machine: `make demo` and `make test` install what is missing.
SHELL := /bin/bash
PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
SUDO := $(shell [ "$$(id -u)" = 0 ] || echo sudo)
STAMP := $(VENV)/.fae-installed
export PYOPENGL_PLATFORM ?= osmesa

.PHONY: all install system-deps browser demo test test-fast clean

all: install

# Debian packages: OSMesa for headless OpenGL; libGL and GLib, which OpenCV (under
# MediaPipe, the face-landmark model of `fae adapt`) loads at import. Installed only when missing.
# npm (tools/package.json) brings three.js for `fae serve --live` and the glTF validator.
system-deps:
	@missing=""; \
	ldconfig -p 2>/dev/null | grep -q 'libOSMesa\.so' || missing="$$missing libosmesa6"; \
	ldconfig -p 2>/dev/null | grep -q 'libGL\.so\.1' || missing="$$missing libgl1"; \
	ldconfig -p 2>/dev/null | grep -q 'libgthread-2\.0\.so\.0' || missing="$$missing libglib2.0-0"; \
	if [ -n "$$missing" ]; then \
	  echo "installing$$missing from Debian"; \
	  $(SUDO) apt-get update -qq && $(SUDO) DEBIAN_FRONTEND=noninteractive apt-get install -y -qq $$missing >/dev/null; \
	fi

# The virtual environment. pyrender is installed last with --no-deps: its pin on
# PyOpenGL==3.1.0 cannot use OSMesa (see the comment in pyproject.toml).
$(STAMP): pyproject.toml | system-deps
	@[ -x $(PY) ] || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	$(PY) -m pip install -q -e '.[dev,landmarks,photo,batch]'
	$(PY) -m pip install -q --no-deps 'pyrender==0.1.45'
	@if command -v npm >/dev/null 2>&1 && { [ ! -d tools/node_modules/gltf-validator ] || [ ! -d tools/node_modules/three ]; }; then \
	  npm install --prefix tools --silent --no-audit --no-fund --no-package-lock >/dev/null 2>&1 \
	  || echo "npm packages not installed: no live view (fae serve --live); the glTF validation test will be skipped"; \
	fi
	@touch $(STAMP)

install: system-deps $(STAMP)

demo: install
	$(VENV)/bin/fae play fap_streams/expressions.fap -o demo.mp4
	@echo "wrote demo.mp4"

# A real browser for the live view's test (the product never needs one): Debian's chromium,
# driven by Playwright's Python API. Installed only when missing.
browser:
	@command -v chromium >/dev/null 2>&1 || { echo "installing chromium from Debian (for the browser tests)"; \
	  $(SUDO) apt-get update -qq && $(SUDO) DEBIAN_FRONTEND=noninteractive apt-get install -y -qq chromium >/dev/null; }

# The whole suite, slow end-to-end tests included, on both cores.
test: install browser
	$(PY) -m pytest -n 2 -q

test-fast: install
	$(PY) -m pytest -n 2 -q -m "not slow"

clean:
	rm -rf $(VENV) build *.egg-info .pytest_cache .hypothesis
