# ebmpc: the two commands of the README, and their parts.
#   make demo   learn cartpole swing-up from scratch: planner daemon + MuJoCo sim-bridge over Zenoh
#   make test   the whole test suite (what CI runs)
#   make docs   the book (docs/, mdBook) and the Python API reference, into target/book/

SHELL := /bin/bash
CARGO ?= cargo
MUJOCO_LIB := .mujoco/lib/libmujoco.so

# Demo knobs: `make demo TASK=cartpole EPISODES=10 SEED=0 METHOD=cem+deen`
TASK ?= cartpole
EPISODES ?= 10
SEED ?= 0
METHOD ?= cem+deen

.PHONY: demo test mujoco python-env toolchain lint fmt docs protoc etcd

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

# The dependencies of the ebmpc Python package (python/), of its tests (eclipse-zenoh, pytest,
# jsonschema, mypy) and of its Gymnasium driver (gymnasium[mujoco]: Gymnasium and the PyPI mujoco
# wheel): its tests, the Python example's and the Gymnasium driver's run through `cargo test`
# with it, importing the package from python/. (The wheel itself, which bundles the planner, is
# built and installed into a clean venv by tests/tests/e2e/gym_driver.rs.)
VENV := .venv

python-env:
	bash examples/setup-python.sh "$(CURDIR)/$(VENV)"

test: toolchain mujoco python-env etcd
	$(CARGO) build --workspace --bins
	EBMPC_PYTHON="$(CURDIR)/$(VENV)/bin/python" $(CARGO) test --workspace --no-fail-fast

lint: toolchain mujoco protoc
	$(CARGO) fmt --all -- --check
	$(CARGO) clippy --workspace --all-targets -- -D warnings
	RUSTDOCFLAGS="-D warnings" $(CARGO) doc --workspace --no-deps

fmt:
	$(CARGO) fmt --all

# The book and the Python API reference (pdoc, from the package's docstrings), with the tools
# python-env installs into .venv/. `make test` checks the same (tests/tests/docs.rs).
docs: python-env
	PATH="$(CURDIR)/$(VENV)/bin:$(CURDIR)/$(VENV)/site/bin:$$PATH" mdbook build
	PYTHONPATH="$(CURDIR)/python" $(VENV)/bin/python -m pdoc --docformat restructuredtext \
	    -o target/book/python-api ebmpc $(subst /,.,$(patsubst python/%.py,%,$(filter-out %/__init__.py,$(wildcard python/ebmpc/*.py))))
	@echo "the book: target/book/index.html"
