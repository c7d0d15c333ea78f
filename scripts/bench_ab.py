"""Two clients' bench rows against one server, taking turns: is a client change no worse? A
benchmark, not a test; needs scipy (the agents' install has it)::

    git worktree add /tmp/before <rev>
    .venv/bin/python scripts/bench_ab.py --before /tmp/before --rounds 12

Each round runs, in a fresh process per side (its ``client-py`` and ``bench`` first on the path),
the bench harness's own single-env and vector-env rows over gRPC and shared memory, each the
median of three repetitions; the side that goes first alternates every round. It prints each
row's median over the rounds for both sides and the after/before ratio's geometric mean over the
rounds' pairs with its 95 % BCa interval (``scipy.stats.bootstrap``): an interval above 1 is
faster, one across 1 a difference this machine's noise hides. ``--pin`` runs the server's threads
on the last CPU and the clients on the others (Linux), so the two do not trade cores between
rounds; ``--rounds-out FILE`` keeps every round's rates (JSON lines). Quiet the machine first;
docs/benchmarks.md quotes runs.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
from dinerdash.testing import LocalCluster
from scipy.stats import bootstrap

ROOT = Path(__file__).resolve().parent.parent

#: One side's rows, run in its own process: (label, harness call), each the median of three.
ROWS = """
import json, statistics, sys
from dinerdash_bench.harness import _single, _vector
a = sys.argv[1]
rows = {
    "gRPC single env": lambda: _single(a, 3000, transport="grpc"),
    "gRPC N = 256": lambda: _vector(a, 256, 300, False, transport="grpc"),
    "gRPC N = 1024": lambda: _vector(a, 1024, 120, False, transport="grpc"),
    "gRPC pipelined 2 x N = 256": lambda: _vector(a, 256, 300, True, transport="grpc"),
    "shm single env": lambda: _single(a, 20000, transport="shm"),
    "shm N = 256": lambda: _vector(a, 256, 2000, False, transport="shm"),
    "shm N = 1024": lambda: _vector(a, 1024, 800, False, transport="shm"),
    "shm pipelined 2 x N = 256": lambda: _vector(a, 256, 2000, True, transport="shm"),
}
print(json.dumps({k: statistics.median(f() for _ in range(3)) for k, f in rows.items()}))
"""


def _side(tree: Path, address: str) -> dict[str, float]:
    path = os.pathsep.join(str(tree / d) for d in ("client-py", "bench"))
    env = {**os.environ, "PYTHONPATH": path}
    out = subprocess.run(
        [sys.executable, "-c", ROWS, address],
        env=env,
        check=True,
        capture_output=True,
        text=True,
        timeout=600,
    )
    return json.loads(out.stdout.splitlines()[-1])


def _pin(server_pid: int) -> None:
    """The server's threads (each set: affinity is a thread's) on the last CPU, this process, and
    so the clients it starts, on the others."""
    cpus = sorted(os.sched_getaffinity(0))
    if len(cpus) < 2:
        raise SystemExit("--pin: needs at least 2 CPUs")
    for tid in os.listdir(f"/proc/{server_pid}/task"):
        os.sched_setaffinity(int(tid), {cpus[-1]})
    os.sched_setaffinity(0, set(cpus[:-1]))


def _rate(x: float) -> str:
    return f"{x / 1e6:.2f} M" if x >= 1e5 else f"{x:,.0f}"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument(
        "--before", type=Path, required=True, help="the other checkout's root"
    )
    parser.add_argument(
        "--after", type=Path, default=ROOT, help="default: this checkout"
    )
    parser.add_argument("--rounds", type=int, default=12, help="default: 12")
    parser.add_argument(
        "--server", help="the server binary (default: this checkout's release)"
    )
    parser.add_argument(
        "--pin",
        action="store_true",
        help="server on the last CPU, clients on the others",
    )
    parser.add_argument(
        "--rounds-out", type=Path, help="every round's rates, as JSON lines"
    )
    args = parser.parse_args()
    if args.rounds < 3:
        parser.error("--rounds: at least 3 (an interval needs them)")
    runs: dict[str, list[dict[str, float]]] = {"before": [], "after": []}
    with LocalCluster(1, binary=args.server) as cluster:
        if args.pin:
            _pin(cluster.pid(0))
        for r in range(args.rounds):
            for side in ("before", "after") if r % 2 == 0 else ("after", "before"):
                runs[side].append(_side(getattr(args, side), cluster.address(0)))
            if args.rounds_out is not None:
                with args.rounds_out.open("a") as out:
                    rates = {side: runs[side][-1] for side in runs}
                    out.write(json.dumps({"round": r + 1, **rates}) + "\n")
            print(f"round {r + 1} of {args.rounds}", file=sys.stderr)
    print(
        "| row | before | after | after / before [95 % BCa] |\n| --- | ---: | ---: | ---: |"
    )
    for row in runs["before"][0]:
        before, after = (
            np.array([run[row] for run in runs[s]]) for s in ("before", "after")
        )
        logs = np.log(after / before)
        ci = bootstrap(
            (logs,), np.mean, method="BCa", random_state=0
        ).confidence_interval
        print(
            f"| {row} | {_rate(np.median(before))} | {_rate(np.median(after))} | "
            f"{np.exp(logs.mean()):.3f} [{np.exp(ci.low):.3f}, {np.exp(ci.high):.3f}] |"
        )


if __name__ == "__main__":
    main()
