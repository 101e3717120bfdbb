# Two commands a new user needs (see README.md):
#   make run    set everything up and run dffd on its embedded default (simulated camera,
#               embedded MQTT broker, live console view)
#   make test   set everything up (incl. mosquitto) and run the test suite
# Both are idempotent: the virtual environment is rebuilt only when pyproject.toml changes.

PYTHON ?= python3
VENV   ?= .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.installed

.PHONY: run test lint setup system-deps bench clean

run: setup
	$(BIN)/dffd run

test: setup system-deps
	$(BIN)/pytest -q

lint: setup
	$(BIN)/ruff check .
	$(BIN)/ruff format --check .
	$(BIN)/mypy

bench: setup
	$(BIN)/python -m hil bench --out hil/out

setup: $(STAMP)

$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/pip install --quiet --upgrade pip
	$(BIN)/pip install --quiet -e '.[dev]'
	$(BIN)/python -m dffd.warmup
	touch $(STAMP)

# mosquitto (a real broker for the MQTT tests) and systemd-analyze (unit verification) come
# from Debian; install them only when missing.
system-deps:
	@if ! command -v mosquitto_sub >/dev/null 2>&1 && ! test -x /usr/sbin/mosquitto \
	   || ! command -v systemd-analyze >/dev/null 2>&1 \
	   || ! command -v chromedriver >/dev/null 2>&1; then \
	  SUDO=$$( [ "$$(id -u)" = 0 ] || echo sudo ); \
	  $$SUDO apt-get update -qq && \
	  DEBIAN_FRONTEND=noninteractive $$SUDO apt-get install -y -qq --no-install-recommends \
	    mosquitto mosquitto-clients systemd openssl chromium chromium-driver; \
	fi

# build/ and *.egg-info/ too: setuptools reuses a stale build/lib, so a module moved or deleted
# since the last build would still end up in the next wheel.
clean:
	rm -rf $(VENV) .mypy_cache .ruff_cache .pytest_cache build *.egg-info
