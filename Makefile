# The two commands of the README:
#   make demo  — install, then run the main job on the embedded synthetic default
#   make test  — install, then run the test suite (what .ci/run calls)
PYTHON ?= python3
PIP ?= $(PYTHON) -m pip
WORKSPACE ?= work
JOBS ?= 2

.PHONY: install demo test bench clean

# torch is pinned to the CPU wheel first so that nothing pulls in CUDA packages.
install:
	$(PIP) install -q torch==2.13.0
	$(PIP) install -q -e '.[test,landmarks,tensorboard]'

demo: install
	reflectmm run recipes/synthetic.toml --workspace $(WORKSPACE) --jobs $(JOBS)

test: install
	$(PYTHON) -m pytest -q -p no:cacheprovider tests

bench: install
	$(PYTHON) benchmarks/run_all.py

clean:
	rm -rf $(WORKSPACE) build *.egg-info
