# The two set-up commands: `make demo` and `make test` (each creates .venv and installs first).
VENV ?= .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed
PYTHON ?= python3

.PHONY: demo test test-slow lint format install clean bench-env pretrained docs

$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	$(PY) -m pip install -q torch==2.13.0
	$(PY) -m pip install -q -e '.[test]'
	touch $(STAMP)

install: $(STAMP)

demo: $(STAMP)
	$(PY) -m adjust.apps.demo

# the default suite on every core (pytest-xdist; a test file stays on one worker, so a module's
# fixtures are built once)
test: $(STAMP)
	$(PY) -m pytest -q -m "not slow" -n auto --dist loadfile

test-slow: $(STAMP)
	$(PY) -m pytest -q -m slow

lint: $(STAMP)
	$(VENV)/bin/ruff check . && $(VENV)/bin/ruff format --check .
	$(PY) -m pytest -q tests/test_layering.py  # the layering contract

# Rebuild the shipped default net (deformnet/pretrained/real_mouse_parts.pt: a part-agnostic net
# trained on filmed and tracked real motion, adjust.pretrain_real; ~6 min on 2 cores: tracking ~2,
# training ~3-4; the same file byte for byte on the same machine). The filmed scenes and their tracks are cached under
# runs/pretrain_real/ (the tracks keyed by adjust-track's settings and the scene's files); the
# weights' SHA-256 goes to runs/benchmarks/pretrain_real_build.json.
# The simulator-only LSTM: $(PY) -m deformnet.pretrained.build
pretrained: $(STAMP)
	$(PY) -m adjust.pretrain_real --targets truth --work runs/pretrain_real \
		--report runs/benchmarks/pretrain_real_build.json

# The documentation site (mkdocs.yml, docs/), built as CI builds it, into runs/site/ (browse it with
# `.venv/bin/mkdocs serve`); mkdocs and mkdocs-material come with the test extra (or '.[docs]').
docs: $(STAMP)
	$(PY) -m mkdocs build --strict   # into runs/site/ (mkdocs.yml)

format: $(STAMP)
	$(VENV)/bin/ruff format . && $(VENV)/bin/ruff check --fix .

# The peers the benchmarks run side by side (aniposelib pulls jax, numba and opencv-contrib-python,
# whose cv2 would replace opencv-python-headless's): their own environment, .venv-bench; the
# Kalman smoother (pykalman) goes into .venv as the `bench` extra.
bench-env: .venv-bench/.installed $(VENV)/.bench

$(VENV)/.bench: $(STAMP)
	$(PY) -m pip install -q -e '.[bench]'
	touch $(VENV)/.bench

.venv-bench/.installed:
	$(PYTHON) -m venv .venv-bench
	.venv-bench/bin/python -m pip install -q --upgrade pip
	.venv-bench/bin/python -m pip install -q aniposelib==0.8.0
	touch .venv-bench/.installed

clean:
	rm -rf $(VENV)
