# torchheat — set-up, demo and tests. `make demo` and `make test` do all set-up on a fresh machine.
PY ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed
OUT ?= out

.PHONY: demo test lint bench clean

$(STAMP): pyproject.toml
	test -x $(BIN)/python || $(PY) -m venv $(VENV)
	$(BIN)/python -m pip install -q --upgrade pip
	@# Torch: never pull a multi-GB CUDA build onto a machine without a GPU.
	@# 1) a local CPU wheel (offline), 2) PyTorch's CPU index when no GPU, 3) the default build.
	$(BIN)/python -c "import torch" 2>/dev/null \
	  || $(BIN)/python -m pip install -q --no-index torch==2.13.0 2>/dev/null \
	  || { command -v nvidia-smi >/dev/null 2>&1 \
	       && $(BIN)/python -m pip install -q torch \
	       || $(BIN)/python -m pip install -q torch --index-url https://download.pytorch.org/whl/cpu; }
	$(BIN)/python -m pip install -q -e ".[dev]"
	touch $(STAMP)

demo: $(STAMP)
	$(BIN)/torchheat demo --out $(OUT)

test: $(STAMP)
	$(BIN)/python -m pytest -q -ra

lint: $(STAMP)
	$(BIN)/ruff check torchheat scripts tests

bench: $(STAMP)
	$(BIN)/python scripts/bench.py heat

clean:
	rm -rf $(VENV) $(OUT) .pytest_cache .ruff_cache
