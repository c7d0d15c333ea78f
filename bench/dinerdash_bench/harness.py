"""The measurements of ``python -m dinerdash bench``: what stepping through the client costs,
beside the floors of the machine it runs on (loopback TCP, the shared-memory doorbell), the
plain-Python reference and the server's own rates, all measured in one run; what each line means:
docs/benchmarks.md#the-python-client.
"""

from __future__ import annotations

import os
import socket
import subprocess
import sys
import time
from contextlib import closing
from typing import Any

import numpy as np
from dinerdash._batch import Batch, join
from dinerdash._proto import pb
from dinerdash.connection import Connection
from dinerdash.env import DinerDashEnv
from dinerdash.game import NUM_ACTIONS
from dinerdash.server import LocalServer, find_server_binary
from dinerdash.vector import DinerDashVectorEnv

__all__ = ["ceiling_lines", "run", "scaling", "tcp_floor", "transports"]

#: The echo child: what its socket (the descriptor in ``argv[1]``) receives goes back, until it
#: closes; a child process, so that the ping-pong crosses processes as a call to a server does.
_ECHO = """
import socket, sys
c = socket.socket(fileno=int(sys.argv[1]))
while True:
    d = c.recv(64)
    if not d:
        break
    c.sendall(d)
"""


def _ping_pong(sock: socket.socket, round_trips: int) -> float:
    """Microseconds of one round trip of a byte over ``sock`` to an echo child (after 200)."""
    for _ in range(200):
        sock.sendall(b"x")
        sock.recv(64)
    start = time.perf_counter()
    for _ in range(round_trips):
        sock.sendall(b"x")
        sock.recv(64)
    return (time.perf_counter() - start) / round_trips * 1e6


def _floor(mine: socket.socket, theirs: socket.socket, round_trips: int) -> float:
    """Microseconds of one round trip of a byte over ``mine`` to a child echoing on ``theirs``."""
    child = subprocess.Popen(
        [sys.executable, "-c", _ECHO, str(theirs.fileno())],
        pass_fds=[theirs.fileno()],
        stdin=subprocess.DEVNULL,
    )
    theirs.close()
    try:
        with mine:
            return _ping_pong(mine, round_trips)
    finally:
        try:
            child.wait(timeout=5)
        except subprocess.TimeoutExpired:
            child.kill()
            child.wait()


def tcp_floor(round_trips: int = 5000) -> float:
    """Microseconds of one loopback TCP round trip (one byte each way) to a child process."""
    with socket.create_server(("127.0.0.1", 0)) as server:
        mine = socket.create_connection(server.getsockname(), timeout=10)
        theirs, _ = server.accept()
    for sock in (mine, theirs):
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
    return _floor(mine, theirs, round_trips)


def doorbell_floor(round_trips: int = 5000) -> float:
    """Microseconds of one Unix ``SOCK_SEQPACKET`` round trip (one byte each way) to a child
    process: the least a shared-memory Step costs here, as :func:`tcp_floor` is gRPC's."""
    return _floor(*socket.socketpair(socket.AF_UNIX, socket.SOCK_SEQPACKET), round_trips)


def _first(address: str | list[str] | None) -> str | None:
    return address[0] if isinstance(address, list) else address


def _round_trip(address: str, calls: int = 2000, **connection: Any) -> float:
    """Microseconds of one bare ``ServerInfo`` call: the floor under any single-env step."""
    connection.pop("transport", None)  # a bare RPC: always gRPC
    with Connection(address, **connection) as conn:
        request = pb.ServerInfoRequest()
        for _ in range(100):
            conn.call("ServerInfo", request)
        start = time.perf_counter()
        for _ in range(calls):
            conn.call("ServerInfo", request)
        return (time.perf_counter() - start) / calls * 1e6


def _single(address: str | None, steps: int, **connection: Any) -> float:
    with DinerDashEnv(address, **connection) as env:
        actions = np.random.default_rng(0).integers(0, NUM_ACTIONS, size=steps)
        env.reset(seed=0)
        start = time.perf_counter()
        for a in actions:
            _, _, terminated, truncated, _ = env.step(a)
            if terminated or truncated:
                env.reset()
        return steps / (time.perf_counter() - start)


