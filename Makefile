# Every target builds what it needs from nothing: a .venv with the pinned versions.
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
INSTALLED := $(VENV)/.pip-installed
STAMP := $(VENV)/.installed
KERNEL_SOURCES := $(wildcard common/learning/batched/*.py) envs/compiled.py \
	common/learning/randomness.py
export OMP_NUM_THREADS ?= 1
export MKL_NUM_THREADS ?= 1
# pip installs without compiling every module to bytecode (torch alone has ~16,000: ~40 s); the
# first import of a module writes its .pyc instead, so only what runs is compiled, once.
unexport PYTHONDONTWRITEBYTECODE

.PHONY: setup demo docs test test-long image test-containers test-cluster bench-cluster bench-containers clean-containers lint tables typecheck contracts bench bench-learning bench-learning-long bench-tuned bench-robustness bench-presets bench-scale bench-device bench-plan bench-async bench-privacy figures clean

setup: $(STAMP)

# The packages, then numba's kernel cache filled once (~25 s, one thread): the static checks
# need only the packages, so make test fills the cache beside them.
$(INSTALLED): pyproject.toml constraints.txt
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet --no-compile -c constraints.txt -e ".[envs,dev]"
	touch $(INSTALLED)

$(STAMP): $(INSTALLED) $(KERNEL_SOURCES)
	$(BIN)/python -m fedhpg.common.learning.kernel_cache
	touch $(STAMP)

demo: $(STAMP)
	$(BIN)/fedhpg-run

# The documentation site (mkdocs-material, mkdocstrings) in build/site, --strict: a broken link
# or a docstring the API reference cannot render is an error. The reference reads fedhpg.*
# through links under build/docs/fedhpg (the package lives in the root folders). No --quiet:
# mkdocs 1.6 then drops the warnings before --strict counts them.
DOCS := build/docs
docs: $(INSTALLED)
	rm -rf $(DOCS) && mkdir -p $(DOCS)/fedhpg
	for d in agent common envs server; do ln -s ../../../$$d $(DOCS)/fedhpg/$$d; done
	ln -s ../../../fedhpg/__init__.py $(DOCS)/fedhpg/__init__.py
	NO_MKDOCS_2_WARNING=1 $(BIN)/mkdocs build --strict

# Two xdist workers: the tests that start federations run one after another on one of them
# (tests/federation_tests.py picks them test by test); both share the rest. From a fresh clone
# on 2 cores: ~7 min in all, ~6 of them the tests. Before them the static checks and the
# kernel cache, each one thread and independent of the others, two at a time (the longest
# first): a sub-make with -j2, each one's output printed whole when it ends (--output-sync),
# and one that fails fails make test once the other running one has ended.
test: $(INSTALLED)
	$(MAKE) --no-print-directory -j2 --output-sync=target typecheck $(STAMP) docs contracts lint \
		tables
	$(BIN)/python -m pytest -q -m "not slow" -n 2 --dist loadscope

# The long tier (marked slow): every shipped env preset learns, every docs page's code runs as
# printed, the longest integration runs, the resource attacks and the 10,000-frame fuzz of a
# live server (~8 min on 2 cores). Two workers first, as make test shares them (the tests that
# start federations one after another on one worker; the learning runs, and the docs pages one
# page a unit, marked alongside, on either); then, on one worker, the tests marked solo: those
# timed against the wall clock or counting what a server does under load (the resource attacks
# time how many connections a server sheds), which a learning run on the other core would
# starve. .ci/run runs it after make test.
test-long: $(STAMP)
	$(BIN)/python -m pytest -q -m "slow and not solo" -n 2 --dist loadscope
	$(BIN)/python -m pytest -q -m "slow and solo"

# The image without Docker Hub or an index: a debootstrap base, this machine's wheels, an offline
# build (the running engine: DOCKER_HOST, or `docker/engine.sh start` prints one).
image: $(STAMP)
	bash docker/make-base.sh fedhpg-base:bookworm
	bash docker/make-wheelhouse.sh $(BIN)/python
	docker build --network none --build-arg BASE_IMAGE=fedhpg-base:bookworm \
		--build-arg PIP_SOURCE=wheelhouse -t fedhpg:latest .

# The image and docker-compose.yml under a real Docker engine (tests/test_containers.py):
# docker/engine.sh installs and starts one where none runs and the machine allows it, else the
# tests are skipped with the reason; everything they start is removed by id when they end.
test-containers: $(STAMP)
	FEDHPG_CONTAINER_TESTS=1 $(BIN)/python -m pytest -q -rs tests/test_containers.py

# fedhpg-cluster on a real SLURM and a real Ray (tests/test_cluster_engines.py): cluster/slurm.sh
# and cluster/ray.sh install what they need (Debian's slurm and munge packages, the ray extra) and
# start private two-node clusters in network namespaces where the machine allows it (root), else
# the tests are skipped with the reason; what they start they stop, by pid (~3 min on 2 cores).
test-cluster: $(STAMP)
	FEDHPG_CLUSTER_TESTS=1 $(BIN)/python -m pytest -q -rs tests/test_cluster_engines.py

# Start-up and per-round cost of fedhpg-cluster on SLURM and on Ray against fedhpg-run, the demo
# and K = 1,000 on 2 hosts, on the clusters of test-cluster (BENCHMARKS.md "Clusters").
bench-cluster: $(STAMP)
	$(BIN)/python -m benchmarks.cluster_overhead

# Timings from nothing (no base, image or build cache), the demo's 60 rounds in containers and
# on loopback: benchmarks/results/containers.json (BENCHMARKS.md "Containers").
bench-containers: $(STAMP)
	FEDHPG_CONTAINER_TESTS=1 FEDHPG_CONTAINER_COLD=1 FEDHPG_CONTAINER_ROUNDS=60 \
	FEDHPG_CONTAINER_TIMINGS=benchmarks/results/containers.json \
	$(BIN)/python -m pytest -q -rs tests/test_containers.py -k "equals_loopback"

# The engine's image store (/var/lib/fedhpg-docker) and the wheelhouse: what the tests cache.
clean-containers:
	bash docker/engine.sh stop
	rm -rf /var/lib/fedhpg-docker docker/wheelhouse/*.whl

# mypy sees the package as fedhpg.* through links (the folders are mapped by package-dir).
TYPECHECK := build/typecheck/fedhpg
typecheck: $(INSTALLED)
	rm -rf $(TYPECHECK) && mkdir -p $(TYPECHECK)
	for d in agent common envs server; do ln -s ../../../$$d $(TYPECHECK)/$$d; done
	ln -s ../../../fedhpg/__init__.py $(TYPECHECK)/__init__.py
	$(BIN)/mypy -p fedhpg

# Layers (pyproject.toml [tool.importlinter]): agent never imports server, common neither
# side, envs nothing of the federation, the maths no wire, configs no torch/zmq/gymnasium.
# grimp wants the checked packages' parent to be a namespace package, and fedhpg is a package
# of its own (fedhpg.__version__): they are linked under build/lint/fedhpg, without it.
LINT := build/lint
contracts: $(INSTALLED)
	rm -rf $(LINT) && mkdir -p $(LINT)/fedhpg
	for d in agent common envs server; do ln -s ../../../$$d $(LINT)/fedhpg/$$d; done
	cd $(LINT) && ../../$(BIN)/lint-imports --config ../../pyproject.toml

lint: $(INSTALLED)
	$(BIN)/ruff check .
	$(BIN)/ruff format --check .

# BENCHMARKS.md is the rendering of benchmarks/results (python -m benchmarks.render writes it).
tables: $(INSTALLED)
	$(BIN)/python -m benchmarks.render --check

figures: $(STAMP)
	$(BIN)/python -m benchmarks.figures

bench-learning: $(STAMP)
	$(BIN)/python -m benchmarks.learning

# LunarLander and HalfCheetah, K=10, 10,000 trajectories per agent, 5 seeds each: hours on
# 2 cores, so it runs at the lowest priority. Results in benchmarks/results/, figures in docs/.
bench-learning-long: $(STAMP)
	nice -n 19 $(BIN)/python -m benchmarks.learning_long --task lunarlander
	nice -n 19 $(BIN)/python -m benchmarks.learning_long --task halfcheetah

# The tuned LunarLander and HalfCheetah presets (experiment=k10_*_tuned) beside the
# paper-faithful set-up, 5 seeds each, in process on the counted clock; hours on 2 cores, so at
# the lowest priority. --resume keeps the stored curves (drop it to rerun them). Results in
# benchmarks/results/tuned_*.json, figures in docs/figures/tuned_*.png.
bench-tuned: $(STAMP)
	nice -n 19 $(BIN)/python -m benchmarks.tuned_presets --task lunarlander --resume
	nice -n 19 $(BIN)/python -m benchmarks.tuned_presets --task halfcheetah --resume

# One learning result per shipped env group (fedhpg-run env=NAME), with K=1 baselines (~40 min
# on 2 cores). Results in benchmarks/results/presets.json, the table on stdout.
bench-presets: $(STAMP)
	nice -n 10 $(BIN)/python -m benchmarks.presets

# CartPole K=10 with 3 sign-flipping agents: mean, median, trimmed mean (~10 min).
# Thousands of agents on agent hosts: CartPole K = 1,000 and 10,000, one process per
# agent, the coordination cost at 10^4 parameters, each case again right after at the fused
# engine's commit (and one process per agent against it run by run), GridWorld K = 1,000.
# Tens of minutes on 2 cores; results in
# benchmarks/results/scale*.json and engine_ab_processes.json, figures in docs/scale*.png.
# numba's kernel cache, filled at setup, is filled afresh first (numba would not notice that
# a kernel another file calls changed), or the first case's start-up would time a compilation.
bench-scale: $(STAMP)
	$(BIN)/python -m fedhpg.common.learning.kernel_cache
	OMP_NUM_THREADS=1 $(BIN)/python -m benchmarks.scale
	OMP_NUM_THREADS=1 $(BIN)/python -m benchmarks.processes_ab
	OMP_NUM_THREADS=1 $(BIN)/python -m benchmarks.scale_gridworld

# A federation on one GPU (docs/gpu.md), one script within 8 minutes (benchmarks/on_device.sh),
# each part under its own time limit: the placement check on the device for the five torch
# families, K = 1,000, 16,000, 65,536 CartPole agents' whole local iteration and peak memory
# against a reference measured in the same run, where one iteration's time goes (engine sections
# and torch's busiest operators, 16,000 agents), a fedhpg-run federation of 65,536 agents on one
# host for 3 rounds. Results in $OUT if set, else benchmarks/results/device/. DEVICE=cpu
# rehearses it here (K = 100 and 1,000, a profile of 200, 2,000 agents; 1–3 min on 2 cores);
# one line and exit 1 where torch sees no CUDA device. A bare GPU machine: `bash benchmarks/on_device.sh run`.
DEVICE ?= cuda
bench-device: $(STAMP)
	DEVICE=$(DEVICE) PYTHON=$(BIN)/python bash benchmarks/on_device.sh local

# The Theorem 1 planner against uniform, speed-proportional and the paper's budgets at one
# emulated-time budget: GridWorld K=4 (two speed spreads), CartPole K=10 and K=100,
# 5 seeds, counted virtual clock (deterministic, so load does not change the figures).
# benchmarks/results/planner.json, docs/figures/planner.png, the table on stdout.
bench-plan: $(STAMP)
	nice -n 10 $(BIN)/python -m benchmarks.planner --settings gridworld-demo,gridworld-spread,cartpole-10,cartpole-100

# Asynchronous (buffered) against synchronous rounds in process on the counted clock: every
# figure is a function of the seed, so it runs at low priority. BENCHMARKS.md "Asynchronous
# rounds"; benchmarks/results/async_rounds.json, docs/figures/async_rounds.png.
bench-async: $(STAMP)
	nice -n 10 $(BIN)/python -m benchmarks.async_rounds
	nice -n 10 $(BIN)/python -m benchmarks.async_rounds --setups cartpole-k100 --seeds 5 \
		--results benchmarks/results/async_rounds_k100.json \
		--figure docs/figures/async_rounds_k100.png

# Privacy (docs/privacy.md): CartPole K = 100 at ε = 1, 4, 8 against the non-private run,
# 5 seeds (a few minutes); secure aggregation's cost per round, the protocol alone and
# fedhpg-run on loopback at K = 10, 100, 1,000. BENCHMARKS.md "Privacy";
# benchmarks/results/privacy_*.json, docs/figures/privacy_utility.png.
bench-privacy: $(STAMP)
	nice -n 10 $(BIN)/python -m benchmarks.privacy --part utility
	nice -n 10 $(BIN)/python -m benchmarks.privacy --part overhead
	nice -n 10 $(BIN)/python -m benchmarks.privacy --part wire

bench-robustness: $(STAMP)
	$(BIN)/python -m benchmarks.robustness
	$(BIN)/python -m benchmarks.fedpgbr

bench: $(STAMP)
	$(BIN)/python -m benchmarks.run_all | tee benchmarks/latest.md

clean:
	rm -rf $(VENV) build *.egg-info .pytest_cache .ruff_cache
