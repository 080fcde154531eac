# SDfR developer entry points.  `make test` works on a fresh clone: every
# target that needs Python depends on the bootstrap stamp.
SHELL := /bin/bash
.SHELLFLAGS := -eu -o pipefail -c

VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed
# netlab/ may not exist yet in a fresh clone
LINT_PATHS := $(wildcard sdfr netlab tests bench)

.PHONY: venv test test-py310 test-vms test-netem test-radio check fmt bench bench-events bench-auth bench-flood bench-traffic bench-paper bench-footprint bench-peers bench-scale bench-scale-hosts netlab image compose-up compose-down clean distclean

$(STAMP): pyproject.toml
	bash scripts/bootstrap.sh

venv:
	bash scripts/bootstrap.sh

# The unit tests (CPU-bound, no timing) on every core (pytest-xdist); then the tiers that
# run fleets, one test at a time (their deadlines and figures assume the machine is theirs).
# Each tier's start time is printed (UTC), so that a run's log says where its time went.
test: $(STAMP)
	@date -u '+make test: %T the unit tests'
	$(BIN)/pytest -q -n auto --maxprocesses=4 --durations=10 tests/unit
	@date -u '+make test: %T the host tier'
	$(BIN)/pytest -q --durations=30 tests/ --ignore=tests/unit
	@date -u '+make test: %T the Python 3.10 tier'
	$(MAKE) --no-print-directory test-py310
	@date -u '+make test: %T the VM tiers'
	$(MAKE) --no-print-directory test-vms
	@date -u '+make test: %T done'

# The Python 3.10 tier (Ubuntu 22.04 / ROS 2 Humble / Jetson): the unit tests and fleet tests
# under 3.10 in .venv310. Fails if no 3.10 can be had; SDFR_SKIP_PY310=1 skips it, saying so.
test-py310: $(STAMP)
	bash scripts/py310.sh

# Both VM tiers at once: each VM emulates one CPU, so on 2 cores they run side by side, once
# the host's tiers (whose deadlines assume the machine is theirs) are done. Each tier's output
# comes whole when it ends; either failing fails this. The radio tier takes four times the
# netem tier, but sharing its tests between both VMs (each busy to the end) made each guest
# about twice as slow and its fleets miss their deadlines (2026-11-29: CONTRIBUTING.md).
test-vms: $(STAMP)
	$(MAKE) --no-print-directory -j2 --output-sync=target test-netem test-radio

# The netem tier: tests/netem in a Debian kernel under virtme-ng (this kernel has no
# sch_netem). Fails if the VM cannot run; SDFR_SKIP_VM=1 skips it, saying so.
test-netem: $(STAMP)
	bash scripts/vm.sh netem

# The radio tier: tests/radio in the same kind of VM, with mac80211_hwsim: robots on 802.11
# radios, each sdfrd joining the fleet's WiFi itself. SDFR_SKIP_RADIO=1 skips it, saying so.
test-radio: $(STAMP)
	bash scripts/vm.sh radio

check: $(STAMP)
	$(BIN)/ruff check $(LINT_PATHS)
	$(BIN)/ruff format --check $(LINT_PATHS)
	$(BIN)/mypy --strict sdfr netlab bench

fmt: $(STAMP)
	$(BIN)/ruff check --fix $(LINT_PATHS)
	$(BIN)/ruff format $(LINT_PATHS)

# A bench's recipe: `$(call run-bench,NAME ARGS)` makes runs/ (where benches write their JSON),
# then runs `python -m bench.NAME ARGS`.
# A comma inside a $(call ...) argument.
, := ,

define run-bench
mkdir -p runs
$(BIN)/python -m bench.$(1)
endef

bench: $(STAMP)
	$(call run-bench,api_latency | tee runs/bench-api.json)
	$(MAKE) --no-print-directory bench-events
	$(MAKE) --no-print-directory bench-auth
	$(MAKE) --no-print-directory bench-flood
	$(MAKE) --no-print-directory bench-traffic
	$(MAKE) --no-print-directory bench-footprint
	$(BIN)/python -m bench.scale --quick --robots 10,50 --out runs/bench-scale-quick.json --plot runs/scale-growth-quick.png

# What one sdfrd costs a robot: RSS, PSS, USS and PSS alone of each process with 100 services
# published and 20 peers known; idle CPU of 7 robots x 10 services at the 10 s beacon, with
# python-zeroconf doing the same job in the same lab (~6 min; root). runs/bench-footprint.json.
bench-footprint: $(STAMP)
	$(call run-bench,footprint --profile > /dev/null)

# SDfR beside what robotics teams use instead (bench/peers.py: python-zeroconf, Avahi, Zenoh,
# ROS 2 on Fast DDS at its default and a 3 s lease), every system at once on one lab, 70
# services a robot under the paper's churn, 6 robots, clean and at 10 % loss on every pair
# (~40 min; root; installs Avahi and the ROS 2 wheels when missing). Avahi and python-zeroconf
# share UDP 5353, so they run in two labs, Zenoh and DDS in both. runs/bench-peers.json and
# runs/bench-peers-avahi.json; a Markdown table and JSON per run in runs/side-by-side-*/.
# (20 robots: `--robots 6,20`; every system at once overloads 2 cores.)
bench-peers: $(STAMP)
	$(call run-bench,side_by_side --robots 6 --loss 0$(,)10 --peers zeroconf$(,)zenoh$(,)dds$(,)dds-lease3s --out runs/bench-peers.json)
	$(call run-bench,side_by_side --robots 6 --loss 0$(,)10 --peers avahi$(,)zenoh$(,)dds$(,)dds-lease3s --out runs/bench-peers-avahi.json)

