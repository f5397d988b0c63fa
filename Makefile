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

# Three pytest workers on the 2-core machines we test on, each taking whole modules in
# collection order so that module fixtures are built once: with two (one per core) the
# cores idled about a tenth of the time (single-threaded imports and tracing, waits on files,
# the last module's tail). Session 46, slow Xeon, two pairs an hour apart: two workers 892
# and 963 s at 191 and 188 % CPU, three 804 and 917 s at 197 and 192 %.
# TEST_WORKERS=0 runs the suite in this process. The suite's wall time is printed at the end.
TEST_WORKERS ?= 3

test: install
	@start=$$(date +%s); \
	$(BIN)/python -m pytest -q -n $(TEST_WORKERS) --dist loadscope --no-loadscope-reorder \
	    --durations=15; rc=$$?; \
	echo "make test: $$(( $$(date +%s) - start )) s wall"; exit $$rc

# The fuzzed input surface with many more damaged inputs per reader than `make test` runs
# (tests/test_fuzz.py; each run draws new ones, and a failure prints how to reproduce it).
fuzz: install
	HYPOTHESIS_PROFILE=fuzz $(BIN)/python -m pytest -q tests/test_fuzz.py

lint: install
	$(BIN)/ruff check scenegen_jax tests experiments

demo: install
	bash experiments/demo.sh $(DATA) $(OUT) $(DEMO_CONFIG)

clean:
	rm -rf $(OUT) .pytest_cache

# `make bench ISA=AVX2` caps both sides to AVX2 (bench/results_avx2.json).
bench: install
	$(BIN)/python bench/run.py --workdir runs/cpu_map --data runs/cache_cpu_val $(if $(ISA),--isa $(ISA))