def _vector(address, num_envs: int, steps: int, pipelined: bool, **connection: Any) -> float:
    """Env-steps/s of one vector env of ``num_envs`` stepped with ``step()``, or (``pipelined``)
    of two, each one's ``step_async`` sent before the other's ``step_wait``."""
    count = 2 if pipelined else 1
    pair = [DinerDashVectorEnv(num_envs, address, **connection) for _ in range(count)]
    try:
        rng = np.random.default_rng(0)
        actions = rng.integers(0, NUM_ACTIONS, size=(steps + 10, count, num_envs), dtype=np.int32)
        for envs in pair:
            envs.reset(seed=0)
            for a in actions[:10, 0]:  # warm-up: connections, allocator
                envs.step(a)
        actions = actions[10:]
        start = time.perf_counter()
        if not pipelined:
            step = pair[0].step
            for a in actions[:, 0]:
                step(a)
        else:
            first, second = pair
            first.step_async(actions[0, 0])
            for t in range(steps):
                second.step_async(actions[t, 1])
                first.step_wait()
                if t + 1 < steps:
                    first.step_async(actions[t + 1, 0])
                second.step_wait()
        return count * num_envs * steps / (time.perf_counter() - start)
    finally:
        for envs in pair:
            envs.close()


def _decode(address, num_envs: int, steps: int = 200, **connection: Any) -> float:
    """Microseconds the client spends on one Step reply of ``num_envs`` environments once it has
    arrived (gRPC: parse it too; shared memory: from the region), over ``steps`` random steps."""
    with closing(DinerDashVectorEnv(num_envs, address, **connection)) as envs:
        rng = np.random.default_rng(0)
        envs.reset(seed=0)
        if connection.get("transport") == "shm":
            total = 0.0
            for _ in range(steps):
                envs.step(rng.integers(0, NUM_ACTIONS, size=num_envs))
                batches = [core.last for core in envs.fleet.cores]
                start = time.perf_counter()
                envs.decode_step(batches)
                total += time.perf_counter() - start
            return total / steps * 1e6
        replies = []
        for _ in range(steps):
            envs.step(rng.integers(0, NUM_ACTIONS, size=num_envs))
            replies.append([core.last.to_pb().SerializeToString() for core in envs.fleet.cores])
        start = time.perf_counter()
        for raw in replies:
            envs.decode_step([Batch.from_pb(pb.Batch.FromString(r)) for r in raw])
        return (time.perf_counter() - start) / steps * 1e6


def _python_floor(address, num_envs: int, steps: int = 2000) -> float:
    """Microseconds of the least work any Python client does for one shared-memory step of
    ``num_envs`` environments beside the server's Step, the 10th percentile of the steps
    (docs/benchmarks.md: "What any Python client could reach")."""
    with closing(DinerDashVectorEnv(num_envs, address, transport="shm")) as envs:
        envs.reset(seed=0)
        fleet, present = envs.fleet, np.ones(num_envs, dtype=np.bool_)
        names = ("observations", "rewards", "terminated", "truncated", "action_masks")
        names += ("scores", "lost", "ticks", "seeds")
        actions = np.random.default_rng(0).integers(0, NUM_ACTIONS, (steps, num_envs), np.int32)
        wire = np.zeros(num_envs, dtype=np.int32)
        times = []
        for step in actions:
            start = time.perf_counter()
            wire[:] = step
            times.append(time.perf_counter() - start)
            batch = join(fleet.step(wire))
            start = time.perf_counter()
            obs, rewards, terminated, truncated, masks, scores, lost, ticks, seeds = (
                batch[k] for k in names
            )
            info = {
                "action_mask": masks.copy(),
                "score": scores.astype(np.int64),
                "lost": lost.astype(np.int64),
                "tick": ticks.astype(np.int64),
                "seed": seeds.astype(np.int64),
            }
            shown = present.copy()
            for key in list(info):
                info["_" + key] = shown
            obs.astype(np.float32), rewards.astype(np.float64)
            terminated.copy(), truncated.copy()
            times[-1] += time.perf_counter() - start
        return float(np.percentile(times, 10)) * 1e6


def _shm_parts(address, num_envs: int, steps: int) -> tuple[float, float]:
    """``(microseconds a shared-memory step() of ``num_envs`` takes, microseconds of it from the
    doorbell's ring to the reply)``: the rest is this client's own work."""
    with closing(DinerDashVectorEnv(num_envs, address, transport="shm")) as envs:
        envs.reset(seed=0)
        (core,) = envs.fleet.cores
        transport, channel = core.transport, core.transport.channel
        receive, waited = transport.receive, [0.0]

        def timed():
            batch = receive()
            waited[0] += time.perf_counter() - channel.sent
            return batch

        transport.receive = timed  # this env's only: an instance attribute
        actions = np.random.default_rng(0).integers(0, NUM_ACTIONS, size=(steps + 100, num_envs))
        for a in actions[:100]:
            envs.step(a)
        waited[0] = 0.0
        start = time.perf_counter()
        for a in actions[100:]:
            envs.step(a)
        return (time.perf_counter() - start) / steps * 1e6, waited[0] / steps * 1e6


