# Two entry points: `make run` (the daemon on the simulated payload) and `make test` (the whole suite).
# Each creates .venv and installs what it needs.
PYTHON ?= python3
VENV   := .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.installed
# Debian packages the daemon uses: GigE cameras (Aravis, and the headers PyGObject builds against) and
# the RTSP live view (GStreamer RTSP server + x264). Without them the daemon still runs; those two don't.
DEBIAN_RUN  := gir1.2-aravis-0.8 libgirepository1.0-dev libcairo2-dev pkg-config gir1.2-gstreamer-1.0 \
               gir1.2-gst-plugins-base-1.0 gir1.2-gst-rtsp-server-1.0 gstreamer1.0-plugins-base \
               gstreamer1.0-plugins-good gstreamer1.0-plugins-ugly
# What only the tests use: the real clients (ffmpeg, Chromium), the fake GigE camera, systemd-analyze.
DEBIAN_TEST := aravis-tools systemd chromium ffmpeg

.PHONY: run test lint bench debian-deps debian-test-deps clean

$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/pip install -q -U pip
	$(BIN)/pip install -q -e ".[test]"
	@if pkg-config --exists gobject-introspection-1.0 2>/dev/null; then \
		$(BIN)/pip install -q -e ".[test,aravis]" || echo "note: PyGObject did not build: GigE (Aravis) and --rtsp are unavailable"; \
	else echo "note: GObject introspection headers missing, GigE (Aravis) and --rtsp unavailable; run 'make debian-deps'"; fi
	touch $@

# Installs the missing ones with apt-get (as root, or through sudo). Where that is not possible (no apt,
# no root) it says which packages are missing and goes on, unless THERMOD_STRICT=1 (CI).
define install_debian
	@missing=""; for p in $(1); do dpkg -s $$p >/dev/null 2>&1 || missing="$$missing $$p"; done; \
	[ -z "$$missing" ] && exit 0; \
	if [ "$$(id -u 2>/dev/null)" = 0 ]; then sudo=""; elif command -v sudo >/dev/null 2>&1; then sudo=sudo; \
	else sudo=none; fi; \
	if [ "$$sudo" != none ] && command -v apt-get >/dev/null 2>&1 && \
		$$sudo apt-get update -qq && DEBIAN_FRONTEND=noninteractive $$sudo apt-get install -y -qq $$missing; \
	then exit 0; fi; \
	echo "note: could not install the Debian packages:$$missing ($(2))" >&2; \
	[ "$${THERMOD_STRICT:-0}" != 1 ]
endef

debian-deps:
	$(call install_debian,$(DEBIAN_RUN),GigE cameras and --rtsp stay unavailable; the simulated payload runs)

debian-test-deps: debian-deps
	$(call install_debian,$(DEBIAN_TEST),the tests that need them skip)

run: debian-deps $(STAMP)
	$(BIN)/thermod run

# Two workers, whole files each (module fixtures such as test_faults' daemon stay in one process),
# in collection order: the `heavy` analysis files first (tests/conftest.py). A worker that crashes
# ends the run, naming its test: xdist 3.8's loadfile replaces it and then waits forever
# (pytest-xdist issues 784, 1378).
test: debian-test-deps $(STAMP)
	$(BIN)/pytest -n 2 --dist loadfile --no-loadscope-reorder --max-worker-restart=0

# ruff, and the layers contract of pyproject.toml (import-linter; .ci/lint_imports.py says why a wrapper)
lint: $(STAMP)
	$(BIN)/ruff check .
	$(BIN)/python .ci/lint_imports.py

bench: $(STAMP)
	$(BIN)/python -m benchmarks

clean:
	rm -rf $(VENV) build *.egg-info
