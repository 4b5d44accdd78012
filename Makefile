# Every target creates the virtual environment it needs; nothing else is required on a fresh machine.
PY ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: setup run test test-typed test-system test-px4 test-radio lint docs bench soak clean

$(STAMP): pyproject.toml
	test -x $(BIN)/python || $(PY) -m venv $(VENV)
	$(BIN)/python -m pip install -q --upgrade pip
	$(BIN)/python -m pip install -q -e '.[dev]'
	-command -v npm >/dev/null && npm ci --prefix tests/js --no-audit --no-fund --loglevel=error
	touch $(STAMP)

setup: $(STAMP)

# The simulated arena flying, with a live status table; Ctrl-C lands every vehicle and returns.
CONFIG ?= deploy/sim.toml
run: $(STAMP)
	$(BIN)/arena demo $(CONFIG)

# Unit and integration tests, in TEST_JOBS parallel workers (pytest-xdist; most tests wait on sockets and
# processes, so more workers than cores pays): about 2 minutes on a 2-core machine, under 3 with two CPU
# burners beside it.  TEST_JOBS=0 runs them in this process.  The whole-system and real-PX4 tiers run apart.
# Bytecode is written even where the environment says not to: pytest then caches its assert-rewritten test
# modules instead of compiling them again in every worker.
TEST_JOBS ?= 4
test: $(STAMP)
	PYTHONDONTWRITEBYTECODE= $(BIN)/python -m pytest -q -n $(TEST_JOBS) --dist worksteal -m "not system and not px4 and not typed"

# Whole-system tests: examples, fault injection, network namespaces, security, fuzzing, the short soak.
test-system: $(STAMP)
	PYTHONDONTWRITEBYTECODE= $(BIN)/python -m pytest -q --durations=12 -m "system and not typed"

# The typed tier: every command of README.md, docs/, `arena --help` and the systemd units, run as a user
# types it (the real console script, shared options before and after, a config named on the line), and
# what each promises: its ports, its vehicles, its errors, nothing left running when its terminal closes.
# Two workers: unlike the unit tests, most of these run a whole arena each (steady ~0.35 of a core for one
# vehicle, ~6 CPU-seconds to start, more flying or benchmarking); the tier takes ~410 CPU-seconds.  At -n 3
# it averaged 1.1 cores, the 2-core machine was saturated 86 % of the time and the demo tests ran 1.1-2.5x
# slower than at -n 2 (0.6 cores on average), which leaves a core for the work beside it.
TYPED_JOBS ?= 2
test-typed: $(STAMP)
	PYTHONDONTWRITEBYTECODE= $(BIN)/python -m pytest -q --durations=12 -n $(TYPED_JOBS) --dist worksteal -m typed tests/typed

# The real-PX4 tier: PX4 v1.16 SITL (PX4_SITL_DIR, else ../shared/px4-sitl) flown through the arena.
test-px4: $(STAMP)
	$(BIN)/python -m pytest -q --durations=12 -m px4 tests/px4

# PX4 SITL over a slow radio link, with and without the arena's compensation: RADIO_FLIGHTS flights per
# link (direct, slow uncompensated, slow compensated; each ~50 s of PX4; ~25 min), their medians compared.
RADIO_FLIGHTS ?= 10
test-radio: $(STAMP)
	ARENA_RADIO=1 ARENA_RADIO_FLIGHTS=$(RADIO_FLIGHTS) $(BIN)/python -m pytest -q -s -m px4 tests/px4/test_px4_slow_link.py

lint: $(STAMP)
	$(BIN)/ruff check arena_common services tests examples bench tools
	$(BIN)/ruff format --check arena_common services tests examples bench tools
	$(BIN)/mypy
	$(BIN)/python -m tools.wiredoc --check
	$(BIN)/python -m tools.rosdoc --check
	$(BIN)/python -m tools.layers
	$(BIN)/python -m tools.mavlint
	$(BIN)/python -m tools.typed --check

# API documentation generated from the docstrings (pdoc), written to build/docs/ (open index.html).
DOC_MODULES := arena_common arena_common.client \
	$(subst /,.,$(basename $(filter-out %/__init__.py,$(wildcard arena_common/client/*.py arena_common/core/*.py))))
docs: $(STAMP)
	rm -rf build/docs
	$(BIN)/pdoc --docformat restructuredtext -o build/docs $(DOC_MODULES)

bench: $(STAMP)
	$(BIN)/python -m pip install -q -e '.[bench]'
	$(BIN)/python -m bench

soak: $(STAMP)
	ARENA_SOAK=full $(BIN)/python -m pytest -q tests/system/test_soak.py

clean:
	rm -rf $(VENV) .pytest_cache .mypy_cache .ruff_cache build/docs