def ceiling_lines(
    sizes: list[int],
    seconds: float = 2.0,
    threads: list[int] | None = None,
    labels: str = "none",
) -> list[tuple[int, int, str, float, float]]:
    """The server's own env-steps/s for a session of each N of ``sizes`` with ``labels`` on each
    number of stepping ``threads`` (default: one per core), measured by its binary here: one
    ``(N, threads, labels, in process, Rust gRPC client)`` per line of ``dinerdash-server
    ceiling``."""
    threads = list(threads or [])
    out = subprocess.run(
        [
            str(find_server_binary()),
            "ceiling",
            "--time",
            f"{int(seconds * 1000)}ms",
            "--labels",
            labels,
            *(f"--num-envs={n}" for n in sizes),
            *(f"--threads={t}" for t in threads),
        ],
        capture_output=True,
        text=True,
        check=True,
        timeout=60 + 4 * seconds * len(sizes) * max(1, len(threads)),
    )
    lines = []
    for line in out.stdout.split("\n"):
        if line.strip():
            n, t, label, local, grpc = line.split()
            lines.append((int(n), int(t), label, float(local), float(grpc)))
    return lines


def transports(
    address: str | list[str],
    steps: int,
    vec_steps: int,
    sizes: tuple[int, ...] = (256, 1024),
    rounds: int = 3,
    pipeline: bool = False,
    ceiling_seconds: float = 1.0,
) -> None:
    """Prints the transports table: this client over gRPC and over shared memory beside the
    server's ceiling, for the single env and a vector env of each N of ``sizes`` (and with
    ``pipeline`` two pipelined vector envs of the first N); each figure the best of ``rounds``
    rounds that take turns."""
    first = _first(address)
    rows = [1] if steps > 0 else []
    rows += list(sizes) if vec_steps > 0 else []
    best: dict[tuple[str, int], float] = {}
    cpu_micros = float("inf")

    def keep(key: tuple[str, int], rate: float) -> None:
        best[key] = max(best.get(key, 0.0), rate)

    floor = doorbell_floor()
    print(f"doorbell floor     : {floor:12,.1f} us/round trip  (Unix SEQPACKET, two processes)")
    for _ in range(rounds):
        for n, _, _, local, rust in ceiling_lines(rows, seconds=ceiling_seconds):
            keep(("local", n), local)
            keep(("rust", n), rust)
        for n in rows:
            for transport in ("grpc", "shm"):
                if n == 1:
                    cpu = time.process_time()
                    rate = _single(first, steps, transport=transport)
                    if transport == "shm":
                        # Client CPU per step (this process: the env, decode, the doorbell).
                        used = (time.process_time() - cpu) / steps * 1e6
                        cpu_micros = min(cpu_micros, used)
                else:
                    rate = _vector(first, n, vec_steps, False, transport=transport)
                    if pipeline and n == sizes[0]:
                        two = _vector(first, n, vec_steps, True, transport=transport)
                        keep((transport, -n), two)
                keep((transport, n), rate)
    print(
        "transports         :     gRPC          shm      server in process  Rust gRPC client"
        "   shm / Rust gRPC   shm / in process   (env-steps/s, best of "
        f"{rounds})"
    )
    for n in rows:
        label = "single env" if n == 1 else f"N={n}"
        grpc, shm, local, rust = (best[(k, n)] for k in ("grpc", "shm", "local", "rust"))
        print(
            f"  {label:<17}: {grpc:10,.0f} {shm:12,.0f} {local:16,.0f} {rust:17,.0f}"
            f" {shm / rust:14.0%} {shm / local:17.0%}"
        )
    if pipeline and vec_steps > 0:
        n = sizes[0]
        grpc, shm = best[("grpc", -n)], best[("shm", -n)]
        print(
            f"  pipelined 2xN={n:<3}: {grpc:10,.0f} {shm:12,.0f}   (two vector envs, one step on "
            f"the wire: {grpc / best[('grpc', n)]:.2f}x / {shm / best[('shm', n)]:.2f}x one env)"
        )
    if vec_steps > 0:
        n = sizes[0]
        grpc, shm = (_decode(first, n, transport=t) for t in ("grpc", "shm"))
        print(
            f"  decode N={n:<8}: {grpc:10,.1f} {shm:12,.1f}   us/step (gRPC: parse the message, "
            "read it into a Batch, build the arrays and infos; shm: the same from the region)"
        )
        step, waited = min(_shm_parts(first, n, vec_steps) for _ in range(rounds))
        server = n / best[("local", n)] * 1e6
        print(
            f"  shm N={n} step   : {step:.1f} us = {waited:.1f} from the doorbell's ring to the "
            f"reply (the server's Step in process: {server:.1f}) + {step - waited:.1f} in this "
            f"client (decode {shm:.1f})"
        )
        floor = _python_floor(first, n, vec_steps)
        print(
            f"  shm N={n} bound  : {server / (server + floor):.0%} of in process at most, for any "
            f"Python client with a transport of no cost: the server's Step {server:.1f} us + "
            f"{floor:.1f} us of the least work a step takes in Python (write the actions; "
            "observations, rewards, flags, infos: one numpy call each, on the fresh reply)"
        )
    if cpu_micros < float("inf"):
        print(
            f"  single env over shm: {cpu_micros:.1f} us of client CPU a step (the rest of a "
            "step is waiting for the server)"
        )


