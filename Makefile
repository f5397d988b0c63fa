# scenegen_jax: `make demo` and `make test` are the two commands; both install first.
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
DATA ?= ../shared/data/av2_sensor_mini
OUT ?= out/demo
DEMO_CONFIG ?= tiny

.PHONY: install test fuzz demo bench lint clean

install: $(VENV)/.installed

$(VENV)/.installed: pyproject.toml
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/pip install -q --upgrade pip
	$(BIN)/pip install -q -e '.[test]'
	touch $@

# Three pytest workers on two cores, each taking whole modules in collection order so that
# module fixtures are built once: the third keeps both cores busy while one worker waits on
# single-threaded imports, tracing or files. TEST_WORKERS=0 runs the suite in this process.
TEST_WORKERS ?= 3

test: install
	@start=$$(date +%s); \
	$(BIN)/python -m pytest -q -n $(TEST_WORKERS) --dist loadscope --no-loadscope-reorder \
	    --durations=15; rc=$$?; \
	echo "make test: $$(( $$(date +%s) - start )) s wall"; exit $$rc

# The fuzzed input surface with many more damaged inputs per reader than `make test` runs
# (tests/test_fuzz.py, and odd names and links in tests/test_fuzz_paths.py; each run draws
# new ones, and a failure prints how to reproduce it),
# and 20 stops at random moments of the commands (tests/test_stress.py, by seed).
fuzz: install
	HYPOTHESIS_PROFILE=fuzz $(BIN)/python -m pytest -q tests/test_fuzz.py tests/test_fuzz_paths.py
	SCENEGEN_STRESS_SEEDS=20 $(BIN)/python -m pytest -q tests/test_stress.py

lint: install
	$(BIN)/ruff check scenegen_jax tests experiments bench

demo: install
	bash experiments/demo.sh $(DATA) $(OUT) $(DEMO_CONFIG)

clean:
	rm -rf $(OUT) .pytest_cache

# `make bench ISA=AVX2` caps both sides to AVX2 (bench/results_avx2.json). The `cpu` model's
# sampling on real maps is timed only where runs/cpu_map holds a trained `cpu` workdir and
# runs/cache_cpu_val its val cache; otherwise its row says it was skipped (bench/README.md).
bench: install
	$(BIN)/python bench/run.py --workdir runs/cpu_map --data runs/cache_cpu_val $(if $(ISA),--isa $(ISA))
