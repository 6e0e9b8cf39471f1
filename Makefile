# snn_rendezvous: every target creates .venv on first use (Python 3.11 with venv and pip).
#   make demo [ESTIMATOR=snn_ekf] [MODE=lockstep|realtime [RTF=10]] [PLANT=cw|basilisk] [LIVE=1]   closed-loop demo
#                             over ROS 2 (LIVE=1: live view, Foxglove at ws://localhost:8765)
#   make demo SCENARIO=approach   5 km to contact over ROS 2 -> results/approach_ros.json; make approach-figure
#                             draws it -> results/figures/approach_ros.png
#   make demo SCENARIO=approach SENSOR=by_range   the same on relative GPS, the LIDAR and the docking camera,
#                             a sensor node each -> results/approach_ros_by_range.json
#   make demo SCENARIO=approach SENSOR=angles_far   the same with a far camera (angles only) instead of
#                             relative GPS and the out-of-plane hop at 5 km -> results/approach_ros_angles_far.json
#   make test                 all tests and the linter (what CI runs)
#   make test-fast            the quick loop: no ROS process, the first case of every-kind tests (~1 min)
#   make experiments [RUNS=n] [WORKERS=2]   the paper's experiments and ours -> results/REPORT.md
#   make campaign SPEC=config/campaigns/example.yaml [WORKERS=2] [SCHEDULER=tcp://host:8786]
#   make campaign SPEC=config/campaigns/approach.yaml   the approach to contact as a campaign: safety figures
#                             per cell, cw beside nonlinear_circular (~1 min) -> runs/campaign_approach/
#   make neuromorphic         NIR export, Brian2 re-run, cost per estimate -> results/neuromorphic.*
#   make spike-rules [RUNS=n]  the local (synchronous) spike rule against greedy and the twin, position and
#                             LIDAR, dispersed -> results/neuromorphic.{json,md} (its section only)
#   make norse-loop [RUNS=n] [NORSE_PYTHON=...]  the synchronous network built by Norse (GitHub master, not on
#                             PyPI: docs/decisions.md, 71) from the .nir file, in the closed loop, against the
#                             package's on the same seeds -> results/norse_loop.json, its section of neuromorphic.md
#   make bench | bench-loop | bench-campaign | bench-live | bench-latency [SAMPLES=n]   speed figures -> results/
#   make spike-budget [RUNS=n]  spikes against accuracy per network coding -> results/spike_budget.{json,md}
#   make chip-synchronous [RUNS=n]  the synchronous rule on the fixed-point (Loihi-format) Eq. 15 network against
#                             float at 8-bit weights -> results/neuromorphic.{json,md} (its section only)
#   make sensors [RUNS=n]     the filters on the LIDAR and the camera, offline -> results/sensors.{json,md}
#   make report RUN=runs/<name>   figures and report.md from a recorded run (written beside it)
#   make faults [CELLS=controller:kill,...]   kill/stop each node mid-run -> results/faults.json, docs/robustness.md
PYTHON ?= python3.11
VENV ?= .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.snn_rendezvous-installed
ESTIMATOR ?=
SCENARIO ?=
SENSOR ?=
MODE ?= lockstep
PLANT ?= cw
RTF ?=
LIVE ?=
RUNS ?=
SAMPLES ?=
SPEC ?= config/campaigns/example.yaml
WORKERS ?= 2
SCHEDULER ?=
# ROS 2 Jazzy from PyPI (cp311 wheels); lark-parser is what they need (never lark 1.x beside it).
ROS_WHEELS := "ros-jazzy-rclpy[fastrtps]" ros-jazzy-common-interfaces

.PHONY: venv warm time-first-demo test test-fast lint demo experiments campaign neuromorphic bench bench-loop bench-campaign bench-live bench-latency \
	spike-budget spike-rules chip-synchronous norse-loop sensors approach approach-basilisk approach-figure \
	docs-screenshots report faults clean

venv: $(STAMP)

$(STAMP): setup.py pyproject.toml scenario_nodes/registry.py
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade "pip>=23"
	$(BIN)/python -m pip install --quiet $(ROS_WHEELS)
	$(BIN)/python -m pip install --quiet -e ".[test,basilisk,campaign,neuromorphic,live]"
	$(BIN)/python -m pip install --quiet colcon-common-extensions
	# compile what make demo runs into numba's cache (the rest compiles on first use, or with make warm)
	$(BIN)/python -m snn_tools.run.warm_cache --demo
	touch $(STAMP)

# every kernel (each filter kind, the closed loops, the Basilisk plant) into numba's cache, on the
# CPUs in parallel: no test, node or Monte Carlo compiles after it
WARM := $(VENV)/.snn_rendezvous-warm
warm: $(WARM)

