# The two commands the README names: `make demo` (main job on the built-in simulated survey)
# and `make test`. Both create .venv when missing and install everything the project needs.
PY      := .venv/bin/python
STAMP   := .venv/.installed
DEMO_OUT ?= demo_out

.PHONY: demo test test-fast lint bench clean

$(STAMP): pyproject.toml
	@test -x $(PY) || python3 -m venv .venv
	@# torch first, pinned: an unpinned torch pulls gigabytes of CUDA packages.
	$(PY) -m pip install --quiet --no-cache-dir torch==2.13.0
	$(PY) -m pip install --quiet --no-cache-dir -e '.[dev]'
	@# open3d needs Debian's libusb-1.0-0; install it when open3d cannot import.
	@$(PY) -c "import open3d" 2>/dev/null || { \
		echo "open3d cannot import: installing Debian's libusb-1.0-0"; \
		apt-get update -qq && apt-get install -y -qq libusb-1.0-0 >/dev/null; }
	@$(PY) -c "import open3d, pycolmap, torch, cv2" || { echo "set-up failed: see the errors above"; exit 1; }
	@touch $(STAMP)

demo: $(STAMP)
	MPLCONFIGDIR=$${MPLCONFIGDIR:-$(CURDIR)/.mplconfig} .venv/bin/watergan demo --out $(DEMO_OUT)

# Tests run on every core (pytest-xdist), a file's tests on one worker so that its shared surveys are made once;
# each worker computes on one thread (tests/conftest.py).
test: $(STAMP)
	MPLCONFIGDIR=$${MPLCONFIGDIR:-$(CURDIR)/.mplconfig} $(PY) -m pytest -q -n auto --dist loadfile

test-fast: $(STAMP)
	MPLCONFIGDIR=$${MPLCONFIGDIR:-$(CURDIR)/.mplconfig} $(PY) -m pytest -q -n auto --dist loadfile -m "not slow"

lint: $(STAMP)
	.venv/bin/ruff check .

bench: $(STAMP)
	$(PY) benchmarks/bench_simulate.py

clean:
	rm -rf .venv $(DEMO_OUT) .pytest_cache .mplconfig
