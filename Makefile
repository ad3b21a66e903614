# Two commands do all set-up on a fresh machine: `make demo` and `make test`.
# TORCH_SPEC picks the torch build (default: the CPU wheel pinned for this project's machines).
PYTHON ?= python3
TORCH_SPEC ?= torch==2.13.0
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.setup-stamp
DEMO_OUT ?= demo_out
PYTEST_ARGS ?=

.PHONY: setup ingest-setup test test-slow docs soak demo bench results own-recording dist clean

setup: $(STAMP)

$(STAMP): pyproject.toml scripts/system_deps.sh scripts/install_ingest.sh
	bash scripts/system_deps.sh
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet "$(TORCH_SPEC)"
	$(PY) -m pip install --quiet -e ".[dev]"
	bash scripts/install_ingest.sh $(PY)
	touch $(STAMP)

# The optional detector of `deliffas ingest` (MediaPipe 0.10.21 without its declared dependencies); `setup` runs it.
ingest-setup: setup
	bash scripts/install_ingest.sh $(PY)

# The suite without the tests marked slow (about 10 min on 2 cores); CI runs both targets.
test: setup
	$(VENV)/bin/lint-imports --no-cache
	$(MAKE) docs
	$(PY) -m pytest -q -m "not slow" $(PYTEST_ARGS)

# The long integration tests (recipe quick runs, the wheel in a fresh venv, SIGKILL chains, memory
# bounds; about 10 min).
test-slow: setup
	$(PY) -m pytest -q -m slow $(PYTEST_ARGS)

# The documentation site (docs/*.md and the API reference from the docstrings) into site/; --strict:
# a broken link or cross-reference fails. Open site/index.html.
docs: setup
	NO_MKDOCS_2_WARNING=1 $(VENV)/bin/mkdocs build --strict --site-dir site

# The reliability suite at soak scale: >= 10,000 fuzz cases per reader, >= 20 SIGKILLs of conversion.
soak: setup
	DELIFFAS_SOAK=1 $(PY) -m pytest -q tests/reliability/test_fuzz_readers.py \
		tests/reliability/test_fuzz_artifacts.py tests/reliability/test_fuzz_capture_readers.py \
		tests/reliability/test_convert_crash.py tests/reliability/test_checkpoints.py $(PYTEST_ARGS)

demo: setup
	$(VENV)/bin/deliffas demo --out $(DEMO_OUT)

bench: setup
	$(PY) -m benchmarks.run

# Every recipe in full mode (3 seeds; hours on 2 cores, not in CI): the numbers of docs/results.md.
RESULTS_OUT ?= results_out
RECIPES := ablation_single_surface ablation_coarse_mesh ablation_perceptual time_to_quality where_it_fails presets ingest_truth
results: setup
	for r in $(RECIPES); do $(PY) -m recipes.$$r --out $(RESULTS_OUT)/$$r || exit 1; done
	$(PY) -m recipes.ablation_template --out $(RESULTS_OUT)/ablation_template --smpl-model procedural

# A real recording to an avatar (docs/own-recording.md): ingest, check, convert, train with the defaults (3 cameras;
# the 4th held out), eval on the held-out camera and frames, an orbit video. RECORDING: videos + a calibration.
RECORDING ?= ../shared/real-captures/pose2sim-demo
OWN_OUT ?= own_recording_out
own-recording: setup
	$(VENV)/bin/deliffas ingest $(RECORDING) --out $(OWN_OUT)/subject --overwrite
	$(VENV)/bin/deliffas check $(OWN_OUT)/subject --out $(OWN_OUT)/check || true
	$(VENV)/bin/deliffas convert $(OWN_OUT)/subject $(OWN_OUT)/shards --overwrite
	$(VENV)/bin/deliffas train $(OWN_OUT)/shards --out $(OWN_OUT)/run --overwrite
	$(VENV)/bin/deliffas eval $(OWN_OUT)/run --split novel_view --grid $(OWN_OUT)/grid_novel_view.png --json > $(OWN_OUT)/eval_novel_view.json
	$(VENV)/bin/deliffas eval $(OWN_OUT)/run --split novel_pose --grid $(OWN_OUT)/grid_novel_pose.png --json > $(OWN_OUT)/eval_novel_pose.json
	$(VENV)/bin/deliffas render $(OWN_OUT)/run --orbit --frames 120 --loop --out $(OWN_OUT)/orbit.mp4 --overwrite

# The sdist and the wheel (python -m build; the wheel is built from the sdist) into dist/.
dist: setup
	$(PY) -m build --outdir dist

clean:
	rm -rf $(VENV) $(DEMO_OUT) $(RESULTS_OUT) bench_out site dist .pytest_cache .import_linter_cache
