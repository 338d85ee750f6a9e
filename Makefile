# ebmpc: the two commands of the README, and their parts.
#   make demo   learn cartpole swing-up from scratch: planner daemon + MuJoCo sim-bridge over Zenoh
#   make test   the whole test suite (what CI runs)

SHELL := /bin/bash
CARGO ?= cargo
MUJOCO_LIB := .mujoco/lib/libmujoco.so

# Demo knobs: `make demo TASK=cartpole EPISODES=10 SEED=0 METHOD=cem+deen`
TASK ?= cartpole
EPISODES ?= 10
SEED ?= 0
METHOD ?= cem+deen

.PHONY: demo test mujoco python-env toolchain lint fmt protoc etcd

toolchain:
	@command -v $(CARGO) >/dev/null || { echo "error: cargo not found: install Rust 1.95+ (https://rustup.rs) first" >&2; exit 1; }

$(MUJOCO_LIB): deploy/install-mujoco.sh
	bash deploy/install-mujoco.sh

mujoco: $(MUJOCO_LIB)

# Debian packages: protoc for the build (the etcd client compiles etcd's gRPC definitions), and
# etcd for the fleet tests (single daemons never need it). Installed only when missing.
protoc:
	bash deploy/install-debian-packages.sh protoc

etcd:
	bash deploy/install-debian-packages.sh protoc etcd

demo: toolchain mujoco protoc
	$(CARGO) build --release --bins
	TASK=$(TASK) EPISODES=$(EPISODES) SEED=$(SEED) METHOD=$(METHOD) bash deploy/demo.sh

# The ebmpc Python package (python/) with its test dependencies (eclipse-zenoh, pytest, jsonschema,
# mypy) and its Gymnasium driver's (gymnasium[mujoco]: Gymnasium and the PyPI mujoco wheel): its
# tests, the Python example's and the Gymnasium driver's run through `cargo test` with it.
VENV := .venv

python-env:
	bash examples/setup-python.sh "$(CURDIR)/$(VENV)"

test: toolchain mujoco python-env etcd
	$(CARGO) build --workspace --bins
	EBMPC_PYTHON="$(CURDIR)/$(VENV)/bin/python" $(CARGO) test --workspace --no-fail-fast

lint: toolchain mujoco protoc
	$(CARGO) fmt --all -- --check
	$(CARGO) clippy --workspace --all-targets -- -D warnings

fmt:
	$(CARGO) fmt --all
