# The project's entry points. `make serve` starts the server, `make test` runs every test.
# Needs only Rust (cargo) and Python 3.10+; everything else is installed here, into .venv.

PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
SERVER := target/release/dinerdash-server

.PHONY: serve build build-server test test-rust test-python test-agents lint bench bench-rllib soak chaos docker-smoke k8s-validate venv clean wheels wheel-smoke cross-check

## Start the gRPC server on port 50051 (Ctrl-C stops it).
serve:
	cargo run --release -p dinerdash-server -- --port 50051

## The server binary alone: the same command the docker image builds with.
build-server:
	cargo build --release --locked -p dinerdash-server --bin dinerdash-server

# The server and every test target (what `cargo test --release` runs). The criterion benches are
# built by `make bench` when run; `make lint`'s clippy checks them (--all-targets) on every CI run.
build: build-server
	cargo build --release --locked --workspace --tests

# The sb3 extra (stable-baselines3, sb3-contrib) is for tests/test_sb3.py; it brings torch from
# PyPI, a large download (2-3 minutes the first time). The ray extra (Ray with RLlib, which pins
# gymnasium 1.2.x) is for tests/test_ray.py; the torchrl extra (TorchRL, on the same torch) for
# tests/test_torchrl.py; the minari extra for the Minari dataset test of tests/test_rollout_cli.py.
# In CI (CI set) a skipped test fails (tests/conftest.py): every extra must be here.
$(VENV)/.installed: client-py/pyproject.toml agents/pyproject.toml bench/pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -e 'client-py[dev,sb3,ray,torchrl,minari]' -e 'agents[dev]' -e bench
	touch $@

venv: $(VENV)/.installed

# The wheels' build tools (maturin, ziglang, auditwheel), apart from the development venv.
BUILD_VENV := .build-venv
$(BUILD_VENV)/.installed: scripts/build-requirements.txt
	$(PYTHON) -m venv $(BUILD_VENV)
	$(BUILD_VENV)/bin/python -m pip install --quiet -r scripts/build-requirements.txt
	touch $@

## dist/: the dinerdash-server wheel (the release binary, stripped; manylinux2014 linked by zig)
## and its sdist, and the pure-Python wheels of dinerdash, dinerdash-agents and dinerdash-bench;
## all one version.
## SERVER_WHEEL_FLAGS= (empty) builds a wheel for this machine's glibc with the system linker.
## Built in target/wheels, so that it never waits for (or holds up) a cargo command on target/.
SERVER_WHEEL_FLAGS ?= --zig --compatibility manylinux2014
wheels: $(BUILD_VENV)/.installed
	$(BUILD_VENV)/bin/python scripts/version.py check
	rm -rf dist
	CARGO_TARGET_DIR="$(abspath target/wheels)" PATH="$(abspath $(BUILD_VENV))/bin:$$PATH" \
		maturin build --release -m server/Cargo.toml $(SERVER_WHEEL_FLAGS) --out dist
	PATH="$(abspath $(BUILD_VENV))/bin:$$PATH" maturin sdist -m server/Cargo.toml --out dist
	$(BUILD_VENV)/bin/python -m pip wheel --quiet --no-deps --wheel-dir dist ./client-py ./agents ./bench
	if [ "$$(uname)" = Linux ]; then $(BUILD_VENV)/bin/auditwheel show dist/dinerdash_server-*.whl; fi
	ls -l dist

## The wheels in a clean venv, as a user without Rust installs them (scripts/wheel_smoke.sh).
wheel-smoke: wheels
	scripts/wheel_smoke.sh dist

## cargo check of the server for Windows, macOS and Linux aarch64 (needs their std: rustup
## target add); zig from .build-venv compiles ring's C (scripts/cross_check.sh).
cross-check: $(BUILD_VENV)/.installed
	scripts/cross_check.sh

## Every test: Rust unit, property, conformance and gRPC tests, the Python end-to-end tests, then
## the agents' tests (BC and DPGM against a local server).
test: test-rust test-python test-agents

test-rust: build
	cargo test --release --workspace

test-python: build venv
	DINERDASH_SERVER=$(abspath $(SERVER)) $(PY) -m pytest -q tests

test-agents: build-server venv
	DINERDASH_SERVER=$(abspath $(SERVER)) $(PY) -m pytest -q agents/tests

