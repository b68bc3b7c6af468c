# Two commands: `make run` (set up and start the app) and `make test` (set up and run the checks).
# Both are idempotent: the virtual environment is rebuilt only when pyproject.toml or
# requirements.lock change, system libraries are installed only when missing.

PYTHON ?= python3.11
VENV   := .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed
HOST   ?= 127.0.0.1
PORT   ?= 8000

.PHONY: run test lint system-deps venv clean

venv: $(STAMP)

$(STAMP): pyproject.toml requirements.lock
	@test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --disable-pip-version-check -c requirements.lock -e '.[dev]'
	@touch $(STAMP)

# open3d-cpu links libusb-1.0, which slim Debian images lack; the browser tests (tests/e2e)
# drive Debian's Chromium (Playwright never downloads a browser here).
system-deps:
	@ldconfig -p | grep -q 'libusb-1.0.so.0' || { \
	  echo "installing libusb-1.0-0 (needed by open3d)"; \
	  apt-get install -y -q libusb-1.0-0 >/dev/null 2>&1 || \
	  { apt-get update -q >/dev/null && apt-get install -y -q libusb-1.0-0 >/dev/null; }; }
	@test -x /usr/bin/chromium || { \
	  echo "installing chromium (needed by the browser tests)"; \
	  apt-get install -y -q chromium >/dev/null 2>&1 || \
	  { apt-get update -q >/dev/null && apt-get install -y -q chromium >/dev/null; }; }

# lint-imports checks the layering contracts in pyproject.toml ([tool.importlinter]).
lint: $(STAMP)
	$(VENV)/bin/ruff check app tests bench
	$(VENV)/bin/ruff format --check app tests bench
	$(VENV)/bin/lint-imports --no-cache

# pytest exits 5 when it collected no tests: that is a failure here, never a pass. The tests run
# in PYTEST_WORKERS processes (pytest-xdist, a test file per process at a time): servers, browsers
# and sleeps leave a core idle that the other file's pipeline uses.
PYTEST_WORKERS ?= 2
test: system-deps $(STAMP) lint
	@$(PY) -m pytest -q -n $(PYTEST_WORKERS) --dist loadfile; rc=$$?; \
	if [ $$rc -eq 5 ]; then echo "pytest collected no tests: failing"; exit 1; fi; exit $$rc

run: system-deps $(STAMP)
	@echo "mmsclean: http://$(HOST):$(PORT)  (health: http://$(HOST):$(PORT)/health)"
	@echo "log in: start with MMSCLEAN_ADMIN_PASSWORD=... set to create the user 'admin' on the"
	@echo "        first start, or add users with: .venv/bin/mmsclean user add NAME --role admin"
	@echo "        (the password is read from stdin); API docs: http://$(HOST):$(PORT)/docs"
	$(VENV)/bin/mmsclean serve --host $(HOST) --port $(PORT)

clean:
	rm -rf $(VENV) var .pytest_cache .ruff_cache
