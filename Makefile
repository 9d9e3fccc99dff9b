# The two commands of the README:
#   make demo  — install, then run the main job on the embedded synthetic default
#   make test  — install, then run the test suite (what .ci/run calls)
PYTHON ?= python3
PIP ?= $(PYTHON) -m pip
WORKSPACE ?= work
JOBS ?= 2
SUDO ?= $(shell [ "$$(id -u)" = 0 ] || echo sudo)

.PHONY: install browser demo test bench clean

# torch is pinned to the CPU wheel first so that nothing pulls in CUDA packages.
install:
	$(PIP) install -q torch==2.13.0
	$(PIP) install -q -e '.[test,landmarks,tensorboard]'

demo: install
	reflectmm run recipes/synthetic.toml --workspace $(WORKSPACE) --jobs $(JOBS)

# The viewer's tests run its page in headless Chromium (Debian's package), installed here where it is missing.
browser:
	@command -v chromium >/dev/null 2>&1 || command -v chromium-browser >/dev/null 2>&1 || \
	  $(SUDO) apt-get install -y -q chromium >/dev/null 2>&1 || \
	  { $(SUDO) apt-get update -q && $(SUDO) apt-get install -y -q chromium; }

test: install browser
	$(PYTHON) -m pytest -q -p no:cacheprovider tests

bench: install
	$(PYTHON) benchmarks/run_all.py

clean:
	rm -rf $(WORKSPACE) build *.egg-info
