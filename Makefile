# The two set-up commands of the README: `make run` and `make test`.
# Each creates .venv when missing and installs what it needs first.
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed-stamp

export MUJOCO_GL ?= egl
export PYOPENGL_PLATFORM ?= egl
export PREFECT_SERVER_ANALYTICS_ENABLED := false
export DO_NOT_TRACK := 1
export PREFECT_HOME ?= $(CURDIR)/.prefect
export PREFECT_LOGGING_LEVEL ?= WARNING
# Python caches each module's bytecode as it first imports it. Our machines set PYTHONDONTWRITEBYTECODE,
# and neither installer below compiles ahead: with it, every process a study or the suite starts would
# compile torch, Prefect and the rest from source again, about twice the CPU of an import
# (benchmarks/results/install.md). Compiling only what is imported, once, is cheaper than compiling
# every installed module at install time.
unexport PYTHONDONTWRITEBYTECODE

# Where torch's CPU build comes from: PyTorch's CPU wheel index, searched beside PyPI for torch alone
# (PyPI's Linux torch is the multi-GB CUDA build). `make install TORCH_CUDA=1` (or `TORCH_INDEX=`)
# takes torch from PyPI alone (CUDA on Linux); TORCH_INDEX=<url> names another index.
TORCH_INDEX ?= https://download.pytorch.org/whl/cpu
ifeq ($(TORCH_CUDA),1)
TORCH_INDEX :=
endif

.PHONY: install run test lint bench clean

$(STAMP): pyproject.toml
	scripts/install_system_deps.sh
	test -x $(PY) || python3 -m venv $(VENV)
	# uv installs the project: it fetches and unpacks in parallel (benchmarks/results/install.md:
	# several times faster than pip for these ~220 packages); pip only installs uv and torch.
	$(PY) -m pip install -q 'uv>=0.9,<0.14'
	# torch first, alone (--no-deps) from TORCH_INDEX as an *extra* index: pip picks 2.13.0+cpu there
	# over PyPI's 2.13.0, and where that index cannot be reached pip falls back to the other indexes
	# (this machine's own wheels among them) after a few retries for this one package. uv then keeps it
	# (it satisfies the project's range) and adds its dependencies with the project's.
	$(PY) -m pip install -q --no-deps --no-compile $(if $(TORCH_INDEX),--extra-index-url $(TORCH_INDEX)) torch==2.13.0
	$(PY) -m uv pip install -q --python $(PY) -e '.[dev]'
	touch $(STAMP)

install: $(STAMP)

run: install
	$(VENV)/bin/capvector study --preset study-control-hard-extraction-3seeds

test: install
	$(PY) -m ruff check .
	# two workers for two cores, a test file each (three measured 1.12x slower: the suite is CPU-bound,
	# docs/guide/reproducing.md); files in collection order, the longest first (tests/conftest.py LONGEST_FIRST)
	$(PY) -m pytest -q -n 2 --dist loadfile --no-loadscope-reorder

lint: install
	$(PY) -m ruff check .

clean:
	rm -rf $(VENV) .prefect .pytest_cache
