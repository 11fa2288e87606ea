# Both targets create the virtual environment on first use.
PY ?= python3
VENV := .venv
BIN := $(VENV)/bin

.PHONY: serve test lint bench-quality bench-speed

$(BIN)/pwlreg: pyproject.toml
	$(PY) -m venv $(VENV)
	$(BIN)/pip install -q --upgrade pip
	$(BIN)/pip install -q -e '.[dev]'
	touch $@

serve: $(BIN)/pwlreg
	$(BIN)/pwlreg serve

test: $(BIN)/pwlreg
	$(BIN)/python -m pytest -q

lint: $(BIN)/pwlreg
	$(BIN)/ruff check .

bench-quality: $(BIN)/pwlreg
	$(BIN)/python -m bench.quality

bench-speed: $(BIN)/pwlreg
	$(BIN)/python -m bench.speed
