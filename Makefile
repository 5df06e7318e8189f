# hydrabench: `make demo` runs the main job on the embedded defaults, `make test` runs the checks.
# Both build .venv from requirements.lock (+ constraints.txt, which pins the local torch) when it
# is missing or older than the lock.
PYTHON ?= python3
VENV   := .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.hydrabench-installed
DEMO   ?= demo
# pytest-xdist workers for `make test`: one per core this shell may use (tests/conftest.py pins each
# worker to its share of the cores, so torch and subprocesses do not fight over them)
TEST_WORKERS ?= $(shell nproc 2>/dev/null || echo 1)

export PYOPENGL_PLATFORM := egl
export SDL_VIDEODRIVER := offscreen
# Python's bytecode caches (__pycache__/, git-ignored) are written even where the environment turns them
# off (PYTHONDONTWRITEBYTECODE=1 in some images): without them each pytest worker compiles and
# assertion-rewrites the ~200 test modules again (16 s of collection instead of 10 s on a 2-core EPYC)
# and every command a test or the demo starts compiles the project's modules again.
unexport PYTHONDONTWRITEBYTECODE

.PHONY: demo demo-scenes demo-data demo-look demo-test demo-compare test venv lint lock clean-venv

venv: $(STAMP)

$(STAMP): requirements.lock requirements-nodeps.txt constraints.txt pyproject.toml
	@test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet -r requirements.lock -c constraints.txt
	$(BIN)/python -m pip install --quiet --no-deps -r requirements-nodeps.txt
	$(BIN)/python -m pip install --quiet --no-deps --no-build-isolation -e .
	@touch $(STAMP)

# a `device_kit.py slim` left in place (docs/gpu.md) is undone first: demo and tests need those files.
# The demo's two chains (the small dataset and its pictures; the test set and its comparison) and the
# scenes run side by side, two recipes at a time (-j2): each step's single-threaded stretches (start-up,
# plotting, the serial parts of inference) fill the other core. The comparison is printed at the end.
demo: $(STAMP)
	@$(BIN)/python scripts/device_kit.py restore
	@mkdir -p $(DEMO)
	@$(MAKE) --no-print-directory -j2 DEMO='$(DEMO)' demo-compare demo-look demo-scenes
	@cat $(DEMO)/compare.txt
	@echo "demo: scenes in $(DEMO)/scenes, dataset in $(DEMO)/data, frames and gallery in $(DEMO)/," \
	  "selective against fixed fusion in $(DEMO)/compare.txt and $(DEMO)/compare.png" >&2

demo-scenes:
	$(BIN)/hydrabench scenes --context all --frames 20 --seed 0 --plot $(DEMO)/scenes

demo-data:
	$(BIN)/hydrabench generate --out $(DEMO)/data --frames-per-context 10 --seed 0 --workers 2 --twins
	$(BIN)/hydrabench verify $(DEMO)/data

demo-look: demo-data
	$(BIN)/hydrabench show $(DEMO)/data --context all --index 0 --out '$(DEMO)/frame_{context}.png'
	$(BIN)/hydrabench gallery $(DEMO)/data --context city --out $(DEMO)/gallery.png

demo-test:
	$(BIN)/hydrabench generate --out $(DEMO)/test --frames-per-context 24 --sequence-length 3 --seed 1 --workers 2

demo-compare: demo-test
	$(BIN)/hydrabench compare cpu-frontier $(DEMO)/test --plot $(DEMO)/compare.png > $(DEMO)/compare.txt

lint: $(STAMP)
	$(BIN)/ruff check .

test: $(STAMP)
	@$(BIN)/python scripts/device_kit.py restore
	$(BIN)/ruff check .
	$(BIN)/python -m pytest -n $(TEST_WORKERS) --dist loadfile --no-loadscope-reorder

# Regenerate the lock from requirements.txt in a scratch venv (needs the registries).
lock:
	rm -rf /tmp/hydrabench-lock && $(PYTHON) -m venv /tmp/hydrabench-lock
	/tmp/hydrabench-lock/bin/pip install --quiet -r requirements.txt -c constraints.txt
	/tmp/hydrabench-lock/bin/pip freeze | grep -v '^-e' > requirements.lock  # requirements-nodeps.txt stays out

clean-venv:
	rm -rf $(VENV)
