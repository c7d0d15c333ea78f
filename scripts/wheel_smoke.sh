#!/usr/bin/env bash
# The wheels of dist/ (`make wheels`) in a clean venv, as a user without Rust gets them: installs
# dinerdash[server], dinerdash-server and dinerdash-agents from the wheel files (not editable; their
# dependencies from the package registry), then, from an empty folder (no source tree on
# sys.path), with a PATH that holds the venv and the system's basic tools but no cargo:
#   - gymnasium.make("dinerdash:DinerDash-v0", expert=True) with no address plays one expert
#     episode on the server the wheel installed (the client starts it, and stops it);
#   - dinerdash-server eval --policy expert --episodes 3;
#   - python -m dinerdash evaluate --episodes 3 --seed 0;
#   - python -m dinerdash_agents evaluate on a committed checkpoint;
#   each checked against the known scores (the game is deterministic for a seed): the expert's
#   seeds 0..2 (EXPERT_SCORES), the checkpoint's seeds 1000..1002 as docs/results/results.json
#   reports them;
#   - dinerdash-server --version, python -m dinerdash_server --version and the three packages'
#     versions agree;
#   - the client's wheel holds no bench, and `python -m dinerdash bench` without dinerdash-bench
#     fails naming the pip command; with the dinerdash-bench wheel installed, a short bench runs.
# Prints the install time and the checks' time. Usage: scripts/wheel_smoke.sh [DIST_DIR]
set -euo pipefail

root="$(cd "$(dirname "$0")/.." && pwd)"
dist="$(cd "${1:-$root/dist}" && pwd)"
python="${PYTHON:-python3}"
checkpoint="$root/docs/results/checkpoints/bc-70"
# The reference expert's final scores on seeds 0, 1, 2 (ruleset v0; `dinerdash-server eval
# --policy expert --episodes 3` prints their mean, 5700.0).
EXPERT_SCORES="[5240, 5600, 6260]"
# bc-70's on seeds 1000..1002, from the results table's per-episode scores.
checkpoint_scores="$("$python" -c 'import json, sys
rows = json.load(open(sys.argv[1]))["agents"]
print([row["scores"][:3] for row in rows if row["name"] == "bc-70"][0])' "$root/docs/results/results.json")"

# The last line of a command's output is its --json; its "scores" must be $1.
check_scores() {
    local want="$1" out got
    shift
    out="$(in_venv "$@")"
    printf '%s\n' "$out"
    got="$(printf '%s\n' "$out" | tail -n 1 | "$python" -c 'import json, sys; print(json.load(sys.stdin)["scores"])')"
    if [ "$got" != "$want" ]; then
        echo "wheel-smoke: $*: scores $got, want $want" >&2
        exit 1
    fi
}

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
bench_whl="$(one_wheel 'dinerdash_bench-*-py3-none-any.whl')"

# The bench is a package of its own (dinerdash-bench): the client's wheel holds none of it.
"$python" - "$client_whl" <<'EOF'
import sys
import zipfile

names = zipfile.ZipFile(sys.argv[1]).namelist()
bench = [n for n in names if n.startswith("dinerdash/bench") or "dinerdash_bench" in n]
assert not bench, f"the client's wheel holds the bench: {bench}"
assert "dinerdash/cli.py" in names, names
EOF
echo "wheel-smoke: $(basename "$client_whl") holds no bench"

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
    # Seed 0's expert episode, as every build of ruleset v0 plays it.
    assert (steps, total, info["score"]) == (365, 5240.0, 5240), (steps, total, info["score"])
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
eval_out="$(in_venv dinerdash-server eval --policy expert --episodes 3)"
echo "$eval_out"
if ! printf '%s\n' "$eval_out" | grep -q '^score  5700.0 '; then
    echo "wheel-smoke: dinerdash-server eval: the expert's mean on seeds 0..2 is not 5700.0" >&2
    exit 1
fi

echo "== wheel-smoke: python -m dinerdash evaluate --episodes 3 --seed 0"
check_scores "$EXPERT_SCORES" python -m dinerdash evaluate --episodes 3 --seed 0 --num-envs 3 --json

echo "== wheel-smoke: python -m dinerdash_agents evaluate (docs/results/checkpoints/bc-70)"
check_scores "$checkpoint_scores" python -m dinerdash_agents evaluate checkpoint --episodes 3 \
    --seed 1000 --num-envs 3 --json

echo "== wheel-smoke: python -m dinerdash bench, without and with dinerdash-bench"
if out="$(in_venv python -m dinerdash bench 2>&1)" || ! grep -q 'pip install dinerdash-bench' <<<"$out"; then
    echo "wheel-smoke: python -m dinerdash bench without dinerdash-bench: $out" >&2
    exit 1
fi
echo "$out"
in_venv python -m pip install --quiet "$bench_whl"
out="$(in_venv python -m dinerdash bench --steps 0 --vec-steps 0 --reference-steps 1000 \
    --no-transports --no-scaling --sb3-steps 0)"
echo "$out"
if ! grep -q '^reference .* steps/s' <<<"$out"; then
    echo "wheel-smoke: python -m dinerdash bench printed no reference line" >&2
    exit 1
fi

done_at=$(date +%s.%N)
awk -v a="$start" -v b="$installed" -v c="$done_at" 'BEGIN {
    printf "wheel-smoke: install %.1f s (venv + pip), checks %.1f s\n", b - a, c - b }'
# the wheel without the bench, install, the episode, the versions, eval, evaluate, the agents'
# evaluate, bench without and with its package; any failure exits above.
echo "wheel-smoke: 9 passed, 0 failed"
