# Set-up is idempotent: a stamp file records that .venv matches pyproject.toml;
# the browser step is a quick check once chromium is there. No npm: Leaflet is
# vendored in the package (swarm/runtime/station/vendor/leaflet, see `make leaflet`).
PY ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed
LEAFLET := swarm/runtime/station/vendor/leaflet
# Debian's chromium drives the page tests and the page benchmark (headless).
CHROMIUM_PKGS := chromium fonts-dejavu-core
CHROMIUM_BIN ?= chromium
# apt-get waits up to 5 minutes for a package lock another program holds (an unattended
# upgrade at boot) instead of failing at once
APT_WAIT := -o DPkg::Lock::Timeout=300

.PHONY: setup browser systemd-analyze demo docs test test-quick lint check clean leaflet screenshots

# Debian's own python3 makes a venv only with its python3-venv package.
$(STAMP): pyproject.toml
	@$(PY) -m venv $(VENV) || { rm -rf $(VENV); \
	  echo "setup: $(PY) -m venv failed (on Debian: sudo apt-get install python3-venv)" >&2; exit 1; }
	$(BIN)/pip install --quiet --upgrade pip
	$(BIN)/pip install --quiet -e '.[test,docs]'
	touch $(STAMP)

# Leaflet for the ground station page, pinned in package.json and package-lock.json,
# is vendored into the package with its licence and checksums (the wheel and the
# sdist carry it; never a CDN). Only to change or re-check the pin (needs npm):
# `make leaflet` copies it from the npm package (npm ci checks the lock's hash);
# `git diff` then shows any change, and tests/test_packaging.py checks the sums.
leaflet:
	@command -v npm >/dev/null 2>&1 || { echo "leaflet: npm not found (apt-get install -y npm)" >&2; exit 1; }
	npm ci --no-audit --no-fund --loglevel=error
	rm -rf $(LEAFLET)
	mkdir -p $(LEAFLET)/images
	cp node_modules/leaflet/dist/leaflet.js node_modules/leaflet/dist/leaflet.css node_modules/leaflet/LICENSE $(LEAFLET)/
	cp node_modules/leaflet/dist/images/*.png $(LEAFLET)/images/
	cd $(LEAFLET) && sha256sum LICENSE leaflet.css leaflet.js images/*.png > SHA256SUMS

# A headless browser for the page tests: Debian's chromium, installed only when
# missing, as root or with a sudo that asks no password (set-up never prompts:
# otherwise it says what to run and goes on). Elsewhere set CHROMIUM=/path/to/chromium.
# Without a browser the page tests fail (tests/gcs_browser.py): they never skip.
browser:
	@if [ -n "$$CHROMIUM" ] || command -v $(CHROMIUM_BIN) >/dev/null 2>&1; then exit 0; fi; \
	if ! command -v apt-get >/dev/null 2>&1; then \
	  echo "setup: no chromium and no apt-get: the page tests will fail (install chromium, or set CHROMIUM=/path/to/chromium)" >&2; exit 0; fi; \
	SUDO=; if [ "$$(id -u)" != 0 ]; then \
	  if sudo -n true 2>/dev/null; then SUDO="sudo -n"; else \
	    echo "setup: chromium missing and no root or password-less sudo: run sudo apt-get install $(CHROMIUM_PKGS), or the page tests fail" >&2; \
	    exit 0; fi; fi; \
	echo "setup: installing Debian's chromium (headless browser for the page tests)"; \
	log=$$(mktemp); \
	if ! { $$SUDO apt-get $(APT_WAIT) update -qq && DEBIAN_FRONTEND=noninteractive \
	       $$SUDO apt-get $(APT_WAIT) install -y -qq --no-install-recommends $(CHROMIUM_PKGS); } >"$$log" 2>&1; then \
	  cat "$$log" >&2; rm -f "$$log"; echo "setup: installing chromium failed" >&2; exit 1; fi; \
	rm -f "$$log"

# systemd-analyze checks the shipped unit files (tests/test_systemd.py): Debian's
# systemd package, installed only when missing (root, or a sudo that asks no password).
systemd-analyze:
	@if command -v systemd-analyze >/dev/null 2>&1; then exit 0; fi; \
	if ! command -v apt-get >/dev/null 2>&1; then \
	  echo "setup: no systemd-analyze and no apt-get: install systemd, or the unit test fails" >&2; exit 0; fi; \
	SUDO=; if [ "$$(id -u)" != 0 ]; then \
	  if sudo -n true 2>/dev/null; then SUDO="sudo -n"; else \
	    echo "setup: systemd-analyze missing and no root or password-less sudo: run sudo apt-get install systemd, or the unit test fails" >&2; \
	    exit 0; fi; fi; \
	echo "setup: installing Debian's systemd (systemd-analyze verify for the unit files)"; \
	log=$$(mktemp); \
	if ! { $$SUDO apt-get $(APT_WAIT) update -qq && DEBIAN_FRONTEND=noninteractive \
	       $$SUDO apt-get $(APT_WAIT) install -y -qq --no-install-recommends systemd; } >"$$log" 2>&1; then \
	  cat "$$log" >&2; rm -f "$$log"; echo "setup: installing systemd failed" >&2; exit 1; fi; \
	rm -f "$$log"

setup: $(STAMP) browser systemd-analyze

# The demo needs no browser (it opens the page only where there is a display): only the venv.
demo: $(STAMP)
	$(BIN)/swarm demo

# Static checks, shared by both test targets.
check: setup
	$(BIN)/ruff check radios firmware_bridge swarm tests tools docs/conf.py
	$(BIN)/ruff format --check radios firmware_bridge swarm tests tools docs/conf.py
	$(BIN)/mypy
	$(BIN)/lint-imports --no-logo

# The documentation site (docs/, Sphinx with MyST): strict, a warning (a broken link or
# reference, a page in no table of contents) fails it. The HTML lands in docs/_build/html.
docs: setup
	$(BIN)/sphinx-build -W --keep-going -q -b html docs docs/_build/html

# Everything (what CI runs): three pytest sessions side by side, the real-time process
# tests in one, the long ones that mostly wait in another, everything else in the third
# (tests/run_all.sh says why).
test: check docs
	PYTEST=$(BIN)/pytest tests/run_all.sh

# The checks and the tests that need no processes, real-time radios, simulators or
# browser (the `processes` marker): about a minute, for the edit-test loop.
test-quick: check
	$(BIN)/pytest -m 'not slow and not hardware and not processes'

# The operator guide's pictures, from the page tests that take them (docs/images/).
screenshots: setup
	$(BIN)/python tools/docs_screenshots.py

clean:
	rm -rf $(VENV) node_modules build *.egg-info .pytest_cache .mypy_cache .ruff_cache docs/_build
