# casmag: make targets. `make demo` and `make test` create the virtual environment themselves.
PYTHON ?= python3
VENV   ?= .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed

.DEFAULT_GOAL := help
.PHONY: help install demo test test-slow test-all test-latest test-lowest lock lint docs clean bench-imu bench-imu-strategies bench-imu-recordings bench-imu-lag bench-imu-mag-rate bench-imu-latest bench-peers bench-peers-pose bench-walks bench-drift bench-localise bench-localise-real bench-real bench-real-ekf bench-scale bench-area bench-exact bench-convergence imu
.PHONY: table1 table2 table3 table4 table5 tables truth-start

help: ## List the targets
	@grep -E '^[a-zA-Z0-9_-]+:.*## ' $(MAKEFILE_LIST) | awk -F':.*## ' '{printf "  %-10s %s\n", $$1, $$2}'

# Installed from the committed lock (requirements.lock: every package, transitive ones
# included, with hashes), then casmag itself without dependencies. `make lock` refreshes it.
LOCK   := requirements.lock
$(STAMP): pyproject.toml $(LOCK)
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --require-hashes --no-deps -r $(LOCK)
	$(PY) -m pip install --quiet --no-deps --no-build-isolation -e .
	$(PY) -m pip check
	touch $(STAMP)

install: $(STAMP) ## Create .venv and install casmag with its test tools

demo: $(STAMP) ## Solve the paper's base case; writes results/demo/ (table, figures)
	$(VENV)/bin/casmag run problems/paper/base.yaml --out results/demo
	$(VENV)/bin/casmag report results/demo --out results/demo/table.md
	@cat results/demo/table.md

# One worker per core (pytest-xdist), a test file's tests on one worker so that a module's
# fixtures are built once. PYTEST_ARGS=-n0 runs them in this process, one after another.
# `make test` leaves out the tests marked slow (each over 12 s in a test run on 2 cores:
# full-size problems, whole real recordings, process pools); `make test-slow` runs them, `make
# test-all` both; CI (.ci/run) runs both.
PYTEST_ARGS ?= -n auto --dist loadfile
test: $(STAMP) ## Run the test suite without the slow tests (under 10 minutes on 2 cores)
	$(PY) -m pytest -q -m "not slow" $(PYTEST_ARGS)

test-slow: $(STAMP) ## Run the slow tests only (full-size problems, real recordings)
	$(PY) -m pytest -q -m slow $(PYTEST_ARGS)

test-all: $(STAMP) ## Run every test, the slow ones included
	$(PY) -m pytest -q $(PYTEST_ARGS)

# uv resolves the lock for every platform (--universal) at Python 3.11; the lock's own tool
# lives in its own environment so that it never enters casmag's.
UV_VERSION ?= 0.13.9
LOCKVENV   := .venv-lock
lock: ## Refresh requirements.lock from pyproject.toml (newest versions the ranges allow)
	$(PYTHON) -m venv $(LOCKVENV)
	$(LOCKVENV)/bin/python -m pip install --quiet uv==$(UV_VERSION)
	printf 'setuptools>=77\nwheel\n' | $(LOCKVENV)/bin/uv pip compile pyproject.toml - \
	  --extra dev --universal --python-version 3.11 --generate-hashes --quiet \
	  --custom-compile-command 'make lock' -o $(LOCK)

# The whole suite on the lowest versions pyproject.toml names for casmag's direct dependencies
# (their own dependencies as those versions allow), in its own environment made anew.
LOWEST := .venv-lowest
test-lowest: ## Run the test suite on the lower bounds in pyproject.toml (.venv-lowest)
	rm -rf $(LOWEST)
	$(PYTHON) -m venv $(LOWEST)
	test -x $(LOCKVENV)/bin/uv || { $(PYTHON) -m venv $(LOCKVENV) && $(LOCKVENV)/bin/python -m pip install --quiet uv==$(UV_VERSION); }
	$(LOCKVENV)/bin/uv pip compile pyproject.toml --extra dev --resolution lowest-direct \
	  --python-version 3.11 --quiet -o $(LOWEST)/requirements.txt
	$(LOWEST)/bin/python -m pip install --quiet -r $(LOWEST)/requirements.txt
	$(LOWEST)/bin/python -m pip install --quiet --no-deps -e .
	$(LOWEST)/bin/python -c 'import casmag.versions as v; print(v.line())'
	$(LOWEST)/bin/python -m pytest -q $(PYTEST_ARGS)

