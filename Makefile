PY ?= python3.11
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: install train scale test demo flight bench results ablations docs check-docs clean

$(BIN)/python:
	$(PY) -m venv $(VENV) || python3 -m venv $(VENV)

# --no-compile: pip byte-compiles every file it installs (about 20 s, half the
# installation); Python compiles the modules a command imports when it first imports them.
$(STAMP): $(BIN)/python pyproject.toml
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet --no-compile -e ".[test,flight,marl]"
	touch $(STAMP)

install: $(STAMP)

train: $(STAMP)
	$(BIN)/python train.py --config recipe_quick

# The curriculum of pretrained/scale, each stage into a fixed folder and starting from the
# folder before (about 70 minutes on a 2-core CPU; a stage whose folder exists and is not
# empty stops it): 3 robots by PPO alone, then 8 (recipe_scale_n8), then 16 in the 3x
# world (recipe_scale).
SCALE_N3 := ppo.teacher_coef=0 ppo.teacher_updates=0 train.updates=200 train.updates_per_chunk=10

scale: $(STAMP)
	$(BIN)/jaxmripp train --config recipe_quick --run-dir runs/scale_n3 --no-eval $(SCALE_N3)
	$(BIN)/jaxmripp train --config recipe_scale_n8 --run-dir runs/scale_n8 --no-eval \
	  train.init_from=runs/scale_n3
	$(BIN)/jaxmripp train --config recipe_scale --run-dir runs/scale train.init_from=runs/scale_n8
	@echo "ship it: $(BIN)/python -m jaxmripp.ship runs/scale pretrained/scale"

# PYTHONDONTWRITEBYTECODE emptied: the suite's first imports write the compiled modules
# that its workers and the commands it starts then read (where the caller's environment
# would otherwise keep every process compiling them again).
test: $(STAMP)
	PYTHONDONTWRITEBYTECODE= $(BIN)/python -m pytest -q -x -n 2 --dist loadfile --no-loadscope-reorder

# The shipped policy against nbv_team and random on 5 held-out worlds x 2 trials, then flown
# by the NumPy runtime (1-2 minutes on 2 cores): tables on the terminal, pictures in
# runs/demo/eval. Compiling dominates so short an evaluation, so XLA's CPU backend skips
# LLVM optimisation and uses its classic fusion emitters (the test suite's settings,
# tests/conftest.py): about 3x faster compiles, the same figures; left out where the
# installed jaxlib does not know the flags.
DEMO_XLA := --xla_backend_optimization_level=0 --xla_cpu_use_fusion_emitters=false
DEMO_OUT := runs/demo/eval

demo: $(STAMP)
	@flags="$(DEMO_XLA)"; \
	XLA_FLAGS="$$XLA_FLAGS $$flags" $(BIN)/python -c "import jax.numpy as j; j.zeros(1).block_until_ready()" \
	  >/dev/null 2>&1 || flags=""; \
	XLA_FLAGS="$$XLA_FLAGS $$flags" $(BIN)/jaxmripp eval --config protocol_table1 \
	  --policy policy=pretrained/default_fast --out $(DEMO_OUT) --no-timing \
	  "eval.planners=[policy,nbv_team,random]" "eval.radio_ranges=[.inf]" eval.worlds=5 \
	  sensor.gain_facade=nearby \
	  eval.trials=2 "eval.pairs=[policy:nbv_team,policy:random]" && \
	echo "the same policy flown by the NumPy runtime (jaxmripp demo), world seed 0:" && \
	$(BIN)/jaxmripp demo --export pretrained/default_fast --quiet && \
	echo "pictures: $(DEMO_OUT)/ (episode_*.png and .gif: one episode per planner;" \
	  "discovered_vs_budget_0.png; missed_windows_0.png; results.md)"

# One mission of simulated quadrotors flown by the shipped policy (about a minute):
# runs/flight/result.json, paths.png (3D) and flight.gif.
flight: $(STAMP)
	$(BIN)/python -m jaxmripp.flight --export pretrained/default --out runs/flight

bench: $(STAMP)
	for b in sensing gp env runtime safety; do $(BIN)/python benchmarks/$$b.py || exit 1; done
	$(BIN)/python benchmarks/train.py --envs 256
	$(BIN)/python benchmarks/train.py --envs 256 --no-update --config benchmarks/train_paper.yaml

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

# The figures and tables of README.md and docs/ from the result files (docs/render.py);
# check-docs changes nothing and fails where a document differs from its files.
docs:
	$(PY) docs/render.py

check-docs:
	$(PY) docs/render.py --check

clean:
	rm -rf $(VENV) runs