# 10, 50 and 100 robots with real daemons in one lab (scenario scale-100), 2 minutes of stay
# each: set-up, convergence, CPU and PSS per daemon, bytes per robot on the air, and how they
# grow with n (~12 min; root). runs/bench-scale.json and docs/scale-growth.png.
bench-scale: $(STAMP)
	$(call run-bench,scale > /dev/null)

# scale-300 on a lab across 3 hosts simulated on this machine (namespaces with their own sshd,
# driven over ssh), then the same scenario on one host, for comparison (~12 min; root).
# runs/bench-scale-hosts.json and runs/bench-scale-300.json.
bench-scale-hosts: $(STAMP)
	$(call run-bench,scale --hosts 3 --robots 300 --out runs/bench-scale-hosts.json --plot runs/scale-hosts.png)
	$(call run-bench,scale --scenario scale-300 --robots 300 --out runs/bench-scale-300.json --plot runs/scale-300.png)

# What GET /events costs: the event log's append and size, change -> subscriber latency for
# 1, 16 and 64 streams, the API layer's CPU (~30 s); JSON in runs/bench-events.json.
bench-events: $(STAMP)
	$(call run-bench,events)

# What authenticated datagrams cost: bytes and CPU per datagram, signed vs unsigned, and a
# 6-robot fleet's bytes open vs keyed (a few seconds); JSON in runs/bench-auth.json.
bench-auth: $(STAMP)
	$(call run-bench,auth > /dev/null)

# A flood of 10,000 fake robots at 5,000 datagrams/s for 60 s against a real daemon of an
# open fleet: its CPU, memory, /neighbors latency and pings, idle vs flooded (~2 min; root).
bench-flood: $(STAMP)
	$(call run-bench,flood)

# SDfR's bytes per robot over 5 minutes at the 10 s beacon, fleets of 2, 4 and 6 at once
# (~6 min); JSON on stdout and in runs/bench-traffic.json, a table on stderr.
bench-traffic: $(STAMP)
	$(call run-bench,traffic)

# The paper's evaluation under its load (section 6, figures 4-6): static 2/4/6 robots x 30/50/70 %
# publishers and the dynamic scenario, 5 minutes each, then python-zeroconf side by side and the
# bytes per robot at 2, 6 and 20 robots (~80 min; ARGS=--quick: ~10 min); root. One run folder
# runs/bench-paper-<time>/ with the figures (PNG and JSON); the result in runs/bench-paper.json.
bench-paper: $(STAMP)
	$(call run-bench,paper --out runs/bench-paper.json $(ARGS) > /dev/null)

netlab: $(STAMP)
	$(BIN)/python -m netlab.demo

# The robot image sdfr-robot:<version> from this checkout (installs and starts Docker's
# engine when missing; builds a Debian base when no registry can be reached).
image: $(STAMP)
	bash scripts/image.sh

# A compose fleet of ROBOTS robot containers on this host (compose/compose.yaml).
ROBOTS ?= 3
compose-up: image
	bash scripts/compose.sh up $(ROBOTS)

# Remove the compose fleet: its containers, network and volumes.
compose-down:
	bash scripts/compose.sh down

# The ROS node's environments: .venv/ros2 (ROS 2 wheels from PyPI, sdfr_msgs built with cmake)
# and .venv/ros1 (Debian's ROS 1, sdfr_msgs generated with genpy). Idempotent; root for apt.
.PHONY: ros-setup test-ros bench-ros test-hosts

# Labs across hosts alone (make test runs them too, in the host tier): hosts simulated as
# namespaces with their own sshd, reached over ssh (netlab/hostsim.py; root, openssh-server).
test-hosts: $(STAMP)
	$(BIN)/pytest -q tests/ns/test_hostsim.py tests/ns/test_span.py tests/ns/test_hosts.py \
		tests/ns/test_lab_across_hosts.py
ros-setup: $(STAMP)
	bash scripts/ros2-setup.sh
	bash scripts/ros1-setup.sh

# The two ROS tiers alone (make test runs them too; SDFR_SKIP_ROS=1 skips them).
test-ros: $(STAMP)
	$(BIN)/pytest -q tests/ros

# Latency from ~/publish on one robot to the change on ~/neighbors of another, p50 over 50
# changes, two netlab robots under ROS 2 (~1 min; root); JSON in runs/bench-ros.json.
bench-ros: $(STAMP) ros-setup
	$(call run-bench,ros_latency)

clean:
	find . -path ./$(VENV) -prune -o -type d -name __pycache__ -exec rm -rf {} +
	rm -rf .pytest_cache .mypy_cache .ruff_cache .hypothesis build dist

distclean: clean
	rm -rf $(VENV) .venv310 runs *.egg-info
