# `make demo` and `make test` set everything up (idempotently) and run. See README.md.
PY      := .venv/bin/python
REQHASH := $(shell cat requirements.txt pyproject.toml scripts/install-system.sh | sha1sum | cut -c1-12)
STAMP   := .venv/.installed-$(REQHASH)
export PYOPENGL_PLATFORM ?= egl

.PHONY: setup demo test test-slow test-all test-gpu bench clean
setup: $(STAMP)

$(STAMP): requirements.txt pyproject.toml scripts/install-system.sh
	bash scripts/install-system.sh
	test -x $(PY) || python3 -m venv .venv
	$(PY) -m pip install -q --disable-pip-version-check -r requirements.txt
	$(PY) -m pip install -q --disable-pip-version-check --no-deps --no-build-isolation -e .
	rm -f .venv/.installed-*
	touch $@

# the VR app: a headset if one is there, else a desktop window if there is a display, else a short headless session
demo: setup
	.venv/bin/sonicverse vr --out out/demo

# two worker processes, a test file each (pytest-xdist): much of the suite waits on JACK's real-time clock and on
# spawned jobs, so two files at a time take about half the time on two cores (README, Tests)
test: setup
	QT_QPA_PLATFORM=offscreen $(PY) -m pytest -q -n 2 --dist loadfile -m "not slow and not gpu"

test-slow: setup
	QT_QPA_PLATFORM=offscreen $(PY) -m pytest -q -m slow

test-all: setup
	QT_QPA_PLATFORM=offscreen $(PY) -m pytest -q -m "not gpu"

# the learned agents on CUDA: fails where torch sees no CUDA device
test-gpu: setup
	QT_QPA_PLATFORM=offscreen $(PY) -m pytest -q -m gpu

bench: setup
	.venv/bin/sonicverse bench rays
	.venv/bin/sonicverse bench audio --sources 64
	.venv/bin/sonicverse bench audio --sources 256
	.venv/bin/sonicverse bench accuracy --plot docs/accuracy.png
	.venv/bin/sonicverse bench vr

clean:
	rm -rf out .pytest_cache
