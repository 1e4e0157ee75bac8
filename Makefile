PY ?= python3.11
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: install train test flight bench results ablations clean

$(BIN)/python:
	$(PY) -m venv $(VENV) || python3 -m venv $(VENV)

$(STAMP): $(BIN)/python pyproject.toml
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -e ".[test,flight,marl]"
	touch $(STAMP)

install: $(STAMP)

train: $(STAMP)
	$(BIN)/python train.py --config configs/default.yaml

test: $(STAMP)
	$(BIN)/python -m pytest -q -x -n 2 --dist loadfile --no-loadscope-reorder

# One mission of simulated quadrotors flown by the shipped policy (about a minute):
# runs/flight/result.json, paths.png (3D) and flight.gif.
flight: $(STAMP)
	$(BIN)/python -m jaxmripp.flight --export pretrained/default --out runs/flight

bench: $(STAMP)
	for b in sensing gp env runtime safety; do $(BIN)/python benchmarks/$$b.py || exit 1; done
	$(BIN)/python benchmarks/train.py --envs 256
	$(BIN)/python benchmarks/train.py --envs 256 --no-update --config configs/train_paper.yaml

# The tables and plots of docs/results/ from the shipped policies (about 20 minutes each on
# a 2-core CPU); the per-episode files are left out of the repository.
results: $(STAMP)
	for p in default paper; do \
	  mkdir -p docs/results/$$p && $(BIN)/python benchmarks/quality.py --preset $$p --out docs/results/$$p > docs/results/$$p/quality.jsonl || exit 1; \
	  rm -f docs/results/$$p/runs.csv docs/results/$$p/runs.json; done

# The ablation tables (hours on a 2-core CPU; stop and rerun to continue).
ablations: $(STAMP)
	$(BIN)/python benchmarks/ablation.py --preset default --out docs/results/ablation_default.md
	$(BIN)/python benchmarks/ablation.py --preset paper --out docs/results/ablation_paper.md

clean:
	rm -rf $(VENV) runs
