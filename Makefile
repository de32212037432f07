# hexjax: `make demo` sets everything up and runs the main job on a small CPU default; `make test` runs the tests.
# Python 3.12 (jax 0.11 needs it): the first of these that runs, pyenv's install included when it is not the
# selected version; `make PY=/path/to/python3.12` chooses another
PY_OK := import sys; sys.exit(sys.version_info[:2] != (3, 12))
ifndef PY
PY := $(firstword $(foreach p,python3.12 $(wildcard $(or $(PYENV_ROOT),$(HOME)/.pyenv)/versions/3.12*/bin/python3.12) python3,\
        $(shell $(p) -c '$(PY_OK)' >/dev/null 2>&1 && echo $(p))))
endif
VENV := .venv
BIN := $(VENV)/bin

.PHONY: setup demo test test-core test-grad bench warp clean

$(BIN)/hexjax: pyproject.toml constraints.txt
	@test -n "$(PY)" || { echo "hexjax needs Python 3.12 (jax 0.11): none found as python3.12, in ~/.pyenv or as python3; run make PY=/path/to/python3.12" >&2; exit 1; }
	$(BIN)/python -c '$(PY_OK)' 2>/dev/null || { rm -rf $(VENV); $(PY) -m venv $(VENV); }
	@echo "installing hexjax and what it runs on (jax, mujoco, mujoco-mjx, flax, optax; about a minute) into $(VENV)"
	$(BIN)/python -m pip install -q --upgrade pip
	$(BIN)/python -m pip install -q -c constraints.txt -e .
	touch $(BIN)/hexjax

# what only the tests need (pytest, scipy, brax, warp-lang: about 400 MB more), installed by `make test` alone
$(VENV)/.test-extras: $(BIN)/hexjax
	@echo "installing the test extras (pytest, hypothesis, scipy, brax, warp-lang; a minute or two)"
	$(BIN)/python -m pip install -q -c constraints.txt -e '.[test]'
	touch $@

setup: $(BIN)/hexjax

demo: setup
	$(BIN)/hexjax evaluate --gait tripod --distance 1.0 --batch 8 --json out/evaluate_tripod.json --png out/evaluate_tripod.png

# two workers (one per core of the reference machine), the costliest tests (`@pytest.mark.cost`) handed out first and one at a time
# (tests/conftest.py's scheduler: xdist's default hands each worker a block of consecutive tests, which gave one
# worker every slow test, 27 min against 19; a test class goes to one worker whole, so a fixture its tests share is built once);
# the slowest 15 are listed at the end;
# HEXJAX_REQUIRE_WARP: the test extra installs warp-lang, so its absence fails instead of skipping;
# PYTHONDONTWRITEBYTECODE emptied: where the shell sets it, each test process (the two workers and the CLI
# processes some tests start) compiled hexjax's sources and rewrote the test modules' asserts afresh, 3.3 s
# of collection each (10.1 s against 6.8 s)
PYTEST := PYTHONDONTWRITEBYTECODE= HEXJAX_REQUIRE_WARP=1 $(BIN)/python -m pytest -q -n 2 --durations=15
test: $(VENV)/.test-extras
	$(PYTEST) tests

# the same suite in two halves that together run every test once: the four files whose gradient checks
# hold most of a cold run's compile, and the rest; on the faster 2-core VM (AVX-512) each half alone fits
# 12 minutes from an empty cache, the whole suite does not (docs/testing.md), so two CI jobs could run one each
GRAD_TESTS := tests/test_tune.py tests/test_forward_mode.py tests/test_implicit.py tests/test_windows.py
test-core: $(VENV)/.test-extras
	$(PYTEST) $(addprefix --ignore=,$(GRAD_TESTS)) tests

test-grad: $(VENV)/.test-extras
	$(PYTEST) $(GRAD_TESTS)

bench: setup
	$(BIN)/hexjax bench --json out/bench_cpu.json

# MuJoCo Warp, the certified GPU engine (warp-lang, about 390 MB): a GPU host's evaluations pick it once installed
warp: setup
	$(BIN)/python -m pip install -q -c constraints.txt -e '.[warp]'

clean:
	rm -rf $(VENV) out