# The whole suite on the newest versions the ranges in pyproject.toml allow (no lock), in
# its own environment made anew each time.
LATEST := .venv-latest
test-latest: ## Run the test suite on the newest versions pyproject.toml allows (.venv-latest)
	rm -rf $(LATEST)
	$(PYTHON) -m venv $(LATEST)
	$(LATEST)/bin/python -m pip install --quiet --upgrade pip
	$(LATEST)/bin/python -m pip install --quiet --upgrade --upgrade-strategy eager -e '.[dev]'
	$(LATEST)/bin/python -c 'import casmag.versions as v; print(v.line())'
	$(LATEST)/bin/python -m pytest -q $(PYTEST_ARGS)

# The paper's Tables 1-5 (problems/paper/table*.yaml): SEEDS seeds per row, runs saved under
# $(PAPER)/runs/ (resumable: finished runs are skipped), tables and figures in $(PAPER)/.
SEEDS  ?= 20
# make bench-imu-lag: the magnetometer's lag put into the recordings [s], and seeds per scenario.
LAG    ?= 0.2
LAG_SEEDS ?= 1
# make bench-imu-mag-rate: the magnetometer on every MAG_EVERY-th IMU row, and seeds per scenario.
MAG_EVERY ?= 4
MAG_SEEDS ?= 2
PAPER  ?= results/paper
TABLES := table1 table2 table3 table4 table5
SWEEP  := $(VENV)/bin/casmag sweep --seeds $(SEEDS)

define paper_report
$(VENV)/bin/casmag report $(PAPER)/runs/$(1) --out $(PAPER)/$(1).md
endef

table1: $(STAMP) ## Paper Table 1 (true sigma_f), 20 seeds per row -> results/paper/table1.md
	$(SWEEP) problems/paper/$@.yaml --out $(PAPER)/runs/$@
	$(call paper_report,$@)

table2: $(STAMP) ## Paper Table 2 (wrong sigma_f), 20 seeds per row -> results/paper/table2.md
	$(SWEEP) problems/paper/$@.yaml --out $(PAPER)/runs/$@
	$(call paper_report,$@)

table3: $(STAMP) ## Paper Table 3 (true l), 20 seeds per row -> results/paper/table3.md
	$(SWEEP) problems/paper/$@.yaml --out $(PAPER)/runs/$@
	$(call paper_report,$@)

table4: $(STAMP) ## Paper Table 4 (wrong l), 20 seeds per row -> results/paper/table4.md
	$(SWEEP) problems/paper/$@.yaml --out $(PAPER)/runs/$@
	$(call paper_report,$@)

table5: $(STAMP) ## Paper Table 5 (odometry noise), 20 seeds per row -> results/paper/table5.md
	$(SWEEP) problems/paper/$@.yaml --out $(PAPER)/runs/$@
	$(call paper_report,$@)

tables: $(STAMP) ## Paper Tables 1-5 in one parallel sweep -> results/paper/tables.md, figures/
	$(SWEEP) $(TABLES:%=problems/paper/%.yaml) --out $(PAPER)/runs
	$(call paper_report,table1)
	$(call paper_report,table2)
	$(call paper_report,table3)
	$(call paper_report,table4)
	$(call paper_report,table5)
	$(VENV)/bin/casmag report $(PAPER)/runs --out $(PAPER)/tables.md

