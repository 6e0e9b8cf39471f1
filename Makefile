# snn_rendezvous: every target creates .venv on first use (Python 3.10+ with venv and pip).
#   make demo [ESTIMATOR=snn_ekf] [MODE=lockstep|realtime]   closed-loop demo over ROS 2
#   make test                                              all tests
#   make experiments [RUNS=100]                            the paper's experiments -> results/
#   make bench                                             us per estimator step -> results/bench.json
#   make bench-loop [ESTIMATOR=..] [RUNS=5]                ROS loop: real-time factor, CPU per node
#   make report RUN=runs/<name>                            figures + report.md from a recorded run
PYTHON ?= python3
VENV ?= .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.snn_rendezvous-installed
ESTIMATOR ?= snn_emsif
MODE ?= lockstep
RUNS ?= 100
# ROS 2 Jazzy from PyPI (cp311 wheels); lark-parser is what they need (never lark 1.x beside it).
ROS_WHEELS := "ros-jazzy-rclpy[fastrtps]" ros-jazzy-common-interfaces

.PHONY: venv test demo experiments bench bench-loop report clean

venv: $(STAMP)

$(STAMP): setup.py pyproject.toml
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade "pip>=23"
	$(BIN)/python -m pip install --quiet $(ROS_WHEELS)
	$(BIN)/python -m pip install --quiet -e ".[test,basilisk,campaign,neuromorphic]"
	$(BIN)/python -m pip install --quiet colcon-common-extensions
	touch $(STAMP)

test: $(STAMP)
	$(BIN)/python -m pytest -q test

demo: $(STAMP)
	$(BIN)/snn_demo --estimator $(ESTIMATOR) --mode $(MODE)

experiments: $(STAMP)
	$(BIN)/snn_experiments --runs $(RUNS) --out results

bench: $(STAMP)
	$(BIN)/snn_bench --out results/bench.json

# RUNS means Monte-Carlo runs (default 100) for experiments; the loop bench takes 5 unless given
bench-loop: $(STAMP)
	$(BIN)/snn_loop_bench --estimator $(ESTIMATOR) --runs $(if $(filter command line,$(origin RUNS)),$(RUNS),5)

report: $(STAMP)
	@test -n "$(RUN)" || (echo "usage: make report RUN=runs/<name>" && exit 2)
	$(BIN)/report $(RUN)

clean:
	rm -rf build install log *.egg-info