lint: venv
	cargo fmt --all -- --check
	cargo clippy --workspace --all-targets -- -D warnings
	RUSTDOCFLAGS="-D warnings" cargo doc --workspace --no-deps --document-private-items
	$(VENV)/bin/ruff check client-py tests agents bench scripts server/python docker
	scripts/buf_check.sh
	$(VENV)/bin/ruff format --check client-py tests agents bench scripts server/python docker

## Criterion benchmarks of the simulator and the gRPC service, then the Python client's bench
## (the dinerdash-bench package, bench/).
bench: build venv
	cargo bench -p dinerdash-server
	DINERDASH_SERVER=$(abspath $(SERVER)) $(PY) -m dinerdash bench

## RLlib PPO's env-steps/s: dinerdash.ray's batched entry point against RLlib's default
## vectorization, and the agents' JAX PPO, on one local server (scripts/bench_rllib.py).
bench-rllib: build-server venv
	DINERDASH_SERVER=$(abspath $(SERVER)) $(PY) scripts/bench_rllib.py

## Ten minutes of well-behaved trainers beside hostile clients against one server; prints the
## server's peak RSS, Step p50/p99, errors and sessions lost (SOAK_ARGS="--duration 60" to shorten).
soak: build-server venv
	$(PY) scripts/soak.py --server $(abspath $(SERVER)) $(SOAK_ARGS)

## Masked PPO across three local servers while a seeded monkey kills, hangs, black-holes, drains
## and restarts them every 10-20 s; prints steps, exceptions, failovers, rejoins, moves, truncated
## episodes and the final score beside an undisturbed run of the same seed and length
## (scripts/chaos.py; CHAOS_DURATION=120 to shorten, CHAOS_ARGS="--seed 1" for more).
CHAOS_DURATION ?= 180
chaos: build-server venv
	$(PY) scripts/chaos.py --server $(abspath $(SERVER)) --duration $(CHAOS_DURATION) \
		--undisturbed $(CHAOS_ARGS)

## The docker image end to end (needs a Docker engine with compose): build it, start three
## healthy replicas and run the example trainer over all three; exit status is the trainer's.
## The servers' token comes from docker/dinerdash.env, made here with a random one if missing,
## and their TLS certificate from docker/tls (below).
COMPOSE := docker compose -f docker/compose.yaml
docker/dinerdash.env:
	umask 077 && echo "DINERDASH_AUTH_TOKEN=$$(openssl rand -hex 32)" > $@

## The servers' TLS certificate and key (docker/tls, not in git): self-signed, naming every
## replica. The key is readable by the containers' user (a Compose secret keeps the file's mode);
## its folder is the invoking user's alone.
docker/tls/server.crt:
	mkdir -p docker/tls && chmod 700 docker/tls
	openssl req -x509 -newkey ec -pkeyopt ec_paramgen_curve:P-256 -nodes -days 365 \
		-subj /CN=dinerdash -keyout docker/tls/server.key -out $@ \
		-addext "subjectAltName=DNS:server1,DNS:server2,DNS:server3,DNS:dinerdash,DNS:localhost,IP:127.0.0.1"
	chmod 644 docker/tls/server.key

docker-smoke: docker/dinerdash.env docker/tls/server.crt
	$(COMPOSE) up --build --abort-on-container-exit --exit-code-from trainer; \
	status=$$?; $(COMPOSE) down; exit $$status

## The Kubernetes manifests against the API schemas of Kubernetes 1.27 and 1.37, strictly (no
## cluster needed): kubernetes-validate from PyPI, in a venv of its own (its schemas are 100 MB).
K8S_VENV := .k8s-venv
$(K8S_VENV)/.installed:
	$(PYTHON) -m venv $(K8S_VENV)
	$(K8S_VENV)/bin/python -m pip install --quiet 'kubernetes-validate==1.37.0'
	touch $@

k8s-validate: $(K8S_VENV)/.installed
	$(K8S_VENV)/bin/kubernetes-validate --strict -k 1.27.0 docker/k8s/*.yaml
	$(K8S_VENV)/bin/kubernetes-validate --strict -k 1.37.0 docker/k8s/*.yaml

clean:
	cargo clean
	rm -rf $(VENV) $(BUILD_VENV) $(K8S_VENV) dist
