#!/usr/bin/env bash
# The wheels of dist/ (`make wheels`) in a clean venv, as a user without Rust gets them: installs
# dinerdash[server], dinerdash-server and dinerdash-agents from the wheel files (not editable; their
# dependencies from the package registry), then, from an empty folder (no source tree on
# sys.path), with a PATH that holds the venv and the system's basic tools but no cargo:
#   - gymnasium.make("dinerdash:DinerDash-v0", expert=True) with no address plays one expert
#     episode on the server the wheel installed (the client starts it, and stops it);
#   - dinerdash-server eval --policy expert --episodes 3;
#   - python -m dinerdash evaluate --episodes 3;
#   - python -m dinerdash_agents evaluate on a committed checkpoint;
#   - dinerdash-server --version, python -m dinerdash_server --version and the three packages'
#     versions agree.
# Prints the install time and the checks' time. Usage: scripts/wheel_smoke.sh [DIST_DIR]
set -euo pipefail

root="$(cd "$(dirname "$0")/.." && pwd)"
dist="$(cd "${1:-$root/dist}" && pwd)"
python="${PYTHON:-python3}"
checkpoint="$root/docs/results/checkpoints/bc-70"

one_wheel() {
    local matches=("$dist"/$1)
    if [ "${#matches[@]}" -ne 1 ] || [ ! -f "${matches[0]}" ]; then
        echo "wheel-smoke: expected one $1 in $dist, found: ${matches[*]}" >&2
        exit 1
    fi
    echo "${matches[0]}"
}
server_whl="$(one_wheel 'dinerdash_server-*.whl')"
client_whl="$(one_wheel 'dinerdash-*-py3-none-any.whl')"
agents_whl="$(one_wheel 'dinerdash_agents-*-py3-none-any.whl')"

work="$(mktemp -d)"
trap 'rm -rf "$work"' EXIT
venv="$work/venv"
mkdir "$work/run"
cp -r "$checkpoint" "$work/run/checkpoint"

# PATH: only the venv and the basic tools (no cargo, no pyenv shims, no repository scripts); no
# Python path or venv inherited, no DINERDASH_* choosing a server (the machine's certificate and
# pip settings stay).
smoke_path="$venv/bin:/usr/bin:/bin"
in_venv() {
    (cd "$work/run" && env -u PYTHONPATH -u PYTHONHOME -u VIRTUAL_ENV -u DINERDASH_SERVER \
        -u DINERDASH_ADDRESS -u DINERDASH_AUTH_TOKEN -u DINERDASH_TLS_CA -u DINERDASH_TIMEOUT \
        PATH="$smoke_path" "$@")
}
if in_venv sh -c 'command -v cargo' >/dev/null; then
    echo "wheel-smoke: cargo is on the smoke PATH ($smoke_path); it must not be" >&2
    exit 1
fi

echo "== wheel-smoke: install $(basename "$client_whl")[server], $(basename "$server_whl"), $(basename "$agents_whl")"
start=$(date +%s.%N)
"$python" -m venv "$venv"
in_venv python -m pip install --quiet "$client_whl[server]" "$server_whl" "$agents_whl"
installed=$(date +%s.%N)

echo "== wheel-smoke: gymnasium.make with no address, on the bundled server"
in_venv python - "$venv" "$root" <<'EOF'
import os
import sys
from importlib.metadata import version

import dinerdash
import dinerdash_agents
import dinerdash_server
import gymnasium
from dinerdash.server import find_server_binary

venv, root = (os.path.realpath(p) for p in sys.argv[1:])
for module in (dinerdash, dinerdash_agents, dinerdash_server):
    where = os.path.realpath(module.__file__)
    assert where.startswith(venv) and not where.startswith(root + os.sep), where
assert not [p for p in sys.path if p and os.path.realpath(p).startswith(root + os.sep)], sys.path
binary = find_server_binary()
assert os.path.realpath(binary) == os.path.realpath(dinerdash_server.find_binary()), binary
assert os.path.realpath(binary).startswith(venv), binary
versions = {name: version(name) for name in ("dinerdash", "dinerdash-server", "dinerdash-agents")}
assert len(set(versions.values())) == 1 and dinerdash.__version__ == versions["dinerdash"], versions

env = gymnasium.make("dinerdash:DinerDash-v0", expert=True)
try:
    server = env.unwrapped.server
    _, info = env.reset(seed=0)
    steps, total, done = 0, 0.0, False
    while not done and steps < 100_000:
        _, reward, terminated, truncated, info = env.step(info["expert_action"])
        steps, total, done = steps + 1, total + float(reward), terminated or truncated
    assert done, f"the expert episode did not end within {steps} steps"
    assert server is not None and os.path.realpath(server.binary) == os.path.realpath(binary)
finally:
    env.close()
assert not server.is_running()
print(f"one expert episode on {binary}: {steps} steps, return {total:g}; versions {versions}")
EOF

echo "== wheel-smoke: dinerdash-server --version, python -m dinerdash_server --version"
want="dinerdash-server $(in_venv python -c 'import dinerdash; print(dinerdash.__version__)')"
for got in "$(in_venv dinerdash-server --version)" "$(in_venv python -m dinerdash_server --version)"; do
    if [ "$got" != "$want" ]; then
        echo "wheel-smoke: '$got', want '$want'" >&2
        exit 1
    fi
done
echo "$want"

echo "== wheel-smoke: dinerdash-server eval --policy expert --episodes 3"
in_venv dinerdash-server eval --policy expert --episodes 3

echo "== wheel-smoke: python -m dinerdash evaluate --episodes 3"
in_venv python -m dinerdash evaluate --episodes 3 --num-envs 3

echo "== wheel-smoke: python -m dinerdash_agents evaluate (docs/results/checkpoints/bc-70)"
in_venv python -m dinerdash_agents evaluate checkpoint --episodes 3 --num-envs 3

done_at=$(date +%s.%N)
awk -v a="$start" -v b="$installed" -v c="$done_at" 'BEGIN {
    printf "wheel-smoke: install %.1f s (venv + pip), checks %.1f s\n", b - a, c - b }'
# install, the episode, the versions, eval, evaluate, the agents' evaluate; any failure exits above.
echo "wheel-smoke: 6 passed, 0 failed"
