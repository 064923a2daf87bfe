# Two commands do everything: `make demo` and `make test` (each creates .venv if missing).
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin

.PHONY: install demo test bench clean

$(BIN)/d2a: pyproject.toml constraints.txt
	$(PYTHON) -m venv $(VENV)
	$(BIN)/pip install --quiet --upgrade pip
	$(BIN)/pip install --quiet -c constraints.txt -e ".[test,ray]"
	touch $(BIN)/d2a

install: $(BIN)/d2a

demo: install
	$(BIN)/d2a demo

test: install
	$(BIN)/python -m pytest -q

bench: install
	$(BIN)/d2a bench envs

clean:
	rm -rf $(VENV) *.egg-info
