# Set-up is idempotent: stamp files record that .venv matches pyproject.toml and
# node_modules matches package-lock.json; the browser step is a quick check once
# chromium is there.
PY ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed
NODE_STAMP := node_modules/.installed
# Debian's chromium drives the page tests and the page benchmark (headless).
CHROMIUM_PKGS := chromium fonts-dejavu-core
CHROMIUM_BIN ?= chromium

.PHONY: setup browser systemd-analyze demo test test-quick lint check clean

$(STAMP): pyproject.toml
	$(PY) -m venv $(VENV)
	$(BIN)/pip install --quiet --upgrade pip
	$(BIN)/pip install --quiet -e '.[test]'
	touch $(STAMP)

# Leaflet for the ground station page, pinned in package-lock.json; served by
# swarm gcs from node_modules/leaflet/dist (never a CDN).
$(NODE_STAMP): package.json package-lock.json
	@command -v npm >/dev/null 2>&1 || { echo "setup: npm not found (install Node.js and npm: apt-get install -y npm)" >&2; exit 1; }
	npm ci --no-audit --no-fund --loglevel=error
	touch $(NODE_STAMP)

# A headless browser for the page tests: Debian's chromium, installed only when
# missing (root, or sudo). Elsewhere set CHROMIUM=/path/to/chromium instead.
browser:
	@if [ -n "$$CHROMIUM" ] || command -v $(CHROMIUM_BIN) >/dev/null 2>&1; then exit 0; fi; \
	if ! command -v apt-get >/dev/null 2>&1; then \
	  echo "setup: no chromium and no apt-get: the page tests will skip (set CHROMIUM=/path/to/chromium)" >&2; exit 0; fi; \
	SUDO=; if [ "$$(id -u)" != 0 ]; then \
	  if sudo -n true 2>/dev/null; then SUDO="sudo -n"; else \
	    echo "setup: chromium missing and no root or sudo: apt-get install chromium, or the page tests skip" >&2; \
	    exit 0; fi; fi; \
	echo "setup: installing Debian's chromium (headless browser for the page tests)"; \
	log=$$(mktemp); \
	if ! { $$SUDO apt-get update -qq && DEBIAN_FRONTEND=noninteractive \
	       $$SUDO apt-get install -y -qq --no-install-recommends $(CHROMIUM_PKGS); } >"$$log" 2>&1; then \
	  cat "$$log" >&2; rm -f "$$log"; echo "setup: installing chromium failed" >&2; exit 1; fi; \
	rm -f "$$log"

# systemd-analyze checks the shipped unit files (tests/test_systemd.py): Debian's
# systemd package, installed only when missing (root, or sudo).
systemd-analyze:
	@if command -v systemd-analyze >/dev/null 2>&1; then exit 0; fi; \
	if ! command -v apt-get >/dev/null 2>&1; then \
	  echo "setup: no systemd-analyze and no apt-get: install systemd, or the unit test fails" >&2; exit 0; fi; \
	SUDO=; if [ "$$(id -u)" != 0 ]; then \
	  if sudo -n true 2>/dev/null; then SUDO="sudo -n"; else \
	    echo "setup: systemd-analyze missing and no root or sudo: apt-get install systemd" >&2; \
	    exit 0; fi; fi; \
	echo "setup: installing Debian's systemd (systemd-analyze verify for the unit files)"; \
	log=$$(mktemp); \
	if ! { $$SUDO apt-get update -qq && DEBIAN_FRONTEND=noninteractive \
	       $$SUDO apt-get install -y -qq --no-install-recommends systemd; } >"$$log" 2>&1; then \
	  cat "$$log" >&2; rm -f "$$log"; echo "setup: installing systemd failed" >&2; exit 1; fi; \
	rm -f "$$log"

setup: $(STAMP) $(NODE_STAMP) browser systemd-analyze

demo: setup
	$(BIN)/swarm demo

# Static checks, shared by both test targets.
check: setup
	$(BIN)/ruff check radios firmware_bridge swarm tests
	$(BIN)/ruff format --check radios firmware_bridge swarm tests
	$(BIN)/mypy
	$(BIN)/lint-imports --no-logo

# Everything (what CI runs).
test: check
	$(BIN)/pytest

# The checks and the tests that need no processes, real-time radios, simulators or
# browser (the `processes` marker): about a minute, for the edit-test loop.
test-quick: check
	$(BIN)/pytest -m 'not slow and not hardware and not processes'

clean:
	rm -rf $(VENV) node_modules build *.egg-info .pytest_cache .mypy_cache .ruff_cache
