# Two entry points: `make run` (the daemon on the simulated payload) and `make test` (the whole suite).
# Each creates .venv and installs what it needs.
PYTHON ?= python3
VENV   := .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.installed
DEBIAN_PKGS := gir1.2-aravis-0.8 aravis-tools libgirepository1.0-dev libcairo2-dev pkg-config systemd chromium gir1.2-gstreamer-1.0 gir1.2-gst-plugins-base-1.0 gir1.2-gst-rtsp-server-1.0 gstreamer1.0-plugins-base gstreamer1.0-plugins-good gstreamer1.0-plugins-ugly ffmpeg

.PHONY: run test lint bench debian-deps clean

$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/pip install -q -U pip
	$(BIN)/pip install -q -e ".[test]"
	@if pkg-config --exists gobject-introspection-1.0 2>/dev/null; then \
		$(BIN)/pip install -q -e ".[test,aravis]"; \
	else echo "note: GObject introspection headers missing, GigE (Aravis) support not installed; run 'make debian-deps'"; fi
	touch $@

# Debian packages: Aravis (GigE Vision), GStreamer RTSP server + x264 (thermod run --rtsp), and the real
# clients the tests use (ffmpeg, Chromium, systemd-analyze); needs root (or sudo).
debian-deps:
	@missing=$$(for p in $(DEBIAN_PKGS); do dpkg -s $$p >/dev/null 2>&1 || echo $$p; done); \
	if [ -n "$$missing" ]; then \
		SUDO=$$( [ "$$(id -u)" = 0 ] || echo sudo ); \
		$$SUDO apt-get update -qq && DEBIAN_FRONTEND=noninteractive $$SUDO apt-get install -y -qq $$missing; \
	fi

run: debian-deps $(STAMP)
	$(BIN)/thermod run

# Two workers, whole files each (module fixtures such as test_faults' daemon stay in one process),
# in collection order: the `heavy` analysis files first (tests/conftest.py).
test: debian-deps $(STAMP)
	$(BIN)/pytest -n 2 --dist loadfile --no-loadscope-reorder

# ruff, and the layers contract of pyproject.toml (import-linter; .ci/lint_imports.py says why a wrapper)
lint: $(STAMP)
	$(BIN)/ruff check .
	$(BIN)/python .ci/lint_imports.py

bench: $(STAMP)
	$(BIN)/python -m benchmarks

clean:
	rm -rf $(VENV) build *.egg-info
