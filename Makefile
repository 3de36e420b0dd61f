# The two commands a newcomer needs: `make demo` and `make test`. Both set up everything themselves.
PY := .venv/bin/python
# The suite's processes (xdist workers and the services they start) keep the memory they free: glibc
# otherwise gives each large block (numpy temporaries of tens of MB: clouds, rays, images) back to the
# kernel on free and faults its pages in again on the next allocation, and page faults are dear on these
# VMs. Measured on 2 cores: `make test-unit`'s tests 101.1 -> 85.1 s, system CPU 26.8 -> 15.3 s; with 4 GiB
# thresholds (no array comes near 1 GiB) the in-process tier 182.9 -> 156.7 s (system CPU 67.5 -> 27.6 s)
# and the system tier 134.3 -> 130.8 s (43.7 -> 30.5 s). For test runs only: a long-running service would
# keep its peak's memory resident, which the tests' short lives do not mind.
PYTEST := MALLOC_MMAP_THRESHOLD_=1073741824 MALLOC_TRIM_THRESHOLD_=1073741824 MALLOC_TOP_PAD_=268435456 $(PY) -m pytest
RENDERERS ?= 1
# ROBOT=ros2: robot-io's ros2 backend against the ROS 2 stand-in robot, in ROS2_KEYS style (bridge | rmw_zenoh).
ROBOT ?= sim
ROS2_KEYS ?= bridge
# ROS2_MOTION=nav2: move_to/turn/look_around as Nav2 goals (NavigateToPose, Spin) instead of cmd_vel.
ROS2_MOTION ?= cmdvel
# ROS2_DRIFT=1: the stand-in's odometry drifts (the noisy robot's drift) and it has no localiser; the
# mapper's own localiser corrects the map (issue 33).
ROS2_DRIFT ?=
# ROBOTS=N: robot0..robotN-1 at once (a robot-io and a gateway each; planner, mapper, renderer and
# reconstructor shared by all), for `make demo` (each robot in its own generated house) and `make eval`.
ROBOTS ?= 1

# Every interpreter these targets start (the xdist workers, each service, each launcher) keeps the
# bytecode it compiles, in the clone's git-ignored __pycache__, even where the environment says not to
# (PYTHONDONTWRITEBYTECODE=1 on the CI machines): otherwise each one compiles the repo's modules again
# and pytest rewrites every test module's asserts again in each worker of each tier (~4 s CPU a worker).
unexport PYTHONDONTWRITEBYTECODE

.PHONY: setup demo up test test-unit test-contract test-e2e test-system bench reliability clean eval eval-set eval-presets eval-preset-cloud eval-preset-anticipation eval-preset-hfov eval-preset-policies

setup:
	@bash deploy/bootstrap.sh

demo: setup
	$(PY) -m deploy.demo --renderers $(RENDERERS) --robot $(ROBOT) --ros2-keys $(ROS2_KEYS) --ros2-motion $(ROS2_MOTION) --robots $(ROBOTS) $(if $(ROS2_DRIFT),--drift)

# The whole system until Ctrl-C: prints the dashboard URL and the API token (PORT=8080 SCENE=generated:0).
PORT ?= 8080
SCENE ?= generated:0
up: setup
	$(PY) -m deploy.up --port $(PORT) --scene $(SCENE) --renderers $(RENDERERS)

# Both runs use XDIST's workers (pytest-xdist; `make test XDIST=` runs them in one process). loadgroup keeps
# each file on one worker (its module fixtures are built once) and gives the costly session fixtures one
# group each (tests/conftest.py). The `system` tests run after the in-process ones, in a run of their own:
# the tests of the launched system (the `system` fixture) one after another on one worker, the tests that
# start processes of their own on the other. Two at once on two cores: 241 -> 169 s of wall time for
# 209 -> 236 s of CPU (issue 31; they wait on their children part of the time, not all of it).
XDIST ?= -n 2 --dist loadgroup

# The long variants (marked slow: more fuzz cases, repeated kills) run in `make reliability`.
# Two runs, exactly the in-process tiers and then test-system; both always run, and either failing fails it.
test: setup
	@rc=0; \
	$(PYTEST) -q -m "not slow and not system" $(XDIST) --durations=25 tests || rc=$$?; \
	$(PYTEST) -q -m "system and not slow" $(XDIST) --durations=25 tests || rc=$$?; \
	exit $$rc

# The tiers: unit (pure logic, in-process), contract (real zenoh peers in this process), e2e (real
# HTTP servers, browsers, in-process services, the reliability suite's in-process system), system (tests
# that start OS processes: a launcher, a router, services, a helper program; marked `system`, wherever they
# live; one launched system is shared by the session). Together they are exactly `make test`.
test-unit: setup
	$(PYTEST) -q -m "not slow and not system" $(XDIST) --durations=15 tests/unit

test-contract: setup
	$(PYTEST) -q -m "not slow and not system" $(XDIST) --durations=15 tests/contract

test-e2e: setup
	$(PYTEST) -q -m "not slow and not system" $(XDIST) --durations=15 tests/e2e tests/integration tests/reliability

test-system: setup
	$(PYTEST) -q -m "system and not slow" $(XDIST) --durations=15 tests

bench: setup
	$(PY) -m bench

reliability: setup
	$(PY) -m bench.reliability

clean:
	rm -rf runs .pytest_cache

# Evaluation: `make eval` generates the evaluation set once (100 episodes, 5 houses, 1-2 floors), starts
# the system, runs it and prints the table; interrupted runs resume. EPISODES=<R2R-CE .json.gz> runs any file.
# ROBOTS=N starts robot0..robotN-1 (shared planner/mapper/renderer/reconstructor) and runs their shards of
# scenes concurrently.
EVAL_SET := runs/eval/generated.json.gz
EPISODES ?= $(EVAL_SET)
POLICY ?= heuristic
MAP_SOURCE ?= reconstructed
EVAL_OUT ?= runs/eval
EVAL_ARGS ?=

$(EVAL_SET):
	$(PY) -m evaluation generate --out $@ --houses 5 --per-house 20 --floors 1,2 --seed 0

eval-set: setup $(EVAL_SET)

eval: setup $(EPISODES)
	$(PY) -m evaluation run --episodes $(EPISODES) --policy $(POLICY) --map-source $(MAP_SOURCE) --out $(EVAL_OUT)/$(POLICY)-$(MAP_SOURCE) --maps $(EVAL_OUT)/maps.json --robots $(ROBOTS) $(EVAL_ARGS)

eval-presets: setup $(EPISODES)
	$(PY) -m evaluation preset all --episodes $(EPISODES) --policy $(POLICY) --out $(EVAL_OUT)/presets-$(POLICY) --maps $(EVAL_OUT)/maps.json --robots $(ROBOTS) $(EVAL_ARGS)

eval-preset-cloud eval-preset-anticipation eval-preset-hfov eval-preset-policies: setup $(EPISODES)
	$(PY) -m evaluation preset $(@:eval-preset-%=%) --episodes $(EPISODES) --policy $(POLICY) --out $(EVAL_OUT)/presets-$(POLICY) --maps $(EVAL_OUT)/maps.json --robots $(ROBOTS) $(EVAL_ARGS)