def scaling(
    address: str | list[str],
    vec_steps: int,
    sizes: tuple[int, ...] = (256, 4096),
    planner_sizes: tuple[int, ...] = (256,),
    ceiling_seconds: float = 1.0,
) -> None:
    """Prints the scaling table: the server's ceiling for each N on one stepping thread and on one
    per core, beside this client's vector env of that N over gRPC and shared memory; the planner
    rows (~0.1 ms a decision) step a tenth as many times."""
    first = _first(address)
    cores = os.cpu_count() or 1
    threads = sorted({1, cores})
    print(
        "scaling            : server in process / Rust gRPC client by stepping threads "
        f"({', '.join(map(str, threads))}), this client over gRPC / shm  (env-steps/s)"
    )
    rows = [("none", n) for n in sizes] + [("planner", n) for n in planner_sizes]
    for labels, n in rows:
        lines = ceiling_lines([n], seconds=ceiling_seconds, threads=threads, labels=labels)
        by_threads = {t: (local, rust) for _, t, _, local, rust in lines}
        steps = max(10, vec_steps * 256 // n // (10 if labels == "planner" else 1))
        expert = {"expert": "planner"} if labels == "planner" else {}
        client = {
            transport: _vector(first, n, steps, False, transport=transport, **expert)
            for transport in ("grpc", "shm")
        }
        server = "  ".join(
            f"{t} thr {by_threads[t][0]:11,.0f} {by_threads[t][1]:11,.0f}" for t in threads
        )
        label = f"N={n}" + (" planner" if labels == "planner" else "")
        speedup = by_threads[threads[-1]][0] / by_threads[1][0] if len(threads) > 1 else 1.0
        print(
            f"  {label:<17}: {server}  ({speedup:.2f}x)   client {client['grpc']:11,.0f}"
            f" {client['shm']:11,.0f}"
        )


def _random_legal(rng: np.random.Generator, masks: np.ndarray) -> np.ndarray:
    """One uniformly random legal action per row of ``masks``."""
    return np.argmax(rng.random(masks.shape) * masks, axis=1)


def _sb3(address, num_envs: int, steps: int, **connection: Any) -> tuple[float, float]:
    """Env-steps/s of SB3's ``DummyVecEnv`` of ``num_envs`` single envs and of
    :func:`dinerdash.sb3.make_vec_env`, both with random legal actions read as MaskablePPO does."""
    from dinerdash.sb3 import make_vec_env
    from stable_baselines3.common.vec_env import DummyVecEnv

    def run(vec) -> float:
        rng = np.random.default_rng(0)
        try:
            vec.reset()
            for _ in range(10):  # warm-up: connections, allocator
                vec.step(_random_legal(rng, np.stack(vec.env_method("action_masks"))))
            start = time.perf_counter()
            for _ in range(steps):
                vec.step(_random_legal(rng, np.stack(vec.env_method("action_masks"))))
            return num_envs * steps / (time.perf_counter() - start)
        finally:
            vec.close()

    first = _first(address)
    dummy = run(
        DummyVecEnv(
            [lambda: DinerDashEnv(first, **connection) for _ in range(num_envs)]  # type: ignore[misc]
        )
    )
    adapter = run(make_vec_env(num_envs, address, monitor=False, **connection))
    return dummy, adapter


def run(
    address: str | list[str] | None = None,
    *,
    steps: int = 20_000,
    num_envs: int = 256,
    vec_steps: int = 2_000,
    pipeline: bool = False,
    reference_steps: int = 100_000,
    servers: int = 1,
    sb3_envs: int = 8,
    sb3_steps: int = 2_000,
    compare_transports: bool = True,
    compare_scaling: bool = True,
    rounds: int = 3,
    ceiling_seconds: float = 1.0,
    **connection: Any,
) -> None:
    """The ``bench`` command: prints one line per measurement. Without ``address`` (and
    ``DINERDASH_ADDRESS``) it starts ``servers`` local servers; a step count of 0 skips its
    measurement; ``connection``'s ``transport`` (default ``"grpc"``) is that of the lines before
    the transports table."""
    connection.setdefault("transport", "grpc")
    reference = None

    def times(rate: float) -> str:
        return (
            f"{rate / reference:.{2 if rate < reference else 1}f}x the reference"
            if reference
            else "no reference run"
        )

    # The floors first, before any gRPC thread competes with them.
    floor = tcp_floor()
    print(f"loopback TCP floor : {floor:12,.1f} us/round trip  (1 byte each way, two processes)")
    if reference_steps > 0:
        from .reference import random_steps_per_second

        reference = random_steps_per_second(reference_steps)
        print(
            f"reference          : {reference:12,.0f} steps/s       (dinerdash_bench.reference in "
            "process, random actions)"
        )
    started = []
    try:
        if address is None and not os.environ.get("DINERDASH_ADDRESS"):
            started = [LocalServer() for _ in range(servers)]
            address = [s.address for s in started]
        first = _first(address)
        shown = address if address is not None else os.environ["DINERDASH_ADDRESS"]
        print(f"servers: {shown}; {os.cpu_count()} cores")
        n = num_envs
        replicas = len(address) if isinstance(address, list) else 1
        if steps > 0:
            micros = _round_trip(first, **connection)
            print(
                f"gRPC round trip    : {micros:12,.1f} us/call        (ServerInfo; "
                f"{micros / floor:.1f}x the TCP floor)"
            )
            rate = _single(first, steps, **connection)
            print(
                f"single env         : {rate:12,.0f} steps/s       ({steps} random steps; "
                f"{times(rate)})"
            )
        if vec_steps > 0:
            rate = _vector(address, n, vec_steps, False, **connection)
            print(
                f"make_vec N={n:<8}: {rate:12,.0f} env-steps/s   ({vec_steps} step() calls, "
                f"{replicas} server(s); {times(rate)})"
            )
            micros = _decode(address, n, **connection)
            print(
                f"decode N={n:<10}: {micros:12,.1f} us/step       (parse the reply, build the "
                "arrays and infos)"
            )
        if vec_steps > 0 and pipeline:
            rate = _vector(address, n, vec_steps, True, **connection)
            print(
                f"pipelined 2 x N={n:<3}: {rate:12,.0f} env-steps/s   (two vector envs, one step "
                f"on the wire; {times(rate)})"
            )
        if compare_transports:
            transports(
                address,
                steps,
                vec_steps,
                rounds=rounds,
                pipeline=pipeline,
                ceiling_seconds=ceiling_seconds,
            )
        if compare_scaling and vec_steps > 0:
            scaling(address, vec_steps, ceiling_seconds=ceiling_seconds)
        if sb3_steps > 0:
            try:
                dummy, adapter = _sb3(address, sb3_envs, sb3_steps, **connection)
            except ImportError:
                print("sb3                : skipped (pip install 'dinerdash[sb3]')")
            else:
                k = sb3_envs
                print(
                    f"SB3 DummyVecEnv N={k:<2}: {dummy:12,.0f} env-steps/s   "
                    f"({sb3_steps} steps, random legal actions, one call per env)"
                )
                print(
                    f"dinerdash.sb3  N={k:<3}: {adapter:12,.0f} env-steps/s   "
                    f"({adapter / dummy:.1f}x: one batched Step per server)"
                )
    finally:
        for s in started:
            s.stop()
