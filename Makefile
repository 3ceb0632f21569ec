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
	bash scripts/install_torch.sh $(BIN)/python
	$(BIN)/python -m pip install -q -e ".[dev]"
	touch $(STAMP)

demo: $(STAMP)
	$(BIN)/torchheat demo --out $(OUT)

# the suite on two processes (pytest-xdist), each test file whole in one of them so that its
# module fixtures are built once (what it saves: RESULTS.md, thirty-ninth session)
test: $(STAMP)
	$(BIN)/python -m pytest -q -ra -n 2 --dist loadfile

lint: $(STAMP)
	$(BIN)/ruff check torchheat scripts tests
	$(BIN)/mypy

bench: $(STAMP)
	$(BIN)/python scripts/bench.py heat

clean:
	rm -rf $(VENV) $(OUT) .pytest_cache .ruff_cache
