PY ?= python3.11
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: install train test bench clean

$(BIN)/python:
	$(PY) -m venv $(VENV) || python3 -m venv $(VENV)

$(STAMP): $(BIN)/python pyproject.toml
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -e ".[test]"
	touch $(STAMP)

install: $(STAMP)

train: $(STAMP)
	$(BIN)/python train.py --config configs/default.yaml

test: $(STAMP)
	$(BIN)/python -m pytest -q -x -n 2 --dist loadfile

bench: $(STAMP)
	for b in sensing gp env runtime safety; do $(BIN)/python benchmarks/$$b.py || exit 1; done
	$(BIN)/python benchmarks/train.py --envs 256
	$(BIN)/python benchmarks/train.py --envs 256 --no-update --config configs/train_paper.yaml

clean:
	rm -rf $(VENV) runs
