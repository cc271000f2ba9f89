# Two commands for a new user: `make demo` and `make test`. Both create .venv if it is missing.
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: demo test setup lint docs bench bench-quick clean

$(STAMP): pyproject.toml
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	# torch first, pinned to the CPU build, so no dependency pulls another torch.
	$(BIN)/python -m pip install --quiet torch==2.13.0
	$(BIN)/python -m pip install --quiet -e '.[dev]'
	touch $(STAMP)

setup: $(STAMP)

# The main job: solver comparison on two built-in games, then the end-to-end learning
# pipeline (small RPI set -> train ours and SC -> evaluate with CV), then two closed-loop
# left turns with the game oracle in the loop; a few minutes.
demo: $(STAMP)
	$(BIN)/epo demo --out results/demo
	$(BIN)/epo pipeline --out results/pipeline
	$(BIN)/epo simulate left-turn --planner oracle --tracker mpc --episodes 2 --workers 2 --no-progress --out results/closed_loop
	@echo "closed loop: results/closed_loop/summary.md, figure results/closed_loop/figures/episode-00000.png (animation: episode-00000.gif)"

test: $(STAMP)
	$(BIN)/python -m pytest -q -n 2 --dist loadfile

# The documentation site (mkdocs.yml) into site/; --strict: a broken link or a missing
# docstring of the API reference fails the build (tests/test_docs.py runs the same build).
docs: $(STAMP)
	NO_MKDOCS_2_WARNING=1 $(BIN)/mkdocs build --strict -d site

lint: $(STAMP)
	$(BIN)/ruff check . && $(BIN)/ruff format --check .

# Benchmarks (minutes, not part of `make test`); `make bench-quick` is a smoke run.
bench: $(STAMP)
	$(BIN)/python bench/bench_lm.py
	$(BIN)/python bench/bench_ilq.py
	$(BIN)/python bench/bench_layer.py
	$(BIN)/python bench/bench_rpi.py --games 10 --pipeline-games 60

bench-quick: $(STAMP)
	$(BIN)/python bench/bench_lm.py --quick
	$(BIN)/python bench/bench_ilq.py --quick
	$(BIN)/python bench/bench_layer.py --quick
	$(BIN)/python bench/bench_rpi.py --games 2 --pipeline-games 4

clean:
	rm -rf $(VENV) build *.egg-info .pytest_cache
