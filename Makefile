# s2camp-ns developer commands. `make demo` and `make test` are the two a newcomer needs.
# Everything runs inside $(VENV); it is created and installed on first use and reused afterwards
# (the editable installs are redone only when a pyproject.toml is newer than the stamp file).

VENV ?= .venv
# Prefer python3.11: the pinned torch 2.14.1 / torchvision 0.29.1 wheels are cached locally for 3.11.
PYTHON ?= $(shell command -v python3.11 2>/dev/null || command -v python3 2>/dev/null)
BIN := $(VENV)/bin
STAMP := $(VENV)/.s2camp-installed
# Installed first, on their own, so resolving the package cannot pull in a different torch.
TORCH_PINS := torch==2.14.1 torchvision==0.29.1

.PHONY: help venv demo test lint bench gpu-check gpu-bundle mutation clean

help:
	@echo "make demo   generate a synthetic scene and run the S2CamP demo (creates $(VENV) on first use)"
	@echo "make test   ruff + the whole pytest suite, end-to-end tests included"
	@echo "make lint   ruff only"
	@echo "make bench  all benchmarks (s2camp-bench all) into outputs/benchmarks (BENCH_DIR=docs/benchmarks rewrites the committed tables)"
	@echo "make gpu-check  on a CUDA machine: time per step at the defaults, the cuda tests, then the rest (docs/GPU-CHECK.md)"
	@echo "make gpu-bundle the offline wheels a lent GPU machine needs, into .whl/ (docs/GPU-CHECK.md)"
	@echo "make mutation  mutation testing of the core and the camera optimizer (mutmut, about 40 min on one CPU)"
	@echo "make venv   create/refresh $(VENV) (VENV=path to use another one, PYTHON=python3.x to pick the interpreter)"
	@echo "make clean  remove caches, build outputs and generated scenes (keeps $(VENV) and ns-train outputs/)"

venv: $(STAMP)

$(BIN)/python:
	@test -n "$(PYTHON)" || { echo "error: no python3 found; install Python >= 3.10 or pass PYTHON=..."; exit 1; }
	@$(PYTHON) -c 'import sys; sys.exit(0 if sys.version_info >= (3, 10) else 1)' || \
		{ echo "error: $(PYTHON) is older than Python 3.10; pass PYTHON=python3.11"; exit 1; }
	@echo ">>> creating virtual environment $(VENV) with $$($(PYTHON) --version) ($(PYTHON))"
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --upgrade pip setuptools wheel

$(STAMP): pyproject.toml benchmarks/pyproject.toml | $(BIN)/python
	@echo ">>> installing the pinned torch pair first: $(TORCH_PINS)"
	$(BIN)/python -m pip install $(TORCH_PINS)
	@echo ">>> installing s2camp-ns (editable) with test extras, and the benchmarks (s2camp-bench, editable)"
	$(BIN)/python -m pip install -e '.[test]' -e benchmarks
	@touch $(STAMP)
	@echo ">>> $(VENV) is ready"

demo: venv
	@echo ">>> running the demo"
	$(BIN)/python -m s2camp_bench.demo

lint: venv
	@echo ">>> ruff check ."
	$(BIN)/ruff check .

test: lint
	@echo ">>> pytest (whole suite, slow end-to-end tests included)"
	@$(BIN)/python -m pytest -q; rc=$$?; \
		if [ $$rc -eq 5 ]; then echo "error: pytest collected no tests"; fi; \
		exit $$rc

# Reports and plots go to $(BENCH_DIR); `make bench BENCH_DIR=docs/benchmarks` rewrites the committed ones.
BENCH_DIR ?= outputs/benchmarks

bench: venv
	@echo ">>> s2camp-bench all --output-dir $(BENCH_DIR)"
	$(BIN)/s2camp-bench all --output-dir $(BENCH_DIR)

# The GPU check (docs/GPU-CHECK.md): refuses to run without CUDA; report in outputs/gpu-check/gpu-check.md.
# Options go through GPU_CHECK_ARGS, e.g. make gpu-check GPU_CHECK_ARGS="--deadline 600 --stages timing".
gpu-check: venv
	@echo ">>> python -m s2camp_bench.gpu_check $(GPU_CHECK_ARGS)"
	$(BIN)/python -m s2camp_bench.gpu_check $(GPU_CHECK_ARGS)

# The wheels a lent GPU machine without a package registry needs (Python 3.12; s2camp-ns and s2camp-bench among
# them), into .whl/ (ignored by git); needs the registry and a Python 3.12 (GPU_BUNDLE_ARGS="--python312 PATH", or
# PYENV_VERSION=3.12.1 with pyenv).
gpu-bundle: venv
	@echo ">>> python -m s2camp_bench.gpu_check.bundle $(GPU_BUNDLE_ARGS)"
	$(BIN)/python -m s2camp_bench.gpu_check.bundle $(GPU_BUNDLE_ARGS)

# Mutation testing (docs/mutation-testing.md): mutmut (the "mutation" extra) mutates the modules listed under
# [tool.mutmut] in pyproject.toml and runs their unit tests against each mutant, one worker at a time. The run
# starts from an empty mutants/: mutmut 3.8.1's incremental mode maps new functions to tests only for new test
# names, so a reused mutants/ can report "no tests" for code that is tested. The report counts the mutants judged
# equivalent in docs/mutation-equivalents.toml and lists every other survivor with its diff.
MUTATION_STAMP := $(VENV)/.s2camp-mutation-installed

$(MUTATION_STAMP): pyproject.toml | $(STAMP)
	$(BIN)/python -m pip install -e '.[test,mutation]'
	@touch $(MUTATION_STAMP)

mutation: $(MUTATION_STAMP)
	rm -rf mutants
	OMP_NUM_THREADS=1 OMP_WAIT_POLICY=PASSIVE $(BIN)/mutmut run --max-children 1
	$(BIN)/python scripts/mutation_report.py

clean:
	@echo ">>> removing caches, build outputs and generated scenes"
	rm -rf build dist *.egg-info .pytest_cache .ruff_cache scenes demo_scene
	find . -path ./$(VENV) -prune -o -name __pycache__ -type d -exec rm -rf {} +