$(WARM): $(STAMP)
	$(BIN)/python -m snn_tools.run.warm_cache
	touch $(WARM)

lint: $(STAMP)
	$(BIN)/ruff check .

# the CPU-sensitive tests (golden numbers of the fast-math kernels) run again compiled for a generic
# x86-64 CPU: the suite must pass on any CPU the wheels support (issue 36)
test: lint warm
	$(BIN)/python -m pytest -q -n 2 -m "not slow" test
	NUMBA_CPU_NAME=generic $(BIN)/python -m pytest -q -n 2 -m cpu_sensitive test
	$(BIN)/python -m pytest -q -m slow --durations=15 test

test-fast: $(STAMP)
	$(BIN)/python -m pytest -q -n 2 -m "not slow and not exhaustive" test

# SCENARIO=approach: 5 km to contact (one BLAS thread: the nonlinear filter's 6x6 exponentials), its
# results file results/approach_ros.json (make approach-figure draws it); SENSOR: position (default) or a
# suite (docs/sensors.md; with the approach: by_range or angles_far -> results/approach_ros_<suite>.json)
demo: $(STAMP)
	$(if $(SCENARIO),OPENBLAS_NUM_THREADS=1 OMP_NUM_THREADS=1) $(BIN)/snn_demo --mode $(MODE) --plant $(PLANT) \
		$(if $(ESTIMATOR),--estimator $(ESTIMATOR)) $(if $(SENSOR),--sensor $(SENSOR)) \
		$(if $(RTF),--real-time-factor $(RTF)) $(if $(LIVE),--live-view) \
		$(if $(SCENARIO),--scenario $(SCENARIO) $(if $(filter approach,$(SCENARIO)),--results results/approach_ros$(if $(filter-out position,$(SENSOR)),_$(SENSOR)).json))

experiments: $(STAMP)
	$(BIN)/snn_experiments $(if $(RUNS),--runs $(RUNS)) --out results \
		$(if $(SCHEDULER),--scheduler $(SCHEDULER),--workers $(WORKERS))

campaign: $(STAMP)
	$(BIN)/snn_campaign --spec $(SPEC) --out runs/campaign_$(notdir $(basename $(SPEC))) \
		$(if $(SCHEDULER),--scheduler $(SCHEDULER),--workers $(WORKERS))

neuromorphic: $(STAMP)
	$(BIN)/snn_neuromorphic $(if $(RUNS),--runs $(RUNS)) --out results

bench: $(STAMP)
	$(BIN)/snn_bench --out results/bench.json
	$(BIN)/python -m snn_tools.bench.codec --out results/codec_bench.json
	$(BIN)/python -m snn_tools.bench.measurement --out results/measurement_bench.json

# RUNS means Monte-Carlo runs (default: each spec's) for experiments; the loop bench takes 5 unless given
bench-loop: $(STAMP)
	$(BIN)/snn_loop_bench --runs $(if $(RUNS),$(RUNS),5) --out results/loop_bench.json \
		$(if $(ESTIMATOR),--estimator $(ESTIMATOR))
	$(BIN)/snn_loop_bench --runs $(if $(RUNS),$(RUNS),5) --single-process \
		--out results/loop_bench_single_process.json $(if $(ESTIMATOR),--estimator $(ESTIMATOR))

# realtime latency measurement -> estimate / control, 1x and 10x, ten cases (10000 samples: ~55 min)
bench-latency: $(STAMP)
	$(BIN)/snn_latency_bench --out results/latency.json --history results/latency_runs $(if $(SAMPLES),--samples $(SAMPLES)) \
		$(if $(ESTIMATOR),--estimator $(ESTIMATOR))

# every spiking kind under each network coding and unit, dispersed rendezvous, against its twin
spike-budget: $(STAMP)
	$(BIN)/python -m snn_tools.experiments.spike_budget $(if $(RUNS),--runs $(RUNS)) --out results/spike_budget.json

# the synchronous (local) spike rule per kind on position and LIDAR (RUNS each, default 100), dispersed start
# NORSE_PYTHON: a Python with torch and Norse master (norse 1.1.0 on PyPI cannot read the graph) that
# imports this package (e.g. PYTHONPATH=$(CURDIR) and the .venv's site-packages appended)
NORSE_PYTHON ?= $(BIN)/python
norse-loop: $(STAMP)
	$(NORSE_PYTHON) -m snn_tools.neuromorphic.norse_loop --out results $(if $(RUNS),--runs $(RUNS))

spike-rules: $(STAMP)
	$(BIN)/python -m snn_tools.neuromorphic.tables --local-rule-only --out results \
		$(if $(RUNS),--local-rule-runs $(RUNS) $(RUNS))