truth-start: $(STAMP) ## Tables 2 and 4 from the dead reckoning and from the truth -> results/paper/truth_start.md
	$(PY) -m casmag.experiments.truthstart problems/paper/table2.yaml problems/paper/table4.yaml --seeds $(SEEDS) --out $(PAPER)

lint: $(STAMP) ## ruff check and format check
	$(VENV)/bin/ruff check casmag tests examples
	$(VENV)/bin/ruff format --check casmag tests examples

docs: $(STAMP) ## API reference from the docstrings (pdoc, every casmag module; warnings are errors) -> docs/api/
	$(PY) -m casmag.apidocs docs/api

clean: ## Remove the environment and caches
	rm -rf $(VENV) $(LATEST) $(LOWEST) $(LOCKVENV) .pytest_cache .ruff_cache build *.egg-info

bench-real: $(STAMP) ## Real field (../shared/data): 5 sequences as translational and planar (2 drifts each) and pose odometry, 2 homogeneous, 2 multi-session -> results/real/table.md
	$(PY) -m casmag.experiments.realbench problems/real/*.yaml --out results/real

bench-real-ekf: $(STAMP) ## The filter baseline on the same single recordings -> results/real-ekf/table.md
	$(PY) -m casmag.experiments.realbench problems/real/seq*.yaml --method ekf --out results/real-ekf

bench-peers: $(STAMP) ## The MAP against the filter baseline (EKF), 20 seeds of problems/bench/peers.yaml -> results/bench/peers/
	$(PY) -m casmag.experiments.peers problems/bench/peers.yaml --seeds 20 --out results/bench/peers

bench-peers-pose: $(STAMP) ## The same as pose odometry (6-DoF increments, rotation noise) -> results/bench/peers-pose/
	$(PY) -m casmag.experiments.peers problems/bench/peers.yaml --motion pose --seeds 20 --out results/bench/peers-pose

bench-walks: $(STAMP) ## Planar and pose odometry walks (problems/planar, problems/pose), 10 seeds -> results/bench/walks/report.md
	$(VENV)/bin/casmag sweep problems/planar/walk.yaml problems/pose/walk.yaml --seeds 10 --figures first --out results/bench/walks
	$(VENV)/bin/casmag report results/bench/walks --out results/bench/walks/report.md

bench-drift: $(STAMP) ## Planar and pose walks drifting beyond one batch's basin: growing vs sliding windows, 5 seeds -> results/bench/drift/report.md
	$(VENV)/bin/casmag sweep problems/planar/drift.yaml problems/pose/drift.yaml --seeds 5 --figures first --out results/bench/drift
	$(VENV)/bin/casmag report results/bench/drift --out results/bench/drift/report.md

bench-localise: $(STAMP) ## Map once, locate later: planar and pose walks located against their saved map (box, then tiles), and IMU recordings (3 scenarios, 3 seeds), beside scratch and joint solves -> results/bench/localise/localise.md, localise-tiled.md, localise-imu.md
	$(PY) -m casmag.experiments.locbench --seeds 5 --out results/bench/localise
	$(PY) -m casmag.experiments.locbench --seeds 5 --form tiled --out results/bench/localise
	$(PY) -m casmag.experiments.locbench --motion imu --seeds 3 --out results/bench/localise

bench-localise-real: $(STAMP) ## Map once, locate later on the real field (../shared/data): sequences 1, 2, 4 mapped, 3 and 5 located (held, updated) beside the sessions solved together -> results/bench/localise/localise-real.md (about 40 min)
	$(PY) -m casmag.experiments.reallocate --pairs --out results/bench/localise

# make bench-scale / bench-area: seconds one run may take before it is stopped (its row then
# says so, with the iterations, seconds per iteration and memory it had reached).
BENCH_TIMEOUT ?= 3600
bench-scale: $(STAMP) ## Scale benchmark: N = 1k..64k walk, one box in 6x6 m and tiles in 50x70 m, exact vs reduced rank; results/bench/scale.json, .png (hours)
	$(PY) -m casmag.experiments.bench scale --timeout $(BENCH_TIMEOUT) --out results/bench

# make bench-area AREA_STARTS=dead-reckoning,truth: each map also solved once from the true
# positions (the model's optimum near the truth, apart from whether a start finds it).
AREA_STARTS ?= dead-reckoning
bench-area: $(STAMP) ## Same walk (10k samples) over 6x6, 20x20, 50x70 m, dipole field: one box vs tiles; results/bench/area.json, .png (hours)
	$(PY) -m casmag.experiments.bench area --timeout $(BENCH_TIMEOUT) --starts $(AREA_STARTS) --out results/bench

bench-exact: $(STAMP) ## Exact GP against reduced rank, N = 100..500; replaces those rows of results/bench/scale.json
	$(PY) -m casmag.experiments.bench exact --out results/bench

bench-convergence: $(STAMP) ## Windowing convergence grid, 20 seeds per cell; results/bench/convergence.json, .png (resumable)
	$(PY) -m casmag.experiments.convergence --out results/bench

imu: $(STAMP) ## Solve every IMU problem; writes results/imu/<name>/ (about 10 minutes)
	@for f in problems/imu/*.yaml; do n=$$(basename $$f .yaml); \
	  $(VENV)/bin/casmag imu $$f --out results/imu/$$n --quiet; echo "$$n: exit $$?"; done

bench-imu: $(STAMP) ## Every IMU scenario over SEEDS seeds (resumable) -> results/bench/imu/imu.json, imu.md
	$(PY) -m casmag.experiments.imubench problems/imu/*.yaml --seeds $(SEEDS) --out results/bench/imu

bench-imu-recordings: $(STAMP) ## Every IMU scenario written as a recording and solved by casmag slam's defaults beside casmag imu, SEEDS seeds -> results/bench/imu-recordings/
	$(PY) -m casmag.experiments.imurecbench problems/imu/*.yaml --seeds $(SEEDS) --out results/bench/imu-recordings

bench-imu-lag: $(STAMP) ## The handwriting, rectangle and spiral recordings with the magnetometer LAG s late (default 0.2), casmag slam with --mag-lag 0 and auto (the IMU default), LAG_SEEDS seeds -> results/bench/imu-lag/ (hours: a lag slows the solve)
	$(PY) -m casmag.experiments.imurecbench problems/imu/handwriting.yaml problems/imu/rectangle.yaml problems/imu/spiral.yaml --seeds $(LAG_SEEDS) --lag $(LAG) --out results/bench/imu-lag

bench-imu-mag-rate: $(STAMP) ## The handwriting and rectangle recordings with the magnetometer on every MAG_EVERY-th IMU row only (default 4: 25 Hz beside 100 Hz), casmag slam on both, MAG_SEEDS seeds -> results/bench/imu-mag-rate/
	$(PY) -m casmag.experiments.imurecbench problems/imu/handwriting.yaml problems/imu/rectangle.yaml --seeds $(MAG_SEEDS) --mag-every $(MAG_EVERY) --out results/bench/imu-mag-rate

bench-imu-strategies: $(STAMP) ## Every IMU scenario with each warm-start strategy (none, coarse-to-fine, sliding) over SEEDS seeds -> results/bench/imu-<strategy>/
	@for s in none coarse-to-fine sliding; do \
	  $(PY) -m casmag.experiments.imubench problems/imu/*.yaml --seeds $(SEEDS) \
	    --set solver.warm_start.strategy=$$s --out results/bench/imu-$$s || exit 1; done

bench-imu-latest: ## The same on the newest versions (the environment of make test-latest) -> results/bench/imu-latest/
	test -x $(LATEST)/bin/python || $(MAKE) test-latest
	$(LATEST)/bin/python -m casmag.experiments.imubench problems/imu/*.yaml --seeds $(SEEDS) --out results/bench/imu-latest