# the synchronous rule on the fixed-point chip network (Eq. 15 in Loihi's formats) against float, RUNS per row (20)
chip-synchronous: $(STAMP)
	$(BIN)/python -m snn_tools.neuromorphic.tables --chip-synchronous-only --out results \
		$(if $(RUNS),--chip-synchronous-runs $(RUNS))

# the LIDAR close approach (dispersed) and angles-only navigation, offline (docs/sensors.md)
sensors: $(STAMP)
	$(BIN)/python -m snn_tools.experiments.sensors $(if $(RUNS),--runs $(RUNS)) --out results

# 5 km to contact through the holds, a few dispersed runs per filter and model (docs/decisions.md, 55-57);
# one BLAS thread: the nonlinear filters' small matrix exponentials are ~40x slower threaded on a loaded machine.
# ANGLES=1 adds the angles-only far camera with and without its observability hop (decisions 73-75; ~7 min more here)
approach: $(STAMP)
	OPENBLAS_NUM_THREADS=1 OMP_NUM_THREADS=1 $(BIN)/python -m snn_tools.experiments.approach --runs $(if $(RUNS),$(RUNS),10) --out results \
		$(if $(ANGLES),--angles)

# the same on Basilisk's two-body truth with J2, 100 runs of each filter on each model, then the EKF
# and SNN-EKF on ss_j2, the Schweighart-Sedwick J2 model, then the EKF with a Q_hat sized for J2's
# pull (J2_Q_CELLS; ~40 + 8 + 14 min) ->
# results/approach_basilisk.{json,md} and its section of results/REPORT.md
approach-basilisk: $(STAMP)
	OPENBLAS_NUM_THREADS=1 OMP_NUM_THREADS=1 $(BIN)/python -m snn_tools.experiments.approach --plant basilisk \
		--runs $(if $(RUNS),$(RUNS),100) --kinds ekf snn_ekf emsif_weighted --no-extra --out results
	OPENBLAS_NUM_THREADS=1 OMP_NUM_THREADS=1 $(BIN)/python -m snn_tools.experiments.approach --plant basilisk \
		--runs $(if $(RUNS),$(RUNS),100) --kinds ekf snn_ekf --models ss_j2 --no-extra --add --out results
	OPENBLAS_NUM_THREADS=1 OMP_NUM_THREADS=1 $(BIN)/python -m snn_tools.experiments.approach --plant basilisk \
		--runs $(if $(RUNS),$(RUNS),100) --kinds --no-extra --j2-q --add --out results

# the README's approach figure from the results file make demo SCENARIO=approach writes
approach-figure: $(STAMP)
	$(BIN)/python -m snn_tools.figures --approach results/approach_ros.json --out results/figures/approach_ros.png

bench-campaign: $(STAMP)
	$(BIN)/snn_campaign_bench --repeat 2 --out results/campaign_bench.json

# the lockstep loop with and without the live view (and a Foxglove client of each subprotocol), interleaved
# pairs; then bytes/s per channel in realtime runs at the default raster settings and two others
bench-live: $(STAMP)
	$(BIN)/python -m snn_tools.bench.live --pairs $(if $(RUNS),$(RUNS),8) --out results/live_view_bench.json

# the README's pictures: the interactive page of a small campaign in headless Chromium, and what a
# Foxglove client receives from the live view during a realtime demo (drawn with matplotlib)
docs-screenshots: $(STAMP)
	$(BIN)/snn_campaign --spec config/campaigns/page_example.yaml --out runs/campaign_page_example --workers $(WORKERS)
	chromium --headless --no-sandbox --disable-gpu --hide-scrollbars --user-data-dir=runs/.chromium \
		--window-size=1100,1700 --virtual-time-budget=10000 --screenshot=docs/campaign_page.png \
		runs/campaign_page_example/campaign.html
	$(BIN)/python -m snn_tools.live.snapshot --out docs/live_view.png

report: $(STAMP)
	@test -n "$(RUN)" || (echo "usage: make report RUN=runs/<name>" && exit 2)
	$(BIN)/report $(RUN)

# ten realtime x10 runs of 480 s (~12 min on an idle 2-core machine)
faults: $(STAMP)
	$(BIN)/python -m snn_tools.experiments.faults --out results/faults.json $(if $(CELLS),--cells $(CELLS))

# a newcomer's first make demo, timed on a fresh clone of HEAD with its own .venv (~1.5 GB in a
# temporary folder, removed after) -> results/first_demo.json
time-first-demo:
	$(PYTHON) -m snn_tools.bench.first_demo --python $(PYTHON) --out results/first_demo.json

clean:
	rm -rf build install log *.egg-info
